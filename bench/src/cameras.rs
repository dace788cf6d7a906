//! The robot's camera load for the benchmarks: `nori-camera` processes, as deployed, fed by
//! camera sockets that stream a pre-encoded MJPEG picture of the simulated A3 at the camera's
//! rate. The picture is rendered and encoded once, before anything is timed: what is measured is
//! the robot's cost (reading, decoding, publishing on the plane), not the simulator's rendering.

use anyhow::{bail, Context, Result};
use camera::stream::StreamHeader;
use sim::camera::Scene;
use sim::RobotDescription;
use std::io::Write;
use std::os::unix::net::UnixListener;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::sensors::PixelFormat;

/// Cameras at work: their processes and the sockets feeding them.
pub struct CameraLoad {
    children: Vec<Child>,
    feeders: Vec<JoinHandle<()>>,
    feeding: Arc<AtomicBool>,
    stop: Arc<AtomicBool>,
    dir: PathBuf,
    /// Bytes of each camera's JPEG.
    pub jpeg_bytes: Vec<usize>,
}

impl CameraLoad {
    /// Starts the first `count` cameras of the A3 at `width`×`height`, `fps`, on plane `domain`;
    /// frames flow only while [`CameraLoad::feed`] is on.
    pub fn start(count: usize, width: u32, height: u32, fps: u32, domain: &str) -> Result<Self> {
        let mut robot = RobotDescription::nori_a3();
        if count > robot.camera.len() {
            bail!("the A3 has {} cameras", robot.camera.len());
        }
        robot.camera.truncate(count);
        for c in &mut robot.camera {
            (c.width, c.height, c.fps) = (width, height, fps);
        }
        let dir = std::env::temp_dir().join(format!("nori-bench-cameras-{}", std::process::id()));
        std::fs::create_dir_all(&dir)?;
        let config = dir.join("camera.toml");
        std::fs::write(&config, camera_config(&robot))?;
        let (feeding, stop) = (
            Arc::new(AtomicBool::new(false)),
            Arc::new(AtomicBool::new(false)),
        );
        let mut load = CameraLoad {
            children: Vec::new(),
            feeders: Vec::new(),
            feeding: feeding.clone(),
            stop: stop.clone(),
            dir: dir.clone(),
            jpeg_bytes: Vec::new(),
        };
        let mut scene = Scene::new(&robot);
        let buses: Vec<sim::SimBus> = robot
            .bus
            .iter()
            .map(|b| sim::SimBus::new(&robot, b))
            .collect();
        scene.pose(&buses);
        let program = stack::sibling("nori-camera")?;
        for cam in &robot.camera {
            let mut rgb = vec![0u8; camera::convert::rgb_len(width, height)];
            scene.render(cam, &mut rgb);
            let mut jpeg = Vec::new();
            jpeg_encoder::Encoder::new(&mut jpeg, 85)
                .encode(
                    &rgb,
                    width as u16,
                    height as u16,
                    jpeg_encoder::ColorType::Rgb,
                )
                .context("encoding the camera picture")?;
            load.jpeg_bytes.push(jpeg.len());
            let socket = dir.join(format!("camera-{}", cam.name));
            let _ = std::fs::remove_file(&socket);
            let listener = UnixListener::bind(&socket)?;
            let (feeding, stop) = (feeding.clone(), stop.clone());
            load.feeders.push(std::thread::spawn(move || {
                feed(&listener, &jpeg, width, height, fps, &feeding, &stop)
            }));
            load.children.push(
                Command::new(&program)
                    .args(["--camera", &cam.name, "--config"])
                    .arg(&config)
                    .arg("--device-dir")
                    .arg(&dir)
                    .args(["--domain", domain])
                    .stdout(Stdio::null())
                    .stderr(Stdio::null())
                    .spawn()
                    .context("starting nori-camera")?,
            );
        }
        Ok(load)
    }

    /// Starts or stops the frames.
    pub fn feed(&self, on: bool) {
        self.feeding.store(on, Ordering::SeqCst);
    }

    /// CPU time the camera processes have used so far, s (user + system).
    pub fn cpu_seconds(&self) -> f64 {
        self.children
            .iter()
            .filter_map(|c| bench::cpu_seconds(c.id()))
            .sum()
    }

    /// Peak resident set of each camera process so far, MB.
    pub fn peak_rss_mb(&self) -> Vec<f64> {
        self.children
            .iter()
            .map(|c| bench::peak_rss_mb(c.id()).unwrap_or(0.0))
            .collect()
    }
}

impl Drop for CameraLoad {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        for c in &mut self.children {
            let _ = c.kill();
            let _ = c.wait();
        }
        for f in self.feeders.drain(..) {
            let _ = f.join();
        }
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// The cameras' configuration: the shipped file's cameras, at the robot's size and rate.
fn camera_config(robot: &RobotDescription) -> String {
    robot
        .camera
        .iter()
        .map(|c| {
            format!(
                "[[camera]]\nname = \"{}\"\ndevice = \"/dev/nori/camera-{}\"\nformat = \"mjpeg\"\n\
                 width = {}\nheight = {}\nfps = {}\n\n",
                c.name, c.name, c.width, c.height, c.fps
            )
        })
        .collect()
}

/// Streams `jpeg` to whoever connects, at `fps` while `feeding`.
fn feed(
    listener: &UnixListener,
    jpeg: &[u8],
    width: u32,
    height: u32,
    fps: u32,
    feeding: &AtomicBool,
    stop: &AtomicBool,
) {
    let _ = listener.set_nonblocking(true);
    let period = Duration::from_secs_f64(1.0 / f64::from(fps));
    let mut reader = None;
    let mut sequence = 0u32;
    let mut next = Instant::now();
    while !stop.load(Ordering::SeqCst) {
        if let Ok((s, _)) = listener.accept() {
            let _ = s.set_nonblocking(false);
            reader = Some(s);
        }
        let now = Instant::now();
        if now < next {
            std::thread::sleep((next - now).min(Duration::from_millis(10)));
            continue;
        }
        next = (next + period).max(now);
        let (Some(out), true) = (reader.as_mut(), feeding.load(Ordering::SeqCst)) else {
            continue;
        };
        let header = StreamHeader {
            fourcc: PixelFormat::Mjpeg.fourcc(),
            width,
            height,
            sequence,
            len: jpeg.len() as u32,
            capture_ns: monotonic_ns(),
        };
        sequence = sequence.wrapping_add(1);
        if out
            .write_all(&header.encode())
            .and_then(|()| out.write_all(jpeg))
            .is_err()
        {
            reader = None;
        }
    }
}
