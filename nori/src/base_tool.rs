//! `nori base`: drive the base at a velocity for a while, printing where the base controller
//! says it is.

use crate::plane_tools::PlaneArgs;
use anyhow::{bail, Context, Result};
use clap::Args;
use std::time::{Duration, Instant};
use telemetry::motion::{BaseCommand, BaseState};
use telemetry::plane;

/// Options of `nori base`.
#[derive(Args, Debug)]
pub struct BaseArgs {
    #[command(flatten)]
    plane: PlaneArgs,
    /// Forward speed, m/s (the controller's limits and protective field apply).
    #[arg(allow_hyphen_values = true)]
    linear: f32,
    /// Turn rate, rad/s, counter-clockwise seen from above.
    #[arg(allow_hyphen_values = true, default_value_t = 0.0)]
    angular: f32,
    /// For this long, s; then the commands stop and the base brakes to rest.
    #[arg(long = "for", default_value_t = 2.0)]
    seconds: f64,
}

/// Sends the command every 50 ms (the controller's timeout is 250 ms) and prints the base's
/// state every half second, then once more when it has come to rest.
pub fn base(args: &BaseArgs) -> Result<()> {
    if !(args.linear.is_finite() && args.angular.is_finite()) {
        bail!("the speeds must be numbers");
    }
    let run = Duration::try_from_secs_f64(args.seconds)
        .ok()
        .filter(|d| *d <= Duration::from_secs(600))
        .ok_or_else(|| anyhow::anyhow!("--for {}: 0 to 600 s", args.seconds))?;
    let (node, _) = args.plane.open("base", Duration::from_secs(2))?;
    let commands = node.publisher(&plane::BASE_COMMAND)?;
    let states = node.subscriber(&plane::BASE_STATE)?;
    let start = Instant::now();
    let (mut seq, mut last_print, mut last) = (0, None::<Instant>, None::<BaseState>);
    while start.elapsed() < run + Duration::from_secs(1) {
        if start.elapsed() < run {
            seq += 1;
            let command = BaseCommand {
                seq,
                timestamp_ns: telemetry::clock::monotonic_ns(),
                linear_m_s: args.linear,
                angular_rad_s: args.angular,
            };
            plane::publish(&commands, &command)?;
        }
        last = plane::newest(&states).or(last);
        if let Some(s) = &last {
            if last_print.is_none_or(|t| t.elapsed() >= Duration::from_millis(500)) {
                println!("{s}");
                last_print = Some(Instant::now());
            }
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let last = last.context("no base state on the plane: is nori-base running?")?;
    println!("{last}");
    Ok(())
}
