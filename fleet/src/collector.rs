//! The fleet side: what `nori fleet` knows about every robot, built from the messages robots
//! publish under `nori/<id>/...`, and rendered as a JSON snapshot (the dashboard) and as
//! Prometheus text (`/metrics`). Pure: bytes and the collector's wall time in, views out; the
//! zenoh subscriptions and the HTTP server live in the `nori` binary.

use crate::journal_seen::{FleetJournals, Taken};
use fleet_agent::keys::robot_of;
use fleet_agent::schema::{
    decode, DecodeError, EventMsg, EventRecord, LayoutMsg, PreviewMsg, ScanMsg, StateMsg, StatusMsg,
};
use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;
use serde_json::{json, Value};
use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::AtomicU64;
use telemetry::frames::EventKind;
use thiserror::Error;

/// Events kept per robot for the dashboard.
const EVENTS_KEPT: usize = 50;

/// Cameras whose thumbnail is kept per robot (the A3 has four): a robot naming more cannot
/// grow the collector without bound.
const PREVIEW_CAMERAS: usize = 8;

/// The events that latch a bus off until an operator re-enables it (a trip): the supervisor's
/// software tier, a firmware protection, the driver's last-resort tier. Exported at 0 for every
/// robot from its first message, so that a rule's `increase()` counts a robot's first trip too
/// (a series that first appears at 1 shows no increase).
const TRIP_KINDS: [EventKind; 3] = [
    EventKind::ThermalTrip,
    EventKind::FirmwareProtection,
    EventKind::DriverTrip,
];

/// The largest thumbnail kept, bytes (a 160×90 one is ~3 KB; this allows 640 px at quality 100).
pub const MAX_PREVIEW_BYTES: usize = 256 * 1024;

/// A message the collector could not use. Counted by kind, never fatal: one robot speaking
/// another schema version must not blind the dashboard to the rest of the fleet.
#[derive(Debug, Error, PartialEq)]
#[allow(missing_docs, reason = "each field is shown in its variant's message")]
pub enum IngestError {
    /// The key is not `nori/<robot-id>/...`.
    #[error("key {0:?} names no robot")]
    Key(String),
    /// The payload does not decode.
    #[error("{key}: {error}")]
    Decode {
        /// The key it came on.
        key: String,
        error: DecodeError,
    },
    /// The payload decodes but cannot be what it claims (a thumbnail that is no JPEG, a scan
    /// whose columns differ in length).
    #[error("{key}: refused: {reason}")]
    Refused {
        /// The key it came on.
        key: String,
        reason: String,
    },
}

/// One plotted sample of a robot's joints.
#[derive(Debug, Clone)]
struct Sample {
    wall_ms: u64,
    temperature_c: Vec<f32>,
    current_a: Vec<f32>,
}

/// Everything known about one robot.
#[derive(Debug, Default)]
struct Robot {
    alive: bool,
    /// Its liveliness token went away: what it last reported is history, not the present.
    offline: bool,
    last_seen_ms: u64,
    layout: Option<LayoutMsg>,
    last_state: Option<StateMsg>,
    history: VecDeque<Sample>,
    events: VecDeque<EventRecord>,
    event_counts: BTreeMap<String, u64>,
    states_received: u64,
    status: Option<StatusMsg>,
    /// Each camera's newest thumbnail and when it arrived (collector's wall time).
    previews: BTreeMap<String, (PreviewMsg, u64)>,
    /// The lidar's newest revolution and when it arrived.
    scan: Option<(ScanMsg, u64)>,
}

/// The fleet as the collector sees it.
#[derive(Debug)]
pub struct Collector {
    robots: BTreeMap<String, Robot>,
    history_len: usize,
    history_every_ms: u64,
    undecodable: BTreeMap<&'static str, u64>,
    refused: BTreeMap<&'static str, u64>,
    journals: FleetJournals,
    /// Events that came again (sent again by a robot not yet acknowledged) and were not counted.
    event_copies: u64,
}

impl Collector {
    /// Keeps `history_len` plot samples per robot, one every `history_every_ms`.
    pub fn new(history_len: usize, history_every_ms: u64) -> Self {
        Collector {
            robots: BTreeMap::new(),
            history_len,
            history_every_ms,
            undecodable: BTreeMap::new(),
            refused: BTreeMap::new(),
            journals: FleetJournals::default(),
            event_copies: 0,
        }
    }

    fn robot(&mut self, key: &str, now_ms: u64) -> Result<&mut Robot, IngestError> {
        let id = robot_of(key).ok_or_else(|| IngestError::Key(key.into()))?;
        // A known robot without a new String per message (the ingest path's one allocation
        // besides the decoded message).
        if !self.robots.contains_key(id) {
            self.robots.insert(id.to_string(), Robot::default());
        }
        let robot = self
            .robots
            .get_mut(id)
            .ok_or_else(|| IngestError::Key(key.into()))?;
        robot.last_seen_ms = now_ms;
        Ok(robot)
    }

    fn decoded<T: for<'de> serde::Deserialize<'de>>(
        &mut self,
        kind: &'static str,
        key: &str,
        payload: &[u8],
    ) -> Result<T, IngestError> {
        decode(payload).map_err(|error| {
            *self.undecodable.entry(kind).or_default() += 1;
            IngestError::Decode {
                key: key.into(),
                error,
            }
        })
    }

    /// A `nori/<id>/state` message.
    pub fn state(&mut self, key: &str, payload: &[u8], now_ms: u64) -> Result<(), IngestError> {
        let msg = decode_state(key, payload);
        self.decoded_state(key, msg, now_ms)
    }

    /// A `nori/<id>/state` message decoded by [`decode_state`] (outside any lock on the
    /// collector: decoding is most of the work).
    pub fn decoded_state(
        &mut self,
        key: &str,
        msg: Result<StateMsg, IngestError>,
        now_ms: u64,
    ) -> Result<(), IngestError> {
        let msg = msg.inspect_err(|e| {
            if matches!(e, IngestError::Decode { .. }) {
                *self.undecodable.entry("state").or_default() += 1;
            }
        })?;
        let (history_len, every) = (self.history_len, self.history_every_ms);
        let robot = self.robot(key, now_ms)?;
        robot.states_received += 1;
        let due = robot
            .history
            .back()
            .is_none_or(|s| now_ms >= s.wall_ms + every);
        if due && history_len > 0 {
            if robot.history.len() == history_len {
                robot.history.pop_front();
            }
            robot.history.push_back(Sample {
                wall_ms: now_ms,
                temperature_c: msg.joints.iter().map(|j| j.temperature_c).collect(),
                current_a: msg.joints.iter().map(|j| j.current_a).collect(),
            });
        }
        robot.last_state = Some(msg);
        Ok(())
    }

    /// A `nori/<id>/layout` message.
    pub fn layout(&mut self, key: &str, payload: &[u8], now_ms: u64) -> Result<(), IngestError> {
        let msg: LayoutMsg = self.decoded("layout", key, payload)?;
        self.robot(key, now_ms)?.layout = Some(msg);
        Ok(())
    }

    /// A `nori/<id>/events` message: kept and counted once, however often the robot sends it
    /// (it does until the fleet's store acknowledges it).
    pub fn event(&mut self, key: &str, payload: &[u8], now_ms: u64) -> Result<(), IngestError> {
        let msg: EventMsg = self.decoded("events", key, payload)?;
        let id = robot_of(key).ok_or_else(|| IngestError::Key(key.into()))?;
        if self
            .journals
            .of(id, msg.journal)
            .take(msg.seq, msg.held_from)
            == Taken::Copy
        {
            self.event_copies += 1;
            return Ok(());
        }
        let robot = self.robot(key, now_ms)?;
        *robot
            .event_counts
            .entry(msg.event.kind.clone())
            .or_default() += 1;
        if robot.events.len() == EVENTS_KEPT {
            robot.events.pop_front();
        }
        robot.events.push_back(msg.event);
        Ok(())
    }

    /// The liveliness token `nori/<id>/alive` appeared (`true`) or went away.
    pub fn alive(&mut self, key: &str, alive: bool, now_ms: u64) -> Result<(), IngestError> {
        let r = self.robot(key, now_ms)?;
        r.alive = alive;
        r.offline = !alive;
        Ok(())
    }

    /// A reply of `nori/<id>/status` (the agent's [`StatusMsg`]).
    pub fn status(&mut self, key: &str, payload: &[u8], now_ms: u64) -> Result<(), IngestError> {
        let msg: StatusMsg = self.decoded("status", key, payload)?;
        self.robot(key, now_ms)?.status = Some(msg);
        Ok(())
    }

    /// A `nori/<id>/preview` message: kept as the camera's newest thumbnail if it is a
    /// whole JPEG of a sane size from a camera with a valid name.
    pub fn preview(&mut self, key: &str, payload: &[u8], now_ms: u64) -> Result<(), IngestError> {
        let msg: PreviewMsg = self.decoded("preview", key, payload)?;
        let d = &msg.data;
        let problem = if !telemetry::sensors::valid_camera_name(&msg.camera) {
            Some(format!("{:?} cannot name a camera", msg.camera))
        } else if msg.encoding != "jpeg" {
            Some(format!("encoding {:?}, not jpeg", msg.encoding))
        } else if d.len() > MAX_PREVIEW_BYTES {
            Some(format!("{} bytes, over {MAX_PREVIEW_BYTES}", d.len()))
        } else if !(d.starts_with(&[0xFF, 0xD8]) && d.ends_with(&[0xFF, 0xD9])) {
            Some("not a whole JPEG (no start or end of image marker)".into())
        } else if !(1..=4096).contains(&msg.width) || !(1..=4096).contains(&msg.height) {
            Some(format!("{}×{} pixels", msg.width, msg.height))
        } else {
            None
        };
        if let Some(reason) = problem {
            return Err(self.refuse("preview", key, reason));
        }
        let robot = self
            .robots
            .get(robot_of(key).unwrap_or_default())
            .map(|r| (r.previews.len(), r.previews.contains_key(&msg.camera)));
        if let Some((n, known)) = robot {
            if !known && n >= PREVIEW_CAMERAS {
                let reason = format!("a {}th camera ({})", n + 1, msg.camera);
                return Err(self.refuse("preview", key, reason));
            }
        }
        let robot = self.robot(key, now_ms)?;
        robot.previews.insert(msg.camera.clone(), (msg, now_ms));
        Ok(())
    }

    /// A `nori/<id>/scan` message: kept as the lidar's newest revolution if its columns agree
    /// and every value is a bearing and a range.
    pub fn scan(&mut self, key: &str, payload: &[u8], now_ms: u64) -> Result<(), IngestError> {
        let msg: ScanMsg = self.decoded("scan", key, payload)?;
        let n = msg.angle_rad.len();
        let problem = if msg.range_m.len() != n || msg.quality.len() != n {
            Some(format!(
                "{n} bearings, {} ranges, {} qualities",
                msg.range_m.len(),
                msg.quality.len()
            ))
        } else if n > telemetry::sensors::MAX_SCAN_POINTS {
            Some(format!(
                "{n} points, over {}",
                telemetry::sensors::MAX_SCAN_POINTS
            ))
        } else if msg.angle_rad.iter().any(|a| !a.is_finite())
            || msg.range_m.iter().any(|r| !(r.is_finite() && *r >= 0.0))
        {
            Some("a bearing or range that is not a finite number (or a negative range)".into())
        } else {
            None
        };
        if let Some(reason) = problem {
            return Err(self.refuse("scan", key, reason));
        }
        self.robot(key, now_ms)?.scan = Some((msg, now_ms));
        Ok(())
    }

    fn refuse(&mut self, kind: &'static str, key: &str, reason: String) -> IngestError {
        *self.refused.entry(kind).or_default() += 1;
        IngestError::Refused {
            key: key.into(),
            reason,
        }
    }

    /// The newest thumbnail of `robot`'s `camera` (JPEG bytes).
    pub fn preview_jpeg(&self, robot: &str, camera: &str) -> Option<&[u8]> {
        let (msg, _) = self.robots.get(robot)?.previews.get(camera)?;
        Some(&msg.data)
    }

    /// The newest lidar revolution of `robot` as JSON: its points' bearings and ranges.
    pub fn scan_json(&self, robot: &str, now_ms: u64) -> Option<Value> {
        let (msg, at) = self.robots.get(robot)?.scan.as_ref()?;
        Some(json!({
            "seq": msg.seq,
            "age_ms": now_ms.saturating_sub(*at),
            "rotation_hz": rotation_hz(msg),
            "angle_rad": msg.angle_rad,
            "range_m": msg.range_m,
        }))
    }

    /// State messages received from `robot` so far.
    pub fn states_received(&self, robot: &str) -> u64 {
        self.robots.get(robot).map_or(0, |r| r.states_received)
    }

    /// Everything the dashboard shows, as JSON.
    pub fn snapshot(&self, now_ms: u64) -> Value {
        let robots: Vec<Value> = self
            .robots
            .iter()
            .map(|(id, r)| {
                let names = joint_names(r);
                let joints: Vec<Value> = r.last_state.as_ref().map_or(Vec::new(), |s| {
                    s.joints
                        .iter()
                        .enumerate()
                        .map(|(i, j)| {
                            json!({
                                "name": names.get(i),
                                "position": finite(j.position),
                                "temperature_c": finite(j.temperature_c),
                                "current_a": finite(j.current_a),
                                "valid": j.valid,
                                "torque": j.torque,
                            })
                        })
                        .collect()
                });
                let counters = r.status.as_ref().map(|s| &s.counters);
                json!({
                    "id": id,
                    "alive": r.alive,
                    "seen_ms_ago": now_ms.saturating_sub(r.last_seen_ms),
                    "safe_state": r.last_state.as_ref().map(|s| s.safe_state),
                    "deadline_misses": r.last_state.as_ref().map(|s| s.deadline_misses),
                    "states_received": r.states_received,
                    "joints": joints,
                    "lift": r.last_state.as_ref().and_then(|s| s.lift).map(|l| json!({
                        "height_m": finite(l.height_m), "goal_m": finite(l.goal_m),
                        "state": telemetry::motion::lift_state_name(l.state),
                        "held": l.held, "duty_wait_s": l.duty_wait_s,
                    })),
                    "base": r.last_state.as_ref().and_then(|s| s.base).map(|b| json!({
                        "x_m": b.x_m, "y_m": b.y_m, "heading_rad": b.heading_rad, "linear_m_s": b.linear_m_s,
                        "angular_rad_s": b.angular_rad_s, "field_distance_m": (b.field_distance_m >= 0.0).then_some(b.field_distance_m),
                        "flags": telemetry::motion::base_flag_names(b.flags).collect::<Vec<_>>(),
                    })),
                    "history": {
                        "ms_ago": r.history.iter().map(|s| now_ms.saturating_sub(s.wall_ms)).collect::<Vec<_>>(),
                        "temperature_c": r.history.iter().map(|s| s.temperature_c.iter().map(|&v| finite(v)).collect::<Vec<_>>()).collect::<Vec<_>>(),
                        "current_a": r.history.iter().map(|s| s.current_a.iter().map(|&v| finite(v)).collect::<Vec<_>>()).collect::<Vec<_>>(),
                    },
                    "events": r.events.iter().rev().map(|e| json!({
                        "kind": e.kind, "joint": e.joint, "bus": e.bus, "level": e.level,
                        "value": finite(e.value), "wall_ms": e.wall_ms,
                    })).collect::<Vec<_>>(),
                    "event_counts": r.event_counts,
                    "actions_accepted": counters.map(|c| c.actions_accepted),
                    "actions_rejected": counters.map(|c| &c.actions_rejected),
                    "last_rejection": r.status.as_ref().map(|s| s.last_rejection.clone()),
                    "running": r.status.as_ref().map(running),
                    "calibration": r.status.as_ref().map(calibration),
                    "buses": r.status.as_ref().map(|s| s.buses.iter().map(|b| json!({
                        "bus": b.name, "connected": b.connected, "enabled": b.enabled, "counters": b.counters,
                    })).collect::<Vec<_>>()),
                    "cameras": cameras_json(r, now_ms),
                    "lidar": lidar_json(r, now_ms),
                })
            })
            .collect();
        json!({ "robots": robots, "undecodable": self.undecodable, "refused": self.refused })
    }

    /// The Prometheus text exposition of the fleet.
    pub fn metrics(&self) -> String {
        let robot = RobotMetrics::default();
        let joints = JointMetrics::default();
        let buses = BusMetrics::default();
        let cameras = CameraMetrics::default();
        let lidar = LidarMetrics::default();
        for (id, r) in &self.robots {
            robot.observe(id, r);
            joints.observe(id, r);
            buses.observe(id, r);
            cameras.observe(id, r);
            lidar.observe(id, r);
        }
        // The families are written in the order they are registered.
        let mut registry = Registry::with_prefix("nori");
        robot.register(&mut registry);
        joints.register(&mut registry);
        buses.register(&mut registry);
        cameras.register(&mut registry);
        lidar.register(&mut registry);
        self.register_collector_metrics(&mut registry);
        let mut text = String::new();
        // Writing into a String cannot fail.
        let _ = encode(&mut text, &registry);
        text
    }

    /// The collector's own counts: messages undecodable, copies of events, messages refused.
    fn register_collector_metrics(&self, registry: &mut Registry) {
        let undecodable = Counters::default();
        for (kind, n) in &self.undecodable {
            undecodable
                .get_or_create(&labels(&[("key", kind)]))
                .inc_by(*n);
        }
        let refused = Counters::default();
        for (kind, n) in &self.refused {
            refused.get_or_create(&labels(&[("key", kind)])).inc_by(*n);
        }
        registry.register(
            "fleet_undecodable_messages",
            "messages the collector could not decode, by key",
            undecodable,
        );
        let copies = Counter::<u64, AtomicU64>::default();
        copies.inc_by(self.event_copies);
        registry.register(
            "fleet_event_copies",
            "events that came again (resent by a robot awaiting the store's acknowledgement) and were counted once",
            copies,
        );
        registry.register(
            "fleet_refused_messages",
            "messages that decoded but were refused (a thumbnail that is no JPEG, a broken scan), by key",
            refused,
        );
    }
}

/// A metric's labels, as name and value.
type Labels = Vec<(String, String)>;
/// A family of gauges, one per set of labels.
type Gauges = Family<Labels, Gauge<f64, AtomicU64>>;
/// A family of counters, one per set of labels.
type Counters = Family<Labels, Counter>;

/// Labels from borrowed pairs.
fn labels(pairs: &[(&str, &str)]) -> Labels {
    pairs
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect()
}

/// A flag as a gauge's value: 1 when set.
fn flag(set: bool) -> f64 {
    f64::from(u8::from(set))
}

/// The robot's last state, unless the robot is offline. An offline robot's last readings are
/// not exported as live: a dashboard or an alert would read a motor that may have cooled, or
/// cooked, since.
fn live_state(r: &Robot) -> Option<&StateMsg> {
    r.last_state.as_ref().filter(|_| !r.offline)
}

/// Each robot's liveliness, safe state, messages, events and the gate's verdicts.
#[derive(Default)]
struct RobotMetrics {
    online: Gauges,
    safe: Gauges,
    misses: Counters,
    states: Counters,
    events: Counters,
    accepted: Counters,
    rejected: Counters,
    version: Gauges,
}

impl RobotMetrics {
    fn observe(&self, id: &str, r: &Robot) {
        let robot = labels(&[("robot", id)]);
        self.online.get_or_create(&robot).set(flag(r.alive));
        self.states.get_or_create(&robot).inc_by(r.states_received);
        for kind in TRIP_KINDS {
            self.events
                .get_or_create(&labels(&[("robot", id), ("kind", &format!("{kind:?}"))]))
                .inc_by(0);
        }
        for (kind, n) in &r.event_counts {
            self.events
                .get_or_create(&labels(&[("robot", id), ("kind", kind)]))
                .inc_by(*n);
        }
        if let Some(s) = live_state(r) {
            self.safe.get_or_create(&robot).set(flag(s.safe_state));
            self.misses.get_or_create(&robot).inc_by(s.deadline_misses);
        }
        if let Some(s) = &r.status {
            let installed = s.installed_version.as_deref().unwrap_or("");
            self.version
                .get_or_create(&labels(&[
                    ("robot", id),
                    ("installed", installed),
                    ("agent", &s.agent_version),
                ]))
                .set(1.0);
        }
        if let Some(c) = r.status.as_ref().map(|s| &s.counters) {
            self.accepted
                .get_or_create(&robot)
                .inc_by(c.actions_accepted);
            for (reason, n) in &c.actions_rejected {
                self.rejected
                    .get_or_create(&labels(&[("robot", id), ("reason", reason)]))
                    .inc_by(*n);
            }
        }
    }

    fn register(self, registry: &mut Registry) {
        registry.register(
            "robot_online",
            "1 while the robot's liveliness token is present",
            self.online,
        );
        registry.register(
            "robot_safe_state",
            "1 while the driver holds its safe state",
            self.safe,
        );
        registry.register(
            "robot_deadline_misses",
            "control cycles that missed their deadline (driver's count)",
            self.misses,
        );
        registry.register(
            "robot_state_messages",
            "telemetry messages received from the robot",
            self.states,
        );
        registry.register(
            "robot_events",
            "journaled events by kind (supervisor and agent), each counted once; the trips (ThermalTrip, FirmwareProtection, DriverTrip) from 0",
            self.events,
        );
        registry.register(
            "robot_actions_accepted",
            "action chunks the robot's gate accepted",
            self.accepted,
        );
        registry.register(
            "robot_actions_rejected",
            "action chunks the robot's gate rejected, by reason",
            self.rejected,
        );
        registry.register(
            "robot_version",
            "1, labelled with the nori-robot package version the robot runs (empty: a build from source) and its agent's crate version (from the agent's status)",
            self.version,
        );
    }
}

/// What a robot runs, as its status says: the package's version, or a build from source.
fn running(s: &StatusMsg) -> String {
    match &s.installed_version {
        Some(v) => format!("nori-robot {v}"),
        None => format!("built from source (agent {})", s.agent_version),
    }
}

/// The calibration a robot runs, as its status says: how and when, and for which robot when
/// the file was made for another.
fn calibration(s: &StatusMsg) -> String {
    let Some(c) = &s.calibration else {
        return "no calibration reported".into();
    };
    if c.method == fleet_agent::installed::UNSTAMPED {
        return format!("calibration written by hand ({} joints)", c.joints);
    }
    if c.method == fleet_agent::installed::EMBEDDED {
        return "the simulated A3's calibration (embedded): no robot's own".into();
    }
    let mut said = format!("calibrated {} {} ({} joints)", c.method, c.at, c.joints);
    if c.robot != s.robot_id {
        said += &format!(": robot {}'s calibration", c.robot);
    }
    said
}

/// Each live robot's servos: temperature, current, whether they answered.
#[derive(Default)]
struct JointMetrics {
    temperature: Gauges,
    current: Gauges,
    valid: Gauges,
}

impl JointMetrics {
    fn observe(&self, id: &str, r: &Robot) {
        let Some(s) = live_state(r) else {
            return;
        };
        let names = joint_names(r);
        for (i, j) in s.joints.iter().enumerate() {
            let fallback = format!("joint{i}");
            let name = names.get(i).map_or(fallback.as_str(), |n| n.as_str());
            let joint = labels(&[("robot", id), ("joint", name)]);
            self.valid.get_or_create(&joint).set(flag(j.valid));
            // A servo missing this cycle has no temperature or current: no sample
            // rather than a made-up one.
            if j.valid && j.temperature_c.is_finite() {
                self.temperature
                    .get_or_create(&joint)
                    .set(f64::from(j.temperature_c));
            }
            if j.valid && j.current_a.is_finite() {
                self.current
                    .get_or_create(&joint)
                    .set(f64::from(j.current_a));
            }
        }
    }

    fn register(self, registry: &mut Registry) {
        registry.register(
            "joint_temperature_celsius",
            "servo temperature register",
            self.temperature,
        );
        registry.register("joint_current_amperes", "servo current", self.current);
        registry.register(
            "joint_valid",
            "1 when the servo answered in the last telemetry frame",
            self.valid,
        );
    }
}

/// Each robot's buses, from its agent's status: connected, cycles, errors by kind.
#[derive(Default)]
struct BusMetrics {
    connected: Gauges,
    cycles: Counters,
    errors: Counters,
}

impl BusMetrics {
    fn observe(&self, id: &str, r: &Robot) {
        for b in r.status.iter().flat_map(|s| &s.buses) {
            let bus = labels(&[("robot", id), ("bus", &b.name)]);
            self.connected.get_or_create(&bus).set(flag(b.connected));
            self.cycles.get_or_create(&bus).inc_by(b.counters.cycles);
            for (kind, n) in b.counters.errors() {
                self.errors
                    .get_or_create(&labels(&[("robot", id), ("bus", &b.name), ("kind", kind)]))
                    .inc_by(n);
            }
        }
    }

    fn register(self, registry: &mut Registry) {
        registry.register(
            "bus_connected",
            "1 while the robot's bus device is open (driver's view, from the agent's status)",
            self.connected,
        );
        registry.register(
            "bus_cycles",
            "feedback transactions on the bus",
            self.cycles,
        );
        registry.register(
            "bus_errors",
            "the driver's error counts on the bus, by kind (see telemetry::frames::BusCounters)",
            self.errors,
        );
    }
}

/// Each robot's cameras, from its agent's status: frames, frames lost by kind, age.
#[derive(Default)]
struct CameraMetrics {
    frames: Counters,
    lost: Counters,
    age: Gauges,
}

impl CameraMetrics {
    fn observe(&self, id: &str, r: &Robot) {
        for c in r.status.iter().flat_map(|s| &s.cameras) {
            let camera = labels(&[("robot", id), ("camera", &c.name)]);
            self.frames.get_or_create(&camera).inc_by(c.frames);
            for (kind, n) in [
                ("dropped", c.dropped),
                ("corrupt", c.corrupt),
                ("late", c.late),
            ] {
                self.lost
                    .get_or_create(&labels(&[
                        ("robot", id),
                        ("camera", &c.name),
                        ("kind", kind),
                    ]))
                    .inc_by(n);
            }
            if let Some(ms) = c.age_ms {
                self.age.get_or_create(&camera).set(ms * 1e-3);
            }
        }
    }

    fn register(self, registry: &mut Registry) {
        registry.register(
            "camera_frames",
            "frames the robot's camera process published (agent's status)",
            self.frames,
        );
        registry.register(
            "camera_frames_lost",
            "camera frames dropped, refused as corrupt, or published late (over two periods), by kind",
            self.lost,
        );
        registry.register(
            "camera_frame_age_seconds",
            "age of the camera's newest frame when the agent answered",
            self.age,
        );
    }
}

/// Each robot's lidar, from its agent's status: scans, faults by kind, age, rotation.
#[derive(Default)]
struct LidarMetrics {
    scans: Counters,
    faults: Counters,
    age: Gauges,
    rotation_hz: Gauges,
}

impl LidarMetrics {
    fn observe(&self, id: &str, r: &Robot) {
        let Some(l) = r.status.as_ref().and_then(|s| s.lidar.as_ref()) else {
            return;
        };
        let robot = labels(&[("robot", id)]);
        self.scans.get_or_create(&robot).inc_by(l.scans);
        for (kind, n) in [
            ("bad_points", l.bad_points),
            ("resyncs", l.resyncs),
            ("short_scans", l.short_scans),
        ] {
            self.faults
                .get_or_create(&labels(&[("robot", id), ("kind", kind)]))
                .inc_by(n);
        }
        if let Some(ms) = l.age_ms {
            self.age.get_or_create(&robot).set(ms * 1e-3);
        }
        if let Some(hz) = l.rotation_hz {
            self.rotation_hz.get_or_create(&robot).set(hz);
        }
    }

    fn register(self, registry: &mut Registry) {
        registry.register(
            "lidar_scans",
            "revolutions the robot's lidar process published",
            self.scans,
        );
        registry.register(
            "lidar_faults",
            "lidar measurements unconfirmed, stream resyncs, revolutions dropped as short, by kind",
            self.faults,
        );
        registry.register(
            "lidar_scan_age_seconds",
            "age of the lidar's newest revolution when the agent answered",
            self.age,
        );
        registry.register(
            "lidar_rotation_hertz",
            "revolutions per second",
            self.rotation_hz,
        );
    }
}

/// Decodes a `nori/<id>/state` message for [`Collector::decoded_state`].
pub fn decode_state(key: &str, payload: &[u8]) -> Result<StateMsg, IngestError> {
    decode(payload).map_err(|error| IngestError::Decode {
        key: key.into(),
        error,
    })
}

/// The robot's cameras for the dashboard: each camera of its status (health) in the status's
/// order, then any other that sent a thumbnail, with its newest thumbnail's figures.
fn cameras_json(r: &Robot, now_ms: u64) -> Vec<Value> {
    let status = r.status.iter().flat_map(|s| &s.cameras);
    let extra = r
        .previews
        .keys()
        .filter(|name| !status.clone().any(|c| &c.name == *name));
    let preview = |name: &str| {
        r.previews.get(name).map(|(p, at)| {
            json!({
                "seq": p.seq,
                "width": p.width,
                "height": p.height,
                "bytes": p.data.len(),
                "age_ms": now_ms.saturating_sub(*at),
            })
        })
    };
    status
        .clone()
        .map(|c| {
            json!({
                "name": c.name, "frames": c.frames, "dropped": c.dropped, "corrupt": c.corrupt,
                "late": c.late, "age_ms": c.age_ms, "preview": preview(&c.name),
            })
        })
        .chain(extra.map(|name| json!({ "name": name, "preview": preview(name) })))
        .collect()
}

/// The robot's lidar for the dashboard: its health from the status and its newest revolution's
/// figures (`None` when it has neither).
fn lidar_json(r: &Robot, now_ms: u64) -> Option<Value> {
    let health = r.status.as_ref().and_then(|s| s.lidar.as_ref());
    if health.is_none() && r.scan.is_none() {
        return None;
    }
    Some(json!({
        "health": health,
        "scan": r.scan.as_ref().map(|(m, at)| json!({
            "seq": m.seq,
            "points": m.range_m.len(),
            "returns": m.range_m.iter().filter(|&&r| r > 0.0).count(),
            "rotation_hz": rotation_hz(m),
            "age_ms": now_ms.saturating_sub(*at),
        })),
    }))
}

/// Revolutions per second a scan implies.
fn rotation_hz(m: &ScanMsg) -> Option<f64> {
    let span = m.end_ns.checked_sub(m.start_ns).filter(|&s| s > 0)?;
    Some(1e9 / span as f64)
}

fn joint_names(r: &Robot) -> Vec<String> {
    r.layout
        .as_ref()
        .map(|l| l.joints.iter().map(|j| j.name.clone()).collect())
        .unwrap_or_default()
}

/// JSON has no NaN: a missing reading is null.
fn finite(v: f32) -> Option<f32> {
    v.is_finite().then_some(v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use fleet_agent::schema::{
        encode, AgentCounters, BusStatus, CalibrationMsg, JointInfoMsg, JointMsg, StatusConfig,
        StatusHealth, SCHEMA_VERSION,
    };
    use fleet_agent::schema::{PreviewMsg, ScanMsg};

    fn state(seq: u64, temps: &[f32]) -> Vec<u8> {
        encode(&StateMsg {
            version: SCHEMA_VERSION,
            seq,
            timestamp_ns: seq * 1_000_000,
            wall_ms: 0,
            safe_state: false,
            deadline_misses: 3,
            joints: temps
                .iter()
                .map(|&t| JointMsg {
                    position: 0.1,
                    velocity: 0.0,
                    temperature_c: t,
                    current_a: 0.2,
                    goal: 0.1,
                    valid: t.is_finite(),
                    torque: true,
                    flags: 0,
                })
                .collect(),
            lift: None,
            base: None,
        })
    }

    fn layout() -> Vec<u8> {
        encode(&LayoutMsg {
            version: SCHEMA_VERSION,
            joints: ["elbow", "wrist"]
                .iter()
                .map(|n| JointInfoMsg {
                    name: n.to_string(),
                    min: -1.0,
                    max: 1.0,
                })
                .collect(),
        })
    }

    #[test]
    fn a_missing_servo_exports_no_temperature() {
        let mut c = Collector::new(10, 0);
        c.layout("nori/r1/layout", &layout(), 0).unwrap();
        c.state("nori/r1/state", &state(1, &[41.0, f32::NAN]), 0)
            .unwrap();
        let text = c.metrics();
        assert!(text.contains(r#"nori_joint_temperature_celsius{robot="r1",joint="elbow"} 41.0"#));
        assert!(!text.contains(r#"nori_joint_temperature_celsius{robot="r1",joint="wrist"}"#));
        assert!(text.contains(r#"nori_joint_valid{robot="r1",joint="wrist"} 0.0"#));
        assert!(text.contains(r#"nori_robot_deadline_misses_total{robot="r1"} 3"#));
        assert!(text.ends_with("# EOF\n"));
        let snap = c.snapshot(0);
        assert_eq!(snap["robots"][0]["joints"][1]["temperature_c"], Value::Null);
    }

    #[test]
    fn bad_messages_are_counted_and_change_nothing() {
        let mut c = Collector::new(10, 0);
        c.state("nori/r1/state", &state(1, &[30.0]), 0).unwrap();
        let mut other_version = state(2, &[99.0]);
        other_version[0] = SCHEMA_VERSION as u8 + 1;
        assert!(matches!(
            c.state("nori/r1/state", &other_version, 1),
            Err(IngestError::Decode { .. })
        ));
        assert!(c.state("nori/r1/state", &[0xff; 3], 1).is_err());
        assert_eq!(
            c.state("elsewhere/r1/state", &state(3, &[99.0]), 1),
            Err(IngestError::Key("elsewhere/r1/state".into()))
        );
        assert_eq!(c.states_received("r1"), 1);
        let text = c.metrics();
        assert!(text.contains(r#"nori_fleet_undecodable_messages_total{key="state"} 2"#));
        assert!(text.contains(r#"nori_joint_temperature_celsius{robot="r1",joint="joint0"} 30.0"#));
    }

    #[test]
    fn an_event_sent_again_is_counted_once_per_journal() {
        use fleet_agent::schema::{encode, EventMsg, EventRecord};
        let event = |journal, seq, kind: &str| {
            encode(&EventMsg {
                version: SCHEMA_VERSION,
                journal,
                seq,
                held_from: 1,
                event: EventRecord {
                    timestamp_ns: seq,
                    wall_ms: 0,
                    origin_seq: seq,
                    kind: kind.into(),
                    joint: "elbow".into(),
                    detail: String::new(),
                    bus: 0,
                    level: 0,
                    value: 0.0,
                },
            })
        };
        let mut c = Collector::new(10, 0);
        for bytes in [
            event(5, 1, "Stall"),
            event(5, 2, "ThermalTrip"),
            event(5, 1, "Stall"),
            event(5, 2, "ThermalTrip"),
            event(6, 1, "Stall"), // a new journal of the same robot: another event
        ] {
            c.event("nori/r1/events", &bytes, 0).unwrap();
        }
        let snap = c.snapshot(0);
        let counts = &snap["robots"][0]["event_counts"];
        assert_eq!(
            (counts["Stall"].as_u64(), counts["ThermalTrip"].as_u64()),
            (Some(2), Some(1))
        );
        assert_eq!(snap["robots"][0]["events"].as_array().unwrap().len(), 3);
        let text = c.metrics();
        assert!(text.contains("nori_fleet_event_copies_total 2"));
        assert!(text.contains(r#"nori_robot_events_total{robot="r1",kind="ThermalTrip"} 1"#));
    }

    #[test]
    fn every_robot_exports_its_trips_at_zero_before_the_first() {
        let mut c = Collector::new(10, 0);
        c.state("nori/r1/state", &state(1, &[30.0]), 0).unwrap();
        let text = c.metrics();
        for kind in ["ThermalTrip", "FirmwareProtection", "DriverTrip"] {
            let zero = format!(r#"nori_robot_events_total{{robot="r1",kind="{kind}"}} 0"#);
            assert!(text.contains(&zero), "no {zero} in:\n{text}");
        }
        assert!(
            !text.contains(r#"kind="Stall""#),
            "only the trips start at 0"
        );
    }

    #[test]
    fn history_is_bounded_and_thinned() {
        let mut c = Collector::new(3, 100);
        for k in 0..50u64 {
            c.state("nori/r1/state", &state(k, &[30.0 + k as f32]), k * 20)
                .unwrap();
        }
        let snap = c.snapshot(1000);
        let temps = snap["robots"][0]["history"]["temperature_c"]
            .as_array()
            .unwrap();
        assert_eq!(temps.len(), 3);
        // One sample every 100 ms (every fifth message): the last three kept.
        assert_eq!(temps[2][0], 30.0 + 45.0);
        assert_eq!(temps[1][0], 30.0 + 40.0);
        assert_eq!(c.states_received("r1"), 50);
    }

    /// A status reply with `counters` and `buses`.
    fn status(counters: AgentCounters, buses: Vec<BusStatus>) -> Vec<u8> {
        encode(&StatusMsg {
            version: SCHEMA_VERSION,
            robot_id: "r".into(),
            agent_version: "0".into(),
            installed_version: Some("0.1.0+57".into()),
            calibration: Some(CalibrationMsg {
                method: "by-hand".into(),
                at: "2026-11-29T05:00:00Z".into(),
                robot: "r".into(),
                joints: 16,
            }),
            config: StatusConfig {
                state_hz: 50.0,
                observation_hz: 50.0,
                max_age_ms: 300,
                horizon_ms: 1000,
                blend_new: 1.0,
                forward_hz: 100.0,
            },
            health: StatusHealth {
                joints: 1,
                state_age_ms: None,
                safe_state: None,
                deadline_misses: None,
                planned_steps: 0,
            },
            counters,
            last_rejection: "stale: 300 ms".into(),
            buses,
            cameras: vec![],
            lidar: None,
        })
    }

    #[test]
    fn rejections_come_from_the_robot_status() {
        let mut c = Collector::new(1, 0);
        let counters = AgentCounters {
            actions_accepted: 4,
            actions_rejected: [("stale".into(), 2), ("out_of_range".into(), 1)].into(),
            ..AgentCounters::default()
        };
        c.status("nori/r2/status", &status(counters, vec![]), 0)
            .unwrap();
        c.alive("nori/r2/alive", true, 0).unwrap();
        let text = c.metrics();
        assert!(text.contains(r#"nori_robot_actions_rejected_total{robot="r2",reason="stale"} 2"#));
        assert!(text.contains(r#"nori_robot_actions_accepted_total{robot="r2"} 4"#));
        assert!(text.contains(r#"nori_robot_online{robot="r2"} 1.0"#));
        c.alive("nori/r2/alive", false, 5).unwrap();
        assert!(c.metrics().contains(r#"nori_robot_online{robot="r2"} 0.0"#));
        let snap = c.snapshot(5);
        assert_eq!(snap["robots"][0]["actions_rejected"]["stale"], 2);
        assert_eq!(snap["robots"][0]["last_rejection"], "stale: 300 ms");
        // A status of another shape is refused and counted, not half-read.
        assert!(c
            .status("nori/r2/status", b"{\"counters\": {}}", 6)
            .is_err());
        assert_eq!(c.snapshot(6)["undecodable"]["status"], 1);
    }

    #[test]
    fn the_version_each_robot_runs_is_on_the_dashboard_and_in_the_metrics() {
        let mut c = Collector::new(1, 0);
        c.status(
            "nori/r2/status",
            &status(AgentCounters::default(), vec![]),
            0,
        )
        .unwrap();
        let mut source: StatusMsg =
            fleet_agent::schema::decode(&status(AgentCounters::default(), vec![])).unwrap();
        source.installed_version = None;
        c.status("nori/r3/status", &encode(&source), 0).unwrap();
        let text = c.metrics();
        assert!(
            text.contains(r#"nori_robot_version{robot="r2",installed="0.1.0+57",agent="0"} 1.0"#),
            "{text}"
        );
        assert!(text.contains(r#"nori_robot_version{robot="r3",installed="",agent="0"} 1.0"#));
        let snap = c.snapshot(0);
        assert_eq!(snap["robots"][0]["running"], "nori-robot 0.1.0+57");
        assert_eq!(snap["robots"][1]["running"], "built from source (agent 0)");
        c.layout("nori/r4/layout", &layout(), 0).unwrap();
        assert!(
            c.snapshot(0)["robots"][2]["running"].is_null(),
            "no status yet"
        );
    }

    #[test]
    fn the_calibration_each_robot_runs_is_on_the_dashboard_and_another_robot_s_is_named() {
        let mut c = Collector::new(1, 0);
        let mut source: StatusMsg =
            fleet_agent::schema::decode(&status(AgentCounters::default(), vec![])).unwrap();
        c.status("nori/r1/status", &encode(&source), 0).unwrap();
        source.calibration.as_mut().unwrap().robot = "a3-0007".into();
        c.status("nori/r2/status", &encode(&source), 0).unwrap();
        source.calibration.as_mut().unwrap().method = "unstamped".into();
        c.status("nori/r3/status", &encode(&source), 0).unwrap();
        source.calibration = None;
        c.status("nori/r4/status", &encode(&source), 0).unwrap();
        source.calibration = Some(fleet_agent::installed::embedded_calibration());
        c.status("nori/r5/status", &encode(&source), 0).unwrap();
        let snap = c.snapshot(0);
        let said: Vec<&str> = (0..5)
            .map(|i| snap["robots"][i]["calibration"].as_str().unwrap())
            .collect();
        assert_eq!(
            said,
            [
                "calibrated by-hand 2026-11-29T05:00:00Z (16 joints)",
                "calibrated by-hand 2026-11-29T05:00:00Z (16 joints): robot a3-0007's calibration",
                "calibration written by hand (16 joints)",
                "no calibration reported",
                "the simulated A3's calibration (embedded): no robot's own",
            ]
        );
    }

    #[test]
    fn an_offline_robot_exports_no_live_readings() {
        let mut c = Collector::new(10, 0);
        c.layout("nori/r1/layout", &layout(), 0).unwrap();
        c.alive("nori/r1/alive", true, 0).unwrap();
        c.state("nori/r1/state", &state(1, &[41.0, 42.0]), 0)
            .unwrap();
        let live = r#"nori_joint_temperature_celsius{robot="r1",joint="elbow"} 41.0"#;
        assert!(c.metrics().contains(live));
        c.alive("nori/r1/alive", false, 10).unwrap();
        let text = c.metrics();
        assert!(
            !text.contains("nori_joint_temperature_celsius{robot=\"r1\""),
            "{text}"
        );
        assert!(!text.contains("nori_joint_current_amperes{robot=\"r1\""));
        assert!(!text.contains("nori_robot_safe_state{robot=\"r1\""));
        assert!(text.contains(r#"nori_robot_online{robot="r1"} 0.0"#));
        c.alive("nori/r1/alive", true, 20).unwrap();
        assert!(
            c.metrics().contains(live),
            "back online: its readings again"
        );
    }

    #[test]
    fn bus_errors_come_from_the_robot_status() {
        let mut c = Collector::new(1, 0);
        let mut counters = telemetry::frames::BusCounters {
            cycles: 1000,
            checksum_errors: 7,
            implausible: 2,
            ..Default::default()
        };
        let bus = |name: &str, connected: bool, counters| BusStatus {
            name: name.into(),
            connected,
            enabled: true,
            counters,
        };
        let first = bus("left_arm", true, counters);
        counters.disconnects = 1;
        let second = bus("wheels", false, counters);
        c.status(
            "nori/r3/status",
            &status(AgentCounters::default(), vec![first, second]),
            0,
        )
        .unwrap();
        let text = c.metrics();
        for line in [
            r#"nori_bus_errors_total{robot="r3",bus="left_arm",kind="checksum_errors"} 7"#,
            r#"nori_bus_errors_total{robot="r3",bus="left_arm",kind="implausible"} 2"#,
            r#"nori_bus_errors_total{robot="r3",bus="wheels",kind="disconnects"} 1"#,
            r#"nori_bus_errors_total{robot="r3",bus="left_arm",kind="disconnects"} 0"#,
            r#"nori_bus_cycles_total{robot="r3",bus="wheels"} 1000"#,
            r#"nori_bus_connected{robot="r3",bus="left_arm"} 1.0"#,
            r#"nori_bus_connected{robot="r3",bus="wheels"} 0.0"#,
        ] {
            assert!(text.contains(line), "{line} not in\n{text}");
        }
        assert!(!text.contains(r#"kind="cycles""#), "cycles are not errors");
    }

    #[test]
    fn sensor_health_comes_from_the_robot_status() {
        use fleet_agent::schema::{CameraStatus, LidarStatus};
        let mut c = Collector::new(1, 0);
        let mut st: StatusMsg =
            fleet_agent::schema::decode(&status(AgentCounters::default(), vec![])).unwrap();
        st.cameras = vec![
            CameraStatus {
                name: "head".into(),
                frames: 900,
                dropped: 3,
                corrupt: 2,
                late: 7,
                age_ms: Some(40.0),
            },
            CameraStatus {
                name: "neck".into(),
                frames: 0,
                dropped: 0,
                corrupt: 0,
                late: 0,
                age_ms: None,
            },
        ];
        st.lidar = Some(LidarStatus {
            scans: 300,
            bad_points: 12,
            resyncs: 4,
            short_scans: 1,
            rotation_hz: Some(10.0),
            age_ms: Some(20.0),
        });
        c.status("nori/r4/status", &encode(&st), 0).unwrap();
        let text = c.metrics();
        for line in [
            r#"nori_camera_frames_total{robot="r4",camera="head"} 900"#,
            r#"nori_camera_frames_lost_total{robot="r4",camera="head",kind="dropped"} 3"#,
            r#"nori_camera_frames_lost_total{robot="r4",camera="head",kind="corrupt"} 2"#,
            r#"nori_camera_frames_lost_total{robot="r4",camera="head",kind="late"} 7"#,
            r#"nori_camera_frame_age_seconds{robot="r4",camera="head"} 0.04"#,
            r#"nori_camera_frames_total{robot="r4",camera="neck"} 0"#,
            r#"nori_lidar_scans_total{robot="r4"} 300"#,
            r#"nori_lidar_faults_total{robot="r4",kind="bad_points"} 12"#,
            r#"nori_lidar_faults_total{robot="r4",kind="short_scans"} 1"#,
            r#"nori_lidar_scan_age_seconds{robot="r4"} 0.02"#,
            r#"nori_lidar_rotation_hertz{robot="r4"} 10.0"#,
        ] {
            assert!(text.contains(line), "{line} not in\n{text}");
        }
        // A camera never seen has no age: no sample rather than a made-up one.
        assert!(!text.contains(r#"nori_camera_frame_age_seconds{robot="r4",camera="neck"}"#));
    }

    fn preview(camera: &str, seq: u64, data: Vec<u8>) -> PreviewMsg {
        PreviewMsg {
            version: SCHEMA_VERSION,
            camera: camera.into(),
            seq,
            capture_ns: 0,
            wall_ms: 0,
            width: 160,
            height: 90,
            source_width: 1280,
            source_height: 720,
            encoding: "jpeg".into(),
            data,
        }
    }

    fn jpeg() -> Vec<u8> {
        let mut out = Vec::new();
        jpeg_encoder::Encoder::new(&mut out, 70)
            .encode(&[50; 16 * 9 * 3], 16, 9, jpeg_encoder::ColorType::Rgb)
            .unwrap();
        out
    }

    #[test]
    fn thumbnails_are_kept_per_camera_and_bad_ones_refused_by_reason() {
        let mut c = Collector::new(1, 0);
        let key = "nori/r5/preview";
        c.preview(key, &encode(&preview("head", 3, jpeg())), 100)
            .unwrap();
        assert_eq!(c.preview_jpeg("r5", "head"), Some(jpeg().as_slice()));
        let snap = c.snapshot(350);
        let head = &snap["robots"][0]["cameras"][0];
        assert_eq!(head["name"], "head");
        assert_eq!(head["preview"]["seq"], 3);
        assert_eq!(head["preview"]["age_ms"], 250);

        let mut cut = jpeg();
        cut.truncate(cut.len() - 10);
        let mut png = preview("head", 4, jpeg());
        png.encoding = "png".into();
        let mut huge = jpeg();
        huge.splice(2..2, vec![0; MAX_PREVIEW_BYTES]);
        for (bad, why) in [
            (preview("head", 4, cut), "not a whole JPEG"),
            (preview("head", 4, b"hello".to_vec()), "not a whole JPEG"),
            (png, "encoding \"png\""),
            (preview("Head Cam", 4, jpeg()), "cannot name a camera"),
            (preview("head", 4, huge), "bytes, over"),
        ] {
            let e = c.preview(key, &encode(&bad), 400).unwrap_err();
            assert!(
                matches!(&e, IngestError::Refused { reason, .. } if reason.contains(why)),
                "{e}"
            );
        }
        assert_eq!(
            c.snapshot(400)["robots"][0]["cameras"][0]["preview"]["seq"],
            3,
            "kept"
        );
        // A robot cannot make the collector keep thumbnails of endless cameras.
        for k in 1..8 {
            c.preview(key, &encode(&preview(&format!("cam{k}"), 1, jpeg())), 500)
                .unwrap();
        }
        assert!(c
            .preview(key, &encode(&preview("cam9", 1, jpeg())), 500)
            .is_err());
        c.preview(key, &encode(&preview("head", 5, jpeg())), 500)
            .unwrap();
        assert!(c
            .metrics()
            .contains(r#"nori_fleet_refused_messages_total{key="preview"} 6"#));
        assert!(c.preview(key, &[9, 9, 9], 500).is_err());
        assert_eq!(c.snapshot(500)["undecodable"]["preview"], 1);
        assert_eq!(c.preview_jpeg("r5", "neck"), None);
        assert_eq!(c.preview_jpeg("r6", "head"), None);
    }

    #[test]
    fn a_scan_is_kept_whole_or_refused() {
        let mut c = Collector::new(1, 0);
        let scan = |ranges: Vec<f32>| ScanMsg {
            version: SCHEMA_VERSION,
            seq: 9,
            start_ns: 0,
            end_ns: 100_000_000,
            wall_ms: 0,
            angle_rad: (0..ranges.len()).map(|i| i as f32 * 0.1).collect(),
            quality: vec![30; ranges.len()],
            range_m: ranges,
        };
        c.scan("nori/r7/scan", &encode(&scan(vec![1.5, 0.0, 2.5])), 10)
            .unwrap();
        let j = c.scan_json("r7", 30).unwrap();
        assert_eq!(j["range_m"], json!([1.5, 0.0, 2.5]));
        assert_eq!(
            (j["seq"].clone(), j["age_ms"].clone()),
            (json!(9), json!(20))
        );
        assert_eq!(j["rotation_hz"], 10.0);
        let lidar = &c.snapshot(30)["robots"][0]["lidar"]["scan"];
        assert_eq!(
            (lidar["points"].clone(), lidar["returns"].clone()),
            (json!(3), json!(2))
        );

        let mut uneven = scan(vec![1.0, 2.0]);
        uneven.quality.pop();
        for bad in [
            uneven,
            scan(vec![1.0, f32::NAN]),
            scan(vec![-1.0]),
            scan(vec![1.0; telemetry::sensors::MAX_SCAN_POINTS + 1]),
        ] {
            assert!(matches!(
                c.scan("nori/r7/scan", &encode(&bad), 40),
                Err(IngestError::Refused { .. })
            ));
        }
        assert_eq!(
            c.scan_json("r7", 40).unwrap()["range_m"],
            json!([1.5, 0.0, 2.5])
        );
        assert!(c
            .metrics()
            .contains(r#"nori_fleet_refused_messages_total{key="scan"} 4"#));
        assert!(c.scan_json("r8", 40).is_none());
    }
}
