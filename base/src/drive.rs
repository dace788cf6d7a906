//! Twist ↔ wheel speeds of a differential drive.

/// A velocity of the base in its own frame: forward speed and turn rate (counter-clockwise
/// seen from above is positive, as in ROS's REP 103).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Twist {
    /// Forward speed, m/s.
    pub linear_m_s: f64,
    /// Turn rate, rad/s.
    pub angular_rad_s: f64,
}

impl Twist {
    /// A twist.
    pub const fn new(linear_m_s: f64, angular_rad_s: f64) -> Twist {
        Twist {
            linear_m_s,
            angular_rad_s,
        }
    }

    /// Both components finite.
    pub fn is_finite(&self) -> bool {
        self.linear_m_s.is_finite() && self.angular_rad_s.is_finite()
    }
}

/// The wheels' speeds about their axles, rad/s, each positive when it drives the base forward.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct WheelSpeeds {
    /// Left wheel, rad/s.
    pub left_rad_s: f64,
    /// Right wheel, rad/s.
    pub right_rad_s: f64,
}

impl WheelSpeeds {
    /// Scaled down together until neither exceeds `max` (rad/s): the ratio of the two, and so
    /// the path's curvature, is kept. Clamping each wheel alone would straighten a turn taken
    /// at speed, or turn a straight run whose wheels differ slightly into a curve.
    pub fn limited(self, max: f64) -> WheelSpeeds {
        let fastest = self.left_rad_s.abs().max(self.right_rad_s.abs());
        if fastest <= max || fastest == 0.0 {
            return self;
        }
        let k = max / fastest;
        WheelSpeeds {
            left_rad_s: self.left_rad_s * k,
            right_rad_s: self.right_rad_s * k,
        }
    }
}

/// A geometry no base can have.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GeometryError {
    /// Radius or track not a positive finite length.
    #[error("{what} {value} m: must be a positive length")]
    NotALength {
        /// Which dimension.
        what: &'static str,
        /// Its value.
        value: f64,
    },
}

/// What the base is: its wheels' radius, the distance between their contact points, and how
/// each servo is mounted (the two are mirror images, so one of them turns backwards to drive
/// the base forward).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Geometry {
    wheel_radius_m: f64,
    track_m: f64,
    /// +1 or −1 per wheel (left, right): the servo's positive direction against the wheel's
    /// forward one.
    servo_sign: [f64; 2],
}

impl Geometry {
    /// A base with wheels of `wheel_radius_m`, `track_m` apart; `left_inverted` /
    /// `right_inverted` when that servo's positive speed drives its wheel backwards.
    pub fn new(
        wheel_radius_m: f64,
        track_m: f64,
        left_inverted: bool,
        right_inverted: bool,
    ) -> Result<Geometry, GeometryError> {
        for (what, value) in [("wheel radius", wheel_radius_m), ("track", track_m)] {
            if !(value.is_finite() && value > 0.0) {
                return Err(GeometryError::NotALength { what, value });
            }
        }
        let sign = |inverted: bool| if inverted { -1.0 } else { 1.0 };
        Ok(Geometry {
            wheel_radius_m,
            track_m,
            servo_sign: [sign(left_inverted), sign(right_inverted)],
        })
    }

    /// Wheel radius, m.
    pub fn wheel_radius_m(&self) -> f64 {
        self.wheel_radius_m
    }

    /// Distance between the wheels' contact points, m.
    pub fn track_m(&self) -> f64 {
        self.track_m
    }

    /// The wheel speeds that move the base at `twist`.
    pub fn wheel_speeds(&self, twist: Twist) -> WheelSpeeds {
        let half = self.track_m / 2.0;
        WheelSpeeds {
            left_rad_s: (twist.linear_m_s - twist.angular_rad_s * half) / self.wheel_radius_m,
            right_rad_s: (twist.linear_m_s + twist.angular_rad_s * half) / self.wheel_radius_m,
        }
    }

    /// The twist that wheel speeds give the base (rolling without slip).
    pub fn twist(&self, wheels: WheelSpeeds) -> Twist {
        let r = self.wheel_radius_m;
        Twist {
            linear_m_s: r * (wheels.left_rad_s + wheels.right_rad_s) / 2.0,
            angular_rad_s: r * (wheels.right_rad_s - wheels.left_rad_s) / self.track_m,
        }
    }

    /// Wheel quantities (speeds or angle changes, left and right) in the servos' own
    /// directions, and back: the mounting is its own inverse.
    pub fn servo_frame(&self, wheels: [f64; 2]) -> [f64; 2] {
        [
            wheels[0] * self.servo_sign[0],
            wheels[1] * self.servo_sign[1],
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn a3() -> Geometry {
        Geometry::new(0.05, 0.36, false, true).unwrap()
    }

    #[test]
    fn straight_turning_and_spinning_in_place() {
        let g = a3();
        let w = g.wheel_speeds(Twist::new(0.3, 0.0));
        assert!((w.left_rad_s - 6.0).abs() < 1e-12 && (w.right_rad_s - 6.0).abs() < 1e-12);
        // Counter-clockwise: the right wheel runs faster.
        let w = g.wheel_speeds(Twist::new(0.0, 1.0));
        assert!((w.left_rad_s + 3.6).abs() < 1e-12 && (w.right_rad_s - 3.6).abs() < 1e-12);
        let w = g.wheel_speeds(Twist::new(0.2, 0.5));
        assert!((w.left_rad_s - 2.2).abs() < 1e-12 && (w.right_rad_s - 5.8).abs() < 1e-12);
    }

    #[test]
    fn twist_and_wheel_speeds_are_inverse() {
        let g = a3();
        for t in [
            Twist::new(0.3, 0.0),
            Twist::new(-0.1, 0.7),
            Twist::new(0.0, -1.2),
        ] {
            let back = g.twist(g.wheel_speeds(t));
            assert!((back.linear_m_s - t.linear_m_s).abs() < 1e-12);
            assert!((back.angular_rad_s - t.angular_rad_s).abs() < 1e-12);
        }
    }

    #[test]
    fn saturation_keeps_the_curvature() {
        let g = a3();
        let t = Twist::new(0.3, 1.0);
        let w = g.wheel_speeds(t);
        let limited = w.limited(6.0);
        assert!(limited.left_rad_s.abs() <= 6.0 && limited.right_rad_s.abs() <= 6.0);
        assert!(
            (limited.right_rad_s - 6.0).abs() < 1e-12,
            "the faster wheel at the limit"
        );
        let radius = |t: Twist| t.linear_m_s / t.angular_rad_s;
        assert!((radius(g.twist(limited)) - radius(t)).abs() < 1e-12);
        // Within the limit nothing changes.
        let slow = g.wheel_speeds(Twist::new(0.1, 0.0));
        assert_eq!(slow.limited(6.0), slow);
    }

    #[test]
    fn the_mounting_turns_one_servo_backwards() {
        let g = a3();
        assert_eq!(g.servo_frame([2.0, 2.0]), [2.0, -2.0]);
        assert_eq!(g.servo_frame(g.servo_frame([1.5, -0.5])), [1.5, -0.5]);
    }

    #[test]
    fn impossible_geometries_are_refused() {
        assert!(Geometry::new(0.0, 0.36, false, true).is_err());
        assert!(Geometry::new(0.05, f64::NAN, false, true).is_err());
        assert!(Geometry::new(-0.05, 0.36, false, true).is_err());
    }
}
