//! The action gate: every action chunk from off-board inference is checked here before any of
//! it can reach the driver. Pure: bytes and the robot's time in, a chunk or a reason out.
//!
//! A chunk is refused whole, with a reason, when it is malformed or of another schema version,
//! has the wrong shape, carries a non-finite or out-of-range target (a joint outside its
//! calibrated range, the lift outside its travel, the base faster than its limits), was computed from an
//! observation older than `max-age-ms` (or one the robot has not made yet), does not come
//! after the last accepted chunk (a replay or a reordering), or was computed from an
//! observation made before the driver last recovered (a driver restart or a safe state: the
//! robot is not where that plan thought it was), or arrives while the driver is in its safe
//! state. The gate watches the driver's state frames for that ([`ActionGate::observe_driver`]).

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
    /// The limits of the lift's and the base's targets.
    pub body: BodyLimits,
}

/// What a policy may ask of the lift and the base.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BodyLimits {
    /// The lift's heights, m above its lowest.
    pub lift_m: Range,
    /// The fastest forward or backward speed, m/s.
    pub max_linear_m_s: f32,
    /// The fastest turn rate either way, rad/s.
    pub max_angular_rad_s: f32,
}

impl BodyLimits {
    /// The range of body axis `axis` ([`BODY_AXES`] order).
    fn range(&self, axis: usize) -> Range {
        match axis {
            0 => self.lift_m,
            1 => Range {
                min: -self.max_linear_m_s,
                max: self.max_linear_m_s,
            },
            _ => Range {
                min: -self.max_angular_rad_s,
                max: self.max_angular_rad_s,
            },
        }
    }

    /// Whether the lift's and the base's values of `target` are within the limits: the check
    /// they pass once more before they leave the agent.
    pub fn within(&self, lift_m: Option<f32>, base_twist: Option<[f32; 2]>) -> bool {
        let ok = |axis: usize, v: f32| {
            let r = self.range(axis);
            (r.min..=r.max).contains(&v)
        };
        lift_m.is_none_or(|h| ok(0, h)) && base_twist.is_none_or(|[v, w]| ok(1, v) && ok(2, w))
    }
}

/// The body's axes in a chunk, by name, in the order of [`BodyLimits::range`].
pub const BODY_AXES: [&str; 3] = ["lift_m", "base_linear_m_s", "base_angular_rad_s"];

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
    /// A lift or base target that is NaN or infinite.
    #[error("step {step} {axis}: target is not finite")]
    BodyNotFinite {
        /// Step index.
        step: usize,
        /// [`BODY_AXES`] name.
        axis: &'static str,
    },
    /// A lift or base target beyond its limits.
    #[error("step {step} {axis}: {value} is outside [{min}, {max}]")]
    BodyOutOfRange {
        /// Step index.
        step: usize,
        /// [`BODY_AXES`] name.
        axis: &'static str,
        /// The target, in the axis's unit (m, m/s or rad/s, as its name ends).
        value: f32,
        /// The axis's lower limit, in the same unit.
        min: f32,
        /// The axis's upper limit, in the same unit.
        max: f32,
    },
    /// Outside the calibrated range.
    #[error("step {step} joint {joint}: {value} rad is outside the calibrated [{min}, {max}]")]
    OutOfRange {
        /// Step index.
        step: usize,
        /// Joint index.
        joint: usize,
        /// The target, rad.
        value: f32,
        /// The calibrated range's lower end, rad.
        min: f32,
        /// The calibrated range's upper end, rad.
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
    /// The driver is in its safe state (or has not been seen driving yet).
    #[error("the driver is in its safe state: nothing planned now may move the arm")]
    SafeState,
    /// Computed from an observation older than the driver's last recovery.
    #[error("observation {observation_ns} is from before the driver's recovery at {recovered_ns}")]
    BeforeRecovery {
        /// The chunk's.
        observation_ns: u64,
        /// When the driver left its last safe state (or restarted), robot time.
        recovered_ns: u64,
    },
}

/// Names of the rejection reasons, in counter order.
pub const REASONS: [&str; 11] = [
    "malformed",
    "version",
    "shape",
    "not_finite",
    "out_of_range",
    "stale",
    "future",
    "replayed",
    "no_layout",
    "safe_state",
    "before_recovery",
];

impl Rejection {
    /// Index into [`REASONS`].
    pub fn reason_index(&self) -> usize {
        match self {
            Rejection::Malformed(_) => 0,
            Rejection::Version(_) => 1,
            Rejection::Shape(_) => 2,
            Rejection::NotFinite { .. } | Rejection::BodyNotFinite { .. } => 3,
            Rejection::OutOfRange { .. } | Rejection::BodyOutOfRange { .. } => 4,
            Rejection::Stale { .. } => 5,
            Rejection::Future { .. } => 6,
            Rejection::Replayed { .. } => 7,
            Rejection::NoLayout => 8,
            Rejection::SafeState => 9,
            Rejection::BeforeRecovery { .. } => 10,
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
    /// When the driver was last seen leaving its safe state (or restarting out of it), robot
    /// time; `None` while it is in its safe state or has not been seen.
    recovered_ns: Option<u64>,
    /// The last driver frame's sequence number (a driver restart starts it again).
    driver_seq: u64,
    accepted: u64,
    rejected: [u64; REASONS.len()],
}

impl ActionGate {
    /// A gate with nothing accepted yet.
    pub fn new(config: GateConfig) -> Self {
        ActionGate {
            config,
            last: None,
            recovered_ns: None,
            driver_seq: 0,
            accepted: 0,
            rejected: [0; REASONS.len()],
        }
    }

    /// What a policy may ask of the lift and the base.
    pub fn body_limits(&self) -> &BodyLimits {
        &self.config.body
    }

    /// Chunks accepted so far.
    pub fn accepted(&self) -> u64 {
        self.accepted
    }

    /// Chunks refused so far, per reason ([`REASONS`] order).
    pub fn rejected(&self) -> &[u64; REASONS.len()] {
        &self.rejected
    }

    /// Feeds one of the driver's joint-state frames (every one, in order). Returns true when
    /// the plan in force must be dropped: the driver entered its safe state or restarted, and
    /// nothing planned before may move the arm. From the first frame out of the safe state on,
    /// chunks are accepted again if computed from an observation made after it.
    pub fn observe_driver(&mut self, seq: u64, timestamp_ns: u64, safe_state: bool) -> bool {
        let restarted = seq <= self.driver_seq;
        self.driver_seq = seq;
        let drop_plan = (safe_state || restarted) && self.recovered_ns.is_some();
        if safe_state {
            self.recovered_ns = None;
        } else if restarted || self.recovered_ns.is_none() {
            self.recovered_ns = Some(timestamp_ns);
        }
        drop_plan || (restarted && !safe_state)
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
        check_body(&chunk, &self.config.body)?;
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
        let Some(recovered_ns) = self.recovered_ns else {
            return Err(Rejection::SafeState);
        };
        if chunk.observation_ns < recovered_ns {
            return Err(Rejection::BeforeRecovery {
                observation_ns: chunk.observation_ns,
                recovered_ns,
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

/// Whether every joint of `mask` has its value in `ranges` (finite, inside the calibrated
/// range): the check a target passes once more before it leaves the agent.
pub fn within(ranges: &[Range], position: &[f32], mask: u32) -> bool {
    (0..32usize).filter(|j| mask & (1 << j) != 0).all(|j| {
        matches!((ranges.get(j), position.get(j)), (Some(r), Some(&v)) if (r.min..=r.max).contains(&v))
    })
}

/// The lift's and the base's targets: finite and within their limits.
fn check_body(chunk: &ActionChunk, limits: &BodyLimits) -> Result<(), Rejection> {
    let lift = chunk.lift_m.iter().enumerate().map(|(k, &v)| (k, 0, v));
    let base = (chunk.base_twist.iter().enumerate()).map(|(i, &v)| (i / 2, 1 + i % 2, v));
    for (step, axis, value) in lift.chain(base) {
        let name = BODY_AXES[axis];
        if !value.is_finite() {
            return Err(Rejection::BodyNotFinite { step, axis: name });
        }
        let Range { min, max } = limits.range(axis);
        if !(min..=max).contains(&value) {
            return Err(Rejection::BodyOutOfRange {
                step,
                axis: name,
                value,
                min,
                max,
            });
        }
    }
    Ok(())
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
    if chunk.joint_mask & !all != 0 {
        return shape(format!("joint mask {:#x}", chunk.joint_mask));
    }
    if !chunk.lift_m.is_empty() && chunk.lift_m.len() != steps {
        return shape(format!(
            "{} lift heights for {steps} steps (none, or one per step)",
            chunk.lift_m.len()
        ));
    }
    if !chunk.base_twist.is_empty() && chunk.base_twist.len() != 2 * steps {
        return shape(format!(
            "{} base values for {steps} steps (none, or a speed and a turn rate per step)",
            chunk.base_twist.len()
        ));
    }
    if chunk.joint_mask == 0 && chunk.lift_m.is_empty() && chunk.base_twist.is_empty() {
        return shape("commands nothing: joint mask 0, no lift, no base".into());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::schema::{encode, SCHEMA_VERSION};

    use telemetry::clock::MS;
    const RANGES: [Range; 2] = [
        Range {
            min: -1.0,
            max: 1.0,
        },
        Range { min: 0.0, max: 2.0 },
    ];

    const BODY: BodyLimits = BodyLimits {
        lift_m: Range { min: 0.0, max: 0.7 },
        max_linear_m_s: 0.2,
        max_angular_rad_s: 1.0,
    };

    /// A gate whose driver has been driving since robot time 0.
    fn gate() -> ActionGate {
        let mut g = ActionGate::new(GateConfig {
            max_age_ns: 200 * MS,
            max_steps: 64,
            max_span_ns: 2000 * MS,
            body: BODY,
        });
        assert!(!g.observe_driver(1, 0, false));
        g
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
            lift_m: Vec::new(),
            base_twist: Vec::new(),
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
        c.version = SCHEMA_VERSION + 1;
        assert_eq!(refused(&c, now), Rejection::Version(SCHEMA_VERSION + 1));
        assert_eq!(refused(&good, 1201 * MS).reason(), "stale");
        assert_eq!(refused(&good, 999 * MS).reason(), "future");
        let mut g = gate();
        assert_eq!(g.check(&encode(&good), now, &[]), Err(Rejection::NoLayout));
        assert_eq!(
            g.check(&[SCHEMA_VERSION as u8, 0xff, 0xff], now, &RANGES)
                .unwrap_err()
                .reason(),
            "malformed"
        );
    }

    #[test]
    fn the_lift_and_base_are_checked_like_joints() {
        let now = 1050 * MS;
        let mut body = chunk(1, 1000 * MS);
        body.lift_m = vec![0.0, 0.35, 0.7];
        body.base_twist = vec![-0.2, 1.0, 0.0, -1.0, 0.2, 0.0];
        assert!(gate().check(&encode(&body), now, &RANGES).is_ok());
        // The base alone, no joint: a chunk that commands something.
        let mut base_only = body.clone();
        base_only.joint_mask = 0;
        base_only.lift_m.clear();
        assert!(gate().check(&encode(&base_only), now, &RANGES).is_ok());
        let mut nothing = base_only.clone();
        nothing.base_twist.clear();
        assert_eq!(refused(&nothing, now).reason(), "shape");
        for (lift, twist, want) in [
            (
                Some((1, 0.71)),
                None,
                Rejection::BodyOutOfRange {
                    step: 1,
                    axis: "lift_m",
                    value: 0.71,
                    min: 0.0,
                    max: 0.7,
                },
            ),
            (
                Some((0, -0.01)),
                None,
                Rejection::BodyOutOfRange {
                    step: 0,
                    axis: "lift_m",
                    value: -0.01,
                    min: 0.0,
                    max: 0.7,
                },
            ),
            (
                None,
                Some((4, 0.25)),
                Rejection::BodyOutOfRange {
                    step: 2,
                    axis: "base_linear_m_s",
                    value: 0.25,
                    min: -0.2,
                    max: 0.2,
                },
            ),
            (
                None,
                Some((3, -1.5)),
                Rejection::BodyOutOfRange {
                    step: 1,
                    axis: "base_angular_rad_s",
                    value: -1.5,
                    min: -1.0,
                    max: 1.0,
                },
            ),
            (
                Some((2, f32::NAN)),
                None,
                Rejection::BodyNotFinite {
                    step: 2,
                    axis: "lift_m",
                },
            ),
            (
                None,
                Some((1, f32::INFINITY)),
                Rejection::BodyNotFinite {
                    step: 0,
                    axis: "base_angular_rad_s",
                },
            ),
        ] {
            let mut c = body.clone();
            if let Some((i, v)) = lift {
                c.lift_m[i] = v;
            }
            if let Some((i, v)) = twist {
                c.base_twist[i] = v;
            }
            assert_eq!(refused(&c, now), want);
        }
        // One value per step (the base: two), or none.
        let mut c = body.clone();
        c.lift_m.pop();
        assert_eq!(refused(&c, now).reason(), "shape");
        let mut c = body.clone();
        c.base_twist.pop();
        assert_eq!(refused(&c, now).reason(), "shape");
        // The last door: what leaves the agent is within the limits.
        assert!(BODY.within(Some(0.7), Some([-0.2, 1.0])));
        assert!(BODY.within(None, None));
        assert!(!BODY.within(Some(0.71), None));
        assert!(!BODY.within(None, Some([0.0, f32::NAN])));
        assert!(!BODY.within(None, Some([0.21, 0.0])));
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

    #[test]
    fn nothing_planned_before_a_driver_recovery_passes() {
        let mut g = gate();
        assert!(g
            .check(&encode(&chunk(1, 1000 * MS)), 1010 * MS, &RANGES)
            .is_ok());
        // The driver enters its safe state at 1020 (the supervisor went away): the plan must go.
        assert!(!g.observe_driver(2, 1015 * MS, false));
        assert!(g.observe_driver(3, 1020 * MS, true), "drop the plan");
        assert!(!g.observe_driver(4, 1025 * MS, true), "once");
        let during = g.check(&encode(&chunk(2, 1022 * MS)), 1030 * MS, &RANGES);
        assert_eq!(during, Err(Rejection::SafeState));
        // It recovers at 1040: a chunk computed from an observation before that is refused, one
        // from after is accepted.
        assert!(!g.observe_driver(5, 1040 * MS, false));
        let r = g.check(&encode(&chunk(3, 1035 * MS)), 1045 * MS, &RANGES);
        assert_eq!(r.unwrap_err().reason(), "before_recovery");
        assert!(g
            .check(&encode(&chunk(4, 1040 * MS)), 1050 * MS, &RANGES)
            .is_ok());
        // The driver restarts (its frames count from 1 again): the plan goes, and what was
        // observed before its first frame is refused, even if that frame is not flagged safe.
        assert!(
            g.observe_driver(1, 1100 * MS, false),
            "a restart drops the plan"
        );
        let r = g.check(&encode(&chunk(5, 1090 * MS)), 1110 * MS, &RANGES);
        assert_eq!(r.unwrap_err().reason(), "before_recovery");
        assert!(g
            .check(&encode(&chunk(6, 1100 * MS)), 1110 * MS, &RANGES)
            .is_ok());
        // A fresh gate refuses everything until it has seen the driver out of its safe state.
        let mut fresh = ActionGate::new(g.config);
        let r = fresh.check(&encode(&chunk(1, 1000 * MS)), 1010 * MS, &RANGES);
        assert_eq!(r, Err(Rejection::SafeState));
        assert!(!fresh.observe_driver(7, 1000 * MS, true));
        assert!(!fresh.observe_driver(8, 1005 * MS, false));
        assert!(fresh
            .check(&encode(&chunk(1, 1005 * MS)), 1010 * MS, &RANGES)
            .is_ok());
    }
}
