//! The driver: servo setup, the control cycle, goal gating, the supervisor's directives and the
//! safe state.
//!
//! Per cycle and bus: one SYNC_READ of the feedback block and one SYNC_WRITE of goals (plus a
//! SYNC_WRITE of torque limits in the rare cycles where one changes). All buses' reads are
//! started before any is collected, so their wire time overlaps. Nothing here reads a clock of
//! its own: time comes in with the goal frames and as the clock `cycle` is passed, so the
//! logic is tested without sleeping.

use crate::approach::{Approach, Sighting};
use crate::backstops;
use crate::bus::{Bus, BusCounters, BusError};
use crate::calibration::{wheel_speed_steps, GoalError, JointCalibration, STEPS_PER_RAD};
use crate::config::{Backstops, LoadedConfig, Mode, Role, SafeState};
use crate::cutoff::CutoffWatch;
use crate::plausibility::FeedbackGate;
use crate::transport::Transport;
use feetech::registers::{self as reg, FeedbackBlock};
use feetech::{ServoModel, ServoStatus, AMPS_PER_CURRENT_UNIT};
use telemetry::clock::{in_force, NotInForce, MS};
use telemetry::frames::{
    BusHealth, BusHealthEntry, Directives, JointInfo, JointLayout, JointRole, BUS_HEALTH_CONNECTED,
    BUS_HEALTH_DRIVER_TRIP, BUS_HEALTH_ENABLED, BUS_HEALTH_LATCHED, DIRECTIVE_FLAG_STOP,
    JOINT_FLAG_BUS_DISABLED, JOINT_FLAG_BUS_LOST, JOINT_FLAG_DRIVER_TRIP, JOINT_FLAG_OUTPUT_LOST,
    MAX_BUSES, STATE_FLAG_OPERATOR_STOP, STATE_FLAG_SAFE_STATE,
};
use telemetry::wire::WireFrame;
use telemetry::{GoalFrame, JointSample, JointState, MAX_JOINTS};
use thiserror::Error;

/// A goal frame the driver refused; nothing of it was applied.
#[derive(Debug, Clone, Copy, PartialEq, Error)]
pub enum GoalRejection {
    /// The sender's joint count differs from the driver's.
    #[error("goal frame for {got} joints, the driver has {expected}")]
    WrongJointCount {
        /// Driver's joints.
        expected: u32,
        /// Frame's joints.
        got: u32,
    },
    /// The mask names joints the driver does not have.
    #[error("goal mask {mask:#x} names joints beyond {joint_count}")]
    MaskOutOfRange {
        /// The mask.
        mask: u32,
        /// Driver's joints.
        joint_count: u32,
    },
    /// Older than `goal-max-age-ms`, or timestamped in the future (a clock that is not ours).
    #[error("goal frame {0}")]
    NotInForce(#[from] NotInForce),
    /// Produced before the driver left its safe state: it was meant for another situation.
    #[error("goal frame older than the end of the safe state")]
    BeforeRecovery,
    /// The driver is in its safe state (no supervisor): goals are refused.
    #[error("the driver is in its safe state (supervisor missing)")]
    SafeState,
    /// A NaN or infinite goal.
    #[error(transparent)]
    NotFinite(#[from] GoalError),
    /// A wheel named on the joints' path, or an arm joint on the wheels': the wheels take
    /// speeds from the base's controller alone (its field, ramp and timeout).
    #[error("goal mask {mask:#x} names {what} on the {path:?} path")]
    WrongPath {
        /// The mask.
        mask: u32,
        /// What it named that the path does not carry.
        what: &'static str,
        /// The path it came on.
        path: GoalPath,
    },
}

/// Where a goal frame came from: each path carries its own joints.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GoalPath {
    /// `nori/goals`: the arms, grippers (and the fleet agent, Nori Lab, `nori goal`).
    Joints,
    /// `nori/base/wheel-goals`: the wheels' speeds, from the base's controller.
    Wheels,
}

/// A directives frame the driver refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
#[error("directives for {got} joints, the driver has {expected}")]
pub struct DirectiveMismatch {
    /// Driver's joints.
    pub expected: u32,
    /// Frame's joints.
    pub got: u32,
}

/// Why a servo could not be brought up.
#[derive(Debug, Error)]
pub enum SetupError {
    /// Bus failure.
    #[error(transparent)]
    Bus(#[from] BusError),
    /// The servo does not hold its joint's calibration (homing offset, position limits):
    /// not the servo the calibration was made with, or its horn was refitted.
    #[error(
        "servo {id} holds homing offset {}, position limits {}..{}; the calibration says {}, \
         {}..{}: not calibrated for this joint (a replaced servo or a refitted horn): left off \
         until the joint is calibrated (`nori calibrate by-hand`)",
        found[0], found[1], found[2], expected[0], expected[1], expected[2]
    )]
    NotCalibrated {
        /// Servo id.
        id: u8,
        /// Homing offset and the two limits read.
        found: [i32; 3],
        /// What the calibration says.
        expected: [i32; 3],
    },
    /// No two readings of the position in a row agreed: a reply the checksum let through, or
    /// a joint moving, and the first goal must not be a wrong one.
    #[error(
        "servo {id} read at {first} then at {second} steps: not one position to hold (a \
         corrupted reply, or the joint moving?); set up again shortly"
    )]
    UnsteadyPosition {
        /// Servo id.
        id: u8,
        /// The last reading but one, steps.
        first: i32,
        /// The last, steps.
        second: i32,
    },
    /// The servo is not the configured model.
    #[error(
        "servo {id} reports model number {found}, configured {expected:?}: left off (`nori \
         servo scan` names what is on the bus, `nori servo setup` sets up the right servo)"
    )]
    WrongModel {
        /// Servo id.
        id: u8,
        /// The model the configuration names.
        expected: ServoModel,
        /// `Model_Number` read.
        found: i32,
    },
}

/// Position reads a setup makes at most to find two in a row that agree.
const POSITION_READS: usize = 4;

/// Where servo `id` is, for its first goal: the second of the first two readings in a row that
/// agree within [`crate::plausibility::POSITION_STEP`], so that a reply with two flipped bits
/// the checksum let through (a sign bit: clamped to the range's end) is never it. A joint read
/// moving is read again (its torque is off meanwhile), at most [`POSITION_READS`] times.
fn steady_position<T: Transport>(bus: &mut Bus<T>, id: u8) -> Result<i32, SetupError> {
    let mut last = bus.read(id, reg::PRESENT_POSITION)?;
    let mut before = last;
    for _ in 1..POSITION_READS {
        let next = bus.read(id, reg::PRESENT_POSITION)?;
        if f64::from((next - last).abs()) <= crate::plausibility::POSITION_STEP {
            return Ok(next);
        }
        (before, last) = (last, next);
    }
    Err(SetupError::UnsteadyPosition {
        id,
        first: before,
        second: last,
    })
}

/// Counters of the driver, for telemetry.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct DriverCounters {
    /// Cycles run.
    pub cycles: u64,
    /// Cycles that overran their period.
    pub deadline_misses: u64,
    /// Goal frames applied.
    pub goals_accepted: u64,
    /// Goal frames refused as stale (or from the future, or from before a recovery).
    pub goals_stale: u64,
    /// Goal frames refused for NaN/inf.
    pub goals_not_finite: u64,
    /// Goal frames refused for their shape.
    pub goals_malformed: u64,
    /// Goal frames refused in the safe state.
    pub goals_in_safe_state: u64,
    /// Single goals clamped into the calibrated range (or to the wheel speed limit).
    pub goals_clamped: u64,
    /// EEPROM registers written at setup (read-compare-write).
    pub eeprom_writes: u64,
    /// Failed servo setups.
    pub setup_failures: u64,
    /// Times the safe state was entered.
    pub safe_state_entries: u64,
    /// Buses disabled by the supervisor.
    pub bus_disables: u64,
    /// Unannounced firmware cutoffs inferred.
    pub outputs_lost: u64,
    /// Buses turned off by the driver's last-resort thermal tier (no supervisor heard).
    pub last_resort_trips: u64,
    /// Wheels stopped because their speed command was not renewed in time.
    pub wheel_stops: u64,
    /// Supervisor heartbeats and directives ignored for their own timestamp (too old or from
    /// the future).
    pub stale_supervisor_frames: u64,
}

struct Joint {
    name: String,
    id: u8,
    model: ServoModel,
    role: JointRole,
    backstops: Backstops,
    calibration: Option<JointCalibration>,
    /// Set up, torque on, goals flowing.
    ready: bool,
    /// Goal in register units (steps, or steps/s in speed mode).
    goal: i32,
    /// The goal last written to the servo, steps: an arm joint's `goal` on its slowed approach
    /// to an end of the range ([`crate::approach`]); a gripper's or a wheel's `goal` itself.
    written: f64,
    /// Where it was read this cycle, or last (a reading held back by the gate is none).
    seen: Sighting,
    /// The timestamp of the goal frame that set `goal` (a wheel's speed expires with it).
    goal_at_ns: u64,
    /// Torque limit the supervisor asks for, 0.1 % (0: the configured maximum).
    torque_wanted: u16,
    /// Torque limit last written to the servo, 0.1 %.
    torque_written: u16,
    cutoff: CutoffWatch,
    /// Holds back readings that jumped further than the servo can move or heat.
    gate: FeedbackGate,
    /// Consecutive feedback reads it did not answer (or answered implausibly).
    misses: u32,
    /// Failed setups in a row (spacing of the next attempt).
    setup_fails: u32,
    /// Cycle from which a setup may be tried again.
    next_setup: u64,
    /// The safety settings last confirmed on the servo by a read-back; the servo is read again
    /// with priority while what the driver wants differs from it.
    confirmed: Option<Want>,
}

/// The safety settings the driver wants a servo to hold now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Want {
    /// Torque off.
    Off,
    /// Torque on at this limit (0.1 %); a held joint (hold safe state) also at its goal.
    On {
        /// Torque_Limit.
        limit: u16,
        /// The goal it must hold (the hold safe state), in register units.
        hold_goal: Option<i32>,
    },
    /// Not driven: torque off, or a limit of at most this (the hold safe state applied to a
    /// servo taken off).
    AtMost {
        /// Highest acceptable Torque_Limit.
        limit: u16,
    },
}

impl Joint {
    /// The goal last written, in whole steps.
    fn written_steps(&self) -> i32 {
        self.written.round() as i32
    }

    /// Not driven until the loop sets it up again (one servo per 1/50 s), with no back-off
    /// left from earlier failures.
    fn set_up_again(&mut self) {
        // Whatever changed while it was off or silent is no glitch: its gate starts afresh.
        self.gate.reset();
        self.ready = false;
        self.next_setup = 0;
        self.setup_fails = 0;
    }

    fn max_torque(&self) -> u16 {
        backstops::max_torque_permille(&self.backstops) as u16
    }
}

struct BusState<T: Transport> {
    name: String,
    mode: Mode,
    bus: Bus<T>,
    ids: Vec<u8>,
    first_joint: usize,
    feedback: Vec<Option<(FeedbackBlock, ServoStatus)>>,
    payload: Vec<u8>,
    /// The supervisor's directive has it off.
    directed_off: bool,
    /// The trip record on disk latches it off (read at start and before a release is obeyed).
    latched: bool,
    /// The driver's own last-resort thermal tier turned it off (no supervisor was heard);
    /// held until a directive of a live supervisor takes the trip over.
    own_trip: bool,
    /// The transport failed this cycle (feedback not requested).
    failed: bool,
    /// The device is open (false after a transport failure, until reopened).
    connected: bool,
    /// Consecutive cycles in which no servo of the bus answered.
    silent_cycles: u32,
}

impl<T: Transport> BusState<T> {
    /// Torque may be on: nothing holds the bus off.
    fn on(&self) -> bool {
        !(self.directed_off || self.latched || self.own_trip)
    }
}

/// The driver over one transport per bus.
pub struct Driver<T: Transport> {
    buses: Vec<BusState<T>>,
    joints: Vec<Joint>,
    state: JointState,
    goal_max_age_ns: u64,
    max_wheel_speed: f64,
    /// A wheel's speed is set to 0 once its command is this old.
    wheel_timeout_ns: u64,
    safe_kind: SafeState,
    hold_permille: u16,
    /// In the safe state (supervisor missing or never seen, or an operator's stop).
    safe: bool,
    /// The supervisor's last applied directives carry an operator's stop.
    operator_stop: bool,
    /// When the safe state was last left: older goals are refused.
    recovered_at_ns: u64,
    setup_retry_cycles: u64,
    /// A live supervisor is heard (set by the loop): the driver's last-resort thermal tier
    /// stands down while it is.
    supervised: bool,
    /// The last-resort tier's trip temperature, °C.
    last_resort_trip_c: f32,
    /// Cycles of silence after which a servo (or a whole bus) counts as lost.
    lost_after: u32,
    /// Cycles between attempts to reopen a lost device.
    reopen_every: u64,
    /// Cycles between background read-backs (one servo per bus each).
    read_back_every: u64,
    /// Slack after a reply's wire time before it is missing.
    reply_margin: std::time::Duration,
    /// The background read-back runs (off only to measure what it costs).
    background_read_back: bool,
    /// A joint's approach to the ends of its range, slowed...
    approach: Approach,
    /// ...unless off (only to measure what it costs).
    slowed_approach: bool,
    /// Per bus: the next joint (offset in the bus) a background read-back looks at, and the
    /// joint whose read-back was requested and not yet collected.
    read_back_cursor: Vec<usize>,
    read_back_now: Vec<Option<usize>>,
    /// No setup before this cycle (one slow setup at a time, spaced out).
    next_setup_any: u64,
    next_retry: usize,
    /// Counts since the driver started (cycles, goals taken and refused, setups…).
    pub counters: DriverCounters,
}

impl<T: Transport> Driver<T> {
    /// A driver for a validated configuration, with one transport per configured bus, in order.
    /// It starts in its safe state when a supervisor is required (until one is heard from).
    pub fn new(config: &LoadedConfig, transports: Vec<T>) -> Self {
        let c = &config.config;
        let margin = std::time::Duration::from_micros(c.reply_timeout_margin_us);
        // A reading after more than two periods' silence (at least the gate's own 0.2 s) waits
        // for confirmation: at a slow rate every reading would otherwise be one.
        let silence_s = (2.5 / c.rate_hz.max(1.0)).max(crate::plausibility::SILENCE_S);
        let mut joints = Vec::new();
        let mut buses = Vec::new();
        for (bus_config, transport) in c.bus.iter().zip(transports) {
            let first_joint = joints.len();
            for s in &bus_config.servo {
                joints.push(Joint {
                    name: s.joint.clone(),
                    id: s.id,
                    // Validated at load: a servo's model has backstops, known models only.
                    model: ServoModel::from_key(&s.model).unwrap_or(ServoModel::Sts3215),
                    role: match (bus_config.mode, s.role) {
                        (Mode::Speed, _) => JointRole::Wheel,
                        (_, Role::Gripper) => JointRole::Gripper,
                        _ => JointRole::Joint,
                    },
                    // Validated: every model has backstops.
                    backstops: c.backstops.get(&s.model).copied().unwrap_or(Backstops {
                        protection_current_a: 1.0,
                        over_current_protection_time_ms: 100,
                        max_torque_limit_percent: 50.0,
                        max_temperature_c: 60,
                    }),
                    calibration: config.calibration_for(bus_config, &s.joint),
                    ready: false,
                    goal: 0,
                    written: 0.0,
                    seen: Sighting::Never,
                    goal_at_ns: 0,
                    torque_wanted: 0,
                    torque_written: 0,
                    cutoff: CutoffWatch::default(),
                    gate: FeedbackGate::with_silence(silence_s),
                    misses: 0,
                    setup_fails: 0,
                    next_setup: 0,
                    confirmed: None,
                });
            }
            let n = bus_config.servo.len();
            buses.push(BusState {
                name: bus_config.name.clone(),
                mode: bus_config.mode,
                bus: Bus::new(transport, margin),
                ids: bus_config.servo.iter().map(|s| s.id).collect(),
                first_joint,
                feedback: vec![None; n],
                payload: Vec::with_capacity(n * 3),
                directed_off: false,
                latched: false,
                own_trip: false,
                failed: false,
                connected: true,
                silent_cycles: 0,
            });
        }
        let state = JointState {
            joint_count: joints.len() as u32,
            ..JointState::default()
        };
        Driver {
            buses,
            joints,
            state,
            goal_max_age_ns: c.goal_max_age_ms * MS,
            max_wheel_speed: c.max_wheel_speed_rad_s,
            wheel_timeout_ns: c.wheel_command_timeout_ms * MS,
            safe_kind: c.safe_state,
            hold_permille: (c.safe_hold_torque_percent * 10.0).round() as u16,
            safe: c.supervisor_timeout_ms > 0,
            operator_stop: false,
            recovered_at_ns: 0,
            supervised: false,
            last_resort_trip_c: f32::from(c.last_resort_trip_c),
            setup_retry_cycles: c.rate_hz.round().max(1.0) as u64,
            // 200 ms of silence: 40 cycles at 200 Hz; a reopen attempt every 100 ms.
            lost_after: (c.rate_hz / 5.0).round().max(2.0) as u32,
            reopen_every: (c.rate_hz / 10.0).round().max(1.0) as u64,
            // Every 20 ms: each of 8 servos confirmed every 160 ms at rest.
            read_back_every: (c.rate_hz / 50.0).round().max(1.0) as u64,
            reply_margin: margin,
            background_read_back: true,
            approach: Approach::new(c.rate_hz, STEPS_PER_RAD),
            slowed_approach: true,
            read_back_cursor: vec![0; c.bus.len()],
            read_back_now: vec![None; c.bus.len()],
            next_setup_any: 0,
            next_retry: 0,
            counters: DriverCounters::default(),
        }
    }

    /// Joint names in frame order.
    pub fn joint_names(&self) -> impl Iterator<Item = &str> {
        self.joints.iter().map(|j| j.name.as_str())
    }

    /// Whether each joint is set up and driven.
    pub fn ready(&self) -> impl Iterator<Item = bool> + '_ {
        self.joints.iter().map(|j| j.ready)
    }

    /// Hands each tapped bus's traffic since the last call to `publish` (stamped with the
    /// cycle and the bus's index; a bus that moved nothing is skipped), then empties it.
    pub fn drain_wire(&mut self, publish: &mut dyn FnMut(&WireFrame)) {
        let cycle = self.counters.cycles;
        for (bi, b) in self.buses.iter_mut().enumerate() {
            b.bus.transport_mut().take_wire(&mut |wire| {
                wire.cycle = cycle;
                wire.bus = bi as u32;
                publish(wire);
            });
        }
    }

    /// Error counters of each bus, by name.
    pub fn bus_counters(&self) -> impl Iterator<Item = (&str, BusCounters)> {
        self.buses.iter().map(|b| (b.name.as_str(), b.bus.counters))
    }

    /// Whether each bus's device is open now, by name.
    pub fn bus_connected(&self) -> impl Iterator<Item = (&str, bool)> {
        self.buses.iter().map(|b| (b.name.as_str(), b.connected))
    }

    /// Fills `out` with every bus's error counts (no allocation: callable every cycle).
    pub fn health(&self, out: &mut BusHealth) {
        out.seq = self.state.seq;
        out.timestamp_ns = self.state.timestamp_ns;
        out.bus_count = self.buses.len().min(MAX_BUSES) as u32;
        for (b, e) in self.buses.iter().zip(out.buses.iter_mut()) {
            *e = BusHealthEntry {
                counters: b.bus.counters,
                flags: (u32::from(b.connected) * BUS_HEALTH_CONNECTED)
                    | (u32::from(b.on()) * BUS_HEALTH_ENABLED)
                    | (u32::from(b.latched) * BUS_HEALTH_LATCHED)
                    | (u32::from(b.own_trip) * BUS_HEALTH_DRIVER_TRIP),
                reserved: 0,
            };
        }
    }

    /// The latest state frame.
    pub fn state(&self) -> &JointState {
        &self.state
    }

    /// Whether the safe state is applied.
    pub fn in_safe_state(&self) -> bool {
        self.safe
    }

    /// Whether the supervisor's directives hold the robot stopped for an operator: the safe
    /// state may not be left while they do.
    pub fn operator_stopped(&self) -> bool {
        self.operator_stop
    }

    /// The joints and buses, for other processes.
    pub fn layout(&self) -> JointLayout {
        let mut layout = JointLayout {
            joint_count: self.joints.len() as u32,
            bus_count: self.buses.len() as u32,
            ..JointLayout::default()
        };
        for (b, bus) in self.buses.iter().enumerate() {
            layout.set_bus_name(b, &bus.name);
            for k in 0..bus.ids.len() {
                let j = &self.joints[bus.first_joint + k];
                let mut info = JointInfo {
                    bus: b as u8,
                    role: j.role as u8,
                    id: j.id,
                    model: j.model.model_number(),
                    max_temperature_c: j.backstops.max_temperature_c,
                    range_rad: j.calibration.map_or([0.0; 2], |c| {
                        let (lo, hi) = c.range_rad();
                        [lo as f32, hi as f32]
                    }),
                    ..JointInfo::default()
                };
                info.set_name(&j.name);
                layout.joints[bus.first_joint + k] = info;
            }
        }
        layout
    }

    /// Brings every servo up, in up to [`SETUP_PASSES`] passes over those that failed (a bus
    /// that just powered up may miss the first requests); returns the last failures. Those
    /// joints stay off and are retried every second by the loop. In the torque-off safe state
    /// nothing is brought up: that happens when the safe state is left.
    ///
    /// Wheels first: a wheel servo keeps turning at its last speed while no driver runs (it has
    /// no watchdog), and its set-up (torque off, then a speed of 0) is what stops it after a
    /// driver crash; an arm servo holds its last goal meanwhile.
    pub fn setup(&mut self) -> Vec<(String, SetupError)> {
        let mut pending: Vec<usize> = (0..self.joints.len())
            .filter(|&j| self.may_drive(j))
            .collect();
        pending.sort_by_key(|&j| self.buses[self.bus_of(j)].mode != Mode::Speed);
        let mut failures = Vec::new();
        for _ in 0..SETUP_PASSES {
            failures.clear();
            let mut still = Vec::new();
            for &j in &pending {
                if let Err(e) = self.setup_joint(j) {
                    self.counters.setup_failures += 1;
                    failures.push((self.joints[j].name.clone(), e));
                    still.push(j);
                }
            }
            pending = still;
            if pending.is_empty() {
                break;
            }
        }
        failures
    }

    fn bus_of(&self, joint: usize) -> usize {
        self.buses
            .iter()
            .rposition(|b| b.first_joint <= joint)
            .unwrap_or(0)
    }

    /// Whether joint `j` may have torque: nothing holds its bus off and no torque-off safe
    /// state holds.
    fn may_drive(&self, j: usize) -> bool {
        self.buses[self.bus_of(j)].on() && !(self.safe && self.safe_kind == SafeState::TorqueOff)
    }

    /// Latches off every bus holding one of `joints` (the trip record's names) and releases
    /// the others; returns the latched buses, one bit each. Called at start, before any torque
    /// is turned on, and by the loop before it obeys a directive that would release a latch.
    /// A newly latched bus gets torque off at once.
    pub fn set_latch(&mut self, joints: &[String]) -> u32 {
        let mut mask = 0;
        for b in 0..self.buses.len() {
            let range =
                self.buses[b].first_joint..self.buses[b].first_joint + self.buses[b].ids.len();
            let named = self.joints[range].iter().any(|j| joints.contains(&j.name));
            self.change_bus(b, |bus| bus.latched = named);
            mask |= u32::from(named) << b;
        }
        mask
    }

    /// Latches off every bus: the record could not be read, and an unknown latch is kept.
    pub fn latch_all(&mut self) {
        for b in 0..self.buses.len() {
            self.change_bus(b, |bus| bus.latched = true);
        }
    }

    /// Whether `d` would turn on a bus that the trip record latches: the record must be read
    /// again first (the supervisor clears it before it releases a bus).
    pub fn latch_release_pending(&self, d: &Directives) -> bool {
        self.buses
            .iter()
            .enumerate()
            .any(|(b, bus)| bus.latched && d.bus_enabled & (1 << b) != 0)
    }

    /// Tells the driver whether a live supervisor is heard (its last-resort thermal tier acts
    /// only while none is).
    pub fn set_supervised(&mut self, supervised: bool) {
        self.supervised = supervised;
    }

    /// Changes what holds bus `b` off and acts on the outcome: a bus turned off gets torque off
    /// at once; a bus turned on gets its servos set up again, one at a time by the loop
    /// ([`Driver::retry_setup`]), so no cycle carries more than one setup.
    fn change_bus(&mut self, b: usize, change: impl FnOnce(&mut BusState<T>)) {
        let was = self.buses[b].on();
        change(&mut self.buses[b]);
        match (was, self.buses[b].on()) {
            (true, false) => self.disable_bus(b),
            (false, true) => {
                let bus = &self.buses[b];
                tracing::info!(bus = %bus.name, "bus on again: its servos are set up one at a time");
                let range = bus.first_joint..bus.first_joint + bus.ids.len();
                self.joints[range].iter_mut().for_each(Joint::set_up_again);
            }
            _ => {}
        }
    }

    /// One servo: model check, EEPROM backstops (read-compare-write), torque limit, first goal at
    /// the present position (clamped into range), torque on.
    fn setup_joint(&mut self, j: usize) -> Result<(), SetupError> {
        let b = self.bus_of(j);
        let (id, model, backstops, calibration) = {
            let joint = &self.joints[j];
            (joint.id, joint.model, joint.backstops, joint.calibration)
        };
        let torque = self.effective_torque(j);
        let mode = self.buses[b].mode;
        let bus = &mut self.buses[b].bus;
        bus.alone_at(id)?;
        let found = bus.read(id, reg::MODEL_NUMBER)?;
        if ServoModel::from_model_number(found as u16) != Some(model) {
            return Err(SetupError::WrongModel {
                id,
                expected: model,
                found,
            });
        }
        bus.write(id, reg::TORQUE_ENABLE, 0)?;
        if let Some(cal) = &calibration {
            let expected = backstops::calibration_settings(cal);
            let mut found = [0; 3];
            for (f, s) in found.iter_mut().zip(&expected) {
                *f = bus.read(id, s.register)?;
            }
            let expected = expected.map(|s| s.value);
            if found != expected {
                return Err(SetupError::NotCalibrated {
                    id,
                    found,
                    expected,
                });
            }
        }
        let desired = backstops::desired(&backstops, mode);
        let mut current = Vec::with_capacity(desired.len());
        for s in &desired {
            current.push(Some(bus.read(id, s.register)?));
        }
        let writes = backstops::plan(&desired, &current);
        if !writes.is_empty() {
            bus.write(id, reg::LOCK, 0)?;
            for s in &writes {
                bus.write(id, s.register, s.value)?;
            }
            bus.write(id, reg::LOCK, 1)?;
            self.counters.eeprom_writes += writes.len() as u64;
            tracing::info!(joint = %self.joints[j].name, id, writes = writes.len(), "EEPROM backstops written");
        }
        let bus = &mut self.buses[b].bus;
        bus.write(id, reg::TORQUE_LIMIT, i32::from(torque))?;
        let goal = match (mode, calibration) {
            (Mode::Position, Some(cal)) => {
                let present = steady_position(bus, id)?;
                let goal = present.clamp(cal.range_min, cal.range_max);
                bus.write(id, reg::GOAL_POSITION, goal)?;
                goal
            }
            _ => {
                bus.write(id, reg::GOAL_VELOCITY, 0)?;
                0
            }
        };
        bus.write(id, reg::TORQUE_ENABLE, 1)?;
        let joint = &mut self.joints[j];
        joint.goal = goal;
        joint.written = f64::from(goal);
        joint.seen = Sighting::Earlier(goal);
        joint.torque_written = torque;
        joint.cutoff.reset();
        joint.ready = true;
        Ok(())
    }

    /// The torque limit joint `j` gets now: the configured maximum, lowered by the supervisor's
    /// directive and by the hold safe state.
    fn effective_torque(&self, j: usize) -> u16 {
        let joint = &self.joints[j];
        let mut t = joint.max_torque();
        if joint.torque_wanted > 0 {
            t = t.min(joint.torque_wanted);
        }
        if self.safe && self.safe_kind == SafeState::Hold {
            t = t.min(self.hold_permille);
        }
        t
    }

    /// Applies a goal frame: all of it or, with the reason, none of it. Goals are clamped into
    /// each joint's calibrated range (or the wheel speed limit) here, at the bus layer.
    /// A frame on `path` naming a joint the path does not carry is refused whole.
    pub fn apply_goals(
        &mut self,
        frame: &GoalFrame,
        now_ns: u64,
        path: GoalPath,
    ) -> Result<(), GoalRejection> {
        let result = self.check_goals(frame, now_ns, path);
        let c = &mut self.counters;
        match result {
            Ok(()) => c.goals_accepted += 1,
            Err(GoalRejection::NotInForce(_) | GoalRejection::BeforeRecovery) => c.goals_stale += 1,
            Err(GoalRejection::SafeState) => c.goals_in_safe_state += 1,
            Err(GoalRejection::NotFinite(_)) => c.goals_not_finite += 1,
            Err(_) => c.goals_malformed += 1,
        }
        result
    }

    fn check_goals(
        &mut self,
        frame: &GoalFrame,
        now_ns: u64,
        path: GoalPath,
    ) -> Result<(), GoalRejection> {
        let n = self.joints.len() as u32;
        if frame.joint_count != n {
            return Err(GoalRejection::WrongJointCount {
                expected: n,
                got: frame.joint_count,
            });
        }
        if n < 32 && frame.mask >> n != 0 {
            return Err(GoalRejection::MaskOutOfRange {
                mask: frame.mask,
                joint_count: n,
            });
        }
        let wheels = self
            .joints
            .iter()
            .enumerate()
            .filter(|(_, j)| j.role == JointRole::Wheel)
            .fold(0u32, |m, (i, _)| m | 1 << i);
        let (foreign, what) = match path {
            GoalPath::Joints => (frame.mask & wheels, "a wheel"),
            GoalPath::Wheels => (frame.mask & !wheels, "a joint that is not a wheel"),
        };
        if foreign != 0 {
            return Err(GoalRejection::WrongPath {
                mask: frame.mask,
                what,
                path,
            });
        }
        in_force(frame.timestamp_ns, now_ns, self.goal_max_age_ns)?;
        if self.safe {
            return Err(GoalRejection::SafeState);
        }
        if frame.timestamp_ns < self.recovered_at_ns {
            return Err(GoalRejection::BeforeRecovery);
        }
        // Convert all before applying any: a frame is applied whole or not at all.
        let mut goals = [0i32; MAX_JOINTS];
        let mut clamped = 0;
        for (i, joint) in self.joints.iter().enumerate() {
            if frame.mask & (1 << i) == 0 {
                continue;
            }
            let q = frame.position_rad[i];
            goals[i] = match joint.calibration {
                Some(cal) => {
                    let steps = cal.goal_steps(i, q)?;
                    let (lo, hi) = cal.range_rad();
                    if f64::from(q) < lo - 1e-3 || f64::from(q) > hi + 1e-3 {
                        clamped += 1;
                    }
                    steps
                }
                None => {
                    if f64::from(q).abs() > self.max_wheel_speed + 1e-3 {
                        clamped += 1;
                    }
                    wheel_speed_steps(i, q, self.max_wheel_speed, false)?
                }
            };
        }
        for (i, joint) in self.joints.iter_mut().enumerate() {
            if frame.mask & (1 << i) != 0 {
                joint.goal = goals[i];
                joint.goal_at_ns = frame.timestamp_ns;
            }
        }
        self.counters.goals_clamped += clamped;
        Ok(())
    }

    /// Applies the supervisor's directives: per-joint torque limits (written in the next cycle)
    /// and bus enables (a disabled bus gets torque off at once; a re-enabled one is set up again,
    /// one servo at a time, starting at its present positions). A bus the trip record latches
    /// stays off whatever the directive says (see [`Driver::set_latch`]); a bus the driver's own
    /// last-resort tier turned off stays off until a directive turns it off too: the supervisor
    /// has then taken the trip over (and recorded it).
    pub fn apply_directives(&mut self, d: &Directives) -> Result<(), DirectiveMismatch> {
        if d.joint_count != self.joints.len() as u32 {
            return Err(DirectiveMismatch {
                expected: self.joints.len() as u32,
                got: d.joint_count,
            });
        }
        for (j, joint) in self.joints.iter_mut().enumerate() {
            joint.torque_wanted = d.torque_limit_permille[j];
        }
        let stop = d.flags & DIRECTIVE_FLAG_STOP != 0;
        if stop != self.operator_stop {
            tracing::warn!(
                "an operator {} the robot",
                if stop { "stops" } else { "resumes" }
            );
        }
        self.operator_stop = stop;
        if stop {
            self.state.flags |= STATE_FLAG_OPERATOR_STOP;
            self.enter_safe_state();
        } else {
            self.state.flags &= !STATE_FLAG_OPERATOR_STOP;
        }
        for b in 0..self.buses.len() {
            let off = d.bus_enabled & (1 << b) == 0;
            if off != self.buses[b].directed_off {
                tracing::warn!(bus = %self.buses[b].name, off, "the supervisor turns the bus {}", if off { "off" } else { "on" });
            }
            self.change_bus(b, |bus| {
                bus.directed_off = off;
                if off {
                    bus.own_trip = false;
                }
            });
        }
        Ok(())
    }

    /// Torque off on the whole bus (broadcast, twice: one corrupted packet must not leave a bus
    /// energised); its joints are no longer driven.
    fn disable_bus(&mut self, b: usize) {
        let bus = &mut self.buses[b];
        let _ = bus.bus.torque_off_all();
        let _ = bus.bus.torque_off_all();
        let range = bus.first_joint..bus.first_joint + bus.ids.len();
        for joint in &mut self.joints[range] {
            joint.ready = false;
        }
        self.counters.bus_disables += 1;
    }

    /// The last-resort thermal tier: with no live supervisor, a bus one of whose motors reads
    /// the trip temperature (validly: the feedback gate has already held back glitches) is
    /// turned off by the driver itself. The firmware cutoff is then not the only protection
    /// during a supervisor crash loop.
    fn last_resort_tier(&mut self) {
        if self.supervised {
            return;
        }
        for b in 0..self.buses.len() {
            if !self.buses[b].on() {
                continue;
            }
            let first = self.buses[b].first_joint;
            let hot = (first..first + self.buses[b].ids.len()).find(|&j| {
                let s = &self.state.joints[j];
                s.is_valid() && s.temperature_c >= self.last_resort_trip_c
            });
            if let Some(j) = hot {
                tracing::warn!(
                    bus = %self.buses[b].name,
                    joint = %self.joints[j].name,
                    temperature_c = self.state.joints[j].temperature_c,
                    "no supervisor heard and a motor reached the trip temperature: the driver turns the bus off itself"
                );
                self.counters.last_resort_trips += 1;
                self.change_bus(b, |bus| bus.own_trip = true);
            }
        }
    }

    /// Applies the configured safe state: `hold` freezes every goal at the present position with
    /// a low torque limit; `torque-off` turns every bus off. Goals are refused until
    /// [`Driver::leave_safe_state`].
    pub fn enter_safe_state(&mut self) {
        if self.safe {
            return;
        }
        self.safe = true;
        self.counters.safe_state_entries += 1;
        self.state.flags |= STATE_FLAG_SAFE_STATE;
        match self.safe_kind {
            SafeState::TorqueOff => {
                for b in &mut self.buses {
                    let _ = b.bus.torque_off_all();
                    let _ = b.bus.torque_off_all();
                }
                for j in &mut self.joints {
                    j.ready = false;
                }
            }
            // Hold where the joints are (their last reading), not where they were sent.
            SafeState::Hold => self.hold_where_they_are(),
        }
    }

    /// Leaves the safe state: torque limits return to the directives, and goals produced
    /// before `now_ns` are refused (they were meant for another situation). `hold` re-holds
    /// every joint where it is now before its torque comes back (an arm that sagged at the
    /// hold torque must not snap back to where it was frozen); `torque-off` brings the servos
    /// up again at their present positions, one at a time. Never while an operator's stop is
    /// in force.
    pub fn leave_safe_state(&mut self, now_ns: u64) {
        if !self.safe || self.operator_stop {
            return;
        }
        self.safe = false;
        self.recovered_at_ns = now_ns;
        self.state.flags &= !STATE_FLAG_SAFE_STATE;
        match self.safe_kind {
            SafeState::Hold => self.hold_where_they_are(),
            SafeState::TorqueOff => self.joints.iter_mut().for_each(Joint::set_up_again),
        }
    }

    /// Every position joint's goal becomes its last valid reading (clamped into range), or,
    /// not read this cycle, the goal its servo was last sent (not one still on its way toward
    /// an end); a wheel's becomes 0.
    fn hold_where_they_are(&mut self) {
        for (j, joint) in self.joints.iter_mut().enumerate() {
            let s = &self.state.joints[j];
            match (joint.calibration, s.is_valid()) {
                (Some(cal), true) => {
                    if let Ok(steps) = cal.goal_steps(j, s.position_rad) {
                        joint.goal = steps;
                    }
                }
                (Some(_), false) => joint.goal = joint.written_steps(),
                (None, _) => joint.goal = 0,
            }
        }
    }

    /// One control cycle: read every bus, fill the state frame, write every bus's goals (and any
    /// torque limit that changed). A bus whose device failed is marked lost (its joints flagged
    /// and missing) and reopened every 100 ms; a servo, or a whole bus, silent for 200 ms is
    /// taken off (the safe state applied to it) and set up again once it answers. `clock`
    /// (CLOCK_MONOTONIC, ns, in the process) is read when the replies come in, for the
    /// plausibility gate, and once they are all in, for the frame's stamp.
    pub fn cycle(&mut self, clock: fn() -> u64) -> &JointState {
        // The replies to the read-backs requested in the last period's idle time have had that
        // time to arrive: take them before anything else is sent on the buses.
        self.collect_read_backs(std::time::Duration::ZERO);
        let now_s = clock() as f64 * 1e-9;
        for b in &mut self.buses {
            b.failed = !b.connected || b.bus.request_feedback(&b.ids).is_err();
        }
        for bi in 0..self.buses.len() {
            let b = &mut self.buses[bi];
            let mut newly_lost = false;
            if b.failed || b.bus.collect_feedback(&b.ids, &mut b.feedback).is_err() {
                b.feedback.iter_mut().for_each(|f| *f = None);
                newly_lost = b.connected;
            }
            let mut answered = 0;
            for (k, fb) in b.feedback.iter().enumerate() {
                let j = b.first_joint + k;
                let joint = &mut self.joints[j];
                let mut fb = fb.as_ref();
                if fb.is_some_and(|(block, _)| !joint.gate.admit(block, now_s)) {
                    // Held back: a missing sample, and a miss towards taking the servo off (a
                    // servo answering garbage for 200 ms is as good as silent).
                    fb = None;
                    b.bus.counters.implausible += 1;
                }
                joint.seen = joint.seen.after(fb.map(|(block, _)| block.position));
                let mut s = sample(joint, fb);
                if fb.is_some() {
                    answered += 1;
                    joint.misses = 0;
                } else {
                    joint.misses = joint.misses.saturating_add(1);
                }
                if let (true, Some(cal), true) = (joint.ready, joint.calibration, s.is_valid()) {
                    // Against the goal the servo holds (on its slowed approach to a range's
                    // end, behind the one asked for, which the state publishes).
                    let error = cal.to_rad(joint.written_steps()) as f32 - s.position_rad;
                    if joint.cutoff.update(error, s.load, s.current_a) {
                        self.counters.outputs_lost += 1;
                    }
                } else {
                    joint.cutoff.reset();
                }
                if joint.cutoff.lost {
                    s.flags |= JOINT_FLAG_OUTPUT_LOST;
                }
                if !b.on() {
                    s.flags |= JOINT_FLAG_BUS_DISABLED;
                }
                if b.own_trip {
                    s.flags |= JOINT_FLAG_DRIVER_TRIP;
                }
                if !b.connected || newly_lost {
                    s.flags |= JOINT_FLAG_BUS_LOST;
                }
                self.state.joints[j] = s;
            }
            b.silent_cycles = if answered == 0 {
                b.silent_cycles.saturating_add(1)
            } else {
                0
            };
            if newly_lost {
                self.lose_bus(bi);
            } else if b.connected {
                self.watch_silence(bi);
            }
        }
        self.state.timestamp_ns = clock();
        self.last_resort_tier();
        self.stop_stale_wheels(self.state.timestamp_ns);
        for bi in 0..self.buses.len() {
            if self.buses[bi].connected {
                self.write_goals(bi);
                self.write_torque_limits(bi);
            }
        }
        if self.request_read_backs(false) {
            self.collect_read_backs(self.read_back_margin());
        }
        self.reopen_lost();
        self.retry_setup();
        self.counters.cycles += 1;
        self.state.seq = self.counters.cycles;
        self.state.deadline_misses = self.counters.deadline_misses;
        &self.state
    }

    /// The bus's device failed: its joints are no longer driven (nothing can reach them) and
    /// are set up again, from their present positions, once the device is back.
    fn lose_bus(&mut self, bi: usize) {
        let b = &mut self.buses[bi];
        b.connected = false;
        b.bus.counters.disconnects += 1;
        let range = b.first_joint..b.first_joint + b.ids.len();
        tracing::warn!(bus = %b.name, "bus device lost: its joints are missing; reopening every {} cycles", self.reopen_every);
        for joint in &mut self.joints[range] {
            joint.set_up_again();
        }
    }

    /// Every `reopen_every` cycles, opens each lost device again. On success the configured
    /// safe state is applied to the whole bus at once (its servos kept the last goal while it
    /// was gone): `torque-off` switches them off, `hold` lowers their torque limit; then the
    /// servos are set up again one at a time as they answer.
    fn reopen_lost(&mut self) {
        if !self.counters.cycles.is_multiple_of(self.reopen_every) {
            return;
        }
        for bi in 0..self.buses.len() {
            let b = &mut self.buses[bi];
            if b.connected || b.bus.reopen().is_err() {
                continue;
            }
            b.connected = true;
            b.silent_cycles = 0;
            b.bus.counters.reconnects += 1;
            tracing::info!(bus = %b.name, "bus device back: safe state applied, servos set up again");
            self.safe_state_on_bus(bi, None);
        }
    }

    /// Applies the configured safe state to one servo (`Some(id)`) or a whole bus (`None`)
    /// without waiting for an answer (a SYNC_WRITE or a broadcast: it may not answer). Sent
    /// twice: one corrupted packet must not leave a servo energised.
    fn safe_state_on_bus(&mut self, bi: usize, id: Option<u8>) {
        let hold = self.hold_permille;
        let kind = self.safe_kind;
        let b = &mut self.buses[bi];
        for _ in 0..2 {
            let _ = match (kind, id) {
                (SafeState::TorqueOff, None) => b.bus.torque_off_all(),
                (SafeState::TorqueOff, Some(id)) => b.bus.torque_off_one(id),
                (SafeState::Hold, None) => b
                    .bus
                    .broadcast_write(reg::TORQUE_LIMIT.addr, &hold.to_le_bytes()),
                (SafeState::Hold, Some(id)) => b.bus.torque_limit_one(id, hold),
            };
        }
    }

    /// A servo silent for `lost_after` cycles is taken off (safe state, not driven, set up
    /// again when it answers); a whole bus silent that long gets the safe state at once.
    fn watch_silence(&mut self, bi: usize) {
        let limit = self.lost_after;
        let first = self.buses[bi].first_joint;
        let n = self.buses[bi].ids.len();
        if self.buses[bi].silent_cycles == limit {
            self.buses[bi].bus.counters.silences += 1;
            tracing::warn!(bus = %self.buses[bi].name, "no servo of the bus answers: safe state applied to it");
            self.safe_state_on_bus(bi, None);
        }
        for k in 0..n {
            let j = first + k;
            if self.joints[j].ready && self.joints[j].misses >= limit {
                self.joints[j].set_up_again();
                self.buses[bi].bus.counters.servos_lost += 1;
                tracing::warn!(joint = %self.joints[j].name, "servo silent: taken off, set up again when it answers");
                let id = self.joints[j].id;
                self.safe_state_on_bus(bi, Some(id));
            }
        }
    }

    /// What joint `j` must hold now (see [`Want`]).
    fn want(&self, j: usize) -> Want {
        let joint = &self.joints[j];
        if !self.may_drive(j) {
            return Want::Off;
        }
        if !joint.ready {
            return match self.safe_kind {
                SafeState::TorqueOff => Want::Off,
                SafeState::Hold => Want::AtMost {
                    limit: self.hold_permille,
                },
            };
        }
        let held = self.safe && self.safe_kind == SafeState::Hold;
        Want::On {
            limit: self.effective_torque(j),
            hold_goal: held.then_some(joint.written_steps()),
        }
    }

    /// Requests, on each bus, the read-back of one servo: with `in_turn`, the next one in turn;
    /// otherwise one whose wanted safety settings are not confirmed yet (they changed: the write
    /// went out this cycle or earlier and may have been lost), which is part of every cycle and
    /// rare. Only servos that answered this cycle's feedback read are read back, so a silent
    /// servo costs no wait. All buses' reads are started before any is collected. Returns
    /// whether any was requested.
    fn request_read_backs(&mut self, in_turn: bool) -> bool {
        let mut any = false;
        for bi in 0..self.buses.len() {
            let b = &self.buses[bi];
            if !b.connected || b.failed || self.read_back_now[bi].is_some() {
                continue;
            }
            let n = b.ids.len();
            let answered = |k: usize| self.state.joints[b.first_joint + k].is_valid();
            let unconfirmed = |k: usize| {
                let j = b.first_joint + k;
                self.joints[j].confirmed != Some(self.want(j))
            };
            let start = self.read_back_cursor[bi];
            let pick = (0..n)
                .map(|i| (start + i) % n)
                .find(|&k| answered(k) && (in_turn || unconfirmed(k)));
            let Some(k) = pick else { continue };
            let (id, j) = (b.ids[k], b.first_joint + k);
            self.read_back_cursor[bi] = (k + 1) % n;
            if self.buses[bi]
                .bus
                .request_read(id, reg::SAFETY_ADDR, reg::SAFETY_LEN)
                .is_ok()
            {
                self.read_back_now[bi] = Some(j);
                any = true;
            }
        }
        any
    }

    /// Collects the read-backs requested, waiting at most `margin` past each reply's wire time,
    /// and holds each against what its servo must hold.
    fn collect_read_backs(&mut self, margin: std::time::Duration) {
        for bi in 0..self.buses.len() {
            let Some(j) = self.read_back_now[bi].take() else {
                continue;
            };
            let mut raw = [0u8; reg::SAFETY_LEN as usize];
            let block = match self.buses[bi].bus.collect_read(&mut raw, margin) {
                Ok(Some(_)) => reg::SafetyBlock::parse(&raw),
                _ => None,
            };
            match block {
                Some(block) => {
                    self.buses[bi].bus.counters.read_backs += 1;
                    self.check_safety(bi, j, &block);
                }
                None => self.buses[bi].bus.counters.read_back_missing += 1,
            }
        }
    }

    /// The background pass: every `read_back_every` cycles, requests the read-back of the next
    /// servo of each bus in turn, confirmed or not (a servo reset, or a write corrupted into
    /// another value that the checksum let through). It does not wait: the replies are taken at
    /// the start of the next cycle. The loop calls it in its idle time, when the rest of the
    /// period can carry the exchange ([`Driver::read_back_cost`]), so it never costs the loop
    /// a wait and a reply never meets the next cycle's transaction on the line.
    pub fn read_back_in_turn(&mut self) {
        if self.background_read_back && self.counters.cycles.is_multiple_of(self.read_back_every) {
            self.request_read_backs(true);
        }
    }

    /// Turns the background read-back off or on (it is on; `nori bench driver-rate` turns it
    /// off for the baseline it measures its cost against). The read-back of changed settings
    /// is part of every cycle and stays.
    pub fn set_background_read_back(&mut self, on: bool) {
        self.background_read_back = on;
    }

    /// Turns the slowed approach to the ends of each range off or on (it is on; `nori bench
    /// driver-rate` turns it off for the baseline it measures its cost against, and the tests
    /// for the unslowed drive they compare with and for the range clamp alone).
    pub fn set_slowed_approach(&mut self, on: bool) {
        self.slowed_approach = on;
    }

    /// The longest one read-back pass can take: its wire time plus its reply margin.
    pub fn read_back_cost(&self) -> std::time::Duration {
        let slowest = self
            .buses
            .iter()
            .map(|b| b.bus.baud())
            .min()
            .unwrap_or(1_000_000);
        crate::bus::read_time(reg::SAFETY_LEN, slowest) + self.read_back_margin()
    }

    /// How long an in-cycle read-back's reply is waited for beyond its wire time: a quarter of
    /// the feedback's margin (a later reply is no loss: the servo is read again next cycle).
    fn read_back_margin(&self) -> std::time::Duration {
        self.reply_margin / 4
    }

    /// Holds a read-back against what joint `j` must hold; what differs is re-sent at once and
    /// counted, and the joint stays unconfirmed (read again next cycle) until it holds.
    fn check_safety(&mut self, bi: usize, j: usize, block: &reg::SafetyBlock) {
        let want = self.want(j);
        let position_mode = self.buses[bi].mode == Mode::Position;
        let goal = if position_mode {
            block.goal_position
        } else {
            block.goal_velocity
        };
        let id = self.joints[j].id;
        let holds = match want {
            Want::Off => block.torque_enable == 0,
            Want::On { limit, hold_goal } => {
                block.torque_enable == 1
                    && block.torque_limit == limit
                    && hold_goal.is_none_or(|g| g == goal)
            }
            Want::AtMost { limit } => block.torque_enable == 0 || block.torque_limit <= limit,
        };
        if holds {
            self.joints[j].confirmed = Some(want);
            return;
        }
        self.joints[j].confirmed = None;
        self.buses[bi].bus.counters.safety_mismatches += 1;
        let bus = &mut self.buses[bi].bus;
        match want {
            Want::Off => {
                let _ = bus.torque_off_one(id);
            }
            Want::AtMost { limit } => {
                let _ = bus.torque_limit_one(id, limit);
            }
            Want::On { limit, .. } if block.torque_enable == 1 => {
                // The goal is written every cycle anyway; the limit is re-sent here.
                let _ = bus.torque_limit_one(id, limit);
            }
            Want::On { .. } => {
                // The servo dropped its torque on its own (a reset restores SRAM defaults):
                // set it up again from where it is, like a servo that came back.
                tracing::warn!(joint = %self.joints[j].name, "servo found with torque off: set up again");
                self.joints[j].set_up_again();
            }
        }
    }

    /// A wheel whose speed command is older than the timeout is stopped (its goal, and so the
    /// state frame's `goal_rad`, becomes 0): the base never drives on at a command nobody
    /// renews. Position joints hold their goals as they always do.
    fn stop_stale_wheels(&mut self, now_ns: u64) {
        for joint in &mut self.joints {
            if joint.calibration.is_none()
                && joint.goal != 0
                && now_ns.saturating_sub(joint.goal_at_ns) > self.wheel_timeout_ns
            {
                joint.goal = 0;
                self.counters.wheel_stops += 1;
            }
        }
    }

    fn write_goals(&mut self, bi: usize) {
        // Held (the safe state), each goal is where its joint was read: written as it is.
        let approach = (self.slowed_approach && !self.safe).then_some(self.approach);
        let b = &mut self.buses[bi];
        b.payload.clear();
        for (k, &id) in b.ids.iter().enumerate() {
            let joint = &mut self.joints[b.first_joint + k];
            // Goal_Position and Goal_Velocity are both sign-magnitude at bit 15; a value the
            // register cannot carry goes out clamped, never skipped (a skipped wheel goal would
            // keep the previous speed).
            if joint.ready {
                joint.written = match (joint.role, joint.calibration, approach) {
                    // Not a gripper: its grip is a goal past what it holds.
                    (JointRole::Joint, Some(cal), Some(a)) => a.next(
                        joint.goal,
                        joint.written,
                        joint.seen,
                        cal.range_min,
                        cal.range_max,
                    ),
                    _ => f64::from(joint.goal),
                };
                let goal = joint.written_steps();
                let raw = feetech::encoding::encode_sign_magnitude_saturating(goal, 15);
                b.payload.push(id);
                b.payload.extend_from_slice(&raw.to_le_bytes());
            }
        }
        if !b.payload.is_empty() {
            let addr = match b.mode {
                Mode::Position => reg::GOAL_POSITION.addr,
                Mode::Speed => reg::GOAL_VELOCITY.addr,
            };
            let _ = b.bus.sync_write(addr, 2, &b.payload);
        }
    }

    /// A SYNC_WRITE of Torque_Limit for the joints whose effective limit changed (rare: a
    /// directive or the safe state changed it).
    fn write_torque_limits(&mut self, bi: usize) {
        let first = self.buses[bi].first_joint;
        let n = self.buses[bi].ids.len();
        let wanted: [u16; MAX_JOINTS] = std::array::from_fn(|j| {
            if j < self.joints.len() {
                self.effective_torque(j)
            } else {
                0
            }
        });
        let b = &mut self.buses[bi];
        b.payload.clear();
        for k in 0..n {
            let joint = &mut self.joints[first + k];
            if joint.ready && joint.torque_written != wanted[first + k] {
                b.payload.push(joint.id);
                b.payload
                    .extend_from_slice(&wanted[first + k].to_le_bytes());
                joint.torque_written = wanted[first + k];
            }
        }
        if !b.payload.is_empty() {
            let _ = b.bus.sync_write(reg::TORQUE_LIMIT.addr, 2, &b.payload);
        }
    }

    /// Brings up at most one joint that is not ready and answered this cycle's feedback read
    /// (it was missing, lost, on a bus that came back, or refused at start), so a silent servo
    /// costs nothing. Setups are spaced by 1/50 s, and a joint that failed three times in a row
    /// is retried once a second. Each setup costs one slow cycle, counted as a deadline miss
    /// if it is one.
    fn retry_setup(&mut self) {
        let now = self.counters.cycles;
        if now < self.next_setup_any {
            return;
        }
        let n = self.joints.len();
        for k in 0..n {
            let j = (self.next_retry + k) % n;
            let b = self.bus_of(j);
            let joint = &self.joints[j];
            if joint.ready
                || now < joint.next_setup
                || !self.buses[b].connected
                || !self.state.joints[j].is_valid()
                || !self.may_drive(j)
            {
                continue;
            }
            self.next_retry = j + 1;
            self.next_setup_any = now + (self.setup_retry_cycles / 50).max(1);
            match self.setup_joint(j) {
                Ok(()) => {
                    self.joints[j].setup_fails = 0;
                    tracing::info!(joint = %self.joints[j].name, "servo came up");
                }
                Err(e) => {
                    self.counters.setup_failures += 1;
                    let joint = &mut self.joints[j];
                    joint.setup_fails += 1;
                    let wait = if joint.setup_fails >= 3 {
                        self.setup_retry_cycles
                    } else {
                        (self.setup_retry_cycles / 20).max(1)
                    };
                    joint.next_setup = now + wait;
                    if joint.setup_fails == 3 {
                        tracing::warn!(joint = %joint.name, "servo answers but setup keeps failing (retried every second): {e}");
                    }
                }
            }
            return;
        }
    }

    /// Torque off on every bus (broadcast), every joint marked not ready. Best effort: a bus
    /// whose transport is gone cannot be told, and its servos' firmware backstops remain.
    pub fn torque_off(&mut self) {
        for b in &mut self.buses {
            // Twice: one corrupted packet must not leave a bus energised.
            let _ = b.bus.torque_off_all();
            let _ = b.bus.torque_off_all();
        }
        for j in &mut self.joints {
            j.ready = false;
        }
        self.state.flags |= STATE_FLAG_SAFE_STATE;
    }
}

/// Passes of [`Driver::setup`] over servos that failed.
pub const SETUP_PASSES: usize = 3;

impl<T: Transport> Drop for Driver<T> {
    /// Every stop path, including errors and panics that unwind, leaves torque off.
    fn drop(&mut self) {
        self.torque_off();
    }
}

fn sample(joint: &Joint, fb: Option<&(FeedbackBlock, ServoStatus)>) -> JointSample {
    let Some((f, status)) = fb else {
        // Missing this cycle: never the previous value.
        return JointSample::default();
    };
    let (position, velocity, goal) = match joint.calibration {
        Some(cal) => {
            let sign = if cal.inverted { -1.0 } else { 1.0 };
            let position = cal.to_rad(f.position);
            // Not set up (torque off), it has no goal in force: none is published but where
            // it is read (a goal asked before its set-up is replaced by its reading then).
            let goal = if joint.ready {
                cal.to_rad(joint.goal)
            } else {
                position
            };
            (position, sign * f64::from(f.velocity) / STEPS_PER_RAD, goal)
        }
        None => (
            f64::from(f.position) / STEPS_PER_RAD,
            f64::from(f.velocity) / STEPS_PER_RAD,
            f64::from(joint.goal) / STEPS_PER_RAD,
        ),
    };
    JointSample {
        position_rad: position as f32,
        velocity_rad_s: velocity as f32,
        load: f.load as f32 / 1000.0,
        voltage_v: f32::from(f.voltage) / 10.0,
        temperature_c: f32::from(f.temperature),
        current_a: (f64::from(f.current) * AMPS_PER_CURRENT_UNIT) as f32,
        goal_rad: goal as f32,
        status: status.0 | f.status.0,
        valid: 1,
        torque_enabled: u8::from(joint.ready),
        flags: 0,
    }
}
