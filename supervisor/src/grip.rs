//! Sensorless grip force (paper, "Sensorless grip force"): from the same `Present_Current` read
//! the stall detector uses, f̂ = clip((|I| − I_idle)/(I_max − I_idle), 0, 1).

use crate::config::GripCalibration;

/// The normalised grip force of a current reading.
pub fn grip_force(current_a: f32, c: &GripCalibration) -> f32 {
    ((current_a.abs() - c.idle_current_a) / (c.max_current_a - c.idle_current_a)).clamp(0.0, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    const C: GripCalibration = GripCalibration {
        idle_current_a: 0.1,
        max_current_a: 0.6,
    };

    #[test]
    fn clipped_linear_map() {
        assert_eq!(grip_force(0.0, &C), 0.0);
        assert_eq!(grip_force(0.1, &C), 0.0);
        assert!((grip_force(0.35, &C) - 0.5).abs() < 1e-6);
        assert!(
            (grip_force(-0.35, &C) - 0.5).abs() < 1e-6,
            "sign of the current does not matter"
        );
        assert_eq!(grip_force(2.0, &C), 1.0);
        assert!(
            grip_force(f32::NAN, &C).is_nan(),
            "a NaN reading is not hidden"
        );
    }

    #[test]
    fn monotone_in_current() {
        let mut last = -1.0;
        for k in 0..100 {
            let f = grip_force(k as f32 * 0.01, &C);
            assert!(f >= last);
            last = f;
        }
    }
}
