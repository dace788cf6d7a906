//! The last line against wrong feedback the checksum let through.
//!
//! Feetech's checksum is the complement of an 8-bit byte sum. One flipped bit never passes it,
//! but two flips of the same bit position in opposite directions cancel (and two flips of bit 7
//! in any direction), so about 7 % of packets with two flipped bits are accepted (9/128 for
//! random positions); the servos also report occasional 0 °C or 150 °C temperature glitches with
//! a valid checksum. Either would be published as a measurement, and one 150 °C reading latches
//! the supervisor's thermal trip.
//!
//! A reading whose temperature, supply voltage or position moved further from the joint's last
//! accepted reading than the servo physically can in the time between them, or whose load,
//! current or speed is beyond what any servo reports, or a first reading (nothing to judge it
//! against), is held back for one read: the next reading accepts it if it confirms it (a real change persists: a servo
//! whose sensor really reads 150 °C trips the bus one read later), and it is dropped as a glitch
//! otherwise. A held reading is a missing sample, like a corrupted one. Small errors (a flip in
//! the low bits) stay within the bounds and pass; what matters for safety (a false trip, a
//! masked hot motor, a position jump) is the large ones. Pure: time passed in.

use feetech::FeedbackBlock;

/// Largest temperature step between two reads at any distance in time, °C (the register's
/// own ±1 °C flicker and a little more).
pub const TEMPERATURE_STEP_C: f64 = 2.0;
/// Fastest real temperature change, °C/s (a stalled winding heats at well under 1 °C/s).
pub const TEMPERATURE_RATE_C_S: f64 = 5.0;
/// Largest supply step between two reads, V (a bus of servos stalling at once sags by about
/// this much). A larger real step is only delayed one read (see the module docs), so the
/// bounds can be tight.
pub const VOLTAGE_STEP_V: f64 = 1.0;
/// Fastest supply drift beyond that, V/s.
pub const VOLTAGE_RATE_V_S: f64 = 10.0;
/// Largest position step between two reads, steps (about 5.6°).
pub const POSITION_STEP: f64 = 64.0;
/// Fastest motion beyond that, steps/s (15 rad/s: twice an STS servo's own top speed, a joint
/// falling with its torque off or back-driven by hand).
pub const POSITION_RATE_STEPS_S: f64 = 15.0 * 4096.0 / std::f64::consts::TAU;
/// Largest |Present_Load| a servo reports, 0.1 % of full duty.
pub const MAX_LOAD: i32 = 1000;
/// Largest |Present_Current| accepted, 6.5 mA units (13 A: above the 8 A over-current backstop
/// of the A3's largest servos, which a held payload approaches; the register's 15 bits reach
/// 213 A).
pub const MAX_CURRENT: i32 = 2000;
/// A last accepted reading older than this, s, is no history: the next reading waits for
/// confirmation like a first one (the driver takes a servo silent this long off; whatever it
/// reads after a silence cannot be judged against what it read before).
pub const SILENCE_S: f64 = 0.2;
/// Steps per turn; positions of a speed-mode wheel wrap around.
const STEPS_PER_TURN: i32 = 4096;

/// Whether `b` is a reading a servo can give at all: load, current and speed within what the
/// servos can do (these change as fast as the load does, so only their range is checked).
pub fn in_range(b: &FeedbackBlock) -> bool {
    b.load.abs() <= MAX_LOAD
        && b.current.abs() <= MAX_CURRENT
        && f64::from(b.velocity.abs()) <= POSITION_RATE_STEPS_S
}

/// Whether `b`, read `dt_s` after `a`, is a change the servo could have made (and `b` is
/// [`in_range`]).
pub fn plausible(a: &FeedbackBlock, b: &FeedbackBlock, dt_s: f64) -> bool {
    let dt = dt_s.max(0.0);
    let temp = f64::from(a.temperature.abs_diff(b.temperature));
    let volts = f64::from(a.voltage.abs_diff(b.voltage)) / 10.0;
    let mut steps = (a.position - b.position).abs();
    if (0..STEPS_PER_TURN).contains(&a.position) && (0..STEPS_PER_TURN).contains(&b.position) {
        steps = steps.min(STEPS_PER_TURN - steps);
    }
    in_range(b)
        && temp <= TEMPERATURE_STEP_C + TEMPERATURE_RATE_C_S * dt
        && volts <= VOLTAGE_STEP_V + VOLTAGE_RATE_V_S * dt
        && f64::from(steps) <= POSITION_STEP + POSITION_RATE_STEPS_S * dt
}

/// One joint's gate: the last accepted reading, and the one held back.
#[derive(Debug, Clone)]
pub struct FeedbackGate {
    accepted: Option<(FeedbackBlock, f64)>,
    held: Option<(FeedbackBlock, f64)>,
    /// A reading this long after the last one judged is no history, s.
    silence_s: f64,
}

impl Default for FeedbackGate {
    fn default() -> Self {
        FeedbackGate::with_silence(SILENCE_S)
    }
}

impl FeedbackGate {
    /// A gate for which a reading `silence_s` or more after the last is no history (a loop
    /// slower than 10 Hz needs more than [`SILENCE_S`]).
    pub fn with_silence(silence_s: f64) -> Self {
        FeedbackGate {
            accepted: None,
            held: None,
            silence_s,
        }
    }

    /// Judges the reading `fb` taken at `now_s`: true to publish it, false to hold it back
    /// (a missing sample this read).
    pub fn admit(&mut self, fb: &FeedbackBlock, now_s: f64) -> bool {
        // With no history (a first reading, after a reset or a silence) nothing follows: the
        // reading is held until the next confirms it.
        let silence_s = self.silence_s;
        let follows = |r: &Option<(FeedbackBlock, f64)>| {
            r.as_ref()
                .is_some_and(|(prev, t)| now_s - t <= silence_s && plausible(prev, fb, now_s - t))
        };
        if follows(&self.accepted) || follows(&self.held) {
            self.accepted = Some((*fb, now_s));
            self.held = None;
            true
        } else {
            self.held = Some((*fb, now_s));
            false
        }
    }

    /// Forgets the history (the servo was set up again, or its bus reopened).
    pub fn reset(&mut self) {
        *self = FeedbackGate::with_silence(self.silence_s);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn block(position: i32, temperature: u8, voltage: u8) -> FeedbackBlock {
        FeedbackBlock {
            position,
            temperature,
            voltage,
            ..FeedbackBlock::default()
        }
    }

    const DT: f64 = 0.005;

    /// A gate that has accepted `b` at 0 (read twice: a first reading waits for the next).
    fn primed(b: &FeedbackBlock) -> FeedbackGate {
        let mut g = FeedbackGate::default();
        assert!(!g.admit(b, -DT));
        assert!(g.admit(b, 0.0));
        g
    }

    #[test]
    fn a_temperature_glitch_is_dropped_and_never_trips() {
        let mut g = primed(&block(2048, 45, 120));
        assert!(!g.admit(&block(2048, 150, 120), DT), "150 °C glitch held");
        assert!(
            g.admit(&block(2048, 45, 120), 2.0 * DT),
            "next normal read passes"
        );
        assert!(!g.admit(&block(2048, 0, 120), 3.0 * DT), "0 °C glitch held");
        assert!(g.admit(&block(2048, 46, 120), 4.0 * DT));
    }

    #[test]
    fn a_change_that_persists_is_accepted_one_read_later() {
        let mut g = primed(&block(2048, 45, 120));
        assert!(!g.admit(&block(2048, 59, 120), DT));
        assert!(
            g.admit(&block(2048, 59, 120), 2.0 * DT),
            "confirmed: a real 59 °C trips"
        );
        assert!(g.admit(&block(2048, 60, 120), 3.0 * DT));
    }

    #[test]
    fn high_bit_position_flips_are_held_low_bit_ones_pass() {
        let mut g = primed(&block(2048, 40, 120));
        assert!(!g.admit(&block(2048 ^ (1 << 9), 40, 120), DT));
        assert!(g.admit(&block(2048 ^ 1, 40, 120), 2.0 * DT));
        // A supply drift of 2.5 V over 0.19 s is accepted; the same jump in one read is held.
        assert!(g.admit(&block(2049, 40, 95), 2.0 * DT + 0.19));
        assert!(!g.admit(&block(2049, 40, 120), 3.0 * DT + 0.19));
    }

    #[test]
    fn impossible_load_current_or_speed_is_never_accepted() {
        let mut b = block(2048, 40, 120);
        let mut g = primed(&b);
        b.current = 1 << 14; // 106 A
        assert!(!g.admit(&b, DT));
        assert!(!g.admit(&b, 2.0 * DT), "not even when it repeats");
        b.current = 300;
        b.load = -1000;
        b.velocity = -3000;
        assert!(g.admit(&b, 3.0 * DT), "a stalled servo at full load");
        b.current = 1231;
        assert!(g.admit(&b, 3.5 * DT), "8 A, the over-current backstop");
        b.velocity = 12_000; // 18 rad/s
        assert!(!g.admit(&b, 4.0 * DT));
    }

    #[test]
    fn a_wheel_wrapping_around_is_plausible() {
        assert!(plausible(&block(4090, 40, 120), &block(10, 40, 120), DT));
        assert!(!plausible(&block(3000, 40, 120), &block(10, 40, 120), DT));
    }

    #[test]
    fn bounds_widen_with_the_time_since_the_last_accepted_read() {
        let mut g = primed(&block(2048, 40, 120));
        // 0.2 s after the last accepted read, a 2.5 °C rise is possible (not at once).
        assert!(!plausible(&block(2048, 40, 120), &block(2048, 43, 120), DT));
        assert!(g.admit(&block(2048, 43, 120), SILENCE_S));
        // After a silence, anything waits for the next reading to confirm it (the bounds
        // would let a supply 12.8 V off through after 1.2 s).
        assert!(!g.admit(&block(2048, 43, 248), 10.0));
        assert!(!g.admit(&block(2048, 70, 120), 10.0 + DT));
        assert!(g.admit(&block(2048, 70, 120), 10.0 + 2.0 * DT));
        g.reset();
        assert!(
            !g.admit(&block(100, 20, 60), 10.1),
            "no history: held until confirmed"
        );
        assert!(g.admit(&block(100, 20, 60), 10.2));
    }

    /// A first reading has nothing to be judged against: a glitch there (a double flip the
    /// checksum let through) was published, and a hold would take its position for where the
    /// joint is. The double-flip soak found one 12.8 V off.
    #[test]
    fn a_first_reading_is_published_only_once_the_next_confirms_it() {
        let mut g = FeedbackGate::default();
        assert!(!g.admit(&block(2048, 45, 248), 0.0), "24.8 V, first: held");
        assert!(
            !g.admit(&block(2048, 45, 120), DT),
            "does not confirm it: held"
        );
        assert!(g.admit(&block(2048, 45, 120), 2.0 * DT), "confirmed");
        g.reset();
        assert!(
            !g.admit(&block(1000, 45, 120), 3.0 * DT),
            "after a reset, the same"
        );
        assert!(g.admit(&block(1001, 45, 120), 4.0 * DT));
    }

    /// A held reading confirms nothing after a silence either; a slow loop's gate waits longer.
    #[test]
    fn a_silence_makes_the_held_reading_no_history_too() {
        let mut g = primed(&block(2048, 40, 120));
        assert!(!g.admit(&block(2048, 40, 248), DT), "a glitch held");
        assert!(g.admit(&block(2048, 40, 120), 2.0 * DT));
        assert!(!g.admit(&block(2048, 40, 248), 3.0 * DT), "held again");
        // The same glitch again after a silence: the held one is no history.
        assert!(!g.admit(&block(2048, 40, 248), 3.0 * DT + SILENCE_S + DT));
        // At 5 Hz, two periods and a half: each reading follows the last.
        let mut slow = FeedbackGate::with_silence(0.5);
        assert!(!slow.admit(&block(2048, 40, 120), 0.0));
        assert!(slow.admit(&block(2048, 40, 120), 0.2));
        assert!(slow.admit(&block(2050, 40, 120), 0.4));
    }

    #[test]
    fn two_different_glitches_in_a_row_confirm_nothing() {
        let mut g = primed(&block(2048, 45, 120));
        assert!(!g.admit(&block(2048, 150, 120), DT));
        assert!(!g.admit(&block(2048, 0, 120), 2.0 * DT));
        assert!(g.admit(&block(2048, 45, 120), 3.0 * DT));
    }
}
