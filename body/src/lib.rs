//! The Nori A3's body, as the simulator and the robot's processes both read it.
//!
//! * [`description`]: the robot description file (servo ratings, buses, arm chains, grippers,
//!   the lift, the base's wheels, sensors, the room); the A3's is embedded.
//! * [`kinematics`]: whole-body forward kinematics: each arm's tool from its joint angles, the
//!   lift's height and the base's pose on the floor.
//! * [`ik`]: inverse kinematics of an arm: the joint angles, within given ranges, that put its
//!   tool at a pose.

pub mod description;
pub mod ik;
pub mod kinematics;

pub use description::RobotDescription;
