//! The fleet's side, off the robot: the collector behind the dashboard and `/metrics`
//! ([`collector`], pure: bytes in, state and metrics out) and the reference policies
//! ([`policy`], scripted, and [`seek`], which sees: both served by `nori policy-server`). Zenoh comes through `fleet_agent`'s
//! re-export; nothing here runs on the robot.

pub mod collector;
pub mod history;
pub mod journal_seen;
pub mod policy;
pub mod report;
pub mod seek;
