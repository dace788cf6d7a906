//! The simulated cameras' pictures: the scene (floor, table, objects, the arms' links and
//! fingers) ray-cast from a pinhole camera, Lambert-shaded. Enough for a policy to see where the
//! arm and a coloured object are; not a photograph.
//!
//! Each shape's bounding sphere is projected once per frame, so a pixel tests only the shapes
//! whose screen rectangle covers it: the cost is the floor's (every pixel) plus each shape's
//! own area.

use nalgebra::{Matrix3, Vector3};

/// A solid in the scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    /// A ball.
    Sphere {
        /// Centre, m.
        center: [f64; 3],
        /// Radius, m.
        radius: f64,
    },
    /// A rod with round ends (an arm link, a finger).
    Capsule {
        /// One end's centre.
        a: [f64; 3],
        /// The other end's centre.
        b: [f64; 3],
        /// Radius, m.
        radius: f64,
    },
    /// An axis-aligned box (a table top, a block).
    Cuboid {
        /// Lowest corner.
        min: [f64; 3],
        /// Highest corner.
        max: [f64; 3],
    },
}

/// A shape and its colour.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Item {
    /// The solid.
    pub shape: Shape,
    /// sRGB colour.
    pub colour: [u8; 3],
}

/// A pinhole camera (OpenCV convention: x right, y down, z forward in its own frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    /// Optical centre, world frame, m.
    pub eye: Vector3<f64>,
    /// Camera frame → world frame.
    pub rotation: Matrix3<f64>,
    /// Horizontal field of view, rad.
    pub fov_rad: f64,
    /// Image width, px.
    pub width: u32,
    /// Image height, px.
    pub height: u32,
}

impl View {
    /// A camera at `eye` looking at `target`, the world's +z up in the picture.
    pub fn looking_at(
        eye: [f64; 3],
        target: [f64; 3],
        fov_rad: f64,
        width: u32,
        height: u32,
    ) -> Self {
        let eye = Vector3::from(eye);
        let forward = (Vector3::from(target) - eye).normalize();
        let up = Vector3::z();
        let right = forward.cross(&up);
        // Looking straight up or down: any right angle will do.
        let right = if right.norm() < 1e-9 {
            Vector3::y()
        } else {
            right.normalize()
        };
        let down = forward.cross(&right);
        View {
            eye,
            rotation: Matrix3::from_columns(&[right, down, forward]),
            fov_rad,
            width,
            height,
        }
    }

    fn focal(&self) -> f64 {
        f64::from(self.width) / 2.0 / (self.fov_rad / 2.0).tan()
    }

    /// The pixel rectangle (x0, y0, x1, y1), inclusive, a sphere covers; the whole image when
    /// it reaches behind the camera.
    fn bounds(&self, center: Vector3<f64>, radius: f64) -> Option<(u32, u32, u32, u32)> {
        let (w, h) = (self.width, self.height);
        let c = self.rotation.transpose() * (center - self.eye);
        if c.z <= radius {
            if c.z < -radius {
                return None;
            }
            return Some((0, 0, w - 1, h - 1));
        }
        let f = self.focal();
        // The sphere's silhouette fits in the circle of radius f·r/√(z² − r²) about its centre.
        let spread = f * radius / (c.z * c.z - radius * radius).sqrt() + 1.0;
        let (u, v) = (
            f * c.x / c.z + f64::from(w) / 2.0,
            f * c.y / c.z + f64::from(h) / 2.0,
        );
        let (x0, x1) = (u - spread, u + spread);
        let (y0, y1) = (v - spread, v + spread);
        if x1 < 0.0 || y1 < 0.0 || x0 >= f64::from(w) || y0 >= f64::from(h) {
            return None;
        }
        let clamp = |x: f64, hi: u32| x.clamp(0.0, f64::from(hi - 1)) as u32;
        Some((clamp(x0, w), clamp(y0, h), clamp(x1, w), clamp(y1, h)))
    }
}

/// Where a ray first meets a shape: distance along the unit direction, and the surface normal.
fn hit(shape: &Shape, o: &Vector3<f64>, d: &Vector3<f64>) -> Option<(f64, Vector3<f64>)> {
    match *shape {
        Shape::Sphere { center, radius } => {
            let c = Vector3::from(center);
            let t = sphere_hit(&c, radius, o, d)?;
            Some((t, (o + d * t - c) / radius))
        }
        Shape::Capsule { a, b, radius } => {
            capsule_hit(&Vector3::from(a), &Vector3::from(b), radius, o, d)
        }
        Shape::Cuboid { min, max } => {
            let (mut t0, mut t1, mut axis) = (0.0f64, f64::INFINITY, 0);
            for k in 0..3 {
                let inv = 1.0 / d[k];
                let (mut near, mut far) = ((min[k] - o[k]) * inv, (max[k] - o[k]) * inv);
                if near > far {
                    std::mem::swap(&mut near, &mut far);
                }
                if near > t0 {
                    (t0, axis) = (near, k);
                }
                t1 = t1.min(far);
                if t0 > t1 {
                    return None;
                }
            }
            let mut n = Vector3::zeros();
            n[axis] = -d[axis].signum();
            (t0 > 1e-9).then_some((t0, n))
        }
    }
}

fn sphere_hit(c: &Vector3<f64>, r: f64, o: &Vector3<f64>, d: &Vector3<f64>) -> Option<f64> {
    let oc = o - c;
    let b = oc.dot(d);
    let disc = b * b - (oc.norm_squared() - r * r);
    if disc < 0.0 {
        return None;
    }
    let t = -b - disc.sqrt();
    (t > 1e-9).then_some(t)
}

fn capsule_hit(
    a: &Vector3<f64>,
    b: &Vector3<f64>,
    r: f64,
    o: &Vector3<f64>,
    d: &Vector3<f64>,
) -> Option<(f64, Vector3<f64>)> {
    // The cylinder's side, then the two end caps; the nearest hit wins.
    let ba = b - a;
    let len2 = ba.norm_squared();
    let mut best: Option<(f64, Vector3<f64>)> = None;
    if len2 > 1e-12 {
        let oa = o - a;
        let (bd, bo) = (ba.dot(d), ba.dot(&oa));
        let qa = len2 - bd * bd;
        let qb = len2 * oa.dot(d) - bo * bd;
        let qc = len2 * oa.norm_squared() - bo * bo - r * r * len2;
        let disc = qb * qb - qa * qc;
        if qa.abs() > 1e-12 && disc >= 0.0 {
            let t = (-qb - disc.sqrt()) / qa;
            let s = bo + t * bd;
            if t > 1e-9 && s > 0.0 && s < len2 {
                let p = o + d * t;
                let axis_point = a + ba * (s / len2);
                best = Some((t, (p - axis_point) / r));
            }
        }
    }
    for end in [a, b] {
        if let Some(t) = sphere_hit(end, r, o, d) {
            if best.is_none_or(|(bt, _)| t < bt) {
                best = Some((t, (o + d * t - end) / r));
            }
        }
    }
    best
}

/// Light from above, a little from the front and left.
fn light() -> Vector3<f64> {
    Vector3::new(-0.3, 0.4, 1.0).normalize()
}

fn shade(colour: [u8; 3], normal: &Vector3<f64>) -> [u8; 3] {
    let k = 0.35 + 0.65 * normal.dot(&light()).max(0.0);
    colour.map(|c| (f64::from(c) * k).min(255.0) as u8)
}

/// Renders `items` above a checkered floor at z = 0 into `out` (RGB24, `width × height × 3`).
pub fn render(items: &[Item], view: &View, out: &mut [u8]) {
    let (w, h) = (view.width as usize, view.height as usize);
    let f = view.focal();
    let bounds: Vec<Option<(u32, u32, u32, u32)>> = items
        .iter()
        .map(|item| {
            let (c, r) = bounding_sphere(&item.shape);
            view.bounds(c, r)
        })
        .collect();
    for (y, row) in out.chunks_exact_mut(w * 3).take(h).enumerate() {
        for (x, px) in row.chunks_exact_mut(3).enumerate() {
            let cam = Vector3::new(
                (x as f64 + 0.5 - w as f64 / 2.0) / f,
                (y as f64 + 0.5 - h as f64 / 2.0) / f,
                1.0,
            );
            let d = (view.rotation * cam).normalize();
            let mut nearest = f64::INFINITY;
            let mut colour = background(&d);
            if d.z < -1e-9 {
                let t = -view.eye.z / d.z;
                let p = view.eye + d * t;
                // 25 cm tiles.
                let tile = ((p.x / 0.25).floor() + (p.y / 0.25).floor()) as i64;
                colour = if tile.rem_euclid(2) == 0 {
                    [150, 140, 125]
                } else {
                    [110, 100, 90]
                };
                nearest = t;
            }
            for (item, b) in items.iter().zip(&bounds) {
                let Some((x0, y0, x1, y1)) = *b else { continue };
                let (xu, yu) = (x as u32, y as u32);
                if xu < x0 || xu > x1 || yu < y0 || yu > y1 {
                    continue;
                }
                if let Some((t, n)) = hit(&item.shape, &view.eye, &d) {
                    if t < nearest {
                        nearest = t;
                        colour = shade(item.colour, &n);
                    }
                }
            }
            px.copy_from_slice(&colour);
        }
    }
}

fn background(d: &Vector3<f64>) -> [u8; 3] {
    // A pale wall, darker towards the floor.
    let k = 0.75 + 0.25 * d.z.clamp(-1.0, 1.0);
    [(200.0 * k) as u8, (205.0 * k) as u8, (215.0 * k) as u8]
}

fn bounding_sphere(s: &Shape) -> (Vector3<f64>, f64) {
    match *s {
        Shape::Sphere { center, radius } => (Vector3::from(center), radius),
        Shape::Capsule { a, b, radius } => {
            let (a, b) = (Vector3::from(a), Vector3::from(b));
            ((a + b) / 2.0, (b - a).norm() / 2.0 + radius)
        }
        Shape::Cuboid { min, max } => {
            let (lo, hi) = (Vector3::from(min), Vector3::from(max));
            ((lo + hi) / 2.0, (hi - lo).norm() / 2.0)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const RED: [u8; 3] = [220, 30, 30];

    fn picture(items: &[Item], view: &View) -> Vec<u8> {
        let mut out = vec![0u8; view.width as usize * view.height as usize * 3];
        render(items, view, &mut out);
        out
    }

    fn red_pixels(img: &[u8]) -> Vec<usize> {
        img.chunks_exact(3)
            .enumerate()
            .filter(|(_, p)| u16::from(p[0]) > 2 * u16::from(p[1]).max(20) && p[0] > 60)
            .map(|(i, _)| i)
            .collect()
    }

    #[test]
    fn a_ball_ahead_is_in_the_middle_and_one_to_the_left_is_on_the_left() {
        let view = View::looking_at([0.0, 0.0, 1.0], [1.0, 0.0, 1.0], 1.2, 64, 48);
        let ball = |y: f64| Item {
            shape: Shape::Sphere {
                center: [1.0, y, 1.0],
                radius: 0.1,
            },
            colour: RED,
        };
        let centre = red_pixels(&picture(&[ball(0.0)], &view));
        assert!(!centre.is_empty());
        let mean_x =
            |px: &[usize]| px.iter().map(|i| (i % 64) as f64).sum::<f64>() / px.len() as f64;
        let mean_y =
            |px: &[usize]| px.iter().map(|i| (i / 64) as f64).sum::<f64>() / px.len() as f64;
        assert!((mean_x(&centre) - 31.5).abs() < 1.0, "{}", mean_x(&centre));
        assert!((mean_y(&centre) - 23.5).abs() < 1.0, "{}", mean_y(&centre));
        // +y is to the camera's left when it looks along +x with z up.
        let left = red_pixels(&picture(&[ball(0.3)], &view));
        assert!(mean_x(&left) < 20.0, "{}", mean_x(&left));
        // Behind the camera: not drawn.
        let behind = Item {
            shape: Shape::Sphere {
                center: [-1.0, 0.0, 1.0],
                radius: 0.1,
            },
            colour: RED,
        };
        assert!(red_pixels(&picture(&[behind], &view)).is_empty());
    }

    #[test]
    fn the_nearer_shape_hides_the_farther_and_the_floor_is_below() {
        let view = View::looking_at([0.0, 0.0, 1.0], [1.0, 0.0, 1.0], 1.2, 32, 24);
        let blue = Item {
            shape: Shape::Cuboid {
                min: [0.8, -0.2, 0.8],
                max: [0.9, 0.2, 1.2],
            },
            colour: [30, 30, 220],
        };
        let red_far = Item {
            shape: Shape::Capsule {
                a: [2.0, -0.1, 1.0],
                b: [2.0, 0.1, 1.0],
                radius: 0.05,
            },
            colour: RED,
        };
        let img = picture(&[red_far, blue], &view);
        assert!(
            red_pixels(&img).is_empty(),
            "the red rod is behind the blue box"
        );
        let middle = &img[(12 * 32 + 16) * 3..(12 * 32 + 16) * 3 + 3];
        assert!(middle[2] > 2 * middle[0], "{middle:?}");
        let without_box = picture(&[red_far], &view);
        assert!(!red_pixels(&without_box).is_empty());
        // The bottom row looks down at the floor, the top row at the wall: they differ.
        assert_ne!(&without_box[..3], &without_box[without_box.len() - 3..]);
    }

    #[test]
    fn rays_meet_shapes_where_geometry_says() {
        let o = Vector3::new(0.0, 0.0, 0.0);
        let d = Vector3::x();
        let rod = Shape::Capsule {
            a: [2.0, -1.0, 0.0],
            b: [2.0, 1.0, 0.0],
            radius: 0.5,
        };
        let (t, n) = hit(&rod, &o, &d).unwrap();
        assert!((t - 1.5).abs() < 1e-9 && (n - Vector3::new(-1.0, 0.0, 0.0)).norm() < 1e-9);
        // Past the rod's end: only the round cap is hit.
        let cap_ray = Vector3::new(0.0, 1.2, 0.0);
        let (t, _) = hit(&rod, &cap_ray, &d).unwrap();
        assert!((t - (2.0 - (0.25f64 - 0.04).sqrt())).abs() < 1e-9, "{t}");
        let cube = Shape::Cuboid {
            min: [1.0, -1.0, -1.0],
            max: [3.0, 1.0, 1.0],
        };
        let (t, n) = hit(&cube, &o, &d).unwrap();
        assert!((t - 1.0).abs() < 1e-9 && n == Vector3::new(-1.0, 0.0, 0.0));
        assert!(hit(&cube, &o, &-d).is_none());
    }
}
