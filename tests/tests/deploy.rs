//! What deploy/ ships, checked against the binaries: the default configuration files are what
//! the binaries print and load, the systemd units verify, and the processes speak the systemd
//! notify protocol (READY=1, then WATCHDOG=1 keep-alives) as the units' `Type=notify` and
//! `WatchdogSec=` expect.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{binary, scratch, wait_for, Proc};
use std::os::unix::net::UnixDatagram;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};
use telemetry::config::ProcessConfig;

fn deploy() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy")
}

fn printed(bin: &str, flag: &str) -> String {
    let out = Command::new(binary(bin)).arg(flag).output().unwrap();
    assert!(out.status.success(), "{bin} {flag} failed");
    String::from_utf8(out.stdout).unwrap()
}

#[test]
fn the_shipped_configuration_files_are_what_the_binaries_print_and_load() {
    for (bin, flag, file) in [
        ("bus-driver", "--print-default-config", "bus-driver.toml"),
        (
            "bus-driver",
            "--print-default-calibration",
            "calibration.toml",
        ),
        ("supervisor", "--print-default-config", "supervisor.toml"),
        ("fleet-agent", "--print-default-config", "fleet-agent.toml"),
        ("nori-camera", "--print-default-config", "camera.toml"),
        ("nori-lidar", "--print-default-config", "lidar.toml"),
        ("nori-base", "--print-default-config", "base.toml"),
        ("nori-lift", "--print-default-config", "lift.toml"),
    ] {
        let shipped = std::fs::read_to_string(deploy().join("config").join(file)).unwrap();
        assert_eq!(
            printed(bin, flag),
            shipped,
            "deploy/config/{file} differs from `{bin} {flag}`"
        );
        // Commented: a reader of /etc/nori learns what each key means.
        let comments = shipped.lines().filter(|l| l.trim_start().starts_with('#'));
        assert!(comments.count() >= 5, "{file} is not commented");
    }
    // The files load as they are installed (the driver finds the calibration next to its file).
    bus_driver::LoadedConfig::load(&deploy().join("config/bus-driver.toml")).unwrap();
    supervisor::SupervisorConfig::load(&deploy().join("config/supervisor.toml")).unwrap();
    fleet_agent::AgentConfig::load(&deploy().join("config/fleet-agent.toml")).unwrap();
    camera::config::CamerasConfig::load(&deploy().join("config/camera.toml")).unwrap();
    lidar::config::LidarConfig::load(&deploy().join("config/lidar.toml")).unwrap();
    base::config::BaseConfig::load(&deploy().join("config/base.toml")).unwrap();
    lift::config::LiftConfig::load(&deploy().join("config/lift.toml")).unwrap();
}

#[test]
fn the_systemd_units_verify() {
    let units = deploy().join("systemd");
    let Ok(out) = Command::new("systemd-analyze").arg("--version").output() else {
        eprintln!("systemd-analyze not on this machine: unit verification skipped");
        return;
    };
    assert!(out.status.success());
    // Verified where they would be installed, with ExecStart at the binaries just built.
    let dir = scratch("units");
    let bin_dir = binary("bus-driver").parent().unwrap().to_path_buf();
    for entry in std::fs::read_dir(&units).unwrap().flatten() {
        let text = std::fs::read_to_string(entry.path()).unwrap();
        let text = text.replace("/usr/bin", bin_dir.to_str().unwrap());
        std::fs::write(dir.join(entry.file_name()), text).unwrap();
    }
    // A template is verified as one of its instances.
    std::fs::copy(
        dir.join("nori-camera@.service"),
        dir.join("nori-camera@head.service"),
    )
    .unwrap();
    for unit in [
        "nori-supervisor.service",
        "nori-bus-driver.service",
        "nori-fleet-agent.service",
        "nori-camera@head.service",
        "nori-lidar.service",
        "nori-base.service",
        "nori-lift.service",
        "nori-blackbox.service",
        "nori.target",
    ] {
        let out = Command::new("systemd-analyze")
            .args(["verify", "--man=no"])
            .arg(dir.join(unit))
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        // Other units of the machine may draw warnings; ours must draw none.
        let ours: Vec<&str> = stderr.lines().filter(|l| l.contains("nori")).collect();
        assert!(out.status.success() && ours.is_empty(), "{unit}: {stderr}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Datagrams received on `socket` until `within` has passed.
fn messages(socket: &UnixDatagram, within: Duration) -> Vec<String> {
    socket
        .set_read_timeout(Some(Duration::from_millis(50)))
        .unwrap();
    let until = Instant::now() + within;
    let mut out = Vec::new();
    let mut buf = [0u8; 512];
    while Instant::now() < until {
        if let Ok(n) = socket.recv(&mut buf) {
            out.push(String::from_utf8_lossy(&buf[..n]).into_owned());
        }
    }
    out
}

#[test]
fn the_processes_notify_readiness_and_keep_the_watchdog_fed() {
    let dir = scratch("notify");
    let domain = format!("nori_notify_{}", std::process::id());
    let dev = dir.join("dev");
    let _sim = Proc::spawn(
        "simulator",
        &binary("nori"),
        &[
            "sim",
            "serve",
            "--bus",
            "left_arm",
            "--dir",
            dev.to_str().unwrap(),
        ],
        &dir.join("sim.log"),
    );
    let mut socks = Vec::new();
    // Killed if the test fails half-way (they would outlive it otherwise).
    let mut procs = KillOnDrop(Vec::new());
    for (name, args) in [
        (
            "supervisor",
            vec!["--domain", &domain, "--status-every", "0", "--trip-file"],
        ),
        (
            "bus-driver",
            vec![
                "--bus",
                "left_arm",
                "--device-dir",
                dev.to_str().unwrap(),
                "--domain",
                &domain,
                "--status-every",
                "0",
            ],
        ),
        ("nori-base", vec!["--domain", &domain]),
    ] {
        let path = dir.join(format!("{name}.notify"));
        let socket = UnixDatagram::bind(&path).unwrap();
        let mut args: Vec<String> = args.into_iter().map(String::from).collect();
        if name == "supervisor" {
            args.push(dir.join("trips").display().to_string());
        }
        let log = std::fs::File::create(dir.join(format!("{name}.log"))).unwrap();
        let child = Command::new(binary(name))
            .args(&args)
            .env("NOTIFY_SOCKET", &path)
            .env("WATCHDOG_USEC", "200000")
            .stderr(log)
            .stdout(std::process::Stdio::null())
            .spawn()
            .unwrap();
        procs.0.push(child);
        socks.push((name, socket));
    }
    for (name, socket) in &socks {
        let ready = wait_for(Duration::from_secs(20), &format!("{name} READY=1"), || {
            messages(socket, Duration::from_millis(100))
                .into_iter()
                .find(|m| m.lines().any(|l| l == "READY=1"))
        });
        assert!(ready.contains("STATUS="), "{name}: {ready}");
        // 200 ms watchdog: a keep-alive every 100 ms, so about ten in a second (a loaded
        // machine may delay a few; far fewer would let systemd kill a healthy process).
        let pings = messages(socket, Duration::from_secs(1))
            .iter()
            .filter(|m| m.lines().any(|l| l == "WATCHDOG=1"))
            .count();
        assert!(
            (3..=15).contains(&pings),
            "{name}: {pings} keep-alives in a second"
        );
    }
    for mut p in procs.0.drain(..) {
        nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(p.id() as i32),
            nix::sys::signal::Signal::SIGTERM,
        )
        .unwrap();
        p.wait().unwrap();
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_fleet_router_configurations_load() {
    for file in ["site-router.json5", "cloud-router.json5"] {
        let path = deploy().join("zenoh").join(file);
        let config = fleet_agent::zenoh::Config::from_file(&path)
            .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let acl = config.get_json("access_control").unwrap();
        assert!(
            acl.contains("\"default_permission\":\"deny\""),
            "{file}: {acl}"
        );
    }
}

/// Children of a test that are killed and reaped when it ends, however it ends.
struct KillOnDrop(Vec<std::process::Child>);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// The words a shell file under deploy/ assigns between `open` and `close` (`name=(` … `)`, or
/// `name="` … `"`, over lines).
fn shell_words(file: &str, open: &str, close: char) -> Vec<String> {
    let text = std::fs::read_to_string(deploy().join(file)).unwrap();
    let start = text
        .find(open)
        .unwrap_or_else(|| panic!("{file} sets {open}..."))
        + open.len();
    let end = start + text[start..].find(close).unwrap();
    text[start..end]
        .split_whitespace()
        .map(str::to_string)
        .collect()
}

/// The list deploy/binaries.sh gives the packages and the arm64 build (`robot_bins=(...)`).
fn robot_binaries() -> Vec<String> {
    shell_words("binaries.sh", "robot_bins=(", ')')
}

#[test]
fn every_unit_runs_a_binary_the_robot_package_ships() {
    let shipped = robot_binaries();
    for name in &shipped {
        binary(name); // a name the workspace builds
    }
    let mut programs = 0;
    for entry in std::fs::read_dir(deploy().join("systemd"))
        .unwrap()
        .flatten()
    {
        let text = std::fs::read_to_string(entry.path()).unwrap();
        for exec in text.lines().filter_map(|l| l.strip_prefix("ExecStart=")) {
            let program = exec.split_whitespace().next().unwrap();
            let name = program.strip_prefix("/usr/bin/").unwrap_or(program);
            assert!(
                shipped.iter().any(|b| b == name),
                "{}: {program} is not in deploy/binaries.sh's robot_bins (the packages and the \
                 arm64 build would leave it out)",
                entry.file_name().to_string_lossy()
            );
            programs += 1;
        }
    }
    assert!(programs >= 8, "{programs} units with an ExecStart found");
}

/// The units as the maintainer scripts list them (`nori_units="..."` in
/// deploy/deb/maintainer-common.sh), in the order the postinst starts them again.
fn maintainer_units() -> Vec<String> {
    shell_words("deb/maintainer-common.sh", "nori_units=\"", '"')
}

#[test]
fn the_maintainer_scripts_start_the_units_in_an_order_their_after_lines_allow() {
    let order = maintainer_units();
    let mut files = 0;
    for entry in std::fs::read_dir(deploy().join("systemd"))
        .unwrap()
        .flatten()
    {
        let file = entry.file_name().to_string_lossy().into_owned();
        if !(file.ends_with(".service") || file.ends_with(".target")) {
            continue;
        }
        files += 1;
        // A template stands for each of its instances the scripts name.
        let names: Vec<&String> = order
            .iter()
            .filter(|u| {
                **u == file || file.ends_with("@.service") && u.starts_with(&file[..file.len() - 8])
            })
            .collect();
        assert!(!names.is_empty(), "{file} is not in nori_units");
        let text = std::fs::read_to_string(entry.path()).unwrap();
        let after = text
            .lines()
            .filter_map(|l| l.strip_prefix("After="))
            .flat_map(str::split_whitespace);
        for partner in after.filter(|p| p.starts_with("nori")) {
            let at = |u: &str| order.iter().position(|o| o == u);
            let partner_at =
                at(partner).unwrap_or_else(|| panic!("{file}: After={partner}, not in nori_units"));
            for name in &names {
                assert!(
                    partner_at < at(name).unwrap(),
                    "{name} comes before {partner} in nori_units, but starts after it"
                );
            }
        }
    }
    assert!(files >= 9, "{files} unit files");
}
