//! How disturbed this shared machine was while a process under test kept its rate: a loop in
//! the test's own process, at the rate under test and under the same scheduling, that counts the
//! ticks it could not keep. A rate bound judged against it is a baseline from the same run: a
//! machine that stole a tenth of every process's time costs the probe a tenth of its ticks too,
//! while a driver that slows itself down (waiting out a timeout per corrupted reply, say) does
//! not slow the probe.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;
use telemetry::clock::monotonic_ns;

/// A running probe; [`SchedulingProbe::finish`] stops it and returns what it kept.
pub struct SchedulingProbe {
    stop: Arc<AtomicBool>,
    thread: JoinHandle<ProbeRecord>,
}

/// Every tick a probe kept, by when it ran (CLOCK_MONOTONIC ns, the clock of the frames).
#[derive(Debug, Clone)]
pub struct ProbeRecord {
    period_ns: u64,
    kept_ns: Vec<u64>,
}

impl SchedulingProbe {
    /// Ticks every `period`, skipping (not catching up) the ticks it woke too late for, as a
    /// control loop that keeps its phase does.
    pub fn start(period: Duration) -> SchedulingProbe {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let period_ns = u64::try_from(period.as_nanos()).expect("a period in u64 ns");
        let thread = std::thread::spawn(move || {
            let mut kept_ns = Vec::with_capacity(1 << 14);
            let mut deadline = monotonic_ns() + period_ns;
            while !flag.load(Ordering::Relaxed) {
                let now = monotonic_ns();
                if now < deadline {
                    std::thread::sleep(Duration::from_nanos(deadline - now));
                    continue;
                }
                // Woken within the tick's period: kept. Later: the ticks overslept are lost.
                if now < deadline + period_ns {
                    kept_ns.push(now);
                }
                deadline += period_ns * ((now - deadline) / period_ns + 1);
            }
            ProbeRecord { period_ns, kept_ns }
        });
        SchedulingProbe { stop, thread }
    }

    /// Stops the probe.
    pub fn finish(self) -> ProbeRecord {
        self.stop.store(true, Ordering::Relaxed);
        self.thread.join().expect("the probe's thread")
    }
}

impl ProbeRecord {
    /// Ticks kept over ticks due between two instants (CLOCK_MONOTONIC ns): 1 on a quiet
    /// machine, lower by the share of time the machine kept a process at this rate from running.
    pub fn kept_ratio(&self, from_ns: u64, to_ns: u64) -> f64 {
        let due = to_ns.saturating_sub(from_ns) / self.period_ns;
        let kept = self
            .kept_ns
            .iter()
            .filter(|&&t| (from_ns..to_ns).contains(&t))
            .count();
        (kept as f64 / due.max(1) as f64).min(1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_window_without_kept_ticks_counts_none_and_a_full_one_counts_all() {
        let r = ProbeRecord {
            period_ns: 10,
            kept_ns: (0..100).map(|k| k * 10 + 1).collect(),
        };
        assert_eq!(r.kept_ratio(0, 1000), 1.0);
        // A gap: ticks from 500 to 700 were lost.
        let gap = ProbeRecord {
            period_ns: 10,
            kept_ns: r
                .kept_ns
                .iter()
                .copied()
                .filter(|t| !(500..700).contains(t))
                .collect(),
        };
        assert!((gap.kept_ratio(0, 1000) - 0.8).abs() < 1e-9);
        assert!(gap.kept_ratio(500, 700) < 1e-9);
    }

    #[test]
    fn a_probe_on_its_own_keeps_ticks() {
        let p = SchedulingProbe::start(Duration::from_millis(5));
        let from = monotonic_ns();
        std::thread::sleep(Duration::from_millis(200));
        let to = monotonic_ns();
        let r = p.finish();
        // Any tick at all: the loop runs and stamps in the window's clock (no timing bound).
        assert!(r.kept_ratio(from, to) > 0.0);
    }
}
