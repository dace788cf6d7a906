//! The protective field: how fast the base may still go along its path given what the lidar
//! sees in it, so that it stops short of an obstacle, as the protective fields of industrial
//! mobile robots do.
//!
//! The path is the corridor the base's body sweeps going straight forward (or backward): as
//! wide as the body, from its front (or back) edge on. The free distance is how far the
//! nearest return in that corridor lies beyond the edge. The speed allowed is the largest from
//! which the base, after the reaction time (the age of a revolution and a control period)
//! and braking at its limit, stops `stop-margin` short of that return.
//!
//! Turning is guarded too: a square body's corners sweep a circle wider than the body, so a
//! turn beside a wall or a table leg would strike it with no obstacle ahead. For each return
//! within that circle, the angle the body can turn (either way) before the return comes within
//! `stop-margin` of it is found by turning the return back around the base in steps of a
//! degree; the turn rate allowed stops within the smallest such angle after the reaction time.
//!
//! The reaction time includes the wheels' blind time: the servos keep their last speed when
//! nobody commands them (they have no watchdog), so a crashed driver leaves the base moving
//! until the restarted one sets the wheels up again (`driver-restart-ms`).

/// What the field guards and how the lidar sits on the base.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FieldConfig {
    /// The lidar's optical centre on the base (x forward, y left), m.
    pub lidar_x_m: f64,
    /// m.
    pub lidar_y_m: f64,
    /// Where the lidar's 0° points, rad counter-clockwise from the base's forward axis.
    pub lidar_yaw_rad: f64,
    /// Half the body's width, m (the corridor's half-width).
    pub half_width_m: f64,
    /// How far the body reaches ahead of the base's centre, m.
    pub front_m: f64,
    /// How far it reaches behind, m.
    pub back_m: f64,
    /// Distance kept from an obstacle at a stop, m.
    pub stop_margin_m: f64,
    /// Time from a measurement to the wheels acting on it, s (a revolution, a control period
    /// and the driver's cycle).
    pub reaction_s: f64,
    /// Returns nearer than this to the lidar are ignored (the robot's own body, dust), m.
    pub min_range_m: f64,
}

/// The field's verdict for one direction of travel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Verdict {
    /// Free distance from the body's edge to the nearest return in the path, m (infinite when
    /// nothing is in it).
    pub free_m: f64,
    /// The largest speed along the path that still stops `stop-margin` short of it, m/s.
    pub max_speed_m_s: f64,
}

/// The turning field's verdict for one direction of turn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TurnVerdict {
    /// The angle the body can turn before a return comes within the stop margin, rad
    /// (infinite when none can).
    pub free_rad: f64,
    /// The largest turn rate that still stops within it, rad/s.
    pub max_rate_rad_s: f64,
}

/// The most sectors [`FieldConfig::trusted`] judges a revolution by.
pub const MAX_SECTORS: usize = 8;

/// The turning field's angular resolution, rad (a degree: 1.7 mm at the A3's corners' 0.35 m).
const TURN_STEP_RAD: f64 = std::f64::consts::PI / 180.0;
/// A return this far inside the body's outline is something touching it (the lidar's range
/// noise puts it there), not one of the body's own parts, m.
const CONTACT_BAND_M: f64 = 0.02;
/// Step along an arc, m.
const ARC_STEP_M: f64 = 0.01;
/// Steps along an arc judged (3 m: more than any stop takes).
const ARC_STEPS: usize = 300;

impl FieldConfig {
    /// Whether a measurement is a return to judge: finite, and beyond the minimum range (no
    /// return reads 0; dust on the window reads nearer).
    fn is_return(&self, bearing: f64, range: f64) -> bool {
        range.is_finite() && range >= self.min_range_m && bearing.is_finite()
    }

    /// A return (bearing in the lidar's frame, rad; range, m) as a point in the base's frame.
    pub fn to_base(&self, bearing: f64, range: f64) -> (f64, f64) {
        let a = self.lidar_yaw_rad + bearing;
        (
            self.lidar_x_m + range * a.cos(),
            self.lidar_y_m + range * a.sin(),
        )
    }

    /// A point in the base's frame as the lidar would see it: (bearing, range).
    pub fn from_base(&self, (x, y): (f64, f64)) -> (f64, f64) {
        let (dx, dy) = (x - self.lidar_x_m, y - self.lidar_y_m);
        (dy.atan2(dx) - self.lidar_yaw_rad, dx.hypot(dy))
    }

    /// Whether a revolution's points (bearing, rad; range, m, 0 for no return) can be judged:
    /// each of `sectors` (1 to [`MAX_SECTORS`]) equal sectors around the lidar holds a return
    /// at or beyond the minimum range. A window covered reads as no return or as the cover
    /// itself: with one sector, only a wholly covered (or dead) lidar is caught; eight would
    /// catch a cover over part of it too (a home has a wall within 12 m everywhere), but they
    /// blinded the base in the simulated room, which is not yet understood (docs/hazards.md B2).
    pub fn trusted(&self, points: impl IntoIterator<Item = (f64, f64)>, sectors: usize) -> bool {
        let n = sectors.clamp(1, MAX_SECTORS);
        let mut seen = [false; MAX_SECTORS];
        let sector = std::f64::consts::TAU / n as f64;
        for (bearing, range) in points {
            if self.is_return(bearing, range) {
                let k = (bearing.rem_euclid(std::f64::consts::TAU) / sector) as usize;
                seen[k.min(n - 1)] = true;
            }
        }
        seen[..n].iter().all(|&s| s)
    }

    /// The verdict for travel forward (`forward`) or backward, from one revolution's points
    /// (bearing in the lidar's frame, rad counter-clockwise; range, m, 0 for no return), with
    /// the base braking at `brake_m_s2`.
    pub fn verdict(
        &self,
        points: impl IntoIterator<Item = (f64, f64)>,
        forward: bool,
        brake_m_s2: f64,
    ) -> Verdict {
        let mut free = f64::INFINITY;
        for (bearing, range) in points {
            if !self.is_return(bearing, range) {
                continue;
            }
            let (x, y) = self.to_base(bearing, range);
            if y.abs() > self.half_width_m {
                continue;
            }
            let ahead = if forward {
                x - self.front_m
            } else {
                -x - self.back_m
            };
            if ahead >= -CONTACT_BAND_M {
                free = free.min(ahead.max(0.0));
            }
        }
        Verdict {
            free_m: free,
            max_speed_m_s: self.stopping_speed(free - self.stop_margin_m, brake_m_s2),
        }
    }

    /// The verdict for turning counter-clockwise (`left`) or clockwise, from one revolution's
    /// points, the base braking its turn at `brake_rad_s2`.
    pub fn turn_verdict(
        &self,
        points: impl IntoIterator<Item = (f64, f64)>,
        left: bool,
        brake_rad_s2: f64,
    ) -> TurnVerdict {
        let m = self.stop_margin_m;
        let (front, back, half) = (self.front_m + m, self.back_m + m, self.half_width_m + m);
        let reach = front.max(back).hypot(half);
        let within = |x: f64, y: f64, f: f64, b: f64, h: f64| x <= f && x >= -b && y.abs() <= h;
        let mut free = f64::INFINITY;
        for (bearing, range) in points {
            if !self.is_return(bearing, range) {
                continue;
            }
            let (x, y) = self.to_base(bearing, range);
            // Beyond the corners' circle, or deep inside the body itself (its own parts):
            // nothing a turn can strike.
            let band = CONTACT_BAND_M;
            let (f, b, h) = (self.front_m, self.back_m, self.half_width_m);
            if x.hypot(y) > reach || within(x, y, f - band, b - band, h - band) {
                continue;
            }
            // Turning the body by φ turns the return by −φ around the base, as the base sees it.
            let sign = if left { -1.0 } else { 1.0 };
            let mut phi = 0.0;
            while phi < free && phi <= std::f64::consts::PI {
                let (s, c) = (sign * phi).sin_cos();
                if within(c * x - s * y, s * x + c * y, front, back, half) {
                    free = free.min((phi - TURN_STEP_RAD).max(0.0));
                    break;
                }
                phi += TURN_STEP_RAD;
            }
        }
        TurnVerdict {
            free_rad: free,
            max_rate_rad_s: self.stopping_speed(free, brake_rad_s2),
        }
    }

    /// The verdict for travel along an arc of `curvature` (rad/m, counter-clockwise positive,
    /// as the base sees its path going `forward` or backward), from one revolution's points:
    /// the body is moved along the arc a centimetre at a time until it would touch a return,
    /// the distance before that is the free one. A straight corridor misses what the arc
    /// sweeps outward (a post ahead and beside that a turning base drives its side into).
    pub fn arc_verdict(
        &self,
        points: impl IntoIterator<Item = (f64, f64)>,
        forward: bool,
        curvature: f64,
        brake_m_s2: f64,
    ) -> Verdict {
        // The body's pose at each step: (cos θ, sin θ, x, y).
        let mut poses = [(1.0, 0.0, 0.0, 0.0); ARC_STEPS];
        let dir = if forward { 1.0 } else { -1.0 };
        for (k, pose) in poses.iter_mut().enumerate() {
            let s = dir * (k + 1) as f64 * ARC_STEP_M;
            let th = curvature * s;
            let (sin, cos) = th.sin_cos();
            let (x, y) = if curvature.abs() < 1e-9 {
                (s, 0.0)
            } else {
                (sin / curvature, (1.0 - cos) / curvature)
            };
            *pose = (cos, sin, x, y);
        }
        let reach = self.front_m.max(self.back_m).hypot(self.half_width_m);
        let within =
            |x: f64, y: f64| x <= self.front_m && x >= -self.back_m && y.abs() <= self.half_width_m;
        let mut free = f64::INFINITY;
        for (bearing, range) in points {
            if !self.is_return(bearing, range) {
                continue;
            }
            let (px, py) = self.to_base(bearing, range);
            // Deep inside the body (its own parts), or beyond anything the arc reaches; a
            // return in the band at its edge is touching it (free 0).
            let band = CONTACT_BAND_M;
            let deep = px <= self.front_m - band
                && px >= -self.back_m + band
                && py.abs() <= self.half_width_m - band;
            if deep || px.hypot(py) > reach + ARC_STEPS as f64 * ARC_STEP_M {
                continue;
            }
            if within(px, py) {
                free = 0.0;
                break;
            }
            for (k, &(c, sn, x, y)) in poses.iter().enumerate() {
                let d = k as f64 * ARC_STEP_M;
                if d >= free {
                    break;
                }
                let (dx, dy) = (px - x, py - y);
                if within(c * dx + sn * dy, -sn * dx + c * dy) {
                    free = d;
                    break;
                }
            }
        }
        Verdict {
            free_m: free,
            max_speed_m_s: self.stopping_speed(free - self.stop_margin_m, brake_m_s2),
        }
    }

    /// The largest v with v·reaction + v²/(2·brake) ≤ `room`: 0 when there is no room.
    fn stopping_speed(&self, room: f64, brake: f64) -> f64 {
        if room <= 0.0 {
            return 0.0;
        }
        if room.is_infinite() {
            return f64::INFINITY;
        }
        let lead = brake * self.reaction_s;
        -lead + (lead * lead + 2.0 * brake * room).sqrt()
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// The A3's field as `base.toml` sets it (a shorter reaction time), for the tests here and
    /// the controller's.
    pub(crate) const A3: FieldConfig = FieldConfig {
        lidar_x_m: 0.15,
        lidar_y_m: 0.0,
        lidar_yaw_rad: 0.0,
        half_width_m: 0.25,
        front_m: 0.25,
        back_m: 0.25,
        stop_margin_m: 0.1,
        reaction_s: 0.2,
        min_range_m: 0.05,
    };

    /// A wall across the path `at` metres ahead of the lidar, as 360 returns of a revolution
    /// (the side walls far away).
    fn wall(at: f64) -> Vec<(f64, f64)> {
        (0..360)
            .map(|k| {
                let b = f64::from(k).to_radians();
                let r = if b.cos() > 1e-6 { at / b.cos() } else { 10.0 };
                (b, r.min(10.0))
            })
            .collect()
    }

    #[test]
    fn a_revolution_with_a_sector_of_no_return_is_not_trusted() {
        assert!(A3.trusted(wall(1.1), MAX_SECTORS));
        // A cover over the window's front quarter: no return, or the cover itself.
        for cover in [0.0, 0.02] {
            let covered = wall(1.1).into_iter().map(|(b, r)| {
                let front = b.cos() > std::f64::consts::FRAC_PI_4.cos();
                (b, if front { cover } else { r })
            });
            assert!(
                !A3.trusted(covered, MAX_SECTORS),
                "covered by returns at {cover} m"
            );
        }
        assert!(!A3.trusted(std::iter::empty(), 1));
        // One return per sector is enough (dark furniture returns little).
        let sparse = (0..MAX_SECTORS).map(|k| (k as f64 * 0.8 + 0.1, 3.0));
        assert!(A3.trusted(sparse.clone(), MAX_SECTORS));
        // One sector: any return at all.
        assert!(A3.trusted(sparse.take(1), 1));
        assert!(!A3.trusted([(0.1, 0.0), (0.2, 0.01)], 1));
    }

    #[test]
    fn the_speed_allowed_stops_the_base_short_of_a_wall_in_its_path() {
        let v = A3.verdict(wall(1.1), true, 1.0);
        // The body's front at 0.25, the lidar at 0.15: the wall 1.0 m beyond the front.
        assert!((v.free_m - 1.0).abs() < 1e-9, "{v:?}");
        // From that speed: reaction then braking ends exactly stop-margin short.
        let s = v.max_speed_m_s;
        assert!((s * 0.2 + s * s / 2.0 - 0.9).abs() < 1e-9, "{v:?}");
        // Closer than the margin: no speed at all.
        assert_eq!(A3.verdict(wall(0.18), true, 1.0).max_speed_m_s, 0.0);
    }

    #[test]
    fn only_the_path_counts() {
        // The wall is ahead: backing away is free.
        let back = A3.verdict(wall(0.5), false, 1.0);
        assert!(back.free_m > 5.0, "{back:?}");
        // A post beside the corridor (0.3 m to the left) does not slow it; in it, it does.
        let beside = [(0.3f64.atan2(1.0), 1.0f64.hypot(0.3))];
        assert_eq!(A3.verdict(beside, true, 1.0).free_m, f64::INFINITY);
        let inside = [(0.2f64.atan2(1.0), 1.0f64.hypot(0.2))];
        assert!((A3.verdict(inside, true, 1.0).free_m - 0.9).abs() < 1e-9);
        // Nothing at all, returns too near (the body) or invalid: nothing limits.
        let junk = [
            (0.0, 0.0),
            (0.0, 0.01),
            (f64::NAN, 1.0),
            (0.0, f64::INFINITY),
        ];
        assert_eq!(A3.verdict(junk, true, 1.0).max_speed_m_s, f64::INFINITY);
    }

    /// Returns along a line `x = at` (a wall across the front) from y = −1 to 1 m, in the
    /// lidar's frame.
    fn wall_points(at: f64) -> Vec<(f64, f64)> {
        (-100..=100)
            .map(|k| {
                let (x, y) = (at - A3.lidar_x_m, f64::from(k) * 0.01);
                (y.atan2(x), x.hypot(y))
            })
            .collect()
    }

    #[test]
    fn a_turn_beside_an_obstacle_is_slowed_and_stopped_before_a_corner_strikes_it() {
        // Far from everything: turning is free.
        let open = A3.turn_verdict(wall_points(2.0), true, 2.0);
        assert_eq!(open.max_rate_rad_s, f64::INFINITY);
        // A wall 0.1 m beyond the front (where the linear field stops the base): either turn
        // swings a front corner into the margin at once.
        for left in [true, false] {
            let v = A3.turn_verdict(wall_points(0.35), left, 2.0);
            assert_eq!(v.max_rate_rad_s, 0.0, "left {left}: {v:?}");
        }
        // 0.2 m beyond the front: the corner of the body grown by the margin (0.35, 0.35),
        // 0.495 m out, reaches the wall (x = 0.45) after 45° − acos(0.45 / 0.495) = 20.4° of
        // turn: slowed, not stopped.
        let near = A3.turn_verdict(wall_points(0.45), true, 2.0);
        let exact = std::f64::consts::FRAC_PI_4 - (0.45 / 0.35f64.hypot(0.35)).acos();
        assert!(
            near.free_rad <= exact && near.free_rad > exact - 2.0 * TURN_STEP_RAD,
            "{near:?} vs {exact}"
        );
        let rate = near.max_rate_rad_s;
        assert!(rate > 0.0 && rate < 1.0, "{near:?}");
        // The rate allowed stops within the free angle after the reaction time.
        assert!((rate * A3.reaction_s + rate * rate / 4.0 - near.free_rad).abs() < 1e-9);
        // A table leg off the front-left corner, ahead of it: turning left sweeps the front
        // edge into it at once; turning right, the left side comes round to it only later.
        let (lx, ly): (f64, f64) = (0.2 - A3.lidar_x_m, 0.38);
        let leg = [(ly.atan2(lx), lx.hypot(ly))];
        let (l, r) = (
            A3.turn_verdict(leg, true, 2.0),
            A3.turn_verdict(leg, false, 2.0),
        );
        // Left: in at 54.7° of bearing (y = 0.35), 7.6° of turn; right: round to 125.3°, 63.1°.
        assert!((l.free_rad.to_degrees() - 7.0).abs() <= 1.0, "left {l:?}");
        assert!((r.free_rad.to_degrees() - 62.5).abs() <= 1.0, "right {r:?}");
        // Returns inside the body (its own parts) and beyond the corners' circle do not count.
        let own = [(0.0, 0.05), (std::f64::consts::PI, 0.2), (0.0, 1.0)];
        assert_eq!(A3.turn_verdict(own, true, 2.0).free_rad, f64::INFINITY);
    }

    /// A lidar mounted off the centre line and sideways, and travel backward: the mount is
    /// added, not subtracted (found by the mutation pass: every earlier mount was symmetric).
    #[test]
    fn a_lidar_mounted_aside_and_sideways_and_travel_backward_are_measured_right() {
        let aside = FieldConfig {
            lidar_y_m: 0.1,
            ..A3
        };
        // 1 m ahead and 0.3 m to the right of the lidar: 0.2 m right of the centre line, in
        // the corridor.
        let p = [((-0.3f64).atan2(1.0), 1.0f64.hypot(0.3))];
        assert!((aside.verdict(p, true, 1.0).free_m - 0.9).abs() < 1e-9);
        let sideways = FieldConfig {
            lidar_yaw_rad: std::f64::consts::FRAC_PI_2,
            ..A3
        };
        // Its −90° looks forward.
        let v = sideways.verdict([(-std::f64::consts::FRAC_PI_2, 1.0)], true, 1.0);
        assert!((v.free_m - 0.9).abs() < 1e-9, "{v:?}");
        // Backward: a wall 1 m behind the lidar is 0.6 m behind the body.
        let back = A3.verdict([(std::f64::consts::PI, 1.0)], false, 1.0);
        assert!((back.free_m - 0.6).abs() < 1e-9, "{back:?}");
        // A bearing a hair below zero (rem_euclid rounds it to a whole turn) lands in the last
        // sector, not past it.
        assert!(!A3.trusted([(-1e-18, 1.0)], MAX_SECTORS));
        assert!(A3.trusted([(-1e-18, 1.0)], 1));
        // A lidar at the front edge: a return nearer than its minimum range (dust on its
        // window) is no obstacle, for travel or for turning.
        let at_front = FieldConfig {
            lidar_x_m: A3.front_m,
            ..A3
        };
        for dust in [(0.0, 0.02), (0.3, 0.03)] {
            assert_eq!(at_front.verdict([dust], true, 1.0).free_m, f64::INFINITY);
            assert_eq!(
                at_front.turn_verdict([dust], true, 2.0).free_rad,
                f64::INFINITY
            );
        }
    }

    /// Driving forward while turning left (0.2 m/s at 0.5 rad/s: a 0.4 m radius), a post
    /// 0.5 m ahead and 0.6 m left is outside the straight corridor and beyond the corners'
    /// circle, yet the base's side sweeps into it along the arc.
    #[test]
    fn an_arc_sees_what_its_sweep_strikes() {
        let (x, y): (f64, f64) = (0.5 - A3.lidar_x_m, 0.6);
        let post = [(y.atan2(x), x.hypot(y))];
        assert_eq!(A3.verdict(post, true, 1.0).free_m, f64::INFINITY);
        assert_eq!(A3.turn_verdict(post, true, 2.0).free_rad, f64::INFINITY);
        let arc = A3.arc_verdict(post, true, 0.5 / 0.2, 1.0);
        assert!(arc.free_m > 0.05 && arc.free_m < 0.6, "{arc:?}");
        let room = arc.free_m - A3.stop_margin_m;
        let v = arc.max_speed_m_s;
        assert!(
            (v * A3.reaction_s + v * v / 2.0 - room).abs() < 1e-9,
            "{arc:?}"
        );
        // Turning right instead: away from it, free.
        assert_eq!(
            A3.arc_verdict(post, true, -0.5 / 0.2, 1.0).free_m,
            f64::INFINITY
        );
        // Backing up along the same circle reaches it only most of the way round.
        let backing = A3.arc_verdict(post, false, 0.5 / 0.2, 1.0);
        assert!(backing.free_m > 1.2, "{backing:?}");
        // A straight arc is the corridor: a wall 1.1 m ahead of the lidar is 1.0 m ahead,
        // to the step.
        let straight = A3.arc_verdict(wall(1.1), true, 0.0, 1.0);
        assert!((straight.free_m - 0.99).abs() < 1e-9, "{straight:?}");
        // Backward: a wall 1 m behind the lidar is 0.6 m behind the body.
        let back = A3.arc_verdict([(std::f64::consts::PI, 1.0)], false, 0.0, 1.0);
        assert!((back.free_m - 0.59).abs() < 1e-9, "{back:?}");
        // Its own parts and junk do not count.
        let own = [
            (0.0, 0.05),
            (0.0, 0.0),
            (f64::NAN, 1.0),
            (0.0, f64::INFINITY),
        ];
        assert_eq!(A3.arc_verdict(own, true, 1.0, 1.0).free_m, f64::INFINITY);
    }

    #[test]
    fn a_lidar_mounted_turned_is_taken_into_account() {
        // Mounted backwards: its 180° looks forward.
        let turned = FieldConfig {
            lidar_yaw_rad: std::f64::consts::PI,
            ..A3
        };
        let v = turned.verdict([(std::f64::consts::PI, 1.0)], true, 1.0);
        assert!((v.free_m - 0.9).abs() < 1e-9, "{v:?}");
    }
}
