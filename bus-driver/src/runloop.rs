//! The fixed-rate loop around the [`Driver`]: goals and directives in, state out, and the
//! supervisor's heartbeat watched. What crosses the process boundary goes through [`LoopIo`], so
//! tests run the same loop with fakes.

use crate::driver::{Driver, DriverCounters, GoalRejection};
use crate::transport::Transport;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::frames::{BusHealth, Directives};
use telemetry::watchdog::{Liveness, Watchdog};
use telemetry::{GoalFrame, JointState};

/// Everything the loop exchanges with other processes.
pub trait LoopIo {
    /// The newest goal frame since the last call.
    fn goals(&mut self) -> Option<GoalFrame>;
    /// The newest directives since the last call.
    fn directives(&mut self) -> Option<Directives>;
    /// The pid of the newest supervisor heartbeat since the last call.
    fn supervisor_heartbeat(&mut self) -> Option<u32>;
    /// Publishes one state frame (and the driver's heartbeat).
    fn publish(&mut self, state: &JointState);
    /// Publishes the error counts of every bus (every 100 ms).
    fn publish_health(&mut self, _health: &BusHealth) {}
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
    fn supervisor_heartbeat(&mut self) -> Option<u32> {
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

/// Runs the loop at `period` until `shutdown` is set (or `max_cycles`), then turns torque off.
///
/// With `supervisor_timeout`, the supervisor's heartbeat is required: until it is first heard,
/// and whenever it is silent for longer, the driver's safe state is applied; directives are
/// applied only from a live supervisor. Rejected goal frames are logged when the reason changes
/// (not per cycle) and counted.
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
    let mut last_rejection: Option<std::mem::Discriminant<GoalRejection>> = None;
    let mut watchdog = supervisor_timeout.map(Watchdog::new);
    let mut supervisor = Liveness::Unknown;
    let mut health = BusHealth::default();
    let health_every = ((0.1 / period.as_secs_f64().max(1e-6)).round() as u64).max(1);
    while !shutdown.load(Ordering::Relaxed) && max_cycles.is_none_or(|m| driver.counters.cycles < m)
    {
        let now = monotonic_ns();
        if let Some(w) = watchdog.as_mut() {
            if let Some(pid) = io.supervisor_heartbeat() {
                w.beat(now, pid);
            }
            let liveness = w.liveness(now);
            if liveness != supervisor {
                match liveness {
                    Liveness::Alive => {
                        driver.leave_safe_state(now);
                        tracing::info!("supervisor present: driving");
                    }
                    _ => {
                        driver.enter_safe_state();
                        tracing::warn!(silence = ?w.silence(now), "supervisor missing: safe state applied");
                    }
                }
                supervisor = liveness;
            }
            if liveness == Liveness::Alive {
                if let Some(d) = io.directives() {
                    if let Err(e) = driver.apply_directives(&d) {
                        tracing::warn!("directives refused: {e}");
                    }
                }
            }
        }
        if let Some(frame) = io.goals() {
            match driver.apply_goals(&frame, now) {
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
        io.publish(state);
        if driver.counters.cycles % health_every == 1 || health_every == 1 {
            driver.health(&mut health);
            io.publish_health(&health);
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
    let elapsed = start.elapsed().as_secs_f64();
    RunSummary {
        counters: driver.counters,
        elapsed_s: elapsed,
        rate_hz: driver.counters.cycles as f64 / elapsed.max(1e-9),
    }
}
