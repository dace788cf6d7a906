//! The A3's differential base, sans-IO: what turns "go 0.3 m/s, turn 0.5 rad/s" into the two
//! wheel servos' speeds, and their positions back into where the base went.
//!
//! Nothing here reads a clock or a device: times come in as nanoseconds on the caller's clock,
//! wheel readings as radians, so the same code serves the robot's process, the simulator's
//! judge and the tests.
//!
//! * [`drive`]: the geometry (wheel radius, track, how each wheel is mounted), twist ↔ wheel
//!   speeds, and saturation that keeps a turn a turn.
//! * [`ramp`]: speed and acceleration limits applied to the commanded twist, cycle by cycle.
//! * [`odometry`]: pose and twist integrated from the wheels' positions, which wrap at one turn.
//! * [`controller`]: all of it in one period: command in force, field, ramp, wheel goals, the
//!   base's state.
//! * [`field`]: the protective field: the speed from which the base still stops short of what
//!   the lidar sees in its path.
//! * [`frames`]: the whole body's frames for tools: each arm's shoulder and tool in the room,
//!   from its joints, the lift's height and the base's odometry.
//!
//! * `history`: where the base was lately, each lidar point moved to where it stands now.
//! * `config` (feature `process`): `nori-base`'s configuration.

#[cfg(feature = "process")]
pub mod config;
pub mod controller;
pub mod drive;
pub mod field;
pub mod frames;
pub mod history;
pub mod odometry;
pub mod ramp;

pub use drive::{Geometry, GeometryError, Twist, WheelSpeeds};
pub use field::{FieldConfig, Verdict};
pub use odometry::{Odometry, Pose2};
pub use ramp::{Limits, Ramp};
