//! `nori-record`, run as `nori record` and `nori dataset`: episodes from the state plane into
//! a LeRobot v3.0 dataset; recover a dataset after a crash, export episodes for the model lab.
//!
//! The process moves frames: joint-state and grip frames into a `recorder::Sampler`, a dataset
//! frame at every tick of the recording rate into a `recorder::EpisodeWriter`, which stages them
//! every flush interval and commits each episode at its end. With `--camera`, each tick also
//! takes each camera's newest JPEG (from its `mjpeg` stream, stored as the camera sent it), or
//! holds the last one when none is fresh. With `--lift` and `--base`, the lift's height and the
//! base's twist widen `observation.state` and `action` (19 wide on the A3) and the base's odometry
//! is recorded. Everything about files and crash safety lives in the library.

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use recorder::dataset::Settings;
use recorder::features::CameraMeta;
use recorder::{Dataset, Features, RecordError, Recovery, Sampler};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::plane::{self, CameraStream, FrameSub, Plane};

/// Options of `nori record`.
#[derive(Args, Debug)]
struct RecordArgs {
    /// Dataset directory (created if absent; an existing one is extended).
    #[arg(long)]
    dataset: PathBuf,
    /// What is demonstrated (LeRobot's task text).
    #[arg(long)]
    task: String,
    /// Frames per second.
    #[arg(long, default_value_t = 30)]
    fps: u32,
    /// Episodes to record.
    #[arg(long, default_value_t = 1)]
    episodes: u32,
    /// Length of an episode, s.
    #[arg(long, default_value_t = 10.0)]
    episode_s: f64,
    /// Pause between episodes (not recorded), s.
    #[arg(long, default_value_t = 0.0)]
    reset_s: f64,
    /// Frames are handed to the staging writer this often, ms (at most 1000). A crash loses the
    /// frames since the last hand-over and the part being written: with 500 ms, under 1 s.
    #[arg(long, default_value_t = 500)]
    flush_ms: u32,
    /// An episode a crash interrupted is dropped at start instead of completed from its parts.
    #[arg(long)]
    drop_unfinished: bool,
    /// `robot_type` in info.json.
    #[arg(long, default_value = "nori_a3")]
    robot_type: String,
    /// State-plane domain.
    #[arg(long, default_value = plane::DEFAULT_DOMAIN)]
    domain: String,
    /// Wait this long for the driver's layout and first frame, s.
    #[arg(long, default_value_t = 10.0)]
    wait_s: f64,
    /// Record this camera's video as `observation.images.<NAME>` (repeat for several; the
    /// camera must publish MJPEG: `nori-camera`).
    #[arg(long = "camera", value_name = "NAME")]
    cameras: Vec<String>,
    /// A camera image captured longer than this before a frame's tick is not fresh: the last
    /// one is held and `observation.camera_valid` is 0 for the frame, ms.
    #[arg(long, default_value_t = 100)]
    camera_stale_ms: u32,
    /// Record the lift's height (state) and goal (action) after the joints (from `nori-lift`).
    #[arg(long)]
    lift: bool,
    /// Record the base's measured and driven twist after the joints, and its odometry as
    /// `observation.odometry` (from `nori-base`).
    #[arg(long)]
    base: bool,
}

/// `nori dataset ...`.
#[derive(Subcommand, Debug)]
enum DatasetCommand {
    /// Repair what a crash left (as `nori record` does at start) and print what was done.
    Recover(RecoverArgs),
    /// Export episodes to the telemetry CSV format the model lab reads (one file per episode).
    ExportCsv(ExportArgs),
}

/// Options of `nori dataset recover`.
#[derive(Args, Debug)]
struct RecoverArgs {
    /// Dataset directory.
    dataset: PathBuf,
    /// Drop an unfinished episode instead of completing it from its flushed parts.
    #[arg(long)]
    drop_unfinished: bool,
}

/// Options of `nori dataset export-csv`.
#[derive(Args, Debug)]
struct ExportArgs {
    /// Dataset directory.
    dataset: PathBuf,
    /// Output directory (`episode-NNNNNN.csv` + `.meta.json` sidecars).
    out: PathBuf,
    /// Episodes to export (all when absent), e.g. `--episode 0 --episode 2`.
    #[arg(long = "episode")]
    episodes: Vec<i64>,
}

/// Runs `nori dataset ...`.
fn dataset(cmd: &DatasetCommand) -> Result<()> {
    match cmd {
        DatasetCommand::Recover(a) => {
            let reader = recorder::dataset::DatasetReader::open(&a.dataset)
                .with_context(|| format!("reading {}", a.dataset.display()))?;
            let settings = Settings {
                fps: reader.info.fps,
                robot_type: reader.info.robot_type.clone().unwrap_or_default(),
                data_files_size_in_mb: reader.info.data_files_size_in_mb,
                video_files_size_in_mb: reader.info.video_files_size_in_mb,
            };
            let (ds, recovery) =
                Dataset::open(&a.dataset, settings, reader.features, a.drop_unfinished)
                    .with_context(|| format!("recovering {}", a.dataset.display()))?;
            report_recovery(&recovery);
            println!(
                "{}",
                serde_json::json!({
                    "episodes": ds.episodes().len(),
                    "frames": ds.episodes().last().map_or(0, |e| e.dataset_to_index),
                    "recovered": recovery.recovered,
                    "dropped": recovery.dropped.iter().map(|(e, n, why)| serde_json::json!({"episode": e, "frames": n, "why": why})).collect::<Vec<_>>(),
                    "orphan_rows_removed": recovery.orphan_rows_removed,
                    "orphan_video_frames_removed": recovery.orphan_video_frames_removed,
                    "temporaries_removed": recovery.temporaries_removed,
                })
            );
            Ok(())
        }
        DatasetCommand::ExportCsv(a) => {
            let files = recorder::csv::export(&a.dataset, &a.out, &a.episodes)
                .with_context(|| format!("exporting {}", a.dataset.display()))?;
            eprintln!(
                "nori dataset export-csv: {} episode file(s) in {}",
                files.len(),
                a.out.display()
            );
            Ok(())
        }
    }
}

fn report_recovery(r: &Recovery) {
    for (e, n) in &r.recovered {
        eprintln!(
            "nori record: episode {e} was interrupted; completed from its {n} flushed frames"
        );
    }
    for (e, n, why) in &r.dropped {
        eprintln!("nori record: dropped the interrupted episode {e} ({n} frames): {why}");
    }
    if r.orphan_video_frames_removed > 0 {
        eprintln!(
            "nori record: cut {} video frames of an interrupted commit",
            r.orphan_video_frames_removed
        );
    }
    if r.orphan_rows_removed > 0 {
        eprintln!(
            "nori record: cut {} rows of an interrupted commit from the data file",
            r.orphan_rows_removed
        );
    }
}

/// Refuses options that cannot make a dataset.
fn check(args: &RecordArgs) -> Result<()> {
    if !(args.wait_s >= 0.0 && args.wait_s <= 3600.0) {
        bail!("--wait-s {} must be 0..=3600 seconds", args.wait_s);
    }
    if !(args.episode_s > 0.0 && args.episode_s.is_finite()) {
        bail!(
            "--episode-s {} must be a positive number of seconds",
            args.episode_s
        );
    }
    if !(args.reset_s >= 0.0 && args.reset_s.is_finite()) {
        bail!("--reset-s {} must be zero or more seconds", args.reset_s);
    }
    if args.flush_ms == 0 || args.flush_ms > 1000 {
        bail!(
            "--flush-ms {} must be 1..=1000: a crash may lose one flush interval",
            args.flush_ms
        );
    }
    if args.fps == 0 || args.fps > 1000 {
        bail!("--fps {} must be 1..=1000", args.fps);
    }
    for (i, name) in args.cameras.iter().enumerate() {
        if !telemetry::sensors::valid_camera_name(name) {
            bail!("--camera {name:?}: a camera name is 1 to 32 of a-z, 0-9 and _");
        }
        if args.cameras[..i].contains(name) {
            bail!("--camera {name} given twice");
        }
    }
    if args.camera_stale_ms == 0 || args.camera_stale_ms > 10_000 {
        bail!(
            "--camera-stale-ms {} must be 1..=10000",
            args.camera_stale_ms
        );
    }
    Ok(())
}

/// One recorded camera: its JPEG stream and its newest JPEG.
struct CameraFeed {
    name: String,
    jpegs: FrameSub,
    newest: Vec<u8>,
    /// JPEGs refused because their size is not the camera's (a restart with another
    /// configuration): the last good one is held instead.
    refused: u64,
}

impl CameraFeed {
    /// Takes in what the camera published since the last call: the newest JPEG of the
    /// recorded size is kept; returns its capture time.
    fn drain(&mut self, meta: Option<&CameraMeta>) -> Option<u64> {
        let mut captured = None;
        while let Ok(Some(sample)) = self.jpegs.receive() {
            let h = sample.user_header();
            if meta.is_some_and(|m| (h.width, h.height) != (m.width, m.height)) {
                self.refused += 1;
                continue;
            }
            self.newest.clear();
            self.newest.extend_from_slice(sample.payload());
            captured = Some(h.capture_ns);
        }
        captured
    }
}

/// Waits for each camera's first JPEG: its size and pixel format make the video feature.
fn first_images(
    feeds: &mut [CameraFeed],
    wait: Duration,
    stop: &AtomicBool,
) -> Result<Vec<CameraMeta>> {
    let deadline = Instant::now() + wait;
    let mut metas: Vec<Option<CameraMeta>> = vec![None; feeds.len()];
    while metas.iter().any(Option::is_none) {
        for (feed, meta) in feeds.iter_mut().zip(&mut metas) {
            if meta.is_none() && feed.drain(None).is_some() {
                let f = recorder::video::jpeg_format(&feed.newest).with_context(|| {
                    format!(
                        "camera {}: its JPEG has no frame header FFmpeg can name",
                        feed.name
                    )
                })?;
                *meta = Some(CameraMeta {
                    name: feed.name.clone(),
                    width: f.width,
                    height: f.height,
                    pix_fmt: f.pix_fmt.into(),
                });
            }
        }
        if stop.load(Ordering::Relaxed) {
            bail!("stopped while waiting for the cameras");
        }
        if Instant::now() >= deadline {
            let silent: Vec<&str> = (feeds.iter().zip(&metas))
                .filter(|(_, m)| m.is_none())
                .map(|(f, _)| f.name.as_str())
                .collect();
            bail!(
                "no JPEG from camera {} within --wait-s {} s (is nori-camera running for it, with an MJPEG source?)",
                silent.join(", "),
                wait.as_secs_f64()
            );
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    Ok(metas.into_iter().flatten().collect())
}

/// Records episodes until done or SIGINT/SIGTERM (which ends the current episode and keeps it).
fn record(args: &RecordArgs) -> Result<()> {
    check(args)?;
    let stop = telemetry::process::stop_flag().context("installing signal handlers")?;
    let node = Plane::open(&args.domain, &format!("nori-record-{}", std::process::id()))?;
    let mut inputs = Inputs::open(&node, &args.cameras)?;

    let wait = Duration::from_secs_f64(args.wait_s);
    let layout = plane::wait_for_layout(&inputs.layouts, &args.domain, wait, Some(&stop))?;
    let cameras = first_images(&mut inputs.feeds, wait, &stop)?;
    let features = Features::from_layout(&layout)
        .with_cameras(cameras)
        .with_body(args.lift, args.base);
    let settings = Settings {
        fps: args.fps,
        robot_type: args.robot_type.clone(),
        ..Settings::default()
    };
    let (mut ds, recovery) = Dataset::open(
        &args.dataset,
        settings,
        features.clone(),
        args.drop_unfinished,
    )
    .with_context(|| format!("opening the dataset {}", args.dataset.display()))?;
    report_recovery(&recovery);

    let mut recording = Recording::new(args, &stop, inputs, features);
    recording.announce();
    let mut summary = Vec::new();
    for episode in 0..args.episodes {
        if recording.stopped() {
            break;
        }
        if episode > 0 && args.reset_s > 0.0 {
            recording.pause_for_reset();
        }
        recording.await_first_reads(episode)?;
        if recording.stopped() {
            break;
        }
        if let Some(row) = recording.record_episode(&mut ds)? {
            summary.push(row);
        }
    }
    println!(
        "{}",
        serde_json::json!({"dataset": args.dataset, "episodes": summary,
            "total_episodes": ds.episodes().len(), "total_frames": ds.episodes().last().map_or(0, |e| e.dataset_to_index)})
    );
    Ok(())
}

/// What is recorded, as the plane carries it: the joints' state and layout, grip forces,
/// the lift's and the base's state, and the cameras' JPEGs.
struct Inputs {
    states: plane::Sub<telemetry::JointState>,
    layouts: plane::Sub<telemetry::frames::JointLayout>,
    grips: plane::Sub<telemetry::frames::GripFrame>,
    lifts: plane::Sub<telemetry::motion::LiftState>,
    bases: plane::Sub<telemetry::motion::BaseState>,
    feeds: Vec<CameraFeed>,
}

impl Inputs {
    /// Subscribes to all of it, with the cameras named.
    fn open(node: &Plane, cameras: &[String]) -> Result<Inputs> {
        let states = node.subscriber(&plane::JOINT_STATE)?;
        let layouts = node.subscriber(&plane::LAYOUT)?;
        let grips = node.subscriber(&plane::GRIP)?;
        let lifts = node.subscriber(&plane::LIFT_STATE)?;
        let bases = node.subscriber(&plane::BASE_STATE)?;
        let feeds = cameras
            .iter()
            .map(|name| {
                Ok(CameraFeed {
                    name: name.clone(),
                    jpegs: node.camera_subscriber(name, CameraStream::Mjpeg)?,
                    newest: Vec::new(),
                    refused: 0,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Inputs {
            states,
            layouts,
            grips,
            lifts,
            bases,
            feeds,
        })
    }

    /// Hands the sampler all that came since the last call (the cameras described by
    /// `cameras`); the newest layout, if one came.
    fn drain(
        &mut self,
        sampler: &mut Sampler,
        cameras: &[CameraMeta],
    ) -> Option<telemetry::frames::JointLayout> {
        while let Some(s) = plane::next(&self.states) {
            sampler.on_state(&s);
        }
        while let Some(g) = plane::next(&self.grips) {
            sampler.on_grip(&g);
        }
        while let Some(l) = plane::next(&self.lifts) {
            sampler.on_lift(&l);
        }
        while let Some(b) = plane::next(&self.bases) {
            sampler.on_base(&b);
        }
        for (i, (feed, meta)) in self.feeds.iter_mut().zip(cameras).enumerate() {
            if let Some(captured) = feed.drain(Some(meta)) {
                sampler.on_camera(i, captured);
            }
        }
        plane::newest(&self.layouts)
    }
}

/// A recording under way: what it records, the sampler that makes frames of it, and its
/// rhythm.
struct Recording<'a> {
    args: &'a RecordArgs,
    stop: &'a AtomicBool,
    inputs: Inputs,
    features: Features,
    sampler: Sampler,
    period_ns: u64,
    /// Frames between flushes of an episode's data (staged in the background).
    flush_every: usize,
    frames_per_episode: usize,
}

impl<'a> Recording<'a> {
    fn new(
        args: &'a RecordArgs,
        stop: &'a AtomicBool,
        inputs: Inputs,
        features: Features,
    ) -> Recording<'a> {
        let period_ns = 1_000_000_000 / u64::from(args.fps);
        let sampler = Sampler::new(features.clone(), period_ns)
            .with_camera_staleness(u64::from(args.camera_stale_ms) * 1_000_000);
        let flush_every = ((u64::from(args.fps) * u64::from(args.flush_ms)) / 1000).max(1) as usize;
        let frames_per_episode = (args.episode_s * f64::from(args.fps)).round().max(1.0) as usize;
        Recording {
            args,
            stop,
            inputs,
            features,
            sampler,
            period_ns,
            flush_every,
            frames_per_episode,
        }
    }

    /// Whether SIGINT or SIGTERM came.
    fn stopped(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }

    /// Hands the sampler what came; the newest layout, if one came.
    fn drain(&mut self) -> Option<telemetry::frames::JointLayout> {
        self.inputs.drain(&mut self.sampler, &self.features.cameras)
    }

    /// Says what is recorded, how and where.
    fn announce(&self) {
        let (args, features) = (self.args, &self.features);
        eprintln!(
            "nori record: {} joints ({}){}, {} camera(s) ({}), {} fps, {} episode(s) of {} frames into {} (staged every {} frames, in the background)",
            features.joints.len(),
            features.joint_names().join(", "),
            features
                .body
                .iter()
                .map(|a| format!(" + {}", a.name()))
                .collect::<String>(),
            features.cameras.len(),
            features
                .cameras
                .iter()
                .map(|c| format!("{} {}x{} {}", c.name, c.width, c.height, c.pix_fmt))
                .collect::<Vec<_>>()
                .join(", "),
            args.fps,
            args.episodes,
            self.frames_per_episode,
            args.dataset.display(),
            self.flush_every
        );
    }

    /// The pause between episodes (`--reset-s`), the inputs kept drained meanwhile.
    fn pause_for_reset(&mut self) {
        let resume = Instant::now() + Duration::from_secs_f64(self.args.reset_s);
        while Instant::now() < resume && !self.stopped() {
            self.drain();
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    /// Waits until every joint and grip force was read (or a stop): an episode starts only
    /// then, as a held value needs a first read to hold.
    fn await_first_reads(&mut self, episode: u32) -> Result<()> {
        let deadline = Instant::now() + Duration::from_secs_f64(self.args.wait_s);
        loop {
            self.drain();
            let unread = self.sampler.unread();
            if unread.is_empty() || self.stopped() {
                return Ok(());
            }
            if Instant::now() >= deadline {
                bail!(
                    "never read within --wait-s {} s: {} (a servo not answering, no supervisor publishing grip force, a camera silent, or the lift or base not running); nothing recorded for episode {episode}",
                    self.args.wait_s,
                    unread.join(", ")
                );
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    /// Records one episode into `ds`, a frame every period, until it is long enough, a stop,
    /// or the video falling behind; its summary once committed.
    fn record_episode(&mut self, ds: &mut Dataset) -> Result<Option<serde_json::Value>> {
        let mut writer = ds.begin_episode(&self.args.task, self.flush_every)?;
        let start = monotonic_ns();
        let mut late_max_ns = 0u64;
        let mut missing = 0usize;
        let mut held = 0usize;
        let mut flush_max = Duration::ZERO;
        while writer.len() < self.frames_per_episode && !self.stopped() {
            if let Some(l) = self.drain() {
                if Features::from_layout(&l).joints != self.features.joints {
                    bail!("the driver's joint layout changed during the recording (driver restarted with another configuration?)");
                }
            }
            let tick = start + writer.len() as u64 * self.period_ns;
            let now = monotonic_ns();
            if now < tick {
                std::thread::sleep(Duration::from_nanos((tick - now).min(1_000_000)));
                continue;
            }
            late_max_ns = late_max_ns.max(now - tick);
            let frame = self
                .sampler
                .frame(now)
                .context("a joint read before the episode began is no longer known")?;
            missing += frame.missing_joints();
            held += frame.held_images();
            let images = self.inputs.feeds.iter().map(|f| f.newest.clone()).collect();
            let t0 = Instant::now();
            match writer.push_with_images(frame, images) {
                Ok(true) => flush_max = flush_max.max(t0.elapsed()),
                Ok(false) => {}
                Err(e @ RecordError::VideoBehind { .. }) => {
                    eprintln!("nori record: {e}");
                    break;
                }
                Err(e) => return Err(e.into()),
            }
        }
        let frames = writer.len();
        let t0 = Instant::now();
        let row = writer.finish()?;
        let commit = t0.elapsed();
        let Some(row) = row else {
            return Ok(None);
        };
        eprintln!(
            "nori record: episode {} committed: {} frames, latest tick {:.1} ms late, {} missing joint samples, {} held images, slowest flush hand-over {:.1} ms, commit {:.1} ms",
            row.episode_index,
            frames,
            late_max_ns as f64 * 1e-6,
            missing,
            held,
            flush_max.as_secs_f64() * 1e3,
            commit.as_secs_f64() * 1e3
        );
        Ok(Some(serde_json::json!({
            "episode": row.episode_index, "frames": frames, "max_tick_late_ms": late_max_ns as f64 * 1e-6,
            "missing_joint_samples": missing, "held_images": held,
            "refused_images": self.inputs.feeds.iter().map(|f| f.refused).sum::<u64>(),
            "max_flush_ms": flush_max.as_secs_f64() * 1e3,
            "commit_ms": commit.as_secs_f64() * 1e3,
        })))
    }
}

/// `nori-record`: demonstrations into LeRobot datasets (run as `nori record` and `nori dataset`).
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Record episodes from the state plane into a LeRobot v3.0 dataset.
    Record(RecordArgs),
    /// Work on a recorded dataset.
    #[command(subcommand)]
    Dataset(DatasetCommand),
}

fn main() -> Result<()> {
    match &Cli::parse().command {
        Command::Record(a) => record(a),
        Command::Dataset(d) => dataset(d),
    }
}
