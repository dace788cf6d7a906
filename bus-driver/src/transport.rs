//! The one narrow transport trait the bus needs, and its serial-port implementation.

use std::path::{Path, PathBuf};
use std::time::Duration;
use thiserror::Error;

/// A failure of the byte transport itself (never a servo's status bits).
#[derive(Debug, Error)]
#[allow(missing_docs, reason = "each field is shown in its variant's message")]
pub enum TransportError {
    /// The device could not be opened.
    #[error("cannot open {device} at {baud} baud: {source}")]
    Open {
        /// Device path.
        device: PathBuf,
        /// Line rate asked for.
        baud: u32,
        source: serialport::Error,
    },
    /// Another process holds the device (the driver, or a commissioning tool).
    #[error("{device} is held by another process (the driver, or a `nori servo` command): stop it first")]
    Busy {
        /// Device path.
        device: PathBuf,
    },
    /// Reading or writing failed; the device may be gone.
    #[error("i/o on {device}: {source}")]
    Io {
        /// Device path.
        device: PathBuf,
        source: std::io::Error,
    },
}

/// A half-duplex byte link to one servo bus.
pub trait Transport {
    /// Line rate, baud (for wire-time deadlines).
    fn baud(&self) -> u32;
    /// Writes all of `bytes`.
    fn send(&mut self, bytes: &[u8]) -> Result<(), TransportError>;
    /// Reads what has arrived, waiting at most `timeout` (zero: only what is already there);
    /// `Ok(0)` when nothing came in time.
    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, TransportError>;
    /// Drops bytes received and not yet read (late replies of an earlier transaction).
    fn discard_input(&mut self) -> Result<(), TransportError>;
    /// Opens the same device again after a failure (an adapter unplugged and plugged back in
    /// comes back at the same udev path). The default, for links that cannot vanish, does
    /// nothing.
    fn reopen(&mut self) -> Result<(), TransportError> {
        Ok(())
    }
    /// Talks at `baud` from now on, on the same open device (a scan tries every rate the
    /// servos support). The default, for links with one rate, refuses.
    fn set_baud(&mut self, baud: u32) -> Result<(), TransportError> {
        Err(TransportError::Io {
            device: PathBuf::from("(a link with one rate)"),
            source: std::io::Error::new(
                std::io::ErrorKind::Unsupported,
                format!("cannot change the line rate to {baud} baud"),
            ),
        })
    }
    /// Hands the traffic recorded since the last call to `publish`, frame by frame in order,
    /// and empties it: on a tapped link ([`crate::tap::Tapped`]); a plain one has none.
    fn take_wire(&mut self, _publish: &mut dyn FnMut(&mut telemetry::wire::WireFrame)) {}
}

/// A servo bus on a serial device (USB adapter, UART, or the simulator's pseudo-terminal).
pub struct SerialTransport {
    port: serialport::TTYPort,
    device: PathBuf,
    baud: u32,
}

impl SerialTransport {
    /// Opens `device` at `baud`, 8N1, and reports the USB latency timer.
    pub fn open(device: &Path, baud: u32) -> Result<Self, TransportError> {
        let port = open_port(device, baud)?;
        match latency_timer(device) {
            LatencyTimer::Ms(1) => {
                tracing::info!(device = %device.display(), "USB latency timer is 1 ms")
            }
            LatencyTimer::Ms(ms) => tracing::warn!(
                device = %device.display(),
                latency_timer_ms = ms,
                "USB latency timer is {ms} ms, not 1 ms: every reply waits up to that long. \
                 Set it with the udev rule in deploy/udev or write 1 to the latency_timer file"
            ),
            LatencyTimer::Unreadable(why) => {
                tracing::warn!(device = %device.display(), "cannot check the USB latency timer: {why}")
            }
            LatencyTimer::NotUsbSerial => {
                tracing::info!(device = %device.display(), "not a USB serial adapter; no latency timer to check")
            }
        }
        Ok(SerialTransport {
            port,
            device: device.into(),
            baud,
        })
    }

    /// The device path.
    pub fn device(&self) -> &Path {
        &self.device
    }

    fn io(&self, source: std::io::Error) -> TransportError {
        TransportError::Io {
            device: self.device.clone(),
            source,
        }
    }
}

fn open_port(device: &Path, baud: u32) -> Result<serialport::TTYPort, TransportError> {
    refuse_if_held(device)?;
    serialport::new(device.to_string_lossy(), baud)
        .timeout(Duration::from_millis(1))
        .open_native()
        .map_err(|source| TransportError::Open {
            device: device.into(),
            baud,
            source,
        })
}

/// Refuses a device another process holds, asking its lock on a plain descriptor first.
/// serialport's exclusive open takes the same lock, but when it is refused it closes its
/// descriptor with TIOCNXCL, which clears the holder's exclusive flag for the whole tty
/// (as root, whose open TIOCEXCL does not stop): one refused `nori servo` run would leave a
/// running driver's bus open to any program. A device that cannot be opened here is left to
/// serialport's open, which says why.
fn refuse_if_held(device: &Path) -> Result<(), TransportError> {
    use nix::errno::Errno;
    use nix::fcntl::{Flock, FlockArg, OFlag};
    use std::os::unix::fs::OpenOptionsExt;
    let busy = || TransportError::Busy {
        device: device.into(),
    };
    let probe = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags((OFlag::O_NOCTTY | OFlag::O_NONBLOCK).bits())
        .open(device);
    match probe {
        Ok(file) => match Flock::lock(file, FlockArg::LockExclusiveNonblock) {
            Err((_, Errno::EWOULDBLOCK)) => Err(busy()),
            // Released at once: serialport takes it for as long as the port is open.
            Ok(_) | Err(_) => Ok(()),
        },
        Err(e) if e.raw_os_error() == Some(Errno::EBUSY as i32) => Err(busy()),
        Err(_) => Ok(()),
    }
}

impl Transport for SerialTransport {
    /// Opens the device path again (the old descriptor is closed once the new one is open;
    /// a path that does not exist yet fails fast).
    fn reopen(&mut self) -> Result<(), TransportError> {
        self.port = open_port(&self.device, self.baud)?;
        Ok(())
    }

    fn baud(&self) -> u32 {
        self.baud
    }

    fn set_baud(&mut self, baud: u32) -> Result<(), TransportError> {
        use serialport::SerialPort;
        self.port
            .set_baud_rate(baud)
            .map_err(|e| self.io(std::io::Error::other(e)))?;
        self.baud = baud;
        Ok(())
    }

    fn send(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        use std::io::Write;
        self.port.write_all(bytes).map_err(|e| self.io(e))
    }

    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, TransportError> {
        use serialport::SerialPort;
        use std::io::Read;
        self.port
            .set_timeout(timeout)
            .map_err(|e| self.io(std::io::Error::other(e)))?;
        received(self.port.read(buf)).map_err(|e| self.io(e))
    }

    fn discard_input(&mut self) -> Result<(), TransportError> {
        use serialport::SerialPort;
        self.port
            .clear(serialport::ClearBuffer::Input)
            .map_err(|e| self.io(std::io::Error::other(e)))
    }
}

/// What a read of the device came to: bytes, or none yet (it timed out, or a signal such as the
/// SIGTERM that stops the driver interrupted the wait: the deadline loop simply goes on), or a
/// failure of the device itself (which marks the bus lost).
fn received(read: std::io::Result<usize>) -> std::io::Result<usize> {
    use std::io::ErrorKind::{Interrupted, TimedOut, WouldBlock};
    match read {
        Err(e) if matches!(e.kind(), TimedOut | Interrupted | WouldBlock) => Ok(0),
        other => other,
    }
}

/// What the USB serial adapter's latency timer is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LatencyTimer {
    /// The timer, ms (FTDI's default is 16; the bus wants 1).
    Ms(u32),
    /// The device is not a USB serial adapter (UART, pseudo-terminal).
    NotUsbSerial,
    /// The sysfs file exists but could not be read or parsed.
    Unreadable(String),
}

/// Parses the content of a `latency_timer` sysfs file.
pub fn parse_latency_timer(text: &str) -> LatencyTimer {
    match text.trim().parse::<u32>() {
        Ok(ms) => LatencyTimer::Ms(ms),
        Err(_) => LatencyTimer::Unreadable(format!("unexpected content {:?}", text.trim())),
    }
}

/// The sysfs file of a tty's latency timer (`/dev/ttyUSB0` or a udev link to it).
pub fn latency_timer_path(device: &Path) -> Option<PathBuf> {
    let real = std::fs::canonicalize(device).ok()?;
    let name = real.file_name()?.to_str()?;
    Some(
        Path::new("/sys/bus/usb-serial/devices")
            .join(name)
            .join("latency_timer"),
    )
}

/// Reads the latency timer of `device`.
pub fn latency_timer(device: &Path) -> LatencyTimer {
    match latency_timer_path(device) {
        Some(path) if path.exists() => match std::fs::read_to_string(&path) {
            Ok(text) => parse_latency_timer(&text),
            Err(e) => LatencyTimer::Unreadable(format!("{}: {e}", path.display())),
        },
        _ => LatencyTimer::NotUsbSerial,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_interrupted_read_is_no_lost_device() {
        use std::io::{Error, ErrorKind};
        assert_eq!(received(Ok(7)).unwrap(), 7);
        for kind in [
            ErrorKind::Interrupted,
            ErrorKind::TimedOut,
            ErrorKind::WouldBlock,
        ] {
            assert_eq!(received(Err(Error::from(kind))).unwrap(), 0, "{kind:?}");
        }
        for kind in [ErrorKind::BrokenPipe, ErrorKind::NotFound, ErrorKind::Other] {
            assert_eq!(received(Err(Error::from(kind))).unwrap_err().kind(), kind);
        }
    }

    #[test]
    fn latency_timer_parsing() {
        assert_eq!(parse_latency_timer("16\n"), LatencyTimer::Ms(16));
        assert_eq!(parse_latency_timer("1"), LatencyTimer::Ms(1));
        assert!(matches!(
            parse_latency_timer("x"),
            LatencyTimer::Unreadable(_)
        ));
    }

    #[test]
    fn a_pseudo_terminal_has_no_latency_timer() {
        use serialport::SerialPort;
        let (_master, slave) = serialport::TTYPort::pair().unwrap();
        let name = slave.name().unwrap();
        assert_eq!(latency_timer(Path::new(&name)), LatencyTimer::NotUsbSerial);
        assert_eq!(
            latency_timer_path(Path::new(&name)).unwrap(),
            Path::new("/sys/bus/usb-serial/devices")
                .join(Path::new(&name).file_name().unwrap())
                .join("latency_timer")
        );
    }
}
