//! The robot's lidar load for the benchmarks: `nori-lidar`, as deployed, reading the simulated
//! RPLIDAR C1 (5000 measurements a second) on a pseudo-terminal. Between measurements the
//! device is unplugged: the process then only waits to open it again, as an idle sensor.

use anyhow::{Context, Result};
use sim::lidar::{serve, LidarDevice, LidarFaults, ServedLidar};
use sim::RobotDescription;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::Duration;
use telemetry::plane::{newest, Plane, LIDAR_SCAN};

/// The lidar at work: its process and the simulated device it reads.
pub struct LidarLoad {
    child: Child,
    device: ServedLidar,
    dir: PathBuf,
}

impl LidarLoad {
    /// Starts the simulated lidar and `nori-lidar` on plane `domain`, unplugged until
    /// [`LidarLoad::feed`].
    pub fn start(domain: &str) -> Result<Self> {
        let robot = RobotDescription::nori_a3();
        let device = LidarDevice::new(&robot, LidarFaults::default())
            .context("the A3's description has no lidar")?;
        let dir = std::env::temp_dir().join(format!("nori-bench-lidar-{}", std::process::id()));
        std::fs::create_dir_all(&dir)?;
        let device = serve(device, dir.join("lidar"))?;
        let child = Command::new(stack::sibling("nori-lidar")?)
            .arg("--device-dir")
            .arg(&dir)
            .args(["--domain", domain])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .context("starting nori-lidar")?;
        // Let it open the device and read the device's identity before unplugging it.
        std::thread::sleep(Duration::from_millis(500));
        device.set_plugged(false);
        Ok(LidarLoad { child, device, dir })
    }

    /// Plugs the device in (the process opens it again within a second and scans) or out.
    pub fn feed(&self, on: bool) {
        self.device.set_plugged(on);
    }

    /// How long [`LidarLoad::feed`] takes to bring scans back: the process's reopen period
    /// and the device's spin-up.
    pub const SETTLE: Duration = Duration::from_millis(1500);

    /// CPU time the process has used so far, s.
    pub fn cpu_seconds(&self) -> f64 {
        bench::cpu_seconds(self.child.id()).unwrap_or(0.0)
    }

    /// Peak resident set of the process so far, MB.
    pub fn peak_rss_mb(&self) -> f64 {
        bench::peak_rss_mb(self.child.id()).unwrap_or(0.0)
    }
}

impl Drop for LidarLoad {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// Revolutions the lidar process published so far (the newest scan's sequence number + 1).
pub fn scans_published(domain: &str) -> u64 {
    let Ok(node) = Plane::open(domain, "bench-lidar-counter") else {
        return 0;
    };
    let Ok(sub) = node.subscriber(&LIDAR_SCAN) else {
        return 0;
    };
    std::thread::sleep(Duration::from_millis(300));
    newest(&sub).map_or(0, |s| s.seq + 1)
}
