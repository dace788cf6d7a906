//! Real-time preparation of the control thread. Each step degrades to a warning where the
//! machine does not allow it (no privileges, a VM, a container): the loop still runs, with
//! worse jitter, and says so.
//!
//! The scheduling class is given by the service manager (deploy/systemd: `CPUSchedulingPolicy=
//! fifo`, `CPUAffinity=`), not set here: the driver only checks what it got and reports it.

use nix::sys::mman::{mlockall, MlockAllFlags};
use nix::sys::resource::{getrlimit, Resource, RLIM_INFINITY};

/// `SCHED_FIFO` in `/proc/<pid>/stat`'s policy field.
const SCHED_FIFO: u32 = 1;

/// What was applied.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RtStatus {
    /// Timer slack reduced to 1 ns (sleeps wake on time instead of up to 50 µs late).
    pub timer_slack: bool,
    /// All pages locked in memory (no page fault in the loop stalls a cycle on a slow SD card).
    pub memory_locked: bool,
    /// The thread runs under `SCHED_FIFO` at this priority.
    pub fifo_priority: Option<u32>,
}

/// Scheduling policy and real-time priority from a `/proc/.../stat` line (fields 41 and 40).
pub fn parse_sched(stat: &str) -> Option<(u32, u32)> {
    // The command name (field 2) may hold spaces and parentheses: count from its closing one.
    let rest = &stat[stat.rfind(')')? + 1..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // rest[0] is field 3 (state).
    let priority = fields.get(40 - 3)?.parse().ok()?;
    let policy = fields.get(41 - 3)?.parse().ok()?;
    Some((policy, priority))
}

/// Locks every page, present and future, when the memory-lock limit is unlimited. Under a
/// finite limit it does not try: with `MCL_FUTURE`, a later mapping over the limit would fail,
/// and a restarted supervisor's shared-memory segment is such a mapping.
fn lock_memory() -> bool {
    match getrlimit(Resource::RLIMIT_MEMLOCK) {
        Ok((soft, _)) if soft == RLIM_INFINITY => {}
        Ok((soft, _)) => {
            tracing::warn!(
                "memory not locked: RLIMIT_MEMLOCK is {} KiB, not unlimited (deploy/systemd sets LimitMEMLOCK=infinity); a page fault may stall a cycle",
                soft / 1024
            );
            return false;
        }
        Err(e) => {
            tracing::warn!("memory not locked: cannot read RLIMIT_MEMLOCK ({e})");
            return false;
        }
    }
    match mlockall(MlockAllFlags::MCL_CURRENT | MlockAllFlags::MCL_FUTURE) {
        Ok(()) => true,
        Err(e) => {
            tracing::warn!("cannot lock memory ({e}): a page fault may stall a cycle");
            false
        }
    }
}

/// Prepares the calling thread for the control loop.
pub fn prepare_control_thread() -> RtStatus {
    let timer_slack = match nix::sys::prctl::set_timerslack(1) {
        Ok(()) => true,
        Err(e) => {
            tracing::warn!(
                "cannot reduce timer slack ({e}): cycle wake-ups may be up to 50 µs late"
            );
            false
        }
    };
    let memory_locked = lock_memory();
    let fifo_priority = match std::fs::read_to_string("/proc/thread-self/stat")
        .ok()
        .as_deref()
        .and_then(parse_sched)
    {
        Some((SCHED_FIFO, priority)) => Some(priority),
        _ => {
            tracing::warn!(
                "not running under SCHED_FIFO (deploy/systemd sets it): other processes may delay cycles"
            );
            None
        }
    };
    RtStatus {
        timer_slack,
        memory_locked,
        fifo_priority,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn policy_and_priority_are_read_past_a_tricky_command_name() {
        let normal = "16038 (cat) R 16034 16034 1064 0 -1 4194304 123 0 0 0 0 0 0 0 20 0 1 0 806988 \
                      3133440 362 18446744073709551615 94412519534592 94412519554473 140732421903360 \
                      0 0 0 0 0 0 0 0 0 17 1 0 0 0 0 0 94412519570480";
        assert_eq!(parse_sched(normal), Some((0, 0)));
        let fifo = "77 (bus driver (x)) S 1 77 77 0 -1 4194560 9 0 0 0 0 0 0 0 -81 0 2 0 100 \
                    3133440 362 18446744073709551615 1 1 1 0 0 0 0 0 0 0 0 0 17 3 80 1 0 0 0 1";
        assert_eq!(parse_sched(fifo), Some((SCHED_FIFO, 80)));
        assert_eq!(parse_sched("garbage"), None);
        assert_eq!(parse_sched("1 (x) R 1 2"), None);
    }
}
