//! Per-joint calibration and the bus-layer clamp: no commanded position leaves a joint's
//! calibrated range, and a non-finite goal never becomes a number on the wire.
//!
//! Joint angle `q` (rad) and `Present_Position` `p` (steps, after the servo subtracts its
//! `Homing_Offset`) relate as `p = 2048 + direction · q · 4096 / 2π`.

use serde::{Deserialize, Serialize};
use std::f64::consts::TAU;
use thiserror::Error;

/// Steps per radian of output rotation.
pub const STEPS_PER_RAD: f64 = 4096.0 / TAU;
/// `Present_Position` at joint angle 0.
pub const CENTER: f64 = 2048.0;

/// The calibration of one joint.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct JointCalibration {
    /// Written to the servo's `Homing_Offset` (steps, ±2047).
    pub homing_offset: i32,
    /// Lowest goal the joint may be sent, steps.
    pub range_min: i32,
    /// Highest goal the joint may be sent, steps.
    pub range_max: i32,
    /// The servo turns against the joint's positive direction.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub inverted: bool,
}

/// A goal the bus layer refuses.
#[derive(Debug, Clone, Copy, PartialEq, Error)]
pub enum GoalError {
    /// NaN or infinite.
    #[error("goal {value} for joint {joint} is not a finite number")]
    NotFinite {
        /// Joint index.
        joint: usize,
        /// The value.
        value: f32,
    },
}

/// A calibration that cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error("calibration of joint {joint}: {reason}")]
#[allow(missing_docs, reason = "each field is shown in the error's message")]
pub struct CalibrationError {
    /// Joint name.
    pub joint: String,
    pub reason: String,
}

impl JointCalibration {
    /// Checks the range lies inside the encoder's travel and the offset fits its register.
    pub fn validate(&self, joint: &str) -> Result<(), CalibrationError> {
        let fail = |reason: String| {
            Err(CalibrationError {
                joint: joint.into(),
                reason,
            })
        };
        if !(0..=4095).contains(&self.range_min) || !(0..=4095).contains(&self.range_max) {
            return fail(format!(
                "range {}..{} is outside the servo's travel 0..4095",
                self.range_min, self.range_max
            ));
        }
        if self.range_min >= self.range_max {
            return fail(format!(
                "range-min {} must be below range-max {}",
                self.range_min, self.range_max
            ));
        }
        if (self.homing_offset, self.range_min, self.range_max) == (0, 0, 4095) {
            return fail(
                "the factory's values (homing offset 0, range 0..4095): a servo never \
                 calibrated holds the same, so the driver could not tell them apart"
                    .into(),
            );
        }
        if self.homing_offset.abs() > 2047 {
            return fail(format!(
                "homing-offset {} exceeds ±2047",
                self.homing_offset
            ));
        }
        Ok(())
    }

    fn sign(&self) -> f64 {
        if self.inverted {
            -1.0
        } else {
            1.0
        }
    }

    /// Joint angle of a `Present_Position`.
    pub fn to_rad(&self, steps: i32) -> f64 {
        self.sign() * (f64::from(steps) - CENTER) / STEPS_PER_RAD
    }

    /// The goal in steps for joint angle `q`, clamped to the calibrated range. Non-finite goals
    /// are refused: a NaN through `min`/`max` would otherwise become an extreme position.
    pub fn goal_steps(&self, joint: usize, q: f32) -> Result<i32, GoalError> {
        if !q.is_finite() {
            return Err(GoalError::NotFinite { joint, value: q });
        }
        let steps = CENTER + self.sign() * f64::from(q) * STEPS_PER_RAD;
        let clamped = steps.clamp(f64::from(self.range_min), f64::from(self.range_max));
        Ok(clamped.round() as i32)
    }

    /// The calibrated range as joint angles (low, high), rad.
    pub fn range_rad(&self) -> (f64, f64) {
        let (a, b) = (self.to_rad(self.range_min), self.to_rad(self.range_max));
        (a.min(b), a.max(b))
    }
}

/// Speed-mode joints (wheels): goals are speeds, clamped to a maximum, never positions.
pub fn wheel_speed_steps(
    joint: usize,
    rad_s: f32,
    max_rad_s: f64,
    inverted: bool,
) -> Result<i32, GoalError> {
    if !rad_s.is_finite() {
        return Err(GoalError::NotFinite {
            joint,
            value: rad_s,
        });
    }
    let sign = if inverted { -1.0 } else { 1.0 };
    let v = (sign * f64::from(rad_s)).clamp(-max_rad_s, max_rad_s);
    Ok((v * STEPS_PER_RAD).round() as i32)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const CAL: JointCalibration = JointCalibration {
        homing_offset: 0,
        range_min: 1000,
        range_max: 3000,
        inverted: false,
    };

    #[test]
    fn far_outside_goals_clamp_to_the_range() {
        assert_eq!(CAL.goal_steps(0, 100.0), Ok(3000));
        assert_eq!(CAL.goal_steps(0, -100.0), Ok(1000));
        assert_eq!(CAL.goal_steps(0, f32::MAX), Ok(3000));
        assert_eq!(CAL.goal_steps(0, 0.0), Ok(2048));
    }

    #[test]
    fn non_finite_goals_are_refused() {
        for v in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            assert!(matches!(
                CAL.goal_steps(3, v),
                Err(GoalError::NotFinite { joint: 3, .. })
            ));
        }
        assert!(wheel_speed_steps(0, f32::NAN, 5.0, false).is_err());
    }

    /// A calibration equal to a factory-fresh servo's EEPROM would let an uncalibrated servo
    /// pass the driver's check: refused.
    #[test]
    fn the_factorys_values_are_no_calibration() {
        let factory = JointCalibration {
            homing_offset: 0,
            range_min: 0,
            range_max: 4095,
            inverted: false,
        };
        let e = factory.validate("j").unwrap_err();
        assert!(e.reason.contains("factory"), "{e}");
        for near in [
            JointCalibration {
                homing_offset: 1,
                ..factory
            },
            JointCalibration {
                range_max: 4094,
                ..factory
            },
        ] {
            near.validate("j").unwrap();
        }
    }

    #[test]
    fn inverted_joints_map_both_ways() {
        let cal = JointCalibration {
            inverted: true,
            ..CAL
        };
        let steps = cal.goal_steps(0, 0.5).unwrap();
        assert!(steps < 2048);
        assert!((cal.to_rad(steps) - 0.5).abs() < 1.0 / STEPS_PER_RAD);
    }

    #[test]
    fn bad_ranges_are_refused() {
        assert!(JointCalibration {
            range_max: 5000,
            ..CAL
        }
        .validate("j")
        .is_err());
        assert!(JointCalibration {
            range_min: 3000,
            ..CAL
        }
        .validate("j")
        .is_err());
        assert!(JointCalibration {
            homing_offset: 3000,
            ..CAL
        }
        .validate("j")
        .is_err());
        assert!(CAL.validate("j").is_ok());
    }

    proptest! {
        /// Whatever float arrives, the result is either refused or inside the range.
        #[test]
        fn any_goal_lands_inside_the_range(bits in any::<u32>(), min in 0i32..4000, span in 1i32..4000, inverted: bool) {
            let cal = JointCalibration { homing_offset: 0, range_min: min, range_max: (min + span).min(4095), inverted };
            prop_assume!(cal.range_min < cal.range_max);
            let q = f32::from_bits(bits);
            match cal.goal_steps(0, q) {
                Ok(steps) => prop_assert!(steps >= cal.range_min && steps <= cal.range_max),
                Err(_) => prop_assert!(!q.is_finite()),
            }
        }
    }
}
