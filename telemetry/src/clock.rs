//! The stack's shared time base: CLOCK_MONOTONIC in nanoseconds, comparable across processes
//! on one machine (unlike `std::time::Instant`, which cannot be sent).

use std::time::Duration;

/// Now on CLOCK_MONOTONIC, ns.
pub fn monotonic_ns() -> u64 {
    let t = nix::time::clock_gettime(nix::time::ClockId::CLOCK_MONOTONIC);
    t.map(|ts| ts.tv_sec() as u64 * 1_000_000_000 + ts.tv_nsec() as u64)
        .unwrap_or(0)
}

/// Age of a timestamp taken with [`monotonic_ns`], at `now_ns`; zero if it is in the future.
pub fn age(timestamp_ns: u64, now_ns: u64) -> Duration {
    Duration::from_nanos(now_ns.saturating_sub(timestamp_ns))
}

/// Nanoseconds in a millisecond.
pub const MS: u64 = 1_000_000;

/// How far ahead of the reader's clock a stamp may lie and still be this machine's clock
/// (two processes read CLOCK_MONOTONIC a moment apart); further ahead, it is another clock's.
pub const FUTURE_SLACK_NS: u64 = MS;

/// Why a stamped message is not in force now.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum NotInForce {
    /// Stamped ahead of the reader's clock by more than [`FUTURE_SLACK_NS`]: not this
    /// machine's clock, and a stamp from the future would never age.
    #[error("stamped {ahead_ms} ms in the future")]
    FromTheFuture {
        /// How far ahead, ms.
        ahead_ms: u64,
    },
    /// Older than its limit: meant for a moment that has passed.
    #[error("{age_ms} ms old (limit {limit_ms} ms)")]
    Stale {
        /// Its age, ms.
        age_ms: u64,
        /// The limit, ms.
        limit_ms: u64,
    },
}

/// The one rule for a stamped message (a goal frame, a base or lift command, a heartbeat, a
/// directive, a lidar revolution): in force at `now_ns` if stamped at most
/// [`FUTURE_SLACK_NS`] ahead and at most `max_age_ns` old. Time is passed in.
pub fn in_force(stamp_ns: u64, now_ns: u64, max_age_ns: u64) -> Result<(), NotInForce> {
    if stamp_ns > now_ns.saturating_add(FUTURE_SLACK_NS) {
        return Err(NotInForce::FromTheFuture {
            ahead_ms: (stamp_ns - now_ns) / MS,
        });
    }
    let age = now_ns.saturating_sub(stamp_ns);
    if age > max_age_ns {
        return Err(NotInForce::Stale {
            age_ms: age / MS,
            limit_ms: max_age_ns / MS,
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stamp_is_in_force_from_its_limit_s_age_to_the_slack_ahead() {
        let now = 10_000 * MS;
        assert_eq!(in_force(now, now, 250 * MS), Ok(()));
        assert_eq!(in_force(now - 250 * MS, now, 250 * MS), Ok(()));
        assert_eq!(
            in_force(now - 250 * MS - 1, now, 250 * MS),
            Err(NotInForce::Stale {
                age_ms: 250,
                limit_ms: 250
            })
        );
        // The slack is 1 ms: two processes read the clock a moment apart, not more.
        assert_eq!(FUTURE_SLACK_NS, MS);
        assert_eq!(in_force(now + MS, now, 250 * MS), Ok(()));
        assert_eq!(
            in_force(now + MS + 1, now, 250 * MS),
            Err(NotInForce::FromTheFuture { ahead_ms: 1 })
        );
        assert_eq!(
            in_force(now + 3 * MS + 1, now, 250 * MS),
            Err(NotInForce::FromTheFuture { ahead_ms: 3 })
        );
        // A reader whose clock is near its end does not wrap the slack around.
        assert_eq!(in_force(u64::MAX, u64::MAX - 5, 0), Ok(()));
    }

    #[test]
    fn monotonic_advances() {
        let a = monotonic_ns();
        std::thread::sleep(Duration::from_millis(2));
        let b = monotonic_ns();
        assert!(b > a && age(a, b) >= Duration::from_millis(2));
        assert_eq!(age(b, a), Duration::ZERO);
    }
}
