//! The automatic calibration on the simulated left arm, in memory: every servo's horn on
//! another tooth (seeded), no hand: each joint driven into its stops by its own servo at the
//! plan's torque limit through the arm's own mechanics (gravity, the stops' give), the
//! calibration chosen and written. Each joint then reads where the simulator has it within 1°,
//! each limit sits the margin inside its real stop, and no motor pressed a stop harder than
//! its sweep's torque limit.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use bus_driver::bus::Bus;
use commission::automatic::{Activity, Automatic, Plan, Progress, Toward};
use commission::calibrate::Refusal;
use commission::session::{Calibrated, SessionError};
use common::{as_set_up_by_the_driver, left_arm, line, targets};
use feetech::registers as reg;
use sim::rng::Rng;
use sim::{RobotDescription, SimBus};
use std::cell::RefCell;
use std::time::Duration;

use commission::calibrate::LIMIT_MARGIN_RAD as MARGIN_RAD;
use commission::calibrate::TRAVEL_TOLERANCE_RAD as TOLERANCE_RAD;

fn plan(robot: &RobotDescription) -> Plan {
    Plan::of(
        robot.bus("left_arm").unwrap(),
        &targets(robot),
        MARGIN_RAD,
        TOLERANCE_RAD,
    )
    .unwrap()
}

/// The arm hanging (each joint at rest, its torque off), each servo set up as the driver
/// sets it up but not calibrated, each horn `horn(id)` steps off.
fn assembled(mut horn: impl FnMut(u8) -> f64) -> RefCell<SimBus> {
    let mut sim = as_set_up_by_the_driver(left_arm());
    for id in 1..=8 {
        let s = sim.servo_mut(id).unwrap();
        s.clear_calibration();
        s.fit_horn(horn(id));
    }
    RefCell::new(sim)
}

thread_local! {
    /// The lowest and highest angle each servo (ids 1–8) reached in the last `run`, rad.
    static EXTREMES: RefCell<Vec<(f64, f64)>> = const { RefCell::new(Vec::new()) };
}

thread_local! {
    /// The longest each servo's output stayed above its `Overload_Torque` in the last `run`,
    /// s, and what the session was doing then: the margin to the press bound's 1 s.
    static ABOVE_OVERLOAD: RefCell<Vec<(f64, f64, String)>> = const { RefCell::new(Vec::new()) };
}

/// Tracks, each tick, how long each servo's output has stayed above its `Overload_Torque`.
fn track_overload(bus: &RefCell<SimBus>, p: &Progress) {
    let mut b = bus.borrow_mut();
    ABOVE_OVERLOAD.with(|a| {
        let mut a = a.borrow_mut();
        a.resize(8, (0.0, 0.0, String::new()));
        for (id, x) in (1..=8).zip(a.iter_mut()) {
            let s = b.servo_mut(id).unwrap();
            let threshold = f64::from(s.get(reg::OVERLOAD_TORQUE)) / 100.0;
            x.0 = if s.duty.abs() > threshold {
                x.0 + 0.02
            } else {
                0.0
            };
            if x.0 > x.1 {
                (x.1, x.2) = (x.0, format!("{p:?}"));
            }
        }
    });
}

/// The lowest and highest angle servo `id` reached in the last `run`, rad.
fn extremes(id: u8) -> (f64, f64) {
    EXTREMES.with(|e| e.borrow()[usize::from(id) - 1])
}

/// Runs a session to its end and commits it, tracking each servo's extremes
/// ([`extremes`]) and checking that the rest of the arm holds where it hung while the gripper
/// is swept.
fn run(bus: &RefCell<SimBus>, plan: Plan) -> Result<Vec<Calibrated>, SessionError> {
    let angles = || -> Vec<f64> {
        (1..=8)
            .map(|id| bus.borrow_mut().servo_mut(id).unwrap().angle)
            .collect()
    };
    let hung = angles();
    EXTREMES.with(|e| *e.borrow_mut() = hung.iter().map(|&a| (a, a)).collect());
    ABOVE_OVERLOAD.with(|a| a.borrow_mut().clear());
    let (end, _) = session_until_end(bus, plan, |p, _, _, _| {
        track_overload(bus, p);
        let now = angles();
        EXTREMES.with(|e| {
            for (x, &a) in e.borrow_mut().iter_mut().zip(&now) {
                *x = (x.0.min(a), x.1.max(a));
            }
        });
        if let Progress::Working(0, _) = p {
            for (id, (was, at)) in (1..=7).zip(hung.iter().zip(&now)) {
                assert!(
                    (at - was).abs() < 0.05,
                    "servo {id} moved from {was} to {at} rad"
                );
            }
        }
        true
    });
    match end? {
        Progress::Done(calibrated) => Ok(calibrated),
        p => panic!("ended {p:?}"),
    }
}

/// Runs a session at 50 Hz to its end, `hook` called after each tick with what it said (and
/// after the commit with what was committed), the session dropped where it answers false;
/// the last progress (`Done` once committed) or the error, and the simulated time it took.
fn session_until_end(
    bus: &RefCell<SimBus>,
    plan: Plan,
    mut hook: impl FnMut(&Progress, f64, &mut Automatic<common::Line<'_>>, &RefCell<SimBus>) -> bool,
) -> (Result<Progress, SessionError>, f64) {
    let began = bus.borrow().time();
    let mut t = began;
    let line = Bus::new(line(bus), Duration::from_micros(600));
    let mut session = match Automatic::start(line, plan, t) {
        Ok(s) => s,
        Err(e) => return (Err(e), 0.0),
    };
    loop {
        t += 0.02;
        bus.borrow_mut().advance_to(t, 0.001);
        match session.tick(t) {
            Ok(Progress::Done(_)) => {
                let end = session.commit().map(Progress::Done);
                if let Ok(p) = &end {
                    hook(p, t, &mut session, bus);
                }
                return (end, t - began);
            }
            Ok(p) => {
                if !hook(&p, t, &mut session, bus) {
                    return (Ok(p), t - began);
                }
            }
            Err(e) => return (Err(e), t - began),
        }
        assert!(t < began + 900.0, "the session did not end");
    }
}

/// Where the servo reads the joint at `q` through `calibration`, rad.
fn read_at(
    bus: &RefCell<SimBus>,
    id: u8,
    q: f64,
    cal: &bus_driver::calibration::JointCalibration,
) -> f64 {
    let mut b = bus.borrow_mut();
    let servo = b.servo_mut(id).unwrap();
    let was = servo.angle;
    servo.angle = q;
    let mut raw = [0u8; 2];
    assert!(servo.read(reg::PRESENT_POSITION.addr, 2, &mut raw));
    servo.angle = was;
    cal.to_rad(i32::from(u16::from_le_bytes(raw)))
}

#[test]
fn each_zero_within_a_degree_and_no_stop_pressed_above_the_torque_limit_over_seeds() {
    let robot = RobotDescription::nori_a3();
    let plan = plan(&robot);
    let (mut worst_zero, mut hardest): (f64, u16) = (0.0, 0);
    let (mut least_inside, mut most_inside) = (f64::MAX, 0f64);
    let mut longest_above: f64 = 0.0;
    for seed in 1..=8 {
        let mut rng = Rng::new(seed);
        let bus = assembled(|_| rng.range(-400.0, 400.0));
        if seed == 1 {
            // The bicep as a session killed in its sweep left it: its own press bound in RAM.
            // Given that back, it would trip holding its pose while the roll sweeps.
            let mut b = bus.borrow_mut();
            let s = b.servo_mut(3).unwrap();
            for (r, v) in [
                (reg::OVERLOAD_TORQUE, 18),
                (reg::PROTECTION_TIME, 100),
                (reg::PROTECTIVE_TORQUE, 0),
            ] {
                assert!(s.write(r.addr, &[v]));
            }
        }
        let t0 = bus.borrow().time();
        let chosen = run(&bus, plan.clone()).unwrap();
        // The press bound (1 s) and the strain rule (0.5 s) are never near: a sweep reverses
        // at a stop within 0.16 s.
        let (above, doing) = ABOVE_OVERLOAD.with(|a| {
            let a = a.borrow();
            let (_, s, d) = a.iter().max_by(|x, y| x.1.total_cmp(&y.1)).unwrap();
            (*s, d.clone())
        });
        assert!(
            above < 0.25,
            "seed {seed}: above the overload threshold {above} s in {doing}"
        );
        longest_above = longest_above.max(above);
        assert_eq!(
            press_bounds(&bus),
            vec![[80, 200, 20, 0x2C]; 8],
            "seed {seed}: the overload protection not given back"
        );
        let took = bus.borrow().time() - t0;
        assert_eq!(chosen.len(), 8);
        for id in 1..=8 {
            // Written to flash, and every torque off at the end.
            let mut b = bus.borrow_mut();
            let s = b.servo_mut(id).unwrap();
            assert!(!s.torque_enabled(), "seed {seed}: servo {id} left driving");
            s.reboot();
        }
        for c in &chosen {
            let sweep = plan.sweeps.iter().find(|s| s.target.id == c.id).unwrap();
            let stops = sweep.target.stops;
            let cal = &c.calibration;
            cal.validate(&c.joint).unwrap();
            // The zero: where the joint reads at its true zero.
            let zero = read_at(&bus, c.id, 0.0, cal);
            worst_zero = worst_zero.max(zero.abs().to_degrees());
            assert!(
                zero.abs() < 1f64.to_radians(),
                "seed {seed}: {} reads {:.2}° at its zero",
                c.joint,
                zero.to_degrees()
            );
            // Each limit, where the joint truly is when it reads there, inside its stop.
            let (lo, hi) = cal.range_rad();
            let inside = [lo - zero - stops.lower_rad, stops.upper_rad - (hi - zero)];
            for d in inside.map(f64::to_degrees) {
                least_inside = least_inside.min(d);
                most_inside = most_inside.max(d);
                // Inside the stop less the zero's own error, and within the 2° of #40.
                assert!(
                    d > MARGIN_RAD.to_degrees() - 1.0 && d <= 2.0,
                    "seed {seed}: {} has a limit {d:.2}° inside its stop",
                    c.joint,
                );
            }
            let pressed = bus
                .borrow_mut()
                .servo_mut(c.id)
                .unwrap()
                .log
                .stop_press_max_permille;
            hardest = hardest.max(pressed);
            assert!(
                pressed <= sweep.torque_permille,
                "seed {seed}: {} pressed its stop at {pressed} ‰, its limit {} ‰",
                c.joint,
                sweep.torque_permille
            );
        }
        eprintln!("seed {seed}: calibrated in {took:.0} s of simulated time");
    }
    eprintln!(
        "automatic, 8 seeds: worst zero {worst_zero:.2}°, limits {least_inside:.2}–{most_inside:.2}° inside their stops, \
         hardest press {hardest} ‰, longest above the overload threshold {longest_above:.2} s"
    );
}

/// Each servo's homing offset and limits, in flash (as a power cycle gives them back).
fn held(bus: &RefCell<SimBus>) -> Vec<[i32; 3]> {
    let mut b = bus.borrow_mut();
    (1..=8)
        .map(|id| {
            let s = b.servo_mut(id).unwrap();
            let mut copy = s.clone();
            copy.reboot();
            [
                copy.get(reg::HOMING_OFFSET),
                copy.get(reg::MIN_POSITION_LIMIT),
                copy.get(reg::MAX_POSITION_LIMIT),
            ]
        })
        .collect()
}

/// Each servo's overload protection and `Unloading_Condition`, as its RAM holds them.
fn press_bounds(bus: &RefCell<SimBus>) -> Vec<[i32; 4]> {
    let mut b = bus.borrow_mut();
    (1..=8)
        .map(|id| {
            let s = b.servo_mut(id).unwrap();
            [
                reg::OVERLOAD_TORQUE,
                reg::PROTECTION_TIME,
                reg::PROTECTIVE_TORQUE,
                reg::UNLOADING_CONDITION,
            ]
            .map(|r| s.get(r))
        })
        .collect()
}

/// Runs a calibration that must be refused: the refusals, after checking that every servo was
/// given back what it held (in flash and in RAM) and left with its torque off.
fn refused(bus: &RefCell<SimBus>, plan: Plan) -> Vec<Refusal> {
    let before = held(bus);
    let limits: Vec<i32> = (1..=8)
        .map(|id| {
            bus.borrow_mut()
                .servo_mut(id)
                .unwrap()
                .get(reg::TORQUE_LIMIT)
        })
        .collect();
    let bounds = press_bounds(bus);
    let e = run(bus, plan).unwrap_err();
    let SessionError::Refused(refusals) = e else {
        panic!("{e}")
    };
    assert_eq!(held(bus), before);
    assert_eq!(
        press_bounds(bus),
        bounds,
        "the overload protection not given back"
    );
    let mut b = bus.borrow_mut();
    for id in 1..=8 {
        let s = b.servo_mut(id).unwrap();
        assert!(!s.torque_enabled(), "servo {id} left driving");
        assert_eq!(s.get(reg::OPERATING_MODE), 0, "servo {id}");
        assert_eq!(s.get(reg::HOMING_OFFSET), before[usize::from(id) - 1][0]);
        assert_eq!(
            s.get(reg::TORQUE_LIMIT),
            limits[usize::from(id) - 1],
            "servo {id}"
        );
    }
    refusals
}

/// The sim's left arm built with `change` made to its mechanics (the description the plan
/// reads does not know it), set up by the driver, calibrated before with its horns 30–240
/// steps off (what must be given back).
fn changed_arm(change: impl FnOnce(&mut sim::description::ArmDescription)) -> RefCell<SimBus> {
    let mut robot = RobotDescription::nori_a3();
    let d = robot.bus.iter_mut().find(|b| b.name == "left_arm").unwrap();
    change(d.arm.as_mut().unwrap());
    let mut sim = as_set_up_by_the_driver(SimBus::new(&robot, robot.bus("left_arm").unwrap()));
    for id in 1..=8 {
        sim.servo_mut(id).unwrap().fit_horn(f64::from(id) * 30.0);
    }
    RefCell::new(sim)
}

/// Something in the way of the elbow 30° before its upper stop: refused, naming the joint and
/// what to look for, and nothing written.
#[test]
fn a_joint_blocked_short_of_its_stop_is_refused_and_every_servo_left_as_found() {
    let robot = RobotDescription::nori_a3();
    let bus = changed_arm(|arm| arm.joint[3].upper_rad -= 0.52);
    // Hanging, it rests on the obstacle.
    bus.borrow_mut().advance_to(2.0, 0.001);
    let began = bus.borrow_mut().servo_mut(4).unwrap().angle;
    let refusals = refused(&bus, plan(&robot));
    assert!(
        matches!(&refusals[..], [Refusal::NotCovered { joint, .. }] if joint == "left_elbow"),
        "{refusals:?}"
    );
    assert!(refusals[0].to_string().contains("something is in its way"));
    // Driven back to where its sweep began before its torque went off.
    let angle = bus.borrow_mut().servo_mut(4).unwrap().angle;
    assert!(
        (angle - began).abs() < 0.1,
        "the elbow began at {began} rad, was left at {angle} rad"
    );
}

/// A wrist whose lower stop broke off (25° more travel): the sweep stops once the joint has
/// gone further than its travel, and is refused.
#[test]
fn a_joint_that_runs_past_its_travel_is_stopped_and_refused() {
    let robot = RobotDescription::nori_a3();
    // Broken 25° further, then gone.
    for broken in [0.45, 20.0] {
        let bus = changed_arm(|arm| arm.joint[5].lower_rad -= broken);
        let began = bus.borrow_mut().servo_mut(6).unwrap().angle;
        let refusals = refused(&bus, plan(&robot));
        assert!(
            matches!(&refusals[..], [Refusal::BeyondTravel { joint, .. }] if joint == "left_wrist_pitch"),
            "{refusals:?}"
        );
        let at = bus.borrow_mut().servo_mut(6).unwrap().angle;
        assert!(
            (at - began).abs() < 0.1,
            "broken {broken} rad: began at {began}, left at {at} rad"
        );
        // Stopped within its travel (3.6 rad) and the tolerance of where its drive began.
        let (lowest, _) = extremes(6);
        assert!(
            lowest > began - 3.6 - 0.05 - 0.05,
            "broken {broken} rad: began at {began}, went down to {lowest} rad"
        );
    }
}

/// A torque limit too low to lift the arm sideways: the shoulder's roll strains under gravity
/// short of its stop, pushing at its limit while it creeps. Refused after half a second as
/// straining and driven back, before its firmware's press bound would end the push; not taken
/// for a stop.
#[test]
fn a_stall_under_gravity_is_not_taken_for_a_stop() {
    let robot = RobotDescription::nori_a3();
    let mut plan = plan(&robot);
    let roll = plan
        .sweeps
        .iter_mut()
        .find(|s| s.target.joint == "left_shoulder_roll")
        .unwrap();
    roll.torque_permille = 100;
    let id = roll.target.id;
    let bus = changed_arm(|_| {});
    let refusals = refused(&bus, plan);
    assert!(
        matches!(&refusals[..], [Refusal::Strained { joint }] if joint == "left_shoulder_roll"),
        "{refusals:?}"
    );
    assert!(refusals[0].to_string().contains("too low for its load"));
    // Refused by the session and driven back before its firmware's bound left it with no
    // output under the arm's weight.
    let trips = bus.borrow_mut().servo_mut(id).unwrap().log.overload_trips;
    assert_eq!(trips, 0, "the firmware ended the strain, not the session");
}

/// A shoulder whose over-current protection is set at 1 A (not as the driver sets it up): it
/// unloads its motor under the calibration's torque. Refused, naming it and what to do.
#[test]
fn a_servo_whose_protection_fires_stops_the_calibration() {
    let robot = RobotDescription::nori_a3();
    let bus = changed_arm(|_| {});
    {
        let mut b = bus.borrow_mut();
        let s = b.servo_mut(1).unwrap();
        assert!(s.write(reg::LOCK.addr, &[0]));
        // 6.5 mA a count.
        assert!(s.write(reg::PROTECTION_CURRENT.addr, &154u16.to_le_bytes()));
        assert!(s.write(reg::LOCK.addr, &[1]));
    }
    let refusals = refused(&bus, plan(&robot));
    let [Refusal::Unloaded { joint, status }] = &refusals[..] else {
        panic!("{refusals:?}")
    };
    assert_eq!(joint, "left_shoulder_pitch");
    assert!(status.contains("over-current"), "{status}");
    assert!(refusals[0].to_string().contains("nori servo setup"));
}

/// A joint held while another is swept (the shoulder, while the gripper is) whose motor its
/// firmware unloads (its temperature limit below the room's): found by the status read in
/// turn, within a second, not when its own sweep comes.
#[test]
fn a_held_joint_unloaded_while_another_is_swept_stops_the_calibration() {
    let robot = RobotDescription::nori_a3();
    let bus = changed_arm(|_| {});
    {
        let mut b = bus.borrow_mut();
        let s = b.servo_mut(1).unwrap();
        assert!(s.write(reg::LOCK.addr, &[0]));
        assert!(s.write(reg::MAX_TEMPERATURE_LIMIT.addr, &[20]));
        assert!(s.write(reg::LOCK.addr, &[1]));
    }
    let t0 = bus.borrow().time();
    let refusals = refused(&bus, plan(&robot));
    let [Refusal::Unloaded { joint, status }] = &refusals[..] else {
        panic!("{refusals:?}")
    };
    assert_eq!(joint, "left_shoulder_pitch");
    assert!(status.contains("overheat"), "{status}");
    let took = bus.borrow().time() - t0;
    assert!(took < 3.0, "refused after {took} s");
    // The gripper, swept when it was found, was stopped: it had not reached its lower stop.
    let (lowest, _) = extremes(8);
    assert!(lowest > 0.1, "the gripper went down to {lowest} rad");
}

/// Stopped in the middle of a sweep (the operator's Ctrl-C, or out of time): the joint driven
/// back, the arm parked, every servo given back what it held; the joints calibrated before it
/// are not kept (nothing half-calibrated).
#[test]
fn a_session_stopped_mid_sweep_leaves_every_servo_as_found() {
    let robot = RobotDescription::nori_a3();
    let bus = changed_arm(|_| {});
    let before = held(&bus);
    // Into the elbow's sweep (the fifth joint), then stopped.
    let mut elbow_began = None;
    let (end, _) = session_until_end(&bus, plan(&robot), |p, t, session, bus| {
        match p {
            Progress::Working(4, Activity::Seeking(Toward::Upper, moved)) if *moved > 0.5 => {
                session.stop(t, 0.0)
            }
            Progress::Working(4, Activity::Posing) => {
                elbow_began = Some(bus.borrow_mut().servo_mut(4).unwrap().angle);
            }
            Progress::Done(_) => panic!("not stopped"),
            _ => {}
        }
        true
    });
    let Err(SessionError::Refused(refusals)) = end else {
        panic!("{end:?}")
    };
    assert!(
        matches!(&refusals[..], [Refusal::Stopped { .. }]),
        "{refusals:?}"
    );
    assert_eq!(held(&bus), before);
    let mut b = bus.borrow_mut();
    let elbow = b.servo_mut(4).unwrap().angle;
    let began_at = elbow_began.unwrap();
    assert!((elbow - began_at).abs() < 0.1, "{began_at} → {elbow}");
    for id in 1..=8 {
        assert!(!b.servo_mut(id).unwrap().torque_enabled(), "servo {id}");
    }
}

/// A torque limit that leaves no whole percent between the stall rule's 80 % of it and itself
/// leaves the firmware no press bound: refused before any servo is touched.
#[test]
fn a_plan_whose_limit_leaves_no_press_bound_is_refused_before_anything_moves() {
    let robot = RobotDescription::nori_a3();
    let mut plan = plan(&robot);
    plan.sweeps[0].torque_permille = 40;
    let bus = changed_arm(|_| {});
    let before = bus.borrow().time();
    let line = Bus::new(line(&bus), Duration::from_micros(600));
    let Err(e) = Automatic::start(line, plan, before) else {
        panic!("started")
    };
    assert!(matches!(e, SessionError::NoPressBound { .. }), "{e}");
    assert!(e.to_string().contains("limit of 4 %"), "{e}");
    let mut b = bus.borrow_mut();
    for id in 1..=8 {
        assert_eq!(
            b.servo_mut(id).unwrap().log.last_torque_write,
            None,
            "servo {id}"
        );
    }
}

/// Killed in the middle of a sweep (SIGKILL: no Drop, nothing more on the line) while the
/// elbow turns toward its lower stop in speed mode: reaching it, the elbow's own firmware ends
/// the press within the session's bound (1 s above 90 % of the sweep's torque limit), and its
/// status says why. It used to press at the limit until its temperature cut it off or the
/// power went.
#[test]
fn a_session_killed_mid_sweep_leaves_no_motor_pressing_its_stop() {
    let robot = RobotDescription::nori_a3();
    let bus = changed_arm(|_| {});
    // Its overload protection not enabled (the session enables it for the sweep).
    assert!(bus
        .borrow_mut()
        .servo_mut(4)
        .unwrap()
        .write(reg::UNLOADING_CONDITION.addr, &[0x0C]));
    let mut t = bus.borrow().time();
    let line = Bus::new(line(&bus), Duration::from_micros(600));
    let mut session = Automatic::start(line, plan(&robot), t).unwrap();
    loop {
        t += 0.02;
        bus.borrow_mut().advance_to(t, 0.001);
        let p = session.tick(t).unwrap();
        if matches!(p, Progress::Working(4, Activity::Seeking(Toward::Lower, moved)) if moved > 0.1)
        {
            break;
        }
        assert!(t < 600.0, "the elbow's sweep never began");
    }
    std::mem::forget(session);
    bus.borrow_mut().advance_to(t + 60.0, 0.001);
    let mut b = bus.borrow_mut();
    let elbow = b.servo_mut(4).unwrap();
    assert!(elbow.torque_enabled(), "nobody turned it off");
    let pressed = elbow.log.stop_press_s;
    assert!(
        pressed > 0.5 && pressed < 1.5,
        "pressed its stop {pressed} s of the minute after the kill"
    );
    assert!(elbow.protections.overload, "{:?}", elbow.protections);
}

/// Stopped after every joint was calibrated, as the last one goes back to rest (or a session
/// dropped halfway): not one calibration is kept, in RAM or in flash.
#[test]
fn a_session_stopped_after_the_last_sweep_or_dropped_keeps_no_calibration() {
    let robot = RobotDescription::nori_a3();
    for drop_it in [false, true] {
        let bus = changed_arm(|_| {});
        let before = held(&bus);
        let offsets = |bus: &RefCell<SimBus>| -> Vec<i32> {
            (1..=8)
                .map(|id| {
                    bus.borrow_mut()
                        .servo_mut(id)
                        .unwrap()
                        .get(reg::HOMING_OFFSET)
                })
                .collect()
        };
        let in_ram = offsets(&bus);
        let mut stopped = false;
        let (end, _) = session_until_end(&bus, plan(&robot), |p, t, session, _| {
            if let (Progress::Working(7, Activity::Resting), false) = (p, stopped) {
                stopped = true;
                if drop_it {
                    return false;
                }
                session.stop(t, 0.0);
            }
            assert!(!matches!(p, Progress::Done(_)), "not stopped");
            true
        });
        match end {
            Ok(_) => assert!(drop_it && stopped),
            Err(SessionError::Refused(r)) => {
                assert!(matches!(&r[..], [Refusal::Stopped { .. }]), "{r:?}")
            }
            Err(e) => panic!("{e}"),
        }
        assert_eq!(held(&bus), before, "dropped: {drop_it}");
        assert_eq!(offsets(&bus), in_ram, "dropped: {drop_it}");
        let mut b = bus.borrow_mut();
        for id in 1..=8 {
            let s = b.servo_mut(id).unwrap();
            assert!(!s.torque_enabled(), "servo {id}");
            assert_eq!(s.get(reg::OPERATING_MODE), 0, "servo {id}");
        }
    }
}

/// The elbow, held folded while the shoulder's pitch is swept, overheats (its motor unloaded
/// by its firmware, its protection latched): refused naming it, and the session still ends
/// (the arm parked as far as it goes, every torque off, every servo given back) instead of
/// parking for ever against the latched bit.
#[test]
fn a_latched_protection_while_parking_still_ends_the_session() {
    let robot = RobotDescription::nori_a3();
    let bus = changed_arm(|_| {});
    let before = held(&bus);
    let mut tripped_at = None;
    let (end, took) = session_until_end(&bus, plan(&robot), |p, t, _, bus| {
        if let (Progress::Working(6, Activity::Seeking(..)), None) = (p, tripped_at) {
            tripped_at = Some(t);
            let mut b = bus.borrow_mut();
            let s = b.servo_mut(4).unwrap();
            assert!(s.write(reg::LOCK.addr, &[0]));
            assert!(s.write(reg::MAX_TEMPERATURE_LIMIT.addr, &[20]));
            assert!(s.write(reg::LOCK.addr, &[1]));
        }
        true
    });
    let Err(SessionError::Refused(refusals)) = end else {
        panic!("{end:?}")
    };
    assert!(
        matches!(&refusals[..], [Refusal::Unloaded { joint, .. }] if joint == "left_elbow"),
        "{refusals:?}"
    );
    let after_trip = took - tripped_at.unwrap();
    assert!(after_trip < 60.0, "ended {after_trip} s after the trip");
    assert_eq!(held(&bus), before);
    let mut b = bus.borrow_mut();
    for id in 1..=8 {
        assert!(!b.servo_mut(id).unwrap().torque_enabled(), "servo {id}");
    }
}

/// Stopped while the arm parks after the last joint: refused, nothing kept; and a committed
/// calibration that cannot be recorded is abandoned: every servo's flash as it was.
#[test]
fn a_stop_while_parking_and_an_abandoned_commit_keep_no_calibration() {
    let robot = RobotDescription::nori_a3();
    let bus = changed_arm(|_| {});
    let before = held(&bus);
    let mut stopped = false;
    let (end, _) = session_until_end(&bus, plan(&robot), |p, t, session, _| {
        if let (Progress::Working(_, Activity::Parking), false) = (p, stopped) {
            stopped = true;
            session.stop(t, 0.0);
        }
        true
    });
    let Err(SessionError::Refused(refusals)) = end else {
        panic!("{end:?}")
    };
    assert!(
        matches!(&refusals[..], [Refusal::Stopped { .. }]),
        "{refusals:?}"
    );
    assert_eq!(held(&bus), before);

    let mut abandoned = false;
    let (end, _) = session_until_end(&bus, plan(&robot), |p, _, session, bus| {
        if let Progress::Done(_) = p {
            // Committed: in flash now.
            assert_ne!(held(bus), before);
            session.abandon().unwrap();
            abandoned = true;
        }
        true
    });
    assert!(end.is_ok() && abandoned, "{end:?}");
    assert_eq!(held(&bus), before);
}
