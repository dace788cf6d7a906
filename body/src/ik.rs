//! Inverse kinematics of one arm: joint angles that put its tool at a target pose in the room,
//! within the joints' ranges, for Cartesian teleoperation (Nori Lab) and anything else that
//! thinks in poses.
//!
//! Damped least squares (Levenberg–Marquardt: the damping shrinks while a step lowers the
//! error and grows when it does not), the orientation error weighted as a length (0.1 m a
//! radian) against the position's. The A3's arm has seven joints for a six-dimensional pose: once
//! the pose is reached, the one redundant direction (the elbow swinging about the shoulder–wrist
//! line) is spent moving the joints toward their ranges' middles along the Jacobian's null
//! space, each move corrected back onto the target and kept only if the pose stays reached (a
//! pull mixed into the descent itself cost success: the damped projection is not exactly in the
//! null space). Each step is clamped into the ranges, so no iterate, and no answer, is outside
//! them. A solve that stalls restarts
//! from another start drawn from the ranges (a fixed sequence: the same target gives the same
//! answer). Pure and allocation-free: chains of up to [`MAX_JOINTS`] joints in fixed-size
//! matrices.

use crate::kinematics::{ArmChain, Body, Pose2};
use nalgebra::{Matrix3, Rotation3, SMatrix, SVector, UnitQuaternion, Vector3, Vector6};
use thiserror::Error;

/// The longest chain solved.
pub const MAX_JOINTS: usize = 8;

type Jacobian = SMatrix<f64, 6, MAX_JOINTS>;
type Angles = SVector<f64, MAX_JOINTS>;

/// A tool pose in the room: position, m, and orientation, a unit quaternion `[w, x, y, z]`
/// (the frame [`Body::arm_pose`] reports).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolTarget {
    /// m.
    pub position: [f64; 3],
    /// `[w, x, y, z]`; normalised before use.
    pub rotation: [f64; 4],
}

/// Where the lift and the base carry the arm: the lift's height, m, and the base's pose.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Mount {
    /// m.
    pub lift_m: f64,
    /// On the floor.
    pub base: Pose2,
}

/// How hard to try.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IkSettings {
    /// Reached when the tool is this close, m.
    pub position_tol_m: f64,
    /// ... and turned this little from the target, rad.
    pub angle_tol_rad: f64,
    /// Steps per start.
    pub max_steps: usize,
    /// Starts: the seed, then ones drawn from the ranges.
    pub max_starts: usize,
    /// Largest change of any joint in one step, rad.
    pub max_step_rad: f64,
    /// Gain of the moves toward the ranges' middles once the pose is reached (0: none; the
    /// plain damped least squares).
    pub centring: f64,
}

impl Default for IkSettings {
    fn default() -> Self {
        IkSettings {
            position_tol_m: 1e-4,
            angle_tol_rad: 1e-3,
            max_steps: 60,
            max_starts: 32,
            max_step_rad: 0.4,
            centring: 0.5,
        }
    }
}

/// An answer: the angles (base outward) and how close they put the tool.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IkSolution {
    /// rad, the chain's joints first; the rest 0.
    pub q: [f64; MAX_JOINTS],
    /// Joints in the chain.
    pub joints: usize,
    /// m.
    pub position_error_m: f64,
    /// rad.
    pub angle_error_rad: f64,
    /// Steps taken, over every start.
    pub steps: usize,
    /// Starts used (1: from the seed).
    pub starts: usize,
}

/// Why there is no answer.
#[derive(Debug, Error, PartialEq)]
pub enum IkError {
    /// The body has no such arm.
    #[error("no arm {0}")]
    NoArm(usize),
    /// The chain is longer than the solver takes.
    #[error("arm of {0} joints: at most {MAX_JOINTS} are solved")]
    TooManyJoints(usize),
    /// A target, seed or range that is not a finite number, or a range whose ends are swapped.
    #[error("target, seed or range not finite or empty: {0}")]
    BadInput(&'static str),
    /// No start came within the tolerances: the closest found (within the ranges).
    #[error(
        "target not reached: closest {position_error_m:.4} m and {angle_error_rad:.4} rad away"
    )]
    NotReached {
        /// The closest angles found.
        best: [f64; MAX_JOINTS],
        /// m.
        position_error_m: f64,
        /// rad.
        angle_error_rad: f64,
    },
}

/// Moves toward the ranges' middles after the pose is reached, at most.
const CENTRING_MOVES: usize = 8;

/// Metres a radian of orientation error counts as.
const ANGLE_LENGTH_M: f64 = 0.1;

/// The tool's pose and each joint's position and axis in the room, for angles `q`.
struct Frames {
    joint_at: [Vector3<f64>; MAX_JOINTS],
    axis: [Vector3<f64>; MAX_JOINTS],
    tool: Vector3<f64>,
    rotation: Matrix3<f64>,
}

fn frames(chain: &ArmChain, shoulder: Vector3<f64>, heading: &Matrix3<f64>, q: &Angles) -> Frames {
    let mut f = Frames {
        joint_at: [Vector3::zeros(); MAX_JOINTS],
        axis: [Vector3::zeros(); MAX_JOINTS],
        tool: Vector3::zeros(),
        rotation: *heading,
    };
    let mut p = shoulder;
    for (k, (axis, origin)) in chain.axes_and_origins().enumerate() {
        p += f.rotation * origin;
        f.joint_at[k] = p;
        f.axis[k] = f.rotation * axis.into_inner();
        f.rotation *= *Rotation3::from_axis_angle(&axis, q[k]).matrix();
    }
    f.tool = p + f.rotation * chain.tip();
    f
}

/// The error from `f` to the target (position, then orientation as a rotation vector scaled
/// by [`ANGLE_LENGTH_M`]) and its two sizes.
fn error(f: &Frames, target: &Vector3<f64>, target_rot: &Matrix3<f64>) -> (Vector6<f64>, f64, f64) {
    let dp = target - f.tool;
    let turn = Rotation3::from_matrix_unchecked(target_rot * f.rotation.transpose());
    let w = turn.scaled_axis();
    let e = Vector6::new(
        dp.x,
        dp.y,
        dp.z,
        ANGLE_LENGTH_M * w.x,
        ANGLE_LENGTH_M * w.y,
        ANGLE_LENGTH_M * w.z,
    );
    (e, dp.norm(), w.norm())
}

/// Coordinate `k` of the `i`-th point of a Kronecker sequence in [0, 1): each joint steps by
/// its own irrational (the fractional part of a prime's square root), so the restarts cover
/// the ranges evenly, and the same way every time. Not random.
fn spread(i: usize, k: usize) -> f64 {
    const STEPS: [f64; MAX_JOINTS] = [
        0.414_213_562, // √2
        0.732_050_808, // √3
        0.236_067_977, // √5
        0.645_751_311, // √7
        0.316_624_790, // √11
        0.605_551_275, // √13
        0.123_105_626, // √17
        0.358_898_944, // √19
    ];
    (0.5 + i as f64 * STEPS[k % MAX_JOINTS]).fract()
}

/// One solve's fixed parts: the chain where the mount puts it, the target, the ranges.
struct Problem<'a> {
    chain: &'a ArmChain,
    shoulder: Vector3<f64>,
    heading: Matrix3<f64>,
    target: Vector3<f64>,
    target_rot: Matrix3<f64>,
    lo: Angles,
    hi: Angles,
    n: usize,
    settings: &'a IkSettings,
}

impl Problem<'_> {
    fn frames(&self, q: &Angles) -> Frames {
        frames(self.chain, self.shoulder, &self.heading, q)
    }

    fn error(&self, f: &Frames) -> (Vector6<f64>, f64, f64) {
        error(f, &self.target, &self.target_rot)
    }

    fn reached(&self, dp: f64, da: f64) -> bool {
        dp <= self.settings.position_tol_m && da <= self.settings.angle_tol_rad
    }

    fn clamp(&self, q: &mut Angles) {
        for k in 0..self.n {
            q[k] = q[k].clamp(self.lo[k], self.hi[k]);
        }
    }

    fn jacobian(&self, f: &Frames) -> Jacobian {
        let mut j = Jacobian::zeros();
        for k in 0..self.n {
            let a = f.axis[k];
            let v = a.cross(&(f.tool - f.joint_at[k]));
            j.fixed_view_mut::<6, 1>(0, k).copy_from(&Vector6::new(
                v.x,
                v.y,
                v.z,
                ANGLE_LENGTH_M * a.x,
                ANGLE_LENGTH_M * a.y,
                ANGLE_LENGTH_M * a.z,
            ));
        }
        j
    }

    /// The damped pseudo-inverse of `j`.
    fn pinv(j: &Jacobian, lambda: f64) -> Option<SMatrix<f64, MAX_JOINTS, 6>> {
        let inv = (j * j.transpose() + nalgebra::Matrix6::identity() * (lambda * lambda))
            .try_inverse()?;
        Some(j.transpose() * inv)
    }

    /// How far `q` is from the ranges' middles: the sum of squares of each joint's offset as a
    /// fraction of its half-range (0 in the middle, 1 at an end).
    fn off_centre(&self, q: &Angles) -> f64 {
        (0..self.n)
            .map(|k| {
                let half = ((self.hi[k] - self.lo[k]) / 2.0).max(1e-6);
                ((q[k] - (self.lo[k] + self.hi[k]) / 2.0) / half).powi(2)
            })
            .sum()
    }

    /// Damped least squares from `q`: the closest angles found, their errors, and the steps
    /// taken. Stops when the pose is reached or a step no longer lowers the error.
    fn descend(&self, mut q: Angles, steps: &mut usize) -> (Angles, f64, f64) {
        let mut f = self.frames(&q);
        let (mut e, mut dp, mut da) = self.error(&f);
        let mut lambda = 0.01;
        for _ in 0..self.settings.max_steps {
            if self.reached(dp, da) {
                break;
            }
            *steps += 1;
            let j = self.jacobian(&f);
            let cost = e.norm_squared();
            // A step that does not lower the error is taken back and the damping raised.
            let mut improved = false;
            for _ in 0..6 {
                let Some(pinv) = Self::pinv(&j, lambda) else {
                    lambda *= 10.0;
                    continue;
                };
                let mut dq = pinv * e;
                let largest = dq.amax();
                if largest > self.settings.max_step_rad {
                    dq *= self.settings.max_step_rad / largest;
                }
                let mut next = q + dq;
                self.clamp(&mut next);
                let nf = self.frames(&next);
                let (ne, ndp, nda) = self.error(&nf);
                if ne.norm_squared() < cost {
                    (q, f, e, dp, da) = (next, nf, ne, ndp, nda);
                    lambda = (lambda / 3.0).max(1e-4);
                    improved = true;
                    break;
                }
                lambda *= 4.0;
            }
            if !improved {
                break;
            }
        }
        (q, dp, da)
    }

    /// The pose reached at `q`: spends the redundancy moving the joints toward their ranges'
    /// middles along the Jacobian's null space, each move corrected back onto the target and
    /// kept only if the pose stays reached and the joints come nearer their middles.
    fn centre(
        &self,
        mut q: Angles,
        mut dp: f64,
        mut da: f64,
        steps: &mut usize,
    ) -> (Angles, f64, f64) {
        let mut gain = self.settings.centring;
        let mut now = self.off_centre(&q);
        for _ in 0..CENTRING_MOVES {
            if gain < 0.05 * self.settings.centring {
                break;
            }
            *steps += 1;
            let f = self.frames(&q);
            let j = self.jacobian(&f);
            let Some(pinv) = Self::pinv(&j, 1e-4) else {
                break;
            };
            let mut pull = Angles::zeros();
            for k in 0..self.n {
                let half = ((self.hi[k] - self.lo[k]) / 2.0).max(1e-6);
                pull[k] = ((self.lo[k] + self.hi[k]) / 2.0 - q[k]) / half;
            }
            let mut dq =
                (SMatrix::<f64, MAX_JOINTS, MAX_JOINTS>::identity() - pinv * j) * pull * gain;
            let largest = dq.amax();
            if largest > self.settings.max_step_rad {
                dq *= self.settings.max_step_rad / largest;
            }
            let mut next = q + dq;
            self.clamp(&mut next);
            // Back onto the target (the null space is only tangent to it).
            let (next, ndp, nda) = self.descend(next, steps);
            let then = self.off_centre(&next);
            if self.reached(ndp, nda) && then < now {
                let gained = now - then;
                (q, dp, da, now) = (next, ndp, nda, then);
                if gained < 0.01 * now {
                    break;
                }
            } else {
                gain /= 2.0;
            }
        }
        (q, dp, da)
    }
}

impl Body {
    /// Angles of arm `arm` that put its tool at `target`, carried as `mount` says, starting
    /// from `seed` (the arm's angles now, for teleoperation), each joint within `limits`
    /// (`(lower, upper)` rad, base outward: the calibrated ranges the driver clamps to;
    /// [`ArmChain::hard_stops`] without a calibration).
    pub fn solve(
        &self,
        arm: usize,
        target: &ToolTarget,
        seed: &[f64],
        limits: &[(f64, f64)],
        mount: Mount,
        settings: &IkSettings,
    ) -> Result<IkSolution, IkError> {
        let Mount { lift_m, base } = mount;
        let chain = self.arms().get(arm).ok_or(IkError::NoArm(arm))?;
        let n = chain.joint_names.len();
        if n > MAX_JOINTS {
            return Err(IkError::TooManyJoints(n));
        }
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        if !finite(&target.position)
            || !finite(&target.rotation)
            || !finite(&[lift_m, base.x, base.y, base.theta])
        {
            return Err(IkError::BadInput("target"));
        }
        if seed.len() < n || !finite(&seed[..n]) {
            return Err(IkError::BadInput("seed"));
        }
        if limits.len() < n
            || limits[..n]
                .iter()
                .any(|(lo, hi)| !(lo.is_finite() && hi.is_finite() && lo <= hi))
        {
            return Err(IkError::BadInput("limits"));
        }
        let rotation = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            target.rotation[0],
            target.rotation[1],
            target.rotation[2],
            target.rotation[3],
        ));
        if !rotation.w.is_finite() {
            return Err(IkError::BadInput("target"));
        }
        let heading = *Rotation3::from_axis_angle(&Vector3::z_axis(), base.theta).matrix();
        let mut problem = Problem {
            chain,
            shoulder: heading * self.shoulder_at(chain, lift_m) + Vector3::new(base.x, base.y, 0.0),
            heading,
            target: Vector3::from(target.position),
            target_rot: *rotation.to_rotation_matrix().matrix(),
            lo: Angles::zeros(),
            hi: Angles::zeros(),
            n,
            settings,
        };
        for (k, &(lo, hi)) in limits[..n].iter().enumerate() {
            (problem.lo[k], problem.hi[k]) = (lo, hi);
        }
        let mut best = (f64::INFINITY, Angles::zeros(), 0.0, 0.0);
        let mut steps = 0;
        for start in 0..settings.max_starts.max(1) {
            let mut q = Angles::zeros();
            for k in 0..n {
                q[k] = if start == 0 {
                    seed[k]
                } else {
                    problem.lo[k] + (problem.hi[k] - problem.lo[k]) * spread(start, k)
                };
            }
            problem.clamp(&mut q);
            let (q, dp, da) = problem.descend(q, &mut steps);
            if problem.reached(dp, da) {
                let (q, dp, da) = if settings.centring > 0.0 {
                    problem.centre(q, dp, da, &mut steps)
                } else {
                    (q, dp, da)
                };
                return Ok(solution(&q, n, dp, da, steps, start + 1));
            }
            let miss = dp * dp + (ANGLE_LENGTH_M * da).powi(2);
            if miss < best.0 {
                best = (miss, q, dp, da);
            }
        }
        let (_, q, dp, da) = best;
        Err(IkError::NotReached {
            best: q.into(),
            position_error_m: dp,
            angle_error_rad: da,
        })
    }
}

fn solution(q: &Angles, n: usize, dp: f64, da: f64, steps: usize, starts: usize) -> IkSolution {
    IkSolution {
        q: (*q).into(),
        joints: n,
        position_error_m: dp,
        angle_error_rad: da,
        steps,
        starts,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::RobotDescription;

    fn a3() -> Body {
        Body::from_description(&RobotDescription::nori_a3()).unwrap()
    }

    fn target_of(body: &Body, arm: usize, q: &[f64], lift: f64, base: Pose2) -> ToolTarget {
        let p = body.arm_pose(arm, q, lift, base).unwrap();
        ToolTarget {
            position: p.tool,
            rotation: p.tool_rotation,
        }
    }

    #[test]
    fn a_pose_the_arm_can_take_is_reached_within_the_ranges_from_elsewhere() {
        let body = a3();
        let base = Pose2 {
            x: 0.5,
            y: -0.2,
            theta: 0.7,
        };
        let limits = body.arms()[0].hard_stops();
        let truth = [0.4, 0.9, -0.5, -1.2, 0.3, 0.6, -0.4];
        let target = target_of(&body, 0, &truth, 0.35, base);
        let s = body
            .solve(
                0,
                &target,
                &[0.0; 7],
                &limits,
                Mount { lift_m: 0.35, base },
                &IkSettings::default(),
            )
            .unwrap();
        let reached = body.arm_pose(0, &s.q[..7], 0.35, base).unwrap();
        let off = Vector3::from(reached.tool) - Vector3::from(target.position);
        assert!(off.norm() < 1e-4, "{s:?}");
        assert!(s.angle_error_rad < 1e-3);
        for (k, (lo, hi)) in limits.iter().enumerate() {
            assert!(s.q[k] >= *lo && s.q[k] <= *hi, "joint {k}: {s:?}");
        }
    }

    #[test]
    fn a_narrower_range_is_kept_and_a_target_beyond_reach_gets_the_closest_angles() {
        let body = a3();
        let mut limits = body.arms()[0].hard_stops();
        // The elbow calibrated to bend no further than −1.0: a target that needs −1.2 is not
        // reached, and the closest answer keeps the elbow at its range's end.
        limits[3] = (-1.0, 0.1);
        let truth = [0.4, 0.9, -0.5, -1.2, 0.3, 0.6, -0.4];
        let target = target_of(&body, 0, &truth, 0.3, Pose2::default());
        let at = Mount {
            lift_m: 0.3,
            base: Pose2::default(),
        };
        let solve = |target| body.solve(0, target, &[0.0; 7], &limits, at, &IkSettings::default());
        match solve(&target) {
            Ok(s) => assert!(s.q[3] >= -1.0, "{s:?}"),
            Err(IkError::NotReached { best, .. }) => {
                assert!(best[3] >= -1.0 && best[3] <= 0.1, "{best:?}")
            }
            Err(e) => panic!("{e}"),
        }
        // Two metres out: no angles reach it; the best is returned with how far it is.
        let far = ToolTarget {
            position: [2.0, 0.18, 1.0],
            rotation: [1.0, 0.0, 0.0, 0.0],
        };
        let e = solve(&far).unwrap_err();
        let IkError::NotReached {
            position_error_m, ..
        } = e
        else {
            panic!("{e}")
        };
        assert!(position_error_m > 1.0);
    }

    #[test]
    fn bad_input_is_refused_not_solved() {
        let body = a3();
        let limits = body.arms()[0].hard_stops();
        let ok = target_of(&body, 0, &[0.0; 7], 0.3, Pose2::default());
        let at = Mount {
            lift_m: 0.3,
            base: Pose2::default(),
        };
        let solve = |arm, target: &ToolTarget, seed: &[f64], limits: &[(f64, f64)], at| {
            body.solve(arm, target, seed, limits, at, &IkSettings::default())
        };
        let nan = ToolTarget {
            position: [f64::NAN, 0.0, 0.0],
            ..ok
        };
        let zero = ToolTarget {
            rotation: [0.0; 4],
            ..ok
        };
        let mut swapped = limits.clone();
        swapped[2] = (1.0, -1.0);
        let adrift = Mount {
            lift_m: f64::INFINITY,
            ..at
        };
        for (result, refused) in [
            (
                solve(0, &nan, &[0.0; 7], &limits, at),
                IkError::BadInput("target"),
            ),
            (
                solve(0, &zero, &[0.0; 7], &limits, at),
                IkError::BadInput("target"),
            ),
            (
                solve(0, &ok, &[0.0; 7], &limits, adrift),
                IkError::BadInput("target"),
            ),
            (
                solve(0, &ok, &[0.0; 3], &limits, at),
                IkError::BadInput("seed"),
            ),
            (
                solve(0, &ok, &[0.0; 7], &swapped, at),
                IkError::BadInput("limits"),
            ),
            (solve(2, &ok, &[0.0; 7], &limits, at), IkError::NoArm(2)),
        ] {
            assert_eq!(result, Err(refused));
        }
    }

    /// The redundancy is spent keeping joints off their ends: against the plain solver, the
    /// answers to the same targets sit farther from the ranges' ends on average.
    #[test]
    fn the_null_space_keeps_the_joints_off_their_ranges_ends() {
        let body = a3();
        let limits = body.arms()[0].hard_stops();
        let margin = |q: &[f64; MAX_JOINTS]| {
            (0..7)
                .map(|k| {
                    let (lo, hi) = limits[k];
                    ((q[k] - lo).min(hi - q[k])) / (hi - lo)
                })
                .fold(f64::INFINITY, f64::min)
        };
        let (mut centred, mut plain, mut n) = (0.0, 0.0, 0);
        for i in 0..100 {
            let truth: Vec<f64> = limits
                .iter()
                .enumerate()
                .map(|(k, (lo, hi))| lo + 0.15 * (hi - lo) + 0.7 * (hi - lo) * spread(100 + i, k))
                .collect();
            let target = target_of(&body, 0, &truth, 0.3, Pose2::default());
            let seed: Vec<f64> = truth.iter().map(|q| q + 0.2).collect();
            let with = IkSettings::default();
            let without = IkSettings {
                centring: 0.0,
                ..with
            };
            let at = Mount {
                lift_m: 0.3,
                base: Pose2::default(),
            };
            let solve = |settings| body.solve(0, &target, &seed, &limits, at, settings);
            if let (Ok(a), Ok(b)) = (solve(&with), solve(&without)) {
                centred += margin(&a.q);
                plain += margin(&b.q);
                n += 1;
            }
        }
        assert!(n > 90, "{n} of 100 solved both ways");
        assert!(
            centred > plain,
            "smallest margin to a range end: {} with the pull, {} without",
            centred / n as f64,
            plain / n as f64
        );
    }
}
