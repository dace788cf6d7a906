//! `supervisor`: the protection process. Reads every joint-state frame, publishes directives
//! (torque limits, bus enables), events, grip force and its heartbeat; watches the driver's.
//!
//! Its heartbeat means "supervising": it is sent only once the driver's layout is known, so a
//! driver never leaves its safe state for a supervisor that cannot yet supervise.

use anyhow::{Context, Result};
use clap::Parser;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};
use supervisor::logic::NONE;
use supervisor::{Supervisor, SupervisorConfig};
use telemetry::clock::monotonic_ns;
use telemetry::frames::{EventKind, Heartbeat, JointLayout, Peer, SupervisorEvent};
use telemetry::latch;
use telemetry::plane::{self, newest, next, publish, Plane};
use telemetry::process::ServiceManager;
use telemetry::watchdog::{Liveness, Watchdog};

#[derive(Parser)]
#[command(
    version,
    about = "Nori A3 supervisor: stall detection, thermal interlock, grip force"
)]
struct Args {
    /// Configuration file (TOML); the embedded default when absent.
    #[arg(long)]
    config: Option<PathBuf>,
    /// State-plane domain.
    #[arg(long, default_value = plane::DEFAULT_DOMAIN)]
    domain: String,
    /// Stop after this many seconds.
    #[arg(long)]
    run_for: Option<f64>,
    /// Seconds between status lines (0: none).
    #[arg(long, default_value_t = 5.0)]
    status_every: f64,
    /// Print the default configuration and exit.
    #[arg(long)]
    print_default_config: bool,
    /// Where latched trips are kept across restarts (one joint name per line; the bus-driver
    /// reads the same record); `<temp dir>/nori-<domain>-trips` when absent. Production:
    /// /var/lib/nori/trips.
    #[arg(long)]
    trip_file: Option<PathBuf>,
}

/// Directives and heartbeat period.
const PUBLISH_EVERY: Duration = Duration::from_millis(5);
/// Poll period of the loop.
const POLL: Duration = Duration::from_millis(1);

fn describe(e: &SupervisorEvent, layout: &JointLayout) -> String {
    let joint = layout
        .joints()
        .get(e.joint as usize)
        .map_or("-", |j| j.name());
    format!(
        "{:?} joint {} bus {} level {} value {:.2}",
        e.kind(),
        joint,
        e.bus,
        e.level,
        e.value
    )
}

fn main() -> Result<()> {
    let args = Args::parse();
    if args.print_default_config {
        print!("{}", supervisor::config::DEFAULT_CONFIG_TOML);
        return Ok(());
    }
    telemetry::process::init_logging();
    let config = match &args.config {
        Some(p) => SupervisorConfig::load(p)?,
        None => SupervisorConfig::embedded()?,
    };
    let trip_file = args
        .trip_file
        .clone()
        .unwrap_or_else(|| latch::default_path(&args.domain));
    let mut recorded_trips = latch::load(&trip_file)?;
    let mut recorded_mask = 0u32;
    let shutdown = telemetry::process::stop_flag().context("installing signal handlers")?;
    let node = Plane::open(&args.domain, "supervisor")?;
    node.cleanup_dead();
    let states = node.subscriber(&plane::JOINT_STATE)?;
    let layouts = node.subscriber(&plane::LAYOUT)?;
    let driver_beats = node.subscriber(&plane::DRIVER_HEARTBEAT)?;
    let commands = node.subscriber(&plane::COMMANDS)?;
    let directives_out = node.publisher(&plane::DIRECTIVES)?;
    let events_out = node.publisher(&plane::EVENTS)?;
    let heartbeat_out = node.publisher(&plane::SUPERVISOR_HEARTBEAT)?;
    let grip_out = node.publisher(&plane::GRIP)?;
    tracing::info!(domain = %args.domain, "waiting for the driver's joint layout on {}", plane::LAYOUT.name);

    let mut sup: Option<Supervisor> = None;
    let mut service = ServiceManager::from_env();
    // Ready as soon as the plane is open: systemd starts the driver after this, and only the
    // driver's layout lets the supervisor supervise.
    service.ready("waiting for the driver's joint layout");
    let mut driver = Watchdog::new(Duration::from_millis(config.driver_timeout_ms));
    let mut driver_state = Liveness::Unknown;
    let mut heartbeat = Heartbeat {
        pid: std::process::id(),
        peer: Peer::Supervisor as u8,
        ..Heartbeat::default()
    };
    let start = Instant::now();
    let (mut last_publish, mut last_status) = (Instant::now(), Instant::now());
    let mut frames = 0u64;
    let mut last_state = None;
    while !shutdown.load(Ordering::Relaxed)
        && args
            .run_for
            .is_none_or(|t| start.elapsed().as_secs_f64() < t)
    {
        let now = monotonic_ns();
        if let Some(layout) = newest(&layouts) {
            if sup.as_ref().is_none_or(|s| *s.layout() != layout) {
                let mut fresh = Supervisor::new(&layout, config.clone())?;
                let restored = fresh.restore_trips(&recorded_trips, now);
                if !restored.is_empty() {
                    tracing::warn!(
                        buses = ?restored,
                        file = %trip_file.display(),
                        "thermal trips latched before a restart stay latched until `nori reenable`"
                    );
                }
                recorded_mask = fresh.tripped_buses();
                service.status(&format!("supervising {} joints", layout.joint_count));
                sup = Some(fresh);
                let names: Vec<&str> = layout.joints().iter().map(|j| j.name()).collect();
                tracing::info!(
                    joints = layout.joint_count,
                    buses = layout.bus_count,
                    "supervising {}",
                    names.join(", ")
                );
            }
        }
        // Kept alive only while the loop turns; before the layout is known that is all it does.
        service.keepalive(Instant::now());
        let Some(s) = sup.as_mut() else {
            std::thread::sleep(POLL);
            continue;
        };
        while let Some(state) = next(&states) {
            frames += 1;
            if s.on_state(&state) {
                let _ = publish(&grip_out, s.grip());
            }
            last_state = Some(state);
        }
        while let Some(cmd) = next(&commands) {
            s.command(&cmd, now);
        }
        while let Some(beat) = next(&driver_beats) {
            if driver.beat(now, beat.pid) {
                s.event(now, EventKind::DriverBack, NONE, NONE, 0, beat.pid as f32);
            }
        }
        match (driver_state, driver.liveness(now)) {
            (Liveness::Alive, Liveness::Lost) => {
                let silence = driver.silence(now).unwrap_or_default();
                s.event(
                    now,
                    EventKind::DriverLost,
                    NONE,
                    NONE,
                    0,
                    silence.as_secs_f32(),
                );
                driver_state = Liveness::Lost;
            }
            (Liveness::Lost, Liveness::Alive) => {
                s.event(now, EventKind::DriverBack, NONE, NONE, 0, 0.0);
                driver_state = Liveness::Alive;
            }
            (_, l) => driver_state = l,
        }
        let layout = *s.layout();
        for e in s.drain_events() {
            let mut line = describe(&e, &layout);
            // A stall names what was seen: where the joint was, where it was sent, its current.
            if let (Some(EventKind::Stall), Some(st)) = (e.kind(), last_state.as_ref()) {
                if let Some(j) = st.joints().get(e.joint as usize) {
                    line += &format!(
                        " | frame {} position {:.3} goal {:.3} current {:.2} A load {:.2}",
                        st.seq, j.position_rad, j.goal_rad, j.current_a, j.load
                    );
                }
            }
            match e.kind() {
                Some(EventKind::ThermalTrip | EventKind::OutputLost | EventKind::DriverLost) => {
                    tracing::warn!("{line}")
                }
                _ => tracing::info!("{line}"),
            }
            let _ = publish(&events_out, &e);
        }
        // Trips outlive this process: recorded before the directives that announce them.
        if s.tripped_buses() != recorded_mask {
            recorded_mask = s.tripped_buses();
            // Latches of joints this layout does not have (a driver started on some of the
            // buses) are not this instance's to release: they stay in the record.
            let names: Vec<&str> = layout.joints().iter().map(|j| j.name()).collect();
            recorded_trips.retain(|n| !names.contains(&n.as_str()));
            recorded_trips.extend(s.tripped_joints());
            if let Err(e) = latch::save(&trip_file, &recorded_trips) {
                tracing::error!("{e}: a restart would forget the latched trips, and the driver keeps a released bus off");
            }
        }
        // Directives go out every period as the heartbeat of the decision, and at once when they
        // change (a trip must not wait for the next period).
        let changed = s.directives_changed();
        if changed || last_publish.elapsed() >= PUBLISH_EVERY {
            let _ = publish(&directives_out, &s.directives(now));
        }
        if last_publish.elapsed() >= PUBLISH_EVERY {
            last_publish = Instant::now();
            heartbeat.seq += 1;
            heartbeat.timestamp_ns = now;
            let _ = publish(&heartbeat_out, &heartbeat);
        }
        if args.status_every > 0.0 && last_status.elapsed().as_secs_f64() >= args.status_every {
            let tripped: Vec<u32> = (0..layout.bus_count)
                .filter(|&b| s.bus_tripped(b as usize))
                .collect();
            tracing::info!(frames, driver = ?driver_state, tripped_buses = ?tripped, "supervising");
            last_status = Instant::now();
        }
        std::thread::sleep(POLL);
    }
    service.stopping();
    tracing::info!(frames, "stopped");
    Ok(())
}
