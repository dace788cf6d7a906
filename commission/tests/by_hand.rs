//! Calibration by hand on the simulated left arm, in memory: every servo's horn on another
//! tooth (seeded), an operator's hand sweeping each joint from stop to stop through the arm's
//! own mechanics (gravity, the stops' give), and the calibration chosen from the readings:
//! each joint then reads where the simulator has it within 2°.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use bus_driver::bus::Bus;
use commission::by_hand::ByHand;
use commission::calibrate::Refusal;
use commission::calibrate::{LIMIT_MARGIN_RAD, TRAVEL_TOLERANCE_RAD};
use commission::session::SessionError;
use common::{left_arm, line, targets};
use feetech::registers as reg;
use sim::rng::Rng;
use sim::{RobotDescription, SimBus};
use std::cell::RefCell;
use std::time::Duration;

/// The arm with each horn `horn(id)` steps off, its hand on.
fn assembled(robot: &RobotDescription, mut horn: impl FnMut(u8) -> f64) -> RefCell<SimBus> {
    let mut sim = left_arm();
    for id in 1..=8 {
        sim.servo_mut(id).unwrap().fit_horn(horn(id));
    }
    assert!(sim.put_hand_on(robot));
    RefCell::new(sim)
}

/// Reads every joint at 50 Hz until the hand is done (at most `within_s` of simulated time).
fn sweep(bus: &RefCell<SimBus>, session: &mut ByHand<common::Line<'_>>, within_s: f64) {
    let mut t = bus.borrow().time();
    let end = t + within_s;
    while bus.borrow().hand_done() != Some(true) && t < end {
        t += 0.02;
        bus.borrow_mut().advance_to(t, 0.001);
        session.read().unwrap();
    }
}

#[test]
fn each_joint_reads_where_it_is_within_two_degrees_over_seeds() {
    let robot = RobotDescription::nori_a3();
    let mut worst: f64 = 0.0;
    for seed in 1..=3 {
        let mut rng = Rng::new(seed);
        let bus = assembled(&robot, |_| rng.range(-400.0, 400.0));
        let mut session = ByHand::start(
            Bus::new(line(&bus), Duration::from_micros(600)),
            targets(&robot),
        )
        .unwrap();
        sweep(&bus, &mut session, 200.0);
        assert_eq!(bus.borrow().hand_done(), Some(true));
        let progress = session.progress(0.02);
        assert!(progress.iter().all(|p| p.covered), "{progress:#?}");
        let chosen = session
            .finish(LIMIT_MARGIN_RAD, TRAVEL_TOLERANCE_RAD)
            .unwrap();
        assert_eq!(chosen.len(), 8);
        // Written to flash, not only to the registers: a power cycle keeps it.
        for id in 1..=8 {
            bus.borrow_mut().servo_mut(id).unwrap().reboot();
        }
        for (target, c) in targets(&robot).iter().zip(&chosen) {
            let (joint, cal) = (&c.joint, &c.calibration);
            assert_eq!(&target.joint, joint);
            assert_eq!(c.firmware, "3.10");
            cal.validate(joint).unwrap();
            let mut b = bus.borrow_mut();
            let servo = b.servo_mut(target.id).unwrap();
            let (lo, hi) = cal.range_rad();
            for q in [lo, 0.5 * (lo + hi), hi] {
                servo.angle = q;
                let mut raw = [0u8; 2];
                assert!(servo.read(reg::PRESENT_POSITION.addr, 2, &mut raw));
                let read = cal.to_rad(i32::from(u16::from_le_bytes(raw)));
                let off = (read - q).abs().to_degrees();
                worst = worst.max(off);
                assert!(off < 2.0, "seed {seed}: {joint} at {q} reads {read}");
            }
        }
    }
    eprintln!("by hand, 3 seeds: the worst joint reads {worst:.2}° off");
}

/// Something in the way of the elbow (an upper stop 30° early): refused, naming the joint, and
/// every servo given back the homing offset and limits it held.
#[test]
fn a_joint_blocked_short_of_its_stop_is_refused_and_nothing_is_written() {
    let mut robot = RobotDescription::nori_a3();
    // The hand (and the arm's mechanics) meet the obstacle; the description does not know it.
    let expected = targets(&robot);
    let d = robot.bus.iter_mut().find(|b| b.name == "left_arm").unwrap();
    let elbow = d.arm.as_mut().unwrap().joint.get_mut(3).unwrap();
    elbow.upper_rad -= 0.52;
    let held = |s: &mut sim::servo::Servo| {
        [
            s.get(reg::HOMING_OFFSET),
            s.get(reg::MIN_POSITION_LIMIT),
            s.get(reg::MAX_POSITION_LIMIT),
        ]
    };
    let bus = {
        let mut sim = SimBus::new(&robot, robot.bus("left_arm").unwrap());
        // Calibrated before (offsets 30 to 240 steps): what must be given back.
        for id in 1..=8 {
            let s = sim.servo_mut(id).unwrap();
            s.fit_horn(f64::from(id) * 30.0);
            let offset = u16::from(id) * 30;
            assert!(s.write(reg::LOCK.addr, &[0]));
            assert!(s.write(reg::HOMING_OFFSET.addr, &offset.to_le_bytes()));
            assert!(s.write(reg::LOCK.addr, &[1]));
        }
        assert!(sim.put_hand_on(&robot));
        RefCell::new(sim)
    };
    let before: Vec<[i32; 3]> = (1..=8)
        .map(|id| held(bus.borrow_mut().servo_mut(id).unwrap()))
        .collect();
    let mut session =
        ByHand::start(Bus::new(line(&bus), Duration::from_micros(600)), expected).unwrap();
    sweep(&bus, &mut session, 200.0);
    let e = session
        .finish(LIMIT_MARGIN_RAD, TRAVEL_TOLERANCE_RAD)
        .unwrap_err();
    let SessionError::Refused(refusals) = &e else {
        panic!("{e}")
    };
    assert_eq!(refusals.len(), 1, "{e}");
    assert!(
        matches!(&refusals[0], Refusal::NotCovered { joint, .. } if joint == "left_elbow"),
        "{e}"
    );
    let mut b = bus.borrow_mut();
    for (id, was) in (1..=8).zip(&before) {
        assert_eq!(&held(b.servo_mut(id).unwrap()), was, "servo {id}");
    }
}

/// The arm calibrated before (offsets 30 to 240 steps), as found by a session.
fn calibrated_before(bus: &RefCell<SimBus>) -> Vec<[i32; 3]> {
    let mut b = bus.borrow_mut();
    (1..=8u8)
        .map(|id| {
            let s = b.servo_mut(id).unwrap();
            let offset = u16::from(id) * 30;
            assert!(s.write(reg::LOCK.addr, &[0]));
            assert!(s.write(reg::HOMING_OFFSET.addr, &offset.to_le_bytes()));
            assert!(s.write(reg::LOCK.addr, &[1]));
            [
                s.get(reg::HOMING_OFFSET),
                s.get(reg::MIN_POSITION_LIMIT),
                s.get(reg::MAX_POSITION_LIMIT),
            ]
        })
        .collect()
}

fn offsets(bus: &RefCell<SimBus>) -> Vec<i32> {
    let mut b = bus.borrow_mut();
    (1..=8)
        .map(|id| b.servo_mut(id).unwrap().get(reg::HOMING_OFFSET))
        .collect()
}

/// A session that cannot take every joint (a servo silent, or of the wrong model) gives the
/// ones it took back what they held: no offset left cleared.
#[test]
fn a_joint_that_cannot_be_taken_leaves_every_servo_as_found() {
    let robot = RobotDescription::nori_a3();
    let bus = RefCell::new(left_arm());
    let before: Vec<i32> = calibrated_before(&bus).iter().map(|v| v[0]).collect();
    bus.borrow_mut().servo_mut(5).unwrap().answering = false;
    let e = ByHand::start(
        Bus::new(line(&bus), Duration::from_micros(600)),
        targets(&robot),
    )
    .err()
    .unwrap();
    assert!(e.to_string().contains("left_forearm_roll"), "{e}");
    assert_eq!(offsets(&bus), before);
    bus.borrow_mut().servo_mut(5).unwrap().answering = true;
    // The configuration names another model for the elbow.
    let mut wrong = targets(&robot);
    wrong[3].model = feetech::ServoModel::Sts3215;
    let e = ByHand::start(Bus::new(line(&bus), Duration::from_micros(600)), wrong)
        .err()
        .unwrap();
    assert!(matches!(e, SessionError::WrongModel { .. }), "{e}");
    assert_eq!(offsets(&bus), before);
}
