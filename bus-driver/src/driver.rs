//! The driver: servo setup, the control cycle, goal gating and the fixed-rate loop.
//!
//! Per cycle and bus: one SYNC_READ of the feedback block and one SYNC_WRITE of goals. All buses'
//! reads are started before any is collected, so their wire time overlaps. Time is passed in
//! (`now_ns`), so the cycle logic is tested without sleeping.

use crate::backstops;
use crate::bus::{Bus, BusCounters, BusError};
use crate::calibration::{wheel_speed_steps, GoalError, JointCalibration, STEPS_PER_RAD};
use crate::config::{Backstops, LoadedConfig, Mode};
use crate::transport::Transport;
use feetech::registers::{self as reg, FeedbackBlock};
use feetech::{ServoModel, ServoStatus, AMPS_PER_CURRENT_UNIT};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use telemetry::frames::STATE_FLAG_SAFE_STATE;
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
    /// Older than `goal-max-age-ms`.
    #[error("goal frame {age_ms} ms old (limit {limit_ms} ms)")]
    Stale {
        /// Age.
        age_ms: u64,
        /// Limit.
        limit_ms: u64,
    },
    /// Timestamped in the future: a clock that is not ours.
    #[error("goal frame timestamped {ahead_ms} ms in the future")]
    FromTheFuture {
        /// How far ahead.
        ahead_ms: u64,
    },
    /// A NaN or infinite goal.
    #[error(transparent)]
    NotFinite(#[from] GoalError),
}

/// Why a servo could not be brought up.
#[derive(Debug, Error)]
pub enum SetupError {
    /// Bus failure.
    #[error(transparent)]
    Bus(#[from] BusError),
    /// The servo is not the configured model.
    #[error("servo {id} reports model number {found}, configured {expected:?}")]
    WrongModel {
        /// Servo id.
        id: u8,
        /// Configured.
        expected: ServoModel,
        /// `Model_Number` read.
        found: i32,
    },
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
    /// Goal frames refused as stale (or from the future).
    pub goals_stale: u64,
    /// Goal frames refused for NaN/inf.
    pub goals_not_finite: u64,
    /// Goal frames refused for their shape.
    pub goals_malformed: u64,
    /// Single goals clamped into the calibrated range.
    pub goals_clamped: u64,
    /// EEPROM registers written at setup (read-compare-write).
    pub eeprom_writes: u64,
    /// Failed servo setups.
    pub setup_failures: u64,
}

/// Passes of [`Driver::setup`] over servos that failed.
pub const SETUP_PASSES: usize = 3;

struct Joint {
    name: String,
    id: u8,
    model: ServoModel,
    backstops: Backstops,
    calibration: Option<JointCalibration>,
    /// Set up, torque on, goals flowing.
    ready: bool,
    /// Goal in register units (steps, or steps/s in speed mode).
    goal: i32,
}

struct BusState<T: Transport> {
    name: String,
    mode: Mode,
    bus: Bus<T>,
    ids: Vec<u8>,
    first_joint: usize,
    feedback: Vec<Option<(FeedbackBlock, ServoStatus)>>,
    payload: Vec<u8>,
    /// The transport failed this cycle (feedback not requested).
    failed: bool,
}

/// The driver over one transport per bus.
pub struct Driver<T: Transport> {
    buses: Vec<BusState<T>>,
    joints: Vec<Joint>,
    state: JointState,
    goal_max_age: Duration,
    max_wheel_speed: f64,
    setup_retry_cycles: u64,
    next_retry: usize,
    /// Counters.
    pub counters: DriverCounters,
}

fn model_of(key: &str) -> ServoModel {
    match key {
        "sts3250" => ServoModel::Sts3250,
        "sts3095" => ServoModel::Sts3095,
        _ => ServoModel::Sts3215,
    }
}

impl<T: Transport> Driver<T> {
    /// A driver for a validated configuration, with one transport per configured bus, in order.
    pub fn new(config: &LoadedConfig, transports: Vec<T>) -> Self {
        let c = &config.config;
        let margin = Duration::from_micros(c.reply_timeout_margin_us);
        let mut joints = Vec::new();
        let mut buses = Vec::new();
        for (bus_config, transport) in c.bus.iter().zip(transports) {
            let first_joint = joints.len();
            for s in &bus_config.servo {
                joints.push(Joint {
                    name: s.joint.clone(),
                    id: s.id,
                    model: model_of(&s.model),
                    // Validated: every model has backstops.
                    backstops: c.backstops.get(&s.model).copied().unwrap_or(Backstops {
                        protection_current_a: 1.0,
                        over_current_protection_time_ms: 100,
                        max_torque_limit_percent: 50.0,
                        max_temperature_c: 60,
                    }),
                    calibration: match bus_config.mode {
                        Mode::Position => config.calibration.joint.get(&s.joint).copied(),
                        Mode::Speed => None,
                    },
                    ready: false,
                    goal: 0,
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
                failed: false,
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
            goal_max_age: Duration::from_millis(c.goal_max_age_ms),
            max_wheel_speed: c.max_wheel_speed_rad_s,
            setup_retry_cycles: c.rate_hz.round().max(1.0) as u64,
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

    /// Error counters of each bus, by name.
    pub fn bus_counters(&self) -> impl Iterator<Item = (&str, BusCounters)> {
        self.buses.iter().map(|b| (b.name.as_str(), b.bus.counters))
    }

    /// The latest state frame.
    pub fn state(&self) -> &JointState {
        &self.state
    }

    /// Brings every servo up, in up to [`SETUP_PASSES`] passes over those that failed (a bus
    /// that just powered up may miss the first requests); returns the last failures. Those
    /// joints stay off and are retried every second by the loop.
    pub fn setup(&mut self) -> Vec<(String, SetupError)> {
        let mut pending: Vec<usize> = (0..self.joints.len()).collect();
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

    /// One servo: model check, EEPROM backstops (read-compare-write), torque limit, first goal at
    /// the present position (clamped into range), torque on.
    fn setup_joint(&mut self, j: usize) -> Result<(), SetupError> {
        let b = self.bus_of(j);
        let (id, model, backstops, calibration) = {
            let joint = &self.joints[j];
            (joint.id, joint.model, joint.backstops, joint.calibration)
        };
        let mode = self.buses[b].mode;
        let bus = &mut self.buses[b].bus;
        bus.ping(id)?;
        let found = bus.read(id, reg::MODEL_NUMBER)?;
        if ServoModel::from_model_number(found as u16) != Some(model) {
            return Err(SetupError::WrongModel {
                id,
                expected: model,
                found,
            });
        }
        bus.write(id, reg::TORQUE_ENABLE, 0)?;
        let desired = backstops::desired(&backstops, mode, calibration.as_ref());
        let current: Vec<Option<i32>> = desired
            .iter()
            .map(|s| bus.read(id, s.register).ok())
            .collect();
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
        bus.write(
            id,
            reg::TORQUE_LIMIT,
            backstops::max_torque_permille(&backstops),
        )?;
        let goal = match (mode, calibration) {
            (Mode::Position, Some(cal)) => {
                let present = bus.read(id, reg::PRESENT_POSITION)?;
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
        joint.ready = true;
        Ok(())
    }

    /// Applies a goal frame: all of it or, with the reason, none of it. Goals are clamped into
    /// each joint's calibrated range (or the wheel speed limit) here, at the bus layer.
    pub fn apply_goals(&mut self, frame: &GoalFrame, now_ns: u64) -> Result<(), GoalRejection> {
        let result = self.check_goals(frame, now_ns);
        match result {
            Ok(()) => self.counters.goals_accepted += 1,
            Err(GoalRejection::Stale { .. } | GoalRejection::FromTheFuture { .. }) => {
                self.counters.goals_stale += 1
            }
            Err(GoalRejection::NotFinite(_)) => self.counters.goals_not_finite += 1,
            Err(_) => self.counters.goals_malformed += 1,
        }
        result
    }

    fn check_goals(&mut self, frame: &GoalFrame, now_ns: u64) -> Result<(), GoalRejection> {
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
        if frame.timestamp_ns > now_ns + 1_000_000 {
            return Err(GoalRejection::FromTheFuture {
                ahead_ms: (frame.timestamp_ns - now_ns) / 1_000_000,
            });
        }
        let age = telemetry::clock::age(frame.timestamp_ns, now_ns);
        if age > self.goal_max_age {
            return Err(GoalRejection::Stale {
                age_ms: age.as_millis() as u64,
                limit_ms: self.goal_max_age.as_millis() as u64,
            });
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
                    if q.is_finite()
                        && (f64::from(q) < cal.range_rad().0 - 1e-3
                            || f64::from(q) > cal.range_rad().1 + 1e-3)
                    {
                        clamped += 1;
                    }
                    steps
                }
                None => wheel_speed_steps(i, q, self.max_wheel_speed, false)?,
            };
        }
        for (i, joint) in self.joints.iter_mut().enumerate() {
            if frame.mask & (1 << i) != 0 {
                joint.goal = goals[i];
            }
        }
        self.counters.goals_clamped += clamped;
        Ok(())
    }

    /// One control cycle: read every bus, fill the state frame, write every bus's goals.
    pub fn cycle(&mut self) -> &JointState {
        for b in &mut self.buses {
            b.failed = b.bus.request_feedback(&b.ids).is_err();
        }
        for bi in 0..self.buses.len() {
            let b = &mut self.buses[bi];
            if b.failed || b.bus.collect_feedback(&b.ids, &mut b.feedback).is_err() {
                b.feedback.iter_mut().for_each(|f| *f = None);
            }
            for (k, fb) in b.feedback.iter().enumerate() {
                let j = b.first_joint + k;
                self.state.joints[j] = sample(&self.joints[j], fb.as_ref());
            }
        }
        self.state.timestamp_ns = telemetry::clock::monotonic_ns();
        for b in &mut self.buses {
            b.payload.clear();
            for (k, &id) in b.ids.iter().enumerate() {
                let joint = &self.joints[b.first_joint + k];
                if !joint.ready {
                    continue;
                }
                // Goal_Position and Goal_Velocity are both sign-magnitude at bit 15.
                if let Ok(raw) = feetech::encoding::encode_sign_magnitude(joint.goal, 15) {
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
        self.retry_setup();
        self.counters.cycles += 1;
        self.state.seq = self.counters.cycles;
        self.state.deadline_misses = self.counters.deadline_misses;
        &self.state
    }

    /// Every `rate` cycles, tries to bring up one joint that is not ready (it was missing or
    /// refused at start). Costs one slow cycle, which is counted as a deadline miss if it is.
    fn retry_setup(&mut self) {
        if !self.counters.cycles.is_multiple_of(self.setup_retry_cycles) {
            return;
        }
        let n = self.joints.len();
        for k in 0..n {
            let j = (self.next_retry + k) % n;
            if !self.joints[j].ready {
                self.next_retry = j + 1;
                match self.setup_joint(j) {
                    Ok(()) => tracing::info!(joint = %self.joints[j].name, "servo came up"),
                    Err(_) => self.counters.setup_failures += 1,
                }
                return;
            }
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
            (
                cal.to_rad(f.position),
                sign * f64::from(f.velocity) / STEPS_PER_RAD,
                cal.to_rad(joint.goal),
            )
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

/// Where the loop gets goals from (the goal service, or a test script).
pub trait GoalSource {
    /// The newest goal frame that arrived since the last call, if any.
    fn latest(&mut self) -> Option<GoalFrame>;
}

/// Where the loop publishes each cycle's state.
pub trait StateSink {
    /// Publishes one state frame.
    fn publish(&mut self, state: &JointState);
}

/// No goals: every joint holds where it came up.
pub struct Hold;

impl GoalSource for Hold {
    fn latest(&mut self) -> Option<GoalFrame> {
        None
    }
}

impl StateSink for () {
    fn publish(&mut self, _: &JointState) {}
}

/// What a run did.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct RunSummary {
    /// Driver counters at the end.
    pub counters: DriverCounters,
    /// Wall time, s.
    pub elapsed_s: f64,
    /// Cycles per second achieved.
    pub rate_hz: f64,
}

/// Runs the fixed-rate loop until `shutdown` is set (or `max_cycles`), then turns torque off.
/// A rejected goal frame is logged when the reason changes (not per cycle) and counted.
pub fn run<T: Transport>(
    driver: &mut Driver<T>,
    period: Duration,
    goals: &mut dyn GoalSource,
    sink: &mut dyn StateSink,
    shutdown: &AtomicBool,
    max_cycles: Option<u64>,
) -> RunSummary {
    let start = Instant::now();
    let mut next = start + period;
    let mut last_rejection: Option<std::mem::Discriminant<GoalRejection>> = None;
    while !shutdown.load(Ordering::Relaxed) && max_cycles.is_none_or(|m| driver.counters.cycles < m)
    {
        if let Some(frame) = goals.latest() {
            match driver.apply_goals(&frame, telemetry::clock::monotonic_ns()) {
                Ok(()) => last_rejection = None,
                Err(e) => {
                    let kind = std::mem::discriminant(&e);
                    if last_rejection != Some(kind) {
                        tracing::warn!(seq = frame.seq, "goal frame rejected: {e}");
                        last_rejection = Some(kind);
                    }
                }
            }
        }
        let state = driver.cycle();
        sink.publish(state);
        let now = Instant::now();
        if now > next {
            driver.counters.deadline_misses += 1;
            next = now + period;
        } else {
            std::thread::sleep(next - now);
            next += period;
        }
    }
    driver.torque_off();
    let elapsed = start.elapsed().as_secs_f64();
    RunSummary {
        counters: driver.counters,
        elapsed_s: elapsed,
        rate_hz: driver.counters.cycles as f64 / elapsed.max(1e-9),
    }
}
