//! The body's frames for a viewer: each arm's shoulder, joints and tool from the joint states,
//! the lift's height and the base's odometry, as Foxglove's transform tree (`/tf`), so Foxglove's
//! 3D panel draws the arms moving without a plugin. Pure: frames in, transforms out.
//!
//! The tree: `odom` → `base_link` (the base's odometry) → `lift` (the base's frame raised by the
//! lift's travel from the description's start height) → `<arm bus>` (its shoulder) → each joint,
//! by the driver's name → `<arm bus>_tool`.

use crate::channel::Transform;
use body::kinematics::{Body, Link};
use telemetry::frames::{JointLayout, JointState};
use telemetry::motion::{BaseState, LiftState};

/// What the tree is computed from: the body, how the driver's layout places its joints,
/// and the lift's and the base's newest states.
#[derive(Debug, Clone)]
pub struct FrameTree {
    body: Body,
    /// Per arm: the joint-state index of each of its joints, base outward (`None`: the driver
    /// does not drive them all, so the arm is not drawn).
    arms: Vec<Option<Vec<usize>>>,
    lift_m: f64,
    base: [f64; 3],
}

impl FrameTree {
    /// The frames of `body`, its arms undrawn until a layout names their joints.
    pub fn new(body: Body) -> FrameTree {
        FrameTree {
            arms: vec![None; body.arms().len()],
            lift_m: body.lift_start_m(),
            base: [0.0; 3],
            body,
        }
    }

    /// The driver's layout: which joint-state entry is which arm joint.
    pub fn layout(&mut self, layout: &JointLayout) {
        self.arms = self.body.arm_indices(|n| layout.joint_index(n));
    }

    /// The lift's newest state (a height that is not finite is not taken).
    pub fn lift(&mut self, s: &LiftState) {
        if s.height_m.is_finite() {
            self.lift_m = f64::from(s.height_m);
        }
    }

    /// The base's newest odometry (a pose that is not finite is not taken).
    pub fn base(&mut self, s: &BaseState) {
        let pose = [s.x_m, s.y_m, s.theta_rad];
        if pose.iter().all(|v| v.is_finite()) {
            self.base = pose;
        }
    }

    /// Every frame at the joint positions of `state` (a reading that is not finite counts as
    /// 0: a viewer draws the arm, `/joint_states` says which readings to trust).
    pub fn frames(&self, state: &JointState) -> Vec<Transform> {
        let [x, y, theta] = self.base;
        let (s, c) = (theta * 0.5).sin_cos();
        let mut out = vec![
            frame("odom", "base_link", [x, y, 0.0], [c, 0.0, 0.0, s]),
            frame(
                "base_link",
                "lift",
                [0.0, 0.0, self.lift_m - self.body.lift_start_m()],
                [1.0, 0.0, 0.0, 0.0],
            ),
        ];
        let joints = state.joints();
        for (a, (chain, idx)) in self.body.arms().iter().zip(&self.arms).enumerate() {
            let Some(idx) = idx else { continue };
            let q: Vec<f64> = idx
                .iter()
                .map(|&j| {
                    let p = joints.get(j).map_or(0.0, |s| f64::from(s.position_rad));
                    if p.is_finite() {
                        p
                    } else {
                        0.0
                    }
                })
                .collect();
            let Some(links) = self.body.arm_links(a, &q) else {
                continue;
            };
            let tool = format!("{}_tool", chain.bus);
            let names = std::iter::once(&chain.bus)
                .chain(&chain.joint_names)
                .chain(std::iter::once(&tool));
            let mut parent = "lift";
            for (name, link) in names.zip(links) {
                out.push(Transform {
                    parent: parent.to_string(),
                    child: name.clone(),
                    link,
                });
                parent = name;
            }
        }
        out
    }
}

fn frame(parent: &str, child: &str, translation: [f64; 3], rotation: [f64; 4]) -> Transform {
    Transform {
        parent: parent.into(),
        child: child.into(),
        link: Link {
            translation,
            rotation,
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use body::kinematics::Pose2;
    use body::RobotDescription;
    use nalgebra::{Quaternion, UnitQuaternion, Vector3};
    use std::collections::BTreeMap;

    /// The A3's layout as the driver names it: its buses' servos in description order.
    fn a3_layout() -> JointLayout {
        let d = RobotDescription::nori_a3();
        let names: Vec<(String, usize)> = d
            .bus
            .iter()
            .enumerate()
            .flat_map(|(b, bus)| bus.servo.iter().map(move |s| (s.joint.clone(), b)))
            .collect();
        let mut l = JointLayout::default();
        for (k, (name, bus)) in names.iter().enumerate() {
            l.joints[k].set_name(name);
            l.joints[k].bus = *bus as u8;
        }
        l.joint_count = names.len() as u32;
        l
    }

    /// Composes the tree from `odom` down to `leaf`.
    fn in_odom(frames: &[Transform], leaf: &str) -> [f64; 3] {
        let by_child: BTreeMap<&str, &Transform> =
            frames.iter().map(|f| (f.child.as_str(), f)).collect();
        let mut chain = vec![];
        let mut at = leaf;
        while let Some(f) = by_child.get(at) {
            chain.push(*f);
            at = &f.parent;
        }
        assert_eq!(at, "odom", "the tree's root");
        let (mut p, mut r) = (Vector3::zeros(), UnitQuaternion::identity());
        for f in chain.iter().rev() {
            p += r * Vector3::from(f.link.translation);
            let [w, x, y, z] = f.link.rotation;
            r *= UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z));
        }
        [p.x, p.y, p.z]
    }

    #[test]
    fn the_tree_puts_each_tool_where_the_kinematics_do_at_the_lift_and_base_pose() {
        let body = Body::from_description(&RobotDescription::nori_a3()).unwrap();
        let layout = a3_layout();
        let mut f = FrameTree::new(body.clone());
        let mut state = JointState {
            joint_count: layout.joint_count,
            ..Default::default()
        };
        assert_eq!(f.frames(&state).len(), 2, "no arm before the layout");
        f.layout(&layout);
        let q = [0.3, -0.2, 0.5, -1.1, 0.4, 0.2, -0.6];
        for (a, chain) in body.arms().iter().enumerate() {
            for (k, name) in chain.joint_names.iter().enumerate() {
                let j = layout.joint_index(name).unwrap();
                state.joints[j].position_rad = (q[k] * if a == 0 { 1.0 } else { -1.0 }) as f32;
            }
        }
        f.lift(&LiftState {
            height_m: 0.42,
            ..Default::default()
        });
        f.base(&BaseState {
            x_m: 1.5,
            y_m: -0.5,
            theta_rad: 0.8,
            ..Default::default()
        });
        let frames = f.frames(&state);
        assert_eq!(frames.len(), 2 + 2 * 9);
        for (a, chain) in body.arms().iter().enumerate() {
            let qa: Vec<f64> = chain
                .joint_names
                .iter()
                .map(|n| f64::from(state.joints[layout.joint_index(n).unwrap()].position_rad))
                .collect();
            let base = Pose2 {
                x: 1.5,
                y: -0.5,
                theta: 0.8,
            };
            let pose = body.arm_pose(a, &qa, 0.42, base).unwrap();
            let tool = in_odom(&frames, &format!("{}_tool", chain.bus));
            for (got, want) in tool.iter().zip(pose.tool) {
                assert!(
                    (got - want).abs() < 1e-5,
                    "{tool:?} against {:?}",
                    pose.tool
                );
            }
        }
        // A lift or base reading that is not finite is not taken.
        f.lift(&LiftState {
            height_m: f32::NAN,
            ..Default::default()
        });
        f.base(&BaseState {
            x_m: f64::INFINITY,
            ..Default::default()
        });
        assert_eq!(f.frames(&state), frames);
    }
}
