//! The simulated base: where the wheels really take it in the room, and the wall that stops it.
//!
//! Written from the description's geometry, not from the `base` crate the stack runs: a
//! misreading shared by both would pass every odometry test. The base rolls without slip; its
//! rectangular footprint may not enter a wall or an object. Driven into one, it stops and
//! its wheels are held where they met it (a stiff spring on each wheel's angle, like an arm's
//! hard stop), so the motors stall against it, current up and position still, as on the real
//! robot; driven back, it is free again. Simplifications: no slip, no turning while pressed
//! against an obstacle, the casters' drag folded into the wheels' rolling resistance.

use crate::description::{RobotDescription, WheelsDescription};
use crate::room::Room;
use serde::Serialize;

/// Stiffness holding a wheel where the base met an obstacle, N·m/rad.
const CONTACT_STIFFNESS: f64 = 40.0;
/// Its damping, N·m·s/rad.
const CONTACT_DAMPING: f64 = 2.0;
/// How far the wheels must turn back from where the base met an obstacle to leave it, rad.
const RELEASE_RAD: f64 = 1e-3;
/// Points along each side of the footprint checked against the room (2.8 cm apart on a 45 cm
/// side: nothing thinner than a table leg passes between them).
const SIDE_POINTS: usize = 16;
/// The footprint touches an obstacle nearer than this, m.
const TOUCH_M: f64 = 0.002;
/// Height of the plane in which the base meets the room, m (a chair's rung, a table's leg).
const BUMP_HEIGHT_M: f64 = 0.15;

/// Where the base is and what it met.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct BaseReport {
    /// m, in the room.
    pub x_m: f64,
    /// m.
    pub y_m: f64,
    /// Heading, rad, counter-clockwise from +x.
    pub theta_rad: f64,
    /// Path length of its centre, m.
    pub travelled_m: f64,
    /// Times it ran into something.
    pub bumps: u64,
    /// Pressed against something now.
    pub blocked: bool,
}

/// The base's motion in the room.
#[derive(Debug, Clone)]
pub struct BaseMotion {
    radius: f64,
    track: f64,
    /// +1/−1: each servo's positive direction against its wheel's forward one.
    sign: [f64; 2],
    /// Half the footprint's length and width, m.
    half: [f64; 2],
    room: Room,
    pose: [f64; 3],
    /// The wheels' angles when the base met an obstacle, and the direction it was going (±1).
    contact: Option<([f64; 2], f64)>,
    travelled: f64,
    bumps: u64,
}

impl BaseMotion {
    /// The moving base of `wheels` (`None` when the description gives no geometry).
    pub fn new(robot: &RobotDescription, wheels: &WheelsDescription) -> Option<BaseMotion> {
        Some(BaseMotion {
            radius: wheels.wheel_radius_m?,
            track: wheels.track_m?,
            sign: [1.0, if wheels.right_inverted { -1.0 } else { 1.0 }],
            half: [wheels.footprint_m[0] / 2.0, wheels.footprint_m[1] / 2.0],
            room: Room::new(robot, BUMP_HEIGHT_M),
            pose: wheels.start,
            contact: None,
            travelled: 0.0,
            bumps: 0,
        })
    }

    /// Pose: x, y (m), heading (rad).
    pub fn pose(&self) -> [f64; 3] {
        self.pose
    }

    /// What it did.
    pub fn report(&self) -> BaseReport {
        BaseReport {
            x_m: self.pose[0],
            y_m: self.pose[1],
            theta_rad: self.pose[2],
            travelled_m: self.travelled,
            bumps: self.bumps,
            blocked: self.contact.is_some(),
        }
    }

    /// The load each wheel servo feels from an obstacle the base is pressed against, N·m in
    /// the servo's own direction (0 when free), for wheel angles and speeds in servo terms.
    pub fn contact_torque(&self, angle: [f64; 2], speed: [f64; 2]) -> [f64; 2] {
        match self.contact {
            Some((at, _)) => std::array::from_fn(|w| {
                CONTACT_STIFFNESS * (angle[w] - at[w]) + CONTACT_DAMPING * speed[w]
            }),
            None => [0.0; 2],
        }
    }

    /// The room's nearest surface to the footprint's outline at `pose`, m (0 when they touch).
    fn clearance(&self, pose: [f64; 3]) -> f64 {
        let (s, c) = pose[2].sin_cos();
        let [hl, hw] = self.half;
        let corners = [[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]];
        let mut nearest = f64::INFINITY;
        for k in 0..4 {
            let (a, b) = (corners[k], corners[(k + 1) % 4]);
            for i in 0..SIDE_POINTS {
                let t = i as f64 / SIDE_POINTS as f64;
                let local = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
                let world = [
                    pose[0] + c * local[0] - s * local[1],
                    pose[1] + s * local[0] + c * local[1],
                ];
                nearest = nearest.min(self.room.clearance(world));
            }
        }
        nearest
    }

    /// Moves the base for `dt` seconds with the wheels at `angle`, turning at `speed` (servo
    /// terms, rad and rad/s); it stops where its footprint would enter an obstacle.
    pub fn step(&mut self, dt: f64, angle: [f64; 2], speed: [f64; 2]) {
        let forward = |v: [f64; 2]| [v[0] * self.sign[0], v[1] * self.sign[1]];
        if let Some((at, direction)) = self.contact {
            // Free again once the wheels are back behind where they met it (touching it without
            // pushing is still touching: no new bump while it rests there).
            let [l, r] = forward([angle[0] - at[0], angle[1] - at[1]]);
            if (l + r) * direction > -RELEASE_RAD {
                return;
            }
            self.contact = None;
        }
        let [l, r] = forward(speed);
        let v = self.radius * (l + r) / 2.0;
        let w = self.radius * (r - l) / self.track;
        let [x, y, theta] = self.pose;
        let mid = theta + w * dt / 2.0;
        let next = [
            x + v * dt * mid.cos(),
            y + v * dt * mid.sin(),
            theta + w * dt,
        ];
        let before = self.clearance(self.pose);
        let after = self.clearance(next);
        if after < TOUCH_M && after < before {
            self.contact = Some((angle, v.signum()));
            self.bumps += 1;
            return;
        }
        self.travelled += (v * dt).abs();
        self.pose = [
            next[0],
            next[1],
            (next[2] + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
                - std::f64::consts::PI,
        ];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn base() -> BaseMotion {
        let robot = RobotDescription::nori_a3();
        let wheels = robot
            .bus
            .iter()
            .find_map(|b| b.wheels.clone())
            .expect("the A3 has wheels");
        BaseMotion::new(&robot, &wheels).expect("its base moves")
    }

    /// Servo speeds that drive the A3 at `v` m/s and `w` rad/s (its geometry written out).
    fn servo_speeds(v: f64, w: f64) -> [f64; 2] {
        let (r, half) = (0.075, 0.18);
        [(v - w * half) / r, -(v + w * half) / r]
    }

    fn run(b: &mut BaseMotion, angle: &mut [f64; 2], speed: [f64; 2], seconds: f64) {
        let dt = 0.001;
        for _ in 0..(seconds / dt).round() as usize {
            b.step(dt, *angle, speed);
            // Pressed against an obstacle, the wheels turn only away from it.
            let away = b.contact.is_none_or(|(_, direction)| {
                (speed[0] * b.sign[0] + speed[1] * b.sign[1]) * direction < 0.0
            });
            if away {
                angle[0] += speed[0] * dt;
                angle[1] += speed[1] * dt;
            }
        }
    }

    #[test]
    fn the_wheels_carry_the_base_straight_and_round() {
        let mut b = base();
        let start = b.pose();
        let mut angle = [0.0; 2];
        run(&mut b, &mut angle, servo_speeds(0.2, 0.0), 1.0);
        let p = b.pose();
        assert!((p[0] - start[0] - 0.2).abs() < 1e-9 && (p[1] - start[1]).abs() < 1e-9);
        // A half turn in place leaves the centre where it was.
        run(
            &mut b,
            &mut angle,
            servo_speeds(0.0, std::f64::consts::PI),
            1.0,
        );
        let q = b.pose();
        assert!((q[0] - p[0]).abs() < 1e-9 && (q[2].abs() - std::f64::consts::PI).abs() < 1e-6);
        assert_eq!(b.report().bumps, 0);
    }

    #[test]
    fn a_wall_stops_the_base_at_its_front_and_holds_the_wheels() {
        let mut b = base();
        let mut angle = [0.0; 2];
        // Forward (+x): the room's wall there is at 3.2 m.
        run(&mut b, &mut angle, servo_speeds(0.3, 0.0), 20.0);
        let r = b.report();
        assert!(r.blocked && r.bumps == 1, "{r:?}");
        // Its front (0.225 m ahead of the centre) at the wall, within a step at 0.3 m/s.
        assert!((3.2 - r.x_m - 0.225).abs() < TOUCH_M + 0.3 * 0.001, "{r:?}");
        // Pressing on: the wheels feel the wall in their own directions.
        let pressed = [angle[0] + 0.05, angle[1] - 0.05];
        let t = b.contact_torque(pressed, [0.0, 0.0]);
        assert!(t[0] > 1.0 && t[1] < -1.0, "{t:?}");
        // Backing off frees it.
        run(&mut b, &mut angle, servo_speeds(-0.1, 0.0), 1.0);
        let r = b.report();
        assert!(!r.blocked && r.x_m < 3.2 - 0.225 - 0.05, "{r:?}");
        assert_eq!(b.contact_torque(angle, [0.0; 2]), [0.0, 0.0]);
    }
}
