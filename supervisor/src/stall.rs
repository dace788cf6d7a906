//! Stall detection and reaction, per joint (paper, "Preventing stall").
//!
//! Over a window of k control cycles, a joint whose current stays high while its position stays
//! static, and which is trying to move (far from its goal), has stalled. A gripper then holds with
//! a reduced grip torque; any other joint gets one retry at full torque and, if it stalls again,
//! a reduced torque until a new target is commanded.

use crate::config::StallConfig;

/// Longest window supported (a fixed ring: nothing allocates per cycle).
pub const MAX_WINDOW: usize = 64;

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

/// One joint's detector.
#[derive(Debug, Clone)]
pub struct StallDetector {
    gripper: bool,
    current_threshold: f32,
    min_error: f32,
    ring: [Sample; MAX_WINDOW],
    filled: usize,
    next: usize,
    /// The joint's state.
    pub state: StallState,
}

impl StallDetector {
    /// A detector for a joint whose servo stalls at `stall_current` A.
    pub fn new(gripper: bool, stall_current: f32, config: &StallConfig) -> Self {
        let (fraction, min_error) = match gripper {
            true => (
                config.gripper_current_fraction,
                config.gripper_min_error_rad,
            ),
            false => (config.current_fraction, config.min_error_rad),
        };
        StallDetector {
            gripper,
            current_threshold: fraction * stall_current,
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

    /// Feeds one cycle. `sample` is `None` when the joint was missing this cycle: the window
    /// restarts (a stall is only declared over k consecutive readings).
    pub fn update(&mut self, sample: Option<(f32, f32, f32)>, config: &StallConfig) -> StallAction {
        let Some((position, current, goal)) = sample else {
            self.clear_window();
            return StallAction::None;
        };
        if let StallState::Reduced { goal: held } = self.state {
            if (goal - held).abs() > config.new_target_rad {
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
        let trying = (goal - position).abs() >= self.min_error;
        if let StallState::Retrying { position: stuck } = self.state {
            // The retry made progress: it is not stuck any more (a bounce off the obstacle is
            // not progress, so one window without a stall is not enough).
            if !trying || (position - stuck).abs() > config.new_target_rad {
                self.state = StallState::Normal;
            }
        }
        if self.filled < k || !trying || !self.stalled(k, config) {
            return StallAction::None;
        }
        self.clear_window();
        match (self.state, self.gripper) {
            (StallState::Normal, false) => {
                self.state = StallState::Retrying { position };
                StallAction::Retry
            }
            _ => {
                self.state = StallState::Reduced { goal };
                StallAction::Reduce
            }
        }
    }

    fn stalled(&self, k: usize, config: &StallConfig) -> bool {
        let window = &self.ring[..k];
        let high = window
            .iter()
            .all(|s| s.current.abs() >= self.current_threshold);
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
            StallState::Reduced { .. } if self.gripper => {
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

    #[test]
    fn a_joint_retries_once_then_is_reduced_until_a_new_target() {
        let c = config();
        let mut d = StallDetector::new(false, 4.2, &c);
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
        let mut d = StallDetector::new(true, 2.7, &c);
        assert_eq!(push(&mut d, &c, 15, -0.5), [StallAction::Reduce]);
        assert_eq!(d.torque_limit_permille(&c), 250);
    }

    #[test]
    fn moving_or_low_current_or_at_goal_is_not_a_stall() {
        let c = config();
        let mut d = StallDetector::new(false, 4.2, &c);
        for i in 0..100 {
            // Moving: position changes by more than static-rad over the window.
            assert_eq!(
                d.update(Some((i as f32 * 0.01, 2.0, 5.0)), &c),
                StallAction::None
            );
        }
        let mut d = StallDetector::new(false, 4.2, &c);
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
        let mut d = StallDetector::new(false, 4.2, &c);
        push(&mut d, &c, 14, 1.0);
        d.update(None, &c);
        assert!(push(&mut d, &c, 14, 1.0).is_empty());
        assert_eq!(push(&mut d, &c, 1, 1.0), [StallAction::Retry]);
    }

    #[test]
    fn a_retry_that_moves_returns_to_normal() {
        let c = config();
        let mut d = StallDetector::new(false, 4.2, &c);
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
        let mut d = StallDetector::new(false, 4.2, &c);
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
