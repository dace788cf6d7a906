//! The thermal channel: the nominal one-node model, its extensions, simulation and fitting.
//!
//! Per motor the nominal model is C·dT/dt = P0 + R·I² − (T − T_amb)/R_th. From temperature and
//! current alone only three combinations are identifiable, so it is fitted in the reduced form
//!
//! ```text
//! τ·dT/dt = T_idle + k·I² − T      τ = R_th·C,  k = R·R_th (K/A²),  T_idle = T_amb + P0·R_th
//! ```
//!
//! integrated exactly over each sample interval with the current held (zero-order hold).
//! Predictions are open-loop: from the segment's initial temperature (a fitted parameter) and the
//! measured currents only, never from past temperature readings, so an error in the dynamics
//! accumulates and shows. The register reads round(T): the nominal model is first fitted by
//! least squares (the rounding taken for zero-mean noise of variance q²/12), then refitted, like
//! every extension, on the register's own likelihood ([`Register`]), which knows a reading of
//! 31 means T + noise in [30.5, 31.5).

use crate::catalog::Effect;
use crate::fit::{levenberg_marquardt, Fitted, Problem};
use crate::register::Register;
use nalgebra::{DMatrix, DVector};

/// Reference temperature of the winding resistance (k is the gain at this temperature), °C.
pub const TEMPCO_REFERENCE_C: f64 = 25.0;

/// Inputs and readings of the motors the thermal channel can use.
#[derive(Debug, Clone)]
pub struct ThermalData {
    /// Sample times, s.
    pub t: Vec<f64>,
    /// Segments as `(start, end)` sample indices.
    pub segments: Vec<(usize, usize)>,
    /// First held-out sample.
    pub split: usize,
    /// Dataset motor index of each thermal motor.
    pub motors: Vec<usize>,
    /// Current, A, with missing samples held from the previous one.
    pub current: Vec<Vec<f64>>,
    /// Temperature readings, °C, NaN where missing or rejected.
    pub measured: Vec<Vec<f64>>,
    /// Neighbours on the chain, as thermal motor indices.
    pub neighbours: Vec<Vec<usize>>,
    /// Valid reading indices in the fitting part.
    pub fit_idx: Vec<Vec<usize>>,
    /// Valid reading indices in the held-out part.
    pub held_idx: Vec<Vec<usize>>,
    /// Segments that start in the fitting part (their initial temperatures are fitted).
    pub fit_segments: usize,
    /// Initial temperature of each motor in each segment, from the first readings (used for
    /// segments that start in the held-out part).
    pub data_init: Vec<Vec<f64>>,
    /// Step of the temperature register, °C.
    pub quantum: f64,
}

/// Parameters of a thermal model, decoded.
#[derive(Debug, Clone)]
pub struct ThermalParams {
    /// The extension's parameter, in the catalog's unit (NaN for none).
    pub extension: f64,
    /// The second extension's (of a pair), NaN without one.
    pub second_extension: f64,
    /// Per motor: time constant τ, s.
    pub tau_s: Vec<f64>,
    /// Per motor: copper-loss gain k = R·R_th, K/A².
    pub gain_k_per_a2: Vec<f64>,
    /// Per motor: idle equilibrium T_amb + P0·R_th, °C.
    pub idle_c: Vec<f64>,
}

/// One thermal model (nominal, extended, or extended by a pair) over one data set.
pub struct ThermalModel<'a> {
    data: &'a ThermalData,
    /// The extensions (none, one or two), their parameters first in the vector, in order.
    effects: Vec<Effect>,
    /// Fit up to this sample (exclusive).
    until: usize,
    /// Fit the register's deviance residuals (None: plain prediction − reading).
    register: Option<&'a Register>,
}

const BOUNDS_LN_TAU: (f64, f64) = (0.0, 14.0); // 1 s .. 1.2e6 s

fn is_extension(effect: Effect) -> bool {
    effect.channel() == crate::catalog::Channel::Thermal
        && !matches!(effect, Effect::None | Effect::Unexplained)
}

/// Admissible range of the extension parameter in its fitted form. Sensor lag is fitted as
/// ln τ_s; the others in their catalog units.
fn ext_bounds(effect: Effect) -> (f64, f64) {
    match effect {
        Effect::SensorLag => (0.0, 10.0),
        // A conductance: heat flows down the temperature difference, never up it.
        Effect::NeighborCoupling => (0.0, 5.0),
        Effect::CopperTempco => (-3.0, 3.0),
        Effect::AmbientDrift => (-50.0, 50.0),
        Effect::CurrentOffset => (-5.0, 5.0),
        _ => (0.0, 0.0),
    }
}

/// Starting values of the extension parameter (fitted form) tried before refining.
fn ext_starts(effect: Effect) -> &'static [f64] {
    match effect {
        // ln 3 s .. ln 600 s.
        Effect::SensorLag => &[1.1, 3.0, 4.1, 5.3, 6.4],
        Effect::NeighborCoupling => &[0.0, 0.3, 1.0],
        Effect::CopperTempco => &[0.0, 0.5, -0.5],
        Effect::AmbientDrift => &[0.0],
        Effect::CurrentOffset => &[0.0, 0.3, -0.3],
        _ => &[0.0],
    }
}

/// ẋ = a − λx over `dt`, exactly.
#[inline]
fn lin_step(x: f64, a: f64, lambda: f64, dt: f64) -> f64 {
    let z = lambda * dt;
    if z.abs() < 1e-9 {
        x + (a - lambda * x) * dt
    } else {
        let xinf = a / lambda;
        xinf + (x - xinf) * (-z).exp()
    }
}

impl ThermalData {
    /// Number of thermal motors.
    pub fn n(&self) -> usize {
        self.motors.len()
    }

    /// Parameters per motor block: ln τ, k, T_idle and one initial temperature per fitted segment.
    pub fn block_len(&self) -> usize {
        3 + self.fit_segments
    }

    /// Readings in the fitting part, all motors.
    pub fn fit_count(&self) -> usize {
        self.fit_idx.iter().map(Vec::len).sum()
    }
}

impl<'a> ThermalModel<'a> {
    /// A model of `effect` over `data`, fitted on the fitting part.
    pub fn new(data: &'a ThermalData, effect: Effect) -> Self {
        Self::composed(data, &[effect])
    }

    /// A model carrying every extension of `effects` at once (the catalog composes: each adds
    /// its term to the same equation), fitted on the fitting part.
    pub fn composed(data: &'a ThermalData, effects: &[Effect]) -> Self {
        ThermalModel {
            data,
            effects: effects
                .iter()
                .copied()
                .filter(|e| is_extension(*e))
                .collect(),
            until: data.split,
            register: None,
        }
    }

    /// The parameter of `effect` in `p`, if the model carries it.
    fn ext(&self, p: &[f64], effect: Effect) -> Option<f64> {
        self.effects.iter().position(|e| *e == effect).map(|i| p[i])
    }

    /// The same model, fitted on the register's likelihood.
    pub fn with_register(mut self, register: &'a Register) -> Self {
        self.register = Some(register);
        self
    }

    #[inline]
    fn residual(&self, prediction: f64, reading: f64) -> f64 {
        let e = prediction - reading;
        self.register.map_or(e, |r| r.residual(e))
    }

    fn block<'p>(&self, p: &'p [f64], m: usize) -> &'p [f64] {
        let s = self.effects.len() + m * self.data.block_len();
        &p[s..s + self.data.block_len()]
    }

    /// The winding's equation over one step for motor block `blk` at current `i` and mid-step
    /// time `tm` (s from the record's start): τ·dT/dt = a − λ·T, each extension adding its term.
    #[inline]
    fn drive(&self, p: &[f64], blk: &[f64], i: f64, tm: f64) -> (f64, f64) {
        let (k, tb) = (blk[1], blk[2]);
        let it = i - self.ext(p, Effect::CurrentOffset).unwrap_or(0.0);
        let q = k * it * it;
        let alpha = self.ext(p, Effect::CopperTempco).unwrap_or(0.0) / 100.0;
        let drift = self.ext(p, Effect::AmbientDrift).unwrap_or(0.0);
        (
            tb + drift * tm / 3600.0 + q * (1.0 - alpha * TEMPCO_REFERENCE_C),
            1.0 - alpha * q,
        )
    }

    /// Simulates the predicted reading of every motor for samples `0..until` into `y`.
    pub fn simulate(&self, p: &[f64], until: usize, y: &mut [Vec<f64>]) {
        if self.effects.contains(&Effect::NeighborCoupling) {
            self.simulate_coupled(p, until, y);
        } else {
            for (m, ym) in y.iter_mut().enumerate() {
                self.simulate_motor(p, m, until, ym);
            }
        }
    }

    fn initial(&self, blk: &[f64], m: usize, si: usize) -> f64 {
        if si < self.data.fit_segments {
            blk[3 + si]
        } else {
            self.data.data_init[m][si]
        }
    }

    /// One motor, for separable models.
    fn simulate_motor(&self, p: &[f64], m: usize, until: usize, y: &mut Vec<f64>) {
        let d = self.data;
        y.clear();
        y.resize(until, f64::NAN);
        let blk = self.block(p, m);
        let tau = blk[0].exp();
        let lag = self.ext(p, Effect::SensorLag).map(f64::exp);
        let t0 = d.t.first().copied().unwrap_or(0.0);
        let cur = &d.current[m];
        for (si, &(s, e)) in d.segments.iter().enumerate() {
            if s >= until {
                break;
            }
            let init = self.initial(blk, m, si);
            let (mut w, mut sens) = (init, init);
            y[s] = sens;
            for kk in s + 1..e.min(until) {
                let dt = d.t[kk] - d.t[kk - 1];
                let tm = 0.5 * (d.t[kk] + d.t[kk - 1]) - t0;
                let (a, lambda) = self.drive(p, blk, cur[kk - 1], tm);
                let w1 = lin_step(w, a / tau, lambda / tau, dt);
                sens = match lag {
                    // The sensor node follows the winding's average over the step.
                    Some(ts) => {
                        let e = (-dt / ts).exp();
                        sens * e + (1.0 - e) * 0.5 * (w + w1)
                    }
                    None => w1,
                };
                w = w1;
                y[kk] = sens;
            }
        }
    }

    /// All motors at once: heat flows to each neighbour in proportion to the temperature
    /// difference (κ = G·R_th), the neighbours' temperatures held over a step; any other
    /// extension of the model acts as in [`Self::simulate_motor`].
    fn simulate_coupled(&self, p: &[f64], until: usize, y: &mut [Vec<f64>]) {
        let d = self.data;
        let n = d.n();
        let kappa = self.ext(p, Effect::NeighborCoupling).unwrap_or(0.0);
        let lag = self.ext(p, Effect::SensorLag).map(f64::exp);
        let t0 = d.t.first().copied().unwrap_or(0.0);
        let mut sens = vec![0.0; n];
        for ym in y.iter_mut() {
            ym.clear();
            ym.resize(until, f64::NAN);
        }
        let mut w = vec![0.0; n];
        let mut w1 = vec![0.0; n];
        for (si, &(s, e)) in d.segments.iter().enumerate() {
            if s >= until {
                break;
            }
            for m in 0..n {
                w[m] = self.initial(self.block(p, m), m, si);
                sens[m] = w[m];
                y[m][s] = w[m];
            }
            for kk in s + 1..e.min(until) {
                let dt = d.t[kk] - d.t[kk - 1];
                let tm = 0.5 * (d.t[kk] + d.t[kk - 1]) - t0;
                for m in 0..n {
                    let blk = self.block(p, m);
                    let tau = blk[0].exp();
                    let nb = &d.neighbours[m];
                    let nb_sum: f64 = nb.iter().map(|&j| w[j]).sum();
                    let (a, lambda) = self.drive(p, blk, d.current[m][kk - 1], tm);
                    let a = a + kappa * nb_sum;
                    let lambda = lambda + kappa * nb.len() as f64;
                    w1[m] = lin_step(w[m], a / tau, lambda / tau, dt);
                }
                for m in 0..n {
                    sens[m] = match lag {
                        Some(ts) => {
                            let e = (-dt / ts).exp();
                            sens[m] * e + (1.0 - e) * 0.5 * (w[m] + w1[m])
                        }
                        None => w1[m],
                    };
                }
                std::mem::swap(&mut w, &mut w1);
                for (ym, sm) in y.iter_mut().zip(&sens) {
                    ym[kk] = *sm;
                }
            }
        }
    }

    /// Number of parameters.
    pub fn n_params(&self) -> usize {
        self.effects.len() + self.data.n() * self.data.block_len()
    }

    /// Decodes a parameter vector.
    pub fn decode(&self, p: &[f64]) -> ThermalParams {
        let n = self.data.n();
        let value = |i: usize| match self.effects.get(i) {
            None => f64::NAN,
            Some(Effect::SensorLag) => p[i].exp(),
            Some(_) => p[i],
        };
        ThermalParams {
            extension: value(0),
            second_extension: value(1),
            tau_s: (0..n).map(|m| self.block(p, m)[0].exp()).collect(),
            gain_k_per_a2: (0..n).map(|m| self.block(p, m)[1]).collect(),
            idle_c: (0..n).map(|m| self.block(p, m)[2]).collect(),
        }
    }

    /// Predicted readings over the whole record.
    pub fn predict(&self, p: &[f64]) -> Vec<Vec<f64>> {
        let mut y = vec![Vec::new(); self.data.n()];
        self.simulate(p, self.data.t.len(), &mut y);
        y
    }
}

impl Problem for ThermalModel<'_> {
    fn n_params(&self) -> usize {
        ThermalModel::n_params(self)
    }

    fn n_blocks(&self) -> usize {
        self.data.n()
    }

    fn param_block(&self, j: usize) -> Option<usize> {
        let e = self.effects.len();
        if j < e || self.effects.contains(&Effect::NeighborCoupling) {
            None
        } else {
            Some((j - e) / self.data.block_len())
        }
    }

    fn residuals(&self, p: &[f64], out: &mut [Vec<f64>]) {
        let mut y = vec![Vec::new(); self.data.n()];
        self.simulate(p, self.until, &mut y);
        for (m, o) in out.iter_mut().enumerate() {
            o.clear();
            o.extend(
                self.data.fit_idx[m]
                    .iter()
                    .map(|&k| self.residual(y[m][k], self.data.measured[m][k])),
            );
        }
    }

    fn block_residuals(&self, p: &[f64], b: usize, out: &mut Vec<f64>) {
        let mut y = Vec::new();
        self.simulate_motor(p, b, self.until, &mut y);
        out.clear();
        out.extend(
            self.data.fit_idx[b]
                .iter()
                .map(|&k| self.residual(y[k], self.data.measured[b][k])),
        );
    }

    fn clamp(&self, p: &mut [f64]) {
        let e = self.effects.len();
        for (i, &effect) in self.effects.iter().enumerate() {
            let (lo, hi) = ext_bounds(effect);
            p[i] = p[i].clamp(lo, hi);
        }
        for m in 0..self.data.n() {
            let s = e + m * self.data.block_len();
            p[s] = p[s].clamp(BOUNDS_LN_TAU.0, BOUNDS_LN_TAU.1);
        }
    }
}

/// Time constants tried to start the nominal fit (the model is linear in everything else).
const TAU_GRID_S: [f64; 12] = [
    20.0, 45.0, 90.0, 180.0, 350.0, 600.0, 1000.0, 1600.0, 2500.0, 4000.0, 7000.0, 15000.0,
];

/// A fitted thermal model.
#[derive(Debug, Clone)]
pub struct ThermalFit {
    /// The extension.
    pub effect: Effect,
    /// The second extension, fitted together with the first ([`fit_pair`]).
    pub second: Option<Effect>,
    /// Fitted parameter vector.
    pub p: Vec<f64>,
    /// Sum of squared residuals on the fitting part.
    pub sse: f64,
    /// LM iterations used.
    pub iterations: usize,
}

/// Fits the nominal model: for each motor and each τ of a grid, the best linear fit of k, T_idle
/// and the initial temperatures; the best τ then starts a joint Levenberg–Marquardt refinement.
pub fn fit_nominal(data: &ThermalData) -> ThermalFit {
    let model = ThermalModel::new(data, Effect::None);
    let bl = data.block_len();
    let mut p = vec![0.0; model.n_params()];
    for m in 0..data.n() {
        let idx = &data.fit_idx[m];
        let mut best = (f64::INFINITY, vec![0.0; bl]);
        for &tau in &TAU_GRID_S {
            // Unit responses: the prediction is linear in (k, T_idle, inits) for a fixed τ.
            let mut cols = Vec::with_capacity(bl - 1);
            for j in 1..bl {
                let mut q = vec![0.0; model.n_params()];
                q[m * bl] = tau.ln();
                q[m * bl + j] = 1.0;
                let mut y = Vec::new();
                model.simulate_motor(&q, m, data.split, &mut y);
                cols.push(y);
            }
            let a = DMatrix::from_fn(idx.len(), bl - 1, |r, c| cols[c][idx[r]]);
            let b = DVector::from_iterator(idx.len(), idx.iter().map(|&k| data.measured[m][k]));
            // Least squares through the normal equations with a small ridge (a segment without
            // readings leaves its initial temperature undetermined).
            let mut ata = a.transpose() * &a;
            for i in 0..ata.nrows() {
                ata[(i, i)] += 1e-9 * (1.0 + ata[(i, i)]);
            }
            let atb = a.transpose() * &b;
            let Some(ch) = ata.cholesky() else { continue };
            let x = ch.solve(&atb);
            let r = &a * &x - &b;
            let s = r.norm_squared();
            if s < best.0 {
                let mut blk = vec![tau.ln()];
                blk.extend(x.iter());
                best = (s, blk);
            }
        }
        p[m * bl..(m + 1) * bl].copy_from_slice(&best.1);
    }
    let f = levenberg_marquardt(&model, &p, 60);
    ThermalFit {
        effect: Effect::None,
        second: None,
        p: f.p,
        sse: f.sse,
        iterations: f.iterations,
    }
}

impl ThermalFit {
    /// The model this fit is of.
    pub fn model<'a>(&self, data: &'a ThermalData) -> ThermalModel<'a> {
        let effects: Vec<Effect> = std::iter::once(self.effect).chain(self.second).collect();
        ThermalModel::composed(data, &effects)
    }
}

/// Refits a least-squares nominal fit on the register's likelihood.
pub fn refit_nominal(data: &ThermalData, ls: &ThermalFit, register: &Register) -> ThermalFit {
    let model = ThermalModel::new(data, Effect::None).with_register(register);
    let f = levenberg_marquardt(&model, &ls.p, 60);
    ThermalFit {
        effect: Effect::None,
        second: None,
        p: f.p,
        sse: f.sse,
        iterations: ls.iterations + f.iterations,
    }
}

/// Most Levenberg–Marquardt iterations of an extension's refining fit (it stops earlier once
/// the squared error no longer improves).
const EXTENSION_MAX_ITERATIONS: usize = 200;

/// Fits an extension, starting from the nominal fit and a few values of the extension's
/// parameter (a short fit each), then refining the best start.
/// `register`: the likelihood the nominal fit was refitted on (None: least squares).
pub fn fit_extension(
    data: &ThermalData,
    nominal: &ThermalFit,
    effect: Effect,
    register: Option<&Register>,
) -> ThermalFit {
    let mut model = ThermalModel::new(data, effect);
    model.register = register;
    let mut best: Option<Fitted> = None;
    if !is_extension(effect) {
        return nominal.clone();
    }
    for &start in ext_starts(effect) {
        let mut p = vec![start];
        p.extend_from_slice(&nominal.p);
        let f = levenberg_marquardt(&model, &p, 8);
        if best.as_ref().is_none_or(|b| f.sse < b.sse) {
            best = Some(f);
        }
    }
    let start = best.map_or_else(
        || {
            let mut p = vec![0.0];
            p.extend_from_slice(&nominal.p);
            p
        },
        |b| b.p,
    );
    // Until it converges: a drift or a lag far from its start can need more than the pair's
    // 60 iterations (stopped at 60, a pair fitted from there "found" a second effect of
    // negligible size, the first merely converging beside it).
    let f = levenberg_marquardt(&model, &start, EXTENSION_MAX_ITERATIONS);
    ThermalFit {
        effect,
        second: None,
        p: f.p,
        sse: f.sse,
        iterations: f.iterations,
    }
}

/// Fits a pair of extensions at once, starting from their single fits' parameters (`first`
/// and `second`, each the extension's value followed by the nominal blocks) and the first's
/// motor constants.
pub fn fit_pair(
    data: &ThermalData,
    first: &ThermalFit,
    second: &ThermalFit,
    register: Option<&Register>,
) -> ThermalFit {
    let mut model = ThermalModel::composed(data, &[first.effect, second.effect]);
    model.register = register;
    let mut p = vec![first.p[0], second.p[0]];
    p.extend_from_slice(&first.p[1..]);
    let f = levenberg_marquardt(&model, &p, 60);
    ThermalFit {
        effect: first.effect,
        second: Some(second.effect),
        p: f.p,
        sse: f.sse,
        iterations: f.iterations,
    }
}
