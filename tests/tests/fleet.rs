//! The fleet link on loopback: simulated robots (simulator, supervisor, driver, fleet agent as
//! separate processes) and the reference policy server, over zenoh.
//!
//! - Actions from the policy server reach the simulated servos of several robots at once, and a
//!   robot whose policy goes away holds.
//! - Malformed, other-version, non-finite, out-of-range, stale, future and replayed chunks are
//!   refused with their reason (counted in the agent's status) and move nothing.
//! - A killed agent takes its queued plan with it: nothing of it runs after the restart, and
//!   telemetry resumes.
//! - Observations carry the configured camera's JPEGs, fresh, and none once the camera dies.
//! - A policy that sees (`nori policy-server --seek-camera`) centres the red ball in the wrist
//!   camera's picture: camera → agent → server → action → arm, closed.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fleet::policy::Motion;
use fleet_agent::keys::robot_key;
use fleet_agent::schema::{decode, encode, ActionChunk, StateMsg, SCHEMA_VERSION};
use fleet_agent::zenoh::{self, Wait};
use nori_tests::{
    binary, check_left_arm_report, free_endpoint, newest_read, scratch, seeing_robot, serial,
    wait_for, ArmStack, Proc,
};
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::frames::{JointLayout, JointState};
use telemetry::plane::{self, newest, next, Plane};

const ELBOW: usize = 3;

fn session(listen: &str) -> zenoh::Session {
    nori_tests::listening_session(listen)
}

/// The agent's status, asked over zenoh.
fn status(session: &zenoh::Session, robot: &str) -> serde_json::Value {
    serde_json::to_value(nori_tests::agent_status(session, robot)).unwrap()
}

/// Waits until the robot's telemetry arrives over zenoh: the agent is on the fleet.
fn wait_online(session: &zenoh::Session, robot: &str) {
    let sub = session
        .declare_subscriber(robot_key(robot, "state"))
        .wait()
        .unwrap();
    wait_for(Duration::from_secs(20), &format!("{robot} online"), || {
        let s = sub.try_recv().ok().flatten()?;
        decode::<StateMsg>(&s.payload().to_bytes()).ok()
    });
}

fn driving(s: &JointState) -> bool {
    s.flags & telemetry::frames::STATE_FLAG_SAFE_STATE == 0
        && s.joints().iter().all(|j| j.is_valid())
}

#[test]
fn policy_actions_reach_the_servos_of_several_robots_and_a_robot_without_policy_holds() {
    let _turn = serial();
    let endpoint = free_endpoint();
    let dir = scratch("policy");
    let wave = Motion::Wave {
        joints: vec!["left_elbow".into()],
        centre: -0.9,
        amplitude: 0.35,
        period_s: 2.0,
    };
    let wave_at = |t_ns: u64| wave.target("left_elbow", t_ns).unwrap();
    let mut server = Proc::spawn(
        "policy-server",
        &binary("nori"),
        &[
            "policy-server",
            "--listen",
            &endpoint,
            "--joints",
            "left_elbow",
            "--centre=-0.9",
            "--amplitude",
            "0.35",
            "--period-s",
            "2",
            "--run-for",
            "120",
        ],
        &dir.join("policy-server.log"),
    );
    let mut robots: Vec<(String, ArmStack)> = ["a", "b"]
        .iter()
        .map(|tag| {
            let mut stack = ArmStack::start(&format!("fleet-{tag}"), &[]);
            let id = format!("test-robot-{tag}");
            stack.restart_agent(&id, &endpoint);
            (id, stack)
        })
        .collect();
    for (id, stack) in &robots {
        let node = Plane::open(&stack.domain, "test").unwrap();
        let states = node.subscriber(&plane::JOINT_STATE).unwrap();
        // The elbow's goal on the wire follows the wave (robot clock, the driver's cycle and the
        // agent's 10 ms forwarding behind it), through two periods.
        let mut seen = (f32::MAX, f32::MIN);
        let mut worst = 0f32;
        let mut samples = 0;
        let start = Instant::now();
        while start.elapsed() < Duration::from_secs(12) && (samples < 400 || seen.1 - seen.0 < 0.6)
        {
            for s in std::iter::from_fn(|| next(&states)) {
                let j = s.joints[ELBOW];
                if !driving(&s) || (j.goal_rad - wave_at(s.timestamp_ns)).abs() > 0.3 {
                    continue; // before the policy took over
                }
                samples += 1;
                seen = (seen.0.min(j.goal_rad), seen.1.max(j.goal_rad));
                worst = worst.max((j.goal_rad - wave_at(s.timestamp_ns)).abs());
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        assert!(samples >= 400, "{id}: {samples} cycles under the policy");
        assert!(
            seen.1 - seen.0 > 0.6,
            "{id}: the elbow's goal spanned only {seen:?}"
        );
        assert!(worst < 0.08, "{id}: goal {worst} rad off the wave");
        eprintln!("{id}: {samples} cycles followed the policy's wave, worst {worst:.3} rad off, goals {seen:?}");
    }
    // The policy goes away: the plan in force runs out (its last chunk's steps, 0.5 s, then
    // the 100 ms horizon), the goals stop changing, and the robot holds.
    let (_, served) = server.terminate(Duration::from_secs(5));
    eprintln!("policy server: {}", served.trim());
    let served: serde_json::Value = serde_json::from_str(served.trim()).unwrap();
    for (id, _) in &robots {
        assert!(
            served["robots"][id]["chunks"].as_u64().unwrap() > 20,
            "{served}"
        );
    }
    std::thread::sleep(Duration::from_millis(1000));
    for (id, stack) in &robots {
        let node = Plane::open(&stack.domain, "test").unwrap();
        let states = node.subscriber(&plane::JOINT_STATE).unwrap();
        let elbow = || {
            wait_for(Duration::from_secs(5), "a frame", || {
                newest_read(&states, ELBOW)
            })
        };
        let held = elbow();
        std::thread::sleep(Duration::from_millis(500));
        let later = elbow();
        assert_eq!(
            held.goal_rad, later.goal_rad,
            "{id}: goals kept changing without a policy"
        );
    }
    for (_, stack) in robots.drain(..) {
        let report = stack.stop();
        check_left_arm_report(&report, 60.0);
    }
}

/// A chunk moving the elbow to `target` from the present, for the layout's joints.
fn elbow_chunk(
    layout: &JointLayout,
    seq: u64,
    observation_ns: u64,
    target: f32,
    steps: u64,
) -> ActionChunk {
    let n = layout.joint_count as usize;
    let mut targets = vec![0.0; n * steps as usize];
    for k in 0..steps as usize {
        targets[k * n + ELBOW] = target;
    }
    ActionChunk {
        version: SCHEMA_VERSION,
        seq,
        observation_ns,
        step_offsets_ns: (1..=steps).map(|k| k * 20_000_000).collect(),
        joint_count: n as u16,
        joint_mask: 1 << ELBOW,
        targets,
        lift_m: Vec::new(),
        base_twist: Vec::new(),
    }
}

#[test]
#[allow(
    clippy::too_many_lines,
    reason = "one scenario read start to end; to be split into phases (#37)"
)]
fn bad_actions_are_refused_with_their_reason_and_a_killed_agent_leaves_nothing_queued() {
    let _turn = serial();
    let endpoint = free_endpoint();
    let fleet = session(&endpoint);
    let id = "test-robot-gate";
    let mut stack = ArmStack::start("fleet-gate", &[]);
    stack.restart_agent(id, &endpoint);
    let node = Plane::open(&stack.domain, "test").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    let layouts = node.subscriber(&plane::LAYOUT).unwrap();
    let layout = wait_for(Duration::from_secs(20), "the layout", || newest(&layouts));
    wait_for(Duration::from_secs(20), "driving", || {
        newest(&states).filter(driving)
    });
    wait_online(&fleet, id);
    let [lo, hi] = layout.joints[ELBOW].range_rad;
    let elbow = || {
        wait_for(Duration::from_secs(5), "the elbow read", || {
            newest_read(&states, ELBOW)
        })
    };
    let start_goal = elbow().goal_rad;
    let actions = robot_key(id, "actions");
    let put = |bytes: Vec<u8>| fleet.put(&actions, bytes).wait().unwrap();

    // The rogue's gallery. Robot time: the same CLOCK_MONOTONIC on this machine.
    let now = monotonic_ns();
    put(vec![SCHEMA_VERSION as u8, 0xff, 0xff, 0xff]);
    let mut other_version = elbow_chunk(&layout, 1, now, -1.0, 10);
    other_version.version = SCHEMA_VERSION + 1;
    put(encode(&other_version));
    put(encode(&elbow_chunk(&layout, 2, now, hi + 0.5, 10)));
    put(encode(&elbow_chunk(&layout, 3, now, f32::NAN, 10)));
    let mut short = elbow_chunk(&layout, 4, now, -1.0, 10);
    short.targets.pop();
    put(encode(&short));
    put(encode(&elbow_chunk(
        &layout,
        5,
        now - 2_000_000_000,
        -1.0,
        10,
    )));
    put(encode(&elbow_chunk(
        &layout,
        6,
        now + 5_000_000_000,
        -1.0,
        10,
    )));
    std::thread::sleep(Duration::from_millis(300));
    let after_bad = elbow();
    assert_eq!(
        after_bad.goal_rad, start_goal,
        "a refused chunk moved the elbow's goal"
    );

    // A good chunk, then the same bytes again (a replay).
    let target = (lo + hi) / 2.0;
    let good = encode(&elbow_chunk(&layout, 7, monotonic_ns(), target, 50));
    put(good.clone());
    std::thread::sleep(Duration::from_millis(50));
    put(good);
    wait_for(
        Duration::from_secs(10),
        "the elbow at the good chunk's target",
        || newest_read(&states, ELBOW).filter(|j| (j.position_rad - target).abs() < 0.05),
    );
    let st = status(&fleet, id);
    let rejected = &st["counters"]["actions_rejected"];
    for reason in [
        "malformed",
        "version",
        "out_of_range",
        "not_finite",
        "shape",
        "stale",
        "future",
        "replayed",
    ] {
        assert_eq!(rejected[reason].as_u64(), Some(1), "{reason}: {st}");
    }
    assert_eq!(st["counters"]["actions_accepted"].as_u64(), Some(1), "{st}");
    eprintln!("agent status after the rogue's gallery: {st}");

    // A long, slow plan; the agent is killed in the middle of it.
    let far = lo + 0.1 * (hi - lo);
    let mut plan = elbow_chunk(&layout, 8, monotonic_ns(), far, 100);
    for k in 0..100usize {
        let f = (k + 1) as f32 / 100.0;
        plan.targets[k * layout.joint_count as usize + ELBOW] = target + f * (far - target);
    }
    put(encode(&plan));
    std::thread::sleep(Duration::from_millis(600));
    stack.agent.kill();
    let killed_at = monotonic_ns();
    std::thread::sleep(Duration::from_millis(300));
    let held = elbow().goal_rad;
    assert!(
        (held - far).abs() > 0.1 && (held - target).abs() > 0.05,
        "the plan should have been under way: goal {held}, from {target} to {far}"
    );
    stack.restart_agent(id, &endpoint);
    wait_online(&fleet, id);
    // The plan's end time has passed now (2 s after it started); had it been kept anywhere,
    // the goal would have moved on. It holds.
    std::thread::sleep(Duration::from_millis(1500));
    let mut last_goal = None;
    let after_kill = std::iter::from_fn(|| next(&states))
        .filter(|s| s.timestamp_ns > killed_at + 100_000_000 && s.joints[ELBOW].is_valid());
    for s in after_kill {
        let g = s.joints[ELBOW].goal_rad;
        assert_eq!(
            g, held,
            "after the agent died the goal moved from {held} to {g}"
        );
        last_goal = Some(g);
    }
    assert!(last_goal.is_some(), "no state frames after the restart");
    let st = status(&fleet, id);
    assert_eq!(
        st["counters"]["actions_accepted"].as_u64(),
        Some(0),
        "a fresh agent: {st}"
    );
    assert!(
        st["counters"]["state_sent"].as_u64().unwrap() > 0,
        "telemetry resumed: {st}"
    );
    drop((states, layouts, node));
    let report = stack.stop();
    check_left_arm_report(&report, 60.0);
}

#[test]
fn observations_carry_the_cameras_jpegs_and_none_once_the_camera_dies() {
    let _turn = serial();
    let endpoint = free_endpoint();
    let id = "test-robot-eyes";
    let (stack, mut camera) = seeing_robot("fleet-images", id, &endpoint);
    let session = session(&endpoint);
    let observations = session
        .declare_subscriber(robot_key(id, "observation"))
        .wait()
        .unwrap();
    let take = |within: Duration| {
        let until = Instant::now() + within;
        let mut out = Vec::new();
        while Instant::now() < until {
            while let Ok(Some(s)) = observations.try_recv() {
                out.push(
                    decode::<fleet_agent::schema::ObservationMsg>(&s.payload().to_bytes()).unwrap(),
                );
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        out
    };
    wait_for(
        Duration::from_secs(30),
        "an observation with an image",
        || {
            take(Duration::from_millis(200))
                .iter()
                .any(|o| !o.images.is_empty())
                .then_some(())
        },
    );
    let seen = take(Duration::from_secs(2));
    let with: Vec<_> = seen.iter().filter(|o| !o.images.is_empty()).collect();
    // Every third observation carries one (observation-hz 30, image-every 3): ~20 in 2 s.
    assert!(
        (10..=30).contains(&with.len()),
        "{} of {} observations with an image",
        with.len(),
        seen.len()
    );
    for o in &with {
        let img = &o.images[0];
        assert_eq!(
            (
                img.camera.as_str(),
                img.encoding.as_str(),
                img.width,
                img.height
            ),
            ("left_wrist", "jpeg", 160, 120)
        );
        assert!(
            o.timestamp_ns.saturating_sub(img.capture_ns) <= 150_000_000,
            "an image {} ms older than its observation",
            (o.timestamp_ns - img.capture_ns) / 1_000_000
        );
        // A JPEG that decodes to the camera's picture size.
        let mut rgb = vec![0u8; camera::convert::rgb_len(160, 120)];
        camera::convert::to_rgb(
            telemetry::sensors::PixelFormat::Mjpeg,
            160,
            120,
            0,
            &img.data,
            &mut rgb,
        )
        .unwrap();
    }
    assert!(
        with.windows(2)
            .all(|w| w[0].images[0].seq < w[1].images[0].seq),
        "each carries a newer frame"
    );

    // The camera dies: observations go on, without images, and the status counts them stale.
    camera.kill();
    // What was queued before, and the last picture's 150 ms of validity, pass.
    take(Duration::from_millis(500));
    let after = take(Duration::from_secs(1));
    assert!(after.len() >= 15, "observations go on: {}", after.len());
    assert!(
        after.iter().all(|o| o.images.is_empty()),
        "no picture older than 150 ms"
    );
    let st = status(&session, id);
    assert!(
        st["counters"]["images_stale"].as_u64().unwrap() >= 5,
        "{st}"
    );
    assert!(
        st["counters"]["images_sent"].as_u64().unwrap() >= 10,
        "{st}"
    );
    drop(observations);
    drop(session);
    stack.stop();
}

/// The red ball's offset from the picture's centre in an RGB frame (normalised, −1..1), if seen.
fn red_offset(rgb: &[u8], w: usize, h: usize) -> Option<f32> {
    let (mut n, mut sx, mut sy) = (0usize, 0f64, 0f64);
    for (i, p) in rgb.chunks_exact(3).enumerate() {
        if p[0] > 150 && p[1] < 90 && p[2] < 90 {
            n += 1;
            sx += (i % w) as f64;
            sy += (i / w) as f64;
        }
    }
    (n >= 20).then(|| {
        let x = 2.0 * (sx / n as f64 + 0.5) / w as f64 - 1.0;
        let y = 2.0 * (sy / n as f64 + 0.5) / h as f64 - 1.0;
        x.hypot(y) as f32
    })
}

#[test]
fn a_policy_that_sees_centres_the_red_ball_in_the_wrist_cameras_picture() {
    let _turn = serial();
    let endpoint = free_endpoint();
    let id = "test-robot-seek";
    let (stack, mut camera) = seeing_robot("fleet-seek", id, &endpoint);
    let node = Plane::open(&stack.domain, "test").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    let goals = node.publisher(&plane::GOALS).unwrap();
    let frames = node
        .camera_subscriber("left_wrist", telemetry::plane::CameraStream::Rgb)
        .unwrap();
    let offset_now = || {
        let mut last = None;
        while let Ok(Some(sample)) = frames.receive() {
            last = Some(sample.payload().to_vec());
        }
        last.and_then(|rgb| red_offset(&rgb, 160, 120))
    };
    // The arm forward over the table, the ball off-centre in the wrist camera's picture.
    wait_for(Duration::from_secs(20), "the driver driving", || {
        newest(&states).filter(driving)
    });
    let mut goal = telemetry::frames::GoalFrame {
        joint_count: 8,
        mask: (1 << 0) | (1 << ELBOW),
        ..Default::default()
    };
    goal.position_rad[0] = -0.6;
    goal.position_rad[ELBOW] = -0.8;
    wait_for(Duration::from_secs(15), "the arm over the table", || {
        goal.seq += 1;
        goal.timestamp_ns = monotonic_ns();
        telemetry::plane::publish(&goals, &goal).unwrap();
        std::thread::sleep(Duration::from_millis(20));
        newest_read(&states, ELBOW).filter(|j| (j.position_rad + 0.8).abs() < 0.05)
    });
    std::thread::sleep(Duration::from_millis(1500));
    let before = wait_for(
        Duration::from_secs(5),
        "the ball in the wrist camera",
        offset_now,
    );
    assert!(before > 0.2, "the ball starts off-centre: {before}");

    let mut server = Proc::spawn(
        "policy-server",
        &binary("nori"),
        &[
            "policy-server",
            "--listen",
            &endpoint,
            "--seek-camera",
            "left_wrist",
            "--run-for",
            "60",
        ],
        &stack.dir.join("policy-server.log"),
    );
    // Within 30 s the ball is near the centre, and stays there.
    let session = session(&free_endpoint());
    let mut trace = Vec::new();
    let start = Instant::now();
    let mut reached = None;
    while start.elapsed() < Duration::from_secs(30) && reached.is_none() {
        std::thread::sleep(Duration::from_millis(250));
        let e = offset_now();
        trace.push(e.map(|e| (e * 100.0).round() / 100.0));
        reached = e.filter(|&e| e < 0.12);
    }
    let Some(reached) = reached else {
        let st = session
            .get(robot_key(id, "status"))
            .timeout(Duration::from_secs(2))
            .wait()
            .ok()
            .and_then(|r| r.recv().ok())
            .and_then(|r| r.result().ok().map(|s| s.payload().to_bytes().into_owned()))
            .and_then(|b| decode::<fleet_agent::schema::StatusMsg>(&b).ok());
        panic!("the ball was not centred in 30 s: offsets {trace:?}; agent status {st:?}");
    };
    std::thread::sleep(Duration::from_secs(2));
    let settled = wait_for(Duration::from_secs(5), "the ball in view", offset_now);
    eprintln!(
        "ball offset: {before:.2} at the start, {reached:.2} when reached, {settled:.2} 2 s later"
    );
    assert!(settled < 0.15, "it stays centred: {settled}");
    let (code, out) = server.terminate(Duration::from_secs(5));
    assert_eq!(code, Some(0));
    let report: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(report["robots"][id]["seek_calibrated"], true, "{report}");
    let (code, _) = camera.terminate(Duration::from_secs(5));
    assert_eq!(code, Some(0));
    drop((frames, goals, states, node));
    stack.stop();
}
