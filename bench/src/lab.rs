//! `nori bench lab-latency`: a key press in Nori Lab's page (headless Chromium) until a goal it
//! caused is on the simulated wire (a servo's Goal_Position register changes), through the
//! page's handler, its WebSocket, `nori-lab` (inverse kinematics, the teleoperation rules),
//! the state plane and the real driver; against the baseline of a goal published straight on
//! the state plane (as `nori goal` or the fleet agent do) in the same run. Also the driver's
//! loop rate without the lab and with it serving a page in control, and the lab's peak RSS.

use anyhow::{bail, Context, Result};
use clap::Args;
use feetech::registers as reg;
use serde_json::json;
use sim::{RobotDescription, SimBus};
use stack::browser::{chromium, Browser};
use stack::{sibling, supervisor_and_driver, Managed, Run};
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::frames::{GoalFrame, JointLayout};
use telemetry::plane::{self, newest, Plane};
use telemetry::stats::quantile_sorted;

const BUS: &str = "left_arm";

/// Options of `nori bench lab-latency`.
#[derive(Args, Debug)]
pub struct LabLatencyArgs {
    /// Trials per path.
    #[arg(long, default_value_t = 100)]
    trials: usize,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// The arm servos' Goal_Position registers as the simulated wire last wrote them.
fn registers(served: &sim::pty::ServedRobot) -> Vec<i32> {
    served
        .with_bus(BUS, |b| {
            b.servos.iter().map(|s| s.get(reg::GOAL_POSITION)).collect()
        })
        .unwrap_or_default()
}

/// Waits until the registers differ from `before`; ms since `since_ns`, or `None` after 500 ms.
fn changed(served: &sim::pty::ServedRobot, before: &[i32], since_ns: u64) -> Option<f64> {
    let until = Instant::now() + Duration::from_millis(500);
    while Instant::now() < until {
        if registers(served) != before {
            return Some((monotonic_ns() - since_ns) as f64 / 1e6);
        }
        std::thread::sleep(Duration::from_micros(100));
    }
    None
}

/// Waits until the registers have not changed for 60 ms (a move finished), at most 2 s.
fn settle(served: &sim::pty::ServedRobot) {
    let until = Instant::now() + Duration::from_secs(2);
    let mut last = registers(served);
    let mut still_since = Instant::now();
    while Instant::now() < until && still_since.elapsed() < Duration::from_millis(60) {
        std::thread::sleep(Duration::from_millis(2));
        let now = registers(served);
        if now != last {
            last = now;
            still_since = Instant::now();
        }
    }
}

/// The driver's cycles per second over `for_s`, from its frames' sequence numbers.
fn driver_rate(states: &plane::Sub<telemetry::JointState>, for_s: f64) -> Result<f64> {
    let first = wait_state(states)?;
    let t0 = Instant::now();
    std::thread::sleep(Duration::from_secs_f64(for_s));
    let last = wait_state(states)?;
    Ok((last.seq - first.seq) as f64 / t0.elapsed().as_secs_f64())
}

fn wait_state(states: &plane::Sub<telemetry::JointState>) -> Result<telemetry::JointState> {
    let until = Instant::now() + Duration::from_secs(2);
    loop {
        if let Some(s) = newest(states) {
            return Ok(s);
        }
        if Instant::now() > until {
            bail!("no joint state");
        }
        std::thread::sleep(Duration::from_millis(1));
    }
}

fn summary(ms: &mut [f64]) -> (f64, f64) {
    ms.sort_by(f64::total_cmp);
    (quantile_sorted(ms, 0.5), quantile_sorted(ms, 0.99))
}

/// Trials of one path: how long each took to reach the wire, and how many never did.
struct Trials {
    ms: Vec<f64>,
    missed: usize,
}

impl Trials {
    fn with_capacity(trials: usize) -> Trials {
        Trials {
            ms: Vec::with_capacity(trials),
            missed: 0,
        }
    }

    /// One trial: once the arm is still, `act` (given when it starts, ns) and the wait for
    /// the registers to change. Gives what `act` gave.
    fn run<T>(
        &mut self,
        served: &sim::pty::ServedRobot,
        act: impl FnOnce(u64) -> Result<T>,
    ) -> Result<T> {
        settle(served);
        let before = registers(served);
        let now = monotonic_ns();
        let acted = act(now)?;
        match changed(served, &before, now) {
            Some(ms) => self.ms.push(ms),
            None => self.missed += 1,
        }
        Ok(acted)
    }
}

/// Waits (30 s at most) for the driver to drive every joint out of its safe state; gives
/// the layout it published.
fn wait_for_arm(
    states: &plane::Sub<telemetry::JointState>,
    layouts: &plane::Sub<JointLayout>,
    dir: &std::path::Path,
) -> Result<JointLayout> {
    let until = Instant::now() + Duration::from_secs(30);
    loop {
        let driving = newest(states).is_some_and(|s| {
            s.flags & telemetry::frames::STATE_FLAG_SAFE_STATE == 0
                && s.joints().iter().all(|j| j.is_valid())
        });
        if let Some(l) = newest(layouts).filter(|_| driving) {
            return Ok(l);
        }
        if Instant::now() > until {
            bail!("the arm did not come up (logs in {})", dir.display());
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The baseline: a goal straight on the plane, the elbow moved 0.02 rad (toward the middle
/// of its range: a goal beyond it would be clamped to where it is) and back.
fn plane_trials(
    served: &sim::pty::ServedRobot,
    states: &plane::Sub<telemetry::JointState>,
    goals: &plane::Pub<GoalFrame>,
    layout: &JointLayout,
    elbow: usize,
    trials: usize,
) -> Result<Trials> {
    let here = wait_state(states)?.joints()[elbow].position_rad;
    let [lo, hi] = layout.joints()[elbow].range_rad;
    let step = if here > (lo + hi) / 2.0 { -0.02 } else { 0.02 };
    let mut out = Trials::with_capacity(trials);
    for trial in 0..trials {
        out.run(served, |now| {
            let mut frame = GoalFrame {
                seq: trial as u64 + 1,
                timestamp_ns: now,
                joint_count: layout.joint_count,
                mask: 1 << elbow,
                ..GoalFrame::default()
            };
            frame.position_rad[elbow] = here + if trial % 2 == 0 { step } else { 0.0 };
            Ok(plane::publish(goals, &frame)?)
        })?;
    }
    Ok(out)
}

/// Starts `nori-lab` on `domain` with a token of its own; gives it and its page's address.
fn start_lab(domain: &str, dir: &std::path::Path, pid: u32) -> Result<(Managed, String)> {
    let token = format!("bench-{pid}-{:016x}", monotonic_ns());
    let token_file = dir.join("token");
    std::fs::write(&token_file, &token)?;
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    let http = format!("127.0.0.1:{port}");
    let mut lab = Managed::new(
        "nori-lab",
        &sibling("nori-lab")?,
        &[
            "--domain".into(),
            domain.to_string(),
            "--http".into(),
            http.clone(),
            "--token-file".into(),
            token_file.display().to_string(),
        ],
    );
    lab.log_to(&dir.join("lab.log"))?;
    lab.capture_stdout();
    lab.start()?;
    std::thread::sleep(Duration::from_millis(500));
    Ok((lab, format!("http://{http}/#token={token}")))
}

/// Opens the lab's page at `url` and, once its model is drawn, takes control of the left
/// arm with the target where the tool is.
fn open_page(chromium: &std::path::Path, url: &str, dir: &std::path::Path) -> Result<Browser> {
    let mut page = Browser::open(chromium, url, dir)?;
    let until = Instant::now() + Duration::from_secs(30);
    while page
        .eval("typeof lab !== 'undefined' && !!lab.model && lab.frames > 5")
        .ok()
        != Some(json!(true))
    {
        if Instant::now() > until {
            bail!("the page did not come up (logs in {})", dir.display());
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    // In control: the target where the tool is.
    page.eval(
        "lab.setTool('left_arm', lab.state.arms[0].points[lab.state.arms[0].points.length - 1])",
    )?;
    std::thread::sleep(Duration::from_millis(500));
    Ok(page)
}

/// The page's path: 5 mm forward, then back, by key presses, each a new target the arm's IK
/// solves.
fn page_trials(
    served: &sim::pty::ServedRobot,
    page: &mut Browser,
    trials: usize,
) -> Result<Trials> {
    let mut out = Trials::with_capacity(trials);
    for trial in 0..trials {
        let key = if trial % 2 == 0 {
            "ArrowUp"
        } else {
            "ArrowDown"
        };
        let ids = out.run(served, |_| Ok(page.send_key(key)?))?;
        for id in ids {
            page.answer(id, "Input.dispatchKeyEvent")?;
        }
    }
    Ok(out)
}

/// Runs `nori bench lab-latency`.
pub fn run(args: &LabLatencyArgs) -> Result<()> {
    let chromium = chromium().context("no chromium: deploy/install-build-deps.sh installs it")?;
    let pid = std::process::id();
    let dir = std::env::temp_dir().join(format!("nori-bench-lab-{pid}"));
    std::fs::create_dir_all(&dir)?;
    let domain = format!("nori_bench_lab_{pid}");
    let robot = RobotDescription::nori_a3();
    let bus = robot.bus(BUS).context("no left_arm bus")?;
    let served = sim::pty::serve(vec![(SimBus::new(&robot, bus), dir.join(BUS))], 0.001)?;
    let trips = dir.join("trips");
    let run = Run {
        domain: &domain,
        device_dir: &dir,
        trips: Some(&trips),
        quiet: true,
    };
    let [mut supervisor, mut driver] = supervisor_and_driver(&run, BUS)?;
    supervisor.log_to(&dir.join("supervisor.log"))?;
    supervisor.start()?;
    driver.log_to(&dir.join("driver.log"))?;
    driver.start()?;
    let node = Plane::open(&domain, &format!("bench-lab-{pid}"))?;
    let states = node.subscriber(&plane::JOINT_STATE)?;
    let goals = node.publisher(&plane::GOALS)?;
    let layouts = node.subscriber(&plane::LAYOUT)?;
    let layout = wait_for_arm(&states, &layouts, &dir)?;
    let elbow = layout.joint_index("left_elbow").context("no left_elbow")?;
    let rate_without = driver_rate(&states, 3.0)?;
    let mut plane_trials = plane_trials(&served, &states, &goals, &layout, elbow, args.trials)?;
    drop(goals);

    // The lab and its page, in control of the left arm.
    let (mut lab, url) = start_lab(&domain, &dir, pid)?;
    let mut page = open_page(&chromium, &url, &dir)?;
    let rate_started = (wait_state(&states)?.seq, Instant::now());
    let mut page_trials = page_trials(&served, &mut page, args.trials)?;
    let missed = plane_trials.missed + page_trials.missed;
    let last = wait_state(&states)?.seq;
    let rate_with = (last - rate_started.0) as f64 / rate_started.1.elapsed().as_secs_f64();
    let refused = page.eval("lab.replies.filter(r => !r.ok).map(r => r.error)")?;
    let lab_rss = lab.pid().and_then(bench::peak_rss_mb);
    drop(page);
    let lab_out = lab
        .stop(Duration::from_secs(5))
        .map(|s| s.stdout)
        .unwrap_or_default();
    drop((states, layouts, node));
    for m in [&mut driver, &mut supervisor] {
        m.stop(Duration::from_secs(3));
    }
    drop(served.stop());
    telemetry::plane::Plane::remove_unused_domain(&domain)?;

    let (page_ms, plane_ms) = (&mut page_trials.ms, &mut plane_trials.ms);
    let (l50, l99) = summary(page_ms);
    let (p50, p99) = summary(plane_ms);
    let out = json!({
        "trials_per_path": args.trials,
        "no_goal_within_500ms": missed,
        "page_key_to_wire_ms": {"p50": l50, "p99": l99, "max": page_ms.last()},
        "baseline_state_plane_ms": {"p50": p50, "p99": p99, "max": plane_ms.last()},
        "ratio_p50": l50 / p50,
        "ratio_p99": l99 / p99,
        "driver_rate_hz": {"without_lab": rate_without, "with_lab_in_control": rate_with, "ratio": rate_with / rate_without},
        "lab_peak_rss_mb": lab_rss,
        "page_refusals": refused,
        "lab": serde_json::from_str::<serde_json::Value>(lab_out.trim()).unwrap_or(json!(lab_out)),
    });
    if args.json {
        println!("{out}");
    } else {
        println!(
            "key press in the lab's page → goal on the simulated wire, {} trials a path:\n  page (Chromium → WebSocket → nori-lab IK → plane → driver) p50 {l50:.2} ms, p99 {l99:.2} ms\n  baseline (goal straight on the state plane)               p50 {p50:.2} ms, p99 {p99:.2} ms\n  ratio p50 {:.2}, p99 {:.2}; {missed} trials without a goal in 500 ms\n  driver loop {rate_without:.1} Hz without the lab, {rate_with:.1} Hz with it in control (ratio {:.3})\n  nori-lab peak RSS {}",
            args.trials,
            l50 / p50,
            l99 / p99,
            rate_with / rate_without,
            lab_rss.map_or("?".into(), |v| format!("{v:.1} MB"))
        );
    }
    if missed > 0 {
        bail!(
            "{missed} trials never reached the wire (logs in {})",
            dir.display()
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}
