//! The supervisor: an isolated process that reads the driver's joint state and protects the
//! servos (paper, "Making Commodity Actuators Viable").
//!
//! * [`stall`]: k = 15 window stall detection; gripper → gentle grip torque, other joints → one
//!   retry at full torque, then reduced torque until a new target.
//! * [`thermal`]: the software tier of the two-tier thermal interlock: warnings from the
//!   temperature trajectory, the whole bus disabled at 59 °C, latched until cooled and commanded.
//! * [`grip`]: sensorless grip force from the same current read.
//! * [`duty`]: the lift motor's duty-cycle budget (its rating as a thermal budget); not yet
//!   fed by a lift (the column's controller is the `lift` crate).
//! * [`event`]: what it reports, typed; a state-plane frame only at the edge.
//! * [`logic`]: all of it as one pure state machine over joint-state frames; the frames'
//!   timestamps are its clock, so tests drive it with a mock clock.
//! * [`process`]: the loop around it (layout, trip record, directives and heartbeat timing)
//!   against an I/O trait, so the process's own behaviour is tested in process too.
//!
//! It depends only on `telemetry`: it must outlive a crashed driver.
//!
//! * `config`: its thresholds (stall, thermal tiers, grip calibration), refused whole when wrong.

pub mod config;
pub mod duty;
pub mod event;
pub mod grip;
pub mod logic;
pub mod process;
pub mod stall;
pub mod thermal;

pub use config::SupervisorConfig;
pub use logic::Supervisor;
