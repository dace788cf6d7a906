//! The project's one quantile rule: linear interpolation between the two nearest ranks (numpy's
//! default, which LeRobot's dataset statistics use), for the recorder's statistics, the
//! benchmarks' latency percentiles and the tests' summaries.

/// The `q`-quantile (0..=1) of values sorted ascending; NaN when there are none.
pub fn quantile_sorted(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let h = (sorted.len() - 1) as f64 * q.clamp(0.0, 1.0);
    let lo = h.floor() as usize;
    let hi = (lo + 1).min(sorted.len() - 1);
    sorted[lo] + (h - lo as f64) * (sorted[hi] - sorted[lo])
}

/// The `q`-quantile (0..=1) of `values` in any order; NaN when there are none.
pub fn quantile(values: &[f64], q: f64) -> f64 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    quantile_sorted(&sorted, q)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_interpolate_between_ranks_as_numpy_does() {
        // numpy.quantile([1, 2, 3, 4], [0, 0.25, 0.5, 0.99, 1]) = 1, 1.75, 2.5, 3.97, 4
        let x = [4.0, 1.0, 3.0, 2.0];
        for (q, want) in [
            (0.0, 1.0),
            (0.25, 1.75),
            (0.5, 2.5),
            (0.99, 3.97),
            (1.0, 4.0),
        ] {
            assert!((quantile(&x, q) - want).abs() < 1e-12, "q {q}");
        }
        assert_eq!(quantile_sorted(&[5.0], 0.3), 5.0);
        assert!(quantile(&[], 0.5).is_nan());
    }
}
