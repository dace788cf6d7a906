//! The event journal's delivery to the fleet, at least once. Pure: records and acknowledgements
//! in, messages out, time passed in.
//!
//! Every event the agent journals is held here until the fleet acknowledges it stored
//! ([`AckMsg`]: "everything through seq N"). Held events go out in order, at most `window` of
//! them unacknowledged at a time; when the oldest one sent goes `resend-after` without an
//! acknowledgement, everything unacknowledged is sent again from the oldest (the fleet
//! de-duplicates by journal and number), and the wait doubles, up to [`MAX_RESEND_AFTER_NS`],
//! until an acknowledgement comes. An outage, a fleet store restarting or an agent killed and
//! restarted (which reloads what the journal holds past the last acknowledgement) lose nothing
//! the journal kept.
//!
//! What is held is bounded like the journal itself: past `bound-bytes` the oldest held events
//! are dropped and counted lost, and every message says where the held events start
//! (`held_from`), so the fleet knows a gap below it will never be filled.
//!
//! It also remembers the journal's recent past, so a restarted agent does not journal twice
//! the supervisor events the state plane replays to a new subscriber (its history), nor a
//! supervisor's or driver's start it journaled already.

use crate::journal::Record;
use crate::schema::{AckMsg, EventMsg, EventRecord, SCHEMA_VERSION};
use std::collections::VecDeque;
use thiserror::Error;

/// The longest wait before sending unacknowledged events again (the backoff's ceiling).
pub const MAX_RESEND_AFTER_NS: u64 = 30_000_000_000;
/// Supervisor events remembered to recognise the state plane's replay (its history is 16).
const RECENT: usize = 64;

/// The agent's `SupervisorStarted` event kind (`value`: the supervisor's process id).
pub const SUPERVISOR_STARTED: &str = "SupervisorStarted";
/// The agent's `DriverStarted` event kind (`value`: the driver's process id).
pub const DRIVER_STARTED: &str = "DriverStarted";
/// The agent's own start (`detail`: the `nori-robot` package version it runs, empty for a build
/// from source; `value`: bytes of a torn journal tail cut at open).
pub const AGENT_STARTED: &str = "AgentStarted";
/// The calibration the robot runs, journaled at the agent's start (`detail`:
/// [`crate::installed::calibration_detail`]; `value`: the joints it calibrates).
pub const CALIBRATION_IN_FORCE: &str = "CalibrationInForce";
/// Action chunks refused for one reason since the last such event (`detail`: the reason,
/// `value`: how many).
pub const ACTIONS_REFUSED: &str = "ActionsRefused";

/// How delivery is paced and bounded.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DeliveryConfig {
    /// Held event bytes at most (the journal's bound).
    pub bound_bytes: usize,
    /// The first wait for an acknowledgement before sending again, ns.
    pub resend_after_ns: u64,
    /// Events sent and not yet acknowledged, at most.
    pub window: usize,
}

/// An acknowledgement that cannot be used.
#[derive(Debug, Error, PartialEq, Eq)]
pub enum AckRefused {
    /// It names another journal (an old one, another robot's).
    #[error("acknowledgement of journal {got:016x}, this robot's is {ours:016x}")]
    OtherJournal {
        /// The journal it names.
        got: u64,
        /// This robot's journal.
        ours: u64,
    },
    /// It acknowledges events never journaled.
    #[error("acknowledgement through event {through}, the journal's newest is {newest}")]
    Beyond {
        /// What it acknowledges.
        through: u64,
        /// The newest journaled.
        newest: u64,
    },
}

#[derive(Debug)]
struct Held {
    seq: u64,
    record: EventRecord,
    /// Bytes it counts against the bound (its journal record's).
    bytes: usize,
    sent_ns: u64,
    sendings: u32,
}

/// What is held for the fleet, and how far it has acknowledged.
#[derive(Debug)]
pub struct Delivery {
    journal: u64,
    config: DeliveryConfig,
    held: VecDeque<Held>,
    held_bytes: usize,
    /// `held[..sent]` went out and await their acknowledgement.
    sent: usize,
    newest_seq: u64,
    stored_through: u64,
    resend_after_ns: u64,
    recent: VecDeque<(u64, u64)>,
    supervisor_pid: Option<u32>,
    driver_pid: Option<u32>,
    lost: u64,
    resent: u64,
    first_sendings: u64,
    acks_refused: u64,
}

impl Delivery {
    /// Delivery of journal `journal`, which keeps `kept` (oldest first) and was acknowledged
    /// through `stored_through`: the kept records after it are held, to be sent again. Returns
    /// it and how many kept records could not be read (another build's format), counted lost
    /// when they were still unacknowledged.
    pub fn new(
        journal: u64,
        kept: &[Record],
        stored_through: u64,
        config: DeliveryConfig,
    ) -> (Delivery, usize) {
        let mut d = Delivery {
            journal,
            config,
            held: VecDeque::new(),
            held_bytes: 0,
            sent: 0,
            newest_seq: stored_through,
            stored_through,
            resend_after_ns: config.resend_after_ns,
            recent: VecDeque::new(),
            supervisor_pid: None,
            driver_pid: None,
            lost: 0,
            resent: 0,
            first_sendings: 0,
            acks_refused: 0,
        };
        let mut unreadable = 0;
        for r in kept {
            match postcard::from_bytes::<EventRecord>(&r.payload) {
                Ok(record) => {
                    d.remember(&record);
                    if r.seq > stored_through {
                        d.hold(r.seq, record, r.payload.len());
                    }
                }
                Err(_) => {
                    unreadable += 1;
                    d.lost += u64::from(r.seq > stored_through);
                }
            }
            d.newest_seq = d.newest_seq.max(r.seq);
        }
        (d, unreadable)
    }

    /// The journal's bytes of `record` (what [`Delivery::journaled`] expects to be kept).
    pub fn journal_bytes(record: &EventRecord) -> Vec<u8> {
        postcard::to_allocvec(record).unwrap_or_default()
    }

    /// The journal kept `record` (`bytes` long) as `seq`: it is held until acknowledged.
    pub fn journaled(&mut self, seq: u64, record: EventRecord, bytes: usize) {
        self.remember(&record);
        self.newest_seq = self.newest_seq.max(seq);
        self.hold(seq, record, bytes);
    }

    /// A supervisor event already journaled (the state plane replays recent events to a new
    /// subscriber): its number and time match one the journal holds.
    pub fn seen(&self, origin_seq: u64, timestamp_ns: u64) -> bool {
        self.recent.contains(&(origin_seq, timestamp_ns))
    }

    /// The process id of the newest `SupervisorStarted` ([`SUPERVISOR_STARTED`]) or
    /// `DriverStarted` journaled.
    pub fn started_pid(&self, kind: &str) -> Option<u32> {
        match kind {
            SUPERVISOR_STARTED => self.supervisor_pid,
            DRIVER_STARTED => self.driver_pid,
            _ => None,
        }
    }

    fn remember(&mut self, r: &EventRecord) {
        match r.kind.as_str() {
            SUPERVISOR_STARTED => self.supervisor_pid = Some(r.value as u32),
            DRIVER_STARTED => self.driver_pid = Some(r.value as u32),
            _ if r.origin_seq > 0 => {
                if self.recent.len() == RECENT {
                    self.recent.pop_front();
                }
                self.recent.push_back((r.origin_seq, r.timestamp_ns));
            }
            _ => {}
        }
    }

    fn hold(&mut self, seq: u64, record: EventRecord, bytes: usize) {
        self.held.push_back(Held {
            seq,
            record,
            bytes,
            sent_ns: 0,
            sendings: 0,
        });
        self.held_bytes += bytes;
        while self.held_bytes > self.config.bound_bytes && self.held.len() > 1 {
            if let Some(old) = self.held.pop_front() {
                self.held_bytes -= old.bytes;
                self.sent = self.sent.saturating_sub(1);
                self.lost += 1;
            }
        }
    }

    /// The next event to send at `now`, if one is due: the oldest not yet sent while fewer than
    /// `window` await their acknowledgement; all of them again from the oldest when the oldest
    /// has waited `resend-after` (which then doubles).
    pub fn next_to_send(&mut self, now_ns: u64) -> Option<EventMsg> {
        let oldest_overdue = self.sent > 0
            && self
                .held
                .front()
                .is_some_and(|h| now_ns.saturating_sub(h.sent_ns) >= self.resend_after_ns);
        if oldest_overdue {
            self.sent = 0;
            self.resend_after_ns = (self.resend_after_ns * 2).min(MAX_RESEND_AFTER_NS);
        }
        if self.sent >= self.config.window {
            return None;
        }
        let held_from = self.held_from();
        let h = self.held.get_mut(self.sent)?;
        self.sent += 1;
        h.sent_ns = now_ns;
        if h.sendings == 0 {
            self.first_sendings += 1;
        } else {
            self.resent += 1;
        }
        h.sendings += 1;
        Some(EventMsg {
            version: SCHEMA_VERSION,
            journal: self.journal,
            seq: h.seq,
            held_from,
            event: h.record.clone(),
        })
    }

    /// The link to the fleet has just come up: what is held goes out again from the oldest at
    /// the next sending, without waiting out a resend interval grown while nothing got through.
    pub fn resend_now(&mut self) {
        self.sent = 0;
        self.resend_after_ns = self.config.resend_after_ns;
    }

    /// An event the journal could not keep, as a message: number 0 (the fleet stores it as
    /// it comes, with nothing to de-duplicate it by), sent once.
    pub fn unnumbered(&self, record: EventRecord) -> EventMsg {
        EventMsg {
            version: SCHEMA_VERSION,
            journal: self.journal,
            seq: 0,
            held_from: self.held_from(),
            event: record,
        }
    }

    /// Where the held events start: the oldest held, or the next to come when none is.
    fn held_from(&self) -> u64 {
        self.held.front().map_or(self.newest_seq + 1, |h| h.seq)
    }

    /// The fleet's acknowledgement: the events it covers are let go. Returns the new
    /// `stored_through` when it moved (for the journal to keep), `None` for an old one.
    pub fn acknowledged(&mut self, ack: &AckMsg) -> Result<Option<u64>, AckRefused> {
        let refused = if ack.journal != self.journal {
            Some(AckRefused::OtherJournal {
                got: ack.journal,
                ours: self.journal,
            })
        } else if ack.stored_through > self.newest_seq {
            Some(AckRefused::Beyond {
                through: ack.stored_through,
                newest: self.newest_seq,
            })
        } else {
            None
        };
        if let Some(r) = refused {
            self.acks_refused += 1;
            return Err(r);
        }
        if ack.stored_through <= self.stored_through {
            return Ok(None);
        }
        self.stored_through = ack.stored_through;
        while let Some(h) = self.held.front() {
            if h.seq > ack.stored_through {
                break;
            }
            self.held_bytes -= h.bytes;
            self.held.pop_front();
            self.sent = self.sent.saturating_sub(1);
        }
        self.resend_after_ns = self.config.resend_after_ns;
        Ok(Some(ack.stored_through))
    }

    /// The journal's identity.
    pub fn journal(&self) -> u64 {
        self.journal
    }
    /// Events held, not yet acknowledged.
    pub fn held(&self) -> usize {
        self.held.len()
    }
    /// How far the fleet has acknowledged.
    pub fn stored_through(&self) -> u64 {
        self.stored_through
    }
    /// Held events dropped at the bound before they were acknowledged.
    pub fn lost(&self) -> u64 {
        self.lost
    }
    /// First sendings.
    pub fn sent(&self) -> u64 {
        self.first_sendings
    }
    /// Sendings again.
    pub fn resent(&self) -> u64 {
        self.resent
    }
    /// Acknowledgements refused.
    pub fn acks_refused(&self) -> u64 {
        self.acks_refused
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: u64 = 1_000_000_000;

    fn config() -> DeliveryConfig {
        DeliveryConfig {
            bound_bytes: 1 << 20,
            resend_after_ns: 2 * S,
            window: 4,
        }
    }

    fn record(origin_seq: u64, t: u64) -> EventRecord {
        EventRecord {
            timestamp_ns: t,
            wall_ms: 0,
            origin_seq,
            kind: "Stall".into(),
            joint: "left_elbow".into(),
            detail: String::new(),
            bus: 0,
            level: 0,
            value: 1.5,
        }
    }

    fn drain(d: &mut Delivery, now: u64) -> Vec<u64> {
        std::iter::from_fn(|| d.next_to_send(now).map(|m| m.seq)).collect()
    }

    fn ack(through: u64) -> AckMsg {
        AckMsg {
            version: SCHEMA_VERSION,
            journal: 7,
            stored_through: through,
        }
    }

    #[test]
    fn events_go_out_in_order_within_the_window_and_an_acknowledgement_lets_them_go() {
        let (mut d, _) = Delivery::new(7, &[], 0, config());
        for seq in 1..=6 {
            d.journaled(seq, record(seq, seq), 40);
        }
        assert_eq!(drain(&mut d, S), [1, 2, 3, 4], "the window");
        assert_eq!(d.acknowledged(&ack(2)), Ok(Some(2)));
        assert_eq!(drain(&mut d, S), [5, 6], "room again");
        assert_eq!((d.held(), d.stored_through(), d.resent()), (4, 2, 0));
        assert_eq!(
            d.acknowledged(&ack(1)),
            Ok(None),
            "an old one changes nothing"
        );
        assert_eq!(d.held(), 4);
        assert_eq!(d.acknowledged(&ack(6)), Ok(Some(6)));
        assert_eq!((d.held(), drain(&mut d, 100 * S)), (0, vec![]));
    }

    #[test]
    fn unacknowledged_events_go_again_from_the_oldest_with_a_growing_wait() {
        let (mut d, _) = Delivery::new(7, &[], 0, config());
        for seq in 1..=3 {
            d.journaled(seq, record(seq, seq), 40);
        }
        assert_eq!(drain(&mut d, 0), [1, 2, 3]);
        assert!(drain(&mut d, 2 * S - 1).is_empty(), "not yet");
        assert_eq!(drain(&mut d, 2 * S), [1, 2, 3], "again, whole");
        assert!(drain(&mut d, 5 * S).is_empty(), "the wait doubled to 4 s");
        assert_eq!(drain(&mut d, 6 * S), [1, 2, 3]);
        assert_eq!(d.resent(), 6);
        assert_eq!(d.sent(), 3);
        // Acknowledged: the wait is back to its first length.
        d.journaled(4, record(4, 4), 40);
        assert_eq!(d.acknowledged(&ack(3)), Ok(Some(3)));
        assert_eq!(drain(&mut d, 7 * S), [4]);
        assert_eq!(drain(&mut d, 9 * S), [4]);
        // The backoff stops at its ceiling.
        let mut t = 9 * S;
        for _ in 0..10 {
            t += MAX_RESEND_AFTER_NS;
            assert_eq!(drain(&mut d, t), [4]);
        }
    }

    #[test]
    fn a_restart_holds_what_was_not_acknowledged_and_knows_what_it_journaled() {
        let mut kept = Vec::new();
        for seq in 1..=5u64 {
            let mut r = record(100 + seq, 1000 * seq);
            if seq == 2 {
                r = EventRecord {
                    kind: SUPERVISOR_STARTED.into(),
                    origin_seq: 0,
                    value: 4242.0,
                    ..r
                };
            }
            kept.push(Record {
                seq,
                payload: Delivery::journal_bytes(&r),
            });
        }
        kept.push(Record {
            seq: 6,
            payload: vec![0xff; 3],
        });
        let (mut d, unreadable) = Delivery::new(7, &kept, 3, config());
        assert_eq!(unreadable, 1);
        assert_eq!(
            d.lost(),
            1,
            "an unreadable one past the acknowledgement is lost"
        );
        assert_eq!(drain(&mut d, 0), [4, 5]);
        assert!(d.seen(101, 1000), "acknowledged, still recognised");
        assert!(d.seen(105, 5000));
        assert!(
            !d.seen(105, 5001),
            "same number, another time: another event"
        );
        assert_eq!(d.started_pid(SUPERVISOR_STARTED), Some(4242));
        assert_eq!(d.started_pid(DRIVER_STARTED), None);
        let m = d.unnumbered(record(0, 1));
        assert_eq!((m.seq, m.held_from), (0, 4));
    }

    #[test]
    fn the_bound_drops_the_oldest_held_and_says_where_the_held_start() {
        let (mut d, _) = Delivery::new(
            7,
            &[],
            0,
            DeliveryConfig {
                bound_bytes: 100,
                ..config()
            },
        );
        for seq in 1..=5 {
            d.journaled(seq, record(seq, seq), 40);
        }
        assert_eq!((d.held(), d.lost()), (2, 3));
        let m = d.next_to_send(0).unwrap();
        assert_eq!((m.seq, m.held_from), (4, 4));
    }

    #[test]
    fn acknowledgements_of_another_journal_or_of_the_future_are_refused_and_counted() {
        let (mut d, _) = Delivery::new(7, &[], 0, config());
        d.journaled(1, record(1, 1), 40);
        let other = AckMsg {
            journal: 8,
            ..ack(1)
        };
        assert!(matches!(
            d.acknowledged(&other),
            Err(AckRefused::OtherJournal { got: 8, ours: 7 })
        ));
        assert_eq!(
            d.acknowledged(&ack(2)),
            Err(AckRefused::Beyond {
                through: 2,
                newest: 1
            })
        );
        assert_eq!((d.acks_refused(), d.held()), (2, 1));
    }
}
