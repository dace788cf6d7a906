//! `nori-lift`: the lift column on the state plane. The board's protocol and the column's
//! controller are the `lift` library (pure); this binary opens the board's serial line, homes
//! the column at start, takes heights from `nori/lift/command` and reports on
//! `nori/lift/state` every period, and what it did at exit (JSON on stdout).

use anyhow::{Context, Result};
use clap::Parser;
use lift::board::{self, Decoder, Message};
use lift::column::{LiftController, LiftEvent, LiftReading, LiftState as Controller, Travel};
use lift::config::LiftConfig;
use serialport::SerialPort;
use std::io::{Read, Write};
use std::path::PathBuf;
use std::time::{Duration, Instant};
use telemetry::clock::{in_force, monotonic_ns};
use telemetry::motion::{
    LiftAllowance, LiftCommand, LiftState, LIFT_ALLOWANCE_LIFE_NS, LIFT_COMMAND_GOAL,
    LIFT_COMMAND_RELEASE, LIFT_HOMING, LIFT_JAMMED, LIFT_LINK_LOST, LIFT_OBSTRUCTED, LIFT_READY,
    LIFT_REFUSED_OPERATOR_STOP, LIFT_UNHOMED,
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
    /// Where a hold (an obstruction, a jam) is kept across restarts, so that a restarted
    /// nori-lift does not home down onto what it was held off; `<temp dir>/nori-<domain>-lift-hold`
    /// when absent. Production: /var/lib/nori/lift-hold.
    #[arg(long, value_name = "FILE")]
    hold_file: Option<PathBuf>,
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
    releases: u32,
    count_jumps: u32,
    board_over_current: u64,
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
    let states = node.publisher(&plane::LIFT_STATE)?;
    let mut service = ServiceManager::from_env();
    service.ready("homing the lift");
    let period = Duration::from_secs_f64(1.0 / config.rate_hz);
    let max_age_ns = config.command_max_age.as_nanos() as u64;
    let mut controller = LiftController::new(config.column);
    let hold_path = args.hold_file.clone().unwrap_or_else(|| {
        std::env::temp_dir().join(format!("nori-{}-lift-hold", args.process.domain))
    });
    let mut hold = HoldRecord::load(hold_path)?;
    match hold.recorded {
        Some(at_m) => {
            tracing::warn!(
                at_m,
                "the lift was held when its controller stopped: jammed until `nori lift release`"
            );
            controller.restore_hold(at_m);
        }
        None => controller.home(),
    }
    let mut decoder = Decoder::new();
    let mut lift = LiftLoop::new(controller);
    let mut out = [0u8; 21];
    let mut buf = [0u8; 256];
    let started = Instant::now();
    let mut ticker = Ticker::new(period);
    while !shutdown.load(std::sync::atomic::Ordering::Relaxed)
        && run_for.is_none_or(|d| started.elapsed() < d)
    {
        service.keepalive(Instant::now());
        let now_ns = monotonic_ns();
        let fresh = lift.read_board(&mut port, &mut decoder, &mut buf, now_ns as f64 * 1e-9);
        let lost = lift.check_link(config.silence);
        // The supervisor's word first: an operator's stop drops the goal before any command
        // of this period is taken.
        let word = lift.take_allowance(&allowances, now_ns);
        lift.take_commands(&commands, now_ns, max_age_ns);
        lift.step(fresh, period, word.travel);
        hold.keep(lift.controller.held_at_m());
        if !lost {
            lift.drive(&mut port, &mut out);
        }
        let state = lift.state(now_ns, lost, word, &decoder);
        let _ = publish(&states, &state);
        lift.counters.periods += 1;
        ticker.wait();
    }
    // Stop the motor on the way out (the board's watchdog would, 100 ms later).
    let n = board::drive(0.0, &mut out);
    let _ = port.write_all(&out[..n]);
    service.stopping();
    println!("{}", serde_json::json!({ "counters": lift.counters }));
    Ok(())
}

/// The supervisor's word on travel as it stands in one period.
#[derive(Debug, Clone, Copy)]
struct TravelWord {
    travel: Travel,
    /// What the duty budget still needs before travel, s.
    duty_wait_s: f32,
}

/// What the serve loop carries from one period to the next. Each phase of a period is one
/// method, called in the loop in the order that matters; none allocates or logs more than the
/// loop did inline.
struct LiftLoop {
    controller: LiftController,
    /// The board's last reading, none while its link is lost.
    reading: Option<LiftReading>,
    /// When the board last sent a status.
    heard: Instant,
    /// The speed last driven, m/s.
    velocity: f64,
    /// The board's fault bits in its last status.
    faults: u8,
    /// The supervisor's newest allowance seen.
    allowance: Option<LiftAllowance>,
    /// Why commands are being refused, so that each reason is logged once.
    refusing: Option<String>,
    counters: Counters,
}

impl LiftLoop {
    fn new(controller: LiftController) -> LiftLoop {
        LiftLoop {
            controller,
            reading: None,
            heard: Instant::now(),
            velocity: 0.0,
            faults: 0,
            allowance: None,
            refusing: None,
            counters: Counters::default(),
        }
    }

    /// Takes the board's newest status, if it sent one this period, as the reading at `t_s`;
    /// true when it did (only a fresh reading steps the controller).
    fn read_board(
        &mut self,
        port: &mut serialport::TTYPort,
        decoder: &mut Decoder,
        buf: &mut [u8],
        t_s: f64,
    ) -> bool {
        let Some(s) = newest_status(port, decoder, buf) else {
            return false;
        };
        self.counters.statuses += 1;
        self.heard = Instant::now();
        self.faults = s.faults;
        let over_current = s.faults & board::FAULT_OVER_CURRENT != 0;
        self.counters.board_over_current += u64::from(over_current);
        self.reading = Some(LiftReading {
            t_s,
            counts: i64::from(s.counts),
            current_a: f64::from(s.current_ma) * 1e-3,
            at_lower: s.switches & 1 != 0,
            at_upper: s.switches & 2 != 0,
            over_current,
        });
        true
    }

    /// Whether the board has been silent longer than `silence`; on the period it goes
    /// silent, the reading is dropped and the position counts as lost.
    fn check_link(&mut self, silence: Duration) -> bool {
        let lost = self.heard.elapsed() > silence;
        if lost && self.reading.take().is_some() {
            // The board may have restarted (its counts with it): home again once it is back.
            tracing::warn!("the lift's board went silent: homing again when it answers");
            self.counters.link_losses += 1;
            position_lost(&mut self.controller);
        }
        lost
    }

    /// Takes the supervisor's newest allowance and sets the travel it gives.
    fn take_allowance(
        &mut self,
        allowances: &plane::Sub<LiftAllowance>,
        now_ns: u64,
    ) -> TravelWord {
        if let Some(a) = newest(allowances) {
            // A stop counted since the last one seen drops the goal, even if a resume came
            // before this period saw it in force.
            if self.allowance.is_some_and(|b| b.stops != a.stops) {
                self.controller.set_travel(Travel::OperatorStop);
            }
            self.allowance = Some(a);
        }
        let (travel, duty_wait_s) = travel(self.allowance, now_ns);
        self.controller.set_travel(travel);
        TravelWord {
            travel,
            duty_wait_s,
        }
    }

    /// Takes every command that came since the last period, in order.
    fn take_commands(&mut self, commands: &plane::Sub<LiftCommand>, now_ns: u64, max_age_ns: u64) {
        while let Some(c) = next(commands) {
            self.counters.commands += 1;
            let outcome = take_command(&mut self.controller, &c, now_ns, max_age_ns);
            self.counters.releases += u32::from(outcome == Ok(Taken::Released));
            match outcome {
                Ok(_) => self.refusing = None,
                Err(why) => {
                    self.counters.commands_refused += 1;
                    // Said once per reason, not at the rate a plan streams it.
                    if self.refusing.as_ref() != Some(&why) {
                        tracing::warn!(seq = c.seq, "lift command refused: {why}");
                        self.refusing = Some(why);
                    }
                }
            }
        }
    }

    /// Steps the controller on a fresh reading; without one, keeps or drops the last speed.
    fn step(&mut self, fresh: bool, period: Duration, travel: Travel) {
        match self.reading {
            Some(r) if fresh => {
                let (v, event) = self.controller.step(&r);
                self.velocity = v;
                if let Some(e) = event {
                    self.counters.obstructions +=
                        u32::from(matches!(e, LiftEvent::Obstruction { .. }));
                    if matches!(e, LiftEvent::CountsJumped { .. }) {
                        self.counters.count_jumps += 1;
                        position_lost(&mut self.controller);
                    }
                    log_event(e);
                }
            }
            _ => {
                self.velocity = unread_speed(self.velocity, self.heard.elapsed(), period, travel);
            }
        }
    }

    /// Sends the board this period's speed.
    fn drive(&mut self, port: &mut serialport::TTYPort, out: &mut [u8; 21]) {
        let n = board::drive(self.velocity, out);
        if port.write_all(&out[..n]).is_ok() {
            self.counters.drives += 1;
        }
    }

    /// This period's state, as published.
    fn state(&self, now_ns: u64, lost: bool, word: TravelWord, decoder: &Decoder) -> LiftState {
        let reading = self.reading;
        LiftState {
            seq: self.counters.periods + 1,
            timestamp_ns: now_ns,
            height_m: reading
                .and_then(|r| self.controller.height_m(&r))
                .map_or(f32::NAN, |h| h as f32),
            goal_m: self.controller.goal_m().map_or(f32::NAN, |g| g as f32),
            velocity_m_s: self.velocity as f32,
            current_a: reading.map_or(0.0, |r| r.current_a as f32),
            state: if lost {
                LIFT_LINK_LOST
            } else {
                state_code(self.controller.state())
            },
            switches: reading.map_or(0, |r| u8::from(r.at_lower) | (u8::from(r.at_upper) << 1)),
            held: held_code(word.travel),
            board_faults: self.faults,
            duty_wait_s: word.duty_wait_s,
            obstructions: self.counters.obstructions,
            commands_refused: self.counters.commands_refused,
            bad_frames: decoder.bad_frames as u32,
        }
    }
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

/// The board went silent or its counts jumped (it may have restarted): a free column homes
/// again (once the board answers); a held one stays jammed until the operator's release.
fn position_lost(controller: &mut LiftController) {
    controller.board_lost();
    if controller.state() == Controller::Unhomed {
        controller.home();
    }
}

/// The hold kept on disk (`telemetry::latch`'s atomic record: one line, the height it is held
/// at), written only when it changes.
struct HoldRecord {
    path: PathBuf,
    recorded: Option<f64>,
}

impl HoldRecord {
    /// The record at `path` (none there: no hold; a line that does not read: held at an
    /// unknown height, which the operator's release clears like any hold).
    fn load(path: PathBuf) -> Result<HoldRecord> {
        let lines = telemetry::latch::load(&path)?;
        let recorded = lines.first().map(|l| l.parse::<f64>().unwrap_or(f64::NAN));
        Ok(HoldRecord { path, recorded })
    }

    /// Records `hold` if it changed; a failure is logged (a restart would then home).
    fn keep(&mut self, hold: Option<f64>) {
        let same = match (hold, self.recorded) {
            (Some(a), Some(b)) => a == b || (a.is_nan() && b.is_nan()),
            (a, b) => a.is_none() == b.is_none(),
        };
        if same {
            return;
        }
        let lines: Vec<String> = hold.iter().map(|h| h.to_string()).collect();
        match telemetry::latch::save(&self.path, &lines) {
            Ok(()) => self.recorded = hold,
            Err(e) => tracing::error!("{e}: a restarted nori-lift would home onto what holds it"),
        }
    }
}

/// What a command did.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Taken {
    /// A goal, clamped into the soft limits, m.
    Goal(f64),
    /// The operator's release.
    Released,
}

/// A command, unless it is stale or from the future (then why not).
fn take_command(
    controller: &mut LiftController,
    c: &LiftCommand,
    now_ns: u64,
    max_age_ns: u64,
) -> Result<Taken, String> {
    in_force(c.timestamp_ns, now_ns, max_age_ns).map_err(|e| e.to_string())?;
    match c.kind {
        LIFT_COMMAND_GOAL => controller
            .set_goal(f64::from(c.height_m))
            .map(Taken::Goal)
            .map_err(|e| e.to_string()),
        LIFT_COMMAND_RELEASE => {
            tracing::warn!(state = ?controller.state(), "the operator releases the lift");
            controller.release();
            Ok(Taken::Released)
        }
        other => Err(format!("unknown command kind {other}")),
    }
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
        LiftEvent::BackOffBlocked { at_m } => tracing::error!(
            at_m,
            "the lift's back-off got nowhere: stopped, jammed until `nori lift release`"
        ),
        LiftEvent::CountsJumped { counts } => tracing::error!(
            counts,
            "the lift's hall counts jumped (its board restarted?): homing again"
        ),
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
        Controller::Jammed { .. } => LIFT_JAMMED,
    }
}

/// The supervisor's word on travel, in force for 200 ms from its stamp (none: no supervisor,
/// no travel, as the driver holds without one), and with the budget spent the rest it still
/// needs, s.
fn travel(allowance: Option<LiftAllowance>, now_ns: u64) -> (Travel, f32) {
    match allowance.filter(|a| in_force(a.timestamp_ns, now_ns, LIFT_ALLOWANCE_LIFE_NS).is_ok()) {
        Some(a) if a.allowed == 1 => (Travel::Allowed, 0.0),
        Some(a) if a.refused == LIFT_REFUSED_OPERATOR_STOP => (Travel::OperatorStop, 0.0),
        Some(a) => (Travel::DutySpent, a.seconds),
        None => (Travel::NoSupervisor, 0.0),
    }
}

/// The speed for the board in a period with no fresh reading: the last one only while the
/// board was heard within two periods and travel is allowed. Without readings nothing checks
/// that speed (no obstruction, no switch), and the supervisor's word (a stop, no allowance)
/// only reaches the board through a step: a board whose STATUS stopped while it still takes
/// DRIVE would otherwise be driven blind until the link counts as lost.
fn unread_speed(last: f64, since_heard: Duration, period: Duration, travel: Travel) -> f64 {
    if since_heard <= 2 * period && travel == Travel::Allowed {
        last
    } else {
        0.0
    }
}

/// [`LiftState::held`]'s code.
fn held_code(travel: Travel) -> u8 {
    match travel {
        Travel::Allowed => 0,
        Travel::DutySpent => 1,
        Travel::NoSupervisor => 2,
        Travel::OperatorStop => 3,
    }
}

/// The board's serial line, read without waiting.
fn open_board(config: &LiftConfig) -> Result<serialport::TTYPort> {
    serialport::new(config.device.to_string_lossy(), config.baud)
        .timeout(Duration::from_millis(1))
        .open_native()
        .with_context(|| format!("the lift's board at {}", config.device.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_board_not_heard_or_a_travel_refused_gets_no_speed_unread() {
        let p = Duration::from_millis(10);
        assert_eq!(unread_speed(0.03, p, p, Travel::Allowed), 0.03);
        assert_eq!(unread_speed(0.03, 2 * p, p, Travel::Allowed), 0.03);
        assert_eq!(
            unread_speed(0.03, 2 * p + Duration::from_micros(1), p, Travel::Allowed),
            0.0
        );
        for t in [
            Travel::OperatorStop,
            Travel::NoSupervisor,
            Travel::DutySpent,
        ] {
            assert_eq!(unread_speed(-0.03, p, p, t), 0.0, "{t:?}");
        }
    }

    const MS: u64 = 1_000_000;

    fn allowance(timestamp_ns: u64) -> LiftAllowance {
        LiftAllowance {
            timestamp_ns,
            allowed: 1,
            ..LiftAllowance::default()
        }
    }

    /// An allowance is in force 200 ms from its stamp, and one stamped ahead of this clock
    /// (another clock, or any publisher on the topic) is none: it would let the column travel
    /// for as long as it is ahead after the supervisor died (hazard L8).
    #[test]
    fn the_lift_travels_only_on_an_allowance_in_force() {
        let now = 100_000 * MS;
        assert_eq!(
            travel(Some(allowance(now - 200 * MS)), now).0,
            Travel::Allowed
        );
        assert_eq!(
            travel(Some(allowance(now - 201 * MS)), now).0,
            Travel::NoSupervisor
        );
        assert_eq!(
            travel(Some(allowance(now + 10_000 * MS)), now + 5_000 * MS).0,
            Travel::NoSupervisor
        );
        assert_eq!(travel(None, now).0, Travel::NoSupervisor);
    }

    /// A command is taken only while in force: neither stale nor stamped ahead (hazard L10).
    #[test]
    fn a_lift_command_stale_or_from_the_future_is_refused_and_changes_nothing() {
        let mut c = LiftController::new(lift::column::ColumnConfig::A3);
        let before = c.state();
        let now = 100_000 * MS;
        // The operator's release: taken whatever the column's state, when in force.
        let release = |timestamp_ns| LiftCommand {
            seq: 1,
            timestamp_ns,
            height_m: 0.0,
            kind: telemetry::motion::LIFT_COMMAND_RELEASE,
        };
        for stamp in [now - 501 * MS, now + 50 * MS] {
            assert!(take_command(&mut c, &release(stamp), now, 500 * MS).is_err());
            assert_eq!(c.state(), before);
        }
        assert_eq!(
            take_command(&mut c, &release(now - 500 * MS), now, 500 * MS),
            Ok(Taken::Released)
        );
    }
}
