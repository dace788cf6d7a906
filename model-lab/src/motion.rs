//! The motion channel: measured runs replayed open-loop through the simulator's own servo
//! model ([`sim::servo::Servo`]: the firmware's position loop and duty, the DC motor with its
//! back-EMF, the gearbox, friction) carrying the run's load (a pendulum, from its sidecar),
//! driven by the run's logged goal, torque-enable and supply-voltage sequences; the simulated
//! position is compared with the measured one (MAE and RMSE in rad, per run).
//!
//! The nominal model is the simulator's servo with its Coulomb and viscous friction calibrated
//! (BAM's "m1", Coulomb–viscous). Each catalog extension adds its parameters to those two and
//! is fitted the same way: Nelder–Mead on the mean absolute error over the training runs (the
//! loss BAM fits with; the stick–slip makes it non-smooth, so no gradients). Runs are held
//! out whole, one at a time: a run's figures are always those of a model fitted without it.
//!
//! An extension is named when, on the held-out runs, it cuts the nominal model's mean absolute
//! error by at least [`MOTION_PRACTICAL_GAIN`] and by [`MOTION_MIN_MAE_CUT`], on a majority
//! of the runs, with its parameters inside the ranges their physics allows (and a directional
//! friction's sides [`DIRECTIONAL_MIN_ASYMMETRY`] apart); among several, the largest gain.
//! Whatever is named, a misfit left beyond the channel's noise floor (the encoder's step and
//! the positions' own noise where the servo stood still) and beyond one encoder step of RMSE
//! ([`MOTION_PRACTICAL_MISFIT`]) is `unexplained`, unless an
//! extension at a size within the servo's own tolerances takes it within the floor: that
//! misfit is the tolerance's (a motor constant 5 % off its rating), no finding.

use crate::analysis::{AgainstFloor, NoiseFloor};
use crate::catalog::Effect;
use crate::data::{Dataset, Mechanics};
use crate::stats;
use crate::verdict::Verdict;
use serde::Serialize;
use sim::description::ServoRating;
use sim::extension::ServoExtension;
use sim::servo::{Servo, Surroundings, RAD_PER_STEP, TICK_TOLERANCE_S};

/// An extension must cut the held-out mean absolute error by this fraction to matter ...
pub const MOTION_PRACTICAL_GAIN: f64 = 0.05;
/// ... and by at least a sixteenth of an encoder step, rad (a quarter of the mean absolute
/// error that rounding to the step alone makes): systematic over a run's hundreds of samples,
/// where an effect that shows only at moments (play where the load reverses) errs by steps
/// there. On runs with nothing hidden the replay follows the servo to within the supply it
/// cannot know (logged at the samples, in 0.1 V steps), and the catalog's extensions cut at
/// most about a thirtieth of a step, each at a size that is no finding.
pub const MOTION_MIN_MAE_CUT: f64 = RAD_PER_STEP / 16.0;
/// A misfit left is `unexplained` only beyond one encoder step of held-out RMSE, rad, as well
/// as beyond the noise floor. The floor, measured where the servo stood still, is the sensor's
/// alone; a right model replayed open loop also misses what the samples do not say (the
/// supply's sag between them, their timing): on generated runs hiding one friction or
/// inertia, the right extension leaves 0.4–0.65 of a step (1.3–2.1 floors), a wrong or missing
/// one 2.8 steps and more. Under a step, the simulator already reads what the robot would.
pub const MOTION_PRACTICAL_MISFIT: f64 = RAD_PER_STEP;
/// A directional friction's two sides differ by at least this fraction of the larger; closer,
/// they are one load-proportional friction. A spur gear train's back-driven losses exceed its
/// driving ones by a few percent (per mesh of efficiency η, back-driven 2 − 1/η: four meshes at
/// 0.95 carry 0.186 and 0.194 of the torque), and the supply, logged at the samples, misses its
/// sag while the motor drives, which a little more friction there imitates (sides up to a sixth
/// apart on generated runs hiding one friction, a twentieth with a steady supply); a worm-like
/// or self-locking train differs by far more.
pub const DIRECTIONAL_MIN_ASYMMETRY: f64 = 1.0 / 3.0;
/// Nelder–Mead evaluations per fit, per parameter and one.
const FIT_EVALUATIONS_PER_VERTEX: usize = 100;

/// One measured run of one servo, as the motion channel uses it.
#[derive(Debug, Clone)]
pub struct MotionRun {
    /// The file.
    pub name: String,
    /// Sample times, s, from the run's start.
    pub t: Vec<f64>,
    /// Commanded position, rad.
    pub goal: Vec<f64>,
    /// Measured position, rad (NaN where missing).
    pub position: Vec<f64>,
    /// Supply voltage, V (held over missing readings).
    pub voltage: Vec<f64>,
    /// Torque enabled.
    pub torque: Vec<bool>,
    /// The load.
    pub mechanics: Mechanics,
}

impl MotionRun {
    /// The runs of `d` the motion channel can replay: each run (file) with its mechanics
    /// known, a goal and a position column, for the first motor that has them; none else.
    pub fn from_dataset(d: &Dataset, rated_voltage: f64) -> Vec<MotionRun> {
        let Some(m) = (0..d.motors.len()).find(|&m| {
            d.goal[m].iter().any(|v| v.is_finite()) && d.position[m].iter().any(|v| v.is_finite())
        }) else {
            return Vec::new();
        };
        d.runs
            .iter()
            .filter_map(|r| {
                let mechanics = r.mechanics?;
                let range = r.start..r.end;
                let t0 = d.t[r.start];
                // Goal and supply held over missing samples (`first` when a run has none).
                let hold = |col: &[f64], first: f64| {
                    let part = &col[range.clone()];
                    if part.iter().any(|v| v.is_finite()) {
                        crate::electrical::hold(part)
                    } else {
                        vec![first; part.len()]
                    }
                };
                let run = MotionRun {
                    name: r.name.clone(),
                    t: d.t[range.clone()].iter().map(|t| t - t0).collect(),
                    goal: hold(&d.goal[m], 0.0),
                    position: d.position[m][range.clone()].to_vec(),
                    voltage: hold(&d.voltage[m], rated_voltage),
                    torque: d.torque_enabled[m][range.clone()]
                        .iter()
                        .map(|v| !(v.is_finite() && *v < 0.5))
                        .collect(),
                    mechanics,
                };
                (run.position.iter().filter(|v| v.is_finite()).count() >= 20).then_some(run)
            })
            .collect()
    }
}

/// The motion model's parameters: the calibrated friction and an extension.
#[derive(Debug, Clone, Copy, Default)]
pub struct MotionParams {
    /// Coulomb friction, N·m.
    pub coulomb_nm: f64,
    /// Viscous friction, N·m·s/rad.
    pub viscous_nms: f64,
    /// The extension's part.
    pub ext: ServoExtension,
}

/// Replays `run` through the simulator's servo of `rating` with `p`: the simulated position at
/// each sample time. Goal, torque and supply are held from one sample to the next; the servo
/// is stepped from one firmware tick to the next (each step holds one duty).
pub fn simulate(rating: &ServoRating, p: &MotionParams, run: &MotionRun) -> Vec<f64> {
    let start = run
        .position
        .iter()
        .copied()
        .find(|v| v.is_finite())
        .unwrap_or(0.0);
    let mut s = Servo::new(1, rating.model, rating, start, 25.0);
    s.plant.coulomb = p.coulomb_nm;
    s.plant.viscous = p.viscous_nms;
    s.extension = p.ext;
    s.configure_for_replay(run.mechanics.kp.round().clamp(0.0, 255.0) as u8);
    let (m, l) = (run.mechanics.mass_kg, run.mechanics.length_m);
    let mut out = Vec::with_capacity(run.t.len());
    let mut torque = None;
    for k in 0..run.t.len() {
        out.push(s.angle);
        if k + 1 == run.t.len() {
            break;
        }
        s.command_goal(run.goal[k]);
        if torque != Some(run.torque[k]) {
            s.command_torque(run.torque[k]);
            torque = Some(run.torque[k]);
        }
        s.supply = run.voltage[k];
        let mut left = (run.t[k + 1] - run.t[k]).max(0.0);
        while left > TICK_TOLERANCE_S {
            let h = left.min(s.until_tick());
            s.step(h, Surroundings::BENCH.pendulum(m, l, &s, h));
            left -= h;
        }
    }
    out
}

/// Mean absolute and root-mean-square error of `sim` against the run's measured positions.
pub fn errors(sim: &[f64], run: &MotionRun) -> (f64, f64) {
    let e: Vec<f64> = sim
        .iter()
        .zip(&run.position)
        .filter(|(_, m)| m.is_finite())
        .map(|(s, m)| s - m)
        .collect();
    let mae = e.iter().map(|x| x.abs()).sum::<f64>() / e.len().max(1) as f64;
    (mae, stats::rmse(&e))
}

/// One parameter of a motion model: name, unit, the range its physics allows (the fit's
/// bounds) and its nominal value.
#[derive(Debug, Clone, Copy)]
pub struct MotionParam {
    /// Its name, as the report and the catalog give it, e.g. `coulomb_friction`.
    pub name: &'static str,
    /// The unit of all its values, e.g. `N·m`, `N·m·s/rad` (`1`: dimensionless).
    pub unit: &'static str,
    /// Lowest physical value.
    pub lo: f64,
    /// Highest physical value.
    pub hi: f64,
    /// Nominal value (where the fit starts).
    pub start: f64,
    /// Where a second fit starts: an extension's effect trades against the friction (a
    /// lighter armature against more friction, a sharp Stribeck peak against a broad one), so
    /// one start can end in the other basin; the best start on the training runs is kept
    /// (see [`fit_models`]).
    pub second_start: f64,
    /// A size smaller than this is no finding whatever it predicts: within what the servo's
    /// own tolerances or the encoder already allow (0: not a size, e.g. a speed scale).
    pub negligible: f64,
    /// The lower bound is what the data resolve, not a physical limit: a fit pinned there is
    /// still physical (a Stribeck speed at its floor is a breakaway sharper than the encoder
    /// and the replay's steps show, a step from static to kinetic friction).
    pub resolution_floor: bool,
}

const COULOMB: MotionParam = MotionParam {
    name: "coulomb_friction",
    unit: "N·m",
    lo: 0.0,
    hi: 0.5,
    start: 0.05,
    second_start: 0.15,
    negligible: 0.0,
    resolution_floor: false,
};
const VISCOUS: MotionParam = MotionParam {
    name: "viscous_friction",
    unit: "N·m·s/rad",
    lo: 0.0,
    hi: 1.0,
    start: 0.06,
    second_start: 0.06,
    negligible: 0.0,
    resolution_floor: false,
};

/// The extension's own parameters (after Coulomb and viscous).
pub fn extension_params(effect: Effect) -> &'static [MotionParam] {
    match effect {
        Effect::ArmatureError => &[MotionParam {
            name: "armature_error",
            unit: "1",
            lo: -0.9,
            hi: 3.0,
            start: 0.0,
            second_start: -0.4,
            // The motor's and the gears' inertia are datasheet figures known to about ±10 %.
            negligible: 0.1,
            resolution_floor: false,
        }],
        Effect::FirmwareGain => &[MotionParam {
            name: "duty_gain_error",
            unit: "1",
            lo: -0.5,
            hi: 1.0,
            start: 0.0,
            second_start: -0.25,
            // The duty's effect scales with the motor constant (about ±10 % from one motor to
            // the next) and with the supply, logged in 0.1 V steps: a gain off by less is no
            // different firmware.
            negligible: 0.1,
            resolution_floor: false,
        }],
        // A hobby servo's gear train: a few milliradians to a few degrees of play.
        Effect::Backlash => &[MotionParam {
            name: "backlash",
            unit: "rad",
            lo: 0.0,
            hi: 0.06,
            start: 0.005,
            second_start: 0.03,
            // Two encoder steps: less is within the encoder's resolution.
            negligible: 2.0 * RAD_PER_STEP,
            resolution_floor: false,
        }],
        Effect::Stribeck => &[
            MotionParam {
                name: "stribeck_friction",
                unit: "N·m",
                lo: 0.0,
                // Breakaway friction up to a tenth of the STS3250's stall torque (4.9 N·m).
                hi: 0.5,
                start: 0.05,
                second_start: 0.2,
                negligible: 0.01,
                resolution_floor: false,
            },
            MotionParam {
                name: "stribeck_speed",
                unit: "rad/s",
                // One encoder step in 77 ms, a seventieth of a step per replay step.
                lo: 0.02,
                hi: 3.0,
                start: 0.3,
                second_start: 1.0,
                negligible: 0.0,
                resolution_floor: true,
            },
        ],
        Effect::LoadFriction => &[MotionParam {
            name: "load_friction_ratio",
            unit: "1",
            lo: 0.0,
            hi: 0.6,
            start: 0.05,
            second_start: 0.3,
            negligible: 0.02,
            resolution_floor: false,
        }],
        Effect::DirectionalFriction => &[
            MotionParam {
                name: "drive_friction_ratio",
                unit: "1",
                lo: 0.0,
                hi: 0.6,
                start: 0.05,
                second_start: 0.3,
                negligible: 0.02,
                resolution_floor: false,
            },
            MotionParam {
                name: "back_friction_ratio",
                unit: "1",
                lo: 0.0,
                hi: 0.6,
                start: 0.05,
                second_start: 0.3,
                negligible: 0.02,
                resolution_floor: false,
            },
        ],
        _ => &[],
    }
}

/// All of a model's parameters: Coulomb, viscous, then the extension's.
fn model_params(effect: Effect) -> Vec<MotionParam> {
    let mut v = vec![COULOMB, VISCOUS];
    v.extend_from_slice(extension_params(effect));
    v
}

/// The parameters of `effect` from a vector (in [`model_params`] order).
pub fn decode(effect: Effect, x: &[f64]) -> MotionParams {
    let mut p = MotionParams {
        coulomb_nm: x[0],
        viscous_nms: x[1],
        ext: ServoExtension::default(),
    };
    let e = &mut p.ext;
    match effect {
        Effect::ArmatureError => e.armature_error = x[2],
        Effect::FirmwareGain => e.duty_gain_error = x[2],
        Effect::Backlash => e.backlash_rad = x[2],
        Effect::Stribeck => {
            e.stribeck_nm = x[2];
            e.stribeck_speed_rad_s = x[3];
        }
        Effect::LoadFriction => {
            e.friction_drive_ratio = x[2];
            e.friction_back_ratio = x[2];
        }
        Effect::DirectionalFriction => {
            e.friction_drive_ratio = x[2];
            e.friction_back_ratio = x[3];
        }
        _ => {}
    }
    p
}

/// Nelder–Mead over the box of `params`, on `loss`, from `x0`; the best point.
fn nelder_mead(
    params: &[MotionParam],
    x0: &[f64],
    loss: &dyn Fn(&[f64]) -> f64,
    evaluations: usize,
) -> Vec<f64> {
    let n = params.len();
    let clamp = |x: &mut [f64]| {
        for (v, p) in x.iter_mut().zip(params) {
            *v = v.clamp(p.lo, p.hi);
        }
    };
    let mut simplex: Vec<(Vec<f64>, f64)> = Vec::with_capacity(n + 1);
    let mut x0 = x0.to_vec();
    clamp(&mut x0);
    simplex.push((x0.clone(), loss(&x0)));
    for (i, p) in params.iter().enumerate() {
        let mut x = x0.clone();
        // A fifth of the range, toward its wider side.
        let step = 0.2 * (p.hi - p.lo);
        x[i] = if p.hi - x[i] >= x[i] - p.lo {
            x[i] + step
        } else {
            x[i] - step
        };
        clamp(&mut x);
        let f = loss(&x);
        simplex.push((x, f));
    }
    let mut used = n + 1;
    while used < evaluations {
        simplex.sort_by(|a, b| a.1.total_cmp(&b.1));
        let worst = simplex[n].clone();
        let centroid: Vec<f64> = (0..n)
            .map(|j| simplex[..n].iter().map(|(x, _)| x[j]).sum::<f64>() / n as f64)
            .collect();
        let along = |t: f64| -> Vec<f64> {
            let mut x: Vec<f64> = (0..n)
                .map(|j| centroid[j] + t * (worst.0[j] - centroid[j]))
                .collect();
            clamp(&mut x);
            x
        };
        let r = along(-1.0);
        let fr = loss(&r);
        used += 1;
        if fr < simplex[0].1 {
            let e = along(-2.0);
            let fe = loss(&e);
            used += 1;
            simplex[n] = if fe < fr { (e, fe) } else { (r, fr) };
        } else if fr < simplex[n - 1].1 {
            simplex[n] = (r, fr);
        } else {
            let c = along(if fr < worst.1 { -0.5 } else { 0.5 });
            let fc = loss(&c);
            used += 1;
            if fc < worst.1.min(fr) {
                simplex[n] = (c, fc);
            } else {
                // Shrink toward the best.
                let best = simplex[0].0.clone();
                for (x, f) in simplex.iter_mut().skip(1) {
                    for j in 0..n {
                        x[j] = best[j] + 0.5 * (x[j] - best[j]);
                    }
                    *f = loss(x);
                    used += 1;
                }
            }
        }
    }
    simplex.sort_by(|a, b| a.1.total_cmp(&b.1));
    simplex.swap_remove(0).0
}

/// The mean over `runs` of their mean absolute error with `effect`'s parameters `x`, rad.
fn training_loss(rating: &ServoRating, effect: Effect, runs: &[&MotionRun], x: &[f64]) -> f64 {
    let p = decode(effect, x);
    runs.iter()
        .map(|r| errors(&simulate(rating, &p, r), r).0)
        .sum::<f64>()
        / runs.len().max(1) as f64
}

/// Fits `effect` (with Coulomb and viscous) on `runs` from `start` (in [`model_params`]
/// order): the parameter vector.
pub fn fit(rating: &ServoRating, effect: Effect, runs: &[&MotionRun], start: &[f64]) -> Vec<f64> {
    let params = model_params(effect);
    let loss = |x: &[f64]| training_loss(rating, effect, runs, x);
    // Two rounds, the second from a fresh simplex around the first's best: Nelder–Mead's
    // simplex collapses along the stick–slip's ridges, a restart frees it.
    let half = FIT_EVALUATIONS_PER_VERTEX * (params.len() + 1) / 2;
    let first = nelder_mead(&params, start, &loss, half);
    nelder_mead(&params, &first, &loss, half)
}

/// Fits `models` in order on `runs`, each extension from the nominal model's fitted friction
/// (and the directional friction from the load-proportional one's ratio, on both sides: the
/// larger model starts where the nested one ended), and again from its parameters' second
/// starts: the best on `runs` is kept.
fn fit_models(
    rating: &ServoRating,
    models: &[Effect],
    runs: &[&MotionRun],
) -> Vec<(Effect, Vec<f64>)> {
    let mut out: Vec<(Effect, Vec<f64>)> = Vec::new();
    for &effect in models {
        let defaults: Vec<f64> = model_params(effect).iter().map(|p| p.start).collect();
        let fitted = |e: Effect| out.iter().find(|(f, _)| *f == e).map(|(_, x)| x.clone());
        let start = match (effect, fitted(Effect::None), fitted(Effect::LoadFriction)) {
            (Effect::DirectionalFriction, _, Some(l)) => vec![l[0], l[1], l[2], l[2]],
            (Effect::None, _, _) | (_, None, _) => defaults,
            (_, Some(n), _) => [n[0], n[1]]
                .into_iter()
                .chain(defaults.into_iter().skip(2))
                .collect(),
        };
        let mut x = fit(rating, effect, runs, &start);
        let mut best = training_loss(rating, effect, runs, &x);
        // Again from every parameter's second start (for the nominal model: more friction,
        // from little the fit can stall where the load's stick-slip is half explained; a
        // hidden effect can pull the nominal fit there too, and an extension's fit from it
        // would stall with it), and an extension also from the nominal's fitted friction with
        // its own second start (its effect trading against the friction).
        let mut starts: Vec<Vec<f64>> = vec![model_params(effect)
            .iter()
            .map(|p| p.second_start)
            .collect()];
        if effect != Effect::None {
            starts.push(
                start
                    .iter()
                    .take(2)
                    .copied()
                    .chain(extension_params(effect).iter().map(|p| p.second_start))
                    .collect(),
            );
        }
        // A Stribeck peak hidden, the nominal model takes its breakaway as Coulomb friction
        // and drops the viscous (a broad peak fading over the speeds the joint moves at is
        // friction falling with speed): from there the peak's fits end at a fraction of its
        // size. Again with that friction moved into the peak: a quarter left as Coulomb, the
        // viscous and the peak's width from their own starts.
        if let (Effect::Stribeck, Some(n)) = (effect, fitted(Effect::None)) {
            starts.push(vec![
                0.25 * n[0],
                VISCOUS.start,
                0.75 * n[0],
                extension_params(effect)[1].start,
            ]);
        }
        for s in starts {
            let y = fit(rating, effect, runs, &s);
            let loss = training_loss(rating, effect, runs, &y);
            if loss < best {
                (x, best) = (y, loss);
            }
        }
        out.push((effect, x));
    }
    out
}

/// One model's held-out figures on one run.
#[derive(Debug, Clone, Serialize)]
pub struct HeldOutRun {
    /// The run.
    pub run: String,
    /// Mean absolute error, rad.
    pub mae_rad: f64,
    /// Root-mean-square error, rad.
    pub rmse_rad: f64,
    /// The parameters fitted without it, in [`extension_params`] order after Coulomb and viscous.
    pub parameters: Vec<f64>,
}

/// One motion model as tried.
#[derive(Debug, Clone, Serialize)]
pub struct MotionCandidate {
    /// The extension (`none`: the calibrated nominal model).
    pub id: Effect,
    /// Per held-out run.
    pub runs: Vec<HeldOutRun>,
    /// Mean held-out MAE, rad.
    pub mae_rad: f64,
    /// Relative reduction of the nominal model's mean held-out MAE.
    pub gain: f64,
    /// Held-out runs it improved.
    pub improved_runs: usize,
    /// Its parameters fitted on all runs, named, with units.
    pub parameters: Vec<crate::analysis::Parameter>,
    /// Every parameter strictly inside its physical range on every fold.
    pub plausible: bool,
    /// Supported, or the first test it failed.
    #[serde(flatten)]
    pub verdict: Verdict,
}

/// The motion channel's analysis.
#[derive(Debug, Clone, Serialize)]
pub struct MotionAnalysis {
    /// The servo model replayed.
    pub servo: String,
    /// The simulator's servo as configured (its rated friction), per run: MAE, RMSE, rad.
    pub as_configured: Vec<(String, f64, f64)>,
    /// Runs never held out: the only ones where the load moves free of the position loop
    /// (friction cannot be fitted without one).
    pub always_fitted: Vec<String>,
    /// The calibrated nominal model and every extension, on held-out runs.
    pub candidates: Vec<MotionCandidate>,
    /// The named cause: a motion extension, `none` or `unexplained`.
    pub cause: Effect,
    /// Mean held-out MAE of the calibrated nominal model, rad.
    pub nominal_mae_rad: f64,
    /// Mean held-out MAE of the best supported extension (or the nominal model's), rad.
    pub chosen_mae_rad: f64,
    /// The model the misfit left is judged with: the best supported extension, or `none`.
    pub chosen: Effect,
    /// The extension that, at a size within the servo's own tolerances (too small to be a
    /// finding), takes the misfit the chosen model leaves within the noise floor: the misfit
    /// is then that tolerance's, and `judged` is that extension's.
    pub within_tolerance: Option<Effect>,
    /// The misfit left with the chosen model (or with `within_tolerance`), against the
    /// positions' noise floor.
    pub judged: AgainstFloor,
    /// Mean time to simulate one run once, s.
    pub seconds_per_run: f64,
    /// Per run, the series behind the plots.
    #[serde(skip)]
    pub traces: Vec<MotionTrace>,
}

/// One run's positions: measured, the calibrated nominal model's and the chosen model's (both
/// fitted on all runs), rad.
#[derive(Debug, Clone)]
pub struct MotionTrace {
    /// The run.
    pub run: String,
    /// Sample times, s.
    pub t: Vec<f64>,
    /// The measured positions, rad.
    pub measured: Vec<f64>,
    /// The calibrated nominal model.
    pub nominal: Vec<f64>,
    /// The chosen model.
    pub chosen: Vec<f64>,
}

/// Whether a model's extension parameters `x` (in [`model_params`] order) lie inside what their
/// physics allows. One pinned at an edge is the fit asking for more than the physics gives (a
/// ratio of friction at 0, a side without friction, is physics, not an edge; nor is a floor of
/// what the data resolve: a Stribeck speed there is a breakaway sharper than the encoder and
/// the replay's steps show, still a Stribeck friction).
fn within_physics(params: &[MotionParam], x: &[f64]) -> bool {
    params.iter().zip(x).skip(2).all(|(p, v)| {
        let margin = 1e-3 * (p.hi - p.lo);
        let floor_ok = p.lo == 0.0 || p.resolution_floor;
        (*v > p.lo + margin || floor_ok && *v >= p.lo) && *v < p.hi - margin
    })
}

/// Whether a run lets the load move free of the position loop: torque released for at least
/// half a second while it moves.
fn moves_free(r: &MotionRun) -> bool {
    let mut free_s = 0.0;
    for k in 1..r.t.len() {
        let moved = (r.position[k] - r.position[k - 1]).abs() > RAD_PER_STEP;
        if !r.torque[k - 1] && moved {
            free_s += r.t[k] - r.t[k - 1];
        }
    }
    free_s >= 0.5
}

impl MotionAnalysis {
    /// What the misfit left was judged with, and how.
    pub fn judged(&self) -> String {
        match self.within_tolerance {
            Some(t) => format!(
                "after `{}` and `{t}` at a size within the servo's tolerances: {}",
                self.chosen, self.judged
            ),
            None => format!("after `{}`: {}", self.chosen, self.judged),
        }
    }

    /// Writes the supported motion extension (fitted on all runs) into the simulator's model
    /// file, with the friction calibrated beside it, the servo model and the held-out gain;
    /// the file's cause names every channel's. An extension supported with a misfit still
    /// left beyond the floor (`unexplained` beside it) is written, and said so: it predicts
    /// better on runs it did not see, which is what the simulator needs of it.
    pub fn write_extension(&self, m: &mut sim::extension::ModelExtension) {
        m.servo = Some(self.servo.clone());
        if !MOTION_CATALOG.contains(&self.chosen) {
            return;
        }
        let Some(c) = self.candidates.iter().find(|c| c.id == self.chosen) else {
            return;
        };
        m.motion_heldout_gain = Some(c.gain);
        m.motion_misfit_left = self.cause == Effect::Unexplained;
        let x: Vec<f64> = c.parameters.iter().map(|p| p.value).collect();
        let p = decode(self.chosen, &x);
        let e = p.ext;
        let id = self.chosen.id();
        m.cause = match m.cause.as_str() {
            "none" => id.to_string(),
            other if other.split('+').any(|c| c == id) => other.to_string(),
            other => format!("{other}+{id}"),
        };
        m.fitted_coulomb_nm = Some(p.coulomb_nm);
        m.fitted_viscous_nms = Some(p.viscous_nms);
        match self.chosen {
            Effect::ArmatureError => m.armature_error = Some(e.armature_error),
            Effect::FirmwareGain => m.duty_gain_error = Some(e.duty_gain_error),
            Effect::Backlash => m.backlash_rad = Some(e.backlash_rad),
            Effect::Stribeck => {
                m.stribeck_nm = Some(e.stribeck_nm);
                m.stribeck_speed_rad_s = Some(e.stribeck_speed_rad_s);
            }
            _ => {
                m.friction_drive_ratio = Some(e.friction_drive_ratio);
                m.friction_back_ratio = Some(e.friction_back_ratio);
            }
        }
    }
}

/// The motion catalog, in the order tried.
pub const MOTION_CATALOG: [Effect; 6] = [
    Effect::Stribeck,
    Effect::LoadFriction,
    Effect::DirectionalFriction,
    Effect::ArmatureError,
    Effect::FirmwareGain,
    Effect::Backlash,
];

/// Runs the motion channel on `runs` (at least two: each is held out in turn), or None.
pub fn analyze_motion(
    rating: &ServoRating,
    servo: &str,
    runs: &[MotionRun],
    candidates: &[Effect],
    progress: &mut dyn FnMut(&str),
) -> Option<MotionAnalysis> {
    if runs.len() < 2 {
        return None;
    }
    let (as_configured, seconds_per_run) = as_configured(rating, runs);
    let models: Vec<Effect> = std::iter::once(Effect::None)
        .chain(
            MOTION_CATALOG
                .into_iter()
                .filter(|e| candidates.contains(e)),
        )
        .collect();
    let held_out = held_out_runs(runs);
    if held_out.is_empty() {
        return None;
    }
    progress(&format!(
        "motion: fitting {} models on {} training sets",
        models.len(),
        held_out.len() + 1
    ));
    let fits = fit_training_sets(rating, &models, runs, &held_out);
    let fitted = |set: usize, effect: Effect| -> Vec<f64> {
        fits.get(set)
            .and_then(|f| f.iter().find(|(e, _)| *e == effect))
            .map_or_else(Vec::new, |(_, x)| x.clone())
    };
    let mut tried: Vec<MotionCandidate> = models
        .iter()
        .map(|&effect| {
            let held = held_out
                .iter()
                .enumerate()
                .map(|(set, &k)| held_out_run(rating, effect, fitted(set, effect), &runs[k]))
                .collect();
            MotionCandidate::of(effect, held, &fitted(held_out.len(), effect))
        })
        .collect();
    let (nominal, extensions) = tried.split_first_mut()?;
    for c in extensions.iter_mut() {
        c.judge_against(nominal);
    }
    let best = best_supported(extensions);
    let chosen = best.unwrap_or(&*nominal);
    let (chosen_id, chosen_mae, nominal_mae) = (chosen.id, chosen.mae_rad, nominal.mae_rad);
    // The misfit left, against the positions' noise floor (pooled over held-out runs).
    let floor = position_floor(runs, &held_out);
    let judge = |c: &MotionCandidate| {
        floor.judge_beyond(c.pooled_rmse(), 0.0, "rad", MOTION_PRACTICAL_MISFIT)
    };
    let mut judged = judge(chosen);
    // A misfit that an extension at a size within the servo's own tolerances takes within the
    // floor is that tolerance, not something unexplained.
    let within_tolerance = if judged.significant {
        extensions
            .iter()
            .filter(|c| matches!(c.verdict, Verdict::TooSmall { .. }))
            .map(|c| (c.id, judge(c)))
            .filter(|(_, j)| !j.significant)
            .min_by(|a, b| a.1.rmse.total_cmp(&b.1.rmse))
    } else {
        None
    };
    if let Some((_, j)) = within_tolerance {
        judged = j;
    }
    let cause = match (judged.significant, best.is_some()) {
        (true, _) => Effect::Unexplained,
        (false, true) => chosen_id,
        (false, false) => Effect::None,
    };
    let on_all = |effect: Effect| decode(effect, &fitted(held_out.len(), effect));
    let traces = traces(rating, runs, &on_all(Effect::None), &on_all(chosen_id));
    Some(MotionAnalysis {
        servo: servo.into(),
        as_configured,
        always_fitted: (0..runs.len())
            .filter(|k| !held_out.contains(k))
            .map(|k| runs[k].name.clone())
            .collect(),
        candidates: tried,
        cause,
        nominal_mae_rad: nominal_mae,
        chosen_mae_rad: chosen_mae,
        chosen: chosen_id,
        within_tolerance: within_tolerance.map(|(e, _)| e),
        judged,
        seconds_per_run,
        traces,
    })
}

/// The simulator's servo as configured (its rated friction) on each run: its name, MAE and
/// RMSE, rad; and the mean time one run's replay took, s.
fn as_configured(rating: &ServoRating, runs: &[MotionRun]) -> (Vec<(String, f64, f64)>, f64) {
    let nominal_rated = MotionParams {
        coulomb_nm: rating.coulomb_nm,
        viscous_nms: rating.viscous_nms,
        ext: ServoExtension::default(),
    };
    let t = std::time::Instant::now();
    let as_configured: Vec<(String, f64, f64)> = runs
        .iter()
        .map(|r| {
            let (mae, rmse) = errors(&simulate(rating, &nominal_rated, r), r);
            (r.name.clone(), mae, rmse)
        })
        .collect();
    let seconds_per_run = t.elapsed().as_secs_f64() / runs.len() as f64;
    (as_configured, seconds_per_run)
}

/// The runs that are held out, in turn. Friction shows where the load moves free of the
/// position loop (torque released): with the loop stiff, it hides behind the loop's gain. A
/// run is held out only if the runs left to fit on still include such a run; the only one is
/// never held out (its figures are then missing, and the report says so).
fn held_out_runs(runs: &[MotionRun]) -> Vec<usize> {
    let free: Vec<bool> = runs.iter().map(moves_free).collect();
    let free_count = free.iter().filter(|f| **f).count();
    (0..runs.len())
        .filter(|&k| free_count == 0 || free_count > usize::from(free[k]))
        .collect()
}

/// `models` fitted on every training set: each held-out run's complement, then all runs (the
/// last), on two threads (the sets are independent).
fn fit_training_sets(
    rating: &ServoRating,
    models: &[Effect],
    runs: &[MotionRun],
    held_out: &[usize],
) -> Vec<Vec<(Effect, Vec<f64>)>> {
    let sets: Vec<Vec<&MotionRun>> = held_out
        .iter()
        .map(|&k| {
            runs.iter()
                .enumerate()
                .filter(|(j, _)| *j != k)
                .map(|(_, r)| r)
                .collect()
        })
        .chain(std::iter::once(runs.iter().collect()))
        .collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let fits = std::sync::Mutex::new(vec![Vec::new(); sets.len()]);
    std::thread::scope(|scope| {
        for _ in 0..2 {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let Some(set) = sets.get(i) else {
                    break;
                };
                let f = fit_models(rating, models, set);
                if let Ok(mut all) = fits.lock() {
                    all[i] = f;
                }
            });
        }
    });
    fits.into_inner().unwrap_or_default()
}

/// The held-out `run` predicted by `effect`'s model with parameters `x` (fitted without it).
fn held_out_run(rating: &ServoRating, effect: Effect, x: Vec<f64>, run: &MotionRun) -> HeldOutRun {
    let (mae, rmse) = errors(&simulate(rating, &decode(effect, &x), run), run);
    HeldOutRun {
        run: run.name.clone(),
        mae_rad: mae,
        rmse_rad: rmse,
        parameters: x,
    }
}

impl MotionCandidate {
    /// Its held-out RMSE, pooled over its held-out runs, rad.
    pub fn pooled_rmse(&self) -> f64 {
        (self.runs.iter().map(|h| h.rmse_rad.powi(2)).sum::<f64>() / self.runs.len() as f64).sqrt()
    }

    /// `effect`'s model on its held-out runs `held`, with its parameters `x` fitted on all runs;
    /// not yet judged.
    fn of(effect: Effect, held: Vec<HeldOutRun>, x: &[f64]) -> MotionCandidate {
        let params = model_params(effect);
        let parameters = params
            .iter()
            .zip(x)
            .map(|(p, v)| crate::analysis::Parameter {
                name: p.name.into(),
                value: *v,
                unit: p.unit.into(),
            })
            .collect();
        let plausible = within_physics(&params, x)
            && held.iter().all(|h| within_physics(&params, &h.parameters));
        let mae = held.iter().map(|h| h.mae_rad).sum::<f64>() / held.len() as f64;
        MotionCandidate {
            id: effect,
            runs: held,
            mae_rad: mae,
            gain: 0.0,
            improved_runs: 0,
            parameters,
            plausible,
            verdict: Verdict::Nominal,
        }
    }

    /// Its gain over the calibrated `nominal` model, the runs it improved, and the first test
    /// of the module docs it fails (or `Supported`).
    fn judge_against(&mut self, nominal: &MotionCandidate) {
        self.gain = 1.0 - self.mae_rad / nominal.mae_rad;
        self.improved_runs = self
            .runs
            .iter()
            .zip(&nominal.runs)
            .filter(|(e, n)| e.mae_rad < n.mae_rad)
            .count();
        let step_gain = nominal.mae_rad - self.mae_rad;
        // Its size: the largest of its parameters that measure one, against what is negligible.
        let size = extension_params(self.id)
            .iter()
            .zip(self.parameters.iter().skip(2))
            .filter(|(p, _)| p.negligible > 0.0)
            .map(|(p, v)| (p, v.value))
            .max_by(|a, b| (a.1.abs() / a.0.negligible).total_cmp(&(b.1.abs() / b.0.negligible)));
        // A directional friction's two sides (driving, back-driven).
        let sides = (self.id == Effect::DirectionalFriction)
            .then(|| self.parameters.get(2..4))
            .flatten()
            .map(|p| (p[0].value, p[1].value));
        self.verdict = if !self.plausible {
            Verdict::AtPhysicsEdge
        } else if let Some((p, v)) = size.filter(|(p, v)| v.abs() < p.negligible) {
            Verdict::TooSmall {
                name: p.name,
                value: v,
                below: p.negligible,
                unit: p.unit,
            }
        } else if let Some((drive, back)) =
            sides.filter(|(d, b)| (d - b).abs() < DIRECTIONAL_MIN_ASYMMETRY * d.max(*b))
        {
            Verdict::OneFriction { drive, back }
        } else if !(self.gain >= MOTION_PRACTICAL_GAIN && step_gain >= MOTION_MIN_MAE_CUT) {
            Verdict::NoPracticalMaeCut {
                nominal_mae: nominal.mae_rad,
                mae: self.mae_rad,
                gain: self.gain,
            }
        } else if 2 * self.improved_runs <= self.runs.len() {
            Verdict::FewRunsBetter {
                improved: self.improved_runs,
                runs: self.runs.len(),
            }
        } else {
            Verdict::Supported
        };
    }
}

/// The supported extension with the largest gain. The directional friction holds the
/// load-proportional one (equal sides): it is named only where it predicts better than that
/// by what matters.
fn best_supported(extensions: &[MotionCandidate]) -> Option<&MotionCandidate> {
    let best = extensions
        .iter()
        .filter(|c| c.verdict.supported())
        .max_by(|a, b| a.gain.total_cmp(&b.gain));
    if let Some(d) = best.filter(|c| c.id == Effect::DirectionalFriction) {
        if let Some(l) = extensions
            .iter()
            .find(|c| c.id == Effect::LoadFriction && c.verdict.supported())
        {
            let cut = l.mae_rad - d.mae_rad;
            if cut < MOTION_PRACTICAL_GAIN * l.mae_rad || cut < MOTION_MIN_MAE_CUT {
                return Some(l);
            }
        }
    }
    best
}

/// The positions' noise floor on the held-out runs: the encoder's step and the readings'
/// noise where the servo stood still (a run's second differences while it moves measure the
/// motion: 53 steps on fast real STS3250 runs).
fn position_floor(runs: &[MotionRun], held_out: &[usize]) -> NoiseFloor {
    let series: Vec<Vec<f64>> = held_out.iter().map(|&k| runs[k].position.clone()).collect();
    NoiseFloor::at_rest(&series, RAD_PER_STEP)
}

/// Each run's positions: measured, and replayed by the calibrated nominal model and the
/// chosen one (both fitted on all runs).
fn traces(
    rating: &ServoRating,
    runs: &[MotionRun],
    nominal: &MotionParams,
    chosen: &MotionParams,
) -> Vec<MotionTrace> {
    runs.iter()
        .map(|r| MotionTrace {
            run: r.name.clone(),
            t: r.t.clone(),
            measured: r.position.clone(),
            nominal: simulate(rating, nominal, r),
            chosen: simulate(rating, chosen, r),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A Stribeck speed pinned at its floor (what the data resolve) is still a Stribeck
    /// friction; at its ceiling, or a negative inertia error at its lower edge, the fit asks
    /// for more than the physics gives. (Refused at the floor, a Stribeck seed was left `none`.)
    #[test]
    fn only_a_resolution_floor_is_no_edge_of_physics() {
        let stribeck = model_params(Effect::Stribeck);
        let speed = extension_params(Effect::Stribeck)[1];
        assert!(within_physics(&stribeck, &[0.1, 0.05, 0.2, speed.lo]));
        assert!(within_physics(&stribeck, &[0.1, 0.05, 0.2, 0.5]));
        assert!(!within_physics(&stribeck, &[0.1, 0.05, 0.2, speed.hi]));
        assert!(!within_physics(
            &stribeck,
            &[0.1, 0.05, 0.2, speed.lo - 1e-3]
        ));
        // A friction ratio of 0 is physics (no such friction); an armature error at its
        // lower bound is the fit asking for a lighter rotor than any.
        assert!(within_physics(
            &model_params(Effect::LoadFriction),
            &[0.1, 0.05, 0.0]
        ));
        let armature = extension_params(Effect::ArmatureError)[0];
        let armature_params = model_params(Effect::ArmatureError);
        assert!(!within_physics(&armature_params, &[0.1, 0.05, armature.lo]));
        assert!(within_physics(&armature_params, &[0.1, 0.05, 0.0]));
    }
}
