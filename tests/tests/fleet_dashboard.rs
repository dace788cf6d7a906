//! `nori fleet` against a running robot: its `/metrics` text, parsed with an independent
//! Prometheus parser, shows the robot online with per-joint temperature and current, the
//! rejected actions by reason, and the robot going offline when its agent is killed; the
//! dashboard page and its JSON are served.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fleet_agent::keys::robot_key;
use fleet_agent::schema::{encode, ActionChunk, SCHEMA_VERSION};
use fleet_agent::zenoh::Wait;
use nori_tests::{binary, free_endpoint, scratch, wait_for, ArmStack, Proc};
use prometheus_parse::{Scrape, Value};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::Duration;
use telemetry::clock::monotonic_ns;

const ROBOT: &str = "sim-dash";
const ELBOW: usize = 3;

/// A plain HTTP/1.0 GET: the body of a 200 answer, or None.
fn get(addr: &str, path: &str) -> Option<String> {
    let mut stream = TcpStream::connect(addr).ok()?;
    stream.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    write!(stream, "GET {path} HTTP/1.0\r\nHost: {addr}\r\n\r\n").ok()?;
    let mut text = String::new();
    stream.read_to_string(&mut text).ok()?;
    let (head, body) = text.split_once("\r\n\r\n")?;
    (head.split_whitespace().nth(1) == Some("200")).then(|| body.to_string())
}

fn scrape(addr: &str) -> Option<Scrape> {
    let text = get(addr, "/metrics")?;
    Scrape::parse(text.lines().map(|l| Ok(l.to_string()))).ok()
}

/// The value of `name` with every label in `labels`.
fn value(scrape: &Scrape, name: &str, labels: &[(&str, &str)]) -> Option<f64> {
    scrape
        .samples
        .iter()
        .find(|s| s.metric == name && labels.iter().all(|(k, v)| s.labels.get(k) == Some(*v)))
        .map(|s| match s.value {
            Value::Counter(v) | Value::Gauge(v) | Value::Untyped(v) => v,
            _ => f64::NAN,
        })
}

fn out_of_range_chunk(seq: u64, joints: usize) -> Vec<u8> {
    let mut targets = vec![0.0; joints];
    targets[ELBOW] = 50.0;
    encode(&ActionChunk {
        version: SCHEMA_VERSION,
        seq,
        observation_ns: monotonic_ns(),
        step_offsets_ns: vec![20_000_000],
        joint_count: joints as u16,
        joint_mask: 1 << ELBOW,
        targets,
    })
}

#[test]
fn metrics_show_the_robot_its_joints_and_its_rejections() {
    let dir = scratch("fleet-dash");
    let (fleet_ep, inference_ep) = (free_endpoint(), free_endpoint());
    let http = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().to_string()
    };
    let _fleet = Proc::spawn(
        "nori fleet",
        &binary("nori"),
        &[
            "fleet",
            "--listen",
            &fleet_ep,
            "--http",
            &http,
            "--status-every-ms",
            "300",
        ],
        &dir.join("fleet.log"),
    );
    let mut stack = ArmStack::start("dash", &[]);
    stack.restart_agent_with(&[
        "--robot-id",
        ROBOT,
        "--connect",
        &fleet_ep,
        "--connect",
        &inference_ep,
    ]);

    // Online, with a temperature and a current for the elbow, by name.
    let robot = [("robot", ROBOT)];
    let elbow = [("robot", ROBOT), ("joint", "left_elbow")];
    let first = wait_for(Duration::from_secs(30), "the robot in /metrics", || {
        let s = scrape(&http)?;
        (value(&s, "nori_robot_online", &robot)? == 1.0
            && value(&s, "nori_joint_temperature_celsius", &elbow).is_some())
        .then_some(s)
    });
    let temperature = value(&first, "nori_joint_temperature_celsius", &elbow).unwrap();
    assert!(
        (15.0..60.0).contains(&temperature),
        "elbow at {temperature} °C"
    );
    assert!(value(&first, "nori_joint_current_amperes", &elbow).unwrap() >= 0.0);
    assert_eq!(value(&first, "nori_joint_valid", &elbow), Some(1.0));
    assert_eq!(value(&first, "nori_robot_safe_state", &robot), Some(0.0));
    assert!(value(&first, "nori_robot_state_messages_total", &robot).unwrap() >= 1.0);

    // Two bad chunks from an inference session: each rejection shows under its reason.
    let inference = fleet_agent::net::open(&fleet_agent::config::ZenohConfig {
        mode: "peer".into(),
        connect: vec![],
        listen: vec![inference_ep.clone()],
        config_file: None,
    })
    .unwrap();
    let joints = wait_for(Duration::from_secs(10), "the layout in the JSON", || {
        let body = get(&http, "/api/fleet")?;
        let snap: serde_json::Value = serde_json::from_str(&body).ok()?;
        let joints = snap["robots"][0]["joints"].as_array()?.len();
        (snap["robots"][0]["joints"][ELBOW]["name"] == "left_elbow").then_some(joints)
    });
    let actions = inference
        .declare_publisher(robot_key(ROBOT, "actions"))
        .wait()
        .unwrap();
    let rejected = |s: &Scrape, reason: &str| {
        value(
            s,
            "nori_robot_actions_rejected_total",
            &[("robot", ROBOT), ("reason", reason)],
        )
    };
    let after = wait_for(
        Duration::from_secs(20),
        "the rejections in /metrics",
        || {
            actions.put(out_of_range_chunk(1, joints)).wait().ok()?;
            actions
                .put(vec![SCHEMA_VERSION as u8, 0xff, 0xff])
                .wait()
                .ok()?;
            let s = scrape(&http)?;
            (rejected(&s, "out_of_range")? >= 1.0 && rejected(&s, "malformed")? >= 1.0).then_some(s)
        },
    );
    assert_eq!(
        value(&after, "nori_robot_actions_accepted_total", &robot),
        Some(0.0)
    );
    assert_eq!(rejected(&after, "stale"), Some(0.0));

    // The driver's bus counts, through the agent's status: the arm's bus (the driver's only
    // one here, named from its layout) connected and cycling, every error kind exported, no
    // disconnect (the simulator here injects no faults).
    let bus = [("robot", ROBOT), ("bus", "left_arm")];
    let buses = wait_for(
        Duration::from_secs(10),
        "the bus counts in /metrics",
        || {
            let s = scrape(&http)?;
            (value(&s, "nori_bus_cycles_total", &bus)? > 0.0).then_some(s)
        },
    );
    assert_eq!(value(&buses, "nori_bus_connected", &bus), Some(1.0));
    let errors = |kind| {
        value(
            &buses,
            "nori_bus_errors_total",
            &[("robot", ROBOT), ("bus", "left_arm"), ("kind", kind)],
        )
    };
    assert_eq!(errors("disconnects"), Some(0.0));
    assert!(errors("implausible").is_some() && errors("checksum_errors").is_some());

    // The page is served and fetches the JSON the test read.
    let page = get(&http, "/").unwrap();
    assert!(page.contains("fetch(\"/api/fleet\")") && page.contains("href=\"/metrics\""));
    assert!(get(&http, "/nothing-here").is_none());

    // The agent killed: its liveliness token goes, the robot shows offline.
    stack.agent.kill();
    wait_for(
        Duration::from_secs(20),
        "the robot offline in /metrics",
        || {
            let s = scrape(&http)?;
            (value(&s, "nori_robot_online", &robot)? == 0.0).then_some(())
        },
    );
    drop(actions);
    drop(inference);
    stack.stop();
}
