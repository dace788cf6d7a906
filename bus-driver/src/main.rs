//! `bus-driver`: the real-time loop on the servo buses, as a process.
//!
//! Parses the configuration, opens one serial transport per bus, brings the servos up, then runs
//! the fixed-rate loop: goals from the `nori/goals` service, state to `nori/joint-state`. SIGINT
//! and SIGTERM end the loop with torque off.

use anyhow::{Context, Result};
use bus_driver::driver::{GoalSource, StateSink};
use bus_driver::{run, Driver, LoadedConfig, SerialTransport};
use clap::Parser;
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::{Duration, Instant};
use telemetry::plane::{self, Plane, Pub, Sub};
use telemetry::{GoalFrame, JointState};

#[derive(Parser)]
#[command(
    version,
    about = "Nori A3 bus driver: the control loop on the servo buses"
)]
struct Args {
    /// Configuration file (TOML); the embedded A3 default when absent.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Open every bus at DIR/<bus name> (where `nori sim serve` links its pseudo-terminals).
    #[arg(long, value_name = "DIR")]
    device_dir: Option<PathBuf>,
    /// State-plane domain (iceoryx2 prefix); processes of one robot share it.
    #[arg(long, default_value = plane::DEFAULT_DOMAIN)]
    domain: String,
    /// Wait this long for the bus devices to appear at start, s.
    #[arg(long, default_value_t = 10.0)]
    wait_for_devices: f64,
    /// Stop after this many seconds (tests and benchmarks).
    #[arg(long)]
    run_for: Option<f64>,
    /// Seconds between status lines (0: none).
    #[arg(long, default_value_t = 5.0)]
    status_every: f64,
    /// Print the default configuration and exit.
    #[arg(long)]
    print_default_config: bool,
    /// Print the default calibration and exit.
    #[arg(long)]
    print_default_calibration: bool,
}

struct IpcGoals(Sub<GoalFrame>);

impl GoalSource for IpcGoals {
    fn latest(&mut self) -> Option<GoalFrame> {
        plane::newest(&self.0)
    }
}

/// Publishes each frame and, every `every`, logs one status line from it.
struct IpcState {
    publisher: Pub<JointState>,
    every: Duration,
    last_status: Instant,
    last_seq: u64,
    publish_errors: u64,
}

impl StateSink for IpcState {
    fn publish(&mut self, state: &JointState) {
        if plane::publish(&self.publisher, state).is_err() {
            self.publish_errors += 1;
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
            "cycle {} | {:.1} Hz | deadline misses {} | joints {} ({} missing) | hottest {:.0} °C",
            state.seq,
            (state.seq - self.last_seq) as f64 / secs,
            state.deadline_misses,
            joints.len(),
            missing,
            hottest
        );
        self.last_seq = state.seq;
        self.last_status = Instant::now();
    }
}

fn open_transports(config: &LoadedConfig, wait: Duration) -> Result<Vec<SerialTransport>> {
    let until = Instant::now() + wait;
    config
        .config
        .bus
        .iter()
        .map(|b| loop {
            match SerialTransport::open(&b.device, b.baud) {
                Ok(t) => break Ok(t),
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

fn main() -> Result<()> {
    let args = Args::parse();
    if args.print_default_config {
        print!("{}", bus_driver::config::DEFAULT_CONFIG_TOML);
        return Ok(());
    }
    if args.print_default_calibration {
        print!("{}", bus_driver::config::DEFAULT_CALIBRATION_TOML);
        return Ok(());
    }
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let mut config = match &args.config {
        Some(path) => LoadedConfig::load(path)?,
        None => LoadedConfig::embedded()?,
    };
    if let Some(dir) = &args.device_dir {
        config = config.with_device_dir(dir);
    }
    let shutdown = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(signal, shutdown.clone())
            .context("installing signal handlers")?;
    }
    let plane = Plane::open(&args.domain, "bus-driver")?;
    plane.cleanup_dead();
    let mut goals = IpcGoals(plane.subscriber(&plane::GOALS)?);
    let mut sink = IpcState {
        publisher: plane.publisher(&plane::JOINT_STATE)?,
        every: Duration::from_secs_f64(args.status_every.max(0.0)),
        last_status: Instant::now(),
        last_seq: 0,
        publish_errors: 0,
    };
    let transports = open_transports(
        &config,
        Duration::from_secs_f64(args.wait_for_devices.max(0.0)),
    )?;
    let mut driver = Driver::new(&config, transports);
    bus_driver::rt::prepare_control_thread();
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
        domain = %args.domain,
        "driving; state on {}, goals from {}",
        plane::JOINT_STATE.name,
        plane::GOALS.name
    );
    let max_cycles = args
        .run_for
        .map(|s| (s * config.config.rate_hz).round() as u64);
    let summary = run(
        &mut driver,
        config.config.period(),
        &mut goals,
        &mut sink,
        &shutdown,
        max_cycles,
    );
    for (bus, counters) in driver.bus_counters() {
        tracing::info!(bus, ?counters, "bus errors by kind");
    }
    tracing::info!(
        cycles = summary.counters.cycles,
        rate_hz = format!("{:.1}", summary.rate_hz),
        deadline_misses = summary.counters.deadline_misses,
        publish_errors = sink.publish_errors,
        "stopped; torque off"
    );
    println!("{}", serde_json::to_string(&summary)?);
    Ok(())
}
