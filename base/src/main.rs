//! `nori-base`: the differential base's controller on the state plane, and the whole body's
//! frames for tools. The controller is `base::controller` and the frames `base::frames` (pure);
//! this binary moves their frames each period and reports what it did at exit (JSON on stdout).

use anyhow::{Context, Result};
use base::config::BaseConfig;
use base::controller::Controller;
use base::frames::BodyFramer;
use body::kinematics::Body;
use body::RobotDescription;
use clap::Parser;
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::frames::JointLayout;
use telemetry::motion::BaseState;
use telemetry::plane::{self, newest, next, publish, Plane};
use telemetry::process::{finish, ProcessArgs, ServiceManager, Started, Ticker};
use telemetry::sensors::LidarScan;
use telemetry::{GoalFrame, JointState};

#[derive(Parser)]
#[command(
    version,
    about = "Nori A3 base controller: velocity commands to the wheels, odometry, the lidar's protective field"
)]
struct Args {
    #[command(flatten)]
    process: ProcessArgs,
    /// The robot description whose arm chains and lift place the body's frames
    /// (`nori/body/frames`); the embedded Nori A3 when absent.
    #[arg(long, value_name = "FILE")]
    robot: Option<std::path::PathBuf>,
}

fn main() -> std::process::ExitCode {
    finish(serve(&Args::parse()), |_| None)
}

/// What the loop counted.
#[derive(Debug, Default, serde::Serialize)]
struct Counters {
    periods: u64,
    goals_sent: u64,
    commands: u64,
    commands_refused: u64,
    state_frames: u64,
    scans: u64,
    body_frames: u64,
    publish_errors: u64,
}

fn serve(args: &Args) -> Result<()> {
    let Some(Started { config, shutdown }) = args.process.start::<BaseConfig>()? else {
        return Ok(());
    };
    let description = match &args.robot {
        Some(path) => RobotDescription::load(path)?,
        None => RobotDescription::nori_a3(),
    };
    let mut framer = BodyFramer::new(
        Body::from_description(&description).context("the robot description's arm chains")?,
    );
    let run_for = args.process.run_for()?;
    let node = Plane::open(&args.process.domain, "base")?;
    node.cleanup_dead();
    let layouts = node.subscriber(&plane::LAYOUT)?;
    let states = node.subscriber(&plane::JOINT_STATE)?;
    let commands = node.subscriber(&plane::BASE_COMMAND)?;
    let scans = node.subscriber(&plane::LIDAR_SCAN)?;
    let lifts = node.subscriber(&plane::LIFT_STATE)?;
    let body_frames = node.publisher(&plane::BODY_FRAMES)?;
    let goals = node.publisher(&plane::WHEEL_GOALS)?;
    let base_state = node.publisher(&plane::BASE_STATE)?;
    if config.controller.field.is_none() {
        tracing::warn!(
            "no lidar configured ([field] lidar = false): the base moves without a protective field"
        );
    }
    let period = Duration::from_secs_f64(1.0 / config.rate_hz);
    let mut controller = Controller::new(config.controller);
    let mut service = ServiceManager::from_env();
    service.ready("waiting for the driver's layout");
    let (mut layout, mut scan) = (None::<JointLayout>, None::<LidarScan>);
    let mut joints = None::<JointState>;
    let mut goal = GoalFrame::default();
    let mut counters = Counters::default();
    let mut last_refusal_log = None::<Instant>;
    let started = Instant::now();
    let mut ticker = Ticker::new(period);
    while !shutdown.load(std::sync::atomic::Ordering::Relaxed)
        && run_for.is_none_or(|d| started.elapsed() < d)
    {
        service.keepalive(Instant::now());
        if let Some(l) = newest(&layouts) {
            if layout.as_ref() != Some(&l) {
                // A driver on other buses (a test, a bench) has no wheels: wait for one that has.
                match controller.set_layout(&l) {
                    Ok(()) => tracing::info!(
                        "driving the base's wheels; commands on {}",
                        plane::BASE_COMMAND.name
                    ),
                    Err(e) => tracing::warn!("{e}: not driving until it has them"),
                }
                framer.set_layout(&l);
                layout = Some(l);
            }
        }
        while let Some(s) = next(&states) {
            controller.on_state(&s);
            counters.state_frames += 1;
            joints = Some(s);
        }
        if let Some(l) = newest(&lifts) {
            framer.on_lift(&l);
        }
        let now = monotonic_ns();
        while let Some(c) = next(&commands) {
            counters.commands += 1;
            if let Err(why) = controller.on_command(&c, now) {
                counters.commands_refused += 1;
                // Counted always, logged at most once a second.
                if last_refusal_log.is_none_or(|t: Instant| t.elapsed() > Duration::from_secs(1)) {
                    tracing::warn!(seq = c.seq, "base command refused: {why}");
                    last_refusal_log = Some(Instant::now());
                }
            }
        }
        if let Some(s) = newest(&scans) {
            scan = Some(s);
            counters.scans += 1;
        }
        let (send, state): (bool, BaseState) = controller.tick(now, scan.as_ref(), &mut goal);
        if send {
            counters.goals_sent += 1;
            if publish(&goals, &goal).is_err() {
                counters.publish_errors += 1;
            }
        }
        if publish(&base_state, &state).is_err() {
            counters.publish_errors += 1;
        }
        if let Some(j) = &joints {
            let frames = framer.frame(j, &state, now);
            counters.body_frames += 1;
            if publish(&body_frames, &frames).is_err() {
                counters.publish_errors += 1;
            }
        }
        counters.periods += 1;
        ticker.wait();
    }
    service.stopping();
    println!("{}", serde_json::json!({ "counters": counters }));
    Ok(())
}
