//! A serial device of the simulated robot that is not a servo bus (the lidar, the lift's
//! board), served on a pseudo-terminal in real time: what its driver opens in place of the USB
//! adapter. The device itself is sans-IO ([`SerialDevice`]: bytes in, bytes out, time passed
//! in); this is the one loop that moves its bytes, and unplugs and plugs it back in.

use crate::pty::open_pty;
use nix::poll::{ppoll, PollFd, PollFlags};
use nix::sys::time::TimeSpec;
use std::os::fd::{AsFd, OwnedFd};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// A device on a serial line, sans-IO. Times are seconds since it was served.
pub trait SerialDevice {
    /// Bytes from the host arrived at `now`.
    fn receive(&mut self, now: f64, bytes: &[u8]);
    /// Time passed to `now`: what the device sends meanwhile goes to `write`.
    fn advance(&mut self, now: f64, write: &mut dyn FnMut(&[u8]));
}

/// A device being served; dropping it stops it.
pub struct Served<D> {
    /// Its device link.
    pub device: PathBuf,
    state: Arc<Mutex<D>>,
    plugged: Arc<AtomicBool>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl<D> Served<D> {
    /// Unplugs it (its pseudo-terminal closed, its link removed) or plugs it back in.
    pub fn set_plugged(&self, plugged: bool) {
        self.plugged.store(plugged, Ordering::SeqCst);
    }

    /// Runs `f` on the device (to read its report, or to raise a fault).
    pub fn with_device<R>(&self, f: impl FnOnce(&mut D) -> R) -> Option<R> {
        self.state.lock().ok().map(|mut d| f(&mut d))
    }
}

impl<D> Drop for Served<D> {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        let _ = std::fs::remove_file(&self.device);
    }
}

/// Serves `device` (named `name` in logs and its thread) on a pseudo-terminal linked at `link`.
pub fn serve<D: SerialDevice + Send + 'static>(
    name: &str,
    device: D,
    link: PathBuf,
) -> Result<Served<D>, crate::pty::ServeError> {
    let master = open_pty(name, &link)?;
    let state = Arc::new(Mutex::new(device));
    let plugged = Arc::new(AtomicBool::new(true));
    let stop = Arc::new(AtomicBool::new(false));
    let thread = {
        let (state, plugged, stop, link, name) = (
            state.clone(),
            plugged.clone(),
            stop.clone(),
            link.clone(),
            name.to_string(),
        );
        std::thread::Builder::new()
            .name(format!("sim-{name}"))
            .spawn(move || run(&name, master, &link, &state, &plugged, &stop))
            .ok()
    };
    Ok(Served {
        device: link,
        state,
        plugged,
        stop,
        thread,
    })
}

fn run<D: SerialDevice>(
    name: &str,
    master: OwnedFd,
    link: &std::path::Path,
    state: &Mutex<D>,
    plugged: &AtomicBool,
    stop: &AtomicBool,
) {
    let start = Instant::now();
    let mut master = Some(master);
    let mut buf = [0u8; 256];
    while !stop.load(Ordering::Relaxed) {
        match (&master, plugged.load(Ordering::SeqCst)) {
            (Some(_), false) => {
                master = None;
                let _ = std::fs::remove_file(link);
            }
            (None, true) => match open_pty(name, link) {
                Ok(m) => master = Some(m),
                Err(e) => tracing::warn!("cannot plug the {name} in again: {e}"),
            },
            _ => {}
        }
        let now = start.elapsed().as_secs_f64();
        if let Ok(mut device) = state.lock() {
            device.advance(now, &mut |bytes| {
                // Nobody listening, or a full buffer: lost, as on a real line.
                if let Some(m) = &master {
                    let _ = nix::unistd::write(m, bytes);
                }
            });
        }
        // Wake every 2 ms (the lidar: ten measurements a wake-up at 5 kHz).
        let Some(m) = &master else {
            std::thread::sleep(Duration::from_millis(2));
            continue;
        };
        let mut fds = [PollFd::new(m.as_fd(), PollFlags::POLLIN)];
        let ready = ppoll(
            &mut fds,
            Some(TimeSpec::from_duration(Duration::from_millis(2))),
            None,
        )
        .is_ok_and(|n| n > 0);
        let readable = fds[0]
            .revents()
            .is_some_and(|r| r.contains(PollFlags::POLLIN));
        if ready && readable {
            match nix::unistd::read(m, &mut buf) {
                Ok(n) if n > 0 => {
                    let now = start.elapsed().as_secs_f64();
                    if let Ok(mut device) = state.lock() {
                        device.receive(now, &buf[..n]);
                    }
                }
                _ => std::thread::sleep(Duration::from_millis(2)),
            }
        } else if ready {
            // A hang-up (no driver has the line open).
            std::thread::sleep(Duration::from_millis(2));
        }
    }
}
