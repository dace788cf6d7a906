//! Sampling the state plane at a fixed frame rate (sans-IO: frames in, dataset frames out).
//!
//! The driver publishes a joint-state frame every cycle (200 Hz) and the supervisor a grip frame
//! per joint-state frame; a dataset frame is taken at each tick of the recording rate from the
//! newest *valid* sample of each joint.
//!
//! A joint whose reads all failed during the last frame period keeps its last read values, and
//! the frame says so: `observation.joint_valid` is 0 for it (1 when every value of the joint,
//! its grip force included for a gripper, is from this period). The driver's rule that a missing
//! servo is missing is carried into the dataset by the mask, not by NaN: LeRobot has no masking,
//! a NaN spreads through its statistics and every loss of an action chunk that touches it, and
//! the mask lets a policy or a filter drop what was held. An episode starts only once every
//! joint (and grip force) has been read ([`Sampler::unread`]), so nothing is ever invented.
//!
//! Cameras are sampled the same way: each frame takes the camera's newest image, and
//! `observation.camera_valid` says whether it was captured within the staleness bound of the
//! tick ([`crate::video::pick`]) or is the last one, held (the camera stalled or died: the
//! video keeps one frame per dataset frame, so the gap is marked, not skipped).
//!
//! The lift and the base are sampled from their controllers' state frames the same way: the
//! newest one that says something true (the lift homed, the base's wheels read) is taken, held
//! and marked invalid when older than the frame period.

use crate::features::{BodyAxis, Features, Vector};
use crate::video::{pick, Pick};
use telemetry::frames::{GripFrame, JointSample, JointState};
use telemetry::motion::{BaseState, LiftState, BASE_FLAG_WHEELS_UNREAD, LIFT_READY};

/// One dataset frame: the vector features, each in [`Features`] order.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Joint position goals sent by the driver, rad.
    pub action: Vec<f32>,
    /// Joint positions, rad.
    pub state: Vec<f32>,
    /// Joint speeds, rad/s.
    pub velocity: Vec<f32>,
    /// Motor currents, A.
    pub current: Vec<f32>,
    /// Temperature registers, °C.
    pub temperature: Vec<f32>,
    /// Supply voltages, V.
    pub voltage: Vec<f32>,
    /// Normalised grip force per gripper.
    pub grip_force: Vec<f32>,
    /// Per joint: 1 if read in this frame period, 0 if its last read is held.
    pub valid: Vec<f32>,
    /// Per camera: 1 if its image is fresh, 0 if its last image is held.
    pub camera_valid: Vec<f32>,
    /// The base's pose (x, y, heading) when the base is recorded.
    pub odometry: Vec<f32>,
}

impl Frame {
    /// A frame of NaN for `features`, every joint invalid (what a reader fills).
    pub fn missing(features: &Features) -> Frame {
        let nan = |v| vec![f32::NAN; features.width(v)];
        Frame {
            action: nan(Vector::Action),
            state: nan(Vector::State),
            velocity: nan(Vector::Velocity),
            current: nan(Vector::Current),
            temperature: nan(Vector::Temperature),
            voltage: nan(Vector::Voltage),
            grip_force: nan(Vector::GripForce),
            valid: vec![0.0; features.width(Vector::Valid)],
            camera_valid: vec![0.0; features.width(Vector::CameraValid)],
            odometry: if features.has_base() {
                nan(Vector::Odometry)
            } else {
                Vec::new()
            },
        }
    }

    /// One vector feature.
    pub fn vector(&self, v: Vector) -> &[f32] {
        match v {
            Vector::Action => &self.action,
            Vector::State => &self.state,
            Vector::Velocity => &self.velocity,
            Vector::Current => &self.current,
            Vector::Temperature => &self.temperature,
            Vector::Voltage => &self.voltage,
            Vector::GripForce => &self.grip_force,
            Vector::Valid => &self.valid,
            Vector::CameraValid => &self.camera_valid,
            Vector::Odometry => &self.odometry,
        }
    }

    /// One vector feature, to fill.
    pub fn vector_mut(&mut self, v: Vector) -> &mut Vec<f32> {
        match v {
            Vector::Action => &mut self.action,
            Vector::State => &mut self.state,
            Vector::Velocity => &mut self.velocity,
            Vector::Current => &mut self.current,
            Vector::Temperature => &mut self.temperature,
            Vector::Voltage => &mut self.voltage,
            Vector::GripForce => &mut self.grip_force,
            Vector::Valid => &mut self.valid,
            Vector::CameraValid => &mut self.camera_valid,
            Vector::Odometry => &mut self.odometry,
        }
    }

    /// Count of joints (and body axes) whose last read is held in this frame.
    pub fn missing_joints(&self) -> usize {
        self.valid.iter().filter(|&&v| v < 0.5).count()
    }

    /// Count of cameras whose last image is held in this frame.
    pub fn held_images(&self) -> usize {
        self.camera_valid.iter().filter(|&&v| v < 0.5).count()
    }
}

/// Keeps the newest valid sample of every recorded joint and gripper; takes frames from them.
#[derive(Debug, Clone)]
pub struct Sampler {
    features: Features,
    /// Newest valid sample per recorded joint, with its frame's timestamp.
    joints: Vec<Option<(u64, JointSample)>>,
    /// Joint-frame index of each gripper (in [`Features::grippers`] order).
    gripper_joints: Vec<usize>,
    /// Index of each gripper among the recorded joints.
    gripper_rows: Vec<usize>,
    /// Newest grip force per gripper, with its timestamp.
    grips: Vec<Option<(u64, f32)>>,
    max_age_ns: u64,
    /// Capture time of each camera's newest image.
    cameras: Vec<Option<u64>>,
    camera_stale_ns: u64,
    /// Newest state of the homed lift (when recorded).
    lift: Option<LiftState>,
    /// Newest state of the base with its wheels read (when recorded).
    base: Option<BaseState>,
}

impl Sampler {
    /// A sampler for `features`; a sample older than `max_age_ns` at a tick is missing, and so
    /// is a camera image captured longer than `max_age_ns` before it unless
    /// [`Sampler::with_camera_staleness`] says otherwise.
    pub fn new(features: Features, max_age_ns: u64) -> Sampler {
        let gripper_joints = features
            .grippers()
            .into_iter()
            .map(|i| features.joints[i].frame_index)
            .collect::<Vec<_>>();
        Sampler {
            joints: vec![None; features.joints.len()],
            grips: vec![None; gripper_joints.len()],
            gripper_rows: features.grippers(),
            gripper_joints,
            cameras: vec![None; features.cameras.len()],
            camera_stale_ns: max_age_ns,
            features,
            max_age_ns,
            lift: None,
            base: None,
        }
    }

    /// Images captured up to `stale_ns` before a tick are fresh (a camera's frame period and
    /// its delivery latency add to the recording's period).
    pub fn with_camera_staleness(mut self, stale_ns: u64) -> Sampler {
        self.camera_stale_ns = stale_ns;
        self
    }

    /// Takes in that camera `index` (in [`Features::cameras`] order) delivered an image
    /// captured at `capture_ns`.
    pub fn on_camera(&mut self, index: usize, capture_ns: u64) {
        if let Some(slot) = self.cameras.get_mut(index) {
            *slot = Some(slot.map_or(capture_ns, |t| t.max(capture_ns)));
        }
    }

    /// The features frames are taken for.
    pub fn features(&self) -> &Features {
        &self.features
    }

    /// Takes in one joint-state frame (in order, every frame).
    pub fn on_state(&mut self, frame: &JointState) {
        let samples = frame.joints();
        for (slot, joint) in self.joints.iter_mut().zip(&self.features.joints) {
            if let Some(s) = samples.get(joint.frame_index).filter(|s| s.is_valid()) {
                *slot = Some((frame.timestamp_ns, *s));
            }
        }
    }

    /// Takes in one grip frame.
    pub fn on_grip(&mut self, frame: &GripFrame) {
        let count = (frame.gripper_count as usize).min(frame.grippers.len());
        for g in &frame.grippers[..count] {
            if g.valid != 1 {
                continue;
            }
            if let Some(k) = self
                .gripper_joints
                .iter()
                .position(|&j| j == g.joint as usize)
            {
                self.grips[k] = Some((frame.timestamp_ns, g.force));
            }
        }
    }

    /// Takes in one lift state frame: kept when the lift is homed and its height known.
    pub fn on_lift(&mut self, s: &LiftState) {
        if s.state == LIFT_READY && s.height_m.is_finite() {
            self.lift = Some(*s);
        }
    }

    /// Takes in one base state frame: kept when it is from a read of the wheels.
    pub fn on_base(&mut self, s: &BaseState) {
        if s.flags & BASE_FLAG_WHEELS_UNREAD == 0 && s.timestamp_ns > 0 {
            self.base = Some(*s);
        }
    }

    /// What has never been read (joint names, `<gripper> grip force`): a frame is taken only
    /// once this is empty.
    pub fn unread(&self) -> Vec<String> {
        let joints = &self.features.joints;
        let unread_joints = (self.joints.iter().zip(joints))
            .filter(|(slot, _)| slot.is_none())
            .map(|(_, j)| j.name.clone());
        let grippers = self.features.grippers();
        let unread_grips = (self.grips.iter().zip(&grippers))
            .filter(|(slot, _)| slot.is_none())
            .map(|(_, &i)| format!("{} grip force", joints[i].name));
        let unseen_cameras = (self.cameras.iter().zip(&self.features.cameras))
            .filter(|(slot, _)| slot.is_none())
            .map(|(_, c)| format!("camera {}", c.name));
        let unread_lift = (self.features.has_lift() && self.lift.is_none())
            .then(|| "lift height (is nori-lift running and homed?)".to_string());
        let unread_base = (self.features.has_base() && self.base.is_none())
            .then(|| "base (is nori-base running with the wheels read?)".to_string());
        unread_joints
            .chain(unread_grips)
            .chain(unseen_cameras)
            .chain(unread_lift)
            .chain(unread_base)
            .collect()
    }

    /// The frame at `now_ns` (CLOCK_MONOTONIC, the driver's clock); `None` while something was
    /// never read ([`Sampler::unread`]).
    pub fn frame(&self, now_ns: u64) -> Option<Frame> {
        let n = self.features.joints.len();
        let wide = self.features.width(Vector::State);
        let mut f = Frame {
            action: Vec::with_capacity(wide),
            state: Vec::with_capacity(wide),
            velocity: Vec::with_capacity(n),
            current: Vec::with_capacity(n),
            temperature: Vec::with_capacity(n),
            voltage: Vec::with_capacity(n),
            grip_force: Vec::with_capacity(self.grips.len()),
            valid: Vec::with_capacity(wide),
            camera_valid: Vec::with_capacity(self.cameras.len()),
            odometry: Vec::new(),
        };
        for &newest in &self.cameras {
            f.camera_valid
                .push(match pick(newest, now_ns, self.camera_stale_ns) {
                    Pick::Fresh => 1.0,
                    Pick::Held => 0.0,
                    Pick::Nothing => return None,
                });
        }
        let fresh = |t: u64| now_ns.saturating_sub(t) <= self.max_age_ns;
        for slot in &self.joints {
            let (t, s) = (*slot)?;
            f.action.push(s.goal_rad);
            f.state.push(s.position_rad);
            f.velocity.push(s.velocity_rad_s);
            f.current.push(s.current_a);
            f.temperature.push(s.temperature_c);
            f.voltage.push(s.voltage_v);
            f.valid.push(if fresh(t) { 1.0 } else { 0.0 });
        }
        for (slot, &gripper) in self.grips.iter().zip(&self.gripper_rows) {
            let (t, force) = (*slot)?;
            f.grip_force.push(force);
            if !fresh(t) {
                f.valid[gripper] = 0.0;
            }
        }
        for &axis in &self.features.body {
            let (t, state, action) = match axis {
                BodyAxis::LiftHeight => {
                    let l = self.lift?;
                    let goal = if l.goal_m.is_finite() {
                        l.goal_m
                    } else {
                        l.height_m
                    };
                    (l.timestamp_ns, l.height_m, goal)
                }
                BodyAxis::BaseLinear => {
                    let b = self.base?;
                    (b.timestamp_ns, b.linear_m_s, b.commanded_linear_m_s)
                }
                BodyAxis::BaseAngular => {
                    let b = self.base?;
                    (b.timestamp_ns, b.angular_rad_s, b.commanded_angular_rad_s)
                }
            };
            f.state.push(state);
            f.action.push(action);
            f.valid.push(if fresh(t) { 1.0 } else { 0.0 });
        }
        if self.features.has_base() {
            let b = self.base?;
            f.odometry
                .extend([b.x_m as f32, b.y_m as f32, b.theta_rad as f32]);
        }
        Some(f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use telemetry::frames::{GripSample, JointInfo, JointLayout, JointRole};

    fn features() -> Features {
        let mut l = JointLayout {
            joint_count: 3,
            bus_count: 1,
            ..JointLayout::default()
        };
        for (i, (n, r)) in [
            ("elbow", JointRole::Joint),
            ("wheel", JointRole::Wheel),
            ("gripper", JointRole::Gripper),
        ]
        .iter()
        .enumerate()
        {
            let mut j = JointInfo {
                role: *r as u8,
                ..JointInfo::default()
            };
            j.set_name(n);
            l.joints[i] = j;
        }
        Features::from_layout(&l)
    }

    fn state(t: u64, valid: [bool; 3], base: f32) -> JointState {
        let mut s = JointState {
            timestamp_ns: t,
            joint_count: 3,
            ..JointState::default()
        };
        for (i, v) in valid.iter().enumerate() {
            s.joints[i] = JointSample {
                position_rad: base + i as f32,
                goal_rad: base + 10.0 + i as f32,
                current_a: 0.5,
                valid: u8::from(*v),
                ..JointSample::default()
            };
        }
        s
    }

    fn grip(t: u64, force: f32) -> GripFrame {
        let mut g = GripFrame {
            timestamp_ns: t,
            gripper_count: 1,
            ..GripFrame::default()
        };
        g.grippers[0] = GripSample {
            joint: 2,
            valid: 1,
            force,
            ..GripSample::default()
        };
        g
    }

    #[test]
    fn a_frame_takes_the_newest_valid_sample_of_each_joint() {
        let mut s = Sampler::new(features(), 40);
        s.on_state(&state(100, [true, true, true], 1.0));
        s.on_state(&state(110, [true, true, false], 2.0));
        s.on_grip(&grip(110, 0.3));
        let f = s.frame(120).unwrap();
        assert_eq!(
            f.state,
            [2.0, 3.0],
            "elbow from the newest frame, the gripper (joint 2) from the older"
        );
        assert_eq!(
            f.action,
            [12.0, 13.0],
            "the goal the driver sent, beside its position"
        );
        assert_eq!(f.current, [0.5, 0.5]);
        assert_eq!(f.valid, [1.0, 1.0]);
        assert_eq!(f.grip_force, [0.3]);
    }

    #[test]
    fn no_frame_until_everything_was_read_once() {
        let mut s = Sampler::new(features(), 40);
        assert_eq!(s.unread(), ["elbow", "gripper", "gripper grip force"]);
        assert_eq!(s.frame(0), None);
        s.on_state(&state(100, [true, true, false], 1.0));
        assert_eq!(s.unread(), ["gripper", "gripper grip force"]);
        assert_eq!(s.frame(100), None);
        s.on_state(&state(110, [true, true, true], 1.0));
        s.on_grip(&grip(110, 0.1));
        assert!(s.unread().is_empty());
        assert!(s.frame(110).is_some());
    }

    #[test]
    fn a_camera_image_is_fresh_within_its_bound_held_after_it_and_awaited_before_the_first() {
        let camera = crate::features::CameraMeta {
            name: "head".into(),
            width: 64,
            height: 48,
            pix_fmt: "yuvj420p".into(),
        };
        let mut s =
            Sampler::new(features().with_cameras(vec![camera]), 40).with_camera_staleness(100);
        s.on_state(&state(1_000, [true, true, true], 1.0));
        s.on_grip(&grip(1_000, 0.1));
        assert_eq!(s.unread(), ["camera head"]);
        assert_eq!(s.frame(1_000), None, "no image yet: nothing to hold");
        s.on_camera(0, 950);
        assert_eq!(s.frame(1_000).unwrap().camera_valid, [1.0]);
        // 100 ns after its capture still fresh (the joints' 40 ns bound does not apply).
        assert_eq!(s.frame(1_050).unwrap().camera_valid, [1.0]);
        let held = s.frame(1_051).unwrap();
        assert_eq!(held.camera_valid, [0.0]);
        assert_eq!(held.held_images(), 1);
        // An older image arriving late does not make the camera look fresher.
        s.on_camera(0, 900);
        assert_eq!(s.frame(1_051).unwrap().camera_valid, [0.0]);
        s.on_camera(0, 1_040);
        assert_eq!(s.frame(1_060).unwrap().camera_valid, [1.0]);
        s.on_camera(7, 5_000);
        assert_eq!(
            s.frame(1_060).unwrap().camera_valid.len(),
            1,
            "unknown index ignored"
        );
    }

    #[test]
    fn a_joint_without_a_valid_read_in_the_last_period_keeps_its_last_read_marked_invalid() {
        let mut s = Sampler::new(features(), 40);
        s.on_state(&state(100, [true, true, true], 1.0));
        s.on_grip(&grip(100, 0.2));
        s.on_state(&state(150, [true, true, false], 2.0));
        s.on_grip(&grip(150, 0.4));
        let f = s.frame(150).unwrap();
        assert_eq!(f.state[0], 2.0);
        assert_eq!(
            (f.state[1], f.action[1]),
            (3.0, 13.0),
            "the gripper's read of t = 100 held (50 ns ago > 40)"
        );
        assert_eq!(f.valid, [1.0, 0.0]);
        assert_eq!(f.missing_joints(), 1);
        assert!(f.vector(Vector::State).iter().all(|x| x.is_finite()));
        // A gripper whose position is fresh but whose grip force is stale is not valid either.
        s.on_state(&state(190, [true, true, true], 3.0));
        let f = s.frame(191).unwrap();
        assert_eq!(f.grip_force, [0.4]);
        assert_eq!(f.valid, [1.0, 0.0], "grip force 41 ns old");
        assert_eq!(s.frame(189).unwrap().valid, [1.0, 1.0]);
    }

    #[test]
    fn the_lift_and_base_follow_the_joints_once_homed_and_read_and_are_marked_when_stale() {
        let mut s = Sampler::new(features().with_body(true, true), 40);
        s.on_state(&state(100, [true, true, true], 1.0));
        s.on_grip(&grip(100, 0.2));
        let unhomed = LiftState {
            timestamp_ns: 100,
            height_m: f32::NAN,
            state: telemetry::motion::LIFT_HOMING,
            ..LiftState::default()
        };
        s.on_lift(&unhomed);
        let unread_wheels = BaseState {
            timestamp_ns: 100,
            flags: BASE_FLAG_WHEELS_UNREAD,
            ..BaseState::default()
        };
        s.on_base(&unread_wheels);
        assert_eq!(s.unread().len(), 2, "{:?}", s.unread());
        assert_eq!(
            s.frame(100),
            None,
            "nothing invented for the lift or the base"
        );
        s.on_lift(&LiftState {
            timestamp_ns: 100,
            height_m: 0.4,
            goal_m: f32::NAN,
            state: LIFT_READY,
            ..LiftState::default()
        });
        s.on_base(&BaseState {
            timestamp_ns: 100,
            x_m: 1.5,
            y_m: -0.25,
            theta_rad: 0.5,
            linear_m_s: 0.18,
            angular_rad_s: -0.1,
            commanded_linear_m_s: 0.2,
            commanded_angular_rad_s: -0.125,
            ..BaseState::default()
        });
        let f = s.frame(120).unwrap();
        assert_eq!(f.state, [1.0, 3.0, 0.4, 0.18, -0.1]);
        assert_eq!(
            f.action,
            [11.0, 13.0, 0.4, 0.2, -0.125],
            "the lift holds its height with no goal; the base's action is what drove the wheels"
        );
        assert_eq!(f.odometry, [1.5, -0.25, 0.5]);
        assert_eq!(f.valid, [1.0; 5]);
        s.on_lift(&LiftState {
            timestamp_ns: 130,
            height_m: 0.41,
            goal_m: 0.5,
            state: LIFT_READY,
            ..LiftState::default()
        });
        // The lift losing its link keeps its last good height, held.
        s.on_lift(&LiftState {
            timestamp_ns: 160,
            height_m: 0.0,
            state: telemetry::motion::LIFT_LINK_LOST,
            ..LiftState::default()
        });
        s.on_state(&state(160, [true, true, true], 1.0));
        s.on_grip(&grip(160, 0.2));
        let f = s.frame(160).unwrap();
        assert_eq!((f.state[2], f.action[2]), (0.41, 0.5));
        assert_eq!(f.valid, [1.0, 1.0, 1.0, 0.0, 0.0], "base 60 ns old");
        assert_eq!(f.missing_joints(), 2);
    }

    #[test]
    fn grip_force_is_matched_to_its_gripper_by_joint_index() {
        let mut s = Sampler::new(features(), 40);
        let mut g = GripFrame {
            timestamp_ns: 100,
            gripper_count: 2,
            ..GripFrame::default()
        };
        g.grippers[0] = GripSample {
            joint: 7,
            valid: 1,
            force: 0.9,
            ..GripSample::default()
        };
        g.grippers[1] = GripSample {
            joint: 2,
            valid: 1,
            force: 0.25,
            ..GripSample::default()
        };
        s.on_grip(&g);
        s.on_state(&state(100, [true, true, true], 1.0));
        let f = s.frame(120).unwrap();
        assert_eq!(
            (f.grip_force.as_slice(), f.valid[1]),
            ([0.25].as_slice(), 1.0)
        );
        let stale = s.frame(141).unwrap();
        assert_eq!(
            (stale.grip_force[0], stale.valid[1]),
            (0.25, 0.0),
            "held, marked"
        );
    }
}
