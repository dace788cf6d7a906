//! A fleet-side subscriber that hears nothing: its robots send state every 100 ms, so a store
//! or a dashboard that has heard no message from any robot for long is deaf, not idle. zenoh has
//! been seen to leave a subscriber so after a site router was frozen and let go (its routes
//! stale; `docs/fleet-sizing.md`); the binary then opens its session again, which declares its
//! subscriptions afresh. Pure: counts and times in, a verdict out.

/// What [`Silence::observe`] concludes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Heard {
    /// Something came within the bound (or the bound has not yet run out).
    Yes,
    /// Nothing for the bound: open the session again. The bound starts over.
    Nothing,
}

/// How long a subscriber has heard nothing.
#[derive(Debug, Clone)]
pub struct Silence {
    after_ms: u64,
    count: u64,
    since_ms: u64,
}

impl Silence {
    /// Deaf after `after_ms` without a message, from `now_ms` on.
    pub fn new(after_ms: u64, now_ms: u64) -> Silence {
        Silence {
            after_ms,
            count: 0,
            since_ms: now_ms,
        }
    }

    /// `count` messages heard so far, at `now_ms`.
    pub fn observe(&mut self, count: u64, now_ms: u64) -> Heard {
        if count != self.count {
            self.count = count;
            self.since_ms = now_ms;
            return Heard::Yes;
        }
        if now_ms.saturating_sub(self.since_ms) < self.after_ms {
            return Heard::Yes;
        }
        self.since_ms = now_ms;
        Heard::Nothing
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nothing_heard_for_the_bound_is_deafness_and_the_bound_starts_over() {
        let mut s = Silence::new(30_000, 1_000);
        assert_eq!(s.observe(0, 30_999), Heard::Yes);
        assert_eq!(s.observe(0, 31_000), Heard::Nothing);
        // Again only after a whole bound more.
        assert_eq!(s.observe(0, 60_999), Heard::Yes);
        assert_eq!(s.observe(0, 61_000), Heard::Nothing);
    }

    #[test]
    fn each_message_heard_starts_the_bound_over() {
        let mut s = Silence::new(30_000, 0);
        assert_eq!(s.observe(5, 29_000), Heard::Yes);
        assert_eq!(s.observe(5, 58_999), Heard::Yes);
        assert_eq!(s.observe(5, 59_000), Heard::Nothing);
        assert_eq!(s.observe(6, 59_500), Heard::Yes);
        assert_eq!(s.observe(6, 89_499), Heard::Yes);
    }
}
