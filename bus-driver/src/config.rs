//! The driver's configuration and calibration files: typed, kebab-case keys, unknown keys and
//! impossible values refused with the file and key named.
//!
//! The defaults for the A3 are embedded (`deploy/config/bus-driver.toml` and
//! `deploy/config/calibration.toml`), so the driver runs on the simulated robot with no file.

use crate::calibration::JointCalibration;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};
pub use telemetry::calibration::{CalibrationMethod, Provenance, CALIBRATION_FORMAT};
pub use telemetry::config::ConfigError;
use telemetry::config::{invalid, parse, read, ProcessConfig};
use telemetry::MAX_JOINTS;

/// The embedded default driver configuration.
pub const DEFAULT_CONFIG_TOML: &str = include_str!("../../deploy/config/bus-driver.toml");
/// The embedded default calibration (the simulated A3).
pub const DEFAULT_CALIBRATION_TOML: &str = include_str!("../../deploy/config/calibration.toml");

/// The firmware over-temperature cutoff may not be set above this (°C): damage begins here.
pub const HARDWARE_TEMPERATURE_CEILING_C: u8 = 60;

/// How a bus's servos are driven.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Mode {
    /// Position goals (arms, grippers).
    Position,
    /// Speed goals (wheels).
    Speed,
}

/// One servo on a bus.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ServoConfig {
    /// Bus id.
    pub id: u8,
    /// Joint name (the key of its calibration).
    pub joint: String,
    /// Model key (`sts3215`, `sts3250`, `sts3095`); checked against `Model_Number` at start.
    pub model: String,
    /// What the joint is: `joint` (default) or `gripper` (the supervisor holds a stalled gripper
    /// gently and estimates its grip force). Speed-mode servos are wheels.
    #[serde(default)]
    pub role: Role,
}

/// A position-mode servo's role.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Role {
    /// An arm joint.
    #[default]
    Joint,
    /// A gripper.
    Gripper,
}

/// What the driver does when the supervisor's heartbeat is missing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SafeState {
    /// Torque off on every bus (the arms go limp).
    TorqueOff,
    /// Hold the present position with a low torque limit; goals are refused.
    Hold,
}

/// One bus.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct BusConfig {
    /// Bus name.
    pub name: String,
    /// Serial device (a stable udev name on the robot).
    pub device: PathBuf,
    /// Line rate, baud.
    #[serde(default = "default_baud")]
    pub baud: u32,
    /// Position or speed mode.
    pub mode: Mode,
    /// Servos, in joint order.
    pub servo: Vec<ServoConfig>,
}

fn default_baud() -> u32 {
    1_000_000
}

/// Firmware backstops for one servo model, written once to EEPROM.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct Backstops {
    /// `Protection_Current`, A.
    pub protection_current_a: f64,
    /// `Over_Current_Protection_Time`, ms (10 ms resolution).
    pub over_current_protection_time_ms: u32,
    /// `Max_Torque_Limit`, % of full output (also the torque limit the driver sets).
    pub max_torque_limit_percent: f64,
    /// `Max_Temperature_Limit`, °C: the hardware thermal tier.
    pub max_temperature_c: u8,
}

/// The driver's configuration.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct DriverConfig {
    /// Control loop rate, Hz.
    #[serde(default = "default_rate")]
    pub rate_hz: f64,
    /// Slack added to a transaction's wire time before a missing reply is declared, µs.
    #[serde(default = "default_margin")]
    pub reply_timeout_margin_us: u64,
    /// Goals older than this are discarded, ms.
    #[serde(default = "default_goal_age")]
    pub goal_max_age_ms: u64,
    /// Largest wheel speed sent, rad/s.
    #[serde(default = "default_wheel_speed")]
    pub max_wheel_speed_rad_s: f64,
    /// A wheel whose speed command is older than this (by the command's timestamp) is
    /// stopped, ms.
    #[serde(default = "default_wheel_command_timeout")]
    pub wheel_command_timeout_ms: u64,
    /// The supervisor is missing after this long without its heartbeat, ms; the driver then
    /// applies its safe state. 0 runs without a supervisor (development only: it warns).
    #[serde(default = "default_supervisor_timeout")]
    pub supervisor_timeout_ms: u64,
    /// The safe state.
    #[serde(default = "default_safe_state")]
    pub safe_state: SafeState,
    /// Torque limit of the `hold` safe state, % of full output.
    #[serde(default = "default_hold_percent")]
    pub safe_hold_torque_percent: f64,
    /// The driver's last-resort thermal tier, °C: while no supervisor is heard, a bus one of
    /// whose motors reads this is turned off by the driver itself. At least 1 °C below every
    /// firmware cutoff (`backstops.*.max-temperature-c`).
    #[serde(default = "default_last_resort_trip")]
    pub last_resort_trip_c: u8,
    /// Calibration file, relative to this file; the embedded A3 calibration when absent.
    #[serde(default)]
    pub calibration_file: Option<PathBuf>,
    /// Backstops by model key.
    pub backstops: BTreeMap<String, Backstops>,
    /// The servo buses (`[[bus]]` tables), each with its device, mode and servos.
    pub bus: Vec<BusConfig>,
}

fn default_rate() -> f64 {
    200.0
}
fn default_margin() -> u64 {
    2000
}
fn default_goal_age() -> u64 {
    100
}
fn default_wheel_speed() -> f64 {
    6.0
}
fn default_wheel_command_timeout() -> u64 {
    200
}
fn default_supervisor_timeout() -> u64 {
    50
}
fn default_safe_state() -> SafeState {
    SafeState::Hold
}
fn default_hold_percent() -> f64 {
    20.0
}
fn default_last_resort_trip() -> u8 {
    59
}

/// The largest wheel speed the Goal_Velocity register carries (sign-magnitude, 15 bits of
/// steps/s), rad/s.
pub fn max_encodable_wheel_speed() -> f64 {
    f64::from(feetech::encoding::max_magnitude(15)) / crate::calibration::STEPS_PER_RAD
}

/// The calibration file: one table per joint, and where `nori calibrate` wrote it, what it was
/// made of.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct CalibrationFile {
    /// Who calibrated the robot, when and how (absent from a file written by hand).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibrated: Option<Provenance>,
    /// By joint name.
    pub joint: BTreeMap<String, JointCalibration>,
    /// The servo each joint was calibrated with, as read then (by joint name).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub servo: BTreeMap<String, ServoIdentity>,
}

/// How much of the robot a calibration must cover to be loaded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coverage {
    /// Every position joint (the driver: a joint without one is never driven blind).
    Every,
    /// The joints calibrated so far, none at all included (the commissioning tools, on a robot
    /// being calibrated bus by bus); each one present is still checked.
    SoFar,
}

/// A servo as the calibration read it.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ServoIdentity {
    /// Its id on the bus.
    pub id: u8,
    /// Its model key.
    pub model: String,
    /// Its firmware, major.minor.
    pub firmware: String,
}

/// A loaded, validated configuration with its calibration.
#[derive(Debug, Clone)]
pub struct LoadedConfig {
    /// The configuration.
    pub config: DriverConfig,
    /// Calibration by joint name.
    pub calibration: CalibrationFile,
}

impl DriverConfig {
    /// Parses configuration text; `origin` names it in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Self, ConfigError> {
        parse(text, origin)
    }

    /// A bus by name.
    pub fn bus(&self, name: &str) -> Option<&BusConfig> {
        self.bus.iter().find(|b| b.name == name)
    }

    /// Joints in the order of the state frame.
    pub fn joints(&self) -> impl Iterator<Item = (&BusConfig, &ServoConfig)> {
        self.bus
            .iter()
            .flat_map(|b| b.servo.iter().map(move |s| (b, s)))
    }

    /// Control period.
    pub fn period(&self) -> std::time::Duration {
        std::time::Duration::from_secs_f64(1.0 / self.rate_hz)
    }

    fn validate(
        &self,
        origin: &str,
        calibration: &CalibrationFile,
        cal_origin: &str,
        coverage: Coverage,
    ) -> Result<(), ConfigError> {
        if !(self.rate_hz.is_finite() && (1.0..=1000.0).contains(&self.rate_hz)) {
            return Err(invalid(
                origin,
                "rate-hz",
                format!("{} is outside 1..=1000", self.rate_hz),
            ));
        }
        if !(self.safe_hold_torque_percent > 0.0 && self.safe_hold_torque_percent <= 100.0) {
            return Err(invalid(
                origin,
                "safe-hold-torque-percent",
                format!("{} is outside (0, 100]", self.safe_hold_torque_percent),
            ));
        }
        if self.bus.len() > telemetry::frames::MAX_BUSES {
            return Err(invalid(
                origin,
                "bus",
                format!(
                    "{} buses exceed {}",
                    self.bus.len(),
                    telemetry::frames::MAX_BUSES
                ),
            ));
        }
        let encodable = max_encodable_wheel_speed();
        if !(self.max_wheel_speed_rad_s.is_finite()
            && self.max_wheel_speed_rad_s > 0.0
            && self.max_wheel_speed_rad_s <= encodable)
        {
            return Err(invalid(
                origin,
                "max-wheel-speed-rad-s",
                format!(
                    "{} is outside (0, {encodable:.2}]: Goal_Velocity cannot carry more",
                    self.max_wheel_speed_rad_s
                ),
            ));
        }
        if let Some((model, b)) = self
            .backstops
            .iter()
            .find(|(_, b)| self.last_resort_trip_c >= b.max_temperature_c)
        {
            return Err(invalid(
                origin,
                "last-resort-trip-c",
                format!(
                    "{} °C is not below backstops.{model}.max-temperature-c {} °C: the driver's trip must come before the firmware cutoff",
                    self.last_resort_trip_c, b.max_temperature_c
                ),
            ));
        }
        self.validate_timing(origin)?;
        if self.bus.is_empty() {
            return Err(invalid(origin, "bus", "no bus configured"));
        }
        if let Some((model, b)) = self
            .backstops
            .iter()
            .find(|(_, b)| self.safe_hold_torque_percent > b.max_torque_limit_percent)
        {
            return Err(invalid(
                origin,
                "safe-hold-torque-percent",
                format!(
                    "{} % exceeds backstops.{model}.max-torque-limit-percent {} %: the safe state must not hold harder than driving",
                    self.safe_hold_torque_percent, b.max_torque_limit_percent
                ),
            ));
        }
        self.validate_backstops(origin)?;
        let joints = self.validate_buses(origin, calibration, cal_origin, coverage)?;
        if joints.len() > MAX_JOINTS {
            return Err(invalid(
                origin,
                "bus",
                format!("{} joints exceed the frame's {MAX_JOINTS}", joints.len()),
            ));
        }
        if let Some(extra) = calibration
            .joint
            .keys()
            .find(|j| !joints.contains(j.as_str()))
        {
            return Err(invalid(
                cal_origin,
                format!("joint.{extra}"),
                "no such joint in the driver configuration",
            ));
        }
        Ok(())
    }

    /// Goal age, supervisor timeout and reply margin.
    fn validate_timing(&self, origin: &str) -> Result<(), ConfigError> {
        if !(1..=10_000).contains(&self.goal_max_age_ms) {
            return Err(invalid(
                origin,
                "goal-max-age-ms",
                format!("{} is outside 1..=10000 ms", self.goal_max_age_ms),
            ));
        }
        if !(10..=2000).contains(&self.wheel_command_timeout_ms) {
            return Err(invalid(
                origin,
                "wheel-command-timeout-ms",
                format!(
                    "{} is outside 10..=2000 ms: a base must stop soon after its commands stop",
                    self.wheel_command_timeout_ms
                ),
            ));
        }
        if self.supervisor_timeout_ms > 10_000 {
            return Err(invalid(
                origin,
                "supervisor-timeout-ms",
                format!(
                    "{} ms: a supervisor silent that long is not watching (at most 10000; 0 runs without one)",
                    self.supervisor_timeout_ms
                ),
            ));
        }
        if self.reply_timeout_margin_us > 100_000 {
            return Err(invalid(
                origin,
                "reply-timeout-margin-us",
                format!(
                    "{} µs: a missing servo would stall every cycle that long (at most 100000)",
                    self.reply_timeout_margin_us
                ),
            ));
        }
        Ok(())
    }

    /// Each model's firmware backstops: settable, and the cutoff at or below 60 °C.
    fn validate_backstops(&self, origin: &str) -> Result<(), ConfigError> {
        for (model, b) in &self.backstops {
            let key = |k: &str| format!("backstops.{model}.{k}");
            if feetech::ServoModel::from_key(model).is_none() {
                return Err(invalid(
                    origin,
                    format!("backstops.{model}"),
                    "unknown model (sts3215, sts3250, sts3095)",
                ));
            }
            if b.max_temperature_c > HARDWARE_TEMPERATURE_CEILING_C || b.max_temperature_c < 30 {
                return Err(invalid(
                    origin,
                    key("max-temperature-c"),
                    format!("{} °C is outside 30..={HARDWARE_TEMPERATURE_CEILING_C} °C (damage begins at 60 °C)", b.max_temperature_c),
                ));
            }
            let units = b.protection_current_a / feetech::AMPS_PER_CURRENT_UNIT;
            if !(1.0..=65535.0).contains(&units) {
                return Err(invalid(
                    origin,
                    key("protection-current-a"),
                    format!("{} A is not settable", b.protection_current_a),
                ));
            }
            if b.over_current_protection_time_ms > 2550 || b.over_current_protection_time_ms < 10 {
                return Err(invalid(
                    origin,
                    key("over-current-protection-time-ms"),
                    "must be 10..=2550 ms",
                ));
            }
            if !(b.max_torque_limit_percent > 0.0 && b.max_torque_limit_percent <= 100.0) {
                return Err(invalid(
                    origin,
                    key("max-torque-limit-percent"),
                    "must be in (0, 100]",
                ));
            }
        }
        Ok(())
    }

    /// Buses and servos: unique names, ids and joints, a servo baud rate, backstops for every
    /// model, a valid calibration for every position joint. Returns the joints' names.
    fn validate_buses<'a>(
        &'a self,
        origin: &str,
        calibration: &CalibrationFile,
        cal_origin: &str,
        coverage: Coverage,
    ) -> Result<HashSet<&'a str>, ConfigError> {
        let mut joints = HashSet::new();
        let mut buses = HashSet::new();
        for (i, bus) in self.bus.iter().enumerate() {
            if !buses.insert(&bus.name) {
                return Err(invalid(
                    origin,
                    format!("bus[{i}].name"),
                    format!("duplicate bus {:?}", bus.name),
                ));
            }
            if feetech::timing::baud_code(bus.baud).is_none() {
                return Err(invalid(
                    origin,
                    format!("bus[{i}].baud"),
                    format!("{} is not a servo baud rate", bus.baud),
                ));
            }
            let mut ids = HashSet::new();
            for s in &bus.servo {
                let at = format!("bus[{i}] ({}).servo id {}", bus.name, s.id);
                if s.id > feetech::MAX_ID || !ids.insert(s.id) {
                    return Err(invalid(origin, at, "invalid or duplicate id"));
                }
                if s.joint.starts_with(telemetry::latch::RESERVED_PREFIX) {
                    return Err(invalid(
                        origin,
                        at,
                        format!(
                            "joint {:?}: a name starting with {:?} is the trip record's own",
                            s.joint,
                            telemetry::latch::RESERVED_PREFIX
                        ),
                    ));
                }
                if !joints.insert(s.joint.as_str()) {
                    return Err(invalid(
                        origin,
                        at,
                        format!("joint {:?} appears twice", s.joint),
                    ));
                }
                if bus.mode == Mode::Speed && s.role == Role::Gripper {
                    return Err(invalid(
                        origin,
                        at,
                        "a speed-mode servo cannot be a gripper",
                    ));
                }
                if !self.backstops.contains_key(&s.model) {
                    return Err(invalid(
                        origin,
                        at,
                        format!("no backstops for model {:?}", s.model),
                    ));
                }
                if bus.mode == Mode::Position {
                    match (calibration.joint.get(&s.joint), coverage) {
                        (Some(cal), _) => cal.validate(&s.joint).map_err(|e| {
                            invalid(cal_origin, format!("joint.{}", s.joint), e.reason)
                        })?,
                        (None, Coverage::SoFar) => {}
                        (None, Coverage::Every) => {
                            return Err(invalid(
                                cal_origin,
                                format!("joint.{}", s.joint),
                                "missing: every position joint needs a calibration",
                            ))
                        }
                    }
                }
            }
        }
        Ok(joints)
    }
}

impl CalibrationFile {
    /// A format this driver does not know is refused, naming both.
    pub fn check_format(&self, origin: &str) -> Result<(), ConfigError> {
        match &self.calibrated {
            Some(p) if p.format != CALIBRATION_FORMAT => Err(invalid(
                origin,
                "calibrated.format",
                format!(
                    "format {} is not the {CALIBRATION_FORMAT} this driver reads",
                    p.format
                ),
            )),
            _ => Ok(()),
        }
    }
}

/// The calibration file the configuration names; none there means a robot never calibrated,
/// said with the tool that calibrates it.
fn read_calibration(path: &Path, origin: &str) -> Result<String, ConfigError> {
    match read(path) {
        Err(ConfigError::Io { source, .. }) if source.kind() == std::io::ErrorKind::NotFound => {
            Err(invalid(
                origin,
                "calibration-file",
                format!(
                    "{}: no such file: this robot is not calibrated yet (`nori calibrate \
                     by-hand BUS` for each arm's bus, with the stack stopped)",
                    path.display()
                ),
            ))
        }
        other => other,
    }
}

/// The driver's configuration and the calibration it names (relative to the file; the
/// embedded calibration when it names none).
impl ProcessConfig for LoadedConfig {
    const DEFAULT_TOML: &'static str = DEFAULT_CONFIG_TOML;
    const FILE_NAME: &'static str = "bus-driver.toml";

    fn parse_in(text: &str, origin: &str, dir: Option<&Path>) -> Result<Self, ConfigError> {
        Self::from_texts(text, origin, dir)
    }
}

impl LoadedConfig {
    /// Parses and validates a configuration text and a calibration text (`origin`s name them
    /// in errors), without reading any file: the configuration's `calibration-file` is
    /// ignored in favour of `calibration`.
    pub fn parse_texts(
        text: &str,
        origin: &str,
        calibration: &str,
        cal_origin: &str,
    ) -> Result<Self, ConfigError> {
        let config = DriverConfig::parse(text, origin)?;
        let calibration: CalibrationFile = parse(calibration, cal_origin)?;
        calibration.check_format(cal_origin)?;
        config.validate(origin, &calibration, cal_origin, Coverage::Every)?;
        Ok(LoadedConfig {
            config,
            calibration,
        })
    }

    fn from_texts(text: &str, origin: &str, dir: Option<&Path>) -> Result<Self, ConfigError> {
        Self::covering(text, origin, dir, Coverage::Every)
    }

    /// The configuration at `path` (the embedded default for `None`) with the calibration it
    /// names as far as the robot is calibrated: none yet (the file not there), or some buses
    /// only. For the commissioning tools, which must run on a robot being calibrated.
    pub fn for_commissioning(path: Option<&Path>) -> Result<Self, ConfigError> {
        match path {
            Some(p) => Self::covering(
                &read(p)?,
                &p.display().to_string(),
                p.parent(),
                Coverage::SoFar,
            ),
            None => Self::embedded(),
        }
    }

    fn covering(
        text: &str,
        origin: &str,
        dir: Option<&Path>,
        coverage: Coverage,
    ) -> Result<Self, ConfigError> {
        let config = DriverConfig::parse(text, origin)?;
        let path = config.calibration_file.as_ref().map(|file| match dir {
            Some(dir) => dir.join(file),
            None => file.clone(),
        });
        let (cal_text, cal_origin) = match path {
            Some(path) if coverage == Coverage::SoFar && !path.exists() => {
                (String::from("[joint]\n"), path.display().to_string())
            }
            Some(path) => (read_calibration(&path, origin)?, path.display().to_string()),
            None => (
                DEFAULT_CALIBRATION_TOML.to_string(),
                "<embedded calibration.toml>".into(),
            ),
        };
        let calibration: CalibrationFile = parse(&cal_text, &cal_origin)?;
        calibration.check_format(&cal_origin)?;
        config.validate(origin, &calibration, &cal_origin, coverage)?;
        Ok(LoadedConfig {
            config,
            calibration,
        })
    }

    /// A joint's calibration as the driver uses it: position-mode joints only (a wheel has
    /// none).
    pub fn calibration_for(&self, bus: &BusConfig, joint: &str) -> Option<JointCalibration> {
        match bus.mode {
            Mode::Position => self.calibration.joint.get(joint).copied(),
            Mode::Speed => None,
        }
    }

    /// Points every bus at `dir/<bus name>` (the simulator's device links).
    pub fn with_device_dir(mut self, dir: &Path) -> Self {
        for bus in &mut self.config.bus {
            bus.device = dir.join(&bus.name);
        }
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with(config: &str, calibration: &str) -> Result<LoadedConfig, ConfigError> {
        // Unique per call: tests run in parallel and texts of equal length are common.
        static NEXT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let dir = std::env::temp_dir().join(format!(
            "nori-config-test-{}-{}",
            std::process::id(),
            NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("calibration.toml"), calibration).unwrap();
        let text = format!("calibration-file = \"calibration.toml\"\n{config}");
        std::fs::write(dir.join("bus-driver.toml"), text).unwrap();
        let r = LoadedConfig::load(&dir.join("bus-driver.toml"));
        let _ = std::fs::remove_dir_all(&dir);
        r
    }

    #[test]
    fn a_calibration_file_not_there_says_the_robot_is_not_calibrated_and_how_to() {
        let dir = std::env::temp_dir().join(format!("nori-uncalibrated-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let text = format!("calibration-file = \"absent.toml\"\n{DEFAULT_CONFIG_TOML}");
        std::fs::write(dir.join("bus-driver.toml"), text).unwrap();
        let e = LoadedConfig::load(&dir.join("bus-driver.toml"))
            .unwrap_err()
            .to_string();
        let _ = std::fs::remove_dir_all(&dir);
        assert!(
            e.contains("absent.toml") && e.contains("calibration-file"),
            "{e}"
        );
        assert!(
            e.contains("not calibrated yet") && e.contains("nori calibrate by-hand"),
            "{e}"
        );
    }

    /// The commissioning tools load a robot not calibrated yet, or calibrated bus by bus; the
    /// driver does not.
    #[test]
    fn a_robot_being_calibrated_loads_for_the_tools_and_not_for_the_driver() {
        let dir = std::env::temp_dir().join(format!("nori-calibrating-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let config = dir.join("bus-driver.toml");
        let text = format!("calibration-file = \"robot.toml\"\n{DEFAULT_CONFIG_TOML}");
        std::fs::write(&config, text).unwrap();
        let none = LoadedConfig::for_commissioning(Some(&config)).unwrap();
        assert!(none.calibration.joint.is_empty());
        assert!(LoadedConfig::load(&config).is_err());
        // One arm calibrated: the tools take it, the driver wants every joint.
        let all = LoadedConfig::embedded().unwrap().calibration;
        let left = all.joint.iter().filter(|(j, _)| j.starts_with("left_"));
        let mut text = String::new();
        for (joint, cal) in left {
            text += &format!(
                "[joint.{joint}]\nhoming-offset = {}\nrange-min = {}\nrange-max = {}\n",
                cal.homing_offset, cal.range_min, cal.range_max
            );
        }
        std::fs::write(dir.join("robot.toml"), &text).unwrap();
        let some = LoadedConfig::for_commissioning(Some(&config)).unwrap();
        assert_eq!(some.calibration.joint.len(), 8);
        let e = LoadedConfig::load(&config).unwrap_err().to_string();
        assert!(e.contains("joint.right_") && e.contains("missing"), "{e}");
        // A joint present is still checked.
        std::fs::write(
            dir.join("robot.toml"),
            text.replace("range-max = ", "range-max = -"),
        )
        .unwrap();
        assert!(LoadedConfig::for_commissioning(Some(&config)).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn embedded_defaults_are_valid() {
        let c = LoadedConfig::embedded().unwrap();
        assert_eq!(c.config.rate_hz, 200.0);
        assert_eq!(c.config.joints().count(), 18);
        assert!(c
            .config
            .backstops
            .values()
            .all(|b| b.max_temperature_c == 60));
    }

    #[test]
    fn unknown_key_names_key_and_file() {
        let err = with(
            &DEFAULT_CONFIG_TOML.replace("rate-hz = 200", "rate-hz = 200\nrate_hz = 100"),
            DEFAULT_CALIBRATION_TOML,
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("rate_hz") && err.contains("bus-driver.toml"),
            "{err}"
        );
    }

    #[test]
    fn wrong_type_is_refused() {
        let err = with(
            &DEFAULT_CONFIG_TOML.replace("rate-hz = 200", "rate-hz = \"fast\""),
            DEFAULT_CALIBRATION_TOML,
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("rate-hz"), "{err}");
    }

    #[test]
    fn a_firmware_cutoff_above_60_is_refused() {
        let err = with(
            &DEFAULT_CONFIG_TOML.replacen("max-temperature-c = 60", "max-temperature-c = 70", 1),
            DEFAULT_CALIBRATION_TOML,
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("max-temperature-c") && err.contains("70"),
            "{err}"
        );
    }

    #[test]
    fn a_range_outside_the_travel_names_the_joint_and_the_calibration_file() {
        let cal = DEFAULT_CALIBRATION_TOML.replacen("range-max = 3906", "range-max = 5000", 1);
        let err = with(DEFAULT_CONFIG_TOML, &cal).unwrap_err().to_string();
        assert!(
            err.contains("calibration.toml")
                && err.contains("joint.left_shoulder_pitch")
                && err.contains("5000"),
            "{err}"
        );
    }

    #[test]
    fn the_largest_wheel_speed_allowed_is_the_largest_the_register_carries() {
        let text = DEFAULT_CONFIG_TOML.replacen(
            "max-wheel-speed-rad-s = 6.0",
            &format!("max-wheel-speed-rad-s = {}", max_encodable_wheel_speed()),
            1,
        );
        let c = with(&text, DEFAULT_CALIBRATION_TOML).unwrap();
        let steps =
            crate::calibration::wheel_speed_steps(0, 1e9, c.config.max_wheel_speed_rad_s, false);
        assert!(feetech::encoding::encode_sign_magnitude(steps.unwrap(), 15).is_ok());
    }

    #[test]
    fn impossible_values_name_the_key_and_the_file() {
        for (from, to, key) in [
            (
                "goal-max-age-ms = 100",
                "goal-max-age-ms = 0",
                "goal-max-age-ms",
            ),
            (
                "supervisor-timeout-ms = 50",
                "supervisor-timeout-ms = 600000",
                "supervisor-timeout-ms",
            ),
            (
                "reply-timeout-margin-us = 2000",
                "reply-timeout-margin-us = 5000000",
                "reply-timeout-margin-us",
            ),
            (
                "safe-hold-torque-percent = 20",
                "safe-hold-torque-percent = 100",
                "safe-hold-torque-percent",
            ),
            (
                "wheel-command-timeout-ms = 200",
                "wheel-command-timeout-ms = 5000",
                "wheel-command-timeout-ms",
            ),
            (
                "wheel-command-timeout-ms = 200",
                "wheel-command-timeout-ms = 0",
                "wheel-command-timeout-ms",
            ),
            ("rate-hz = 200", "rate-hz = nan", "rate-hz"),
            ("rate-hz = 200", "rate-hz = 5000", "rate-hz"),
            (
                "max-wheel-speed-rad-s = 6.0",
                "max-wheel-speed-rad-s = inf",
                "max-wheel-speed-rad-s",
            ),
            // Beyond what Goal_Velocity's 15 bits of steps/s carry (50.27 rad/s): an encode
            // that fails would leave the wheel at its previous speed.
            (
                "max-wheel-speed-rad-s = 6.0",
                "max-wheel-speed-rad-s = 60.0",
                "max-wheel-speed-rad-s",
            ),
            (
                "last-resort-trip-c = 59",
                "last-resort-trip-c = 60",
                "last-resort-trip-c",
            ),
            (
                "safe-state = \"hold\"",
                "safe-state = \"limp\"",
                "safe-state",
            ),
        ] {
            let text = DEFAULT_CONFIG_TOML.replacen(from, to, 1);
            assert_ne!(text, DEFAULT_CONFIG_TOML, "{from}");
            let err = with(&text, DEFAULT_CALIBRATION_TOML)
                .unwrap_err()
                .to_string();
            assert!(
                err.contains(key) && err.contains("bus-driver.toml"),
                "{key}: {err}"
            );
        }
    }

    #[test]
    fn impossible_calibrations_name_the_joint_and_the_file() {
        for (from, to, what) in [
            ("range-max = 3906", "range-max = -1", "travel"),
            ("range-min = ", "range-min = 4000 #", "below range-max"),
            ("homing-offset = 0", "homing-offset = 3000", "2047"),
            ("range-max = 3906", "range-max = 3906\nspeed = 1", "speed"),
            ("range-max = 3906", "range-max = \"x\"", "range-max"),
        ] {
            let cal = DEFAULT_CALIBRATION_TOML.replacen(from, to, 1);
            assert_ne!(cal, DEFAULT_CALIBRATION_TOML, "{from}");
            let err = with(DEFAULT_CONFIG_TOML, &cal).unwrap_err().to_string();
            assert!(
                err.contains("calibration.toml") && err.contains(what),
                "{what}: {err}"
            );
        }
    }

    #[test]
    fn a_missing_calibration_is_refused() {
        let cal =
            DEFAULT_CALIBRATION_TOML.replacen("[joint.left_elbow]", "[joint.left_elbow_typo]", 1);
        let err = with(DEFAULT_CONFIG_TOML, &cal).unwrap_err().to_string();
        assert!(err.contains("left_elbow"), "{err}");
    }
}
