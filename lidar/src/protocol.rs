//! The Slamtec RPLIDAR serial protocol as the C1 speaks it, sans-IO: requests as bytes out,
//! received bytes in, decoded answers and measurements out. Nothing here reads a clock or a port.
//!
//! Written from the protocol notes in `docs/rplidar-c1.md` (Slamtec's SDK and interface
//! protocol documents). The standard SCAN mode is implemented: it is the one Slamtec's own C1
//! launch files select, and it carries the full 5 kHz.
//!
//! Wire summary:
//! * request: `A5 cmd` (commands without payload), or `A5 cmd size payload… xor` with the XOR
//!   of every byte before it;
//! * answer: a 7-byte descriptor `A5 5A len(30 bits)|mode(2 bits) type`, then `len` bytes once
//!   (mode 0) or packets of `len` bytes until the next request (mode 1, the scan stream);
//! * scan node (type 0x81, 5 bytes): `quality<<2 | !S<<1 | S`, `angle_q6<<1 | C` (16 bits
//!   little-endian, C = 1), `distance_q2` (16 bits little-endian). The angle runs clockwise seen
//!   from above, in 1/64 degree; the distance is in 1/4 mm, 0 when nothing returned.
//!
//! The standard scan carries no checksum: a node is checked by its two check bits (S against
//! !S, C set) and its angle (below 360°). A misaligned window passes those checks about one time
//! in six, and the bytes of a misaligned stream are not random (neighbouring nodes share their
//! quality and nearly their distance), so after losing alignment the decoder emits nothing until
//! [`LOCK_NODES`] successive windows at one offset pass their checks *and* advance like a
//! turning lidar (each angle a little past the one before, or wrapping with S set).
//! [`crate::scan`] checks each node against its neighbours again.

use thiserror::Error;

/// The C1's line rate, 8N1.
pub const BAUD: u32 = 460_800;

/// First byte of every request and answer descriptor.
pub const SYNC: u8 = 0xA5;
/// Second byte of an answer descriptor.
pub const ANSWER_SYNC: u8 = 0x5A;

/// Answer type of GET_INFO.
pub const TYPE_INFO: u8 = 0x04;
/// Answer type of GET_HEALTH.
pub const TYPE_HEALTH: u8 = 0x06;
/// Answer type of SCAN and FORCE_SCAN: standard 5-byte nodes.
pub const TYPE_SCAN_NODE: u8 = 0x81;

/// Bytes of a GET_INFO answer.
pub const INFO_LEN: usize = 20;
/// Bytes of a GET_HEALTH answer.
pub const HEALTH_LEN: usize = 3;
/// Bytes of a standard scan node.
pub const NODE_LEN: usize = 5;

/// A full turn in the node's 1/64 degree.
pub const FULL_TURN_Q6: u16 = 360 * 64;

/// Longest single answer this decoder keeps (GET_INFO is 20 bytes; longer ones are skipped).
const MAX_ANSWER: usize = 64;

/// Successors that must confirm a node before it goes out.
pub const CONFIRMING: usize = 2;
/// Successive nodes that must agree before a realigned stream is trusted. The first is dropped:
/// it follows the damage, and its first byte (S, quality) may be a stray byte that passed the
/// check bits. The second goes out; the others are its confirmation.
pub const LOCK_NODES: usize = CONFIRMING + 2;
/// While locking, the smallest step between successive nodes: 0.1° (a C1 steps 0.58-0.86°).
const LOCK_MIN_STEP_Q6: u16 = 6;
/// While locking, the largest step: 5° (a few nodes lost).
const LOCK_MAX_STEP_Q6: u16 = 5 * 64;

/// The requests the driver sends (none carries a payload).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Command {
    /// Stop scanning (and the C1's motor); no answer. Wait ≥ 1 ms before the next request.
    Stop = 0x25,
    /// Reboot the core; no answer, a boot banner may follow. Wait before the next request.
    Reset = 0x40,
    /// Start the standard scan: descriptor `A5 5A 05 00 00 40 81`, then nodes.
    Scan = 0x20,
    /// Model, firmware, hardware, serial number: 20 bytes, type 0x04.
    GetInfo = 0x50,
    /// Status and error code: 3 bytes, type 0x06.
    GetHealth = 0x52,
}

impl Command {
    /// The request's bytes.
    pub const fn bytes(self) -> [u8; 2] {
        [SYNC, self as u8]
    }
}

/// A request that cannot be encoded.
#[derive(Debug, Error, PartialEq, Eq)]
pub enum RequestError {
    /// A payload longer than the size byte can say.
    #[error("payload of {0} bytes: at most 255")]
    PayloadTooLong(usize),
    /// A command with bit 7 clear cannot carry a payload (the device would not read it).
    #[error("command {0:#04x} takes no payload (bit 7 clear)")]
    NoPayloadCommand(u8),
}

/// A request with a payload (`cmd` has bit 7 set): `A5 cmd size payload… checksum`, the
/// checksum the XOR of every byte before it. Appended to `out`.
pub fn request_with_payload(
    cmd: u8,
    payload: &[u8],
    out: &mut Vec<u8>,
) -> Result<(), RequestError> {
    if cmd & 0x80 == 0 {
        return Err(RequestError::NoPayloadCommand(cmd));
    }
    let size =
        u8::try_from(payload.len()).map_err(|_| RequestError::PayloadTooLong(payload.len()))?;
    let start = out.len();
    out.extend_from_slice(&[SYNC, cmd, size]);
    out.extend_from_slice(payload);
    let checksum = out[start..].iter().fold(0u8, |x, b| x ^ b);
    out.push(checksum);
    Ok(())
}

/// How an answer is sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SendMode {
    /// One packet of `len` bytes.
    Single,
    /// Packets of `len` bytes until the next request (a scan).
    Multiple,
    /// The two reserved codes.
    Reserved(u8),
}

/// An answer descriptor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Descriptor {
    /// Bytes per packet.
    pub len: u32,
    /// Once or repeated.
    pub mode: SendMode,
    /// What the packets hold.
    pub data_type: u8,
}

impl Descriptor {
    /// Reads the five bytes after `A5 5A`.
    pub fn parse(bytes: [u8; 5]) -> Self {
        let word = u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]);
        let mode = match (word >> 30) as u8 {
            0 => SendMode::Single,
            1 => SendMode::Multiple,
            m => SendMode::Reserved(m),
        };
        Descriptor {
            len: word & 0x3FFF_FFFF,
            mode,
            data_type: bytes[4],
        }
    }
}

/// GET_INFO's answer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DeviceInfo {
    /// High nibble the series (4: the C series), low nibble the sub-model: a C1M1 is 0x41.
    pub model: u8,
    /// Firmware major version.
    pub firmware_major: u8,
    /// Firmware minor version.
    pub firmware_minor: u8,
    /// Hardware revision.
    pub hardware: u8,
    /// Serial number, printed as hex from its first byte.
    pub serial: [u8; 16],
}

impl DeviceInfo {
    /// Reads the 20 bytes of the answer.
    pub fn parse(bytes: &[u8; INFO_LEN]) -> Self {
        let mut serial = [0u8; 16];
        serial.copy_from_slice(&bytes[4..]);
        DeviceInfo {
            model: bytes[0],
            firmware_minor: bytes[1],
            firmware_major: bytes[2],
            hardware: bytes[3],
            serial,
        }
    }

    /// The model's name as Slamtec's SDK prints it for the C series ("C1M1"); `None` for
    /// another series.
    pub fn c_series_name(&self) -> Option<String> {
        let series = self.model >> 4;
        (series == 4).then(|| format!("C{}M{}", series - 3, self.model & 0x0F))
    }

    /// The serial number in hex.
    pub fn serial_hex(&self) -> String {
        self.serial.iter().map(|b| format!("{b:02X}")).collect()
    }
}

/// The device's own verdict on itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HealthStatus {
    /// Working, no problem reported (status 0).
    Good,
    /// Working, with a problem reported in the error code.
    Warning,
    /// Stopped to protect itself ("protection stop"): it needs a RESET.
    Error,
    /// A status code the protocol does not define.
    Unknown(u8),
}

/// GET_HEALTH's answer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Health {
    /// The status.
    pub status: HealthStatus,
    /// The device's error code (meaningful with a warning or an error).
    pub error_code: u16,
}

impl Health {
    /// Reads the 3 bytes of the answer.
    pub fn parse(bytes: &[u8; HEALTH_LEN]) -> Self {
        let status = match bytes[0] {
            0 => HealthStatus::Good,
            1 => HealthStatus::Warning,
            2 => HealthStatus::Error,
            s => HealthStatus::Unknown(s),
        };
        Health {
            status,
            error_code: u16::from_le_bytes([bytes[1], bytes[2]]),
        }
    }
}

/// One measurement of the standard scan.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Node {
    /// The first measurement of a new revolution.
    pub start: bool,
    /// Signal quality, 0..=63 (0 with no return).
    pub quality: u8,
    /// Bearing, clockwise seen from above, 1/64 degree, below [`FULL_TURN_Q6`].
    pub angle_q6: u16,
    /// Range, 1/4 mm; 0 when nothing returned.
    pub distance_q2: u16,
}

impl Node {
    /// Decodes five bytes, or `None` if the check bits or the angle refuse them.
    pub fn parse(b: [u8; NODE_LEN]) -> Option<Self> {
        if !first_byte_ok(b[0]) || !second_byte_ok(b[1]) {
            return None;
        }
        let angle_q6 = u16::from_le_bytes([b[1], b[2]]) >> 1;
        (angle_q6 < FULL_TURN_Q6).then_some(Node {
            start: b[0] & 1 == 1,
            quality: b[0] >> 2,
            angle_q6,
            distance_q2: u16::from_le_bytes([b[3], b[4]]),
        })
    }

    /// Bearing in degrees, clockwise.
    pub fn angle_deg(&self) -> f64 {
        f64::from(self.angle_q6) / 64.0
    }

    /// Range in metres (0: no return).
    pub fn distance_m(&self) -> f64 {
        f64::from(self.distance_q2) / 4000.0
    }
}

/// S and !S differ.
fn first_byte_ok(b: u8) -> bool {
    (b ^ (b >> 1)) & 1 == 1
}

/// The check bit C is set.
fn second_byte_ok(b: u8) -> bool {
    b & 1 == 1
}

/// What the decoder made of the bytes so far.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Event {
    /// GET_INFO's answer.
    Info(DeviceInfo),
    /// GET_HEALTH's answer.
    Health(Health),
    /// A scan's descriptor: nodes follow.
    ScanStarted,
    /// One scan node that passed its checks.
    Node(Node),
    /// A well-formed answer this driver did not ask for or does not know (its bytes skipped).
    Unexpected(Descriptor),
}

/// What the decoder refused, cumulative.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[cfg_attr(feature = "process", derive(serde::Serialize))]
pub struct DecodeCounters {
    /// Bytes skipped outside any answer or between nodes (line noise, a boot banner, a stream
    /// that lost its alignment).
    pub skipped_bytes: u64,
    /// Times the node stream lost its alignment: a node's checks failed after a good node.
    pub resyncs: u64,
    /// Nodes dropped because the stream lost its alignment right after them (a byte lost in
    /// their distance would look just like that).
    pub unconfirmed: u64,
    /// Answers of an unknown type or an unexpected length.
    pub unexpected: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    /// Looking for `A5`.
    Sync,
    /// Saw `A5`, expecting `5A`.
    AnswerSync,
    /// Reading the descriptor's five bytes.
    Descriptor { have: usize },
    /// Reading a single answer's bytes.
    Answer { descriptor: Descriptor, have: usize },
    /// In the scan stream: `have` bytes of the next node (or, not locked, of the nodes being
    /// locked onto) so far.
    Nodes { have: usize, locked: bool },
    /// In a repeated answer this decoder does not read: everything until the next request is
    /// skipped.
    Ignoring,
}

/// The host side of the protocol: bytes in, [`Event`]s out, one byte at a time (a C1 sends
/// 25 kB/s). Call [`Decoder::request_sent`] whenever a request goes out: it ends a scan stream,
/// as the device does.
#[derive(Debug, Clone)]
pub struct Decoder {
    state: State,
    buf: [u8; MAX_ANSWER],
    /// Nodes that passed their checks and wait for successors to confirm them, oldest first.
    held: [Node; CONFIRMING],
    held_len: usize,
    counters: DecodeCounters,
}

impl Default for Decoder {
    fn default() -> Self {
        Self::new()
    }
}

impl Decoder {
    /// A decoder waiting for an answer.
    pub fn new() -> Self {
        Decoder {
            state: State::Sync,
            buf: [0; MAX_ANSWER],
            held: [Node::default(); CONFIRMING],
            held_len: 0,
            counters: DecodeCounters::default(),
        }
    }

    /// What was refused so far.
    pub fn counters(&self) -> DecodeCounters {
        self.counters
    }

    /// Whether the decoder is inside a scan stream.
    pub fn scanning(&self) -> bool {
        matches!(self.state, State::Nodes { .. })
    }

    /// A request went out: the device leaves any stream and answers afresh.
    pub fn request_sent(&mut self) {
        self.state = State::Sync;
        self.held_len = 0;
    }

    /// Takes one received byte.
    pub fn push(&mut self, byte: u8) -> Option<Event> {
        match self.state {
            State::Sync => {
                if byte == SYNC {
                    self.state = State::AnswerSync;
                } else {
                    self.counters.skipped_bytes += 1;
                }
                None
            }
            State::AnswerSync => {
                match byte {
                    ANSWER_SYNC => self.state = State::Descriptor { have: 0 },
                    // `A5 A5 5A`: the second A5 may start the descriptor (Slamtec's decoder
                    // loses it).
                    SYNC => self.counters.skipped_bytes += 1,
                    _ => {
                        self.counters.skipped_bytes += 2;
                        self.state = State::Sync;
                    }
                }
                None
            }
            State::Descriptor { have } => {
                self.buf[have] = byte;
                if have + 1 < 5 {
                    self.state = State::Descriptor { have: have + 1 };
                    return None;
                }
                let mut raw = [0u8; 5];
                raw.copy_from_slice(&self.buf[..5]);
                self.start_answer(Descriptor::parse(raw))
            }
            State::Answer { descriptor, have } => {
                if have < MAX_ANSWER {
                    self.buf[have] = byte;
                }
                let have = have + 1;
                if (have as u64) < u64::from(descriptor.len) {
                    self.state = State::Answer { descriptor, have };
                    return None;
                }
                self.state = State::Sync;
                Some(self.finish_answer(descriptor))
            }
            State::Nodes { have, locked } => self.push_node_byte(byte, have, locked),
            State::Ignoring => {
                self.counters.skipped_bytes += 1;
                None
            }
        }
    }

    fn start_answer(&mut self, d: Descriptor) -> Option<Event> {
        let known_single = matches!(
            (d.data_type, d.len as usize),
            (TYPE_INFO, INFO_LEN) | (TYPE_HEALTH, HEALTH_LEN)
        );
        match d.mode {
            SendMode::Multiple if d.data_type == TYPE_SCAN_NODE && d.len as usize == NODE_LEN => {
                self.state = State::Nodes {
                    have: 0,
                    locked: true,
                };
                Some(Event::ScanStarted)
            }
            SendMode::Single if d.len > 0 && (known_single || d.len as usize <= MAX_ANSWER) => {
                self.state = State::Answer {
                    descriptor: d,
                    have: 0,
                };
                None
            }
            // A stream in another format, an answer too long to be one of ours, an empty
            // one, a reserved mode: nothing that follows can be read until the next request.
            _ => {
                self.counters.unexpected += 1;
                self.state = if d.mode == SendMode::Multiple {
                    State::Ignoring
                } else {
                    State::Sync
                };
                Some(Event::Unexpected(d))
            }
        }
    }

    fn finish_answer(&mut self, d: Descriptor) -> Event {
        match (d.mode, d.data_type, d.len as usize) {
            (SendMode::Single, TYPE_INFO, INFO_LEN) => {
                let mut b = [0u8; INFO_LEN];
                b.copy_from_slice(&self.buf[..INFO_LEN]);
                Event::Info(DeviceInfo::parse(&b))
            }
            (SendMode::Single, TYPE_HEALTH, HEALTH_LEN) => {
                let mut b = [0u8; HEALTH_LEN];
                b.copy_from_slice(&self.buf[..HEALTH_LEN]);
                Event::Health(Health::parse(&b))
            }
            _ => {
                self.counters.unexpected += 1;
                Event::Unexpected(d)
            }
        }
    }

    /// Byte-wise resynchronisation: a window whose checks fail loses its first byte and the
    /// rest is tried again. A node goes out only once [`CONFIRMING`] successors confirm it (each
    /// passes its checks and advances from the one before): a byte lost inside a node's
    /// distance leaves its angle right and its distance wrong, and only the misaligned
    /// windows after it show that. Once a check failed, the stream must lock again
    /// ([`LOCK_NODES`] agreeing nodes).
    fn push_node_byte(&mut self, byte: u8, have: usize, locked: bool) -> Option<Event> {
        self.buf[have] = byte;
        let mut have = have + 1;
        let mut locked = locked;
        loop {
            let prev = self.held[..self.held_len].last().copied();
            if stream_ok(&self.buf[..have], if locked { prev } else { None }, locked) {
                break;
            }
            if locked {
                self.counters.resyncs += 1;
                self.counters.unconfirmed += self.held_len as u64;
                self.held_len = 0;
                locked = false;
            }
            self.counters.skipped_bytes += 1;
            self.buf.copy_within(1..have, 0);
            have -= 1;
        }
        let need = if locked {
            NODE_LEN
        } else {
            NODE_LEN * LOCK_NODES
        };
        if have < need {
            self.state = State::Nodes { have, locked };
            return None;
        }
        self.state = State::Nodes {
            have: 0,
            locked: true,
        };
        let mut out = None;
        let skip = if locked { 0 } else { 1 };
        self.counters.unconfirmed += skip as u64;
        for node in self.buf[skip * NODE_LEN..need]
            .chunks_exact(NODE_LEN)
            .filter_map(node_of)
        {
            if self.held_len == CONFIRMING {
                out = Some(Event::Node(self.held[0]));
                self.held.copy_within(1.., 0);
                self.held_len -= 1;
            }
            self.held[self.held_len] = node;
            self.held_len += 1;
        }
        out
    }
}

fn node_of(bytes: &[u8]) -> Option<Node> {
    let mut b = [0u8; NODE_LEN];
    b.copy_from_slice(bytes);
    Node::parse(b)
}

/// Whether the bytes so far can continue the stream: every window passes its checks and each
/// whole node advances from the one before it (from `prev`, the newest node awaiting
/// confirmation, for the first). Locked, the bytes are one window; locking, up to [`LOCK_NODES`].
fn stream_ok(bytes: &[u8], prev: Option<Node>, locked: bool) -> bool {
    let windows = bytes
        .chunks(NODE_LEN)
        .take(if locked { 1 } else { LOCK_NODES });
    if !windows.clone().all(window_ok) {
        return false;
    }
    let mut prev = prev;
    for node in bytes.chunks_exact(NODE_LEN).map(node_of) {
        match (prev, node) {
            (Some(a), Some(b)) if !advances(a, b) => return false,
            _ => prev = node,
        }
    }
    true
}

/// Whether `b` can follow `a` from a turning lidar: a small step forward, across 0° only on
/// a node that starts a turn. (A misaligned stream can carry a "start" with a plausible angle
/// far from 0°: two bytes off, the angle is half a distance and S is a bit of the next angle.)
fn advances(a: Node, b: Node) -> bool {
    let step = if b.start {
        (FULL_TURN_Q6 - a.angle_q6) + b.angle_q6
    } else {
        b.angle_q6.wrapping_sub(a.angle_q6)
    };
    (LOCK_MIN_STEP_Q6..=LOCK_MAX_STEP_Q6).contains(&step)
}

/// Whether the bytes so far can begin a node (an empty window can).
fn window_ok(w: &[u8]) -> bool {
    let first = w.first().is_none_or(|&b| first_byte_ok(b));
    let second = w.get(1).is_none_or(|&b| second_byte_ok(b));
    let angle = w.len() < 3 || (u16::from_le_bytes([w[1], w[2]]) >> 1) < FULL_TURN_Q6;
    first && second && angle
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode(bytes: &[u8]) -> (Vec<Event>, DecodeCounters) {
        let mut d = Decoder::new();
        let events = bytes.iter().filter_map(|&b| d.push(b)).collect();
        (events, d.counters())
    }

    /// A node as the protocol document draws it, built bit by bit here (not with the decoder's
    /// own helpers).
    fn node_bytes(start: bool, quality: u8, angle_q6: u16, distance_q2: u16) -> [u8; 5] {
        let s = u8::from(start);
        let not_s = 1 - s;
        let angle = (angle_q6 << 1) | 1;
        [
            (quality << 2) | (not_s << 1) | s,
            angle as u8,
            (angle >> 8) as u8,
            distance_q2 as u8,
            (distance_q2 >> 8) as u8,
        ]
    }

    #[test]
    fn requests_are_the_documented_bytes() {
        assert_eq!(Command::Scan.bytes(), [0xA5, 0x20]);
        assert_eq!(Command::Stop.bytes(), [0xA5, 0x25]);
        assert_eq!(Command::Reset.bytes(), [0xA5, 0x40]);
        assert_eq!(Command::GetInfo.bytes(), [0xA5, 0x50]);
        assert_eq!(Command::GetHealth.bytes(), [0xA5, 0x52]);
        // The two examples with a checksum in the protocol notes (EXPRESS_SCAN mode 0,
        // GET_ACC_BOARD_FLAG).
        let mut out = Vec::new();
        request_with_payload(0x82, &[0, 0, 0, 0, 0], &mut out).unwrap();
        assert_eq!(out, [0xA5, 0x82, 0x05, 0, 0, 0, 0, 0, 0x22]);
        out.clear();
        request_with_payload(0xFF, &[0, 0, 0, 0], &mut out).unwrap();
        assert_eq!(out, [0xA5, 0xFF, 0x04, 0, 0, 0, 0, 0x5E]);
        assert_eq!(
            request_with_payload(0x20, &[1], &mut out),
            Err(RequestError::NoPayloadCommand(0x20))
        );
        assert_eq!(
            request_with_payload(0x84, &[0; 256], &mut out),
            Err(RequestError::PayloadTooLong(256))
        );
    }

    #[test]
    fn descriptors_read_length_mode_and_type() {
        let scan = Descriptor::parse([0x05, 0x00, 0x00, 0x40, 0x81]);
        assert_eq!(
            scan,
            Descriptor {
                len: 5,
                mode: SendMode::Multiple,
                data_type: 0x81
            }
        );
        let info = Descriptor::parse([0x14, 0, 0, 0, 0x04]);
        assert_eq!((info.len, info.mode), (20, SendMode::Single));
        assert_eq!(
            Descriptor::parse([1, 0, 0, 0xC0, 7]).mode,
            SendMode::Reserved(3)
        );
    }

    #[test]
    fn info_and_health_answers_decode_after_line_noise() {
        let mut bytes = b"RP LIDAR System.\r\nFirmware Ver 1.02\r\n".to_vec();
        // A sync byte followed by something else is two bytes of noise.
        bytes.extend_from_slice(&[0xA5, 0x00]);
        bytes.extend_from_slice(&[0xA5, 0x5A, 0x14, 0, 0, 0, 0x04]);
        bytes.extend_from_slice(&[0x41, 0x02, 0x01, 18]);
        bytes.extend_from_slice(&[0xAB; 16]);
        // `A5 A5 5A`: the second A5 starts the descriptor.
        bytes.extend_from_slice(&[0xA5, 0xA5, 0x5A, 0x03, 0, 0, 0, 0x06, 2, 0x34, 0x12]);
        let (events, counters) = decode(&bytes);
        let Event::Info(info) = events[0] else {
            panic!("{events:?}")
        };
        assert_eq!(info.model, 0x41);
        assert_eq!((info.firmware_major, info.firmware_minor), (1, 2));
        assert_eq!(info.hardware, 18);
        assert_eq!(info.c_series_name().as_deref(), Some("C1M1"));
        assert_eq!(info.serial_hex(), "AB".repeat(16));
        assert_eq!(
            events[1],
            Event::Health(Health {
                status: HealthStatus::Error,
                error_code: 0x1234
            })
        );
        assert_eq!(counters.skipped_bytes, 37 + 2 + 1);
    }

    #[test]
    fn scan_nodes_decode_to_angles_and_ranges() {
        let mut bytes = vec![0xA5, 0x5A, 0x05, 0x00, 0x00, 0x40, 0x81];
        // 0.5° clockwise, 1.5 m, quality 47, a new revolution; then 1.25°, no return; two
        // more to confirm them.
        bytes.extend_from_slice(&node_bytes(true, 47, 32, 6000));
        bytes.extend_from_slice(&node_bytes(false, 0, 80, 0));
        bytes.extend_from_slice(&node_bytes(false, 9, 128, 100));
        let (events, _) = decode(&bytes);
        assert_eq!(events.len(), 2, "the last node waits for its confirmation");
        bytes.extend_from_slice(&node_bytes(false, 9, 176, 100));
        let (events, _) = decode(&bytes);
        assert_eq!(events[0], Event::ScanStarted);
        let Event::Node(a) = events[1] else { panic!() };
        assert!(a.start);
        assert_eq!(a.quality, 47);
        assert_eq!(a.angle_deg(), 0.5);
        assert_eq!(a.distance_m(), 1.5);
        let Event::Node(b) = events[2] else { panic!() };
        assert!(!b.start);
        assert_eq!((b.angle_deg(), b.distance_m()), (1.25, 0.0));
    }

    #[test]
    fn a_node_with_broken_check_bits_or_angle_is_refused() {
        let good = node_bytes(false, 10, 100, 4000);
        assert!(Node::parse(good).is_some());
        for (byte, bit) in [(0, 0), (0, 1), (1, 0)] {
            let mut bad = good;
            bad[byte] ^= 1 << bit;
            assert_eq!(Node::parse(bad), None, "byte {byte} bit {bit}");
        }
        // 360° and beyond do not exist.
        assert_eq!(Node::parse(node_bytes(false, 10, FULL_TURN_Q6, 4000)), None);
        assert!(Node::parse(node_bytes(false, 10, FULL_TURN_Q6 - 1, 4000)).is_some());
    }

    #[test]
    fn the_stream_realigns_after_garbage_and_counts_it() {
        let mut bytes = vec![0xA5, 0x5A, 0x05, 0x00, 0x00, 0x40, 0x81];
        let nodes: Vec<[u8; 5]> = (0..40)
            .map(|i| node_bytes(i == 0, 30, i * 46, 2000 + i))
            .collect();
        for n in &nodes[..20] {
            bytes.extend_from_slice(n);
        }
        // Three stray bytes whose checks fail (even first byte: S == !S == 0).
        bytes.extend_from_slice(&[0x00, 0x00, 0x00]);
        for n in &nodes[20..] {
            bytes.extend_from_slice(n);
        }
        let (events, counters) = decode(&bytes);
        let decoded: Vec<Node> = events
            .iter()
            .filter_map(|e| match e {
                Event::Node(n) => Some(*n),
                _ => None,
            })
            .collect();
        // The two nodes before the noise are not confirmed (a distance could hold a stray
        // byte), nor the first after it (its first byte could be one); the rest come through
        // but the last two, which wait for successors.
        assert_eq!(decoded.len(), 35);
        assert_eq!(decoded[17].angle_q6, 17 * 46);
        assert_eq!(decoded[18].angle_q6, 21 * 46);
        assert_eq!(counters.resyncs, 1);
        assert_eq!(counters.unconfirmed, 3);
        assert_eq!(counters.skipped_bytes, 3);
    }

    #[test]
    fn a_damaged_stream_of_real_measurements_yields_no_invented_node() {
        // A room's wall: neighbouring nodes share their quality and nearly their distance, so
        // a misaligned stream is far from random. Damage 4 % of the nodes in four ways; every
        // node that comes out must be one that went in, whole.
        let real: Vec<[u8; 5]> = (0..5000u32)
            .map(|i| {
                let turn_index = i % 500;
                let angle = (f64::from(turn_index) * 0.72 * 64.0).round() as u16;
                let wall = 2.0 + 0.4 * (f64::from(turn_index) * 0.0126).sin();
                let q2 = (wall * 4000.0) as u16 + (i * 7 % 13) as u16;
                node_bytes(turn_index == 0, 42, angle, q2)
            })
            .collect();
        let known: std::collections::HashSet<[u8; 5]> = real.iter().copied().collect();
        for seed in [1u64, 2, 3, 12345] {
            let mut state = seed;
            let mut random = move |n: u64| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (state >> 33) % n
            };
            let mut bytes = vec![0xA5, 0x5A, 0x05, 0x00, 0x00, 0x40, 0x81];
            for node in &real {
                let mut node = *node;
                match random(100) {
                    // A byte lost on the line, two lost, a check bit flipped, noise inserted.
                    0 => {
                        let k = random(5) as usize;
                        bytes.extend((0..5).filter(|&j| j != k).map(|j| node[j]));
                        continue;
                    }
                    1 => {
                        bytes.extend_from_slice(&node[..3]);
                        continue;
                    }
                    2 => node[random(2) as usize] ^= 1,
                    3 => bytes.extend((0..random(20)).map(|_| random(256) as u8)),
                    _ => {}
                }
                bytes.extend_from_slice(&node);
            }
            let (events, counters) = decode(&bytes);
            let decoded: Vec<[u8; 5]> = events
                .iter()
                .filter_map(|e| match e {
                    Event::Node(n) => {
                        Some(node_bytes(n.start, n.quality, n.angle_q6, n.distance_q2))
                    }
                    _ => None,
                })
                .collect();
            let invented = decoded.iter().filter(|n| !known.contains(*n)).count();
            assert_eq!(invented, 0, "seed {seed}: of {} decoded", decoded.len());
            // Each damage costs the two nodes before it, the one after and the search.
            assert!(
                decoded.len() > 4000,
                "seed {seed}: {} of 5000 kept",
                decoded.len()
            );
            assert!(counters.resyncs > 100, "seed {seed}: {counters:?}");
        }
    }

    #[test]
    fn single_answers_of_unknown_type_or_length_are_skipped_whole() {
        let mut bytes = Vec::new();
        // GET_SAMPLERATE's answer (not asked for by this driver): its 4 bytes skipped.
        bytes.extend_from_slice(&[0xA5, 0x5A, 0x04, 0, 0, 0, 0x15, 0xC8, 0, 0xC8, 0]);
        // GET_INFO's type with a wrong length: read whole, then refused.
        bytes.extend_from_slice(&[0xA5, 0x5A, 0x05, 0, 0, 0, 0x04, 0x41, 1, 2, 3, 4]);
        // An empty answer, one too long to be ours, a scan descriptor with a wrong node size.
        bytes.extend_from_slice(&[0xA5, 0x5A, 0x00, 0, 0, 0, 0x06]);
        bytes.extend_from_slice(&[0xA5, 0x5A, 0xFF, 0, 0, 0, 0x20]);
        bytes.extend_from_slice(&[0xA5, 0x5A, 0x06, 0, 0, 0x40, 0x81]);
        let (events, counters) = decode(&bytes);
        let unexpected: Vec<(u8, u32)> = events
            .iter()
            .map(|e| match e {
                Event::Unexpected(d) => (d.data_type, d.len),
                other => panic!("{other:?}"),
            })
            .collect();
        assert_eq!(
            unexpected,
            [(0x15, 4), (0x04, 5), (0x06, 0), (0x20, 255), (0x81, 6)]
        );
        assert_eq!(counters.unexpected, 5);
        assert_eq!(counters.skipped_bytes, 0);
        // After the long one, the decoder looks for a descriptor again at once: a health
        // answer right behind it is read.
        let mut d = Decoder::new();
        for b in [0xA5, 0x5A, 0xFF, 0, 0, 0, 0x20] {
            d.push(b);
        }
        let health = [0xA5, 0x5A, 0x03, 0, 0, 0, 0x06, 1, 7, 0];
        let events: Vec<_> = health.iter().filter_map(|&b| d.push(b)).collect();
        assert!(
            matches!(
                events[..],
                [Event::Health(Health {
                    status: HealthStatus::Warning,
                    error_code: 7
                })]
            ),
            "{events:?}"
        );
    }

    fn stream(nodes: impl IntoIterator<Item = [u8; 5]>) -> Vec<u8> {
        let mut bytes = vec![0xA5, 0x5A, 0x05, 0x00, 0x00, 0x40, 0x81];
        for n in nodes {
            bytes.extend_from_slice(&n);
        }
        bytes
    }

    #[test]
    fn whole_turns_pass_without_a_resync_and_only_the_last_two_wait() {
        // 500 nodes a turn, 46 q6 apart, S on the first, three turns: the step across 0° is as
        // small as any other.
        let nodes: Vec<[u8; 5]> = (0..1500u16)
            .map(|i| node_bytes(i % 500 == 0, 40, (i % 500) * 46, 4000 + i))
            .collect();
        let (events, counters) = decode(&stream(nodes.iter().copied()));
        assert_eq!(counters, DecodeCounters::default());
        assert_eq!(events.len(), 1 + 1500 - CONFIRMING);
        assert_eq!(events[501], Event::Node(Node::parse(nodes[500]).unwrap()));
    }

    #[test]
    fn a_jump_of_up_to_five_degrees_is_a_gap_and_a_larger_one_a_resync() {
        let turn = |missing: std::ops::Range<u16>| {
            (0..60u16)
                .filter(move |i| !missing.contains(i))
                .map(|i| node_bytes(i == 0, 40, i * 46, 4000))
        };
        // Five whole nodes lost: a 4.3° step, alignment kept.
        let (events, counters) = decode(&stream(turn(20..25)));
        assert_eq!(counters.resyncs, 0);
        assert_eq!(events.len(), 1 + 55 - CONFIRMING);
        // Seven lost: a 5.75° step, which a stream that lost its alignment could make up.
        let (_, counters) = decode(&stream(turn(20..27)));
        assert_eq!(counters.resyncs, 1);
        // An angle of exactly 360° does not exist either.
        let mut nodes: Vec<[u8; 5]> = turn(0..0).collect();
        nodes.insert(30, node_bytes(false, 40, FULL_TURN_Q6, 4000));
        let (_, counters) = decode(&stream(nodes));
        assert_eq!(counters.resyncs, 1);
    }

    #[test]
    fn a_new_request_ends_the_stream_and_unknown_answers_are_skipped() {
        let mut d = Decoder::new();
        for b in [0xA5, 0x5A, 0x05, 0x00, 0x00, 0x40, 0x81] {
            d.push(b);
        }
        assert!(d.scanning());
        d.request_sent();
        assert!(!d.scanning());
        // An express-scan stream nobody asked for: skipped to the next request, even bytes
        // in it that look like an answer.
        let mut events = Vec::new();
        let express = [0xA5, 0x5A, 0x54, 0x00, 0x00, 0x40, 0x85];
        let lookalike = [0xA5, 0x5A, 0x03, 0, 0, 0, 0x06, 0, 0, 0];
        for b in express.into_iter().chain(lookalike) {
            events.extend(d.push(b));
        }
        assert!(matches!(
            events[..],
            [Event::Unexpected(Descriptor {
                data_type: 0x85,
                ..
            })]
        ));
        assert_eq!(d.counters().unexpected, 1);
        assert_eq!(d.counters().skipped_bytes, 10);
        d.request_sent();
        let health = [0xA5, 0x5A, 0x03, 0, 0, 0, 0x06, 0, 0, 0];
        let events: Vec<_> = health.iter().filter_map(|&b| d.push(b)).collect();
        assert!(matches!(
            events[..],
            [Event::Health(Health {
                status: HealthStatus::Good,
                ..
            })]
        ));
    }
}
