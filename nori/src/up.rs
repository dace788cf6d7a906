//! `nori up`: the whole stack on the simulated robot, for development. Starts the simulator and
//! the driver as separate processes, restarts a process that dies (with backoff), and on Ctrl-C
//! stops the driver first (it turns torque off while the buses are still there), then the rest.
//! Production uses systemd (deploy/systemd) instead.

use crate::sim_serve::default_device_dir;
use anyhow::{bail, Context, Result};
use clap::Args;
use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Options of `nori up`.
#[derive(Args, Debug)]
pub struct UpArgs {
    /// Directory for the simulator's device links and report.
    #[arg(long, value_name = "DIR", default_value_os_t = default_device_dir())]
    pub dir: PathBuf,
    /// State-plane domain.
    #[arg(long, default_value = telemetry::plane::DEFAULT_DOMAIN)]
    pub domain: String,
    /// Driver configuration file; the embedded default when absent.
    #[arg(long)]
    pub driver_config: Option<PathBuf>,
    /// Stop by itself after this many seconds.
    #[arg(long)]
    pub run_for: Option<f64>,
}

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

struct Managed {
    name: &'static str,
    command: Command,
    child: Option<Child>,
    restarts: u32,
    backoff: Duration,
    restart_at: Option<Instant>,
}

impl Managed {
    fn new(name: &'static str, program: &Path, args: &[String]) -> Self {
        let mut command = Command::new(program);
        command.args(args);
        // Own process group: the terminal's Ctrl-C reaches `nori up` only, which stops the
        // children in a safe order.
        command.process_group(0);
        Managed {
            name,
            command,
            child: None,
            restarts: 0,
            backoff: Duration::from_millis(500),
            restart_at: None,
        }
    }

    fn start(&mut self) -> Result<()> {
        let child = self
            .command
            .spawn()
            .with_context(|| format!("starting {}", self.name))?;
        eprintln!("nori up: started {} (pid {})", self.name, child.id());
        self.child = Some(child);
        Ok(())
    }

    /// Restarts a process that exited, with exponential backoff (0.5 s to 8 s).
    fn supervise(&mut self) -> Result<()> {
        if let Some(child) = &mut self.child {
            if let Some(status) = child.try_wait()? {
                eprintln!(
                    "nori up: {} exited ({status}); restarting in {:.1} s",
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

    fn stop(&mut self, within: Duration) {
        let Some(mut child) = self.child.take() else {
            return;
        };
        let _ = kill(Pid::from_raw(child.id() as i32), Signal::SIGTERM);
        let until = Instant::now() + within;
        loop {
            match child.try_wait() {
                Ok(Some(status)) => {
                    eprintln!("nori up: {} stopped ({status})", self.name);
                    return;
                }
                Ok(None) if Instant::now() < until => std::thread::sleep(Duration::from_millis(20)),
                _ => {
                    eprintln!(
                        "nori up: {} did not stop in {:.0} s; killing it",
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

/// Runs the stack until Ctrl-C (or `--run-for`).
pub fn run(args: &UpArgs) -> Result<()> {
    let nori = std::env::current_exe()?;
    let driver = sibling("bus-driver")?;
    let shutdown = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(signal, shutdown.clone())?;
    }
    let dir = args.dir.display().to_string();
    let report = args.dir.join("sim-report.json").display().to_string();
    let mut sim = Managed::new(
        "simulator",
        &nori,
        &[
            "sim".into(),
            "serve".into(),
            "--dir".into(),
            dir.clone(),
            "--report".into(),
            report.clone(),
        ],
    );
    let mut driver_args = vec![
        "--device-dir".into(),
        dir,
        "--domain".into(),
        args.domain.clone(),
    ];
    if let Some(c) = &args.driver_config {
        driver_args.extend(["--config".into(), c.display().to_string()]);
    }
    let mut bus_driver = Managed::new("bus-driver", &driver, &driver_args);
    eprintln!("nori up: the Nori A3 stack on the simulated robot (no hardware)");
    sim.start()?;
    bus_driver.start()?;
    eprintln!(
        "nori up: watch the joints with `nori state --domain {d}`, move one with `nori goal --domain {d} left_elbow=-1.0`; \
         the simulator's report is {report}. Ctrl-C stops everything with torque off.",
        d = args.domain
    );
    let start = Instant::now();
    while !shutdown.load(Ordering::Relaxed)
        && args
            .run_for
            .is_none_or(|t| start.elapsed().as_secs_f64() < t)
    {
        sim.supervise()?;
        bus_driver.supervise()?;
        std::thread::sleep(Duration::from_millis(50));
    }
    eprintln!("nori up: stopping (driver first, so torque goes off while the buses are up)");
    bus_driver.stop(Duration::from_secs(5));
    sim.stop(Duration::from_secs(5));
    eprintln!(
        "nori up: stopped; restarts: simulator {}, bus-driver {}",
        sim.restarts, bus_driver.restarts
    );
    Ok(())
}
