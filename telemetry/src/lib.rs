//! Shared types of the Nori stack: the state-plane frames every process exchanges, the common
//! time base, and (behind the `ipc` feature) the one place where iceoryx2 services are opened
//! with their QoS.
//!
//! The frames and clock do no I/O; the `plane` module does (shared memory), which is why it is
//! a feature that only the processes enable.

pub mod clock;
pub mod frames;
#[cfg(feature = "ipc")]
pub mod plane;
pub mod watchdog;

pub use frames::{GoalFrame, JointSample, JointState, MAX_JOINTS};
