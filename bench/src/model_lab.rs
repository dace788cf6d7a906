//! `model-lab`: the model lab's accuracy over many seeds per hidden effect, its detection limits,
//! and its analysis time next to the nominal fit alone on the same data.

use anyhow::{bail, Result};
use clap::Args;
use model_lab::bench::Report;
use model_lab::generate::{generate, Spec};
use model_lab::{analyze, Effect, Options};
use std::time::Instant;

/// Options of `nori bench model-lab`.
#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Seeds per effect.
    #[arg(long, default_value_t = 50)]
    seeds: u64,
    /// Seeds per size step of the detection-limit sweep (0: skip the sweep).
    #[arg(long, default_value_t = 20)]
    sweep_seeds: u64,
    /// Seeds per motion effect (generated runs through the motion channel; 0: skip it).
    #[arg(long, default_value_t = 50)]
    motion_seeds: u64,
    /// Only these families of rows: catalog, foreign, pairs, dirty, motion (all by default).
    #[arg(long, value_delimiter = ',')]
    rows: Vec<String>,
    /// Worker threads.
    #[arg(long, default_value_t = 2)]
    jobs: usize,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
    /// Only these hidden effects (catalog ids or `none`, comma-separated; all by default).
    #[arg(long, value_delimiter = ',')]
    effects: Vec<String>,
    /// Skip the 2 h × 8 motors timing runs (for quick accuracy checks).
    #[arg(long)]
    no_timing: bool,
}

/// Runs `nori bench model-lab`.
pub fn run_bench(a: &BenchArgs) -> Result<()> {
    let mut only = Vec::new();
    for id in &a.effects {
        let Some(e) = Effect::from_id(id) else {
            bail!("unknown effect {id:?}");
        };
        only.push(e);
    }
    let timing = if a.no_timing {
        Vec::new()
    } else {
        analysis_timing()?
    };
    let settings = model_lab::bench::Settings {
        seeds: a.seeds,
        sweep_seeds: a.sweep_seeds,
        jobs: a.jobs,
        effects: only,
        motion_seeds: a.motion_seeds,
        rows: a.rows.clone(),
        ..Default::default()
    };
    if !a.no_timing {
        motion_timing();
    }
    let report = model_lab::bench::run(&settings, &mut |l| eprintln!("{l}"));
    if a.json {
        let mut v = serde_json::to_value(&report)?;
        v["timing_2h_8_motors_2hz"] = serde_json::Value::Array(timing);
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    print_summary(&report, &timing);
    print_accuracy_table(&report);
    println!();
    print_sweep_table(&report);
    Ok(())
}

/// Analysis time on the acceptance case: 2 h of 8 motors at 2 Hz (CSV parsing included),
/// next to its baseline in the same run: the nominal model alone (calibration and misfit
/// statistics, no extension tried) on the same data. One row per hidden effect timed.
fn analysis_timing() -> Result<Vec<serde_json::Value>> {
    let nominal_only = Options {
        candidates: Vec::new(),
        search_form: false,
        ..Options::default()
    };
    let mut timing = Vec::new();
    for effect in [Effect::None, Effect::NeighborCoupling] {
        let g = generate(
            &Spec {
                motors: Some(8),
                period_s: 0.5,
                ..Spec::new(effect)
            },
            7,
        );
        let t = Instant::now();
        let base = analyze(g.dataset()?, &nominal_only, &mut |_| {})?;
        let baseline_s = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let out = analyze(g.dataset()?, &Options::default(), &mut |_| {})?;
        let s = t.elapsed().as_secs_f64();
        eprintln!(
            "2 h × 8 motors at 2 Hz, hidden {effect}: named {} in {s:.2} s; nominal fit only \
             {baseline_s:.2} s; ratio {:.1}",
            out.analysis.cause,
            s / baseline_s
        );
        timing.push(serde_json::json!({
            "hidden": effect, "named": out.analysis.cause, "seconds": s,
            "nominal_only_seconds": baseline_s, "ratio": s / baseline_s,
            "nominal_only_cause": base.analysis.cause,
            "samples": g.truth.motors * 14_400,
        }));
    }
    Ok(timing)
}

/// The report's headline: its scale, the analysis times, the false alarms on null data.
fn print_summary(report: &Report, timing: &[serde_json::Value]) {
    println!(
        "{} seeds per effect, {:.0} s at {} s per sample, 2..=8 motors; {:.0} s total",
        report.seeds, report.duration_s, report.period_s, report.seconds
    );
    for t in timing {
        println!(
            "analysis of 2 h × 8 motors at 2 Hz (hidden {}, named {}): {:.2} s; nominal fit \
             only: {:.2} s; ratio {:.1} (goal ≤ 10 s)",
            t["hidden"].as_str().unwrap_or("?"),
            t["named"].as_str().unwrap_or("?"),
            t["seconds"].as_f64().unwrap_or(f64::NAN),
            t["nominal_only_seconds"].as_f64().unwrap_or(f64::NAN),
            t["ratio"].as_f64().unwrap_or(f64::NAN),
        );
    }
    if let Some(null) = report
        .effects
        .iter()
        .find(|e| e.effect == Effect::None && e.runs > 0)
    {
        println!(
            "false alarms on null data: {:.1} % ({} of {} runs named an effect; goal ≤ 5 %)",
            100.0 * (1.0 - null.accuracy),
            null.runs - (null.accuracy * null.runs as f64).round() as usize,
            null.runs
        );
    }
}

/// The accuracy table: per hidden effect, how often it was named, its parameter recovered,
/// its detection limit.
fn print_accuracy_table(report: &Report) {
    println!("| hidden | size range | named correctly | a wrong catalog name | parameter within 25 % | median parameter error | detection limit (≥ 90 %) | a form found | mean analysis |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for e in &report.effects {
        println!(
            "| `{}` | {} | {:.0} % (`{}`) | {:.0} % | {} | {} | {} | {:.0} % | {:.2} s |",
            e.hidden,
            if matches!(e.effect, Effect::None | Effect::Unexplained) {
                "–".to_string()
            } else {
                format!("{}–{} {}", e.size_range.0, e.size_range.1, e.unit)
            },
            100.0 * e.accuracy,
            e.effect,
            100.0 * e.wrong_name(),
            if matches!(e.effect, Effect::None | Effect::Unexplained) {
                "–".to_string()
            } else {
                format!("{:.0} %", 100.0 * e.recovered)
            },
            e.median_parameter_error
                .map_or("–".into(), |v| format!("{:.1} %", 100.0 * v)),
            e.detection_limit
                .map_or("–".into(), |v| format!("{v:.4} {}", e.unit)),
            100.0 * e.form_found,
            e.mean_seconds
        );
    }
}

/// The detection sweep and the confusions, per hidden effect.
fn print_sweep_table(report: &Report) {
    println!(
        "| hidden | detection sweep: size → named (seeds 1000..) | confusions (accuracy runs) |"
    );
    println!("|---|---|---|");
    for e in &report.effects {
        let sweep: Vec<String> = e
            .sweep
            .iter()
            .map(|(s, r)| format!("{s:.4} → {:.0} %", 100.0 * r))
            .collect();
        let conf: Vec<String> = e
            .confusions
            .iter()
            .map(|(c, n)| format!("{c} × {n}"))
            .collect();
        println!(
            "| `{}` | {} {} | {} |",
            e.hidden,
            sweep.join(", "),
            e.unit,
            if conf.is_empty() {
                "–".into()
            } else {
                conf.join(", ")
            }
        );
    }
}

/// The motion channel's replay of a 6 s run (the goal: ≤ 50 ms) next to its baseline in the
/// same run: the simulator's servo stepped bare for the same 6 s (no log to follow, no load).
fn motion_timing() {
    use model_lab::motion::{simulate, MotionParams, MotionRun};
    use sim::servo::{Surroundings, FIRMWARE_PERIOD_S};
    let g = model_lab::generate::generate_motion(Effect::None, 7);
    let robot = sim::RobotDescription::nori_a3();
    let (Ok(d), Some(rating)) = (g.dataset(), robot.rating("sts3250")) else {
        return;
    };
    let runs = MotionRun::from_dataset(&d, rating.rated_voltage);
    let p = MotionParams::default();
    let repeats = 20;
    let t = Instant::now();
    for _ in 0..repeats {
        for r in &runs {
            std::hint::black_box(simulate(rating, &p, r));
        }
    }
    let replay = t.elapsed().as_secs_f64() / (repeats * runs.len()) as f64;
    let t = Instant::now();
    for _ in 0..repeats * runs.len() {
        let mut s = sim::servo::Servo::new(1, rating.model, rating, 0.0, 25.0);
        for _ in 0..(6.0 / FIRMWARE_PERIOD_S) as usize {
            s.step(FIRMWARE_PERIOD_S, Surroundings::BENCH);
        }
        std::hint::black_box(s.angle);
    }
    let bare = t.elapsed().as_secs_f64() / (repeats * runs.len()) as f64;
    println!(
        "motion: a 6 s run replayed in {:.2} ms (goal ≤ 50 ms); the servo stepped bare for 6 s: \
         {:.2} ms; ratio {:.2}",
        1e3 * replay,
        1e3 * bare,
        replay / bare
    );
}
