//! Shared types of the Nori stack: the state-plane frames every process exchanges, the common
//! time base, the configuration error every process reports, and (behind the `ipc` feature) the
//! one place where iceoryx2 services are opened with their QoS, and the start-up every process
//! shares (logging, SIGINT/SIGTERM).
//!
//! The frames, clock and config parsing do no I/O beyond reading a file the caller names; `plane`
//! (shared memory), `process` (signals) and `latch` (the trip record on disk) do, which is why
//! they are a feature that only the processes enable.

pub mod clock;
pub mod config;
pub mod frames;
#[cfg(feature = "ipc")]
pub mod latch;
pub mod motion;
#[cfg(feature = "ipc")]
pub mod plane;
#[cfg(feature = "ipc")]
pub mod process;
pub mod sensors;
pub mod stats;
pub mod watchdog;

pub use frames::{GoalFrame, JointSample, JointState, MAX_JOINTS};
