//! `nori-blackbox`: the robot's black box as a process (`record`), and the operator's commands
//! on its boxes (`list`, `show`, `export`, `save`; run as `nori blackbox …`).
//!
//! `record` moves every frame of the state plane it keeps into the recorder at 100 Hz, freezes
//! a box on each trigger, flushes the open box's chunk every second, and names a box whole
//! once its window has passed. It only reads the plane: killed, hung or slow, it holds no
//! other process (the plane's queues overwrite their oldest frame).

use anyhow::{bail, Context, Result};
use blackbox::channel::{self, Channel, EventMessage, Names};
use blackbox::config::BlackboxConfig;
use blackbox::frame_tree::FrameTree;
use blackbox::frozen::{self, BoxWriter, Durable};
use blackbox::recorder::{Recorder, Window, COPY_STEP};
use blackbox::ring::{Record, Ring};
use blackbox::shelf::{self, Shelf};
use blackbox::trigger::{OwnTrigger, Watch};
use camera::thumbnail::Thumbnailer;
use clap::{Parser, Subcommand};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime};
use telemetry::clock::monotonic_ns;
use telemetry::frames::{BusHealth, Directives, JointLayout, SupervisorEvent};
use telemetry::motion::{BaseState, LiftState};
use telemetry::plane::{self, Plane, Sub};
use telemetry::process::{ProcessArgs, ServiceManager, Started, Ticker};
use telemetry::wire::{BlackboxSave, WireFrame};
use telemetry::{GoalFrame, JointState};

#[derive(Parser)]
#[command(
    version,
    about = "Nori A3 black box: the robot's last minutes, frozen when it matters"
)]
struct Args {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Record: the process (systemd's nori-blackbox.service).
    Record {
        #[command(flatten)]
        process: ProcessArgs,
        /// Keep boxes here instead of the configuration's `dir`.
        #[arg(long)]
        dir: Option<PathBuf>,
        /// The robot description the body's frames (`/tf`) are drawn from (the embedded Nori
        /// A3 when absent).
        #[arg(long)]
        robot: Option<PathBuf>,
    },
    /// The boxes kept, oldest first.
    List {
        /// The box directory (the configuration's `dir` when absent).
        #[arg(long)]
        dir: Option<PathBuf>,
        /// One JSON object per box.
        #[arg(long)]
        json: bool,
    },
    /// What one box holds.
    Show {
        /// The box (a path, or a name in the box directory).
        r#box: PathBuf,
        /// The box directory.
        #[arg(long)]
        dir: Option<PathBuf>,
    },
    /// A box's joint states as the model lab's CSV (with a NAME.meta.json sidecar), or its MCAP.
    Export {
        /// The box.
        r#box: PathBuf,
        /// The box directory.
        #[arg(long)]
        dir: Option<PathBuf>,
        /// Write the joint states as CSV here.
        #[arg(long)]
        csv: Option<PathBuf>,
        /// Copy the raw MCAP here.
        #[arg(long)]
        mcap: Option<PathBuf>,
    },
    /// Freeze the last minutes now (the running recorder saves a box).
    Save {
        /// State-plane domain.
        #[arg(long, default_value = plane::DEFAULT_DOMAIN)]
        domain: String,
    },
}

fn main() -> std::process::ExitCode {
    telemetry::process::finish(run(Args::parse()), |_| None)
}

fn run(args: Args) -> Result<()> {
    match args.command {
        Command::Record {
            process,
            dir,
            robot,
        } => record(&process, dir, robot.as_deref()),
        Command::List { dir, json } => list(&box_dir(dir)?, json),
        Command::Show { r#box, dir } => show(&find_box(&r#box, dir)?),
        Command::Export {
            r#box,
            dir,
            csv,
            mcap,
        } => export(&find_box(&r#box, dir)?, csv.as_deref(), mcap.as_deref()),
        Command::Save { domain } => save(&domain),
    }
}

/// `--dir`, or the embedded configuration's.
fn box_dir(dir: Option<PathBuf>) -> Result<PathBuf> {
    use telemetry::config::ProcessConfig;
    Ok(match dir {
        Some(d) => d,
        None => BlackboxConfig::embedded()?.dir,
    })
}

fn find_box(b: &Path, dir: Option<PathBuf>) -> Result<PathBuf> {
    if b.exists() {
        return Ok(b.into());
    }
    let in_dir = box_dir(dir)?.join(b);
    if in_dir.exists() {
        return Ok(in_dir);
    }
    bail!("no box {} (nor {})", b.display(), in_dir.display())
}

/// The recorder's subscriptions.
struct Inputs {
    wire: Sub<WireFrame>,
    states: Sub<JointState>,
    layout: Sub<JointLayout>,
    goals: Sub<GoalFrame>,
    wheel_goals: Sub<GoalFrame>,
    directives: Sub<Directives>,
    events: Sub<SupervisorEvent>,
    health: Sub<BusHealth>,
    lift: Sub<LiftState>,
    base: Sub<BaseState>,
    save: Sub<BlackboxSave>,
    lidar: Sub<telemetry::sensors::LidarScan>,
    /// The thumbnails' cameras' RGB frames (`None`: a camera whose service cannot be opened).
    cameras: Vec<Option<plane::FrameSub>>,
}

impl Inputs {
    fn open(node: &Plane, cameras: &[String]) -> Result<Inputs> {
        Ok(Inputs {
            wire: node.subscriber(&plane::BUS_WIRE)?,
            states: node.subscriber(&plane::JOINT_STATE)?,
            layout: node.subscriber(&plane::LAYOUT)?,
            goals: node.subscriber(&plane::GOALS)?,
            wheel_goals: node.subscriber(&plane::WHEEL_GOALS)?,
            directives: node.subscriber(&plane::DIRECTIVES)?,
            events: node.subscriber(&plane::EVENTS)?,
            health: node.subscriber(&plane::BUS_HEALTH)?,
            lift: node.subscriber(&plane::LIFT_STATE)?,
            base: node.subscriber(&plane::BASE_STATE)?,
            save: node.subscriber(&plane::BLACKBOX_SAVE)?,
            lidar: node.subscriber(&plane::LIDAR_SCAN)?,
            cameras: cameras
                .iter()
                .map(|name| {
                    node.camera_subscriber(name, plane::CameraStream::Rgb)
                        .inspect_err(|e| tracing::warn!("camera {name}: {e}; no thumbnails of it"))
                        .ok()
                })
                .collect(),
        })
    }
}

/// The recording process's state: the recorder, where its boxes go, what it watches.
struct Recording {
    recorder: Recorder<Durable>,
    shelf: Shelf,
    robot: String,
    wall_offset_ns: i128,
    names: Names,
    bus_count: usize,
    watch: Watch,
    partial: Option<PathBuf>,
    disk_cap_bytes: u64,
    /// The driver's last state frame seen, and the frames never seen between two seen (the
    /// plane's queue overwrote them: the recorder fell behind).
    last_state_seq: Option<u64>,
    states_missed: u64,
    states_missed_logged: u64,
    /// Each bus's last wire frame's cycle, and the cycles between two seen with no frame
    /// (overwritten unread, or a cycle the bus moved nothing: a lost bus).
    last_wire_cycle: [Option<u64>; telemetry::frames::MAX_BUSES],
    wire_cycles_missed: u64,
    /// When the last lidar revolution kept was measured (one a second is kept).
    last_scan_ns: u64,
    thumbnails: Thumbnails,
    /// The body's frames (`None`: `[transforms] hz = 0`), their period, the last one's time.
    tree: Option<FrameTree>,
    tree_every_ns: u64,
    last_tree_ns: Option<u64>,
}

/// The cameras' thumbnails: what makes them, how often, each camera's last.
struct Thumbnails {
    cameras: Vec<String>,
    every_ns: u64,
    maker: Thumbnailer,
    last_ns: Vec<Option<u64>>,
    /// Frames that gave no thumbnail (not RGB, short of bytes, no camera's shape): counted,
    /// logged when the count reaches a power of two.
    failed: u64,
}

impl Recording {
    /// The box being frozen was given up (a write failed): its file is no longer protected.
    fn given_up(&mut self, e: &blackbox::frozen::BoxError) {
        tracing::error!("the box being frozen is given up: {e}");
        self.partial = None;
    }

    fn record(&mut self, channel: Channel, (t_ns, data): (u64, Vec<u8>)) {
        // A stamp ahead of the clock (a publisher's bug, a frame from the future) is taken as
        // now: it must neither hold a ring segment open nor push the ring's end ahead. A
        // missing stamp (a wire frame that only lost bytes) is now too.
        let now = monotonic_ns();
        let t_ns = if t_ns == 0 { now } else { t_ns.min(now) };
        if let Err(e) = self.recorder.record(Record {
            channel,
            t_ns,
            data: &data,
        }) {
            self.given_up(&e);
        }
    }

    /// Every frame waiting on the plane into the recorder; the triggers they carry.
    fn drain(&mut self, i: &Inputs) -> Vec<EventMessage> {
        let mut triggers = Vec::new();
        if let Some(l) = plane::newest(&i.layout) {
            self.names = Names::from_layout(&l);
            self.bus_count = l.bus_count as usize;
            if let Some(tree) = &mut self.tree {
                tree.layout(&l);
            }
            // Once a second from the driver: every box's window holds one.
            self.record(Channel::Layout, channel::layout(&l, monotonic_ns()));
        }
        while let Some(w) = plane::next(&i.wire) {
            if let Some(last) = self.last_wire_cycle.get_mut(w.bus as usize) {
                if let Some(prev) = last.filter(|p| w.cycle > p + 1) {
                    self.wire_cycles_missed += w.cycle - prev - 1;
                }
                *last = Some(w.cycle);
            }
            self.record(Channel::Wire, channel::wire(&w, &self.names));
        }
        while let Some(s) = plane::next(&i.states) {
            // A driver restarted counts from 1 again: no gap.
            if let Some(prev) = self.last_state_seq.filter(|p| s.seq > p + 1) {
                self.states_missed += s.seq - prev - 1;
            }
            self.last_state_seq = Some(s.seq);
            triggers.extend(self.watch.joint_state(&s));
            self.record(Channel::JointStates, channel::joint_states(&s, &self.names));
            if let Some(m) = self.frames_due(&s) {
                self.record(Channel::Transforms, m);
            }
        }
        while let Some(g) = plane::next(&i.goals) {
            self.record(Channel::Goals, channel::goals(&g, &self.names));
        }
        while let Some(g) = plane::next(&i.wheel_goals) {
            self.record(Channel::WheelGoals, channel::goals(&g, &self.names));
        }
        while let Some(d) = plane::next(&i.directives) {
            let m = channel::directives(&d, self.bus_count);
            self.record(Channel::Directives, m);
        }
        while let Some(e) = plane::next(&i.events) {
            triggers.extend(self.watch.event(&e, &self.names));
            let m = channel::event(&e, &self.names);
            self.record(Channel::Events, (m.timestamp_ns, channel::to_json(&m)));
        }
        while let Some(h) = plane::next(&i.health) {
            self.record(Channel::BusHealth, channel::bus_health(&h, &self.names));
        }
        while let Some(s) = plane::next(&i.lift) {
            triggers.extend(self.watch.lift(&s));
            if let Some(tree) = &mut self.tree {
                tree.lift(&s);
            }
            self.record(Channel::LiftState, channel::lift_state(&s));
        }
        while let Some(s) = plane::next(&i.base) {
            triggers.extend(self.watch.base(&s));
            if let Some(tree) = &mut self.tree {
                tree.base(&s);
            }
            self.record(Channel::BaseState, channel::base_state(&s));
        }
        while let Some(scan) = plane::next(&i.lidar) {
            if scan.start_ns >= self.last_scan_ns.saturating_add(1_000_000_000) {
                self.last_scan_ns = scan.start_ns;
                let m = channel::laser_scan(&scan, self.wall_offset_ns);
                self.record(Channel::LidarScan, m);
            }
        }
        while let Some(s) = plane::next(&i.save) {
            triggers.push(OwnTrigger::Saved.at(s.timestamp_ns, s.pid as f32));
        }
        self.thumbnails(&i.cameras);
        triggers
    }

    /// The body's frames at `s`, if one is due (a stamp ahead of the clock counts as now: it
    /// must not hold the next ones back).
    fn frames_due(&mut self, s: &JointState) -> Option<(u64, Vec<u8>)> {
        let tree = self.tree.as_ref()?;
        let at = s.timestamp_ns.min(monotonic_ns());
        if self
            .last_tree_ns
            .is_some_and(|last| at < last.saturating_add(self.tree_every_ns))
        {
            return None;
        }
        self.last_tree_ns = Some(at);
        Some(channel::transforms(
            s.timestamp_ns,
            &tree.frames(s),
            self.wall_offset_ns,
        ))
    }

    /// A thumbnail of a camera's newest frame, where one is due: one a turn at most, so the
    /// turn stays short whatever the cameras. The pixels are read in shared memory, never
    /// copied; a capture stamp ahead of the clock counts as now.
    fn thumbnails(&mut self, cameras: &[Option<plane::FrameSub>]) {
        for (k, sub) in cameras.iter().enumerate() {
            let Some(sub) = sub else { continue };
            let mut newest = None;
            while let Ok(Some(sample)) = sub.receive() {
                newest = Some(sample);
            }
            let Some(sample) = newest else { continue };
            let (h, t) = (sample.user_header(), &mut self.thumbnails);
            let at = h.capture_ns.min(monotonic_ns());
            if t.last_ns[k].is_some_and(|last| at < last.saturating_add(t.every_ns)) {
                continue;
            }
            t.last_ns[k] = Some(at);
            let message = match t.maker.make(h, sample.payload()) {
                Ok((jpeg, _, _)) => {
                    channel::thumbnail(&t.cameras[k], at, jpeg, self.wall_offset_ns)
                }
                Err(e) => {
                    t.failed += 1;
                    if t.failed.is_power_of_two() {
                        tracing::warn!(failed = t.failed, "no thumbnail: {e}");
                    }
                    continue;
                }
            };
            self.record(Channel::Thumbnail(k as u8), message);
            return;
        }
    }

    /// Freezes a box on `event` (or keeps the open one longer); a stamp ahead of the clock is
    /// taken as now (a box must end).
    fn trigger(&mut self, event: &EventMessage) {
        let mut event = event.clone();
        event.timestamp_ns = event.timestamp_ns.min(monotonic_ns());
        let event = &event;
        tracing::info!(kind = %event.kind, joint = ?event.joint, bus = ?event.bus, "freezing the black box");
        let stamp = humantime::format_rfc3339_millis(SystemTime::now())
            .to_string()
            .replace([':', '-', '.'], "");
        let (robot, offset) = (self.robot.clone(), self.wall_offset_ns);
        let (shelf, cameras) = (&mut self.shelf, &self.thumbnails.cameras);
        let mut opened = None;
        let result = self.recorder.trigger(event, |e| {
            let path = opened.insert(shelf.new_partial(&stamp, &e.kind));
            BoxWriter::with_cameras(Durable::create(path)?, e, &robot, offset, cameras)
        });
        match result {
            Ok(true) => self.partial = opened,
            Ok(false) => {}
            Err(e) => {
                tracing::error!(path = ?opened, "cannot freeze a box: {e}");
                if !self.recorder.is_freezing() {
                    self.partial = None;
                }
            }
        }
    }

    /// Flushes the open box; names it whole once its window has passed (or `force`).
    fn housekeeping(&mut self, force: bool) {
        if self.states_missed > self.states_missed_logged {
            tracing::warn!(
                missed = self.states_missed - self.states_missed_logged,
                total = self.states_missed,
                wire_cycles_missed = self.wire_cycles_missed,
                "the recorder fell behind: joint-state frames overwritten unread"
            );
            self.states_missed_logged = self.states_missed;
        }
        if let Err(e) = self.recorder.flush() {
            self.given_up(&e);
        }
        self.finish(force);
    }

    /// Finishes the open box if its window has passed (or `force`), names it whole, trims the
    /// shelf.
    fn finish(&mut self, force: bool) {
        let Some(done) = self.recorder.finish_due(monotonic_ns(), force) else {
            return;
        };
        let Some(partial) = self.partial.take() else {
            return;
        };
        let result = done
            .map_err(anyhow::Error::from)
            .and_then(|mut w| Ok(std::io::Write::flush(&mut w)?))
            .and_then(|()| {
                let whole = shelf::whole_name(&partial);
                std::fs::rename(&partial, &whole)?;
                Ok(whole)
            });
        match result {
            Ok(whole) => tracing::info!(path = %whole.display(), "box frozen"),
            Err(e) => tracing::error!(path = %partial.display(), "box not finished: {e:#}"),
        }
        self.trim();
    }

    /// Keeps the shelf within its cap (the box being written stays).
    fn trim(&self) {
        let (removed, errors) = self
            .shelf
            .trim(self.disk_cap_bytes, self.partial.as_deref());
        for p in removed {
            tracing::warn!(path = %p.display(), "box removed: the disk cap is reached");
        }
        for e in errors {
            tracing::error!(dir = %self.shelf.dir().display(), "cannot remove an old box: {e}");
        }
    }
}

/// Makes whole every box a crash cut short.
fn recover_partials(shelf: &Shelf) {
    for p in shelf.partials() {
        match frozen::recover(&p) {
            Ok(r) if r.bad_chunks > 0 => tracing::error!(
                path = %r.path.display(), messages = r.messages, bad_chunks = r.bad_chunks,
                "a box cut short is recovered without its damaged chunks (the cut file kept as .mcap.cut)"
            ),
            Ok(r) => tracing::warn!(
                path = %r.path.display(), messages = r.messages, "a box cut short is recovered"
            ),
            Err(e) => tracing::error!(path = %p.display(), "cannot recover a box: {e}"),
        }
    }
}

fn wall_offset_ns() -> i128 {
    let wall = SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as i128);
    wall - monotonic_ns() as i128
}

fn record(process: &ProcessArgs, dir: Option<PathBuf>, robot: Option<&Path>) -> Result<()> {
    let Some(Started { config, shutdown }) = process.start::<BlackboxConfig>()? else {
        return Ok(());
    };
    let run_for = process.run_for()?;
    let dir = dir.unwrap_or(config.dir.clone());
    let shelf = Shelf::open(&dir).with_context(|| format!("opening {}", dir.display()))?;
    let s = |x: f64| (x * 1e9) as u64;
    let ring = Ring::new(
        s(config.ring_seconds),
        s(config.segment_seconds),
        (config.ring_megabytes * 1e6) as usize,
    );
    let window = Window {
        before_ns: s(config.before_seconds),
        after_ns: s(config.after_seconds),
        longest_ns: s(config.longest_box_seconds),
    };
    let description = match robot {
        Some(p) => body::RobotDescription::load(p)?,
        None => body::RobotDescription::nori_a3(),
    };
    let body = body::kinematics::Body::from_description(&description)?;
    let thumbs = &config.thumbnails;
    let cameras = if thumbs.every_s > 0.0 {
        thumbs.cameras.clone()
    } else {
        Vec::new()
    };
    let node = Plane::open(&process.domain, "blackbox")?;
    // A recorder killed before left its ports: free them before taking new ones.
    node.cleanup_dead();
    let inputs = Inputs::open(&node, &cameras)?;
    let mut rec = Recording {
        recorder: Recorder::new(ring, window),
        shelf,
        robot: std::fs::read_to_string("/etc/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_default(),
        wall_offset_ns: wall_offset_ns(),
        names: Names::default(),
        bus_count: 0,
        watch: Watch::since(monotonic_ns()),
        partial: None,
        disk_cap_bytes: (config.disk_megabytes * 1e6) as u64,
        last_state_seq: None,
        states_missed: 0,
        states_missed_logged: 0,
        last_wire_cycle: [None; telemetry::frames::MAX_BUSES],
        wire_cycles_missed: 0,
        last_scan_ns: 0,
        thumbnails: Thumbnails {
            every_ns: s(thumbs.every_s),
            maker: Thumbnailer::new(thumbs.width, thumbs.quality),
            last_ns: vec![None; cameras.len()],
            cameras,
            failed: 0,
        },
        tree: (config.transforms.hz > 0.0).then(|| FrameTree::new(body)),
        tree_every_ns: s(1.0 / config.transforms.hz.max(1e-3)),
        last_tree_ns: None,
    };
    let mut service = ServiceManager::from_env();
    service.ready(&format!(
        "recording; boxes in {}",
        rec.shelf.dir().display()
    ));
    // After READY, and beside the loop: nothing waits on a recovery, and the loop keeps
    // recording and telling the watchdog it lives while a long box is rewritten.
    let recovering = {
        let shelf = Shelf::open(rec.shelf.dir())?;
        std::thread::Builder::new()
            .name("recover".into())
            .spawn(move || recover_partials(&shelf))
            .context("starting the recovery")?
    };
    rec.trim();
    tracing::info!(dir = %rec.shelf.dir().display(), ring_s = config.ring_seconds, "recording the last minutes");
    let started = Instant::now();
    let mut ticker = Ticker::new(Duration::from_millis(10));
    let mut last_housekeeping = Instant::now();
    while !shutdown.load(std::sync::atomic::Ordering::Relaxed)
        && run_for.is_none_or(|d| started.elapsed() < d)
    {
        for t in rec.drain(&inputs) {
            // A box whose window has passed ends before a new event: the event opens its own.
            rec.finish(false);
            rec.trigger(&t);
        }
        // A new box copies the ring in steps, the plane drained between them.
        if let Err(e) = rec.recorder.pump(COPY_STEP) {
            rec.given_up(&e);
        }
        if last_housekeeping.elapsed() >= Duration::from_secs(1) {
            rec.housekeeping(false);
            last_housekeeping = Instant::now();
        }
        service.keepalive(Instant::now());
        ticker.wait();
    }
    service.stopping();
    let _ = recovering.join();
    rec.housekeeping(true);
    tracing::info!(counters = ?rec.recorder.counters, ring = ?rec.recorder.ring_stats(), "stopped");
    println!(
        "{}",
        serde_json::json!({
            "recorder": rec.recorder.counters,
            "ring": rec.recorder.ring_stats(),
            "joint_states_missed": rec.states_missed,
            "wire_cycles_missed": rec.wire_cycles_missed,
            "thumbnails_failed": rec.thumbnails.failed,
        })
    );
    Ok(())
}

fn list(dir: &Path, json: bool) -> Result<()> {
    for p in Shelf::open(dir)?.boxes() {
        let bytes = std::fs::read(&p).with_context(|| format!("reading {}", p.display()))?;
        let sum = blackbox::export::summary(&bytes);
        let event: Option<EventMessage> = sum
            .metadata
            .get("event")
            .and_then(|e| serde_json::from_str(e).ok());
        let name = p.file_name().map(|n| n.to_string_lossy().into_owned());
        let messages: usize = sum.per_topic.values().sum();
        if json {
            let v = serde_json::json!({
                "box": name, "path": p, "bytes": bytes.len(), "extent": sum.extent,
                "event": event, "span_s": sum.span_s, "messages": sum.per_topic,
            });
            println!("{v}");
        } else {
            let what = event.map_or("?".into(), |e| {
                format!("{} {}", e.kind, e.joint.or(e.bus).unwrap_or_default())
            });
            println!(
                "{}  {what}  {:.0} s  {messages} messages  {:.1} MB{}",
                name.unwrap_or_default(),
                sum.span_s,
                bytes.len() as f64 / 1e6,
                damage(&sum.extent)
            );
        }
    }
    Ok(())
}

/// What an operator is told of a box that is not whole.
fn damage(e: &frozen::Extent) -> String {
    match (e.complete, e.bad_chunks) {
        (true, 0) => String::new(),
        (false, 0) => " (cut short: every finished chunk read)".into(),
        (_, n) => format!(" ({n} damaged chunks not read)"),
    }
}

fn show(path: &Path) -> Result<()> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let sum = blackbox::export::summary(&bytes);
    println!("{}{}", path.display(), damage(&sum.extent));
    for (k, v) in &sum.metadata {
        println!("  {k}: {v}");
    }
    let messages: usize = sum.per_topic.values().sum();
    println!("  span: {:.1} s, {messages} messages", sum.span_s);
    for (topic, n) in &sum.per_topic {
        println!("    {topic}: {n}");
    }
    for t in &sum.triggers {
        println!("  trigger: {t}");
    }
    Ok(())
}

fn export(path: &Path, csv: Option<&Path>, mcap: Option<&Path>) -> Result<()> {
    if csv.is_none() && mcap.is_none() {
        bail!("say what to export: --csv FILE and/or --mcap FILE");
    }
    if let Some(out) = mcap {
        std::fs::copy(path, out).with_context(|| format!("copying to {}", out.display()))?;
    }
    if let Some(out) = csv {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let (text, side) = blackbox::export::joint_states_csv(&bytes);
        std::fs::write(out, text).with_context(|| format!("writing {}", out.display()))?;
        let sidecar = out.with_extension("meta.json");
        std::fs::write(&sidecar, side.to_string())
            .with_context(|| format!("writing {}", sidecar.display()))?;
    }
    Ok(())
}

fn save(domain: &str) -> Result<()> {
    let node = Plane::open(domain, "blackbox-save")?;
    let publisher = node.publisher(&plane::BLACKBOX_SAVE)?;
    let request = BlackboxSave {
        seq: 1,
        timestamp_ns: monotonic_ns(),
        pid: std::process::id(),
        reserved: 0,
    };
    // The recorder drains the plane every 10 ms; the sample lives only as long as its
    // publisher, so wait until no subscriber holds it unread.
    let receivers = publisher
        .send_copy(request)
        .map_err(telemetry::plane::PlaneError::Send)?;
    if receivers == 0 {
        bail!("no black box is recording on domain {domain:?} (is nori-blackbox running?)");
    }
    std::thread::sleep(Duration::from_millis(200));
    println!("asked the black box to save the last minutes");
    Ok(())
}
