//! The fleet agent's loop, shaped like the driver's: [`Agent`] holds everything the agent knows
//! (the gate, the plan, the rates, its counters) and [`Agent::poll`] does one turn of the loop
//! against an [`AgentIo`], the state plane on one side and the fleet on the other, with time
//! passed in. The binary wires iceoryx2 and zenoh into an `AgentIo` and calls [`run`]; the
//! tests wire queues and call `poll` with the clock they choose.
//!
//! The agent's state is its plan of accepted actions and the events it holds for the fleet.
//! Killed, it takes the plan with it, the driver stops getting goals and holds, and a restarted
//! agent starts with none; the events are in the robot's journal ([`crate::journal`], through
//! [`AgentIo::journal`]) before they are sent, and a restarted agent sends again what the fleet
//! has not acknowledged ([`crate::delivery`]).

use crate::box_shelf::ChunkRead;
use crate::box_upload::{BoxAck, ChunkToSend, ShelvedBox, Upload};
use crate::delivery::{
    Delivery, ACTIONS_REFUSED, AGENT_STARTED, CALIBRATION_IN_FORCE, DRIVER_STARTED,
    SUPERVISOR_STARTED,
};
use crate::gate::{within, ActionGate, Range, REASONS};
use crate::installed::calibration_detail;
use crate::journal::{JournalError, Record, Recovery};
use crate::outbound::{self, Every};
use crate::preview::{preview_msg, scan_msg};
use crate::schedule::Scheduler;
use crate::schema::{
    decode, encode, AckMsg, AgentCounters, BoxAckMsg, BoxChunkMsg, BoxCounters, BusStatus,
    CalibrationMsg, CameraStatus, EventRecord, ImageMsg, LidarStatus, StatusConfig, StatusHealth,
    StatusMsg, SCHEMA_VERSION,
};
use crate::AgentConfig;
use camera::thumbnail::Thumbnailer;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use telemetry::frames::{
    BusHealth, GoalFrame, Heartbeat, JointLayout, JointState, Peer, SupervisorEvent,
    BUS_HEALTH_CONNECTED, BUS_HEALTH_ENABLED, STATE_FLAG_SAFE_STATE,
};
use telemetry::motion::{BaseCommand, BaseState, LiftCommand, LiftState};
use telemetry::sensors::{CameraFrameHeader, LidarScan};

/// The lift's or the base's state is shown and observed while at most this old (their
/// controllers publish every 10 and 20 ms): older, its controller is not running.
const BODY_FRESH_NS: u64 = 500_000_000;

/// What the agent sends to the fleet, each on its own key expression of the robot.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outbound {
    /// `nori/<robot>/state` (dropped on congestion).
    State,
    /// `nori/<robot>/observation` (dropped on congestion).
    Observation,
    /// `nori/<robot>/layout`.
    Layout,
    /// `nori/<robot>/preview` (dropped on congestion).
    Preview,
    /// `nori/<robot>/scan` (dropped on congestion).
    Scan,
    /// `nori/<robot>/events` (dropped on congestion: the journal sends them again).
    Event,
    /// `nori/<robot>/blackbox/chunk` (dropped on congestion: sent again until acknowledged).
    BoxChunk,
}

/// A chunk asked of the shelf's thread and not read within this is taken as a failed read, ns.
const BOX_READ_TIMEOUT_NS: u64 = 10_000_000_000;

/// Action refusals are journaled as one event per reason at most this often (a policy sending
/// bad chunks at 30 Hz must not fill the journal), ns.
const REFUSALS_EVERY_NS: u64 = 10_000_000_000;

/// What the journal held when the agent started: the delivery picks up from it.
#[derive(Debug, Clone, Default)]
pub struct JournalStart {
    /// The journal's identity.
    pub id: u64,
    /// Every record it keeps, oldest first.
    pub kept: Vec<Record>,
    /// What opening it found (a torn tail cut, how far the fleet had acknowledged).
    pub recovery: Recovery,
}

/// The agent's two planes, as its loop uses them. Every call returns at once.
pub trait AgentIo {
    /// The newest joint layout of the driver, if one was published.
    fn layout(&mut self) -> Option<JointLayout>;
    /// The next joint-state frame not yet taken, oldest first.
    fn next_state(&mut self) -> Option<JointState>;
    /// The newest bus health of the driver.
    fn bus_health(&mut self) -> Option<BusHealth>;
    /// The header of the newest frame of configured camera `index` (`sensors.cameras`)
    /// published since the last call, after `look` has seen it with its pixels (in place: a
    /// thumbnail is made from shared memory).
    fn camera(
        &mut self,
        index: usize,
        look: &mut dyn FnMut(&CameraFrameHeader, &[u8]),
    ) -> Option<CameraFrameHeader>;
    /// The newest JPEG of observation camera `index` (`observation.cameras`) published since
    /// the last call: copied into `jpeg`, its header returned; `None` (and `jpeg` untouched)
    /// if there is none newer.
    fn image(&mut self, index: usize, jpeg: &mut Vec<u8>) -> Option<CameraFrameHeader>;
    /// The newest lidar scan.
    fn lidar(&mut self) -> Option<LidarScan>;
    /// The next supervisor event not yet taken.
    fn next_event(&mut self) -> Option<SupervisorEvent>;
    /// The newest heartbeat of the driver or the supervisor.
    fn heartbeat(&mut self, peer: Peer) -> Option<Heartbeat>;
    /// Appends an event's record to the robot's journal; its number, once on the storage.
    fn journal(&mut self, record: &[u8]) -> Result<u64, JournalError>;
    /// Keeps (across restarts) that the fleet has stored the journal's events through `seq`.
    fn acknowledged(&mut self, seq: u64);
    /// The next acknowledgement of the fleet's store (its bytes, undecoded).
    fn next_ack(&mut self) -> Option<Vec<u8>>;
    /// Publishes a goal frame to the driver; whether it went out.
    fn send_goal(&mut self, goal: &GoalFrame) -> bool;
    /// The lift controller's newest state, if one was published since the last call.
    fn lift(&mut self) -> Option<LiftState>;
    /// The base controller's newest state, if one was published since the last call.
    fn base(&mut self) -> Option<BaseState>;
    /// Publishes a height to the lift's controller; whether it went out.
    fn send_lift(&mut self, command: &LiftCommand) -> bool;
    /// Publishes a velocity to the base's controller; whether it went out.
    fn send_base(&mut self, command: &BaseCommand) -> bool;
    /// Publishes `payload` to the fleet; whether it went out.
    fn publish(&mut self, what: Outbound, payload: Vec<u8>) -> bool;
    /// The next action chunk received from the fleet (its bytes, undecoded).
    fn next_action(&mut self) -> Option<Vec<u8>>;
    /// Answers every status query waiting, each with `status()`'s bytes.
    fn answer_status(&mut self, status: &mut dyn FnMut() -> Vec<u8>);
    /// Whether the link to the fleet has come up since the last call, after the agent had
    /// run without it (it started with its router out of reach). Until then `publish` sends
    /// nothing and nothing arrives; events are journaled all the same.
    fn fleet_joined(&mut self) -> bool {
        false
    }
    /// The black box's finished boxes, if the shelf's listing changed since the last call
    /// (`None` too when the agent watches no shelf).
    fn shelf(&mut self) -> Option<Vec<ShelvedBox>> {
        None
    }
    /// Asks for the bytes of `chunk` of a box on the shelf, read away from the loop; whether
    /// the request was taken (one at a time).
    fn ask_box(&mut self, _chunk: &ChunkToSend) -> bool {
        false
    }
    /// A chunk asked for, once read: its bytes, or why they could not be.
    fn box_bytes(&mut self) -> Option<ChunkRead> {
        None
    }
    /// The next acknowledgement of a box by the fleet's store (its bytes, undecoded).
    fn next_box_ack(&mut self) -> Option<Vec<u8>> {
        None
    }
}

/// The agent's counters beyond the gate's and the scheduler's own.
#[derive(Debug, Default, Clone)]
struct Counters {
    state_sent: u64,
    observations_sent: u64,
    events_unjournaled: u64,
    acks_malformed: u64,
    goals_forwarded: u64,
    lift_commands_forwarded: u64,
    base_commands_forwarded: u64,
    plans_dropped: u64,
    goals_withheld: u64,
    images_sent: u64,
    images_stale: u64,
    previews_sent: u64,
    previews_failed: u64,
    scans_sent: u64,
    box_acks_malformed: u64,
    box_read_failures: u64,
    last_rejection: String,
}

/// Everything the agent knows.
pub struct Agent {
    config: AgentConfig,
    gate: ActionGate,
    scheduler: Scheduler,
    layout: JointLayout,
    ranges: Vec<Range>,
    state_every: Every,
    observation_every: Every,
    layout_every: Every,
    forward_every: Every,
    warn_every: Every,
    counters: Counters,
    last_state: Option<JointState>,
    last_health: Option<BusHealth>,
    last_cameras: Vec<Option<CameraFrameHeader>>,
    last_lidar: Option<LidarStatusOf>,
    last_lift: Option<LiftState>,
    last_base: Option<BaseState>,
    /// Each observation camera's newest JPEG and its header.
    images: Vec<(Option<CameraFrameHeader>, Vec<u8>)>,
    observations: u64,
    goal_seq: u64,
    /// When every camera's next thumbnail is due, and which cameras still owe theirs.
    preview_every: Every,
    preview_pending: Vec<bool>,
    thumbnailer: Thumbnailer,
    /// When the next lidar revolution is due for the fleet, and whether it is owed.
    scan_every: Every,
    scan_pending: bool,
    /// The journal's events on their way to the fleet.
    delivery: Delivery,
    /// The black box's boxes on their way to the fleet, and the chunk being read for it.
    upload: Upload,
    box_reading: Option<(ChunkToSend, u64)>,
    /// Bytes of a torn tail cut when the journal opened (journaled with the agent's start),
    /// `None` once the start is journaled.
    starting: Option<u64>,
    /// Refusals per reason since they were last journaled.
    refusals: Vec<u64>,
    refusals_every: Every,
    /// The package version the robot runs, if it was installed from one (`installed`).
    installed_version: Option<String>,
    /// The calibration the robot runs, if its file was read (`calibrated`).
    calibration: Option<CalibrationMsg>,
}

/// A rate from a period in seconds, 0 meaning never.
fn every_s(period_s: f64) -> Every {
    Every::hz(if period_s > 0.0 { 1.0 / period_s } else { 0.0 })
}

/// What the status says of the newest scan (a scan frame is 12 KB; this is what is kept).
#[derive(Debug, Clone, Copy)]
struct LidarStatusOf {
    seq: u64,
    bad_points: u32,
    resyncs: u32,
    short_scans: u32,
    end_ns: u64,
    rotation_hz: Option<f64>,
}

impl Agent {
    /// An agent with `config`, no layout and no plan yet, on a journal that was empty.
    pub fn new(config: &AgentConfig) -> Agent {
        Agent::resuming(config, JournalStart::default())
    }

    /// An agent with `config` on the journal `journal` found at its start: what the fleet has
    /// not acknowledged is sent again.
    pub fn resuming(config: &AgentConfig, journal: JournalStart) -> Agent {
        let (delivery, unreadable) = Delivery::new(
            journal.id,
            &journal.kept,
            journal.recovery.acked_through,
            config.delivery(),
        );
        if unreadable > 0 {
            tracing::warn!("{unreadable} journal records of another format could not be read");
        }
        Agent {
            delivery,
            upload: Upload::new(config.box_upload()),
            box_reading: None,
            starting: Some(journal.recovery.cut_bytes),
            refusals: vec![0; REASONS.len()],
            refusals_every: Every::hz(1e9 / REFUSALS_EVERY_NS as f64),
            gate: ActionGate::new(config.gate()),
            scheduler: Scheduler::new(
                config.actions.blend_new,
                config.actions.horizon_ms * 1_000_000,
            ),
            layout: JointLayout::default(),
            ranges: Vec::new(),
            state_every: Every::hz(config.telemetry.state_hz),
            observation_every: Every::hz(config.telemetry.observation_hz),
            layout_every: Every::hz(1.0 / config.telemetry.layout_every_s),
            forward_every: Every::hz(config.actions.forward_hz),
            warn_every: Every::hz(1.0),
            counters: Counters::default(),
            last_state: None,
            last_health: None,
            last_cameras: vec![None; config.sensors.cameras.len()],
            last_lidar: None,
            last_lift: None,
            last_base: None,
            images: vec![(None, Vec::new()); config.observation.cameras.len()],
            observations: 0,
            goal_seq: 0,
            preview_every: every_s(config.preview.every_s),
            preview_pending: vec![false; config.sensors.cameras.len()],
            thumbnailer: Thumbnailer::new(config.preview.width, config.preview.quality),
            scan_every: every_s(config.preview.scan_every_s),
            scan_pending: false,
            installed_version: None,
            calibration: None,
            config: config.clone(),
        }
    }

    /// The agent of a robot installed from the `nori-robot` package at `version` (`None`: a
    /// build from source): its status says so, and its start's event carries it, so the
    /// fleet's store keeps which version ran when.
    pub fn installed(mut self, version: Option<String>) -> Agent {
        self.installed_version = version;
        self
    }

    /// The agent of a robot running `calibration` (`None`: no file, or an unreadable one): its
    /// status says so, and its start journals it, so the fleet's store keeps which
    /// calibration ran when.
    pub fn calibrated(mut self, calibration: Option<CalibrationMsg>) -> Agent {
        self.calibration = calibration;
        self
    }

    /// One turn of the loop at robot time `now` (CLOCK_MONOTONIC ns) and wall time `wall_ms`
    /// (for the fleet's plots only).
    pub fn poll(&mut self, io: &mut impl AgentIo, now: u64, wall_ms: u64) {
        if io.fleet_joined() {
            // Everything held goes out now, and the layout with it (the fleet reads the
            // telemetry by it), not at their next intervals.
            self.delivery.resend_now();
            self.upload.link_up();
            self.layout_every = Every::hz(1.0 / self.config.telemetry.layout_every_s);
        }
        if let Some(cut_bytes) = self.starting.take() {
            let version = self.installed_version.clone().unwrap_or_default();
            self.journal(
                io,
                agent_record(now, wall_ms, AGENT_STARTED, &version, cut_bytes as f32),
            );
            let detail = calibration_detail(self.calibration.as_ref());
            let joints = self
                .calibration
                .as_ref()
                .map_or(0.0, |c| f32::from(c.joints));
            self.journal(
                io,
                agent_record(now, wall_ms, CALIBRATION_IN_FORCE, &detail, joints),
            );
        }
        self.take_layout(io, now);
        self.forward_telemetry(io, now, wall_ms);
        let new_plan = self.take_actions(io, now);
        // A new plan goes out at once, not at the next forwarding tick (up to 10 ms later).
        let due = self.forward_every.due(now);
        if new_plan || due {
            self.forward_goal(io, now);
        }
        self.journal_refusals(io, now, wall_ms);
        self.deliver(io, now);
        self.ship_boxes(io, now);
        io.answer_status(&mut || encode(&self.status(now)));
    }

    /// Keeps `record` in the journal and holds it for the fleet; if the journal cannot keep it,
    /// it goes out once, live and unnumbered, and is counted.
    fn journal(&mut self, io: &mut impl AgentIo, record: EventRecord) {
        let bytes = Delivery::journal_bytes(&record);
        match io.journal(&bytes) {
            Ok(seq) => self.delivery.journaled(seq, record, bytes.len()),
            Err(e) => {
                self.counters.events_unjournaled += 1;
                tracing::error!("event {} not journaled: {e}", record.kind);
                io.publish(Outbound::Event, encode(&self.delivery.unnumbered(record)));
            }
        }
    }

    /// Sends what is due of the journal and takes the fleet's acknowledgements.
    fn deliver(&mut self, io: &mut impl AgentIo, now: u64) {
        while let Some(bytes) = io.next_ack() {
            let through = match decode::<AckMsg>(&bytes) {
                Ok(a) => self.delivery.acknowledged(&a).map_err(|e| e.to_string()),
                Err(e) => {
                    self.counters.acks_malformed += 1;
                    Err(e.to_string())
                }
            };
            match through {
                Ok(Some(seq)) => io.acknowledged(seq),
                Ok(None) => {}
                Err(e) => {
                    if self.warn_every.due(now) {
                        tracing::warn!("acknowledgement refused: {e}");
                    }
                }
            }
        }
        while let Some(msg) = self.delivery.next_to_send(now) {
            io.publish(Outbound::Event, encode(&msg));
        }
    }

    /// Sends what is due of the black box's boxes (only while every event is acknowledged: a
    /// box never goes ahead of the journal) and takes the store's acknowledgements.
    fn ship_boxes(&mut self, io: &mut impl AgentIo, now: u64) {
        if let Some(listing) = io.shelf() {
            self.upload.shelf(&listing);
        }
        while let Some(bytes) = io.next_box_ack() {
            match decode::<BoxAckMsg>(&bytes) {
                Ok(a) => {
                    self.upload.acknowledged(BoxAck {
                        number: a.number,
                        digest: a.digest,
                        received: a.received,
                        complete: a.complete,
                        refused: a.refused,
                    });
                }
                Err(e) => {
                    self.counters.box_acks_malformed += 1;
                    if self.warn_every.due(now) {
                        tracing::warn!("a box's acknowledgement refused: {e}");
                    }
                }
            }
        }
        if let Some((asked, at)) = &self.box_reading {
            let Some((chunk, read)) = io.box_bytes() else {
                if now.saturating_sub(*at) > BOX_READ_TIMEOUT_NS {
                    // The shelf's thread is gone or stuck: taken as a failed read.
                    let asked = asked.clone();
                    self.box_reading = None;
                    self.box_unread(&asked, now, "no answer from the shelf's thread");
                }
                return;
            };
            self.box_reading = None;
            match read {
                Ok(data) => {
                    io.publish(Outbound::BoxChunk, encode(&box_chunk_msg(&chunk, data)));
                }
                Err(e) => self.box_unread(&chunk, now, &e.to_string()),
            }
        }
        let quiet = self.delivery.held() == 0;
        while let Some(chunk) = self.upload.next_chunk(now, quiet) {
            if chunk.len == 0 {
                // A probe carries no bytes: nothing to read.
                io.publish(
                    Outbound::BoxChunk,
                    encode(&box_chunk_msg(&chunk, Vec::new())),
                );
                continue;
            }
            if io.ask_box(&chunk) {
                self.box_reading = Some((chunk, now));
            } else {
                self.box_unread(&chunk, now, "the shelf is not watched");
            }
            break;
        }
    }

    /// `chunk` could not be read: tried again after the wait, the box set aside after a few
    /// failures in a row, or counted lost once off the shelf.
    fn box_unread(&mut self, chunk: &ChunkToSend, now: u64, why: &str) {
        self.upload.unsent(chunk, now);
        self.counters.box_read_failures += 1;
        if self.warn_every.due(now) {
            tracing::warn!("a chunk of box {} not read: {why}", chunk.name);
        }
    }

    /// Journals the supervisor's and the driver's starts: a heartbeat from a process id the
    /// journal does not know yet.
    fn watch_starts(&mut self, io: &mut impl AgentIo, now: u64, wall_ms: u64) {
        for (peer, kind) in [
            (Peer::Supervisor, SUPERVISOR_STARTED),
            (Peer::Driver, DRIVER_STARTED),
        ] {
            if let Some(h) = io.heartbeat(peer) {
                if self.delivery.started_pid(kind) != Some(h.pid) {
                    self.journal(io, agent_record(now, wall_ms, kind, "", h.pid as f32));
                }
            }
        }
    }

    /// Journals the refusals counted since the last time, one event per reason, when due.
    fn journal_refusals(&mut self, io: &mut impl AgentIo, now: u64, wall_ms: u64) {
        if self.refusals.iter().all(|&n| n == 0) || !self.refusals_every.due(now) {
            return;
        }
        for (i, reason) in REASONS.iter().enumerate() {
            let n = std::mem::take(&mut self.refusals[i]);
            if n > 0 {
                self.journal(
                    io,
                    agent_record(now, wall_ms, ACTIONS_REFUSED, reason, n as f32),
                );
            }
        }
    }

    fn take_layout(&mut self, io: &mut impl AgentIo, now: u64) {
        if let Some(l) = io.layout() {
            if l != self.layout {
                self.layout = l;
                self.ranges = outbound::ranges(&self.layout);
                // A new driver (or a new layout): the old plan was made for another robot state.
                self.scheduler.clear();
                self.layout_every = Every::hz(1.0 / self.config.telemetry.layout_every_s);
            }
        }
        if self.layout.joint_count > 0 && self.layout_every.due(now) {
            io.publish(
                Outbound::Layout,
                encode(&outbound::layout_msg(&self.layout)),
            );
        }
    }

    fn forward_telemetry(&mut self, io: &mut impl AgentIo, now: u64, wall_ms: u64) {
        // Every frame, in order: the gate must see the driver enter its safe state or restart,
        // however briefly, to drop the plan made before it.
        let mut newest = None;
        while let Some(s) = io.next_state() {
            let safe = s.flags & STATE_FLAG_SAFE_STATE != 0;
            if self.gate.observe_driver(s.seq, s.timestamp_ns, safe)
                && self.scheduler.planned_steps() > 0
            {
                self.scheduler.clear();
                self.counters.plans_dropped += 1;
                tracing::info!(
                    "driver restarted or in its safe state: the plan made before is dropped"
                );
            }
            newest = Some(s);
        }
        self.last_lift = io.lift().or(self.last_lift);
        self.last_base = io.base().or(self.last_base);
        let body = self.body(now);
        if let Some(s) = newest {
            self.last_state = Some(s);
            if self.state_every.due(now)
                && io.publish(
                    Outbound::State,
                    encode(&outbound::state_msg(&s, body, wall_ms)),
                )
            {
                self.counters.state_sent += 1;
            }
            for (i, (header, jpeg)) in self.images.iter_mut().enumerate() {
                if let Some(h) = io.image(i, jpeg) {
                    *header = Some(h);
                }
            }
            if self.observation_every.due(now) {
                let images = self.observation_images(&s);
                if io.publish(
                    Outbound::Observation,
                    encode(&outbound::observation_msg(&s, images, body)),
                ) {
                    self.counters.observations_sent += 1;
                }
            }
        }
        if let Some(h) = io.bus_health() {
            self.last_health = Some(h);
        }
        self.watch_sensors(io, now, wall_ms);
        self.watch_starts(io, now, wall_ms);
        while let Some(e) = io.next_event() {
            // The state plane replays its recent events to a restarted agent: journaled once.
            if !self.delivery.seen(e.seq, e.timestamp_ns) {
                self.journal(io, outbound::event_record(&e, &self.layout, wall_ms));
            }
        }
    }

    /// The lift and the base as their controllers last said, when that is fresh.
    fn body(&self, now: u64) -> outbound::Body {
        let fresh = |t: u64| now.saturating_sub(t) <= BODY_FRESH_NS;
        outbound::Body {
            lift: (self.last_lift)
                .filter(|l| fresh(l.timestamp_ns))
                .map(|l| outbound::lift_msg(&l)),
            base: (self.last_base)
                .filter(|b| fresh(b.timestamp_ns))
                .map(|b| outbound::base_msg(&b)),
        }
    }

    /// Takes each sensor's newest frame for the status and, when due, sends the fleet a
    /// thumbnail of every camera (each from its first frame after the due time: a camera that
    /// sends nothing owes its thumbnail until it does) and a lidar revolution. One thumbnail a
    /// turn at most (~2 ms of a 720p frame here): four cameras due together never hold up the
    /// goals forwarded in between.
    fn watch_sensors(&mut self, io: &mut impl AgentIo, now: u64, wall_ms: u64) {
        if self.preview_every.due(now) {
            self.preview_pending.fill(true);
        }
        let mut thumbnail_made = false;
        for i in 0..self.last_cameras.len() {
            let (pending, thumbnailer) = (&mut self.preview_pending[i], &mut self.thumbnailer);
            let mut made = None;
            let header = io.camera(i, &mut |h, pixels| {
                if *pending && !thumbnail_made {
                    thumbnail_made = true;
                    *pending = false;
                    made = Some(
                        thumbnailer
                            .make(h, pixels)
                            .map(|(jpeg, w, ht)| preview_msg(h, jpeg, w, ht, wall_ms)),
                    );
                }
            });
            if let Some(h) = header {
                self.last_cameras[i] = Some(h);
            }
            match made {
                Some(Ok(msg)) if io.publish(Outbound::Preview, encode(&msg)) => {
                    self.counters.previews_sent += 1;
                }
                Some(Err(e)) => {
                    self.counters.previews_failed += 1;
                    if self.warn_every.due(now) {
                        tracing::warn!("no thumbnail: {e}");
                    }
                }
                Some(Ok(_)) | None => {}
            }
        }
        if self.config.sensors.lidar {
            self.scan_pending |= self.scan_every.due(now);
            if let Some(scan) = io.lidar() {
                if std::mem::take(&mut self.scan_pending)
                    && io.publish(Outbound::Scan, encode(&scan_msg(&scan, wall_ms)))
                {
                    self.counters.scans_sent += 1;
                }
                self.last_lidar = Some(LidarStatusOf {
                    seq: scan.seq,
                    bad_points: scan.bad_points,
                    resyncs: scan.resyncs,
                    short_scans: scan.short_scans,
                    end_ns: scan.end_ns,
                    rotation_hz: scan.rotation_hz(),
                });
            }
        }
    }

    /// The images the observation of state `s` carries: on every `image-every`-th observation,
    /// each observation camera's newest JPEG if it was captured within `image-max-age-ms` of
    /// the state (a later capture is as good: the policy sees the newest picture), else none
    /// for that camera, counted.
    fn observation_images(&mut self, s: &JointState) -> Vec<ImageMsg> {
        let o = &self.config.observation;
        let carries = self.observations.is_multiple_of(u64::from(o.image_every));
        self.observations += 1;
        if !carries {
            return Vec::new();
        }
        let max_age = o.image_max_age_ms * 1_000_000;
        let mut out = Vec::with_capacity(self.images.len());
        for (name, (header, jpeg)) in o.cameras.iter().zip(&self.images) {
            match header {
                Some(h) if s.timestamp_ns.saturating_sub(h.capture_ns) <= max_age => {
                    out.push(ImageMsg {
                        camera: name.clone(),
                        seq: h.seq,
                        capture_ns: h.capture_ns,
                        width: h.width,
                        height: h.height,
                        encoding: "jpeg".into(),
                        data: jpeg.clone(),
                    });
                    self.counters.images_sent += 1;
                }
                _ => self.counters.images_stale += 1,
            }
        }
        out
    }

    /// Checks every chunk received; whether one was accepted (a new plan).
    fn take_actions(&mut self, io: &mut impl AgentIo, now: u64) -> bool {
        let mut new_plan = false;
        while let Some(bytes) = io.next_action() {
            match self.gate.check(&bytes, now, &self.ranges) {
                Ok(chunk) => {
                    self.scheduler.insert(&chunk, now);
                    new_plan = true;
                }
                Err(r) => {
                    self.refusals[r.reason_index()] += 1;
                    self.counters.last_rejection = r.to_string();
                    if self.warn_every.due(now) {
                        tracing::warn!(reason = r.reason(), "action refused: {r}");
                    }
                }
            }
        }
        new_plan
    }

    fn forward_goal(&mut self, io: &mut impl AgentIo, now: u64) {
        match self.scheduler.target(now) {
            // The last door: a value outside a calibrated range (or the lift's and the base's
            // limits) never leaves the agent, whatever the scheduler made of the chunks.
            Some(target)
                if !within(&self.ranges, &target.position, target.mask)
                    || !(self.gate.body_limits()).within(target.lift_m, target.base_twist) =>
            {
                self.counters.goals_withheld += 1;
                self.scheduler.clear();
                tracing::error!(
                    "a scheduled target outside the calibrated range was withheld and the plan dropped"
                );
            }
            Some(target) => {
                self.goal_seq += 1;
                let seq = self.goal_seq;
                let c = &mut self.counters;
                if target.mask != 0 {
                    let frame = outbound::goal_frame(&target, self.layout.joint_count, seq, now);
                    c.goals_forwarded += u64::from(io.send_goal(&frame));
                }
                if let Some(lift) = outbound::lift_command(&target, seq, now) {
                    c.lift_commands_forwarded += u64::from(io.send_lift(&lift));
                }
                if let Some(base) = outbound::base_command(&target, seq, now) {
                    c.base_commands_forwarded += u64::from(io.send_base(&base));
                }
            }
            None => {}
        }
    }

    /// The status reply at `now`.
    pub fn status(&self, now: u64) -> StatusMsg {
        let c = &self.counters;
        let a = &self.config.actions;
        let state = self.last_state.as_ref();
        StatusMsg {
            version: SCHEMA_VERSION,
            robot_id: self.config.robot_id.clone(),
            agent_version: env!("CARGO_PKG_VERSION").into(),
            installed_version: self.installed_version.clone(),
            calibration: self.calibration.clone(),
            config: StatusConfig {
                state_hz: self.config.telemetry.state_hz,
                observation_hz: self.config.telemetry.observation_hz,
                max_age_ms: a.max_age_ms,
                horizon_ms: a.horizon_ms,
                blend_new: a.blend_new,
                forward_hz: a.forward_hz,
            },
            health: StatusHealth {
                joints: self.layout.joint_count,
                state_age_ms: state.map(|s| now.saturating_sub(s.timestamp_ns) as f64 / 1e6),
                safe_state: state.map(|s| s.flags & STATE_FLAG_SAFE_STATE != 0),
                deadline_misses: state.map(|s| s.deadline_misses),
                planned_steps: self.scheduler.planned_steps() as u64,
            },
            counters: AgentCounters {
                state_sent: c.state_sent,
                observations_sent: c.observations_sent,
                events_sent: self.delivery.sent(),
                events_resent: self.delivery.resent(),
                events_unacknowledged: self.delivery.held() as u64,
                events_stored_through: self.delivery.stored_through(),
                events_lost: self.delivery.lost(),
                events_unjournaled: c.events_unjournaled,
                acks_refused: self.delivery.acks_refused() + c.acks_malformed,
                actions_accepted: self.gate.accepted(),
                actions_rejected: REASONS
                    .iter()
                    .zip(self.gate.rejected())
                    .map(|(r, n)| (r.to_string(), *n))
                    .collect(),
                steps_dropped_past: self.scheduler.dropped_past_steps(),
                plans_expired: self.scheduler.expired(),
                goals_forwarded: c.goals_forwarded,
                lift_commands_forwarded: c.lift_commands_forwarded,
                base_commands_forwarded: c.base_commands_forwarded,
                plans_dropped: c.plans_dropped,
                goals_withheld: c.goals_withheld,
                images_sent: c.images_sent,
                images_stale: c.images_stale,
                previews_sent: c.previews_sent,
                previews_failed: c.previews_failed,
                scans_sent: c.scans_sent,
                boxes: self.box_counters(),
            },
            last_rejection: c.last_rejection.clone(),
            // Named from the driver's layout: the one source of names.
            buses: self
                .last_health
                .as_ref()
                .map(BusHealth::buses)
                .unwrap_or_default()
                .iter()
                .enumerate()
                .map(|(i, b)| BusStatus {
                    name: self
                        .layout
                        .bus_names()
                        .nth(i)
                        .map_or_else(|| format!("bus{i}"), str::to_string),
                    connected: b.flags & BUS_HEALTH_CONNECTED != 0,
                    enabled: b.flags & BUS_HEALTH_ENABLED != 0,
                    counters: b.counters,
                })
                .collect(),
            cameras: self
                .config
                .sensors
                .cameras
                .iter()
                .zip(&self.last_cameras)
                .map(|(name, h)| CameraStatus {
                    name: name.clone(),
                    frames: h.map_or(0, |h| h.seq + 1),
                    dropped: h.map_or(0, |h| u64::from(h.dropped)),
                    corrupt: h.map_or(0, |h| u64::from(h.corrupt)),
                    late: h.map_or(0, |h| u64::from(h.late)),
                    age_ms: h.map(|h| now.saturating_sub(h.capture_ns) as f64 * 1e-6),
                })
                .collect(),
            lidar: self.config.sensors.lidar.then(|| {
                let l = self.last_lidar;
                LidarStatus {
                    scans: l.map_or(0, |l| l.seq + 1),
                    bad_points: l.map_or(0, |l| u64::from(l.bad_points)),
                    resyncs: l.map_or(0, |l| u64::from(l.resyncs)),
                    short_scans: l.map_or(0, |l| u64::from(l.short_scans)),
                    rotation_hz: l.and_then(|l| l.rotation_hz),
                    age_ms: l.map(|l| now.saturating_sub(l.end_ns) as f64 * 1e-6),
                }
            }),
        }
    }

    fn box_counters(&self) -> BoxCounters {
        let u = self.upload.counters();
        BoxCounters {
            pending: self.upload.pending() as u64,
            stored: u.boxes_stored,
            lost: u.boxes_lost,
            refused: u.boxes_refused,
            unreadable: u.boxes_unreadable,
            bytes_sent: u.bytes_sent,
            bytes_resent: u.bytes_resent,
            acks_refused: u.acks_refused + self.counters.box_acks_malformed,
            read_failures: self.counters.box_read_failures,
        }
    }

    /// Action chunks accepted so far.
    pub fn accepted(&self) -> u64 {
        self.gate.accepted()
    }

    /// Goal frames forwarded so far.
    pub fn goals_forwarded(&self) -> u64 {
        self.counters.goals_forwarded
    }
}

/// How often the loop polls.
pub const POLL: Duration = Duration::from_millis(1);

/// Runs the agent until `shutdown` (or `run_for`), polling every [`POLL`]; `keepalive` is
/// called every turn (the service manager's watchdog).
pub fn run(
    agent: &mut Agent,
    io: &mut impl AgentIo,
    shutdown: &AtomicBool,
    run_for: Option<Duration>,
    keepalive: &mut dyn FnMut(Instant),
) {
    let started = Instant::now();
    while !shutdown.load(Ordering::Relaxed) && run_for.is_none_or(|d| started.elapsed() < d) {
        keepalive(Instant::now());
        agent.poll(io, telemetry::clock::monotonic_ns(), wall_ms());
        std::thread::sleep(POLL);
    }
}

/// Wall-clock time, ms since the Unix epoch.
pub fn wall_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// The message carrying `chunk`'s bytes.
fn box_chunk_msg(chunk: &ChunkToSend, data: Vec<u8>) -> BoxChunkMsg {
    BoxChunkMsg {
        version: SCHEMA_VERSION,
        number: chunk.number,
        name: chunk.name.clone(),
        size: chunk.size,
        digest: chunk.digest,
        offset: chunk.offset,
        data,
    }
}

/// One of the agent's own events.
fn agent_record(now: u64, wall_ms: u64, kind: &str, detail: &str, value: f32) -> EventRecord {
    EventRecord {
        timestamp_ns: now,
        wall_ms,
        origin_seq: 0,
        kind: kind.into(),
        joint: String::new(),
        detail: detail.into(),
        bus: u8::MAX,
        level: 0,
        value,
    }
}
