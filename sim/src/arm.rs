//! Arm mechanics: the serial chain's gravity torques and inertia, hard stops, obstacle contacts
//! and the compliant gripper.
//!
//! Each joint is integrated by its servo with the load this module computes from the whole
//! configuration: gravity of every distal link (and the payload), the inertia of the distal
//! masses about the joint axis, and contact torques mapped through the chain (τ = Jᵀ F).
//! Coriolis and off-diagonal inertia coupling are neglected: at servo speeds they are small
//! next to gravity and friction, and this keeps a step cheap enough for ≥ 1000× real time.

use crate::description::{ArmDescription, GraspObject, GripperDescription, Obstacle};
use nalgebra::{Rotation3, Unit, Vector3};

/// Stiffness of a mechanical hard stop, N·m/rad.
const STOP_STIFFNESS: f64 = 200.0;
/// Damping of a hard stop, N·m·s/rad.
const STOP_DAMPING: f64 = 2.0;
/// Damping of an obstacle contact, N·s/m.
const CONTACT_DAMPING: f64 = 50.0;

#[derive(Debug, Clone)]
struct Joint {
    axis: Unit<Vector3<f64>>,
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
}

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
            .map(|j| Joint {
                axis: Unit::new_normalize(Vector3::from(j.axis)),
                origin: Vector3::from(j.origin),
                mass: j.mass_kg,
                com: Vector3::from(j.com),
                lower: j.lower_rad,
                upper: j.upper_rad,
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
        }
    }

    /// Number of chain joints (the gripper excluded).
    pub fn dof(&self) -> usize {
        self.joints.len()
    }

    /// Forward kinematics: fills joint positions/axes/coms; returns the tip position.
    fn forward(&mut self, q: &[f64]) -> Vector3<f64> {
        let mut rot = Rotation3::identity();
        let mut p = self.base;
        for (i, j) in self.joints.iter().enumerate() {
            p += rot * j.origin;
            let axis = rot * j.axis.into_inner();
            rot *= Rotation3::from_axis_angle(&j.axis, q[i]);
            self.positions[i] = p;
            self.axes[i] = axis;
            self.coms[i] = p + rot * j.com;
        }
        let tip = p + rot * self.tip;
        self.positions[self.joints.len()] = tip;
        tip
    }

    /// The tool point at configuration `q`, world frame.
    pub fn tip_position(&mut self, q: &[f64]) -> [f64; 3] {
        let t = self.forward(q);
        [t.x, t.y, t.z]
    }

    /// Computes the loads on each chain joint at configuration `q`, speeds `qd`.
    pub fn loads(&mut self, q: &[f64], qd: &[f64], out: &mut JointLoads) {
        let n = self.joints.len();
        out.torque.resize(n, 0.0);
        out.inertia.resize(n, 0.0);
        let tip = self.forward(q);
        for i in 0..n {
            let (p, z) = (self.positions[i], self.axes[i]);
            let mut tau = 0.0;
            let mut inertia = 0.0;
            let mut add_mass = |m: f64, at: Vector3<f64>| {
                let r = at - p;
                // Torque of gravity about the axis, and the point mass's inertia about it.
                tau += z.dot(&r.cross(&(self.gravity * m)));
                let radial = r - z * z.dot(&r);
                inertia += m * radial.norm_squared();
            };
            for k in i..n {
                add_mass(self.joints[k].mass, self.coms[k]);
            }
            if self.payload > 0.0 {
                add_mass(self.payload, tip);
            }
            let j = &self.joints[i];
            tau += stop_torque(q[i], qd[i], j.lower, j.upper);
            out.torque[i] = -tau;
            out.inertia[i] = inertia;
        }
        self.add_contacts(qd, out);
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
        // Σ m·g·r over the links: about 1.1 N·m for this arm; the sign opposes lifting further.
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
