//! The half-duplex line the servos answer on. Each servo starts its status packet at its own
//! time (the end of the request, or of the reply before it, plus its return delay); two servos
//! that talk at once garble each other. The model of a collision: the bytes that overlap are
//! AND-ed, as on a line whose idle level is high and where a driven low wins, aligned to the
//! nearest whole byte (a real collision is worse: misaligned start bits add framing errors).
//! Either way the host's checksum refuses the result unless the packets were the same bytes.

/// What is on the line in answer to one instruction.
#[derive(Debug, Default)]
pub struct Line {
    /// Each packet and when its first byte starts, s.
    packets: Vec<(f64, Vec<u8>)>,
    byte_s: f64,
}

impl Line {
    /// A packet whose first byte starts at `at` (s); each byte takes `byte_s`.
    pub fn put(&mut self, at: f64, packet: &[u8], byte_s: f64) {
        self.packets.push((at, packet.to_vec()));
        self.byte_s = byte_s;
    }

    /// The packets put on the line.
    pub fn packets(&self) -> usize {
        self.packets.len()
    }

    /// The bytes the host receives, in time order, and when the last of them has arrived (s);
    /// `None` if no servo answered. A packet that starts before the one ahead of it has ended
    /// is AND-ed into its tail; one that starts after is appended (the idle gap carries no
    /// bytes).
    pub fn finish(mut self) -> Option<(Vec<u8>, f64)> {
        self.packets.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut packets = self.packets.into_iter();
        let (first_at, mut bytes) = packets.next()?;
        let mut end = first_at + bytes.len() as f64 * self.byte_s;
        for (at, packet) in packets {
            let overlap = ((end - at) / self.byte_s).round().max(0.0) as usize;
            let overlap = overlap.min(bytes.len()).min(packet.len());
            let start = bytes.len() - overlap;
            for (on_line, b) in bytes[start..].iter_mut().zip(&packet) {
                *on_line &= b;
            }
            bytes.extend_from_slice(&packet[overlap..]);
            end = end.max(at + packet.len() as f64 * self.byte_s);
        }
        Some((bytes, end))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const BYTE: f64 = 10e-6;

    #[test]
    fn one_packet_arrives_whole_after_its_wire_time() {
        let mut line = Line::default();
        line.put(1e-3, &[0xFF, 0xFF, 1, 2, 0, 0xFC], BYTE);
        let (bytes, end) = line.finish().unwrap();
        assert_eq!(bytes, [0xFF, 0xFF, 1, 2, 0, 0xFC]);
        assert!((end - (1e-3 + 60e-6)).abs() < 1e-12);
    }

    #[test]
    fn packets_apart_in_time_follow_each_other_in_time_order() {
        let mut line = Line::default();
        line.put(500e-6, &[0xFF, 0xFF, 2, 2, 0, 0xFB], BYTE);
        line.put(0.0, &[0xFF, 0xFF, 1, 2, 0, 0xFC], BYTE);
        let (bytes, end) = line.finish().unwrap();
        assert_eq!(bytes[2], 1);
        assert_eq!(bytes[8], 2);
        assert!((end - 560e-6).abs() < 1e-12);
    }

    #[test]
    fn a_packet_between_two_apart_in_time_arrives_intact_in_its_place() {
        // Put out of time order; the middle one starts after the first has ended.
        let ping = |id: u8| [0xFF, 0xFF, id, 2, 0, !(id + 2)];
        let mut line = Line::default();
        line.put(0.0, &ping(1), BYTE);
        line.put(500e-6, &ping(2), BYTE);
        line.put(100e-6, &ping(3), BYTE);
        let (bytes, _) = line.finish().unwrap();
        let mut d = feetech::Decoder::new();
        d.push(&bytes);
        let ids: Vec<u8> = std::iter::from_fn(|| d.finish())
            .map(|f| f.unwrap().id)
            .collect();
        assert_eq!(ids, [1, 3, 2]);
    }

    #[test]
    fn packets_at_once_garble_each_other() {
        let (a, b) = (
            [0xFF, 0xFF, 1, 4, 0, 0x09, 0x03, 0xEE],
            [0xFF, 0xFF, 1, 4, 0, 0x19, 0x0B, 0xD6],
        );
        let mut line = Line::default();
        line.put(0.0, &a, BYTE);
        line.put(0.4 * BYTE, &b, BYTE);
        let (bytes, _) = line.finish().unwrap();
        let decoded: Vec<_> = {
            let mut d = feetech::Decoder::new();
            d.push(&bytes);
            std::iter::from_fn(|| d.finish()).collect()
        };
        assert!(decoded.iter().all(|f| f.is_err()), "{decoded:?}");
        // The same bytes at once are one packet to the host.
        let mut same = Line::default();
        same.put(0.0, &a, BYTE);
        same.put(0.0, &a, BYTE);
        assert_eq!(same.packets(), 2);
        assert_eq!(same.finish().unwrap().0, a);
    }
}
