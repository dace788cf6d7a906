//! `blackbox.toml`: where boxes go, how long the ring is, and each box's window.

use serde::Deserialize;
use std::path::{Path, PathBuf};
use telemetry::config::{self, ConfigError, ProcessConfig};

/// The recorder's configuration.
#[derive(Debug, Clone, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct BlackboxConfig {
    /// Where frozen boxes are kept.
    pub dir: PathBuf,
    /// Seconds the ring keeps in memory.
    pub ring_seconds: f64,
    /// The ring's cap, MB (the oldest dropped beyond it, whatever `ring-seconds` says).
    pub ring_megabytes: f64,
    /// Seconds of a ring segment (compressed as one).
    pub segment_seconds: f64,
    /// Seconds kept before the event that freezes a box.
    pub before_seconds: f64,
    /// Seconds kept after it (or after the last event while the box is open).
    pub after_seconds: f64,
    /// A box is finished this long after it opened, s, whatever keeps happening.
    pub longest_box_seconds: f64,
    /// Frozen boxes kept on disk, MB (the oldest removed beyond it).
    pub disk_megabytes: f64,
}

impl ProcessConfig for BlackboxConfig {
    const DEFAULT_TOML: &'static str = include_str!("../../deploy/config/blackbox.toml");
    const FILE_NAME: &'static str = "blackbox.toml";

    fn parse_in(text: &str, origin: &str, _dir: Option<&Path>) -> Result<Self, ConfigError> {
        let c: BlackboxConfig = config::parse(text, origin)?;
        config::within(origin, "ring-seconds", c.ring_seconds, 10.0..=3600.0, " s")?;
        config::within(
            origin,
            "ring-megabytes",
            c.ring_megabytes,
            1.0..=64.0,
            " MB",
        )?;
        config::within(
            origin,
            "segment-seconds",
            c.segment_seconds,
            0.5..=30.0,
            " s",
        )?;
        config::within(
            origin,
            "before-seconds",
            c.before_seconds,
            1.0..=c.ring_seconds,
            " s",
        )?;
        config::within(origin, "after-seconds", c.after_seconds, 0.0..=600.0, " s")?;
        config::within(
            origin,
            "longest-box-seconds",
            c.longest_box_seconds,
            c.after_seconds..=3600.0,
            " s",
        )?;
        config::within(
            origin,
            "disk-megabytes",
            c.disk_megabytes,
            1.0..=100_000.0,
            " MB",
        )?;
        Ok(c)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_default_loads_and_a_bad_key_is_named() {
        let c = BlackboxConfig::embedded().unwrap();
        assert!(c.before_seconds <= c.ring_seconds);
        let bad = BlackboxConfig::DEFAULT_TOML.replace("after-seconds = ", "after-secs = ");
        let e = BlackboxConfig::parse_in(&bad, "t.toml", None).unwrap_err();
        assert!(e.to_string().contains("after-secs"), "{e}");
        let too_long =
            BlackboxConfig::DEFAULT_TOML.replace("before-seconds = 120", "before-seconds = 4000");
        let e = BlackboxConfig::parse_in(&too_long, "t.toml", None).unwrap_err();
        assert!(e.to_string().contains("before-seconds"), "{e}");
    }
}
