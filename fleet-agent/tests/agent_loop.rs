//! The fleet agent's loop in process: `Agent::poll` against queues standing for the state plane
//! and the fleet, on a clock the test chooses. (The process tests in `tests/` run the binary
//! over real iceoryx2 and zenoh.)

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fleet_agent::agent::{Agent, AgentIo, JournalStart, Outbound};
use fleet_agent::box_shelf::{ChunkRead, ShelfError};
use fleet_agent::box_upload::{ChunkToSend, ShelvedBox};
use fleet_agent::delivery::Delivery;
use fleet_agent::journal::{JournalError, Record, Recovery};
use fleet_agent::schema::{
    decode, encode, AckMsg, ActionChunk, BoxAckMsg, BoxChunkMsg, EventMsg, EventRecord,
    ObservationMsg, PreviewMsg, ScanMsg, StateMsg, StatusMsg, SCHEMA_VERSION,
};
use fleet_agent::AgentConfig;
use std::collections::VecDeque;
use telemetry::config::ProcessConfig;
use telemetry::frames::{
    BusHealth, BusHealthEntry, EventKind, GoalFrame, Heartbeat, JointInfo, JointLayout,
    JointSample, JointState, Peer, SupervisorEvent, BUS_HEALTH_CONNECTED, BUS_HEALTH_ENABLED,
    STATE_FLAG_SAFE_STATE,
};
use telemetry::motion::{BaseCommand, BaseState, LiftCommand, LiftState, LIFT_READY};
use telemetry::sensors::{CameraFrameHeader, LidarScan, PixelFormat};

use telemetry::clock::MS;

#[derive(Default)]
struct Queues {
    layout: Option<JointLayout>,
    states: VecDeque<JointState>,
    health: Option<BusHealth>,
    /// Per configured camera, the frame it publishes next (header, RGB pixels).
    cameras: Vec<Option<(CameraFrameHeader, Vec<u8>)>>,
    /// Per observation camera, the JPEG it publishes next.
    images: Vec<Option<(CameraFrameHeader, Vec<u8>)>>,
    lidar: Option<LidarScan>,
    events: VecDeque<SupervisorEvent>,
    actions: VecDeque<Vec<u8>>,
    status_queries: usize,
    goals: Vec<GoalFrame>,
    lift: Option<LiftState>,
    base: Option<BaseState>,
    lift_sent: Vec<LiftCommand>,
    base_sent: Vec<BaseCommand>,
    published: Vec<(Outbound, Vec<u8>)>,
    status_replies: Vec<Vec<u8>>,
    /// The journal: its records in order (numbered from 1), whether its storage fails, and
    /// every acknowledgement kept.
    journal: Vec<Vec<u8>>,
    journal_broken: bool,
    acked: Vec<u64>,
    acks: VecDeque<Vec<u8>>,
    driver_beat: Option<Heartbeat>,
    supervisor_beat: Option<Heartbeat>,
    /// The link to the fleet comes up at the next turn.
    joining: bool,
    /// The black box's shelf listing handed over at the next turn, the boxes' bytes by name,
    /// and the store's acknowledgements of them.
    shelf: Option<Vec<ShelvedBox>>,
    box_files: std::collections::HashMap<String, Vec<u8>>,
    box_acks: VecDeque<Vec<u8>>,
    /// Chunks asked for, read at the next turn (never, when the shelf's thread is stuck).
    asked: VecDeque<ChunkToSend>,
    shelf_stuck: bool,
}

impl AgentIo for Queues {
    fn layout(&mut self) -> Option<JointLayout> {
        self.layout
    }
    fn next_state(&mut self) -> Option<JointState> {
        self.states.pop_front()
    }
    fn bus_health(&mut self) -> Option<BusHealth> {
        self.health
    }
    fn camera(
        &mut self,
        index: usize,
        look: &mut dyn FnMut(&CameraFrameHeader, &[u8]),
    ) -> Option<CameraFrameHeader> {
        let (h, pixels) = self.cameras.get_mut(index)?.take()?;
        look(&h, &pixels);
        Some(h)
    }
    fn image(&mut self, index: usize, jpeg: &mut Vec<u8>) -> Option<CameraFrameHeader> {
        let (h, data) = self.images.get_mut(index)?.take()?;
        *jpeg = data;
        Some(h)
    }
    fn lidar(&mut self) -> Option<LidarScan> {
        self.lidar.take()
    }
    fn next_event(&mut self) -> Option<SupervisorEvent> {
        self.events.pop_front()
    }
    fn heartbeat(&mut self, peer: Peer) -> Option<Heartbeat> {
        match peer {
            Peer::Driver => self.driver_beat.take(),
            Peer::Supervisor => self.supervisor_beat.take(),
        }
    }
    fn journal(&mut self, record: &[u8]) -> Result<u64, JournalError> {
        if self.journal_broken {
            return Err(JournalError::Io {
                path: "/x".into(),
                source: std::io::Error::other("disk full"),
            });
        }
        self.journal.push(record.to_vec());
        Ok(self.journal.len() as u64)
    }
    fn acknowledged(&mut self, seq: u64) {
        self.acked.push(seq);
    }
    fn next_ack(&mut self) -> Option<Vec<u8>> {
        self.acks.pop_front()
    }
    fn send_goal(&mut self, goal: &GoalFrame) -> bool {
        self.goals.push(*goal);
        true
    }
    fn lift(&mut self) -> Option<LiftState> {
        self.lift.take()
    }
    fn base(&mut self) -> Option<BaseState> {
        self.base.take()
    }
    fn send_lift(&mut self, command: &LiftCommand) -> bool {
        self.lift_sent.push(*command);
        true
    }
    fn send_base(&mut self, command: &BaseCommand) -> bool {
        self.base_sent.push(*command);
        true
    }
    fn publish(&mut self, what: Outbound, payload: Vec<u8>) -> bool {
        self.published.push((what, payload));
        true
    }
    fn next_action(&mut self) -> Option<Vec<u8>> {
        self.actions.pop_front()
    }
    fn answer_status(&mut self, status: &mut dyn FnMut() -> Vec<u8>) {
        for _ in 0..std::mem::take(&mut self.status_queries) {
            self.status_replies.push(status());
        }
    }
    fn fleet_joined(&mut self) -> bool {
        std::mem::take(&mut self.joining)
    }
    fn shelf(&mut self) -> Option<Vec<ShelvedBox>> {
        self.shelf.take()
    }
    fn ask_box(&mut self, chunk: &ChunkToSend) -> bool {
        self.asked.push_back(chunk.clone());
        true
    }
    fn box_bytes(&mut self) -> Option<ChunkRead> {
        if self.shelf_stuck {
            return None;
        }
        let chunk = self.asked.pop_front()?;
        let gone = || ShelfError::Io {
            name: chunk.name.clone(),
            source: std::io::Error::from(std::io::ErrorKind::NotFound),
        };
        let (from, len) = (chunk.offset as usize, chunk.len as usize);
        let read = (self.box_files.get(&chunk.name))
            .and_then(|b| b.get(from..from + len))
            .map(<[u8]>::to_vec)
            .ok_or_else(gone);
        Some((chunk, read))
    }
    fn next_box_ack(&mut self) -> Option<Vec<u8>> {
        self.box_acks.pop_front()
    }
}

/// Two joints of bus "right_arm", each with the range [-1, 1] rad.
fn layout() -> JointLayout {
    let mut l = JointLayout {
        joint_count: 2,
        bus_count: 1,
        ..JointLayout::default()
    };
    l.set_bus_name(0, "right_arm");
    for (i, name) in ["right_elbow", "right_wrist"].iter().enumerate() {
        let mut j = JointInfo {
            range_rad: [-1.0, 1.0],
            ..JointInfo::default()
        };
        j.set_name(name);
        l.joints[i] = j;
    }
    l
}

fn state(seq: u64, t: u64, safe: bool) -> JointState {
    let mut s = JointState {
        seq,
        timestamp_ns: t,
        joint_count: 2,
        flags: if safe { STATE_FLAG_SAFE_STATE } else { 0 },
        ..JointState::default()
    };
    for j in &mut s.joints[..2] {
        *j = JointSample {
            temperature_c: 30.0,
            ..JointSample::default()
        };
    }
    s
}

/// A chunk computed from the observation at `obs`: joint 0 to `target` over 10 steps 20 ms apart.
fn chunk(seq: u64, obs: u64, target: f32) -> Vec<u8> {
    encode(&ActionChunk {
        version: SCHEMA_VERSION,
        seq,
        observation_ns: obs,
        step_offsets_ns: (1..=10).map(|k| k * 20 * MS).collect(),
        joint_count: 2,
        joint_mask: 0b01,
        targets: (0..10).flat_map(|_| [target, 0.0]).collect(),
        lift_m: Vec::new(),
        base_twist: Vec::new(),
    })
}

/// A chunk for the body alone: the lift from 0.2 m to 0.38 m and the base from 0.02 m/s to
/// `top` m/s (turning at 0.5 rad/s) over 10 steps 20 ms apart.
fn body_chunk(seq: u64, obs: u64, top: f32) -> Vec<u8> {
    let steps = 1..=10u64;
    encode(&ActionChunk {
        version: SCHEMA_VERSION,
        seq,
        observation_ns: obs,
        step_offsets_ns: steps.clone().map(|k| k * 20 * MS).collect(),
        joint_count: 2,
        joint_mask: 0,
        targets: vec![0.0; 20],
        lift_m: steps.clone().map(|k| 0.18 + 0.02 * k as f32).collect(),
        base_twist: steps.flat_map(|k| [top * k as f32 / 10.0, 0.5]).collect(),
    })
}

/// An agent that has seen the layout and the driver running (frames 1..=5, 1 ms apart from
/// t0): ready to accept actions.
fn running() -> (Agent, Queues, u64) {
    let mut agent = Agent::new(&AgentConfig::embedded().unwrap());
    let mut io = Queues {
        layout: Some(layout()),
        ..Queues::default()
    };
    let t0 = 1_000_000 * MS;
    io.states
        .extend((1..=5).map(|k| state(k, t0 + k * MS, false)));
    agent.poll(&mut io, t0 + 5 * MS, 0);
    (agent, io, t0 + 5 * MS)
}

/// The status as a query gets it: answered in the next turn of the loop, decoded.
fn status(agent: &mut Agent, io: &mut Queues, now: u64) -> StatusMsg {
    io.status_queries = 1;
    io.status_replies.clear();
    agent.poll(io, now, 0);
    assert_eq!(io.status_replies.len(), 1, "one query, one answer");
    decode(&io.status_replies[0]).unwrap()
}

#[test]
fn observations_carry_the_configured_cameras_fresh_jpegs_every_nth_time_never_a_stale_one() {
    let mut config = AgentConfig::embedded().unwrap();
    config.observation.cameras = vec!["left_wrist".into(), "head".into()];
    config.observation.image_every = 2;
    config.observation.image_max_age_ms = 50;
    config.telemetry.observation_hz = 1000.0;
    let mut agent = Agent::new(&config);
    let mut io = Queues {
        layout: Some(layout()),
        images: vec![None, None],
        ..Queues::default()
    };
    let t0 = 1_000_000 * MS;
    let header = |seq: u64, capture_ns: u64| {
        let mut h = CameraFrameHeader {
            seq,
            capture_ns,
            width: 160,
            height: 120,
            ..CameraFrameHeader::default()
        };
        h.set_camera("left_wrist");
        h
    };
    let mut observations = Vec::new();
    // Observation k at t0 + k·10 ms. The wrist camera sends a JPEG before observations 0 and
    // 4; the head camera never does.
    for k in 0..6u64 {
        let t = t0 + k * 10 * MS;
        if k == 0 || k == 4 {
            io.images[0] = Some((header(k, t - 5 * MS), vec![0xFF, 0xD8, k as u8, 0xFF, 0xD9]));
        }
        io.states.push_back(state(k + 1, t, false));
        io.published.clear();
        agent.poll(&mut io, t, 0);
        let obs: Vec<ObservationMsg> = io
            .published
            .iter()
            .filter(|(w, _)| *w == Outbound::Observation)
            .map(|(_, b)| decode(b).unwrap())
            .collect();
        assert_eq!(obs.len(), 1, "one observation a turn at 1 kHz");
        observations.push(obs[0].clone());
    }
    let images: Vec<Vec<(String, u64, Vec<u8>)>> = observations
        .iter()
        .map(|o| {
            o.images
                .iter()
                .map(|i| (i.camera.clone(), i.seq, i.data.clone()))
                .collect()
        })
        .collect();
    let wrist = |seq: u64| {
        (
            "left_wrist".to_string(),
            seq,
            vec![0xFF, 0xD8, seq as u8, 0xFF, 0xD9],
        )
    };
    // 0: fresh (5 ms). 1, 3, 5: no images (every 2nd). 2: the JPEG of t0 is 25 ms old: still
    // within 50 ms. 4: the new one.
    assert_eq!(images[0], [wrist(0)]);
    assert!(images[1].is_empty() && images[3].is_empty() && images[5].is_empty());
    assert_eq!(images[2], [wrist(0)]);
    assert_eq!(images[4], [wrist(4)]);
    let o = &observations[0].images[0];
    assert_eq!((o.width, o.height, o.encoding.as_str()), (160, 120, "jpeg"));
    assert_eq!(o.capture_ns, t0 - 5 * MS);
    // No new JPEG after the one captured at 35 ms: it ages past the 50 ms bound.
    for k in 6..13u64 {
        io.states.push_back(state(k + 1, t0 + k * 10 * MS, false));
        io.published.clear();
        agent.poll(&mut io, t0 + k * 10 * MS, 0);
    }
    let last: ObservationMsg = decode(
        &io.published
            .iter()
            .find(|(w, _)| *w == Outbound::Observation)
            .unwrap()
            .1,
    )
    .unwrap();
    assert!(
        last.images.is_empty(),
        "a stale picture beside a fresh state"
    );
    let st = status(&mut agent, &mut io, t0 + 130 * MS);
    // Wrist images sent on observations 0, 2, 4, 6 (25 ms old) and 8 (45 ms); at 10 (65 ms)
    // and 12 (85 ms) stale.
    assert_eq!(st.counters.images_sent, 5, "{:?}", st.counters);
    // The head camera never sent anything: stale on each of the 7 image-bearing observations,
    // plus the wrist's at 100 and 120 ms.
    assert_eq!(st.counters.images_stale, 7 + 2, "{:?}", st.counters);
}

#[test]
fn a_checked_chunk_is_forwarded_and_an_out_of_range_one_never_is() {
    let (mut agent, mut io, now) = running();
    io.actions.push_back(chunk(1, now, 1.5));
    agent.poll(&mut io, now + MS, 0);
    assert!(io.goals.is_empty(), "an out-of-range chunk moved the arm");
    let st = status(&mut agent, &mut io, now + MS);
    assert_eq!(st.counters.actions_rejected["out_of_range"], 1);
    assert!(
        st.last_rejection.contains("outside the calibrated"),
        "{st:?}"
    );

    io.actions.push_back(chunk(2, now, 0.5));
    agent.poll(&mut io, now + 2 * MS, 0);
    let first = *io
        .goals
        .first()
        .expect("the accepted plan goes out at once");
    assert_eq!((first.mask, first.joint_count), (0b01, 2));
    // Along the plan: at its last step (200 ms after the observation), the chunk's target.
    agent.poll(&mut io, now + 200 * MS, 0);
    let last = io.goals.last().unwrap();
    assert!((last.position_rad[0] - 0.5).abs() < 1e-6, "{last:?}");
    assert!(io.goals.iter().all(|g| g.position_rad[0].abs() <= 1.0));
    assert_eq!(
        status(&mut agent, &mut io, now + 200 * MS)
            .counters
            .actions_accepted,
        1
    );
}

#[test]
fn the_lift_and_base_follow_a_checked_plan_and_are_no_longer_commanded_when_it_ends() {
    let (mut agent, mut io, now) = running();
    // 0.25 m/s is beyond the configured 0.2: refused whole, nothing moves.
    io.actions.push_back(body_chunk(1, now, 0.25));
    agent.poll(&mut io, now + MS, 0);
    assert!(io.base_sent.is_empty() && io.lift_sent.is_empty());
    let st = status(&mut agent, &mut io, now + MS);
    assert_eq!(st.counters.actions_rejected["out_of_range"], 1);
    assert!(st.last_rejection.contains("base_linear_m_s"), "{st:?}");

    io.actions.push_back(body_chunk(2, now, 0.2));
    for k in 2..=400 {
        agent.poll(&mut io, now + k * MS, 0);
    }
    assert!(io.goals.is_empty(), "no joint commanded, no goal frame");
    // Interpolated along the plan: at 100 ms after the observation, step 5 exactly.
    let at = |t: u64| io.base_sent.iter().find(|c| c.timestamp_ns == t).unwrap();
    let mid = at(now + 100 * MS);
    assert!(
        (mid.linear_m_s - 0.1).abs() < 1e-6 && mid.angular_rad_s == 0.5,
        "{mid:?}"
    );
    let lift = io
        .lift_sent
        .iter()
        .find(|c| c.timestamp_ns == now + 100 * MS);
    assert!((lift.unwrap().height_m - 0.28).abs() < 1e-6);
    assert!(io.base_sent.iter().all(|c| c.linear_m_s <= 0.2));
    // The plan's last step is at 200 ms, held for the horizon (100 ms): the base's last
    // command is no later, and its timestamp is when it was sent (the base controller stops
    // once it is older than its timeout).
    let last = io.base_sent.last().unwrap();
    assert!(last.timestamp_ns <= now + 300 * MS, "{last:?}");
    assert!(
        last.timestamp_ns >= now + 290 * MS,
        "held to the horizon: {last:?}"
    );
    assert!(io.lift_sent.last().unwrap().timestamp_ns <= now + 300 * MS);
    let st = status(&mut agent, &mut io, now + 400 * MS);
    assert_eq!(
        st.counters.base_commands_forwarded,
        io.base_sent.len() as u64
    );
    assert_eq!(st.counters.plans_expired, 1);
}

#[test]
fn the_lift_and_base_go_out_in_telemetry_and_observations_while_fresh() {
    let mut config = AgentConfig::embedded().unwrap();
    config.telemetry.state_hz = 1000.0;
    config.telemetry.observation_hz = 1000.0;
    let mut agent = Agent::new(&config);
    let mut io = Queues {
        layout: Some(layout()),
        ..Queues::default()
    };
    let t0 = 1_000_000 * MS;
    io.lift = Some(LiftState {
        timestamp_ns: t0,
        height_m: 0.4,
        goal_m: 0.5,
        state: LIFT_READY,
        ..LiftState::default()
    });
    io.base = Some(BaseState {
        timestamp_ns: t0,
        x_m: 1.5,
        linear_m_s: 0.125,
        ..BaseState::default()
    });
    let turn = |agent: &mut Agent, io: &mut Queues, k: u64, t: u64| {
        io.states.push_back(state(k, t, false));
        io.published.clear();
        agent.poll(io, t, 0);
        let state: Vec<StateMsg> = sent(io, Outbound::State);
        let obs: Vec<ObservationMsg> = sent(io, Outbound::Observation);
        (state[0].clone(), obs[0].clone())
    };
    let (s, o) = turn(&mut agent, &mut io, 1, t0 + 10 * MS);
    let lift = s.lift.unwrap();
    assert_eq!(
        (lift.height_m, lift.goal_m, lift.state),
        (0.4, 0.5, LIFT_READY)
    );
    assert_eq!(
        (s.base.unwrap().x_m, s.base.unwrap().linear_m_s),
        (1.5, 0.125)
    );
    assert_eq!((o.lift, o.base), (s.lift, s.base), "a policy sees the same");
    // Its controllers stopped publishing: half a second on, the lift and base are not shown.
    let (s, o) = turn(&mut agent, &mut io, 2, t0 + 500 * MS);
    assert!(s.lift.is_some(), "500 ms old: still fresh");
    let (s, o2) = turn(&mut agent, &mut io, 3, t0 + 501 * MS);
    assert_eq!((s.lift, s.base, o2.lift, o2.base), (None, None, None, None));
    assert!(o.base.is_some());
}

#[test]
fn a_driver_restart_or_safe_state_drops_the_plan() {
    for restart in [true, false] {
        let (mut agent, mut io, now) = running();
        io.actions.push_back(chunk(1, now, 0.5));
        agent.poll(&mut io, now + MS, 0);
        assert!(!io.goals.is_empty());
        // The driver comes back (its frame numbers start again) or goes to its safe state.
        let frame = if restart {
            state(1, now + 10 * MS, false)
        } else {
            state(6, now + 10 * MS, true)
        };
        io.states.push_back(frame);
        agent.poll(&mut io, now + 10 * MS, 0);
        let sent = io.goals.len();
        for k in 11..=200 {
            agent.poll(&mut io, now + k * MS, 0);
        }
        assert_eq!(
            io.goals.len(),
            sent,
            "restart {restart}: the old plan went on"
        );
        let st = status(&mut agent, &mut io, now + 200 * MS);
        assert_eq!(st.counters.plans_dropped, 1, "restart {restart}");
        assert_eq!(st.health.planned_steps, 0);
    }
}

#[test]
fn telemetry_events_and_status_go_out_named_from_the_layout() {
    let (mut agent, mut io, now) = running();
    let mut health = BusHealth {
        bus_count: 1,
        ..BusHealth::default()
    };
    health.buses[0] = BusHealthEntry {
        flags: BUS_HEALTH_CONNECTED | BUS_HEALTH_ENABLED,
        ..BusHealthEntry::default()
    };
    health.buses[0].counters.checksum_errors = 3;
    io.health = Some(health);
    io.events.push_back(SupervisorEvent {
        seq: 1,
        timestamp_ns: now,
        kind: EventKind::ThermalTrip as u8,
        joint: 1,
        ..SupervisorEvent::default()
    });
    agent.poll(&mut io, now + MS, 0);
    let events: Vec<EventMsg> = sent(&mut io, Outbound::Event);
    let event = &events.last().expect("the event went out").event;
    assert_eq!(
        (event.kind.as_str(), event.joint.as_str()),
        ("ThermalTrip", "right_wrist")
    );
    assert!(io.published.iter().any(|(k, _)| *k == Outbound::State));
    assert!(io.published.iter().any(|(k, _)| *k == Outbound::Layout));
    let st = status(&mut agent, &mut io, now + MS);
    assert_eq!(st.buses.len(), 1);
    assert_eq!(st.buses[0].name, "right_arm");
    assert!(st.buses[0].connected && st.buses[0].enabled);
    assert_eq!(st.buses[0].counters.checksum_errors, 3);
    assert_eq!(st.health.joints, 2);
    assert_eq!(
        st.counters.events_sent, 3,
        "the agent's start, its calibration, the trip"
    );
}

#[test]
fn the_status_reports_each_configured_sensor_from_its_newest_frame() {
    let (mut agent, mut io, now) = running();
    // The embedded configuration watches the four cameras and the lidar.
    let st = status(&mut agent, &mut io, now);
    let names: Vec<&str> = st.cameras.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["head", "neck", "left_wrist", "right_wrist"]);
    assert!(st
        .cameras
        .iter()
        .all(|c| c.frames == 0 && c.age_ms.is_none()));
    let lidar = st.lidar.clone().unwrap();
    assert_eq!((lidar.scans, lidar.age_ms), (0, None));

    let mut neck = CameraFrameHeader {
        seq: 41,
        capture_ns: now - 40 * MS,
        dropped: 3,
        corrupt: 2,
        late: 5,
        ..CameraFrameHeader::default()
    };
    neck.set_camera("neck");
    io.cameras = vec![None, Some((neck, Vec::new())), None, None];
    io.lidar = Some(LidarScan {
        seq: 99,
        start_ns: now - 120 * MS,
        end_ns: now - 20 * MS,
        bad_points: 4,
        resyncs: 1,
        short_scans: 2,
        ..LidarScan::default()
    });
    let st = status(&mut agent, &mut io, now);
    let c = &st.cameras[1];
    assert_eq!((c.frames, c.dropped, c.corrupt, c.late), (42, 3, 2, 5));
    assert!((c.age_ms.unwrap() - 40.0).abs() < 1e-9);
    assert_eq!(st.cameras[0].frames, 0, "head: nothing seen");
    let l = st.lidar.unwrap();
    assert_eq!(
        (l.scans, l.bad_points, l.resyncs, l.short_scans),
        (100, 4, 1, 2)
    );
    assert!((l.rotation_hz.unwrap() - 10.0).abs() < 1e-9);
    assert!((l.age_ms.unwrap() - 20.0).abs() < 1e-9);
    // Kept while nothing newer comes, aging.
    let later = status(&mut agent, &mut io, now + 1000 * MS);
    assert_eq!(later.cameras[1].frames, 42);
    assert!((later.cameras[1].age_ms.unwrap() - 1040.0).abs() < 1e-9);
}

#[test]
fn the_status_reports_what_the_agent_did_and_saw() {
    let (mut agent, mut io, now) = running();
    assert_eq!(agent.accepted(), 0);
    let st = status(&mut agent, &mut io, now);
    assert_eq!(st.health.safe_state, Some(false));
    assert_eq!(st.health.joints, 2);
    // A restart with no plan in force drops nothing.
    io.states.push_back(state(1, now + MS, false));
    agent.poll(&mut io, now + MS, 0);
    let mut last = state(2, now + 2 * MS, true);
    last.deadline_misses = 3;
    io.states.push_back(last);
    let mut health = BusHealth {
        bus_count: 2,
        ..BusHealth::default()
    };
    health.buses[0].flags = BUS_HEALTH_CONNECTED;
    health.buses[1].flags = BUS_HEALTH_ENABLED;
    io.health = Some(health);
    io.events.extend((1..=2).map(|seq| SupervisorEvent {
        seq,
        kind: EventKind::Stall as u8,
        ..SupervisorEvent::default()
    }));
    let st = status(&mut agent, &mut io, now + 7 * MS);
    assert_eq!(st.counters.plans_dropped, 0);
    assert_eq!(st.health.safe_state, Some(true));
    assert_eq!(st.health.deadline_misses, Some(3));
    assert_eq!(st.health.state_age_ms, Some(5.0));
    assert_eq!(
        st.counters.events_sent, 4,
        "the agent's start, its calibration, two stalls"
    );
    let sent = |k| io.published.iter().filter(|(o, _)| *o == k).count() as u64;
    assert_eq!(st.counters.state_sent, sent(Outbound::State));
    assert_eq!(st.counters.observations_sent, sent(Outbound::Observation));
    assert!(st.counters.state_sent >= 1 && st.counters.observations_sent >= 1);
    let flags: Vec<(bool, bool)> = st.buses.iter().map(|b| (b.connected, b.enabled)).collect();
    assert_eq!(flags, [(true, false), (false, true)]);
    // The second bus has no name in the layout: named by its index, not left blank.
    assert_eq!(st.buses[1].name, "bus1");
    assert_eq!(st.counters.goals_forwarded, 0);

    // In the driver's running state again, a plan: every goal sent is counted, and the
    // binary's summary getters agree with the status.
    io.states.push_back(state(3, now + 8 * MS, false));
    agent.poll(&mut io, now + 8 * MS, 0);
    io.actions.push_back(chunk(1, now + 8 * MS, 0.5));
    for k in 9..60 {
        agent.poll(&mut io, now + k * MS, 0);
    }
    let st = status(&mut agent, &mut io, now + 60 * MS);
    assert!(io.goals.len() > 1);
    assert_eq!(st.counters.goals_forwarded, io.goals.len() as u64);
    assert_eq!(agent.goals_forwarded(), io.goals.len() as u64);
    assert_eq!(agent.accepted(), 1);
    assert_eq!(st.counters.goals_withheld, 0);
    let seqs: Vec<u64> = io.goals.iter().map(|g| g.seq).collect();
    assert!(seqs.windows(2).all(|w| w[1] == w[0] + 1), "{seqs:?}");
}

#[test]
fn the_loop_turns_until_told_to_stop_or_its_time_is_up() {
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::time::Duration;
    let mut agent = Agent::new(&AgentConfig::embedded().unwrap());
    let mut io = Queues {
        layout: Some(layout()),
        ..Queues::default()
    };
    let stop = AtomicBool::new(true);
    let mut turns = 0;
    fleet_agent::agent::run(&mut agent, &mut io, &stop, None, &mut |_| turns += 1);
    assert_eq!(turns, 0, "stopped before the first turn");
    stop.store(false, Ordering::Relaxed);
    let run_for = Some(Duration::from_millis(30));
    fleet_agent::agent::run(&mut agent, &mut io, &stop, run_for, &mut |_| turns += 1);
    assert!(turns > 0, "the loop never turned");
    assert!(io.published.iter().any(|(k, _)| *k == Outbound::Layout));
    // Wall time for the fleet's plots is the Unix clock's.
    assert!(fleet_agent::agent::wall_ms() > 1_700_000_000_000);
}

/// A `w`×`h` RGB24 frame of camera `name`, every pixel `rgb`.
fn rgb_frame(name: &str, seq: u64, w: u32, h: u32, rgb: [u8; 3]) -> (CameraFrameHeader, Vec<u8>) {
    let mut hd = CameraFrameHeader {
        seq,
        capture_ns: seq * MS,
        fourcc: PixelFormat::Rgb24.fourcc(),
        width: w,
        height: h,
        stride: w * 3,
        ..CameraFrameHeader::default()
    };
    hd.set_camera(name);
    (hd, rgb.repeat((w * h) as usize))
}

/// Each thumbnail's camera and frame number.
fn cameras_and_frames(previews: &[PreviewMsg]) -> Vec<(&str, u64)> {
    previews
        .iter()
        .map(|p| (p.camera.as_str(), p.seq))
        .collect()
}

/// What the agent published on `what` since the last look, decoded (and taken).
fn sent<T: for<'de> serde::Deserialize<'de>>(io: &mut Queues, what: Outbound) -> Vec<T> {
    let (mine, rest) = std::mem::take(&mut io.published)
        .into_iter()
        .partition::<Vec<_>, _>(|(w, _)| *w == what);
    io.published = rest;
    mine.iter().map(|(_, b)| decode(b).unwrap()).collect()
}

#[test]
fn thumbnails_and_scans_go_to_the_fleet_at_their_rates_each_from_a_fresh_frame() {
    let mut config = AgentConfig::embedded().unwrap();
    config.sensors.cameras = vec!["head".into(), "neck".into()];
    (config.preview.every_s, config.preview.width) = (2.0, 32);
    config.preview.scan_every_s = 1.0;
    let mut agent = Agent::new(&config);
    let mut io = Queues {
        cameras: vec![None, None],
        ..Queues::default()
    };
    let t = 1_000_000 * MS;
    let scan = |seq| LidarScan {
        seq,
        point_count: 2,
        ..LidarScan::default()
    };
    let green = [10, 200, 30];

    // Due at once: the head's frame gives its thumbnail (64×48 averaged by 2 to fit 32); the
    // neck has sent nothing and owes its own. The lidar's revolution goes out.
    io.cameras[0] = Some(rgb_frame("head", 10, 64, 48, green));
    io.lidar = Some(scan(0));
    agent.poll(&mut io, t, 77);
    let scans: Vec<ScanMsg> = sent(&mut io, Outbound::Scan);
    assert_eq!(scans.iter().map(|s| s.seq).collect::<Vec<_>>(), [0]);
    assert_eq!(scans[0].range_m.len(), 2);
    let previews: Vec<PreviewMsg> = sent(&mut io, Outbound::Preview);
    assert_eq!(previews.len(), 1);
    let p = &previews[0];
    assert_eq!(
        (
            p.camera.as_str(),
            p.seq,
            p.width,
            p.height,
            p.source_width,
            p.source_height
        ),
        ("head", 10, 32, 24, 64, 48)
    );
    assert_eq!(
        (p.encoding.as_str(), p.wall_ms, p.capture_ns),
        ("jpeg", 77, 10 * MS)
    );
    let mut d = zune_jpeg::JpegDecoder::new(zune_core::bytestream::ZCursor::new(&p.data));
    let px = d.decode().unwrap();
    assert_eq!(px.len(), 32 * 24 * 3);
    assert!(
        px.chunks_exact(3)
            .all(|c| c.iter().zip(green).all(|(a, b)| a.abs_diff(b) <= 4)),
        "the thumbnail is the picture"
    );

    // 100 ms later: the head's next frame is not due; the neck's first frame pays its debt,
    // with that frame. The lidar's next revolution is not due.
    io.cameras = vec![
        Some(rgb_frame("head", 11, 64, 48, green)),
        Some(rgb_frame("neck", 5, 64, 48, green)),
    ];
    io.lidar = Some(scan(1));
    agent.poll(&mut io, t + 100 * MS, 78);
    let previews: Vec<PreviewMsg> = sent(&mut io, Outbound::Preview);
    assert_eq!(cameras_and_frames(&previews), [("neck", 5)]);
    io.published.clear();

    // At 1 s the lidar is due but sends nothing: owed until its next revolution, at 1.1 s.
    agent.poll(&mut io, t + 1000 * MS, 79);
    io.lidar = Some(scan(2));
    agent.poll(&mut io, t + 1100 * MS, 80);
    let scans: Vec<ScanMsg> = sent(&mut io, Outbound::Scan);
    assert_eq!(
        scans.iter().map(|s| (s.seq, s.wall_ms)).collect::<Vec<_>>(),
        [(2, 80)]
    );

    // At 2 s both cameras are due again, with a frame each: one thumbnail a turn, the head's
    // first. The neck's next frame is YUYV (not what the plane carries): no thumbnail of it,
    // counted.
    let yuyv = |seq| {
        let (mut h, pixels) = rgb_frame("neck", seq, 64, 48, green);
        h.fourcc = PixelFormat::Yuyv.fourcc();
        Some((h, pixels))
    };
    io.cameras = vec![Some(rgb_frame("head", 70, 64, 48, green)), yuyv(66)];
    agent.poll(&mut io, t + 2000 * MS, 81);
    let previews: Vec<PreviewMsg> = sent(&mut io, Outbound::Preview);
    assert_eq!(cameras_and_frames(&previews), [("head", 70)]);
    io.cameras[1] = yuyv(67);
    agent.poll(&mut io, t + 2001 * MS, 82);
    assert!(sent::<PreviewMsg>(&mut io, Outbound::Preview).is_empty());
    let st = status(&mut agent, &mut io, t + 2002 * MS);
    assert_eq!(
        (
            st.counters.previews_sent,
            st.counters.previews_failed,
            st.counters.scans_sent
        ),
        (3, 1, 2)
    );
    assert_eq!(
        st.cameras[1].frames, 68,
        "the refused frame still counts for the status"
    );
}

fn trip(seq: u64, t: u64) -> SupervisorEvent {
    SupervisorEvent {
        seq,
        timestamp_ns: t,
        kind: EventKind::ThermalTrip as u8,
        joint: 1,
        value: 59.5,
        ..SupervisorEvent::default()
    }
}

fn ack(journal: u64, through: u64) -> Vec<u8> {
    encode(&AckMsg {
        version: SCHEMA_VERSION,
        journal,
        stored_through: through,
    })
}

fn journaled(io: &Queues) -> Vec<EventRecord> {
    io.journal
        .iter()
        .map(|b| postcard::from_bytes(b).unwrap())
        .collect()
}

#[test]
fn every_event_is_journaled_before_it_is_sent_and_sent_again_until_acknowledged() {
    let (mut agent, mut io, now) = running();
    io.events.push_back(trip(1, now));
    io.published.clear();
    agent.poll(&mut io, now + MS, 1_700_000_000_000);
    let kinds: Vec<String> = journaled(&io).into_iter().map(|r| r.kind).collect();
    assert_eq!(kinds, ["AgentStarted", "CalibrationInForce", "ThermalTrip"]);
    let out: Vec<EventMsg> = sent(&mut io, Outbound::Event);
    assert_eq!(out.len(), 1, "the start went out in the first turn");
    assert_eq!(
        (out[0].seq, out[0].held_from),
        (3, 1),
        "numbered as journaled"
    );
    assert_eq!(out[0].event, journaled(&io)[2]);
    assert_eq!(out[0].event.wall_ms, 1_700_000_000_000, "when it happened");
    // No acknowledgement within resend-after (2 s): both go again, the oldest first.
    agent.poll(&mut io, now + 1_999 * MS, 0);
    assert!(sent::<EventMsg>(&mut io, Outbound::Event).is_empty());
    agent.poll(&mut io, now + 2_100 * MS, 0);
    let again: Vec<u64> = sent::<EventMsg>(&mut io, Outbound::Event)
        .iter()
        .map(|m| m.seq)
        .collect();
    assert_eq!(again, [1, 2, 3]);
    // Acknowledged: kept across restarts, and nothing goes again.
    io.acks.push_back(ack(0, 3));
    agent.poll(&mut io, now + 2_200 * MS, 0);
    assert_eq!(io.acked, [3]);
    agent.poll(&mut io, now + 60_000 * MS, 0);
    assert!(sent::<EventMsg>(&mut io, Outbound::Event).is_empty());
    let st = status(&mut agent, &mut io, now + 60_001 * MS);
    let c = &st.counters;
    assert_eq!(
        (
            c.events_sent,
            c.events_resent,
            c.events_unacknowledged,
            c.events_stored_through
        ),
        (3, 3, 0, 3)
    );
}

/// A robot that started with its router out of reach: its events are journaled while nothing
/// gets through, and when the link comes up everything held goes out in that turn, the layout
/// with it, not at the next resend (by then 30 s apart).
#[test]
fn when_the_fleet_is_reached_late_everything_held_goes_out_at_once() {
    let (mut agent, mut io, now) = running();
    io.events.push_back(trip(1, now));
    let (mut t, mut last_sending) = (now, now);
    while t < now + 125_000 * MS {
        agent.poll(&mut io, t, 0);
        if !sent::<EventMsg>(&mut io, Outbound::Event).is_empty() {
            last_sending = t;
        }
        t += 100 * MS;
    }
    let kinds: Vec<String> = journaled(&io).into_iter().map(|r| r.kind).collect();
    assert_eq!(kinds, ["AgentStarted", "CalibrationInForce", "ThermalTrip"]);
    io.published.clear();
    agent.poll(&mut io, last_sending + 1_000 * MS, 0);
    assert!(
        io.published.is_empty(),
        "nothing due a second after a resend"
    );
    io.joining = true;
    agent.poll(&mut io, last_sending + 1_100 * MS, 0);
    assert!(
        !sent::<fleet_agent::schema::LayoutMsg>(&mut io, Outbound::Layout).is_empty(),
        "the layout goes out on joining"
    );
    let seqs: Vec<u64> = sent::<EventMsg>(&mut io, Outbound::Event)
        .iter()
        .map(|m| m.seq)
        .collect();
    assert_eq!(
        seqs,
        [1, 2, 3],
        "everything held goes out on joining, oldest first"
    );
}

#[test]
fn a_restarted_agent_sends_what_was_not_acknowledged_and_journals_nothing_twice() {
    // The journal as a killed agent left it: its start, the supervisor's, a trip; the fleet
    // had acknowledged the first.
    let rec = |kind: &str, origin_seq, t, value| EventRecord {
        timestamp_ns: t,
        wall_ms: 0,
        origin_seq,
        kind: kind.into(),
        joint: String::new(),
        detail: String::new(),
        bus: 0,
        level: 0,
        value,
    };
    let kept: Vec<Record> = [
        rec("AgentStarted", 0, 1, 0.0),
        rec("SupervisorStarted", 0, 2, 4242.0),
        rec("ThermalTrip", 1, 3 * MS, 59.5),
    ]
    .iter()
    .enumerate()
    .map(|(i, r)| Record {
        seq: i as u64 + 1,
        payload: Delivery::journal_bytes(r),
    })
    .collect();
    let start = JournalStart {
        id: 77,
        kept: kept.clone(),
        recovery: Recovery {
            records: 3,
            cut_bytes: 5,
            acked_through: 1,
        },
    };
    let mut agent = Agent::resuming(&AgentConfig::embedded().unwrap(), start);
    let mut io = Queues {
        layout: Some(layout()),
        journal: kept.iter().map(|r| r.payload.clone()).collect(),
        ..Queues::default()
    };
    // The state plane replays the trip; the supervisor is the same process; the driver is new.
    io.events.push_back(trip(1, 3 * MS));
    io.supervisor_beat = Some(Heartbeat {
        pid: 4242,
        ..Heartbeat::default()
    });
    io.driver_beat = Some(Heartbeat {
        pid: 99,
        ..Heartbeat::default()
    });
    agent.poll(&mut io, 10 * MS, 0);
    let new: Vec<(String, f32)> = journaled(&io)[3..]
        .iter()
        .map(|r| (r.kind.clone(), r.value))
        .collect();
    assert_eq!(
        new,
        [
            ("AgentStarted".into(), 5.0),
            ("CalibrationInForce".into(), 0.0),
            ("DriverStarted".into(), 99.0)
        ],
        "its start (5 torn bytes cut, no calibration file), the driver's; not the replayed \
         trip nor the known supervisor"
    );
    let out: Vec<EventMsg> = sent(&mut io, Outbound::Event);
    assert!(out.iter().all(|m| m.journal == 77));
    assert_eq!(
        out.iter().map(|m| m.seq).collect::<Vec<_>>(),
        [2, 3, 4, 5, 6],
        "the unacknowledged, then the new, in order"
    );
    // A supervisor restarted: journaled once, however many heartbeats.
    for k in 0..3 {
        io.supervisor_beat = Some(Heartbeat {
            pid: 5000,
            ..Heartbeat::default()
        });
        agent.poll(&mut io, (11 + k) * MS, 0);
    }
    let starts = journaled(&io)
        .iter()
        .filter(|r| r.kind == "SupervisorStarted")
        .count();
    assert_eq!(starts, 2);
    // An acknowledgement of another journal, or of events never journaled, is refused.
    io.acks.push_back(ack(78, 2));
    io.acks.push_back(ack(77, 99));
    io.acks.push_back(b"\x06garbage".to_vec());
    let st = status(&mut agent, &mut io, 20 * MS);
    assert_eq!(
        st.counters.acks_refused, 3,
        "another journal's, one of the future and a malformed one"
    );
    assert!(io.acked.is_empty());
}

#[test]
fn refusals_are_journaled_per_reason_at_most_every_ten_seconds() {
    let (mut agent, mut io, now) = running();
    for k in 0..50 {
        io.actions.push_back(chunk(k, now - 5_000 * MS, 0.5)); // stale
    }
    io.actions.push_back(chunk(99, now, 7.0)); // out of range
    agent.poll(&mut io, now + MS, 0);
    for k in 0..50 {
        io.actions.push_back(chunk(100 + k, now, 0.5 + k as f32));
        agent.poll(&mut io, now + (2 + k) * MS, 0);
    }
    let refused = |io: &Queues| -> Vec<(String, f32)> {
        journaled(io)
            .into_iter()
            .filter(|r| r.kind == "ActionsRefused")
            .map(|r| (r.detail, r.value))
            .collect()
    };
    assert_eq!(
        refused(&io).len(),
        2,
        "one per reason at the first refusals"
    );
    let first: f32 = refused(&io).iter().map(|r| r.1).sum();
    agent.poll(&mut io, now + 9_000 * MS, 0);
    assert_eq!(refused(&io).len(), 2, "not yet ten seconds");
    agent.poll(&mut io, now + 10_100 * MS, 0);
    let all = refused(&io);
    let total: f32 = all.iter().map(|r| r.1).sum();
    let st = status(&mut agent, &mut io, now + 10_200 * MS);
    let counted: u64 = st.counters.actions_rejected.values().sum();
    assert_eq!(
        total as u64, counted,
        "every refusal in the journal: {all:?} after {first}"
    );
    assert!(all.len() <= 4);
}

#[test]
fn an_event_the_journal_cannot_keep_still_goes_out_once_unnumbered_and_counted() {
    let (mut agent, mut io, now) = running();
    io.journal_broken = true;
    io.events.push_back(trip(1, now));
    io.published.clear();
    agent.poll(&mut io, now + MS, 0);
    let out: Vec<EventMsg> = sent(&mut io, Outbound::Event);
    assert_eq!(out.len(), 1);
    assert_eq!((out[0].seq, out[0].event.kind.as_str()), (0, "ThermalTrip"));
    agent.poll(&mut io, now + 60_000 * MS, 0);
    let again = sent::<EventMsg>(&mut io, Outbound::Event);
    let start = ["AgentStarted", "CalibrationInForce"];
    assert!(
        again.iter().all(|m| start.contains(&m.event.kind.as_str())),
        "once"
    );
    let st = status(&mut agent, &mut io, now + 60_001 * MS);
    assert_eq!(st.counters.events_unjournaled, 1);
}

#[test]
fn the_package_version_the_robot_runs_is_in_its_status_and_its_start_s_event() {
    let mut io = Queues {
        layout: Some(layout()),
        ..Queues::default()
    };
    let config = AgentConfig::embedded().unwrap();
    let mut agent = Agent::new(&config).installed(Some("0.1.0+57".into()));
    let st = status(&mut agent, &mut io, 1_000 * MS);
    assert_eq!(st.installed_version.as_deref(), Some("0.1.0+57"));
    assert_eq!(st.agent_version, env!("CARGO_PKG_VERSION"));
    let start = &journaled(&io)[0];
    assert_eq!(
        (start.kind.as_str(), start.detail.as_str()),
        ("AgentStarted", "0.1.0+57")
    );

    // A build from source claims no package.
    let mut io = Queues::default();
    let mut agent = Agent::new(&config);
    assert_eq!(
        status(&mut agent, &mut io, 1_000 * MS).installed_version,
        None
    );
    assert_eq!(journaled(&io)[0].detail, "");
}

#[test]
fn the_calibration_the_robot_runs_is_in_its_status_and_journaled_at_its_start() {
    let text = "[calibrated]\nformat = 1\nrobot = \"a3-0042\"\nat = \"2026-11-29T05:00:00Z\"\n\
                method = \"by-hand\"\n[joint.left_elbow]\nhoming-offset = 3\n\
                range-min = 1000\nrange-max = 3000\n";
    let calibration = fleet_agent::installed::calibration_in_force(text).unwrap();
    let config = AgentConfig::embedded().unwrap();
    let mut io = Queues {
        layout: Some(layout()),
        ..Queues::default()
    };
    let mut agent = Agent::new(&config).calibrated(Some(calibration.clone()));
    let st = status(&mut agent, &mut io, 1_000 * MS);
    assert_eq!(st.calibration, Some(calibration));
    let journal = journaled(&io);
    let event = journal
        .iter()
        .find(|r| r.kind == "CalibrationInForce")
        .unwrap();
    assert_eq!(
        (event.detail.as_str(), event.value),
        ("by-hand 2026-11-29T05:00:00Z a3-0042", 1.0)
    );

    // No file: no calibration claimed, and the start says so.
    let mut io = Queues::default();
    let mut agent = Agent::new(&config).calibrated(None);
    assert_eq!(status(&mut agent, &mut io, 1_000 * MS).calibration, None);
    assert_eq!(journaled(&io)[1].detail, "none");
}

/// A store that keeps a box's chunks arriving at the offset it holds, and answers each.
fn store_takes(held: &mut Vec<u8>, c: &BoxChunkMsg) -> Vec<u8> {
    if c.offset == held.len() as u64 {
        held.extend_from_slice(&c.data);
    }
    encode(&BoxAckMsg {
        version: SCHEMA_VERSION,
        number: c.number,
        digest: c.digest,
        received: held.len() as u64,
        complete: held.len() as u64 == c.size,
        refused: false,
    })
}

/// A frozen box reaches the store byte for byte, chunk by chunk at the configured pace, and
/// only once the journal's events are acknowledged: a box never goes ahead of them.
#[test]
fn a_frozen_box_goes_to_the_store_after_the_events_at_its_pace() {
    let (mut agent, mut io, mut now) = running();
    let bytes: Vec<u8> = (0..200_000u32).map(|i| (i % 251) as u8).collect();
    let name = "000004-20261130T020000Z-thermal_trip.mcap".to_string();
    io.box_files.insert(name.clone(), bytes.clone());
    io.shelf = Some(vec![ShelvedBox {
        number: 4,
        name: name.clone(),
        size: bytes.len() as u64,
        digest: [4; 32],
    }]);
    io.published.clear();
    for _ in 0..10 {
        now += 100 * MS;
        agent.poll(&mut io, now, 0);
    }
    assert!(
        sent::<BoxChunkMsg>(&mut io, Outbound::BoxChunk).is_empty(),
        "nothing while the agent's start is not acknowledged"
    );
    io.acks.push_back(ack(0, 2));
    // A malformed acknowledgement of a box is refused and counted, nothing else.
    io.box_acks.push_back(b"garbage".to_vec());
    let (mut held, mut chunks, started) = (Vec::new(), 0, now);
    while now < started + 10_000 * MS && (held.len() < bytes.len() || chunks == 0) {
        now += 10 * MS;
        agent.poll(&mut io, now, 0);
        for c in sent::<BoxChunkMsg>(&mut io, Outbound::BoxChunk) {
            assert_eq!((c.number, &c.name, c.digest), (4, &name, [4; 32]));
            chunks += 1;
            io.box_acks.push_back(store_takes(&mut held, &c));
        }
    }
    assert_eq!(held, bytes, "the box byte for byte");
    let took = (now - started) as f64 / 1e9;
    // 200 000 bytes at 65 536 B/s after a 64 KiB burst: about 2 s, never much faster.
    assert!(took > 1.9, "faster than its pace: {took} s");
    assert_eq!(chunks, 1 + 4, "a probe and four chunks of at most 64 KiB");
    now += 10 * MS;
    agent.poll(&mut io, now, 0);
    let b = status(&mut agent, &mut io, now + MS).counters.boxes;
    assert_eq!(
        (
            b.pending,
            b.stored,
            b.bytes_sent,
            b.bytes_resent,
            b.acks_refused
        ),
        (0, 1, 200_000, 0, 1)
    );
    // Stored: listed again, it is not sent again.
    io.shelf = Some(vec![ShelvedBox {
        number: 4,
        name,
        size: bytes.len() as u64,
        digest: [4; 32],
    }]);
    for _ in 0..100 {
        now += 100 * MS;
        agent.poll(&mut io, now, 0);
    }
    assert!(sent::<BoxChunkMsg>(&mut io, Outbound::BoxChunk).is_empty());
}

/// The store's answer to box 1 (digest `[1; 32]`): it holds none of it.
fn nothing_held_of_box_1() -> Vec<u8> {
    encode(&BoxAckMsg {
        version: SCHEMA_VERSION,
        number: 1,
        digest: [1; 32],
        received: 0,
        complete: false,
        refused: false,
    })
}

/// A box whose file cannot be read is counted, not sent as something else, tried again after
/// each wait, and set aside after three failures in a row.
#[test]
fn a_box_that_cannot_be_read_is_counted_tried_again_then_set_aside() {
    let (mut agent, mut io, mut now) = running();
    io.acks.push_back(ack(0, 2));
    io.shelf = Some(vec![ShelvedBox {
        number: 1,
        name: "000001-T-saved.mcap".into(),
        size: 1000,
        digest: [1; 32],
    }]);
    let mut probes = 0;
    for _ in 0..50 {
        now += 100 * MS;
        agent.poll(&mut io, now, 0);
        for c in sent::<BoxChunkMsg>(&mut io, Outbound::BoxChunk) {
            assert!(c.data.is_empty());
            probes += 1;
            io.box_acks.push_back(nothing_held_of_box_1());
        }
    }
    assert_eq!(probes, 1);
    let b = status(&mut agent, &mut io, now + MS).counters.boxes;
    assert_eq!(
        (b.read_failures, b.unreadable, b.pending, b.bytes_sent),
        (3, 1, 0, 0),
        "tried again after each wait, then set aside: {b:?}"
    );
}

/// A shelf whose reading thread never answers holds the upload up for ten seconds a try, then
/// the box is set aside: the loop never waits on it.
#[test]
fn a_shelf_that_never_answers_is_taken_as_failed_reads() {
    let (mut agent, mut io, mut now) = running();
    io.acks.push_back(ack(0, 2));
    io.shelf_stuck = true;
    io.shelf = Some(vec![ShelvedBox {
        number: 1,
        name: "000001-T-saved.mcap".into(),
        size: 1000,
        digest: [1; 32],
    }]);
    for _ in 0..600 {
        now += 100 * MS;
        agent.poll(&mut io, now, 0);
        for c in sent::<BoxChunkMsg>(&mut io, Outbound::BoxChunk) {
            assert!(c.data.is_empty(), "only the probe goes");
            io.box_acks.push_back(nothing_held_of_box_1());
        }
    }
    let b = status(&mut agent, &mut io, now + MS).counters.boxes;
    assert_eq!(
        (b.read_failures, b.unreadable, b.pending),
        (3, 1, 0),
        "{b:?}"
    );
}
