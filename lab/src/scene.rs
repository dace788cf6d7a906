//! What the page draws, pure: the robot's model once (its joints with their ranges and
//! firmware cutoffs, its arms with their reachable workspace), then each state frame as the
//! arms' points in the base's frame (the one description's kinematics), every motor's
//! temperature, current and protection flags, and the robot's safe state.

use body::kinematics::{Body, Pose2};
use serde::Serialize;
use serde_json::{json, Value};
use telemetry::frames::{JointLayout, JointRole, STATE_FLAG_OPERATOR_STOP, STATE_FLAG_SAFE_STATE};
use telemetry::JointState;

/// Tool points sampled per arm for the workspace view.
pub const WORKSPACE_SAMPLES: usize = 800;

/// The body on the driver's layout.
pub struct Scene {
    body: Body,
    layout: JointLayout,
    /// Per body arm: the frame index of each of its joints, if the driver drives them all.
    arms: Vec<Option<Vec<usize>>>,
}

fn role_name(r: JointRole) -> &'static str {
    match r {
        JointRole::Joint => "joint",
        JointRole::Gripper => "gripper",
        JointRole::Wheel => "wheel",
    }
}

impl Scene {
    /// The scene of `body` as the driver's `layout` names its joints.
    pub fn new(body: Body, layout: JointLayout) -> Scene {
        let arms = body.arm_indices(|n| layout.joint_index(n));
        Scene { body, layout, arms }
    }

    /// The model the page builds its view from.
    pub fn model(&self) -> Value {
        let bus_names: Vec<&str> = self.layout.bus_names().collect();
        let joints: Vec<Value> = self
            .layout
            .joints()
            .iter()
            .map(|j| {
                json!({
                    "name": j.name(),
                    "role": role_name(j.role()),
                    "bus": bus_names.get(j.bus as usize),
                    "range": j.range_rad,
                    "cutoff_c": j.max_temperature_c,
                })
            })
            .collect();
        let arms: Vec<Value> = self
            .body
            .arms()
            .iter()
            .zip(&self.arms)
            .enumerate()
            .filter_map(|(a, (chain, idx))| {
                let idx = idx.as_ref()?;
                Some(json!({
                    "bus": chain.bus,
                    "joints": chain.joint_names,
                    "workspace": self.workspace(a, idx),
                }))
            })
            .collect();
        json!({
            "type": "model",
            "joints": joints,
            "arms": arms,
            "lift_start_m": self.body.lift_start_m(),
        })
    }

    /// Tool points over the arm's calibrated ranges (a fixed low-discrepancy sequence, so the
    /// cloud is the same at every start), rounded to the millimetre.
    fn workspace(&self, arm: usize, idx: &[usize]) -> Vec<[f64; 3]> {
        // Fractional parts of the square roots of primes: independent per joint.
        const STEPS: [f64; 8] = [
            0.414_213_562,
            0.732_050_808,
            0.236_067_977,
            0.645_751_311,
            0.316_624_790,
            0.605_551_275,
            0.123_105_626,
            0.358_898_944,
        ];
        let ranges: Vec<[f32; 2]> = idx
            .iter()
            .map(|&j| self.layout.joints()[j].range_rad)
            .collect();
        let lift = self.body.lift_start_m();
        (1..=WORKSPACE_SAMPLES)
            .filter_map(|i| {
                let q: Vec<f64> = ranges
                    .iter()
                    .enumerate()
                    .map(|(k, [lo, hi])| {
                        let u = (i as f64 * STEPS[k % STEPS.len()]).fract();
                        f64::from(*lo) + u * f64::from(hi - lo)
                    })
                    .collect();
                let p = self.body.arm_pose(arm, &q, lift, Pose2::default())?.tool;
                Some(p.map(|x| (x * 1000.0).round() / 1000.0))
            })
            .collect()
    }

    /// One state frame for the page: the arms posed from the joints read (the lift at
    /// `lift_m`), each joint's figures, the safe state, and `extra` (teleoperation, events).
    pub fn frame(&self, state: &JointState, lift_m: f64, extra: &impl Serialize) -> Value {
        let joints = state.joints();
        let arms: Vec<Value> = self
            .arms
            .iter()
            .enumerate()
            .filter_map(|(a, idx)| {
                let idx = idx.as_ref()?;
                let q: Vec<f64> = idx
                    .iter()
                    .map(|&j| joints.get(j).map_or(0.0, |s| f64::from(s.position_rad)))
                    .collect();
                let points = self.body.arm_points(a, &q, lift_m, Pose2::default())?;
                let pose = self.body.arm_pose(a, &q, lift_m, Pose2::default())?;
                let valid = idx
                    .iter()
                    .all(|&j| joints.get(j).is_some_and(|s| s.is_valid()));
                Some(json!({
                    "bus": self.body.arms()[a].bus,
                    "points": points,
                    "rotation": pose.tool_rotation,
                    "valid": valid,
                }))
            })
            .collect();
        let joint_figures: Vec<Value> = joints
            .iter()
            .map(|j| {
                json!({
                    "p": j.position_rad, "g": j.goal_rad, "t": j.temperature_c,
                    "c": j.current_a, "v": j.is_valid(), "on": j.torque_enabled == 1,
                    "f": j.flags,
                })
            })
            .collect();
        json!({
            "type": "state",
            "seq": state.seq,
            "t_ns": state.timestamp_ns,
            "safe": state.flags & STATE_FLAG_SAFE_STATE != 0,
            "stopped": state.flags & STATE_FLAG_OPERATOR_STOP != 0,
            "lift_m": lift_m,
            "arms": arms,
            "joints": joint_figures,
            "extra": extra,
        })
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::teleop::tests::a3_left_layout;

    #[test]
    fn the_model_and_the_frames_place_the_arm_where_its_kinematics_do() {
        let body = Body::from_description(&body::RobotDescription::nori_a3()).unwrap();
        let layout = a3_left_layout();
        let scene = Scene::new(body.clone(), layout);
        let model = scene.model();
        // Only the left arm is driven: only it is drawn.
        assert_eq!(model["arms"].as_array().unwrap().len(), 1);
        assert_eq!(model["arms"][0]["bus"], "left_arm");
        let cloud = model["arms"][0]["workspace"].as_array().unwrap();
        assert_eq!(cloud.len(), WORKSPACE_SAMPLES);
        // Every sampled point is within the arm's reach of its shoulder.
        let shoulder = body
            .arm_pose(0, &[0.0; 7], body.lift_start_m(), Pose2::default())
            .unwrap()
            .shoulder;
        let reach: f64 = body
            .arm_points(0, &[0.0; 7], 0.0, Pose2::default())
            .unwrap()
            .windows(2)
            .map(|w| {
                (0..3)
                    .map(|i| (w[1][i] - w[0][i]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
            .sum();
        for p in cloud {
            let d: f64 = (0..3)
                .map(|i| (p[i].as_f64().unwrap() - shoulder[i]).powi(2))
                .sum::<f64>()
                .sqrt();
            assert!(d <= reach + 1e-3, "{p} beyond the arm's reach {reach}");
        }
        assert_eq!(model["joints"][3]["name"], "left_elbow");
        assert_eq!(model["joints"][7]["role"], "gripper");

        let mut state = JointState {
            joint_count: 8,
            flags: STATE_FLAG_SAFE_STATE | STATE_FLAG_OPERATOR_STOP,
            ..JointState::default()
        };
        let q = [0.2, 0.1, -0.3, -1.0, 0.2, 0.3, 0.1];
        for (i, j) in state.joints[..8].iter_mut().enumerate() {
            j.valid = 1;
            j.position_rad = q.get(i).copied().unwrap_or(0.0) as f32;
            j.temperature_c = 40.0 + i as f32;
        }
        let frame = scene.frame(&state, 0.3, &());
        let tool = body.arm_pose(0, &q, 0.3, Pose2::default()).unwrap().tool;
        let drawn = &frame["arms"][0]["points"][8];
        for i in 0..3 {
            assert!(
                (drawn[i].as_f64().unwrap() - tool[i]).abs() < 1e-6,
                "{drawn} vs {tool:?}"
            );
        }
        assert_eq!(frame["safe"], true);
        assert_eq!(frame["stopped"], true);
        assert_eq!(frame["joints"][5]["t"], 45.0);
        assert_eq!(frame["arms"][0]["valid"], true);
        state.joints[2].valid = 0;
        assert_eq!(scene.frame(&state, 0.3, &())["arms"][0]["valid"], false);
    }
}
