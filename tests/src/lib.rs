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
        let status = Command::new(cargo)
            .args([
                "build",
                "--release",
                "--quiet",
                "-p",
                "nori",
                "-p",
                "bus-driver",
                "-p",
                "supervisor",
                "--bins",
            ])
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
