//! The analysis: split, calibrate the nominal model, measure its held-out misfit, try every
//! extension of the catalog and name the cause the data support.
//!
//! An extension is *supported* when all of these hold:
//! 1. it is significant on the fitting part at [`ALPHA`] / (catalog size) (Bonferroni over the
//!    six tries). Thermal: the likelihood ratio of the register model (the nominal model and
//!    every extension are fitted on the temperature register's own likelihood, rounding and
//!    noise, see [`crate::register`]), divided by the variance inflation of the extension's
//!    score contributions over 10 contiguous blocks per motor, so a model error that is slow
//!    and correlated (real data) is not taken for thousands of independent readings; against
//!    χ²(1). Electrical: the block (cluster-robust) t of "the nominal residuals follow the
//!    fitted correction" on the least-squares voltage fits;
//! 2. its Bayesian information criterion beats the nominal model's (ΔBIC > 0) at the test's
//!    effective sample size;
//! 3. where the held-out part is informative (block standard error of the slope at most
//!    [`MAX_INFORMATIVE_SE`]), it confirms it: the nominal model's held-out
//!    residuals follow the correction the extension predicts there (δ = nominal − extended
//!    prediction), i.e. the slope β of residual on δ is positive with a t statistic above
//!    [`MIN_HELDOUT_T`] (standard error from contiguous blocks, 10 per motor, so the test
//!    survives the residuals' autocorrelation), and the extension's held-out RMSE is not worse
//!    than the nominal model's. Where it is uninformative (the correction is far below the
//!    register's rounding noise), it must merely not go against the extension: neither the
//!    slope nor the squared-error drop significantly negative (t > −[`MIN_HELDOUT_T`]).
//!
//! Why a slope and not "the squared error drops significantly": with e = b − δ the drop
//! Σ(b² − e²) = 2Σbδ − Σδ² tests β > ½, at half the t of testing β > 0 for the same data. Where
//! the extension's correction on the held-out part is a few hundredths of a kelvin against a
//! register that rounds to 1 K (copper's tempco on a few kelvin of rise), the drop test misses a
//! correction the held-out readings plainly follow; the slope test still refuses corrections
//! the readings do not follow (β ≈ 0 on null data), and "not worse" refuses over-corrections.
//! A relative-gain threshold would not do either: where the held-out error is mostly sensor
//! noise and rounding, a real effect removes a real but small fraction of it.
//!
//! Two more conditions make a supported extension a finding rather than an artefact of many
//! samples:
//! 4. *practical significance*, whatever its p-value: its correction of the held-out
//!    predictions (RMS of δ) reaches [`PRACTICAL_OF_FLOOR`] of the channel's noise floor (the
//!    register's resolution is the yardstick where the nominal model fits to within the
//!    noise), and where the nominal misfit is beyond the noise it removes at least
//!    [`PRACTICAL_GAIN`] of the held-out RMSE (the misfit is the yardstick there: a 0.25 %
//!    gain explains nothing, however many samples make it significant);
//! 5. *physical plausibility*: its parameter lies in the range its physics allows
//!    ([`Effect::bounds`]); a fit outside it is evidence against the name; and its size is
//!    not negligible ([`Effect::negligible`]): a fit that needs the extension's shape at a size
//!    within the model's own tolerances or the readings' noise is fitting something else.
//!
//! A pair's second (tried beside the best single, against it) passes the same tests; where
//! the fitting part's test alone falls short (1 or 2), its p-value combined with the held-out
//! slope's by Fisher's method may stand in for both, provided the held-out readings follow
//! the second's correction at about its fitted size ([`HELDOUT_SIZE`]): two effects that
//! scale the same heating are nearly collinear on the fitting part and part where the
//! windings run hottest.
//!
//! Among supported extensions the candidate is the one with the largest ΔBIC. Whether it (or
//! nothing) is the answer depends on what is left: each channel's held-out misfit — after its
//! best supported extension, or the nominal model's if none — is compared with the channel's
//! *noise floor*, what a right model still misses (the register's rounding, q/√12, and the
//! readings' own high-frequency noise, from their second differences, see [`NoiseFloor`]). A
//! misfit whose RMSE exceeds [`MISFIT_RMSE_FLOORS`] floors, or whose bias exceeds
//! [`MISFIT_BIAS_FLOORS`] of them, is significant: the cause is then `unexplained` (with the
//! residual's structure and the partial explanations, [`Unexplained`]); otherwise it is the
//! candidate, or `none`: the nominal model fits to within the data's noise.

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
use serde::Serialize;
use std::collections::BTreeMap;
use thiserror::Error;

/// Family-wise false-alarm rate of the significance test.
pub const ALPHA: f64 = 0.01;
/// Smallest t statistic of the held-out confirmation (one-sided 5 %): the held-out residuals
/// must follow the extension's correction, and not by the luck of a few samples.
pub const MIN_HELDOUT_T: f64 = 1.645;
/// Largest block standard error of the held-out slope at which the held-out part can refute an
/// extension: 1 / (2 · 1.645), so a correction the readings follow fully (β = 1) reaches
/// [`MIN_HELDOUT_T`] with about 95 % probability.
pub const MAX_INFORMATIVE_SE: f64 = 0.304;
/// A pair's second that stands only on the fitting part and the held-out slope combined
/// must be followed by the held-out readings at about its fitted size: this range of the
/// slope (a correction 10 times too small that happens to point the right way says nothing
/// of the effect's size).
const HELDOUT_SIZE: std::ops::RangeInclusive<f64> = 0.5..=2.0;
/// Contiguous blocks per motor of the block statistics (held-out slope, fitting-part score
/// variance): residuals are correlated within a block, roughly independent between blocks.
const TEST_BLOCKS: usize = 10;

/// The [`TEST_BLOCKS`] contiguous index ranges a series of `len` samples is split into; none
/// when the series is shorter than that.
fn test_blocks(len: usize) -> impl Iterator<Item = std::ops::Range<usize>> {
    let count = if len < TEST_BLOCKS { 0 } else { TEST_BLOCKS };
    (0..count).map(move |j| j * len / TEST_BLOCKS..(j + 1) * len / TEST_BLOCKS)
}
/// A held-out misfit whose RMSE exceeds this many noise floors is significant.
pub const MISFIT_RMSE_FLOORS: f64 = 2.0;
/// A held-out misfit whose mean error exceeds this many noise floors is significant.
pub const MISFIT_BIAS_FLOORS: f64 = 1.0;
/// An extension's held-out correction (RMS) must reach this fraction of the noise floor to
/// matter (1 °C register: about 0.02 °C).
pub const PRACTICAL_OF_FLOOR: f64 = 0.05;
/// Where the nominal misfit is beyond the noise, an extension must cut the held-out RMSE by
/// at least this fraction to matter.
pub const PRACTICAL_GAIN: f64 = 0.05;
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
        }
    }
}

/// A named parameter with its unit.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Parameter {
    /// Name.
    pub name: String,
    /// Value.
    pub value: f64,
    /// Unit.
    pub unit: String,
}

/// Per-motor figures.
#[derive(Debug, Clone, Serialize)]
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

/// What a right model still misses on one channel, judged from the readings alone (no model):
/// the register's rounding (uniform over one step: q/√12) and the readings' own noise, from
/// their second differences within segments (E[(Δ²x)²] = 6σ² for white noise on a signal
/// that is smooth at the sampling rate; it also counts part of the rounding, so the floor
/// errs high, towards `none`).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct NoiseFloor {
    /// The register's step.
    pub quantum: f64,
    /// The readings' high-frequency noise.
    pub readings_noise: f64,
    /// √(q²/12 + σ²).
    pub floor: f64,
}

impl NoiseFloor {
    /// The floor of `series` (per motor, NaN where missing) read in steps of `quantum`.
    pub fn of(series: &[Vec<f64>], quantum: f64, segments: &[(usize, usize)]) -> NoiseFloor {
        let (mut sum, mut n) = (0.0, 0usize);
        for x in series {
            for &(s, e) in segments {
                for k in s + 1..e.min(x.len()).saturating_sub(1) {
                    let d2 = x[k + 1] - 2.0 * x[k] + x[k - 1];
                    if d2.is_finite() {
                        sum += d2 * d2;
                        n += 1;
                    }
                }
            }
        }
        let readings_noise = if n > 0 {
            (sum / n as f64 / 6.0).sqrt()
        } else {
            0.0
        };
        NoiseFloor {
            quantum,
            readings_noise,
            floor: (quantum * quantum / 12.0 + readings_noise * readings_noise).sqrt(),
        }
    }

    /// Whether a held-out misfit (RMSE, bias) is beyond this floor, and how that was judged.
    pub fn judge(&self, rmse: f64, bias: f64, unit: &str) -> (bool, String) {
        let (r, b) = (rmse / self.floor, bias.abs() / self.floor);
        // NaN (no residuals) is no evidence of a misfit.
        let significant = r > MISFIT_RMSE_FLOORS || b > MISFIT_BIAS_FLOORS;
        let how = format!(
            "held-out RMSE {rmse:.3} {unit} = {r:.1} noise floors, |bias| {:.3} {unit} = {b:.1} \
             (floor {:.3} {unit}: step {} {unit}, readings' noise {:.3} {unit}); significant \
             beyond {MISFIT_RMSE_FLOORS} floors of RMSE or {MISFIT_BIAS_FLOORS} of bias",
            bias.abs(),
            self.floor,
            (self.quantum * 1e6).round() / 1e6,
            self.readings_noise
        );
        (significant, how)
    }
}

/// One channel's held-out misfit once its best supported extension (if any) is applied.
#[derive(Debug, Clone, Serialize)]
pub struct ChannelVerdict {
    /// The channel.
    pub channel: Channel,
    /// Its best supported extension, if any.
    pub extension: Option<Effect>,
    /// Held-out RMSE with it (or the nominal model's).
    pub rmse: f64,
    /// Held-out mean error with it.
    pub bias: f64,
    /// Unit of both.
    pub unit: &'static str,
    /// Beyond the noise floor: the model misses something still.
    pub significant: bool,
    /// How that was judged, with the figures.
    pub judged: String,
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
}

/// One extension as tried.
#[derive(Debug, Clone, Serialize)]
pub struct Candidate {
    /// Catalog id.
    pub id: Effect,
    /// Tried on top of this extension (a pair, fitted together; the tests then weigh what
    /// `id` adds to it).
    pub with: Option<Effect>,
    /// Channel.
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
    /// Every test passed.
    pub supported: bool,
    /// Why not, when not.
    pub verdict: String,
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
    /// Diagnostics.
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

/// Prepares the thermal channel, or None when it has nothing to work with.
fn thermal_data(d: &Dataset, split: usize) -> Option<ThermalData> {
    let motors: Vec<usize> = (0..d.motors.len())
        .filter(|&m| {
            d.current[m].iter().any(|v| v.is_finite())
                && d.temperature[m][..split]
                    .iter()
                    .filter(|v| v.is_finite())
                    .count()
                    >= 20
        })
        .collect();
    if motors.is_empty() {
        return None;
    }
    let segments = d.segments();
    let fit_segments = segments.iter().filter(|(s, _)| *s < split).count();
    let measured: Vec<Vec<f64>> = motors.iter().map(|&m| d.temperature[m].clone()).collect();
    let valid = |m: usize, r: std::ops::Range<usize>| -> Vec<usize> {
        r.filter(|&k| measured[m][k].is_finite()).collect()
    };
    let pos = |dm: usize| motors.iter().position(|&x| x == dm);
    let data_init = (0..motors.len())
        .map(|m| {
            let fallback = stats::mean(&measured[m]);
            segments
                .iter()
                .map(|&(s, e)| {
                    let mut first: Vec<f64> = measured[m][s..e]
                        .iter()
                        .copied()
                        .filter(|v| v.is_finite())
                        .take(5)
                        .collect();
                    first.sort_by(f64::total_cmp);
                    first.get(first.len() / 2).copied().unwrap_or(fallback)
                })
                .collect()
        })
        .collect();
    Some(ThermalData {
        t: d.t.clone(),
        segments,
        split,
        current: motors
            .iter()
            .map(|&m| electrical::hold(&d.current[m]))
            .collect(),
        neighbours: motors
            .iter()
            .map(|&m| d.neighbours(m).into_iter().filter_map(pos).collect())
            .collect(),
        fit_idx: (0..motors.len()).map(|m| valid(m, 0..split)).collect(),
        held_idx: (0..motors.len())
            .map(|m| valid(m, split..d.t.len()))
            .collect(),
        fit_segments,
        data_init,
        quantum: d.temperature_quantum,
        measured,
        motors,
    })
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

/// Candidate regressors of the thermal residuals, pooled like the residuals (motor-major,
/// held-out readings). Each is what one extension would add to the prediction.
fn thermal_regressors(td: &ThermalData, nominal: &[Vec<f64>]) -> BTreeMap<String, Vec<f64>> {
    let mut r: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    let t0 = td.t.first().copied().unwrap_or(0.0);
    for m in 0..td.n() {
        let bus_current: Vec<f64> = (0..td.t.len())
            .map(|k| (0..td.n()).map(|j| td.current[j][k].abs()).sum())
            .collect();
        for &k in &td.held_idx[m] {
            let i = td.current[m][k];
            let kp = k.saturating_sub(1);
            let dtk = (td.t[k] - td.t[kp]).max(1e-9);
            let nb = &td.neighbours[m];
            let nb_diff = if nb.is_empty() {
                0.0
            } else {
                nb.iter().map(|&j| nominal[j][k]).sum::<f64>() / nb.len() as f64 - nominal[m][k]
            };
            let push = |r: &mut BTreeMap<String, Vec<f64>>, name: &str, v: f64| {
                r.entry(name.to_string()).or_default().push(v)
            };
            push(&mut r, "current_squared", i * i);
            push(&mut r, "current", i);
            push(
                &mut r,
                "temperature_x_current_squared",
                nominal[m][k] * i * i,
            );
            push(&mut r, "time", td.t[k] - t0);
            push(&mut r, "neighbor_temperature_difference", nb_diff);
            push(
                &mut r,
                "temperature_rate",
                (nominal[m][k] - nominal[m][kp]) / dtk,
            );
            push(&mut r, "bus_current", bus_current[k]);
        }
    }
    r
}

/// Runs the analysis. `progress` receives one line per step (fits take seconds on hours of data).
pub fn analyze(
    mut d: Dataset,
    opts: &Options,
    progress: &mut dyn FnMut(&str),
) -> Result<Outcome, AnalysisError> {
    let n = d.t.len();
    if !(opts.fit_fraction > 0.0 && opts.fit_fraction < 1.0) {
        return Err(AnalysisError::BadSplit(opts.fit_fraction));
    }
    let split = ((n as f64) * opts.fit_fraction).round() as usize;
    if split < 2 || split >= n {
        return Err(AnalysisError::BadSplit(opts.fit_fraction));
    }
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
        return Err(AnalysisError::NoChannel(
            audit
                .iter()
                .filter(|f| f.action == "refused")
                .map(|f| format!("{}: {}", f.column, f.detail))
                .collect::<Vec<_>>()
                .join("; "),
        ));
    }
    let mut candidates = Vec::new();
    let mut channels = Vec::new();
    // The record's span, h (what an ambient drift's size is judged against).
    let hours = match (d.t.first(), d.t.last()) {
        (Some(a), Some(b)) => (b - a) / 3600.0,
        _ => 0.0,
    };

    // Thermal channel.
    let mut thermal_nominal = None;
    let mut thermal_misfit = None;
    let mut register_noise = None;
    let mut thermal_fits: Vec<(Effect, ThermalFit, Vec<Vec<f64>>)> = Vec::new();
    let mut verdicts = Vec::new();
    // Two thermal effects named together: the first, the second, their parameters.
    let mut pair_named: Option<(Effect, Effect, f64, f64)> = None;
    // Per channel, the nominal model's held-out residuals per motor: id, indices, residuals.
    let mut nominal_held: Vec<(Channel, Vec<HeldResiduals>)> = Vec::new();
    if let Some(td) = &td {
        channels.push(Channel::Thermal);
        progress(&format!(
            "thermal: fitting the nominal model on {} motors, {} readings",
            td.n(),
            td.fit_count()
        ));
        let ls = fit_nominal(td);
        let ls_pred = ThermalModel::new(td, Effect::None).predict(&ls.p);
        let ls_res: Vec<f64> = (0..td.n())
            .flat_map(|m| residuals_at(&ls_pred[m], &td.measured[m], &td.fit_idx[m]))
            .collect();
        let reg = Register::estimate(td.quantum, &ls_res);
        progress(&format!(
            "thermal: refitting on the register's likelihood (step {} °C, noise {:.3} °C)",
            td.quantum,
            reg.sigma()
        ));
        let nom = refit_nominal(td, &ls, &reg);
        let nom_pred = ThermalModel::new(td, Effect::None).predict(&nom.p);
        let held: Vec<Vec<f64>> = (0..td.n())
            .map(|m| residuals_at(&nom_pred[m], &td.measured[m], &td.held_idx[m]))
            .collect();
        register_noise = Some(reg.sigma());
        let floor = NoiseFloor::of(&td.measured, td.quantum, &td.segments);
        let ids: Vec<i64> = td.motors.iter().map(|&dm| d.motors[dm]).collect();
        let nominal_verdict = verdict(Channel::Thermal, None, &ids, &held, "°C", &floor);
        thermal_misfit = Some(misfit(
            &held,
            thermal_regressors(td, &nom_pred),
            "°C",
            floor,
        ));
        for (i, &effect) in opts
            .candidates
            .iter()
            .filter(|e| {
                e.channel() == Channel::Thermal && !matches!(e, Effect::None | Effect::Unexplained)
            })
            .enumerate()
        {
            if effect == Effect::NeighborCoupling && td.neighbours.iter().all(Vec::is_empty) {
                continue;
            }
            progress(&format!("thermal: fitting {effect} ({})", i + 1));
            let fit = fit_extension(td, &nom, effect, Some(&reg));
            let model = ThermalModel::new(td, effect);
            let pred = model.predict(&fit.p);
            let held_ext: Vec<Vec<f64>> = (0..td.n())
                .map(|m| residuals_at(&pred[m], &td.measured[m], &td.held_idx[m]))
                .collect();
            let value = model.decode(&fit.p).extension;
            let parameter = effect.parameter().map(|(name, unit)| Parameter {
                name: name.into(),
                value,
                unit: unit.into(),
            });
            let test = deviance_test(td, &reg, &nom_pred, &pred, nom.sse, fit.sse);
            candidates.push(judge(
                effect,
                parameter,
                &nominal_verdict,
                floor.floor,
                hours,
                nom.sse,
                fit.sse,
                test,
                &held,
                &held_ext,
                fit.iterations,
            ));
            thermal_fits.push((effect, fit, pred));
        }
        let mut best = best_supported(&candidates, Channel::Thermal);
        // Two effects at once: the best supported extension fitted together with each other
        // one (an effect can hide another: a drift masks a lag until the drift is modelled);
        // a second is named beside the first when it passes every test against the first
        // alone; among several, the one with the largest ΔBIC.
        let singles: Vec<(Effect, ThermalFit)> = thermal_fits
            .iter()
            .map(|(e, f, _)| (*e, f.clone()))
            .collect();
        // Without a supported one, the strongest significant one (two effects can spoil each
        // other's held-out test alone): its pair must then stand against the nominal model too.
        let alpha = ALPHA / Effect::CATALOG.len() as f64;
        let base = best.or_else(|| {
            candidates
                .iter()
                .filter(|c| {
                    c.channel == Channel::Thermal
                        && c.with.is_none()
                        && c.plausible
                        && c.p_value < alpha
                        && c.delta_bic > 0.0
                })
                .max_by(|a, b| a.delta_bic.total_cmp(&b.delta_bic))
                .map(|c| c.id)
        });
        let first = base.and_then(|b| {
            thermal_fits
                .iter()
                .find(|(e, _, _)| *e == b)
                .map(|(e, f, p)| (*e, f.clone(), p.clone()))
        });
        let mut best_pair: Option<PairFit> = None;
        if let Some((a, fa, base_pred)) = &first {
            let base_held: Vec<Vec<f64>> = (0..td.n())
                .map(|m| residuals_at(&base_pred[m], &td.measured[m], &td.held_idx[m]))
                .collect();
            let after_first = verdict(Channel::Thermal, Some(*a), &ids, &base_held, "°C", &floor);
            for (b, fb) in singles.iter().filter(|(e, _)| e != a) {
                progress(&format!("thermal: fitting {a} with {b}"));
                let pair = fit_pair(td, fa, fb, Some(&reg));
                let model = pair.model(td);
                let pair_pred = model.predict(&pair.p);
                let decoded = model.decode(&pair.p);
                let pair_held: Vec<Vec<f64>> = (0..td.n())
                    .map(|m| residuals_at(&pair_pred[m], &td.measured[m], &td.held_idx[m]))
                    .collect();
                let test = deviance_test(td, &reg, base_pred, &pair_pred, fa.sse, pair.sse);
                let parameter = b.parameter().map(|(name, unit)| Parameter {
                    name: name.into(),
                    value: decoded.second_extension,
                    unit: unit.into(),
                });
                // The second against the first alone, under the fitting part's test or another.
                let (pair_sse, pair_iterations) = (pair.sse, pair.iterations);
                let judge_second = |test: FitTest| {
                    judge(
                        *b,
                        parameter.clone(),
                        &after_first,
                        floor.floor,
                        hours,
                        fa.sse,
                        pair_sse,
                        test,
                        &base_held,
                        &pair_held,
                        pair_iterations,
                    )
                };
                let mut c = judge_second(test);
                // The second is often nearly collinear with the first on the fitting part (a
                // current offset and copper's coefficient both scale the heating) and shows
                // where the winding runs hottest, in the held-out part: where the fitting part
                // alone falls short, its test and the held-out slope's decide together.
                if !c.supported && c.plausible && (c.p_value >= alpha || c.delta_bic <= 0.0) {
                    let alone = c.verdict.clone();
                    let combined = judge_second(test.with_heldout(c.heldout_slope_t));
                    if combined.supported {
                        c = Candidate {
                            verdict: format!(
                                "supported on the fitting part and the held-out slope together \
                                 (Fisher p = {:.2e}; the fitting part alone: {alone})",
                                combined.p_value
                            ),
                            ..combined
                        };
                    }
                }
                c.with = Some(*a);
                if c.supported && best.is_none() {
                    let pair_param = a.parameter().map(|(name, unit)| Parameter {
                        name: name.into(),
                        value: decoded.extension,
                        unit: unit.into(),
                    });
                    // Two parameters against the nominal model: χ²(2), two BIC penalties.
                    let test = deviance_test(td, &reg, &nom_pred, &pair_pred, nom.sse, pair.sse)
                        .with_params(2.0);
                    let whole = judge(
                        *a,
                        pair_param,
                        &nominal_verdict,
                        floor.floor,
                        hours,
                        nom.sse,
                        pair.sse,
                        test,
                        &held,
                        &pair_held,
                        pair.iterations,
                    );
                    if !whole.supported {
                        c.supported = false;
                        c.verdict = format!(
                            "with {a}, not supported against the nominal model: {}",
                            whole.verdict
                        );
                    }
                }
                // The first's parameter, refitted beside the second, must still be physical.
                if c.supported
                    && !a
                        .bounds()
                        .is_none_or(|(lo, hi, _)| (lo..=hi).contains(&decoded.extension))
                {
                    c.supported = false;
                    c.verdict = format!(
                        "beside it, {a} moves to {:.4}, outside what its physics allows",
                        decoded.extension
                    );
                }
                if c.supported
                    && best_pair
                        .as_ref()
                        .is_none_or(|b| stronger_second(&c, &b.candidate))
                {
                    best_pair = Some(PairFit {
                        candidate: c.clone(),
                        fit: pair,
                        prediction: pair_pred,
                        values: (decoded.extension, decoded.second_extension),
                    });
                }
                candidates.push(c);
            }
        }
        if let (Some((a, _, _)), Some(p)) = (&first, best_pair) {
            pair_named = Some((*a, p.candidate.id, p.values.0, p.values.1));
            thermal_fits.push((*a, p.fit, p.prediction));
            // A first that stood only with its second is supported now, and says so.
            if let Some(c) = candidates
                .iter_mut()
                .find(|c| c.id == *a && c.with.is_none() && !c.supported)
            {
                c.supported = true;
                c.verdict = format!("supported beside {} (alone: {})", p.candidate.id, c.verdict);
            }
            best = Some(*a);
        }
        // The fit the thermal channel is judged with: the pair's when named, else the best
        // single's (the pair's fit is the last one pushed for its first effect).
        let pred = thermal_fits
            .iter()
            .rev()
            .find(|(e, f, _)| Some(*e) == best && (pair_named.is_some() || f.second.is_none()))
            .map_or(&nom_pred, |(_, _, p)| p);
        let left: Vec<Vec<f64>> = (0..td.n())
            .map(|m| residuals_at(&pred[m], &td.measured[m], &td.held_idx[m]))
            .collect();
        verdicts.push(verdict(Channel::Thermal, best, &ids, &left, "°C", &floor));
        nominal_held.push((
            Channel::Thermal,
            td.motors
                .iter()
                .enumerate()
                .map(|(m, &dm)| (d.motors[dm], td.held_idx[m].clone(), held[m].clone()))
                .collect(),
        ));
        thermal_nominal = Some((nom, nom_pred));
    }

    // Electrical channel.
    let mut elec_nominal = None;
    let mut elec_misfit = None;
    let mut elec_sag = None;
    if let Some(ed) = &ed {
        channels.push(Channel::Electrical);
        progress(&format!(
            "electrical: {} motors, {} voltage readings, current {}",
            ed.motors.len(),
            ed.fit_count(),
            ed.current_source
        ));
        let nom = electrical::fit(ed, false);
        let held_idx: Vec<Vec<usize>> = ed
            .voltage
            .iter()
            .map(|v| (ed.split..v.len()).filter(|&k| v[k].is_finite()).collect())
            .collect();
        let fit_idx: Vec<Vec<usize>> = ed
            .voltage
            .iter()
            .map(|v| (0..ed.split).filter(|&k| v[k].is_finite()).collect())
            .collect();
        let res = |f: &ElectricalFit, idx: &[Vec<usize>]| -> Vec<Vec<f64>> {
            (0..ed.motors.len())
                .map(|m| residuals_at(&f.predict(ed, m), &ed.voltage[m], &idx[m]))
                .collect()
        };
        let held = res(&nom, &held_idx);
        let mut regs = BTreeMap::new();
        regs.insert(
            "bus_current".to_string(),
            (0..ed.motors.len())
                .flat_map(|m| held_idx[m].iter().map(move |&k| ed.bus_current[m][k]))
                .collect(),
        );
        let floor = NoiseFloor::of(&ed.voltage, data::quantum(&ed.voltage), &d.segments());
        let ids: Vec<i64> = ed.motors.iter().map(|&dm| d.motors[dm]).collect();
        let nominal_verdict = verdict(Channel::Electrical, None, &ids, &held, "V", &floor);
        elec_misfit = Some(misfit(&held, regs, "V", floor));
        if opts.candidates.contains(&Effect::SupplySag) {
            progress("electrical: fitting supply_sag");
            let sag = electrical::fit(ed, true);
            let test = block_wald_test(&res(&nom, &fit_idx), &res(&sag, &fit_idx));
            candidates.push(judge(
                Effect::SupplySag,
                Some(Parameter {
                    name: "supply_resistance".into(),
                    value: sag.resistance_ohm,
                    unit: "ohm".into(),
                }),
                &nominal_verdict,
                floor.floor,
                hours,
                nom.sse,
                sag.sse,
                test,
                &held,
                &res(&sag, &held_idx),
                1,
            ));
            elec_sag = Some(sag);
        }
        let best = best_supported(&candidates, Channel::Electrical);
        let left = match (&elec_sag, best) {
            (Some(sag), Some(_)) => res(sag, &held_idx),
            _ => held.clone(),
        };
        verdicts.push(verdict(Channel::Electrical, best, &ids, &left, "V", &floor));
        nominal_held.push((
            Channel::Electrical,
            ed.motors
                .iter()
                .enumerate()
                .map(|(m, &dm)| (d.motors[dm], held_idx[m].clone(), held[m].clone()))
                .collect(),
        ));
        elec_nominal = Some(nom);
    }

    // The cause: the supported extension with the largest ΔBIC, unless a channel's misfit
    // stays beyond its noise floor; then `unexplained`.
    let left_over = verdicts.iter().find(|v| v.significant);
    let chosen = candidates
        .iter()
        .filter(|c| c.supported && c.with.is_none() && left_over.is_none())
        .max_by(|a, b| a.delta_bic.total_cmp(&b.delta_bic))
        .cloned();
    let cause = match (left_over, &chosen) {
        (Some(_), _) => Effect::Unexplained,
        (None, Some(c)) => c.id,
        // Motion alone: its answer.
        (None, None) if td.is_none() && ed.is_none() => {
            motion.as_ref().map_or(Effect::None, |m| m.cause)
        }
        (None, None) => Effect::None,
    };
    let unexplained = left_over.map(|v| {
        let misfit = match v.channel {
            Channel::Thermal => thermal_misfit.as_ref(),
            Channel::Electrical => elec_misfit.as_ref(),
            Channel::Motion => None,
        };
        let held = nominal_held
            .iter()
            .find(|(c, _)| *c == v.channel)
            .map_or(&[][..], |(_, h)| &h[..]);
        structure(v.channel, &candidates, misfit, held, &d.t, split)
    });
    // Each channel's named extension (whatever the cause across channels), when nothing is
    // left unexplained.
    let named_on = |channel: Channel| {
        verdicts
            .iter()
            .find(|v| v.channel == channel)
            .and_then(|v| v.extension)
            .filter(|_| left_over.is_none())
    };
    let chosen_fit = Chosen {
        effect: cause,
        // The pair's fit when one was named (pushed after the single's), else the single's.
        thermal: named_on(Channel::Thermal).and_then(|t| {
            thermal_fits
                .iter()
                .rev()
                .find(|(e, f, _)| *e == t && (pair_named.is_some() || f.second.is_none()))
                .map(|(_, f, p)| (f.clone(), p.clone()))
        }),
        electrical: named_on(Channel::Electrical).and_then(|_| elec_sag.clone()),
    };

    // Per-motor figures.
    let mut motors: Vec<MotorFigures> = d
        .motors
        .iter()
        .map(|&id| MotorFigures {
            motor: id,
            tau_s: None,
            gain_k_per_a2: None,
            idle_c: None,
            readings: (0, 0),
            baseline_rmse_c: None,
            extended_rmse_c: None,
            baseline_bias_c: None,
            baseline_rmse_v: None,
            extended_rmse_v: None,
        })
        .collect();
    let mut traces = Traces {
        t: d.t.clone(),
        split,
        ..Default::default()
    };
    let (mut base_c, mut ext_c) = (None, None);
    if let (Some(td), Some((nom, nom_pred))) = (&td, &thermal_nominal) {
        let params = ThermalModel::new(td, Effect::None).decode(&nom.p);
        let ext_pred = chosen_fit.thermal.as_ref().map_or(nom_pred, |(_, p)| p);
        let (mut all_b, mut all_e) = (Vec::new(), Vec::new());
        for (m, &dm) in td.motors.iter().enumerate() {
            let rb = residuals_at(&nom_pred[m], &td.measured[m], &td.held_idx[m]);
            let re = residuals_at(&ext_pred[m], &td.measured[m], &td.held_idx[m]);
            let f = &mut motors[dm];
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
        base_c = Some(stats::rmse(&all_b));
        ext_c = Some(stats::rmse(&all_e));
        if cause.channel() == Channel::Thermal || ed.is_none() {
            traces.unit = "°C";
            traces.series = td
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
    let (mut base_v, mut ext_v) = (None, None);
    if let (Some(ed), Some(nom)) = (&ed, &elec_nominal) {
        let ext = chosen_fit.electrical.as_ref().unwrap_or(nom);
        let (mut all_b, mut all_e) = (Vec::new(), Vec::new());
        for (m, &dm) in ed.motors.iter().enumerate() {
            let idx: Vec<usize> = (ed.split..ed.voltage[m].len())
                .filter(|&k| ed.voltage[m][k].is_finite())
                .collect();
            let rb = residuals_at(&nom.predict(ed, m), &ed.voltage[m], &idx);
            let re = residuals_at(&ext.predict(ed, m), &ed.voltage[m], &idx);
            motors[dm].baseline_rmse_v = Some(stats::rmse(&rb));
            motors[dm].extended_rmse_v = Some(stats::rmse(&re));
            all_b.extend(rb);
            all_e.extend(re);
        }
        base_v = Some(stats::rmse(&all_b));
        ext_v = Some(stats::rmse(&all_e));
        if traces.series.is_empty() {
            traces.unit = "V";
            traces.series = ed
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
    let channel = match (&unexplained, cause) {
        (Some(u), _) => u.channel,
        // Motion alone: its channel, whatever its answer.
        _ if td.is_none() && ed.is_none() => Channel::Motion,
        (None, Effect::None) if td.is_some() => Channel::Thermal,
        (None, Effect::None) => Channel::Electrical,
        (None, c) => c.channel(),
    };
    let (baseline, extended, unit) = match channel {
        Channel::Thermal => (base_c, ext_c, "°C"),
        Channel::Electrical => (base_v, ext_v, "V"),
        Channel::Motion => (
            motion.as_ref().map(|m| m.nominal_mae_rad),
            motion.as_ref().map(|m| m.chosen_mae_rad),
            "rad",
        ),
    };
    let (baseline, extended) = (baseline.unwrap_or(f64::NAN), extended.unwrap_or(f64::NAN));
    // Every effect named: each channel's best (and the thermal pair's second), unless some
    // channel's misfit is left unexplained; then the motion channel's.
    let mut named: Vec<Effect> = if left_over.is_some() {
        vec![Effect::Unexplained]
    } else {
        verdicts.iter().filter_map(|v| v.extension).collect()
    };
    if let Some((first, second, _, _)) = pair_named.filter(|_| left_over.is_none()) {
        if let Some(i) = named.iter().position(|e| *e == first) {
            named.insert(i + 1, second);
        }
    }
    // Their parameters, the cause's first; a pair's each with the value it took beside the
    // other.
    named.sort_by_key(|e| *e != cause);
    let parameters: Vec<Parameter> = named
        .iter()
        .filter_map(|&e| {
            let value = match pair_named {
                Some((first, _, v1, _)) if first == e => Some(v1),
                Some((_, second, _, v2)) if second == e => Some(v2),
                _ => candidates
                    .iter()
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
    if let Some(m) = motion.as_ref().filter(|m| m.cause != Effect::None) {
        if !named.contains(&m.cause) {
            named.push(m.cause);
        }
    }
    let segs = d.segments();
    let mut model = model_file(&d, &td, &thermal_nominal, &chosen_fit, &chosen);
    // Every effect named, with its parameter as named (a pair's refitted together).
    for (e, p) in named.iter().zip(&parameters) {
        set_key(&mut model, *e, p.value);
        if *e != cause {
            model.cause = format!("{}+{}", model.cause, e.id());
        }
    }
    if let Some(m) = &motion {
        m.write_extension(&mut model);
    }
    let analysis = Analysis {
        cause,
        description: cause.describe(),
        parameters,
        channel,
        baseline_rmse_c: base_c,
        extended_rmse_c: ext_c,
        baseline_rmse: baseline,
        extended_rmse: extended,
        unit,
        gain: if baseline > 0.0 {
            1.0 - extended / baseline
        } else {
            0.0
        },
        motors,
        unexplained,
        causes: named,
        motion,
        diagnostics: Diagnostics {
            samples: n,
            motors: d.motors.len(),
            duration_s: segs.iter().map(|&(s, e)| d.t[e - 1] - d.t[s]).sum(),
            split_t_s: d.t[split],
            segments: segs.len(),
            channels,
            current_source: ed.as_ref().map(|e| e.current_source),
            audit,
            cleaning,
            temperature_quantum_c: d.temperature_quantum,
            register_noise_c: register_noise,
            thermal: thermal_misfit,
            electrical: elec_misfit,
            candidates,
            verdicts,
            alpha_per_test: ALPHA / Effect::CATALOG.len() as f64,
            min_heldout_t: MIN_HELDOUT_T,
            notes: d.notes.clone(),
        },
    };
    Ok(Outcome {
        analysis,
        traces,
        model,
    })
}

/// Whether the supported pair second `c` beats `than`: one supported on the fitting part
/// alone beats one that needed the held-out slope; among the first kind the larger ΔBIC wins,
/// among the second the smaller combined p-value (their ΔBIC, the fitting part's alone, is
/// what fell short).
fn stronger_second(c: &Candidate, than: &Candidate) -> bool {
    match (c.with_heldout, than.with_heldout) {
        (false, true) => true,
        (true, false) => false,
        (false, false) => c.delta_bic > than.delta_bic,
        (true, true) => c.p_value < than.p_value,
    }
}

/// A pair of thermal extensions fitted together, as tried.
struct PairFit {
    /// The second's candidate (tried beside the first).
    candidate: Candidate,
    /// The pair's fit.
    fit: ThermalFit,
    /// Its predictions.
    prediction: Vec<Vec<f64>>,
    /// The first's and the second's parameters, in the catalog's units.
    values: (f64, f64),
}

/// A motor's held-out residuals: its id, the sample indices and the residuals there.
type HeldResiduals = (i64, Vec<usize>, Vec<f64>);

/// The supported candidate of `channel` with the largest ΔBIC.
fn best_supported(candidates: &[Candidate], channel: Channel) -> Option<Effect> {
    candidates
        .iter()
        .filter(|c| c.supported && c.channel == channel && c.with.is_none())
        .max_by(|a, b| a.delta_bic.total_cmp(&b.delta_bic))
        .map(|c| c.id)
}

/// Fewest held-out residuals of a motor judged on its own.
const MIN_MOTOR_RESIDUALS: usize = 20;

/// The verdict on the misfit `left` (held-out residuals per motor, of motors `ids`) after
/// `extension`: all motors pooled, and each on its own (one motor's misfit must not drown in
/// its well-fitted neighbours'); the worst one is named.
fn verdict(
    channel: Channel,
    extension: Option<Effect>,
    ids: &[i64],
    left: &[Vec<f64>],
    unit: &'static str,
    floor: &NoiseFloor,
) -> ChannelVerdict {
    let all = left.concat();
    let (rmse, bias) = (stats::rmse(&all), stats::mean(&all));
    let (mut significant, mut judged) = floor.judge(rmse, bias, unit);
    judged = format!("all motors: {judged}");
    let worst = ids
        .iter()
        .zip(left)
        .filter(|(_, r)| r.len() >= MIN_MOTOR_RESIDUALS)
        .map(|(id, r)| (id, stats::rmse(r), stats::mean(r)))
        .filter(|(_, rmse, bias)| rmse.is_finite() && bias.is_finite())
        .max_by(|a, b| {
            let score = |x: &(&i64, f64, f64)| {
                (x.1 / MISFIT_RMSE_FLOORS).max(x.2.abs() / MISFIT_BIAS_FLOORS)
            };
            score(a).total_cmp(&score(b))
        });
    if let Some((id, r, b)) = worst {
        let (s, how) = floor.judge(r, b, unit);
        significant |= s;
        judged = format!("{judged}; worst motor {id}: {how}");
    }
    ChannelVerdict {
        channel,
        extension,
        rmse,
        bias,
        unit,
        significant,
        judged,
    }
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
        .filter(|c| c.supported && c.channel == channel)
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
    }
}

/// The fitting part's significance test of one extension.
#[derive(Debug, Clone, Copy)]
struct FitTest {
    /// Likelihood-ratio statistic, corrected for dependent samples.
    lr: f64,
    /// Effective sample size.
    n_eff: f64,
    /// p-value.
    p_value: f64,
    /// Parameters the test weighs (its χ² degrees of freedom and BIC penalty).
    params: f64,
    /// The p-value combines the fitting part's with the held-out slope's (see
    /// [`FitTest::with_heldout`]): the BIC, a fitting-part criterion, does not apply.
    with_heldout: bool,
}

impl FitTest {
    /// The same statistic weighing `params` parameters instead of one (a pair against the
    /// nominal model: two).
    fn with_params(self, params: f64) -> FitTest {
        FitTest {
            p_value: stats::chi2_sf(self.lr, params),
            params,
            ..self
        }
    }

    /// The fitting part's p-value combined (Fisher) with the held-out slope's one-sided one,
    /// `slope_t` its t statistic: two tests of one null hypothesis, taken as independent (the
    /// held-out readings are never fitted; a correction that partly undoes the first's own
    /// fit error makes them not quite so, which the size guards of [`judge`] answer).
    fn with_heldout(self, slope_t: f64) -> FitTest {
        let heldout_p = if slope_t.is_nan() {
            1.0
        } else {
            stats::normal_sf(slope_t)
        };
        FitTest {
            p_value: stats::fisher(&[self.p_value, heldout_p]),
            with_heldout: true,
            ..self
        }
    }
}

/// The thermal channel's test: the likelihood ratio of the register model, Σρ²(nominal) −
/// Σρ²(extended) (ρ the deviance residuals both fits minimised), against χ²(1), valid
/// (asymptotically) for independent readings. Where the model misses something slow (real
/// data), the per-reading score contributions of the extension, ρ·∂ρ/∂θ, are correlated in
/// time: the statistic is then divided by their variance inflation φ (their variance over
/// [`TEST_BLOCKS`] contiguous blocks per motor over their independent-sample variance, at least
/// 1), and the effective sample size is n/φ.
/// (The score contributions, unlike the ρ themselves, have zero conditional mean under a
/// correct model: ρ alone is correlated in time even then, through the slowly moving position
/// of T between two register steps.)
fn deviance_test(
    td: &ThermalData,
    reg: &Register,
    nominal: &[Vec<f64>],
    extended: &[Vec<f64>],
    base_sse: f64,
    sse: f64,
) -> FitTest {
    let (mut block_var, mut plain_var, mut n) = (0.0, 0.0, 0usize);
    for m in 0..td.n() {
        let idx = &td.fit_idx[m];
        let scores: Vec<f64> = idx
            .iter()
            .map(|&k| {
                let e = extended[m][k] - td.measured[m][k];
                reg.residual(e) * reg.derivative(e) * (extended[m][k] - nominal[m][k])
            })
            .collect();
        n += scores.len();
        if scores.len() < TEST_BLOCKS {
            continue;
        }
        let mean = stats::mean(&scores);
        for r in test_blocks(scores.len()) {
            let sum: f64 = scores[r].iter().map(|s| s - mean).sum();
            block_var += sum * sum;
        }
        plain_var += scores.iter().map(|s| (s - mean).powi(2)).sum::<f64>();
    }
    let phi = if plain_var > 0.0 {
        (block_var / plain_var).max(1.0)
    } else {
        1.0
    };
    let lr = ((base_sse - sse) / phi).max(0.0);
    FitTest {
        lr,
        n_eff: (n as f64 / phi).max(1.0),
        p_value: stats::chi2_sf(lr, 1.0),
        params: 1.0,
        with_heldout: false,
    }
}

/// The electrical channel's test (least squares on the voltage register): the block
/// (cluster-robust) Wald t of "the nominal residuals follow the fitted correction", LR at the
/// residuals' AR(1) effective sample size for the BIC.
fn block_wald_test(base: &[Vec<f64>], ext: &[Vec<f64>]) -> FitTest {
    let (base_sse, sse): (f64, f64) = (
        base.iter().flatten().map(|v| v * v).sum(),
        ext.iter().flatten().map(|v| v * v).sum(),
    );
    let n_eff = n_eff_of(ext);
    let lr = if sse > 0.0 && base_sse > 0.0 {
        (n_eff * (base_sse / sse).ln()).max(0.0)
    } else {
        0.0
    };
    let (_, t, _) = slope_stats(base, ext);
    let p_value = if t.is_finite() && t > 0.0 {
        stats::chi2_sf(t * t, 1.0)
    } else if t.is_infinite() && t > 0.0 {
        0.0
    } else {
        1.0
    };
    FitTest {
        lr,
        n_eff,
        p_value,
        params: 1.0,
        with_heldout: false,
    }
}

/// The three tests of the module docs.
#[allow(clippy::too_many_arguments)]
fn judge(
    effect: Effect,
    parameter: Option<Parameter>,
    nominal: &ChannelVerdict,
    floor: f64,
    hours: f64,
    base_sse: f64,
    sse: f64,
    test: FitTest,
    base_res: &[Vec<f64>],
    res: &[Vec<f64>],
    iterations: usize,
) -> Candidate {
    let base_held = stats::rmse(&base_res.concat());
    let held = stats::rmse(&res.concat());
    let heldout_t = improvement_t(base_res, res);
    let (heldout_slope, heldout_slope_t, heldout_slope_se) = slope_stats(base_res, res);
    let FitTest {
        lr,
        n_eff,
        p_value,
        params,
        with_heldout,
    } = test;
    let delta_bic = lr - params * n_eff.ln();
    // The held-out test can only refute an extension where it has the power to see it: with a
    // block standard error of the slope above [`MAX_INFORMATIVE_SE`], a correction the readings
    // follow fully (β = 1) would not reach [`MIN_HELDOUT_T`] most of the time (the correction is
    // far below the register's rounding noise there). Such a held-out part is uninformative:
    // the extension then stands on the fitting part, provided the held-out readings do not go
    // significantly against it and its held-out error is not significantly worse.
    let informative = heldout_slope_se.is_finite() && heldout_slope_se <= MAX_INFORMATIVE_SE;
    let gain = if base_held > 0.0 {
        1.0 - held / base_held
    } else {
        0.0
    };
    let alpha = ALPHA / Effect::CATALOG.len() as f64;
    let heldout_change = stats::rmse(
        &base_res
            .iter()
            .zip(res)
            .flat_map(|(b, e)| b.iter().zip(e).map(|(b, e)| b - e))
            .collect::<Vec<f64>>(),
    );
    let required_change = PRACTICAL_OF_FLOOR * floor;
    let required_gain = if nominal.significant {
        PRACTICAL_GAIN
    } else {
        0.0
    };
    let bounds = effect.bounds();
    let value = parameter.as_ref().map_or(f64::NAN, |p| p.value);
    let plausible = bounds.is_none_or(|(lo, hi, _)| value >= lo && value <= hi);
    let verdict = if !plausible {
        let (lo, hi, why) = bounds.unwrap_or((f64::NAN, f64::NAN, ""));
        format!("parameter {value:.4} outside what its physics allows, [{lo}, {hi}]: {why}")
    } else if let Some((small, why)) = effect
        .negligible(hours, floor)
        .filter(|(s, _)| value.abs() < *s)
    {
        format!("too small to be a finding: {value:.4} (below {small:.4} counts as none: {why})")
    } else if p_value >= alpha {
        format!("not significant (p = {p_value:.2e} ≥ {alpha:.1e})")
    } else if with_heldout && !HELDOUT_SIZE.contains(&heldout_slope) {
        format!(
            "the held-out readings follow {heldout_slope:.2} times its correction: named on \
             held-out evidence, it must be about its fitted size ({:.1}–{:.1})",
            HELDOUT_SIZE.start(),
            HELDOUT_SIZE.end()
        )
    } else if !with_heldout && delta_bic <= 0.0 {
        format!("BIC does not improve (ΔBIC = {delta_bic:.1})")
    } else if informative && (heldout_slope_t.is_nan() || heldout_slope_t < MIN_HELDOUT_T) {
        format!(
            "held-out readings do not follow the extension (slope {heldout_slope:.2}, \
             t = {heldout_slope_t:.2} < {MIN_HELDOUT_T})"
        )
    } else if !informative
        && (heldout_slope_t.is_nan()
            || heldout_slope_t <= -MIN_HELDOUT_T
            || heldout_t <= -MIN_HELDOUT_T
            || held.is_nan())
    {
        format!(
            "held-out part uninformative (slope s.e. {heldout_slope_se:.2}) and against the \
             extension (slope t = {heldout_slope_t:.2}, error-reduction t = {heldout_t:.2})"
        )
    } else if informative && (held.is_nan() || held > base_held) {
        format!(
            "held-out error worse (gain {:.1} %, slope {heldout_slope:.2})",
            100.0 * gain
        )
    } else if heldout_change.is_nan() || heldout_change < required_change {
        format!(
            "no practical difference: it changes the held-out predictions by {heldout_change:.4} \
             RMS, {required_change:.4} would matter ({PRACTICAL_OF_FLOOR} of the noise floor \
             {floor:.4})"
        )
    } else if gain.is_nan() || gain < required_gain {
        format!(
            "explains too little: held-out gain {:.2} % of a misfit beyond the noise, {:.0} % \
             would matter",
            100.0 * gain,
            100.0 * required_gain
        )
    } else {
        "supported".to_string()
    };
    Candidate {
        id: effect,
        with: None,
        channel: effect.channel(),
        parameter,
        baseline_fit_sse: base_sse,
        fit_sse: sse,
        n_eff,
        lr,
        p_value,
        with_heldout,
        delta_bic,
        baseline_heldout_rmse: base_held,
        heldout_rmse: held,
        gain,
        heldout_t,
        heldout_slope,
        heldout_slope_t,
        heldout_change,
        required_change,
        required_gain,
        bounds: bounds.map(|(lo, hi, _)| (lo, hi)),
        plausible,
        supported: verdict == "supported",
        verdict,
        iterations,
    }
}

/// Slope β of the nominal residuals b on the extension's correction δ = b − e (b, e: nominal
/// and extended held-out residuals, prediction − reading) and its t statistic, with a
/// cluster-robust standard error over contiguous blocks of each motor's residuals (the
/// residuals are autocorrelated within a block, roughly independent between blocks).
/// (0, 0) when there are too few blocks or no correction at all.
#[cfg(test)]
fn confirmation_slope(base: &[Vec<f64>], ext: &[Vec<f64>]) -> (f64, f64) {
    let (beta, t, _) = slope_stats(base, ext);
    (beta, t)
}

/// The held-out slope (see `confirmation_slope`) with the slope's block standard error as well (infinite when there
/// are too few blocks or no correction: nothing can be concluded).
fn slope_stats(base: &[Vec<f64>], ext: &[Vec<f64>]) -> (f64, f64, f64) {
    let mut blocks: Vec<(f64, f64)> = Vec::new();
    for (b, e) in base.iter().zip(ext) {
        for r in test_blocks(b.len().min(e.len())) {
            let (mut s, mut dd) = (0.0, 0.0);
            for k in r {
                let d = b[k] - e[k];
                s += b[k] * d;
                dd += d * d;
            }
            blocks.push((s, dd));
        }
    }
    let m = blocks.len() as f64;
    let s: f64 = blocks.iter().map(|x| x.0).sum();
    let dd: f64 = blocks.iter().map(|x| x.1).sum();
    if m < 3.0 || dd <= 0.0 {
        return (0.0, 0.0, f64::INFINITY);
    }
    let beta = s / dd;
    let var = blocks
        .iter()
        .map(|(sj, dj)| (sj - beta * dj).powi(2))
        .sum::<f64>()
        * m
        / (m - 1.0)
        / (dd * dd);
    if var <= 0.0 {
        return (beta, if beta > 0.0 { f64::INFINITY } else { 0.0 }, 0.0);
    }
    (beta, beta / var.sqrt(), var.sqrt())
}

/// t statistic of the mean reduction of squared error, over contiguous blocks of each motor's
/// held-out residuals (0 when there are too few blocks).
fn improvement_t(base: &[Vec<f64>], ext: &[Vec<f64>]) -> f64 {
    let mut means = Vec::new();
    for (b, e) in base.iter().zip(ext) {
        for r in test_blocks(b.len().min(e.len())) {
            let len = r.len().max(1) as f64;
            let d: f64 = r.map(|k| b[k] * b[k] - e[k] * e[k]).sum();
            means.push(d / len);
        }
    }
    let m = means.len() as f64;
    if m < 3.0 {
        return 0.0;
    }
    let mean = means.iter().sum::<f64>() / m;
    let var = means.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (m - 1.0);
    if var <= 0.0 {
        return if mean > 0.0 { f64::INFINITY } else { 0.0 };
    }
    mean / (var / m).sqrt()
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
    nominal: &Option<(ThermalFit, Vec<Vec<f64>>)>,
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

#[cfg(test)]
mod tests {
    use super::*;
    use sim::rng::Rng;

    /// Nominal residuals b = (true correction δ) + noise, the extension removing δ.
    fn residuals(follow: f64, seed: u64) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
        let mut rng = Rng::new(seed);
        let (mut base, mut ext) = (Vec::new(), Vec::new());
        for m in 0..4 {
            let (mut b, mut e) = (Vec::new(), Vec::new());
            for k in 0..2000 {
                let delta = 0.05 * ((k as f64) / 150.0 + m as f64).sin();
                let r = follow * delta + 0.3 * rng.normal();
                b.push(r);
                e.push(r - delta);
            }
            base.push(b);
            ext.push(e);
        }
        (base, ext)
    }

    #[test]
    fn the_slope_test_sees_a_correction_the_squared_error_test_misses() {
        let (b, e) = residuals(1.0, 3);
        let (slope, t) = confirmation_slope(&b, &e);
        assert!((slope - 1.0).abs() < 0.3, "{slope}");
        assert!(t > MIN_HELDOUT_T, "{t}");
        // The same data through the squared-error drop: about half the t.
        assert!(improvement_t(&b, &e) < t, "{}", improvement_t(&b, &e));
    }

    #[test]
    fn the_slope_test_refuses_a_correction_the_readings_do_not_follow() {
        let (b, e) = residuals(0.0, 4);
        let (slope, t) = confirmation_slope(&b, &e);
        assert!(slope.abs() < 0.3 && t < MIN_HELDOUT_T, "{slope} {t}");
    }
}
