//! `supervisor`: the protection process. The loop is `supervisor::process`; this binary reads
//! its configuration and the trip record, and wires the state plane (iceoryx2) and the record's
//! file into it.

use anyhow::Result;
use clap::Parser;
use std::path::PathBuf;
use std::time::Instant;
use supervisor::process::{Change, Process, SupervisorIo};
use supervisor::SupervisorConfig;
use telemetry::frames::{
    Directives, GripFrame, Heartbeat, JointLayout, JointState, SupervisorCommand, SupervisorEvent,
};
use telemetry::latch::{self, LatchError};
use telemetry::motion::{LiftAllowance, LiftState};
use telemetry::plane::{self, newest, next, publish, Plane, Pub, Sub};
use telemetry::process::Exit;
use telemetry::process::{ProcessArgs, ServiceManager, Started};

#[derive(Parser)]
#[command(
    version,
    about = "Nori A3 supervisor: stall detection, thermal interlock, grip force"
)]
struct Args {
    #[command(flatten)]
    process: ProcessArgs,
    /// Seconds between status lines (0: none).
    #[arg(long, default_value_t = 5.0)]
    status_every: f64,
    /// Where latched trips are kept across restarts (one joint name per line; the bus-driver
    /// reads the same record); `<temp dir>/nori-<domain>-trips` when absent. Production:
    /// /var/lib/nori/trips.
    #[arg(long)]
    trip_file: Option<PathBuf>,
}

/// The supervisor's ports on the state plane, and its trip record.
struct Wired {
    layouts: Sub<JointLayout>,
    states: Sub<JointState>,
    commands: Sub<SupervisorCommand>,
    driver_beats: Sub<Heartbeat>,
    directives: Pub<Directives>,
    events: Pub<SupervisorEvent>,
    heartbeat: Pub<Heartbeat>,
    grip: Pub<GripFrame>,
    lift_states: Sub<LiftState>,
    lift_allowance: Pub<LiftAllowance>,
    trip_file: PathBuf,
}

impl SupervisorIo for Wired {
    fn layout(&mut self) -> Option<JointLayout> {
        newest(&self.layouts)
    }
    fn next_state(&mut self) -> Option<JointState> {
        next(&self.states)
    }
    fn next_command(&mut self) -> Option<SupervisorCommand> {
        next(&self.commands)
    }
    fn next_driver_beat(&mut self) -> Option<Heartbeat> {
        next(&self.driver_beats)
    }
    fn directives(&mut self, d: &Directives) {
        let _ = publish(&self.directives, d);
    }
    fn event(&mut self, e: &SupervisorEvent) {
        let _ = publish(&self.events, e);
    }
    fn heartbeat(&mut self, h: &Heartbeat) {
        let _ = publish(&self.heartbeat, h);
        // A subscriber that joined since the last event (a restarted fleet agent) gets the
        // recent events (the service's history) now, not at the next event: those of its
        // absence reach the robot's journal within a tenth of a second.
        if h.seq.is_multiple_of(20) {
            plane::offer_history(&self.events);
        }
    }
    fn grip(&mut self, g: &GripFrame) {
        let _ = publish(&self.grip, g);
    }
    fn save_trips(&mut self, joints: &[String]) -> Result<(), LatchError> {
        latch::save(&self.trip_file, joints)
    }
    fn next_lift_state(&mut self) -> Option<LiftState> {
        next(&self.lift_states)
    }
    fn lift_allowance(&mut self, a: &LiftAllowance) {
        let _ = publish(&self.lift_allowance, a);
    }
}

fn main() -> std::process::ExitCode {
    telemetry::process::finish(run(Args::parse()), |e| {
        e.is::<supervisor::logic::LayoutError>()
            .then_some(Exit::Config)
    })
}

/// The process; an error ends it with its fault class's exit code (ARCHITECTURE.md, "Exit
/// codes").
fn run(args: Args) -> Result<()> {
    let Some(Started { config, shutdown }) = args.process.start::<SupervisorConfig>()? else {
        return Ok(());
    };
    let run_for = args.process.run_for()?;
    let trip_file = args
        .trip_file
        .clone()
        .unwrap_or_else(|| latch::default_path(&args.process.domain));
    let trips = latch::load(&trip_file)?;
    let node = Plane::open(&args.process.domain, "supervisor")?;
    node.cleanup_dead();
    let mut io = Wired {
        layouts: node.subscriber(&plane::LAYOUT)?,
        states: node.subscriber(&plane::JOINT_STATE)?,
        commands: node.subscriber(&plane::COMMANDS)?,
        driver_beats: node.subscriber(&plane::DRIVER_HEARTBEAT)?,
        directives: node.publisher(&plane::DIRECTIVES)?,
        events: node.publisher(&plane::EVENTS)?,
        heartbeat: node.publisher(&plane::SUPERVISOR_HEARTBEAT)?,
        grip: node.publisher(&plane::GRIP)?,
        lift_states: node.subscriber(&plane::LIFT_STATE)?,
        lift_allowance: node.publisher(&plane::LIFT_ALLOWANCE)?,
        trip_file: trip_file.clone(),
    };
    tracing::info!(domain = %args.process.domain, "waiting for the driver's joint layout on {}", plane::LAYOUT.name);
    let mut service = ServiceManager::from_env();
    // Ready as soon as the plane is open: systemd starts the driver after this, and only the
    // driver's layout lets the supervisor supervise.
    service.ready("waiting for the driver's joint layout");
    let mut process = Process::new(config, trips, std::process::id());
    let mut last_status = Instant::now();
    supervisor::process::run(
        &mut process,
        &mut io,
        &shutdown,
        run_for,
        &mut |p, change| {
            // Kept alive only while the loop turns; before the layout is known that is all it does.
            service.keepalive(Instant::now());
            if let Some(Change::Supervising { joints, restored }) = change {
                if !restored.is_empty() {
                    tracing::warn!(buses = ?restored, file = %trip_file.display(),
                    "thermal trips latched before a restart stay latched until `nori reenable`");
                }
                service.status(&format!("supervising {joints} joints"));
                if let Some(layout) = p.supervisor().map(|s| *s.layout()) {
                    let names: Vec<&str> = layout.joint_names().collect();
                    tracing::info!(
                        joints,
                        buses = layout.bus_count,
                        "supervising {}",
                        names.join(", ")
                    );
                }
            }
            if args.status_every > 0.0 && last_status.elapsed().as_secs_f64() >= args.status_every {
                if let Some(s) = p.supervisor() {
                    let tripped: Vec<u32> = (0..s.layout().bus_count)
                        .filter(|&b| s.bus_tripped(b as usize))
                        .collect();
                    tracing::info!(frames = p.frames(), driver = ?p.driver(), tripped_buses = ?tripped, "supervising");
                }
                last_status = Instant::now();
            }
        },
    )?;
    service.stopping();
    tracing::info!(frames = process.frames(), "stopped");
    Ok(())
}
