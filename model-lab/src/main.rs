//! `nori-model` (`nori model`): the model lab on measured data (`analyze`) and its truth-model
//! generator (`generate`); its accuracy benchmark is `nori bench model-lab` (`nori model bench`
//! runs it). The work is in the library; this binary reads arguments, writes files and prints.

use anyhow::{bail, Context, Result};
use clap::{Args, Parser};
use model_lab::generate::{generate, Spec};
use model_lab::motion::MotionAnalysis;
use model_lab::{analyze, Analysis, Effect, Options, Outcome};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The model-lab commands.
#[derive(Parser, Debug)]
#[command(
    name = "nori-model",
    version,
    about = "The model lab: the simulation's servo model held against measured data"
)]
enum ModelCommand {
    /// Hold the simulation's servo model against measured data: misfit, cause, extension, gain.
    Analyze(AnalyzeArgs),
    /// Write measured-like data with one hidden effect (the truth model of the tests).
    Generate(GenerateArgs),
    /// Play a black box's bus traffic into the simulated servos and hold the simulator's
    /// replies against the recorded ones, register by register (`nori sim replay`).
    Replay(ReplayArgs),
}

/// Options of `nori sim replay`.
#[derive(Args, Debug)]
struct ReplayArgs {
    /// The box (`nori blackbox list`; `nori blackbox export --mcap` copies one out).
    #[arg(value_name = "BOX.mcap")]
    path: PathBuf,
    /// Robot description (TOML) of the robot the box was recorded on; the embedded Nori A3
    /// when absent.
    #[arg(long)]
    description: Option<PathBuf>,
    /// Loads known on the robot when it was recorded: a protection scenario's set-up, as
    /// `nori sim serve --scenario` (repeatable).
    #[arg(long, value_enum)]
    scenario: Vec<sim::scenario::Scenario>,
    /// Temperatures integrated this many times faster than real time: as the simulator that
    /// recorded the box did (`nori sim scenario overheat` heats 120 times faster); 1 for a
    /// real robot.
    #[arg(long, default_value_t = 1.0)]
    thermal_speedup: f64,
    /// The servos' constants (as `nori sim serve`).
    #[arg(long, value_enum, default_value_t = sim::constants::ConstantsChoice::Fitted)]
    servo_constants: sim::constants::ConstantsChoice,
    /// A model extension on every servo (what `nori model analyze` wrote): does it close the
    /// gap?
    #[arg(long, value_name = "FILE")]
    model_extension: Option<PathBuf>,
    /// Mechanics step, s.
    #[arg(long, default_value_t = 0.001)]
    dt: f64,
    /// Stretches of the box each register's error is also given over.
    #[arg(long, default_value_t = 6)]
    windows: usize,
    /// Print one JSON object instead of the summary.
    #[arg(long)]
    json: bool,
}

/// `paths` with each black box (`.mcap`) written as a run of CSV and its sidecar in `dir`.
fn boxes_as_runs(paths: &[PathBuf], dir: &std::path::Path) -> Result<Vec<PathBuf>> {
    paths
        .iter()
        .map(|p| {
            if p.extension().is_none_or(|x| x != "mcap") {
                return Ok(p.clone());
            }
            let bytes = std::fs::read(p).with_context(|| format!("reading {}", p.display()))?;
            let (csv, side) = blackbox::export::joint_states_csv(&bytes);
            std::fs::create_dir_all(dir)?;
            let stem = p.file_stem().unwrap_or_default().to_string_lossy();
            let run = dir.join(format!("{stem}.csv"));
            std::fs::write(&run, csv)?;
            std::fs::write(run.with_extension("meta.json"), side.to_string())?;
            Ok(run)
        })
        .collect()
}

/// Options of `nori model analyze`.
#[derive(Args, Debug)]
struct AnalyzeArgs {
    /// Telemetry CSVs (data/README.md format) or directories of them, one run per file, taken
    /// together (name files one by one to leave runs out of the fit); a black box (`.mcap`,
    /// `nori blackbox list`) is read as one run of its joint states.
    #[arg(required = true)]
    data: Vec<PathBuf>,
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
struct GenerateArgs {
    /// Output CSV (a `.meta.json` sidecar is written next to it).
    out: PathBuf,
    /// Hidden effect: a catalog id or `none`.
    #[arg(long, default_value = "none")]
    effect: String,
    /// Seed of the generator's random draws: the same seed and options, the same data.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Effect size in the catalog unit (random in the generator's range when absent).
    #[arg(long)]
    size: Option<f64>,
    /// Also hide an effect outside the catalog: cooling_loss or hidden_heater.
    #[arg(long)]
    foreign: Option<String>,
    /// Also hide a second catalog effect (its size drawn from its range).
    #[arg(long)]
    second: Option<String>,
    /// Write one channel wrong: milliamps, stuck or clock_jump.
    #[arg(long)]
    dirty: Option<String>,
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

fn main() -> Result<()> {
    match &ModelCommand::parse() {
        ModelCommand::Analyze(a) => run_analyze(a),
        ModelCommand::Generate(a) => run_generate(a),
        ModelCommand::Replay(a) => run_replay(a),
    }
}

fn write(path: &Path, text: &str) -> Result<()> {
    std::fs::write(path, text).with_context(|| format!("cannot write {}", path.display()))
}

/// `nori model analyze`: the analysis, its report and model file, and its summary or JSON.
fn run_analyze(a: &AnalyzeArgs) -> Result<()> {
    let opts = options(a)?;
    let scratch = std::env::temp_dir().join(format!("nori-model-boxes-{}", std::process::id()));
    let runs = boxes_as_runs(&a.data, &scratch);
    let data = runs.and_then(|runs| Ok(model_lab::load_all(&runs)?));
    let _ = std::fs::remove_dir_all(&scratch);
    let data = data?;
    let start = Instant::now();
    let out = analyze(data, &opts, &mut |line| {
        eprintln!("[{:6.1} s] {line}", start.elapsed().as_secs_f64())
    })?;
    let an = &out.analysis;
    let source = a
        .data
        .iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(" ");
    let model_text = format!(
        "# Model extension fitted by `nori model analyze --servo {} {source}`.\n{}",
        a.servo,
        out.model.to_toml()
    );
    if let Some(dir) = &a.report {
        write_report(dir, &out, &source, &model_text)?;
    }
    if let Some(path) = &a.model_out {
        write(path, &model_text)?;
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(an)?);
        return Ok(());
    }
    print_summary(an, &source);
    if let Some(m) = &an.motion {
        print_motion(m);
    }
    Ok(())
}

/// The analysis options of the arguments: the servo's rating estimates the currents and
/// bounds what the data may read.
fn options(a: &AnalyzeArgs) -> Result<Options> {
    Ok(Options {
        fit_fraction: a.fit_fraction,
        ..Options::for_servo(&a.servo, a.kp)?
    })
}

/// Writes the report's files, the extended model and the analysis as JSON into `dir`.
fn write_report(dir: &Path, out: &Outcome, source: &str, model_text: &str) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    for (name, text) in model_lab::report::render(&out.analysis, &out.traces, source) {
        write(&dir.join(name), &text)?;
    }
    write(&dir.join("extended-model.toml"), model_text)?;
    write(
        &dir.join("analysis.json"),
        &serde_json::to_string_pretty(&out.analysis)?,
    )?;
    eprintln!("report written to {}", dir.join("report.md").display());
    Ok(())
}

/// Prints the cause with its figures, what the audit did, the verdicts, what is left
/// unexplained and every extension tried.
fn print_summary(an: &Analysis, source: &str) {
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
    if an.causes.len() > 1 {
        let all: Vec<&str> = an.causes.iter().map(|c| c.id()).collect();
        println!("effects named together: {}", all.join(" + "));
    }
    for p in &an.parameters {
        println!("  {} = {:.4} {}", p.name, p.value, p.unit);
    }
    for f in &an.diagnostics.audit {
        println!(
            "  data: {} {} ({}): {}",
            f.column, f.action, f.kind, f.detail
        );
    }
    for v in &an.diagnostics.verdicts {
        println!(
            "  judged {:?} after {}: {}",
            v.channel,
            v.extension.map_or("none", |e| e.id()),
            v.judged()
        );
    }
    if let Some(u) = &an.unexplained {
        let r: Vec<String> = u
            .strongest_regressors
            .iter()
            .map(|(k, r)| format!("{k} {r:+.2}"))
            .collect();
        println!("  unexplained: the residual follows {}", r.join(", "));
        if let Some(f) = &u.form {
            println!("  unexplained; {}", f.describe());
        }
        if let Some((m, rmse, bias)) = u.motors.first() {
            println!(
                "  worst motor {m}: RMSE {rmse:.3} {u}, bias {bias:+.3} {u}",
                u = an.unit
            );
        }
    }
    for c in &an.diagnostics.candidates {
        println!(
            "  tried {:18} gain {:+6.1} %  ΔBIC {:10.1}  {}",
            match c.with {
                Some(w) => format!("{} + {}", w.id(), c.id.id()),
                None => c.id.id().to_string(),
            },
            100.0 * c.gain,
            c.delta_bic,
            c.verdict
        );
    }
}

/// Prints the motion channel: its cause, the servo as configured and each model held out.
fn print_motion(m: &MotionAnalysis) {
    println!(
        "motion ({} runs through the simulator's {}): cause {}; {}",
        m.as_configured.len(),
        m.servo,
        m.cause,
        m.judged()
    );
    for (run, mae, rmse) in &m.as_configured {
        println!("  as configured  {run}: MAE {mae:.4} rad, RMSE {rmse:.4} rad");
    }
    if !m.always_fitted.is_empty() {
        println!(
            "  never held out (the only run with the load free of the position loop): {}",
            m.always_fitted.join(", ")
        );
    }
    for c in &m.candidates {
        let runs: Vec<String> = c.runs.iter().map(|h| format!("{:.4}", h.mae_rad)).collect();
        println!(
            "  {:20} held-out MAE {:.4} rad ({}) gain {:+6.1} %  {}",
            c.id.id(),
            c.mae_rad,
            runs.join(" "),
            100.0 * c.gain,
            c.verdict
        );
    }
    println!("  one run simulated in {:.1} ms", 1e3 * m.seconds_per_run);
}

fn run_generate(a: &GenerateArgs) -> Result<()> {
    let Some(effect) = Effect::from_id(&a.effect) else {
        bail!("unknown effect {:?}", a.effect);
    };
    let foreign = match &a.foreign {
        None => None,
        Some(f) => Some(model_lab::generate::Foreign::from_id(f).with_context(|| {
            format!("unknown foreign effect {f:?} (cooling_loss, hidden_heater)")
        })?),
    };
    let second = match &a.second {
        None => None,
        Some(e) => Some(Effect::from_id(e).with_context(|| format!("unknown effect {e:?}"))?),
    };
    let dirty = match &a.dirty {
        None => None,
        Some(k) => Some(
            model_lab::generate::Dirty::ALL
                .into_iter()
                .find(|d| d.id() == k)
                .with_context(|| {
                    format!("unknown dirty channel {k:?} (milliamps, stuck, clock_jump)")
                })?,
        ),
    };
    let spec = Spec {
        effect,
        foreign,
        second,
        dirty,
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

/// `nori sim replay`: the box replayed, and the simulator's misfit per servo and register.
fn run_replay(a: &ReplayArgs) -> Result<()> {
    let mut robot = match &a.description {
        Some(p) => sim::RobotDescription::load(p)?,
        None => sim::RobotDescription::nori_a3(),
    };
    for s in &a.scenario {
        s.apply(&mut robot);
    }
    let extension = match &a.model_extension {
        Some(p) => Some(sim::extension::ModelExtension::load(p)?),
        None => None,
    };
    let setup = model_lab::replay::Setup {
        robot,
        thermal_speedup: a.thermal_speedup,
        constants: sim::constants::shipped(a.servo_constants)?,
        extension,
        dt: a.dt,
        windows: a.windows,
    };
    let bytes = std::fs::read(&a.path).with_context(|| format!("reading {}", a.path.display()))?;
    let replay = model_lab::replay::replay(&bytes, &setup)
        .with_context(|| format!("replaying {}", a.path.display()))?;
    if a.json {
        println!("{}", serde_json::to_string(&replay)?);
    } else {
        print!(
            "{}",
            model_lab::replay::summary(&replay, &a.path.display().to_string())
        );
    }
    Ok(())
}
