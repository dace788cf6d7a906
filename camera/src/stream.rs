//! A camera on a byte stream (a Unix socket): how the simulated cameras deliver their frames, one
//! V4L2-like buffer at a time, and what `nori-camera` reads when its device is `socket:PATH`.
//!
//! Each frame is a 32-byte header, then its bytes:
//!
//! | bytes | field |
//! |---|---|
//! | 0..4 | magic `NCAM` |
//! | 4..8 | V4L2 four-character code (`YUYV`, `MJPG`, `RGB3`) |
//! | 8..12, 12..16 | width, height (u32, little-endian) |
//! | 16..20 | the device's frame sequence (u32; a gap is a frame the device dropped) |
//! | 20..24 | payload length (u32) |
//! | 24..32 | capture time, ns on CLOCK_MONOTONIC (u64): the device's timestamp |
//!
//! The reader is sans-IO: bytes in, frames out. A header that does not start with the magic, or
//! announces a payload larger than the camera can send, loses the stream's framing: the reader
//! counts it and searches for the next magic, as a V4L2 driver drops a bad buffer.

use telemetry::sensors::PixelFormat;

/// Bytes of a frame header.
pub const HEADER_LEN: usize = 32;
/// The magic that opens a header.
pub const MAGIC: [u8; 4] = *b"NCAM";

/// A frame's header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StreamHeader {
    /// V4L2 four-character code.
    pub fourcc: [u8; 4],
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// The device's sequence number.
    pub sequence: u32,
    /// Payload bytes.
    pub len: u32,
    /// Capture time, ns (CLOCK_MONOTONIC).
    pub capture_ns: u64,
}

impl StreamHeader {
    /// The header's bytes.
    pub fn encode(&self) -> [u8; HEADER_LEN] {
        let mut b = [0u8; HEADER_LEN];
        b[0..4].copy_from_slice(&MAGIC);
        b[4..8].copy_from_slice(&self.fourcc);
        b[8..12].copy_from_slice(&self.width.to_le_bytes());
        b[12..16].copy_from_slice(&self.height.to_le_bytes());
        b[16..20].copy_from_slice(&self.sequence.to_le_bytes());
        b[20..24].copy_from_slice(&self.len.to_le_bytes());
        b[24..32].copy_from_slice(&self.capture_ns.to_le_bytes());
        b
    }

    fn decode(b: &[u8; HEADER_LEN]) -> Self {
        let u32_at = |i: usize| u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
        let mut ns = [0u8; 8];
        ns.copy_from_slice(&b[24..32]);
        StreamHeader {
            fourcc: [b[4], b[5], b[6], b[7]],
            width: u32_at(8),
            height: u32_at(12),
            sequence: u32_at(16),
            len: u32_at(20),
            capture_ns: u64::from_le_bytes(ns),
        }
    }

    /// The pixel format, if known.
    pub fn format(&self) -> Option<PixelFormat> {
        PixelFormat::from_fourcc(self.fourcc)
    }
}

/// Reads frames out of a byte stream.
#[derive(Debug)]
pub struct StreamReader {
    buf: Vec<u8>,
    max_len: usize,
    /// Bytes of the frame last returned, dropped at the next call.
    consumed: usize,
    /// Times the framing was lost (no magic where a header should be, an impossible length).
    pub resyncs: u64,
    /// Bytes skipped while searching for a header.
    pub skipped_bytes: u64,
}

impl StreamReader {
    /// A reader of frames of at most `max_len` payload bytes.
    pub fn new(max_len: usize) -> Self {
        StreamReader {
            buf: Vec::with_capacity(max_len + HEADER_LEN),
            max_len,
            consumed: 0,
            resyncs: 0,
            skipped_bytes: 0,
        }
    }

    /// Takes bytes from the stream.
    pub fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
    }

    /// Whether a whole frame is buffered (garbage before it is skipped, and counted, here).
    pub fn has_frame(&mut self) -> bool {
        self.buf.drain(..std::mem::take(&mut self.consumed));
        loop {
            let Some(header) = self.header() else {
                return false;
            };
            if header.len as usize > self.max_len || self.buf[..4] != MAGIC {
                self.resync();
                continue;
            }
            return self.buf.len() >= HEADER_LEN + header.len as usize;
        }
    }

    /// The next whole frame, if one is buffered: its header and payload. The payload is valid
    /// until the next call.
    pub fn next_frame(&mut self) -> Option<(StreamHeader, &[u8])> {
        if !self.has_frame() {
            return None;
        }
        let header = self.header()?;
        // The frame stays at the front of the buffer until the next call drops it.
        self.consumed = HEADER_LEN + header.len as usize;
        Some((header, &self.buf[HEADER_LEN..self.consumed]))
    }

    fn header(&self) -> Option<StreamHeader> {
        let head: &[u8; HEADER_LEN] = self.buf.get(..HEADER_LEN)?.try_into().ok()?;
        Some(StreamHeader::decode(head))
    }

    /// Drops the bytes up to the next magic after the current position.
    fn resync(&mut self) {
        self.resyncs += 1;
        let next = self.buf[1..]
            .windows(MAGIC.len())
            .position(|w| w == MAGIC)
            .map_or(self.buf.len() - (MAGIC.len() - 1), |p| p + 1);
        self.skipped_bytes += next as u64;
        self.buf.drain(..next);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(sequence: u32, payload: &[u8]) -> Vec<u8> {
        let header = StreamHeader {
            fourcc: *b"YUYV",
            width: 2,
            height: 1,
            sequence,
            len: payload.len() as u32,
            capture_ns: 1_000 + u64::from(sequence),
        };
        let mut bytes = header.encode().to_vec();
        bytes.extend_from_slice(payload);
        bytes
    }

    #[test]
    fn frames_come_out_whole_however_the_bytes_arrive() {
        let stream: Vec<u8> = [frame(1, &[1, 2, 3, 4]), frame(2, &[5, 6, 7, 8])].concat();
        for chunk in [1, 3, 7, 32, 33, stream.len()] {
            let mut r = StreamReader::new(16);
            let mut got = Vec::new();
            for piece in stream.chunks(chunk) {
                r.push(piece);
                while let Some((h, p)) = r.next_frame() {
                    assert_eq!(h.format(), Some(PixelFormat::Yuyv));
                    assert_eq!(h.capture_ns, 1_000 + u64::from(h.sequence));
                    got.push((h.sequence, p.to_vec()));
                }
            }
            assert_eq!(
                got,
                [(1, vec![1, 2, 3, 4]), (2, vec![5, 6, 7, 8])],
                "chunk {chunk}"
            );
            assert_eq!(r.resyncs, 0);
        }
    }

    #[test]
    fn garbage_and_an_impossible_length_cost_a_resync_not_the_next_frame() {
        let mut too_long = frame(2, &[0; 4]);
        too_long[20..24].copy_from_slice(&1_000u32.to_le_bytes());
        let stream = [
            vec![0xAB; 40],
            frame(1, &[9; 4]),
            too_long,
            frame(3, &[7; 4]),
        ]
        .concat();
        let mut r = StreamReader::new(16);
        r.push(&stream);
        let mut got = Vec::new();
        while let Some((h, p)) = r.next_frame() {
            got.push((h.sequence, p[0]));
        }
        assert_eq!(got, [(1, 9), (3, 7)]);
        assert_eq!(r.resyncs, 2);
        assert_eq!(r.skipped_bytes, 40 + HEADER_LEN as u64 + 4);
    }

    #[test]
    fn a_header_round_trips() {
        let h = StreamHeader {
            fourcc: *b"MJPG",
            width: 1280,
            height: 720,
            sequence: u32::MAX,
            len: 123_456,
            capture_ns: u64::MAX - 5,
        };
        assert_eq!(StreamHeader::decode(&h.encode()), h);
        assert_eq!(h.format(), Some(PixelFormat::Mjpeg));
    }
}
