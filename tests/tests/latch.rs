//! A bus a trip has latched off stays off from the moment the driver starts, whatever the start
//! order of the processes, whether a supervisor is up at all, and in either safe state: the
//! simulated servos (which log every write they receive) get no Torque_Enable = 1 and no goal
//! until the operator's re-enable is granted. Then the bus comes back. The robot ran before
//! its trip: a driver set its servos up and died with their torque on.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{binary, wait_for, ArmStack};
use serde_json::Value;
use std::process::Command;
use std::time::Duration;
use telemetry::frames::{JOINT_FLAG_BUS_DISABLED, STATE_FLAG_SAFE_STATE};
use telemetry::plane::{self, newest, Plane};

#[derive(Clone, Copy, PartialEq, Debug)]
enum Start {
    SupervisorFirst,
    DriverFirst,
    NoSupervisor,
}

struct Run {
    report: Value,
    trips: String,
    /// Each servo's torque-on and goal writes before the latched start.
    before: Vec<(u64, u64)>,
    /// The simulator's report while the bus was latched, before anything stopped (a driver
    /// stopping turns every torque off).
    latched: Value,
}

/// Each servo's torque-on and goal writes in `report`.
fn writes(report: &Value) -> Vec<(u64, u64)> {
    (report["buses"][0]["servos"].as_array().unwrap().iter())
        .map(|s| {
            let n = |k: &str| s[k].as_u64().unwrap();
            (n("torque_on_writes"), n("goal_writes"))
        })
        .collect()
}

/// A driver sets the arm's servos up (they hold their torque on, their replies prompt as a
/// driver leaves them) and is killed; returns each servo's writes as the simulator then reports
/// them.
fn ran_before(stack: &mut ArmStack) -> Vec<(u64, u64)> {
    stack.restart_driver();
    let node = Plane::open(&stack.domain, "test-before").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    wait_for(Duration::from_secs(20), "the arm set up", || {
        newest(&states).filter(|s| {
            s.joint_count == 8 && (s.joints().iter()).all(|j| j.is_valid() && j.torque_enabled == 1)
        })
    });
    stack.driver.kill();
    // The simulator's report, written every second, after the kill.
    std::thread::sleep(Duration::from_millis(2200));
    writes(&stack.sim_report())
}

/// The left arm latched in the trip record before anything starts; the processes started in
/// `order`; 1.5 s of running (with a supervisor: 1.5 s after it directs the driver); then, if
/// `reenable`, the operator's re-enable and the bus's return.
fn run(tag: &str, order: Start, torque_off: bool, reenable: bool) -> Run {
    let mut stack = ArmStack::simulator_only(tag, &[]);
    let before = ran_before(&mut stack);
    std::fs::write(stack.trips(), "left_shoulder_pitch\nleft_gripper\n").unwrap();
    if torque_off {
        let config = stack.dir.join("bus-driver.toml");
        let text = bus_driver::config::DEFAULT_CONFIG_TOML
            .replace("safe-state = \"hold\"", "safe-state = \"torque-off\"");
        assert!(text.contains("torque-off"));
        std::fs::write(&config, text).unwrap();
        stack.driver_args = vec!["--config".into(), config.display().to_string()];
    }
    let node = Plane::open(&stack.domain, "test").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    match order {
        Start::SupervisorFirst => {
            stack.restart_supervisor();
            std::thread::sleep(Duration::from_millis(300));
            stack.restart_driver();
        }
        Start::DriverFirst | Start::NoSupervisor => {
            stack.restart_driver();
            // Running and reading its servos before anything else is there.
            wait_for(Duration::from_secs(20), "the driver's first frames", || {
                newest(&states).filter(|s| s.joints().iter().all(|j| j.is_valid()))
            });
            std::thread::sleep(Duration::from_millis(500));
            if order == Start::DriverFirst {
                stack.restart_supervisor();
            }
        }
    }
    let off = |s: &telemetry::JointState| {
        s.joint_count == 8
            && s.joints()
                .iter()
                .all(|j| j.is_valid() && j.flags & JOINT_FLAG_BUS_DISABLED != 0)
    };
    if order == Start::NoSupervisor {
        wait_for(Duration::from_secs(20), "the bus read, off", || {
            newest(&states).filter(off)
        });
    } else {
        wait_for(Duration::from_secs(20), "the supervisor directing", || {
            newest(&states).filter(|s| off(s) && s.flags & STATE_FLAG_SAFE_STATE == 0)
        });
    }
    std::thread::sleep(Duration::from_millis(1500));
    let latched = stack.sim_report();
    if reenable {
        let out = Command::new(binary("nori"))
            .args(["reenable", "left_arm", "--domain", &stack.domain])
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "re-enable refused: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        wait_for(Duration::from_secs(20), "the bus back, torque on", || {
            newest(&states).filter(|s| {
                s.joints()
                    .iter()
                    .all(|j| j.is_valid() && j.torque_enabled == 1 && j.flags == 0)
            })
        });
    }
    let trips = std::fs::read_to_string(stack.trips()).unwrap_or_default();
    drop((states, node));
    Run {
        report: stack.stop(),
        trips,
        before,
        latched,
    }
}

/// Every servo of the left arm: no Torque_Enable = 1 and no goal received since the latched
/// start, and its torque off while latched (the dead driver before left it on).
fn assert_never_energised(r: &Run, what: &str) {
    let servos = r.report["buses"][0]["servos"].as_array().unwrap();
    let after = writes(&r.report);
    assert_eq!((servos.len(), after.len(), r.before.len()), (8, 8, 8));
    for ((s, after), before) in servos.iter().zip(after).zip(&r.before) {
        assert_eq!(
            after, *before,
            "{what}: {} received torque-on or goal writes while latched off: {s}",
            s["joint"]
        );
    }
    for s in r.latched["buses"][0]["servos"].as_array().unwrap() {
        assert_eq!(
            s["torque_enabled"], false,
            "{what}: {} while latched",
            s["joint"]
        );
    }
    assert!(
        r.trips.contains("left_shoulder_pitch"),
        "{what}: the latch was dropped from the record: {:?}",
        r.trips
    );
}

#[test]
fn a_latched_bus_gets_no_torque_when_the_supervisor_starts_first() {
    let r = run("latch-sup-first", Start::SupervisorFirst, false, false);
    assert_never_energised(&r, "supervisor first, hold");
}

#[test]
fn a_latched_bus_gets_no_torque_when_the_driver_starts_first() {
    let r = run("latch-drv-first", Start::DriverFirst, false, false);
    assert_never_energised(&r, "driver first, hold");
}

#[test]
fn a_latched_bus_gets_no_torque_without_any_supervisor() {
    let r = run("latch-no-sup", Start::NoSupervisor, false, false);
    assert_never_energised(&r, "no supervisor, hold");
}

#[test]
fn a_latched_bus_gets_no_torque_in_the_torque_off_safe_state() {
    let r = run("latch-torque-off", Start::DriverFirst, true, false);
    assert_never_energised(&r, "driver first, torque-off");
}

/// Released by the operator: the record is cleared first, then the driver brings the bus up.
#[test]
fn the_operators_reenable_releases_the_latch_and_the_bus_comes_back() {
    let r = run("latch-release", Start::SupervisorFirst, false, true);
    assert_eq!(r.trips.trim(), "", "the record no longer latches the bus");
    let servos = r.report["buses"][0]["servos"].as_array().unwrap();
    let after = writes(&r.report);
    assert_eq!((servos.len(), after.len(), r.before.len()), (8, 8, 8));
    for ((s, after), before) in servos.iter().zip(after).zip(&r.before) {
        assert!(after.0 > before.0, "{} not set up again: {s}", s["joint"]);
    }
}
