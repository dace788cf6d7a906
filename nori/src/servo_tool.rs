//! `nori servo scan` (what is on the servo buses) and `nori servo setup` (a new servo given its
//! joint's id and settings), for commissioning and service. Each opens a bus itself, so the stack must be stopped first: the port is opened exclusively (a lock the
//! driver holds too), and whichever comes second is refused.

use anyhow::{bail, Context, Result};
use bus_driver::config::BusConfig;
use bus_driver::{LoadedConfig, SerialTransport};
use commission::findings::{judge, model_name, Finding, Severity};
use commission::scan::{scan, AtRate, BroadcastAnswer, BusScan, Plan};
use commission::setup::{set_up as set_up_servo, Target};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The driver's configuration on an installed robot.
const INSTALLED_CONFIG: &str = "/etc/nori/bus-driver.toml";

/// `nori servo …`.
#[derive(clap::Subcommand)]
pub enum ServoCommand {
    /// Find every servo on a bus at every line rate: id, model, firmware, EEPROM settings;
    /// duplicated ids, servos at the wrong rate, missing and unexpected servos named. Reads
    /// only. Exits 1 when a fault is found.
    Scan(ScanArgs),
    /// Set up a new servo for a joint: connected alone, or at the factory's id 1 (1 Mbps)
    /// among servos that do not use it, it gets the joint's id, the bus's rate, the driver's
    /// EEPROM settings and Lock (torque off). Refused when the joint's id already answers, the
    /// servo is not alone, or it is the wrong model. Calibrate the joint afterwards.
    Setup(SetupArgs),
}

/// Where the buses are: the driver's configuration and devices.
#[derive(clap::Args)]
pub struct Buses {
    /// The driver's configuration: /etc/nori/bus-driver.toml when it exists, else the embedded
    /// default (the simulated A3).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Open every bus at DIR/<bus name> (where `nori sim serve` links its pseudo-terminals).
    #[arg(long, value_name = "DIR")]
    device_dir: Option<PathBuf>,
}

impl Buses {
    /// The configuration, its devices moved to `--device-dir`, and where it came from.
    pub(crate) fn load(&self) -> Result<(LoadedConfig, String)> {
        let (loaded, origin) = load_config(self.config.as_deref())?;
        Ok(match &self.device_dir {
            Some(dir) => (loaded.with_device_dir(dir), origin),
            None => (loaded, origin),
        })
    }
}

/// `nori servo setup`.
#[derive(clap::Args)]
pub struct SetupArgs {
    /// The bus.
    bus: String,
    /// The joint whose servo this is.
    joint: String,
    #[command(flatten)]
    buses: Buses,
}

/// `nori servo scan`.
#[derive(clap::Args)]
pub struct ScanArgs {
    /// The bus (a name in the driver's configuration); every bus when absent.
    bus: Option<String>,
    #[command(flatten)]
    buses: Buses,
    /// Only at the bus's own rate (a servo at another rate is not found).
    #[arg(long)]
    bus_rate_only: bool,
    /// Print the scans and findings as JSON.
    #[arg(long)]
    json: bool,
}

/// Runs a `nori servo` command.
pub fn servo(command: &ServoCommand) -> Result<()> {
    match command {
        ServoCommand::Scan(args) => scan_buses(args),
        ServoCommand::Setup(args) => set_up(args),
    }
}

fn set_up(args: &SetupArgs) -> Result<()> {
    let (loaded, origin) = args.buses.load()?;
    let Some(bus) = loaded.config.bus(&args.bus) else {
        bail!("no bus {:?} in {origin}", args.bus);
    };
    let target = Target::of(&loaded, bus, &args.joint)?;
    let plan = plan_for(&loaded, bus);
    let line = SerialTransport::open(&bus.device, bus.baud)?;
    let report = set_up_servo(line, &target, &plan).with_context(|| {
        format!(
            "setting up {} on bus {} ({})",
            args.joint,
            bus.name,
            bus.device.display()
        )
    })?;
    println!(
        "found the servo at id {} at {} baud; wrote:",
        report.found.id, report.found.baud
    );
    for s in &report.written {
        println!("  {} = {}", s.register.name, s.value);
    }
    println!(
        "{} is id {} at {} baud, its EEPROM locked. Next: calibrate the joint.",
        args.joint, target.id, target.baud
    );
    Ok(())
}

fn scan_buses(args: &ScanArgs) -> Result<()> {
    let (loaded, origin) = args.buses.load()?;
    let buses: Vec<&BusConfig> = loaded
        .config
        .bus
        .iter()
        .filter(|b| args.bus.as_ref().is_none_or(|name| &b.name == name))
        .collect();
    if buses.is_empty() {
        let names: Vec<&str> = loaded.config.bus.iter().map(|b| b.name.as_str()).collect();
        bail!("no bus {:?} in {origin} (its buses: {names:?})", args.bus);
    }
    let mut reports = Vec::new();
    for bus in buses {
        let mut plan = plan_for(&loaded, bus);
        if args.bus_rate_only {
            plan.rates.truncate(1);
        }
        let line = SerialTransport::open(&bus.device, bus.baud)?;
        let scanned = scan(line, &plan)
            .with_context(|| format!("scanning bus {} on {}", bus.name, bus.device.display()))?;
        let findings = judge(&loaded, bus, &scanned);
        reports.push((bus, scanned, findings));
    }
    let faults = reports
        .iter()
        .flat_map(|(_, _, f)| f)
        .filter(|f| f.severity() == Severity::Fault)
        .count();
    if args.json {
        let json: Vec<_> = reports
            .iter()
            .map(|(bus, scan, findings)| {
                serde_json::json!({ "bus": bus.name, "device": bus.device, "baud": bus.baud,
                    "calibration": calibration_origin(&loaded), "scan": scan,
                    "findings": findings })
            })
            .collect();
        println!("{}", serde_json::to_string_pretty(&json)?);
    } else {
        println!("configuration: {origin}");
        println!("calibration: {}", calibration_origin(&loaded));
        for (bus, scan, findings) in &reports {
            print_bus(bus, scan, findings);
        }
    }
    if faults > 0 {
        eprintln!("nori servo scan: {faults} fault(s) found");
        std::process::exit(1);
    }
    Ok(())
}

/// Every id at every rate, the bus's first, each joint's id tried again when silent; the
/// adapter's latency is the driver's reply margin.
fn plan_for(loaded: &LoadedConfig, bus: &BusConfig) -> Plan {
    let latency = Duration::from_micros(loaded.config.reply_timeout_margin_us);
    Plan::full(bus.baud, latency, bus.servo.iter().map(|s| s.id).collect())
}

/// Where the calibration the scan compares with comes from.
fn calibration_origin(loaded: &LoadedConfig) -> String {
    match &loaded.config.calibration_file {
        Some(file) => file.display().to_string(),
        None => "the embedded one of the simulated A3 (no `calibration-file`: wrong for any \
                 real robot)"
            .to_string(),
    }
}

/// The configuration asked for, the installed one, or the embedded default; and what it was.
fn load_config(path: Option<&Path>) -> Result<(LoadedConfig, String)> {
    let installed = Path::new(INSTALLED_CONFIG);
    let path = path.or(installed.exists().then_some(installed));
    let origin = path.map_or("the embedded default (the simulated A3)".into(), |p| {
        p.display().to_string()
    });
    // As far as the robot is calibrated: these are the tools that calibrate it.
    let loaded =
        LoadedConfig::for_commissioning(path).with_context(|| format!("loading {origin}"))?;
    Ok((loaded, origin))
}

fn print_bus(bus: &BusConfig, scan: &BusScan, findings: &[Finding]) {
    println!(
        "\nbus {} on {} at {} baud",
        bus.name,
        bus.device.display(),
        bus.baud
    );
    for rate in &scan.rates {
        print_rate(bus, rate);
    }
    if findings.is_empty() {
        println!("  findings: none");
    }
    for f in findings {
        let tag = match f.severity() {
            Severity::Fault => "FAULT",
            Severity::Note => "note ",
        };
        println!("  {tag} {f}");
    }
}

fn print_rate(bus: &BusConfig, rate: &AtRate) {
    let broadcast = match &rate.broadcast {
        BroadcastAnswer::Silent => "no answer".to_string(),
        BroadcastAnswer::One { id } => format!("id {id} alone"),
        BroadcastAnswer::Several { ids, .. } if ids.is_empty() => {
            "garbled (several servos answered at once)".to_string()
        }
        BroadcastAnswer::Several { ids, damaged } => {
            format!("intact answers from {ids:?}, {damaged} damaged")
        }
    };
    if rate.found.is_empty() && rate.baud != bus.baud {
        return;
    }
    println!("  at {} baud: broadcast ping: {broadcast}", rate.baud);
    println!(
        "    {:>3}  {:<22} {:<8} {:>5} {:>7} {:>11} {:>5} {:>6} {:>6} {:>4}",
        "id", "joint", "model", "fw", "delay", "limits", "°C", "torque", "offset", "lock"
    );
    for f in &rate.found {
        let joint = bus
            .servo
            .iter()
            .find(|s| s.id == f.id)
            .map_or("-", |s| s.joint.as_str());
        match (&f.settings, &f.duplicate) {
            (_, Some(d)) => println!("    {:>3}  {joint:<22} duplicated id ({d:?})", f.id),
            (None, None) => println!("    {:>3}  {joint:<22} table unreadable", f.id),
            (Some(s), None) => println!(
                "    {:>3}  {joint:<22} {:<8} {:>5} {:>4} µs {:>11} {:>5} {:>5.1}% {:>6} {:>4}",
                f.id,
                model_name(s.model_number),
                format!("{}.{}", s.firmware.0, s.firmware.1),
                s.return_delay_us,
                format!("{}..{}", s.position_limits.0, s.position_limits.1),
                s.max_temperature_c,
                f64::from(s.max_torque_permille) / 10.0,
                s.homing_offset,
                s.lock
            ),
        }
    }
}
