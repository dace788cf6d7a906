//! `nori bench fleet-store`: how fast the history store (`nori fleet store`, its own process)
//! takes a fleet's backlog of events (robots back from an outage, each sending what its
//! journal held, at most 256 unacknowledged as the agents do, again from the oldest when 2 s
//! pass without an acknowledgement, the wait doubling to 30 s), against the same number of rows
//! inserted straight into the same database with the store's own statement in transactions of
//! the store's size: the database's own cost, measured in the same run, before and after (the
//! table grows as the run goes).

use anyhow::{bail, Context, Result};
use clap::Args;
use fleet::history::{EventColumns, EventRow, INSERT_EVENTS_SQL, INSERT_EVENT_SQL, SCHEMA_SQL};
use fleet_agent::keys::{robot_key, robot_of};
use fleet_agent::schema::{decode, encode, AckMsg, EventMsg, EventRecord, SCHEMA_VERSION};
use fleet_agent::zenoh::qos::CongestionControl;
use fleet_agent::zenoh::Wait;
use std::collections::HashMap;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Options of `nori bench fleet-store`.
#[derive(Args, Debug)]
pub struct FleetStoreArgs {
    /// The database, a scratch one: the bench adds its rows (`deploy/fleet-db/scratch-postgres.sh
    /// start DIR PORT` makes one and prints its connection string).
    #[arg(long)]
    database: String,
    /// Robots sending their backlog at once.
    #[arg(long, default_value_t = 200)]
    robots: usize,
    /// Events in each robot's backlog.
    #[arg(long, default_value_t = 500)]
    events: u64,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

/// Events the agents keep unacknowledged at most (`[journal] window`).
const WINDOW: u64 = 256;
/// Rows per transaction in the baseline: what the store takes from its queue in one turn.
const BATCH: usize = 4097;

fn record(seq: u64) -> EventRecord {
    EventRecord {
        timestamp_ns: 1_000_000_000 + seq * 1_000_000,
        wall_ms: 1_790_000_000_000 + seq,
        origin_seq: seq,
        kind: "ThermalWarning".into(),
        joint: "left_shoulder_pitch".into(),
        detail: String::new(),
        bus: 0,
        level: 1,
        value: 52.5,
    }
}

/// How the baseline writes a transaction's rows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Statement {
    /// One `INSERT` a row (`INSERT_EVENT_SQL`, the store's until #38).
    PerRow,
    /// One statement a transaction (`INSERT_EVENTS_SQL`, the store's now).
    Batch,
}

/// The baseline: `rows` events of `robots` robots straight into the database, `BATCH` to a
/// transaction. Returns the seconds it took.
fn raw_inserts(
    db: &mut postgres::Client,
    run: &str,
    robots: usize,
    events: u64,
    statement: Statement,
) -> Result<f64> {
    let started = Instant::now();
    let rows: Vec<(String, u64)> = (0..robots)
        .flat_map(|r| (1..=events).map(move |seq| (format!("{run}-{r}"), seq)))
        .collect();
    for batch in rows.chunks(BATCH) {
        let mut tx = db.transaction()?;
        match statement {
            Statement::PerRow => {
                let insert = tx.prepare(INSERT_EVENT_SQL)?;
                for (robot, seq) in batch {
                    let e = record(*seq);
                    tx.execute(&insert, &EventRow::new(robot, 1, *seq, &e).params())?;
                }
            }
            Statement::Batch => {
                let mut columns = EventColumns::default();
                for (robot, seq) in batch {
                    columns.push(robot, 1, *seq, &record(*seq));
                }
                tx.execute(INSERT_EVENTS_SQL, &columns.params())?;
            }
        }
        tx.commit()?;
    }
    Ok(started.elapsed().as_secs_f64())
}

/// One robot's backlog as its agent sends it.
struct Backlog {
    id: String,
    next: u64,
    acked: u64,
    last_progress: Instant,
    resend_after: Duration,
}

/// The store's run: the backlogs published on `session` until every event is acknowledged.
/// Returns the seconds it took and how many events were sent again.
fn through_store(
    session: &fleet_agent::zenoh::Session,
    run: &str,
    robots: usize,
    events: u64,
) -> Result<(f64, u64)> {
    let acks = session
        .declare_subscriber(format!("nori/{run}-store-$*/acks"))
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut publishers = Vec::new();
    for r in 0..robots {
        publishers.push(
            session
                .declare_publisher(robot_key(&format!("{run}-store-{r}"), "events"))
                .congestion_control(CongestionControl::Block)
                .wait()
                .map_err(|e| anyhow::anyhow!("{e}"))?,
        );
    }
    // The store subscribes when it is up.
    let up = Instant::now();
    while !publishers[0]
        .matching_status()
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?
        .matching()
    {
        if up.elapsed() > Duration::from_secs(20) {
            bail!("the store did not subscribe within 20 s");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let mut backlogs: Vec<Backlog> = (0..robots)
        .map(|r| Backlog {
            id: format!("{run}-store-{r}"),
            next: 1,
            acked: 0,
            last_progress: Instant::now(),
            resend_after: Duration::from_secs(2),
        })
        .collect();
    let index: HashMap<String, usize> = backlogs
        .iter()
        .enumerate()
        .map(|(i, b)| (b.id.clone(), i))
        .collect();
    let started = Instant::now();
    let mut resent = 0;
    while backlogs.iter().any(|b| b.acked < events) {
        if started.elapsed() > Duration::from_secs(600) {
            bail!("the backlog was not stored within 600 s");
        }
        for (b, publisher) in backlogs.iter_mut().zip(&publishers) {
            if b.acked < events && b.last_progress.elapsed() > b.resend_after {
                resent += b.next - 1 - b.acked;
                b.next = b.acked + 1;
                b.last_progress = Instant::now();
                b.resend_after = (b.resend_after * 2).min(Duration::from_secs(30));
            }
            while b.next <= events && b.next <= b.acked + WINDOW {
                let msg = EventMsg {
                    version: SCHEMA_VERSION,
                    journal: 1,
                    seq: b.next,
                    held_from: b.acked + 1,
                    event: record(b.next),
                };
                publisher
                    .put(encode(&msg))
                    .wait()
                    .map_err(|e| anyhow::anyhow!("{e}"))?;
                b.next += 1;
            }
        }
        while let Ok(Some(sample)) = acks.recv_timeout(Duration::from_millis(1)) {
            let Some(&i) = robot_of(sample.key_expr().as_str()).and_then(|id| index.get(id)) else {
                continue;
            };
            if let Ok(a) = decode::<AckMsg>(&sample.payload().to_bytes()) {
                let b = &mut backlogs[i];
                if a.stored_through > b.acked {
                    b.acked = a.stored_through;
                    b.last_progress = Instant::now();
                    b.resend_after = Duration::from_secs(2);
                }
            }
        }
    }
    Ok((started.elapsed().as_secs_f64(), resent))
}

/// The database alone, the same rows with each statement: seconds, before and after the
/// store's run (the table grows).
#[derive(Debug, Default)]
struct Alone {
    per_row: [f64; 2],
    batch: [f64; 2],
}

impl Alone {
    fn measure(
        &mut self,
        db: &mut postgres::Client,
        run: &str,
        when: usize,
        args: &FleetStoreArgs,
    ) -> Result<()> {
        let tag = ["before", "after"][when];
        self.per_row[when] = raw_inserts(
            db,
            &format!("{run}-{tag}-row"),
            args.robots,
            args.events,
            Statement::PerRow,
        )?;
        self.batch[when] = raw_inserts(
            db,
            &format!("{run}-{tag}-batch"),
            args.robots,
            args.events,
            Statement::Batch,
        )?;
        Ok(())
    }
}

/// The store's run, in its own process: seconds, events sent again, the store's CPU seconds.
fn store_run(args: &FleetStoreArgs, run: &str) -> Result<(f64, u64, f64)> {
    let endpoint = crate::fleet::free_endpoint()?;
    let mut store = Command::new(stack::sibling("nori-fleet")?)
        .args(["store", "--database", &args.database, "--listen", &endpoint])
        .args(["--robots", &format!("{run}-store-$*")])
        .stderr(Stdio::null())
        .spawn()
        .context("starting nori fleet store")?;
    let result = (|| {
        // A peer connecting: it opens at once and links up when the store listens.
        let session = bench::zenoh_session(vec![], vec![endpoint.clone()], "peer")?;
        let cpu = || bench::cpu_seconds(store.id()).unwrap_or(0.0);
        let cpu_before = cpu();
        let (store_s, resent) = through_store(&session, run, args.robots, args.events)?;
        Ok::<_, anyhow::Error>((store_s, resent, cpu() - cpu_before))
    })();
    let _ = store.kill();
    let _ = store.wait();
    result
}

pub fn run(args: &FleetStoreArgs) -> Result<()> {
    if args.robots == 0 || args.events == 0 {
        bail!("--robots and --events: at least 1");
    }
    let mut db = postgres::Client::connect(&args.database, postgres::NoTls)
        .with_context(|| format!("connecting to {}", args.database))?;
    db.batch_execute(SCHEMA_SQL)?;
    let run = format!(
        "bench{}t{}",
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)?
            .as_secs()
    );
    let total = args.robots as u64 * args.events;
    let mut alone = Alone::default();
    alone.measure(&mut db, &run, 0, args)?;
    let (store_s, resent, store_cpu_s) = store_run(args, &run)?;
    alone.measure(&mut db, &run, 1, args)?;
    let stored: i64 = db
        .query_one(
            "SELECT count(*) FROM events WHERE robot LIKE $1 || '-store-%'",
            &[&run],
        )?
        .get(0);
    let rate = |s: [f64; 2]| 2.0 * total as f64 / (s[0] + s[1]);
    let (row_rate, batch_rate, store_rate) = (
        rate(alone.per_row),
        rate(alone.batch),
        total as f64 / store_s,
    );
    // A fleet of 1 000 robots whose journals all filled (1 MiB each, the records ~100 B).
    let backlog_1000 = 1_000.0 * (1024.0 * 1024.0 / 100.0);
    if args.json {
        println!(
            "{}",
            serde_json::json!({
                "robots": args.robots, "events": total, "stored": stored, "resent": resent,
                "per_row_s": alone.per_row, "per_row_rows_per_s": row_rate,
                "batch_s": alone.batch, "batch_rows_per_s": batch_rate,
                "store_s": store_s, "store_events_per_s": store_rate,
                "store_cpu_s": store_cpu_s,
                "store_over_per_row": store_rate / row_rate, "store_over_batch": store_rate / batch_rate,
            })
        );
    } else {
        let [row_b, row_a] = alone.per_row;
        let [batch_b, batch_a] = alone.batch;
        println!(
            "fleet store: {} robots × {} events = {total}\n  \
             database alone, {BATCH} to a transaction (before, after the store's run):\n    \
             one INSERT a row:     {row_b:.2} s, {row_a:.2} s: {row_rate:.0} rows/s\n    \
             one statement (unnest): {batch_b:.2} s, {batch_a:.2} s: {batch_rate:.0} rows/s\n  \
             through nori fleet store (zenoh, 256 in flight per robot, acknowledged after commit): \
             {store_s:.2} s, {store_rate:.0} events/s, {store_cpu_s:.2} s of the store's CPU; \
             {stored} stored, {resent} sent again\n  \
             store's rate / one INSERT a row: {:.2}×; / one statement: {:.2}×\n  \
             a 1 000-robot fleet's full journals ({:.1} M events) would take {:.1} min to store",
            args.robots,
            args.events,
            store_rate / row_rate,
            store_rate / batch_rate,
            backlog_1000 / 1e6,
            backlog_1000 / store_rate / 60.0
        );
    }
    if stored != total as i64 {
        bail!("{stored} of {total} events stored");
    }
    Ok(())
}
