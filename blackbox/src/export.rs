//! A box's joint states as the telemetry CSV the model lab reads (`data/README.md`: long
//! format, one row per motor per sample, empty cells for a missing reading), and what a box
//! holds, for `nori blackbox show`.

use crate::channel::Channel;
use crate::frozen::ReadBox;
use std::collections::BTreeMap;
use std::fmt::Write as _;

/// The CSV header (as `recorder::csv`).
pub const HEADER: &str =
    "t_s,motor,goal_rad,position_rad,velocity_rad_s,voltage_v,temperature_c,current_a";

/// The box's joint states as CSV, time from its first frame, and the joints' names in motor
/// order (the sidecar's `joints`).
pub fn joint_states_csv(b: &ReadBox) -> (String, Vec<String>) {
    let mut out = String::from(HEADER);
    out.push('\n');
    let mut names = Vec::new();
    let mut t0 = None;
    for m in b
        .messages
        .iter()
        .filter(|m| m.channel == Some(Channel::JointStates))
    {
        let Ok(v) = serde_json::from_slice::<serde_json::Value>(&m.data) else {
            continue;
        };
        let Some(t_ns) = v["timestamp_ns"].as_u64() else {
            continue;
        };
        let t = (t_ns - *t0.get_or_insert(t_ns)) as f64 * 1e-9;
        if names.is_empty() {
            names = column(&v, "name", |x| x.as_str().map(str::to_string));
        }
        let valid = column(&v, "valid", serde_json::Value::as_bool);
        let cols: Vec<Vec<f64>> = [
            "goal",
            "position",
            "velocity",
            "voltage_v",
            "temperature_c",
            "current_a",
        ]
        .iter()
        .map(|c| column(&v, c, serde_json::Value::as_f64))
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
    (out, names)
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

/// What a box holds: messages per topic, and its span on the wall clock, s.
pub fn summary(b: &ReadBox) -> (BTreeMap<String, usize>, f64) {
    let mut per_topic = BTreeMap::new();
    for m in &b.messages {
        *per_topic.entry(m.topic.clone()).or_insert(0) += 1;
    }
    let lo = b.messages.iter().map(|m| m.log_time).min().unwrap_or(0);
    let hi = b.messages.iter().map(|m| m.log_time).max().unwrap_or(0);
    (per_topic, (hi - lo) as f64 * 1e-9)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::channel::{joint_states, Names};
    use crate::frozen::Message;
    use telemetry::JointState;

    #[test]
    fn joint_states_become_one_row_per_motor_and_a_missing_reading_empty_cells() {
        let mut s = JointState {
            joint_count: 2,
            timestamp_ns: 1_000_000_000,
            ..Default::default()
        };
        s.joints[0].valid = 1;
        s.joints[0].position_rad = 0.5;
        s.joints[0].temperature_c = 41.0;
        s.joints[1].valid = 0;
        let mut b = ReadBox::default();
        for k in 0..2 {
            s.timestamp_ns += k * 5_000_000;
            let (_, data) = joint_states(&s, &Names::default());
            b.messages.push(Message {
                channel: Some(Channel::JointStates),
                topic: Channel::JointStates.topic().into(),
                log_time: s.timestamp_ns,
                data,
            });
        }
        let (csv, names) = joint_states_csv(&b);
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines[0], HEADER);
        assert_eq!(lines[1], "0.000000,0,0,0.5,0,0,41,0");
        assert_eq!(lines[2], "0.000000,1,,,,,,");
        assert_eq!(lines[3], "0.005000,0,0,0.5,0,0,41,0");
        assert_eq!(names, ["j0", "j1"]);
        let (per_topic, span) = summary(&b);
        assert_eq!(per_topic["/joint_states"], 2);
        assert!((span - 0.005).abs() < 1e-9);
    }
}
