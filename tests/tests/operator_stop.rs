//! The operator's stop with the real processes: `nori stop` puts the driver in its safe state,
//! where no goal moves the arm however fresh; a supervisor SIGKILLed and restarted finds the
//! stop in the trip record and keeps it; only `nori resume` ends it, after which goals move the
//! arm again.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{check_left_arm_report, newest_read, nori_ok as nori, wait_for, ArmStack};
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::frames::{STATE_FLAG_OPERATOR_STOP, STATE_FLAG_SAFE_STATE};
use telemetry::plane::{self, newest, Plane};
use telemetry::{GoalFrame, JointState};

#[test]
fn a_stop_holds_through_a_supervisor_restart_until_the_operator_resumes() {
    let mut stack = ArmStack::start("operator-stop", &[]);
    let node = Plane::open(&stack.domain, "test").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    let goals = node.publisher(&plane::GOALS).unwrap();
    let stopped = STATE_FLAG_SAFE_STATE | STATE_FLAG_OPERATOR_STOP;
    let driving = |s: &JointState| {
        s.joint_count == 8 && s.joints().iter().all(|j| j.is_valid()) && s.flags & stopped == 0
    };
    wait_for(Duration::from_secs(20), "the arm driven", || {
        newest(&states).filter(driving)
    });
    let layouts = node.subscriber(&plane::LAYOUT).unwrap();
    let layout = wait_for(Duration::from_secs(2), "the layout", || newest(&layouts));
    let elbow = layout.joint_index("left_elbow").unwrap();
    let [lo, hi] = layout.joints()[elbow].range_rad;
    // Fresh goals for the elbow every 10 ms for `for_ms`, to `rad`; the elbow's last position.
    let mut seq = 0;
    let mut drive = |rad: f32, for_ms: u64| -> f32 {
        let until = Instant::now() + Duration::from_millis(for_ms);
        while Instant::now() < until {
            seq += 1;
            let mut g = GoalFrame {
                seq,
                timestamp_ns: monotonic_ns(),
                joint_count: 8,
                mask: 1 << elbow,
                ..GoalFrame::default()
            };
            g.position_rad[elbow] = rad;
            plane::publish(&goals, &g).unwrap();
            std::thread::sleep(Duration::from_millis(10));
        }
        // A read that failed under load carries no position (a zero): the newest that did not.
        wait_for(Duration::from_secs(1), "an elbow reading", || {
            newest_read(&states, elbow)
        })
        .position_rad
    };
    let (a, b) = (lo + 0.3 * (hi - lo), lo + 0.7 * (hi - lo));
    let at_a = drive(a, 1500);
    assert!((at_a - a).abs() < 0.05, "driven to {a}: at {at_a}");

    let said = nori(&["stop"], &stack.domain);
    assert!(said.contains("stopped"), "{said}");
    wait_for(Duration::from_secs(1), "the stop in the frames", || {
        newest(&states).filter(|s| s.flags & stopped == stopped)
    });
    let held = drive(b, 1000);
    assert!(
        (held - at_a).abs() < 0.03,
        "moved during the stop: {at_a} → {held}"
    );
    let s = wait_for(Duration::from_secs(1), "a frame", || newest(&states));
    assert_eq!(s.flags & stopped, stopped);

    // The supervisor dies and comes back: the record holds the stop.
    stack.restart_supervisor();
    wait_for(
        Duration::from_secs(10),
        "the new supervisor's stop in the frames",
        || {
            let s = newest(&states)?;
            (s.flags & stopped == stopped).then_some(())
        },
    );
    let held = drive(b, 1500);
    assert!(
        (held - at_a).abs() < 0.03,
        "moved after the supervisor's restart: {at_a} → {held}"
    );
    let record = std::fs::read_to_string(stack.trips()).unwrap();
    assert!(
        record.contains(telemetry::latch::OPERATOR_STOP),
        "{record:?}"
    );

    let said = nori(&["resume"], &stack.domain);
    assert!(said.contains("resumed"), "{said}");
    wait_for(Duration::from_secs(2), "driving again", || {
        newest(&states).filter(driving)
    });
    let at_b = drive(b, 1500);
    assert!(
        (at_b - b).abs() < 0.05,
        "driven to {b} after the resume: {at_b}"
    );
    let record = std::fs::read_to_string(stack.trips()).unwrap();
    assert!(
        !record.contains(telemetry::latch::OPERATOR_STOP),
        "{record:?}"
    );
    drop((states, layouts, goals, node));
    let report = stack.stop();
    check_left_arm_report(&report, 60.0);
}

/// Nori Lab's stop button answers only what the supervisor showed it heard: with no supervisor
/// running, a stop is said to be unheard (the operator must not walk up to an arm that still
/// moves); with one, a stop is confirmed stopped, a second stop too (already stopped), and a
/// resume resumed.
#[test]
fn the_labs_stop_button_says_whether_a_supervisor_heard_it() {
    let dir = nori_tests::scratch("lab-stop-button");
    let domain = format!("nori_lab_stop_{}", std::process::id());
    let mut lab = nori_tests::Lab::start(&domain, &dir, &[]);
    lab.connect().unwrap();
    let press = |lab: &mut nori_tests::Lab, to: &str| {
        assert!(lab.send(&serde_json::json!({ "type": to })));
        lab.reply_to(to, Duration::from_secs(4))
            .unwrap_or_else(|| panic!("no reply to {to}"))
    };
    let unheard = press(&mut lab, "stop");
    assert_eq!(unheard["ok"], false, "{unheard}");
    assert!(
        unheard["error"].as_str().unwrap().contains("NO SUPERVISOR"),
        "{unheard}"
    );

    let mut supervisor = nori_tests::Proc::spawn(
        "supervisor",
        &nori_tests::binary("supervisor"),
        &[
            "--domain",
            &domain,
            "--trip-file",
            dir.join("trips").to_str().unwrap(),
        ],
        &dir.join("supervisor.log"),
    );
    std::thread::sleep(Duration::from_millis(500));
    for _ in 0..2 {
        let heard = press(&mut lab, "stop");
        assert_eq!(heard["ok"], true, "{heard}");
        assert!(
            heard["text"].as_str().unwrap().contains("stopped"),
            "{heard}"
        );
    }
    let resumed = press(&mut lab, "resume");
    assert_eq!(resumed["ok"], true, "{resumed}");
    assert_eq!(resumed["text"], "resumed", "{resumed}");
    supervisor.terminate(Duration::from_secs(5));
    lab.proc.terminate(Duration::from_secs(5));
}
