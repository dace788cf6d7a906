//! A joint's approach to the ends of its calibrated range, slowed so that it can stop.
//!
//! A servo given a goal far away runs at full speed and stops past it: on the simulated A3,
//! 1.7–3.9° past a limit it was driven to at full speed, and further when gravity helps it on.
//! A calibration that puts the limits within 2° of the mechanical stops would then have every
//! joint strike a stop whenever a goal reaches the end of its range. While the goal asked for
//! lies within [`ZONE_RAD`] of an end (`docs/hazards.md` A14, `docs/approach.md`):
//!
//! * **The written goal is a braking profile.** It moves toward the end no faster than a joint
//!   that can still stop at the end decelerating at [`DECEL_RAD_S2`], `v ≤ √(2·a·d)` with `d`
//!   the written goal's distance to the end (Franka's bound; [`CRAWL_RAD_S`] at the least, so
//!   it arrives), and within the zone never more than [`LEAD_RAD`] ahead of where the joint
//!   stands: a loaded joint holding short of its goal still arrives, one held back (a hand)
//!   is not pushed on from further away, nor met by a goal far ahead when it is let go.
//!   A joint that runs past its written goal (thrown by the rest of the arm, or overshooting)
//!   is not followed: its servo holds it back to the profile.
//! * **Not read**, the written goal goes no further toward the end, nor more than the lead past
//!   where the joint was last read.
//!
//! The written goal always lies inside the range, between the one last written and the goal
//! asked for, or pulled back toward where the joint stands: never a goal further on than both.

/// Width of the zone inside each end of a range where a goal is approached, rad: wider than
/// the worst overshoot past a goal sent at full speed (0.15 rad, the shoulder roll helped by
/// gravity), so a goal just outside the zone is not struck past either.
pub const ZONE_RAD: f64 = 0.3;
/// The deceleration the approach allows for, rad/s²: each arm joint of the A3 brakes harder
/// than this at its torque limit, gravity helping or not (`docs/approach.md`).
pub const DECEL_RAD_S2: f64 = 4.0;
/// The least speed of the written goal toward an end, rad/s: slow enough that a joint arriving
/// at it stops short of a stop 1° on.
pub const CRAWL_RAD_S: f64 = 0.25;
/// The most the written goal leads the joint toward an end, rad: ten times the error a loaded
/// joint of the simulated arm holds at an end (under 0.01 rad).
pub const LEAD_RAD: f64 = 0.1;

/// What the driver knows of where a joint is, in its servo's steps (`Present_Position`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Sighting {
    /// Read this cycle, there.
    Now(i32),
    /// Not read this cycle; last read (or set up) there.
    Earlier(i32),
    /// Never read.
    Never,
}

impl Sighting {
    /// After this cycle's reading, `None` if it was missed or held back.
    pub fn after(self, read: Option<i32>) -> Sighting {
        match (read, self) {
            (Some(p), _) => Sighting::Now(p),
            (None, Sighting::Now(p)) => Sighting::Earlier(p),
            (None, earlier) => earlier,
        }
    }

    /// The same, in the mirrored range (steps negated).
    fn mirrored(self) -> Sighting {
        match self {
            Sighting::Now(p) => Sighting::Now(-p),
            Sighting::Earlier(p) => Sighting::Earlier(-p),
            Sighting::Never => Sighting::Never,
        }
    }
}

/// The approach in a servo's steps, for a loop at a given rate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Approach {
    /// The zone's width, steps.
    zone: f64,
    /// The deceleration allowed for, steps/s².
    decel: f64,
    /// The least speed of the written goal toward an end, steps/s.
    crawl: f64,
    /// The most the written goal leads the joint within the zone, steps.
    lead: f64,
    /// The loop's period, s.
    period: f64,
}

impl Approach {
    /// The approach for a loop of `rate_hz` cycles per second, at `steps_per_rad`.
    pub fn new(rate_hz: f64, steps_per_rad: f64) -> Self {
        Approach {
            zone: ZONE_RAD * steps_per_rad,
            decel: DECEL_RAD_S2 * steps_per_rad,
            crawl: CRAWL_RAD_S * steps_per_rad,
            lead: LEAD_RAD * steps_per_rad,
            period: 1.0 / rate_hz.max(1.0),
        }
    }

    /// The goal to write this cycle, steps: toward `goal` (inside `min..=max`) from `written`
    /// (last cycle's), the joint `seen` as it was.
    pub fn next(&self, goal: i32, written: f64, seen: Sighting, min: i32, max: i32) -> f64 {
        let goal = f64::from(goal);
        let up = self.toward_end(goal, written, seen, f64::from(max));
        // The lower end is the upper end of the mirrored range.
        let both = -self.toward_end(-up, -written, seen.mirrored(), -f64::from(min));
        both.clamp(f64::from(min), f64::from(max))
    }

    /// Toward the upper `end` only.
    fn toward_end(&self, goal: f64, written: f64, seen: Sighting, end: f64) -> f64 {
        if goal <= end - self.zone {
            return goal;
        }
        let stands = match seen {
            Sighting::Now(p) => f64::from(p),
            // Not read: away from the end as asked; never further toward it, nor more than the
            // lead past where it was last seen.
            Sighting::Earlier(p) => return goal.min(written).min(self.ahead_of(f64::from(p), end)),
            Sighting::Never => return goal.min(written),
        };
        let ahead = self.ahead_of(stands, end);
        if goal <= written {
            return goal.min(ahead);
        }
        // On from what was written, even with the joint further on: a joint that ran past its
        // goal (thrown, or overshooting) is held back by its servo, not followed to the stop.
        let profiled = written + self.allowed(end - written) * self.period;
        goal.min(profiled).min(ahead)
    }

    /// The furthest toward `end` the goal of a joint standing at `stands` may be: the lead
    /// ahead of it within the zone (so a joint let go there is not met by a goal further on);
    /// anywhere short of the zone (a joint let go there stops before its edge).
    fn ahead_of(&self, stands: f64, end: f64) -> f64 {
        (stands + self.lead).max(end - self.zone)
    }

    /// The fastest a joint `to_end` steps from the end may move toward it, steps/s.
    fn allowed(&self, to_end: f64) -> f64 {
        (2.0 * self.decel * to_end.max(0.0)).sqrt().max(self.crawl)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const STEPS_PER_RAD: f64 = 4096.0 / std::f64::consts::TAU;
    const RATE: f64 = 200.0;
    const MIN: i32 = 1000;
    const MAX: i32 = 3000;

    fn approach() -> Approach {
        Approach::new(RATE, STEPS_PER_RAD)
    }

    fn read(position: f64) -> Sighting {
        Sighting::Now(position.round() as i32)
    }

    /// The most the written goal may move in one cycle from `d` steps short of the end.
    fn allowed_step(d: f64) -> f64 {
        let v = (2.0 * DECEL_RAD_S2 * STEPS_PER_RAD * d.max(0.0)).sqrt();
        v.max(CRAWL_RAD_S * STEPS_PER_RAD) / RATE
    }

    fn lead() -> f64 {
        LEAD_RAD * STEPS_PER_RAD
    }

    /// The written goals of `cycles` cycles toward `goal` from `start`, the joint read where
    /// `stands` puts it given the last written goal (and still).
    fn run(goal: i32, start: f64, cycles: usize, stands: impl Fn(f64) -> f64) -> Vec<f64> {
        let a = approach();
        let mut written = start;
        (0..cycles)
            .map(|_| {
                written = a.next(goal, written, read(stands(written)), MIN, MAX);
                written
            })
            .collect()
    }

    #[test]
    fn a_goal_outside_the_zones_or_away_from_an_end_is_written_as_asked() {
        let a = approach();
        let zone = ZONE_RAD * STEPS_PER_RAD;
        let inside = (f64::from(MAX) - zone - 1.0) as i32;
        // Outside the zone, read or not.
        assert_eq!(
            a.next(inside, 1500.0, read(1500.0), MIN, MAX),
            f64::from(inside)
        );
        assert_eq!(
            a.next(inside, 1500.0, Sighting::Never, MIN, MAX),
            f64::from(inside)
        );
        // Away from the upper end, from deep in its zone: at once.
        assert_eq!(a.next(2000, 2990.0, read(2990.0), MIN, MAX), 2000.0);
        assert_eq!(
            a.next(2980, 2990.0, Sighting::Earlier(2990), MIN, MAX),
            2980.0
        );
        assert_eq!(a.next(2000, 1010.0, read(1010.0), MIN, MAX), 2000.0);
        // Holding where it was written: unchanged, read or not.
        assert_eq!(a.next(2990, 2990.0, Sighting::Never, MIN, MAX), 2990.0);
        assert_eq!(a.next(2990, 2990.0, read(2989.0), MIN, MAX), 2990.0);
    }

    /// Toward either end the written goal slows as a joint braking at the allowed deceleration
    /// would, never faster, and reaches the end in about the time that takes.
    #[test]
    fn toward_an_end_the_written_goal_brakes_to_arrive_at_it() {
        for (goal, sign) in [(MAX, 1.0), (MIN, -1.0)] {
            let end = f64::from(goal);
            let w = run(goal, 2000.0, 1000, |w| w);
            let mut last = 2000.0;
            for &v in &w {
                let moved = sign * (v - last);
                assert!(moved >= 0.0, "backwards: {last} to {v}");
                assert!(
                    moved <= allowed_step(sign * (end - last)) + 1e-9,
                    "{last} to {v}"
                );
                assert!((f64::from(MIN)..=f64::from(MAX)).contains(&v));
                last = v;
            }
            let reached = w.iter().position(|&v| v == end).expect("reached the end");
            // From 1000 steps away at √(2·a·d): √(2·d/a) seconds, plus the crawl's last steps.
            let d = 1000.0;
            let expected = (2.0 * d / (DECEL_RAD_S2 * STEPS_PER_RAD)).sqrt() * RATE;
            assert!(
                (reached as f64 - expected).abs() < 0.1 * expected,
                "{reached} cycles, expected {expected:.0}"
            );
        }
    }

    /// A joint that holds a little short of its goal (a load) still arrives at the end; one
    /// held back (a hand) within the zone has its goal no more than the lead ahead of it,
    /// toward either end, even once the goal had reached the end before it was pushed back;
    /// held short of the zone, its goal waits at the zone's edge.
    #[test]
    fn a_joint_held_back_is_led_by_the_lead_at_most() {
        let zone = ZONE_RAD * STEPS_PER_RAD;
        for (goal, sign) in [(MAX, 1.0), (MIN, -1.0)] {
            let end = f64::from(goal);
            let loaded = run(goal, end - sign * 400.0, 600, |w| w - sign * 30.0);
            assert_eq!(*loaded.last().unwrap(), end);
            let far = run(goal, end - sign * 400.0, 600, |_| end - sign * 400.0);
            assert_eq!(*far.last().unwrap(), end - sign * zone);
            let held = end - sign * 150.0;
            let w = run(goal, end - sign * 200.0, 600, |_| held);
            assert!(
                w.iter().all(|&v| sign * (v - held) <= lead() + 1e-9),
                "{w:?}"
            );
            assert_eq!(*w.last().unwrap(), held + sign * lead());
            let a = approach();
            let pushed_back = a.next(goal, end, read(held), MIN, MAX);
            assert_eq!(pushed_back, held + sign * lead());
        }
    }

    /// Not read, the written goal does not advance toward the end, and comes back to within
    /// the lead of where the joint was last read.
    #[test]
    fn the_goal_waits_for_a_joint_that_is_not_read() {
        let a = approach();
        assert_eq!(a.next(MAX, 2950.0, Sighting::Never, MIN, MAX), 2950.0);
        assert_eq!(a.next(MIN, 1050.0, Sighting::Never, MIN, MAX), 1050.0);
        assert_eq!(
            a.next(MAX, 2950.0, Sighting::Earlier(2940), MIN, MAX),
            2950.0
        );
        assert_eq!(
            a.next(MAX, 2950.0, Sighting::Earlier(2800), MIN, MAX),
            2800.0 + lead()
        );
        assert_eq!(
            a.next(MIN, 1050.0, Sighting::Earlier(1200), MIN, MAX),
            1200.0 - lead()
        );
        // What it knows goes on from the last reading.
        assert_eq!(Sighting::Now(2800).after(None), Sighting::Earlier(2800));
        assert_eq!(Sighting::Earlier(2800).after(None), Sighting::Earlier(2800));
        assert_eq!(Sighting::Never.after(Some(2810)), Sighting::Now(2810));
    }

    /// A joint read further toward the end than the written goal (thrown, or overshooting) is
    /// not followed: the written goal goes on from where it was, at the profile's pace, and its
    /// servo holds the joint back.
    #[test]
    fn a_joint_past_the_written_goal_is_held_back_to_the_profile() {
        let a = approach();
        let w = a.next(MAX, 2800.0, read(2900.0), MIN, MAX);
        assert_eq!(w, 2800.0 + allowed_step(200.0));
        assert_eq!(
            a.next(2970, 2950.0, read(2980.0), MIN, MAX),
            2950.0 + allowed_step(50.0)
        );
        let w = a.next(MIN, 1200.0, read(1100.0), MIN, MAX);
        assert_eq!(w, 1200.0 - allowed_step(200.0));
    }

    /// Never beyond the goal asked for, nor the range, even one step short of it or with the
    /// joint read past the end.
    #[test]
    fn the_written_goal_never_passes_the_goal_asked_for_nor_the_range() {
        let a = approach();
        assert_eq!(a.next(2999, 2998.9, read(2999.0), MIN, MAX), 2999.0);
        assert_eq!(a.next(1001, 1001.1, read(1001.0), MIN, MAX), 1001.0);
        assert_eq!(
            a.next(MAX, 2990.0, read(3010.0), MIN, MAX),
            2990.0 + allowed_step(10.0)
        );
        assert_eq!(
            a.next(MIN, 1010.0, read(990.0), MIN, MAX),
            1010.0 - allowed_step(10.0)
        );
        assert_eq!(a.next(MAX, 2999.5, read(3010.0), MIN, MAX), 3000.0);
        assert_eq!(a.next(2995, 3000.0, read(3010.0), MIN, MAX), 2995.0);
    }
}
