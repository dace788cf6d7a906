//! The whole body's frames (`nori/body/frames`) on the simulated robot: with the lift raised,
//! the base driven to a new pose and an elbow bent, `nori-base` places both arms' shoulders and
//! tools in the room where the simulator's own truth puts them (its base pose, its lift's
//! height, its servos' angles through its own arm chain, written separately from the robot's).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{binary, wait_for, WholeRobot};
use std::process::Command;
use std::time::Duration;
use telemetry::clock::monotonic_ns;
use telemetry::motion::BaseCommand;
use telemetry::plane::{self, newest, publish, Plane};
use telemetry::GoalFrame;

/// Where the simulator says arm `bus`'s shoulder and tool are, in the room (m), from its report:
/// its arm chain at its servos' angles, raised by the lift's height above the description's,
/// carried by the base's true pose.
fn truth(report: &serde_json::Value, d: &sim::RobotDescription, bus: &str) -> [[f64; 3]; 2] {
    let buses = report["buses"].as_array().unwrap();
    let arm_bus = buses.iter().find(|b| b["name"] == bus).unwrap();
    let base = buses.iter().find_map(|b| b["base"].as_object()).unwrap();
    let (x, y, theta) = (
        base["x_m"].as_f64().unwrap(),
        base["y_m"].as_f64().unwrap(),
        base["theta_rad"].as_f64().unwrap(),
    );
    let lift = report["lift"]["height_m"].as_f64().unwrap() - d.lift.as_ref().unwrap().start_m;
    let description = d.bus(bus).unwrap();
    let arm_d = description.arm.as_ref().unwrap();
    let q: Vec<f64> = arm_d
        .joint
        .iter()
        .map(|j| {
            let servo = arm_bus["servos"].as_array().unwrap();
            let s = servo.iter().find(|s| s["id"] == j.servo).unwrap();
            s["angle_rad"].as_f64().unwrap()
        })
        .collect();
    let mut arm = sim::arm::Arm::new(arm_d, d.gravity);
    let tool = arm.tip_position(&q);
    let place = |p: [f64; 3]| {
        let (s, c) = theta.sin_cos();
        [
            x + c * p[0] - s * p[1],
            y + s * p[0] + c * p[1],
            p[2] + lift,
        ]
    };
    [place(arm_d.base), place(tool)]
}

#[test]
fn the_bodys_frames_place_both_arms_where_the_simulator_has_them() {
    let robot = WholeRobot::start("body");
    let d = &robot.description;
    let node = Plane::open(&robot.domain, "test").unwrap();
    let lifts = node.subscriber(&plane::LIFT_STATE).unwrap();
    let frames = node.subscriber(&plane::BODY_FRAMES).unwrap();
    let goals = node.publisher(&plane::GOALS).unwrap();
    let base_commands = node.publisher(&plane::BASE_COMMAND).unwrap();
    // Homed: both arms are placed.
    let first = wait_for(Duration::from_secs(5), "the body's frames", || {
        newest(&frames).filter(|f| f.arms[0].valid == 1 && f.arms[1].valid == 1)
    });
    assert_eq!(first.arm_count, 2);

    // The lift to 0.12 m (as an operator does: `nori goal lift=0.12`, which reports what the
    // lift made of it), the left elbow bent, the base backing and turning for 2 s.
    let out = Command::new(binary("nori"))
        .args(["goal", "--domain", &robot.domain, "lift=0.12"])
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "nori goal: {said}");
    assert!(said.contains("goal 0.120 m"), "nori goal: {said}");
    // The elbow's goal and the base's command streamed together, as a teleoperator's are
    // (a single frame would be dropped by a safe state the loaded machine can cause).
    for seq in 1..=40 {
        let now = monotonic_ns();
        let mut goal = GoalFrame {
            seq,
            timestamp_ns: now,
            joint_count: 18,
            mask: 1 << 3,
            ..GoalFrame::default()
        };
        goal.position_rad[3] = -1.2;
        publish(&goals, &goal).unwrap();
        let c = BaseCommand {
            seq,
            timestamp_ns: now,
            linear_m_s: -0.1,
            angular_rad_s: 0.4,
        };
        publish(&base_commands, &c).unwrap();
        std::thread::sleep(Duration::from_millis(50));
    }
    // At rest (the lift travels 7 cm at 30 mm/s), then the simulator's next report.
    wait_for(Duration::from_secs(10), "the lift at 0.12 m", || {
        newest(&lifts).filter(|l| (l.height_m - 0.12).abs() < 0.002 && l.velocity_m_s == 0.0)
    });
    std::thread::sleep(Duration::from_millis(2500));
    // A frame with both arms read (a reply missed in a cycle leaves its arm unplaced there).
    let published = wait_for(Duration::from_secs(1), "both arms placed", || {
        newest(&frames).filter(|f| f.arms[0].valid == 1 && f.arms[1].valid == 1)
    });
    let report = robot.report();
    assert!(published.theta_rad > 0.5, "the base turned: {published:?}");
    for (k, bus) in ["left_arm", "right_arm"].iter().enumerate() {
        let [shoulder, tool] = truth(&report, d, bus);
        let arm = published.arms[k];
        assert_eq!(arm.valid, 1, "{bus}");
        let off = |a: [f32; 3], b: [f64; 3]| {
            (0..3)
                .map(|i| (f64::from(a[i]) - b[i]).powi(2))
                .sum::<f64>()
                .sqrt()
        };
        // The odometry's drift over ~0.2 m of travel and a turn (the base test bounds it at 1 cm
        // + 1 %), the lift's halls (0.1 mm) and the servos' steps (0.0015 rad at 0.5 m).
        let (s, t) = (off(arm.shoulder, shoulder), off(arm.tool, tool));
        eprintln!(
            "{bus}: shoulder {:?} off by {s:.4} m, tool {:?} off by {t:.4} m",
            arm.shoulder, arm.tool
        );
        assert!(
            s < 0.015 && t < 0.02,
            "{bus}: {arm:?} vs truth {shoulder:?} {tool:?}"
        );
    }
    // The bent elbow is in the frames: the left tool is not where the right one's mirror is.
    let (l, r) = (published.arms[0].tool, published.arms[1].tool);
    assert!((l[2] - r[2]).abs() > 0.1, "left {l:?} right {r:?}");
    // `nori state` shows the lift and the base as their controllers publish them.
    let out = Command::new(binary("nori"))
        .args(["state", "--json", "--domain", &robot.domain])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let state: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(state["lift"]["state"], "ready", "{state}");
    assert!((state["lift"]["height_m"].as_f64().unwrap() - 0.12).abs() < 0.002);
    let x = state["base"]["x_m"].as_f64().unwrap();
    assert!((x - published.x_m).abs() < 0.01, "{state}");
    drop((lifts, frames, goals, base_commands, node));
    robot.stop();
}
