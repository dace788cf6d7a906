//! Heartbeats both ways, with the real processes: a supervisor that dies leaves the driver in its
//! safe state within the heartbeat bound (goals refused) until a supervisor is back; a driver
//! that dies is reported lost by the supervisor.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{binary, newest_read, scratch, wait_for, Proc};
use std::time::Duration;
use telemetry::clock::monotonic_ns;
use telemetry::frames::{EventKind, STATE_FLAG_SAFE_STATE};
use telemetry::plane::{self, newest, next, publish, Plane};
use telemetry::{GoalFrame, JointState};

#[test]
fn safe_state_follows_the_supervisor_and_a_lost_driver_is_reported() {
    let dir = scratch("heartbeats");
    let domain = format!("nori_hb_{}", std::process::id());
    let dev = dir.join("dev");
    let d = dev.to_str().unwrap();
    let _sim = Proc::spawn(
        "simulator",
        &binary("nori"),
        &["sim", "serve", "--bus", "left_arm", "--dir", d],
        &dir.join("sim.log"),
    );
    let supervisor_args = ["--domain", domain.as_str(), "--status-every", "0"];
    let mut supervisor = Proc::spawn(
        "supervisor",
        &binary("supervisor"),
        &supervisor_args,
        &dir.join("supervisor.log"),
    );
    let driver_args = [
        "--bus",
        "left_arm",
        "--device-dir",
        d,
        "--domain",
        domain.as_str(),
        "--status-every",
        "0",
    ];
    let mut driver = Proc::spawn(
        "bus-driver",
        &binary("bus-driver"),
        &driver_args,
        &dir.join("driver.log"),
    );
    let node = Plane::open(&domain, "test").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    let events = node.subscriber(&plane::EVENTS).unwrap();
    let goals = node.publisher(&plane::GOALS).unwrap();
    let driving = |s: &JointState| {
        s.flags & STATE_FLAG_SAFE_STATE == 0 && s.joints().iter().all(|j| j.torque_enabled == 1)
    };
    wait_for(
        Duration::from_secs(20),
        "the driver driving under supervision",
        || newest(&states).filter(driving),
    );

    // SIGKILL the supervisor: the driver's frames carry the safe-state flag within the bound.
    let killed_at = monotonic_ns();
    supervisor.kill();
    let safe = wait_for(Duration::from_secs(2), "the safe state", || {
        std::iter::from_fn(|| next(&states)).find(|s| s.flags & STATE_FLAG_SAFE_STATE != 0)
    });
    let reaction_ms = (safe.timestamp_ns.saturating_sub(killed_at)) as f64 * 1e-6;
    eprintln!("safe state {reaction_ms:.1} ms after the supervisor was killed (bound 50 ms)");
    // The bound (50 ms) after a heartbeat at most 5 ms old, applied in the next 5 ms cycle,
    // plus 40 ms of this shared VM's scheduling slack (see crash_isolation.rs).
    // (Not before the bound counted from the last heartbeat sent: crash_isolation.rs.)
    assert!(
        reaction_ms <= 100.0,
        "safe state after {reaction_ms} ms (bound 50 ms, ceiling 100 ms)"
    );

    // In the safe state goals are refused: the elbow does not move.
    let mut g = GoalFrame {
        joint_count: 8,
        mask: 1 << 3,
        ..GoalFrame::default()
    };
    g.position_rad[3] = -1.0;
    for _ in 0..20 {
        g.timestamp_ns = monotonic_ns();
        publish(&goals, &g).unwrap();
        std::thread::sleep(Duration::from_millis(10));
    }
    let elbow = wait_for(Duration::from_secs(1), "a frame", || {
        newest_read(&states, 3)
    });
    assert!(
        elbow.position_rad > -0.3,
        "a goal acted on without a supervisor: {}",
        elbow.position_rad
    );

    // A supervisor again: the driver leaves the safe state and goals move the elbow.
    let _supervisor = Proc::spawn(
        "supervisor",
        &binary("supervisor"),
        &supervisor_args,
        &dir.join("supervisor2.log"),
    );
    wait_for(Duration::from_secs(10), "driving again", || {
        newest(&states).filter(driving)
    });
    wait_for(Duration::from_secs(10), "the elbow at its goal", || {
        g.timestamp_ns = monotonic_ns();
        publish(&goals, &g).unwrap();
        std::thread::sleep(Duration::from_millis(20));
        newest(&states).filter(|s| (s.joints[3].position_rad + 1.0).abs() < 0.05)
    });

    // SIGKILL the driver: the supervisor reports it lost.
    while next(&events).is_some() {}
    driver.kill();
    wait_for(Duration::from_secs(2), "DriverLost", || {
        std::iter::from_fn(|| next(&events)).find(|e| e.kind() == Some(EventKind::DriverLost))
    });
    let _ = std::fs::remove_dir_all(&dir);
}
