//! Forms for what has no name: when no catalog entry explains a misfit, a sparse regression of
//! the residual over a library of candidate terms says what it looks like, never as a catalog
//! name.
//!
//! The regression is SINDy's question (which few terms of a library make up the missing
//! dynamics) asked by forward selection with held-out error, not by a threshold: terms enter
//! one at a time, each the one that lowers the cross-validated error most, and only while it
//! lowers it by [`MIN_TERM_GAIN`] over [`FOLDS`] contiguous blocks of time, and lowers it in
//! all but one of the blocks whose readings it touches, at least two ([`confirmed`]). A
//! library with a step at every candidate time makes a change of regime one more term. Every fit is solved from per-fold sums of products ([`FoldGrams`]), so a
//! candidate costs a small linear solve, not a pass over the data. Why this and not STLSQ is in
//! `docs/model-lab.md` ("A form for what has no name").

use crate::catalog::Channel;
use nalgebra::{DMatrix, DVector};
use serde::Serialize;

/// Contiguous blocks of time the held-out error is measured on, each held out in turn.
pub const FOLDS: usize = 5;
/// A form has at most this many terms (beyond the refit of the nominal model's own).
pub const MAX_TERMS: usize = 3;
/// The search refits the nominal model's own terms per motor with every candidate: beyond this
/// many motors (a robot has 19) its solves grow too large, and it is not run.
pub const MAX_MOTORS: usize = 32;
/// A term enters when it lowers the cross-validated RMSE by this fraction of what is left.
pub const MIN_TERM_GAIN: f64 = 0.05;
/// Whether a term lowering the error in `improved` of the `touched` blocks whose readings it
/// touches is confirmed: in all of them but one, and in two at least (a term one block alone
/// sees, a change of regime inside the last, cannot be held out on another).
pub fn confirmed(improved: usize, touched: usize) -> bool {
    improved <= touched && improved >= touched.saturating_sub(1).max(2)
}
/// Ridge on the standardised normal equations: keeps a column that is zero in a fold's
/// fitting blocks (a step after them) at a zero coefficient instead of a singular solve.
const RIDGE: f64 = 1e-9;

/// One candidate term of the thermal channel's missing dynamics (τ·dT/dt = nominal + Σ c·term).
/// ΔT is the temperature's rise above the motor's idle equilibrium, I the motor current, ΔV
/// the supply voltage's deviation from its mean, ω the shaft speed, t the time since the
/// record's start.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Term {
    /// ΔT to a power (2 or 3: the first power is the nominal model's own).
    Rise {
        /// The power.
        power: u8,
    },
    /// I, signed.
    Current,
    /// |I|.
    CurrentMagnitude,
    /// I²·ΔT.
    CurrentSquaredTimesRise,
    /// I⁴.
    CurrentFourth,
    /// ΔV.
    Voltage,
    /// ΔV·I².
    VoltageTimesCurrentSquared,
    /// |ω|.
    Speed,
    /// ω².
    SpeedSquared,
    /// t, h (a ramp).
    Time,
    /// I² a while ago.
    LaggedCurrentSquared {
        /// The lag, s.
        lag_s: f64,
    },
    /// The mean of the chain neighbours' temperatures minus the motor's.
    NeighbourDifference,
    /// dT/dt, in the readings rather than the dynamics (what a lagging sensor adds).
    TemperatureRate,
    /// A step: 1 from `at_s` on (the heat balance shifts at that time).
    StepAt {
        /// The time of the step, s.
        at_s: f64,
    },
    /// ΔT from `at_s` on (the cooling changes at that time).
    RiseAfter {
        /// The time of the change, s.
        at_s: f64,
    },
    /// I² from `at_s` on (the heating changes at that time).
    CurrentSquaredAfter {
        /// The time of the change, s.
        at_s: f64,
    },
}

impl Term {
    /// The term in its variables.
    pub fn formula(self) -> String {
        match self {
            Term::Rise { power: 2 } => "ΔT²".into(),
            Term::Rise { power: 3 } => "ΔT³".into(),
            Term::Rise { power } => format!("ΔT^{power}"),
            Term::Current => "I".into(),
            Term::CurrentMagnitude => "|I|".into(),
            Term::CurrentSquaredTimesRise => "I²·ΔT".into(),
            Term::CurrentFourth => "I⁴".into(),
            Term::Voltage => "ΔV".into(),
            Term::VoltageTimesCurrentSquared => "ΔV·I²".into(),
            Term::Speed => "|ω|".into(),
            Term::SpeedSquared => "ω²".into(),
            Term::Time => "t".into(),
            Term::LaggedCurrentSquared { lag_s } => format!("I²(t − {lag_s:.0} s)"),
            Term::NeighbourDifference => "(T_neighbours − T)".into(),
            Term::TemperatureRate => "dT/dt".into(),
            Term::StepAt { at_s } => format!("[t ≥ {at_s:.0} s]"),
            Term::RiseAfter { at_s } => format!("ΔT·[t ≥ {at_s:.0} s]"),
            Term::CurrentSquaredAfter { at_s } => format!("I²·[t ≥ {at_s:.0} s]"),
        }
    }

    /// The unit of the term's value.
    pub fn unit(self) -> &'static str {
        match self {
            Term::Rise { power: 2 } => "K²",
            Term::Rise { .. } => "K³",
            Term::Current | Term::CurrentMagnitude => "A",
            Term::CurrentSquaredTimesRise => "A²·K",
            Term::CurrentFourth => "A⁴",
            Term::Voltage => "V",
            Term::VoltageTimesCurrentSquared => "V·A²",
            Term::Speed => "rad/s",
            Term::SpeedSquared => "rad²/s²",
            Term::Time => "h",
            Term::LaggedCurrentSquared { .. } | Term::CurrentSquaredAfter { .. } => "A²",
            Term::NeighbourDifference | Term::RiseAfter { .. } => "K",
            Term::TemperatureRate => "K/s",
            Term::StepAt { .. } => "1",
        }
    }

    /// The time a change of regime happens, for the terms that are one.
    pub fn regime_change_s(self) -> Option<f64> {
        match self {
            Term::StepAt { at_s }
            | Term::RiseAfter { at_s }
            | Term::CurrentSquaredAfter { at_s } => Some(at_s),
            _ => None,
        }
    }
}

/// A term of a form with its coefficient (°C per unit of the term, in τ·dT/dt).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct FormTerm {
    /// The term.
    pub term: Term,
    /// Its coefficient, fitted on every block.
    pub coefficient: f64,
}

/// What the search found: the terms that entered (none: no form), with the held-out figures.
#[derive(Debug, Clone, Serialize)]
pub struct Form {
    /// The channel whose residual was searched.
    pub channel: Channel,
    /// The terms that entered, in the order they did.
    pub terms: Vec<FormTerm>,
    /// Terms in the library.
    pub library: usize,
    /// Readings the regression saw.
    pub readings: usize,
    /// Cross-validated RMSE with the nominal model's own terms refitted, nothing added.
    pub baseline_rmse: f64,
    /// Cross-validated RMSE with the form.
    pub rmse: f64,
    /// Unit of both.
    pub unit: &'static str,
    /// 1 − rmse / baseline_rmse.
    pub heldout_gain: f64,
    /// Blocks in which the form lowers the held-out error, of [`FOLDS`].
    pub folds_improved: usize,
    /// The best term that did not enter, with the gain it would have brought, the blocks it
    /// lowered the error in and the blocks it touches.
    pub best_refused: Option<(Term, f64, usize, usize)>,
    /// The fitted columns (the nominal model's own included) with their coefficients, to
    /// evaluate the fitted correction on a row of the design.
    #[serde(skip)]
    pub fitted: Vec<(usize, f64)>,
}

impl Form {
    /// A form was found.
    pub fn found(&self) -> bool {
        !self.terms.is_empty()
    }

    /// The time of the change of regime the form has, if any.
    pub fn regime_change_s(&self) -> Option<f64> {
        self.terms.iter().find_map(|t| t.term.regime_change_s())
    }

    /// The form's terms as a sum, e.g. `−0.0123·ΔT² + 0.41·I`.
    pub fn expression(&self) -> String {
        let mut s = String::new();
        for (i, t) in self.terms.iter().enumerate() {
            let sign = if t.coefficient < 0.0 { "−" } else { "+" };
            let sep = match (i, sign) {
                (0, "+") => String::new(),
                (0, _) => sign.into(),
                _ => format!(" {sign} "),
            };
            s += &format!(
                "{sep}{}·{}",
                three_significant(t.coefficient.abs()),
                t.term.formula()
            );
        }
        s
    }

    /// The answer as the lab gives it: the form and its held-out gain, or a change of regime.
    pub fn describe(&self) -> String {
        if !self.found() {
            return format!(
                "no form: no term of {} lowers the held-out error by {:.0} %, in all but one of \
                 the {} blocks of time it touches",
                self.library,
                100.0 * MIN_TERM_GAIN,
                FOLDS
            );
        }
        let gain = 100.0 * self.heldout_gain;
        match self.regime_change_s() {
            Some(at) => format!(
                "a change of regime at {at:.0} s: the residual follows {} (held-out gain {gain:.0} %)",
                self.expression()
            ),
            None => format!(
                "the residual follows {} (held-out gain {gain:.0} %)",
                self.expression()
            ),
        }
    }
}

/// `x` (≥ 0) to three significant digits: a ΔT³ coefficient is ten-thousandths of a kelvin.
fn three_significant(x: f64) -> String {
    let digits = if x > 0.0 && x.is_finite() {
        (2 - x.log10().floor() as i32).max(0) as usize
    } else {
        0
    };
    format!("{x:.digits$}")
}

/// Sums of products of a design's columns and its target, one set per block of time: any
/// subset of columns is fitted on any blocks, and scored on the others, from these alone.
#[derive(Debug, Clone)]
pub struct FoldGrams {
    cols: usize,
    /// Per block: the (cols + 1)² sums of x·xᵀ, the target last.
    grams: Vec<DMatrix<f64>>,
    rows: usize,
    /// The current row's nonzero columns (kept to reuse its allocation).
    nonzero: Vec<usize>,
}

/// The error of one set of columns, block by block.
#[derive(Debug, Clone)]
struct Scored {
    /// Held-out sum of squared errors per block.
    sse: Vec<f64>,
}

impl Scored {
    fn total(&self) -> f64 {
        self.sse.iter().sum()
    }
}

impl FoldGrams {
    /// Empty sums for `cols` columns.
    pub fn new(cols: usize) -> FoldGrams {
        FoldGrams {
            cols,
            grams: vec![DMatrix::zeros(cols + 1, cols + 1); FOLDS],
            rows: 0,
            nonzero: Vec::with_capacity(cols),
        }
    }

    /// Adds one row (its columns `x`, its target `y`) to block `fold`. Rows with a value that
    /// is not finite are left out. Only the row's nonzero columns are visited: a motor's own
    /// columns are zero on every other motor's rows.
    pub fn add(&mut self, fold: usize, x: &[f64], y: f64) {
        if x.len() != self.cols || !y.is_finite() || x.iter().any(|v| !v.is_finite()) {
            return;
        }
        let g = &mut self.grams[fold.min(FOLDS - 1)];
        let n = self.cols;
        self.nonzero.clear();
        self.nonzero.extend((0..n).filter(|&i| x[i] != 0.0));
        for (a, &i) in self.nonzero.iter().enumerate() {
            for &j in &self.nonzero[a..] {
                g[(i, j)] += x[i] * x[j];
            }
            g[(i, n)] += x[i] * y;
        }
        g[(n, n)] += y * y;
        self.rows += 1;
    }

    /// Rows added.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Entry (i, j) of block `b`'s sums (only the upper triangle is accumulated).
    fn at(&self, b: usize, i: usize, j: usize) -> f64 {
        let (i, j) = if i <= j { (i, j) } else { (j, i) };
        self.grams[b][(i, j)]
    }

    /// Fits `active` on every block but `held` (or on all with None): the coefficients.
    fn solve(&self, active: &[usize], held: Option<usize>) -> DVector<f64> {
        let k = active.len();
        if k == 0 {
            return DVector::zeros(0);
        }
        let y = self.cols;
        let sum = |i: usize, j: usize| -> f64 {
            (0..FOLDS)
                .filter(|&b| Some(b) != held)
                .map(|b| self.at(b, i, j))
                .sum()
        };
        let mut a = DMatrix::zeros(k, k);
        let mut g = DVector::zeros(k);
        for (r, &i) in active.iter().enumerate() {
            for (c, &j) in active.iter().enumerate() {
                a[(r, c)] = sum(i, j);
            }
            g[r] = sum(i, y);
        }
        // Standardised, so that one ridge suits columns of any unit.
        let scale: Vec<f64> = (0..k)
            .map(|r| {
                let d = a[(r, r)].sqrt();
                if d > 0.0 {
                    d
                } else {
                    1.0
                }
            })
            .collect();
        for r in 0..k {
            for c in 0..k {
                a[(r, c)] /= scale[r] * scale[c];
            }
            a[(r, r)] += RIDGE;
            g[r] /= scale[r];
        }
        let beta = match a.clone().cholesky() {
            Some(ch) => ch.solve(&g),
            None => a
                .svd(true, true)
                .solve(&g, 1e-12)
                .unwrap_or_else(|_| DVector::zeros(k)),
        };
        DVector::from_iterator(k, (0..k).map(|r| beta[r] / scale[r]))
    }

    /// Block `b`'s sum of squared errors with coefficients `beta` on `active`.
    fn sse(&self, b: usize, active: &[usize], beta: &DVector<f64>) -> f64 {
        let y = self.cols;
        let mut s = self.at(b, y, y);
        for (r, &i) in active.iter().enumerate() {
            s -= 2.0 * beta[r] * self.at(b, i, y);
            for (c, &j) in active.iter().enumerate() {
                s += beta[r] * beta[c] * self.at(b, i, j);
            }
        }
        s.max(0.0)
    }

    /// The blocks in whose readings any of `columns` is not zero.
    fn touched(&self, columns: &[usize]) -> Vec<bool> {
        (0..FOLDS)
            .map(|b| columns.iter().any(|&c| self.at(b, c, c) > 0.0))
            .collect()
    }

    /// `active` held out block by block.
    fn score(&self, active: &[usize]) -> Scored {
        Scored {
            sse: (0..FOLDS)
                .map(|b| self.sse(b, active, &self.solve(active, Some(b))))
                .collect(),
        }
    }
}

/// Blocks in which `new` has the smaller held-out error than `old`, among those `touched`.
fn improved(new: &Scored, old: &Scored, touched: &[bool]) -> usize {
    new.sse
        .iter()
        .zip(&old.sse)
        .zip(touched)
        .filter(|((n, o), t)| **t && n < o)
        .count()
}

/// RMSE of a score over `rows` readings.
fn rmse(s: &Scored, rows: usize) -> f64 {
    (s.total() / rows.max(1) as f64).sqrt()
}

/// One candidate of the library: its columns of the design and the terms they hold (a change
/// of regime enters as its level, its cooling and its heating together, at one time).
#[derive(Debug, Clone, PartialEq)]
pub struct Entry {
    /// Columns of the design.
    pub columns: Vec<usize>,
    /// The term of each column.
    pub terms: Vec<Term>,
}

impl Entry {
    /// A candidate of one column.
    pub fn single(column: usize, term: Term) -> Entry {
        Entry {
            columns: vec![column],
            terms: vec![term],
        }
    }
}

/// Forward selection over the library's entries, the columns `always` refitted with every
/// candidate: the form the held-out error supports.
pub fn select(
    grams: &FoldGrams,
    always: &[usize],
    library: &[Entry],
    channel: Channel,
    unit: &'static str,
) -> Form {
    let rows = grams.rows();
    let baseline = grams.score(always);
    let mut active: Vec<usize> = always.to_vec();
    let mut current = baseline.clone();
    let mut chosen: Vec<&Entry> = Vec::new();
    let mut best_refused = None;
    while chosen.len() < MAX_TERMS {
        // An entry sharing a column with one that entered (a step beside the change of regime
        // at its time) would enter that column twice.
        let best = library
            .iter()
            .filter(|e| !e.columns.iter().any(|c| active.contains(c)))
            .map(|e| {
                let mut with = active.clone();
                with.extend(&e.columns);
                (e, grams.score(&with))
            })
            .min_by(|a, b| a.1.total().total_cmp(&b.1.total()));
        let Some((entry, scored)) = best else { break };
        let gain = 1.0 - rmse(&scored, rows) / rmse(&current, rows).max(f64::MIN_POSITIVE);
        let touched = grams.touched(&entry.columns);
        let blocks = touched.iter().filter(|t| **t).count();
        let folds = improved(&scored, &current, &touched);
        if gain < MIN_TERM_GAIN || !confirmed(folds, blocks) {
            best_refused = Some((entry.terms[0], gain, folds, blocks));
            break;
        }
        chosen.push(entry);
        active.extend(&entry.columns);
        current = scored;
    }
    let beta = grams.solve(&active, None);
    let terms = chosen
        .iter()
        .flat_map(|e| &e.terms)
        .enumerate()
        .map(|(r, &term)| FormTerm {
            term,
            coefficient: beta[always.len() + r],
        })
        .collect();
    let (b, f) = (rmse(&baseline, rows), rmse(&current, rows));
    Form {
        channel,
        terms,
        library: library.len(),
        readings: rows,
        baseline_rmse: b,
        rmse: f,
        unit,
        heldout_gain: if b > 0.0 { 1.0 - f / b } else { 0.0 },
        folds_improved: improved(&current, &baseline, &[true; FOLDS]),
        best_refused,
        fitted: active.iter().copied().zip(beta.iter().copied()).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic pseudo-random sequence in [−1, 1).
    fn noise(seed: &mut u64) -> f64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    /// Rows whose target is 0.8·x² + noise, with x, a distractor, and an always-in constant.
    fn design(signal: f64) -> (FoldGrams, Vec<Entry>) {
        let mut g = FoldGrams::new(4);
        let mut seed = 7;
        let n = 2000;
        for k in 0..n {
            let x = 3.0 * (k as f64 / 97.0).sin();
            let distractor = noise(&mut seed);
            let y = 1.5 + signal * x * x + 0.3 * noise(&mut seed);
            g.add(k * FOLDS / n, &[1.0, x * x, distractor, x * x * x], y);
        }
        let lib = vec![
            Entry::single(1, Term::Rise { power: 2 }),
            Entry::single(2, Term::Current),
            Entry::single(3, Term::Rise { power: 3 }),
        ];
        (g, lib)
    }

    #[test]
    fn the_term_that_makes_the_residual_is_found_with_its_coefficient() {
        let (g, lib) = design(0.8);
        let f = select(&g, &[0], &lib, Channel::Thermal, "°C");
        assert_eq!(f.terms.len(), 1, "{f:?}");
        assert_eq!(f.terms[0].term, Term::Rise { power: 2 });
        assert!((f.terms[0].coefficient - 0.8).abs() < 0.02, "{f:?}");
        assert!(f.heldout_gain > 0.5 && f.folds_improved == FOLDS, "{f:?}");
        assert!(
            f.describe().starts_with("the residual follows 0.800·ΔT²"),
            "{}",
            f.describe()
        );
        assert_eq!(three_significant(0.000_312_4), "0.000312");
        assert_eq!(three_significant(2.437), "2.44");
    }

    #[test]
    fn noise_alone_has_no_form() {
        let (g, lib) = design(0.0);
        let f = select(&g, &[0], &lib, Channel::Thermal, "°C");
        assert!(!f.found(), "{f:?}");
        let (_, gain, _, _) = f.best_refused.unwrap();
        assert!(gain < MIN_TERM_GAIN);
        assert!(f.describe().starts_with("no form"));
    }

    /// A step inside the last block touches that block alone: whatever it does there, no other
    /// block can confirm it, and the blocks it does not touch do not count as confirming it.
    #[test]
    fn a_change_one_block_alone_sees_is_no_form() {
        let mut g = FoldGrams::new(2);
        let n = 1000;
        let mut seed = 5;
        for k in 0..n {
            let step = if k >= 900 { 1.0 } else { 0.0 };
            g.add(
                k * FOLDS / n,
                &[1.0, step],
                2.0 * step + 0.2 * noise(&mut seed),
            );
        }
        let lib = vec![Entry::single(1, Term::StepAt { at_s: 900.0 })];
        let f = select(&g, &[0], &lib, Channel::Thermal, "°C");
        assert!(!f.found(), "{f:?}");
        assert_eq!(f.best_refused.map(|r| r.3), Some(1));
        assert!(confirmed(4, 5) && confirmed(2, 2) && !confirmed(1, 2) && !confirmed(1, 1));
    }

    /// A step after every fitting block's end has a zero column there: the ridge keeps its
    /// coefficient at zero rather than failing, and a step inside the data is found.
    #[test]
    fn a_step_is_a_change_of_regime_at_its_time() {
        let mut g = FoldGrams::new(3);
        let n = 1000;
        let mut seed = 3;
        for k in 0..n {
            let t = k as f64;
            let step = |at: f64| if t >= at { 1.0 } else { 0.0 };
            let y = 2.0 * step(430.0) + 0.2 * noise(&mut seed);
            g.add(k * FOLDS / n, &[1.0, step(430.0), step(990.0)], y);
        }
        let lib = vec![
            Entry::single(1, Term::StepAt { at_s: 430.0 }),
            Entry::single(2, Term::StepAt { at_s: 990.0 }),
        ];
        let f = select(&g, &[0], &lib, Channel::Thermal, "°C");
        assert_eq!(f.regime_change_s(), Some(430.0), "{f:?}");
        assert!(f.describe().starts_with("a change of regime at 430 s"));
    }
}
