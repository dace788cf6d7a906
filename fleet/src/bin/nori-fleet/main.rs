//! `nori-fleet`: the fleet-side processes. `nori fleet`, `nori policy-server` and `nori router`
//! are its commands.

mod dashboard;
mod policy_server;
mod report_command;
mod router;
mod store;

use anyhow::Result;
use clap::Parser;

#[derive(Parser)]
#[command(
    name = "nori-fleet",
    version,
    about = "The fleet side of the Nori A3 stack: dashboard, history store, reference inference server, zenoh router"
)]
enum Command {
    /// The live dashboard and Prometheus /metrics of every robot on zenoh (`nori fleet`).
    Dashboard(dashboard::FleetArgs),
    /// The reference inference server: a scripted policy for every robot on the fleet (`nori
    /// policy-server`).
    PolicyServer(policy_server::PolicyServerArgs),
    /// A zenoh router for a site or a test fleet, TLS and access control from its JSON5 file
    /// (`nori router`).
    Router(router::RouterArgs),
    /// The fleet's history: every robot's events (once each, acknowledged to the robot when
    /// committed) and its telemetry rolled up, in PostgreSQL (`nori fleet store`).
    Store(store::StoreArgs),
    /// The fleet's statistics over a period from the store's database: protection events by
    /// kind and per robot-day, time above the warning levels, the hottest motors, stalls per
    /// joint, drifting robots (`nori fleet report`).
    Report(report_command::ReportArgs),
}

fn main() -> Result<()> {
    match Command::parse() {
        Command::Dashboard(a) => dashboard::run(&a),
        Command::PolicyServer(a) => policy_server::run(&a),
        Command::Router(a) => router::run(&a),
        Command::Store(a) => store::run(&a),
        Command::Report(a) => report_command::run(&a),
    }
}
