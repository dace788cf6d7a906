//! `nori up` as a developer uses it: the whole stack on the simulated robot, its lidar included,
//! and Ctrl-C leaves torque off on every servo, the lidar stopped, no process and nothing of the
//! state plane behind.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{binary, plane_files, scratch, wait_for};
use std::process::{Command, Stdio};
use std::time::Duration;
use telemetry::frames::STATE_FLAG_SAFE_STATE;
use telemetry::plane::{self, newest, Plane};

/// Processes whose command line mentions `needle`.
fn processes_with(needle: &str) -> Vec<String> {
    nori_tests::processes(|args| args.iter().any(|a| a.contains(needle)))
        .into_iter()
        .map(|(pid, args)| format!("{pid}: {}", args.join(" ")))
        .collect()
}

#[test]
fn ctrl_c_leaves_torque_off_no_process_and_no_plane_resource() {
    let dir = scratch("up");
    let domain = format!("nori_up_{}", std::process::id());
    let dev = dir.join("dev");
    let log = std::fs::File::create(dir.join("up.log")).unwrap();
    let mut up = Command::new(binary("nori"))
        .args(["up", "--dir", dev.to_str().unwrap(), "--domain", &domain])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .unwrap();
    {
        let node = Plane::open(&domain, "test").unwrap();
        let states = node.subscriber(&plane::JOINT_STATE).unwrap();
        let all_up = wait_for(Duration::from_secs(30), "all 18 joints driven", || {
            newest(&states).filter(|s| {
                s.joint_count == 18
                    && s.flags & STATE_FLAG_SAFE_STATE == 0
                    && s.joints()
                        .iter()
                        .all(|j| j.is_valid() && j.torque_enabled == 1)
            })
        });
        assert_eq!(all_up.joint_count, 18);
        let scans = node.subscriber(&plane::LIDAR_SCAN).unwrap();
        let scan = wait_for(Duration::from_secs(20), "a lidar scan", || newest(&scans));
        assert!(scan.point_count > 400, "{} points", scan.point_count);
    }
    // Ctrl-C: the terminal sends SIGINT to nori (its children are in their own process group).
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(up.id() as i32),
        nix::sys::signal::Signal::SIGINT,
    )
    .unwrap();
    let status = wait_for(Duration::from_secs(20), "nori up to exit", || {
        up.try_wait().unwrap()
    });
    assert!(status.success(), "nori up exited with {status}");
    let log = std::fs::read_to_string(dir.join("up.log")).unwrap();

    let left = processes_with(&domain);
    assert!(left.is_empty(), "processes left: {left:?}\n{log}");
    let files = plane_files(&domain);
    assert!(
        files.is_empty(),
        "left on the state plane: {files:?}\n{log}"
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dev.join("sim-report.json")).unwrap())
            .unwrap();
    let mut servos = 0;
    for bus in report["buses"].as_array().unwrap() {
        for servo in bus["servos"].as_array().unwrap() {
            assert_eq!(
                servo["torque_enabled"], false,
                "{} left energised\n{log}",
                servo["joint"]
            );
            servos += 1;
        }
    }
    assert_eq!(servos, 18);
    assert_eq!(
        report["lidar"]["scanning"], false,
        "the lidar was told to stop\n{log}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
