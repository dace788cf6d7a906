//! Crash isolation with the real processes on the simulator: any process of the robot may die
//! at any moment (SIGKILL: no chance to clean up) and nothing may get hurt. Kill moments come
//! from a seeded generator, so a failure replays.
//!
//! The three tests take turns (a mutex): they measure reaction times, and two stacks at once on
//! a two-core machine would measure each other.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fleet_agent::keys::robot_key;
use fleet_agent::zenoh::Wait;
use nori_tests::{
    check_left_arm_report, free_endpoint, plane_files, quantile, scratch, wait_for, ArmStack, Rng,
};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::config::ProcessConfig;
use telemetry::frames::{EventKind, SupervisorEvent, STATE_FLAG_SAFE_STATE};
use telemetry::plane::{self, newest, next, publish, Plane};
use telemetry::{GoalFrame, JointState};

static SERIAL: Mutex<()> = Mutex::new(());

/// The driver's supervisor timeout (deploy/config/bus-driver.toml), ms.
const HEARTBEAT_BOUND_MS: f64 = 50.0;
/// What the design promises after a supervisor dies: the last heartbeat is at most one
/// heartbeat period (5 ms) old at the kill, the driver declares it missing at the bound and
/// applies the safe state in the cycle that sees it (5 ms): 60 ms. Every sample must come in
/// under that plus 40 ms, the scheduling slack this shared two-core VM keeps.
const REACTION_CEILING_MS: f64 = HEARTBEAT_BOUND_MS + 5.0 + 5.0 + 40.0;
/// Joints of the left arm.
const JOINTS: u32 = 8;
/// The elbow's index in the frame.
const ELBOW: usize = 3;

fn serial() -> std::sync::MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

/// Under supervision, every servo answering with torque on.
fn driving(s: &JointState) -> bool {
    s.flags & STATE_FLAG_SAFE_STATE == 0
        && s.joint_count == JOINTS
        && s.joints()
            .iter()
            .all(|j| j.is_valid() && j.torque_enabled == 1)
}

fn elbow_goal(position: f32, timestamp_ns: u64) -> GoalFrame {
    let mut g = GoalFrame {
        joint_count: JOINTS,
        mask: 1 << ELBOW,
        timestamp_ns,
        ..GoalFrame::default()
    };
    g.position_rad[ELBOW] = position;
    g
}

#[test]
fn killing_the_supervisor_puts_the_driver_in_its_safe_state_within_the_bound() {
    let _turn = serial();
    const KILLS: usize = 12;
    let mut stack = ArmStack::start("crash-sup", &[]);
    let node = Plane::open(&stack.domain, "test").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    let beats = node.subscriber(&plane::SUPERVISOR_HEARTBEAT).unwrap();
    let mut rng = Rng::new(0x5AFE_0001);
    let mut latencies_ms = Vec::new();
    let mut after_last_beat_ms = Vec::new();
    for _ in 0..KILLS {
        wait_for(
            Duration::from_secs(20),
            "the driver driving under supervision",
            || newest(&states).filter(driving),
        );
        std::thread::sleep(Duration::from_secs_f64(rng.range(0.05, 0.5)));
        while next(&states).is_some() {}
        let killed_at = monotonic_ns();
        stack.supervisor.kill();
        // The last heartbeat it sent (its own timestamp is what the driver judges).
        let last_beat = std::iter::from_fn(|| next(&beats))
            .map(|b| b.timestamp_ns)
            .max()
            .unwrap_or(killed_at);
        let safe = wait_for(Duration::from_secs(2), "the safe state", || {
            std::iter::from_fn(|| next(&states)).find(|s| s.flags & STATE_FLAG_SAFE_STATE != 0)
        });
        latencies_ms.push(safe.timestamp_ns.saturating_sub(killed_at) as f64 * 1e-6);
        after_last_beat_ms.push(safe.timestamp_ns.saturating_sub(last_beat) as f64 * 1e-6);
        stack.restart_supervisor();
    }
    let (p50, p99, max) = (
        quantile(&latencies_ms, 0.5),
        quantile(&latencies_ms, 0.99),
        quantile(&latencies_ms, 1.0),
    );
    eprintln!(
        "safe state after a supervisor SIGKILL, {KILLS} kills: p50 {p50:.1} ms, p99 {p99:.1} ms, \
         max {max:.1} ms (bound {HEARTBEAT_BOUND_MS} ms, goal p99 <= {} ms: {})",
        2.0 * HEARTBEAT_BOUND_MS,
        if p99 <= 2.0 * HEARTBEAT_BOUND_MS {
            "met"
        } else {
            "MISSED"
        }
    );
    // The safe state is the heartbeat's doing: it comes after the bound counted from the last
    // heartbeat the supervisor sent (a loaded machine may have sent it well before the kill),
    // typically within two cycles of the kill's bound, and every time within the ceiling.
    assert!(
        after_last_beat_ms
            .iter()
            .all(|&l| l >= HEARTBEAT_BOUND_MS - 1.0),
        "safe state before the bound after the last heartbeat: {after_last_beat_ms:?}"
    );
    assert!(p50 <= HEARTBEAT_BOUND_MS + 15.0, "p50 {p50:.1} ms");
    assert!(
        max <= REACTION_CEILING_MS,
        "max {max:.1} ms (ceiling {REACTION_CEILING_MS} ms): {latencies_ms:?}"
    );
    drop((states, beats, node));
    stack.stop();
}

#[test]
fn a_killed_driver_is_reported_and_restarts_without_a_jump_or_a_stale_goal() {
    let _turn = serial();
    const ROUNDS: usize = 4;
    let mut stack = ArmStack::start("crash-drv", &[]);
    let node = Plane::open(&stack.domain, "test").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    let events = node.subscriber(&plane::EVENTS).unwrap();
    let goals = node.publisher(&plane::GOALS).unwrap();
    let mut rng = Rng::new(0xD71E_0002);
    wait_for(Duration::from_secs(20), "driving", || {
        newest(&states).filter(driving)
    });
    let files_at_start = plane_files(&stack.domain).len();
    for round in 0..ROUNDS {
        // The elbow follows a moving goal, as under a policy, and the driver dies mid-motion.
        let moving_for = rng.range(0.3, 1.2);
        let start = Instant::now();
        while start.elapsed().as_secs_f64() < moving_for {
            let t = start.elapsed().as_secs_f32();
            let target = -0.6 + 0.4 * (std::f32::consts::PI * t).sin();
            publish(&goals, &elbow_goal(target, monotonic_ns())).unwrap();
            std::thread::sleep(Duration::from_millis(10));
        }
        while next(&events).is_some() {}
        let last_seq = newest(&states).unwrap().seq;
        stack.driver.kill();
        wait_for(Duration::from_secs(2), "DriverLost", || {
            std::iter::from_fn(|| next(&events)).find(|e| e.kind() == Some(EventKind::DriverLost))
        });

        // A goal produced while no driver ran, for a moment that has passed: far from where the
        // elbow is. It keeps arriving while the new driver comes up; it must not be acted on.
        let stale = elbow_goal(-1.4, monotonic_ns());
        stack.restart_driver();
        let first = wait_for(Duration::from_secs(20), "the new driver's frames", || {
            let _ = publish(&goals, &stale);
            std::thread::sleep(Duration::from_millis(5));
            std::iter::from_fn(|| next(&states)).find(|s| s.seq < last_seq && driving(s))
        });
        // Its first goal is the present position, and nothing moves.
        for (i, j) in first.joints().iter().enumerate() {
            assert!(
                (j.goal_rad - j.position_rad).abs() < 0.05,
                "round {round}: joint {i} restarted with goal {} at position {}",
                j.goal_rad,
                j.position_rad
            );
        }
        let watch = Instant::now();
        let (mut largest_move, mut moved) = (0f32, String::new());
        while watch.elapsed() < Duration::from_secs(1) {
            let _ = publish(&goals, &stale);
            for s in std::iter::from_fn(|| next(&states)) {
                // A servo missing in one cycle (a late reply on a loaded machine) says nothing.
                let pairs = s.joints().iter().zip(first.joints()).enumerate();
                for (i, (a, b)) in pairs.filter(|(_, (a, _))| a.is_valid()) {
                    let d = (a.position_rad - b.position_rad).abs();
                    if d > largest_move {
                        largest_move = d;
                        moved = format!(
                            "joint {i} from {} (goal {}) to {} (goal {}) at seq {} -> {}, flags {:#x}",
                            b.position_rad, b.goal_rad, a.position_rad, a.goal_rad, first.seq, s.seq, s.flags
                        );
                    }
                }
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        assert!(
            largest_move < 0.05,
            "round {round}: a joint moved {largest_move} rad after the restart: {moved}"
        );
        wait_for(Duration::from_secs(5), "DriverBack", || {
            std::iter::from_fn(|| next(&events)).find(|e| e.kind() == Some(EventKind::DriverBack))
        });
        // Fresh goals are followed again.
        let target = -0.9 - 0.1 * round as f32;
        wait_for(Duration::from_secs(10), "the elbow at a fresh goal", || {
            publish(&goals, &elbow_goal(target, monotonic_ns())).unwrap();
            std::thread::sleep(Duration::from_millis(10));
            newest(&states).filter(|s| (s.joints[ELBOW].position_rad - target).abs() < 0.05)
        });
        // What the dead driver left on the plane was cleaned up when the new one started.
        let files = plane_files(&stack.domain).len();
        assert!(
            files <= files_at_start,
            "round {round}: {files} plane files, {files_at_start} at start: a dead driver's resources remain"
        );
    }
    let (_, summary) = stack.driver.terminate(Duration::from_secs(5));
    let summary: serde_json::Value = serde_json::from_str(summary.trim()).unwrap();
    let refused = summary["counters"]["goals_stale"].as_u64().unwrap();
    assert!(
        refused >= 1,
        "the last driver refused no stale goal: {summary}"
    );
    eprintln!(
        "{ROUNDS} driver kills mid-motion: no jump, stale goals refused ({refused} by the last driver), plane files {files_at_start} -> {}",
        plane_files(&stack.domain).len()
    );
    drop((states, events, goals, node));
    stack.stop();
}

/// Random goals at 50 Hz, many outside the calibrated ranges and some NaN: a policy gone wrong.
/// Each random target is held for 0.1–1.5 s, long enough for a joint to stall against the
/// obstacle or squeeze the gripper's object, as a policy stuck on a bad plan does.
fn wild_goals(domain: String, seed: u64, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<u64> {
    std::thread::spawn(move || {
        let node = Plane::open(&domain, "wild-policy").unwrap();
        let goals = node.publisher(&plane::GOALS).unwrap();
        let mut rng = Rng::new(seed);
        let mut sent = 0;
        let mut target = [0f32; JOINTS as usize];
        let mut until = Instant::now();
        while !stop.load(Ordering::Relaxed) {
            if Instant::now() >= until {
                for p in &mut target {
                    *p = rng.range(-4.0, 4.0) as f32;
                }
                until = Instant::now() + Duration::from_secs_f64(rng.range(0.1, 1.5));
            }
            let mut g = GoalFrame {
                joint_count: JOINTS,
                mask: (1 << JOINTS) - 1,
                timestamp_ns: monotonic_ns(),
                ..GoalFrame::default()
            };
            g.position_rad[..JOINTS as usize].copy_from_slice(&target);
            if rng.below(20) == 0 {
                g.position_rad[rng.below(u64::from(JOINTS)) as usize] = f32::NAN;
            }
            let _ = publish(&goals, &g);
            sent += 1;
            std::thread::sleep(Duration::from_millis(20));
        }
        sent
    })
}

const CHAOS_ROBOT: &str = "chaos-robot";

/// How many events of each kind.
fn event_counts(events: &[SupervisorEvent]) -> std::collections::BTreeMap<String, usize> {
    let mut counts = std::collections::BTreeMap::new();
    for e in events {
        *counts.entry(format!("{:?}", e.kind())).or_default() += 1;
    }
    counts
}

/// Seeded chaos for `NORI_CHAOS_SECONDS` (default 120 s): the overheat, stall and grip set-ups
/// all on the left arm, a wild policy, 0.5 % of the host's instructions dropped and 0.5 %
/// corrupted on the line, and SIGKILLs of the supervisor, the driver and the fleet agent at
/// random moments. Afterwards, from what the simulated servos received: no motor reached
/// 60 °C, no goal outside a calibrated range reached the wire, the bus latched off by the
/// thermal trip got no Torque_Enable = 1 and no goal after it was turned off (through every
/// later restart), and every torque reduction the supervisor announced was holding on the
/// servo within 100 ms (or was overtaken within that time by a kill, a restore or the bus
/// going off, each counted).
#[test]
fn a_seeded_chaos_run_keeps_every_invariant() {
    let _turn = serial();
    let seed = std::env::var("NORI_CHAOS_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(0xC4A0_5EED_u64);
    let seconds: f64 = std::env::var("NORI_CHAOS_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(120.0);
    let fault_seed = (seed ^ 7).to_string();
    // A warm room (30 °C): under the wild policy's random postures the loaded shoulder's
    // average heat settles near the trip in a 25 °C room (58.5 °C after 120 s on one run, a
    // trip at 118 s on another); five degrees more make the trip come mid-run on every seed.
    let description = scratch("chaos-description").join("warm-room.toml");
    std::fs::write(
        &description,
        sim::description::NORI_A3_TOML.replacen("ambient-c = 25.0", "ambient-c = 30.0", 1),
    )
    .unwrap();
    // A heavy payload heating fast enough to trip mid-run, an obstacle and an object in the
    // gripper: every protection is in play while processes die around it.
    let mut stack = ArmStack::start(
        "chaos",
        &[
            "--description",
            description.to_str().unwrap(),
            "--scenario",
            "overheat",
            "--scenario",
            "stall",
            "--scenario",
            "grip",
            // Faster heating shrinks the thermal time of a process restart with it: at ×40 a
            // driver killed just before a trip left a motor 20 s of thermal time at full load,
            // which real time never gives it.
            "--thermal-speedup",
            "30",
            "--instruction-drop-rate",
            "0.005",
            "--instruction-corrupt-rate",
            "0.005",
            "--fault-seed",
            &fault_seed,
        ],
    );
    let node = Plane::open(&stack.domain, "test").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    let events = node.subscriber(&plane::EVENTS).unwrap();
    let driver_beats = node.subscriber(&plane::DRIVER_HEARTBEAT).unwrap();
    let supervisor_beats = node.subscriber(&plane::SUPERVISOR_HEARTBEAT).unwrap();
    wait_for(Duration::from_secs(20), "driving", || {
        newest(&states).filter(driving)
    });
    // The fleet agent too: "back" is its telemetry arriving on zenoh again.
    let endpoint = free_endpoint();
    let fleet = nori_tests::listening_session(&endpoint);
    let telemetry = fleet
        .declare_subscriber(robot_key(CHAOS_ROBOT, "state"))
        .wait()
        .unwrap();
    stack.restart_agent(CHAOS_ROBOT, &endpoint);
    let stop = Arc::new(AtomicBool::new(false));
    let policy = wild_goals(stack.domain.clone(), seed ^ 1, stop.clone());
    let mut rng = Rng::new(seed);
    let mut restarts = [0u32; 3];
    let mut back_ms = Vec::new();
    // (monotonic ns, victim) of every kill; every supervisor event seen.
    let mut kills: Vec<(u64, usize)> = Vec::new();
    let mut seen: Vec<SupervisorEvent> = Vec::new();
    let pause = |seen: &mut Vec<SupervisorEvent>, d: Duration| {
        let until = Instant::now() + d;
        while Instant::now() < until {
            seen.extend(std::iter::from_fn(|| next(&events)));
            std::thread::sleep(Duration::from_millis(10));
        }
    };
    let start = Instant::now();
    while start.elapsed().as_secs_f64() < seconds {
        pause(&mut seen, Duration::from_secs_f64(rng.range(0.2, 1.5)));
        let victim = rng.below(3) as usize;
        kills.push((monotonic_ns(), victim));
        match victim {
            0 => stack.supervisor.kill(),
            1 => stack.driver.kill(),
            _ => stack.agent.kill(),
        }
        // systemd's RestartSec, randomised.
        pause(&mut seen, Duration::from_secs_f64(rng.range(0.0, 0.3)));
        let restarted = Instant::now();
        let what = ["the supervisor", "the driver", "the fleet agent"][victim];
        let label = format!("{what} back after restart {}", restarts[victim] + 1);
        if victim == 2 {
            while let Ok(Some(_)) = telemetry.try_recv() {}
            stack.restart_agent(CHAOS_ROBOT, &endpoint);
            wait_for(Duration::from_secs(20), &label, || {
                telemetry.try_recv().ok().flatten()
            });
        } else {
            let (beats, pid) = if victim == 0 {
                stack.restart_supervisor();
                (&supervisor_beats, stack.supervisor.pid())
            } else {
                stack.restart_driver();
                (&driver_beats, stack.driver.pid())
            };
            wait_for(Duration::from_secs(20), &label, || {
                std::iter::from_fn(|| next(beats)).find(|b| b.pid == pid)
            });
        }
        back_ms.push(restarted.elapsed().as_secs_f64() * 1e3);
        restarts[victim] += 1;
    }
    pause(&mut seen, Duration::from_millis(200));
    stop.store(true, Ordering::Relaxed);
    let sent = policy.join().unwrap();
    drop((
        states,
        events,
        driver_beats,
        supervisor_beats,
        node,
        telemetry,
        fleet,
    ));
    let report = stack.stop();
    // No motor above the firmware's 60 °C cutoff. The software tiers trip at 59 °C, but a
    // driver killed just before a trip leaves its servos their last goal and their firmware
    // backstops until the next driver reads the trip record (by design: nothing else talks to
    // them): 0.5 s of real time, which at ×30 is 15 s of heating at full load, enough to reach
    // the cutoff, which then holds the winding within a step of it.
    let hottest = check_left_arm_report(&report, 60.1);
    let bus = &report["buses"][0];
    let epoch = bus["epoch_monotonic_ns"].as_u64().unwrap();
    let sim_s = |ns: u64| ns.saturating_sub(epoch) as f64 * 1e-9;
    let line = &bus["line"]["faults"];
    let (dropped, corrupted) = (
        line["instructions_dropped"].as_u64().unwrap(),
        line["instructions_corrupted"].as_u64().unwrap(),
    );

    // The latch: from the torque-off that followed the first trip, nothing turned a servo of
    // the bus on or sent it a goal, through every restart to the end of the run.
    let trip = seen
        .iter()
        .find(|e| e.kind() == Some(EventKind::ThermalTrip));
    let off_at = trip.and_then(|trip| {
        bus["torque_off_broadcasts_s"]
            .as_array()?
            .iter()
            .filter_map(serde_json::Value::as_f64)
            .find(|&t| t >= sim_s(trip.timestamp_ns))
    });
    let mut writes_to_latched = 0;
    for servo in bus["servos"].as_array().unwrap() {
        let after = |key: &str| {
            servo[key]
                .as_f64()
                .is_some_and(|t| off_at.is_some_and(|off| t > off))
        };
        if after("last_goal_write_s") || after("last_torque_on_s") {
            writes_to_latched += 1;
            eprintln!("written after the latch at {off_at:?} s: {servo}");
        }
    }

    // Torque reductions: the servo holds the reduced limit within 100 ms of the announcement.
    let config = bus_driver::LoadedConfig::embedded().unwrap();
    let ids: Vec<u64> = config.config.bus[0]
        .servo
        .iter()
        .map(|s| u64::from(s.id))
        .collect();
    let changes: Vec<(f64, u64, f64)> = bus["torque_limit_changes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            (
                c["t_s"].as_f64().unwrap(),
                c["id"].as_u64().unwrap(),
                c["permille"].as_f64().unwrap(),
            )
        })
        .collect();
    let (mut confirmed, mut overtaken, mut late) = (Vec::new(), 0, Vec::new());
    for e in seen
        .iter()
        .filter(|e| e.kind() == Some(EventKind::TorqueReduced))
    {
        let (t, id, limit) = (
            sim_s(e.timestamp_ns),
            ids[e.joint as usize],
            f64::from(e.value) * 10.0,
        );
        let in_force = changes
            .iter()
            .rfind(|c| c.1 == id && c.0 <= t)
            .is_some_and(|c| c.2 <= limit + 0.5);
        let landed = changes
            .iter()
            .find(|c| c.1 == id && c.0 >= t - 0.005 && c.0 <= t + 0.1 && c.2 <= limit + 0.5);
        if in_force {
            confirmed.push(0.0);
        } else if let Some(c) = landed {
            confirmed.push((c.0 - t).max(0.0) * 1e3);
        } else {
            let window =
                |ns: u64| ns + 100_000_000 >= e.timestamp_ns && ns <= e.timestamp_ns + 100_000_000;
            let killed = kills.iter().any(|&(ns, victim)| victim < 2 && window(ns));
            let superseded = seen.iter().any(|o| {
                o.timestamp_ns >= e.timestamp_ns
                    && o.timestamp_ns <= e.timestamp_ns + 100_000_000
                    && match o.kind() {
                        Some(EventKind::TorqueRestored) => o.joint == e.joint,
                        Some(
                            EventKind::ThermalTrip
                            | EventKind::FirmwareProtection
                            | EventKind::OutputLost
                            | EventKind::DriverTrip,
                        ) => true,
                        _ => false,
                    }
            });
            if killed || superseded {
                overtaken += 1;
            } else {
                late.push((e.joint, t, limit));
            }
        }
    }
    eprintln!(
        "chaos seed {seed:#x}, {seconds} s: {} supervisor, {} driver and {} fleet-agent kills, every restart back \
         (p50 {:.0} ms, max {:.0} ms to the first heartbeat, or telemetry from the agent), {sent} wild goal frames; \
         host instructions dropped {dropped}, corrupted {corrupted}; hottest motor {hottest:.1} °C, no goal outside a \
         calibrated range on the wire; trip at {:?} s (bus off at {off_at:?} s), {writes_to_latched} servos written \
         after the latch; events {:?}; \
         {} torque reductions holding on the servo (p50 {:.1} ms, max {:.1} ms), {overtaken} overtaken within 100 ms, \
         {} late",
        restarts[0],
        restarts[1],
        restarts[2],
        quantile(&back_ms, 0.5),
        quantile(&back_ms, 1.0),
        trip.map(|t| sim_s(t.timestamp_ns)),
        event_counts(&seen),
        confirmed.len(),
        quantile(&confirmed, 0.5),
        quantile(&confirmed, 1.0),
        late.len()
    );
    assert!(restarts.iter().all(|&n| n >= 1), "{restarts:?}");
    assert!(
        dropped > 0 && corrupted > 0,
        "the line faults were injected"
    );
    assert!(trip.is_some(), "the overheat set-up never tripped the bus");
    assert!(off_at.is_some(), "the trip did not turn the bus off");
    assert_eq!(writes_to_latched, 0, "a latched bus was written to");
    assert!(!confirmed.is_empty(), "no torque reduction was exercised");
    assert!(
        late.is_empty(),
        "reductions not holding within 100 ms: {late:?}"
    );
}

/// The pid of `nori up`'s child `binary` on `domain` (its command line names both).
fn child_pid(binary: &str, domain: &str) -> Option<i32> {
    let program = format!("/{binary}");
    let ours = |args: &[String]| {
        args.first().is_some_and(|a| a.ends_with(&program)) && args.iter().any(|a| a == domain)
    };
    nori_tests::processes(ours)
        .first()
        .map(|(pid, _)| *pid as i32)
}

/// A wild operator of the body until `stop`: twists renewed every 50 ms for a while, within
/// and beyond the base's limits, now and then NaN, stale or from the future, with silences
/// longer than the command timeout; lift heights within and beyond its travel, or NaN.
fn wild_body(domain: String, seed: u64, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<u64> {
    std::thread::spawn(move || {
        use telemetry::motion::{BaseCommand, LiftCommand};
        let node = Plane::open(&domain, "test-wild-body").unwrap();
        let base = node.publisher(&plane::BASE_COMMAND).unwrap();
        let lift = node.publisher(&plane::LIFT_COMMAND).unwrap();
        let mut rng = Rng::new(seed);
        let (mut seq, mut sent) = (0, 0);
        while !stop.load(Ordering::Relaxed) {
            let (mut v, mut w) = (rng.range(-0.3, 0.3) as f32, rng.range(-1.5, 1.5) as f32);
            let mut skew_ns: i64 = 0;
            match rng.below(10) {
                0 => v = f32::NAN,
                1 => w = f32::INFINITY,
                2 => skew_ns = -1_000_000_000,
                3 => skew_ns = 1_000_000_000,
                4 => {
                    std::thread::sleep(Duration::from_secs_f64(rng.range(0.3, 1.0)));
                    continue;
                }
                _ => {}
            }
            if rng.chance(0.3) {
                let height = match rng.below(5) {
                    0 => f32::NAN,
                    1 => rng.range(-0.2, 1.0) as f32,
                    _ => rng.range(0.0, 0.6) as f32,
                };
                seq += 1;
                let c = LiftCommand {
                    seq,
                    timestamp_ns: monotonic_ns(),
                    height_m: height,
                    kind: telemetry::motion::LIFT_COMMAND_GOAL,
                };
                let _ = publish(&lift, &c);
            }
            let until = Instant::now() + Duration::from_secs_f64(rng.range(0.2, 2.0));
            while Instant::now() < until && !stop.load(Ordering::Relaxed) {
                seq += 1;
                let c = BaseCommand {
                    seq,
                    timestamp_ns: monotonic_ns().saturating_add_signed(skew_ns),
                    linear_m_s: v,
                    angular_rad_s: w,
                };
                if publish(&base, &c).is_ok() {
                    sent += 1;
                }
                std::thread::sleep(Duration::from_millis(50));
            }
        }
        sent
    })
}

/// Seeded chaos on the whole body for `NORI_BODY_CHAOS_SECONDS` (default 60 s): `nori up` (both
/// arms, the wheels, the lift, the base and its lidar), a wild operator of the base and the
/// lift, and SIGKILLs of nori-base, nori-lift, the driver and the supervisor at random moments
/// (`nori up` starts each again, as systemd would). Whatever happens: the base never runs into
/// anything (the simulator counts bumps); it is never driven beyond its limits, nor the lift's
/// goal outside its soft limits (every state frame seen); after every nori-base kill the
/// wheels are still within the driver's wheel timeout and a wheel's stopping. A killed driver
/// leaves the wheels at their last speed until a driver sets them up again (the servos have no
/// command watchdog): that time is measured and bounded by the restart (500 ms, as systemd's)
/// and the wheels' set-up coming first, and the protective field counts it in its reaction,
/// turns included, so the blind travel still ends short of what the lidar saw. (The first run
/// of this test, before the field counted it and guarded turns, ran the base into a table leg
/// twice in 40 s, and a dead driver left the wheels turning for up to 2.2 s.)
#[test]
fn a_seeded_body_chaos_run_keeps_the_base_and_the_lift_safe() {
    let _turn = serial();
    let seed = std::env::var("NORI_CHAOS_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(0xB0D1_C4A0_u64);
    let seconds: f64 = std::env::var("NORI_BODY_CHAOS_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(60.0);
    let robot = nori_tests::WholeRobot::start("body-chaos");
    let domain = robot.domain.clone();
    let node = Plane::open(&domain, "test").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    let bases = node.subscriber(&plane::BASE_STATE).unwrap();
    let lifts = node.subscriber(&plane::LIFT_STATE).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let operator = wild_body(domain.clone(), seed ^ 1, stop.clone());
    const VICTIMS: [&str; 4] = ["nori-base", "nori-lift", "bus-driver", "supervisor"];
    let mut rng = Rng::new(seed);
    let mut kills = [0u32; 4];
    // Per kill of nori-base (or the driver): when, the driver's cycle then, and when the wheels
    // were first seen still (after a driver kill: when the new driver, which stops the wheels
    // in its set-up before its first cycle, published its first frame; the base is driven
    // again from then on).
    let mut wheel_stops: Vec<(usize, u64, u64, Option<u64>)> = Vec::new();
    let mut driver_seq = 0;
    let (mut base_frames, mut lift_frames, mut overdriven, mut bad_lift_goals) = (0u64, 0u64, 0, 0);
    let (mut most_v, mut most_w) = (0f32, 0f32);
    let start = Instant::now();
    let mut next_kill = start + Duration::from_secs_f64(rng.range(2.0, 5.0));
    while start.elapsed().as_secs_f64() < seconds {
        std::thread::sleep(Duration::from_millis(5));
        while let Some(b) = next(&bases) {
            base_frames += 1;
            let (v, w) = (b.commanded_linear_m_s, b.commanded_angular_rad_s);
            most_v = most_v.max(v.abs());
            most_w = most_w.max(w.abs());
            if !(v.abs() <= 0.2 + 1e-4 && w.abs() <= 1.0 + 1e-4) {
                overdriven += 1;
            }
        }
        while let Some(l) = next(&lifts) {
            lift_frames += 1;
            if !(l.goal_m.is_nan() || (0.01 - 1e-4..=0.75 + 1e-4).contains(&l.goal_m)) {
                bad_lift_goals += 1;
            }
        }
        if let Some(s) = newest(&states) {
            driver_seq = s.seq;
            let still = s.joint_count == 18
                && s.joints[16].is_valid()
                && s.joints[17].is_valid()
                && s.joints[16].velocity_rad_s.abs() < 0.05
                && s.joints[17].velocity_rad_s.abs() < 0.05;
            for (victim, at, seq, done) in wheel_stops.iter_mut().filter(|w| w.3.is_none()) {
                let restarted = *victim == 2 && s.seq < *seq;
                if s.timestamp_ns > *at && (restarted || (*victim == 0 && still)) {
                    *done = Some(s.timestamp_ns);
                }
            }
        }
        // No kill in the last 3 s: every one's aftermath is seen.
        if Instant::now() >= next_kill && start.elapsed().as_secs_f64() < seconds - 3.0 {
            let victim = rng.below(4) as usize;
            if let Some(pid) = child_pid(VICTIMS[victim], &domain) {
                let _ = nix::sys::signal::kill(
                    nix::unistd::Pid::from_raw(pid),
                    nix::sys::signal::Signal::SIGKILL,
                );
                kills[victim] += 1;
                if victim == 0 || victim == 2 {
                    wheel_stops.push((victim, monotonic_ns(), driver_seq, None));
                }
            }
            next_kill = Instant::now() + Duration::from_secs_f64(rng.range(1.0, 4.0));
        }
    }
    stop.store(true, Ordering::Relaxed);
    let sent = operator.join().unwrap();
    drop((states, bases, lifts, node));
    let report = robot.stop();
    let base = report["buses"]
        .as_array()
        .unwrap()
        .iter()
        .find_map(|b| b["base"].as_object())
        .unwrap()
        .clone();
    let ms =
        |(_, at, _, done): &(usize, u64, u64, Option<u64>)| done.map(|t| (t - at) as f64 * 1e-6);
    let after = |who: usize| -> Vec<f64> {
        wheel_stops
            .iter()
            .filter(|w| w.0 == who)
            .map(|w| ms(w).unwrap_or(f64::INFINITY))
            .collect()
    };
    let (after_base, after_driver) = (after(0), after(2));
    eprintln!(
        "body chaos seed {seed:#x}, {seconds} s: kills {:?} of {VICTIMS:?}; {sent} base commands sent; \
         {base_frames} base and {lift_frames} lift states seen, most driven {most_v:.3} m/s {most_w:.3} rad/s, \
         {overdriven} beyond the limits, {bad_lift_goals} lift goals outside the soft limits; base travelled \
         {:.2} m, bumps {}; wheels still after a nori-base kill (ms) {after_base:?}, stopped by the new driver after a driver kill {after_driver:?}; \
         lift {}",
        kills,
        base["travelled_m"].as_f64().unwrap(),
        base["bumps"],
        report["lift"],
    );
    assert!(
        kills.iter().all(|&k| k >= 1),
        "every victim killed: {kills:?}"
    );
    assert!(
        base["travelled_m"].as_f64().unwrap() > 1.0,
        "the base was driven"
    );
    assert_eq!(base["bumps"], 0, "the base ran into something: {base:?}");
    assert_eq!(overdriven, 0);
    assert_eq!(bad_lift_goals, 0);
    assert!(most_v > 0.15, "the operator drove the base near its limit");
    // The driver's wheel timeout (200 ms), a wheel's stop from 3 rad/s and the feedback's
    // period: 500 ms. A frame from before the kill does not count (the test saw them after).
    for t in &after_base {
        assert!(
            *t <= 500.0,
            "wheels still {t} ms after nori-base died: {after_base:?}"
        );
    }
    // A dead driver: the restart's 500 ms, the new driver's start and the wheels' set-up, first
    // of all (measured about 0.65 s; the field counts 0.7 s, `driver-restart-ms`), with a loaded
    // machine's slack. Bounded by nothing but the restart: the servos have no watchdog.
    for t in &after_driver {
        assert!(
            *t <= 1200.0,
            "wheels stopped only {t} ms after the driver died: {after_driver:?}"
        );
    }
}
