//! Scans of the simulated A3's left arm over an in-memory line (the simulator's servos, their
//! return delays, rates and collisions), judged against the embedded driver configuration.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{as_set_up_by_the_driver, left_arm, plan};

use bus_driver::LoadedConfig;
use commission::findings::{judge, Finding, SettingChange, Severity};
use commission::scan::{scan, BroadcastAnswer, BusScan, Duplicate};
use feetech::registers as reg;
use sim::{RobotDescription, SimBus};
use std::cell::RefCell;
use telemetry::config::ProcessConfig;

fn run(bus: &mut SimBus) -> (BusScan, Vec<Finding>) {
    let line = RefCell::new(std::mem::replace(bus, left_arm()));
    let result = scan(common::line(&line), &plan());
    let found = result.unwrap();
    let loaded = LoadedConfig::embedded().unwrap();
    let config = loaded.config.bus("left_arm").unwrap();
    let findings = judge(&loaded, config, &found);
    (found, findings)
}

fn faults(findings: &[Finding]) -> Vec<&Finding> {
    findings
        .iter()
        .filter(|f| f.severity() == Severity::Fault)
        .collect()
}

fn write(bus: &mut SimBus, id: u8, r: reg::Register, value: u8) {
    let s = bus.servo_mut(id).unwrap();
    assert!(s.write(r.addr, &[value]));
}

#[test]
fn the_arm_as_the_driver_set_it_up_has_no_fault_and_no_change_to_make() {
    let mut bus = as_set_up_by_the_driver(left_arm());
    let (found, findings) = run(&mut bus);
    let ids: Vec<u8> = found.found().map(|f| f.id).collect();
    assert_eq!(ids, [1, 2, 3, 4, 5, 6, 7, 8]);
    assert!(found
        .found()
        .all(|f| f.settings.is_some() && f.duplicate.is_none()));
    assert!(findings.is_empty(), "{findings:#?}");
    // Eight servos answering a broadcast PING together: not one intact answer; at another
    // rate nothing answers, so its ids are not swept.
    match &found.rates[0].broadcast {
        BroadcastAnswer::Several { ids, damaged } => assert!(ids.is_empty() && *damaged > 0),
        other => panic!("{other:?}"),
    }
    assert_eq!(found.rates[1].broadcast, BroadcastAnswer::Silent);
}

/// On a robot being calibrated bus by bus, a joint with no calibration yet is named, with the
/// tool that calibrates it; one calibrated is judged as ever.
#[test]
fn a_joint_with_no_calibration_yet_is_named() {
    let bus = as_set_up_by_the_driver(left_arm());
    let line = RefCell::new(bus);
    let found = scan(common::line(&line), &plan()).unwrap();
    let mut loaded = LoadedConfig::embedded().unwrap();
    loaded.calibration.joint.remove("left_elbow");
    let config = loaded.config.bus("left_arm").unwrap();
    let findings = judge(&loaded, config, &found);
    assert_eq!(
        findings,
        [Finding::Uncalibrated {
            joint: "left_elbow".into(),
            id: 4
        }]
    );
    assert!(findings[0].to_string().contains("nori calibrate by-hand"));
}

#[test]
fn servos_never_set_up_are_each_a_fault_and_the_driver_s_changes_named_once_set_up() {
    let mut bus = left_arm();
    let (_, findings) = run(&mut bus);
    let not_set_up = findings
        .iter()
        .filter(|f| {
            matches!(
                f,
                Finding::NotSetUp {
                    max_temperature_c: 70,
                    ..
                }
            )
        })
        .count();
    assert_eq!(not_set_up, 8, "{findings:#?}");
    // Set up, with the return delay back at the factory's: that is a change the driver makes.
    let mut bus = as_set_up_by_the_driver(left_arm());
    write(&mut bus, 4, reg::LOCK, 0);
    write(&mut bus, 4, reg::RETURN_DELAY_TIME, 250);
    let (_, findings) = run(&mut bus);
    let delay = SettingChange {
        register: "Return_Delay_Time",
        found: 250,
        driver_writes: 0,
    };
    assert_eq!(
        findings,
        [Finding::Settings {
            joint: "left_elbow".into(),
            id: 4,
            changes: vec![delay]
        }]
    );
}

#[test]
fn a_servo_at_another_rate_is_named_and_not_missing() {
    let mut bus = as_set_up_by_the_driver(left_arm());
    write(&mut bus, 4, reg::LOCK, 0);
    write(&mut bus, 4, reg::BAUD_RATE, 6);
    let (_, findings) = run(&mut bus);
    assert_eq!(
        faults(&findings),
        [&Finding::WrongRate {
            joint: Some("left_elbow".into()),
            id: 4,
            baud: 57_600,
            bus_baud: 1_000_000
        }]
    );
}

#[test]
fn a_factory_fresh_servo_in_a_joint_s_place_is_a_duplicate_at_id_1_and_the_joint_is_missing() {
    // The elbow's servo replaced by a fresh one: id 1, the factory's return delay, its horn on
    // another tooth. Beside a set-up shoulder (return delay 0) both answer a PING, one after
    // the other; beside one never set up, at once.
    let d = RobotDescription::nori_a3();
    let mut bus = as_set_up_by_the_driver(left_arm());
    assert!(bus.fit_fresh_servo(&d, "left_elbow", 180.0));
    let (found, _) = run(&mut bus);
    let at_1 = found.found().find(|f| f.id == 1).unwrap();
    assert_eq!(
        at_1.duplicate,
        Some(Duplicate::AnsweredTwice { answers: 2 })
    );
    let mut bus = left_arm();
    assert!(bus.fit_fresh_servo(&d, "left_elbow", 180.0));
    let (found, findings) = run(&mut bus);
    let at_1 = found.found().find(|f| f.id == 1).unwrap();
    assert_eq!(
        at_1.duplicate,
        Some(Duplicate::Garbled {
            garbled: 3,
            attempts: 3
        })
    );
    let faults = faults(&findings);
    assert!(
        faults.contains(&&Finding::Missing {
            joint: "left_elbow".into(),
            id: 4
        }),
        "{faults:#?}"
    );
    assert!(
        faults
            .iter()
            .any(|f| matches!(f, Finding::Duplicated { id: 1, .. })),
        "{faults:#?}"
    );
}

#[test]
fn a_duplicate_with_another_return_delay_answers_twice() {
    let mut bus = left_arm();
    write(&mut bus, 1, reg::RETURN_DELAY_TIME, 0);
    write(&mut bus, 4, reg::ID, 1);
    let (found, _) = run(&mut bus);
    let at_1 = found.found().find(|f| f.id == 1).unwrap();
    assert_eq!(
        at_1.duplicate,
        Some(Duplicate::AnsweredTwice { answers: 2 })
    );
}

#[test]
fn the_wrong_model_at_a_joint_is_named() {
    let mut bus = as_set_up_by_the_driver(left_arm());
    // An STS3215 where the configuration says STS3095 (the elbow).
    let d = RobotDescription::nori_a3();
    let r = d.rating("sts3215").unwrap();
    let at = bus.servos.iter().position(|s| s.id == 4).unwrap();
    bus.servos[at] = sim::servo::Servo::new(4, r.model, r, 0.0, 25.0);
    let (_, findings) = run(&mut bus);
    assert_eq!(
        faults(&findings),
        [&Finding::WrongModel {
            joint: "left_elbow".into(),
            id: 4,
            expected: "sts3095",
            model_number: 777
        }]
    );
    assert!(faults(&findings)[0]
        .to_string()
        .contains("sts3215 where the configuration says sts3095"));
}

#[test]
fn a_servo_alone_answers_the_broadcast_ping() {
    let mut bus = as_set_up_by_the_driver(left_arm());
    for s in &mut bus.servos {
        s.answering = s.id == 6;
    }
    let (found, findings) = run(&mut bus);
    assert_eq!(found.rates[0].broadcast, BroadcastAnswer::One { id: 6 });
    assert_eq!(
        faults(&findings).len(),
        7,
        "the seven others are missing: {findings:#?}"
    );
}

#[test]
fn a_servo_only_the_broadcast_hears_is_named() {
    // Alone, at an id the sweep does not reach in this plan (ids 0-12).
    let mut bus = as_set_up_by_the_driver(left_arm());
    for s in &mut bus.servos {
        s.answering = s.id == 7;
    }
    write(&mut bus, 7, reg::LOCK, 0);
    write(&mut bus, 7, reg::ID, 40);
    let (_, findings) = run(&mut bus);
    assert!(
        findings.contains(&Finding::HeardOnlyByBroadcast {
            id: 40,
            baud: 1_000_000
        }),
        "{findings:#?}"
    );
}
