//! The supervisor process's loop in process: `Process::poll` against queues standing for the
//! state plane and the trip record, on a clock the test chooses, with every call the loop makes
//! logged in order. (The process tests in `tests/` run the binary over real iceoryx2.)

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::VecDeque;
use supervisor::process::{Change, Process, SupervisorIo};
use supervisor::SupervisorConfig;
use telemetry::config::ProcessConfig;
use telemetry::frames::{
    Directives, EventKind, GripFrame, Heartbeat, JointInfo, JointLayout, JointRole, JointSample,
    JointState, SupervisorCommand, SupervisorEvent, COMMAND_REENABLE_BUS, COMMAND_RESUME,
    COMMAND_STOP, DIRECTIVE_FLAG_STOP,
};
use telemetry::latch::LatchError;
use telemetry::motion::{
    LiftAllowance, LiftState, LIFT_REFUSED_OPERATOR_STOP, LIFT_REFUSED_RECORD,
};

use telemetry::clock::MS;

/// One call the loop made, in order.
#[derive(Debug, Clone, PartialEq)]
enum Call {
    Directives { bus_enabled: u32, stop: bool },
    Event(Option<EventKind>, f32),
    Heartbeat,
    Grip,
    Save(Vec<String>),
}

#[derive(Default)]
struct Queues {
    layout: Option<JointLayout>,
    states: VecDeque<JointState>,
    commands: VecDeque<SupervisorCommand>,
    beats: VecDeque<Heartbeat>,
    calls: Vec<Call>,
    beat_seqs: Vec<u64>,
    lift_states: VecDeque<LiftState>,
    allowances: Vec<LiftAllowance>,
    /// The record as last saved, whole.
    record: Vec<String>,
    /// Saving the record fails (a full or read-only disk).
    saves_fail: bool,
}

impl SupervisorIo for Queues {
    fn layout(&mut self) -> Option<JointLayout> {
        self.layout
    }
    fn next_state(&mut self) -> Option<JointState> {
        self.states.pop_front()
    }
    fn next_command(&mut self) -> Option<SupervisorCommand> {
        self.commands.pop_front()
    }
    fn next_driver_beat(&mut self) -> Option<Heartbeat> {
        self.beats.pop_front()
    }
    fn directives(&mut self, d: &Directives) {
        self.calls.push(Call::Directives {
            bus_enabled: d.bus_enabled,
            stop: d.flags & DIRECTIVE_FLAG_STOP != 0,
        });
    }
    fn event(&mut self, e: &SupervisorEvent) {
        self.calls.push(Call::Event(e.kind(), e.value));
    }
    fn heartbeat(&mut self, h: &Heartbeat) {
        self.calls.push(Call::Heartbeat);
        self.beat_seqs.push(h.seq);
    }
    fn grip(&mut self, _: &GripFrame) {
        self.calls.push(Call::Grip);
    }
    fn save_trips(&mut self, joints: &[String]) -> Result<(), LatchError> {
        if self.saves_fail {
            return Err(LatchError {
                path: "trips".into(),
                action: "writing",
                source: std::io::Error::other("no space left on device"),
            });
        }
        // The lift's budget line aside: the trips and the stop are what most tests look at.
        self.record = joints.to_vec();
        let kept = joints.iter().filter(|l| !l.starts_with("@lift-duty"));
        self.calls.push(Call::Save(kept.cloned().collect()));
        Ok(())
    }
    fn next_lift_state(&mut self) -> Option<LiftState> {
        self.lift_states.pop_front()
    }
    fn lift_allowance(&mut self, a: &LiftAllowance) {
        self.allowances.push(*a);
    }
}

/// Two buses: bus 0 two arm joints, bus 1 one joint; firmware cutoffs at 60 °C.
fn layout() -> JointLayout {
    let mut l = JointLayout {
        joint_count: 3,
        bus_count: 2,
        ..JointLayout::default()
    };
    l.set_bus_name(0, "left_arm");
    l.set_bus_name(1, "right_arm");
    for (i, (name, bus)) in [
        ("left_elbow", 0),
        ("left_wrist_pitch", 0),
        ("right_elbow", 1),
    ]
    .into_iter()
    .enumerate()
    {
        let mut info = JointInfo {
            bus,
            role: JointRole::Joint as u8,
            model: 2825,
            max_temperature_c: 60,
            ..JointInfo::default()
        };
        info.set_name(name);
        l.joints[i] = info;
    }
    l
}

/// A frame at `t` with joint 0 at `hot_c` and the others at 30 °C.
fn state(seq: u64, t: u64, hot_c: f32) -> JointState {
    let mut s = JointState {
        seq,
        timestamp_ns: t,
        joint_count: 3,
        ..JointState::default()
    };
    for (i, j) in s.joints[..3].iter_mut().enumerate() {
        *j = JointSample {
            valid: 1,
            torque_enabled: 1,
            temperature_c: if i == 0 { hot_c } else { 30.0 },
            ..JointSample::default()
        };
    }
    s
}

fn config() -> SupervisorConfig {
    SupervisorConfig::embedded().unwrap()
}

fn beat(pid: u32) -> Heartbeat {
    Heartbeat {
        pid,
        ..Heartbeat::default()
    }
}

fn events(io: &Queues, kind: EventKind) -> Vec<f32> {
    io.calls
        .iter()
        .filter_map(|c| match c {
            Call::Event(Some(k), v) if *k == kind => Some(*v),
            _ => None,
        })
        .collect()
}

#[test]
fn nothing_is_published_before_the_layout_and_the_heartbeat_follows_it() {
    let mut p = Process::new(config(), vec![], 7);
    let mut io = Queues::default();
    for k in 0..20 {
        assert_eq!(p.poll(&mut io, k * MS).unwrap(), None);
    }
    assert!(io.calls.is_empty(), "{:?}", io.calls);
    io.layout = Some(layout());
    let change = p.poll(&mut io, 20 * MS).unwrap();
    assert_eq!(
        change,
        Some(Change::Supervising {
            joints: 3,
            restored: vec![]
        })
    );
    assert_eq!(
        io.calls,
        [
            Call::Directives {
                bus_enabled: u32::MAX,
                stop: false
            },
            Call::Heartbeat
        ]
    );
    assert!(p.supervisor().is_some());
    // The same layout again is no change; the next heartbeat waits for the period (5 ms).
    io.calls.clear();
    io.states.push_back(state(1, 24 * MS, 30.0));
    assert_eq!(p.poll(&mut io, 24 * MS).unwrap(), None);
    assert_eq!(io.calls, [Call::Grip], "{:?}", io.calls);
    assert_eq!(p.frames(), 1);
    io.calls.clear();
    p.poll(&mut io, 25 * MS).unwrap();
    assert_eq!(
        io.calls,
        [
            Call::Directives {
                bus_enabled: u32::MAX,
                stop: false
            },
            Call::Heartbeat
        ]
    );
    // Heartbeats count up: the driver tells a live supervisor from a replayed frame by them.
    assert_eq!(io.beat_seqs, [1, 2]);
}

#[test]
fn the_loop_turns_until_told_to_stop_or_its_time_is_up() {
    use std::sync::atomic::AtomicBool;
    use std::time::Duration;
    let mut io = Queues {
        layout: Some(layout()),
        ..Queues::default()
    };
    let mut turns = 0;
    let mut p = Process::new(config(), vec![], 7);
    let stop = AtomicBool::new(true);
    supervisor::process::run(&mut p, &mut io, &stop, None, &mut |_, _| turns += 1).unwrap();
    assert_eq!(turns, 0, "stopped before the first turn");
    stop.store(false, std::sync::atomic::Ordering::Relaxed);
    let run_for = Some(Duration::from_millis(30));
    supervisor::process::run(&mut p, &mut io, &stop, run_for, &mut |_, _| turns += 1).unwrap();
    assert!(turns > 0, "the loop never turned");
    assert!(io.calls.contains(&Call::Heartbeat));
    // A layout it cannot supervise ends the loop with the error.
    let mut bad = layout();
    bad.joints[0].max_temperature_c = 59;
    let mut p = Process::new(config(), vec![], 7);
    io.layout = Some(bad);
    let e = supervisor::process::run(&mut p, &mut io, &stop, run_for, &mut |_, _| {});
    assert!(e.is_err());
}

#[test]
fn a_trip_is_saved_before_the_directives_that_announce_it_and_they_go_out_at_once() {
    let mut p = Process::new(config(), vec![], 7);
    let mut io = Queues {
        layout: Some(layout()),
        ..Queues::default()
    };
    p.poll(&mut io, 0).unwrap();
    io.calls.clear();
    // Within the publish period (1 ms later): only a change may publish.
    io.states.push_back(state(1, MS, 59.5));
    p.poll(&mut io, MS).unwrap();
    let save = io
        .calls
        .iter()
        .position(|c| matches!(c, Call::Save(_)))
        .expect("the trip was recorded");
    let off = io
        .calls
        .iter()
        .position(|c| matches!(c, Call::Directives { bus_enabled, .. } if bus_enabled & 1 == 0))
        .expect("bus 0 turned off at once, not at the next period");
    assert!(
        save < off,
        "recorded after it was announced: {:?}",
        io.calls
    );
    assert_eq!(
        io.calls[save],
        Call::Save(vec!["left_elbow".into(), "left_wrist_pitch".into()])
    );
    assert_eq!(events(&io, EventKind::ThermalTrip), [59.5]);
}

#[test]
fn recorded_trips_latch_again_and_a_release_keeps_what_this_layout_lacks() {
    let record = vec!["left_wrist_pitch".to_string(), "head_pan".to_string()];
    let mut p = Process::new(config(), record, 7);
    let mut io = Queues {
        layout: Some(layout()),
        ..Queues::default()
    };
    let change = p.poll(&mut io, 0).unwrap();
    assert_eq!(
        change,
        Some(Change::Supervising {
            joints: 3,
            restored: vec![0]
        })
    );
    // The very first directives already keep bus 0 off.
    assert_eq!(
        io.calls[1],
        Call::Directives {
            bus_enabled: !1,
            stop: false
        }
    );
    // Cool, then released by the operator: the record drops bus 0's joints, keeps head_pan.
    io.states.push_back(state(1, 10 * MS, 30.0));
    io.commands.push_back(SupervisorCommand {
        kind: COMMAND_REENABLE_BUS,
        bus: 0,
        ..SupervisorCommand::default()
    });
    io.calls.clear();
    p.poll(&mut io, 10 * MS).unwrap();
    assert_eq!(
        events(&io, EventKind::BusReenabled).len(),
        1,
        "{:?}",
        io.calls
    );
    assert!(
        io.calls.contains(&Call::Save(vec!["head_pan".into()])),
        "{:?}",
        io.calls
    );
    assert!(io.calls.contains(&Call::Directives {
        bus_enabled: u32::MAX,
        stop: false
    }));
}

#[test]
fn a_silent_driver_is_reported_lost_once_and_its_successor_back_with_its_pid() {
    let config = config();
    let timeout = config.driver_timeout_ms * MS;
    let mut p = Process::new(config, vec![], 7);
    let mut io = Queues {
        layout: Some(layout()),
        ..Queues::default()
    };
    io.beats.push_back(beat(100));
    p.poll(&mut io, 0).unwrap();
    for k in 1..=3 {
        p.poll(&mut io, k * timeout).unwrap();
    }
    let lost = events(&io, EventKind::DriverLost);
    assert_eq!(lost.len(), 1, "{:?}", io.calls);
    assert!(lost[0] * 1e9 > timeout as f32, "silence {} s", lost[0]);
    io.beats.push_back(beat(200));
    p.poll(&mut io, 4 * timeout).unwrap();
    let back = events(&io, EventKind::DriverBack);
    assert_eq!(back.first(), Some(&200.0), "{:?}", io.calls);
}

#[test]
fn a_layout_without_room_for_the_software_tier_is_an_error() {
    let mut l = layout();
    l.joints[2].max_temperature_c = 59;
    let mut p = Process::new(config(), vec![], 7);
    let mut io = Queues {
        layout: Some(l),
        ..Queues::default()
    };
    let e = p.poll(&mut io, 0).unwrap_err().to_string();
    assert!(e.contains("right_elbow"), "{e}");
    assert!(io.calls.is_empty());
}

/// A lift rated 4 s on per 36 s off, travel again with 2 s regained (a test spends it).
fn short_lift_rating() -> SupervisorConfig {
    let text = SupervisorConfig::DEFAULT_TOML.replacen("on-s = 120", "on-s = 4", 1);
    let text = text.replacen("off-s = 1080", "off-s = 36", 1);
    let text = text.replacen("resume-s = 30", "resume-s = 2", 1);
    SupervisorConfig::parse(&text, "test").unwrap()
}

/// The lift's state at `t_ms`, moving or not.
fn lift_state(t_ms: u64, moving: bool) -> LiftState {
    LiftState {
        timestamp_ns: t_ms * MS,
        velocity_m_s: if moving { 0.03 } else { 0.0 },
        ..LiftState::default()
    }
}

/// The lift's duty-cycle budget runs with or without the driver's layout (the lift is not on
/// its buses): moving for the rated time spends it, the allowance turns to a refusal at once
/// with the rest it needs, and comes back once the resume time is regained.
#[test]
fn the_lift_moving_past_its_rating_is_refused_travel_and_told_for_how_long() {
    let config = short_lift_rating();
    let mut p = Process::new(config, Vec::new(), 1);
    let mut io = Queues::default();
    let state = lift_state;
    // 10 ms states of a moving lift for 3.99 s: still allowed, the rest of the budget said.
    let mut t = 0;
    while t < 3990 {
        io.lift_states.push_back(state(t, true));
        p.poll(&mut io, t * MS).unwrap();
        t += 10;
    }
    let a = *io.allowances.last().unwrap();
    assert_eq!(a.allowed, 1);
    assert!((a.seconds - 0.01).abs() < 0.02, "{a:?}");
    // At 4 s: refused, 2 s of running to regain at 4/36 s per s of rest: 18 s.
    io.lift_states.push_back(state(t, true));
    io.lift_states.push_back(state(t + 10, false));
    p.poll(&mut io, (t + 10) * MS).unwrap();
    let a = *io.allowances.last().unwrap();
    assert_eq!(a.allowed, 0, "{a:?}");
    assert!((a.seconds - 18.0).abs() < 0.2, "{a:?}");
    // Resting 17 s: still refused; 18 s: allowed again, with 2 s of running.
    let rest_from = t + 10;
    for k in 1..=1800u64 {
        io.lift_states.push_back(state(rest_from + 10 * k, false));
        p.poll(&mut io, (rest_from + 10 * k) * MS).unwrap();
        let a = *io.allowances.last().unwrap();
        if k == 1700 {
            assert_eq!(a.allowed, 0, "allowed after 17 s of rest");
        }
    }
    let a = *io.allowances.last().unwrap();
    assert_eq!(a.allowed, 1, "{a:?}");
    assert!((a.seconds - 2.0).abs() < 0.05, "{a:?}");
    // Published with the heartbeat's period, each newer than the last.
    assert!(io.allowances.windows(2).all(|w| w[1].seq == w[0].seq + 1));
}

/// The lift's budget must outlive the supervisor: while the record cannot be saved (a full or
/// read-only disk), a restart would forget what the motor ran, so the lift is refused travel
/// until a save succeeds again (tried again every second). (Before: a failed save was only
/// logged, and the lift ran on a budget no restart would remember.)
#[test]
fn the_lift_is_refused_travel_while_its_budget_cannot_be_recorded() {
    let mut p = Process::new(short_lift_rating(), Vec::new(), 1);
    let mut io = Queues {
        saves_fail: true,
        ..Queues::default()
    };
    // Moving for 1 s: the budget is saved every 0.5 s of running, and each save fails.
    let mut t = 0;
    while t < 1000 {
        io.lift_states.push_back(lift_state(t, true));
        p.poll(&mut io, t * MS).unwrap();
        t += 10;
    }
    let a = *io.allowances.last().unwrap();
    assert_eq!((a.allowed, a.refused), (0, LIFT_REFUSED_RECORD), "{a:?}");
    // The disk writable again: the next try saves it, travel is allowed again.
    io.saves_fail = false;
    while t < 2200 {
        io.lift_states.push_back(lift_state(t, false));
        p.poll(&mut io, t * MS).unwrap();
        t += 10;
    }
    let a = *io.allowances.last().unwrap();
    assert_eq!((a.allowed, a.refused), (1, 0), "{a:?}");
    assert!(
        io.record.iter().any(|l| l.starts_with("@lift-duty")),
        "{:?}",
        io.record
    );
}

/// An operator's stop is recorded before the directives that carry it go out (at once, not at
/// the next period), survives a restart of the supervisor (the new one's first directives
/// carry it, before any command), and only the resume clears it, from the record too; trips
/// in the record stay where they are.
#[test]
fn an_operators_stop_is_recorded_before_it_is_announced_and_outlives_a_restart() {
    let stop_line = telemetry::latch::OPERATOR_STOP.to_string();
    let command = |kind| SupervisorCommand {
        seq: 1,
        kind,
        ..SupervisorCommand::default()
    };
    let mut p = Process::new(config(), vec!["head_pan".into()], 7);
    let mut io = Queues {
        layout: Some(layout()),
        ..Queues::default()
    };
    p.poll(&mut io, 0).unwrap();
    io.calls.clear();
    io.commands.push_back(command(COMMAND_STOP));
    p.poll(&mut io, MS).unwrap();
    let saved = io
        .calls
        .iter()
        .position(|c| *c == Call::Save(vec!["head_pan".into(), stop_line.clone()]))
        .expect("the stop recorded");
    let announced = io
        .calls
        .iter()
        .position(|c| matches!(c, Call::Directives { stop: true, .. }))
        .expect("the stop announced at once, 1 ms after the last directives");
    assert!(saved < announced, "{:?}", io.calls);
    assert!(io
        .calls
        .contains(&Call::Event(Some(EventKind::OperatorStop), 0.0)));
    // A second press: nothing new.
    io.calls.clear();
    io.commands.push_back(command(COMMAND_STOP));
    p.poll(&mut io, 2 * MS).unwrap();
    assert!(!io
        .calls
        .iter()
        .any(|c| matches!(c, Call::Save(_) | Call::Event(..))));

    // A new supervisor on the record as saved: stopped from its first directives.
    let mut q = Process::new(config(), vec!["head_pan".into(), stop_line.clone()], 8);
    let mut io = Queues {
        layout: Some(layout()),
        ..Queues::default()
    };
    q.poll(&mut io, 0).unwrap();
    let first = io
        .calls
        .iter()
        .find(|c| matches!(c, Call::Directives { .. }))
        .unwrap();
    assert_eq!(
        *first,
        Call::Directives {
            bus_enabled: u32::MAX,
            stop: true
        }
    );
    assert!(
        !io.calls.iter().any(|c| matches!(c, Call::Save(_))),
        "nothing to save"
    );
    io.calls.clear();
    io.commands.push_back(command(COMMAND_RESUME));
    q.poll(&mut io, MS).unwrap();
    let saved = io
        .calls
        .iter()
        .position(|c| *c == Call::Save(vec!["head_pan".into()]))
        .expect("the stop taken off the record, the trip kept");
    let announced = io
        .calls
        .iter()
        .position(|c| matches!(c, Call::Directives { stop: false, .. }))
        .expect("the end announced at once");
    assert!(saved < announced);
    // Resuming what is not stopped is refused and said.
    io.calls.clear();
    io.commands.push_back(command(COMMAND_RESUME));
    q.poll(&mut io, 2 * MS).unwrap();
    assert!(io.calls.iter().any(|c| matches!(c, Call::Event(Some(EventKind::CommandRefused), v) if *v == f32::from(COMMAND_RESUME))));
}

/// An operator's command of `kind`.
fn operator(kind: u8) -> SupervisorCommand {
    SupervisorCommand {
        seq: 1,
        kind,
        ..SupervisorCommand::default()
    }
}

/// A supervisor with no record, supervising the driver's layout after its first turn.
fn supervising() -> (Process, Queues) {
    let mut p = Process::new(config(), Vec::new(), 7);
    let mut io = Queues {
        layout: Some(layout()),
        ..Queues::default()
    };
    p.poll(&mut io, 0).unwrap();
    (p, io)
}

/// The newest allowance's word: travel allowed.
fn lift_allowed(io: &Queues) -> bool {
    io.allowances.last().expect("an allowance").allowed == 1
}

/// The operator's stop stops the lift too (the lift is not on the driver's buses: its
/// allowance carries the stop), with or without the driver's layout, from a restarted
/// supervisor's first allowance on, until the resume.
#[test]
fn an_operators_stop_refuses_the_lift_travel_until_the_resume() {
    let stop = operator;
    // With the driver's layout.
    let (mut p, mut io) = supervising();
    assert!(lift_allowed(&io));
    io.commands.push_back(stop(COMMAND_STOP));
    p.poll(&mut io, MS).unwrap();
    let refused = *io.allowances.last().unwrap();
    assert_eq!(
        (refused.allowed, refused.refused, refused.timestamp_ns),
        (0, LIFT_REFUSED_OPERATOR_STOP, MS),
        "said in the turn the stop came"
    );
    p.poll(&mut io, 10 * MS).unwrap();
    assert!(!lift_allowed(&io));
    io.commands.push_back(stop(COMMAND_RESUME));
    p.poll(&mut io, 11 * MS).unwrap();
    assert!(lift_allowed(&io));

    // The driver dead (no layout): the stop still reaches the lift, and is recorded.
    let mut p = Process::new(config(), Vec::new(), 8);
    let mut io = Queues::default();
    p.poll(&mut io, 0).unwrap();
    assert!(lift_allowed(&io));
    io.commands.push_back(stop(COMMAND_STOP));
    p.poll(&mut io, MS).unwrap();
    assert!(!lift_allowed(&io), "{:?}", io.allowances.last());
    let stop_line = telemetry::latch::OPERATOR_STOP.to_string();
    assert!(
        io.calls
            .iter()
            .any(|c| matches!(c, Call::Save(lines) if lines.contains(&stop_line))),
        "{:?}",
        io.calls
    );

    // Restarted with the stop in its record and no driver: refused from the first allowance.
    let mut p = Process::new(config(), vec![stop_line], 9);
    let mut io = Queues::default();
    p.poll(&mut io, 0).unwrap();
    assert!(!lift_allowed(&io), "{:?}", io.allowances);
}

/// The lift motor's duty budget outlives the supervisor as the trip record does: a
/// supervisor restarted (a crash loop) after the budget is spent still refuses travel, and
/// grants it again only once the rest the motor needs has passed.
#[test]
fn a_restarted_supervisor_remembers_the_lifts_spent_budget() {
    let config = short_lift_rating();
    let mut p = Process::new(config.clone(), Vec::new(), 1);
    let mut io = Queues::default();
    let state = lift_state;
    let mut t = 0;
    while t <= 4100 {
        io.lift_states.push_back(state(t, true));
        p.poll(&mut io, t * MS).unwrap();
        t += 10;
    }
    assert!(!lift_allowed(&io), "spent");
    let record = io.record.clone();
    // Killed and started again 1 s later: still refused, for about the rest it still needs.
    let mut q = Process::new(config.clone(), record.clone(), 2);
    let mut io = Queues::default();
    q.poll(&mut io, (t + 1000) * MS).unwrap();
    assert!(!lift_allowed(&io), "a restart granted a spent budget again");
    // 18 s from spent, 1 s of which passed; the 0.7 s the record covers after its save (the
    // running ahead of it and on the last allowance) is not counted as rest.
    let wait = io.allowances.last().unwrap().seconds;
    assert!((wait - 17.6).abs() < 0.5, "{wait} s of rest still needed");
    // Started again after the rest it needed: allowed.
    let mut r = Process::new(config, record, 3);
    let mut io = Queues::default();
    r.poll(&mut io, (t + 19_500) * MS).unwrap();
    assert!(lift_allowed(&io));
}

/// The record's heat is never below the motor's, whatever it did since the save: run, rest
/// long, run again (without spending the budget), and a restart at that moment restores at
/// least the heat the motor has (a rule that saved only when the heat passed its last saved
/// value would credit the second run as rest).
#[test]
fn a_restart_after_rest_and_running_again_restores_at_least_the_motors_heat() {
    let mut p = Process::new(short_lift_rating(), Vec::new(), 1);
    let mut io = Queues::default();
    let mut t = 0;
    for (moving, until_ms) in [(true, 3500), (false, 23_500), (true, 25_000)] {
        while t <= until_ms {
            io.lift_states.push_back(lift_state(t, moving));
            p.poll(&mut io, t * MS).unwrap();
            t += 10;
        }
    }
    let heat = io.allowances.last().unwrap().used_s;
    let mut q = Process::new(short_lift_rating(), io.record.clone(), 2);
    let mut io = Queues::default();
    q.poll(&mut io, t * MS).unwrap();
    let restored = io.allowances.last().unwrap().used_s;
    assert!(
        restored >= heat - 1e-3,
        "restored {restored} s of heat for the motor's {heat} s"
    );
}

/// `nori stop` and `nori resume` taken in the same turn, or in two turns between two periods
/// of nori-lift (which reads only the newest allowance): the lift still learns of each stop
/// (the allowance counts them, and a changed count drops its goal), from the turn it came.
#[test]
fn a_stop_and_resume_in_one_turn_still_reach_the_lift() {
    let cmd = operator;
    let (mut p, mut io) = supervising();
    io.commands.push_back(cmd(COMMAND_STOP));
    io.commands.push_back(cmd(COMMAND_RESUME));
    p.poll(&mut io, MS).unwrap();
    let first = *io.allowances.last().unwrap();
    assert_eq!((first.timestamp_ns, first.stops), (MS, 1), "{first:?}");
    p.poll(&mut io, 10 * MS).unwrap();
    io.commands.push_back(cmd(COMMAND_STOP));
    p.poll(&mut io, 21 * MS).unwrap();
    io.commands.push_back(cmd(COMMAND_RESUME));
    p.poll(&mut io, 22 * MS).unwrap();
    p.poll(&mut io, 30 * MS).unwrap();
    // Whichever of them nori-lift reads last, the count has moved since before the stops.
    let newest = *io.allowances.last().unwrap();
    assert_eq!((newest.allowed, newest.stops), (1, 2), "{newest:?}");
}

/// A crash loop of the supervisor timed just before its next save of the lift's budget, the
/// lift moving whenever its newest allowance says so and is at most 200 ms old (nori-lift's
/// `travel`): the motor's real heat (a budget fed with the real motion) against what the
/// supervisor allows.
const TAIL_MS: u64 = 200;
fn crash_loop(alive_ms: u64, dead_ms: u64, seconds: u64) -> (f64, f64, u32, f64) {
    use supervisor::duty::DutyBudget;
    let config = config();
    let mut real = DutyBudget::new(config.lift.rating());
    let mut record: Vec<String> = Vec::new();
    let (mut p, mut io): (Option<Process>, Queues) = (None, Queues::default());
    let mut seen: Option<LiftAllowance> = None;
    let mut newest_state: Option<LiftState> = None;
    let (mut moving, mut over_s, mut ran_s, mut lives) = (false, 0.0, 0.0, 0u32);
    // The heat as running time without the budget's cap: its peak against the rating's 120 s.
    let (mut heat, mut peak) = (0.0f64, 0.0f64);
    let t0 = 1_000_000u64; // ms
    let cycle = alive_ms + dead_ms;
    for t in t0..t0 + seconds * 1000 {
        let phase = (t - t0) % cycle;
        if phase == 0 {
            // Started again: the record as last saved; history 1 gives the newest lift state.
            p = Some(Process::new(config.clone(), record.clone(), lives));
            io = Queues {
                record: record.clone(),
                ..Queues::default()
            };
            io.lift_states.extend(newest_state);
            lives += 1;
        }
        if phase == alive_ms {
            // SIGKILL: what was saved is what the next one reads.
            record = io.record.clone();
            p = None;
        }
        // nori-lift's period (10 ms): the newest allowance, 200 ms at most.
        if t % 10 == 0 {
            moving =
                seen.is_some_and(|a| a.allowed == 1 && t * MS - a.timestamp_ns <= TAIL_MS * MS);
            let s = LiftState {
                timestamp_ns: t * MS,
                velocity_m_s: if moving { 0.03 } else { 0.0 },
                ..LiftState::default()
            };
            newest_state = Some(s);
            if p.is_some() {
                io.lift_states.push_back(s);
            }
        }
        real.update(moving, 0.001);
        heat = if moving {
            heat + 0.001
        } else {
            (heat - 0.001 / 9.0).max(0.0)
        };
        peak = peak.max(heat);
        if moving {
            ran_s += 0.001;
            if real.exhausted() {
                over_s += 0.001;
            }
        }
        if let Some(p) = p.as_mut() {
            p.poll(&mut io, t * MS).unwrap();
            seen = io.allowances.last().copied().or(seen);
        }
    }
    (ran_s, over_s, lives, peak)
}

#[test]
fn a_crash_loop_of_the_supervisor_never_runs_the_lift_past_its_rating() {
    // The motor's heat may pass its rating by what runs in a period of the lift's loop after
    // each refusal (10 ms each time it is spent): under a second against 120 s. (Before the
    // record covered the running after its save: 190 s.)
    let mut worst = (0, 0.0f64);
    for (alive_ms, dead_ms) in [
        (300, 500),
        (400, 500),
        (505, 500),
        (515, 500),
        (515, 700),
        (700, 500),
        (1005, 500),
    ] {
        let (ran, over, lives, peak) = crash_loop(alive_ms, dead_ms, 600);
        eprintln!(
            "alive {alive_ms} ms, dead {dead_ms} ms, 600 s: {lives} lives, the lift ran {ran:.1} s, {over:.1} s of it with the motor's real budget spent; peak heat {peak:.1} s of the rated 120 s"
        );
        if peak > worst.1 {
            worst = (alive_ms, peak);
        }
    }
    assert!(
        worst.1 <= 120.0 + 1.0,
        "alive {} ms: the motor's heat reached {:.1} s of its 120 s rating",
        worst.0,
        worst.1
    );
}

/// A lift state stamped far ahead (nothing bounds the interval between two states) is rest.
#[test]
fn a_lift_state_stamped_ahead_rests_no_spent_budget() {
    let mut p = Process::new(config(), Vec::new(), 1);
    let mut io = Queues::default();
    let state = |t_ns: u64, moving: bool| LiftState {
        timestamp_ns: t_ns,
        velocity_m_s: if moving { 0.03 } else { 0.0 },
        ..LiftState::default()
    };
    let mut t = 0;
    while t <= 121_000 {
        io.lift_states.push_back(state(t * MS, true));
        p.poll(&mut io, t * MS).unwrap();
        t += 10;
    }
    assert!(!lift_allowed(&io), "spent");
    io.lift_states.push_back(state(t * MS, false));
    io.lift_states.push_back(state(u64::MAX / 2, false));
    p.poll(&mut io, t * MS).unwrap();
    let a = io.allowances.last().unwrap();
    eprintln!(
        "after one state stamped ahead: allowed {} used {} s",
        a.allowed, a.used_s
    );
    assert!(!lift_allowed(&io), "a spent budget granted again");
}
