//! The analysis: split, calibrate the nominal model, measure its held-out misfit, try every
//! extension of the catalog and name the cause the data support.
//!
//! [`analyze`] goes forward through its rooms: the data audit and glitch rejection
//! ([`crate::audit`], [`crate::data`]), the motion channel ([`crate::motion`]), the thermal
//! channel ([`thermal_channel`], and when it stays unexplained the form of its misfit,
//! [`thermal_form`]), the electrical channel ([`electrical_channel`]), each
//! extension judged by the tests of [`significance`] and each channel's misfit against its
//! noise [`floor`]; then the cause across channels ([`Decision`]), the figures and the model
//! file. The rules an extension must pass, and why, are in `docs/model-lab.md` ("Name the
//! cause", "Findings are judged", "Two effects at once").

mod electrical_channel;
mod floor;
mod significance;
mod thermal_channel;
mod thermal_form;

use crate::audit::{self, Finding};
use crate::catalog::{Channel, Effect};
use crate::data::{self, Cleaning, Dataset};
use crate::electrical::{self, CurrentEstimator, ElectricalData, ElectricalFit};
use crate::motion::{self, MotionAnalysis, MotionRun};
use crate::register::Register;
use crate::stats;
use crate::thermal::{
    fit_extension, fit_nominal, fit_pair, refit_nominal, ThermalData, ThermalFit, ThermalModel,
};
use crate::verdict::Verdict;
use electrical_channel::{electrical_channel, ElectricalOutcome};
use floor::verdict;
pub use floor::{
    AgainstFloor, ChannelVerdict, FloorBasis, NoiseFloor, MISFIT_BIAS_FLOORS, MISFIT_RMSE_FLOORS,
};
use serde::Serialize;
pub(crate) use significance::HELDOUT_SIZE;
use significance::{
    block_wald_test, deviance_test, judge, stronger_second, strongest_significant, Evidence,
    FitTest, Regimes, Yardstick,
};
pub use significance::{
    ALPHA, MAX_INFORMATIVE_SE, MIN_HELDOUT_T, PRACTICAL_GAIN, PRACTICAL_OF_FLOOR,
};
use std::collections::BTreeMap;
use thermal_channel::{thermal_channel, thermal_data, NamedPair, ThermalOutcome};
use thiserror::Error;

/// Lags of the Ljung–Box whiteness test.
pub const LJUNG_BOX_LAGS: usize = 20;

/// Why an analysis cannot run.
#[derive(Debug, Error)]
pub enum AnalysisError {
    /// Neither channel has what it needs.
    #[error(
        "nothing to analyse: the thermal channel needs temperature_c and current_a, the \
         electrical channel voltage_v and a current (measured, or goal/position to estimate \
         it){}", if .0.is_empty() { String::new() } else { format!("; refused: {}", .0) }
    )]
    NoChannel(String),
    /// The servo model is not in the robot description.
    #[error("unknown servo model {0:?} (sts3215, sts3250, sts3095)")]
    UnknownServo(String),
    /// The split leaves a part empty.
    #[error("split fraction {0} leaves no fitting or no held-out data")]
    BadSplit(f64),
}

/// Options of an analysis.
#[derive(Debug, Clone)]
pub struct Options {
    /// Fraction of the samples (in time order) used for fitting; the rest is held out.
    pub fit_fraction: f64,
    /// How to estimate currents when the data carry none.
    pub estimator: Option<CurrentEstimator>,
    /// Extensions to try (the whole catalog by default).
    pub candidates: Vec<Effect>,
    /// The physical ranges the data are checked against before anything is fitted.
    pub limits: audit::Limits,
    /// The servo model (`sim`'s description) the motion channel replays runs through.
    pub servo: String,
    /// Search the thermal misfit's form ([`crate::form`]; up to [`crate::form::MAX_MOTORS`]).
    pub search_form: bool,
}

impl Options {
    /// The options `nori model analyze --servo SERVO --kp KP` runs with: the servo's rating
    /// estimates the currents the data do not carry and bounds what the data may read.
    pub fn for_servo(servo: &str, kp: f64) -> Result<Options, AnalysisError> {
        let robot = sim::RobotDescription::nori_a3();
        let rating = robot
            .rating(servo)
            .ok_or_else(|| AnalysisError::UnknownServo(servo.into()))?;
        Ok(Options {
            estimator: Some(CurrentEstimator {
                kp,
                resistance_ohm: rating.rated_voltage / rating.stall_current_a,
                ke_v_s_per_rad: rating.rated_voltage / rating.no_load_speed_rad_s,
            }),
            limits: audit::Limits {
                stall_current_a: rating.stall_current_a,
                // Feetech's 12 V servos take up to 14.8 V (a charged 4S pack); margin for a
                // charger's ripple. A lower-rated servo may run on the 12 V bus (the STS3095).
                max_supply_v: (1.4 * rating.rated_voltage).max(16.8),
                max_speed_rad_s: 3.0 * rating.no_load_speed_rad_s,
                ..audit::Limits::default()
            },
            servo: servo.into(),
            ..Options::default()
        })
    }
}

impl Default for Options {
    fn default() -> Self {
        Options {
            fit_fraction: 0.7,
            estimator: None,
            candidates: Effect::CATALOG
                .into_iter()
                .chain(motion::MOTION_CATALOG)
                .collect(),
            limits: audit::Limits::default(),
            servo: "sts3215".into(),
            search_form: true,
        }
    }
}

/// A named parameter with its unit.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Parameter {
    /// Its name as the catalog gives it, e.g. `sensor_time_constant`, `coulomb_friction`.
    pub name: String,
    /// Its value, in `unit`.
    pub value: f64,
    /// The unit of `value`, e.g. `s`, `ohm`, `N·m` (`1`: dimensionless).
    pub unit: String,
}

/// Per-motor figures.
#[derive(Debug, Clone, Default, Serialize)]
pub struct MotorFigures {
    /// Motor id.
    pub motor: i64,
    /// Nominal model: time constant, s.
    pub tau_s: Option<f64>,
    /// Nominal model: copper-loss gain R·R_th, K/A².
    pub gain_k_per_a2: Option<f64>,
    /// Nominal model: idle equilibrium T_amb + P0·R_th, °C.
    pub idle_c: Option<f64>,
    /// Temperature readings used for fitting / held out.
    pub readings: (usize, usize),
    /// Held-out temperature RMSE of the nominal model, °C.
    pub baseline_rmse_c: Option<f64>,
    /// Held-out temperature RMSE of the chosen model, °C.
    pub extended_rmse_c: Option<f64>,
    /// Held-out mean error (prediction − reading) of the nominal model, °C.
    pub baseline_bias_c: Option<f64>,
    /// Held-out voltage RMSE of the nominal (constant) supply, V.
    pub baseline_rmse_v: Option<f64>,
    /// Held-out voltage RMSE with the chosen model, V.
    pub extended_rmse_v: Option<f64>,
}

/// The nominal model's misfit on one channel.
#[derive(Debug, Clone, Serialize)]
pub struct Misfit {
    /// Held-out RMSE.
    pub rmse: f64,
    /// Held-out mean error (prediction − reading).
    pub bias: f64,
    /// Unit of both.
    pub unit: &'static str,
    /// Lag-1 autocorrelation of the held-out residuals (pooled over motors).
    pub lag1_autocorrelation: f64,
    /// Ljung–Box statistic over [`LJUNG_BOX_LAGS`] lags, summed over motors.
    pub ljung_box_q: f64,
    /// Its p-value (small: the residuals are not white, the model misses structure).
    pub ljung_box_p: f64,
    /// Correlation of the held-out residuals with candidate regressors.
    pub correlations: BTreeMap<String, f64>,
    /// What a right model would still miss on this channel.
    pub noise_floor: NoiseFloor,
}

/// What the lab can see of a misfit it cannot name.
#[derive(Debug, Clone, Serialize)]
pub struct Unexplained {
    /// The channel whose misfit is left.
    pub channel: Channel,
    /// Supported extensions that reduce it without bringing it to the noise floor, with their
    /// held-out gain.
    pub partial: Vec<(Effect, f64)>,
    /// The regressors the nominal model's held-out residual correlates with most (|r| first).
    pub strongest_regressors: Vec<(String, f64)>,
    /// Per motor, worst first: id, held-out RMSE, bias.
    pub motors: Vec<(i64, f64, f64)>,
    /// The held-out part in ten spans of time: start, end (s), RMSE, bias (all motors).
    pub time_course: Vec<(f64, f64, f64, f64)>,
    /// What the misfit looks like, when the channel's form search found terms it follows.
    pub form: Option<crate::form::Form>,
}

/// One extension as tried.
#[derive(Debug, Clone, Serialize)]
pub struct Candidate {
    /// Catalog id.
    pub id: Effect,
    /// Tried on top of this extension (a pair, fitted together; the tests then weigh what
    /// `id` adds to it).
    pub with: Option<Effect>,
    /// The channel the extension predicts (thermal, electrical or motion).
    pub channel: Channel,
    /// Fitted parameter.
    pub parameter: Option<Parameter>,
    /// SSE of the nominal model on the fitting part.
    pub baseline_fit_sse: f64,
    /// SSE of the extension on the fitting part.
    pub fit_sse: f64,
    /// Effective sample size of the test.
    pub n_eff: f64,
    /// Likelihood-ratio statistic.
    pub lr: f64,
    /// p-value of the fitting part's test of the extension (thermal: the register model's
    /// likelihood ratio; electrical: the block Wald test), tested against the per-test α;
    /// with `with_heldout`, combined with the held-out slope's.
    pub p_value: f64,
    /// A pair's second judged on the fitting part and the held-out slope together (the
    /// fitting part's test alone fell short; ΔBIC then does not apply).
    pub with_heldout: bool,
    /// BIC improvement over the nominal model (positive: better).
    pub delta_bic: f64,
    /// Held-out RMSE of the nominal model.
    pub baseline_heldout_rmse: f64,
    /// Held-out RMSE of the extension.
    pub heldout_rmse: f64,
    /// Relative reduction of the held-out RMSE.
    pub gain: f64,
    /// t statistic of the held-out reduction of squared error (block means); reported, not
    /// tested (see the module docs).
    pub heldout_t: f64,
    /// Slope of the nominal model's held-out residuals on the extension's predicted correction
    /// (1: the readings follow the correction fully, 0: not at all).
    pub heldout_slope: f64,
    /// t statistic of that slope (block standard error), tested against [`MIN_HELDOUT_T`].
    pub heldout_slope_t: f64,
    /// RMS of the extension's correction of the held-out predictions (nominal − extended).
    pub heldout_change: f64,
    /// The correction that matters: [`PRACTICAL_OF_FLOOR`] noise floors.
    pub required_change: f64,
    /// The held-out gain that matters: [`PRACTICAL_GAIN`] where the nominal misfit is beyond
    /// the noise, else none (0).
    pub required_gain: f64,
    /// The range the parameter's physics allows ([`Effect::bounds`]).
    pub bounds: Option<(f64, f64)>,
    /// The parameter lies within it.
    pub plausible: bool,
    /// Supported, or the first test it failed.
    #[serde(flatten)]
    pub verdict: Verdict,
    /// Fit iterations.
    pub iterations: usize,
}

/// Everything else worth knowing about the run.
#[derive(Debug, Clone, Serialize)]
pub struct Diagnostics {
    /// Samples on the time grid.
    pub samples: usize,
    /// Motors in the data.
    pub motors: usize,
    /// Covered time, s (segments only, gaps excluded).
    pub duration_s: f64,
    /// Time of the first held-out sample, s.
    pub split_t_s: f64,
    /// Segments (restarts of the state at logging gaps and run boundaries).
    pub segments: usize,
    /// Channels analysed.
    pub channels: Vec<Channel>,
    /// Where currents came from for the electrical channel.
    pub current_source: Option<&'static str>,
    /// What the data audit found and did, before anything was fitted.
    pub audit: Vec<Finding>,
    /// Glitch rejection.
    pub cleaning: Cleaning,
    /// Register resolution, °C.
    pub temperature_quantum_c: f64,
    /// Noise of the temperature readings before rounding, as estimated with the nominal model
    /// (its own misfit counts as noise), °C.
    pub register_noise_c: Option<f64>,
    /// Nominal misfit, thermal channel.
    pub thermal: Option<Misfit>,
    /// Nominal misfit, electrical channel.
    pub electrical: Option<Misfit>,
    /// Every extension tried.
    pub candidates: Vec<Candidate>,
    /// The form search on the thermal channel's nominal misfit, whatever the verdict (a form
    /// found where the verdict is `none` is what the false-alarm rate counts).
    pub thermal_form: Option<crate::form::Form>,
    /// Per channel, the misfit left and whether it is beyond the noise floor.
    pub verdicts: Vec<ChannelVerdict>,
    /// Significance level per test (family-wise [`ALPHA`] over the catalog).
    pub alpha_per_test: f64,
    /// Required t statistic of the held-out improvement.
    pub min_heldout_t: f64,
    /// How the input was adapted.
    pub notes: Vec<String>,
}

/// The analysis, as `--json` prints it.
#[derive(Debug, Clone, Serialize)]
pub struct Analysis {
    /// The named cause (a catalog id, or `none`).
    pub cause: Effect,
    /// What the cause means.
    pub description: &'static str,
    /// The extension's fitted parameters, named, with units.
    pub parameters: Vec<Parameter>,
    /// Channel the cause acts on.
    pub channel: Channel,
    /// Held-out temperature RMSE of the nominal model, °C (thermal channel).
    pub baseline_rmse_c: Option<f64>,
    /// Held-out temperature RMSE of the chosen model, °C.
    pub extended_rmse_c: Option<f64>,
    /// Held-out RMSE of the nominal model on the cause's channel.
    pub baseline_rmse: f64,
    /// Held-out RMSE of the chosen model on the cause's channel.
    pub extended_rmse: f64,
    /// Unit of the two figures above.
    pub unit: &'static str,
    /// Relative reduction of the held-out error, 1 − extended/baseline.
    pub gain: f64,
    /// Per-motor figures.
    pub motors: Vec<MotorFigures>,
    /// When the cause is `unexplained`: what the lab can see of the misfit.
    pub unexplained: Option<Unexplained>,
    /// Every cause named, one per channel that names one (thermal or electrical first, then
    /// motion): the effects found together.
    pub causes: Vec<Effect>,
    /// The motion channel, when the data carry runs it can replay.
    pub motion: Option<MotionAnalysis>,
    /// The rest worth knowing: the data's size and segments, the audit, the glitch rejection.
    pub diagnostics: Diagnostics,
}

/// Time series for the report's plots.
#[derive(Debug, Clone, Default)]
pub struct Traces {
    /// Sample times, s.
    pub t: Vec<f64>,
    /// First held-out sample.
    pub split: usize,
    /// Per motor: id, readings, nominal prediction, chosen-model prediction.
    pub series: Vec<Trace>,
    /// Unit of the series.
    pub unit: &'static str,
}

/// One motor's series.
#[derive(Debug, Clone)]
pub struct Trace {
    /// Motor id.
    pub motor: i64,
    /// Readings (NaN where missing or rejected).
    pub measured: Vec<f64>,
    /// Nominal model, open loop.
    pub nominal: Vec<f64>,
    /// Chosen model, open loop.
    pub extended: Vec<f64>,
}

/// What [`analyze`] returns.
#[derive(Debug, Clone)]
pub struct Outcome {
    /// The figures.
    pub analysis: Analysis,
    /// The series behind the plots.
    pub traces: Traces,
    /// The extended model, for the simulator.
    pub model: sim::extension::ModelExtension,
}

/// The chosen model's fits.
struct Chosen {
    effect: Effect,
    thermal: Option<(ThermalFit, Vec<Vec<f64>>)>,
    electrical: Option<ElectricalFit>,
}

/// Residuals (prediction − reading) at the given indices.
fn residuals_at(pred: &[f64], meas: &[f64], idx: &[usize]) -> Vec<f64> {
    idx.iter().map(|&k| pred[k] - meas[k]).collect()
}

/// Effective sample size of per-motor residual series, summed.
fn n_eff_of(res: &[Vec<f64>]) -> f64 {
    res.iter()
        .filter(|r| !r.is_empty())
        .map(|r| {
            let rho = stats::autocorrelation(r, 1).get(1).copied().unwrap_or(0.0);
            stats::effective_n(r.len(), rho)
        })
        .sum()
}

fn misfit(
    res: &[Vec<f64>],
    regressors: BTreeMap<String, Vec<f64>>,
    unit: &'static str,
    noise_floor: NoiseFloor,
) -> Misfit {
    let all: Vec<f64> = res.concat();
    let (mut q, mut df) = (0.0, 0.0);
    let mut lag1 = 0.0;
    let mut w = 0.0;
    for r in res {
        let (qm, _) = stats::ljung_box(r, LJUNG_BOX_LAGS);
        if qm.is_finite() {
            q += qm;
            df += LJUNG_BOX_LAGS as f64;
        }
        if r.len() > 2 {
            lag1 += stats::autocorrelation(r, 1)[1] * r.len() as f64;
            w += r.len() as f64;
        }
    }
    Misfit {
        rmse: stats::rmse(&all),
        bias: stats::mean(&all),
        unit,
        lag1_autocorrelation: if w > 0.0 { lag1 / w } else { f64::NAN },
        ljung_box_q: q,
        ljung_box_p: if df > 0.0 {
            stats::chi2_sf(q, df)
        } else {
            f64::NAN
        },
        correlations: regressors
            .into_iter()
            .map(|(k, v)| (k, stats::correlation(&all, &v)))
            .collect(),
        noise_floor,
    }
}

/// The fitting part's end: `fit_fraction` of `n` samples.
fn split_at(n: usize, fit_fraction: f64) -> Result<usize, AnalysisError> {
    if !(fit_fraction > 0.0 && fit_fraction < 1.0) {
        return Err(AnalysisError::BadSplit(fit_fraction));
    }
    let split = ((n as f64) * fit_fraction).round() as usize;
    if split < 2 || split >= n {
        return Err(AnalysisError::BadSplit(fit_fraction));
    }
    Ok(split)
}

/// Runs the analysis. `progress` receives one line per step (fits take seconds on hours of data).
pub fn analyze(
    mut d: Dataset,
    opts: &Options,
    progress: &mut dyn FnMut(&str),
) -> Result<Outcome, AnalysisError> {
    let split = split_at(d.t.len(), opts.fit_fraction)?;
    let audit = audit::check(&mut d, &opts.limits);
    let cleaning = data::reject_glitches(&mut d);
    let td = thermal_data(&d, split);
    let ed = ElectricalData::new(&d, split, opts.estimator);
    let robot = sim::RobotDescription::nori_a3();
    let rating = robot
        .rating(&opts.servo)
        .ok_or_else(|| AnalysisError::UnknownServo(opts.servo.clone()))?;
    let motion_runs = MotionRun::from_dataset(&d, rating.rated_voltage);
    let motion = motion::analyze_motion(
        rating,
        &opts.servo,
        &motion_runs,
        &opts.candidates,
        progress,
    );
    if td.is_none() && ed.is_none() && motion.is_none() {
        return Err(AnalysisError::NoChannel(audit::refused(&audit)));
    }
    // The record's span, h (what an ambient drift's size is judged against).
    let hours = match (d.t.first(), d.t.last()) {
        (Some(a), Some(b)) => (b - a) / 3600.0,
        _ => 0.0,
    };
    let thermal = td
        .as_ref()
        .map(|td| thermal_channel(td, &d, opts, hours, progress));
    let electrical = ed
        .as_ref()
        .map(|ed| electrical_channel(ed, &d, opts, hours, progress));
    let channels: Vec<&ChannelOutcome> = thermal
        .iter()
        .map(|t| &t.channel)
        .chain(electrical.iter().map(|e| &e.channel))
        .collect();
    let form = thermal.as_ref().and_then(|t| t.form.as_ref());
    let decision = Decision::of(&channels, motion.as_ref(), form, &d.t, split);
    let chosen = Chosen {
        effect: decision.cause,
        thermal: thermal
            .as_ref()
            .filter(|_| decision.named_on(&channels, Channel::Thermal).is_some())
            .and_then(|t| t.best.clone()),
        electrical: electrical
            .as_ref()
            .filter(|_| decision.named_on(&channels, Channel::Electrical).is_some())
            .and_then(|e| e.sag.clone()),
    };
    let figures = Figures::of(&d, split, &td, &thermal, &ed, &electrical, &chosen);
    let (named, parameters) = named_effects(
        &decision,
        &channels,
        thermal.as_ref().and_then(|t| t.pair),
        motion.as_ref(),
    );
    let mut model = model_file(
        &d,
        &td,
        thermal.as_ref().map(|t| &t.nominal),
        &chosen,
        &decision.chosen,
    );
    // Every effect named, with its parameter as named (a pair's refitted together).
    for (e, p) in named.iter().zip(&parameters) {
        set_key(&mut model, *e, p.value);
        if *e != decision.cause {
            model.cause = format!("{}+{}", model.cause, e.id());
        }
    }
    if let Some(m) = &motion {
        m.write_extension(&mut model);
    }
    let channel = decision.channel(td.is_some(), ed.is_some());
    let (baseline, extended, unit) = match channel {
        Channel::Thermal => (figures.thermal_rmse.0, figures.thermal_rmse.1, "°C"),
        Channel::Electrical => (figures.voltage_rmse.0, figures.voltage_rmse.1, "V"),
        Channel::Motion => (
            motion.as_ref().map(|m| m.nominal_mae_rad),
            motion.as_ref().map(|m| m.chosen_mae_rad),
            "rad",
        ),
    };
    let (baseline, extended) = (baseline.unwrap_or(f64::NAN), extended.unwrap_or(f64::NAN));
    let diagnostics = Diagnostics::of(
        &d,
        split,
        &channels,
        thermal.as_ref(),
        ed.as_ref().map(|e| e.current_source),
        audit,
        cleaning,
    );
    let analysis = Analysis {
        cause: decision.cause,
        description: decision.cause.describe(),
        parameters,
        channel,
        baseline_rmse_c: figures.thermal_rmse.0,
        extended_rmse_c: figures.thermal_rmse.1,
        baseline_rmse: baseline,
        extended_rmse: extended,
        unit,
        gain: if baseline > 0.0 {
            1.0 - extended / baseline
        } else {
            0.0
        },
        motors: figures.motors,
        unexplained: decision.unexplained,
        causes: named,
        motion,
        diagnostics,
    };
    Ok(Outcome {
        analysis,
        traces: figures.traces,
        model,
    })
}

impl Diagnostics {
    /// The run's diagnostics: the data's shape, what the audit and the cleaning did, each
    /// channel's nominal misfit, every candidate tried and each channel's verdict.
    fn of(
        d: &Dataset,
        split: usize,
        channels: &[&ChannelOutcome],
        thermal: Option<&ThermalOutcome>,
        current_source: Option<&'static str>,
        audit: Vec<Finding>,
        cleaning: Cleaning,
    ) -> Diagnostics {
        let segs = d.segments();
        let misfit_of = |channel: Channel| {
            channels
                .iter()
                .find(|c| c.verdict.channel == channel)
                .map(|c| c.misfit.clone())
        };
        Diagnostics {
            samples: d.t.len(),
            motors: d.motors.len(),
            duration_s: segs.iter().map(|&(s, e)| d.t[e - 1] - d.t[s]).sum(),
            split_t_s: d.t[split],
            segments: segs.len(),
            channels: channels.iter().map(|c| c.verdict.channel).collect(),
            current_source,
            audit,
            cleaning,
            temperature_quantum_c: d.temperature_quantum,
            register_noise_c: thermal.map(|t| t.register_noise),
            thermal: misfit_of(Channel::Thermal),
            electrical: misfit_of(Channel::Electrical),
            candidates: channels.iter().flat_map(|c| c.candidates.clone()).collect(),
            thermal_form: thermal.and_then(|t| t.form.clone()),
            verdicts: channels.iter().map(|c| c.verdict.clone()).collect(),
            alpha_per_test: ALPHA / Effect::CATALOG.len() as f64,
            min_heldout_t: MIN_HELDOUT_T,
            notes: d.notes.clone(),
        }
    }
}

/// The cause across channels.
struct Decision {
    /// The named cause.
    cause: Effect,
    /// The supported single with the largest ΔBIC, when nothing is left unexplained.
    chosen: Option<Candidate>,
    /// A channel whose misfit stays beyond its noise floor.
    left_over: Option<Channel>,
    /// What can be seen of that misfit.
    unexplained: Option<Unexplained>,
}

impl Decision {
    /// The supported extension with the largest ΔBIC, unless a channel's misfit stays beyond
    /// its noise floor; then `unexplained`. With neither thermal nor electrical data, the
    /// motion channel's answer.
    fn of(
        channels: &[&ChannelOutcome],
        motion: Option<&MotionAnalysis>,
        thermal_form: Option<&crate::form::Form>,
        t: &[f64],
        split: usize,
    ) -> Decision {
        let left_over = channels.iter().find(|c| c.verdict.significant);
        let chosen = channels
            .iter()
            .flat_map(|c| &c.candidates)
            .filter(|c| c.verdict.supported() && c.with.is_none() && left_over.is_none())
            .max_by(|a, b| a.delta_bic.total_cmp(&b.delta_bic))
            .cloned();
        let cause = match (left_over, &chosen) {
            (Some(_), _) => Effect::Unexplained,
            (None, Some(c)) => c.id,
            (None, None) if channels.is_empty() => motion.map_or(Effect::None, |m| m.cause),
            (None, None) => Effect::None,
        };
        let unexplained = left_over.map(|c| {
            let channel = c.verdict.channel;
            let mut u = structure(channel, &c.candidates, Some(&c.misfit), &c.held, t, split);
            u.form = thermal_form
                .filter(|f| f.found() && channel == Channel::Thermal)
                .cloned();
            u
        });
        Decision {
            cause,
            chosen,
            left_over: left_over.map(|c| c.verdict.channel),
            unexplained,
        }
    }

    /// `channel`'s named extension (whatever the cause across channels), when nothing is left
    /// unexplained.
    fn named_on(&self, channels: &[&ChannelOutcome], channel: Channel) -> Option<Effect> {
        channels
            .iter()
            .find(|c| c.verdict.channel == channel)
            .and_then(|c| c.verdict.extension)
            .filter(|_| self.left_over.is_none())
    }

    /// The channel the headline figures are of.
    fn channel(&self, thermal: bool, electrical: bool) -> Channel {
        match (self.left_over, self.cause) {
            (Some(c), _) => c,
            // Motion alone: its channel, whatever its answer.
            _ if !thermal && !electrical => Channel::Motion,
            (None, Effect::None) if thermal => Channel::Thermal,
            (None, Effect::None) => Channel::Electrical,
            (None, c) => c.channel(),
        }
    }
}

/// Every effect named: each channel's best (and the thermal pair's second beside its first),
/// unless some channel's misfit is left unexplained; then `unexplained`; and the motion
/// channel's. With their parameters, the cause's first; a pair's each with the value it took
/// beside the other.
fn named_effects(
    decision: &Decision,
    channels: &[&ChannelOutcome],
    pair: Option<NamedPair>,
    motion: Option<&MotionAnalysis>,
) -> (Vec<Effect>, Vec<Parameter>) {
    let pair = pair.filter(|_| decision.left_over.is_none());
    let mut named: Vec<Effect> = if decision.left_over.is_some() {
        vec![Effect::Unexplained]
    } else {
        channels
            .iter()
            .filter_map(|c| c.verdict.extension)
            .collect()
    };
    if let Some(p) = pair {
        if let Some(i) = named.iter().position(|e| *e == p.first) {
            named.insert(i + 1, p.second);
        }
    }
    named.sort_by_key(|e| *e != decision.cause);
    let parameters: Vec<Parameter> = named
        .iter()
        .filter_map(|&e| {
            let value = match pair {
                Some(p) if p.first == e => Some(p.values.0),
                Some(p) if p.second == e => Some(p.values.1),
                _ => channels
                    .iter()
                    .flat_map(|c| &c.candidates)
                    .find(|c| c.id == e && c.with.is_none())
                    .and_then(|c| c.parameter.as_ref())
                    .map(|p| p.value),
            }?;
            e.parameter().map(|(name, unit)| Parameter {
                name: name.into(),
                value,
                unit: unit.into(),
            })
        })
        .collect();
    if let Some(m) = motion.filter(|m| m.cause != Effect::None) {
        if !named.contains(&m.cause) {
            named.push(m.cause);
        }
    }
    (named, parameters)
}

/// The per-motor figures, the headline RMSEs and the plots' series.
struct Figures {
    motors: Vec<MotorFigures>,
    /// Held-out temperature RMSE, nominal and chosen model, °C.
    thermal_rmse: (Option<f64>, Option<f64>),
    /// Held-out voltage RMSE, nominal and chosen model, V.
    voltage_rmse: (Option<f64>, Option<f64>),
    traces: Traces,
}

impl Figures {
    fn of(
        d: &Dataset,
        split: usize,
        td: &Option<ThermalData>,
        thermal: &Option<ThermalOutcome>,
        ed: &Option<ElectricalData>,
        electrical: &Option<ElectricalOutcome>,
        chosen: &Chosen,
    ) -> Figures {
        let mut f = Figures {
            motors: d
                .motors
                .iter()
                .map(|&id| MotorFigures {
                    motor: id,
                    ..MotorFigures::default()
                })
                .collect(),
            thermal_rmse: (None, None),
            voltage_rmse: (None, None),
            traces: Traces {
                t: d.t.clone(),
                split,
                ..Default::default()
            },
        };
        if let (Some(td), Some(t)) = (td, thermal) {
            let plotted = chosen.effect.channel() == Channel::Thermal || ed.is_none();
            f.thermal(d, td, &t.nominal, chosen, plotted);
        }
        if let (Some(ed), Some(e)) = (ed, electrical) {
            f.electrical(d, ed, &e.nominal, chosen);
        }
        f
    }

    /// The thermal channel's figures; its series plotted when `plotted`.
    fn thermal(
        &mut self,
        d: &Dataset,
        td: &ThermalData,
        (nom, nom_pred): &(ThermalFit, Vec<Vec<f64>>),
        chosen: &Chosen,
        plotted: bool,
    ) {
        let params = ThermalModel::new(td, Effect::None).decode(&nom.p);
        let ext_pred = chosen.thermal.as_ref().map_or(nom_pred, |(_, p)| p);
        let (mut all_b, mut all_e) = (Vec::new(), Vec::new());
        for (m, &dm) in td.motors.iter().enumerate() {
            let rb = residuals_at(&nom_pred[m], &td.measured[m], &td.held_idx[m]);
            let re = residuals_at(&ext_pred[m], &td.measured[m], &td.held_idx[m]);
            let f = &mut self.motors[dm];
            f.tau_s = Some(params.tau_s[m]);
            f.gain_k_per_a2 = Some(params.gain_k_per_a2[m]);
            f.idle_c = Some(params.idle_c[m]);
            f.readings = (td.fit_idx[m].len(), td.held_idx[m].len());
            f.baseline_rmse_c = Some(stats::rmse(&rb));
            f.extended_rmse_c = Some(stats::rmse(&re));
            f.baseline_bias_c = Some(stats::mean(&rb));
            all_b.extend(rb);
            all_e.extend(re);
        }
        self.thermal_rmse = (Some(stats::rmse(&all_b)), Some(stats::rmse(&all_e)));
        if plotted {
            self.traces.unit = "°C";
            self.traces.series = td
                .motors
                .iter()
                .enumerate()
                .map(|(m, &dm)| Trace {
                    motor: d.motors[dm],
                    measured: td.measured[m].clone(),
                    nominal: nom_pred[m].clone(),
                    extended: ext_pred[m].clone(),
                })
                .collect();
        }
    }

    /// The electrical channel's figures; its series plotted when no other channel's are.
    fn electrical(
        &mut self,
        d: &Dataset,
        ed: &ElectricalData,
        nom: &ElectricalFit,
        chosen: &Chosen,
    ) {
        let ext = chosen.electrical.as_ref().unwrap_or(nom);
        let (mut all_b, mut all_e) = (Vec::new(), Vec::new());
        for (m, &dm) in ed.motors.iter().enumerate() {
            let idx: Vec<usize> = (ed.split..ed.voltage[m].len())
                .filter(|&k| ed.voltage[m][k].is_finite())
                .collect();
            let rb = residuals_at(&nom.predict(ed, m), &ed.voltage[m], &idx);
            let re = residuals_at(&ext.predict(ed, m), &ed.voltage[m], &idx);
            self.motors[dm].baseline_rmse_v = Some(stats::rmse(&rb));
            self.motors[dm].extended_rmse_v = Some(stats::rmse(&re));
            all_b.extend(rb);
            all_e.extend(re);
        }
        self.voltage_rmse = (Some(stats::rmse(&all_b)), Some(stats::rmse(&all_e)));
        if self.traces.series.is_empty() {
            self.traces.unit = "V";
            self.traces.series = ed
                .motors
                .iter()
                .enumerate()
                .map(|(m, &dm)| Trace {
                    motor: d.motors[dm],
                    measured: ed.voltage[m].clone(),
                    nominal: nom.predict(ed, m),
                    extended: ext.predict(ed, m),
                })
                .collect();
        }
    }
}

/// A channel's part of the analysis.
struct ChannelOutcome {
    /// The nominal model's held-out misfit.
    misfit: Misfit,
    /// Every extension tried on it, in the order tried.
    candidates: Vec<Candidate>,
    /// The misfit left after its best supported extension.
    verdict: ChannelVerdict,
    /// The nominal model's held-out residuals per motor.
    held: Vec<HeldResiduals>,
}

/// Per motor: its id, its held-out indices and residuals.
fn held_residuals(ids: &[i64], idx: &[Vec<usize>], res: &[Vec<f64>]) -> Vec<HeldResiduals> {
    ids.iter()
        .zip(idx)
        .zip(res)
        .map(|((&id, i), r)| (id, i.clone(), r.clone()))
        .collect()
}

/// A motor's held-out residuals: its id, the sample indices and the residuals there.
type HeldResiduals = (i64, Vec<usize>, Vec<f64>);

/// The supported candidate of `channel` with the largest ΔBIC.
fn best_supported(candidates: &[Candidate], channel: Channel) -> Option<Effect> {
    candidates
        .iter()
        .filter(|c| c.verdict.supported() && c.channel == channel && c.with.is_none())
        .max_by(|a, b| a.delta_bic.total_cmp(&b.delta_bic))
        .map(|c| c.id)
}

/// What can be seen of a misfit no catalog entry explains: the partial explanations, the
/// regressors the residual follows, the worst motors and the residual's course in time.
fn structure(
    channel: Channel,
    candidates: &[Candidate],
    misfit: Option<&Misfit>,
    held: &[HeldResiduals],
    t: &[f64],
    split: usize,
) -> Unexplained {
    let mut partial: Vec<(Effect, f64)> = candidates
        .iter()
        .filter(|c| c.verdict.supported() && c.channel == channel)
        .map(|c| (c.id, c.gain))
        .collect();
    partial.sort_by(|a, b| b.1.total_cmp(&a.1));
    let mut strongest: Vec<(String, f64)> = misfit
        .map(|m| {
            m.correlations
                .iter()
                .filter(|(_, r)| r.is_finite())
                .map(|(k, r)| (k.clone(), *r))
                .collect()
        })
        .unwrap_or_default();
    strongest.sort_by(|a, b| b.1.abs().total_cmp(&a.1.abs()));
    strongest.truncate(3);
    let mut motors: Vec<(i64, f64, f64)> = held
        .iter()
        .map(|(id, _, r)| (*id, stats::rmse(r), stats::mean(r)))
        .collect();
    motors.sort_by(|a, b| b.1.total_cmp(&a.1));
    let (t0, t1) = (
        t.get(split).copied().unwrap_or(0.0),
        t.last().copied().unwrap_or(0.0),
    );
    let span = ((t1 - t0) / 10.0).max(1e-9);
    let mut spans = vec![Vec::new(); 10];
    for (_, idx, r) in held {
        for (&k, &e) in idx.iter().zip(r) {
            let j = (((t[k] - t0) / span) as usize).min(9);
            spans[j].push(e);
        }
    }
    let time_course = spans
        .iter()
        .enumerate()
        .filter(|(_, e)| !e.is_empty())
        .map(|(j, e)| {
            let a = t0 + j as f64 * span;
            (a, a + span, stats::rmse(e), stats::mean(e))
        })
        .collect();
    Unexplained {
        channel,
        partial,
        strongest_regressors: strongest,
        motors,
        time_course,
        form: None,
    }
}

/// The model file's key of a thermal or electrical extension, in the file's units.
fn set_key(m: &mut sim::extension::ModelExtension, effect: Effect, v: f64) {
    match effect {
        Effect::SensorLag => m.sensor_time_constant_s = Some(v),
        Effect::NeighborCoupling => m.neighbor_coupling_ratio = Some(v),
        Effect::CopperTempco => m.resistance_tempco_per_k = Some(v / 100.0),
        Effect::AmbientDrift => m.ambient_drift_k_per_h = Some(v),
        Effect::SupplySag => m.supply_resistance_ohm = Some(v),
        Effect::CurrentOffset => m.current_offset_a = Some(v),
        _ => {}
    }
}

fn model_file(
    d: &Dataset,
    td: &Option<ThermalData>,
    nominal: Option<&(ThermalFit, Vec<Vec<f64>>)>,
    chosen: &Chosen,
    cand: &Option<Candidate>,
) -> sim::extension::ModelExtension {
    use sim::extension::{FittedMotor, ModelExtension};
    let mut m = ModelExtension::none();
    m.cause = chosen.effect.id().to_string();
    let value = cand
        .as_ref()
        .and_then(|c| c.parameter.as_ref())
        .map(|p| p.value);
    if let Some(v) = value {
        set_key(&mut m, chosen.effect, v);
    }
    m.heldout_gain = cand.as_ref().map(|c| c.gain);
    m.fitted_on = d.runs.iter().map(|r| r.name.clone()).collect();
    if let (Some(td), Some((nom, _))) = (td, nominal) {
        // The calibrated constants travel with the extension: with the extension, the fitted
        // per-motor constants are the extended fit's, since they were fitted together.
        let (effect, p) = match &chosen.thermal {
            Some((f, _)) => (chosen.effect, &f.p),
            None => (Effect::None, &nom.p),
        };
        let params = match &chosen.thermal {
            Some((f, _)) => f.model(td).decode(p),
            None => ThermalModel::new(td, effect).decode(p),
        };
        m.motor = td
            .motors
            .iter()
            .enumerate()
            .map(|(i, &dm)| FittedMotor {
                id: d.motors[dm],
                tau_s: params.tau_s[i],
                gain_k_per_a2: params.gain_k_per_a2[i],
                idle_c: params.idle_c[i],
            })
            .collect();
    }
    m
}
