//! The A3's lift: a three-stage telescoping desk column (76 cm of travel at 30 mm/s, 55 kg
//! rated) carrying the head and both arms, driven by one brushed DC motor.
//!
//! **The interface** (what the paper leaves open): the column's 24 V motor with its two hall
//! sensors, as desk frames ship it, on a small motor-controller board (H-bridge with current
//! sensing, the halls counted in quadrature, the column's lower and upper limit switches wired
//! in, a watchdog that stops the motor when no command came within 100 ms), on USB serial.
//! Why: the Feetech bus cannot drive a 24 V DC motor; the halls and the current are what a
//! column offers to know where it is and whether it is pushing on something; and a board that
//! stops by itself keeps a dead or hung host from driving the column into a hand.
//! [`column::LiftActuator`] is that board as the controller sees it.
//!
//! **The controller** ([`column::LiftController`], pure: readings and time in, a velocity out):
//! homing down to the lower switch at start (no position is trusted before), soft limits inside
//! the switches, goals clamped into them, a trapezoidal move at the rated speed, and the stop on
//! an obstruction: moving and not getting anywhere, or drawing the current of a stall, for
//! 150 ms, it stops and backs off a centimetre (the home's worst case is a column coming down on
//! a hand). The motor's duty-cycle limit is the supervisor's (`supervisor::duty`): the
//! controller is told whether travel is allowed.
//!
//! * `board`: the board's serial protocol (sans-IO); `column`: the controller; `config` (feature
//!   `process`): `nori-lift`'s configuration.

pub mod board;
pub mod column;
#[cfg(feature = "process")]
pub mod config;

pub use column::{
    ColumnConfig, LiftActuator, LiftController, LiftError, LiftEvent, LiftReading, LiftState,
};
