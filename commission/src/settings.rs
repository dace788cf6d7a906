//! The control table a servo answered to one READ of addresses 0–70, decoded: its identity
//! (model, firmware) and the EEPROM settings the stack relies on.

use feetech::registers::{self as reg, Register};
use feetech::ServoModel;
use serde::Serialize;

/// Addresses read in one go: the whole table through the feedback block (0–70). The feedback
/// part makes two servos at one id differ (their positions do), so they garble each other.
pub const TABLE_READ: (u8, u8) = (0, 71);

/// What one servo's control table says.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Settings {
    /// `Model_Number`.
    pub model_number: u16,
    /// `Firmware_Major`, `Firmware_Minor`.
    pub firmware: (u8, u8),
    /// `Baud_Rate` code.
    pub baud_code: u8,
    /// `Return_Delay_Time`, µs.
    pub return_delay_us: u16,
    /// `Min_Position_Limit`, `Max_Position_Limit`, steps.
    pub position_limits: (u16, u16),
    /// `Max_Temperature_Limit`, °C.
    pub max_temperature_c: u8,
    /// `Max_Torque_Limit`, 0.1 %.
    pub max_torque_permille: u16,
    /// `Protection_Current`, raw (6.5 mA).
    pub protection_current: u16,
    /// `Over_Current_Protection_Time`, raw (10 ms).
    pub over_current_time: u8,
    /// `Unloading_Condition` bits.
    pub unloading_condition: u8,
    /// `Overload_Torque`, `Protection_Time` (10 ms), `Protective_Torque`: the firmware's
    /// overload protection.
    pub overload: (u8, u8, u8),
    /// `Homing_Offset`, steps.
    pub homing_offset: i16,
    /// `Operating_Mode`.
    pub operating_mode: u8,
    /// `Lock` (1: EEPROM writes are not kept).
    pub lock: u8,
    /// `Torque_Enable`.
    pub torque_enable: u8,
    /// `Present_Position`, steps.
    pub present_position: i32,
}

impl Settings {
    /// Decodes the data of a READ of [`TABLE_READ`]; `None` if it is short.
    pub fn parse(table: &[u8]) -> Option<Settings> {
        if table.len() < usize::from(TABLE_READ.1) {
            return None;
        }
        let get = |r: Register| {
            let at = usize::from(r.addr);
            r.decode(&table[at..at + usize::from(r.size)]).unwrap_or(0)
        };
        Some(Settings {
            model_number: get(reg::MODEL_NUMBER) as u16,
            firmware: (
                get(reg::FIRMWARE_MAJOR) as u8,
                get(reg::FIRMWARE_MINOR) as u8,
            ),
            baud_code: get(reg::BAUD_RATE) as u8,
            return_delay_us: get(reg::RETURN_DELAY_TIME) as u16 * 2,
            position_limits: (
                get(reg::MIN_POSITION_LIMIT) as u16,
                get(reg::MAX_POSITION_LIMIT) as u16,
            ),
            max_temperature_c: get(reg::MAX_TEMPERATURE_LIMIT) as u8,
            max_torque_permille: get(reg::MAX_TORQUE_LIMIT) as u16,
            protection_current: get(reg::PROTECTION_CURRENT) as u16,
            over_current_time: get(reg::OVER_CURRENT_PROTECTION_TIME) as u8,
            unloading_condition: get(reg::UNLOADING_CONDITION) as u8,
            overload: (
                get(reg::OVERLOAD_TORQUE) as u8,
                get(reg::PROTECTION_TIME) as u8,
                get(reg::PROTECTIVE_TORQUE) as u8,
            ),
            homing_offset: get(reg::HOMING_OFFSET) as i16,
            operating_mode: get(reg::OPERATING_MODE) as u8,
            lock: get(reg::LOCK) as u8,
            torque_enable: get(reg::TORQUE_ENABLE) as u8,
            present_position: get(reg::PRESENT_POSITION),
        })
    }

    /// Whether this stack set it up: it holds the temperature backstop the stack writes, at
    /// most the hardware ceiling (a servo leaves the factory above it, at 70 or 80 °C).
    pub fn set_up_here(&self) -> bool {
        self.max_temperature_c <= bus_driver::config::HARDWARE_TEMPERATURE_CEILING_C
    }

    /// The model, if the stack knows its number.
    pub fn model(&self) -> Option<ServoModel> {
        ServoModel::from_model_number(self.model_number)
    }

    /// The value of a register the driver writes at start, for comparing with what it wants.
    pub fn value_of(&self, r: Register) -> Option<i32> {
        let v = match r.addr {
            a if a == reg::RETURN_DELAY_TIME.addr => i32::from(self.return_delay_us / 2),
            a if a == reg::OPERATING_MODE.addr => i32::from(self.operating_mode),
            a if a == reg::MAX_TEMPERATURE_LIMIT.addr => i32::from(self.max_temperature_c),
            a if a == reg::PROTECTION_CURRENT.addr => i32::from(self.protection_current),
            a if a == reg::OVER_CURRENT_PROTECTION_TIME.addr => i32::from(self.over_current_time),
            a if a == reg::MAX_TORQUE_LIMIT.addr => i32::from(self.max_torque_permille),
            a if a == reg::UNLOADING_CONDITION.addr => i32::from(self.unloading_condition),
            a if a == reg::OVERLOAD_TORQUE.addr => i32::from(self.overload.0),
            a if a == reg::PROTECTION_TIME.addr => i32::from(self.overload.1),
            a if a == reg::PROTECTIVE_TORQUE.addr => i32::from(self.overload.2),
            a if a == reg::HOMING_OFFSET.addr => i32::from(self.homing_offset),
            a if a == reg::MIN_POSITION_LIMIT.addr => i32::from(self.position_limits.0),
            a if a == reg::MAX_POSITION_LIMIT.addr => i32::from(self.position_limits.1),
            _ => return None,
        };
        Some(v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_factory_servo_s_table_decodes() {
        let d = sim::RobotDescription::nori_a3();
        let r = d.rating("sts3095").unwrap();
        let mut s = sim::servo::Servo::new(7, r.model, r, 0.0, 25.0);
        let mut table = [0u8; 80];
        assert!(s.read(TABLE_READ.0, TABLE_READ.1, &mut table));
        let got = Settings::parse(&table[..71]).unwrap();
        assert_eq!(got.model(), Some(ServoModel::Sts3095));
        assert_eq!(got.firmware, (3, 10));
        assert_eq!(got.return_delay_us, 500);
        assert_eq!(got.position_limits, (0, 4095));
        assert_eq!(got.lock, 1);
        assert_eq!(got.overload, (80, 200, 20));
        assert_eq!(got.present_position, 2048);
        assert_eq!(got.value_of(reg::RETURN_DELAY_TIME), Some(250));
        assert!(Settings::parse(&table[..70]).is_none());
    }

    #[test]
    fn every_register_the_driver_writes_is_compared() {
        use bus_driver::config::{Backstops, Mode};
        let backstops = Backstops {
            protection_current_a: 2.0,
            over_current_protection_time_ms: 1000,
            max_torque_limit_percent: 80.0,
            max_temperature_c: 60,
        };
        let calibration: bus_driver::calibration::JointCalibration =
            toml::from_str("homing-offset = 12\nrange-min = 100\nrange-max = 4000").unwrap();
        let table = [0u8; 71];
        let settings = Settings::parse(&table).unwrap();
        for mode in [Mode::Position, Mode::Speed] {
            let calibrated = bus_driver::backstops::calibration_settings(&calibration);
            for want in bus_driver::backstops::desired(&backstops, mode)
                .into_iter()
                .chain(calibrated)
            {
                assert!(
                    settings.value_of(want.register).is_some(),
                    "{}",
                    want.register.name
                );
            }
        }
    }
}
