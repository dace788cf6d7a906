//! A new servo set up for a joint on the simulated left arm over an in-memory line: found alone
//! or at the factory's id, given the joint's id, rate and EEPROM; every refusal leaves the
//! servos as they were.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use bus_driver::LoadedConfig;
use commission::setup::{set_up, Report, SetupError, Target};
use common::{left_arm, plan};
use feetech::registers as reg;
use sim::{RobotDescription, SimBus};
use std::cell::RefCell;
use telemetry::config::ProcessConfig;

fn target(joint: &str) -> Target {
    let loaded = LoadedConfig::embedded().unwrap();
    let bus = loaded.config.bus("left_arm").unwrap();
    Target::of(&loaded, bus, joint).unwrap()
}

/// The elbow's servo replaced by a factory-fresh one; `alone`: every other servo unpowered.
fn fresh_elbow(alone: bool) -> SimBus {
    let mut bus = left_arm();
    assert!(bus.fit_fresh_servo(&RobotDescription::nori_a3(), "left_elbow", 180.0));
    if alone {
        for s in &mut bus.servos {
            // The fresh one is the one with its horn off the joint's zero.
            s.answering = s.horn_steps != 0.0;
        }
    }
    bus
}

fn run(bus: SimBus, joint: &str) -> (RefCell<SimBus>, Result<Report, SetupError>) {
    let line = RefCell::new(bus);
    let result = set_up(common::line(&line), &target(joint), &plan());
    (line, result)
}

/// Every servo's EEPROM flash writes (a refused setup writes none).
fn flash_writes(bus: &SimBus) -> u64 {
    bus.servos.iter().map(|s| s.log.eeprom_writes).sum()
}

#[test]
fn a_fresh_servo_alone_becomes_the_elbow_and_keeps_it_across_a_power_cycle() {
    let (line, result) = run(fresh_elbow(true), "left_elbow");
    let report = result.unwrap();
    assert_eq!((report.found.id, report.found.baud), (1, 1_000_000));
    let now = report.now.settings.unwrap();
    assert_eq!(now.return_delay_us, 0);
    assert_eq!(now.max_temperature_c, 60);
    assert_eq!(now.lock, 1);
    assert_eq!(
        now.position_limits,
        (0, 4095),
        "the calibration sets the limits"
    );
    let mut bus = line.into_inner();
    let elbow = bus.servos.iter_mut().find(|s| s.horn_steps != 0.0).unwrap();
    elbow.reboot();
    assert_eq!(elbow.id, 4, "written with the EEPROM unlocked");
    assert_eq!(elbow.get(reg::RETURN_DELAY_TIME), 0);
    assert_eq!(elbow.get(reg::TORQUE_ENABLE), 0, "never turned on");
}

#[test]
fn a_fresh_servo_among_servos_using_id_1_is_refused_and_nothing_is_written() {
    let (line, result) = run(fresh_elbow(false), "left_elbow");
    match result {
        Err(SetupError::NotAlone {
            id: 1,
            baud: 1_000_000,
        }) => {}
        other => panic!("{other:?}"),
    }
    assert_eq!(flash_writes(&line.borrow()), 0);
    assert_eq!(line.borrow().servos.iter().filter(|s| s.id == 1).count(), 2);
}

#[test]
fn a_fresh_servo_for_the_joint_at_id_1_is_set_up_in_place() {
    let mut bus = left_arm();
    assert!(bus.fit_fresh_servo(&RobotDescription::nori_a3(), "left_shoulder_pitch", 90.0));
    for s in &mut bus.servos {
        s.answering = s.horn_steps != 0.0;
    }
    let (line, result) = run(bus, "left_shoulder_pitch");
    let report = result.unwrap();
    assert_eq!(report.found.id, 1);
    assert!(!report.written.iter().any(|w| w.register.name == "ID"));
    assert_eq!(line.borrow().servos[0].get(reg::MAX_TEMPERATURE_LIMIT), 60);
}

#[test]
fn the_joint_s_id_answering_with_a_set_up_servo_is_refused() {
    let mut bus = left_arm();
    let elbow = bus.servo_mut(4).unwrap();
    assert!(elbow.write(reg::MAX_TEMPERATURE_LIMIT.addr, &[60]));
    let (line, result) = run(bus, "left_elbow");
    let e = result.unwrap_err();
    assert!(matches!(e, SetupError::IdTaken { id: 4, .. }), "{e:?}");
    assert!(e.to_string().contains("an sts3095"), "{e}");
    assert_eq!(flash_writes(&line.borrow()), 0);
}

#[test]
fn the_wrong_model_for_the_joint_is_refused_and_nothing_is_written() {
    let mut bus = fresh_elbow(true);
    let d = RobotDescription::nori_a3();
    let r = d.rating("sts3215").unwrap();
    let at = bus.servos.iter().position(|s| s.answering).unwrap();
    bus.servos[at] = sim::servo::Servo::new(1, r.model, r, 0.0, 25.0);
    let (line, result) = run(bus, "left_elbow");
    let e = result.unwrap_err();
    assert!(
        e.to_string()
            .contains("an sts3215 where left_elbow needs an sts3095"),
        "{e}"
    );
    assert_eq!(flash_writes(&line.borrow()), 0);
}

#[test]
fn another_joint_s_servo_connected_alone_is_not_renumbered() {
    let mut bus = left_arm();
    for s in &mut bus.servos {
        s.answering = s.id == 2;
    }
    // The shoulder roll's servo, set up by the driver: its backstop at 60 °C.
    let roll = bus.servo_mut(2).unwrap();
    assert!(roll.write(reg::LOCK.addr, &[0]));
    assert!(roll.write(reg::MAX_TEMPERATURE_LIMIT.addr, &[60]));
    let flashed = roll.log.eeprom_writes;
    let (line, result) = run(bus, "left_elbow");
    let e = result.unwrap_err();
    assert!(
        matches!(&e, SetupError::OtherJoint { id: 2, other } if other == "left_shoulder_roll"),
        "{e:?}"
    );
    assert_eq!(flash_writes(&line.borrow()), flashed);
}

#[test]
fn a_used_servo_alone_at_another_rate_is_found_and_brought_to_the_bus_s_rate() {
    let mut bus = fresh_elbow(true);
    let at = bus.servos.iter().position(|s| s.answering).unwrap();
    assert!(bus.servos[at].write(reg::LOCK.addr, &[0]));
    assert!(bus.servos[at].write(reg::ID.addr, &[9]));
    assert!(bus.servos[at].write(reg::BAUD_RATE.addr, &[6]));
    let (line, result) = run(bus, "left_elbow");
    let report = result.unwrap();
    assert_eq!((report.found.id, report.found.baud), (9, 57_600));
    let servo = &line.borrow().servos[at];
    assert_eq!((servo.id, servo.line_baud()), (4, Some(1_000_000)));
}
