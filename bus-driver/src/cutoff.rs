//! Inferring the hardware tier from the motor's behaviour. A firmware protection (over-
//! temperature, over-current, overload) unloads the motor; what the driver sees is a motor with
//! torque enabled, far from its goal, whose output (load and current) has vanished. The STS
//! firmware also sets the protection's bit in the status byte, and the supervisor acts on that
//! bit directly; the inference does not depend on it, so a servo that does not announce (or
//! whose announcement is lost) is caught too. Pure: one reading in, a verdict out.

/// Consecutive cycles of vanished output before the cutoff is inferred (50 ms at 200 Hz): a
/// motor passing through zero output on its way to a goal does not stay there that long while
/// far from it.
pub const CONFIRM_CYCLES: u16 = 10;
/// The motor is trying to move: at least this far from its goal, rad.
pub const MIN_ERROR_RAD: f32 = 0.05;
/// Output below this (fraction of full duty) and current below [`MAX_CURRENT_A`] is "vanished".
pub const MAX_LOAD: f32 = 0.01;
/// See [`MAX_LOAD`], A.
pub const MAX_CURRENT_A: f32 = 0.02;

/// One joint's watch.
#[derive(Debug, Clone, Copy, Default)]
pub struct CutoffWatch {
    quiet_cycles: u16,
    /// The cutoff is inferred (until the output comes back).
    pub lost: bool,
}

impl CutoffWatch {
    /// Feeds one valid reading of a joint with torque enabled; returns true when the output has
    /// just been inferred lost.
    pub fn update(&mut self, error_rad: f32, load: f32, current_a: f32) -> bool {
        let vanished = error_rad.abs() >= MIN_ERROR_RAD
            && load.abs() < MAX_LOAD
            && current_a.abs() < MAX_CURRENT_A;
        if !vanished {
            self.quiet_cycles = 0;
            self.lost = false;
            return false;
        }
        self.quiet_cycles = self.quiet_cycles.saturating_add(1);
        if self.quiet_cycles >= CONFIRM_CYCLES && !self.lost {
            self.lost = true;
            return true;
        }
        false
    }

    /// Forgets the joint's history (torque turned off or on by the driver).
    pub fn reset(&mut self) {
        *self = CutoffWatch::default();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_silent_motor_far_from_its_goal_is_inferred_cut_off() {
        let mut w = CutoffWatch::default();
        for k in 1..CONFIRM_CYCLES {
            assert!(!w.update(0.3, 0.0, 0.0), "cycle {k}");
        }
        assert!(w.update(0.3, 0.0, 0.0));
        assert!(w.lost);
        assert!(!w.update(0.3, 0.0, 0.0), "reported once");
        w.update(0.3, 0.4, 1.0);
        assert!(!w.lost, "output came back");
        // A reset (torque turned off or on by the driver) forgets the count.
        for _ in 1..CONFIRM_CYCLES {
            w.update(0.3, 0.0, 0.0);
        }
        w.reset();
        assert!(
            !w.update(0.3, 0.0, 0.0),
            "counting starts again after a reset"
        );
        for _ in 0..CONFIRM_CYCLES {
            w.update(0.3, 0.0, 0.0);
        }
        w.reset();
        assert!(!w.lost, "a reset clears the verdict");
    }

    #[test]
    fn at_the_goal_or_driving_is_not_a_cutoff() {
        // Each case alone, for twice the confirmation: any one of the three conditions missing
        // is enough to rule the cutoff out.
        for (what, error, load, current) in [
            ("resting at its goal", 0.01, 0.0, 0.0),
            ("just inside the goal band", MIN_ERROR_RAD - 1e-4, 0.0, 0.0),
            ("driving toward its goal", 0.3, 0.5, 1.2),
            ("current still flows", -0.3, 0.0, 0.5),
            ("load still there", 0.3, -0.2, 0.0),
            ("load at the threshold", 0.3, MAX_LOAD, 0.0),
            ("current at the threshold", 0.3, 0.0, MAX_CURRENT_A),
        ] {
            let mut w = CutoffWatch::default();
            for _ in 0..2 * CONFIRM_CYCLES {
                assert!(!w.update(error, load, current), "{what}");
            }
            assert!(!w.lost, "{what}");
        }
        // Just past every threshold it is one.
        let mut w = CutoffWatch::default();
        for _ in 0..CONFIRM_CYCLES {
            w.update(MIN_ERROR_RAD, MAX_LOAD * 0.99, MAX_CURRENT_A * 0.99);
        }
        assert!(w.lost);
    }
}
