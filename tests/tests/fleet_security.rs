//! The fleet link with mutual TLS and access control, as `deploy/zenoh/make-dev-ca.sh` sets it
//! up: a router (`nori router`), a robot's agent, the policy server with the inference identity,
//! and intruders. Only the inference identity moves the robot; another robot's valid
//! certificate, a dashboard's, no certificate or plain TCP do not. Only the store identity
//! acknowledges the robot's events: forged acknowledgements from another robot, the robot itself
//! or a dashboard never reach it.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fleet_agent::keys::robot_key;
use fleet_agent::schema::{decode, encode, ActionChunk, StateMsg, SCHEMA_VERSION};
use fleet_agent::zenoh::{self, Wait};
use nori_tests::{binary, check_left_arm_report, newest_read, scratch, wait_for, ArmStack, Proc};
use std::path::Path;
use std::process::Command;
use std::time::Duration;
use telemetry::clock::monotonic_ns;
use telemetry::frames::JointLayout;
use telemetry::plane::{self, newest, Plane};

const ELBOW: usize = 3;
const ROBOT: &str = "robot-a";

fn client(dir: &Path, identity: &str) -> zenoh::Session {
    fleet_agent::net::open_file(&dir.join(format!("{identity}.json5"))).unwrap()
}

fn status(dashboard: &zenoh::Session) -> serde_json::Value {
    wait_for(Duration::from_secs(10), "the agent's status", || {
        let replies = dashboard
            .get(robot_key(ROBOT, "status"))
            .timeout(Duration::from_secs(2))
            .wait()
            .ok()?;
        let sample = replies.recv().ok()?.into_result().ok()?;
        let msg: fleet_agent::schema::StatusMsg =
            fleet_agent::schema::decode(&sample.payload().to_bytes()).ok()?;
        serde_json::to_value(msg).ok()
    })
}

fn accepted(dashboard: &zenoh::Session) -> (u64, u64) {
    let st = status(dashboard);
    let rejected = st["counters"]["actions_rejected"]
        .as_object()
        .unwrap()
        .values()
        .map(|v| v.as_u64().unwrap())
        .sum();
    (
        st["counters"]["actions_accepted"].as_u64().unwrap(),
        rejected,
    )
}

/// A valid, fresh chunk sending the elbow to `target`: it would move the robot if it got in.
fn valid_chunk(layout: &JointLayout, seq: u64, target: f32) -> Vec<u8> {
    let n = layout.joint_count as usize;
    let mut targets = vec![0.0; n * 50];
    for k in 0..50 {
        targets[k * n + ELBOW] = target;
    }
    encode(&ActionChunk {
        version: SCHEMA_VERSION,
        seq,
        observation_ns: monotonic_ns(),
        step_offsets_ns: (1..=50).map(|k| k * 20_000_000).collect(),
        joint_count: n as u16,
        joint_mask: 1 << ELBOW,
        targets,
        lift_m: Vec::new(),
        base_twist: Vec::new(),
    })
}

/// The development CA of `make-dev-ca.sh` for robots `ROBOT` and robot-b, and its router on a
/// free TLS port: the scratch directory, the certificates' directory, the router's endpoint and
/// port, and the router.
fn fleet(tag: &str) -> (std::path::PathBuf, std::path::PathBuf, String, u16, Proc) {
    let dir = scratch(tag);
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let endpoint = format!("tls/127.0.0.1:{port}");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/zenoh/make-dev-ca.sh");
    let certs = dir.join("certs");
    let made = Command::new(&script)
        .args([certs.to_str().unwrap(), &endpoint, ROBOT, "robot-b"])
        .status()
        .unwrap();
    assert!(made.success(), "make-dev-ca.sh failed");
    let router = Proc::spawn(
        "router",
        &binary("nori"),
        &[
            "router",
            "--config",
            certs.join("router.json5").to_str().unwrap(),
        ],
        &dir.join("router.log"),
    );
    (dir, certs, endpoint, port, router)
}

/// The robot's agent as a client of the router with its certificate (and `journal`).
fn robot_on_fleet(stack: &mut ArmStack, certs: &Path, endpoint: &str, journal: &Path) {
    let agent_toml = stack.dir.join("agent.toml");
    let toml = fleet_agent::config::DEFAULT_CONFIG_TOML
        .replace(
            "robot-id = \"sim-0001\"",
            &format!("robot-id = \"{ROBOT}\""),
        )
        .replace("mode = \"peer\"", "mode = \"client\"")
        .replace(
            "[\"tcp/127.0.0.1:7447\", \"tcp/127.0.0.1:7448\", \"tcp/127.0.0.1:7449\"]",
            &format!("[\"{endpoint}\"]"),
        )
        .replace(
            "# config-file = \"/etc/nori/zenoh-robot.json5\"",
            &format!(
                "config-file = \"{}\"",
                certs.join(format!("{ROBOT}.json5")).display()
            ),
        );
    assert!(
        toml.contains(&format!("connect = [\"{endpoint}\"]")),
        "the agent's default endpoints were not replaced by the router's"
    );
    std::fs::write(&agent_toml, toml).unwrap();
    stack.restart_agent_with(&[
        "--config",
        agent_toml.to_str().unwrap(),
        "--journal-dir",
        journal.to_str().unwrap(),
    ]);
}

#[test]
fn only_the_inference_identity_moves_the_robot() {
    let (dir, certs, endpoint, port, _router) = fleet("tls-fleet");
    let dashboard = wait_for(Duration::from_secs(20), "the router", || {
        fleet_agent::net::open_file(&certs.join("dashboard.json5")).ok()
    });

    let mut stack = ArmStack::start("tls", &[]);
    robot_on_fleet(&mut stack, &certs, &endpoint, &dir.join("journal"));
    let node = Plane::open(&stack.domain, "test").unwrap();
    let states = node.subscriber(&plane::JOINT_STATE).unwrap();
    let layouts = node.subscriber(&plane::LAYOUT).unwrap();
    let layout = wait_for(Duration::from_secs(20), "the layout", || newest(&layouts));

    // The dashboard reads the robot's telemetry through the router.
    let telemetry = dashboard.declare_subscriber("nori/*/state").wait().unwrap();
    wait_for(
        Duration::from_secs(20),
        "telemetry at the dashboard",
        || {
            let s = telemetry.try_recv().ok().flatten()?;
            decode::<StateMsg>(&s.payload().to_bytes()).ok()
        },
    );

    // The inference identity's policy moves the elbow.
    let mut server = Proc::spawn(
        "policy-server",
        &binary("nori"),
        &[
            "policy-server",
            "--zenoh-config",
            certs.join("inference.json5").to_str().unwrap(),
            "--joints",
            "left_elbow",
            "--centre=-0.9",
            "--amplitude",
            "0.3",
            "--period-s",
            "2",
        ],
        &dir.join("policy-server.log"),
    );
    wait_for(
        Duration::from_secs(20),
        "the policy's chunks accepted",
        || (accepted(&dashboard).0 >= 10).then_some(()),
    );
    server.terminate(Duration::from_secs(5));
    std::thread::sleep(Duration::from_millis(1000));
    let before = accepted(&dashboard);
    let goal = || {
        wait_for(Duration::from_secs(5), "the elbow read", || {
            newest_read(&states, ELBOW)
        })
        .goal_rad
    };
    let held = goal();
    let target = if held < -0.9 { -0.4 } else { -1.4 };

    // Intruders, each with a valid, fresh chunk that would move the elbow by half a radian.
    let actions = robot_key(ROBOT, "actions");
    for identity in ["robot-b", ROBOT, "dashboard"] {
        let intruder = client(&certs, identity);
        for seq in 1..=5 {
            intruder
                .put(&actions, valid_chunk(&layout, seq, target))
                .wait()
                .unwrap();
        }
        std::thread::sleep(Duration::from_millis(300));
        intruder.close().wait().unwrap();
    }
    // No client certificate: the router refuses the handshake.
    let no_cert = dir.join("no-cert.json5");
    std::fs::write(
        &no_cert,
        format!(
            "{{ mode: \"client\", connect: {{ endpoints: [\"{endpoint}\"] }}, scouting: {{ multicast: {{ enabled: false }} }}, \
             transport: {{ link: {{ tls: {{ root_ca_certificate: \"{}\" }} }} }} }}",
            certs.join("ca.pem").display()
        ),
    )
    .unwrap();
    assert!(
        fleet_agent::net::open_file(&no_cert).is_err(),
        "a client without a certificate joined the fleet"
    );
    // Plain TCP on the TLS port: no session either.
    let plain = fleet_agent::net::open(&fleet_agent::config::ZenohConfig {
        mode: "client".into(),
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        listen: vec![],
        config_file: None,
    });
    assert!(plain.is_err(), "plain TCP joined the TLS fleet");

    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(
        accepted(&dashboard),
        before,
        "an intruder's chunk reached the agent's gate"
    );
    assert_eq!(goal(), held, "an intruder moved the elbow");
    eprintln!(
        "TLS + ACL: the inference identity's chunks accepted ({}); robot-b, robot-a itself and the \
         dashboard published 15 valid chunks, none reached the gate; no certificate and plain TCP refused",
        before.0
    );
    drop((telemetry, dashboard, states, layouts, node));
    let report = stack.stop();
    check_left_arm_report(&report, 60.0);
}

/// The store's acknowledgements through the router: only the store identity's reach the robot.
#[test]
fn only_the_store_identity_acknowledges_the_robots_events() {
    use fleet_agent::schema::{AckMsg, EventMsg};
    use telemetry::frames::{SupervisorCommand, COMMAND_REENABLE_BUS};
    let (dir, certs, endpoint, _, _router) = fleet("tls-store");
    let db = nori_tests::ScratchPostgres::start(&dir.join("postgres"));
    let store_args = |n: u32| {
        Proc::spawn(
            "nori fleet store",
            &binary("nori"),
            &[
                "fleet",
                "store",
                "--database",
                &db.url,
                "--zenoh-config",
                certs.join("store.json5").to_str().unwrap(),
            ],
            &dir.join(format!("store-{n}.log")),
        )
    };
    let mut store = store_args(1);
    let dashboard = wait_for(Duration::from_secs(20), "the router", || {
        fleet_agent::net::open_file(&certs.join("dashboard.json5")).ok()
    });
    let events = dashboard
        .declare_subscriber("nori/*/events")
        .wait()
        .unwrap();
    let mut stack = ArmStack::start("tls-store-robot", &[]);
    robot_on_fleet(&mut stack, &certs, &endpoint, &dir.join("journal"));
    let counters = || {
        let st = status(&dashboard);
        let c = |k: &str| st["counters"][k].as_u64().unwrap();
        (
            c("events_unacknowledged"),
            c("events_stored_through"),
            c("acks_refused") + st["counters"]["boxes"]["acks_refused"].as_u64().unwrap(),
        )
    };
    // The store's acknowledgements come through the router.
    let (_, through, _) = wait_for(
        Duration::from_secs(30),
        "the robot's events acknowledged",
        || {
            let c = counters();
            (c.0 == 0 && c.1 >= 3).then_some(c)
        },
    );
    let journal = wait_for(Duration::from_secs(10), "an event at the dashboard", || {
        let s = events.try_recv().ok().flatten()?;
        decode::<EventMsg>(&s.payload().to_bytes()).ok()
    })
    .journal;
    // The store gone, three events held on the robot.
    store.terminate(Duration::from_secs(5));
    let node = Plane::open(&stack.domain, "test-store").unwrap();
    let commands = node.publisher(&plane::COMMANDS).unwrap();
    for seq in 1..=3 {
        let cmd = SupervisorCommand {
            seq,
            timestamp_ns: monotonic_ns(),
            kind: COMMAND_REENABLE_BUS,
            ..SupervisorCommand::default()
        };
        plane::publish(&commands, &cmd).unwrap();
        std::thread::sleep(Duration::from_millis(50));
    }
    wait_for(Duration::from_secs(10), "three events held", || {
        (counters().0 >= 3).then_some(())
    });
    // Forged acknowledgements, one valid for what the robot holds and one beyond it: from
    // another robot, from the robot itself and from the dashboard. Had one arrived, the held
    // events would be let go, or the refusal counted.
    // A box's acknowledgement forged the same way would be counted refused (no box is on
    // its way): none may arrive either.
    let acks = robot_key(ROBOT, "acks");
    let box_acks = robot_key(ROBOT, "blackbox/ack");
    for identity in ["robot-b", ROBOT, "dashboard"] {
        let forger = client(&certs, identity);
        for stored_through in [through + 3, through + 1000] {
            let ack = AckMsg {
                version: SCHEMA_VERSION,
                journal,
                stored_through,
            };
            forger.put(&acks, encode(&ack)).wait().unwrap();
            let box_ack = fleet_agent::schema::BoxAckMsg {
                version: SCHEMA_VERSION,
                number: stored_through,
                digest: [1; 32],
                received: 0,
                complete: true,
                refused: false,
            };
            forger.put(&box_acks, encode(&box_ack)).wait().unwrap();
        }
        std::thread::sleep(Duration::from_millis(300));
        forger.close().wait().unwrap();
    }
    std::thread::sleep(Duration::from_millis(500));
    let (held, now_through, refused) = counters();
    assert!(
        held >= 3,
        "a forged acknowledgement let the robot's events go: {held} held"
    );
    assert_eq!(
        (now_through, refused),
        (through, 0),
        "a forged acknowledgement reached the robot"
    );
    // The store back: they are stored and acknowledged.
    let mut store = store_args(2);
    wait_for(
        Duration::from_secs(30),
        "the held events acknowledged",
        || (counters().0 == 0).then_some(()),
    );
    let mut c = db.client();
    let n: i64 = c
        .query_one(
            "SELECT count(*) FROM events WHERE kind = 'CommandRefused'",
            &[],
        )
        .unwrap()
        .get(0);
    assert_eq!(n, 3);
    store.terminate(Duration::from_secs(5));
    drop((events, dashboard, commands, node));
    stack.stop();
}
