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
}

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
        NoiseFloor {
            quantum,
            readings_noise,
            floor: (quantum * quantum / 12.0 + readings_noise * readings_noise).sqrt(),
        }
    }

    /// A held-out misfit (RMSE, bias, in `unit`) held against this floor.
    pub fn judge(&self, rmse: f64, bias: f64, unit: &'static str) -> AgainstFloor {
        let (rmse_floors, bias_floors) = (rmse / self.floor, bias.abs() / self.floor);
        AgainstFloor {
            rmse,
            bias,
            unit,
            floor: *self,
            rmse_floors,
            bias_floors,
            // NaN (no residuals) is no evidence of a misfit.
            significant: rmse_floors > MISFIT_RMSE_FLOORS || bias_floors > MISFIT_BIAS_FLOORS,
        }
    }
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
    /// Beyond [`MISFIT_RMSE_FLOORS`] of RMSE or [`MISFIT_BIAS_FLOORS`] of bias.
    pub significant: bool,
}

impl std::fmt::Display for AgainstFloor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let Self { rmse, unit, .. } = self;
        write!(
            f,
            "held-out RMSE {rmse:.3} {unit} = {:.1} noise floors, |bias| {:.3} {unit} = {:.1} \
             (floor {:.3} {unit}: step {} {unit}, readings' noise {:.3} {unit}); significant \
             beyond {MISFIT_RMSE_FLOORS} floors of RMSE or {MISFIT_BIAS_FLOORS} of bias",
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
