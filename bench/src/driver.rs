//! `driver-rate` (the driver's loop against the wire-timed simulator) and `sim-speed` (batch
//! simulation against real time).

use crate::base::BaseLoad;
use crate::blackbox::{BlackboxLoad, PlaneIo};
use crate::cameras::CameraLoad;
use crate::lidar::LidarLoad;
use anyhow::{Context, Result};
use bus_driver::tap::Tapped;
use bus_driver::{Driver, LoadedConfig, LoopIo, SerialTransport, Standalone, Transport};
use clap::Args;
use feetech::registers as reg;
use feetech::timing::{cycle_bytes, wire_time};
use sim::pty::serve;
use sim::{RobotDescription, SimBus};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use telemetry::config::ProcessConfig;

/// Options of `nori bench driver-rate`.
#[derive(Args, Debug)]
pub struct DriverRateArgs {
    /// Seconds to run.
    #[arg(long, default_value_t = 5.0)]
    seconds: f64,
    /// Buses to drive (in parallel).
    #[arg(long = "bus", default_values_t = ["left_arm".to_string(), "right_arm".to_string()])]
    buses: Vec<String>,
    /// Loop set-point, Hz: 1000 runs free (shorter than any cycle's wire time), 200 is the
    /// deployed rate (where the background read-back uses the idle time of each period).
    #[arg(long, default_value_t = 1000.0)]
    rate_hz: f64,
    /// Compare against this many cameras streaming MJPEG into `nori-camera` processes (the
    /// robot's camera load, as deployed) instead of against the background read-back: both
    /// halves then read back as deployed, and the cameras stream in every other one.
    #[arg(long, default_value_t = 0)]
    cameras: usize,
    /// Camera image width, px.
    #[arg(long, default_value_t = 1280)]
    camera_width: u32,
    /// Camera image height, px.
    #[arg(long, default_value_t = 720)]
    camera_height: u32,
    /// Camera frames per second.
    #[arg(long, default_value_t = 30)]
    camera_fps: u32,
    /// Compare against the lidar scanning into `nori-lidar` (as deployed; with `--cameras`,
    /// both sensors together): both halves read back as deployed, the lidar scans in every
    /// other one and is unplugged in the rest.
    #[arg(long)]
    lidar: bool,
    /// Compare against the base controller (`nori-base`, as deployed) driving: fed a stand-in
    /// driver's wheel readings at 200 Hz, revolutions at 10 Hz and commands at 20 Hz in every
    /// other half, idle (no layout) in the rest.
    #[arg(long)]
    base: bool,
    /// Compare against the black box: both halves run the driver as deployed (its wire
    /// tapped, its state and wire frames published on the plane); in every other half
    /// `nori-blackbox` records and freezes a box, in the rest none runs.
    #[arg(long)]
    blackbox: bool,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

/// Options of `nori bench sim-speed`.
#[derive(Args, Debug)]
pub struct SimSpeedArgs {
    /// Simulated seconds per repetition.
    #[arg(long, default_value_t = 120.0)]
    sim_seconds: f64,
    /// Repetitions (the best is the least disturbed by other load on the machine).
    #[arg(long, default_value_t = 5)]
    repetitions: usize,
    /// Mechanics step, s.
    #[arg(long, default_value_t = 0.001)]
    dt: f64,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

/// One run of the loop for `driver_rate`.
struct RateRun {
    summary: bus_driver::RunSummary,
    replies: u64,
    missing: u64,
    read_backs: u64,
    late_bursts: u64,
    max_lateness_us: f64,
}

/// Serves the buses, sets the driver up and runs its loop for `seconds` at `rate_hz` (no
/// supervisor), with or without the background read-back of safety settings and the slowed
/// approach to the ranges' ends (`as_deployed`); with `plane`, as
/// deployed on that domain (its wire tapped, its state and wire frames published), otherwise
/// publishing nothing.
fn rate_run(
    buses: &[String],
    rate_hz: f64,
    seconds: f64,
    as_deployed: bool,
    plane: Option<&str>,
) -> Result<RateRun> {
    let robot = RobotDescription::nori_a3();
    let dir = std::env::temp_dir().join(format!("nori-bench-{}", std::process::id()));
    let mut sims = Vec::new();
    for name in buses {
        let bus = robot
            .bus(name)
            .with_context(|| format!("no bus {name:?}"))?;
        sims.push((SimBus::new(&robot, bus), dir.join(name)));
    }
    let served = serve(sims, 0.001)?;
    let mut config = LoadedConfig::embedded()?.with_device_dir(&dir);
    config.config.bus.retain(|b| buses.contains(&b.name));
    config.config.rate_hz = rate_hz;
    config.config.supervisor_timeout_ms = 0;
    let transports = config
        .config
        .bus
        .iter()
        .map(|b| SerialTransport::open(&b.device, b.baud))
        .collect::<Result<Vec<_>, _>>()?;
    let counts = match plane {
        None => measure(
            Driver::new(&config, transports),
            &config,
            &mut Standalone,
            as_deployed,
            seconds,
        )?,
        Some(domain) => measure(
            Driver::new(&config, transports.into_iter().map(Tapped::new).collect()),
            &config,
            &mut PlaneIo::open(domain)?,
            as_deployed,
            seconds,
        )?,
    };
    let lines: Vec<_> = served.stop().into_iter().map(|r| r.line).collect();
    Ok(RateRun {
        late_bursts: lines.iter().map(|l| l.late_bursts).sum(),
        max_lateness_us: lines.iter().map(|l| l.max_lateness_us).fold(0.0, f64::max),
        ..counts
    })
}

/// Sets `driver` up and runs its loop for `seconds` against `io`; the run's counts (the
/// simulator's lateness left to the caller).
fn measure<T: Transport>(
    mut driver: Driver<T>,
    config: &LoadedConfig,
    io: &mut dyn LoopIo,
    as_deployed: bool,
    seconds: f64,
) -> Result<RateRun> {
    // The baseline: without the background read-back and the slowed approach to the ranges'
    // ends, the two parts of the loop that exist for safety and have a per-cycle cost.
    driver.set_background_read_back(as_deployed);
    driver.set_slowed_approach(as_deployed);
    // A servo missed at setup (machine hiccup) is set up again before measuring.
    let mut failures = driver.setup();
    for _ in 0..5 {
        if failures.is_empty() {
            break;
        }
        failures = driver.setup();
    }
    anyhow::ensure!(failures.is_empty(), "setup failed: {failures:?}");
    let shutdown = Arc::new(AtomicBool::new(false));
    let timer = {
        let stop = shutdown.clone();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_secs_f64(seconds));
            stop.store(true, Ordering::SeqCst);
        })
    };
    let summary = bus_driver::run(
        &mut driver,
        config.config.period(),
        None,
        io,
        &shutdown,
        None,
    );
    let _ = timer.join();
    let sum = |f: fn(&bus_driver::bus::BusCounters) -> u64| -> u64 {
        driver.bus_counters().map(|(_, c)| f(&c)).sum()
    };
    let (replies, missing, read_backs) = (
        sum(|c| c.replies),
        sum(|c| c.missing),
        sum(|c| c.read_backs),
    );
    Ok(RateRun {
        summary,
        replies,
        missing,
        read_backs,
        late_bursts: 0,
        max_lateness_us: 0.0,
    })
}

pub fn driver_rate(args: &DriverRateArgs) -> Result<()> {
    bus_driver::rt::prepare_control_thread();
    let jitter = wakeup_jitter(Duration::from_secs(1));
    let wire = WireLimit::of(&args.buses);
    // The baseline and the variant in the same run, in alternating halves so that a slow
    // stretch of this shared machine hits both alike. The variant is the background read-back
    // and the slowed approach (the stack as deployed), or with --cameras the cameras streaming
    // (both halves as deployed).
    let domain = format!("nori_bench_sensors_{}", std::process::id());
    let sensors = args.cameras > 0 || args.lidar || args.base || args.blackbox;
    let mut loads = SensorLoads::start(args, &domain)?;
    let halves = run_halves(args, &mut loads, sensors, &domain)?;
    loads.feed(false)?;
    let blackbox_load = loads.blackbox.as_ref().map(BlackboxLoad::figures);
    let load = load_figures(loads, args, &domain, &halves);
    let without = rate_figures(&halves.runs[0], wire.hz);
    let with = rate_figures(&halves.runs[1], wire.hz);
    let out = serde_json::json!({
        "buses": args.buses.len(),
        "servos_per_bus": wire.slowest,
        "rate_hz_set": args.rate_hz,
        "cycle_bytes_per_bus": wire.bytes,
        "wire_limited_hz": wire.hz,
        "baseline": labels(args, sensors).0,
        "variant": labels(args, sensors).1,
        "baseline_figures": without,
        "variant_figures": with,
        "camera_load": load.cameras,
        "lidar_load": load.lidar,
        "base_load": load.base,
        "blackbox_load": blackbox_load,
        "rate_ratio_variant_to_baseline": measured_hz(&with) / measured_hz(&without).max(1e-9),
        "machine_wakeup_overshoot_p99_us": jitter.0,
        "machine_wakeup_overshoot_max_us": jitter.1,
    });
    if args.json {
        println!("{out}");
    } else {
        print_rate_report(&out, args, &wire, sensors, jitter);
    }
    Ok(())
}

/// The rate the wire allows the slowest of the buses driven.
struct WireLimit {
    /// Servos on the busiest bus.
    slowest: usize,
    /// Bytes of its cycle.
    bytes: usize,
    /// Cycles a second at 1 Mbps, Hz.
    hz: f64,
}

impl WireLimit {
    fn of(buses: &[String]) -> WireLimit {
        let robot = RobotDescription::nori_a3();
        let slowest = buses
            .iter()
            .filter_map(|b| robot.bus(b))
            .map(|b| b.servo.len())
            .max()
            .unwrap_or(0);
        let bytes = cycle_bytes(slowest, reg::FEEDBACK_LEN as usize, 2);
        let hz = 1.0 / wire_time(bytes, 1_000_000).as_secs_f64();
        WireLimit { slowest, bytes, hz }
    }
}

/// The sensor loads the driver is compared against, each only when asked for.
struct SensorLoads {
    cameras: Option<CameraLoad>,
    lidar: Option<LidarLoad>,
    base: Option<BaseLoad>,
    blackbox: Option<BlackboxLoad>,
}

/// CPU time the loads' processes used, s.
#[derive(Debug, Default, Clone, Copy)]
struct LoadCpu {
    cameras: f64,
    lidar: f64,
    base: f64,
}

impl SensorLoads {
    /// Starts the loads asked for on `domain` (the base's, the lidar's, then the cameras').
    fn start(args: &DriverRateArgs, domain: &str) -> Result<SensorLoads> {
        let base = if args.base {
            Some(BaseLoad::start(domain)?)
        } else {
            None
        };
        let lidar = if args.lidar {
            Some(LidarLoad::start(domain)?)
        } else {
            None
        };
        let cameras = match args.cameras {
            0 => None,
            n => Some(CameraLoad::start(
                n,
                args.camera_width,
                args.camera_height,
                args.camera_fps,
                domain,
            )?),
        };
        let blackbox = if args.blackbox {
            Some(BlackboxLoad::new(domain)?)
        } else {
            None
        };
        Ok(SensorLoads {
            cameras,
            lidar,
            base,
            blackbox,
        })
    }

    /// Streams every load (or idles it); the black box is started, freezing a box, or stopped.
    fn feed(&mut self, on: bool) -> Result<()> {
        if let Some(load) = &mut self.blackbox {
            load.feed(on)?;
            if on {
                load.save()?;
            }
        }
        if let Some(load) = &self.cameras {
            load.feed(on);
        }
        if let Some(load) = &self.lidar {
            load.feed(on);
        }
        if let Some(load) = &self.base {
            load.feed(on);
        }
        Ok(())
    }

    /// CPU time each load used so far.
    fn cpu_seconds(&self) -> LoadCpu {
        LoadCpu {
            cameras: self.cameras.as_ref().map_or(0.0, CameraLoad::cpu_seconds),
            lidar: self.lidar.as_ref().map_or(0.0, LidarLoad::cpu_seconds),
            base: self.base.as_ref().map_or(0.0, BaseLoad::cpu_seconds),
        }
    }
}

/// The runs of the baseline's halves (`runs[0]`) and the variant's (`runs[1]`), and what the
/// loads cost during the variant's.
struct Halves {
    runs: [Vec<RateRun>; 2],
    /// CPU time of the loads while they streamed.
    cpu: LoadCpu,
    /// Time they streamed, s.
    streaming_s: f64,
}

/// Runs the driver in four alternating halves: baseline, variant, baseline, variant.
fn run_halves(
    args: &DriverRateArgs,
    loads: &mut SensorLoads,
    sensors: bool,
    domain: &str,
) -> Result<Halves> {
    let half = args.seconds / 2.0;
    let mut halves = Halves {
        runs: [Vec::new(), Vec::new()],
        cpu: LoadCpu::default(),
        streaming_s: 0.0,
    };
    for variant in [false, true, false, true] {
        let as_deployed = variant || sensors;
        loads.feed(variant)?;
        if sensors {
            // Let the sensors reach (or leave) their steady rate before timing.
            let settle = if args.lidar {
                LidarLoad::SETTLE
            } else {
                Duration::from_millis(500)
            };
            std::thread::sleep(settle);
        }
        let before = loads.cpu_seconds();
        let plane = args.blackbox.then_some(domain);
        let run = rate_run(&args.buses, args.rate_hz, half, as_deployed, plane)?;
        if variant {
            let after = loads.cpu_seconds();
            halves.cpu.cameras += after.cameras - before.cameras;
            halves.cpu.lidar += after.lidar - before.lidar;
            halves.cpu.base += after.base - before.base;
            halves.streaming_s += run.summary.elapsed_s;
        }
        halves.runs[usize::from(variant)].push(run);
    }
    Ok(halves)
}

/// Each load's figures (none for a load not asked for).
struct LoadFigures {
    cameras: Option<serde_json::Value>,
    lidar: Option<serde_json::Value>,
    base: Option<serde_json::Value>,
}

/// The loads' figures; each load is stopped once its own are taken.
fn load_figures(
    loads: SensorLoads,
    args: &DriverRateArgs,
    domain: &str,
    halves: &Halves,
) -> LoadFigures {
    let SensorLoads {
        cameras,
        lidar,
        base,
        blackbox: _,
    } = loads;
    let (cpu, streaming_s) = (halves.cpu, halves.streaming_s);
    let camera_figures = cameras.as_ref().map(|load| {
        let published = camera_frames_published(domain, args.cameras);
        serde_json::json!({
            "cameras": args.cameras,
            "width": args.camera_width,
            "height": args.camera_height,
            "fps": args.camera_fps,
            "jpeg_bytes": load.jpeg_bytes,
            "frames_published": published,
            "streaming_seconds": streaming_s,
            "cpu_per_camera_percent_of_a_core": 100.0 * cpu.cameras / streaming_s.max(1e-9) / args.cameras as f64,
            "peak_rss_mb": load.peak_rss_mb(),
        })
    });
    drop(cameras);
    let lidar_figures = lidar.as_ref().map(|load| {
        serde_json::json!({
            "scans_published": crate::lidar::scans_published(domain),
            "scanning_seconds": streaming_s,
            "cpu_percent_of_a_core": 100.0 * cpu.lidar / streaming_s.max(1e-9),
            "peak_rss_mb": load.peak_rss_mb(),
        })
    });
    drop(lidar);
    let base_figures = base.as_ref().map(|load| {
        serde_json::json!({
            "goals_sent": load.goals_sent(),
            "driving_seconds": streaming_s,
            "cpu_percent_of_a_core": 100.0 * cpu.base / streaming_s.max(1e-9),
            "peak_rss_mb": load.peak_rss_mb(),
        })
    });
    drop(base);
    LoadFigures {
        cameras: camera_figures,
        lidar: lidar_figures,
        base: base_figures,
    }
}

/// The figures of one side's runs, summed over its halves.
fn rate_figures(r: &[RateRun], wire_limited_hz: f64) -> serde_json::Value {
    let cycles: u64 = r.iter().map(|x| x.summary.counters.cycles).sum();
    let elapsed: f64 = r.iter().map(|x| x.summary.elapsed_s).sum();
    let misses: u64 = r.iter().map(|x| x.summary.counters.deadline_misses).sum();
    serde_json::json!({
        "measured_hz": cycles as f64 / elapsed.max(1e-9),
        "ratio_to_wire_limited": cycles as f64 / elapsed.max(1e-9) / wire_limited_hz,
        "cycles": cycles,
        "deadline_misses": misses,
        "deadline_miss_ratio": misses as f64 / cycles.max(1) as f64,
        "replies": r.iter().map(|x| x.replies).sum::<u64>(),
        "missing_replies": r.iter().map(|x| x.missing).sum::<u64>(),
        "read_backs": r.iter().map(|x| x.read_backs).sum::<u64>(),
        "sim_late_bursts": r.iter().map(|x| x.late_bursts).sum::<u64>(),
        "sim_max_lateness_us": r.iter().map(|x| x.max_lateness_us).fold(0.0, f64::max),
    })
}

/// What the baseline and the variant are.
fn labels(args: &DriverRateArgs, sensors: bool) -> (&'static str, &'static str) {
    if args.blackbox && args.cameras == 0 && !args.lidar && !args.base {
        (
            "as deployed, no recorder",
            "as deployed, the black box recording",
        )
    } else if sensors {
        ("as deployed, loads idle", "as deployed, loads running")
    } else {
        (
            "baseline, no background read-back or slowed approach",
            "as deployed",
        )
    }
}

/// The rate a side's figures measured, Hz.
fn measured_hz(v: &serde_json::Value) -> f64 {
    v["measured_hz"].as_f64().unwrap_or(0.0)
}

/// Prints `nori bench driver-rate`'s result (`out`, its JSON) for a reader.
fn print_rate_report(
    out: &serde_json::Value,
    args: &DriverRateArgs,
    wire: &WireLimit,
    sensors: bool,
    jitter: (f64, f64),
) {
    let (without, with) = (&out["baseline_figures"], &out["variant_figures"]);
    let hz = measured_hz;
    let line = |name: &str, v: &serde_json::Value| {
        format!(
            "{name}: {:.1} Hz (ratio to the wire-limited {:.3}), deadline misses {} of {} ({:.4}), {} replies, {} missing, {} read-backs",
            hz(v), v["ratio_to_wire_limited"].as_f64().unwrap_or(0.0), v["deadline_misses"], v["cycles"],
            v["deadline_miss_ratio"].as_f64().unwrap_or(0.0), v["replies"], v["missing_replies"], v["read_backs"]
        )
    };
    let (base, variant) = labels(args, sensors);
    let WireLimit {
        slowest,
        bytes,
        hz: wire_limited_hz,
    } = wire;
    println!(
        "driver loop, {} buses × {slowest} servos in parallel at a {} Hz set-point; {wire_limited_hz:.1} Hz wire-limited ({bytes} bytes a cycle at 1 Mbps)\n  {}\n  {}\n  rate {variant} / {base}: {:.3}; this machine wakes a 200 µs sleep up to {:.0} µs late at p99 ({:.0} µs max)",
        args.buses.len(), args.rate_hz, line(base, without), line(variant, with),
        hz(with) / hz(without).max(1e-9), jitter.0, jitter.1
    );
    if let Some(c) = out["camera_load"].as_object() {
        println!(
            "  cameras: {} × {}×{} MJPEG at {} fps into nori-camera (JPEG {} bytes): {} frames published, {:.1} % of a core per camera while streaming, peak RSS {} MB",
            c["cameras"], c["width"], c["height"], c["fps"], c["jpeg_bytes"], c["frames_published"],
            c["cpu_per_camera_percent_of_a_core"].as_f64().unwrap_or(f64::NAN), c["peak_rss_mb"]
        );
    }
    if let Some(b) = out["base_load"].as_object() {
        println!(
            "  base: nori-base driving (wheel readings at 200 Hz, commands at 20 Hz): {} wheel goal frames sent, {:.1} % of a core while driving, peak RSS {} MB",
            b["goals_sent"],
            b["cpu_percent_of_a_core"].as_f64().unwrap_or(f64::NAN), b["peak_rss_mb"]
        );
    }
    if let Some(b) = out["blackbox_load"].as_object() {
        println!(
            "  black box: nori-blackbox recording the driver's state and wire, a box frozen in each half: {:.1} % of a core, peak RSS {:.1} MB, boxes {}",
            b["cpu_percent_of_a_core"].as_f64().unwrap_or(f64::NAN),
            b["peak_rss_mb"].as_f64().unwrap_or(f64::NAN),
            b["box_bytes"]
        );
    }
    if let Some(l) = out["lidar_load"].as_object() {
        println!(
            "  lidar: the simulated C1 (5000 measurements/s, 10 Hz) into nori-lidar: {} revolutions published, {:.1} % of a core while scanning, peak RSS {} MB",
            l["scans_published"],
            l["cpu_percent_of_a_core"].as_f64().unwrap_or(f64::NAN), l["peak_rss_mb"]
        );
    }
}

/// Frames each camera process published so far: the newest frame's sequence number + 1. (A
/// new subscriber is connected at its publisher's next frame, so this waits a few frames.)
fn camera_frames_published(domain: &str, count: usize) -> Vec<u64> {
    let robot = RobotDescription::nori_a3();
    let Ok(node) = telemetry::plane::Plane::open(domain, "bench-counter") else {
        return Vec::new();
    };
    let subs: Vec<_> = robot
        .camera
        .iter()
        .take(count)
        .map(|c| {
            node.camera_subscriber(&c.name, telemetry::plane::CameraStream::Rgb)
                .ok()
        })
        .collect();
    std::thread::sleep(Duration::from_millis(300));
    subs.iter()
        .map(|sub| {
            let mut newest = 0;
            while let Some(Ok(Some(sample))) = sub.as_ref().map(|s| s.receive()) {
                newest = sample.user_header().seq + 1;
            }
            newest
        })
        .collect()
}

/// How late this machine wakes a thread from a 200 µs sleep (p99, max), µs: the noise floor
/// every timing figure here sits on.
fn wakeup_jitter(over: Duration) -> (f64, f64) {
    let nominal = Duration::from_micros(200);
    let mut late = Vec::new();
    let start = Instant::now();
    while start.elapsed() < over {
        let t = Instant::now();
        std::thread::sleep(nominal);
        late.push(t.elapsed().saturating_sub(nominal).as_secs_f64() * 1e6);
    }
    late.sort_by(f64::total_cmp);
    let p99 = late.get(late.len() * 99 / 100).copied().unwrap_or(0.0);
    (p99, late.last().copied().unwrap_or(0.0))
}

pub fn sim_speed(args: &SimSpeedArgs) -> Result<()> {
    let mut walls: Vec<f64> = (0..args.repetitions.max(1))
        .map(|_| batch_run(args.sim_seconds, args.dt))
        .collect();
    walls.sort_by(f64::total_cmp);
    let (best, median) = (walls[0], walls[walls.len() / 2]);
    let out = serde_json::json!({
        "servos": 16,
        "dt_s": args.dt,
        "sim_seconds": args.sim_seconds,
        "repetitions": walls.len(),
        "best_wall_seconds": best,
        "median_wall_seconds": median,
        "realtime_multiple_best": args.sim_seconds / best,
        "realtime_multiple_median": args.sim_seconds / median,
        "baseline": "real time (1×)",
    });
    if args.json {
        println!("{out}");
    } else {
        println!(
            "batch simulation, 16 servos on two arms, dt {} ms: {:.0} s simulated in {:.3} s wall at best, {:.3} s median of {} = {:.0}× real time at best, {:.0}× median (baseline 1×)",
            args.dt * 1e3,
            args.sim_seconds,
            best,
            median,
            walls.len(),
            args.sim_seconds / best,
            args.sim_seconds / median
        );
    }
    Ok(())
}

/// Steps both arm buses for `sim_seconds` with a 200 Hz stream of moving goals, as the driver
/// would send; returns the wall time, s.
fn batch_run(sim_seconds: f64, dt: f64) -> f64 {
    let robot = RobotDescription::nori_a3();
    let mut buses: Vec<SimBus> = ["left_arm", "right_arm"]
        .iter()
        .filter_map(|n| robot.bus(n))
        .map(|b| SimBus::new(&robot, b))
        .collect();
    for bus in &mut buses {
        for s in &mut bus.servos {
            s.write(reg::TORQUE_ENABLE.addr, &[1]);
        }
    }
    let steps = (sim_seconds / dt).round() as u64;
    let goal_every = (0.005 / dt).round().max(1.0) as u64;
    let start = Instant::now();
    for k in 0..steps {
        if k % goal_every == 0 {
            let t = k as f64 * dt;
            for bus in &mut buses {
                for (i, s) in bus.servos.iter_mut().enumerate() {
                    let q = 0.4 * (t * 0.5 + i as f64).sin();
                    let goal = (2048.0 + q * 651.9).round() as u16;
                    s.write(reg::GOAL_POSITION.addr, &goal.to_le_bytes());
                }
            }
        }
        for bus in &mut buses {
            bus.step(dt);
        }
    }
    start.elapsed().as_secs_f64()
}
