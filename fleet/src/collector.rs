//! The fleet side: what `nori fleet` knows about every robot, built from the messages robots
//! publish under `nori/<id>/...`, and rendered as a JSON snapshot (the dashboard) and as
//! Prometheus text (`/metrics`). Pure: bytes and the collector's wall time in, views out; the
//! zenoh subscriptions and the HTTP server live in the `nori` binary.

use fleet_agent::keys::robot_of;
use fleet_agent::schema::{decode, DecodeError, EventMsg, LayoutMsg, StateMsg, StatusMsg};
use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;
use serde_json::{json, Value};
use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::AtomicU64;
use thiserror::Error;

/// Events kept per robot for the dashboard.
const EVENTS_KEPT: usize = 50;

/// A message the collector could not use. Counted by kind, never fatal: one robot speaking
/// another schema version must not blind the dashboard to the rest of the fleet.
#[derive(Debug, Error, PartialEq)]
pub enum IngestError {
    /// The key is not `nori/<robot-id>/...`.
    #[error("key {0:?} names no robot")]
    Key(String),
    /// The payload does not decode.
    #[error("{key}: {error}")]
    Decode {
        /// The key it came on.
        key: String,
        /// Why.
        error: DecodeError,
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
    events: VecDeque<EventMsg>,
    event_counts: BTreeMap<String, u64>,
    states_received: u64,
    status: Option<StatusMsg>,
}

/// The fleet as the collector sees it.
#[derive(Debug)]
pub struct Collector {
    robots: BTreeMap<String, Robot>,
    history_len: usize,
    history_every_ms: u64,
    undecodable: BTreeMap<&'static str, u64>,
}

impl Collector {
    /// Keeps `history_len` plot samples per robot, one every `history_every_ms`.
    pub fn new(history_len: usize, history_every_ms: u64) -> Self {
        Collector {
            robots: BTreeMap::new(),
            history_len,
            history_every_ms,
            undecodable: BTreeMap::new(),
        }
    }

    fn robot(&mut self, key: &str, now_ms: u64) -> Result<&mut Robot, IngestError> {
        let id = robot_of(key).ok_or_else(|| IngestError::Key(key.into()))?;
        let robot = self.robots.entry(id.to_string()).or_default();
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
        let msg: StateMsg = self.decoded("state", key, payload)?;
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

    /// A `nori/<id>/events` message.
    pub fn event(&mut self, key: &str, payload: &[u8], now_ms: u64) -> Result<(), IngestError> {
        let msg: EventMsg = self.decoded("events", key, payload)?;
        let robot = self.robot(key, now_ms)?;
        *robot.event_counts.entry(msg.kind.clone()).or_default() += 1;
        if robot.events.len() == EVENTS_KEPT {
            robot.events.pop_front();
        }
        robot.events.push_back(msg);
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
                    "buses": r.status.as_ref().map(|s| s.buses.iter().map(|b| json!({
                        "bus": b.name, "connected": b.connected, "enabled": b.enabled, "counters": b.counters,
                    })).collect::<Vec<_>>()),
                })
            })
            .collect();
        json!({ "robots": robots, "undecodable": self.undecodable })
    }

    /// The Prometheus text exposition of the fleet.
    pub fn metrics(&self) -> String {
        type Labels = Vec<(String, String)>;
        let gauge = || Family::<Labels, Gauge<f64, AtomicU64>>::default();
        let counter = || Family::<Labels, Counter>::default();
        let (online, safe, temperature, current, valid) =
            (gauge(), gauge(), gauge(), gauge(), gauge());
        let (misses, states, events, accepted, rejected, undecodable) = (
            counter(),
            counter(),
            counter(),
            counter(),
            counter(),
            counter(),
        );
        let (bus_connected, bus_cycles, bus_errors) = (gauge(), counter(), counter());
        let (camera_frames, camera_lost, camera_age) = (counter(), counter(), gauge());
        let (lidar_scans, lidar_lost, lidar_age, lidar_hz) =
            (counter(), counter(), gauge(), gauge());
        let label = |pairs: &[(&str, &str)]| -> Labels {
            pairs
                .iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect()
        };
        for (id, r) in &self.robots {
            let robot = label(&[("robot", id)]);
            online
                .get_or_create(&robot)
                .set(f64::from(u8::from(r.alive)));
            states.get_or_create(&robot).inc_by(r.states_received);
            for (kind, n) in &r.event_counts {
                events
                    .get_or_create(&label(&[("robot", id), ("kind", kind)]))
                    .inc_by(*n);
            }
            // An offline robot's last readings are not exported as live: a dashboard or an
            // alert would read a motor that may have cooled, or cooked, since.
            if let Some(s) = r.last_state.as_ref().filter(|_| !r.offline) {
                safe.get_or_create(&robot)
                    .set(f64::from(u8::from(s.safe_state)));
                misses.get_or_create(&robot).inc_by(s.deadline_misses);
                let names = joint_names(r);
                for (i, j) in s.joints.iter().enumerate() {
                    let fallback = format!("joint{i}");
                    let name = names.get(i).map_or(fallback.as_str(), |n| n.as_str());
                    let joint = label(&[("robot", id), ("joint", name)]);
                    valid
                        .get_or_create(&joint)
                        .set(f64::from(u8::from(j.valid)));
                    // A servo missing this cycle has no temperature or current: no sample
                    // rather than a made-up one.
                    if j.valid && j.temperature_c.is_finite() {
                        temperature
                            .get_or_create(&joint)
                            .set(f64::from(j.temperature_c));
                    }
                    if j.valid && j.current_a.is_finite() {
                        current.get_or_create(&joint).set(f64::from(j.current_a));
                    }
                }
            }
            for b in r.status.iter().flat_map(|s| &s.buses) {
                let labels = label(&[("robot", id), ("bus", &b.name)]);
                bus_connected
                    .get_or_create(&labels)
                    .set(f64::from(u8::from(b.connected)));
                bus_cycles.get_or_create(&labels).inc_by(b.counters.cycles);
                let counts = serde_json::to_value(b.counters).unwrap_or_default();
                for kind in BUS_ERROR_KINDS {
                    if let Some(n) = counts[kind].as_u64() {
                        bus_errors
                            .get_or_create(&label(&[
                                ("robot", id),
                                ("bus", &b.name),
                                ("kind", kind),
                            ]))
                            .inc_by(n);
                    }
                }
            }
            for c in r.status.iter().flat_map(|s| &s.cameras) {
                let labels = label(&[("robot", id), ("camera", &c.name)]);
                camera_frames.get_or_create(&labels).inc_by(c.frames);
                for (kind, n) in [
                    ("dropped", c.dropped),
                    ("corrupt", c.corrupt),
                    ("late", c.late),
                ] {
                    camera_lost
                        .get_or_create(&label(&[
                            ("robot", id),
                            ("camera", &c.name),
                            ("kind", kind),
                        ]))
                        .inc_by(n);
                }
                if let Some(ms) = c.age_ms {
                    camera_age.get_or_create(&labels).set(ms * 1e-3);
                }
            }
            if let Some(l) = r.status.as_ref().and_then(|s| s.lidar.as_ref()) {
                lidar_scans.get_or_create(&robot).inc_by(l.scans);
                for (kind, n) in [
                    ("bad_points", l.bad_points),
                    ("resyncs", l.resyncs),
                    ("short_scans", l.short_scans),
                ] {
                    lidar_lost
                        .get_or_create(&label(&[("robot", id), ("kind", kind)]))
                        .inc_by(n);
                }
                if let Some(ms) = l.age_ms {
                    lidar_age.get_or_create(&robot).set(ms * 1e-3);
                }
                if let Some(hz) = l.rotation_hz {
                    lidar_hz.get_or_create(&robot).set(hz);
                }
            }
            if let Some(c) = r.status.as_ref().map(|s| &s.counters) {
                accepted.get_or_create(&robot).inc_by(c.actions_accepted);
                for (reason, n) in &c.actions_rejected {
                    rejected
                        .get_or_create(&label(&[("robot", id), ("reason", reason)]))
                        .inc_by(*n);
                }
            }
        }
        for (kind, n) in &self.undecodable {
            undecodable
                .get_or_create(&label(&[("key", kind)]))
                .inc_by(*n);
        }
        let mut registry = Registry::with_prefix("nori");
        registry.register(
            "robot_online",
            "1 while the robot's liveliness token is present",
            online,
        );
        registry.register(
            "robot_safe_state",
            "1 while the driver holds its safe state",
            safe,
        );
        registry.register(
            "robot_deadline_misses",
            "control cycles that missed their deadline (driver's count)",
            misses,
        );
        registry.register(
            "robot_state_messages",
            "telemetry messages received from the robot",
            states,
        );
        registry.register("robot_events", "supervisor events by kind", events);
        registry.register(
            "robot_actions_accepted",
            "action chunks the robot's gate accepted",
            accepted,
        );
        registry.register(
            "robot_actions_rejected",
            "action chunks the robot's gate rejected, by reason",
            rejected,
        );
        registry.register(
            "joint_temperature_celsius",
            "servo temperature register",
            temperature,
        );
        registry.register("joint_current_amperes", "servo current", current);
        registry.register(
            "joint_valid",
            "1 when the servo answered in the last telemetry frame",
            valid,
        );
        registry.register(
            "bus_connected",
            "1 while the robot's bus device is open (driver's view, from the agent's status)",
            bus_connected,
        );
        registry.register("bus_cycles", "feedback transactions on the bus", bus_cycles);
        registry.register(
            "bus_errors",
            "the driver's error counts on the bus, by kind (see telemetry::frames::BusCounters)",
            bus_errors,
        );
        registry.register(
            "camera_frames",
            "frames the robot's camera process published (agent's status)",
            camera_frames,
        );
        registry.register(
            "camera_frames_lost",
            "camera frames dropped, refused as corrupt, or published late (over two periods), by kind",
            camera_lost,
        );
        registry.register(
            "camera_frame_age_seconds",
            "age of the camera's newest frame when the agent answered",
            camera_age,
        );
        registry.register(
            "lidar_scans",
            "revolutions the robot's lidar process published",
            lidar_scans,
        );
        registry.register(
            "lidar_faults",
            "lidar measurements unconfirmed, stream resyncs, revolutions dropped as short, by kind",
            lidar_lost,
        );
        registry.register(
            "lidar_scan_age_seconds",
            "age of the lidar's newest revolution when the agent answered",
            lidar_age,
        );
        registry.register("lidar_rotation_hz", "revolutions per second", lidar_hz);
        registry.register(
            "fleet_undecodable_messages",
            "messages the collector could not decode, by key",
            undecodable,
        );
        let mut text = String::new();
        // Writing into a String cannot fail.
        let _ = encode(&mut text, &registry);
        text
    }
}

/// The [`telemetry::frames::BusCounters`] fields that count something going wrong.
const BUS_ERROR_KINDS: [&str; 13] = [
    "missing",
    "checksum_errors",
    "garbage_bytes",
    "framing_errors",
    "unexpected_replies",
    "implausible",
    "status_errors",
    "transport_errors",
    "disconnects",
    "silences",
    "servos_lost",
    "read_back_missing",
    "safety_mismatches",
];

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
        encode, AgentCounters, BusStatus, JointInfoMsg, JointMsg, StatusConfig, StatusHealth,
        SCHEMA_VERSION,
    };

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
            r#"nori_lidar_rotation_hz{robot="r4"} 10.0"#,
        ] {
            assert!(text.contains(line), "{line} not in\n{text}");
        }
        // A camera never seen has no age: no sample rather than a made-up one.
        assert!(!text.contains(r#"nori_camera_frame_age_seconds{robot="r4",camera="neck"}"#));
    }
}
