//! The lift board's serial protocol, sans-IO: bytes in, messages out.
//!
//! ```text
//! frame   A5 | type | len | payload (len bytes) | crc16 (CRC-16/CCITT-FALSE over type, len, payload; little-endian)
//! host → board   0x01 DRIVE    i16 velocity, 0.1 mm/s (up positive); the board stops the motor
//!                              when no DRIVE came within its watchdog time (100 ms)
//! board → host   0x81 STATUS   i32 hall counts (up positive), u16 current mA, u8 switches
//!                              (bit 0 lower, bit 1 upper), u8 faults (bit 0 over-current,
//!                              bit 1 watchdog stop), sent every 10 ms
//! ```
//! A frame whose CRC or length does not check is dropped and counted; the decoder resyncs on
//! the next start byte.

/// Start of every frame.
pub const START: u8 = 0xA5;
/// Host → board: drive.
pub const DRIVE: u8 = 0x01;
/// Board → host: status.
pub const STATUS: u8 = 0x81;
/// [`Status::faults`]: the board stopped the motor on its over-current protection.
pub const FAULT_OVER_CURRENT: u8 = 1;
/// [`Status::faults`]: the board stopped the motor because no DRIVE came in time.
pub const FAULT_WATCHDOG: u8 = 2;
/// The longest payload.
const MAX_PAYLOAD: usize = 16;

/// CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF).
pub fn crc16(bytes: &[u8]) -> u16 {
    let mut crc: u16 = 0xFFFF;
    for &b in bytes {
        crc ^= u16::from(b) << 8;
        for _ in 0..8 {
            crc = if crc & 0x8000 != 0 {
                (crc << 1) ^ 0x1021
            } else {
                crc << 1
            };
        }
    }
    crc
}

/// A frame of `kind` carrying `payload` into `out`; returns its length.
pub fn encode(kind: u8, payload: &[u8], out: &mut [u8; 5 + MAX_PAYLOAD]) -> usize {
    let n = payload.len().min(MAX_PAYLOAD);
    out[0] = START;
    out[1] = kind;
    out[2] = n as u8;
    out[3..3 + n].copy_from_slice(&payload[..n]);
    let crc = crc16(&out[1..3 + n]);
    out[3 + n..5 + n].copy_from_slice(&crc.to_le_bytes());
    5 + n
}

/// A DRIVE frame for `velocity_m_s` (clamped to what the field carries).
pub fn drive(velocity_m_s: f64, out: &mut [u8; 5 + MAX_PAYLOAD]) -> usize {
    let tenths_mm = (velocity_m_s * 10_000.0).round().clamp(-32767.0, 32767.0);
    let v = if tenths_mm.is_finite() {
        tenths_mm as i16
    } else {
        0
    };
    encode(DRIVE, &v.to_le_bytes(), out)
}

/// The board's status.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Status {
    /// Hall counts (up positive).
    pub counts: i32,
    /// Motor current, mA.
    pub current_ma: u16,
    /// Bit 0: lower switch pressed; bit 1: upper.
    pub switches: u8,
    /// Bit 0: over-current stop; bit 1: watchdog stop.
    pub faults: u8,
}

impl Status {
    /// Its payload.
    pub fn payload(&self) -> [u8; 8] {
        let mut p = [0u8; 8];
        p[..4].copy_from_slice(&self.counts.to_le_bytes());
        p[4..6].copy_from_slice(&self.current_ma.to_le_bytes());
        p[6] = self.switches;
        p[7] = self.faults;
        p
    }
}

/// A decoded frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Message {
    /// A DRIVE (what the simulated board decodes), 0.1 mm/s.
    Drive(i16),
    /// A STATUS (what the host decodes).
    Status(Status),
}

/// The incremental decoder: push bytes, take messages.
#[derive(Debug, Clone, Default)]
pub struct Decoder {
    buf: Vec<u8>,
    /// Frames dropped (CRC, length or type), and bytes skipped looking for a start.
    pub bad_frames: u64,
    /// Bytes skipped while looking for a frame's start.
    pub skipped: u64,
}

impl Decoder {
    /// A decoder with nothing buffered.
    pub fn new() -> Decoder {
        Decoder {
            buf: Vec::with_capacity(64),
            ..Decoder::default()
        }
    }

    /// Takes `bytes`; returns the messages now complete, in order, through `each`.
    pub fn push(&mut self, bytes: &[u8], mut each: impl FnMut(Message)) {
        self.buf.extend_from_slice(bytes);
        loop {
            let Some(start) = self.buf.iter().position(|&b| b == START) else {
                self.skipped += self.buf.len() as u64;
                self.buf.clear();
                return;
            };
            if start > 0 {
                self.skipped += start as u64;
                self.buf.drain(..start);
            }
            if self.buf.len() < 3 {
                return;
            }
            let n = usize::from(self.buf[2]);
            if n > MAX_PAYLOAD {
                self.bad_frames += 1;
                self.buf.drain(..1);
                continue;
            }
            if self.buf.len() < 5 + n {
                return;
            }
            let crc = u16::from_le_bytes([self.buf[3 + n], self.buf[4 + n]]);
            let message = (crc == crc16(&self.buf[1..3 + n]))
                .then(|| parse(self.buf[1], &self.buf[3..3 + n]))
                .flatten();
            match message {
                Some(m) => {
                    self.buf.drain(..5 + n);
                    each(m);
                }
                None => {
                    // Not a frame here: look for the next start after this one.
                    self.bad_frames += 1;
                    self.buf.drain(..1);
                }
            }
        }
    }
}

fn parse(kind: u8, p: &[u8]) -> Option<Message> {
    match (kind, p.len()) {
        (DRIVE, 2) => Some(Message::Drive(i16::from_le_bytes([p[0], p[1]]))),
        (STATUS, 8) => Some(Message::Status(Status {
            counts: i32::from_le_bytes([p[0], p[1], p[2], p[3]]),
            current_ma: u16::from_le_bytes([p[4], p[5]]),
            switches: p[6],
            faults: p[7],
        })),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_crc_is_ccitt_false() {
        // The standard check value of CRC-16/CCITT-FALSE.
        assert_eq!(crc16(b"123456789"), 0x29B1);
    }

    #[test]
    fn frames_round_trip_and_the_golden_bytes_hold() {
        let mut out = [0u8; 21];
        let n = drive(0.03, &mut out);
        // 0.03 m/s = 300 × 0.1 mm/s.
        assert_eq!(&out[..5], &[0xA5, 0x01, 0x02, 0x2C, 0x01]);
        let mut got = Vec::new();
        let mut d = Decoder::new();
        d.push(&out[..n], |m| got.push(m));
        assert_eq!(got, [Message::Drive(300)]);
        let s = Status {
            counts: -1234,
            current_ma: 1500,
            switches: 1,
            faults: 2,
        };
        let n = encode(STATUS, &s.payload(), &mut out);
        d.push(&out[..n], |m| got.push(m));
        assert_eq!(got[1], Message::Status(s));
    }

    #[test]
    fn garbage_cut_and_corrupted_frames_are_dropped_and_the_next_one_read() {
        let mut out = [0u8; 21];
        let n = encode(STATUS, &Status::default().payload(), &mut out);
        let good = out[..n].to_vec();
        let mut bad = good.clone();
        bad[5] ^= 0x10;
        let mut stream = vec![0x00, 0xA5, 0xFF, 0x13];
        stream.extend(&bad);
        stream.extend(&good[..4]);
        let mut got = Vec::new();
        let mut d = Decoder::new();
        d.push(&stream, |m| got.push(m));
        assert!(got.is_empty());
        // The rest of the frame that arrived cut, then a whole one, byte by byte: both read.
        for &b in good[4..].iter().chain(&good) {
            d.push(&[b], |m| got.push(m));
        }
        assert_eq!(got.len(), 2, "{got:?}");
        assert!(d.bad_frames >= 2 && d.skipped >= 1, "{d:?}");
    }
}
