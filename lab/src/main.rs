//! `nori-lab` (`nori lab`): Nori Lab's server. Reads the driver's layout and state, the lift's
//! state and the supervisor's events from the state plane, serves the page on loopback, turns
//! the page's teleoperation into goal frames on the driver's goal path (`lab::teleop`) and its
//! stop button into the supervisor's stop. Prints the page's address, with its access token, on
//! stderr, and what it counted on stdout (JSON) at exit.

use anyhow::{bail, Context, Result};
use body::kinematics::Body;
use body::RobotDescription;
use clap::Parser;
use lab::page::{Access, PageMessage};
use lab::recording::{outcome_json, Recording, RecordingSettings};
use lab::scene::Scene;
use lab::server::{self, Event, Files, Inbound, Outgoing, Pages};
use lab::stop_button::{Answer, Pending, Press};
use lab::teleop::{Ended, Teleop, TeleopSettings};
use serde_json::json;
use std::collections::VecDeque;
use std::net::{SocketAddr, TcpListener};
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::mpsc::RecvTimeoutError;
use std::sync::Arc;
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::frames::{EventKind, SupervisorCommand, COMMAND_RESUME, COMMAND_STOP};
use telemetry::motion::{lift_state_name, BaseState, LiftState, LIFT_READY};
use telemetry::plane::{self, newest, next, publish, CameraStream, FrameSub, Plane};
use telemetry::process::finish;
use telemetry::JointState;

#[derive(Parser)]
#[command(
    version,
    about = "Nori Lab: the robot in the browser (3D view, teleoperation, stop), served on loopback"
)]
struct Args {
    /// State-plane domain.
    #[arg(long, default_value = plane::DEFAULT_DOMAIN)]
    domain: String,
    /// Where to serve the page: a loopback address (the link is plain ws://; from another
    /// machine, through an SSH tunnel).
    #[arg(long, default_value = "127.0.0.1:8765")]
    http: SocketAddr,
    /// A file holding the access token (one line, at least 16 characters); one is generated at
    /// each start when absent.
    #[arg(long, value_name = "FILE")]
    token_file: Option<PathBuf>,
    /// The robot description (the embedded Nori A3 when absent).
    #[arg(long, value_name = "FILE")]
    robot: Option<PathBuf>,
    /// A controlling page silent this long is released and the arm held, ms.
    #[arg(long, default_value_t = 300)]
    deadman_ms: u64,
    /// Fastest a teleoperated joint moves toward its target, rad/s.
    #[arg(long, default_value_t = 1.5)]
    max_speed: f64,
    /// State frames sent to each page per second.
    #[arg(long, default_value_t = 30.0)]
    frame_hz: f64,
    /// Record the page's episodes into this LeRobot dataset (through `nori record`); without
    /// it the page cannot record.
    #[arg(long, value_name = "DIR")]
    dataset: Option<PathBuf>,
    /// A camera to show on the page and record with the episodes (repeat for several; its
    /// `nori-camera` must publish MJPEG, as `nori record --camera` needs).
    #[arg(long = "camera", value_name = "NAME")]
    cameras: Vec<String>,
    /// Camera images sent to each page per second, per camera (the device's JPEGs as they
    /// are: nothing is decoded or encoded on the robot).
    #[arg(long, default_value_t = 5.0)]
    camera_hz: f64,
    /// Stop after this many seconds.
    #[arg(long)]
    run_for: Option<f64>,
}

/// What the loop counted, printed at exit.
#[derive(Debug, Default, serde::Serialize)]
struct Counts {
    goal_frames: u64,
    malformed: u64,
    stops: u64,
    resumes: u64,
    publish_errors: u64,
}

/// The teleoperation loop's period.
const TICK: Duration = Duration::from_millis(10);
/// Supervisor events kept for the page.
const RECENT_EVENTS: usize = 12;

fn main() -> std::process::ExitCode {
    finish(serve(&Args::parse()), |_| None)
}

/// The access token: read from the file, or made from the kernel's random bytes.
fn token(file: Option<&PathBuf>) -> Result<String> {
    if let Some(path) = file {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading the token file {}", path.display()))?;
        let token = text.trim().to_string();
        if token.len() < 16
            || !token
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
        {
            bail!(
                "{}: a token is at least 16 letters, digits, '-' or '_'",
                path.display()
            );
        }
        return Ok(token);
    }
    let mut bytes = [0u8; 16];
    std::io::Read::read_exact(&mut std::fs::File::open("/dev/urandom")?, &mut bytes)
        .context("reading /dev/urandom for a token")?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// One camera shown on the pages: its newest JPEG, passed on as the camera sent it.
struct CameraView {
    name: String,
    jpegs: FrameSub,
    /// The next binary message: the header and the newest JPEG.
    newest: Vec<u8>,
    header_len: usize,
    /// Capture time (ns) and size of the newest, and whether it went out already.
    captured_ns: Option<u64>,
    size: (u32, u32),
    sent: bool,
    images: u64,
}

impl CameraView {
    fn new(name: &str, jpegs: FrameSub) -> CameraView {
        let mut newest = vec![1, name.len() as u8];
        newest.extend_from_slice(name.as_bytes());
        CameraView {
            name: name.to_string(),
            jpegs,
            header_len: newest.len(),
            newest,
            captured_ns: None,
            size: (0, 0),
            sent: true,
            images: 0,
        }
    }

    /// Takes in what the camera published; keeps the newest.
    fn take(&mut self) {
        while let Ok(Some(sample)) = self.jpegs.receive() {
            let h = sample.user_header();
            self.newest.truncate(self.header_len);
            self.newest.extend_from_slice(sample.payload());
            self.captured_ns = Some(h.capture_ns);
            self.size = (h.width, h.height);
            self.sent = false;
        }
    }

    /// The newest image, if not sent yet.
    fn message(&mut self) -> Option<Outgoing> {
        if self.sent || self.newest.len() == self.header_len {
            return None;
        }
        self.sent = true;
        self.images += 1;
        Some(Outgoing::Binary(self.newest.as_slice().into()))
    }

    fn status(&self, now_ns: u64) -> serde_json::Value {
        json!({"name": self.name, "width": self.size.0, "height": self.size.1, "images": self.images,
            "age_ms": self.captured_ns.map(|t| now_ns.saturating_sub(t) as f64 * 1e-6)})
    }
}

fn event_name(kind: Option<EventKind>) -> String {
    kind.map_or_else(|| "unknown".to_string(), |k| format!("{k:?}"))
}

fn ended_name(e: Ended) -> &'static str {
    match e {
        Ended::DeadMan => "dead_man",
        Ended::PageClosed => "page_closed",
        Ended::Released => "released",
        Ended::SafeState => "safe_state",
        Ended::DriverRestarted => "driver_restarted",
        Ended::DriverSilent => "driver_silent",
    }
}

fn serve(args: &Args) -> Result<()> {
    telemetry::process::init_logging();
    let shutdown = telemetry::process::stop_flag()?;
    let description = match &args.robot {
        Some(path) => RobotDescription::load(path)?,
        None => RobotDescription::nori_a3(),
    };
    let body = Body::from_description(&description)?;
    // Plain ws:// would carry the token and every command readable (and replayable) on the
    // network: the lab has no TLS of its own, so it is reached through a tunnel or a proxy.
    if !args.http.ip().is_loopback() {
        bail!(
            "--http {}: Nori Lab serves loopback only (its link is plain ws://: the token and every command would cross the network readable); reach it from another machine through an SSH tunnel (ssh -L 8765:127.0.0.1:8765 <robot>)",
            args.http
        );
    }
    if !(args.max_speed.is_finite() && args.max_speed > 0.0 && args.max_speed <= 6.0) {
        bail!("--max-speed {}: between 0 and 6 rad/s", args.max_speed);
    }
    if !(50..=2000).contains(&args.deadman_ms) {
        bail!("--deadman-ms {}: between 50 and 2000 ms", args.deadman_ms);
    }
    if args.run_for.is_some_and(|s| !(s.is_finite() && s >= 0.0)) {
        bail!("--run-for: a number of seconds, 0 or more");
    }
    if !(args.camera_hz.is_finite() && (0.5..=30.0).contains(&args.camera_hz)) {
        bail!("--camera-hz {}: between 0.5 and 30", args.camera_hz);
    }
    for (i, name) in args.cameras.iter().enumerate() {
        if !telemetry::sensors::valid_camera_name(name) || args.cameras[..i].contains(name) {
            bail!("--camera {name:?}: a camera name (1 to 32 of a-z, 0-9 and _), once");
        }
    }
    if !(args.frame_hz.is_finite() && (1.0..=120.0).contains(&args.frame_hz)) {
        bail!("--frame-hz {}: between 1 and 120", args.frame_hz);
    }
    let settings = TeleopSettings {
        deadman_ms: args.deadman_ms,
        max_speed_rad_s: args.max_speed,
        ..TeleopSettings::default()
    };
    let token = token(args.token_file.as_ref())?;

    let node = Plane::open(&args.domain, &format!("nori-lab-{}", std::process::id()))?;
    let layouts = node.subscriber(&plane::LAYOUT)?;
    let states = node.subscriber(&plane::JOINT_STATE)?;
    let lifts = node.subscriber(&plane::LIFT_STATE)?;
    let bases = node.subscriber(&plane::BASE_STATE)?;
    let events = node.subscriber(&plane::EVENTS)?;
    let allowances = node.subscriber(&plane::LIFT_ALLOWANCE)?;
    let goals = node.publisher(&plane::GOALS)?;
    let commands = node.publisher(&plane::COMMANDS)?;
    let mut cameras = args
        .cameras
        .iter()
        .map(|name| {
            Ok(CameraView::new(
                name,
                node.camera_subscriber(name, CameraStream::Mjpeg)?,
            ))
        })
        .collect::<Result<Vec<_>>>()?;
    let camera_every = Duration::from_secs_f64(1.0 / args.camera_hz);
    let mut next_images = Instant::now();

    let listener =
        TcpListener::bind(args.http).with_context(|| format!("listening on {}", args.http))?;
    let address = listener.local_addr()?;
    let pages = Arc::new(Pages::default());
    let (inbound_tx, inbound) = std::sync::mpsc::channel::<Inbound>();
    let files = Files {
        index_html: include_str!("page/index.html"),
        lab_js: include_str!("page/lab.js"),
    };
    let http = server::serve(
        listener,
        files,
        Access::new(token.clone()),
        pages.clone(),
        inbound_tx,
        shutdown.clone(),
    )?;
    eprintln!("Nori Lab: http://{address}/#token={token}");

    let mut recording = match &args.dataset {
        Some(dataset) => Some(Recording::new(RecordingSettings {
            nori: telemetry::process::sibling("nori")?,
            dataset: dataset.clone(),
            domain: args.domain.clone(),
            cameras: args.cameras.clone(),
            log: std::env::temp_dir().join(format!("nori-lab-record-{}.log", std::process::id())),
        })),
        None => None,
    };

    let started = Instant::now();
    let run_for = args.run_for.map(Duration::from_secs_f64);
    let frame_every = Duration::from_secs_f64(1.0 / args.frame_hz);
    let mut next_frame = Instant::now();
    let mut next_tick = Instant::now();
    let mut lab: Option<(Teleop, Scene, Arc<str>)> = None;
    let mut state: Option<JointState> = None;
    let mut lift_m = body.lift_start_m();
    // The lift's and the base's newest states, for the page (none without them).
    let mut lift: Option<LiftState> = None;
    let mut base: Option<BaseState> = None;
    let mut recent: VecDeque<serde_json::Value> = VecDeque::new();
    let mut command_seq = 0u64;
    // Stop and resume presses waiting for the supervisor to show it heard them.
    let mut presses: Vec<Pending> = Vec::new();
    let mut counts = Counts::default();
    let say =
        |pages: &Pages, page: u64, v: serde_json::Value| pages.send(page, v.to_string().into());

    while !shutdown.load(Ordering::Relaxed) && run_for.is_none_or(|d| started.elapsed() < d) {
        // The plane.
        if let Some(l) = newest(&layouts).filter(|l| l.joint_count > 0) {
            if lab
                .as_ref()
                .is_none_or(|(teleop, ..)| *teleop.layout() != l)
            {
                let scene = Scene::new(body.clone(), l);
                let model: Arc<str> = scene.model().to_string().into();
                pages.broadcast(&model);
                lab = Some((Teleop::new(body.clone(), l, settings), scene, model));
                tracing::info!(joints = l.joint_count, "the driver's layout");
            }
        }
        while let Some(s) = next(&states) {
            if let Some((teleop, ..)) = lab.as_mut() {
                teleop.observe(&s);
            }
            state = Some(s);
        }
        // The lift's height once it is homed; without a lift, where the description has it.
        if let Some(l) = newest::<LiftState>(&lifts) {
            if l.state == LIFT_READY && l.height_m.is_finite() {
                lift_m = f64::from(l.height_m);
            }
            lift = Some(l);
        }
        base = newest::<BaseState>(&bases).or(base);
        for c in &mut cameras {
            c.take();
        }
        let allowance = newest(&allowances);
        let mut answers = Vec::new();
        while let Some(e) = next(&events) {
            if recent.len() == RECENT_EVENTS {
                recent.pop_front();
            }
            recent.push_back(json!({"kind": event_name(e.kind()), "joint": e.joint, "bus": e.bus, "level": e.level, "value": e.value}));
            answers.extend(presses.iter().filter_map(|p| Some((*p, p.on_event(&e)?))));
        }
        let now_ns = monotonic_ns();
        for p in &presses {
            let answer = allowance
                .and_then(|a| p.on_allowance(&a))
                .or(p.expired(now_ns));
            answers.extend(answer.map(|a| (*p, a)));
        }
        for (p, answer) in answers {
            if presses.contains(&p) {
                presses.retain(|q| *q != p);
                say(&pages, p.page, press_reply(p.press, answer));
            }
        }

        // The pages, until the next tick.
        let wait = next_tick.saturating_duration_since(Instant::now());
        let mut acted = false;
        match inbound.recv_timeout(wait) {
            Ok(Inbound { page, event, at_ns }) => match event {
                Event::Opened => {
                    say(
                        &pages,
                        page,
                        json!({"type": "hello", "page": page, "deadman_ms": args.deadman_ms,
                            "cameras": args.cameras}),
                    );
                    if let Some((.., model)) = &lab {
                        pages.send(page, model.clone());
                    }
                }
                Event::Closed => {
                    if let Some((teleop, ..)) = lab.as_mut() {
                        teleop.page_closed(page);
                    }
                    acted = true;
                }
                Event::Message(Err(e)) => {
                    counts.malformed += 1;
                    say(
                        &pages,
                        page,
                        json!({"type": "reply", "ok": false, "error": e.to_string()}),
                    );
                }
                Event::Message(Ok(m @ (PageMessage::Stop {} | PageMessage::Resume {}))) => {
                    let press = if matches!(m, PageMessage::Stop {}) {
                        counts.stops += 1;
                        Press::Stop
                    } else {
                        counts.resumes += 1;
                        Press::Resume
                    };
                    command_seq += 1;
                    let sent_ns = monotonic_ns();
                    let cmd = SupervisorCommand {
                        seq: command_seq,
                        timestamp_ns: sent_ns,
                        kind: match press {
                            Press::Stop => COMMAND_STOP,
                            Press::Resume => COMMAND_RESUME,
                        },
                        ..SupervisorCommand::default()
                    };
                    if press == Press::Stop {
                        // Teleoperation ends with the press, whatever the supervisor makes of it.
                        if let Some((teleop, ..)) = lab.as_mut() {
                            teleop.let_go();
                        }
                        tracing::warn!(page, "stop pressed");
                    }
                    // Answered once the supervisor shows it heard it (or says nobody did).
                    match publish(&commands, &cmd) {
                        Ok(()) => presses.push(Pending::new(page, press, sent_ns)),
                        Err(e) => say(
                            &pages,
                            page,
                            json!({"type": "reply", "to": press_name(press), "ok": false, "error": e.to_string()}),
                        ),
                    }
                    acted = true;
                }
                Event::Message(Ok(
                    m @ (PageMessage::RecordStart { .. }
                    | PageMessage::RecordStop {}
                    | PageMessage::RecordDiscard {}),
                )) => {
                    let done = match (recording.as_mut(), &m) {
                        (None, _) => {
                            Err("this lab records nothing: start it with --dataset DIR".to_string())
                        }
                        (Some(r), PageMessage::RecordStart { task }) => r.start(task),
                        (Some(r), PageMessage::RecordStop {}) => r.end(false),
                        (Some(r), _) => r.end(true),
                    };
                    say(
                        &pages,
                        page,
                        json!({"type": "reply", "to": "record", "ok": done.is_ok(), "error": done.err()}),
                    );
                }
                Event::Message(Ok(m)) => {
                    let reply = match (lab.as_mut(), m.command()) {
                        (Some((teleop, ..)), Some(c)) => {
                            match teleop.command(page, &c, state.as_ref(), at_ns) {
                                Ok(solved) => {
                                    json!({"type": "reply", "ok": true, "solved": solved.map(|s| json!({
                                    "position_error_m": s.position_error_m, "angle_error_rad": s.angle_error_rad, "starts": s.starts}))})
                                }
                                Err(r) => {
                                    json!({"type": "reply", "ok": false, "refused": r.kind(), "error": r.to_string()})
                                }
                            }
                        }
                        _ => {
                            json!({"type": "reply", "ok": false, "refused": "not_ready", "error": "the driver's layout is not known yet"})
                        }
                    };
                    // Alive messages are answered only when refused (they come ten times a second).
                    if !(matches!(m, PageMessage::Alive {}) && reply["ok"] == true) {
                        say(&pages, page, reply);
                    }
                    acted = !matches!(m, PageMessage::Alive {});
                }
            },
            Err(RecvTimeoutError::Timeout) => {}
            // The server's thread ends only once asked to stop.
            Err(RecvTimeoutError::Disconnected) if shutdown.load(Ordering::Relaxed) => break,
            Err(RecvTimeoutError::Disconnected) => bail!("the lab's server stopped"),
        }

        // Teleoperation: at every tick, and at once after a page acted.
        let now = Instant::now();
        if now >= next_tick || acted {
            if now >= next_tick {
                next_tick = now + TICK;
            }
            if let Some((teleop, ..)) = lab.as_mut() {
                teleop.set_lift_m(lift_m);
                let (frame, ended) = teleop.tick(state.as_ref(), monotonic_ns());
                if let Some(f) = frame {
                    match publish(&goals, &f) {
                        Ok(()) => counts.goal_frames += 1,
                        Err(e) => {
                            counts.publish_errors += 1;
                            tracing::warn!("goal frame not published: {e}");
                        }
                    }
                }
                if let Some(why) = ended {
                    tracing::info!("teleoperation ended: {}", ended_name(why));
                    pages.broadcast(
                        &json!({"type": "ended", "why": ended_name(why)})
                            .to_string()
                            .into(),
                    );
                }
            }
        }

        if let Some(outcome) = recording.as_mut().and_then(Recording::poll) {
            tracing::info!("recording: {outcome:?}");
            pages.broadcast(
                &json!({"type": "recorded", "outcome": outcome_json(&outcome)})
                    .to_string()
                    .into(),
            );
        }

        // The cameras' newest images, each once.
        if now >= next_images {
            next_images = now + camera_every;
            for c in &mut cameras {
                if let Some(message) = c.message() {
                    pages.broadcast_message(&message);
                }
            }
        }

        // The pages' view.
        if now >= next_frame {
            next_frame += frame_every;
            if next_frame < now {
                next_frame = now + frame_every;
            }
            if let (Some((teleop, scene, _)), Some(s)) = (lab.as_ref(), state.as_ref()) {
                let c = teleop.counters();
                let extra = json!({
                    "teleop": {"owner": teleop.owner(), "active": teleop.active(), "taken": c.taken,
                        "refused": c.refused, "deadman_releases": c.deadman_releases,
                        "closed_releases": c.closed_releases, "safe_state_releases": c.safe_state_releases},
                    "events": recent,
                    "pages": pages.open(),
                    "recording": recording.as_ref().map(Recording::status),
                    "cameras": cameras.iter().map(|c| c.status(monotonic_ns())).collect::<Vec<_>>(),
                    "lift": lift.map(|l| json!({"state": lift_state_name(l.state),
                        "height_m": l.height_m.is_finite().then_some(l.height_m),
                        "goal_m": l.goal_m.is_finite().then_some(l.goal_m), "current_a": l.current_a})),
                    "base": base.map(|b| json!({"x_m": b.x_m, "y_m": b.y_m, "heading_rad": b.theta_rad,
                        "linear_m_s": b.linear_m_s, "angular_rad_s": b.angular_rad_s,
                        "flags": b.flag_names().collect::<Vec<_>>()})),
                });
                pages.broadcast(&scene.frame(s, lift_m, extra).to_string().into());
            }
        }
    }
    shutdown.store(true, Ordering::Relaxed);
    let _ = http.join();
    // An episode being recorded is kept, as `nori record` keeps it on SIGINT.
    if let Some(r) = recording.as_mut().filter(|r| r.busy()) {
        let _ = r.end(false);
        let until = Instant::now() + Duration::from_secs(20);
        while r.busy() && Instant::now() < until {
            if let Some(outcome) = r.poll() {
                tracing::info!("recording at exit: {outcome:?}");
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
    let mut summary = serde_json::to_value(&counts)?;
    if let Some((teleop, ..)) = &lab {
        let c = teleop.counters();
        summary["teleop"] = json!({"taken": c.taken, "refused": c.refused, "frames": c.frames,
            "deadman_releases": c.deadman_releases, "closed_releases": c.closed_releases,
            "safe_state_releases": c.safe_state_releases});
    }
    summary["dropped_messages"] = json!(pages.dropped.load(Ordering::Relaxed));
    summary["denied_links"] = json!(pages.denied.load(Ordering::Relaxed));
    println!("{summary}");
    Ok(())
}

fn press_name(press: Press) -> &'static str {
    match press {
        Press::Stop => "stop",
        Press::Resume => "resume",
    }
}

/// The page's reply to a press, once answered.
fn press_reply(press: Press, answer: Answer) -> serde_json::Value {
    let (ok, text) = answer.reply(press);
    json!({"type": "reply", "to": press_name(press), "ok": ok, "text": text,
        "error": (!ok).then_some(text)})
}
