//! A reference policy for the loop's other end: what `nori policy-server` serves to every robot
//! that sends observations. Scripted (a smooth wave of chosen joints), so a test knows exactly
//! which targets must reach the servos. Pure: an observation in, an action chunk out.

use crate::schema::{ActionChunk, LayoutMsg, ObservationMsg, SCHEMA_VERSION};

/// Waves `joints` around `centre` rad with `amplitude` rad and `period_s`, on the robot's clock,
/// clamped into each joint's calibrated range.
#[derive(Debug, Clone, PartialEq)]
pub struct WavePolicy {
    /// Joint names to move.
    pub joints: Vec<String>,
    /// Centre of the wave, rad.
    pub centre: f32,
    /// Amplitude, rad.
    pub amplitude: f32,
    /// Period, s.
    pub period_s: f32,
    /// Steps per chunk.
    pub steps: usize,
    /// Time between steps, ms.
    pub step_ms: u64,
}

impl WavePolicy {
    /// The wave's target at robot time `t_ns`.
    pub fn at(&self, t_ns: u64) -> f32 {
        let phase = (t_ns as f64 / 1e9 / f64::from(self.period_s)).fract();
        self.centre + self.amplitude * (std::f64::consts::TAU * phase).sin() as f32
    }

    /// The chunk answering `obs` (numbered `seq`), or `None` when none of the policy's joints
    /// is in the robot's layout or the observation does not match it.
    pub fn chunk(&self, obs: &ObservationMsg, layout: &LayoutMsg, seq: u64) -> Option<ActionChunk> {
        let n = layout.joints.len();
        if n == 0 || n > 32 || obs.position.len() != n {
            return None;
        }
        let mask = layout
            .joints
            .iter()
            .enumerate()
            .filter(|(_, j)| self.joints.contains(&j.name))
            .fold(0u32, |m, (i, _)| m | 1 << i);
        if mask == 0 {
            return None;
        }
        let offsets: Vec<u64> = (1..=self.steps as u64)
            .map(|k| k * self.step_ms * 1_000_000)
            .collect();
        let mut targets = Vec::with_capacity(offsets.len() * n);
        for &offset in &offsets {
            let wave = self.at(obs.timestamp_ns + offset);
            for (i, j) in layout.joints.iter().enumerate() {
                targets.push(if mask & (1 << i) != 0 {
                    wave.clamp(j.min, j.max)
                } else {
                    // Not commanded: a finite placeholder the agent ignores.
                    0.0
                });
            }
        }
        Some(ActionChunk {
            version: SCHEMA_VERSION,
            seq,
            observation_ns: obs.timestamp_ns,
            step_offsets_ns: offsets,
            joint_count: n as u16,
            joint_mask: mask,
            targets,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gate::{ActionGate, GateConfig, Range};
    use crate::schema::{encode, JointInfoMsg};

    #[test]
    fn the_reference_policy_passes_the_gate_and_stays_in_range() {
        let layout = LayoutMsg {
            version: SCHEMA_VERSION,
            joints: vec![
                JointInfoMsg {
                    name: "left_elbow".into(),
                    min: -2.0,
                    max: -0.2,
                },
                JointInfoMsg {
                    name: "left_gripper".into(),
                    min: 0.0,
                    max: 1.0,
                },
            ],
        };
        let policy = WavePolicy {
            joints: vec!["left_elbow".into()],
            centre: -0.5,
            amplitude: 0.6,
            period_s: 2.0,
            steps: 25,
            step_ms: 20,
        };
        let obs = ObservationMsg {
            version: SCHEMA_VERSION,
            seq: 1,
            timestamp_ns: 4_000_000_000,
            position: vec![-0.5, f32::NAN],
            velocity: vec![0.0, 0.0],
        };
        let c = policy.chunk(&obs, &layout, 1).unwrap();
        assert_eq!(c.joint_mask, 0b01);
        assert!(c.targets.chunks(2).all(|s| (-2.0..=-0.2).contains(&s[0])));
        assert!(
            c.targets.chunks(2).any(|s| s[0] == -0.2),
            "clamped at the range's end"
        );
        let ranges: Vec<Range> = layout
            .joints
            .iter()
            .map(|j| Range {
                min: j.min,
                max: j.max,
            })
            .collect();
        let mut gate = ActionGate::new(GateConfig {
            max_age_ns: 250_000_000,
            max_steps: 128,
            max_span_ns: 3_000_000_000,
        });
        assert!(gate
            .check(&encode(&c), obs.timestamp_ns + 30_000_000, &ranges)
            .is_ok());
    }
}
