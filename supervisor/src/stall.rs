//! Stall detection and reaction, per joint (paper, "Preventing stall").
//!
//! Over a window of k control cycles, a joint whose current stays high while its position stays
//! static, and which is trying to move (far from its goal), has stalled. A gripper then holds with
//! a reduced grip torque; any other joint gets one retry at full torque and, if it stalls again,
//! a reduced torque until a new target is commanded.
//!
//! A wheel (speed mode) is the same detector on speeds: it is trying to move when its goal
//! speed is at least [`WHEEL_MIN_SPEED_RAD_S`], static when it turns at no more than
//! [`WHEEL_STATIC_FRACTION`] of it, with the current high over the window: a base pushing a
//! wall. One retry at full torque, then a reduced torque until the command changes by more than
//! [`WHEEL_NEW_COMMAND_RAD_S`] (the operator steers away, or stops).

use crate::config::StallConfig;

/// Longest window supported (a fixed ring: nothing allocates per cycle).
pub const MAX_WINDOW: usize = 64;
/// A wheel asked for less than this is not trying to move, rad/s.
pub const WHEEL_MIN_SPEED_RAD_S: f32 = 0.3;
/// A wheel turning at no more than this fraction of its goal speed is static.
pub const WHEEL_STATIC_FRACTION: f32 = 0.2;
/// A wheel's goal speed this far from the one at reduction is a new command, rad/s.
pub const WHEEL_NEW_COMMAND_RAD_S: f32 = 0.5;

/// Where a joint's stall handling is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StallState {
    /// Full torque, watching.
    Normal,
    /// Stalled once at `position`; full torque until it stalls again (→ reduced) or makes
    /// progress (moves `new-target-rad` away, or reaches its goal).
    Retrying {
        /// Where it stalled.
        position: f32,
    },
    /// Stalled again after the retry (or a gripper that closed on something): torque reduced
    /// until the goal moves by more than `new-target-rad` from `goal`.
    Reduced {
        /// The goal when the torque was reduced.
        goal: f32,
    },
}

/// What the detector decided this cycle.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StallAction {
    /// Nothing new.
    None,
    /// Stalled: one retry at full torque begins.
    Retry,
    /// Torque reduced (gripper hold, or a joint that stalled again).
    Reduce,
    /// A new target: full torque again.
    Restore,
}

#[derive(Debug, Clone, Copy, Default)]
struct Sample {
    position: f32,
    current: f32,
}

/// What kind of joint a detector watches.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StallKind {
    /// An arm joint: positions against a position goal.
    Joint,
    /// A gripper: reduced at once to its grip torque.
    Gripper,
    /// A wheel: speeds against a speed goal.
    Wheel,
}

/// One joint's detector.
#[derive(Debug, Clone)]
pub struct StallDetector {
    kind: StallKind,
    current_threshold: f32,
    min_error: f32,
    ring: [Sample; MAX_WINDOW],
    filled: usize,
    next: usize,
    /// The joint's state.
    pub state: StallState,
}

impl StallDetector {
    /// A detector for a joint of `kind` whose servo stalls at `stall_current` A.
    pub fn new(kind: StallKind, stall_current: f32, config: &StallConfig) -> Self {
        let (fraction, min_error) = match kind {
            StallKind::Gripper => (
                config.gripper_current_fraction,
                config.gripper_min_error_rad,
            ),
            StallKind::Joint => (config.current_fraction, config.min_error_rad),
            StallKind::Wheel => (config.current_fraction, WHEEL_MIN_SPEED_RAD_S),
        };
        Self::with_threshold(kind, fraction * stall_current, min_error)
    }

    /// A detector judging the effort against `threshold` in its own unit (the calibration
    /// judges `Present_Load` against the torque limit it set): stalled when the effort stays
    /// at or above it over the window while the position stays static, `min_error` or more
    /// from the goal.
    pub fn with_threshold(kind: StallKind, threshold: f32, min_error: f32) -> Self {
        StallDetector {
            kind,
            current_threshold: threshold,
            min_error,
            ring: [Sample::default(); MAX_WINDOW],
            filled: 0,
            next: 0,
            state: StallState::Normal,
        }
    }

    fn clear_window(&mut self) {
        self.filled = 0;
        self.next = 0;
    }

    /// The current threshold, A.
    pub fn current_threshold(&self) -> f32 {
        self.current_threshold
    }

    /// Feeds one cycle: position, current and goal (a wheel: speed, current and goal speed).
    /// `sample` is `None` when the joint was missing this cycle: the window restarts (a stall
    /// is only declared over k consecutive readings).
    pub fn update(&mut self, sample: Option<(f32, f32, f32)>, config: &StallConfig) -> StallAction {
        let Some((position, current, goal)) = sample else {
            self.clear_window();
            return StallAction::None;
        };
        let wheel = self.kind == StallKind::Wheel;
        if let StallState::Reduced { goal: held } = self.state {
            let new = if wheel {
                WHEEL_NEW_COMMAND_RAD_S
            } else {
                config.new_target_rad
            };
            if (goal - held).abs() > new {
                self.state = StallState::Normal;
                self.clear_window();
                return StallAction::Restore;
            }
            return StallAction::None;
        }
        let k = config.window.min(MAX_WINDOW);
        self.ring[self.next] = Sample { position, current };
        self.next = (self.next + 1) % k;
        self.filled = (self.filled + 1).min(k);
        let trying = if wheel {
            goal.abs() >= self.min_error
        } else {
            (goal - position).abs() >= self.min_error
        };
        if wheel && !trying {
            // A wheel's window holds only cycles in which it was asked to turn: holding still
            // against a load, then asked to go, is not a stall at the first cycle.
            self.clear_window();
        }
        if let StallState::Retrying { position: stuck } = self.state {
            // The retry made progress: it is not stuck any more (a bounce off the obstacle is
            // not progress, so one window without a stall is not enough). A wheel that turns
            // at half its goal speed again is free.
            let progress = if wheel {
                position.abs() >= 0.5 * goal.abs()
            } else {
                (position - stuck).abs() > config.new_target_rad
            };
            if !trying || progress {
                self.state = StallState::Normal;
            }
        }
        if self.filled < k || !trying || !self.stalled(k, goal, config) {
            return StallAction::None;
        }
        self.clear_window();
        match (self.state, self.kind) {
            (StallState::Normal, StallKind::Joint | StallKind::Wheel) => {
                self.state = StallState::Retrying { position };
                StallAction::Retry
            }
            _ => {
                self.state = StallState::Reduced { goal };
                StallAction::Reduce
            }
        }
    }

    fn stalled(&self, k: usize, goal: f32, config: &StallConfig) -> bool {
        let window = &self.ring[..k];
        let high = window
            .iter()
            .all(|s| s.current.abs() >= self.current_threshold);
        if self.kind == StallKind::Wheel {
            let slow = WHEEL_STATIC_FRACTION * goal.abs();
            return high && window.iter().all(|s| s.position.abs() <= slow);
        }
        let (lo, hi) = window
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), s| {
                (lo.min(s.position), hi.max(s.position))
            });
        high && hi - lo <= config.static_rad
    }

    /// The torque limit this state asks for, 0.1 % (0 = the configured maximum).
    pub fn torque_limit_permille(&self, config: &StallConfig) -> u16 {
        match self.state {
            StallState::Reduced { .. } if self.kind == StallKind::Gripper => {
                (config.gripper_hold_percent * 10.0).round() as u16
            }
            StallState::Reduced { .. } => (config.reduced_percent * 10.0).round() as u16,
            _ => 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::SupervisorConfig;
    use telemetry::config::ProcessConfig;

    fn config() -> StallConfig {
        SupervisorConfig::embedded().unwrap().stall
    }

    /// Feeds `n` cycles of a joint pushing against something: static position, high current.
    fn push(d: &mut StallDetector, c: &StallConfig, n: usize, goal: f32) -> Vec<StallAction> {
        (0..n)
            .map(|_| d.update(Some((0.2, 2.0, goal)), c))
            .filter(|a| *a != StallAction::None)
            .collect()
    }

    /// `n` cycles of a wheel turning at `speed` for `goal` with `current` A.
    fn wheel(
        d: &mut StallDetector,
        c: &StallConfig,
        n: usize,
        (speed, current, goal): (f32, f32, f32),
    ) -> Vec<StallAction> {
        (0..n)
            .map(|_| d.update(Some((speed, current, goal)), c))
            .filter(|a| *a != StallAction::None)
            .collect()
    }

    #[test]
    fn a_wheel_pushing_a_wall_retries_once_then_is_reduced_until_the_command_changes() {
        let c = config();
        let mut d = StallDetector::new(StallKind::Wheel, 2.7, &c);
        // Turning near its goal under a heavy load (a ramp, a threshold): no stall.
        assert!(wheel(&mut d, &c, 100, (2.3, 2.5, 2.5)).is_empty());
        // Asked for nothing, or for a crawl below 0.3 rad/s, while holding: no stall.
        assert!(wheel(&mut d, &c, 100, (0.0, 2.5, 0.0)).is_empty());
        assert!(wheel(&mut d, &c, 100, (0.0, 2.5, 0.2)).is_empty());
        // Against a wall: still, current high.
        assert!(wheel(&mut d, &c, 14, (0.05, 2.5, 2.5)).is_empty());
        assert_eq!(wheel(&mut d, &c, 1, (0.05, 2.5, 2.5)), [StallAction::Retry]);
        assert_eq!(
            d.torque_limit_permille(&c),
            0,
            "the retry is at full torque"
        );
        assert_eq!(
            wheel(&mut d, &c, 15, (0.0, 2.5, 2.5)),
            [StallAction::Reduce]
        );
        assert_eq!(d.torque_limit_permille(&c), 300);
        // The same command (and small changes of it) keeps it reduced; another one restores.
        assert!(wheel(&mut d, &c, 50, (0.0, 1.0, 2.2)).is_empty());
        assert_eq!(
            wheel(&mut d, &c, 1, (0.0, 1.0, -1.0)),
            [StallAction::Restore]
        );
        assert_eq!(d.torque_limit_permille(&c), 0);
        // A retry that turns freely again (half its goal speed) is not stalled any more.
        assert_eq!(wheel(&mut d, &c, 15, (0.0, 2.5, 2.5)), [StallAction::Retry]);
        assert!(wheel(&mut d, &c, 5, (1.5, 2.5, 2.5)).is_empty());
        assert_eq!(wheel(&mut d, &c, 15, (0.0, 2.5, 2.5)), [StallAction::Retry]);
        // Low current (nothing pushing back: a wheel in the air that does not turn) is no
        // stall either.
        let mut free = StallDetector::new(StallKind::Wheel, 2.7, &c);
        assert!(wheel(&mut free, &c, 100, (0.0, 0.2, 2.5)).is_empty());
    }

    #[test]
    fn a_joint_retries_once_then_is_reduced_until_a_new_target() {
        let c = config();
        let mut d = StallDetector::new(StallKind::Joint, 4.2, &c);
        assert!(
            push(&mut d, &c, 14, 1.0).is_empty(),
            "no stall before k = 15 cycles"
        );
        assert_eq!(push(&mut d, &c, 1, 1.0), [StallAction::Retry]);
        assert_eq!(
            d.torque_limit_permille(&c),
            0,
            "the retry is at full torque"
        );
        assert_eq!(push(&mut d, &c, 15, 1.0), [StallAction::Reduce]);
        assert_eq!(d.torque_limit_permille(&c), 300);
        assert!(
            push(&mut d, &c, 100, 1.0).is_empty(),
            "stays reduced while the target stands"
        );
        assert_eq!(d.update(Some((0.2, 0.5, 0.0)), &c), StallAction::Restore);
        assert_eq!(d.torque_limit_permille(&c), 0);
    }

    #[test]
    fn a_gripper_holds_gently_at_once() {
        let c = config();
        let mut d = StallDetector::new(StallKind::Gripper, 2.7, &c);
        assert_eq!(push(&mut d, &c, 15, -0.5), [StallAction::Reduce]);
        assert_eq!(d.torque_limit_permille(&c), 250);
    }

    #[test]
    fn moving_or_low_current_or_at_goal_is_not_a_stall() {
        let c = config();
        let mut d = StallDetector::new(StallKind::Joint, 4.2, &c);
        for i in 0..100 {
            // Moving: position changes by more than static-rad over the window.
            assert_eq!(
                d.update(Some((i as f32 * 0.01, 2.0, 5.0)), &c),
                StallAction::None
            );
        }
        let mut d = StallDetector::new(StallKind::Joint, 4.2, &c);
        for _ in 0..100 {
            // Holding a heavy load: high current, static, with the P loop's steady-state error.
            assert_eq!(d.update(Some((1.0, 2.0, 1.1)), &c), StallAction::None);
            // Low current.
            assert_eq!(d.update(Some((1.0, 0.1, 2.0)), &c), StallAction::None);
        }
    }

    #[test]
    fn a_missing_sample_restarts_the_window() {
        let c = config();
        let mut d = StallDetector::new(StallKind::Joint, 4.2, &c);
        push(&mut d, &c, 14, 1.0);
        d.update(None, &c);
        assert!(push(&mut d, &c, 14, 1.0).is_empty());
        assert_eq!(push(&mut d, &c, 1, 1.0), [StallAction::Retry]);
    }

    #[test]
    fn a_retry_that_moves_returns_to_normal() {
        let c = config();
        let mut d = StallDetector::new(StallKind::Joint, 4.2, &c);
        push(&mut d, &c, 15, 1.0);
        assert_eq!(d.state, StallState::Retrying { position: 0.2 });
        for i in 0..15 {
            d.update(Some((0.2 + i as f32 * 0.02, 2.0, 1.0)), &c);
        }
        assert_eq!(d.state, StallState::Normal);
    }

    #[test]
    fn a_bounce_during_the_retry_is_not_progress() {
        let c = config();
        let mut d = StallDetector::new(StallKind::Joint, 4.2, &c);
        push(&mut d, &c, 15, 1.0);
        // Bounces off the obstacle: current dips, position wobbles by less than new-target-rad.
        for i in 0..15 {
            let (p, cur) = if i % 2 == 0 { (0.21, 0.5) } else { (0.19, 2.0) };
            assert_eq!(d.update(Some((p, cur, 1.0)), &c), StallAction::None);
        }
        assert_eq!(
            push(&mut d, &c, 15, 1.0),
            [StallAction::Reduce],
            "the second stall reduces"
        );
    }
}
