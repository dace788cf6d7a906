//! The lidar process against the simulator's RPLIDAR C1, as on the robot: `nori-lidar` opens
//! the pseudo-terminal the simulator serves, resets a device that reports a protection stop,
//! and publishes one frame a revolution on the state plane. The room's walls are where the
//! description puts them, in the right directions; a damaged line (broken check bits, turns cut
//! short, bursts of noise) and an unplugged adapter are counted and never published as points;
//! a lidar killed mid-scan leaves the driver's loop untouched; a clean exit stops the motor.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{binary, wait_for, ArmStack, Proc};
use std::f32::consts::PI;
use std::time::Duration;
use telemetry::clock::monotonic_ns;
use telemetry::plane::{self, newest, Plane};
use telemetry::sensors::LidarScan;

/// The range at the point nearest to bearing `deg` (counter-clockwise from forward).
fn range_towards(scan: &LidarScan, deg: f32) -> f32 {
    let target = deg.to_radians();
    let off = |a: f32| {
        let d = (a - target).rem_euclid(2.0 * PI);
        d.min(2.0 * PI - d)
    };
    scan.points()
        .iter()
        .min_by(|a, b| off(a.angle_rad).total_cmp(&off(b.angle_rad)))
        .map(|p| p.range_m)
        .unwrap()
}

/// The lidar (0.15 m ahead of the base's centre, 0.2 m up) in the embedded room: walls at
/// x = 3.2 and -1.8, y = 1.9 and -2.6; the nearest thing a table leg 0.21 m away, the farthest
/// a corner about 4.0 m away. Asserted from these numbers, not from the simulator's ray caster.
fn assert_sees_the_room(scan: &LidarScan) {
    let n = scan.point_count;
    // 5000 measurements a second at 10 Hz; a few lost to line damage at most.
    assert!((480..=500).contains(&n), "{n} points in a turn");
    let hz = scan.rotation_hz().unwrap();
    assert!((8.5..12.0).contains(&hz), "{hz} Hz");
    for (deg, expected) in [(0.0, 3.05), (90.0, 1.9), (180.0, 1.95), (270.0, 2.6)] {
        let r = range_towards(scan, deg);
        assert!(
            (r - expected).abs() < 0.04,
            "towards {deg}°: {r} m, the wall is {expected} m away"
        );
    }
    for p in scan.points() {
        assert!(
            p.quality > 0 && (0.2..4.1).contains(&p.range_m),
            "a point no wall or object of the room explains: {p:?}"
        );
    }
    // In measured order: clockwise, so the counter-clockwise bearing falls through the turn
    // (once across 0).
    let rises = scan
        .points()
        .windows(2)
        .filter(|w| w[1].angle_rad > w[0].angle_rad)
        .count();
    assert!(rises <= 1, "{rises} bearings out of order");
}

#[test]
fn the_lidar_scans_the_room_survives_a_damaged_line_and_dies_alone() {
    let mut stack = ArmStack::start(
        "lidar",
        &[
            "--lidar-protection-stop",
            "--lidar-corrupt-rate",
            "0.001",
            "--lidar-truncate-rate",
            "0.1",
            "--lidar-garbage-rate",
            "0.1",
            "--unplug",
            "lidar@12+1.5",
        ],
    );
    let dev = stack.device_dir_with("lidar");
    let spawn = |n: u32| {
        Proc::spawn(
            "nori-lidar",
            &binary("nori-lidar"),
            &["--device-dir", &dev, "--domain", &stack.domain],
            &stack.dir.join(format!("lidar-{n}.log")),
        )
    };
    // The simulator started before this: its clock's 13.5 s (the replug) is before ours.
    let replugged_by = monotonic_ns() + 13_500_000_000;
    let mut lidar = spawn(1);
    let node = Plane::open(&stack.domain, "test").unwrap();
    let scans = node.subscriber(&plane::LIDAR_SCAN).unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();

    let first = wait_for(Duration::from_secs(20), "a lidar scan", || newest(&scans));
    assert!(first.start_ns < first.end_ns && first.end_ns <= monotonic_ns());
    assert_sees_the_room(&first);

    // Damage on the line is refused and counted, and what is published still fits the room.
    let damaged = wait_for(Duration::from_secs(30), "damage counted", || {
        let s = newest(&scans)?;
        assert_sees_the_room(&s);
        (s.bad_points > 0 && s.resyncs > 0 && s.short_scans > 0).then_some(s)
    });
    assert!(damaged.seq > first.seq);

    // Unplugged at 12 s for 1.5 s: the lidar opens it again and scans resume.
    let resumed = wait_for(Duration::from_secs(40), "scans after the replug", || {
        newest(&scans).filter(|s| s.start_ns > replugged_by)
    });
    assert_sees_the_room(&resumed);

    // Kill it mid-scan: the driver's frames go on.
    let before_kill = newest(&states).unwrap().seq;
    lidar.kill();
    std::thread::sleep(Duration::from_millis(500));
    let after_kill = wait_for(Duration::from_secs(2), "driver frames", || newest(&states));
    assert!(
        after_kill.seq >= before_kill + 50,
        "the driver slowed when the lidar died: {before_kill} -> {}",
        after_kill.seq
    );
    assert!(stack.driver.running() && stack.supervisor.running());
    // Restarted, it scans again, numbering from 0.
    let mut lidar = spawn(2);
    let restarted = wait_for(Duration::from_secs(20), "scans again", || {
        newest(&scans).filter(|s| s.start_ns > after_kill.timestamp_ns)
    });
    assert!(
        restarted.seq < resumed.seq,
        "a new process: {}",
        restarted.seq
    );

    // SIGTERM: a clean exit with its counters, and the device told to stop (its motor off).
    let (code, out) = lidar.terminate(Duration::from_secs(5));
    assert_eq!(code, Some(0), "{out}");
    let summary: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(summary["device"]["name"], "C1M1", "{summary}");
    assert_eq!(summary["device"]["firmware"], "1.02", "{summary}");
    let c = &summary["counters"];
    assert!(c["scan"]["scans"].as_u64().unwrap() > 0, "{summary}");
    // The first process found the protection stop and reset it; this one found it clear.
    assert_eq!(c["process"]["resets"], 0, "{summary}");
    std::thread::sleep(Duration::from_millis(1500));
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(stack.dir.join("sim-report.json")).unwrap()).unwrap();
    assert_eq!(report["lidar"]["scanning"], false, "{report}");
    assert!(report["lidar"]["corrupted"].as_u64().unwrap() > 0);
    let log = std::fs::read_to_string(stack.dir.join("lidar-1.log")).unwrap();
    assert!(log.contains("protection stop; resetting it"), "{log}");
    assert!(log.contains("opening it again"), "{log}");
    drop((scans, states, node));
    stack.stop();
}

#[test]
fn a_lidar_that_is_not_there_or_a_bad_configuration_is_a_clear_error() {
    let dir = nori_tests::scratch("lidar-missing");
    let run = |args: &[&str]| {
        std::process::Command::new(binary("nori-lidar"))
            .args(args)
            .args(["--domain", "nori_lidar_missing", "--run-for", "1"])
            .output()
            .unwrap()
    };
    let missing = run(&["--device-dir", &dir.display().to_string()]);
    let err = String::from_utf8_lossy(&missing.stderr);
    assert_eq!(missing.status.code(), Some(69), "{err}");
    assert!(
        err.contains("cannot open") && err.contains("lidar"),
        "{err}"
    );
    let config = dir.join("lidar.toml");
    std::fs::write(
        &config,
        lidar::config::DEFAULT_CONFIG_TOML.replace("max-gap-deg = 5.0", "max-gap-deg = 500.0"),
    )
    .unwrap();
    let bad = run(&["--config", &config.display().to_string()]);
    let err = String::from_utf8_lossy(&bad.stderr);
    assert_eq!(bad.status.code(), Some(78), "{err}");
    assert!(err.contains("max-gap-deg"), "{err}");
}
