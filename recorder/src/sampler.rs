//! Sampling the state plane at a fixed frame rate (sans-IO: frames in, dataset frames out).
//!
//! The driver publishes a joint-state frame every cycle (200 Hz) and the supervisor a grip frame
//! per joint-state frame; a dataset frame is taken at each tick of the recording rate from the
//! newest *valid* sample of each joint. A joint whose reads all failed during the last frame
//! period is recorded as NaN (missing), never as an old value: the driver's rule that a missing
//! servo is missing, carried into the dataset.

use crate::features::{Features, Vector};
use telemetry::frames::{GripFrame, JointSample, JointState};

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
}

impl Frame {
    /// A frame of NaN for `features`.
    pub fn missing(features: &Features) -> Frame {
        let n = features.joints.len();
        let g = features.grippers().len();
        Frame {
            action: vec![f32::NAN; n],
            state: vec![f32::NAN; n],
            velocity: vec![f32::NAN; n],
            current: vec![f32::NAN; n],
            temperature: vec![f32::NAN; n],
            voltage: vec![f32::NAN; n],
            grip_force: vec![f32::NAN; g],
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
        }
    }

    /// Count of missing (NaN) joint positions in this frame.
    pub fn missing_joints(&self) -> usize {
        self.state.iter().filter(|x| x.is_nan()).count()
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
    /// Newest grip force per gripper, with its timestamp.
    grips: Vec<Option<(u64, f32)>>,
    max_age_ns: u64,
}

impl Sampler {
    /// A sampler for `features`; a sample older than `max_age_ns` at a tick is missing.
    pub fn new(features: Features, max_age_ns: u64) -> Sampler {
        let gripper_joints = features
            .grippers()
            .into_iter()
            .map(|i| features.joints[i].frame_index)
            .collect::<Vec<_>>();
        Sampler {
            joints: vec![None; features.joints.len()],
            grips: vec![None; gripper_joints.len()],
            gripper_joints,
            features,
            max_age_ns,
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

    /// The frame at `now_ns` (CLOCK_MONOTONIC, the driver's clock).
    pub fn frame(&self, now_ns: u64) -> Frame {
        let mut f = Frame::missing(&self.features);
        let fresh = |t: u64| now_ns.saturating_sub(t) <= self.max_age_ns;
        for (i, slot) in self.joints.iter().enumerate() {
            if let Some((t, s)) = slot.filter(|(t, _)| fresh(*t)) {
                let _ = t;
                f.action[i] = s.goal_rad;
                f.state[i] = s.position_rad;
                f.velocity[i] = s.velocity_rad_s;
                f.current[i] = s.current_a;
                f.temperature[i] = s.temperature_c;
                f.voltage[i] = s.voltage_v;
            }
        }
        for (k, slot) in self.grips.iter().enumerate() {
            if let Some((_, force)) = slot.filter(|(t, _)| fresh(*t)) {
                f.grip_force[k] = force;
            }
        }
        f
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

    #[test]
    fn a_frame_takes_the_newest_valid_sample_of_each_joint() {
        let mut s = Sampler::new(features(), 40);
        s.on_state(&state(100, [true, true, true], 1.0));
        s.on_state(&state(110, [true, true, false], 2.0));
        let f = s.frame(120);
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
    }

    #[test]
    fn a_joint_without_a_valid_read_in_the_last_period_is_missing() {
        let mut s = Sampler::new(features(), 40);
        s.on_state(&state(100, [true, true, true], 1.0));
        s.on_state(&state(150, [true, true, false], 2.0));
        let f = s.frame(150);
        assert_eq!(f.state[0], 2.0);
        assert!(
            f.state[1].is_nan() && f.action[1].is_nan(),
            "gripper last read 50 ns ago > 40"
        );
        assert_eq!(f.missing_joints(), 1);
        assert!(f.grip_force[0].is_nan(), "no grip frame yet");
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
        assert_eq!(s.frame(120).grip_force, [0.25]);
        assert!(s.frame(141).grip_force[0].is_nan(), "stale");
    }
}
