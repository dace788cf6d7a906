//! `nori-bench-fleet-publisher`: the publishing robots of `nori bench fleet-ingest` (started by
//! it, not by hand): `robots` client sessions, each a robot streaming telemetry as its agent does
//! (congestion control Drop), paced together; prints the messages sent per robot (JSON).

use anyhow::{anyhow, Context, Result};
use bench::{state_msg, zenoh_session};
use clap::Parser;
use fleet_agent::keys::robot_key;
use fleet_agent::schema::encode;
use fleet_agent::zenoh::qos::CongestionControl;
use fleet_agent::zenoh::Wait;
use std::time::{Duration, Instant};

/// The publishers of `nori bench fleet-ingest`.
#[derive(Parser, Debug)]
#[command(name = "nori-bench-fleet-publisher", version)]
struct FleetPublishArgs {
    /// The collector's endpoint.
    #[arg(long)]
    connect: String,
    #[arg(long)]
    robots: usize,
    #[arg(long)]
    hz: f64,
    #[arg(long)]
    seconds: f64,
}

fn main() -> Result<()> {
    let args = &FleetPublishArgs::parse();
    let mut robots = Vec::with_capacity(args.robots);
    for r in 0..args.robots {
        let session = zenoh_session(vec![], vec![args.connect.clone()], "client")
            .context("opening a zenoh session")?;
        let publisher = session
            .declare_publisher(robot_key(&format!("r{r:04}"), "state"))
            .congestion_control(CongestionControl::Drop)
            .wait()
            .map_err(|e| anyhow!("{e}"))?;
        robots.push((session, publisher));
    }
    // Let every session finish joining before the clock starts.
    std::thread::sleep(Duration::from_millis(500));
    let period = Duration::from_secs_f64(1.0 / args.hz);
    let ticks = (args.seconds * args.hz).round() as u64;
    let mut sent = vec![0u64; args.robots];
    let start = Instant::now();
    for tick in 0..ticks {
        let payload = encode(&state_msg(tick));
        for ((_, publisher), n) in robots.iter().zip(&mut sent) {
            if publisher.put(payload.clone()).wait().is_ok() {
                *n += 1;
            }
        }
        let next = start + period * (tick as u32 + 1);
        if let Some(wait) = next.checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
    }
    println!("{}", serde_json::to_string(&sent)?);
    Ok(())
}
