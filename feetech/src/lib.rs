//! Feetech STS serial-bus servo protocol, sans-IO.
//!
//! Bytes in, frames out: nothing here opens a port or reads a clock, so the same code serves
//! the bus driver (host side), the simulator (device side), fuzzers and tests.
//!
//! ```text
//! instruction  FF FF | ID | LEN | INSTR | P1 .. Pn | CHK      LEN = n + 2
//! status       FF FF | ID | LEN | ERR   | P1 .. Pn | CHK      CHK = !(ID + LEN + INSTR/ERR + ΣP)
//! ```
//!
//! * [`frame`]: checksum, framing, and the incremental [`frame::Decoder`] that finds valid packets
//!   inside arbitrary garbage and never panics.
//! * [`instruction`]: host → servo packets (PING, READ, WRITE, REG_WRITE, ACTION, REBOOT,
//!   SYNC_READ, SYNC_WRITE …), encoded by the host and parsed by the device side.
//! * [`status`]: servo → host packets; the status error bits are data ([`status::ServoStatus`]),
//!   never a transport failure.
//! * [`registers`]: the control table shared by STS3215, STS3250 and STS3095, with units.
//! * [`encoding`]: sign-magnitude words (bit 15, 11 or 10) and little-endian helpers.
//! * [`timing`]: wire time of frames at a baud rate, for deadlines and the simulator.

pub mod encoding;
pub mod frame;
pub mod instruction;
pub mod registers;
pub mod status;
pub mod timing;

pub use frame::{DecodeError, Decoder, Frame};
pub use instruction::{EncodeError, Instruction, InstructionError};
pub use registers::{FeedbackBlock, Register, ServoModel};
pub use status::{ServoStatus, StatusError, StatusPacket};

/// Broadcast id: every servo executes, none answers.
pub const BROADCAST_ID: u8 = 0xFE;
/// Largest unicast id a servo can have.
pub const MAX_ID: u8 = 0xFC;
/// Largest value of the LEN byte.
pub const MAX_LEN: u8 = 250;
/// Largest whole packet: header (2) + id + len + LEN bytes.
pub const MAX_PACKET: usize = 4 + MAX_LEN as usize;
/// Encoder steps in one output turn.
pub const STEPS_PER_TURN: u32 = 4096;
/// Amperes per raw unit of `Present_Current` and `Protection_Current`.
pub const AMPS_PER_CURRENT_UNIT: f64 = 0.0065;
