//! `nori-sim` (`nori sim serve`): the simulated robot on pseudo-terminals, one per bus, in real
//! time, with its scheduled faults; a JSON report of what the servos received.

use anyhow::{Context, Result};
use clap::Parser;
use sim::faults::{Schedule, Scheduled};
use sim::pty::{default_device_dir, serve_logged};
use sim::{BusReport, RobotDescription, SimBus};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// Options of `nori-sim` (`nori sim serve`).
#[derive(Parser, Debug, Clone)]
#[command(
    name = "nori-sim",
    version,
    about = "The simulated Nori A3: its servo buses on pseudo-terminals, in real time"
)]
struct ServeArgs {
    /// Robot description (TOML); the embedded Nori A3 when absent.
    #[arg(long)]
    pub description: Option<PathBuf>,
    /// Directory for the device links, one per bus (DIR/<bus name>).
    #[arg(long, value_name = "DIR", default_value_os_t = default_device_dir())]
    pub dir: PathBuf,
    /// Serve only these buses (repeatable); all when absent.
    #[arg(long = "bus")]
    pub buses: Vec<String>,
    /// Set up a protection scenario on the left arm (payload, obstacle or grasped object);
    /// repeatable: the set-ups combine (the chaos run uses all three).
    #[arg(long, value_enum)]
    pub scenario: Vec<sim::scenario::Scenario>,
    /// The servos' constants: the description's ratings with the model lab's shipped findings
    /// on top (each model it found wrong on measured runs), or the ratings alone.
    #[arg(long, value_enum, default_value_t = sim::constants::ConstantsChoice::Fitted)]
    pub servo_constants: sim::constants::ConstantsChoice,
    /// A model extension (TOML, as `nori model analyze` writes it) on every servo, on top of
    /// the servo constants: an effect the model lab must find, or a finding to run.
    #[arg(long, value_name = "FILE")]
    pub model_extension: Option<PathBuf>,
    /// Integrate temperatures this many times faster than real time (accelerated heating).
    #[arg(long, default_value_t = 1.0)]
    pub thermal_speedup: f64,
    /// Mechanics step, s.
    #[arg(long, default_value_t = 0.001)]
    pub dt: f64,
    /// Write a JSON report here every second and at exit (what the servos received, temperatures).
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Stop after this many seconds.
    #[arg(long)]
    pub run_for: Option<f64>,
    /// Append every byte each bus receives and sends to DIR/<bus>.received and DIR/<bus>.sent:
    /// the simulator's own record of the wire (a black box is checked against it).
    #[arg(long, value_name = "DIR")]
    pub wire_log: Option<PathBuf>,
    /// Line fault: probability per status packet of one flipped bit.
    #[arg(long, default_value_t = 0.0)]
    pub bit_flip_rate: f64,
    /// Line fault: probability per status packet of two flipped bits (about 7 % of them pass
    /// the checksum).
    #[arg(long, default_value_t = 0.0)]
    pub double_flip_rate: f64,
    /// Line fault: probability per status packet that it is not sent.
    #[arg(long, default_value_t = 0.0)]
    pub drop_rate: f64,
    /// Line fault: probability per status packet that only a prefix is sent.
    #[arg(long, default_value_t = 0.0)]
    pub truncate_rate: f64,
    /// Line fault: probability per host instruction that no servo receives it (a lost write).
    #[arg(long, default_value_t = 0.0)]
    pub instruction_drop_rate: f64,
    /// Line fault: probability per host instruction of one flipped bit (the servos' checksum
    /// refuses it: a corrupted write).
    #[arg(long, default_value_t = 0.0)]
    pub instruction_corrupt_rate: f64,
    /// Seed of the line faults (each bus adds its index).
    #[arg(long, default_value_t = 1)]
    pub fault_seed: u64,
    /// Unplug a bus (or `lidar`) for a while, as a USB adapter pulled out and put back:
    /// BUS@AT+FOR (seconds since start), e.g. `right_arm@10+3`; the device link comes back at
    /// the same path. Repeatable.
    #[arg(long, value_name = "BUS@AT+FOR")]
    pub unplug: Vec<String>,
    /// Make one servo stop answering for a while: BUS:ID@AT+FOR, e.g. `left_arm:3@5+2`.
    /// Repeatable.
    #[arg(long, value_name = "BUS:ID@AT+FOR")]
    pub silence: Vec<String>,
    /// Camera fault: probability per MJPEG frame that the JPEG is cut short.
    #[arg(long, default_value_t = 0.0)]
    pub camera_truncate_rate: f64,
    /// Camera fault: probability per frame that its bytes are garbage.
    #[arg(long, default_value_t = 0.0)]
    pub camera_garbage_rate: f64,
    /// Lidar fault: probability per measurement that its check bits are broken.
    #[arg(long, default_value_t = 0.0)]
    pub lidar_corrupt_rate: f64,
    /// Lidar fault: probability per turn that the device stops sending part-way through it.
    #[arg(long, default_value_t = 0.0)]
    pub lidar_truncate_rate: f64,
    /// Lidar fault: probability per turn of a burst of random bytes on the line.
    #[arg(long, default_value_t = 0.0)]
    pub lidar_garbage_rate: f64,
    /// Make the lidar report a protection stop (until a RESET clears it).
    #[arg(long)]
    pub lidar_protection_stop: bool,
    /// Something solid under the lift column at this height, m (a hand): the column coming
    /// down stops there, its motor stalled.
    #[arg(long, value_name = "M")]
    pub lift_obstacle_at: Option<f64>,
    /// The obstacle under the lift appears this many seconds after start.
    #[arg(long, value_name = "S", default_value_t = 0.0)]
    pub lift_obstacle_from: f64,
    /// A factory-fresh servo of the same model where a joint's servo was (a burnt one
    /// replaced, before `nori servo setup`): id 1, 1 Mbps, the factory's EEPROM. BUS:JOINT,
    /// e.g. `left_arm:left_elbow`; repeatable.
    #[arg(long, value_name = "BUS:JOINT")]
    pub fresh_servo: Vec<String>,
    /// An operator's hand on an arm from AT seconds after start (calibration by hand): it
    /// sweeps each joint whose torque is off from stop to stop, in the arm's order (or only
    /// JOINT). BUS[:JOINT]@AT, e.g. `left_arm:left_elbow@5`; repeatable.
    #[arg(long, value_name = "BUS[:JOINT]@AT")]
    pub hand: Vec<String>,
    /// A robot off the line before its calibration: every arm joint's horn fitted at random
    /// on its spline (seeded: the same seed, the same robot), its servo set up but not
    /// calibrated. The horns are in the report (`horn_steps`).
    #[arg(long, value_name = "SEED")]
    pub assembly_seed: Option<u64>,
}

/// A hand to put on an arm: its bus, the one joint it sweeps (or all), and when.
struct HandOn {
    bus: String,
    joint: Option<String>,
    at_s: f64,
    on: bool,
}

/// `--hand BUS[:JOINT]@AT`, each on a served bus with an arm (and that joint).
fn hands(args: &ServeArgs, robot: &RobotDescription) -> Result<Vec<HandOn>> {
    args.hand
        .iter()
        .map(|text| {
            let bad = || format!("--hand {text:?}: BUS[:JOINT]@AT");
            let (what, at) = text.split_once('@').with_context(bad)?;
            let at_s: f64 = at
                .parse()
                .ok()
                .filter(|t: &f64| t.is_finite() && *t >= 0.0)
                .with_context(bad)?;
            let (bus, joint) = match what.split_once(':') {
                Some((b, j)) => (b, Some(j.to_string())),
                None => (what, None),
            };
            let d = robot
                .bus(bus)
                .filter(|d| serves_bus(args, &d.name) && d.arm.is_some());
            let Some(d) = d else {
                anyhow::bail!("--hand {text:?}: no arm on a served bus {bus:?}");
            };
            if let Some(j) = &joint {
                if !d.servo.iter().any(|s| &s.joint == j) {
                    anyhow::bail!("--hand {text:?}: bus {bus} has no joint {j:?}");
                }
            }
            Ok(HandOn {
                bus: bus.to_string(),
                joint,
                at_s,
                on: false,
            })
        })
        .collect()
}

/// The simulator's report: one entry per bus, the lidar's and the lift's.
#[derive(serde::Serialize)]
struct SimReport {
    /// Each bus's report (its servos, line counters, torque-limit changes).
    buses: Vec<BusReport>,
    /// The lidar, if served.
    lidar: Option<sim::lidar::LidarReport>,
    /// The lift, if served.
    lift: Option<sim::lift::LiftReport>,
}

fn write_report(
    path: &Path,
    buses: &[BusReport],
    (lidar, lift): (
        Option<sim::lidar::LidarReport>,
        Option<sim::lift::LiftReport>,
    ),
) -> Result<()> {
    let tmp = path.with_extension("tmp");
    let report = SimReport {
        buses: buses.to_vec(),
        lidar,
        lift,
    };
    std::fs::write(&tmp, serde_json::to_vec_pretty(&report)?)
        .with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("renaming to {}", path.display()))?;
    Ok(())
}

/// Whether a scheduled unplug is the lidar's (not a bus's).
fn is_lidar(s: &Scheduled) -> bool {
    s.bus == "lidar" && s.id.is_none()
}

fn main() -> Result<()> {
    run(&ServeArgs::parse())
}

/// Serves until SIGINT/SIGTERM or `--run-for`.
fn run(args: &ServeArgs) -> Result<()> {
    let robot = load_robot(args)?;
    check_settings(args, &robot)?;
    let faults = line_faults(args)?;
    let mut schedule = fault_schedule(args, &robot)?;
    let mut hands = hands(args, &robot)?;
    let shutdown = telemetry::process::stop_flag()?;
    let constants = sim::constants::shipped(args.servo_constants)?;
    announce_constants(&robot, &constants);
    let extension = match &args.model_extension {
        Some(p) => Some(sim::extension::ModelExtension::load(p)?),
        None => None,
    };
    let mut buses = sim_buses(args, &robot, &faults)?;
    for (bus, _) in &mut buses {
        for c in &constants {
            bus.apply_constants(c);
        }
        if let Some(m) = &extension {
            bus.apply_extension(m);
        }
    }
    if let Some(m) = &extension {
        eprintln!("nori sim: model extension {} on every servo", m.cause);
    }
    let lidar_faults = sensor_faults(args)?;
    let served = serve_logged(buses, args.dt, args.wire_log.as_deref())?;
    let devices = Devices {
        lidar: serve_lidar(args, &robot, lidar_faults)?,
        lift: serve_lift(args, &robot)?,
    };
    // Cameras render only while a reader is connected: a run without nori-camera pays nothing.
    let cameras = sim::camera::serve(
        &robot,
        served.shared_buses(),
        &args.dir,
        sim::camera::CameraFaults {
            truncate_rate: args.camera_truncate_rate,
            garbage_rate: args.camera_garbage_rate,
            seed: args.fault_seed,
        },
    )?;
    announce(args, &robot, &served, &cameras, &faults);
    let start = Instant::now();
    let mut last_report = Instant::now();
    while !shutdown.load(Ordering::Relaxed)
        && args
            .run_for
            .is_none_or(|t| start.elapsed().as_secs_f64() < t)
    {
        std::thread::sleep(Duration::from_millis(20));
        let t = start.elapsed().as_secs_f64();
        devices.follow(args, &served, t);
        for (s, active) in schedule.advance(t) {
            apply_fault(s, active, t, &served, devices.lidar.as_ref());
        }
        for h in hands.iter_mut().filter(|h| !h.on && t >= h.at_s) {
            h.on = true;
            served.with_bus(&h.bus, |b| {
                b.put_hand_on_joints(&robot, |j| h.joint.as_deref().is_none_or(|only| only == j))
            });
            eprintln!("nori sim: a hand on {} at {t:.1} s", h.bus);
        }
        if let Some(path) = &args.report {
            if last_report.elapsed() >= Duration::from_secs(1) {
                write_report(path, &served.reports(), devices.reports())?;
                last_report = Instant::now();
            }
        }
    }
    drop(cameras);
    let final_lidar = devices.reports();
    drop(devices);
    let reports = served.stop();
    if let Some(path) = &args.report {
        write_report(path, &reports, final_lidar)?;
    }
    let hottest = reports
        .iter()
        .flat_map(|b| b.servos.iter())
        .map(|s| s.max_temperature_c)
        .fold(f64::NAN, f64::max);
    eprintln!("nori sim: stopped; hottest servo reached {hottest:.1} °C");
    Ok(())
}

/// The robot described (`--description`, else the Nori A3), with the scenarios set up on it.
fn load_robot(args: &ServeArgs) -> Result<RobotDescription> {
    let mut robot = match &args.description {
        Some(p) => RobotDescription::load(p)?,
        None => RobotDescription::nori_a3(),
    };
    for &scenario in &args.scenario {
        scenario.apply(&mut robot);
        eprintln!(
            "nori sim: scenario {scenario:?} set up on {}",
            sim::scenario::SCENARIO_BUS
        );
    }
    Ok(robot)
}

/// The thermal speed-up, the mechanics step and the buses asked for are ones the simulator
/// can serve.
fn check_settings(args: &ServeArgs, robot: &RobotDescription) -> Result<()> {
    if !(args.thermal_speedup.is_finite() && args.thermal_speedup >= 1.0) {
        anyhow::bail!(
            "--thermal-speedup must be ≥ 1, got {}",
            args.thermal_speedup
        );
    }
    if !(args.dt > 0.0 && args.dt <= 0.005) {
        anyhow::bail!("--dt must be in (0, 0.005] s, got {}", args.dt);
    }
    for name in &args.buses {
        if robot.bus(name).is_none() {
            anyhow::bail!(
                "no bus {name:?} in the description (have: {})",
                robot
                    .bus
                    .iter()
                    .map(|b| b.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
    }
    Ok(())
}

/// Whether bus `name` is served: every bus when `--bus` names none.
fn serves_bus(args: &ServeArgs, name: &str) -> bool {
    args.buses.is_empty() || args.buses.iter().any(|b| b == name)
}

/// The servo lines' faults asked for.
fn line_faults(args: &ServeArgs) -> Result<sim::faults::LineFaults> {
    let faults = sim::faults::LineFaults {
        seed: args.fault_seed,
        bit_flip_rate: args.bit_flip_rate,
        double_flip_rate: args.double_flip_rate,
        drop_rate: args.drop_rate,
        truncate_rate: args.truncate_rate,
        instruction_drop_rate: args.instruction_drop_rate,
        instruction_corrupt_rate: args.instruction_corrupt_rate,
    };
    faults
        .validate()
        .map_err(|e| anyhow::anyhow!("line faults: {e}"))?;
    Ok(faults)
}

/// The unplugs and silences in time (`--unplug`, `--silence`), each on a bus served and a
/// servo it has, or on the lidar the description has.
fn fault_schedule(args: &ServeArgs, robot: &RobotDescription) -> Result<Schedule> {
    let mut faults_in_time = Vec::new();
    for text in &args.unplug {
        faults_in_time.push(Scheduled::parse(text, false).context("--unplug")?);
    }
    for text in &args.silence {
        faults_in_time.push(Scheduled::parse(text, true).context("--silence")?);
    }
    for s in faults_in_time.iter().filter(|s| !is_lidar(s)) {
        let bus = robot.bus(&s.bus).filter(|_| serves_bus(args, &s.bus));
        let Some(bus) = bus else {
            anyhow::bail!("scheduled fault on bus {:?}, which is not served", s.bus);
        };
        if let Some(id) = s.id {
            if !bus.servo.iter().any(|v| v.id == id) {
                anyhow::bail!(
                    "scheduled fault on servo {id}, which bus {} does not have",
                    s.bus
                );
            }
        }
    }
    if faults_in_time.iter().any(is_lidar) && robot.lidar.is_none() {
        anyhow::bail!("--unplug lidar: the description has no lidar");
    }
    Ok(Schedule::new(faults_in_time))
}

/// The buses served, each with its line's faults (a seed of its own) and its device's path.
fn sim_buses(
    args: &ServeArgs,
    robot: &RobotDescription,
    faults: &sim::faults::LineFaults,
) -> Result<Vec<(SimBus, PathBuf)>> {
    let fresh = fresh_servos(args, robot)?;
    let mut buses = Vec::new();
    for (i, bus) in robot
        .bus
        .iter()
        .filter(|b| serves_bus(args, &b.name))
        .enumerate()
    {
        let mut sim_bus = SimBus::new(robot, bus);
        sim_bus.thermal_speedup = args.thermal_speedup;
        sim_bus.set_line_faults(Some(sim::faults::LineFaults {
            seed: faults.seed.wrapping_add(i as u64),
            ..*faults
        }));
        if let Some(seed) = args.assembly_seed {
            sim_bus.assemble(seed);
        }
        for (_, joint) in fresh.iter().filter(|(b, _)| *b == bus.name) {
            // A horn goes on the spline at any of its teeth: seeded by the joint, so a run is
            // repeatable; never where the old one was.
            let seed = sim::rng::seed_for(args.fault_seed, joint);
            let horn = sim::rng::Rng::new(seed).range(40.0, 400.0).round();
            if !sim_bus.fit_fresh_servo(robot, joint, horn) {
                anyhow::bail!(
                    "--fresh-servo: cannot fit a servo at {joint} on {}",
                    bus.name
                );
            }
            eprintln!(
                "nori sim: a factory-fresh servo (id 1) at {joint} on {}, its horn {horn} \
                 steps off the old one's",
                bus.name
            );
        }
        buses.push((sim_bus, args.dir.join(&bus.name)));
    }
    Ok(buses)
}

/// `--fresh-servo BUS:JOINT`, each a joint of a bus served.
fn fresh_servos<'a>(
    args: &'a ServeArgs,
    robot: &RobotDescription,
) -> Result<Vec<(&'a str, &'a str)>> {
    args.fresh_servo
        .iter()
        .map(|text| {
            let (bus, joint) = text
                .split_once(':')
                .with_context(|| format!("--fresh-servo {text:?}: BUS:JOINT"))?;
            let served = robot.bus(bus).filter(|_| serves_bus(args, bus));
            let Some(described) = served else {
                anyhow::bail!("--fresh-servo {text:?}: no bus {bus:?} served");
            };
            if !described.servo.iter().any(|s| s.joint == joint) {
                anyhow::bail!("--fresh-servo {text:?}: bus {bus} has no joint {joint:?}");
            }
            Ok((bus, joint))
        })
        .collect()
}

/// Checks the cameras' fault rates; gives the lidar's faults.
fn sensor_faults(args: &ServeArgs) -> Result<sim::lidar::LidarFaults> {
    for (name, rate) in [
        ("--camera-truncate-rate", args.camera_truncate_rate),
        ("--camera-garbage-rate", args.camera_garbage_rate),
    ] {
        if !(0.0..=1.0).contains(&rate) {
            anyhow::bail!("{name} must be a probability in [0, 1], got {rate}");
        }
    }
    let lidar_faults = sim::lidar::LidarFaults {
        corrupt_rate: args.lidar_corrupt_rate,
        truncate_rate: args.lidar_truncate_rate,
        garbage_rate: args.lidar_garbage_rate,
        seed: args.fault_seed,
    };
    lidar_faults.validate().map_err(|e| anyhow::anyhow!(e))?;
    Ok(lidar_faults)
}

/// Serves the lidar, if the description has one.
fn serve_lidar(
    args: &ServeArgs,
    robot: &RobotDescription,
    faults: sim::lidar::LidarFaults,
) -> Result<Option<sim::lidar::ServedLidar>> {
    let Some(mut device) = sim::lidar::LidarDevice::new(robot, faults) else {
        return Ok(None);
    };
    device.protection_stop = args.lidar_protection_stop;
    let served = sim::lidar::serve(device, args.dir.join("lidar"))?;
    eprintln!(
        "nori sim: serving the lidar (RPLIDAR C1 protocol) on {}",
        served.device.display()
    );
    Ok(Some(served))
}

/// Serves the lift's board, if the description has a lift; the obstacle is under it from
/// the start unless `--lift-obstacle-from` says later.
fn serve_lift(
    args: &ServeArgs,
    robot: &RobotDescription,
) -> Result<Option<sim::device::Served<sim::lift::LiftBoard>>> {
    let Some(d) = &robot.lift else {
        return Ok(None);
    };
    let mut board = sim::lift::LiftBoard::new(d);
    if args.lift_obstacle_from <= 0.0 {
        board.obstacle_m = args.lift_obstacle_at;
    }
    let served = sim::device::serve("lift", board, args.dir.join("lift"))?;
    eprintln!(
        "nori sim: serving the lift's board (column at {} m of {} m) on {}",
        d.start_m,
        d.travel_m,
        served.device.display()
    );
    Ok(Some(served))
}

/// The devices served beside the buses (dropped in this order: the lidar, then the lift).
struct Devices {
    lidar: Option<sim::lidar::ServedLidar>,
    lift: Option<sim::device::Served<sim::lift::LiftBoard>>,
}

impl Devices {
    /// The lidar's and the lift's reports, for those served.
    fn reports(
        &self,
    ) -> (
        Option<sim::lidar::LidarReport>,
        Option<sim::lift::LiftReport>,
    ) {
        (
            self.lidar.as_ref().map(sim::lidar::ServedLidar::report),
            self.lift
                .as_ref()
                .and_then(|l| l.with_device(|b: &mut sim::lift::LiftBoard| b.report())),
        )
    }

    /// Keeps the devices' world up to date at `t` s: the obstacle under the lift once it is
    /// due, the lidar where the base is.
    fn follow(&self, args: &ServeArgs, served: &sim::pty::ServedRobot, t: f64) {
        if let (Some(l), Some(m)) = (&self.lift, args.lift_obstacle_at) {
            if args.lift_obstacle_from > 0.0 && t >= args.lift_obstacle_from {
                l.with_device(|b: &mut sim::lift::LiftBoard| b.obstacle_m = Some(m));
            }
        }
        // The lidar rides on the base (every 20 ms: 6 mm at the base's 0.3 m/s).
        if let Some(l) = &self.lidar {
            let pose = served
                .shared_buses()
                .lock()
                .ok()
                .and_then(|b| b.iter().find_map(SimBus::base_pose));
            if let Some(pose) = pose {
                l.with_device(|d| d.set_base_pose(pose));
            }
        }
    }
}

/// Says which constants each servo model of the robot runs: a finding's, or its rating's.
fn announce_constants(robot: &RobotDescription, constants: &[sim::constants::ModelConstants]) {
    let mut models: Vec<&str> = robot
        .bus
        .iter()
        .flat_map(|b| &b.servo)
        .map(|s| s.model.as_str())
        .collect();
    models.sort_unstable();
    models.dedup();
    for model in models {
        match constants.iter().find(|c| c.model.key() == model) {
            Some(c) => eprintln!("nori sim: servo constants of {}", c.describe()),
            None => eprintln!("nori sim: servo constants of {model}: its rating"),
        }
    }
}

/// Says what is served where: the cameras, the buses, the robot, the line's faults.
fn announce(
    args: &ServeArgs,
    robot: &RobotDescription,
    served: &sim::pty::ServedRobot,
    cameras: &sim::camera::ServedCameras,
    faults: &sim::faults::LineFaults,
) {
    for (camera, socket) in robot.camera.iter().zip(&cameras.sockets) {
        eprintln!(
            "nori sim: serving camera {} ({} {}×{} at {} fps) on {}",
            camera.name,
            camera.format,
            camera.width,
            camera.height,
            camera.fps,
            socket.display()
        );
    }
    for (device, bus) in served
        .devices
        .iter()
        .zip(robot.bus.iter().filter(|b| serves_bus(args, &b.name)))
    {
        let target = std::fs::read_link(device).unwrap_or_default();
        eprintln!(
            "nori sim: serving bus {} ({} servos, {} baud) on {} -> {}",
            bus.name,
            bus.servo.len(),
            bus.baud,
            device.display(),
            target.display()
        );
    }
    eprintln!(
        "nori sim: robot {} running in real time (thermal ×{}); Ctrl-C stops it",
        robot.name, args.thermal_speedup
    );
    if faults.any() {
        eprintln!(
            "nori sim: line faults per status packet: bit flip {}, double flip {}, drop {}, \
             truncate {}; per instruction: drop {}, corrupt {} (seed {})",
            faults.bit_flip_rate,
            faults.double_flip_rate,
            faults.drop_rate,
            faults.truncate_rate,
            faults.instruction_drop_rate,
            faults.instruction_corrupt_rate,
            faults.seed
        );
    }
}

/// A scheduled fault starting (`active`) or ending at `t` s: the lidar unplugged or plugged
/// in, a bus unplugged or plugged in, a servo silent or answering again.
fn apply_fault(
    s: &Scheduled,
    active: bool,
    t: f64,
    served: &sim::pty::ServedRobot,
    lidar: Option<&sim::lidar::ServedLidar>,
) {
    if is_lidar(s) {
        if let Some(l) = lidar {
            l.set_plugged(!active);
        }
        eprintln!(
            "nori sim: t = {t:.2} s: lidar {}",
            if active { "unplugged" } else { "plugged in" }
        );
        return;
    }
    match s.id {
        None if active => {
            served.unplug(&s.bus);
        }
        None => {
            served.replug(&s.bus);
        }
        Some(id) => {
            served.with_bus(&s.bus, |b| {
                if let Some(servo) = b.servo_mut(id) {
                    servo.answering = !active;
                }
            });
        }
    }
    eprintln!(
        "nori sim: t = {t:.2} s: {} {}{}",
        if active { "fault on" } else { "fault over" },
        s.bus,
        s.id.map(|i| format!(" servo {i}")).unwrap_or_default()
    );
}
