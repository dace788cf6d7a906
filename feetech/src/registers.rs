//! The STS control table (STS3215; STS3250 and STS3095 share it) with sizes, areas and units.
//!
//! EEPROM 0–39 persists only while `Lock` (55) is 0; SRAM 40–55 is volatile; 56–70 is the
//! read-only feedback block, which one 15-byte read returns whole.

use crate::encoding::{decode_sign_magnitude, u16_le};
use crate::status::ServoStatus;

/// Where a register lives.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Area {
    /// Persistent across power cycles; each write wears the flash.
    Eeprom,
    /// Volatile, writable.
    Sram,
    /// Feedback, read-only.
    ReadOnly,
}

/// How a register's raw bits map to a signed or unsigned integer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoding {
    /// Plain unsigned.
    Unsigned,
    /// Sign-magnitude with the sign at this bit.
    SignMagnitude(u8),
}

/// The physical unit of one raw count.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Unit {
    /// No unit (ids, codes, flags, bit masks).
    None,
    /// Encoder steps, 4096 a turn.
    Steps,
    /// Steps per second.
    StepsPerSecond,
    /// 100 steps/s².
    HundredStepsPerSecond2,
    /// 0.1 % of full output.
    PerMille,
    /// 1 % of full output.
    Percent,
    /// 0.1 V.
    DeciVolt,
    /// °C.
    Celsius,
    /// 6.5 mA.
    CurrentUnit,
    /// 10 ms.
    TenMilliseconds,
    /// 2 µs.
    TwoMicroseconds,
}

impl Unit {
    /// One count in a unit a person reads, and that unit's symbol (angles in degrees; `count`
    /// for a register without a unit).
    pub fn scale(self) -> (f64, &'static str) {
        let degrees_per_step = 360.0 / f64::from(crate::STEPS_PER_TURN);
        match self {
            Unit::None => (1.0, "count"),
            Unit::Steps => (degrees_per_step, "°"),
            Unit::StepsPerSecond => (degrees_per_step, "°/s"),
            Unit::HundredStepsPerSecond2 => (100.0 * degrees_per_step, "°/s²"),
            Unit::PerMille => (0.1, "%"),
            Unit::Percent => (1.0, "%"),
            Unit::DeciVolt => (0.1, "V"),
            Unit::Celsius => (1.0, "°C"),
            Unit::CurrentUnit => (crate::AMPS_PER_CURRENT_UNIT, "A"),
            Unit::TenMilliseconds => (0.01, "s"),
            Unit::TwoMicroseconds => (2e-6, "s"),
        }
    }
}

/// One entry of the control table.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Register {
    /// Name as in Feetech's documentation.
    pub name: &'static str,
    /// Address in the control table (of the low byte, for a 2-byte register).
    pub addr: u8,
    /// Size in bytes (1 or 2).
    pub size: u8,
    /// Memory area.
    pub area: Area,
    /// Raw encoding.
    pub encoding: Encoding,
    /// Unit of one count.
    pub unit: Unit,
}

impl Register {
    /// Decodes this register's value from `bytes`, the first `size` bytes of a read at `addr`.
    pub fn decode(&self, bytes: &[u8]) -> Option<i32> {
        let raw = match (self.size, bytes) {
            (1, [b, ..]) => u16::from(*b),
            (2, [lo, hi, ..]) => u16_le(*lo, *hi),
            _ => return None,
        };
        Some(match self.encoding {
            Encoding::Unsigned => i32::from(raw),
            Encoding::SignMagnitude(bit) => decode_sign_magnitude(raw, bit),
        })
    }
}

macro_rules! registers {
    ($($(#[$doc:meta])* $ident:ident = $name:literal, $addr:literal, $size:literal, $area:ident, $enc:expr, $unit:ident;)*) => {
        $( $(#[$doc])* pub const $ident: Register = Register {
            name: $name, addr: $addr, size: $size, area: Area::$area, encoding: $enc, unit: Unit::$unit,
        }; )*
        /// Every register, by address.
        pub const TABLE: &[Register] = &[$($ident),*];
    };
}

const U: Encoding = Encoding::Unsigned;

registers! {
    /// Firmware major version.
    FIRMWARE_MAJOR = "Firmware_Major", 0, 1, Eeprom, U, None;
    /// Firmware minor version.
    FIRMWARE_MINOR = "Firmware_Minor", 1, 1, Eeprom, U, None;
    /// Model number (STS3215 = 777, STS3250 = 2825, STS3095 = 2569).
    MODEL_NUMBER = "Model_Number", 3, 2, Eeprom, U, None;
    /// Servo id.
    ID = "ID", 5, 1, Eeprom, U, None;
    /// Baud rate code (0 = 1 Mbps).
    BAUD_RATE = "Baud_Rate", 6, 1, Eeprom, U, None;
    /// Delay before a reply.
    RETURN_DELAY_TIME = "Return_Delay_Time", 7, 1, Eeprom, U, TwoMicroseconds;
    /// Lower goal limit enforced by the firmware.
    MIN_POSITION_LIMIT = "Min_Position_Limit", 9, 2, Eeprom, U, Steps;
    /// Upper goal limit enforced by the firmware.
    MAX_POSITION_LIMIT = "Max_Position_Limit", 11, 2, Eeprom, U, Steps;
    /// Over-temperature cutoff (the hardware thermal tier).
    MAX_TEMPERATURE_LIMIT = "Max_Temperature_Limit", 13, 1, Eeprom, U, Celsius;
    /// Over-voltage limit.
    MAX_VOLTAGE_LIMIT = "Max_Voltage_Limit", 14, 1, Eeprom, U, DeciVolt;
    /// Under-voltage limit.
    MIN_VOLTAGE_LIMIT = "Min_Voltage_Limit", 15, 1, Eeprom, U, DeciVolt;
    /// Torque limit copied to `Torque_Limit` at power-up.
    MAX_TORQUE_LIMIT = "Max_Torque_Limit", 16, 2, Eeprom, U, PerMille;
    /// Phase bit field.
    PHASE = "Phase", 18, 1, Eeprom, U, None;
    /// Protection enable mask (same bits as `Status`).
    UNLOADING_CONDITION = "Unloading_Condition", 19, 1, Eeprom, U, None;
    /// LED alarm mask.
    LED_ALARM_CONDITION = "LED_Alarm_Condition", 20, 1, Eeprom, U, None;
    /// Position loop P.
    P_COEFFICIENT = "P_Coefficient", 21, 1, Eeprom, U, None;
    /// Position loop D.
    D_COEFFICIENT = "D_Coefficient", 22, 1, Eeprom, U, None;
    /// Position loop I.
    I_COEFFICIENT = "I_Coefficient", 23, 1, Eeprom, U, None;
    /// Over-current threshold.
    PROTECTION_CURRENT = "Protection_Current", 28, 2, Eeprom, U, CurrentUnit;
    /// Offset subtracted from the raw position.
    HOMING_OFFSET = "Homing_Offset", 31, 2, Eeprom, Encoding::SignMagnitude(11), Steps;
    /// 0 position, 1 speed, 2 PWM, 3 step.
    OPERATING_MODE = "Operating_Mode", 33, 1, Eeprom, U, None;
    /// Output after overload protection trips.
    PROTECTIVE_TORQUE = "Protective_Torque", 34, 1, Eeprom, U, Percent;
    /// Overload duration before protection trips.
    PROTECTION_TIME = "Protection_Time", 35, 1, Eeprom, U, TenMilliseconds;
    /// Overload threshold.
    OVERLOAD_TORQUE = "Overload_Torque", 36, 1, Eeprom, U, Percent;
    /// Over-current duration before protection trips.
    OVER_CURRENT_PROTECTION_TIME = "Over_Current_Protection_Time", 38, 1, Eeprom, U, TenMilliseconds;
    /// 0 off, 1 on, 2 damping.
    TORQUE_ENABLE = "Torque_Enable", 40, 1, Sram, U, None;
    /// Profile acceleration (0 = maximum).
    ACCELERATION = "Acceleration", 41, 1, Sram, U, HundredStepsPerSecond2;
    /// Position goal.
    GOAL_POSITION = "Goal_Position", 42, 2, Sram, Encoding::SignMagnitude(15), Steps;
    /// PWM goal in mode 2.
    GOAL_TIME = "Goal_Time", 44, 2, Sram, Encoding::SignMagnitude(10), PerMille;
    /// Velocity goal (speed mode) or profile velocity (position mode, 0 = maximum).
    GOAL_VELOCITY = "Goal_Velocity", 46, 2, Sram, Encoding::SignMagnitude(15), StepsPerSecond;
    /// Volatile torque limit.
    TORQUE_LIMIT = "Torque_Limit", 48, 2, Sram, U, PerMille;
    /// 1 = EEPROM locked.
    LOCK = "Lock", 55, 1, Sram, U, None;
    /// Present position, steps (4096 a turn) less `Homing_Offset`; sign-magnitude, sign at bit 15.
    PRESENT_POSITION = "Present_Position", 56, 2, ReadOnly, Encoding::SignMagnitude(15), Steps;
    /// Present velocity, steps/s; sign-magnitude, sign at bit 15.
    PRESENT_VELOCITY = "Present_Velocity", 58, 2, ReadOnly, Encoding::SignMagnitude(15), StepsPerSecond;
    /// Output duty.
    PRESENT_LOAD = "Present_Load", 60, 2, ReadOnly, Encoding::SignMagnitude(10), PerMille;
    /// Supply voltage.
    PRESENT_VOLTAGE = "Present_Voltage", 62, 1, ReadOnly, U, DeciVolt;
    /// Present temperature, whole °C.
    PRESENT_TEMPERATURE = "Present_Temperature", 63, 1, ReadOnly, U, Celsius;
    /// Status bits.
    STATUS = "Status", 65, 1, ReadOnly, U, None;
    /// Moving flag.
    MOVING = "Moving", 66, 1, ReadOnly, U, None;
    /// Motor current.
    PRESENT_CURRENT = "Present_Current", 69, 2, ReadOnly, Encoding::SignMagnitude(15), CurrentUnit;
}

/// Size of the register file the simulator keeps (addresses 0..=70 and a little slack).
pub const TABLE_SIZE: usize = 0x50;

/// Looks a register up by address.
pub fn by_addr(addr: u8) -> Option<&'static Register> {
    TABLE.iter().find(|r| r.addr == addr)
}

/// The servo models on the A3.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ServoModel {
    /// 30 kg·cm at 12 V (forearm roll, wrist second axis, gripper).
    Sts3215,
    /// 50 kg·cm at 12 V (bicep rotation, wrist pitch).
    Sts3250,
    /// ~95 kg·cm (shoulder axes, bicep).
    Sts3095,
}

impl ServoModel {
    /// The value of register 3 `Model_Number`.
    pub const fn model_number(self) -> u16 {
        match self {
            ServoModel::Sts3215 => 777,
            ServoModel::Sts3250 => 2825,
            ServoModel::Sts3095 => 2569,
        }
    }

    /// Its key in configuration files and the robot description (`sts3215`, ...).
    pub const fn key(self) -> &'static str {
        match self {
            ServoModel::Sts3215 => "sts3215",
            ServoModel::Sts3250 => "sts3250",
            ServoModel::Sts3095 => "sts3095",
        }
    }

    /// The model of a key (see [`ServoModel::key`]).
    pub fn from_key(key: &str) -> Option<Self> {
        [
            ServoModel::Sts3215,
            ServoModel::Sts3250,
            ServoModel::Sts3095,
        ]
        .into_iter()
        .find(|m| m.key() == key)
    }

    /// The model of a `Model_Number` value.
    pub const fn from_model_number(n: u16) -> Option<Self> {
        match n {
            777 => Some(ServoModel::Sts3215),
            2825 => Some(ServoModel::Sts3250),
            2569 => Some(ServoModel::Sts3095),
            _ => None,
        }
    }
}

/// First address of the feedback block.
pub const FEEDBACK_ADDR: u8 = 56;
/// Length of the feedback block (56..=70).
pub const FEEDBACK_LEN: u8 = 15;

/// The decoded feedback block (registers 56–70), in raw register units.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FeedbackBlock {
    /// `Present_Position`, steps.
    pub position: i32,
    /// `Present_Velocity`, steps/s.
    pub velocity: i32,
    /// `Present_Load`, 0.1 % of full duty.
    pub load: i32,
    /// `Present_Voltage`, 0.1 V.
    pub voltage: u8,
    /// `Present_Temperature`, °C.
    pub temperature: u8,
    /// `Status` bits.
    pub status: ServoStatus,
    /// `Moving` flag.
    pub moving: bool,
    /// `Present_Current`, 6.5 mA units.
    pub current: i32,
}

impl FeedbackBlock {
    /// Decodes the 15 bytes read at address 56.
    pub fn parse(bytes: &[u8]) -> Option<Self> {
        let b: &[u8; FEEDBACK_LEN as usize] =
            bytes.get(..FEEDBACK_LEN as usize)?.try_into().ok()?;
        let word = |i: usize| u16_le(b[i], b[i + 1]);
        Some(FeedbackBlock {
            position: decode_sign_magnitude(word(0), 15),
            velocity: decode_sign_magnitude(word(2), 15),
            load: decode_sign_magnitude(word(4), 10),
            voltage: b[6],
            temperature: b[7],
            status: ServoStatus(b[9]),
            moving: b[10] != 0,
            current: decode_sign_magnitude(word(13), 15),
        })
    }
}

/// First address of the safety block: `Torque_Enable` (40) through `Torque_Limit` (48–49), the
/// settings that keep a motor from cooking, read back to confirm that a servo holds them.
pub const SAFETY_ADDR: u8 = 40;
/// Length of the safety block (40..=49).
pub const SAFETY_LEN: u8 = 10;

/// The decoded safety block (registers 40–49), in raw register units.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SafetyBlock {
    /// `Torque_Enable` (0 off, 1 on).
    pub torque_enable: u8,
    /// `Goal_Position`, steps.
    pub goal_position: i32,
    /// `Goal_Velocity`, steps/s.
    pub goal_velocity: i32,
    /// `Torque_Limit`, 0.1 % of full output.
    pub torque_limit: u16,
}

impl SafetyBlock {
    /// Decodes the 10 bytes read at address 40.
    pub fn parse(bytes: &[u8]) -> Option<Self> {
        let b: &[u8; SAFETY_LEN as usize] = bytes.get(..SAFETY_LEN as usize)?.try_into().ok()?;
        let word = |addr: u8| {
            let i = usize::from(addr - SAFETY_ADDR);
            u16_le(b[i], b[i + 1])
        };
        Some(SafetyBlock {
            torque_enable: b[usize::from(TORQUE_ENABLE.addr - SAFETY_ADDR)],
            goal_position: decode_sign_magnitude(word(GOAL_POSITION.addr), 15),
            goal_velocity: decode_sign_magnitude(word(GOAL_VELOCITY.addr), 15),
            torque_limit: word(TORQUE_LIMIT.addr),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn safety_block_spans_torque_enable_to_torque_limit() {
        assert_eq!(SAFETY_ADDR, TORQUE_ENABLE.addr);
        assert_eq!(
            SAFETY_ADDR + SAFETY_LEN,
            TORQUE_LIMIT.addr + TORQUE_LIMIT.size
        );
        // Torque on, goal -5 steps, speed 300 steps/s, limit 25 %.
        let bytes = [1, 0, 0x05, 0x80, 0, 0, 0x2C, 0x01, 0xFA, 0x00];
        let b = SafetyBlock::parse(&bytes).unwrap();
        assert_eq!(
            b,
            SafetyBlock {
                torque_enable: 1,
                goal_position: -5,
                goal_velocity: 300,
                torque_limit: 250
            }
        );
        assert_eq!(SafetyBlock::parse(&bytes[..9]), None);
    }

    #[test]
    fn table_is_sorted_and_does_not_overlap() {
        for pair in TABLE.windows(2) {
            assert!(
                pair[0].addr + pair[0].size <= pair[1].addr,
                "{} overlaps {}",
                pair[0].name,
                pair[1].name
            );
        }
        assert!(TABLE
            .iter()
            .all(|r| (r.addr + r.size) as usize <= TABLE_SIZE));
    }

    #[test]
    fn feedback_block_is_contiguous_56_to_70() {
        let last = PRESENT_CURRENT.addr + PRESENT_CURRENT.size - 1;
        assert_eq!(last - FEEDBACK_ADDR + 1, FEEDBACK_LEN);
        for r in TABLE.iter().filter(|r| r.area == Area::ReadOnly) {
            assert!(r.addr >= FEEDBACK_ADDR && r.addr + r.size <= FEEDBACK_ADDR + FEEDBACK_LEN);
        }
    }

    #[test]
    fn feedback_block_parses_signs() {
        let mut b = [0u8; 15];
        b[0..2].copy_from_slice(&2048u16.to_le_bytes());
        b[2..4].copy_from_slice(&(0x8000u16 | 100).to_le_bytes());
        b[4..6].copy_from_slice(&(0x0400u16 | 500).to_le_bytes());
        b[6] = 121;
        b[7] = 41;
        b[9] = ServoStatus::OVERLOAD;
        b[10] = 1;
        b[13..15].copy_from_slice(&(0x8000u16 | 300).to_le_bytes());
        let f = FeedbackBlock::parse(&b).unwrap();
        assert_eq!(
            (f.position, f.velocity, f.load, f.current),
            (2048, -100, -500, -300)
        );
        assert_eq!((f.voltage, f.temperature, f.moving), (121, 41, true));
        assert!(f.status.overload());
        assert!(FeedbackBlock::parse(&b[..14]).is_none());
    }

    #[test]
    fn model_numbers_round_trip() {
        for m in [
            ServoModel::Sts3215,
            ServoModel::Sts3250,
            ServoModel::Sts3095,
        ] {
            assert_eq!(ServoModel::from_model_number(m.model_number()), Some(m));
        }
        assert_eq!(GOAL_POSITION.decode(&[0x01, 0x80]), Some(-1));
        assert_eq!(HOMING_OFFSET.decode(&[0xFF, 0x0F]), Some(-2047));
    }
}
