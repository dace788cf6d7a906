//! `nori record` on the live stack (simulator, supervisor, driver): datasets an independent
//! reader (pyarrow, pandas, numpy: `tests/python/check_lerobot_dataset.py`) accepts as LeRobot
//! v3.0, the CSV export read by the model lab's own reader, and `kill -9` of the recorder at
//! chosen and at random moments: at most the last flush interval lost, never an unreadable file.
//!
//! The tests take turns (a mutex): each runs a stack and a recorder on two cores.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{binary, lerobot_check, serial, wait_for, ArmStack, Proc, Rng, SchedulingProbe};
use std::path::Path;
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use telemetry::clock::monotonic_ns;
use telemetry::frames::STATE_FLAG_SAFE_STATE;
use telemetry::plane::{self, newest, publish, Plane};
use telemetry::GoalFrame;

const FPS: u32 = 30;
const ELBOW: usize = 3;
const JOINTS: u32 = 8;

/// Waves the elbow (as a policy would) until `stop`, so the recording has motion in it.
fn wave(domain: String, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<()> {
    std::thread::spawn(move || {
        let node = Plane::open(&domain, "test-waver").unwrap();
        let goals = node.publisher(&plane::GOALS).unwrap();
        let t0 = monotonic_ns();
        let mut seq = 0;
        while !stop.load(Ordering::Relaxed) {
            let t = (monotonic_ns() - t0) as f64 * 1e-9;
            seq += 1;
            let mut g = GoalFrame {
                seq,
                joint_count: JOINTS,
                mask: 1 << ELBOW,
                timestamp_ns: monotonic_ns(),
                ..GoalFrame::default()
            };
            g.position_rad[ELBOW] = (-1.0 + 0.5 * (t * 2.0).sin()) as f32;
            let _ = publish(&goals, &g);
            std::thread::sleep(Duration::from_millis(10));
        }
    })
}

fn wait_driving(domain: &str) {
    let node = Plane::open(domain, "test-watch").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    wait_for(
        Duration::from_secs(20),
        "the driver driving under supervision",
        || {
            newest(&states).filter(|s| {
                s.flags & STATE_FLAG_SAFE_STATE == 0
                    && s.joint_count == JOINTS
                    && s.joints().iter().all(|j| j.is_valid())
            })
        },
    );
}

fn record_args<'a>(domain: &'a str, dataset: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let mut a = vec![
        "record",
        "--domain",
        domain,
        "--dataset",
        dataset,
        "--task",
        "wave the left elbow",
        "--fps",
        "30",
    ];
    a.extend_from_slice(extra);
    a
}

fn recover(dataset: &Path) -> serde_json::Value {
    let out = Command::new(binary("nori"))
        .args(["dataset", "recover"])
        .arg(dataset)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "nori dataset recover: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

fn staged_parts(dataset: &Path, episode: usize) -> usize {
    std::fs::read_dir(dataset.join(format!(".nori-staging/episode-{episode:06}")))
        .map(|d| {
            d.flatten()
                .filter(|e| e.path().extension().is_some_and(|x| x == "parquet"))
                .count()
        })
        .unwrap_or(0)
}

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_millis() as u64
}

#[test]
fn recorded_episodes_read_as_lerobot_v3_and_export_to_the_model_lab() {
    let _turn = serial();
    let stack = ArmStack::start("record", &[]);
    wait_driving(&stack.domain);
    let stop = Arc::new(AtomicBool::new(false));
    let waver = wave(stack.domain.clone(), stop.clone());
    let dataset = stack.dir.join("dataset");
    let ds = dataset.to_str().unwrap();
    let out = Command::new(binary("nori"))
        .args(record_args(
            &stack.domain,
            ds,
            &["--episodes", "2", "--episode-s", "2", "--reset-s", "0.5"],
        ))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "nori record: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    eprintln!("nori record: {report}");
    assert_eq!(report["total_frames"], 2 * 2 * FPS);
    // A second session extends the dataset (LeRobot's resume), with a second task.
    let out = Command::new(binary("nori"))
        .args([
            "record",
            "--domain",
            &stack.domain,
            "--dataset",
            ds,
            "--task",
            "hold still",
            "--episode-s",
            "1",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stop.store(true, Ordering::Relaxed);
    waver.join().unwrap();

    if let Some(summary) = lerobot_check(&dataset, &["--episodes", "3", "--closed"]) {
        eprintln!("LeRobot check: {summary}");
        assert_eq!(summary["lengths"], serde_json::json!([60, 60, 30]));
        assert_eq!(summary["grippers"], serde_json::json!(["left_gripper"]));
        assert_eq!(
            summary["tasks"],
            serde_json::json!(["wave the left elbow", "hold still"])
        );
        assert_eq!(summary["joints"].as_array().unwrap().len(), JOINTS as usize);
        assert!(
            summary["state_span_rad"].as_f64().unwrap() > 0.3,
            "the wave is in the data: {summary}"
        );
        // A joint is held (marked in observation.joint_valid) only when all its reads failed
        // for a whole frame period: rare, though a loaded two-core machine can make the
        // simulator late enough.
        assert!(
            summary["missing_fraction"].as_f64().unwrap() < 0.05,
            "{summary}"
        );
        if !summary["hf_datasets_loaded"].is_null() {
            assert_eq!(
                summary["hf_datasets_loaded"], 150,
                "LeRobot's loader reads every frame"
            );
        }
    }

    // The model lab reads the export with its own reader: one run per episode.
    let csv = stack.dir.join("csv");
    let out = Command::new(binary("nori"))
        .args(["dataset", "export-csv", ds, csv.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lab = model_lab::data::load(&csv).unwrap();
    assert_eq!(lab.motors, (0..i64::from(JOINTS)).collect::<Vec<_>>());
    assert_eq!(lab.t.len(), 150, "every frame of the three episodes");
    assert_eq!(lab.segment_starts, [0, 60, 120], "each episode its own run");
    let elbow = ELBOW;
    let goals = &lab.goal[elbow];
    let positions = &lab.position[elbow];
    let finite = goals
        .iter()
        .chain(positions)
        .filter(|x| x.is_finite())
        .count();
    assert!(
        finite as f64 >= 0.95 * 2.0 * 150.0,
        "goal and position exported: {finite} of 300"
    );
    let span = positions.iter().copied().fold(f64::MIN, f64::max)
        - positions.iter().copied().fold(f64::MAX, f64::min);
    assert!(span > 0.3, "elbow motion in the export: {span}");
    assert!(lab.temperature[elbow]
        .iter()
        .filter(|t| t.is_finite())
        .all(|t| (15.0..60.0).contains(t)));
    assert_eq!(lab.chains, vec![(0..JOINTS as usize).collect::<Vec<_>>()]);
    stack.stop();
}

#[test]
fn kill_9_loses_at_most_the_last_flush_interval_and_never_the_dataset() {
    let _turn = serial();
    let stack = ArmStack::start("record-kill", &[]);
    wait_driving(&stack.domain);
    let stop = Arc::new(AtomicBool::new(false));
    let waver = wave(stack.domain.clone(), stop.clone());
    let dataset = stack.dir.join("dataset");
    let ds = dataset.to_str().unwrap().to_string();

    // Killed 2.x s into its second episode of 4 s (staged every 500 ms, `nori record`'s default).
    let mut rec = Proc::spawn(
        "nori record",
        &binary("nori"),
        &record_args(&stack.domain, &ds, &["--episodes", "3", "--episode-s", "4"]),
        &stack.dir.join("record-1.log"),
    );
    wait_for(
        Duration::from_secs(30),
        "four flushed parts of episode 1 (2 s)",
        || (staged_parts(&dataset, 1) >= 4).then_some(()),
    );
    std::thread::sleep(Duration::from_millis(400));
    let staged: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dataset.join(".nori-staging/episode-000001/episode.json"))
            .unwrap(),
    )
    .unwrap();
    let killed_ms = unix_ms();
    rec.kill();
    let recorded_s = (killed_ms - staged["started_unix_ms"].as_u64().unwrap()) as f64 * 1e-3;

    // Before any repair: the finished episode is intact and every file reads.
    if let Some(s) = lerobot_check(&dataset, &["--episodes", "1"]) {
        assert_eq!(s["lengths"], serde_json::json!([120]));
    }
    let repaired = recover(&dataset);
    eprintln!("after the kill: {repaired}");
    let recovered = repaired["recovered"][0][1].as_f64().unwrap();
    let expected = recorded_s * f64::from(FPS);
    eprintln!("killed {recorded_s:.2} s into episode 1: {expected:.0} frames taken, {recovered} recovered");
    assert_eq!(repaired["recovered"][0][0], 1);
    assert!(
        recovered <= expected + 2.0,
        "more frames than time allows: {recovered} > {expected:.0}"
    );
    // At most a second (the frames since the last hand-over and the part being written), plus
    // scheduling slack of the kill and of the frame clock.
    assert!(
        recovered >= expected - f64::from(FPS) - 8.0,
        "lost more than a second: {recovered} of {expected:.0}"
    );
    assert_eq!(recovered % 15.0, 0.0, "whole flush intervals of 500 ms");
    if let Some(s) = lerobot_check(&dataset, &["--episodes", "2"]) {
        assert_eq!(s["lengths"][0], 120);
    }

    // SIGTERM (Ctrl-C, systemd's stop) mid-episode: the episode is kept with what was taken,
    // nothing stays staged, the process exits cleanly.
    let mut rec = Proc::spawn(
        "nori record",
        &binary("nori"),
        &record_args(&stack.domain, &ds, &["--episodes", "3", "--episode-s", "4"]),
        &stack.dir.join("record-term.log"),
    );
    wait_for(
        Duration::from_secs(30),
        "a flushed part of episode 2",
        || (staged_parts(&dataset, 2) >= 1).then_some(()),
    );
    let (code, stdout) = rec.terminate(Duration::from_secs(10));
    assert_eq!(code, Some(0), "stopped cleanly");
    let report: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    let kept = report["episodes"][0]["frames"].as_u64().unwrap();
    assert!(
        (15..120).contains(&kept),
        "a partial episode kept: {kept} frames"
    );
    assert_eq!(report["total_episodes"], 3);
    assert!(!dataset.join(".nori-staging/episode-000002").exists());
    if let Some(s) = lerobot_check(&dataset, &["--episodes", "3"]) {
        assert_eq!(s["lengths"][2].as_u64().unwrap(), kept);
    }

    // Kills at random moments, many of them during commits (episodes of half a second):
    // after each, every file reads; after the repair, the dataset is exact again.
    let mut rng = Rng::new(0x0DA7_A5E7);
    let mut episodes = 3;
    for round in 0..4 {
        let mut rec = Proc::spawn(
            "nori record",
            &binary("nori"),
            &record_args(
                &stack.domain,
                &ds,
                &[
                    "--episodes",
                    "100",
                    "--episode-s",
                    "0.5",
                    "--flush-ms",
                    "200",
                ],
            ),
            &stack.dir.join(format!("record-chaos-{round}.log")),
        );
        std::thread::sleep(Duration::from_secs_f64(rng.range(0.5, 3.0)));
        rec.kill();
        let summary = lerobot_check(&dataset, &["--in-flight"]);
        let repaired = recover(&dataset);
        let after = lerobot_check(&dataset, &[]);
        eprintln!("chaos round {round}: before repair {summary:?}, repair {repaired}");
        let now = repaired["episodes"].as_u64().unwrap();
        assert!(now >= episodes, "episodes lost: {now} < {episodes}");
        episodes = now;
        if let Some(a) = after {
            assert_eq!(a["orphan_rows"], 0);
            assert_eq!(a["episodes"].as_u64().unwrap(), now);
        }
    }
    stop.store(true, Ordering::Relaxed);
    waver.join().unwrap();
    stack.stop();
}

#[test]
fn a_servo_that_goes_silent_is_held_and_marked_never_nan_and_one_never_read_is_refused() {
    let _turn = serial();
    // The left elbow (id 4) stops answering 12 s after the simulator starts, for 1.5 s: inside
    // the 15 s episode whenever the stack came up in under 12 s.
    let stack = ArmStack::start("record-silent", &["--silence", "left_arm:4@12+1.5"]);
    wait_driving(&stack.domain);
    let stop = Arc::new(AtomicBool::new(false));
    let waver = wave(stack.domain.clone(), stop.clone());
    let dataset = stack.dir.join("dataset");
    let ds = dataset.to_str().unwrap();
    let out = Command::new(binary("nori"))
        .args(record_args(&stack.domain, ds, &["--episode-s", "15"]))
        .output()
        .unwrap();
    stop.store(true, Ordering::Relaxed);
    waver.join().unwrap();
    assert!(
        out.status.success(),
        "nori record: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    if let Some(summary) = lerobot_check(&dataset, &["--episodes", "1", "--closed"]) {
        // 1.5 s of 15 s held: about a tenth of the elbow's frames, an eighth of a joint.
        let held = summary["missing_fraction"].as_f64().unwrap();
        assert!(
            held > 0.5 / 15.0 / 8.0,
            "the silence is in the mask: {summary}"
        );
    }
    // Read back with the recorder's reader: while held, the elbow's values are its last read.
    let reader = recorder::dataset::DatasetReader::open(&dataset).unwrap();
    let rows = reader.read_episode(0).unwrap();
    let held: Vec<usize> = (0..rows.len())
        .filter(|&i| rows[i].frame.valid[ELBOW] < 0.5)
        .collect();
    assert!(
        held.len() >= FPS as usize,
        "at least a second of the silence held: {held:?}"
    );
    // A frame whose whole arm is invalid had no read of the arm within its period: on a loaded
    // machine the simulator's replies come after the driver's deadline, or the driver is late
    // (seen under two CPU hogs: 370 ms of cycles reading nothing). The mask says so. The
    // silence itself must not spread: no held frame marks some other joints, and most mark the
    // elbow alone.
    let mut whole_arm_stale = Vec::new();
    for &i in &held {
        let f = &rows[i].frame;
        assert!(f.state.iter().chain(&f.action).all(|x| x.is_finite()));
        if i > 0 && rows[i - 1].frame.valid[ELBOW] < 0.5 {
            assert_eq!(
                f.state[ELBOW],
                rows[i - 1].frame.state[ELBOW],
                "frame {i}: a held value does not change"
            );
        }
        match f.valid.iter().filter(|&&v| v < 0.5).count() {
            1 => {}
            n if n == JOINTS as usize => whole_arm_stale.push(i),
            n => panic!("frame {i}: {n} joints marked, only the elbow is silent"),
        }
    }
    assert!(
        whole_arm_stale.len() * 2 < held.len(),
        "the other joints go on being read during the silence: frames {whole_arm_stale:?} of {held:?} held the whole arm"
    );
    drop(stack);

    // A servo silent from the start: the recorder refuses to begin, naming it.
    let stack = ArmStack::start("record-never", &["--silence", "left_arm:4@0+120"]);
    let never = stack.dir.join("never");
    let out = Command::new(binary("nori"))
        .args(record_args(
            &stack.domain,
            never.to_str().unwrap(),
            &["--episode-s", "1", "--wait-s", "8"],
        ))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains("never read") && err.contains("left_elbow"),
        "{err}"
    );
    let info = never.join("meta/info.json");
    if info.exists() {
        let info: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(info).unwrap()).unwrap();
        assert_eq!(info["total_frames"], 0);
    }
    assert!(
        !never.join(".nori-staging").exists(),
        "closed on the error path too"
    );
}

/// ffprobe's packet sizes of a video (bytes, in order).
fn packet_sizes(path: &Path) -> Vec<u64> {
    let out = Command::new("ffprobe")
        .args(["-v", "error", "-select_streams", "v:0", "-of", "csv=p=0"])
        .args(["-show_entries", "packet=size"])
        .arg(path)
        .output()
        .expect("ffprobe (deploy/install-build-deps.sh installs ffmpeg)");
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| l.trim_end_matches(',').parse().unwrap())
        .collect()
}

#[test]
#[allow(
    clippy::too_many_lines,
    reason = "one scenario read start to end; to be split into phases (#37)"
)]
fn cameras_are_recorded_as_video_frame_for_frame_and_a_dead_camera_is_held_and_marked() {
    let _turn = serial();
    let files = nori_tests::scratch("record-video-files");
    let (robot, camera_toml) = nori_tests::small_camera_files(&files);
    let stack = ArmStack::start("record-video", &["--description", &robot]);
    let spawn_camera = |name: &str, n: u32| stack.camera(name, &camera_toml, n);
    let mut head = spawn_camera("head", 1);
    let mut wrist = spawn_camera("left_wrist", 1);
    wait_driving(&stack.domain);
    let stop = Arc::new(AtomicBool::new(false));
    let waver = wave(stack.domain.clone(), stop.clone());
    let dataset = stack.dir.join("dataset");
    let ds = dataset.to_str().unwrap().to_string();

    // Two episodes of 3 s; the wrist camera is killed 1.5 s into the first and restarted once
    // it is committed.
    let cameras = ["--camera", "head", "--camera", "left_wrist"];
    let mut extra = vec!["--episodes", "2", "--episode-s", "3", "--reset-s", "1"];
    extra.extend(cameras);
    let mut rec = Proc::spawn(
        "nori record",
        &binary("nori"),
        &record_args(&stack.domain, &ds, &extra),
        &stack.dir.join("record-video.log"),
    );
    wait_for(Duration::from_secs(30), "episode 0 recording", || {
        (staged_parts(&dataset, 0) >= 3).then_some(())
    });
    let node = Plane::open(&stack.domain, "test-video").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    let before_kill = wait_for(Duration::from_secs(2), "driver frames", || newest(&states));
    wrist.kill();
    wait_for(Duration::from_secs(30), "episode 0 committed", || {
        dataset.join("meta/episodes").exists().then_some(())
    });
    let after_kill = wait_for(Duration::from_secs(2), "driver frames", || newest(&states));
    assert!(
        after_kill.seq >= before_kill.seq + 200,
        "the driver kept its loop while a camera died: {} -> {}",
        before_kill.seq,
        after_kill.seq
    );
    let mut wrist = spawn_camera("left_wrist", 2);
    let (code, stdout) = rec.wait_exit(Duration::from_secs(60));
    assert_eq!(code, Some(0), "nori record: see record-video.log");
    let report: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    eprintln!("nori record: {report}");
    stop.store(true, Ordering::Relaxed);
    waver.join().unwrap();

    let reader = recorder::dataset::DatasetReader::open(&dataset).unwrap();
    let names: Vec<&str> = reader
        .features
        .cameras
        .iter()
        .map(|c| c.name.as_str())
        .collect();
    assert_eq!(names, ["head", "left_wrist"]);
    assert_eq!(
        (
            reader.features.cameras[0].width,
            reader.features.cameras[0].height
        ),
        (160, 120)
    );
    // Episode 0: the wrist camera valid, then held to the end once killed (never valid again:
    // nothing invented); the head camera valid throughout but for scheduling hiccups.
    let rows = reader.read_episode(0).unwrap();
    assert_eq!(rows.len(), 90);
    let wrist_valid: Vec<f32> = rows.iter().map(|r| r.frame.camera_valid[1]).collect();
    let first_held = wrist_valid.iter().position(|&v| v < 0.5).expect("a gap");
    assert!(
        wrist_valid[first_held..].iter().all(|&v| v < 0.5),
        "held from the kill to the end: {wrist_valid:?}"
    );
    assert!(
        (15..80).contains(&first_held),
        "killed about 1.5 s in: held from frame {first_held}"
    );
    let head_held = rows
        .iter()
        .filter(|r| r.frame.camera_valid[0] < 0.5)
        .count();
    assert!(head_held < 18, "{head_held} of 90 head images held");
    // The held frames of the video are the camera's last JPEG, repeated.
    let wrist_video = dataset.join("videos/observation.images.left_wrist/chunk-000/file-000.mp4");
    let sizes = packet_sizes(&wrist_video);
    assert_eq!(sizes.len(), 180, "one frame per data frame, both episodes");
    assert!(
        sizes[first_held..90].windows(2).all(|w| w[0] == w[1]),
        "the gap repeats one image: {:?}",
        &sizes[first_held..90]
    );
    assert!(
        sizes[..first_held].windows(2).any(|w| w[0] != w[1]),
        "a live camera's images differ"
    );
    // Episode 1: the restarted camera is valid again once it streams.
    let rows = reader.read_episode(1).unwrap();
    assert!(
        rows.iter()
            .rev()
            .take(30)
            .all(|r| r.frame.camera_valid[1] > 0.5),
        "the restarted wrist camera's last second is fresh"
    );

    if let Some(s) = lerobot_check(&dataset, &["--episodes", "2", "--closed"]) {
        eprintln!("LeRobot check: {s}");
        assert_eq!(
            s["cameras"],
            serde_json::json!(["observation.images.head", "observation.images.left_wrist"])
        );
        assert_eq!(s["lengths"], serde_json::json!([90, 90]));
        let held_in_1 = rows
            .iter()
            .filter(|r| r.frame.camera_valid[1] < 0.5)
            .count();
        assert_eq!(
            s["held_images_per_camera"][1].as_u64().unwrap() as usize,
            90 - first_held + held_in_1,
            "the independent reader sees the same mask"
        );
    }

    // kill -9 mid-episode: what the data parts and both videos hold is recovered, and the
    // dataset reads, videos included.
    let mut extra = vec!["--episodes", "1", "--episode-s", "6"];
    extra.extend(cameras);
    let mut rec = Proc::spawn(
        "nori record",
        &binary("nori"),
        &record_args(&stack.domain, &ds, &extra),
        &stack.dir.join("record-video-kill.log"),
    );
    wait_for(
        Duration::from_secs(30),
        "two flushed parts of episode 2",
        || (staged_parts(&dataset, 2) >= 4).then_some(()),
    );
    rec.kill();
    let repaired = recover(&dataset);
    eprintln!("after the kill: {repaired}");
    let recovered = repaired["recovered"][0][1].as_u64().unwrap();
    assert!(recovered >= 60, "at least the 4 flushed parts: {repaired}");
    if let Some(s) = lerobot_check(&dataset, &["--episodes", "3", "--closed"]) {
        assert_eq!(s["lengths"][2].as_u64().unwrap(), recovered);
    }

    // A camera that publishes nothing (none runs for the neck) and a name that cannot be one:
    // clear errors naming them, and the dataset untouched.
    for (camera, says) in [
        ("neck", "no JPEG from camera neck"),
        ("Neck Cam", "camera name"),
    ] {
        let mut extra = vec!["--episodes", "1", "--episode-s", "1", "--wait-s", "2"];
        extra.extend(["--camera", "head", "--camera", camera]);
        let out = Command::new(binary("nori"))
            .args(record_args(&stack.domain, &ds, &extra))
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains(says),
            "{camera}: {err}"
        );
    }
    let reader = recorder::dataset::DatasetReader::open(&dataset).unwrap();
    assert_eq!(
        reader.episodes.len(),
        3,
        "nothing recorded by the refused runs"
    );
    assert!(!dataset.join(".nori-staging").exists());
    drop((states, node));
    for camera in [&mut head, &mut wrist] {
        let (code, _) = camera.terminate(Duration::from_secs(5));
        assert_eq!(code, Some(0));
    }
    stack.stop();
}

/// The base at its commanded twist where it was let drive, measured by the wheels: the
/// action is what went to the wheels after the limits and the field, so a frame whose
/// action was the operator's twist for the 0.3 s before it (the ramp through) is judged; a
/// loaded machine's starved lidar holds the base, rightly, and restarts the ramp. At least
/// a second of the episode must be so (a base that never drove fails). One frame's twist is
/// from one control period of the wheels' positions, a few encoder counts: ±0.07 rad/s of
/// turn rate (seen in CI: a late control period's 0.68 rad/s in one frame).
fn assert_the_base_drove_as_asked(rows: &[recorder::pq::DataRow]) {
    let asked =
        |r: &recorder::pq::DataRow| (r.frame.action[17], r.frame.action[18]) == (-0.15, 0.3);
    let settle = (0.3 * FPS as f64).ceil() as usize;
    let driven: Vec<usize> = (settle..rows.len())
        .filter(|&k| rows[k - settle..=k].iter().all(asked))
        .collect();
    assert!(
        driven.len() >= FPS as usize,
        "the base let drive in {} of {} frames",
        driven.len(),
        rows.len()
    );
    assert!(
        rows.iter().all(|r| r.frame.action[17] <= 0.0
            && r.frame.action[17] >= -0.15
            && (0.0..=0.3).contains(&r.frame.action[18])),
        "the wheels never sent more than the operator asked"
    );
    let frames = |i: usize| -> Vec<(f32, usize)> {
        driven
            .iter()
            .map(|&k| (rows[k].frame.state[i], k))
            .collect()
    };
    nori_tests::assert_cruising(&frames(17), -0.15, 0.02);
    nori_tests::assert_cruising(&frames(18), 0.3, 0.05);
}

/// The whole body recorded: `nori up` (both arms, the wheels, the lift, the base), the lift
/// rising and the base backing along a curve while `nori record --lift --base` records. The state and
/// the action are 19 wide (16 arm joints, the lift's height, the base's twist) and named; the
/// motion is in them; the odometry follows the base; LeRobot's layout checks out.
#[test]
fn the_whole_body_is_recorded_nineteen_wide_with_the_lift_rising_and_the_base_driving() {
    use telemetry::motion::{BaseCommand, LiftCommand};
    let _turn = serial();
    let robot = nori_tests::WholeRobot::start("record-body");
    let domain = robot.domain.clone();
    // The operator: the lift to 20 cm, the base backing away from the table and turning left
    // (a 0.5 m radius, clear of everything in the room), until told to stop.
    let stop = Arc::new(AtomicBool::new(false));
    let operator = {
        let (domain, stop) = (domain.clone(), stop.clone());
        std::thread::spawn(move || {
            let node = Plane::open(&domain, "test-operator").unwrap();
            let base = node.publisher(&plane::BASE_COMMAND).unwrap();
            let lift = node.publisher(&plane::LIFT_COMMAND).unwrap();
            std::thread::sleep(Duration::from_millis(100));
            let mut seq = 0;
            while !stop.load(Ordering::Relaxed) {
                seq += 1;
                let now = monotonic_ns();
                let twist = BaseCommand {
                    seq,
                    timestamp_ns: now,
                    linear_m_s: -0.15,
                    angular_rad_s: 0.3,
                };
                publish(&base, &twist).unwrap();
                let height = LiftCommand {
                    seq,
                    timestamp_ns: now,
                    height_m: 0.2,
                    kind: telemetry::motion::LIFT_COMMAND_GOAL,
                };
                publish(&lift, &height).unwrap();
                std::thread::sleep(Duration::from_millis(50));
            }
        })
    };
    // Recording starts once the lift holds the operator's goal: before it, the goal recorded
    // is the height (none in force), which is true but not what this test asks.
    let node = Plane::open(&domain, "test-record-body").unwrap();
    let lifts = node.subscriber(&plane::LIFT_STATE).unwrap();
    wait_for(Duration::from_secs(20), "the lift's goal taken", || {
        newest(&lifts).filter(|l| l.goal_m == 0.2)
    });
    let dataset = robot.dir.join("dataset");
    // How much the machine keeps a 200 Hz loop from running meanwhile (the bound on held
    // samples below is judged against it).
    let probe = SchedulingProbe::start(Duration::from_millis(5));
    let recording_from = monotonic_ns();
    let out = Command::new(binary("nori"))
        .args(record_args(
            &domain,
            dataset.to_str().unwrap(),
            &["--lift", "--base", "--episode-s", "4"],
        ))
        .output()
        .unwrap();
    let kept = probe.finish().kept_ratio(recording_from, monotonic_ns());
    stop.store(true, Ordering::Relaxed);
    operator.join().unwrap();
    assert!(
        out.status.success(),
        "nori record: {}",
        String::from_utf8_lossy(&out.stderr)
    );

    let body = ["lift.height_m", "base.linear_m_s", "base.angular_rad_s"];
    if let Some(summary) = lerobot_check(&dataset, &["--episodes", "1", "--closed"]) {
        eprintln!("LeRobot check: {summary}");
        let names = summary["joints"].as_array().unwrap();
        assert_eq!(names.len(), 19, "{summary}");
        assert_eq!(names[16..], body.map(serde_json::Value::from));
    }
    let reader = recorder::dataset::DatasetReader::open(&dataset).unwrap();
    let f = &reader.features;
    assert_eq!(f.width(recorder::features::Vector::State), 19);
    assert_eq!(f.width(recorder::features::Vector::Action), 19);
    assert_eq!(f.names(recorder::features::Vector::State)[16..], body);
    let rows = reader.read_episode(0).unwrap();
    assert_eq!(rows.len(), 4 * FPS as usize);
    let (first, last) = (&rows[0].frame, &rows[rows.len() - 1].frame);
    let column = |i: usize| rows.iter().map(move |r| r.frame.state[i]);
    // The lift from its lowest toward 0.2 m at about 30 mm/s: 4 s cover 0.1 m or more.
    assert!(first.state[16] < 0.03, "lift at {}", first.state[16]);
    assert!(last.state[16] > 0.09, "lift at {}", last.state[16]);
    assert!(
        column(16)
            .zip(column(16).skip(1))
            .all(|(a, b)| b >= a - 1e-3),
        "the lift only rises"
    );
    let off_goal: Vec<(usize, f32)> = (rows.iter().enumerate())
        .map(|(i, r)| (i, r.frame.action[16]))
        .filter(|&(_, goal)| goal != 0.2)
        .collect();
    assert!(off_goal.is_empty(), "its goal in every frame: {off_goal:?}");
    assert_the_base_drove_as_asked(&rows);
    // The odometry: backwards, to the right, and turned left by about the twist's integral.
    let (x0, y0, h0) = (first.odometry[0], first.odometry[1], first.odometry[2]);
    let (x1, y1, h1) = (last.odometry[0], last.odometry[1], last.odometry[2]);
    assert!(
        x1 - x0 < -0.2 && y1 < y0,
        "odometry {:?} -> {:?}",
        first.odometry,
        last.odometry
    );
    assert!(h1 - h0 > 0.6, "heading {h0} -> {h1}");
    // A sample is held when its source's newest state is older than the recorder allows (a
    // starved lift or base loop, rightly marked): at most one in twenty of the body's samples
    // (three a frame; the bound once counted frames, not samples, and failed at 6 of 360) on a
    // quiet machine, more by twice the share of ticks a 200 Hz loop in this process lost
    // meanwhile (a loaded CI machine held 38 of 360).
    let body_samples: Vec<f32> = rows
        .iter()
        .flat_map(|r| r.frame.valid[16..].iter().copied())
        .collect();
    let held = body_samples.iter().filter(|v| **v < 0.5).count();
    assert_eq!(body_samples.len(), 3 * rows.len());
    let allowed = 0.05 + 2.0 * (1.0 - kept);
    assert!(
        (held as f64) < allowed * body_samples.len() as f64,
        "{held} of {} body samples held (allowed {allowed:.3} with the probe keeping {kept:.3})",
        body_samples.len()
    );
    robot.stop();
}
