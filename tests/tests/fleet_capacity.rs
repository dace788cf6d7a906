//! The fleet tier past zenoh's default of 1 000 sessions a node: a fleet-side process that
//! robots connect to (`nori fleet`, listening as a peer, as in development and on a small
//! site) takes every robot, and each shipped router template is sized past it.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fleet_agent::keys::robot_key;
use fleet_agent::zenoh::Wait;
use nori_tests::{binary, free_endpoint, http_get, wait_for, Proc};
use std::time::Duration;

/// Robots connecting at once: past zenoh's default `transport/unicast/max_sessions`.
const ROBOTS: usize = 1_100;

/// Each robot a client session of its own, as each robot's agent is.
#[test]
fn eleven_hundred_robots_connect_to_one_fleet_process_and_are_each_seen() {
    let dir = nori_tests::scratch("fleet-capacity");
    let (fleet_at, http) = (free_endpoint(), format!("127.0.0.1:{}", free_port()));
    let _fleet = Proc::spawn(
        "nori fleet",
        &binary("nori"),
        &["fleet", "--listen", &fleet_at, "--http", &http],
        &dir.join("fleet.log"),
    );
    wait_for(Duration::from_secs(20), "the dashboard", || {
        http_get(&http, "/metrics")
    });
    let mut robots = Vec::with_capacity(ROBOTS);
    for r in 0..ROBOTS {
        let session = nori_tests::connecting_session(&fleet_at, "client")
            .unwrap_or_else(|e| panic!("robot {r} of {ROBOTS} could not connect: {e}"));
        let layout = fleet_agent::schema::LayoutMsg {
            version: fleet_agent::schema::SCHEMA_VERSION,
            joints: Vec::new(),
        };
        session
            .put(
                robot_key(&format!("cap-{r:04}"), "layout"),
                fleet_agent::schema::encode(&layout),
            )
            .wait()
            .unwrap();
        robots.push(session);
    }
    // Every robot on the dashboard.
    let mut seen = 0;
    wait_for(
        Duration::from_secs(30),
        "every robot on the dashboard",
        || {
            let (_, body) = http_get(&http, "/metrics")?;
            let text = String::from_utf8_lossy(&body);
            seen = text
                .lines()
                .filter(|l| l.starts_with("nori_robot_online{"))
                .count();
            (seen >= ROBOTS).then_some(())
        },
    );
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .unwrap()
        .port()
}

/// The shipped router templates (and so `make-dev-ca.sh --site`'s routers, made from them)
/// take as many sessions as the fleet's sizing rule gives a router, with its lease
/// (`docs/fleet-sizing.md`).
#[test]
fn each_shipped_router_template_takes_the_sessions_its_rule_gives_it() {
    let deploy = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/zenoh");
    for template in ["site-router.json5", "cloud-router.json5"] {
        let config = fleet_agent::zenoh::Config::from_file(deploy.join(template)).unwrap();
        let sessions: usize = config
            .get_json("transport/unicast/max_sessions")
            .unwrap()
            .parse()
            .unwrap();
        assert_eq!(
            sessions,
            fleet_agent::net::FLEET_NODE_MAX_SESSIONS,
            "{template}: transport/unicast/max_sessions"
        );
        // A frozen router is given up by its robots within its lease (docs/fleet-sizing.md).
        let lease = config.get_json("transport/link/tx/lease").unwrap();
        assert_eq!(lease, "5000", "{template}: transport/link/tx/lease");
    }
}

/// A router at its limit refuses the next robot, and says so: in its log, and as its gauges.
#[test]
fn a_full_router_says_it_is_full_and_refuses_the_next_robot() {
    let dir = nori_tests::scratch("fleet-router-full");
    let (endpoint, metrics) = (free_endpoint(), format!("127.0.0.1:{}", free_port()));
    let config = dir.join("router.json5");
    std::fs::write(
        &config,
        format!(
            "{{ mode: \"router\", listen: {{ endpoints: [\"{endpoint}\"] }}, \
             scouting: {{ multicast: {{ enabled: false }} }}, \
             transport: {{ unicast: {{ max_sessions: 5 }} }} }}"
        ),
    )
    .unwrap();
    let log = dir.join("router.log");
    let _router = Proc::spawn(
        "nori router",
        &binary("nori-fleet"),
        &[
            "router",
            "--config",
            &config.display().to_string(),
            "--metrics",
            &metrics,
        ],
        &log,
    );
    wait_for(Duration::from_secs(20), "the router's metrics", || {
        http_get(&metrics, "/metrics")
    });
    let robot = || nori_tests::connecting_session(&endpoint, "client");
    let robots: Vec<_> = (0..5)
        .map(|r| robot().unwrap_or_else(|e| panic!("robot {r}: {e}")))
        .collect();
    assert!(robot().is_err(), "the sixth robot refused");
    let gauge = |text: &str, name: &str| {
        text.lines()
            .find_map(|l| l.strip_prefix(name)?.trim().parse::<usize>().ok())
    };
    wait_for(
        Duration::from_secs(30),
        "the router counting five sessions",
        || {
            let (_, body) = http_get(&metrics, "/metrics")?;
            let text = String::from_utf8_lossy(&body).to_string();
            assert_eq!(gauge(&text, "nori_router_max_sessions "), Some(5), "{text}");
            (gauge(&text, "nori_router_sessions ") == Some(5)).then_some(())
        },
    );
    // Said in the tick that counted them, once its log line is out (the router's writer is
    // its own thread: the gauge can be read first).
    wait_for(
        Duration::from_secs(15),
        "the router saying it is full",
        || {
            let said = std::fs::read_to_string(&log).ok()?;
            said.contains("the router is full: new robots are refused")
                .then_some(())
        },
    );
    drop(robots);
}
