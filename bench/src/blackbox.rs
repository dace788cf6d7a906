//! The black box's load for `nori bench driver-rate --blackbox`: the driver as deployed (its
//! wire tapped, its state and wire frames published on the plane), with `nori-blackbox record`
//! recording and a box being frozen in every other half, and no recorder in the rest.

use anyhow::{Context, Result};
use bus_driver::LoopIo;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use telemetry::plane::{self, Plane, Pub};
use telemetry::wire::{BlackboxSave, WireFrame};
use telemetry::JointState;

/// The driver's side of the plane in the benchmark: what the deployed driver publishes every
/// cycle (its state, and each bus's wire frame).
pub struct PlaneIo {
    state: Pub<JointState>,
    wire: Pub<WireFrame>,
    _node: Plane,
}

impl PlaneIo {
    /// Joins `domain` as the driver would.
    pub fn open(domain: &str) -> Result<PlaneIo> {
        let node = Plane::open(domain, "bench-driver")?;
        Ok(PlaneIo {
            state: node.publisher(&plane::JOINT_STATE)?,
            wire: node.publisher(&plane::BUS_WIRE)?,
            _node: node,
        })
    }
}

impl LoopIo for PlaneIo {
    fn goals(&mut self) -> Option<telemetry::GoalFrame> {
        None
    }
    fn directives(&mut self) -> Option<telemetry::frames::Directives> {
        None
    }
    fn supervisor_heartbeat(&mut self) -> Option<telemetry::frames::Heartbeat> {
        None
    }
    fn publish(&mut self, state: &JointState) {
        let _ = plane::publish(&self.state, state);
    }
    fn publish_wire(&mut self, wire: &WireFrame) {
        let _ = plane::publish(&self.wire, wire);
    }
}

/// The recorder, started for a variant half and stopped after it.
pub struct BlackboxLoad {
    domain: String,
    /// Kept while the recorder runs: a sample outlives its publisher only until it is read.
    save: Pub<BlackboxSave>,
    _node: Plane,
    dir: PathBuf,
    child: Option<Child>,
    /// CPU time of the recorders stopped so far, s.
    cpu_s: f64,
    /// The largest peak resident set of any of them, MB.
    peak_rss_mb: f64,
    /// Time they recorded, s.
    recording_s: f64,
    started: Option<Instant>,
}

impl BlackboxLoad {
    /// A load on `domain`, its boxes in a scratch directory.
    pub fn new(domain: &str) -> Result<BlackboxLoad> {
        let dir = std::env::temp_dir().join(format!("nori-bench-blackbox-{}", std::process::id()));
        std::fs::create_dir_all(&dir)?;
        let node = Plane::open(domain, "bench-blackbox-save")?;
        Ok(BlackboxLoad {
            domain: domain.into(),
            save: node.publisher(&plane::BLACKBOX_SAVE)?,
            _node: node,
            dir,
            child: None,
            cpu_s: 0.0,
            peak_rss_mb: 0.0,
            recording_s: 0.0,
            started: None,
        })
    }

    /// Starts the recorder and asks it to freeze a box (the half then runs with a box being
    /// written), or stops it.
    pub fn feed(&mut self, on: bool) -> Result<()> {
        if on {
            let log = self.dir.join("recorder.log");
            let child = Command::new(stack::sibling("nori-blackbox")?)
                .args(["record", "--domain", &self.domain, "--dir"])
                .arg(self.dir.join("boxes"))
                .stdout(Stdio::null())
                .stderr(std::fs::File::create(&log)?)
                .spawn()
                .context("starting nori-blackbox")?;
            self.child = Some(child);
            // Its subscriptions open before it says it records: a save asked earlier is lost.
            let until = Instant::now() + Duration::from_secs(10);
            while !std::fs::read_to_string(&log)?.contains("recording the last minutes") {
                anyhow::ensure!(
                    Instant::now() < until,
                    "nori-blackbox did not start recording"
                );
                std::thread::sleep(Duration::from_millis(10));
            }
            self.started = Some(Instant::now());
            return Ok(());
        }
        if let Some(mut child) = self.child.take() {
            self.cpu_s += bench::cpu_seconds(child.id()).unwrap_or(0.0);
            self.peak_rss_mb = self
                .peak_rss_mb
                .max(bench::peak_rss_mb(child.id()).unwrap_or(0.0));
            self.recording_s += self
                .started
                .take()
                .map_or(0.0, |t| t.elapsed().as_secs_f64());
            let _ = nix::sys::signal::kill(
                nix::unistd::Pid::from_raw(child.id() as i32),
                nix::sys::signal::Signal::SIGTERM,
            );
            let _ = child.wait();
        }
        Ok(())
    }

    /// Asks the running recorder to freeze a box now (as `nori blackbox save`).
    pub fn save(&self) -> Result<()> {
        plane::publish(
            &self.save,
            &BlackboxSave {
                seq: 1,
                timestamp_ns: telemetry::clock::monotonic_ns(),
                pid: std::process::id(),
                reserved: 0,
            },
        )?;
        Ok(())
    }

    /// The recorder's figures: CPU, peak memory, and the boxes it wrote.
    pub fn figures(&self) -> serde_json::Value {
        let boxes: Vec<u64> = std::fs::read_dir(self.dir.join("boxes"))
            .into_iter()
            .flatten()
            .flatten()
            .filter_map(|e| e.metadata().ok().map(|m| m.len()))
            .collect();
        serde_json::json!({
            "recording_seconds": self.recording_s,
            "cpu_percent_of_a_core": 100.0 * self.cpu_s / self.recording_s.max(1e-9),
            "peak_rss_mb": self.peak_rss_mb,
            "boxes": boxes.len(),
            "box_bytes": boxes,
        })
    }
}

impl Drop for BlackboxLoad {
    fn drop(&mut self) {
        let _ = self.feed(false);
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}
