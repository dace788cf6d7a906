//! Line faults injected on a simulated bus: into the replies (one or two flipped bits, dropped
//! and truncated status packets; rates per status packet) and into the host's instructions
//! (dropped, or one bit flipped before the servos decode them; rates per instruction packet).
//! Seeded, so a run is reproducible.
//!
//! The device side stays honest about what it meant to send: the bus records the true
//! feedback block of every servo before any fault is applied (`SimBus::feedback_truth`), so a
//! test can compare what the driver published as valid with what the servo really measured.

use serde::{Deserialize, Serialize};

/// Fault rates of one bus, each the probability per status packet (mutually exclusive: at most
/// one fault per packet).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct LineFaults {
    /// Seed of the fault sequence.
    pub seed: u64,
    /// One random bit of one random byte flipped.
    pub bit_flip_rate: f64,
    /// Two random bits flipped in one packet (a burst of line noise). About 7 % of such
    /// packets pass Feetech's 8-bit sum checksum.
    #[serde(default)]
    pub double_flip_rate: f64,
    /// The packet never sent (the servo seems not to answer this once).
    pub drop_rate: f64,
    /// Only a random prefix of the packet sent.
    pub truncate_rate: f64,
    /// A host instruction lost on the line: no servo sees it (a lost write).
    #[serde(default)]
    pub instruction_drop_rate: f64,
    /// One random bit of a host instruction flipped on the line; the servos decode what
    /// arrives (the checksum refuses a single flip, so the write is lost as a corrupted one).
    #[serde(default)]
    pub instruction_corrupt_rate: f64,
}

impl LineFaults {
    /// Whether any fault can happen.
    pub fn any(&self) -> bool {
        self.bit_flip_rate > 0.0
            || self.double_flip_rate > 0.0
            || self.drop_rate > 0.0
            || self.truncate_rate > 0.0
            || self.instruction_drop_rate > 0.0
            || self.instruction_corrupt_rate > 0.0
    }

    /// Checks that the rates are probabilities whose sum is at most 1.
    pub fn validate(&self) -> Result<(), String> {
        for (name, r) in [
            ("bit-flip rate", self.bit_flip_rate),
            ("double-flip rate", self.double_flip_rate),
            ("drop rate", self.drop_rate),
            ("truncate rate", self.truncate_rate),
            ("instruction drop rate", self.instruction_drop_rate),
            ("instruction corrupt rate", self.instruction_corrupt_rate),
        ] {
            if !(0.0..=1.0).contains(&r) {
                return Err(format!("{name} must be in [0, 1], got {r}"));
            }
        }
        let sum = self.bit_flip_rate + self.double_flip_rate + self.drop_rate + self.truncate_rate;
        if sum > 1.0 {
            return Err(format!("fault rates sum to {sum}, more than 1"));
        }
        let sum = self.instruction_drop_rate + self.instruction_corrupt_rate;
        if sum > 1.0 {
            return Err(format!("instruction fault rates sum to {sum}, more than 1"));
        }
        Ok(())
    }
}

/// What the injector did, by kind.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct FaultCounts {
    /// Status packets that had one bit flipped.
    pub flipped: u64,
    /// Status packets that had two bits flipped.
    pub double_flipped: u64,
    /// Status packets dropped.
    pub dropped: u64,
    /// Status packets truncated.
    pub truncated: u64,
    /// Host instructions dropped.
    pub instructions_dropped: u64,
    /// Host instructions with a bit flipped.
    pub instructions_corrupted: u64,
}

impl FaultCounts {
    /// All faults injected into status packets.
    pub fn total(&self) -> u64 {
        self.flipped + self.double_flipped + self.dropped + self.truncated
    }
}

/// What happens to one status packet.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fault {
    /// Sent as is.
    None,
    /// Bit `bit` (0–7) of byte `byte` flipped.
    Flip {
        /// Byte index.
        byte: usize,
        /// Bit index.
        bit: u8,
    },
    /// Two different bits flipped: `(byte, bit)` each.
    DoubleFlip([(usize, u8); 2]),
    /// Not sent.
    Drop,
    /// Only the first `keep` bytes sent.
    Truncate {
        /// Bytes kept (at least 1, fewer than the packet).
        keep: usize,
    },
}

/// SplitMix64: a small, fast, seedable generator (no dependency, same sequence everywhere).
#[derive(Debug, Clone)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    /// A generator from `seed`.
    pub fn new(seed: u64) -> Self {
        SplitMix64(seed)
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in `0..n` (`n` > 0).
    pub fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n.max(1) as u64) as usize
    }
}

/// Draws the faults of a bus's status packets.
#[derive(Debug, Clone)]
pub struct FaultInjector {
    /// The rates.
    pub config: LineFaults,
    rng: SplitMix64,
    /// A stream of its own, so adding instruction faults does not change the reply faults a
    /// seed gives.
    instruction_rng: SplitMix64,
    /// What was injected so far.
    pub counts: FaultCounts,
}

impl FaultInjector {
    /// An injector with `config`'s rates and seed.
    pub fn new(config: LineFaults) -> Self {
        FaultInjector {
            config,
            rng: SplitMix64::new(config.seed),
            instruction_rng: SplitMix64::new(config.seed ^ 0x1A57_0000_DEAD_BEEF),
            counts: FaultCounts::default(),
        }
    }

    /// Draws the fault of one host instruction of `len` bytes and counts it: `Drop`, `Flip`
    /// or `None`.
    pub fn draw_instruction(&mut self, len: usize) -> Fault {
        let c = self.config;
        let r = self.instruction_rng.unit();
        if r < c.instruction_drop_rate {
            self.counts.instructions_dropped += 1;
            Fault::Drop
        } else if r < c.instruction_drop_rate + c.instruction_corrupt_rate && len > 0 {
            self.counts.instructions_corrupted += 1;
            Fault::Flip {
                byte: self.instruction_rng.below(len),
                bit: self.instruction_rng.below(8) as u8,
            }
        } else {
            Fault::None
        }
    }

    /// Draws the fault of one status packet of `len` bytes and counts it.
    pub fn draw(&mut self, len: usize) -> Fault {
        let c = self.config;
        let r = self.rng.unit();
        if r < c.drop_rate {
            self.counts.dropped += 1;
            Fault::Drop
        } else if r < c.drop_rate + c.truncate_rate && len > 1 {
            self.counts.truncated += 1;
            Fault::Truncate {
                keep: 1 + self.rng.below(len - 1),
            }
        } else if r < c.drop_rate + c.truncate_rate + c.bit_flip_rate && len > 0 {
            self.counts.flipped += 1;
            Fault::Flip {
                byte: self.rng.below(len),
                bit: self.rng.below(8) as u8,
            }
        } else if r < c.drop_rate + c.truncate_rate + c.bit_flip_rate + c.double_flip_rate
            && len > 0
        {
            self.counts.double_flipped += 1;
            let first = (self.rng.below(len), self.rng.below(8) as u8);
            let mut second = first;
            while second == first {
                second = (self.rng.below(len), self.rng.below(8) as u8);
            }
            Fault::DoubleFlip([first, second])
        } else {
            Fault::None
        }
    }
}

/// Applies `fault` to `packet`; returns the bytes to send.
pub fn apply(fault: Fault, packet: &mut [u8]) -> &[u8] {
    match fault {
        Fault::None => packet,
        Fault::Drop => &[],
        Fault::Truncate { keep } => &packet[..keep.min(packet.len())],
        Fault::Flip { byte, bit } => {
            if let Some(b) = packet.get_mut(byte) {
                *b ^= 1 << bit;
            }
            packet
        }
        Fault::DoubleFlip(flips) => {
            for (byte, bit) in flips {
                if let Some(b) = packet.get_mut(byte) {
                    *b ^= 1 << bit;
                }
            }
            packet
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rates_are_honoured_and_seeded() {
        let cfg = LineFaults {
            seed: 7,
            bit_flip_rate: 0.01,
            double_flip_rate: 0.015,
            drop_rate: 0.02,
            truncate_rate: 0.03,
            ..LineFaults::default()
        };
        let mut a = FaultInjector::new(cfg);
        let mut b = FaultInjector::new(cfg);
        let n = 100_000;
        for _ in 0..n {
            assert_eq!(a.draw(21), b.draw(21), "same seed, same faults");
        }
        let c = a.counts;
        let near = |got: u64, rate: f64| (got as f64 / n as f64 - rate).abs() < rate * 0.15;
        assert!(near(c.flipped, 0.01), "{c:?}");
        assert!(near(c.double_flipped, 0.015), "{c:?}");
        assert!(near(c.dropped, 0.02), "{c:?}");
        assert!(near(c.truncated, 0.03), "{c:?}");
        let mut other = FaultInjector::new(LineFaults { seed: 8, ..cfg });
        let differs = (0..1000).any(|_| other.draw(21) != FaultInjector::new(cfg).draw(21));
        assert!(differs, "another seed, other faults");
    }

    /// The fact the driver's plausibility gate exists for: Feetech's sum checksum catches every
    /// single flipped bit but lets about 9/128 of double flips through (same bit position,
    /// opposite directions; or bit 7 twice).
    #[test]
    fn two_flipped_bits_often_pass_the_checksum() {
        let mut inj = FaultInjector::new(LineFaults {
            seed: 3,
            double_flip_rate: 1.0,
            ..LineFaults::default()
        });
        let mut data = SplitMix64::new(11);
        let (n, mut passed) = (20_000, 0);
        for _ in 0..n {
            // A feedback status packet: FF FF id len err params(15) checksum.
            let mut p = vec![0xFF, 0xFF, 1 + data.below(20) as u8, 17, 0];
            p.extend((0..15).map(|_| data.next_u64() as u8));
            let sum = feetech::frame::checksum(p[2], p[3], p[4], &p[5..]);
            p.push(sum);
            // Flips in the body only (a broken header or length is refused anyway).
            let fault = match inj.draw(p.len() - 4) {
                Fault::DoubleFlip(f) => Fault::DoubleFlip(f.map(|(byte, bit)| (byte + 4, bit))),
                other => panic!("{other:?}"),
            };
            apply(fault, &mut p);
            let last = p.len() - 1;
            passed +=
                usize::from(feetech::frame::checksum(p[2], p[3], p[4], &p[5..last]) == p[last]);
        }
        let rate = passed as f64 / n as f64;
        assert!((rate - 9.0 / 128.0).abs() < 0.01, "passed {rate}");
    }

    #[test]
    fn faults_change_the_packet_as_said() {
        let mut p = [1u8, 2, 3, 4];
        assert_eq!(apply(Fault::Flip { byte: 2, bit: 1 }, &mut p), [1, 2, 1, 4]);
        let mut p = [1u8, 2, 3, 4];
        assert_eq!(
            apply(Fault::DoubleFlip([(0, 0), (3, 7)]), &mut p),
            [0, 2, 3, 0x84]
        );
        let mut p = [1u8, 2, 3, 4];
        assert_eq!(apply(Fault::Truncate { keep: 3 }, &mut p), [1, 2, 3]);
        assert!(apply(Fault::Drop, &mut p).is_empty());
        let bad = LineFaults {
            drop_rate: 0.7,
            truncate_rate: 0.7,
            ..LineFaults::default()
        };
        assert!(bad.validate().is_err());
        assert!(LineFaults {
            bit_flip_rate: -0.1,
            ..LineFaults::default()
        }
        .validate()
        .is_err());
    }
}
