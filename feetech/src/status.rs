//! Servo → host status packets. The error byte is data about the servo, never a transport error:
//! the instruction was executed all the same.

use crate::frame::{write_packet, Frame};
use crate::MAX_ID;
use thiserror::Error;

/// The servo status bits (the status packet's error byte, also register 65 `Status`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Hash)]
pub struct ServoStatus(pub u8);

impl ServoStatus {
    /// Input voltage outside the Min/Max_Voltage_Limit window.
    pub const VOLTAGE: u8 = 1 << 0;
    /// Magnetic angle sensor fault.
    pub const ANGLE_SENSOR: u8 = 1 << 1;
    /// Over-temperature.
    pub const OVERHEAT: u8 = 1 << 2;
    /// Over-current protection tripped.
    pub const OVER_CURRENT: u8 = 1 << 3;
    /// Overload protection tripped.
    pub const OVERLOAD: u8 = 1 << 5;

    /// No bit set.
    pub fn is_ok(self) -> bool {
        self.0 == 0
    }
    /// Voltage bit.
    pub fn voltage(self) -> bool {
        self.0 & Self::VOLTAGE != 0
    }
    /// Angle-sensor bit.
    pub fn angle_sensor(self) -> bool {
        self.0 & Self::ANGLE_SENSOR != 0
    }
    /// Overheat bit.
    pub fn overheat(self) -> bool {
        self.0 & Self::OVERHEAT != 0
    }
    /// Over-current bit.
    pub fn over_current(self) -> bool {
        self.0 & Self::OVER_CURRENT != 0
    }
    /// Overload bit.
    pub fn overload(self) -> bool {
        self.0 & Self::OVERLOAD != 0
    }
}

impl std::fmt::Display for ServoStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let names = [
            (Self::VOLTAGE, "voltage"),
            (Self::ANGLE_SENSOR, "angle-sensor"),
            (Self::OVERHEAT, "overheat"),
            (Self::OVER_CURRENT, "over-current"),
            (Self::OVERLOAD, "overload"),
        ];
        if self.is_ok() {
            return f.write_str("ok");
        }
        let mut first = true;
        for (bit, name) in names {
            if self.0 & bit != 0 {
                if !first {
                    f.write_str("+")?;
                }
                f.write_str(name)?;
                first = false;
            }
        }
        if self.0 & !(0x2F) != 0 {
            write!(
                f,
                "{}reserved({:#04x})",
                if first { "" } else { "+" },
                self.0 & !0x2F
            )?;
        }
        Ok(())
    }
}

/// A frame that cannot be a status packet.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum StatusError {
    /// Status packets come from unicast ids only.
    #[error("status packet from invalid id {0:#04x}")]
    InvalidId(u8),
    /// The error byte has bit 7 set, which no servo sends.
    #[error("status packet from id {id} with invalid error byte {error:#04x}")]
    InvalidErrorByte {
        /// Servo id.
        id: u8,
        /// The error byte.
        error: u8,
    },
}

/// A status packet: a borrowed view of a frame that passed the status checks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StatusPacket<'a> {
    /// The answering servo.
    pub id: u8,
    /// Its status bits.
    pub status: ServoStatus,
    /// Returned data (empty for PING and WRITE replies).
    pub params: &'a [u8],
}

impl<'a> StatusPacket<'a> {
    /// Interprets a decoded frame as a status packet (host side).
    pub fn parse(frame: &'a Frame) -> Result<Self, StatusError> {
        if frame.id > MAX_ID {
            return Err(StatusError::InvalidId(frame.id));
        }
        if frame.code > 0x7F {
            return Err(StatusError::InvalidErrorByte {
                id: frame.id,
                error: frame.code,
            });
        }
        Ok(StatusPacket {
            id: frame.id,
            status: ServoStatus(frame.code),
            params: frame.params(),
        })
    }

    /// Encodes a status packet (device side), returning its length, or `None` if `out` is too
    /// small or `params` too long.
    pub fn encode(&self, out: &mut [u8]) -> Option<usize> {
        write_packet(out, self.id, self.status.0, self.params)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Decoder;

    #[test]
    fn golden_read_reply() {
        let mut d = Decoder::new();
        d.push(&[0xFF, 0xFF, 0x01, 0x04, 0x00, 0x18, 0x05, 0xDD]);
        let frame = d.next_frame().unwrap().unwrap();
        let status = StatusPacket::parse(&frame).unwrap();
        assert_eq!(status.id, 1);
        assert!(status.status.is_ok());
        assert_eq!(
            crate::encoding::u16_le(status.params[0], status.params[1]),
            1304
        );
        let mut out = [0u8; 16];
        let n = status.encode(&mut out).unwrap();
        assert_eq!(&out[..n], &[0xFF, 0xFF, 0x01, 0x04, 0x00, 0x18, 0x05, 0xDD]);
    }

    #[test]
    fn status_bits_are_data() {
        let frame = Frame::new(3, ServoStatus::OVERHEAT | ServoStatus::OVERLOAD, &[]).unwrap();
        let status = StatusPacket::parse(&frame).unwrap();
        assert!(status.status.overheat() && status.status.overload());
        assert!(!status.status.over_current());
        assert_eq!(status.status.to_string(), "overheat+overload");
    }

    #[test]
    fn invalid_status_frames_are_refused() {
        let f = Frame::new(0xFE, 0, &[]).unwrap();
        assert_eq!(StatusPacket::parse(&f), Err(StatusError::InvalidId(0xFE)));
        let f = Frame::new(1, 0x80, &[]).unwrap();
        assert_eq!(
            StatusPacket::parse(&f),
            Err(StatusError::InvalidErrorByte { id: 1, error: 0x80 })
        );
    }
}
