//! The fixed-rate loop around the [`Driver`]: goals and directives in, state out, and the
//! supervisor's heartbeat watched. What crosses the process boundary goes through [`LoopIo`], so
//! tests run the same loop with fakes.

use crate::driver::{Driver, DriverCounters, GoalPath, GoalRejection};
use crate::transport::Transport;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use telemetry::clock::{in_force, monotonic_ns};
use telemetry::frames::{BusHealth, Directives, Heartbeat};
use telemetry::watchdog::{Liveness, Watchdog};
use telemetry::wire::WireFrame;
use telemetry::{GoalFrame, JointState};

/// Everything the loop exchanges with other processes.
pub trait LoopIo {
    /// The newest goal frame for the arms and grippers since the last call.
    fn goals(&mut self) -> Option<GoalFrame>;
    /// The newest wheel-speed frame from the base's controller since the last call (a path of
    /// its own: a wheel goal anywhere else is refused). None without a base.
    fn wheel_goals(&mut self) -> Option<GoalFrame> {
        None
    }
    /// The newest directives since the last call.
    fn directives(&mut self) -> Option<Directives>;
    /// The newest supervisor heartbeat since the last call.
    fn supervisor_heartbeat(&mut self) -> Option<Heartbeat>;
    /// The joints the trip record latches now (read again before a latched bus is released);
    /// an error keeps every bus latched. Without a record: none.
    fn latched_joints(&mut self) -> Result<Vec<String>, String> {
        Ok(Vec::new())
    }
    /// Publishes one state frame (and the driver's heartbeat).
    fn publish(&mut self, state: &JointState);
    /// Publishes the error counts of every bus (every 100 ms).
    fn publish_health(&mut self, _health: &BusHealth) {}
    /// Publishes one bus's traffic of the cycle (tapped buses only).
    fn publish_wire(&mut self, _wire: &WireFrame) {}
}

/// No other process: no goals, no supervisor (every joint holds where it came up).
pub struct Standalone;

impl LoopIo for Standalone {
    fn goals(&mut self) -> Option<GoalFrame> {
        None
    }
    fn directives(&mut self) -> Option<Directives> {
        None
    }
    fn supervisor_heartbeat(&mut self) -> Option<Heartbeat> {
        None
    }
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

/// Reads the trip record again before a release: an unreadable record latches every bus.
fn read_latch<T: Transport>(driver: &mut Driver<T>, io: &mut dyn LoopIo) {
    match io.latched_joints() {
        Ok(joints) => {
            driver.set_latch(&joints);
        }
        Err(e) => {
            tracing::error!("{e}: every bus stays latched off");
            driver.latch_all();
        }
    }
}

/// Applies a fresh directive of the live supervisor; whether it was applied. A refusal is
/// logged once until one is applied again (the safe state holds meanwhile).
fn apply_directives<T: Transport>(
    driver: &mut Driver<T>,
    d: &Directives,
    refused: &mut bool,
) -> bool {
    match driver.apply_directives(d) {
        Ok(()) => {
            *refused = false;
            true
        }
        Err(e) => {
            if !*refused {
                tracing::warn!("directives refused (the safe state holds): {e}");
            }
            *refused = true;
            false
        }
    }
}

/// Runs the loop at `period` until `shutdown` is set (or `max_cycles`), then turns torque off.
///
/// With `supervisor_timeout`, the supervisor's heartbeat is required: until it is first heard,
/// and whenever it is silent for longer, the driver's safe state is applied. A heartbeat or a
/// directive counts by its own timestamp (one older than the timeout proves nothing about now).
/// The safe state is left only once a directive of the live supervisor has been applied, so a
/// bus that supervisor keeps off is never energised on the way out. Rejected goal frames are
/// logged when the reason changes (not per cycle) and counted.
pub fn run<T: Transport>(
    driver: &mut Driver<T>,
    period: Duration,
    supervisor_timeout: Option<Duration>,
    io: &mut dyn LoopIo,
    shutdown: &AtomicBool,
    max_cycles: Option<u64>,
) -> RunSummary {
    let start = Instant::now();
    let mut next = start + period;
    let mut last_rejection: [Option<std::mem::Discriminant<GoalRejection>>; 2] = [None; 2];
    let mut watchdog = supervisor_timeout.map(Watchdog::new);
    let timeout_ns = supervisor_timeout.map_or(0, |t| t.as_nanos() as u64);
    let fresh = |stamp: u64, now: u64| in_force(stamp, now, timeout_ns).is_ok();
    let mut supervisor = Liveness::Unknown;
    // A directive of the live supervisor has been applied since it was (last) heard again.
    let mut directed = false;
    let mut directives_refused = false;
    // Cycles in 100 ms: how often bus health is published, and how often at most the trip
    // record is read again while a directive asks to release a latched bus (a release the
    // record refuses must not read the disk every cycle).
    let every_100ms = ((0.1 / period.as_secs_f64().max(1e-6)).round() as u64).max(1);
    let mut next_latch_read = 0u64;
    let mut health = BusHealth::default();
    while !shutdown.load(Ordering::Relaxed) && max_cycles.is_none_or(|m| driver.counters.cycles < m)
    {
        let now = monotonic_ns();
        if let Some(w) = watchdog.as_mut() {
            if let Some(beat) = io.supervisor_heartbeat() {
                if fresh(beat.timestamp_ns, now) {
                    w.beat(beat.timestamp_ns.min(now), beat.pid);
                } else {
                    driver.counters.stale_supervisor_frames += 1;
                }
            }
            let liveness = w.liveness(now);
            if liveness == Liveness::Alive {
                if let Some(d) = io.directives() {
                    if !fresh(d.timestamp_ns, now) {
                        driver.counters.stale_supervisor_frames += 1;
                    } else {
                        if driver.latch_release_pending(&d)
                            && driver.counters.cycles >= next_latch_read
                        {
                            next_latch_read = driver.counters.cycles + every_100ms;
                            read_latch(driver, io);
                        }
                        let applied = apply_directives(driver, &d, &mut directives_refused);
                        directed |= applied;
                    }
                }
                // Supervised once its directive is applied, stopped or not: its thermal tier
                // is then live and the driver's last-resort one stands down.
                driver.set_supervised(directed);
                if directed && driver.in_safe_state() && !driver.operator_stopped() {
                    driver.leave_safe_state(now);
                    tracing::info!("supervisor present and directing: driving");
                }
            } else {
                directed = false;
                driver.set_supervised(false);
                if supervisor == Liveness::Alive || !driver.in_safe_state() {
                    driver.enter_safe_state();
                    tracing::warn!(silence = ?w.silence(now), "supervisor missing: safe state applied");
                }
            }
            supervisor = liveness;
        }
        for (path, frame) in [
            (GoalPath::Joints, io.goals()),
            (GoalPath::Wheels, io.wheel_goals()),
        ] {
            let Some(frame) = frame else { continue };
            match driver.apply_goals(&frame, now, path) {
                Ok(()) => last_rejection[path as usize] = None,
                Err(e) => {
                    let kind = std::mem::discriminant(&e);
                    if last_rejection[path as usize] != Some(kind) {
                        tracing::warn!(seq = frame.seq, ?path, "goal frame rejected: {e}");
                        last_rejection[path as usize] = Some(kind);
                    }
                }
            }
        }
        let state = driver.cycle(monotonic_ns);
        io.publish(state);
        driver.drain_wire(&mut |w| io.publish_wire(w));
        if driver.counters.cycles % every_100ms == 1 || every_100ms == 1 {
            driver.health(&mut health);
            io.publish_health(&health);
        }
        // The background read-back of safety settings runs in idle time only.
        if Instant::now() + driver.read_back_cost() < next {
            driver.read_back_in_turn();
        }
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
    // The torque going off, for the black box.
    driver.drain_wire(&mut |w| io.publish_wire(w));
    let elapsed = start.elapsed().as_secs_f64();
    RunSummary {
        counters: driver.counters,
        elapsed_s: elapsed,
        rate_hz: driver.counters.cycles as f64 / elapsed.max(1e-9),
    }
}
