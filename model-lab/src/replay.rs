//! `nori sim replay BOX.mcap`: a black box's bus traffic played into the simulated servos, and
//! the simulator's replies held against the servos' own, register by register: what the
//! simulation gets wrong on this robot's own data (docs/blackbox.md, "Replay").
//!
//! Sans-IO: the box's bytes in, a comparison out. Each bus of the box is rebuilt from the robot
//! description; its servos are placed where the box first saw them (position, temperature, and
//! the settings the driver reads back: torque, goal, torque limit); then every instruction that
//! went out is delivered to the simulator at its recorded time. The replies are paired by servo
//! within each transaction (the instructions sent before the driver read its answers) and
//! compared over every register each read covers.

use blackbox::channel::{wire_chunks, Channel, Direction, LayoutJoint, WireChunk};
use blackbox::frozen::{visit, Extent, Item};
use feetech::registers::{self as reg, Register, TABLE, TABLE_SIZE};
use feetech::{Decoder, Instruction, StatusPacket};
use serde::Serialize;
use sim::{RobotDescription, SimBus};
use std::collections::BTreeMap;
use thiserror::Error;

/// How the simulator is set up for a replay.
#[derive(Debug, Clone)]
pub struct Setup {
    /// The robot the box was recorded on (with the loads known on it: a scenario's payload).
    pub robot: RobotDescription,
    /// Temperatures integrated this many times faster than real time (as the recording
    /// simulator did; 1 for a real robot).
    pub thermal_speedup: f64,
    /// The servo models' constants (the simulator's default: the model lab's findings).
    pub constants: Vec<sim::constants::ModelConstants>,
    /// A model extension on every servo (what the lab found, to see whether it closes the gap).
    pub extension: Option<sim::extension::ModelExtension>,
    /// Mechanics step, s.
    pub dt: f64,
    /// Consecutive stretches of the box each register's error is also given over.
    pub windows: usize,
}

/// The longest stretch of traffic replayed, s: a box holds minutes (`longest-box-seconds`);
/// a span of days is a damaged clock, not hours of simulation to step through.
pub const MAX_SPAN_S: f64 = 3600.0;
/// The most stretches a register's error is given over.
pub const MAX_WINDOWS: usize = 1000;

/// A box that cannot be replayed.
#[derive(Debug, Error)]
pub enum ReplayError {
    /// Nothing of the wire in it.
    #[error("the box holds no bus traffic (no {} messages): nothing to replay", Channel::Wire.topic())]
    NoWire,
    /// A bus the description does not have.
    #[error("the box's bus {bus:?} is not in the robot description (it has: {have})")]
    UnknownBus {
        /// The box's bus.
        bus: String,
        /// The description's buses.
        have: String,
    },
    /// The box's robot is not the one described.
    #[error(
        "the box's {joint} (bus {bus}, servo {id}) is {found}, the description has {described}: \
         replay into the robot the box was recorded on (--description)"
    )]
    OtherRobot {
        /// The joint.
        joint: String,
        /// Its bus.
        bus: String,
        /// Its servo id.
        id: u8,
        /// What the box's layout says.
        found: String,
        /// What the description says.
        described: String,
    },
    /// Traffic over a span no box holds.
    #[error("the box's bus traffic spans {0:.0} s, over the {MAX_SPAN_S} s a replay steps through (its clock is damaged)")]
    Span(f64),
    /// Settings that cannot be simulated.
    #[error("replay settings: {0}")]
    Settings(String),
}

/// What a replay found.
#[derive(Debug, Clone, Serialize)]
pub struct Replay {
    /// From the box's first bus chunk to its last, s.
    pub duration_s: f64,
    /// How far the box could be read.
    pub extent: Extent,
    /// Wire messages that could not be read: their traffic is left out.
    pub undecodable_wire_messages: u64,
    /// Each bus the box holds traffic of.
    pub buses: Vec<BusReplay>,
}

/// One bus replayed.
#[derive(Debug, Clone, Serialize)]
pub struct BusReplay {
    /// Its name.
    pub bus: String,
    /// Instructions delivered to the simulator.
    pub instructions: u64,
    /// Transactions replayed (the instructions sent before the driver read their answers).
    pub transactions: u64,
    /// Driver cycles between the box's first and last with no record of this bus (lost
    /// before the box, or nothing moved on it).
    pub cycles_missing: u64,
    /// The box's layout named this bus's servos and the description agreed (false: no
    /// layout of this bus in the box, nothing checked).
    pub layout_checked: bool,
    /// Writes that failed on the robot (not delivered: what went out is unknown).
    pub failed_sends: u64,
    /// Times the robot's driver opened its device again.
    pub reopens: u64,
    /// Bytes the driver's tap lost (cycles whose traffic is incomplete).
    pub lost_bytes: u64,
    /// Recorded replies that are not valid status packets (a damaged line).
    pub undecodable_replies: u64,
    /// Recorded replies that answer no read of their transaction: an answer that came after
    /// the driver gave up on it, read with the next one's.
    pub stray_replies: u64,
    /// Recorded bytes that arrived before any instruction of the box.
    pub orphan_bytes: u64,
    /// Each servo of the bus, in the description's order.
    pub servos: Vec<ServoReplay>,
}

/// One servo's replies, simulated against recorded.
#[derive(Debug, Clone, Serialize)]
pub struct ServoReplay {
    /// Its id.
    pub id: u8,
    /// Its joint.
    pub joint: String,
    /// Where it was placed before the first instruction (as the box first read it).
    pub placed: Placed,
    /// Replies both gave.
    pub compared: u64,
    /// The servo answered and the simulator did not.
    pub only_recorded: u64,
    /// The simulator answered and the servo did not (a silent servo, a lost reply).
    pub only_simulated: u64,
    /// Every register read back, in address order.
    pub registers: Vec<RegisterFit>,
}

/// How a servo was placed: what the box says it held at its start (`None`: the box never
/// read it before writing it, or never read it at all; the simulator's own value stands).
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct Placed {
    /// Stored settings (EEPROM) the box read, of those it has (a box that holds the driver's
    /// set-up has them all; one from the middle of a run none, and the simulator's factory
    /// settings stand).
    pub settings: usize,
    /// `Present_Position`, steps.
    pub position: Option<i32>,
    /// `Present_Temperature`, °C.
    pub temperature_c: Option<i32>,
    /// `Torque_Enable`.
    pub torque_enable: Option<i32>,
}

/// One register: simulated − recorded, in the register's unit.
#[derive(Debug, Clone, Serialize)]
pub struct RegisterFit {
    /// Its name (Feetech's).
    pub register: &'static str,
    /// The unit of the figures (`count` for one without a unit).
    pub unit: &'static str,
    /// Readings compared.
    pub n: u64,
    /// Readings that differ at all.
    pub differ: u64,
    /// Error figures over the whole box.
    pub error: ErrorFigures,
    /// The same over consecutive stretches of the box (a misfit that grows shows here).
    pub windows: Vec<WindowFit>,
}

/// Mean, root-mean-square and largest error.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct ErrorFigures {
    /// Mean of simulated − recorded.
    pub bias: f64,
    /// Root mean square of simulated − recorded.
    pub rms: f64,
    /// Largest |simulated − recorded|.
    pub max_abs: f64,
}

/// A register's error over one stretch of the box.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct WindowFit {
    /// From, s since the box's first chunk.
    pub from_s: f64,
    /// To, s.
    pub to_s: f64,
    /// Readings compared.
    pub n: u64,
    /// Error figures.
    pub error: ErrorFigures,
}

/// Replays `bytes`, a box, into the simulator set up by `setup`.
pub fn replay(bytes: &[u8], setup: &Setup) -> Result<Replay, ReplayError> {
    if !(setup.dt > 0.0 && setup.dt <= 0.005) {
        return Err(ReplayError::Settings(format!(
            "the mechanics step must be in (0, 5] ms, got {} s",
            setup.dt
        )));
    }
    if !(setup.thermal_speedup.is_finite() && setup.thermal_speedup >= 1.0) {
        return Err(ReplayError::Settings(format!(
            "the thermal speed-up must be ≥ 1, got {}",
            setup.thermal_speedup
        )));
    }
    if !(1..=MAX_WINDOWS).contains(&setup.windows) {
        return Err(ReplayError::Settings(format!(
            "the stretches must number 1 to {MAX_WINDOWS}, got {}",
            setup.windows
        )));
    }
    let recorded = Recorded::read(bytes);
    let (Some(t0), Some(t1)) = (recorded.first_ns(), recorded.last_ns()) else {
        return Err(ReplayError::NoWire);
    };
    let clock = Clock {
        t0_ns: t0,
        duration_s: (t1 - t0) as f64 * 1e-9,
        windows: setup.windows,
    };
    if clock.duration_s > MAX_SPAN_S {
        return Err(ReplayError::Span(clock.duration_s));
    }
    let buses = recorded
        .buses
        .iter()
        .map(|(name, traffic)| replay_bus(name, traffic, &recorded.layout, setup, &clock))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Replay {
        duration_s: clock.duration_s,
        extent: recorded.extent,
        undecodable_wire_messages: recorded.undecodable,
        buses,
    })
}

/// The box's traffic, per bus, and its layout.
struct Recorded {
    buses: BTreeMap<String, Traffic>,
    layout: Vec<LayoutJoint>,
    extent: Extent,
    /// Wire messages that could not be read (their bus unknown, their traffic left out).
    undecodable: u64,
}

/// One bus's chunks in time order, the bytes its tap lost, and the driver cycles it has.
#[derive(Default)]
struct Traffic {
    chunks: Vec<WireChunk>,
    lost_bytes: u64,
    cycles: Vec<u64>,
}

impl Traffic {
    /// Driver cycles between the first and the last with no record of this bus: lost before
    /// the box (the recorder's queue overwritten) or cycles that moved nothing on it.
    fn cycles_missing(&self) -> u64 {
        let mut c = self.cycles.clone();
        c.sort_unstable();
        c.dedup();
        c.windows(2).map(|w| w[1] - w[0] - 1).sum()
    }
}

impl Recorded {
    fn read(bytes: &[u8]) -> Recorded {
        let mut buses: BTreeMap<String, Traffic> = BTreeMap::new();
        let mut layout = Vec::new();
        let mut undecodable = 0;
        let extent = visit(bytes, &mut |item| {
            let Item::Message { topic, data, .. } = item else {
                return;
            };
            match Channel::from_topic(topic) {
                Some(Channel::Wire) => match wire_chunks(data) {
                    Some(w) => {
                        let traffic = buses.entry(w.bus).or_default();
                        traffic.lost_bytes += w.lost_bytes;
                        traffic.cycles.push(w.cycle);
                        traffic.chunks.extend(w.chunks);
                    }
                    None => undecodable += 1,
                },
                Some(Channel::Layout) => {
                    let joints = serde_json::from_slice::<serde_json::Value>(data)
                        .ok()
                        .and_then(|v| serde_json::from_value(v["joints"].clone()).ok());
                    if let Some(joints) = joints {
                        layout = joints;
                    }
                }
                _ => {}
            }
        });
        for traffic in buses.values_mut() {
            // Stable: chunks of one time keep the order they went in.
            traffic.chunks.sort_by_key(|c| c.0);
        }
        Recorded {
            buses,
            layout,
            extent,
            undecodable,
        }
    }

    fn first_ns(&self) -> Option<u64> {
        self.buses
            .values()
            .filter_map(|t| t.chunks.first())
            .map(|c| c.0)
            .min()
    }

    fn last_ns(&self) -> Option<u64> {
        self.buses
            .values()
            .filter_map(|t| t.chunks.last())
            .map(|c| c.0)
            .max()
    }
}

/// The box's time: where it starts, how long it is, and its stretches.
struct Clock {
    t0_ns: u64,
    duration_s: f64,
    windows: usize,
}

impl Clock {
    fn seconds(&self, t_ns: u64) -> f64 {
        t_ns.saturating_sub(self.t0_ns) as f64 * 1e-9
    }

    fn window(&self, t_s: f64) -> usize {
        if self.duration_s <= 0.0 {
            return 0;
        }
        ((t_s / self.duration_s * self.windows as f64) as usize).min(self.windows - 1)
    }
}

/// Instructions the driver sent before it read their answers, and the bytes it read.
#[derive(Default)]
struct Transaction {
    /// Each instruction write: when, and its bytes.
    sent: Vec<(u64, Vec<u8>)>,
    /// The replies its instructions ask for, in the order they come.
    reads: Vec<Read>,
    /// What came back.
    received: Vec<u8>,
    /// A line rate set before it.
    baud: Option<u32>,
}

/// A reply an instruction asks for: from servo `id`, the `len` bytes at `addr` (none for a
/// PING or a WRITE's acknowledgement).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Read {
    id: u8,
    addr: u8,
    len: u8,
}

/// What happened on the line besides transactions.
#[derive(Default)]
struct LineCounts {
    failed_sends: u64,
    reopens: u64,
    orphan_bytes: u64,
}

/// Groups a bus's chunks into transactions: the driver drops its input before each request it
/// waits an answer for, which starts one; so do a failed write, a reopen and a change of rate.
/// Without those marks (another driver), an instruction sent after answers were read starts
/// one (the line is half duplex). Writes sent before the answers come (a broadcast torque-off
/// between a read-back and its collection) stay in the read's transaction.
fn transactions(chunks: &[WireChunk], counts: &mut LineCounts) -> Vec<Transaction> {
    let mut out: Vec<Transaction> = Vec::new();
    let mut open = false;
    let mut baud = None;
    for (t, direction, bytes) in chunks {
        match direction {
            Direction::Sent => {
                let answered = out
                    .last()
                    .is_some_and(|tx| !tx.reads.is_empty() && !tx.received.is_empty());
                if !open || answered {
                    out.push(Transaction {
                        baud: baud.take(),
                        ..Transaction::default()
                    });
                    open = true;
                }
                if let Some(tx) = out.last_mut() {
                    reads(bytes, &mut tx.reads);
                    tx.sent.push((*t, bytes.clone()));
                }
            }
            Direction::Received => match out.last_mut().filter(|_| open) {
                Some(tx) => tx.received.extend_from_slice(bytes),
                None => counts.orphan_bytes += bytes.len() as u64,
            },
            Direction::Discarded => open = false,
            Direction::SendFailed => {
                counts.failed_sends += 1;
                open = false;
            }
            Direction::Reopened => {
                counts.reopens += 1;
                open = false;
            }
            Direction::BaudChanged => {
                open = false;
                if let Ok(b) = <[u8; 4]>::try_from(bytes.as_slice()) {
                    baud = Some(u32::from_le_bytes(b));
                }
            }
        }
    }
    out
}

/// Appends the replies the instructions in `bytes` ask for (a broadcast PING, which any servo
/// may answer, is not compared; what does not parse is left to the simulator, which counts it).
fn reads(bytes: &[u8], out: &mut Vec<Read>) {
    for frame in frames(bytes).0 {
        let Ok(i) = Instruction::parse(&frame) else {
            continue;
        };
        match i {
            Instruction::Read { id, addr, len } => out.push(Read { id, addr, len }),
            Instruction::SyncRead { addr, len, ids } => {
                out.extend(ids.iter().map(|&id| Read { id, addr, len }));
            }
            other if other.expects_reply() && other.id() != feetech::BROADCAST_ID => {
                out.push(Read {
                    id: other.id(),
                    addr: 0,
                    len: 0,
                });
            }
            _ => {}
        }
    }
}

/// The well-formed packets in `bytes`, and how many framing errors lay between them.
fn frames(bytes: &[u8]) -> (Vec<feetech::Frame>, u64) {
    let mut decoder = Decoder::new();
    let mut out = Vec::new();
    let mut errors = 0;
    let mut keep = |r: Result<feetech::Frame, feetech::DecodeError>| match r {
        Ok(f) => out.push(f),
        Err(_) => errors += 1,
    };
    let mut rest = bytes;
    while !rest.is_empty() {
        let taken = decoder.push(rest);
        rest = &rest[taken..];
        while let Some(r) = decoder.next_frame() {
            keep(r);
        }
    }
    while let Some(r) = decoder.finish() {
        keep(r);
    }
    (out, errors)
}

/// A status packet: its servo and the bytes it returned.
struct Reply {
    id: u8,
    params: Vec<u8>,
}

/// The status packets in `bytes`, and how many packets or fragments were not valid ones.
fn replies(bytes: &[u8]) -> (Vec<Reply>, u64) {
    let (frames, mut bad) = frames(bytes);
    let mut out = Vec::with_capacity(frames.len());
    for f in &frames {
        match StatusPacket::parse(f) {
            Ok(p) => out.push(Reply {
                id: p.id,
                params: p.params.to_vec(),
            }),
            Err(_) => bad += 1,
        }
    }
    (out, bad)
}

/// The first reply not taken yet that answers `read` (its servo, as many bytes as it asked
/// for), taken. A reply of another length is another read's: a late answer to an earlier one.
fn take<'r>(replies: &'r [Reply], taken: &mut [bool], read: Read) -> Option<&'r Reply> {
    let answers = |r: &Reply| r.id == read.id && r.params.len() == usize::from(read.len);
    let k = (0..replies.len()).find(|&k| !taken[k] && answers(&replies[k]))?;
    taken[k] = true;
    Some(&replies[k])
}

/// The registers a read of `read` covers whole, with their offset in its reply.
fn covered(read: Read) -> impl Iterator<Item = (usize, usize, &'static Register)> {
    let (from, to) = (
        u16::from(read.addr),
        u16::from(read.addr) + u16::from(read.len),
    );
    TABLE.iter().enumerate().filter_map(move |(k, r)| {
        let (a, end) = (u16::from(r.addr), u16::from(r.addr) + u16::from(r.size));
        (a >= from && end <= to).then(|| (k, usize::from(a - from), r))
    })
}

/// What the box says a servo held at its start, byte by byte of its control table: the first
/// reading of each byte that no write the box holds went to before it.
type FirstSeen = [Option<u8>; TABLE_SIZE];

/// Calls `f(id, first address, length)` for each write in `bytes` (`BROADCAST_ID`: every
/// servo).
fn writes(bytes: &[u8], f: &mut dyn FnMut(u8, usize, usize)) {
    for frame in frames(bytes).0 {
        match Instruction::parse(&frame) {
            Ok(
                Instruction::Write { id, addr, data } | Instruction::RegWrite { id, addr, data },
            ) => {
                f(id, usize::from(addr), data.len());
            }
            Ok(i @ Instruction::SyncWrite { addr, len, .. }) => {
                for (id, _) in i.sync_write_records() {
                    f(id, usize::from(addr), usize::from(len));
                }
            }
            _ => {}
        }
    }
}

/// Each servo's state at the box's start, as far as the box tells it ([`FirstSeen`]).
fn first_seen(txs: &[Transaction]) -> BTreeMap<u8, FirstSeen> {
    let mut out: BTreeMap<u8, FirstSeen> = BTreeMap::new();
    let mut written: BTreeMap<u8, [bool; TABLE_SIZE]> = BTreeMap::new();
    let mut broadcast = [false; TABLE_SIZE];
    for tx in txs {
        // A transaction's writes go before the answers to its reads.
        for (_, bytes) in &tx.sent {
            writes(bytes, &mut |id, addr, len| {
                let mask = match id {
                    feetech::BROADCAST_ID => &mut broadcast,
                    id => written.entry(id).or_insert([false; TABLE_SIZE]),
                };
                for slot in mask.iter_mut().skip(addr).take(len) {
                    *slot = true;
                }
            });
        }
        let (recorded, _) = replies(&tx.received);
        let mut taken = vec![false; recorded.len()];
        for read in &tx.reads {
            let Some(r) = take(&recorded, &mut taken, *read) else {
                continue;
            };
            let mask = written.get(&read.id);
            let table = out.entry(read.id).or_insert([None; TABLE_SIZE]);
            for (k, b) in r.params.iter().enumerate() {
                let at = usize::from(read.addr) + k;
                let overwritten = broadcast.get(at) == Some(&true)
                    || mask.is_some_and(|m| m.get(at) == Some(&true));
                match table.get_mut(at) {
                    Some(slot) if !overwritten => {
                        slot.get_or_insert(*b);
                    }
                    _ => {}
                }
            }
        }
    }
    out
}

/// The bytes of `r` first seen, if all were.
fn seen_bytes(seen: &FirstSeen, r: Register) -> Option<Vec<u8>> {
    (0..usize::from(r.size))
        .map(|k| seen.get(usize::from(r.addr) + k).copied().flatten())
        .collect()
}

fn seen_value(seen: &FirstSeen, r: Register) -> Option<i32> {
    r.decode(&seen_bytes(seen, r)?)
}

/// Settings placed from the box before the working ones, in address order: the stored
/// settings (limits, protections, gains, mode), less the id and the line rate, which the
/// simulated bus already has right.
fn stored_settings() -> impl Iterator<Item = &'static Register> {
    TABLE.iter().filter(|r| {
        r.area == feetech::registers::Area::Eeprom && *r != &reg::ID && *r != &reg::BAUD_RATE
    })
}

/// Puts servo `id` of `bus` as the box says it was at its start: its position and temperature,
/// its stored settings, then the working ones (the torque limit and the goal before the
/// torque). A wheel's mode not in the box is the speed mode the driver runs wheels in.
fn place(bus: &mut SimBus, id: u8, seen: Option<&FirstSeen>, wheel: bool) -> Placed {
    let Some(servo) = bus.servo_mut(id) else {
        return Placed::default();
    };
    let none = [None; TABLE_SIZE];
    let seen = seen.unwrap_or(&none);
    let placed = Placed {
        position: seen_value(seen, reg::PRESENT_POSITION),
        temperature_c: seen_value(seen, reg::PRESENT_TEMPERATURE),
        torque_enable: seen_value(seen, reg::TORQUE_ENABLE),
        settings: stored_settings()
            .filter(|r| seen_bytes(seen, **r).is_some())
            .count(),
    };
    let angle = placed
        .position
        .map_or(servo.angle, |p| servo.angle_of_present(p));
    let temperature = placed.temperature_c.map_or(servo.temperature, f64::from);
    servo.place(angle, temperature);
    if wheel && seen_value(seen, reg::OPERATING_MODE).is_none() {
        servo.write(reg::OPERATING_MODE.addr, &[SPEED_MODE]);
    }
    let working = [
        &reg::TORQUE_LIMIT,
        &reg::ACCELERATION,
        &reg::GOAL_VELOCITY,
        &reg::GOAL_POSITION,
        &reg::TORQUE_ENABLE,
    ];
    for r in stored_settings().chain(working) {
        if let Some(bytes) = seen_bytes(seen, *r) {
            servo.write(r.addr, &bytes);
        }
    }
    placed
}

/// `Operating_Mode` of the speed mode (wheels).
const SPEED_MODE: u8 = 1;

/// Sums of one register's errors.
#[derive(Debug, Clone, Copy, Default)]
struct Moments {
    n: u64,
    sum: f64,
    sum2: f64,
    max_abs: f64,
}

impl Moments {
    fn add(&mut self, e: f64) {
        self.n += 1;
        self.sum += e;
        self.sum2 += e * e;
        self.max_abs = self.max_abs.max(e.abs());
    }

    fn figures(&self) -> ErrorFigures {
        if self.n == 0 {
            return ErrorFigures::default();
        }
        let n = self.n as f64;
        ErrorFigures {
            bias: self.sum / n,
            rms: (self.sum2 / n).sqrt(),
            max_abs: self.max_abs,
        }
    }
}

/// One register's errors, over the box and per stretch.
#[derive(Debug, Clone)]
struct RegisterSums {
    differ: u64,
    all: Moments,
    windows: Vec<Moments>,
}

/// One servo's comparison so far.
struct ServoSums {
    compared: u64,
    only_recorded: u64,
    only_simulated: u64,
    registers: Vec<RegisterSums>,
}

impl ServoSums {
    fn new(windows: usize) -> ServoSums {
        let empty = RegisterSums {
            differ: 0,
            all: Moments::default(),
            windows: vec![Moments::default(); windows],
        };
        ServoSums {
            compared: 0,
            only_recorded: 0,
            only_simulated: 0,
            registers: vec![empty; TABLE.len()],
        }
    }

    /// Adds the registers of a reply to `read`, recorded and simulated.
    fn add(&mut self, read: Read, recorded: &[u8], simulated: &[u8], window: usize) {
        for (k, offset, r) in covered(read) {
            let value = |p: &[u8]| p.get(offset..).and_then(|b| r.decode(b));
            let (Some(a), Some(b)) = (value(recorded), value(simulated)) else {
                continue;
            };
            let e = f64::from(b - a) * r.unit.scale().0;
            let sums = &mut self.registers[k];
            sums.differ += u64::from(a != b);
            sums.all.add(e);
            if let Some(w) = sums.windows.get_mut(window) {
                w.add(e);
            }
        }
    }

    fn fits(&self, clock: &Clock) -> Vec<RegisterFit> {
        let span = clock.duration_s / clock.windows as f64;
        TABLE
            .iter()
            .zip(&self.registers)
            .filter(|(_, s)| s.all.n > 0)
            .map(|(r, s)| RegisterFit {
                register: r.name,
                unit: r.unit.scale().1,
                n: s.all.n,
                differ: s.differ,
                error: s.all.figures(),
                windows: s
                    .windows
                    .iter()
                    .enumerate()
                    .map(|(w, m)| WindowFit {
                        from_s: w as f64 * span,
                        to_s: (w + 1) as f64 * span,
                        n: m.n,
                        error: m.figures(),
                    })
                    .collect(),
            })
            .collect()
    }
}

/// What a transaction's recorded replies held besides the answers paired.
#[derive(Default)]
struct Leftover {
    /// Bytes that are not valid status packets.
    undecodable: u64,
    /// Valid replies that answer no read of the transaction (late answers to earlier ones).
    stray: u64,
}

/// Pairs a transaction's replies, recorded and simulated, servo by servo, and adds them to
/// `sums`; gives what of the recorded replies answered nothing.
fn compare(
    tx: &Transaction,
    simulated: &[u8],
    window: usize,
    sums: &mut BTreeMap<u8, ServoSums>,
) -> Leftover {
    let (recorded, undecodable) = replies(&tx.received);
    let (simulated, _) = replies(simulated);
    let mut taken_recorded = vec![false; recorded.len()];
    let mut taken_simulated = vec![false; simulated.len()];
    for &read in &tx.reads {
        let Some(servo) = sums.get_mut(&read.id) else {
            continue;
        };
        let r = take(&recorded, &mut taken_recorded, read);
        let s = take(&simulated, &mut taken_simulated, read);
        match (r, s) {
            (Some(r), Some(s)) => {
                servo.compared += 1;
                servo.add(read, &r.params, &s.params, window);
            }
            (Some(_), None) => servo.only_recorded += 1,
            (None, Some(_)) => servo.only_simulated += 1,
            (None, None) => {}
        }
    }
    Leftover {
        undecodable,
        stray: taken_recorded.iter().filter(|t| !**t).count() as u64,
    }
}

/// The box's layout agrees with the description on bus `name`: each joint's servo there, of
/// the model the box read.
fn check_layout(
    name: &str,
    described: &sim::description::BusDescription,
    layout: &[LayoutJoint],
    robot: &RobotDescription,
) -> Result<(), ReplayError> {
    for j in layout.iter().filter(|j| j.bus == name) {
        let servo = described.servo.iter().find(|s| s.id == j.id);
        let model = servo.and_then(|s| robot.rating(&s.model)).map(|r| r.model);
        if model.map(|m| m.model_number()) == Some(j.model) {
            continue;
        }
        let found = feetech::ServoModel::from_model_number(j.model)
            .map_or(format!("model number {}", j.model), |m| m.key().to_string());
        return Err(ReplayError::OtherRobot {
            joint: j.name.clone(),
            bus: name.to_string(),
            id: j.id,
            found,
            described: servo.map_or("no servo with that id".to_string(), |s| {
                format!("{} at {}", s.model, s.joint)
            }),
        });
    }
    Ok(())
}

/// Replays one bus's traffic.
fn replay_bus(
    name: &str,
    traffic: &Traffic,
    layout: &[LayoutJoint],
    setup: &Setup,
    clock: &Clock,
) -> Result<BusReplay, ReplayError> {
    let Some(described) = setup.robot.bus(name) else {
        return Err(ReplayError::UnknownBus {
            bus: name.to_string(),
            have: setup
                .robot
                .bus
                .iter()
                .map(|b| b.name.as_str())
                .collect::<Vec<_>>()
                .join(", "),
        });
    };
    check_layout(name, described, layout, &setup.robot)?;
    let mut bus = SimBus::new(&setup.robot, described);
    bus.thermal_speedup = setup.thermal_speedup;
    for c in &setup.constants {
        bus.apply_constants(c);
    }
    if let Some(m) = &setup.extension {
        bus.apply_extension(m);
    }
    let mut counts = LineCounts::default();
    let txs = transactions(&traffic.chunks, &mut counts);
    let seen = first_seen(&txs);
    let wheels = described.wheels.as_ref().map(|w| w.servos.as_slice());
    let placed: Vec<Placed> = described
        .servo
        .iter()
        .map(|s| {
            let wheel = wheels.is_some_and(|w| w.contains(&s.id));
            place(&mut bus, s.id, seen.get(&s.id), wheel)
        })
        .collect();
    let mut sums: BTreeMap<u8, ServoSums> = described
        .servo
        .iter()
        .map(|s| (s.id, ServoSums::new(clock.windows)))
        .collect();
    let (mut instructions, mut undecodable, mut stray) = (0, 0, 0);
    let mut simulated = Vec::new();
    for tx in &txs {
        if let Some(b) = tx.baud {
            bus.set_host_baud(b);
        }
        simulated.clear();
        for (t, bytes) in &tx.sent {
            let now = clock.seconds(*t);
            bus.advance_to(now, setup.dt);
            bus.receive(now, bytes);
            instructions += frames(bytes).0.len() as u64;
            while let Some(r) = bus.pop_due(f64::INFINITY) {
                simulated.extend_from_slice(&r.bytes);
            }
        }
        let t = clock.seconds(tx.sent.first().map_or(0, |s| s.0));
        let left = compare(tx, &simulated, clock.window(t), &mut sums);
        undecodable += left.undecodable;
        stray += left.stray;
    }
    let servos = described
        .servo
        .iter()
        .zip(placed)
        .filter_map(|(s, placed)| {
            let sums = sums.get(&s.id)?;
            Some(ServoReplay {
                id: s.id,
                joint: s.joint.clone(),
                placed,
                compared: sums.compared,
                only_recorded: sums.only_recorded,
                only_simulated: sums.only_simulated,
                registers: sums.fits(clock),
            })
        })
        .collect();
    Ok(BusReplay {
        bus: name.to_string(),
        instructions,
        transactions: txs.len() as u64,
        cycles_missing: traffic.cycles_missing(),
        layout_checked: layout.iter().any(|j| j.bus == name),
        failed_sends: counts.failed_sends,
        reopens: counts.reopens,
        lost_bytes: traffic.lost_bytes,
        undecodable_replies: undecodable,
        stray_replies: stray,
        orphan_bytes: counts.orphan_bytes,
        servos,
    })
}

/// The registers a summary shows, in its columns.
const SUMMARY_REGISTERS: [Register; 5] = [
    reg::PRESENT_POSITION,
    reg::PRESENT_LOAD,
    reg::PRESENT_CURRENT,
    reg::PRESENT_TEMPERATURE,
    reg::PRESENT_VOLTAGE,
];

/// A replay as text: per bus what was replayed, per servo each feedback register's bias and
/// RMS error, and how the worst temperature error runs over the box.
pub fn summary(replay: &Replay, source: &str) -> String {
    use std::fmt::Write as _;
    let mut out = String::new();
    let _ = writeln!(
        out,
        "nori sim replay {source}: {:.1} s of bus traffic{}; simulated − recorded, bias / rms",
        replay.duration_s,
        match (replay.extent.complete, replay.extent.bad_chunks) {
            (true, 0) => String::new(),
            (complete, bad) => format!(
                " ({}{bad} damaged chunks)",
                if complete { "" } else { "cut short, " }
            ),
        }
    );
    for b in &replay.buses {
        let _ = writeln!(
            out,
            "bus {}: {} instructions in {} transactions; {} failed writes, {} lost bytes, {} \
             damaged replies, {} late",
            b.bus,
            b.instructions,
            b.transactions,
            b.failed_sends,
            b.lost_bytes,
            b.undecodable_replies,
            b.stray_replies
        );
        if !b.layout_checked {
            let _ = writeln!(
                out,
                "  no layout of this bus in the box: its servos are taken to be the \
                 description's, unchecked"
            );
        }
        if b.cycles_missing + b.reopens + b.orphan_bytes > 0 {
            let _ = writeln!(
                out,
                "  {} driver cycles with no record of the bus, {} reopens, {} bytes read \
                 before any instruction",
                b.cycles_missing, b.reopens, b.orphan_bytes
            );
        }
        let factory = b.servos.iter().filter(|s| s.placed.settings == 0).count();
        if factory > 0 {
            let _ = writeln!(
                out,
                "  {factory} servos' stored settings (limits, protections, gains) are not in \
                 the box (it starts after the driver's set-up): the simulator's factory \
                 settings stand"
            );
        }
        let _ = write!(out, "  {:<22} {:>7}", "joint", "replies");
        for r in SUMMARY_REGISTERS {
            let head = format!("{} {}", short_name(r), r.unit.scale().1);
            let _ = write!(out, " {head:>17}");
        }
        out.push('\n');
        for s in &b.servos {
            let _ = write!(out, "  {:<22} {:>7}", s.joint, s.compared);
            for r in SUMMARY_REGISTERS {
                let cell = s
                    .registers
                    .iter()
                    .find(|f| f.register == r.name)
                    .map_or("–".to_string(), |f| {
                        format!("{:+.2}/{:.2}", f.error.bias, f.error.rms)
                    });
                let _ = write!(out, " {cell:>17}");
            }
            out.push('\n');
            if s.placed.torque_enable.is_none() {
                let _ = writeln!(
                    out,
                    "  {:<22} its torque was not read before it was written: placed off",
                    ""
                );
            }
            if s.only_recorded + s.only_simulated > 0 {
                let _ = writeln!(
                    out,
                    "  {:<22} {} replies only the servo gave, {} only the simulator",
                    "", s.only_recorded, s.only_simulated
                );
            }
        }
        if let Some((joint, fit)) = worst(b, reg::PRESENT_TEMPERATURE) {
            let runs: Vec<String> = fit
                .windows
                .iter()
                .map(|w| format!("{:+.2}", w.error.bias))
                .collect();
            let _ = writeln!(
                out,
                "  temperature bias per stretch of {:.1} s, worst servo ({joint}): {}",
                replay.duration_s / fit.windows.len().max(1) as f64,
                runs.join(" ")
            );
        }
    }
    out
}

/// A register's name without Feetech's `Present_` prefix.
fn short_name(r: Register) -> String {
    r.name
        .trim_start_matches("Present_")
        .to_lowercase()
        .replace('_', " ")
}

/// The servo of `b` whose `r` misfits most (by RMS), and its figures.
fn worst(b: &BusReplay, r: Register) -> Option<(&str, &RegisterFit)> {
    b.servos
        .iter()
        .filter_map(|s| {
            let fit = s.registers.iter().find(|f| f.register == r.name)?;
            Some((s.joint.as_str(), fit))
        })
        .max_by(|a, b| a.1.error.rms.total_cmp(&b.1.error.rms))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use blackbox::channel::{to_json, wire, EventMessage, Names};
    use blackbox::frozen::BoxWriter;
    use blackbox::ring::Record;
    use sim::extension::ModelExtension;
    use telemetry::frames::JointLayout;
    use telemetry::wire::WireFrame;

    const BUS: &str = "left_arm";
    const CYCLE_NS: u64 = 5_000_000;
    const SPEEDUP: f64 = 60.0;

    /// A servo's status packet carrying `params`.
    fn status(id: u8, params: &[u8]) -> Vec<u8> {
        let mut buf = [0u8; feetech::MAX_PACKET];
        let p = StatusPacket {
            id,
            status: feetech::ServoStatus(0),
            params,
        };
        let n = p.encode(&mut buf).unwrap();
        buf[..n].to_vec()
    }

    fn packet(i: Instruction) -> Vec<u8> {
        let mut buf = [0u8; feetech::MAX_PACKET];
        let n = i.encode(&mut buf).unwrap();
        buf[..n].to_vec()
    }

    /// A driver's cycle on `bus` at `t_ns`: the feedback of every servo, one servo's settings
    /// read back in turn, and goals swinging each joint; what went on the wire, as the tap
    /// records it.
    fn cycle(bus: &mut SimBus, ids: &[u8], k: u64, frame: &mut WireFrame) {
        let t_ns = k * CYCLE_NS;
        let mut exchange = |bytes: Vec<u8>, at_ns: u64, frame: &mut WireFrame| {
            let now = at_ns as f64 * 1e-9;
            bus.advance_to(now, 0.001);
            bus.receive(now, &bytes);
            let mut answered = Vec::new();
            reads(&bytes, &mut answered);
            if !answered.is_empty() {
                // As the driver does before each request it waits an answer for.
                frame.record(Direction::Discarded, at_ns, &[]);
            }
            frame.record(Direction::Sent, at_ns, &bytes);
            let mut back = Vec::new();
            while let Some(r) = bus.pop_due(f64::INFINITY) {
                back.extend_from_slice(&r.bytes);
            }
            if !back.is_empty() {
                frame.record(Direction::Received, at_ns + 400_000, &back);
            }
        };
        let read = Instruction::SyncRead {
            addr: reg::FEEDBACK_ADDR,
            len: reg::FEEDBACK_LEN,
            ids,
        };
        exchange(packet(read), t_ns, frame);
        let id = ids[(k as usize) % ids.len()];
        let back = Instruction::Read {
            id,
            addr: reg::SAFETY_ADDR,
            len: reg::SAFETY_LEN,
        };
        exchange(packet(back), t_ns + 1_500_000, frame);
        let mut payload = Vec::new();
        for (n, &id) in ids.iter().enumerate() {
            let swing = 0.3 * (k as f64 * 0.004 + n as f64).sin();
            let raw = (2048.0 + swing / sim::servo::RAD_PER_STEP).round() as u16;
            payload.push(id);
            payload.extend_from_slice(&raw.to_le_bytes());
        }
        let goals = Instruction::SyncWrite {
            addr: reg::GOAL_POSITION.addr,
            len: 2,
            payload: &payload,
        };
        exchange(packet(goals), t_ns + 2_500_000, frame);
    }

    /// A box of `seconds` of the left arm driven through [`cycle`] on a simulator that runs
    /// `extension`, after 20 s of holding warm (the box starts mid-run, as a frozen one does).
    fn recorded_box(extension: Option<&ModelExtension>, seconds: f64) -> Vec<u8> {
        let robot = RobotDescription::nori_a3();
        let described = robot.bus(BUS).unwrap();
        let mut bus = SimBus::new(&robot, described);
        bus.thermal_speedup = SPEEDUP;
        if let Some(m) = extension {
            bus.apply_extension(m);
        }
        let ids: Vec<u8> = described.servo.iter().map(|s| s.id).collect();
        for &id in &ids {
            let s = bus.servo_mut(id).unwrap();
            let angle = s.angle;
            s.place(angle, 41.0 + f64::from(id) * 0.3);
            s.write(reg::TORQUE_ENABLE.addr, &[1]);
        }
        let mut layout = JointLayout {
            bus_count: 1,
            ..JointLayout::default()
        };
        layout.set_bus_name(0, BUS);
        let names = Names::from_layout(&layout);
        let trigger = EventMessage {
            timestamp_ns: 0,
            kind: "saved".into(),
            joint: None,
            bus: None,
            level: 0,
            value: 0.0,
        };
        let mut writer =
            BoxWriter::new(std::io::Cursor::new(Vec::new()), &trigger, "test", 0).unwrap();
        let warm = (20.0e9 / CYCLE_NS as f64) as u64;
        let end = warm + (seconds * 1e9 / CYCLE_NS as f64) as u64;
        for k in 0..end {
            let mut frame = WireFrame {
                cycle: k,
                ..WireFrame::default()
            };
            cycle(&mut bus, &ids, k, &mut frame);
            if k >= warm {
                let (t_ns, data) = wire(&frame, &names);
                let r = Record {
                    channel: Channel::Wire,
                    t_ns,
                    data: &data,
                };
                writer.write(r).unwrap();
            }
        }
        writer.finish().unwrap().into_inner()
    }

    fn setup(extension: Option<ModelExtension>) -> Setup {
        Setup {
            robot: RobotDescription::nori_a3(),
            thermal_speedup: SPEEDUP,
            constants: Vec::new(),
            extension,
            dt: 0.001,
            windows: 4,
        }
    }

    fn fit(s: &ServoReplay, r: Register) -> &RegisterFit {
        s.registers.iter().find(|f| f.register == r.name).unwrap()
    }

    fn offset(amps: f64) -> ModelExtension {
        let text = format!("format = 1\ncause = \"current_offset\"\ncurrent-offset-a = {amps}\n");
        ModelExtension::parse(&text, "offset.toml").unwrap()
    }

    #[test]
    fn a_box_replayed_into_the_simulator_that_recorded_it_agrees() {
        let bytes = recorded_box(None, 30.0);
        let r = replay(&bytes, &setup(None)).unwrap();
        eprintln!("{}", summary(&r, "the box"));
        assert!(r.extent.complete);
        assert!((r.duration_s - 30.0).abs() < 0.01, "{}", r.duration_s);
        let [b] = r.buses.as_slice() else {
            panic!("{:?}", r.buses.len())
        };
        assert_eq!(b.bus, BUS);
        let n = b.servos.len() as u64;
        assert_eq!(b.transactions, 3 * 6000);
        assert_eq!((b.cycles_missing, b.stray_replies), (0, 0));
        assert_eq!(b.instructions, 6000 * 3);
        assert_eq!(b.undecodable_replies + b.failed_sends + b.lost_bytes, 0);
        for s in &b.servos {
            // Every feedback read, and its share of the read-backs, paired.
            assert!(s.compared >= 6000 + 6000 / n, "{}: {}", s.joint, s.compared);
            assert_eq!(s.only_recorded + s.only_simulated, 0, "{}", s.joint);
            // Placed as the box first read it: warm, torque on.
            assert_eq!(s.placed.torque_enable, Some(1), "{}", s.joint);
            assert!(s.placed.temperature_c.unwrap() > 26, "{:?}", s.placed);
            let (pos, temp) = (
                fit(s, reg::PRESENT_POSITION),
                fit(s, reg::PRESENT_TEMPERATURE),
            );
            assert!(pos.error.rms < 0.1, "{} position {:?}", s.joint, pos.error);
            assert!(
                temp.error.rms < 0.6,
                "{} temperature {:?}",
                s.joint,
                temp.error
            );
            let current = fit(s, reg::PRESENT_CURRENT);
            assert!(
                current.error.bias.abs() < 0.02,
                "{} {:?}",
                s.joint,
                current.error
            );
            assert_eq!(fit(s, reg::TORQUE_ENABLE).differ, 0, "{}", s.joint);
            assert_eq!(pos.windows.len(), 4);
            assert_eq!(pos.windows.iter().map(|w| w.n).sum::<u64>(), pos.n);
        }
    }

    #[test]
    fn a_hidden_offset_shows_as_the_misfit_it_makes_and_closes_when_modelled() {
        let bytes = recorded_box(Some(&offset(0.2)), 10.0);
        let nominal = replay(&bytes, &setup(None)).unwrap();
        let modelled = replay(&bytes, &setup(Some(offset(0.2)))).unwrap();
        eprintln!("{}", summary(&nominal, "nominal"));
        eprintln!("{}", summary(&modelled, "modelled"));
        for (a, b) in nominal.buses[0]
            .servos
            .iter()
            .zip(&modelled.buses[0].servos)
        {
            let (missed, closed) = (
                fit(a, reg::PRESENT_CURRENT).error,
                fit(b, reg::PRESENT_CURRENT).error,
            );
            // The simulator reads 0.2 A less than the servo, within two counts of the
            // register (its rounding, and the heaviest joint's transients).
            assert!((missed.bias + 0.2).abs() < 0.013, "{} {missed:?}", a.joint);
            assert!(closed.bias.abs() < 0.013, "{} {closed:?}", b.joint);
            assert!(missed.max_abs >= 0.19, "{} {missed:?}", a.joint);
            let current = fit(a, reg::PRESENT_CURRENT);
            assert!(
                current.differ * 10 > current.n * 9,
                "{} {current:?}",
                a.joint
            );
            // Over every stretch of the box alike: an offset does not grow.
            for w in &current.windows {
                assert!(w.n > 0 && (w.error.bias + 0.2).abs() < 0.02, "{w:?}");
            }
            let pos = fit(a, reg::PRESENT_POSITION).error;
            assert!(pos.rms < 0.5, "{} {pos:?}", a.joint);
        }
    }

    #[test]
    fn the_driver_s_writes_are_grouped_until_their_answers_are_read() {
        let ping = |id| packet(Instruction::Ping { id });
        let write = packet(Instruction::Write {
            id: 3,
            addr: reg::TORQUE_ENABLE.addr,
            data: &[1],
        });
        let sync = packet(Instruction::SyncWrite {
            addr: reg::GOAL_POSITION.addr,
            len: 2,
            payload: &[1, 0, 8],
        });
        let chunks: Vec<WireChunk> = vec![
            (1, Direction::Received, vec![1, 2, 3]),
            (2, Direction::Sent, sync.clone()),
            (3, Direction::Sent, ping(1)),
            (4, Direction::Received, vec![0xFF]),
            (5, Direction::Received, vec![0xFF, 1]),
            (6, Direction::Sent, write.clone()),
            (7, Direction::Discarded, vec![]),
            (8, Direction::Received, vec![9]),
            (9, Direction::SendFailed, ping(2)),
            (
                10,
                Direction::BaudChanged,
                500_000u32.to_le_bytes().to_vec(),
            ),
            (11, Direction::Sent, sync.clone()),
            (12, Direction::Reopened, vec![]),
        ];
        let mut counts = LineCounts::default();
        let txs = transactions(&chunks, &mut counts);
        assert_eq!(
            (counts.orphan_bytes, counts.failed_sends, counts.reopens),
            (4, 1, 1)
        );
        assert_eq!(txs.len(), 3);
        assert_eq!(txs[0].sent.len(), 2, "a sync write then the ping answered");
        assert_eq!(
            txs[0].reads,
            vec![Read {
                id: 1,
                addr: 0,
                len: 0
            }]
        );
        assert_eq!(txs[0].received, vec![0xFF, 0xFF, 1]);
        assert_eq!(
            txs[1].reads,
            vec![Read {
                id: 3,
                addr: 0,
                len: 0
            }]
        );
        assert!(txs[1].received.is_empty(), "input dropped: not its answer");
        assert_eq!((txs[2].baud, txs[2].reads.len()), (Some(500_000), 0));

        // A read-back sent in the loop's idle time, the bus tripped (broadcast torque off)
        // before its answer is collected: the answer stays the read-back's.
        let off = packet(Instruction::Write {
            id: feetech::BROADCAST_ID,
            addr: reg::TORQUE_ENABLE.addr,
            data: &[0],
        });
        let chunks: Vec<WireChunk> = vec![
            (1, Direction::Discarded, vec![]),
            (2, Direction::Sent, ping(4)),
            (3, Direction::Sent, off.clone()),
            (4, Direction::Sent, off),
            (5, Direction::Received, vec![0xFF, 0xFF, 4]),
        ];
        let txs = transactions(&chunks, &mut counts);
        assert_eq!(txs.len(), 1);
        assert_eq!(txs[0].sent.len(), 3);
        assert_eq!(txs[0].received, vec![0xFF, 0xFF, 4]);
    }

    /// Seen in the overheat scenario's box: a read-back's answer that came after the driver
    /// gave up on it, read at the head of the next cycle's feedback.
    #[test]
    fn a_late_answer_to_an_earlier_read_is_not_taken_for_this_one() {
        let mut feedback = [0u8; reg::FEEDBACK_LEN as usize];
        feedback[..2].copy_from_slice(&2100u16.to_le_bytes());
        let read = Read {
            id: 5,
            addr: reg::FEEDBACK_ADDR,
            len: reg::FEEDBACK_LEN,
        };
        let mut received = status(5, &[1, 0, 0, 8, 0, 0, 0, 0, 0x20, 3]);
        received.extend(status(5, &feedback));
        let tx = Transaction {
            sent: vec![(0, Vec::new())],
            reads: vec![read],
            received,
            baud: None,
        };
        let mut sums = BTreeMap::from([(5, ServoSums::new(1))]);
        let left = compare(&tx, &status(5, &feedback), 0, &mut sums);
        assert_eq!((left.stray, left.undecodable), (1, 0));
        let servo = &sums[&5];
        assert_eq!((servo.compared, servo.only_recorded), (1, 0));
        let k = TABLE
            .iter()
            .position(|r| *r == reg::PRESENT_POSITION)
            .unwrap();
        assert_eq!(servo.registers[k].all.n, 1);
        assert_eq!(servo.registers[k].differ, 0);
    }

    /// A byte the box read after writing it tells nothing of the start; a stored setting read
    /// at the driver's set-up is placed, a wheel runs in speed mode.
    #[test]
    fn a_servo_is_placed_with_what_the_box_read_before_any_write() {
        let read = |id, r: Register| Read {
            id,
            addr: r.addr,
            len: r.size,
        };
        let enable = packet(Instruction::Write {
            id: 1,
            addr: reg::TORQUE_ENABLE.addr,
            data: &[1],
        });
        let txs = vec![
            Transaction {
                sent: vec![(0, enable)],
                reads: vec![read(1, reg::TORQUE_ENABLE)],
                received: status(1, &[1]),
                baud: None,
            },
            Transaction {
                sent: vec![(1, Vec::new())],
                reads: vec![
                    read(2, reg::MAX_TEMPERATURE_LIMIT),
                    read(2, reg::TORQUE_ENABLE),
                ],
                received: [status(2, &[60]), status(2, &[1])].concat(),
                baud: None,
            },
        ];
        let seen = first_seen(&txs);
        assert_eq!(seen_value(&seen[&1], reg::TORQUE_ENABLE), None);
        assert_eq!(seen_value(&seen[&2], reg::TORQUE_ENABLE), Some(1));
        let robot = RobotDescription::nori_a3();
        let mut bus = SimBus::new(&robot, robot.bus(BUS).unwrap());
        let placed = place(&mut bus, 2, seen.get(&2), false);
        assert_eq!((placed.settings, placed.torque_enable), (1, Some(1)));
        let servo = bus.servo_mut(2).unwrap();
        assert_eq!(servo.get(reg::MAX_TEMPERATURE_LIMIT), 60);
        assert!(servo.torque_enabled());
        let placed = place(&mut bus, 1, seen.get(&1), true);
        assert_eq!(placed.torque_enable, None);
        let servo = bus.servo_mut(1).unwrap();
        assert!(
            !servo.torque_enabled(),
            "unknown: left as the simulator has it"
        );
        assert_eq!(servo.get(reg::OPERATING_MODE), i32::from(SPEED_MODE));
    }

    #[test]
    fn a_box_without_traffic_or_of_another_robot_is_refused() {
        let trigger = EventMessage {
            timestamp_ns: 0,
            kind: "saved".into(),
            joint: None,
            bus: None,
            level: 0,
            value: 0.0,
        };
        let empty = BoxWriter::new(std::io::Cursor::new(Vec::new()), &trigger, "t", 0)
            .unwrap()
            .finish()
            .unwrap()
            .into_inner();
        assert!(matches!(
            replay(&empty, &setup(None)),
            Err(ReplayError::NoWire)
        ));
        // The box's layout has an STS3250 where the description has another model.
        let bytes = recorded_box(None, 0.05);
        let robot = RobotDescription::nori_a3();
        let elbow = robot
            .bus(BUS)
            .unwrap()
            .servo
            .iter()
            .find(|s| s.joint.contains("elbow"))
            .unwrap()
            .clone();
        let other = if elbow.model == "sts3250" { 777 } else { 2825 };
        let joint = LayoutJoint {
            name: elbow.joint.clone(),
            bus: BUS.into(),
            id: elbow.id,
            model: other,
            role: "joint".into(),
            range_rad: [-1.0, 1.0],
        };
        let layout = to_json(&serde_json::json!({ "timestamp_ns": 0, "joints": [joint] }));
        let mut w = BoxWriter::new(std::io::Cursor::new(Vec::new()), &trigger, "t", 0).unwrap();
        w.write(Record {
            channel: Channel::Layout,
            t_ns: 0,
            data: &layout,
        })
        .unwrap();
        let recorded = blackbox::frozen::read(&bytes);
        for m in &recorded.messages {
            w.write(Record {
                channel: Channel::Wire,
                t_ns: 0,
                data: &m.data,
            })
            .unwrap();
        }
        let mixed = w.finish().unwrap().into_inner();
        let err = replay(&mixed, &setup(None)).unwrap_err().to_string();
        assert!(
            err.contains(&elbow.joint) && err.contains("--description"),
            "{err}"
        );
        // A clock that jumps two hours: refused, not stepped through.
        let mut layout = JointLayout {
            bus_count: 1,
            ..JointLayout::default()
        };
        layout.set_bus_name(0, BUS);
        let mut w = BoxWriter::new(std::io::Cursor::new(Vec::new()), &trigger, "t", 0).unwrap();
        for t_ns in [1_000, 7_200_000_000_000] {
            let mut frame = WireFrame::default();
            frame.record(Direction::Sent, t_ns, &packet(Instruction::Ping { id: 1 }));
            let (t_ns, data) = wire(&frame, &Names::from_layout(&layout));
            w.write(Record {
                channel: Channel::Wire,
                t_ns,
                data: &data,
            })
            .unwrap();
        }
        let jumped = w.finish().unwrap().into_inner();
        assert!(matches!(
            replay(&jumped, &setup(None)),
            Err(ReplayError::Span(s)) if s > 7000.0
        ));
        let mut many = setup(None);
        many.windows = MAX_WINDOWS + 1;
        assert!(matches!(
            replay(&bytes, &many),
            Err(ReplayError::Settings(_))
        ));
        let mut unknown = setup(None);
        unknown.robot.bus.retain(|b| b.name != BUS);
        let err = replay(&bytes, &unknown).unwrap_err().to_string();
        assert!(
            err.contains("left_arm") && err.contains("not in the robot"),
            "{err}"
        );
    }
}
