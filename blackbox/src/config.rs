//! `blackbox.toml`: where boxes go, how long the ring is, and each box's window.

use crate::channel::MAX_CAMERAS;
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
    /// The cameras' thumbnails (the shipped values when the section is absent: a file edited
    /// before it existed still loads).
    #[serde(default)]
    pub thumbnails: ThumbnailsConfig,
    /// The body's frames for a viewer (likewise).
    #[serde(default)]
    pub transforms: TransformsConfig,
}

/// `[thumbnails]`: a small JPEG of each camera's picture now and then.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct ThumbnailsConfig {
    /// The cameras (`nori/camera/<name>`), at most [`MAX_CAMERAS`].
    pub cameras: Vec<String>,
    /// A thumbnail of each camera every this-many seconds (0: none).
    pub every_s: f64,
    /// At most this many pixels wide.
    pub width: u32,
    /// JPEG quality, 1-100.
    pub quality: u8,
}

impl Default for ThumbnailsConfig {
    fn default() -> Self {
        ThumbnailsConfig {
            cameras: ["head", "neck", "left_wrist", "right_wrist"]
                .map(String::from)
                .to_vec(),
            every_s: 1.0,
            width: 160,
            quality: 70,
        }
    }
}

/// `[transforms]`: the body's frames from the joint states.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct TransformsConfig {
    /// The frames this many times a second (0: none).
    pub hz: f64,
}

impl Default for TransformsConfig {
    fn default() -> Self {
        TransformsConfig { hz: 10.0 }
    }
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
        // Bounded so that no configuration makes a ring segment large: 8 cameras at 320
        // pixels, one each 0.5 s, are under 1 MB a second; the ring's cap bounds the rest
        // (docs/blackbox.md).
        let t = &c.thumbnails;
        if t.every_s != 0.0 {
            config::within(
                origin,
                "thumbnails.every-s",
                t.every_s,
                0.5..=3600.0,
                " s (or 0)",
            )?;
        }
        config::within(origin, "thumbnails.width", t.width, 16..=320, " px")?;
        config::within(origin, "thumbnails.quality", t.quality, 1..=100, "")?;
        let key = "thumbnails.cameras";
        for (i, name) in t.cameras.iter().enumerate() {
            if !telemetry::sensors::valid_camera_name(name) || t.cameras[..i].contains(name) {
                let reason = format!("{name:?}: a camera named once, of a-z, 0-9 and _");
                return Err(config::invalid(origin, key, reason));
            }
        }
        if t.cameras.len() > MAX_CAMERAS {
            let reason = format!("{} cameras: at most {MAX_CAMERAS}", t.cameras.len());
            return Err(config::invalid(origin, key, reason));
        }
        config::within(origin, "transforms.hz", c.transforms.hz, 0.0..=50.0, " Hz")?;
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

    #[test]
    fn a_file_from_before_the_thumbnails_loads_with_the_shipped_values() {
        let shipped = BlackboxConfig::embedded().unwrap();
        let cut = BlackboxConfig::DEFAULT_TOML;
        let old = &cut[..cut.find("\n# Camera thumbnails").unwrap()];
        let c = BlackboxConfig::parse_in(old, "old.toml", None).unwrap();
        assert_eq!(c.thumbnails, shipped.thumbnails);
        assert_eq!(c.transforms, shipped.transforms);
        for (from, to, key) in [
            ("width = 160", "width = 4", "thumbnails.width"),
            ("quality = 70", "quality = 0", "thumbnails.quality"),
            ("\"neck\"", "\"head\"", "thumbnails.cameras"),
            ("\"neck\"", "\"Neck Cam\"", "thumbnails.cameras"),
            ("hz = 10.0", "hz = -1.0", "transforms.hz"),
            ("hz = 10.0", "hz = 200.0", "transforms.hz"),
            ("width = 160", "width = 1920", "thumbnails.width"),
            ("every-s = 1.0", "every-s = 0.01", "thumbnails.every-s"),
            ("every-s = 1.0", "every-s = 1.0\nfps = 3", "fps"),
        ] {
            let bad = cut.replace(from, to);
            assert_ne!(bad, cut, "{from}");
            let e = BlackboxConfig::parse_in(&bad, "t.toml", None).unwrap_err();
            assert!(e.to_string().contains(key), "{key}: {e}");
        }
        let nine = cut.replace(
            "\"right_wrist\"]",
            "\"right_wrist\", \"a\", \"b\", \"c\", \"d\", \"e\"]",
        );
        let e = BlackboxConfig::parse_in(&nine, "t.toml", None).unwrap_err();
        assert!(e.to_string().contains("at most 8"), "{e}");
    }
}
