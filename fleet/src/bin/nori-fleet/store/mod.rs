//! `nori fleet store`: the fleet's history in PostgreSQL. Subscribes to every robot's events,
//! telemetry and layout under `nori/**`; writes each journaled event once (a unique index on
//! robot, journal and number) and one telemetry row per robot and period
//! (`fleet::history`); and, once a batch is committed, acknowledges each robot's journal
//! through the last event it has them all to (`nori/<robot>/acks`), so the robot stops sending
//! them. Nothing is acknowledged before it is committed: a database that is down, or a store
//! killed mid-batch, leaves the events on the robots, which send them again.
//!
//! One robot's garbage holds up nobody (`fleet::admission`): a message PostgreSQL cannot hold
//! is refused and counted in `refusals`, an event is quarantined with its reason and
//! acknowledged.
//!
//! zenoh's callbacks only queue the bytes (bounded; what does not fit is counted and, for
//! events, sent again by the robot); one thread decodes and writes:
//!
//! * [`writer`]: that thread's turn: decode, check, write, acknowledge.
//! * [`boxes`]: the black boxes robots send, chunk by chunk (`fleet::boxes`), on a queue of
//!   their own (a chunk is up to 1 MiB: 64 of them queued at most).

mod boxes;
mod writer;

use crate::dashboard::FleetSideArgs;
use anyhow::{anyhow, Context, Result};
use clap::Args;
use fleet::admission::RefusalCounts;
use fleet::history::{RollupConfig, Rollups};
use fleet::journal_seen::FleetJournals;
use fleet::silence::{Heard, Silence};
use fleet_agent::agent::wall_ms;
use fleet_agent::keys::{robot_key, robot_of, robots_matching};
use fleet_agent::schema::encode;
use fleet_agent::zenoh::sample::Sample;
use fleet_agent::zenoh::Wait;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, SyncSender, TrySendError};
use std::sync::Arc;
use std::time::{Duration, Instant};
use writer::Writer;

/// Where `nori fleet store` listens when told nothing (the robots' agents connect here by
/// default).
pub const DEFAULT_LISTEN: &str = "tcp/127.0.0.1:7449";

/// Options of `nori fleet store`.
#[derive(Args, Debug)]
pub struct StoreArgs {
    #[command(flatten)]
    pub zenoh: FleetSideArgs,
    /// The database, as a PostgreSQL connection string (`host=127.0.0.1 port=5432 user=nori
    /// dbname=fleet`, or a `postgresql://` URL).
    #[arg(long)]
    pub database: String,
    /// Telemetry is rolled up into one row per robot per this many seconds.
    #[arg(long, default_value_t = 60.0)]
    pub rollup_s: f64,
    /// The warning temperatures whose time above is kept per joint, °C (the supervisor's
    /// `thermal.warn-c`).
    #[arg(long, value_delimiter = ',', default_value = "50,54,57")]
    pub warn_c: Vec<f32>,
    /// The robots served, as key-expression chunks of their ids (repeatable): `*` for all,
    /// `$*0` for ids ending in 0, `lab-$*` for ids starting with lab-. A fleet too big for one
    /// process runs several, each with its share.
    #[arg(long = "robots", default_value = "*")]
    pub robots: Vec<String>,
    /// Messages queued between zenoh and the writer, at most.
    #[arg(long, default_value_t = 65_536)]
    pub queue: usize,
    /// Having heard no robot for this many seconds (they send state every 100 ms), the store
    /// opens its zenoh session again (`fleet::silence`).
    #[arg(long, default_value_t = 30.0)]
    pub deaf_after_s: f64,
    /// Stop after this many seconds.
    #[arg(long)]
    pub run_for: Option<f64>,
}

/// What zenoh's callbacks hand the writer.
enum Inbound {
    Event(String, Vec<u8>),
    State(String, Vec<u8>),
    Layout(String, Vec<u8>),
}

/// The store's counts, logged every ten seconds and at the end.
#[derive(Debug, Default)]
struct Counts {
    events_stored: u64,
    event_copies: u64,
    /// Events kept in `quarantine` (`fleet::admission`).
    events_quarantined: u64,
    /// Messages refused (and quarantined events), every robot's.
    refused: u64,
    acks_sent: u64,
    rows_written: u64,
    rows_dropped: u64,
    undecodable: u64,
    database_failures: u64,
    /// Times the zenoh session was opened again, deaf.
    reopened: u64,
    /// Black boxes held whole and checked.
    boxes_stored: u64,
    /// Bytes of black boxes appended.
    box_bytes: u64,
}

/// Black-box chunks queued between zenoh and the writer, at most.
const BOX_QUEUE: usize = 64;

/// The largest chunk message taken: the largest chunk and room for its other fields.
const MAX_CHUNK_MESSAGE: usize = fleet_agent::config::MAX_BOX_CHUNK_BYTES as usize + 4096;

/// What zenoh's callbacks feed: the writer's queue, and counts.
struct Taps {
    tx: SyncSender<Inbound>,
    /// Messages dropped, the queue full.
    queue_full: Arc<AtomicU64>,
    /// Black-box chunks: robot, bytes.
    boxes: SyncSender<(String, Vec<u8>)>,
    /// Chunks dropped, their queue full or too large to be one (the robot sends them again).
    box_queue_full: Arc<AtomicU64>,
    /// Messages heard, any robot's.
    heard: Arc<AtomicU64>,
}

/// The store's zenoh session and its subscriptions (opened again when deaf).
struct Link {
    session: fleet_agent::zenoh::Session,
    _subscribers: Vec<fleet_agent::zenoh::pubsub::Subscriber<()>>,
}

impl Link {
    fn open(args: &StoreArgs, keys: &[(&'static str, String)], taps: &Taps) -> Result<Link> {
        let session = args
            .zenoh
            .open(DEFAULT_LISTEN)
            .context("opening the fleet store's zenoh session")?;
        let mut subscribers = Vec::new();
        for (leaf, key) in keys {
            if *leaf == "blackbox/chunk" {
                subscribers.push(box_subscriber(&session, key, taps)?);
                continue;
            }
            let (tx, full, heard, leaf) = (
                taps.tx.clone(),
                taps.queue_full.clone(),
                taps.heard.clone(),
                *leaf,
            );
            let subscriber = session
                .declare_subscriber(key.clone())
                .callback(move |s: Sample| {
                    let Some(robot) = robot_of(s.key_expr().as_str()) else {
                        return;
                    };
                    heard.fetch_add(1, Ordering::Relaxed);
                    let (robot, bytes) = (robot.to_string(), s.payload().to_bytes().into_owned());
                    let item = match leaf {
                        "events" => Inbound::Event(robot, bytes),
                        "state" => Inbound::State(robot, bytes),
                        _ => Inbound::Layout(robot, bytes),
                    };
                    if let Err(TrySendError::Full(_)) = tx.try_send(item) {
                        full.fetch_add(1, Ordering::Relaxed);
                    }
                })
                .wait()
                .map_err(|e| anyhow!("{e}"))?;
            subscribers.push(subscriber);
        }
        tracing::info!(zid = %session.zid(), "fleet store: events and telemetry into the database");
        Ok(Link {
            session,
            _subscribers: subscribers,
        })
    }
}

/// The subscriber of the robots' black-box chunks, into their own queue.
fn box_subscriber(
    session: &fleet_agent::zenoh::Session,
    key: &str,
    taps: &Taps,
) -> Result<fleet_agent::zenoh::pubsub::Subscriber<()>> {
    let (tx, full, heard) = (
        taps.boxes.clone(),
        taps.box_queue_full.clone(),
        taps.heard.clone(),
    );
    session
        .declare_subscriber(key.to_string())
        .callback(move |s: Sample| {
            let Some(robot) = robot_of(s.key_expr().as_str()) else {
                return;
            };
            heard.fetch_add(1, Ordering::Relaxed);
            // Larger than any chunk the store takes: dropped before it is copied, so the
            // queue holds 64 chunks of 1 MiB at most (the robot is answered nothing and sends
            // it again; counted with the queue's drops).
            if s.payload().len() > MAX_CHUNK_MESSAGE {
                full.fetch_add(1, Ordering::Relaxed);
                return;
            }
            let item = (robot.to_string(), s.payload().to_bytes().into_owned());
            if let Err(TrySendError::Full(_)) = tx.try_send(item) {
                full.fetch_add(1, Ordering::Relaxed);
            }
        })
        .wait()
        .map_err(|e| anyhow!("{e}"))
}

/// Runs the store until Ctrl-C (or `--run-for`).
pub fn run(args: &StoreArgs) -> Result<()> {
    telemetry::process::init_logging();
    if !(args.rollup_s >= 1.0 && args.rollup_s <= 86_400.0) {
        return Err(anyhow!(
            "--rollup-s {}: use 1 to 86400 seconds",
            args.rollup_s
        ));
    }
    if args.warn_c.iter().any(|t| !t.is_finite()) || args.warn_c.len() > 8 {
        return Err(anyhow!(
            "--warn-c {:?}: up to 8 finite temperatures",
            args.warn_c
        ));
    }
    if !(args.deaf_after_s >= 1.0 && args.deaf_after_s <= 86_400.0) {
        return Err(anyhow!(
            "--deaf-after-s {}: use 1 to 86400 seconds",
            args.deaf_after_s
        ));
    }
    // Made before anything is opened: a bad pattern is a configuration error.
    let mut keys = Vec::new();
    for leaf in ["events", "state", "layout", "blackbox/chunk"] {
        for key in robots_matching(&args.robots, leaf)? {
            keys.push((leaf, key));
        }
    }
    let stop = telemetry::process::stop_flag()?;
    let (tx, rx) = sync_channel::<Inbound>(args.queue.max(1));
    let (boxes, box_rx) = sync_channel(BOX_QUEUE);
    let taps = Taps {
        tx,
        queue_full: Arc::new(AtomicU64::new(0)),
        boxes,
        box_queue_full: Arc::new(AtomicU64::new(0)),
        heard: Arc::new(AtomicU64::new(0)),
    };
    let mut link = Some(Link::open(args, &keys, &taps)?);
    let (queue_full, box_queue_full) = (taps.queue_full.clone(), taps.box_queue_full.clone());
    let full = || {
        (
            queue_full.load(Ordering::Relaxed),
            box_queue_full.load(Ordering::Relaxed),
        )
    };
    let mut silence = Silence::new((args.deaf_after_s * 1000.0) as u64, wall_ms());
    let mut writer = Writer {
        rollups: Rollups::new(RollupConfig {
            period_ms: (args.rollup_s * 1000.0) as u64,
            warn_c: args.warn_c.clone(),
            max_gap_ms: 1_000,
        }),
        journals: FleetJournals::default(),
        rows: Vec::new(),
        refusals: RefusalCounts::default(),
        counts: Counts::default(),
        db: None,
        next_connect: Instant::now(),
        database: args.database.clone(),
    };
    let started = Instant::now();
    let mut next_log = Instant::now() + Duration::from_secs(10);
    while !stop.load(Ordering::Relaxed)
        && args
            .run_for
            .is_none_or(|s| started.elapsed().as_secs_f64() < s)
    {
        let acks = writer.turn(&rx);
        let box_acks = writer.store_boxes(&box_rx);
        if let Some(link) = &link {
            let journals = acks.iter().map(|(r, a)| (r, "acks", encode(a)));
            let boxes = box_acks.iter().map(|(r, a)| (r, "blackbox/ack", encode(a)));
            for (robot, leaf, ack) in journals.chain(boxes) {
                match link.session.put(robot_key(robot, leaf), ack).wait() {
                    Ok(()) => writer.counts.acks_sent += 1,
                    Err(e) => tracing::warn!("acknowledging {robot}: {e}"),
                }
            }
        }
        if silence.observe(taps.heard.load(Ordering::Relaxed), wall_ms()) == Heard::Nothing {
            // Heard no robot for the bound: the session's routes may be stale. Nothing is
            // lost meanwhile: unacknowledged events stay on the robots.
            tracing::warn!(
                "fleet store: heard no robot for {} s; opening the zenoh session again",
                args.deaf_after_s
            );
            writer.counts.reopened += 1;
            // The old one closed first: a peer store listens on the same endpoint again.
            drop(link.take());
            link = Link::open(args, &keys, &taps)
                .map_err(|e| tracing::warn!("fleet store: reopening: {e:#}"))
                .ok();
        }
        if Instant::now() >= next_log {
            next_log += Duration::from_secs(10);
            let (q, b) = full();
            writer.log(q, b);
        }
    }
    writer.rows.extend(writer.rollups.close_all());
    writer.flush_rows();
    writer.flush_refusals();
    let (q, b) = full();
    writer.log(q, b);
    Ok(())
}
