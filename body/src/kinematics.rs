//! Whole-body forward kinematics from the robot description: where each arm's shoulder and
//! tool are on the floor of the room, given its joint angles, the lift's height and the base's
//! pose (its odometry, or the simulator's truth).
//!
//! Frames: the description gives each arm's shoulder (`base`) in the base's frame (x forward,
//! y left, z up from the floor, the base's centre at the origin) with the lift standing at its
//! start height (`lift.start-m`: the height the description was drawn at); the lift carries both
//! arms on one cross-member, so a height `h` raises every shoulder by `h − start-m`. A joint's
//! origin is in its parent's frame, its axis in its own frame, as in the simulator's arm. The
//! base's pose `(x, y, θ)` places the base's frame in the room (a rotation `θ` about the
//! vertical). Pure; [`Body::tool`] allocates nothing.

use crate::description::RobotDescription;
use nalgebra::{Matrix3, Rotation3, Unit, UnitQuaternion, Vector3};
use thiserror::Error;

/// A description the kinematics cannot use.
#[derive(Debug, Error, PartialEq)]
pub enum KinematicsError {
    /// An arm joint names a servo its bus does not have.
    #[error("bus {bus}: arm joint driven by servo {servo}, which the bus does not have")]
    UnknownServo {
        /// The bus.
        bus: String,
        /// The servo id.
        servo: u8,
    },
}

/// The base on the floor: position, m, and heading, rad (counter-clockwise from +x).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Pose2 {
    /// m.
    pub x: f64,
    /// m.
    pub y: f64,
    /// rad.
    pub theta: f64,
}

#[derive(Debug, Clone)]
struct ChainJoint {
    axis: Unit<Vector3<f64>>,
    origin: Vector3<f64>,
    hard_stops: (f64, f64),
}

/// One arm's kinematic chain.
#[derive(Debug, Clone)]
pub struct ArmChain {
    /// The bus that drives it (`left_arm`, `right_arm`).
    pub bus: String,
    /// Its joints' names, base outward (the names of the driver's layout).
    pub joint_names: Vec<String>,
    joints: Vec<ChainJoint>,
    shoulder: Vector3<f64>,
    tip: Vector3<f64>,
}

/// Where an arm is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArmPose {
    /// The shoulder (the chain's first joint's parent frame), m, in the room.
    pub shoulder: [f64; 3],
    /// The tool point, m, in the room.
    pub tool: [f64; 3],
    /// The tool frame's orientation in the room, a unit quaternion `[w, x, y, z]`.
    pub tool_rotation: [f64; 4],
}

impl ArmChain {
    /// Each joint's axis (in its own frame) and origin (in its parent's), base outward.
    pub(crate) fn axes_and_origins(
        &self,
    ) -> impl Iterator<Item = (Unit<Vector3<f64>>, Vector3<f64>)> + '_ {
        self.joints.iter().map(|j| (j.axis, j.origin))
    }

    /// The tool point in the last joint's frame, m.
    pub(crate) fn tip(&self) -> Vector3<f64> {
        self.tip
    }

    /// Each joint's mechanical hard stops `(lower, upper)`, rad, base outward.
    pub fn hard_stops(&self) -> Vec<(f64, f64)> {
        self.joints.iter().map(|j| j.hard_stops).collect()
    }
}

/// One frame of the body in its parent's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Link {
    /// Where its origin is in the parent's frame, m.
    pub translation: [f64; 3],
    /// Its orientation in the parent's frame, a unit quaternion `[w, x, y, z]`.
    pub rotation: [f64; 4],
}

impl Link {
    fn translation(t: Vector3<f64>) -> Link {
        Link {
            translation: t.into(),
            rotation: [1.0, 0.0, 0.0, 0.0],
        }
    }
}

/// The body's chains and the lift's reference height.
#[derive(Debug, Clone)]
pub struct Body {
    arms: Vec<ArmChain>,
    lift_start_m: f64,
}

impl Body {
    /// The arms of `d` (each bus with an arm, in description order).
    pub fn from_description(d: &RobotDescription) -> Result<Body, KinematicsError> {
        let mut arms = Vec::new();
        for bus in &d.bus {
            let Some(arm) = &bus.arm else { continue };
            let mut joint_names = Vec::with_capacity(arm.joint.len());
            for j in &arm.joint {
                let servo = bus.servo.iter().find(|s| s.id == j.servo).ok_or_else(|| {
                    KinematicsError::UnknownServo {
                        bus: bus.name.clone(),
                        servo: j.servo,
                    }
                })?;
                joint_names.push(servo.joint.clone());
            }
            arms.push(ArmChain {
                bus: bus.name.clone(),
                joint_names,
                joints: arm
                    .joint
                    .iter()
                    .map(|j| ChainJoint {
                        axis: Unit::new_normalize(Vector3::from(j.axis)),
                        origin: Vector3::from(j.origin),
                        hard_stops: (j.lower_rad, j.upper_rad),
                    })
                    .collect(),
                shoulder: Vector3::from(arm.base),
                tip: Vector3::from(arm.tip),
            });
        }
        Ok(Body {
            arms,
            lift_start_m: d.lift.as_ref().map_or(0.0, |l| l.start_m),
        })
    }

    /// The lift's height at which the description places the shoulders, m.
    pub fn lift_start_m(&self) -> f64 {
        self.lift_start_m
    }

    /// The arms, in description order.
    pub fn arms(&self) -> &[ArmChain] {
        &self.arms
    }

    /// Per arm, where each of its joints is, base outward, in a list `index_of` finds names in
    /// (the driver's layout): `None` for an arm one of whose joints the list does not have.
    pub fn arm_indices(&self, index_of: impl Fn(&str) -> Option<usize>) -> Vec<Option<Vec<usize>>> {
        self.arms
            .iter()
            .map(|a| a.joint_names.iter().map(|n| index_of(n)).collect())
            .collect()
    }

    /// `chain`'s shoulder in the base's frame with the lift at `lift_m`.
    pub(crate) fn shoulder_at(&self, chain: &ArmChain, lift_m: f64) -> Vector3<f64> {
        chain.shoulder + Vector3::new(0.0, 0.0, lift_m - self.lift_start_m)
    }

    /// The points a drawing of arm `arm` joins, in the room, at joint angles `q` (as
    /// [`Body::arm_pose`]): its shoulder, each joint's origin base outward, and the tool point.
    pub fn arm_points(
        &self,
        arm: usize,
        q: &[f64],
        lift_m: f64,
        base: Pose2,
    ) -> Option<Vec<[f64; 3]>> {
        let chain = self.arms.get(arm)?;
        let heading = Rotation3::from_axis_angle(&Vector3::z_axis(), base.theta);
        let place = |p: Vector3<f64>| {
            let r = heading * p + Vector3::new(base.x, base.y, 0.0);
            [r.x, r.y, r.z]
        };
        let mut p = self.shoulder_at(chain, lift_m);
        let mut points = Vec::with_capacity(chain.joints.len() + 2);
        points.push(place(p));
        let mut rot = Matrix3::identity();
        for (k, j) in chain.joints.iter().enumerate() {
            p += rot * j.origin;
            points.push(place(p));
            rot *= *Rotation3::from_axis_angle(&j.axis, q.get(k).copied().unwrap_or(0.0)).matrix();
        }
        points.push(place(p + rot * chain.tip));
        Some(points)
    }

    /// Arm `arm`'s frame tree at joint angles `q` (as [`Body::arm_pose`]), base outward: the
    /// shoulder in the lift's frame (the base's frame raised by the lift's travel from its start
    /// height), each joint in its parent's (its origin, and its angle about its axis), and the
    /// tool point in the last joint's. Composed, they give [`Body::arm_pose`]'s tool; a viewer
    /// draws the arm from them (the black box's `/tf`).
    pub fn arm_links(&self, arm: usize, q: &[f64]) -> Option<Vec<Link>> {
        let chain = self.arms.get(arm)?;
        let mut links = Vec::with_capacity(chain.joints.len() + 2);
        links.push(Link::translation(chain.shoulder));
        for (k, j) in chain.joints.iter().enumerate() {
            let angle = q.get(k).copied().unwrap_or(0.0);
            let r = UnitQuaternion::from_axis_angle(&j.axis, angle);
            links.push(Link {
                translation: j.origin.into(),
                rotation: [r.w, r.i, r.j, r.k],
            });
        }
        links.push(Link::translation(chain.tip));
        Some(links)
    }

    /// Arm `arm` at joint angles `q` (rad, base outward; missing angles count as 0), the lift at
    /// `lift_m` and the base at `base`; `None` for an arm the body does not have.
    pub fn arm_pose(&self, arm: usize, q: &[f64], lift_m: f64, base: Pose2) -> Option<ArmPose> {
        let chain = self.arms.get(arm)?;
        let heading = Rotation3::from_axis_angle(&Vector3::z_axis(), base.theta);
        let place = |p: Vector3<f64>| heading * p + Vector3::new(base.x, base.y, 0.0);
        let shoulder = self.shoulder_at(chain, lift_m);
        let mut rot = Matrix3::identity();
        let mut p = shoulder;
        for (k, j) in chain.joints.iter().enumerate() {
            p += rot * j.origin;
            let angle = q.get(k).copied().unwrap_or(0.0);
            rot *= *Rotation3::from_axis_angle(&j.axis, angle).matrix();
        }
        let tool = p + rot * chain.tip;
        let tool_rotation = UnitQuaternion::from_rotation_matrix(
            &Rotation3::from_matrix_unchecked(*heading.matrix() * rot),
        );
        let (s, t) = (place(shoulder), place(tool));
        let q = tool_rotation.quaternion();
        Some(ArmPose {
            shoulder: [s.x, s.y, s.z],
            tool: [t.x, t.y, t.z],
            tool_rotation: [q.w, q.i, q.j, q.k],
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn a3() -> Body {
        Body::from_description(&RobotDescription::nori_a3()).unwrap()
    }

    fn close(a: [f64; 3], b: [f64; 3], tol: f64) -> bool {
        a.iter().zip(&b).all(|(x, y)| (x - y).abs() < tol)
    }

    #[test]
    fn the_a3_has_two_arms_named_as_the_driver_names_their_joints() {
        let body = a3();
        let names: Vec<&str> = body.arms().iter().map(|a| a.bus.as_str()).collect();
        assert_eq!(names, ["left_arm", "right_arm"]);
        assert_eq!(body.arms()[0].joint_names.len(), 7);
        assert_eq!(body.arms()[0].joint_names[3], "left_elbow");
        assert_eq!(body.arms()[1].joint_names[0], "right_shoulder_pitch");
    }

    #[test]
    fn an_arms_links_composed_put_its_tool_where_its_pose_does() {
        let body = a3();
        let q = [0.3, -0.2, 0.5, -1.1, 0.4, 0.2, -0.6];
        let lift = 0.31;
        for arm in 0..2 {
            let links = body.arm_links(arm, &q).unwrap();
            assert_eq!(links.len(), 9, "shoulder, 7 joints, tool");
            // The lift's frame: the base's, raised by the lift's travel.
            let mut p = Vector3::new(0.0, 0.0, lift - body.lift_start_m());
            let mut r = UnitQuaternion::identity();
            for l in &links {
                p += r * Vector3::from(l.translation);
                let [w, x, y, z] = l.rotation;
                r *= UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z));
            }
            let pose = body.arm_pose(arm, &q, lift, Pose2::default()).unwrap();
            assert!(close([p.x, p.y, p.z], pose.tool, 1e-12), "{p:?} {pose:?}");
            let q_ = r.quaternion();
            let same = [q_.w, q_.i, q_.j, q_.k]
                .iter()
                .zip(&pose.tool_rotation)
                .all(|(a, b)| (a - b).abs() < 1e-9)
                || [q_.w, q_.i, q_.j, q_.k]
                    .iter()
                    .zip(&pose.tool_rotation)
                    .all(|(a, b)| (a + b).abs() < 1e-9);
            assert!(same, "{r:?} against {:?}", pose.tool_rotation);
        }
        assert!(body.arm_links(2, &q).is_none());
    }

    #[test]
    fn an_arms_drawing_runs_from_its_shoulder_through_each_joint_to_its_tool() {
        let body = a3();
        let q = [0.3, -0.2, 0.5, -1.1, 0.4, 0.2, -0.6];
        let base = Pose2 {
            x: 0.4,
            y: -0.2,
            theta: 0.7,
        };
        for arm in 0..2 {
            let pose = body.arm_pose(arm, &q, 0.25, base).unwrap();
            let points = body.arm_points(arm, &q, 0.25, base).unwrap();
            assert_eq!(points.len(), 9);
            assert!(close(points[0], pose.shoulder, 1e-12));
            assert!(close(points[8], pose.tool, 1e-12));
            // The links keep their lengths whatever the angles.
            let zero = body
                .arm_points(arm, &[0.0; 7], 0.0, Pose2::default())
                .unwrap();
            for k in 0..8 {
                let d = |p: &[[f64; 3]]| {
                    (0..3)
                        .map(|i| (p[k + 1][i] - p[k][i]).powi(2))
                        .sum::<f64>()
                        .sqrt()
                };
                assert!((d(&points) - d(&zero)).abs() < 1e-12, "link {k}");
            }
        }
        assert!(body.arm_points(2, &q, 0.0, base).is_none());
    }

    #[test]
    fn the_lift_raises_both_shoulders_and_the_base_carries_them() {
        let body = a3();
        let q = [0.0; 7];
        let home = body.arm_pose(0, &q, 0.3, Pose2::default()).unwrap();
        assert!(close(home.shoulder, [0.0, 0.18, 1.0], 1e-12), "{home:?}");
        let up = body.arm_pose(0, &q, 0.5, Pose2::default()).unwrap();
        assert!(close(up.shoulder, [0.0, 0.18, 1.2], 1e-12));
        assert!(
            (up.tool[2] - home.tool[2] - 0.2).abs() < 1e-12,
            "the tool rises with it"
        );
        // The base 1 m ahead, turned a quarter left: the left shoulder is now behind the centre
        // (its +y becomes −x) and the tool turns with the base.
        let base = Pose2 {
            x: 1.0,
            y: 0.0,
            theta: std::f64::consts::FRAC_PI_2,
        };
        let moved = body.arm_pose(0, &q, 0.3, base).unwrap();
        assert!(
            close(moved.shoulder, [1.0 - 0.18, 0.0, 1.0], 1e-12),
            "{moved:?}"
        );
        let (t, h) = (moved.tool, home.tool);
        assert!(
            close(t, [1.0 - h[1], h[0], h[2]], 1e-12),
            "{moved:?} vs {home:?}"
        );
        let [w, _, _, z] = moved.tool_rotation;
        let [w0, _, _, z0] = home.tool_rotation;
        // Hanging straight down with q = 0, the tool frame is the base's: a yaw of 90°.
        assert!((w0 - 1.0).abs() < 1e-12 && z0.abs() < 1e-12, "{home:?}");
        assert!((w - 0.5f64.sqrt()).abs() < 1e-12 && (z - 0.5f64.sqrt()).abs() < 1e-12);
        assert_eq!(body.arm_pose(2, &q, 0.3, base), None);
    }

    #[test]
    fn a_chain_naming_a_servo_its_bus_lacks_is_refused() {
        let mut d = RobotDescription::nori_a3();
        d.bus[0].arm.as_mut().unwrap().joint[2].servo = 99;
        assert_eq!(
            Body::from_description(&d).unwrap_err(),
            KinematicsError::UnknownServo {
                bus: "left_arm".into(),
                servo: 99
            }
        );
    }
}
