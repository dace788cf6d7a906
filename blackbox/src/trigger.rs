//! What freezes a box: the supervisor's and the driver's protection events, the lift stopping
//! on an obstruction, the base's protective stop, the driver's safe state (its supervisor
//! lost), a process lost or back, the operator's stop, and an operator's `nori blackbox save`.

use crate::channel::{event, event_name, EventMessage, Names};
use telemetry::frames::{EventKind, JointState, SupervisorEvent, STATE_FLAG_SAFE_STATE};
use telemetry::motion::{BaseState, LiftState, BASE_FLAG_FIELD_STOPPED};

/// Whether a supervisor event freezes a box.
pub fn freezes(kind: EventKind) -> bool {
    use EventKind::*;
    matches!(
        kind,
        ThermalTrip
            | FirmwareProtection
            | DriverTrip
            | OutputLost
            | StallRetry
            | DriverLost
            | DriverBack
            | OperatorStop
    )
}

/// A trigger that is not a supervisor event, named as one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OwnTrigger {
    /// The lift stopped on an obstruction (its count rose).
    LiftObstruction,
    /// The base's protective field stopped it.
    BaseProtectiveStop,
    /// The driver entered its safe state (its supervisor silent).
    DriverSafeState,
    /// An operator asked (`nori blackbox save`).
    Saved,
}

impl OwnTrigger {
    /// Its event, at `t_ns`.
    pub fn at(self, t_ns: u64, value: f32) -> EventMessage {
        EventMessage {
            timestamp_ns: t_ns,
            kind: crate::channel::snake(&format!("{self:?}")),
            joint: None,
            bus: None,
            level: 0,
            value,
        }
    }
}

/// Watches the plane's frames for what freezes a box; remembers the edges it has seen.
#[derive(Debug, Default)]
pub struct Watch {
    obstructions: Option<u32>,
    base_stopped: bool,
    safe_state: Option<bool>,
    since_ns: u64,
}

impl Watch {
    /// A watch for what happens from `since_ns` (the recorder's start) on.
    pub fn since(since_ns: u64) -> Watch {
        Watch {
            since_ns,
            ..Watch::default()
        }
    }

    /// A supervisor event that freezes a box, as its message. An event from before the
    /// recorder started (the plane's history, which the supervisor offers again to late
    /// subscribers) freezes nothing: it is recorded, not frozen again at every restart.
    pub fn event(&self, e: &SupervisorEvent, names: &Names) -> Option<EventMessage> {
        let kind = e.kind()?;
        (freezes(kind) && e.timestamp_ns >= self.since_ns).then(|| {
            let mut m = event(e, names);
            m.kind = event_name(kind);
            m
        })
    }

    /// The lift's obstruction count rising (not its first reading: a restarted recorder must
    /// not freeze on an old count).
    pub fn lift(&mut self, s: &LiftState) -> Option<EventMessage> {
        let before = self.obstructions.replace(s.obstructions)?;
        (s.obstructions > before)
            .then(|| OwnTrigger::LiftObstruction.at(s.timestamp_ns, s.height_m))
    }

    /// The base's protective field stopping it, on the edge.
    pub fn base(&mut self, s: &BaseState) -> Option<EventMessage> {
        let stopped = s.flags & BASE_FLAG_FIELD_STOPPED != 0
            && (s.requested_linear_m_s != 0.0 || s.requested_angular_rad_s != 0.0);
        let edge = stopped && !self.base_stopped;
        self.base_stopped = stopped;
        edge.then(|| OwnTrigger::BaseProtectiveStop.at(s.timestamp_ns, s.field_distance_m))
    }

    /// The driver entering its safe state after it had left it (not the safe state it starts
    /// in, nor the one a recorder started late first sees).
    pub fn joint_state(&mut self, s: &JointState) -> Option<EventMessage> {
        let safe = s.flags & STATE_FLAG_SAFE_STATE != 0;
        let before = self.safe_state.replace(safe)?;
        (safe && !before).then(|| OwnTrigger::DriverSafeState.at(s.timestamp_ns, 0.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rising_obstruction_count_freezes_and_the_first_reading_does_not() {
        let mut w = Watch::default();
        let mut s = LiftState {
            obstructions: 3,
            ..Default::default()
        };
        assert!(w.lift(&s).is_none());
        assert!(w.lift(&s).is_none());
        s.obstructions = 4;
        assert_eq!(w.lift(&s).unwrap().kind, "lift_obstruction");
        assert!(w.lift(&s).is_none());
    }

    #[test]
    fn the_base_freezes_once_per_protective_stop_of_a_requested_motion() {
        let mut w = Watch::default();
        let mut s = BaseState {
            flags: BASE_FLAG_FIELD_STOPPED,
            ..Default::default()
        };
        assert!(
            w.base(&s).is_none(),
            "standing still before a wall is no stop"
        );
        s.requested_linear_m_s = 0.3;
        assert_eq!(w.base(&s).unwrap().kind, "base_protective_stop");
        assert!(w.base(&s).is_none());
        s.flags = 0;
        assert!(w.base(&s).is_none());
        s.flags = BASE_FLAG_FIELD_STOPPED;
        assert!(w.base(&s).is_some());
    }

    #[test]
    fn the_safe_state_freezes_on_entry_after_driving() {
        let mut w = Watch::default();
        let mut s = JointState {
            flags: STATE_FLAG_SAFE_STATE,
            ..Default::default()
        };
        assert!(w.joint_state(&s).is_none(), "the start-up safe state");
        s.flags = 0;
        assert!(w.joint_state(&s).is_none());
        s.flags = STATE_FLAG_SAFE_STATE;
        assert_eq!(w.joint_state(&s).unwrap().kind, "driver_safe_state");
    }

    #[test]
    fn an_event_from_before_the_recorder_started_freezes_nothing() {
        // Found by the review: the supervisor offers its last events again, and a restarted
        // recorder froze a box for an old trip at every restart.
        let w = Watch::since(1_000);
        let mut e = SupervisorEvent {
            kind: EventKind::ThermalTrip as u8,
            timestamp_ns: 999,
            ..Default::default()
        };
        assert!(w.event(&e, &Names::default()).is_none());
        e.timestamp_ns = 1_000;
        assert_eq!(w.event(&e, &Names::default()).unwrap().kind, "thermal_trip");
    }

    #[test]
    fn protection_events_freeze_and_routine_ones_do_not() {
        assert!(freezes(EventKind::ThermalTrip));
        assert!(freezes(EventKind::StallRetry));
        assert!(!freezes(EventKind::ThermalWarning));
        assert!(!freezes(EventKind::TorqueRestored));
    }
}
