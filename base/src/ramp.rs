//! Speed and acceleration limits on the commanded twist: a command may ask for anything; the
//! base gets there at the rates its wheels, its load and the people around it allow.

use crate::drive::Twist;

/// How fast the base may go and change speed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Limits {
    /// Largest forward or backward speed, m/s.
    pub max_linear_m_s: f64,
    /// Largest turn rate, rad/s.
    pub max_angular_rad_s: f64,
    /// Largest rise of |linear speed|, m/s².
    pub linear_acc_m_s2: f64,
    /// Largest fall of |linear speed|, m/s² (braking may be harder than speeding up).
    pub linear_brake_m_s2: f64,
    /// Largest change of the turn rate, rad/s².
    pub angular_acc_rad_s2: f64,
}

impl Limits {
    /// The name of the first limit that is not a positive finite number.
    pub fn invalid(&self) -> Option<&'static str> {
        [
            ("max-linear-m-s", self.max_linear_m_s),
            ("max-angular-rad-s", self.max_angular_rad_s),
            ("linear-acc-m-s2", self.linear_acc_m_s2),
            ("linear-brake-m-s2", self.linear_brake_m_s2),
            ("angular-acc-rad-s2", self.angular_acc_rad_s2),
        ]
        .into_iter()
        .find(|(_, v)| !(v.is_finite() && *v > 0.0))
        .map(|(name, _)| name)
    }

    /// Distance to a standstill from forward speed `v` at the braking limit, m.
    pub fn braking_distance_m(&self, v: f64) -> f64 {
        v * v / (2.0 * self.linear_brake_m_s2)
    }
}

/// The twist sent to the wheels, moved toward each cycle's target within [`Limits`].
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Ramp {
    now: Twist,
}

impl Ramp {
    /// At rest.
    pub fn new() -> Ramp {
        Ramp::default()
    }

    /// The twist last returned.
    pub fn twist(&self) -> Twist {
        self.now
    }

    /// Starts over from `twist` (e.g. the base's measured motion after the wheels were off).
    pub fn reset_to(&mut self, twist: Twist) {
        self.now = if twist.is_finite() {
            twist
        } else {
            Twist::default()
        };
    }

    /// The twist for the next `dt_s` seconds: `target` clamped to the speed limits, reached no
    /// faster than the acceleration limits allow. A non-finite target is taken as a stop (the
    /// command path refuses such commands with a reason; this never lets one through), and a
    /// non-positive or non-finite `dt_s` changes nothing.
    pub fn step(&mut self, target: Twist, dt_s: f64, limits: &Limits) -> Twist {
        if !(dt_s.is_finite() && dt_s > 0.0) {
            return self.now;
        }
        let target = if target.is_finite() {
            target
        } else {
            Twist::default()
        };
        let v_goal = target
            .linear_m_s
            .clamp(-limits.max_linear_m_s, limits.max_linear_m_s);
        let w_goal = target
            .angular_rad_s
            .clamp(-limits.max_angular_rad_s, limits.max_angular_rad_s);
        let v = self.now.linear_m_s;
        // Speeding up (away from zero, same direction) at the acceleration limit; slowing down
        // or reversing through zero at the braking limit until zero.
        let speeding_up = v_goal.abs() > v.abs() && v_goal * v >= 0.0;
        let rate = if speeding_up {
            limits.linear_acc_m_s2
        } else {
            limits.linear_brake_m_s2
        };
        let mut v_next = approach(v, v_goal, rate * dt_s);
        if v != 0.0 && v_next * v < 0.0 {
            // Never through zero in one step at the braking rate: stop first.
            v_next = 0.0;
        }
        let w_next = approach(
            self.now.angular_rad_s,
            w_goal,
            limits.angular_acc_rad_s2 * dt_s,
        );
        self.now = Twist::new(v_next, w_next);
        self.now
    }
}

/// `from` moved toward `to` by at most `step`.
fn approach(from: f64, to: f64, step: f64) -> f64 {
    from + (to - from).clamp(-step, step)
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMITS: Limits = Limits {
        max_linear_m_s: 0.3,
        max_angular_rad_s: 1.0,
        linear_acc_m_s2: 0.5,
        linear_brake_m_s2: 1.0,
        angular_acc_rad_s2: 2.0,
    };

    fn run(ramp: &mut Ramp, target: Twist, seconds: f64) -> Vec<Twist> {
        let dt = 0.005;
        (0..(seconds / dt).round() as usize)
            .map(|_| ramp.step(target, dt, &LIMITS))
            .collect()
    }

    #[test]
    fn a_step_command_is_reached_at_the_acceleration_limit() {
        let mut ramp = Ramp::new();
        let path = run(&mut ramp, Twist::new(0.3, 0.5), 1.0);
        // 0.3 m/s at 0.5 m/s² takes 0.6 s; 0.5 rad/s at 2 rad/s² takes 0.25 s.
        let reached = |f: fn(&Twist) -> f64, goal: f64| {
            path.iter()
                .position(|t| (f(t) - goal).abs() < 1e-9)
                .unwrap()
                + 1
        };
        assert_eq!(reached(|t| t.linear_m_s, 0.3), 120);
        assert_eq!(reached(|t| t.angular_rad_s, 0.5), 50);
        for w in path.windows(2) {
            assert!(w[1].linear_m_s - w[0].linear_m_s <= 0.5 * 0.005 + 1e-12);
            assert!((w[1].angular_rad_s - w[0].angular_rad_s).abs() <= 2.0 * 0.005 + 1e-12);
        }
    }

    #[test]
    fn speeds_beyond_the_limits_are_clamped() {
        let mut ramp = Ramp::new();
        let last = *run(&mut ramp, Twist::new(5.0, -9.0), 2.0).last().unwrap();
        assert_eq!(last, Twist::new(0.3, -1.0));
    }

    #[test]
    fn braking_is_at_the_braking_rate_and_stops_before_reversing() {
        let mut ramp = Ramp::new();
        ramp.reset_to(Twist::new(0.3, 0.0));
        let path = run(&mut ramp, Twist::new(-0.3, 0.0), 1.0);
        // Down from 0.3 at 1 m/s²: 0.3 s (60 steps) to zero, then up backwards at 0.5 m/s².
        // (60 steps, or 61 where rounding leaves a few 1e-17 m/s for one more step.)
        let stopped = path.iter().position(|t| t.linear_m_s == 0.0).unwrap() + 1;
        assert!(
            (60..=61).contains(&stopped),
            "stopped after {stopped} steps"
        );
        assert!((path[stopped].linear_m_s + 0.0025).abs() < 1e-12);
        assert!((LIMITS.braking_distance_m(0.3) - 0.045).abs() < 1e-12);
    }

    #[test]
    fn a_non_finite_target_is_a_stop_and_a_bad_dt_changes_nothing() {
        let mut ramp = Ramp::new();
        ramp.reset_to(Twist::new(0.2, 0.4));
        assert_eq!(
            ramp.step(Twist::new(0.2, 0.4), f64::NAN, &LIMITS),
            Twist::new(0.2, 0.4)
        );
        assert_eq!(
            ramp.step(Twist::new(0.2, 0.4), -0.1, &LIMITS),
            Twist::new(0.2, 0.4)
        );
        let t = ramp.step(Twist::new(f64::NAN, 0.0), 0.1, &LIMITS);
        assert!((t.linear_m_s - 0.1).abs() < 1e-12 && (t.angular_rad_s - 0.2).abs() < 1e-12);
        ramp.reset_to(Twist::new(f64::INFINITY, 0.0));
        assert_eq!(ramp.twist(), Twist::default());
    }

    #[test]
    fn invalid_limits_are_named() {
        assert_eq!(LIMITS.invalid(), None);
        let bad = Limits {
            linear_brake_m_s2: 0.0,
            ..LIMITS
        };
        assert_eq!(bad.invalid(), Some("linear-brake-m-s2"));
        let bad = Limits {
            max_angular_rad_s: f64::NAN,
            ..LIMITS
        };
        assert_eq!(bad.invalid(), Some("max-angular-rad-s"));
    }
}
