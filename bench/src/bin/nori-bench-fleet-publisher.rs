//! `nori-bench-fleet-publisher`: the publishing robots of `nori bench fleet-ingest` (started by
//! it, not by hand): `robots` client sessions, each a robot streaming telemetry as its agent does
//! (congestion control Drop), paced together. Prints `ready` once every session is open, starts
//! streaming when a line comes on its standard input (the bench starts every publisher process
//! at once, and measures only the stream), then prints the messages sent per robot (JSON).

use anyhow::{anyhow, Context, Result};
use bench::{state_msg, zenoh_session};
use clap::Parser;
use fleet_agent::keys::robot_key;
use fleet_agent::schema::encode;
use fleet_agent::zenoh::qos::CongestionControl;
use fleet_agent::zenoh::Wait;
use std::io::Write;
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
    /// The first robot's number (robots are `r00000`, `r00001` ...).
    #[arg(long, default_value_t = 0)]
    first: usize,
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
            .declare_publisher(robot_key(&format!("r{:05}", args.first + r), "state"))
            .congestion_control(CongestionControl::Drop)
            .wait()
            .map_err(|e| anyhow!("{e}"))?;
        robots.push((session, publisher));
    }
    // Let every session finish joining, then wait for the bench's word.
    std::thread::sleep(Duration::from_millis(500));
    println!("ready");
    std::io::stdout().flush()?;
    std::io::stdin().read_line(&mut String::new())?;
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
