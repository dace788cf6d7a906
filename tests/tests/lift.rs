//! The lift on the simulated robot, as on the robot: the simulator serves the column's board on
//! a pseudo-terminal (its motor, halls, switches and watchdog), `nori-lift` drives it. The lift
//! homes, goes to a height at its rated speed and holds it (the simulator's truth agrees), a
//! stale command is refused, and coming down onto a hand it stops within its obstruction time
//! and backs off.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{binary, nori_ok, scratch, wait_for, ArmStack, Proc};
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::config::ProcessConfig;
use telemetry::motion::{
    LiftCommand, LiftState, LIFT_HOMING, LIFT_JAMMED, LIFT_OBSTRUCTED, LIFT_READY,
};
use telemetry::plane::{self, newest, Plane};

/// The column's obstruction time (lift.toml) and a control period and a status period of slack.
const PRESS_BOUND_S: f64 = 0.15 + 0.02 + 0.02;

/// How far from its goal a lift that got there may stand: the controller's hold band (twice
/// its tolerance: it moves again only beyond it, so as not to hunt) and a hall count. A starved
/// controller brakes a period late and lands at the band's edge (seen in CI on a loaded runner:
/// exactly 2.0 mm past the goal, held there as designed).
const HOLD_M: f32 = (2.0 * lift::column::ColumnConfig::A3.tolerance_m
    + 1.0 / lift::column::ColumnConfig::A3.counts_per_m) as f32;

/// The simulator with the lift standing 5 cm up at start (homing takes seconds, not twenty)
/// and `sim_args`, and `nori-lift` on its board (started once the simulator has linked it:
/// before, nori-lift exits 69 as it should without its board, and systemd would start it again).
fn lift_on_sim(tag: &str, sim_args: &[&str]) -> (ArmStack, Proc) {
    let files = scratch(&format!("{tag}-files"));
    let robot = files.join("robot.toml");
    let text = sim::description::NORI_A3_TOML.replacen("start-m = 0.3", "start-m = 0.05", 1);
    assert_ne!(text, sim::description::NORI_A3_TOML);
    std::fs::write(&robot, text).unwrap();
    let robot = robot.display().to_string();
    let mut args = vec!["--description", robot.as_str()];
    args.extend(sim_args);
    let stack = ArmStack::simulator_only_on(tag, "base", &args);
    let link = stack.dir.join("dev").join("lift");
    wait_for(Duration::from_secs(10), "the lift's board", || {
        link.exists().then_some(())
    });
    let lift = spawn_lift(&stack, "lift.log");
    (stack, lift)
}

/// `nori-lift` on the simulator's board, its hold record in the stack's directory, logging to
/// `log` there.
fn spawn_lift(stack: &ArmStack, log: &str) -> Proc {
    let dev = stack.device_dir_with("lift");
    let hold = stack.dir.join("lift-hold").display().to_string();
    Proc::spawn(
        "nori-lift",
        &binary("nori-lift"),
        &[
            "--device-dir",
            &dev,
            "--domain",
            &stack.domain,
            "--hold-file",
            &hold,
        ],
        &stack.dir.join(log),
    )
}

/// A goal of `h` m numbered `seq`, made `age_ms` ago.
fn goal(seq: u64, h: f32, age_ms: u64) -> LiftCommand {
    LiftCommand {
        seq,
        timestamp_ns: monotonic_ns() - age_ms * 1_000_000,
        height_m: h,
        kind: telemetry::motion::LIFT_COMMAND_GOAL,
    }
}

/// The simulator's figure `key` of its lift (its report, written as it runs).
fn sim_lift(stack: &ArmStack, key: &str) -> f64 {
    let text = std::fs::read_to_string(stack.dir.join("sim-report.json")).unwrap();
    let report: serde_json::Value = serde_json::from_str(&text).unwrap();
    report["lift"][key].as_f64().unwrap()
}

#[test]
fn the_lift_homes_goes_to_a_height_holds_it_and_stops_on_a_hand() {
    // A hand appearing under it at 0.25 m after 24 s.
    let started = Instant::now();
    let (mut stack, mut lift) = lift_on_sim(
        "lift",
        &["--lift-obstacle-at", "0.25", "--lift-obstacle-from", "24"],
    );
    // The supervisor's allowance (the lift's duty-cycle budget): no travel without it.
    stack.restart_supervisor();
    let node = Plane::open(&stack.domain, "test").unwrap();
    let commands = node.publisher(&plane::LIFT_COMMAND).unwrap();
    let states = node.subscriber(&plane::LIFT_STATE).unwrap();
    let truth = || -> f64 { sim_lift(&stack, "height_m") };
    let mut seq = 0;
    let mut command = |h: f32, age_ms: u64| {
        seq += 1;
        plane::publish(&commands, &goal(seq, h, age_ms)).unwrap();
    };

    // Homed at its lower switch.
    let homed = wait_for(Duration::from_secs(15), "the lift homed", || {
        newest(&states).filter(|s: &LiftState| s.state == LIFT_READY)
    });
    assert!(
        homed.height_m.abs() < 0.002 && homed.switches & 1 == 1,
        "{homed:?}"
    );

    // To 0.4 m: 0.4 m at the rated 30 mm/s is about 14 s.
    command(0.4, 0);
    let sent = Instant::now();
    let there = wait_for(Duration::from_secs(20), "the lift at 0.4 m", || {
        newest(&states).filter(|s| (s.height_m - 0.4).abs() <= HOLD_M && s.velocity_m_s == 0.0)
    });
    let took = sent.elapsed().as_secs_f64();
    assert!(
        took > 0.4 / 0.032,
        "0.4 m in {took} s: faster than the column can go"
    );
    assert_eq!(there.goal_m, 0.4);
    // Held: the simulator's column where nori-lift says, and staying there.
    std::thread::sleep(Duration::from_millis(2000));
    let held = newest(&states).unwrap();
    assert!((held.height_m - 0.4).abs() <= HOLD_M, "{held:?}");
    std::thread::sleep(Duration::from_millis(1100));
    let h = truth();
    // The simulator's column where nori-lift has it: within the switch's width at homing
    // (0.5 mm) and the halls' resolution.
    let now = newest(&states).unwrap();
    assert!(
        (h - f64::from(now.height_m)).abs() < 0.0007,
        "the simulator has the column at {h} m, nori-lift at {} m",
        now.height_m
    );

    // A command 500 ms old is refused; the lift stays.
    command(0.1, 500);
    std::thread::sleep(Duration::from_millis(300));
    let s = newest(&states).unwrap();
    assert_eq!(s.commands_refused, 1, "{s:?}");
    assert!((s.height_m - 0.4).abs() <= HOLD_M, "{s:?}");

    // A hand under it at 0.25 m (from 24 s after start): coming down, it stops on it and backs
    // off a centimetre.
    let hand_from = Duration::from_secs(25);
    if let Some(wait) = hand_from.checked_sub(started.elapsed()) {
        std::thread::sleep(wait);
    }
    command(0.1, 0);
    let stopped = wait_for(
        Duration::from_secs(15),
        "the lift stopped on the hand",
        || newest(&states).filter(|s| s.state == LIFT_OBSTRUCTED && s.velocity_m_s == 0.0),
    );
    assert_eq!(stopped.obstructions, 1);
    std::thread::sleep(Duration::from_millis(1500));
    let s = newest(&states).unwrap();
    assert!(
        (s.height_m - 0.26).abs() < 0.003,
        "backed off to {} m",
        s.height_m
    );
    let pressed = sim_lift(&stack, "longest_press_s");
    assert!(
        pressed > 0.0 && pressed <= PRESS_BOUND_S,
        "the column pressed on the hand for {pressed} s (bound {PRESS_BOUND_S} s)"
    );
    eprintln!(
        "lift: pressed on the hand {:.0} ms, backed off to {:.3} m",
        pressed * 1000.0,
        s.height_m
    );

    let (code, out) = lift.terminate(Duration::from_secs(5));
    assert_eq!(code, Some(0), "{out}");
    drop(commands);
    drop(states);
    drop(node);
    stack.stop();
}

/// The motor's duty-cycle rating (here 6 s on per 54 s off, 2 s to regain, so that a test
/// spends it): the supervisor refuses travel once it is spent and says for how long; the lift
/// stops and holds, then goes on when allowed. Without a live supervisor the lift holds too.
#[test]
fn the_duty_budget_stops_travel_when_spent_and_no_supervisor_means_no_travel() {
    let files = scratch("lift-duty-config");
    let config = files.join("supervisor.toml");
    let text = supervisor::SupervisorConfig::DEFAULT_TOML
        .replacen("on-s = 120", "on-s = 6", 1)
        .replacen("off-s = 1080", "off-s = 54", 1)
        .replacen("resume-s = 30", "resume-s = 2", 1);
    std::fs::write(&config, text).unwrap();
    let (stack, mut lift) = lift_on_sim("lift-duty", &[]);
    let node = Plane::open(&stack.domain, "test").unwrap();
    let commands = node.publisher(&plane::LIFT_COMMAND).unwrap();
    let states = node.subscriber(&plane::LIFT_STATE).unwrap();

    // No supervisor yet: not even homing moves it.
    std::thread::sleep(Duration::from_millis(1500));
    let s = newest(&states).unwrap();
    assert!(
        s.held == 2 && s.velocity_m_s == 0.0 && s.state == LIFT_HOMING,
        "{s:?}"
    );
    let mut supervisor = Proc::spawn(
        "supervisor",
        &binary("supervisor"),
        &[
            "--domain",
            &stack.domain,
            "--config",
            config.to_str().unwrap(),
            "--trip-file",
            stack.dir.join("trips").to_str().unwrap(),
        ],
        &stack.dir.join("supervisor.log"),
    );
    wait_for(Duration::from_secs(15), "the lift homed", || {
        newest(&states).filter(|s| s.state == LIFT_READY)
    });
    // Homing ran about 3.3 s of the 6 s: the rest of the budget spent going up.
    plane::publish(&commands, &goal(1, 0.4, 0)).unwrap();
    let refused = wait_for(Duration::from_secs(10), "the budget spent", || {
        newest(&states).filter(|s| s.held == 1)
    });
    // 2 s of running to regain at 6/54 s per s of rest: 18 s.
    assert!((refused.duty_wait_s - 18.0).abs() < 1.0, "{refused:?}");
    std::thread::sleep(Duration::from_millis(500));
    let stopped = newest(&states).unwrap();
    assert_eq!(stopped.velocity_m_s, 0.0, "{stopped:?}");
    assert!(stopped.height_m < 0.2, "{stopped:?}");
    std::thread::sleep(Duration::from_millis(3000));
    let still = newest(&states).unwrap();
    assert!(
        (still.height_m - stopped.height_m).abs() < 0.001,
        "moved while refused: {still:?}"
    );
    // Allowed again after the rest: it goes on up.
    let going = wait_for(Duration::from_secs(25), "travel allowed again", || {
        newest(&states).filter(|s| s.held == 0 && s.height_m > stopped.height_m + 0.01)
    });
    eprintln!(
        "lift duty: refused at {:.3} m for {:.1} s, going on at {:?}",
        stopped.height_m, refused.duty_wait_s, going.height_m
    );

    // The supervisor killed: no live allowance within 200 ms, the lift holds.
    supervisor.kill();
    let killed = Instant::now();
    let held = wait_for(
        Duration::from_secs(2),
        "the lift held without a supervisor",
        || newest(&states).filter(|s| s.held == 2 && s.velocity_m_s == 0.0),
    );
    assert!(
        killed.elapsed() < Duration::from_millis(400),
        "held only after {:?}",
        killed.elapsed()
    );
    let _ = held;
    let (code, _) = lift.terminate(Duration::from_secs(5));
    assert_eq!(code, Some(0));
    drop(commands);
    drop(states);
    drop(node);
    stack.stop();
}

/// From outside, as the operator and a streaming planner would, with no bus-driver running:
/// `nori stop` stops a column moving up at once, drops its goal and refuses goals until
/// `nori resume`, after which nothing told before moves it; a goal re-sent every 60 ms onto a
/// hand at 0.25 m presses it once, within the obstruction time, and leaves the column backed
/// off and holding; `nori lift release` ends the hold without moving it; held again and
/// SIGKILLed, a restarted nori-lift keeps the hold (jammed) instead of homing onto the hand.
#[test]
#[allow(
    clippy::too_many_lines,
    reason = "one scenario read start to end; to be split into phases (#37)"
)]
fn the_operators_stop_stops_the_lift_and_a_streamed_goal_presses_a_hand_once() {
    let (mut stack, mut lift) = lift_on_sim(
        "lift-stop",
        &["--lift-obstacle-at", "0.25", "--lift-obstacle-from", "0"],
    );
    stack.restart_supervisor();
    let node = Plane::open(&stack.domain, "test").unwrap();
    let commands = node.publisher(&plane::LIFT_COMMAND).unwrap();
    let states = node.subscriber(&plane::LIFT_STATE).unwrap();
    let mut seq = 0;
    let mut command = |h: f32| {
        seq += 1;
        plane::publish(&commands, &goal(seq, h, 0)).unwrap();
    };
    wait_for(Duration::from_secs(15), "the lift homed", || {
        newest(&states).filter(|s: &LiftState| s.state == LIFT_READY)
    });
    command(0.35);
    wait_for(
        Duration::from_secs(15),
        "the lift going up past 0.15 m",
        || newest(&states).filter(|s| s.height_m > 0.15 && s.velocity_m_s > 0.0),
    );
    let said = nori_ok(&["stop"], &stack.domain);
    assert!(said.contains("stopped"), "{said}");
    let stopped_at = Instant::now();
    let stopped = wait_for(Duration::from_secs(1), "the lift stopped", || {
        newest(&states).filter(|s| s.held == 3 && s.velocity_m_s == 0.0)
    });
    assert!(
        stopped_at.elapsed() < Duration::from_millis(200),
        "stopped only after {:?}",
        stopped_at.elapsed()
    );
    assert!(stopped.goal_m.is_nan(), "the goal kept: {stopped:?}");
    std::thread::sleep(Duration::from_millis(300));
    let stood = newest(&states).unwrap();
    // A goal during the stop is refused; the column stands.
    command(0.5);
    std::thread::sleep(Duration::from_millis(1500));
    let s = newest(&states).unwrap();
    assert_eq!(s.commands_refused, stood.commands_refused + 1, "{s:?}");
    assert!(
        (s.height_m - stood.height_m).abs() < 0.001,
        "moved during the stop: {s:?}"
    );
    eprintln!(
        "lift stop: {:.1} mm of travel after the stop",
        (stood.height_m - stopped.height_m) * 1000.0
    );
    // Resumed: nothing told before moves it.
    nori_ok(&["resume"], &stack.domain);
    wait_for(Duration::from_secs(1), "the stop ended", || {
        newest(&states).filter(|s| s.held == 0)
    });
    std::thread::sleep(Duration::from_millis(1000));
    let s = newest(&states).unwrap();
    assert!(
        (s.height_m - stood.height_m).abs() < 0.001,
        "moved after the resume: {s:?}"
    );

    // Up above the hand, then down onto it under a goal re-sent every 60 ms for 8 s.
    command(0.35);
    wait_for(Duration::from_secs(15), "the lift at 0.35 m", || {
        newest(&states).filter(|s| (s.height_m - 0.35).abs() <= HOLD_M && s.velocity_m_s == 0.0)
    });
    let until = Instant::now() + Duration::from_secs(8);
    while Instant::now() < until {
        command(0.1);
        std::thread::sleep(Duration::from_millis(60));
    }
    let s = newest(&states).unwrap();
    assert_eq!((s.state, s.obstructions), (LIFT_OBSTRUCTED, 1), "{s:?}");
    assert!(
        (s.height_m - 0.26).abs() < 0.003,
        "left at {} m",
        s.height_m
    );
    let pressed = sim_lift(&stack, "pressed_s");
    assert!(
        pressed > 0.0 && pressed <= PRESS_BOUND_S,
        "pressed on the hand {pressed} s in all under a streamed goal (bound {PRESS_BOUND_S} s)"
    );
    eprintln!(
        "lift streamed onto a hand: pressed {:.0} ms in all",
        pressed * 1000.0
    );
    // The hand gone, the operator releases the hold: the column stays where its back-off
    // left it (its goal, if any, is where it stands).
    let said = nori_ok(&["lift", "release"], &stack.domain);
    assert!(said.contains("released"), "{said}");
    std::thread::sleep(Duration::from_millis(500));
    let released = newest(&states).unwrap();
    assert_eq!(released.state, LIFT_READY, "{released:?}");
    assert!(
        (released.goal_m.is_nan() || (released.goal_m - released.height_m).abs() < 0.002)
            && (released.height_m - s.height_m).abs() < 0.001,
        "{released:?}"
    );
    // Onto the hand again (a second time at the same place: only a release ends this hold),
    // then nori-lift killed and started again.
    for _ in 0..40 {
        command(0.1);
        std::thread::sleep(Duration::from_millis(60));
    }
    let held = newest(&states).unwrap();
    assert_eq!(held.state, LIFT_OBSTRUCTED, "{held:?}");
    let pressed = sim_lift(&stack, "pressed_s");
    lift.kill();
    lift = spawn_lift(&stack, "lift-2.log");
    let jammed = wait_for(Duration::from_secs(5), "the restarted lift jammed", || {
        newest(&states).filter(|s| s.state == LIFT_JAMMED)
    });
    std::thread::sleep(Duration::from_millis(1500));
    let still = newest(&states).unwrap();
    assert_eq!(
        (still.state, still.velocity_m_s),
        (LIFT_JAMMED, 0.0),
        "{still:?} after {jammed:?}"
    );
    let pressed_after = sim_lift(&stack, "pressed_s");
    assert!(
        pressed_after - pressed < 1e-9,
        "the restarted lift pressed the hand {:.3} s more",
        pressed_after - pressed
    );
    let (code, out) = lift.terminate(Duration::from_secs(5));
    assert_eq!(code, Some(0), "{out}");
    drop((commands, states, node));
    stack.stop();
}
