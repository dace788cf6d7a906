//! `nori router`: a zenoh router from a JSON5 configuration, for a site or a test fleet, without
//! building `zenohd` (which reads the same file: `zenohd -c router.json5`). The configuration
//! made by `deploy/zenoh/make-dev-ca.sh` listens with mutual TLS and enforces the fleet's
//! access control.
//!
//! It says how full it is (`fleet::sessions`): the sessions it accepts at start, with its file
//! descriptors raised to match; every ten seconds the sessions on its listening ports, warned
//! at 90 % and at the limit, where zenoh refuses a new robot without a word; and, with
//! `--metrics`, both as Prometheus gauges.

use anyhow::{Context, Result};
use clap::Args;
use fleet::sessions::{established_on, fullness, port_of, Fullness};
use fleet_agent::net::{descriptors_for, max_sessions};
use nix::sys::resource::{getrlimit, setrlimit, Resource};
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Options of `nori router`.
#[derive(Args, Debug)]
pub struct RouterArgs {
    /// zenoh JSON5 configuration (mode "router").
    #[arg(long)]
    pub config: PathBuf,
    /// Serve `nori_router_sessions` and `nori_router_max_sessions` on this HTTP address's
    /// `/metrics` (e.g. 127.0.0.1:9748).
    #[arg(long)]
    pub metrics: Option<String>,
    /// Stop after this many seconds.
    #[arg(long)]
    pub run_for: Option<f64>,
}

/// zenoh's own default, when the file sets none.
const ZENOH_DEFAULT_MAX_SESSIONS: usize = 1_000;

/// Routes until Ctrl-C (or `--run-for`).
pub fn run(args: &RouterArgs) -> Result<()> {
    telemetry::process::init_logging();
    let stop = telemetry::process::stop_flag()?;
    let config = fleet_agent::zenoh::Config::from_file(&args.config)
        .map_err(|e| anyhow::anyhow!("{}: {e}", args.config.display()))?;
    let limit = max_sessions(&config).unwrap_or(ZENOH_DEFAULT_MAX_SESSIONS);
    let ports = listening_ports(&config);
    raise_descriptors(limit);
    let session = fleet_agent::net::open_file(&args.config)
        .with_context(|| format!("starting the router from {}", args.config.display()))?;
    tracing::info!(config = %args.config.display(), zid = %session.zid(), max_sessions = limit, ?ports, "routing");
    let sessions = Arc::new(AtomicUsize::new(0));
    if let Some(address) = &args.metrics {
        serve_metrics(address, sessions.clone(), limit)?;
    }
    let started = Instant::now();
    let mut next_watch = Instant::now();
    while !stop.load(Ordering::Relaxed)
        && args
            .run_for
            .is_none_or(|s| started.elapsed().as_secs_f64() < s)
    {
        if Instant::now() >= next_watch {
            next_watch += Duration::from_secs(10);
            let now = count_sessions(&ports);
            sessions.store(now, Ordering::Relaxed);
            match fullness(now, limit) {
                Fullness::Room => tracing::debug!(sessions = now, max_sessions = limit, "router"),
                Fullness::Near => tracing::warn!(sessions = now, max_sessions = limit, "the router is near its session limit: raise transport/unicast/max_sessions (docs/fleet-sizing.md)"),
                Fullness::Full => tracing::error!(sessions = now, max_sessions = limit, "the router is full: new robots are refused (transport/unicast/max_sessions, docs/fleet-sizing.md)"),
            }
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    Ok(())
}

fn listening_ports(config: &fleet_agent::zenoh::Config) -> Vec<u16> {
    let endpoints: Vec<String> = config
        .get_json("listen/endpoints")
        .ok()
        .and_then(|j| serde_json::from_str(&j).ok())
        .unwrap_or_default();
    endpoints.iter().filter_map(|e| port_of(e)).collect()
}

fn count_sessions(ports: &[u16]) -> usize {
    ["/proc/net/tcp", "/proc/net/tcp6"]
        .iter()
        .filter_map(|p| std::fs::read_to_string(p).ok())
        .map(|table| established_on(&table, ports))
        .sum()
}

/// Raises the soft limit on open files to what `max_sessions` needs (up to the hard limit),
/// and says so when the hard limit is short: past it, sessions fail for want of a descriptor.
fn raise_descriptors(max_sessions: usize) {
    let needed = descriptors_for(max_sessions);
    match getrlimit(Resource::RLIMIT_NOFILE) {
        Ok((soft, hard)) if soft < needed => {
            let raised = needed.min(hard);
            if let Err(e) = setrlimit(Resource::RLIMIT_NOFILE, raised, hard) {
                tracing::warn!("cannot raise the open-file limit from {soft} ({e})");
            } else if raised < needed {
                tracing::warn!("{max_sessions} sessions need {needed} open files; the hard limit is {hard}: raise LimitNOFILE");
            }
        }
        Ok(_) => {}
        Err(e) => tracing::warn!("cannot read the open-file limit ({e})"),
    }
}

/// Serves the two gauges on `address`'s `/metrics`, on a thread of its own.
fn serve_metrics(address: &str, sessions: Arc<AtomicUsize>, limit: usize) -> Result<()> {
    let server = tiny_http::Server::http(address)
        .map_err(|e| anyhow::anyhow!("--metrics {address}: {e}"))?;
    std::thread::spawn(move || {
        for request in server.incoming_requests() {
            let body = format!(
                "# HELP nori_router_sessions Sessions established on the router's listening ports.\n\
                 # TYPE nori_router_sessions gauge\n\
                 nori_router_sessions {}\n\
                 # HELP nori_router_max_sessions Sessions the router accepts (transport/unicast/max_sessions).\n\
                 # TYPE nori_router_max_sessions gauge\n\
                 nori_router_max_sessions {limit}\n",
                sessions.load(Ordering::Relaxed)
            );
            let _ = request.respond(tiny_http::Response::from_string(body));
        }
    });
    Ok(())
}
