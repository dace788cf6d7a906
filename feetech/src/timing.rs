//! Wire time of frames, for deadlines (host) and for the simulator's line model (device).
//!
//! 8N1 framing: ten bits a byte, so a byte takes `10 / baud` seconds.

use std::time::Duration;

/// Bits on the wire for one byte (start + 8 data + stop).
pub const BITS_PER_BYTE: u64 = 10;

/// Time `bytes` bytes take on the line at `baud`.
pub fn wire_time(bytes: usize, baud: u32) -> Duration {
    let baud = u64::from(baud.max(1));
    Duration::from_nanos((bytes as u64) * BITS_PER_BYTE * 1_000_000_000 / baud)
}

/// Bytes of a SYNC_READ request for `servos` servos.
pub const fn sync_read_request_bytes(servos: usize) -> usize {
    servos + 8
}

/// Bytes of one status packet carrying `data_len` data bytes.
pub const fn status_bytes(data_len: usize) -> usize {
    data_len + 6
}

/// Bytes of a SYNC_WRITE of `data_len` bytes to each of `servos` servos.
pub const fn sync_write_bytes(servos: usize, data_len: usize) -> usize {
    8 + servos * (data_len + 1)
}

/// Bytes of one control cycle: a SYNC_READ of `read_len` bytes from `servos` servos, their
/// replies, and a SYNC_WRITE of `write_len` bytes to each.
pub const fn cycle_bytes(servos: usize, read_len: usize, write_len: usize) -> usize {
    sync_read_request_bytes(servos)
        + servos * status_bytes(read_len)
        + sync_write_bytes(servos, write_len)
}

/// Baud rates by the code of register 6 `Baud_Rate`.
pub const BAUD_CODES: [u32; 8] = [
    1_000_000, 500_000, 250_000, 128_000, 115_200, 76_800, 57_600, 38_400,
];

/// The register code of a baud rate, if the servo supports it.
pub fn baud_code(baud: u32) -> Option<u8> {
    BAUD_CODES.iter().position(|&b| b == baud).map(|c| c as u8)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eight_servo_cycle_matches_the_doc() {
        // Doc: a sync read of the 15-byte block for 8 servos ≈ 1.84 ms, a sync write ≈ 0.32 ms.
        let read = sync_read_request_bytes(8) + 8 * status_bytes(15);
        assert_eq!(read, 184);
        assert_eq!(wire_time(read, 1_000_000), Duration::from_micros(1840));
        assert_eq!(
            wire_time(sync_write_bytes(8, 2), 1_000_000),
            Duration::from_micros(320)
        );
        assert_eq!(cycle_bytes(8, 15, 2), 216);
    }

    #[test]
    fn baud_codes() {
        assert_eq!(baud_code(1_000_000), Some(0));
        assert_eq!(baud_code(38_400), Some(7));
        assert_eq!(baud_code(9_600), None);
    }
}
