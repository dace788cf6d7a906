//! The EEPROM settings each servo must hold, and the read-compare-write plan that writes only
//! what differs, so a normal boot wears no flash.

use crate::calibration::JointCalibration;
use crate::config::{Backstops, Mode};
use feetech::registers::{self as reg, Register};
use feetech::AMPS_PER_CURRENT_UNIT;

/// Protections the firmware must keep enabled: over-temperature, over-current and overload.
pub const UNLOADING_CONDITION: i32 = 0x2C;

/// The firmware's overload protection as the servo leaves the factory: more than
/// `Overload_Torque` (80 % of full output) for `Protection_Time` (2 s), then at most
/// `Protective_Torque` (20 %). A backstop behind the supervisor's stall rule. A calibration
/// session narrows it in RAM while it sweeps (`commission::automatic`); a driver starting after
/// a session that was killed puts it back.
pub const OVERLOAD_PROTECTION: [(Register, i32); 3] = [
    (reg::OVERLOAD_TORQUE, 80),
    (reg::PROTECTION_TIME, 200),
    (reg::PROTECTIVE_TORQUE, 20),
];

/// One EEPROM register and the value it must hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Setting {
    /// The register.
    pub register: Register,
    /// The value (decoded units of the register).
    pub value: i32,
}

/// The protection EEPROM a servo must hold for this joint (the driver writes what differs).
pub fn desired(backstops: &Backstops, mode: Mode) -> Vec<Setting> {
    let s = |register: Register, value: i32| Setting { register, value };
    vec![
        // Replies without the factory 500 µs delay: the cycle budget is wire time.
        s(reg::RETURN_DELAY_TIME, 0),
        s(reg::OPERATING_MODE, if mode == Mode::Speed { 1 } else { 0 }),
        s(
            reg::MAX_TEMPERATURE_LIMIT,
            i32::from(backstops.max_temperature_c),
        ),
        s(
            reg::PROTECTION_CURRENT,
            (backstops.protection_current_a / AMPS_PER_CURRENT_UNIT).round() as i32,
        ),
        s(
            reg::OVER_CURRENT_PROTECTION_TIME,
            (backstops.over_current_protection_time_ms / 10) as i32,
        ),
        s(reg::MAX_TORQUE_LIMIT, max_torque_permille(backstops)),
        s(reg::UNLOADING_CONDITION, UNLOADING_CONDITION),
    ]
    .into_iter()
    .chain(OVERLOAD_PROTECTION.map(|(register, value)| s(register, value)))
    .collect()
}

/// The EEPROM a calibrated servo holds for its joint: the homing offset and the firmware's own
/// goal limits (a second clamp behind the bus layer's). The calibration writes them; the driver
/// only checks them, so a servo nobody calibrated for this joint (a replaced one, a refitted
/// horn) is refused, not quietly given a range that is not its joint's.
pub fn calibration_settings(cal: &JointCalibration) -> [Setting; 3] {
    [
        Setting {
            register: reg::HOMING_OFFSET,
            value: cal.homing_offset,
        },
        Setting {
            register: reg::MIN_POSITION_LIMIT,
            value: cal.range_min,
        },
        Setting {
            register: reg::MAX_POSITION_LIMIT,
            value: cal.range_max,
        },
    ]
}

/// `Max_Torque_Limit` (and the volatile `Torque_Limit`) in 0.1 % units.
pub fn max_torque_permille(backstops: &Backstops) -> i32 {
    (backstops.max_torque_limit_percent * 10.0).round() as i32
}

/// The settings whose current value differs from the desired one.
pub fn plan(desired: &[Setting], current: &[Option<i32>]) -> Vec<Setting> {
    desired
        .iter()
        .zip(current)
        .filter(|(d, c)| **c != Some(d.value))
        .map(|(d, _)| *d)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const B: Backstops = Backstops {
        protection_current_a: 2.0,
        over_current_protection_time_ms: 1000,
        max_torque_limit_percent: 80.0,
        max_temperature_c: 60,
    };

    #[test]
    fn backstops_in_register_units() {
        let d = desired(&B, Mode::Position);
        let get = |r: Register| d.iter().find(|s| s.register == r).unwrap().value;
        assert_eq!(get(reg::MAX_TEMPERATURE_LIMIT), 60);
        assert_eq!(get(reg::PROTECTION_CURRENT), 308); // 2.0 A / 6.5 mA
        assert_eq!(get(reg::OVER_CURRENT_PROTECTION_TIME), 100); // 10 ms units
        assert_eq!(get(reg::MAX_TORQUE_LIMIT), 800);
        assert_eq!(get(reg::OVERLOAD_TORQUE), 80);
        assert_eq!(get(reg::PROTECTION_TIME), 200); // 10 ms units
        assert_eq!(get(reg::PROTECTIVE_TORQUE), 20);
    }

    #[test]
    fn only_differences_are_written() {
        let d = desired(&B, Mode::Position);
        let same: Vec<Option<i32>> = d.iter().map(|s| Some(s.value)).collect();
        assert!(
            plan(&d, &same).is_empty(),
            "a configured servo needs no write"
        );
        let mut one_off = same.clone();
        one_off[2] = Some(70);
        assert_eq!(plan(&d, &one_off), vec![d[2]]);
        // An unreadable register is written (it cannot be shown to hold the value).
        let mut unread = same;
        unread[0] = None;
        assert_eq!(plan(&d, &unread).len(), 1);
    }
}
