//! Word encodings of the STS control table.
//!
//! Signed registers are sign-magnitude, not two's complement: the sign sits in bit 15 for
//! position, speed and current, bit 11 for the homing offset and bit 10 for load and PWM.
//! Words are little-endian on STS/SMS servos.

use thiserror::Error;

/// A value that cannot be represented in a register's encoding.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
#[error("value {value} does not fit a sign-magnitude word with the sign at bit {sign_bit} (|v| ≤ {max})")]
pub struct OutOfRange {
    /// The value asked for.
    pub value: i32,
    /// The sign bit of the encoding.
    pub sign_bit: u8,
    /// The largest magnitude the encoding holds.
    pub max: i32,
}

/// Largest magnitude a sign-magnitude word with the sign at `sign_bit` holds.
pub const fn max_magnitude(sign_bit: u8) -> i32 {
    (1i32 << sign_bit) - 1
}

/// Decodes a sign-magnitude word. Bits above the sign bit are ignored, as the firmware does.
pub const fn decode_sign_magnitude(raw: u16, sign_bit: u8) -> i32 {
    let magnitude = (raw as i32) & max_magnitude(sign_bit);
    if raw & (1 << sign_bit) != 0 {
        -magnitude
    } else {
        magnitude
    }
}

/// Encodes `value` as a sign-magnitude word, refusing magnitudes the encoding cannot hold.
pub const fn encode_sign_magnitude(value: i32, sign_bit: u8) -> Result<u16, OutOfRange> {
    let max = max_magnitude(sign_bit);
    if value > max || value < -max {
        return Err(OutOfRange {
            value,
            sign_bit,
            max,
        });
    }
    if value < 0 {
        Ok(((-value) as u16) | (1 << sign_bit))
    } else {
        Ok(value as u16)
    }
}

/// Encodes `value` as a sign-magnitude word, clamped to the largest magnitude it holds: for a
/// goal that must be sent (a wheel speed beyond the register is sent at the register's limit,
/// never skipped).
pub const fn encode_sign_magnitude_saturating(value: i32, sign_bit: u8) -> u16 {
    let max = max_magnitude(sign_bit);
    let clamped = if value > max {
        max
    } else if value < -max {
        -max
    } else {
        value
    };
    if clamped < 0 {
        ((-clamped) as u16) | (1 << sign_bit)
    } else {
        clamped as u16
    }
}

/// Little-endian u16 from two bytes.
pub const fn u16_le(lo: u8, hi: u8) -> u16 {
    (lo as u16) | ((hi as u16) << 8)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn saturating_encoding_clamps_instead_of_failing() {
        assert_eq!(encode_sign_magnitude_saturating(40_000, 15), 0x7FFF);
        assert_eq!(encode_sign_magnitude_saturating(-40_000, 15), 0xFFFF);
        assert_eq!(
            encode_sign_magnitude_saturating(-5, 15),
            encode_sign_magnitude(-5, 15).unwrap_or(0)
        );
        assert_eq!(
            decode_sign_magnitude(encode_sign_magnitude_saturating(i32::MIN, 11), 11),
            -2047
        );
    }

    #[test]
    fn sign_magnitude_is_not_twos_complement() {
        assert_eq!(decode_sign_magnitude(0x8001, 15), -1);
        assert_eq!(decode_sign_magnitude(0x0001, 15), 1);
        assert_eq!(decode_sign_magnitude(0x0401, 10), -1);
        assert_eq!(decode_sign_magnitude(0x0800 | 2047, 11), -2047);
        assert_eq!(encode_sign_magnitude(-1, 15), Ok(0x8001));
        assert_eq!(encode_sign_magnitude(-2047, 11), Ok(0x0FFF));
        assert_eq!(encode_sign_magnitude(1000, 10), Ok(1000));
    }

    #[test]
    fn out_of_range_is_refused() {
        assert!(encode_sign_magnitude(2048, 11).is_err());
        assert!(encode_sign_magnitude(-1024, 10).is_err());
        assert!(encode_sign_magnitude(i32::MIN, 15).is_err());
    }

    #[test]
    fn round_trip_every_value() {
        for bit in [10u8, 11, 15] {
            let max = max_magnitude(bit);
            for v in -max..=max {
                let raw = encode_sign_magnitude(v, bit).unwrap();
                assert_eq!(decode_sign_magnitude(raw, bit), v);
            }
        }
    }
}
