//! `nori-lift`: the lift column on the state plane. The board's protocol and the column's
//! controller are the `lift` library (pure); this binary opens the board's serial line, homes
//! the column at start, takes heights from `nori/lift/command` and reports on
//! `nori/lift/state` every period, and what it did at exit (JSON on stdout).

use anyhow::{Context, Result};
use clap::Parser;
use lift::board::{self, Decoder, Message};
use lift::column::{LiftController, LiftEvent, LiftReading, LiftState as Controller};
use lift::config::LiftConfig;
use serialport::SerialPort;
use std::io::{Read, Write};
use std::path::PathBuf;
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::motion::{
    LiftAllowance, LiftState, LIFT_HOMING, LIFT_LINK_LOST, LIFT_OBSTRUCTED, LIFT_READY,
    LIFT_UNHOMED,
};
use telemetry::plane::{self, newest, next, publish, Plane};
use telemetry::process::{finish, Exit, ProcessArgs, ServiceManager, Started, Ticker};

#[derive(Parser)]
#[command(
    version,
    about = "Nori A3 lift: the column's board onto the state plane (homing, heights, obstruction stop)"
)]
struct Args {
    #[command(flatten)]
    process: ProcessArgs,
    /// Open the board at DIR/lift (the simulator's pseudo-terminal) instead of its device.
    #[arg(long, value_name = "DIR")]
    device_dir: Option<PathBuf>,
}

fn main() -> std::process::ExitCode {
    finish(serve(&Args::parse()), |e| {
        // The board not plugged in: restarting helps once it is.
        e.downcast_ref::<serialport::Error>()
            .map(|_| Exit::Unavailable)
    })
}

/// What the loop counted.
#[derive(Debug, Default, serde::Serialize)]
struct Counters {
    periods: u64,
    statuses: u64,
    drives: u64,
    commands: u64,
    commands_refused: u32,
    obstructions: u32,
    link_losses: u64,
}

fn serve(args: &Args) -> Result<()> {
    let Some(Started { config, shutdown }) = args.process.start::<LiftConfig>()? else {
        return Ok(());
    };
    let config = match &args.device_dir {
        Some(dir) => config.with_device_dir(dir),
        None => config,
    };
    let run_for = args.process.run_for()?;
    let mut port = open_board(&config)?;
    let node = Plane::open(&args.process.domain, "lift")?;
    node.cleanup_dead();
    let commands = node.subscriber(&plane::LIFT_COMMAND)?;
    let allowances = node.subscriber(&plane::LIFT_ALLOWANCE)?;
    let mut allowance = None::<LiftAllowance>;
    let states = node.publisher(&plane::LIFT_STATE)?;
    let mut service = ServiceManager::from_env();
    service.ready("homing the lift");
    let period = Duration::from_secs_f64(1.0 / config.rate_hz);
    let max_age_ns = config.command_max_age.as_nanos() as u64;
    let mut controller = LiftController::new(config.column);
    controller.home();
    let mut decoder = Decoder::new();
    let (mut reading, mut heard) = (None::<LiftReading>, Instant::now());
    let (mut velocity, mut goal) = (0.0, f32::NAN);
    let mut counters = Counters::default();
    let mut out = [0u8; 21];
    let mut buf = [0u8; 256];
    let started = Instant::now();
    let mut ticker = Ticker::new(period);
    while !shutdown.load(std::sync::atomic::Ordering::Relaxed)
        && run_for.is_none_or(|d| started.elapsed() < d)
    {
        service.keepalive(Instant::now());
        let now_ns = monotonic_ns();
        let t_s = now_ns as f64 * 1e-9;
        let fresh = newest_status(&mut port, &mut decoder, &mut buf);
        if let Some(s) = fresh {
            counters.statuses += 1;
            heard = Instant::now();
            reading = Some(LiftReading {
                t_s,
                counts: i64::from(s.counts),
                current_a: f64::from(s.current_ma) * 1e-3,
                at_lower: s.switches & 1 != 0,
                at_upper: s.switches & 2 != 0,
            });
        }
        let lost = heard.elapsed() > config.silence;
        if lost && reading.take().is_some() {
            // The board may have restarted (its counts with it): home again once it is back.
            tracing::warn!("the lift's board went silent: homing again when it answers");
            counters.link_losses += 1;
            controller.home();
        }
        while let Some(c) = next(&commands) {
            counters.commands += 1;
            match take_command(&mut controller, &c, now_ns, max_age_ns) {
                Ok(g) => goal = g as f32,
                Err(why) => {
                    counters.commands_refused += 1;
                    tracing::warn!(seq = c.seq, "lift command refused: {why}");
                }
            }
        }
        // Travel only on a live allowance of the supervisor's duty-cycle budget.
        if let Some(a) = newest(&allowances) {
            allowance = Some(a);
        }
        let (held, duty_wait_s) = held_back(allowance, now_ns);
        if let (Some(r), Some(_)) = (reading, fresh) {
            let (v, event) = controller.step(&r, held == 0);
            velocity = v;
            if let Some(e) = event {
                counters.obstructions += u32::from(matches!(e, LiftEvent::Obstruction { .. }));
                log_event(e);
            }
        }
        if !lost {
            let n = board::drive(velocity, &mut out);
            if port.write_all(&out[..n]).is_ok() {
                counters.drives += 1;
            }
        }
        let state = LiftState {
            seq: counters.periods + 1,
            timestamp_ns: now_ns,
            height_m: reading
                .and_then(|r| controller.height_m(&r))
                .map_or(f32::NAN, |h| h as f32),
            goal_m: goal,
            velocity_m_s: velocity as f32,
            current_a: reading.map_or(0.0, |r| r.current_a as f32),
            state: if lost {
                LIFT_LINK_LOST
            } else {
                state_code(controller.state())
            },
            switches: reading.map_or(0, |r| u8::from(r.at_lower) | (u8::from(r.at_upper) << 1)),
            held,
            reserved: 0,
            duty_wait_s,
            obstructions: counters.obstructions,
            commands_refused: counters.commands_refused,
            bad_frames: decoder.bad_frames as u32,
        };
        let _ = publish(&states, &state);
        counters.periods += 1;
        ticker.wait();
    }
    // Stop the motor on the way out (the board's watchdog would, 100 ms later).
    let n = board::drive(0.0, &mut out);
    let _ = port.write_all(&out[..n]);
    service.stopping();
    println!("{}", serde_json::json!({ "counters": counters }));
    Ok(())
}

/// The newest status the board sent since the last call (older ones are superseded).
fn newest_status(
    port: &mut serialport::TTYPort,
    decoder: &mut Decoder,
    buf: &mut [u8],
) -> Option<board::Status> {
    let mut fresh = None;
    while port.bytes_to_read().unwrap_or(0) > 0 {
        let Ok(n) = port.read(buf) else { break };
        decoder.push(&buf[..n], |m| {
            if let Message::Status(s) = m {
                fresh = Some(s);
            }
        });
    }
    fresh
}

/// A height command, unless it is stale or from the future (then why not).
fn take_command(
    controller: &mut LiftController,
    c: &telemetry::motion::LiftCommand,
    now_ns: u64,
    max_age_ns: u64,
) -> Result<f64, String> {
    let age = now_ns.saturating_sub(c.timestamp_ns);
    if age > max_age_ns || c.timestamp_ns > now_ns + 1_000_000 {
        return Err(format!("{} ms old", age / 1_000_000));
    }
    controller
        .set_goal(f64::from(c.height_m))
        .map_err(|e| e.to_string())
}

fn log_event(e: LiftEvent) {
    match e {
        LiftEvent::Obstruction { at_m, up } => {
            tracing::warn!(
                at_m,
                up,
                "the lift met an obstruction: stopped, backing off"
            )
        }
        LiftEvent::Homed => tracing::info!("the lift is homed"),
        LiftEvent::Reached(h) => tracing::info!(height_m = h, "the lift is there"),
    }
}

fn state_code(s: Controller) -> u8 {
    match s {
        Controller::Unhomed => LIFT_UNHOMED,
        Controller::Homing => LIFT_HOMING,
        Controller::Ready => LIFT_READY,
        Controller::Obstructed { .. } => LIFT_OBSTRUCTED,
    }
}

/// Whether travel is held back (0 no, 1 the duty budget is spent, 2 no live allowance: none
/// for 200 ms, no supervisor, no travel, as the driver holds without one), and the rest the
/// budget still needs, s.
fn held_back(allowance: Option<LiftAllowance>, now_ns: u64) -> (u8, f32) {
    match allowance.filter(|a| now_ns.saturating_sub(a.timestamp_ns) <= 200_000_000) {
        Some(a) if a.allowed == 1 => (0, 0.0),
        Some(a) => (1, a.seconds),
        None => (2, 0.0),
    }
}

/// The board's serial line, read without waiting.
fn open_board(config: &LiftConfig) -> Result<serialport::TTYPort> {
    serialport::new(config.device.to_string_lossy(), config.baud)
        .timeout(Duration::from_millis(1))
        .open_native()
        .with_context(|| format!("the lift's board at {}", config.device.display()))
}
