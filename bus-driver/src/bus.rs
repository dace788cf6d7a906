//! Transactions on one bus: the per-cycle SYNC_READ / SYNC_WRITE pair, and the unicast reads and
//! writes of setup. Replies are matched by id; a servo that does not answer in time is missing
//! for that transaction, never given an older value.

use crate::transport::{Transport, TransportError};
use feetech::instruction::Instruction;
use feetech::registers::{self as reg, FeedbackBlock, Register, FEEDBACK_ADDR, FEEDBACK_LEN};
use feetech::timing::{status_bytes, sync_read_request_bytes, wire_time};
use feetech::{DecodeError, Decoder, ServoStatus, StatusPacket, BROADCAST_ID, MAX_PACKET};
use std::time::{Duration, Instant};
use thiserror::Error;

/// Why a unicast transaction failed.
#[derive(Debug, Error)]
pub enum BusError {
    /// The transport failed.
    #[error(transparent)]
    Transport(#[from] TransportError),
    /// No valid reply from the servo before the deadline.
    #[error("servo {id} did not answer within {waited_us} µs")]
    NoReply {
        /// Servo id.
        id: u8,
        /// How long we waited.
        waited_us: u64,
    },
    /// More than one servo answered a PING at one id.
    #[error(
        "more than one servo answers at id {id} ({answers} intact answers, {damaged} damaged): \
         two servos share the id (a new servo fitted at the factory's id?), or a noisy line \
         damaged the answer"
    )]
    NotAlone {
        /// Servo id.
        id: u8,
        /// Intact answers heard.
        answers: usize,
        /// Damaged packets heard (answers over each other).
        damaged: u64,
    },
    /// The reply carried the wrong amount of data.
    #[error("servo {id} answered {got} bytes, expected {expected}")]
    ShortReply {
        /// Servo id.
        id: u8,
        /// Bytes expected.
        expected: usize,
        /// Bytes received.
        got: usize,
    },
    /// The value does not fit the register.
    #[error("value {value} does not fit register {register}")]
    Encode {
        /// Register name.
        register: &'static str,
        /// The value asked for, in the register's units before encoding (0 when `register` is
        /// `instruction`: the packet itself did not encode).
        value: i32,
    },
}

/// Error counts by kind (the type the driver publishes on `nori/bus-health`).
pub use telemetry::frames::BusCounters;

/// Counts a decoder error by kind.
fn count(c: &mut BusCounters, e: DecodeError) {
    match e {
        DecodeError::Garbage { bytes } => c.garbage_bytes += bytes as u64,
        DecodeError::Checksum { .. } => c.checksum_errors += 1,
        DecodeError::InvalidId { .. }
        | DecodeError::InvalidLength { .. }
        | DecodeError::Truncated { .. } => c.framing_errors += 1,
    }
}

/// One bus and its scratch buffers (nothing allocates per cycle).
pub struct Bus<T: Transport> {
    transport: T,
    decoder: Decoder,
    tx: [u8; MAX_PACKET],
    // At most what the decoder can always take after draining (it keeps < one packet).
    rx: [u8; 256],
    margin: Duration,
    feedback_sent: Option<Instant>,
    /// A unicast READ started by [`Bus::request_read`]: when, and the expected reply's size.
    read_sent: Option<(Instant, u8, u8)>,
    /// Error counts.
    pub counters: BusCounters,
}

impl<T: Transport> Bus<T> {
    /// A bus over `transport`; replies later than their wire time plus `margin` are missing.
    pub fn new(transport: T, margin: Duration) -> Self {
        Bus {
            transport,
            decoder: Decoder::new(),
            tx: [0; MAX_PACKET],
            rx: [0; 256],
            margin,
            feedback_sent: None,
            read_sent: None,
            counters: BusCounters::default(),
        }
    }

    fn send(&mut self, instruction: Instruction) -> Result<(), BusError> {
        let n = instruction
            .encode(&mut self.tx)
            .map_err(|_| BusError::Encode {
                register: "instruction",
                value: 0,
            })?;
        self.transport
            .send(&self.tx[..n])
            .inspect_err(|_| self.counters.transport_errors += 1)?;
        Ok(())
    }

    fn start(&mut self) -> Result<(), BusError> {
        self.transport
            .discard_input()
            .inspect_err(|_| self.counters.transport_errors += 1)?;
        self.decoder.clear();
        Ok(())
    }

    /// The link under the bus (its wire tap, if it has one).
    pub fn transport_mut(&mut self) -> &mut T {
        &mut self.transport
    }

    /// The line rate, baud.
    pub fn baud(&self) -> u32 {
        self.transport.baud()
    }

    /// Talks at `baud` from now on (the device stays open), with no partial input kept.
    pub fn set_baud(&mut self, baud: u32) -> Result<(), BusError> {
        self.transport.set_baud(baud)?;
        self.decoder.clear();
        Ok(())
    }

    /// Opens the transport's device again and forgets any partial input.
    pub fn reopen(&mut self) -> Result<(), BusError> {
        self.transport.reopen()?;
        self.decoder.clear();
        self.feedback_sent = None;
        self.read_sent = None;
        Ok(())
    }

    /// Starts a feedback read (registers 56–70) of `ids`. Collect with [`Bus::collect_feedback`];
    /// in between, other buses can be started so their wire time overlaps.
    pub fn request_feedback(&mut self, ids: &[u8]) -> Result<(), BusError> {
        self.start()?;
        self.send(Instruction::SyncRead {
            addr: FEEDBACK_ADDR,
            len: FEEDBACK_LEN,
            ids,
        })?;
        self.feedback_sent = Some(Instant::now());
        Ok(())
    }

    /// Collects the replies to [`Bus::request_feedback`]: `out[i]` gets servo `ids[i]`'s block or
    /// `None` if it did not answer in time. Returns how many answered.
    pub fn collect_feedback(
        &mut self,
        ids: &[u8],
        out: &mut [Option<(FeedbackBlock, ServoStatus)>],
    ) -> Result<usize, BusError> {
        out.iter_mut().for_each(|o| *o = None);
        let Some(sent) = self.feedback_sent.take() else {
            return Ok(0);
        };
        self.counters.cycles += 1;
        let bytes =
            sync_read_request_bytes(ids.len()) + ids.len() * status_bytes(FEEDBACK_LEN as usize);
        let deadline = sent + wire_time(bytes, self.transport.baud()) + self.margin;
        let mut answered = 0;
        self.collect_until(deadline, |counters, status| {
            let slot = ids.iter().position(|&id| id == status.id);
            match (slot, FeedbackBlock::parse(status.params)) {
                (Some(i), Some(block))
                    if status.params.len() == FEEDBACK_LEN as usize && out[i].is_none() =>
                {
                    out[i] = Some((block, status.status));
                    answered += 1;
                    counters.replies += 1;
                    if !status.status.is_ok() {
                        counters.status_errors += 1;
                    }
                }
                _ => counters.unexpected_replies += 1,
            }
            answered == ids.len()
        })?;
        self.counters.missing += (ids.len() - answered) as u64;
        Ok(answered)
    }

    /// Starts a unicast READ of `len` bytes at `addr` from `id` without waiting for the reply
    /// (collect it with [`Bus::collect_read`]; other buses can be started in between).
    pub fn request_read(&mut self, id: u8, addr: u8, len: u8) -> Result<(), BusError> {
        self.start()?;
        self.send(Instruction::Read { id, addr, len })?;
        self.read_sent = Some((Instant::now(), id, len));
        Ok(())
    }

    /// Collects the reply to [`Bus::request_read`] into `out` (which must hold `len` bytes):
    /// `Some(status)` if it arrived intact within its wire time plus `margin`, `None` if not.
    pub fn collect_read(
        &mut self,
        out: &mut [u8],
        margin: Duration,
    ) -> Result<Option<ServoStatus>, BusError> {
        let Some((sent, id, len)) = self.read_sent.take() else {
            return Ok(None);
        };
        let deadline = sent + read_time(len, self.transport.baud()) + margin;
        let mut got = None;
        self.collect_until(deadline, |counters, status| {
            match out.get_mut(..usize::from(len)) {
                Some(dst) if status.id == id && status.params.len() == usize::from(len) => {
                    dst.copy_from_slice(status.params);
                    got = Some(status.status);
                    counters.replies += 1;
                }
                _ => counters.unexpected_replies += 1,
            }
            got.is_some()
        })?;
        Ok(got)
    }

    /// Decodes what arrives until `done` says so or `deadline` has passed (then whatever has
    /// already arrived is still taken, and a header that never completed is looked behind).
    /// Every intact status packet goes to `on_reply`; decoder errors are counted by kind.
    fn collect_until(
        &mut self,
        deadline: Instant,
        mut on_reply: impl FnMut(&mut BusCounters, &StatusPacket) -> bool,
    ) -> Result<(), BusError> {
        let mut done = false;
        let mut at_end = false;
        loop {
            let decoded = if at_end {
                self.decoder.finish()
            } else {
                self.decoder.next_frame()
            };
            match decoded {
                Some(Ok(frame)) => {
                    match StatusPacket::parse(&frame) {
                        Ok(status) => done |= on_reply(&mut self.counters, &status),
                        Err(_) => self.counters.unexpected_replies += 1,
                    }
                    continue;
                }
                Some(Err(e)) => {
                    count(&mut self.counters, e);
                    continue;
                }
                None if done || at_end => return Ok(()),
                None => {}
            }
            let now = Instant::now();
            // Past the deadline, take only what has already arrived (a bus collected after
            // another may find its replies waiting), then give up on a header that never
            // completed and look behind it.
            let timeout = deadline.saturating_duration_since(now);
            let n = self
                .transport
                .receive(&mut self.rx, timeout)
                .inspect_err(|_| self.counters.transport_errors += 1)?;
            if n == 0 && timeout.is_zero() {
                at_end = true;
                continue;
            }
            let mut rest = &self.rx[..n];
            while !rest.is_empty() {
                let taken = self.decoder.push(rest);
                rest = &rest[taken..];
                if taken == 0 {
                    // Buffer full of undecodable bytes: drop them, count as garbage.
                    self.counters.garbage_bytes += self.decoder.buffered() as u64;
                    self.decoder.clear();
                }
            }
        }
    }

    /// SYNC_WRITE of `len` bytes per servo at `addr`; `payload` is `[id d…] × N`. No reply.
    pub fn sync_write(&mut self, addr: u8, len: u8, payload: &[u8]) -> Result<(), BusError> {
        self.send(Instruction::SyncWrite { addr, len, payload })
    }

    /// Broadcast WRITE of `data` at `addr`: every servo on the bus obeys, none answers.
    pub fn broadcast_write(&mut self, addr: u8, data: &[u8]) -> Result<(), BusError> {
        self.send(Instruction::Write {
            id: BROADCAST_ID,
            addr,
            data,
        })
    }

    /// `Torque_Enable = 0` to one servo, without waiting for an answer (it may not give one).
    pub fn torque_off_one(&mut self, id: u8) -> Result<(), BusError> {
        self.sync_write(reg::TORQUE_ENABLE.addr, 1, &[id, 0])
    }

    /// `Torque_Limit` (0.1 %) to one servo, without waiting for an answer.
    pub fn torque_limit_one(&mut self, id: u8, permille: u16) -> Result<(), BusError> {
        let t = permille.to_le_bytes();
        self.sync_write(reg::TORQUE_LIMIT.addr, 2, &[id, t[0], t[1]])
    }

    /// Broadcast `Torque_Enable = 0`: one packet that every servo on the bus obeys.
    pub fn torque_off_all(&mut self) -> Result<(), BusError> {
        self.send(Instruction::Write {
            id: BROADCAST_ID,
            addr: reg::TORQUE_ENABLE.addr,
            data: &[0],
        })
    }

    /// Waits for one status packet from `id`. Unicast transactions serve setup, which is not
    /// time-critical: they wait at least [`UNICAST_REPLY_MARGIN`], so a busy host (or a servo
    /// that just powered up, or replies queued ahead on the line) does not fail a servo's setup.
    fn reply(
        &mut self,
        id: u8,
        expected_params: usize,
    ) -> Result<(ServoStatus, [u8; 4]), BusError> {
        let bytes = status_bytes(expected_params) + 16;
        let budget =
            wire_time(bytes, self.transport.baud()) + self.margin.max(UNICAST_REPLY_MARGIN);
        let deadline = Instant::now() + budget;
        loop {
            while let Some(decoded) = self.decoder.next_frame() {
                match decoded {
                    Ok(frame) => match StatusPacket::parse(&frame) {
                        // A reply of another size is a late answer to an earlier transaction.
                        Ok(s) if s.id == id && s.params.len() == expected_params => {
                            let mut data = [0u8; 4];
                            data[..expected_params.min(4)]
                                .copy_from_slice(&s.params[..expected_params.min(4)]);
                            return Ok((s.status, data));
                        }
                        _ => self.counters.unexpected_replies += 1,
                    },
                    Err(e) => count(&mut self.counters, e),
                }
            }
            let timeout = deadline.saturating_duration_since(Instant::now());
            let n = self
                .transport
                .receive(&mut self.rx, timeout)
                .inspect_err(|_| self.counters.transport_errors += 1)?;
            if n == 0 && timeout.is_zero() {
                return Err(BusError::NoReply {
                    id,
                    waited_us: budget.as_micros() as u64,
                });
            }
            self.decoder.push(&self.rx[..n]);
        }
    }

    /// One unicast request and its reply, retried: a lost or late reply is common on these
    /// buses under load, and every request here is idempotent. Between attempts the line is
    /// left to drain so that a late reply cannot be taken for the next one.
    fn transact(
        &mut self,
        id: u8,
        instruction: Instruction,
        reply_params: usize,
    ) -> Result<(ServoStatus, [u8; 4]), BusError> {
        let mut last = BusError::NoReply { id, waited_us: 0 };
        for _ in 0..UNICAST_ATTEMPTS {
            self.start()?;
            self.send(instruction)?;
            match self.reply(id, reply_params) {
                Ok(r) => return Ok(r),
                Err(e @ BusError::NoReply { .. }) => {
                    last = e;
                    std::thread::sleep(self.margin);
                }
                Err(e) => return Err(e),
            }
        }
        Err(last)
    }

    /// Sends `instruction` once and listens for the whole `window` after its wire time,
    /// keeping everything that comes back: a scan's evidence (a second servo with the same id
    /// answers after the first, or over it). Not retried.
    pub fn listen(
        &mut self,
        instruction: Instruction,
        window: Duration,
    ) -> Result<Heard, BusError> {
        self.start()?;
        let before = self.counters;
        self.send(instruction)?;
        // `send` encoded it into `tx`; its length sets the wire time.
        let request = instruction.encode(&mut self.tx).unwrap_or(0);
        let deadline = Instant::now() + wire_time(request, self.transport.baud()) + window;
        let mut heard = Heard::default();
        self.collect_until(deadline, |_, status| {
            heard.replies.push(Reply::of(status));
            false
        })?;
        heard.damaged = damage(&before, &self.counters);
        Ok(heard)
    }

    /// One servo, and only one, answers a PING at `id`: a second one (a factory-fresh servo
    /// fitted at the factory's id beside the servo there) takes every write meant for the
    /// first, while the first's intact reply hides it from a transaction that takes the first
    /// reply. Listens [`TWIN_WINDOW`] past the first answer.
    pub fn alone_at(&mut self, id: u8) -> Result<(), BusError> {
        let heard = self.ping_listening(id, TWIN_WINDOW)?;
        let answers = heard.replies.iter().filter(|r| r.id == id).count();
        match (answers, heard.damaged) {
            (1, 0) => Ok(()),
            // Only another id's late answer: as if nothing answered.
            (0, 0) => Err(BusError::NoReply { id, waited_us: 0 }),
            (answers, damaged) => Err(BusError::NotAlone {
                id,
                answers,
                damaged,
            }),
        }
    }

    /// PING `id`, then listen `window` past the first answer for another one (two servos at
    /// one id answer one after the other, or over each other): every answer heard, intact and
    /// damaged. Nothing heard within a unicast transaction's budget is retried as one is.
    pub fn ping_listening(&mut self, id: u8, window: Duration) -> Result<Heard, BusError> {
        let budget = wire_time(status_bytes(0) + 16, self.transport.baud())
            + self.margin.max(UNICAST_REPLY_MARGIN);
        for _ in 0..UNICAST_ATTEMPTS {
            self.start()?;
            let before = self.counters;
            self.send(Instruction::Ping { id })?;
            let mut heard = Heard::default();
            self.collect_until(Instant::now() + budget, |c, status| heard.take(c, status))?;
            if heard.replies.is_empty() && damage(&before, &self.counters) == 0 {
                std::thread::sleep(self.margin);
                continue;
            }
            self.collect_until(Instant::now() + window, |c, status| {
                heard.take(c, status);
                false
            })?;
            heard.damaged = damage(&before, &self.counters);
            return Ok(heard);
        }
        Err(BusError::NoReply {
            id,
            waited_us: budget.as_micros() as u64,
        })
    }

    /// PING: the servo's status bits, or why it did not answer.
    pub fn ping(&mut self, id: u8) -> Result<ServoStatus, BusError> {
        Ok(self.transact(id, Instruction::Ping { id }, 0)?.0)
    }

    /// Reads one register.
    pub fn read(&mut self, id: u8, register: Register) -> Result<i32, BusError> {
        let read = Instruction::Read {
            id,
            addr: register.addr,
            len: register.size,
        };
        let (_, data) = self.transact(id, read, register.size as usize)?;
        register.decode(&data).ok_or(BusError::ShortReply {
            id,
            expected: register.size as usize,
            got: 0,
        })
    }

    /// Writes one register and waits for the acknowledgement.
    pub fn write(
        &mut self,
        id: u8,
        register: Register,
        value: i32,
    ) -> Result<ServoStatus, BusError> {
        let raw = encode(register, value)?;
        let bytes = raw.to_le_bytes();
        let write = Instruction::Write {
            id,
            addr: register.addr,
            data: &bytes[..register.size as usize],
        };
        Ok(self.transact(id, write, 0)?.0)
    }
}

/// One intact status packet heard by [`Bus::listen`].
#[derive(Debug, Clone, PartialEq)]
pub struct Reply {
    /// The id it came from.
    pub id: u8,
    /// Its status bits.
    pub status: ServoStatus,
    /// Its data (empty for a PING or WRITE).
    pub data: Vec<u8>,
}

impl Reply {
    fn of(status: &StatusPacket) -> Reply {
        Reply {
            id: status.id,
            status: status.status,
            data: status.params.to_vec(),
        }
    }
}

/// What came back to one instruction within a listening window.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Heard {
    /// Every intact status packet, in arrival order.
    pub replies: Vec<Reply>,
    /// Damaged packets (bad checksum or framing) and runs of bytes that were no packet: on a
    /// clean line, two servos that talked at once.
    pub damaged: u64,
}

impl Heard {
    /// Keeps `status` if it answers a PING (no parameters: one with data is a late answer to
    /// an earlier read, from a servo slower than the host waited for, and counted as
    /// unexpected); returns whether it did.
    fn take(&mut self, counters: &mut BusCounters, status: &StatusPacket) -> bool {
        let answers = status.params.is_empty();
        if answers {
            self.replies.push(Reply::of(status));
        } else {
            counters.unexpected_replies += 1;
        }
        answers
    }
}

/// Damaged packets and runs of bytes that were no packet between two counts: on a clean line,
/// two servos that talked at once.
fn damage(before: &BusCounters, after: &BusCounters) -> u64 {
    (after.checksum_errors - before.checksum_errors)
        + (after.framing_errors - before.framing_errors)
        + u64::from(after.garbage_bytes > before.garbage_bytes)
}

/// Bytes of a READ request: header, id, length, instruction, address, count, checksum.
const READ_REQUEST_BYTES: usize = 8;

/// Wire time of a READ of `len` bytes and its reply at `baud`.
pub fn read_time(len: u8, baud: u32) -> Duration {
    wire_time(READ_REQUEST_BYTES + status_bytes(usize::from(len)), baud)
}

/// How long a PING listens past the first answer for a second servo at the same id: the
/// slowest return delay a servo can be set to (254 × 2 µs; the factory's is 500 µs), a reply's
/// wire time, and the host's scheduling.
pub const TWIN_WINDOW: Duration = Duration::from_millis(3);

/// Attempts of a unicast transaction before the servo is declared unreachable.
pub const UNICAST_ATTEMPTS: usize = 3;
/// Least reply margin of a unicast (setup) transaction.
pub const UNICAST_REPLY_MARGIN: Duration = Duration::from_millis(20);

/// Encodes `value` for `register` (sign-magnitude where the register is signed).
pub fn encode(register: Register, value: i32) -> Result<u16, BusError> {
    let err = BusError::Encode {
        register: register.name,
        value,
    };
    match register.encoding {
        reg::Encoding::SignMagnitude(bit) => {
            feetech::encoding::encode_sign_magnitude(value, bit).map_err(|_| err)
        }
        reg::Encoding::Unsigned => {
            let max = if register.size == 1 { 0xFF } else { 0xFFFF };
            if (0..=max).contains(&value) {
                Ok(value as u16)
            } else {
                Err(err)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A line that answers each request sent with the status packets scripted for it.
    struct Scripted {
        answers: std::collections::VecDeque<Vec<StatusPacket<'static>>>,
        incoming: Vec<u8>,
    }

    impl Transport for Scripted {
        fn baud(&self) -> u32 {
            1_000_000
        }
        fn send(&mut self, _: &[u8]) -> Result<(), TransportError> {
            for packet in self.answers.pop_front().unwrap_or_default() {
                let mut out = [0u8; MAX_PACKET];
                let n = packet.encode(&mut out).unwrap_or(0);
                self.incoming.extend_from_slice(&out[..n]);
            }
            Ok(())
        }
        fn receive(&mut self, buf: &mut [u8], _: Duration) -> Result<usize, TransportError> {
            let n = buf.len().min(self.incoming.len());
            buf[..n].copy_from_slice(&self.incoming[..n]);
            self.incoming.drain(..n);
            Ok(n)
        }
        fn discard_input(&mut self) -> Result<(), TransportError> {
            self.incoming.clear();
            Ok(())
        }
    }

    fn status(id: u8, params: &'static [u8]) -> StatusPacket<'static> {
        StatusPacket {
            id,
            status: ServoStatus::default(),
            params,
        }
    }

    /// A servo at the factory's return delay answers a read-back after the host stopped
    /// waiting; its late answer, parameters and all, arrives while the next setup pings it.
    /// That is one servo, not two: only a parameterless answer answers a PING.
    #[test]
    fn a_late_answer_to_a_read_is_not_a_second_servo_at_the_id() {
        let late = status(3, &[0; 10]);
        let mut bus = Bus::new(
            Scripted {
                answers: [vec![late, status(3, &[])]].into(),
                incoming: Vec::new(),
            },
            Duration::from_millis(2),
        );
        let heard = bus.alone_at(3);
        assert!(heard.is_ok(), "{heard:?}");
        let twin = Scripted {
            answers: [vec![status(3, &[]), status(3, &[])]].into(),
            incoming: Vec::new(),
        };
        let mut bus = Bus::new(twin, Duration::from_millis(2));
        assert!(matches!(
            bus.alone_at(3),
            Err(BusError::NotAlone { answers: 2, .. })
        ));
    }
}
