//! Child processes of the stack, for `nori up` and the scenario runner: started in their own
//! process group (the terminal's Ctrl-C reaches `nori` only, which stops them in a safe order),
//! restarted with backoff, stopped with SIGTERM and a deadline.

use anyhow::{bail, Context, Result};
use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A sibling executable (installed next to `nori`, as cargo builds them).
pub fn sibling(name: &str) -> Result<PathBuf> {
    let exe = std::env::current_exe().context("locating the nori executable")?;
    let path = exe.with_file_name(name);
    if !path.exists() {
        bail!(
            "{} not found next to {}: build all binaries first (cargo build --release --workspace --bins)",
            name,
            exe.display()
        );
    }
    Ok(path)
}

/// The supervisor and the driver of one bus, for the scenarios and benchmarks that run a single
/// arm: status printing off, trips recorded in `dir/trips` (read by both), the driver's
/// devices in `device_dir`. Not started.
pub fn supervisor_and_driver(
    domain: &str,
    dir: &Path,
    bus: &str,
    device_dir: &Path,
) -> Result<[Managed; 2]> {
    let s = |v: &str| v.to_string();
    Ok([
        Managed::new(
            "supervisor",
            &sibling("supervisor")?,
            &[
                s("--domain"),
                s(domain),
                s("--status-every"),
                s("0"),
                s("--trip-file"),
                dir.join("trips").display().to_string(),
            ],
        ),
        Managed::new(
            "bus-driver",
            &sibling("bus-driver")?,
            &[
                s("--bus"),
                s(bus),
                s("--device-dir"),
                device_dir.display().to_string(),
                s("--domain"),
                s(domain),
                s("--status-every"),
                s("0"),
                s("--trip-file"),
                dir.join("trips").display().to_string(),
            ],
        ),
    ])
}

/// One managed child process. Dropping it stops it.
pub struct Managed {
    name: &'static str,
    command: Command,
    child: Option<Child>,
    quiet: bool,
    backoff: Duration,
    restart_at: Option<Instant>,
    /// Restarts so far.
    pub restarts: u32,
}

impl Managed {
    /// A process to run `program` with `args`.
    pub fn new(name: &'static str, program: &Path, args: &[String]) -> Self {
        let mut command = Command::new(program);
        command.args(args).stdin(Stdio::null());
        command.process_group(0);
        Managed {
            name,
            command,
            child: None,
            quiet: false,
            backoff: Duration::from_millis(500),
            restart_at: None,
            restarts: 0,
        }
    }

    /// Adds arguments (before it is started).
    pub fn add_args(&mut self, args: &[String]) {
        self.command.args(args);
    }

    /// Sends its output to `log` instead of the terminal, and starts/stops it silently.
    pub fn log_to(&mut self, log: &Path) -> Result<()> {
        let file =
            std::fs::File::create(log).with_context(|| format!("creating {}", log.display()))?;
        self.command.stderr(file).stdout(Stdio::null());
        self.quiet = true;
        Ok(())
    }

    /// Its name, for messages.
    pub fn name(&self) -> &'static str {
        self.name
    }

    /// Its process id while it runs.
    pub fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(Child::id)
    }

    /// Starts it.
    pub fn start(&mut self) -> Result<()> {
        let child = self
            .command
            .spawn()
            .with_context(|| format!("starting {}", self.name))?;
        if !self.quiet {
            eprintln!("nori: started {} (pid {})", self.name, child.id());
        }
        self.child = Some(child);
        Ok(())
    }

    /// Whether it has exited by itself.
    pub fn exited(&mut self) -> bool {
        self.child
            .as_mut()
            .is_some_and(|c| c.try_wait().ok().flatten().is_some())
    }

    /// Restarts a process that exited, with exponential backoff (0.5 s to 8 s).
    pub fn supervise(&mut self) -> Result<()> {
        if let Some(child) = &mut self.child {
            if let Some(status) = child.try_wait()? {
                eprintln!(
                    "nori: {} exited ({status}); restarting in {:.1} s",
                    self.name,
                    self.backoff.as_secs_f64()
                );
                self.child = None;
                self.restart_at = Some(Instant::now() + self.backoff);
                self.backoff = (self.backoff * 2).min(Duration::from_secs(8));
            }
        } else if self.restart_at.is_some_and(|t| Instant::now() >= t) {
            self.restart_at = None;
            self.restarts += 1;
            self.start()?;
        }
        Ok(())
    }

    /// SIGKILL at once (a crash), and reaps it.
    pub fn kill(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }

    /// SIGTERM, then SIGKILL after `within`.
    pub fn stop(&mut self, within: Duration) {
        let Some(mut child) = self.child.take() else {
            return;
        };
        let _ = kill(Pid::from_raw(child.id() as i32), Signal::SIGTERM);
        let until = Instant::now() + within;
        loop {
            match child.try_wait() {
                Ok(Some(status)) => {
                    if !self.quiet {
                        eprintln!("nori: {} stopped ({status})", self.name);
                    }
                    return;
                }
                Ok(None) if Instant::now() < until => std::thread::sleep(Duration::from_millis(20)),
                _ => {
                    eprintln!(
                        "nori: {} did not stop in {:.0} s; killing it",
                        self.name,
                        within.as_secs_f64()
                    );
                    let _ = child.kill();
                    let _ = child.wait();
                    return;
                }
            }
        }
    }
}

impl Drop for Managed {
    fn drop(&mut self) {
        self.stop(Duration::from_secs(3));
    }
}
