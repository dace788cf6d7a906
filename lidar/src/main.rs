//! `nori-lidar`: the lidar onto the state plane. The loop is `lidar::process`; this binary reads
//! the configuration, opens the plane and reports what it did at exit (JSON on stdout).

use anyhow::{Context, Result};
use clap::Parser;
use lidar::config::LidarConfig;
use lidar::process::{run, Lidar, LidarError, LinkError, SerialLink};
use std::path::PathBuf;
use telemetry::plane::{Plane, LIDAR_SCAN};
use telemetry::process::{finish, Exit, ProcessArgs, Started};

#[derive(Parser)]
#[command(
    version,
    about = "Nori A3 lidar: revolutions of an RPLIDAR C1 onto the state plane"
)]
struct Args {
    /// Read the lidar at DIR/lidar (the simulator's pseudo-terminal) instead of its device.
    #[arg(long, value_name = "DIR")]
    device_dir: Option<PathBuf>,
    #[command(flatten)]
    process: ProcessArgs,
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
    }) = args.process.start::<LidarConfig>()?
    else {
        return Ok(());
    };
    let config = match &args.device_dir {
        Some(dir) => config.with_device_dir(dir),
        None => config,
    };
    let run_for = args.process.run_for()?;
    let node = Plane::open(&args.process.domain, "lidar")?;
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
