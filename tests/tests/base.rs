//! The base on the simulated robot, as on the robot: the simulator's wheels carry the base
//! through its room (the truth), the driver drives the two wheel servos, `nori-lidar` scans the
//! room from the moving base and `nori-base` turns velocity commands into wheel goals. The base
//! follows a velocity profile and its odometry agrees with where the simulator says it went;
//! commands that stop stop the wheels within the command timeout and the braking time; a
//! killed controller leaves no wheel turning beyond the driver's own timeout; driven at a wall,
//! the protective field stops it short of it.

#![allow(clippy::unwrap_used, clippy::expect_used)]

// The tests take turns (`serial`): each runs a whole stack and measures speeds and stopping
// times; two at once on two cores starved the controllers (a CI run saw a cruise dip in 9 of
// 40 samples: the driver's wheel timeout stopping wheels whose controller was starved).
use nori_tests::{binary, scratch, serial, wait_for, ArmStack, Proc};
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::frames::{EventKind, SupervisorEvent};
use telemetry::motion::{
    BaseCommand, BaseState, BASE_FLAG_FIELD_BLIND, BASE_FLAG_FIELD_STOPPED, BASE_FLAG_NOT_DRIVEN,
};
use telemetry::plane::{self, newest, next, Plane, Pub, Sub};
use telemetry::JointState;

/// The embedded base.toml's command timeout and braking, and the driver's wheel timeout.
const COMMAND_TIMEOUT: Duration = Duration::from_millis(250);
const BRAKE_M_S2: f64 = 1.0;
const WHEEL_TIMEOUT: Duration = Duration::from_millis(200);

struct Base {
    stack: ArmStack,
    lidar: Proc,
    controller: Proc,
    base_args: Vec<String>,
    starts: u32,
    commands: Pub<BaseCommand>,
    states: Sub<BaseState>,
    joints: Sub<JointState>,
    seq: u64,
    _node: Plane,
}

impl Base {
    /// The base's bus alone (the driver calls its wheels joints 0 and 1), the lidar and the
    /// controller (with `base_args`, e.g. a `--config`), the simulator given `sim_args`.
    fn start(tag: &str, sim_args: &[&str], base_args: &[&str]) -> Base {
        let mut stack = ArmStack::simulator_only_on(tag, "base", sim_args);
        stack.restart_supervisor();
        stack.restart_driver();
        let dev = stack.device_dir_with("lidar");
        let lidar = Proc::spawn(
            "nori-lidar",
            &binary("nori-lidar"),
            &["--device-dir", &dev, "--domain", &stack.domain],
            &stack.dir.join("lidar.log"),
        );
        let node = Plane::open(&stack.domain, "test").unwrap();
        let mut base = Base {
            commands: node.publisher(&plane::BASE_COMMAND).unwrap(),
            states: node.subscriber(&plane::BASE_STATE).unwrap(),
            joints: node.subscriber(&plane::JOINT_STATE).unwrap(),
            _node: node,
            stack,
            lidar,
            controller: Proc::none("nori-base"),
            base_args: base_args.iter().map(|a| a.to_string()).collect(),
            starts: 0,
            seq: 0,
        };
        base.restart_controller();
        base
    }

    fn restart_controller(&mut self) {
        self.controller.kill();
        self.starts += 1;
        let mut args = vec!["--domain".to_string(), self.stack.domain.clone()];
        args.extend(self.base_args.iter().cloned());
        self.controller = Proc::spawn_owned(
            "nori-base",
            &binary("nori-base"),
            &args,
            &self.stack.dir.join(format!("base-{}.log", self.starts)),
        );
        // Driven (the driver out of its safe state) and seeing (the lidar's revolutions).
        let states = &self.states;
        wait_for(
            Duration::from_secs(30),
            "the base driven and seeing",
            || {
                newest(states)
                    .filter(|s| s.flags & (BASE_FLAG_NOT_DRIVEN | BASE_FLAG_FIELD_BLIND) == 0)
            },
        );
    }

    fn command(&mut self, v: f32, w: f32) {
        self.seq += 1;
        let c = BaseCommand {
            seq: self.seq,
            timestamp_ns: monotonic_ns(),
            linear_m_s: v,
            angular_rad_s: w,
        };
        plane::publish(&self.commands, &c).unwrap();
    }

    /// Commands (v, w) every 50 ms for `seconds`; returns the controller's states meanwhile.
    fn drive(&mut self, v: f32, w: f32, seconds: f64) -> Vec<BaseState> {
        self.drive_until(v, w, seconds..=seconds, |_| false)
    }

    /// Commands (v, w) every 50 ms for the least of `seconds` and then until a state
    /// satisfies `done` or the most of `seconds` pass; returns the controller's states
    /// meanwhile. On a starved machine the controller stops often (wheels unread, lidar
    /// silent) and gets less far in a given time, so a drive ends at what the test waits for.
    fn drive_until(
        &mut self,
        v: f32,
        w: f32,
        seconds: std::ops::RangeInclusive<f64>,
        mut done: impl FnMut(&BaseState) -> bool,
    ) -> Vec<BaseState> {
        let start = Instant::now();
        let (least, most) = seconds.into_inner();
        let mut seen = Vec::new();
        let mut finished = false;
        while start.elapsed().as_secs_f64() < most {
            self.command(v, w);
            std::thread::sleep(Duration::from_millis(50));
            let before = seen.len();
            seen.extend(std::iter::from_fn(|| next(&self.states)));
            // Every state is shown to `done` once, in order (it may count them).
            finished |= seen[before..].iter().fold(false, |any, s| done(s) | any);
            if finished && start.elapsed().as_secs_f64() >= least {
                break;
            }
        }
        seen
    }

    /// How long after `since` (monotonic ns) the wheels first read still (both under 0.05
    /// rad/s in a frame that read both).
    fn wheels_still_after(&self, since: u64, within: Duration) -> Duration {
        wait_for(within, "the wheels still", || {
            let s = newest(&self.joints)?;
            let (l, r) = (&s.joints[0], &s.joints[1]);
            let still = l.is_valid()
                && r.is_valid()
                && l.velocity_rad_s.abs() < 0.05
                && r.velocity_rad_s.abs() < 0.05;
            (still && s.timestamp_ns > since).then(|| Duration::from_nanos(s.timestamp_ns - since))
        })
    }

    /// The simulator's truth: the base's pose (its report, written every second).
    fn truth(&self) -> serde_json::Value {
        let text = std::fs::read_to_string(self.stack.dir.join("sim-report.json")).unwrap();
        let report: serde_json::Value = serde_json::from_str(&text).unwrap();
        report["buses"][0]["base"].clone()
    }
}

/// What the controller said while driving, as runs of the same flags, each with its last
/// state's speeds and position, for a failure's message.
fn flag_story(states: &[BaseState]) -> String {
    let mut runs: Vec<(u32, usize, &BaseState)> = Vec::new();
    for s in states {
        match runs.last_mut() {
            Some((flags, n, last)) if *flags == s.flags => {
                *n += 1;
                *last = s;
            }
            _ => runs.push((s.flags, 1, s)),
        }
    }
    runs.iter()
        .map(|(flags, n, s)| {
            format!(
                "[{:?} × {n}: asked {:.3}, sent {:.3}, v {:.3}, x {:.3}]",
                telemetry::motion::base_flag_names(*flags).collect::<Vec<_>>(),
                s.requested_linear_m_s,
                s.commanded_linear_m_s,
                s.linear_m_s,
                s.x_m
            )
        })
        .collect::<Vec<_>>()
        .join(" ")
}

/// How long the wheels are given to follow a command that has stopped changing: the ramp
/// is done when the command sent is steady; the wheels' own response and the driver's cycle.
const SETTLE: Duration = Duration::from_millis(300);

/// Samples of a steady drive wanted before judging it: half a second at 50 Hz.
const STEADY_SAMPLES: usize = 25;

/// Where what was sent to the wheels has been (`linear`, `angular`) for `SETTLE`: on a
/// starved machine the controller stops for a moment whenever the wheels go unread or the
/// lidar falls silent, and ramps up again, as it must; following is judged where it was let
/// drive.
struct Steady {
    linear: f32,
    angular: f32,
    since: Option<u64>,
}

impl Steady {
    fn new(linear: f32, angular: f32) -> Self {
        Steady {
            linear,
            angular,
            since: None,
        }
    }

    /// Fed each state in order: whether it was driven steadily.
    fn settled(&mut self, s: &BaseState) -> bool {
        let sent = (s.commanded_linear_m_s - self.linear).abs() < 1e-4
            && (s.commanded_angular_rad_s - self.angular).abs() < 1e-4;
        self.since = if sent {
            self.since.or(Some(s.timestamp_ns))
        } else {
            None
        };
        self.since
            .is_some_and(|t| s.timestamp_ns >= t + SETTLE.as_nanos() as u64)
    }

    /// `done` for `Base::drive_until`: once `STEADY_SAMPLES` were driven steadily.
    fn enough(linear: f32, angular: f32) -> impl FnMut(&BaseState) -> bool {
        let mut steady = Steady::new(linear, angular);
        let mut count = 0;
        move |s| {
            count += usize::from(steady.settled(s));
            count >= STEADY_SAMPLES
        }
    }
}

/// The base cruised at `want` (of `measure`) where it was driven steadily at (`linear`,
/// `angular`), each sample shown with its flags.
fn assert_cruising(
    states: &[BaseState],
    measure: impl Fn(&BaseState) -> f32,
    (linear, angular): (f32, f32),
    want: f32,
    tolerance: f32,
) {
    let mut steady = Steady::new(linear, angular);
    let samples: Vec<(f32, u32)> = states
        .iter()
        .filter(|s| steady.settled(s))
        .map(|s| (measure(s), s.flags))
        .collect();
    assert!(
        samples.len() >= STEADY_SAMPLES,
        "only {} samples driven steadily at ({linear}, {angular}): {}",
        samples.len(),
        flag_story(states)
    );
    nori_tests::assert_cruising(&samples, want, tolerance);
}

#[test]
fn the_base_follows_knows_where_it_went_stops_when_told_nothing_and_short_of_a_wall() {
    let _turn = serial();
    let mut base = Base::start("base", &[], &[]);

    // From where it starts (facing +x, between the legs of the table in front), straight at
    // the far wall (x = 3.2 m in the room): the protective field stops the base short of it.
    let field_stopped =
        |s: &BaseState| s.flags & BASE_FLAG_FIELD_STOPPED != 0 && s.commanded_linear_m_s == 0.0;
    let toward = base.drive_until(0.2, 0.0, 0.0..=90.0, field_stopped);
    let stopped_by_field = toward.iter().any(field_stopped);
    // Still commanded toward the wall, the field holds it.
    base.drive(0.2, 0.0, 3.0);
    assert!(
        stopped_by_field,
        "the field never stopped the base: {}",
        flag_story(&toward)
    );
    std::thread::sleep(Duration::from_millis(1500));
    let truth = base.truth();
    assert_eq!(truth["bumps"], 0, "the base ran into something: {truth}");
    let front = truth["x_m"].as_f64().unwrap() + 0.225;
    assert!(
        front < 3.2 - 0.05,
        "its front {front} m, the wall at 3.2 m: {truth}"
    );
    assert!(front > 3.2 - 0.5, "stopped far short: front at {front} m");
    eprintln!("stopped by the field with its front at {front:.3} m, the wall at 3.2 m");

    // A velocity profile from there: back, a turn on the spot and back, an arc.
    let back = base.drive_until(-0.15, 0.0, 2.5..=8.0, Steady::enough(-0.15, 0.0));
    base.drive(0.0, 0.8, 1.5);
    base.drive(0.0, -0.8, 1.5);
    let arc = base.drive_until(0.12, 0.3, 2.0..=8.0, Steady::enough(0.12, 0.3));
    // Followed: once ramped up (0.3 s at 0.5 m/s²), the measured speed is the command's.
    for (states, v, w) in [(&back, -0.15, 0.0), (&arc, 0.12, 0.3)] {
        assert_cruising(states, |s| s.linear_m_s, (v, w), v, 0.1 * v.abs());
    }
    assert_cruising(&arc, |s| s.angular_rad_s, (0.12, 0.3), 0.3, 0.05);

    // Commands stop: still within the command timeout and the braking from 0.12 m/s (plus a
    // control period, a driver cycle and the wheels' own deceleration: 150 ms).
    let last = monotonic_ns();
    let stopped = base.wheels_still_after(last, Duration::from_secs(3));
    let bound =
        COMMAND_TIMEOUT + Duration::from_secs_f64(0.12 / BRAKE_M_S2) + Duration::from_millis(150);
    assert!(
        stopped <= bound,
        "wheels still {stopped:?} after the last command (bound {bound:?})"
    );
    assert!(
        stopped >= COMMAND_TIMEOUT,
        "stopped before the command had timed out: {stopped:?}"
    );

    // Where it went: the odometry against the simulator's truth, once the report is fresh.
    std::thread::sleep(Duration::from_millis(1500));
    let odometry = newest(&base.states).unwrap();
    let truth = base.truth();
    let (tx, ty, tt) = (
        truth["x_m"].as_f64().unwrap(),
        truth["y_m"].as_f64().unwrap(),
        truth["theta_rad"].as_f64().unwrap(),
    );
    let travelled = truth["travelled_m"].as_f64().unwrap();
    assert!(travelled > 0.5, "{truth}");
    let error = (odometry.x_m - tx).hypot(odometry.y_m - ty);
    assert!(
        error < 0.01 + 0.01 * travelled,
        "odometry {odometry} vs truth {truth}: {error} m off"
    );
    assert!(
        (odometry.theta_rad - tt).abs() < 0.02,
        "odometry {odometry} vs truth {truth}"
    );
    eprintln!("odometry {odometry}; truth {truth}; {error:.4} m off after {travelled:.2} m");

    // The controller killed while driving: the driver stops the wheels on its own timeout.
    base.drive(0.12, 0.0, 1.0);
    base.controller.kill();
    let killed = monotonic_ns();
    let stopped = base.wheels_still_after(killed, Duration::from_secs(3));
    assert!(
        stopped <= WHEEL_TIMEOUT + Duration::from_millis(200),
        "wheels still only {stopped:?} after the controller died"
    );
    base.restart_controller();

    let (code, out) = base.controller.terminate(Duration::from_secs(5));
    assert_eq!(code, Some(0), "{out}");
    assert!(out.contains("\"commands_refused\":0"), "{out}");
    base.stop();
}

impl Base {
    fn stop(mut self) -> serde_json::Value {
        if self.controller.running() {
            self.controller.terminate(Duration::from_secs(5));
        }
        self.lidar.terminate(Duration::from_secs(5));
        drop(self.commands);
        drop(self.states);
        drop(self.joints);
        drop(self._node);
        self.stack.stop()
    }
}

/// A base with no protective field (a robot without a lidar: `[field] lidar = false`) driven
/// into a wall: its wheels stall, the supervisor retries once and then reduces their torque, as
/// for an arm joint, so the motors do not cook pushing; a new command (backing off) restores it.
#[test]
fn a_wheel_pushing_a_wall_stalls_and_its_torque_is_reduced_until_the_command_changes() {
    let _turn = serial();
    let files = scratch("base-wall-files");
    // Started 0.5 m from the far wall (x = 3.2 m), facing it.
    let robot = files.join("robot.toml");
    let text = sim::description::NORI_A3_TOML.replacen(
        "start = [0.0, 0.0, 0.0]",
        "start = [2.5, 0.0, 0.0]",
        1,
    );
    assert_ne!(text, sim::description::NORI_A3_TOML);
    std::fs::write(&robot, text).unwrap();
    let config = files.join("base.toml");
    let text = base::config::DEFAULT_CONFIG_TOML.replacen("lidar = true", "lidar = false", 1);
    std::fs::write(&config, text).unwrap();
    let (robot, config) = (robot.display().to_string(), config.display().to_string());
    let mut base = Base::start(
        "base-wall",
        &["--description", &robot],
        &["--config", &config],
    );
    let events = base._node.subscriber(&plane::EVENTS).unwrap();

    base.drive(0.15, 0.0, 6.0);
    let seen: Vec<SupervisorEvent> = std::iter::from_fn(|| next(&events)).collect();
    let of = |kind: EventKind, joint: u8| {
        seen.iter()
            .any(|e| e.kind() == Some(kind) && e.joint == joint)
    };
    for wheel in [0, 1] {
        for kind in [
            EventKind::Stall,
            EventKind::StallRetry,
            EventKind::TorqueReduced,
        ] {
            assert!(of(kind, wheel), "no {kind:?} of wheel {wheel}: {seen:?}");
        }
    }
    // The reduction reached the servos: Torque_Limit 30 % on each while it pushed.
    std::thread::sleep(Duration::from_millis(1500));
    let text = std::fs::read_to_string(base.stack.dir.join("sim-report.json")).unwrap();
    let report: serde_json::Value = serde_json::from_str(&text).unwrap();
    let bus = &report["buses"][0];
    assert!(
        bus["base"]["bumps"].as_u64().unwrap() >= 1,
        "it never met the wall: {}",
        bus["base"]
    );
    let changes = bus["torque_limit_changes"].as_array().unwrap();
    for id in [1, 2] {
        assert!(
            changes
                .iter()
                .any(|c| c["id"] == id && c["permille"] == 300),
            "servo {id}'s torque limit never went to 30 %: {changes:?}"
        );
    }

    // Backing off is a new command: full torque again, and the base leaves the wall.
    base.drive(-0.1, 0.0, 2.0);
    let later: Vec<SupervisorEvent> = std::iter::from_fn(|| next(&events)).collect();
    for wheel in [0, 1] {
        assert!(
            later
                .iter()
                .any(|e| e.kind() == Some(EventKind::TorqueRestored) && e.joint == wheel),
            "wheel {wheel} not restored: {later:?}"
        );
    }
    std::thread::sleep(Duration::from_millis(1500));
    let truth = base.truth();
    assert_eq!(truth["blocked"], false, "{truth}");
    // The stall tier acted before the firmware's own protections (over-current after 1 s):
    // none fired, so the base's bus was never latched off.
    let all: Vec<&SupervisorEvent> = seen.iter().chain(&later).collect();
    assert!(
        !all.iter()
            .any(|e| e.kind() == Some(EventKind::FirmwareProtection)),
        "a firmware protection fired: {all:?}"
    );
    drop(events);
    let report = base.stop();
    eprintln!("base after the wall: {}", report["buses"][0]["base"]);
}

/// A policy off the robot drives the base through the fleet agent: its chunks' twists pass the
/// gate (one beyond the base's limits is refused whole and moves nothing), the agent renews the
/// base's command along the plan, and when the policy falls silent the wheels stop within the
/// plan's last step, the agent's horizon, the base's command timeout and its braking.
#[test]
fn a_policy_drives_the_base_through_the_gate_and_the_base_stops_when_it_falls_silent() {
    let _turn = serial();
    use fleet_agent::keys::robot_key;
    use fleet_agent::schema::{encode, ActionChunk, SCHEMA_VERSION};
    use fleet_agent::zenoh::Wait;
    let mut base = Base::start("base-policy", &[], &[]);
    let endpoint = nori_tests::free_endpoint();
    let id = "sim-base";
    base.stack
        .restart_agent_with(&["--robot-id", id, "--connect", &endpoint]);
    let fleet = nori_tests::listening_session(&endpoint);
    // The agent has the driver's layout: the base's bus alone, its two wheels.
    wait_for(Duration::from_secs(10), "the agent's layout", || {
        Some(nori_tests::agent_status(&fleet, id)).filter(|s| s.health.joints == 2)
    });
    let actions = robot_key(id, "actions");
    let mut seq = 0;
    // Ten steps 20 ms apart of (v, w), computed "now" (the robot's clock: same machine).
    let mut chunk = |v: f32, w: f32| {
        seq += 1;
        let c = ActionChunk {
            version: SCHEMA_VERSION,
            seq,
            observation_ns: monotonic_ns(),
            step_offsets_ns: (1..=10).map(|k| k * 20_000_000).collect(),
            joint_count: 2,
            joint_mask: 0,
            targets: vec![0.0; 20],
            lift_m: Vec::new(),
            base_twist: (0..10).flat_map(|_| [v, w]).collect(),
        };
        fleet.put(&actions, encode(&c)).wait().unwrap();
    };

    // Beyond the configured 0.2 m/s: refused, the base stays put.
    chunk(0.3, 0.0);
    std::thread::sleep(Duration::from_millis(500));
    let status = nori_tests::agent_status(&fleet, id);
    assert_eq!(
        status.counters.actions_rejected["out_of_range"], 1,
        "{status:?}"
    );
    assert!(status.last_rejection.contains("base_linear_m_s"));
    assert_eq!(status.counters.base_commands_forwarded, 0);
    assert!(newest(&base.states).unwrap().linear_m_s.abs() < 0.01);

    // The policy: a chunk every 100 ms for 2 s and until it has cruised (at most 4 s), backing away from the table at 0.12 m/s.
    let mut seen = Vec::new();
    let mut enough = Steady::enough(-0.12, 0.0);
    let mut chunks = 0;
    for _ in 0..40 {
        chunks += 1;
        chunk(-0.12, 0.0);
        std::thread::sleep(Duration::from_millis(100));
        let before = seen.len();
        seen.extend(std::iter::from_fn(|| next(&base.states)));
        if seen[before..].iter().fold(false, |any, s| enough(s) | any) && chunks >= 20 {
            break;
        }
    }
    let silent = monotonic_ns();
    // After the first chunk's arrival, the agent kept the command in force along the plan.
    let first = seen
        .iter()
        .position(|s| s.requested_linear_m_s != 0.0)
        .expect("the base never heard the plan");
    let along = &seen[first..];
    assert!(
        along
            .iter()
            .all(|s| (s.requested_linear_m_s + 0.12).abs() < 1e-4),
        "the agent let the command lapse along the plan: {}",
        flag_story(along)
    );
    assert_cruising(&seen, |s| s.linear_m_s, (-0.12, 0.0), -0.12, 0.012);
    // Silent: the last chunk's last step is 200 ms after it was sent (at most 100 ms before
    // `silent`), held 100 ms (the horizon); then the base's command times out and it brakes.
    let stopped = base.wheels_still_after(silent, Duration::from_secs(3));
    let bound = Duration::from_millis(200 + 100)
        + COMMAND_TIMEOUT
        + Duration::from_secs_f64(0.12 / BRAKE_M_S2)
        + Duration::from_millis(150);
    assert!(
        stopped <= bound,
        "wheels still {stopped:?} after the policy fell silent (bound {bound:?})"
    );
    assert!(
        stopped >= Duration::from_millis(100 + 100) + COMMAND_TIMEOUT - Duration::from_millis(50),
        "stopped {stopped:?} after: before the plan had run out and the command timed out"
    );
    let status = nori_tests::agent_status(&fleet, id);
    assert_eq!(status.counters.actions_accepted, chunks, "{status:?}");
    assert!(
        status.counters.base_commands_forwarded > 5 * chunks,
        "{status:?}"
    );
    assert_eq!(status.counters.goals_forwarded, 0, "no joint was commanded");
    drop(fleet);
    base.stop();
}

/// A wheel goal published on the joints' goals (`nori/goals`: what `nori goal`, Nori Lab and
/// the fleet agent send, or any other program on the robot) would drive a wheel with no
/// protective field, no ramp and no command timeout but the driver's. The wheels take speeds
/// only from the base's controller, on a path of their own; the driver refuses the rest.
#[test]
fn a_wheel_goal_from_anyone_but_the_base_is_refused() {
    let _turn = serial();
    let base = Base::start("base-wheel-goals", &[], &[]);
    let node = Plane::open(&base.stack.domain, "test-rogue").unwrap();
    let goals = node.publisher(&plane::GOALS).unwrap();
    let mut fastest = 0f32;
    for seq in 1..=100u64 {
        let mut frame = telemetry::GoalFrame {
            seq,
            timestamp_ns: monotonic_ns(),
            joint_count: 2,
            mask: 0b11,
            ..Default::default()
        };
        frame.position_rad[0] = 3.0;
        frame.position_rad[1] = -3.0;
        plane::publish(&goals, &frame).unwrap();
        std::thread::sleep(Duration::from_millis(10));
        if let Some(s) = newest(&base.joints) {
            for j in &s.joints()[..2] {
                if j.is_valid() {
                    fastest = fastest.max(j.velocity_rad_s.abs());
                }
            }
        }
    }
    let truth = base.truth();
    assert!(
        fastest < 0.05,
        "a wheel turned at {fastest} rad/s on goals from outside the base: {truth}"
    );
    drop((goals, node));
    base.stop();
}
