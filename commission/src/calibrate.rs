//! Calibration by hand, the pure part: a joint's travel recorded from its encoder while an
//! operator moves it from stop to stop (torque off, its homing offset cleared), across the
//! encoder's 0/4095 wrap, and the calibration chosen from it. The joint's zero is placed between
//! the two stops where the robot's description puts it, the homing offset makes
//! `Present_Position` read 2048 there, and the limits sit a margin inside the stops. A travel
//! that is not the description's (a stop hit early: something in the way, a wrong part) is
//! refused, not written.

use bus_driver::calibration::{JointCalibration, CENTER, STEPS_PER_RAD};
use thiserror::Error;

/// Encoder steps in one turn.
const TURN: i64 = 4096;
/// The largest homing offset the register holds (sign and 11 bits).
const MAX_OFFSET: i64 = 2047;

/// A joint's mechanical stops, from the robot's description, rad; whether its servo turns
/// against the joint's positive direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stops {
    /// The lower stop, rad.
    pub lower_rad: f64,
    /// The upper stop, rad.
    pub upper_rad: f64,
    /// The servo counts down as the joint angle grows.
    pub inverted: bool,
}

impl Stops {
    fn travel_rad(&self) -> f64 {
        self.upper_rad - self.lower_rad
    }
}

/// The most a reading may differ from the one before it for the joint to count as held there,
/// steps: an extreme is where the joint was held (against its stop), not where it bounced
/// through on its way (a dangling link swung into a stop goes in by tenths of a radian for a
/// moment).
const STILL_STEPS: i64 = 3;
/// Readings in a row within [`STILL_STEPS`] of each other before the joint counts as held
/// (0.1 s at the tool's 50 Hz): a bounce reverses at its apex, slow for a reading or two.
const HELD_READINGS: u32 = 5;

/// The readings of one joint so far: the encoder unwrapped across 0/4095 (two readings a
/// sampling period apart never differ by half a turn: a hand does not turn a joint 180° in
/// 20 ms), and the extremes where it was held.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Sweep {
    last: Option<i64>,
    unwrapped: i64,
    min: i64,
    max: i64,
    held: bool,
    readings: u32,
    /// Readings in a row within [`STILL_STEPS`] of the one before.
    still: u32,
}

impl Sweep {
    /// One `Present_Position` reading (steps, homing offset 0).
    pub fn observe(&mut self, raw: u16) {
        let raw = i64::from(raw).rem_euclid(TURN);
        let Some(last) = self.last.replace(raw) else {
            self.unwrapped = raw;
            self.readings = 1;
            return;
        };
        let step = (raw - last + TURN / 2).rem_euclid(TURN) - TURN / 2;
        self.unwrapped += step;
        self.still = if step.abs() <= STILL_STEPS {
            self.still + 1
        } else {
            0
        };
        if self.still + 1 >= HELD_READINGS {
            if self.held {
                self.min = self.min.min(self.unwrapped);
                self.max = self.max.max(self.unwrapped);
            } else {
                (self.min, self.max, self.held) = (self.unwrapped, self.unwrapped, true);
            }
        }
        self.readings = self.readings.saturating_add(1);
    }

    /// The angle swept between the extremes, rad.
    pub fn swept_rad(&self) -> f64 {
        (self.max - self.min) as f64 / STEPS_PER_RAD
    }

    /// Where the joint is now, unwrapped from its first reading's turn, rad.
    pub fn position_rad(&self) -> f64 {
        self.unwrapped as f64 / STEPS_PER_RAD
    }

    /// Where the joint is now, as a share of the sweep so far (0 at one extreme, 1 at the
    /// other), for the operator's live view.
    pub fn place(&self) -> f64 {
        if !self.held || self.max == self.min {
            return 0.5;
        }
        ((self.unwrapped - self.min) as f64 / (self.max - self.min) as f64).clamp(0.0, 1.0)
    }

    /// Whether the sweep has reached both stops (within `tolerance_rad` of the travel).
    pub fn covers(&self, stops: &Stops, tolerance_rad: f64) -> bool {
        self.held && self.swept_rad() >= stops.travel_rad() - tolerance_rad
    }
}

/// Why a joint's sweep gives no calibration.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum Refusal {
    /// Nothing was read, or the joint was never held still.
    #[error("{joint}: never read while held still")]
    NoReadings {
        /// The joint.
        joint: String,
    },
    /// The sweep is short of the travel: the stops were not both reached, or something stops
    /// the joint early.
    #[error(
        "{joint}: swept {swept_deg:.1}° of its {travel_deg:.1}° travel: move it from stop to \
         stop (if it will not go further, something is in its way)"
    )]
    NotCovered {
        /// The joint.
        joint: String,
        /// Swept, degrees.
        swept_deg: f64,
        /// The description's travel, degrees.
        travel_deg: f64,
    },
    /// The stops are further apart than the description's: a broken stop or a part that is
    /// not the description's.
    #[error(
        "{joint}: its stops are {swept_deg:.1}° apart, the description says {travel_deg:.1}°: \
         a stop is not where the description puts it (a broken or wrong part)"
    )]
    BeyondTravel {
        /// The joint.
        joint: String,
        /// Swept, degrees.
        swept_deg: f64,
        /// The description's travel, degrees.
        travel_deg: f64,
    },
    /// Driven toward a stop, the joint neither stalled nor ran past its travel in the time
    /// it should take: it does not answer the drive as the description's joint would.
    #[error(
        "{joint}: driven toward its {toward} stop for {after_s:.0} s without finding it (is the \
         joint connected to its servo?)"
    )]
    NoStop {
        /// The joint.
        joint: String,
        /// Which stop.
        toward: &'static str,
        /// How long it was driven, s.
        after_s: f64,
    },
    /// A servo's firmware unloaded its motor (a protection fired) during the calibration.
    #[error(
        "{joint}: its servo unloaded its motor ({status}): set it up (`nori servo setup`) so \
         its protections are the driver's, let it cool, and calibrate again"
    )]
    Unloaded {
        /// The joint.
        joint: String,
        /// The protections the servo reported.
        status: String,
    },
    /// Driven toward a stop, the joint pushed at its torque limit without standing still (for
    /// half a second, or until its firmware's press bound ended the push): something gives way
    /// slowly, or its load is more than the plan's torque limit moves.
    #[error(
        "{joint}: driven toward a stop, it pushed at its torque limit without standing still: \
         something gives way in its path, or the plan's torque limit is too low for its load"
    )]
    Strained {
        /// The joint.
        joint: String,
    },
    /// A servo does not do what the automatic calibration relies on: it is not driven further.
    #[error(
        "{joint}: its servo does not behave as the calibration expects ({what}): calibrate it \
         by hand"
    )]
    FirmwareDiffers {
        /// The joint.
        joint: String,
        /// What it did.
        what: String,
    },
    /// The session was stopped before it was done (the operator, or its time ran out).
    #[error("stopped after {after_s:.0} s, before every joint was calibrated")]
    Stopped {
        /// When, s after it began.
        after_s: f64,
    },
    /// A joint did not reach where the session drove it (a pose or its rest): something holds
    /// it, or its torque limit is too low for the pose.
    #[error("{joint}: driven to {wanted_deg:.1}°, stayed at {at_deg:.1}°: something holds it")]
    NotReached {
        /// The joint.
        joint: String,
        /// Where it was driven, degrees.
        wanted_deg: f64,
        /// Where it stayed, degrees.
        at_deg: f64,
    },
}

/// How far inside each stop a joint's limits are put, rad: 1°, for both calibrations, and
/// further in by [`shift_allowance`], so that each range ends within 2° of its stops (#40). A
/// servo sent to a limit at full speed runs 1.7–3.9° past it: the driver's approach to a
/// range's ends (`bus_driver::approach`) is what keeps a joint calibrated this near off them.
pub const LIMIT_MARGIN_RAD: f64 = 1.0 * std::f64::consts::PI / 180.0;

/// The most the limits move further in for the zero's uncertainty, rad (0.6°).
pub const MAX_SHIFT_ALLOWANCE_RAD: f64 = 0.6 * std::f64::consts::PI / 180.0;

/// How far the travel swept may differ from the description's before it is refused, rad
/// (2.9°), by hand and automatic: a stop not reached, something in the way, a broken stop. At
/// most half of it shifts the zero, and the margin with the whole allowance covers that, so no
/// stop pressed harder than the other puts a limit past its stop, but for the rounding
/// (checked as the crate builds, below). What no sweep shows, one stop pressed and the other not reached by as much, is
/// hazard C6's open residual.
pub const TRAVEL_TOLERANCE_RAD: f64 = 0.05;

// A stop pressed harder than the other by all of the tolerance shifts the zero by half of it:
// the margin and the whole allowance must still keep each limit inside its stop. They leave
// 1.9 steps; the rounding of the zero, the limits and the offset can take up to 2.5, so at
// the whole tolerance a limit ends within a step (0.09°) of its stop, either side (the second
// outside review). More margin would put the automatic calibration's limits past 2°.
const _: () = assert!(
    LIMIT_MARGIN_RAD + MAX_SHIFT_ALLOWANCE_RAD
        > TRAVEL_TOLERANCE_RAD / 2.0 + std::f64::consts::TAU / 4096.0,
    "a one-sided difference of the whole tolerance could put a limit past its stop"
);

/// How much further in than the margin the limits go, rad: however a sweep's difference from
/// the travel splits between the two stops (one pressed harder, or not reached), it shifts the
/// zero by at most half of it; up to [`MAX_SHIFT_ALLOWANCE_RAD`]. Beyond that a limit may lie
/// less than the margin inside its stop, by the excess, not past it (the automatic
/// calibration presses both stops at one torque: its zeros were within 0.26° over eight seeds,
/// where half the difference reached 1.35°; `docs/commissioning.md`).
pub fn shift_allowance(swept_rad: f64, travel_rad: f64) -> f64 {
    ((swept_rad - travel_rad).abs() / 2.0).min(MAX_SHIFT_ALLOWANCE_RAD)
}

/// The calibration of a joint from its sweep: `margin_rad` inside each stop, refused when the
/// sweep differs from the description's travel by more than `tolerance_rad`.
pub fn choose(
    joint: &str,
    sweep: &Sweep,
    stops: &Stops,
    margin_rad: f64,
    tolerance_rad: f64,
) -> Result<JointCalibration, Refusal> {
    if !sweep.held {
        return Err(Refusal::NoReadings {
            joint: joint.into(),
        });
    }
    let (swept_deg, travel_deg) = (
        sweep.swept_rad().to_degrees(),
        stops.travel_rad().to_degrees(),
    );
    if sweep.swept_rad() < stops.travel_rad() - tolerance_rad {
        return Err(Refusal::NotCovered {
            joint: joint.into(),
            swept_deg,
            travel_deg,
        });
    }
    if sweep.swept_rad() > stops.travel_rad() + tolerance_rad {
        return Err(Refusal::BeyondTravel {
            joint: joint.into(),
            swept_deg,
            travel_deg,
        });
    }
    let margin_rad = margin_rad + shift_allowance(sweep.swept_rad(), stops.travel_rad());
    // The reading at the joint's zero, estimated from each stop and averaged: the lower stop
    // reads lowest unless the servo is inverted.
    let sign = if stops.inverted { -1.0 } else { 1.0 };
    let (at_lower, at_upper) = if stops.inverted {
        (sweep.max as f64, sweep.min as f64)
    } else {
        (sweep.min as f64, sweep.max as f64)
    };
    let zero = 0.5
        * ((at_lower - sign * stops.lower_rad * STEPS_PER_RAD)
            + (at_upper - sign * stops.upper_rad * STEPS_PER_RAD));
    // Present = raw − offset (mod a turn) reads 2048 at the zero.
    let offset = ((zero - CENTER).round() as i64 + TURN / 2).rem_euclid(TURN) - TURN / 2;
    let step = |rad: f64| (CENTER + sign * rad * STEPS_PER_RAD).round() as i32;
    let (a, b) = (
        step(stops.lower_rad + margin_rad),
        step(stops.upper_rad - margin_rad),
    );
    Ok(JointCalibration {
        // −2048 and 2048 are one offset; the register holds neither (a step off, 0.09°).
        homing_offset: offset.clamp(-MAX_OFFSET, MAX_OFFSET) as i32,
        range_min: a.min(b).max(0),
        range_max: a.max(b).min(TURN as i32 - 1),
        inverted: stops.inverted,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use feetech::registers as reg;
    use sim::rng::Rng;
    use sim::servo::Servo;

    const ELBOW: Stops = Stops {
        lower_rad: -2.4,
        upper_rad: 0.1,
        inverted: false,
    };

    /// A simulated servo of the description's kind, its horn on tooth `horn` (steps), its
    /// homing offset cleared, read at `q`.
    fn reading(servo: &mut Servo, q: f64) -> u16 {
        servo.angle = q;
        let mut b = [0u8; 2];
        assert!(servo.read(reg::PRESENT_POSITION.addr, 2, &mut b));
        u16::from_le_bytes(b)
    }

    fn servo(horn: f64) -> Servo {
        let d = sim::RobotDescription::nori_a3();
        let rating = d.rating("sts3095").unwrap();
        let mut s = Servo::new(4, rating.model, rating, 0.0, 25.0);
        s.fit_horn(horn);
        s
    }

    /// An operator's sweep at 50 Hz: from where the joint rests to the lower stop, pressed
    /// `press` rad into it (the stop's give), to the upper stop, back to rest.
    fn swept(servo: &mut Servo, stops: &Stops, press: f64, rng: &mut Rng) -> Sweep {
        let waypoints = [-0.5, stops.lower_rad - press, stops.upper_rad + press, -0.5];
        sweep_through(servo, &waypoints, rng)
    }

    /// A sweep at 50 Hz through `waypoints`, held a while at each.
    fn sweep_through(servo: &mut Servo, waypoints: &[f64], rng: &mut Rng) -> Sweep {
        let mut sweep = Sweep::default();
        for w in waypoints.windows(2) {
            let n = ((w[1] - w[0]).abs() / 0.02).ceil() as usize;
            for k in 0..=n {
                let q = w[0] + (w[1] - w[0]) * k as f64 / n as f64;
                sweep.observe(reading(servo, q + rng.normal() * 0.001));
            }
            // Held at the waypoint a while, as against a stop.
            for _ in 0..10 {
                sweep.observe(reading(servo, w[1] + rng.normal() * 0.001));
            }
        }
        sweep
    }

    /// Over horns on every part of the encoder's turn (the sweep crossing 0/4095 in most), the
    /// chosen offset reads the joint's zero within 2° on the simulator's own encoder, and the
    /// limits sit the margin inside the stops.
    #[test]
    fn by_hand_the_zero_is_found_within_two_degrees_across_the_wrap() {
        let mut rng = Rng::new(11);
        for seed in 0..40 {
            let horn = -2047.0 + 4094.0 * f64::from(seed) / 39.0;
            let mut s = servo(horn);
            let sweep = swept(&mut s, &ELBOW, 0.01, &mut rng);
            let cal = choose("left_elbow", &sweep, &ELBOW, 0.15, 0.1).unwrap();
            cal.validate("left_elbow").unwrap();
            assert!(s.write(reg::LOCK.addr, &[0]));
            let encoded = bus_driver::bus::encode(reg::HOMING_OFFSET, cal.homing_offset).unwrap();
            assert!(s.write(reg::HOMING_OFFSET.addr, &encoded.to_le_bytes()));
            let zero = cal.to_rad(i32::from(reading(&mut s, 0.0)));
            assert!(
                zero.abs() < 2f64.to_radians(),
                "horn {horn}: zero reads {zero} rad"
            );
            // The margin, and half the sweep's difference from the travel (the stops' give).
            let inside = 0.15 + shift_allowance(sweep.swept_rad(), ELBOW.travel_rad());
            let (lo, hi) = cal.range_rad();
            assert!((lo - (ELBOW.lower_rad + inside)).abs() < 0.002, "{lo}");
            assert!((hi - (ELBOW.upper_rad - inside)).abs() < 0.002, "{hi}");
            // Where the joint is read at each calibrated limit is where the calibration says.
            let at_low = cal.to_rad(i32::from(reading(&mut s, lo)));
            assert!((at_low - lo).abs() < 2f64.to_radians(), "{at_low} vs {lo}");
        }
    }

    /// Pressed 0.01 rad into the lower stop and not into the upper: the zero shifts by half
    /// that, and the limits move in by as much, so each stays the margin inside its real stop.
    /// Pressed further into one (0.045 rad, within the tolerance), the limits move in by
    /// [`MAX_SHIFT_ALLOWANCE_RAD`] at most, and one lies less than the margin inside its stop
    /// by the rest of the zero's shift, still inside it; pressed 0.09 rad, the sweep is refused.
    /// What the sweep cannot see: pressed into one stop and short of the other by as much (the
    /// travel right), the zero shifts by that and a limit is that much less inside (the
    /// residual documented in hazard C6; the automatic calibration's remedy).
    #[test]
    fn a_stop_pressed_harder_than_the_other_moves_the_limits_in_up_to_the_allowance() {
        let mut rng = Rng::new(5);
        let margin = LIMIT_MARGIN_RAD;
        for (press_lower, press_upper, unseen) in [
            (0.01, 0.0, 0.0),
            (0.0, 0.02, 0.0),
            (0.045, 0.0, 0.0),
            (0.0, 0.045, 0.0),
            (0.03, 0.01, 0.0),
            (0.09, 0.0, 0.0),
            (0.012, -0.012, 0.012),
        ] {
            let mut s = servo(300.0);
            let waypoints = [
                -0.5,
                ELBOW.lower_rad - press_lower,
                ELBOW.upper_rad + press_upper,
                -0.5,
            ];
            let sweep = sweep_through(&mut s, &waypoints, &mut rng);
            let chosen = choose("left_elbow", &sweep, &ELBOW, margin, TRAVEL_TOLERANCE_RAD);
            let half = (sweep.swept_rad() - ELBOW.travel_rad()).abs() / 2.0;
            if 2.0 * half > TRAVEL_TOLERANCE_RAD {
                assert!(
                    matches!(chosen, Err(Refusal::BeyondTravel { .. })),
                    "{chosen:?}"
                );
                continue;
            }
            let cal = chosen.unwrap();
            let allowance = half.min(MAX_SHIFT_ALLOWANCE_RAD);
            // In the calibration's own frame: the margin and the allowance inside each stop.
            let (lo, hi) = cal.range_rad();
            let from_stops = [lo - ELBOW.lower_rad, ELBOW.upper_rad - hi];
            for d in from_stops {
                assert!((d - margin - allowance).abs() < 0.002, "{d} rad");
            }
            assert!(s.write(reg::LOCK.addr, &[0]));
            let encoded = bus_driver::bus::encode(reg::HOMING_OFFSET, cal.homing_offset).unwrap();
            assert!(s.write(reg::HOMING_OFFSET.addr, &encoded.to_le_bytes()));
            // Where the joint truly is when the driver believes it at each limit.
            let zero = cal.to_rad(i32::from(reading(&mut s, 0.0)));
            let inside = [lo - zero - ELBOW.lower_rad, ELBOW.upper_rad - (hi - zero)];
            let excess = half - allowance;
            for d in inside {
                assert!(
                    d >= margin - unseen - excess - 0.003 && d > 0.0,
                    "pressed {press_lower}/{press_upper}: a limit {:.2}° inside its stop",
                    d.to_degrees()
                );
            }
        }
    }

    /// A dangling link bouncing into a stop reverses there: its readings at the apex differ by
    /// little, but for a moment, not as a joint held against its stop.
    #[test]
    fn a_bounce_s_apex_is_not_an_extreme() {
        let mut sweep = Sweep::default();
        for raw in [
            2000u16, 2000, 2000, 2000, 2000, 1950, 1920, 1920, 1950, 2000, 2000,
        ] {
            sweep.observe(raw);
        }
        assert_eq!((sweep.min, sweep.max), (2000, 2000));
    }

    #[test]
    fn an_inverted_servo_is_calibrated_the_other_way_round() {
        let stops = Stops {
            inverted: true,
            ..ELBOW
        };
        let mut s = servo(700.0);
        let mut sweep = Sweep::default();
        // Inverted: the servo reads the joint's angle negated.
        for k in 0..=250 {
            let q = stops.lower_rad + stops.travel_rad() * f64::from(k) / 250.0;
            // Held at each stop: the first and last readings repeated.
            for _ in 0..if k % 250 == 0 { 5 } else { 1 } {
                sweep.observe(reading(&mut s, -q));
            }
        }
        let cal = choose("j", &sweep, &stops, 0.15, 0.1).unwrap();
        assert!(cal.inverted);
        let (lo, hi) = cal.range_rad();
        assert!((lo - (stops.lower_rad + 0.15)).abs() < 0.002, "{lo}");
        assert!((hi - (stops.upper_rad - 0.15)).abs() < 0.002, "{hi}");
        // At the joint's zero the raw reading less the offset is the centre.
        let raw = i64::from(reading(&mut s, 0.0));
        let present = (raw - i64::from(cal.homing_offset)).rem_euclid(TURN);
        assert!((present - 2048).abs() <= 2, "{present}");
    }

    #[test]
    fn a_short_sweep_and_a_travel_beyond_the_description_are_refused() {
        let mut rng = Rng::new(3);
        let mut s = servo(0.0);
        // Blocked 30° before the upper stop: the sweep is short.
        let blocked = Stops {
            upper_rad: ELBOW.upper_rad - 0.52,
            ..ELBOW
        };
        let sweep = swept(&mut s, &blocked, 0.0, &mut rng);
        assert!(!sweep.covers(&ELBOW, 0.1));
        let e = choose("left_elbow", &sweep, &ELBOW, 0.15, 0.1).unwrap_err();
        assert!(matches!(e, Refusal::NotCovered { .. }), "{e}");
        assert!(e.to_string().contains("something is in its way"), "{e}");
        // A stop broken off: 20° more travel than described.
        let broken = Stops {
            lower_rad: ELBOW.lower_rad - 0.35,
            ..ELBOW
        };
        let sweep = swept(&mut s, &broken, 0.0, &mut rng);
        let e = choose("left_elbow", &sweep, &ELBOW, 0.15, 0.1).unwrap_err();
        assert!(matches!(e, Refusal::BeyondTravel { .. }), "{e}");
        assert_eq!(
            choose("j", &Sweep::default(), &ELBOW, 0.15, 0.1),
            Err(Refusal::NoReadings { joint: "j".into() })
        );
    }

    #[test]
    fn the_sweep_unwraps_across_the_encoder_wrap_and_tracks_where_the_joint_is() {
        let mut sweep = Sweep::default();
        // Each reading held (repeated): an extreme counts where the joint stood still a while.
        for raw in [4000u16, 4090, 5, 100, 50, 4095, 3990] {
            for _ in 0..HELD_READINGS {
                sweep.observe(raw);
            }
        }
        // 3990 .. 4096 + 100: 206 steps swept, now at the low end.
        assert_eq!(sweep.max - sweep.min, 206);
        assert!(sweep.place() < 0.01);
        sweep.observe(100);
        assert!((sweep.place() - 1.0).abs() < 1e-9);
        // Passing through beyond it without stopping: not an extreme.
        sweep.observe(300);
        sweep.observe(100);
        assert_eq!(sweep.max - sweep.min, 206);
    }
}
