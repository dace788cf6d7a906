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
    check_left_arm_report, free_endpoint, plane_files, quantile, scratch, serial, wait_for,
    ArmStack, Rng,
};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::config::ProcessConfig;
use telemetry::frames::{EventKind, SupervisorEvent, STATE_FLAG_SAFE_STATE};
use telemetry::plane::{self, newest, next, publish, Plane};
use telemetry::{GoalFrame, JointState};

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
#[allow(
    clippy::too_many_lines,
    reason = "one scenario read start to end; to be split into phases (#37)"
)]
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
            // Restored after it, or a bus turned off within 100 ms either side (a reduction
            // announced just after its bus's trip cannot land: the torque is off).
            let after = |o: &SupervisorEvent| {
                o.timestamp_ns >= e.timestamp_ns && o.timestamp_ns <= e.timestamp_ns + 100_000_000
            };
            let superseded = seen.iter().any(|o| match o.kind() {
                Some(EventKind::TorqueRestored) => after(o) && o.joint == e.joint,
                Some(
                    EventKind::ThermalTrip
                    | EventKind::FirmwareProtection
                    | EventKind::OutputLost
                    | EventKind::DriverTrip,
                ) => window(o.timestamp_ns),
                _ => false,
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

/// A wild driver of the base until `stop`: twists renewed every 50 ms for a while, within and
/// beyond the base's limits, now and then NaN, stale or from the future, with silences longer
/// than the command timeout.
fn wild_base(domain: String, seed: u64, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<u64> {
    std::thread::spawn(move || {
        use telemetry::motion::BaseCommand;
        let node = Plane::open(&domain, "test-wild-base").unwrap();
        let base = node.publisher(&plane::BASE_COMMAND).unwrap();
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

/// The hand under the lift column in the body's chaos run, m above its lower switch.
const LIFT_OBSTACLE_M: f64 = 0.3;

/// A policy streaming the lift's goal until `stop`, every goal re-sent every 60 ms (as a plan
/// or a teleoperator streams it). First up past the hand (0.55 m, until the lift reads 0.45 m)
/// and down onto it (0.1 m, 8 s), then `scripted` is raised; then heights held 4–12 s, about
/// half of them below the hand, now and then NaN or beyond its travel, and before two in five
/// of the changes the operator's release (`nori lift release`). Returns (goals, releases)
/// sent.
fn streamed_lift(
    domain: String,
    seed: u64,
    stop: Arc<AtomicBool>,
    scripted: Arc<AtomicBool>,
) -> std::thread::JoinHandle<(u64, u64)> {
    std::thread::spawn(move || {
        use telemetry::motion::{LiftCommand, LIFT_COMMAND_GOAL, LIFT_COMMAND_RELEASE};
        let node = Plane::open(&domain, "test-streamed-lift").unwrap();
        let lift = node.publisher(&plane::LIFT_COMMAND).unwrap();
        let states = node.subscriber(&plane::LIFT_STATE).unwrap();
        let mut rng = Rng::new(seed);
        let (mut seq, mut goals, mut releases) = (0, 0, 0);
        let mut send = |height_m: f32, kind: u32| {
            seq += 1;
            let c = LiftCommand {
                seq,
                timestamp_ns: monotonic_ns(),
                height_m,
                kind,
            };
            publish(&lift, &c).is_ok()
        };
        let running = || !stop.load(Ordering::Relaxed);
        let up_by = Instant::now() + Duration::from_secs(40);
        while running() && Instant::now() < up_by {
            goals += u64::from(send(0.55, LIFT_COMMAND_GOAL));
            std::thread::sleep(Duration::from_millis(60));
            if newest(&states).is_some_and(|l| l.height_m >= 0.45) {
                break;
            }
        }
        let down_until = Instant::now() + Duration::from_secs(8);
        while running() && Instant::now() < down_until {
            goals += u64::from(send(0.1, LIFT_COMMAND_GOAL));
            std::thread::sleep(Duration::from_millis(60));
        }
        scripted.store(true, Ordering::Relaxed);
        while running() {
            let height = match rng.below(10) {
                0 => f32::NAN,
                1 => rng.range(-0.2, 1.0) as f32,
                2..=5 => rng.range(0.0, LIFT_OBSTACLE_M - 0.05) as f32,
                _ => rng.range(LIFT_OBSTACLE_M + 0.05, 0.7) as f32,
            };
            if rng.chance(0.4) && send(f32::NAN, LIFT_COMMAND_RELEASE) {
                releases += 1;
            }
            let until = Instant::now() + Duration::from_secs_f64(rng.range(4.0, 12.0));
            while running() && Instant::now() < until {
                goals += u64::from(send(height, LIFT_COMMAND_GOAL));
                std::thread::sleep(Duration::from_millis(60));
            }
        }
        (goals, releases)
    })
}

/// An operator's stop pressed in Nori Lab: when the press the supervisor heard was sent, and
/// when the resume was.
#[derive(Debug, Clone, Copy)]
struct StopPressed {
    pressed_ns: u64,
    resumed_ns: u64,
}

/// What the teleoperator did and what the lab answered.
#[derive(Debug, Default)]
struct Teleoperation {
    commands: u64,
    taken: u64,
    refused: std::collections::BTreeMap<String, u64>,
    ended: std::collections::BTreeMap<String, u64>,
    lab_kills: u32,
    unheard_presses: u32,
    stops: Vec<StopPressed>,
}

impl Teleoperation {
    /// Tallies the lab's messages.
    fn tally(&mut self, messages: Vec<serde_json::Value>) {
        for m in messages {
            match (m["type"].as_str(), m["ok"].as_bool()) {
                (Some("reply"), Some(true)) if m["to"].is_null() => self.taken += 1,
                (Some("reply"), Some(false)) => {
                    let why = m["refused"].as_str().unwrap_or("other").to_string();
                    *self.refused.entry(why).or_default() += 1;
                }
                (Some("ended"), _) => {
                    let why = m["why"].as_str().unwrap_or("?").to_string();
                    *self.ended.entry(why).or_default() += 1;
                }
                _ => {}
            }
        }
    }

    /// Presses `button` until the supervisor is heard taking it; when the heard press was sent.
    fn press(&mut self, lab: &mut nori_tests::Lab, button: &str) -> u64 {
        loop {
            if !lab.linked() && lab.connect().is_err() {
                std::thread::sleep(Duration::from_millis(100));
                continue;
            }
            let sent_ns = monotonic_ns();
            if !lab.send(&serde_json::json!({ "type": button })) {
                continue;
            }
            match lab.reply_to(button, Duration::from_secs(3)) {
                Some(r) if r["ok"] == true => return sent_ns,
                _ => self.unheard_presses += 1,
            }
        }
    }
}

/// A teleoperator in Nori Lab until `stop`: targets for one to three arm joints every 0.2–1 s
/// (a tenth of them beyond a range's end), the dead-man's `alive` every 100 ms; every 15–25 s
/// the stop button, held 2 s, then resume (each pressed again until the supervisor is heard);
/// the lab SIGKILLed whenever `kill` is raised and started again 500 ms later, as systemd
/// would, and the page linked again.
fn teleoperator(
    mut lab: nori_tests::Lab,
    arms: Vec<(String, [f32; 2])>,
    seed: u64,
    stop: Arc<AtomicBool>,
    kill: Arc<AtomicBool>,
) -> std::thread::JoinHandle<Teleoperation> {
    std::thread::spawn(move || {
        let mut rng = Rng::new(seed);
        let mut t = Teleoperation::default();
        let mut next_target = Instant::now();
        let mut next_stop = Instant::now() + Duration::from_secs_f64(rng.range(8.0, 15.0));
        while !stop.load(Ordering::Relaxed) {
            if kill.swap(false, Ordering::Relaxed) {
                lab.proc.kill();
                t.lab_kills += 1;
                std::thread::sleep(Duration::from_millis(500));
                lab.restart();
            }
            if !lab.linked() && lab.connect().is_err() {
                std::thread::sleep(Duration::from_millis(100));
                continue;
            }
            let received = lab.receive();
            t.tally(received);
            lab.send(&serde_json::json!({"type": "alive"}));
            if Instant::now() >= next_target {
                let mut goals = serde_json::Map::new();
                for _ in 0..1 + rng.below(3) {
                    let (name, [lo, hi]) = &arms[rng.below(arms.len() as u64) as usize];
                    let beyond = if rng.chance(0.1) { 0.2 } else { -0.05 };
                    let q = rng.range(f64::from(*lo) - beyond, f64::from(*hi) + beyond);
                    goals.insert(name.clone(), q.into());
                }
                if lab.send(&serde_json::json!({"type": "joints", "goals": goals})) {
                    t.commands += 1;
                }
                next_target = Instant::now() + Duration::from_secs_f64(rng.range(0.2, 1.0));
            }
            if Instant::now() >= next_stop {
                let pressed_ns = t.press(&mut lab, "stop");
                std::thread::sleep(Duration::from_secs(2));
                let resumed_ns = t.press(&mut lab, "resume");
                t.stops.push(StopPressed {
                    pressed_ns,
                    resumed_ns,
                });
                next_stop = Instant::now() + Duration::from_secs_f64(rng.range(15.0, 25.0));
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        lab.proc.terminate(Duration::from_secs(5));
        t
    })
}

/// The arm joints' names and ranges in `layout` (grippers and wheels left out).
fn arm_joints(layout: &telemetry::frames::JointLayout) -> Vec<(String, [f32; 2])> {
    layout
        .joints()
        .iter()
        .filter(|j| j.role == telemetry::frames::JointRole::Joint as u8)
        .map(|j| (j.name().to_string(), j.range_rad))
        .collect()
}

/// The goals outside the calibrated ranges, or naming a wheel, in `frame`: (joint, goal).
fn goals_out_of_range(
    frame: &GoalFrame,
    layout: &telemetry::frames::JointLayout,
) -> Vec<(String, f32)> {
    let joints = layout.joints();
    (0..joints.len())
        .filter(|&i| frame.mask & (1 << i) != 0)
        .filter(|&i| {
            let [lo, hi] = joints[i].range_rad;
            let q = frame.position_rad[i];
            joints[i].role == telemetry::frames::JointRole::Wheel as u8
                || !(lo - 1e-3..=hi + 1e-3).contains(&q)
        })
        .map(|i| (joints[i].name().to_string(), frame.position_rad[i]))
        .collect()
}

/// The lift's largest travel while each stop was in force (from its height when the stop the
/// supervisor heard was pressed to the resume's press), m.
fn lift_travel_in_stops(lift: &[(u64, f32)], stops: &[StopPressed]) -> Vec<f64> {
    stops
        .iter()
        .filter_map(|s| {
            let at = lift
                .iter()
                .rev()
                .find(|(t, h)| *t <= s.pressed_ns && h.is_finite())?
                .1;
            let most = lift
                .iter()
                .filter(|(t, h)| *t > s.pressed_ns && *t < s.resumed_ns && h.is_finite())
                .map(|(_, h)| f64::from((h - at).abs()))
                .fold(0.0, f64::max);
            Some(most)
        })
        .collect()
}

/// The victims of the body's chaos run: `nori up`'s children, and the lab the test runs.
const BODY_VICTIMS: [&str; 6] = [
    "nori-base",
    "nori-lift",
    "bus-driver",
    "supervisor",
    "nori-lidar",
    "nori-lab",
];
/// Indices into [`BODY_VICTIMS`] after whose kill the wheels are watched.
const BASE: usize = 0;
const DRIVER: usize = 2;
const LIDAR: usize = 4;

/// What the body's chaos run saw on the state plane.
#[derive(Debug, Default)]
struct BodySeen {
    base_frames: u64,
    overdriven: u64,
    most_v: f32,
    most_w: f32,
    lift_frames: u64,
    bad_lift_goals: u64,
    obstructions: u64,
    lift: Vec<(u64, f32)>,
    goal_frames: u64,
    bad_goals: Vec<(String, f32)>,
    /// Lift state frames by state.
    lift_states: std::collections::BTreeMap<&'static str, u64>,
    /// Largest |goal − reading| of an arm joint outside the safe state, rad.
    most_lead: f32,
    /// Where it was seen: the joint, its goal and reading (rad), the frame's number.
    most_lead_at: Option<(String, f32, f32, u64)>,
    driver_seq: u64,
    lift_state: u8,
}

impl BodySeen {
    fn base(&mut self, b: &telemetry::motion::BaseState) {
        self.base_frames += 1;
        let (v, w) = (b.commanded_linear_m_s, b.commanded_angular_rad_s);
        self.most_v = self.most_v.max(v.abs());
        self.most_w = self.most_w.max(w.abs());
        if !(v.abs() <= 0.2 + 1e-4 && w.abs() <= 1.0 + 1e-4) {
            self.overdriven += 1;
        }
    }

    fn lift(&mut self, l: &telemetry::motion::LiftState) {
        self.lift_frames += 1;
        if !(l.goal_m.is_nan() || (0.01 - 1e-4..=0.75 + 1e-4).contains(&l.goal_m)) {
            self.bad_lift_goals += 1;
        }
        let obstructed = telemetry::motion::LIFT_OBSTRUCTED;
        if l.state == obstructed && self.lift_state != obstructed {
            self.obstructions += 1;
        }
        self.lift_state = l.state;
        *self
            .lift_states
            .entry(telemetry::motion::lift_state_name(l.state))
            .or_default() += 1;
        self.lift.push((l.timestamp_ns, l.height_m));
    }

    fn arms(&mut self, s: &JointState, layout: &telemetry::frames::JointLayout) {
        self.driver_seq = s.seq;
        if s.flags & STATE_FLAG_SAFE_STATE != 0 {
            return;
        }
        for (j, info) in s.joints().iter().zip(layout.joints()) {
            let lead = (j.goal_rad - j.position_rad).abs();
            if j.is_valid()
                && info.role == telemetry::frames::JointRole::Joint as u8
                && lead > self.most_lead
            {
                self.most_lead = lead;
                let name = info.name().to_string();
                self.most_lead_at = Some((name, j.goal_rad, j.position_rad, s.seq));
            }
        }
    }
}

/// Seeded chaos on the whole body for `NORI_BODY_CHAOS_SECONDS` (default 120 s): `nori up`
/// (both arms, the wheels, the lift with a hand under it at 0.3 m, the base and its lidar),
/// Nori Lab with a teleoperator in it who now and then presses the stop button, a wild driver
/// of the base, a policy streaming the lift's goal onto the hand, and SIGKILLs of nori-base,
/// nori-lift, the driver, the supervisor, nori-lidar and the lab at random moments (`nori up`
/// starts each of its own again, as systemd would; the test starts the lab again). Whatever
/// happens: the base never runs into anything (the simulator counts bumps), it is never driven
/// beyond its limits, nor the lift's goal outside its soft limits (every state frame seen);
/// no goal on the wire is outside a calibrated range; the hand is pressed at most one stall
/// stop at a time (the simulator's own count); the lift does not move while a stop is in
/// force; after every nori-base or nori-lidar kill the wheels are still within the bound. A
/// killed driver leaves the wheels at their last speed until a driver sets them up again (the
/// servos have no command watchdog): that time is measured and bounded by the restart (500
/// ms, as systemd's) and the wheels' set-up coming first, and the protective field counts it.
/// (The first run, before the field counted it and guarded turns, ran the base into a table
/// leg twice in 40 s, and a dead driver left the wheels turning for up to 2.2 s.)
#[test]
#[allow(
    clippy::too_many_lines,
    reason = "one scenario read start to end; to be split into phases (#37)"
)]
fn a_seeded_body_chaos_run_keeps_the_base_and_the_lift_safe() {
    let _turn = serial();
    let seed = std::env::var("NORI_CHAOS_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(0xB0D1_C4A0_u64);
    let seconds: f64 = std::env::var("NORI_BODY_CHAOS_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(120.0);
    let hand = LIFT_OBSTACLE_M.to_string();
    let robot = nori_tests::WholeRobot::start_with("body-chaos", &["--lift-obstacle-at", &hand]);
    let domain = robot.domain.clone();
    let node = Plane::open(&domain, "test").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    let bases = node.subscriber(&plane::BASE_STATE).unwrap();
    let lifts = node.subscriber(&plane::LIFT_STATE).unwrap();
    let goals = node.subscriber(&plane::GOALS).unwrap();
    let layouts = node.subscriber(&plane::LAYOUT).unwrap();
    let layout = wait_for(Duration::from_secs(5), "the layout", || newest(&layouts));
    let stop = Arc::new(AtomicBool::new(false));
    let kill_lab = Arc::new(AtomicBool::new(false));
    let lab = nori_tests::Lab::start(&domain, &robot.dir, &[]);
    let teleop = teleoperator(
        lab,
        arm_joints(&layout),
        seed ^ 3,
        stop.clone(),
        kill_lab.clone(),
    );
    let driver = wild_base(domain.clone(), seed ^ 1, stop.clone());
    // nori-lift is not killed until the policy has brought the lift down on the hand once.
    let scripted = Arc::new(AtomicBool::new(false));
    let policy = streamed_lift(domain.clone(), seed ^ 2, stop.clone(), scripted.clone());
    let mut rng = Rng::new(seed);
    let mut kills = [0u32; BODY_VICTIMS.len()];
    // Per kill of nori-base, the driver or the lidar: which, when, the driver's cycle then,
    // and when the wheels were first seen still (after a driver kill: when the new driver,
    // which stops the wheels in its set-up before its first cycle, published its first frame;
    // the base is driven again from then on).
    let mut wheel_stops: Vec<(usize, u64, u64, Option<u64>)> = Vec::new();
    let mut seen = BodySeen::default();
    let start = Instant::now();
    let mut next_kill = start + Duration::from_secs_f64(rng.range(2.0, 5.0));
    while start.elapsed().as_secs_f64() < seconds {
        std::thread::sleep(Duration::from_millis(5));
        while let Some(b) = next(&bases) {
            seen.base(&b);
        }
        while let Some(l) = next(&lifts) {
            seen.lift(&l);
        }
        while let Some(g) = next(&goals) {
            seen.goal_frames += 1;
            seen.bad_goals.extend(goals_out_of_range(&g, &layout));
        }
        if let Some(s) = newest(&states) {
            seen.arms(&s, &layout);
            let still = s.joint_count == 18
                && s.joints[16].is_valid()
                && s.joints[17].is_valid()
                && s.joints[16].velocity_rad_s.abs() < 0.05
                && s.joints[17].velocity_rad_s.abs() < 0.05;
            for (victim, at, seq, done) in wheel_stops.iter_mut().filter(|w| w.3.is_none()) {
                let restarted = *victim == DRIVER && s.seq < *seq;
                if s.timestamp_ns > *at && (restarted || (*victim != DRIVER && still)) {
                    *done = Some(s.timestamp_ns);
                }
            }
        }
        // No kill in the last 3 s: every one's aftermath is seen.
        if Instant::now() >= next_kill && start.elapsed().as_secs_f64() < seconds - 3.0 {
            let victim = rng.below(BODY_VICTIMS.len() as u64) as usize;
            if BODY_VICTIMS[victim] == "nori-lift" && !scripted.load(Ordering::Relaxed) {
                // Not yet (the draw is still made: the seed's sequence stays the same).
            } else if BODY_VICTIMS[victim] == "nori-lab" {
                kill_lab.store(true, Ordering::Relaxed);
                kills[victim] += 1;
            } else if let Some(pid) = child_pid(BODY_VICTIMS[victim], &domain) {
                let _ = nix::sys::signal::kill(
                    nix::unistd::Pid::from_raw(pid),
                    nix::sys::signal::Signal::SIGKILL,
                );
                kills[victim] += 1;
                if [BASE, DRIVER, LIDAR].contains(&victim) {
                    wheel_stops.push((victim, monotonic_ns(), seen.driver_seq, None));
                }
            }
            next_kill = Instant::now() + Duration::from_secs_f64(rng.range(1.0, 4.0));
        }
    }
    stop.store(true, Ordering::Relaxed);
    let sent = driver.join().unwrap();
    let (lift_goals, releases) = policy.join().unwrap();
    let teleop = teleop.join().unwrap();
    drop((states, bases, lifts, goals, layouts, node));
    let report = robot.stop();
    let base = report["buses"]
        .as_array()
        .unwrap()
        .iter()
        .find_map(|b| b["base"].as_object())
        .unwrap()
        .clone();
    let after = |who: usize| -> Vec<f64> {
        wheel_stops
            .iter()
            .filter(|w| w.0 == who)
            .map(|(_, at, _, done)| done.map_or(f64::INFINITY, |t| (t - at) as f64 * 1e-6))
            .collect()
    };
    let (after_base, after_driver, after_lidar) = (after(BASE), after(DRIVER), after(LIDAR));
    let stop_travel = lift_travel_in_stops(&seen.lift, &teleop.stops);
    let lift = &report["lift"];
    eprintln!(
        "body chaos seed {seed:#x}, {seconds} s: kills {kills:?} of {BODY_VICTIMS:?}; {sent} base commands, \
         {lift_goals} lift goals and {releases} releases sent; teleoperation {teleop:?}; \
         {} base and {} lift states seen, most driven {:.3} m/s {:.3} rad/s, {} beyond the limits, \
         {} lift goals outside the soft limits; {} goal frames on the wire, goals outside a range {:?}, \
         largest arm lead {:.3} rad; base travelled {:.2} m, bumps {}; wheels still after a nori-base kill (ms) \
         {after_base:?}, after a lidar kill {after_lidar:?}, stopped by the new driver after a driver kill \
         {after_driver:?}; lift {lift}, {} obstructions seen, lift state frames {:?}; lift travel while stopped (m) {stop_travel:?}",
        seen.base_frames,
        seen.lift_frames,
        seen.most_v,
        seen.most_w,
        seen.overdriven,
        seen.bad_lift_goals,
        seen.goal_frames,
        seen.bad_goals,
        seen.most_lead,
        base["travelled_m"].as_f64().unwrap(),
        base["bumps"],
        seen.obstructions,
        seen.lift_states,
    );
    assert!(
        kills.iter().all(|&k| k >= 1),
        "every victim killed: {kills:?}"
    );
    assert_eq!(teleop.lab_kills, kills[5]);
    assert_eq!(base["bumps"], 0, "the base ran into something: {base:?}");
    assert_eq!(seen.overdriven, 0);
    assert_eq!(seen.bad_lift_goals, 0);
    // The run means something only if the base moved: at least half a metre (CI's starved
    // debug build drove it 0.83 m in 120 s, a release build 1.48 m; the field and the blind
    // stops hold it back the more the machine is loaded), near its speed limit. Under an
    // emulator every process is several times slower (0.28 m at most 0.141 m/s under qemu):
    // reported above, not held.
    if let Some(emulator) = nori_tests::emulated() {
        eprintln!("under {emulator}: how far and how fast the base was driven are not held to bounds, and a new driver's stop of the wheels only to 10 s");
    } else {
        assert!(
            base["travelled_m"].as_f64().unwrap() > 0.5,
            "the base was driven"
        );
        assert!(
            seen.most_v > 0.15,
            "the operator drove the base near its limit"
        );
    }
    // The teleoperator drove the arms, and nothing on the wire was outside a range.
    assert!(teleop.taken > 20 && seen.goal_frames > 100, "{teleop:?}");
    assert!(
        seen.bad_goals.is_empty(),
        "goals outside the calibrated ranges: {:?}",
        seen.bad_goals
    );
    assert!(
        seen.most_lead < 0.5,
        "an arm's goal {} rad from its reading (joint, goal, reading, frame: {:?})",
        seen.most_lead,
        seen.most_lead_at
    );
    // The hand: met, and pressed at most one stall stop (150 ms, a period, the board's 10 ms
    // report) at a time, by the simulator's count.
    assert!(
        lift["presses"].as_u64().unwrap() >= 2 && seen.obstructions >= 1,
        "the lift came down on the hand too seldom: {lift}, {} obstructions seen",
        seen.obstructions
    );
    assert!(
        lift["longest_press_s"].as_f64().unwrap() <= 0.25,
        "the hand pressed too long at once: {lift}"
    );
    // Stops: the lift does not move while one is in force (30 mm/s for the allowance's turn
    // to reach it, a period and the board's deceleration: a few mm).
    assert!(teleop.stops.len() >= 3, "{teleop:?}");
    for t in &stop_travel {
        assert!(
            *t <= 0.01,
            "the lift moved {t} m during a stop: {stop_travel:?}"
        );
    }
    // The driver's wheel timeout (200 ms), a wheel's stop from 3 rad/s and the feedback's
    // period: 500 ms. A frame from before the kill does not count (the test saw them after).
    for t in &after_base {
        assert!(
            *t <= 500.0,
            "wheels still {t} ms after nori-base died: {after_base:?}"
        );
    }
    // A dead lidar: the scan's age bound (300 ms), a revolution (100 ms), braking from
    // 0.2 m/s at 1 m/s² and the wheels' own deceleration.
    for t in &after_lidar {
        assert!(
            *t <= 1000.0,
            "wheels still {t} ms after the lidar died: {after_lidar:?}"
        );
    }
    // A dead driver: the restart's 500 ms, the new driver's start and the wheels' set-up, first
    // of all (about 0.65 s alone; 0.64–1.16 s with the lab and every process on two cores: more
    // than the 0.7 s the field counts, `driver-restart-ms`, an open item in docs/hazards.md).
    // Bounded by nothing but the restart: the servos have no watchdog. Under an emulator the
    // new driver's start is the emulator's (1.2–5.6 s under qemu): a loose bound there still
    // catches a wheel that a new driver never stops.
    let bound = if nori_tests::emulated().is_some() {
        10_000.0
    } else {
        1500.0
    };
    for t in &after_driver {
        assert!(
            *t <= bound,
            "wheels stopped only {t} ms after the driver died: {after_driver:?}"
        );
    }
}
