//! The agent's configuration. Kebab-case TOML; unknown keys and impossible values are refused
//! with the file and key named.

use crate::gate::{BodyLimits, GateConfig, Range};
use crate::keys::check_robot_id;
use crate::schedule::MAX_PLAN_STEPS;
use serde::Deserialize;
use std::path::{Path, PathBuf};
pub use telemetry::config::ConfigError;
use telemetry::config::{invalid, parse, within, ProcessConfig};

/// The embedded default (also `deploy/config/fleet-agent.toml`).
pub const DEFAULT_CONFIG_TOML: &str = include_str!("../../deploy/config/fleet-agent.toml");

/// How to reach the fleet.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ZenohConfig {
    /// `peer` or `client`.
    pub mode: String,
    /// Endpoints to connect to.
    pub connect: Vec<String>,
    /// Endpoints to listen on.
    pub listen: Vec<String>,
    /// A zenoh JSON5 file applied first (TLS, access control).
    pub config_file: Option<PathBuf>,
}

/// What goes out, how often.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct TelemetryConfig {
    /// State messages per second.
    pub state_hz: f64,
    /// Observations per second.
    pub observation_hz: f64,
    /// Layout re-sent every, s.
    pub layout_every_s: f64,
}

/// How actions are gated and scheduled.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ActionsConfig {
    /// Stale beyond, ms.
    pub max_age_ms: u64,
    /// Last target held at most, ms.
    pub horizon_ms: u64,
    /// Steps per chunk at most.
    pub max_steps: usize,
    /// Last step at most this long after the observation, ms.
    pub max_span_ms: u64,
    /// Weight of the newer chunk where chunks overlap.
    pub blend_new: f32,
    /// Goals per second to the driver.
    pub forward_hz: f64,
    /// The lift's heights a policy may ask, m above its lowest.
    pub lift_range_m: [f32; 2],
    /// The base's fastest speed a policy may ask, either way, m/s.
    pub base_max_linear_m_s: f32,
    /// The base's fastest turn rate a policy may ask, either way, rad/s.
    pub base_max_angular_rad_s: f32,
}

/// Which sensors the agent watches (their health goes into its status).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct SensorsConfig {
    /// Cameras, by name (`nori/camera/<name>`).
    pub cameras: Vec<String>,
    /// Whether the robot has a lidar (`nori/lidar/scan`).
    pub lidar: bool,
}

/// What an observation carries beyond the joints.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ObservationConfig {
    /// Cameras whose newest JPEG rides in the observation (`nori/camera/<name>/mjpeg`).
    pub cameras: Vec<String>,
    /// Images go with every this-many-th observation.
    pub image_every: u32,
    /// An image captured longer than this before the observation's joint sample is left out, ms.
    pub image_max_age_ms: u64,
}

/// What the fleet's dashboard gets of the sensors (`sensors.cameras`, `sensors.lidar`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct PreviewConfig {
    /// A thumbnail of each camera this often, s (0: none).
    pub every_s: f64,
    /// Thumbnails at most this wide, pixels (the frame averaged down by an integer factor).
    pub width: u32,
    /// Their JPEG quality, 1-100.
    pub quality: u8,
    /// A lidar revolution this often, s (0: none).
    pub scan_every_s: f64,
}

/// The event journal and its delivery to the fleet.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct JournalConfig {
    /// The journal's files at most, bytes (also the events held for the fleet at most).
    pub bound_bytes: u64,
    /// The first wait for the fleet's acknowledgement before events are sent again, ms.
    pub resend_after_ms: u64,
    /// Events sent and not yet acknowledged, at most.
    pub window: usize,
}

/// The black box's frozen boxes to the fleet's store (`crate::box_upload`). A section added
/// after robots shipped: a configuration from before it (an edited conffile kept across an
/// upgrade) gets the shipped values rather than stopping the agent.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct BlackboxUploadConfig {
    /// Bytes a second, on average.
    pub bytes_per_second: u64,
    /// Bytes a chunk carries at most (also the burst after a quiet while).
    pub chunk_bytes: u64,
    /// Chunks sent and not yet acknowledged, at most.
    pub window: usize,
    /// The first wait for the store's acknowledgement before chunks are sent again, ms.
    pub resend_after_ms: u64,
}

impl Default for BlackboxUploadConfig {
    /// The shipped values (`deploy/config/fleet-agent.toml`).
    fn default() -> Self {
        BlackboxUploadConfig {
            bytes_per_second: 65_536,
            chunk_bytes: 65_536,
            window: 4,
            resend_after_ms: 1_000,
        }
    }
}

/// The largest chunk of a box (the fleet's store refuses larger ones).
pub const MAX_BOX_CHUNK_BYTES: u64 = 1 << 20;

/// The largest chunk the agent reads from the shelf in its loop, and the highest pace: a read
/// of the SD card between two goals forwarded is kept short.
const MOST_CHUNK_READ: u64 = 256 << 10;
const MOST_BYTES_PER_SECOND: u64 = 8 << 20;

impl ZenohConfig {
    fn check(&self, origin: &str) -> Result<(), ConfigError> {
        if !matches!(self.mode.as_str(), "peer" | "client") {
            return Err(invalid(
                origin,
                "zenoh.mode",
                format!("{:?}: use \"peer\" or \"client\"", self.mode),
            ));
        }
        for (key, list) in [
            ("zenoh.connect", &self.connect),
            ("zenoh.listen", &self.listen),
        ] {
            for e in list {
                let ok = e.split_once('/').is_some_and(|(proto, addr)| {
                    matches!(proto, "tcp" | "tls") && !addr.is_empty()
                });
                if !ok {
                    return Err(invalid(
                        origin,
                        key,
                        format!("{e:?}: an endpoint is tcp/<host>:<port> or tls/<host>:<port>"),
                    ));
                }
            }
        }
        if self.mode == "client" && self.connect.is_empty() {
            return Err(invalid(
                origin,
                "zenoh.connect",
                "a client needs at least one router to connect to",
            ));
        }
        Ok(())
    }
}

impl ActionsConfig {
    fn check(&self, origin: &str) -> Result<(), ConfigError> {
        within(
            origin,
            "actions.max-age-ms",
            self.max_age_ms,
            1..=10_000,
            " ms",
        )?;
        if self.horizon_ms > 1000 {
            return Err(invalid(
                origin,
                "actions.horizon-ms",
                format!(
                    "{} ms: holding a target longer than 1 s after its time is not a plan",
                    self.horizon_ms
                ),
            ));
        }
        within(
            origin,
            "actions.max-steps",
            self.max_steps,
            1..=MAX_PLAN_STEPS,
            "",
        )?;
        within(
            origin,
            "actions.max-span-ms",
            self.max_span_ms,
            1..=60_000,
            " ms",
        )?;
        if !(self.blend_new > 0.0 && self.blend_new <= 1.0) {
            return Err(invalid(
                origin,
                "actions.blend-new",
                format!("{} is outside (0, 1]", self.blend_new),
            ));
        }
        let [low, high] = self.lift_range_m;
        if !(low >= 0.0 && low < high && high <= 2.0) {
            return Err(invalid(
                origin,
                "actions.lift-range-m",
                format!("[{low}, {high}]: 0 <= low < high <= 2 m"),
            ));
        }
        for (key, v, most) in [
            ("actions.base-max-linear-m-s", self.base_max_linear_m_s, 2.0),
            (
                "actions.base-max-angular-rad-s",
                self.base_max_angular_rad_s,
                6.0,
            ),
        ] {
            if !(v >= 0.0 && v <= most) {
                return Err(invalid(origin, key, format!("{v}: 0 to {most}")));
            }
        }
        Ok(())
    }
}

impl PreviewConfig {
    fn check(&self, origin: &str) -> Result<(), ConfigError> {
        for (key, every) in [
            ("preview.every-s", self.every_s),
            ("preview.scan-every-s", self.scan_every_s),
        ] {
            if !(every == 0.0 || (0.1..=3600.0).contains(&every)) {
                return Err(invalid(
                    origin,
                    key,
                    format!("{every} s: use 0 (none) or 0.1 to 3600"),
                ));
            }
        }
        within(origin, "preview.width", self.width, 16..=640, " pixels")?;
        within(origin, "preview.quality", self.quality, 1..=100, "")
    }
}

/// The agent's configuration.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct AgentConfig {
    /// This robot's fleet name.
    pub robot_id: String,
    /// Fleet link.
    pub zenoh: ZenohConfig,
    /// Outgoing rates.
    pub telemetry: TelemetryConfig,
    /// Incoming actions.
    pub actions: ActionsConfig,
    /// Sensors watched.
    pub sensors: SensorsConfig,
    /// What observations carry.
    pub observation: ObservationConfig,
    /// What the fleet's dashboard sees.
    pub preview: PreviewConfig,
    /// The event journal.
    pub journal: JournalConfig,
    /// The black box's boxes to the fleet.
    #[serde(default)]
    pub blackbox: BlackboxUploadConfig,
}

impl ProcessConfig for AgentConfig {
    const DEFAULT_TOML: &'static str = DEFAULT_CONFIG_TOML;
    const FILE_NAME: &'static str = "fleet-agent.toml";

    fn parse_in(text: &str, origin: &str, _dir: Option<&Path>) -> Result<Self, ConfigError> {
        Self::parse(text, origin)
    }
}

impl AgentConfig {
    /// Parses and validates text; `origin` names it in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Self, ConfigError> {
        let c: AgentConfig = parse(text, origin)?;
        if let Err(e) = check_robot_id(&c.robot_id) {
            return Err(invalid(origin, "robot-id", e.to_string()));
        }
        c.zenoh.check(origin)?;
        c.check_rates(origin)?;
        c.actions.check(origin)?;
        c.check_cameras(origin)?;
        c.preview.check(origin)?;
        c.check_journal(origin)?;
        c.check_blackbox(origin)?;
        Ok(c)
    }

    fn check_rates(&self, origin: &str) -> Result<(), ConfigError> {
        for (key, hz) in [
            ("telemetry.state-hz", self.telemetry.state_hz),
            ("telemetry.observation-hz", self.telemetry.observation_hz),
            ("actions.forward-hz", self.actions.forward_hz),
        ] {
            if !(hz > 0.0 && hz <= 1000.0) {
                return Err(invalid(
                    origin,
                    key,
                    format!("{hz} is outside (0, 1000] Hz"),
                ));
            }
        }
        let every = self.telemetry.layout_every_s;
        if !(every.is_finite() && every >= 0.1) {
            return Err(invalid(
                origin,
                "telemetry.layout-every-s",
                format!("{every}: must be finite and ≥ 0.1 s"),
            ));
        }
        Ok(())
    }

    fn check_cameras(&self, origin: &str) -> Result<(), ConfigError> {
        for (key, cameras) in [
            ("sensors.cameras", &self.sensors.cameras),
            ("observation.cameras", &self.observation.cameras),
        ] {
            for (i, name) in cameras.iter().enumerate() {
                let ok = telemetry::sensors::valid_camera_name(name);
                if !ok || cameras[..i].contains(name) {
                    return Err(invalid(
                        origin,
                        key,
                        format!(
                            "{name:?}: a camera named once, 1 to {} of a-z, 0-9 and _",
                            telemetry::frames::NAME_LEN
                        ),
                    ));
                }
            }
        }
        let o = &self.observation;
        within(
            origin,
            "observation.image-every",
            o.image_every,
            1..=1000,
            "",
        )?;
        within(
            origin,
            "observation.image-max-age-ms",
            o.image_max_age_ms,
            1..=5000,
            " ms",
        )
    }

    fn check_journal(&self, origin: &str) -> Result<(), ConfigError> {
        let j = &self.journal;
        within(
            origin,
            "journal.bound-bytes",
            j.bound_bytes,
            crate::journal::MIN_BOUND..=1 << 30,
            " bytes",
        )?;
        within(
            origin,
            "journal.resend-after-ms",
            j.resend_after_ms,
            100..=crate::delivery::MAX_RESEND_AFTER_NS / 1_000_000,
            " ms",
        )?;
        within(origin, "journal.window", j.window, 1..=65_536, "")
    }

    fn check_blackbox(&self, origin: &str) -> Result<(), ConfigError> {
        let b = &self.blackbox;
        within(
            origin,
            "blackbox.bytes-per-second",
            b.bytes_per_second,
            1024..=MOST_BYTES_PER_SECOND,
            " bytes/s",
        )?;
        within(
            origin,
            "blackbox.chunk-bytes",
            b.chunk_bytes,
            1024..=MOST_CHUNK_READ,
            " bytes",
        )?;
        within(origin, "blackbox.window", b.window, 1..=64, "")?;
        within(
            origin,
            "blackbox.resend-after-ms",
            b.resend_after_ms,
            100..=crate::box_upload::MAX_RESEND_AFTER_NS / 1_000_000,
            " ms",
        )
    }

    /// How the black box's boxes go to the fleet.
    pub fn box_upload(&self) -> crate::box_upload::UploadConfig {
        let b = &self.blackbox;
        crate::box_upload::UploadConfig {
            chunk_bytes: b.chunk_bytes,
            bytes_per_second: b.bytes_per_second as f64,
            burst_bytes: b.chunk_bytes as f64,
            window: b.window,
            resend_after_ns: b.resend_after_ms * 1_000_000,
        }
    }

    /// How the journal's events are delivered.
    pub fn delivery(&self) -> crate::delivery::DeliveryConfig {
        crate::delivery::DeliveryConfig {
            bound_bytes: usize::try_from(self.journal.bound_bytes).unwrap_or(usize::MAX),
            resend_after_ns: self.journal.resend_after_ms * 1_000_000,
            window: self.journal.window,
        }
    }

    /// The gate's limits.
    pub fn gate(&self) -> GateConfig {
        GateConfig {
            max_age_ns: self.actions.max_age_ms * 1_000_000,
            max_steps: self.actions.max_steps,
            max_span_ns: self.actions.max_span_ms * 1_000_000,
            body: BodyLimits {
                lift_m: Range {
                    min: self.actions.lift_range_m[0],
                    max: self.actions.lift_range_m[1],
                },
                max_linear_m_s: self.actions.base_max_linear_m_s,
                max_angular_rad_s: self.actions.base_max_angular_rad_s,
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_default_loads() {
        let c = AgentConfig::embedded().unwrap();
        assert_eq!(c.zenoh.mode, "peer");
        assert_eq!(c.gate().max_age_ns, 250_000_000);
    }

    #[test]
    fn a_configuration_from_before_the_black_box_s_upload_gets_the_shipped_values() {
        let before = DEFAULT_CONFIG_TOML
            .split("\n[blackbox]")
            .next()
            .unwrap()
            .to_string();
        assert!(!before.contains("bytes-per-second"));
        let old = AgentConfig::parse(&before, "old.toml").unwrap();
        let shipped = AgentConfig::embedded().unwrap();
        assert_eq!(old.blackbox, shipped.blackbox);
        assert_eq!(old.blackbox, BlackboxUploadConfig::default());
        // One key of the section given, the rest shipped.
        let one = format!("{before}\n[blackbox]\nwindow = 2\n");
        let c = AgentConfig::parse(&one, "one.toml").unwrap();
        assert_eq!((c.blackbox.window, c.blackbox.chunk_bytes), (2, 65_536));
    }

    #[test]
    fn bad_values_name_their_key() {
        for (from, to, key) in [
            ("robot-id = \"sim-0001\"", "robot-id = \"a/b\"", "robot-id"),
            (
                "cameras = [\"head\", \"neck\", \"left_wrist\", \"right_wrist\"]",
                "cameras = [\"head\", \"head\"]",
                "sensors.cameras",
            ),
            (
                "cameras = [\"head\", \"neck\", \"left_wrist\", \"right_wrist\"]",
                "cameras = [\"Head Cam\"]",
                "sensors.cameras",
            ),
            ("mode = \"peer\"", "mode = \"router\"", "zenoh.mode"),
            ("state-hz = 10.0", "state-hz = nan", "telemetry.state-hz"),
            ("max-age-ms = 250", "max-age-ms = 0", "actions.max-age-ms"),
            (
                "horizon-ms = 100",
                "horizon-ms = 5000",
                "actions.horizon-ms",
            ),
            ("max-steps = 128", "max-steps = 100000", "actions.max-steps"),
            ("blend-new = 0.7", "blend-new = 0.0", "actions.blend-new"),
            (
                "lift-range-m = [0.01, 0.75]",
                "lift-range-m = [0.5, 0.2]",
                "actions.lift-range-m",
            ),
            (
                "base-max-linear-m-s = 0.2",
                "base-max-linear-m-s = nan",
                "actions.base-max-linear-m-s",
            ),
            ("blend-new = 0.7", "blend-now = 0.7", "blend-now"),
            (
                "image-every = 3",
                "image-every = 0",
                "observation.image-every",
            ),
            (
                "image-max-age-ms = 150",
                "image-max-age-ms = 0",
                "observation.image-max-age-ms",
            ),
            (
                "cameras = []",
                "cameras = [\"left wrist\"]",
                "observation.cameras",
            ),
            ("max-steps = 128", "max-steps = -1", "max-steps"),
            ("max-span-ms = ", "max-span-ms = 0 #", "actions.max-span-ms"),
            ("forward-hz = ", "forward-hz = inf #", "actions.forward-hz"),
            (
                "layout-every-s = ",
                "layout-every-s = 0.0 #",
                "telemetry.layout-every-s",
            ),
            ("every-s = 2.0", "every-s = 0.01", "preview.every-s"),
            (
                "scan-every-s = 1.0",
                "scan-every-s = -1.0",
                "preview.scan-every-s",
            ),
            ("width = 160", "width = 4000", "preview.width"),
            ("quality = 70", "quality = 0", "preview.quality"),
            (
                "bytes-per-second = 65536",
                "bytes-per-second = 10",
                "blackbox.bytes-per-second",
            ),
            (
                "chunk-bytes = 65536",
                "chunk-bytes = 4194304",
                "blackbox.chunk-bytes",
            ),
            ("window = 4\n", "window = 0\n", "blackbox.window"),
            ("window = 4\n", "window = 65\n", "blackbox.window"),
            (
                "bytes-per-second = 65536",
                "bytes-per-second = 16777216",
                "blackbox.bytes-per-second",
            ),
            (
                "chunk-bytes = 65536",
                "chunk-bytes = 524288",
                "blackbox.chunk-bytes",
            ),
            (
                "resend-after-ms = 1000",
                "resend-after-ms = 0",
                "blackbox.resend-after-ms",
            ),
        ] {
            let text = DEFAULT_CONFIG_TOML.replace(from, to);
            assert_ne!(text, DEFAULT_CONFIG_TOML);
            let e = AgentConfig::parse(&text, "agent.toml")
                .unwrap_err()
                .to_string();
            assert!(e.contains(key) && e.contains("agent.toml"), "{e}");
        }
    }
}
