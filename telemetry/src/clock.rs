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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn monotonic_advances() {
        let a = monotonic_ns();
        std::thread::sleep(Duration::from_millis(2));
        let b = monotonic_ns();
        assert!(b > a && age(a, b) >= Duration::from_millis(2));
        assert_eq!(age(b, a), Duration::ZERO);
    }
}
