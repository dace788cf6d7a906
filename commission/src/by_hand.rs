//! A calibration by hand on one bus, over the line: each joint's servo found alone at its id
//! ([`Bus::alone_at`]), its torque off and its homing offset cleared so its encoder reads raw; the operator moves
//! every joint from stop to stop while the session reads them (the caller sets the pace and
//! shows [`ByHand::progress`]); then each joint's calibration is chosen
//! ([`crate::calibrate::choose`]) and written into its servo, Lock around it, and read back.
//! Refused joints leave every servo as it was found: nothing half-calibrated.

use crate::calibrate::{choose, Sweep};
use crate::session::{
    self, give_back, write_calibration, write_checked, Calibrated, JointToCalibrate, SessionError,
    Taken,
};
use bus_driver::bus::Bus;
use bus_driver::transport::Transport;
use feetech::registers as reg;

/// One joint's progress, for the operator.
#[derive(Debug, Clone, PartialEq)]
pub struct Progress {
    /// The joint.
    pub joint: String,
    /// Swept so far, degrees.
    pub swept_deg: f64,
    /// The description's travel, degrees.
    pub travel_deg: f64,
    /// Where it is within the sweep so far (0 to 1).
    pub place: f64,
    /// Whether both stops have been reached.
    pub covered: bool,
}

struct Joint {
    taken: Taken,
    sweep: Sweep,
}

/// A calibration by hand in progress.
pub struct ByHand<T: Transport> {
    bus: Bus<T>,
    joints: Vec<Joint>,
}

impl<T: Transport> ByHand<T> {
    /// Takes the joints: each servo alone at its id and of its joint's model, its torque off,
    /// its calibration as found kept, its homing offset cleared (read back). A joint that
    /// cannot be taken gives every one taken before it back what it held.
    pub fn start(bus: Bus<T>, targets: Vec<JointToCalibrate>) -> Result<Self, SessionError> {
        let mut session = ByHand {
            bus,
            joints: Vec::with_capacity(targets.len()),
        };
        for target in targets {
            if let Err(e) = session.take(target) {
                // Best effort: the error that stopped the session is the one to report.
                let _ = session.give_back();
                return Err(e);
            }
        }
        Ok(session)
    }

    fn take(&mut self, target: JointToCalibrate) -> Result<(), SessionError> {
        let taken = session::take(&mut self.bus, target)?;
        // Kept before anything is written, so that it is given back whatever happens next.
        self.joints.push(Joint {
            taken: taken.clone(),
            sweep: Sweep::default(),
        });
        write_checked(&mut self.bus, &taken, &[(reg::HOMING_OFFSET, 0)], true)
    }

    /// Reads every joint once.
    pub fn read(&mut self) -> Result<(), SessionError> {
        for j in &mut self.joints {
            let raw = self
                .bus
                .read(j.taken.target.id, reg::PRESENT_POSITION)
                .map_err(|e| j.taken.failed(e))?;
            j.sweep.observe(raw.clamp(0, 4095) as u16);
        }
        Ok(())
    }

    /// Every joint's progress; a joint is covered within `tolerance_rad` of its travel.
    pub fn progress(&self, tolerance_rad: f64) -> Vec<Progress> {
        self.joints
            .iter()
            .map(|j| {
                let target = &j.taken.target;
                Progress {
                    joint: target.joint.clone(),
                    swept_deg: j.sweep.swept_rad().to_degrees(),
                    travel_deg: (target.stops.upper_rad - target.stops.lower_rad).to_degrees(),
                    place: j.sweep.place(),
                    covered: j.sweep.covers(&target.stops, tolerance_rad),
                }
            })
            .collect()
    }

    /// Chooses each joint's calibration (`margin_rad` inside its stops, refused beyond
    /// `tolerance_rad` of its travel) and writes it into the servo, read back. Any joint
    /// refused: every servo given back what it held, and the refusals returned.
    pub fn finish(
        mut self,
        margin_rad: f64,
        tolerance_rad: f64,
    ) -> Result<Vec<Calibrated>, SessionError> {
        let (mut chosen, mut refused) = (Vec::new(), Vec::new());
        for j in &self.joints {
            let target = &j.taken.target;
            match choose(
                &target.joint,
                &j.sweep,
                &target.stops,
                margin_rad,
                tolerance_rad,
            ) {
                Ok(calibration) => chosen.push((j.taken.clone(), calibration)),
                Err(e) => refused.push(e),
            }
        }
        if !refused.is_empty() {
            self.give_back()?;
            return Err(SessionError::Refused(refused));
        }
        for (taken, calibration) in &chosen {
            if let Err(e) = write_calibration(&mut self.bus, taken, calibration) {
                // Best effort: the failure that stopped the writes is the one to report.
                let _ = self.give_back();
                return Err(e);
            }
        }
        Ok(chosen
            .into_iter()
            .map(|(taken, calibration)| taken.calibrated(calibration))
            .collect())
    }

    /// Gives every servo back the homing offset and limits it held, and ends the session.
    pub fn abandon(mut self) -> Result<(), SessionError> {
        self.give_back()
    }

    fn give_back(&mut self) -> Result<(), SessionError> {
        let taken: Vec<Taken> = self.joints.iter().map(|j| j.taken.clone()).collect();
        give_back(&mut self.bus, &taken, true)
    }
}
