//! The half-duplex line the servos answer on. Each servo starts its status packet at its own
//! time (the end of the request, or of the reply before it, plus its return delay); two servos
//! that talk at once garble each other. The model of a collision: the bytes that overlap are
//! AND-ed, as on a line whose idle level is high and where a driven low wins, aligned to the
//! nearest whole byte (a real collision is worse: misaligned start bits add framing errors).
//! Either way the host's checksum refuses the result unless the packets were the same bytes.

/// What is on the line in answer to one instruction.
#[derive(Debug, Default)]
pub struct Line {
    begin: f64,
    end: f64,
    bytes: Vec<u8>,
    packets: usize,
}

impl Line {
    /// A packet whose first byte starts at `at` (s); each byte takes `byte_s`.
    pub fn put(&mut self, at: f64, packet: &[u8], byte_s: f64) {
        let packet_end = at + packet.len() as f64 * byte_s;
        self.packets += 1;
        if self.packets == 1 {
            (self.begin, self.end) = (at, packet_end);
            self.bytes = packet.to_vec();
            return;
        }
        let (first_at, mut merged, second_at, second) = if at < self.begin {
            (
                at,
                packet.to_vec(),
                self.begin,
                std::mem::take(&mut self.bytes),
            )
        } else {
            (
                self.begin,
                std::mem::take(&mut self.bytes),
                at,
                packet.to_vec(),
            )
        };
        let offset = ((second_at - first_at) / byte_s).round().max(0.0) as usize;
        for (k, b) in second.into_iter().enumerate() {
            match merged.get_mut(offset + k) {
                Some(on_line) => *on_line &= b,
                // After the first packet has ended (an idle gap carries no bytes).
                None => merged.push(b),
            }
        }
        self.begin = first_at;
        self.end = self.end.max(packet_end);
        self.bytes = merged;
    }

    /// The packets put on the line.
    pub fn packets(&self) -> usize {
        self.packets
    }

    /// The bytes the host receives and when the last of them has arrived (s); `None` if no
    /// servo answered.
    pub fn finish(self) -> Option<(Vec<u8>, f64)> {
        (self.packets > 0).then_some((self.bytes, self.end))
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
