//! `nori-lidar`: the lidar onto the state plane. The loop is `lidar::process`; this binary reads
//! the configuration, opens the plane and reports what it did at exit (JSON on stdout).

use anyhow::{Context, Result};
use clap::Parser;
use lidar::config::LidarConfig;
use lidar::process::{run, Lidar, LidarError, LinkError, SerialLink};
use std::path::PathBuf;
use telemetry::plane::{self, Plane, LIDAR_SCAN};
use telemetry::process::{finish, start, Exit, Started};

#[derive(Parser)]
#[command(
    version,
    about = "Nori A3 lidar: revolutions of an RPLIDAR C1 onto the state plane"
)]
struct Args {
    /// Configuration file (TOML); the embedded default when absent.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Read the lidar at DIR/lidar (the simulator's pseudo-terminal) instead of its device.
    #[arg(long, value_name = "DIR")]
    device_dir: Option<PathBuf>,
    /// State-plane domain.
    #[arg(long, default_value = plane::DEFAULT_DOMAIN)]
    domain: String,
    /// Stop after this many seconds.
    #[arg(long)]
    run_for: Option<f64>,
    /// Print the default configuration and exit.
    #[arg(long)]
    print_default_config: bool,
}

fn main() -> std::process::ExitCode {
    finish(serve(&Args::parse()), |e| {
        match e.downcast_ref::<LidarError>() {
            // Not plugged in: restarting helps once someone plugs it in.
            Some(LidarError::Link(LinkError::Open { .. })) => Some(Exit::Unavailable),
            _ => None,
        }
    })
}

fn serve(args: &Args) -> Result<()> {
    let Some(Started {
        config, shutdown, ..
    }) = start::<LidarConfig>(args.print_default_config, args.config.as_deref())?
    else {
        return Ok(());
    };
    let config = match &args.device_dir {
        Some(dir) => config.with_device_dir(dir),
        None => config,
    };
    let run_for = telemetry::process::run_for(args.run_for)?;
    let node = Plane::open(&args.domain, "lidar")?;
    let mut lidar = Lidar::new(config.limits, node.publisher(&LIDAR_SCAN)?);
    let baud = config.baud;
    let result = run(
        &mut lidar,
        &config.device,
        |device| SerialLink::open(device, baud),
        config.silence,
        &shutdown,
        run_for,
    )
    .with_context(|| format!("lidar on {}", config.device.display()));
    let device = lidar.info.map(|i| {
        serde_json::json!({
            "model": i.model,
            "name": i.c_series_name(),
            "firmware": format!("{}.{:02}", i.firmware_major, i.firmware_minor),
            "hardware": i.hardware,
            "serial": i.serial_hex(),
        })
    });
    println!(
        "{}",
        serde_json::json!({"device": device, "counters": lidar.report()})
    );
    result
}
