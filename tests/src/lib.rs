//! Process-level test support: the real binaries, started, watched and cleaned up.
//!
//! Tests here spawn `nori` (the simulator), `supervisor` and `bus-driver` exactly as `nori up` or
//! systemd do,
//! talk to them over the state plane, and check what the simulated servos received. Every child
//! is killed when its guard drops, so a failing test leaves no process behind.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

/// The workspace's `target/release` (this test binary lives in `target/<profile>/deps`).
fn release_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    let target = exe
        .ancestors()
        .nth(3)
        .expect("target/<profile>/deps/<test>");
    target.join("release")
}

/// Path of a workspace binary, built once per test run in the release profile: the processes
/// run as deployed. (Unoptimised, the simulator falls behind real time in bursts on a two-core
/// machine, so a moving joint looks static to the supervisor: a timing artefact no robot has.)
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
            // The README's build command exactly: the same feature set, so the two never
            // invalidate each other's artifacts.
            .args(["build", "--release", "--quiet", "--workspace", "--bins"])
            .status()
            .expect("running cargo build for the binaries");
        assert!(status.success(), "building the binaries failed");
    });
    let path = release_dir().join(name);
    assert!(path.exists(), "{} was not built", path.display());
    path
}

/// A child process killed (SIGKILL) and reaped when dropped, unless stopped before.
pub struct Proc {
    /// What it is, for messages.
    pub name: String,
    child: Option<Child>,
}

impl Proc {
    /// Starts `program` with `args`; its stderr goes to `log`.
    pub fn spawn(name: &str, program: &Path, args: &[&str], log: &Path) -> Proc {
        let err = std::fs::File::create(log).expect("log file");
        let child = Command::new(program)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(err)
            .spawn()
            .unwrap_or_else(|e| panic!("starting {name}: {e}"));
        Proc {
            name: name.into(),
            child: Some(child),
        }
    }

    /// A placeholder for a process not started yet.
    pub fn none(name: &str) -> Proc {
        Proc {
            name: name.into(),
            child: None,
        }
    }

    /// Process id.
    pub fn pid(&self) -> u32 {
        self.child.as_ref().map_or(0, Child::id)
    }

    /// Sends SIGTERM and waits up to `within`; returns the exit code and stdout.
    pub fn terminate(&mut self, within: Duration) -> (Option<i32>, String) {
        let mut child = self.child.take().expect("already stopped");
        let _ = Command::new("kill")
            .args(["-TERM", &child.id().to_string()])
            .status();
        let until = Instant::now() + within;
        while Instant::now() < until {
            if child.try_wait().ok().flatten().is_some() {
                let out = child.wait_with_output().expect("output");
                return (
                    out.status.code(),
                    String::from_utf8_lossy(&out.stdout).into_owned(),
                );
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = child.kill();
        let out = child.wait_with_output().expect("output");
        panic!(
            "{} did not stop within {:?} of SIGTERM (stdout: {})",
            self.name,
            within,
            String::from_utf8_lossy(&out.stdout)
        );
    }

    /// SIGKILL, at once (a crash), and reaps it.
    pub fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// Whether it is still running.
    pub fn running(&mut self) -> bool {
        self.child
            .as_mut()
            .is_some_and(|c| c.try_wait().ok().flatten().is_none())
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// A fresh scratch directory for one test.
pub fn scratch(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("nori-it-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("scratch dir");
    dir
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

/// A small seeded generator (SplitMix64) for randomised process tests: the same seed gives the
/// same kill schedule.
pub struct Rng(u64);

impl Rng {
    /// Seeded.
    pub fn new(seed: u64) -> Rng {
        Rng(seed)
    }

    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[lo, hi)`.
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in `0..n`.
    pub fn below(&mut self, n: u64) -> u64 {
        self.next_u64() % n
    }
}

/// The `q`-quantile (0..=1) of `values`, nearest rank.
pub fn quantile(values: &[f64], q: f64) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let rank = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len());
    v[rank - 1]
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
        let mut args = vec![
            "sim",
            "serve",
            "--bus",
            bus,
            "--dir",
            dev.to_str().unwrap(),
            "--report",
            report.to_str().unwrap(),
        ];
        args.extend_from_slice(sim_args);
        let sim = Proc::spawn("simulator", &binary("nori"), &args, &dir.join("sim.log"));
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

    /// The trip record both the supervisor and the driver are given.
    pub fn trips(&self) -> PathBuf {
        self.dir.join("trips")
    }

    /// (Re)starts the supervisor; a running one is killed first.
    pub fn restart_supervisor(&mut self) {
        self.supervisor.kill();
        self.starts += 1;
        let trips = self.trips();
        self.supervisor = Proc::spawn(
            "supervisor",
            &binary("supervisor"),
            &[
                "--domain",
                &self.domain,
                "--status-every",
                "0",
                "--trip-file",
                trips.to_str().unwrap(),
            ],
            &self.dir.join(format!("supervisor-{}.log", self.starts)),
        );
    }

    /// (Re)starts the driver; a running one is killed first.
    pub fn restart_driver(&mut self) {
        self.driver.kill();
        self.starts += 1;
        let dev = self.dir.join("dev");
        let trips = self.trips();
        let mut args = vec![
            "--bus",
            &self.bus,
            "--device-dir",
            dev.to_str().unwrap(),
            "--domain",
            &self.domain,
            "--status-every",
            "0",
            "--trip-file",
            trips.to_str().unwrap(),
        ];
        args.extend(self.driver_args.iter().map(String::as_str));
        self.driver = Proc::spawn(
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
        let mut all = vec!["--domain", &self.domain];
        all.extend_from_slice(args);
        self.agent = Proc::spawn(
            "fleet-agent",
            &binary("fleet-agent"),
            &all,
            &self.dir.join(format!("agent-{}.log", self.starts)),
        );
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

/// A free TCP port on loopback for a zenoh endpoint (`tcp/127.0.0.1:<port>`).
pub fn free_endpoint() -> String {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    format!("tcp/127.0.0.1:{}", listener.local_addr().unwrap().port())
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
