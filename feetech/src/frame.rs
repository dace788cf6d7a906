//! Framing shared by both directions: header, checksum, and the incremental decoder.
//!
//! Instruction and status packets share one layout (`FF FF ID LEN X P.. CHK`); only the meaning
//! of the fifth byte differs (instruction code or error byte). The decoder therefore yields
//! [`Frame`]s, and [`crate::status`] / [`crate::instruction`] give them meaning.

use crate::{MAX_LEN, MAX_PACKET};
use thiserror::Error;

/// The checksum of a packet: `!(id + len + code + Σ params) & 0xFF`.
pub fn checksum(id: u8, len: u8, code: u8, params: &[u8]) -> u8 {
    let sum = params
        .iter()
        .fold(id.wrapping_add(len).wrapping_add(code), |acc, b| {
            acc.wrapping_add(*b)
        });
    !sum
}

/// Writes a whole packet `FF FF id len code params chk` into `out`, returning its length.
/// Returns `None` if `params` is too long for one packet or `out` too small.
pub fn write_packet(out: &mut [u8], id: u8, code: u8, params: &[u8]) -> Option<usize> {
    let len = params.len() + 2;
    if len > MAX_LEN as usize || out.len() < len + 4 {
        return None;
    }
    let len_byte = len as u8;
    out[0] = 0xFF;
    out[1] = 0xFF;
    out[2] = id;
    out[3] = len_byte;
    out[4] = code;
    out[5..5 + params.len()].copy_from_slice(params);
    out[5 + params.len()] = checksum(id, len_byte, code, params);
    Some(len + 4)
}

/// One checksum-valid packet, either direction. Parameters are stored inline (no allocation).
#[derive(Clone, PartialEq, Eq)]
pub struct Frame {
    /// Servo id (or broadcast id for instructions).
    pub id: u8,
    /// Instruction code (host → servo) or error byte (servo → host).
    pub code: u8,
    params_len: u8,
    params: [u8; MAX_LEN as usize - 2],
}

impl Frame {
    /// The parameter bytes.
    pub fn params(&self) -> &[u8] {
        &self.params[..self.params_len as usize]
    }

    /// Builds a frame from parts (used by tests and by the device side when echoing).
    pub fn new(id: u8, code: u8, params: &[u8]) -> Option<Self> {
        if params.len() > MAX_LEN as usize - 2 {
            return None;
        }
        let mut frame = Frame {
            id,
            code,
            params_len: params.len() as u8,
            params: [0; MAX_LEN as usize - 2],
        };
        frame.params[..params.len()].copy_from_slice(params);
        Some(frame)
    }

    /// Encodes the frame back into bytes, returning the length written.
    pub fn encode(&self, out: &mut [u8]) -> Option<usize> {
        write_packet(out, self.id, self.code, self.params())
    }
}

impl std::fmt::Debug for Frame {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Frame")
            .field("id", &self.id)
            .field("code", &format_args!("{:#04x}", self.code))
            .field("params", &self.params())
            .finish()
    }
}

/// Why bytes in the stream were not a packet. Each error consumed the bytes it names, so the
/// decoder can go on: these are counters for telemetry, not reasons to stop.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum DecodeError {
    /// Bytes before the next `FF FF` header were skipped.
    #[error("skipped {bytes} bytes of garbage before a header")]
    Garbage {
        /// How many bytes were dropped.
        bytes: usize,
    },
    /// A header whose id byte cannot be an id (0xFF).
    #[error("invalid id {id:#04x} after header")]
    InvalidId {
        /// The id byte seen.
        id: u8,
    },
    /// A header whose LEN byte is outside 2..=250.
    #[error("invalid length {len} for id {id}")]
    InvalidLength {
        /// The id byte of the header.
        id: u8,
        /// The LEN byte seen.
        len: u8,
    },
    /// A complete packet whose checksum does not match.
    #[error("checksum mismatch for id {id}: expected {expected:#04x}, got {actual:#04x}")]
    Checksum {
        /// The id byte of the packet.
        id: u8,
        /// The checksum computed over the received bytes.
        expected: u8,
        /// The checksum byte received.
        actual: u8,
    },
    /// [`Decoder::finish`] dropped a header whose packet never completed.
    #[error("truncated packet for id {id}: {have} of {need} bytes")]
    Truncated {
        /// The id byte of the header.
        id: u8,
        /// Bytes received.
        have: usize,
        /// Bytes the header announced.
        need: usize,
    },
}

const BUFFER: usize = 2 * MAX_PACKET + 8;

/// Incremental packet decoder: push bytes as they arrive, pull frames and errors.
///
/// It never panics and never allocates. On any framing error it drops one byte and searches the
/// next `FF FF`, so a valid packet after garbage is always found. A header announcing more bytes
/// than ever arrive would hold the packets behind it; [`Decoder::finish`] (called when the
/// transaction's deadline passes) gives up on it and recovers what follows.
#[derive(Clone)]
pub struct Decoder {
    buf: [u8; BUFFER],
    start: usize,
    end: usize,
}

impl Default for Decoder {
    fn default() -> Self {
        Self::new()
    }
}

impl Decoder {
    /// An empty decoder.
    pub const fn new() -> Self {
        Decoder {
            buf: [0; BUFFER],
            start: 0,
            end: 0,
        }
    }

    /// Drops all buffered bytes.
    pub fn clear(&mut self) {
        self.start = 0;
        self.end = 0;
    }

    /// Bytes buffered and not yet decoded.
    pub fn buffered(&self) -> usize {
        self.end - self.start
    }

    /// Appends bytes, returning how many were taken. Fewer than `bytes.len()` are taken only when
    /// the buffer is full: drain with [`Decoder::next_frame`] and push the rest.
    pub fn push(&mut self, bytes: &[u8]) -> usize {
        if self.start > 0 && self.end + bytes.len() > BUFFER {
            self.buf.copy_within(self.start..self.end, 0);
            self.end -= self.start;
            self.start = 0;
        }
        let n = bytes.len().min(BUFFER - self.end);
        self.buf[self.end..self.end + n].copy_from_slice(&bytes[..n]);
        self.end += n;
        n
    }

    /// The next frame or framing error, or `None` when more bytes are needed.
    pub fn next_frame(&mut self) -> Option<Result<Frame, DecodeError>> {
        self.decode(false)
    }

    /// Like [`Decoder::next_frame`], but at the end of input: an incomplete packet at the front is
    /// dropped as [`DecodeError::Truncated`] so that packets behind a corrupted header are found.
    /// Call it repeatedly until it returns `None`; leftover bytes that may begin a header stay.
    pub fn finish(&mut self) -> Option<Result<Frame, DecodeError>> {
        self.decode(true)
    }

    fn decode(&mut self, at_end: bool) -> Option<Result<Frame, DecodeError>> {
        let data = &self.buf[self.start..self.end];
        // Find the header: the first "FF FF", or a lone trailing FF that may become one.
        let header = data.windows(2).position(|w| w == [0xFF, 0xFF]);
        let skip = match header {
            Some(p) => p,
            None if data.last() == Some(&0xFF) => data.len() - 1,
            None => data.len(),
        };
        if skip > 0 {
            self.start += skip;
            return Some(Err(DecodeError::Garbage { bytes: skip }));
        }
        if data.len() < 4 {
            return None;
        }
        let (id, len) = (data[2], data[3]);
        if id == 0xFF {
            // "FF FF FF": the header may start one byte later.
            self.start += 1;
            return Some(Err(DecodeError::InvalidId { id }));
        }
        if !(2..=MAX_LEN).contains(&len) {
            self.start += 1;
            return Some(Err(DecodeError::InvalidLength { id, len }));
        }
        let total = 4 + len as usize;
        if data.len() < total {
            if at_end {
                self.start += 1;
                return Some(Err(DecodeError::Truncated {
                    id,
                    have: data.len(),
                    need: total,
                }));
            }
            return None;
        }
        let code = data[4];
        let params = &data[5..total - 1];
        let actual = data[total - 1];
        let expected = checksum(id, len, code, params);
        if expected != actual {
            self.start += 1;
            return Some(Err(DecodeError::Checksum {
                id,
                expected,
                actual,
            }));
        }
        let frame = Frame::new(id, code, params);
        self.start += total;
        if self.start == self.end {
            self.start = 0;
            self.end = 0;
        }
        // `params.len() == len - 2 <= 248`, so `Frame::new` cannot fail here.
        frame.map(Ok)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode_all(bytes: &[u8]) -> (Vec<Frame>, Vec<DecodeError>) {
        let mut d = Decoder::new();
        let (mut frames, mut errors) = (vec![], vec![]);
        let mut rest = bytes;
        loop {
            let n = d.push(rest);
            rest = &rest[n..];
            while let Some(r) = d.next_frame() {
                match r {
                    Ok(f) => frames.push(f),
                    Err(e) => errors.push(e),
                }
            }
            if rest.is_empty() {
                break;
            }
        }
        while let Some(r) = d.finish() {
            match r {
                Ok(f) => frames.push(f),
                Err(e) => errors.push(e),
            }
        }
        (frames, errors)
    }

    #[test]
    fn golden_ping_reply() {
        let (frames, errors) = decode_all(&[0xFF, 0xFF, 0x01, 0x02, 0x00, 0xFC]);
        assert!(errors.is_empty());
        assert_eq!(frames.len(), 1);
        assert_eq!((frames[0].id, frames[0].code), (1, 0));
        assert!(frames[0].params().is_empty());
    }

    #[test]
    fn checksum_error_names_both_values() {
        let (frames, errors) = decode_all(&[0xFF, 0xFF, 0x01, 0x02, 0x00, 0xFD]);
        assert!(frames.is_empty());
        assert_eq!(
            errors[0],
            DecodeError::Checksum {
                id: 1,
                expected: 0xFC,
                actual: 0xFD
            }
        );
    }

    #[test]
    fn packet_split_in_single_bytes() {
        let mut d = Decoder::new();
        let bytes = [0xFF, 0xFF, 0x01, 0x04, 0x00, 0x18, 0x05, 0xDD];
        for (i, b) in bytes.iter().enumerate() {
            d.push(&[*b]);
            let r = d.next_frame();
            if i < bytes.len() - 1 {
                assert!(r.is_none(), "early result at byte {i}: {r:?}");
            } else {
                assert_eq!(r.unwrap().unwrap().params(), &[0x18, 0x05]);
            }
        }
    }

    #[test]
    fn header_claiming_too_much_is_dropped_at_finish() {
        // A corrupted header announcing 200 bytes, then a good reply.
        let mut bytes = vec![0xFF, 0xFF, 0x07, 200, 0x00];
        bytes.extend_from_slice(&[0xFF, 0xFF, 0x01, 0x02, 0x00, 0xFC]);
        let (frames, errors) = decode_all(&bytes);
        assert_eq!(frames.len(), 1);
        assert!(matches!(errors[0], DecodeError::Truncated { id: 7, .. }));
    }

    #[test]
    fn triple_ff_resyncs() {
        let (frames, _) = decode_all(&[0xFF, 0xFF, 0xFF, 0x01, 0x02, 0x00, 0xFC]);
        assert_eq!(frames.len(), 1);
        assert_eq!(frames[0].id, 1);
    }
}
