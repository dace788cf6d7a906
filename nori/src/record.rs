//! `nori record`: episodes from the state plane into a LeRobot v3.0 dataset; `nori dataset`:
//! recover a dataset after a crash, export episodes for the model lab.
//!
//! The process moves frames: joint-state and grip frames into a `recorder::Sampler`, a dataset
//! frame at every tick of the recording rate into a `recorder::EpisodeWriter`, which stages them
//! every flush interval and commits each episode at its end. Everything about files and crash
//! safety lives in the `recorder` crate.

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use recorder::dataset::Settings;
use recorder::{Dataset, Features, Recovery, Sampler};
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::plane::{self, Plane};

/// Options of `nori record`.
#[derive(Args, Debug)]
pub struct RecordArgs {
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
}

/// `nori dataset ...`.
#[derive(Subcommand, Debug)]
pub enum DatasetCommand {
    /// Repair what a crash left (as `nori record` does at start) and print what was done.
    Recover(RecoverArgs),
    /// Export episodes to the telemetry CSV format the model lab reads (one file per episode).
    ExportCsv(ExportArgs),
}

/// Options of `nori dataset recover`.
#[derive(Args, Debug)]
pub struct RecoverArgs {
    /// Dataset directory.
    dataset: PathBuf,
    /// Drop an unfinished episode instead of completing it from its flushed parts.
    #[arg(long)]
    drop_unfinished: bool,
}

/// Options of `nori dataset export-csv`.
#[derive(Args, Debug)]
pub struct ExportArgs {
    /// Dataset directory.
    dataset: PathBuf,
    /// Output directory (`episode-NNNNNN.csv` + `.meta.json` sidecars).
    out: PathBuf,
    /// Episodes to export (all when absent), e.g. `--episode 0 --episode 2`.
    #[arg(long = "episode")]
    episodes: Vec<i64>,
}

/// Runs `nori dataset ...`.
pub fn dataset(cmd: &DatasetCommand) -> Result<()> {
    match cmd {
        DatasetCommand::Recover(a) => {
            let reader = recorder::dataset::DatasetReader::open(&a.dataset)
                .with_context(|| format!("reading {}", a.dataset.display()))?;
            let settings = Settings {
                fps: reader.info.fps,
                robot_type: reader.info.robot_type.clone().unwrap_or_default(),
                data_files_size_in_mb: reader.info.data_files_size_in_mb,
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
    Ok(())
}

/// Records episodes until done or SIGINT/SIGTERM (which ends the current episode and keeps it).
pub fn record(args: &RecordArgs) -> Result<()> {
    check(args)?;
    let stop = telemetry::process::stop_flag().context("installing signal handlers")?;
    let node = Plane::open(&args.domain, &format!("nori-record-{}", std::process::id()))?;
    let states = node.subscriber(&plane::JOINT_STATE)?;
    let layouts = node.subscriber(&plane::LAYOUT)?;
    let grips = node.subscriber(&plane::GRIP)?;

    let wait = Duration::from_secs_f64(args.wait_s);
    let layout = crate::plane_tools::wait_for_layout(&layouts, &args.domain, wait, Some(&stop))?;
    let features = Features::from_layout(&layout);
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

    let period_ns = 1_000_000_000 / u64::from(args.fps);
    let mut sampler = Sampler::new(features.clone(), period_ns);
    let flush_every = ((u64::from(args.fps) * u64::from(args.flush_ms)) / 1000).max(1) as usize;
    let frames_per_episode = (args.episode_s * f64::from(args.fps)).round().max(1.0) as usize;
    eprintln!(
        "nori record: {} joints ({}), {} fps, {} episode(s) of {} frames into {} (staged every {} frames, in the background)",
        features.joints.len(),
        features.joint_names().join(", "),
        args.fps,
        args.episodes,
        frames_per_episode,
        args.dataset.display(),
        flush_every
    );
    let drain = |sampler: &mut Sampler| {
        while let Some(s) = plane::next(&states) {
            sampler.on_state(&s);
        }
        while let Some(g) = plane::next(&grips) {
            sampler.on_grip(&g);
        }
        plane::newest(&layouts)
    };
    let mut summary = Vec::new();
    for episode in 0..args.episodes {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        if episode > 0 && args.reset_s > 0.0 {
            let resume = Instant::now() + Duration::from_secs_f64(args.reset_s);
            while Instant::now() < resume && !stop.load(Ordering::Relaxed) {
                drain(&mut sampler);
                std::thread::sleep(Duration::from_millis(1));
            }
        }
        // An episode starts once every joint and grip force was read: a held value needs a
        // first read to hold.
        let deadline = Instant::now() + wait;
        loop {
            drain(&mut sampler);
            let unread = sampler.unread();
            if unread.is_empty() || stop.load(Ordering::Relaxed) {
                break;
            }
            if Instant::now() >= deadline {
                bail!(
                    "never read within --wait-s {} s: {} (a servo not answering, or no supervisor publishing grip force); nothing recorded for episode {episode}",
                    args.wait_s,
                    unread.join(", ")
                );
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        if stop.load(Ordering::Relaxed) {
            break;
        }
        let mut writer = ds.begin_episode(&args.task, flush_every)?;
        let start = monotonic_ns();
        let mut late_max_ns = 0u64;
        let mut missing = 0usize;
        let mut flush_max = Duration::ZERO;
        while writer.len() < frames_per_episode && !stop.load(Ordering::Relaxed) {
            if let Some(l) = drain(&mut sampler) {
                if Features::from_layout(&l) != features {
                    bail!("the driver's joint layout changed during the recording (driver restarted with another configuration?)");
                }
            }
            let tick = start + writer.len() as u64 * period_ns;
            let now = monotonic_ns();
            if now < tick {
                std::thread::sleep(Duration::from_nanos((tick - now).min(1_000_000)));
                continue;
            }
            late_max_ns = late_max_ns.max(now - tick);
            let frame = sampler
                .frame(now)
                .context("a joint read before the episode began is no longer known")?;
            missing += frame.missing_joints();
            let t0 = Instant::now();
            if writer.push(frame)? {
                flush_max = flush_max.max(t0.elapsed());
            }
        }
        let frames = writer.len();
        let t0 = Instant::now();
        let row = writer.finish()?;
        let commit = t0.elapsed();
        if let Some(row) = row {
            eprintln!(
                "nori record: episode {} committed: {} frames, latest tick {:.1} ms late, {} missing joint samples, slowest flush hand-over {:.1} ms, commit {:.1} ms",
                row.episode_index,
                frames,
                late_max_ns as f64 * 1e-6,
                missing,
                flush_max.as_secs_f64() * 1e3,
                commit.as_secs_f64() * 1e3
            );
            summary.push(serde_json::json!({
                "episode": row.episode_index, "frames": frames, "max_tick_late_ms": late_max_ns as f64 * 1e-6,
                "missing_joint_samples": missing, "max_flush_ms": flush_max.as_secs_f64() * 1e3,
                "commit_ms": commit.as_secs_f64() * 1e3,
            }));
        }
    }
    println!(
        "{}",
        serde_json::json!({"dataset": args.dataset, "episodes": summary,
            "total_episodes": ds.episodes().len(), "total_frames": ds.episodes().last().map_or(0, |e| e.dataset_to_index)})
    );
    Ok(())
}
