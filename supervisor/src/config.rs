//! The supervisor's configuration: thresholds of the stall detector, the thermal tiers and the
//! grip-force calibration. Kebab-case TOML; unknown keys and impossible values are refused.

use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::Path;
pub use telemetry::config::ConfigError;
use telemetry::config::{parse, ProcessConfig};

/// The embedded default (also `deploy/config/supervisor.toml`).
pub const DEFAULT_CONFIG_TOML: &str = include_str!("../../deploy/config/supervisor.toml");

/// The firmware cutoff the driver writes; the software trip must come before it.
pub const HARDWARE_CUTOFF_C: f32 = 60.0;

/// Stall detection (paper: a k = 15 loop window; current high, position static).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct StallConfig {
    /// Window length, control cycles.
    pub window: usize,
    /// Current threshold as a fraction of the model's rated stall current (arm joints).
    pub current_fraction: f32,
    /// The same for grippers.
    pub gripper_current_fraction: f32,
    /// Largest position spread over the window that still counts as static, rad.
    pub static_rad: f32,
    /// An arm joint must be this far from its goal to be "trying to move", rad. Holding a load
    /// within capacity leaves the firmware's P loop a steady-state error below this (the duty
    /// saturates at kp·0.166·error = the torque limit, about 0.15 rad), so heavy holding is not
    /// a stall: the thermal tier covers it.
    pub min_error_rad: f32,
    /// The same for grippers, whose compliant squeeze settles close to the goal.
    pub gripper_min_error_rad: f32,
    /// A goal this far from the one at reduction is a new target (torque restored), rad.
    pub new_target_rad: f32,
    /// Grip torque after a gripper stalls (hold gently), % of full output.
    pub gripper_hold_percent: f32,
    /// Torque of a joint that stalled again after its retry, % of full output.
    pub reduced_percent: f32,
}

/// The two-tier thermal interlock's software tier.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ThermalConfig {
    /// Software trip, °C: the whole bus is disabled (must be below the 60 °C firmware cutoff).
    pub trip_c: f32,
    /// A tripped bus may be re-enabled (by explicit command) once every motor is at or below, °C.
    pub reenable_below_c: f32,
    /// Seconds of history for the temperature slope.
    pub slope_window_s: f32,
    /// Warning levels 1..3: temperature thresholds, °C.
    pub warn_c: [f32; 3],
    /// Warning levels 1..3: predicted seconds to the trip at the present slope.
    pub warn_time_to_trip_s: [f32; 3],
}

/// Grip-force calibration of one gripper: f̂ = clip((|I| − idle)/(max − idle), 0, 1).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct GripCalibration {
    /// Friction floor of the closing gripper, A.
    pub idle_current_a: f32,
    /// Empirical peak before the stall detector engages, A.
    pub max_current_a: f32,
}

/// The supervisor's configuration.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct SupervisorConfig {
    /// The driver is lost after this long without its heartbeat, ms.
    pub driver_timeout_ms: u64,
    /// Rated stall current by model key, A.
    pub stall_current_a: BTreeMap<String, f32>,
    /// Stall detection.
    pub stall: StallConfig,
    /// Thermal tier.
    pub thermal: ThermalConfig,
    /// Grip calibration by gripper joint name.
    pub grip: BTreeMap<String, GripCalibration>,
    /// The lift motor's duty-cycle rating.
    pub lift: LiftDutyConfig,
}

/// The lift motor's duty-cycle rating (`[lift]`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct LiftDutyConfig {
    /// Longest running from cold, s.
    pub on_s: f64,
    /// Rest that running needs, s.
    pub off_s: f64,
    /// Running regained before a spent budget allows travel again, s.
    pub resume_s: f64,
}

impl LiftDutyConfig {
    /// As the budget's rating.
    pub fn rating(&self) -> crate::duty::DutyRating {
        crate::duty::DutyRating {
            on_s: self.on_s,
            off_s: self.off_s,
            resume_s: self.resume_s,
        }
    }
}

impl ProcessConfig for SupervisorConfig {
    const DEFAULT_TOML: &'static str = DEFAULT_CONFIG_TOML;
    const FILE_NAME: &'static str = "supervisor.toml";

    fn parse_in(text: &str, origin: &str, _dir: Option<&Path>) -> Result<Self, ConfigError> {
        Self::parse(text, origin)
    }
}

impl SupervisorConfig {
    /// Parses and validates text; `origin` names it in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Self, ConfigError> {
        let c: SupervisorConfig = parse(text, origin)?;
        let invalid = |key: &str, reason: String| telemetry::config::invalid(origin, key, reason);
        if let Some(key) = c.lift.rating().invalid() {
            return Err(invalid(
                &format!("lift.{key}"),
                "a positive number of seconds (resume-s at most on-s)".into(),
            ));
        }
        if !(5..=10_000).contains(&c.driver_timeout_ms) {
            return Err(invalid(
                "driver-timeout-ms",
                format!("{} is outside 5..=10000 ms", c.driver_timeout_ms),
            ));
        }
        for (model, a) in &c.stall_current_a {
            if !matches!(model.as_str(), "sts3215" | "sts3250" | "sts3095") {
                return Err(invalid(
                    &format!("stall-current-a.{model}"),
                    "unknown model (sts3215, sts3250, sts3095)".into(),
                ));
            }
            if !(a.is_finite() && *a > 0.0 && *a <= 50.0) {
                return Err(invalid(
                    &format!("stall-current-a.{model}"),
                    format!("{a} A is outside (0, 50]"),
                ));
            }
        }
        let t = &c.thermal;
        if !(t.trip_c < HARDWARE_CUTOFF_C && t.trip_c > 30.0) {
            return Err(invalid(
                "thermal.trip-c",
                format!(
                    "{} °C must be below the {HARDWARE_CUTOFF_C} °C firmware cutoff (and above 30)",
                    t.trip_c
                ),
            ));
        }
        if t.reenable_below_c.partial_cmp(&t.trip_c) != Some(std::cmp::Ordering::Less) {
            return Err(invalid(
                "thermal.reenable-below-c",
                format!(
                    "{} °C must be below trip-c {}",
                    t.reenable_below_c, t.trip_c
                ),
            ));
        }
        if !(t.warn_c.windows(2).all(|w| w[0] <= w[1]) && t.warn_c[2] < t.trip_c) {
            return Err(invalid(
                "thermal.warn-c",
                "levels must rise and stay below trip-c".into(),
            ));
        }
        if !(t.warn_time_to_trip_s.windows(2).all(|w| w[0] >= w[1])
            && t.warn_time_to_trip_s[2] > 0.0)
        {
            return Err(invalid(
                "thermal.warn-time-to-trip-s",
                "times must fall with the level and stay > 0".into(),
            ));
        }
        if t.slope_window_s.is_nan() || t.slope_window_s < 2.0 {
            return Err(invalid("thermal.slope-window-s", "must be ≥ 2 s".into()));
        }
        let s = &c.stall;
        if !(2..=crate::stall::MAX_WINDOW).contains(&s.window) {
            return Err(invalid(
                "stall.window",
                format!("{} is outside 2..={}", s.window, crate::stall::MAX_WINDOW),
            ));
        }
        for (key, v) in [
            ("stall.gripper-hold-percent", s.gripper_hold_percent),
            ("stall.reduced-percent", s.reduced_percent),
        ] {
            if !(v > 0.0 && v <= 100.0) {
                return Err(invalid(key, format!("{v} is outside (0, 100]")));
            }
        }
        let thresholds = [
            s.current_fraction,
            s.gripper_current_fraction,
            s.static_rad,
            s.min_error_rad,
            s.gripper_min_error_rad,
            s.new_target_rad,
        ];
        if !thresholds.iter().all(|v| v.is_finite() && *v > 0.0) {
            return Err(invalid("stall", "thresholds must be finite and > 0".into()));
        }
        if s.current_fraction > 1.0 || s.gripper_current_fraction > 1.0 {
            return Err(invalid(
                "stall.current-fraction",
                "a fraction of the rated stall current above 1 can never be reached".into(),
            ));
        }
        for (name, g) in &c.grip {
            if !(g.idle_current_a >= 0.0
                && g.max_current_a > g.idle_current_a
                && g.max_current_a.is_finite())
            {
                return Err(invalid(
                    &format!("grip.{name}"),
                    "max-current-a must exceed idle-current-a ≥ 0".into(),
                ));
            }
        }
        Ok(c)
    }

    /// Rated stall current of a `Model_Number`, A.
    pub fn stall_current(&self, model_number: u16) -> f32 {
        let key = match model_number {
            2825 => "sts3250",
            2569 => "sts3095",
            _ => "sts3215",
        };
        self.stall_current_a.get(key).copied().unwrap_or(2.7)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_is_valid_and_orders_the_tiers() {
        let c = SupervisorConfig::embedded().unwrap();
        assert_eq!(c.stall.window, 15);
        assert_eq!(c.thermal.trip_c, 59.0);
    }

    #[test]
    fn a_trip_at_or_above_the_firmware_cutoff_is_refused() {
        let text = DEFAULT_CONFIG_TOML.replace("trip-c = 59", "trip-c = 60");
        let err = SupervisorConfig::parse(&text, "s.toml")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("thermal.trip-c") && err.contains("s.toml"),
            "{err}"
        );
    }

    #[test]
    fn impossible_values_name_the_key_and_the_file() {
        for (from, to, key) in [
            (
                "driver-timeout-ms = 50",
                "driver-timeout-ms = 0",
                "driver-timeout-ms",
            ),
            ("sts3215 = 2.7", "sts3215 = -2.7", "stall-current-a.sts3215"),
            ("sts3215 = 2.7", "sts9999 = 2.7", "stall-current-a.sts9999"),
            ("window = 15", "window = 1000", "stall.window"),
            ("static-rad = 0.01", "static-rad = inf", "stall"),
            (
                "current-fraction = 0.35",
                "current-fraction = 3.5",
                "stall.current-fraction",
            ),
            ("trip-c = 59", "trip-c = nan", "thermal.trip-c"),
            ("window = 15", "window = \"15\"", "window"),
        ] {
            let text = DEFAULT_CONFIG_TOML.replacen(from, to, 1);
            assert_ne!(text, DEFAULT_CONFIG_TOML, "{from}");
            let err = SupervisorConfig::parse(&text, "s.toml")
                .unwrap_err()
                .to_string();
            assert!(err.contains(key) && err.contains("s.toml"), "{key}: {err}");
        }
    }

    #[test]
    fn unknown_keys_are_refused() {
        let text = DEFAULT_CONFIG_TOML.replace("[stall]", "[stall]\nwindw = 3");
        let err = SupervisorConfig::parse(&text, "s.toml")
            .unwrap_err()
            .to_string();
        assert!(err.contains("windw"), "{err}");
    }
}
