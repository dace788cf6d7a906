//! Shared types of the Nori stack: the state-plane frames every process exchanges, the common
//! time base, the configuration error every process reports, and (behind the `ipc` feature) the
//! one place where iceoryx2 services are opened with their QoS, and the start-up every process
//! shares (logging, SIGINT/SIGTERM).
//!
//! The frames, clock and config parsing do no I/O beyond reading a file the caller names; `plane`
//! (shared memory), `process` (signals) and `latch` (the trip record on disk) do, which is why
//! they are a feature that only the processes enable.
//!
//! * `calibration`: where a robot's calibration came from (the stamp `nori calibrate` writes).
//! * `clock`: the common time base, and the one rule for a stamped message (in force, stale,
//!   or from the future).
//! * `config`: one error and one way to read a process's TOML file.
//! * `durable`: a file replaced atomically and durably (the trip record, a calibration).
//! * `frames`: the state plane's fixed-size frames (joints, goals, directives, heartbeats,
//!   bus health, events).
//! * `motion`: the base's and the lift's commands and states.
//! * `sensors`: camera images and lidar revolutions.
//! * `stats`: the project's one quantile rule.
//! * `watchdog`: a peer's liveness from its timestamps.
//! * `wire`: what went on a bus's wire in one cycle, byte for byte, and the operator's
//!   request to save the black box.
//! * With `ipc`: `plane` (the services and their QoS), `process` (start-up, signals, the
//!   service manager), `latch` (the trip record on disk).
//! * In tests with `ipc`: `versions` (each frame's layout against `frame-layouts.txt`, so a
//!   changed layout is a deliberate, reviewed edit).

pub mod calibration;
pub mod clock;
pub mod config;
pub mod durable;
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
pub mod wire;

#[cfg(all(test, feature = "ipc"))]
mod versions;

pub use frames::{GoalFrame, JointSample, JointState, MAX_JOINTS};
