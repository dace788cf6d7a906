//! Feature statistics as LeRobot keeps them (`lerobot/datasets/compute_stats.py`): per feature
//! and dimension min, max, mean, std (population), count (frames, shape `[1]`) and the quantiles
//! q01, q10, q50, q90, q99.
//!
//! Per episode they are exact over the episode's finite values (NaN marks a missing sample, see
//! [`crate::sampler`]); quantiles interpolate linearly between order statistics (numpy's
//! default), which LeRobot's 5000-bin histogram approximates. Across episodes (`stats.json`)
//! min/max are exact, mean and std combine exactly by the parallel formula, and quantiles are
//! the count-weighted average of the episodes' quantiles: LeRobot's own `aggregate_stats`,
//! approximate by construction (exact global quantiles would need every frame again).

use serde_json::{json, Value};
use telemetry::stats::quantile_sorted;

/// Quantile levels and their key names.
pub const QUANTILES: [(f64, &str); 5] = [
    (0.01, "q01"),
    (0.10, "q10"),
    (0.50, "q50"),
    (0.90, "q90"),
    (0.99, "q99"),
];

/// Statistic names, in the order they are stored.
pub const STAT_NAMES: [&str; 10] = [
    "min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99",
];

/// Statistics of one feature (every vector has the feature's width).
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureStats {
    /// Minimum per dimension (NaN when a dimension has no finite value).
    pub min: Vec<f64>,
    /// Maximum per dimension (NaN as for `min`).
    pub max: Vec<f64>,
    /// Mean per dimension, of its finite values.
    pub mean: Vec<f64>,
    /// Population standard deviation.
    pub std: Vec<f64>,
    /// Frames the statistics cover (of an image feature: the images sampled).
    pub count: u64,
    /// Quantiles in [`QUANTILES`] order, each per dimension.
    pub quantiles: [Vec<f64>; 5],
}

impl FeatureStats {
    /// Statistics of `frames` values per dimension: `columns[d][frame]`.
    pub fn of_columns(columns: &[Vec<f64>], frames: usize) -> FeatureStats {
        let width = columns.len();
        let mut s = FeatureStats {
            min: Vec::with_capacity(width),
            max: Vec::with_capacity(width),
            mean: Vec::with_capacity(width),
            std: Vec::with_capacity(width),
            count: frames as u64,
            quantiles: Default::default(),
        };
        for column in columns {
            let mut x: Vec<f64> = column.iter().copied().filter(|v| v.is_finite()).collect();
            x.sort_by(f64::total_cmp);
            let n = x.len() as f64;
            let mean = x.iter().sum::<f64>() / n;
            let var = x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
            s.min.push(x.first().copied().unwrap_or(f64::NAN));
            s.max.push(x.last().copied().unwrap_or(f64::NAN));
            s.mean.push(mean);
            s.std.push(var.sqrt());
            for (k, (q, _)) in QUANTILES.iter().enumerate() {
                s.quantiles[k].push(quantile_sorted(&x, *q));
            }
        }
        s
    }

    /// Statistics of 8-bit image channels given as histograms (`histograms[channel][value]`),
    /// values scaled to 0..1 as LeRobot scales pixels; `frames` is the images sampled (LeRobot's
    /// `count` of an image feature). Exact: the same as [`FeatureStats::of_columns`] over every
    /// sampled pixel.
    pub fn of_histograms(histograms: &[[u64; 256]], frames: u64) -> FeatureStats {
        let mut s = FeatureStats {
            min: Vec::new(),
            max: Vec::new(),
            mean: Vec::new(),
            std: Vec::new(),
            count: frames,
            quantiles: Default::default(),
        };
        for h in histograms {
            let n: u64 = h.iter().sum();
            let value = |v: usize| v as f64 / 255.0;
            let present = || (0..256).filter(|&v| h[v] > 0);
            let mean = (0..256).map(|v| value(v) * h[v] as f64).sum::<f64>() / n as f64;
            let var = (0..256)
                .map(|v| (value(v) - mean).powi(2) * h[v] as f64)
                .sum::<f64>()
                / n as f64;
            s.min.push(present().next().map_or(f64::NAN, value));
            s.max.push(present().next_back().map_or(f64::NAN, value));
            s.mean.push(mean);
            s.std.push(var.sqrt());
            // The value of rank r (0-based) in the sorted samples.
            let ranked = |r: u64| {
                let mut seen = 0;
                for (v, count) in h.iter().enumerate() {
                    seen += count;
                    if seen > r {
                        return value(v);
                    }
                }
                f64::NAN
            };
            for (k, (q, _)) in QUANTILES.iter().enumerate() {
                // numpy's linear interpolation between order statistics, as `quantile_sorted`.
                let x = if n == 0 {
                    f64::NAN
                } else {
                    let pos = (n - 1) as f64 * q;
                    let lo = pos.floor() as u64;
                    let hi = (lo + 1).min(n - 1);
                    ranked(lo) + (pos - lo as f64) * (ranked(hi) - ranked(lo))
                };
                s.quantiles[k].push(x);
            }
        }
        s
    }

    /// One statistic by name, as stored (count as a one-element vector).
    pub fn get(&self, name: &str) -> Option<Vec<f64>> {
        Some(match name {
            "min" => self.min.clone(),
            "max" => self.max.clone(),
            "mean" => self.mean.clone(),
            "std" => self.std.clone(),
            "count" => vec![self.count as f64],
            _ => self.quantiles[QUANTILES.iter().position(|(_, n)| *n == name)?].clone(),
        })
    }

    /// Rebuilds from stored statistics (`get` by name); `None` if one is missing or misshapen.
    pub fn from_named(mut get: impl FnMut(&str) -> Option<Vec<f64>>) -> Option<FeatureStats> {
        let min = get("min")?;
        let width = min.len();
        let count = get_count(&mut get)?;
        let mut take = |n: &str| get(n).filter(|v| v.len() == width);
        Some(FeatureStats {
            max: take("max")?,
            mean: take("mean")?,
            std: take("std")?,
            count,
            quantiles: [
                take("q01")?,
                take("q10")?,
                take("q50")?,
                take("q90")?,
                take("q99")?,
            ],
            min,
        })
    }

    /// Combines the statistics of several episodes of one feature (LeRobot's
    /// `aggregate_feature_stats`, NaN dimensions of an episode left out of min/max).
    pub fn aggregate(parts: &[FeatureStats]) -> Option<FeatureStats> {
        let first = parts.first()?;
        let width = first.mean.len();
        let total: u64 = parts.iter().map(|p| p.count).sum();
        if total == 0 || parts.iter().any(|p| p.mean.len() != width) {
            return None;
        }
        let weight = |p: &FeatureStats| p.count as f64 / total as f64;
        let mut out = FeatureStats {
            min: vec![f64::NAN; width],
            max: vec![f64::NAN; width],
            mean: vec![0.0; width],
            std: vec![0.0; width],
            count: total,
            quantiles: Default::default(),
        };
        for d in 0..width {
            out.min[d] = parts.iter().map(|p| p.min[d]).fold(f64::NAN, f64::min);
            out.max[d] = parts.iter().map(|p| p.max[d]).fold(f64::NAN, f64::max);
            let mean: f64 = parts.iter().map(|p| p.mean[d] * weight(p)).sum();
            let var: f64 = parts
                .iter()
                .map(|p| (p.std[d].powi(2) + (p.mean[d] - mean).powi(2)) * weight(p))
                .sum();
            out.mean[d] = mean;
            out.std[d] = var.sqrt();
        }
        for k in 0..QUANTILES.len() {
            out.quantiles[k] = (0..width)
                .map(|d| parts.iter().map(|p| p.quantiles[k][d] * weight(p)).sum())
                .collect();
        }
        Some(out)
    }

    /// The object LeRobot writes per feature in `stats.json` (non-finite values as `null`); an
    /// image's statistics per channel shaped `[3, 1, 1]`, as LeRobot keeps them so that they
    /// broadcast over a `[3, H, W]` image.
    pub fn to_json(&self, image: bool) -> crate::features::Ordered<Value> {
        let mut out = Vec::new();
        for name in STAT_NAMES {
            let v = if name == "count" {
                json!([self.count])
            } else {
                let values = self.get(name).unwrap_or_default();
                if image {
                    json!(values.iter().map(|v| json!([[v]])).collect::<Vec<_>>())
                } else {
                    json!(values)
                }
            };
            out.push((name.to_string(), v));
        }
        crate::features::Ordered(out)
    }
}

fn get_count(get: &mut impl FnMut(&str) -> Option<Vec<f64>>) -> Option<u64> {
    match get("count")?.as_slice() {
        [c] if *c >= 0.0 => Some(*c as u64),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn episode_stats_match_the_definitions_and_skip_missing_values() {
        let s = FeatureStats::of_columns(&[vec![1.0, 2.0, 3.0, 4.0, f64::NAN], vec![5.0; 5]], 5);
        assert_eq!(s.min, [1.0, 5.0]);
        assert_eq!(s.max, [4.0, 5.0]);
        assert_eq!(s.mean, [2.5, 5.0]);
        assert!((s.std[0] - 1.25f64.sqrt()).abs() < 1e-12, "population std");
        assert_eq!(s.std[1], 0.0);
        assert_eq!(s.count, 5, "frames, as LeRobot counts");
        // numpy.quantile([1,2,3,4], q) with linear interpolation: h = 3q.
        assert!((s.quantiles[2][0] - 2.5).abs() < 1e-12);
        assert!((s.quantiles[0][0] - 1.03).abs() < 1e-12);
        assert!((s.quantiles[4][0] - 3.97).abs() < 1e-12);
    }

    #[test]
    fn aggregation_is_exact_for_min_max_mean_std() {
        let a: Vec<f64> = (0..7).map(|i| i as f64 * 0.5).collect();
        let b: Vec<f64> = (0..13).map(|i| 10.0 - i as f64).collect();
        let all: Vec<f64> = a.iter().chain(&b).copied().collect();
        let sa = FeatureStats::of_columns(std::slice::from_ref(&a), a.len());
        let sb = FeatureStats::of_columns(std::slice::from_ref(&b), b.len());
        let whole = FeatureStats::of_columns(std::slice::from_ref(&all), all.len());
        let agg = FeatureStats::aggregate(&[sa.clone(), sb.clone()]).unwrap();
        assert_eq!(agg.count, 20);
        assert_eq!(agg.min, whole.min);
        assert_eq!(agg.max, whole.max);
        assert!((agg.mean[0] - whole.mean[0]).abs() < 1e-12);
        assert!((agg.std[0] - whole.std[0]).abs() < 1e-12);
        let weighted = (sa.quantiles[2][0] * 7.0 + sb.quantiles[2][0] * 13.0) / 20.0;
        assert!(
            (agg.quantiles[2][0] - weighted).abs() < 1e-12,
            "LeRobot's weighted quantiles"
        );
    }

    #[test]
    fn stored_stats_round_trip_and_misshapen_ones_are_refused() {
        let s = FeatureStats::of_columns(&[vec![1.0, 2.0], vec![3.0, 5.0]], 2);
        let back = FeatureStats::from_named(|n| s.get(n)).unwrap();
        assert_eq!(back, s);
        assert!(FeatureStats::from_named(|n| if n == "std" {
            Some(vec![1.0])
        } else {
            s.get(n)
        })
        .is_none());
        let json = serde_json::to_value(s.to_json(false)).unwrap();
        assert_eq!(json["count"], json!([2]));
        assert_eq!(json["q50"], json!([1.5, 4.0]));
        let image = serde_json::to_value(s.to_json(true)).unwrap();
        assert_eq!(image["count"], json!([2]));
        assert_eq!(image["q50"], json!([[[1.5]], [[4.0]]]));
    }

    #[test]
    fn image_histograms_give_the_statistics_of_their_pixels() {
        // Three channels of pixels with uneven, gappy distributions.
        let pixels: Vec<[u8; 3]> = (0..1001u32)
            .map(|i| {
                [
                    (i * 7 % 256) as u8,
                    (i % 3 * 100) as u8,
                    (255 - i % 40) as u8,
                ]
            })
            .collect();
        let mut h = [[0u64; 256]; 3];
        for p in &pixels {
            for c in 0..3 {
                h[c][usize::from(p[c])] += 1;
            }
        }
        let columns: Vec<Vec<f64>> = (0..3)
            .map(|c| pixels.iter().map(|p| f64::from(p[c]) / 255.0).collect())
            .collect();
        let direct = FeatureStats::of_columns(&columns, 7);
        let from_h = FeatureStats::of_histograms(&h, 7);
        assert_eq!(from_h.count, 7, "the images sampled, not the pixels");
        for (a, b) in [
            (&from_h.min, &direct.min),
            (&from_h.max, &direct.max),
            (&from_h.mean, &direct.mean),
            (&from_h.std, &direct.std),
        ]
        .into_iter()
        .chain(from_h.quantiles.iter().zip(&direct.quantiles))
        {
            for (x, y) in a.iter().zip(b) {
                assert!((x - y).abs() < 1e-12, "{a:?} vs {b:?}");
            }
        }
    }
}
