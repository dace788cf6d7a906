//! What crosses zenoh, encoded with postcard. Every message starts with its schema version
//! (a varint), so a receiver refuses a message of another version by name instead of
//! misreading it. The layouts are documented for non-Rust peers in `docs/fleet-schema.md`.
//!
//! Times are the robot's CLOCK_MONOTONIC in ns: an action names the observation it was
//! computed from by that observation's own timestamp, and its steps are offsets from it, so the
//! robot judges age with its own clock and no clock synchronisation is needed.

use serde::{Deserialize, Serialize};
use thiserror::Error;

/// The schema version this build speaks.
pub const SCHEMA_VERSION: u16 = 9;

/// Joint telemetry for dashboards, rate-limited (`nori/<robot>/state`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StateMsg {
    /// [`SCHEMA_VERSION`].
    pub version: u16,
    /// The driver's cycle number of this sample.
    pub seq: u64,
    /// Robot monotonic time of the sample, ns.
    pub timestamp_ns: u64,
    /// Wall-clock time when the agent sent it, ms since the Unix epoch (for plots across robots).
    pub wall_ms: u64,
    /// The driver is in its safe state (no supervisor).
    pub safe_state: bool,
    /// The driver's deadline misses so far.
    pub deadline_misses: u64,
    /// Per joint, in the layout's order.
    pub joints: Vec<JointMsg>,
    /// The lift (absent when its controller publishes nothing fresh).
    pub lift: Option<LiftMsg>,
    /// The base (absent when its controller publishes nothing fresh).
    pub base: Option<BaseMsg>,
}

/// The lift, from its controller's newest state.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LiftMsg {
    /// Height above its lowest, m (NaN before homing).
    pub height_m: f32,
    /// The goal in force, m (NaN when none).
    pub goal_m: f32,
    /// `0` not homed, `1` homing, `2` ready, `3` stopped on an obstruction, `4` board silent.
    pub state: u8,
    /// Travel held back: `0` no, `1` the duty-cycle budget is spent, `2` no allowance.
    pub held: u8,
    /// With the budget spent: rest still needed, s.
    pub duty_wait_s: f32,
}

/// The base, from its controller's newest state.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BaseMsg {
    /// Odometry, m, in the frame its controller started in.
    pub x_m: f32,
    /// m.
    pub y_m: f32,
    /// rad.
    pub heading_rad: f32,
    /// Measured forward speed, m/s.
    pub linear_m_s: f32,
    /// Measured turn rate, rad/s.
    pub angular_rad_s: f32,
    /// Free distance along the path the lidar sees, m (negative: none known).
    pub field_distance_m: f32,
    /// The controller's flags (`nori::BaseState` flags: no command, field slowing or
    /// stopped, lidar silent, no lidar, wheels not read, not driven).
    pub flags: u32,
}

/// One joint of a [`StateMsg`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct JointMsg {
    /// rad (rad/s for wheels).
    pub position: f32,
    /// rad/s.
    pub velocity: f32,
    /// °C.
    pub temperature_c: f32,
    /// A.
    pub current_a: f32,
    /// Goal sent to the servo, rad.
    pub goal: f32,
    /// The servo answered in this cycle (otherwise the other fields are zero).
    pub valid: bool,
    /// Torque is on.
    pub torque: bool,
    /// Output lost / bus disabled flags of the state plane.
    pub flags: u8,
}

/// The joint layout (`nori/<robot>/layout`, also in the status reply): names and calibrated
/// ranges, in the order of every joint vector.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LayoutMsg {
    /// [`SCHEMA_VERSION`].
    pub version: u16,
    /// Per joint.
    pub joints: Vec<JointInfoMsg>,
}

/// One joint of a [`LayoutMsg`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JointInfoMsg {
    /// Name (`left_elbow`).
    pub name: String,
    /// Calibrated range, rad.
    pub min: f32,
    /// Calibrated range, rad.
    pub max: f32,
}

/// Something that happened on the robot, as its event journal keeps it: a supervisor event
/// (a trip, a stall, a torque reduction, a driver lost and back ...) or one of the agent's own
/// (`AgentStarted`, `SupervisorStarted`, `DriverStarted`, `ActionsRefused`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EventRecord {
    /// Robot monotonic time, ns.
    pub timestamp_ns: u64,
    /// Wall-clock time when it happened, ms since the Unix epoch (for plots across robots).
    pub wall_ms: u64,
    /// The supervisor's own event number (0 for the agent's events).
    pub origin_seq: u64,
    /// Kind (`ThermalTrip`, `Stall`, `ActionsRefused` ...).
    pub kind: String,
    /// Joint name, empty when the event concerns no joint.
    pub joint: String,
    /// What the kind needs beyond the figures (the reason of `ActionsRefused`), else empty.
    pub detail: String,
    /// Bus index.
    pub bus: u8,
    /// Level (thermal warnings 1..3).
    pub level: u8,
    /// The figure the event is about (°C, s, A, a count, a process id ...).
    pub value: f32,
}

/// One event of the robot's journal (`nori/<robot>/events`): sent when it happens, and again
/// until the fleet acknowledges it stored ([`AckMsg`]); `journal` and `seq` name it, so a
/// receiver keeps it once however often it comes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EventMsg {
    /// [`SCHEMA_VERSION`].
    pub version: u16,
    /// The journal's identity (random, made with it; a robot whose journal was wiped starts a
    /// new one).
    pub journal: u64,
    /// The event's number in that journal, from 1, rising across restarts of the agent.
    pub seq: u64,
    /// The oldest event the robot still holds unacknowledged: one below it that the fleet does
    /// not have was dropped at the journal's bound and is lost for good.
    pub held_from: u64,
    /// What happened.
    pub event: EventRecord,
}

/// The fleet's acknowledgement (`nori/<robot>/acks`): every event of `journal` up to and
/// including `stored_through` is stored; the robot need not send them again.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct AckMsg {
    /// [`SCHEMA_VERSION`].
    pub version: u16,
    /// The journal acknowledged.
    pub journal: u64,
    /// Its events are stored through this number.
    pub stored_through: u64,
}

/// A piece of a frozen black box (`nori/<robot>/blackbox/chunk`): `data` is the box's bytes
/// from `offset`; no bytes is a probe, asking how much of the box the store holds. Sent until
/// the store acknowledges it ([`BoxAckMsg`]); the store keeps a box by `digest`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BoxChunkMsg {
    /// [`SCHEMA_VERSION`].
    pub version: u16,
    /// The box's number on the robot's shelf.
    pub number: u64,
    /// Its file name on the shelf (`NNNNNN-TIME-KIND.mcap`).
    pub name: String,
    /// Its size, bytes.
    pub size: u64,
    /// The SHA-256 of the whole box.
    pub digest: [u8; 32],
    /// Where `data` starts in the box.
    pub offset: u64,
    /// The bytes.
    pub data: Vec<u8>,
}

/// The store's answer to a [`BoxChunkMsg`] (`nori/<robot>/blackbox/ack`): it holds the box's
/// first `received` bytes, and the whole of it, checked against its digest, when `complete`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct BoxAckMsg {
    /// [`SCHEMA_VERSION`].
    pub version: u16,
    /// The box's number on the robot's shelf.
    pub number: u64,
    /// The box's SHA-256.
    pub digest: [u8; 32],
    /// Bytes the store holds, from the start.
    pub received: u64,
    /// Stored whole and checked.
    pub complete: bool,
    /// The store will not take this box (its reason counted there, in `refusals`): the robot
    /// sets it aside.
    pub refused: bool,
}

/// What a policy sees (`nori/<robot>/observation`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ObservationMsg {
    /// [`SCHEMA_VERSION`].
    pub version: u16,
    /// The driver's cycle number.
    pub seq: u64,
    /// Robot monotonic time of the sample, ns: an action computed from this observation
    /// carries it back as `observation_ns`.
    pub timestamp_ns: u64,
    /// Joint positions in the layout's order, rad (NaN for a servo missing in that cycle).
    pub position: Vec<f32>,
    /// Joint velocities, rad/s.
    pub velocity: Vec<f32>,
    /// The configured cameras' newest images (`[observation] cameras`), on the observations
    /// that carry images (every `image-every`-th), each captured at most `image-max-age-ms`
    /// before `timestamp_ns`; a camera without such an image is absent, never a stale picture.
    pub images: Vec<ImageMsg>,
    /// The lift, when its controller is running and homed.
    pub lift: Option<LiftMsg>,
    /// The base, when its controller is running.
    pub base: Option<BaseMsg>,
}

/// One camera image of an observation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ImageMsg {
    /// The camera's name (`head`, `left_wrist`, ...): the dataset key is
    /// `observation.images.<camera>`.
    pub camera: String,
    /// The camera process's frame number.
    pub seq: u64,
    /// Robot monotonic time of the capture, ns.
    pub capture_ns: u64,
    /// Pixels per row.
    pub width: u32,
    /// Rows (the height in pixels).
    pub height: u32,
    /// `"jpeg"`: the camera's own JPEG, untouched (what a dataset's video holds too).
    pub encoding: String,
    /// The encoded image.
    pub data: Vec<u8>,
}

/// A thumbnail of one camera's picture for the fleet's dashboard (`nori/<robot>/preview`),
/// every `preview.every-s` per camera: the RGB frame averaged down on the robot and encoded as
/// a small JPEG (not for policies: their images ride in observations).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PreviewMsg {
    /// [`SCHEMA_VERSION`].
    pub version: u16,
    /// The camera's name.
    pub camera: String,
    /// The camera process's frame number of the picture.
    pub seq: u64,
    /// Robot monotonic time of the capture, ns.
    pub capture_ns: u64,
    /// Wall-clock time when the agent sent it, ms since the Unix epoch.
    pub wall_ms: u64,
    /// Thumbnail pixels per row.
    pub width: u32,
    /// Thumbnail rows.
    pub height: u32,
    /// The camera's own width, pixels.
    pub source_width: u32,
    /// The camera's own height.
    pub source_height: u32,
    /// `"jpeg"`.
    pub encoding: String,
    /// The encoded thumbnail.
    pub data: Vec<u8>,
}

/// One lidar revolution for the fleet's dashboard (`nori/<robot>/scan`), every
/// `preview.scan-every-s`: each point measured, in order, in the lidar's frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScanMsg {
    /// [`SCHEMA_VERSION`].
    pub version: u16,
    /// The lidar process's revolution number.
    pub seq: u64,
    /// Robot monotonic time of the revolution's first point, ns.
    pub start_ns: u64,
    /// Robot monotonic time of its last point, ns.
    pub end_ns: u64,
    /// Wall-clock time when the agent sent it, ms since the Unix epoch.
    pub wall_ms: u64,
    /// Bearing of each point, rad, counter-clockwise from the lidar's forward axis.
    pub angle_rad: Vec<f32>,
    /// Range of each point, m (0: no return).
    pub range_m: Vec<f32>,
    /// The device's signal quality of each point, 0..63.
    pub quality: Vec<u8>,
}

/// An action chunk from a policy (`nori/<robot>/actions`): `steps` targets for every joint of
/// the layout, the k-th to be reached at `observation_ns + step_offsets_ns[k]`, and, when the
/// policy commands them, the lift's height and the base's twist at the same steps.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ActionChunk {
    /// [`SCHEMA_VERSION`].
    pub version: u16,
    /// Rises with every chunk of one policy session.
    pub seq: u64,
    /// `timestamp_ns` of the observation the chunk was computed from (robot clock).
    pub observation_ns: u64,
    /// Per step, ns after `observation_ns`, strictly increasing.
    pub step_offsets_ns: Vec<u64>,
    /// Joints per step (must be the layout's joint count).
    pub joint_count: u16,
    /// Bit j set: joint j is commanded; the others keep their present goal.
    pub joint_mask: u32,
    /// Row-major, `step_offsets_ns.len() × joint_count`, rad.
    pub targets: Vec<f32>,
    /// Per step, the lift's height above its lowest, m; empty: the chunk leaves the lift alone.
    pub lift_m: Vec<f32>,
    /// Per step, the base's forward speed (m/s) then turn rate (rad/s); empty: the chunk leaves
    /// the base alone. The base stops when the plan ends (its commands are no longer renewed).
    pub base_twist: Vec<f32>,
}

/// The agent's answer to `nori/<robot>/status`: what it is, how it is configured, how the
/// link is doing, and the driver's per-bus error counts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StatusMsg {
    /// [`SCHEMA_VERSION`].
    pub version: u16,
    /// The robot's id.
    pub robot_id: String,
    /// The fleet agent's version (its crate version).
    pub agent_version: String,
    /// The `nori-robot` package's version the robot runs (read at the agent's start); `None`:
    /// not installed from a package (a build from source).
    pub installed_version: Option<String>,
    /// The calibration the robot runs (read at the agent's start); `None`: no calibration file
    /// where the robot keeps it, or one that cannot be read.
    pub calibration: Option<CalibrationMsg>,
    /// The agent's rates and action limits.
    pub config: StatusConfig,
    /// The robot as the agent sees it now.
    pub health: StatusHealth,
    /// What the agent has done since it started.
    pub counters: AgentCounters,
    /// The last refusal of an action chunk, with its reason (empty when none).
    pub last_rejection: String,
    /// Per bus of the driver, in its order.
    pub buses: Vec<BusStatus>,
    /// Per configured camera, in the configuration's order.
    pub cameras: Vec<CameraStatus>,
    /// The lidar, when the agent watches one.
    pub lidar: Option<LidarStatus>,
}

/// The calibration a robot runs, from its calibration file's stamp, in a [`StatusMsg`].
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CalibrationMsg {
    /// How: `by-hand`, `automatic`, or `unstamped` (a file written by hand).
    pub method: String,
    /// When, RFC 3339 (empty when unstamped).
    pub at: String,
    /// The robot the file was made for (empty when unstamped): another robot's file shows here.
    pub robot: String,
    /// Joints it calibrates.
    pub joints: u16,
}

/// One camera, from the header of its newest frame on the state plane, in a [`StatusMsg`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraStatus {
    /// The camera's name.
    pub name: String,
    /// Frames its process published (newest sequence number + 1; 0: none seen).
    pub frames: u64,
    /// Frames lost (the device's gaps, a reader too slow).
    pub dropped: u64,
    /// Frames refused as corrupt.
    pub corrupt: u64,
    /// Frames published more than two frame periods after capture.
    pub late: u64,
    /// Age of the newest frame's capture, ms (none seen: `None`).
    pub age_ms: Option<f64>,
}

/// The lidar, from its newest scan on the state plane, in a [`StatusMsg`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LidarStatus {
    /// Revolutions its process published (newest sequence number + 1; 0: none seen).
    pub scans: u64,
    /// Measurements dropped as unconfirmed.
    pub bad_points: u64,
    /// Times the byte stream lost its alignment.
    pub resyncs: u64,
    /// Revolutions dropped for a hole in their coverage.
    pub short_scans: u64,
    /// Revolutions per second of the newest scan.
    pub rotation_hz: Option<f64>,
    /// Age of the newest scan's end, ms (none seen: `None`).
    pub age_ms: Option<f64>,
}

/// The agent's configured rates and action limits, in a [`StatusMsg`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StatusConfig {
    /// Telemetry rate, Hz.
    pub state_hz: f64,
    /// Observation rate, Hz.
    pub observation_hz: f64,
    /// Oldest accepted action, ms after its observation.
    pub max_age_ms: u64,
    /// Longest plan, ms.
    pub horizon_ms: u64,
    /// Weight of a new chunk where it overlaps the plan.
    pub blend_new: f32,
    /// Goal forwarding rate, Hz.
    pub forward_hz: f64,
}

/// The robot as the agent sees it, in a [`StatusMsg`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StatusHealth {
    /// Joints in the driver's layout.
    pub joints: u32,
    /// Age of the newest joint state, ms (none seen yet: `None`).
    pub state_age_ms: Option<f64>,
    /// The driver is in its safe state.
    pub safe_state: Option<bool>,
    /// The driver's deadline misses.
    pub deadline_misses: Option<u64>,
    /// Steps planned ahead by the scheduler.
    pub planned_steps: u64,
}

/// The agent's counters, in a [`StatusMsg`].
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct AgentCounters {
    /// Telemetry messages sent.
    pub state_sent: u64,
    /// Observations sent.
    pub observations_sent: u64,
    /// Events sent (first sendings).
    pub events_sent: u64,
    /// Events sent again (not acknowledged in time: an outage, a fleet store restarting).
    pub events_resent: u64,
    /// Events held in the journal not yet acknowledged by the fleet.
    pub events_unacknowledged: u64,
    /// Events the fleet has acknowledged stored: the journal's number up to which.
    pub events_stored_through: u64,
    /// Events dropped at the journal's bound before the fleet acknowledged them.
    pub events_lost: u64,
    /// Events the journal could not keep (its storage failed): sent once, live, unnumbered.
    pub events_unjournaled: u64,
    /// Acknowledgements that could not be used (malformed, another journal, beyond what was
    /// sent).
    pub acks_refused: u64,
    /// Action chunks accepted by the gate.
    pub actions_accepted: u64,
    /// Action chunks refused, by reason (every reason listed, zeros included).
    pub actions_rejected: std::collections::BTreeMap<String, u64>,
    /// Planned steps dropped because their time had passed.
    pub steps_dropped_past: u64,
    /// Plans that ran out.
    pub plans_expired: u64,
    /// Goal frames forwarded to the driver.
    pub goals_forwarded: u64,
    /// Heights forwarded to the lift's controller.
    pub lift_commands_forwarded: u64,
    /// Velocities forwarded to the base's controller.
    pub base_commands_forwarded: u64,
    /// Plans dropped because the driver restarted or entered its safe state.
    pub plans_dropped: u64,
    /// Scheduled targets withheld at the last check (none, unless the scheduler is wrong).
    pub goals_withheld: u64,
    /// Camera images sent in observations.
    pub images_sent: u64,
    /// Images left out of an observation: none captured within `image-max-age-ms` of it (a
    /// camera stalled, dead or not started).
    pub images_stale: u64,
    /// Camera thumbnails sent to the fleet (`nori/<robot>/preview`).
    pub previews_sent: u64,
    /// Frames that gave no thumbnail (not RGB24, shorter than their header says).
    pub previews_failed: u64,
    /// Lidar revolutions sent to the fleet (`nori/<robot>/scan`).
    pub scans_sent: u64,
    /// The black box's upload to the fleet.
    pub boxes: BoxCounters,
}

/// The black box's upload to the fleet, in [`AgentCounters`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct BoxCounters {
    /// Boxes on the shelf not yet stored whole by the fleet.
    pub pending: u64,
    /// Boxes the fleet's store acknowledged whole.
    pub stored: u64,
    /// Boxes trimmed off the shelf (its cap) before the fleet had them.
    pub lost: u64,
    /// Boxes the fleet's store refused (too large, a name that is no box's, bytes that fail
    /// their digest): set aside while the agent runs.
    pub refused: u64,
    /// Boxes whose file could not be read: set aside while the agent runs.
    pub unreadable: u64,
    /// Bytes sent the first time.
    pub bytes_sent: u64,
    /// Bytes sent again (an outage, a store restarting).
    pub bytes_resent: u64,
    /// Acknowledgements that could not be used (malformed, of no box in flight, another
    /// digest, beyond the box).
    pub acks_refused: u64,
    /// Chunks that could not be read from the shelf.
    pub read_failures: u64,
}

/// One bus of the driver, in a [`StatusMsg`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BusStatus {
    /// The bus's name in the driver's layout.
    pub name: String,
    /// Its device is open.
    pub connected: bool,
    /// It is on (not disabled by the supervisor, a latch or the driver's own trip).
    pub enabled: bool,
    /// The driver's error and read-back counts.
    pub counters: telemetry::frames::BusCounters,
}

/// A message that cannot be read.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum DecodeError {
    /// Not postcard of the expected layout.
    #[error("malformed: {0}")]
    Malformed(String),
    /// Another schema version.
    #[error("schema version {got}, this robot speaks {SCHEMA_VERSION}")]
    Version {
        /// The version the message carries.
        got: u16,
    },
}

/// Encodes a message.
pub fn encode<T: Serialize>(msg: &T) -> Vec<u8> {
    // postcard serialises these types into a Vec without failure modes of its own (no
    // unsupported serde features); an error would be a bug in the types above.
    postcard::to_allocvec(msg).unwrap_or_default()
}

/// Decodes a message whose first field is the schema version; trailing bytes are refused.
pub fn decode<T: for<'de> Deserialize<'de>>(bytes: &[u8]) -> Result<T, DecodeError> {
    let (version, _) = postcard::take_from_bytes::<u16>(bytes)
        .map_err(|e| DecodeError::Malformed(format!("no version: {e}")))?;
    if version != SCHEMA_VERSION {
        return Err(DecodeError::Version { got: version });
    }
    let (msg, rest) =
        postcard::take_from_bytes::<T>(bytes).map_err(|e| DecodeError::Malformed(e.to_string()))?;
    if !rest.is_empty() {
        return Err(DecodeError::Malformed(format!(
            "{} bytes after the message",
            rest.len()
        )));
    }
    Ok(msg)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chunk() -> ActionChunk {
        ActionChunk {
            version: SCHEMA_VERSION,
            seq: 7,
            observation_ns: 1_000_000_000,
            step_offsets_ns: vec![20_000_000, 40_000_000],
            joint_count: 2,
            joint_mask: 0b11,
            targets: vec![0.1, -0.2, 0.3, -0.4],
            lift_m: vec![0.25, 0.26],
            base_twist: vec![0.1, 0.0, 0.15, -0.5],
        }
    }

    #[test]
    fn messages_round_trip() {
        let c = chunk();
        assert_eq!(decode::<ActionChunk>(&encode(&c)), Ok(c));
    }

    #[test]
    fn another_version_is_refused_by_name() {
        let mut c = chunk();
        c.version = SCHEMA_VERSION + 1;
        assert_eq!(
            decode::<ActionChunk>(&encode(&c)),
            Err(DecodeError::Version {
                got: SCHEMA_VERSION + 1
            })
        );
    }

    #[test]
    fn truncated_padded_and_garbage_bytes_are_malformed() {
        let bytes = encode(&chunk());
        for cut in 0..bytes.len() {
            assert!(matches!(
                decode::<ActionChunk>(&bytes[..cut]),
                Err(DecodeError::Malformed(_))
            ));
        }
        let mut padded = bytes.clone();
        padded.push(0);
        assert!(matches!(
            decode::<ActionChunk>(&padded),
            Err(DecodeError::Malformed(_))
        ));
        assert!(decode::<ActionChunk>(b"\x01{\"seq\": 1}").is_err());
    }
}
