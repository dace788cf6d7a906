//! Commissioning on the simulated robot, with the real binaries on pseudo-terminals: a servo
//! replaced by a factory-fresh one is found by `nori servo scan`, and a scan never talks on a
//! bus the driver holds.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{binary, serial, wait_for, ArmStack};
use serde_json::{json, Value};
use std::process::{Command, Output};
use std::time::Duration;
use telemetry::plane::{self, newest, Plane};

fn scan(stack: &ArmStack, extra: &[&str]) -> Output {
    let dev = stack.dir.join("dev");
    wait_for(Duration::from_secs(10), "the bus's device link", || {
        dev.join("left_arm").exists().then_some(())
    });
    Command::new(binary("nori"))
        .args(["servo", "scan", "left_arm", "--device-dir"])
        .arg(&dev)
        .args(extra)
        .output()
        .unwrap()
}

fn findings(out: &Output) -> Vec<Value> {
    let report: Value = serde_json::from_slice(&out.stdout).unwrap();
    report[0]["findings"].as_array().unwrap().clone()
}

#[test]
fn a_factory_fresh_servo_in_the_elbow_s_place_is_found_at_id_1_and_the_elbow_missing() {
    let _turn = serial();
    let stack = ArmStack::simulator_only("scan-fresh", &["--fresh-servo", "left_arm:left_elbow"]);
    let out = scan(&stack, &["--json"]);
    let said = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "faults found: {said}");
    assert!(said.contains("fault(s) found"), "{said}");
    let findings = findings(&out);
    let faults: Vec<&Value> = findings
        .iter()
        .filter(|f| f["finding"] != "settings")
        .collect();
    // The fresh servo and the shoulder's, both at id 1 with the factory's return delay,
    // answer at once.
    assert_eq!(
        faults,
        [
            &json!({"finding": "missing", "joint": "left_elbow", "id": 4}),
            &json!({"finding": "duplicated", "joint": "left_shoulder_pitch", "id": 1,
                    "evidence": {"evidence": "garbled", "attempts": 3}}),
        ],
        "{findings:#?}"
    );
    // Seven servos answered their table at 1 Mbps, nothing at another rate.
    let report: Value = serde_json::from_slice(&out.stdout).unwrap();
    let rates = report[0]["scan"]["rates"].as_array().unwrap();
    assert_eq!(rates.len(), 8);
    let read: Vec<u64> = rates[0]["found"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|f| !f["settings"].is_null())
        .map(|f| f["id"].as_u64().unwrap())
        .collect();
    assert_eq!(read, [2, 3, 5, 6, 7, 8]);
    assert!(rates[1..]
        .iter()
        .all(|r| r["found"].as_array().unwrap().is_empty()));
    stack.stop();
}

#[test]
fn a_scan_is_refused_on_a_bus_the_driver_holds_and_the_driver_drives_on() {
    let _turn = serial();
    let mut stack = ArmStack::start("scan-held", &[]);
    let node = Plane::open(&stack.domain, "test").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    let first = wait_for(Duration::from_secs(20), "the driver's frames", || {
        newest(&states).filter(|s| s.joints().iter().all(|j| j.is_valid()))
    });
    let out = scan(&stack, &["--bus-rate-only"]);
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    // Refused at the open (the port's lock): not one byte went on the driver's line.
    assert!(
        said.contains("stop the stack first") && said.contains("cannot open"),
        "{said}"
    );
    std::thread::sleep(Duration::from_millis(500));
    let later = newest(&states).unwrap();
    assert!(later.seq > first.seq && later.joints().iter().all(|j| j.is_valid()));
    assert!(stack.driver.running());
    drop((states, node));
    stack.stop();
}
