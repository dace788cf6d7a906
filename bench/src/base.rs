//! The base controller's load for the benchmarks: `nori-base`, as deployed, on the bench's
//! plane, fed what the robot would feed it: a driver's layout with the two wheels, their
//! readings at 200 Hz, the lidar's revolutions at 10 Hz and a velocity command every 50 ms
//! (while driving). Idle, it hears nothing (no layout yet: it waits, as before a driver).

use anyhow::{Context, Result};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;
use telemetry::clock::monotonic_ns;
use telemetry::frames::JointLayout;
use telemetry::motion::BaseCommand;
use telemetry::plane::{self, Plane};
use telemetry::sensors::LidarScan;
use telemetry::JointState;

/// `nori-base` and the stand-in that feeds it.
pub struct BaseLoad {
    child: Child,
    driving: Arc<AtomicBool>,
    stop: Arc<AtomicBool>,
    goals: Arc<AtomicU64>,
    feeder: Option<JoinHandle<()>>,
}

impl BaseLoad {
    /// Starts `nori-base` on plane `domain`, idle until [`BaseLoad::feed`].
    pub fn start(domain: &str) -> Result<Self> {
        let child = Command::new(stack::sibling("nori-base")?)
            .args(["--domain", domain])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .context("starting nori-base")?;
        let (driving, stop, goals) = (
            Arc::new(AtomicBool::new(false)),
            Arc::new(AtomicBool::new(false)),
            Arc::new(AtomicU64::new(0)),
        );
        let feeder = {
            let (domain, driving, stop, goals) = (
                domain.to_string(),
                driving.clone(),
                stop.clone(),
                goals.clone(),
            );
            std::thread::spawn(move || {
                if let Err(e) = feed(&domain, &driving, &stop, &goals) {
                    eprintln!("bench: the base's stand-in driver failed: {e}");
                }
            })
        };
        Ok(BaseLoad {
            child,
            driving,
            stop,
            goals,
            feeder: Some(feeder),
        })
    }

    /// Drives the base (layout, wheel readings, scans and commands flow) or leaves it idle.
    pub fn feed(&self, on: bool) {
        self.driving.store(on, Ordering::SeqCst);
    }

    /// Wheel goal frames the controller sent so far.
    pub fn goals_sent(&self) -> u64 {
        self.goals.load(Ordering::SeqCst)
    }

    /// CPU time the process has used so far, s.
    pub fn cpu_seconds(&self) -> f64 {
        bench::cpu_seconds(self.child.id()).unwrap_or(0.0)
    }

    /// Peak resident set of the process so far, MB.
    pub fn peak_rss_mb(&self) -> f64 {
        bench::peak_rss_mb(self.child.id()).unwrap_or(0.0)
    }
}

impl Drop for BaseLoad {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(f) = self.feeder.take() {
            let _ = f.join();
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The stand-in driver, lidar and operator: 200 Hz joint states of two turning wheels, a
/// revolution every 100 ms, a command every 50 ms, while `driving`; counts the goals back.
fn feed(domain: &str, driving: &AtomicBool, stop: &AtomicBool, goals: &AtomicU64) -> Result<()> {
    let node = Plane::open(domain, "bench-base-feeder")?;
    let layouts = node.publisher(&plane::LAYOUT)?;
    let states = node.publisher(&plane::JOINT_STATE)?;
    let scans = node.publisher(&plane::LIDAR_SCAN)?;
    let commands = node.publisher(&plane::BASE_COMMAND)?;
    let goal_sub = node.subscriber(&plane::WHEEL_GOALS)?;
    let mut layout = JointLayout {
        joint_count: 2,
        bus_count: 1,
        ..JointLayout::default()
    };
    layout.set_bus_name(0, "base");
    for (j, name) in ["left_wheel", "right_wheel"].iter().enumerate() {
        layout.joints[j].name[..name.len()].copy_from_slice(name.as_bytes());
    }
    let mut scan = LidarScan {
        point_count: 500,
        ..LidarScan::default()
    };
    // A room 3 m around, and a wall 0.3 m ahead of the lidar (0.2 m beyond the body's front,
    // inside the circle its corners sweep): the protective field's costliest case, every
    // return of the wall turned around the base a degree at a time by the turn guard.
    for (k, p) in scan.points.iter_mut().take(500).enumerate() {
        p.angle_rad = k as f32 * std::f32::consts::TAU / 500.0;
        let ahead = p.angle_rad.cos();
        p.range_m = if ahead > 0.5 {
            (0.3 / ahead).min(3.0)
        } else {
            3.0
        };
        p.quality = 40;
    }
    let mut tick = 0u64;
    let mut angle = 0.0f32;
    while !stop.load(Ordering::SeqCst) {
        std::thread::sleep(Duration::from_millis(5));
        while plane::next(&goal_sub).is_some() {
            goals.fetch_add(1, Ordering::SeqCst);
        }
        if !driving.load(Ordering::SeqCst) {
            continue;
        }
        tick += 1;
        let now = monotonic_ns();
        if tick % 200 == 1 {
            plane::publish(&layouts, &layout)?;
        }
        angle = (angle + 2.0 * 0.005) % std::f32::consts::TAU;
        let mut s = JointState {
            seq: tick,
            timestamp_ns: now,
            joint_count: 2,
            ..JointState::default()
        };
        for (j, sign) in [(0, 1.0), (1, -1.0)] {
            let w = &mut s.joints[j];
            (w.valid, w.torque_enabled) = (1, 1);
            w.position_rad = (sign * angle).rem_euclid(std::f32::consts::TAU);
            w.velocity_rad_s = sign * 2.0;
        }
        plane::publish(&states, &s)?;
        if tick.is_multiple_of(20) {
            scan.seq += 1;
            (scan.start_ns, scan.end_ns) = (now - 100_000_000, now);
            plane::publish(&scans, &scan)?;
        }
        if tick.is_multiple_of(10) {
            let c = BaseCommand {
                seq: tick,
                timestamp_ns: now,
                linear_m_s: 0.15,
                angular_rad_s: 0.3,
            };
            plane::publish(&commands, &c)?;
        }
    }
    Ok(())
}
