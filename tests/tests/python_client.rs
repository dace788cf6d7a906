//! The Python client (`python/nori_client`): its own tests (the codec against the golden bytes
//! the Rust side checks too), and a round trip through a real zenoh session against the real
//! fleet agent on the simulated robot: the layout by name, observations with the wrist
//! camera's picture decoded to numpy, action chunks that move the elbow through the gate, and
//! nonsense the gate refuses and counts.
//!
//! The client lives in its own virtual environment (`python/nori_client/install.sh`, which
//! `.ci/run` calls); outside CI a missing one skips these tests loudly, in CI it fails them.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{check_left_arm_report, free_endpoint, newest_read, scratch, wait_for, ArmStack};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};
use telemetry::plane::{self, Plane};

const ELBOW: usize = 3;

fn client_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../python/nori_client")
}

/// The client's Python (`NORI_CLIENT_PYTHON`, else the install script's environment); `None`
/// (said loudly) outside CI when it is not installed.
fn client_python() -> Option<PathBuf> {
    let python = std::env::var_os("NORI_CLIENT_PYTHON")
        .map(PathBuf::from)
        .or_else(|| {
            std::env::var_os("HOME")
                .map(|h| PathBuf::from(h).join(".cache/nori/client-venv/bin/python"))
        })?;
    let ok = Command::new(&python)
        .args(["-c", "import nori_client, pytest"])
        .status()
        .is_ok_and(|s| s.success());
    if !ok {
        assert!(
            std::env::var_os("CI").is_none(),
            "the Python client is not installed in CI (.ci/run runs python/nori_client/install.sh)"
        );
        eprintln!("\n!!!!!!!! SKIPPED the Python client's tests: run python/nori_client/install.sh !!!!!!!!\n");
        return None;
    }
    Some(python)
}

/// Runs `command` to its end, killed (and the test failed) after `within`: a Python process
/// that hangs (a zenoh session never closed) must not hang the test run.
fn run_bounded(command: &mut Command, within: Duration) -> Output {
    let mut child = command
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let until = Instant::now() + within;
    while child.try_wait().unwrap().is_none() {
        if Instant::now() > until {
            child.kill().unwrap();
            let out = child.wait_with_output().unwrap();
            panic!(
                "{command:?} still running after {within:?}:\n{}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.wait_with_output().unwrap()
}

#[test]
fn the_python_clients_own_tests_pass() {
    let Some(python) = client_python() else {
        return;
    };
    let out = run_bounded(
        Command::new(python)
            .args(["-m", "pytest", "-q", "-p", "no:cacheprovider"])
            .arg(client_dir().join("tests")),
        Duration::from_secs(120),
    );
    assert!(
        out.status.success(),
        "pytest:\n{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn a_python_policy_moves_the_simulated_arm_through_the_gate() {
    let Some(python) = client_python() else {
        return;
    };
    let endpoint = free_endpoint();
    let id = "sim-python";
    let (stack, mut camera) = nori_tests::seeing_robot("py-client", id, &endpoint);
    let node = Plane::open(&stack.domain, "test").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();

    let out = run_bounded(
        Command::new(python)
            .arg(client_dir().join("tests/robot_round_trip.py"))
            .args([
                "--listen",
                &endpoint,
                "--robot",
                id,
                "--camera",
                "left_wrist",
            ])
            .args([
                "--joint",
                "left_elbow",
                "--target",
                "-0.8",
                "--seconds",
                "4",
            ]),
        Duration::from_secs(120),
    );
    assert!(
        out.status.success(),
        "the Python policy:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    eprintln!("Python policy: {report}");
    assert_eq!(
        report["joints"][ELBOW], "left_elbow",
        "names from the layout"
    );
    assert_eq!(report["picture_shape"], serde_json::json!([120, 160, 3]));
    assert!(
        report["picture_spread"].as_i64().unwrap() > 60,
        "a picture, not a blank"
    );
    assert!(report["observations"].as_u64().unwrap() >= 20, "{report}");
    assert_eq!(report["undecodable"], serde_json::json!({}));
    // The elbow went where the Python policy sent it, as read on the state plane.
    let elbow = wait_for(Duration::from_secs(5), "an elbow reading", || {
        newest_read(&states, ELBOW)
    });
    assert!(
        (elbow.position_rad + 0.8).abs() < 0.1,
        "elbow at {} rad, the policy's target -0.8",
        elbow.position_rad
    );

    // The robot's own account: the chunks accepted, the nonsense refused by reason.
    let session = nori_tests::listening_session(&endpoint);
    let status = nori_tests::agent_status(&session, id);
    let c = &status.counters;
    let sent = report["chunks_sent"].as_u64().unwrap();
    assert!(
        c.actions_accepted >= sent * 9 / 10,
        "{} of {sent} chunks accepted: {c:?}",
        c.actions_accepted
    );
    assert_eq!(c.actions_rejected["not_finite"], 1, "{c:?}");
    assert_eq!(c.actions_rejected["out_of_range"], 1, "{c:?}");
    drop(session);
    camera.kill();
    drop(states);
    drop(node);
    check_left_arm_report(&stack.stop(), 60.0);
}

/// `nori-serve-lerobot` against a checkpoint trained on joints the robot does not have: refused
/// at start (before any LeRobot code loads), the mismatch named, nothing sent.
#[test]
fn a_checkpoint_that_names_other_joints_is_refused_at_start() {
    let Some(python) = client_python() else {
        return;
    };
    let files = scratch("py-serve-files");
    let checkpoint = files.join("pretrained_model");
    let dataset = files.join("dataset");
    std::fs::create_dir_all(&checkpoint).unwrap();
    std::fs::create_dir_all(dataset.join("meta")).unwrap();
    let feature = |kind: &str| serde_json::json!({"type": kind, "shape": [2]});
    std::fs::write(
        checkpoint.join("config.json"),
        serde_json::json!({
            "type": "act",
            "input_features": {"observation.state": feature("STATE")},
            "output_features": {"action": feature("ACTION")},
        })
        .to_string(),
    )
    .unwrap();
    let names =
        serde_json::json!({"dtype": "float32", "shape": [2], "names": ["left_elbow", "left_knee"]});
    std::fs::write(
        dataset.join("meta/info.json"),
        serde_json::json!({"fps": 30, "features": {"observation.state": names, "action": names}})
            .to_string(),
    )
    .unwrap();
    let endpoint = free_endpoint();
    let id = "sim-mismatch";
    let mut stack = ArmStack::start("py-serve", &[]);
    stack.restart_agent(id, &endpoint);

    let server = python.with_file_name("nori-serve-lerobot");
    let out = run_bounded(
        Command::new(&server)
            .arg(&checkpoint)
            .args(["--robot", id, "--listen", &endpoint])
            .arg("--dataset")
            .arg(&dataset),
        Duration::from_secs(90),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("does not fit robot sim-mismatch")
            && stderr.contains("joints ['left_knee'] are not the robot's"),
        "{stderr}"
    );
    check_left_arm_report(&stack.stop(), 60.0);
}
