//! The temperature register as a measurement: reading = q·round((T + n)/q), n ~ N(0, σ²).
//!
//! Least squares on the readings treats the rounding error as noise of variance q²/12, but with
//! a 1 °C register and little sensor noise the rounding error is a slow, deterministic function
//! of T: it is strongly autocorrelated and most of the information sits in the moments the
//! reading steps from one value to the next. The likelihood of the register itself,
//! P(reading | T) = Φ((q/2 − e)/σ) − Φ((−q/2 − e)/σ) with e = T − reading, uses it. Fits stay
//! least squares by fitting the signed deviance residual ρ(e) = sign(e)·√(2·(ℓ(0) − ℓ(e))) (ℓ
//! the log-likelihood): Σρ² is twice the negative log-likelihood up to a constant, ρ ≈ e/σ
//! where the register is fine against the noise (σ ≫ q), and under a correct model the ρ are
//! roughly independent and standard normal.

/// Points of the tabulated ρ over |e| ∈ [0, q/2 + [`TABLE_SIGMAS`]·σ].
const TABLE_POINTS: usize = 4096;
/// Reach of the table beyond the rounding interval, in σ; further out ρ grows linearly.
const TABLE_SIGMAS: f64 = 12.0;
/// Smallest σ considered, as a fraction of the quantum (below it the likelihood is a step
/// function the fit cannot descend).
const MIN_SIGMA_OF_QUANTUM: f64 = 0.05;

/// The register model at one noise level, with ρ tabulated for the fitting loop (a table lookup
/// per reading instead of two `erfc`).
#[derive(Debug, Clone)]
pub struct Register {
    quantum: f64,
    sigma: f64,
    step: f64,
    table: Vec<f64>,
    tail_slope: f64,
}

/// ln P(reading | T) for e = T − reading.
fn log_likelihood(e: f64, q: f64, sigma: f64) -> f64 {
    // P = Φ(a) − Φ(b) with a = (q/2 − e)/σ, b = (−q/2 − e)/σ; by symmetry evaluate at |e| so
    // both arguments sit in Φ's lower tail or straddle zero, where the erfc difference keeps
    // its relative precision.
    let e = e.abs();
    let s = std::f64::consts::SQRT_2 * sigma;
    let upper = libm::erfc((e - 0.5 * q) / s); // 2Φ(a)
    let lower = libm::erfc((e + 0.5 * q) / s); // 2Φ(b)
    (0.5 * (upper - lower)).max(f64::MIN_POSITIVE).ln()
}

impl Register {
    /// The register with quantum `q` (> 0) and noise σ (floored at a small fraction of q).
    pub fn new(quantum: f64, sigma: f64) -> Self {
        let q = quantum;
        let sigma = sigma.max(MIN_SIGMA_OF_QUANTUM * q);
        let reach = 0.5 * q + TABLE_SIGMAS * sigma;
        let step = reach / (TABLE_POINTS - 1) as f64;
        let l0 = log_likelihood(0.0, q, sigma);
        let table: Vec<f64> = (0..TABLE_POINTS)
            .map(|i| {
                (2.0 * (l0 - log_likelihood(i as f64 * step, q, sigma)))
                    .max(0.0)
                    .sqrt()
            })
            .collect();
        let tail_slope = (table[TABLE_POINTS - 1] - table[TABLE_POINTS - 2]) / step;
        Register {
            quantum: q,
            sigma,
            step,
            table,
            tail_slope,
        }
    }

    /// The maximum-likelihood noise level given residuals e = prediction − reading of a fitted
    /// model (golden-section search on ln σ). The model's own error counts as noise, which is
    /// what the fit's weighting should see.
    pub fn estimate(quantum: f64, residuals: &[f64]) -> Self {
        let q = quantum;
        let spread = crate::stats::rmse(residuals);
        if residuals.is_empty() || !spread.is_finite() {
            return Register::new(q, q);
        }
        let ll = |ln_sigma: f64| -> f64 {
            let s = ln_sigma.exp();
            residuals.iter().map(|&e| log_likelihood(e, q, s)).sum()
        };
        let (mut lo, mut hi) = ((MIN_SIGMA_OF_QUANTUM * q).ln(), (q + 3.0 * spread).ln());
        let g = 0.5 * (5f64.sqrt() - 1.0);
        let (mut x1, mut x2) = (hi - g * (hi - lo), lo + g * (hi - lo));
        let (mut f1, mut f2) = (ll(x1), ll(x2));
        for _ in 0..40 {
            if f1 > f2 {
                hi = x2;
                (x2, f2) = (x1, f1);
                x1 = hi - g * (hi - lo);
                f1 = ll(x1);
            } else {
                lo = x1;
                (x1, f1) = (x2, f2);
                x2 = lo + g * (hi - lo);
                f2 = ll(x2);
            }
        }
        Register::new(q, (0.5 * (lo + hi)).exp())
    }

    /// Noise level σ, in the reading's unit.
    pub fn sigma(&self) -> f64 {
        self.sigma
    }

    /// Quantum q, in the reading's unit.
    pub fn quantum(&self) -> f64 {
        self.quantum
    }

    /// dρ/de at e = prediction − reading.
    #[inline]
    pub fn derivative(&self, e: f64) -> f64 {
        let i = (e.abs() / self.step) as usize;
        if i + 1 < TABLE_POINTS {
            (self.table[i + 1] - self.table[i]) / self.step
        } else {
            self.tail_slope
        }
    }

    /// Signed deviance residual of e = prediction − reading (dimensionless, in σ).
    #[inline]
    pub fn residual(&self, e: f64) -> f64 {
        let a = e.abs();
        let x = a / self.step;
        let i = x as usize;
        let r = if i + 1 < TABLE_POINTS {
            let f = x - i as f64;
            self.table[i] + f * (self.table[i + 1] - self.table[i])
        } else {
            self.table[TABLE_POINTS - 1]
                + (a - self.step * (TABLE_POINTS - 1) as f64) * self.tail_slope
        };
        if e < 0.0 {
            -r
        } else {
            r
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sim::rng::Rng;

    #[test]
    fn a_fine_register_is_least_squares_in_sigma_units() {
        let r = Register::new(0.01, 0.5);
        for e in [-1.3, -0.2, 0.0, 0.4, 2.0] {
            assert!(
                (r.residual(e) - e / 0.5).abs() < 0.01 * (1.0 + e.abs() / 0.5),
                "{e}"
            );
        }
    }

    #[test]
    fn a_coarse_register_barely_penalises_errors_inside_the_interval() {
        let r = Register::new(1.0, 0.05);
        assert!(r.residual(0.3).abs() < 0.05);
        assert!(r.residual(0.7) > 3.0 && r.residual(-0.7) < -3.0);
        // Monotonic and odd.
        let mut last = 0.0;
        for i in 1..200 {
            let e = i as f64 * 0.01;
            let v = r.residual(e);
            assert!(v >= last, "not monotonic at {e}");
            assert_eq!(r.residual(-e), -v);
            last = v;
        }
    }

    #[test]
    fn the_noise_level_is_recovered_from_rounded_readings() {
        let mut rng = Rng::new(7);
        for sigma in [0.05, 0.15, 0.3, 0.8] {
            // A slowly varying temperature read through an integer register.
            let res: Vec<f64> = (0..20_000)
                .map(|k| {
                    let t = 30.0 + 5.0 * (k as f64 * 0.001).sin();
                    t - (t + sigma * rng.normal()).round()
                })
                .collect();
            let got = Register::estimate(1.0, &res).sigma();
            assert!(
                (got / sigma - 1.0).abs() < 0.15,
                "σ {sigma}: estimated {got}"
            );
        }
    }
}
