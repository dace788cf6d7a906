//! Probing a bus: at each line rate the servos support, a broadcast PING, a PING to every
//! unicast id, and one READ of the whole control table from each id that answered. Each request
//! is sent once and listened to for a whole window, so that a second servo with the same id is
//! heard (answering after the first, or over it). Nothing is written.

use crate::settings::{Settings, TABLE_READ};
use bus_driver::bus::{Bus, BusError, Heard};
use bus_driver::transport::{Transport, TransportError};
use feetech::instruction::Instruction;
use feetech::timing::{status_bytes, wire_time, BAUD_CODES};
use feetech::{BROADCAST_ID, MAX_ID};
use serde::Serialize;
use std::ops::RangeInclusive;
use std::time::Duration;

/// The longest return delay a servo can be set to (254 × 2 µs).
pub const LONGEST_RETURN_DELAY: Duration = Duration::from_micros(508);

/// What to probe.
#[derive(Debug, Clone)]
pub struct Plan {
    /// The ids pinged one by one.
    pub ids: RangeInclusive<u8>,
    /// The line rates, the bus's own first.
    pub rates: Vec<u32>,
    /// How long to listen beyond the wire time of a request and of two replies: the longest
    /// return delay and the adapter's latency.
    pub window: Duration,
    /// Reads of a servo's table before it is judged garbled.
    pub attempts: usize,
}

impl Plan {
    /// Every unicast id at every rate the servos support, the bus's own first; `latency`: what
    /// the serial adapter adds to a reply (the driver's reply margin).
    pub fn full(bus_rate: u32, latency: Duration) -> Plan {
        let mut rates = vec![bus_rate];
        rates.extend(BAUD_CODES.iter().copied().filter(|&b| b != bus_rate));
        Plan {
            ids: 0..=MAX_ID,
            rates,
            window: LONGEST_RETURN_DELAY + latency,
            attempts: 3,
        }
    }

    fn listening(&self, reply_data: usize, baud: u32) -> Duration {
        self.window + wire_time(2 * status_bytes(reply_data), baud)
    }
}

/// How the servos answered a broadcast PING at one rate.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "answer", rename_all = "kebab-case")]
pub enum BroadcastAnswer {
    /// Nobody answered.
    Silent,
    /// One servo, alone at this rate (Feetech documents the broadcast PING for this case).
    One {
        /// Its id.
        id: u8,
    },
    /// Several servos answered: intact where their return delays kept them apart, damaged
    /// where they talked at once.
    Several {
        /// The ids of the intact answers.
        ids: Vec<u8>,
        /// Damaged answers.
        damaged: u64,
    },
}

impl BroadcastAnswer {
    fn of(heard: &Heard) -> BroadcastAnswer {
        let ids: Vec<u8> = heard.replies.iter().map(|r| r.id).collect();
        match (ids.as_slice(), heard.damaged) {
            ([], 0) => BroadcastAnswer::Silent,
            ([id], 0) => BroadcastAnswer::One { id: *id },
            _ => BroadcastAnswer::Several {
                ids,
                damaged: heard.damaged,
            },
        }
    }
}

/// Evidence that more than one servo answers at an id.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(tag = "evidence", rename_all = "kebab-case")]
pub enum Duplicate {
    /// Two or more intact answers to one request (servos with different return delays).
    AnsweredTwice {
        /// Intact answers to one request.
        answers: usize,
    },
    /// Every read of the table came back damaged (servos answering at once).
    Garbled {
        /// Reads tried.
        attempts: usize,
    },
}

/// An id that answered at one rate.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Found {
    /// Its id.
    pub id: u8,
    /// The rate it answered at, baud.
    pub baud: u32,
    /// Its control table, when one servo answered it intact.
    pub settings: Option<Settings>,
    /// Evidence that more than one servo has this id.
    pub duplicate: Option<Duplicate>,
}

/// One rate's answers.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct AtRate {
    /// The rate, baud.
    pub baud: u32,
    /// The broadcast PING's answer.
    pub broadcast: BroadcastAnswer,
    /// Each id that answered its PING, in id order.
    pub found: Vec<Found>,
}

/// A bus scanned at every rate of a plan.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BusScan {
    /// By rate, in the plan's order.
    pub rates: Vec<AtRate>,
}

impl BusScan {
    /// Every id found, at every rate.
    pub fn found(&self) -> impl Iterator<Item = &Found> {
        self.rates.iter().flat_map(|r| r.found.iter())
    }
}

/// Scans a bus: `open` opens its line at a rate (a serial port, or a simulated bus in tests).
pub fn scan<T: Transport>(
    mut open: impl FnMut(u32) -> Result<T, TransportError>,
    plan: &Plan,
) -> Result<BusScan, BusError> {
    let mut rates = Vec::with_capacity(plan.rates.len());
    for &baud in &plan.rates {
        let mut bus = Bus::new(open(baud)?, Duration::ZERO);
        // Listened to longer: it is sent once a rate, and every servo may answer it.
        let broadcast = bus.listen(
            Instruction::Ping { id: BROADCAST_ID },
            BROADCAST_WINDOW + plan.listening(0, baud),
        )?;
        let mut found = Vec::new();
        for id in plan.ids.clone() {
            if let Some(ping) = ping(&mut bus, id, baud, plan)? {
                found.push(identify(&mut bus, id, baud, &ping, plan)?);
            }
        }
        rates.push(AtRate {
            baud,
            broadcast: BroadcastAnswer::of(&broadcast),
            found,
        });
    }
    Ok(BusScan { rates })
}

/// How long the broadcast PING is listened to beyond a unicast one.
const BROADCAST_WINDOW: Duration = Duration::from_millis(20);

/// PINGs `id`: what it heard if a servo answers there (an intact answer from `id`, or damaged
/// bytes in every attempt: servos answering at once), `None` if nothing does (damage that does
/// not come again is a stray byte, such as a late answer to the request before).
fn ping<T: Transport>(
    bus: &mut Bus<T>,
    id: u8,
    baud: u32,
    plan: &Plan,
) -> Result<Option<Heard>, BusError> {
    for _ in 0..plan.attempts {
        let heard = bus.listen(Instruction::Ping { id }, plan.listening(0, baud))?;
        if heard.replies.iter().any(|r| r.id == id) {
            return Ok(Some(heard));
        }
        if heard.damaged == 0 {
            return Ok(None);
        }
    }
    Ok(Some(Heard {
        replies: Vec::new(),
        damaged: plan.attempts as u64,
    }))
}

/// Reads the table of an id that answered its PING (`ping`), and judges whether one servo or
/// several answer there.
fn identify<T: Transport>(
    bus: &mut Bus<T>,
    id: u8,
    baud: u32,
    ping: &Heard,
    plan: &Plan,
) -> Result<Found, BusError> {
    let mut found = Found {
        id,
        baud,
        settings: None,
        duplicate: None,
    };
    let pings = ping.replies.iter().filter(|r| r.id == id).count();
    if pings > 1 {
        found.duplicate = Some(Duplicate::AnsweredTwice { answers: pings });
        return Ok(found);
    }
    let (addr, len) = TABLE_READ;
    let mut garbled = 0;
    for _ in 0..plan.attempts {
        let read = Instruction::Read { id, addr, len };
        let heard = bus.listen(read, plan.listening(usize::from(len), baud))?;
        let intact: Vec<&[u8]> = heard
            .replies
            .iter()
            .filter(|r| r.id == id && r.data.len() == usize::from(len))
            .map(|r| r.data.as_slice())
            .collect();
        match (intact.as_slice(), heard.damaged) {
            ([table], 0) => {
                found.settings = Settings::parse(table);
                return Ok(found);
            }
            ([_, _, ..], _) => {
                let answers = intact.len();
                found.duplicate = Some(Duplicate::AnsweredTwice { answers });
                return Ok(found);
            }
            (_, 0) => {}
            _ => garbled += 1,
        }
    }
    if garbled == plan.attempts {
        found.duplicate = Some(Duplicate::Garbled { attempts: garbled });
    }
    Ok(found)
}
