//! Bad configuration files given to the real binaries: each one refuses to start, exits with an
//! error, and its message names the file and the key. Nothing starts: no device is opened, no
//! state-plane service created (the run would otherwise wait for devices or a supervisor).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{binary, scratch};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Runs `program args`, which must exit within 10 s; returns (exit code, stderr).
fn run(program: &Path, args: &[&str], err_path: &Path) -> (Option<i32>, String) {
    let err_file = std::fs::File::create(err_path).unwrap();
    let mut child = Command::new(program)
        .args(args)
        // The message as an operator sees it, without a backtrace.
        .env("RUST_BACKTRACE", "0")
        .env("RUST_LIB_BACKTRACE", "0")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(err_file)
        .spawn()
        .unwrap();
    let until = Instant::now() + Duration::from_secs(10);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if Instant::now() > until {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "{} {args:?} did not exit: the configuration was accepted",
                program.display()
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    (status.code(), std::fs::read_to_string(err_path).unwrap())
}

/// Each `(from, to)` edit of `default` written to a file and given to `program --config`;
/// `key` must appear in the error with the file's path.
fn refuses(
    program: &str,
    default: &str,
    edits: &[(&str, &str, &str)],
    extra: &[&str],
    file_name: &str,
) {
    let dir = scratch(&format!("bad-configs-{program}"));
    for (i, (from, to, key)) in edits.iter().enumerate() {
        let text = default.replacen(from, to, 1);
        assert_ne!(text, default, "{program}: edit {from:?} did not apply");
        let path = dir.join(format!("{i}-{file_name}"));
        std::fs::write(&path, &text).unwrap();
        let mut args = vec!["--config", path.to_str().unwrap()];
        args.extend_from_slice(extra);
        let (code, stderr) = run(&binary(program), &args, &dir.join(format!("{i}.stderr")));
        // EX_CONFIG: the unit does not restart a process that refused its configuration.
        assert_eq!(code, Some(78), "{program} with {to:?}: {stderr}");
        assert!(
            stderr.contains(key) && stderr.contains(path.to_str().unwrap()),
            "{program} with {to:?}: the error does not name {key:?} and the file:\n{stderr}"
        );
        eprintln!("{program}: {to:?} -> {}", stderr.trim_end());
    }
}

#[test]
fn the_bus_driver_refuses_bad_configurations_naming_file_and_key() {
    let dir = scratch("bad-configs-domain");
    let domain = format!("nori_badcfg_{}", std::process::id());
    let devices = dir.join("no-devices");
    refuses(
        "bus-driver",
        bus_driver::config::DEFAULT_CONFIG_TOML,
        &[
            ("rate-hz = 200", "rate-hz = 200\nrate_hz = 100", "rate_hz"),
            ("rate-hz = 200", "rate-hz = \"fast\"", "rate-hz"),
            (
                "max-temperature-c = 60",
                "max-temperature-c = 70",
                "max-temperature-c",
            ),
            (
                "goal-max-age-ms = 100",
                "goal-max-age-ms = 0",
                "goal-max-age-ms",
            ),
            (
                "safe-hold-torque-percent = 20",
                "safe-hold-torque-percent = 100",
                "safe-hold-torque-percent",
            ),
        ],
        &[
            "--domain",
            &domain,
            "--device-dir",
            devices.to_str().unwrap(),
            "--wait-for-devices",
            "0",
        ],
        "bus-driver.toml",
    );
    // A calibration range outside the servo's travel: the calibration file and joint named.
    let cal = bus_driver::config::DEFAULT_CALIBRATION_TOML.replacen(
        "range-max = 3906",
        "range-max = 5000",
        1,
    );
    let cal_path = dir.join("calibration.toml");
    std::fs::write(&cal_path, cal).unwrap();
    let config = nori_tests::driver_config_with_calibration_beside(&dir);
    let (code, stderr) = run(
        &binary("bus-driver"),
        &[
            "--config",
            config.to_str().unwrap(),
            "--domain",
            &domain,
            "--wait-for-devices",
            "0",
        ],
        &dir.join("calibration.stderr"),
    );
    assert_eq!(code, Some(78), "{stderr}");
    assert!(
        stderr.contains(cal_path.to_str().unwrap())
            && stderr.contains("joint.left_shoulder_pitch")
            && stderr.contains("5000"),
        "{stderr}"
    );
    assert!(
        nori_tests::plane_files(&domain).is_empty(),
        "a refused configuration opened the state plane"
    );
}

#[test]
fn the_supervisor_refuses_bad_configurations_naming_file_and_key() {
    let domain = format!("nori_badcfg_sup_{}", std::process::id());
    refuses(
        "supervisor",
        supervisor::config::DEFAULT_CONFIG_TOML,
        &[
            ("trip-c = 59", "trip-c = 61", "thermal.trip-c"),
            ("[stall]", "[stall]\nwindw = 3", "windw"),
            ("window = 15", "window = \"15\"", "window"),
            (
                "driver-timeout-ms = 50",
                "driver-timeout-ms = 0",
                "driver-timeout-ms",
            ),
        ],
        &["--domain", &domain],
        "supervisor.toml",
    );
    assert!(nori_tests::plane_files(&domain).is_empty());
}

#[test]
fn the_fleet_agent_refuses_bad_configurations_naming_file_and_key() {
    let domain = format!("nori_badcfg_agent_{}", std::process::id());
    refuses(
        "fleet-agent",
        fleet_agent::config::DEFAULT_CONFIG_TOML,
        &[
            ("mode = \"peer\"", "mode = \"router\"", "zenoh.mode"),
            ("max-age-ms = 250", "max-age-ms = 0", "actions.max-age-ms"),
            ("blend-new = 0.7", "blend-now = 0.7", "blend-now"),
            (
                "connect = [\"tcp/127.0.0.1:7447\", \"tcp/127.0.0.1:7448\", \"tcp/127.0.0.1:7449\"]",
                "connect = [\"udp/127.0.0.1:7447\"]",
                "zenoh.connect",
            ),
            ("bound-bytes = 1048576", "bound-bytes = 100", "journal.bound-bytes"),
            ("resend-after-ms = 2000", "resend-after-ms = 0", "journal.resend-after-ms"),
            ("window = 256", "window = 0", "journal.window"),
        ],
        &["--domain", &domain],
        "fleet-agent.toml",
    );
    assert!(nori_tests::plane_files(&domain).is_empty());
}

/// The exit code says the fault's class (ARCHITECTURE.md, "Exit codes"): a device that is not
/// there is worth a restart (69), a bus the configuration does not have is not (78).
#[test]
fn the_driver_exits_with_the_class_of_its_fault() {
    let dir = scratch("exit-codes");
    let domain = format!("nori_exit_{}", std::process::id());
    let devices = dir.join("no-devices");
    let common = [
        "--domain",
        &domain,
        "--device-dir",
        devices.to_str().unwrap(),
        "--wait-for-devices",
        "0",
    ];
    let (code, stderr) = run(&binary("bus-driver"), &common, &dir.join("absent.stderr"));
    assert_eq!(code, Some(69), "no device: {stderr}");
    assert!(stderr.contains("no device"), "{stderr}");
    let mut args = common.to_vec();
    args.extend(["--bus", "tail"]);
    let (code, stderr) = run(&binary("bus-driver"), &args, &dir.join("bus.stderr"));
    assert_eq!(code, Some(78), "unknown bus: {stderr}");
    assert!(
        stderr.contains("--bus") && stderr.contains("\"tail\""),
        "{stderr}"
    );
}

/// Every robot process takes the same `--run-for` and refuses one that is no positive number
/// of seconds as a configuration fault, naming the option; before the options were shared,
/// the supervisor and the fleet agent panicked on it (a crash, restarted by systemd for ever).
#[test]
fn every_robot_process_refuses_a_run_time_that_is_no_positive_number() {
    let dir = scratch("run-for");
    let domain = format!("nori_runfor_{}", std::process::id());
    for program in [
        "bus-driver",
        "supervisor",
        "fleet-agent",
        "nori-lidar",
        "nori-camera",
    ] {
        for bad in ["-1", "nan", "inf", "0"] {
            let run_for = format!("--run-for={bad}");
            let mut args = vec!["--domain", &domain, &run_for];
            if program == "nori-camera" {
                args.extend(["--camera", "head"]);
            }
            let err = dir.join(format!("{program}{bad}.stderr"));
            let (code, stderr) = run(&binary(program), &args, &err);
            assert_eq!(code, Some(78), "{program} {run_for}: {stderr}");
            assert!(stderr.contains("--run-for"), "{program}: {stderr}");
        }
    }
}

/// Nori Lab off loopback would carry its access token and every command over plain `ws://`,
/// readable and replayable by anyone on the network: it refuses to serve there, even with a
/// token file, and says how to reach it instead.
#[test]
fn nori_lab_refuses_to_serve_beyond_loopback_without_tls() {
    let dir = scratch("bad-configs-lab");
    let token = dir.join("token");
    std::fs::write(&token, "a-token-of-sixteen-or-more\n").unwrap();
    let (code, stderr) = run(
        &binary("nori-lab"),
        &[
            "--http",
            "0.0.0.0:0",
            "--token-file",
            token.to_str().unwrap(),
            "--domain",
            "nori_bad_configs_lab",
        ],
        &dir.join("lab.stderr"),
    );
    assert_ne!(code, Some(0), "{stderr}");
    assert!(
        stderr.contains("0.0.0.0:0") && stderr.contains("ssh -L"),
        "{stderr}"
    );
}
