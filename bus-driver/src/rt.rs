//! Real-time preparation of the control thread. Each step degrades to a warning where the
//! machine does not allow it (no privileges, a VM, a container): the loop still runs, with
//! worse jitter, and says so.

/// What was applied.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RtStatus {
    /// Timer slack reduced to 1 ns (sleeps wake on time instead of up to 50 µs late).
    pub timer_slack: bool,
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
    RtStatus { timer_slack }
}
