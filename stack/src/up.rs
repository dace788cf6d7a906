//! `nori up`: the whole stack on the simulated robot, for development. Starts the simulator, the
//! supervisor, the driver and the fleet agent as separate processes, restarts a process that dies (with backoff), and on Ctrl-C
//! stops the driver first (it turns torque off while the buses are still there), then the rest.
//! Production uses systemd (deploy/systemd) instead.

use anyhow::Result;
use clap::Args;
use sim::pty::default_device_dir;
use stack::{sibling, Managed, Run};
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// Options of `nori up`.
#[derive(Args, Debug)]
pub struct UpArgs {
    /// Directory for the simulator's device links and report.
    #[arg(long, value_name = "DIR", default_value_os_t = default_device_dir())]
    pub dir: PathBuf,
    /// State-plane domain.
    #[arg(long, default_value = telemetry::plane::DEFAULT_DOMAIN)]
    pub domain: String,
    /// Driver configuration file; the embedded default when absent.
    #[arg(long)]
    pub driver_config: Option<PathBuf>,
    /// Fleet-agent configuration file; the embedded default (robot `sim-0001`, zenoh peer
    /// connecting to `nori policy-server` on 127.0.0.1:7447) when absent.
    #[arg(long)]
    pub agent_config: Option<PathBuf>,
    /// Stop by itself after this many seconds.
    #[arg(long)]
    pub run_for: Option<f64>,
}

/// Runs the stack until Ctrl-C (or `--run-for`).
pub fn run(args: &UpArgs) -> Result<()> {
    let shutdown = telemetry::process::stop_flag()?;
    let run = Run {
        domain: &args.domain,
        device_dir: &args.dir,
        trips: None,
        quiet: false,
    };
    let report = args.dir.join("sim-report.json");
    let mut sim = Managed::new(
        "simulator",
        &sibling("nori-sim")?,
        &run.simulator(&[], &report),
    );
    let mut bus_driver = Managed::new("bus-driver", &sibling("bus-driver")?, &run.driver(&[]));
    if let Some(c) = &args.driver_config {
        bus_driver.add_args(&["--config".into(), c.display().to_string()]);
    }
    let mut supervising = Managed::new("supervisor", &sibling("supervisor")?, &run.supervisor());
    let mut fleet_agent = Managed::new("fleet-agent", &sibling("fleet-agent")?, &run.agent());
    if let Some(c) = &args.agent_config {
        fleet_agent.add_args(&["--config".into(), c.display().to_string()]);
    }
    eprintln!("nori up: the Nori A3 stack on the simulated robot (no hardware)");
    sim.start()?;
    // The supervisor first: the driver holds its safe state until the supervisor is heard from.
    supervising.start()?;
    bus_driver.start()?;
    fleet_agent.start()?;
    eprintln!(
        "nori up: watch the joints with `nori state --domain {d}`, move one with `nori goal --domain {d} left_elbow=-1.0`; \
         the simulator's report is {}. `nori policy-server` in another terminal drives the elbows \
         through the fleet agent. Ctrl-C stops everything with torque off.",
        report.display(),
        d = args.domain
    );
    let start = Instant::now();
    while !shutdown.load(Ordering::Relaxed)
        && args
            .run_for
            .is_none_or(|t| start.elapsed().as_secs_f64() < t)
    {
        sim.supervise()?;
        supervising.supervise()?;
        bus_driver.supervise()?;
        fleet_agent.supervise()?;
        std::thread::sleep(Duration::from_millis(50));
    }
    eprintln!("nori up: stopping (driver first, so torque goes off while the buses are up)");
    // The agent first: no new goals while the driver turns torque off.
    fleet_agent.stop(Duration::from_secs(5));
    bus_driver.stop(Duration::from_secs(5));
    supervising.stop(Duration::from_secs(5));
    sim.stop(Duration::from_secs(5));
    match telemetry::plane::Plane::remove_unused_domain(&args.domain) {
        Ok(_) => {}
        Err(e) => eprintln!(
            "nori up: could not clear the state plane {}: {e}",
            args.domain
        ),
    }
    eprintln!(
        "nori up: stopped; restarts: simulator {}, supervisor {}, bus-driver {}, fleet-agent {}",
        sim.restarts, supervising.restarts, bus_driver.restarts, fleet_agent.restarts
    );
    Ok(())
}
