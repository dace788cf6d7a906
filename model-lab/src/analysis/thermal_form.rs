//! The thermal channel's form ([`crate::form`]): the nominal model's residual (reading −
//! prediction) regressed on the library's terms over the whole record, each term passed
//! through the motor's own first-order dynamics. A term g missing from τ·dT/dt = … + g shows in
//! the temperature as g filtered by 1/(1 + τs), so the regression is linear in the terms'
//! coefficients. The nominal model's own terms (its idle temperature, its copper gain, its time
//! constant) are refitted with every candidate: a form must beat the nominal model fitted on
//! every block, not only the one fitted on the first part.

use super::*;
use crate::form::{self, Entry, FoldGrams, Form, Term, FOLDS};

/// Times a change of regime is tried at: every 1/`STEP_GRID` of the record, from the end of
/// its first block of time to the start of its last (a change inside the first or last block
/// is seen by one block alone: no held-out block can confirm it).
const STEP_GRID: usize = 60;
/// Lags of the lagged copper-loss terms, s.
const LAGS_S: [f64; 2] = [60.0, 300.0];
/// The nominal model's own terms, refitted with every candidate: 1, I² and its right-hand
/// side (a change of the idle temperature, of the copper gain, of the time constant).
const NOMINAL_TERMS: usize = 3;

/// One motor's variables at one sample, from which every term's value follows.
struct Sample {
    rise: f64,
    current: f64,
    voltage: f64,
    speed: f64,
    t_s: f64,
    hours: f64,
    lagged: [f64; 2],
    neighbours: f64,
    rate: f64,
}

impl Sample {
    fn value(&self, term: Term) -> f64 {
        let (i, dt) = (self.current, self.rise);
        let after = |at: f64| if self.t_s >= at { 1.0 } else { 0.0 };
        match term {
            Term::Rise { power } => dt.powi(i32::from(power)),
            Term::Current => i,
            Term::CurrentMagnitude => i.abs(),
            Term::CurrentSquaredTimesRise => i * i * dt,
            Term::CurrentFourth => i.powi(4),
            Term::Voltage => self.voltage,
            Term::VoltageTimesCurrentSquared => self.voltage * i * i,
            Term::Speed => self.speed.abs(),
            Term::SpeedSquared => self.speed * self.speed,
            Term::Time => self.hours,
            Term::LaggedCurrentSquared { lag_s } => LAGS_S
                .iter()
                .position(|&l| l == lag_s)
                .map_or(0.0, |j| self.lagged[j]),
            Term::NeighbourDifference => self.neighbours,
            Term::TemperatureRate => self.rate,
            Term::StepAt { at_s } => after(at_s),
            Term::RiseAfter { at_s } => dt * after(at_s),
            Term::CurrentSquaredAfter { at_s } => i * i * after(at_s),
        }
    }
}

/// A channel of the dataset, held over gaps, for the thermal motors; None when fewer than half
/// the samples carry it or it never changes.
fn held_channel(channel: &[Vec<f64>], td: &ThermalData) -> Option<Vec<Vec<f64>>> {
    let len = td.t.len();
    let usable = td.motors.iter().all(|&dm| {
        let x = &channel[dm];
        let finite: Vec<f64> = x.iter().copied().filter(|v| v.is_finite()).collect();
        2 * finite.len() >= len && finite.iter().any(|&v| v != finite[0])
    });
    usable.then(|| {
        td.motors
            .iter()
            .map(|&dm| electrical::hold(&channel[dm]))
            .collect()
    })
}

/// The library the data allow: voltage and speed terms only where the data carry them, the
/// neighbours only on chains, a change of regime at every time of the grid.
fn library(td: &ThermalData, voltage: bool, speed: bool) -> Vec<Term> {
    let mut lib = vec![
        Term::Rise { power: 2 },
        Term::Rise { power: 3 },
        Term::Current,
        Term::CurrentMagnitude,
        Term::CurrentSquaredTimesRise,
        Term::CurrentFourth,
        Term::Time,
        Term::TemperatureRate,
    ];
    lib.extend(LAGS_S.map(|lag_s| Term::LaggedCurrentSquared { lag_s }));
    if voltage {
        lib.extend([Term::Voltage, Term::VoltageTimesCurrentSquared]);
    }
    if speed {
        lib.extend([Term::Speed, Term::SpeedSquared]);
    }
    if td.neighbours.iter().any(|n| !n.is_empty()) {
        lib.push(Term::NeighbourDifference);
    }
    let (t0, t1) = (
        td.t.first().copied().unwrap_or(0.0),
        td.t.last().copied().unwrap_or(0.0),
    );
    for g in (STEP_GRID / FOLDS)..(STEP_GRID - STEP_GRID / FOLDS) {
        let at_s = (t0 + (t1 - t0) * g as f64 / STEP_GRID as f64).round();
        lib.extend([
            Term::StepAt { at_s },
            Term::RiseAfter { at_s },
            Term::CurrentSquaredAfter { at_s },
        ]);
    }
    lib
}

/// The library as candidates, the terms of column `base + i`: each term alone, and a change
/// of regime at each time as the nominal model's three terms changing together (its idle
/// temperature, its cooling, its heating).
fn entries(lib: &[Term], base: usize) -> Vec<Entry> {
    let mut out: Vec<Entry> = lib
        .iter()
        .enumerate()
        .map(|(i, &t)| Entry::single(base + i, t))
        .collect();
    for &t in lib {
        if let Term::StepAt { at_s } = t {
            let regime = [
                t,
                Term::RiseAfter { at_s },
                Term::CurrentSquaredAfter { at_s },
            ];
            let columns: Option<Vec<usize>> = regime
                .iter()
                .map(|r| lib.iter().position(|u| u == r).map(|j| base + j))
                .collect();
            if let Some(columns) = columns {
                out.push(Entry {
                    columns,
                    terms: regime.to_vec(),
                });
            }
        }
    }
    out
}

/// I² of motor `m` `lag` seconds before sample `k`, within its segment starting at `s`.
fn lagged_squared(td: &ThermalData, m: usize, s: usize, k: usize, lag: f64) -> f64 {
    let j = td.t[s..=k].partition_point(|&t| t <= td.t[k] - lag);
    let i = td.current[m][s + j.saturating_sub(1)];
    i * i
}

/// The form of the thermal channel's nominal misfit over the whole record. The terms are built
/// from the nominal model's prediction, never from the readings (whose own residual would then
/// explain itself on the held-out blocks); once a form is found, the search runs again with the
/// temperature that form predicts (one Gauss–Newton step: a change of cooling acts on the
/// temperature the change itself raised).
pub(super) fn thermal_form(
    d: &Dataset,
    td: &ThermalData,
    nominal: &ThermalFit,
    pred: &[Vec<f64>],
) -> Form {
    let design = Design::new(d, td, nominal);
    let first = design.search(pred, pred);
    if !first.found() {
        return first;
    }
    let mut seen = pred.to_vec();
    design.rows(pred, pred, |m, k, row| {
        let correction: f64 = first.fitted.iter().map(|&(c, b)| row[c] * b).sum();
        seen[m][k] = pred[m][k] + correction;
    });
    design.search(pred, &seen)
}

/// The design of the thermal form's regression: what its rows are computed from.
struct Design<'a> {
    td: &'a ThermalData,
    params: crate::thermal::ThermalParams,
    lib: Vec<Term>,
    /// Supply voltage about its mean and shaft speed, per motor, where the data carry them.
    voltage: Option<Vec<Vec<f64>>>,
    speed: Option<Vec<Vec<f64>>>,
}

impl<'a> Design<'a> {
    fn new(d: &Dataset, td: &'a ThermalData, nominal: &ThermalFit) -> Design<'a> {
        let voltage = held_channel(&d.voltage, td).map(|v| {
            v.into_iter()
                .map(|x| {
                    let mean = stats::mean(&x);
                    x.into_iter().map(|v| v - mean).collect()
                })
                .collect()
        });
        let speed = held_channel(&d.velocity, td);
        Design {
            td,
            params: ThermalModel::new(td, Effect::None).decode(&nominal.p),
            lib: library(td, voltage.is_some(), speed.is_some()),
            voltage,
            speed,
        }
    }

    /// The search with the terms seeing the temperature `seen`.
    fn search(&self, pred: &[Vec<f64>], seen: &[Vec<f64>]) -> Form {
        let base = NOMINAL_TERMS * self.td.n();
        let mut grams = FoldGrams::new(base + self.lib.len());
        let len = self.td.t.len();
        self.rows(pred, seen, |m, k, row| {
            let reading = self.td.measured[m][k];
            if reading.is_finite() {
                grams.add(k * FOLDS / len, row, reading - pred[m][k]);
            }
        });
        let always: Vec<usize> = (0..base).collect();
        form::select(
            &grams,
            &always,
            &entries(&self.lib, base),
            Channel::Thermal,
            "°C",
        )
    }

    /// Calls `visit(motor, sample, row)` with the design's row at every sample: the nominal
    /// model's own terms in the motor's columns, then the library's, each passed through the
    /// motor's lag (but dT/dt, which a lagging sensor adds to the readings).
    fn rows(
        &self,
        pred: &[Vec<f64>],
        seen: &[Vec<f64>],
        mut visit: impl FnMut(usize, usize, &[f64]),
    ) {
        let (td, lib) = (self.td, &self.lib);
        let n = td.n();
        let base = NOMINAL_TERMS * n;
        let t0 = td.t.first().copied().unwrap_or(0.0);
        let width = NOMINAL_TERMS + lib.len();
        let (mut state, mut before, mut now) =
            (vec![0.0; width], vec![0.0; width], vec![0.0; width]);
        let mut row = vec![0.0; base + lib.len()];
        for m in 0..n {
            let p = &self.params;
            let (tau, idle, gain) = (p.tau_s[m], p.idle_c[m], p.gain_k_per_a2[m]);
            for &(s, e) in &td.segments {
                state.fill(0.0);
                for k in s..e {
                    let i = td.current[m][k];
                    let nb = &td.neighbours[m];
                    let sample = Sample {
                        rise: seen[m][k] - idle,
                        current: i,
                        voltage: self.voltage.as_ref().map_or(0.0, |v| v[m][k]),
                        speed: self.speed.as_ref().map_or(0.0, |w| w[m][k]),
                        t_s: td.t[k],
                        hours: (td.t[k] - t0) / 3600.0,
                        lagged: LAGS_S.map(|lag| lagged_squared(td, m, s, k, lag)),
                        neighbours: if nb.is_empty() {
                            0.0
                        } else {
                            nb.iter().map(|&j| pred[j][k]).sum::<f64>() / nb.len() as f64
                                - pred[m][k]
                        },
                        rate: if k > s {
                            (pred[m][k] - pred[m][k - 1]) / (td.t[k] - td.t[k - 1]).max(1e-9)
                        } else {
                            0.0
                        },
                    };
                    now[0] = 1.0;
                    now[1] = i * i;
                    now[2] = idle + gain * i * i - pred[m][k];
                    for (j, &term) in lib.iter().enumerate() {
                        now[NOMINAL_TERMS + j] = sample.value(term);
                    }
                    if k > s {
                        // Zero-order hold over the interval, as the nominal model integrates.
                        let a = (-(td.t[k] - td.t[k - 1]) / tau).exp();
                        for (x, b) in state.iter_mut().zip(&before) {
                            *x = a * *x + (1.0 - a) * b;
                        }
                    }
                    std::mem::swap(&mut before, &mut now);
                    row.fill(0.0);
                    row[NOMINAL_TERMS * m..NOMINAL_TERMS * (m + 1)]
                        .copy_from_slice(&state[..NOMINAL_TERMS]);
                    for (j, &term) in lib.iter().enumerate() {
                        row[base + j] = if term == Term::TemperatureRate {
                            before[NOMINAL_TERMS + j]
                        } else {
                            state[NOMINAL_TERMS + j]
                        };
                    }
                    visit(m, k, &row);
                }
            }
        }
    }
}
