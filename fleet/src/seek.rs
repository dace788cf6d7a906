//! A policy that sees: it turns two joints so that a coloured object comes to the centre of a
//! camera's picture (image-based visual servoing), the reference for the loop camera → agent →
//! server → action → arm. Pure: an observation (with the camera's JPEG) in, an action chunk out.
//!
//! The picture-to-joint relation is not given: the policy measures it. It nudges each joint in
//! turn and watches where the object goes (the columns of the image Jacobian), then steps
//! toward the centre by damped least squares, correcting its Jacobian from every move it sees
//! (Broyden's update). So it needs no camera calibration or arm kinematics, and a wrong sign or
//! scale is learnt, not assumed.

use fleet_agent::schema::{ActionChunk, LayoutMsg, ObservationMsg, SCHEMA_VERSION};
use thiserror::Error;
use zune_core::bytestream::ZCursor;
use zune_core::colorspace::ColorSpace;
use zune_core::options::DecoderOptions;
use zune_jpeg::JpegDecoder;

/// Why a picture could not be looked at.
#[derive(Debug, Error, PartialEq)]
pub enum SeekError {
    /// The image is not a JPEG that decodes.
    #[error("camera image: {0}")]
    Jpeg(String),
}

/// Where the object is in the picture.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sighting {
    /// Centroid, −1 (left) to 1 (right).
    pub x: f32,
    /// Centroid, −1 (top) to 1 (bottom).
    pub y: f32,
    /// Pixels of the object's colour.
    pub pixels: usize,
}

/// The object's colour in `jpeg`: the centroid of the pixels within `tolerance` of `colour` on
/// every channel; `None` if fewer than `min_pixels` are.
pub fn locate(
    jpeg: &[u8],
    colour: [u8; 3],
    tolerance: u8,
    min_pixels: usize,
) -> Result<Option<Sighting>, SeekError> {
    let options = DecoderOptions::default().jpeg_set_out_colorspace(ColorSpace::RGB);
    let mut decoder = JpegDecoder::new_with_options(ZCursor::new(jpeg), options);
    let rgb = decoder
        .decode()
        .map_err(|e| SeekError::Jpeg(e.to_string()))?;
    let (w, h) = decoder
        .info()
        .map(|i| (usize::from(i.width), usize::from(i.height)))
        .ok_or_else(|| SeekError::Jpeg("no header".into()))?;
    if w == 0 || h == 0 || rgb.len() < w * h * 3 {
        return Err(SeekError::Jpeg(format!("{} bytes for {w}x{h}", rgb.len())));
    }
    let (mut n, mut sx, mut sy) = (0usize, 0f64, 0f64);
    for (i, px) in rgb.chunks_exact(3).take(w * h).enumerate() {
        if px
            .iter()
            .zip(colour)
            .all(|(&p, c)| p.abs_diff(c) <= tolerance)
        {
            n += 1;
            sx += (i % w) as f64;
            sy += (i / w) as f64;
        }
    }
    if n < min_pixels.max(1) {
        return Ok(None);
    }
    let norm = |s: f64, size: usize| (2.0 * (s / n as f64 + 0.5) / size as f64 - 1.0) as f32;
    Ok(Some(Sighting {
        x: norm(sx, w),
        y: norm(sy, h),
        pixels: n,
    }))
}

/// Where the measuring of the image Jacobian is.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
enum Probe {
    /// Nothing measured yet.
    #[default]
    Start,
    /// Joint `joint` sent a probe step from `origin` (joints, sighting); `settled`
    /// observations seen since it stopped, `previous` its position at the last one.
    Moving {
        joint: usize,
        origin: ([f32; 2], [f32; 2]),
        previous: f32,
        settled: u32,
        waited: u32,
    },
    /// Both columns measured.
    Done,
}

/// What the policy has learnt about one robot.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SeekState {
    /// d(x, y)/d(q0, q1), column-major: `[column q0, column q1]`, once measured.
    jacobian: Option<[[f32; 2]; 2]>,
    /// Column of q0 while the second probe runs.
    first_column: Option<[f32; 2]>,
    /// The previous joints and sighting (for Broyden's update).
    last: Option<([f32; 2], [f32; 2])>,
    /// The targets last sent. Every new target is this plus a step, never the measured
    /// position plus a step: a servo holding against gravity sits a little off its target,
    /// and re-commanding where it sits would let it sag a little more each time.
    command: Option<[f32; 2]>,
    probe: Probe,
}

impl SeekState {
    /// Whether the image Jacobian has been measured.
    pub fn calibrated(&self) -> bool {
        self.jacobian.is_some()
    }
}

/// The policy: which camera, which colour, which two joints.
#[derive(Debug, Clone, PartialEq)]
pub struct ColourSeek {
    /// Camera whose image is servoed (`observation.cameras` of the robot).
    pub camera: String,
    /// The object's colour, RGB.
    pub colour: [u8; 3],
    /// Per-channel tolerance.
    pub tolerance: u8,
    /// The two joints turned (the first moves the object mostly sideways, ideally).
    pub joints: [String; 2],
    /// Fraction of the error corrected per chunk.
    pub gain: f32,
    /// Largest joint step per chunk, rad.
    pub max_step_rad: f32,
    /// The probes' step, rad: small enough to keep the object in the picture.
    pub probe_rad: f32,
    /// Centred within this (normalised image units): hold.
    pub deadband: f32,
    /// Steps per chunk.
    pub steps: usize,
    /// Time between steps, ms.
    pub step_ms: u64,
}

/// Smallest joint move the Jacobian learns from, rad (below it the picture's change is noise).
const MIN_MOVE_RAD: f32 = 0.01;

/// Observations a probe waits, once its joint has arrived, before it reads the picture: the
/// picture lags the joints (capture, the camera's latency, every third observation).
const SETTLE: u32 = 3;

/// Observations a probe waits for its joint at most before it measures what it got.
const PROBE_PATIENCE: u32 = 30;

impl ColourSeek {
    /// The next joint targets from joints `q` and sighting `e` (the object's offset from the
    /// centre), updating what is learnt in `state`. Pure.
    pub fn step(&self, state: &mut SeekState, q: [f32; 2], e: [f32; 2]) -> [f32; 2] {
        let command = *state.command.get_or_insert(q);
        match state.probe {
            Probe::Start => {
                return self.probe(state, 0, command, q, e);
            }
            Probe::Moving {
                joint,
                origin,
                previous,
                settled,
                waited,
            } => {
                let moved = q[joint] - origin.0[joint];
                // Stopped, most of the way: the servo has done what it will.
                let stopped = moved.abs() >= 0.5 * self.probe_rad
                    && (q[joint] - previous).abs() < 0.1 * self.probe_rad;
                let settled = if stopped { settled + 1 } else { 0 };
                let waited = waited + 1;
                if !(settled >= SETTLE || waited >= PROBE_PATIENCE) {
                    state.probe = Probe::Moving {
                        joint,
                        origin,
                        previous: q[joint],
                        settled,
                        waited,
                    };
                    return command;
                }
                if moved.abs() < MIN_MOVE_RAD {
                    // The joint did not move (held, or at its limit): back, and again.
                    let back = origin.0;
                    state.command = Some(back);
                    return self.probe(state, joint, back, q, e);
                }
                let column = [(e[0] - origin.1[0]) / moved, (e[1] - origin.1[1]) / moved];
                if joint == 0 {
                    state.first_column = Some(column);
                    return self.probe(state, 1, command, q, e);
                }
                state.jacobian = state.first_column.map(|c0| [c0, column]);
                state.probe = Probe::Done;
                state.last = Some((q, e));
            }
            Probe::Done => {}
        }
        if let (Some(j), Some((q0, e0))) = (&mut state.jacobian, state.last) {
            let dq = [q[0] - q0[0], q[1] - q0[1]];
            let de = [e[0] - e0[0], e[1] - e0[1]];
            let norm2 = dq[0] * dq[0] + dq[1] * dq[1];
            if norm2 >= MIN_MOVE_RAD * MIN_MOVE_RAD {
                // Broyden: J += (de − J dq) dqᵀ / |dq|².
                let pred = [
                    j[0][0] * dq[0] + j[1][0] * dq[1],
                    j[0][1] * dq[0] + j[1][1] * dq[1],
                ];
                for r in 0..2 {
                    for (c, col) in j.iter_mut().enumerate() {
                        col[r] += (de[r] - pred[r]) * dq[c] / norm2;
                    }
                }
                state.last = Some((q, e));
            }
        } else {
            state.last = Some((q, e));
        }
        let Some(j) = state.jacobian else {
            return command;
        };
        if e[0].hypot(e[1]) <= self.deadband {
            return command;
        }
        // Damped least squares: dq = −gain · Jᵀ (J Jᵀ + λ²I)⁻¹ e.
        let (a, b, c, d) = (j[0][0], j[1][0], j[0][1], j[1][1]); // J = [[a, b], [c, d]]
        let lambda2 = 1e-3;
        let (m00, m01, m11) = (
            a * a + b * b + lambda2,
            a * c + b * d,
            c * c + d * d + lambda2,
        );
        let det = m00 * m11 - m01 * m01;
        if det.abs() < 1e-9 {
            return command;
        }
        let y = [
            (m11 * e[0] - m01 * e[1]) / det,
            (m00 * e[1] - m01 * e[0]) / det,
        ];
        let mut dq = [
            -self.gain * (a * y[0] + c * y[1]),
            -self.gain * (b * y[0] + d * y[1]),
        ];
        let n = dq[0].hypot(dq[1]);
        if n > self.max_step_rad {
            dq = [dq[0] * self.max_step_rad / n, dq[1] * self.max_step_rad / n];
        }
        let target = [command[0] + dq[0], command[1] + dq[1]];
        state.command = Some(target);
        target
    }

    /// Sends joint `joint` one probe step from the targets `command` (the joints at `q`, the
    /// object at `e`).
    fn probe(
        &self,
        state: &mut SeekState,
        joint: usize,
        command: [f32; 2],
        q: [f32; 2],
        e: [f32; 2],
    ) -> [f32; 2] {
        let mut target = command;
        target[joint] += self.probe_rad;
        state.command = Some(target);
        state.probe = Probe::Moving {
            joint,
            origin: (q, e),
            previous: q[joint],
            settled: 0,
            waited: 0,
        };
        target
    }

    /// The chunk answering `obs` (numbered `seq`): `None` when the observation carries no image
    /// of the camera, the object is not in it, or the layout lacks a joint (the robot holds).
    pub fn chunk(
        &self,
        obs: &ObservationMsg,
        layout: &LayoutMsg,
        state: &mut SeekState,
        seq: u64,
    ) -> Result<Option<ActionChunk>, SeekError> {
        let n = layout.joints.len();
        let index = |name: &str| layout.joints.iter().position(|j| j.name == name);
        let (Some(i0), Some(i1)) = (index(&self.joints[0]), index(&self.joints[1])) else {
            return Ok(None);
        };
        if n > 32 || obs.position.len() != n {
            return Ok(None);
        }
        let Some(image) = obs.images.iter().find(|i| i.camera == self.camera) else {
            return Ok(None);
        };
        let Some(seen) = locate(&image.data, self.colour, self.tolerance, 20)? else {
            return Ok(None);
        };
        let q = [obs.position[i0], obs.position[i1]];
        if !q.iter().all(|v| v.is_finite()) {
            return Ok(None);
        }
        // Each chunk goes from the targets last sent to the new ones (see `SeekState::command`).
        let from = state.command.unwrap_or(q);
        let target = self.step(state, q, [seen.x, seen.y]);
        let target = [
            target[0].clamp(layout.joints[i0].min, layout.joints[i0].max),
            target[1].clamp(layout.joints[i1].min, layout.joints[i1].max),
        ];
        state.command = Some(target);
        let offsets: Vec<u64> = (1..=self.steps as u64)
            .map(|k| k * self.step_ms * 1_000_000)
            .collect();
        let mut targets = vec![0.0; offsets.len() * n];
        for (k, row) in targets.chunks_exact_mut(n).enumerate() {
            // From where the joints are to the target, evenly over the chunk.
            let w = (k + 1) as f32 / self.steps as f32;
            row[i0] = from[0] + (target[0] - from[0]) * w;
            row[i1] = from[1] + (target[1] - from[1]) * w;
        }
        Ok(Some(ActionChunk {
            version: SCHEMA_VERSION,
            seq,
            observation_ns: obs.timestamp_ns,
            step_offsets_ns: offsets,
            joint_count: n as u16,
            joint_mask: (1 << i0) | (1 << i1),
            targets,
            lift_m: Vec::new(),
            base_twist: Vec::new(),
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn seek() -> ColourSeek {
        ColourSeek {
            camera: "left_wrist".into(),
            colour: [210, 30, 30],
            tolerance: 60,
            joints: ["a".into(), "b".into()],
            gain: 0.5,
            max_step_rad: 0.08,
            probe_rad: 0.08,
            deadband: 0.03,
            steps: 5,
            step_ms: 20,
        }
    }

    /// A camera whose picture moves by `a` with the joints: e = A (q − q*).
    fn converges(a: [[f32; 2]; 2]) -> (usize, f32) {
        let p = seek();
        let goal = [0.3f32, -0.2];
        let mut q = [0.0f32, 0.0];
        let mut state = SeekState::default();
        let sight = |q: [f32; 2]| {
            let d = [q[0] - goal[0], q[1] - goal[1]];
            [
                a[0][0] * d[0] + a[1][0] * d[1],
                a[0][1] * d[0] + a[1][1] * d[1],
            ]
        };
        for it in 0..120 {
            let e = sight(q);
            if e[0].hypot(e[1]) <= p.deadband && state.calibrated() {
                return (it, e[0].hypot(e[1]));
            }
            q = p.step(&mut state, q, e);
        }
        let e = sight(q);
        (120, e[0].hypot(e[1]))
    }

    #[test]
    fn it_centres_the_object_whatever_the_cameras_signs_and_scale() {
        for a in [
            [[1.5, 0.0], [0.0, 1.5]],
            [[-1.5, 0.0], [0.0, 1.5]],
            [[0.0, 2.0], [-2.0, 0.0]], // the camera turned a quarter
            [[0.8, 0.6], [0.5, -1.2]], // coupled, one sign flipped
        ] {
            let (iterations, err) = converges(a);
            assert!(
                iterations < 40 && err <= 0.03,
                "{a:?}: {err} after {iterations}"
            );
        }
    }

    #[test]
    fn the_jacobian_is_measured_before_any_step_toward_the_object() {
        let p = seek();
        let mut s = SeekState::default();
        let t = p.step(&mut s, [0.0, 0.0], [0.5, 0.5]);
        assert_eq!(
            t,
            [0.08, 0.0],
            "the first probe moves the first joint alone"
        );
        // On its way: the probe's target is held, nothing is measured from a moving arm.
        assert_eq!(p.step(&mut s, [0.04, 0.0], [0.55, 0.5]), [0.08, 0.0]);
        // Stopped: SETTLE observations for the picture to catch up, then the second probe.
        for _ in 0..SETTLE {
            assert_eq!(p.step(&mut s, [0.08, 0.0], [0.6, 0.5]), [0.08, 0.0]);
        }
        let t = p.step(&mut s, [0.08, 0.0], [0.6, 0.5]);
        assert_eq!(t, [0.08, 0.08], "then the second joint");
        assert!(!s.calibrated());
        for _ in 0..=SETTLE {
            p.step(&mut s, [0.08, 0.08], [0.6, 0.3]);
        }
        assert!(s.calibrated());
        let j = s.jacobian.unwrap();
        let want = [[1.25, 0.0], [0.0, -2.5]];
        for c in 0..2 {
            for r in 0..2 {
                assert!((j[c][r] - want[c][r]).abs() < 1e-4, "{j:?}");
            }
        }
    }

    #[test]
    fn a_probe_whose_joint_does_not_move_is_sent_again_not_measured() {
        let p = seek();
        let mut s = SeekState::default();
        p.step(&mut s, [0.0, 0.0], [0.5, 0.5]);
        for _ in 0..PROBE_PATIENCE {
            p.step(&mut s, [0.0, 0.0], [0.5, 0.5]);
        }
        assert!(!s.calibrated() && s.first_column.is_none(), "{s:?}");
    }

    fn disc_jpeg(cx: f32, cy: f32) -> Vec<u8> {
        let (w, h) = (160usize, 120usize);
        let mut rgb = vec![90u8; w * h * 3];
        for y in 0..h {
            for x in 0..w {
                if (x as f32 - cx).hypot(y as f32 - cy) < 10.0 {
                    rgb[(y * w + x) * 3..][..3].copy_from_slice(&[210, 30, 30]);
                }
            }
        }
        let mut out = Vec::new();
        jpeg_encoder::Encoder::new(&mut out, 85)
            .encode(&rgb, w as u16, h as u16, jpeg_encoder::ColorType::Rgb)
            .unwrap();
        out
    }

    #[test]
    fn the_object_is_found_where_it_is_drawn() {
        let s = locate(&disc_jpeg(120.0, 30.0), [210, 30, 30], 60, 20)
            .unwrap()
            .unwrap();
        assert!(
            (s.x - 0.5).abs() < 0.02 && (s.y + 0.5).abs() < 0.03,
            "{s:?}"
        );
        assert!((250..380).contains(&s.pixels), "{s:?}");
        let none = locate(&disc_jpeg(-100.0, -100.0), [210, 30, 30], 60, 20).unwrap();
        assert_eq!(none, None, "out of the picture");
        assert!(matches!(
            locate(b"not a jpeg", [210, 30, 30], 60, 20),
            Err(SeekError::Jpeg(_))
        ));
    }
}
