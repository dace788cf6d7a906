//! Probing a bus: at each line rate the servos support, a broadcast PING, a PING to every
//! unicast id, and one READ of the whole control table from each id that answered. Each request
//! is sent once and listened to for a whole window, so that a second servo with the same id is
//! heard (answering after the first, or over it). Nothing is written.

use crate::settings::{Settings, TABLE_READ};
use bus_driver::bus::{Bus, BusError, Heard};
use bus_driver::transport::Transport;
use feetech::instruction::Instruction;
use feetech::timing::{status_bytes, wire_time, BAUD_CODES};
use feetech::{BROADCAST_ID, MAX_ID};
use serde::Serialize;
use std::ops::RangeInclusive;
use std::time::Duration;

/// The longest return delay a servo can be set to (255 × 2 µs).
pub const LONGEST_RETURN_DELAY: Duration = Duration::from_micros(510);

/// What to probe.
#[derive(Debug, Clone)]
pub struct Plan {
    /// The ids pinged one by one.
    pub ids: RangeInclusive<u8>,
    /// The ids a servo should answer at (the bus's joints): a silent PING there is tried
    /// again, as a lost answer is not a missing servo.
    pub expected: Vec<u8>,
    /// The line rates, the bus's own first; at the others the ids are swept only if the
    /// broadcast PING heard something there.
    pub rates: Vec<u32>,
    /// How long to listen beyond the wire time of a request and of two replies: the longest
    /// return delay and the adapter's latency.
    pub window: Duration,
    /// Requests to an id (PINGs to an expected one, READs of a table) before it is judged
    /// silent or garbled.
    pub attempts: usize,
}

impl Plan {
    /// Every unicast id at every rate the servos support, the bus's own first; `latency`: what
    /// the serial adapter adds to a reply (the driver's reply margin).
    pub fn full(bus_rate: u32, latency: Duration, expected: Vec<u8>) -> Plan {
        let mut rates = vec![bus_rate];
        rates.extend(BAUD_CODES.iter().copied().filter(|&b| b != bus_rate));
        Plan {
            ids: 0..=MAX_ID,
            expected,
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
    pub(crate) fn of(heard: &Heard) -> BroadcastAnswer {
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
    /// No read of the table came back intact and confirmed, and some came back damaged
    /// (servos answering at once; the others' answers lost or late).
    Garbled {
        /// Reads that came back damaged.
        garbled: usize,
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

/// Scans a bus over `line` (a serial port, or a simulated bus in tests), its rate changed for
/// each of the plan's (the device stays open: closing and opening it again between rates
/// would let another program in, and a pseudo-terminal's server takes a moment to see it back).
pub fn scan<T: Transport>(line: T, plan: &Plan) -> Result<BusScan, BusError> {
    let mut bus = Bus::new(line, Duration::ZERO);
    let mut rates = Vec::with_capacity(plan.rates.len());
    for &baud in &plan.rates {
        bus.set_baud(baud)?;
        // Listened to longer: it is sent once a rate, and every servo may answer it.
        let broadcast = bus.listen(
            Instruction::Ping { id: BROADCAST_ID },
            BROADCAST_WINDOW + plan.listening(0, baud),
        )?;
        let broadcast = BroadcastAnswer::of(&broadcast);
        // At a rate that is not the bus's, a sweep only where something answered: fewer
        // requests at a rate the bus's servos would misread (and a quicker scan).
        let sweep = Some(&baud) == plan.rates.first() || broadcast != BroadcastAnswer::Silent;
        let mut found = Vec::new();
        for id in plan.ids.clone().filter(|_| sweep) {
            if let Some(ping) = ping(&mut bus, id, baud, plan)? {
                found.push(identify(&mut bus, id, baud, &ping, plan)?);
            }
        }
        rates.push(AtRate {
            baud,
            broadcast,
            found,
        });
    }
    Ok(BusScan { rates })
}

/// The intact answers from `id` carrying `len` bytes.
fn intact(heard: &Heard, id: u8, len: u8) -> Vec<&[u8]> {
    heard
        .replies
        .iter()
        .filter(|r| r.id == id && r.data.len() == usize::from(len))
        .map(|r| r.data.as_slice())
        .collect()
}

/// A table confirmed by a second READ of its EEPROM part (another length, so a checksum over
/// other bytes): two servos answering at once can AND into one valid packet, hardly into two
/// that agree.
fn confirmed<T: Transport>(
    bus: &mut Bus<T>,
    id: u8,
    baud: u32,
    table: &[u8],
    plan: &Plan,
) -> Result<bool, BusError> {
    let len = EEPROM_LEN;
    let read = Instruction::Read { id, addr: 0, len };
    let heard = bus.listen(read, plan.listening(usize::from(len), baud))?;
    Ok(matches!(intact(&heard, id, len).as_slice(), [eeprom] if table.starts_with(eeprom)))
}

/// Addresses 0–39: the EEPROM.
const EEPROM_LEN: u8 = 40;

/// How long the broadcast PING is listened to beyond a unicast one.
pub(crate) const BROADCAST_WINDOW: Duration = Duration::from_millis(20);

/// PINGs `id`: what it heard if a servo answers there (one intact answer; two in every
/// attempt: servos with different return delays; or damaged bytes in every attempt: servos
/// answering at once), `None` if nothing does. Anything else is asked again after a pause in
/// which a late answer to an earlier request arrives (and is discarded): a stray byte, or an
/// answer from before taken for a second servo. Silence at an expected id is asked again too.
pub(crate) fn ping<T: Transport>(
    bus: &mut Bus<T>,
    id: u8,
    baud: u32,
    plan: &Plan,
) -> Result<Option<Heard>, BusError> {
    let mut damaged = 0;
    for attempt in 0..plan.attempts {
        if attempt > 0 {
            std::thread::sleep(plan.listening(0, baud));
        }
        let heard = bus.listen(Instruction::Ping { id }, plan.listening(0, baud))?;
        match heard.replies.iter().filter(|r| r.id == id).count() {
            1 => return Ok(Some(heard)),
            n if n > 1 && attempt + 1 == plan.attempts => return Ok(Some(heard)),
            0 if heard.damaged > 0 => damaged += 1,
            0 if !plan.expected.contains(&id) => return Ok(None),
            _ => {}
        }
    }
    Ok((damaged == plan.attempts).then(|| Heard {
        replies: Vec::new(),
        damaged: damaged as u64,
    }))
}

/// Reads the table of an id that answered its PING (`ping`), and judges whether one servo or
/// several answer there.
pub(crate) fn identify<T: Transport>(
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
    for attempt in 0..plan.attempts {
        if attempt > 0 {
            std::thread::sleep(plan.listening(usize::from(len), baud));
        }
        let read = Instruction::Read { id, addr, len };
        let heard = bus.listen(read, plan.listening(usize::from(len), baud))?;
        let tables = intact(&heard, id, len);
        match (tables.as_slice(), heard.damaged) {
            // Damage beside an intact table is stray: two answers to a READ this long always
            // overlap (it outlasts the longest return delay), so they never leave one intact.
            ([table], _) => {
                if confirmed(bus, id, baud, table, plan)? {
                    found.settings = Settings::parse(table);
                    return Ok(found);
                }
                garbled += 1;
            }
            ([_, _, ..], _) => {
                let answers = tables.len();
                found.duplicate = Some(Duplicate::AnsweredTwice { answers });
                return Ok(found);
            }
            ([], 0) => {}
            ([], _) => garbled += 1,
        }
    }
    if garbled > 0 {
        found.duplicate = Some(Duplicate::Garbled {
            garbled,
            attempts: plan.attempts,
        });
    }
    Ok(found)
}
