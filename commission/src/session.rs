//! What every calibration session does to a servo on the line: take it (found alone at its
//! id, of its joint's model, its torque off, what it held kept), write EEPROM values with the
//! Lock opened around them and read them back, write a chosen calibration, and give back what
//! it held when the session ends without one.

use crate::calibrate::{Refusal, Stops};
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

/// Why a calibration session stopped.
#[derive(Debug, Error)]
pub enum SessionError {
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
    /// Joints whose travel gives no calibration: every servo was given back what it held.
    #[error("not calibrated, every servo left as found: {}", list(.0))]
    Refused(Vec<Refusal>),
    /// A joint's torque limit leaves the firmware no press bound: nothing was touched.
    #[error(
        "{joint}: a torque limit of {limit_percent} % leaves no whole percent between the stall \
         rule's 80 % of it and itself for the firmware's press bound: raise it in the \
         description's calibration plan"
    )]
    NoPressBound {
        /// The joint.
        joint: String,
        /// Its plan's torque limit, %.
        limit_percent: f64,
    },
    /// The session has ended (released): nothing more is driven.
    #[error("the calibration session has ended")]
    Ended,
    /// Committed before every joint was calibrated and parked.
    #[error("the calibration is not done: nothing to commit")]
    NotDone,
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

/// A joint taken by a session: what its servo held when found, given back if the session
/// ends without a calibration.
#[derive(Debug, Clone)]
pub struct Taken {
    /// The joint.
    pub target: JointToCalibrate,
    /// Homing offset and limits as found ([`CALIBRATION_REGISTERS`]' order).
    pub found: [i32; 3],
    /// Its servo's firmware, major.minor.
    pub firmware: String,
}

impl Taken {
    /// The error of an exchange with this joint's servo.
    pub fn failed(&self, source: BusError) -> SessionError {
        SessionError::Bus {
            joint: self.target.joint.clone(),
            id: self.target.id,
            source,
        }
    }

    /// The joint calibrated as `calibration`.
    pub fn calibrated(&self, calibration: JointCalibration) -> Calibrated {
        Calibrated {
            joint: self.target.joint.clone(),
            id: self.target.id,
            calibration,
            model: self.target.model.key(),
            firmware: self.firmware.clone(),
        }
    }
}

/// The registers a calibration writes, in [`calibration_settings`]' order.
pub const CALIBRATION_REGISTERS: [reg::Register; 3] = [
    reg::HOMING_OFFSET,
    reg::MIN_POSITION_LIMIT,
    reg::MAX_POSITION_LIMIT,
];

/// Takes a joint: its servo alone at its id and of its model, its torque off, what it held
/// read. Nothing is written but the torque.
pub fn take<T: Transport>(
    bus: &mut Bus<T>,
    target: JointToCalibrate,
) -> Result<Taken, SessionError> {
    let (joint, id) = (target.joint.clone(), target.id);
    let fail = |source| SessionError::Bus {
        joint: joint.clone(),
        id,
        source,
    };
    bus.alone_at(id).map_err(fail)?;
    let number = bus.read(id, reg::MODEL_NUMBER).map_err(fail)?;
    let model = ServoModel::from_model_number(number as u16);
    if model != Some(target.model) {
        return Err(SessionError::WrongModel {
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
    Ok(Taken {
        target,
        found,
        firmware,
    })
}

/// Writes `values` into a joint's servo and reads each back; `to_flash` opens the Lock around
/// them (the EEPROM keeps them across a power cycle), else they hold until one (RAM only).
pub fn write_checked<T: Transport>(
    bus: &mut Bus<T>,
    taken: &Taken,
    values: &[(reg::Register, i32)],
    to_flash: bool,
) -> Result<(), SessionError> {
    let id = taken.target.id;
    let write = |bus: &mut Bus<T>| -> Result<(), BusError> {
        if to_flash {
            bus.write(id, reg::LOCK, 0)?;
        }
        for &(register, value) in values {
            bus.write(id, register, value)?;
        }
        if to_flash {
            bus.write(id, reg::LOCK, 1)?;
        }
        Ok(())
    };
    write(bus).map_err(|e| taken.failed(e))?;
    for &(register, wanted) in values {
        let found = bus.read(id, register).map_err(|e| taken.failed(e))?;
        if found != wanted {
            return Err(SessionError::NotHeld {
                joint: taken.target.joint.clone(),
                id,
                register: register.name,
                found,
                wanted,
            });
        }
    }
    Ok(())
}

/// Writes a joint's chosen calibration into its servo's EEPROM, read back.
pub fn write_calibration<T: Transport>(
    bus: &mut Bus<T>,
    taken: &Taken,
    calibration: &JointCalibration,
) -> Result<(), SessionError> {
    let settings = calibration_settings(calibration).map(|s| (s.register, s.value));
    write_checked(bus, taken, &settings, true)
}

/// Gives every joint taken back the homing offset and limits it held (`to_flash`: in its
/// EEPROM too, else until a power cycle).
pub fn give_back<T: Transport>(
    bus: &mut Bus<T>,
    taken: &[Taken],
    to_flash: bool,
) -> Result<(), SessionError> {
    for t in taken {
        let values: Vec<_> = CALIBRATION_REGISTERS.into_iter().zip(t.found).collect();
        write_checked(bus, t, &values, to_flash)?;
    }
    Ok(())
}
