//! Serving the simulated buses on pseudo-terminals, in real time, so that the unmodified bus
//! driver opens them with `serialport` exactly as it would open `/dev/ttyUSB0`.
//!
//! One thread serves the whole robot: it keeps every pty master, steps each bus's mechanics to
//! the wall clock, feeds received bytes to the device side and writes each reply burst when its
//! last byte would have arrived on a real line. One thread (not one per bus) leaves the other
//! core to the driver on a two-core machine. The slave side is closed after creation, as a USB
//! adapter's tty is when no driver has it open: a driver that dies releases it and a restarted
//! one opens it again. Masters are non-blocking: with no driver attached, replies are lost, as
//! on a line nobody listens to.

use crate::bus::{BusReport, SimBus};
use nix::fcntl::{fcntl, FcntlArg, FdFlag, OFlag};
use nix::poll::{ppoll, PollFd, PollFlags};
use nix::sys::termios::{cfmakeraw, tcgetattr, tcsetattr, SetArg};
use nix::sys::time::TimeSpec;
use std::os::fd::{AsFd, OwnedFd};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use thiserror::Error;

/// Where the simulator links its devices by default (DIR/<bus name>), and the driver's
/// `--device-dir` in a development run finds them.
pub fn default_device_dir() -> std::path::PathBuf {
    std::env::temp_dir().join("nori-sim")
}

/// How long a hung-up pty (no driver attached) is left out of the poll set.
const HANGUP_BACKOFF: f64 = 0.005;

/// Why the robot could not be served.
#[derive(Debug, Error)]
#[allow(missing_docs, reason = "each field is shown in its variant's message")]
pub enum ServeError {
    /// Creating or configuring a pseudo-terminal failed.
    #[error("pseudo-terminal for bus {bus}: {what}: {source}")]
    Pty {
        /// Bus name.
        bus: String,
        /// The step that failed.
        what: &'static str,
        source: nix::Error,
    },
    /// Creating the device link failed.
    #[error("cannot create device link {path}: {source}")]
    Link {
        /// Link path.
        path: PathBuf,
        source: std::io::Error,
    },
    /// Creating a wire log's file failed.
    #[error("cannot create the wire log {path}: {source}")]
    WireLog {
        /// The file.
        path: PathBuf,
        source: std::io::Error,
    },
}

/// The simulated robot being served; call [`ServedRobot::stop`] to end it.
pub struct ServedRobot {
    /// Device link of each bus, in order.
    pub devices: Vec<PathBuf>,
    buses: Arc<Mutex<Vec<SimBus>>>,
    stop: Arc<AtomicBool>,
    /// Bit `i`: bus `i` is unplugged (its pseudo-terminal closed, its link removed).
    unplugged: Arc<AtomicU32>,
    thread: Option<JoinHandle<()>>,
}

impl ServedRobot {
    /// Runs `f` on the bus named `name` (to place obstacles, unplug a servo, read state).
    pub fn with_bus<R>(&self, name: &str, f: impl FnOnce(&mut SimBus) -> R) -> Option<R> {
        let mut buses = self.buses.lock().ok()?;
        buses.iter_mut().find(|b| b.name == name).map(f)
    }

    /// The buses, shared with the threads that read the simulated state (the cameras).
    pub fn shared_buses(&self) -> Arc<Mutex<Vec<SimBus>>> {
        self.buses.clone()
    }

    /// Unplugs bus `name`, as a USB adapter pulled out: its pseudo-terminal is closed (a driver
    /// that has it open gets a hang-up) and its device link removed; the servos behind it keep
    /// running on their last goals. Returns false for an unknown bus.
    pub fn unplug(&self, name: &str) -> bool {
        self.set_plugged(name, false)
    }

    /// Plugs bus `name` back in: a new pseudo-terminal linked at the same device path.
    pub fn replug(&self, name: &str) -> bool {
        self.set_plugged(name, true)
    }

    /// Whether bus `name` is plugged in and its device link exists now.
    pub fn is_plugged(&self, name: &str) -> bool {
        self.index(name).is_some_and(|i| {
            self.unplugged.load(Ordering::SeqCst) & (1 << i) == 0
                && std::fs::symlink_metadata(&self.devices[i]).is_ok()
        })
    }

    fn index(&self, name: &str) -> Option<usize> {
        let buses = self.buses.lock().ok()?;
        buses.iter().position(|b| b.name == name)
    }

    fn set_plugged(&self, name: &str, plugged: bool) -> bool {
        let Some(i) = self.index(name) else {
            return false;
        };
        if plugged {
            self.unplugged.fetch_and(!(1 << i), Ordering::SeqCst);
        } else {
            self.unplugged.fetch_or(1 << i, Ordering::SeqCst);
        }
        true
    }

    /// Reports of every bus now.
    pub fn reports(&self) -> Vec<BusReport> {
        self.buses
            .lock()
            .map(|b| b.iter().map(SimBus::report).collect())
            .unwrap_or_default()
    }

    /// Stops serving, removes the device links and returns the final reports.
    pub fn stop(mut self) -> Vec<BusReport> {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        for d in &self.devices {
            let _ = std::fs::remove_file(d);
        }
        self.reports()
    }
}

impl Drop for ServedRobot {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

pub(crate) fn open_pty(bus: &str, device: &Path) -> Result<OwnedFd, ServeError> {
    let fail = |what| {
        move |source| ServeError::Pty {
            bus: bus.into(),
            what,
            source,
        }
    };
    let pty = nix::pty::openpty(None, None).map_err(fail("openpty"))?;
    // Raw mode: binary frames must pass untouched (no echo, no CR/LF mapping).
    let mut termios = tcgetattr(&pty.slave).map_err(fail("tcgetattr"))?;
    cfmakeraw(&mut termios);
    tcsetattr(&pty.slave, SetArg::TCSANOW, &termios).map_err(fail("tcsetattr"))?;
    let name = nix::unistd::ttyname(&pty.slave).map_err(fail("ttyname"))?;
    fcntl(&pty.master, FcntlArg::F_SETFL(OFlag::O_NONBLOCK))
        .map_err(fail("non-blocking master"))?;
    // Not inherited by programs this process starts (a benchmark serves the lidar and then
    // starts nori-lidar): a child holding a copy of the master would keep the line up after
    // an unplug, and the reader would never see the hang-up.
    fcntl(&pty.master, FcntlArg::F_SETFD(FdFlag::FD_CLOEXEC)).map_err(fail("close-on-exec"))?;
    drop(pty.slave);
    let link = |source| ServeError::Link {
        path: device.into(),
        source,
    };
    if let Some(dir) = device.parent() {
        std::fs::create_dir_all(dir).map_err(link)?;
    }
    let _ = std::fs::remove_file(device);
    std::os::unix::fs::symlink(&name, device).map_err(link)?;
    Ok(pty.master)
}

/// Serves each `(bus, device link)` on a new pseudo-terminal, stepping mechanics every `dt` s.
///
/// At most 32 buses (the unplug mask is a `u32`).
pub fn serve(buses: Vec<(SimBus, PathBuf)>, dt: f64) -> Result<ServedRobot, ServeError> {
    serve_logged(buses, dt, None)
}

/// [`serve`], and with `wire_log` every byte each bus received and sent appended to
/// `DIR/<bus>.received` and `DIR/<bus>.sent` as it crossed the line: the simulator's own record
/// of the wire, to hold a recording of the driver's side against.
pub fn serve_logged(
    buses: Vec<(SimBus, PathBuf)>,
    dt: f64,
    wire_log: Option<&Path>,
) -> Result<ServedRobot, ServeError> {
    let mut masters = Vec::with_capacity(buses.len());
    let mut devices = Vec::with_capacity(buses.len());
    let mut names = Vec::with_capacity(buses.len());
    for (bus, device) in buses.iter().take(32) {
        masters.push(Some(open_pty(&bus.name, device)?));
        devices.push(device.clone());
        names.push(bus.name.clone());
    }
    let buses = Arc::new(Mutex::new(
        buses
            .into_iter()
            .take(32)
            .map(|(b, _)| b)
            .collect::<Vec<_>>(),
    ));
    let stop = Arc::new(AtomicBool::new(false));
    let unplugged = Arc::new(AtomicU32::new(0));
    let thread = {
        let (buses, stop, unplugged) = (buses.clone(), stop.clone(), unplugged.clone());
        let logs = names
            .iter()
            .map(|name| wire_log.map(|dir| WireLog::create(dir, name)).transpose())
            .collect::<Result<Vec<_>, _>>()?;
        let lines = Lines {
            masters,
            devices: devices.clone(),
            names,
            unplugged,
            logs,
        };
        std::thread::Builder::new()
            .name("sim-buses".into())
            .spawn(move || run(lines, &buses, &stop, dt))
            .ok()
    };
    Ok(ServedRobot {
        devices,
        buses,
        stop,
        unplugged,
        thread,
    })
}

/// CLOCK_MONOTONIC, ns: the stack's shared time base (as `telemetry::clock`).
fn monotonic_ns() -> u64 {
    nix::time::clock_gettime(nix::time::ClockId::CLOCK_MONOTONIC)
        .map(|t| t.tv_sec() as u64 * 1_000_000_000 + t.tv_nsec() as u64)
        .unwrap_or(0)
}

/// The serving thread's pseudo-terminals: `None` while a bus is unplugged.
struct Lines {
    masters: Vec<Option<OwnedFd>>,
    devices: Vec<PathBuf>,
    names: Vec<String>,
    unplugged: Arc<AtomicU32>,
    logs: Vec<Option<WireLog>>,
}

/// One bus's record of its wire: the bytes received and the bytes sent, each as a stream.
struct WireLog {
    received: std::fs::File,
    sent: std::fs::File,
}

impl WireLog {
    fn create(dir: &Path, bus: &str) -> Result<WireLog, ServeError> {
        let open = |suffix: &str| {
            let path = dir.join(format!("{bus}.{suffix}"));
            std::fs::File::create(&path).map_err(|source| ServeError::WireLog { path, source })
        };
        Ok(WireLog {
            received: open("received")?,
            sent: open("sent")?,
        })
    }

    /// Appends `bytes` to one stream (a failed write is logged, and the record has a hole).
    fn append(file: &mut std::fs::File, bytes: &[u8]) {
        use std::io::Write;
        if let Err(e) = file.write_all(bytes) {
            tracing::warn!("wire log: {e}");
        }
    }
}

impl Lines {
    /// Closes or reopens the pseudo-terminals whose plug state was changed.
    fn follow_plugs(&mut self) {
        let mask = self.unplugged.load(Ordering::SeqCst);
        for i in 0..self.masters.len() {
            let want_plugged = mask & (1 << i) == 0;
            match (&self.masters[i], want_plugged) {
                (Some(_), false) => {
                    self.masters[i] = None;
                    let _ = std::fs::remove_file(&self.devices[i]);
                    tracing::info!(bus = %self.names[i], "unplugged");
                }
                (None, true) => match open_pty(&self.names[i], &self.devices[i]) {
                    Ok(m) => {
                        self.masters[i] = Some(m);
                        tracing::info!(bus = %self.names[i], "plugged in again");
                    }
                    Err(e) => tracing::warn!("cannot plug the bus in again: {e}"),
                },
                _ => {}
            }
        }
    }
}

fn run(mut lines: Lines, buses: &Mutex<Vec<SimBus>>, stop: &AtomicBool, dt: f64) {
    // Wake-ups on time (the default 50 µs timer slack would distort the line timing).
    if nix::sys::prctl::set_timerslack(1).is_err() {
        tracing::warn!("cannot reduce timer slack: reply timing may be up to 50 µs late");
    }
    let start = Instant::now();
    let epoch = monotonic_ns();
    if let Ok(mut b) = buses.lock() {
        b.iter_mut().for_each(|b| b.epoch_monotonic_ns = epoch);
    }
    let mut buf = [0u8; 512];
    let mut hung_up_until = vec![0.0f64; lines.masters.len()];
    while !stop.load(Ordering::Relaxed) {
        lines.follow_plugs();
        let masters = &lines.masters;
        let now = start.elapsed().as_secs_f64();
        let mut next_due = now + dt;
        {
            let Ok(mut buses) = buses.lock() else { return };
            for ((bus, master), log) in buses.iter_mut().zip(masters).zip(&mut lines.logs) {
                bus.advance_to(now, dt);
                while let Some(reply) = bus.pop_due(now) {
                    // Nobody listening (or a full buffer, or unplugged): the reply is lost, as
                    // on a real line.
                    let written = master
                        .as_ref()
                        .and_then(|m| nix::unistd::write(m, &reply.bytes).ok());
                    if let (Some(n), Some(log)) = (written, log.as_mut()) {
                        WireLog::append(&mut log.sent, &reply.bytes[..n]);
                    }
                }
                if let Some(due) = bus.next_due() {
                    next_due = next_due.min(due);
                }
            }
        }
        let wait = Duration::from_secs_f64((next_due - now).max(0.0));
        let polled: Vec<usize> = (0..masters.len())
            .filter(|&i| hung_up_until[i] <= now && masters[i].is_some())
            .collect();
        let mut fds: Vec<PollFd> = polled
            .iter()
            .filter_map(|&i| masters[i].as_ref())
            .map(|m| PollFd::new(m.as_fd(), PollFlags::POLLIN))
            .collect();
        if ppoll(&mut fds, Some(TimeSpec::from_duration(wait)), None).is_err() {
            continue;
        }
        let events: Vec<(usize, PollFlags)> = polled
            .iter()
            .zip(&fds)
            .filter_map(|(&i, fd)| fd.revents().filter(|r| !r.is_empty()).map(|r| (i, r)))
            .collect();
        drop(fds);
        for (i, revents) in events {
            let now = start.elapsed().as_secs_f64();
            let Some(master) = &masters[i] else { continue };
            if revents.contains(PollFlags::POLLIN) {
                match nix::unistd::read(master, &mut buf) {
                    Ok(n) if n > 0 => {
                        if let Some(log) = lines.logs[i].as_mut() {
                            WireLog::append(&mut log.received, &buf[..n]);
                        }
                        if let Ok(mut buses) = buses.lock() {
                            let bus = &mut buses[i];
                            bus.advance_to(now, dt);
                            bus.receive(now, &buf[..n]);
                        }
                    }
                    // EIO: the driver closed the slave.
                    _ => hung_up_until[i] = now + HANGUP_BACKOFF,
                }
            } else {
                hung_up_until[i] = now + HANGUP_BACKOFF;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_program_started_while_serving_does_not_inherit_the_line() {
        // Otherwise the child's copy of the master keeps the line up after an unplug, and a
        // driver or lidar process started by the same program never sees the hang-up.
        let dir = std::env::temp_dir().join(format!("nori-pty-cloexec-{}", std::process::id()));
        let master = open_pty("test", &dir.join("line")).unwrap();
        let out = std::process::Command::new("ls")
            .args(["-l", "/proc/self/fd"])
            .output()
            .unwrap();
        let fds = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success());
        assert!(!fds.contains("ptmx"), "the child holds the master: {fds}");
        drop(master);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
