//! Host → servo instruction packets: encoded by the host, parsed by the device side.

use crate::frame::{write_packet, Frame};
use crate::{BROADCAST_ID, MAX_ID, MAX_LEN};
use thiserror::Error;

/// Instruction codes.
pub mod code {
    /// PING: the servo answers with an empty status packet.
    pub const PING: u8 = 0x01;
    /// READ addr, len.
    pub const READ: u8 = 0x02;
    /// WRITE addr, data…
    pub const WRITE: u8 = 0x03;
    /// REG_WRITE addr, data…: stored until ACTION.
    pub const REG_WRITE: u8 = 0x04;
    /// ACTION: executes the registered writes.
    pub const ACTION: u8 = 0x05;
    /// Factory reset of the control table.
    pub const FACTORY_RESET: u8 = 0x06;
    /// REBOOT: no reply, the servo is gone for ~800 ms.
    pub const REBOOT: u8 = 0x08;
    /// Reset (clears the multi-turn count on some firmware).
    pub const RESET: u8 = 0x0A;
    /// Midpoint calibration.
    pub const CALIBRATE: u8 = 0x0B;
    /// SYNC_READ addr, len, ids…: each servo answers in request order.
    pub const SYNC_READ: u8 = 0x82;
    /// SYNC_WRITE addr, len, [id data…]×N: broadcast, no reply.
    pub const SYNC_WRITE: u8 = 0x83;
}

/// An instruction, borrowing its variable-length parts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Instruction<'a> {
    /// PING.
    Ping {
        /// Target id.
        id: u8,
    },
    /// READ `len` bytes from `addr`.
    Read {
        /// Target id.
        id: u8,
        /// First register address.
        addr: u8,
        /// Bytes to read.
        len: u8,
    },
    /// WRITE `data` at `addr`.
    Write {
        /// Target id, or broadcast.
        id: u8,
        /// First register address.
        addr: u8,
        /// Bytes to write.
        data: &'a [u8],
    },
    /// REG_WRITE `data` at `addr`, applied at the next ACTION.
    RegWrite {
        /// Target id, or broadcast.
        id: u8,
        /// First register address.
        addr: u8,
        /// Bytes to write.
        data: &'a [u8],
    },
    /// ACTION.
    Action {
        /// Target id, usually broadcast.
        id: u8,
    },
    /// Factory reset.
    FactoryReset {
        /// Target id.
        id: u8,
    },
    /// REBOOT.
    Reboot {
        /// Target id.
        id: u8,
    },
    /// SYNC_READ `len` bytes at `addr` from each of `ids`.
    SyncRead {
        /// First register address.
        addr: u8,
        /// Bytes each servo returns.
        len: u8,
        /// Servos, in the order they answer.
        ids: &'a [u8],
    },
    /// SYNC_WRITE: `payload` is `[id d1..d_len] × N`.
    SyncWrite {
        /// First register address.
        addr: u8,
        /// Data bytes per servo.
        len: u8,
        /// `[id, d1..d_len]` repeated for each servo.
        payload: &'a [u8],
    },
}

/// An instruction that cannot be encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum EncodeError {
    /// The parameters do not fit in one packet (LEN ≤ 250).
    #[error("{params} parameter bytes exceed one packet (at most {max})")]
    TooLong {
        /// Parameter bytes asked for.
        params: usize,
        /// The most one packet carries.
        max: usize,
    },
    /// The output buffer is smaller than the packet.
    #[error("output buffer of {have} bytes, packet needs {need}")]
    BufferTooSmall {
        /// Buffer size.
        have: usize,
        /// Packet size.
        need: usize,
    },
    /// An id that is neither a unicast id nor (where allowed) broadcast.
    #[error("invalid servo id {0}")]
    InvalidId(u8),
    /// A SYNC_WRITE payload that is not a whole number of `[id data…]` records.
    #[error(
        "sync write payload of {payload} bytes is not a multiple of {record} (id + {len} data)"
    )]
    RaggedSyncWrite {
        /// Payload size.
        payload: usize,
        /// Record size (len + 1).
        record: usize,
        /// Data bytes per servo.
        len: u8,
    },
}

/// A frame that is not a well-formed instruction (device side).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum InstructionError {
    /// Unknown instruction code.
    #[error("unknown instruction {0:#04x}")]
    Unknown(u8),
    /// Parameters of the wrong shape for the instruction.
    #[error("instruction {code:#04x} with {len} parameter bytes is malformed")]
    BadParameters {
        /// Instruction code.
        code: u8,
        /// Parameter bytes received.
        len: usize,
    },
}

impl<'a> Instruction<'a> {
    /// The instruction code.
    pub fn code(&self) -> u8 {
        match self {
            Instruction::Ping { .. } => code::PING,
            Instruction::Read { .. } => code::READ,
            Instruction::Write { .. } => code::WRITE,
            Instruction::RegWrite { .. } => code::REG_WRITE,
            Instruction::Action { .. } => code::ACTION,
            Instruction::FactoryReset { .. } => code::FACTORY_RESET,
            Instruction::Reboot { .. } => code::REBOOT,
            Instruction::SyncRead { .. } => code::SYNC_READ,
            Instruction::SyncWrite { .. } => code::SYNC_WRITE,
        }
    }

    /// The id byte of the packet.
    pub fn id(&self) -> u8 {
        match *self {
            Instruction::Ping { id }
            | Instruction::Read { id, .. }
            | Instruction::Write { id, .. }
            | Instruction::RegWrite { id, .. }
            | Instruction::Action { id }
            | Instruction::FactoryReset { id }
            | Instruction::Reboot { id } => id,
            Instruction::SyncRead { .. } | Instruction::SyncWrite { .. } => BROADCAST_ID,
        }
    }

    /// Whether a servo answers this instruction with a status packet.
    pub fn expects_reply(&self) -> bool {
        match self {
            Instruction::SyncWrite { .. } | Instruction::Reboot { .. } => false,
            Instruction::SyncRead { .. } | Instruction::Ping { .. } => true,
            other => other.id() != BROADCAST_ID,
        }
    }

    /// Encodes the packet into `out`, returning its length.
    pub fn encode(&self, out: &mut [u8]) -> Result<usize, EncodeError> {
        let id = self.id();
        // A broadcast PING is answered by each servo that hears it: Feetech documents it for
        // one servo alone on the bus (docs/commissioning.md); a broadcast READ has no meaning.
        let broadcast_ok = !matches!(self, Instruction::Read { .. } | Instruction::Reboot { .. });
        if id > MAX_ID && !(id == BROADCAST_ID && broadcast_ok) {
            return Err(EncodeError::InvalidId(id));
        }
        let mut params = [0u8; MAX_LEN as usize];
        let n = match *self {
            Instruction::Ping { .. }
            | Instruction::Action { .. }
            | Instruction::FactoryReset { .. }
            | Instruction::Reboot { .. } => 0,
            Instruction::Read { addr, len, .. } => {
                params[0] = addr;
                params[1] = len;
                2
            }
            Instruction::Write { addr, data, .. } | Instruction::RegWrite { addr, data, .. } => {
                put(&mut params, &[&[addr], data])?
            }
            Instruction::SyncRead { addr, len, ids } => {
                if let Some(&bad) = ids.iter().find(|&&i| i > MAX_ID) {
                    return Err(EncodeError::InvalidId(bad));
                }
                put(&mut params, &[&[addr, len], ids])?
            }
            Instruction::SyncWrite { addr, len, payload } => {
                let record = len as usize + 1;
                if !payload.len().is_multiple_of(record) {
                    return Err(EncodeError::RaggedSyncWrite {
                        payload: payload.len(),
                        record,
                        len,
                    });
                }
                if let Some(bad) = payload.chunks(record).map(|r| r[0]).find(|&i| i > MAX_ID) {
                    return Err(EncodeError::InvalidId(bad));
                }
                put(&mut params, &[&[addr, len], payload])?
            }
        };
        let need = n + 6;
        write_packet(out, id, self.code(), &params[..n]).ok_or(EncodeError::BufferTooSmall {
            have: out.len(),
            need,
        })
    }

    /// Parses a frame received by a servo (device side).
    pub fn parse(frame: &'a Frame) -> Result<Self, InstructionError> {
        let p = frame.params();
        let id = frame.id;
        let bad = || InstructionError::BadParameters {
            code: frame.code,
            len: p.len(),
        };
        Ok(match frame.code {
            code::PING if p.is_empty() => Instruction::Ping { id },
            code::READ if p.len() == 2 => Instruction::Read {
                id,
                addr: p[0],
                len: p[1],
            },
            code::WRITE if p.len() >= 2 => Instruction::Write {
                id,
                addr: p[0],
                data: &p[1..],
            },
            code::REG_WRITE if p.len() >= 2 => Instruction::RegWrite {
                id,
                addr: p[0],
                data: &p[1..],
            },
            code::ACTION if p.is_empty() => Instruction::Action { id },
            code::FACTORY_RESET if p.is_empty() => Instruction::FactoryReset { id },
            code::REBOOT if p.is_empty() => Instruction::Reboot { id },
            code::SYNC_READ if p.len() >= 3 && p[1] > 0 => Instruction::SyncRead {
                addr: p[0],
                len: p[1],
                ids: &p[2..],
            },
            code::SYNC_WRITE
                if p.len() >= 3 && p[1] > 0 && (p.len() - 2).is_multiple_of(p[1] as usize + 1) =>
            {
                Instruction::SyncWrite {
                    addr: p[0],
                    len: p[1],
                    payload: &p[2..],
                }
            }
            code::PING
            | code::READ
            | code::WRITE
            | code::REG_WRITE
            | code::ACTION
            | code::FACTORY_RESET
            | code::REBOOT
            | code::SYNC_READ
            | code::SYNC_WRITE => return Err(bad()),
            other => return Err(InstructionError::Unknown(other)),
        })
    }

    /// For a SYNC_WRITE, the `(id, data)` records; empty for other instructions.
    pub fn sync_write_records(&self) -> impl Iterator<Item = (u8, &'a [u8])> {
        let (len, payload): (usize, &'a [u8]) = match *self {
            Instruction::SyncWrite { len, payload, .. } => (len as usize, payload),
            _ => (0, &[]),
        };
        payload
            .chunks_exact(len + 1)
            .map(|record| (record[0], &record[1..]))
    }
}

fn put(out: &mut [u8], parts: &[&[u8]]) -> Result<usize, EncodeError> {
    let total: usize = parts.iter().map(|p| p.len()).sum();
    let max = MAX_LEN as usize - 2;
    if total > max {
        return Err(EncodeError::TooLong { params: total, max });
    }
    let mut at = 0;
    for part in parts {
        out[at..at + part.len()].copy_from_slice(part);
        at += part.len();
    }
    Ok(total)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn enc(i: Instruction) -> Vec<u8> {
        let mut buf = [0u8; 300];
        let n = i.encode(&mut buf).unwrap();
        buf[..n].to_vec()
    }

    #[test]
    fn golden_vectors_from_the_protocol_doc() {
        assert_eq!(
            enc(Instruction::Ping { id: 1 }),
            [0xFF, 0xFF, 0x01, 0x02, 0x01, 0xFB]
        );
        assert_eq!(
            enc(Instruction::Read {
                id: 1,
                addr: 0x38,
                len: 2
            }),
            [0xFF, 0xFF, 0x01, 0x04, 0x02, 0x38, 0x02, 0xBE]
        );
        assert_eq!(
            enc(Instruction::Action { id: BROADCAST_ID }),
            [0xFF, 0xFF, 0xFE, 0x02, 0x05, 0xFA]
        );
        assert_eq!(
            enc(Instruction::SyncRead {
                addr: 0x1E,
                len: 2,
                ids: &[0x0B, 0x0C]
            }),
            [0xFF, 0xFF, 0xFE, 0x06, 0x82, 0x1E, 0x02, 0x0B, 0x0C, 0x42]
        );
    }

    #[test]
    fn sync_write_sizes_match_the_doc() {
        // LEN = (L+1)·N + 4; frame = 8 + N·(L+1).
        let payload = [1, 0x00, 0x08, 2, 0x10, 0x08, 3, 0x20, 0x08];
        let bytes = enc(Instruction::SyncWrite {
            addr: 42,
            len: 2,
            payload: &payload,
        });
        assert_eq!(bytes.len(), 8 + 3 * 3);
        assert_eq!(bytes[3], 3 * 3 + 4);
        assert_eq!(bytes[2], BROADCAST_ID);
    }

    #[test]
    fn device_side_parses_what_the_host_encodes() {
        let payload = [1, 0x00, 0x08, 2, 0x10, 0x08];
        let cases = [
            Instruction::Ping { id: 3 },
            Instruction::Read {
                id: 4,
                addr: 56,
                len: 15,
            },
            Instruction::Write {
                id: 5,
                addr: 40,
                data: &[1],
            },
            Instruction::RegWrite {
                id: 5,
                addr: 42,
                data: &[0, 8],
            },
            Instruction::Action { id: BROADCAST_ID },
            Instruction::Reboot { id: 9 },
            Instruction::SyncRead {
                addr: 56,
                len: 15,
                ids: &[1, 2, 3],
            },
            Instruction::SyncWrite {
                addr: 42,
                len: 2,
                payload: &payload,
            },
        ];
        for case in cases {
            let bytes = enc(case);
            let mut d = crate::Decoder::new();
            d.push(&bytes);
            let frame = d.next_frame().unwrap().unwrap();
            assert_eq!(Instruction::parse(&frame).unwrap(), case);
        }
        let sw = Instruction::SyncWrite {
            addr: 42,
            len: 2,
            payload: &payload,
        };
        let records: Vec<_> = sw.sync_write_records().collect();
        assert_eq!(records, [(1, &[0u8, 8][..]), (2, &[0x10, 8][..])]);
    }

    #[test]
    fn a_broadcast_ping_is_the_packet_the_sdks_send_and_expects_replies() {
        // LeRobot's `_broadcast_ping` and Feetech's C++ `Ping(0xFE)`.
        let mut buf = [0u8; 8];
        let ping = Instruction::Ping { id: BROADCAST_ID };
        assert_eq!(ping.encode(&mut buf), Ok(6));
        assert_eq!(buf[..6], [0xFF, 0xFF, 0xFE, 0x02, 0x01, 0xFE]);
        assert!(ping.expects_reply());
    }

    #[test]
    fn bad_encodes_are_refused() {
        let mut buf = [0u8; 300];
        assert_eq!(
            Instruction::Read {
                id: BROADCAST_ID,
                addr: 0,
                len: 1
            }
            .encode(&mut buf),
            Err(EncodeError::InvalidId(BROADCAST_ID))
        );
        assert!(matches!(
            Instruction::SyncWrite {
                addr: 42,
                len: 2,
                payload: &[1, 2]
            }
            .encode(&mut buf),
            Err(EncodeError::RaggedSyncWrite { .. })
        ));
        assert!(matches!(
            Instruction::Ping { id: 1 }.encode(&mut buf[..3]),
            Err(EncodeError::BufferTooSmall { have: 3, need: 6 })
        ));
        let long = [0u8; 260];
        assert!(matches!(
            Instruction::Write {
                id: 1,
                addr: 0,
                data: &long
            }
            .encode(&mut buf),
            Err(EncodeError::TooLong { .. })
        ));
    }

    #[test]
    fn malformed_instructions_are_typed() {
        let f = Frame::new(1, 0x77, &[]).unwrap();
        assert_eq!(Instruction::parse(&f), Err(InstructionError::Unknown(0x77)));
        let f = Frame::new(1, code::READ, &[56]).unwrap();
        assert_eq!(
            Instruction::parse(&f),
            Err(InstructionError::BadParameters {
                code: code::READ,
                len: 1
            })
        );
    }
}
