//! The box's channels: what each carries, its JSON schema (so Foxglove, Rerun and the `mcap`
//! tools decode it without a plugin), and each state-plane frame written as its JSON message.
//!
//! JSON rather than a binary encoding: every generic viewer reads it with the schema alone, and
//! zstd takes back most of its size (BENCHMARKS.md, "Black box"). Bytes on the wire are base64,
//! as Foxglove's JSON schemas carry bytes.

use base64::Engine;
use serde::Serialize;
use telemetry::frames::{
    BusHealth, Directives, EventKind, GoalFrame, JointLayout, JointState, SupervisorEvent,
    DIRECTIVE_FLAG_STOP,
};
use telemetry::motion::{BaseState, LiftState};
pub use telemetry::wire::Direction;
use telemetry::wire::WireFrame;

/// One channel of a box.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Channel {
    /// Every bus's bytes on the wire, per bus and cycle.
    Wire,
    /// The driver's joint-state frames, every cycle.
    JointStates,
    /// Goals for the arms and grippers, from every source.
    Goals,
    /// The base controller's wheel goals.
    WheelGoals,
    /// The supervisor's directives.
    Directives,
    /// The supervisor's and the driver's events.
    Events,
    /// Each bus's error counts.
    BusHealth,
    /// The lift's state.
    LiftState,
    /// The base's state.
    BaseState,
    /// Why the box was frozen (one message per freezing event).
    Triggers,
    /// The driver's layout: each joint's name, bus, id, servo model and range (once a second).
    Layout,
    /// A lidar revolution a second, in Foxglove's `LaserScan`.
    LidarScan,
    /// The body's frames (each arm's shoulder, joints and tool, the lift, the base), in
    /// Foxglove's `FrameTransforms`, so a viewer draws the arms moving.
    Transforms,
    /// Camera `k`'s thumbnails, in Foxglove's `CompressedImage`: `k` is its place in the box's
    /// cameras (its metadata `cameras`), its topic `/camera/<name>/thumbnail`.
    Thumbnail(u8),
}

/// Cameras a box can hold thumbnails of.
pub const MAX_CAMERAS: usize = 8;
const THUMBNAIL_ID: u8 = 32;

impl Channel {
    /// Every channel but the thumbnails (one per camera), in id order.
    pub const ALL: [Channel; 13] = [
        Channel::Wire,
        Channel::JointStates,
        Channel::Goals,
        Channel::WheelGoals,
        Channel::Directives,
        Channel::Events,
        Channel::BusHealth,
        Channel::LiftState,
        Channel::BaseState,
        Channel::Triggers,
        Channel::Layout,
        Channel::LidarScan,
        Channel::Transforms,
    ];

    /// Its id in the ring.
    pub fn id(self) -> u8 {
        match self {
            Channel::Thumbnail(k) => THUMBNAIL_ID + k,
            c => Channel::ALL.iter().position(|&a| a == c).unwrap_or(0) as u8,
        }
    }

    /// The channel with id `id`.
    pub fn from_id(id: u8) -> Option<Channel> {
        match id.checked_sub(THUMBNAIL_ID) {
            Some(k) if (k as usize) < MAX_CAMERAS => Some(Channel::Thumbnail(k)),
            Some(_) => None,
            None => Channel::ALL.get(id as usize).copied(),
        }
    }

    /// Its topic in a box whose cameras are `cameras` (a thumbnail of a camera it does not
    /// name is `/camera/<k>/thumbnail`).
    pub fn topic_in(self, cameras: &[String]) -> std::borrow::Cow<'static, str> {
        match self {
            Channel::Thumbnail(k) => format!(
                "/camera/{}/thumbnail",
                cameras
                    .get(k as usize)
                    .map_or_else(|| k.to_string(), Clone::clone)
            )
            .into(),
            c => c.topic().into(),
        }
    }

    /// The channel whose topic is `topic` in a box whose cameras are `cameras`.
    pub fn from_topic_in(topic: &str, cameras: &[String]) -> Option<Channel> {
        let camera = topic
            .strip_prefix("/camera/")
            .and_then(|t| t.strip_suffix("/thumbnail"));
        match camera {
            Some(name) => cameras
                .iter()
                .take(MAX_CAMERAS)
                .position(|c| c == name)
                .map(|k| Channel::Thumbnail(k as u8)),
            None => Channel::from_topic(topic),
        }
    }

    /// Its topic in the box (a thumbnail's without its camera's name: see [`Channel::topic_in`]).
    pub fn topic(self) -> &'static str {
        match self {
            Channel::Wire => "/bus/wire",
            Channel::JointStates => "/joint_states",
            Channel::Goals => "/goals",
            Channel::WheelGoals => "/base/wheel_goals",
            Channel::Directives => "/supervisor/directives",
            Channel::Events => "/events",
            Channel::BusHealth => "/bus/health",
            Channel::LiftState => "/lift/state",
            Channel::BaseState => "/base/state",
            Channel::Triggers => "/blackbox/triggers",
            Channel::Layout => "/layout",
            Channel::LidarScan => "/lidar/scan",
            Channel::Transforms => "/tf",
            Channel::Thumbnail(_) => "/camera/thumbnail",
        }
    }

    /// The channel whose topic is `topic` (a thumbnail's: `None`, see
    /// [`Channel::from_topic_in`]).
    pub fn from_topic(topic: &str) -> Option<Channel> {
        Channel::ALL.into_iter().find(|c| c.topic() == topic)
    }

    /// Its schema's name.
    pub fn schema_name(self) -> &'static str {
        match self {
            Channel::Wire => "nori.BusWire",
            Channel::JointStates => "nori.JointStates",
            Channel::Goals | Channel::WheelGoals => "nori.Goals",
            Channel::Directives => "nori.Directives",
            Channel::Events => "nori.Event",
            Channel::BusHealth => "nori.BusHealth",
            Channel::LiftState => "nori.LiftState",
            Channel::BaseState => "nori.BaseState",
            Channel::Triggers => "nori.Trigger",
            Channel::Layout => "nori.Layout",
            Channel::LidarScan => "foxglove.LaserScan",
            Channel::Transforms => "foxglove.FrameTransforms",
            Channel::Thumbnail(_) => "foxglove.CompressedImage",
        }
    }

    /// Its JSON schema (draft 2020-12).
    pub fn schema(self) -> String {
        let properties = match self {
            Channel::LidarScan => return LASER_SCAN_SCHEMA.to_string(),
            Channel::Transforms => return FRAME_TRANSFORMS_SCHEMA.clone(),
            Channel::Thumbnail(_) => return COMPRESSED_IMAGE_SCHEMA.clone(),
            Channel::Wire => WIRE_PROPERTIES,
            Channel::JointStates => JOINT_STATES_PROPERTIES,
            Channel::Goals | Channel::WheelGoals => GOALS_PROPERTIES,
            Channel::Directives => DIRECTIVES_PROPERTIES,
            Channel::Events | Channel::Triggers => EVENT_PROPERTIES,
            Channel::Layout => LAYOUT_PROPERTIES,
            Channel::BusHealth => {
                r#""seq": {"type": "integer"}, "buses": {"type": "array", "items": {"type": "object"}}"#
            }
            Channel::LiftState => {
                r#""seq": {"type": "integer"}, "height_m": {"type": "number"}, "goal_m": {"type": "number"}, "velocity_m_s": {"type": "number"}, "current_a": {"type": "number"}, "state": {"type": "integer"}, "held": {"type": "boolean"}, "obstructions": {"type": "integer"}"#
            }
            Channel::BaseState => {
                r#""seq": {"type": "integer"}, "x_m": {"type": "number"}, "y_m": {"type": "number"}, "theta_rad": {"type": "number"}, "linear_m_s": {"type": "number"}, "angular_rad_s": {"type": "number"}, "field_distance_m": {"type": "number"}, "flags": {"type": "array", "items": {"type": "string"}}"#
            }
        };
        format!(
            r#"{{"$schema": "https://json-schema.org/draft/2020-12/schema", "title": "{}", "type": "object", "properties": {{"timestamp_ns": {{"type": "integer", "description": "CLOCK_MONOTONIC of the robot, ns"}}, {properties}}}, "required": ["timestamp_ns"]}}"#,
            self.schema_name()
        )
    }
}

const WIRE_PROPERTIES: &str = r#""cycle": {"type": "integer"}, "bus": {"type": "string"}, "lost_bytes": {"type": "integer"}, "chunks": {"type": "array", "items": {"type": "object", "properties": {"t_ns": {"type": "integer"}, "direction": {"type": "string", "enum": ["sent", "received", "send_failed", "discarded", "reopened", "baud_changed"]}, "data": {"type": "string", "contentEncoding": "base64"}}, "required": ["t_ns", "direction", "data"]}}"#;
const JOINT_STATES_PROPERTIES: &str = r#""seq": {"type": "integer"}, "safe_state": {"type": "boolean"}, "name": {"type": "array", "items": {"type": "string"}}, "valid": {"type": "array", "items": {"type": "boolean"}}, "position": {"type": "array", "items": {"type": "number"}}, "velocity": {"type": "array", "items": {"type": "number"}}, "load": {"type": "array", "items": {"type": "number"}}, "current_a": {"type": "array", "items": {"type": "number"}}, "voltage_v": {"type": "array", "items": {"type": "number"}}, "temperature_c": {"type": "array", "items": {"type": "number"}}, "goal": {"type": "array", "items": {"type": "number"}}, "status": {"type": "array", "items": {"type": "integer"}}, "torque_enabled": {"type": "array", "items": {"type": "boolean"}}, "flags": {"type": "array", "items": {"type": "integer"}}"#;
const GOALS_PROPERTIES: &str = r#""seq": {"type": "integer"}, "name": {"type": "array", "items": {"type": "string"}}, "goal": {"type": "array", "items": {"type": "number"}}"#;
const DIRECTIVES_PROPERTIES: &str = r#""seq": {"type": "integer"}, "stop": {"type": "boolean"}, "bus_enabled": {"type": "array", "items": {"type": "boolean"}}, "torque_limit_permille": {"type": "array", "items": {"type": "integer"}}"#;
/// Foxglove's `LaserScan`, as its JSON schema has it (the well-known schema every Foxglove
/// panel draws without a plugin): ranges evenly spaced from `start_angle` to `end_angle`.
const LASER_SCAN_SCHEMA: &str = r#"{"$schema": "https://json-schema.org/draft/2020-12/schema", "title": "foxglove.LaserScan", "type": "object", "properties": {"timestamp": {"type": "object", "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}}, "frame_id": {"type": "string"}, "pose": {"type": "object", "properties": {"position": {"type": "object", "properties": {"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}}}, "orientation": {"type": "object", "properties": {"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}, "w": {"type": "number"}}}}}, "start_angle": {"type": "number"}, "end_angle": {"type": "number"}, "ranges": {"type": "array", "items": {"type": "number"}}, "intensities": {"type": "array", "items": {"type": "number"}}}, "required": ["timestamp", "frame_id", "start_angle", "end_angle", "ranges"]}"#;

/// Foxglove's `Time` in a JSON schema.
const TIME_SCHEMA: &str = r#"{"type": "object", "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}, "required": ["sec", "nsec"]}"#;

/// Foxglove's `CompressedImage`, as its JSON schema has it (the Image panel draws it).
static COMPRESSED_IMAGE_SCHEMA: std::sync::LazyLock<String> = std::sync::LazyLock::new(|| {
    format!(
        r#"{{"$schema": "https://json-schema.org/draft/2020-12/schema", "title": "foxglove.CompressedImage", "type": "object", "properties": {{"timestamp": {TIME_SCHEMA}, "timestamp_ns": {{"type": "integer", "description": "the frame's capture, CLOCK_MONOTONIC of the robot, ns"}}, "frame_id": {{"type": "string"}}, "data": {{"type": "string", "contentEncoding": "base64"}}, "format": {{"type": "string"}}}}, "required": ["timestamp", "frame_id", "data", "format"]}}"#
    )
});

/// Foxglove's `FrameTransforms`, as its JSON schema has it (the 3D panel's transform tree).
static FRAME_TRANSFORMS_SCHEMA: std::sync::LazyLock<String> = std::sync::LazyLock::new(|| {
    let xyz = r#"{"type": "object", "properties": {"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}}, "required": ["x", "y", "z"]}"#;
    let xyzw = r#"{"type": "object", "properties": {"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}, "w": {"type": "number"}}, "required": ["x", "y", "z", "w"]}"#;
    format!(
        r#"{{"$schema": "https://json-schema.org/draft/2020-12/schema", "title": "foxglove.FrameTransforms", "type": "object", "properties": {{"timestamp_ns": {{"type": "integer", "description": "the joint-state frame's, CLOCK_MONOTONIC of the robot, ns"}}, "transforms": {{"type": "array", "items": {{"title": "foxglove.FrameTransform", "type": "object", "properties": {{"timestamp": {TIME_SCHEMA}, "parent_frame_id": {{"type": "string"}}, "child_frame_id": {{"type": "string"}}, "translation": {xyz}, "rotation": {xyzw}}}, "required": ["timestamp", "parent_frame_id", "child_frame_id", "translation", "rotation"]}}}}}}, "required": ["transforms"]}}"#
    )
});

/// A monotonic stamp as Foxglove's `Time` on the wall clock (`wall_offset_ns` from the robot's
/// monotonic one).
fn wall_time(t_ns: u64, wall_offset_ns: i128) -> serde_json::Value {
    let wall = (t_ns as i128 + wall_offset_ns).max(0) as u128;
    serde_json::json!({"sec": (wall / 1_000_000_000) as u64, "nsec": (wall % 1_000_000_000) as u64})
}

/// A camera's thumbnail (a JPEG) as Foxglove's `CompressedImage`, stamped at the frame's
/// capture.
pub fn thumbnail(
    camera: &str,
    capture_ns: u64,
    jpeg: &[u8],
    wall_offset_ns: i128,
) -> (u64, Vec<u8>) {
    let msg = serde_json::json!({
        "timestamp": wall_time(capture_ns, wall_offset_ns),
        "timestamp_ns": capture_ns,
        "frame_id": camera,
        "format": "jpeg",
        "data": base64::engine::general_purpose::STANDARD.encode(jpeg),
    });
    (capture_ns, to_json(&msg))
}

/// One frame of the body in its parent's, for [`transforms`].
#[derive(Debug, Clone, PartialEq)]
pub struct Transform {
    /// The parent frame's name.
    pub parent: String,
    /// This frame's name.
    pub child: String,
    /// The body's link.
    pub link: body::kinematics::Link,
}

/// The body's frames at `t_ns` as Foxglove's `FrameTransforms`.
pub fn transforms(t_ns: u64, frames: &[Transform], wall_offset_ns: i128) -> (u64, Vec<u8>) {
    let stamp = wall_time(t_ns, wall_offset_ns);
    let transforms: Vec<serde_json::Value> = frames
        .iter()
        .map(|f| {
            let ([x, y, z], [qw, qx, qy, qz]) = (f.link.translation, f.link.rotation);
            serde_json::json!({
                "timestamp": stamp, "parent_frame_id": f.parent, "child_frame_id": f.child,
                "translation": {"x": x, "y": y, "z": z},
                "rotation": {"x": qx, "y": qy, "z": qz, "w": qw},
            })
        })
        .collect();
    let msg = serde_json::json!({"timestamp_ns": t_ns, "transforms": transforms});
    (t_ns, to_json(&msg))
}

/// Bins of a revolution in a `LaserScan` (0.5°: the C1's spacing at 10 Hz is about 0.72°).
pub const SCAN_BINS: usize = 720;

/// A lidar revolution as Foxglove's `LaserScan`, its points put in their 0.5° bins (a bin
/// with no return reads 0, below any range the lidar measures), stamped on the wall clock
/// (`wall_offset_ns` from the robot's monotonic one); the monotonic stamp beside it.
pub fn laser_scan(scan: &telemetry::sensors::LidarScan, wall_offset_ns: i128) -> (u64, Vec<u8>) {
    let step = std::f64::consts::TAU / SCAN_BINS as f64;
    let mut ranges = vec![0.0f32; SCAN_BINS];
    let mut intensities = vec![0.0f32; SCAN_BINS];
    for p in scan.points() {
        let bin = (p.angle_rad as f64 / step).round() as usize % SCAN_BINS;
        if p.range_m.is_finite() && p.range_m > 0.0 {
            ranges[bin] = p.range_m;
            intensities[bin] = p.quality as f32;
        }
    }
    let msg = serde_json::json!({
        "timestamp": wall_time(scan.start_ns, wall_offset_ns),
        "timestamp_ns": scan.start_ns,
        "frame_id": "lidar",
        "pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0},
                 "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
        "start_angle": 0.0,
        "end_angle": step * (SCAN_BINS - 1) as f64,
        "ranges": ranges,
        "intensities": intensities,
    });
    (scan.start_ns, to_json(&msg))
}

const LAYOUT_PROPERTIES: &str = r#""joints": {"type": "array", "items": {"type": "object", "properties": {"name": {"type": "string"}, "bus": {"type": "string"}, "id": {"type": "integer"}, "model": {"type": "integer", "description": "Model_Number: 777 STS3215, 2825 STS3250, 2569 STS3095"}, "role": {"type": "string"}, "range_rad": {"type": "array", "items": {"type": "number"}}}}}"#;
const EVENT_PROPERTIES: &str = r#""kind": {"type": "string"}, "joint": {"type": ["string", "null"]}, "bus": {"type": ["string", "null"]}, "level": {"type": "integer"}, "value": {"type": "number"}"#;

/// The names the messages carry: the driver's layout (`j<k>`, `bus<k>` until it is heard).
#[derive(Debug, Clone, Default)]
pub struct Names {
    joints: Vec<String>,
    buses: Vec<String>,
}

impl Names {
    /// The names of `layout`.
    pub fn from_layout(layout: &JointLayout) -> Names {
        Names {
            joints: layout
                .joints()
                .iter()
                .map(|j| j.name().to_string())
                .collect(),
            buses: layout.bus_names().map(str::to_string).collect(),
        }
    }

    /// Joint `k`'s name.
    pub fn joint(&self, k: usize) -> String {
        self.joints
            .get(k)
            .cloned()
            .unwrap_or_else(|| format!("j{k}"))
    }

    /// Bus `k`'s name.
    pub fn bus(&self, k: usize) -> String {
        self.buses
            .get(k)
            .cloned()
            .unwrap_or_else(|| format!("bus{k}"))
    }
}

/// One joint of the layout, as a message.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct LayoutJoint {
    /// Its name.
    pub name: String,
    /// Its bus's name.
    pub bus: String,
    /// Its servo's id on the bus.
    pub id: u8,
    /// Its servo's `Model_Number`.
    pub model: u16,
    /// `joint`, `gripper` or `wheel`.
    pub role: String,
    /// Its calibrated range, rad.
    pub range_rad: [f32; 2],
}

/// The layout as a message, stamped `t_ns` (the layout frame carries no time).
pub fn layout(l: &JointLayout, t_ns: u64) -> (u64, Vec<u8>) {
    let names = Names::from_layout(l);
    let joints: Vec<LayoutJoint> = l
        .joints()
        .iter()
        .map(|j| LayoutJoint {
            name: j.name().to_string(),
            bus: names.bus(j.bus as usize),
            id: j.id,
            model: j.model,
            role: snake(&format!("{:?}", j.role())),
            range_rad: j.range_rad.map(finite),
        })
        .collect();
    let msg = serde_json::json!({ "timestamp_ns": t_ns, "joints": joints });
    (t_ns, to_json(&msg))
}

/// A bus's traffic of one cycle as a message.
#[derive(Serialize)]
struct WireMessage<'a> {
    timestamp_ns: u64,
    cycle: u64,
    bus: String,
    lost_bytes: u32,
    chunks: Vec<WireChunkMessage<'a>>,
}

#[derive(Serialize)]
struct WireChunkMessage<'a> {
    t_ns: u64,
    direction: &'a str,
    data: String,
}

/// `frame` as a message; stamped with its first chunk's time.
pub fn wire(frame: &WireFrame, names: &Names) -> (u64, Vec<u8>) {
    let chunks: Vec<WireChunkMessage> = frame
        .chunks()
        .map(|(d, t_ns, bytes)| WireChunkMessage {
            t_ns,
            direction: d.name(),
            data: base64::engine::general_purpose::STANDARD.encode(bytes),
        })
        .collect();
    let t = chunks.first().map_or(0, |c| c.t_ns);
    let msg = WireMessage {
        timestamp_ns: t,
        cycle: frame.cycle,
        bus: names.bus(frame.bus as usize),
        lost_bytes: frame.lost_bytes,
        chunks,
    };
    (t, to_json(&msg))
}

/// One chunk of a bus's traffic read back: its time, its direction, its bytes.
pub type WireChunk = (u64, Direction, Vec<u8>);

/// One wire message read back: a bus's traffic of one cycle.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WireRecord {
    /// The bus's name.
    pub bus: String,
    /// The driver's cycle.
    pub cycle: u64,
    /// Bytes the driver's tap could not keep this cycle (its chunks are incomplete).
    pub lost_bytes: u64,
    /// The chunks, in the order they went.
    pub chunks: Vec<WireChunk>,
}

/// Decodes a wire message; `None` if it is not one.
pub fn wire_chunks(data: &[u8]) -> Option<WireRecord> {
    let v: serde_json::Value = serde_json::from_slice(data).ok()?;
    let bus = v.get("bus")?.as_str()?.to_string();
    let lost_bytes = v.get("lost_bytes")?.as_u64()?;
    let cycle = v.get("cycle")?.as_u64()?;
    let chunks = v
        .get("chunks")?
        .as_array()?
        .iter()
        .map(|c| {
            let direction = Direction::from_name(c.get("direction")?.as_str()?)?;
            let bytes = base64::engine::general_purpose::STANDARD
                .decode(c.get("data")?.as_str()?)
                .ok()?;
            Some((c.get("t_ns")?.as_u64()?, direction, bytes))
        })
        .collect::<Option<Vec<_>>>()?;
    Some(WireRecord {
        bus,
        cycle,
        lost_bytes,
        chunks,
    })
}

#[derive(Serialize)]
struct JointStatesMessage {
    timestamp_ns: u64,
    seq: u64,
    safe_state: bool,
    name: Vec<String>,
    valid: Vec<bool>,
    position: Vec<f32>,
    velocity: Vec<f32>,
    load: Vec<f32>,
    current_a: Vec<f32>,
    voltage_v: Vec<f32>,
    temperature_c: Vec<f32>,
    goal: Vec<f32>,
    status: Vec<u8>,
    torque_enabled: Vec<bool>,
    flags: Vec<u8>,
}

/// A joint-state frame as a message (a missing reading's values are written as read: `valid`
/// says which to trust).
pub fn joint_states(state: &JointState, names: &Names) -> (u64, Vec<u8>) {
    let j = state.joints();
    let col = |f: fn(&telemetry::JointSample) -> f32| j.iter().map(f).map(finite).collect();
    let msg = JointStatesMessage {
        timestamp_ns: state.timestamp_ns,
        seq: state.seq,
        safe_state: state.flags & telemetry::frames::STATE_FLAG_SAFE_STATE != 0,
        name: (0..j.len()).map(|k| names.joint(k)).collect(),
        valid: j.iter().map(|s| s.is_valid()).collect(),
        position: col(|s| s.position_rad),
        velocity: col(|s| s.velocity_rad_s),
        load: col(|s| s.load),
        current_a: col(|s| s.current_a),
        voltage_v: col(|s| s.voltage_v),
        temperature_c: col(|s| s.temperature_c),
        goal: col(|s| s.goal_rad),
        status: j.iter().map(|s| s.status).collect(),
        torque_enabled: j.iter().map(|s| s.torque_enabled != 0).collect(),
        flags: j.iter().map(|s| s.flags).collect(),
    };
    (state.timestamp_ns, to_json(&msg))
}

/// JSON has no NaN: a non-finite value (never in a valid reading) is written as 0.
fn finite(x: f32) -> f32 {
    if x.is_finite() {
        x
    } else {
        0.0
    }
}

#[derive(Serialize)]
struct GoalsMessage {
    timestamp_ns: u64,
    seq: u64,
    name: Vec<String>,
    goal: Vec<f32>,
}

/// A goal frame as a message: the joints its mask names.
pub fn goals(frame: &GoalFrame, names: &Names) -> (u64, Vec<u8>) {
    let n = (frame.joint_count as usize).min(frame.position_rad.len());
    let named: Vec<usize> = (0..n.min(32))
        .filter(|k| frame.mask & (1 << k) != 0)
        .collect();
    let msg = GoalsMessage {
        timestamp_ns: frame.timestamp_ns,
        seq: frame.seq,
        name: named.iter().map(|&k| names.joint(k)).collect(),
        goal: named
            .iter()
            .map(|&k| finite(frame.position_rad[k]))
            .collect(),
    };
    (frame.timestamp_ns, to_json(&msg))
}

#[derive(Serialize)]
struct DirectivesMessage {
    timestamp_ns: u64,
    seq: u64,
    stop: bool,
    bus_enabled: Vec<bool>,
    torque_limit_permille: Vec<u16>,
}

/// A directive as a message.
pub fn directives(d: &Directives, buses: usize) -> (u64, Vec<u8>) {
    let n = (d.joint_count as usize).min(d.torque_limit_permille.len());
    let msg = DirectivesMessage {
        timestamp_ns: d.timestamp_ns,
        seq: d.seq,
        stop: d.flags & DIRECTIVE_FLAG_STOP != 0,
        bus_enabled: (0..buses.min(32))
            .map(|b| d.bus_enabled & (1 << b) != 0)
            .collect(),
        torque_limit_permille: d.torque_limit_permille[..n].to_vec(),
    };
    (d.timestamp_ns, to_json(&msg))
}

/// An event or a trigger, as a message.
#[derive(Debug, Clone, Serialize, serde::Deserialize, PartialEq)]
pub struct EventMessage {
    /// When, on the robot's monotonic clock.
    pub timestamp_ns: u64,
    /// What (`thermal_trip`, `lift_obstruction`, `saved`, …).
    pub kind: String,
    /// The joint it is about.
    pub joint: Option<String>,
    /// The bus it is about.
    pub bus: Option<String>,
    /// The event's level.
    pub level: u8,
    /// The event's value (°C, A, s, by kind).
    pub value: f32,
}

/// A supervisor event as a message.
pub fn event(e: &SupervisorEvent, names: &Names) -> EventMessage {
    EventMessage {
        timestamp_ns: e.timestamp_ns,
        kind: e
            .kind()
            .map_or_else(|| format!("unknown_{}", e.kind), event_name),
        joint: (e.joint != 0xFF).then(|| names.joint(e.joint as usize)),
        bus: (e.bus != 0xFF).then(|| names.bus(e.bus as usize)),
        level: e.level,
        value: finite(e.value),
    }
}

/// An event kind's name in snake case (`ThermalTrip` → `thermal_trip`).
pub fn event_name(kind: EventKind) -> String {
    snake(&format!("{kind:?}"))
}

/// `CamelCase` → `camel_case`.
pub(crate) fn snake(camel: &str) -> String {
    let mut out = String::new();
    for (i, c) in camel.chars().enumerate() {
        if c.is_uppercase() && i > 0 {
            out.push('_');
        }
        out.extend(c.to_lowercase());
    }
    out
}

/// Bus health as a message.
pub fn bus_health(h: &BusHealth, names: &Names) -> (u64, Vec<u8>) {
    let buses: Vec<serde_json::Value> = h
        .buses()
        .iter()
        .enumerate()
        .map(|(k, b)| {
            let mut v = serde_json::to_value(b).unwrap_or_default();
            if let Some(o) = v.as_object_mut() {
                o.insert("bus".into(), names.bus(k).into());
            }
            v
        })
        .collect();
    let msg = serde_json::json!({"timestamp_ns": h.timestamp_ns, "seq": h.seq, "buses": buses});
    (h.timestamp_ns, to_json(&msg))
}

/// The lift's state as a message.
pub fn lift_state(s: &LiftState) -> (u64, Vec<u8>) {
    let msg = serde_json::json!({
        "timestamp_ns": s.timestamp_ns, "seq": s.seq, "height_m": finite(s.height_m),
        "goal_m": finite(s.goal_m), "velocity_m_s": finite(s.velocity_m_s),
        "current_a": finite(s.current_a), "state": s.state, "held": s.held != 0,
        "obstructions": s.obstructions,
    });
    (s.timestamp_ns, to_json(&msg))
}

/// The base's state as a message.
pub fn base_state(s: &BaseState) -> (u64, Vec<u8>) {
    let f = |x: f64| if x.is_finite() { x } else { 0.0 };
    let msg = serde_json::json!({
        "timestamp_ns": s.timestamp_ns, "seq": s.seq, "x_m": f(s.x_m), "y_m": f(s.y_m),
        "theta_rad": f(s.theta_rad), "linear_m_s": finite(s.linear_m_s),
        "angular_rad_s": finite(s.angular_rad_s), "field_distance_m": finite(s.field_distance_m),
        "flags": s.flag_names().collect::<Vec<_>>(),
    });
    (s.timestamp_ns, to_json(&msg))
}

/// Serialises a message; our own types always serialise, so a failure is an empty object.
pub fn to_json<T: Serialize>(msg: &T) -> Vec<u8> {
    serde_json::to_vec(msg).unwrap_or_else(|_| b"{}".to_vec())
}

/// [`to_json`] as text.
pub(crate) fn to_json_string<T: Serialize>(msg: &T) -> String {
    String::from_utf8_lossy(&to_json(msg)).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_channel_has_a_topic_of_its_own_and_a_schema_that_parses() {
        let cameras = ["head".to_string(), "left_wrist".to_string()];
        let thumbnails = (0..MAX_CAMERAS as u8).map(Channel::Thumbnail);
        for c in Channel::ALL.into_iter().chain(thumbnails) {
            assert_eq!(Channel::from_id(c.id()), Some(c));
            if !matches!(c, Channel::Thumbnail(k) if k >= 2) {
                assert_eq!(
                    Channel::from_topic_in(&c.topic_in(&cameras), &cameras),
                    Some(c)
                );
            }
            let schema: serde_json::Value = serde_json::from_str(&c.schema()).unwrap();
            assert_eq!(schema["type"], "object", "{c:?}");
        }
        let ids: std::collections::BTreeSet<u8> = Channel::ALL
            .into_iter()
            .chain((0..MAX_CAMERAS as u8).map(Channel::Thumbnail))
            .map(Channel::id)
            .collect();
        assert_eq!(ids.len(), Channel::ALL.len() + MAX_CAMERAS, "ids collide");
        assert_eq!(Channel::from_id(THUMBNAIL_ID + MAX_CAMERAS as u8), None);
        assert_eq!(Channel::from_id(Channel::ALL.len() as u8), None);
        assert_eq!(
            Channel::Thumbnail(1).topic_in(&cameras),
            "/camera/left_wrist/thumbnail"
        );
        assert_eq!(
            Channel::from_topic_in("/camera/neck/thumbnail", &cameras),
            None
        );
        assert_eq!(Channel::from_topic("/camera/head/thumbnail"), None);
        // A box naming more cameras than a box can hold: those beyond are no channel.
        let many: Vec<String> = (0..MAX_CAMERAS + 2).map(|k| format!("c{k}")).collect();
        assert_eq!(
            Channel::from_topic_in("/camera/c7/thumbnail", &many),
            Some(Channel::Thumbnail(7))
        );
        assert_eq!(Channel::from_topic_in("/camera/c8/thumbnail", &many), None);
    }

    #[test]
    fn a_wire_frame_comes_back_byte_for_byte() {
        let mut f = WireFrame::default();
        f.record(Direction::Sent, 5, &[0xFF, 0xFF, 0xFE, 4, 0x82]);
        f.record(Direction::Received, 9, &[0xFF, 0xFF, 1, 2, 0, 0xFC]);
        f.bus = 1;
        f.cycle = 7;
        let (t, data) = wire(&f, &Names::default());
        assert_eq!(t, 5);
        let record = wire_chunks(&data).unwrap();
        assert_eq!((record.bus.as_str(), record.lost_bytes), ("bus1", 0));
        assert_eq!(record.cycle, 7);
        assert_eq!(
            record.chunks,
            vec![
                (5, Direction::Sent, vec![0xFF, 0xFF, 0xFE, 4, 0x82]),
                (9, Direction::Received, vec![0xFF, 0xFF, 1, 2, 0, 0xFC]),
            ]
        );
    }

    #[test]
    fn a_revolution_becomes_a_laser_scan_with_each_point_in_its_bin() {
        let mut scan = telemetry::sensors::LidarScan {
            start_ns: 1_500_000_000,
            point_count: 3,
            ..Default::default()
        };
        let step = std::f32::consts::TAU / SCAN_BINS as f32;
        for (k, (bin, range)) in [(0usize, 1.5f32), (180, 2.0), (719, 0.0)]
            .into_iter()
            .enumerate()
        {
            scan.points[k].angle_rad = bin as f32 * step + step * 0.3;
            scan.points[k].range_m = range;
            scan.points[k].quality = 40;
        }
        let (t, data) = laser_scan(&scan, 1_000_000_000);
        assert_eq!(t, 1_500_000_000);
        let v: serde_json::Value = serde_json::from_slice(&data).unwrap();
        assert_eq!(v["timestamp"]["sec"], 2);
        assert_eq!(v["timestamp"]["nsec"], 500_000_000);
        let ranges = v["ranges"].as_array().unwrap();
        assert_eq!(ranges.len(), SCAN_BINS);
        assert_eq!(ranges[0], 1.5);
        assert_eq!(ranges[180], 2.0);
        assert_eq!(ranges[719], 0.0, "no return: below any measured range");
        assert_eq!(v["intensities"][180], 40.0);
        assert_eq!(ranges.iter().filter(|r| r.as_f64() != Some(0.0)).count(), 2);
    }

    #[test]
    fn a_thumbnail_and_a_tree_carry_their_bytes_and_wall_time() {
        let (t, data) = thumbnail("head", 1_500_000_000, &[0xFF, 0xD8, 0x00], 1_000_000_000);
        assert_eq!(t, 1_500_000_000);
        let v: serde_json::Value = serde_json::from_slice(&data).unwrap();
        assert_eq!(
            (
                v["timestamp"]["sec"].as_u64(),
                v["timestamp"]["nsec"].as_u64()
            ),
            (Some(2), Some(500_000_000))
        );
        assert_eq!(v["frame_id"], "head");
        assert_eq!(v["data"], "/9gA", "base64 of the bytes");
        let link = body::kinematics::Link {
            translation: [0.1, 0.2, 0.3],
            rotation: [0.1, 0.2, 0.3, 0.4],
        };
        let frame = Transform {
            parent: "lift".into(),
            child: "left_arm".into(),
            link,
        };
        let (_, data) = transforms(7, &[frame], 0);
        let v: serde_json::Value = serde_json::from_slice(&data).unwrap();
        let t = &v["transforms"][0];
        assert_eq!(
            (&t["parent_frame_id"], &t["child_frame_id"]),
            (&"lift".into(), &"left_arm".into())
        );
        assert_eq!(t["translation"]["z"], 0.3);
        // Foxglove's quaternion is x, y, z, w.
        let r = &t["rotation"];
        let xyzw = ["x", "y", "z", "w"].map(|k| r[k].as_f64().unwrap());
        assert_eq!(xyzw, [0.2, 0.3, 0.4, 0.1]);
        assert_eq!(t["timestamp"]["nsec"], 7);
    }

    #[test]
    fn event_kinds_are_named_in_snake_case() {
        assert_eq!(event_name(EventKind::ThermalTrip), "thermal_trip");
        assert_eq!(
            event_name(EventKind::FirmwareProtection),
            "firmware_protection"
        );
    }
}
