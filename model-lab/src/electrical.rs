//! The electrical channel: the supply voltage the servos report.
//!
//! The nominal electrical model has a constant supply (one level per servo, to allow for each
//! servo's own ADC calibration and wiring). The `supply_sag` extension lets it drop with the
//! bus current, V = V0 − R_s·Σ|I| over the servos of the chain, the same law as the simulator's
//! `supply-resistance-ohm`. When the data carry no current column (BAM's logs), the current is
//! estimated from the firmware's position loop, duty = kp·0.166·(goal − position) clamped at
//! 0.97, and the motor equation I = (duty·V − ke·ω)/R with the servo's rated constants.

use crate::data::Dataset;
use crate::stats;

/// Constants to estimate a servo's current when it was not logged.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct CurrentEstimator {
    /// Position gain register (Feetech default 32).
    pub kp: f64,
    /// Winding resistance, Ω.
    pub resistance_ohm: f64,
    /// Back-EMF constant at the output, V·s/rad.
    pub ke_v_s_per_rad: f64,
}

/// Duty per kp per radian of position error (BAM's identification of the Feetech firmware).
const DUTY_PER_KP_RAD: f64 = 0.166;
/// The firmware's duty ceiling.
const MAX_DUTY: f64 = 0.97;

/// The electrical channel's inputs.
#[derive(Debug, Clone)]
pub struct ElectricalData {
    /// Dataset motor index of each motor with voltage readings.
    pub motors: Vec<usize>,
    /// Voltage readings, V (NaN where missing).
    pub voltage: Vec<Vec<f64>>,
    /// Σ|I| over each motor's bus, A (missing currents held).
    pub bus_current: Vec<Vec<f64>>,
    /// Where the current came from: "measured" or "estimated".
    pub current_source: &'static str,
    /// First held-out sample.
    pub split: usize,
}

/// Fills missing values with the previous one (0 before the first).
pub fn hold(x: &[f64]) -> Vec<f64> {
    let mut last = x.iter().copied().find(|v| v.is_finite()).unwrap_or(0.0);
    x.iter()
        .map(|v| {
            if v.is_finite() {
                last = *v;
            }
            last
        })
        .collect()
}

impl ElectricalData {
    /// The channel's data, or None when no voltage was logged or no current can be had.
    pub fn new(d: &Dataset, split: usize, estimator: Option<CurrentEstimator>) -> Option<Self> {
        let motors: Vec<usize> = (0..d.motors.len())
            .filter(|&m| d.voltage[m].iter().filter(|v| v.is_finite()).count() >= 10)
            .collect();
        if motors.is_empty() {
            return None;
        }
        let measured = crate::data::has_values(&d.current);
        let currents: Vec<Vec<f64>> = if measured {
            d.current.iter().map(|c| hold(c)).collect()
        } else {
            let est = estimator?;
            let (g, p, v) = (&d.goal, &d.position, &d.velocity);
            if !(crate::data::has_values(g) && crate::data::has_values(p)) {
                return None;
            }
            let vmean = stats::mean(&d.voltage.concat());
            (0..d.motors.len())
                .map(|m| {
                    let (g, p, w) = (hold(&g[m]), hold(&p[m]), hold(&v[m]));
                    // With torque disabled the bridge is open: no current, whatever the error.
                    let on = |k: usize| d.torque_enabled[m].get(k).is_none_or(|t| *t != 0.0);
                    (0..d.t.len())
                        .map(|k| {
                            if !on(k) {
                                return 0.0;
                            }
                            let duty = (est.kp * DUTY_PER_KP_RAD * (g[k] - p[k]))
                                .clamp(-MAX_DUTY, MAX_DUTY);
                            (duty * vmean - est.ke_v_s_per_rad * w[k]) / est.resistance_ohm
                        })
                        .collect()
                })
                .collect()
        };
        let bus_current = motors
            .iter()
            .map(|&m| {
                let bus = d.bus_of(m);
                (0..d.t.len())
                    .map(|k| bus.iter().map(|&j| currents[j][k].abs()).sum())
                    .collect()
            })
            .collect();
        Some(ElectricalData {
            voltage: motors.iter().map(|&m| d.voltage[m].clone()).collect(),
            motors,
            bus_current,
            current_source: if measured { "measured" } else { "estimated" },
            split,
        })
    }

    /// Voltage readings in the fitting part.
    pub fn fit_count(&self) -> usize {
        self.voltage
            .iter()
            .map(|v| v[..self.split].iter().filter(|x| x.is_finite()).count())
            .sum()
    }
}

/// A fitted electrical model: per-motor levels and the shared supply resistance (0 nominal).
#[derive(Debug, Clone)]
pub struct ElectricalFit {
    /// Supply level per motor, V.
    pub v0: Vec<f64>,
    /// Supply resistance, Ω (0 for the nominal model).
    pub resistance_ohm: f64,
    /// Sum of squared residuals on the fitting part.
    pub sse: f64,
}

impl ElectricalFit {
    /// Predicted voltage of motor `m` (channel index) over the record.
    pub fn predict(&self, e: &ElectricalData, m: usize) -> Vec<f64> {
        e.bus_current[m]
            .iter()
            .map(|i| self.v0[m] - self.resistance_ohm * i)
            .collect()
    }
}

/// Least squares on the fitting part: per-motor levels, and the resistance when `sag`.
pub fn fit(e: &ElectricalData, sag: bool) -> ElectricalFit {
    let fit_pairs = |m: usize| {
        (0..e.split)
            .filter(move |&k| e.voltage[m][k].is_finite())
            .map(move |k| (e.bus_current[m][k], e.voltage[m][k]))
    };
    // Within-motor centring eliminates the levels; the slope is shared.
    let (mut sxy, mut sxx) = (0.0, 0.0);
    let mut means = Vec::new();
    for m in 0..e.motors.len() {
        let n = fit_pairs(m).count().max(1) as f64;
        let (mi, mv) = fit_pairs(m).fold((0.0, 0.0), |(a, b), (i, v)| (a + i / n, b + v / n));
        for (i, v) in fit_pairs(m) {
            sxy += (i - mi) * (v - mv);
            sxx += (i - mi) * (i - mi);
        }
        means.push((mi, mv));
    }
    let r = if sag && sxx > 0.0 { -sxy / sxx } else { 0.0 };
    let v0: Vec<f64> = means.iter().map(|(mi, mv)| mv + r * mi).collect();
    let sse = (0..e.motors.len())
        .map(|m| {
            fit_pairs(m)
                .map(|(i, v)| (v0[m] - r * i - v).powi(2))
                .sum::<f64>()
        })
        .sum();
    ElectricalFit {
        v0,
        resistance_ohm: r,
        sse,
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use crate::data::{parse_csv, Dataset, Meta};

    #[test]
    fn estimated_current_follows_the_error_and_is_zero_with_torque_off() {
        let text = "t_s,motor,goal_rad,position_rad,velocity_rad_s,voltage_v,torque_enabled\n\
                    0.00,1,0.10,0.00,0,12.0,1\n0.02,1,0.10,0.05,0,12.0,1\n\
                    0.04,1,0.10,0.00,0,12.0,0\n0.06,1,0.00,0.00,0,12.0,1\n";
        let rows = parse_csv(text, "x").unwrap();
        let d = Dataset::from_runs(vec![("x".into(), rows)], Meta::default(), "x").unwrap();
        assert_eq!(d.torque_enabled[0], [1.0, 1.0, 0.0, 1.0]);
        let est = CurrentEstimator {
            kp: 32.0,
            resistance_ohm: 2.0,
            ke_v_s_per_rad: 1.0,
        };
        // Fewer than 10 voltage readings: no channel.
        assert!(ElectricalData::new(&d, 2, Some(est)).is_none());
        let mut d10 = d.clone();
        for col in [
            &mut d10.voltage,
            &mut d10.goal,
            &mut d10.position,
            &mut d10.velocity,
            &mut d10.torque_enabled,
            &mut d10.current,
            &mut d10.temperature,
        ] {
            let c = col[0].clone();
            col[0] = c.iter().cycle().take(12).copied().collect();
        }
        d10.t = (0..12).map(|k| 0.02 * k as f64).collect();
        let e = ElectricalData::new(&d10, 8, Some(est)).unwrap();
        assert_eq!(e.current_source, "estimated");
        let i = &e.bus_current[0];
        // duty = 32·0.166·error, I = duty·12 V / 2 Ω.
        assert!(
            (i[0] - 32.0 * 0.166 * 0.10 * 12.0 / 2.0).abs() < 1e-9,
            "{i:?}"
        );
        assert!((i[1] - 32.0 * 0.166 * 0.05 * 12.0 / 2.0).abs() < 1e-9);
        assert_eq!(i[2], 0.0, "torque off: no current despite the error");
        assert_eq!(i[3], 0.0);
    }
}
