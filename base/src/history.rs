//! Where the base was over the last moments (the odometry's poses), to move each point of a
//! lidar revolution from where the base stood when the point was measured to where it stands
//! now. A revolution takes 100 ms and may be 300 ms old when it is judged: a base turning at
//! 1 rad/s has turned 0.3 rad since its oldest point was measured, and a post 1 m ahead has
//! moved 30 cm across the base's frame since. Fixed size, no allocation.

use crate::odometry::{wrap_angle, Pose2};

/// Poses kept.
const LEN: usize = 64;
/// A pose is kept at most this often, ns: 64 of them span 640 ms, more than the oldest
/// revolution the field takes (300 ms) and its own duration (100 ms).
const EVERY_NS: u64 = 10_000_000;

/// The base's recent poses, oldest first, at most one per [`EVERY_NS`] (the newest always the
/// latest given).
#[derive(Debug, Clone)]
pub struct PoseHistory {
    poses: [(u64, Pose2); LEN],
    /// Index of the oldest.
    first: usize,
    len: usize,
}

impl Default for PoseHistory {
    fn default() -> Self {
        PoseHistory {
            poses: [(0, Pose2::default()); LEN],
            first: 0,
            len: 0,
        }
    }
}

impl PoseHistory {
    fn get(&self, k: usize) -> (u64, Pose2) {
        self.poses[(self.first + k) % LEN]
    }

    /// The pose at `t_ns` (later than every pose given before; an earlier one is ignored).
    pub fn push(&mut self, t_ns: u64, pose: Pose2) {
        if self.len > 0 {
            let (newest, _) = self.get(self.len - 1);
            if t_ns < newest {
                return;
            }
            // The newest is kept only once it is far enough from the one before it;
            // until then the next pose replaces it.
            if self.len > 1 && newest < self.get(self.len - 2).0 + EVERY_NS {
                self.poses[(self.first + self.len - 1) % LEN] = (t_ns, pose);
                return;
            }
        }
        if self.len == LEN {
            self.first = (self.first + 1) % LEN;
            self.len -= 1;
        }
        self.poses[(self.first + self.len) % LEN] = (t_ns, pose);
        self.len += 1;
    }

    /// Forgets every pose (the odometry started again).
    pub fn clear(&mut self) {
        self.len = 0;
    }

    /// The newest pose.
    pub fn newest(&self) -> Option<Pose2> {
        (self.len > 0).then(|| self.get(self.len - 1).1)
    }

    /// The pose at `t_ns`, interpolated between the two around it; the newest for a later
    /// time; `None` before the oldest (where the base was then is not known).
    pub fn at(&self, t_ns: u64) -> Option<Pose2> {
        let (newest_t, newest) = self.get(self.len.checked_sub(1)?);
        if t_ns >= newest_t {
            return Some(newest);
        }
        for k in (0..self.len - 1).rev() {
            let (t0, p0) = self.get(k);
            if t0 <= t_ns {
                let (t1, p1) = self.get(k + 1);
                let f = (t_ns - t0) as f64 / (t1 - t0).max(1) as f64;
                return Some(Pose2 {
                    x_m: p0.x_m + f * (p1.x_m - p0.x_m),
                    y_m: p0.y_m + f * (p1.y_m - p0.y_m),
                    theta_rad: p0.theta_rad + f * wrap_angle(p1.theta_rad - p0.theta_rad),
                });
            }
        }
        None
    }
}

/// A point `p` in the base's frame when it stood at `then`, in its frame at `now`.
pub fn moved(p: (f64, f64), then: Pose2, now: Pose2) -> (f64, f64) {
    let (s, c) = then.theta_rad.sin_cos();
    let (wx, wy) = (then.x_m + c * p.0 - s * p.1, then.y_m + s * p.0 + c * p.1);
    let (dx, dy) = (wx - now.x_m, wy - now.y_m);
    let (s, c) = now.theta_rad.sin_cos();
    (c * dx + s * dy, -s * dx + c * dy)
}

#[cfg(test)]
mod tests {
    use super::*;

    use telemetry::clock::MS;

    fn pose(x: f64, y: f64, theta: f64) -> Pose2 {
        Pose2 {
            x_m: x,
            y_m: y,
            theta_rad: theta,
        }
    }

    #[test]
    fn poses_are_kept_every_10_ms_and_interpolated_between() {
        let mut h = PoseHistory::default();
        assert_eq!(h.at(0), None);
        // Every 5 ms (the driver's rate) for 1 s, turning at 1 rad/s and moving at 0.1 m/s.
        for k in 0..=200u64 {
            let t = k as f64 * 0.005;
            h.push(k * 5 * MS, pose(0.1 * t, 0.0, wrap_angle(t)));
        }
        assert_eq!(h.newest(), Some(pose(0.1, 0.0, wrap_angle(1.0))));
        // 640 ms kept, no more.
        assert!(h.at(1000 * MS - 600 * MS).is_some());
        assert_eq!(h.at(1000 * MS - 700 * MS), None);
        let mid = h.at(700 * MS + 2 * MS).unwrap();
        assert!((mid.theta_rad - 0.702).abs() < 1e-9, "{mid:?}");
        assert!((mid.x_m - 0.0702).abs() < 1e-9, "{mid:?}");
        // Later than the newest: the newest. An older pose given late is ignored.
        assert_eq!(h.at(2000 * MS), h.newest());
        h.push(10 * MS, pose(9.0, 9.0, 0.0));
        assert_eq!(h.at(2000 * MS), Some(pose(0.1, 0.0, wrap_angle(1.0))));
        h.clear();
        assert_eq!((h.at(1000 * MS), h.newest()), (None, None));
    }

    #[test]
    fn interpolation_takes_the_short_way_across_the_half_turn() {
        let mut h = PoseHistory::default();
        h.push(0, pose(0.0, 0.0, 3.1));
        h.push(20 * MS, pose(0.0, 0.0, -3.1));
        let mid = h.at(10 * MS).unwrap();
        assert!(
            wrap_angle(mid.theta_rad - std::f64::consts::PI).abs() < 1e-9,
            "{mid:?}"
        );
    }

    #[test]
    fn a_point_moves_opposite_to_the_base() {
        // Driven 0.5 m forward: a post 1 m ahead is 0.5 m ahead.
        let p = moved((1.0, 0.0), pose(0.0, 0.0, 0.0), pose(0.5, 0.0, 0.0));
        assert!((p.0 - 0.5).abs() < 1e-12 && p.1.abs() < 1e-12, "{p:?}");
        // Turned 90° left: a post 1 m ahead is now 1 m to the right.
        let q = moved(
            (1.0, 0.0),
            pose(0.0, 0.0, 0.0),
            pose(0.0, 0.0, std::f64::consts::FRAC_PI_2),
        );
        assert!(q.0.abs() < 1e-12 && (q.1 + 1.0).abs() < 1e-12, "{q:?}");
        // From a pose turned and moved, back to where it was seen.
        let a = pose(1.0, 2.0, 0.7);
        let b = pose(1.3, 1.8, -0.4);
        let back = moved(moved((0.4, -0.2), a, b), b, a);
        assert!((back.0 - 0.4).abs() < 1e-12 && (back.1 + 0.2).abs() < 1e-12);
    }
}
