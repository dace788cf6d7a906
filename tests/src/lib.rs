//! Process-level test support: the real binaries, started, watched and cleaned up.
//!
//! Tests here spawn `nori` (the simulator), `supervisor` and `bus-driver` exactly as `nori up` or
//! systemd do,
//! talk to them over the state plane, and check what the simulated servos received. Every child
//! is killed when its guard drops, so a failing test leaves no process behind. [`probe`]
//! measures how much this shared machine disturbed a loop, for rate bounds judged against it.

#![allow(clippy::unwrap_used, clippy::expect_used)]

pub mod probe;
pub use probe::SchedulingProbe;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;
use std::time::{Duration, Instant};
use telemetry::config::ProcessConfig;

/// The profile the binaries a test starts are built in, and their directory: the test's own
/// (`tested` under the README's command), or `tested` under an unoptimised test (unoptimised,
/// the simulator falls behind real time in bursts on a two-core machine, so a moving joint looks
/// static to the supervisor: a timing artefact no robot has).
fn binaries_profile() -> (String, PathBuf) {
    let exe = std::env::current_exe().expect("test executable path");
    let dir = exe
        .ancestors()
        .nth(2)
        .expect("target/<profile>/deps/<test>")
        .to_path_buf();
    match dir.file_name().and_then(|n| n.to_str()) {
        Some(name) if name != "debug" => (name.to_string(), dir),
        _ => ("tested".into(), dir.with_file_name("tested")),
    }
}

/// Runs the operator's `nori ARGS --domain DOMAIN`, which must succeed; returns what it said
/// (its stderr).
pub fn nori_ok(args: &[&str], domain: &str) -> String {
    let out = std::process::Command::new(binary("nori"))
        .args(args)
        .args(["--domain", domain])
        .output()
        .expect("nori runs");
    let said = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "nori {args:?}: {said}");
    said
}

/// One test of this binary at a time, for the tests that run whole stacks and measure their
/// timing: two stacks at once on a two-core machine starve each other's control loops.
pub fn serial() -> std::sync::MutexGuard<'static, ()> {
    static TURN: std::sync::Mutex<()> = std::sync::Mutex::new(());
    TURN.lock().unwrap_or_else(|e| e.into_inner())
}

/// Path of a workspace binary, built once per test run ([`binaries_profile`]: the release's
/// optimisation, the workspace's code with overflow checks): the processes run as deployed.
/// Under the README's `cargo test --profile tested` every library they link is already built,
/// with the same features, so this compiles the binaries' own crates and no more.
pub fn binary(name: &str) -> PathBuf {
    static BUILT: OnceLock<()> = OnceLock::new();
    BUILT.get_or_init(|| {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let mut build = Command::new(cargo);
        // Without the variables cargo sets for this test (CARGO_PKG_NAME, CARGO_MANIFEST_DIR,
        // ...): some build scripts (ring's) declare them with rerun-if-env-changed, and seeing
        // this crate's values would rebuild TLS and zenoh from scratch, then again for the
        // README's command from a shell.
        for (key, _) in std::env::vars_os() {
            let key = key.to_string_lossy();
            let set_for_this_crate = ["CARGO_PKG_", "CARGO_MANIFEST_", "CARGO_BIN_"]
                .iter()
                .any(|p| key.starts_with(p))
                || [
                    "CARGO_CRATE_NAME",
                    "CARGO_PRIMARY_PACKAGE",
                    "CARGO_TARGET_TMPDIR",
                    "CARGO_RUSTC_CURRENT_DIR",
                    "OUT_DIR",
                ]
                .contains(&key.as_ref());
            if set_for_this_crate {
                build.env_remove(key.as_ref());
            }
        }
        let status = build
            // With the test targets: the dev-dependencies' features (proptest's tempfile,
            // prometheus-parse's regex) are then unified as in the README's test command, so
            // the binaries link the very libraries the test build made. `--bins` alone
            // resolves without them and rebuilt a third of the workspace.
            .args([
                "build",
                "--profile",
                &binaries_profile().0,
                "--quiet",
                "--workspace",
            ])
            .args(["--bins", "--tests"])
            .status()
            .expect("running cargo build for the binaries");
        assert!(status.success(), "building the binaries failed");
    });
    let path = binaries_profile().1.join(name);
    assert!(path.exists(), "{} was not built", path.display());
    path
}

/// A child process of a test ([`stack::Managed`], as `nori up` runs them): its stderr to a log,
/// its stdout kept; killed (SIGKILL) and reaped when dropped, unless stopped before.
pub struct Proc(stack::Managed);

impl Proc {
    /// Starts `program` with `args`; its stderr goes to `log`.
    pub fn spawn(name: &str, program: &Path, args: &[&str], log: &Path) -> Proc {
        let args: Vec<String> = args.iter().map(|a| a.to_string()).collect();
        Proc::spawn_owned(name, program, &args, log)
    }

    /// [`Proc::spawn`] with owned arguments (as [`stack::Run`] spells them).
    pub fn spawn_owned(name: &str, program: &Path, args: &[String], log: &Path) -> Proc {
        let mut child = stack::Managed::new(name, program, args);
        child.log_to(log).expect("log file");
        child.capture_stdout();
        child.start().unwrap_or_else(|e| panic!("{e}"));
        Proc(child)
    }

    /// A placeholder for a process not started yet.
    pub fn none(name: &str) -> Proc {
        Proc(stack::Managed::new(name, Path::new(name), &[]))
    }

    /// Process id (0 when not running).
    pub fn pid(&self) -> u32 {
        self.0.pid().unwrap_or(0)
    }

    /// Sends SIGTERM and waits up to `within`; returns the exit code and stdout. Fails the test
    /// if it had to be killed.
    pub fn terminate(&mut self, within: Duration) -> (Option<i32>, String) {
        let name = self.0.name().to_string();
        let stopped = self.0.stop(within).expect("already stopped");
        assert!(
            !stopped.killed,
            "{name} did not stop within {within:?} of SIGTERM (stdout: {})",
            stopped.stdout
        );
        (stopped.code(), stopped.stdout)
    }

    /// Waits up to `within` for it to exit by itself; returns the exit code and stdout. Fails
    /// the test if it is still running then.
    pub fn wait_exit(&mut self, within: Duration) -> (Option<i32>, String) {
        let until = std::time::Instant::now() + within;
        while !self.0.exited() {
            assert!(
                std::time::Instant::now() < until,
                "{} still running after {within:?}",
                self.0.name()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        let stopped = self.0.stop(Duration::ZERO).expect("exited");
        (stopped.code(), stopped.stdout)
    }

    /// SIGKILL, at once (a crash), and reaps it.
    pub fn kill(&mut self) {
        self.0.kill();
    }

    /// SIGTERM, then SIGKILL after `within` if it still runs; asserts nothing (a failed test's
    /// unwinding stops what it started this way).
    pub fn stop_within(&mut self, within: Duration) {
        let _ = self.0.stop(within);
    }

    /// Whether it is still running.
    pub fn running(&mut self) -> bool {
        self.0.running()
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.0.kill();
    }
}

/// The embedded robot and camera configuration with every camera at 160×120, 15 fps (a test's
/// two cores render them), written to `dir`: (robot description, camera configuration).
pub fn small_camera_files(dir: &Path) -> (String, String) {
    let shrink = |text: &str| {
        text.replace(
            "width = 1280\nheight = 720\nfps = 30",
            "width = 160\nheight = 120\nfps = 15",
        )
    };
    let robot = dir.join("robot.toml");
    std::fs::write(&robot, shrink(sim::description::NORI_A3_TOML)).expect("robot.toml");
    let cameras = dir.join("camera.toml");
    std::fs::write(&cameras, shrink(camera::config::DEFAULT_CONFIG_TOML)).expect("camera.toml");
    (robot.display().to_string(), cameras.display().to_string())
}

/// A simulated robot (the left arm, cameras at 160×120) whose fleet agent, robot `id`,
/// connects to zenoh `endpoint` and sends the left wrist camera's JPEGs in its observations;
/// the camera's process is the second value (the test kills it, or drops it before
/// [`ArmStack::stop`]).
pub fn seeing_robot(tag: &str, id: &str, endpoint: &str) -> (ArmStack, Proc) {
    let files = scratch(&format!("{tag}-files"));
    let (robot, camera_toml) = small_camera_files(&files);
    let agent_toml = files.join("fleet-agent.toml");
    std::fs::write(
        &agent_toml,
        fleet_agent::config::DEFAULT_CONFIG_TOML
            .replace("cameras = []", "cameras = [\"left_wrist\"]"),
    )
    .expect("fleet-agent.toml");
    let mut stack = ArmStack::start(tag, &["--description", &robot]);
    let camera = stack.camera("left_wrist", &camera_toml, 1);
    let config = agent_toml.display().to_string();
    stack.restart_agent_with(&["--robot-id", id, "--connect", endpoint, "--config", &config]);
    (stack, camera)
}

/// A zenoh peer listening on `endpoint` (where a robot's agent connects), as a policy server
/// or a dashboard would be.
pub fn listening_session(endpoint: &str) -> fleet_agent::zenoh::Session {
    fleet_agent::net::open(&fleet_agent::config::ZenohConfig {
        mode: "peer".into(),
        connect: vec![],
        listen: vec![endpoint.into()],
        config_file: None,
    })
    .expect("a zenoh session on loopback")
}

/// A zenoh session of `mode` (`peer`, or `client` as a robot's agent is) connecting to
/// `endpoint`.
pub fn connecting_session(
    endpoint: &str,
    mode: &str,
) -> Result<fleet_agent::zenoh::Session, fleet_agent::net::NetError> {
    fleet_agent::net::open(&fleet_agent::config::ZenohConfig {
        mode: mode.into(),
        connect: vec![endpoint.into()],
        listen: vec![],
        config_file: None,
    })
}

/// Robot `robot`'s fleet agent's status, asked on `session` (retried for up to 10 s).
pub fn agent_status(
    session: &fleet_agent::zenoh::Session,
    robot: &str,
) -> fleet_agent::schema::StatusMsg {
    use fleet_agent::zenoh::Wait;
    wait_for(Duration::from_secs(10), "the agent's status", || {
        let replies = session
            .get(fleet_agent::keys::robot_key(robot, "status"))
            .timeout(Duration::from_secs(2))
            .wait()
            .ok()?;
        let sample = replies.recv().ok()?.into_result().ok()?;
        fleet_agent::schema::decode(&sample.payload().to_bytes()).ok()
    })
}

/// The emulator the process tests run under, if any: `deploy/arm64/cross.sh` runs them as arm64
/// processes under qemu and says so in `NORI_EMULATED`. A timing there measures the emulator,
/// so a test holds its safety invariants under it and only reports its timings.
pub fn emulated() -> Option<String> {
    // Only an arm64 build under the emulator the script names: a variable left set on a native
    // run must not loosen a bound.
    let emulator = std::env::var("NORI_EMULATED").ok()?;
    (cfg!(target_arch = "aarch64") && emulator == "qemu-aarch64").then_some(emulator)
}

/// A fresh scratch directory for one test.
pub fn scratch(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("nori-it-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("scratch dir");
    dir
}

/// Writes `dir/bus-driver.toml`: the default driver configuration reading its calibration from
/// `dir/calibration.toml`; returns its path.
pub fn driver_config_with_calibration_beside(dir: &Path) -> PathBuf {
    let config = dir.join("bus-driver.toml");
    std::fs::write(
        &config,
        format!(
            "calibration-file = \"calibration.toml\"\n{}",
            bus_driver::config::DEFAULT_CONFIG_TOML
        ),
    )
    .expect("the driver's configuration");
    config
}

/// Waits until `f` returns `Some`, polling every 10 ms, or panics after `within` with `what`.
pub fn wait_for<T>(within: Duration, what: &str, mut f: impl FnMut() -> Option<T>) -> T {
    let until = Instant::now() + within;
    loop {
        if let Some(v) = f() {
            return v;
        }
        assert!(
            Instant::now() < until,
            "timed out after {within:?} waiting for {what}"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// The random generator of the randomised process tests (the same seed, the same schedule).
pub use sim::rng::Rng;

pub use telemetry::stats::quantile;

/// A speed held at `want`, judged as a loaded machine allows: the median of the samples within
/// `tolerance`, and at most a fifth of them off by more than three tolerances (a starved lidar
/// holds the base, rightly; a late control period measures its wheels over a longer time than
/// it divides by). Each sample carries what explains it (its flags, its frame), shown when it
/// fails. A product that never reached the speed, or dipped in most samples, still fails.
pub fn assert_cruising<L: std::fmt::Debug>(samples: &[(f32, L)], want: f32, tolerance: f32) {
    assert!(
        !samples.is_empty(),
        "no samples of a speed meant to be {want}"
    );
    let values: Vec<f64> = samples.iter().map(|(v, _)| f64::from(*v)).collect();
    let median = quantile(&values, 0.5) as f32;
    let off: Vec<&(f32, L)> = samples
        .iter()
        .filter(|(v, _)| (v - want).abs() > 3.0 * tolerance)
        .collect();
    assert!(
        (median - want).abs() < tolerance && off.len() * 5 <= samples.len(),
        "measured a median {median} for {want} (within {tolerance}); {} of {} samples off: \
         {off:?}",
        off.len(),
        samples.len()
    );
}

/// `joint` in the newest state frame that read it, older frames dropped; `None` if no waiting
/// frame did. A servo that missed its reply in a cycle (a late reply on a loaded machine) is
/// reported as zeros with `valid == 0`, so reading its goal or position from such a frame
/// reads 0, not where the joint is.
pub fn newest_read(
    states: &telemetry::plane::Sub<telemetry::frames::JointState>,
    joint: usize,
) -> Option<telemetry::frames::JointSample> {
    std::iter::from_fn(|| telemetry::plane::next(states))
        .map(|s| s.joints[joint])
        .filter(|j| j.is_valid())
        .last()
}

/// Files of iceoryx2 under `/dev/shm` and `/tmp/iceoryx2` belonging to `domain`.
pub fn plane_files(domain: &str) -> Vec<PathBuf> {
    fn walk(dir: &Path, prefix: &str, out: &mut Vec<PathBuf>) {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return;
        };
        for e in entries.flatten() {
            let path = e.path();
            if path.is_dir() {
                walk(&path, prefix, out);
            } else if e.file_name().to_string_lossy().starts_with(prefix) {
                out.push(path);
            }
        }
    }
    let prefix = format!("{domain}_");
    let mut out = Vec::new();
    walk(Path::new("/dev/shm"), &prefix, &mut out);
    walk(&std::env::temp_dir().join("iceoryx2"), &prefix, &mut out);
    out.sort();
    out
}

/// The left arm of the robot as three processes on the simulator (a pseudo-terminal), each of
/// which a test may kill and restart as systemd would.
pub struct ArmStack {
    /// Scratch directory (logs, devices, report, trip record).
    pub dir: PathBuf,
    /// State-plane domain.
    pub domain: String,
    /// The simulator.
    pub sim: Proc,
    /// The supervisor.
    pub supervisor: Proc,
    /// The driver.
    pub driver: Proc,
    /// The fleet agent (not started by [`ArmStack::start`]).
    pub agent: Proc,
    /// Arguments added to the driver's (a `--config`, say) at its next (re)start.
    pub driver_args: Vec<String>,
    /// The one bus simulated and driven.
    bus: String,
    starts: u32,
}

impl ArmStack {
    /// Starts the simulator (with `sim_args` added), the supervisor, then the driver.
    pub fn start(tag: &str, sim_args: &[&str]) -> ArmStack {
        let mut stack = ArmStack::simulator_only(tag, sim_args);
        stack.restart_supervisor();
        stack.restart_driver();
        stack
    }

    /// Starts the simulator (with `sim_args` added) only: the test starts the others, in the
    /// order it is about.
    pub fn simulator_only(tag: &str, sim_args: &[&str]) -> ArmStack {
        ArmStack::simulator_only_on(tag, "left_arm", sim_args)
    }

    /// [`ArmStack::simulator_only`] on `bus` instead of the left arm: the driver, started with
    /// `--bus <bus>`, calls it bus 0 whatever its index in the configuration.
    pub fn simulator_only_on(tag: &str, bus: &str, sim_args: &[&str]) -> ArmStack {
        let dir = scratch(tag);
        let domain = format!("nori_{tag}_{}", std::process::id()).replace('-', "_");
        let dev = dir.join("dev");
        let report = dir.join("sim-report.json");
        let mut args = ArmStack::run_of(&domain, &dev, None).simulator(&[bus], &report);
        args.extend(sim_args.iter().map(|a| a.to_string()));
        let sim = Proc::spawn_owned(
            "simulator",
            &binary("nori-sim"),
            &args,
            &dir.join("sim.log"),
        );
        ArmStack {
            supervisor: Proc::none("supervisor"),
            driver: Proc::none("bus-driver"),
            agent: Proc::none("fleet-agent"),
            driver_args: Vec::new(),
            bus: bus.to_string(),
            dir,
            domain,
            sim,
            starts: 0,
        }
    }

    /// The simulator's newest report (written every second).
    pub fn sim_report(&self) -> serde_json::Value {
        let report = std::fs::read_to_string(self.dir.join("sim-report.json")).expect("the report");
        serde_json::from_str(&report).expect("a JSON report")
    }

    /// The trip record both the supervisor and the driver are given.
    pub fn trips(&self) -> PathBuf {
        self.dir.join("trips")
    }

    /// This stack's run: its domain, devices and trip record, status printing off.
    fn run_of<'a>(domain: &'a str, dev: &'a Path, trips: Option<&'a Path>) -> stack::Run<'a> {
        stack::Run {
            domain,
            device_dir: dev,
            trips,
            quiet: true,
        }
    }

    /// (Re)starts the supervisor; a running one is killed first.
    pub fn restart_supervisor(&mut self) {
        self.supervisor.kill();
        self.starts += 1;
        let (dev, trips) = (self.dir.join("dev"), self.trips());
        let args = ArmStack::run_of(&self.domain, &dev, Some(&trips)).supervisor();
        self.supervisor = Proc::spawn_owned(
            "supervisor",
            &binary("supervisor"),
            &args,
            &self.dir.join(format!("supervisor-{}.log", self.starts)),
        );
    }

    /// (Re)starts the driver; a running one is killed first.
    pub fn restart_driver(&mut self) {
        self.driver.kill();
        self.starts += 1;
        let (dev, trips) = (self.dir.join("dev"), self.trips());
        let mut args = ArmStack::run_of(&self.domain, &dev, Some(&trips)).driver(&[&self.bus]);
        args.extend(self.driver_args.iter().cloned());
        self.driver = Proc::spawn_owned(
            "bus-driver",
            &binary("bus-driver"),
            &args,
            &self.dir.join(format!("driver-{}.log", self.starts)),
        );
    }

    /// (Re)starts the fleet agent as `robot_id`, connecting to zenoh `endpoint`; a running one
    /// is killed first.
    pub fn restart_agent(&mut self, robot_id: &str, endpoint: &str) {
        self.restart_agent_with(&["--robot-id", robot_id, "--connect", endpoint]);
    }

    /// (Re)starts the fleet agent with `args` (after `--domain`).
    pub fn restart_agent_with(&mut self, args: &[&str]) {
        self.agent.kill();
        self.starts += 1;
        let dev = self.dir.join("dev");
        let mut all = ArmStack::run_of(&self.domain, &dev, None).agent();
        all.extend(args.iter().map(|a| a.to_string()));
        self.agent = Proc::spawn_owned(
            "fleet-agent",
            &binary("fleet-agent"),
            &all,
            &self.dir.join(format!("agent-{}.log", self.starts)),
        );
    }

    /// The simulator's device directory, once it serves `device` there: a sensor's process
    /// exits when its device is missing (systemd restarts it on the robot; a test starts it
    /// once), and the simulator makes its devices one after another as it starts.
    pub fn device_dir_with(&self, device: &str) -> String {
        let dev = self.dir.join("dev");
        wait_for(
            Duration::from_secs(20),
            &format!("the simulator's {device}"),
            || dev.join(device).exists().then_some(()),
        );
        dev.display().to_string()
    }

    /// Starts `nori-camera` for camera `name` (configuration `camera_toml`) on the simulator's
    /// rendering of it; its log is `camera-<name>-<n>.log`.
    pub fn camera(&self, name: &str, camera_toml: &str, n: u32) -> Proc {
        let dev = self.dir.join("dev").display().to_string();
        Proc::spawn(
            "nori-camera",
            &binary("nori-camera"),
            &[
                "--camera",
                name,
                "--config",
                camera_toml,
                "--device-dir",
                &dev,
                "--domain",
                &self.domain,
            ],
            &self.dir.join(format!("camera-{name}-{n}.log")),
        )
    }

    /// Starts the black box's recorder (`nori-blackbox record`, with `args` added) keeping its
    /// boxes in `boxes`, its log `log`; returns once it records.
    pub fn recorder(&self, boxes: &Path, args: &[&str], log: &str) -> Proc {
        let mut all = vec![
            "record".to_string(),
            "--domain".into(),
            self.domain.clone(),
            "--dir".into(),
            boxes.display().to_string(),
        ];
        all.extend(args.iter().map(|a| a.to_string()));
        let log = self.dir.join(log);
        let p = Proc::spawn_owned("blackbox", &binary("nori-blackbox"), &all, &log);
        wait_for(Duration::from_secs(10), "the recorder to record", || {
            std::fs::read_to_string(&log)
                .unwrap_or_default()
                .contains("recording the last minutes")
                .then_some(())
        });
        p
    }

    /// Stops agent, driver (torque off), supervisor and simulator in that order, with SIGTERM, checks
    /// that nothing of the domain is left in shared memory (the test's own ports must be
    /// dropped before), and returns the simulator's final report.
    pub fn stop(mut self) -> serde_json::Value {
        if self.agent.running() {
            self.agent.terminate(Duration::from_secs(5));
        }
        if self.driver.running() {
            self.driver.terminate(Duration::from_secs(5));
        }
        if self.supervisor.running() {
            self.supervisor.terminate(Duration::from_secs(5));
        }
        self.sim.terminate(Duration::from_secs(5));
        telemetry::plane::Plane::remove_unused_domain(&self.domain).unwrap();
        let left = plane_files(&self.domain);
        assert!(left.is_empty(), "left in shared memory: {left:?}");
        let text = std::fs::read_to_string(self.dir.join("sim-report.json")).unwrap();
        serde_json::from_str(&text).unwrap()
    }
}

/// Holds `joint` horizontal (π/2) from the state plane of `domain`, as the overheat scenario
/// does, until `stop`: the payload at the tool heats the shoulder toward the trip.
pub fn hold_horizontal(
    domain: &str,
    joint: &'static str,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
) -> std::thread::JoinHandle<()> {
    use telemetry::plane::{self, newest, publish, Plane};
    let domain = domain.to_string();
    std::thread::spawn(move || {
        let node = Plane::open(&domain, "hold-horizontal").unwrap();
        let layouts = node.subscriber(&plane::LAYOUT).unwrap();
        let goals = node.publisher(&plane::GOALS).unwrap();
        let layout = wait_for(Duration::from_secs(20), "a layout on the plane", || {
            newest(&layouts)
        });
        let target = layout
            .joints()
            .iter()
            .position(|j| j.name() == joint)
            .expect("the joint in the layout");
        let mut frame = telemetry::GoalFrame {
            joint_count: layout.joint_count,
            mask: 1 << target,
            ..telemetry::GoalFrame::default()
        };
        frame.position_rad[target] = std::f32::consts::FRAC_PI_2;
        while !stop.load(std::sync::atomic::Ordering::Relaxed) {
            frame.seq += 1;
            frame.timestamp_ns = telemetry::clock::monotonic_ns();
            let _ = publish(&goals, &frame);
            std::thread::sleep(Duration::from_millis(5));
        }
    })
}

/// A free TCP port on loopback for a zenoh endpoint (`tcp/127.0.0.1:<port>`).
pub fn free_endpoint() -> String {
    format!("tcp/{}", free_port_addr())
}

/// A free TCP address on loopback (`127.0.0.1:<port>`), for an HTTP server.
pub fn free_port_addr() -> String {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    listener.local_addr().unwrap().to_string()
}

/// Checks a simulator report of the left arm against the embedded calibration: no goal outside
/// a calibrated range ever reached the wire and no motor reached `max_c`. Returns the hottest
/// temperature seen.
pub fn check_left_arm_report(report: &serde_json::Value, max_c: f64) -> f64 {
    let config = bus_driver::LoadedConfig::embedded().unwrap();
    let bus = &config.config.bus[0];
    assert_eq!(bus.name, "left_arm");
    let servos = report["buses"][0]["servos"].as_array().unwrap();
    assert_eq!(servos.len(), bus.servo.len());
    let mut hottest = f64::MIN;
    for (servo, cfg) in servos.iter().zip(&bus.servo) {
        let cal = config.calibration.joint[&cfg.joint];
        // No goal at all is no evidence: every servo of a running arm gets goals (its present
        // position at setup, then each cycle's), so absent data fail the check.
        let (Some(lo), Some(hi)) = (servo["goal_min"].as_i64(), servo["goal_max"].as_i64()) else {
            panic!("{}: no goal ever reached the servo: {servo}", cfg.joint);
        };
        assert!(
            lo >= i64::from(cal.range_min) && hi <= i64::from(cal.range_max),
            "{}: goals {lo}..{hi} reached the wire, calibrated range {}..{}",
            cfg.joint,
            cal.range_min,
            cal.range_max
        );
        let t = servo["max_temperature_c"].as_f64().unwrap();
        assert!(t < max_c, "{} reached {t:.2} °C", cfg.joint);
        hottest = hottest.max(t);
    }
    hottest
}

/// A simulator report's servo was left with torque off by a stop: the last Torque_Enable write
/// it received is 0, it came after its last goal, and its output is off. (A count of torque-off
/// writes would not do: setup writes one too.)
pub fn assert_left_off(servo: &serde_json::Value, what: &str) {
    let joint = &servo["joint"];
    let last = servo["last_torque_write"]
        .as_array()
        .unwrap_or_else(|| panic!("{what}: {joint} never got a torque write: {servo}"));
    let (t, value) = (last[0].as_f64().unwrap(), last[1].as_u64().unwrap());
    assert_eq!(
        value, 0,
        "{what}: {joint}'s last torque write turned it on: {servo}"
    );
    if let Some(goal_t) = servo["last_goal_write_s"].as_f64() {
        assert!(
            goal_t <= t,
            "{what}: {joint} got a goal at {goal_t} s after its last torque-off at {t} s"
        );
    }
    assert_eq!(
        servo["torque_enabled"], false,
        "{what}: {joint} left energised"
    );
}

/// The whole robot on the simulator as a developer runs it (`nori up`: both arms, the wheels,
/// the lift, the base and its lidar), its lift standing 5 cm up at start (homing takes two
/// seconds, not ten).
pub struct WholeRobot {
    /// Scratch directory (`up.log`, the devices and `dev/sim-report.json`).
    pub dir: PathBuf,
    /// State-plane domain.
    pub domain: String,
    /// `nori up`.
    pub up: Proc,
    /// The robot description the simulator runs.
    pub description: sim::RobotDescription,
}

impl WholeRobot {
    /// Starts `nori up` and waits until the driver drives all 18 joints, each read, and the
    /// lift is homed.
    pub fn start(tag: &str) -> WholeRobot {
        WholeRobot::start_with(tag, &[])
    }

    /// [`WholeRobot::start`] with more arguments for `nori up`.
    pub fn start_with(tag: &str, up_args: &[&str]) -> WholeRobot {
        use telemetry::plane::{self, newest, Plane};
        let dir = scratch(tag);
        let domain = format!("nori_{tag}_{}", std::process::id()).replace('-', "_");
        let robot = dir.join("robot.toml");
        let text = sim::description::NORI_A3_TOML.replacen("start-m = 0.3", "start-m = 0.05", 1);
        assert_ne!(text, sim::description::NORI_A3_TOML);
        std::fs::write(&robot, &text).expect("robot.toml");
        let description = sim::RobotDescription::parse(&text, "robot.toml").expect("description");
        let (dev, robot) = (dir.join("dev"), robot.display().to_string());
        let mut args = vec![
            "up",
            "--dir",
            dev.to_str().expect("a UTF-8 path"),
            "--domain",
            &domain,
            "--robot",
            &robot,
        ];
        args.extend_from_slice(up_args);
        let up = Proc::spawn("nori up", &binary("nori"), &args, &dir.join("up.log"));
        // Owned from here, so a wait below that fails stops the stack too.
        let robot = WholeRobot {
            dir: dir.clone(),
            domain: domain.clone(),
            up,
            description,
        };
        let node = Plane::open(&domain, "test-whole-robot").expect("the plane");
        let states = node.subscriber(&plane::JOINT_STATE).expect("joint state");
        let lifts = node.subscriber(&plane::LIFT_STATE).expect("lift state");
        wait_for(Duration::from_secs(40), "18 joints driven", || {
            newest(&states).filter(|s| {
                s.joint_count == 18
                    && s.flags & telemetry::frames::STATE_FLAG_SAFE_STATE == 0
                    && s.joints().iter().all(|j| j.is_valid())
            })
        });
        wait_for(Duration::from_secs(20), "the lift homed", || {
            newest(&lifts).filter(|l| l.state == telemetry::motion::LIFT_READY)
        });
        robot
    }

    /// The simulator's newest report (written every second).
    pub fn report(&self) -> serde_json::Value {
        let path = self.dir.join("dev/sim-report.json");
        serde_json::from_str(&std::fs::read_to_string(path).expect("the report"))
            .expect("a JSON report")
    }

    /// Stops `nori up` (Ctrl-C's SIGTERM path), asserts it exited cleanly, and removes the
    /// scratch directory; returns the simulator's last report.
    pub fn stop(mut self) -> serde_json::Value {
        let (code, log) = self.up.terminate(Duration::from_secs(30));
        assert_eq!(code, Some(0), "nori up: {log}");
        let report = self.report();
        let _ = std::fs::remove_dir_all(&self.dir);
        report
    }
}

/// A test that fails before [`WholeRobot::stop`] still stops the stack: `nori up` killed
/// would leave its children running (each its own process group), loading the machine for
/// every later test.
impl Drop for WholeRobot {
    fn drop(&mut self) {
        self.up.stop_within(Duration::from_secs(10));
    }
}

/// The running processes whose arguments (the program first) `matching` accepts: pid and
/// arguments.
pub fn processes(matching: impl Fn(&[String]) -> bool) -> Vec<(u32, Vec<String>)> {
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    entries
        .flatten()
        .filter_map(|entry| {
            let pid = entry.file_name().to_str()?.parse().ok()?;
            let cmdline = std::fs::read(entry.path().join("cmdline")).ok()?;
            let args: Vec<String> = cmdline
                .split(|&b| b == 0)
                .filter(|a| !a.is_empty())
                .map(|a| String::from_utf8_lossy(a).into_owned())
                .collect();
            let args = without_emulator(args);
            matching(&args).then_some((pid, args))
        })
        .collect()
}

/// A process's arguments as it was started, without the emulator that runs it: an arm64
/// binary run on another machine through binfmt_misc (deploy/arm64/cross.sh) shows
/// `qemu-aarch64 /path/program [argv0] args…` in `/proc/<pid>/cmdline` (argv0 again when the
/// interpreter is registered to preserve it).
fn without_emulator(mut args: Vec<String>) -> Vec<String> {
    let base = |a: &str| a.rsplit('/').next().unwrap_or(a).to_string();
    let emulator = |a: &String| base(a).starts_with("qemu-") || a.contains("/qemu-binfmt/");
    if !args.first().is_some_and(emulator) {
        return args;
    }
    args.remove(0);
    if args.len() >= 2 && base(&args[0]) == base(&args[1]) {
        args.remove(1);
    }
    args
}

/// A scratch PostgreSQL server on loopback (`deploy/fleet-db/scratch-postgres.sh`), stopped when
/// dropped.
pub struct ScratchPostgres {
    /// Its directory (cluster, logs, socket).
    pub dir: PathBuf,
    /// Its connection string.
    pub url: String,
    port: u16,
}

impl ScratchPostgres {
    fn script() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/fleet-db/scratch-postgres.sh")
    }

    /// Creates and starts one in `dir` on a free port.
    pub fn start(dir: &Path) -> ScratchPostgres {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("a free port")
            .port();
        let mut db = ScratchPostgres {
            dir: dir.to_path_buf(),
            url: String::new(),
            port,
        };
        db.resume();
        db
    }

    /// Starts it again after [`ScratchPostgres::stop`] (same data, same port).
    pub fn resume(&mut self) {
        let out = std::process::Command::new(ScratchPostgres::script())
            .args([
                "start",
                &self.dir.display().to_string(),
                &self.port.to_string(),
            ])
            .output()
            .expect("running scratch-postgres.sh");
        assert!(
            out.status.success(),
            "starting PostgreSQL failed (deploy/fleet-db/install-postgres.sh installs it): {}",
            String::from_utf8_lossy(&out.stderr)
        );
        self.url = String::from_utf8_lossy(&out.stdout).trim().to_string();
    }

    /// Stops it (fast shutdown: its clients are cut off).
    pub fn stop(&self) {
        let _ = std::process::Command::new(ScratchPostgres::script())
            .args(["stop", &self.dir.display().to_string()])
            .status();
    }

    /// A client of it.
    pub fn client(&self) -> postgres::Client {
        postgres::Client::connect(&self.url, postgres::NoTls).expect("connecting to PostgreSQL")
    }
}

impl Drop for ScratchPostgres {
    fn drop(&mut self) {
        self.stop();
    }
}

/// A plain HTTP/1.0 GET: the status code and the body.
pub fn http_get(addr: &str, path: &str) -> Option<(u16, Vec<u8>)> {
    use std::io::{Read, Write};
    let mut stream = std::net::TcpStream::connect(addr).ok()?;
    stream.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    write!(stream, "GET {path} HTTP/1.0\r\nHost: {addr}\r\n\r\n").ok()?;
    let mut raw = Vec::new();
    stream.read_to_end(&mut raw).ok()?;
    let split = raw.windows(4).position(|w| w == b"\r\n\r\n")?;
    let head = String::from_utf8_lossy(&raw[..split]);
    let code = head.split_whitespace().nth(1)?.parse().ok()?;
    Some((code, raw[split + 4..].to_vec()))
}

/// Runs the independent LeRobot check; `None` (said loudly) only outside CI when pyarrow is
/// not installed. In CI (`CI` set) a missing pyarrow fails: `.ci/run` installs it.
pub fn lerobot_check(root: &Path, args: &[&str]) -> Option<serde_json::Value> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("python/check_lerobot_dataset.py");
    let out = Command::new("python3")
        // Hugging Face `datasets` (optional) reads local files only, into a cache of this test.
        .env("HF_DATASETS_OFFLINE", "1")
        .env("HF_DATASETS_CACHE", root.with_extension("hf-cache"))
        .arg(&script)
        .arg(root)
        .args(args)
        .output()
        .expect("running python3");
    let stderr = String::from_utf8_lossy(&out.stderr);
    if out.status.code() == Some(3) {
        assert!(
            std::env::var_os("CI").is_none(),
            "pyarrow/pandas/numpy missing in CI (.ci/run installs them): {stderr}"
        );
        eprintln!("\n!!!!!!!! SKIPPED the independent LeRobot check: {stderr} (pip install pyarrow pandas numpy) !!!!!!!!\n");
        return None;
    }
    assert!(
        out.status.success(),
        "LeRobot check of {}: {stderr}",
        root.display()
    );
    Some(serde_json::from_slice(&out.stdout).expect("check summary"))
}

/// `nori-lab` on `domain` and one page's link to it (a WebSocket, spoken as the page speaks
/// it): what the tests send as an operator would, and the lab's replies.
pub struct Lab {
    /// The process.
    pub proc: Proc,
    /// `127.0.0.1:port`.
    pub http: String,
    token: String,
    args: Vec<String>,
    log: PathBuf,
    starts: u32,
    link: Option<tungstenite::WebSocket<std::net::TcpStream>>,
}

impl Lab {
    /// Starts `nori-lab` (with `extra` arguments) and waits until it serves.
    pub fn start(domain: &str, dir: &Path, extra: &[&str]) -> Lab {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("a free port")
            .port();
        let token = format!("lab-test-token-{}", std::process::id());
        let token_file = dir.join("lab-token");
        std::fs::write(&token_file, &token).expect("token file");
        let http = format!("127.0.0.1:{port}");
        let mut args: Vec<String> = ["--domain", domain, "--http", &http, "--token-file"]
            .iter()
            .map(|a| a.to_string())
            .collect();
        args.push(token_file.display().to_string());
        args.extend(extra.iter().map(|a| a.to_string()));
        let mut lab = Lab {
            proc: Proc::none("nori-lab"),
            http,
            token,
            args,
            log: dir.join("lab"),
            starts: 0,
            link: None,
        };
        lab.restart();
        lab
    }

    /// (Re)starts the process, as systemd would after a crash, and waits until it serves.
    pub fn restart(&mut self) {
        self.proc.kill();
        self.link = None;
        self.starts += 1;
        let log = self.log.with_extension(format!("{}.log", self.starts));
        self.proc = Proc::spawn_owned("nori-lab", &binary("nori-lab"), &self.args, &log);
        let http = self.http.clone();
        wait_for(Duration::from_secs(10), "the lab serving", || {
            http_get(&http, "/").filter(|(code, _)| *code == 200)
        });
    }

    /// Opens the page's link (with the token, the lab's own origin and host).
    pub fn connect(&mut self) -> std::io::Result<()> {
        use tungstenite::client::IntoClientRequest;
        let url = format!("ws://{}/ws?token={}", self.http, self.token);
        let mut request = url.into_client_request().map_err(std::io::Error::other)?;
        let origin = format!("http://{}", self.http);
        request
            .headers_mut()
            .insert("Origin", origin.parse().map_err(std::io::Error::other)?);
        let stream = std::net::TcpStream::connect(&self.http)?;
        stream.set_read_timeout(Some(Duration::from_millis(20)))?;
        let (link, _) = tungstenite::client::client(request, stream)
            .map_err(|e| std::io::Error::other(e.to_string()))?;
        self.link = Some(link);
        Ok(())
    }

    /// Sends one message; an error (the lab gone) drops the link.
    pub fn send(&mut self, message: &serde_json::Value) -> bool {
        let Some(link) = self.link.as_mut() else {
            return false;
        };
        let sent = link
            .send(tungstenite::Message::text(message.to_string()))
            .is_ok();
        if !sent {
            self.link = None;
        }
        sent
    }

    /// The JSON messages received so far (none waits longer than the read timeout); the
    /// link dropped when the lab is gone.
    pub fn receive(&mut self) -> Vec<serde_json::Value> {
        let mut got = Vec::new();
        while let Some(link) = self.link.as_mut() {
            match link.read() {
                Ok(tungstenite::Message::Text(t)) => {
                    got.extend(serde_json::from_str(t.as_str()).ok());
                }
                Ok(_) => {}
                Err(tungstenite::Error::Io(e))
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) =>
                {
                    break
                }
                Err(_) => self.link = None,
            }
        }
        got
    }

    /// Whether the link is open.
    pub fn linked(&self) -> bool {
        self.link.is_some()
    }

    /// Waits up to `within` for a reply of the lab's with `"to": to`.
    pub fn reply_to(&mut self, to: &str, within: Duration) -> Option<serde_json::Value> {
        let until = Instant::now() + within;
        while Instant::now() < until {
            if let Some(r) = self
                .receive()
                .into_iter()
                .find(|m| m["type"] == "reply" && m["to"] == to)
            {
                return Some(r);
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::without_emulator;

    fn v(a: &[&str]) -> Vec<String> {
        a.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn a_process_under_qemu_is_known_by_its_own_program_and_arguments() {
        let native = v(&["/t/release/bus-driver", "--domain", "d"]);
        assert_eq!(without_emulator(native.clone()), native);
        for raw in [
            v(&[
                "/usr/libexec/qemu-binfmt/aarch64-binfmt-P",
                "/t/release/bus-driver",
                "bus-driver",
                "--domain",
                "d",
            ]),
            v(&[
                "/usr/bin/qemu-aarch64",
                "/t/release/bus-driver",
                "--domain",
                "d",
            ]),
            v(&[
                "qemu-aarch64-static",
                "/t/release/bus-driver",
                "/t/release/bus-driver",
                "--domain",
                "d",
            ]),
            v(&[
                "/usr/bin/qemu-aarch64",
                "/t/release/bus-driver",
                "bus-driver",
                "--domain",
                "d",
            ]),
        ] {
            assert_eq!(without_emulator(raw.clone()), native, "{raw:?}");
        }
    }
}
