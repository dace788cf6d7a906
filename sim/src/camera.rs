//! The simulated cameras: each renders the simulated robot and its room from where it is
//! mounted, at its rate, and streams the frames in its device format (YUYV or MJPEG) on a Unix
//! socket at `<device dir>/camera-<name>`, framed as `camera::stream` says: what `nori-camera`
//! reads in place of a V4L2 device. A wrist camera moves with its arm's tip.

use crate::arm::Arm;
use crate::bus::SimBus;
use crate::description::{CameraDescription, RobotDescription, SceneObject};
use crate::render::{render, Item, Shape, View};
use crate::rng::Rng;
use camera::convert::rgb_to_yuyv;
use camera::mode::{check, format_named};
use camera::stream::StreamHeader;
use nalgebra::{Matrix3, Vector3};
use std::io::Write;
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use telemetry::sensors::PixelFormat;
use thiserror::Error;

/// A camera description that cannot be served.
#[derive(Debug, Error)]
#[allow(missing_docs, reason = "each field is shown in its variant's message")]
pub enum CameraError {
    /// A value that cannot be right.
    #[error("camera {camera}: {reason}")]
    Invalid { camera: String, reason: String },
    /// Its socket could not be made.
    #[error("camera {camera}: socket {path}: {source}")]
    Socket {
        camera: String,
        path: PathBuf,
        source: std::io::Error,
    },
}

/// Link and finger thickness, m.
const LINK_RADIUS: f64 = 0.025;
const FINGER_RADIUS: f64 = 0.01;
const FINGER_LENGTH: f64 = 0.06;

/// One arm as the cameras see it.
struct ArmView {
    bus: String,
    arm: Arm,
    q: Vec<f64>,
    gripper: Option<f64>,
    points: Vec<[f64; 3]>,
    tip_rotation: Matrix3<f64>,
}

/// The room and the robot's arms, posed from the simulated servos.
pub struct Scene {
    arms: Vec<ArmView>,
    fixed: Vec<Item>,
    items: Vec<Item>,
}

impl Scene {
    /// The scene of `robot`: its arms (posed by [`Scene::pose`]), its body and objects.
    pub fn new(robot: &RobotDescription) -> Self {
        let arms = robot
            .bus
            .iter()
            .filter_map(|b| {
                let d = b.arm.as_ref()?;
                Some(ArmView {
                    bus: b.name.clone(),
                    arm: Arm::new(d, robot.gravity),
                    q: vec![0.0; d.joint.len()],
                    gripper: d.gripper.as_ref().map(|_| 0.0),
                    points: Vec::new(),
                    tip_rotation: Matrix3::identity(),
                })
            })
            .collect();
        let mut fixed = vec![Item {
            // The column carrying the shoulders.
            shape: Shape::Capsule {
                a: [-0.08, 0.0, 0.15],
                b: [-0.08, 0.0, 1.05],
                radius: 0.1,
            },
            colour: [60, 60, 70],
        }];
        fixed.extend(robot.object.iter().filter_map(object_item));
        Scene {
            arms,
            fixed,
            items: Vec::new(),
        }
    }

    /// Takes the arms' joint angles from the simulated buses.
    pub fn pose(&mut self, buses: &[SimBus]) {
        for view in &mut self.arms {
            if let Some(bus) = buses.iter().find(|b| b.name == view.bus) {
                if let Some(gripper) = bus.arm_angles(&mut view.q) {
                    view.gripper = gripper;
                }
            }
            view.tip_rotation = view.arm.chain(&view.q, &mut view.points);
        }
        self.refresh_items();
    }

    /// Poses arm `bus` at `q` (its joints in the arm's order, the gripper as it was) without
    /// redrawing: what a camera on it sees is [`Scene::view`]. Returns the tool point, world
    /// frame (the origin for a bus without an arm).
    pub fn pose_arm(&mut self, bus: &str, q: &[f64]) -> [f64; 3] {
        let Some(view) = self.arms.iter_mut().find(|a| a.bus == bus) else {
            return [0.0; 3];
        };
        view.q.clear();
        view.q.extend_from_slice(q);
        view.tip_rotation = view.arm.chain(&view.q, &mut view.points);
        view.points.last().copied().unwrap_or([0.0; 3])
    }

    /// Rebuilds what is drawn from the arms as last posed.
    pub fn refresh_items(&mut self) {
        self.items.clear();
        self.items.extend_from_slice(&self.fixed);
        for view in &self.arms {
            for pair in view.points.windows(2) {
                self.items.push(Item {
                    shape: Shape::Capsule {
                        a: pair[0],
                        b: pair[1],
                        radius: LINK_RADIUS,
                    },
                    colour: [215, 215, 220],
                });
            }
            let Some((&tip, opening)) = view.points.last().zip(view.gripper) else {
                continue;
            };
            // Two fingers from the tool point along the tip's −z, spread by the gripper angle.
            let r = view.tip_rotation;
            let tip = Vector3::from(tip);
            for side in [-1.0, 1.0] {
                let spread = side * (0.01 + 0.03 * opening.clamp(0.0, 1.5));
                let end = tip + r * Vector3::new(spread, 0.0, -FINGER_LENGTH);
                let base = tip + r * Vector3::new(side * 0.01, 0.0, 0.0);
                self.items.push(Item {
                    shape: Shape::Capsule {
                        a: base.into(),
                        b: end.into(),
                        radius: FINGER_RADIUS,
                    },
                    colour: [40, 40, 45],
                });
            }
        }
    }

    /// Where `camera` is and what it looks at, with the arms as last posed.
    pub fn view(&self, camera: &CameraDescription) -> View {
        let fov = camera.fov_deg.to_radians();
        let Some(arm) = self.arms.iter().find(|a| a.bus == camera.mount) else {
            return View::looking_at(
                camera.position,
                camera.look,
                fov,
                camera.width,
                camera.height,
            );
        };
        let r = arm.tip_rotation;
        let tip = arm
            .points
            .last()
            .copied()
            .map_or(Vector3::zeros(), Vector3::from);
        let eye = tip + r * Vector3::from(camera.position);
        let target = eye + r * Vector3::from(camera.look);
        View::looking_at(eye.into(), target.into(), fov, camera.width, camera.height)
    }

    /// Renders `camera`'s picture into `out` (RGB24).
    pub fn render(&self, camera: &CameraDescription, out: &mut [u8]) {
        render(&self.items, &self.view(camera), out);
    }
}

fn object_item(o: &SceneObject) -> Option<Item> {
    let shape = match (o.center, o.radius_m, o.min, o.max) {
        (Some(center), Some(radius), None, None) => Shape::Sphere { center, radius },
        (None, None, Some(min), Some(max)) => Shape::Cuboid { min, max },
        _ => return None,
    };
    Some(Item {
        shape,
        colour: o.colour,
    })
}

/// Checks the cameras and objects of `robot`.
pub fn validate(robot: &RobotDescription) -> Result<(), CameraError> {
    for c in &robot.camera {
        let bad = |reason: String| CameraError::Invalid {
            camera: c.name.clone(),
            reason,
        };
        format_named(&c.format)
            .ok_or_else(|| bad(format!("format {:?}: yuyv or mjpeg", c.format)))?;
        if c.mount != "body"
            && !robot
                .bus
                .iter()
                .any(|b| b.name == c.mount && b.arm.is_some())
        {
            return Err(bad(format!(
                "mount {:?}: \"body\" or a bus with an arm",
                c.mount
            )));
        }
        check(c.width, c.height, c.fps).map_err(|(_, reason)| bad(reason))?;
        if !(10.0..=170.0).contains(&c.fov_deg) {
            return Err(bad(format!("fov {}°: 10 to 170", c.fov_deg)));
        }
    }
    for o in &robot.object {
        if object_item(o).is_none() {
            return Err(CameraError::Invalid {
                camera: format!("object {}", o.name),
                reason: "a ball (center, radius-m) or a box (min, max)".into(),
            });
        }
    }
    Ok(())
}

/// Camera faults: a probability per frame that its JPEG is cut short (a USB packet lost), and
/// that its bytes are replaced by garbage of the same length.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct CameraFaults {
    /// Probability per MJPEG frame of a truncated JPEG.
    pub truncate_rate: f64,
    /// Probability per frame of garbage bytes.
    pub garbage_rate: f64,
    /// Seed of the frame faults (each camera adds its index).
    pub seed: u64,
}

/// The cameras being served; dropping it stops them and removes their sockets.
pub struct ServedCameras {
    stop: Arc<AtomicBool>,
    threads: Vec<JoinHandle<()>>,
    /// Socket of each camera.
    pub sockets: Vec<PathBuf>,
}

impl Drop for ServedCameras {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
        for s in &self.sockets {
            let _ = std::fs::remove_file(s);
        }
    }
}

/// Serves every camera of `robot` from `dir`, posed from `buses`.
pub fn serve(
    robot: &RobotDescription,
    buses: Arc<Mutex<Vec<SimBus>>>,
    dir: &Path,
    faults: CameraFaults,
) -> Result<ServedCameras, CameraError> {
    validate(robot)?;
    let stop = Arc::new(AtomicBool::new(false));
    let mut served = ServedCameras {
        stop: stop.clone(),
        threads: Vec::new(),
        sockets: Vec::new(),
    };
    for (i, cam) in robot.camera.iter().enumerate() {
        let path = dir.join(format!("camera-{}", cam.name));
        let _ = std::fs::remove_file(&path);
        let listener = UnixListener::bind(&path)
            .and_then(|l| l.set_nonblocking(true).map(|()| l))
            .map_err(|source| CameraError::Socket {
                camera: cam.name.clone(),
                path: path.clone(),
                source,
            })?;
        served.sockets.push(path);
        let mut stream = CameraStream {
            camera: cam.clone(),
            format: format_named(&cam.format).unwrap_or(PixelFormat::Yuyv),
            scene: Scene::new(robot),
            faults: Rng::new(faults.seed.wrapping_add(i as u64)),
            fault_rates: faults,
        };
        let (stop, buses) = (stop.clone(), buses.clone());
        served.threads.push(std::thread::spawn(move || {
            stream.run(&listener, &buses, &stop)
        }));
    }
    Ok(served)
}

struct CameraStream {
    camera: CameraDescription,
    format: PixelFormat,
    scene: Scene,
    faults: Rng,
    fault_rates: CameraFaults,
}

impl CameraStream {
    /// Renders at the camera's rate while a reader is connected (a camera streams only once
    /// opened), one reader at a time; a reader that goes away is replaced by the next.
    fn run(&mut self, listener: &UnixListener, buses: &Mutex<Vec<SimBus>>, stop: &AtomicBool) {
        let c = &self.camera;
        let period = Duration::from_secs_f64(1.0 / f64::from(c.fps));
        let mut rgb = vec![0u8; c.width as usize * c.height as usize * 3];
        let mut payload = Vec::with_capacity(rgb.len());
        let mut reader: Option<UnixStream> = None;
        let mut sequence = 0u32;
        let mut next = Instant::now();
        while !stop.load(Ordering::Relaxed) {
            if let Ok((s, _)) = listener.accept() {
                // The newest reader wins (a restarted camera process).
                if s.set_nonblocking(false).is_ok()
                    && s.set_write_timeout(Some(Duration::from_secs(1))).is_ok()
                {
                    reader = Some(s);
                    sequence = 0;
                }
            }
            let now = Instant::now();
            if now < next {
                std::thread::sleep((next - now).min(Duration::from_millis(20)));
                continue;
            }
            next += period;
            if next < now {
                next = now + period;
            }
            let Some(out) = reader.as_mut() else { continue };
            let capture_ns = telemetry::clock::monotonic_ns();
            if let Ok(b) = buses.lock() {
                self.scene.pose(&b);
            }
            self.scene.render(&self.camera, &mut rgb);
            self.encode(&rgb, &mut payload);
            let header = StreamHeader {
                fourcc: self.format.fourcc(),
                width: self.camera.width,
                height: self.camera.height,
                sequence,
                len: payload.len() as u32,
                capture_ns,
            };
            sequence = sequence.wrapping_add(1);
            if out
                .write_all(&header.encode())
                .and_then(|()| out.write_all(&payload))
                .is_err()
            {
                reader = None;
            }
        }
    }

    fn encode(&mut self, rgb: &[u8], payload: &mut Vec<u8>) {
        let (w, h) = (self.camera.width, self.camera.height);
        payload.clear();
        match self.format {
            PixelFormat::Mjpeg => {
                let encoder = jpeg_encoder::Encoder::new(&mut *payload, 85);
                if encoder
                    .encode(rgb, w as u16, h as u16, jpeg_encoder::ColorType::Rgb)
                    .is_err()
                {
                    payload.clear();
                }
                if self.faults.chance(self.fault_rates.truncate_rate) {
                    payload.truncate(payload.len() / 2);
                }
            }
            _ => {
                payload.resize(w as usize * h as usize * 2, 0);
                rgb_to_yuyv(rgb, payload);
            }
        }
        if self.faults.chance(self.fault_rates.garbage_rate) {
            for b in payload.iter_mut() {
                *b = self.faults.below(256) as u8;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn a3() -> RobotDescription {
        RobotDescription::nori_a3()
    }

    #[test]
    fn the_a3_has_four_valid_cameras_and_a_chain_ending_at_its_tool_point() {
        let robot = a3();
        validate(&robot).unwrap();
        let names: Vec<_> = robot.camera.iter().map(|c| c.name.as_str()).collect();
        assert_eq!(names, ["head", "neck", "left_wrist", "right_wrist"]);
        let arm_d = robot.bus[0].arm.as_ref().unwrap();
        let mut arm = Arm::new(arm_d, robot.gravity);
        let q = [0.3, 0.5, -0.4, -1.1, 0.2, 0.6, -0.3];
        let mut points = Vec::new();
        arm.chain(&q, &mut points);
        let tip = arm.tip_position(&q);
        let last = points.last().unwrap();
        for k in 0..3 {
            assert!((last[k] - tip[k]).abs() < 1e-12, "{last:?} vs {tip:?}");
        }
        assert_eq!(points.len(), q.len() + 2);
    }

    #[test]
    fn the_picture_changes_when_the_arm_moves_and_the_wrist_camera_moves_with_it() {
        let mut robot = a3();
        for c in &mut robot.camera {
            (c.width, c.height) = (160, 90);
        }
        let mut buses: Vec<SimBus> = robot.bus.iter().map(|b| SimBus::new(&robot, b)).collect();
        let mut scene = Scene::new(&robot);
        let head = &robot.camera[0];
        let wrist = robot.camera.iter().find(|c| c.mount == "left_arm").unwrap();
        let picture = |scene: &Scene, cam: &CameraDescription| {
            let mut out = vec![0u8; cam.width as usize * cam.height as usize * 3];
            scene.render(cam, &mut out);
            out
        };
        scene.pose(&buses);
        let (head_before, wrist_before) = (picture(&scene, head), picture(&scene, wrist));
        let view_before = scene.view(wrist);
        // Raise the left arm forward: shoulder pitch and elbow.
        let servos = &mut buses[0].servos;
        servos[1].angle = 1.2;
        servos[3].angle = -1.2;
        scene.pose(&buses);
        let (head_after, wrist_after) = (picture(&scene, head), picture(&scene, wrist));
        let changed = |a: &[u8], b: &[u8]| {
            a.chunks_exact(3)
                .zip(b.chunks_exact(3))
                .filter(|(x, y)| x != y)
                .count()
        };
        let pixels = head.width as usize * head.height as usize;
        assert!(
            changed(&head_before, &head_after) > pixels / 100,
            "the head camera sees the arm move"
        );
        assert!(
            changed(&wrist_before, &wrist_after) > pixels / 10,
            "the wrist camera moved"
        );
        assert!((scene.view(wrist).eye - view_before.eye).norm() > 0.1);
        // The right arm did not move: a camera that sees only it would not change. Its own
        // wrist camera moves with the right tip, which stayed put.
        let right = robot
            .camera
            .iter()
            .find(|c| c.mount == "right_arm")
            .unwrap();
        let eye_right = scene.view(right).eye;
        scene.pose(&buses);
        assert_eq!(scene.view(right).eye, eye_right);
    }

    #[test]
    fn a_bad_camera_description_is_refused() {
        let mut robot = a3();
        robot.camera[0].format = "h264".into();
        assert!(validate(&robot).unwrap_err().to_string().contains("format"));
        let mut robot = a3();
        robot.camera[1].mount = "wheels".into();
        assert!(validate(&robot).unwrap_err().to_string().contains("mount"));
        let mut robot = a3();
        robot.camera[2].width = 641;
        assert!(validate(&robot).is_err());
        let mut robot = a3();
        robot.object[0].radius_m = None;
        robot.object[0].min = None;
        assert!(validate(&robot).is_err());
    }
}
