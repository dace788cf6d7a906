//! Where an object is in a camera's picture for given joint angles, and the angles of two
//! joints that centre it: the simulated world's ground truth, for a scripted demonstrator (it
//! knows where it put the object) and for judging where a policy left the arm. Pure: the
//! description in, figures out; the same kinematics and camera model the rendering uses.

use crate::camera::Scene;
use crate::description::{CameraDescription, RobotDescription};
use nalgebra::{Matrix2, Vector2, Vector3};
use std::collections::BTreeMap;
use thiserror::Error;

/// Why an aim cannot be computed.
#[derive(Debug, Error, PartialEq)]
pub enum AimError {
    /// No camera of that name.
    #[error("no camera {0:?} in the description")]
    Camera(String),
    /// No object of that name, or one with neither a centre nor a box.
    #[error("no object {0:?} with a centre or a box in the description")]
    Object(String),
    /// A joint that is not one of the camera's arm.
    #[error("joint {joint:?} is not a joint of arm {arm:?} (its joints: {joints:?})")]
    Joint {
        /// The name asked for.
        joint: String,
        /// The camera's arm.
        arm: String,
        /// Its joints.
        joints: Vec<String>,
    },
    /// The camera is not on an arm: no joint moves it.
    #[error("camera {0:?} is on the body: no joint aims it")]
    Fixed(String),
    /// The object is behind the camera at the start.
    #[error("the object is behind camera {0:?} at the start pose")]
    Behind(String),
    /// The two joints cannot bring it to the centre within their ranges.
    #[error("the object cannot be centred with {joints:?} within their ranges (best offset {offset:.3})")]
    Unreachable {
        /// The joints turned.
        joints: [String; 2],
        /// The smallest offset reached (normalised, 1 = the picture's edge).
        offset: f64,
    },
}

/// One camera and one object of a robot description.
pub struct Aim {
    scene: Scene,
    camera: CameraDescription,
    target: Vector3<f64>,
    /// The camera's arm's joints, in the arm's order, with their ranges.
    joints: Vec<(String, f64, f64)>,
}

impl Aim {
    /// `camera` and `object` (by name) of `robot`.
    pub fn new(robot: &RobotDescription, camera: &str, object: &str) -> Result<Aim, AimError> {
        let cam = robot
            .camera
            .iter()
            .find(|c| c.name == camera)
            .ok_or_else(|| AimError::Camera(camera.into()))?
            .clone();
        let o = robot
            .object
            .iter()
            .find(|o| o.name == object)
            .ok_or_else(|| AimError::Object(object.into()))?;
        let target = match (o.center, o.min, o.max) {
            (Some(c), _, _) => Vector3::from(c),
            (None, Some(lo), Some(hi)) => (Vector3::from(lo) + Vector3::from(hi)) / 2.0,
            _ => return Err(AimError::Object(object.into())),
        };
        let bus = robot
            .bus
            .iter()
            .find(|b| b.name == cam.mount)
            .ok_or_else(|| AimError::Fixed(camera.into()))?;
        let arm = bus
            .arm
            .as_ref()
            .ok_or_else(|| AimError::Fixed(camera.into()))?;
        let joints = arm
            .joint
            .iter()
            .map(|j| {
                let name = bus
                    .servo
                    .iter()
                    .find(|s| s.id == j.servo)
                    .map_or_else(|| format!("servo{}", j.servo), |s| s.joint.clone());
                (name, j.lower_rad, j.upper_rad)
            })
            .collect();
        Ok(Aim {
            scene: Scene::new(robot),
            camera: cam,
            target,
            joints,
        })
    }

    fn angles(&self, at: &BTreeMap<String, f64>) -> Vec<f64> {
        self.joints
            .iter()
            .map(|(name, _, _)| at.get(name).copied().unwrap_or(0.0))
            .collect()
    }

    /// Where the object's centre is in the picture with the arm at `at` (joints not named
    /// at 0): (right, down), normalised so that ±1 is the picture's edge; `None` behind the
    /// camera.
    pub fn offset(&mut self, at: &BTreeMap<String, f64>) -> Option<[f64; 2]> {
        let q = self.angles(at);
        self.scene.pose_arm(&self.camera.mount, &q);
        let view = self.scene.view(&self.camera);
        let c = view.rotation.transpose() * (self.target - view.eye);
        if c.z <= 1e-6 {
            return None;
        }
        let half_fov = (view.fov_rad / 2.0).tan();
        let aspect = f64::from(view.width) / f64::from(view.height);
        Some([c.x / c.z / half_fov, c.y / c.z / half_fov * aspect])
    }

    /// Distance from the arm's tool point to the object's centre with the arm at `at`, m.
    pub fn tip_distance(&mut self, at: &BTreeMap<String, f64>) -> f64 {
        let q = self.angles(at);
        let tip = self.scene.pose_arm(&self.camera.mount, &q);
        (Vector3::from(tip) - self.target).norm()
    }

    /// The angles of `joints` (the others as in `start`) that put the object at the picture's
    /// centre, found from `start` by damped Gauss-Newton within the joints' ranges.
    pub fn centre(
        &mut self,
        start: &BTreeMap<String, f64>,
        joints: [&str; 2],
    ) -> Result<BTreeMap<String, f64>, AimError> {
        let mut ranges = [(0.0, 0.0); 2];
        for (k, name) in joints.iter().enumerate() {
            let (_, lo, hi) = self
                .joints
                .iter()
                .find(|(n, _, _)| n == name)
                .ok_or_else(|| AimError::Joint {
                    joint: name.to_string(),
                    arm: self.camera.mount.clone(),
                    joints: self.joints.iter().map(|j| j.0.clone()).collect(),
                })?;
            ranges[k] = (*lo, *hi);
        }
        let mut at = start.clone();
        let residual = |aim: &mut Aim, at: &BTreeMap<String, f64>| {
            aim.offset(at).map(|o| Vector2::new(o[0], o[1]))
        };
        let mut r =
            residual(self, &at).ok_or_else(|| AimError::Behind(self.camera.name.clone()))?;
        for _ in 0..100 {
            if r.norm() < 1e-4 {
                break;
            }
            let mut jac = Matrix2::zeros();
            for (k, name) in joints.iter().enumerate() {
                let h = 1e-5;
                let mut probe = at.clone();
                *probe.entry(name.to_string()).or_insert(0.0) += h;
                let rp = residual(self, &probe).unwrap_or(r);
                jac.set_column(k, &((rp - r) / h));
            }
            let step = (jac.transpose() * jac + Matrix2::identity() * 1e-6)
                .try_inverse()
                .map(|inv| -(inv * jac.transpose() * r))
                .unwrap_or_else(Vector2::zeros);
            // At most 0.2 rad a step: the picture is far from linear in the angles.
            let step = step * (0.2 / step.amax().max(0.2));
            let mut next = at.clone();
            for (k, name) in joints.iter().enumerate() {
                let v = next.entry(name.to_string()).or_insert(0.0);
                *v = (*v + step[k]).clamp(ranges[k].0, ranges[k].1);
            }
            match residual(self, &next) {
                Some(rn) if rn.norm() < r.norm() => {
                    at = next;
                    r = rn;
                }
                _ => break,
            }
        }
        if r.norm() > 0.02 {
            return Err(AimError::Unreachable {
                joints: joints.map(String::from),
                offset: r.norm(),
            });
        }
        Ok(at)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn start() -> BTreeMap<String, f64> {
        [("left_shoulder_pitch", -0.6), ("left_elbow", -0.8)]
            .into_iter()
            .map(|(k, v)| (k.to_string(), v))
            .collect()
    }

    #[test]
    fn the_red_ball_is_centred_by_two_joints_and_the_render_agrees() {
        let robot = RobotDescription::nori_a3();
        let mut aim = Aim::new(&robot, "left_wrist", "red ball").unwrap();
        let before = aim.offset(&start()).unwrap();
        assert!(
            before[0].hypot(before[1]) > 0.1,
            "off-centre at the start: {before:?}"
        );
        let centred = aim
            .centre(&start(), ["left_shoulder_roll", "left_elbow"])
            .unwrap();
        let after = aim.offset(&centred).unwrap();
        assert!(after[0].hypot(after[1]) < 0.02, "{after:?}");
        assert_eq!(
            centred["left_shoulder_pitch"], -0.6,
            "the other joints stay"
        );

        // The renderer, posed the same, draws the ball where the projection says (a small
        // ball, no fingers in the way: the centroid of its pixels, told red by hue so that the
        // shaded side counts too, is then its centre's image).
        let mut clear = robot.clone();
        for b in &mut clear.bus {
            if let Some(arm) = b.arm.as_mut() {
                arm.gripper = None;
            }
        }
        let ball = clear
            .object
            .iter_mut()
            .find(|o| o.name == "red ball")
            .unwrap();
        ball.radius_m = Some(0.008);
        let (w, h) = (320u32, 240u32);
        for c in &mut clear.camera {
            (c.width, c.height) = (w, h);
        }
        let cam = clear
            .camera
            .iter()
            .find(|c| c.name == "left_wrist")
            .unwrap()
            .clone();
        let mut seen_by = Aim::new(&clear, "left_wrist", "red ball").unwrap();
        let mut mid = start();
        mid.insert(
            "left_shoulder_roll".into(),
            centred["left_shoulder_roll"] / 2.0,
        );
        mid.insert("left_elbow".into(), (centred["left_elbow"] - 0.8) / 2.0);
        for at in [&start(), &mid, &centred] {
            let expect = seen_by.offset(at).unwrap();
            let q = seen_by.angles(at);
            seen_by.scene.pose_arm("left_arm", &q);
            seen_by.scene.refresh_items();
            let mut rgb = vec![0u8; (w * h * 3) as usize];
            seen_by.scene.render(&cam, &mut rgb);
            let (mut n, mut sx, mut sy) = (0.0, 0.0, 0.0);
            for (i, p) in rgb.chunks_exact(3).enumerate() {
                if u16::from(p[0]) > 2 * u16::from(p[1]) + 20
                    && u16::from(p[0]) > 2 * u16::from(p[2]) + 20
                {
                    n += 1.0;
                    sx += (i as u32 % w) as f64;
                    sy += (i as u32 / w) as f64;
                }
            }
            assert!(n > 3.0, "the ball is in the picture at {at:?}");
            let seen = [
                (sx / n + 0.5) / (f64::from(w) / 2.0) - 1.0,
                (sy / n + 0.5) / (f64::from(h) / 2.0) - 1.0,
            ];
            assert!(
                (seen[0] - expect[0]).abs() < 0.02 && (seen[1] - expect[1]).abs() < 0.02,
                "rendered at {seen:?}, projected at {expect:?}"
            );
        }
    }

    #[test]
    fn bad_names_and_an_object_out_of_reach_are_refused() {
        let robot = RobotDescription::nori_a3();
        assert_eq!(
            Aim::new(&robot, "tail", "red ball").err(),
            Some(AimError::Camera("tail".into()))
        );
        assert_eq!(
            Aim::new(&robot, "left_wrist", "unicorn").err(),
            Some(AimError::Object("unicorn".into()))
        );
        assert!(matches!(
            Aim::new(&robot, "head", "red ball").err(),
            Some(AimError::Fixed(_))
        ));
        let mut aim = Aim::new(&robot, "left_wrist", "red ball").unwrap();
        assert!(matches!(
            aim.centre(&start(), ["left_elbow", "right_elbow"]),
            Err(AimError::Joint { .. })
        ));
        let mut far = robot.clone();
        let ball = far
            .object
            .iter_mut()
            .find(|o| o.name == "red ball")
            .unwrap();
        ball.center = Some([0.5, -1.5, 0.74]);
        let mut aim = Aim::new(&far, "left_wrist", "red ball").unwrap();
        let r = aim.centre(&start(), ["left_shoulder_roll", "left_elbow"]);
        assert!(
            matches!(
                r,
                Err(AimError::Unreachable { .. }) | Err(AimError::Behind(_))
            ),
            "{r:?}"
        );
    }
}
