//! Frames of the body's motion: the velocity a tool or a policy asks of the differential base
//! and what the base controller (`nori-base`) did with it and measured; the height asked of the
//! lift and where the lift's controller (`nori-lift`) has it; where the whole body is (the arms'
//! shoulders and tools in the room, from the joints, the lift and the base's odometry).

use iceoryx2::prelude::ZeroCopySend;

/// A velocity command for the base, in its own frame. It is in force until a newer one
/// arrives or it is older than the controller's command timeout (then the base stops).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("nori::BaseCommand/1")]
pub struct BaseCommand {
    /// Sender's sequence number.
    pub seq: u64,
    /// When it was made, CLOCK_MONOTONIC ns: its age is judged from this.
    pub timestamp_ns: u64,
    /// Forward speed, m/s.
    pub linear_m_s: f32,
    /// Turn rate, rad/s, counter-clockwise seen from above.
    pub angular_rad_s: f32,
}

/// [`BaseState::flags`]: no command in force (none yet, or the last one is older than the
/// command timeout): the base is brought to a stop.
pub const BASE_FLAG_COMMAND_STALE: u32 = 1 << 0;
/// The protective field lowers the forward (or backward) speed: something is in the base's path.
pub const BASE_FLAG_FIELD_SLOWING: u32 = 1 << 1;
/// The protective field allows no motion along the path: the base stops short of an obstacle.
pub const BASE_FLAG_FIELD_STOPPED: u32 = 1 << 2;
/// A lidar is configured but its newest revolution is too old (or none came): the base does
/// not move along its path blind.
pub const BASE_FLAG_FIELD_BLIND: u32 = 1 << 3;
/// No lidar on this robot: no protective field (warned at start).
pub const BASE_FLAG_NO_LIDAR: u32 = 1 << 4;
/// The wheels were not read in the newest joint-state frame: the odometry holds.
pub const BASE_FLAG_WHEELS_UNREAD: u32 = 1 << 5;
/// The driver is in its safe state (or has the wheels' bus off): nothing is driven, the
/// controller starts again from rest.
pub const BASE_FLAG_NOT_DRIVEN: u32 = 1 << 6;

/// Each `BASE_FLAG_*` with what it means to an operator.
pub const BASE_FLAG_NAMES: [(u32, &str); 7] = [
    (BASE_FLAG_COMMAND_STALE, "no command"),
    (BASE_FLAG_FIELD_SLOWING, "field: slowing"),
    (
        BASE_FLAG_FIELD_STOPPED,
        "field: stopped short of an obstacle",
    ),
    (
        BASE_FLAG_FIELD_BLIND,
        "field: lidar silent, no motion along the path",
    ),
    (BASE_FLAG_NO_LIDAR, "no lidar"),
    (BASE_FLAG_WHEELS_UNREAD, "wheels not read"),
    (
        BASE_FLAG_NOT_DRIVEN,
        "not driven (safe state or wheels off)",
    ),
];

/// What the base controller did and measured, once per control period.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("nori::BaseState/1")]
pub struct BaseState {
    /// Frames published by this controller, from 1.
    pub seq: u64,
    /// When the wheels were last read (the joint-state frame the pose is from), ns.
    pub timestamp_ns: u64,
    /// Odometry: position, m, and heading, rad, in the frame the controller started in.
    pub x_m: f64,
    /// m.
    pub y_m: f64,
    /// rad, within (−π, π].
    pub theta_rad: f64,
    /// Path length covered, m.
    pub travelled_m: f64,
    /// Measured forward speed, m/s.
    pub linear_m_s: f32,
    /// Measured turn rate, rad/s.
    pub angular_rad_s: f32,
    /// The command in force (0 when stale), m/s.
    pub requested_linear_m_s: f32,
    /// rad/s.
    pub requested_angular_rad_s: f32,
    /// Sent to the wheels after the limits and the protective field, m/s.
    pub commanded_linear_m_s: f32,
    /// rad/s.
    pub commanded_angular_rad_s: f32,
    /// Free distance along the direction of travel (from the body's edge to the nearest point
    /// the lidar sees in its path), m; negative when none is known.
    pub field_distance_m: f32,
    /// `BASE_FLAG_*`.
    pub flags: u32,
    /// Commands refused so far (non-finite, from the future, or older than the timeout).
    pub commands_refused: u32,
    /// Zero: the padding to the frame's 8-byte alignment, made a field so that every byte of the
    /// shared frame is defined.
    pub reserved: u32,
}

impl BaseState {
    /// What its flags say, for operators.
    pub fn flag_names(&self) -> impl Iterator<Item = &'static str> {
        base_flag_names(self.flags)
    }
}

/// What `BASE_FLAG_*` bits say, for operators.
pub fn base_flag_names(flags: u32) -> impl Iterator<Item = &'static str> {
    BASE_FLAG_NAMES
        .iter()
        .filter(move |(f, _)| flags & f != 0)
        .map(|(_, name)| *name)
}

/// What a `LIFT_*` state code says, for operators.
pub fn lift_state_name(state: u8) -> &'static str {
    match state {
        LIFT_HOMING => "homing",
        LIFT_READY => "ready",
        LIFT_OBSTRUCTED => {
            "stopped on an obstruction (no goal toward it until `nori lift release`)"
        }
        LIFT_LINK_LOST => "board not answering",
        LIFT_JAMMED => "jammed: its back-off got nowhere (`nori lift release` homes it)",
        _ => "not homed",
    }
}

/// One line for operators: pose, measured and sent speeds, flags.
impl std::fmt::Display for BaseState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "x {:+.3} m  y {:+.3} m  heading {:+.3} rad  speed {:+.3} m/s {:+.3} rad/s  \
             sent {:+.3} m/s {:+.3} rad/s",
            self.x_m,
            self.y_m,
            self.theta_rad,
            self.linear_m_s,
            self.angular_rad_s,
            self.commanded_linear_m_s,
            self.commanded_angular_rad_s,
        )?;
        for name in self.flag_names() {
            write!(f, "  [{name}]")?;
        }
        Ok(())
    }
}

/// A height for the lift, m above its lowest (the lower switch): clamped into the soft limits
/// by the lift's controller; refused when older than its timeout on arrival. Or, with
/// [`LIFT_COMMAND_RELEASE`], the operator's release of an obstruction's hold or a jam.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("nori::LiftCommand/2")]
pub struct LiftCommand {
    /// Sender's sequence number.
    pub seq: u64,
    /// When it was made, CLOCK_MONOTONIC ns.
    pub timestamp_ns: u64,
    /// Height, m (a goal).
    pub height_m: f32,
    /// `LIFT_COMMAND_*`.
    pub kind: u32,
}

/// [`LiftCommand::kind`]: go to `height_m`.
pub const LIFT_COMMAND_GOAL: u32 = 0;
/// [`LiftCommand::kind`]: the operator releases an obstruction's hold (the column stays, with
/// no goal) or a jam (the column homes again). Only an operator's tool sends it.
pub const LIFT_COMMAND_RELEASE: u32 = 1;

/// The supervisor's word on the lift's travel (its duty-cycle budget), every 5 ms: the lift
/// moves only while the newest one is fresh and allows it.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("nori::LiftAllowance/2")]
pub struct LiftAllowance {
    /// The supervisor's sequence number.
    pub seq: u64,
    /// When it was decided, CLOCK_MONOTONIC ns.
    pub timestamp_ns: u64,
    /// 1: travel allowed.
    pub allowed: u8,
    /// Why not: `LIFT_REFUSED_*`.
    pub refused: u8,
    /// Operator's stops this supervisor has taken (wrapping): a change is a stop, even one
    /// the lift never saw in force (a stop and a resume between two of its periods).
    pub stops: u16,
    /// Allowed: running left, s; refused: rest still needed, s.
    pub seconds: f32,
    /// The budget used (heat as running time), s.
    pub used_s: f32,
    /// Zero: the padding to the frame's 8-byte alignment, made a field so that every byte of the
    /// shared frame is defined.
    pub reserved2: u32,
}

/// The lift travels on an allowance at most this old (no supervisor, no travel), ns: the
/// longest the lift can run after its supervisor died.
pub const LIFT_ALLOWANCE_LIFE_NS: u64 = 200_000_000;

/// [`LiftAllowance::refused`]: the motor's duty-cycle budget is spent.
pub const LIFT_REFUSED_DUTY: u8 = 1;
/// [`LiftAllowance::refused`]: an operator's stop is in force (the lift drops its goal).
pub const LIFT_REFUSED_OPERATOR_STOP: u8 = 2;
/// [`LiftAllowance::refused`]: the budget cannot be recorded (a restart would forget it).
pub const LIFT_REFUSED_RECORD: u8 = 4;

/// [`LiftState::state`]: not homed (no height is known).
pub const LIFT_UNHOMED: u8 = 0;
/// Homing: going down to the lower switch.
pub const LIFT_HOMING: u8 = 1;
/// Homed, following goals.
pub const LIFT_READY: u8 = 2;
/// Stopped on an obstruction (and backed off): no goal toward it until one away from it or the
/// operator's release.
pub const LIFT_OBSTRUCTED: u8 = 3;
/// The board does not answer (unplugged, or its link broken): the board's watchdog holds it.
pub const LIFT_LINK_LOST: u8 = 4;
/// Its back-off from an obstruction got nowhere: stopped until the operator's release.
pub const LIFT_JAMMED: u8 = 5;

/// Where the lift is, every control period of `nori-lift`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("nori::LiftState/2")]
pub struct LiftState {
    /// Frames published, from 1.
    pub seq: u64,
    /// When the board's reading was taken, ns.
    pub timestamp_ns: u64,
    /// Height, m above the lower switch (NaN before homing).
    pub height_m: f32,
    /// The goal in force (clamped), m; NaN when none.
    pub goal_m: f32,
    /// Velocity commanded, m/s.
    pub velocity_m_s: f32,
    /// Motor current, A.
    pub current_a: f32,
    /// `LIFT_*`.
    pub state: u8,
    /// Bit 0: lower switch, bit 1: upper switch.
    pub switches: u8,
    /// Travel held back: 0 allowed, 1 the duty-cycle budget is spent, 2 no live allowance
    /// from the supervisor, 3 an operator's stop.
    pub held: u8,
    /// The board's fault bits in its newest status (bit 0 its over-current stop, bit 1 its
    /// watchdog stop).
    pub board_faults: u8,
    /// With the budget spent: rest still needed, s.
    pub duty_wait_s: f32,
    /// Obstructions met so far.
    pub obstructions: u32,
    /// Commands refused so far (non-finite, stale, before homing).
    pub commands_refused: u32,
    /// Frames from the board refused so far (CRC, length).
    pub bad_frames: u32,
}

/// Where one arm is, in a [`BodyFrames`].
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
pub struct ArmFrame {
    /// The shoulder, m, in the odometry's frame (z up from the floor).
    pub shoulder: [f32; 3],
    /// The tool point, m.
    pub tool: [f32; 3],
    /// The tool frame's orientation, a unit quaternion `[w, x, y, z]`.
    pub tool_rotation: [f32; 4],
    /// 1: every joint of the arm was read in the frame and the lift's height is known; 0: the
    /// values are not to be used.
    pub valid: u8,
    /// Zero: the padding to the arm's 4-byte alignment, made a field so that every byte of the
    /// shared frame is defined.
    pub reserved: [u8; 3],
}

/// The whole body's forward kinematics for tools (`nori/body/frames`): each arm's shoulder and
/// tool in the frame the base's odometry started in, from the joint-state frame's positions,
/// the lift's height and the base's pose; computed from the robot description the simulator
/// uses (`body::kinematics`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("nori::BodyFrames/1")]
pub struct BodyFrames {
    /// Frames published, from 1.
    pub seq: u64,
    /// The joint-state frame the arms are from, ns.
    pub timestamp_ns: u64,
    /// The base's pose (its odometry), m.
    pub x_m: f64,
    /// m.
    pub y_m: f64,
    /// rad.
    pub theta_rad: f64,
    /// The lift's height, m (NaN when not known: not homed, or no lift state).
    pub lift_m: f64,
    /// The arms, in the description's order (left, right).
    pub arms: [ArmFrame; 2],
    /// Arms in `arms`.
    pub arm_count: u32,
    /// Zero: the padding to the frame's 8-byte alignment, made a field so that every byte of the
    /// shared frame is defined.
    pub reserved: u32,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A layout change must bump the type name's version.
    #[test]
    fn motion_layouts_are_stable() {
        assert_eq!(std::mem::size_of::<BaseCommand>(), 24);
        assert_eq!(std::mem::size_of::<BaseState>(), 88);
        assert_eq!(std::mem::size_of::<LiftCommand>(), 24);
        assert_eq!(std::mem::size_of::<LiftState>(), 56);
        assert_eq!(std::mem::size_of::<LiftAllowance>(), 32);
        assert_eq!(std::mem::size_of::<BodyFrames>(), 144);
    }

    #[test]
    fn a_state_reads_as_one_line_with_its_flags() {
        let s = BaseState {
            x_m: 1.5,
            flags: BASE_FLAG_COMMAND_STALE | BASE_FLAG_FIELD_BLIND,
            ..BaseState::default()
        };
        let line = s.to_string();
        assert!(line.starts_with("x +1.500 m"), "{line}");
        assert!(line.ends_with("[no command]  [field: lidar silent, no motion along the path]"));
    }
}
