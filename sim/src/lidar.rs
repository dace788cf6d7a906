//! The simulated lidar: an RPLIDAR C1 on a pseudo-terminal at `<device dir>/lidar`, speaking
//! the device side of its serial protocol, its measurements ray-cast in the room from the
//! base's pose. What `nori-lidar` opens in place of the USB adapter.
//!
//! The wire format is written here from the protocol notes (`docs/rplidar-c1.md`), not taken
//! from the `lidar` crate the driver uses: a misreading shared by both would otherwise pass
//! every test.
//!
//! * requests `A5 cmd` (or `A5 cmd size payload… xor`, refused when the XOR is wrong);
//! * GET_INFO: model 0x41 (C1M1), firmware 1.02, hardware 18; GET_HEALTH: good, or a
//!   protection stop that a RESET clears; RESET: a boot banner in ASCII;
//! * SCAN: the descriptor at once, measurements after a spin-up, `sample_rate_hz` of them a
//!   second, `sample_rate_hz / rotation_hz` a turn, clockwise, S set on each turn's first;
//!   other requests are ignored while scanning (STOP, RESET and SCAN are not);
//! * faults: a node whose check bits are broken, a turn cut short, a burst of line noise.
//!
//! The lidar rides on the base: its beams leave from where the base is
//! ([`LidarDevice::set_base_pose`], updated by the simulator as the wheels move it).

use crate::description::{LidarDescription, RobotDescription};
use crate::device::{SerialDevice, Served};
use crate::rng::Rng;
pub use crate::room::Room;
use std::path::PathBuf;

/// Time from SCAN to the first measurement (the rotor reaching speed).
const SPIN_UP_S: f64 = 0.05;

/// What a booting C1 prints (line noise to the host).
const BOOT_BANNER: &[u8] =
    b"RP S1 LIDAR System.\r\nFirmware Ver 1.02 - rc1, HW Ver 18\r\nModel: 65\r\n";

/// The line faults of the simulated lidar.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LidarFaults {
    /// Probability per measurement that one of its check bits is broken (the standard scan's
    /// only integrity check: the driver must refuse it).
    pub corrupt_rate: f64,
    /// Probability per turn that the device stops sending part-way through it (a turn cut
    /// short: the driver must not publish it).
    pub truncate_rate: f64,
    /// Probability per turn of a burst of random bytes between two measurements.
    pub garbage_rate: f64,
    /// Seed of the line faults.
    pub seed: u64,
}

impl LidarFaults {
    /// Checks that every rate is a probability.
    pub fn validate(&self) -> Result<(), String> {
        for (name, rate) in [
            ("corrupt", self.corrupt_rate),
            ("truncate", self.truncate_rate),
            ("garbage", self.garbage_rate),
        ] {
            if !(0.0..=1.0).contains(&rate) {
                return Err(format!("lidar {name} rate must be in [0, 1], got {rate}"));
            }
        }
        Ok(())
    }
}

/// What the simulated lidar did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct LidarReport {
    /// Requests received with a valid frame.
    pub requests: u64,
    /// Requests refused (bad checksum).
    pub bad_requests: u64,
    /// Scans started.
    pub scans_started: u64,
    /// Measurements sent.
    pub nodes_sent: u64,
    /// Measurements sent with broken check bits.
    pub corrupted: u64,
    /// Turns cut short.
    pub truncated: u64,
    /// Bursts of line noise sent.
    pub garbage_bursts: u64,
    /// Whether it is scanning now (its motor turning).
    pub scanning: bool,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Mode {
    Idle,
    /// Scanning since `since` (measurements from `since + SPIN_UP_S`), `sent` of them so far.
    Scanning {
        since: f64,
        sent: u64,
    },
}

/// The device, sans-IO: requests in, bytes out, time passed in (seconds).
pub struct LidarDevice {
    description: LidarDescription,
    room: Room,
    mode: Mode,
    request: Vec<u8>,
    out: Vec<u8>,
    /// A protection stop the next GET_HEALTH reports, until a RESET.
    pub protection_stop: bool,
    faults: LidarFaults,
    rng: Rng,
    /// Index within the turn from which this turn's measurements are withheld.
    cut_at: Option<u64>,
    /// Index within the turn before which a burst of noise goes out.
    noise_at: Option<u64>,
    report: LidarReport,
    /// The base's pose in the room: x, y (m), heading (rad).
    base_pose: [f64; 3],
}

impl LidarDevice {
    /// The lidar of `robot` (`None` if it has none).
    pub fn new(robot: &RobotDescription, faults: LidarFaults) -> Option<Self> {
        let description = robot.lidar.clone()?;
        Some(LidarDevice {
            room: Room::new(robot, description.position[2]),
            description,
            mode: Mode::Idle,
            request: Vec::new(),
            out: Vec::new(),
            protection_stop: false,
            faults,
            rng: Rng::new(faults.seed ^ 0x11DA),
            cut_at: None,
            noise_at: None,
            report: LidarReport::default(),
            base_pose: [0.0; 3],
        })
    }

    /// The base moved: x, y (m), heading (rad) in the room.
    pub fn set_base_pose(&mut self, pose: [f64; 3]) {
        self.base_pose = pose;
    }

    /// What it did so far.
    pub fn report(&self) -> LidarReport {
        LidarReport {
            scanning: self.scanning(),
            ..self.report
        }
    }

    /// Whether it is scanning.
    pub fn scanning(&self) -> bool {
        matches!(self.mode, Mode::Scanning { .. })
    }

    /// Bytes from the host at time `now`.
    pub fn receive(&mut self, now: f64, bytes: &[u8]) {
        for &b in bytes {
            if self.request.is_empty() && b != 0xA5 {
                continue;
            }
            self.request.push(b);
            let r = &self.request;
            let complete = match r.len() {
                1 => false,
                2 => r[1] & 0x80 == 0,
                n => r[1] & 0x80 != 0 && n >= 4 && n == 4 + usize::from(r[2]),
            };
            if !complete {
                continue;
            }
            let request = std::mem::take(&mut self.request);
            let valid = request.len() == 2 || request.iter().fold(0u8, |x, b| x ^ b) == 0;
            if valid {
                self.report.requests += 1;
                self.execute(now, request[1]);
            } else {
                self.report.bad_requests += 1;
            }
        }
    }

    fn execute(&mut self, now: f64, cmd: u8) {
        let scanning = self.scanning();
        match cmd {
            0x25 => self.mode = Mode::Idle,
            0x40 => {
                self.mode = Mode::Idle;
                self.protection_stop = false;
                self.out.extend_from_slice(BOOT_BANNER);
            }
            0x20 | 0x21 => {
                self.out
                    .extend_from_slice(&[0xA5, 0x5A, 0x05, 0x00, 0x00, 0x40, 0x81]);
                self.mode = Mode::Scanning {
                    since: now,
                    sent: 0,
                };
                self.report.scans_started += 1;
            }
            _ if scanning => {}
            0x50 => {
                self.out
                    .extend_from_slice(&[0xA5, 0x5A, 0x14, 0x00, 0x00, 0x00, 0x04]);
                self.out.extend_from_slice(&[0x41, 0x02, 0x01, 18]);
                self.out.extend((0..16u8).map(|i| 0x10 + i));
            }
            0x52 => {
                self.out
                    .extend_from_slice(&[0xA5, 0x5A, 0x03, 0x00, 0x00, 0x00, 0x06]);
                if self.protection_stop {
                    self.out.extend_from_slice(&[2, 0x04, 0x80]);
                } else {
                    self.out.extend_from_slice(&[0, 0, 0]);
                }
            }
            _ => {}
        }
    }

    /// Measurements a turn.
    fn per_turn(&self) -> u64 {
        (self.description.sample_rate_hz / self.description.rotation_hz)
            .round()
            .max(1.0) as u64
    }

    /// Produces everything due by `now` and hands the bytes to `write`.
    pub fn advance(&mut self, now: f64, mut write: impl FnMut(&[u8])) {
        if let Mode::Scanning { since, mut sent } = self.mode {
            let due = ((now - since - SPIN_UP_S) * self.description.sample_rate_hz).floor();
            let per_turn = self.per_turn();
            while (sent as f64) < due {
                let index = sent % per_turn;
                if index == 0 {
                    self.plan_turn(per_turn);
                }
                if self.noise_at == Some(index) {
                    let n = self.rng.int(5, 40);
                    self.out.extend((0..n).map(|_| self.rng.next_u64() as u8));
                    self.report.garbage_bursts += 1;
                }
                if self.cut_at.is_none_or(|cut| index < cut) {
                    self.node(index, per_turn);
                }
                sent += 1;
            }
            self.mode = Mode::Scanning { since, sent };
        }
        if !self.out.is_empty() {
            write(&self.out);
            self.out.clear();
        }
    }

    fn plan_turn(&mut self, per_turn: u64) {
        self.cut_at = None;
        self.noise_at = None;
        if self.rng.chance(self.faults.truncate_rate) {
            self.cut_at = Some(self.rng.below(per_turn / 2) + per_turn / 4);
            self.report.truncated += 1;
        }
        if self.rng.chance(self.faults.garbage_rate) {
            self.noise_at = Some(self.rng.below(per_turn - 1) + 1);
        }
    }

    /// Measurement `index` of a turn of `per_turn`, encoded as the protocol document draws it.
    fn node(&mut self, index: u64, per_turn: u64) {
        let d = &self.description;
        let cw_deg = index as f64 * 360.0 / per_turn as f64;
        // The device turns clockwise seen from above; the world's angles run counter-clockwise.
        let [bx, by, heading] = self.base_pose;
        let world = heading + (d.yaw_deg - cw_deg).to_radians();
        let (s, c) = heading.sin_cos();
        let origin = [
            bx + c * d.position[0] - s * d.position[1],
            by + s * d.position[0] + c * d.position[1],
        ];
        let range = self
            .room
            .cast(origin, [world.cos(), world.sin()])
            .map(|r| r + d.noise_m * self.rng.normal())
            .filter(|&r| r > 0.0 && r <= d.range_m);
        let (quality, distance_q2) = match range {
            Some(r) => (
                (60.0 - 3.0 * r).clamp(8.0, 63.0) as u8,
                (r * 4000.0).round() as u16,
            ),
            None => (0, 0),
        };
        let start = u8::from(index == 0);
        let angle_q6 = ((cw_deg * 64.0).round() as u16).min(360 * 64 - 1);
        let angle_field = (angle_q6 << 1) | 1;
        let mut node = [
            (quality << 2) | ((1 - start) << 1) | start,
            angle_field as u8,
            (angle_field >> 8) as u8,
            distance_q2 as u8,
            (distance_q2 >> 8) as u8,
        ];
        if self.rng.chance(self.faults.corrupt_rate) {
            // One of the three check bits: S, !S (byte 0) or C (byte 1).
            match self.rng.below(3) {
                0 => node[0] ^= 0b01,
                1 => node[0] ^= 0b10,
                _ => node[1] ^= 0b01,
            }
            self.report.corrupted += 1;
        }
        self.out.extend_from_slice(&node);
        self.report.nodes_sent += 1;
    }
}

/// The lidar being served; dropping it stops it.
pub type ServedLidar = Served<LidarDevice>;

impl SerialDevice for LidarDevice {
    fn receive(&mut self, now: f64, bytes: &[u8]) {
        LidarDevice::receive(self, now, bytes);
    }

    fn advance(&mut self, now: f64, write: &mut dyn FnMut(&[u8])) {
        LidarDevice::advance(self, now, write);
    }
}

impl ServedLidar {
    /// What it did so far.
    pub fn report(&self) -> LidarReport {
        self.with_device(|d| d.report()).unwrap_or_default()
    }
}

/// Serves `device` on a pseudo-terminal linked at `link`, in real time.
pub fn serve(device: LidarDevice, link: PathBuf) -> Result<ServedLidar, crate::pty::ServeError> {
    crate::device::serve("lidar", device, link)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn device(faults: LidarFaults) -> LidarDevice {
        LidarDevice::new(&RobotDescription::nori_a3(), faults).unwrap()
    }

    fn out(d: &mut LidarDevice, now: f64) -> Vec<u8> {
        let mut bytes = Vec::new();
        d.advance(now, |b| bytes.extend_from_slice(b));
        bytes
    }

    #[test]
    fn the_room_is_where_the_description_puts_it() {
        let robot = RobotDescription::nori_a3();
        let room = Room::new(&robot, 0.2);
        let at = |deg: f64| {
            let a = f64::to_radians(deg);
            room.cast([0.15, 0.0], [a.cos(), a.sin()]).unwrap()
        };
        // Ahead between the table's legs to the far wall; left, behind, right to the walls.
        assert!((at(0.0) - 3.05).abs() < 1e-9);
        assert!((at(90.0) - 1.9).abs() < 1e-9);
        assert!((at(180.0) - 1.95).abs() < 1e-9);
        assert!((at(270.0) - 2.6).abs() < 1e-9);
        // A table leg: its near face at x = 0.36.
        let leg = room.cast([0.15, -0.425], [1.0, 0.0]).unwrap();
        assert!((leg - 0.21).abs() < 1e-9);
        // Above the table top the plane sees no leg.
        assert!(
            Room::new(&robot, 0.72)
                .cast([0.15, -0.425], [1.0, 0.0])
                .unwrap()
                > 3.0
        );
        // A ball cut by the plane is a circle of the cut's radius.
        let mut balls = Room::default();
        balls.add(
            &crate::description::SceneObject {
                name: "ball".into(),
                colour: [0; 3],
                center: Some([1.0, 0.0, 0.3]),
                radius_m: Some(0.5),
                min: None,
                max: None,
            },
            0.0,
        );
        assert!((balls.cast([0.0, 0.0], [1.0, 0.0]).unwrap() - 0.6).abs() < 1e-9);
    }

    #[test]
    fn it_answers_info_and_health_and_refuses_a_bad_checksum() {
        let mut d = device(LidarFaults::default());
        d.receive(0.0, &[0xA5, 0x50]);
        let info = out(&mut d, 0.0);
        assert_eq!(&info[..7], &[0xA5, 0x5A, 0x14, 0, 0, 0, 0x04]);
        assert_eq!(info[7], 0x41);
        assert_eq!(info.len(), 27);
        d.protection_stop = true;
        d.receive(0.0, &[0xA5, 0x52]);
        assert_eq!(out(&mut d, 0.0), [0xA5, 0x5A, 3, 0, 0, 0, 6, 2, 0x04, 0x80]);
        d.receive(0.0, &[0xA5, 0x40]);
        assert!(out(&mut d, 0.0).starts_with(b"RP S1"));
        d.receive(0.0, &[0xA5, 0x52]);
        assert_eq!(out(&mut d, 0.0)[7], 0);
        // A request with a payload and a wrong XOR is refused; a right one is taken.
        d.receive(0.0, &[0xA5, 0x84, 0x04, 0x7C, 0, 0, 0, 0x00]);
        d.receive(0.0, &[0xA5, 0x84, 0x04, 0x7C, 0, 0, 0, 0x59]);
        assert_eq!(d.report().bad_requests, 1);
        assert_eq!(d.report().requests, 5);
    }

    #[test]
    fn a_scan_streams_clockwise_turns_at_the_configured_rate() {
        let mut d = device(LidarFaults::default());
        d.receive(0.0, &[0xA5, 0x20]);
        let bytes = out(&mut d, 0.05 + 0.2);
        assert_eq!(&bytes[..7], &[0xA5, 0x5A, 0x05, 0x00, 0x00, 0x40, 0x81]);
        let nodes: Vec<&[u8]> = bytes[7..].chunks(5).collect();
        // 200 ms at 5 kHz: 1000 measurements, two turns of 500.
        assert_eq!(nodes.len(), 1000);
        let starts: Vec<usize> = (0..nodes.len()).filter(|&i| nodes[i][0] & 1 == 1).collect();
        assert_eq!(starts, [0, 500]);
        let angle = |n: &[u8]| f64::from(u16::from_le_bytes([n[1], n[2]]) >> 1) / 64.0;
        let range = |n: &[u8]| f64::from(u16::from_le_bytes([n[3], n[4]])) / 4000.0;
        assert!(nodes
            .iter()
            .all(|n| n[0] & 1 != (n[0] >> 1) & 1 && n[1] & 1 == 1));
        assert!((angle(nodes[125]) - 90.0).abs() < 0.01);
        // Clockwise: 90° on the wire is the right-hand wall (2.6 m), 270° the left (1.9 m).
        assert!(
            (range(nodes[125]) - 2.6).abs() < 0.03,
            "{}",
            range(nodes[125])
        );
        assert!(
            (range(nodes[375]) - 1.9).abs() < 0.03,
            "{}",
            range(nodes[375])
        );
        d.receive(0.3, &[0xA5, 0x25]);
        assert!(out(&mut d, 1.0).is_empty(), "STOP stops the stream");
        // GET_INFO while scanning is ignored.
        d.receive(1.0, &[0xA5, 0x20, 0xA5, 0x50]);
        assert_eq!(out(&mut d, 1.0).len(), 7);
    }

    #[test]
    fn the_beams_leave_from_where_the_base_is_and_turn_with_it() {
        let mut d = device(LidarFaults::default());
        // A metre forward and turned a quarter left: the lidar (0.15 m ahead of the centre)
        // at (1.0, 0.15), its 0° facing +y, the left wall (y = 1.9) 1.75 m ahead; its 90°
        // (clockwise) faces +x, the far wall (x = 3.2) 2.2 m away.
        d.set_base_pose([1.0, 0.0, std::f64::consts::FRAC_PI_2]);
        d.receive(0.0, &[0xA5, 0x20]);
        let bytes = out(&mut d, 0.05 + 0.1);
        let nodes: Vec<&[u8]> = bytes[7..].chunks(5).collect();
        let range = |n: &[u8]| f64::from(u16::from_le_bytes([n[3], n[4]])) / 4000.0;
        assert!((range(nodes[0]) - 1.75).abs() < 0.03, "{}", range(nodes[0]));
        assert!(
            (range(nodes[125]) - 2.2).abs() < 0.03,
            "{}",
            range(nodes[125])
        );
    }

    #[test]
    fn faults_break_check_bits_cut_turns_and_add_noise() {
        let faults = LidarFaults {
            corrupt_rate: 0.1,
            truncate_rate: 0.5,
            garbage_rate: 0.5,
            seed: 3,
        };
        let mut d = device(faults);
        d.receive(0.0, &[0xA5, 0x20]);
        out(&mut d, 0.05 + 2.0);
        let r = d.report();
        assert!(r.corrupted > 500 && r.corrupted < 1500, "{r:?}");
        assert!(r.truncated > 3 && r.truncated < 17, "{r:?}");
        assert!(r.garbage_bursts > 3, "{r:?}");
        assert!(r.nodes_sent < 10_000, "cut turns withhold measurements");
        assert!(faults.validate().is_ok());
        assert!(LidarFaults {
            garbage_rate: 1.5,
            ..faults
        }
        .validate()
        .is_err());
    }
}
