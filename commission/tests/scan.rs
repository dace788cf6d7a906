//! Scans of the simulated A3's left arm over an in-memory line (the simulator's servos, their
//! return delays, rates and collisions), judged against the embedded driver configuration.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use bus_driver::transport::{Transport, TransportError};
use bus_driver::LoadedConfig;
use commission::findings::{judge, Finding, SettingChange, Severity};
use commission::scan::{scan, BroadcastAnswer, BusScan, Duplicate, Plan};
use feetech::registers as reg;
use sim::{RobotDescription, SimBus};
use std::cell::RefCell;
use std::collections::VecDeque;
use std::time::Duration;
use telemetry::config::ProcessConfig;

/// The host's end of a simulated bus, opened at a rate.
struct Line<'a> {
    bus: &'a RefCell<SimBus>,
    inbox: VecDeque<u8>,
    baud: u32,
}

impl Transport for Line<'_> {
    fn baud(&self) -> u32 {
        self.baud
    }
    fn send(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        let mut bus = self.bus.borrow_mut();
        let t = bus.time();
        bus.receive(t, bytes);
        Ok(())
    }
    fn receive(&mut self, buf: &mut [u8], _timeout: Duration) -> Result<usize, TransportError> {
        while let Some(r) = self.bus.borrow_mut().pop_due(f64::MAX) {
            self.inbox.extend(r.bytes);
        }
        let n = buf.len().min(self.inbox.len());
        for (b, v) in buf.iter_mut().zip(self.inbox.drain(..n)) {
            *b = v;
        }
        Ok(n)
    }
    fn discard_input(&mut self) -> Result<(), TransportError> {
        self.inbox.clear();
        Ok(())
    }
}

fn left_arm() -> SimBus {
    let d = RobotDescription::nori_a3();
    SimBus::new(&d, d.bus("left_arm").unwrap())
}

/// Ids 0–12 at the bus's rate and at 57 600 baud (a whole scan is every id at eight rates;
/// the in-memory line makes these few enough for a unit test).
fn plan() -> Plan {
    Plan {
        ids: 0..=12,
        rates: vec![1_000_000, 57_600],
        window: Duration::from_micros(600),
        attempts: 3,
    }
}

fn run(bus: &mut SimBus) -> (BusScan, Vec<Finding>) {
    let line = RefCell::new(std::mem::replace(bus, left_arm()));
    let result = scan(
        |baud| {
            line.borrow_mut().set_host_baud(baud);
            Ok(Line {
                bus: &line,
                inbox: VecDeque::new(),
                baud,
            })
        },
        &plan(),
    );
    let found = result.unwrap();
    let loaded = LoadedConfig::embedded().unwrap();
    let config = loaded
        .config
        .bus
        .iter()
        .find(|b| b.name == "left_arm")
        .unwrap();
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
fn the_arm_as_built_has_no_fault_and_the_driver_s_settings_are_named() {
    let mut bus = left_arm();
    let (found, findings) = run(&mut bus);
    let ids: Vec<u8> = found.found().map(|f| f.id).collect();
    assert_eq!(ids, [1, 2, 3, 4, 5, 6, 7, 8]);
    assert!(found
        .found()
        .all(|f| f.settings.is_some() && f.duplicate.is_none()));
    assert!(faults(&findings).is_empty(), "{findings:#?}");
    // Factory EEPROM: the driver will set the return delay and its backstops.
    let elbow = findings.iter().find_map(|f| match f {
        Finding::Settings { joint, changes, .. } if joint == "left_elbow" => Some(changes),
        _ => None,
    });
    let delay = SettingChange {
        register: "Return_Delay_Time",
        found: 250,
        driver_writes: 0,
    };
    assert!(elbow.unwrap().contains(&delay), "{findings:#?}");
    // Eight servos answering a broadcast PING together: not one intact answer.
    match &found.rates[0].broadcast {
        BroadcastAnswer::Several { ids, damaged } => assert!(ids.is_empty() && *damaged > 0),
        other => panic!("{other:?}"),
    }
    assert_eq!(found.rates[1].broadcast, BroadcastAnswer::Silent);
}

#[test]
fn a_servo_at_another_rate_is_named_and_not_missing() {
    let mut bus = left_arm();
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
    let mut bus = left_arm();
    // The elbow's servo replaced by a fresh one: id 1, the factory's return delay (as id 1's,
    // which has not been set up either), so both answer at once; its horn on another tooth.
    let d = RobotDescription::nori_a3();
    assert!(bus.fit_fresh_servo(&d, "left_elbow", 180.0));
    let (found, findings) = run(&mut bus);
    let at_1 = found.found().find(|f| f.id == 1).unwrap();
    assert_eq!(at_1.duplicate, Some(Duplicate::Garbled { attempts: 3 }));
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
    let mut bus = left_arm();
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
    let mut bus = left_arm();
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
