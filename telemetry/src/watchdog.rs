//! Liveness of a peer from the timestamps of what it sends: pure, time passed in.

use std::time::Duration;

/// What is known about a peer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Liveness {
    /// Never heard from.
    Unknown,
    /// Heard from within the bound.
    Alive,
    /// Silent for longer than the bound.
    Lost,
}

/// Tracks one peer's heartbeats.
#[derive(Debug, Clone, Copy)]
pub struct Watchdog {
    timeout_ns: u64,
    last_ns: Option<u64>,
    last_pid: Option<u32>,
}

impl Watchdog {
    /// A watchdog declaring the peer lost after `timeout` of silence.
    pub fn new(timeout: Duration) -> Self {
        Watchdog {
            timeout_ns: timeout.as_nanos() as u64,
            last_ns: None,
            last_pid: None,
        }
    }

    /// Records a heartbeat received at `now_ns` from process `pid`; returns true when the pid
    /// changed (the peer restarted).
    pub fn beat(&mut self, now_ns: u64, pid: u32) -> bool {
        self.last_ns = Some(now_ns);
        let restarted = self.last_pid.is_some_and(|p| p != pid);
        self.last_pid = Some(pid);
        restarted
    }

    /// The peer's liveness at `now_ns`.
    pub fn liveness(&self, now_ns: u64) -> Liveness {
        match self.last_ns {
            None => Liveness::Unknown,
            Some(t) if now_ns.saturating_sub(t) > self.timeout_ns => Liveness::Lost,
            Some(_) => Liveness::Alive,
        }
    }

    /// Time since the last heartbeat, if any.
    pub fn silence(&self, now_ns: u64) -> Option<Duration> {
        self.last_ns
            .map(|t| Duration::from_nanos(now_ns.saturating_sub(t)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::clock::MS;

    #[test]
    fn lost_after_the_bound_and_back_on_a_beat() {
        let mut w = Watchdog::new(Duration::from_millis(50));
        assert_eq!(w.liveness(0), Liveness::Unknown);
        assert!(!w.beat(10 * MS, 7));
        assert_eq!(w.liveness(60 * MS), Liveness::Alive);
        assert_eq!(w.liveness(61 * MS), Liveness::Lost);
        assert!(w.beat(70 * MS, 8), "a new pid is a restart");
        assert_eq!(w.liveness(71 * MS), Liveness::Alive);
        assert_eq!(w.silence(80 * MS), Some(Duration::from_millis(10)));
    }
}
