//! Setting up a new servo for a joint (`nori servo setup BUS JOINT`): the servo connected alone,
//! or found at the factory's id (1) at the factory's rate (1 Mbps) among servos that do not use
//! that id, gets the joint's id, the bus's rate, the driver's EEPROM settings (return delay 0,
//! the backstops) and Lock, with its torque off throughout. Refused, with the reason, when the
//! joint's id already answers, when the servo is not alone at the id it was found at, or when it
//! is the wrong model for the joint. The position limits and the homing offset come later, from
//! the calibration (the new servo's horn sits on another tooth than the old one's).

use crate::findings::model_name;
use crate::scan::{self, BroadcastAnswer, Found, Plan};
use bus_driver::backstops::{self, Setting};
use bus_driver::bus::{Bus, BusError};
use bus_driver::config::{BusConfig, LoadedConfig};
use bus_driver::transport::{Transport, TransportError};
use feetech::instruction::Instruction;
use feetech::registers as reg;
use feetech::timing::baud_code;
use feetech::{ServoModel, BROADCAST_ID};
use thiserror::Error;

/// The servo's factory id and rate.
pub const FACTORY_ID: u8 = 1;
/// The factory's line rate, baud.
pub const FACTORY_BAUD: u32 = 1_000_000;

/// What a joint's servo must become.
#[derive(Debug, Clone, PartialEq)]
pub struct Target {
    /// The bus.
    pub bus: String,
    /// The joint.
    pub joint: String,
    /// Its id.
    pub id: u8,
    /// Its model.
    pub model: ServoModel,
    /// The bus's rate, baud.
    pub baud: u32,
    /// The EEPROM the driver writes, less what the calibration gives (limits, homing offset).
    pub eeprom: Vec<Setting>,
    /// The bus's other joints by id.
    pub others: Vec<(u8, String)>,
}

/// Why a setup was refused or failed.
#[derive(Debug, Error)]
pub enum SetupError {
    /// The configuration has no such joint on the bus.
    #[error("bus {bus} has no joint {joint:?} (its joints: {joints})")]
    NoJoint {
        /// The bus.
        bus: String,
        /// The joint asked for.
        joint: String,
        /// The bus's joints.
        joints: String,
    },
    /// The bus's rate is none the servos support.
    #[error("bus {bus} runs at {baud} baud, which no STS servo can be set to")]
    Rate {
        /// The bus.
        bus: String,
        /// Its rate.
        baud: u32,
    },
    /// The joint's id already answers.
    #[error(
        "id {id} already answers on bus {bus} ({what}): {joint}'s servo is in place; to replace \
         it, take the old one off the bus first"
    )]
    IdTaken {
        /// The bus.
        bus: String,
        /// The joint.
        joint: String,
        /// Its id.
        id: u8,
        /// What answered there.
        what: String,
    },
    /// No servo to set up was found.
    #[error(
        "no servo alone on bus {bus}: a broadcast PING found none at any rate, nor one at the \
         factory's id {FACTORY_ID} at {FACTORY_BAUD} baud; connect the new servo (alone, or \
         at id {FACTORY_ID} among servos that do not use that id) and power it"
    )]
    NotFound {
        /// The bus.
        bus: String,
    },
    /// Several servos answer where the new one was looked for.
    #[error(
        "more than one servo answers at id {id} at {baud} baud: connect the new servo alone \
         (each servo leaves the factory at id {FACTORY_ID})"
    )]
    NotAlone {
        /// The id.
        id: u8,
        /// The rate.
        baud: u32,
    },
    /// The servo found is the wrong model for the joint.
    #[error("the servo found (id {id}) is an {found} where {joint} needs an {expected}: fit the right servo")]
    WrongModel {
        /// The joint.
        joint: String,
        /// Where the servo was found.
        id: u8,
        /// Its model.
        found: String,
        /// The joint's model.
        expected: &'static str,
    },
    /// The servo found answers at another joint's id and holds this stack's backstops: that
    /// joint's servo, connected alone by mistake.
    #[error(
        "the servo found answers at id {id}, {other}'s, and holds the backstops a set-up \
         servo holds: it is {other}'s servo, connected by mistake, not a new one"
    )]
    OtherJoint {
        /// Its id.
        id: u8,
        /// The joint configured at that id.
        other: String,
    },
    /// After the writes nothing answers at the joint's id and the bus's rate.
    #[error("after setup, nothing answers at id {id} at {baud} baud")]
    Silent {
        /// The joint's id.
        id: u8,
        /// The bus's rate.
        baud: u32,
    },
    /// After the writes the servo does not hold what was written.
    #[error("after setup, {joint} (id {id}) holds {register} = {found}, not {wanted}")]
    NotHeld {
        /// The joint.
        joint: String,
        /// Its id.
        id: u8,
        /// The register.
        register: &'static str,
        /// What it holds.
        found: i32,
        /// What was written.
        wanted: i32,
    },
    /// A transaction failed.
    #[error(transparent)]
    Bus(#[from] BusError),
}

impl From<TransportError> for SetupError {
    fn from(e: TransportError) -> Self {
        SetupError::Bus(BusError::Transport(e))
    }
}

impl Target {
    /// What `joint` on `bus` must become, from the driver's configuration.
    pub fn of(loaded: &LoadedConfig, bus: &BusConfig, joint: &str) -> Result<Target, SetupError> {
        let no_joint = || SetupError::NoJoint {
            bus: bus.name.clone(),
            joint: joint.to_string(),
            joints: bus
                .servo
                .iter()
                .map(|s| s.joint.as_str())
                .collect::<Vec<_>>()
                .join(", "),
        };
        let servo = bus
            .servo
            .iter()
            .find(|s| s.joint == joint)
            .ok_or_else(no_joint)?;
        // Validated at load: every servo's model is known and has backstops.
        let model = ServoModel::from_key(&servo.model).ok_or_else(no_joint)?;
        let backstops = loaded
            .config
            .backstops
            .get(&servo.model)
            .ok_or_else(no_joint)?;
        if baud_code(bus.baud).is_none() {
            return Err(SetupError::Rate {
                bus: bus.name.clone(),
                baud: bus.baud,
            });
        }
        Ok(Target {
            bus: bus.name.clone(),
            joint: joint.to_string(),
            id: servo.id,
            model,
            baud: bus.baud,
            eeprom: backstops::desired(backstops, bus.mode),
            others: bus
                .servo
                .iter()
                .filter(|s| s.joint != joint)
                .map(|s| (s.id, s.joint.clone()))
                .collect(),
        })
    }
}

/// What a setup did.
#[derive(Debug, Clone, PartialEq)]
pub struct Report {
    /// Where the servo was found.
    pub found: Found,
    /// Each register written, in order, with its value.
    pub written: Vec<Setting>,
    /// The servo read back at its new id and rate.
    pub now: Found,
}

/// Sets up the new servo for `target` over the bus's `line` (its rate changed as needed; the
/// device stays open throughout).
pub fn set_up<T: Transport>(line: T, target: &Target, plan: &Plan) -> Result<Report, SetupError> {
    let mut bus = Bus::new(line, plan.window);
    bus.set_baud(target.baud)?;
    let at_joint_id = match scan::ping(&mut bus, target.id, target.baud, plan)? {
        Some(heard) => Some(scan::identify(
            &mut bus,
            target.id,
            target.baud,
            &heard,
            plan,
        )?),
        None => None,
    };
    let found = match at_joint_id {
        // A new servo already at the joint's id (the factory's, for the joint at id 1).
        Some(f) if f.settings.is_some_and(|s| !s.set_up_here()) => f,
        Some(f) => {
            return Err(SetupError::IdTaken {
                bus: target.bus.clone(),
                joint: target.joint.clone(),
                id: target.id,
                what: describe(&f),
            })
        }
        None => find(&mut bus, target, plan)?,
    };
    let Some(settings) = found.settings else {
        return Err(SetupError::NotAlone {
            id: found.id,
            baud: found.baud,
        });
    };
    if let Some((id, other)) = target.others.iter().find(|(id, _)| *id == found.id) {
        if settings.set_up_here() {
            return Err(SetupError::OtherJoint {
                id: *id,
                other: other.clone(),
            });
        }
    }
    if settings.model() != Some(target.model) {
        return Err(SetupError::WrongModel {
            joint: target.joint.clone(),
            id: found.id,
            found: model_name(settings.model_number),
            expected: target.model.key(),
        });
    }
    let written = write(&mut bus, &found, target)?;
    let now = verify(&mut bus, target, plan)?;
    Ok(Report {
        found,
        written,
        now,
    })
}

/// The servo to set up: alone at some rate (the one intact answer to a broadcast PING), or
/// at the factory's id and rate.
fn find<T: Transport>(bus: &mut Bus<T>, target: &Target, plan: &Plan) -> Result<Found, SetupError> {
    for &baud in &plan.rates {
        bus.set_baud(baud)?;
        let broadcast = bus.listen(
            Instruction::Ping { id: BROADCAST_ID },
            scan::BROADCAST_WINDOW + plan.window,
        )?;
        if let BroadcastAnswer::One { id } = BroadcastAnswer::of(&broadcast) {
            if let Some(ping) = scan::ping(bus, id, baud, plan)? {
                return Ok(scan::identify(bus, id, baud, &ping, plan)?);
            }
        }
        if baud == FACTORY_BAUD {
            if let Some(ping) = scan::ping(bus, FACTORY_ID, baud, plan)? {
                return Ok(scan::identify(bus, FACTORY_ID, baud, &ping, plan)?);
            }
        }
    }
    Err(SetupError::NotFound {
        bus: target.bus.clone(),
    })
}

/// The writes, torque off and the EEPROM unlocked first: the id (acknowledged under the old
/// one), the settings at the new id, the rate last (acknowledged at the old one), then Lock.
fn write<T: Transport>(
    bus: &mut Bus<T>,
    found: &Found,
    target: &Target,
) -> Result<Vec<Setting>, SetupError> {
    bus.set_baud(found.baud)?;
    let mut written = Vec::new();
    let mut put = |bus: &mut Bus<T>, id: u8, register, value| -> Result<(), SetupError> {
        bus.write(id, register, value)?;
        written.push(Setting { register, value });
        Ok(())
    };
    put(bus, found.id, reg::TORQUE_ENABLE, 0)?;
    put(bus, found.id, reg::LOCK, 0)?;
    if found.id != target.id {
        put(bus, found.id, reg::ID, i32::from(target.id))?;
    }
    for s in &target.eeprom {
        put(bus, target.id, s.register, s.value)?;
    }
    if found.baud != target.baud {
        let code = baud_code(target.baud).map_or(0, i32::from);
        put(bus, target.id, reg::BAUD_RATE, code)?;
        bus.set_baud(target.baud)?;
    }
    put(bus, target.id, reg::LOCK, 1)?;
    Ok(written)
}

/// The servo read back at the joint's id and the bus's rate: every setting held.
fn verify<T: Transport>(
    bus: &mut Bus<T>,
    target: &Target,
    plan: &Plan,
) -> Result<Found, SetupError> {
    bus.set_baud(target.baud)?;
    let not_held = |register: reg::Register, found: i32, wanted: i32| SetupError::NotHeld {
        joint: target.joint.clone(),
        id: target.id,
        register: register.name,
        found,
        wanted,
    };
    let silent = || SetupError::Silent {
        id: target.id,
        baud: target.baud,
    };
    let ping = scan::ping(bus, target.id, target.baud, plan)?.ok_or_else(silent)?;
    let now = scan::identify(bus, target.id, target.baud, &ping, plan)?;
    let settings = now.settings.ok_or_else(silent)?;
    for s in &target.eeprom {
        let held = settings.value_of(s.register).unwrap_or(-1);
        if held != s.value {
            return Err(not_held(s.register, held, s.value));
        }
    }
    if settings.lock != 1 {
        return Err(not_held(reg::LOCK, i32::from(settings.lock), 1));
    }
    Ok(now)
}

/// A servo found, in a few words.
fn describe(found: &Found) -> String {
    match (&found.settings, found.duplicate) {
        (_, Some(_)) => "more than one servo".to_string(),
        (Some(s), None) => format!("an {}", model_name(s.model_number)),
        (None, None) => "a servo whose table is unreadable".to_string(),
    }
}
