//! `nori bench ik`: the arm's inverse kinematics (`body::ik`) over random reachable targets
//! (the tool pose of angles drawn uniformly within the joints' ranges), against the plain damped
//! least squares (the same solver without the null-space moves toward the ranges' middles) on
//! the same targets in the same run: success within 1 mm and 1°, time per solve, and how far the
//! answers keep from the ranges' ends.

use anyhow::Result;
use body::ik::{IkSettings, Mount, ToolTarget, MAX_JOINTS};
use body::kinematics::{Body, Pose2};
use clap::Args;
use std::time::Instant;
use telemetry::stats::quantile_sorted;

/// Options of `nori bench ik`.
#[derive(Args, Debug)]
pub struct IkArgs {
    /// Random targets per start kind.
    #[arg(long, default_value_t = 2000)]
    targets: usize,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

#[derive(Default)]
struct Tally {
    solved: usize,
    micros: Vec<f64>,
    margin: f64,
}

/// Within 1 mm and 1°, the acceptance's tolerance (the solver's own is tighter).
fn reached(body: &Body, q: &[f64; MAX_JOINTS], target: &ToolTarget) -> bool {
    let Some(p) = body.arm_pose(0, &q[..7], 0.3, Pose2::default()) else {
        return false;
    };
    let d = (0..3)
        .map(|i| (p.tool[i] - target.position[i]).powi(2))
        .sum::<f64>()
        .sqrt();
    let dot = (0..4)
        .map(|i| p.tool_rotation[i] * target.rotation[i])
        .sum::<f64>()
        .abs()
        .min(1.0);
    d <= 1e-3 && 2.0 * dot.acos() <= 1f64.to_radians()
}

pub fn run(args: &IkArgs) -> Result<()> {
    let body = Body::from_description(&body::RobotDescription::nori_a3())?;
    let limits = body.arms()[0].hard_stops();
    let mount = Mount {
        lift_m: 0.3,
        base: Pose2::default(),
    };
    let solvers = [
        ("with centring (body::ik)", IkSettings::default()),
        (
            "plain damped least squares",
            IkSettings {
                centring: 0.0,
                ..IkSettings::default()
            },
        ),
    ];
    let mut report = Vec::new();
    for (starts, seed_noise) in [
        ("tracking (seed 0.1 rad off)", 0.1),
        ("cold (seed all zeros)", -1.0),
    ] {
        // The same targets every run.
        let mut draws = sim::rng::Rng::new(42);
        let mut tallies: Vec<Tally> = solvers.iter().map(|_| Tally::default()).collect();
        for _ in 0..args.targets {
            let truth: Vec<f64> = limits
                .iter()
                .map(|(lo, hi)| lo + (hi - lo) * draws.uniform())
                .collect();
            let Some(p) = body.arm_pose(0, &truth, 0.3, Pose2::default()) else {
                anyhow::bail!("the A3 has no left arm");
            };
            let target = ToolTarget {
                position: p.tool,
                rotation: p.tool_rotation,
            };
            let seed: Vec<f64> = if seed_noise > 0.0 {
                truth
                    .iter()
                    .map(|q| q + seed_noise * (2.0 * draws.uniform() - 1.0))
                    .collect()
            } else {
                vec![0.0; truth.len()]
            };
            // The two solvers alternate on each target: the machine's noise falls on both.
            for (tally, (_, settings)) in tallies.iter_mut().zip(&solvers) {
                let t = Instant::now();
                let solved = body.solve(0, &target, &seed, &limits, mount, settings);
                tally.micros.push(t.elapsed().as_secs_f64() * 1e6);
                if let Ok(s) = solved {
                    if reached(&body, &s.q, &target) {
                        tally.solved += 1;
                        tally.margin += (0..7)
                            .map(|k| {
                                let (lo, hi) = limits[k];
                                (s.q[k] - lo).min(hi - s.q[k]) / (hi - lo)
                            })
                            .fold(f64::INFINITY, f64::min);
                    }
                }
            }
        }
        for (tally, (name, _)) in tallies.iter_mut().zip(&solvers) {
            tally.micros.sort_by(f64::total_cmp);
            report.push(serde_json::json!({
                "starts": starts,
                "solver": name,
                "targets": args.targets,
                "success": tally.solved as f64 / args.targets as f64,
                "p50_us": quantile_sorted(&tally.micros, 0.5),
                "p99_us": quantile_sorted(&tally.micros, 0.99),
                "mean_us": tally.micros.iter().sum::<f64>() / tally.micros.len() as f64,
                "smallest_margin_mean": tally.margin / tally.solved.max(1) as f64,
            }));
        }
    }
    if args.json {
        println!("{}", serde_json::Value::Array(report));
        return Ok(());
    }
    println!(
        "arm IK, the A3's left arm (7 joints, hard stops), {} random reachable targets each; \
         success = within 1 mm and 1°",
        args.targets
    );
    for r in &report {
        println!(
            "  {:<28} {:<28} success {:>6.2} %  per solve p50 {:>7.1} µs  p99 {:>7.1} µs  \
             mean {:>7.1} µs  smallest margin to a range end {:.3} of the range",
            r["starts"].as_str().unwrap_or(""),
            r["solver"].as_str().unwrap_or(""),
            100.0 * r["success"].as_f64().unwrap_or(0.0),
            r["p50_us"].as_f64().unwrap_or(0.0),
            r["p99_us"].as_f64().unwrap_or(0.0),
            r["mean_us"].as_f64().unwrap_or(0.0),
            r["smallest_margin_mean"].as_f64().unwrap_or(0.0),
        );
    }
    Ok(())
}
