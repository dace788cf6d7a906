//! The lidar process's configuration (`deploy/config/lidar.toml`, embedded).

use crate::scan::ScanLimits;
use serde::Deserialize;
use std::path::{Path, PathBuf};
use std::time::Duration;
use telemetry::config::{invalid, parse, ConfigError, ProcessConfig};

/// The commented default.
pub const DEFAULT_CONFIG_TOML: &str = include_str!("../../deploy/config/lidar.toml");

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct File {
    device: PathBuf,
    baud: u32,
    min_range_m: f64,
    max_range_m: f64,
    max_gap_deg: f64,
    silence_ms: u64,
}

/// The lidar's settings.
#[derive(Debug, Clone, PartialEq)]
pub struct LidarConfig {
    /// Serial device (or the simulator's pseudo-terminal).
    pub device: PathBuf,
    /// Line rate.
    pub baud: u32,
    /// What a published revolution keeps.
    pub limits: ScanLimits,
    /// No measurement for this long restarts the scan.
    pub silence: Duration,
}

impl ProcessConfig for LidarConfig {
    const DEFAULT_TOML: &'static str = DEFAULT_CONFIG_TOML;
    const FILE_NAME: &'static str = "lidar.toml";

    fn parse_in(text: &str, origin: &str, _dir: Option<&Path>) -> Result<Self, ConfigError> {
        let f: File = parse(text, origin)?;
        let bad = |key: &str, reason: String| invalid(origin, key, reason);
        if !(9_600..=4_000_000).contains(&f.baud) {
            return Err(bad("baud", format!("{}: 9600 to 4000000", f.baud)));
        }
        if !(f.min_range_m.is_finite() && f.min_range_m >= 0.0) {
            return Err(bad("min-range-m", format!("{}: 0 or more", f.min_range_m)));
        }
        if !(f.max_range_m.is_finite() && f.max_range_m > f.min_range_m && f.max_range_m <= 100.0) {
            return Err(bad(
                "max-range-m",
                format!("{}: above min-range-m, at most 100", f.max_range_m),
            ));
        }
        // A hole of a degree is two measurements at 10 Hz; half a turn is no coverage at all.
        if !(f.max_gap_deg.is_finite() && (1.0..=180.0).contains(&f.max_gap_deg)) {
            return Err(bad("max-gap-deg", format!("{}: 1 to 180", f.max_gap_deg)));
        }
        // Below a revolution at the slowest rate (125 ms) a healthy lidar would be restarted.
        if !(200..=60_000).contains(&f.silence_ms) {
            return Err(bad("silence-ms", format!("{}: 200 to 60000", f.silence_ms)));
        }
        Ok(LidarConfig {
            device: f.device,
            baud: f.baud,
            limits: ScanLimits {
                min_range_m: f.min_range_m,
                max_range_m: f.max_range_m,
                max_gap_deg: f.max_gap_deg,
            },
            silence: Duration::from_millis(f.silence_ms),
        })
    }
}

impl LidarConfig {
    /// The device at `dir/lidar` (the simulator's pseudo-terminal).
    pub fn with_device_dir(mut self, dir: &Path) -> Self {
        self.device = dir.join("lidar");
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_default_is_the_c1() {
        let c = LidarConfig::embedded().unwrap();
        assert_eq!(c.device, Path::new("/dev/nori/lidar"));
        assert_eq!(c.baud, crate::protocol::BAUD);
        assert_eq!(c.limits, ScanLimits::C1);
        assert_eq!(c.silence, Duration::from_secs(1));
        let sim = c.with_device_dir(Path::new("/tmp/nori-sim"));
        assert_eq!(sim.device, Path::new("/tmp/nori-sim/lidar"));
    }

    #[test]
    fn a_bad_value_is_refused_with_its_key() {
        let good = DEFAULT_CONFIG_TOML;
        let cases = [
            ("baud = 460800", "baud = 300", "baud"),
            ("min-range-m = 0.05", "min-range-m = -1.0", "min-range-m"),
            ("max-range-m = 12.0", "max-range-m = 0.01", "max-range-m"),
            ("max-range-m = 12.0", "max-range-m = nan", "max-range-m"),
            ("max-gap-deg = 5.0", "max-gap-deg = 270.0", "max-gap-deg"),
            ("silence-ms = 1000", "silence-ms = 50", "silence-ms"),
            (
                "silence-ms = 1000",
                "silence-ms = 1000\nspeed-rpm = 600",
                "speed-rpm",
            ),
        ];
        for (from, to, key) in cases {
            assert!(good.contains(from), "{from}");
            let text = good.replace(from, to);
            let err = LidarConfig::parse_in(&text, "t.toml", None).unwrap_err();
            assert!(err.to_string().contains(key), "{to}: {err}");
        }
    }
}
