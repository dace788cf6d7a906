//! `nori-stack`: the whole stack as one run on the simulated robot. `nori up` and `nori sim
//! scenario` are these commands.

mod scenario;
mod up;

use anyhow::Result;
use clap::Parser;

#[derive(Parser)]
#[command(
    name = "nori-stack",
    version,
    about = "The Nori A3 stack on the simulated robot: run it, or drive it into a protection scenario"
)]
enum Command {
    /// Run the whole stack on the simulated robot (no hardware) until Ctrl-C (`nori up`).
    Up(up::UpArgs),
    /// Run the whole stack into a protection scenario and print the outcome (`nori sim
    /// scenario`).
    Scenario(scenario::ScenarioArgs),
}

fn main() -> Result<()> {
    match Command::parse() {
        Command::Up(a) => up::run(&a),
        Command::Scenario(a) => scenario::run(&a),
    }
}
