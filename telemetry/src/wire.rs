//! What went on one bus's wire in one control cycle, byte for byte: the driver's tap fills a
//! [`WireFrame`] as it sends and receives (a copy into fixed buffers, no allocation), and
//! publishes it once per cycle for the black box.

use iceoryx2::prelude::ZeroCopySend;

/// Chunks (one `send` or one non-empty `receive` each) a frame holds.
pub const MAX_WIRE_CHUNKS: usize = 64;
/// Bytes a frame holds: a cycle of a 7-servo bus moves about 230 (the SYNC_READ, seven
/// 21-byte replies, the SYNC_WRITE), a set-up or read-back a few dozen more.
pub const WIRE_BYTES: usize = 2048;

/// Which way a chunk went, or what happened to the line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum Direction {
    /// Host → servos (an instruction).
    Sent = 0,
    /// Servos → host (replies, or whatever the line carried).
    Received = 1,
    /// A write that failed: the bytes asked for (some may have gone out).
    SendFailed = 2,
    /// Input not yet read was dropped (a transaction starts); no bytes.
    Discarded = 3,
    /// The device was opened again after a failure; no bytes.
    Reopened = 4,
    /// The line rate changed: the new rate, 4 bytes little-endian.
    BaudChanged = 5,
}

impl Direction {
    /// Every direction, by its byte.
    pub const ALL: [Direction; 6] = [
        Direction::Sent,
        Direction::Received,
        Direction::SendFailed,
        Direction::Discarded,
        Direction::Reopened,
        Direction::BaudChanged,
    ];

    /// The direction of a chunk's byte.
    pub fn from_byte(b: u8) -> Option<Direction> {
        Direction::ALL.get(b as usize).copied()
    }

    /// Its name in a box (`sent`, `received`, `send_failed`, …).
    pub fn name(self) -> &'static str {
        match self {
            Direction::Sent => "sent",
            Direction::Received => "received",
            Direction::SendFailed => "send_failed",
            Direction::Discarded => "discarded",
            Direction::Reopened => "reopened",
            Direction::BaudChanged => "baud_changed",
        }
    }

    /// The direction named `name`.
    pub fn from_name(name: &str) -> Option<Direction> {
        Direction::ALL.into_iter().find(|d| d.name() == name)
    }
}

/// One chunk's place in [`WireFrame::bytes`].
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
pub struct WireChunk {
    /// When the chunk was written, or read, on the common clock (CLOCK_MONOTONIC, ns).
    pub t_ns: u64,
    /// Offset in `bytes`.
    pub offset: u16,
    /// Length in `bytes`.
    pub len: u16,
    /// [`Direction`] as a byte.
    pub direction: u8,
    /// Reserved, zero.
    pub reserved: [u8; 3],
}

/// One bus's traffic in one cycle.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[type_name("nori::WireFrame/1")]
pub struct WireFrame {
    /// The driver's cycle (its joint-state `seq`) this traffic ended with.
    pub cycle: u64,
    /// Bus index in the driver's layout.
    pub bus: u32,
    /// Chunks in use.
    pub chunk_count: u32,
    /// Bytes in use.
    pub byte_count: u32,
    /// Bytes of this cycle that did not fit (counted, never silently lost).
    pub lost_bytes: u32,
    /// The chunks, in the order they happened.
    pub chunks: [WireChunk; MAX_WIRE_CHUNKS],
    /// Their bytes, back to back.
    pub bytes: [u8; WIRE_BYTES],
}

impl Default for WireFrame {
    fn default() -> Self {
        WireFrame {
            cycle: 0,
            bus: 0,
            chunk_count: 0,
            byte_count: 0,
            lost_bytes: 0,
            chunks: [WireChunk::default(); MAX_WIRE_CHUNKS],
            bytes: [0; WIRE_BYTES],
        }
    }
}

impl WireFrame {
    /// Whether a chunk of `len` bytes fits.
    pub fn fits(&self, len: usize) -> bool {
        (self.chunk_count as usize) < MAX_WIRE_CHUNKS
            && self.byte_count as usize + len <= WIRE_BYTES
    }

    /// Appends one chunk; what does not fit is counted in `lost_bytes`.
    pub fn record(&mut self, direction: Direction, t_ns: u64, bytes: &[u8]) {
        let start = self.byte_count as usize;
        let data = matches!(direction, Direction::Sent | Direction::Received);
        if bytes.is_empty() && data {
            return;
        }
        if !self.fits(bytes.len()) {
            self.lost_bytes = self.lost_bytes.saturating_add(bytes.len() as u32);
            return;
        }
        self.bytes[start..start + bytes.len()].copy_from_slice(bytes);
        self.chunks[self.chunk_count as usize] = WireChunk {
            t_ns,
            offset: start as u16,
            len: bytes.len() as u16,
            direction: direction as u8,
            reserved: [0; 3],
        };
        self.chunk_count += 1;
        self.byte_count += bytes.len() as u32;
    }

    /// Empties the frame for the next cycle (the buffers are kept).
    pub fn clear(&mut self) {
        self.chunk_count = 0;
        self.byte_count = 0;
        self.lost_bytes = 0;
    }

    /// Whether nothing was recorded (or lost) since the last [`WireFrame::clear`].
    pub fn is_empty(&self) -> bool {
        self.chunk_count == 0 && self.lost_bytes == 0
    }

    /// The chunks in use: direction, time and bytes (a chunk with a corrupted place is skipped).
    pub fn chunks(&self) -> impl Iterator<Item = (Direction, u64, &[u8])> {
        self.chunks[..(self.chunk_count as usize).min(MAX_WIRE_CHUNKS)]
            .iter()
            .filter_map(|c| {
                let bytes = self
                    .bytes
                    .get(c.offset as usize..c.offset as usize + c.len as usize)?;
                Some((Direction::from_byte(c.direction)?, c.t_ns, bytes))
            })
    }
}

/// An operator's `nori blackbox save`: freeze the last minutes now.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("nori::BlackboxSave/1")]
pub struct BlackboxSave {
    /// The requester's sequence number.
    pub seq: u64,
    /// When it was asked, on the common clock.
    pub timestamp_ns: u64,
    /// The requester's process id.
    pub pid: u32,
    /// Reserved, zero.
    pub reserved: u32,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chunks_come_back_in_order_and_what_does_not_fit_is_counted() {
        let mut f = WireFrame::default();
        f.record(Direction::Sent, 10, &[0xFF, 0xFF, 1, 2]);
        f.record(Direction::Received, 20, &[]);
        f.record(Direction::Received, 30, &[0xFF, 0xFF, 1, 3, 0]);
        let got: Vec<_> = f.chunks().map(|(d, t, b)| (d, t, b.to_vec())).collect();
        assert_eq!(
            got,
            vec![
                (Direction::Sent, 10, vec![0xFF, 0xFF, 1, 2]),
                (Direction::Received, 30, vec![0xFF, 0xFF, 1, 3, 0]),
            ]
        );
        f.record(Direction::Sent, 40, &[7; WIRE_BYTES]);
        assert_eq!(f.lost_bytes, WIRE_BYTES as u32);
        assert_eq!(f.chunks().count(), 2);
        for k in 0..MAX_WIRE_CHUNKS {
            f.record(Direction::Sent, 50 + k as u64, &[1]);
        }
        assert_eq!(f.chunk_count as usize, MAX_WIRE_CHUNKS);
        assert_eq!(f.lost_bytes, WIRE_BYTES as u32 + 2);
        f.clear();
        assert!(f.is_empty());
        assert_eq!(f.chunks().count(), 0);
        f.record(Direction::Discarded, 60, &[]);
        f.record(Direction::Received, 61, &[]);
        let marks: Vec<_> = f.chunks().map(|(d, t, b)| (d, t, b.len())).collect();
        assert_eq!(
            marks,
            vec![(Direction::Discarded, 60, 0)],
            "a mark has no bytes, data has"
        );
        for d in Direction::ALL {
            assert_eq!(Direction::from_byte(d as u8), Some(d));
            assert_eq!(Direction::from_name(d.name()), Some(d));
        }
    }
}
