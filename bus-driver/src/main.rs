//! `bus-driver`: the real-time loop on the servo buses, as a process.
//!
//! Parses the configuration, opens one serial transport per bus, brings the servos up, then runs
//! the fixed-rate loop: goals from the `nori/goals` service, state to `nori/joint-state`. SIGINT
//! and SIGTERM end the loop with torque off.

use anyhow::{Context, Result};
use bus_driver::tap::Tapped;
use bus_driver::{Driver, LoadedConfig, LoopIo, SerialTransport};
use clap::Parser;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use telemetry::frames::{BusHealth, Directives, Heartbeat, JointLayout, Peer};
use telemetry::latch;
use telemetry::plane::{self, Plane, Pub, Sub};
use telemetry::process::Exit;
use telemetry::process::{ProcessArgs, ServiceManager, Started};
use telemetry::wire::WireFrame;
use telemetry::{GoalFrame, JointState};

#[derive(Parser)]
#[command(
    version,
    about = "Nori A3 bus driver: the control loop on the servo buses"
)]
struct Args {
    #[command(flatten)]
    process: ProcessArgs,
    /// Open every bus at DIR/<bus name> (where `nori sim serve` links its pseudo-terminals).
    #[arg(long, value_name = "DIR")]
    device_dir: Option<PathBuf>,
    /// Drive only these buses of the configuration (repeatable); all when absent.
    #[arg(long = "bus")]
    buses: Vec<String>,
    /// Wait this long for the bus devices to appear at start, s.
    #[arg(long, default_value_t = 10.0)]
    wait_for_devices: f64,
    /// Seconds between status lines (0: none).
    #[arg(long, default_value_t = 5.0)]
    status_every: f64,
    /// Print the default calibration and exit.
    #[arg(long)]
    print_default_calibration: bool,
    /// The trip record the supervisor keeps (the same path as its `--trip-file`): buses it
    /// latches stay off from the start; `<temp dir>/nori-<domain>-trips` when absent.
    /// Production: /var/lib/nori/trips.
    #[arg(long)]
    trip_file: Option<PathBuf>,
}

/// The driver's side of the state plane.
struct Ipc {
    goals: Sub<GoalFrame>,
    wheel_goals: Sub<GoalFrame>,
    directives: Sub<Directives>,
    supervisor: Sub<Heartbeat>,
    state: Pub<JointState>,
    heartbeat: Pub<Heartbeat>,
    layout_out: Pub<JointLayout>,
    health: Pub<BusHealth>,
    wire: Pub<WireFrame>,
    layout: JointLayout,
    beat: Heartbeat,
    every: Duration,
    last_status: Instant,
    last_seq: u64,
    publish_errors: u64,
    service: ServiceManager,
    trip_file: PathBuf,
}

impl LoopIo for Ipc {
    fn goals(&mut self) -> Option<GoalFrame> {
        plane::newest(&self.goals)
    }

    fn wheel_goals(&mut self) -> Option<GoalFrame> {
        plane::newest(&self.wheel_goals)
    }

    fn directives(&mut self) -> Option<Directives> {
        plane::newest(&self.directives)
    }

    fn supervisor_heartbeat(&mut self) -> Option<Heartbeat> {
        plane::newest(&self.supervisor)
    }

    fn latched_joints(&mut self) -> Result<Vec<String>, String> {
        latch::load(&self.trip_file).map_err(|e| e.to_string())
    }

    fn publish_health(&mut self, health: &BusHealth) {
        if plane::publish(&self.health, health).is_err() {
            self.publish_errors += 1;
        }
    }

    fn publish_wire(&mut self, wire: &WireFrame) {
        if plane::publish(&self.wire, wire).is_err() {
            self.publish_errors += 1;
        }
    }

    /// Publishes the frame and the heartbeat; the layout once a second (history 1 serves late
    /// subscribers, this serves a plane that was cleaned up); a status line every `every`.
    fn publish(&mut self, state: &JointState) {
        self.beat.seq = state.seq;
        self.beat.timestamp_ns = state.timestamp_ns;
        let ok = plane::publish(&self.state, state).is_ok()
            & plane::publish(&self.heartbeat, &self.beat).is_ok();
        if !ok {
            self.publish_errors += 1;
        }
        self.service.keepalive(Instant::now());
        if state.seq % 200 == 1 {
            let _ = plane::publish(&self.layout_out, &self.layout);
        }
        if self.every.is_zero() || self.last_status.elapsed() < self.every {
            return;
        }
        let secs = self.last_status.elapsed().as_secs_f64();
        let joints = state.joints();
        let missing = joints.iter().filter(|j| !j.is_valid()).count();
        let hottest = joints
            .iter()
            .filter(|j| j.is_valid())
            .map(|j| j.temperature_c)
            .fold(f32::NAN, f32::max);
        tracing::info!(
            "cycle {} | {:.1} Hz | deadline misses {} | joints {} ({} missing) | hottest {:.0} °C{}",
            state.seq,
            (state.seq - self.last_seq) as f64 / secs,
            state.deadline_misses,
            joints.len(),
            missing,
            hottest,
            if state.flags & telemetry::frames::STATE_FLAG_SAFE_STATE != 0 { " | SAFE STATE" } else { "" }
        );
        self.last_seq = state.seq;
        self.last_status = Instant::now();
    }
}

/// Every bus's device, tapped for the black box.
fn open_transports(config: &LoadedConfig, wait: Duration) -> Result<Vec<Tapped<SerialTransport>>> {
    let until = Instant::now() + wait;
    config
        .config
        .bus
        .iter()
        .map(|b| loop {
            match SerialTransport::open(&b.device, b.baud) {
                Ok(t) => break Ok(Tapped::new(t)),
                Err(e) if Instant::now() >= until => {
                    break Err(e).with_context(|| {
                        format!(
                            "bus {:?}: no device after {:.0} s",
                            b.name,
                            wait.as_secs_f64()
                        )
                    })
                }
                Err(_) => std::thread::sleep(Duration::from_millis(50)),
            }
        })
        .collect()
}

fn main() -> std::process::ExitCode {
    telemetry::process::finish(run(Args::parse()), |e| {
        e.is::<bus_driver::transport::TransportError>()
            .then_some(Exit::Unavailable)
    })
}

/// The process; an error ends it with its fault class's exit code (ARCHITECTURE.md, "Exit
/// codes").
fn run(args: Args) -> Result<()> {
    if args.print_default_calibration {
        print!("{}", bus_driver::config::DEFAULT_CALIBRATION_TOML);
        return Ok(());
    }
    let Some(Started { config, shutdown }) = args.process.start::<LoadedConfig>()? else {
        return Ok(());
    };
    let run_for = args.process.run_for()?;
    let config = select_buses(config, &args)?;
    let node = Plane::open(&args.process.domain, "bus-driver")?;
    node.cleanup_dead();
    let transports = open_transports(
        &config,
        Duration::from_secs_f64(args.wait_for_devices.max(0.0)),
    )?;
    let mut driver = Driver::new(&config, transports);
    // Before any torque is turned on: a bus latched off by a trip stays off, whatever the start
    // order of the processes and whether a supervisor is up.
    let trip_file = args
        .trip_file
        .clone()
        .unwrap_or_else(|| latch::default_path(&args.process.domain));
    apply_trip_record(&mut driver, &config, &trip_file);
    let mut io = Ipc {
        goals: node.subscriber(&plane::GOALS)?,
        wheel_goals: node.subscriber(&plane::WHEEL_GOALS)?,
        directives: node.subscriber(&plane::DIRECTIVES)?,
        supervisor: node.subscriber(&plane::SUPERVISOR_HEARTBEAT)?,
        state: node.publisher(&plane::JOINT_STATE)?,
        heartbeat: node.publisher(&plane::DRIVER_HEARTBEAT)?,
        layout_out: node.publisher(&plane::LAYOUT)?,
        health: node.publisher(&plane::BUS_HEALTH)?,
        wire: node.publisher(&plane::BUS_WIRE)?,
        layout: driver.layout(),
        beat: Heartbeat {
            pid: std::process::id(),
            peer: Peer::Driver as u8,
            ..Heartbeat::default()
        },
        every: Duration::from_secs_f64(args.status_every.max(0.0)),
        last_status: Instant::now(),
        last_seq: 0,
        publish_errors: 0,
        service: ServiceManager::from_env(),
        trip_file,
    };
    plane::publish(&io.layout_out, &io.layout)?;
    let supervisor_timeout = supervisor_timeout(&config);
    let rt = bus_driver::rt::prepare_control_thread();
    tracing::info!(?rt, "real-time preparation of the control thread");
    let failures = driver.setup();
    for (joint, error) in &failures {
        tracing::warn!(
            joint,
            "servo not brought up (retried every second): {error}"
        );
    }
    tracing::info!(
        buses = config.config.bus.len(),
        joints = driver.joint_names().count(),
        ready = driver.ready().filter(|r| *r).count(),
        eeprom_writes = driver.counters.eeprom_writes,
        rate_hz = config.config.rate_hz,
        domain = %args.process.domain,
        "driving; state on {}, goals from {}, the wheels' from {}",
        plane::JOINT_STATE.name,
        plane::GOALS.name,
        plane::WHEEL_GOALS.name
    );
    io.service.ready(&format!(
        "driving {} joints on {} buses at {} Hz",
        driver.joint_names().count(),
        config.config.bus.len(),
        config.config.rate_hz
    ));
    let max_cycles = run_for.map(|d| (d.as_secs_f64() * config.config.rate_hz).round() as u64);
    let summary = bus_driver::run(
        &mut driver,
        config.config.period(),
        supervisor_timeout,
        &mut io,
        &shutdown,
        max_cycles,
    );
    io.service.stopping();
    for (bus, counters) in driver.bus_counters() {
        tracing::info!(bus, ?counters, "bus errors by kind");
    }
    tracing::info!(
        cycles = summary.counters.cycles,
        rate_hz = format!("{:.1}", summary.rate_hz),
        deadline_misses = summary.counters.deadline_misses,
        publish_errors = io.publish_errors,
        "stopped; torque off"
    );
    println!("{}", serde_json::to_string(&summary)?);
    Ok(())
}

/// The configuration with its devices in `--device-dir` and only the buses named by `--bus`.
fn select_buses(mut config: LoadedConfig, args: &Args) -> Result<LoadedConfig> {
    if let Some(dir) = &args.device_dir {
        config = config.with_device_dir(dir);
    }
    if !args.buses.is_empty() {
        if let Some(unknown) = args
            .buses
            .iter()
            .find(|n| !config.config.bus.iter().any(|b| &b.name == *n))
        {
            let known: Vec<&str> = config.config.bus.iter().map(|b| b.name.as_str()).collect();
            let why = format!(
                "no bus {unknown:?} in the configuration (have: {})",
                known.join(", ")
            );
            return Err(telemetry::config::invalid("the command line", "--bus", why).into());
        }
        config.config.bus.retain(|b| args.buses.contains(&b.name));
    }
    Ok(config)
}

/// Latches off, before any torque, every bus the trip record names (all of them if it cannot
/// be read): whatever the start order of the processes and whether a supervisor is up.
fn apply_trip_record(
    driver: &mut Driver<Tapped<SerialTransport>>,
    config: &LoadedConfig,
    trip_file: &Path,
) {
    match latch::load(trip_file) {
        Ok(joints) => {
            let latched = driver.set_latch(&joints);
            if latched != 0 {
                tracing::warn!(
                    buses = ?config.config.bus.iter().enumerate().filter(|(b, _)| latched & (1 << b) != 0).map(|(_, bus)| bus.name.as_str()).collect::<Vec<_>>(),
                    file = %trip_file.display(),
                    "buses latched off by a trip stay off until `nori reenable`"
                );
            }
        }
        Err(e) => {
            tracing::error!("{e}: every bus stays off until the record can be read");
            driver.latch_all();
        }
    }
}

/// The supervisor's heartbeat bound (`None`: driving without a supervisor, development only).
fn supervisor_timeout(config: &LoadedConfig) -> Option<Duration> {
    match config.config.supervisor_timeout_ms {
        0 => {
            tracing::warn!(
                "supervisor-timeout-ms = 0: driving WITHOUT a supervisor (no stall or thermal protection beyond the firmware); development only"
            );
            None
        }
        ms => {
            tracing::info!(
                "safe state ({:?}) until the supervisor is heard from on {}",
                config.config.safe_state,
                plane::SUPERVISOR_HEARTBEAT.name
            );
            Some(Duration::from_millis(ms))
        }
    }
}
