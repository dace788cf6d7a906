//! One source of names: the operator's tools name joints and buses through the layout the
//! running driver publishes, not through a configuration file. Against a driver started with a
//! subset of the configuration's buses (`--bus right_arm`: the driver's bus 0, the
//! configuration's bus 1), re-enabling a latched bus and moving a joint by name act on that bus
//! and that joint.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{binary, wait_for, ArmStack};
use std::process::{Command, Output};
use std::time::Duration;
use telemetry::frames::{JOINT_FLAG_BUS_DISABLED, STATE_FLAG_SAFE_STATE};
use telemetry::plane::{self, newest, Plane};

fn nori(args: &[&str], domain: &str) -> Output {
    let out = Command::new(binary("nori"))
        .args(args)
        .args(["--domain", domain])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "nori {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

#[test]
fn a_driver_on_a_subset_of_buses_is_reenabled_and_moved_by_name() {
    let mut stack = ArmStack::simulator_only_on("names", "right_arm", &[]);
    stack.restart_supervisor();
    stack.restart_driver();
    let node = Plane::open(&stack.domain, "test").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    let all_valid =
        |s: &telemetry::JointState| s.joint_count == 8 && s.joints().iter().all(|j| j.is_valid());
    let all_on = |s: &telemetry::JointState| {
        all_valid(s)
            && s.joints()
                .iter()
                .all(|j| j.torque_enabled == 1 && j.flags == 0)
    };
    // A robot that ran (its servos set up), then tripped: the record read at the restart.
    wait_for(Duration::from_secs(20), "the right arm set up", || {
        newest(&states).filter(|s| all_on(s))
    });
    std::fs::write(stack.trips(), "right_shoulder_pitch\n").unwrap();
    stack.restart_supervisor();
    stack.restart_driver();
    wait_for(
        Duration::from_secs(20),
        "the right arm latched off, directed",
        || {
            newest(&states).filter(|s| {
                all_valid(s)
                    && s.flags & STATE_FLAG_SAFE_STATE == 0
                    && s.joints()
                        .iter()
                        .all(|j| j.flags & JOINT_FLAG_BUS_DISABLED != 0)
            })
        },
    );

    // `nori state` names the driver's joints and its one bus.
    let out = nori(&["state", "--json"], &stack.domain);
    let state: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let joints: Vec<&str> = state["joints"]
        .as_array()
        .unwrap()
        .iter()
        .map(|j| j["joint"].as_str().unwrap())
        .collect();
    assert_eq!(joints.len(), 8, "{joints:?}");
    assert_eq!(joints[0], "right_shoulder_pitch");
    assert_eq!(joints[3], "right_elbow");
    assert_eq!(state["buses"][0]["bus"], "right_arm", "{state}");

    // Re-enabled by its name: the supervisor grants it (cool motors) and the bus comes back.
    nori(&["reenable", "right_arm"], &stack.domain);
    wait_for(
        Duration::from_secs(20),
        "the right arm back, torque on",
        || newest(&states).filter(|s| all_on(s)),
    );

    // Moved by name: the right elbow (the driver's joint 3) takes the goal and goes there.
    nori(&["goal", "right_elbow=-1.0"], &stack.domain);
    wait_for(
        Duration::from_secs(20),
        "the right elbow at -1.0 rad",
        || {
            newest(&states).filter(|s| {
                let elbow = s.joints()[3];
                (elbow.goal_rad + 1.0).abs() < 0.01 && (elbow.position_rad + 1.0).abs() < 0.05
            })
        },
    );
    drop((states, node));
    let report = stack.stop();
    assert_eq!(report["buses"][0]["name"], "right_arm", "{report}");
}
