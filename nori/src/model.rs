//! `nori model`: the model lab on measured data (`analyze`), its truth-model generator
//! (`generate`) and its accuracy benchmark (`bench`). The work is in the `model-lab` crate;
//! this module reads arguments, writes files and prints.

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use model_lab::electrical::CurrentEstimator;
use model_lab::generate::{generate, Spec};
use model_lab::{analyze, Effect, Options};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The model-lab commands.
#[derive(Subcommand, Debug)]
pub enum ModelCommand {
    /// Hold the simulation's servo model against measured data: misfit, cause, extension, gain.
    Analyze(AnalyzeArgs),
    /// Write measured-like data with one hidden effect (the truth model of the tests).
    Generate(GenerateArgs),
    /// Accuracy over many seeds per hidden effect, detection limits and analysis time.
    Bench(BenchArgs),
}

/// Options of `nori model analyze`.
#[derive(Args, Debug)]
pub struct AnalyzeArgs {
    /// Telemetry CSV (shared/data/README.md format), or a directory of them (one run each).
    data: PathBuf,
    /// Print one JSON object instead of the summary.
    #[arg(long)]
    json: bool,
    /// Write a report (Markdown + SVG plots) and the extended model into this directory.
    #[arg(long, value_name = "DIR")]
    report: Option<PathBuf>,
    /// Write the extended model (TOML, loaded by the simulator) to this file.
    #[arg(long, value_name = "FILE")]
    model_out: Option<PathBuf>,
    /// Fraction of the samples, in time order, used for fitting.
    #[arg(long, default_value_t = 0.7)]
    fit_fraction: f64,
    /// Servo model whose rated constants estimate currents the data do not carry.
    #[arg(long, default_value = "sts3215")]
    servo: String,
    /// Position gain (P_Coefficient) the data were recorded with, to estimate currents.
    #[arg(long, default_value_t = 32.0)]
    kp: f64,
}

/// Options of `nori model generate`.
#[derive(Args, Debug)]
pub struct GenerateArgs {
    /// Output CSV (a `.meta.json` sidecar is written next to it).
    out: PathBuf,
    /// Hidden effect: a catalog id or `none`.
    #[arg(long, default_value = "none")]
    effect: String,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Effect size in the catalog unit (random in the generator's range when absent).
    #[arg(long)]
    size: Option<f64>,
    /// Motors (random 2..=8 when absent).
    #[arg(long)]
    motors: Option<usize>,
    /// Recording length, s.
    #[arg(long, default_value_t = 7200.0)]
    duration_s: f64,
    /// Sample period, s.
    #[arg(long, default_value_t = 1.0)]
    period_s: f64,
}

/// Options of `nori model bench`.
#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Seeds per effect.
    #[arg(long, default_value_t = 50)]
    seeds: u64,
    /// Seeds per size step of the detection-limit sweep (0: skip the sweep).
    #[arg(long, default_value_t = 20)]
    sweep_seeds: u64,
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

/// Runs a model-lab command.
pub fn run(cmd: &ModelCommand) -> Result<()> {
    match cmd {
        ModelCommand::Analyze(a) => run_analyze(a),
        ModelCommand::Generate(a) => run_generate(a),
        ModelCommand::Bench(a) => run_bench(a),
    }
}

fn write(path: &Path, text: &str) -> Result<()> {
    std::fs::write(path, text).with_context(|| format!("cannot write {}", path.display()))
}

fn run_analyze(a: &AnalyzeArgs) -> Result<()> {
    let robot = sim::RobotDescription::nori_a3();
    let Some(rating) = robot.rating(&a.servo) else {
        bail!(
            "unknown servo model {:?} (sts3215, sts3250, sts3095)",
            a.servo
        );
    };
    let opts = Options {
        fit_fraction: a.fit_fraction,
        estimator: Some(CurrentEstimator {
            kp: a.kp,
            resistance_ohm: rating.rated_voltage / rating.stall_current_a,
            ke_v_s_per_rad: rating.rated_voltage / rating.no_load_speed_rad_s,
        }),
        ..Options::default()
    };
    let data = model_lab::load(&a.data)?;
    let start = Instant::now();
    let out = analyze(data, &opts, &mut |line| {
        eprintln!("[{:6.1} s] {line}", start.elapsed().as_secs_f64())
    })?;
    let an = &out.analysis;
    let source = a.data.display().to_string();
    let model_text = format!(
        "# Model extension fitted by `nori model analyze {source}`.\n{}",
        out.model.to_toml()
    );
    if let Some(dir) = &a.report {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        for (name, text) in model_lab::report::render(an, &out.traces, &source) {
            write(&dir.join(name), &text)?;
        }
        write(&dir.join("extended-model.toml"), &model_text)?;
        write(
            &dir.join("analysis.json"),
            &serde_json::to_string_pretty(an)?,
        )?;
        eprintln!("report written to {}", dir.join("report.md").display());
    }
    if let Some(path) = &a.model_out {
        write(path, &model_text)?;
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(an)?);
        return Ok(());
    }
    println!("data: {source}");
    println!(
        "cause: {} ({})\nheld-out RMSE ({:?}): nominal {:.4} {u}, extended {:.4} {u}, gain {:.1} %",
        an.cause,
        an.description,
        an.channel,
        an.baseline_rmse,
        an.extended_rmse,
        100.0 * an.gain,
        u = an.unit
    );
    for p in &an.parameters {
        println!("  {} = {:.4} {}", p.name, p.value, p.unit);
    }
    for c in &an.diagnostics.candidates {
        println!(
            "  tried {:18} gain {:+6.1} %  ΔBIC {:10.1}  {}",
            c.id.id(),
            100.0 * c.gain,
            c.delta_bic,
            c.verdict
        );
    }
    Ok(())
}

fn run_generate(a: &GenerateArgs) -> Result<()> {
    let Some(effect) = Effect::from_id(&a.effect) else {
        bail!("unknown effect {:?}", a.effect);
    };
    let spec = Spec {
        effect,
        size: a.size,
        duration_s: a.duration_s,
        period_s: a.period_s,
        motors: a.motors,
    };
    let g = generate(&spec, a.seed);
    write(&a.out, &g.csv)?;
    write(&a.out.with_extension("meta.json"), &g.meta)?;
    let p = g.truth.parameter.as_ref();
    println!(
        "wrote {}: {} motors, sensor noise {:.3} °C, hidden {} {}",
        a.out.display(),
        g.truth.motors,
        g.truth.sensor_noise_c,
        effect,
        p.map_or(String::new(), |p| format!(
            "{} = {:.4} {}",
            p.name, p.value, p.unit
        ))
    );
    Ok(())
}

fn run_bench(a: &BenchArgs) -> Result<()> {
    // Analysis time on the acceptance case: 2 h of 8 motors at 2 Hz (CSV parsing included),
    // next to its baseline in the same run: the nominal model alone (calibration and misfit
    // statistics, no extension tried) on the same data.
    let nominal_only = Options {
        candidates: Vec::new(),
        ..Options::default()
    };
    let mut only = Vec::new();
    for id in &a.effects {
        let Some(e) = Effect::from_id(id) else {
            bail!("unknown effect {id:?}");
        };
        only.push(e);
    }
    let mut timing = Vec::new();
    let timed: &[Effect] = if a.no_timing {
        &[]
    } else {
        &[Effect::None, Effect::NeighborCoupling]
    };
    for &effect in timed {
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
    let settings = model_lab::bench::Settings {
        seeds: a.seeds,
        sweep_seeds: a.sweep_seeds,
        jobs: a.jobs,
        effects: only,
        ..Default::default()
    };
    let report = model_lab::bench::run(&settings, &mut |l| eprintln!("{l}"));
    if a.json {
        let mut v = serde_json::to_value(&report)?;
        v["timing_2h_8_motors_2hz"] = serde_json::Value::Array(timing);
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    println!(
        "{} seeds per effect, {:.0} s at {} s per sample, 2..=8 motors; {:.0} s total",
        report.seeds, report.duration_s, report.period_s, report.seconds
    );
    for t in &timing {
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
    if let Some(null) = report.effects.iter().find(|e| e.effect == Effect::None) {
        println!(
            "false alarms on null data: {:.1} % ({} of {} runs named an effect; goal ≤ 5 %)",
            100.0 * (1.0 - null.accuracy),
            null.runs - (null.accuracy * null.runs as f64).round() as usize,
            null.runs
        );
    }
    println!("| hidden | size range | named correctly | parameter within 25 % | median parameter error | detection limit (≥ 90 %) | mean analysis |");
    println!("|---|---|---|---|---|---|---|");
    for e in &report.effects {
        println!(
            "| `{}` | {} | {:.0} % | {} | {} | {} | {:.2} s |",
            e.effect,
            if e.effect == Effect::None {
                "–".to_string()
            } else {
                format!("{}–{} {}", e.size_range.0, e.size_range.1, e.unit)
            },
            100.0 * e.accuracy,
            if e.effect == Effect::None {
                "–".to_string()
            } else {
                format!("{:.0} %", 100.0 * e.recovered)
            },
            e.median_parameter_error
                .map_or("–".into(), |v| format!("{:.1} %", 100.0 * v)),
            e.detection_limit
                .map_or("–".into(), |v| format!("{v:.4} {}", e.unit)),
            e.mean_seconds
        );
    }
    println!();
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
            e.effect,
            sweep.join(", "),
            e.unit,
            if conf.is_empty() {
                "–".into()
            } else {
                conf.join(", ")
            }
        );
    }
    Ok(())
}
