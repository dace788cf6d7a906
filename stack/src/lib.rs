//! The stack's processes as one run: their command lines ([`commands`]) and the management of
//! each child ([`child`]), shared by the orchestration commands (`nori up`, `nori sim
//! scenario`, in this crate's `nori-stack` binary), the benchmarks and the process tests, so
//! the stack is started one way everywhere.
//!
//! * `browser`: headless Chromium over its DevTools protocol, for Nori Lab's page.

pub mod browser;
pub mod child;
pub mod commands;

pub use child::{ChildError, Managed, Stopped};
pub use commands::Run;
pub use telemetry::process::sibling;

/// The supervisor and the driver of `bus`, for the scenarios and benchmarks that run a single
/// arm from sibling executables; not started.
pub fn supervisor_and_driver(run: &Run, bus: &str) -> Result<[Managed; 2], ChildError> {
    Ok([
        Managed::new("supervisor", &sibling("supervisor")?, &run.supervisor()),
        Managed::new("bus-driver", &sibling("bus-driver")?, &run.driver(&[bus])),
    ])
}
