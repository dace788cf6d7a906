//! The stop and resume buttons' answers, pure: a press is answered only once the supervisor
//! has shown it heard it, and a press nobody heard is said to be unheard, never `ok`. An
//! operator who reads "stopped" while no supervisor runs would walk up to an arm that still
//! moves (`nori stop` answers the same way).
//!
//! Heard, for a stop: the supervisor's `OperatorStop` event, or its lift allowance stamped
//! after the press and refusing for the operator's stop (the stop was already in force: a
//! second stop makes no event). For a resume: `OperatorResume`, its refusal (nothing was
//! stopped), or an allowance after the press with no stop in it.

use telemetry::frames::{EventKind, SupervisorEvent, COMMAND_REFUSED_NOT_STOPPED};
use telemetry::motion::{LiftAllowance, LIFT_REFUSED_OPERATOR_STOP};

/// How long a press waits for the supervisor, ns (its answers come within a few ms).
pub const ANSWER_WITHIN_NS: u64 = 2_000_000_000;

/// Which button.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Press {
    /// Stop the robot.
    Stop,
    /// End the stop.
    Resume,
}

/// What became of a press.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Answer {
    /// The supervisor took it: the robot is stopped (or resumed).
    Done,
    /// A resume with no stop in force: nothing to do.
    NotStopped,
    /// No supervisor showed it heard the press within [`ANSWER_WITHIN_NS`].
    Unheard,
}

impl Answer {
    /// What the page shows: `(ok, text)`.
    pub fn reply(self, press: Press) -> (bool, &'static str) {
        match (self, press) {
            (Answer::Done, Press::Stop) => (true, "stopped: the supervisor holds the robot until resumed"),
            (Answer::Done, Press::Resume) => (true, "resumed"),
            (Answer::NotStopped, _) => (true, "nothing to do: the robot was not stopped"),
            (Answer::Unheard, Press::Stop) => (
                false,
                "NO SUPERVISOR HEARD THE STOP: the robot is not known to be stopped (is the supervisor running?)",
            ),
            (Answer::Unheard, Press::Resume) => {
                (false, "no supervisor heard the resume (is the supervisor running?)")
            }
        }
    }
}

/// A press waiting for the supervisor's answer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pending {
    /// The page that pressed.
    pub page: u64,
    /// Which button.
    pub press: Press,
    sent_ns: u64,
}

impl Pending {
    /// `press` from `page`, its command published at `sent_ns`.
    pub fn new(page: u64, press: Press, sent_ns: u64) -> Pending {
        Pending {
            page,
            press,
            sent_ns,
        }
    }

    /// The answer a supervisor event gives, if it is one.
    pub fn on_event(&self, e: &SupervisorEvent) -> Option<Answer> {
        if e.timestamp_ns < self.sent_ns {
            return None;
        }
        match (self.press, e.kind()?) {
            (Press::Stop, EventKind::OperatorStop) => Some(Answer::Done),
            (Press::Resume, EventKind::OperatorResume) => Some(Answer::Done),
            (Press::Resume, EventKind::CommandRefused)
                if e.level == COMMAND_REFUSED_NOT_STOPPED =>
            {
                Some(Answer::NotStopped)
            }
            _ => None,
        }
    }

    /// The answer the supervisor's allowance gives, if it is one.
    pub fn on_allowance(&self, a: &LiftAllowance) -> Option<Answer> {
        if a.timestamp_ns <= self.sent_ns {
            return None;
        }
        let stopped = a.refused & LIFT_REFUSED_OPERATOR_STOP != 0;
        match self.press {
            Press::Stop => stopped.then_some(Answer::Done),
            // Before the supervisor read the command its allowance still says stopped.
            Press::Resume => (!stopped).then_some(Answer::Done),
        }
    }

    /// [`Answer::Unheard`] once the press has waited its time at `now_ns`.
    pub fn expired(&self, now_ns: u64) -> Option<Answer> {
        (now_ns.saturating_sub(self.sent_ns) >= ANSWER_WITHIN_NS).then_some(Answer::Unheard)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn event(kind: EventKind, level: u8, at: u64) -> SupervisorEvent {
        SupervisorEvent {
            timestamp_ns: at,
            kind: kind as u8,
            level,
            ..SupervisorEvent::default()
        }
    }

    fn allowance(refused: u8, at: u64) -> LiftAllowance {
        LiftAllowance {
            timestamp_ns: at,
            refused,
            ..LiftAllowance::default()
        }
    }

    #[test]
    fn a_stop_is_done_only_when_the_supervisor_shows_it() {
        let p = Pending::new(3, Press::Stop, 1_000);
        assert_eq!(
            p.on_event(&event(EventKind::OperatorStop, 0, 1_000)),
            Some(Answer::Done)
        );
        // An event from before the press, or of another kind, says nothing.
        assert_eq!(p.on_event(&event(EventKind::OperatorStop, 0, 999)), None);
        assert_eq!(
            p.on_event(&event(EventKind::OperatorResume, 0, 2_000)),
            None
        );
        assert_eq!(p.on_event(&event(EventKind::TorqueReduced, 0, 2_000)), None);
        // Already stopped: the allowance after the press says so.
        assert_eq!(
            p.on_allowance(&allowance(LIFT_REFUSED_OPERATOR_STOP, 1_001)),
            Some(Answer::Done)
        );
        assert_eq!(
            p.on_allowance(&allowance(LIFT_REFUSED_OPERATOR_STOP | 1, 1_001)),
            Some(Answer::Done)
        );
        assert_eq!(
            p.on_allowance(&allowance(LIFT_REFUSED_OPERATOR_STOP, 1_000)),
            None
        );
        // Not (yet) stopped, or refused for the duty budget alone: no answer.
        assert_eq!(p.on_allowance(&allowance(0, 5_000)), None);
        assert_eq!(p.on_allowance(&allowance(1, 5_000)), None);
        // Nobody heard it: said so, never ok.
        assert_eq!(p.expired(1_000 + ANSWER_WITHIN_NS - 1), None);
        assert_eq!(p.expired(1_000 + ANSWER_WITHIN_NS), Some(Answer::Unheard));
        assert!(!Answer::Unheard.reply(Press::Stop).0);
        assert!(Answer::Unheard
            .reply(Press::Stop)
            .1
            .contains("NO SUPERVISOR"));
    }

    #[test]
    fn a_resume_is_done_refused_or_unheard() {
        let p = Pending::new(1, Press::Resume, 1_000);
        assert_eq!(
            p.on_event(&event(EventKind::OperatorResume, 0, 1_500)),
            Some(Answer::Done)
        );
        assert_eq!(p.on_event(&event(EventKind::OperatorStop, 0, 1_500)), None);
        assert_eq!(
            p.on_event(&event(
                EventKind::CommandRefused,
                COMMAND_REFUSED_NOT_STOPPED,
                1_500
            )),
            Some(Answer::NotStopped)
        );
        assert_eq!(
            p.on_event(&event(EventKind::CommandRefused, 0, 1_500)),
            None
        );
        assert_eq!(
            p.on_event(&event(
                EventKind::CommandRefused,
                COMMAND_REFUSED_NOT_STOPPED,
                999
            )),
            None
        );
        // The allowance before the supervisor read the command still says stopped.
        assert_eq!(
            p.on_allowance(&allowance(LIFT_REFUSED_OPERATOR_STOP, 1_500)),
            None
        );
        assert_eq!(p.on_allowance(&allowance(0, 1_500)), Some(Answer::Done));
        assert_eq!(p.on_allowance(&allowance(0, 900)), None);
        assert!(Answer::Done.reply(Press::Resume).0);
        assert!(!Answer::Unheard.reply(Press::Resume).0);
    }
}
