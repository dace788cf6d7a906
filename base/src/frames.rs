//! The whole body's frames (`nori/body/frames`), pure: each arm's shoulder and tool in the
//! frame the base's odometry started in, from the newest joint-state frame, the lift's height
//! and the base's pose, by the robot description's kinematics (`body::kinematics`).
//!
//! An arm's frame is valid only when every one of its joints was read in the joint-state frame
//! and the lift's height is known (homed, and its state no older than [`LIFT_FRESH_NS`]): a tool
//! is never placed from a held reading or a guessed height.

use body::kinematics::{Body, Pose2};
use telemetry::frames::{JointLayout, JointState};
use telemetry::motion::{ArmFrame, BaseState, BodyFrames, LiftState, LIFT_READY};

/// The lift's state is used while at most this old (its controller publishes every 10 ms).
pub const LIFT_FRESH_NS: u64 = 200_000_000;

/// Most joints in one arm's chain.
const MAX_CHAIN: usize = 8;

/// Makes the body's frames from what the state plane says.
#[derive(Debug, Clone)]
pub struct BodyFramer {
    body: Body,
    /// Per arm, each chain joint's index in the driver's joint-state frame (`None`: the
    /// driver does not drive it).
    indices: Vec<[Option<usize>; MAX_CHAIN]>,
    lift: Option<LiftState>,
    seq: u64,
}

impl BodyFramer {
    /// A framer for `body`'s arms (at most two are published), with no layout yet.
    pub fn new(body: Body) -> BodyFramer {
        let arms = body.arms().len().min(2);
        BodyFramer {
            body,
            indices: vec![[None; MAX_CHAIN]; arms],
            lift: None,
            seq: 0,
        }
    }

    /// Finds each chain joint in the driver's layout, by name.
    pub fn set_layout(&mut self, layout: &JointLayout) {
        for (chain, indices) in self.body.arms().iter().zip(&mut self.indices) {
            *indices = [None; MAX_CHAIN];
            for (slot, name) in indices.iter_mut().zip(&chain.joint_names) {
                *slot = layout.joint_names().position(|n| n == name);
            }
        }
    }

    /// Takes the lift's newest state.
    pub fn on_lift(&mut self, lift: &LiftState) {
        self.lift = Some(*lift);
    }

    /// The lift's height if known at `now_ns`.
    fn lift_m(&self, now_ns: u64) -> Option<f64> {
        self.lift
            .filter(|l| l.state == LIFT_READY && l.height_m.is_finite())
            .filter(|l| now_ns.saturating_sub(l.timestamp_ns) <= LIFT_FRESH_NS)
            .map(|l| f64::from(l.height_m))
    }

    /// The frames of joint-state frame `joints` with the base at `base`'s pose, at `now_ns`.
    pub fn frame(&mut self, joints: &JointState, base: &BaseState, now_ns: u64) -> BodyFrames {
        self.seq += 1;
        let lift = self.lift_m(now_ns);
        let pose = Pose2 {
            x: base.x_m,
            y: base.y_m,
            theta: base.theta_rad,
        };
        let mut out = BodyFrames {
            seq: self.seq,
            timestamp_ns: joints.timestamp_ns,
            x_m: base.x_m,
            y_m: base.y_m,
            theta_rad: base.theta_rad,
            lift_m: lift.unwrap_or(f64::NAN),
            arm_count: self.indices.len() as u32,
            ..BodyFrames::default()
        };
        let samples = joints.joints();
        for (arm, (indices, slot)) in self.indices.iter().zip(&mut out.arms).enumerate() {
            let mut q = [0.0f64; MAX_CHAIN];
            let n = self.body.arms()[arm].joint_names.len().min(MAX_CHAIN);
            let read = (indices[..n].iter().zip(&mut q)).all(|(index, angle)| {
                match index.and_then(|i| samples.get(i)).filter(|s| s.is_valid()) {
                    Some(s) => {
                        *angle = f64::from(s.position_rad);
                        true
                    }
                    None => false,
                }
            });
            let (Some(h), true) = (lift, read) else {
                continue;
            };
            if let Some(p) = self.body.arm_pose(arm, &q[..n], h, pose) {
                let f = |v: f64| v as f32;
                *slot = ArmFrame {
                    shoulder: p.shoulder.map(f),
                    tool: p.tool.map(f),
                    tool_rotation: p.tool_rotation.map(f),
                    valid: 1,
                    reserved: [0; 3],
                };
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use body::RobotDescription;
    use telemetry::frames::{JointInfo, JointSample};

    /// The driver's layout of the A3 (both arms, then the wheels) and a frame with every joint
    /// read at `q` (the left elbow at `elbow`).
    fn a3() -> (BodyFramer, JointLayout, JointState) {
        let d = RobotDescription::nori_a3();
        let mut layout = JointLayout::default();
        let mut state = JointState::default();
        let names: Vec<String> = d
            .bus
            .iter()
            .flat_map(|b| b.servo.iter().map(|s| s.joint.clone()))
            .collect();
        for (i, name) in names.iter().enumerate() {
            let mut j = JointInfo::default();
            j.set_name(name);
            layout.joints[i] = j;
            state.joints[i] = JointSample {
                valid: 1,
                ..JointSample::default()
            };
        }
        layout.joint_count = names.len() as u32;
        state.joint_count = names.len() as u32;
        state.timestamp_ns = 5_000;
        let mut framer = BodyFramer::new(Body::from_description(&d).unwrap());
        framer.set_layout(&layout);
        (framer, layout, state)
    }

    fn lift(h: f32, t: u64) -> LiftState {
        LiftState {
            timestamp_ns: t,
            height_m: h,
            state: LIFT_READY,
            ..LiftState::default()
        }
    }

    #[test]
    fn each_arm_is_placed_from_its_joints_the_lift_and_the_base() {
        let (mut framer, _, mut state) = a3();
        let body = Body::from_description(&RobotDescription::nori_a3()).unwrap();
        state.joints[3].position_rad = -1.0; // left_elbow
        framer.on_lift(&lift(0.5, 1_000));
        let base = BaseState {
            x_m: 0.5,
            y_m: -0.2,
            theta_rad: 0.3,
            ..BaseState::default()
        };
        let f = framer.frame(&state, &base, 2_000);
        assert_eq!((f.seq, f.arm_count, f.timestamp_ns), (1, 2, 5_000));
        assert_eq!((f.x_m, f.lift_m), (0.5, 0.5));
        let pose = Pose2 {
            x: 0.5,
            y: -0.2,
            theta: 0.3,
        };
        let mut q = [0.0; 7];
        q[3] = -1.0;
        let left = body.arm_pose(0, &q, 0.5, pose).unwrap();
        let right = body.arm_pose(1, &[0.0; 7], 0.5, pose).unwrap();
        assert_eq!(f.arms[0].valid, 1);
        assert_eq!(f.arms[0].tool, left.tool.map(|v| v as f32));
        assert_eq!(f.arms[1].tool, right.tool.map(|v| v as f32));
        assert_eq!(f.arms[1].shoulder, right.shoulder.map(|v| v as f32));
    }

    #[test]
    fn no_arm_is_placed_from_a_missing_joint_or_an_unknown_height() {
        let (mut framer, layout, mut state) = a3();
        let base = BaseState::default();
        // No lift state yet.
        let f = framer.frame(&state, &base, 2_000);
        assert!(f.lift_m.is_nan());
        assert_eq!((f.arms[0].valid, f.arms[1].valid), (0, 0));
        // Homed, then its state too old.
        framer.on_lift(&lift(0.3, 1_000));
        assert_eq!(
            framer.frame(&state, &base, 1_000 + LIFT_FRESH_NS).arms[0].valid,
            1
        );
        let stale = framer.frame(&state, &base, 1_001 + LIFT_FRESH_NS);
        assert_eq!((stale.arms[0].valid, stale.arms[1].valid), (0, 0));
        // Not homed: no height.
        framer.on_lift(&LiftState {
            state: telemetry::motion::LIFT_HOMING,
            ..lift(0.3, 1_000)
        });
        assert_eq!(framer.frame(&state, &base, 1_000).arms[0].valid, 0);
        // A right-arm joint not read: the right arm only.
        framer.on_lift(&lift(0.3, 1_000));
        state.joints[10].valid = 0;
        let f = framer.frame(&state, &base, 1_000);
        assert_eq!((f.arms[0].valid, f.arms[1].valid), (1, 0));
        // A driver without the right arm's bus: the right arm is never placed.
        let mut left_only = layout;
        left_only.joint_count = 8;
        framer.set_layout(&left_only);
        state.joints[10].valid = 1;
        state.joint_count = 8;
        let f = framer.frame(&state, &base, 1_000);
        assert_eq!((f.arms[0].valid, f.arms[1].valid), (1, 0));
    }
}
