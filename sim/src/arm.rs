//! Arm mechanics: the serial chain's gravity torques and inertia, hard stops, obstacle contacts
//! and the compliant gripper.
//!
//! Each joint is integrated by its servo with the load this module computes from the whole
//! configuration: gravity of every distal link (and the payload), the inertia of the distal
//! masses about the joint axis, and contact torques mapped through the chain (τ = Jᵀ F).
//! Coriolis and off-diagonal inertia coupling are neglected: at servo speeds they are small
//! next to gravity and friction, and this keeps a step cheap enough for ≥ 1000× real time.

use crate::description::{ArmDescription, GraspObject, GripperDescription, Obstacle};
use nalgebra::{Matrix3, Unit, Vector3};

/// Stiffness of a mechanical hard stop, N·m/rad.
const STOP_STIFFNESS: f64 = 200.0;
/// Damping of a hard stop, N·m·s/rad.
const STOP_DAMPING: f64 = 2.0;
/// Damping of an obstacle contact, N·s/m.
const CONTACT_DAMPING: f64 = 50.0;

#[derive(Debug, Clone)]
struct Joint {
    axis: Unit<Vector3<f64>>,
    /// Cross-product matrix of the axis and its outer product, for Rodrigues' formula.
    axis_cross: Matrix3<f64>,
    axis_outer: Matrix3<f64>,
    /// `Some((k, sign))` when the axis is ±e_k: the rotation then mixes only two columns.
    coordinate_axis: Option<(usize, f64)>,
    origin: Vector3<f64>,
    mass: f64,
    com: Vector3<f64>,
    lower: f64,
    upper: f64,
}

/// One arm's chain, gripper and obstacles.
#[derive(Debug, Clone)]
pub struct Arm {
    joints: Vec<Joint>,
    base: Vector3<f64>,
    tip: Vector3<f64>,
    gravity: Vector3<f64>,
    /// Mass held at the tip, kg.
    pub payload: f64,
    /// Gripper, if fitted.
    pub gripper: Option<GripperDescription>,
    /// Obstacles in reach.
    pub obstacles: Vec<Obstacle>,
    // Scratch space, so a step allocates nothing.
    positions: Vec<Vector3<f64>>,
    axes: Vec<Vector3<f64>>,
    coms: Vec<Vector3<f64>>,
    inertia_age: usize,
}

/// Steps between refreshes of the configuration-dependent inertia.
pub const INERTIA_REFRESH_STEPS: usize = 10;

/// Loads the arm puts on its joint servos.
#[derive(Debug, Clone, Default)]
pub struct JointLoads {
    /// Torque opposing positive motion, N·m, per chain joint.
    pub torque: Vec<f64>,
    /// Inertia of the distal masses about each axis, kg·m².
    pub inertia: Vec<f64>,
}

impl Arm {
    /// Builds the arm from its description and the world gravity.
    pub fn new(d: &ArmDescription, gravity: [f64; 3]) -> Self {
        let joints: Vec<Joint> = d
            .joint
            .iter()
            .map(|j| {
                let axis = Unit::new_normalize(Vector3::from(j.axis));
                let coordinate_axis = (0..3)
                    .find(|&k| (axis[k].abs() - 1.0).abs() < 1e-12)
                    .map(|k| (k, axis[k].signum()));
                Joint {
                    coordinate_axis,
                    axis_cross: axis.cross_matrix(),
                    axis_outer: axis.into_inner() * axis.transpose(),
                    axis,
                    origin: Vector3::from(j.origin),
                    mass: j.mass_kg,
                    com: Vector3::from(j.com),
                    lower: j.lower_rad,
                    upper: j.upper_rad,
                }
            })
            .collect();
        let n = joints.len();
        Arm {
            joints,
            base: Vector3::from(d.base),
            tip: Vector3::from(d.tip),
            gravity: Vector3::from(gravity),
            payload: d.payload_kg,
            gripper: d.gripper.clone(),
            obstacles: d.obstacle.clone(),
            positions: vec![Vector3::zeros(); n + 1],
            axes: vec![Vector3::zeros(); n],
            coms: vec![Vector3::zeros(); n],
            inertia_age: 0,
        }
    }

    /// Joint `k`'s hard stops, rad (lower, upper); `None` past the chain.
    pub fn stops(&self, k: usize) -> Option<(f64, f64)> {
        self.joints.get(k).map(|j| (j.lower, j.upper))
    }

    /// Number of chain joints (the gripper excluded).
    pub fn dof(&self) -> usize {
        self.joints.len()
    }

    /// Forward kinematics: fills joint positions/axes/coms; returns the tip position.
    fn forward(&mut self, q: &[f64]) -> Vector3<f64> {
        let mut rot = Matrix3::identity();
        let mut p = self.base;
        let frames = self
            .positions
            .iter_mut()
            .zip(self.axes.iter_mut())
            .zip(self.coms.iter_mut());
        for ((j, &qi), ((position, axis), com)) in self.joints.iter().zip(q).zip(frames) {
            p += rot * j.origin;
            *axis = rot * j.axis.into_inner();
            match j.coordinate_axis {
                Some((k, sign)) => rotate_about_coordinate_axis(&mut rot, k, sign * qi),
                None => {
                    // Rodrigues: R = cos·I + sin·[k]× + (1 − cos)·k·kᵀ.
                    let (sin, cos) = qi.sin_cos();
                    rot *= Matrix3::from_diagonal_element(cos)
                        + j.axis_cross * sin
                        + j.axis_outer * (1.0 - cos);
                }
            }
            *position = p;
            *com = p + rot * j.com;
        }
        let tip = p + rot * self.tip;
        if let Some(last) = self.positions.last_mut() {
            *last = tip;
        }
        tip
    }

    /// The tool point at configuration `q`, world frame.
    pub fn tip_position(&mut self, q: &[f64]) -> [f64; 3] {
        let t = self.forward(q);
        [t.x, t.y, t.z]
    }

    /// The chain at configuration `q` for drawing it: the shoulder, each joint's position and
    /// the tool point, world frame, into `points`; returns the tool frame's rotation.
    pub fn chain(&mut self, q: &[f64], points: &mut Vec<[f64; 3]>) -> Matrix3<f64> {
        let mut rot = Matrix3::identity();
        let mut p = self.base;
        points.clear();
        points.push([p.x, p.y, p.z]);
        for (j, &qi) in self.joints.iter().zip(q) {
            p += rot * j.origin;
            points.push([p.x, p.y, p.z]);
            rot *= *nalgebra::Rotation3::from_axis_angle(&j.axis, qi).matrix();
        }
        let tip = p + rot * self.tip;
        points.push([tip.x, tip.y, tip.z]);
        rot
    }

    /// Computes the loads on each chain joint at configuration `q`, speeds `qd`.
    ///
    /// Gravity torque about joint `i` follows from suffix sums of the distal mass moments
    /// (Σm, Σm·c), so a step is O(n). The inertia of the distal masses changes only with the
    /// configuration, slowly next to a 1 ms step, and is refreshed every
    /// [`INERTIA_REFRESH_STEPS`] calls.
    pub fn loads(&mut self, q: &[f64], qd: &[f64], out: &mut JointLoads) {
        let n = self.joints.len();
        out.torque.resize(n, 0.0);
        out.inertia.resize(n, 0.0);
        let tip = self.forward(q);
        if self.inertia_age == 0 {
            self.refresh_inertia(tip, out);
        }
        self.inertia_age = (self.inertia_age + 1) % INERTIA_REFRESH_STEPS;
        let (mut mass, mut first) = (self.payload, tip * self.payload);
        for i in (0..n).rev() {
            mass += self.joints[i].mass;
            first += self.coms[i] * self.joints[i].mass;
            // Σ m·(c − p) about the joint origin, crossed with gravity, along the axis.
            let moment = first - self.positions[i] * mass;
            let gravity = self.axes[i].dot(&moment.cross(&self.gravity));
            let j = &self.joints[i];
            out.torque[i] = -(gravity + stop_torque(q[i], qd[i], j.lower, j.upper));
        }
        if !self.obstacles.is_empty() {
            self.add_contacts(qd, out);
        }
    }

    /// Inertia of the distal point masses about each axis: Σ m·|r⊥|² from the suffix sums of
    /// Σm, Σm·c and Σm·c·cᵀ (r = c − p).
    fn refresh_inertia(&self, tip: Vector3<f64>, out: &mut JointLoads) {
        let (mut mass, mut first, mut second) = (
            self.payload,
            tip * self.payload,
            tip * tip.transpose() * self.payload,
        );
        for i in (0..self.joints.len()).rev() {
            let (m, c) = (self.joints[i].mass, self.coms[i]);
            mass += m;
            first += c * m;
            second += c * c.transpose() * m;
            let (p, z) = (self.positions[i], self.axes[i]);
            let spread =
                second - p * first.transpose() - first * p.transpose() + p * p.transpose() * mass;
            out.inertia[i] = spread.trace() - z.dot(&(spread * z));
        }
    }

    /// Obstacle contacts at every joint origin and the tip: a penalty force along the sphere's
    /// normal, mapped to the joints proximal to the contact point.
    fn add_contacts(&self, qd: &[f64], out: &mut JointLoads) {
        let n = self.joints.len();
        for obstacle in &self.obstacles {
            let c = Vector3::from(obstacle.center);
            for point in 1..=n {
                let x = self.positions[point];
                let d = x - c;
                let dist = d.norm();
                let depth = obstacle.radius_m - dist;
                if depth <= 0.0 || dist < 1e-9 {
                    continue;
                }
                let normal = d / dist;
                // Point velocity from the proximal joints, for contact damping.
                let v: Vector3<f64> = (0..point.min(n))
                    .map(|k| self.axes[k].cross(&(x - self.positions[k])) * qd[k])
                    .sum();
                let force = normal
                    * (obstacle.stiffness_n_per_m * depth - CONTACT_DAMPING * v.dot(&normal))
                        .max(0.0);
                for k in 0..point.min(n) {
                    let r = x - self.positions[k];
                    out.torque[k] -= self.axes[k].dot(&r.cross(&force));
                }
            }
        }
    }
}

/// `rot ← rot · R_k(angle)` for the coordinate axis `k`: only the two columns orthogonal to the
/// axis change.
fn rotate_about_coordinate_axis(rot: &mut Matrix3<f64>, k: usize, angle: f64) {
    let (sin, cos) = angle.sin_cos();
    let (a, b) = ((k + 1) % 3, (k + 2) % 3);
    let (col_a, col_b) = (rot.column(a).into_owned(), rot.column(b).into_owned());
    rot.set_column(a, &(col_a * cos + col_b * sin));
    rot.set_column(b, &(col_b * cos - col_a * sin));
}

/// The torque a hard stop applies (positive pushes toward positive angles).
pub fn stop_torque(q: f64, qd: f64, lower: f64, upper: f64) -> f64 {
    if q < lower {
        STOP_STIFFNESS * (lower - q) - STOP_DAMPING * qd.min(0.0)
    } else if q > upper {
        -STOP_STIFFNESS * (q - upper) - STOP_DAMPING * qd.max(0.0)
    } else {
        0.0
    }
}

/// The torque opposing the gripper's motion: its stops and, past first contact, the fingers and
/// the object in series. Closing is toward lower angles, so the squeeze pushes positive.
pub fn gripper_load(g: &GripperDescription, q: f64, qd: f64) -> f64 {
    let mut tau = stop_torque(q, qd, g.lower_rad, g.upper_rad);
    if let Some(GraspObject {
        contact_rad,
        stiffness_nm_per_rad,
    }) = g.object
    {
        if q < contact_rad {
            let k = g.finger_stiffness_nm_per_rad * stiffness_nm_per_rad
                / (g.finger_stiffness_nm_per_rad + stiffness_nm_per_rad);
            tau += k * (contact_rad - q);
        }
    }
    -tau
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::description::RobotDescription;

    fn left_arm() -> Arm {
        let d = RobotDescription::nori_a3();
        Arm::new(d.bus("left_arm").unwrap().arm.as_ref().unwrap(), d.gravity)
    }

    /// The robot's kinematics (`body::kinematics`, what `nori-base` publishes) and the
    /// simulator's own chain (fast paths for coordinate axes, written separately) agree on
    /// every arm at random configurations, with the lift at the description's height and the
    /// base at the origin (the simulator's world frame).
    #[test]
    fn the_robots_kinematics_agree_with_the_simulators_arms() {
        let d = RobotDescription::nori_a3();
        let body = body::kinematics::Body::from_description(&d).unwrap();
        let lift = d.lift.as_ref().unwrap().start_m;
        let mut rng = crate::rng::Rng::new(7);
        for (k, chain) in body.arms().iter().enumerate() {
            let arm_d = d.bus(&chain.bus).unwrap().arm.as_ref().unwrap();
            let mut arm = Arm::new(arm_d, d.gravity);
            for _ in 0..200 {
                let q: Vec<f64> = arm_d
                    .joint
                    .iter()
                    .map(|j| rng.range(j.lower_rad, j.upper_rad))
                    .collect();
                let sim = arm.tip_position(&q);
                let robot = body.arm_pose(k, &q, lift, Default::default()).unwrap();
                let err = (0..3)
                    .map(|i| (sim[i] - robot.tool[i]).abs())
                    .fold(0.0, f64::max);
                assert!(
                    err < 1e-9,
                    "{}: {q:?}: {sim:?} vs {:?}",
                    chain.bus,
                    robot.tool
                );
            }
        }
    }

    #[test]
    fn hanging_arm_has_no_gravity_torque_and_reaches_55_cm() {
        let mut arm = left_arm();
        let q = [0.0; 7];
        let mut loads = JointLoads::default();
        arm.loads(&q, &[0.0; 7], &mut loads);
        assert!(
            loads.torque.iter().all(|t| t.abs() < 1e-9),
            "{:?}",
            loads.torque
        );
        let tip = arm.tip_position(&q);
        assert!((1.0 - tip[2] - 0.55).abs() < 1e-9, "reach {}", 1.0 - tip[2]);
    }

    #[test]
    fn horizontal_arm_loads_the_shoulder_with_its_weight() {
        let mut arm = left_arm();
        let mut q = [0.0; 7];
        q[0] = std::f64::consts::FRAC_PI_2; // shoulder pitch: arm horizontal
        let mut loads = JointLoads::default();
        arm.loads(&q, &[0.0; 7], &mut loads);
        // Σ m·g·r over the links (3.7 N·m for the A3 arm); the sign opposes lifting further.
        let expected: f64 = {
            let d = RobotDescription::nori_a3();
            let a = d.bus("left_arm").unwrap().arm.clone().unwrap();
            let mut z = 0.0;
            let mut sum = 0.0;
            for j in &a.joint {
                z += -j.origin[2];
                sum += j.mass_kg * (z - j.com[2]);
            }
            sum * 9.81
        };
        assert!(
            (loads.torque[0] - expected).abs() < 1e-6,
            "{} vs {expected}",
            loads.torque[0]
        );
        assert!(loads.inertia[0] > loads.inertia[3]);
        arm.payload = 1.5;
        let before = loads.torque[0];
        arm.loads(&q, &[0.0; 7], &mut loads);
        assert!((loads.torque[0] - before - 1.5 * 9.81 * 0.55).abs() < 1e-6);
    }

    #[test]
    fn coordinate_axis_fast_path_matches_rodrigues() {
        for k in 0..3 {
            for angle in [-2.0, -0.3, 0.0, 0.7, 3.0] {
                let mut fast = Matrix3::new(0.36, 0.48, -0.8, -0.8, 0.6, 0.0, 0.48, 0.64, 0.6);
                let general = fast
                    * nalgebra::Rotation3::from_axis_angle(&Vector3::ith_axis(k), angle)
                        .into_inner();
                rotate_about_coordinate_axis(&mut fast, k, angle);
                assert!((fast - general).norm() < 1e-12, "axis {k} angle {angle}");
            }
        }
    }

    #[test]
    fn obstacle_pushes_back() {
        let mut arm = left_arm();
        let q = [0.0; 7];
        let tip = arm.tip_position(&q);
        // Positive shoulder pitch swings the tip toward −x: a sphere there, overlapping by 1 cm.
        arm.obstacles.push(Obstacle {
            center: [tip[0] - 0.04, tip[1], tip[2]],
            radius_m: 0.05,
            stiffness_n_per_m: 10_000.0,
        });
        let mut loads = JointLoads::default();
        arm.loads(&q, &[0.0; 7], &mut loads);
        // Contact force +x at the tip, 0.55 m below the shoulder: it resists positive motion.
        assert!(loads.torque[0] > 10.0, "{:?}", loads.torque);
    }

    #[test]
    fn gripper_squeeze_is_stiffer_past_contact() {
        let mut g = RobotDescription::nori_a3()
            .bus("left_arm")
            .unwrap()
            .arm
            .clone()
            .unwrap()
            .gripper
            .unwrap();
        assert_eq!(gripper_load(&g, 0.3, 0.0), 0.0);
        g.object = Some(GraspObject {
            contact_rad: 0.5,
            stiffness_nm_per_rad: 3.0,
        });
        let a = gripper_load(&g, 0.45, 0.0);
        let b = gripper_load(&g, 0.40, 0.0);
        assert!(a < 0.0 && b < a, "load grows with squeeze: {a} {b}");
    }
}
