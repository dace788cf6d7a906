//! `nori up`: the whole stack on the simulated robot, for development. Starts the simulator, the
//! supervisor, the driver, the fleet agent, the base controller, the lidar and (on request)
//! cameras as separate processes, restarts a process that dies (with backoff), and on Ctrl-C
//! stops the driver first
//! (it turns torque off while the buses are still there), then the rest. Production uses systemd
//! (deploy/systemd) instead.

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
    /// Cameras to run (`nori-camera` each, reading the simulator's rendering of it), by name
    /// (`head`, `neck`, `left_wrist`, `right_wrist`) or `all`; repeatable. None by default: the
    /// simulator renders a camera only while it is read, at 720p30, and that is a core's work
    /// on a small machine.
    #[arg(long = "camera", value_name = "NAME")]
    pub cameras: Vec<String>,
    /// Leave the lidar out.
    #[arg(long)]
    pub no_lidar: bool,
    /// The simulated robot's description (TOML, `nori-sim --description`); the embedded Nori A3
    /// when absent.
    #[arg(long, value_name = "FILE")]
    pub robot: Option<PathBuf>,
    /// The cameras' configuration (TOML, `nori-camera --config`); the embedded default when
    /// absent. Give it with `--robot` when that changes a camera's size or rate.
    #[arg(long, value_name = "FILE")]
    pub camera_config: Option<PathBuf>,
    /// Make one simulated servo stop answering for a while (`BUS:ID@AT+FOR`, seconds from the
    /// simulator's start, e.g. `left_arm:4@30+2`): try the stack's handling of a missing servo.
    /// Repeatable.
    #[arg(long, value_name = "BUS:ID@AT+FOR")]
    pub silence: Vec<String>,
    /// Put something under the simulated lift column at this height, m (a hand): try the lift's
    /// obstruction stop (the simulator reports the seconds it was pressed).
    #[arg(long, value_name = "M")]
    pub lift_obstacle_at: Option<f64>,
    /// Stop by itself after this many seconds.
    #[arg(long)]
    pub run_for: Option<f64>,
}

/// The cameras asked for, checked against the simulated robot's.
fn cameras(asked: &[String], robot: Option<&std::path::Path>) -> Result<Vec<String>> {
    let robot = match robot {
        Some(path) => sim::RobotDescription::load(path)?,
        None => sim::RobotDescription::nori_a3(),
    };
    let have: Vec<String> = robot.camera.iter().map(|c| c.name.clone()).collect();
    if asked.iter().any(|a| a == "all") {
        return Ok(have);
    }
    for a in asked {
        if !have.contains(a) {
            anyhow::bail!(
                "--camera {a}: the simulated A3 has {} (or all)",
                have.join(", ")
            );
        }
    }
    Ok(asked.to_vec())
}

/// The simulated robot as `args` ask for it, reporting to `report`.
fn simulator(args: &UpArgs, run: &Run, report: &std::path::Path) -> Result<Managed> {
    let mut sim = Managed::new(
        "simulator",
        &sibling("nori-sim")?,
        &run.simulator(&[], report),
    );
    if let Some(robot) = &args.robot {
        sim.add_args(&["--description".into(), robot.display().to_string()]);
    }
    if let Some(m) = args.lift_obstacle_at {
        sim.add_args(&["--lift-obstacle-at".into(), m.to_string()]);
    }
    for silence in &args.silence {
        sim.add_args(&["--silence".into(), silence.clone()]);
    }
    Ok(sim)
}

/// The sensors, each its own process as on the robot: nothing of the control loop waits on
/// them, and one that dies is restarted like the rest.
fn sensors(args: &UpArgs, run: &Run) -> Result<Vec<Managed>> {
    let mut sensors = Vec::new();
    if !args.no_lidar {
        sensors.push(Managed::new(
            "nori-lidar",
            &sibling("nori-lidar")?,
            &run.lidar(),
        ));
    }
    for name in cameras(&args.cameras, args.robot.as_deref())? {
        let mut camera = Managed::new(
            &format!("nori-camera {name}"),
            &sibling("nori-camera")?,
            &run.camera(&name),
        );
        if let Some(config) = &args.camera_config {
            camera.add_args(&["--config".into(), config.display().to_string()]);
        }
        sensors.push(camera);
    }
    Ok(sensors)
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
    let mut sim = simulator(args, &run, &report)?;
    let mut bus_driver = Managed::new("bus-driver", &sibling("bus-driver")?, &run.driver(&[]));
    // Restarted as systemd restarts it on the robot (RestartSec=500ms), never backing off: the
    // wheel servos keep their last speed while no driver runs, and the base's protective field
    // counts that time (base.toml, driver-restart-ms).
    bus_driver.restart_after(std::time::Duration::from_millis(500));
    if let Some(c) = &args.driver_config {
        bus_driver.add_args(&["--config".into(), c.display().to_string()]);
    }
    let mut supervising = Managed::new("supervisor", &sibling("supervisor")?, &run.supervisor());
    let mut fleet_agent = Managed::new("fleet-agent", &sibling("fleet-agent")?, &run.agent());
    // The base's controller: velocity commands to the wheels, odometry, the protective field,
    // and the body's frames from the same robot description as the simulator's.
    let mut base = Managed::new("nori-base", &sibling("nori-base")?, &run.base());
    // The lift: homes at start, then takes heights (nori/lift/command).
    let mut lift = Managed::new("nori-lift", &sibling("nori-lift")?, &run.lift());
    // The black box: the last minutes in memory, a box frozen on each protection event (in
    // DIR/blackbox here; /var/lib/nori/blackbox on the robot).
    let boxes = args.dir.join("blackbox");
    let mut blackbox = Managed::new(
        "nori-blackbox",
        &sibling("nori-blackbox")?,
        &run.blackbox(&boxes),
    );
    // The base's frames and the boxes' (`/tf`) from the robot the simulator runs.
    if let Some(robot) = &args.robot {
        let robot = ["--robot".into(), robot.display().to_string()];
        base.add_args(&robot);
        blackbox.add_args(&robot);
    }
    if let Some(c) = &args.agent_config {
        fleet_agent.add_args(&["--config".into(), c.display().to_string()]);
    }
    // The agent sends the frozen boxes to the fleet's store, when one runs.
    fleet_agent.add_args(&["--blackbox-dir".into(), boxes.display().to_string()]);
    let mut sensors = sensors(args, &run)?;
    eprintln!("nori up: the Nori A3 stack on the simulated robot (no hardware)");
    sim.start()?;
    blackbox.start()?;
    // The supervisor first: the driver holds its safe state until the supervisor is heard from.
    supervising.start()?;
    bus_driver.start()?;
    fleet_agent.start()?;
    base.start()?;
    lift.start()?;
    for s in &mut sensors {
        s.start()?;
    }
    eprintln!(
        "nori up: watch the joints with `nori state --domain {d}`, move one with `nori goal --domain {d} left_elbow=-1.0`; \
         the simulator's report is {}; boxes frozen by the black box are listed by \
         `nori blackbox list --dir {}`. `nori policy-server` in another terminal drives the elbows \
         through the fleet agent. Ctrl-C stops everything with torque off.",
        report.display(),
        boxes.display(),
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
        base.supervise()?;
        lift.supervise()?;
        blackbox.supervise()?;
        for s in &mut sensors {
            s.supervise()?;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    eprintln!("nori up: stopping (driver first, so torque goes off while the buses are up)");
    // The agent first: no new goals while the driver turns torque off. The sensors with it (the
    // lidar stops its motor on the way out).
    fleet_agent.stop(Duration::from_secs(5));
    base.stop(Duration::from_secs(5));
    lift.stop(Duration::from_secs(5));
    for s in &mut sensors {
        s.stop(Duration::from_secs(5));
    }
    bus_driver.stop(Duration::from_secs(5));
    supervising.stop(Duration::from_secs(5));
    // After the driver: the box being frozen holds the torque going off.
    blackbox.stop(Duration::from_secs(5));
    sim.stop(Duration::from_secs(5));
    match telemetry::plane::Plane::remove_unused_domain(&args.domain) {
        Ok(_) => {}
        Err(e) => eprintln!(
            "nori up: could not clear the state plane {}: {e}",
            args.domain
        ),
    }
    let sensor_restarts: Vec<String> = sensors
        .iter()
        .map(|s| format!(", {} {}", s.name(), s.restarts))
        .collect();
    eprintln!(
        "nori up: stopped; restarts: simulator {}, supervisor {}, bus-driver {}, fleet-agent {}{}",
        sim.restarts,
        supervising.restarts,
        bus_driver.restarts,
        fleet_agent.restarts,
        sensor_restarts.concat()
    );
    Ok(())
}
