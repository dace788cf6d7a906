//! `fleet-agent`: the zenoh bridge of one robot. The loop is `fleet_agent::agent`; this binary
//! reads its configuration and wires the state plane (iceoryx2) and the fleet (zenoh, whose own
//! threads run behind non-blocking calls) into it.

use anyhow::{Context, Result};
use clap::Parser;
use fleet_agent::agent::{Agent, AgentIo, JournalStart, Outbound};
use fleet_agent::box_shelf::{ChunkRead, ShelfWatch};
use fleet_agent::box_upload::{ChunkToSend, ShelvedBox};
use fleet_agent::journal::{Journal, JournalError};
use fleet_agent::keys::robot_key;
use fleet_agent::zenoh::handlers::FifoChannelHandler;
use fleet_agent::zenoh::pubsub::{Publisher, Subscriber};
use fleet_agent::zenoh::qos::{CongestionControl, Priority};
use fleet_agent::zenoh::query::{Query, Queryable};
use fleet_agent::zenoh::sample::Sample;
use fleet_agent::zenoh::Wait;
use fleet_agent::{net, AgentConfig};
use std::path::PathBuf;
use telemetry::frames::{
    BusHealth, GoalFrame, Heartbeat, JointLayout, JointState, Peer, SupervisorEvent,
};
use telemetry::motion::{BaseCommand, BaseState, LiftCommand, LiftState};
use telemetry::plane::{self, newest, next, publish, CameraStream, FrameSub, Plane, Pub, Sub};
use telemetry::process::Exit;
use telemetry::process::{ProcessArgs, ServiceManager, Started};
use telemetry::sensors::{CameraFrameHeader, LidarScan};

#[derive(Parser)]
#[command(
    version,
    about = "Nori A3 fleet agent: telemetry out, gated policy actions in (zenoh)"
)]
struct Args {
    #[command(flatten)]
    process: ProcessArgs,
    /// Overrides `robot-id`.
    #[arg(long)]
    robot_id: Option<String>,
    /// Overrides `zenoh.connect` (repeatable).
    #[arg(long)]
    connect: Vec<String>,
    /// Overrides `zenoh.listen` (repeatable).
    #[arg(long)]
    listen: Vec<String>,
    /// The event journal's directory (default: `<temp dir>/nori-<domain>-journal`; the robot's
    /// unit passes /var/lib/nori/journal).
    #[arg(long)]
    journal_dir: Option<PathBuf>,
    /// The black box's shelf (`nori-blackbox`'s `dir`, /var/lib/nori/blackbox on the robot):
    /// its finished boxes go to the fleet's store. Absent: no box is sent.
    #[arg(long)]
    blackbox_dir: Option<PathBuf>,
    /// The file the `nori-robot` package writes its version to (absent: a build from source).
    #[arg(long, default_value = fleet_agent::installed::VERSION_FILE)]
    version_file: PathBuf,
    /// The calibration file the driver loads (its stamp goes to the fleet); by default the one
    /// the driver's configuration (`--driver-config`) names.
    #[arg(long)]
    calibration_file: Option<PathBuf>,
    /// The driver's configuration, for the calibration it names (absent: the driver runs on its
    /// embedded defaults, the simulated A3's calibration among them).
    #[arg(long, default_value = fleet_agent::installed::DRIVER_CONFIG)]
    driver_config: PathBuf,
}

/// The agent's two planes: iceoryx2 ports, and zenoh declarations once the fleet is reached.
struct Wired {
    /// `None` until the session opens (the robot may start with its router out of reach).
    fleet: Option<FleetPorts>,
    /// Sessions opened in the background, until one is.
    connecting: Option<std::sync::mpsc::Receiver<fleet_agent::zenoh::Session>>,
    zenoh_config: fleet_agent::zenoh::Config,
    id: String,
    layouts: Sub<JointLayout>,
    states: Sub<JointState>,
    events: Sub<SupervisorEvent>,
    driver_beats: Sub<Heartbeat>,
    supervisor_beats: Sub<Heartbeat>,
    /// `None` when it could not be opened (logged): events then go out live, unnumbered.
    journal: Option<Journal>,
    journal_dir: PathBuf,
    bus_health: Sub<BusHealth>,
    /// Per configured camera; `None` where the service could not be opened (logged).
    cameras: Vec<Option<FrameSub>>,
    /// Per observation camera, its JPEG stream; `None` where it could not be opened (logged).
    images: Vec<Option<FrameSub>>,
    lidar: Option<Sub<LidarScan>>,
    goals: Pub<GoalFrame>,
    lift_states: Sub<LiftState>,
    base_states: Sub<BaseState>,
    lift_commands: Pub<LiftCommand>,
    base_commands: Pub<BaseCommand>,
    /// The black box's shelf, when `--blackbox-dir` names one.
    shelf: Option<ShelfWatch>,
}

/// The agent's declarations on the fleet's session.
struct FleetPorts {
    state_pub: Publisher<'static>,
    observation_pub: Publisher<'static>,
    layout_pub: Publisher<'static>,
    preview_pub: Publisher<'static>,
    scan_pub: Publisher<'static>,
    event_pub: Publisher<'static>,
    box_pub: Publisher<'static>,
    acks: Subscriber<FifoChannelHandler<Sample>>,
    box_acks: Subscriber<FifoChannelHandler<Sample>>,
    actions: Subscriber<FifoChannelHandler<Sample>>,
    status_key: String,
    status_queries: Queryable<FifoChannelHandler<Query>>,
    /// The fleet sees the robot while this lives.
    _alive: fleet_agent::zenoh::liveliness::LivelinessToken,
    _session: fleet_agent::zenoh::Session,
}

impl FleetPorts {
    fn declare(session: fleet_agent::zenoh::Session, id: &str) -> Result<FleetPorts> {
        let z = |e: fleet_agent::zenoh::Error| anyhow::anyhow!("{e}");
        // Everything is dropped on congestion: blocking would stall this loop (the one
        // forwarding goals), and what must arrive (events, boxes) is sent again until
        // acknowledged.
        let publisher = |key: &str, priority| {
            session
                .declare_publisher(robot_key(id, key))
                .congestion_control(CongestionControl::Drop)
                .priority(priority)
                .wait()
                .map_err(z)
        };
        let status_key = robot_key(id, "status");
        Ok(FleetPorts {
            state_pub: publisher("state", Priority::Data)?,
            observation_pub: publisher("observation", Priority::Data)?,
            layout_pub: publisher("layout", Priority::Data)?,
            preview_pub: publisher("preview", Priority::Data)?,
            scan_pub: publisher("scan", Priority::Data)?,
            // Held in the journal until the fleet acknowledges them; blocking on a frozen
            // router would stall the loop for as long as it takes to be declared dead.
            event_pub: publisher("events", Priority::Data)?,
            // At zenoh's lowest priority: queued behind the telemetry and the events.
            box_pub: publisher("blackbox/chunk", Priority::Background)?,
            box_acks: session
                .declare_subscriber(robot_key(id, "blackbox/ack"))
                .wait()
                .map_err(z)?,
            acks: session
                .declare_subscriber(robot_key(id, "acks"))
                .wait()
                .map_err(z)?,
            actions: session
                .declare_subscriber(robot_key(id, "actions"))
                .wait()
                .map_err(z)?,
            status_queries: session.declare_queryable(&status_key).wait().map_err(z)?,
            status_key,
            _alive: session
                .liveliness()
                .declare_token(robot_key(id, "alive"))
                .wait()
                .map_err(z)?,
            _session: session,
        })
    }
}

/// Opens the fleet's session on a thread of its own, trying again (1 s, doubling to 30 s) while
/// the fleet is out of reach: a zenoh client cannot open without its router, and the robot must
/// journal its events from boot whatever the network does.
fn connect_in_background(
    config: fleet_agent::zenoh::Config,
    id: String,
) -> std::sync::mpsc::Receiver<fleet_agent::zenoh::Session> {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut wait = std::time::Duration::from_secs(1);
        loop {
            match fleet_agent::zenoh::open(config.clone()).wait() {
                Ok(session) => {
                    let _ = tx.send(session);
                    return;
                }
                Err(e) => {
                    tracing::warn!(robot = %id, "the fleet is out of reach ({e}): events are journaled; trying again in {wait:?}");
                    std::thread::sleep(wait);
                    wait = (wait * 2).min(std::time::Duration::from_secs(30));
                }
            }
        }
    });
    rx
}

impl AgentIo for Wired {
    fn layout(&mut self) -> Option<JointLayout> {
        newest(&self.layouts)
    }
    fn next_state(&mut self) -> Option<JointState> {
        next(&self.states)
    }
    fn bus_health(&mut self) -> Option<BusHealth> {
        newest(&self.bus_health)
    }
    fn camera(
        &mut self,
        index: usize,
        look: &mut dyn FnMut(&CameraFrameHeader, &[u8]),
    ) -> Option<CameraFrameHeader> {
        // The newest frame only; its pixels are looked at in shared memory, never copied.
        let sub = self.cameras.get(index)?.as_ref()?;
        let mut newest = None;
        while let Ok(Some(sample)) = sub.receive() {
            newest = Some(sample);
        }
        let sample = newest?;
        look(sample.user_header(), sample.payload());
        Some(*sample.user_header())
    }
    fn image(&mut self, index: usize, jpeg: &mut Vec<u8>) -> Option<CameraFrameHeader> {
        let sub = self.images.get(index)?.as_ref()?;
        // Only the newest is copied out of shared memory: the queue holds at most two.
        let mut newest = None;
        while let Ok(Some(sample)) = sub.receive() {
            newest = Some(sample);
        }
        let sample = newest?;
        jpeg.clear();
        jpeg.extend_from_slice(sample.payload());
        Some(*sample.user_header())
    }
    fn lidar(&mut self) -> Option<LidarScan> {
        newest(self.lidar.as_ref()?)
    }
    fn next_event(&mut self) -> Option<SupervisorEvent> {
        next(&self.events)
    }
    fn heartbeat(&mut self, peer: Peer) -> Option<Heartbeat> {
        newest(match peer {
            Peer::Driver => &self.driver_beats,
            Peer::Supervisor => &self.supervisor_beats,
        })
    }
    fn journal(&mut self, record: &[u8]) -> Result<u64, JournalError> {
        match &mut self.journal {
            Some(j) => j.append(record),
            None => Err(JournalError::Io {
                path: self.journal_dir.display().to_string(),
                source: std::io::Error::other("the journal did not open at start"),
            }),
        }
    }
    fn acknowledged(&mut self, seq: u64) {
        if let Some(Err(e)) = self.journal.as_ref().map(|j| j.acknowledge(seq)) {
            tracing::warn!("{e}: the fleet may be sent again what it has");
        }
    }
    fn next_ack(&mut self) -> Option<Vec<u8>> {
        let sample = self.fleet.as_ref()?.acks.try_recv().ok().flatten()?;
        Some(sample.payload().to_bytes().into_owned())
    }
    fn send_goal(&mut self, goal: &GoalFrame) -> bool {
        publish(&self.goals, goal).is_ok()
    }
    fn lift(&mut self) -> Option<LiftState> {
        newest(&self.lift_states)
    }
    fn base(&mut self) -> Option<BaseState> {
        newest(&self.base_states)
    }
    fn send_lift(&mut self, command: &LiftCommand) -> bool {
        publish(&self.lift_commands, command).is_ok()
    }
    fn send_base(&mut self, command: &BaseCommand) -> bool {
        publish(&self.base_commands, command).is_ok()
    }
    fn publish(&mut self, what: Outbound, payload: Vec<u8>) -> bool {
        let Some(f) = &self.fleet else {
            return false;
        };
        let publisher = match what {
            Outbound::State => &f.state_pub,
            Outbound::Observation => &f.observation_pub,
            Outbound::Layout => &f.layout_pub,
            Outbound::Preview => &f.preview_pub,
            Outbound::Scan => &f.scan_pub,
            Outbound::Event => &f.event_pub,
            Outbound::BoxChunk => &f.box_pub,
        };
        publisher.put(payload).wait().is_ok()
    }
    fn next_action(&mut self) -> Option<Vec<u8>> {
        let sample = self.fleet.as_ref()?.actions.try_recv().ok().flatten()?;
        Some(sample.payload().to_bytes().into_owned())
    }
    fn answer_status(&mut self, status: &mut dyn FnMut() -> Vec<u8>) {
        let Some(f) = &self.fleet else {
            return;
        };
        while let Ok(Some(query)) = f.status_queries.try_recv() {
            // Answered on the robot's own key: a fleet asking `nori/*/status` learns from the
            // key which robot answered (a reply on the query's wildcard would not be valid).
            if let Err(e) = query.reply(&f.status_key, status()).wait() {
                tracing::debug!("status reply: {e}");
            }
        }
    }
    fn shelf(&mut self) -> Option<Vec<ShelvedBox>> {
        self.shelf.as_ref()?.listing()
    }
    fn ask_box(&mut self, chunk: &ChunkToSend) -> bool {
        self.shelf.as_ref().is_some_and(|s| s.ask(chunk))
    }
    fn box_bytes(&mut self) -> Option<ChunkRead> {
        self.shelf.as_ref()?.read()
    }
    fn next_box_ack(&mut self) -> Option<Vec<u8>> {
        let sample = self.fleet.as_ref()?.box_acks.try_recv().ok().flatten()?;
        Some(sample.payload().to_bytes().into_owned())
    }
    fn fleet_joined(&mut self) -> bool {
        let Some(session) = self.connecting.as_ref().and_then(|rx| rx.try_recv().ok()) else {
            return false;
        };
        self.connecting = None;
        match FleetPorts::declare(session, &self.id) {
            Ok(ports) => {
                tracing::info!(robot = %self.id, "on the fleet");
                self.fleet = Some(ports);
                true
            }
            Err(e) => {
                tracing::error!("declaring the robot's keys on the fleet: {e}; joining again");
                self.connecting = Some(connect_in_background(
                    self.zenoh_config.clone(),
                    self.id.clone(),
                ));
                false
            }
        }
    }
}

fn main() -> std::process::ExitCode {
    telemetry::process::finish(run(Args::parse()), |e| {
        if e.is::<fleet_agent::keys::BadRobotId>() {
            return Some(Exit::Config);
        }
        match e.downcast_ref::<fleet_agent::net::NetError>()? {
            fleet_agent::net::NetError::Config(_) => Some(Exit::Config),
            fleet_agent::net::NetError::Open(_) => Some(Exit::Unavailable),
        }
    })
}

/// The process; an error ends it with its fault class's exit code (ARCHITECTURE.md, "Exit
/// codes").
fn run(args: Args) -> Result<()> {
    let Some(Started {
        mut config,
        shutdown,
    }) = args.process.start::<AgentConfig>()?
    else {
        return Ok(());
    };
    if let Some(id) = &args.robot_id {
        fleet_agent::keys::check_robot_id(id)?;
        config.robot_id = id.clone();
    }
    if !args.connect.is_empty() {
        config.zenoh.connect = args.connect.clone();
    }
    if !args.listen.is_empty() {
        config.zenoh.listen = args.listen.clone();
    }
    let node = Plane::open(&args.process.domain, "fleet-agent")?;
    node.cleanup_dead();
    let id = config.robot_id.clone();
    let zenoh_config = net::zenoh_config(&config.zenoh)
        .with_context(|| format!("joining the fleet as {id} via {:?}", config.zenoh.connect))?;
    let journal_dir = args.journal_dir.clone().unwrap_or_else(|| {
        std::env::temp_dir().join(format!("nori-{}-journal", args.process.domain))
    });
    let (journal, start) = open_journal(&journal_dir, config.journal.bound_bytes);
    let mut io = wire(&node, zenoh_config, &id, &config, journal, journal_dir)?;
    io.shelf = watch_shelf(args.blackbox_dir.as_deref());
    tracing::info!(robot = %id, domain = %args.process.domain, connect = ?config.zenoh.connect,
        "joining the fleet: telemetry on {}, actions from {}", robot_key(&id, "state"), robot_key(&id, "actions"));
    let mut service = ServiceManager::from_env();
    service.ready(&format!("robot {id} joining the fleet"));
    let mut agent = Agent::resuming(&config, start)
        .installed(installed_version(&args.version_file))
        .calibrated(calibration_of_the_driver(&args, &id));
    let run_for = args.process.run_for()?;
    fleet_agent::agent::run(&mut agent, &mut io, &shutdown, run_for, &mut |t| {
        service.keepalive(t)
    });
    service.stopping();
    tracing::info!(robot = %id, accepted = agent.accepted(), forwarded = agent.goals_forwarded(), "leaving the fleet");
    // The token, publishers and session close on drop: the fleet sees the robot leave.
    Ok(())
}

/// The calibration the driver runs: `--calibration-file`'s, else the one the driver's
/// configuration names, else the embedded one (no configuration, or one naming none).
fn calibration_of_the_driver(
    args: &Args,
    robot_id: &str,
) -> Option<fleet_agent::schema::CalibrationMsg> {
    use fleet_agent::installed::{calibration_file_of, embedded_calibration};
    if let Some(path) = &args.calibration_file {
        return calibration_in_force(path, robot_id);
    }
    let config = &args.driver_config;
    let text = match std::fs::read_to_string(config) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            tracing::info!(
                "no {}: the driver runs its embedded calibration",
                config.display()
            );
            return Some(embedded_calibration());
        }
        Err(e) => {
            tracing::warn!(
                "the calibration in force is unknown: {}: {e}",
                config.display()
            );
            return None;
        }
    };
    let dir = config.parent().unwrap_or(std::path::Path::new("."));
    match calibration_file_of(&text, dir) {
        Ok(Some(path)) => calibration_in_force(&path, robot_id),
        Ok(None) => {
            tracing::warn!(
                "{} names no calibration file: the driver runs the simulated A3's",
                config.display()
            );
            Some(embedded_calibration())
        }
        Err(e) => {
            tracing::warn!(
                "the calibration in force is unknown: {}: {e}",
                config.display()
            );
            None
        }
    }
}

/// The calibration stamp of the file at `path`: `None`, said once, when there is none or it
/// cannot be read (the status names no calibration rather than a wrong one); another robot's
/// file is reported as it is, and warned of.
fn calibration_in_force(
    path: &std::path::Path,
    robot_id: &str,
) -> Option<fleet_agent::schema::CalibrationMsg> {
    let text = match std::fs::read_to_string(path) {
        Ok(text) => text,
        Err(e) => {
            tracing::info!("no calibration to report: {}: {e}", path.display());
            return None;
        }
    };
    match fleet_agent::installed::calibration_in_force(&text) {
        Ok(c) => {
            if !c.robot.is_empty() && c.robot != robot_id {
                tracing::warn!(
                    "{} is robot {:?}'s calibration, not {robot_id:?}'s",
                    path.display(),
                    c.robot
                );
            }
            tracing::info!(
                "calibration in force: {} {} ({} joints)",
                c.method,
                c.at,
                c.joints
            );
            Some(c)
        }
        Err(e) => {
            tracing::warn!(
                "the calibration in force is unknown: {}: {e}",
                path.display()
            );
            None
        }
    }
}

/// The package version from `path`: `None`, said once, when there is no such file (a build
/// from source) or it is not one version (the status then names no version rather than a
/// wrong one; the agent runs on, as it serves the fleet and guards nothing).
fn installed_version(path: &std::path::Path) -> Option<String> {
    let read = std::fs::read_to_string(path);
    if matches!(&read, Err(e) if e.kind() == std::io::ErrorKind::NotFound) {
        tracing::info!("no {}: not installed from a package", path.display());
        return None;
    }
    let parsed = read.map_err(|e| e.to_string()).and_then(|text| {
        fleet_agent::installed::parse_version_file(&text).map_err(|e| e.to_string())
    });
    match parsed {
        Ok(v) => {
            tracing::info!("running nori-robot {v}");
            Some(v)
        }
        Err(e) => {
            tracing::warn!("the installed version is unknown: {}: {e}", path.display());
            None
        }
    }
}

/// Opens the event journal and reads what it keeps. A journal that cannot be opened (its
/// storage gone, its identity lost) leaves the agent running without it: events then go out
/// live, unnumbered, each counted in the status (`events_unjournaled`).
fn open_journal(dir: &std::path::Path, bound: u64) -> (Option<Journal>, JournalStart) {
    let opened = Journal::open(dir, bound).and_then(|(j, recovery)| {
        let kept = j.records_after(0)?;
        Ok((j, recovery, kept))
    });
    match opened {
        Ok((j, recovery, kept)) => {
            tracing::info!(dir = %dir.display(), records = recovery.records, cut_bytes = recovery.cut_bytes,
                acked_through = recovery.acked_through, next = j.next_seq(), "event journal open");
            let start = JournalStart {
                id: j.id(),
                kept,
                recovery,
            };
            (Some(j), start)
        }
        Err(e) => {
            tracing::error!("{e}: running without the event journal (events are sent once, live)");
            (None, JournalStart::default())
        }
    }
}

/// Watches the black box's shelf in `dir`, if one is named: `None` (said once) otherwise, or
/// when its thread cannot start (the agent runs on; its boxes stay on the robot).
fn watch_shelf(dir: Option<&std::path::Path>) -> Option<ShelfWatch> {
    let Some(dir) = dir else {
        tracing::info!("no --blackbox-dir: the black box's boxes are not sent to the fleet");
        return None;
    };
    match ShelfWatch::spawn(dir.to_path_buf(), std::time::Duration::from_secs(1)) {
        Ok(w) => {
            tracing::info!(dir = %dir.display(), "the black box's boxes go to the fleet's store");
            Some(w)
        }
        Err(e) => {
            tracing::error!(
                "watching the black box's shelf {}: {e}; its boxes are not sent",
                dir.display()
            );
            None
        }
    }
}

/// Opens the agent's ports on the state plane and starts joining the fleet.
fn wire(
    node: &Plane,
    zenoh_config: fleet_agent::zenoh::Config,
    id: &str,
    config: &AgentConfig,
    journal: Option<Journal>,
    journal_dir: PathBuf,
) -> Result<Wired> {
    let sensors = &config.sensors;
    Ok(Wired {
        fleet: None,
        connecting: Some(connect_in_background(zenoh_config.clone(), id.into())),
        zenoh_config,
        id: id.into(),
        layouts: node.subscriber(&plane::LAYOUT)?,
        states: node.subscriber(&plane::JOINT_STATE)?,
        events: node.subscriber(&plane::EVENTS)?,
        driver_beats: node.subscriber(&plane::DRIVER_HEARTBEAT)?,
        supervisor_beats: node.subscriber(&plane::SUPERVISOR_HEARTBEAT)?,
        journal,
        journal_dir,
        bus_health: node.subscriber(&plane::BUS_HEALTH)?,
        cameras: sensors
            .cameras
            .iter()
            .map(|name| {
                node.camera_subscriber(name, CameraStream::Rgb)
                    .inspect_err(|e| tracing::warn!("camera {name}: {e}; not watched"))
                    .ok()
            })
            .collect(),
        images: config
            .observation
            .cameras
            .iter()
            .map(|name| {
                node.camera_subscriber(name, CameraStream::Mjpeg)
                    .inspect_err(|e| tracing::warn!("camera {name} (JPEG): {e}; no images of it"))
                    .ok()
            })
            .collect(),
        lidar: if sensors.lidar {
            Some(node.subscriber(&plane::LIDAR_SCAN)?)
        } else {
            None
        },
        goals: node.publisher(&plane::GOALS)?,
        lift_states: node.subscriber(&plane::LIFT_STATE)?,
        base_states: node.subscriber(&plane::BASE_STATE)?,
        lift_commands: node.publisher(&plane::LIFT_COMMAND)?,
        base_commands: node.publisher(&plane::BASE_COMMAND)?,
        shelf: None,
    })
}
