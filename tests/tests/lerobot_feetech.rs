//! LeRobot's own Feetech driver (lerobot 0.6.1, feetech-servo-sdk) against `nori sim serve`:
//! its handshake, reads, sync reads and writes, its broadcast ping and `scan_port`, through
//! `tests/python/lerobot-feetech-check.sh` (a venv of lerobot without torch, from PyPI).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{serial, ArmStack};
use serde_json::{json, Value};
use std::path::Path;
use std::process::Command;
use telemetry::config::ProcessConfig;

fn script() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("python/lerobot-feetech-check.sh")
}

/// The left arm's servos as the driver's configuration has them: `ID:MODEL,...`.
fn left_arm_motors() -> (String, Vec<(u8, u16)>) {
    let loaded = bus_driver::LoadedConfig::embedded().unwrap();
    let bus = loaded.config.bus("left_arm").unwrap();
    let text: Vec<String> = bus
        .servo
        .iter()
        .map(|s| format!("{}:{}", s.id, s.model))
        .collect();
    let models = bus
        .servo
        .iter()
        .map(|s| {
            (
                s.id,
                feetech::ServoModel::from_key(&s.model)
                    .unwrap()
                    .model_number(),
            )
        })
        .collect();
    (text.join(","), models)
}

fn check(stack: &ArmStack, extra: &[&str]) -> Value {
    let install = Command::new(script()).arg("--install").status().unwrap();
    assert!(install.success(), "the lerobot venv");
    let (motors, _) = left_arm_motors();
    let out = Command::new(script())
        .arg(stack.dir.join("dev/left_arm"))
        .args(["--motors", &motors])
        .args(extra)
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{said}");
    // LeRobot prints what its scan found before the check's line.
    let stdout = String::from_utf8_lossy(&out.stdout);
    let last = stdout.lines().last().unwrap_or_default();
    serde_json::from_str(last).unwrap_or_else(|e| panic!("{e}: {stdout}"))
}

#[test]
fn lerobot_s_feetech_bus_connects_reads_and_writes_the_whole_arm() {
    let _turn = serial();
    let stack = ArmStack::simulator_only("lerobot-feetech", &[]);
    let got = check(&stack, &[]);
    let (_, models) = left_arm_motors();
    for step in [
        "connect",
        "ping",
        "firmware",
        "read",
        "sync_read",
        "return_delay",
        "sync_write",
    ] {
        assert!(got[step].get("ok").is_some(), "{step}: {got:#}");
    }
    for (id, model) in models {
        assert_eq!(got["ping"]["ok"][format!("m{id}")], json!(model), "{got:#}");
        // At rest at the joint's zero (the gripper open), the description's start.
        let position = got["read"]["ok"][format!("m{id}")].as_u64().unwrap();
        assert_eq!(got["sync_read"]["ok"][format!("m{id}")], json!(position));
    }
    // Eight servos answering a broadcast ping at once: garbled, as on a real bus, so LeRobot's
    // parser finds nothing (Feetech documents the broadcast ping for one servo alone).
    assert_eq!(got["broadcast_ping"], json!({"ok": null}), "{got:#}");
    assert_eq!(got["scan_port"], json!({"ok": {}}), "{got:#}");
    stack.stop();
}

#[test]
fn a_servo_alone_on_the_bus_answers_lerobot_s_broadcast_ping_and_scan() {
    let _turn = serial();
    // Every servo of the arm powered off but the wrist pitch's (id 6, an STS3250).
    let silenced: Vec<String> = [1, 2, 3, 4, 5, 7, 8]
        .iter()
        .flat_map(|id| ["--silence".to_string(), format!("left_arm:{id}@0+100000")])
        .collect();
    let args: Vec<&str> = silenced.iter().map(String::as_str).collect();
    let stack = ArmStack::simulator_only("lerobot-feetech-alone", &args);
    let got = check(&stack, &["--alone", "6"]);
    assert_eq!(got["connect"], json!({"ok": true}), "{got:#}");
    assert_eq!(got["broadcast_ping"], json!({"ok": {"6": 2825}}), "{got:#}");
    // Found at the bus's rate (the pseudo-terminal does not follow the host's rate yet, so
    // the servo answers at every rate LeRobot tries: docs/commissioning.md).
    assert_eq!(got["scan_port"]["ok"]["1000000"], json!([6]), "{got:#}");
    stack.stop();
}
