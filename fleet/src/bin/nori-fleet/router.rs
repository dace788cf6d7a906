//! `nori router`: a zenoh router from a JSON5 configuration, for a site or a test fleet, without
//! building `zenohd` (which reads the same file: `zenohd -c router.json5`). The configuration
//! made by `deploy/zenoh/make-dev-ca.sh` listens with mutual TLS and enforces the fleet's
//! access control.

use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// Options of `nori router`.
#[derive(Args, Debug)]
pub struct RouterArgs {
    /// zenoh JSON5 configuration (mode "router").
    #[arg(long)]
    pub config: PathBuf,
    /// Stop after this many seconds.
    #[arg(long)]
    pub run_for: Option<f64>,
}

/// Routes until Ctrl-C (or `--run-for`).
pub fn run(args: &RouterArgs) -> Result<()> {
    telemetry::process::init_logging();
    let stop = telemetry::process::stop_flag()?;
    let session = fleet_agent::net::open_file(&args.config)
        .with_context(|| format!("starting the router from {}", args.config.display()))?;
    tracing::info!(config = %args.config.display(), zid = %session.zid(), "routing");
    let started = Instant::now();
    while !stop.load(Ordering::Relaxed)
        && args
            .run_for
            .is_none_or(|s| started.elapsed().as_secs_f64() < s)
    {
        std::thread::sleep(Duration::from_millis(50));
    }
    Ok(())
}
