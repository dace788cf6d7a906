//! `fleet-agent`: the zenoh bridge of one robot. One loop (1 ms poll) moves the state plane's
//! frames out and gated actions in; zenoh runs its own threads behind non-blocking calls.
//!
//! Its state is its plan of accepted actions and nothing else: killed, it takes the plan with
//! it, the driver stops getting goals and holds, and a restarted agent starts with none.

use anyhow::{Context, Result};
use clap::Parser;
use fleet_agent::gate::{ActionGate, Range, REASONS};
use fleet_agent::keys::robot_key;
use fleet_agent::outbound::{self, Every};
use fleet_agent::schedule::Scheduler;
use fleet_agent::schema::{encode, SCHEMA_VERSION};
use fleet_agent::zenoh::qos::CongestionControl;
use fleet_agent::zenoh::Wait;
use fleet_agent::{net, AgentConfig};
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use telemetry::clock::monotonic_ns;
use telemetry::frames::JointLayout;
use telemetry::plane::{self, newest, next, publish, Plane};
use telemetry::process::ServiceManager;

#[derive(Parser)]
#[command(
    version,
    about = "Nori A3 fleet agent: telemetry out, gated policy actions in (zenoh)"
)]
struct Args {
    /// Configuration file (TOML); the embedded default when absent.
    #[arg(long)]
    config: Option<PathBuf>,
    /// State-plane domain.
    #[arg(long, default_value = plane::DEFAULT_DOMAIN)]
    domain: String,
    /// Overrides `robot-id`.
    #[arg(long)]
    robot_id: Option<String>,
    /// Overrides `zenoh.connect` (repeatable).
    #[arg(long)]
    connect: Vec<String>,
    /// Overrides `zenoh.listen` (repeatable).
    #[arg(long)]
    listen: Vec<String>,
    /// Stop after this many seconds.
    #[arg(long)]
    run_for: Option<f64>,
    /// Print the default configuration and exit.
    #[arg(long)]
    print_default_config: bool,
}

const POLL: Duration = Duration::from_millis(1);

fn wall_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// What the status queryable reports besides the gate's and scheduler's own counters.
#[derive(Default)]
struct Counters {
    state_sent: u64,
    observations_sent: u64,
    events_sent: u64,
    goals_forwarded: u64,
    /// Plans dropped because the driver restarted or entered its safe state.
    plans_dropped: u64,
    /// Scheduled targets withheld at the last check (none, unless the scheduler is wrong).
    goals_withheld: u64,
    last_rejection: String,
}

fn main() -> Result<()> {
    let args = Args::parse();
    if args.print_default_config {
        print!("{}", fleet_agent::config::DEFAULT_CONFIG_TOML);
        return Ok(());
    }
    telemetry::process::init_logging();
    let mut config = match &args.config {
        Some(p) => AgentConfig::load(p)?,
        None => AgentConfig::embedded()?,
    };
    if let Some(id) = &args.robot_id {
        fleet_agent::keys::check_robot_id(id)?;
        config.robot_id = id.clone();
    }
    if !args.connect.is_empty() {
        config.zenoh.connect = args.connect.clone();
    }
    if !args.listen.is_empty() {
        config.zenoh.listen = args.listen.clone();
    }
    let stop = telemetry::process::stop_flag().context("installing signal handlers")?;

    let node = Plane::open(&args.domain, "fleet-agent")?;
    node.cleanup_dead();
    let states = node.subscriber(&plane::JOINT_STATE)?;
    let layouts = node.subscriber(&plane::LAYOUT)?;
    let events = node.subscriber(&plane::EVENTS)?;
    let bus_health = node.subscriber(&plane::BUS_HEALTH)?;
    let goals = node.publisher(&plane::GOALS)?;

    let id = config.robot_id.clone();
    let session = net::open(&config.zenoh)
        .with_context(|| format!("joining the fleet as {id} via {:?}", config.zenoh.connect))?;
    let z = |e: fleet_agent::zenoh::Error| anyhow::anyhow!("{e}");
    let fresh = |key: &str| {
        session
            .declare_publisher(robot_key(&id, key))
            .congestion_control(CongestionControl::Drop)
            .wait()
    };
    let state_pub = fresh("state").map_err(z)?;
    let observation_pub = fresh("observation").map_err(z)?;
    let layout_pub = session
        .declare_publisher(robot_key(&id, "layout"))
        .wait()
        .map_err(z)?;
    // Events are rare and matter: block rather than drop them on congestion.
    let event_pub = session
        .declare_publisher(robot_key(&id, "events"))
        .congestion_control(CongestionControl::Block)
        .wait()
        .map_err(z)?;
    let actions = session
        .declare_subscriber(robot_key(&id, "actions"))
        .wait()
        .map_err(z)?;
    let status_key = robot_key(&id, "status");
    let status_queries = session.declare_queryable(&status_key).wait().map_err(z)?;
    let _alive = session
        .liveliness()
        .declare_token(robot_key(&id, "alive"))
        .wait()
        .map_err(z)?;
    tracing::info!(robot = %id, domain = %args.domain, connect = ?config.zenoh.connect,
        "on the fleet: telemetry on {}, actions from {}", robot_key(&id, "state"), robot_key(&id, "actions"));

    let mut service = ServiceManager::from_env();
    service.ready(&format!("robot {id} on the fleet"));
    let mut gate = ActionGate::new(config.gate());
    let mut scheduler = Scheduler::new(
        config.actions.blend_new,
        config.actions.horizon_ms * 1_000_000,
    );
    let mut layout = JointLayout::default();
    let mut ranges: Vec<Range> = Vec::new();
    let mut state_every = Every::hz(config.telemetry.state_hz);
    let mut observation_every = Every::hz(config.telemetry.observation_hz);
    let mut layout_every = Every::hz(1.0 / config.telemetry.layout_every_s);
    let mut forward_every = Every::hz(config.actions.forward_hz);
    let mut warn_every = Every::hz(1.0);
    let mut counters = Counters::default();
    let mut last_state: Option<telemetry::frames::JointState> = None;
    let mut last_health: Option<telemetry::frames::BusHealth> = None;
    let mut goal_seq = 0u64;
    let started = std::time::Instant::now();

    while !stop.load(Ordering::Relaxed)
        && args
            .run_for
            .is_none_or(|s| started.elapsed().as_secs_f64() < s)
    {
        let now = monotonic_ns();
        service.keepalive(std::time::Instant::now());
        if let Some(l) = newest(&layouts) {
            if l != layout {
                layout = l;
                ranges = outbound::ranges(&layout);
                // A new driver (or a new layout): the old plan was made for another robot state.
                scheduler.clear();
                layout_every = Every::hz(1.0 / config.telemetry.layout_every_s);
            }
        }
        if layout.joint_count > 0 && layout_every.due(now) {
            let _ = layout_pub
                .put(encode(&outbound::layout_msg(&layout)))
                .wait();
        }
        // Every frame, in order: the gate must see the driver enter its safe state or restart,
        // however briefly, to drop the plan made before it.
        let mut newest_state = None;
        while let Some(s) = next(&states) {
            let safe = s.flags & telemetry::frames::STATE_FLAG_SAFE_STATE != 0;
            if gate.observe_driver(s.seq, s.timestamp_ns, safe) && scheduler.planned_steps() > 0 {
                scheduler.clear();
                counters.plans_dropped += 1;
                tracing::info!(
                    "driver restarted or in its safe state: the plan made before is dropped"
                );
            }
            newest_state = Some(s);
        }
        if let Some(s) = newest_state {
            last_state = Some(s);
            if state_every.due(now)
                && state_pub
                    .put(encode(&outbound::state_msg(&s, wall_ms())))
                    .wait()
                    .is_ok()
            {
                counters.state_sent += 1;
            }
            if observation_every.due(now)
                && observation_pub
                    .put(encode(&outbound::observation_msg(&s)))
                    .wait()
                    .is_ok()
            {
                counters.observations_sent += 1;
            }
        }
        if let Some(h) = newest(&bus_health) {
            last_health = Some(h);
        }
        while let Some(e) = next(&events) {
            if event_pub
                .put(encode(&outbound::event_msg(&e, &layout, wall_ms())))
                .wait()
                .is_ok()
            {
                counters.events_sent += 1;
            }
        }
        let mut new_plan = false;
        while let Ok(Some(sample)) = actions.try_recv() {
            let bytes = sample.payload().to_bytes();
            let now = monotonic_ns();
            match gate.check(&bytes, now, &ranges) {
                Ok(chunk) => {
                    scheduler.insert(&chunk, now);
                    new_plan = true;
                }
                Err(r) => {
                    counters.last_rejection = r.to_string();
                    if warn_every.due(now) {
                        tracing::warn!(reason = r.reason(), "action refused: {r}");
                    }
                }
            }
        }
        // A new plan goes out at once, not at the next forwarding tick (up to 10 ms later).
        let due = forward_every.due(now);
        if new_plan || due {
            match scheduler.target(now) {
                // The last door: a value outside a calibrated range never leaves the agent,
                // whatever the scheduler made of the chunks.
                Some(target)
                    if !fleet_agent::gate::within(&ranges, &target.position, target.mask) =>
                {
                    counters.goals_withheld += 1;
                    scheduler.clear();
                    tracing::error!("a scheduled target outside the calibrated range was withheld and the plan dropped");
                }
                Some(target) => {
                    goal_seq += 1;
                    let frame = outbound::goal_frame(&target, layout.joint_count, goal_seq, now);
                    if publish(&goals, &frame).is_ok() {
                        counters.goals_forwarded += 1;
                    }
                }
                None => {}
            }
        }
        while let Ok(Some(query)) = status_queries.try_recv() {
            let mut status = status_json(
                &config,
                &gate,
                &scheduler,
                &counters,
                last_state.as_ref(),
                &layout,
                now,
            );
            status["buses"] = buses_json(last_health.as_ref());
            // Answered on the robot's own key: a fleet asking `nori/*/status` learns from the
            // key which robot answered (a reply on the query's wildcard would not be valid).
            if let Err(e) = query.reply(&status_key, status.to_string()).wait() {
                tracing::debug!("status reply: {e}");
            }
        }
        std::thread::sleep(POLL);
    }
    service.stopping();
    tracing::info!(robot = %id, accepted = gate.accepted(), forwarded = counters.goals_forwarded, "leaving the fleet");
    // The token, publishers and session close on drop: the fleet sees the robot leave.
    Ok(())
}

fn status_json(
    config: &AgentConfig,
    gate: &ActionGate,
    scheduler: &Scheduler,
    c: &Counters,
    state: Option<&telemetry::frames::JointState>,
    layout: &JointLayout,
    now: u64,
) -> serde_json::Value {
    let rejected: serde_json::Map<String, serde_json::Value> = REASONS
        .iter()
        .zip(gate.rejected())
        .map(|(r, n)| (r.to_string(), (*n).into()))
        .collect();
    serde_json::json!({
        "robot_id": config.robot_id,
        "versions": {"fleet_agent": env!("CARGO_PKG_VERSION"), "schema": SCHEMA_VERSION},
        "config": {
            "state_hz": config.telemetry.state_hz,
            "observation_hz": config.telemetry.observation_hz,
            "max_age_ms": config.actions.max_age_ms,
            "horizon_ms": config.actions.horizon_ms,
            "blend_new": config.actions.blend_new,
            "forward_hz": config.actions.forward_hz,
        },
        "health": {
            "joints": layout.joint_count,
            "state_age_ms": state.map(|s| now.saturating_sub(s.timestamp_ns) as f64 / 1e6),
            "safe_state": state.map(|s| s.flags & telemetry::frames::STATE_FLAG_SAFE_STATE != 0),
            "deadline_misses": state.map(|s| s.deadline_misses),
            "planned_steps": scheduler.planned_steps(),
        },
        "counters": {
            "state_sent": c.state_sent,
            "observations_sent": c.observations_sent,
            "events_sent": c.events_sent,
            "actions_accepted": gate.accepted(),
            "actions_rejected": rejected,
            "steps_dropped_past": scheduler.dropped_past_steps(),
            "plans_expired": scheduler.expired(),
            "goals_forwarded": c.goals_forwarded,
            "plans_dropped": c.plans_dropped,
            "goals_withheld": c.goals_withheld,
        },
        "last_rejection": c.last_rejection,
    })
}

/// The driver's error counts per bus, in its configuration's order (`bus` is that index, as in
/// the joint layout): how a fleet sees a failing cable or adapter before it fails.
fn buses_json(health: Option<&telemetry::frames::BusHealth>) -> serde_json::Value {
    use telemetry::frames::{BUS_HEALTH_CONNECTED, BUS_HEALTH_ENABLED};
    health
        .map(|h| h.buses())
        .unwrap_or_default()
        .iter()
        .enumerate()
        .map(|(i, b)| {
            serde_json::json!({
                "bus": i,
                "connected": b.flags & BUS_HEALTH_CONNECTED != 0,
                "enabled": b.flags & BUS_HEALTH_ENABLED != 0,
                "counters": b.counters,
            })
        })
        .collect()
}
