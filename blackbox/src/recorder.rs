//! The recorder's core: every message into the ring, and into the box being frozen if one is;
//! a trigger opens a box with the ring's last minutes (or keeps the open one longer), and the
//! box is finished once its window has passed. Time is passed in; the files are the caller's.

use crate::channel::{to_json, Channel, EventMessage};
use crate::frozen::{BoxError, BoxWriter};
use crate::ring::{Record, Ring, RingStats};
use std::io::{Seek, Write};

/// A box's window around the event that froze it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Window {
    /// Kept before the event, ns.
    pub before_ns: u64,
    /// Kept after the (last) event, ns.
    pub after_ns: u64,
    /// A box is finished this long after it opened whatever keeps happening, ns (a trigger
    /// after that opens the next box).
    pub longest_ns: u64,
}

/// What the recorder did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct RecorderCounters {
    /// Triggers seen.
    pub triggers: u64,
    /// Boxes opened.
    pub boxes_opened: u64,
    /// Boxes finished.
    pub boxes_finished: u64,
    /// Writes to a box that failed (the box is given up; the ring goes on).
    pub box_errors: u64,
}

struct Open<W: Write + Seek> {
    writer: BoxWriter<W>,
    opened_ns: u64,
    until_ns: u64,
    /// While the box catches up with the ring: the ring's sequence number to copy next, and
    /// the oldest time the box takes. Live messages reach the box through the ring until then.
    catching_up: Option<(u64, u64)>,
}

/// Ring records copied into a new box per step ([`Recorder::pump`]): a few milliseconds, so
/// the process drains the plane's queues (80 ms of joint states) between steps.
pub const COPY_STEP: usize = 400;

/// The ring and the box being frozen.
pub struct Recorder<W: Write + Seek> {
    ring: Ring,
    open: Option<Open<W>>,
    window: Window,
    /// What it did.
    pub counters: RecorderCounters,
}

impl<W: Write + Seek> Recorder<W> {
    /// A recorder over `ring`, freezing `window` around each trigger.
    pub fn new(ring: Ring, window: Window) -> Self {
        Recorder {
            ring,
            open: None,
            window,
            counters: RecorderCounters::default(),
        }
    }

    /// What the ring holds.
    pub fn ring_stats(&self) -> RingStats {
        self.ring.stats()
    }

    /// Whether a box is being frozen.
    pub fn is_freezing(&self) -> bool {
        self.open.is_some()
    }

    /// One message from the plane. A box that cannot be written is given up (its error
    /// returned); the ring keeps recording.
    pub fn record(&mut self, r: Record) -> Result<(), BoxError> {
        self.ring.push(r);
        let Some(open) = self.open.as_mut() else {
            return Ok(());
        };
        if open.catching_up.is_some() {
            return Ok(());
        }
        open.writer.write(r).inspect_err(|_| {
            self.counters.box_errors += 1;
            self.open = None;
        })
    }

    /// One step of a new box's copy of the ring (at most `max` records); the box then takes
    /// live messages once it has caught up. Whether it is still catching up.
    pub fn pump(&mut self, max: usize) -> Result<bool, BoxError> {
        let Some(open) = self.open.as_mut() else {
            return Ok(false);
        };
        let Some((cursor, since)) = open.catching_up else {
            return Ok(false);
        };
        let mut failed = None;
        let writer = &mut open.writer;
        let next = self.ring.read_from(cursor, max, &mut |r| {
            if failed.is_none() && r.t_ns >= since {
                failed = writer.write(r).err();
            }
        });
        if let Some(e) = failed {
            self.counters.box_errors += 1;
            self.open = None;
            return Err(e);
        }
        let behind = next < self.ring.next_seq();
        open.catching_up = behind.then_some((next, since));
        Ok(behind)
    }

    /// A trigger: opens a box on the writer `create` gives (the ring's messages from
    /// `before_ns` ahead of the event, then everything until `after_ns` past it), or keeps the
    /// open box longer. Whether a box was opened.
    pub fn trigger(
        &mut self,
        event: &EventMessage,
        create: impl FnOnce(&EventMessage) -> Result<BoxWriter<W>, BoxError>,
    ) -> Result<bool, BoxError> {
        self.counters.triggers += 1;
        let data = to_json(event);
        let trigger = Record {
            channel: Channel::Triggers,
            t_ns: event.timestamp_ns,
            data: &data,
        };
        let until = event.timestamp_ns.saturating_add(self.window.after_ns);
        if let Some(open) = self.open.as_mut() {
            open.until_ns = open
                .until_ns
                .max(until)
                .min(open.opened_ns.saturating_add(self.window.longest_ns));
            self.record(trigger)?;
            return Ok(false);
        }
        let writer = create(event).inspect_err(|_| self.counters.box_errors += 1)?;
        let since = event.timestamp_ns.saturating_sub(self.window.before_ns);
        self.counters.boxes_opened += 1;
        self.open = Some(Open {
            writer,
            opened_ns: event.timestamp_ns,
            until_ns: until,
            catching_up: Some((self.ring.oldest_seq(), since)),
        });
        // The trigger goes through the ring, so the box takes it in its place.
        self.record(trigger)?;
        self.pump(COPY_STEP)?;
        Ok(true)
    }

    /// Ends the open box's chunk and syncs it (called about once a second).
    pub fn flush(&mut self) -> Result<(), BoxError> {
        let Some(open) = self.open.as_mut() else {
            return Ok(());
        };
        open.writer.flush().inspect_err(|_| {
            self.counters.box_errors += 1;
            self.open = None;
        })
    }

    /// Seals the ring's open segment (the recorder is stopping, or idle).
    pub fn seal(&mut self) {
        self.ring.seal();
    }

    /// Finishes the open box once `now_ns` is past its window (or `force`): its writer,
    /// summary and footer written, for the caller to name whole.
    pub fn finish_due(&mut self, now_ns: u64, force: bool) -> Option<Result<W, BoxError>> {
        let due = self.open.as_ref()?.until_ns <= now_ns || force;
        if !due {
            return None;
        }
        if let Err(e) = self.pump(usize::MAX) {
            return Some(Err(e));
        }
        let open = self.open.take()?;
        let finished = open.writer.finish();
        match &finished {
            Ok(_) => self.counters.boxes_finished += 1,
            Err(_) => self.counters.box_errors += 1,
        }
        Some(finished)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frozen::read;
    use std::io::Cursor;

    const S: u64 = 1_000_000_000;

    fn recorder() -> Recorder<Cursor<Vec<u8>>> {
        Recorder::new(
            Ring::new(60 * S, S, usize::MAX),
            Window {
                before_ns: 10 * S,
                after_ns: 2 * S,
                longest_ns: 20 * S,
            },
        )
    }

    fn feed(r: &mut Recorder<Cursor<Vec<u8>>>, from_s: u64, to_s: u64) {
        for t in (from_s * 10)..(to_s * 10) {
            let t_ns = t * S / 10;
            let data = format!("{{\"timestamp_ns\": {t_ns}}}");
            r.record(Record {
                channel: Channel::JointStates,
                t_ns,
                data: data.as_bytes(),
            })
            .unwrap();
        }
    }

    fn trip(t_s: u64) -> EventMessage {
        EventMessage {
            timestamp_ns: t_s * S,
            kind: "thermal_trip".into(),
            joint: Some("left_elbow".into()),
            bus: Some("left_arm".into()),
            level: 0,
            value: 59.0,
        }
    }

    fn open(e: &EventMessage) -> Result<BoxWriter<Cursor<Vec<u8>>>, BoxError> {
        BoxWriter::new(Cursor::new(Vec::new()), e, "r1", 0)
    }

    fn times(bytes: &[u8], channel: Channel) -> Vec<u64> {
        read(bytes)
            .messages
            .iter()
            .filter(|m| m.channel == Some(channel))
            .map(|m| m.log_time)
            .collect()
    }

    #[test]
    fn a_box_holds_the_window_before_and_after_its_event_and_the_event() {
        let mut r = recorder();
        feed(&mut r, 0, 30);
        assert!(r.trigger(&trip(30), open).unwrap());
        feed(&mut r, 30, 31);
        assert!(r.finish_due(31 * S, false).is_none(), "the window is open");
        feed(&mut r, 31, 40);
        let bytes = r.finish_due(32 * S, false).unwrap().unwrap().into_inner();
        let t = times(&bytes, Channel::JointStates);
        assert_eq!(t.first(), Some(&(20 * S)), "10 s before the event");
        assert!(*t.last().unwrap() >= 32 * S - S / 10);
        assert!(t.windows(2).all(|w| w[0] < w[1]), "in order, none twice");
        assert_eq!(times(&bytes, Channel::Triggers), vec![30 * S]);
        assert!(read(&bytes).extent.complete);
        assert!(!r.is_freezing());
        assert_eq!(r.counters.boxes_finished, 1);
    }

    #[test]
    fn a_box_catches_up_with_the_ring_in_steps_and_takes_what_came_meanwhile_once() {
        let mut r = recorder();
        feed(&mut r, 0, 60);
        assert!(r.trigger(&trip(60), open).unwrap());
        assert!(r.is_freezing());
        // Live messages come between the copy's steps, as the plane's do between loop turns.
        let mut t = 600;
        while r.pump(7).unwrap() {
            let data = format!("{{\"timestamp_ns\": {}}}", t * S / 10);
            r.record(Record {
                channel: Channel::JointStates,
                t_ns: t * S / 10,
                data: data.as_bytes(),
            })
            .unwrap();
            t += 1;
        }
        assert!(t > 600 + 10, "the copy took several steps");
        let bytes = r.finish_due(u64::MAX, true).unwrap().unwrap().into_inner();
        let times = times(&bytes, Channel::JointStates);
        assert_eq!(times.first(), Some(&(50 * S)), "10 s before the event");
        assert_eq!(
            times.len() as u64,
            t - 500,
            "everything from the window on, once each"
        );
        assert!(times.windows(2).all(|w| w[0] < w[1]));
    }

    #[test]
    fn a_second_event_in_the_window_extends_the_box_up_to_its_longest() {
        let mut r = recorder();
        feed(&mut r, 0, 30);
        assert!(r.trigger(&trip(30), open).unwrap());
        feed(&mut r, 30, 31);
        assert!(!r.trigger(&trip(31), open).unwrap());
        assert!(
            r.finish_due(32 * S + 1, false).is_none(),
            "extended to 33 s"
        );
        for k in 0..30 {
            assert!(!r.trigger(&trip(31 + k), open).unwrap());
        }
        let bytes = r.finish_due(50 * S, false).unwrap().unwrap().into_inner();
        assert_eq!(times(&bytes, Channel::Triggers).len(), 32);
        assert!(r.finish_due(50 * S, false).is_none());
        assert!(
            r.trigger(&trip(60), open).unwrap(),
            "the next event opens the next box"
        );
    }

    #[test]
    fn a_box_that_cannot_be_opened_leaves_the_ring_recording() {
        let mut r = recorder();
        feed(&mut r, 0, 5);
        let refused = r.trigger(&trip(5), |_| {
            Err(BoxError::Io {
                path: "/full".into(),
                source: std::io::Error::other("no space left"),
            })
        });
        assert!(refused.is_err());
        assert_eq!(r.counters.box_errors, 1);
        feed(&mut r, 5, 10);
        assert!(r.trigger(&trip(10), open).unwrap());
        let bytes = r.finish_due(100 * S, true).unwrap().unwrap().into_inner();
        assert_eq!(times(&bytes, Channel::JointStates).first(), Some(&0));
    }
}
