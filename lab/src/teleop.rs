//! Teleoperation from a page, pure (time passed in): what the page asks (joint targets from its
//! sliders, a tool pose dragged in 3D) becomes goal frames on the driver's one goal path, under
//! these rules:
//!
//! - **Nothing the stack would refuse is sent**: a joint the driver does not have, a wheel, a
//!   value that is not finite or lies outside the joint's calibrated range (from the driver's
//!   layout: the range the driver clamps to) refuses the whole message, with its reason, and
//!   is counted; a tool pose is solved by [`body::Body::solve`] within those same ranges, and
//!   one out of reach is refused with how far the closest solution stays.
//! - **No jump**: each joint is taken from where it was read when it is first commanded, then
//!   moves toward its target at most `max_speed_rad_s`, and never more than `max_lead_rad`
//!   ahead of where it is read (a joint held back, or a servo that stopped answering, is not
//!   waited for by a goal running on); the goals go out every tick.
//! - **Dead-man**: one page controls at a time; it must be heard (any control message, or its
//!   `alive`) within `deadman_ms`, else the arm is held where it is read (one frame of the
//!   measured positions; grippers keep their grip) and nothing more is sent. A page whose
//!   connection closes is released at once.
//! - **The robot's safe state wins**: while the driver is in its safe state (an operator's stop,
//!   no supervisor) nothing is taken and everything commanded is dropped, so no target set
//!   before a recovery moves the arm after it. Every frame is watched, not only the newest: a
//!   safe state shorter than a tick, a driver that restarted (its frames numbered from the
//!   start again) or one silent for [`READ_MAX_AGE_NS`] drops everything as well, and nothing
//!   is sent to a driver that is not heard.
//!
//! The driver then applies its own checks (finite, age, calibration clamp) and the supervisor
//! watches the motors, as for every other source of goals.

use body::ik::{IkError, IkSettings, Mount, ToolTarget};
use body::kinematics::{Body, Pose2};
use std::collections::BTreeMap;
use telemetry::frames::{JointLayout, JointRole, STATE_FLAG_SAFE_STATE};
use telemetry::{GoalFrame, JointState, MAX_JOINTS};
use thiserror::Error;

/// A joint is started from a reading at most this old (a few of the driver's cycles: one
/// missed reply does not refuse the operator's move).
pub const READ_MAX_AGE_NS: u64 = 100_000_000;

/// How teleoperation behaves.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TeleopSettings {
    /// A controlling page silent this long is released, ms.
    pub deadman_ms: u64,
    /// Fastest a commanded joint moves toward its target, rad/s.
    pub max_speed_rad_s: f64,
    /// The inverse kinematics' tolerances and effort.
    pub ik: IkSettings,
    /// A pose the solver did not reach within its tolerances is still taken when its closest
    /// solution is this close, m (the operator steers by eye: a tenth of a millimetre short at
    /// a range's end is no reason to stop the arm) ...
    pub accept_position_m: f64,
    /// ... and turned this little, rad.
    pub accept_angle_rad: f64,
    /// The farthest a goal runs ahead of where its joint is read, rad (beyond the firmware
    /// loop's error under the arm's weight, under 0.15 rad, where the supervisor deems it
    /// saturated).
    pub max_lead_rad: f64,
}

impl Default for TeleopSettings {
    fn default() -> Self {
        TeleopSettings {
            deadman_ms: 300,
            max_speed_rad_s: 1.5,
            ik: IkSettings::default(),
            accept_position_m: 1e-3,
            accept_angle_rad: 1f64.to_radians(),
            max_lead_rad: 0.2,
        }
    }
}

/// What a page asks of the arms.
#[derive(Debug, Clone, PartialEq)]
pub enum Command {
    /// Joint targets by name, rad.
    Joints(BTreeMap<String, f64>),
    /// An arm's tool (named by its bus, `left_arm`) to a pose in the base's frame.
    Tool {
        /// The arm's bus name.
        arm: String,
        /// The target.
        target: ToolTarget,
    },
    /// The controlling page is still there (sent while its operator holds control).
    Alive,
    /// The page lets go: the arm is held where it is.
    Release,
}

/// Why a command was not taken.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum Refusal {
    /// The driver is in its safe state.
    #[error("the robot is in its safe state (stopped, or no supervisor): nothing is taken")]
    SafeState,
    /// No joint state or layout yet.
    #[error("the driver's layout and state are not known yet")]
    NotReady,
    /// The driver's newest frame is too old.
    #[error("the driver is not heard (no joint state for 100 ms): nothing is taken")]
    DriverSilent,
    /// Sent before the driver's last safe state, restart or silence, or before an operator's
    /// stop pressed on a page (it waited in the lab's queue across it).
    #[error("sent before the driver's last safe state, restart or an operator's stop: not taken")]
    BeforeInterruption,
    /// A stop was pressed and the supervisor has not yet answered it.
    #[error("a stop was pressed and is not answered yet: nothing is taken")]
    Stopping,
    /// Another page controls the robot.
    #[error("another page controls the robot")]
    OtherPage,
    /// No such joint in the driver's layout.
    #[error("no joint {0:?} in the driver's layout")]
    UnknownJoint(String),
    /// A wheel takes speeds, not targets.
    #[error("{0:?} is a wheel: the base takes velocities, not targets")]
    Wheel(String),
    /// Not a finite number.
    #[error("{0}: not a finite number")]
    NotFinite(String),
    /// Outside the calibrated range.
    #[error("{joint} = {value:.4} rad is outside its calibrated range [{low:.4}, {high:.4}]")]
    OutOfRange {
        /// The joint.
        joint: String,
        /// What was asked.
        value: f64,
        /// The range.
        low: f64,
        /// The range.
        high: f64,
    },
    /// A joint to command was not read validly lately.
    #[error("{0} was not read in the last 100 ms: it is not moved from a guess")]
    NotRead(String),
    /// No such arm.
    #[error("no arm {0:?} (the body's arms are named by their buses)")]
    UnknownArm(String),
    /// The tool pose cannot be reached within the calibrated ranges.
    #[error("out of reach: the closest pose is {position_error_m:.4} m and {angle_error_rad:.3} rad away")]
    Unreachable {
        /// m.
        position_error_m: f64,
        /// rad.
        angle_error_rad: f64,
    },
    /// The pose is not a finite position and a non-zero quaternion.
    #[error("the tool pose is not a finite position and rotation")]
    BadPose,
}

impl Refusal {
    /// A short name for counting.
    pub fn kind(&self) -> &'static str {
        match self {
            Refusal::SafeState => "safe_state",
            Refusal::NotReady => "not_ready",
            Refusal::DriverSilent => "driver_silent",
            Refusal::BeforeInterruption => "before_interruption",
            Refusal::Stopping => "stopping",
            Refusal::OtherPage => "other_page",
            Refusal::UnknownJoint(_) => "unknown_joint",
            Refusal::Wheel(_) => "wheel",
            Refusal::NotFinite(_) => "not_finite",
            Refusal::OutOfRange { .. } => "out_of_range",
            Refusal::NotRead(_) => "not_read",
            Refusal::UnknownArm(_) => "unknown_arm",
            Refusal::Unreachable { .. } => "unreachable",
            Refusal::BadPose => "bad_pose",
        }
    }
}

/// What a taken tool command solved to.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Solved {
    /// m.
    pub position_error_m: f64,
    /// rad.
    pub angle_error_rad: f64,
    /// Starts the solver needed (1: from where the arm is commanded).
    pub starts: usize,
}

/// Why teleoperation ended by itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ended {
    /// The controlling page was not heard within the dead-man bound.
    DeadMan,
    /// Its connection closed.
    PageClosed,
    /// The page let go.
    Released,
    /// The driver entered its safe state.
    SafeState,
    /// The driver restarted (its frames numbered from the start again).
    DriverRestarted,
    /// No frame of the driver within [`READ_MAX_AGE_NS`].
    DriverSilent,
}

impl Ended {
    /// Its name, for the log and the page.
    pub fn name(self) -> &'static str {
        match self {
            Ended::DeadMan => "dead_man",
            Ended::PageClosed => "page_closed",
            Ended::Released => "released",
            Ended::SafeState => "safe_state",
            Ended::DriverRestarted => "driver_restarted",
            Ended::DriverSilent => "driver_silent",
        }
    }
}

impl serde::Serialize for Ended {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

/// Counts, for the page and the log.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct TeleopCounters {
    /// Commands taken.
    pub taken: u64,
    /// Commands refused, by [`Refusal::kind`].
    pub refused: BTreeMap<&'static str, u64>,
    /// Teleoperation ended by the dead-man bound.
    pub deadman_releases: u64,
    /// ... by the page's connection closing.
    pub closed_releases: u64,
    /// ... by the driver's safe state, restart or silence.
    pub safe_state_releases: u64,
    /// Goal frames produced.
    pub frames: u64,
}

#[derive(Debug, Clone, Copy)]
struct Owner {
    page: u64,
    heard_ns: u64,
}

/// One arm of the body on the driver's layout.
#[derive(Debug, Clone)]
struct Arm {
    /// Its index among the body's arms.
    index: usize,
    bus: String,
    /// Frame index of each chain joint, base outward.
    joints: Vec<usize>,
    /// Calibrated ranges within the hard stops, base outward.
    limits: Vec<(f64, f64)>,
}

/// The teleoperation state.
pub struct Teleop {
    body: Body,
    settings: TeleopSettings,
    layout: JointLayout,
    arms: Vec<Arm>,
    owner: Option<Owner>,
    /// Bit `i`: joint `i` is commanded.
    active: u32,
    target: [f64; MAX_JOINTS],
    commanded: [f64; MAX_JOINTS],
    last_tick_ns: Option<u64>,
    /// Each joint's last valid reading: position, rad, and when (ns), from [`Teleop::observe`].
    read: [Option<(f64, u64)>; MAX_JOINTS],
    /// The lift's height the arms are solved at, m.
    lift_m: f64,
    /// The hold frame owed once teleoperation ends (sent at the next tick).
    hold: Option<Ended>,
    /// The driver's newest frame number, a safe state or restart seen since the last tick, and
    /// when the last one was (its frame's time, or the tick that found the driver silent):
    /// nothing that arrived before it is taken.
    driver_seq: Option<u64>,
    interrupted: Option<Ended>,
    interrupted_ns: Option<u64>,
    seq: u64,
    counters: TeleopCounters,
}

impl Teleop {
    /// Teleoperation of `body`'s arms as the driver's `layout` names and limits them. An arm
    /// some of whose joints the driver does not drive cannot be teleoperated in Cartesian
    /// space (its joints still by sliders).
    pub fn new(body: Body, layout: JointLayout, settings: TeleopSettings) -> Teleop {
        let arms = body
            .arms()
            .iter()
            .enumerate()
            .filter_map(|(index, chain)| {
                let joints: Option<Vec<usize>> = chain
                    .joint_names
                    .iter()
                    .map(|n| layout.joint_index(n))
                    .collect();
                let joints = joints?;
                let limits = joints
                    .iter()
                    .zip(chain.hard_stops())
                    .map(|(&j, (lo, hi))| {
                        let [a, b] = layout.joints()[j].range_rad;
                        (f64::from(a).max(lo), f64::from(b).min(hi))
                    })
                    .collect();
                Some(Arm {
                    index,
                    bus: chain.bus.clone(),
                    joints,
                    limits,
                })
            })
            .collect();
        let lift_m = body.lift_start_m();
        Teleop {
            body,
            settings,
            layout,
            arms,
            owner: None,
            active: 0,
            target: [0.0; MAX_JOINTS],
            commanded: [0.0; MAX_JOINTS],
            last_tick_ns: None,
            read: [None; MAX_JOINTS],
            lift_m,
            hold: None,
            driver_seq: None,
            interrupted: None,
            interrupted_ns: None,
            seq: 0,
            counters: TeleopCounters::default(),
        }
    }

    /// The lift's height now, m: tool poses are in the base's frame, solved with the shoulders
    /// where the lift carries them.
    pub fn set_lift_m(&mut self, lift_m: f64) {
        if lift_m.is_finite() {
            self.lift_m = lift_m;
        }
    }

    /// Takes a joint-state frame's valid readings (every frame, as they come: a joint missed in
    /// the newest frame still has a recent reading to start from).
    pub fn observe(&mut self, state: &JointState) {
        if state.joint_count != self.layout.joint_count {
            return;
        }
        // The same frame seen again (a command's newest) is not a restart.
        if self.driver_seq.is_some_and(|s| state.seq < s) {
            self.interrupt(Ended::DriverRestarted, state.timestamp_ns);
        }
        if state.flags & STATE_FLAG_SAFE_STATE != 0 {
            self.interrupt(Ended::SafeState, state.timestamp_ns);
        }
        self.driver_seq = Some(state.seq);
        for (i, j) in state.joints().iter().enumerate() {
            if j.is_valid() {
                self.read[i] = Some((f64::from(j.position_rad), state.timestamp_ns));
            }
        }
    }

    /// The driver interrupted (`why`) at `at_ns`: everything commanded is dropped at the next
    /// tick, and nothing that arrived before is taken.
    fn interrupt(&mut self, why: Ended, at_ns: u64) {
        self.interrupted = Some(why);
        self.interrupted_ns = Some(self.interrupted_ns.map_or(at_ns, |t| t.max(at_ns)));
    }

    /// Joint `i`'s position read within [`READ_MAX_AGE_NS`] before the frame stamped
    /// `newest_ns` (the driver's clock).
    fn recent_read(&self, i: usize, newest_ns: u64) -> Option<f64> {
        let (position, at) = self.read[i]?;
        (newest_ns.saturating_sub(at) <= READ_MAX_AGE_NS).then_some(position)
    }

    /// The layout this teleoperation was made for.
    pub fn layout(&self) -> &JointLayout {
        &self.layout
    }

    /// The counts so far.
    pub fn counters(&self) -> &TeleopCounters {
        &self.counters
    }

    /// The page in control, if one is.
    pub fn owner(&self) -> Option<u64> {
        self.owner.map(|o| o.page)
    }

    /// Joints commanded now (bit per frame index).
    pub fn active(&self) -> u32 {
        self.active
    }

    /// The goal last commanded to joint `i` (meaningful while it is active).
    pub fn commanded(&self, i: usize) -> Option<f64> {
        (self.active & (1 << i) != 0).then(|| self.commanded[i])
    }

    /// Page `page`'s command at `now_ns`, against the newest joint state.
    pub fn command(
        &mut self,
        page: u64,
        command: &Command,
        state: Option<&JointState>,
        now_ns: u64,
    ) -> Result<Option<Solved>, Refusal> {
        let result = self.take(page, command, state, now_ns);
        match &result {
            Ok(_) => self.counters.taken += 1,
            Err(r) => *self.counters.refused.entry(r.kind()).or_default() += 1,
        }
        result
    }

    fn take(
        &mut self,
        page: u64,
        command: &Command,
        state: Option<&JointState>,
        now_ns: u64,
    ) -> Result<Option<Solved>, Refusal> {
        let deadman_ns = self.settings.deadman_ms * 1_000_000;
        let owner_alive = self
            .owner
            .is_some_and(|o| now_ns.saturating_sub(o.heard_ns) <= deadman_ns);
        if owner_alive && self.owner.is_some_and(|o| o.page != page) {
            return Err(Refusal::OtherPage);
        }
        match command {
            Command::Alive => {
                if let Some(o) = self.owner.as_mut().filter(|o| o.page == page) {
                    o.heard_ns = now_ns;
                }
                return Ok(None);
            }
            Command::Release => {
                if self.owner.is_some_and(|o| o.page == page) {
                    self.end(Ended::Released);
                }
                return Ok(None);
            }
            _ => {}
        }
        let state = state
            .filter(|s| s.joint_count == self.layout.joint_count)
            .ok_or(Refusal::NotReady)?;
        if state.flags & STATE_FLAG_SAFE_STATE != 0 {
            return Err(Refusal::SafeState);
        }
        if now_ns.saturating_sub(state.timestamp_ns) > READ_MAX_AGE_NS {
            return Err(Refusal::DriverSilent);
        }
        self.observe(state);
        if self.interrupted_ns.is_some_and(|t| now_ns <= t) {
            return Err(Refusal::BeforeInterruption);
        }
        let (goals, solved) = match command {
            Command::Joints(by_name) => (self.check_joints(by_name)?, None),
            Command::Tool { arm, target } => {
                let (goals, solved) = self.solve(arm, target, state)?;
                (goals, Some(solved))
            }
            Command::Alive | Command::Release => return Ok(None),
        };
        // Every joint newly commanded starts from where it was read recently: refused whole if
        // one was not.
        let mut start = [0.0; MAX_JOINTS];
        for &(i, _) in &goals {
            if self.active & (1 << i) == 0 {
                start[i] = self
                    .recent_read(i, state.timestamp_ns)
                    .ok_or_else(|| Refusal::NotRead(self.layout.joints()[i].name().to_string()))?;
            }
        }
        for &(i, v) in &goals {
            if self.active & (1 << i) == 0 {
                let [lo, hi] = self.layout.joints()[i].range_rad.map(f64::from);
                self.commanded[i] = start[i].clamp(lo, hi);
                self.active |= 1 << i;
            }
            self.target[i] = v;
        }
        self.hold = None;
        self.owner = Some(Owner {
            page,
            heard_ns: now_ns,
        });
        Ok(solved)
    }

    /// Joint targets checked against the layout: every one known, not a wheel, finite and
    /// within its calibrated range.
    fn check_joints(&self, by_name: &BTreeMap<String, f64>) -> Result<Vec<(usize, f64)>, Refusal> {
        by_name
            .iter()
            .map(|(name, &v)| {
                let i = self
                    .layout
                    .joint_index(name)
                    .ok_or_else(|| Refusal::UnknownJoint(name.clone()))?;
                let info = &self.layout.joints()[i];
                if info.role() == JointRole::Wheel {
                    return Err(Refusal::Wheel(name.clone()));
                }
                if !v.is_finite() {
                    return Err(Refusal::NotFinite(name.clone()));
                }
                let [lo, hi] = info.range_rad.map(f64::from);
                if v < lo || v > hi {
                    return Err(Refusal::OutOfRange {
                        joint: name.clone(),
                        value: v,
                        low: lo,
                        high: hi,
                    });
                }
                Ok((i, v))
            })
            .collect()
    }

    /// The arm's joint targets that put its tool at `target`, solved from where the arm is
    /// commanded (or read, for joints not commanded).
    fn solve(
        &self,
        arm: &str,
        target: &ToolTarget,
        state: &JointState,
    ) -> Result<(Vec<(usize, f64)>, Solved), Refusal> {
        let a = self
            .arms
            .iter()
            .find(|a| a.bus == arm)
            .ok_or_else(|| Refusal::UnknownArm(arm.to_string()))?;
        let mut seed = [0.0; MAX_JOINTS];
        for (k, &j) in a.joints.iter().enumerate() {
            let read = self
                .recent_read(j, state.timestamp_ns)
                .unwrap_or(f64::from(state.joints()[j].position_rad));
            let (lo, hi) = a.limits[k];
            seed[k] = self.commanded(j).unwrap_or(read).clamp(lo, hi);
        }
        let mount = Mount {
            lift_m: self.lift_m,
            base: Pose2::default(),
        };
        let n = a.joints.len();
        match self.body.solve(
            a.index,
            target,
            &seed[..n],
            &a.limits,
            mount,
            &self.settings.ik,
        ) {
            Ok(s) => Ok((
                a.joints
                    .iter()
                    .enumerate()
                    .map(|(k, &j)| (j, s.q[k]))
                    .collect(),
                Solved {
                    position_error_m: s.position_error_m,
                    angle_error_rad: s.angle_error_rad,
                    starts: s.starts,
                },
            )),
            Err(IkError::NotReached {
                best,
                position_error_m,
                angle_error_rad,
            }) if position_error_m <= self.settings.accept_position_m
                && angle_error_rad <= self.settings.accept_angle_rad =>
            {
                Ok((
                    a.joints
                        .iter()
                        .enumerate()
                        .map(|(k, &j)| (j, best[k]))
                        .collect(),
                    Solved {
                        position_error_m,
                        angle_error_rad,
                        starts: self.settings.ik.max_starts,
                    },
                ))
            }
            Err(IkError::NotReached {
                position_error_m,
                angle_error_rad,
                ..
            }) => Err(Refusal::Unreachable {
                position_error_m,
                angle_error_rad,
            }),
            // A target that is not a finite position and a non-zero quaternion (the solver's
            // own check).
            Err(_) => Err(Refusal::BadPose),
        }
    }

    /// Page `page`'s connection closed: if it controlled, the arm is held where it is at the
    /// next tick.
    pub fn page_closed(&mut self, page: u64) {
        if self.owner.is_some_and(|o| o.page == page) {
            self.end(Ended::PageClosed);
        }
    }

    /// Ends teleoperation, whichever page controls: the arm is held where it is at the next
    /// tick (the stop button, pressed on any page at `at_ns`). A command sent at or before the
    /// press is refused as sent before an interruption, wherever it waited.
    pub fn let_go(&mut self, at_ns: u64) {
        self.end(Ended::Released);
        self.interrupted_ns = Some(self.interrupted_ns.map_or(at_ns, |t| t.max(at_ns)));
    }

    fn end(&mut self, why: Ended) {
        self.owner = None;
        if self.active != 0 {
            self.hold = Some(why);
        }
    }

    /// One tick at `now_ns`: the goal frame to publish, if any, and why teleoperation ended if
    /// it did in this tick.
    pub fn tick(
        &mut self,
        state: Option<&JointState>,
        now_ns: u64,
    ) -> (Option<GoalFrame>, Option<Ended>) {
        let dt = self
            .last_tick_ns
            .map_or(0.0, |t| now_ns.saturating_sub(t) as f64 * 1e-9)
            .min(0.05);
        self.last_tick_ns = Some(now_ns);
        if self.active == 0 {
            self.interrupted = None;
            return (None, None);
        }
        let Some(state) = state.filter(|s| s.joint_count == self.layout.joint_count) else {
            return (None, None);
        };
        self.observe(state);
        if now_ns.saturating_sub(state.timestamp_ns) > READ_MAX_AGE_NS {
            self.interrupt(Ended::DriverSilent, now_ns);
        }
        if let Some(why) = self.interrupted.take() {
            // The driver holds the robot itself, or is not there to be told: nothing
            // commanded before survives it.
            self.owner = None;
            self.active = 0;
            self.hold = None;
            self.counters.safe_state_releases += 1;
            return (None, Some(why));
        }
        let deadman_ns = self.settings.deadman_ms * 1_000_000;
        if let Some(o) = self.owner {
            if now_ns.saturating_sub(o.heard_ns) > deadman_ns {
                self.end(Ended::DeadMan);
            }
        }
        if let Some(why) = self.hold.take() {
            match why {
                Ended::DeadMan => self.counters.deadman_releases += 1,
                Ended::PageClosed => self.counters.closed_releases += 1,
                _ => {}
            }
            let frame = self.hold_frame(state, now_ns);
            self.active = 0;
            return (Some(frame), Some(why));
        }
        let (step, lead) = (
            self.settings.max_speed_rad_s * dt,
            self.settings.max_lead_rad,
        );
        let mut frame = self.frame(now_ns);
        for (i, info) in self.layout.joints().iter().enumerate() {
            if self.active & (1 << i) == 0 {
                continue;
            }
            // Toward the target, an arm joint never further ahead of where it is read than the
            // lead (a gripper's goal beyond its reading is its grip); a joint not read lately
            // keeps its goal.
            if let Some(read) = self.recent_read(i, state.timestamp_ns) {
                let d = (self.target[i] - self.commanded[i]).clamp(-step, step);
                self.commanded[i] += d;
                if info.role() == JointRole::Joint {
                    self.commanded[i] = self.commanded[i].clamp(read - lead, read + lead);
                }
                // The range over the lead: a joint read beyond its end is sent back into it.
                let [lo, hi] = info.range_rad.map(f64::from);
                self.commanded[i] = self.commanded[i].clamp(lo, hi);
            }
            frame.position_rad[i] = self.commanded[i] as f32;
        }
        frame.mask = self.active;
        self.counters.frames += 1;
        (Some(frame), None)
    }

    /// The frame that ends teleoperation: every commanded arm joint held where it was read
    /// (within its range); a gripper keeps its commanded grip (opening it would drop what it
    /// holds); a joint not read keeps its commanded goal.
    fn hold_frame(&mut self, state: &JointState, now_ns: u64) -> GoalFrame {
        let mut frame = self.frame(now_ns);
        for (i, info) in self.layout.joints().iter().enumerate() {
            if self.active & (1 << i) == 0 {
                continue;
            }
            let read = state.joints()[i];
            if info.role() == JointRole::Joint && read.is_valid() {
                let [lo, hi] = info.range_rad.map(f64::from);
                self.commanded[i] = f64::from(read.position_rad).clamp(lo, hi);
            }
            frame.position_rad[i] = self.commanded[i] as f32;
        }
        frame.mask = self.active;
        self.counters.frames += 1;
        frame
    }

    fn frame(&mut self, now_ns: u64) -> GoalFrame {
        self.seq += 1;
        GoalFrame {
            seq: self.seq,
            timestamp_ns: now_ns,
            joint_count: self.layout.joint_count,
            ..GoalFrame::default()
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use body::RobotDescription;
    use telemetry::frames::JointInfo;

    use telemetry::clock::MS;

    /// The A3's left arm as a driver on its bus alone lays it out: its seven joints (ranges
    /// 0.05 rad inside the hard stops) and the gripper.
    pub(crate) fn a3_left_layout() -> JointLayout {
        let body = Body::from_description(&RobotDescription::nori_a3()).unwrap();
        let chain = &body.arms()[0];
        let mut l = JointLayout {
            joint_count: 8,
            bus_count: 1,
            ..JointLayout::default()
        };
        l.set_bus_name(0, "left_arm");
        for (i, (name, (lo, hi))) in chain.joint_names.iter().zip(chain.hard_stops()).enumerate() {
            let mut info = JointInfo {
                id: i as u8 + 1,
                max_temperature_c: 60,
                range_rad: [(lo + 0.05) as f32, (hi - 0.05) as f32],
                ..JointInfo::default()
            };
            info.set_name(name);
            l.joints[i] = info;
        }
        let mut gripper = JointInfo {
            id: 8,
            role: JointRole::Gripper as u8,
            max_temperature_c: 60,
            range_rad: [0.0, 1.2],
            ..JointInfo::default()
        };
        gripper.set_name("left_gripper");
        l.joints[7] = gripper;
        l
    }

    fn teleop() -> Teleop {
        let body = Body::from_description(&RobotDescription::nori_a3()).unwrap();
        Teleop::new(body, a3_left_layout(), TeleopSettings::default())
    }

    /// A frame with every joint read at `q` (the gripper at 0.6).
    fn state_at(q: &[f64]) -> JointState {
        let mut s = JointState {
            joint_count: 8,
            ..JointState::default()
        };
        for (i, j) in s.joints[..8].iter_mut().enumerate() {
            j.valid = 1;
            j.position_rad = q.get(i).copied().unwrap_or(0.6) as f32;
        }
        s
    }

    /// Where the left arm stands in the tests, and where they send its tool.
    const HERE: [f64; 7] = [0.1, 0.2, -0.1, -0.8, 0.1, 0.3, 0.0];
    const WANT: [f64; 7] = [0.3, 0.35, -0.2, -1.2, 0.3, 0.1, 0.2];

    /// The left arm's tool to where angles `q` put it with the lift at `lift_m`; that pose.
    fn tool_to(body: &Body, q: &[f64], lift_m: f64) -> (Command, body::kinematics::ArmPose) {
        let pose = body.arm_pose(0, q, lift_m, Pose2::default()).unwrap();
        let target = ToolTarget {
            position: pose.tool,
            rotation: pose.tool_rotation,
        };
        let tool = Command::Tool {
            arm: "left_arm".into(),
            target,
        };
        (tool, pose)
    }

    fn joints(goals: &[(&str, f64)]) -> Command {
        Command::Joints(goals.iter().map(|(n, v)| (n.to_string(), *v)).collect())
    }

    #[test]
    fn a_bad_joint_message_is_refused_whole_and_counted_and_moves_nothing() {
        let mut t = teleop();
        let s = state_at(&[0.0; 7]);
        let range = t.layout().joints()[3].range_rad;
        for (bad, kind) in [
            (
                joints(&[("left_elbow", -0.5), ("left_knee", 0.0)]),
                "unknown_joint",
            ),
            (joints(&[("left_elbow", f64::NAN)]), "not_finite"),
            (
                joints(&[("left_elbow", f64::from(range[0]) - 0.01)]),
                "out_of_range",
            ),
            (
                joints(&[("left_elbow", -0.5), ("left_gripper", 1.3)]),
                "out_of_range",
            ),
        ] {
            assert_eq!(
                t.command(1, &bad, Some(&at(&s, 0)), 0).unwrap_err().kind(),
                kind
            );
        }
        assert_eq!(t.counters().refused.values().sum::<u64>(), 4);
        assert_eq!(t.active(), 0);
        assert_eq!(t.tick(Some(&at(&s, MS)), MS), (None, None), "nothing sent");
        // Not ready: no state, or one of another layout.
        let other = JointState {
            joint_count: 19,
            ..s
        };
        let ok = joints(&[("left_elbow", -0.5)]);
        assert_eq!(t.command(1, &ok, Some(&other), 0), Err(Refusal::NotReady));
        assert_eq!(t.command(1, &ok, None, 0), Err(Refusal::NotReady));
        // A joint not read lately is not moved from a guess; one missed in the newest frame
        // only starts from its reading of a moment before.
        let mut fresh = teleop();
        let mut unread = s;
        unread.joints[3].valid = 0;
        unread.timestamp_ns = 50 * MS;
        assert_eq!(
            fresh.command(1, &ok, Some(&unread), 0),
            Err(Refusal::NotRead("left_elbow".into())),
            "never read"
        );
        let mut read = s;
        read.joints[3].position_rad = -0.3;
        read.timestamp_ns = 10 * MS;
        fresh.observe(&read);
        unread.timestamp_ns = 200 * MS;
        assert_eq!(
            fresh.command(1, &ok, Some(&unread), 0),
            Err(Refusal::NotRead("left_elbow".into())),
            "read 190 ms before"
        );
        unread.timestamp_ns = 60 * MS;
        fresh.command(1, &ok, Some(&unread), 0).unwrap();
        assert_eq!(
            fresh.commanded(3),
            Some(f64::from(-0.3f32)),
            "from the reading 50 ms before"
        );
    }

    #[test]
    fn a_taken_target_is_approached_from_where_the_joint_was_read_at_the_bounded_speed() {
        let mut t = teleop();
        let s = state_at(&[0.0, 0.0, 0.0, -0.2, 0.0, 0.0, 0.0]);
        t.command(1, &joints(&[("left_elbow", -1.0)]), Some(&at(&s, 0)), 0)
            .unwrap();
        let mut last = -0.2;
        let mut now = 0;
        for k in 0..100 {
            // The page keeps control.
            let f = followed(&t, &s, now);
            t.command(1, &Command::Alive, Some(&f), now).unwrap();
            let (frame, ended) = t.tick(Some(&f), now);
            assert_eq!(ended, None);
            let f = frame.unwrap();
            assert_eq!((f.mask, f.joint_count), (1 << 3, 8));
            let g = f64::from(f.position_rad[3]);
            let step = if k == 0 { 0.0 } else { 1.5 * 0.01 };
            assert!(
                (last - g) <= step + 1e-6 && g <= last + 1e-9,
                "tick {k}: {last} → {g}"
            );
            last = g;
            now += 10 * MS;
        }
        assert!((last + 1.0).abs() < 1e-6, "reached: {last}");
        assert_eq!(t.counters().frames, 100);
    }

    #[test]
    fn a_range_end_is_in_range_and_frames_carry_fresh_stamps_and_rising_numbers() {
        let mut t = teleop();
        let s = state_at(&[0.0; 7]);
        let [lo, hi] = t.layout().joints()[3].range_rad.map(f64::from);
        t.command(1, &joints(&[("left_elbow", lo)]), Some(&at(&s, 0)), 0)
            .unwrap();
        t.command(1, &joints(&[("left_elbow", hi)]), Some(&at(&s, 0)), 0)
            .unwrap();
        assert_eq!(t.counters().taken, 2);
        assert_eq!(t.commanded(2), None, "a joint not commanded has no goal");
        let mut seq = 0;
        for k in 1..=3u64 {
            let f = t.tick(Some(&at(&s, k * 7 * MS)), k * 7 * MS).0.unwrap();
            assert_eq!(
                f.timestamp_ns,
                k * 7 * MS,
                "stamped now: the driver refuses old goals"
            );
            assert!(f.seq > seq);
            seq = f.seq;
        }
        t.command(1, &Command::Release, Some(&at(&s, 30 * MS)), 30 * MS)
            .unwrap();
        let (f, ended) = t.tick(Some(&at(&s, 40 * MS)), 40 * MS);
        let f = f.unwrap();
        assert_eq!(ended, Some(Ended::Released), "the owner lets go");
        assert_eq!((f.timestamp_ns, f.seq > seq), (40 * MS, true));
        assert_eq!(t.counters().frames, 4);
    }

    #[test]
    fn a_joint_already_commanded_goes_on_from_its_goal_not_from_its_reading() {
        let mut t = teleop();
        // The reading lags (the servo has not moved yet).
        let s = state_at(&[0.0, 0.0, 0.0, -0.2, 0.0, 0.0, 0.0]);
        t.command(1, &joints(&[("left_elbow", -1.0)]), Some(&at(&s, 0)), 0)
            .unwrap();
        for k in 0..20 {
            t.command(1, &Command::Alive, Some(&at(&s, k * 10 * MS)), k * 10 * MS)
                .unwrap();
            t.tick(Some(&at(&s, k * 10 * MS)), k * 10 * MS);
        }
        // As far ahead of the reading as the lead lets it.
        let goal = t.commanded(3).unwrap();
        assert!((goal + 0.2 + 0.2).abs() < 1e-6, "{goal}");
        // A new target: the goal goes on from where it was (one step of 20 ms at 1.5 rad/s), no
        // jump back to the reading.
        t.command(
            1,
            &joints(&[("left_elbow", -1.1)]),
            Some(&at(&s, 200 * MS)),
            200 * MS,
        )
        .unwrap();
        let f = t.tick(Some(&at(&s, 210 * MS)), 210 * MS).0.unwrap();
        assert!(
            (f64::from(f.position_rad[3]) - goal).abs() <= 1.5 * 0.02 + 1e-6,
            "{} from {goal}",
            f.position_rad[3]
        );
    }

    /// The driver silent for exactly the bound is still heard; a nanosecond more is silence:
    /// a command is refused, and what is commanded is dropped at the next tick (found by the
    /// mutation pass: no test stood at the bound).
    #[test]
    fn the_drivers_silence_is_judged_at_its_bound() {
        let s = state_at(&HERE);
        let mut t = teleop();
        let seen = at(&s, 0);
        assert!(t
            .command(
                1,
                &joints(&[("left_elbow", -1.0)]),
                Some(&seen),
                READ_MAX_AGE_NS
            )
            .is_ok());
        let (frame, ended) = t.tick(Some(&seen), READ_MAX_AGE_NS);
        assert!(frame.is_some() && ended.is_none());
        assert_eq!(
            t.command(
                1,
                &joints(&[("left_elbow", -1.1)]),
                Some(&seen),
                READ_MAX_AGE_NS + 1
            ),
            Err(Refusal::DriverSilent)
        );
        let (_, ended) = t.tick(Some(&seen), READ_MAX_AGE_NS + 1);
        assert_eq!(ended, Some(Ended::DriverSilent));
    }

    /// A joint already commanded takes a new target even when its own reading is missing from
    /// the newest frames (a joint not read goes on from its goal; only a joint newly commanded
    /// needs a recent reading).
    #[test]
    fn a_joint_already_commanded_takes_a_new_target_while_unread() {
        let s = state_at(&HERE);
        let mut t = teleop();
        t.command(1, &joints(&[("left_elbow", -1.0)]), Some(&at(&s, 0)), 0)
            .unwrap();
        t.tick(Some(&at(&s, 0)), 0);
        let mut unread = at(&s, 150 * MS);
        unread.joints[3].valid = 0;
        t.observe(&unread);
        assert!(t
            .command(1, &joints(&[("left_elbow", -1.1)]), Some(&unread), 150 * MS)
            .is_ok());
        // Newly commanded and unread: refused, naming it.
        let wrist = t.layout().joints()[6].name().to_string();
        let mut u = at(&s, 300 * MS);
        u.joints[3].valid = 0;
        u.joints[6].valid = 0;
        t.observe(&u);
        assert_eq!(
            t.command(
                1,
                &joints(&[("left_elbow", -1.1), (&wrist, 0.1)]),
                Some(&u),
                300 * MS
            ),
            Err(Refusal::NotRead(wrist.clone()))
        );
    }

    /// A joint read beyond its range's end (pushed there, or sagging in a hold) is commanded
    /// within its range from the first frame: the lead toward its reading never carries a
    /// goal out of the range. (Seen in the body's chaos run: one goal on the wire outside its
    /// joint's range.)
    #[test]
    fn a_joint_read_beyond_its_range_is_never_commanded_beyond_it() {
        let [lo, hi] = teleop().layout().joints()[3].range_rad.map(f64::from);
        for (read, target) in [(hi + 0.3, hi - 0.1), (lo - 0.3, lo + 0.1), (hi + 0.01, hi)] {
            let mut t2 = teleop();
            let mut q = [0.0; 7];
            q[3] = read;
            let s = state_at(&q);
            t2.command(1, &joints(&[("left_elbow", target)]), Some(&at(&s, 0)), 0)
                .unwrap();
            for k in 0..10 {
                let now = k * 20 * MS;
                t2.command(1, &Command::Alive, Some(&at(&s, now)), now)
                    .unwrap();
                let g = f64::from(t2.tick(Some(&at(&s, now)), now).0.unwrap().position_rad[3]);
                assert!(
                    (lo - 1e-6..=hi + 1e-6).contains(&g),
                    "read {read}, goal {g} outside [{lo}, {hi}]"
                );
            }
        }
    }

    #[test]
    fn tool_poses_are_solved_where_the_lift_carries_the_shoulders() {
        let body = Body::from_description(&RobotDescription::nori_a3()).unwrap();
        let raised = body.lift_start_m() + 0.2;
        let (tool, pose) = tool_to(&body, &WANT, raised);
        let s = state_at(&HERE);
        let mut t = teleop();
        t.set_lift_m(raised);
        t.command(1, &tool, Some(&at(&s, 0)), 0).unwrap();
        let mut f = None;
        for k in 0..300 {
            let now = k * 10 * MS;
            let read = followed(&t, &s, now);
            t.command(1, &Command::Alive, Some(&read), now).unwrap();
            f = t.tick(Some(&read), now).0;
        }
        let q: Vec<f64> = (0..7)
            .map(|i| f64::from(f.unwrap().position_rad[i]))
            .collect();
        let at = body.arm_pose(0, &q, raised, Pose2::default()).unwrap().tool;
        let d: f64 = (0..3)
            .map(|i| (at[i] - pose.tool[i]).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(d < 1e-3, "{d} m off with the lift raised 0.2 m");
    }

    #[test]
    fn a_tool_pose_is_solved_within_the_ranges_and_one_out_of_reach_is_refused() {
        let mut t = teleop();
        let body = Body::from_description(&RobotDescription::nori_a3()).unwrap();
        let s = state_at(&HERE);
        let lift = body.lift_start_m();
        let (tool, pose) = tool_to(&body, &WANT, lift);
        let Command::Tool { target, .. } = tool.clone() else {
            unreachable!()
        };
        let solved = t.command(1, &tool, Some(&at(&s, 0)), 0).unwrap().unwrap();
        assert!(solved.position_error_m < 1e-3 && solved.angle_error_rad < 1e-2);
        // Ticks until every joint got there (well within 3 s at 1.5 rad/s).
        let mut frame = None;
        for k in 0..300 {
            let now = k * 10 * MS;
            let read = followed(&t, &s, now);
            t.command(1, &Command::Alive, Some(&read), now).unwrap();
            frame = t.tick(Some(&read), now).0;
        }
        let f = frame.unwrap();
        assert_eq!(f.mask, 0x7f, "the seven joints, not the gripper");
        let q: Vec<f64> = (0..7).map(|i| f64::from(f.position_rad[i])).collect();
        let reached = body.arm_pose(0, &q, lift, Pose2::default()).unwrap();
        let d: f64 = (0..3)
            .map(|i| (reached.tool[i] - pose.tool[i]).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(d < 1e-3, "the tool {d} m from the target");
        for (k, v) in q.iter().enumerate() {
            let [lo, hi] = t.layout().joints()[k].range_rad;
            assert!(
                *v >= f64::from(lo) - 1e-6 && *v <= f64::from(hi) + 1e-6,
                "joint {k}"
            );
        }
        // Two metres away: refused, how far said; the plan stands.
        let far = Command::Tool {
            arm: "left_arm".into(),
            target: ToolTarget {
                position: [2.0, 2.0, 0.9],
                rotation: [1.0, 0.0, 0.0, 0.0],
            },
        };
        let e = t
            .command(1, &far, Some(&at(&s, 3_000 * MS)), 3_000 * MS)
            .unwrap_err();
        assert!(
            matches!(e, Refusal::Unreachable { position_error_m, .. } if position_error_m > 1.0),
            "{e}"
        );
        let bad = Command::Tool {
            arm: "left_arm".into(),
            target: ToolTarget {
                position: [0.3, f64::INFINITY, 0.9],
                rotation: [1.0, 0.0, 0.0, 0.0],
            },
        };
        assert_eq!(
            t.command(1, &bad, Some(&at(&s, 3_000 * MS)), 3_000 * MS),
            Err(Refusal::BadPose)
        );
        let zero = Command::Tool {
            arm: "left_arm".into(),
            target: ToolTarget {
                position: [0.3, 0.2, 0.9],
                rotation: [0.0; 4],
            },
        };
        assert_eq!(
            t.command(1, &zero, Some(&at(&s, 3_000 * MS)), 3_000 * MS),
            Err(Refusal::BadPose)
        );
        let right = Command::Tool {
            arm: "right_arm".into(),
            target,
        };
        assert_eq!(
            t.command(1, &right, Some(&at(&s, 3_000 * MS)), 3_000 * MS),
            Err(Refusal::UnknownArm("right_arm".into())),
            "the right arm is not driven here"
        );
        assert_eq!(t.active(), 0x7f);
    }

    #[test]
    fn a_pose_reached_nearly_is_taken_within_the_acceptance_and_refused_beyond_it() {
        let body = Body::from_description(&RobotDescription::nori_a3()).unwrap();
        let (tool, _) = tool_to(&body, &WANT, body.lift_start_m());
        let s = state_at(&HERE);
        // Two steps from one start cannot get within the solver's own tolerance...
        let tight = |accept_position_m| TeleopSettings {
            ik: IkSettings {
                max_steps: 2,
                max_starts: 1,
                ..IkSettings::default()
            },
            accept_position_m,
            accept_angle_rad: 1.0,
            ..TeleopSettings::default()
        };
        let mut refusing = Teleop::new(body.clone(), a3_left_layout(), tight(0.0));
        let e = refusing.command(1, &tool, Some(&at(&s, 0)), 0).unwrap_err();
        let Refusal::Unreachable {
            position_error_m, ..
        } = e
        else {
            panic!("{e}")
        };
        // ... and is taken when the acceptance covers how close it came.
        let mut taking = Teleop::new(body, a3_left_layout(), tight(position_error_m + 1e-9));
        let solved = taking
            .command(1, &tool, Some(&at(&s, 0)), 0)
            .unwrap()
            .unwrap();
        assert_eq!(solved.position_error_m, position_error_m);
        assert_eq!(taking.active(), 0x7f);
    }

    #[test]
    fn a_silent_page_is_released_within_the_dead_man_bound_and_the_arm_held_where_it_is() {
        let mut t = teleop();
        let s = state_at(&[0.0, 0.0, 0.0, -0.2, 0.0, 0.0, 0.0]);
        t.command(
            1,
            &joints(&[("left_elbow", -1.0), ("left_gripper", 0.2)]),
            Some(&at(&s, 0)),
            0,
        )
        .unwrap();
        // Heard at 0 only: frames until 300 ms, then the hold.
        let mut ended_at = None;
        let mut moving = s;
        for k in 0..50u64 {
            let now = k * 10 * MS;
            moving.joints[3].position_rad = -0.2 - 0.01 * k as f32;
            let (frame, ended) = t.tick(Some(&at(&moving, now)), now);
            if let Some(why) = ended {
                assert_eq!(why, Ended::DeadMan);
                let f = frame.unwrap();
                assert_eq!(f.mask, (1 << 3) | (1 << 7));
                assert_eq!(
                    f.position_rad[3], moving.joints[3].position_rad,
                    "held where read"
                );
                assert!(
                    (f.position_rad[7] - 0.2).abs() < 0.2,
                    "the gripper keeps its grip goal, not the read 0.6"
                );
                assert!(f.position_rad[7] < 0.6);
                ended_at = Some(now);
                break;
            }
            assert!(frame.is_some());
        }
        let ended_at = ended_at.expect("released");
        assert!(ended_at > 300 * MS && ended_at <= 310 * MS, "{ended_at}");
        assert_eq!(
            t.tick(Some(&at(&moving, ended_at + 10 * MS)), ended_at + 10 * MS),
            (None, None)
        );
        assert_eq!(t.counters().deadman_releases, 1);
        assert_eq!(t.owner(), None);
    }

    #[test]
    fn a_closed_page_is_released_at_the_next_tick_and_another_page_waits_for_the_first() {
        let mut t = teleop();
        let s = state_at(&[0.0; 7]);
        let elbow = joints(&[("left_elbow", -0.5)]);
        t.command(1, &elbow, Some(&at(&s, 0)), 0).unwrap();
        assert_eq!(
            t.command(2, &elbow, Some(&at(&s, 100 * MS)), 100 * MS),
            Err(Refusal::OtherPage)
        );
        // Page 2 cannot end page 1's control either.
        t.command(2, &Command::Release, Some(&at(&s, 100 * MS)), 100 * MS)
            .unwrap_err();
        t.page_closed(2);
        assert_eq!(t.owner(), Some(1));
        t.page_closed(1);
        let (frame, ended) = t.tick(Some(&at(&s, 110 * MS)), 110 * MS);
        assert_eq!(ended, Some(Ended::PageClosed));
        assert_eq!(frame.unwrap().mask, 1 << 3);
        assert_eq!(t.tick(Some(&at(&s, 120 * MS)), 120 * MS), (None, None));
        t.command(2, &elbow, Some(&at(&s, 130 * MS)), 130 * MS)
            .unwrap();
        assert_eq!(t.owner(), Some(2));
        // Page 2 goes silent: page 1 may take over after the bound.
        assert_eq!(
            t.command(1, &elbow, Some(&at(&s, 400 * MS)), 400 * MS),
            Err(Refusal::OtherPage)
        );
        t.command(1, &elbow, Some(&at(&s, 431 * MS + 1)), 431 * MS + 1)
            .unwrap();
        assert_eq!(t.owner(), Some(1));
        assert_eq!(t.counters().closed_releases, 1);
        // The stop button, pressed on any page, lets go of whichever controls.
        t.let_go(435 * MS);
        let (frame, ended) = t.tick(Some(&at(&s, 440 * MS)), 440 * MS);
        assert_eq!(
            (frame.map(|f| f.mask), ended),
            (Some(1 << 3), Some(Ended::Released))
        );
        assert_eq!((t.owner(), t.active()), (None, 0));
    }

    #[test]
    fn the_safe_state_drops_everything_commanded_and_refuses_what_comes_during_it() {
        let mut t = teleop();
        let s = state_at(&[0.0; 7]);
        t.command(1, &joints(&[("left_elbow", -1.0)]), Some(&at(&s, 0)), 0)
            .unwrap();
        assert!(t.tick(Some(&at(&s, 10 * MS)), 10 * MS).0.is_some());
        let safe = JointState {
            flags: STATE_FLAG_SAFE_STATE,
            ..s
        };
        assert_eq!(
            t.tick(Some(&at(&safe, 20 * MS)), 20 * MS),
            (None, Some(Ended::SafeState))
        );
        assert_eq!(
            t.command(
                1,
                &joints(&[("left_elbow", -1.0)]),
                Some(&at(&safe, 30 * MS)),
                30 * MS
            ),
            Err(Refusal::SafeState)
        );
        // Recovered: nothing planned before moves the arm.
        assert_eq!(t.tick(Some(&at(&s, 40 * MS)), 40 * MS), (None, None));
        assert_eq!(t.active(), 0);
        assert_eq!(t.counters().safe_state_releases, 1);
    }

    /// The driver's frame at `t_ns` of servos that follow their goals: `s` with every
    /// commanded joint read where it was last commanded.
    fn followed(t: &Teleop, s: &JointState, t_ns: u64) -> JointState {
        let mut f = at(s, t_ns);
        for (i, j) in f.joints[..8].iter_mut().enumerate() {
            if let Some(g) = t.commanded(i) {
                j.position_rad = g as f32;
            }
        }
        f
    }

    /// `s` as the driver's frame at `t_ns` (numbered by the millisecond: a frame seen again
    /// is the same frame).
    fn at(s: &JointState, t_ns: u64) -> JointState {
        frame_at(s, t_ns / MS + 1, t_ns)
    }

    /// `s` as the driver's frame number `seq`, stamped `t_ns`.
    fn frame_at(s: &JointState, seq: u64, t_ns: u64) -> JointState {
        JointState {
            seq,
            timestamp_ns: t_ns,
            ..*s
        }
    }

    /// Teleoperation with the elbow read at `from` (the driver's first frame, at 0) and sent
    /// toward `to`.
    fn elbow_sent_from(from: f64, to: f64) -> (Teleop, JointState) {
        let mut t = teleop();
        let s = state_at(&[0.0, 0.0, 0.0, from, 0.0, 0.0, 0.0]);
        t.command(
            1,
            &joints(&[("left_elbow", to)]),
            Some(&frame_at(&s, 1, 0)),
            0,
        )
        .unwrap();
        (t, s)
    }

    #[test]
    fn a_driver_that_dies_and_restarts_gets_nothing_commanded_before() {
        let (mut t, s) = elbow_sent_from(-0.2, -1.2);
        let mut now = 0;
        // 100 ms of teleoperation with the driver's frames coming, the elbow following.
        let mut newest = at(&s, 0);
        for _ in 0..10 {
            now += 10 * MS;
            newest = followed(&t, &s, now);
            t.command(1, &Command::Alive, Some(&newest), now).unwrap();
            t.tick(Some(&newest), now);
        }
        let left_at = f64::from(newest.joints[3].position_rad);
        // The driver dies: no frame for a second; the page still holds control.
        let mut sent_while_dead = Vec::new();
        for _ in 0..100 {
            now += 10 * MS;
            let _ = t.command(1, &Command::Alive, Some(&newest), now);
            if let (Some(f), _) = t.tick(Some(&newest), now) {
                sent_while_dead.push(f64::from(f.position_rad[3]));
            }
        }
        assert!(
            sent_while_dead.iter().all(|g| (g - left_at).abs() <= 0.25),
            "goals ran on from {left_at} while the driver was dead: {:?}",
            sent_while_dead.last()
        );
        // A new driver: its frames numbered from 1 again, out of its safe state at once (a
        // live supervisor), the elbow where it was left.
        let mut moved = Vec::new();
        for k in 1..=20u64 {
            now += 10 * MS;
            let mut f = frame_at(&s, k, now);
            f.joints[3].position_rad = left_at as f32;
            t.observe(&f);
            let _ = t.command(1, &Command::Alive, Some(&f), now);
            if let (Some(g), _) = t.tick(Some(&f), now) {
                moved.push(f64::from(g.position_rad[3]));
            }
        }
        assert!(
            moved.iter().all(|g| (g - left_at).abs() < 1e-6),
            "a restarted driver was sent goals commanded before it: {moved:?} from {left_at}"
        );
    }

    #[test]
    fn a_safe_state_shorter_than_a_tick_still_drops_everything() {
        let mut t = teleop();
        let s = state_at(&[0.0; 7]);
        t.command(
            1,
            &joints(&[("left_elbow", -1.0)]),
            Some(&frame_at(&s, 1, 0)),
            0,
        )
        .unwrap();
        assert!(t.tick(Some(&frame_at(&s, 1, 0)), 0).0.is_some());
        // Between two ticks the driver entered its safe state and left it again.
        let safe = JointState {
            flags: STATE_FLAG_SAFE_STATE,
            ..frame_at(&s, 2, 4 * MS)
        };
        t.observe(&safe);
        let after = frame_at(&s, 3, 8 * MS);
        t.observe(&after);
        let (frame, ended) = t.tick(Some(&after), 10 * MS);
        assert_eq!(ended, Some(Ended::SafeState), "{frame:?}");
        assert_eq!(frame, None);
        assert_eq!(t.active(), 0);
    }

    #[test]
    fn the_speed_bound_holds_against_where_the_joint_is_read() {
        let (mut t, s) = elbow_sent_from(-0.2, -1.2);
        // The elbow does not follow (held by something, or its servo off): the goal must not
        // run ahead of it toward the target, to be met at once when it is free.
        let mut now = 0;
        for k in 2..200u64 {
            now += 10 * MS;
            let f = frame_at(&s, k, now);
            t.observe(&f);
            t.command(1, &Command::Alive, Some(&f), now).unwrap();
            t.tick(Some(&f), now);
        }
        let ahead = (t.commanded(3).unwrap() + 0.2).abs();
        assert!(
            ahead <= 0.25,
            "the goal ran {ahead} rad ahead of the reading"
        );
    }

    /// The page's message that reached the lab at `arrived_ns` (the lab's `at_ns`), before a
    /// driver interruption, handled by the lab's loop only after it (one inbound message a
    /// turn, behind others or an IK solve): `interrupt` feeds the frames of the interruption.
    fn queued_across(
        interrupt: impl Fn(&mut Teleop, &JointState) -> JointState,
    ) -> (Result<Option<Solved>, Refusal>, Vec<f64>) {
        let mut t = teleop();
        let s = state_at(&[0.0, 0.0, 0.0, -0.2, 0.0, 0.0, 0.0]);
        // The page controls the elbow (a small move), frames following.
        t.command(
            1,
            &joints(&[("left_elbow", -0.25)]),
            Some(&frame_at(&s, 1, 0)),
            0,
        )
        .unwrap();
        t.tick(Some(&frame_at(&s, 1, 0)), 0);
        // 2 ms: the page's next message (the elbow to -1.2) reaches the lab and waits in its
        // queue. Then the interruption, and a tick that drops everything.
        let arrived_ns = 2 * MS;
        let after = interrupt(&mut t, &s);
        let (_, ended) = t.tick(Some(&after), after.timestamp_ns + 2 * MS);
        assert!(ended.is_some(), "the interruption was seen");
        // The queued message is handled now, with its arrival time.
        let taken = t.command(
            1,
            &joints(&[("left_elbow", -1.2)]),
            Some(&after),
            arrived_ns,
        );
        let mut sent = Vec::new();
        let mut now = after.timestamp_ns + 2 * MS;
        for k in 0..100u64 {
            now += 10 * MS;
            let f = followed(&t, &frame_at(&s, after.seq + 1 + k, now), now);
            t.observe(&f);
            let _ = t.command(1, &Command::Alive, Some(&f), now);
            if let (Some(g), _) = t.tick(Some(&f), now) {
                sent.push(f64::from(g.position_rad[3]));
            }
        }
        (taken, sent)
    }

    /// A command that waited across `what` was refused and moved nothing after it.
    fn assert_nothing_sent(taken: &Result<Option<Solved>, Refusal>, sent: &[f64], what: &str) {
        assert_eq!(
            taken,
            &Err(Refusal::BeforeInterruption),
            "across the {what}"
        );
        assert!(
            sent.is_empty(),
            "a command from before the {what} moved the elbow to {:?}",
            sent.last()
        );
    }

    #[test]
    fn a_command_sent_before_a_short_safe_state_is_refused_after_it() {
        let (taken, sent) = queued_across(|t, s| {
            t.observe(&JointState {
                flags: STATE_FLAG_SAFE_STATE,
                ..frame_at(s, 2, 4 * MS)
            });
            let after = frame_at(s, 3, 8 * MS);
            t.observe(&after);
            after
        });
        assert_nothing_sent(&taken, &sent, "safe state");
    }

    #[test]
    fn a_command_sent_before_a_driver_restart_is_refused_after_it() {
        let (taken, sent) = queued_across(|t, s| {
            // The driver dies at 3 ms; a new one numbers its frames from 1 again, 600 ms
            // later, in its safe state for 50 ms, then out of it.
            for k in 1..=5u64 {
                t.observe(&JointState {
                    flags: STATE_FLAG_SAFE_STATE,
                    ..frame_at(s, k, 600 * MS + k * 10 * MS)
                });
            }
            let after = frame_at(s, 6, 660 * MS);
            t.observe(&after);
            after
        });
        assert_nothing_sent(&taken, &sent, "restart");
    }
}
