//! `nori fleet`: the fleet side. Subscribes to every robot's telemetry, events, layout, camera
//! thumbnails, lidar revolutions and liveliness under `nori/**`, asks each robot's status (the
//! gate's counters, the sensors' health) every second, and serves a live dashboard (`/`,
//! `/api/fleet`, `/api/robots/<id>/preview/<camera>`, `/api/robots/<id>/scan`) and Prometheus
//! metrics (`/metrics`) over HTTP.
//! What it knows is `fleet::collector::Collector`; this file only wires zenoh and HTTP.

use anyhow::{anyhow, Context, Result};
use clap::Args;
use fleet::collector::Collector;
use fleet_agent::agent::wall_ms;
use fleet_agent::keys::robots_matching;
use fleet_agent::zenoh::pubsub::Subscriber;
use fleet_agent::zenoh::query::{ConsolidationMode, QueryTarget};
use fleet_agent::zenoh::sample::{Sample, SampleKind};
use fleet_agent::zenoh::Session;
use fleet_agent::zenoh::Wait;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

const DASHBOARD: &str = include_str!("dashboard.html");

/// Where `nori fleet` listens when told nothing: the robots' agents connect here by default.
pub const DEFAULT_LISTEN: &str = "tcp/127.0.0.1:7448";

/// How a fleet-side process (`nori fleet`, `nori policy-server`) joins zenoh.
#[derive(Args, Debug)]
pub struct FleetSideArgs {
    /// zenoh endpoints to listen on (default, where robots' agents connect: tcp/127.0.0.1:7448
    /// for `nori fleet`, tcp/127.0.0.1:7447 for `nori policy-server`; none when it connects
    /// somewhere itself).
    #[arg(long)]
    pub listen: Vec<String>,
    /// zenoh endpoints to connect to (a router, in a real fleet).
    #[arg(long)]
    pub connect: Vec<String>,
    /// A zenoh JSON5 configuration (the process's TLS identity, made by
    /// deploy/zenoh/make-dev-ca.sh); it is then a client of the router its file names.
    #[arg(long, conflicts_with_all = ["listen", "connect"])]
    pub zenoh_config: Option<PathBuf>,
}

impl FleetSideArgs {
    /// Opens the session, listening on `default_listen` when told nothing.
    pub fn open(
        &self,
        default_listen: &str,
    ) -> Result<fleet_agent::zenoh::Session, fleet_agent::net::NetError> {
        fleet_agent::net::open_fleet_side(
            self.zenoh_config.as_deref(),
            &self.listen,
            &self.connect,
            default_listen,
        )
    }
}

/// Options of `nori fleet` (listens on tcp/127.0.0.1:7448 by default).
#[derive(Args, Debug)]
pub struct FleetArgs {
    #[command(flatten)]
    pub zenoh: FleetSideArgs,
    /// HTTP address of the dashboard and /metrics.
    #[arg(long, default_value = "127.0.0.1:9747")]
    pub http: String,
    /// How often each robot's status (action counters) is asked for, ms.
    #[arg(long, default_value_t = 1000)]
    pub status_every_ms: u64,
    /// Seconds of temperature and current history plotted per robot.
    #[arg(long, default_value_t = 60)]
    pub history_s: u64,
    /// Stop after this many seconds.
    #[arg(long)]
    pub run_for: Option<f64>,
    /// The robots served, as key-expression chunks of their ids (repeatable): `*` for all,
    /// `$*0` for ids ending in 0, `lab-$*` for ids starting with lab-. A fleet too big for one
    /// process runs several, each with its share.
    #[arg(long = "robots", default_value = "*")]
    pub robots: Vec<String>,
    /// The history's database (`nori fleet store --database`): the dashboard then serves the
    /// fleet's report on `/report?days=N` (7 by default).
    #[arg(long)]
    pub database: Option<String>,
}

/// The collector, shared by zenoh's callbacks and the HTTP thread. A panic while it was held
/// leaves it usable (it holds plain data), so a poisoned lock is taken over, not propagated.
fn lock(c: &Mutex<Collector>) -> MutexGuard<'_, Collector> {
    c.lock().unwrap_or_else(|p| p.into_inner())
}

/// Runs the collector and the dashboard until Ctrl-C (or `--run-for`).
pub fn run(args: &FleetArgs) -> Result<()> {
    telemetry::process::init_logging();
    // Made before anything is opened: a bad pattern is a configuration error.
    let FleetKeys {
        state,
        alive,
        status,
        leaves,
    } = FleetKeys::new(&args.robots)?;
    let stop = telemetry::process::stop_flag()?;
    let session = args
        .zenoh
        .open(DEFAULT_LISTEN)
        .context("opening the fleet collector's zenoh session")?;

    // Two samples a second for the plots.
    let collector = Arc::new(Mutex::new(Collector::new(
        (args.history_s * 2) as usize,
        500,
    )));
    let _subscribers = subscribe_messages(&session, &collector, state, leaves)?;
    let _alive = watch_liveliness(&session, &collector, alive)?;

    let server = tiny_http::Server::http(&args.http)
        .map_err(|e| anyhow!("serving HTTP on {}: {e}", args.http))?;
    tracing::info!(http = %args.http, zid = %session.zid(),
        "fleet dashboard on http://{}/ , metrics on /metrics", args.http);
    let http = {
        let (c, stop) = (collector.clone(), stop.clone());
        std::thread::Builder::new()
            .name("http".into())
            .spawn({
                let database = args.database.clone();
                move || serve_http(&server, &c, database.as_deref(), &stop)
            })
            .context("starting the HTTP thread")?
    };

    let started = Instant::now();
    let mut next_status = Instant::now();
    while !stop.load(Ordering::Relaxed)
        && args
            .run_for
            .is_none_or(|s| started.elapsed().as_secs_f64() < s)
    {
        if Instant::now() >= next_status {
            let every = Duration::from_millis(args.status_every_ms.max(100));
            next_status += every;
            ask_status(&session, &status, &collector, every);
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    stop.store(true, Ordering::Relaxed);
    let _ = http.join();
    Ok(())
}

/// How a message of one leaf is taken into the collector.
type Ingest = fn(&mut Collector, &str, &[u8], u64) -> Result<(), fleet::collector::IngestError>;

/// The key expressions `nori fleet` listens to and asks, for the robots it serves.
struct FleetKeys {
    state: Vec<String>,
    alive: Vec<String>,
    status: Vec<String>,
    /// The other leaves (layout, events, thumbnails, scans), each with how it is taken.
    leaves: Vec<(String, Ingest)>,
}

impl FleetKeys {
    /// The keys of the robots `patterns` name.
    fn new(patterns: &[String]) -> Result<FleetKeys> {
        let keys = |leaf: &str| robots_matching(patterns, leaf);
        let (state, alive, status) = (keys("state")?, keys("alive")?, keys("status")?);
        let mut leaves = Vec::new();
        for (leaf, ingest) in [
            ("layout", Collector::layout as Ingest),
            ("events", Collector::event),
            ("preview", Collector::preview),
            ("scan", Collector::scan),
        ] {
            for key in keys(leaf)? {
                leaves.push((key, ingest));
            }
        }
        Ok(FleetKeys {
            state,
            alive,
            status,
            leaves,
        })
    }
}

/// zenoh's error, which is no `std::error::Error` anyhow can take.
pub(crate) fn zenoh_error(e: fleet_agent::zenoh::Error) -> anyhow::Error {
    anyhow!("{e}")
}

/// Subscribes the collector to the robots' telemetry and other leaves; the subscriptions
/// last as long as what is returned is kept.
fn subscribe_messages(
    session: &Session,
    collector: &Arc<Mutex<Collector>>,
    state: Vec<String>,
    leaves: Vec<(String, Ingest)>,
) -> Result<Vec<Subscriber<()>>> {
    let mut subscribers = Vec::new();
    // Telemetry, the bulk, is decoded before the collector is locked.
    for key in state {
        let c = collector.clone();
        subscribers.push(
            session
                .declare_subscriber(key)
                .callback(move |s: Sample| {
                    let key = s.key_expr().as_str();
                    let msg = fleet::collector::decode_state(key, &s.payload().to_bytes());
                    if let Err(e) = lock(&c).decoded_state(key, msg, wall_ms()) {
                        tracing::debug!("{e}");
                    }
                })
                .wait()
                .map_err(zenoh_error)?,
        );
    }
    for (key, ingest) in leaves {
        let c = collector.clone();
        subscribers.push(
            session
                .declare_subscriber(key)
                .callback(move |s: Sample| {
                    let bytes = s.payload().to_bytes();
                    if let Err(e) = ingest(&mut lock(&c), s.key_expr().as_str(), &bytes, wall_ms())
                    {
                        tracing::debug!("{e}");
                    }
                })
                .wait()
                .map_err(zenoh_error)?,
        );
    }
    Ok(subscribers)
}

/// Follows the robots' liveliness tokens (those already there too); it lasts as long as what
/// is returned is kept.
fn watch_liveliness(
    session: &Session,
    collector: &Arc<Mutex<Collector>>,
    alive: Vec<String>,
) -> Result<Vec<Subscriber<()>>> {
    let mut watching = Vec::new();
    for key in alive {
        let c = collector.clone();
        watching.push(
            session
                .liveliness()
                .declare_subscriber(key)
                .history(true)
                .callback(move |s: Sample| {
                    let alive = s.kind() == SampleKind::Put;
                    let _ = lock(&c).alive(s.key_expr().as_str(), alive, wall_ms());
                })
                .wait()
                .map_err(zenoh_error)?,
        );
    }
    Ok(watching)
}

/// Asks every robot's status; the replies reach the collector within `timeout`.
fn ask_status(
    session: &Session,
    status_keys: &[String],
    collector: &Arc<Mutex<Collector>>,
    timeout: Duration,
) {
    for key in status_keys {
        let c = collector.clone();
        // Every robot answers for itself: all queryables, no consolidation.
        let asked = session
            .get(key)
            .target(QueryTarget::All)
            .consolidation(ConsolidationMode::None)
            .timeout(timeout)
            .callback(move |reply| {
                if let Ok(s) = reply.result() {
                    let bytes = s.payload().to_bytes();
                    let _ = lock(&c).status(s.key_expr().as_str(), &bytes, wall_ms());
                }
            })
            .wait();
        if let Err(e) = asked {
            tracing::warn!("asking the robots' status: {e}");
        }
    }
}

fn serve_http(
    server: &tiny_http::Server,
    collector: &Mutex<Collector>,
    database: Option<&str>,
    stop: &AtomicBool,
) {
    while !stop.load(Ordering::Relaxed) {
        let Ok(Some(request)) = server.recv_timeout(Duration::from_millis(100)) else {
            continue;
        };
        let (path, query) = request.url().split_once('?').unwrap_or((request.url(), ""));
        let (path, query) = (path.to_string(), query.to_string());
        let mut attachment = None;
        let (body, kind, code) = if path == "/report" {
            report_page(database, &query)
        } else if let Some(rest) = path.strip_prefix("/boxes/") {
            let (answer, name) = box_download(database, rest);
            attachment = name;
            answer
        } else {
            page(&path, &lock(collector))
        };
        let mut response = tiny_http::Response::from_data(body).with_status_code(code);
        if let Some(name) = attachment {
            // The name is the store's, checked when the box came (`fleet::boxes`): no quotes.
            let disposition = format!("Content-Disposition: attachment; filename=\"{name}\"");
            if let Ok(h) = disposition.parse::<tiny_http::Header>() {
                response = response.with_header(h);
            }
        }
        // Every answer is the present: a browser must ask again, not show a cached thumbnail.
        for header in [
            format!("Content-Type: {kind}"),
            "Cache-Control: no-store".into(),
        ] {
            if let Ok(h) = header.parse::<tiny_http::Header>() {
                response = response.with_header(h);
            }
        }
        if let Err(e) = request.respond(response) {
            tracing::debug!("HTTP client went away: {e}");
        }
    }
}

/// The fleet's report over the last `days=N` days (7 by default) from the history's database.
fn report_page(database: Option<&str>, query: &str) -> (Vec<u8>, &'static str, u16) {
    const TEXT: &str = "text/plain; charset=utf-8";
    let Some(database) = database else {
        return (
            b"no history: start nori fleet with --database (the one nori fleet store writes)\n"
                .to_vec(),
            TEXT,
            404,
        );
    };
    let days = query
        .split('&')
        .find_map(|kv| kv.strip_prefix("days="))
        .map_or(Ok(7.0), str::parse::<f64>);
    match days {
        Ok(days) => match crate::report_command::html(database, days) {
            Ok(page) => (page.into_bytes(), "text/html; charset=utf-8", 200),
            Err(e) => (
                format!("the report failed: {e:#}\n").into_bytes(),
                TEXT,
                503,
            ),
        },
        Err(e) => (format!("days: {e}\n").into_bytes(), TEXT, 400),
    }
}

/// A black box from the store, `ROBOT/DIGEST.mcap` (its SHA-256 in hex), whole: the answer,
/// and the box's file name.
fn box_download(
    database: Option<&str>,
    rest: &str,
) -> ((Vec<u8>, &'static str, u16), Option<String>) {
    const TEXT: &str = "text/plain; charset=utf-8";
    let fail = |code, why: String| ((format!("{why}\n").into_bytes(), TEXT, code), None);
    let Some(database) = database else {
        return fail(404, "no history: start nori fleet with --database".into());
    };
    let Some((robot, digest)) = rest
        .strip_suffix(".mcap")
        .and_then(|r| r.split_once('/'))
        .filter(|(_, d)| d.len() == 64 && d.bytes().all(|b| b.is_ascii_hexdigit()))
    else {
        return fail(400, "a box is /boxes/ROBOT/SHA256.mcap".into());
    };
    match crate::report_command::box_bytes(database, robot, digest) {
        Ok(Some((name, bytes))) => ((bytes, "application/octet-stream", 200), Some(name)),
        Ok(None) => fail(
            404,
            format!("robot {robot} has no whole box {digest} in the store"),
        ),
        Err(e) => fail(503, format!("reading the box failed: {e:#}")),
    }
}

/// The answer to a GET of `path`: body, content type, status code.
fn page(path: &str, collector: &Collector) -> (Vec<u8>, &'static str, u16) {
    const TEXT: &str = "text/plain; charset=utf-8";
    let json = |v: serde_json::Value| (v.to_string().into_bytes(), "application/json", 200);
    let missing = |what: String| (format!("{what}\n").into_bytes(), TEXT, 404);
    let parts: Vec<&str> = path.trim_start_matches('/').split('/').collect();
    match parts.as_slice() {
        [""] | ["index.html"] => (
            DASHBOARD.as_bytes().to_vec(),
            "text/html; charset=utf-8",
            200,
        ),
        ["api", "fleet"] => json(collector.snapshot(wall_ms())),
        ["metrics"] => (
            collector.metrics().into_bytes(),
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
            200,
        ),
        ["api", "robots", robot, "preview", camera] => {
            match collector.preview_jpeg(robot, camera) {
                Some(jpeg) => (jpeg.to_vec(), "image/jpeg", 200),
                None => missing(format!("no thumbnail of camera {camera} of robot {robot}")),
            }
        }
        ["api", "robots", robot, "scan"] => match collector.scan_json(robot, wall_ms()) {
            Some(scan) => json(scan),
            None => missing(format!("no lidar scan of robot {robot}")),
        },
        _ => missing(format!("no page {path}")),
    }
}
