//! The statistical tests an extension must pass and the judgement that weighs them
//! ([`judge`]); the rules are set out in `docs/model-lab.md`, "Name the cause".

use super::*;
use crate::verdict::Regime;

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
pub(crate) const HELDOUT_SIZE: std::ops::RangeInclusive<f64> = 0.5..=2.0;

/// Contiguous blocks per motor of the block statistics (held-out slope, fitting-part score
/// variance): residuals are correlated within a block, roughly independent between blocks.
pub(super) const TEST_BLOCKS: usize = 10;

/// The [`TEST_BLOCKS`] contiguous index ranges a series of `len` samples is split into; none
/// when the series is shorter than that.
pub(super) fn test_blocks(len: usize) -> impl Iterator<Item = std::ops::Range<usize>> {
    let count = if len < TEST_BLOCKS { 0 } else { TEST_BLOCKS };
    (0..count).map(move |j| j * len / TEST_BLOCKS..(j + 1) * len / TEST_BLOCKS)
}

/// An extension's held-out correction (RMS) must reach this fraction of the noise floor to
/// matter (1 °C register: about 0.02 °C).
pub const PRACTICAL_OF_FLOOR: f64 = 0.05;

/// Where the nominal misfit is beyond the noise, an extension must cut the held-out RMSE by
/// at least this fraction to matter.
pub const PRACTICAL_GAIN: f64 = 0.05;

/// The significant, plausible single of `channel` with the largest ΔBIC (supported or not).
pub(super) fn strongest_significant(candidates: &[Candidate], channel: Channel) -> Option<Effect> {
    let alpha = ALPHA / Effect::CATALOG.len() as f64;
    candidates
        .iter()
        .filter(|c| {
            c.channel == channel
                && c.with.is_none()
                && c.plausible
                && c.p_value < alpha
                && c.delta_bic > 0.0
        })
        .max_by(|a, b| a.delta_bic.total_cmp(&b.delta_bic))
        .map(|c| c.id)
}

/// Whether the supported pair second `c` beats `than`: one supported on the fitting part
/// alone beats one that needed the held-out slope; among the first kind the larger ΔBIC wins,
/// among the second the smaller combined p-value (their ΔBIC, the fitting part's alone, is
/// what fell short).
pub(super) fn stronger_second(c: &Candidate, than: &Candidate) -> bool {
    match (c.with_heldout, than.with_heldout) {
        (false, true) => true,
        (true, false) => false,
        (false, false) => c.delta_bic > than.delta_bic,
        (true, true) => c.p_value < than.p_value,
    }
}

/// The fitting part's significance test of one extension.
#[derive(Debug, Clone, Copy)]
pub(super) struct FitTest {
    /// Likelihood-ratio statistic, corrected for dependent samples.
    pub(super) lr: f64,
    /// Effective sample size.
    pub(super) n_eff: f64,
    /// p-value.
    pub(super) p_value: f64,
    /// Parameters the test weighs (its χ² degrees of freedom and BIC penalty).
    pub(super) params: f64,
    /// The p-value combines the fitting part's with the held-out slope's (see
    /// [`FitTest::with_heldout`]): the BIC, a fitting-part criterion, does not apply.
    pub(super) with_heldout: bool,
}

impl FitTest {
    /// The same statistic weighing `params` parameters instead of one (a pair against the
    /// nominal model: two).
    pub(super) fn with_params(self, params: f64) -> FitTest {
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
    pub(super) fn with_heldout(self, slope_t: f64) -> FitTest {
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
pub(super) fn deviance_test(
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
pub(super) fn block_wald_test(base: &[Vec<f64>], ext: &[Vec<f64>]) -> FitTest {
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

/// One extension's evidence, as [`judge`] weighs it.
pub(super) struct Evidence<'a> {
    pub(super) effect: Effect,
    /// Its fitted parameter.
    pub(super) parameter: Option<Parameter>,
    /// SSE on the fitting part without it (the nominal model's, or a pair's first's) and with.
    pub(super) base_sse: f64,
    pub(super) sse: f64,
    /// The fitting part's test.
    pub(super) test: FitTest,
    /// Held-out residuals per motor (prediction − reading) without it and with it.
    pub(super) base_res: &'a [Vec<f64>],
    pub(super) res: &'a [Vec<f64>],
    /// Fit iterations.
    pub(super) iterations: usize,
}

/// What an extension is judged against.
#[derive(Clone, Copy)]
pub(super) struct Yardstick<'a> {
    /// The channel's verdict without it (the nominal model's, or a pair's first's).
    pub(super) before: &'a ChannelVerdict,
    /// The channel's noise floor.
    pub(super) floor: f64,
    /// The record's span, h (what an ambient drift's size is judged against).
    pub(super) hours: f64,
    /// The regimes of the held-out readings, where the channel has them.
    pub(super) regimes: Option<&'a Regimes>,
}

/// The family-wise level of the regime test over all of a channel's regimes.
const REGIME_ALPHA: f64 = 0.05;

/// The regimes of a channel's held-out readings, aligned with its held-out residuals: idle or
/// under load, and the motor.
pub(super) struct Regimes {
    /// Per motor, per held-out reading: under load.
    pub(super) load: Vec<Vec<bool>>,
    /// Motor ids, in the channel's order.
    pub(super) ids: Vec<i64>,
}

impl Regimes {
    /// A motor is under load where its current exceeds a tenth of its held-out peak.
    pub(super) fn of(currents: &[Vec<f64>], ids: &[i64]) -> Regimes {
        let load = currents
            .iter()
            .map(|i| {
                let peak = i.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
                i.iter()
                    .map(|v| peak > 0.0 && v.abs() > 0.1 * peak)
                    .collect()
            })
            .collect();
        Regimes {
            load,
            ids: ids.to_vec(),
        }
    }

    /// The first regime in which a correction that matters there (RMS ≥ `required`) is
    /// followed by significantly less than half (one-sided against the low end of
    /// [`HELDOUT_SIZE`], at 5 % over all the regimes: Bonferroni, each motor being one), where
    /// the regime's readings can tell: its slope, s.e.
    pub(super) fn first_unfollowed(
        &self,
        base: &[Vec<f64>],
        ext: &[Vec<f64>],
        required: f64,
    ) -> Option<(Regime, f64, f64)> {
        let mut regimes = vec![Regime::Idle, Regime::Load];
        regimes.extend(self.ids.iter().map(|&id| Regime::Motor(id)));
        // One-sided 5 % over the regimes: P(Z > z) = 0.05 / regimes.
        let z = stats::chi2_isf(2.0 * REGIME_ALPHA / regimes.len() as f64, 1.0).sqrt();
        regimes.into_iter().find_map(|regime| {
            let pick = |m: usize, k: usize| match regime {
                Regime::Idle => !self.load[m][k],
                Regime::Load => self.load[m][k],
                Regime::Motor(id) => self.ids[m] == id,
            };
            let part = |r: &[Vec<f64>]| -> Vec<Vec<f64>> {
                r.iter()
                    .enumerate()
                    .map(|(m, x)| {
                        x.iter()
                            .enumerate()
                            .filter(|&(k, _)| k < self.load[m].len() && pick(m, k))
                            .map(|(_, v)| *v)
                            .collect()
                    })
                    .collect()
            };
            let (b, e) = (part(base), part(ext));
            let change: Vec<f64> = b
                .iter()
                .zip(&e)
                .flat_map(|(b, e)| b.iter().zip(e).map(|(b, e)| b - e))
                .collect();
            if change.is_empty() || stats::rmse(&change) < required {
                return None;
            }
            let (slope, _, se) = slope_stats(&b, &e);
            let informative = se.is_finite() && se > 0.0 && se <= MAX_INFORMATIVE_SE;
            (informative && (slope - HELDOUT_SIZE.start()) / se < -z).then_some((regime, slope, se))
        })
    }
}

/// The three tests of the module docs.
pub(super) fn judge(e: Evidence, against: &Yardstick) -> Candidate {
    let Evidence {
        effect,
        parameter,
        base_sse,
        sse,
        test,
        base_res,
        res,
        iterations,
    } = e;
    let Yardstick {
        before: nominal,
        floor,
        regimes,
        ..
    } = *against;
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
    let gain = if base_held > 0.0 {
        1.0 - held / base_held
    } else {
        0.0
    };
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
    let mut c = Candidate {
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
        verdict: Verdict::Supported,
        iterations,
    };
    let unfollowed = regimes.and_then(|r| r.first_unfollowed(base_res, res, required_change));
    c.verdict = first_failed(&c, heldout_slope_se, against, unfollowed);
    c
}

/// The first test `c` fails (`docs/model-lab.md`, "Name the cause"), or `Supported`;
/// `slope_se` is its held-out slope's block standard error, `unfollowed` the first regime in
/// which the held-out readings do not follow it.
///
/// The held-out test can only refute an extension where it has the power to see it: with a
/// block standard error of the slope above [`MAX_INFORMATIVE_SE`], a correction the readings
/// follow fully (β = 1) would not reach [`MIN_HELDOUT_T`] most of the time (the correction is
/// far below the register's rounding noise there). Such a held-out part is uninformative:
/// the extension then stands on the fitting part, provided the held-out readings do not go
/// significantly against it and its held-out error is not significantly worse.
fn first_failed(
    c: &Candidate,
    slope_se: f64,
    against: &Yardstick,
    unfollowed: Option<(Regime, f64, f64)>,
) -> Verdict {
    let Yardstick { floor, hours, .. } = *against;
    let informative = slope_se.is_finite() && slope_se <= MAX_INFORMATIVE_SE;
    let alpha = ALPHA / Effect::CATALOG.len() as f64;
    let value = c.parameter.as_ref().map_or(f64::NAN, |p| p.value);
    let (slope, slope_t, held) = (c.heldout_slope, c.heldout_slope_t, c.heldout_rmse);
    if !c.plausible {
        let (lo, hi, why) = c.id.bounds().unwrap_or((f64::NAN, f64::NAN, ""));
        Verdict::OutsidePhysics { value, lo, hi, why }
    } else if let Some((below, why)) =
        c.id.negligible(hours, floor)
            .filter(|(s, _)| value.abs() < *s)
    {
        Verdict::Negligible { value, below, why }
    } else if c.p_value >= alpha {
        Verdict::NotSignificant {
            p: c.p_value,
            alpha,
        }
    } else if c.with_heldout && !HELDOUT_SIZE.contains(&slope) {
        Verdict::HeldOutSize { slope }
    } else if !c.with_heldout && c.delta_bic <= 0.0 {
        Verdict::NoBicGain {
            delta_bic: c.delta_bic,
        }
    } else if informative && (slope_t.is_nan() || slope_t < MIN_HELDOUT_T) {
        Verdict::NotFollowed { slope, t: slope_t }
    } else if !informative
        && (slope_t.is_nan()
            || slope_t <= -MIN_HELDOUT_T
            || c.heldout_t <= -MIN_HELDOUT_T
            || held.is_nan())
    {
        Verdict::Against {
            slope_se,
            slope_t,
            error_t: c.heldout_t,
        }
    } else if informative && (held.is_nan() || held > c.baseline_heldout_rmse) {
        Verdict::HeldOutWorse {
            gain: c.gain,
            slope,
        }
    } else if c.heldout_change.is_nan() || c.heldout_change < c.required_change {
        Verdict::NoPracticalChange {
            change: c.heldout_change,
            required: c.required_change,
            floor,
        }
    } else if let Some((regime, slope, se)) = unfollowed {
        Verdict::NotInEveryRegime { regime, slope, se }
    } else if c.gain.is_nan() || c.gain < c.required_gain {
        Verdict::ExplainsTooLittle {
            gain: c.gain,
            required: c.required_gain,
        }
    } else {
        Verdict::Supported
    }
}

/// Slope β of the nominal residuals b on the extension's correction δ = b − e (b, e: nominal
/// and extended held-out residuals, prediction − reading) and its t statistic, with a
/// cluster-robust standard error over contiguous blocks of each motor's residuals (the
/// residuals are autocorrelated within a block, roughly independent between blocks).
/// (0, 0) when there are too few blocks or no correction at all.
#[cfg(test)]
pub(super) fn confirmation_slope(base: &[Vec<f64>], ext: &[Vec<f64>]) -> (f64, f64) {
    let (beta, t, _) = slope_stats(base, ext);
    (beta, t)
}

/// The held-out slope (see `confirmation_slope`) with the slope's block standard error as well (infinite when there
/// are too few blocks or no correction: nothing can be concluded).
pub(super) fn slope_stats(base: &[Vec<f64>], ext: &[Vec<f64>]) -> (f64, f64, f64) {
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
pub(super) fn improvement_t(base: &[Vec<f64>], ext: &[Vec<f64>]) -> f64 {
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

#[cfg(test)]
mod tests {
    use super::*;
    use sim::rng::Rng;

    /// Nominal residuals b = (true correction δ) + noise, the extension removing δ.
    pub(super) fn residuals(follow: f64, seed: u64) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
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
    pub(super) fn the_slope_test_sees_a_correction_the_squared_error_test_misses() {
        let (b, e) = residuals(1.0, 3);
        let (slope, t) = confirmation_slope(&b, &e);
        assert!((slope - 1.0).abs() < 0.3, "{slope}");
        assert!(t > MIN_HELDOUT_T, "{t}");
        // The same data through the squared-error drop: about half the t.
        assert!(improvement_t(&b, &e) < t, "{}", improvement_t(&b, &e));
    }

    /// Two motors whose readings alternate between idle and load every 100 readings; the
    /// extension corrects both regimes by `size_idle` and `size_load`, the readings follow
    /// `follow_idle` and `follow_load` of it.
    fn regimes_case(
        size_idle: f64,
        follow_idle: f64,
        follow_load: f64,
    ) -> (Regimes, Vec<Vec<f64>>, Vec<Vec<f64>>) {
        let mut rng = Rng::new(11);
        let (mut base, mut ext, mut current) = (Vec::new(), Vec::new(), Vec::new());
        for m in 0..2 {
            let (mut b, mut e, mut i) = (Vec::new(), Vec::new(), Vec::new());
            for k in 0..4000 {
                let load = (k / 100) % 2 == 1;
                let wave = ((k as f64) / 37.0 + m as f64).sin();
                let (delta, follow) = if load {
                    (0.3 * wave, follow_load)
                } else {
                    (size_idle * wave, follow_idle)
                };
                let r = follow * delta + 0.1 * rng.normal();
                b.push(r);
                e.push(r - delta);
                i.push(if load { 1.2 } else { 0.03 });
            }
            base.push(b);
            ext.push(e);
            current.push(i);
        }
        (Regimes::of(&current, &[1, 2]), base, ext)
    }

    /// A correction the readings follow under load and not at idle is no name there.
    #[test]
    fn a_name_that_holds_under_load_and_not_at_idle_is_refused_at_idle() {
        let (regimes, b, e) = regimes_case(0.3, 0.0, 1.0);
        let (regime, slope, se) = regimes.first_unfollowed(&b, &e, 0.01).unwrap();
        assert_eq!(regime, Regime::Idle);
        assert!(slope.abs() < 0.2 && se < MAX_INFORMATIVE_SE, "{slope} {se}");
        // Followed in both: nothing to refuse.
        let (regimes, b, e) = regimes_case(0.3, 1.0, 1.0);
        assert_eq!(regimes.first_unfollowed(&b, &e, 0.01), None);
        // A regime where it predicts nothing that matters is not judged there.
        let (regimes, b, e) = regimes_case(0.001, 0.0, 1.0);
        assert_eq!(regimes.first_unfollowed(&b, &e, 0.01), None);
        // Half followed is not "significantly less than half".
        let (regimes, b, e) = regimes_case(0.3, 0.6, 1.0);
        assert_eq!(regimes.first_unfollowed(&b, &e, 0.01), None);
    }

    /// The same through [`judge`]: a current offset (an effect that predicts a change at idle
    /// as under load) whose correction the idle readings do not follow is refused for it, and
    /// would be supported without the rule.
    #[test]
    fn judge_refuses_a_name_for_the_regime_it_does_not_hold_in() {
        let (regimes, b, e) = regimes_case(0.1, 0.0, 1.0);
        let floor = NoiseFloor::of(&b, 0.0, &[(0, 4000)]);
        let before = verdict(Channel::Thermal, None, &[1, 2], &b, "°C", &floor);
        let judged = |regimes: Option<&Regimes>| {
            let evidence = Evidence {
                effect: Effect::CurrentOffset,
                parameter: Some(Parameter {
                    name: "current_offset".into(),
                    value: 0.1,
                    unit: "A".into(),
                }),
                base_sse: 1000.0,
                sse: 500.0,
                test: FitTest {
                    lr: 500.0,
                    n_eff: 1000.0,
                    p_value: 1e-20,
                    params: 1.0,
                    with_heldout: false,
                },
                base_res: &b,
                res: &e,
                iterations: 1,
            };
            let against = Yardstick {
                before: &before,
                floor: floor.floor,
                hours: 2.0,
                regimes,
            };
            judge(evidence, &against).verdict
        };
        assert_eq!(judged(None), Verdict::Supported);
        let refused = judged(Some(&regimes));
        assert!(
            matches!(
                refused,
                Verdict::NotInEveryRegime {
                    regime: Regime::Idle,
                    ..
                }
            ),
            "{refused}"
        );
        assert!(
            refused.to_string().starts_with("not followed at idle"),
            "{refused}"
        );
    }

    #[test]
    pub(super) fn the_slope_test_refuses_a_correction_the_readings_do_not_follow() {
        let (b, e) = residuals(0.0, 4);
        let (slope, t) = confirmation_slope(&b, &e);
        assert!(slope.abs() < 0.3 && t < MIN_HELDOUT_T, "{slope} {t}");
    }
}
