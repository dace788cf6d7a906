//! The store's black boxes (`fleet::boxes`): each chunk in a transaction of its own, its box's
//! row locked, the bytes appended only at the offset held; a box held whole is checked against
//! its digest and read for what froze it and what led to it. The acknowledgement goes after the
//! commit: nothing acknowledged is lost.

use super::writer::Writer;
use fleet::admission::{Message, Refusal};
use fleet::boxes::{check_chunk, plan, within_quota, Held, Plan, ABANDONED_AFTER};
use fleet_agent::schema::{decode, BoxAckMsg, BoxChunkMsg, SCHEMA_VERSION};
use sha2::{Digest, Sha256};
use std::sync::mpsc::Receiver;

/// Chunks taken in one turn, at most.
const TURN: usize = 64;

/// What became of a chunk.
struct Taken {
    /// The answer: what the store holds of the box now, or that it refuses it.
    ack: BoxAckMsg,
    /// Why it was refused, or a refusal met on the way (a box whose bytes failed their digest).
    refused: Option<Refusal>,
    /// Bytes appended.
    appended: u64,
    /// The box became whole and checked.
    completed: bool,
}

/// The answer to chunk `c`: the store holds `received` bytes of its box, whole or not.
fn answer(c: &BoxChunkMsg, received: u64, complete: bool) -> BoxAckMsg {
    BoxAckMsg {
        version: SCHEMA_VERSION,
        number: c.number,
        digest: c.digest,
        received,
        complete,
        refused: false,
    }
}

/// The answer to chunk `c` the store refuses: the robot sets its box aside.
fn refusal(c: &BoxChunkMsg) -> BoxAckMsg {
    BoxAckMsg {
        refused: true,
        ..answer(c, 0, false)
    }
}

impl Writer {
    /// Takes the chunks queued (robot, bytes); returns the answers to send.
    pub(super) fn store_boxes(
        &mut self,
        rx: &Receiver<(String, Vec<u8>)>,
    ) -> Vec<(String, BoxAckMsg)> {
        let mut acks = Vec::new();
        if self.db.is_none() {
            // Left queued (bounded; what does not fit is dropped and sent again by the robot).
            return acks;
        }
        for (robot, bytes) in rx.try_iter().take(TURN) {
            let chunk = match decode::<BoxChunkMsg>(&bytes) {
                Ok(c) => c,
                Err(e) => {
                    self.undecodable("blackbox/chunk", &robot, &e.to_string());
                    continue;
                }
            };
            if let Err(why) = check_chunk(&robot, &chunk) {
                self.refused(&robot, Message::BoxChunk, &why);
                acks.push((robot, refusal(&chunk)));
                continue;
            }
            let Some(db) = self.db.as_mut() else {
                break;
            };
            match take_chunk(db, &robot, &chunk) {
                Ok(t) => {
                    if let Some(why) = &t.refused {
                        self.refused(&robot, Message::BoxChunk, why);
                    }
                    self.counts.box_bytes += t.appended;
                    self.counts.boxes_stored += u64::from(t.completed);
                    if t.completed {
                        tracing::info!(
                            robot,
                            name = chunk.name,
                            size = chunk.size,
                            "a black box stored"
                        );
                    }
                    acks.push((robot, t.ack));
                }
                Err(e) => {
                    // Not acknowledged: the robot sends it again.
                    self.failed(&e);
                    break;
                }
            }
        }
        acks
    }
}

/// What the store holds of the box `c` names, its row locked for the transaction.
fn held(
    tx: &mut postgres::Transaction<'_>,
    robot: &str,
    c: &BoxChunkMsg,
) -> Result<Option<Held>, postgres::Error> {
    let row = tx.query_opt(
        "SELECT number, name, size, received, complete FROM boxes WHERE robot = $1 AND digest = $2 FOR UPDATE",
        &[&robot, &&c.digest[..]],
    )?;
    Ok(row.map(|r| Held {
        number: r.get::<_, i64>(0) as u64,
        name: r.get(1),
        size: r.get::<_, i64>(2) as u64,
        received: r.get::<_, i64>(3) as u64,
        complete: r.get(4),
    }))
}

/// Takes one checked chunk in a transaction of its own.
fn take_chunk(
    db: &mut postgres::Client,
    robot: &str,
    c: &BoxChunkMsg,
) -> Result<Taken, postgres::Error> {
    let mut tx = db.transaction()?;
    let digest = &c.digest[..];
    let refused = |why| Taken {
        ack: refusal(c),
        refused: Some(why),
        appended: 0,
        completed: false,
    };
    let Plan {
        open,
        append,
        held: mut h,
    } = match plan(held(&mut tx, robot, c)?, c) {
        Ok(p) => p,
        Err(why) => return Ok(refused(why)),
    };
    if open {
        // This robot's abandoned boxes first: they no longer count against its bound.
        tx.execute(
            &format!(
                "DELETE FROM box_chunks c USING boxes b WHERE b.robot = $1 AND c.robot = b.robot \
                 AND c.digest = b.digest AND NOT b.complete AND b.touched_at < now() - interval '{ABANDONED_AFTER}'"
            ),
            &[&robot],
        )?;
        tx.execute(
            &format!(
                "DELETE FROM boxes WHERE robot = $1 AND NOT complete \
                 AND touched_at < now() - interval '{ABANDONED_AFTER}'"
            ),
            &[&robot],
        )?;
        let open_bytes: i64 = tx
            .query_one(
                "SELECT coalesce(sum(size - received), 0)::bigint FROM boxes \
                 WHERE robot = $1 AND NOT complete",
                &[&robot],
            )?
            .get(0);
        if let Err(why) = within_quota(open_bytes as u64, c.size) {
            // The abandoned boxes stay dropped: a robot refused now is not refused for ever.
            tx.commit()?;
            return Ok(refused(why));
        }
        tx.execute(
            "INSERT INTO boxes (robot, digest, number, name, size) VALUES ($1, $2, $3, $4, $5)",
            &[
                &robot,
                &digest,
                &(c.number as i64),
                &c.name,
                &(c.size as i64),
            ],
        )?;
    }
    let mut taken = Taken {
        ack: answer(c, 0, false),
        refused: None,
        appended: 0,
        completed: false,
    };
    if append {
        let len = c.data.len() as u64;
        tx.execute(
            "INSERT INTO box_chunks (robot, digest, at_byte, data) VALUES ($1, $2, $3, $4)",
            &[&robot, &digest, &(c.offset as i64), &c.data],
        )?;
        tx.execute(
            "UPDATE boxes SET received = received + $3, touched_at = now() \
             WHERE robot = $1 AND digest = $2",
            &[&robot, &digest, &(len as i64)],
        )?;
        h.received += len;
        taken.appended = len;
        if h.received == h.size {
            match complete(&mut tx, robot, c)? {
                Whole::Described => h.complete = true,
                Whole::Undescribed(why) => {
                    h.complete = true;
                    taken.refused = Some(why);
                }
                Whole::Damaged => {
                    tx.commit()?;
                    return Ok(refused(Refusal::BoxDigest));
                }
            }
            taken.completed = h.complete;
        }
    }
    tx.commit()?;
    taken.ack = answer(c, h.received, h.complete);
    Ok(taken)
}

/// A box just held whole.
enum Whole {
    /// Checked, and what froze it and what led to it kept.
    Described,
    /// Checked, kept; what it says could not be (the refusal).
    Undescribed(Refusal),
    /// Its bytes fail its digest: dropped with its row (a robot that hashes it again and
    /// sends it anew begins a new box).
    Damaged,
}

/// The box held whole: checked against its digest and read for what froze it.
fn complete(
    tx: &mut postgres::Transaction<'_>,
    robot: &str,
    c: &BoxChunkMsg,
) -> Result<Whole, postgres::Error> {
    let digest = &c.digest[..];
    let mut bytes = Vec::with_capacity(usize::try_from(c.size).unwrap_or(0));
    for r in tx.query(
        "SELECT data FROM box_chunks WHERE robot = $1 AND digest = $2 ORDER BY at_byte",
        &[&robot, &digest],
    )? {
        bytes.extend_from_slice(r.get::<_, &[u8]>(0));
    }
    let sum: [u8; 32] = Sha256::digest(&bytes).into();
    if sum != c.digest || bytes.len() as u64 != c.size {
        tx.execute(
            "DELETE FROM box_chunks WHERE robot = $1 AND digest = $2",
            &[&robot, &digest],
        )?;
        tx.execute(
            "DELETE FROM boxes WHERE robot = $1 AND digest = $2",
            &[&robot, &digest],
        )?;
        return Ok(Whole::Damaged);
    }
    // A box is the robot's bytes: a reader that panics on one must not take the store down.
    let lead = std::panic::catch_unwind(|| blackbox::lead_up::lead_up(&bytes)).unwrap_or_default();
    let trigger = lead.trigger.as_ref();
    let trigger_ns: Vec<i64> = lead
        .triggers
        .iter()
        .map(|t| t.timestamp_ns as i64)
        .collect();
    let mut sp = tx.savepoint("described")?;
    let described = sp.execute(
        "UPDATE boxes SET complete = true, completed_at = now(), trigger = $3, joint = $4, \
         event_ns = $5, trigger_ns = $6, lead_up = $7::text::jsonb WHERE robot = $1 AND digest = $2",
        &[
            &robot,
            &digest,
            &trigger.map(|t| t.kind.clone()),
            &lead.joint,
            &trigger.map(|t| t.timestamp_ns as i64),
            &trigger_ns,
            &serde_json::to_string(&lead).unwrap_or_default(),
        ],
    );
    match described {
        Ok(_) => {
            sp.commit()?;
            Ok(Whole::Described)
        }
        Err(e) => {
            // What the box says cannot be kept (jsonb refuses a NUL, a value beyond its
            // limits...): the box is kept whole all the same, undescribed, and the refusal
            // counted. Only a lost connection fails the chunk (not answered, sent again).
            let why = server_refusal(&e).ok_or(e)?;
            sp.rollback()?;
            tx.execute(
                "UPDATE boxes SET complete = true, completed_at = now() WHERE robot = $1 AND digest = $2",
                &[&robot, &digest],
            )?;
            Ok(Whole::Undescribed(why))
        }
    }
}

/// The server refused a statement, whatever its class: its refusal (`None`: not the server's
/// answer, the connection failed).
fn server_refusal(e: &postgres::Error) -> Option<Refusal> {
    let db = e.as_db_error()?;
    Some(Refusal::Database {
        sqlstate: db.code().code().to_string(),
        message: db.message().to_string(),
    })
}
