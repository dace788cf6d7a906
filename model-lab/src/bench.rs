//! The accuracy benchmark: hidden effects over many seeds, and the detection limit per effect.
//!
//! For each effect (and `none`), data sets are generated on seeds `0..seeds` with a size drawn
//! from [`crate::generate::size_range`]; the lab is scored on naming the effect and recovering
//! its parameter. The detection limit sweeps the size downward by halving from the range's lower
//! end: the smallest size at which the effect is still named in ≥ [`DETECTION_RATE`] of the runs
//! (and at every larger size of the sweep).

use crate::analysis::{analyze, Options, Parameter};
use crate::catalog::Effect;
use crate::generate::{generate, size_range, Dirty, Foreign, Spec};
use serde::Serialize;
use std::time::Instant;

/// Detection rate that defines the detection limit.
pub const DETECTION_RATE: f64 = 0.9;
/// A recovered parameter within this relative error of the truth counts as recovered.
pub const PARAMETER_TOLERANCE: f64 = 0.25;

/// Benchmark settings.
#[derive(Debug, Clone)]
pub struct Settings {
    /// Seeds per effect for the accuracy figures.
    pub seeds: u64,
    /// Seeds per size step of the detection-limit sweep (0: no sweep).
    pub sweep_seeds: u64,
    /// Most size steps of the sweep (factors of two from the range's lower end).
    pub sweep_steps: usize,
    /// Recording length, s.
    pub duration_s: f64,
    /// Sample period, s.
    pub period_s: f64,
    /// Worker threads.
    pub jobs: usize,
    /// Hidden effects to score (`none` included); empty: `none` and the whole catalog.
    pub effects: Vec<Effect>,
    /// Seeds per motion effect (generated runs through the motion channel; 0: none).
    pub motion_seeds: u64,
    /// Families of rows to score (`catalog`, `foreign`, `pairs`, `dirty`, `motion`); empty: all.
    pub rows: Vec<String>,
}

impl Settings {
    /// `spec` recorded at these settings' length and period.
    fn spec(&self, spec: Spec) -> Spec {
        Spec {
            duration_s: self.duration_s,
            period_s: self.period_s,
            ..spec
        }
    }
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            seeds: 50,
            sweep_seeds: 20,
            sweep_steps: 5,
            duration_s: 7200.0,
            period_s: 1.0,
            jobs: 1,
            effects: Vec::new(),
            motion_seeds: 50,
            rows: Vec::new(),
        }
    }
}

/// The pairs of hidden effects scored: two thermal ones of different kinds, and a thermal one
/// with the electrical one.
pub const PAIRS: [(Effect, Effect); 4] = [
    (Effect::SensorLag, Effect::AmbientDrift),
    (Effect::CopperTempco, Effect::CurrentOffset),
    (Effect::NeighborCoupling, Effect::AmbientDrift),
    (Effect::SensorLag, Effect::SupplySag),
];

/// One run.
#[derive(Debug, Clone, Serialize)]
pub struct Run {
    /// The seed its data set was generated from.
    pub seed: u64,
    /// Hidden size.
    pub size: f64,
    /// Named cause.
    pub named: Effect,
    /// A further cause named beside the hidden one when only one was hidden (a spurious
    /// second: the run counts as wrong, under this name).
    pub extra: Option<Effect>,
    /// Recovered parameter (when the named cause is the hidden one).
    pub recovered: Option<f64>,
    /// Motors in its data set.
    pub motors: usize,
    /// Analysis wall time, s.
    pub seconds: f64,
    /// With a second hidden effect: both named.
    pub both_named: bool,
    /// With a second hidden effect: both parameters within [`PARAMETER_TOLERANCE`].
    pub both_recovered: bool,
    /// With a dirty channel: the audit found it (a finding of its kind).
    pub flagged: bool,
    /// The thermal channel's form search found terms its residual follows (on null data, a
    /// false alarm).
    pub form: bool,
}

/// Accuracy on one effect.
#[derive(Debug, Clone, Serialize)]
pub struct EffectScore {
    /// What was hidden: a catalog id, `none`, a pair `a+b`, or an effect outside the catalog.
    pub hidden: String,
    /// The answer that is right: the hidden catalog effect, `none`, or `unexplained` for an
    /// effect outside the catalog.
    pub effect: Effect,
    /// Size range drawn from.
    pub size_range: (f64, f64),
    /// Unit of the sizes.
    pub unit: &'static str,
    /// Runs scored (one generated data set each).
    pub runs: usize,
    /// Fraction named correctly.
    pub accuracy: f64,
    /// Fraction with the parameter within [`PARAMETER_TOLERANCE`] (of all runs).
    pub recovered: f64,
    /// Median relative parameter error among correct runs.
    pub median_parameter_error: Option<f64>,
    /// What was named instead, when wrong.
    pub confusions: Vec<(Effect, usize)>,
    /// Mean analysis time, s.
    pub mean_seconds: f64,
    /// Detection-limit sweep: (size, detection rate).
    pub sweep: Vec<(f64, f64)>,
    /// Smallest size of the sweep reliably found (None: not even the largest).
    pub detection_limit: Option<f64>,
    /// Fraction of runs whose thermal residual has a form ([`crate::form`]).
    pub form_found: f64,
    /// Every run.
    #[serde(skip)]
    pub detail: Vec<Run>,
}

/// The benchmark's result.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// Seeds per effect.
    pub seeds: u64,
    /// Recording length, s; sample period, s; motors drawn from 2..=8.
    pub duration_s: f64,
    /// Sample period, s.
    pub period_s: f64,
    /// Per effect, `none` first (its accuracy is 1 − the false-alarm rate).
    pub effects: Vec<EffectScore>,
    /// Total wall time, s.
    pub seconds: f64,
}

/// Scores the motion channel on `effect` over `settings.motion_seeds` seeds.
fn motion_score(
    effect: Effect,
    settings: &Settings,
    progress: &mut dyn FnMut(&str),
) -> EffectScore {
    let next = std::sync::atomic::AtomicU64::new(0);
    let out = std::sync::Mutex::new(Vec::new());
    std::thread::scope(|scope| {
        for _ in 0..settings.jobs.max(1) {
            scope.spawn(|| loop {
                let seed = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                if seed >= settings.motion_seeds {
                    break;
                }
                let g = crate::generate::generate_motion(effect, seed);
                let t = Instant::now();
                let opts = Options {
                    servo: "sts3250".into(),
                    ..Options::default()
                };
                let m = g
                    .dataset()
                    .ok()
                    .and_then(|d| analyze(d, &opts, &mut |_| {}).ok())
                    .and_then(|o| o.analysis.motion);
                let named = m.as_ref().map_or(Effect::None, |m| m.cause);
                let i = g.carrier();
                let recovered = m.as_ref().and_then(|m| {
                    (named == effect)
                        .then(|| m.candidates.iter().find(|c| c.id == effect))
                        .flatten()
                        .and_then(|c| c.parameters.get(2 + i).map(|p| p.value))
                });
                let run = Run {
                    extra: None,
                    both_named: false,
                    both_recovered: false,
                    flagged: false,
                    form: false,
                    seed,
                    size: g.parameters.get(i).copied().unwrap_or(0.0),
                    named,
                    recovered,
                    motors: 1,
                    seconds: t.elapsed().as_secs_f64(),
                };
                if let Ok(mut o) = out.lock() {
                    o.push(run);
                }
            });
        }
    });
    let mut runs = out.into_inner().unwrap_or_default();
    runs.sort_by_key(|r| r.seed);
    let n = runs.len().max(1) as f64;
    let errors = parameter_errors(runs.iter().filter(|r| r.named == effect));
    let confusions = confusions(&runs, |r| r.named != effect);
    let score = EffectScore {
        hidden: if effect == Effect::None {
            "none (motion)".into()
        } else {
            effect.id().into()
        },
        effect,
        size_range: crate::generate::motion_size_range(effect),
        unit: effect.parameter().map_or("", |p| p.1),
        runs: runs.len(),
        accuracy: fraction(&runs, |r| r.named == effect),
        recovered: errors.iter().filter(|e| **e <= PARAMETER_TOLERANCE).count() as f64 / n,
        median_parameter_error: errors.get(errors.len() / 2).copied(),
        confusions,
        mean_seconds: mean_seconds(&runs),
        sweep: Vec::new(),
        detection_limit: None,
        form_found: fraction(&runs, |r| r.form),
        detail: runs,
    };
    progress(&format!(
        "{:18} accuracy {:5.1} %  parameter within {:.0} %: {:5.1} %",
        score.hidden,
        100.0 * score.accuracy,
        100.0 * PARAMETER_TOLERANCE,
        100.0 * score.recovered
    ));
    score
}

/// `spec` (with the settings' length and period) over the settings' seeds.
fn seeded(settings: &Settings, spec: Spec) -> Vec<Run> {
    let spec = settings.spec(spec);
    let jobs: Vec<(Spec, u64)> = (0..settings.seeds).map(|s| (spec.clone(), s)).collect();
    run_many(&jobs, settings.jobs)
}

impl Run {
    /// The run's answer: its cause, or the spurious second named beside it.
    fn answer(&self) -> Effect {
        self.extra.unwrap_or(self.named)
    }
}

/// What the runs `wrong` picks answered instead, with how often.
fn confusions(runs: &[Run], wrong: impl Fn(&Run) -> bool) -> Vec<(Effect, usize)> {
    let mut out: Vec<(Effect, usize)> = Vec::new();
    for r in runs.iter().filter(|r| wrong(r)) {
        match out.iter_mut().find(|(e, _)| *e == r.answer()) {
            Some(c) => c.1 += 1,
            None => out.push((r.answer(), 1)),
        }
    }
    out
}

impl EffectScore {
    /// Fraction of runs given a catalog name that is not the hidden effect's.
    pub fn wrong_name(&self) -> f64 {
        let wrong: usize = self
            .confusions
            .iter()
            .filter(|(e, _)| {
                Effect::CATALOG.contains(e) || crate::motion::MOTION_CATALOG.contains(e)
            })
            .map(|(_, n)| n)
            .sum();
        wrong as f64 / self.runs.max(1) as f64
    }
}

fn run_one(spec: &Spec, seed: u64) -> Run {
    let g = generate(spec, seed);
    let size = g.truth.parameter.as_ref().map_or(0.0, |p| p.value);
    let motors = g.truth.motors;
    let t = Instant::now();
    let out = g
        .dataset()
        .ok()
        .and_then(|d| analyze(d, &Options::default(), &mut |_| {}).ok());
    let seconds = t.elapsed().as_secs_f64();
    // Each hidden effect's parameter, found among those named.
    let hidden: Vec<Parameter> = g
        .truth
        .parameter
        .iter()
        .cloned()
        .chain(g.truth.second.iter().map(|(_, p)| p.clone()))
        .collect();
    match out {
        Some(o) => {
            let a = &o.analysis;
            let within = |t: &Parameter| {
                a.parameters.iter().any(|p| {
                    p.name == t.name
                        && (p.value - t.value).abs() <= PARAMETER_TOLERANCE * t.value.abs()
                })
            };
            let second = g.truth.second.as_ref().map(|(e, _)| *e);
            Run {
                seed,
                size,
                named: a.cause,
                extra: second
                    .is_none()
                    .then(|| a.causes.iter().find(|c| **c != a.cause).copied())
                    .flatten(),
                recovered: (a.cause == spec.effect)
                    .then(|| a.parameters.first().map(|p| p.value))
                    .flatten(),
                motors,
                seconds,
                both_named: second
                    .is_some_and(|s| a.causes.contains(&spec.effect) && a.causes.contains(&s)),
                both_recovered: second.is_some() && hidden.iter().all(within),
                flagged: spec
                    .dirty
                    .is_some_and(|k| a.diagnostics.audit.iter().any(|f| f.kind == k.id())),
                form: a
                    .diagnostics
                    .thermal_form
                    .as_ref()
                    .is_some_and(|f| f.found()),
            }
        }
        None => Run {
            seed,
            size,
            named: Effect::None,
            extra: None,
            recovered: None,
            motors,
            seconds,
            both_named: false,
            both_recovered: false,
            flagged: false,
            form: false,
        },
    }
}

/// Runs `specs × seeds` on `jobs` threads, in a stable order.
fn run_many(jobs: &[(Spec, u64)], threads: usize) -> Vec<Run> {
    let next = std::sync::atomic::AtomicUsize::new(0);
    let out = std::sync::Mutex::new(vec![None; jobs.len()]);
    std::thread::scope(|s| {
        for _ in 0..threads.max(1) {
            s.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let Some((spec, seed)) = jobs.get(i) else {
                    break;
                };
                let r = run_one(spec, *seed);
                if let Ok(mut o) = out.lock() {
                    o[i] = Some(r);
                }
            });
        }
    });
    out.into_inner()
        .unwrap_or_default()
        .into_iter()
        .flatten()
        .collect()
}

/// Runs the benchmark; `progress` gets one line per effect.
pub fn run(settings: &Settings, progress: &mut dyn FnMut(&str)) -> Report {
    let start = Instant::now();
    let mut effects = Vec::new();
    let wants =
        |family: &str| settings.rows.is_empty() || settings.rows.iter().any(|r| r == family);
    for effect in std::iter::once(Effect::None).chain(Effect::CATALOG) {
        if !wants("catalog") || !settings.effects.is_empty() && !settings.effects.contains(&effect)
        {
            continue;
        }
        effects.push(catalog_score(effect, settings, progress));
    }
    if wants("foreign")
        && (settings.effects.is_empty() || settings.effects.contains(&Effect::Unexplained))
    {
        for foreign in Foreign::ALL {
            effects.push(foreign_score(foreign, settings, progress));
        }
    }
    if wants("pairs") && settings.effects.is_empty() {
        for (first, second) in PAIRS {
            effects.push(pair_score(first, second, settings, progress));
        }
    }
    if wants("dirty") && settings.effects.is_empty() {
        for dirty in Dirty::ALL {
            effects.push(dirty_score(dirty, settings, progress));
        }
    }
    // The motion channel: generated runs hiding one mechanical effect (or none).
    let motion_wanted = |e: Effect| settings.effects.is_empty() || settings.effects.contains(&e);
    for effect in std::iter::once(Effect::None).chain(crate::motion::MOTION_CATALOG) {
        if settings.motion_seeds == 0 || !wants("motion") || !motion_wanted(effect) {
            continue;
        }
        let score = motion_score(effect, settings, progress);
        effects.push(score);
    }
    Report {
        seeds: settings.seeds,
        duration_s: settings.duration_s,
        period_s: settings.period_s,
        effects,
        seconds: start.elapsed().as_secs_f64(),
    }
}

/// Scores the lab on one hidden catalog effect (or `none`): named, its parameter recovered,
/// and its detection limit.
fn catalog_score(
    effect: Effect,
    settings: &Settings,
    progress: &mut dyn FnMut(&str),
) -> EffectScore {
    let runs = seeded(settings, Spec::new(effect));
    let n = runs.len().max(1) as f64;
    let correct: Vec<&Run> = runs.iter().filter(|r| r.answer() == effect).collect();
    let errors = parameter_errors(correct.iter().copied());
    let confusions = confusions(&runs, |r| r.answer() != effect);
    let sweep = detection_sweep(effect, settings);
    // The smallest size found reliably, with every larger size of the sweep also found.
    let detection_limit = sweep
        .iter()
        .take_while(|(_, r)| *r >= DETECTION_RATE)
        .last()
        .map(|(s, _)| *s);
    let score = EffectScore {
        hidden: effect.id().into(),
        effect,
        size_range: size_range(effect),
        unit: effect.parameter().map_or("", |p| p.1),
        runs: runs.len(),
        accuracy: correct.len() as f64 / n,
        recovered: errors.iter().filter(|e| **e <= PARAMETER_TOLERANCE).count() as f64 / n,
        median_parameter_error: errors.get(errors.len() / 2).copied(),
        confusions,
        mean_seconds: mean_seconds(&runs),
        sweep,
        detection_limit,
        form_found: fraction(&runs, |r| r.form),
        detail: runs,
    };
    progress(&format!(
        "{:18} accuracy {:5.1} %  parameter within {:.0} %: {:5.1} %  limit {:?}  form {:5.1} %",
        effect.id(),
        100.0 * score.accuracy,
        100.0 * PARAMETER_TOLERANCE,
        100.0 * score.recovered,
        score.detection_limit,
        100.0 * score.form_found
    ));
    score
}

/// The detection-limit sweep of `effect`, (size, detection rate) by decreasing size: from the
/// range's lower end, halve while the effect is still found reliably; when it is not found
/// there, double until it is. Empty for `none` or without sweep seeds.
fn detection_sweep(effect: Effect, settings: &Settings) -> Vec<(f64, f64)> {
    let mut sweep: Vec<(f64, f64)> = Vec::new();
    if effect == Effect::None || settings.sweep_seeds == 0 {
        return sweep;
    }
    let spec = settings.spec(Spec::new(effect));
    let rate_at = |size: f64| {
        let jobs: Vec<(Spec, u64)> = (0..settings.sweep_seeds)
            .map(|s| {
                (
                    Spec {
                        size: Some(size),
                        ..spec.clone()
                    },
                    1000 + s,
                )
            })
            .collect();
        let r = run_many(&jobs, settings.jobs);
        r.iter().filter(|r| r.answer() == effect).count() as f64 / r.len().max(1) as f64
    };
    let lo = size_range(effect).0;
    let first = rate_at(lo);
    sweep.push((lo, first));
    let factor = if first >= DETECTION_RATE { 0.5 } else { 2.0 };
    let mut size = lo;
    for _ in 1..settings.sweep_steps {
        size *= factor;
        let rate = rate_at(size);
        sweep.push((size, rate));
        if (rate >= DETECTION_RATE) != (first >= DETECTION_RATE) {
            break;
        }
    }
    sweep.sort_by(|a, b| b.0.total_cmp(&a.0));
    sweep
}

/// Scores an effect outside the catalog: the right answer is `unexplained`, never a catalog
/// name.
fn foreign_score(
    foreign: Foreign,
    settings: &Settings,
    progress: &mut dyn FnMut(&str),
) -> EffectScore {
    let runs = seeded(
        settings,
        Spec {
            foreign: Some(foreign),
            ..Spec::new(Effect::None)
        },
    );
    let confusions = confusions(&runs, |r| r.answer() != Effect::Unexplained);
    let score = EffectScore {
        hidden: foreign.id().into(),
        effect: Effect::Unexplained,
        size_range: (0.0, 0.0),
        unit: "",
        runs: runs.len(),
        accuracy: fraction(&runs, |r| r.answer() == Effect::Unexplained),
        recovered: 0.0,
        median_parameter_error: None,
        confusions,
        mean_seconds: mean_seconds(&runs),
        sweep: Vec::new(),
        detection_limit: None,
        form_found: fraction(&runs, |r| r.form),
        detail: runs,
    };
    progress(&format!(
        "{:18} unexplained {:5.1} %  a catalog name {:5.1} %  form {:5.1} %",
        foreign.id(),
        100.0 * score.accuracy,
        100.0 * score.wrong_name(),
        100.0 * score.form_found
    ));
    score
}

/// Scores two effects hidden at once: both must be named (the score's `effect` is the first).
fn pair_score(
    first: Effect,
    second: Effect,
    settings: &Settings,
    progress: &mut dyn FnMut(&str),
) -> EffectScore {
    let runs = seeded(
        settings,
        Spec {
            second: Some(second),
            ..Spec::new(first)
        },
    );
    let confusions = confusions(&runs, |r| !r.both_named);
    let score = EffectScore {
        hidden: format!("{}+{}", first.id(), second.id()),
        effect: first,
        size_range: size_range(first),
        unit: first.parameter().map_or("", |p| p.1),
        runs: runs.len(),
        accuracy: fraction(&runs, |r| r.both_named),
        recovered: fraction(&runs, |r| r.both_recovered),
        median_parameter_error: None,
        confusions,
        mean_seconds: mean_seconds(&runs),
        sweep: Vec::new(),
        detection_limit: None,
        form_found: fraction(&runs, |r| r.form),
        detail: runs,
    };
    progress(&format!(
        "{:18} both named {:5.1} %  both parameters within {:.0} %: {:5.1} %",
        score.hidden,
        100.0 * score.accuracy,
        100.0 * PARAMETER_TOLERANCE,
        100.0 * score.recovered
    ));
    score
}

/// Scores data that lie: the audit must find each kind (the score's accuracy), and the
/// analysis still answer `none` on the null data behind it (its `recovered`).
fn dirty_score(dirty: Dirty, settings: &Settings, progress: &mut dyn FnMut(&str)) -> EffectScore {
    let runs = seeded(
        settings,
        Spec {
            dirty: Some(dirty),
            ..Spec::new(Effect::None)
        },
    );
    let score = EffectScore {
        hidden: format!("dirty: {}", dirty.id()),
        effect: Effect::None,
        size_range: (0.0, 0.0),
        unit: "",
        runs: runs.len(),
        accuracy: fraction(&runs, |r| r.flagged),
        recovered: fraction(&runs, |r| r.answer() == Effect::None),
        median_parameter_error: None,
        confusions: Vec::new(),
        mean_seconds: mean_seconds(&runs),
        sweep: Vec::new(),
        detection_limit: None,
        form_found: fraction(&runs, |r| r.form),
        detail: runs,
    };
    progress(&format!(
        "{:18} flagged {:5.1} %  still none {:5.1} %",
        score.hidden,
        100.0 * score.accuracy,
        100.0 * score.recovered
    ));
    score
}

/// The fraction of `runs` that `pick` picks (0 of no runs).
fn fraction(runs: &[Run], pick: impl Fn(&Run) -> bool) -> f64 {
    runs.iter().filter(|r| pick(r)).count() as f64 / runs.len().max(1) as f64
}

/// The runs' mean analysis time, s.
fn mean_seconds(runs: &[Run]) -> f64 {
    runs.iter().map(|r| r.seconds).sum::<f64>() / runs.len().max(1) as f64
}

/// The relative errors of the parameters recovered by `runs`, ascending.
fn parameter_errors<'a>(runs: impl Iterator<Item = &'a Run>) -> Vec<f64> {
    let mut errors: Vec<f64> = runs
        .filter_map(|r| r.recovered.map(|v| ((v - r.size) / r.size).abs()))
        .collect();
    errors.sort_by(f64::total_cmp);
    errors
}
