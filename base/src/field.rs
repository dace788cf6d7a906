//! The protective field: how fast the base may still go along its path given what the lidar
//! sees in it, so that it stops short of an obstacle, as the protective fields of industrial
//! mobile robots do.
//!
//! The path is the corridor the base's body sweeps going straight forward (or backward): as
//! wide as the body, from its front (or back) edge on. The free distance is how far the
//! nearest return in that corridor lies beyond the edge. The speed allowed is the largest from
//! which the base, after the reaction time (the age of a revolution and a control period)
//! and braking at its limit, stops `stop-margin` short of that return. Turning in place is not
//! limited (the footprint's corners sweep a circle the corridor test does not cover: a square
//! base turning beside a wall is left to the operator, said in ARCHITECTURE.md).

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

impl FieldConfig {
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
            if !(range.is_finite() && range >= self.min_range_m && bearing.is_finite()) {
                continue;
            }
            let a = self.lidar_yaw_rad + bearing;
            let x = self.lidar_x_m + range * a.cos();
            let y = self.lidar_y_m + range * a.sin();
            if y.abs() > self.half_width_m {
                continue;
            }
            let ahead = if forward {
                x - self.front_m
            } else {
                -x - self.back_m
            };
            if ahead >= 0.0 {
                free = free.min(ahead);
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
