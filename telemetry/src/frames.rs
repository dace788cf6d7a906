//! Frames of the state plane: fixed-size `#[repr(C)]` layouts shared zero-copy over iceoryx2.
//!
//! Type name, size and alignment are part of a service's identity, so every process uses these
//! definitions and a layout change bumps the version in the type name.

use iceoryx2::prelude::ZeroCopySend;

/// Joints a frame can carry (the A3 has 18 bus joints: 2 × (7 + gripper) + 2 wheels).
pub const MAX_JOINTS: usize = 24;
const _: () = assert!(MAX_JOINTS <= 32, "the goal mask is a u32");

/// One joint in one cycle, in calibrated physical units.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
pub struct JointSample {
    /// Joint angle, rad (speed-mode joints: wheel angle modulo a turn).
    pub position_rad: f32,
    /// Joint speed, rad/s.
    pub velocity_rad_s: f32,
    /// Output duty, −1..1 (`Present_Load`).
    pub load: f32,
    /// Supply voltage at the servo, V.
    pub voltage_v: f32,
    /// Temperature register, °C (an integer on Feetech servos).
    pub temperature_c: f32,
    /// Motor current, A (`Present_Current` × 6.5 mA).
    pub current_a: f32,
    /// Goal sent this cycle, rad (rad/s for speed-mode joints), after clamping.
    pub goal_rad: f32,
    /// Servo status bits (`feetech::ServoStatus`).
    pub status: u8,
    /// 1 when this cycle's read succeeded; 0 means missing: every other field is meaningless.
    pub valid: u8,
    /// 1 when the driver has torque enabled on this joint.
    pub torque_enabled: u8,
    /// Reserved, zero.
    pub reserved: u8,
}

impl JointSample {
    /// Whether this cycle's read of the joint succeeded.
    pub fn is_valid(&self) -> bool {
        self.valid == 1
    }
}

/// The bus driver's output, one per control cycle.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("nori::JointState/1")]
pub struct JointState {
    /// Cycle number since the driver started (restarts at 0 with the driver).
    pub seq: u64,
    /// CLOCK_MONOTONIC, ns, when the feedback read completed.
    pub timestamp_ns: u64,
    /// Cycles that overran their period since the driver started.
    pub deadline_misses: u64,
    /// Joints in use (the first `joint_count` entries of `joints`).
    pub joint_count: u32,
    /// [`STATE_FLAG_SAFE_STATE`] and friends.
    pub flags: u32,
    /// Per joint, in the driver configuration's order.
    pub joints: [JointSample; MAX_JOINTS],
}

/// The driver has applied its safe state.
pub const STATE_FLAG_SAFE_STATE: u32 = 1;

impl Default for JointState {
    fn default() -> Self {
        JointState {
            seq: 0,
            timestamp_ns: 0,
            deadline_misses: 0,
            joint_count: 0,
            flags: 0,
            joints: [JointSample::default(); MAX_JOINTS],
        }
    }
}

impl JointState {
    /// The joints in use.
    pub fn joints(&self) -> &[JointSample] {
        &self.joints[..(self.joint_count as usize).min(MAX_JOINTS)]
    }
}

/// Joint goals for the driver.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("nori::GoalFrame/1")]
pub struct GoalFrame {
    /// Sender's sequence number.
    pub seq: u64,
    /// CLOCK_MONOTONIC, ns, when the goal was produced: the driver discards stale goals.
    pub timestamp_ns: u64,
    /// Number of joints the sender believes the driver has (must match).
    pub joint_count: u32,
    /// Bit `i` set: joint `i` has a goal in this frame; others keep their previous goal.
    pub mask: u32,
    /// Goals, rad (rad/s for speed-mode joints).
    pub position_rad: [f32; MAX_JOINTS],
}

impl Default for GoalFrame {
    fn default() -> Self {
        GoalFrame {
            seq: 0,
            timestamp_ns: 0,
            joint_count: 0,
            mask: 0,
            position_rad: [0.0; MAX_JOINTS],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layouts_are_stable() {
        // A change here changes the service identity: bump the version in the type name.
        assert_eq!(std::mem::size_of::<JointSample>(), 32);
        assert_eq!(std::mem::size_of::<JointState>(), 32 + 32 * MAX_JOINTS);
        assert_eq!(std::mem::size_of::<GoalFrame>(), 24 + 4 * MAX_JOINTS);
    }
}
