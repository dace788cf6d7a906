//! From the state plane to fleet messages, and from the plan to goal frames. Pure.

use crate::gate::Range;
use crate::schedule::Target;
use crate::schema::{
    BaseMsg, EventRecord, ImageMsg, JointInfoMsg, JointMsg, LayoutMsg, LiftMsg, ObservationMsg,
    StateMsg, SCHEMA_VERSION,
};
use telemetry::frames::{
    GoalFrame, JointLayout, JointState, SupervisorEvent, STATE_FLAG_SAFE_STATE,
};
use telemetry::motion::{BaseCommand, BaseState, LiftCommand, LiftState};

/// The lift and the base as the fleet sees them (each absent when its controller publishes
/// nothing fresh).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Body {
    /// The lift.
    pub lift: Option<LiftMsg>,
    /// The base.
    pub base: Option<BaseMsg>,
}

/// The lift's state as a fleet message.
pub fn lift_msg(l: &LiftState) -> LiftMsg {
    LiftMsg {
        height_m: l.height_m,
        goal_m: l.goal_m,
        state: l.state,
        held: l.held,
        duty_wait_s: l.duty_wait_s,
    }
}

/// The base's state as a fleet message.
pub fn base_msg(b: &BaseState) -> BaseMsg {
    BaseMsg {
        x_m: b.x_m as f32,
        y_m: b.y_m as f32,
        heading_rad: b.theta_rad as f32,
        linear_m_s: b.linear_m_s,
        angular_rad_s: b.angular_rad_s,
        field_distance_m: b.field_distance_m,
        flags: b.flags,
    }
}

/// The layout as a fleet message.
pub fn layout_msg(layout: &JointLayout) -> LayoutMsg {
    LayoutMsg {
        version: SCHEMA_VERSION,
        joints: layout
            .joints()
            .iter()
            .map(|j| JointInfoMsg {
                name: j.name().into(),
                min: j.range_rad[0],
                max: j.range_rad[1],
            })
            .collect(),
    }
}

/// The calibrated ranges the gate checks actions against.
pub fn ranges(layout: &JointLayout) -> Vec<Range> {
    layout
        .joints()
        .iter()
        .map(|j| Range {
            min: j.range_rad[0],
            max: j.range_rad[1],
        })
        .collect()
}

/// A state frame as telemetry.
pub fn state_msg(s: &JointState, body: Body, wall_ms: u64) -> StateMsg {
    StateMsg {
        version: SCHEMA_VERSION,
        seq: s.seq,
        timestamp_ns: s.timestamp_ns,
        wall_ms,
        safe_state: s.flags & STATE_FLAG_SAFE_STATE != 0,
        deadline_misses: s.deadline_misses,
        joints: s
            .joints()
            .iter()
            .map(|j| JointMsg {
                position: j.position_rad,
                velocity: j.velocity_rad_s,
                temperature_c: j.temperature_c,
                current_a: j.current_a,
                goal: j.goal_rad,
                valid: j.is_valid(),
                torque: j.torque_enabled != 0,
                flags: j.flags,
            })
            .collect(),
        lift: body.lift,
        base: body.base,
    }
}

/// A state frame as a policy's observation, with `images` and the body; a servo missing in that
/// cycle reads NaN, never its old value.
pub fn observation_msg(s: &JointState, images: Vec<ImageMsg>, body: Body) -> ObservationMsg {
    let pick = |f: fn(&telemetry::frames::JointSample) -> f32| {
        s.joints()
            .iter()
            .map(|j| if j.is_valid() { f(j) } else { f32::NAN })
            .collect()
    };
    ObservationMsg {
        version: SCHEMA_VERSION,
        seq: s.seq,
        timestamp_ns: s.timestamp_ns,
        position: pick(|j| j.position_rad),
        velocity: pick(|j| j.velocity_rad_s),
        images,
        lift: body.lift,
        base: body.base,
    }
}

/// A supervisor event as the journal keeps it, with the joint named.
pub fn event_record(e: &SupervisorEvent, layout: &JointLayout, wall_ms: u64) -> EventRecord {
    EventRecord {
        timestamp_ns: e.timestamp_ns,
        wall_ms,
        origin_seq: e.seq,
        kind: e
            .kind()
            .map_or_else(|| format!("Unknown{}", e.kind), |k| format!("{k:?}")),
        joint: layout
            .joints()
            .get(usize::from(e.joint))
            .map(|j| j.name().to_string())
            .unwrap_or_default(),
        detail: String::new(),
        bus: e.bus,
        level: e.level,
        value: e.value,
    }
}

/// The goal frame for one tick of the plan.
pub fn goal_frame(target: &Target, joint_count: u32, seq: u64, now_ns: u64) -> GoalFrame {
    GoalFrame {
        seq,
        timestamp_ns: now_ns,
        joint_count,
        mask: target.mask,
        position_rad: target.position,
    }
}

/// The lift's command for one tick of the plan (when it commands the lift).
pub fn lift_command(target: &Target, seq: u64, now_ns: u64) -> Option<LiftCommand> {
    target.lift_m.map(|height_m| LiftCommand {
        seq,
        timestamp_ns: now_ns,
        height_m,
        kind: telemetry::motion::LIFT_COMMAND_GOAL,
    })
}

/// The base's command for one tick of the plan (when it commands the base).
pub fn base_command(target: &Target, seq: u64, now_ns: u64) -> Option<BaseCommand> {
    target
        .base_twist
        .map(|[linear_m_s, angular_rad_s]| BaseCommand {
            seq,
            timestamp_ns: now_ns,
            linear_m_s,
            angular_rad_s,
        })
}

/// "Every `period`": true at most once per period, on the robot's clock.
#[derive(Debug, Clone, Copy)]
pub struct Every {
    period_ns: u64,
    next_ns: u64,
}

impl Every {
    /// `hz` times a second (0: never).
    pub fn hz(hz: f64) -> Self {
        Every {
            period_ns: if hz > 0.0 {
                (1e9 / hz) as u64
            } else {
                u64::MAX
            },
            next_ns: 0,
        }
    }

    /// Due at `now_ns`? (Then the next one is a period later, without catching up.)
    pub fn due(&mut self, now_ns: u64) -> bool {
        if self.period_ns == u64::MAX || now_ns < self.next_ns {
            return false;
        }
        self.next_ns = now_ns.saturating_add(self.period_ns);
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use telemetry::frames::JointSample;

    #[test]
    fn a_missing_servo_is_nan_in_the_observation_and_invalid_in_telemetry() {
        let mut s = JointState {
            joint_count: 2,
            ..JointState::default()
        };
        s.joints[0] = JointSample {
            position_rad: 0.5,
            valid: 1,
            ..JointSample::default()
        };
        s.joints[1] = JointSample {
            position_rad: 0.7, // a stale value that must not leak
            valid: 0,
            ..JointSample::default()
        };
        let o = observation_msg(&s, Vec::new(), Body::default());
        assert_eq!(o.position[0], 0.5);
        assert!(o.position[1].is_nan());
        let t = state_msg(&s, Body::default(), 0);
        assert!(t.joints[0].valid && !t.joints[1].valid);
    }

    #[test]
    fn every_fires_once_per_period_without_catching_up() {
        let mut e = Every::hz(10.0);
        assert!(e.due(0));
        assert!(!e.due(50_000_000));
        assert!(e.due(100_000_000));
        assert!(e.due(1_000_000_000), "after a gap: once");
        assert!(!e.due(1_050_000_000));
        assert!(!Every::hz(0.0).due(0));
    }
}
