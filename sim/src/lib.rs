//! The simulated Nori A3: servos, arms and buses that speak the real Feetech wire protocol.
//!
//! * [`servo`]: one STS servo, its register file, firmware (position/speed loops, torque limit,
//!   over-current, overload and over-temperature protections) and plant (DC motor through a
//!   gearbox, Coulomb + viscous friction, one-node thermal model read as an integer °C).
//! * [`arm`]: the 7-DoF chain's gravity and inertia (nalgebra), hard stops, obstacles, and the
//!   compliant TPU gripper.
//! * [`bus`]: one bus, sans-IO: the device side of the `feetech` codec with the line's timing
//!   (replies complete `bytes × 10 / baud` after the request, plus the return delay).
//! * [`line`]: what the servos put on the shared half-duplex line: each answer after its own
//!   return delay, overlapping answers garbled (duplicated ids, a broadcast PING).
//! * [`pty`]: serving buses on pseudo-terminals in real time for the unmodified driver.
//! * [`camera`], [`lidar`]: the sensors, rendered and ray-cast from the simulated robot and
//!   its room, served as the devices `nori-camera` and `nori-lidar` read.
//! * [`description`]: the robot description file; the A3's is embedded.
//! * [`extension`]: model extensions fitted on measured data by the model lab.
//! * [`constants`]: the constants each servo model runs: its rating, and the model lab's
//!   shipped finding on top where it found the rating wrong.
//!
//! Batch mode is [`bus::SimBus::step`] in a loop: no wall clock, as fast as the CPU goes.
//!
//! * `base`, `lift`, `room`: the base in its room, the lift's column and board; `device`: the
//!   serial devices that are no servo bus, on pseudo-terminals; `render`: the cameras'
//!   pictures; `aim`: where an object is in a picture (a scripted demonstrator's truth);
//!   `faults`: line faults injected on a bus; `scenario`: the protection scenarios' set-ups;
//!   `hand`: an operator's hand sweeping an arm's joints from stop to stop (calibration by
//!   hand); `rng`: the project's one seeded random generator.

pub mod aim;
pub mod arm;
pub mod base;
pub mod bus;
pub mod camera;
pub mod constants;
/// The robot description (the `body` crate's, re-exported: the one description the simulator and
/// the robot's processes read).
pub use body::description;
pub mod device;
pub mod extension;
pub mod faults;
pub mod hand;
pub mod lidar;
pub mod lift;
pub mod line;
pub mod pty;
pub mod render;
pub mod rng;
pub mod room;
pub mod scenario;
pub mod servo;

pub use bus::{BusReport, SimBus};
pub use description::RobotDescription;
