//! What a right model still misses on a channel (its noise floor), and the verdict on the
//! misfit an analysis leaves there: beyond the floor, the cause is `unexplained`.

use super::*;

/// A held-out misfit whose RMSE exceeds this many noise floors is significant.
pub const MISFIT_RMSE_FLOORS: f64 = 2.0;

/// A held-out misfit whose mean error exceeds this many noise floors is significant.
pub const MISFIT_BIAS_FLOORS: f64 = 1.0;

/// What a right model still misses on one channel, judged from the readings alone (no model):
/// the register's rounding (uniform over one step: q/√12) and the readings' own noise, from
/// their second differences within segments (E[(Δ²x)²] = 6σ² for white noise on a signal
/// that is smooth at the sampling rate; it also counts part of the rounding, so the floor
/// errs high, towards `none`).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct NoiseFloor {
    /// The register's step.
    pub quantum: f64,
    /// The readings' high-frequency noise.
    pub readings_noise: f64,
    /// √(q²/12 + σ²).
    pub floor: f64,
    /// What the readings' noise was measured on.
    pub measured_on: FloorBasis,
}

/// What a noise floor's readings noise was measured on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum FloorBasis {
    /// Second differences over whole segments (a signal smooth at the sampling rate).
    SecondDifferences,
    /// Second differences where the readings were at rest: `samples` of them, on `runs`
    /// runs (the motion's own curvature excluded, whatever the speed).
    AtRest {
        /// Second differences used.
        samples: usize,
        /// Runs they came from.
        runs: usize,
    },
    /// No reading was at rest long enough: the register's step alone.
    StepOnly,
}

/// A reading moving by at most this many register steps from the one before is at rest (an
/// encoder's jitter at a standstill is a step or two).
pub const REST_STEPS: f64 = 2.0;
/// Readings in a row at rest before they count (0.1 s at 100 Hz): a reversal's apex is not a
/// rest.
pub const REST_MIN_READINGS: usize = 10;

impl NoiseFloor {
    /// The floor of `series` (per motor, NaN where missing) read in steps of `quantum`.
    pub fn of(series: &[Vec<f64>], quantum: f64, segments: &[(usize, usize)]) -> NoiseFloor {
        let (mut sum, mut n) = (0.0, 0usize);
        for x in series {
            for &(s, e) in segments {
                for k in s + 1..e.min(x.len()).saturating_sub(1) {
                    let d2 = x[k + 1] - 2.0 * x[k] + x[k - 1];
                    if d2.is_finite() {
                        sum += d2 * d2;
                        n += 1;
                    }
                }
            }
        }
        let readings_noise = if n > 0 {
            (sum / n as f64 / 6.0).sqrt()
        } else {
            0.0
        };
        NoiseFloor::with(quantum, readings_noise, FloorBasis::SecondDifferences)
    }

    fn with(quantum: f64, readings_noise: f64, measured_on: FloorBasis) -> NoiseFloor {
        NoiseFloor {
            quantum,
            readings_noise,
            floor: (quantum * quantum / 12.0 + readings_noise * readings_noise).sqrt(),
            measured_on,
        }
    }

    /// The floor of `runs` (each a series of readings, NaN where missing, in steps of
    /// `quantum`) measured where the readings are at rest: [`REST_MIN_READINGS`] or more in a
    /// row, each within [`REST_STEPS`] steps of the one before. There the second differences
    /// see the sensor, not the motion, so the floor does not grow when a run is replayed
    /// faster; with no rest anywhere it is the register's step alone.
    pub fn at_rest(runs: &[Vec<f64>], quantum: f64) -> NoiseFloor {
        let (mut sum, mut n, mut used) = (0.0, 0usize, 0usize);
        for x in runs {
            let before = n;
            for (s, e) in rests(x, quantum) {
                for k in s + 1..e - 1 {
                    let d2 = x[k + 1] - 2.0 * x[k] + x[k - 1];
                    sum += d2 * d2;
                    n += 1;
                }
            }
            used += usize::from(n > before);
        }
        if n == 0 {
            return NoiseFloor::with(quantum, 0.0, FloorBasis::StepOnly);
        }
        let basis = FloorBasis::AtRest {
            samples: n,
            runs: used,
        };
        NoiseFloor::with(quantum, (sum / n as f64 / 6.0).sqrt(), basis)
    }

    /// A held-out misfit (RMSE, bias, in `unit`) held against this floor.
    pub fn judge(&self, rmse: f64, bias: f64, unit: &'static str) -> AgainstFloor {
        self.judge_beyond(rmse, bias, unit, 0.0)
    }

    /// As [`NoiseFloor::judge`], and significant only where the RMSE or the bias also exceeds
    /// `practical` (in `unit`): a misfit too small to matter is none, however well measured.
    pub fn judge_beyond(
        &self,
        rmse: f64,
        bias: f64,
        unit: &'static str,
        practical: f64,
    ) -> AgainstFloor {
        let (rmse_floors, bias_floors) = (rmse / self.floor, bias.abs() / self.floor);
        // NaN (no residuals) is no evidence of a misfit.
        let beyond_floor = rmse_floors > MISFIT_RMSE_FLOORS || bias_floors > MISFIT_BIAS_FLOORS;
        AgainstFloor {
            rmse,
            bias,
            unit,
            floor: *self,
            rmse_floors,
            bias_floors,
            practical,
            significant: beyond_floor && rmse.max(bias.abs()) > practical,
        }
    }
}

/// The stretches `[s, e)` of `x` at rest: [`REST_MIN_READINGS`] or more finite readings in a
/// row, each within [`REST_STEPS`] steps of the one before.
fn rests(x: &[f64], quantum: f64) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut start = 0;
    for k in 1..=x.len() {
        let still = k < x.len()
            && x[k].is_finite()
            && x[k - 1].is_finite()
            && (x[k] - x[k - 1]).abs() <= REST_STEPS * quantum * (1.0 + 1e-9);
        if !still {
            if k - start >= REST_MIN_READINGS {
                out.push((start, k));
            }
            start = k;
        }
    }
    out
}

/// A held-out misfit held against a channel's noise floor ([`NoiseFloor::judge`]).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct AgainstFloor {
    /// Held-out RMSE.
    pub rmse: f64,
    /// Held-out mean error.
    pub bias: f64,
    /// Unit of both.
    pub unit: &'static str,
    /// The floor.
    pub floor: NoiseFloor,
    /// The RMSE in floors.
    pub rmse_floors: f64,
    /// |bias| in floors.
    pub bias_floors: f64,
    /// The size below which a misfit does not matter, in `unit` (0: none).
    pub practical: f64,
    /// Beyond [`MISFIT_RMSE_FLOORS`] of RMSE or [`MISFIT_BIAS_FLOORS`] of bias, and beyond
    /// `practical`.
    pub significant: bool,
}

impl std::fmt::Display for AgainstFloor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let Self { rmse, unit, .. } = self;
        let on = match self.floor.measured_on {
            FloorBasis::SecondDifferences => String::new(),
            FloorBasis::AtRest { samples, runs } => {
                format!(" at rest, {samples} readings on {runs} run(s)")
            }
            FloorBasis::StepOnly => " (no reading at rest: the step alone)".into(),
        };
        let practical = if self.practical > 0.0 {
            format!(
                ", and beyond {:.4} {unit}, the size that matters",
                self.practical
            )
        } else {
            String::new()
        };
        write!(
            f,
            "held-out RMSE {rmse:.3} {unit} = {:.1} noise floors, |bias| {:.3} {unit} = {:.1} \
             (floor {:.4} {unit}: step {} {unit}, readings' noise {:.4} {unit}{on}); \
             significant beyond {MISFIT_RMSE_FLOORS} floors of RMSE or {MISFIT_BIAS_FLOORS} of \
             bias{practical}",
            self.rmse_floors,
            self.bias.abs(),
            self.bias_floors,
            self.floor.floor,
            (self.floor.quantum * 1e6).round() / 1e6,
            self.floor.readings_noise
        )
    }
}

/// One channel's held-out misfit once its best supported extension (if any) is applied.
#[derive(Debug, Clone, Serialize)]
pub struct ChannelVerdict {
    /// The channel.
    pub channel: Channel,
    /// Its best supported extension, if any.
    pub extension: Option<Effect>,
    /// Held-out RMSE with it (or the nominal model's).
    pub rmse: f64,
    /// Held-out mean error with it.
    pub bias: f64,
    /// Unit of both.
    pub unit: &'static str,
    /// Beyond the noise floor, pooled or on its worst motor: the model misses something still.
    pub significant: bool,
    /// All motors pooled, against the floor.
    pub pooled: AgainstFloor,
    /// The worst motor judged on its own (one motor's misfit must not drown in its
    /// well-fitted neighbours'): its id and its misfit against the floor.
    pub worst: Option<(i64, AgainstFloor)>,
}

impl ChannelVerdict {
    /// How it was judged, with the figures.
    pub fn judged(&self) -> String {
        match &self.worst {
            Some((id, w)) => format!("all motors: {}; worst motor {id}: {w}", self.pooled),
            None => format!("all motors: {}", self.pooled),
        }
    }
}

/// Fewest held-out residuals of a motor judged on its own.
pub(super) const MIN_MOTOR_RESIDUALS: usize = 20;

/// The verdict on the misfit `left` (held-out residuals per motor, of motors `ids`) after
/// `extension`: all motors pooled, and each on its own (one motor's misfit must not drown in
/// its well-fitted neighbours'); the worst one is named.
pub(super) fn verdict(
    channel: Channel,
    extension: Option<Effect>,
    ids: &[i64],
    left: &[Vec<f64>],
    unit: &'static str,
    floor: &NoiseFloor,
) -> ChannelVerdict {
    let all = left.concat();
    let (rmse, bias) = (stats::rmse(&all), stats::mean(&all));
    let pooled = floor.judge(rmse, bias, unit);
    let worst = ids
        .iter()
        .zip(left)
        .filter(|(_, r)| r.len() >= MIN_MOTOR_RESIDUALS)
        .map(|(id, r)| (*id, stats::rmse(r), stats::mean(r)))
        .filter(|(_, rmse, bias)| rmse.is_finite() && bias.is_finite())
        .max_by(|a, b| {
            let score = |x: &(i64, f64, f64)| {
                (x.1 / MISFIT_RMSE_FLOORS).max(x.2.abs() / MISFIT_BIAS_FLOORS)
            };
            score(a).total_cmp(&score(b))
        })
        .map(|(id, r, b)| (id, floor.judge(r, b, unit)));
    ChannelVerdict {
        channel,
        extension,
        rmse,
        bias,
        unit,
        significant: pooled.significant || worst.is_some_and(|(_, w)| w.significant),
        pooled,
        worst,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A servo that swings hard between holds, read by a 4096-step encoder with a step of
    /// jitter: the floor at rest is the jitter's, and replayed at twice the speed (every other
    /// reading) it stays within a fifth; the second differences over the whole run take the
    /// swings for noise and grow with the speed.
    #[test]
    fn the_floor_at_rest_does_not_grow_when_a_run_is_replayed_faster() {
        let q = std::f64::consts::TAU / 4096.0;
        let mut rng = 7u64;
        let mut jitter = || {
            // A step up or down one reading in four.
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            match rng >> 62 {
                0 => q,
                1 => -q,
                _ => 0.0,
            }
        };
        let mut x = Vec::new();
        for cycle in 0..6 {
            let hold = if cycle % 2 == 0 { 0.0 } else { 1.5 };
            for _ in 0..60 {
                x.push(((hold + jitter()) / q).round() * q);
            }
            // A swing of 1.5 rad in 0.3 s at 100 Hz.
            for k in 0..30 {
                let s = f64::from(k) / 30.0;
                let p = if cycle % 2 == 0 {
                    1.5 * s
                } else {
                    1.5 * (1.0 - s)
                };
                x.push(((p + 0.5 * (std::f64::consts::PI * s).sin()) / q).round() * q);
            }
        }
        let faster: Vec<f64> = x.iter().step_by(2).copied().collect();
        let (slow, fast) = (
            NoiseFloor::at_rest(std::slice::from_ref(&x), q),
            NoiseFloor::at_rest(std::slice::from_ref(&faster), q),
        );
        assert!(matches!(
            slow.measured_on,
            FloorBasis::AtRest { runs: 1, .. }
        ));
        assert!(
            (fast.floor / slow.floor - 1.0).abs() < 0.2,
            "{} vs {}",
            slow.floor,
            fast.floor
        );
        assert!(slow.readings_noise < 2.0 * q, "{}", slow.readings_noise);
        let whole = |x: &Vec<f64>| NoiseFloor::of(std::slice::from_ref(x), q, &[(0, x.len())]);
        assert!(whole(&x).floor > 3.0 * slow.floor);
        assert!(whole(&faster).floor > 2.0 * whole(&x).floor);
    }

    /// Never at rest: the register's step alone, said so.
    #[test]
    fn a_run_never_at_rest_has_the_step_alone() {
        let q = 0.01;
        let x: Vec<f64> = (0..500).map(|k| f64::from(k) * 0.05).collect();
        let f = NoiseFloor::at_rest(&[x], q);
        assert_eq!(f.measured_on, FloorBasis::StepOnly);
        assert!((f.floor - q / 12f64.sqrt()).abs() < 1e-12);
    }
}
