//! A scan judged against the driver's configuration: every configured servo at its id, rate
//! and model, no other servo on the bus, and the EEPROM the driver would find.

use crate::scan::{BroadcastAnswer, BusScan, Duplicate, Found};
use bus_driver::backstops;
use bus_driver::config::{BusConfig, LoadedConfig, Mode};
use feetech::ServoModel;
use serde::Serialize;

/// How much a finding matters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Severity {
    /// The driver writes it right at start: nothing to do.
    Note,
    /// The driver would refuse the servo or drive the wrong one: service needed.
    Fault,
}

/// One thing a scan found wrong or worth knowing.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "finding", rename_all = "kebab-case")]
pub enum Finding {
    /// A configured servo answered at no rate.
    Missing {
        /// Its joint.
        joint: String,
        /// Its id.
        id: u8,
    },
    /// A servo answers only at a rate that is not the bus's.
    WrongRate {
        /// The joint configured at its id, if any.
        joint: Option<String>,
        /// Its id.
        id: u8,
        /// The rate it answers at.
        baud: u32,
        /// The bus's rate.
        bus_baud: u32,
    },
    /// The servo at a joint's id is another model.
    WrongModel {
        /// The joint.
        joint: String,
        /// Its id.
        id: u8,
        /// The model the configuration names.
        expected: ServoModelName,
        /// The `Model_Number` read.
        model_number: u16,
    },
    /// More than one servo answers at an id.
    Duplicated {
        /// The joint configured at it, if any.
        joint: Option<String>,
        /// The id.
        id: u8,
        /// How it showed.
        evidence: Duplicate,
    },
    /// A servo no joint is configured at.
    Unexpected {
        /// Its id.
        id: u8,
        /// Its `Model_Number`, if it was read.
        model_number: Option<u16>,
    },
    /// A servo at its joint's id that this stack never set up (the factory's EEPROM): a new
    /// servo, whose horn the joint's calibration knows nothing of.
    NotSetUp {
        /// The joint.
        joint: String,
        /// Its id.
        id: u8,
        /// Its over-temperature cutoff, °C (the factory's).
        max_temperature_c: u8,
    },
    /// A servo answered a broadcast PING at an id the sweep did not find (beyond 252, or one
    /// that answers now and then).
    HeardOnlyByBroadcast {
        /// The id it answered under.
        id: u8,
        /// The rate.
        baud: u32,
    },
    /// A servo answered its PING but never its table.
    Unreadable {
        /// The joint configured at its id, if any.
        joint: Option<String>,
        /// Its id.
        id: u8,
    },
    /// A servo whose homing offset or position limits are not its joint's calibration: the
    /// driver refuses it (a replaced servo, a refitted horn, or a calibration file from
    /// another robot).
    NotCalibrated {
        /// The joint.
        joint: String,
        /// Its id.
        id: u8,
        /// Homing offset and position limits it holds.
        found: [i32; 3],
        /// What the calibration says.
        calibration: [i32; 3],
    },
    /// A servo whose joint has no calibration yet (a robot being calibrated bus by bus): the
    /// driver does not start until every joint has one.
    Uncalibrated {
        /// The joint.
        joint: String,
        /// Its id.
        id: u8,
    },
    /// EEPROM settings that differ from what the driver writes at start (and will write).
    Settings {
        /// The joint.
        joint: String,
        /// Its id.
        id: u8,
        /// Each setting that differs.
        changes: Vec<SettingChange>,
    },
}

/// One EEPROM setting the driver will change.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SettingChange {
    /// The register.
    pub register: &'static str,
    /// What the servo holds.
    pub found: i32,
    /// What the driver writes.
    pub driver_writes: i32,
}

/// A model's configuration key, for reports.
pub type ServoModelName = &'static str;

impl Finding {
    /// How much it matters.
    pub fn severity(&self) -> Severity {
        match self {
            Finding::Settings { .. } => Severity::Note,
            _ => Severity::Fault,
        }
    }
}

impl std::fmt::Display for Finding {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let at = |joint: &Option<String>, id: &u8| match joint {
            Some(j) => format!("{j} (id {id})"),
            None => format!("id {id}"),
        };
        match self {
            Finding::Missing { joint, id } => write!(
                f,
                "{joint} (id {id}) answers at no rate tried: unplugged, unpowered, or a new \
                 servo not yet given its id"
            ),
            Finding::WrongRate {
                joint,
                id,
                baud,
                bus_baud,
            } => write!(
                f,
                "{} answers at {baud} baud, the bus runs at {bus_baud}: its rate must be set \
                 again",
                at(joint, id)
            ),
            Finding::WrongModel {
                joint,
                id,
                expected,
                model_number,
            } => write!(
                f,
                "{joint} (id {id}) is a {} where the configuration says {expected}: the driver \
                 refuses it; fit the right servo",
                model_name(*model_number)
            ),
            Finding::Duplicated {
                joint,
                id,
                evidence,
            } => write!(
                f,
                "more than one servo answers at {} ({}): connect one at a time and give each \
                 its id",
                at(joint, id),
                match evidence {
                    Duplicate::AnsweredTwice { answers } =>
                        format!("{answers} answers to one request"),
                    Duplicate::Garbled { garbled, attempts } =>
                        format!("{garbled} of {attempts} reads garbled"),
                }
            ),
            Finding::Unexpected { id, model_number } => write!(
                f,
                "id {id} ({}) is no joint of this bus (a factory-fresh servo answers at id 1)",
                model_number.map_or("model unread".into(), model_name)
            ),
            Finding::NotSetUp {
                joint,
                id,
                max_temperature_c,
            } => write!(
                f,
                "{joint} (id {id}) was never set up by this stack (its over-temperature cutoff \
                 is the factory's {max_temperature_c} °C): a new servo, to set up and calibrate \
                 before the driver drives it (on a robot never started, the driver's first \
                 start sets it up)"
            ),
            Finding::NotCalibrated {
                joint,
                id,
                found: [o, lo, hi],
                calibration: [co, clo, chi],
            } => write!(
                f,
                "{joint} (id {id}) holds homing offset {o} and limits {lo}..{hi}, the \
                 calibration {co} and {clo}..{chi}: the driver refuses it until the joint is \
                 calibrated"
            ),
            Finding::Uncalibrated { joint, id } => write!(
                f,
                "{joint} (id {id}) has no calibration yet: `nori calibrate by-hand` its bus \
                 (the driver starts once every joint has one)"
            ),
            Finding::HeardOnlyByBroadcast { id, baud } => write!(
                f,
                "id {id} answered a broadcast PING at {baud} baud but not its own PING: an id \
                 beyond the sweep, or a servo that answers now and then"
            ),
            Finding::Unreadable { joint, id } => write!(
                f,
                "{} answers a PING but never its table: a damaged line or servo",
                at(joint, id)
            ),
            Finding::Settings { joint, id, changes } => {
                write!(f, "{joint} (id {id}): the driver will write")?;
                for (i, c) in changes.iter().enumerate() {
                    let sep = if i == 0 { " " } else { ", " };
                    write!(f, "{sep}{} {} → {}", c.register, c.found, c.driver_writes)?;
                }
                Ok(())
            }
        }
    }
}

/// A `Model_Number` as a model's name where known.
pub fn model_name(model_number: u16) -> String {
    match ServoModel::from_model_number(model_number) {
        Some(m) => m.key().to_string(),
        None => format!("model number {model_number}"),
    }
}

/// Judges a bus's scan against its configuration (in `loaded`).
pub fn judge(loaded: &LoadedConfig, bus: &BusConfig, scan: &BusScan) -> Vec<Finding> {
    let mut findings: Vec<Finding> = bus
        .servo
        .iter()
        .filter(|s| !scan.found().any(|f| f.id == s.id))
        .map(|s| Finding::Missing {
            joint: s.joint.clone(),
            id: s.id,
        })
        .collect();
    // A servo answers at one rate; an id also heard at another (a line that does not follow
    // the host's rate, as a pseudo-terminal) is judged where the bus runs.
    let at_bus_rate = |id: u8| scan.found().any(|f| f.id == id && f.baud == bus.baud);
    findings.extend(
        scan.found()
            .filter(|f| f.baud == bus.baud || !at_bus_rate(f.id))
            .filter_map(|f| judge_found(loaded, bus, f)),
    );
    for rate in &scan.rates {
        let heard = match &rate.broadcast {
            BroadcastAnswer::One { id } => std::slice::from_ref(id),
            BroadcastAnswer::Several { ids, .. } => ids.as_slice(),
            BroadcastAnswer::Silent => &[],
        };
        findings.extend(
            heard
                .iter()
                .filter(|id| !rate.found.iter().any(|f| f.id == **id))
                .map(|&id| Finding::HeardOnlyByBroadcast {
                    id,
                    baud: rate.baud,
                }),
        );
    }
    findings.sort_by_key(|f| std::cmp::Reverse(f.severity()));
    findings
}

/// What one id found says: at most one finding (the first that applies).
fn judge_found(loaded: &LoadedConfig, bus: &BusConfig, f: &Found) -> Option<Finding> {
    let servo = bus.servo.iter().find(|s| s.id == f.id);
    let joint = servo.map(|s| s.joint.clone());
    if let Some(evidence) = f.duplicate {
        return Some(Finding::Duplicated {
            joint,
            id: f.id,
            evidence,
        });
    }
    if f.baud != bus.baud {
        return Some(Finding::WrongRate {
            joint,
            id: f.id,
            baud: f.baud,
            bus_baud: bus.baud,
        });
    }
    let Some(settings) = f.settings else {
        return Some(Finding::Unreadable { joint, id: f.id });
    };
    let Some(servo) = servo else {
        return Some(Finding::Unexpected {
            id: f.id,
            model_number: Some(settings.model_number),
        });
    };
    let expected = ServoModel::from_key(&servo.model);
    if settings.model() != expected || expected.is_none() {
        return Some(Finding::WrongModel {
            joint: servo.joint.clone(),
            id: f.id,
            expected: expected.map_or("unknown", ServoModel::key),
            model_number: settings.model_number,
        });
    }
    if !settings.set_up_here() {
        return Some(Finding::NotSetUp {
            joint: servo.joint.clone(),
            id: f.id,
            max_temperature_c: settings.max_temperature_c,
        });
    }
    let calibration = loaded.calibration_for(bus, &servo.joint);
    if calibration.is_none() && bus.mode == Mode::Position {
        return Some(Finding::Uncalibrated {
            joint: servo.joint.clone(),
            id: f.id,
        });
    }
    if let Some(cal) = calibration {
        let want = backstops::calibration_settings(&cal);
        let found = want.map(|s| settings.value_of(s.register).unwrap_or(i32::MIN));
        let calibration = want.map(|s| s.value);
        if found != calibration {
            return Some(Finding::NotCalibrated {
                joint: servo.joint.clone(),
                id: f.id,
                found,
                calibration,
            });
        }
    }
    let changes = settings_against_driver(loaded, bus, &servo.model, &settings);
    (!changes.is_empty()).then(|| Finding::Settings {
        joint: servo.joint.clone(),
        id: f.id,
        changes,
    })
}

/// What the driver's read-compare-write at start would change in this servo's EEPROM.
fn settings_against_driver(
    loaded: &LoadedConfig,
    bus: &BusConfig,
    model: &str,
    settings: &crate::settings::Settings,
) -> Vec<SettingChange> {
    let Some(b) = loaded.config.backstops.get(model) else {
        return Vec::new();
    };
    backstops::desired(b, bus.mode)
        .into_iter()
        .filter_map(|want| {
            let found = settings.value_of(want.register)?;
            (found != want.value).then_some(SettingChange {
                register: want.register.name,
                found,
                driver_writes: want.value,
            })
        })
        .collect()
}
