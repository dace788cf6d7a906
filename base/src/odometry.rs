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

/// How far back the reported twist looks. A reading's time is stamped when the driver has read
/// the whole bus, a little after the wheels were sampled and by an amount that varies with the
/// machine's load. Differenced over one 5 ms driver period, that jitter alone makes the speed
/// read high on average, by about Var(δ)/period² where δ is the difference of two successive
/// stamps' lateness (2.6 % for a lateness uniform in 0–2 ms; a loaded CI machine measured
/// 0.171 m/s for 0.15). Over 100 ms the bias is 400 times smaller; the price is a twist 50 ms
/// late, which nothing closes a loop on (the wheels' speed loops run in the servos).
pub const TWIST_WINDOW_NS: u64 = 100_000_000;

/// Readings kept for the twist's window: 100 ms at up to 600 Hz (at a faster rate the window
/// shrinks to what the ring holds).
const TRACK_LEN: usize = 64;

/// Where the base had got to at a reading: the path its centre covered (signed, forward
/// positive) and its heading, unwrapped.
#[derive(Debug, Clone, Copy, Default)]
struct Track {
    t_ns: u64,
    s_m: f64,
    theta_rad: f64,
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
    /// The newest readings' tracks (a ring: `track_len` of them ending at `track_head`).
    track: [Track; TRACK_LEN],
    track_head: usize,
    track_len: usize,
    /// The newest reading's track.
    at: Track,
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
            track: [Track::default(); TRACK_LEN],
            track_head: 0,
            track_len: 0,
            at: Track::default(),
        }
    }

    /// The pose now.
    pub fn pose(&self) -> Pose2 {
        self.pose
    }

    /// The twist over the last [`TWIST_WINDOW_NS`] of readings (over the last interval when
    /// that is longer).
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
        self.track_len = 0;
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
            self.at.t_ns = t_ns;
            self.push_track();
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
        self.travelled_m += ds.abs();
        self.last = Some(Reading { t_ns, angle_rad });
        self.at = Track {
            t_ns,
            s_m: self.at.s_m + ds,
            theta_rad: self.at.theta_rad + dtheta,
        };
        let since = self.window_start(t_ns);
        let span = (t_ns - since.t_ns) as f64 * 1e-9;
        self.twist = Twist::new(
            (self.at.s_m - since.s_m) / span,
            (self.at.theta_rad - since.theta_rad) / span,
        );
        self.push_track();
        self.pose
    }

    /// The newest kept track at least [`TWIST_WINDOW_NS`] before `t_ns`, or the oldest kept.
    /// There is always one: the previous reading's.
    fn window_start(&self, t_ns: u64) -> Track {
        let mut start = self.track[self.track_head];
        for back in 0..self.track_len {
            start = self.track[(self.track_head + TRACK_LEN - back) % TRACK_LEN];
            if t_ns - start.t_ns >= TWIST_WINDOW_NS {
                break;
            }
        }
        start
    }

    fn push_track(&mut self) {
        if self.track_len > 0 {
            self.track_head = (self.track_head + 1) % TRACK_LEN;
        }
        self.track[self.track_head] = self.at;
        self.track_len = (self.track_len + 1).min(TRACK_LEN);
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

    /// Readings stamped up to 2 ms late at random (a loaded machine): the measured speed over
    /// a run is the true one (differenced over single 5 ms periods it read 2.6 % high on
    /// average, a single reading up to 5/3 of it), and a change of speed shows in full once a
    /// window has passed.
    #[test]
    fn a_late_time_stamp_does_not_make_the_base_read_fast() {
        let g = a3();
        let mut odo = Odometry::new(g);
        let mut rng = 0x2545_f491_4f6c_dd1d_u64;
        let mut jitter_ns = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            rng % 2_000_000
        };
        let (mut angle, mut t_s) = ([0.0f64; 2], 0.0);
        let mut run = |odo: &mut Odometry, v: f64, seconds: f64| {
            let w = g.wheel_speeds(Twist::new(v, 0.0));
            let speed = g.servo_frame([w.left_rad_s, w.right_rad_s]);
            let mut measured = Vec::new();
            for _ in 0..(seconds / 0.005) as usize {
                t_s += 0.005;
                for (a, s) in angle.iter_mut().zip(speed) {
                    *a += s * 0.005;
                }
                let stamp = (t_s * 1e9) as u64 + jitter_ns();
                odo.update(stamp, angle.map(|a| a.rem_euclid(TAU)), speed);
                measured.push(odo.twist().linear_m_s);
            }
            measured
        };
        let cruise = run(&mut odo, 0.15, 2.0);
        let mean = cruise[40..].iter().sum::<f64>() / (cruise.len() - 40) as f64;
        assert!((mean - 0.15).abs() < 0.002, "measured {mean} m/s for 0.15");
        let worst = cruise[40..]
            .iter()
            .fold(0.0f64, |m, v| m.max((v - 0.15).abs()));
        assert!(worst < 0.01, "one reading {worst} m/s off");
        let after = run(&mut odo, -0.1, 0.2);
        let last = after[after.len() - 1];
        assert!(
            (last + 0.1).abs() < 0.005,
            "{last} m/s 200 ms after a change to -0.1"
        );
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
