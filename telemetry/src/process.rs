//! What every process of the stack does first: log to stderr (level from `RUST_LOG`, default
//! info), and turn SIGINT/SIGTERM into a flag its loop checks, so it can stop cleanly (torque
//! off, in the driver's case) instead of dying.

use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// Logging to stderr, level from `RUST_LOG` (default `info`).
pub fn init_logging() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
}

/// A flag set when SIGINT or SIGTERM arrives.
pub fn stop_flag() -> std::io::Result<Arc<AtomicBool>> {
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(signal, stop.clone())?;
    }
    Ok(stop)
}

/// The service manager's side of a process: readiness and watchdog keep-alives over
/// `$NOTIFY_SOCKET` (systemd's `Type=notify` and `WatchdogSec=`). Outside systemd every call
/// is a no-op, so the binaries call it unconditionally.
///
/// Written here rather than with the `sd-notify` crate because that one sends blocking: a
/// manager that stops reading would stall the driver's control loop once the socket's queue
/// is full. Ours is non-blocking: a message that does not fit is dropped (and said once).
#[derive(Debug)]
pub struct ServiceManager {
    socket: Option<std::os::unix::net::UnixDatagram>,
    ping_every: Option<std::time::Duration>,
    last_ping: Option<std::time::Instant>,
    warned: bool,
}

impl ServiceManager {
    /// Reads `NOTIFY_SOCKET`, `WATCHDOG_USEC` and `WATCHDOG_PID` from the environment.
    pub fn from_env() -> Self {
        let var = |k: &str| std::env::var(k).ok();
        let socket = var("NOTIFY_SOCKET").and_then(|path| match notify_socket(&path) {
            Ok(s) => Some(s),
            Err(e) => {
                tracing::warn!(
                    "NOTIFY_SOCKET={path} cannot be used: {e}; no readiness or watchdog"
                );
                None
            }
        });
        ServiceManager {
            ping_every: socket.as_ref().and_then(|_| {
                watchdog_ping_interval(
                    var("WATCHDOG_USEC").as_deref(),
                    var("WATCHDOG_PID").as_deref(),
                    std::process::id(),
                )
            }),
            socket,
            last_ping: None,
            warned: false,
        }
    }

    /// The watchdog is armed: keep-alives are due every this long.
    pub fn ping_every(&self) -> Option<std::time::Duration> {
        self.ping_every
    }

    /// `READY=1` with a status line: the process is serving.
    pub fn ready(&mut self, status: &str) {
        self.send(&format!("READY=1\nSTATUS={status}\n"));
    }

    /// A new status line (`systemctl status` shows it).
    pub fn status(&mut self, status: &str) {
        self.send(&format!("STATUS={status}\n"));
    }

    /// `STOPPING=1`.
    pub fn stopping(&mut self) {
        self.send("STOPPING=1\n");
    }

    /// Call from the loop that must be alive: sends `WATCHDOG=1` when one is due (at half the
    /// watchdog period, so one late cycle does not get the process killed). Cheap otherwise.
    pub fn keepalive(&mut self, now: std::time::Instant) {
        let Some(every) = self.ping_every else {
            return;
        };
        if self
            .last_ping
            .is_some_and(|t| now.duration_since(t) < every)
        {
            return;
        }
        self.last_ping = Some(now);
        self.send("WATCHDOG=1\n");
    }

    fn send(&mut self, message: &str) {
        let Some(socket) = &self.socket else {
            return;
        };
        if let Err(e) = socket.send(message.as_bytes()) {
            if !self.warned {
                self.warned = true;
                tracing::warn!(
                    "cannot notify the service manager ({e}); further failures are silent"
                );
            }
        }
    }
}

/// A non-blocking datagram socket connected to `$NOTIFY_SOCKET` (a path, or `@name` for the
/// abstract namespace).
fn notify_socket(path: &str) -> std::io::Result<std::os::unix::net::UnixDatagram> {
    use std::os::unix::net::{SocketAddr, UnixDatagram};
    let addr = match path.strip_prefix('@') {
        Some(name) => {
            use std::os::linux::net::SocketAddrExt;
            SocketAddr::from_abstract_name(name)?
        }
        None => SocketAddr::from_pathname(path)?,
    };
    let socket = UnixDatagram::unbound()?;
    socket.connect_addr(&addr)?;
    socket.set_nonblocking(true)?;
    Ok(socket)
}

/// Keep-alive period for a watchdog of `WATCHDOG_USEC` (half of it), if the watchdog is meant
/// for process `pid` (systemd sets `WATCHDOG_PID` to the main process; absent means us).
pub fn watchdog_ping_interval(
    usec: Option<&str>,
    watchdog_pid: Option<&str>,
    pid: u32,
) -> Option<std::time::Duration> {
    let usec: u64 = usec?.trim().parse().ok().filter(|&u| u > 0)?;
    if let Some(p) = watchdog_pid {
        if p.trim().parse::<u32>().ok()? != pid {
            return None;
        }
    }
    Some(std::time::Duration::from_micros(usec / 2))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn the_watchdog_is_pinged_at_half_its_period_and_only_for_its_process() {
        assert_eq!(
            watchdog_ping_interval(Some("2000000"), Some("42"), 42),
            Some(Duration::from_secs(1))
        );
        assert_eq!(
            watchdog_ping_interval(Some("2000000"), None, 42),
            Some(Duration::from_secs(1))
        );
        assert_eq!(watchdog_ping_interval(Some("2000000"), Some("7"), 42), None);
        assert_eq!(watchdog_ping_interval(Some("0"), None, 42), None);
        assert_eq!(watchdog_ping_interval(Some("soon"), None, 42), None);
        assert_eq!(watchdog_ping_interval(None, Some("42"), 42), None);
    }

    #[test]
    fn keepalives_are_rate_limited() {
        let mut sm = ServiceManager {
            socket: None,
            ping_every: Some(Duration::from_millis(100)),
            last_ping: None,
            warned: false,
        };
        let t0 = std::time::Instant::now();
        sm.keepalive(t0);
        assert_eq!(sm.last_ping, Some(t0));
        sm.keepalive(t0 + Duration::from_millis(50));
        assert_eq!(sm.last_ping, Some(t0));
        sm.keepalive(t0 + Duration::from_millis(100));
        assert_eq!(sm.last_ping, Some(t0 + Duration::from_millis(100)));
    }

    #[test]
    fn a_manager_that_stops_reading_never_blocks_the_sender() {
        let dir = std::env::temp_dir().join(format!("nori-notify-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("notify");
        let manager = std::os::unix::net::UnixDatagram::bind(&path).unwrap();
        let mut sm = ServiceManager {
            socket: Some(notify_socket(path.to_str().unwrap()).unwrap()),
            ping_every: Some(Duration::ZERO),
            last_ping: None,
            warned: false,
        };
        sm.ready("serving");
        let mut buf = [0u8; 64];
        let n = manager.recv(&mut buf).unwrap();
        assert_eq!(&buf[..n], b"READY=1\nSTATUS=serving\n");
        // Far more than a datagram queue holds, none read: every call returns.
        let (done_tx, done_rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let t0 = std::time::Instant::now();
            for i in 0..10_000u32 {
                sm.keepalive(t0 + Duration::from_micros(u64::from(i)));
            }
            done_tx.send(sm.warned).unwrap();
        });
        let warned = done_rx
            .recv_timeout(Duration::from_secs(30))
            .expect("the sender blocked");
        assert!(warned, "a full queue is reported once");
        drop(manager);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
