//! The store's one writing thread: decodes what zenoh queued, checks it (`fleet::admission`),
//! and writes it to PostgreSQL: the events of a turn in one statement, the telemetry rows,
//! the quarantined events and the refusals' counts. A connection or server fault drops the
//! connection (reconnect, nothing acknowledged); a row the database refuses for its data is
//! quarantined and the rest written.

use super::{Counts, Inbound};
use fleet::admission::{self, escaped, Message, Refusal, RefusalCounts};
use fleet::history::{
    EventColumns, EventRow, RollupRow, Rollups, COUNT_REFUSALS_SQL, INSERT_EVENTS_SQL,
    INSERT_EVENT_SQL, QUARANTINE_SQL, SCHEMA_SQL,
};
use fleet::journal_seen::{FleetJournals, JournalSeen, Taken};
use fleet_agent::agent::wall_ms;
use fleet_agent::schema::{decode, AckMsg, EventMsg, EventRecord, SCHEMA_VERSION};
use postgres::Transaction;
use std::collections::BTreeMap;
use std::sync::mpsc::Receiver;
use std::time::{Duration, Instant};

/// Telemetry rows kept while the database is away, at most (then the oldest go, counted).
const ROWS_KEPT: usize = 100_000;

/// Messages taken from the queue in one turn, at most.
const TURN: usize = 4097;

const INSERT_TELEMETRY_SQL: &str = "INSERT INTO telemetry (robot, at, period_s, samples, joints, \
     temp_max_c, temp_mean_c, current_max_a, above_warn_s) VALUES ($1, to_timestamp($2::float8 / \
     1000.0), $3, $4, $5, $6, $7, $8, $9) ON CONFLICT (robot, at) DO NOTHING";

const UPSERT_JOURNAL_SQL: &str =
    "INSERT INTO journals (robot, journal, stored_through, lost) VALUES ($1, $2, $3, $4) \
     ON CONFLICT (robot, journal) DO UPDATE SET \
     stored_through = GREATEST(journals.stored_through, excluded.stored_through), \
     lost = journals.lost + excluded.lost, updated_at = now()";

/// One event of a turn, new to this store.
struct Admitted<'a> {
    robot: &'a str,
    journal: u64,
    seq: u64,
    event: &'a EventRecord,
}

/// An event kept out of `events`, and why.
struct Quarantined<'a> {
    event: Admitted<'a>,
    why: Refusal,
}

pub(super) struct Writer {
    pub(super) rollups: Rollups,
    pub(super) journals: FleetJournals,
    /// Telemetry rows not yet written.
    pub(super) rows: Vec<RollupRow>,
    pub(super) refusals: RefusalCounts,
    pub(super) counts: Counts,
    pub(super) db: Option<postgres::Client>,
    pub(super) next_connect: Instant,
    pub(super) database: String,
}

/// The database refused a row for what it holds: the reason, else `None` (the connection or
/// the server failed).
fn row_refusal(e: &postgres::Error) -> Option<Refusal> {
    let db = e.as_db_error()?;
    let sqlstate = db.code().code();
    admission::is_row_fault(sqlstate).then(|| Refusal::Database {
        sqlstate: sqlstate.to_string(),
        message: db.message().to_string(),
    })
}

/// Writes `rows` with `all` in one statement; if the database refuses one of them for its
/// data, writes them again one by one with `one`, each in a savepoint, and returns the ones
/// refused with why. Returns the rows affected too.
fn all_or_each<T>(
    tx: &mut Transaction<'_>,
    rows: &[T],
    all: impl Fn(&mut Transaction<'_>, &[T]) -> Result<u64, postgres::Error>,
    one: impl Fn(&mut Transaction<'_>, &T) -> Result<u64, postgres::Error>,
) -> Result<(u64, Vec<(usize, Refusal)>), postgres::Error> {
    let mut whole = tx.savepoint("whole")?;
    match all(&mut whole, rows) {
        Ok(n) => {
            whole.commit()?;
            return Ok((n, Vec::new()));
        }
        Err(e) if row_refusal(&e).is_none() => return Err(e),
        Err(_) => whole.rollback()?,
    }
    let (mut affected, mut refused) = (0, Vec::new());
    for (i, row) in rows.iter().enumerate() {
        let mut single = tx.savepoint("single")?;
        match one(&mut single, row) {
            Ok(n) => {
                single.commit()?;
                affected += n;
            }
            Err(e) => {
                let why = row_refusal(&e).ok_or(e)?;
                single.rollback()?;
                refused.push((i, why));
            }
        }
    }
    Ok((affected, refused))
}

impl Writer {
    pub(super) fn log(&self, queue_full: u64, box_queue_full: u64) {
        let c = &self.counts;
        tracing::info!(
            events_stored = c.events_stored,
            event_copies = c.event_copies,
            events_quarantined = c.events_quarantined,
            acks_sent = c.acks_sent,
            rows_written = c.rows_written,
            rows_dropped = c.rows_dropped,
            refused = c.refused,
            undecodable = c.undecodable,
            queue_full,
            box_queue_full,
            database_failures = c.database_failures,
            reopened = c.reopened,
            boxes_stored = c.boxes_stored,
            box_bytes = c.box_bytes,
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
    pub(super) fn turn(&mut self, rx: &Receiver<Inbound>) -> Vec<(String, AckMsg)> {
        self.connect();
        let events = self.take(rx);
        self.rows.extend(self.rollups.close_idle(wall_ms()));
        if self.rows.len() > ROWS_KEPT {
            let over = self.rows.len() - ROWS_KEPT;
            self.rows.drain(..over);
            self.counts.rows_dropped += over as u64;
        }
        self.flush_rows();
        self.flush_refusals();
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

    /// Decodes and checks what came: state and layouts folded into the rollups, the events
    /// returned.
    fn take(&mut self, rx: &Receiver<Inbound>) -> Vec<(String, EventMsg)> {
        let mut events = Vec::new();
        let first = rx.recv_timeout(Duration::from_millis(100)).ok();
        let rest = std::iter::from_fn(|| rx.try_recv().ok()).take(TURN - 1);
        for item in first.into_iter().chain(rest) {
            match item {
                Inbound::Event(robot, bytes) => match decode::<EventMsg>(&bytes) {
                    Ok(m) => events.push((robot, m)),
                    Err(e) => self.undecodable("events", &robot, &e.to_string()),
                },
                Inbound::State(robot, bytes) => match decode(&bytes) {
                    Ok(m) => match admission::check_state(&robot, &m) {
                        Ok(()) => self.rows.extend(self.rollups.state(&robot, &m)),
                        Err(why) => self.refused(&robot, Message::State, &why),
                    },
                    Err(e) => self.undecodable("state", &robot, &e.to_string()),
                },
                Inbound::Layout(robot, bytes) => match decode(&bytes) {
                    Ok(m) => match admission::check_layout(&robot, &m) {
                        Ok(()) => self.rollups.layout(&robot, &m),
                        Err(why) => self.refused(&robot, Message::Layout, &why),
                    },
                    Err(e) => self.undecodable("layout", &robot, &e.to_string()),
                },
            }
        }
        events
    }

    pub(super) fn undecodable(&mut self, what: &str, robot: &str, e: &str) {
        self.counts.undecodable += 1;
        tracing::debug!("{what} of {robot}: {e}");
    }

    pub(super) fn refused(&mut self, robot: &str, message: Message, why: &Refusal) {
        self.counts.refused += 1;
        self.refusals.count(robot, message, why);
        tracing::debug!("{} of {}: refused, {why}", message.as_str(), escaped(robot));
    }

    pub(super) fn failed(&mut self, e: &postgres::Error) {
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
        // What the journals will be once this batch is in; applied only after the commit.
        let mut after: BTreeMap<(String, u64), (JournalSeen, u64)> = BTreeMap::new();
        let (mut admitted, mut quarantined) = (Vec::new(), Vec::new());
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
            let event = Admitted {
                robot,
                journal: m.journal,
                seq: m.seq,
                event: &m.event,
            };
            match admission::check_event(robot, &m.event) {
                Ok(()) => admitted.push(event),
                Err(why) => quarantined.push(Quarantined { event, why }),
            }
        }
        let Some(db) = self.db.as_mut() else {
            return Ok(Vec::new());
        };
        let mut tx = db.transaction()?;
        let (stored, refused) = all_or_each(&mut tx, &admitted, insert_events, insert_event)?;
        // Refused by the database: quarantined too, in the order they came.
        let mut refused = refused.into_iter().peekable();
        let mut kept_out = Vec::new();
        for (i, event) in admitted.into_iter().enumerate() {
            if let Some((_, why)) = refused.next_if(|(k, _)| *k == i) {
                kept_out.push(Quarantined { event, why });
            }
        }
        kept_out.append(&mut quarantined);
        let newly_quarantined = quarantine(&mut tx, &kept_out)?;
        for ((robot, journal), (seen, lost_before)) in &after {
            let lost_now = (seen.lost() - *lost_before) as i64;
            let through = seen.had_through() as i64;
            tx.execute(
                UPSERT_JOURNAL_SQL,
                &[robot, &(*journal as i64), &through, &lost_now],
            )?;
        }
        tx.commit()?;
        for q in &kept_out {
            self.counts.refused += 1;
            self.refusals.count(q.event.robot, Message::Event, &q.why);
            tracing::warn!(
                "event {} of {}'s journal {} quarantined: {}",
                q.event.seq,
                escaped(q.event.robot),
                q.event.journal,
                q.why
            );
        }
        self.counts.events_stored += stored;
        self.counts.events_quarantined += newly_quarantined;
        // Copies: known to this store, or found in the table (stored before a restart).
        self.counts.event_copies += events.len() as u64 - stored - newly_quarantined;
        Ok(self.acknowledge(after))
    }

    /// The acknowledgements of a committed batch; the journals remembered as they now are.
    fn acknowledge(
        &mut self,
        after: BTreeMap<(String, u64), (JournalSeen, u64)>,
    ) -> Vec<(String, AckMsg)> {
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
        acks
    }

    /// Writes the telemetry rows waiting (kept for the next turn if the database is away; a
    /// row it refuses for its data is dropped and counted for its robot).
    pub(super) fn flush_rows(&mut self) {
        if self.rows.is_empty() {
            return;
        }
        let Some(db) = self.db.as_mut() else {
            return;
        };
        let written = (|| {
            let mut tx = db.transaction()?;
            let insert = tx.prepare(INSERT_TELEMETRY_SQL)?;
            let one = |tx: &mut Transaction<'_>, r: &RollupRow| {
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
                )
            };
            let all = |tx: &mut Transaction<'_>, rows: &[RollupRow]| {
                rows.iter().try_fold(0, |n, r| Ok(n + one(tx, r)?))
            };
            let (_, refused) = all_or_each(&mut tx, &self.rows, all, one)?;
            tx.commit()?;
            Ok(refused)
        })();
        match written {
            Ok(refused) => {
                for (i, why) in &refused {
                    let robot = self.rows[*i].robot.clone();
                    self.refused(&robot, Message::Telemetry, why);
                }
                self.counts.rows_written += (self.rows.len() - refused.len()) as u64;
                self.rows.clear();
            }
            Err(e) => self.failed(&e),
        }
    }

    /// Adds the refusals counted since the last write to the `refusals` table.
    pub(super) fn flush_refusals(&mut self) {
        if self.refusals.is_empty() {
            return;
        }
        let Some(db) = self.db.as_mut() else {
            return;
        };
        let rows = self.refusals.rows();
        let written = (|| {
            let mut tx = db.transaction()?;
            for r in &rows {
                let count = r.count as i64;
                tx.execute(
                    COUNT_REFUSALS_SQL,
                    &[
                        &r.robot,
                        &r.message.as_str(),
                        &r.kind.as_str(),
                        &count,
                        &r.last_reason,
                    ],
                )?;
            }
            tx.commit()
        })();
        match written {
            Ok(()) => self.refusals.written(&rows),
            Err(e) => self.failed(&e),
        }
    }
}

/// The batch in one statement.
fn insert_events(tx: &mut Transaction<'_>, batch: &[Admitted<'_>]) -> Result<u64, postgres::Error> {
    if batch.is_empty() {
        return Ok(0);
    }
    let mut columns = EventColumns::default();
    for a in batch {
        columns.push(a.robot, a.journal, a.seq, a.event);
    }
    tx.execute(INSERT_EVENTS_SQL, &columns.params())
}

/// One event (when the batch was refused: finding which).
fn insert_event(tx: &mut Transaction<'_>, a: &Admitted<'_>) -> Result<u64, postgres::Error> {
    let row = EventRow::new(a.robot, a.journal, a.seq, a.event);
    tx.execute(INSERT_EVENT_SQL, &row.params())
}

/// Keeps each event in `quarantine` with its reason; returns how many were new there.
fn quarantine(
    tx: &mut Transaction<'_>,
    kept_out: &[Quarantined<'_>],
) -> Result<u64, postgres::Error> {
    let mut new = 0;
    for q in kept_out {
        let e = &q.event;
        // JSON escapes a NUL (`\u0000`), which `text` then holds.
        let event = serde_json::to_string(e.event).unwrap_or_default();
        new += tx.execute(
            QUARANTINE_SQL,
            &[
                &escaped(e.robot),
                &(e.journal as i64),
                &(e.seq as i64),
                &q.why.to_string(),
                &event,
            ],
        )?;
    }
    Ok(new)
}
