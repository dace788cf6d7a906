//! The lab's loop, shaped like the supervisor's: [`Lab`] holds what the loop knows between
//! turns (teleoperation and the scene once the driver's layout is known, the newest states,
//! the supervisor's recent events, the presses waiting for their answer, what it counted), and
//! [`Lab::turn`] does one turn against a [`LabIo`], whose clock it reads. The binary wires the
//! state plane, the pages' server, the cameras and the recorder into a `LabIo`; the tests wire
//! queues and a clock of their own, so the loop is tested without a browser.
//!
//! A turn, in order: the plane (layout, states, lift, base, camera images); the presses the
//! supervisor has answered; at most one thing a page did, waited for until the next tick; the
//! teleoperation tick (every [`TICK`], and at once after a page acted, so a command or a
//! release is not held back a tick); a recording that ended; the cameras' images and the
//! pages' view when due.

use crate::messages::{BaseView, CameraStatus, LiftView};
use crate::messages::{EventView, FrameExtras, Reply, TeleopView, ToPage};
use crate::page::PageMessage;
use crate::recording::{Outcome, RecordingStatus};
use crate::scene::Scene;
use crate::server::{Event, Inbound, Outgoing};
use crate::stop_button::{Pending, Press};
use crate::teleop::{Refusal, Teleop, TeleopCounters, TeleopSettings};
use body::kinematics::Body;
use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;
use telemetry::frames::{
    GoalFrame, JointLayout, SupervisorCommand, SupervisorEvent, COMMAND_RESUME, COMMAND_STOP,
};
use telemetry::motion::{BaseState, LiftAllowance, LiftState, LIFT_READY};
use telemetry::JointState;

/// The teleoperation loop's period.
pub const TICK: Duration = Duration::from_millis(10);
/// Supervisor events kept for the page.
pub const RECENT_EVENTS: usize = 12;

/// The pages' server stopped (it stops only once the lab is asked to).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the lab's server stopped")]
pub struct ServerStopped;

/// What a record button asks of the recorder.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RecordRequest {
    /// Start an episode of this task.
    Start(String),
    /// End the episode and keep it.
    Keep,
    /// End the episode and throw it away.
    Discard,
}

/// The lab's plane, pages, cameras and recorder, as its loop uses them. Every call returns at
/// once except [`LabIo::next_page_event`], which waits at most its bound.
pub trait LabIo {
    /// CLOCK_MONOTONIC, ns (the plane's and the pages' clock).
    fn now_ns(&self) -> u64;
    /// The driver's newest joint layout, if one was published.
    fn layout(&mut self) -> Option<JointLayout>;
    /// The next joint-state frame not yet taken, oldest first.
    fn next_state(&mut self) -> Option<JointState>;
    /// The lift's newest state (none on a robot without a lift).
    fn lift(&mut self) -> Option<LiftState>;
    /// The base's newest state (none on a robot without a base).
    fn base(&mut self) -> Option<BaseState>;
    /// The next supervisor event not yet taken.
    fn next_event(&mut self) -> Option<SupervisorEvent>;
    /// The supervisor's newest lift allowance.
    fn allowance(&mut self) -> Option<LiftAllowance>;
    /// Publishes a goal frame on the driver's goal path.
    fn publish_goal(&mut self, frame: &GoalFrame) -> Result<(), String>;
    /// Publishes an operator's command to the supervisor.
    fn publish_command(&mut self, command: &SupervisorCommand) -> Result<(), String>;
    /// The next thing a page did, waiting at most `wait` for one.
    fn next_page_event(&mut self, wait: Duration) -> Result<Option<Inbound>, ServerStopped>;
    /// Queues `text` for page `page`.
    fn send(&mut self, page: u64, text: Arc<str>);
    /// Queues `message` for every open page.
    fn broadcast(&mut self, message: &Outgoing);
    /// Pages open now.
    fn pages_open(&self) -> usize;
    /// Takes in what the cameras published, keeping each one's newest image.
    fn take_camera_images(&mut self);
    /// Sends each camera's newest image to the pages, once.
    fn send_camera_images(&mut self);
    /// The cameras shown, at `now_ns`.
    fn camera_status(&self, now_ns: u64) -> Vec<CameraStatus>;
    /// Asks the recorder for `request`; why not, if it cannot.
    fn record(&mut self, request: RecordRequest) -> Result<(), String>;
    /// An episode that ended since the last call.
    fn recorded(&mut self) -> Option<Outcome>;
    /// The recording, for the page (none when the lab records nothing).
    fn recording_status(&self) -> Option<RecordingStatus>;
}

/// The lab's settings.
#[derive(Clone)]
pub struct LabSettings {
    /// The robot's kinematics.
    pub body: Body,
    /// Teleoperation's bounds.
    pub teleop: TeleopSettings,
    /// The cameras shown on the pages.
    pub cameras: Vec<String>,
    /// State frames sent to the pages this often.
    pub frame_every: Duration,
    /// Camera images sent to the pages this often.
    pub camera_every: Duration,
}

/// What the loop counted, printed at exit.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct Counts {
    /// Goal frames published.
    pub goal_frames: u64,
    /// Page messages that were not messages.
    pub malformed: u64,
    /// Stop presses.
    pub stops: u64,
    /// Resume presses.
    pub resumes: u64,
    /// Goal frames or messages to a page that could not be sent.
    pub publish_errors: u64,
}

/// What the lab prints at exit.
#[derive(Debug, serde::Serialize)]
pub struct Summary<'a> {
    /// The loop's counts.
    #[serde(flatten)]
    pub counts: &'a Counts,
    /// Teleoperation's (none before the driver's layout).
    pub teleop: Option<&'a TeleopCounters>,
    /// Messages dropped because a page did not keep up.
    pub dropped_messages: u64,
    /// Link requests refused.
    pub denied_links: u64,
}

/// Teleoperation and the scene, for the driver's layout.
struct Driven {
    teleop: Teleop,
    scene: Scene,
    /// The model message, as sent to every page.
    model: Arc<str>,
}

/// The lab's loop state.
pub struct Lab {
    settings: LabSettings,
    driven: Option<Driven>,
    state: Option<JointState>,
    /// The lift's height once homed; without a lift, where the description has it.
    lift_m: f64,
    lift: Option<LiftState>,
    base: Option<BaseState>,
    recent: VecDeque<EventView>,
    command_seq: u64,
    /// Stop and resume presses waiting for the supervisor to show it heard them.
    presses: Vec<Pending>,
    counts: Counts,
    next_tick_ns: u64,
    next_frame_ns: u64,
    next_images_ns: u64,
}

fn ns(d: Duration) -> u64 {
    u64::try_from(d.as_nanos()).unwrap_or(u64::MAX)
}

impl Lab {
    /// A lab with `settings`, its first turn at `now_ns`.
    pub fn new(settings: LabSettings, now_ns: u64) -> Lab {
        Lab {
            lift_m: settings.body.lift_start_m(),
            settings,
            driven: None,
            state: None,
            lift: None,
            base: None,
            recent: VecDeque::with_capacity(RECENT_EVENTS),
            command_seq: 0,
            presses: Vec::new(),
            counts: Counts::default(),
            next_tick_ns: now_ns,
            next_frame_ns: now_ns,
            next_images_ns: now_ns,
        }
    }

    /// One turn of the loop (see the module's doc for its order).
    pub fn turn(&mut self, io: &mut impl LabIo) -> Result<(), ServerStopped> {
        self.take_plane(io);
        self.answer_presses(io);
        let wait = self.next_tick_ns.saturating_sub(io.now_ns());
        let acted = match io.next_page_event(Duration::from_nanos(wait))? {
            Some(inbound) => self.on_page(io, inbound),
            None => false,
        };
        let now = io.now_ns();
        if now >= self.next_tick_ns || acted {
            if now >= self.next_tick_ns {
                self.next_tick_ns = now + ns(TICK);
            }
            self.teleop_tick(io, now);
        }
        if let Some(outcome) = io.recorded() {
            tracing::info!("recording: {outcome:?}");
            self.broadcast(io, &ToPage::Recorded { outcome: &outcome });
        }
        if now >= self.next_images_ns {
            self.next_images_ns = now + ns(self.settings.camera_every);
            io.send_camera_images();
        }
        if now >= self.next_frame_ns {
            self.next_frame_ns += ns(self.settings.frame_every);
            if self.next_frame_ns < now {
                self.next_frame_ns = now + ns(self.settings.frame_every);
            }
            self.send_view(io, now);
        }
        Ok(())
    }

    /// What was counted, for the exit's summary.
    pub fn summary(&self, dropped_messages: u64, denied_links: u64) -> Summary<'_> {
        Summary {
            counts: &self.counts,
            teleop: self.driven.as_ref().map(|d| d.teleop.counters()),
            dropped_messages,
            denied_links,
        }
    }

    /// The driver's layout (a new one: a new teleoperation and model for every page), the
    /// joint states, the lift's, the base's and the cameras'.
    fn take_plane(&mut self, io: &mut impl LabIo) {
        if let Some(l) = io.layout().filter(|l| l.joint_count > 0) {
            if self.driven.as_ref().is_none_or(|d| *d.teleop.layout() != l) {
                let body = &self.settings.body;
                let scene = Scene::new(body.clone(), l);
                let model: Arc<str> = scene.model().to_string().into();
                io.broadcast(&Outgoing::Text(model.clone()));
                let teleop = Teleop::new(body.clone(), l, self.settings.teleop);
                self.driven = Some(Driven {
                    teleop,
                    scene,
                    model,
                });
                tracing::info!(joints = l.joint_count, "the driver's layout");
            }
        }
        while let Some(s) = io.next_state() {
            if let Some(d) = self.driven.as_mut() {
                d.teleop.observe(&s);
            }
            self.state = Some(s);
        }
        if let Some(l) = io.lift() {
            if l.state == LIFT_READY && l.height_m.is_finite() {
                self.lift_m = f64::from(l.height_m);
            }
            self.lift = Some(l);
        }
        self.base = io.base().or(self.base);
        io.take_camera_images();
    }

    /// The supervisor's events (kept for the page) and allowance answer the presses waiting;
    /// a press waiting too long is answered unheard.
    fn answer_presses(&mut self, io: &mut impl LabIo) {
        let mut answers = Vec::new();
        while let Some(e) = io.next_event() {
            if self.recent.len() == RECENT_EVENTS {
                self.recent.pop_front();
            }
            self.recent.push_back(EventView::from(&e));
            answers.extend(
                self.presses
                    .iter()
                    .filter_map(|p| Some((*p, p.on_event(&e)?))),
            );
        }
        let allowance = io.allowance();
        let now_ns = io.now_ns();
        for p in &self.presses {
            let answer = allowance
                .and_then(|a| p.on_allowance(&a))
                .or(p.expired(now_ns));
            answers.extend(answer.map(|a| (*p, a)));
        }
        for (p, answer) in answers {
            if self.presses.contains(&p) {
                self.presses.retain(|q| *q != p);
                self.say(io, p.page, ToPage::Reply(Reply::press(p.press, answer)));
            }
        }
    }

    /// What page `page` did; whether it acted (then teleoperation ticks at once).
    fn on_page(&mut self, io: &mut impl LabIo, inbound: Inbound) -> bool {
        let Inbound { page, event, at_ns } = inbound;
        match event {
            Event::Opened => {
                let hello = ToPage::Hello {
                    page,
                    deadman_ms: self.settings.teleop.deadman_ms,
                    cameras: &self.settings.cameras,
                };
                let hello = hello.text();
                self.send_text(io, page, hello);
                if let Some(d) = &self.driven {
                    io.send(page, d.model.clone());
                }
                false
            }
            Event::Closed => {
                if let Some(d) = self.driven.as_mut() {
                    d.teleop.page_closed(page);
                }
                true
            }
            Event::Message(Err(e)) => {
                self.counts.malformed += 1;
                self.say(io, page, ToPage::Reply(Reply::malformed(&e)));
                false
            }
            Event::Message(Ok(PageMessage::Stop {})) => self.on_press(io, page, Press::Stop),
            Event::Message(Ok(PageMessage::Resume {})) => self.on_press(io, page, Press::Resume),
            Event::Message(Ok(PageMessage::RecordStart { task })) => {
                self.on_record(io, page, RecordRequest::Start(task))
            }
            Event::Message(Ok(PageMessage::RecordStop {})) => {
                self.on_record(io, page, RecordRequest::Keep)
            }
            Event::Message(Ok(PageMessage::RecordDiscard {})) => {
                self.on_record(io, page, RecordRequest::Discard)
            }
            Event::Message(Ok(m)) => self.on_teleop(io, page, &m, at_ns),
        }
    }

    /// A stop or resume press: sent to the supervisor, answered once it shows it heard it
    /// (or says nobody did). A stop ends teleoperation with the press, whatever the
    /// supervisor makes of it.
    fn on_press(&mut self, io: &mut impl LabIo, page: u64, press: Press) -> bool {
        match press {
            Press::Stop => self.counts.stops += 1,
            Press::Resume => self.counts.resumes += 1,
        }
        self.command_seq += 1;
        let sent_ns = io.now_ns();
        let command = SupervisorCommand {
            seq: self.command_seq,
            timestamp_ns: sent_ns,
            kind: match press {
                Press::Stop => COMMAND_STOP,
                Press::Resume => COMMAND_RESUME,
            },
            ..SupervisorCommand::default()
        };
        if press == Press::Stop {
            if let Some(d) = self.driven.as_mut() {
                d.teleop.let_go(sent_ns);
            }
            tracing::warn!(page, "stop pressed");
        }
        match io.publish_command(&command) {
            Ok(()) => self.presses.push(Pending::new(page, press, sent_ns)),
            Err(e) => self.say(io, page, ToPage::Reply(Reply::unsent(press, &e))),
        }
        true
    }

    /// A record button: the recorder's answer.
    fn on_record(&mut self, io: &mut impl LabIo, page: u64, request: RecordRequest) -> bool {
        let done = io.record(request);
        self.say(io, page, ToPage::Reply(Reply::record(done)));
        false
    }

    /// A teleoperation message. Alive messages (ten a second) are answered only when
    /// refused, and are no action.
    fn on_teleop(&mut self, io: &mut impl LabIo, page: u64, m: &PageMessage, at_ns: u64) -> bool {
        let alive = matches!(m, PageMessage::Alive {});
        // A stop awaiting its answer may be one the supervisor never heard: nothing moves the
        // arm until it is answered (done, or said unheard).
        let stopping = self.presses.iter().any(|p| p.press == Press::Stop);
        let outcome = match (self.driven.as_mut(), m.command()) {
            (Some(_), Some(_)) if stopping && !alive => Err(Refusal::Stopping),
            (Some(d), Some(c)) => d.teleop.command(page, &c, self.state.as_ref(), at_ns),
            _ => Err(Refusal::NotReady),
        };
        if !(alive && outcome.is_ok()) {
            self.say(io, page, ToPage::Reply(Reply::teleop(outcome)));
        }
        !alive
    }

    /// Teleoperation's tick: its goal frame published, and why it ended told every page.
    fn teleop_tick(&mut self, io: &mut impl LabIo, now_ns: u64) {
        let Some(d) = self.driven.as_mut() else {
            return;
        };
        d.teleop.set_lift_m(self.lift_m);
        let (frame, ended) = d.teleop.tick(self.state.as_ref(), now_ns);
        if let Some(f) = frame {
            match io.publish_goal(&f) {
                Ok(()) => self.counts.goal_frames += 1,
                Err(e) => {
                    self.counts.publish_errors += 1;
                    tracing::warn!("goal frame not published: {e}");
                }
            }
        }
        if let Some(why) = ended {
            tracing::info!("teleoperation ended: {}", why.name());
            self.broadcast(io, &ToPage::Ended { why });
        }
    }

    /// The pages' view: the arms posed from the newest state, and what goes with it.
    fn send_view(&self, io: &mut impl LabIo, now_ns: u64) {
        let (Some(d), Some(s)) = (self.driven.as_ref(), self.state.as_ref()) else {
            return;
        };
        let events: Vec<EventView> = self.recent.iter().cloned().collect();
        let extras = FrameExtras {
            teleop: TeleopView {
                owner: d.teleop.owner(),
                active: d.teleop.active(),
                counters: d.teleop.counters(),
            },
            events: &events,
            pages: io.pages_open(),
            recording: io.recording_status(),
            cameras: io.camera_status(now_ns),
            lift: self.lift.as_ref().map(LiftView::from),
            base: self.base.as_ref().map(BaseView::from),
        };
        let frame = d.scene.frame(s, self.lift_m, &extras);
        io.broadcast(&Outgoing::Text(frame.to_string().into()));
    }

    fn say(&mut self, io: &mut impl LabIo, page: u64, message: ToPage) {
        let text = message.text();
        self.send_text(io, page, text);
    }

    fn send_text(
        &mut self,
        io: &mut impl LabIo,
        page: u64,
        text: Result<Arc<str>, serde_json::Error>,
    ) {
        match text {
            Ok(text) => io.send(page, text),
            Err(e) => self.unsendable(&e),
        }
    }

    fn broadcast(&mut self, io: &mut impl LabIo, message: &ToPage) {
        match message.text() {
            Ok(text) => io.broadcast(&Outgoing::Text(text)),
            Err(e) => self.unsendable(&e),
        }
    }

    fn unsendable(&mut self, e: &serde_json::Error) {
        self.counts.publish_errors += 1;
        tracing::warn!("a message to the pages could not be written: {e}");
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::teleop::tests::a3_left_layout;
    use body::RobotDescription;
    use serde_json::Value;
    use telemetry::clock::MS;
    use telemetry::frames::EventKind;

    /// Queues and a clock: the plane, the pages and the recorder as the loop sees them.
    #[derive(Default)]
    struct Queues {
        now: u64,
        layout: Option<JointLayout>,
        states: VecDeque<JointState>,
        lift: Option<LiftState>,
        events: VecDeque<SupervisorEvent>,
        allowance: Option<LiftAllowance>,
        goals: Vec<GoalFrame>,
        commands: Vec<SupervisorCommand>,
        /// Publishing commands fails with this.
        command_error: Option<String>,
        inbound: VecDeque<Inbound>,
        /// Sent to one page (`Some`) or to all.
        sent: Vec<(Option<u64>, Value)>,
    }

    impl LabIo for Queues {
        fn now_ns(&self) -> u64 {
            self.now
        }
        fn layout(&mut self) -> Option<JointLayout> {
            self.layout
        }
        fn next_state(&mut self) -> Option<JointState> {
            self.states.pop_front()
        }
        fn lift(&mut self) -> Option<LiftState> {
            self.lift
        }
        fn base(&mut self) -> Option<BaseState> {
            None
        }
        fn next_event(&mut self) -> Option<SupervisorEvent> {
            self.events.pop_front()
        }
        fn allowance(&mut self) -> Option<LiftAllowance> {
            self.allowance
        }
        fn publish_goal(&mut self, frame: &GoalFrame) -> Result<(), String> {
            self.goals.push(*frame);
            Ok(())
        }
        fn publish_command(&mut self, command: &SupervisorCommand) -> Result<(), String> {
            match &self.command_error {
                Some(e) => Err(e.clone()),
                None => {
                    self.commands.push(*command);
                    Ok(())
                }
            }
        }
        /// The page's next event, or none after waiting `wait` on the clock.
        fn next_page_event(&mut self, wait: Duration) -> Result<Option<Inbound>, ServerStopped> {
            let inbound = self.inbound.pop_front();
            if inbound.is_none() {
                self.now += ns(wait).max(1);
            }
            Ok(inbound)
        }
        fn send(&mut self, page: u64, text: Arc<str>) {
            self.sent
                .push((Some(page), serde_json::from_str(&text).unwrap()));
        }
        fn broadcast(&mut self, message: &Outgoing) {
            if let Outgoing::Text(text) = message {
                self.sent.push((None, serde_json::from_str(text).unwrap()));
            }
        }
        fn pages_open(&self) -> usize {
            1
        }
        fn take_camera_images(&mut self) {}
        fn send_camera_images(&mut self) {}
        fn camera_status(&self, _now_ns: u64) -> Vec<CameraStatus> {
            Vec::new()
        }
        fn record(&mut self, _request: RecordRequest) -> Result<(), String> {
            Err("this lab records nothing".into())
        }
        fn recorded(&mut self) -> Option<Outcome> {
            None
        }
        fn recording_status(&self) -> Option<RecordingStatus> {
            None
        }
    }

    impl Queues {
        /// The left arm read at rest, stamped now.
        fn read(&mut self) {
            let mut s = JointState {
                joint_count: 8,
                timestamp_ns: self.now,
                ..JointState::default()
            };
            for j in &mut s.joints[..8] {
                j.valid = 1;
                j.torque_enabled = 1;
                j.position_rad = 0.1;
            }
            self.states.push_back(s);
        }

        fn page_does(&mut self, page: u64, event: Event) {
            self.inbound.push_back(Inbound {
                page,
                event,
                at_ns: self.now,
            });
        }

        /// Messages of `type` sent so far, taken out.
        fn taken(&mut self, kind: &str) -> Vec<(Option<u64>, Value)> {
            let (of, rest) = std::mem::take(&mut self.sent)
                .into_iter()
                .partition(|(_, m)| m["type"] == kind);
            self.sent = rest;
            of
        }
    }

    fn lab(now: u64) -> Lab {
        let body = Body::from_description(&RobotDescription::nori_a3()).unwrap();
        let settings = LabSettings {
            body,
            teleop: TeleopSettings::default(),
            cameras: vec!["left_wrist".into()],
            frame_every: Duration::from_millis(33),
            camera_every: Duration::from_millis(200),
        };
        Lab::new(settings, now)
    }

    /// A lab with the left arm's layout, read, and page 1 open; `turns` turns run.
    fn ready() -> (Lab, Queues) {
        let mut io = Queues {
            now: 1_000 * MS,
            layout: Some(a3_left_layout()),
            ..Queues::default()
        };
        let mut lab = lab(io.now);
        io.read();
        io.page_does(1, Event::Opened);
        lab.turn(&mut io).unwrap();
        (lab, io)
    }

    fn run(lab: &mut Lab, io: &mut Queues, ms: u64) {
        let until = io.now + ms * MS;
        while io.now < until {
            io.read();
            lab.turn(io).unwrap();
        }
    }

    fn elbow_to(rad: f64) -> Event {
        Event::Message(Ok(PageMessage::Joints {
            goals: [("left_elbow".to_string(), rad)].into(),
        }))
    }

    #[test]
    fn a_page_opened_gets_its_hello_then_the_model() {
        let (_, mut io) = ready();
        let to_page: Vec<&Value> = io
            .sent
            .iter()
            .filter(|(p, _)| *p == Some(1))
            .map(|(_, m)| m)
            .collect();
        assert_eq!(to_page[0]["type"], "hello", "{to_page:?}");
        assert_eq!(to_page[0]["page"], 1);
        assert_eq!(to_page[0]["cameras"][0], "left_wrist");
        assert_eq!(to_page[1]["type"], "model");
        // The model also went to every page when the layout first came.
        assert_eq!(io.taken("model").len(), 2);
    }

    #[test]
    fn a_joint_command_drives_goal_frames_and_the_view_shows_who_controls() {
        let (mut lab, mut io) = ready();
        io.page_does(1, elbow_to(-0.5));
        run(&mut lab, &mut io, 300);
        let replies = io.taken("reply");
        assert_eq!(replies.len(), 1, "{replies:?}");
        assert_eq!(replies[0].1["ok"], true);
        assert!(
            io.goals.len() >= 25,
            "{} goal frames in 0.3 s",
            io.goals.len()
        );
        assert_eq!(lab.counts.goal_frames, io.goals.len() as u64);
        let frames = io.taken("state");
        // 33 ms apart: 9 or 10 in 0.3 s.
        assert!((8..=11).contains(&frames.len()), "{}", frames.len());
        let last = &frames.last().unwrap().1;
        assert_eq!(last["extra"]["teleop"]["owner"], 1);
        assert_eq!(last["extra"]["teleop"]["taken"], 1);
        assert_eq!(last["extra"]["lift"], Value::Null);
    }

    #[test]
    fn before_the_layout_a_command_is_refused_as_not_ready() {
        let mut io = Queues {
            now: 5 * MS,
            ..Queues::default()
        };
        let mut lab = lab(io.now);
        io.page_does(2, elbow_to(-0.5));
        lab.turn(&mut io).unwrap();
        let replies = io.taken("reply");
        assert_eq!(replies[0].0, Some(2));
        assert_eq!(replies[0].1["refused"], "not_ready");
        assert!(io.goals.is_empty());
    }

    #[test]
    fn a_stop_lets_go_at_once_and_is_answered_only_when_the_supervisor_shows_it() {
        let (mut lab, mut io) = ready();
        io.page_does(1, elbow_to(-0.5));
        run(&mut lab, &mut io, 100);
        io.page_does(1, Event::Message(Ok(PageMessage::Stop {})));
        run(&mut lab, &mut io, 50);
        assert_eq!(io.commands.len(), 1);
        let stop = io.commands[0];
        assert_eq!(stop.kind, COMMAND_STOP);
        let ended = io.taken("ended");
        assert_eq!(ended.len(), 1, "{ended:?}");
        assert_eq!(ended[0].1["why"], "released");
        // Nothing said of the stop until the supervisor shows it heard it.
        assert!(io.taken("reply").iter().all(|(_, m)| m["to"] != "stop"));
        // An event from before the press answers nothing.
        let mut heard = SupervisorEvent {
            timestamp_ns: stop.timestamp_ns - 1,
            kind: EventKind::OperatorStop as u8,
            ..SupervisorEvent::default()
        };
        io.events.push_back(heard);
        run(&mut lab, &mut io, 20);
        assert!(io.taken("reply").is_empty());
        heard.timestamp_ns = stop.timestamp_ns + MS;
        io.events.push_back(heard);
        run(&mut lab, &mut io, 50);
        let replies = io.taken("reply");
        assert_eq!(replies.len(), 1, "{replies:?}");
        assert_eq!(
            (replies[0].1["to"].clone(), replies[0].1["ok"].clone()),
            ("stop".into(), true.into())
        );
        // The page's view lists the events.
        let frame = io.taken("state").pop().unwrap().1;
        assert_eq!(
            frame["extra"]["events"][1]["kind"], "OperatorStop",
            "{frame}"
        );
    }

    /// Found by review: a stop only released control, so a command another page sent while
    /// its answer was awaited, or before the press (queued behind it, or late), took control
    /// again until the driver's safe state showed on the plane.
    #[test]
    fn no_command_sent_before_a_stop_or_while_it_is_awaited_drives_the_arm() {
        let (mut lab, mut io) = ready();
        io.page_does(1, elbow_to(-0.5));
        run(&mut lab, &mut io, 100);
        io.page_does(1, Event::Message(Ok(PageMessage::Stop {})));
        run(&mut lab, &mut io, 20);
        // Page 2's command while the stop waits for the supervisor.
        io.page_does(2, elbow_to(-1.2));
        run(&mut lab, &mut io, 50);
        // The supervisor answers; the driver's safe state has not reached the plane yet, and
        // page 2's command sent 5 ms before the press arrives now.
        let stop_ns = io.commands[0].timestamp_ns;
        io.events.push_back(SupervisorEvent {
            timestamp_ns: stop_ns + MS,
            kind: EventKind::OperatorStop as u8,
            ..SupervisorEvent::default()
        });
        run(&mut lab, &mut io, 20);
        io.inbound.push_back(Inbound {
            page: 2,
            event: elbow_to(-1.2),
            at_ns: stop_ns - 5 * MS,
        });
        run(&mut lab, &mut io, 50);
        let refused: Vec<Value> = io
            .taken("reply")
            .into_iter()
            .filter(|(p, _)| *p == Some(2))
            .map(|(_, m)| m["refused"].clone())
            .collect();
        assert_eq!(refused, ["stopping", "before_interruption"], "{refused:?}");
        let elbow = 3;
        let goals_after: Vec<f32> = io
            .goals
            .iter()
            .filter(|g| g.timestamp_ns > stop_ns && g.mask & (1 << elbow) != 0)
            .map(|g| g.position_rad[elbow])
            .collect();
        // At most the hold where the arm stands: nothing toward page 2's target.
        assert!(goals_after.iter().all(|g| *g > -0.3), "{goals_after:?}");
    }

    #[test]
    fn a_stop_nobody_hears_is_said_so_after_its_wait_and_one_unsent_at_once() {
        let (mut lab, mut io) = ready();
        io.page_does(1, Event::Message(Ok(PageMessage::Stop {})));
        run(&mut lab, &mut io, 1_900);
        assert!(io.taken("reply").is_empty());
        run(&mut lab, &mut io, 200);
        let replies = io.taken("reply");
        assert_eq!(replies.len(), 1);
        assert_eq!(replies[0].1["ok"], false);
        assert!(replies[0].1["error"]
            .as_str()
            .unwrap()
            .contains("NO SUPERVISOR"));

        io.command_error = Some("the plane is gone".into());
        io.page_does(1, Event::Message(Ok(PageMessage::Resume {})));
        lab.turn(&mut io).unwrap();
        let replies = io.taken("reply");
        assert_eq!(replies[0].1["to"], "resume");
        assert_eq!(replies[0].1["error"], "the plane is gone");
        assert_eq!((lab.counts.stops, lab.counts.resumes), (1, 1));
    }

    #[test]
    fn a_closed_page_ends_its_control_and_every_page_is_told_why() {
        let (mut lab, mut io) = ready();
        io.page_does(1, elbow_to(-0.5));
        run(&mut lab, &mut io, 100);
        io.page_does(1, Event::Closed);
        run(&mut lab, &mut io, 50);
        let ended = io.taken("ended");
        assert_eq!(ended.len(), 1, "{ended:?}");
        assert_eq!(
            ended[0],
            (
                None,
                serde_json::json!({"type": "ended", "why": "page_closed"})
            )
        );
        let frame = io.taken("state").pop().unwrap().1;
        assert_eq!(frame["extra"]["teleop"]["owner"], Value::Null);
        assert_eq!(frame["extra"]["teleop"]["closed_releases"], 1);
    }

    #[test]
    fn a_malformed_message_is_refused_counted_and_moves_nothing() {
        let (mut lab, mut io) = ready();
        let bad = crate::page::parse("{\"type\":\"joints\",\"goals\":7}").unwrap_err();
        io.page_does(1, Event::Message(Err(bad)));
        io.page_does(
            1,
            Event::Message(Ok(PageMessage::RecordStart { task: "t".into() })),
        );
        run(&mut lab, &mut io, 100);
        let replies = io.taken("reply");
        assert_eq!(replies.len(), 2, "{replies:?}");
        assert_eq!(replies[0].1["ok"], false);
        assert_eq!(replies[1].1["to"], "record");
        assert_eq!(lab.counts.malformed, 1);
        assert!(io.goals.is_empty());
    }

    #[test]
    fn the_view_draws_the_arm_at_the_homed_lift_only() {
        let (mut lab, mut io) = ready();
        io.lift = Some(LiftState {
            state: telemetry::motion::LIFT_HOMING,
            height_m: 0.6,
            ..LiftState::default()
        });
        run(&mut lab, &mut io, 50);
        let start = lab.settings.body.lift_start_m();
        let frame = io.taken("state").pop().unwrap().1;
        assert_eq!(frame["lift_m"], start);
        assert_eq!(frame["extra"]["lift"]["state"], "homing");
        io.lift = Some(LiftState {
            state: LIFT_READY,
            height_m: 0.5,
            ..LiftState::default()
        });
        run(&mut lab, &mut io, 50);
        let frame = io.taken("state").pop().unwrap().1;
        assert_eq!(frame["lift_m"], 0.5);
    }
}
