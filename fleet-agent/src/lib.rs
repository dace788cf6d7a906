//! The fleet agent: the robot's only door to the outside, over zenoh. It forwards telemetry,
//! events and observations from the state plane, and lets policy actions in only through the
//! gate ([`gate`]) and the scheduler ([`schedule`]). Every event goes into the robot's journal
//! ([`journal`]) and reaches the fleet at least once ([`delivery`]). Everything but [`net`] and
//! the journal's files is pure.
//!
//! Only what runs on the robot is here; the fleet's side (collector, dashboard, reference
//! policies, router) is the `fleet` crate. The two are the only crates that use zenoh, through
//! this crate's re-export [`zenoh`], so there is one zenoh version and one way to open a session.
//!
//! * `agent`: the loop's state and one turn of it; `config`: its configuration; `keys`: the zenoh
//!   key expressions; `schema`: what crosses zenoh (postcard, versioned); `outbound`: plane
//!   frames to fleet messages and the plan to goal frames; `preview`: camera thumbnails and
//!   lidar scans for the dashboard; `installed`: the package version the robot runs;
//!   `box_upload`: the black box's frozen boxes to the fleet, chunk by chunk, paced and never
//!   ahead of the events; `box_shelf`: the boxes on disk, listed and hashed by a thread of
//!   their own.

pub mod agent;
pub mod box_shelf;
pub mod box_upload;
pub mod config;
pub mod delivery;
pub mod gate;
pub mod installed;
pub mod journal;
pub mod keys;
pub mod net;
pub mod outbound;
pub mod preview;
pub mod schedule;
pub mod schema;

pub use config::AgentConfig;
pub use zenoh;
