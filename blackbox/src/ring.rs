//! The last minutes in memory: messages appended to an open segment, which is sealed (zstd)
//! once it spans `segment` of time; sealed segments are dropped oldest first beyond the byte cap
//! and the time span. Nothing here writes to the SD card: a box is written only when frozen.

use crate::channel::Channel;
use std::collections::VecDeque;
use thiserror::Error;

/// A sealed segment that cannot be read back (memory corrupted, a bug): its messages are lost.
#[derive(Debug, Error)]
#[error("a sealed segment of the ring ({start_ns}..{end_ns} ns) cannot be read: {why}")]
pub struct RingError {
    /// Its first message's time.
    pub start_ns: u64,
    /// Its last message's time.
    pub end_ns: u64,
    /// What the decompressor said.
    pub why: String,
}

/// One message as the ring holds it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Record<'a> {
    /// Its channel.
    pub channel: Channel,
    /// Its time on the robot's monotonic clock, ns.
    pub t_ns: u64,
    /// Its JSON.
    pub data: &'a [u8],
}

const HEADER: usize = 1 + 8 + 4;

fn append(buf: &mut Vec<u8>, r: Record) {
    buf.push(r.channel.id());
    buf.extend_from_slice(&r.t_ns.to_le_bytes());
    buf.extend_from_slice(&(r.data.len() as u32).to_le_bytes());
    buf.extend_from_slice(r.data);
}

/// The records of a segment's raw bytes, in order (a torn record ends them).
fn records(buf: &[u8]) -> impl Iterator<Item = Record<'_>> {
    let mut at = 0;
    std::iter::from_fn(move || {
        let head = buf.get(at..at + HEADER)?;
        let channel = Channel::from_id(head[0])?;
        let t_ns = u64::from_le_bytes(head[1..9].try_into().ok()?);
        let len = u32::from_le_bytes(head[9..13].try_into().ok()?) as usize;
        let data = buf.get(at + HEADER..at + HEADER + len)?;
        at += HEADER + len;
        Some(Record {
            channel,
            t_ns,
            data,
        })
    })
}

struct Sealed {
    start_ns: u64,
    end_ns: u64,
    /// The sequence number of its first record, and how many it holds.
    first_seq: u64,
    count: u64,
    compressed: Vec<u8>,
    raw_len: usize,
}

/// What the ring holds and has dropped.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct RingStats {
    /// Bytes held (sealed, compressed, and the open segment).
    pub bytes: usize,
    /// Messages appended.
    pub messages: u64,
    /// Segments dropped to keep within the cap or the span.
    pub dropped_segments: u64,
    /// Raw bytes sealed, and what they took compressed (the compression ratio).
    pub sealed_raw_bytes: u64,
    /// Compressed bytes sealed.
    pub sealed_compressed_bytes: u64,
    /// Sealed segments that could not be read back (their records lost to a box).
    pub unreadable_segments: u64,
    /// Records dropped before a box's copy reached them (a copy slower than the ring).
    pub dropped_before_copied: u64,
}

/// The ring.
pub struct Ring {
    sealed: VecDeque<Sealed>,
    open: Vec<u8>,
    /// One zstd context for every seal, and a buffer of the bound's size that each result is
    /// copied out of at its own size (`zstd::bulk::compress` returns a vector with the bound
    /// as its capacity, which each sealed segment kept).
    compressor: Option<zstd::bulk::Compressor<'static>>,
    scratch: Vec<u8>,
    /// The sequence number the next record pushed gets, and the open segment's first.
    next_seq: u64,
    open_first_seq: u64,
    /// The sealed segment last read back, decompressed (a copy into a box reads one segment
    /// in several steps).
    cache: Option<(u64, Vec<u8>)>,
    open_start_ns: Option<u64>,
    open_end_ns: u64,
    segment_ns: u64,
    span_ns: u64,
    cap_bytes: usize,
    stats: RingStats,
}

impl Ring {
    /// A ring keeping at least `span_ns` of messages when they fit in `cap_bytes`, sealed in
    /// segments of `segment_ns`.
    pub fn new(span_ns: u64, segment_ns: u64, cap_bytes: usize) -> Ring {
        Ring {
            sealed: VecDeque::new(),
            open: Vec::new(),
            compressor: zstd::bulk::Compressor::new(3).ok(),
            scratch: Vec::new(),
            next_seq: 0,
            open_first_seq: 0,
            cache: None,
            open_start_ns: None,
            open_end_ns: 0,
            segment_ns: segment_ns.max(1),
            span_ns,
            cap_bytes,
            stats: RingStats::default(),
        }
    }

    /// Appends a message; seals the open segment once it spans a segment's time.
    pub fn push(&mut self, r: Record) {
        let start = *self.open_start_ns.get_or_insert(r.t_ns);
        append(&mut self.open, r);
        self.next_seq += 1;
        self.open_end_ns = self.open_end_ns.max(r.t_ns);
        self.stats.messages += 1;
        if r.t_ns.saturating_sub(start) >= self.segment_ns {
            self.seal();
        }
    }

    /// Compresses the open segment into the sealed ones, then drops the oldest beyond the
    /// cap or older than the span.
    pub fn seal(&mut self) {
        let Some(start_ns) = self.open_start_ns.take() else {
            return;
        };
        let compressed = self.compress();
        self.stats.sealed_raw_bytes += self.open.len() as u64;
        self.stats.sealed_compressed_bytes += compressed.len() as u64;
        self.sealed.push_back(Sealed {
            start_ns,
            end_ns: self.open_end_ns,
            first_seq: self.open_first_seq,
            count: self.next_seq - self.open_first_seq,
            raw_len: self.open.len(),
            compressed,
        });
        self.open.clear();
        self.open_first_seq = self.next_seq;
        let newest = self.open_end_ns;
        while let Some(oldest) = self.sealed.front() {
            let too_old = newest.saturating_sub(oldest.end_ns) > self.span_ns;
            if self.held_bytes() <= self.cap_bytes && !too_old {
                break;
            }
            self.sealed.pop_front();
            self.stats.dropped_segments += 1;
        }
    }

    /// The open segment compressed (zstd's level 3: a fraction of a core at the ring's rate,
    /// BENCHMARKS.md), in a vector of its own size; empty if zstd fails (the segment is then
    /// lost, and reported when read).
    fn compress(&mut self) -> Vec<u8> {
        let Some(c) = self.compressor.as_mut() else {
            return Vec::new();
        };
        self.scratch.clear();
        self.scratch
            .reserve(zstd::zstd_safe::compress_bound(self.open.len()));
        match c.compress_to_buffer(&self.open, &mut self.scratch) {
            Ok(n) => self.scratch[..n].to_vec(),
            Err(_) => Vec::new(),
        }
    }

    /// What it holds in memory: the sealed segments' allocations, the open one's and the
    /// compression buffer's.
    fn held_bytes(&self) -> usize {
        self.sealed
            .iter()
            .map(|s| s.compressed.capacity())
            .sum::<usize>()
            + self.open.capacity()
            + self.scratch.capacity()
    }

    /// What it holds and has dropped.
    pub fn stats(&self) -> RingStats {
        RingStats {
            bytes: self.held_bytes(),
            ..self.stats
        }
    }

    /// The oldest time it holds.
    pub fn oldest_ns(&self) -> Option<u64> {
        self.sealed
            .front()
            .map(|s| s.start_ns)
            .or(self.open_start_ns)
    }

    /// The sequence number of the oldest record held.
    pub fn oldest_seq(&self) -> u64 {
        self.sealed
            .front()
            .map_or(self.open_first_seq, |s| s.first_seq)
    }

    /// The sequence number the next record pushed will get: a cursor there has read all.
    pub fn next_seq(&self) -> u64 {
        self.next_seq
    }

    /// Up to `max` records from sequence number `cursor` on, oldest first, to `f`; the cursor
    /// after them. Records dropped before the cursor reached them are skipped (the cursor
    /// moves to the oldest held), and so is a sealed segment that cannot be read (counted in
    /// [`RingStats::unreadable_segments`]).
    pub fn read_from(&mut self, cursor: u64, max: usize, f: &mut dyn FnMut(Record)) -> u64 {
        let oldest = self.oldest_seq();
        self.stats.dropped_before_copied += oldest.saturating_sub(cursor);
        let mut cursor = cursor.max(oldest);
        let mut left = max;
        while left > 0 && cursor < self.next_seq {
            let sealed = self
                .sealed
                .iter()
                .find(|s| cursor < s.first_seq + s.count)
                .map(|s| (s.first_seq, s.first_seq + s.count));
            let (first, end) = sealed.unwrap_or((self.open_first_seq, self.next_seq));
            let raw = match sealed {
                Some(_) => match self.decompressed(first) {
                    Ok(raw) => raw,
                    Err(_) => {
                        self.stats.unreadable_segments += 1;
                        cursor = end;
                        continue;
                    }
                },
                None => self.open.as_slice(),
            };
            let mut n = 0;
            for r in records(raw).skip((cursor - first) as usize).take(left) {
                f(r);
                n += 1;
            }
            cursor += n as u64;
            left -= n;
            if n == 0 {
                // A torn segment: what it lacks is lost; on from the next.
                cursor = end;
            }
        }
        cursor
    }

    /// The records of the sealed segment starting at `first`, decompressed once and kept.
    fn decompressed(&mut self, first: u64) -> Result<&[u8], RingError> {
        if self.cache.as_ref().is_none_or(|(f, _)| *f != first) {
            let Some(s) = self.sealed.iter().find(|s| s.first_seq == first) else {
                return Ok(&[]);
            };
            let raw = zstd::bulk::decompress(&s.compressed, s.raw_len).map_err(|e| RingError {
                start_ns: s.start_ns,
                end_ns: s.end_ns,
                why: e.to_string(),
            })?;
            self.cache = Some((first, raw));
        }
        Ok(self
            .cache
            .as_ref()
            .map_or(&[][..], |(_, raw)| raw.as_slice()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn msg(t_ns: u64) -> Vec<u8> {
        format!(
            "{{\"timestamp_ns\": {t_ns}, \"pad\": \"{}\"}}",
            "x".repeat(100)
        )
        .into_bytes()
    }

    fn all_since(ring: &mut Ring, since: u64) -> Vec<u64> {
        let mut out = Vec::new();
        let end = ring.read_from(0, usize::MAX, &mut |r| {
            assert_eq!(r.data, msg(r.t_ns).as_slice());
            if r.t_ns >= since {
                out.push(r.t_ns)
            }
        });
        assert_eq!(end, ring.next_seq());
        out
    }

    #[test]
    fn what_is_pushed_comes_back_in_order_across_sealed_and_open_segments() {
        let mut ring = Ring::new(1_000, 100, usize::MAX);
        for t in 0..350u64 {
            let data = msg(t);
            ring.push(Record {
                channel: Channel::JointStates,
                t_ns: t,
                data: &data,
            });
        }
        assert_eq!(all_since(&mut ring, 0), (0..350).collect::<Vec<_>>());
        assert_eq!(all_since(&mut ring, 200), (200..350).collect::<Vec<_>>());
        let s = ring.stats();
        assert!(s.sealed_compressed_bytes * 5 < s.sealed_raw_bytes, "{s:?}");
    }

    #[test]
    fn a_cursor_reads_in_steps_across_segments_and_skips_what_was_dropped() {
        let mut ring = Ring::new(300, 100, usize::MAX);
        let push = |ring: &mut Ring, t: u64| {
            let data = msg(t);
            ring.push(Record {
                channel: Channel::Wire,
                t_ns: t,
                data: &data,
            })
        };
        for t in 0..250u64 {
            push(&mut ring, t);
        }
        let mut got = Vec::new();
        let mut cursor = 0;
        for _ in 0..10 {
            cursor = ring.read_from(cursor, 7, &mut |r| got.push(r.t_ns));
        }
        assert_eq!(
            got,
            (0..70).collect::<Vec<_>>(),
            "steps of 7, in order, none twice"
        );
        // The ring drops what the cursor had not reached: it goes on from the oldest held.
        for t in 250..1_000u64 {
            push(&mut ring, t);
        }
        let mut rest = Vec::new();
        let end = ring.read_from(cursor, usize::MAX, &mut |r| rest.push(r.t_ns));
        assert_eq!(end, ring.next_seq());
        assert!(rest[0] > 400, "{}", rest[0]);
        assert!(rest.windows(2).all(|w| w[1] == w[0] + 1));
        assert_eq!(*rest.last().unwrap(), 999);
    }

    #[test]
    fn sealed_segments_hold_only_their_compressed_bytes() {
        // Found on the whole robot: each sealed segment kept a vector of its raw size (88 MB
        // resident after 3 minutes, for 9 MB of ring).
        let mut ring = Ring::new(u64::MAX, 100, usize::MAX);
        for t in 0..2_000u64 {
            let data = msg(t);
            ring.push(Record {
                channel: Channel::JointStates,
                t_ns: t,
                data: &data,
            });
        }
        let s = ring.stats();
        let sealed: usize = ring.sealed.iter().map(|s| s.compressed.capacity()).sum();
        assert_eq!(sealed as u64, s.sealed_compressed_bytes, "{s:?}");
    }

    #[test]
    fn the_oldest_segments_go_beyond_the_span_and_beyond_the_cap() {
        let mut ring = Ring::new(300, 100, usize::MAX);
        for t in 0..1_000u64 {
            let data = msg(t);
            ring.push(Record {
                channel: Channel::Wire,
                t_ns: t,
                data: &data,
            });
        }
        let kept = all_since(&mut ring, 0);
        assert!(kept[0] >= 1_000 - 300 - 200, "{:?}", &kept[..3]);
        assert_eq!(*kept.last().unwrap(), 999);
        assert!(ring.stats().dropped_segments >= 5);

        let mut small = Ring::new(u64::MAX, 100, 4_000);
        for t in 0..10_000u64 {
            let data = format!("{t:x}{}", t.wrapping_mul(0x9E37_79B9_7F4A_7C15)).into_bytes();
            small.push(Record {
                channel: Channel::Wire,
                t_ns: t,
                data: &data,
            });
        }
        assert!(small.stats().bytes <= 4_000 + 16_384, "{:?}", small.stats());
        assert!(small.oldest_ns().unwrap() > 5_000);
    }
}
