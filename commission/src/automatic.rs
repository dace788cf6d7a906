//! A calibration without a hand, over the line: the arm held where it hangs, then each joint
//! in the plan's order driven slowly toward each of its stops in speed mode at a low torque
//! limit, each stop found where the joint stalls (the supervisor's stall signal: the effort at
//! the limit, the position still), its calibration chosen from the two
//! ([`crate::calibrate::choose`]), written, and the joint driven back to rest before the next.
//! The caller sets the pace ([`Automatic::tick`] at a steady rate, the time passed in).
//!
//! Nothing here can drive a joint the wrong way round the encoder: a joint is swept in speed
//! mode (no position goal, so no 0/4095 wrap to cross) and driven to positions only once its
//! calibration puts its travel inside the turn. Until then it holds where it was found, its
//! homing offset provisionally making it read mid-turn. Every write but the calibration goes
//! to RAM (the Lock closed): a power cycle in the middle gives back what the servo held, and a
//! refusal does the same at once, after the joint is driven back to where its sweep began.
//! docs/commissioning.md gives the reasons; docs/hazards.md C7 the hazards.

use crate::calibrate::{choose, Refusal, Sweep};
use crate::session::{
    self, give_back, write_calibration, write_checked, Calibrated, JointToCalibrate, SessionError,
    Taken,
};
use body::description::BusDescription;
use bus_driver::backstops::{calibration_settings, OVERLOAD_PROTECTION};
use bus_driver::bus::Bus;
use bus_driver::calibration::{JointCalibration, CENTER, STEPS_PER_RAD};
use bus_driver::transport::Transport;
use feetech::registers as reg;
use feetech::ServoStatus;
use supervisor::stall::{StallAction, StallDetector, StallKind};

/// One joint's sweep.
#[derive(Debug, Clone, PartialEq)]
pub struct PlannedSweep {
    /// The joint.
    pub target: JointToCalibrate,
    /// Its torque limit while swept and held, 0.1 %.
    pub torque_permille: u16,
    /// Joints swept before it, held at these angles (by index into the plan, rad) while it is.
    pub pose: Vec<(usize, f64)>,
}

/// The whole calibration.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    /// The joints in the order they are swept.
    pub sweeps: Vec<PlannedSweep>,
    /// The speed toward each stop, rad/s.
    pub speed_rad_s: f64,
    /// How far inside each stop the limits go, rad.
    pub margin_rad: f64,
    /// How far the travel found may differ from the description's, rad.
    pub tolerance_rad: f64,
}

/// Why a description gives no plan over the joints to calibrate.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlanError {
    /// The bus has no arm with a calibration plan.
    #[error(
        "the description gives bus {0} no calibration plan (`[bus.arm.calibration]`): \
         calibrate it by hand"
    )]
    NoPlan(String),
    /// The plan sweeps a servo whose joint is not among those to calibrate.
    #[error(
        "the description's calibration plan sweeps servo {0}, whose joint is not among those \
         the driver's configuration names"
    )]
    UnknownServo(u8),
}

impl Plan {
    /// The description's plan for `bus` over `targets`: each servo the plan names is the
    /// target of the joint the description gives that servo (the driver's configuration may
    /// number the servos otherwise).
    pub fn of(
        bus: &BusDescription,
        targets: &[JointToCalibrate],
        margin_rad: f64,
        tolerance_rad: f64,
    ) -> Result<Plan, PlanError> {
        let described = (bus.arm.as_ref())
            .and_then(|a| a.calibration.as_ref())
            .ok_or_else(|| PlanError::NoPlan(bus.name.clone()))?;
        let target = |servo: u8| {
            let joint = bus.servo.iter().find(|s| s.id == servo).map(|s| &s.joint);
            targets
                .iter()
                .position(|t| Some(&t.joint) == joint)
                .ok_or(PlanError::UnknownServo(servo))
        };
        let index = |servo: u8| {
            (described.sweep.iter())
                .position(|s| s.servo == servo)
                .ok_or(PlanError::UnknownServo(servo))
        };
        let sweeps = (described.sweep.iter())
            .map(|s| {
                let pose = (s.pose.iter())
                    .map(|p| Ok((index(p.servo)?, p.rad)))
                    .collect::<Result<_, PlanError>>()?;
                Ok(PlannedSweep {
                    target: targets[target(s.servo)?].clone(),
                    torque_permille: (s.torque_percent * 10.0).round() as u16,
                    pose,
                })
            })
            .collect::<Result<_, PlanError>>()?;
        Ok(Plan {
            sweeps,
            speed_rad_s: described.speed_rad_s,
            margin_rad,
            tolerance_rad,
        })
    }
}

/// Which stop a joint is driven toward.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Toward {
    /// Its lower stop.
    Lower,
    /// Its upper stop.
    Upper,
}

impl Toward {
    fn name(self) -> &'static str {
        match self {
            Toward::Lower => "lower",
            Toward::Upper => "upper",
        }
    }
}

/// What the session is doing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Activity {
    /// Driving the joints of a sweep's pose there.
    Posing,
    /// Driving a joint toward a stop; how far it has gone, rad.
    Seeking(Toward, f64),
    /// Driving a calibrated joint back to rest.
    Resting,
    /// Driving the swept joint back to where its sweep began, after a refusal.
    Returning,
    /// Every joint to rest, then its torque off.
    Parking,
}

/// Where the session is, for the operator.
#[derive(Debug, Clone, PartialEq)]
pub enum Progress {
    /// Working on `joint` (index into the plan).
    Working(usize, Activity),
    /// Every joint calibrated and written, the arm at rest with its torque off.
    Done(Vec<Calibrated>),
}

/// Readings in a row that make a stall (at a 50 Hz tick, 0.16 s: the supervisor's window is
/// 75 ms at its rate).
const WINDOW: usize = 8;
/// The position spread over the window that still counts as still, rad (the supervisor's).
const STILL_RAD: f32 = 0.01;
/// The effort that counts as pushing: this share of the torque limit.
const PUSHING_SHARE: f32 = 0.8;
/// A joint is where it was driven within this, rad.
const ARRIVED_RAD: f64 = 0.05;
/// How far above its torque limit a joint's load may read before the limit is judged not
/// to hold, 0.1 % (a reading's noise).
const LOAD_SLACK: i32 = 50;
/// How far a driven joint may go the other way (a start's sag) before it is judged to turn
/// the wrong way, rad.
const WRONG_WAY_RAD: f64 = 0.2;
/// A pose's joint this far from its pose while another is swept is pushed out of it, rad.
const POSE_HELD_RAD: f64 = 0.15;
/// Longest a move to a pose or to rest may take beyond its travel at the speed, s.
const MOVE_SLACK_S: f64 = 5.0;
/// Longest a swept joint may push above its press bound's threshold without standing still
/// (that is a stop) before the session refuses it and drives it back, s: it strains against a
/// load its limit cannot move, or something gives way. Half the firmware's time below, which
/// would end the push wherever it is, moving or not, and leave it with no output there (the
/// roll under the arm's weight).
const STRAIN_S: f64 = 0.5;
/// Readings in a row under the threshold that end a strain (one reading's noise does not).
const STRAIN_LOW_READINGS: u8 = 5;
/// The firmware's own bound on a press while a joint turns in speed mode (from its first drive
/// toward a stop until it is calibrated and held by position): an output above this share of
/// its torque limit (above the stall rule's [`PUSHING_SHARE`], so the rule fires first)...
const OVERLOAD_SHARE: f64 = 0.9;
/// ...for this long (10 ms units: 1 s, six times the stall rule's window)...
const OVERLOAD_TIME: i32 = 100;
/// ...and the firmware leaves the motor no output (whether it unloads or holds its protective
/// torque, none is none). A session killed mid-sweep (SIGKILL, no Drop) leaves a servo in
/// speed mode turning into its stop with nobody on the line: this ends that press. While the
/// session lives, its own rules (the stall, [`STRAIN_S`]) act first.
const PROTECTIVE_PERCENT: i32 = 0;
/// The registers of that bound, and `Unloading_Condition` with its overload bit.
/// The driver's own list, so the bound and what is given back name the same registers.
const PRESS_BOUND: [reg::Register; 4] = [
    OVERLOAD_PROTECTION[0].0,
    OVERLOAD_PROTECTION[1].0,
    OVERLOAD_PROTECTION[2].0,
    reg::UNLOADING_CONDITION,
];

struct Joint {
    taken: Taken,
    plan: PlannedSweep,
    /// The homing offset that made it read mid-turn where it was found.
    provisional: i32,
    /// The `Torque_Limit` it had when taken, given back at the end.
    torque_limit: i32,
    /// The `Unloading_Condition` it held when taken, given back with the driver's overload
    /// protection once it is calibrated (or at the end).
    unloading: i32,
    sweep: Sweep,
    /// Where its sweep began, unwrapped, rad: where a refused sweep drives it back to.
    began_rad: f64,
    /// In speed mode with a speed goal (it turns until told otherwise).
    turning: bool,
    calibration: Option<JointCalibration>,
}

/// A joint driven toward a stop.
struct Seeking {
    k: usize,
    toward: Toward,
    since: f64,
    /// Where it was when this drive began, unwrapped, rad.
    from_rad: f64,
    detector: StallDetector,
    strain: StrainWatch,
}

/// How long a swept joint has pushed above its press bound's threshold, either way (the
/// load's sign is the direction it pushes), without a break of [`STRAIN_LOW_READINGS`]
/// readings under it: the firmware's own clock restarts at any one reading under it, so this
/// one runs ahead of it.
#[derive(Debug, Default)]
struct StrainWatch {
    /// Since when it has pushed above the threshold, s.
    since: Option<f64>,
    /// Readings in a row below it.
    low_readings: u8,
}

impl StrainWatch {
    /// Takes one reading of `load` (0.1 %) at `now_s`; whether it has pushed above
    /// `threshold` (0.1 %) for [`STRAIN_S`].
    fn strained(&mut self, load: i32, threshold: i32, now_s: f64) -> bool {
        if load.abs() > threshold {
            self.low_readings = 0;
            self.since.get_or_insert(now_s);
        } else {
            self.low_readings = self.low_readings.saturating_add(1);
            if self.low_readings >= STRAIN_LOW_READINGS {
                self.since = None;
            }
        }
        self.since.is_some_and(|t| now_s - t >= STRAIN_S)
    }
}

/// A refused joint driven back to where its sweep began.
struct Returning {
    k: usize,
    since: f64,
    to_rad: f64,
    /// Further than this from where it goes back to, it is not going back: stopped.
    farthest_rad: f64,
    refusal: Refusal,
    /// Something in its way back stops it there.
    detector: StallDetector,
}

enum Stage {
    Pose {
        k: usize,
        since: f64,
    },
    /// Boxed: the detector's window is large beside the other stages.
    Seek(Box<Seeking>),
    Rest {
        k: usize,
        since: f64,
    },
    /// Boxed, as [`Stage::Seek`].
    Return(Box<Returning>),
    Park {
        since: f64,
        refusal: Option<Refusal>,
    },
    /// Every joint calibrated (in RAM) and at rest, held there: waiting for
    /// [`Automatic::commit`].
    Parked,
}

/// An automatic calibration in progress.
pub struct Automatic<T: Transport> {
    bus: Bus<T>,
    joints: Vec<Joint>,
    speed_rad_s: f64,
    margin_rad: f64,
    tolerance_rad: f64,
    stage: Stage,
    /// The held joint whose protections are read next (one a tick, in turn).
    watched: usize,
    /// Every joint released (torque off, RAM as a driver expects it): the session is over.
    released: bool,
}

impl<T: Transport> Automatic<T> {
    /// Takes every joint (alone at its id, of its model, its torque off, what it held kept),
    /// gives each a provisional offset reading mid-turn where it is and the whole turn as its
    /// range (RAM only), and holds it there at its torque limit. A joint that cannot be taken
    /// gives every one taken before it back what it held, its torque off.
    pub fn start(bus: Bus<T>, plan: Plan, now_s: f64) -> Result<Self, SessionError> {
        // Before any servo is touched.
        let unbounded =
            (plan.sweeps.iter()).find(|p| overload_percent(p.torque_permille).is_none());
        if let Some(p) = unbounded {
            return Err(no_press_bound(p));
        }
        let mut session = Automatic {
            bus,
            joints: Vec::with_capacity(plan.sweeps.len()),
            speed_rad_s: plan.speed_rad_s,
            margin_rad: plan.margin_rad,
            tolerance_rad: plan.tolerance_rad,
            stage: Stage::Pose { k: 0, since: now_s },
            watched: 0,
            released: false,
        };
        for p in plan.sweeps {
            if let Err(e) = session.take(p) {
                // Best effort: the error that stopped the session is the one to report.
                let _ = session.release(false);
                return Err(e);
            }
        }
        if let Err(e) = session.begin_pose(0) {
            let _ = session.release(false);
            return Err(e);
        }
        Ok(session)
    }

    fn take(&mut self, plan: PlannedSweep) -> Result<(), SessionError> {
        let taken = session::take(&mut self.bus, plan.target.clone())?;
        let id = taken.target.id;
        let bus = &mut self.bus;
        // Closed, so that nothing below reaches the flash.
        bus.write(id, reg::LOCK, 1).map_err(|e| taken.failed(e))?;
        let present = bus
            .read(id, reg::PRESENT_POSITION)
            .map_err(|e| taken.failed(e))?;
        let torque_limit = bus
            .read(id, reg::TORQUE_LIMIT)
            .map_err(|e| taken.failed(e))?;
        let unloading = bus
            .read(id, reg::UNLOADING_CONDITION)
            .map_err(|e| taken.failed(e))?;
        let raw = (i64::from(present) + i64::from(taken.found[0])).rem_euclid(4096);
        // Reads 2048 where it is. −2048 and 2048 are one offset; the register holds neither
        // (a step off mid-turn).
        let provisional = raw - CENTER as i64;
        let provisional = provisional.clamp(-2047, 2047) as i32;
        self.joints.push(Joint {
            taken: taken.clone(),
            plan,
            provisional,
            torque_limit,
            unloading,
            sweep: Sweep::default(),
            began_rad: 0.0,
            turning: false,
            calibration: None,
        });
        let values = [
            (reg::HOMING_OFFSET, provisional),
            (reg::MIN_POSITION_LIMIT, 0),
            (reg::MAX_POSITION_LIMIT, 4095),
        ];
        write_checked(&mut self.bus, &taken, &values, false)?;
        let k = self.joints.len() - 1;
        // Everything below relies on the firmware applying a homing offset written to RAM.
        let reads = self.read(k, reg::PRESENT_POSITION)?;
        if (reads - CENTER as i32).abs() > 8 {
            return Err(SessionError::Refused(vec![Refusal::FirmwareDiffers {
                joint: taken.target.joint.clone(),
                what: format!(
                    "given a homing offset to read 2048 where it stands (Lock closed), it reads \
                     {reads}"
                ),
            }]));
        }
        self.hold(k)
    }

    /// Holds a joint where it is, in position mode at its torque limit.
    fn hold(&mut self, k: usize) -> Result<(), SessionError> {
        let speed = self.speed_steps();
        let present = self.read(k, reg::PRESENT_POSITION)?;
        let j = &self.joints[k];
        let values = [
            (reg::GOAL_VELOCITY, speed),
            (reg::GOAL_POSITION, present),
            (reg::OPERATING_MODE, 0),
            (reg::TORQUE_LIMIT, i32::from(j.plan.torque_permille)),
            (reg::TORQUE_ENABLE, 1),
        ];
        let taken = j.taken.clone();
        write_checked(&mut self.bus, &taken, &values, false)
    }

    fn speed_steps(&self) -> i32 {
        (self.speed_rad_s * STEPS_PER_RAD).round() as i32
    }

    fn read(&mut self, k: usize, register: reg::Register) -> Result<i32, SessionError> {
        let j = &self.joints[k];
        self.bus
            .read(j.taken.target.id, register)
            .map_err(|e| j.taken.failed(e))
    }

    fn write(&mut self, k: usize, register: reg::Register, value: i32) -> Result<(), SessionError> {
        let j = &self.joints[k];
        self.bus
            .write(j.taken.target.id, register, value)
            .map(|_| ())
            .map_err(|e| j.taken.failed(e))
    }

    /// A calibrated joint driven toward `rad` (within its range), at the session's speed.
    fn drive_to(&mut self, k: usize, rad: f64) -> Result<(), SessionError> {
        let Some(cal) = self.joints[k].calibration else {
            return Ok(());
        };
        // The angle is finite (the description's, or 0): the goal cannot be refused.
        let goal = cal.goal_steps(k, rad as f32).unwrap_or(CENTER as i32);
        self.write(k, reg::GOAL_POSITION, goal)
    }

    /// Whether a calibrated joint is within [`ARRIVED_RAD`] of `rad` (clamped into its range);
    /// where it is, rad.
    fn arrived(&mut self, k: usize, rad: f64) -> Result<(bool, f64), SessionError> {
        let Some(cal) = self.joints[k].calibration else {
            return Ok((true, rad));
        };
        let at = cal.to_rad(self.read(k, reg::PRESENT_POSITION)?);
        let (lo, hi) = cal.range_rad();
        Ok(((at - rad.clamp(lo, hi)).abs() <= ARRIVED_RAD, at))
    }

    fn begin_pose(&mut self, k: usize) -> Result<(), SessionError> {
        for (i, rad) in self.joints[k].plan.pose.clone() {
            self.drive_to(i, rad)?;
        }
        Ok(())
    }

    /// Stops the session before it is done: the joint being swept driven back to where its
    /// sweep began, the arm parked, every servo given back what it held, by the ticks that
    /// follow (they end in [`SessionError::Refused`]).
    pub fn stop(&mut self, now_s: f64, began_s: f64) {
        let refusal = Refusal::Stopped {
            after_s: now_s - began_s,
        };
        let stage = std::mem::replace(
            &mut self.stage,
            Stage::Park {
                since: now_s,
                refusal: None,
            },
        );
        self.stage = match stage {
            Stage::Seek(seeking) => self.return_refused(seeking.k, refusal, now_s).0,
            Stage::Return(_) | Stage::Parked => stage,
            // Parking after the last joint: stopped now, it is not done.
            Stage::Park {
                since,
                refusal: first,
            } => Stage::Park {
                since,
                refusal: first.or(Some(refusal)),
            },
            Stage::Pose { .. } | Stage::Rest { .. } => self.park(Some(refusal), now_s).0,
        };
    }

    /// One step of the session at `now_s` (the caller's clock, s): reads what the stage needs
    /// and drives what it decides. Every refusal drives the joint back, parks the arm, gives
    /// every servo back what it held and returns [`SessionError::Refused`].
    pub fn tick(&mut self, now_s: f64) -> Result<Progress, SessionError> {
        let result = self.step(now_s);
        if result.is_err() && !self.released {
            // Best effort: the line failed, so the error that stopped it is the one to report.
            let _ = self.release(false);
        }
        result
    }

    fn step(&mut self, now_s: f64) -> Result<Progress, SessionError> {
        if self.released {
            return Err(SessionError::Ended);
        }
        if let Stage::Parked = self.stage {
            return Ok(Progress::Done(self.calibrated()));
        }
        let mut stage = std::mem::replace(&mut self.stage, Stage::Parked);
        let active = match &stage {
            Stage::Pose { k, .. } | Stage::Rest { k, .. } => *k,
            Stage::Seek(s) => s.k,
            Stage::Return(r) => r.k,
            Stage::Park { .. } | Stage::Parked => self.watched,
        };
        self.watched = (self.watched + 1) % self.joints.len();
        for i in [active, self.watched] {
            let Some(unloaded) = self.unloaded(i)? else {
                continue;
            };
            if let Stage::Park { refusal, .. } = &mut stage {
                // Parking already: its clock and its first refusal stand.
                refusal.get_or_insert(unloaded);
                break;
            }
            let refusal = match stage {
                // Refused already: that is the refusal to report.
                Stage::Return(r) => r.refusal,
                _ => unloaded,
            };
            self.stage = self.park(Some(refusal), now_s).0;
            return Ok(Progress::Working(active, Activity::Parking));
        }
        let (next, progress) = match stage {
            Stage::Pose { k, since } => self.posing(k, since, now_s)?,
            Stage::Seek(seeking) => self.seeking(seeking, now_s)?,
            Stage::Rest { k, since } => self.resting(k, since, now_s)?,
            Stage::Return(returning) => self.returning(returning, now_s)?,
            Stage::Park { since, refusal } => return self.parking(since, refusal, now_s),
            Stage::Parked => return Ok(Progress::Done(self.calibrated())),
        };
        self.stage = next;
        Ok(progress)
    }

    /// Time a move over `rad` should take at the session's speed, with slack, s.
    fn allowed_s(&self, rad: f64) -> f64 {
        rad.abs() / self.speed_rad_s * 1.5 + MOVE_SLACK_S
    }

    fn posing(
        &mut self,
        k: usize,
        since: f64,
        now_s: f64,
    ) -> Result<(Stage, Progress), SessionError> {
        let mut all = true;
        for (i, rad) in self.joints[k].plan.pose.clone() {
            let (there, at) = self.arrived(i, rad)?;
            if !there && now_s - since > self.allowed_s(std::f64::consts::PI) {
                let refusal = Refusal::NotReached {
                    joint: self.joints[i].taken.target.joint.clone(),
                    wanted_deg: rad.to_degrees(),
                    at_deg: at.to_degrees(),
                };
                return Ok(self.park(Some(refusal), now_s));
            }
            all &= there;
        }
        if !all {
            return Ok((
                Stage::Pose { k, since },
                Progress::Working(k, Activity::Posing),
            ));
        }
        let from_rad = self.observe(k)?;
        self.joints[k].began_rad = from_rad;
        self.begin_seek(k, Toward::Lower)?;
        Ok((
            self.seek(k, Toward::Lower, now_s, from_rad),
            Progress::Working(k, Activity::Seeking(Toward::Lower, 0.0)),
        ))
    }

    fn seek(&self, k: usize, toward: Toward, since: f64, from_rad: f64) -> Stage {
        Stage::Seek(Box::new(Seeking {
            k,
            toward,
            since,
            from_rad,
            detector: self.detector(k),
            strain: StrainWatch::default(),
        }))
    }

    /// The stall rule for a joint driven at its torque limit.
    fn detector(&self, k: usize) -> StallDetector {
        let limit = f32::from(self.joints[k].plan.torque_permille) / 1000.0;
        StallDetector::with_threshold(StallKind::Joint, PUSHING_SHARE * limit, 0.1)
    }

    /// Whether a joint's servo has unloaded its motor (a protection fired).
    fn unloaded(&mut self, k: usize) -> Result<Option<Refusal>, SessionError> {
        let status = ServoStatus(self.read(k, reg::STATUS)? as u8);
        // The protections that unload the motor, and an encoder that cannot be trusted.
        let unloading = ServoStatus::OVERHEAT
            | ServoStatus::OVER_CURRENT
            | ServoStatus::OVERLOAD
            | ServoStatus::ANGLE_SENSOR;
        let j = &self.joints[k];
        let joint = j.taken.target.joint.clone();
        Ok(match status.0 & unloading {
            0 => None,
            // The press bound, on while it turns: pushing for a second and never still.
            ServoStatus::OVERLOAD if j.turning => Some(Refusal::Strained { joint }),
            _ => Some(Refusal::Unloaded {
                joint,
                status: status.to_string(),
            }),
        })
    }

    /// What a swept joint does that the calibration does not expect: pressing harder than
    /// its torque limit allows, or going the other way than it is driven (`progress_rad`, in
    /// the direction driven).
    fn misbehaves(&self, k: usize, load: i32, progress_rad: f64) -> Option<String> {
        let limit = i32::from(self.joints[k].plan.torque_permille);
        if load.abs() > limit + LOAD_SLACK {
            return Some(format!(
                "Present_Load {load} ‰ beyond its Torque_Limit {limit} ‰"
            ));
        }
        (progress_rad < -WRONG_WAY_RAD).then(|| {
            format!(
                "driven one way, it went {progress_rad:.2} rad the other: it turns the other \
                 way in speed mode, or its torque limit cannot hold it against gravity"
            )
        })
    }

    /// A joint of `k`'s pose pushed out of it while `k` is swept (the sweep's motion, or
    /// something else), if any.
    fn out_of_pose(&mut self, k: usize) -> Result<Option<Refusal>, SessionError> {
        for (i, rad) in self.joints[k].plan.pose.clone() {
            let (_, at) = self.arrived(i, rad)?;
            if (at - rad).abs() > POSE_HELD_RAD {
                return Ok(Some(Refusal::NotReached {
                    joint: self.joints[i].taken.target.joint.clone(),
                    wanted_deg: rad.to_degrees(),
                    at_deg: at.to_degrees(),
                }));
            }
        }
        Ok(None)
    }

    /// Reads a joint's position into its sweep; where it is, unwrapped, rad.
    fn observe(&mut self, k: usize) -> Result<f64, SessionError> {
        let present = self.read(k, reg::PRESENT_POSITION)?;
        let j = &mut self.joints[k];
        let raw = (i64::from(present) + i64::from(j.provisional)).rem_euclid(4096);
        j.sweep.observe(raw as u16);
        Ok(j.sweep.position_rad())
    }

    /// Speed mode toward a stop (the servo counting down toward the lower one unless it is
    /// inverted).
    fn begin_seek(&mut self, k: usize, toward: Toward) -> Result<(), SessionError> {
        let down = (toward == Toward::Lower) != self.joints[k].plan.target.stops.inverted;
        let speed = self.speed_steps();
        let j = &self.joints[k];
        let taken = j.taken.clone();
        let bound = press_bound(j).ok_or_else(|| no_press_bound(&j.plan))?;
        let values: Vec<_> = (bound.into_iter())
            .chain([
                (reg::GOAL_VELOCITY, if down { -speed } else { speed }),
                (reg::OPERATING_MODE, 1),
            ])
            .collect();
        write_checked(&mut self.bus, &taken, &values, false)?;
        self.joints[k].turning = true;
        Ok(())
    }

    fn seeking(
        &mut self,
        mut seeking: Box<Seeking>,
        now_s: f64,
    ) -> Result<(Stage, Progress), SessionError> {
        let Seeking {
            k,
            toward,
            since,
            from_rad,
            ..
        } = *seeking;
        let at = self.observe(k)?;
        let load = self.read(k, reg::PRESENT_LOAD)?;
        let stops = self.joints[k].plan.target.stops;
        let travel = stops.upper_rad - stops.lower_rad;
        let joint = self.joints[k].taken.target.joint.clone();
        let moved = (at - from_rad).abs();
        if moved > travel + self.tolerance_rad {
            let refusal = Refusal::BeyondTravel {
                joint,
                swept_deg: moved.to_degrees(),
                travel_deg: travel.to_degrees(),
            };
            return Ok(self.return_refused(k, refusal, now_s));
        }
        if now_s - since > self.allowed_s(travel) {
            let refusal = Refusal::NoStop {
                joint,
                toward: toward.name(),
                after_s: now_s - since,
            };
            return Ok(self.return_refused(k, refusal, now_s));
        }
        // Always trying: the goal is a radian beyond where it is, the way it is driven.
        let ahead = if (toward == Toward::Lower) != stops.inverted {
            -1.0
        } else {
            1.0
        };
        if let Some(what) = self.misbehaves(k, load, (at - from_rad) * ahead) {
            let refusal = Refusal::FirmwareDiffers { joint, what };
            return Ok(self.return_refused(k, refusal, now_s));
        }
        if let Some(refusal) = self.out_of_pose(k)? {
            return Ok(self.return_refused(k, refusal, now_s));
        }
        let sample = (at as f32, load as f32 / 1000.0, (at + ahead) as f32);
        let stalled = seeking.detector.update(Some(sample), &stall_config()) != StallAction::None;
        // Above the firmware's threshold (a light joint moves at its stall rule's effort).
        let limit = self.joints[k].plan.torque_permille;
        let threshold = overload_percent(limit).map_or(i32::from(limit), |p| 10 * p);
        let strained = seeking.strain.strained(load, threshold, now_s);
        if !stalled && strained {
            return Ok(self.return_refused(k, Refusal::Strained { joint }, now_s));
        }
        let progress = Progress::Working(k, Activity::Seeking(toward, moved));
        match (stalled, toward) {
            (false, _) => Ok((Stage::Seek(seeking), progress)),
            (true, Toward::Lower) => {
                self.begin_seek(k, Toward::Upper)?;
                Ok((self.seek(k, Toward::Upper, now_s, at), progress))
            }
            (true, Toward::Upper) => self.calibrate(k, now_s),
        }
    }

    /// Both stops found: the calibration chosen and written, the joint held in position mode
    /// and sent to rest.
    fn calibrate(&mut self, k: usize, now_s: f64) -> Result<(Stage, Progress), SessionError> {
        let j = &self.joints[k];
        let target = &j.taken.target;
        let chosen = choose(
            &target.joint,
            &j.sweep,
            &target.stops,
            self.margin_rad,
            self.tolerance_rad,
        );
        let calibration = match chosen {
            Ok(c) => c,
            Err(refusal) => return Ok(self.return_refused(k, refusal, now_s)),
        };
        let taken = j.taken.clone();
        // Still pressing its stop at the torque limit while the calibration is written (to
        // RAM: the flash gets every joint's at the end, or none): it moves nowhere, and its
        // position then reads in the calibrated frame (no wrap).
        let settings = calibration_settings(&calibration).map(|s| (s.register, s.value));
        write_checked(&mut self.bus, &taken, &settings, false)?;
        self.joints[k].calibration = Some(calibration);
        let present = self.read(k, reg::PRESENT_POSITION)?;
        // The profile's speed positive (it was the sweep's signed speed); held by position
        // from here, with the driver's overload protection (a pose's load may be near its
        // limit for longer than the press bound allows).
        let values: Vec<_> = [
            (reg::GOAL_VELOCITY, self.speed_steps()),
            (reg::GOAL_POSITION, present),
            (reg::OPERATING_MODE, 0),
        ]
        .into_iter()
        .chain(press_unbound(&self.joints[k]))
        .collect();
        write_checked(&mut self.bus, &taken, &values, false)?;
        self.joints[k].turning = false;
        self.drive_to(k, 0.0)?;
        Ok((
            Stage::Rest { k, since: now_s },
            Progress::Working(k, Activity::Resting),
        ))
    }

    fn resting(
        &mut self,
        k: usize,
        since: f64,
        now_s: f64,
    ) -> Result<(Stage, Progress), SessionError> {
        let (there, at) = self.arrived(k, 0.0)?;
        let stops = self.joints[k].plan.target.stops;
        if !there {
            if now_s - since > self.allowed_s(stops.upper_rad - stops.lower_rad) {
                let refusal = Refusal::NotReached {
                    joint: self.joints[k].taken.target.joint.clone(),
                    wanted_deg: 0.0,
                    at_deg: at.to_degrees(),
                };
                return Ok(self.park(Some(refusal), now_s));
            }
            return Ok((
                Stage::Rest { k, since },
                Progress::Working(k, Activity::Resting),
            ));
        }
        if k + 1 == self.joints.len() {
            return Ok(self.park(None, now_s));
        }
        // The joints the last pose held go back to rest unless the next pose holds them.
        for (i, _) in self.joints[k].plan.pose.clone() {
            self.drive_to(i, 0.0)?;
        }
        self.begin_pose(k + 1)?;
        Ok((
            Stage::Pose {
                k: k + 1,
                since: now_s,
            },
            Progress::Working(k + 1, Activity::Posing),
        ))
    }

    /// A refused sweep: the joint driven back toward where its sweep began (still in speed
    /// mode: it has no calibration), then the arm parked.
    fn return_refused(&mut self, k: usize, refusal: Refusal, now_s: f64) -> (Stage, Progress) {
        let to_rad = self.joints[k].began_rad;
        let away = (to_rad - self.joints[k].sweep.position_rad()).abs();
        (
            Stage::Return(Box::new(Returning {
                k,
                since: now_s,
                to_rad,
                farthest_rad: away + WRONG_WAY_RAD,
                refusal,
                detector: self.detector(k),
            })),
            Progress::Working(k, Activity::Returning),
        )
    }

    fn returning(
        &mut self,
        mut r: Box<Returning>,
        now_s: f64,
    ) -> Result<(Stage, Progress), SessionError> {
        let (k, since, to_rad) = (r.k, r.since, r.to_rad);
        let at = self.observe(k)?;
        let load = self.read(k, reg::PRESENT_LOAD)?;
        let left = to_rad - at;
        let travel = self.joints[k].plan.target.stops;
        let expired = now_s - since > self.allowed_s(travel.upper_rad - travel.lower_rad);
        let sample = (at as f32, load as f32 / 1000.0, (at + left.signum()) as f32);
        let blocked = r.detector.update(Some(sample), &stall_config()) != StallAction::None;
        // Going away from where it is sent back to: it does not turn as driven.
        let astray = left.abs() > r.farthest_rad;
        if left.abs() <= ARRIVED_RAD || expired || blocked || astray {
            self.write(k, reg::GOAL_VELOCITY, 0)?;
            return Ok(self.park(Some(r.refusal), now_s));
        }
        // Toward the start: the servo counts up when the unwrapped reading must grow.
        let speed = self.speed_steps();
        self.write(
            k,
            reg::GOAL_VELOCITY,
            if left > 0.0 { speed } else { -speed },
        )?;
        Ok((Stage::Return(r), Progress::Working(k, Activity::Returning)))
    }

    /// Every calibrated joint to rest; the others hold where they are.
    fn park(&self, refusal: Option<Refusal>, now_s: f64) -> (Stage, Progress) {
        let k = self.joints.len().saturating_sub(1);
        (
            Stage::Park {
                since: now_s,
                refusal,
            },
            Progress::Working(k, Activity::Parking),
        )
    }

    fn parking(
        &mut self,
        since: f64,
        refusal: Option<Refusal>,
        now_s: f64,
    ) -> Result<Progress, SessionError> {
        for k in 0..self.joints.len() {
            if std::mem::take(&mut self.joints[k].turning) {
                // It has no calibration to hold by: it stops where it is.
                self.write(k, reg::GOAL_VELOCITY, 0)?;
            }
        }
        let mut away = None;
        for k in 0..self.joints.len() {
            self.drive_to(k, 0.0)?;
            let (there, at) = self.arrived(k, 0.0)?;
            if !there {
                away = away.or(Some((k, at)));
            }
        }
        let expired = now_s - since > self.allowed_s(std::f64::consts::PI);
        let refusal = match away {
            Some(_) if !expired => {
                self.stage = Stage::Park { since, refusal };
                let k = self.joints.len().saturating_sub(1);
                return Ok(Progress::Working(k, Activity::Parking));
            }
            Some((k, at)) => refusal.or(Some(Refusal::NotReached {
                joint: self.joints[k].taken.target.joint.clone(),
                wanted_deg: 0.0,
                at_deg: at.to_degrees(),
            })),
            None => refusal,
        };
        match refusal {
            Some(r) => {
                self.release(false)?;
                Err(SessionError::Refused(vec![r]))
            }
            None => {
                self.stage = Stage::Parked;
                Ok(Progress::Done(self.calibrated()))
            }
        }
    }

    fn calibrated(&self) -> Vec<Calibrated> {
        (self.joints.iter())
            .filter_map(|j| j.calibration.map(|c| j.taken.calibrated(c)))
            .collect()
    }

    /// Once done ([`Progress::Done`]): every joint's calibration written to flash and read
    /// back, every torque off and its RAM as a driver expects it. A failure gives every servo
    /// back what it held. What the calibration is recorded in comes after: if that fails,
    /// [`Automatic::abandon`].
    pub fn commit(&mut self) -> Result<Vec<Calibrated>, SessionError> {
        if !matches!(self.stage, Stage::Parked) || self.released {
            return Err(SessionError::NotDone);
        }
        if let Err(e) = self.flash().and_then(|()| self.release(true)) {
            // Best effort: the failure that stopped the commit is the one to report.
            let _ = self.give_back_all(true);
            return Err(e);
        }
        Ok(self.calibrated())
    }

    /// After [`Automatic::commit`], when the calibration cannot be recorded: every servo
    /// given back what it held, in flash.
    pub fn abandon(&mut self) -> Result<(), SessionError> {
        self.give_back_all(true)
    }

    /// Every joint's calibration, held so far in RAM, written to flash and read back.
    fn flash(&mut self) -> Result<(), SessionError> {
        for j in &self.joints {
            if let Some(c) = &j.calibration {
                write_calibration(&mut self.bus, &j.taken, c)?;
            }
        }
        Ok(())
    }

    /// Every joint's torque off and its RAM as a driver expects it (position mode, the torque
    /// limit it had); unless the session is `done`, every servo given back what it held (in
    /// RAM: nothing reached the flash), each tried even when one fails. Once.
    fn release(&mut self, done: bool) -> Result<(), SessionError> {
        if std::mem::replace(&mut self.released, true) {
            return Ok(());
        }
        let mut first_error = None;
        for k in 0..self.joints.len() {
            let j = &self.joints[k];
            let taken = j.taken.clone();
            let rest: Vec<_> = [
                (reg::GOAL_VELOCITY, 0),
                (reg::OPERATING_MODE, 0),
                (reg::TORQUE_LIMIT, j.torque_limit),
            ]
            .into_iter()
            .chain(press_unbound(j))
            .collect();
            // The torque off first and on its own: a failure there does not keep the rest
            // (the driver's overload protection among it) from being written.
            for values in [&[(reg::TORQUE_ENABLE, 0)][..], &rest] {
                if let Err(e) = write_checked(&mut self.bus, &taken, values, false) {
                    first_error.get_or_insert(e);
                }
            }
        }
        if !done {
            if let Err(e) = self.give_back_all(false) {
                first_error.get_or_insert(e);
            }
        }
        first_error.map_or(Ok(()), Err)
    }

    /// Every servo given back the homing offset and limits it held (`to_flash`: in its
    /// EEPROM too), each tried even when one fails.
    fn give_back_all(&mut self, to_flash: bool) -> Result<(), SessionError> {
        let mut first_error = None;
        for j in &self.joints {
            if let Err(e) = give_back(&mut self.bus, std::slice::from_ref(&j.taken), to_flash) {
                first_error.get_or_insert(e);
            }
        }
        first_error.map_or(Ok(()), Err)
    }
}

impl<T: Transport> Drop for Automatic<T> {
    /// A session dropped before it ended (a panic in the caller, an early return): every
    /// torque off and every servo given back, as far as the line allows. A servo left in
    /// speed mode would turn into its stop until it cooked.
    fn drop(&mut self) {
        let _ = self.release(false);
    }
}

/// `Overload_Torque` for a torque limit of `permille`: the [`OVERLOAD_SHARE`] of it in whole
/// percent, if that lies above the stall rule's [`PUSHING_SHARE`] of it and below the limit
/// (a limit under 5 % leaves no such percent).
fn overload_percent(permille: u16) -> Option<i32> {
    let limit = f64::from(permille) / 10.0;
    let percent = (limit * OVERLOAD_SHARE).floor();
    let between = percent > limit * f64::from(PUSHING_SHARE) && percent < limit;
    between.then_some(percent as i32)
}

/// The press bound of a joint about to turn in speed mode ([`PRESS_BOUND`]'s registers); none
/// when its limit leaves no [`overload_percent`].
fn press_bound(j: &Joint) -> Option<[(reg::Register, i32); 4]> {
    let overload = overload_percent(j.plan.torque_permille)?;
    let unloading = j.unloading | i32::from(ServoStatus::OVERLOAD);
    let values = [overload, OVERLOAD_TIME, PROTECTIVE_PERCENT, unloading];
    Some(std::array::from_fn(|i| (PRESS_BOUND[i], values[i])))
}

/// What a joint's servo gets back for the press bound: the driver's overload protection (not
/// what it held: a session killed before left its own bound there) and the
/// `Unloading_Condition` it held.
fn press_unbound(j: &Joint) -> impl Iterator<Item = (reg::Register, i32)> {
    OVERLOAD_PROTECTION
        .into_iter()
        .chain([(reg::UNLOADING_CONDITION, j.unloading)])
}

fn no_press_bound(p: &PlannedSweep) -> SessionError {
    SessionError::NoPressBound {
        joint: p.target.joint.clone(),
        limit_percent: f64::from(p.torque_permille) / 10.0,
    }
}

/// The supervisor's stall rule over the calibration's window.
fn stall_config() -> supervisor::config::StallConfig {
    supervisor::config::StallConfig {
        window: WINDOW,
        current_fraction: 0.0,
        gripper_current_fraction: 0.0,
        static_rad: STILL_RAD,
        min_error_rad: 0.1,
        gripper_min_error_rad: 0.1,
        new_target_rad: 0.2,
        gripper_hold_percent: 0.0,
        reduced_percent: 0.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A push above the threshold either way (the load's sign is its direction) for
    /// [`STRAIN_S`] is a strain; four readings under it do not end the count, five do; at the
    /// threshold is not above it.
    #[test]
    fn a_strain_is_a_push_above_the_threshold_either_way_for_half_a_second() {
        // A reading every 1/64 s (exact in binary): STRAIN_S is 32 readings after the first.
        let period = 1.0 / 64.0;
        let after = (STRAIN_S / period) as usize;
        let run = |loads: &dyn Fn(usize) -> i32| {
            let mut watch = StrainWatch::default();
            (0..200).find(|&i| watch.strained(loads(i), 270, i as f64 * period))
        };
        for sign in [1, -1] {
            assert_eq!(run(&|_| sign * 271), Some(after), "sign {sign}");
            assert_eq!(run(&|_| sign * 270), None, "at the threshold, sign {sign}");
            // Four low readings in the middle: the count goes on from the first push.
            let gap4 = |i: usize| if (10..14).contains(&i) { 0 } else { sign * 300 };
            assert_eq!(run(&gap4), Some(after), "sign {sign}");
            // Five: it starts again after them.
            let gap5 = |i: usize| if (10..15).contains(&i) { 0 } else { sign * 300 };
            assert_eq!(run(&gap5), Some(15 + after), "sign {sign}");
        }
    }

    #[test]
    fn the_press_bound_lies_between_the_stall_rule_and_the_limit() {
        // The shipped plan's limits: 10, 15, 20, 30 and 35 %.
        let shipped = [(100, 9), (150, 13), (200, 18), (300, 27), (350, 31)];
        for (permille, percent) in shipped {
            assert_eq!(overload_percent(permille), Some(percent), "{permille} ‰");
        }
        // No whole percent strictly between 80 % of the limit and the limit.
        for permille in [0, 10, 40, 50, 55] {
            assert_eq!(overload_percent(permille), None, "{permille} ‰");
        }
        assert_eq!(overload_percent(60), Some(5));
    }
}
