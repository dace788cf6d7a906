//! The room in a horizontal plane: what the lidar's beams hit and what the base bumps into.

use crate::description::{RobotDescription, SceneObject};

/// The room as a horizontal plane cuts it: its walls, and the objects crossing the plane.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Room {
    walls: Vec<([f64; 2], [f64; 2])>,
    boxes: Vec<([f64; 2], [f64; 2])>,
    circles: Vec<([f64; 2], f64)>,
}

impl Room {
    /// The walls of `robot`'s room and the objects crossing the plane at height `z`.
    pub fn new(robot: &RobotDescription, z: f64) -> Self {
        let mut room = Room::default();
        if let Some(r) = &robot.room {
            let n = r.walls.len();
            room.walls = (0..n).map(|i| (r.walls[i], r.walls[(i + 1) % n])).collect();
        }
        for o in &robot.object {
            room.add(o, z);
        }
        room
    }

    pub(crate) fn add(&mut self, o: &SceneObject, z: f64) {
        match (o.center, o.radius_m, o.min, o.max) {
            (Some(c), Some(r), _, _) if (c[2] - z).abs() < r => {
                self.circles
                    .push(([c[0], c[1]], (r * r - (c[2] - z).powi(2)).sqrt()));
            }
            (_, _, Some(min), Some(max)) if min[2] <= z && z <= max[2] => {
                self.boxes.push(([min[0], min[1]], [max[0], max[1]]));
            }
            _ => {}
        }
    }

    /// Distance from `o` along the unit direction `d` to the nearest surface, if any.
    pub fn cast(&self, o: [f64; 2], d: [f64; 2]) -> Option<f64> {
        let walls = self
            .walls
            .iter()
            .filter_map(|&(a, b)| segment_hit(o, d, a, b));
        let boxes = self
            .boxes
            .iter()
            .filter_map(|&(lo, hi)| box_hit(o, d, lo, hi));
        let circles = self
            .circles
            .iter()
            .filter_map(|&(c, r)| circle_hit(o, d, c, r));
        walls.chain(boxes).chain(circles).reduce(f64::min)
    }

    /// Distance from `p` to the nearest surface (wall, box or circle) in the plane; infinite
    /// in an empty room, 0 inside an object.
    pub fn clearance(&self, p: [f64; 2]) -> f64 {
        let walls = self.walls.iter().map(|&(a, b)| segment_distance(p, a, b));
        let boxes = self.boxes.iter().map(|&(lo, hi)| {
            let dx = (lo[0] - p[0]).max(p[0] - hi[0]).max(0.0);
            let dy = (lo[1] - p[1]).max(p[1] - hi[1]).max(0.0);
            dx.hypot(dy)
        });
        let circles = self
            .circles
            .iter()
            .map(|&(c, r)| ((p[0] - c[0]).hypot(p[1] - c[1]) - r).max(0.0));
        walls
            .chain(boxes)
            .chain(circles)
            .fold(f64::INFINITY, f64::min)
    }
}

fn segment_distance(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let e = [b[0] - a[0], b[1] - a[1]];
    let len2 = e[0] * e[0] + e[1] * e[1];
    let t = if len2 > 0.0 {
        (((p[0] - a[0]) * e[0] + (p[1] - a[1]) * e[1]) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (p[0] - a[0] - t * e[0]).hypot(p[1] - a[1] - t * e[1])
}

fn segment_hit(o: [f64; 2], d: [f64; 2], a: [f64; 2], b: [f64; 2]) -> Option<f64> {
    let e = [b[0] - a[0], b[1] - a[1]];
    let denom = d[0] * e[1] - d[1] * e[0];
    if denom.abs() < 1e-12 {
        return None;
    }
    let w = [a[0] - o[0], a[1] - o[1]];
    let t = (w[0] * e[1] - w[1] * e[0]) / denom;
    let s = (w[0] * d[1] - w[1] * d[0]) / denom;
    (t > 1e-9 && (0.0..=1.0).contains(&s)).then_some(t)
}

fn box_hit(o: [f64; 2], d: [f64; 2], lo: [f64; 2], hi: [f64; 2]) -> Option<f64> {
    let (mut near, mut far) = (0.0f64, f64::INFINITY);
    for k in 0..2 {
        if d[k].abs() < 1e-12 {
            if o[k] < lo[k] || o[k] > hi[k] {
                return None;
            }
            continue;
        }
        let (a, b) = ((lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]);
        near = near.max(a.min(b));
        far = far.min(a.max(b));
    }
    (near <= far && near > 1e-9).then_some(near)
}

fn circle_hit(o: [f64; 2], d: [f64; 2], c: [f64; 2], r: f64) -> Option<f64> {
    let oc = [o[0] - c[0], o[1] - c[1]];
    let b = oc[0] * d[0] + oc[1] * d[1];
    let disc = b * b - (oc[0] * oc[0] + oc[1] * oc[1] - r * r);
    let t = -b - disc.sqrt();
    (disc >= 0.0 && t > 1e-9).then_some(t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clearance_is_the_distance_to_the_nearest_surface() {
        let mut room = Room {
            walls: vec![([-1.0, -1.0], [1.0, -1.0]), ([1.0, -1.0], [1.0, 1.0])],
            ..Room::default()
        };
        assert!((room.clearance([0.0, 0.0]) - 1.0).abs() < 1e-12);
        assert!((room.clearance([0.7, 0.5]) - 0.3).abs() < 1e-12);
        // Past a wall's end: the distance to its end point.
        assert!((room.clearance([-2.0, -1.0]) - 1.0).abs() < 1e-12);
        room.boxes.push(([0.2, 0.2], [0.4, 0.4]));
        assert!((room.clearance([0.0, 0.3]) - 0.2).abs() < 1e-12);
        assert_eq!(room.clearance([0.3, 0.3]), 0.0);
        room.circles.push(([-0.5, 0.5], 0.1));
        assert!((room.clearance([-0.5, 0.7]) - 0.1).abs() < 1e-12);
        assert_eq!(Room::default().clearance([0.0, 0.0]), f64::INFINITY);
    }
}
