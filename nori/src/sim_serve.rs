//! `nori sim serve`: the simulated robot on pseudo-terminals, one per bus.

use anyhow::{Context, Result};
use clap::Args;
use sim::pty::serve;
use sim::{BusReport, RobotDescription, SimBus};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// Where the simulator links its devices by default.
pub fn default_device_dir() -> PathBuf {
    std::env::temp_dir().join("nori-sim")
}

/// Options of `nori sim serve`.
#[derive(Args, Debug, Clone)]
pub struct ServeArgs {
    /// Robot description (TOML); the embedded Nori A3 when absent.
    #[arg(long)]
    pub description: Option<PathBuf>,
    /// Directory for the device links, one per bus (DIR/<bus name>).
    #[arg(long, value_name = "DIR", default_value_os_t = default_device_dir())]
    pub dir: PathBuf,
    /// Serve only these buses (repeatable); all when absent.
    #[arg(long = "bus")]
    pub buses: Vec<String>,
    /// Set up a protection scenario on the left arm (payload, obstacle or grasped object).
    #[arg(long, value_enum)]
    pub scenario: Option<sim::scenario::Scenario>,
    /// Integrate temperatures this many times faster than real time (accelerated heating).
    #[arg(long, default_value_t = 1.0)]
    pub thermal_speedup: f64,
    /// Mechanics step, s.
    #[arg(long, default_value_t = 0.001)]
    pub dt: f64,
    /// Write a JSON report here every second and at exit (what the servos received, temperatures).
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Stop after this many seconds.
    #[arg(long)]
    pub run_for: Option<f64>,
}

/// The simulator's report: one entry per bus.
#[derive(serde::Serialize)]
pub struct SimReport {
    /// Buses.
    pub buses: Vec<BusReport>,
}

fn write_report(path: &Path, buses: &[BusReport]) -> Result<()> {
    let tmp = path.with_extension("tmp");
    let report = SimReport {
        buses: buses.to_vec(),
    };
    std::fs::write(&tmp, serde_json::to_vec_pretty(&report)?)
        .with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("renaming to {}", path.display()))?;
    Ok(())
}

/// Runs `nori sim serve` until SIGINT/SIGTERM or `--run-for`.
pub fn run(args: &ServeArgs) -> Result<()> {
    let mut robot = match &args.description {
        Some(p) => RobotDescription::load(p)?,
        None => RobotDescription::nori_a3(),
    };
    if let Some(scenario) = args.scenario {
        scenario.apply(&mut robot);
        eprintln!(
            "nori sim: scenario {scenario:?} set up on {}",
            sim::scenario::SCENARIO_BUS
        );
    }
    if !(args.thermal_speedup.is_finite() && args.thermal_speedup >= 1.0) {
        anyhow::bail!(
            "--thermal-speedup must be ≥ 1, got {}",
            args.thermal_speedup
        );
    }
    if !(args.dt > 0.0 && args.dt <= 0.005) {
        anyhow::bail!("--dt must be in (0, 0.005] s, got {}", args.dt);
    }
    for name in &args.buses {
        if robot.bus(name).is_none() {
            anyhow::bail!(
                "no bus {name:?} in the description (have: {})",
                robot
                    .bus
                    .iter()
                    .map(|b| b.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
    }
    let shutdown = telemetry::process::stop_flag()?;
    let mut buses = Vec::new();
    for bus in robot
        .bus
        .iter()
        .filter(|b| args.buses.is_empty() || args.buses.contains(&b.name))
    {
        let mut sim_bus = SimBus::new(&robot, bus);
        sim_bus.thermal_speedup = args.thermal_speedup;
        buses.push((sim_bus, args.dir.join(&bus.name)));
    }
    let served = serve(buses, args.dt)?;
    for (device, bus) in served.devices.iter().zip(
        robot
            .bus
            .iter()
            .filter(|b| args.buses.is_empty() || args.buses.contains(&b.name)),
    ) {
        let target = std::fs::read_link(device).unwrap_or_default();
        eprintln!(
            "nori sim: serving bus {} ({} servos, {} baud) on {} -> {}",
            bus.name,
            bus.servo.len(),
            bus.baud,
            device.display(),
            target.display()
        );
    }
    eprintln!(
        "nori sim: robot {} running in real time (thermal ×{}); Ctrl-C stops it",
        robot.name, args.thermal_speedup
    );
    let start = Instant::now();
    let mut last_report = Instant::now();
    while !shutdown.load(Ordering::Relaxed)
        && args
            .run_for
            .is_none_or(|t| start.elapsed().as_secs_f64() < t)
    {
        std::thread::sleep(Duration::from_millis(20));
        if let Some(path) = &args.report {
            if last_report.elapsed() >= Duration::from_secs(1) {
                write_report(path, &served.reports())?;
                last_report = Instant::now();
            }
        }
    }
    let reports = served.stop();
    if let Some(path) = &args.report {
        write_report(path, &reports)?;
    }
    let hottest = reports
        .iter()
        .flat_map(|b| b.servos.iter())
        .map(|s| s.max_temperature_c)
        .fold(f64::NAN, f64::max);
    eprintln!("nori sim: stopped; hottest servo reached {hottest:.1} °C");
    Ok(())
}
