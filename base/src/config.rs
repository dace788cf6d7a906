//! `nori-base`'s configuration (`deploy/config/base.toml`, embedded).

use crate::controller::ControllerConfig;
use crate::drive::Geometry;
use crate::field::FieldConfig;
use crate::ramp::Limits;
use serde::Deserialize;
use std::path::Path;
use telemetry::config::{invalid, parse, within, ConfigError, ProcessConfig};

/// The commented default.
pub const DEFAULT_CONFIG_TOML: &str = include_str!("../../deploy/config/base.toml");

/// The largest wheel speed a Goal_Velocity register carries, rad/s (15 bits of steps/s).
const REGISTER_MAX_WHEEL_SPEED: f64 = 32767.0 * std::f64::consts::TAU / 4096.0;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct File {
    rate_hz: f64,
    command_timeout_ms: u64,
    max_wheel_speed_rad_s: f64,
    wheels: Wheels,
    limits: LimitsFile,
    field: Field,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct Wheels {
    left: String,
    right: String,
    radius_m: f64,
    track_m: f64,
    left_inverted: bool,
    right_inverted: bool,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct LimitsFile {
    max_linear_m_s: f64,
    max_angular_rad_s: f64,
    linear_acc_m_s2: f64,
    linear_brake_m_s2: f64,
    angular_acc_rad_s2: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct Field {
    lidar: bool,
    lidar_position: [f64; 2],
    lidar_yaw_deg: f64,
    half_width_m: f64,
    front_m: f64,
    back_m: f64,
    stop_margin_m: f64,
    scan_max_age_ms: u64,
    min_range_m: f64,
    driver_restart_ms: u64,
}

/// The base controller's process settings.
#[derive(Debug, Clone, PartialEq)]
pub struct BaseConfig {
    /// Control periods per second.
    pub rate_hz: f64,
    /// What the controller does.
    pub controller: ControllerConfig,
}

impl ProcessConfig for BaseConfig {
    const DEFAULT_TOML: &'static str = DEFAULT_CONFIG_TOML;
    const FILE_NAME: &'static str = "base.toml";

    fn parse_in(text: &str, origin: &str, _dir: Option<&Path>) -> Result<Self, ConfigError> {
        let f: File = parse(text, origin)?;
        let bad = |key: &str, reason: String| invalid(origin, key, reason);
        if !(f.rate_hz.is_finite() && (5.0..=500.0).contains(&f.rate_hz)) {
            return Err(bad("rate-hz", format!("{}: 5 to 500", f.rate_hz)));
        }
        within(
            origin,
            "command-timeout-ms",
            f.command_timeout_ms,
            20..=2000,
            " ms",
        )?;
        let max_wheel = f.max_wheel_speed_rad_s;
        if !(max_wheel.is_finite() && max_wheel > 0.0 && max_wheel <= REGISTER_MAX_WHEEL_SPEED) {
            return Err(bad(
                "max-wheel-speed-rad-s",
                format!("{max_wheel}: above 0, at most {REGISTER_MAX_WHEEL_SPEED:.2}"),
            ));
        }
        let w = &f.wheels;
        let geometry = Geometry::new(w.radius_m, w.track_m, w.left_inverted, w.right_inverted)
            .map_err(|e| bad("wheels", e.to_string()))?;
        if w.left.is_empty() || w.left == w.right {
            return Err(bad("wheels.left", "two different joints".into()));
        }
        let l = &f.limits;
        let limits = Limits {
            max_linear_m_s: l.max_linear_m_s,
            max_angular_rad_s: l.max_angular_rad_s,
            linear_acc_m_s2: l.linear_acc_m_s2,
            linear_brake_m_s2: l.linear_brake_m_s2,
            angular_acc_rad_s2: l.angular_acc_rad_s2,
        };
        if let Some(key) = limits.invalid() {
            return Err(bad(&format!("limits.{key}"), "a positive number".into()));
        }
        let field = Self::field(&f, 1.0 / f.rate_hz).map_err(|(key, why)| bad(key, why))?;
        Ok(BaseConfig {
            rate_hz: f.rate_hz,
            controller: ControllerConfig {
                geometry,
                limits,
                max_wheel_speed_rad_s: max_wheel,
                command_timeout_ns: f.command_timeout_ms * 1_000_000,
                wheels: [w.left.clone(), w.right.clone()],
                field,
            },
        })
    }
}

impl BaseConfig {
    fn field(
        f: &File,
        period_s: f64,
    ) -> Result<Option<(FieldConfig, u64)>, (&'static str, String)> {
        let d = &f.field;
        if !d.lidar {
            return Ok(None);
        }
        for (key, v) in [
            ("field.half-width-m", d.half_width_m),
            ("field.front-m", d.front_m),
            ("field.back-m", d.back_m),
            ("field.stop-margin-m", d.stop_margin_m),
        ] {
            if !(v.is_finite() && v > 0.0 && v < 5.0) {
                return Err((key, format!("{v}: a length above 0 and below 5 m")));
            }
        }
        if !(d.min_range_m.is_finite() && (0.0..1.0).contains(&d.min_range_m)) {
            return Err(("field.min-range-m", format!("{}: 0 to 1 m", d.min_range_m)));
        }
        if !(d.lidar_position.iter().all(|v| v.is_finite()) && d.lidar_yaw_deg.is_finite()) {
            return Err(("field.lidar-position", "finite numbers".into()));
        }
        // A revolution takes 80-125 ms; older than a second is no picture of the path.
        if !(100..=1000).contains(&d.scan_max_age_ms) {
            return Err((
                "field.scan-max-age-ms",
                format!("{}: 100 to 1000 ms", d.scan_max_age_ms),
            ));
        }
        // The servos keep their last speed while no driver runs (they have no watchdog): a
        // crashed driver's restart is time the base moves blind. Over 5 s is no restart.
        if d.driver_restart_ms > 5000 {
            return Err((
                "field.driver-restart-ms",
                format!("{}: 0 to 5000 ms", d.driver_restart_ms),
            ));
        }
        let max_age_s = d.scan_max_age_ms as f64 * 1e-3;
        let blind_s = d.driver_restart_ms as f64 * 1e-3;
        Ok(Some((
            FieldConfig {
                lidar_x_m: d.lidar_position[0],
                lidar_y_m: d.lidar_position[1],
                lidar_yaw_rad: d.lidar_yaw_deg.to_radians(),
                half_width_m: d.half_width_m,
                front_m: d.front_m,
                back_m: d.back_m,
                stop_margin_m: d.stop_margin_m,
                // The oldest revolution acted on, a control period, the driver's cycle and the
                // wheels' blind time through a driver restart.
                reaction_s: max_age_s + period_s + 0.01 + blind_s,
                min_range_m: d.min_range_m,
            },
            d.scan_max_age_ms * 1_000_000,
        )))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_default_loads() {
        let c = BaseConfig::embedded().unwrap();
        assert_eq!(c.rate_hz, 50.0);
        assert_eq!(c.controller.wheels, ["left_wheel", "right_wheel"]);
        let (field, age) = c.controller.field.unwrap();
        assert_eq!(age, 300_000_000);
        assert!((field.reaction_s - 1.03).abs() < 1e-9, "{field:?}");
    }

    #[test]
    fn bad_values_name_their_key() {
        for (from, to, key) in [
            ("rate-hz = 50", "rate-hz = 0", "rate-hz"),
            (
                "command-timeout-ms = 250",
                "command-timeout-ms = 5",
                "command-timeout-ms",
            ),
            (
                "max-wheel-speed-rad-s = 3.0",
                "max-wheel-speed-rad-s = 60.0",
                "max-wheel-speed-rad-s",
            ),
            ("radius-m = 0.075", "radius-m = -0.05", "wheels"),
            (
                "right = \"right_wheel\"",
                "right = \"left_wheel\"",
                "wheels.left",
            ),
            (
                "linear-brake-m-s2 = 1.0",
                "linear-brake-m-s2 = 0.0",
                "limits.linear-brake-m-s2",
            ),
            (
                "stop-margin-m = 0.1",
                "stop-margin-m = nan",
                "field.stop-margin-m",
            ),
            (
                "scan-max-age-ms = 300",
                "scan-max-age-ms = 5000",
                "field.scan-max-age-ms",
            ),
            (
                "driver-restart-ms = 700",
                "driver-restart-ms = 60000",
                "field.driver-restart-ms",
            ),
            (
                "lidar-yaw-deg = 0.0",
                "lidar-yaw-deg = inf",
                "field.lidar-position",
            ),
            (
                "min-range-m = 0.05",
                "min-range-m = 2.0",
                "field.min-range-m",
            ),
            ("rate-hz = 50", "rate_hz = 50", "rate_hz"),
        ] {
            let text = DEFAULT_CONFIG_TOML.replacen(from, to, 1);
            assert_ne!(text, DEFAULT_CONFIG_TOML, "{from}");
            let err = BaseConfig::parse_in(&text, "base.toml", None)
                .unwrap_err()
                .to_string();
            assert!(
                err.contains(key) && err.contains("base.toml"),
                "{to}: {err}"
            );
        }
        let without = DEFAULT_CONFIG_TOML.replacen("lidar = true", "lidar = false", 1);
        let c = BaseConfig::parse_in(&without, "base.toml", None).unwrap();
        assert!(c.controller.field.is_none());
    }
}
