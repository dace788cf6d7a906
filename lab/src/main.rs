//! `nori-lab` (`nori lab`): Nori Lab's server. Reads the driver's layout and state, the lift's
//! state and the supervisor's events from the state plane, serves the page on loopback, turns
//! the page's teleoperation into goal frames on the driver's goal path (`lab::teleop`) and its
//! stop button into the supervisor's stop. Prints the page's address, with its access token, on
//! stderr, and what it counted on stdout (JSON) at exit.

use anyhow::{bail, Context, Result};
use body::kinematics::Body;
use body::RobotDescription;
use clap::Parser;
use lab::messages::CameraStatus;
use lab::page::Access;
use lab::process::{Lab, LabIo, LabSettings, RecordRequest, ServerStopped};
use lab::recording::{Outcome, Recording, RecordingSettings, RecordingStatus};
use lab::server::{self, Files, Inbound, Outgoing, Pages};
use lab::teleop::TeleopSettings;
use std::net::{SocketAddr, TcpListener};
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::sync::Arc;
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::frames::{GoalFrame, JointLayout, SupervisorCommand, SupervisorEvent};
use telemetry::motion::{BaseState, LiftAllowance, LiftState};
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

    fn status(&self, now_ns: u64) -> CameraStatus {
        CameraStatus {
            name: self.name.clone(),
            width: self.size.0,
            height: self.size.1,
            images: self.images,
            age_ms: self
                .captured_ns
                .map(|t| now_ns.saturating_sub(t) as f64 * 1e-6),
        }
    }
}

/// The lab's settings from its arguments, each checked.
fn settings(args: &Args) -> Result<LabSettings> {
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
    let description = match &args.robot {
        Some(path) => RobotDescription::load(path)?,
        None => RobotDescription::nori_a3(),
    };
    Ok(LabSettings {
        body: Body::from_description(&description)?,
        teleop: TeleopSettings {
            deadman_ms: args.deadman_ms,
            max_speed_rad_s: args.max_speed,
            ..TeleopSettings::default()
        },
        cameras: args.cameras.clone(),
        frame_every: Duration::from_secs_f64(1.0 / args.frame_hz),
        camera_every: Duration::from_secs_f64(1.0 / args.camera_hz),
    })
}

/// The lab's plane, pages, cameras and recorder.
struct Wired {
    layouts: plane::Sub<JointLayout>,
    states: plane::Sub<JointState>,
    lifts: plane::Sub<LiftState>,
    bases: plane::Sub<BaseState>,
    events: plane::Sub<SupervisorEvent>,
    allowances: plane::Sub<LiftAllowance>,
    goals: plane::Pub<GoalFrame>,
    commands: plane::Pub<SupervisorCommand>,
    cameras: Vec<CameraView>,
    pages: Arc<Pages>,
    inbound: Receiver<Inbound>,
    recording: Option<Recording>,
}

impl Wired {
    fn open(
        node: &Plane,
        args: &Args,
        pages: Arc<Pages>,
        inbound: Receiver<Inbound>,
    ) -> Result<Wired> {
        let cameras = args
            .cameras
            .iter()
            .map(|name| {
                Ok(CameraView::new(
                    name,
                    node.camera_subscriber(name, CameraStream::Mjpeg)?,
                ))
            })
            .collect::<Result<Vec<_>>>()?;
        let recording = match &args.dataset {
            Some(dataset) => Some(Recording::new(RecordingSettings {
                nori: telemetry::process::sibling("nori")?,
                dataset: dataset.clone(),
                domain: args.domain.clone(),
                cameras: args.cameras.clone(),
                log: std::env::temp_dir()
                    .join(format!("nori-lab-record-{}.log", std::process::id())),
            })),
            None => None,
        };
        Ok(Wired {
            layouts: node.subscriber(&plane::LAYOUT)?,
            states: node.subscriber(&plane::JOINT_STATE)?,
            lifts: node.subscriber(&plane::LIFT_STATE)?,
            bases: node.subscriber(&plane::BASE_STATE)?,
            events: node.subscriber(&plane::EVENTS)?,
            allowances: node.subscriber(&plane::LIFT_ALLOWANCE)?,
            goals: node.publisher(&plane::GOALS)?,
            commands: node.publisher(&plane::COMMANDS)?,
            cameras,
            pages,
            inbound,
            recording,
        })
    }

    /// An episode being recorded is kept, as `nori record` keeps it on SIGINT.
    fn finish_recording(&mut self) {
        if let Some(r) = self.recording.as_mut().filter(|r| r.busy()) {
            let _ = r.end(false);
            let until = Instant::now() + Duration::from_secs(20);
            while r.busy() && Instant::now() < until {
                if let Some(outcome) = r.poll() {
                    tracing::info!("recording at exit: {outcome:?}");
                }
                std::thread::sleep(Duration::from_millis(20));
            }
        }
    }
}

impl LabIo for Wired {
    fn now_ns(&self) -> u64 {
        monotonic_ns()
    }
    fn layout(&mut self) -> Option<JointLayout> {
        newest(&self.layouts)
    }
    fn next_state(&mut self) -> Option<JointState> {
        next(&self.states)
    }
    fn lift(&mut self) -> Option<LiftState> {
        newest(&self.lifts)
    }
    fn base(&mut self) -> Option<BaseState> {
        newest(&self.bases)
    }
    fn next_event(&mut self) -> Option<SupervisorEvent> {
        next(&self.events)
    }
    fn allowance(&mut self) -> Option<LiftAllowance> {
        newest(&self.allowances)
    }
    fn publish_goal(&mut self, frame: &GoalFrame) -> Result<(), String> {
        publish(&self.goals, frame).map_err(|e| e.to_string())
    }
    fn publish_command(&mut self, command: &SupervisorCommand) -> Result<(), String> {
        publish(&self.commands, command).map_err(|e| e.to_string())
    }
    fn next_page_event(&mut self, wait: Duration) -> Result<Option<Inbound>, ServerStopped> {
        match self.inbound.recv_timeout(wait) {
            Ok(inbound) => Ok(Some(inbound)),
            Err(RecvTimeoutError::Timeout) => Ok(None),
            Err(RecvTimeoutError::Disconnected) => Err(ServerStopped),
        }
    }
    fn send(&mut self, page: u64, text: Arc<str>) {
        self.pages.send(page, text);
    }
    fn broadcast(&mut self, message: &Outgoing) {
        self.pages.broadcast_message(message);
    }
    fn pages_open(&self) -> usize {
        self.pages.open()
    }
    fn take_camera_images(&mut self) {
        for c in &mut self.cameras {
            c.take();
        }
    }
    fn send_camera_images(&mut self) {
        for c in &mut self.cameras {
            if let Some(message) = c.message() {
                self.pages.broadcast_message(&message);
            }
        }
    }
    fn camera_status(&self, now_ns: u64) -> Vec<CameraStatus> {
        self.cameras.iter().map(|c| c.status(now_ns)).collect()
    }
    fn record(&mut self, request: RecordRequest) -> Result<(), String> {
        let Some(r) = self.recording.as_mut() else {
            return Err("this lab records nothing: start it with --dataset DIR".to_string());
        };
        match request {
            RecordRequest::Start(task) => r.start(&task),
            RecordRequest::Keep => r.end(false),
            RecordRequest::Discard => r.end(true),
        }
    }
    fn recorded(&mut self) -> Option<Outcome> {
        self.recording.as_mut().and_then(Recording::poll)
    }
    fn recording_status(&self) -> Option<RecordingStatus> {
        self.recording.as_ref().map(Recording::status)
    }
}

fn serve(args: &Args) -> Result<()> {
    telemetry::process::init_logging();
    let shutdown = telemetry::process::stop_flag()?;
    let settings = settings(args)?;
    let token = token(args.token_file.as_ref())?;
    let node = Plane::open(&args.domain, &format!("nori-lab-{}", std::process::id()))?;
    let listener =
        TcpListener::bind(args.http).with_context(|| format!("listening on {}", args.http))?;
    let address = listener.local_addr()?;
    let pages = Arc::new(Pages::default());
    let (inbound_tx, inbound) = std::sync::mpsc::channel::<Inbound>();
    let files = Files {
        index_html: include_str!("page/index.html"),
        lab_js: include_str!("page/lab.js"),
    };
    let mut io = Wired::open(&node, args, pages.clone(), inbound)?;
    let http = server::serve(
        listener,
        files,
        Access::new(token.clone()),
        pages.clone(),
        inbound_tx,
        shutdown.clone(),
    )?;
    eprintln!("Nori Lab: http://{address}/#token={token}");

    let started = Instant::now();
    let run_for = args.run_for.map(Duration::from_secs_f64);
    let mut lab = Lab::new(settings, monotonic_ns());
    while !shutdown.load(Ordering::Relaxed) && run_for.is_none_or(|d| started.elapsed() < d) {
        match lab.turn(&mut io) {
            Ok(()) => {}
            // The server's thread ends only once asked to stop.
            Err(_) if shutdown.load(Ordering::Relaxed) => break,
            Err(e) => return Err(e.into()),
        }
    }
    shutdown.store(true, Ordering::Relaxed);
    let _ = http.join();
    io.finish_recording();
    let summary = lab.summary(
        pages.dropped.load(Ordering::Relaxed),
        pages.denied.load(Ordering::Relaxed),
    );
    println!("{}", serde_json::to_string(&summary)?);
    Ok(())
}
