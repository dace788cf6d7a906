//! `nori state` and `nori goal`: look at and move the robot through the state plane, its arms'
//! joints and wheels (from the driver), the lift and the base (from their controllers).

use anyhow::{bail, Context, Result};
use clap::Args;
use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};
use telemetry::frames::JointLayout;
use telemetry::motion::{lift_state_name, BaseState, LiftCommand, LiftState};
use telemetry::plane::{self, Plane};
use telemetry::GoalFrame;

/// How long `goal` and `reenable` wait for the driver's layout (published every second).
const LAYOUT_TIMEOUT: Duration = Duration::from_secs(2);

/// Options shared by the plane tools.
#[derive(Args, Debug)]
pub struct PlaneArgs {
    /// State-plane domain.
    #[arg(long, default_value = plane::DEFAULT_DOMAIN)]
    pub domain: String,
    /// No longer used: joint and bus names come from the layout the running driver publishes
    /// (accepted so that existing scripts keep working).
    #[arg(long, hide = true)]
    pub driver_config: Option<PathBuf>,
}

impl PlaneArgs {
    /// Opens the plane as `tool` and waits up to `timeout` for the running driver's layout: the
    /// one source of joint and bus names.
    pub fn open(&self, tool: &str, timeout: Duration) -> Result<(Plane, JointLayout)> {
        if self.driver_config.is_some() {
            eprintln!(
                "nori {tool}: --driver-config is ignored: names come from the running driver's layout"
            );
        }
        let node = self.node(tool)?;
        let layouts = node.subscriber(&plane::LAYOUT)?;
        let layout = plane::wait_for_layout(&layouts, &self.domain, timeout, None)?;
        Ok((node, layout))
    }

    /// Opens the plane as `tool`, without waiting for a driver (what does not name joints or
    /// buses: the operator's stop, the lift).
    pub fn node(&self, tool: &str) -> Result<Plane> {
        Ok(Plane::open(
            &self.domain,
            &format!("nori-{tool}-{}", std::process::id()),
        )?)
    }
}

/// Options of `nori state`.
#[derive(Args, Debug)]
pub struct StateArgs {
    #[command(flatten)]
    plane: PlaneArgs,
    /// Wait this long for a frame, s.
    #[arg(long, default_value_t = 2.0)]
    timeout: f64,
    /// Print the frame as JSON.
    #[arg(long)]
    json: bool,
}

/// Options of `nori goal`.
#[derive(Args, Debug)]
pub struct GoalArgs {
    #[command(flatten)]
    plane: PlaneArgs,
    /// Goals as JOINT=RAD (rad/s for wheels), e.g. left_elbow=-1.0, and `lift=M` for the lift's
    /// height above its lowest (clamped into its soft limits by `nori-lift`). The base takes a
    /// velocity that must be renewed: `nori base`.
    #[arg(required = true)]
    goals: Vec<String>,
}

/// Prints the newest joint state.
pub fn state(args: &StateArgs) -> Result<()> {
    let timeout = Duration::try_from_secs_f64(args.timeout).with_context(|| {
        format!(
            "--timeout {}: not a non-negative number of seconds",
            args.timeout
        )
    })?;
    let (node, layout) = args.plane.open("state", timeout)?;
    let names: Vec<String> = layout.joint_names().map(str::to_string).collect();
    let bus_names: Vec<String> = layout.bus_names().map(str::to_string).collect();
    let sub = node.subscriber(&plane::JOINT_STATE)?;
    let health_sub = node.subscriber(&plane::BUS_HEALTH)?;
    let until = Instant::now() + timeout;
    let frame = loop {
        if let Some(f) = plane::newest(&sub) {
            break f;
        }
        if Instant::now() > until {
            bail!(
                "no joint state on domain {:?} within {} s: is the bus-driver running?",
                args.plane.domain,
                args.timeout
            );
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    // Published a few times a second (history 1): the newest is there at once, or soon.
    let health_until = Instant::now() + Duration::from_millis(300);
    let health = loop {
        let h = plane::newest(&health_sub);
        if h.is_some() || Instant::now() > health_until {
            break h;
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    let (lift, base) = body_states(&node)?;
    let buses: Vec<(String, telemetry::frames::BusHealthEntry)> = health
        .iter()
        .flat_map(|h| h.buses().iter().copied().enumerate())
        .map(|(i, b)| {
            (
                bus_names
                    .get(i)
                    .cloned()
                    .unwrap_or_else(|| format!("bus{i}")),
                b,
            )
        })
        .collect();
    if args.json {
        let joints: Vec<_> = frame
            .joints()
            .iter()
            .enumerate()
            .map(|(i, j)| {
                serde_json::json!({
                    "joint": names.get(i), "valid": j.is_valid(), "position_rad": j.position_rad, "goal_rad": j.goal_rad,
                    "velocity_rad_s": j.velocity_rad_s, "current_a": j.current_a, "temperature_c": j.temperature_c,
                    "voltage_v": j.voltage_v, "load": j.load, "status": j.status, "torque_enabled": j.torque_enabled == 1,
                })
            })
            .collect();
        let buses: Vec<_> = buses
            .iter()
            .map(|(name, b)| serde_json::json!({"bus": name, "health": b}))
            .collect();
        let json = serde_json::json!({"seq": frame.seq, "deadline_misses": frame.deadline_misses, "joints": joints, "buses": buses,
            "lift": lift.as_ref().map(lift_json), "base": base.as_ref().map(base_json)});
        return quiet_pipe(writeln!(std::io::stdout(), "{json}"));
    }
    let mut out = std::io::stdout().lock();
    quiet_pipe(print_table(&mut out, &frame, &names).and_then(|()| {
        for (name, b) in &buses {
            writeln!(out, "bus {name}: {b}")?;
        }
        match &lift {
            Some(l) => writeln!(out, "lift: {}", lift_line(l))?,
            None => writeln!(out, "lift: no state (nori-lift not running)")?,
        }
        match &base {
            Some(b) => writeln!(out, "base: {b}")?,
            None => writeln!(out, "base: no state (nori-base not running)")?,
        }
        Ok(())
    }))
}

/// The lift's and the base's newest states, if their controllers publish (each does at 50 Hz or
/// more: a tenth of a second says whether it runs).
fn body_states(node: &Plane) -> Result<(Option<LiftState>, Option<BaseState>)> {
    let lifts = node.subscriber(&plane::LIFT_STATE)?;
    let bases = node.subscriber(&plane::BASE_STATE)?;
    let until = Instant::now() + Duration::from_millis(100);
    let (mut lift, mut base) = (None, None);
    while Instant::now() < until && (lift.is_none() || base.is_none()) {
        lift = plane::newest(&lifts).or(lift);
        base = plane::newest(&bases).or(base);
        std::thread::sleep(Duration::from_millis(5));
    }
    Ok((lift, base))
}

/// The lift's newest state, if `nori-lift` publishes (it does at 50 Hz: a tenth of a second
/// says whether it runs).
pub fn lift_state(node: &Plane) -> Result<Option<LiftState>> {
    Ok(body_states(node)?.0)
}

/// Why the lift's travel is held back, if it is.
fn lift_held(l: &LiftState) -> Option<String> {
    match l.held {
        0 => None,
        1 => Some(format!(
            "duty-cycle budget spent: travel again in {:.0} s",
            l.duty_wait_s
        )),
        3 => Some("the operator's stop (`nori resume`)".into()),
        _ => Some("no allowance from the supervisor".into()),
    }
}

fn lift_line(l: &LiftState) -> String {
    let mut line = format!(
        "{}  height {:.3} m  goal {:.3} m  speed {:+.3} m/s  current {:.2} A",
        lift_state_name(l.state),
        l.height_m,
        l.goal_m,
        l.velocity_m_s,
        l.current_a
    );
    if let Some(why) = lift_held(l) {
        line.push_str(&format!("  [held: {why}]"));
    }
    line
}

fn lift_json(l: &LiftState) -> serde_json::Value {
    let finite = |x: f32| x.is_finite().then_some(x);
    serde_json::json!({"state": lift_state_name(l.state), "height_m": finite(l.height_m), "goal_m": finite(l.goal_m),
        "velocity_m_s": l.velocity_m_s, "current_a": l.current_a, "held": lift_held(l),
        "obstructions": l.obstructions, "commands_refused": l.commands_refused})
}

fn base_json(b: &BaseState) -> serde_json::Value {
    serde_json::json!({"x_m": b.x_m, "y_m": b.y_m, "heading_rad": b.theta_rad, "linear_m_s": b.linear_m_s,
        "angular_rad_s": b.angular_rad_s, "sent_linear_m_s": b.commanded_linear_m_s,
        "sent_angular_rad_s": b.commanded_angular_rad_s, "travelled_m": b.travelled_m,
        "field_distance_m": (b.field_distance_m >= 0.0).then_some(b.field_distance_m),
        "flags": b.flag_names().collect::<Vec<_>>(), "commands_refused": b.commands_refused})
}

/// A closed pipe (`nori state | head`) ends the output quietly.
fn quiet_pipe(r: std::io::Result<()>) -> Result<()> {
    match r {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        other => Ok(other?),
    }
}

fn print_table(
    out: &mut impl Write,
    frame: &telemetry::JointState,
    names: &[String],
) -> std::io::Result<()> {
    writeln!(
        out,
        "cycle {}  deadline misses {}",
        frame.seq, frame.deadline_misses
    )?;
    writeln!(
        out,
        "{:<22} {:>9} {:>9} {:>8} {:>6} {:>6}  status",
        "joint", "pos rad", "goal rad", "curr A", "°C", "V"
    )?;
    for (i, j) in frame.joints().iter().enumerate() {
        let name = names.get(i).map_or("?", |s| s.as_str());
        if !j.is_valid() {
            writeln!(out, "{name:<22} {:>9}", "missing")?;
            continue;
        }
        writeln!(
            out,
            "{name:<22} {:>9.3} {:>9.3} {:>8.3} {:>6.0} {:>6.1}  {}",
            j.position_rad,
            j.goal_rad,
            j.current_a,
            j.temperature_c,
            j.voltage_v,
            feetech::ServoStatus(j.status)
        )?;
    }
    Ok(())
}

/// What `nori goal` sends: joint goals to the driver, a height to the lift.
#[derive(Debug)]
pub struct Goals {
    /// The joints' goals (mask 0: none).
    pub joints: GoalFrame,
    /// The lift's height, m.
    pub lift_m: Option<f32>,
}

/// The goals `goals` (`JOINT=RAD` or `lift=M` each) over the driver's joints `names`: refused,
/// with the reason, for an unknown joint, a joint named twice, or a value that is not a finite
/// number (the driver would refuse the whole frame; better said here, before it is sent).
pub fn parse_goals(names: &[String], goals: &[String]) -> Result<Goals> {
    let mut frame = GoalFrame {
        joint_count: names.len() as u32,
        ..GoalFrame::default()
    };
    let mut lift_m = None;
    for g in goals {
        let (joint, value) = g
            .split_once('=')
            .with_context(|| format!("{g:?}: expected JOINT=RAD"))?;
        if joint == "base" {
            bail!("{g:?}: the base takes a velocity that must be renewed, not a goal: nori base LINEAR ANGULAR --for SECONDS");
        }
        if joint == "lift" {
            let h: f32 = value
                .parse()
                .with_context(|| format!("{g:?}: {value:?} is not a number"))?;
            if !h.is_finite() {
                bail!("{g:?}: {value:?} is not a finite number");
            }
            if lift_m.replace(h).is_some() {
                bail!("{g:?}: the lift is given twice");
            }
            continue;
        }
        let i = names
            .iter()
            .position(|n| n == joint)
            .with_context(|| format!("no joint {joint:?} (have: {})", names.join(", ")))?;
        let v: f32 = value
            .parse()
            .with_context(|| format!("{g:?}: {value:?} is not a number"))?;
        if !v.is_finite() {
            bail!("{g:?}: {value:?} is not a finite number");
        }
        if frame.mask & (1 << i) != 0 {
            bail!("{g:?}: joint {joint:?} is given twice");
        }
        frame.mask |= 1 << i;
        frame.position_rad[i] = v;
    }
    Ok(Goals {
        joints: frame,
        lift_m,
    })
}

/// Publishes one goal frame.
pub fn goal(args: &GoalArgs) -> Result<()> {
    let (node, layout) = args.plane.open("goal", LAYOUT_TIMEOUT)?;
    let names: Vec<String> = layout.joint_names().map(str::to_string).collect();
    let Goals { mut joints, lift_m } = parse_goals(&names, &args.goals)?;
    // A wheel goal would reach the wheel with no protective field and no ramp: the base's
    // protections are `nori-base`'s, reached through `nori base`.
    if let Some(w) = layout.joints().iter().enumerate().find(|(i, j)| {
        joints.mask & (1 << i) != 0 && j.role() == telemetry::frames::JointRole::Wheel
    }) {
        bail!(
            "{} is a wheel: the base is driven through its protections (lidar field, ramp, timeout) with `nori base LINEAR ANGULAR --for SECONDS`",
            w.1.name()
        );
    }
    let publisher = node.publisher(&plane::GOALS)?;
    let lift_commands = node.publisher(&plane::LIFT_COMMAND)?;
    let lift_states = node.subscriber(&plane::LIFT_STATE)?;
    // Give the driver's and the lift's subscribers a moment to connect to fresh publishers.
    std::thread::sleep(Duration::from_millis(100));
    let now = telemetry::clock::monotonic_ns();
    if joints.mask != 0 {
        joints.timestamp_ns = now;
        joints.seq = 1;
        plane::publish(&publisher, &joints)?;
        eprintln!("nori goal: sent {} joint goal(s)", joints.mask.count_ones());
    }
    if let Some(height_m) = lift_m {
        let command = LiftCommand {
            seq: 1,
            timestamp_ns: now,
            height_m,
            kind: telemetry::motion::LIFT_COMMAND_GOAL,
        };
        plane::publish(&lift_commands, &command)?;
    }
    // Keep the publishers alive until the driver's and the lift's next cycles took the frames.
    std::thread::sleep(Duration::from_millis(50));
    if let Some(h) = lift_m {
        // The lift's controller says what it made of it (its goal in force, clamped).
        let until = Instant::now() + Duration::from_millis(300);
        let mut answer = None;
        while Instant::now() < until {
            answer = plane::newest(&lift_states).or(answer);
            if answer.is_some_and(|l: LiftState| l.timestamp_ns > now) {
                break;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        match answer {
            Some(l) => eprintln!("nori goal: lift {h} m sent; the lift: {}", lift_line(&l)),
            None => bail!("lift {h} m sent, but no lift state on the plane: is nori-lift running?"),
        }
    }
    Ok(())
}

/// Options of `nori reenable`.
#[derive(Args, Debug)]
pub struct ReenableArgs {
    #[command(flatten)]
    plane: PlaneArgs,
    /// The tripped bus to re-enable (its name, as the running driver's layout gives it).
    bus: String,
}

/// Options of `nori lift`.
#[derive(Args, Debug)]
pub struct LiftArgs {
    #[command(subcommand)]
    action: LiftAction,
}

/// What `nori lift` does.
#[derive(clap::Subcommand, Debug)]
pub enum LiftAction {
    /// The operator's release, once whatever the lift stopped on is gone: an obstruction's
    /// hold ends (the column stays, with no goal), a jammed column homes again (down to its
    /// lower switch, watched for obstructions as it goes).
    Release {
        #[command(flatten)]
        plane: PlaneArgs,
    },
}

/// Sends the operator's release to the lift and says what it made of it.
pub fn lift(args: &LiftArgs) -> Result<()> {
    let LiftAction::Release { plane } = &args.action;
    let node = plane.node("lift")?;
    let commands = node.publisher(&plane::LIFT_COMMAND)?;
    let states = node.subscriber(&plane::LIFT_STATE)?;
    std::thread::sleep(Duration::from_millis(100));
    let now = telemetry::clock::monotonic_ns();
    let command = LiftCommand {
        seq: 1,
        timestamp_ns: now,
        height_m: f32::NAN,
        kind: telemetry::motion::LIFT_COMMAND_RELEASE,
    };
    plane::publish(&commands, &command)?;
    let until = Instant::now() + Duration::from_millis(1000);
    let mut seen = None;
    while Instant::now() < until {
        seen = plane::newest(&states).or(seen);
        if let Some(l) = seen.filter(|l: &LiftState| l.timestamp_ns > now) {
            eprintln!("nori lift: released; the lift: {}", lift_line(&l));
            return Ok(());
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    match seen {
        Some(l) => bail!(
            "release sent, but the lift's state is {} ms old: is nori-lift running?",
            now.saturating_sub(l.timestamp_ns) / 1_000_000
        ),
        None => bail!("release sent, but no lift state on the plane: is nori-lift running?"),
    }
}

/// Options of `nori stop` and `nori resume`.
#[derive(Args, Debug)]
pub struct StopArgs {
    #[command(flatten)]
    plane: PlaneArgs,
}

/// Asks the supervisor to re-enable a bus it tripped, and reports its answer: granted only once
/// every motor of the bus has cooled to the configured threshold.
pub fn reenable(args: &ReenableArgs) -> Result<()> {
    use telemetry::frames::{EventKind, COMMAND_REENABLE_BUS, COMMAND_REFUSED_NOT_TRIPPED};
    let (node, layout) = args.plane.open("reenable", LAYOUT_TIMEOUT)?;
    let bus = layout.bus_index(&args.bus).with_context(|| {
        format!(
            "the driver has no bus {:?} (it drives: {})",
            args.bus,
            layout.bus_names().collect::<Vec<_>>().join(", ")
        )
    })?;
    let answer = command_supervisor(&node, &args.plane.domain, COMMAND_REENABLE_BUS, bus, |e| {
        if e.bus as usize != bus {
            return None;
        }
        match e.kind()? {
            EventKind::BusReenabled => Some(Ok(())),
            EventKind::ReenableRefused => Some(Err(format!(
                "refused: bus {} is still at {:.0} °C",
                args.bus, e.value
            ))),
            EventKind::CommandRefused if e.level == COMMAND_REFUSED_NOT_TRIPPED => Some(Err(
                format!("nothing to do: bus {} is not tripped", args.bus),
            )),
            EventKind::CommandRefused => Some(Err(format!(
                "the supervisor refused the command (reason {})",
                e.level
            ))),
            _ => None,
        }
    })?;
    answer.map_err(anyhow::Error::msg)?;
    eprintln!("nori reenable: bus {} re-enabled", args.bus);
    Ok(())
}

/// Stops the robot: the supervisor holds the driver in its safe state (no goal taken, from any
/// source) until `nori resume`; recorded, so no restart ends it.
pub fn stop(args: &StopArgs) -> Result<()> {
    use telemetry::frames::{EventKind, COMMAND_STOP};
    // No driver needed: the supervisor takes the stop for the lift, and records it for the
    // driver to come.
    let node = args.plane.node("stop")?;
    let stopped = |node: &Plane| -> Result<bool> {
        let states = node.subscriber(&plane::JOINT_STATE)?;
        let until = Instant::now() + Duration::from_millis(300);
        while Instant::now() < until {
            if let Some(s) = plane::newest(&states) {
                return Ok(s.flags & telemetry::frames::STATE_FLAG_OPERATOR_STOP != 0);
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        Ok(false)
    };
    if stopped(&node)? {
        eprintln!("nori stop: the robot is already stopped (nori resume ends it)");
        return Ok(());
    }
    let answer = command_supervisor(&node, &args.plane.domain, COMMAND_STOP, 0, |e| {
        (e.kind()? == EventKind::OperatorStop).then_some(Ok(()))
    })?;
    answer.map_err(anyhow::Error::msg)?;
    eprintln!("nori stop: stopped; the driver holds its safe state until `nori resume`");
    Ok(())
}

/// Ends an operator's stop: the driver leaves its safe state, re-holding every joint where it
/// is, and takes only goals produced from then on.
pub fn resume(args: &StopArgs) -> Result<()> {
    use telemetry::frames::{EventKind, COMMAND_REFUSED_NOT_STOPPED, COMMAND_RESUME};
    let node = args.plane.node("resume")?;
    let answer = command_supervisor(&node, &args.plane.domain, COMMAND_RESUME, 0, |e| {
        match e.kind()? {
            EventKind::OperatorResume => Some(Ok(())),
            EventKind::CommandRefused if e.level == COMMAND_REFUSED_NOT_STOPPED => {
                Some(Err("nothing to do: the robot is not stopped".to_string()))
            }
            _ => None,
        }
    })?;
    answer.map_err(anyhow::Error::msg)?;
    eprintln!("nori resume: resumed");
    Ok(())
}

/// Sends the supervisor one command and waits up to 2 s for the event `answer` recognises
/// (`Some(Ok)` granted, `Some(Err(why))` refused, `None` another event).
fn command_supervisor(
    node: &Plane,
    domain: &str,
    kind: u8,
    bus: usize,
    mut answer: impl FnMut(&telemetry::frames::SupervisorEvent) -> Option<Result<(), String>>,
) -> Result<Result<(), String>> {
    use telemetry::frames::SupervisorCommand;
    let events = node.subscriber(&plane::EVENTS)?;
    let commands = node.publisher(&plane::COMMANDS)?;
    std::thread::sleep(Duration::from_millis(100));
    while plane::next(&events).is_some() {}
    let cmd = SupervisorCommand {
        seq: 1,
        timestamp_ns: telemetry::clock::monotonic_ns(),
        kind,
        bus: bus as u8,
        ..SupervisorCommand::default()
    };
    plane::publish(&commands, &cmd)?;
    let until = Instant::now() + Duration::from_secs(2);
    while Instant::now() < until {
        while let Some(e) = plane::next(&events) {
            if let Some(a) = answer(&e) {
                return Ok(a);
            }
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    bail!("no answer from the supervisor (is it running on domain {domain:?}?)")
}

#[cfg(test)]
mod goal_tests {
    use super::*;

    #[test]
    fn bad_goals_are_refused_before_anything_is_sent() {
        let names: Vec<String> = ["a", "b"].iter().map(|s| s.to_string()).collect();
        let goals = |g: &[&str]| g.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let g = parse_goals(&names, &goals(&["b=-1.5"])).unwrap();
        let f = g.joints;
        assert_eq!((f.mask, f.position_rad[1], f.joint_count), (0b10, -1.5, 2));
        assert_eq!(g.lift_m, None);
        let g = parse_goals(&names, &goals(&["lift=0.4", "a=1"])).unwrap();
        assert_eq!((g.lift_m, g.joints.mask), (Some(0.4), 0b01));
        for (bad, why) in [
            ("a=nan", "not a finite number"),
            ("a=inf", "not a finite number"),
            ("a=-inf", "not a finite number"),
            ("a=x", "not a number"),
            ("c=1", "no joint \"c\""),
            ("a", "expected JOINT=RAD"),
            ("lift=nan", "not a finite number"),
            ("lift=up", "not a number"),
            ("base=0.2", "nori base LINEAR ANGULAR"),
        ] {
            let e = format!("{:#}", parse_goals(&names, &goals(&[bad])).unwrap_err());
            assert!(e.contains(why), "{bad}: {e}");
        }
        let e = parse_goals(&names, &goals(&["a=1", "a=2"])).unwrap_err();
        assert!(e.to_string().contains("twice"), "{e}");
        let e = parse_goals(&names, &goals(&["lift=0.1", "lift=0.2"])).unwrap_err();
        assert!(e.to_string().contains("lift is given twice"), "{e}");
    }
}
