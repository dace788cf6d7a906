//! The real bus-driver process against the simulator process over pseudo-terminals: 16 servos
//! on two buses, goals followed, a goal far outside a joint's range never on the wire, bad goal
//! frames refused, torque off when the driver is stopped.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{binary, newest_read, scratch, wait_for, Proc};
use std::time::Duration;
use telemetry::config::ProcessConfig;
use telemetry::plane::{newest, publish, Plane};
use telemetry::{GoalFrame, JointState};

/// The embedded driver configuration without the base bus, with a reply margin wide enough
/// for this shared VM's scheduling hiccups.
fn two_arm_config(dir: &std::path::Path) -> std::path::PathBuf {
    let text = bus_driver::config::DEFAULT_CONFIG_TOML;
    let base = text
        .find("[[bus]]\nname = \"base\"")
        .expect("base bus in the default config");
    let config = text[..base].replace(
        "reply-timeout-margin-us = 2000",
        "reply-timeout-margin-us = 25000",
    );
    let path = dir.join("bus-driver.toml");
    std::fs::write(&path, config).unwrap();
    path
}

#[test]
#[allow(
    clippy::too_many_lines,
    reason = "one scenario read start to end; to be split into phases (#37)"
)]
fn sixteen_servos_follow_goals_and_nothing_outside_a_range_reaches_the_wire() {
    let dir = scratch("stack");
    let domain = format!("nori_it_{}", std::process::id());
    let devices = dir.join("dev");
    let report = dir.join("sim-report.json");
    let d = devices.to_str().unwrap();
    let mut sim = Proc::spawn(
        "simulator",
        &binary("nori"),
        &[
            "sim",
            "serve",
            "--bus",
            "left_arm",
            "--bus",
            "right_arm",
            "--dir",
            d,
            "--report",
            report.to_str().unwrap(),
        ],
        &dir.join("sim.log"),
    );
    let config = two_arm_config(&dir);
    // The supervisor first: the driver holds its safe state until it hears from it.
    let mut supervisor = Proc::spawn(
        "supervisor",
        &binary("supervisor"),
        &["--domain", &domain, "--status-every", "0"],
        &dir.join("supervisor.log"),
    );
    let mut driver = Proc::spawn(
        "bus-driver",
        &binary("bus-driver"),
        &[
            "--config",
            config.to_str().unwrap(),
            "--device-dir",
            d,
            "--domain",
            &domain,
            "--status-every",
            "1",
        ],
        &dir.join("driver.log"),
    );
    let plane = Plane::open(&domain, "test").unwrap();
    let state = plane.subscriber(&telemetry::plane::JOINT_STATE).unwrap();
    let goals = plane.publisher(&telemetry::plane::GOALS).unwrap();
    let ready = |s: &JointState| {
        s.joint_count == 16
            && s.joints()
                .iter()
                .all(|j| j.is_valid() && j.torque_enabled == 1)
    };
    wait_for(Duration::from_secs(20), "all 16 joints up", || {
        newest(&state).filter(ready)
    });

    // Left elbow (joint 3) to −1.0 rad, right forearm roll (joint 12) to 0.7 rad, and the left
    // wrist roll (joint 6) a hundred radians out of its range.
    let mut frame = GoalFrame {
        joint_count: 16,
        mask: (1 << 3) | (1 << 12) | (1 << 6),
        ..GoalFrame::default()
    };
    frame.position_rad[3] = -1.0;
    frame.position_rad[12] = 0.7;
    frame.position_rad[6] = 100.0;
    // The wrist's far goal is clamped to the top of its range, which the approach to a range's
    // end writes to the wire once the joint has followed it there.
    let calibration = bus_driver::LoadedConfig::embedded().unwrap().calibration;
    let wrist = calibration.joint["left_wrist_roll"];
    let wrist_top = wrist.range_rad().1 as f32;
    let reached = |s: &JointState| {
        let j = s.joints();
        (j[3].position_rad + 1.0).abs() < 0.05
            && (j[12].position_rad - 0.7).abs() < 0.05
            && (j[6].position_rad - wrist_top).abs() < 0.02
    };
    let s = wait_for(Duration::from_secs(10), "goals reached", || {
        frame.seq += 1;
        frame.timestamp_ns = telemetry::clock::monotonic_ns();
        publish(&goals, &frame).unwrap();
        std::thread::sleep(Duration::from_millis(20));
        newest(&state).filter(reached)
    });
    // The far goal was clamped to the top of the calibrated range, and the joint went there.
    assert!(
        (f64::from(s.joints[6].goal_rad) - wrist.range_rad().1).abs() < 0.01,
        "goal {}",
        s.joints[6].goal_rad
    );

    // A NaN goal frame is refused whole: the elbow keeps its goal.
    let mut bad = frame;
    bad.mask = (1 << 3) | (1 << 4);
    bad.position_rad[3] = 0.0;
    bad.position_rad[4] = f32::NAN;
    for _ in 0..5 {
        bad.timestamp_ns = telemetry::clock::monotonic_ns();
        publish(&goals, &bad).unwrap();
        std::thread::sleep(Duration::from_millis(20));
    }
    let elbow = wait_for(Duration::from_secs(2), "a fresh frame", || {
        newest_read(&state, 3)
    });
    assert!(
        (elbow.goal_rad + 1.0).abs() < 1e-3,
        "NaN frame applied: goal {}",
        elbow.goal_rad
    );
    assert!(driver.running() && sim.running() && supervisor.running());

    // SIGTERM: the driver stops cleanly with torque off.
    let (code, summary) = driver.terminate(Duration::from_secs(5));
    assert_eq!(code, Some(0), "driver exit code");
    let summary: serde_json::Value =
        serde_json::from_str(summary.trim()).expect("driver summary JSON");
    assert!(summary["counters"]["goals_not_finite"].as_u64().unwrap() >= 1);
    assert!(summary["counters"]["goals_clamped"].as_u64().unwrap() >= 1);
    supervisor.terminate(Duration::from_secs(5));
    sim.terminate(Duration::from_secs(5));

    // What the simulated servos received: every goal inside its joint's calibrated range, and
    // a torque-off write after the last goal.
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    let config = bus_driver::LoadedConfig::load(&config).unwrap();
    let mut checked = 0;
    for (bus, bus_config) in report["buses"]
        .as_array()
        .unwrap()
        .iter()
        .zip(&config.config.bus)
    {
        for (servo, servo_config) in bus["servos"]
            .as_array()
            .unwrap()
            .iter()
            .zip(&bus_config.servo)
        {
            let cal = config.calibration.joint[&servo_config.joint];
            let (lo, hi) = (
                servo["goal_min"].as_i64().unwrap(),
                servo["goal_max"].as_i64().unwrap(),
            );
            assert!(
                lo >= i64::from(cal.range_min) && hi <= i64::from(cal.range_max),
                "{}: goals {lo}..{hi} reached the wire, range {}..{}",
                servo_config.joint,
                cal.range_min,
                cal.range_max
            );
            nori_tests::assert_left_off(servo, "stack stopped");
            assert!(servo["max_temperature_c"].as_f64().unwrap() < 60.0);
            checked += 1;
        }
    }
    assert_eq!(checked, 16);
    let wrist_report = &report["buses"][0]["servos"][6];
    assert_eq!(
        wrist_report["goal_max"].as_i64().unwrap(),
        i64::from(wrist.range_max),
        "clamped goal on the wire"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
