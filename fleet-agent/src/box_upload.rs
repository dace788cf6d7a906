//! The black box's frozen boxes to the fleet, chunk by chunk, at least once (docs/blackbox.md,
//! "To the fleet"). Pure: the shelf's listing, the fleet's acknowledgements and the time in,
//! the chunks to read and send out.
//!
//! Boxes go newest first, one at a time (the recorder trims the oldest beyond its cap: after a
//! long outage the newest are the ones that can still arrive, and the ones asked about). Each starts with a probe (a chunk of no bytes at
//! offset 0), which the store answers with how much of it it holds: a box it has whole is
//! never sent again, one it holds part of resumes there (an agent restarted, a store that was
//! down). Then chunks go in order, at most `window` unacknowledged; when the oldest has waited
//! `resend-after` without an acknowledgement, everything unacknowledged goes again from the
//! store's offset, and the wait doubles. Bytes are paced by a token bucket, and nothing is
//! sent while the event journal has anything unacknowledged: a box never goes ahead of the
//! events.

use std::collections::VecDeque;

/// The longest wait before sending unacknowledged chunks again.
pub const MAX_RESEND_AFTER_NS: u64 = 60_000_000_000;

/// Reads of a box's chunk that fail in a row before the box is set aside (its file unreadable):
/// one bad file never holds up the boxes after it.
pub const MAX_READ_FAILURES: u32 = 3;

/// A finished box on the robot's shelf.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ShelvedBox {
    /// Its number on the shelf (counts up across restarts).
    pub number: u64,
    /// Its file name.
    pub name: String,
    /// Its size, bytes.
    pub size: u64,
    /// The SHA-256 of its bytes: its identity at the store (a wiped shelf numbers from 1
    /// again; its boxes are still new to the store).
    pub digest: [u8; 32],
}

/// How the upload is paced.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UploadConfig {
    /// Bytes a chunk carries at most.
    pub chunk_bytes: u64,
    /// Bytes a second, on average.
    pub bytes_per_second: f64,
    /// Bytes that may go at once after a quiet while.
    pub burst_bytes: f64,
    /// Chunks sent and not yet acknowledged, at most.
    pub window: usize,
    /// The first wait for an acknowledgement before sending again, ns.
    pub resend_after_ns: u64,
}

/// A chunk to send: `len` bytes of box `number` from `offset` (0 bytes: a probe).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChunkToSend {
    /// The box's number.
    pub number: u64,
    /// Its file name.
    pub name: String,
    /// Its size.
    pub size: u64,
    /// The SHA-256 of the whole box.
    pub digest: [u8; 32],
    /// Where the chunk starts.
    pub offset: u64,
    /// Its length (0: a probe, asking how much the store holds).
    pub len: u64,
}

/// The store's acknowledgement of a box: it holds `received` bytes of it from the start, and
/// `complete` when it has it whole and checked; `refused` when it will not take it (its
/// reason counted at the store): the box is set aside.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BoxAck {
    /// The box's number.
    pub number: u64,
    /// The SHA-256 of the box (an acknowledgement of another box of that number, from before
    /// the shelf was wiped, is refused).
    pub digest: [u8; 32],
    /// Bytes the store holds, from the start.
    pub received: u64,
    /// Held whole, checked against its digest.
    pub complete: bool,
    /// The store will not take it.
    pub refused: bool,
}

/// What the upload did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct UploadCounters {
    /// Boxes the store holds whole.
    pub boxes_stored: u64,
    /// Boxes gone from the shelf (its cap) before the store had them whole.
    pub boxes_lost: u64,
    /// Boxes the store refused (set aside while this agent runs).
    pub boxes_refused: u64,
    /// Boxes whose file could not be read (set aside while this agent runs).
    pub boxes_unreadable: u64,
    /// Bytes sent the first time.
    pub bytes_sent: u64,
    /// Bytes sent again.
    pub bytes_resent: u64,
    /// Acknowledgements of no box in flight, of another digest, or beyond its size.
    pub acks_refused: u64,
}

/// The box being sent.
#[derive(Debug)]
struct InFlight {
    shelved: ShelvedBox,
    /// The store answered the probe: `acked` is what it holds.
    probed: bool,
    acked: u64,
    /// The next byte to send.
    next: u64,
    /// Chunks sent and unacknowledged: their end, when they went, and the bytes of them sent
    /// the first time.
    unacked: VecDeque<(u64, u64, u64)>,
    /// The furthest byte ever sent (bytes before it go out again as resent).
    furthest: u64,
    /// Nothing more of it goes before this time (a chunk the shelf could not give).
    held_until_ns: u64,
    /// Reads of its chunks that failed in a row.
    read_failures: u32,
}

/// The upload's state.
#[derive(Debug)]
pub struct Upload {
    config: UploadConfig,
    waiting: VecDeque<ShelvedBox>,
    in_flight: Option<InFlight>,
    /// Boxes known whole at the store, or refused by it, by number and digest (never sent
    /// again while this agent runs).
    done: Vec<(u64, [u8; 32])>,
    tokens: f64,
    tokens_at_ns: u64,
    resend_after_ns: u64,
    counters: UploadCounters,
}

impl Upload {
    /// An upload with nothing on the shelf yet.
    pub fn new(config: UploadConfig) -> Upload {
        Upload {
            config,
            waiting: VecDeque::new(),
            in_flight: None,
            done: Vec::new(),
            tokens: config.burst_bytes,
            tokens_at_ns: 0,
            resend_after_ns: config.resend_after_ns,
            counters: UploadCounters::default(),
        }
    }

    /// The shelf's finished boxes now: new ones wait their turn (the newest goes next); one
    /// gone before the store had it whole is counted lost.
    pub fn shelf(&mut self, boxes: &[ShelvedBox]) {
        let on_shelf = |n: u64, d: &[u8; 32]| boxes.iter().any(|b| b.number == n && &b.digest == d);
        let before = self.waiting.len();
        self.waiting.retain(|b| on_shelf(b.number, &b.digest));
        self.done.retain(|(n, d)| on_shelf(*n, d));
        let mut lost = (before - self.waiting.len()) as u64;
        if self
            .in_flight
            .as_ref()
            .is_some_and(|f| !on_shelf(f.shelved.number, &f.shelved.digest))
        {
            self.in_flight = None;
            lost += 1;
        }
        self.counters.boxes_lost += lost;
        for b in boxes {
            let same = |w: &ShelvedBox| w.number == b.number && w.digest == b.digest;
            let known = self.done.contains(&(b.number, b.digest))
                || self.waiting.iter().any(same)
                || self.in_flight.as_ref().is_some_and(|f| same(&f.shelved));
            if !known {
                self.waiting.push_back(b.clone());
            }
        }
        self.waiting.make_contiguous().sort_by_key(|b| b.number);
    }

    /// The next chunk to send at `now_ns`, if one is due. `quiet`: the event journal has
    /// nothing unacknowledged.
    pub fn next_chunk(&mut self, now_ns: u64, quiet: bool) -> Option<ChunkToSend> {
        self.refill(now_ns);
        if !quiet {
            return None;
        }
        if self.in_flight.is_none() {
            let shelved = self.waiting.pop_back()?;
            self.in_flight = Some(InFlight {
                shelved,
                probed: false,
                acked: 0,
                next: 0,
                unacked: VecDeque::new(),
                furthest: 0,
                held_until_ns: 0,
                read_failures: 0,
            });
        }
        let resend_after = self.resend_after_ns;
        let f = self.in_flight.as_mut()?;
        let overdue = f
            .unacked
            .front()
            .is_some_and(|&(_, at, _)| now_ns.saturating_sub(at) >= resend_after);
        if overdue {
            f.unacked.clear();
            f.next = f.acked;
            self.resend_after_ns = (self.resend_after_ns * 2).min(MAX_RESEND_AFTER_NS);
        }
        if !f.probed {
            if !f.unacked.is_empty() {
                return None;
            }
            f.unacked.push_back((0, now_ns, 0));
            return Some(chunk(&f.shelved, 0, 0));
        }
        let held = now_ns < f.held_until_ns;
        if held || f.unacked.len() >= self.config.window || f.next >= f.shelved.size {
            return None;
        }
        let len = self.config.chunk_bytes.min(f.shelved.size - f.next);
        if self.tokens < len as f64 {
            return None;
        }
        self.tokens -= len as f64;
        let out = chunk(&f.shelved, f.next, len);
        let fresh = (f.next + len).saturating_sub(f.furthest.max(f.next));
        self.counters.bytes_sent += fresh;
        self.counters.bytes_resent += len - fresh;
        f.next += len;
        f.furthest = f.furthest.max(f.next);
        f.unacked.push_back((f.next, now_ns, fresh));
        Some(out)
    }

    fn refill(&mut self, now_ns: u64) {
        let dt = now_ns.saturating_sub(self.tokens_at_ns) as f64 * 1e-9;
        self.tokens_at_ns = self.tokens_at_ns.max(now_ns);
        self.tokens =
            (self.tokens + dt * self.config.bytes_per_second).min(self.config.burst_bytes);
    }

    /// The store's acknowledgement. An old one, or one of a box not in flight, changes
    /// nothing; one beyond the box's size is refused.
    pub fn acknowledged(&mut self, ack: BoxAck) -> bool {
        let Some(f) = self
            .in_flight
            .as_mut()
            .filter(|f| f.shelved.number == ack.number && f.shelved.digest == ack.digest)
        else {
            self.counters.acks_refused += 1;
            return false;
        };
        if ack.received > f.shelved.size {
            self.counters.acks_refused += 1;
            return false;
        }
        // Held to its end yet not whole: the store cannot take it (nothing would be sent
        // again), so it is set aside like a refused one.
        let stuck = ack.received == f.shelved.size && !ack.complete;
        if ack.complete || ack.refused || stuck {
            self.done.push((ack.number, ack.digest));
            if ack.complete {
                self.counters.boxes_stored += 1;
            } else {
                self.counters.boxes_refused += 1;
            }
            self.in_flight = None;
            self.resend_after_ns = self.config.resend_after_ns;
            return true;
        }
        if !f.probed {
            // The store's offset is where this box resumes.
            f.probed = true;
            f.acked = ack.received;
            f.next = ack.received;
            f.furthest = f.furthest.max(ack.received);
            f.unacked.clear();
        } else if ack.received < f.acked || ack.received > f.next {
            // The store lost what it had (a restart without it), or holds what was never
            // sent to it this time: resume where it is.
            f.acked = ack.received;
            f.next = ack.received;
            f.unacked.clear();
        } else {
            f.acked = ack.received;
            f.unacked.retain(|&(end, _, _)| end > ack.received);
        }
        f.read_failures = 0;
        self.resend_after_ns = self.config.resend_after_ns;
        true
    }

    /// `chunk`, the last one handed out, could not be read and did not go: it is not counted
    /// as sent, and nothing more of its box goes before the wait for an acknowledgement has
    /// passed (then it is read again); after [`MAX_READ_FAILURES`] in a row the box is set
    /// aside, counted unreadable.
    pub fn unsent(&mut self, chunk: &ChunkToSend, now_ns: u64) {
        let Some(f) = self.in_flight.as_mut().filter(|f| {
            f.shelved.number == chunk.number
                && f.shelved.digest == chunk.digest
                && f.next == chunk.offset + chunk.len
        }) else {
            return;
        };
        if let Some((_, _, fresh)) = f.unacked.pop_back() {
            let c = &mut self.counters;
            c.bytes_sent = c.bytes_sent.saturating_sub(fresh);
            c.bytes_resent = c.bytes_resent.saturating_sub(chunk.len - fresh);
            f.furthest = f.furthest.saturating_sub(fresh);
        }
        f.next = chunk.offset;
        f.held_until_ns = now_ns.saturating_add(self.resend_after_ns);
        f.read_failures += 1;
        self.tokens = (self.tokens + chunk.len as f64).min(self.config.burst_bytes);
        if f.read_failures >= MAX_READ_FAILURES {
            self.done.push((f.shelved.number, f.shelved.digest));
            self.counters.boxes_unreadable += 1;
            self.in_flight = None;
        }
    }

    /// The link to the fleet has just come up: what is unacknowledged goes again at once.
    pub fn link_up(&mut self) {
        if let Some(f) = self.in_flight.as_mut() {
            f.unacked.clear();
            f.next = f.acked;
        }
        self.resend_after_ns = self.config.resend_after_ns;
    }

    /// Boxes waiting or in flight.
    pub fn pending(&self) -> usize {
        self.waiting.len() + usize::from(self.in_flight.is_some())
    }

    /// What it did.
    pub fn counters(&self) -> UploadCounters {
        self.counters
    }
}

fn chunk(b: &ShelvedBox, offset: u64, len: u64) -> ChunkToSend {
    ChunkToSend {
        number: b.number,
        name: b.name.clone(),
        size: b.size,
        digest: b.digest,
        offset,
        len,
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    const MS: u64 = 1_000_000;

    fn config() -> UploadConfig {
        UploadConfig {
            chunk_bytes: 100,
            bytes_per_second: 1000.0,
            burst_bytes: 300.0,
            window: 2,
            resend_after_ns: 500 * MS,
        }
    }

    fn shelved(number: u64, size: u64) -> ShelvedBox {
        ShelvedBox {
            number,
            name: format!("{number:06}-box.mcap"),
            size,
            digest: [number as u8; 32],
        }
    }

    /// The store's answer to `c`: it holds `received` bytes of its box, not whole; `refused`.
    fn answer(c: &ChunkToSend, received: u64, refused: bool) -> BoxAck {
        BoxAck {
            number: c.number,
            digest: c.digest,
            received,
            complete: false,
            refused,
        }
    }

    /// A store that holds what arrives in order, and answers each chunk.
    #[derive(Default)]
    struct Store {
        held: std::collections::BTreeMap<u64, u64>,
        whole: Vec<u64>,
    }

    impl Store {
        fn take(&mut self, c: &ChunkToSend) -> BoxAck {
            let held = self.held.entry(c.number).or_insert(0);
            if c.offset == *held {
                *held += c.len;
            }
            let complete = *held == c.size;
            if complete && !self.whole.contains(&c.number) {
                self.whole.push(c.number);
            }
            BoxAck {
                number: c.number,
                digest: c.digest,
                received: *held,
                complete,
                refused: false,
            }
        }
    }

    /// Runs the upload against `store` for `steps` turns of 10 ms from `t`, the link up when
    /// `link(t)`; gives the time reached.
    fn run(
        u: &mut Upload,
        store: &mut Store,
        mut t: u64,
        steps: usize,
        link: impl Fn(u64) -> bool,
    ) -> u64 {
        for _ in 0..steps {
            t += 10 * MS;
            while let Some(c) = u.next_chunk(t, true) {
                if link(t) {
                    let ack = store.take(&c);
                    u.acknowledged(ack);
                }
            }
        }
        t
    }

    #[test]
    fn boxes_reach_the_store_whole_newest_first_at_the_paced_rate() {
        let mut u = Upload::new(config());
        u.shelf(&[shelved(1, 250), shelved(2, 1000)]);
        let mut store = Store::default();
        run(&mut u, &mut store, 0, 100, |_| true);
        assert_eq!(store.whole, vec![2, 1]);
        assert_eq!(u.pending(), 0);
        let c = u.counters();
        assert_eq!((c.boxes_stored, c.bytes_sent, c.bytes_resent), (2, 1250, 0));
        // 1250 bytes at 1000 B/s with a 300-byte burst: not before 0.95 s.
        let mut slow = Upload::new(config());
        slow.shelf(&[shelved(1, 1250)]);
        let mut store = Store::default();
        run(&mut slow, &mut store, 0, 90, |_| true);
        assert!(store.whole.is_empty(), "faster than its pace");
        run(&mut slow, &mut store, 900 * MS, 20, |_| true);
        assert_eq!(store.whole, vec![1]);
    }

    #[test]
    fn nothing_goes_while_events_wait() {
        let mut u = Upload::new(config());
        u.shelf(&[shelved(1, 100)]);
        assert_eq!(u.next_chunk(10 * MS, false), None);
        assert_eq!(u.next_chunk(20 * MS, true).map(|c| c.len), Some(0));
    }

    #[test]
    fn an_outage_resumes_where_the_store_is_and_a_stored_box_is_not_sent_again() {
        let mut u = Upload::new(config());
        u.shelf(&[shelved(1, 1000)]);
        let mut store = Store::default();
        // The link goes down after 0.3 s and comes back at 3 s.
        let down = |t: u64| !(300 * MS..3000 * MS).contains(&t);
        let t = run(&mut u, &mut store, 0, 500, down);
        assert_eq!(store.whole, vec![1]);
        let c = u.counters();
        assert_eq!(c.bytes_sent, 1000);
        assert!(c.bytes_resent > 0, "what was lost in the outage went again");

        // An agent restarted with the same shelf: the probe finds the box stored.
        let mut again = Upload::new(config());
        again.shelf(&[shelved(1, 1000), shelved(3, 50)]);
        run(&mut again, &mut store, t, 50, |_| true);
        assert_eq!(store.whole, vec![1, 3]);
        assert_eq!(again.counters().bytes_sent, 50, "box 1 not sent again");
    }

    #[test]
    fn a_box_the_store_holds_part_of_resumes_there() {
        let mut store = Store::default();
        store.held.insert(1, 600);
        let mut u = Upload::new(config());
        u.shelf(&[shelved(1, 1000)]);
        run(&mut u, &mut store, 0, 100, |_| true);
        assert_eq!(store.whole, vec![1]);
        assert_eq!(u.counters().bytes_sent, 400);
    }

    #[test]
    fn a_box_trimmed_off_the_shelf_before_it_was_stored_is_counted_lost() {
        let mut u = Upload::new(config());
        u.shelf(&[shelved(1, 100), shelved(2, 1000)]);
        let first = u.next_chunk(10 * MS, true).unwrap();
        assert_eq!(first.number, 2, "the newest first");
        u.shelf(&[shelved(1, 100)]);
        assert_eq!(u.counters().boxes_lost, 1);
        assert_eq!(u.next_chunk(20 * MS, true).map(|c| c.number), Some(1));
        // Box 1 rewritten under its number (another digest): the one in flight is lost, the
        // new one waits its turn.
        let mut rewritten = shelved(1, 100);
        rewritten.digest = [8; 32];
        u.shelf(&[rewritten]);
        assert_eq!(u.counters().boxes_lost, 2);
        assert_eq!(u.next_chunk(30 * MS, true).map(|c| c.digest), Some([8; 32]));
    }

    #[test]
    fn a_wrong_acknowledgement_changes_nothing() {
        let mut u = Upload::new(config());
        u.shelf(&[shelved(1, 100)]);
        u.next_chunk(10 * MS, true).unwrap();
        let beyond = BoxAck {
            number: 1,
            digest: [1; 32],
            received: 101,
            complete: false,
            refused: false,
        };
        let other = BoxAck {
            number: 9,
            digest: [9; 32],
            received: 0,
            complete: true,
            refused: false,
        };
        // Box 1 of a shelf since wiped: its number, another digest.
        let wiped = BoxAck {
            digest: [7; 32],
            ..other
        };
        let wiped = BoxAck { number: 1, ..wiped };
        assert!(!u.acknowledged(beyond));
        assert!(!u.acknowledged(other));
        assert!(!u.acknowledged(wiped));
        assert_eq!(u.counters().acks_refused, 3);
        assert_eq!(u.counters().boxes_stored, 0);
        assert_eq!(u.pending(), 1);
    }

    #[test]
    fn a_box_the_store_refuses_is_set_aside_and_the_next_goes() {
        let mut u = Upload::new(config());
        u.shelf(&[shelved(1, 100), shelved(2, 100)]);
        let probe = u.next_chunk(10 * MS, true).unwrap();
        assert_eq!(probe.number, 2);
        assert!(u.acknowledged(answer(&probe, 0, true)));
        assert_eq!(u.counters().boxes_refused, 1);
        let probe = u.next_chunk(20 * MS, true).unwrap();
        assert_eq!(probe.number, 1);
        // Held to its end and not whole: set aside too (nothing would ever go again).
        assert!(u.acknowledged(answer(&probe, 100, false)));
        assert_eq!(u.counters().boxes_refused, 2);
        // Listed again, neither is sent again.
        u.shelf(&[shelved(1, 100), shelved(2, 100)]);
        assert_eq!(u.pending(), 0);
        assert_eq!(u.next_chunk(30 * MS, true), None);
    }

    #[test]
    fn a_chunk_that_could_not_be_read_is_not_counted_and_goes_again_after_the_wait() {
        let mut u = Upload::new(config());
        u.shelf(&[shelved(1, 300)]);
        let mut store = Store::default();
        let probe = u.next_chunk(10 * MS, true).unwrap();
        u.acknowledged(store.take(&probe));
        let first = u.next_chunk(20 * MS, true).unwrap();
        assert_eq!((first.offset, first.len), (0, 100));
        u.unsent(&first, 20 * MS);
        assert_eq!(u.counters().bytes_sent, 0, "not sent");
        assert_eq!(
            u.next_chunk(30 * MS, true),
            None,
            "held until the wait has passed"
        );
        let again = u.next_chunk(20 * MS + 500 * MS, true).unwrap();
        assert_eq!(
            (again.offset, again.len),
            (0, 100),
            "the same bytes, no gap"
        );
        assert_eq!(u.counters().bytes_sent, 100);
    }

    #[test]
    fn a_wiped_shelf_s_new_box_of_a_stored_number_is_sent() {
        let mut u = Upload::new(config());
        u.shelf(&[shelved(1, 100)]);
        let mut store = Store::default();
        run(&mut u, &mut store, 0, 50, |_| true);
        assert_eq!(u.counters().boxes_stored, 1);
        let mut renumbered = shelved(1, 100);
        renumbered.digest = [42; 32];
        u.shelf(&[renumbered]);
        assert_eq!(u.pending(), 1, "box 1 of the new shelf is another box");
    }

    #[test]
    fn a_box_whose_file_cannot_be_read_is_set_aside_and_the_next_goes() {
        let mut u = Upload::new(config());
        u.shelf(&[shelved(1, 300), shelved(2, 300)]);
        let mut store = Store::default();
        let probe = u.next_chunk(0, true).unwrap();
        u.acknowledged(store.take(&probe));
        let mut t = 10 * MS;
        for failed in 1..=MAX_READ_FAILURES {
            let c = u.next_chunk(t, true).unwrap();
            assert_eq!((c.number, c.offset), (2, 0));
            u.unsent(&c, t);
            assert_eq!(
                u.counters().boxes_unreadable,
                u64::from(failed / MAX_READ_FAILURES)
            );
            t += 600 * MS;
        }
        assert_eq!(u.next_chunk(t, true).map(|c| c.number), Some(1));
        assert_eq!(u.counters().bytes_sent, 0);
    }
}
