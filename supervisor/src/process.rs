//! The supervisor's loop, shaped like the driver's: [`Process`] holds what the process knows
//! beyond the pure [`Supervisor`] (the trip record as last saved, the heartbeat, the publish
//! timer) and [`Process::poll`] does one turn of the loop against a [`SupervisorIo`] with time
//! passed in. The binary wires iceoryx2 and the trip file into a `SupervisorIo` and calls
//! [`run`]; the tests wire queues and a clock of their own.
//!
//! Its heartbeat means "supervising": it is sent only once the driver's layout is known, so a
//! driver never leaves its safe state for a supervisor that cannot yet supervise. A trip is
//! saved to the record before the directives that announce it are published, so no restart
//! can come between a bus turned off and the latch that keeps it off.

use crate::duty::{Allowance, DutyBudget, RECORD_PREFIX};
use crate::event::Event;
use crate::logic::{LayoutError, Supervisor};
use crate::SupervisorConfig;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use telemetry::clock::in_force;
use telemetry::frames::{
    Directives, EventKind, GripFrame, Heartbeat, JointLayout, JointState, Peer, SupervisorCommand,
    SupervisorEvent, COMMAND_REFUSED_NOT_STOPPED, COMMAND_RESUME, COMMAND_STOP,
};
use telemetry::latch::{LatchError, OPERATOR_STOP};
use telemetry::motion::{
    LiftAllowance, LiftState, LIFT_REFUSED_DUTY, LIFT_REFUSED_OPERATOR_STOP, LIFT_REFUSED_RECORD,
};
use telemetry::watchdog::Liveness;

/// A record that failed to save is tried again this often, ns.
const RECORD_RETRY_NS: u64 = 1_000_000_000;
/// Directives and heartbeat period.
pub const PUBLISH_EVERY: Duration = Duration::from_millis(5);
/// Poll period of the loop.
pub const POLL: Duration = Duration::from_millis(1);
/// The lift's budget is saved with this much running ahead, and again once the motor has run
/// it; with the lift's last allowance's life after a crash, the running a restore counts as
/// not rest: the record never holds less heat than the motor (a crash between saves, or a
/// crash loop, forgets none).
const DUTY_SAVE_AHEAD_S: f64 = 0.5;
/// The longest interval between two lift states counted (the lift publishes every 10 ms; a
/// longer silence is a dead nori-lift, whose board stops the motor in 100 ms), s.
const MAX_LIFT_GAP_S: f64 = 1.0;

/// The running a record's line covers after it was saved, s.
fn duty_unsaved_s() -> f64 {
    DUTY_SAVE_AHEAD_S + telemetry::motion::LIFT_ALLOWANCE_LIFE_NS as f64 * 1e-9
}

/// The supervisor's plane and its trip record, as its loop uses them. Every call returns at
/// once.
pub trait SupervisorIo {
    /// The newest joint layout of the driver, if one was published.
    fn layout(&mut self) -> Option<JointLayout>;
    /// The next joint-state frame not yet taken, oldest first.
    fn next_state(&mut self) -> Option<JointState>;
    /// The next operator command not yet taken.
    fn next_command(&mut self) -> Option<SupervisorCommand>;
    /// The next driver heartbeat not yet taken.
    fn next_driver_beat(&mut self) -> Option<Heartbeat>;
    /// Publishes the directives.
    fn directives(&mut self, d: &Directives);
    /// Publishes an event.
    fn event(&mut self, e: &SupervisorEvent);
    /// Publishes the heartbeat.
    fn heartbeat(&mut self, h: &Heartbeat);
    /// Publishes the grip force.
    fn grip(&mut self, g: &GripFrame);
    /// Saves the trip record: the joints of every latched bus, by name.
    fn save_trips(&mut self, joints: &[String]) -> Result<(), LatchError>;
    /// The next lift state not yet taken (none on a robot without a lift).
    fn next_lift_state(&mut self) -> Option<LiftState> {
        None
    }
    /// Publishes the lift's allowance (its duty-cycle budget's word).
    fn lift_allowance(&mut self, _a: &LiftAllowance) {}
}

/// What a turn of the loop changed, for the binary's status line and log.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Change {
    /// Supervising a (new) layout; the buses re-latched from the record.
    Supervising {
        /// Joints supervised.
        joints: u32,
        /// Buses latched again from the record.
        restored: Vec<u8>,
    },
}

/// The supervisor process's state.
pub struct Process {
    config: SupervisorConfig,
    supervisor: Option<Supervisor>,
    /// The trip record as last loaded or saved (names of joints of latched buses, including
    /// those of buses this layout does not have).
    trips: Vec<String>,
    /// Buses latched, and whether an operator's stop was in force, when the record was last
    /// written.
    recorded_mask: u32,
    recorded_stop: bool,
    heartbeat: Heartbeat,
    last_publish_ns: Option<u64>,
    frames: u64,
    last_state: Option<JointState>,
    /// The lift motor's duty-cycle budget, and the lift's last state (when, moving).
    lift_duty: DutyBudget,
    last_lift: Option<(u64, bool)>,
    allowance: LiftAllowance,
    /// The budget's line of the record as loaded, until the first turn restores it (it needs
    /// the time).
    duty_line: Option<String>,
    /// Running the last save still covers, s (below zero: save again), and whether the budget
    /// was spent then.
    duty_ahead_s: f64,
    duty_saved_spent: bool,
    /// Since when saving the record has failed (the lift gets no travel meanwhile), ns, and
    /// the last try.
    record_failing: Option<(u64, u64)>,
    /// Events of the operator's stop taken before the driver's layout, numbered.
    early_events: u64,
    /// Operator's stops taken (restored ones too), for the lift's allowance.
    stops: u16,
}

impl Process {
    /// A process with `config` and the trip record `trips` as loaded at start; its heartbeat
    /// carries `pid`.
    pub fn new(config: SupervisorConfig, mut trips: Vec<String>, pid: u32) -> Process {
        let duty_line = trips
            .iter()
            .position(|l| l.starts_with(RECORD_PREFIX.trim_end()))
            .map(|i| trips.remove(i));
        trips.retain(|l| !l.starts_with(RECORD_PREFIX.trim_end()));
        Process {
            supervisor: None,
            trips,
            duty_line,
            duty_ahead_s: 0.0,
            duty_saved_spent: false,
            record_failing: None,
            early_events: 0,
            stops: 0,
            recorded_mask: 0,
            recorded_stop: false,
            heartbeat: Heartbeat {
                pid,
                peer: Peer::Supervisor as u8,
                ..Heartbeat::default()
            },
            last_publish_ns: None,
            frames: 0,
            last_state: None,
            lift_duty: DutyBudget::new(config.lift.rating()),
            last_lift: None,
            allowance: LiftAllowance::default(),
            config,
        }
    }

    /// The supervisor, once a layout is known.
    pub fn supervisor(&self) -> Option<&Supervisor> {
        self.supervisor.as_ref()
    }

    /// Joint-state frames seen so far.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// One turn of the loop at `now` (CLOCK_MONOTONIC ns). A layout the supervisor cannot
    /// supervise is an error (the process exits: a configuration fault, not a crash).
    pub fn poll(
        &mut self,
        io: &mut impl SupervisorIo,
        now: u64,
    ) -> Result<Option<Change>, LayoutError> {
        if let Some(line) = self.duty_line.take() {
            self.restore_duty(&line, now);
        }
        let change = self.take_layout(io, now)?;
        if self.supervisor.is_none() {
            // No driver's layout (the driver dead or not yet started): the operator's stop is
            // still taken, for the lift, and recorded for the supervisor to come.
            self.early_commands(io, now);
        }
        let Some(s) = self.supervisor.as_mut() else {
            // The lift's budget does not wait for the driver's layout: the lift is not on its
            // buses.
            self.lift_duty_tier(io, now);
            self.save_duty(io, now);
            return Ok(change);
        };
        while let Some(state) = io.next_state() {
            self.frames += 1;
            if s.on_state(&state) {
                io.grip(s.grip());
            }
            self.last_state = Some(state);
        }
        while let Some(cmd) = io.next_command() {
            s.command(&cmd, now);
        }
        while let Some(beat) = io.next_driver_beat() {
            s.driver_beat(now, beat.pid);
        }
        s.watch_driver(now);
        let layout = *s.layout();
        for e in s.drain_events() {
            log_event(&e, &layout, self.last_state.as_ref());
            let stop = e.kind() == Some(EventKind::OperatorStop);
            self.stops = self.stops.wrapping_add(u16::from(stop));
            io.event(&e);
        }
        // Trips and stops outlive this process: recorded before the directives that announce
        // them.
        if s.tripped_buses() != self.recorded_mask || s.stopped() != self.recorded_stop {
            self.recorded_mask = s.tripped_buses();
            self.recorded_stop = s.stopped();
            // Latches of joints this layout does not have (a driver started on some of the
            // buses) are not this instance's to release: they stay in the record.
            let names: Vec<&str> = layout.joint_names().collect();
            self.trips
                .retain(|n| !names.contains(&n.as_str()) && n != OPERATOR_STOP);
            self.trips.extend(s.tripped_joints());
            if s.stopped() {
                self.trips.push(OPERATOR_STOP.to_string());
            }
            self.save_record(io, now);
        }
        self.lift_duty_tier(io, now);
        self.save_duty(io, now);
        let Some(s) = self.supervisor.as_mut() else {
            return Ok(change);
        };
        // Directives go out every period as the heartbeat of the decision, and at once when they
        // change (a trip must not wait for the next period).
        let period_over = self
            .last_publish_ns
            .is_none_or(|t| now.saturating_sub(t) >= PUBLISH_EVERY.as_nanos() as u64);
        if s.directives_changed() || period_over {
            io.directives(&s.directives(now));
        }
        if period_over {
            self.last_publish_ns = Some(now);
            self.heartbeat.seq += 1;
            self.heartbeat.timestamp_ns = now;
            io.heartbeat(&self.heartbeat);
        }
        Ok(change)
    }

    /// Whether an operator's stop is in force: the supervisor's word, or before the driver's
    /// layout the record's.
    fn stopped(&self) -> bool {
        match &self.supervisor {
            Some(s) => s.stopped(),
            None => self.trips.iter().any(|l| l == OPERATOR_STOP),
        }
    }

    /// The operator's stop and resume before the driver's layout is known: kept in the record
    /// (restored by the supervisor made for the layout) and said as events; other commands
    /// wait for the layout.
    fn early_commands(&mut self, io: &mut impl SupervisorIo, now: u64) {
        while let Some(cmd) = io.next_command() {
            let event = match cmd.kind {
                COMMAND_STOP if !self.stopped() => {
                    self.trips.push(OPERATOR_STOP.to_string());
                    Event::OperatorStop { restored: false }
                }
                COMMAND_RESUME if self.stopped() => {
                    self.trips.retain(|l| l != OPERATOR_STOP);
                    Event::OperatorResume
                }
                COMMAND_RESUME => Event::CommandRefused {
                    bus: cmd.bus,
                    why: COMMAND_REFUSED_NOT_STOPPED,
                    command: cmd.kind,
                },
                // A second stop changes nothing; a bus to re-enable is not known yet.
                _ => continue,
            };
            if !matches!(event, Event::CommandRefused { .. }) {
                self.save_record(io, now);
            }
            if matches!(event, Event::OperatorStop { .. }) {
                self.stops = self.stops.wrapping_add(1);
            }
            self.early_events += 1;
            io.event(&event.frame(self.early_events, now));
        }
    }

    /// Saves the trip record: the latched joints, the operator's stop, the lift's budget.
    fn save_record(&mut self, io: &mut impl SupervisorIo, now: u64) {
        let mut lines = self.trips.clone();
        // A cold motor needs no line (a robot without a lift keeps a record of trips only).
        if self.lift_duty.used_s() > 0.0 || self.lift_duty.exhausted() {
            lines.push(self.lift_duty.record_line(duty_unsaved_s(), now));
        }
        self.duty_ahead_s = DUTY_SAVE_AHEAD_S;
        self.duty_saved_spent = self.lift_duty.exhausted();
        match io.save_trips(&lines) {
            Ok(()) => {
                if self.record_failing.take().is_some() {
                    tracing::warn!("the record is saved again: the lift may travel");
                }
            }
            Err(e) => {
                if self.record_failing.is_none() {
                    tracing::error!("{e}: a restart would forget the latched trips and the lift's duty budget, and the driver keeps a released bus off; the lift gets no travel until a save succeeds");
                }
                let since = self.record_failing.map_or(now, |(since, _)| since);
                self.record_failing = Some((since, now));
            }
        }
    }

    /// Saves the record when the lift has run the margin it was last saved with (the rest a
    /// restore credits from the save's time is then rest indeed), or its budget turned spent or
    /// allowed.
    fn save_duty(&mut self, io: &mut impl SupervisorIo, now: u64) {
        let retry = self
            .record_failing
            .is_some_and(|(_, tried)| now.saturating_sub(tried) >= RECORD_RETRY_NS);
        if retry || self.duty_ahead_s < 0.0 || self.lift_duty.exhausted() != self.duty_saved_spent {
            self.save_record(io, now);
        }
    }

    /// The budget as the record kept it; a line that does not read is a spent budget (the
    /// motor's heat is not known: it rests).
    fn restore_duty(&mut self, line: &str, now: u64) {
        let rating = self.config.lift.rating();
        self.lift_duty =
            DutyBudget::restore(rating, line, now, duty_unsaved_s()).unwrap_or_else(|| {
                tracing::error!(
                    line,
                    "the lift's duty budget in the trip record does not read: taken as spent"
                );
                let mut spent = DutyBudget::new(rating);
                spent.update(true, rating.on_s);
                spent
            });
        self.duty_saved_spent = self.lift_duty.exhausted();
    }

    /// The lift motor's duty-cycle budget: filled while the lift's states say it moves, its
    /// allowance (refused too during an operator's stop) published with the heartbeat's
    /// period, and at once when it changes.
    fn lift_duty_tier(&mut self, io: &mut impl SupervisorIo, now: u64) {
        while let Some(s) = io.next_lift_state() {
            // A state stamped ahead of this clock would stop the count of what follows.
            if in_force(s.timestamp_ns, now, u64::MAX).is_err() {
                continue;
            }
            if let Some((t, moving)) = self.last_lift {
                let dt = (s.timestamp_ns.saturating_sub(t) as f64 * 1e-9).min(MAX_LIFT_GAP_S);
                self.lift_duty.update(moving, dt);
                if moving {
                    self.duty_ahead_s -= dt;
                }
            }
            self.last_lift = Some((s.timestamp_ns, s.velocity_m_s != 0.0));
        }
        let (allowed, refused, seconds) = match self.lift_duty.allowance() {
            _ if self.stopped() => (0, LIFT_REFUSED_OPERATOR_STOP, 0.0),
            _ if self.record_failing.is_some() => (0, LIFT_REFUSED_RECORD, 0.0),
            Allowance::Allowed { left_s } => (1, 0, left_s),
            Allowance::Refused { wait_s } => (0, LIFT_REFUSED_DUTY, wait_s),
        };
        let changed = (allowed, refused, self.stops)
            != (
                self.allowance.allowed,
                self.allowance.refused,
                self.allowance.stops,
            );
        let due =
            now.saturating_sub(self.allowance.timestamp_ns) >= PUBLISH_EVERY.as_nanos() as u64;
        if changed || due {
            if changed && refused == LIFT_REFUSED_DUTY {
                tracing::warn!(
                    wait_s = seconds,
                    "the lift's duty-cycle budget is spent: no travel for {seconds:.0} s"
                );
            }
            self.allowance = LiftAllowance {
                seq: self.allowance.seq + 1,
                timestamp_ns: now,
                allowed,
                refused,
                seconds: seconds as f32,
                used_s: self.lift_duty.used_s() as f32,
                stops: self.stops,
                ..LiftAllowance::default()
            };
            io.lift_allowance(&self.allowance);
        }
    }

    /// Takes a new layout: a fresh supervisor, the recorded trips latched again.
    fn take_layout(
        &mut self,
        io: &mut impl SupervisorIo,
        now: u64,
    ) -> Result<Option<Change>, LayoutError> {
        let Some(layout) = io.layout() else {
            return Ok(None);
        };
        if self
            .supervisor
            .as_ref()
            .is_some_and(|s| *s.layout() == layout)
        {
            return Ok(None);
        }
        let mut fresh = Supervisor::new(&layout, self.config.clone())?;
        if let Some(previous) = &self.supervisor {
            fresh.inherit_driver_watch(previous);
        }
        let restored = fresh.restore_trips(&self.trips, now);
        self.recorded_mask = fresh.tripped_buses();
        self.recorded_stop = fresh.stopped();
        self.supervisor = Some(fresh);
        Ok(Some(Change::Supervising {
            joints: layout.joint_count,
            restored,
        }))
    }

    /// The driver's liveness as last judged (unknown before a layout).
    pub fn driver(&self) -> Liveness {
        self.supervisor
            .as_ref()
            .map_or(Liveness::Unknown, Supervisor::driver_liveness)
    }
}

/// Logs an event (rare: never per cycle); a stall names what was seen.
fn log_event(e: &SupervisorEvent, layout: &JointLayout, last: Option<&JointState>) {
    let joint = layout
        .joints()
        .get(e.joint as usize)
        .map_or("-", |j| j.name());
    let mut line = format!(
        "{:?} joint {} bus {} level {} value {:.2}",
        e.kind(),
        joint,
        e.bus,
        e.level,
        e.value
    );
    if let (Some(EventKind::Stall), Some(st)) = (e.kind(), last) {
        if let Some(j) = st.joints().get(e.joint as usize) {
            line += &format!(
                " | frame {} position {:.3} goal {:.3} current {:.2} A load {:.2}",
                st.seq, j.position_rad, j.goal_rad, j.current_a, j.load
            );
        }
    }
    match e.kind() {
        Some(EventKind::ThermalTrip | EventKind::OutputLost | EventKind::DriverLost) => {
            tracing::warn!("{line}")
        }
        _ => tracing::info!("{line}"),
    }
}

/// Runs the loop until `shutdown` (or `run_for`), polling every [`POLL`]; `each_turn` is called
/// with what changed (the service manager's keep-alive and status).
pub fn run(
    process: &mut Process,
    io: &mut impl SupervisorIo,
    shutdown: &AtomicBool,
    run_for: Option<Duration>,
    each_turn: &mut dyn FnMut(&mut Process, Option<Change>),
) -> Result<(), LayoutError> {
    let started = Instant::now();
    while !shutdown.load(Ordering::Relaxed) && run_for.is_none_or(|d| started.elapsed() < d) {
        let change = process.poll(io, telemetry::clock::monotonic_ns())?;
        each_turn(process, change);
        std::thread::sleep(POLL);
    }
    Ok(())
}
