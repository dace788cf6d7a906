//! A box's joint states as the telemetry CSV the model lab reads (`data/README.md`: long
//! format, one row per motor per sample, empty cells for a missing reading), and what a box
//! holds, for `nori blackbox list` and `show`; both read the box as a stream.

use crate::channel::{Channel, LayoutJoint};
use crate::frozen::{visit, Extent, Item};
use std::collections::BTreeMap;
use std::fmt::Write as _;

/// The CSV header (as `recorder::csv`).
pub const HEADER: &str =
    "t_s,motor,goal_rad,position_rad,velocity_rad_s,voltage_v,temperature_c,current_a";

/// The box's joint states as CSV, time from its first frame, and its sidecar
/// (`NAME.meta.json`: the joints' names in motor order, the daisy chains per bus and each
/// servo's model, from the box's last layout).
pub fn joint_states_csv(bytes: &[u8]) -> (String, serde_json::Value) {
    let mut out = String::from(HEADER);
    out.push('\n');
    let mut names = Vec::new();
    let mut layout: Vec<LayoutJoint> = Vec::new();
    let mut t0 = None;
    visit(bytes, &mut |item| {
        let Item::Message { topic, data, .. } = item else {
            return;
        };
        if Channel::from_topic(topic) == Some(Channel::Layout) {
            if let Ok(v) = serde_json::from_slice::<serde_json::Value>(data) {
                layout = serde_json::from_value(v["joints"].clone()).unwrap_or_default();
            }
            return;
        }
        if Channel::from_topic(topic) != Some(Channel::JointStates) {
            return;
        }
        let Ok(v) = serde_json::from_slice::<serde_json::Value>(data) else {
            return;
        };
        let Some(t_ns) = v["timestamp_ns"].as_u64() else {
            return;
        };
        let t = t_ns.saturating_sub(*t0.get_or_insert(t_ns)) as f64 * 1e-9;
        if names.is_empty() {
            names = column(&v, "name", |x| x.as_str().map(str::to_string));
        }
        rows(&mut out, t, &v);
    });
    (out, sidecar(&names, &layout))
}

/// The model lab's sidecar: the joints, the chains (motor indices per bus, in the driver's
/// order) and the servo models, where the layout names the joint.
fn sidecar(names: &[String], layout: &[LayoutJoint]) -> serde_json::Value {
    let mut chains: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
    let mut servo = serde_json::Map::new();
    for (k, name) in names.iter().enumerate() {
        let Some(j) = layout.iter().find(|j| &j.name == name) else {
            continue;
        };
        chains.entry(j.bus.as_str()).or_default().push(k);
        if let Some(model) = feetech::ServoModel::from_model_number(j.model) {
            servo.insert(k.to_string(), model.key().into());
        }
    }
    let mut side = serde_json::json!({ "joints": names });
    if !chains.is_empty() {
        side["chains"] = chains.into_values().collect::<Vec<_>>().into();
        side["servo"] = servo.into();
    }
    side
}

/// One frame's rows.
fn rows(out: &mut String, t: f64, v: &serde_json::Value) {
    let valid = column(v, "valid", serde_json::Value::as_bool);
    let cols: Vec<Vec<f64>> = [
        "goal",
        "position",
        "velocity",
        "voltage_v",
        "temperature_c",
        "current_a",
    ]
    .iter()
    .map(|c| column(v, c, serde_json::Value::as_f64))
    .collect();
    for (j, ok) in valid.iter().enumerate() {
        let _ = write!(out, "{t:.6},{j}");
        for c in &cols {
            out.push(',');
            if let (true, Some(x)) = (*ok, c.get(j)) {
                let _ = write!(out, "{x}");
            }
        }
        out.push('\n');
    }
}

fn column<T>(
    v: &serde_json::Value,
    key: &str,
    f: impl Fn(&serde_json::Value) -> Option<T>,
) -> Vec<T> {
    v[key]
        .as_array()
        .map(|a| a.iter().filter_map(&f).collect())
        .unwrap_or_default()
}

/// What a box holds.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct Summary {
    /// Its metadata (what froze it).
    pub metadata: BTreeMap<String, String>,
    /// Messages per topic.
    pub per_topic: BTreeMap<String, usize>,
    /// Its span on the wall clock, s.
    pub span_s: f64,
    /// How far it could be read.
    pub extent: Extent,
    /// Its triggers, as JSON.
    pub triggers: Vec<String>,
}

/// What the box in `bytes` holds, read as a stream.
pub fn summary(bytes: &[u8]) -> Summary {
    let mut out = Summary::default();
    let (mut lo, mut hi) = (u64::MAX, 0);
    out.extent = visit(bytes, &mut |item| match item {
        Item::Metadata(m) => out.metadata = m.clone(),
        Item::Message {
            topic,
            log_time,
            data,
        } => {
            *out.per_topic.entry(topic.to_string()).or_insert(0) += 1;
            lo = lo.min(log_time);
            hi = hi.max(log_time);
            if Channel::from_topic(topic) == Some(Channel::Triggers) {
                out.triggers
                    .push(String::from_utf8_lossy(data).into_owned());
            }
        }
    });
    out.span_s = hi.saturating_sub(lo) as f64 * 1e-9;
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::channel::{joint_states, EventMessage, Names};
    use crate::frozen::BoxWriter;
    use crate::ring::Record;
    use std::io::Cursor;
    use telemetry::JointState;

    #[test]
    fn joint_states_become_one_row_per_motor_and_a_missing_reading_empty_cells() {
        let trigger = EventMessage {
            timestamp_ns: 0,
            kind: "saved".into(),
            joint: None,
            bus: None,
            level: 0,
            value: 0.0,
        };
        let mut w = BoxWriter::new(Cursor::new(Vec::new()), &trigger, "r1", 0).unwrap();
        let mut s = JointState {
            joint_count: 2,
            timestamp_ns: 1_000_000_000,
            ..Default::default()
        };
        s.joints[0].valid = 1;
        s.joints[0].position_rad = 0.5;
        s.joints[0].temperature_c = 41.0;
        s.joints[1].valid = 0;
        for k in 0..2 {
            s.timestamp_ns += k * 5_000_000;
            let (t_ns, data) = joint_states(&s, &Names::default());
            w.write(Record {
                channel: Channel::JointStates,
                t_ns,
                data: &data,
            })
            .unwrap();
        }
        let bytes = w.finish().unwrap().into_inner();
        let (csv, side) = joint_states_csv(&bytes);
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines[0], HEADER);
        assert_eq!(lines[1], "0.000000,0,0,0.5,0,0,41,0");
        assert_eq!(lines[2], "0.000000,1,,,,,,");
        assert_eq!(lines[3], "0.005000,0,0,0.5,0,0,41,0");
        assert_eq!(side["joints"], serde_json::json!(["j0", "j1"]));
        assert!(side.get("chains").is_none(), "no layout, no chains");
        let layout = [LayoutJoint {
            name: "j1".into(),
            bus: "left_arm".into(),
            id: 2,
            model: 2825,
            role: "joint".into(),
            range_rad: [-1.0, 1.0],
        }];
        let side = sidecar(&["j0".into(), "j1".into()], &layout);
        assert_eq!(side["chains"], serde_json::json!([[1]]));
        assert_eq!(side["servo"], serde_json::json!({"1": "sts3250"}));
        let sum = summary(&bytes);
        assert_eq!(sum.per_topic["/joint_states"], 2);
        assert!((sum.span_s - 0.005).abs() < 1e-9);
        assert!(sum.extent.complete);
        assert_eq!(sum.metadata["trigger"], "saved");
    }
}
