//! Why an extension is named or not: the first test it failed, with its figures, as a type
//! (the report and `--json` print it as the sentence its `Display` writes).

use crate::analysis::{HELDOUT_SIZE, MIN_HELDOUT_T, PRACTICAL_OF_FLOOR};
use crate::catalog::Effect;
use crate::motion::{DIRECTIONAL_MIN_ASYMMETRY, MOTION_MIN_MAE_CUT, MOTION_PRACTICAL_GAIN};
use serde::ser::{Serialize, SerializeMap, Serializer};
use std::fmt;

/// An extension's verdict (thermal and electrical channels, [`crate::analysis`]; motion
/// channel, [`crate::motion`]), in the order the tests are taken.
#[derive(Debug, Clone, PartialEq)]
pub enum Verdict {
    /// Every test passed.
    Supported,
    /// A pair's second whose fitting-part test alone fell short, supported on it and the
    /// held-out slope together.
    SupportedWithHeldout {
        /// The combined (Fisher) p-value.
        fisher_p: f64,
        /// What the fitting part alone said.
        alone: Box<Verdict>,
    },
    /// A first that stood only with its second.
    SupportedBeside {
        /// The second.
        second: Effect,
        /// What it said alone.
        alone: Box<Verdict>,
    },
    /// The motion channel's calibrated nominal model: the baseline, not a candidate.
    Nominal,
    /// Its parameter lies outside what its physics allows.
    OutsidePhysics {
        /// The fitted value.
        value: f64,
        /// The range allowed.
        lo: f64,
        /// The range allowed.
        hi: f64,
        /// What its physics allows, in words (why the range is what it is).
        why: &'static str,
    },
    /// Its size is within the model's own tolerances or the readings' noise.
    Negligible {
        /// The fitted value.
        value: f64,
        /// Below this counts as none.
        below: f64,
        /// Why a size below `below` is none, in words (the tolerances or the noise it is within).
        why: &'static str,
    },
    /// The fitting part's test falls short.
    NotSignificant {
        /// Its p-value.
        p: f64,
        /// The per-test level.
        alpha: f64,
    },
    /// Named on held-out evidence, the readings follow a correction of another size.
    HeldOutSize {
        /// The held-out slope.
        slope: f64,
    },
    /// The BIC does not improve.
    NoBicGain {
        /// ΔBIC.
        delta_bic: f64,
    },
    /// The held-out readings do not follow the extension's correction.
    NotFollowed {
        /// The held-out slope.
        slope: f64,
        /// Its t statistic.
        t: f64,
    },
    /// An uninformative held-out part that goes against the extension.
    Against {
        /// The slope's block standard error.
        slope_se: f64,
        /// The slope's t.
        slope_t: f64,
        /// The squared-error reduction's t.
        error_t: f64,
    },
    /// Its held-out error is worse than the nominal model's.
    HeldOutWorse {
        /// Held-out gain (negative).
        gain: f64,
        /// The held-out slope.
        slope: f64,
    },
    /// Its correction of the held-out predictions is too small to matter.
    NoPracticalChange {
        /// RMS of the correction.
        change: f64,
        /// What would matter.
        required: f64,
        /// The channel's noise floor.
        floor: f64,
    },
    /// Where it predicts a change, the held-out readings of one regime follow significantly
    /// less than half of it: a name that explains one regime and not another is no name.
    NotInEveryRegime {
        /// The regime.
        regime: Regime,
        /// The held-out slope there.
        slope: f64,
        /// Its block standard error.
        se: f64,
    },
    /// It removes too little of a misfit beyond the noise.
    ExplainsTooLittle {
        /// Held-out gain.
        gain: f64,
        /// What would matter.
        required: f64,
    },
    /// A pair's second, supported against the first, whose pair is not against the nominal
    /// model.
    PairNotSupported {
        /// The first.
        first: Effect,
        /// The pair's verdict against the nominal model.
        whole: Box<Verdict>,
    },
    /// Beside the second, the first's parameter moves out of its physics.
    FirstOutsidePhysics {
        /// The first.
        first: Effect,
        /// Its refitted value.
        value: f64,
    },
    /// Motion: a parameter at the edge of (or beyond) what its physics allows on some fold.
    AtPhysicsEdge,
    /// Motion: its size, in its own unit, is negligible.
    TooSmall {
        /// The parameter.
        name: &'static str,
        /// Its value.
        value: f64,
        /// Below this counts as none.
        below: f64,
        /// Its unit.
        unit: &'static str,
    },
    /// Motion: a directional friction whose sides are one friction.
    OneFriction {
        /// The fitted friction ratio while driving the load (`drive_friction_ratio`).
        drive: f64,
        /// The fitted friction ratio while back-driven by it (`back_friction_ratio`).
        back: f64,
    },
    /// Motion: the held-out error does not drop by what matters.
    NoPracticalMaeCut {
        /// The nominal model's mean held-out MAE, rad.
        nominal_mae: f64,
        /// Its own, rad.
        mae: f64,
        /// Relative reduction.
        gain: f64,
    },
    /// Motion: better on too few held-out runs.
    FewRunsBetter {
        /// Runs improved.
        improved: usize,
        /// Runs held out.
        runs: usize,
    },
}

/// A part of the held-out readings in which an extension's prediction must hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Regime {
    /// Readings where the motor carries little current (under a tenth of its held-out peak).
    Idle,
    /// Readings where it carries more.
    Load,
    /// One motor's readings.
    Motor(i64),
}

impl Regime {
    /// Why a name is refused for this regime.
    fn not_followed(self, f: &mut fmt::Formatter<'_>, slope: f64, se: f64) -> fmt::Result {
        write!(
            f,
            "not followed {self}: the held-out readings there follow {slope:.2} of its \
             correction (s.e. {se:.2}), significantly less than half; a name that explains one \
             regime and not another is no name"
        )
    }
}

impl fmt::Display for Regime {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Regime::Idle => write!(f, "at idle"),
            Regime::Load => write!(f, "under load"),
            Regime::Motor(id) => write!(f, "on motor {id}"),
        }
    }
}

impl Verdict {
    /// Whether it names the extension.
    pub fn supported(&self) -> bool {
        matches!(
            self,
            Verdict::Supported
                | Verdict::SupportedWithHeldout { .. }
                | Verdict::SupportedBeside { .. }
        )
    }
}

impl fmt::Display for Verdict {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Verdict::Supported => write!(f, "supported"),
            Verdict::SupportedWithHeldout { fisher_p, alone } => write!(
                f,
                "supported on the fitting part and the held-out slope together (Fisher p = \
                 {fisher_p:.2e}; the fitting part alone: {alone})"
            ),
            Verdict::SupportedBeside { second, alone } => {
                write!(f, "supported beside {second} (alone: {alone})")
            }
            Verdict::Nominal => write!(
                f,
                "the calibrated nominal model (Coulomb and viscous friction)"
            ),
            Verdict::OutsidePhysics { value, lo, hi, why } => write!(
                f,
                "parameter {value:.4} outside what its physics allows, [{lo}, {hi}]: {why}"
            ),
            Verdict::Negligible { value, below, why } => write!(
                f,
                "too small to be a finding: {value:.4} (below {below:.4} counts as none: {why})"
            ),
            Verdict::NotSignificant { p, alpha } => {
                write!(f, "not significant (p = {p:.2e} ≥ {alpha:.1e})")
            }
            Verdict::HeldOutSize { slope } => write!(
                f,
                "the held-out readings follow {slope:.2} times its correction: named on \
                 held-out evidence, it must be about its fitted size ({:.1}–{:.1})",
                HELDOUT_SIZE.start(),
                HELDOUT_SIZE.end()
            ),
            Verdict::NoBicGain { delta_bic } => {
                write!(f, "BIC does not improve (ΔBIC = {delta_bic:.1})")
            }
            Verdict::NotInEveryRegime { regime, slope, se } => regime.not_followed(f, *slope, *se),
            Verdict::NotFollowed { slope, t } => write!(
                f,
                "held-out readings do not follow the extension (slope {slope:.2}, t = {t:.2} < \
                 {MIN_HELDOUT_T})"
            ),
            Verdict::Against {
                slope_se,
                slope_t,
                error_t,
            } => write!(
                f,
                "held-out part uninformative (slope s.e. {slope_se:.2}) and against the \
                 extension (slope t = {slope_t:.2}, error-reduction t = {error_t:.2})"
            ),
            Verdict::HeldOutWorse { gain, slope } => write!(
                f,
                "held-out error worse (gain {:.1} %, slope {slope:.2})",
                100.0 * gain
            ),
            Verdict::NoPracticalChange {
                change,
                required,
                floor,
            } => write!(
                f,
                "no practical difference: it changes the held-out predictions by {change:.4} \
                 RMS, {required:.4} would matter ({PRACTICAL_OF_FLOOR} of the noise floor \
                 {floor:.4})"
            ),
            Verdict::ExplainsTooLittle { gain, required } => write!(
                f,
                "explains too little: held-out gain {:.2} % of a misfit beyond the noise, {:.0} \
                 % would matter",
                100.0 * gain,
                100.0 * required
            ),
            Verdict::PairNotSupported { first, whole } => write!(
                f,
                "with {first}, not supported against the nominal model: {whole}"
            ),
            Verdict::FirstOutsidePhysics { first, value } => write!(
                f,
                "beside it, {first} moves to {value:.4}, outside what its physics allows"
            ),
            Verdict::AtPhysicsEdge => write!(
                f,
                "a parameter at the edge of (or beyond) what its physics allows"
            ),
            Verdict::TooSmall {
                name,
                value,
                below,
                unit,
            } => write!(
                f,
                "too small to be a finding: {name} {value:.4} {unit} (below {below:.4} {unit} \
                 counts as none)"
            ),
            Verdict::OneFriction { drive, back } => write!(
                f,
                "one friction, not a directional one: driving {drive:.3} and back-driven \
                 {back:.3} differ by {:.0} % of the larger ({:.0} % would be directional)",
                100.0 * (drive - back).abs() / drive.max(*back),
                100.0 * DIRECTIONAL_MIN_ASYMMETRY
            ),
            Verdict::NoPracticalMaeCut {
                nominal_mae,
                mae,
                gain,
            } => write!(
                f,
                "no practical difference: held-out MAE {nominal_mae:.5} → {mae:.5} rad ({:+.1} \
                 %; {:.0} % and a sixteenth of an encoder step, {MOTION_MIN_MAE_CUT:.5} rad, \
                 would matter)",
                100.0 * gain,
                100.0 * MOTION_PRACTICAL_GAIN
            ),
            Verdict::FewRunsBetter { improved, runs } => {
                write!(f, "better on only {improved} of {runs} held-out runs")
            }
        }
    }
}

/// As `--json` has always printed it: `"supported": bool, "verdict": "the sentence"` (flattened
/// into the candidate).
impl Serialize for Verdict {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut map = s.serialize_map(Some(2))?;
        map.serialize_entry("supported", &self.supported())?;
        map.serialize_entry("verdict", &self.to_string())?;
        map.end()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_supported_kinds_name_an_extension_and_json_keeps_its_two_fields() {
        let alone = Box::new(Verdict::NoBicGain { delta_bic: -1.0 });
        for (v, named) in [
            (Verdict::Supported, true),
            (
                Verdict::SupportedWithHeldout {
                    fisher_p: 1e-4,
                    alone: alone.clone(),
                },
                true,
            ),
            (
                Verdict::SupportedBeside {
                    second: Effect::SensorLag,
                    alone: alone.clone(),
                },
                true,
            ),
            (Verdict::Nominal, false),
            (
                Verdict::NotSignificant {
                    p: 0.5,
                    alpha: 1e-3,
                },
                false,
            ),
            (
                Verdict::PairNotSupported {
                    first: Effect::AmbientDrift,
                    whole: alone,
                },
                false,
            ),
        ] {
            assert_eq!(v.supported(), named, "{v}");
            let json = serde_json::to_value(&v).unwrap();
            assert_eq!(json["supported"], named);
            assert_eq!(json["verdict"], v.to_string());
        }
        assert_eq!(
            Verdict::NotSignificant {
                p: 0.5,
                alpha: 1e-3
            }
            .to_string(),
            "not significant (p = 5.00e-1 ≥ 1.0e-3)"
        );
    }
}
