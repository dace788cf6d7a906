//! `nori bench record-video`: what recording the cameras costs the robot. Cameras stream as
//! deployed (`nori-camera` processes fed MJPEG at their rate, [`crate::cameras::CameraLoad`]);
//! a stand-in driver publishes an eight-joint arm's layout, joint states and grip frames at
//! 200 Hz (the recorder's inputs; the driver's own cost is `nori bench driver-rate`). The
//! baseline, in the same run, is the cameras streaming with nobody recording; then `nori record`
//! records one episode from every camera, and its CPU (FFmpeg's included: the recorder waits
//! for its FFmpegs, so their time is in its children's account) and peak resident sets (its own
//! and each FFmpeg's, which run one at a time at the commit) are reported beside the cameras'.
//! An FFmpeg's resident set is mostly its shared libraries' clean pages (the kernel can drop
//! them); its anonymous memory (`RssAnon`, polled) is reported too.

use crate::cameras::CameraLoad;
use anyhow::{bail, Context, Result};
use clap::Args;
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::frames::{
    GripFrame, GripSample, JointInfo, JointLayout, JointRole, JointSample, JointState,
};
use telemetry::plane::{self, publish, Plane};

/// Options of `nori bench record-video`.
#[derive(Args, Debug)]
pub struct RecordVideoArgs {
    /// Cameras streaming and recorded.
    #[arg(long, default_value_t = 4)]
    cameras: usize,
    /// Camera width, px.
    #[arg(long, default_value_t = 1280)]
    camera_width: u32,
    /// Camera height, px.
    #[arg(long, default_value_t = 720)]
    camera_height: u32,
    /// Camera and recording rate, frames per second.
    #[arg(long, default_value_t = 30)]
    fps: u32,
    /// Length of the baseline and of the recorded episode, s.
    #[arg(long, default_value_t = 20.0)]
    seconds: f64,
}

/// Publishes what a driver and a supervisor would for one arm until `stop`.
fn stand_in_driver(domain: String, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<Result<()>> {
    std::thread::spawn(move || {
        let node = Plane::open(&domain, "bench-stand-in-driver")?;
        let layouts = node.publisher(&plane::LAYOUT)?;
        let states = node.publisher(&plane::JOINT_STATE)?;
        let grips = node.publisher(&plane::GRIP)?;
        let joints = 8u32;
        let mut layout = JointLayout {
            joint_count: joints,
            bus_count: 1,
            ..JointLayout::default()
        };
        for i in 0..joints as usize {
            let gripper = i + 1 == joints as usize;
            let mut j = JointInfo {
                role: if gripper {
                    JointRole::Gripper
                } else {
                    JointRole::Joint
                } as u8,
                id: i as u8 + 1,
                model: 777,
                range_rad: [-2.0, 2.0],
                ..JointInfo::default()
            };
            j.set_name(&format!("joint_{i}"));
            layout.joints[i] = j;
        }
        let mut seq = 0u64;
        let mut next = Instant::now();
        while !stop.load(Ordering::Relaxed) {
            if seq.is_multiple_of(200) {
                publish(&layouts, &layout)?;
            }
            seq += 1;
            let now = monotonic_ns();
            let mut state = JointState {
                seq,
                timestamp_ns: now,
                joint_count: joints,
                ..JointState::default()
            };
            for (i, s) in state.joints[..joints as usize].iter_mut().enumerate() {
                *s = JointSample {
                    position_rad: (seq as f32 * 0.005 + i as f32).sin(),
                    temperature_c: 30.0,
                    voltage_v: 12.0,
                    valid: 1,
                    ..JointSample::default()
                };
            }
            publish(&states, &state)?;
            let mut grip = GripFrame {
                state_seq: seq,
                timestamp_ns: now,
                gripper_count: 1,
                ..GripFrame::default()
            };
            grip.grippers[0] = GripSample {
                joint: joints as u8 - 1,
                valid: 1,
                force: 0.2,
                ..GripSample::default()
            };
            publish(&grips, &grip)?;
            next += Duration::from_millis(5);
            std::thread::sleep(next.saturating_duration_since(Instant::now()));
        }
        Ok(())
    })
}

fn dir_bytes(dir: &Path) -> u64 {
    std::fs::read_dir(dir)
        .map(|d| {
            d.flatten()
                .map(|e| {
                    let p = e.path();
                    if p.is_dir() {
                        dir_bytes(&p)
                    } else {
                        e.metadata().map_or(0, |m| m.len())
                    }
                })
                .sum()
        })
        .unwrap_or(0)
}

/// `nori record` recording one episode of `args.seconds` from the `cameras` named into
/// `dataset`.
fn record_command(
    args: &RecordVideoArgs,
    domain: &str,
    dataset: &Path,
    cameras: &[String],
) -> Result<Command> {
    let mut cmd = Command::new(stack::sibling("nori")?);
    cmd.args([
        "record",
        "--domain",
        domain,
        "--task",
        "bench",
        "--episodes",
        "1",
    ])
    .args([
        "--fps",
        &args.fps.to_string(),
        "--episode-s",
        &args.seconds.to_string(),
    ])
    .arg("--dataset")
    .arg(dataset);
    for n in cameras {
        cmd.args(["--camera", n]);
    }
    Ok(cmd)
}

/// The memory the recorder and its FFmpegs held at their peaks.
struct RecordingPeaks {
    /// The recorder's peak RSS, MB.
    recorder_rss: f64,
    /// Per FFmpeg: (peak RSS, peak anonymous RSS), MB.
    ffmpeg: std::collections::BTreeMap<u32, (f64, f64)>,
}

/// Samples the recorder's and its FFmpegs' memory every 20 ms until the recorder exits.
fn watch_recording(rec: &mut std::process::Child) -> Result<RecordingPeaks> {
    let mut peaks = RecordingPeaks {
        recorder_rss: 0.0,
        ffmpeg: std::collections::BTreeMap::new(),
    };
    while rec.try_wait()?.is_none() {
        peaks.recorder_rss = peaks
            .recorder_rss
            .max(bench::peak_rss_mb(rec.id()).unwrap_or(0.0));
        for pid in bench::children_of(rec.id()) {
            let e = peaks.ffmpeg.entry(pid).or_insert((0.0, 0.0));
            e.0 = e.0.max(bench::peak_rss_mb(pid).unwrap_or(0.0));
            e.1 = e.1.max(bench::rss_anon_mb(pid).unwrap_or(0.0));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Ok(peaks)
}

pub fn run(args: &RecordVideoArgs) -> Result<()> {
    if args.cameras == 0 || args.seconds.is_nan() || args.seconds < 2.0 {
        bail!("--cameras must be at least 1 and --seconds at least 2");
    }
    let domain = format!("nori_bench_record_{}", std::process::id());
    let load = CameraLoad::start(
        args.cameras,
        args.camera_width,
        args.camera_height,
        args.fps,
        &domain,
    )?;
    let names: Vec<String> = sim::RobotDescription::nori_a3()
        .camera
        .iter()
        .take(args.cameras)
        .map(|c| c.name.clone())
        .collect();
    let stop = Arc::new(AtomicBool::new(false));
    let driver = stand_in_driver(domain.clone(), stop.clone());
    load.feed(true);
    std::thread::sleep(Duration::from_secs(1));

    // Baseline: the cameras streaming, nobody recording.
    let (c0, t0) = (load.cpu_seconds(), Instant::now());
    std::thread::sleep(Duration::from_secs_f64(args.seconds));
    let capture_only = (load.cpu_seconds() - c0) / t0.elapsed().as_secs_f64();

    // One episode recorded from every camera.
    let dataset = std::env::temp_dir().join(format!("nori-bench-record-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dataset);
    let mut cmd = record_command(args, &domain, &dataset, &names)?;
    let children_before = bench::children_cpu_seconds().context("/proc/self/stat")?;
    let (c1, t1) = (load.cpu_seconds(), Instant::now());
    let mut rec = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .context("starting nori record")?;
    let RecordingPeaks {
        recorder_rss,
        ffmpeg,
    } = watch_recording(&mut rec)?;
    let wall = t1.elapsed().as_secs_f64();
    let capture_while_recording = (load.cpu_seconds() - c1) / wall;
    let output = rec.wait_with_output()?;
    let recorder_cpu = bench::children_cpu_seconds().context("/proc/self/stat")? - children_before;
    stop.store(true, Ordering::Relaxed);
    driver
        .join()
        .map_err(|_| anyhow::anyhow!("the stand-in driver panicked"))??;
    if !output.status.success() {
        bail!("nori record failed ({})", output.status);
    }
    let report: serde_json::Value = serde_json::from_slice(&output.stdout)?;
    let episode = &report["episodes"][0];
    let video_bytes = dir_bytes(&dataset.join("videos"));
    let n = args.cameras as f64;
    let out = serde_json::json!({
        "cameras": args.cameras,
        "width": args.camera_width,
        "height": args.camera_height,
        "fps": args.fps,
        "jpeg_bytes": load.jpeg_bytes,
        "episode_s": args.seconds,
        "frames": episode["frames"],
        "held_images": episode["held_images"],
        "commit_ms": episode["commit_ms"],
        "capture_only_percent_of_a_core_per_camera": 100.0 * capture_only / n,
        "capture_while_recording_percent_of_a_core_per_camera": 100.0 * capture_while_recording / n,
        "recorder_with_ffmpeg_percent_of_a_core_per_camera": 100.0 * recorder_cpu / wall / n,
        "ratio_capture_and_record_to_capture": (capture_while_recording + recorder_cpu / wall) / capture_only.max(1e-9),
        "recorder_peak_rss_mb": recorder_rss,
        "ffmpeg_runs": ffmpeg.len(),
        "ffmpeg_peak_rss_mb": ffmpeg.values().map(|m| m.0).fold(0.0, f64::max),
        "ffmpeg_peak_rss_anon_mb": ffmpeg.values().map(|m| m.1).fold(0.0, f64::max),
        "camera_peak_rss_mb": load.peak_rss_mb(),
        "video_mb_per_camera_minute": video_bytes as f64 / 1e6 / n / (args.seconds / 60.0),
        "recording_wall_s": wall,
    });
    let _ = std::fs::remove_dir_all(&dataset);
    println!("{out}");
    eprintln!(
        "record-video: {} cameras {}x{} at {} fps, an episode of {} s ({} frames, {} held images, commit {:.0} ms)\n\
         capture only: {:.1} % of a core per camera (baseline)\n\
         capture while recording: {:.1} %, recorder with its FFmpegs: {:.1} % per camera; (capture + record) / capture = {:.2}\n\
         peak RSS: recorder {:.1} MB; {} FFmpeg runs at the commit, one at a time, at most {:.1} MB ({:.1} MB anonymous); cameras {:.1?} MB; video {:.0} MB per camera-minute",
        args.cameras, args.camera_width, args.camera_height, args.fps, args.seconds,
        out["frames"], out["held_images"], out["commit_ms"].as_f64().unwrap_or(f64::NAN),
        100.0 * capture_only / n,
        100.0 * capture_while_recording / n,
        100.0 * recorder_cpu / wall / n,
        out["ratio_capture_and_record_to_capture"].as_f64().unwrap_or(f64::NAN),
        recorder_rss,
        ffmpeg.len(),
        out["ffmpeg_peak_rss_mb"].as_f64().unwrap_or(f64::NAN),
        out["ffmpeg_peak_rss_anon_mb"].as_f64().unwrap_or(f64::NAN),
        load.peak_rss_mb(),
        out["video_mb_per_camera_minute"].as_f64().unwrap_or(f64::NAN)
    );
    Ok(())
}
