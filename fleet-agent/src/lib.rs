//! The fleet agent: the robot's only door to the outside, over zenoh. It forwards telemetry,
//! events and observations from the state plane, and lets policy actions in only through the
//! gate ([`gate`]) and the scheduler ([`schedule`]). Everything but [`net`] is pure.
//!
//! This is the only crate of the workspace that depends on zenoh; others that need a session
//! (the `nori` CLI's fleet tools, tests) use the re-export [`zenoh`].

pub mod collector;
pub mod config;
pub mod gate;
pub mod keys;
pub mod net;
pub mod outbound;
pub mod policy;
pub mod schedule;
pub mod schema;

pub use config::AgentConfig;
pub use zenoh;
