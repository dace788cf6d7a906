//! The camera process against the simulator's cameras, as on the robot: `nori-camera` reads the
//! simulated head camera's MJPEG stream and publishes RGB frames on the state plane. The picture
//! follows the arm; corrupt JPEGs are refused and counted while good frames keep coming; a
//! camera killed mid-stream leaves the driver's loop untouched and comes back when restarted.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{binary, newest_read, small_camera_files, wait_for, ArmStack, Proc};
use std::time::Duration;
use telemetry::clock::monotonic_ns;
use telemetry::frames::GoalFrame;
use telemetry::plane::{self, newest, publish, CameraStream, FrameSub, Plane};
use telemetry::sensors::{CameraFrameHeader, PixelFormat};

/// The left arm's shoulder pitch (about y: negative swings the arm forward) and elbow.
const SHOULDER: usize = 0;
const ELBOW: usize = 3;
const W: u32 = 160;
const H: u32 = 120;

fn newest_frame(sub: &FrameSub) -> Option<(CameraFrameHeader, Vec<u8>)> {
    let mut last = None;
    while let Ok(Some(sample)) = sub.receive() {
        last = Some((*sample.user_header(), sample.payload().to_vec()));
    }
    last
}

fn changed_pixels(a: &[u8], b: &[u8]) -> usize {
    a.chunks_exact(3)
        .zip(b.chunks_exact(3))
        .filter(|(x, y)| x.iter().zip(y.iter()).any(|(p, q)| p.abs_diff(*q) > 24))
        .count()
}

#[test]
#[allow(
    clippy::too_many_lines,
    reason = "one scenario read start to end; to be split into phases (#37)"
)]
fn the_head_camera_sees_the_arm_move_refuses_corrupt_jpegs_and_dies_alone() {
    let dir = nori_tests::scratch("cameras-files");
    let (robot, cameras) = small_camera_files(&dir);
    let mut stack = ArmStack::start(
        "cameras",
        &["--description", &robot, "--camera-truncate-rate", "0.2"],
    );
    let dev = stack.dir.join("dev").display().to_string();
    let camera_args = [
        "--camera",
        "head",
        "--config",
        &cameras,
        "--device-dir",
        &dev,
        "--domain",
        &stack.domain,
    ];
    let spawn_camera = |n: u32| {
        Proc::spawn(
            "nori-camera",
            &binary("nori-camera"),
            &camera_args,
            &stack.dir.join(format!("camera-{n}.log")),
        )
    };
    let mut head = spawn_camera(1);
    let node = Plane::open(&stack.domain, "test").unwrap();
    let frames = node.camera_subscriber("head", CameraStream::Rgb).unwrap();
    let jpegs = node.camera_subscriber("head", CameraStream::Mjpeg).unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    let goals = node.publisher(&plane::GOALS).unwrap();

    let (first, before) = wait_for(Duration::from_secs(20), "a head camera frame", || {
        newest_frame(&frames)
    });
    assert_eq!(first.camera(), "head");
    assert_eq!(first.format(), Some(PixelFormat::Rgb24));
    assert_eq!((first.width, first.height, first.stride), (W, H, W * 3));
    assert_eq!(before.len(), (W * H * 3) as usize);
    assert!(first.capture_ns <= first.publish_ns, "{first:?}");
    assert!(first.publish_ns <= monotonic_ns());

    // Raise the left arm forward over the table: the head camera's picture changes.
    wait_for(Duration::from_secs(20), "the driver driving", || {
        newest(&states).filter(|s| {
            s.flags & telemetry::frames::STATE_FLAG_SAFE_STATE == 0
                && s.joints().iter().all(|j| j.torque_enabled == 1)
        })
    });
    let mut goal = GoalFrame {
        joint_count: 8,
        mask: (1 << ELBOW) | (1 << SHOULDER),
        ..GoalFrame::default()
    };
    goal.position_rad[SHOULDER] = -0.8;
    goal.position_rad[ELBOW] = -0.8;
    wait_for(Duration::from_secs(15), "the arm raised", || {
        goal.seq += 1;
        goal.timestamp_ns = monotonic_ns();
        publish(&goals, &goal).unwrap();
        std::thread::sleep(Duration::from_millis(20));
        newest_read(&states, ELBOW).filter(|j| j.position_rad < -0.6)
    });
    // Let the arm settle (the shoulder is slower than the elbow).
    std::thread::sleep(Duration::from_millis(1500));
    let (after_header, after) = wait_for(Duration::from_secs(5), "a frame after the move", || {
        newest_frame(&frames)
    });
    let moved = changed_pixels(&before, &after);
    assert!(
        moved > (W * H / 50) as usize,
        "only {moved} pixels changed when the arm rose"
    );
    // A still arm, a still picture (apart from JPEG noise): the change above is the arm.
    std::thread::sleep(Duration::from_millis(300));
    let (_, still) = wait_for(Duration::from_secs(5), "a later frame", || {
        newest_frame(&frames)
    });
    let drift = changed_pixels(&after, &still);
    assert!(
        drift < moved / 10,
        "the picture changes without motion: {drift} pixels, {moved} when the arm rose"
    );

    // The MJPEG stream carries each published frame's JPEG untouched: same sequence number, and
    // it decodes to exactly the RGB frame published under that number.
    let mut rgb_by_seq = std::collections::HashMap::new();
    let mut matched = 0;
    wait_for(Duration::from_secs(10), "JPEGs matching RGB frames", || {
        while let Ok(Some(sample)) = frames.receive() {
            rgb_by_seq.insert(sample.user_header().seq, sample.payload().to_vec());
        }
        while let Ok(Some(sample)) = jpegs.receive() {
            let h = *sample.user_header();
            assert_eq!(h.format(), Some(PixelFormat::Mjpeg), "{h:?}");
            assert_eq!((h.width, h.height, h.stride), (W, H, 0));
            let Some(rgb) = rgb_by_seq.get(&h.seq) else {
                continue;
            };
            let mut decoded = vec![0u8; rgb.len()];
            camera::convert::to_rgb(PixelFormat::Mjpeg, W, H, 0, sample.payload(), &mut decoded)
                .unwrap();
            assert!(decoded == *rgb, "JPEG {} is not RGB frame {}", h.seq, h.seq);
            matched += 1;
        }
        (matched >= 5).then_some(())
    });

    // One JPEG in five is cut short: refused and counted, and frames keep coming.
    let (late, _) = wait_for(Duration::from_secs(10), "corrupt frames counted", || {
        newest_frame(&frames).filter(|(h, _)| h.corrupt >= 3)
    });
    assert!(late.seq > after_header.seq, "published frames went on");

    // Kill the camera mid-stream: the driver's frames go on without a gap in their sequence.
    let before_kill = newest(&states).unwrap().seq;
    head.kill();
    std::thread::sleep(Duration::from_millis(500));
    let after_kill = wait_for(Duration::from_secs(2), "driver frames", || newest(&states));
    assert!(
        after_kill.seq >= before_kill + 50,
        "the driver slowed when the camera died: {before_kill} -> {}",
        after_kill.seq
    );
    assert!(stack.driver.running() && stack.supervisor.running());
    // Restarted, it streams again, numbering from 0.
    let mut head = spawn_camera(2);
    let (restarted, _) = wait_for(Duration::from_secs(20), "frames again", || {
        newest_frame(&frames).filter(|(h, _)| h.publish_ns > after_kill.timestamp_ns)
    });
    assert!(restarted.seq < late.seq, "a new process: {restarted:?}");

    // SIGTERM: a clean exit with its counters.
    let (code, out) = head.terminate(Duration::from_secs(5));
    assert_eq!(code, Some(0), "{out}");
    let summary: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    let c = &summary["counters"];
    assert!(c["published"].as_u64().unwrap() > 0, "{summary}");
    assert_eq!(
        c["captured"].as_u64().unwrap(),
        c["published"].as_u64().unwrap() + c["corrupt"].as_u64().unwrap(),
        "every frame captured is published or refused: {summary}"
    );
    assert_eq!(
        c["jpegs_published"], c["published"],
        "every published frame's JPEG, and no corrupt one: {summary}"
    );
    drop((frames, jpegs, states, goals, node));
    stack.stop();
}

#[test]
fn a_camera_that_is_not_there_or_not_in_the_configuration_is_a_clear_error() {
    let dir = nori_tests::scratch("cameras-missing");
    let dev = dir.join("dev");
    std::fs::create_dir_all(&dev).unwrap();
    let run = |camera: &str| {
        std::process::Command::new(binary("nori-camera"))
            .args(["--camera", camera, "--device-dir"])
            .arg(&dev)
            .args(["--domain", "nori_cameras_missing", "--run-for", "1"])
            .output()
            .unwrap()
    };
    let missing = run("head");
    let err = String::from_utf8_lossy(&missing.stderr);
    assert_eq!(missing.status.code(), Some(69), "{err}");
    assert!(
        err.contains("no camera at") && err.contains("camera-head"),
        "{err}"
    );
    let unknown = run("tail");
    let err = String::from_utf8_lossy(&unknown.stderr);
    assert_eq!(unknown.status.code(), Some(78), "{err}");
    assert!(err.contains("no camera \"tail\""), "{err}");
}
