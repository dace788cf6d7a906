//! `nori-lift`'s configuration (`deploy/config/lift.toml`, embedded).

use crate::column::ColumnConfig;
use serde::Deserialize;
use std::path::{Path, PathBuf};
use std::time::Duration;
use telemetry::config::{invalid, parse, within, ConfigError, ProcessConfig};

/// The commented default.
pub const DEFAULT_CONFIG_TOML: &str = include_str!("../../deploy/config/lift.toml");

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct File {
    device: PathBuf,
    baud: u32,
    rate_hz: f64,
    command_max_age_ms: u64,
    silence_ms: u64,
    column: Column,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct Column {
    travel_m: f64,
    counts_per_m: f64,
    soft_margin_m: f64,
    max_speed_m_s: f64,
    accel_m_s2: f64,
    homing_speed_m_s: f64,
    obstruction_speed_fraction: f64,
    obstruction_current_a: f64,
    obstruction_time_ms: u64,
    back_off_m: f64,
    tolerance_m: f64,
}

/// The lift process's settings.
#[derive(Debug, Clone, PartialEq)]
pub struct LiftConfig {
    /// The board's serial device.
    pub device: PathBuf,
    /// Its line rate.
    pub baud: u32,
    /// Control periods per second.
    pub rate_hz: f64,
    /// Commands older than this on arrival are refused.
    pub command_max_age: Duration,
    /// The board silent this long is a lost link.
    pub silence: Duration,
    /// The column.
    pub column: ColumnConfig,
}

impl ProcessConfig for LiftConfig {
    const DEFAULT_TOML: &'static str = DEFAULT_CONFIG_TOML;
    const FILE_NAME: &'static str = "lift.toml";

    fn parse_in(text: &str, origin: &str, _dir: Option<&Path>) -> Result<Self, ConfigError> {
        let f: File = parse(text, origin)?;
        within(origin, "baud", f.baud, 9_600..=4_000_000, "")?;
        // The board's watchdog is 100 ms: at least 20 commands a second.
        if !(f.rate_hz.is_finite() && (20.0..=1000.0).contains(&f.rate_hz)) {
            return Err(invalid(
                origin,
                "rate-hz",
                format!("{}: 20 to 1000", f.rate_hz),
            ));
        }
        within(
            origin,
            "command-max-age-ms",
            f.command_max_age_ms,
            1..=10_000,
            " ms",
        )?;
        within(origin, "silence-ms", f.silence_ms, 50..=10_000, " ms")?;
        let c = &f.column;
        for (key, v) in [
            ("column.travel-m", c.travel_m),
            ("column.counts-per-m", c.counts_per_m),
            ("column.max-speed-m-s", c.max_speed_m_s),
            ("column.accel-m-s2", c.accel_m_s2),
            ("column.homing-speed-m-s", c.homing_speed_m_s),
            (
                "column.obstruction-speed-fraction",
                c.obstruction_speed_fraction,
            ),
            ("column.obstruction-current-a", c.obstruction_current_a),
            ("column.back-off-m", c.back_off_m),
            ("column.tolerance-m", c.tolerance_m),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(invalid(origin, key, format!("{v}: a positive number")));
            }
        }
        if !(c.soft_margin_m.is_finite()
            && c.soft_margin_m >= 0.0
            && 2.0 * c.soft_margin_m < c.travel_m)
        {
            return Err(invalid(
                origin,
                "column.soft-margin-m",
                format!("{}: 0 or more, and the soft limits apart", c.soft_margin_m),
            ));
        }
        // The home's worst case: the stop must come within half a second of meeting a hand.
        within(
            origin,
            "column.obstruction-time-ms",
            c.obstruction_time_ms,
            20..=500,
            " ms",
        )?;
        Ok(LiftConfig {
            device: f.device,
            baud: f.baud,
            rate_hz: f.rate_hz,
            command_max_age: Duration::from_millis(f.command_max_age_ms),
            silence: Duration::from_millis(f.silence_ms),
            column: ColumnConfig {
                travel_m: c.travel_m,
                counts_per_m: c.counts_per_m,
                soft_margin_m: c.soft_margin_m,
                max_speed_m_s: c.max_speed_m_s,
                accel_m_s2: c.accel_m_s2,
                homing_speed_m_s: c.homing_speed_m_s,
                obstruction_current_a: c.obstruction_current_a,
                obstruction_speed_fraction: c.obstruction_speed_fraction,
                obstruction_time_s: c.obstruction_time_ms as f64 * 1e-3,
                back_off_m: c.back_off_m,
                tolerance_m: c.tolerance_m,
            },
        })
    }
}

impl LiftConfig {
    /// The board at `dir/lift` (the simulator's pseudo-terminal).
    pub fn with_device_dir(mut self, dir: &Path) -> Self {
        self.device = dir.join("lift");
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_default_is_the_a3s_column() {
        let c = LiftConfig::embedded().unwrap();
        assert_eq!(c.column, ColumnConfig::A3);
        assert_eq!(c.rate_hz, 100.0);
    }

    #[test]
    fn bad_values_name_their_key() {
        for (from, to, key) in [
            ("rate-hz = 100", "rate-hz = 5", "rate-hz"),
            ("travel-m = 0.76", "travel-m = -1", "column.travel-m"),
            (
                "soft-margin-m = 0.01",
                "soft-margin-m = 0.5",
                "column.soft-margin-m",
            ),
            (
                "obstruction-time-ms = 150",
                "obstruction-time-ms = 5000",
                "column.obstruction-time-ms",
            ),
            (
                "max-speed-m-s = 0.03",
                "max-speed-m-s = nan",
                "column.max-speed-m-s",
            ),
            ("baud = 115200", "bawd = 115200", "bawd"),
        ] {
            let text = DEFAULT_CONFIG_TOML.replacen(from, to, 1);
            assert_ne!(text, DEFAULT_CONFIG_TOML, "{from}");
            let err = LiftConfig::parse_in(&text, "lift.toml", None)
                .unwrap_err()
                .to_string();
            assert!(
                err.contains(key) && err.contains("lift.toml"),
                "{to}: {err}"
            );
        }
    }
}
