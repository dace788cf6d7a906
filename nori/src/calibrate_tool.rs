//! `nori calibrate by-hand BUS`: the joints of one bus calibrated by an operator moving each
//! from stop to stop with its torque off, the tool showing live how much of each joint's travel
//! is covered; the calibration written into the servos and into a versioned file, atomically,
//! the previous one kept and what changed shown. The stack must be stopped: the bus is opened
//! exclusively, as the driver opens it.

use anyhow::{bail, Context, Result};
use body::description::RobotDescription;
use bus_driver::bus::Bus;
use bus_driver::config::{
    BusConfig, CalibrationFile, CalibrationMethod, Mode, Provenance, ServoIdentity,
    CALIBRATION_FORMAT,
};
use bus_driver::{LoadedConfig, SerialTransport};
use commission::by_hand::{ByHand, Calibrated, JointToCalibrate};
use commission::calibrate::Stops;
use commission::record;
use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Where a robot keeps its calibration: state, not a package's conffile.
const INSTALLED_CALIBRATION: &str = "/var/lib/nori/calibration.toml";
/// How far inside each stop a joint's limits are put, rad.
const MARGIN_RAD: f64 = 0.15;
/// How far the travel swept may differ from the description's before it is refused, rad
/// (the stops' give under an operator's push is a few degrees).
const TOLERANCE_RAD: f64 = 0.15;
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
}

/// `nori calibrate by-hand`.
#[derive(clap::Args)]
pub struct ByHandArgs {
    /// The bus.
    bus: String,
    /// Only these joints (repeatable); every position joint of the bus by default.
    #[arg(long = "joint", value_name = "JOINT")]
    joints: Vec<String>,
    #[command(flatten)]
    buses: crate::servo_tool::Buses,
    /// The robot's description (its joints' stops); the embedded Nori A3 when absent.
    #[arg(long, value_name = "FILE")]
    robot: Option<PathBuf>,
    /// The calibration file written (the previous one kept beside it as `.previous`).
    #[arg(long, value_name = "FILE", default_value = INSTALLED_CALIBRATION)]
    output: PathBuf,
    /// The robot's id, recorded in the file (the host's name when absent).
    #[arg(long)]
    robot_id: Option<String>,
    /// Finish as soon as every joint's travel is covered (no Enter needed).
    #[arg(long)]
    finish_when_covered: bool,
    /// Give up after this many seconds, every servo given back what it held.
    #[arg(long, value_name = "S", default_value_t = 600.0)]
    within: f64,
}

/// Runs a `nori calibrate` command.
pub fn calibrate(command: &CalibrateCommand) -> Result<()> {
    match command {
        CalibrateCommand::ByHand(args) => by_hand(args),
    }
}

fn by_hand(args: &ByHandArgs) -> Result<()> {
    let (loaded, origin) = args.buses.load()?;
    let Some(bus) = loaded.config.bus(&args.bus) else {
        bail!("no bus {:?} in {origin}", args.bus);
    };
    if bus.mode != Mode::Position {
        bail!(
            "bus {} drives wheels: there is nothing to calibrate",
            bus.name
        );
    }
    let robot = match &args.robot {
        Some(p) => RobotDescription::load(p)?,
        None => RobotDescription::nori_a3(),
    };
    let targets = targets(&loaded, bus, &robot, &args.joints)?;
    let line = SerialTransport::open(&bus.device, bus.baud)?;
    let margin = Duration::from_micros(loaded.config.reply_timeout_margin_us);
    let mut session = ByHand::start(Bus::new(line, margin), targets)?;
    let which = if args.joints.is_empty() {
        format!("every joint of {}", args.bus)
    } else {
        args.joints.join(", ")
    };
    println!("torque off on {which}: move each joint from one stop to the other, then press Enter");
    let entered = enter_pressed();
    let (start, mut shown) = (Instant::now(), Instant::now());
    loop {
        std::thread::sleep(Duration::from_secs_f64(1.0 / RATE_HZ));
        if let Err(e) = session.read() {
            session.abandon()?;
            return Err(e.into());
        }
        let progress = session.progress(COVERED_RAD);
        let covered = progress.iter().all(|p| p.covered);
        if shown.elapsed() >= Duration::from_secs(1) {
            shown = Instant::now();
            for p in &progress {
                println!(
                    "  {:<24} {:6.1}° of {:6.1}° {}",
                    p.joint,
                    p.swept_deg,
                    p.travel_deg,
                    if p.covered { "covered" } else { "" }
                );
            }
        }
        let done = entered.load(Ordering::Relaxed) || (covered && args.finish_when_covered);
        if done || start.elapsed().as_secs_f64() > args.within {
            break;
        }
    }
    let calibrated = session.finish(MARGIN_RAD, TOLERANCE_RAD)?;
    write_file(args, &loaded, &calibrated)
}

/// The joints to calibrate, with their stops from the description.
fn targets(
    loaded: &LoadedConfig,
    bus: &BusConfig,
    robot: &RobotDescription,
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
            Ok(JointToCalibrate {
                joint: s.joint.clone(),
                id: s.id,
                stops: Stops {
                    lower_rad: stops.0,
                    upper_rad: stops.1,
                    inverted: loaded
                        .calibration
                        .joint
                        .get(&s.joint)
                        .is_some_and(|c| c.inverted),
                },
            })
        })
        .collect()
}

/// The calibration file: the previous one at the output (else the loaded calibration) with
/// these joints replaced, stamped; written atomically, and what changed shown.
fn write_file(args: &ByHandArgs, loaded: &LoadedConfig, calibrated: &[Calibrated]) -> Result<()> {
    let previous: Option<CalibrationFile> = match std::fs::read_to_string(&args.output) {
        Ok(text) => Some(
            toml::from_str(&text)
                .with_context(|| format!("the previous calibration {}", args.output.display()))?,
        ),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
        Err(e) => return Err(e).context(args.output.display().to_string()),
    };
    let mut file = previous
        .clone()
        .unwrap_or_else(|| loaded.calibration.clone());
    let models = loaded.config.bus(&args.bus).map(|b| &b.servo);
    for c in calibrated {
        file.joint.insert(c.joint.clone(), c.calibration);
        let model = models
            .and_then(|m| m.iter().find(|s| s.joint == c.joint))
            .map_or_else(String::new, |s| s.model.clone());
        file.servo.insert(
            c.joint.clone(),
            ServoIdentity {
                id: c.id,
                model,
                firmware: c.firmware.clone(),
            },
        );
    }
    file.calibrated = Some(Provenance {
        format: CALIBRATION_FORMAT,
        robot: args.robot_id.clone().unwrap_or_else(host_name),
        at: humantime::format_rfc3339_seconds(std::time::SystemTime::now()).to_string(),
        method: CalibrationMethod::ByHand,
    });
    let before = previous.as_ref().unwrap_or(&loaded.calibration);
    let changes = record::changes(Some(before), &file);
    record::replace(&args.output, &record::render(&file)?)?;
    println!(
        "calibrated {} joint(s), written to {} (the previous kept as {}):",
        calibrated.len(),
        args.output.display(),
        record::previous_path(&args.output).display()
    );
    for c in &changes {
        println!("  {c}");
    }
    if changes.is_empty() {
        println!("  nothing changed");
    }
    println!(
        "the driver reads it when its configuration says calibration-file = {:?}",
        absolute(&args.output).display().to_string()
    );
    Ok(())
}

fn absolute(path: &Path) -> PathBuf {
    std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf())
}

fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_string())
        .unwrap_or_else(|_| "unknown".into())
}

/// A flag set when the operator presses Enter (a line on standard input, or its end).
fn enter_pressed() -> Arc<AtomicBool> {
    let flag = Arc::new(AtomicBool::new(false));
    let set = flag.clone();
    std::thread::spawn(move || {
        let mut line = String::new();
        // A closed input (a script without one) is no Enter: the tool waits for coverage.
        if matches!(std::io::stdin().lock().read_line(&mut line), Ok(n) if n > 0) {
            set.store(true, Ordering::Relaxed);
        }
    });
    flag
}
