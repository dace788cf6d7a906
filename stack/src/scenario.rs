//! `nori sim scenario overheat|stall|grip`: the whole multi-process stack (simulator on
//! pseudo-terminals, supervisor, bus-driver) driven into a protection scenario, observed over the
//! state plane, and summarised as one JSON object.

use anyhow::{bail, Context, Result};
use clap::Args;
use serde_json::json;
use sim::scenario::{Scenario, GRIP_CONTACT_RAD, SCENARIO_BUS};
use stack::{sibling, supervisor_and_driver, Managed, Run};
use std::path::Path;
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::frames::{EventKind, JointLayout, JOINT_FLAG_DRIVER_TRIP, STATE_FLAG_SAFE_STATE};
use telemetry::plane::{self, newest, next, publish, Plane};
use telemetry::GoalFrame;

/// Options of `nori sim scenario`.
#[derive(Args, Debug)]
pub struct ScenarioArgs {
    /// The scenario.
    #[arg(value_enum)]
    scenario: Scenario,
    /// Print one JSON object (otherwise a short summary).
    #[arg(long)]
    json: bool,
    /// Heat this many times faster than real time (default: 120 for overheat, 1 otherwise).
    #[arg(long)]
    thermal_speedup: Option<f64>,
    /// Give up after this many seconds of wall time.
    #[arg(long, default_value_t = 90.0)]
    timeout: f64,
    /// Keep the processes' logs (printed at the end) instead of deleting them.
    #[arg(long)]
    keep_logs: bool,
    /// Overheat only: SIGKILL the supervisor once a motor reads this (°C), as a crash loop
    /// would leave it; the driver's own last-resort tier must then turn the bus off. The
    /// supervisor is started again once the driver has, and must take the trip over.
    #[arg(long, value_name = "CELSIUS")]
    kill_supervisor_at: Option<f32>,
    /// A model extension on every servo of the simulator (`nori sim serve --model-extension`):
    /// an effect hidden from the model lab.
    #[arg(long, value_name = "FILE")]
    model_extension: Option<std::path::PathBuf>,
    /// Run the black box too, its boxes in DIR/boxes, and the simulator's own record of the
    /// wire in DIR/sim-wire (kept after the run, to hold the boxes against).
    #[arg(long, value_name = "DIR")]
    blackbox: Option<std::path::PathBuf>,
}

#[derive(Debug, Clone, serde::Serialize)]
struct SeenEvent {
    kind: String,
    joint: Option<String>,
    t_s: f64,
    level: u8,
    value: f32,
}

/// Runs one scenario and prints its result.
pub fn run(args: &ScenarioArgs) -> Result<()> {
    let scenario = args.scenario;
    let speedup = args.thermal_speedup.unwrap_or(match scenario {
        Scenario::Overheat => 120.0,
        _ => 1.0,
    });
    let pid = std::process::id();
    let dir = std::env::temp_dir().join(format!("nori-scenario-{pid}"));
    let dev = dir.join("dev");
    std::fs::create_dir_all(&dev).with_context(|| format!("creating {}", dev.display()))?;
    let report_path = dir.join("sim-report.json");
    let domain = format!("nori_scenario_{pid}");
    let trips = dir.join("trips");
    let run = Run {
        domain: &domain,
        device_dir: &dev,
        trips: Some(&trips),
        quiet: true,
    };
    let mut stack = Stack::start(args, speedup, &run, &dir, &report_path)?;
    let io = ScenarioPlane::open(&domain, pid)?;
    let layout = stack.wait_until_up(&io, &dir)?;
    let names: Vec<String> = layout
        .joints()
        .iter()
        .map(|j| j.name().to_string())
        .collect();
    let mut goals = GoalStream::new(scenario, &layout, &names)?;
    let mut watch = Watch::new(args, goals.target, names);
    let timed_out = watch.observe(args, &io, &mut goals, &mut stack.supervisor)?;
    // Driver first: torque goes off while the bus is still there. Only what reached the wire
    // before this counts as the protection's doing (the stop turns torque off by itself).
    let stopped_ns = monotonic_ns();
    stack.driver.stop(Duration::from_secs(5));
    stack.supervisor.stop(Duration::from_secs(5));
    if let Some(b) = stack.blackbox.as_mut() {
        // Stopped, it finishes the box it is freezing.
        b.stop(Duration::from_secs(10));
    }
    stack.sim.stop(Duration::from_secs(5));
    drop(io);
    Plane::remove_unused_domain(&domain)?;
    let findings = SimFindings::read(&report_path, watch.first_trip_reading_ns, stopped_ns)?;
    let trip_record = std::fs::read_to_string(dir.join("trips")).unwrap_or_default();
    let out = watch.summary(speedup, timed_out, &findings, &trip_record);
    if args.json {
        println!("{out}");
    } else {
        println!("{}", serde_json::to_string_pretty(&out)?);
    }
    if args.keep_logs {
        eprintln!("nori sim scenario: logs in {}", dir.display());
    } else {
        remove_dir(&dir);
    }
    Ok(())
}

/// The stack under test: the simulator, the supervisor and the driver (and the black box).
struct Stack {
    sim: Managed,
    supervisor: Managed,
    driver: Managed,
    blackbox: Option<Managed>,
}

impl Stack {
    /// Starts the stack of `run` on the scenario's bus, each process logging into `dir`, the
    /// simulator set up for the scenario and reporting to `report_path`.
    fn start(
        args: &ScenarioArgs,
        speedup: f64,
        run: &Run,
        dir: &Path,
        report_path: &Path,
    ) -> Result<Stack> {
        let mut sim = Managed::new(
            "simulator",
            &sibling("nori-sim")?,
            &run.simulator(&[SCENARIO_BUS], report_path),
        );
        sim.add_args(&[
            "--scenario".into(),
            format!("{:?}", args.scenario).to_lowercase(),
            "--thermal-speedup".into(),
            speedup.to_string(),
        ]);
        if let Some(m) = &args.model_extension {
            sim.add_args(&["--model-extension".into(), m.display().to_string()]);
        }
        let [mut supervisor, mut driver] = supervisor_and_driver(run, SCENARIO_BUS)?;
        if args.kill_supervisor_at.is_some() {
            // A hold that still carries the payload (80 %, the drive limit), so the motor keeps
            // heating while the supervisor is gone, as it does in a crash loop that keeps
            // handing the arm back to full torque: only the driver's own tier stands before
            // the firmware.
            let config = dir.join("bus-driver.toml");
            let text = bus_driver::config::DEFAULT_CONFIG_TOML.replace(
                "safe-hold-torque-percent = 20",
                "safe-hold-torque-percent = 80",
            );
            std::fs::write(&config, text)
                .with_context(|| format!("writing {}", config.display()))?;
            driver.add_args(&["--config".into(), config.display().to_string()]);
        }
        for (m, log) in [
            (&mut sim, "sim.log"),
            (&mut supervisor, "supervisor.log"),
            (&mut driver, "driver.log"),
        ] {
            m.log_to(&dir.join(log))?;
        }
        let blackbox = match &args.blackbox {
            Some(out) => Some(blackbox_beside(&mut sim, run, out)?),
            None => None,
        };
        sim.start()?;
        if let Some(out) = &args.blackbox {
            // Recording before the driver starts: the box holds the whole run.
            wait_until_recording(&out.join("blackbox.log"))?;
        }
        supervisor.start()?;
        driver.start()?;
        Ok(Stack {
            sim,
            supervisor,
            driver,
            blackbox,
        })
    }

    /// Waits (30 s at most) until the stack is up and supervised: every joint answering with
    /// torque on, no safe state. Gives the driver's layout.
    fn wait_until_up(&mut self, io: &ScenarioPlane, dir: &Path) -> Result<JointLayout> {
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            if let (Some(l), Some(st)) = (newest(&io.layouts), newest(&io.states)) {
                let ready = st
                    .joints()
                    .iter()
                    .all(|j| j.is_valid() && j.torque_enabled == 1);
                if ready && st.flags & STATE_FLAG_SAFE_STATE == 0 && l.joint_count == st.joint_count
                {
                    return Ok(l);
                }
            }
            if Instant::now() > deadline
                || self.sim.exited()
                || self.driver.exited()
                || self.supervisor.exited()
            {
                bail!("the stack did not come up (logs in {})", dir.display());
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

/// The black box for a scenario: the simulator told to record its wire in `out/sim-wire`, the
/// recorder started (logging to `out/blackbox.log`) with its boxes in `out/boxes`.
fn blackbox_beside(sim: &mut Managed, run: &Run, out: &Path) -> Result<Managed> {
    let wire = out.join("sim-wire");
    let boxes = out.join("boxes");
    for d in [&wire, &boxes] {
        std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
    }
    sim.add_args(&["--wire-log".into(), wire.display().to_string()]);
    let mut b = Managed::new(
        "blackbox",
        &sibling("nori-blackbox")?,
        &run.blackbox(&boxes),
    );
    b.log_to(&out.join("blackbox.log"))?;
    b.start()?;
    Ok(b)
}

/// Waits (10 s at most) until the recorder says it records (its subscriptions are open).
fn wait_until_recording(log: &Path) -> Result<()> {
    let deadline = Instant::now() + Duration::from_secs(10);
    while Instant::now() < deadline {
        let text = std::fs::read_to_string(log).unwrap_or_default();
        if text.contains("recording the last minutes") {
            return Ok(());
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    bail!(
        "the black box did not start recording (its log: {})",
        log.display()
    )
}

/// The scenario's link to the state plane (dropped in this order, the node last).
struct ScenarioPlane {
    states: plane::Sub<telemetry::JointState>,
    events: plane::Sub<telemetry::frames::SupervisorEvent>,
    grips: plane::Sub<telemetry::frames::GripFrame>,
    layouts: plane::Sub<JointLayout>,
    goals: plane::Pub<GoalFrame>,
    _node: Plane,
}

impl ScenarioPlane {
    fn open(domain: &str, pid: u32) -> Result<ScenarioPlane> {
        let node = Plane::open(domain, &format!("scenario-{pid}"))?;
        Ok(ScenarioPlane {
            states: node.subscriber(&plane::JOINT_STATE)?,
            events: node.subscriber(&plane::EVENTS)?,
            grips: node.subscriber(&plane::GRIP)?,
            layouts: node.subscriber(&plane::LAYOUT)?,
            goals: node.publisher(&plane::GOALS)?,
            _node: node,
        })
    }
}

/// The goals that drive the scenario's target joint into its protection.
struct GoalStream {
    scenario: Scenario,
    frame: GoalFrame,
    /// The target joint's index in the layout.
    target: usize,
    /// Its goal, rad (where the gripper's ramp ends).
    goal: f32,
    last: Instant,
}

impl GoalStream {
    fn new(scenario: Scenario, layout: &JointLayout, names: &[String]) -> Result<GoalStream> {
        let (target, goal) = match scenario {
            Scenario::Overheat => ("left_shoulder_pitch", std::f32::consts::FRAC_PI_2),
            Scenario::Stall => ("left_shoulder_pitch", 1.2),
            Scenario::Grip => ("left_gripper", 0.05),
        };
        let target = names
            .iter()
            .position(|n| n == target)
            .context("target joint not in the layout")?;
        let mut frame = GoalFrame {
            joint_count: layout.joint_count,
            mask: 1 << target,
            ..GoalFrame::default()
        };
        frame.position_rad[target] = goal;
        Ok(GoalStream {
            scenario,
            frame,
            target,
            goal,
            last: Instant::now() - Duration::from_secs(1),
        })
    }

    /// Publishes the next goal when one is due: a goal stream at the control rate (a
    /// policy's 200 Hz; the gripper's ramp in small steps).
    fn tick(&mut self, goals: &plane::Pub<GoalFrame>, started: Instant) -> Result<()> {
        if self.last.elapsed() < Duration::from_millis(5) {
            return Ok(());
        }
        self.frame.seq += 1;
        self.frame.timestamp_ns = monotonic_ns();
        if self.scenario == Scenario::Grip {
            // Close gradually, as an operator or a policy does: 0.3 rad/s from 0.6 rad.
            self.frame.position_rad[self.target] =
                (0.6 - 0.3 * started.elapsed().as_secs_f32()).max(self.goal);
        }
        publish(goals, &self.frame)?;
        self.last = Instant::now();
        Ok(())
    }
}

/// What the scenario watches for on the plane, and what it saw.
struct Watch {
    scenario: Scenario,
    target: usize,
    names: Vec<String>,
    kill_supervisor_at: Option<f32>,
    /// When watching began, ns: events are timed from it.
    t0: u64,
    seen: Vec<SeenEvent>,
    grip_series: Vec<f32>,
    /// (squeeze depth past first contact, grip force) while squeezing.
    squeeze: Vec<(f64, f32)>,
    /// Squeeze depth by state frame.
    depth_by_seq: std::collections::HashMap<u64, f64>,
    hold_at: Option<usize>,
    first_trip_reading_ns: Option<u64>,
    supervisor_killed_ns: Option<u64>,
    driver_trip_ns: Option<u64>,
    supervisor_restarted: bool,
    end_at: Option<Instant>,
}

impl Watch {
    fn new(args: &ScenarioArgs, target: usize, names: Vec<String>) -> Watch {
        Watch {
            scenario: args.scenario,
            target,
            names,
            kill_supervisor_at: args.kill_supervisor_at,
            t0: monotonic_ns(),
            seen: Vec::new(),
            grip_series: Vec::new(),
            squeeze: Vec::new(),
            depth_by_seq: std::collections::HashMap::new(),
            hold_at: None,
            first_trip_reading_ns: None,
            supervisor_killed_ns: None,
            driver_trip_ns: None,
            supervisor_restarted: false,
            end_at: None,
        }
    }

    /// Seconds from the start of watching to `ns`.
    fn secs(&self, ns: u64) -> f64 {
        ns.saturating_sub(self.t0) as f64 * 1e-9
    }

    /// Drives the target and watches until 700 ms after the protection acted, or the
    /// timeout (then true).
    fn observe(
        &mut self,
        args: &ScenarioArgs,
        io: &ScenarioPlane,
        goals: &mut GoalStream,
        supervisor: &mut Managed,
    ) -> Result<bool> {
        let started = Instant::now();
        while self.end_at.is_none_or(|t| Instant::now() < t) {
            if started.elapsed().as_secs_f64() > args.timeout {
                return Ok(true);
            }
            goals.tick(&io.goals, started)?;
            self.take_states(&io.states, supervisor);
            // The driver has tripped the bus alone: a supervisor comes back and must take it
            // over.
            if self.driver_trip_ns.is_some() && !self.supervisor_restarted {
                supervisor.start()?;
                self.supervisor_restarted = true;
            }
            self.take_grips(&io.grips);
            self.take_events(&io.events);
            std::thread::sleep(Duration::from_millis(2));
        }
        Ok(false)
    }

    /// The state frames: the gripper's squeeze depth, the first reading at the trip
    /// temperature, the supervisor killed when due, the driver's own trip.
    fn take_states(
        &mut self,
        states: &plane::Sub<telemetry::JointState>,
        supervisor: &mut Managed,
    ) {
        while let Some(st) = next(states) {
            let gripper = &st.joints[self.target];
            if self.scenario == Scenario::Grip && gripper.is_valid() {
                self.depth_by_seq
                    .insert(st.seq, GRIP_CONTACT_RAD - f64::from(gripper.position_rad));
            }
            let hot = st
                .joints()
                .iter()
                .any(|j| j.is_valid() && j.temperature_c >= 59.0);
            if hot && self.first_trip_reading_ns.is_none() {
                self.first_trip_reading_ns = Some(st.timestamp_ns);
            }
            let hottest = st
                .joints()
                .iter()
                .filter(|j| j.is_valid())
                .map(|j| j.temperature_c)
                .fold(f32::MIN, f32::max);
            if let Some(at) = self.kill_supervisor_at {
                if hottest >= at && self.supervisor_killed_ns.is_none() {
                    supervisor.kill();
                    self.supervisor_killed_ns = Some(monotonic_ns());
                }
            }
            let driver_tripped = st
                .joints()
                .iter()
                .any(|j| j.flags & JOINT_FLAG_DRIVER_TRIP != 0);
            if driver_tripped && self.driver_trip_ns.is_none() {
                self.driver_trip_ns = Some(st.timestamp_ns);
            }
        }
    }

    /// The target's grip force, and with the depth of its state frame while squeezing.
    fn take_grips(&mut self, grips: &plane::Sub<telemetry::frames::GripFrame>) {
        while let Some(g) = next(grips) {
            if let Some(sample) = g.grippers[..g.gripper_count as usize]
                .iter()
                .find(|s| s.joint as usize == self.target && s.valid == 1)
            {
                self.grip_series.push(sample.force);
                match self.depth_by_seq.remove(&g.state_seq) {
                    Some(depth) if self.hold_at.is_none() && depth > 0.0 => {
                        self.squeeze.push((depth, sample.force))
                    }
                    _ => {}
                }
            }
        }
    }

    /// The events, each kept; the one the scenario waits for sets its end.
    fn take_events(&mut self, events: &plane::Sub<telemetry::frames::SupervisorEvent>) {
        while let Some(e) = next(events) {
            let kind = e.kind();
            let on_target = e.joint as usize == self.target;
            let done = match (self.scenario, kind) {
                (Scenario::Overheat, Some(EventKind::ThermalTrip)) => {
                    self.kill_supervisor_at.is_none() || self.supervisor_restarted
                }
                (Scenario::Stall | Scenario::Grip, Some(EventKind::TorqueReduced)) => on_target,
                _ => false,
            };
            if done && self.end_at.is_none() {
                self.end_at = Some(Instant::now() + Duration::from_millis(700));
                if self.scenario == Scenario::Grip {
                    self.hold_at = Some(self.grip_series.len());
                }
            }
            self.seen.push(SeenEvent {
                kind: kind.map_or_else(|| format!("unknown {}", e.kind), |k| format!("{k:?}")),
                joint: self.names.get(e.joint as usize).cloned(),
                t_s: self.secs(e.timestamp_ns),
                level: e.level,
                value: e.value,
            });
        }
    }

    /// The scenario's result, as printed.
    fn summary(
        &self,
        speedup: f64,
        timed_out: bool,
        findings: &SimFindings,
        trip_record: &str,
    ) -> serde_json::Value {
        let (scenario, seen) = (self.scenario, &self.seen);
        let trip = seen.iter().find(|e| e.kind == "ThermalTrip");
        // The paper's claim: force rises monotonically with squeeze depth. Median force per
        // 0.02 rad of depth past first contact (the median sets aside the transients of each
        // goal step), non-decreasing within one 6.5 mA register step of the estimate (0.008).
        let by_depth = median_by_depth(&self.squeeze, 0.02);
        let monotone = by_depth.len() >= 3 && by_depth.windows(2).all(|w| w[1].1 >= w[0].1 - 0.008);
        let count = |k: &str| seen.iter().filter(|e| e.kind == k).count();
        let target = self.names.get(self.target).map(String::as_str);
        json!({
            "scenario": format!("{scenario:?}").to_lowercase(),
            "thermal_speedup": speedup,
            "timed_out": timed_out,
            "software_trip_s": trip.map(|e| e.t_s * speedup),
            "software_trip_wall_s": trip.map(|e| e.t_s),
            "hardware_cutoff_fired": findings.hardware_cutoffs > 0,
            "max_temperature_c": findings.max_temperature,
            "stall_events": count("Stall"),
            "torque_reduced": seen.iter().any(|e| e.kind == "TorqueReduced" && e.joint.as_deref() == target),
            "bus_disabled": trip.is_some(),
            "trip_reaction_ms": findings.reaction_ms,
            "supervisor_killed_s": self.supervisor_killed_ns.map(|t| self.secs(t) * speedup),
            "driver_trip_s": self.driver_trip_ns.map(|t| self.secs(t) * speedup),
            "driver_trip_reaction_ms": self.driver_trip_ns.zip(self.first_trip_reading_ns).map(|(t, read)| t.saturating_sub(read) as f64 * 1e-6),
            "trip_record": trip_record.lines().collect::<Vec<_>>(),
            "grip_force_max": (scenario == Scenario::Grip).then(|| self.grip_series.iter().copied().fold(0.0f32, f32::max)),
            "grip_force_monotone_in_depth": (scenario == Scenario::Grip).then_some(monotone),
            "grip_force_by_depth": (scenario == Scenario::Grip).then_some(&by_depth),
            "grip_samples": self.grip_series.len(),
            "grip_squeeze_samples": self.squeeze.len(),
            "events": seen,
        })
    }
}

/// What the simulator's report says of the scenario's bus.
struct SimFindings {
    hardware_cutoffs: u64,
    max_temperature: f64,
    /// From the driver's first reading at the trip temperature to the bus's torque-off
    /// broadcast arriving at the simulated servos, ms.
    reaction_ms: Option<f64>,
}

impl SimFindings {
    /// Reads the report at `path`; the reaction counts only a broadcast before `stopped_ns`.
    fn read(
        path: &Path,
        first_trip_reading_ns: Option<u64>,
        stopped_ns: u64,
    ) -> Result<SimFindings> {
        let report: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?,
        )?;
        let bus = &report["buses"][0];
        let servos = bus["servos"].as_array().cloned().unwrap_or_default();
        let hardware_cutoffs: u64 = servos
            .iter()
            .filter_map(|s| s["hardware_cutoffs"].as_u64())
            .sum();
        let max_temperature = servos
            .iter()
            .filter_map(|s| s["max_temperature_c"].as_f64())
            .fold(f64::NAN, f64::max);
        let epoch = bus["epoch_monotonic_ns"].as_u64().unwrap_or(0);
        let reaction_ms = first_trip_reading_ns.and_then(|read| {
            bus["torque_off_broadcasts_s"]
                .as_array()?
                .iter()
                .filter_map(|t| t.as_f64())
                .map(|t| epoch + (t * 1e9) as u64)
                .find(|&ns| ns >= read && ns < stopped_ns)
                .map(|ns| (ns - read) as f64 * 1e-6)
        });
        Ok(SimFindings {
            hardware_cutoffs,
            max_temperature,
            reaction_ms,
        })
    }
}

/// Median of the second element per bin of the first, bins of `width` from 0; (bin centre,
/// median) for bins with at least three samples.
fn median_by_depth(samples: &[(f64, f32)], width: f64) -> Vec<(f64, f32)> {
    let mut bins: std::collections::BTreeMap<i64, Vec<f32>> = std::collections::BTreeMap::new();
    for &(depth, force) in samples {
        bins.entry((depth / width).floor() as i64)
            .or_default()
            .push(force);
    }
    bins.into_iter()
        .filter(|(_, v)| v.len() >= 3)
        .map(|(bin, mut v)| {
            v.sort_by(f32::total_cmp);
            ((bin as f64 + 0.5) * width, v[v.len() / 2])
        })
        .collect()
}

fn remove_dir(dir: &Path) {
    let _ = std::fs::remove_dir_all(dir);
}
