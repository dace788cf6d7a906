//! The fleet's metrics in a real Prometheus (Debian's `prometheus`, started here on loopback):
//! the simulated arm's fleet agent → `nori fleet` → Prometheus scraping its `/metrics` every
//! second with the shipped rules (`deploy/prometheus/nori-fleet.rules.yml`). Its HTTP API gives
//! the shoulder's temperature as the simulator has it, and after the overheat set-up trips the
//! bus a trip count of one; its alerts fire as the robot gives them cause: refused action
//! chunks, a motor within 3 °C of the trip, the robot offline once its agent is killed, the
//! collector down once `nori fleet` is.
//!
//! Without Prometheus the test says so and passes, except in CI (`CI` set), where it fails:
//! `deploy/install-build-deps.sh` installs it.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fleet_agent::keys::robot_key;
use fleet_agent::schema::SCHEMA_VERSION;
use fleet_agent::zenoh::Wait;
use nori_tests::{binary, free_endpoint, free_port_addr, http_get, scratch, ArmStack, Proc};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use supervisor::SupervisorConfig;
use telemetry::config::ProcessConfig;

const ROBOT: &str = "sim-prom";
const SHOULDER: &str = "left_shoulder_pitch";
/// The simulator heats this many times faster than real time: the overheat set-up's shoulder
/// reaches the 59 °C trip about 20 s after it is held horizontal.
const THERMAL_SPEEDUP: &str = "30";

/// Debian's Prometheus server, or `None` (then the test says so; under CI it fails instead).
fn prometheus_binary() -> Option<PathBuf> {
    let found = std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|dir| dir.join("prometheus"))
            .find(|p| p.is_file())
    });
    if found.is_none() {
        assert!(
            std::env::var_os("CI").is_none(),
            "no prometheus: deploy/install-build-deps.sh installs it"
        );
        eprintln!(
            "\n!!!!!!!! SKIPPED: no prometheus (deploy/install-build-deps.sh installs it) !!!!!!!!\n"
        );
    }
    found
}

/// `s` as a URL's query value.
fn percent_encoded(s: &str) -> String {
    s.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => {
                char::from(b).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}

/// The shipped rules, as the test loads them: every `for:` shortened to 1 s (the shipped ones,
/// 15 s to a minute, are meant for a fleet scraped every 15 s; the test evaluates every second
/// and would otherwise wait minutes). Nothing else is changed.
fn rules_for_the_test() -> String {
    let shipped =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/prometheus/nori-fleet.rules.yml");
    let text = std::fs::read_to_string(&shipped).unwrap();
    // The hot-motor alert's threshold is the supervisor's trip less 3 °C: the two must agree.
    let trip_c = SupervisorConfig::embedded().unwrap().thermal.trip_c;
    let expr = format!("expr: nori_joint_temperature_celsius >= {trip_c} - 3\n");
    assert!(
        text.contains(&expr),
        "{} does not say `{}` (the supervisor trips at {trip_c} °C)",
        shipped.display(),
        expr.trim()
    );
    let mut shortened = 0;
    let lines: Vec<String> = text
        .lines()
        .map(|line| {
            let indent = line.len() - line.trim_start().len();
            if line.trim_start().starts_with("for:") {
                shortened += 1;
                format!("{}for: 1s", &line[..indent])
            } else {
                line.to_string()
            }
        })
        .collect();
    assert!(shortened >= 3, "only {shortened} `for:` lines in the rules");
    lines.join("\n") + "\n"
}

/// A Prometheus server of this test: scraping `target` (job `nori-fleet`) every second,
/// evaluating `rules` every second, on a free loopback port.
struct Prometheus {
    proc: Proc,
    addr: String,
    log: PathBuf,
}

impl Prometheus {
    fn start(program: &Path, dir: &Path, rules: &str, target: &str) -> Prometheus {
        let rules_file = dir.join("nori-fleet.rules.yml");
        std::fs::write(&rules_file, rules).unwrap();
        let config = dir.join("prometheus.yml");
        std::fs::write(
            &config,
            format!(
                "global:\n  scrape_interval: 1s\n  scrape_timeout: 1s\n  evaluation_interval: 1s\n\
                 rule_files:\n  - {}\n\
                 scrape_configs:\n  - job_name: nori-fleet\n    static_configs:\n      \
                 - targets: [\"{target}\"]\n",
                rules_file.display()
            ),
        )
        .unwrap();
        let addr = free_port_addr();
        let log = dir.join("prometheus.log");
        let proc = Proc::spawn_owned(
            "prometheus",
            program,
            &[
                format!("--config.file={}", config.display()),
                format!("--storage.tsdb.path={}", dir.join("tsdb").display()),
                format!("--web.listen-address={addr}"),
            ],
            &log,
        );
        Prometheus { proc, addr, log }
    }

    /// Its last warnings and errors, for a failure's message.
    fn log_tail(&self) -> String {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        let lines: Vec<&str> = text
            .lines()
            .filter(|l| l.contains("level=warn") || l.contains("level=error"))
            .collect();
        lines[lines.len().saturating_sub(15)..].join("\n")
    }

    /// `data` of an API answer, or what came instead.
    fn api(&self, path: &str) -> Result<Value, String> {
        let (code, body) =
            http_get(&self.addr, path).ok_or_else(|| format!("no answer to GET {path}"))?;
        let body = String::from_utf8_lossy(&body);
        let json: Value = serde_json::from_str(&body)
            .map_err(|e| format!("GET {path}: {code}, not JSON ({e}): {body}"))?;
        if code != 200 || json["status"] != "success" {
            return Err(format!("GET {path}: {code} {body}"));
        }
        Ok(json["data"].clone())
    }

    /// The instant vector of `promql`: each sample's labels and value.
    fn query(&self, promql: &str) -> Result<Vec<(Value, f64)>, String> {
        let data = self.api(&format!("/api/v1/query?query={}", percent_encoded(promql)))?;
        let result = data["result"]
            .as_array()
            .ok_or_else(|| format!("{promql}: no result in {data}"))?;
        Ok(result
            .iter()
            .map(|s| {
                let v = s["value"][1].as_str().and_then(|v| v.parse().ok());
                (s["metric"].clone(), v.unwrap_or(f64::NAN))
            })
            .collect())
    }

    /// The one value of `promql`.
    fn value(&self, promql: &str) -> Result<f64, String> {
        match self.query(promql)?.as_slice() {
            [(_, v)] => Ok(*v),
            other => Err(format!("{promql}: {other:?}")),
        }
    }

    /// The alert `name` firing with every label of `labels`, or every alert seen.
    fn firing(&self, name: &str, labels: &[(&str, &str)]) -> Result<Value, String> {
        let data = self.api("/api/v1/alerts")?;
        let alerts = data["alerts"].as_array().cloned().unwrap_or_default();
        alerts
            .iter()
            .find(|a| {
                a["state"] == "firing"
                    && a["labels"]["alertname"] == name
                    && labels.iter().all(|(k, v)| a["labels"][k] == *v)
            })
            .cloned()
            .ok_or_else(|| {
                let seen: Vec<String> = alerts
                    .iter()
                    .map(|a| {
                        let (state, value) = (&a["state"], &a["value"]);
                        format!(
                            "{} {} at {}",
                            state.as_str().unwrap_or("?"),
                            a["labels"],
                            value.as_str().unwrap_or("?")
                        )
                    })
                    .collect();
                format!("alerts [{}]", seen.join("; "))
            })
    }

    /// Polls `f` every 200 ms until it succeeds; fails after `within` with what it last saw
    /// and the server's log.
    fn wait<T>(&self, within: Duration, what: &str, mut f: impl FnMut() -> Result<T, String>) -> T {
        let until = Instant::now() + within;
        loop {
            match f() {
                Ok(v) => return v,
                Err(saw) => assert!(
                    Instant::now() < until,
                    "timed out after {within:?} waiting for {what}; last saw: {saw}\n\
                     --- {}, its last warnings:\n{}",
                    self.log.display(),
                    self.log_tail()
                ),
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }
}

/// `nori fleet` on a free zenoh endpoint and HTTP address, asking the robots' status every
/// 300 ms: the process, its endpoint, its HTTP address.
fn start_fleet(dir: &Path) -> (Proc, String, String) {
    let endpoint = free_endpoint();
    let http = free_port_addr();
    let fleet = Proc::spawn(
        "nori fleet",
        &binary("nori"),
        &[
            "fleet",
            "--listen",
            &endpoint,
            "--http",
            &http,
            "--status-every-ms",
            "300",
        ],
        &dir.join("fleet.log"),
    );
    (fleet, endpoint, http)
}

/// The simulator's winding temperature of `joint` (its report, rewritten every second).
fn simulated_temperature(stack: &ArmStack, joint: &str) -> Result<f64, String> {
    let path = stack.dir.join("sim-report.json");
    let text = std::fs::read_to_string(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    let report: Value = serde_json::from_str(&text).map_err(|e| e.to_string())?;
    report["buses"][0]["servos"]
        .as_array()
        .and_then(|s| s.iter().find(|s| s["joint"] == joint))
        .and_then(|s| s["temperature_c"].as_f64())
        .ok_or_else(|| format!("no {joint} in the simulator's report"))
}

#[test]
#[allow(
    clippy::too_many_lines,
    reason = "one scenario read start to end, each phase a paragraph"
)]
fn prometheus_scrapes_the_fleet_and_the_shipped_alerts_fire_on_the_simulated_robot() {
    let Some(program) = prometheus_binary() else {
        return;
    };
    let started = Instant::now();
    let rules = rules_for_the_test();
    let dir = scratch("fleet-prometheus");
    let (mut fleet, fleet_ep, http) = start_fleet(&dir);
    let inference_ep = free_endpoint();
    let mut stack = ArmStack::start(
        "prom",
        &[
            "--scenario",
            "overheat",
            "--thermal-speedup",
            THERMAL_SPEEDUP,
        ],
    );
    stack.restart_agent_with(&[
        "--robot-id",
        ROBOT,
        "--connect",
        &fleet_ep,
        "--connect",
        &inference_ep,
    ]);
    let mut prom = Prometheus::start(&program, &dir, &rules, &http);
    let robot = format!("robot=\"{ROBOT}\"");

    // Scraped: the collector up, every rule loaded and evaluating without error.
    prom.wait(Duration::from_secs(20), "nori fleet scraped", || {
        let up = prom.value("up{job=\"nori-fleet\"}")?;
        (up == 1.0).then_some(()).ok_or(format!("up = {up}"))
    });
    let loaded = prom.wait(Duration::from_secs(10), "the rules evaluated", || {
        let data = prom.api("/api/v1/rules")?;
        let rules: Vec<Value> = data["groups"]
            .as_array()
            .into_iter()
            .flatten()
            .flat_map(|g| g["rules"].as_array().cloned().unwrap_or_default())
            .collect();
        let evaluated = rules.len() == 7
            && rules
                .iter()
                .all(|r| r["health"] == "ok" && r["lastEvaluation"] != "0001-01-01T00:00:00Z");
        evaluated
            .then_some(rules.clone())
            .ok_or(format!("{rules:?}"))
    });
    let names: Vec<&str> = loaded.iter().filter_map(|r| r["name"].as_str()).collect();
    for alert in [
        "NoriMotorNearThermalTrip",
        "NoriRobotOffline",
        "NoriActionsRefused",
        "NoriFleetCollectorDown",
    ] {
        assert!(names.contains(&alert), "{alert} not loaded: {names:?}");
    }

    // The shoulder's temperature, as the simulator has it (the arm hangs: it is steady).
    let shoulder = format!("nori_joint_temperature_celsius{{{robot},joint=\"{SHOULDER}\"}}");
    let (scraped, simulated) = prom.wait(
        Duration::from_secs(30),
        "the shoulder's temperature near the simulator's",
        || {
            let scraped = prom.value(&shoulder)?;
            let simulated = simulated_temperature(&stack, SHOULDER)?;
            ((scraped - simulated).abs() <= 2.0)
                .then_some((scraped, simulated))
                .ok_or(format!("{scraped} °C scraped, {simulated:.2} °C simulated"))
        },
    );
    assert!(
        (15.0..45.0).contains(&scraped),
        "the resting shoulder at {scraped} °C (simulated {simulated:.2} °C)"
    );
    assert_eq!(
        prom.value(&format!("nori_robot_online{{{robot}}}")),
        Ok(1.0)
    );
    let hottest_recorded = format!("robot:nori_joint_temperature_celsius:max{{{robot}}}");
    prom.wait(
        Duration::from_secs(10),
        "the hottest motor recorded",
        || {
            let t = prom.value(&hottest_recorded)?;
            (t >= scraped - 1.0 && t < 45.0)
                .then_some(())
                .ok_or(format!(
                    "{hottest_recorded} = {t}, the shoulder at {scraped}"
                ))
        },
    );

    // Refused actions: malformed chunks from an inference session, once Prometheus has the
    // gate's counts at 0 (a counter first seen at 1 is no increase).
    let malformed = [("robot", ROBOT), ("reason", "malformed")];
    let rejected = format!("nori_robot_actions_rejected_total{{{robot},reason=\"malformed\"}}");
    prom.wait(Duration::from_secs(20), "no refusals scraped yet", || {
        let n = prom.value(&rejected)?;
        (n == 0.0).then_some(()).ok_or(format!("{rejected} = {n}"))
    });
    let inference = nori_tests::listening_session(&inference_ep);
    let actions = inference
        .declare_publisher(robot_key(ROBOT, "actions"))
        .wait()
        .unwrap();
    let refused = prom.wait(Duration::from_secs(20), "NoriActionsRefused", || {
        actions
            .put(vec![SCHEMA_VERSION as u8, 0xff, 0xff])
            .wait()
            .map_err(|e| e.to_string())?;
        prom.firing("NoriActionsRefused", &malformed)
    });
    assert_eq!(refused["labels"]["severity"], "warning");
    drop(actions);
    drop(inference);

    // The shoulder held horizontal heats: within 3 °C of the trip the alert fires, with the
    // temperature it saw; then the trip, counted once.
    let stop = Arc::new(AtomicBool::new(false));
    let holding = nori_tests::hold_horizontal(&stack.domain, SHOULDER, stop.clone());
    let mut hottest = f64::MIN;
    let hot = prom.wait(Duration::from_secs(45), "NoriMotorNearThermalTrip", || {
        if let Ok(t) = prom.value(&shoulder) {
            hottest = hottest.max(t);
        }
        prom.firing(
            "NoriMotorNearThermalTrip",
            &[("robot", ROBOT), ("joint", SHOULDER)],
        )
        .map_err(|seen| format!("hottest scraped {hottest} °C; {seen}"))
    });
    let at: f64 = hot["value"].as_str().unwrap().parse().unwrap();
    assert!(
        (56.0..60.0).contains(&at),
        "NoriMotorNearThermalTrip fired at {at} °C: {hot}"
    );
    let trips = format!("nori_robot_events_total{{{robot},kind=\"ThermalTrip\"}}");
    let per_day = format!("robot:nori_robot_trips:increase1d{{{robot}}}");
    let (count, day) = prom.wait(Duration::from_secs(30), "the trip counted", || {
        let count = prom.value(&trips)?;
        let day = prom.value(&per_day)?;
        (count >= 1.0 && day >= 1.0)
            .then_some((count, day))
            .ok_or(format!("{trips} = {count}, {per_day} = {day}"))
    });
    assert_eq!(count, 1.0, "one trip");
    assert!(
        (1.0..1.5).contains(&day),
        "{per_day} = {day} for the one trip"
    );
    stop.store(true, Ordering::Relaxed);
    holding.join().unwrap();

    // The agent killed: the robot offline.
    stack.agent.kill();
    prom.wait(Duration::from_secs(20), "NoriRobotOffline", || {
        prom.firing("NoriRobotOffline", &[("robot", ROBOT)])
    });

    // The collector killed: it cannot be scraped.
    fleet.kill();
    prom.wait(Duration::from_secs(15), "NoriFleetCollectorDown", || {
        prom.firing("NoriFleetCollectorDown", &[("job", "nori-fleet")])
    });

    prom.proc.terminate(Duration::from_secs(10));
    stack.stop();
    eprintln!(
        "fleet_prometheus: shoulder {scraped} °C (simulated {simulated:.2}), alert at {at} °C, \
         trip counted {count} ({per_day} = {day:.3}); {:.1} s",
        started.elapsed().as_secs_f64()
    );
}
