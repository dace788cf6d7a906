//! `nori`: the operator CLI of the Nori A3 stack.
//!
//! `nori up` runs the stack on the simulated robot; `nori sim serve` serves the simulated buses;
//! `nori state` / `nori goal` look at and move the robot; `nori fleet` shows the fleet; `nori bench` measures; `nori model` holds the simulation against measured data;
//! `nori record` records demonstrations, `nori dataset` recovers and exports them.

mod bench;
mod bench_fleet;
mod bench_plane;
mod fleet;
mod model;
mod plane_tools;
mod policy_server;
mod record;
mod router;
mod scenario;
mod sim_serve;
mod stack;
mod up;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(version, about = "Operator CLI of the Nori A3 control stack")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the whole stack on the simulated robot (no hardware) until Ctrl-C.
    Up(up::UpArgs),
    /// The simulated robot.
    #[command(subcommand)]
    Sim(SimCommand),
    /// Print the newest joint state from the state plane.
    State(plane_tools::StateArgs),
    /// Send joint goals to the driver (JOINT=RAD ...).
    Goal(plane_tools::GoalArgs),
    /// Ask the supervisor to re-enable a bus it tripped (granted once the bus has cooled).
    Reenable(plane_tools::ReenableArgs),
    /// The reference inference server: a scripted policy for every robot on the fleet.
    PolicyServer(policy_server::PolicyServerArgs),
    /// The fleet side: live dashboard and Prometheus /metrics of every robot on zenoh.
    Fleet(fleet::FleetArgs),
    /// A zenoh router for a site or a test fleet (TLS and access control from its JSON5 file).
    Router(router::RouterArgs),
    /// Benchmarks (figures next to their baseline).
    #[command(subcommand)]
    Bench(bench::Bench),
    /// The model lab: the simulation held against measured data.
    #[command(subcommand)]
    Model(model::ModelCommand),
    /// Record demonstrations from the state plane into a LeRobot v3.0 dataset (crash-safe).
    Record(record::RecordArgs),
    /// Datasets recorded by `nori record`: recover after a crash, export for the model lab.
    #[command(subcommand)]
    Dataset(record::DatasetCommand),
}

#[derive(Subcommand)]
enum SimCommand {
    /// Serve the simulated buses on pseudo-terminals in real time.
    Serve(Box<sim_serve::ServeArgs>),
    /// Run the whole stack into a protection scenario and print the outcome.
    Scenario(scenario::ScenarioArgs),
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    match &cli.command {
        Command::Up(a) => up::run(a),
        Command::Sim(SimCommand::Serve(a)) => sim_serve::run(a),
        Command::Sim(SimCommand::Scenario(a)) => scenario::run(a),
        Command::State(a) => plane_tools::state(a),
        Command::Goal(a) => plane_tools::goal(a),
        Command::Reenable(a) => plane_tools::reenable(a),
        Command::PolicyServer(a) => policy_server::run(a),
        Command::Router(a) => router::run(a),
        Command::Fleet(a) => fleet::run(a),
        Command::Bench(b) => bench::run(b),
        Command::Model(m) => model::run(m),
        Command::Record(a) => record::record(a),
        Command::Dataset(d) => record::dataset(d),
    }
}
