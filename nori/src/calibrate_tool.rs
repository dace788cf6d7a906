//! `nori calibrate by-hand BUS`: the joints of one bus calibrated by an operator moving each
//! from stop to stop with its torque off, the tool showing live how much of each joint's travel
//! is covered. `nori calibrate auto BUS`: the arm of one bus calibrating itself, each joint
//! driven slowly at a low torque into its stops in the order the robot's description gives,
//! the lift high enough first. Either way the calibration is written into the servos and into
//! a versioned file, atomically, the previous one kept and what changed shown. The driver of
//! that bus must be stopped: the bus is opened exclusively, as the driver opens it.

use anyhow::{bail, Context, Result};
use body::description::RobotDescription;
use bus_driver::bus::Bus;
use bus_driver::config::{
    BusConfig, CalibrationFile, CalibrationMethod, DriverConfig, Mode, Provenance, ServoIdentity,
    CALIBRATION_FORMAT,
};
use bus_driver::{LoadedConfig, SerialTransport};
use commission::automatic::{Activity, Automatic, Plan, Progress, Toward};
use commission::by_hand::ByHand;
use commission::calibrate::Stops;
use commission::record;
use commission::session::{Calibrated, JointToCalibrate};
use feetech::ServoModel;
use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use commission::calibrate::{LIMIT_MARGIN_RAD as MARGIN_RAD, TRAVEL_TOLERANCE_RAD};
/// A joint counts as covered within this of its travel, rad.
const COVERED_RAD: f64 = 0.02;
/// Readings a second.
const RATE_HZ: f64 = 50.0;

/// `nori calibrate …`.
#[derive(clap::Subcommand)]
pub enum CalibrateCommand {
    /// Calibrate a bus's joints by hand: torque off, move each joint from stop to stop (the
    /// tool shows each one's travel covered), press Enter. Each joint's homing offset and range
    /// are chosen from its stops and the robot's description, written into its servo and into
    /// the calibration file; refused, writing nothing, when a joint's travel is not the
    /// description's.
    ByHand(ByHandArgs),
    /// Calibrate a bus's arm without a hand: from hanging, each joint in the description's
    /// order driven slowly at a low torque limit toward each of its stops, each stop found
    /// where the joint stalls, the joint then driven back to rest. Refused, writing nothing
    /// and every joint driven back, when a stop is not where the description says (something
    /// in the way, a broken or wrong part). The lift must be at the description's height or
    /// higher (read from `nori-lift`, or measured: `--lift-at`).
    Auto(AutoArgs),
}

/// What both methods are told.
#[derive(clap::Args)]
pub struct Common {
    /// The bus.
    bus: String,
    #[command(flatten)]
    buses: crate::servo_tool::Buses,
    /// The robot's description (its joints' stops); the embedded Nori A3 when absent.
    #[arg(long, value_name = "FILE")]
    robot: Option<PathBuf>,
    /// The calibration file written (the previous one kept beside it as `.previous`).
    #[arg(long, value_name = "FILE", default_value = telemetry::calibration::CALIBRATION_FILE)]
    output: PathBuf,
    /// The robot's id, recorded in the file (the host's name when absent).
    #[arg(long)]
    robot_id: Option<String>,
}

/// `nori calibrate auto`.
#[derive(clap::Args)]
pub struct AutoArgs {
    #[command(flatten)]
    common: Common,
    /// The lift's height as measured, m above its lowest, when `nori-lift` is not running to
    /// say it.
    #[arg(long, value_name = "M")]
    lift_at: Option<f64>,
    #[command(flatten)]
    plane: crate::plane_tools::PlaneArgs,
    /// Give up after this many seconds: every joint driven back, every servo given back
    /// what it held, nothing written.
    #[arg(long, value_name = "S", default_value_t = 900.0)]
    within: f64,
}

/// `nori calibrate by-hand`.
#[derive(clap::Args)]
pub struct ByHandArgs {
    #[command(flatten)]
    common: Common,
    /// Only these joints (repeatable); every position joint of the bus by default.
    #[arg(long = "joint", value_name = "JOINT")]
    joints: Vec<String>,
    /// Finish as soon as every joint's travel is covered (no Enter needed).
    #[arg(long)]
    finish_when_covered: bool,
    /// Give up after this many seconds unless every joint is covered: every servo given back
    /// what it held, nothing written.
    #[arg(long, value_name = "S", default_value_t = 600.0)]
    within: f64,
}

/// Runs a `nori calibrate` command.
pub fn calibrate(command: &CalibrateCommand) -> Result<()> {
    match command {
        CalibrateCommand::ByHand(args) => by_hand(args),
        CalibrateCommand::Auto(args) => auto(args),
    }
}

/// What a session needs, everything the file needs checked before a servo is touched.
struct Prepared {
    loaded: LoadedConfig,
    robot: RobotDescription,
    targets: Vec<JointToCalibrate>,
    robot_id: String,
    base: CalibrationFile,
    /// Held to the end: a second session on the same file (the other arm's) is refused, not
    /// left to overwrite this one's joints with its own older base.
    _lock: std::fs::File,
}

impl Prepared {
    fn of(common: &Common, only: &[String], within: f64) -> Result<Self> {
        if !(within.is_finite() && within > 0.0) {
            bail!("--within {within}: a number of seconds above 0");
        }
        refuse_conffile(&common.output)?;
        let lock = lock_output(&common.output)?;
        let (loaded, origin) = common.buses.load()?;
        let Some(bus) = loaded.config.bus(&common.bus) else {
            bail!("no bus {:?} in {origin}", common.bus);
        };
        if bus.mode != Mode::Position {
            bail!(
                "bus {} drives wheels: there is nothing to calibrate",
                bus.name
            );
        }
        let robot = match &common.robot {
            Some(p) => RobotDescription::load(p)?,
            None => RobotDescription::nori_a3(),
        };
        let targets = targets(bus, &robot, &loaded.calibration, only)?;
        let robot_id = common.robot_id.clone().unwrap_or_else(host_name);
        let base = base_file(&common.output, &robot_id, &loaded)?;
        Ok(Prepared {
            loaded,
            robot,
            targets,
            robot_id,
            base,
            _lock: lock,
        })
    }

    /// The bus's line, opened exclusively.
    fn open(&self, common: &Common) -> Result<Bus<SerialTransport>> {
        let Some(bus) = self.loaded.config.bus(&common.bus) else {
            bail!("no bus {:?}", common.bus);
        };
        let line = SerialTransport::open(&bus.device, bus.baud)?;
        let margin = Duration::from_micros(self.loaded.config.reply_timeout_margin_us);
        Ok(Bus::new(line, margin))
    }

    fn write(
        self,
        common: &Common,
        method: CalibrationMethod,
        calibrated: &[Calibrated],
    ) -> Result<()> {
        write_file(
            &common.output,
            &self.loaded.config,
            self.base,
            &self.robot_id,
            method,
            calibrated,
        )
    }
}

fn auto(args: &AutoArgs) -> Result<()> {
    let common = &args.common;
    let prepared = Prepared::of(common, &[], args.within)?;
    let described = (prepared.robot.bus(&common.bus))
        .with_context(|| format!("the description has no bus {}", common.bus))?;
    let plan = Plan::of(
        described,
        &prepared.targets,
        MARGIN_RAD,
        TRAVEL_TOLERANCE_RAD,
    )?;
    let lift_m = described.arm.as_ref().and_then(|a| a.calibration.as_ref());
    lift_high_enough(args, lift_m.map_or(0.0, |c| c.lift_m))?;
    let names: Vec<String> = plan.sweeps.iter().map(|s| s.target.joint.clone()).collect();
    say(&format!(
        "calibrating {} without a hand: keep clear of the arm, it moves each joint into its \
         stops in turn ({})",
        common.bus,
        names.join(", ")
    ));
    // Stopped (Ctrl-C, SIGTERM, the terminal gone) or out of time, the session still drives
    // the joint back and gives every servo back what it held: a speed-mode servo left turning
    // would press its stop until it cooked. A panic drops the session, which releases it.
    let interrupted = telemetry::process::stop_or_hangup_flag()?;
    let start = Instant::now();
    let mut session = Automatic::start(prepared.open(common)?, plan, 0.0)?;
    let (mut shown, mut stopping) = (None, false);
    let calibrated = loop {
        std::thread::sleep(Duration::from_secs_f64(1.0 / RATE_HZ));
        let now = start.elapsed().as_secs_f64();
        if !stopping && (now > args.within || interrupted.load(Ordering::Relaxed)) {
            stopping = true;
            session.stop(now, 0.0);
            say("stopping: the joint driven back, every servo given back what it held");
        }
        match session.tick(now)? {
            Progress::Done(_) => break session.commit()?,
            Progress::Working(k, activity) => {
                let line = (k, std::mem::discriminant(&activity));
                if shown != Some(line) {
                    shown = Some(line);
                    say(&format!("  {:<24} {}", names[k], activity_name(activity)));
                }
            }
        }
    };
    if let Err(e) = prepared.write(common, CalibrationMethod::Automatic, &calibrated) {
        // The servos hold a calibration no file records: they get back what they held.
        session.abandon()?;
        return Err(e.context("not recorded: every servo given back what it held"));
    }
    Ok(())
}

/// A line to the operator; a closed output (a pipe whose reader went with the Ctrl-C) must
/// not end the session before it has driven the arm back.
fn say(line: &str) {
    use std::io::Write;
    let _ = writeln!(std::io::stdout(), "{line}");
}

fn activity_name(a: Activity) -> &'static str {
    match a {
        Activity::Posing => "driving the arm to its pose",
        Activity::Seeking(Toward::Lower, _) => "seeking its lower stop",
        Activity::Seeking(Toward::Upper, _) => "seeking its upper stop",
        Activity::Resting => "calibrated, back to rest",
        Activity::Returning => "refused, driven back to where it began",
        Activity::Parking => "every joint to rest",
    }
}

/// The lift at `lift_m` or higher, and not on its way down: as `nori-lift` publishes it when
/// it runs (whatever `--lift-at` says), else as the operator measured it.
fn lift_high_enough(args: &AutoArgs, lift_m: f64) -> Result<()> {
    let node = args.plane.node("calibrate")?;
    let published = crate::plane_tools::lift_state(&node)?
        .map(|l| (f64::from(l.height_m), f64::from(l.goal_m)));
    lift_verdict(published, args.lift_at, lift_m)
}

/// The judgment of [`lift_high_enough`] on the lift's published height and goal (a NaN goal:
/// none in force) and the operator's measurement.
fn lift_verdict(published: Option<(f64, f64)>, lift_at: Option<f64>, lift_m: f64) -> Result<()> {
    let (height, source) = match (published, lift_at) {
        (Some((height, goal)), _) => {
            if goal < lift_m {
                bail!(
                    "the lift is on its way to {goal:.2} m: the description asks {lift_m} m or \
                     higher for the arm to sweep clear of a table (`nori goal lift={lift_m}`)"
                );
            }
            (height, "as nori-lift reports it")
        }
        (None, Some(h)) => (h, "as measured (--lift-at)"),
        (None, None) => bail!(
            "the lift's height is unknown (nori-lift is not running): the arm sweeps below the \
             table with the lift under {lift_m} m. Raise it (`nori goal lift={lift_m}` with \
             nori-lift running), or measure it and pass --lift-at M"
        ),
    };
    if !(height.is_finite() && height >= lift_m) {
        bail!(
            "the lift is at {height} m {source}: the description asks {lift_m} m or higher for \
             the arm to sweep clear of a table (`nori goal lift={lift_m}`)"
        );
    }
    Ok(())
}

fn by_hand(args: &ByHandArgs) -> Result<()> {
    let common = &args.common;
    let prepared = Prepared::of(common, &args.joints, args.within)?;
    let targets = prepared.targets.clone();
    let mut session = ByHand::start(prepared.open(common)?, targets)?;
    let which = if args.joints.is_empty() {
        format!("every joint of {}", common.bus)
    } else {
        args.joints.join(", ")
    };
    println!("torque off on {which}: move each joint from one stop to the other, then press Enter");
    let entered = enter_pressed();
    let (start, mut shown) = (Instant::now(), Instant::now());
    loop {
        std::thread::sleep(Duration::from_secs_f64(1.0 / RATE_HZ));
        if let Err(e) = session.read() {
            // Best effort: the read that failed is the error to report.
            let _ = session.abandon();
            return Err(e.into());
        }
        let progress = session.progress(COVERED_RAD);
        let covered = progress.iter().all(|p| p.covered);
        let pressed = entered.swap(false, Ordering::Relaxed);
        let expired = start.elapsed().as_secs_f64() > args.within;
        if shown.elapsed() >= Duration::from_secs(1) || pressed {
            shown = Instant::now();
            show(&progress);
        }
        match Step::after(covered, pressed || args.finish_when_covered, expired) {
            Step::Sweep => {
                if pressed {
                    println!("not every joint is covered yet: go on, or wait for --within");
                }
            }
            Step::Finish => break,
            Step::GiveUp => {
                session.abandon()?;
                let short: Vec<&str> = progress
                    .iter()
                    .filter(|p| !p.covered)
                    .map(|p| p.joint.as_str())
                    .collect();
                bail!(
                    "gave up after {} s, every servo given back what it held: not covered: {}",
                    args.within,
                    short.join(", ")
                );
            }
        }
    }
    let calibrated = session.finish(MARGIN_RAD, TRAVEL_TOLERANCE_RAD)?;
    prepared.write(common, CalibrationMethod::ByHand, &calibrated)
}

/// What the sweep does next.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Step {
    /// Go on reading.
    Sweep,
    /// Every joint covered and the operator (or `--finish-when-covered`) done: calibrate.
    Finish,
    /// Out of time before every joint was covered: nothing written.
    GiveUp,
}

impl Step {
    fn after(covered: bool, done: bool, expired: bool) -> Step {
        match (covered, done, expired) {
            (true, true, _) => Step::Finish,
            (_, _, true) => Step::GiveUp,
            _ => Step::Sweep,
        }
    }
}

fn show(progress: &[commission::by_hand::Progress]) {
    for p in progress {
        println!(
            "  {:<24} {:6.1}° of {:6.1}° {}",
            p.joint,
            p.swept_deg,
            p.travel_deg,
            if p.covered { "covered" } else { "" }
        );
    }
}

/// The package owns `/etc/nori` (conffiles an upgrade compares); a calibration is the robot's
/// state.
fn refuse_conffile(output: &Path) -> Result<()> {
    if absolute(output).starts_with("/etc") {
        bail!(
            "{}: /etc/nori holds the package's configuration files; a calibration is the \
             robot's state: write it under /var/lib/nori (the default) and name it in the \
             driver's configuration",
            output.display()
        );
    }
    Ok(())
}

/// The joints to calibrate, with their stops from the description.
fn targets(
    bus: &BusConfig,
    robot: &RobotDescription,
    calibration: &CalibrationFile,
    only: &[String],
) -> Result<Vec<JointToCalibrate>> {
    let d = robot
        .bus(&bus.name)
        .with_context(|| format!("the description has no bus {}", bus.name))?;
    for j in only {
        if !bus.servo.iter().any(|s| &s.joint == j) {
            bail!("bus {} has no joint {j:?}", bus.name);
        }
    }
    bus.servo
        .iter()
        .filter(|s| only.is_empty() || only.contains(&s.joint))
        .map(|s| {
            let id = d
                .servo
                .iter()
                .find(|v| v.joint == s.joint)
                .map(|v| v.id)
                .with_context(|| format!("the description has no joint {}", s.joint))?;
            let arm = d.arm.as_ref();
            let stops = arm
                .and_then(|a| a.joint.iter().find(|j| j.servo == id))
                .map(|j| (j.lower_rad, j.upper_rad))
                .or_else(|| {
                    arm.and_then(|a| a.gripper.as_ref())
                        .filter(|g| g.servo == id)
                        .map(|g| (g.lower_rad, g.upper_rad))
                })
                .with_context(|| format!("the description gives {} no stops", s.joint))?;
            let model = ServoModel::from_key(&s.model)
                .with_context(|| format!("{}: no model {:?}", s.joint, s.model))?;
            Ok(JointToCalibrate {
                joint: s.joint.clone(),
                id: s.id,
                model,
                stops: Stops {
                    lower_rad: stops.0,
                    upper_rad: stops.1,
                    inverted: calibration.joint.get(&s.joint).is_some_and(|c| c.inverted),
                },
            })
        })
        .collect()
}

/// The file this calibration goes into: the one already at `output` (its format known, this
/// robot's, every joint valid), else the calibration file the driver's configuration names;
/// never the embedded one, which is the simulated A3's and no robot's record: with none, the
/// file holds only the joints calibrated now (the driver needs every position joint's, so it
/// runs once every bus is calibrated).
fn base_file(output: &Path, robot_id: &str, loaded: &LoadedConfig) -> Result<CalibrationFile> {
    let text = match std::fs::read_to_string(output) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Ok(match loaded.config.calibration_file {
                Some(_) => loaded.calibration.clone(),
                None => CalibrationFile {
                    calibrated: None,
                    joint: Default::default(),
                    servo: Default::default(),
                },
            });
        }
        Err(e) => return Err(e).context(output.display().to_string()),
    };
    let origin = output.display().to_string();
    let file = checked(&text, &origin)?;
    if let Some(p) = file.calibrated.as_ref().filter(|p| p.robot != robot_id) {
        bail!(
            "{origin} is robot {:?}'s calibration, not {robot_id:?}'s: give another --output \
             (or --robot-id)",
            p.robot
        );
    }
    Ok(file)
}

/// A calibration file's text as the driver would take it: its format known, every joint valid.
fn checked(text: &str, origin: &str) -> Result<CalibrationFile> {
    let file: CalibrationFile = toml::from_str(text).with_context(|| origin.to_string())?;
    file.check_format(origin)?;
    for (joint, cal) in &file.joint {
        cal.validate(joint).with_context(|| origin.to_string())?;
    }
    Ok(file)
}

/// `base` with these joints replaced, stamped; written atomically, and what changed shown.
fn write_file(
    output: &Path,
    config: &DriverConfig,
    mut file: CalibrationFile,
    robot_id: &str,
    method: CalibrationMethod,
    calibrated: &[Calibrated],
) -> Result<()> {
    let before = file.clone();
    for c in calibrated {
        file.joint.insert(c.joint.clone(), c.calibration);
        file.servo.insert(
            c.joint.clone(),
            ServoIdentity {
                id: c.id,
                model: c.model.to_string(),
                firmware: c.firmware.clone(),
            },
        );
    }
    file.calibrated = Some(Provenance {
        format: CALIBRATION_FORMAT,
        robot: robot_id.to_string(),
        at: humantime::format_rfc3339_seconds(std::time::SystemTime::now()).to_string(),
        method,
    });
    let text = record::render(&file)?;
    checked(&text, "the calibration to write").context("not written")?;
    let changes = record::changes(Some(&before), &file);
    record::replace(output, &text)?;
    println!(
        "calibrated {} joint(s), written to {} (the previous kept as {}):",
        calibrated.len(),
        output.display(),
        record::previous_path(output).display()
    );
    for c in &changes {
        println!("  {c}");
    }
    if changes.is_empty() {
        println!("  nothing changed");
    }
    let missing = not_calibrated(config, &file);
    if !missing.is_empty() {
        println!(
            "not in the file yet (the driver needs every arm joint's calibration): {}",
            missing.join(", ")
        );
    }
    println!(
        "the driver reads it when its configuration says calibration-file = {:?}",
        absolute(output).display().to_string()
    );
    Ok(())
}

/// An exclusive lock on `<output>.lock` for the whole session.
fn lock_output(output: &Path) -> Result<std::fs::File> {
    let mut name = output.as_os_str().to_owned();
    name.push(".lock");
    let path = PathBuf::from(name);
    let file = std::fs::File::options()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .with_context(|| path.display().to_string())?;
    match file.try_lock() {
        Ok(()) => Ok(file),
        Err(std::fs::TryLockError::WouldBlock) => bail!(
            "another calibration is writing {} (its lock {} is held): one session at a time",
            output.display(),
            path.display()
        ),
        Err(std::fs::TryLockError::Error(e)) => Err(e).context(path.display().to_string()),
    }
}

/// The position joints of `config` that `file` has no calibration for.
fn not_calibrated(config: &DriverConfig, file: &CalibrationFile) -> Vec<String> {
    (config.bus.iter())
        .filter(|b| b.mode == Mode::Position)
        .flat_map(|b| &b.servo)
        .filter(|s| !file.joint.contains_key(&s.joint))
        .map(|s| s.joint.clone())
        .collect()
}

fn absolute(path: &Path) -> PathBuf {
    std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf())
}

fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_string())
        .unwrap_or_else(|_| "unknown".into())
}

/// A flag set each time the operator presses Enter (a line on standard input).
fn enter_pressed() -> Arc<AtomicBool> {
    let flag = Arc::new(AtomicBool::new(false));
    let set = flag.clone();
    std::thread::spawn(move || {
        let mut line = String::new();
        // A closed input (a script without one) is no Enter: the tool waits for coverage.
        while matches!(std::io::stdin().lock().read_line(&mut line), Ok(n) if n > 0) {
            set.store(true, Ordering::Relaxed);
            line.clear();
        }
    });
    flag
}

#[cfg(test)]
mod tests {
    use super::*;
    use telemetry::config::ProcessConfig;

    /// The lift's own report wins over the operator's measurement; a goal below the plan's
    /// height (on its way down) or a height below it is refused; none at all is refused.
    #[test]
    fn the_lift_must_be_high_enough_and_not_going_down() {
        let ok = |published, at| lift_verdict(published, at, 0.6).is_ok();
        assert!(ok(Some((0.6, f64::NAN)), None));
        assert!(ok(Some((0.7, 0.6)), Some(0.1)));
        assert!(!ok(Some((0.59, f64::NAN)), Some(0.9)));
        assert!(!ok(Some((0.7, 0.59)), None));
        assert!(!ok(Some((f64::NAN, f64::NAN)), None));
        assert!(ok(None, Some(0.6)));
        assert!(!ok(None, Some(0.59)));
        assert!(!ok(None, None));
    }

    #[test]
    fn the_sweep_finishes_only_when_covered_and_gives_up_when_out_of_time() {
        assert_eq!(Step::after(true, true, false), Step::Finish);
        assert_eq!(Step::after(true, true, true), Step::Finish);
        // Enter pressed with a joint short of its travel: go on.
        assert_eq!(Step::after(false, true, false), Step::Sweep);
        assert_eq!(Step::after(true, false, false), Step::Sweep);
        // Out of time, not covered (Enter or not): nothing written.
        assert_eq!(Step::after(false, true, true), Step::GiveUp);
        assert_eq!(Step::after(false, false, true), Step::GiveUp);
        // Covered, but nobody said done and out of time: given up, not written.
        assert_eq!(Step::after(true, false, true), Step::GiveUp);
    }

    #[test]
    fn a_previous_file_of_another_robot_or_format_or_a_conffile_is_refused() {
        let dir = std::env::temp_dir().join(format!("nori-calibrate-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let loaded = LoadedConfig::embedded().unwrap();
        let path = dir.join("calibration.toml");
        // None there, and the driver on the embedded calibration (the simulated A3's): no
        // joint carried over, so no robot's file holds the simulator's values unmeasured.
        let _ = std::fs::remove_file(&path);
        let base = base_file(&path, "a3-0007", &loaded).unwrap();
        assert!(
            base.joint.is_empty() && base.calibrated.is_none(),
            "{base:?}"
        );
        assert_eq!(not_calibrated(&loaded.config, &base).len(), 16);
        // The driver on a calibration file: that file is the base.
        let mut configured = loaded.clone();
        configured.config.calibration_file = Some(dir.join("robot.toml"));
        assert_eq!(
            base_file(&path, "a3-0007", &configured).unwrap(),
            loaded.calibration
        );
        assert!(not_calibrated(&configured.config, &loaded.calibration).is_empty());
        let mut theirs = loaded.calibration.clone();
        theirs.calibrated = Some(Provenance {
            format: CALIBRATION_FORMAT,
            robot: "a3-0001".into(),
            at: "2026-11-01T00:00:00Z".into(),
            method: CalibrationMethod::ByHand,
        });
        std::fs::write(&path, record::render(&theirs).unwrap()).unwrap();
        let e = base_file(&path, "a3-0007", &loaded)
            .unwrap_err()
            .to_string();
        assert!(e.contains("a3-0001"), "{e}");
        assert!(base_file(&path, "a3-0001", &loaded).is_ok());
        let future = record::render(&theirs)
            .unwrap()
            .replace("format = 1", "format = 2");
        std::fs::write(&path, future).unwrap();
        let e = format!("{:#}", base_file(&path, "a3-0001", &loaded).unwrap_err());
        assert!(e.contains("format 2"), "{e}");
        std::fs::write(&path, "joint = 3").unwrap();
        assert!(base_file(&path, "a3-0001", &loaded).is_err());
        // One session at a time on a file.
        let held = lock_output(&path).unwrap();
        let e = lock_output(&path).unwrap_err().to_string();
        assert!(e.contains("another calibration"), "{e}");
        drop(held);
        lock_output(&path).unwrap();
        let e = refuse_conffile(Path::new("/etc/nori/calibration.toml")).unwrap_err();
        assert!(e.to_string().contains("/var/lib/nori"), "{e}");
        refuse_conffile(&path).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
