//! Misfit statistics: RMSE, bias, autocorrelation, the Ljung–Box whiteness test, the χ²
//! distribution for likelihood-ratio tests, and correlation with candidate regressors.

/// Root mean square of the finite values (NaN when there are none).
pub fn rmse(r: &[f64]) -> f64 {
    let (s, n) = r
        .iter()
        .filter(|v| v.is_finite())
        .fold((0.0, 0usize), |(s, n), v| (s + v * v, n + 1));
    if n == 0 {
        f64::NAN
    } else {
        (s / n as f64).sqrt()
    }
}

/// Mean of the finite values (NaN when there are none).
pub fn mean(r: &[f64]) -> f64 {
    let (s, n) = r
        .iter()
        .filter(|v| v.is_finite())
        .fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    if n == 0 {
        f64::NAN
    } else {
        s / n as f64
    }
}

/// Sample autocorrelation of `x` at lags 0..=max_lag (missing values skipped pairwise).
pub fn autocorrelation(x: &[f64], max_lag: usize) -> Vec<f64> {
    let m = mean(x);
    let var: f64 = x
        .iter()
        .filter(|v| v.is_finite())
        .map(|v| (v - m).powi(2))
        .sum();
    (0..=max_lag)
        .map(|lag| {
            if var <= 0.0 || lag >= x.len() {
                return 0.0;
            }
            let c: f64 = x
                .iter()
                .zip(&x[lag..])
                .filter(|(a, b)| a.is_finite() && b.is_finite())
                .map(|(a, b)| (a - m) * (b - m))
                .sum();
            c / var
        })
        .collect()
}

/// The Ljung–Box statistic over lags 1..=h and its p-value (χ² with h degrees of freedom):
/// a small p-value says the residuals are not white, i.e. the model misses structure.
pub fn ljung_box(x: &[f64], h: usize) -> (f64, f64) {
    let n = x.iter().filter(|v| v.is_finite()).count() as f64;
    if n <= (h + 1) as f64 {
        return (f64::NAN, f64::NAN);
    }
    let acf = autocorrelation(x, h);
    let q = n
        * (n + 2.0)
        * (1..=h)
            .map(|k| acf[k] * acf[k] / (n - k as f64))
            .sum::<f64>();
    (q, chi2_sf(q, h as f64))
}

/// Pearson correlation of the pairs where both are finite (0 when undefined).
pub fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let pairs: Vec<(f64, f64)> = a
        .iter()
        .zip(b)
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .map(|(x, y)| (*x, *y))
        .collect();
    let n = pairs.len() as f64;
    if n < 3.0 {
        return 0.0;
    }
    let (ma, mb) = (
        pairs.iter().map(|p| p.0).sum::<f64>() / n,
        pairs.iter().map(|p| p.1).sum::<f64>() / n,
    );
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in &pairs {
        sab += (x - ma) * (y - mb);
        saa += (x - ma).powi(2);
        sbb += (y - mb).powi(2);
    }
    if saa <= 0.0 || sbb <= 0.0 {
        0.0
    } else {
        sab / (saa * sbb).sqrt()
    }
}

/// ln Γ(x) for x > 0 (Lanczos, g = 7).
fn ln_gamma(x: f64) -> f64 {
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        // Reflection.
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + 7.5;
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Regularised upper incomplete gamma Q(a, x) (series below a+1, continued fraction above).
fn gamma_q(a: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 1.0;
    }
    let lg = ln_gamma(a);
    if x < a + 1.0 {
        let (mut sum, mut term, mut ap) = (1.0 / a, 1.0 / a, a);
        for _ in 0..1000 {
            ap += 1.0;
            term *= x / ap;
            sum += term;
            if term.abs() < sum.abs() * 1e-15 {
                break;
            }
        }
        1.0 - sum * (-x + a * x.ln() - lg).exp()
    } else {
        // Lentz's continued fraction.
        let tiny = 1e-300;
        let mut b = x + 1.0 - a;
        let mut c = 1.0 / tiny;
        let mut d = 1.0 / b;
        let mut h = d;
        for i in 1..1000 {
            let an = -(i as f64) * (i as f64 - a);
            b += 2.0;
            d = an * d + b;
            if d.abs() < tiny {
                d = tiny;
            }
            c = b + an / c;
            if c.abs() < tiny {
                c = tiny;
            }
            d = 1.0 / d;
            let del = d * c;
            h *= del;
            if (del - 1.0).abs() < 1e-15 {
                break;
            }
        }
        (-x + a * x.ln() - lg).exp() * h
    }
}

/// Survival function of the χ² distribution with `df` degrees of freedom: P(X > x).
pub fn chi2_sf(x: f64, df: f64) -> f64 {
    if !x.is_finite() {
        return if x > 0.0 { 0.0 } else { 1.0 };
    }
    gamma_q(df / 2.0, x / 2.0).clamp(0.0, 1.0)
}

/// One-sided upper tail of the standard normal distribution: P(Z > z).
pub fn normal_sf(z: f64) -> f64 {
    let tail = 0.5 * chi2_sf(z * z, 1.0);
    if z >= 0.0 {
        tail
    } else {
        1.0 - tail
    }
}

/// Fisher's combination of independent p-values of one null hypothesis: under it,
/// −2 Σ ln pᵢ is χ² with 2k degrees of freedom; its upper tail is the combined p-value.
pub fn fisher(p: &[f64]) -> f64 {
    let x: f64 = p.iter().map(|p| -2.0 * p.max(f64::MIN_POSITIVE).ln()).sum();
    chi2_sf(x, 2.0 * p.len() as f64)
}

/// The χ² quantile with upper tail `p` (bisection on [`chi2_sf`]).
pub fn chi2_isf(p: f64, df: f64) -> f64 {
    let (mut lo, mut hi) = (0.0, 1.0);
    while chi2_sf(hi, df) > p {
        hi *= 2.0;
    }
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if chi2_sf(mid, df) > p {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// The number of independent samples `n` correlated residuals are worth, from their lag-1
/// autocorrelation ρ (AR(1) approximation): n·(1−ρ)/(1+ρ). Testing with the raw count would
/// treat the slowly varying rounding error of a 1 °C register as thousands of independent
/// observations and "find" effects in it.
pub fn effective_n(n: usize, rho1: f64) -> f64 {
    let rho = rho1.clamp(0.0, 0.999);
    (n as f64 * (1.0 - rho) / (1.0 + rho)).max(1.0)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    #[test]
    fn chi2_matches_tables() {
        // Table values: χ²(1) 95 % = 3.841, χ²(2) 99 % = 9.210, χ²(20) 95 % = 31.410.
        assert!((chi2_isf(0.05, 1.0) - 3.841).abs() < 1e-3);
        assert!((chi2_isf(0.01, 2.0) - 9.210).abs() < 1e-3);
        assert!((chi2_isf(0.05, 20.0) - 31.410).abs() < 1e-3);
        assert!((chi2_sf(3.841_458_8, 1.0) - 0.05).abs() < 1e-6);
    }

    #[test]
    fn normal_tail_and_fisher_match_tables() {
        // Φ̄(1.645) = 0.0500, Φ̄(2.326) = 0.0100, Φ̄(0) = 0.5, Φ̄(−1.645) = 0.95.
        assert!((normal_sf(1.644_854) - 0.05).abs() < 1e-6);
        assert!((normal_sf(2.326_348) - 0.01).abs() < 1e-6);
        assert!((normal_sf(0.0) - 0.5).abs() < 1e-12);
        assert!((normal_sf(-1.644_854) - 0.95).abs() < 1e-6);
        // Two p-values of 0.05: −2 Σ ln p = 11.983, χ²(4) upper tail 0.0175.
        assert!((fisher(&[0.05, 0.05]) - 0.017_5).abs() < 1e-4);
        // One p-value alone is itself (χ²(2) of −2 ln p is p).
        assert!((fisher(&[0.003]) - 0.003).abs() < 1e-9);
    }

    #[test]
    fn ljung_box_separates_white_from_correlated() {
        // A deterministic pseudo-random sequence is white; its running sum is not.
        let mut s = 12345u64;
        let white: Vec<f64> = (0..2000)
            .map(|_| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (s >> 11) as f64 / (1u64 << 53) as f64 - 0.5
            })
            .collect();
        let walk: Vec<f64> = white
            .iter()
            .scan(0.0, |a, x| {
                *a += x;
                Some(*a)
            })
            .collect();
        assert!(ljung_box(&white, 20).1 > 0.01);
        assert!(ljung_box(&walk, 20).1 < 1e-10);
        assert!(correlation(&walk, &walk) > 0.999);
        assert!(rmse(&[3.0, f64::NAN, -3.0]) == 3.0);
    }
}
