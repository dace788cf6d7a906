//! Line faults injected on a simulated bus: into the replies (one or two flipped bits, dropped
//! and truncated status packets; rates per status packet) and into the host's instructions
//! (dropped, or one bit flipped before the servos decode them; rates per instruction packet).
//! Seeded, so a run is reproducible.
//!
//! The device side stays honest about what it meant to send: the bus records the true
//! feedback block of every servo before any fault is applied (`SimBus::feedback_truth`), so a
//! test can compare what the driver published as valid with what the servo really measured.

use crate::rng::Rng;
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

/// Draws the faults of a bus's status packets.
#[derive(Debug, Clone)]
pub struct FaultInjector {
    /// The rates.
    pub config: LineFaults,
    rng: Rng,
    /// A stream of its own, so adding instruction faults does not change the reply faults a
    /// seed gives.
    instruction_rng: Rng,
    /// What was injected so far.
    pub counts: FaultCounts,
}

impl FaultInjector {
    /// An injector with `config`'s rates and seed.
    pub fn new(config: LineFaults) -> Self {
        FaultInjector {
            config,
            rng: Rng::new(config.seed),
            instruction_rng: Rng::new(config.seed ^ 0x1A57_0000_DEAD_BEEF),
            counts: FaultCounts::default(),
        }
    }

    /// Draws the fault of one host instruction of `len` bytes and counts it: `Drop`, `Flip`
    /// or `None`.
    pub fn draw_instruction(&mut self, len: usize) -> Fault {
        let c = self.config;
        let r = self.instruction_rng.uniform();
        if r < c.instruction_drop_rate {
            self.counts.instructions_dropped += 1;
            Fault::Drop
        } else if r < c.instruction_drop_rate + c.instruction_corrupt_rate && len > 0 {
            self.counts.instructions_corrupted += 1;
            Fault::Flip {
                byte: self.instruction_rng.below(len as u64) as usize,
                bit: self.instruction_rng.below(8) as u8,
            }
        } else {
            Fault::None
        }
    }

    /// Draws the fault of one status packet of `len` bytes and counts it.
    pub fn draw(&mut self, len: usize) -> Fault {
        let c = self.config;
        let r = self.rng.uniform();
        if r < c.drop_rate {
            self.counts.dropped += 1;
            Fault::Drop
        } else if r < c.drop_rate + c.truncate_rate && len > 1 {
            self.counts.truncated += 1;
            Fault::Truncate {
                keep: 1 + self.rng.below(len as u64 - 1) as usize,
            }
        } else if r < c.drop_rate + c.truncate_rate + c.bit_flip_rate && len > 0 {
            self.counts.flipped += 1;
            Fault::Flip {
                byte: self.rng.below(len as u64) as usize,
                bit: self.rng.below(8) as u8,
            }
        } else if r < c.drop_rate + c.truncate_rate + c.bit_flip_rate + c.double_flip_rate
            && len > 0
        {
            self.counts.double_flipped += 1;
            let first = (self.rng.below(len as u64) as usize, self.rng.below(8) as u8);
            let mut second = first;
            while second == first {
                second = (self.rng.below(len as u64) as usize, self.rng.below(8) as u8);
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

/// A fault the simulator schedules in time: a bus unplugged (`id` none: the USB adapter pulled
/// out and put back) or one servo silent, from `at` for `duration` seconds of the run.
#[derive(Debug, Clone, PartialEq)]
pub struct Scheduled {
    /// Bus name.
    pub bus: String,
    /// Servo id (silence) or none (unplug).
    pub id: Option<u8>,
    /// Start, s since the simulator started.
    pub at: f64,
    /// Duration, s.
    pub duration: f64,
}

/// A scheduled fault that does not parse.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{text:?}: expected {form} (seconds), e.g. {example}")]
pub struct ScheduleError {
    /// What was given.
    pub text: String,
    /// The expected form.
    pub form: &'static str,
    /// An example of it.
    pub example: &'static str,
}

impl Scheduled {
    /// Parses `BUS@AT+FOR` (`with_id` false) or `BUS:ID@AT+FOR` (`with_id` true).
    pub fn parse(text: &str, with_id: bool) -> Result<Scheduled, ScheduleError> {
        let bad = || ScheduleError {
            text: text.into(),
            form: if with_id {
                "BUS:ID@AT+FOR"
            } else {
                "BUS@AT+FOR"
            },
            example: if with_id {
                "right_arm:3@10+3"
            } else {
                "right_arm@10+3"
            },
        };
        let (target, when) = text.split_once('@').ok_or_else(bad)?;
        let (at, duration) = when.split_once('+').ok_or_else(bad)?;
        let at: f64 = at.trim().parse().map_err(|_| bad())?;
        let duration: f64 = duration.trim().parse().map_err(|_| bad())?;
        if !(at.is_finite() && at >= 0.0 && duration.is_finite() && duration > 0.0) {
            return Err(bad());
        }
        let (bus, id) = if with_id {
            let (bus, id) = target.split_once(':').ok_or_else(bad)?;
            (bus, Some(id.trim().parse::<u8>().map_err(|_| bad())?))
        } else {
            (target, None)
        };
        if bus.is_empty() {
            return Err(bad());
        }
        Ok(Scheduled {
            bus: bus.to_string(),
            id,
            at,
            duration,
        })
    }
}

/// Where a scheduled fault stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    Pending,
    Active,
    Over,
}

/// The run's fault schedule: which faults turn on or off as time passes (time passed in).
#[derive(Debug, Clone, Default)]
pub struct Schedule {
    faults: Vec<(Scheduled, Phase)>,
}

impl Schedule {
    /// A schedule of `faults`, none started.
    pub fn new(faults: Vec<Scheduled>) -> Schedule {
        Schedule {
            faults: faults.into_iter().map(|f| (f, Phase::Pending)).collect(),
        }
    }

    /// The faults.
    pub fn faults(&self) -> impl Iterator<Item = &Scheduled> {
        self.faults.iter().map(|(f, _)| f)
    }

    /// The changes due at `t` s since the start: each fault that turns on (`true`) or off
    /// (`false`). A fault that began and ended between two calls only turns off (it never
    /// took effect, and whatever it would have changed is restored).
    pub fn advance(&mut self, t: f64) -> Vec<(&Scheduled, bool)> {
        let mut changes = Vec::new();
        for (fault, phase) in &mut self.faults {
            let want = if t < fault.at {
                Phase::Pending
            } else if t < fault.at + fault.duration {
                Phase::Active
            } else {
                Phase::Over
            };
            if want != *phase {
                *phase = want;
                changes.push((&*fault, want == Phase::Active));
            }
        }
        changes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scheduled_faults_parse_or_say_why() {
        assert_eq!(
            Scheduled::parse("right_arm@10+3", false).unwrap(),
            Scheduled {
                bus: "right_arm".into(),
                id: None,
                at: 10.0,
                duration: 3.0
            }
        );
        assert_eq!(
            Scheduled::parse("left_arm:3@5.5+0.5", true).unwrap().id,
            Some(3)
        );
        for bad in [
            "right_arm",
            "right_arm@x+1",
            "@1+1",
            "a@1+0",
            "a@-1+2",
            "a@1+nan",
        ] {
            let e = Scheduled::parse(bad, false).unwrap_err().to_string();
            assert!(e.contains("BUS@AT+FOR"), "{bad}: {e}");
        }
        let e = Scheduled::parse("left_arm:300@1+1", true).unwrap_err();
        assert_eq!(e.form, "BUS:ID@AT+FOR");
        assert!(Scheduled::parse("left_arm@1+1", true).is_err());
    }

    #[test]
    fn a_schedule_turns_each_fault_on_then_off_once() {
        let unplug = Scheduled::parse("a@1+2", false).unwrap();
        let blip = Scheduled::parse("b:3@1.5+0.01", true).unwrap();
        let mut s = Schedule::new(vec![unplug.clone(), blip.clone()]);
        let names = |c: Vec<(&Scheduled, bool)>| {
            c.into_iter()
                .map(|(f, on)| (f.bus.clone(), on))
                .collect::<Vec<_>>()
        };
        assert!(s.advance(0.5).is_empty());
        assert_eq!(names(s.advance(1.0)), [("a".to_string(), true)]);
        assert!(s.advance(1.2).is_empty());
        // The blip began and ended between two calls: only its end is reported.
        assert_eq!(names(s.advance(1.6)), [("b".to_string(), false)]);
        assert!(s.advance(2.9).is_empty());
        assert_eq!(names(s.advance(3.0)), [("a".to_string(), false)]);
        assert!(s.advance(100.0).is_empty());
        assert_eq!(s.faults().count(), 2);
    }

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
        let mut data = Rng::new(11);
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
