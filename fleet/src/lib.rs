//! The fleet's side, off the robot; nothing here runs on the robot, and zenoh comes through
//! `fleet_agent`'s re-export. The library is pure (bytes and wall time in, state, rows and
//! text out):
//!
//! * [`admission`]: what the store lets into its tables; one robot's garbage refused or
//!   quarantined, counted, and holding up nobody else.
//! * [`boxes`]: the black boxes robots send the store, chunk by chunk: what is kept, and how.
//! * [`collector`]: what `nori fleet` knows about every robot, its dashboard JSON and `/metrics`.
//! * [`history`]: the store's rows: every journaled event once, telemetry rolled up.
//! * [`journal_seen`]: which events of each robot's journal the store has (each kept once).
//! * [`report`]: the fleet's statistics over a period (`nori fleet report`).
//! * [`policy`], [`seek`]: the reference policies `nori policy-server` serves (scripted, and
//!   one that sees).
//! * [`sessions`]: how full a router is, from the kernel's socket table (`nori router`).
//! * [`silence`]: a subscriber that has heard no robot for long is deaf (the store reopens).
//!
//! The binary `nori-fleet` (`src/bin/nori-fleet/`) wires them to zenoh, HTTP and PostgreSQL:
//! the dashboard, the store, the report, the policy server and the router.

pub mod admission;
pub mod boxes;
pub mod collector;
pub mod history;
pub mod journal_seen;
pub mod policy;
pub mod report;
pub mod seek;
pub mod sessions;
pub mod silence;
