//! Fleet benchmarks.
//!
//! - `action-latency`: a policy's action chunk published on zenoh until its goal is on the
//!   simulated wire (the servo's Goal_Position register changes), through the real fleet agent,
//!   supervisor and bus-driver processes; interleaved with the baseline path that skips zenoh
//!   and the agent (a goal frame published straight on the state plane). Also reports the peak
//!   RSS of the three on-robot processes.
//! - `policy-latency`: an observation until the goal computed from it is on the simulated wire,
//!   through a policy server: the Rust reference (in the bench) against the Python client
//!   (`python -m nori_client.flip`), the same flip policy.
//! - `fleet-ingest`: how many robots streaming telemetry one collector (`nori fleet`'s
//!   [`Collector`]) takes with no loss, against the offered load.

use anyhow::{anyhow, bail, Context, Result};
use bench::zenoh_session;
use clap::Args;
use feetech::registers as reg;
use fleet::collector::Collector;
use stack::{sibling, supervisor_and_driver, Managed, Run};
use telemetry::stats::quantile_sorted;

use fleet_agent::keys::{all_robots, robot_key};
use fleet_agent::schema::{decode, encode, ActionChunk, LayoutMsg, ObservationMsg, SCHEMA_VERSION};

use fleet_agent::zenoh::sample::Sample;
use fleet_agent::zenoh::Wait;
use sim::{RobotDescription, SimBus};
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::frames::GoalFrame;
use telemetry::plane::{self, Plane};

const BUS: &str = "left_arm";
const JOINT: &str = "left_elbow";
const ROBOT: &str = "bench-robot";

/// Options of `nori bench action-latency`.
#[derive(Args, Debug)]
pub struct ActionLatencyArgs {
    /// Trials per path (zenoh + agent, and the state-plane baseline), interleaved.
    #[arg(long, default_value_t = 100)]
    trials: usize,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

/// Options of `nori bench policy-latency`.
#[derive(Args, Debug)]
pub struct PolicyLatencyArgs {
    /// Target flips per server (one every half second of the robot's clock).
    #[arg(long, default_value_t = 40)]
    flips: usize,
    /// The Python with `nori_client` (python/nori_client/install.sh makes it).
    #[arg(long)]
    python: Option<std::path::PathBuf>,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

/// Options of `nori bench fleet-ingest`.
#[derive(Args, Debug)]
pub struct FleetIngestArgs {
    /// Fleet sizes to try, in order (comma-separated).
    #[arg(long, value_delimiter = ',', default_values_t = [10usize, 50, 100, 200])]
    robots: Vec<usize>,
    /// Telemetry rate of every robot, messages per second.
    #[arg(long, default_value_t = 50.0)]
    hz: f64,
    /// Seconds each fleet size streams.
    #[arg(long, default_value_t = 5.0)]
    seconds: f64,
    /// Processes the robots' sessions are spread over (each its own zenoh runtime), as a
    /// fleet's robots are over machines.
    #[arg(long, default_value_t = 4)]
    publisher_processes: usize,
    /// The robots reach the collector through a zenoh router (`nori router`, its own process),
    /// as a fleet's site routers make them: one link into the collector instead of one per
    /// robot. The router's CPU is reported beside the collector's.
    #[arg(long)]
    via_router: bool,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

/// A zenoh router on loopback for `--via-router` (plain TCP: the bench measures ingest, not
/// TLS), killed when dropped.
struct Router {
    child: std::process::Child,
    endpoint: String,
    _dir: std::path::PathBuf,
}

impl Router {
    fn start() -> Result<Router> {
        let endpoint = free_endpoint()?;
        let dir = std::env::temp_dir().join(format!("nori-bench-router-{}", std::process::id()));
        std::fs::create_dir_all(&dir)?;
        let config = dir.join("router.json5");
        std::fs::write(
            &config,
            format!(
                "{{ mode: \"router\", listen: {{ endpoints: [\"{endpoint}\"] }}, \
                 scouting: {{ multicast: {{ enabled: false }} }}, \
                 transport: {{ unicast: {{ max_sessions: {} }} }} }}",
                fleet_agent::net::FLEET_NODE_MAX_SESSIONS
            ),
        )?;
        let child = Command::new(stack::sibling("nori-fleet")?)
            .args(["router", "--config"])
            .arg(&config)
            .stderr(Stdio::null())
            .spawn()
            .context("starting the router")?;
        std::thread::sleep(Duration::from_millis(500));
        Ok(Router {
            child,
            endpoint,
            _dir: dir,
        })
    }

    /// Its CPU seconds so far (user + system, from /proc).
    fn cpu_seconds(&self) -> f64 {
        bench::cpu_seconds(self.child.id()).unwrap_or(0.0)
    }

    /// Its peak resident memory so far, MB.
    fn peak_rss_mb(&self) -> f64 {
        bench::peak_rss_mb(self.child.id()).unwrap_or(0.0)
    }
}

impl Drop for Router {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub(crate) fn free_endpoint() -> Result<String> {
    let l = std::net::TcpListener::bind("127.0.0.1:0")?;
    Ok(format!("tcp/127.0.0.1:{}", l.local_addr()?.port()))
}

/// The simulated left arm on a pseudo-terminal with the real supervisor, driver and fleet
/// agent (robot [`ROBOT`], connecting to `connect`), the agent's layout seen on `session`.
struct ArmOnFleet {
    dir: std::path::PathBuf,
    domain: String,
    served: sim::pty::ServedRobot,
    servo: usize,
    processes: [Managed; 3],
    joints: usize,
    joint: usize,
}

impl ArmOnFleet {
    fn start(tag: &str, connect: &[String], session: &fleet_agent::zenoh::Session) -> Result<Self> {
        let pid = std::process::id();
        let dir = std::env::temp_dir().join(format!("nori-bench-{tag}-{pid}"));
        std::fs::create_dir_all(&dir)?;
        let domain = format!("nori_bench_{tag}_{pid}").replace('-', "_");
        let robot = RobotDescription::nori_a3();
        let bus = robot.bus(BUS).context("no left_arm bus")?;
        let served = sim::pty::serve(vec![(SimBus::new(&robot, bus), dir.join(BUS))], 0.001)?;
        let servo = served
            .with_bus(BUS, |b| {
                b.report().servos.iter().position(|s| s.joint == JOINT)
            })
            .flatten()
            .context("no left_elbow servo")?;
        let trips = dir.join("trips");
        let run = Run {
            domain: &domain,
            device_dir: &dir,
            trips: Some(&trips),
            quiet: true,
        };
        let [supervisor, driver] = supervisor_and_driver(&run, BUS)?;
        let mut agent = Managed::new("fleet-agent", &sibling("fleet-agent")?, &run.agent());
        agent.add_args(&["--robot-id".into(), ROBOT.into()]);
        for endpoint in connect {
            agent.add_args(&["--connect".into(), endpoint.clone()]);
        }
        let mut processes = [supervisor, driver, agent];
        for (m, log) in processes
            .iter_mut()
            .zip(["supervisor.log", "driver.log", "agent.log"])
        {
            m.log_to(&dir.join(log))?;
            m.start()?;
        }
        // The robot on the fleet: its layout arriving, every servo set up.
        let layouts = session
            .declare_subscriber(robot_key(ROBOT, "layout"))
            .wait()
            .map_err(|e| anyhow!("{e}"))?;
        let deadline = Instant::now() + Duration::from_secs(30);
        let (joints, joint) = loop {
            if Instant::now() > deadline {
                bail!("the robot did not come up (logs in {})", dir.display());
            }
            if let Ok(Some(sample)) = layouts.try_recv() {
                let layout: LayoutMsg = decode(&sample.payload().to_bytes())?;
                if let Some(j) = layout.joints.iter().position(|j| j.name == JOINT) {
                    break (layout.joints.len(), j);
                }
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        Ok(ArmOnFleet {
            dir,
            domain,
            served,
            servo,
            processes,
            joints,
            joint,
        })
    }

    /// The elbow servo's Goal_Position register, as the simulated wire last wrote it.
    fn goal_register(&self) -> i32 {
        self.served
            .with_bus(BUS, |b| b.servos[self.servo].get(reg::GOAL_POSITION))
            .unwrap_or(i32::MIN)
    }

    /// Stops everything; the peak RSS of the three processes.
    fn stop(mut self) -> Vec<(String, Option<f64>)> {
        let rss = self
            .processes
            .iter()
            .map(|m| (m.name().to_string(), m.pid().and_then(bench::peak_rss_mb)))
            .collect();
        for m in &mut self.processes {
            m.stop(Duration::from_secs(3));
        }
        drop(self.served.stop());
        rss
    }
}

/// What a policy server declares for [`ROBOT`]: its observations and its action publisher.
fn policy_keys(
    session: &fleet_agent::zenoh::Session,
) -> Result<(
    fleet_agent::zenoh::pubsub::Subscriber<
        fleet_agent::zenoh::handlers::FifoChannelHandler<Sample>,
    >,
    fleet_agent::zenoh::pubsub::Publisher<'static>,
)> {
    let z = |e: fleet_agent::zenoh::Error| anyhow!("{e}");
    let observations = session
        .declare_subscriber(robot_key(ROBOT, "observation"))
        .wait()
        .map_err(z)?;
    let actions = session
        .declare_publisher(robot_key(ROBOT, "actions"))
        .wait()
        .map_err(z)?;
    Ok((observations, actions))
}

/// Runs `nori bench action-latency`.
pub fn action_latency(args: &ActionLatencyArgs) -> Result<()> {
    let endpoint = free_endpoint()?;
    let session =
        zenoh_session(vec![endpoint.clone()], vec![], "peer").context("opening a zenoh session")?;
    let arm = ArmOnFleet::start("fleet", std::slice::from_ref(&endpoint), &session)?;
    let (joints, joint) = (arm.joints, arm.joint);
    let goal_register = || arm.goal_register();
    let z = |e: fleet_agent::zenoh::Error| anyhow!("{e}");
    let (observations, actions) = policy_keys(&session)?;
    let node = Plane::open(&arm.domain, &format!("bench-fleet-{}", std::process::id()))?;
    let goals = node.publisher(&plane::GOALS)?;

    let mut last_observation_ns = 0;
    let mut zenoh_ms = Vec::with_capacity(args.trials);
    let mut plane_ms = Vec::with_capacity(args.trials);
    let mut missed = 0usize;
    let mut goal_seq = 0u64;
    std::thread::sleep(Duration::from_secs(1));
    for trial in 0..args.trials * 2 {
        while let Ok(Some(sample)) = observations.try_recv() {
            if let Ok(o) = decode::<ObservationMsg>(&sample.payload().to_bytes()) {
                last_observation_ns = o.timestamp_ns;
            }
        }
        // Each trial moves the goal away from where the previous one left it.
        let target = if trial % 2 == 0 { -0.9f32 } else { -0.5 };
        let before = goal_register();
        let through_zenoh = trial % 2 == 0;
        let published_ns = monotonic_ns();
        if through_zenoh {
            // One step 20 ms ahead, as a policy plans: the agent forwards its target at once
            // (before the first step the plan holds the first step's target).
            let mut targets = vec![0.0; joints];
            targets[joint] = target;
            let offset = published_ns.saturating_sub(last_observation_ns) + 20_000_000;
            actions
                .put(encode(&ActionChunk {
                    version: SCHEMA_VERSION,
                    seq: trial as u64 + 1,
                    observation_ns: last_observation_ns,
                    step_offsets_ns: vec![offset],
                    joint_count: joints as u16,
                    joint_mask: 1 << joint,
                    targets,
                    lift_m: Vec::new(),
                    base_twist: Vec::new(),
                }))
                .wait()
                .map_err(z)?;
        } else {
            goal_seq += 1;
            let mut frame = GoalFrame {
                seq: goal_seq,
                timestamp_ns: published_ns,
                joint_count: joints as u32,
                mask: 1 << joint,
                ..GoalFrame::default()
            };
            frame.position_rad[joint] = target;
            plane::publish(&goals, &frame)?;
        }
        let wait_until = Instant::now() + Duration::from_millis(500);
        let arrived = loop {
            if goal_register() != before {
                break Some((monotonic_ns() - published_ns) as f64 / 1e6);
            }
            if Instant::now() > wait_until {
                break None;
            }
            std::thread::sleep(Duration::from_micros(100));
        };
        match (arrived, through_zenoh) {
            (Some(ms), true) => zenoh_ms.push(ms),
            (Some(ms), false) => plane_ms.push(ms),
            (None, _) => missed += 1,
        }
        // Let the chunk's plan run out (step + horizon) before the next trial.
        std::thread::sleep(Duration::from_millis(250));
    }
    drop((goals, node));
    let dir = arm.dir.clone();
    let rss = arm.stop();
    zenoh_ms.sort_by(f64::total_cmp);
    plane_ms.sort_by(f64::total_cmp);
    let (z50, z99) = (
        quantile_sorted(&zenoh_ms, 0.5),
        quantile_sorted(&zenoh_ms, 0.99),
    );
    let (p50, p99) = (
        quantile_sorted(&plane_ms, 0.5),
        quantile_sorted(&plane_ms, 0.99),
    );
    let out = serde_json::json!({
        "trials_per_path": args.trials,
        "no_goal_within_500ms": missed,
        "zenoh_agent_ms": {"p50": z50, "p99": z99, "max": zenoh_ms.last()},
        "baseline_state_plane_ms": {"p50": p50, "p99": p99, "max": plane_ms.last()},
        "ratio_p50": z50 / p50,
        "ratio_p99": z99 / p99,
        "peak_rss_mb": rss.iter().map(|(n, v)| (n.to_string(), serde_json::json!(v))).collect::<serde_json::Map<_, _>>(),
    });
    if args.json {
        println!("{out}");
    } else {
        println!(
            "action → goal on the simulated wire, {} trials a path: zenoh + fleet agent p50 {z50:.2} ms, p99 {z99:.2} ms; baseline (goal straight on the state plane) p50 {p50:.2} ms, p99 {p99:.2} ms; ratio p50 {:.2}, p99 {:.2}; {missed} trials without a goal in 500 ms",
            args.trials, z50 / p50, z99 / p99
        );
        for (name, mb) in rss {
            println!(
                "  peak RSS {name}: {}",
                mb.map_or("?".into(), |v| format!("{v:.1} MB"))
            );
        }
    }
    if missed > 0 {
        bail!(
            "{missed} trials never reached the wire (logs in {})",
            dir.display()
        );
    }
    Ok(())
}

/// The flip policy's target for an observation at `timestamp_ns` (the same rule as
/// `python -m nori_client.flip`).
fn flip_target(timestamp_ns: u64) -> f32 {
    const TARGETS: [f32; 2] = [-0.9, -0.5];
    TARGETS[((timestamp_ns / FLIP_NS) % 2) as usize]
}

const FLIP_NS: u64 = 500_000_000;

/// The flip policy in Rust, on `session` (listening where the agent connects): answers each
/// observation at once with a one-step chunk 20 ms after it, until `stop`.
fn rust_flip(
    session: fleet_agent::zenoh::Session,
    joints: usize,
    joint: usize,
    stop: Arc<std::sync::atomic::AtomicBool>,
) -> Result<std::thread::JoinHandle<()>> {
    let (observations, actions) = policy_keys(&session)?;
    Ok(std::thread::spawn(move || {
        let mut seq = 0;
        while !stop.load(std::sync::atomic::Ordering::Relaxed) {
            let Ok(Some(sample)) = observations.recv_timeout(Duration::from_millis(100)) else {
                continue;
            };
            let Ok(o) = decode::<ObservationMsg>(&sample.payload().to_bytes()) else {
                continue;
            };
            let mut targets = vec![0.0; joints];
            targets[joint] = flip_target(o.timestamp_ns);
            seq += 1;
            let _ = actions
                .put(encode(&ActionChunk {
                    version: SCHEMA_VERSION,
                    seq,
                    observation_ns: o.timestamp_ns,
                    step_offsets_ns: vec![20_000_000],
                    joint_count: joints as u16,
                    joint_mask: 1 << joint,
                    targets,
                    lift_m: Vec::new(),
                    base_twist: Vec::new(),
                }))
                .wait();
        }
        drop(session);
    }))
}

/// Observation → goal on the wire through one policy server: for each flip of the target, the
/// time from the first observation after the flip (the one the server answers with the new
/// target) to the Goal_Position register's change, ms.
fn flips_through(arm: &ArmOnFleet, observations: &Mutex<Vec<u64>>, flips: usize) -> Vec<f64> {
    let mut out = Vec::with_capacity(flips);
    let first = monotonic_ns() / FLIP_NS + 2;
    for k in first..first + flips as u64 {
        let boundary = k * FLIP_NS;
        // Wait for the boundary, then for the register to leave the value it held before.
        while monotonic_ns() < boundary {
            std::thread::sleep(Duration::from_micros(200));
        }
        let before = arm.goal_register();
        let until = Instant::now() + Duration::from_millis(FLIP_NS / 1_000_000 - 20);
        let changed = loop {
            if arm.goal_register() != before {
                break Some(monotonic_ns());
            }
            if Instant::now() > until {
                break None;
            }
            std::thread::sleep(Duration::from_micros(100));
        };
        let answered = observations
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .iter()
            .copied()
            .filter(|&t| t >= boundary)
            .min();
        if let (Some(wire), Some(obs)) = (changed, answered) {
            if wire > obs {
                out.push((wire - obs) as f64 / 1e6);
            }
        }
    }
    out
}

/// Runs `nori bench policy-latency`.
pub fn policy_latency(args: &PolicyLatencyArgs) -> Result<()> {
    let python = match &args.python {
        Some(p) => p.clone(),
        None => std::path::PathBuf::from(std::env::var("HOME").unwrap_or_default())
            .join(".cache/nori/client-venv/bin/python"),
    };
    let mut rows = serde_json::Map::new();
    for server in ["rust", "python"] {
        rows.insert(server.into(), server_latency(server, args, &python)?);
    }
    let f = |k: &str, q: &str| rows[k][q].as_f64().unwrap_or(f64::NAN);
    let out = serde_json::json!({
        "servers": rows,
        "ratio_p50": f("python", "p50_ms") / f("rust", "p50_ms"),
        "ratio_p99": f("python", "p99_ms") / f("rust", "p99_ms"),
        "path": "observation read by the driver → agent → zenoh → policy server → chunk → zenoh → agent gate and scheduler → state plane → driver → Goal_Position on the simulated wire",
    });
    if args.json {
        println!("{out}");
    } else {
        println!(
            "observation → goal on the simulated wire through a policy server ({} flips each):\n  Rust reference   p50 {:.2} ms  p99 {:.2} ms\n  Python (nori_client) p50 {:.2} ms  p99 {:.2} ms\n  ratio Python/Rust p50 {:.2}, p99 {:.2}",
            args.flips,
            f("rust", "p50_ms"), f("rust", "p99_ms"),
            f("python", "p50_ms"), f("python", "p99_ms"),
            out["ratio_p50"].as_f64().unwrap_or(f64::NAN),
            out["ratio_p99"].as_f64().unwrap_or(f64::NAN),
        );
    }
    Ok(())
}

/// One server's row of `nori bench policy-latency`: an arm on a fleet of its own, the
/// server flipping its joint, the flips timed from observation to wire.
fn server_latency(
    server: &str,
    args: &PolicyLatencyArgs,
    python: &std::path::Path,
) -> Result<serde_json::Value> {
    let (server_ep, bench_ep) = (free_endpoint()?, free_endpoint()?);
    // The bench watches the observations on its own link to the agent.
    let session =
        zenoh_session(vec![bench_ep.clone()], vec![], "peer").context("opening a zenoh session")?;
    let arm = ArmOnFleet::start(
        &format!("policy-{server}"),
        &[server_ep.clone(), bench_ep.clone()],
        &session,
    )?;
    let seen = Arc::new(Mutex::new(Vec::new()));
    let s = seen.clone();
    let _observations = session
        .declare_subscriber(robot_key(ROBOT, "observation"))
        .callback(move |sample: Sample| {
            if let Ok(o) = decode::<ObservationMsg>(&sample.payload().to_bytes()) {
                s.lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .push(o.timestamp_ns);
            }
        })
        .wait()
        .map_err(|e| anyhow!("{e}"))?;
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    // Until killed after the flips (a generous bound, should the bench be stopped).
    let run_for = args.flips as f64 * FLIP_NS as f64 / 1e9 + 60.0;
    let flipper = FlipServer::start(server, python, &server_ep, &arm, &stop, run_for)?;
    await_first_flips(server, &arm)?;
    let mut ms = flips_through(&arm, &seen, args.flips);
    flipper.stop(&stop);
    let dir = arm.dir.clone();
    arm.stop();
    if ms.len() < args.flips / 2 {
        bail!(
            "{server}: {} of {} flips reached the wire (logs in {})",
            ms.len(),
            args.flips,
            dir.display()
        );
    }
    ms.sort_by(f64::total_cmp);
    Ok(serde_json::json!({
        "flips": args.flips, "measured": ms.len(),
        "p50_ms": quantile_sorted(&ms, 0.5), "p99_ms": quantile_sorted(&ms, 0.99),
        "max_ms": ms.last(),
    }))
}

/// The policy server under test: the Rust reference in a thread of this process, or the
/// Python client's in a child process.
enum FlipServer {
    Rust(std::thread::JoinHandle<()>),
    Python(std::process::Child),
}

impl FlipServer {
    /// Starts `server` ("rust", else Python's) listening on `endpoint`, flipping the arm's
    /// joint until `stop` (the thread) or for `run_for` s (the child).
    fn start(
        server: &str,
        python: &std::path::Path,
        endpoint: &str,
        arm: &ArmOnFleet,
        stop: &Arc<std::sync::atomic::AtomicBool>,
        run_for: f64,
    ) -> Result<FlipServer> {
        if server == "rust" {
            let server_session = zenoh_session(vec![endpoint.to_string()], vec![], "peer")?;
            return Ok(FlipServer::Rust(rust_flip(
                server_session,
                arm.joints,
                arm.joint,
                stop.clone(),
            )?));
        }
        let child = Command::new(python)
            .args([
                "-m",
                "nori_client.flip",
                "--listen",
                endpoint,
                "--robot",
                ROBOT,
            ])
            .args(["--joint", JOINT, "--run-for", &format!("{run_for:.0}")])
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(arm.dir.join("python.log"))?)
            .spawn()
            .with_context(|| {
                format!(
                    "running {} -m nori_client.flip (python/nori_client/install.sh)",
                    python.display()
                )
            })?;
        Ok(FlipServer::Python(child))
    }

    /// Stops the server: `stop` set (the thread's word), the thread joined or the child killed.
    fn stop(self, stop: &std::sync::atomic::AtomicBool) {
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        match self {
            FlipServer::Rust(thread) => {
                let _ = thread.join();
            }
            FlipServer::Python(mut child) => {
                let _ = child.kill();
                let _ = child.wait();
            }
        }
    }
}

/// Waits for the server to answer (the register flipped twice: a Python server first waits
/// for the agent's layout, sent every 5 s) before the trials count.
fn await_first_flips(server: &str, arm: &ArmOnFleet) -> Result<()> {
    let warm = Instant::now() + Duration::from_secs(30);
    let (mut last, mut flipped) = (arm.goal_register(), 0);
    while flipped < 2 {
        if Instant::now() > warm {
            bail!(
                "{server}: the policy server never answered (logs in {})",
                arm.dir.display()
            );
        }
        std::thread::sleep(Duration::from_millis(5));
        let now = arm.goal_register();
        if now != last {
            (last, flipped) = (now, flipped + 1);
        }
    }
    Ok(())
}

/// CPU time this process has used, s.
fn cpu_seconds() -> f64 {
    nix::sys::resource::getrusage(nix::sys::resource::UsageWho::RUSAGE_SELF).map_or(0.0, |u| {
        let t = |tv: nix::sys::time::TimeVal| tv.tv_sec() as f64 + tv.tv_usec() as f64 * 1e-6;
        t(u.user_time()) + t(u.system_time())
    })
}

/// The publishing robots, spread over processes as a fleet is over machines: each process's
/// sessions open, waiting for the word to stream.
struct Publishers {
    children: Vec<(
        std::process::Child,
        std::io::BufReader<std::process::ChildStdout>,
    )>,
    /// Seconds from the first spawn until every session was open.
    setup_s: f64,
}

impl Publishers {
    fn start(
        publisher: &std::path::Path,
        endpoint: &str,
        robots: usize,
        args: &FleetIngestArgs,
    ) -> Result<Publishers> {
        use std::io::BufRead;
        let started = Instant::now();
        let processes = args.publisher_processes.clamp(1, robots.max(1));
        let mut children = Vec::new();
        for k in 0..processes {
            let (first, end) = (robots * k / processes, robots * (k + 1) / processes);
            let mut child = Command::new(publisher)
                .args(["--connect", endpoint, "--hz", &args.hz.to_string()])
                .args([
                    "--robots",
                    &(end - first).to_string(),
                    "--first",
                    &first.to_string(),
                ])
                .args(["--seconds", &args.seconds.to_string()])
                .stdin(Stdio::piped())
                .stdout(Stdio::piped())
                .stderr(Stdio::inherit())
                .spawn()
                .context("running the publishers")?;
            let stdout = child.stdout.take().context("the publisher's output")?;
            children.push((child, std::io::BufReader::new(stdout)));
        }
        for (_, out) in &mut children {
            let mut line = String::new();
            out.read_line(&mut line)?;
            anyhow::ensure!(
                line.trim() == "ready",
                "a publisher failed before streaming"
            );
        }
        Ok(Publishers {
            children,
            setup_s: started.elapsed().as_secs_f64(),
        })
    }

    /// Streams; returns each robot's messages sent.
    fn stream(self) -> Result<Vec<u64>> {
        use std::io::{Read, Write};
        let mut children = self.children;
        for (child, _) in &mut children {
            child
                .stdin
                .as_mut()
                .context("the publisher's input")?
                .write_all(b"go\n")?;
        }
        let mut sent = Vec::new();
        for (mut child, mut out) in children {
            let mut json = String::new();
            out.read_to_string(&mut json)?;
            anyhow::ensure!(child.wait()?.success(), "the publishers failed");
            sent.extend(serde_json::from_str::<Vec<u64>>(&json)?);
        }
        Ok(sent)
    }
}

/// One stream's figures.
struct Stream {
    sent: Vec<u64>,
    received: Vec<u64>,
    /// This process's CPU seconds over the stream.
    cpu: f64,
    /// The router's CPU seconds over the stream.
    router_cpu: f64,
    /// The publishers' CPU seconds, their sessions' opening included.
    publishers_cpu: f64,
    /// The stream's wall seconds (the publishers' pacing, and what is still in flight).
    stream_s: f64,
    /// Seconds until every robot's session was open.
    setup_s: f64,
}

/// Robot `r`'s number from its state key (`nori/r00042/state`).
fn robot_number(key: &str) -> Option<usize> {
    key.get(6..11).and_then(|r| r.parse().ok())
}

/// One stream of `robots` robots' telemetry into this process: `raw` only counts what zenoh
/// delivers (the baseline); otherwise the collector ingests it as `nori fleet` does (decoded
/// outside the lock). CPU is measured over the stream only, not the sessions' opening.
fn ingest_run(
    publisher: &std::path::Path,
    robots: usize,
    args: &FleetIngestArgs,
    raw: bool,
    router: Option<&Router>,
) -> Result<Stream> {
    let (endpoint, session) = match router {
        Some(r) => (
            r.endpoint.clone(),
            zenoh_session(vec![], vec![r.endpoint.clone()], "client"),
        ),
        None => {
            let e = free_endpoint()?;
            (e.clone(), zenoh_session(vec![e], vec![], "peer"))
        }
    };
    let session = session.context("opening a zenoh session")?;
    let collector = Arc::new(Mutex::new(Collector::new(120, 500)));
    let counts: Arc<Vec<std::sync::atomic::AtomicU64>> =
        Arc::new((0..robots).map(|_| Default::default()).collect());
    let (c, n) = (collector.clone(), counts.clone());
    let _states = session
        .declare_subscriber(all_robots("state"))
        .callback(move |s: Sample| {
            let key = s.key_expr().as_str();
            if raw {
                // What zenoh costs: the sample delivered, its bytes looked at, counted.
                let bytes = s.payload().to_bytes();
                let robot = robot_number(key).filter(|_| !bytes.is_empty());
                if let Some(k) = robot.and_then(|r| n.get(r)) {
                    k.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                }
                return;
            }
            let msg = fleet::collector::decode_state(key, &s.payload().to_bytes());
            let mut c = c.lock().unwrap_or_else(|p| p.into_inner());
            let _ = c.decoded_state(key, msg, 0);
        })
        .wait()
        .map_err(|e| anyhow!("{e}"))?;
    let children_before = bench::children_cpu_seconds().unwrap_or(0.0);
    let publishers = Publishers::start(publisher, &endpoint, robots, args)?;
    let router_cpu = || router.map_or(0.0, Router::cpu_seconds);
    let (cpu_before, router_before, started) = (cpu_seconds(), router_cpu(), Instant::now());
    let setup_s = publishers.setup_s;
    let sent = publishers.stream()?;
    let publishers_cpu = bench::children_cpu_seconds().unwrap_or(0.0) - children_before;
    // Whatever is still in flight arrives within a moment.
    std::thread::sleep(Duration::from_millis(500));
    let (cpu, router_cpu) = (cpu_seconds() - cpu_before, router_cpu() - router_before);
    let received = if raw {
        counts
            .iter()
            .map(|k| k.load(std::sync::atomic::Ordering::Relaxed))
            .collect()
    } else {
        let c = collector.lock().unwrap_or_else(|p| p.into_inner());
        (0..robots)
            .map(|r| c.states_received(&format!("r{r:05}")))
            .collect()
    };
    Ok(Stream {
        sent,
        received,
        cpu,
        router_cpu,
        publishers_cpu,
        stream_s: started.elapsed().as_secs_f64(),
        setup_s,
    })
}

/// One fleet size's figures: the collector's stream against zenoh's own delivery (`raw`).
fn ingest_row(
    robots: usize,
    args: &FleetIngestArgs,
    raw: &Stream,
    run: &Stream,
    router: Option<&Router>,
) -> serde_json::Value {
    let (sent_total, received_total) = (
        run.sent.iter().sum::<u64>(),
        run.received.iter().sum::<u64>(),
    );
    let raw_total = raw.received.iter().sum::<u64>();
    let offered = robots as f64 * args.hz * args.seconds;
    let per_message_us = |cpu: f64, n: u64| if n == 0 { 0.0 } else { cpu / n as f64 * 1e6 };
    serde_json::json!({
        "robots": robots,
        "publisher_processes": args.publisher_processes.clamp(1, robots.max(1)),
        "offered": offered,
        "sent": sent_total,
        "received": received_total,
        "lost": sent_total.saturating_sub(received_total),
        "worst_robot_received_ratio": run.sent.iter().zip(&run.received)
            .map(|(&s, &r)| if s == 0 { 1.0 } else { r as f64 / s as f64 })
            .fold(1.0, f64::min),
        "sent_vs_offered": sent_total as f64 / offered,
        "sessions_open_s": run.setup_s,
        "stream_s": run.stream_s,
        "collector_cpu_share_of_a_core": run.cpu / run.stream_s,
        "raw_received": raw_total,
        "raw_cpu_share_of_a_core": raw.cpu / raw.stream_s,
        "collector_us_per_message": per_message_us(run.cpu, received_total),
        "raw_us_per_message": per_message_us(raw.cpu, raw_total),
        "collector_vs_raw": if raw.cpu > 0.0 { run.cpu / raw.cpu } else { 0.0 },
        "router_cpu_share_of_a_core": run.router_cpu / run.stream_s,
        "router_us_per_message": per_message_us(run.router_cpu, received_total),
        "router_peak_rss_mb": router.map_or(0.0, Router::peak_rss_mb),
        "publishers_cpu_share_of_a_core": run.publishers_cpu / (run.setup_s + run.stream_s),
    })
}

/// Runs `nori bench fleet-ingest`.
pub fn fleet_ingest(args: &FleetIngestArgs) -> Result<()> {
    let publisher = stack::sibling("nori-bench-fleet-publisher")?;
    let mut rows = Vec::new();
    for &robots in &args.robots {
        // The baseline first, then the collector, each on its own session and stream.
        let router = if args.via_router {
            Some(Router::start()?)
        } else {
            None
        };
        let raw = ingest_run(&publisher, robots, args, true, router.as_ref())?;
        let run = ingest_run(&publisher, robots, args, false, router.as_ref())?;
        rows.push(ingest_row(robots, args, &raw, &run, router.as_ref()));
    }
    let out = serde_json::json!({"hz": args.hz, "seconds": args.seconds, "via_router": args.via_router, "runs": rows});
    if args.json {
        println!("{out}");
    } else {
        println!(
            "fleet ingest, 18-joint telemetry at {} Hz per robot, {} s per fleet size{} (baselines: the offered load; zenoh's own delivery of the same stream, counted and dropped)",
            args.hz, args.seconds, if args.via_router { ", through a router" } else { "" }
        );
        let f = |r: &serde_json::Value, k: &str| r[k].as_f64().unwrap_or(0.0);
        for r in &rows {
            println!(
                "  {:>4} robots: sent {} of {} offered ({:.3}), received {} (lost {}, worst robot {:.3}); \
                 collector {:.0} % of a core, {:.1} µs a message; raw zenoh {:.0} %, {:.1} µs ({} received); ratio {:.2}",
                r["robots"], r["sent"], r["offered"], f(r, "sent_vs_offered"),
                r["received"], r["lost"], f(r, "worst_robot_received_ratio"),
                f(r, "collector_cpu_share_of_a_core") * 100.0, f(r, "collector_us_per_message"),
                f(r, "raw_cpu_share_of_a_core") * 100.0, f(r, "raw_us_per_message"), r["raw_received"],
                f(r, "collector_vs_raw"),
            );
            println!(
                "        the publishers ({} processes): {:.0} % of a core",
                r["publisher_processes"],
                f(r, "publishers_cpu_share_of_a_core") * 100.0
            );
            if args.via_router {
                println!(
                    "        the router: {:.0} % of a core, {:.1} µs a message, while the collector ingested; peak RSS {:.0} MB ({:.0} kB a robot); sessions open in {:.1} s",
                    f(r, "router_cpu_share_of_a_core") * 100.0,
                    f(r, "router_us_per_message"),
                    f(r, "router_peak_rss_mb"),
                    f(r, "router_peak_rss_mb") * 1000.0 / f(r, "robots").max(1.0),
                    f(r, "sessions_open_s")
                );
            }
        }
    }
    Ok(())
}
