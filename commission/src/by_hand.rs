//! A calibration by hand on one bus, over the line: each joint's servo found alone at its id
//! ([`Bus::alone_at`]), its torque off and its homing offset cleared so its encoder reads raw; the operator moves
//! every joint from stop to stop while the session reads them (the caller sets the pace and
//! shows [`ByHand::progress`]); then each joint's calibration is chosen
//! ([`crate::calibrate::choose`]) and written into its servo, Lock around it, and read back.
//! Refused joints leave every servo as it was found: nothing half-calibrated.

use crate::calibrate::{choose, Refusal, Stops, Sweep};
use bus_driver::backstops::calibration_settings;
use bus_driver::bus::{Bus, BusError};
use bus_driver::calibration::JointCalibration;
use bus_driver::transport::Transport;
use feetech::registers as reg;
use feetech::ServoModel;
use thiserror::Error;

/// A joint to calibrate.
#[derive(Debug, Clone, PartialEq)]
pub struct JointToCalibrate {
    /// The joint.
    pub joint: String,
    /// Its servo's id.
    pub id: u8,
    /// Its servo's model, from the configuration (checked against the servo's).
    pub model: ServoModel,
    /// Its stops, from the robot's description.
    pub stops: Stops,
}

/// Why a calibration by hand stopped.
#[derive(Debug, Error)]
pub enum ByHandError {
    /// The line failed.
    #[error("{joint} (id {id}): {source}")]
    Bus {
        /// The joint.
        joint: String,
        /// Its id.
        id: u8,
        /// What went wrong on the line.
        source: BusError,
    },
    /// The servo at a joint's id is not its model.
    #[error("{joint} (id {id}): model number {model_number}, not the {expected} the configuration names")]
    WrongModel {
        /// The joint.
        joint: String,
        /// Its id.
        id: u8,
        /// The model the configuration names.
        expected: &'static str,
        /// The `Model_Number` read.
        model_number: i32,
    },
    /// Joints whose sweep gives no calibration: every servo was given back what it held.
    #[error("not calibrated, every servo left as found: {}", list(.0))]
    Refused(Vec<Refusal>),
    /// A written value did not read back.
    #[error("{joint} (id {id}): {register} reads {found} after writing {wanted}")]
    NotHeld {
        /// The joint.
        joint: String,
        /// Its id.
        id: u8,
        /// The register.
        register: &'static str,
        /// What it reads.
        found: i32,
        /// What was written.
        wanted: i32,
    },
}

fn list(refusals: &[Refusal]) -> String {
    refusals
        .iter()
        .map(ToString::to_string)
        .collect::<Vec<_>>()
        .join("; ")
}

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
    target: JointToCalibrate,
    sweep: Sweep,
    /// Homing offset and limits as found, given back if the calibration is abandoned.
    found: [i32; 3],
    firmware: String,
}

impl Joint {
    fn model(&self) -> &'static str {
        self.target.model.key()
    }
}

/// A joint calibrated and written.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibrated {
    /// The joint.
    pub joint: String,
    /// Its servo's id.
    pub id: u8,
    /// Its calibration.
    pub calibration: JointCalibration,
    /// Its servo's model, as read.
    pub model: &'static str,
    /// Its servo's firmware, major.minor.
    pub firmware: String,
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
    pub fn start(bus: Bus<T>, targets: Vec<JointToCalibrate>) -> Result<Self, ByHandError> {
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

    fn take(&mut self, target: JointToCalibrate) -> Result<(), ByHandError> {
        let (joint, id) = (target.joint.clone(), target.id);
        let fail = |source| ByHandError::Bus {
            joint: joint.clone(),
            id,
            source,
        };
        let bus = &mut self.bus;
        bus.alone_at(id).map_err(fail)?;
        let number = bus.read(id, reg::MODEL_NUMBER).map_err(fail)?;
        let model = ServoModel::from_model_number(number as u16);
        if model != Some(target.model) {
            return Err(ByHandError::WrongModel {
                joint,
                id,
                expected: target.model.key(),
                model_number: number,
            });
        }
        bus.write(id, reg::TORQUE_ENABLE, 0).map_err(fail)?;
        let mut found = [0; 3];
        for (f, r) in found.iter_mut().zip(CALIBRATION_REGISTERS) {
            *f = bus.read(id, r).map_err(fail)?;
        }
        let firmware = format!(
            "{}.{}",
            bus.read(id, reg::FIRMWARE_MAJOR).map_err(fail)?,
            bus.read(id, reg::FIRMWARE_MINOR).map_err(fail)?
        );
        // Kept before anything is written, so that it is given back whatever happens next.
        self.joints.push(Joint {
            target,
            sweep: Sweep::default(),
            found,
            firmware,
        });
        let bus = &mut self.bus;
        write_locked(bus, id, &[(reg::HOMING_OFFSET, 0)]).map_err(fail)?;
        let offset = bus.read(id, reg::HOMING_OFFSET).map_err(fail)?;
        if offset != 0 {
            return Err(ByHandError::NotHeld {
                joint,
                id,
                register: reg::HOMING_OFFSET.name,
                found: offset,
                wanted: 0,
            });
        }
        Ok(())
    }

    /// Reads every joint once.
    pub fn read(&mut self) -> Result<(), ByHandError> {
        for j in &mut self.joints {
            let id = j.target.id;
            let raw =
                self.bus
                    .read(id, reg::PRESENT_POSITION)
                    .map_err(|source| ByHandError::Bus {
                        joint: j.target.joint.clone(),
                        id,
                        source,
                    })?;
            j.sweep.observe(raw.clamp(0, 4095) as u16);
        }
        Ok(())
    }

    /// Every joint's progress; a joint is covered within `tolerance_rad` of its travel.
    pub fn progress(&self, tolerance_rad: f64) -> Vec<Progress> {
        self.joints
            .iter()
            .map(|j| Progress {
                joint: j.target.joint.clone(),
                swept_deg: j.sweep.swept_rad().to_degrees(),
                travel_deg: (j.target.stops.upper_rad - j.target.stops.lower_rad).to_degrees(),
                place: j.sweep.place(),
                covered: j.sweep.covers(&j.target.stops, tolerance_rad),
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
    ) -> Result<Vec<Calibrated>, ByHandError> {
        let (mut chosen, mut refused) = (Vec::new(), Vec::new());
        for j in &self.joints {
            match choose(
                &j.target.joint,
                &j.sweep,
                &j.target.stops,
                margin_rad,
                tolerance_rad,
            ) {
                Ok(calibration) => chosen.push(Calibrated {
                    joint: j.target.joint.clone(),
                    id: j.target.id,
                    calibration,
                    model: j.model(),
                    firmware: j.firmware.clone(),
                }),
                Err(e) => refused.push(e),
            }
        }
        if !refused.is_empty() {
            self.give_back()?;
            return Err(ByHandError::Refused(refused));
        }
        if let Err(e) = self.write_chosen(&chosen) {
            // Best effort: the failure that stopped the writes is the one to report.
            let _ = self.give_back();
            return Err(e);
        }
        Ok(chosen)
    }

    /// Each chosen calibration written into its servo and read back.
    fn write_chosen(&mut self, chosen: &[Calibrated]) -> Result<(), ByHandError> {
        for c in chosen {
            let (joint, id, cal) = (&c.joint, c.id, &c.calibration);
            let fail = |source| ByHandError::Bus {
                joint: joint.clone(),
                id,
                source,
            };
            let settings = calibration_settings(cal).map(|s| (s.register, s.value));
            write_locked(&mut self.bus, id, &settings).map_err(fail)?;
            for (register, wanted) in settings {
                let found = self.bus.read(id, register).map_err(fail)?;
                if found != wanted {
                    return Err(ByHandError::NotHeld {
                        joint: joint.clone(),
                        id,
                        register: register.name,
                        found,
                        wanted,
                    });
                }
            }
        }
        Ok(())
    }

    /// Gives every servo back the homing offset and limits it held, and ends the session.
    pub fn abandon(mut self) -> Result<(), ByHandError> {
        self.give_back()
    }

    fn give_back(&mut self) -> Result<(), ByHandError> {
        for j in &self.joints {
            let values: Vec<_> = CALIBRATION_REGISTERS.into_iter().zip(j.found).collect();
            write_locked(&mut self.bus, j.target.id, &values).map_err(|source| {
                ByHandError::Bus {
                    joint: j.target.joint.clone(),
                    id: j.target.id,
                    source,
                }
            })?;
        }
        Ok(())
    }
}

/// The registers a calibration writes, in [`calibration_settings`]' order.
const CALIBRATION_REGISTERS: [reg::Register; 3] = [
    reg::HOMING_OFFSET,
    reg::MIN_POSITION_LIMIT,
    reg::MAX_POSITION_LIMIT,
];

/// EEPROM writes with the Lock opened around them.
fn write_locked<T: Transport>(
    bus: &mut Bus<T>,
    id: u8,
    values: &[(reg::Register, i32)],
) -> Result<(), BusError> {
    bus.write(id, reg::LOCK, 0)?;
    for &(register, value) in values {
        bus.write(id, register, value)?;
    }
    bus.write(id, reg::LOCK, 1)?;
    Ok(())
}
