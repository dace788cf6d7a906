//! What led to the event that froze a box, read from the box itself: the figures of its joint
//! before it (temperature, current) and the protections that acted on that joint before it
//! (stall retries, torque reductions, warnings). A box kept open by later events names every
//! one of them; the one told about is the box's first trip (a bus latched off) if it holds
//! one, else what froze it. The fleet's store reads it from every box it receives, for the
//! protection statistics of `nori fleet report`. Pure: the box's bytes in.

use crate::channel::{Channel, EventMessage};
use crate::frozen::{visit_within, Item};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// What led to a box's event.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LeadUp {
    /// The event told about: the box's first trip, else what froze it (`None`: a box that
    /// says neither).
    pub trigger: Option<EventMessage>,
    /// Every event that froze or kept open the box, in order (at most [`MOST_TRIGGERS`]).
    pub triggers: Vec<EventMessage>,
    /// The joint the figures are of: the trigger's, else the hottest before it.
    pub joint: Option<String>,
    /// Seconds of joint states in the box before the event.
    pub seconds_before: f64,
    /// The joint's temperature at the box's start, its highest before the event, and its last
    /// before it, °C.
    pub temperature_c: Option<[f32; 3]>,
    /// The joint's current before the event: its mean and its peak, A.
    pub current_a: Option<[f32; 2]>,
    /// The box's events before the event that are about the joint or about no joint, by kind.
    pub events_before: BTreeMap<String, u64>,
    /// The box was read only in part: beyond [`READ_BUDGET`] bytes, or its joints or kinds of
    /// events beyond what is kept (a box from outside is read at a bounded cost).
    pub cut_short: bool,
}

/// The bytes of a box decompressed at most, in each of its two readings (a box of five minutes
/// of every channel is a few hundred MB of JSON).
pub const READ_BUDGET: u64 = 1 << 30;

/// Triggers kept of one box.
pub const MOST_TRIGGERS: usize = 64;

/// The triggers that are trips (a bus latched off), as a box names them.
pub const TRIPS: [&str; 3] = ["thermal_trip", "firmware_protection", "driver_trip"];

/// Joints, and kinds of events per joint, told apart at most (the A3 has 19 joints), and the
/// longest name of either kept (a longer one is not counted).
const MOST_JOINTS: usize = 64;
const MOST_KINDS: usize = 64;
const LONGEST_NAME: usize = 64;

/// One joint's readings before the event.
#[derive(Debug, Clone, Copy)]
struct Figures {
    first_c: f32,
    max_c: f32,
    last_c: f32,
    current_sum: f64,
    current_peak: f32,
    readings: u64,
}

impl Figures {
    fn new(temperature_c: f32) -> Figures {
        Figures {
            first_c: temperature_c,
            max_c: temperature_c,
            last_c: temperature_c,
            current_sum: 0.0,
            current_peak: 0.0,
            readings: 0,
        }
    }

    fn add(&mut self, temperature_c: f32, current_a: f32) {
        self.max_c = self.max_c.max(temperature_c);
        self.last_c = temperature_c;
        self.current_sum += f64::from(current_a.abs());
        self.current_peak = self.current_peak.max(current_a.abs());
        self.readings += 1;
    }
}

/// What led to the box's first trip, else to the event that froze it, from the box in `bytes`
/// (read as far as it is whole, twice within [`READ_BUDGET`]: its triggers, then what came
/// before the one told about).
pub fn lead_up(bytes: &[u8]) -> LeadUp {
    let (frozen_by, triggers, mut cut_short) = triggers(bytes);
    let trigger = triggers
        .iter()
        .find(|t| TRIPS.contains(&t.kind.as_str()))
        .or(frozen_by.as_ref())
        .cloned();
    let before = trigger.as_ref().map_or(u64::MAX, |t| t.timestamp_ns);
    let mut joints: BTreeMap<String, Figures> = BTreeMap::new();
    // Events before the trigger, counted by the joint they are about (`None`: no joint).
    let mut events: BTreeMap<Option<String>, BTreeMap<String, u64>> = BTreeMap::new();
    let (mut first_ns, mut last_ns) = (None, 0);
    let extent = visit_within(bytes, READ_BUDGET, &mut |item| {
        let Item::Message { topic, data, .. } = item else {
            return;
        };
        match Channel::from_topic(topic) {
            Some(Channel::JointStates) => {
                let Ok(v) = serde_json::from_slice::<serde_json::Value>(data) else {
                    return;
                };
                let Some(t) = v["timestamp_ns"].as_u64().filter(|&t| t < before) else {
                    return;
                };
                first_ns.get_or_insert(t);
                last_ns = last_ns.max(t);
                cut_short |= !readings(&v, &mut joints);
            }
            Some(Channel::Events) => {
                let Ok(e) = serde_json::from_slice::<EventMessage>(data) else {
                    return;
                };
                if e.timestamp_ns < before {
                    cut_short |= !count_event(&mut events, e);
                }
            }
            _ => {}
        }
    });
    let joint = trigger.as_ref().and_then(|t| t.joint.clone()).or_else(|| {
        joints
            .iter()
            .max_by(|a, b| a.1.max_c.total_cmp(&b.1.max_c))
            .map(|(name, _)| name.clone())
    });
    let figures = joint.as_ref().and_then(|j| joints.get(j));
    let mut events_before = events.remove(&None).unwrap_or_default();
    for (kind, n) in events.remove(&joint).unwrap_or_default() {
        *events_before.entry(kind).or_insert(0) += n;
    }
    LeadUp {
        seconds_before: first_ns.map_or(0.0, |f| (last_ns - f) as f64 * 1e-9),
        temperature_c: figures.map(|f| [f.first_c, f.max_c, f.last_c]),
        current_a: figures
            .filter(|f| f.readings > 0)
            .map(|f| [(f.current_sum / f.readings as f64) as f32, f.current_peak]),
        trigger,
        triggers,
        joint,
        events_before,
        cut_short: cut_short || extent.cut_at_budget,
    }
}

/// What froze the box (its metadata), every trigger it holds (names within bounds), and
/// whether it was read only in part.
fn triggers(bytes: &[u8]) -> (Option<EventMessage>, Vec<EventMessage>, bool) {
    let (mut frozen_by, mut all, mut cut_short) = (None, Vec::new(), false);
    let kept = |e: &EventMessage| {
        e.kind.len() <= LONGEST_NAME && e.joint.as_ref().is_none_or(|j| j.len() <= LONGEST_NAME)
    };
    let extent = visit_within(bytes, READ_BUDGET, &mut |item| match item {
        Item::Metadata(m) => {
            frozen_by = m
                .get("event")
                .and_then(|e| serde_json::from_str::<EventMessage>(e).ok())
                .filter(kept);
        }
        Item::Message { topic, data, .. } => {
            if Channel::from_topic(topic) != Some(Channel::Triggers) {
                return;
            }
            match serde_json::from_slice::<EventMessage>(data) {
                Ok(e) if kept(&e) && all.len() < MOST_TRIGGERS => all.push(e),
                Ok(_) => cut_short = true,
                Err(_) => {}
            }
        }
    });
    (frozen_by, all, cut_short || extent.cut_at_budget)
}

/// Counts event `e` under its joint; `false` when its joint or its kind is beyond what is kept.
fn count_event(
    events: &mut BTreeMap<Option<String>, BTreeMap<String, u64>>,
    e: EventMessage,
) -> bool {
    let too_long =
        e.kind.len() > LONGEST_NAME || e.joint.as_ref().is_some_and(|j| j.len() > LONGEST_NAME);
    if too_long || (!events.contains_key(&e.joint) && events.len() >= MOST_JOINTS) {
        return false;
    }
    let kinds = events.entry(e.joint).or_default();
    if !kinds.contains_key(&e.kind) && kinds.len() >= MOST_KINDS {
        return false;
    }
    *kinds.entry(e.kind).or_insert(0) += 1;
    true
}

/// Folds one joint-state message's valid readings into each joint's figures; `false` when a
/// joint beyond what is kept was left out.
fn readings(v: &serde_json::Value, joints: &mut BTreeMap<String, Figures>) -> bool {
    let Some(names) = v["name"].as_array() else {
        return true;
    };
    let mut all = true;
    for (k, name) in names.iter().enumerate() {
        let (Some(name), Some(true)) = (name.as_str(), v["valid"][k].as_bool()) else {
            continue;
        };
        let (Some(t), Some(i)) = (v["temperature_c"][k].as_f64(), v["current_a"][k].as_f64())
        else {
            continue;
        };
        let (t, i) = (t as f32, i as f32);
        if name.len() > LONGEST_NAME || (!joints.contains_key(name) && joints.len() >= MOST_JOINTS)
        {
            all = false;
            continue;
        }
        joints
            .entry(name.to_string())
            .or_insert_with(|| Figures::new(t))
            .add(t, i);
    }
    all
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use crate::channel::{joint_states, to_json, Names};
    use crate::frozen::BoxWriter;
    use crate::ring::Record;
    use std::io::Cursor;
    use telemetry::JointState;

    const S: u64 = 1_000_000_000;

    /// Writes one message of `channel` at `t_ns` into the box.
    fn put(w: &mut BoxWriter<Cursor<Vec<u8>>>, channel: Channel, t_ns: u64, data: &[u8]) {
        w.write(Record {
            channel,
            t_ns,
            data,
        })
        .unwrap();
    }

    fn event(t: u64, kind: &str, joint: Option<&str>, value: f32) -> EventMessage {
        EventMessage {
            timestamp_ns: t,
            kind: kind.into(),
            joint: joint.map(str::to_string),
            bus: Some("left_arm".into()),
            level: 0,
            value,
        }
    }

    /// A box frozen by `trigger` at 10 s: joint j1 heating from 40 °C by 1 °C/s drawing
    /// 0.5 A then 1.5 A from 5 s, j0 steady at 30 °C; a stall of j1 at 6 s, one of j0 at
    /// 7 s, a torque reduction of the bus at 8 s, and readings after the trigger that do not
    /// count.
    fn a_box(trigger: &EventMessage) -> Vec<u8> {
        let mut w = BoxWriter::new(Cursor::new(Vec::new()), trigger, "r1", 0).unwrap();
        let names = Names::from_layout(&{
            let mut l = telemetry::frames::JointLayout {
                joint_count: 2,
                ..Default::default()
            };
            l.joints[0].set_name("j0");
            l.joints[1].set_name("j1");
            l
        });
        for k in 0..=12u64 {
            let mut s = JointState {
                joint_count: 2,
                timestamp_ns: k * S,
                ..Default::default()
            };
            s.joints[0].valid = 1;
            s.joints[0].temperature_c = 30.0;
            s.joints[1].valid = 1;
            s.joints[1].temperature_c = 40.0 + k as f32;
            s.joints[1].current_a = if k < 5 { 0.5 } else { 1.5 };
            let (t_ns, data) = joint_states(&s, &names);
            let channel = Channel::JointStates;
            put(&mut w, channel, t_ns, &data);
        }
        for e in [
            event(6 * S, "stall", Some("j1"), 1.2),
            event(7 * S, "stall", Some("j0"), 1.2),
            event(8 * S, "torque_reduced", None, 500.0),
            event(11 * S, "stall", Some("j1"), 1.2),
        ] {
            let data = to_json(&e);
            let (channel, t_ns) = (Channel::Events, e.timestamp_ns);
            put(&mut w, channel, t_ns, &data);
        }
        w.finish().unwrap().into_inner()
    }

    #[test]
    fn the_trip_s_joint_before_it_and_the_protections_that_acted_on_it() {
        let trip = event(10 * S, "thermal_trip", Some("j1"), 59.0);
        let l = lead_up(&a_box(&trip));
        assert_eq!(l.trigger, Some(trip));
        assert_eq!(l.joint.as_deref(), Some("j1"));
        assert_eq!(l.seconds_before, 9.0, "0 to 9 s: the readings before 10 s");
        assert_eq!(l.temperature_c, Some([40.0, 49.0, 49.0]));
        // Five readings at 0.5 A, five at 1.5 A.
        assert_eq!(l.current_a, Some([1.0, 1.5]));
        let expected = BTreeMap::from([("stall".into(), 1), ("torque_reduced".into(), 1)]);
        assert_eq!(
            l.events_before, expected,
            "j0's stall and the later one left out"
        );
    }

    #[test]
    fn an_event_of_no_joint_is_told_by_the_hottest_and_garbage_by_nothing() {
        let saved = event(10 * S, "saved", None, 0.0);
        let l = lead_up(&a_box(&saved));
        assert_eq!(l.joint.as_deref(), Some("j1"), "the hottest");
        assert_eq!(l.events_before["stall"], 1);
        assert_eq!(lead_up(b"not a box"), LeadUp::default());
    }

    #[test]
    fn a_box_from_outside_is_read_at_a_bounded_cost() {
        let saved = event(10 * S, "saved", None, 0.0);
        let mut w = BoxWriter::new(Cursor::new(Vec::new()), &saved, "r1", 0).unwrap();
        for k in 0..200u64 {
            let (joint, kind) = (format!("j{k}"), format!("k{k}"));
            let data = to_json(&event(k, &kind, Some(&joint), 0.0));
            let (channel, t_ns) = (Channel::Events, k);
            put(&mut w, channel, t_ns, &data);
        }
        let bytes = w.finish().unwrap().into_inner();
        let l = lead_up(&bytes);
        assert!(l.cut_short, "200 joints: more than are kept");
        assert!(!lead_up(&a_box(&saved)).cut_short);
        let cut = crate::frozen::visit_within(&a_box(&saved), 1, &mut |_| {});
        assert!(cut.cut_at_budget);
        assert!(!crate::frozen::visit_within(&a_box(&saved), u64::MAX, &mut |_| {}).cut_at_budget);
    }

    #[test]
    fn a_box_kept_open_by_a_trip_tells_about_the_trip() {
        let stall = event(6 * S, "stall_retry", Some("j1"), 1.0);
        let trip = event(10 * S, "thermal_trip", Some("j1"), 59.0);
        let l = lead_up(&a_box_with_triggers(&stall, &[&stall, &trip]));
        assert_eq!(l.trigger, Some(trip.clone()));
        assert_eq!(l.triggers, vec![stall.clone(), trip]);
        assert_eq!(
            l.temperature_c,
            Some([40.0, 49.0, 49.0]),
            "up to the trip at 10 s, not the stall at 6 s"
        );
        let alone = lead_up(&a_box_with_triggers(&stall, &[&stall]));
        assert_eq!(alone.trigger, Some(stall));
        assert_eq!(alone.temperature_c, Some([40.0, 45.0, 45.0]));
    }

    /// [`a_box`] frozen by `frozen_by`, with `triggers` on its channel.
    fn a_box_with_triggers(frozen_by: &EventMessage, triggers: &[&EventMessage]) -> Vec<u8> {
        let base = a_box(frozen_by);
        let mut w = BoxWriter::new(Cursor::new(Vec::new()), frozen_by, "r1", 0).unwrap();
        crate::frozen::visit(&base, &mut |item| {
            if let Item::Message {
                topic,
                log_time,
                data,
            } = item
            {
                let channel = Channel::from_topic(topic).unwrap();
                put(&mut w, channel, log_time, data);
            }
        });
        for t in triggers {
            let data = to_json(*t);
            let (channel, t_ns) = (Channel::Triggers, t.timestamp_ns);
            put(&mut w, channel, t_ns, &data);
        }
        w.finish().unwrap().into_inner()
    }

    #[test]
    fn kinds_and_names_beyond_the_bounds_are_not_kept() {
        let saved = event(10 * S, "saved", Some("j1"), 0.0);
        let mut w = BoxWriter::new(Cursor::new(Vec::new()), &saved, "r1", 0).unwrap();
        for k in 0..100u64 {
            let data = to_json(&event(k, &format!("kind{k}"), Some("j1"), 0.0));
            let (channel, t_ns) = (Channel::Events, k);
            put(&mut w, channel, t_ns, &data);
        }
        let long = "x".repeat(LONGEST_NAME + 1);
        let data = to_json(&event(200, &long, Some("j1"), 0.0));
        put(&mut w, Channel::Events, 200, &data);
        let names: Vec<String> = (0..100).map(|k| format!("n{k}")).collect();
        let states = serde_json::json!({
            "timestamp_ns": 300,
            "name": names,
            "valid": vec![true; 100],
            "temperature_c": vec![30.0; 100],
            "current_a": vec![0.1; 100],
        });
        let data = serde_json::to_vec(&states).unwrap();
        put(&mut w, Channel::JointStates, 300, &data);
        let l = lead_up(&w.finish().unwrap().into_inner());
        assert!(l.cut_short);
        assert_eq!(
            l.events_before.len(),
            MOST_KINDS,
            "64 kinds of the 100, not the long one"
        );
        assert!(!l.events_before.contains_key(&long));
    }
}
