//! What every process of the stack does first: log to stderr (level from `RUST_LOG`, default
//! info), and turn SIGINT/SIGTERM into a flag its loop checks, so it can stop cleanly (torque
//! off, in the driver's case) instead of dying.

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// How a robot process ends, by fault class (the numbers of `sysexits.h`), so that systemd can
/// tell a fault a restart cannot fix (`RestartPreventExitStatus=78` in the units) from one it
/// may (a device not there yet, a crash).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum Exit {
    /// Stopped as asked (SIGINT/SIGTERM, `--run-for`).
    Clean = 0,
    /// Any other failure: restarted.
    Failure = 1,
    /// A command line that does not parse (clap's own code).
    Usage = 2,
    /// The state plane or a device could not be opened (`EX_UNAVAILABLE`): restarted, it may
    /// be there next time.
    Unavailable = 69,
    /// A file the process must read or write failed, e.g. the trip record (`EX_IOERR`):
    /// restarted.
    Io = 74,
    /// The configuration cannot be used: a bad file or key, an impossible value, a layout the
    /// supervisor cannot supervise (`EX_CONFIG`). Not restarted: the same configuration would
    /// fail the same way.
    Config = 78,
}

/// The class of the first error in `error`'s chain that `class` (the binary's own types) or
/// this crate (configuration, state plane, trip record) recognises; [`Exit::Failure`] when none
/// does.
pub fn fault_class(
    error: &(dyn std::error::Error + 'static),
    class: impl Fn(&(dyn std::error::Error + 'static)) -> Option<Exit>,
) -> Exit {
    let mut next = Some(error);
    while let Some(e) = next {
        if let Some(exit) = class(e) {
            return exit;
        }
        if e.is::<crate::config::ConfigError>() {
            return Exit::Config;
        }
        if e.is::<crate::plane::PlaneError>() {
            return Exit::Unavailable;
        }
        if e.is::<crate::latch::LatchError>() {
            return Exit::Io;
        }
        next = e.source();
    }
    Exit::Failure
}

/// Ends a process with `result`: an error is logged with its causes and turned into its
/// class's exit code ([`fault_class`]).
pub fn finish<E>(
    result: Result<(), E>,
    class: impl Fn(&(dyn std::error::Error + 'static)) -> Option<Exit>,
) -> std::process::ExitCode
where
    E: AsRef<dyn std::error::Error + Send + Sync + 'static>,
{
    let Err(e) = result else {
        return std::process::ExitCode::SUCCESS;
    };
    let e = e.as_ref();
    let mut line = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        line += &format!(": {c}");
        cause = c.source();
    }
    let exit = fault_class(e, class);
    eprintln!("error: {line} (exit {}, {exit:?})", exit as u8);
    std::process::ExitCode::from(exit as u8)
}

/// A sibling executable that cannot be found.
#[derive(Debug, thiserror::Error)]
pub enum SiblingError {
    /// Not installed next to the running executable.
    #[error("{name} not found next to {exe}: build all binaries first (cargo build --release --workspace --bins)")]
    NotBuilt {
        /// The executable looked for.
        name: String,
        /// The running executable.
        exe: String,
    },
    /// The running executable's path is unknown.
    #[error("locating the running executable: {0}")]
    CurrentExe(#[source] std::io::Error),
}

/// A sibling executable: installed next to the running one, as cargo builds them and as
/// `deploy/README.md` installs them.
pub fn sibling(name: &str) -> Result<PathBuf, SiblingError> {
    let exe = std::env::current_exe().map_err(SiblingError::CurrentExe)?;
    let path = exe.with_file_name(name);
    if !path.exists() {
        return Err(SiblingError::NotBuilt {
            name: name.into(),
            exe: exe.display().to_string(),
        });
    }
    Ok(path)
}

/// The options every process of the stack takes (flattened into each binary's own arguments,
/// so the five spell them once).
#[derive(Debug, Clone, clap::Args)]
pub struct ProcessArgs {
    /// Configuration file (TOML); the embedded default when absent.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// State-plane domain (iceoryx2 prefix); the processes of one robot share it.
    #[arg(long, default_value = crate::plane::DEFAULT_DOMAIN)]
    pub domain: String,
    /// Stop after this many seconds (tests and benchmarks).
    #[arg(long)]
    pub run_for: Option<f64>,
    /// Print the default configuration and exit.
    #[arg(long)]
    pub print_default_config: bool,
}

impl ProcessArgs {
    /// [`start`] with these options.
    pub fn start<C: crate::config::ProcessConfig>(&self) -> Result<Option<Started<C>>, StartError> {
        start(self.print_default_config, self.config.as_deref())
    }

    /// `--run-for` as a duration ([`run_for`]: refused unless positive and finite).
    pub fn run_for(&self) -> Result<Option<std::time::Duration>, crate::config::ConfigError> {
        run_for(self.run_for)
    }
}

/// A loop's period: [`Ticker::wait`] sleeps until the next tick of an absolute schedule (no
/// drift); after a turn that ran past its tick it returns at once and the schedule starts again
/// from there (no burst of catch-up turns).
#[derive(Debug, Clone)]
pub struct Ticker {
    period: std::time::Duration,
    next: std::time::Instant,
}

impl Ticker {
    /// Ticks every `period`, the first one `period` from now.
    pub fn new(period: std::time::Duration) -> Ticker {
        Ticker {
            period,
            next: std::time::Instant::now() + period,
        }
    }

    /// Sleeps until the next tick.
    pub fn wait(&mut self) {
        let now = std::time::Instant::now();
        if self.next > now {
            std::thread::sleep(self.next - now);
            self.next += self.period;
        } else {
            self.next = now + self.period;
        }
    }
}

/// A process that started: its configuration and its stop flag.
#[derive(Debug)]
pub struct Started<C> {
    /// The configuration (`--config`, or the embedded default).
    pub config: C,
    /// Set when SIGINT or SIGTERM arrives.
    pub shutdown: Arc<AtomicBool>,
}

/// Why a process could not start.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// Its configuration was refused.
    #[error("configuration")]
    Config(#[source] crate::config::ConfigError),
    /// Its signal handlers could not be installed.
    #[error("installing signal handlers")]
    Signals(#[source] std::io::Error),
}

/// What every process of the stack does first, once its command line is parsed: print its
/// commented default configuration and stop when asked (`None`), else log to stderr, load its
/// configuration (`config`: `--config`, or the embedded default) and turn SIGINT/SIGTERM into
/// the flag its loop checks.
pub fn start<C: crate::config::ProcessConfig>(
    print_default: bool,
    config: Option<&std::path::Path>,
) -> Result<Option<Started<C>>, StartError> {
    if print_default {
        print!("{}", C::DEFAULT_TOML);
        return Ok(None);
    }
    init_logging();
    let config = C::from_arg(config).map_err(StartError::Config)?;
    let shutdown = stop_flag().map_err(StartError::Signals)?;
    Ok(Some(Started { config, shutdown }))
}

/// A process's `--run-for` in seconds as a duration, refused (naming the option) unless
/// positive and finite.
pub fn run_for(
    seconds: Option<f64>,
) -> Result<Option<std::time::Duration>, crate::config::ConfigError> {
    match seconds {
        Some(s) if !(s.is_finite() && s > 0.0) => Err(crate::config::invalid(
            "--run-for",
            "run-for",
            format!("{s}: a positive number of seconds"),
        )),
        s => Ok(s.map(std::time::Duration::from_secs_f64)),
    }
}

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
    flag_on(&[signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM])
}

/// A flag set when SIGINT, SIGTERM or SIGHUP arrives: for a tool that must finish what it
/// started (a motor left turning) even when its terminal goes away.
pub fn stop_or_hangup_flag() -> std::io::Result<Arc<AtomicBool>> {
    use signal_hook::consts::{SIGHUP, SIGINT, SIGTERM};
    flag_on(&[SIGINT, SIGTERM, SIGHUP])
}

fn flag_on(signals: &[i32]) -> std::io::Result<Arc<AtomicBool>> {
    let stop = Arc::new(AtomicBool::new(false));
    for &signal in signals {
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

    #[test]
    fn a_ticker_keeps_its_schedule_and_does_not_catch_up_after_a_long_turn() {
        let mut t = Ticker::new(std::time::Duration::from_millis(5));
        let start = std::time::Instant::now();
        for _ in 0..4 {
            t.wait();
        }
        // Four ticks of an absolute schedule: at least 20 ms (never early).
        assert!(start.elapsed() >= std::time::Duration::from_millis(20));
        // A turn three periods long: the late tick is taken at once, and the schedule starts
        // again from there (the next one a whole period later, not three at once).
        std::thread::sleep(std::time::Duration::from_millis(15));
        t.wait();
        let resumed = std::time::Instant::now();
        t.wait();
        assert!(resumed.elapsed() >= std::time::Duration::from_millis(5));
    }

    #[test]
    fn run_for_takes_positive_seconds_and_names_the_option_otherwise() {
        assert_eq!(run_for(None).unwrap(), None);
        assert_eq!(
            run_for(Some(1.5)).unwrap(),
            Some(std::time::Duration::from_millis(1500))
        );
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(run_for(Some(bad))
                .unwrap_err()
                .to_string()
                .contains("--run-for"));
        }
    }

    #[test]
    fn a_missing_sibling_is_named() {
        let e = sibling("no-such-nori-binary").unwrap_err().to_string();
        assert!(e.contains("no-such-nori-binary not found"), "{e}");
    }

    #[test]
    fn a_fault_is_classed_by_the_first_known_error_in_its_chain() {
        #[derive(Debug, thiserror::Error)]
        #[error("outer")]
        struct Outer(#[source] crate::config::ConfigError);
        let config = Outer(crate::config::invalid("f.toml", "k", "bad"));
        assert_eq!(fault_class(&config, |_| None), Exit::Config);
        // The binary's own classes come first.
        assert_eq!(
            fault_class(&config, |e| e.is::<Outer>().then_some(Exit::Unavailable)),
            Exit::Unavailable
        );
        let io = std::io::Error::other("x");
        assert_eq!(fault_class(&io, |_| None), Exit::Failure);
        assert_eq!(Exit::Config as u8, 78);
    }
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
