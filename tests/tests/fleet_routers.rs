//! The fleet's router tier under failure: robot agents (each a zenoh client of two site
//! routers, in opposite orders) → two site routers → a cloud router → the history store on a
//! real PostgreSQL server. A site router is killed for a few seconds while every robot's
//! supervisor keeps publishing events: the robots on it reconnect (to the other router, or to
//! it when it returns), their journals catch up, and the store holds every event exactly once.
//!
//! The robots here are fleet agents without a driver: the test publishes on each robot's state
//! plane as its supervisor would (`nori/events`), so the events and their count are known.
//! (Mutual TLS and access control through the routers: `fleet_security.rs`.)

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::{binary, free_endpoint, scratch, wait_for, Proc, ScratchPostgres};
use std::path::Path;
use std::time::{Duration, Instant};
use telemetry::frames::{EventKind, SupervisorEvent};
use telemetry::plane::{self, Plane};

const ROBOTS: usize = 6;

fn router(dir: &Path, name: &str, listen: &str, connect: Option<&str>) -> Proc {
    let config = dir.join(format!("{name}.json5"));
    let connect = connect.map_or(String::new(), |c| {
        format!("connect: {{ endpoints: [\"{c}\"] }},")
    });
    std::fs::write(
        &config,
        format!(
            "{{ mode: \"router\", listen: {{ endpoints: [\"{listen}\"] }}, {connect} \
             scouting: {{ multicast: {{ enabled: false }} }} }}"
        ),
    )
    .unwrap();
    Proc::spawn(
        name,
        &binary("nori"),
        &["router", "--config", config.to_str().unwrap()],
        &dir.join(format!("{name}-{}.log", telemetry::clock::monotonic_ns())),
    )
}

struct Robot {
    id: String,
    domain: String,
    events: plane::Pub<SupervisorEvent>,
    seq: u64,
    node: Plane,
    agent: Proc,
}

#[test]
fn a_site_router_killed_loses_no_event_and_stores_none_twice() {
    let dir = scratch("fleet-routers");
    let db = ScratchPostgres::start(&dir.join("postgres"));
    let (cloud, site_a, site_b) = (free_endpoint(), free_endpoint(), free_endpoint());
    let _cloud = router(&dir, "cloud", &cloud, None);
    let mut router_a = router(&dir, "site-a", &site_a, Some(&cloud));
    let _router_b = router(&dir, "site-b", &site_b, Some(&cloud));
    let mut store = Proc::spawn(
        "nori fleet store",
        &binary("nori"),
        &["fleet", "store", "--database", &db.url, "--connect", &cloud],
        &dir.join("store.log"),
    );
    let watcher = wait_for(Duration::from_secs(20), "the cloud router", || {
        fleet_agent::net::open(&fleet_agent::config::ZenohConfig {
            mode: "client".into(),
            connect: vec![cloud.clone()],
            listen: vec![],
            config_file: None,
        })
        .ok()
    });
    let mut robots = Vec::new();
    for r in 0..ROBOTS {
        let id = format!("site-robot-{r}");
        let domain = format!("nori_routers_{r}_{}", std::process::id());
        let node = Plane::open(&domain, "test-supervisor").unwrap();
        let events = node.publisher(&plane::EVENTS).unwrap();
        // Half the robots prefer site A, half site B.
        let sites = if r % 2 == 0 {
            [&site_a, &site_b]
        } else {
            [&site_b, &site_a]
        };
        let config = dir.join(format!("{id}.toml"));
        let toml = fleet_agent::config::DEFAULT_CONFIG_TOML
            .replace("mode = \"peer\"", "mode = \"client\"")
            .replace(
                "[\"tcp/127.0.0.1:7447\", \"tcp/127.0.0.1:7448\", \"tcp/127.0.0.1:7449\"]",
                &format!("[\"{}\", \"{}\"]", sites[0], sites[1]),
            )
            // A quick first resend: the test's outage is seconds, not minutes.
            .replace("resend-after-ms = 2000", "resend-after-ms = 500");
        assert!(toml.contains(&format!("[\"{}\", \"{}\"]", sites[0], sites[1])));
        std::fs::write(&config, toml).unwrap();
        let journal = dir.join(format!("journal-{r}"));
        let agent = Proc::spawn(
            "fleet-agent",
            &binary("fleet-agent"),
            &[
                "--domain",
                &domain,
                "--config",
                config.to_str().unwrap(),
                "--robot-id",
                &id,
                "--journal-dir",
                journal.to_str().unwrap(),
            ],
            &dir.join(format!("agent-{r}.log")),
        );
        robots.push(Robot {
            id,
            domain,
            events,
            seq: 0,
            node,
            agent,
        });
    }
    let held = |id: &str| nori_tests::agent_status(&watcher, id).counters;
    // Every robot on the fleet: its start stored and acknowledged.
    for r in &robots {
        wait_for(
            Duration::from_secs(30),
            &format!("{} on the fleet", r.id),
            || {
                let c = held(&r.id);
                (c.events_stored_through >= 1 && c.events_unacknowledged == 0).then_some(())
            },
        );
    }
    // Events at 20 a second from each robot; site A is killed 2 s in and back 5 s later.
    let publish = |robots: &mut Vec<Robot>| {
        for r in robots.iter_mut() {
            r.seq += 1;
            let e = SupervisorEvent {
                seq: r.seq,
                timestamp_ns: telemetry::clock::monotonic_ns(),
                kind: EventKind::Stall as u8,
                value: r.seq as f32,
                ..SupervisorEvent::default()
            };
            plane::publish(&r.events, &e).unwrap();
        }
    };
    let start = Instant::now();
    let mut killed_at = None;
    let mut back_at = None;
    while start.elapsed() < Duration::from_secs(10) {
        publish(&mut robots);
        let t = start.elapsed();
        if killed_at.is_none() && t >= Duration::from_secs(2) {
            router_a.kill();
            killed_at = Some(Instant::now());
        }
        if back_at.is_none() && t >= Duration::from_secs(7) {
            router_a = router(&dir, "site-a", &site_a, Some(&cloud));
            back_at = Some(Instant::now());
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let outage = back_at.unwrap() - killed_at.unwrap();
    let back_at = back_at.unwrap();
    // Every robot's journal caught up.
    let mut back = Duration::ZERO;
    for r in &robots {
        wait_for(
            Duration::from_secs(60),
            &format!("{} caught up", r.id),
            || {
                let c = held(&r.id);
                // Its start (number 1), then its supervisor's events.
                (c.events_unacknowledged == 0 && c.events_stored_through > r.seq).then_some(())
            },
        );
        back = back.max(back_at.elapsed());
    }
    let mut c = db.client();
    let (mut lost, mut copies, mut published) = (0, 0, 0);
    for r in &robots {
        let row = c
            .query_one(
                "SELECT count(*), count(DISTINCT origin_seq) FROM events WHERE robot = $1 AND kind = 'Stall'",
                &[&r.id],
            )
            .unwrap();
        let (n, distinct): (i64, i64) = (row.get(0), row.get(1));
        published += r.seq as i64;
        lost += r.seq as i64 - distinct;
        copies += n - distinct;
    }
    let resent: u64 = robots.iter().map(|r| held(&r.id).events_resent).sum();
    eprintln!(
        "router tier: {ROBOTS} robots, {published} events published, site A down {:.1} s; \
         lost {lost}, stored twice {copies}, {resent} sent again; every robot caught up {:.1} s \
         after site A was back",
        outage.as_secs_f64(),
        back.as_secs_f64()
    );
    assert_eq!((lost, copies), (0, 0));
    store.terminate(Duration::from_secs(5));
    drop(watcher);
    for mut r in robots {
        r.agent.terminate(Duration::from_secs(5));
        drop((r.events, r.node));
        Plane::remove_unused_domain(&r.domain).unwrap();
    }
}
