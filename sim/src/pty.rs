//! Serving simulated buses on pseudo-terminals, in real time, so that the unmodified bus driver
//! opens them with `serialport` exactly as it would open `/dev/ttyUSB0`.
//!
//! One thread per bus: it keeps the pty master, steps the mechanics to the wall clock, feeds
//! received bytes to the device side and writes each reply when its last byte would have arrived
//! on a real line. The slave side is closed after creation, as a USB adapter's tty is when no
//! driver has it open: a driver that dies releases it and a restarted one can open it again.

use crate::bus::{BusReport, SimBus};
use serialport::{SerialPort, TTYPort};
use std::io::{ErrorKind, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use thiserror::Error;

/// Sleep precision we do not trust: the last stretch before a reply is due is spun.
const SPIN: Duration = Duration::from_micros(150);

/// Why a bus could not be served.
#[derive(Debug, Error)]
pub enum ServeError {
    /// Creating the pseudo-terminal failed.
    #[error("cannot create a pseudo-terminal for bus {bus}: {source}")]
    Pty {
        /// Bus name.
        bus: String,
        /// Cause.
        source: serialport::Error,
    },
    /// Creating the device link failed.
    #[error("cannot create device link {path}: {source}")]
    Link {
        /// Link path.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
}

/// A bus being served; dropping it does not stop it: call [`ServedBus::stop`].
pub struct ServedBus {
    /// Path of the device link the driver opens.
    pub device: PathBuf,
    /// The bus, shared with its thread (lock it briefly to place obstacles or read a report).
    pub bus: Arc<Mutex<SimBus>>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl ServedBus {
    /// A report of the bus now.
    pub fn report(&self) -> Option<BusReport> {
        self.bus.lock().ok().map(|b| b.report())
    }

    /// Stops the thread, removes the device link and returns the final report.
    pub fn stop(mut self) -> Option<BusReport> {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        let _ = std::fs::remove_file(&self.device);
        self.report()
    }
}

/// Serves `bus` on a new pseudo-terminal linked at `device`, stepping mechanics every `dt` s.
pub fn serve(bus: SimBus, device: &Path, dt: f64) -> Result<ServedBus, ServeError> {
    let name = bus.name.clone();
    let (master, slave) = TTYPort::pair().map_err(|source| ServeError::Pty {
        bus: name.clone(),
        source,
    })?;
    let slave_path = slave.name().unwrap_or_default();
    drop(slave);
    let _ = std::fs::remove_file(device);
    if let Some(dir) = device.parent() {
        std::fs::create_dir_all(dir).map_err(|source| ServeError::Link {
            path: device.into(),
            source,
        })?;
    }
    std::os::unix::fs::symlink(&slave_path, device).map_err(|source| ServeError::Link {
        path: device.into(),
        source,
    })?;
    let bus = Arc::new(Mutex::new(bus));
    let stop = Arc::new(AtomicBool::new(false));
    let thread = {
        let (bus, stop) = (bus.clone(), stop.clone());
        std::thread::Builder::new()
            .name(format!("sim-{name}"))
            .spawn(move || run(master, &bus, &stop, dt))
            .ok()
    };
    Ok(ServedBus {
        device: device.into(),
        bus,
        stop,
        thread,
    })
}

fn run(mut master: TTYPort, bus: &Mutex<SimBus>, stop: &AtomicBool, dt: f64) {
    let start = Instant::now();
    let mut buf = [0u8; 512];
    while !stop.load(Ordering::Relaxed) {
        let now = start.elapsed().as_secs_f64();
        let next_due = {
            let Ok(mut b) = bus.lock() else { return };
            b.advance_to(now, dt);
            while let Some(reply) = b.pop_due(now) {
                // A driver that is not there loses the reply, as on a real line.
                let _ = master.write_all(&reply.bytes);
            }
            b.next_due()
        };
        let until = next_due.map_or(dt, |due| (due - now).min(dt)).max(0.0);
        let wait = Duration::from_secs_f64(until);
        if wait <= SPIN && next_due.is_some() {
            std::hint::spin_loop();
            continue;
        }
        let _ = master.set_timeout(wait.saturating_sub(if next_due.is_some() {
            SPIN
        } else {
            Duration::ZERO
        }));
        match master.read(&mut buf) {
            Ok(n) if n > 0 => {
                let now = start.elapsed().as_secs_f64();
                if let Ok(mut b) = bus.lock() {
                    b.advance_to(now, dt);
                    b.receive(&buf[..n]);
                }
            }
            Ok(_) => {}
            Err(e) if e.kind() == ErrorKind::TimedOut => {}
            // No driver has the slave open (hang-up): nothing to read, keep simulating.
            Err(_) => std::thread::sleep(
                Duration::from_millis(2).min(wait.max(Duration::from_micros(200))),
            ),
        }
    }
}
