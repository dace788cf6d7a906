//! The lidar process's loop: the start sequence (STOP, GET_INFO, GET_HEALTH, RESET when the
//! device stopped itself, SCAN), then measurements into revolutions onto the plane. A lidar
//! that goes silent is restarted; one that vanishes (unplugged) is opened again every second.
//! A bad byte, node or revolution is refused and counted; it never stops the loop.

use crate::protocol::{Command, DecodeCounters, Decoder, DeviceInfo, Event, Health, HealthStatus};
use crate::scan::{saturate, Assembler, ScanCounters, ScanLimits};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use telemetry::plane::{publish, PlaneError, Pub};
use telemetry::sensors::LidarScan;

/// How long the device has to answer GET_INFO or GET_HEALTH, or to start a scan (the SDK
/// waits 500 ms on connect; a C1 spins up before its descriptor).
const ANSWER_TIMEOUT: Duration = Duration::from_millis(1000);
/// After STOP: the protocol asks for 1 ms; Slamtec's SDK waits 100.
const AFTER_STOP: Duration = Duration::from_millis(20);
/// After RESET: the device reboots (community C1 drivers wait 500 ms).
const AFTER_RESET: Duration = Duration::from_millis(700);

/// A failure of the byte link (never of the device's answers).
#[derive(Debug, thiserror::Error)]
#[allow(missing_docs, reason = "each field is shown in its variant's message")]
pub enum LinkError {
    /// The device could not be opened.
    #[error("cannot open {device} at {baud} baud: {source}")]
    Open {
        /// Device path.
        device: PathBuf,
        /// Line rate.
        baud: u32,
        source: serialport::Error,
    },
    /// Reading or writing failed: the device may be gone.
    #[error("i/o on {device}: {source}")]
    Io {
        /// Device path.
        device: PathBuf,
        source: std::io::Error,
    },
}

/// A byte link to the lidar.
pub trait Link {
    /// Writes all of `bytes`.
    fn send(&mut self, bytes: &[u8]) -> Result<(), LinkError>;
    /// Reads what has arrived, waiting at most `timeout`; `Ok(0)` when nothing came.
    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError>;
    /// Drops bytes received and not read.
    fn discard_input(&mut self) -> Result<(), LinkError>;
}

/// The lidar on a serial device (its USB adapter, or the simulator's pseudo-terminal).
pub struct SerialLink {
    port: serialport::TTYPort,
    device: PathBuf,
}

impl SerialLink {
    /// Opens `device` at `baud`, 8N1, no flow control.
    pub fn open(device: &Path, baud: u32) -> Result<Self, LinkError> {
        let port = serialport::new(device.to_string_lossy(), baud)
            .timeout(Duration::from_millis(100))
            .open_native()
            .map_err(|source| LinkError::Open {
                device: device.into(),
                baud,
                source,
            })?;
        Ok(SerialLink {
            port,
            device: device.into(),
        })
    }

    fn io(&self, source: std::io::Error) -> LinkError {
        LinkError::Io {
            device: self.device.clone(),
            source,
        }
    }
}

impl Link for SerialLink {
    fn send(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        use std::io::Write;
        self.port.write_all(bytes).map_err(|e| self.io(e))
    }

    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
        use serialport::SerialPort;
        use std::io::ErrorKind::{Interrupted, TimedOut, WouldBlock};
        use std::io::Read;
        self.port
            .set_timeout(timeout)
            .map_err(|e| self.io(std::io::Error::other(e)))?;
        match self.port.read(buf) {
            Err(e) if matches!(e.kind(), TimedOut | Interrupted | WouldBlock) => Ok(0),
            // A pseudo-terminal whose other side closed reads 0 bytes at once: gone.
            Ok(0) => Err(self.io(std::io::ErrorKind::UnexpectedEof.into())),
            other => other.map_err(|e| self.io(e)),
        }
    }

    fn discard_input(&mut self) -> Result<(), LinkError> {
        use serialport::SerialPort;
        self.port
            .clear(serialport::ClearBuffer::Input)
            .map_err(|e| self.io(std::io::Error::other(e)))
    }
}

/// Why the loop stopped, or why a start failed.
#[derive(Debug, thiserror::Error)]
pub enum LidarError {
    /// The link failed.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// The device did not answer a request in time.
    #[error("no answer to {request} within {timeout:?}")]
    NoAnswer {
        /// The request.
        request: &'static str,
        /// How long it had.
        timeout: Duration,
    },
    /// The device reports a protection stop that a RESET did not clear.
    #[error(
        "the lidar reports a protection stop (error code {code:#06x}) that a reset did not clear"
    )]
    ProtectionStop {
        /// The device's error code.
        code: u16,
    },
    /// The plane refused a scan.
    #[error(transparent)]
    Plane(#[from] PlaneError),
}

/// What the process itself did, reported at exit.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct Counters {
    /// Scans started (the first, and each restart).
    pub scan_starts: u64,
    /// Times no measurement came for the configured silence.
    pub silences: u64,
    /// Times the device was lost and opened again.
    pub reconnects: u64,
    /// RESETs sent because the device reported a protection stop.
    pub resets: u64,
}

/// Everything counted, as printed at exit.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct Report {
    /// Revolutions and points.
    pub scan: ScanCounters,
    /// Bytes and answers refused by the protocol decoder.
    pub decode: DecodeCounters,
    /// Starts, silences, reconnects.
    pub process: Counters,
}

/// The lidar's publishing state.
pub struct Lidar {
    decoder: Decoder,
    assembler: Assembler,
    publisher: Pub<LidarScan>,
    counters: Counters,
    /// The device's identity, once it answered.
    pub info: Option<DeviceInfo>,
    /// Its last health report.
    pub health: Option<Health>,
    /// Nodes decoded so far (to notice silence).
    nodes: u64,
}

impl Lidar {
    /// A lidar publishing on `publisher`.
    pub fn new(limits: ScanLimits, publisher: Pub<LidarScan>) -> Self {
        Lidar {
            decoder: Decoder::new(),
            assembler: Assembler::new(limits),
            publisher,
            counters: Counters::default(),
            info: None,
            health: None,
            nodes: 0,
        }
    }

    /// Everything counted so far.
    pub fn report(&self) -> Report {
        Report {
            scan: self.assembler.counters(),
            decode: self.decoder.counters(),
            process: self.counters,
        }
    }

    /// Feeds received bytes: nodes go into revolutions (each completed one is published);
    /// returns the last other event.
    pub fn pump(&mut self, bytes: &[u8], now_ns: u64) -> Result<Option<Event>, PlaneError> {
        let mut answer = None;
        for &b in bytes {
            match self.decoder.push(b) {
                Some(Event::Node(node)) => {
                    self.nodes += 1;
                    if self.assembler.push(node, now_ns) {
                        let decoded = self.decoder.counters();
                        let scan = self.assembler.scan_mut();
                        scan.bad_points = saturate(decoded.unconfirmed);
                        scan.resyncs = saturate(decoded.resyncs);
                        publish(&self.publisher, scan)?;
                    }
                }
                Some(Event::Unexpected(d)) => {
                    tracing::warn!("unexpected answer from the lidar: {d:?}");
                }
                Some(e) => answer = Some(e),
                None => {}
            }
        }
        Ok(answer)
    }

    fn request(&mut self, link: &mut dyn Link, command: Command) -> Result<(), LidarError> {
        self.decoder.request_sent();
        link.send(&command.bytes())?;
        Ok(())
    }

    /// Sends `command` and waits for the answer `want` picks.
    fn ask<T>(
        &mut self,
        link: &mut dyn Link,
        command: Command,
        request: &'static str,
        want: impl Fn(Event) -> Option<T>,
    ) -> Result<T, LidarError> {
        self.request(link, command)?;
        let deadline = Instant::now() + ANSWER_TIMEOUT;
        let mut buf = [0u8; 512];
        while let Some(left) = deadline.checked_duration_since(Instant::now()) {
            let n = link.receive(&mut buf, left)?;
            let now = telemetry::clock::monotonic_ns();
            if let Some(answer) = self.pump(&buf[..n], now)?.and_then(&want) {
                return Ok(answer);
            }
        }
        Err(LidarError::NoAnswer {
            request,
            timeout: ANSWER_TIMEOUT,
        })
    }

    /// Stops whatever the device was doing, reads its identity and health (resetting it once
    /// if it stopped itself), and starts the standard scan.
    pub fn start_scan(&mut self, link: &mut dyn Link) -> Result<(), LidarError> {
        self.request(link, Command::Stop)?;
        std::thread::sleep(AFTER_STOP);
        link.discard_input()?;
        let info = self.ask(link, Command::GetInfo, "GET_INFO", |e| match e {
            Event::Info(i) => Some(i),
            _ => None,
        })?;
        if self.info != Some(info) {
            log_identity(&info);
        }
        self.info = Some(info);
        let get_health = |e| match e {
            Event::Health(h) => Some(h),
            _ => None,
        };
        let mut health = self.ask(link, Command::GetHealth, "GET_HEALTH", get_health)?;
        if health.status == HealthStatus::Error {
            tracing::warn!(
                code = health.error_code,
                "the lidar reports a protection stop; resetting it"
            );
            self.counters.resets += 1;
            self.request(link, Command::Reset)?;
            std::thread::sleep(AFTER_RESET);
            link.discard_input()?;
            health = self.ask(link, Command::GetHealth, "GET_HEALTH", get_health)?;
            if health.status == HealthStatus::Error {
                self.health = Some(health);
                return Err(LidarError::ProtectionStop {
                    code: health.error_code,
                });
            }
        }
        if health.status != HealthStatus::Good {
            tracing::warn!(
                code = health.error_code,
                "the lidar reports {:?}; scanning anyway",
                health.status
            );
        }
        self.health = Some(health);
        self.assembler.restart();
        self.ask(link, Command::Scan, "SCAN", |e| {
            (e == Event::ScanStarted).then_some(())
        })?;
        self.counters.scan_starts += 1;
        Ok(())
    }

    /// Asks the device to stop scanning (its motor stops with the scan).
    pub fn stop(&mut self, link: &mut dyn Link) -> Result<(), LidarError> {
        self.request(link, Command::Stop)
    }
}

fn log_identity(info: &DeviceInfo) {
    let name = info
        .c_series_name()
        .unwrap_or_else(|| format!("model {:#04x}", info.model));
    tracing::info!(
        "lidar {name}, firmware {}.{:02}, hardware {}, serial {}",
        info.firmware_major,
        info.firmware_minor,
        info.hardware,
        info.serial_hex()
    );
    if info.c_series_name().is_none() {
        tracing::warn!(
            "not an RPLIDAR C series device (model {:#04x}): its standard scan is read, other \
             limits may differ",
            info.model
        );
    }
}

/// Runs `lidar` on the device `device` until `stop` (or `run_for`). `open` opens the link; a
/// link lost while running is opened again every second; a device that does not answer, or
/// goes silent for `silence`, is started again.
pub fn run<L: Link>(
    lidar: &mut Lidar,
    device: &Path,
    open: impl Fn(&Path) -> Result<L, LinkError>,
    silence: Duration,
    stop: &AtomicBool,
    run_for: Option<Duration>,
) -> Result<(), LidarError> {
    let started = Instant::now();
    let running = || !stop.load(Ordering::Relaxed) && run_for.is_none_or(|t| started.elapsed() < t);
    let mut link = open(device)?;
    while running() {
        let lost = match lidar.start_scan(&mut link) {
            Ok(()) => {
                tracing::info!("scanning from {}", device.display());
                match scan(lidar, &mut link, silence, &running)? {
                    Scanned::Stopped => break,
                    Scanned::Silent => continue,
                    Scanned::Lost(e) => e,
                }
            }
            Err(e @ LidarError::NoAnswer { .. }) => {
                lidar.counters.silences += 1;
                tracing::warn!("{e}; trying again");
                continue;
            }
            Err(LidarError::Link(e)) => e,
            Err(e) => return Err(e),
        };
        tracing::warn!("{lost}; opening it again");
        match reopen(&open, device, &running) {
            Some(l) => link = l,
            None => return Ok(()),
        }
        lidar.counters.reconnects += 1;
    }
    // The C1's motor spins while it scans: stop it on the way out.
    if let Err(e) = lidar.stop(&mut link) {
        tracing::warn!("cannot stop the lidar: {e}");
    }
    Ok(())
}

/// How a scan ended.
enum Scanned {
    /// Asked to stop.
    Stopped,
    /// No measurement for the silence bound: start the scan again.
    Silent,
    /// The link failed: open it again.
    Lost(LinkError),
}

/// Reads the scan stream until it stops, goes silent or loses its link.
fn scan(
    lidar: &mut Lidar,
    link: &mut dyn Link,
    silence: Duration,
    running: &impl Fn() -> bool,
) -> Result<Scanned, LidarError> {
    let mut buf = [0u8; 1024];
    let mut last_node = Instant::now();
    while running() {
        let n = match link.receive(&mut buf, Duration::from_millis(100)) {
            Ok(n) => n,
            Err(e) => return Ok(Scanned::Lost(e)),
        };
        let before = lidar.nodes;
        lidar.pump(&buf[..n], telemetry::clock::monotonic_ns())?;
        if lidar.nodes > before {
            last_node = Instant::now();
        } else if last_node.elapsed() >= silence {
            lidar.counters.silences += 1;
            tracing::warn!("no measurement for {silence:?}; starting the scan again");
            return Ok(Scanned::Silent);
        }
    }
    Ok(Scanned::Stopped)
}

fn reopen<L>(
    open: &impl Fn(&Path) -> Result<L, LinkError>,
    device: &Path,
    running: &impl Fn() -> bool,
) -> Option<L> {
    loop {
        std::thread::sleep(Duration::from_secs(1));
        if !running() {
            return None;
        }
        if let Ok(link) = open(device) {
            return Some(link);
        }
    }
}
