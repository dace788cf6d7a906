//! The column's controller, sans-IO.
//!
//! The rules it keeps, and why, are in `docs/hazards.md` (the lift's rows); in short: no
//! position is trusted before homing or after the hall counts jump; goals are clamped into the
//! soft limits; an obstruction stops the column and backs it off, and it then goes no further
//! toward the obstruction until a goal away from it or an operator's release (a re-sent goal is
//! the same goal); a back-off that gets nowhere jams it until an operator's release; the
//! operator's stop drops the goal and refuses new ones until it ends.

/// The motor-controller board as the controller sees it.
pub trait LiftActuator {
    /// A failure of the link to the board.
    type Error;
    /// Drives the motor at `velocity_m_s` (up positive) until the next command; the board
    /// stops it by itself when no command follows within its watchdog time.
    fn command(&mut self, velocity_m_s: f64) -> Result<(), Self::Error>;
    /// The board's newest reading.
    fn read(&mut self) -> Result<LiftReading, Self::Error>;
}

/// One reading of the board.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LiftReading {
    /// When it was taken, s (the caller's monotonic clock).
    pub t_s: f64,
    /// Hall counts since the board started (up positive).
    pub counts: i64,
    /// Motor current, A.
    pub current_a: f64,
    /// The lower limit switch is pressed (the column fully down).
    pub at_lower: bool,
    /// The upper limit switch is pressed.
    pub at_upper: bool,
    /// The board stopped the motor on its own over-current protection.
    pub over_current: bool,
}

/// The column and how it is driven.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColumnConfig {
    /// Travel between the limit switches, m.
    pub travel_m: f64,
    /// Hall counts per metre of travel.
    pub counts_per_m: f64,
    /// The soft limits' distance inside each switch, m.
    pub soft_margin_m: f64,
    /// Rated speed, m/s.
    pub max_speed_m_s: f64,
    /// Acceleration and braking, m/s².
    pub accel_m_s2: f64,
    /// Speed while homing (down to the lower switch), m/s.
    pub homing_speed_m_s: f64,
    /// A current this high is the motor stalling, A.
    pub obstruction_current_a: f64,
    /// Moving at less than this fraction of the commanded speed is not getting anywhere.
    pub obstruction_speed_fraction: f64,
    /// Either for this long is an obstruction, s.
    pub obstruction_time_s: f64,
    /// How far it backs off an obstruction, m.
    pub back_off_m: f64,
    /// A goal this close is reached, m.
    pub tolerance_m: f64,
}

impl ColumnConfig {
    /// The A3's column: 76 cm at 30 mm/s; halls giving 0.1 mm a count.
    pub const A3: ColumnConfig = ColumnConfig {
        travel_m: 0.76,
        counts_per_m: 10_000.0,
        soft_margin_m: 0.01,
        max_speed_m_s: 0.03,
        accel_m_s2: 0.1,
        homing_speed_m_s: 0.015,
        obstruction_current_a: 6.0,
        obstruction_speed_fraction: 0.3,
        obstruction_time_s: 0.15,
        back_off_m: 0.01,
        tolerance_m: 0.001,
    };

    /// The soft limits: heights a goal is clamped into, m above the lower switch.
    pub fn soft_limits(&self) -> (f64, f64) {
        (self.soft_margin_m, self.travel_m - self.soft_margin_m)
    }

    /// The most the counts can change in `dt_s` (at most [`MAX_DT_S`]): half again the rated
    /// speed, and half the soft margin (a sag, a reading's jitter). A larger change is not the
    /// column moving. It stays under the soft margin, so a shift believed keeps the soft
    /// limits inside the switches.
    fn plausible_counts(&self, dt_s: f64) -> f64 {
        (1.5 * self.max_speed_m_s * dt_s + 0.5 * self.soft_margin_m) * self.counts_per_m
    }
}

/// The longest interval a step integrates, s (a reading after a longer silence is judged as
/// this far from the last).
const MAX_DT_S: f64 = 0.1;

/// The speed that tells motion from getting nowhere is measured over this long, s: one
/// period's hall count (0.01 m/s at 10 ms) is a third of the rated speed, too coarse to see a
/// column slowed to a fifth.
const SPEED_WINDOW_S: f64 = 0.1;
/// Readings kept for it (10 ms apart).
const SPEED_READINGS: usize = 16;

/// A second obstruction this close to the last one, m, within [`REPEAT_WINDOW_S`], is the same
/// thing still there: its hold is the operator's to release.
const REPEAT_M: f64 = 0.02;
/// s.
const REPEAT_WINDOW_S: f64 = 60.0;

/// Whether the lift may travel now: the supervisor's word as `nori-lift` last heard it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Travel {
    /// Travel allowed.
    Allowed,
    /// The motor's duty-cycle budget is spent: held, its goal kept for when it has rested.
    DutySpent,
    /// No live supervisor: held, its goal kept.
    NoSupervisor,
    /// An operator's stop: held, its goal dropped, no goal taken until the stop ends.
    OperatorStop,
}

/// Where the controller is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LiftState {
    /// Not homed: no position is trusted, no goal taken.
    Unhomed,
    /// Going down to the lower switch.
    Homing,
    /// Homed: following goals.
    Ready,
    /// Stopped on an obstruction at `at_m` going up (`up`) or down, backing off and then held;
    /// no goal toward it is taken until a goal away from it or an operator's release, and only
    /// the operator's release once it met the same obstruction again (`repeated`).
    Obstructed {
        /// Where it met it, m.
        at_m: f64,
        /// The direction it was going.
        up: bool,
        /// It met an obstruction at the same place less than a minute before: a goal away is
        /// taken, but only the operator's release ends the hold.
        repeated: bool,
    },
    /// Its back-off from an obstruction at `at_m` got nowhere either (something else in the
    /// way, or hall counts that no longer count), or a held column lost its position (its
    /// counts jumped, its board went silent, its controller restarted): stopped, nothing taken
    /// until an operator's release, which homes it again.
    Jammed {
        /// Where it met the obstruction, m.
        at_m: f64,
    },
}

/// What happened in a step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LiftEvent {
    /// Homed: the lower switch is height 0.
    Homed,
    /// Stopped on an obstruction at this height, going up (`true`) or down.
    Obstruction {
        /// Height, m.
        at_m: f64,
        /// Direction it was going.
        up: bool,
    },
    /// The back-off from an obstruction got nowhere: jammed.
    BackOffBlocked {
        /// Where it met the obstruction, m.
        at_m: f64,
    },
    /// The hall counts jumped further than the column can move (a board that restarted):
    /// no position is trusted; the column stands until homed again.
    CountsJumped {
        /// The jump, counts.
        counts: i64,
    },
    /// A goal was reached, m.
    Reached(f64),
}

/// A goal the controller cannot take.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum LiftError {
    /// Not homed yet.
    #[error("the lift is not homed yet")]
    NotHomed,
    /// NaN or infinite.
    #[error("the height {0} is not a finite number")]
    NotFinite(f64),
    /// Toward an obstruction it stopped on.
    #[error("the lift stopped on an obstruction at {at_m:.3} m: no goal toward it until a goal away from it or `nori lift release`")]
    TowardObstruction {
        /// Where it met it, m.
        at_m: f64,
    },
    /// Jammed: its back-off from an obstruction got nowhere; `nori lift release` homes it again.
    #[error("the lift is jammed (its back-off from an obstruction at {at_m:.3} m got nowhere): `nori lift release` homes it again")]
    Jammed {
        /// Where it met the obstruction, m.
        at_m: f64,
    },
    /// An operator's stop is in force.
    #[error("an operator's stop is in force: nothing moves until `nori resume`")]
    OperatorStop,
}

/// The column's controller.
#[derive(Debug, Clone)]
pub struct LiftController {
    config: ColumnConfig,
    state: LiftState,
    travel: Travel,
    zero: i64,
    goal_m: Option<f64>,
    velocity: f64,
    last: Option<LiftReading>,
    /// Since when it has been pushing without getting anywhere, s.
    stuck_since: Option<f64>,
    /// At its goal (within the tolerance) since it last got there.
    arrived: bool,
    /// The last obstruction: where, and when, s.
    last_obstruction: Option<(f64, f64)>,
    /// Recent (time, counts), oldest first, for the speed over [`SPEED_WINDOW_S`].
    recent: [(f64, i64); SPEED_READINGS],
    recent_len: usize,
}

impl LiftController {
    /// A controller that knows nothing of where the column is.
    pub fn new(config: ColumnConfig) -> LiftController {
        LiftController {
            config,
            state: LiftState::Unhomed,
            travel: Travel::NoSupervisor,
            zero: 0,
            goal_m: None,
            velocity: 0.0,
            last: None,
            stuck_since: None,
            arrived: false,
            last_obstruction: None,
            recent: [(0.0, 0); SPEED_READINGS],
            recent_len: 0,
        }
    }

    /// The speed over the last [`SPEED_WINDOW_S`] (or what of it the readings cover) with
    /// reading `r` added, m/s; 0 with a single reading.
    fn windowed_speed(&mut self, r: &LiftReading) -> f64 {
        if self.recent_len == SPEED_READINGS {
            self.recent.copy_within(1.., 0);
            self.recent_len -= 1;
        }
        self.recent[self.recent_len] = (r.t_s, r.counts);
        self.recent_len += 1;
        let newest = self.recent[self.recent_len - 1];
        let oldest = self.recent[..self.recent_len]
            .iter()
            .find(|(t, _)| newest.0 - t <= SPEED_WINDOW_S + 1e-9)
            .copied()
            .unwrap_or(newest);
        let dt = newest.0 - oldest.0;
        if dt > 0.0 {
            (newest.1 - oldest.1) as f64 / self.config.counts_per_m / dt
        } else {
            0.0
        }
    }

    /// Where it is.
    pub fn state(&self) -> LiftState {
        self.state
    }

    /// The goal in force, m.
    pub fn goal_m(&self) -> Option<f64> {
        self.goal_m
    }

    /// The height of `r`, m above the lower switch (`None` before homing).
    pub fn height_m(&self, r: &LiftReading) -> Option<f64> {
        match self.state {
            LiftState::Unhomed | LiftState::Homing => None,
            _ => Some(self.height_of(r)),
        }
    }

    fn height_of(&self, r: &LiftReading) -> f64 {
        (r.counts - self.zero) as f64 / self.config.counts_per_m
    }

    /// Starts homing.
    pub fn home(&mut self) {
        self.state = LiftState::Homing;
        self.goal_m = None;
    }

    /// The board lost (silent, or its counts jumped: it may have restarted): no position is
    /// trusted. A column free to move is unhomed (`nori-lift` homes it again); a held one stays
    /// held, jammed, until the operator's release (homing goes down, onto whatever it was
    /// held off).
    pub fn board_lost(&mut self) {
        self.goal_m = None;
        self.recent_len = 0;
        self.state = match self.state {
            LiftState::Obstructed { at_m, .. } | LiftState::Jammed { at_m } => {
                LiftState::Jammed { at_m }
            }
            _ => LiftState::Unhomed,
        };
    }

    /// Held by a previous controller (its record, after a restart): jammed at `at_m` until
    /// the operator's release, instead of homing down onto what it was held off.
    pub fn restore_hold(&mut self, at_m: f64) {
        self.goal_m = None;
        self.state = LiftState::Jammed { at_m };
    }

    /// Where a hold keeps it: the obstruction's height while obstructed or jammed.
    pub fn held_at_m(&self) -> Option<f64> {
        match self.state {
            LiftState::Obstructed { at_m, .. } | LiftState::Jammed { at_m } => Some(at_m),
            _ => None,
        }
    }

    /// The supervisor's word on travel, before the commands of a period. An operator's stop
    /// drops the goal and ends homing: the column stays where it stops, and nothing it was
    /// told or was doing before the stop moves it after (homing again waits for the operator's
    /// release). Only the back-off from an obstruction is kept, for after the stop.
    pub fn set_travel(&mut self, travel: Travel) {
        if travel == Travel::OperatorStop {
            match self.state {
                // The back-off from what it pressed is kept: it moves away from the crush,
                // and finishes once the stop ends (dropped, it would leave a hand clamped).
                LiftState::Obstructed { .. } => {}
                LiftState::Homing => {
                    self.goal_m = None;
                    self.state = LiftState::Unhomed;
                }
                _ => self.goal_m = None,
            }
        }
        self.travel = travel;
    }

    /// A goal height, clamped into the soft limits (returned). The goal in force sent again
    /// changes nothing: not the obstruction timer, not an obstruction's hold.
    pub fn set_goal(&mut self, height_m: f64) -> Result<f64, LiftError> {
        if !height_m.is_finite() {
            return Err(LiftError::NotFinite(height_m));
        }
        if self.travel == Travel::OperatorStop {
            return Err(LiftError::OperatorStop);
        }
        let (lo, hi) = self.config.soft_limits();
        let goal = height_m.clamp(lo, hi);
        match self.state {
            LiftState::Unhomed | LiftState::Homing => return Err(LiftError::NotHomed),
            LiftState::Jammed { at_m } => return Err(LiftError::Jammed { at_m }),
            LiftState::Obstructed { at_m, up, repeated } => {
                // Away from it means beyond the back-off point: nothing short of it is safe
                // from pressing again.
                let away = if up {
                    goal <= at_m - self.config.back_off_m
                } else {
                    goal >= at_m + self.config.back_off_m
                };
                if !away {
                    return Err(LiftError::TowardObstruction { at_m });
                }
                if !repeated {
                    self.state = LiftState::Ready;
                }
            }
            LiftState::Ready => {}
        }
        if self.goal_m != Some(goal) {
            self.goal_m = Some(goal);
            self.arrived = false;
        }
        Ok(goal)
    }

    /// An operator's deliberate release: an obstruction's hold ends (the column finishes its
    /// back-off, if it has not, and takes goals toward it again), a jammed or unhomed column
    /// homes (its position is not known).
    pub fn release(&mut self) {
        match self.state {
            // Free to go toward it again; the back-off, if not done yet, still finishes.
            LiftState::Obstructed { .. } => self.state = LiftState::Ready,
            LiftState::Jammed { .. } | LiftState::Unhomed => self.home(),
            LiftState::Ready | LiftState::Homing => {}
        }
    }

    /// One step with the board's reading `r`. Returns the velocity to command (m/s, up
    /// positive) and what happened.
    pub fn step(&mut self, r: &LiftReading) -> (f64, Option<LiftEvent>) {
        let c = self.config;
        let dt = self
            .last
            .map_or(0.0, |l| (r.t_s - l.t_s).clamp(0.0, MAX_DT_S));
        let jump = self.last.map_or(0, |l| r.counts - l.counts);
        self.last = Some(*r);
        if jump.unsigned_abs() as f64 > c.plausible_counts(dt) && self.homed() {
            // Not the column moving: the board restarted (its counts with it) or lies. Nothing
            // it says of the height can be trusted until homed again.
            self.board_lost();
            self.velocity = 0.0;
            return (0.0, Some(LiftEvent::CountsJumped { counts: jump }));
        }
        let measured = self.windowed_speed(r);
        let (want, mut event) = self.wanted(r);
        // Acceleration limit, then the switches, then the supervisor's word.
        let step = c.accel_m_s2 * dt;
        let mut v = self.velocity + (want - self.velocity).clamp(-step, step);
        if (r.at_upper && v > 0.0) || (r.at_lower && v < 0.0 && self.state != LiftState::Homing) {
            v = 0.0;
        }
        if self.travel != Travel::Allowed {
            v = 0.0;
        }
        if let Some(e) = self.watch_obstruction(r, v, measured) {
            event = Some(e);
            v = 0.0;
        }
        self.velocity = v;
        (v, event)
    }

    fn homed(&self) -> bool {
        !matches!(self.state, LiftState::Unhomed | LiftState::Homing)
    }

    /// The speed the state asks for before the limits, and a homing or arrival.
    fn wanted(&mut self, r: &LiftReading) -> (f64, Option<LiftEvent>) {
        let c = self.config;
        match self.state {
            LiftState::Unhomed | LiftState::Jammed { .. } => (0.0, None),
            LiftState::Homing if r.at_lower => {
                self.zero = r.counts;
                self.state = LiftState::Ready;
                (0.0, Some(LiftEvent::Homed))
            }
            LiftState::Homing => (-c.homing_speed_m_s, None),
            LiftState::Ready | LiftState::Obstructed { .. } => {
                let Some(goal) = self.goal_m else {
                    return (0.0, None);
                };
                let h = self.height_of(r);
                // Held at the goal: moving again only if it drifts past twice the tolerance
                // (a sag under load, an overshoot), so it does not hunt around it.
                let band = if self.arrived {
                    2.0 * c.tolerance_m
                } else {
                    c.tolerance_m
                };
                let distance = goal - h;
                if distance.abs() > band {
                    self.arrived = false;
                    let speed = c
                        .max_speed_m_s
                        .min((2.0 * c.accel_m_s2 * distance.abs()).sqrt());
                    return (distance.signum() * speed, None);
                }
                let reached = !self.arrived && self.state == LiftState::Ready;
                self.arrived = true;
                (0.0, reached.then_some(LiftEvent::Reached(goal)))
            }
        }
    }

    /// Pushing without getting anywhere, or at a stall's current, for the obstruction time:
    /// stop and back off; the same while backing off: stop, jammed.
    fn watch_obstruction(&mut self, r: &LiftReading, v: f64, measured: f64) -> Option<LiftEvent> {
        let c = self.config;
        // Getting nowhere is told apart from the counts' resolution only at a speed; a
        // stall's current, or the board's own stop, at any speed commanded.
        let pushing = v.abs() >= 0.5 * c.homing_speed_m_s;
        let stuck = (pushing && measured.abs() < c.obstruction_speed_fraction * v.abs())
            || (v != 0.0 && (r.current_a.abs() >= c.obstruction_current_a || r.over_current));
        if !stuck {
            self.stuck_since = None;
            return None;
        }
        let since = *self.stuck_since.get_or_insert(r.t_s);
        if r.t_s - since < c.obstruction_time_s {
            return None;
        }
        self.stuck_since = None;
        self.arrived = false;
        let h = self.height_of(r);
        match self.state {
            LiftState::Homing => {
                // Homing stopped short of the switch: something is under the column. Stay
                // unhomed.
                self.state = LiftState::Unhomed;
                Some(LiftEvent::Obstruction {
                    at_m: f64::NAN,
                    up: false,
                })
            }
            LiftState::Obstructed { at_m, .. } => {
                self.goal_m = None;
                self.state = LiftState::Jammed { at_m };
                Some(LiftEvent::BackOffBlocked { at_m })
            }
            _ => {
                let up = v > 0.0;
                let (lo, hi) = c.soft_limits();
                let back = if up {
                    h - c.back_off_m
                } else {
                    h + c.back_off_m
                };
                let repeated = self.last_obstruction.is_some_and(|(at, t)| {
                    (at - h).abs() < REPEAT_M && r.t_s - t < REPEAT_WINDOW_S
                });
                self.last_obstruction = Some((h, r.t_s));
                self.goal_m = Some(back.clamp(lo, hi));
                self.state = LiftState::Obstructed {
                    at_m: h,
                    up,
                    repeated,
                };
                Some(LiftEvent::Obstruction { at_m: h, up })
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A simulated column, written for these tests: the motor follows its command with a
    /// 50 ms lag, the switches at the ends, something solid under it at `obstacle_m` (when
    /// set): driven onto it, it stops and its current rises to a stall's.
    struct Column {
        h: f64,
        v: f64,
        t: f64,
        counts_at_start: f64,
        obstacle_m: Option<f64>,
        /// Something solid above it at this height (a table top the column rises under).
        ceiling_m: Option<f64>,
        /// Seconds pressed on the obstacle so far.
        pressed_s: f64,
        /// The halls report this count whatever the column does (a lost hall signal, a board
        /// repeating one STATUS).
        frozen_counts: Option<i64>,
        /// The controller's last command, which the next step drives.
        command: f64,
    }

    impl Column {
        fn new(h: f64) -> Column {
            Column {
                h,
                v: 0.0,
                t: 0.0,
                counts_at_start: h,
                obstacle_m: None,
                ceiling_m: None,
                pressed_s: 0.0,
                frozen_counts: None,
                command: 0.0,
            }
        }

        fn step(&mut self, command: f64, dt: f64) -> LiftReading {
            let c = ColumnConfig::A3;
            self.v += (command - self.v) * (dt / 0.05).min(1.0);
            let mut blocked = false;
            let next = (self.h + self.v * dt).clamp(0.0, c.travel_m);
            match self.obstacle_m {
                Some(o) if self.v < 0.0 && next < o => {
                    blocked = true;
                    self.h = o;
                    self.v = 0.0;
                }
                _ => match self.ceiling_m {
                    Some(o) if self.v > 0.0 && next > o => {
                        blocked = true;
                        self.h = o;
                        self.v = 0.0;
                    }
                    _ => self.h = next,
                },
            }
            self.t += dt;
            if blocked {
                self.pressed_s += dt;
            }
            let counts = ((self.h - self.counts_at_start) * c.counts_per_m).round() as i64;
            LiftReading {
                t_s: self.t,
                counts: self.frozen_counts.unwrap_or(counts),
                current_a: if blocked {
                    8.0
                } else if command != 0.0 {
                    1.5
                } else {
                    0.0
                },
                at_lower: self.h <= 0.0005,
                at_upper: self.h >= c.travel_m - 0.0005,
                ..LiftReading::default()
            }
        }
    }

    impl Column {
        /// One 10 ms period of the loop: the column driven by the controller's last command,
        /// its reading fed to the controller.
        fn turn(&mut self, lift: &mut LiftController) -> (LiftReading, Option<LiftEvent>) {
            let r = self.step(self.command, 0.01);
            let (v, e) = lift.step(&r);
            self.command = v;
            (r, e)
        }

        /// Periods until the controller stops on an obstruction (at most `periods`).
        fn until_obstruction(&mut self, lift: &mut LiftController, periods: usize) -> LiftReading {
            for _ in 0..periods {
                if let (r, Some(LiftEvent::Obstruction { .. })) = self.turn(lift) {
                    return r;
                }
            }
            panic!("no obstruction in {periods} periods");
        }
    }

    /// Runs `seconds` at 100 Hz; returns the events and the largest speed commanded.
    fn run(
        lift: &mut LiftController,
        col: &mut Column,
        seconds: f64,
        allowed: bool,
    ) -> (Vec<LiftEvent>, f64) {
        let mut events = Vec::new();
        let mut fastest: f64 = 0.0;
        lift.set_travel(if allowed {
            Travel::Allowed
        } else {
            Travel::DutySpent
        });
        for _ in 0..(seconds * 100.0).round() as usize {
            let (_, e) = col.turn(lift);
            fastest = fastest.max(col.command.abs());
            events.extend(e);
        }
        (events, fastest)
    }

    fn homed() -> (LiftController, Column) {
        let mut lift = LiftController::new(ColumnConfig::A3);
        lift.set_travel(Travel::Allowed);
        let mut col = Column::new(0.3);
        assert_eq!(lift.set_goal(0.4), Err(LiftError::NotHomed));
        lift.home();
        // 0.3 m at 15 mm/s: 20 s.
        let (events, _) = run(&mut lift, &mut col, 22.0, true);
        assert_eq!(events, [LiftEvent::Homed]);
        (lift, col)
    }

    #[test]
    fn it_homes_moves_to_a_height_at_the_rated_speed_and_holds_it() {
        let (mut lift, mut col) = homed();
        assert_eq!(lift.set_goal(0.4), Ok(0.4));
        // 0.4 m at 30 mm/s: about 14 s.
        let (events, fastest) = run(&mut lift, &mut col, 16.0, true);
        assert_eq!(events, [LiftEvent::Reached(0.4)]);
        assert!(fastest <= 0.03 + 1e-9, "{fastest} m/s");
        assert!((col.h - 0.4).abs() < 0.002, "{} m", col.h);
        // And holds it: sagged 4 mm under a load, it comes back (once, no hunting).
        run(&mut lift, &mut col, 5.0, true);
        assert!((col.h - 0.4).abs() < 0.002, "{} m", col.h);
        col.h -= 0.004;
        let (events, _) = run(&mut lift, &mut col, 3.0, true);
        assert!((col.h - 0.4).abs() < 0.002, "{} m after a sag", col.h);
        assert_eq!(events, [LiftEvent::Reached(0.4)]);
    }

    #[test]
    fn goals_are_clamped_into_the_soft_limits_and_bad_ones_refused() {
        let (mut lift, mut col) = homed();
        assert_eq!(lift.set_goal(1.0), Ok(0.75));
        assert_eq!(lift.set_goal(-3.0), Ok(0.01));
        assert!(matches!(
            lift.set_goal(f64::NAN),
            Err(LiftError::NotFinite(_))
        ));
        assert!(matches!(
            lift.set_goal(f64::INFINITY),
            Err(LiftError::NotFinite(_))
        ));
        lift.set_goal(1.0).unwrap();
        run(&mut lift, &mut col, 30.0, true);
        assert!(
            (col.h - 0.75).abs() < 0.002,
            "stopped at {} m, not the soft limit",
            col.h
        );
    }

    #[test]
    fn an_obstruction_under_the_column_stops_it_and_it_backs_off() {
        let (mut lift, mut col) = homed();
        lift.set_goal(0.5).unwrap();
        run(&mut lift, &mut col, 20.0, true);
        // A hand under it at 0.3 m: coming down onto it.
        col.obstacle_m = Some(0.3);
        lift.set_goal(0.1).unwrap();
        let (events, _) = run(&mut lift, &mut col, 12.0, true);
        assert!(
            matches!(events.as_slice(), [LiftEvent::Obstruction { at_m, up: false }] if (at_m - 0.3).abs() < 0.002),
            "{events:?}"
        );
        // Backed off a centimetre and stays there until told otherwise.
        assert!((col.h - 0.31).abs() < 0.002, "{} m", col.h);
        assert!(matches!(lift.state(), LiftState::Obstructed { .. }));
        // The same goal again, or one toward the hand, is refused; the hand gone, the
        // operator's release lets it go there.
        assert!(
            matches!(lift.set_goal(0.1), Err(LiftError::TowardObstruction { at_m }) if (at_m - 0.3).abs() < 0.002)
        );
        col.obstacle_m = None;
        lift.release();
        assert_eq!(lift.state(), LiftState::Ready);
        lift.set_goal(0.1).unwrap();
        let (events, _) = run(&mut lift, &mut col, 12.0, true);
        assert_eq!(events, [LiftEvent::Reached(0.1)]);
    }

    #[test]
    fn the_obstruction_stop_comes_within_its_time_and_the_push_is_short() {
        let (mut lift, mut col) = homed();
        lift.set_goal(0.2).unwrap();
        run(&mut lift, &mut col, 10.0, true);
        col.obstacle_m = Some(0.1);
        lift.set_goal(0.01).unwrap();
        // From the moment it meets the obstacle to the command 0: at most the obstruction
        // time and a step.
        let mut met = None;
        for _ in 0..1500 {
            let (r, e) = col.turn(&mut lift);
            if r.current_a >= 8.0 && met.is_none() {
                met = Some(r.t_s);
            }
            let v = col.command;
            if matches!(e, Some(LiftEvent::Obstruction { .. })) {
                let pushed = r.t_s - met.expect("stopped before meeting it");
                assert!(pushed <= 0.15 + 0.011, "pushed for {pushed} s");
                assert_eq!(v, 0.0);
                return;
            }
        }
        panic!("never stopped");
    }

    #[test]
    fn no_travel_when_the_duty_budget_refuses_and_homing_onto_something_stays_unhomed() {
        let (mut lift, mut col) = homed();
        lift.set_goal(0.4).unwrap();
        let (_, fastest) = run(&mut lift, &mut col, 3.0, false);
        assert_eq!(fastest, 0.0);
        assert!(col.h < 0.011);
        let mut lift = LiftController::new(ColumnConfig::A3);
        lift.set_travel(Travel::Allowed);
        let mut col = Column::new(0.3);
        col.obstacle_m = Some(0.2);
        lift.home();
        let (events, _) = run(&mut lift, &mut col, 10.0, true);
        assert!(
            matches!(
                events.as_slice(),
                [LiftEvent::Obstruction { up: false, .. }]
            ),
            "{events:?}"
        );
        assert_eq!(lift.state(), LiftState::Unhomed);
        assert_eq!(lift.set_goal(0.4), Err(LiftError::NotHomed));
    }

    /// The obstruction time, the step in which the column meets the hand and the one in which
    /// it is told to stop, s.
    const PRESS_BOUND_S: f64 = 0.15 + 0.02 + 1e-9;

    /// Homed and standing at 0.5 m, a hand under it at 0.25 m.
    fn above_a_hand() -> (LiftController, Column) {
        let (mut lift, mut col) = homed();
        lift.set_goal(0.5).unwrap();
        run(&mut lift, &mut col, 20.0, true);
        col.obstacle_m = Some(0.25);
        (lift, col)
    }

    /// Free travel: the speed ramps at the configured acceleration (never a step), reaches
    /// the rated speed, meets no obstruction on the way (the measured speed keeps up with the
    /// commanded one) and arrives; the goal in force is what it was told. (Found by the
    /// mutation pass: the measured speed's formula and the acceleration step were untested.)
    #[test]
    fn free_travel_ramps_at_its_acceleration_and_meets_no_obstruction() {
        let (mut lift, mut col) = homed();
        assert_eq!(lift.goal_m(), None);
        assert_eq!(lift.set_goal(0.5), Ok(0.5));
        assert_eq!(lift.goal_m(), Some(0.5));
        let c = ColumnConfig::A3;
        let mut last = col.command;
        let mut events = Vec::new();
        let mut fastest: f64 = 0.0;
        for _ in 0..2500 {
            let (_, e) = col.turn(&mut lift);
            assert!(
                (col.command - last).abs() <= c.accel_m_s2 * 0.01 + 1e-9,
                "a step of {} m/s in 10 ms",
                col.command - last
            );
            last = col.command;
            fastest = fastest.max(col.command);
            events.extend(e);
        }
        assert!((fastest - c.max_speed_m_s).abs() < 1e-9, "{fastest}");
        assert_eq!(events, [LiftEvent::Reached(0.5)], "{events:?}");
        assert!((col.h - 0.5).abs() <= 0.003, "{}", col.h);
    }

    /// Something soft under the column (a cushion, an arm): it still moves, at a fifth of the
    /// speed commanded, drawing far less than a stall's current. Getting nowhere fast enough
    /// is an obstruction all the same. (Found by the mutation pass: the speed measured over one
    /// 10 ms period resolves one hall count, a third of the rated speed; a column at a fifth
    /// counted 0 or 1 in turn and the rule's timer restarted at every count.)
    #[test]
    fn a_column_moving_at_a_fifth_of_its_speed_meets_an_obstruction() {
        let (mut lift, mut col) = homed();
        lift.set_goal(0.3).unwrap();
        run(&mut lift, &mut col, 15.0, true);
        lift.set_goal(0.1).unwrap();
        // Driven at full speed first, on nothing.
        for _ in 0..100 {
            col.turn(&mut lift);
        }
        assert!((col.command + ColumnConfig::A3.max_speed_m_s).abs() < 1e-9);
        let mut r = col.step(col.command, 0.01);
        let mut at = col.h;
        let mut v = col.command;
        let mut met = None;
        for k in 0..300 {
            r.t_s += 0.01;
            // Now a fifth of the commanded speed, counted in whole halls as a board does.
            at += 0.2 * v * 0.01;
            r.counts = ((at - col.counts_at_start) * ColumnConfig::A3.counts_per_m).floor() as i64;
            r.current_a = 1.0;
            let (next, e) = lift.step(&r);
            v = next;
            if let Some(LiftEvent::Obstruction { .. }) = e {
                met = Some(k);
                break;
            }
        }
        let met = met.expect("a column getting nowhere was never stopped");
        assert!(met <= 40, "stopped only after {met} periods");
    }

    /// The lower switch pressed while a ready column is driven down (its counts drifted, or a
    /// goal at the soft limit): it is not driven into the switch. Homing is, to find it.
    #[test]
    fn a_pressed_lower_switch_stops_a_ready_column_going_down() {
        let (mut lift, mut col) = homed();
        lift.set_goal(0.3).unwrap();
        run(&mut lift, &mut col, 15.0, true);
        lift.set_goal(0.02).unwrap();
        for _ in 0..50 {
            col.turn(&mut lift);
        }
        assert!(col.command < 0.0);
        let mut r = col.step(col.command, 0.01);
        r.at_lower = true;
        let (v, _) = lift.step(&r);
        assert_eq!(v, 0.0, "driven into the lower switch");
        let mut homing = LiftController::new(ColumnConfig::A3);
        homing.set_travel(Travel::Allowed);
        homing.home();
        let mut h = Column::new(0.3);
        for _ in 0..50 {
            h.turn(&mut homing);
        }
        let mut r = h.step(h.command, 0.01);
        r.at_lower = false;
        assert!(
            homing.step(&r).0 < 0.0,
            "homing goes down to find the switch"
        );
    }

    /// The operator's stop pressed while the column backs off a hand (someone heard the cry):
    /// the back-off waits for the resume, then finishes; the hand is not left clamped. The
    /// operator's release during the back-off finishes it too. (Found by an outside review:
    /// the stop dropped the back-off goal, and the column stayed on the hand after the
    /// resume and after a release.)
    #[test]
    fn a_stop_or_a_release_during_a_back_off_does_not_leave_the_hand_clamped() {
        for release in [false, true] {
            let (mut lift, mut col) = above_a_hand();
            lift.set_goal(0.1).unwrap();
            col.until_obstruction(&mut lift, 2000);
            assert!((col.h - 0.25).abs() < 1e-9, "on the hand at {} m", col.h);
            let on_the_hand = col.h;
            for _ in 0..100 {
                lift.set_travel(Travel::OperatorStop);
                col.turn(&mut lift);
            }
            assert!(
                col.h - on_the_hand < 1e-3,
                "moved during the stop: {}",
                col.h
            );
            if release {
                lift.release();
            }
            for _ in 0..500 {
                lift.set_travel(Travel::Allowed);
                col.turn(&mut lift);
            }
            assert!(
                col.h >= 0.25 + 0.5 * ColumnConfig::A3.back_off_m,
                "release {release}: the column still sits on the hand at {} m ({:?})",
                col.h,
                lift.state()
            );
        }
    }

    /// Runs `seconds` at 100 Hz with `goal(t)` sent every `every_s` (as a policy's plan or a
    /// teleoperator streams it, taken before the step as `nori-lift` does); returns the
    /// obstructions met.
    fn streamed(
        lift: &mut LiftController,
        col: &mut Column,
        seconds: f64,
        every_s: f64,
        goal: impl Fn(f64) -> f64,
    ) -> usize {
        let (mut next_send, mut met) = (0.0, 0);
        for k in 0..(seconds * 100.0).round() as usize {
            let t = k as f64 * 0.01;
            if t >= next_send - 1e-9 {
                let _ = lift.set_goal(goal(t));
                next_send += every_s;
            }
            let (_, e) = col.turn(lift);
            met += usize::from(matches!(e, Some(LiftEvent::Obstruction { .. })));
        }
        met
    }

    #[test]
    fn a_goal_sent_again_and_again_does_not_press_the_hand_again() {
        // The agent renews its goal every 10 ms; a teleoperator's page and a policy's plan
        // every 60-140 ms.
        for every_s in [0.01, 0.06, 0.14] {
            let (mut lift, mut col) = above_a_hand();
            let met = streamed(&mut lift, &mut col, 12.0, every_s, |_| 0.1);
            assert_eq!(met, 1, "every {every_s} s: met the hand {met} times");
            assert!(
                col.pressed_s <= PRESS_BOUND_S,
                "every {every_s} s: pressed {} s in all",
                col.pressed_s
            );
            assert!(
                (col.h - 0.26).abs() < 0.002,
                "every {every_s} s: left at {} m, not backed off",
                col.h
            );
        }
    }

    #[test]
    fn goals_toward_an_obstruction_are_refused_and_one_away_from_it_is_taken() {
        let (mut lift, mut col) = above_a_hand();
        streamed(&mut lift, &mut col, 12.0, 0.05, |_| 0.1);
        // A plan creeping down toward the hand (every goal a different one) moves nothing.
        let met = streamed(&mut lift, &mut col, 4.0, 0.05, |t| 0.24 - 0.01 * t);
        assert_eq!(met, 0);
        assert!(
            col.pressed_s <= PRESS_BOUND_S,
            "pressed {} s",
            col.pressed_s
        );
        assert!((col.h - 0.26).abs() < 0.002, "{} m", col.h);
        // A goal away from it is taken.
        assert_eq!(lift.set_goal(0.4), Ok(0.4));
        run(&mut lift, &mut col, 8.0, true);
        assert!((col.h - 0.4).abs() < 0.002, "{} m", col.h);
    }

    #[test]
    fn a_back_off_that_gets_nowhere_stops_the_column() {
        let (mut lift, mut col) = above_a_hand();
        lift.set_goal(0.1).unwrap();
        let r = col.until_obstruction(&mut lift, 1200);
        // The halls stop counting as it starts backing off: it must not drive on blind.
        col.frozen_counts = Some(r.counts);
        let (_, fastest) = run(&mut lift, &mut col, 10.0, true);
        assert!(fastest > 0.0, "it never tried to back off");
        assert!(
            col.h < 0.25 + 0.01 + 0.01,
            "the back-off drove on to {} m with its counts frozen",
            col.h
        );
    }

    #[test]
    fn a_jump_of_the_hall_counts_is_not_believed() {
        let (mut lift, mut col) = homed();
        lift.set_goal(0.4).unwrap();
        run(&mut lift, &mut col, 16.0, true);
        assert!((col.h - 0.4).abs() < 0.002, "{} m", col.h);
        // The board browns out and restarts within a status period: its counts start at 0
        // again, here, 0.4 m up.
        col.counts_at_start = col.h;
        run(&mut lift, &mut col, 6.0, true);
        assert!(
            (col.h - 0.4).abs() < 0.003,
            "the counts' jump moved the column to {} m",
            col.h
        );
    }

    #[test]
    fn the_operators_stop_drops_the_goal_and_refuses_goals_until_it_ends() {
        let (mut lift, mut col) = homed();
        lift.set_goal(0.6).unwrap();
        run(&mut lift, &mut col, 4.0, true);
        let at = col.h;
        assert!(at > 0.05, "{at} m");
        lift.set_travel(Travel::OperatorStop);
        assert_eq!(lift.goal_m(), None);
        assert_eq!(lift.set_goal(0.6), Err(LiftError::OperatorStop));
        for _ in 0..300 {
            col.turn(&mut lift);
            assert_eq!(col.command, 0.0);
        }
        // Resumed: nothing told before the stop moves it; a new goal does.
        lift.set_travel(Travel::Allowed);
        let stood = col.h;
        for _ in 0..300 {
            col.turn(&mut lift);
        }
        assert!(
            (col.h - stood).abs() < 1e-3,
            "moved to {} m after the resume",
            col.h
        );
        assert!(lift.set_goal(0.6).is_ok());
    }

    #[test]
    fn a_jammed_column_takes_no_goal_and_the_operators_release_homes_it() {
        let (mut lift, mut col) = above_a_hand();
        lift.set_goal(0.1).unwrap();
        let r = col.until_obstruction(&mut lift, 2000);
        col.frozen_counts = Some(r.counts);
        let mut jammed = false;
        for _ in 0..200 {
            jammed |= matches!(
                col.turn(&mut lift).1,
                Some(LiftEvent::BackOffBlocked { .. })
            );
        }
        assert!(jammed);
        assert!(matches!(lift.state(), LiftState::Jammed { .. }));
        assert!(matches!(lift.set_goal(0.5), Err(LiftError::Jammed { .. })));
        lift.release();
        assert_eq!(lift.state(), LiftState::Homing);
    }

    #[test]
    fn the_boards_over_current_stop_is_an_obstruction() {
        let (mut lift, mut col) = homed();
        lift.set_goal(0.5).unwrap();
        let mut command = 0.0;
        for k in 0..400 {
            let mut r = col.step(command, 0.01);
            // From 2 s on the board reports its over-current stop (only the bit says so: the
            // column here goes on moving).
            r.over_current = k >= 200;
            let (v, e) = lift.step(&r);
            command = v;
            if let Some(LiftEvent::Obstruction { up, .. }) = e {
                assert!(up);
                assert!((200..=200 + 17).contains(&k), "stopped at step {k}");
                return;
            }
        }
        panic!("the board's over-current stop was not taken as an obstruction");
    }

    /// The hand under the column, stopped on once (streamed 0.1 m as the existing test does):
    /// backed off to 0.26 m and held, `Obstructed`.
    fn stopped_on_the_hand_once() -> (LiftController, Column) {
        let (mut lift, mut col) = above_a_hand();
        let met = streamed(&mut lift, &mut col, 12.0, 0.05, |_| 0.1);
        assert_eq!(met, 1);
        assert!(matches!(lift.state(), LiftState::Obstructed { .. }));
        assert!(col.pressed_s <= PRESS_BOUND_S);
        (lift, col)
    }

    #[test]
    fn a_second_obstruction_at_the_same_place_holds_until_released() {
        let (mut lift, mut col) = stopped_on_the_hand_once();
        let before = col.pressed_s;
        // A plan streaming 0.1 m every 60 ms that, once a second, has one step at 0.3 m
        // (2 cm above the hold point: "away").
        let met = streamed(&mut lift, &mut col, 20.0, 0.06, |t| {
            if t % 1.0 < 0.06 {
                0.3
            } else {
                0.1
            }
        });
        eprintln!(
            "after the first stop: met the hand {met} more times, pressed {:.3} s more (bound for one press {:.3} s)",
            col.pressed_s - before,
            PRESS_BOUND_S
        );
        // Once more at most (the first goal away released it); then only the operator's
        // release ends the hold.
        assert!(met <= 1, "pressed the hand again {met} times");
        assert!(col.pressed_s - before <= PRESS_BOUND_S);
        assert!(
            matches!(lift.state(), LiftState::Obstructed { repeated: true, .. }),
            "{:?}",
            lift.state()
        );
    }

    #[test]
    fn alternating_goals_stop_on_the_hand_like_any_other() {
        let (mut lift, mut col) = stopped_on_the_hand_once();
        let before = col.pressed_s;
        // One goal at 0.5 m ("away": the hold ends), 0.1 m for 8 periods (the commanded
        // speed ramps to 7 mm/s down), then 0.5 m and 0.1 m alternately every 10 ms: the
        // command stays at 6-7 mm/s down, under the 7.5 mm/s below which nothing is
        // "pushing", so neither the stall current nor the lack of motion is ever looked at.
        let (mut command, mut met, mut slowest_pressing) = (0.0, 0, f64::INFINITY);
        for k in 0..6000usize {
            let goal = if k == 0 || (k > 8 && k % 2 == 1) {
                0.5
            } else {
                0.1
            };
            let _ = lift.set_goal(goal);
            let r = col.step(command, 0.01);
            let (v, e) = lift.step(&r);
            command = v;
            if r.current_a >= 8.0 {
                slowest_pressing = slowest_pressing.min(v.abs());
            }
            met += usize::from(matches!(e, Some(LiftEvent::Obstruction { .. })));
        }
        eprintln!(
            "60 s of alternating goals: obstruction stops {met}, pressed {:.2} s more at {:.1} A, column at {:.4} m, state {:?}, slowest command while pressing {:.4} m/s",
            col.pressed_s - before,
            8.0,
            col.h,
            lift.state(),
            slowest_pressing
        );
        assert!(
            col.pressed_s - before <= PRESS_BOUND_S,
            "pressed {:.2} s more",
            col.pressed_s - before
        );
    }

    #[test]
    fn a_count_jump_while_held_keeps_the_hold() {
        // Obstructed (the hand below): the board browns out, its counts restart at 0.
        let (mut lift, mut col) = stopped_on_the_hand_once();
        let before = col.pressed_s;
        col.counts_at_start = col.h;
        let r = col.step(0.0, 0.01);
        let (_, e) = lift.step(&r);
        assert!(matches!(e, Some(LiftEvent::CountsJumped { .. })), "{e:?}");
        // As nori-lift does after a count jump: home an unhomed column.
        if lift.state() == LiftState::Unhomed {
            lift.home();
        }
        let (events, _) = run(&mut lift, &mut col, 3.0, true);
        eprintln!(
            "Obstructed, counts jump: events {events:?}, pressed {:.3} s more",
            col.pressed_s - before
        );
        let pressed_again = col.pressed_s - before;

        // Jammed (needs the operator's release): a jump of the counts, or a silent board,
        // homes it with no release.
        let (mut lift, mut col) = above_a_hand();
        lift.set_goal(0.1).unwrap();
        let mut command = 0.0;
        for _ in 0..2000 {
            let r = col.step(command, 0.01);
            let (v, e) = lift.step(&r);
            command = v;
            if matches!(e, Some(LiftEvent::Obstruction { .. })) {
                col.frozen_counts = Some(r.counts);
            }
        }
        assert!(matches!(lift.state(), LiftState::Jammed { .. }));
        col.frozen_counts = Some(-12_345);
        let r = col.step(0.0, 0.01);
        let (_, e) = lift.step(&r);
        assert!(matches!(e, Some(LiftEvent::CountsJumped { .. })), "{e:?}");
        if lift.state() == LiftState::Unhomed {
            lift.home();
        }
        let state_after = lift.state();
        let (_, fastest) = run(&mut lift, &mut col, 1.0, true);
        eprintln!("Jammed, counts jump: state {state_after:?}, then drove at {fastest} m/s without a release");
        assert!(
            pressed_again <= 1e-9,
            "pressed the hand again {pressed_again:.3} s"
        );
        assert_eq!(
            fastest, 0.0,
            "a jammed column moved without the operator's release"
        );
    }

    #[test]
    fn homing_stopped_by_the_operator_waits_for_a_release() {
        // Homing (at nori-lift's start; the operator's release of a jammed column and a silent
        // board take the same path), then `nori stop`, then `nori resume`.
        let mut lift = LiftController::new(ColumnConfig::A3);
        let mut col = Column::new(0.3);
        lift.home();
        run(&mut lift, &mut col, 1.0, true);
        assert_eq!(lift.state(), LiftState::Homing);
        lift.set_travel(Travel::OperatorStop);
        let mut command = 0.0;
        for _ in 0..100 {
            let r = col.step(command, 0.01);
            command = lift.step(&r).0;
        }
        let stood = col.h;
        lift.set_travel(Travel::Allowed);
        for _ in 0..300 {
            let r = col.step(command, 0.01);
            command = lift.step(&r).0;
        }
        eprintln!(
            "stopped at {stood:.4} m while homing; 3 s after the resume at {:.4} m, {:?}",
            col.h,
            lift.state()
        );
        assert!(
            (col.h - stood).abs() < 1e-3,
            "moved {:.4} m after the resume",
            stood - col.h
        );
    }

    #[test]
    fn no_jump_the_counts_are_allowed_shifts_the_soft_limits_past_a_switch() {
        let c = ColumnConfig::A3;
        assert!(c.plausible_counts(MAX_DT_S) < c.soft_margin_m * c.counts_per_m);
    }

    #[test]
    fn a_count_jump_after_a_long_gap_is_not_believed_either() {
        // A board whose counts are 0 at the lower switch (started there).
        let mut lift = LiftController::new(ColumnConfig::A3);
        let mut col = Column::new(0.0);
        lift.home();
        run(&mut lift, &mut col, 1.0, true);
        lift.set_goal(0.01).unwrap();
        run(&mut lift, &mut col, 3.0, true);
        // Standing at the lower soft limit (within its 2 mm hold band: a sag).
        col.h = 0.0105;
        run(&mut lift, &mut col, 0.5, true);
        let at = col.h;
        // The board browns out: no STATUS for 100 ms (within the 200 ms silence bound), and
        // its counts start again at 0 here.
        col.counts_at_start = col.h;
        let r = col.step(0.0, 0.1);
        let (_, e) = lift.step(&r);
        eprintln!(
            "column at {at:.4} m, counts restarted after 100 ms: event {e:?}, believed height {:?}",
            lift.height_m(&r)
        );
        let _ = lift.set_goal(1.0);
        let mut highest: f64 = 0.0;
        let mut command = 0.0;
        for _ in 0..3000 {
            let r = col.step(command, 0.01);
            command = lift.step(&r).0;
            highest = highest.max(col.h);
        }
        let (_, hi) = ColumnConfig::A3.soft_limits();
        eprintln!("then a goal of 1 m: the column went to {highest:.4} m (soft limit {hi} m, switch at {} m)", ColumnConfig::A3.travel_m);
        assert!(
            highest <= hi + 0.002,
            "past the soft limit to {highest:.4} m"
        );
    }

    #[test]
    fn a_restarted_controller_keeps_its_predecessors_hold() {
        let (held, mut col) = stopped_on_the_hand_once();
        let before = col.pressed_s;
        let at_m = held.held_at_m().expect("held");
        // nori-lift killed and restarted three times: each new controller starts from the
        // hold its predecessor recorded (nori-lift's hold record) instead of homing onto it.
        for _ in 0..3 {
            let mut lift = LiftController::new(ColumnConfig::A3);
            lift.restore_hold(at_m);
            assert!(matches!(lift.set_goal(0.1), Err(LiftError::Jammed { .. })));
            let (events, fastest) = run(&mut lift, &mut col, 3.0, true);
            assert_eq!((events, fastest), (vec![], 0.0));
        }
        assert!(
            col.pressed_s - before <= 1e-9,
            "pressed {:.3} s more",
            col.pressed_s - before
        );
    }

    #[test]
    fn rising_under_something_stops_backs_down_and_holds_against_it() {
        let (mut lift, mut col) = homed();
        col.ceiling_m = Some(0.5);
        assert!(lift.held_at_m().is_none());
        lift.set_goal(0.7).unwrap();
        let (events, _) = run(&mut lift, &mut col, 25.0, true);
        assert!(
            matches!(events.as_slice(), [LiftEvent::Obstruction { at_m, up: true }] if (at_m - 0.5).abs() < 0.002),
            "{events:?}"
        );
        assert!((col.h - 0.49).abs() < 0.002, "backed down to {} m", col.h);
        let at = lift.held_at_m().expect("held");
        assert!(
            (at - 0.5).abs() < 0.002
                && (lift.height_m(&col.step(0.0, 0.01)).unwrap() - col.h).abs() < 0.001
        );
        // Up toward it, or short of the back-off point: refused; down, away: taken.
        assert!(matches!(
            lift.set_goal(0.7),
            Err(LiftError::TowardObstruction { .. })
        ));
        assert!(matches!(
            lift.set_goal(0.495),
            Err(LiftError::TowardObstruction { .. })
        ));
        assert_eq!(lift.set_goal(0.45), Ok(0.45));
        assert_eq!(lift.state(), LiftState::Ready);
        assert_eq!(lift.held_at_m(), None);
    }

    #[test]
    fn only_a_second_obstruction_near_the_first_and_soon_is_a_repeat() {
        let repeated = |lift: &LiftController| {
            matches!(lift.state(), LiftState::Obstructed { repeated: true, .. })
        };
        // Elsewhere (the hand moved 3 cm down): a first obstruction again.
        let (mut lift, mut col) = stopped_on_the_hand_once();
        lift.set_goal(0.4).unwrap();
        run(&mut lift, &mut col, 6.0, true);
        col.obstacle_m = Some(0.22);
        lift.set_goal(0.1).unwrap();
        run(&mut lift, &mut col, 8.0, true);
        assert!(matches!(lift.state(), LiftState::Obstructed { .. }) && !repeated(&lift));
        // At the same place after more than a minute: a first obstruction again.
        let (mut lift, mut col) = stopped_on_the_hand_once();
        lift.set_goal(0.4).unwrap();
        run(&mut lift, &mut col, 61.0, true);
        lift.set_goal(0.1).unwrap();
        run(&mut lift, &mut col, 8.0, true);
        assert!(matches!(lift.state(), LiftState::Obstructed { .. }) && !repeated(&lift));
    }

    #[test]
    fn the_switches_stop_the_motor_and_a_count_jump_while_homing_is_no_event() {
        let (mut lift, mut col) = homed();
        lift.set_goal(0.75).unwrap();
        run(&mut lift, &mut col, 2.0, true);
        let mut r = col.step(0.03, 0.01);
        r.at_upper = true;
        assert_eq!(lift.step(&r).0, 0.0, "driven up into the upper switch");
        lift.set_goal(0.01).unwrap();
        run(&mut lift, &mut col, 2.0, true);
        let mut r = col.step(-0.03, 0.01);
        r.at_lower = true;
        assert_eq!(lift.step(&r).0, 0.0, "driven down into the lower switch");
        // Homing trusts no count: a jump is nothing to it.
        let mut lift = LiftController::new(ColumnConfig::A3);
        lift.set_travel(Travel::Allowed);
        let mut col = Column::new(0.3);
        lift.home();
        run(&mut lift, &mut col, 1.0, true);
        assert_eq!(lift.height_m(&col.step(0.0, 0.01)), None);
        col.counts_at_start += 0.2;
        let (events, _) = run(&mut lift, &mut col, 1.0, true);
        assert_eq!((events, lift.state()), (vec![], LiftState::Homing));
    }
}
