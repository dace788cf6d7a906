//! The action gate: every action chunk from off-board inference is checked here before any of
//! it can reach the driver. Pure: bytes and the robot's time in, a chunk or a reason out.
//!
//! A chunk is refused whole, with a reason, when it is malformed or of another schema version,
//! has the wrong shape, carries a non-finite or out-of-range target, was computed from an
//! observation older than `max-age-ms` (or one the robot has not made yet), or does not come
//! after the last accepted chunk (a replay or a reordering).

use crate::schema::{decode, ActionChunk, DecodeError};
use thiserror::Error;

/// A joint's calibrated range, rad.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Range {
    /// Low end.
    pub min: f32,
    /// High end.
    pub max: f32,
}

/// The gate's limits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GateConfig {
    /// A chunk whose observation is older than this on arrival is stale, ns.
    pub max_age_ns: u64,
    /// Most steps in one chunk.
    pub max_steps: usize,
    /// The last step may be at most this far after the observation, ns.
    pub max_span_ns: u64,
}

/// Why a chunk was refused.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum Rejection {
    /// Not a chunk.
    #[error("malformed: {0}")]
    Malformed(String),
    /// Another schema version.
    #[error("schema version {0} is not spoken here")]
    Version(u16),
    /// Joint count, step count, target count, step times or mask do not fit.
    #[error("wrong shape: {0}")]
    Shape(String),
    /// NaN or infinite target.
    #[error("step {step} joint {joint}: target is not finite")]
    NotFinite {
        /// Step index.
        step: usize,
        /// Joint index.
        joint: usize,
    },
    /// Outside the calibrated range.
    #[error("step {step} joint {joint}: {value} rad is outside the calibrated [{min}, {max}]")]
    OutOfRange {
        /// Step index.
        step: usize,
        /// Joint index.
        joint: usize,
        /// Target.
        value: f32,
        /// Range.
        min: f32,
        /// Range.
        max: f32,
    },
    /// Computed from an observation too old.
    #[error("stale: observation {age_ms:.1} ms old (limit {limit_ms:.1} ms)")]
    Stale {
        /// Age on arrival.
        age_ms: f64,
        /// The limit.
        limit_ms: f64,
    },
    /// Names an observation later than now.
    #[error("observation time {ahead_ms:.1} ms in the future")]
    Future {
        /// How far ahead.
        ahead_ms: f64,
    },
    /// Not after the last accepted chunk.
    #[error("replayed or reordered: observation {observation_ns} seq {seq} is not after the last accepted ({last_observation_ns}, {last_seq})")]
    Replayed {
        /// The chunk's.
        observation_ns: u64,
        /// The chunk's.
        seq: u64,
        /// The last accepted chunk's.
        last_observation_ns: u64,
        /// The last accepted chunk's.
        last_seq: u64,
    },
    /// The driver's layout is not known yet.
    #[error("no joint layout from the driver yet")]
    NoLayout,
}

/// Names of the rejection reasons, in counter order.
pub const REASONS: [&str; 9] = [
    "malformed",
    "version",
    "shape",
    "not_finite",
    "out_of_range",
    "stale",
    "future",
    "replayed",
    "no_layout",
];

impl Rejection {
    /// Index into [`REASONS`].
    pub fn reason_index(&self) -> usize {
        match self {
            Rejection::Malformed(_) => 0,
            Rejection::Version(_) => 1,
            Rejection::Shape(_) => 2,
            Rejection::NotFinite { .. } => 3,
            Rejection::OutOfRange { .. } => 4,
            Rejection::Stale { .. } => 5,
            Rejection::Future { .. } => 6,
            Rejection::Replayed { .. } => 7,
            Rejection::NoLayout => 8,
        }
    }

    /// Short name ([`REASONS`]).
    pub fn reason(&self) -> &'static str {
        REASONS[self.reason_index()]
    }
}

impl From<DecodeError> for Rejection {
    fn from(e: DecodeError) -> Self {
        match e {
            DecodeError::Malformed(m) => Rejection::Malformed(m),
            DecodeError::Version { got } => Rejection::Version(got),
        }
    }
}

/// Checks chunks and counts what it refused.
#[derive(Debug, Clone)]
pub struct ActionGate {
    config: GateConfig,
    last: Option<(u64, u64)>,
    accepted: u64,
    rejected: [u64; REASONS.len()],
}

impl ActionGate {
    /// A gate with nothing accepted yet.
    pub fn new(config: GateConfig) -> Self {
        ActionGate {
            config,
            last: None,
            accepted: 0,
            rejected: [0; REASONS.len()],
        }
    }

    /// Chunks accepted so far.
    pub fn accepted(&self) -> u64 {
        self.accepted
    }

    /// Chunks refused so far, per reason ([`REASONS`] order).
    pub fn rejected(&self) -> &[u64; REASONS.len()] {
        &self.rejected
    }

    /// Checks `bytes` at robot time `now_ns` against the calibrated `ranges` (the layout, in
    /// joint order; empty when the layout is not known). Counts the outcome.
    pub fn check(
        &mut self,
        bytes: &[u8],
        now_ns: u64,
        ranges: &[Range],
    ) -> Result<ActionChunk, Rejection> {
        let outcome = self.judge(bytes, now_ns, ranges);
        match &outcome {
            Ok(c) => {
                self.accepted += 1;
                self.last = Some((c.observation_ns, c.seq));
            }
            Err(r) => self.rejected[r.reason_index()] += 1,
        }
        outcome
    }

    fn judge(&self, bytes: &[u8], now_ns: u64, ranges: &[Range]) -> Result<ActionChunk, Rejection> {
        let chunk: ActionChunk = decode(bytes)?;
        if ranges.is_empty() {
            return Err(Rejection::NoLayout);
        }
        check_shape(&chunk, ranges.len(), &self.config)?;
        let joints = usize::from(chunk.joint_count);
        for (i, &value) in chunk.targets.iter().enumerate() {
            let (step, joint) = (i / joints, i % joints);
            if !value.is_finite() {
                return Err(Rejection::NotFinite { step, joint });
            }
            let Range { min, max } = ranges[joint];
            if chunk.joint_mask & (1 << joint) != 0 && !(min..=max).contains(&value) {
                return Err(Rejection::OutOfRange {
                    step,
                    joint,
                    value,
                    min,
                    max,
                });
            }
        }
        if chunk.observation_ns > now_ns {
            return Err(Rejection::Future {
                ahead_ms: (chunk.observation_ns - now_ns) as f64 / 1e6,
            });
        }
        let age = now_ns - chunk.observation_ns;
        if age > self.config.max_age_ns {
            return Err(Rejection::Stale {
                age_ms: age as f64 / 1e6,
                limit_ms: self.config.max_age_ns as f64 / 1e6,
            });
        }
        if let Some((last_observation_ns, last_seq)) = self.last {
            if (chunk.observation_ns, chunk.seq) <= (last_observation_ns, last_seq) {
                return Err(Rejection::Replayed {
                    observation_ns: chunk.observation_ns,
                    seq: chunk.seq,
                    last_observation_ns,
                    last_seq,
                });
            }
        }
        Ok(chunk)
    }
}

fn check_shape(chunk: &ActionChunk, joints: usize, config: &GateConfig) -> Result<(), Rejection> {
    let shape = |m: String| Err(Rejection::Shape(m));
    let steps = chunk.step_offsets_ns.len();
    if usize::from(chunk.joint_count) != joints {
        return shape(format!(
            "{} joints, the robot has {joints}",
            chunk.joint_count
        ));
    }
    if steps == 0 || steps > config.max_steps {
        return shape(format!("{steps} steps (1..={})", config.max_steps));
    }
    if chunk.targets.len() != steps * joints {
        return shape(format!(
            "{} targets for {steps} steps × {joints} joints",
            chunk.targets.len()
        ));
    }
    if !chunk.step_offsets_ns.windows(2).all(|w| w[0] < w[1]) {
        return shape("step times do not rise".into());
    }
    if chunk.step_offsets_ns[steps - 1] > config.max_span_ns {
        return shape(format!(
            "last step {:.0} ms after the observation (limit {:.0} ms)",
            chunk.step_offsets_ns[steps - 1] as f64 / 1e6,
            config.max_span_ns as f64 / 1e6
        ));
    }
    let all = if joints >= 32 {
        u32::MAX
    } else {
        (1u32 << joints) - 1
    };
    if chunk.joint_mask == 0 || chunk.joint_mask & !all != 0 {
        return shape(format!("joint mask {:#x}", chunk.joint_mask));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::schema::{encode, SCHEMA_VERSION};

    const MS: u64 = 1_000_000;
    const RANGES: [Range; 2] = [
        Range {
            min: -1.0,
            max: 1.0,
        },
        Range { min: 0.0, max: 2.0 },
    ];

    fn gate() -> ActionGate {
        ActionGate::new(GateConfig {
            max_age_ns: 200 * MS,
            max_steps: 64,
            max_span_ns: 2000 * MS,
        })
    }

    fn chunk(seq: u64, observation_ns: u64) -> ActionChunk {
        ActionChunk {
            version: SCHEMA_VERSION,
            seq,
            observation_ns,
            step_offsets_ns: vec![20 * MS, 40 * MS, 60 * MS],
            joint_count: 2,
            joint_mask: 0b11,
            targets: vec![0.0, 0.5, 0.1, 0.6, 0.2, 0.7],
        }
    }

    fn refused(c: &ActionChunk, now: u64) -> Rejection {
        let mut g = gate();
        let r = g.check(&encode(c), now, &RANGES).unwrap_err();
        assert_eq!(g.rejected()[r.reason_index()], 1);
        assert_eq!(g.accepted(), 0);
        r
    }

    #[test]
    fn a_fresh_valid_chunk_passes() {
        let mut g = gate();
        let c = chunk(1, 1000 * MS);
        assert_eq!(g.check(&encode(&c), 1050 * MS, &RANGES), Ok(c));
        assert_eq!(g.accepted(), 1);
        assert_eq!(g.rejected().iter().sum::<u64>(), 0);
    }

    #[test]
    fn each_bad_chunk_is_refused_with_its_reason() {
        let now = 1050 * MS;
        let good = chunk(1, 1000 * MS);
        let mut c = good.clone();
        c.targets[3] = f32::NAN;
        assert_eq!(refused(&c, now), Rejection::NotFinite { step: 1, joint: 1 });
        c.targets[3] = f32::INFINITY;
        assert_eq!(refused(&c, now).reason(), "not_finite");
        let mut c = good.clone();
        c.targets[4] = 1.2;
        assert_eq!(
            refused(&c, now),
            Rejection::OutOfRange {
                step: 2,
                joint: 0,
                value: 1.2,
                min: -1.0,
                max: 1.0
            }
        );
        // An uncommanded joint's value is not a target and is not range-checked.
        c.joint_mask = 0b10;
        assert!(gate().check(&encode(&c), now, &RANGES).is_ok());
        let mut c = good.clone();
        c.joint_count = 3;
        assert_eq!(refused(&c, now).reason(), "shape");
        let mut c = good.clone();
        c.targets.pop();
        assert_eq!(refused(&c, now).reason(), "shape");
        let mut c = good.clone();
        c.step_offsets_ns = vec![20 * MS, 20 * MS, 60 * MS];
        assert_eq!(refused(&c, now).reason(), "shape");
        let mut c = good.clone();
        c.joint_mask = 0b100;
        assert_eq!(refused(&c, now).reason(), "shape");
        let mut c = good.clone();
        c.step_offsets_ns = vec![];
        c.targets = vec![];
        assert_eq!(refused(&c, now).reason(), "shape");
        let mut c = good.clone();
        c.step_offsets_ns[2] = 5000 * MS;
        assert_eq!(refused(&c, now).reason(), "shape");
        let mut c = good.clone();
        c.version = 9;
        assert_eq!(refused(&c, now), Rejection::Version(9));
        assert_eq!(refused(&good, 1201 * MS).reason(), "stale");
        assert_eq!(refused(&good, 999 * MS).reason(), "future");
        let mut g = gate();
        assert_eq!(g.check(&encode(&good), now, &[]), Err(Rejection::NoLayout));
        assert_eq!(
            g.check(&[0x01, 0xff, 0xff], now, &RANGES)
                .unwrap_err()
                .reason(),
            "malformed"
        );
    }

    #[test]
    fn a_replayed_or_reordered_chunk_is_refused_and_a_new_session_is_not() {
        let mut g = gate();
        let first = encode(&chunk(5, 1000 * MS));
        assert!(g.check(&first, 1010 * MS, &RANGES).is_ok());
        let r = g.check(&first, 1020 * MS, &RANGES).unwrap_err();
        assert_eq!(r.reason(), "replayed");
        // Same observation, older sequence: reordered.
        let older = encode(&chunk(4, 1000 * MS));
        assert_eq!(
            g.check(&older, 1020 * MS, &RANGES).unwrap_err().reason(),
            "replayed"
        );
        // A restarted policy server counts from 1 again, from a newer observation: accepted.
        assert!(g
            .check(&encode(&chunk(1, 1030 * MS)), 1040 * MS, &RANGES)
            .is_ok());
        assert_eq!(g.rejected()[7], 2);
        assert_eq!(g.accepted(), 2);
    }
}
