//! One child process of the stack, as `nori up`, the scenario runner, the benchmarks and the
//! process tests run them: started in its own process group (the terminal's Ctrl-C reaches the
//! parent only, which stops the children in a safe order), restarted with backoff, stopped with
//! SIGTERM and a deadline, or killed at once (a crash).

use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use std::io::Read;
use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};
use thiserror::Error;

/// Why a child could not be started.
#[derive(Debug, Error)]
#[allow(missing_docs, reason = "each field is shown in its variant's message")]
pub enum ChildError {
    /// A sibling executable cannot be found.
    #[error(transparent)]
    Sibling(#[from] telemetry::process::SiblingError),
    /// A log file could not be created.
    #[error("creating {path}: {source}")]
    Log {
        /// The log file.
        path: String,
        source: std::io::Error,
    },
    /// The process could not be spawned.
    #[error("starting {name}: {source}")]
    Spawn {
        /// The child's name.
        name: String,
        source: std::io::Error,
    },
    /// Its state could not be read.
    #[error("waiting for {name}: {source}")]
    Wait {
        /// The child's name.
        name: String,
        source: std::io::Error,
    },
}

/// How a stopped child ended.
#[derive(Debug)]
pub struct Stopped {
    /// Its exit status (`None` if it could not be read).
    pub status: Option<ExitStatus>,
    /// What it wrote to stdout, when captured ([`Managed::capture_stdout`]).
    pub stdout: String,
    /// It did not stop within the deadline and was killed.
    pub killed: bool,
}

impl Stopped {
    /// Its exit code, if it exited (rather than being killed by a signal).
    pub fn code(&self) -> Option<i32> {
        self.status.and_then(|s| s.code())
    }
}

/// One managed child process. Dropping it stops it (SIGTERM, then SIGKILL after 3 s).
pub struct Managed {
    name: String,
    command: Command,
    child: Option<Child>,
    quiet: bool,
    backoff: Duration,
    max_backoff: Duration,
    restart_at: Option<Instant>,
    /// Restarts so far.
    pub restarts: u32,
}

impl Managed {
    /// A process to run `program` with `args`; not started.
    pub fn new(name: &str, program: &Path, args: &[String]) -> Self {
        let mut command = Command::new(program);
        command.args(args).stdin(Stdio::null());
        command.process_group(0);
        Managed {
            name: name.into(),
            command,
            child: None,
            quiet: false,
            backoff: Duration::from_millis(500),
            max_backoff: Duration::from_secs(8),
            restart_at: None,
            restarts: 0,
        }
    }

    /// Restarts it after `delay` every time, however often it exits (systemd's `RestartSec`),
    /// instead of backing off: for a process whose absence costs more than a crash loop.
    pub fn restart_after(&mut self, delay: Duration) {
        self.backoff = delay;
        self.max_backoff = delay;
    }

    /// Adds arguments (before it is started).
    pub fn add_args(&mut self, args: &[String]) {
        self.command.args(args);
    }

    /// Sends its stderr to `log` (and its stdout nowhere, unless captured), and starts and stops
    /// it silently.
    pub fn log_to(&mut self, log: &Path) -> Result<(), ChildError> {
        let file = std::fs::File::create(log).map_err(|source| ChildError::Log {
            path: log.display().to_string(),
            source,
        })?;
        self.command.stderr(file).stdout(Stdio::null());
        self.quiet = true;
        Ok(())
    }

    /// Keeps its stdout, returned by [`Managed::stop`] (a process that prints a summary at exit).
    pub fn capture_stdout(&mut self) {
        self.command.stdout(Stdio::piped());
    }

    /// Its name, for messages.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Its process id while it runs.
    pub fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(Child::id)
    }

    /// Starts it.
    pub fn start(&mut self) -> Result<(), ChildError> {
        let child = self.command.spawn().map_err(|source| ChildError::Spawn {
            name: self.name.clone(),
            source,
        })?;
        if !self.quiet {
            eprintln!("nori: started {} (pid {})", self.name, child.id());
        }
        self.child = Some(child);
        Ok(())
    }

    /// Whether it was started and has exited by itself.
    pub fn exited(&mut self) -> bool {
        self.child
            .as_mut()
            .is_some_and(|c| c.try_wait().ok().flatten().is_some())
    }

    /// Whether it was started and still runs.
    pub fn running(&mut self) -> bool {
        self.child
            .as_mut()
            .is_some_and(|c| c.try_wait().ok().flatten().is_none())
    }

    /// Restarts a process that exited, with exponential backoff (0.5 s to 8 s, or the fixed
    /// delay of [`Managed::restart_after`]).
    pub fn supervise(&mut self) -> Result<(), ChildError> {
        if let Some(child) = &mut self.child {
            let exited = child.try_wait().map_err(|source| ChildError::Wait {
                name: self.name.clone(),
                source,
            })?;
            if let Some(status) = exited {
                eprintln!(
                    "nori: {} exited ({status}); restarting in {:.1} s",
                    self.name,
                    self.backoff.as_secs_f64()
                );
                self.child = None;
                self.restart_at = Some(Instant::now() + self.backoff);
                self.backoff = (self.backoff * 2).min(self.max_backoff);
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

    /// SIGTERM, then SIGKILL after `within`; `None` if it was not running.
    pub fn stop(&mut self, within: Duration) -> Option<Stopped> {
        let mut child = self.child.take()?;
        let _ = kill(Pid::from_raw(child.id() as i32), Signal::SIGTERM);
        let until = Instant::now() + within;
        let (status, killed) = loop {
            match child.try_wait() {
                Ok(Some(status)) => {
                    if !self.quiet {
                        eprintln!("nori: {} stopped ({status})", self.name);
                    }
                    break (Some(status), false);
                }
                Ok(None) if Instant::now() < until => std::thread::sleep(Duration::from_millis(20)),
                _ => {
                    eprintln!(
                        "nori: {} did not stop in {:.0} s; killing it",
                        self.name,
                        within.as_secs_f64()
                    );
                    let _ = child.kill();
                    break (child.wait().ok(), true);
                }
            }
        };
        let mut stdout = String::new();
        if let Some(mut out) = child.stdout.take() {
            let _ = out.read_to_string(&mut stdout);
        }
        Some(Stopped {
            status,
            stdout,
            killed,
        })
    }
}

impl Drop for Managed {
    fn drop(&mut self) {
        self.stop(Duration::from_secs(3));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sh(script: &str) -> Managed {
        let mut m = Managed::new("sh", Path::new("/bin/sh"), &["-c".into(), script.into()]);
        m.quiet = true;
        m
    }

    #[test]
    fn a_stopped_child_gives_its_exit_code_and_captured_stdout() {
        let mut m = sh("trap 'echo bye; exit 3' TERM; echo hello; while :; do sleep 0.01; done");
        m.capture_stdout();
        m.start().unwrap();
        assert!(m.running());
        std::thread::sleep(Duration::from_millis(200));
        let s = m.stop(Duration::from_secs(5)).unwrap();
        assert_eq!((s.code(), s.killed), (Some(3), false));
        assert_eq!(s.stdout, "hello\nbye\n");
        assert!(!m.running() && m.stop(Duration::from_secs(1)).is_none());
    }

    #[test]
    fn a_child_that_ignores_sigterm_is_killed_at_the_deadline() {
        let mut m = sh("trap '' TERM; while :; do sleep 0.01; done");
        m.start().unwrap();
        std::thread::sleep(Duration::from_millis(100));
        let s = m.stop(Duration::from_millis(300)).unwrap();
        assert!(s.killed && s.code().is_none(), "{s:?}");
    }

    #[test]
    fn an_exited_child_is_restarted_after_its_backoff() {
        let mut m = sh("exit 0");
        m.start().unwrap();
        let until = Instant::now() + Duration::from_secs(5);
        while m.restarts == 0 && Instant::now() < until {
            m.supervise().unwrap();
            std::thread::sleep(Duration::from_millis(20));
        }
        assert_eq!(m.restarts, 1);
        assert!(m.backoff >= Duration::from_secs(1), "backoff doubled");
        // A fixed delay: exits again and again, restarted after the same delay each time.
        m.restart_after(Duration::from_millis(100));
        while m.restarts < 3 && Instant::now() < until + Duration::from_secs(5) {
            m.supervise().unwrap();
            std::thread::sleep(Duration::from_millis(20));
        }
        assert_eq!(m.restarts, 3);
        assert_eq!(m.backoff, Duration::from_millis(100), "fixed: no doubling");
    }
}
