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
#[derive(
    Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, serde::Serialize, serde::Deserialize,
)]
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
    /// [`JOINT_FLAG_OUTPUT_LOST`] and friends.
    pub flags: u8,
}

/// The joint's output vanished while torque was on (far from its goal, no load, no current, for
/// 50 ms): the driver's inference of a firmware protection that cut the motor, announced in the
/// status bits or not (the hardware tier).
pub const JOINT_FLAG_OUTPUT_LOST: u8 = 1;
/// The joint's bus is off: the supervisor disabled it, the trip record latches it, or the
/// driver's own last-resort tier tripped it.
pub const JOINT_FLAG_BUS_DISABLED: u8 = 2;
/// The joint's bus device is gone (transport failure); the driver reopens it and, when it
/// answers, applies the safe state and sets the servos up again.
pub const JOINT_FLAG_BUS_LOST: u8 = 4;
/// The driver's last-resort thermal tier turned the joint's bus off (a motor read the trip
/// temperature while no supervisor was heard); the supervisor latches such a bus as its own
/// trip when it sees this.
pub const JOINT_FLAG_DRIVER_TRIP: u8 = 8;

impl JointSample {
    /// Whether this cycle's read of the joint succeeded.
    pub fn is_valid(&self) -> bool {
        self.valid == 1
    }
}

/// The bus driver's output, one per control cycle.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend, serde::Serialize, serde::Deserialize)]
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

/// The driver has applied its safe state (supervisor heartbeat lost, an operator's stop, or
/// stopping).
pub const STATE_FLAG_SAFE_STATE: u32 = 1;
/// The safe state is an operator's stop (the supervisor's directives carry
/// [`DIRECTIVE_FLAG_STOP`]): it holds until the operator resumes.
pub const STATE_FLAG_OPERATOR_STOP: u32 = 2;

/// Buses a frame can describe.
pub const MAX_BUSES: usize = 4;
/// Bytes of a joint name in [`JointLayout`] (UTF-8, zero-padded).
pub const NAME_LEN: usize = 24;

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

/// What a joint is, for the supervisor's choice of reaction.
#[repr(u8)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum JointRole {
    /// An arm joint in position mode.
    #[default]
    Joint = 0,
    /// A gripper (reduced grip torque on stall, grip-force estimate).
    Gripper = 1,
    /// A wheel in speed mode.
    Wheel = 2,
}

/// One joint of the layout.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
pub struct JointInfo {
    /// Name, UTF-8, zero-padded.
    pub name: [u8; NAME_LEN],
    /// Index of its bus in the driver's configuration.
    pub bus: u8,
    /// [`JointRole`] as a byte.
    pub role: u8,
    /// Servo id on the bus.
    pub id: u8,
    /// Reserved, zero.
    pub reserved: u8,
    /// `Model_Number` (777 STS3215, 2825 STS3250, 2569 STS3095).
    pub model: u16,
    /// Firmware over-temperature cutoff written to this servo, °C.
    pub max_temperature_c: u8,
    /// Reserved, zero.
    pub reserved2: u8,
    /// Calibrated range, rad (low, high).
    pub range_rad: [f32; 2],
}

/// A zero-padded UTF-8 name as text ("?" if it is not UTF-8).
pub(crate) fn name_text(name: &[u8; NAME_LEN]) -> &str {
    let end = name.iter().position(|&b| b == 0).unwrap_or(NAME_LEN);
    std::str::from_utf8(&name[..end]).unwrap_or("?")
}

/// `name` zero-padded, truncated to [`NAME_LEN`] bytes at a character boundary.
pub(crate) fn name_bytes(name: &str) -> [u8; NAME_LEN] {
    let mut bytes = [0; NAME_LEN];
    let mut end = name.len().min(NAME_LEN);
    while !name.is_char_boundary(end) {
        end -= 1;
    }
    bytes[..end].copy_from_slice(&name.as_bytes()[..end]);
    bytes
}

impl JointInfo {
    /// The name as text.
    pub fn name(&self) -> &str {
        name_text(&self.name)
    }

    /// Sets the name, truncated to [`NAME_LEN`] bytes at a character boundary.
    pub fn set_name(&mut self, name: &str) {
        self.name = name_bytes(name);
    }

    /// The role.
    pub fn role(&self) -> JointRole {
        match self.role {
            1 => JointRole::Gripper,
            2 => JointRole::Wheel,
            _ => JointRole::Joint,
        }
    }
}

/// The driver's joints and buses as it runs them (history 1): the one source of names. A driver
/// started on a subset of its configuration's buses numbers them from 0 in its own order, so
/// every other process and tool names joints and buses from this frame, never from a file.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("nori::JointLayout/2")]
pub struct JointLayout {
    /// Joints in use.
    pub joint_count: u32,
    /// Buses in use.
    pub bus_count: u32,
    /// Bus names in the driver's order (the index frames and directives use), UTF-8,
    /// zero-padded.
    pub bus_names: [[u8; NAME_LEN]; MAX_BUSES],
    /// Per joint, in frame order.
    pub joints: [JointInfo; MAX_JOINTS],
}

impl Default for JointLayout {
    fn default() -> Self {
        JointLayout {
            joint_count: 0,
            bus_count: 0,
            bus_names: [[0; NAME_LEN]; MAX_BUSES],
            joints: [JointInfo::default(); MAX_JOINTS],
        }
    }
}

impl JointLayout {
    /// The joints in use.
    pub fn joints(&self) -> &[JointInfo] {
        &self.joints[..(self.joint_count as usize).min(MAX_JOINTS)]
    }

    /// The names of the buses in use, by index.
    pub fn bus_names(&self) -> impl Iterator<Item = &str> {
        self.bus_names[..(self.bus_count as usize).min(MAX_BUSES)]
            .iter()
            .map(name_text)
    }

    /// Sets bus `b`'s name (ignored beyond [`MAX_BUSES`]).
    pub fn set_bus_name(&mut self, b: usize, name: &str) {
        if let Some(slot) = self.bus_names.get_mut(b) {
            *slot = name_bytes(name);
        }
    }

    /// The index of the bus named `name`.
    pub fn bus_index(&self, name: &str) -> Option<usize> {
        self.bus_names().position(|n| n == name)
    }

    /// The index of the joint named `name` in frames.
    pub fn joint_index(&self, name: &str) -> Option<usize> {
        self.joints().iter().position(|j| j.name() == name)
    }

    /// The joint names in frame order.
    pub fn joint_names(&self) -> impl Iterator<Item = &str> {
        self.joints().iter().map(JointInfo::name)
    }
}

/// What the supervisor wants the driver to do; the newest frame wins (state, not events).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("nori::Directives/2")]
pub struct Directives {
    /// Supervisor's sequence number.
    pub seq: u64,
    /// CLOCK_MONOTONIC, ns.
    pub timestamp_ns: u64,
    /// Joints the supervisor believes the driver has (must match).
    pub joint_count: u32,
    /// Bit `b` set: bus `b` is enabled. A cleared bit disables the whole bus (torque off).
    pub bus_enabled: u32,
    /// Per joint torque limit, 0.1 % of full output; 0 means the configured maximum.
    pub torque_limit_permille: [u16; MAX_JOINTS],
    /// [`DIRECTIVE_FLAG_STOP`].
    pub flags: u32,
    /// Reserved, zero.
    pub reserved: u32,
}

/// [`Directives::flags`]: an operator stopped the robot: the driver holds its safe state (and
/// takes no goal) for as long as the directives carry it, whatever else they allow.
pub const DIRECTIVE_FLAG_STOP: u32 = 1;

impl Default for Directives {
    fn default() -> Self {
        Directives {
            seq: 0,
            timestamp_ns: 0,
            joint_count: 0,
            bus_enabled: u32::MAX,
            torque_limit_permille: [0; MAX_JOINTS],
            flags: 0,
            reserved: 0,
        }
    }
}

/// Who sends a heartbeat.
#[repr(u8)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Peer {
    /// The bus driver.
    Driver = 1,
    /// The supervisor.
    Supervisor = 2,
}

/// "I am alive", sent by the driver and the supervisor every cycle.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("nori::Heartbeat/1")]
pub struct Heartbeat {
    /// Sender's sequence number (restarts with the process).
    pub seq: u64,
    /// CLOCK_MONOTONIC, ns.
    pub timestamp_ns: u64,
    /// Sender's process id (a change means a restart).
    pub pid: u32,
    /// [`Peer`] as a byte.
    pub peer: u8,
    /// Reserved, zero.
    pub reserved: [u8; 3],
}

/// Kinds of [`SupervisorEvent`].
#[repr(u8)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EventKind {
    /// A joint stalled (current high, position static over the window).
    Stall = 1,
    /// A stalled joint gets its one retry at full torque.
    StallRetry = 2,
    /// A joint's torque was reduced (gripper grip, or a joint that stalled again).
    TorqueReduced = 3,
    /// A reduced joint got a new target and its torque back.
    TorqueRestored = 4,
    /// Thermal warning level changed (`level` 0..3, `value` predicted seconds to the trip).
    ThermalWarning = 5,
    /// Software thermal trip: the whole bus is disabled, latched (`value` °C).
    ThermalTrip = 6,
    /// A tripped bus was re-enabled after cooling and an explicit command.
    BusReenabled = 7,
    /// The driver inferred from the motor that a firmware protection cut its output (`value` °C).
    OutputLost = 8,
    /// The supervisor lost the driver (no joint state within the bound).
    DriverLost = 9,
    /// The driver is back (`value`: its new pid).
    DriverBack = 10,
    /// A re-enable command was refused (`value` hottest °C on the bus).
    ReenableRefused = 11,
    /// An operator command was not carried out: `level` says why (`COMMAND_REFUSED_*`).
    CommandRefused = 12,
    /// A servo reported a firmware protection in its status bits (`level`: the bits, overheat
    /// 0x04, over-current 0x08, overload 0x20; `value` °C): the hardware tier fired, the bus
    /// is disabled and latched.
    FirmwareProtection = 13,
    /// The driver's last-resort thermal tier had turned the bus off while no supervisor was
    /// heard (`value` hottest °C on the bus); the supervisor latches it as its own trip.
    DriverTrip = 14,
    /// An operator stopped the robot (`level` 1: restored from the trip record at start).
    OperatorStop = 15,
    /// An operator ended the stop.
    OperatorResume = 16,
}

/// [`EventKind::CommandRefused`]: a command kind the supervisor does not know.
pub const COMMAND_REFUSED_UNKNOWN_KIND: u8 = 1;
/// [`EventKind::CommandRefused`]: the command names a bus the robot does not have.
pub const COMMAND_REFUSED_NO_SUCH_BUS: u8 = 2;
/// [`EventKind::CommandRefused`]: re-enable asked for a bus that is not tripped.
pub const COMMAND_REFUSED_NOT_TRIPPED: u8 = 3;
/// [`EventKind::CommandRefused`]: resume asked while no stop is in force.
pub const COMMAND_REFUSED_NOT_STOPPED: u8 = 4;

/// Something the supervisor (or the driver) decided or observed.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("nori::SupervisorEvent/1")]
pub struct SupervisorEvent {
    /// Sender's sequence number.
    pub seq: u64,
    /// CLOCK_MONOTONIC, ns.
    pub timestamp_ns: u64,
    /// [`EventKind`] as a byte.
    pub kind: u8,
    /// Joint index (or 0xFF when the event is about a bus).
    pub joint: u8,
    /// Bus index (or 0xFF).
    pub bus: u8,
    /// Warning level or similar small number.
    pub level: u8,
    /// A value whose meaning depends on the kind (°C, A, s).
    pub value: f32,
}

impl SupervisorEvent {
    /// The kind, if known.
    pub fn kind(&self) -> Option<EventKind> {
        use EventKind::*;
        [
            Stall,
            StallRetry,
            TorqueReduced,
            TorqueRestored,
            ThermalWarning,
            ThermalTrip,
            BusReenabled,
            OutputLost,
            DriverLost,
            DriverBack,
            ReenableRefused,
            CommandRefused,
            FirmwareProtection,
            DriverTrip,
            OperatorStop,
            OperatorResume,
        ]
        .into_iter()
        .find(|k| *k as u8 == self.kind)
    }
}

/// Grippers a grip frame carries.
pub const MAX_GRIPPERS: usize = 4;

/// One gripper's force estimate, beside the raw current it comes from.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
pub struct GripSample {
    /// Joint index of the gripper.
    pub joint: u8,
    /// 1 when the current was read this cycle.
    pub valid: u8,
    /// Reserved, zero.
    pub reserved: [u8; 2],
    /// Raw motor current, A.
    pub current_a: f32,
    /// Normalised grip force f̂ = clip((|I| − I_idle)/(I_max − I_idle), 0, 1).
    pub force: f32,
}

/// Grip force of every gripper, one per joint-state frame.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("nori::GripFrame/1")]
pub struct GripFrame {
    /// `seq` of the joint-state frame it was computed from.
    pub state_seq: u64,
    /// That frame's timestamp, ns.
    pub timestamp_ns: u64,
    /// Grippers in use.
    pub gripper_count: u32,
    /// Reserved, zero.
    pub reserved: u32,
    /// Per gripper.
    pub grippers: [GripSample; MAX_GRIPPERS],
}

/// An operator's command to the supervisor.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("nori::SupervisorCommand/1")]
pub struct SupervisorCommand {
    /// Sender's sequence number.
    pub seq: u64,
    /// CLOCK_MONOTONIC, ns.
    pub timestamp_ns: u64,
    /// [`COMMAND_REENABLE_BUS`], [`COMMAND_STOP`] or [`COMMAND_RESUME`].
    pub kind: u8,
    /// Bus index.
    pub bus: u8,
    /// Reserved, zero.
    pub reserved: [u8; 6],
}

/// [`SupervisorCommand::kind`]: re-enable a tripped bus.
pub const COMMAND_REENABLE_BUS: u8 = 1;
/// [`SupervisorCommand::kind`]: stop the robot: the driver's safe state until [`COMMAND_RESUME`]
/// (recorded, so no restart of any process ends it).
pub const COMMAND_STOP: u8 = 2;
/// [`SupervisorCommand::kind`]: end an operator's stop.
pub const COMMAND_RESUME: u8 = 3;

/// One bus's error counts by kind: kept by the driver's bus layer (`bus_driver::bus`) as they
/// happen and published as they are in [`BusHealthEntry`], so the two never drift apart.
#[repr(C)]
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend, serde::Serialize, serde::Deserialize,
)]
pub struct BusCounters {
    /// Feedback transactions.
    pub cycles: u64,
    /// Servo replies received and used.
    pub replies: u64,
    /// Servos that did not answer a feedback read in time.
    pub missing: u64,
    /// Packets with a bad checksum.
    pub checksum_errors: u64,
    /// Bytes skipped as garbage.
    pub garbage_bytes: u64,
    /// Headers with an impossible id or length, or truncated packets.
    pub framing_errors: u64,
    /// Replies from an id not asked, or of the wrong size.
    pub unexpected_replies: u64,
    /// Replies whose status byte had an error bit set.
    pub status_errors: u64,
    /// Replies that passed the checksum but jumped further than the servo can move or heat
    /// since its last accepted reading (held back as a missing sample; see
    /// `bus_driver::plausibility`).
    pub implausible: u64,
    /// Transport failures.
    pub transport_errors: u64,
    /// Times the bus's device was lost (a transport failure: adapter unplugged).
    pub disconnects: u64,
    /// Times the device was opened again after a loss.
    pub reconnects: u64,
    /// Times every servo of the bus fell silent for the loss bound (safe state applied).
    pub silences: u64,
    /// Times one servo fell silent for the loss bound (taken off and set up again on return).
    pub servos_lost: u64,
    /// Read-backs of a servo's safety settings (torque enable, torque limit, held goal) that
    /// answered.
    pub read_backs: u64,
    /// Read-backs that got no intact answer in time.
    pub read_back_missing: u64,
    /// Safety settings found different on the servo from what the driver wants (a lost or
    /// corrupted write, a servo reset): each re-sent.
    pub safety_mismatches: u64,
}

impl BusCounters {
    /// The counts of something going wrong, each named as its field (the fleet's
    /// `bus_errors{kind}`): written next to the fields, so a renamed or added field is
    /// classified here or the build fails.
    pub fn errors(&self) -> [(&'static str, u64); 13] {
        [
            ("missing", self.missing),
            ("checksum_errors", self.checksum_errors),
            ("garbage_bytes", self.garbage_bytes),
            ("framing_errors", self.framing_errors),
            ("unexpected_replies", self.unexpected_replies),
            ("implausible", self.implausible),
            ("status_errors", self.status_errors),
            ("transport_errors", self.transport_errors),
            ("disconnects", self.disconnects),
            ("silences", self.silences),
            ("servos_lost", self.servos_lost),
            ("read_back_missing", self.read_back_missing),
            ("safety_mismatches", self.safety_mismatches),
        ]
    }

    /// The counts of work done, not of faults.
    pub fn work(&self) -> [(&'static str, u64); 4] {
        [
            ("cycles", self.cycles),
            ("replies", self.replies),
            ("reconnects", self.reconnects),
            ("read_backs", self.read_backs),
        ]
    }
}

/// One bus's entry of [`BusHealth`].
#[repr(C)]
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend, serde::Serialize, serde::Deserialize,
)]
pub struct BusHealthEntry {
    /// The driver's counts.
    #[serde(flatten)]
    pub counters: BusCounters,
    /// [`BUS_HEALTH_CONNECTED`] and friends.
    pub flags: u32,
    /// Reserved, zero.
    pub reserved: u32,
}

/// One line for operators (`nori state`): connected or lost, why it is off if it is, and the
/// counts.
impl std::fmt::Display for BusHealthEntry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let on = self.flags & BUS_HEALTH_ENABLED != 0;
        let why_off = if on {
            ""
        } else if self.flags & BUS_HEALTH_LATCHED != 0 {
            ", OFF: latched by a trip"
        } else if self.flags & BUS_HEALTH_DRIVER_TRIP != 0 {
            ", OFF: the driver's last-resort trip"
        } else {
            ", OFF: disabled by the supervisor"
        };
        let connected = self.flags & BUS_HEALTH_CONNECTED != 0;
        let c = &self.counters;
        write!(
            f,
            "{}{why_off}; {} cycles, missing {}, checksum {}, framing {}, unexpected {}, \
             implausible {}, status {}, transport {}, disconnects {}, reconnects {}, silences {}, \
             servos lost {}, safety read-backs {} (missing {}), safety mismatches {}",
            if connected { "connected" } else { "LOST" },
            c.cycles,
            c.missing,
            c.checksum_errors,
            c.framing_errors,
            c.unexpected_replies,
            c.implausible,
            c.status_errors,
            c.transport_errors,
            c.disconnects,
            c.reconnects,
            c.silences,
            c.servos_lost,
            c.read_backs,
            c.read_back_missing,
            c.safety_mismatches
        )
    }
}

/// [`BusHealthEntry::flags`]: the bus's device is open.
pub const BUS_HEALTH_CONNECTED: u32 = 1;
/// [`BusHealthEntry::flags`]: nothing holds the bus off (supervisor, trip record, driver).
pub const BUS_HEALTH_ENABLED: u32 = 2;
/// [`BusHealthEntry::flags`]: the trip record on disk latches the bus off.
pub const BUS_HEALTH_LATCHED: u32 = 4;
/// [`BusHealthEntry::flags`]: the driver's last-resort thermal tier turned the bus off.
pub const BUS_HEALTH_DRIVER_TRIP: u32 = 8;

/// The driver's error counts per bus, a few times a second: faults are counted, never logged
/// per cycle, and this is where operators and tests see them.
#[repr(C)]
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend, serde::Serialize, serde::Deserialize,
)]
#[type_name("nori::BusHealth/3")]
pub struct BusHealth {
    /// Driver cycle of the counts.
    pub seq: u64,
    /// CLOCK_MONOTONIC, ns.
    pub timestamp_ns: u64,
    /// Buses in use (the first `bus_count` entries).
    pub bus_count: u32,
    /// Reserved, zero.
    pub reserved: u32,
    /// Per bus, in the driver configuration's order.
    pub buses: [BusHealthEntry; MAX_BUSES],
}

impl BusHealth {
    /// The buses in use.
    pub fn buses(&self) -> &[BusHealthEntry] {
        &self.buses[..(self.bus_count as usize).min(MAX_BUSES)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every field of the bus counters is either an error or work, under its own name: a
    /// field added without a place in one of the two lists fails here (the literal fails to
    /// build; the names are checked against the fields' values).
    #[test]
    fn every_bus_counter_is_an_error_or_work_under_its_field_s_name() {
        // Every field written, each a value of its own (a field added fails to build here).
        let c = BusCounters {
            cycles: 100,
            replies: 101,
            missing: 102,
            checksum_errors: 103,
            garbage_bytes: 104,
            framing_errors: 105,
            unexpected_replies: 106,
            status_errors: 107,
            implausible: 108,
            transport_errors: 109,
            disconnects: 110,
            reconnects: 111,
            silences: 112,
            servos_lost: 113,
            read_backs: 114,
            read_back_missing: 115,
            safety_mismatches: 116,
        };
        let json = serde_json::to_value(c).unwrap();
        let named: Vec<(&str, u64)> = c.errors().into_iter().chain(c.work()).collect();
        assert_eq!(named.len(), json.as_object().unwrap().len());
        for (name, value) in named {
            assert_eq!(json[name], value, "{name}");
        }
    }

    #[test]
    fn layouts_are_stable() {
        // A change here changes the service identity: bump the version in the type name.
        assert_eq!(std::mem::size_of::<JointSample>(), 32);
        assert_eq!(std::mem::size_of::<JointState>(), 32 + 32 * MAX_JOINTS);
        assert_eq!(std::mem::size_of::<GoalFrame>(), 24 + 4 * MAX_JOINTS);
        assert_eq!(std::mem::size_of::<Directives>(), 24 + 2 * MAX_JOINTS + 8);
        assert_eq!(std::mem::size_of::<JointInfo>(), 40);
        assert_eq!(std::mem::size_of::<SupervisorEvent>(), 24);
        assert_eq!(std::mem::size_of::<Heartbeat>(), 24);
        assert_eq!(std::mem::size_of::<BusHealthEntry>(), 144);
        assert_eq!(std::mem::size_of::<BusHealth>(), 24 + 144 * MAX_BUSES);
        assert_eq!(
            std::mem::size_of::<JointLayout>(),
            8 + NAME_LEN * MAX_BUSES + 40 * MAX_JOINTS
        );
    }

    #[test]
    fn a_layout_names_its_buses_and_joints_by_index() {
        let mut l = JointLayout {
            joint_count: 2,
            bus_count: 2,
            ..JointLayout::default()
        };
        l.set_bus_name(0, "right_arm");
        l.set_bus_name(1, "wheels");
        l.set_bus_name(MAX_BUSES, "ignored");
        l.joints[0].set_name("right_elbow");
        l.joints[1].set_name("left_wheel");
        // A name beyond the buses in use is not a bus.
        l.bus_names[2] = *b"stale\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0";
        assert_eq!(l.bus_names().collect::<Vec<_>>(), ["right_arm", "wheels"]);
        assert_eq!(l.bus_index("wheels"), Some(1));
        assert_eq!(l.bus_index("stale"), None);
        assert_eq!(l.joint_index("left_wheel"), Some(1));
        assert_eq!(l.joint_index("left_elbow"), None);
        assert_eq!(
            l.joint_names().collect::<Vec<_>>(),
            ["right_elbow", "left_wheel"]
        );
    }

    #[test]
    fn names_round_trip_and_truncate() {
        let mut j = JointInfo::default();
        j.set_name("left_gripper");
        assert_eq!(j.name(), "left_gripper");
        j.set_name("a_very_long_joint_name_that_does_not_fit");
        assert_eq!(j.name().len(), NAME_LEN);
    }
}
