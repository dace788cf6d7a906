//! `nori fleet store`: the fleet's history in PostgreSQL. Subscribes to every robot's events,
//! telemetry and layout under `nori/**`; writes each journaled event once (a unique index on
//! robot, journal and number) and one telemetry row per robot and period
//! (`fleet::history`); and, once a batch is committed, acknowledges each robot's journal
//! through the last event it has them all to (`nori/<robot>/acks`), so the robot stops sending
//! them. Nothing is acknowledged before it is committed: a database that is down, or a store
//! killed mid-batch, leaves the events on the robots, which send them again.
//!
//! zenoh's callbacks only queue the bytes (bounded; what does not fit is counted and, for
//! events, sent again by the robot); one thread decodes and writes.

use crate::dashboard::FleetSideArgs;
use anyhow::{anyhow, Context, Result};
use clap::Args;
use fleet::history::{RollupConfig, RollupRow, Rollups, SCHEMA_SQL};
use fleet::journal_seen::{FleetJournals, JournalSeen, Taken};
use fleet_agent::agent::wall_ms;
use fleet_agent::keys::{robot_key, robot_of, robots_matching};
use fleet_agent::schema::{decode, encode, AckMsg, EventMsg, LayoutMsg, StateMsg, SCHEMA_VERSION};
use fleet_agent::zenoh::sample::Sample;
use fleet_agent::zenoh::Wait;
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, TrySendError};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Where `nori fleet store` listens when told nothing (the robots' agents connect here by
/// default).
pub const DEFAULT_LISTEN: &str = "tcp/127.0.0.1:7449";

/// Telemetry rows kept while the database is away, at most (then the oldest go, counted).
const ROWS_KEPT: usize = 100_000;

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
    acks_sent: u64,
    rows_written: u64,
    rows_dropped: u64,
    undecodable: u64,
    database_failures: u64,
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
    // Made before anything is opened: a bad pattern is a configuration error.
    let mut keys = Vec::new();
    for leaf in ["events", "state", "layout"] {
        for key in robots_matching(&args.robots, leaf)? {
            keys.push((leaf, key));
        }
    }
    let stop = telemetry::process::stop_flag()?;
    let session = args
        .zenoh
        .open(DEFAULT_LISTEN)
        .context("opening the fleet store's zenoh session")?;
    let z = |e: fleet_agent::zenoh::Error| anyhow!("{e}");
    let (tx, rx) = sync_channel::<Inbound>(args.queue.max(1));
    let queue_full = Arc::new(AtomicU64::new(0));
    let mut subscribers = Vec::new();
    for (leaf, key) in keys {
        let (tx, full) = (tx.clone(), queue_full.clone());
        subscribers.push(
            session
                .declare_subscriber(key)
                .callback(move |s: Sample| {
                    let Some(robot) = robot_of(s.key_expr().as_str()) else {
                        return;
                    };
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
                .map_err(z)?,
        );
    }
    drop(tx);
    tracing::info!(zid = %session.zid(), "fleet store: events and telemetry into the database");
    let mut writer = Writer {
        rollups: Rollups::new(RollupConfig {
            period_ms: (args.rollup_s * 1000.0) as u64,
            warn_c: args.warn_c.clone(),
            max_gap_ms: 1_000,
        }),
        journals: FleetJournals::default(),
        rows: Vec::new(),
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
        for (robot, ack) in acks {
            match session.put(robot_key(&robot, "acks"), encode(&ack)).wait() {
                Ok(()) => writer.counts.acks_sent += 1,
                Err(e) => tracing::warn!("acknowledging {robot}: {e}"),
            }
        }
        if Instant::now() >= next_log {
            next_log += Duration::from_secs(10);
            writer.log(queue_full.load(Ordering::Relaxed));
        }
    }
    writer.rows.extend(writer.rollups.close_all());
    writer.flush_rows();
    writer.log(queue_full.load(Ordering::Relaxed));
    Ok(())
}

struct Writer {
    rollups: Rollups,
    journals: FleetJournals,
    /// Telemetry rows not yet written.
    rows: Vec<RollupRow>,
    counts: Counts,
    db: Option<postgres::Client>,
    next_connect: Instant,
    database: String,
}

impl Writer {
    fn log(&self, queue_full: u64) {
        let c = &self.counts;
        tracing::info!(
            events_stored = c.events_stored,
            event_copies = c.event_copies,
            acks_sent = c.acks_sent,
            rows_written = c.rows_written,
            rows_dropped = c.rows_dropped,
            undecodable = c.undecodable,
            queue_full,
            database_failures = c.database_failures,
            connected = self.db.is_some(),
            "fleet store"
        );
    }

    /// Connects when not connected (at most once a second), creating the tables and reading
    /// how far each journal is stored.
    fn connect(&mut self) {
        if self.db.is_some() || Instant::now() < self.next_connect {
            return;
        }
        self.next_connect = Instant::now() + Duration::from_secs(1);
        let opened =
            postgres::Client::connect(&self.database, postgres::NoTls).and_then(|mut c| {
                c.batch_execute(SCHEMA_SQL)?;
                let rows = c.query("SELECT robot, journal, stored_through FROM journals", &[])?;
                Ok((c, rows))
            });
        match opened {
            Ok((client, rows)) => {
                for r in &rows {
                    let (robot, journal, through): (String, i64, i64) =
                        (r.get(0), r.get(1), r.get(2));
                    self.journals.restore(
                        &robot,
                        journal as u64,
                        JournalSeen::through(through as u64),
                    );
                }
                tracing::info!(journals = rows.len(), "fleet store: database connected");
                self.db = Some(client);
            }
            Err(e) => {
                self.counts.database_failures += 1;
                tracing::warn!("fleet store: database unavailable ({e}); events stay on the robots until it is back");
            }
        }
    }

    /// One turn: takes what came (waiting up to 100 ms for the first), writes it, and returns
    /// the acknowledgements to send.
    fn turn(&mut self, rx: &Receiver<Inbound>) -> Vec<(String, AckMsg)> {
        self.connect();
        let mut events: Vec<(String, EventMsg)> = Vec::new();
        let first = rx.recv_timeout(Duration::from_millis(100)).ok();
        for item in first
            .into_iter()
            .chain(std::iter::from_fn(|| rx.try_recv().ok()).take(4096))
        {
            match item {
                Inbound::Event(robot, bytes) => match decode::<EventMsg>(&bytes) {
                    Ok(m) => events.push((robot, m)),
                    Err(e) => self.undecodable("events", &robot, &e.to_string()),
                },
                Inbound::State(robot, bytes) => match decode::<StateMsg>(&bytes) {
                    Ok(m) => self.rows.extend(self.rollups.state(&robot, &m)),
                    Err(e) => self.undecodable("state", &robot, &e.to_string()),
                },
                Inbound::Layout(robot, bytes) => match decode::<LayoutMsg>(&bytes) {
                    Ok(m) => self.rollups.layout(&robot, &m),
                    Err(e) => self.undecodable("layout", &robot, &e.to_string()),
                },
            }
        }
        self.rows.extend(self.rollups.close_idle(wall_ms()));
        if self.rows.len() > ROWS_KEPT {
            let over = self.rows.len() - ROWS_KEPT;
            self.rows.drain(..over);
            self.counts.rows_dropped += over as u64;
        }
        self.flush_rows();
        if events.is_empty() || self.db.is_none() {
            // Without the database nothing is acknowledged: the robots send them again.
            return Vec::new();
        }
        match self.store_events(&events) {
            Ok(acks) => acks,
            Err(e) => {
                self.failed(&e);
                Vec::new()
            }
        }
    }

    fn undecodable(&mut self, what: &str, robot: &str, e: &str) {
        self.counts.undecodable += 1;
        tracing::debug!("{what} of {robot}: {e}");
    }

    fn failed(&mut self, e: &postgres::Error) {
        self.counts.database_failures += 1;
        tracing::warn!("fleet store: database write failed ({e}); reconnecting");
        self.db = None;
    }

    /// Writes the events in one transaction with how far each journal is now stored; once
    /// committed, the journals are acknowledged (every one that sent something, so a lost
    /// acknowledgement is made good by the next copy).
    fn store_events(
        &mut self,
        events: &[(String, EventMsg)],
    ) -> Result<Vec<(String, AckMsg)>, postgres::Error> {
        let Some(db) = self.db.as_mut() else {
            return Ok(Vec::new());
        };
        // What the journals will be once this batch is in; applied only after the commit.
        let mut after: BTreeMap<(String, u64), (JournalSeen, u64)> = BTreeMap::new();
        let mut tx = db.transaction()?;
        let insert = tx.prepare(fleet::history::INSERT_EVENT_SQL)?;
        let mut stored = 0;
        for (robot, m) in events {
            let key = (robot.clone(), m.journal);
            let (seen, _) = after.entry(key).or_insert_with(|| {
                let s = self.journals.of(robot, m.journal).clone();
                let lost = s.lost();
                (s, lost)
            });
            if seen.take(m.seq, m.held_from) == Taken::Copy {
                continue;
            }
            let row = fleet::history::EventRow::new(robot, m.journal, m.seq, &m.event);
            stored += tx.execute(&insert, &row.params())?;
        }
        let upsert = tx.prepare(
            "INSERT INTO journals (robot, journal, stored_through, lost) VALUES ($1, $2, $3, $4) \
             ON CONFLICT (robot, journal) DO UPDATE SET \
             stored_through = GREATEST(journals.stored_through, excluded.stored_through), \
             lost = journals.lost + excluded.lost, updated_at = now()",
        )?;
        for ((robot, journal), (seen, lost_before)) in &after {
            let lost_now = (seen.lost() - *lost_before) as i64;
            tx.execute(
                &upsert,
                &[
                    robot,
                    &(*journal as i64),
                    &(seen.had_through() as i64),
                    &lost_now,
                ],
            )?;
        }
        tx.commit()?;
        self.counts.events_stored += stored;
        // Copies: known to this store, or found in the table (stored before a restart).
        self.counts.event_copies += events.len() as u64 - stored;
        let mut acks = Vec::with_capacity(after.len());
        for ((robot, journal), (seen, _)) in after {
            acks.push((
                robot.clone(),
                AckMsg {
                    version: SCHEMA_VERSION,
                    journal,
                    stored_through: seen.had_through(),
                },
            ));
            self.journals.restore(&robot, journal, seen);
        }
        Ok(acks)
    }

    /// Writes the telemetry rows waiting (kept for the next turn if the database is away).
    fn flush_rows(&mut self) {
        if self.rows.is_empty() {
            return;
        }
        let Some(db) = self.db.as_mut() else {
            return;
        };
        let written = (|| {
            let mut tx = db.transaction()?;
            let insert = tx.prepare(
                "INSERT INTO telemetry (robot, at, period_s, samples, joints, temp_max_c, temp_mean_c, current_max_a, above_warn_s) \
                 VALUES ($1, to_timestamp($2::float8 / 1000.0), $3, $4, $5, $6, $7, $8, $9) ON CONFLICT (robot, at) DO NOTHING",
            )?;
            for r in &self.rows {
                tx.execute(
                    &insert,
                    &[
                        &r.robot,
                        &(r.start_ms as f64),
                        &r.period_s,
                        &(r.samples as i32),
                        &r.joints,
                        &r.temp_max_c,
                        &r.temp_mean_c,
                        &r.current_max_a,
                        &r.above_warn_s,
                    ],
                )?;
            }
            tx.commit()
        })();
        match written {
            Ok(()) => {
                self.counts.rows_written += self.rows.len() as u64;
                self.rows.clear();
            }
            Err(e) => self.failed(&e),
        }
    }
}
