//! `nori-camera`: one camera onto the state plane. The loop is `camera::process`; this binary
//! reads the configuration, opens the plane and reports what it did at exit (JSON on stdout).

use anyhow::{Context, Result};
use camera::config::CamerasConfig;
use camera::convert::rgb_len;
use camera::process::{jpeg_max_len, run, Camera, RunError};
use camera::source::{self, SourceError};
use clap::Parser;
use std::path::PathBuf;
use telemetry::plane::{CameraStream, Plane};
use telemetry::process::{finish, Exit, ProcessArgs, Started};
use telemetry::sensors::PixelFormat;

#[derive(Parser)]
#[command(
    version,
    about = "Nori A3 camera: frames from a V4L2 camera onto the state plane"
)]
struct Args {
    /// The camera to serve, by its name in the configuration.
    #[arg(long, required_unless_present = "print_default_config")]
    camera: Option<String>,
    /// Read the camera at DIR/camera-<name> (the simulator's sockets) instead of its device.
    #[arg(long, value_name = "DIR")]
    device_dir: Option<PathBuf>,
    #[command(flatten)]
    process: ProcessArgs,
}

fn main() -> std::process::ExitCode {
    finish(serve(&Args::parse()), |e| {
        match e.downcast_ref::<RunError>() {
            Some(RunError::Source(SourceError::Mode { .. } | SourceError::Unexpected { .. })) => {
                Some(Exit::Config)
            }
            Some(RunError::Source(_)) => Some(Exit::Unavailable),
            _ => None,
        }
    })
}

fn serve(args: &Args) -> Result<()> {
    let Some(Started {
        config, shutdown, ..
    }) = args.process.start::<CamerasConfig>()?
    else {
        return Ok(());
    };
    let config = match &args.device_dir {
        Some(dir) => config.with_device_dir(dir),
        None => config,
    };
    let name = args.camera.as_deref().unwrap_or_default();
    let Some(cam) = config.camera(name) else {
        let have: Vec<_> = config.cameras.iter().map(|c| c.name.as_str()).collect();
        return Err(telemetry::config::invalid(
            "--camera",
            "camera",
            format!("no camera {name:?} (have: {})", have.join(", ")),
        )
        .into());
    };
    let run_for = args.process.run_for()?;
    let node = Plane::open(&args.process.domain, &format!("camera_{name}"))?;
    let (width, height) = (cam.mode.width, cam.mode.height);
    let publisher = node.camera_publisher(name, CameraStream::Rgb, rgb_len(width, height))?;
    let jpegs = match cam.mode.format {
        PixelFormat::Mjpeg => {
            Some(node.camera_publisher(name, CameraStream::Mjpeg, jpeg_max_len(width, height))?)
        }
        _ => None,
    };
    let mut camera = Camera::new(name, cam.mode, publisher, jpegs);
    let result = run(&mut camera, &cam.device, source::open, &shutdown, run_for)
        .with_context(|| format!("camera {name}"));
    println!(
        "{}",
        serde_json::json!({"camera": name, "counters": camera.counters})
    );
    result
}
