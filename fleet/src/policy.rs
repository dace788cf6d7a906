//! Reference policies for the loop's other end: what `nori policy-server` serves to every robot
//! that sends observations. Scripted (a smooth wave of chosen joints, so a test knows exactly
//! which targets must reach the servos) or replayed (a recorded trajectory, looped on the
//! robot's clock). Pure: an observation in, an action chunk out.

use fleet_agent::schema::{ActionChunk, LayoutMsg, ObservationMsg, SCHEMA_VERSION};
use thiserror::Error;

/// Where the policy sends its joints over time.
#[derive(Debug, Clone, PartialEq)]
pub enum Motion {
    /// Waves `joints` around `centre` rad with `amplitude` rad and `period_s`.
    Wave {
        /// Joint names to move.
        joints: Vec<String>,
        /// Centre of the wave, rad.
        centre: f32,
        /// Amplitude, rad.
        amplitude: f32,
        /// Period, s.
        period_s: f32,
    },
    /// A recorded trajectory, looped.
    Replay(Trajectory),
}

impl Motion {
    /// Joint `name`'s target at robot time `t_ns`, or `None` if this motion does not move it.
    pub fn target(&self, name: &str, t_ns: u64) -> Option<f32> {
        match self {
            Motion::Wave {
                joints,
                centre,
                amplitude,
                period_s,
            } => joints.iter().any(|j| j == name).then(|| {
                let phase = (t_ns as f64 / 1e9 / f64::from(*period_s)).fract();
                centre + amplitude * (std::f64::consts::TAU * phase).sin() as f32
            }),
            Motion::Replay(t) => t.target(name, t_ns),
        }
    }
}

/// A recorded trajectory that could not be read.
#[derive(Debug, Error, PartialEq)]
pub enum TrajectoryError {
    /// The header is not `t_s,<joint>,...`.
    #[error("header: expected t_s followed by joint names, got {0:?}")]
    Header(String),
    /// A row that is not numbers, has the wrong width, goes back in time or holds a non-finite
    /// target.
    #[error("line {line}: {why}")]
    Row {
        /// 1-based line number.
        line: usize,
        /// What is wrong with it.
        why: String,
    },
    /// Fewer than two rows: nothing to interpolate or loop.
    #[error("a trajectory needs at least two rows spanning a positive time")]
    TooShort,
}

/// Joint targets over time, from a CSV `t_s,<joint>,<joint>,...` (one row per time, rad),
/// played in a loop and interpolated linearly between rows.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    joints: Vec<String>,
    times_s: Vec<f64>,
    /// Row-major: `rows[k * joints.len() + j]`.
    rows: Vec<f32>,
}

impl Trajectory {
    /// Parses the CSV text.
    pub fn parse(text: &str) -> Result<Self, TrajectoryError> {
        let mut lines = text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty() && !l.starts_with('#'));
        let (_, header) = lines
            .next()
            .ok_or_else(|| TrajectoryError::Header(String::new()))?;
        let mut cols = header.split(',').map(str::trim);
        let joints: Vec<String> = match cols.next() {
            Some("t_s") => cols.map(String::from).collect(),
            _ => return Err(TrajectoryError::Header(header.into())),
        };
        if joints.is_empty() || joints.iter().any(String::is_empty) {
            return Err(TrajectoryError::Header(header.into()));
        }
        let (mut times_s, mut rows) = (Vec::new(), Vec::new());
        for (i, line) in lines {
            let bad = |why: String| TrajectoryError::Row { line: i + 1, why };
            let cells: Vec<&str> = line.split(',').map(str::trim).collect();
            if cells.len() != joints.len() + 1 {
                return Err(bad(format!(
                    "{} cells, the header has {}",
                    cells.len(),
                    joints.len() + 1
                )));
            }
            let t: f64 = cells[0]
                .parse()
                .map_err(|_| bad(format!("time {:?} is not a number", cells[0])))?;
            if !t.is_finite() || times_s.last().is_some_and(|&last| t <= last) {
                return Err(bad(format!("time {t} does not rise")));
            }
            for (name, cell) in joints.iter().zip(&cells[1..]) {
                let v: f32 = cell
                    .parse()
                    .ok()
                    .filter(|v: &f32| v.is_finite())
                    .ok_or_else(|| bad(format!("{name}: {cell:?} is not a finite number")))?;
                rows.push(v);
            }
            times_s.push(t);
        }
        if times_s.len() < 2 {
            return Err(TrajectoryError::TooShort);
        }
        Ok(Trajectory {
            joints,
            times_s,
            rows,
        })
    }

    /// Seconds the trajectory lasts before it loops.
    pub fn duration_s(&self) -> f64 {
        self.times_s[self.times_s.len() - 1] - self.times_s[0]
    }

    fn target(&self, name: &str, t_ns: u64) -> Option<f32> {
        let j = self.joints.iter().position(|n| n == name)?;
        let n = self.joints.len();
        let t = self.times_s[0] + (t_ns as f64 / 1e9).rem_euclid(self.duration_s());
        let k = self
            .times_s
            .partition_point(|&s| s <= t)
            .clamp(1, self.times_s.len() - 1);
        let (t0, t1) = (self.times_s[k - 1], self.times_s[k]);
        let (a, b) = (self.rows[(k - 1) * n + j], self.rows[k * n + j]);
        let w = ((t - t0) / (t1 - t0)) as f32;
        Some(a + (b - a) * w)
    }
}

/// A policy: a motion cut into chunks of `steps` steps `step_ms` apart, clamped into each
/// joint's calibrated range.
#[derive(Debug, Clone, PartialEq)]
pub struct ScriptedPolicy {
    /// What it plays.
    pub motion: Motion,
    /// Steps per chunk.
    pub steps: usize,
    /// Time between steps, ms.
    pub step_ms: u64,
}

impl ScriptedPolicy {
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
            .filter(|(_, j)| self.motion.target(&j.name, 0).is_some())
            .fold(0u32, |m, (i, _)| m | 1 << i);
        if mask == 0 {
            return None;
        }
        let offsets: Vec<u64> = (1..=self.steps as u64)
            .map(|k| k * self.step_ms * 1_000_000)
            .collect();
        let mut targets = Vec::with_capacity(offsets.len() * n);
        for &offset in &offsets {
            for j in &layout.joints {
                // A joint it does not move gets a finite placeholder the agent ignores.
                let target = self.motion.target(&j.name, obs.timestamp_ns + offset);
                targets.push(target.map_or(0.0, |v| v.clamp(j.min, j.max)));
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
            lift_m: Vec::new(),
            base_twist: Vec::new(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fleet_agent::gate::{ActionGate, GateConfig, Range};
    use fleet_agent::schema::{encode, JointInfoMsg};

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
        let policy = ScriptedPolicy {
            motion: Motion::Wave {
                joints: vec!["left_elbow".into()],
                centre: -0.5,
                amplitude: 0.6,
                period_s: 2.0,
            },
            steps: 25,
            step_ms: 20,
        };
        let obs = ObservationMsg {
            version: SCHEMA_VERSION,
            seq: 1,
            timestamp_ns: 4_000_000_000,
            position: vec![-0.5, f32::NAN],
            velocity: vec![0.0, 0.0],
            images: Vec::new(),
            lift: None,
            base: None,
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
            body: fleet_agent::gate::BodyLimits {
                lift_m: fleet_agent::gate::Range {
                    min: 0.01,
                    max: 0.75,
                },
                max_linear_m_s: 0.2,
                max_angular_rad_s: 1.0,
            },
        });
        // The driver has been driving since before the observation.
        gate.observe_driver(1, 0, false);
        assert!(gate
            .check(&encode(&c), obs.timestamp_ns + 30_000_000, &ranges)
            .is_ok());
    }

    #[test]
    fn a_trajectory_replays_interpolated_and_looped() {
        let t = Trajectory::parse(
            "t_s,left_elbow,left_gripper\n1.0,-1.0,0.0\n2.0,-0.5,1.0\n3.0,-1.0,0.5\n",
        )
        .unwrap();
        assert_eq!(t.duration_s(), 2.0);
        let motion = Motion::Replay(t);
        let at = |s: f64| motion.target("left_elbow", (s * 1e9) as u64).unwrap();
        assert_eq!(at(0.0), -1.0);
        assert_eq!(at(0.5), -0.75);
        assert_eq!(at(1.0), -0.5);
        assert_eq!(at(2.5), -0.75, "looped");
        assert_eq!(motion.target("right_elbow", 0), None);
    }

    #[test]
    fn a_bad_trajectory_names_its_line() {
        use TrajectoryError::*;
        assert!(matches!(
            Trajectory::parse("time,a\n0,1\n1,2"),
            Err(Header(_))
        ));
        assert_eq!(
            Trajectory::parse("t_s,a\n0,1\n0,2"),
            Err(Row {
                line: 3,
                why: "time 0 does not rise".into()
            })
        );
        assert!(matches!(
            Trajectory::parse("t_s,a\n0,1\n1,NaN"),
            Err(Row { line: 3, .. })
        ));
        assert!(matches!(
            Trajectory::parse("t_s,a\n0,1,2\n1,2"),
            Err(Row { line: 2, .. })
        ));
        assert_eq!(Trajectory::parse("t_s,a\n0,1\n"), Err(TooShort));
    }
}
