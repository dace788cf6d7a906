//! `nori`: the operator's command. Its own commands look at and move the robot (`state`,
//! `goal`, `reenable`, `stop`, `resume`), commission its servo buses (`servo scan`) and record demonstrations (`record`, `dataset`); every other command is
//! a program of its own, installed next to it, that `nori` runs in its place (same process,
//! same arguments), so the one command name reaches all of them:
//!
//! | command | program | crate |
//! |---|---|---|
//! | `nori up`, `nori sim scenario` | `nori-stack up`, `nori-stack scenario` | `stack` |
//! | `nori lab` | `nori-lab` | `lab` |
//! | `nori sim serve` | `nori-sim` | `sim` |
//! | `nori sim aim` | `nori-sim-aim` | `sim` |
//! | `nori fleet`, `nori fleet store`, `nori fleet report`, `nori policy-server`, `nori router` | `nori-fleet dashboard`, `… store`, `… report`, `… policy-server`, `… router` | `fleet` |
//! | `nori bench …`, `nori model bench` | `nori-bench …`, `nori-bench model-lab` | `bench` |
//! | `nori model analyze`, `nori model generate`, `nori sim replay` | `nori-model …`, `nori-model replay` | `model-lab` |
//! | `nori blackbox list`, `show`, `export`, `save`, `record` | `nori-blackbox …` | `blackbox` |

mod base_tool;
mod calibrate_tool;
mod plane_tools;
mod servo_tool;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use std::os::unix::process::CommandExt;

#[derive(Parser)]
#[command(version, about = "Operator CLI of the Nori A3 control stack")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// The arguments of a command another program carries out, passed on as they are (`--help`
/// included: that program answers it).
#[derive(clap::Args, Debug)]
struct Passed {
    #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
    args: Vec<String>,
}

#[derive(Subcommand)]
enum Command {
    /// Run the whole stack on the simulated robot (no hardware) until Ctrl-C.
    #[command(disable_help_flag = true)]
    Up(Passed),
    /// The simulated robot.
    #[command(subcommand)]
    Sim(SimCommand),
    /// Print the newest joint state from the state plane.
    State(plane_tools::StateArgs),
    /// Send joint goals to the driver (JOINT=RAD ...).
    Goal(plane_tools::GoalArgs),
    /// Drive the base at a velocity (LINEAR m/s, ANGULAR rad/s) for a while.
    Base(base_tool::BaseArgs),
    /// The lift: `nori lift release` ends an obstruction's hold or a jam (heights: `nori goal
    /// lift=M`).
    Lift(plane_tools::LiftArgs),
    /// Commissioning and service of the servo buses (`nori servo scan`); the stack stopped.
    #[command(subcommand)]
    Servo(servo_tool::ServoCommand),
    /// Calibrate the joints (`nori calibrate by-hand BUS`); the stack stopped.
    #[command(subcommand)]
    Calibrate(calibrate_tool::CalibrateCommand),
    /// Ask the supervisor to re-enable a bus it tripped (granted once the bus has cooled).
    Reenable(plane_tools::ReenableArgs),
    /// Stop the robot: its safe state, no goal from any source, until `nori resume` (no
    /// restart of any process ends it).
    Stop(plane_tools::StopArgs),
    /// End an operator's stop: every joint re-held where it is.
    Resume(plane_tools::StopArgs),
    /// Nori Lab: the robot in the browser (3D view, teleoperation, stop), on loopback.
    #[command(disable_help_flag = true)]
    Lab(Passed),
    /// The reference inference server: a scripted policy for every robot on the fleet.
    #[command(disable_help_flag = true)]
    PolicyServer(Passed),
    /// The fleet side: live dashboard and Prometheus /metrics of every robot on zenoh.
    #[command(disable_help_flag = true)]
    Fleet(Passed),
    /// A zenoh router for a site or a test fleet (TLS and access control from its JSON5 file).
    #[command(disable_help_flag = true)]
    Router(Passed),
    /// Benchmarks (figures next to their baseline; `nori bench --help` lists them all):
    /// driver-rate, state-plane, action-latency, fleet-ingest, fleet-store, model-lab ...
    #[command(disable_help_flag = true)]
    Bench(Passed),
    /// The model lab: the simulation held against measured data (analyze, generate, bench).
    #[command(disable_help_flag = true)]
    Model(Passed),
    /// Record demonstrations from the state plane into a LeRobot v3.0 dataset (crash-safe).
    #[command(disable_help_flag = true)]
    Record(Passed),
    /// Datasets recorded by `nori record`: recover after a crash, export for the model lab.
    #[command(disable_help_flag = true)]
    Dataset(Passed),
    /// The black box: the boxes frozen when something went wrong (list, show, export), and
    /// `save` to freeze the last minutes now.
    #[command(disable_help_flag = true)]
    Blackbox(Passed),
}

#[derive(Subcommand)]
enum SimCommand {
    /// Serve the simulated buses on pseudo-terminals in real time.
    #[command(disable_help_flag = true)]
    Serve(Passed),
    /// Run the whole stack into a protection scenario and print the outcome.
    #[command(disable_help_flag = true)]
    Scenario(Passed),
    /// Play a black box's bus traffic into the simulated servos and compare their replies
    /// with the recorded ones, register by register.
    #[command(disable_help_flag = true)]
    Replay(Passed),
    /// Where an object is in a simulated arm camera's picture, and the joint angles that
    /// centre it (the simulated world's ground truth, for demonstrators and evaluations).
    #[command(disable_help_flag = true)]
    Aim(Passed),
}

/// Replaces this process with `program` (installed next to `nori`) run with `first` then
/// `passed`; returns only if that fails.
fn run_instead(program: &str, first: &[&str], passed: &Passed) -> Result<()> {
    let path = telemetry::process::sibling(program)?;
    let err = std::process::Command::new(&path)
        .args(first)
        .args(&passed.args)
        .exec();
    Err(err).with_context(|| format!("running {}", path.display()))
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    match &cli.command {
        Command::Up(p) => run_instead("nori-stack", &["up"], p),
        Command::Sim(SimCommand::Serve(p)) => run_instead("nori-sim", &[], p),
        Command::Sim(SimCommand::Scenario(p)) => run_instead("nori-stack", &["scenario"], p),
        Command::Sim(SimCommand::Aim(p)) => run_instead("nori-sim-aim", &[], p),
        Command::Sim(SimCommand::Replay(p)) => run_instead("nori-model", &["replay"], p),
        Command::State(a) => plane_tools::state(a),
        Command::Goal(a) => plane_tools::goal(a),
        Command::Reenable(a) => plane_tools::reenable(a),
        Command::Lift(a) => plane_tools::lift(a),
        Command::Stop(a) => plane_tools::stop(a),
        Command::Resume(a) => plane_tools::resume(a),
        Command::Base(a) => base_tool::base(a),
        Command::Servo(c) => servo_tool::servo(c),
        Command::Calibrate(c) => calibrate_tool::calibrate(c),
        Command::Lab(p) => run_instead("nori-lab", &[], p),
        Command::PolicyServer(p) => run_instead("nori-fleet", &["policy-server"], p),
        // `nori fleet store` and `nori fleet report` are commands of their own; plain `nori fleet`
        // is the dashboard.
        Command::Fleet(p)
            if p.args
                .first()
                .is_some_and(|a| a == "store" || a == "report") =>
        {
            run_instead("nori-fleet", &[], p)
        }
        Command::Fleet(p) => run_instead("nori-fleet", &["dashboard"], p),
        Command::Router(p) => run_instead("nori-fleet", &["router"], p),
        Command::Bench(p) => run_instead("nori-bench", &[], p),
        Command::Model(p) if p.args.first().is_some_and(|a| a == "bench") => {
            let rest = Passed {
                args: p.args[1..].to_vec(),
            };
            run_instead("nori-bench", &["model-lab"], &rest)
        }
        Command::Model(p) => run_instead("nori-model", &[], p),
        Command::Record(p) => run_instead("nori-record", &["record"], p),
        Command::Dataset(p) => run_instead("nori-record", &["dataset"], p),
        Command::Blackbox(p) => run_instead("nori-blackbox", &[], p),
    }
}
