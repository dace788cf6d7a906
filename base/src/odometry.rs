//! Where the base went, from its wheels: each cycle's change of the two wheel angles (which
//! wrap at one turn on the servos' position registers) integrated along an arc.

use crate::drive::{Geometry, Twist, WheelSpeeds};
use std::f64::consts::{PI, TAU};

/// A pose in the plane: position and heading (counter-clockwise from the x axis), in the frame
/// the odometry started in.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Pose2 {
    /// m.
    pub x_m: f64,
    /// m.
    pub y_m: f64,
    /// rad, within (−π, π].
    pub theta_rad: f64,
}

/// One reading of both wheels, in the servos' own directions.
#[derive(Debug, Clone, Copy)]
struct Reading {
    t_ns: u64,
    angle_rad: [f64; 2],
}

/// Pose and twist of the base integrated from the wheels' positions.
///
/// A wheel's position register wraps at one turn, so a change between two readings is known
/// only up to whole turns; it is taken as the one nearest what the wheel's measured speed
/// predicts over the interval. Without that, a gap of readings longer than half a turn at the
/// wheel's speed (0.5 s at 6 rad/s) would lose or invent whole turns.
#[derive(Debug, Clone)]
pub struct Odometry {
    geometry: Geometry,
    last: Option<Reading>,
    pose: Pose2,
    twist: Twist,
    travelled_m: f64,
}

impl Odometry {
    /// At the origin, not yet read.
    pub fn new(geometry: Geometry) -> Odometry {
        Odometry {
            geometry,
            last: None,
            pose: Pose2::default(),
            twist: Twist::default(),
            travelled_m: 0.0,
        }
    }

    /// The pose now.
    pub fn pose(&self) -> Pose2 {
        self.pose
    }

    /// The twist over the last interval.
    pub fn twist(&self) -> Twist {
        self.twist
    }

    /// Path length covered by the base's centre, m.
    pub fn travelled_m(&self) -> f64 {
        self.travelled_m
    }

    /// Starts again from `pose`; the next reading only sets the reference.
    pub fn reset(&mut self, pose: Pose2) {
        self.pose = pose;
        self.last = None;
        self.twist = Twist::default();
    }

    /// The wheels read at `t_ns`: their angles and speeds in the servos' own directions
    /// (as the state plane carries them: angle within one turn, speed in rad/s). Returns the
    /// pose. A reading not later than the last one, or with a non-finite value, is ignored.
    pub fn update(&mut self, t_ns: u64, angle_rad: [f64; 2], speed_rad_s: [f64; 2]) -> Pose2 {
        if !angle_rad.iter().chain(&speed_rad_s).all(|v| v.is_finite()) {
            return self.pose;
        }
        let Some(last) = self.last else {
            self.last = Some(Reading { t_ns, angle_rad });
            return self.pose;
        };
        if t_ns <= last.t_ns {
            return self.pose;
        }
        let dt = (t_ns - last.t_ns) as f64 * 1e-9;
        let mut turned = [0.0; 2];
        for w in 0..2 {
            turned[w] = unwrap(angle_rad[w] - last.angle_rad[w], speed_rad_s[w] * dt);
        }
        let [left, right] = self.geometry.servo_frame(turned);
        // The twist the wheels' turns give over the interval, integrated along its arc.
        let step = self.geometry.twist(WheelSpeeds {
            left_rad_s: left,
            right_rad_s: right,
        });
        let (ds, dtheta) = (step.linear_m_s, step.angular_rad_s);
        let heading = self.pose.theta_rad + dtheta / 2.0;
        // Exact for a constant twist: the chord of the arc, 2·sin(dθ/2)/dθ times the arc.
        let chord = if dtheta.abs() < 1e-9 {
            1.0
        } else {
            (dtheta / 2.0).sin() / (dtheta / 2.0)
        };
        self.pose.x_m += ds * chord * heading.cos();
        self.pose.y_m += ds * chord * heading.sin();
        self.pose.theta_rad = wrap_angle(self.pose.theta_rad + dtheta);
        self.twist = Twist::new(ds / dt, dtheta / dt);
        self.travelled_m += ds.abs();
        self.last = Some(Reading { t_ns, angle_rad });
        self.pose
    }
}

/// `delta` plus the whole number of turns that brings it nearest `expected`.
fn unwrap(delta: f64, expected: f64) -> f64 {
    delta + TAU * ((expected - delta) / TAU).round()
}

/// An angle within (−π, π].
pub fn wrap_angle(a: f64) -> f64 {
    let w = a.rem_euclid(TAU);
    if w > PI {
        w - TAU
    } else {
        w
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn a3() -> Geometry {
        Geometry::new(0.05, 0.36, false, true).unwrap()
    }

    /// Simulated wheels: their true angles (unwrapped) and the time.
    #[derive(Default)]
    struct Wheels {
        t_s: f64,
        angle: [f64; 2],
    }

    impl Wheels {
        /// Driven at `twist` for `seconds`, read every `every_s` (angles wrapped to one turn as
        /// the registers give them, in the servos' directions).
        fn drive(&mut self, odo: &mut Odometry, twist: Twist, seconds: f64, every_s: f64) {
            let g = a3();
            let w = g.wheel_speeds(twist);
            let speed = g.servo_frame([w.left_rad_s, w.right_rad_s]);
            for _ in 0..(seconds / every_s).round() as usize {
                self.t_s += every_s;
                for (a, s) in self.angle.iter_mut().zip(speed) {
                    *a += s * every_s;
                }
                let wrapped = self.angle.map(|a| a.rem_euclid(TAU));
                odo.update((self.t_s * 1e9).round() as u64, wrapped, speed);
            }
        }
    }

    fn started() -> (Odometry, Wheels) {
        let mut odo = Odometry::new(a3());
        odo.update(0, [0.0, 0.0], [0.0, 0.0]);
        (odo, Wheels::default())
    }

    #[test]
    fn a_straight_run_a_turn_and_a_circle() {
        let (mut odo, mut wheels) = started();
        wheels.drive(&mut odo, Twist::new(0.3, 0.0), 2.0, 0.005);
        let p = odo.pose();
        assert!((p.x_m - 0.6).abs() < 1e-9 && p.y_m.abs() < 1e-9 && p.theta_rad.abs() < 1e-9);
        assert!((odo.twist().linear_m_s - 0.3).abs() < 1e-9);
        // A quarter turn in place.
        wheels.drive(&mut odo, Twist::new(0.0, PI / 2.0), 1.0, 0.005);
        let p = odo.pose();
        assert!((p.x_m - 0.6).abs() < 1e-9 && (p.theta_rad - PI / 2.0).abs() < 1e-9);
        // A full circle of radius 0.5 m comes back to where it started.
        wheels.drive(&mut odo, Twist::new(0.25, 0.5), 4.0 * PI, 4.0 * PI / 2500.0);
        let q = odo.pose();
        assert!(
            (q.x_m - p.x_m).abs() < 1e-6 && (q.y_m - p.y_m).abs() < 1e-6,
            "{q:?}"
        );
        assert!((wrap_angle(q.theta_rad - p.theta_rad)).abs() < 1e-6);
        assert!((odo.travelled_m() - (0.6 + 2.0 * PI * 0.5)).abs() < 1e-6);
    }

    #[test]
    fn a_gap_of_readings_longer_than_half_a_turn_loses_no_turn() {
        // 6 rad/s read every 0.7 s: 4.2 rad between readings, more than half a turn.
        let (mut odo, mut wheels) = started();
        wheels.drive(&mut odo, Twist::new(0.3, 0.0), 2.1, 0.7);
        assert!((odo.pose().x_m - 0.63).abs() < 1e-9, "{:?}", odo.pose());
        // Backwards too.
        let (mut odo, mut wheels) = started();
        wheels.drive(&mut odo, Twist::new(-0.3, 0.0), 2.1, 0.7);
        assert!((odo.pose().x_m + 0.63).abs() < 1e-9, "{:?}", odo.pose());
    }

    #[test]
    fn a_mirrored_mounting_is_what_makes_equal_servo_speeds_a_spin() {
        let mut odo = Odometry::new(a3());
        // Both servos at +2 rad/s: the right wheel (inverted) drives backwards.
        for i in 0..=200u64 {
            let t = i as f64 * 0.005;
            let a = (2.0 * t).rem_euclid(TAU);
            odo.update(i * 5_000_000, [a, a], [2.0, 2.0]);
        }
        let p = odo.pose();
        assert!(p.x_m.abs() < 1e-9 && p.y_m.abs() < 1e-9);
        // Clockwise: 2 rad/s × 0.05 m × 2 / 0.36 m for 1 s.
        assert!(
            (p.theta_rad + 2.0 * 0.05 * 2.0 / 0.36).abs() < 1e-9,
            "{p:?}"
        );
    }

    #[test]
    fn stale_repeated_or_non_finite_readings_are_ignored() {
        let mut odo = Odometry::new(a3());
        odo.update(1_000, [0.0, 0.0], [0.0, 0.0]);
        odo.update(1_000, [1.0, -1.0], [0.0, 0.0]);
        odo.update(500, [1.0, -1.0], [0.0, 0.0]);
        odo.update(2_000, [f64::NAN, 0.0], [0.0, 0.0]);
        assert_eq!(odo.pose(), Pose2::default());
        odo.reset(Pose2 {
            x_m: 1.0,
            y_m: 2.0,
            theta_rad: 0.5,
        });
        odo.update(3_000, [3.0, 3.0], [0.0, 0.0]);
        assert_eq!(
            odo.pose().x_m,
            1.0,
            "the first reading after a reset is only a reference"
        );
    }

    #[test]
    fn angles_wrap_into_minus_pi_to_pi() {
        assert!((wrap_angle(3.0 * PI / 2.0) + PI / 2.0).abs() < 1e-12);
        assert_eq!(wrap_angle(PI), PI);
        assert!((wrap_angle(-PI) - PI).abs() < 1e-12);
        assert!(wrap_angle(0.1) == 0.1);
    }
}
