//! One simulated bus: its servos, the mechanics they drive, and the device side of the
//! protocol with the line's timing. Sans-IO: bytes in at a simulated time, reply bytes out with
//! the time they finish arriving on a real line.

use crate::arm::{gripper_load, Arm, JointLoads};
use crate::description::{BusDescription, RobotDescription};
use crate::servo::{Servo, Surroundings};
use feetech::instruction::Instruction;
use feetech::registers::{FEEDBACK_ADDR, FEEDBACK_LEN, TABLE_SIZE};
use feetech::timing::wire_time;
use feetech::{Decoder, StatusPacket, BROADCAST_ID, MAX_PACKET};
use serde::Serialize;
use std::collections::VecDeque;

/// The hard stops of a servo's joint or gripper, rad (lower, upper); `None` for the others.
fn stops(arm: &Arm, role: Role) -> Option<(f64, f64)> {
    match role {
        Role::ArmJoint(k) => arm.stops(k),
        Role::Gripper => arm.gripper.as_ref().map(|g| (g.lower_rad, g.upper_rad)),
        Role::Wheel | Role::Free => None,
    }
}

/// What a servo does in the mechanics.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Role {
    ArmJoint(usize),
    Gripper,
    Wheel,
    Free,
}

/// The replies to one instruction, delivered together when the last byte has arrived, as a USB
/// adapter delivers a burst (each packet still costs its full wire time).
#[derive(Debug, Clone)]
pub struct Reply {
    /// Simulated time at which its last byte has arrived, s.
    pub due: f64,
    /// The status packets, back to back.
    pub bytes: Vec<u8>,
    /// The instruction they answer (a counter).
    instruction: u64,
}

/// Protocol counters of the bus.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct LineStats {
    /// Instruction packets received.
    pub instructions: u64,
    /// SYNC_READs received.
    pub sync_reads: u64,
    /// SYNC_WRITEs received.
    pub sync_writes: u64,
    /// Framing errors (garbage, checksum, length).
    pub decode_errors: u64,
    /// Well-framed packets that were not valid instructions.
    pub bad_instructions: u64,
    /// Status packets sent.
    pub replies: u64,
    /// Reply bursts written later than due by more than 200 µs (host or scheduler latency).
    pub late_bursts: u64,
    /// Worst lateness of a reply burst, µs.
    pub max_lateness_us: f64,
    /// Answers cut because the host sent its next request before they were sent.
    pub replies_talked_over: u64,
    /// Faults injected into status packets (see [`crate::faults`]).
    pub faults: crate::faults::FaultCounts,
}

/// Per-servo figures of a report.
#[derive(Debug, Clone, Serialize)]
pub struct ServoReport {
    /// Bus id.
    pub id: u8,
    /// Joint name.
    pub joint: String,
    /// Joint angle now, rad.
    pub angle_rad: f64,
    /// Where its encoder reads, less 2048, at the joint's zero: the homing offset its
    /// calibration must find ([`crate::servo::Servo::horn_steps`]).
    pub horn_steps: f64,
    /// Winding temperature now, °C.
    pub temperature_c: f64,
    /// Highest winding temperature reached, °C.
    pub max_temperature_c: f64,
    /// Torque enabled now.
    pub torque_enabled: bool,
    /// What the servo received and did.
    #[serde(flatten)]
    pub log: crate::servo::ServoLog,
}

/// A bus's report.
#[derive(Debug, Clone, Serialize)]
pub struct BusReport {
    /// Bus name.
    pub name: String,
    /// Simulated seconds elapsed.
    pub time_s: f64,
    /// CLOCK_MONOTONIC (ns) at simulated time 0 when served in real time, else 0: simulated
    /// times below convert to the stack's clock as `epoch + t × 1e9`.
    pub epoch_monotonic_ns: u64,
    /// Simulated times of the last broadcast torque-off writes received (a bus disabled), s.
    pub torque_off_broadcasts_s: Vec<f64>,
    /// Protocol counters.
    pub line: LineStats,
    /// One report per servo, in description order.
    pub servos: Vec<ServoReport>,
    /// Every change of a servo's Torque_Limit, in order (at most
    /// [`MAX_TORQUE_LIMIT_CHANGES`]).
    pub torque_limit_changes: Vec<TorqueLimitChange>,
    /// The base these wheels move: where it really is (the truth odometry is judged by).
    pub base: Option<crate::base::BaseReport>,
}

/// Broadcast torque-off writes a bus keeps for its report (the newest).
const MAX_TORQUE_OFF_BROADCASTS: usize = 1024;
/// Most servos on one bus whose torque-limit changes are tracked.
const MAX_SERVOS: usize = 32;
/// Torque-limit changes a bus keeps for its report (a long test run's worth).
pub const MAX_TORQUE_LIMIT_CHANGES: usize = 20_000;

/// A servo's Torque_Limit register changed (a write that reached it).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct TorqueLimitChange {
    /// Simulated time, s.
    pub t_s: f64,
    /// Servo id.
    pub id: u8,
    /// New value, 0.1 %.
    pub permille: u16,
}

/// One simulated bus.
pub struct SimBus {
    /// Bus name.
    pub name: String,
    /// Line rate of the description (the servos' factory rate is 1 Mbps).
    pub baud: u32,
    /// The line rate the host talks at now: a servo set to another rate hears garbage and
    /// answers nothing (set by a link that knows it; the pseudo-terminals do not follow the
    /// host's rate yet, docs/commissioning.md).
    host_baud: u32,
    supply_v: f64,
    supply_resistance: f64,
    /// The servos, in description order.
    pub servos: Vec<Servo>,
    joints: Vec<String>,
    roles: Vec<Role>,
    arm: Option<Arm>,
    arm_servos: Vec<usize>,
    wheel_load: (f64, f64),
    /// The base the wheels move (when the description gives its geometry), and the positions
    /// of its left and right wheel servos in `servos`.
    base: Option<(crate::base::BaseMotion, [usize; 2])>,
    /// Ambient temperature, °C.
    pub ambient: f64,
    /// Thermal integration speed-up (1 = physical).
    pub thermal_speedup: f64,
    /// Heat conductance between chain neighbours relative to each one's conductance to
    /// ambient (0: none; from a fitted model extension).
    pub neighbor_coupling: f64,
    /// Ambient drift, K/s of thermal time (from a fitted model extension).
    pub ambient_drift_k_per_s: f64,
    time: f64,
    arrival: f64,
    decoder: Decoder,
    line_free_at: f64,
    /// When the host's last request has been sent.
    request_end: f64,
    pending: VecDeque<Reply>,
    registered: Vec<Option<(u8, Vec<u8>)>>,
    /// Protocol counters.
    pub stats: LineStats,
    /// See [`BusReport::epoch_monotonic_ns`].
    pub epoch_monotonic_ns: u64,
    torque_off_broadcasts: VecDeque<f64>,
    torque_limit_changes: Vec<TorqueLimitChange>,
    loads: JointLoads,
    q: Vec<f64>,
    qd: Vec<f64>,
    faults: Option<crate::faults::FaultInjector>,
    truth: Vec<Option<[u8; FEEDBACK_LEN as usize]>>,
    /// An operator's hand sweeping the arm's joints (calibration by hand), when put on.
    hand: Option<crate::hand::Hand>,
    /// Per servo: its joint was past a hard stop at the last step.
    past_stop: Vec<bool>,
}

/// How far inside each stop the robot's calibration put a joint's limits (rad): the simulated
/// A3 leaves the line calibrated so, and `deploy/config/calibration.toml` is that calibration.
pub const CALIBRATION_MARGIN_RAD: f64 = 0.15;

/// How far off the joint's zero a horn goes on at assembly, steps: a spline tooth either way
/// and more (an STS horn's 25 teeth are 164 steps apart), so the robot's calibration cannot
/// be guessed.
pub const ASSEMBLY_SPREAD_STEPS: f64 = 400.0;

impl SimBus {
    /// Builds a bus from its description: each servo set to its joint's id and rate, its arm
    /// joints calibrated ([`CALIBRATION_MARGIN_RAD`]), the rest of its EEPROM the factory's.
    pub fn new(robot: &RobotDescription, d: &BusDescription) -> Self {
        let mut servos = Vec::with_capacity(d.servo.len());
        let mut index = [None; 256];
        for (i, s) in d.servo.iter().enumerate() {
            // Validated: every model key exists.
            let rating = robot
                .rating(&s.model)
                .cloned()
                .unwrap_or_else(|| panic!("servo {} has unvalidated model {}", s.id, s.model));
            let mut servo = Servo::new(s.id, rating.model, &rating, s.initial_rad, robot.ambient_c);
            servo.supply = d.supply_v;
            servos.push(servo);
            index[s.id as usize] = Some(i as u8);
        }
        let pos = |id: u8| index[id as usize].map(usize::from).unwrap_or(0);
        let mut roles = vec![Role::Free; servos.len()];
        let mut arm_servos = Vec::new();
        if let Some(a) = &d.arm {
            for (k, j) in a.joint.iter().enumerate() {
                roles[pos(j.servo)] = Role::ArmJoint(k);
                arm_servos.push(pos(j.servo));
            }
            if let Some(g) = &a.gripper {
                roles[pos(g.servo)] = Role::Gripper;
            }
        }
        let mut wheel_load = (0.0, 0.0);
        let mut base = None;
        if let Some(w) = &d.wheels {
            for &id in &w.servos {
                roles[pos(id)] = Role::Wheel;
            }
            wheel_load = (w.inertia_kgm2, w.viscous_nms);
            // Validated: a moving base has two wheel servos.
            if let (Some(motion), [left, right]) =
                (crate::base::BaseMotion::new(robot, w), w.servos.as_slice())
            {
                base = Some((motion, [pos(*left), pos(*right)]));
            }
        }
        let n_arm = arm_servos.len();
        let mut bus = SimBus {
            name: d.name.clone(),
            baud: d.baud,
            host_baud: d.baud,
            supply_v: d.supply_v,
            supply_resistance: d.supply_resistance_ohm,
            joints: d.servo.iter().map(|s| s.joint.clone()).collect(),
            registered: vec![None; servos.len()],
            servos,
            roles,
            arm: d.arm.as_ref().map(|a| Arm::new(a, robot.gravity)),
            arm_servos,
            wheel_load,
            base,
            ambient: robot.ambient_c,
            thermal_speedup: 1.0,
            neighbor_coupling: 0.0,
            ambient_drift_k_per_s: 0.0,
            time: 0.0,
            arrival: 0.0,
            decoder: Decoder::new(),
            line_free_at: 0.0,
            request_end: 0.0,
            pending: VecDeque::new(),
            stats: LineStats::default(),
            epoch_monotonic_ns: 0,
            torque_off_broadcasts: VecDeque::new(),
            torque_limit_changes: Vec::new(),
            loads: JointLoads::default(),
            q: vec![0.0; n_arm],
            qd: vec![0.0; n_arm],
            faults: None,
            truth: vec![None; d.servo.len()],
            hand: None,
            past_stop: vec![false; d.servo.len()],
        };
        bus.calibrate_arm(CALIBRATION_MARGIN_RAD);
        bus
    }

    /// Calibrates every arm joint's and the gripper's servo `margin_rad` inside its stops, as
    /// a calibration procedure would leave them (the delivered robot's margin is
    /// [`CALIBRATION_MARGIN_RAD`]).
    pub fn calibrate_arm(&mut self, margin_rad: f64) {
        let Some(arm) = &self.arm else {
            return;
        };
        for (servo, &role) in self.servos.iter_mut().zip(&self.roles) {
            if let Some((lower, upper)) = stops(arm, role) {
                servo.calibrate(lower, upper, margin_rad);
            }
        }
    }

    /// Puts an operator's hand on the arm: from now on it sweeps each joint whose torque is off
    /// from stop to stop, in the arm's order, the gripper last ([`crate::hand`]). False on a
    /// bus without an arm.
    pub fn put_hand_on(&mut self, robot: &RobotDescription) -> bool {
        self.put_hand_on_joints(robot, |_| true)
    }

    /// [`SimBus::put_hand_on`] for the joints (by name) `sweep` accepts only. False on a bus
    /// without an arm, or when no joint is accepted.
    pub fn put_hand_on_joints(
        &mut self,
        robot: &RobotDescription,
        sweep: impl Fn(&str) -> bool,
    ) -> bool {
        let Some(arm) = robot.bus(&self.name).and_then(|d| d.arm.as_ref()) else {
            return false;
        };
        let joints = &self.joints;
        let at = |id: u8| {
            self.servos
                .iter()
                .position(|s| s.id == id)
                .filter(|&i| sweep(&joints[i]))
        };
        let mut joints: Vec<crate::hand::HandJoint> = arm
            .joint
            .iter()
            .filter_map(|j| {
                Some(crate::hand::HandJoint {
                    servo: at(j.servo)?,
                    lower_rad: j.lower_rad,
                    upper_rad: j.upper_rad,
                })
            })
            .collect();
        if let Some(g) = &arm.gripper {
            joints.extend(at(g.servo).map(|servo| crate::hand::HandJoint {
                servo,
                lower_rad: g.lower_rad,
                upper_rad: g.upper_rad,
            }));
        }
        if joints.is_empty() {
            return false;
        }
        self.hand = Some(crate::hand::Hand::new(joints));
        true
    }

    /// Whether the hand put on has swept every joint (`None`: no hand).
    pub fn hand_done(&self) -> Option<bool> {
        self.hand.as_ref().map(crate::hand::Hand::done)
    }

    /// Runs a servo model's constants as the model lab found them: its extension and the
    /// friction calibrated with it, on every servo of that model on the bus.
    pub fn apply_constants(&mut self, c: &crate::constants::ModelConstants) {
        let ext = crate::extension::ServoExtension::from(&c.finding);
        for s in self.servos.iter_mut().filter(|s| s.model == c.model) {
            s.extension = ext;
            s.sensor_temperature = s.temperature;
            if let Some(v) = c.finding.fitted_coulomb_nm {
                s.plant.coulomb = v;
            }
            if let Some(v) = c.finding.fitted_viscous_nms {
                s.plant.viscous = v;
            }
        }
    }

    /// Puts a model extension (fitted by the model lab, or an effect hidden from it) on every
    /// servo of the bus, on top of its model's constants: the parameters it sets replace
    /// theirs.
    pub fn apply_extension(&mut self, m: &crate::extension::ModelExtension) {
        for s in &mut self.servos {
            s.extension.overlay(m);
            s.sensor_temperature = s.temperature;
        }
        if let Some(k) = m.neighbor_coupling_ratio {
            self.neighbor_coupling = k;
        }
        if let Some(d) = m.ambient_drift_k_per_h {
            self.ambient_drift_k_per_s = d / 3600.0;
        }
        if let Some(r) = m.supply_resistance_ohm {
            self.supply_resistance = r;
        }
    }

    /// Injects line faults into every status packet from now on (`None`: a clean line).
    pub fn set_line_faults(&mut self, faults: Option<crate::faults::LineFaults>) {
        self.faults = faults
            .filter(crate::faults::LineFaults::any)
            .map(crate::faults::FaultInjector::new);
    }

    /// The feedback block (registers 56–70) servo `id` really answered to the last feedback
    /// SYNC_READ, before any line fault; `None` if it did not answer (silent or absent).
    pub fn feedback_truth(&self, id: u8) -> Option<&[u8]> {
        let i = self.position(id)?;
        self.truth.get(i)?.as_ref().map(|b| &b[..])
    }

    /// Where servo `id` is in `servos` (the first, if the id is duplicated).
    fn position(&self, id: u8) -> Option<usize> {
        self.servos.iter().position(|s| s.id == id)
    }

    /// The host now talks at `baud` (its serial line's setting).
    pub fn set_host_baud(&mut self, baud: u32) {
        self.host_baud = baud;
    }

    /// The positions of the servos that hear a request to `id` (a duplicated id: each of them).
    fn addressed(&self, id: u8) -> Vec<usize> {
        (0..self.servos.len())
            .filter(|&i| self.hears(i) && (id == BROADCAST_ID || self.servos[i].id == id))
            .collect()
    }

    /// Whether the servo at position `i` hears the host: powered and at the host's rate.
    fn hears(&self, i: usize) -> bool {
        let s = &self.servos[i];
        s.answering && s.line_baud() == Some(self.host_baud)
    }

    /// Puts a factory-fresh servo of the same model where `joint`'s servo was (a burnt one
    /// replaced): id 1, 1 Mbps, the factory's EEPROM, at the joint's angle, its horn fitted
    /// `horn_steps` off the old one's. False if the bus has no such joint.
    pub fn fit_fresh_servo(
        &mut self,
        robot: &RobotDescription,
        joint: &str,
        horn_steps: f64,
    ) -> bool {
        let Some(i) = self.joints.iter().position(|j| j == joint) else {
            return false;
        };
        let old = &self.servos[i];
        let Some(rating) = robot.rating(old.model.key()) else {
            return false;
        };
        let mut fresh = Servo::new(1, old.model, rating, old.angle, self.ambient);
        fresh.supply = old.supply;
        fresh.fit_horn(old.horn_steps + horn_steps);
        self.servos[i] = fresh;
        true
    }

    /// As the robot comes off the line before its calibration: each arm joint's and gripper's
    /// horn where the assembler fitted it on the spline, up to [`ASSEMBLY_SPREAD_STEPS`] off
    /// the joint's zero (seeded by `seed` and the joint's name, so a robot is repeatable), and
    /// its servo set up but not calibrated ([`Servo::clear_calibration`]). The truth is each
    /// servo's `horn_steps` in the report.
    pub fn assemble(&mut self, seed: u64) {
        for (i, servo) in self.servos.iter_mut().enumerate() {
            if matches!(self.roles[i], Role::ArmJoint(_) | Role::Gripper) {
                let mut rng = crate::rng::Rng::new(crate::rng::seed_for(seed, &self.joints[i]));
                let spread = ASSEMBLY_SPREAD_STEPS;
                servo.fit_horn(rng.range(-spread, spread));
                servo.clear_calibration();
            }
        }
    }

    /// The pose of the base these wheels move (x, y in m, heading in rad), if they move one.
    pub fn base_pose(&self) -> Option<[f64; 3]> {
        self.base.as_ref().map(|(motion, _)| motion.pose())
    }

    /// Simulated time, s.
    pub fn time(&self) -> f64 {
        self.time
    }

    /// The servo with bus id `id`.
    pub fn servo_mut(&mut self, id: u8) -> Option<&mut Servo> {
        let i = self.position(id)?;
        self.servos.get_mut(i)
    }

    /// The arm's mechanics, if this bus drives an arm (to place obstacles or objects).
    pub fn arm_mut(&mut self) -> Option<&mut Arm> {
        self.arm.as_mut()
    }

    /// The arm's joint angles into `q` (chain order) and its gripper's angle, rad; `None` for a
    /// bus without an arm.
    pub fn arm_angles(&self, q: &mut Vec<f64>) -> Option<Option<f64>> {
        self.arm.as_ref()?;
        q.clear();
        q.extend(self.arm_servos.iter().map(|&i| self.servos[i].angle));
        let gripper = self
            .roles
            .iter()
            .position(|r| *r == Role::Gripper)
            .map(|i| self.servos[i].angle);
        Some(gripper)
    }

    /// Advances the mechanics and thermal state by one step of `dt` seconds.
    pub fn step(&mut self, dt: f64) {
        let total_current: f64 = self.servos.iter().map(|s| s.current.abs()).sum();
        let supply = (self.supply_v - self.supply_resistance * total_current).max(0.0);
        if let Some(arm) = &mut self.arm {
            for (k, &i) in self.arm_servos.iter().enumerate() {
                self.q[k] = self.servos[i].angle;
                self.qd[k] = self.servos[i].speed;
            }
            arm.loads(&self.q, &self.qd, &mut self.loads);
        }
        if self.neighbor_coupling != 0.0 {
            // Servos on one chain sit next to each other in description order.
            let n = self.servos.len();
            for i in 0..n {
                let t = self.servos[i].temperature;
                let g = self.neighbor_coupling / self.servos[i].plant.thermal_resistance;
                let near = |j: usize| self.servos[j].temperature - t;
                let mut flow = 0.0;
                if i > 0 {
                    flow += near(i - 1);
                }
                if i + 1 < n {
                    flow += near(i + 1);
                }
                self.servos[i].external_heat_w = g * flow;
            }
        }
        self.ambient += self.ambient_drift_k_per_s * dt * self.thermal_speedup;
        let (ambient, speedup) = (self.ambient, self.thermal_speedup);
        // An obstacle the base is pressed against loads its wheels.
        let contact = self.base.as_ref().map(|(motion, wheels)| {
            let angle = wheels.map(|w| self.servos[w].angle);
            let speed = wheels.map(|w| self.servos[w].speed);
            (*wheels, motion.contact_torque(angle, speed))
        });
        let servos = &self.servos;
        let hand = self.hand.as_mut().and_then(|h| {
            h.push(dt, |i| crate::hand::Feel {
                angle_rad: servos[i].angle,
                speed_rad_s: servos[i].speed,
                torque_on: servos[i].torque_enabled(),
            })
        });
        let contact_on = |i: usize| match contact {
            Some((wheels, torque)) => wheels
                .iter()
                .position(|&w| w == i)
                .map_or(0.0, |k| torque[k]),
            None => 0.0,
        };
        for (i, servo) in self.servos.iter_mut().enumerate() {
            servo.supply = supply;
            let (torque, inertia) = match self.roles[i] {
                Role::ArmJoint(k) => (self.loads.torque[k], self.loads.inertia[k]),
                Role::Gripper => match self.arm.as_ref().and_then(|a| a.gripper.as_ref()) {
                    Some(g) => (gripper_load(g, servo.angle, servo.speed), 0.0),
                    None => (0.0, 0.0),
                },
                Role::Wheel => (
                    self.wheel_load.1 * servo.speed + contact_on(i),
                    self.wheel_load.0,
                ),
                Role::Free => (0.0, 0.0),
            };
            // The hand's push is a load the other way.
            let torque = match hand {
                Some((k, push)) if k == i => torque - push,
                _ => torque,
            };
            servo.step(
                dt,
                Surroundings {
                    load_torque_n_m: torque,
                    load_inertia_kg_m2: inertia,
                    ambient_c: ambient,
                    thermal_speedup: speedup,
                },
            );
        }
        if let Some((motion, wheels)) = &mut self.base {
            let angle = wheels.map(|w| self.servos[w].angle);
            let speed = wheels.map(|w| self.servos[w].speed);
            motion.step(dt, angle, speed);
        }
        self.log_stop_presses(dt);
        self.time += dt;
    }

    /// Counts each arm joint or gripper its own motor pushes past a hard stop: the witness that
    /// nothing the stack drives presses a stop (a calibration's limits inside them); and each
    /// time one goes past a stop, with the speed it struck at.
    fn log_stop_presses(&mut self, dt: f64) {
        let Some(arm) = &self.arm else {
            return;
        };
        for (i, servo) in self.servos.iter_mut().enumerate() {
            let Some((lower, upper)) = stops(arm, self.roles[i]) else {
                continue;
            };
            let past = servo.angle > upper || servo.angle < lower;
            if past && !self.past_stop[i] {
                servo.log.stop_hits += 1;
                // With the torque on, a strike the motor drove or failed to stop; limp, an
                // operator's hand, or an arm dropped by a trip: kept apart.
                let driven = servo.torque_enabled();
                let log = &mut servo.log;
                let fastest = if driven {
                    &mut log.stop_hit_max_speed_rad_s
                } else {
                    &mut log.limp_hit_max_speed_rad_s
                };
                *fastest = fastest.max(servo.speed.abs());
            }
            self.past_stop[i] = past;
            // Its motor pushes it further in (a joint sagging past a stop under gravity while
            // its motor holds against it is not pressed by the motor).
            let into = (servo.angle > upper && servo.duty > 0.0)
                || (servo.angle < lower && servo.duty < 0.0);
            if servo.torque_enabled() && into {
                let log = &mut servo.log;
                log.stop_press_s += dt;
                let pushed = (servo.duty.abs() * 1000.0).round().min(1000.0) as u16;
                log.stop_press_max_permille = log.stop_press_max_permille.max(pushed);
            }
        }
    }

    /// Steps the mechanics with `dt` until the simulated time reaches `t`.
    pub fn advance_to(&mut self, t: f64, dt: f64) {
        while self.time + dt <= t {
            self.step(dt);
        }
    }

    /// Bytes from the host arrive at simulated time `now` (≥ the mechanics' time, which lags
    /// by up to one step); replies are scheduled on the line from there.
    pub fn receive(&mut self, now: f64, mut bytes: &[u8]) {
        self.arrival = now.max(self.time);
        while !bytes.is_empty() {
            let taken = self.decoder.push(bytes);
            bytes = &bytes[taken..];
            while let Some(result) = self.decoder.next_frame() {
                match result {
                    Ok(frame) => self.deliver(&frame),
                    Err(_) => self.stats.decode_errors += 1,
                }
            }
        }
    }

    /// The next reply whose last byte has arrived by `now`, if any.
    pub fn pop_due(&mut self, now: f64) -> Option<Reply> {
        if self.pending.front().is_some_and(|r| r.due <= now) {
            let reply = self.pending.pop_front()?;
            let late_us = (now - reply.due) * 1e6;
            self.stats.max_lateness_us = self.stats.max_lateness_us.max(late_us);
            if late_us > 200.0 {
                self.stats.late_bursts += 1;
            }
            return Some(reply);
        }
        None
    }

    /// When the next reply is due.
    pub fn next_due(&self) -> Option<f64> {
        self.pending.front().map(|r| r.due)
    }

    /// A report of the bus now.
    pub fn report(&self) -> BusReport {
        BusReport {
            name: self.name.clone(),
            time_s: self.time,
            epoch_monotonic_ns: self.epoch_monotonic_ns,
            torque_off_broadcasts_s: self.torque_off_broadcasts.iter().copied().collect(),
            torque_limit_changes: self.torque_limit_changes.clone(),
            base: self.base.as_ref().map(|(motion, _)| motion.report()),
            line: self.stats,
            servos: self
                .servos
                .iter()
                .zip(&self.joints)
                .map(|(s, joint)| ServoReport {
                    id: s.id,
                    joint: joint.clone(),
                    angle_rad: s.angle,
                    horn_steps: s.horn_steps,
                    temperature_c: s.temperature,
                    max_temperature_c: s.max_temperature,
                    torque_enabled: s.torque_enabled(),
                    log: s.log,
                })
                .collect(),
        }
    }

    /// Puts one host instruction on the line to the servos, through the instruction faults: a
    /// dropped one reaches nobody; a flipped bit is decoded by the servos as it arrives (the
    /// checksum refuses a single flip, so it is lost too, counted as a decode error).
    fn deliver(&mut self, frame: &feetech::Frame) {
        let mut bytes = [0u8; MAX_PACKET];
        let Some(n) = frame.encode(&mut bytes) else {
            return;
        };
        let fault = match self.faults.as_mut() {
            Some(f) => {
                let fault = f.draw_instruction(n);
                self.stats.faults = f.counts;
                fault
            }
            None => crate::faults::Fault::None,
        };
        if fault == crate::faults::Fault::None {
            return self.execute(frame);
        }
        let arrived = crate::faults::apply(fault, &mut bytes[..n]);
        let mut line = feetech::Decoder::new();
        line.push(arrived);
        while let Some(result) = line.finish() {
            match result {
                Ok(f) => self.execute(&f),
                Err(_) => self.stats.decode_errors += 1,
            }
        }
    }

    /// Executes one instruction that reached the servos, and records the torque limits it
    /// changed and when (what a test holds against the supervisor's reductions).
    fn execute(&mut self, frame: &feetech::Frame) {
        let now = self.arrival;
        for s in &mut self.servos {
            s.now = now;
        }
        let before: [u16; MAX_SERVOS] =
            std::array::from_fn(|i| self.servos.get(i).map_or(0, Servo::torque_limit));
        self.execute_instruction(frame);
        for (i, s) in self.servos.iter().enumerate() {
            let limit = s.torque_limit();
            if i < MAX_SERVOS
                && limit != before[i]
                && self.torque_limit_changes.len() < MAX_TORQUE_LIMIT_CHANGES
            {
                self.torque_limit_changes.push(TorqueLimitChange {
                    t_s: now,
                    id: s.id,
                    permille: limit,
                });
            }
        }
    }

    fn execute_instruction(&mut self, frame: &feetech::Frame) {
        let instruction = match Instruction::parse(frame) {
            Ok(i) => i,
            Err(_) => {
                self.stats.bad_instructions += 1;
                return;
            }
        };
        self.stats.instructions += 1;
        let instruction_number = self.stats.instructions;
        // The request occupies the line first; replies follow it back to back. The host's
        // own packets follow each other; one sent before the servos finished answering talks
        // over them (a half-duplex line queues nothing): what they had yet to send is lost.
        let request_bytes = frame.params().len() + 6;
        let start = self.request_end.max(self.arrival);
        self.talk_over(start);
        self.request_end = start + wire_time(request_bytes, self.host_baud).as_secs_f64();
        self.line_free_at = self.request_end;
        match instruction {
            Instruction::Ping { id: BROADCAST_ID } => {
                self.answer_broadcast_ping(instruction_number)
            }
            Instruction::Ping { id } => self.answer(id, None, instruction_number),
            Instruction::Read { id, addr, len } => {
                self.answer(id, Some((addr, len)), instruction_number)
            }
            Instruction::Write { id, addr, data } => {
                let torque_off = feetech::registers::TORQUE_ENABLE.addr;
                if id == BROADCAST_ID && addr == torque_off && data.first() == Some(&0) {
                    if self.torque_off_broadcasts.len() == MAX_TORQUE_OFF_BROADCASTS {
                        self.torque_off_broadcasts.pop_front();
                    }
                    self.torque_off_broadcasts.push_back(self.arrival);
                }
                // The reply goes out under the id the request named, even when it changed it.
                let at = self.addressed(id);
                for &i in &at {
                    self.servos[i].write(addr, data);
                }
                if id != BROADCAST_ID {
                    self.answer_from(&at, Some(id), None, instruction_number);
                }
            }
            Instruction::RegWrite { id, addr, data } => {
                for i in self.addressed(id) {
                    self.registered[i] = Some((addr, data.to_vec()));
                }
                self.answer(id, None, instruction_number);
            }
            Instruction::Action { id } => {
                for i in self.addressed(id) {
                    if let Some((addr, data)) = self.registered[i].take() {
                        self.servos[i].write(addr, &data);
                    }
                }
                self.answer(id, None, instruction_number);
            }
            Instruction::FactoryReset { id } => self.answer(id, None, instruction_number),
            Instruction::Reboot { id } => {
                for i in self.addressed(id) {
                    self.servos[i].reboot();
                }
            }
            Instruction::SyncRead { addr, len, ids } => {
                self.stats.sync_reads += 1;
                if (addr, len) == (FEEDBACK_ADDR, FEEDBACK_LEN) {
                    self.truth.iter_mut().for_each(|t| *t = None);
                }
                for &id in ids {
                    self.answer(id, Some((addr, len)), instruction_number);
                }
            }
            Instruction::SyncWrite { addr, .. } => {
                self.stats.sync_writes += 1;
                for (id, data) in instruction.sync_write_records() {
                    for i in self.addressed(id) {
                        self.servos[i].write(addr, data);
                    }
                }
            }
        }
    }

    /// The status packets of every servo that hears the request and has id `id` (nothing for
    /// broadcast), each after its return delay: with `read`, the registers read. Two servos
    /// with one id talk at once and garble each other (see [`crate::line`]).
    fn answer(&mut self, id: u8, read: Option<(u8, u8)>, instruction: u64) {
        if id == BROADCAST_ID {
            return;
        }
        let at = self.addressed(id);
        self.answer_from(&at, Some(id), read, instruction);
    }

    /// The status packets of the servos at `positions`, under `id` (`None`: each its own).
    fn answer_from(
        &mut self,
        positions: &[usize],
        id: Option<u8>,
        read: Option<(u8, u8)>,
        instruction: u64,
    ) {
        let start = self.line_free_at;
        let byte_s = wire_time(1, self.host_baud).as_secs_f64();
        let mut line = crate::line::Line::default();
        for &i in positions {
            let mut data = [0u8; TABLE_SIZE];
            let servo = &mut self.servos[i];
            let params = match read {
                None => &data[..0],
                Some((addr, len)) if servo.read(addr, len, &mut data) => &data[..usize::from(len)],
                Some(_) => continue,
            };
            let at = start + servo.return_delay_s();
            let packet = StatusPacket {
                id: id.unwrap_or(servo.id),
                status: servo.status(),
                params,
            };
            let mut out = [0u8; MAX_PACKET];
            let Some(n) = packet.encode(&mut out) else {
                continue;
            };
            if read == Some((FEEDBACK_ADDR, FEEDBACK_LEN)) {
                let mut block = [0u8; FEEDBACK_LEN as usize];
                block.copy_from_slice(&data[..FEEDBACK_LEN as usize]);
                self.truth[i] = Some(block);
            }
            line.put(at, &out[..n], byte_s);
        }
        self.put_on_line(line, instruction);
    }

    /// The host starts sending at `at`: answers not wholly sent by then are cut.
    fn talk_over(&mut self, at: f64) {
        while self.pending.back().is_some_and(|r| r.due > at) {
            self.pending.pop_back();
            self.stats.replies_talked_over += 1;
        }
    }

    /// Schedules what the servos put on the line, through the line faults.
    fn put_on_line(&mut self, line: crate::line::Line, instruction: u64) {
        self.stats.replies += line.packets() as u64;
        let Some((mut out, due)) = line.finish() else {
            return;
        };
        self.line_free_at = due;
        let fault = match self.faults.as_mut() {
            Some(f) => {
                let fault = f.draw(out.len());
                self.stats.faults = f.counts;
                fault
            }
            None => crate::faults::Fault::None,
        };
        let bytes = crate::faults::apply(fault, &mut out);
        if bytes.is_empty() {
            return;
        }
        if let Some(last) = self
            .pending
            .back_mut()
            .filter(|r| r.instruction == instruction)
        {
            last.bytes.extend_from_slice(bytes);
            last.due = due;
            return;
        }
        let bytes = bytes.to_vec();
        self.pending.push_back(Reply {
            due,
            bytes,
            instruction,
        });
    }

    /// A broadcast PING. Feetech documents it for one servo alone on the bus ("broadcast is
    /// only applicable when there is only one servo", their SMS_STS Ping example), which then
    /// answers under its own id after its return delay (their C++ `ping` takes a reply from any
    /// id to 0xFE); nothing documents a stagger between several servos, so here each answers
    /// as the lone one would, and answers that overlap collide (see `docs/commissioning.md`).
    fn answer_broadcast_ping(&mut self, instruction: u64) {
        let at = self.addressed(BROADCAST_ID);
        self.answer_from(&at, None, None, instruction);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use feetech::registers as reg;

    fn left_arm() -> SimBus {
        let d = RobotDescription::nori_a3();
        SimBus::new(&d, d.bus("left_arm").unwrap())
    }

    fn send(bus: &mut SimBus, i: Instruction) {
        let mut buf = [0u8; 300];
        let n = i.encode(&mut buf).unwrap();
        bus.receive(bus.time(), &buf[..n]);
    }

    /// The shipped finding changes the STS3250s of the bus (the bicep rotation, the wrist
    /// pitch) and nothing else: their inertia's error and the friction fitted with it.
    #[test]
    fn a_models_constants_change_that_models_servos_only() {
        let mut bus = left_arm();
        let before: Vec<_> = bus.servos.iter().map(|s| (s.plant, s.extension)).collect();
        let found = crate::constants::shipped(crate::constants::ConstantsChoice::Fitted).unwrap();
        let c = found
            .iter()
            .find(|c| c.model == reg::ServoModel::Sts3250)
            .unwrap();
        bus.apply_constants(c);
        let mut changed = 0;
        for (s, (plant, ext)) in bus.servos.iter().zip(before) {
            if s.model == reg::ServoModel::Sts3250 {
                changed += 1;
                assert_eq!(Some(s.extension.armature_error), c.finding.armature_error);
                assert_eq!(Some(s.plant.coulomb), c.finding.fitted_coulomb_nm);
                assert_eq!(Some(s.plant.viscous), c.finding.fitted_viscous_nms);
                assert_ne!(s.plant, plant, "servo {}", s.id);
            } else {
                assert_eq!((s.plant, s.extension), (plant, ext), "servo {}", s.id);
            }
        }
        assert_eq!(changed, 2);
    }

    #[test]
    fn ping_is_answered_after_the_wire_time() {
        let mut bus = left_arm();
        send(&mut bus, Instruction::Ping { id: 1 });
        // 6 bytes request + 500 µs factory return delay + 6 bytes reply at 1 Mbps.
        let due = bus.next_due().unwrap();
        assert!((due - (60e-6 + 500e-6 + 60e-6)).abs() < 1e-9, "{due}");
        assert!(bus.pop_due(due - 1e-6).is_none());
        assert_eq!(bus.pop_due(due).unwrap().bytes, [0xFF, 0xFF, 1, 2, 0, 0xFC]);
    }

    /// A host that sends before the servos have finished answering talks over them (a
    /// half-duplex line): what they had not yet sent is lost, and the new request is answered
    /// from its own arrival. Servos do not queue requests, so a host sending faster than the
    /// answers fit (eight servos at the factory's 500 µs return delay read every 5 ms) never
    /// sees answers later and later, seconds behind.
    #[test]
    fn a_request_sent_over_unfinished_answers_cuts_them_and_is_answered_at_once() {
        let mut bus = left_arm();
        let ids: Vec<u8> = bus.servos.iter().map(|s| s.id).collect();
        let read = Instruction::SyncRead {
            addr: 56,
            len: 15,
            ids: &ids,
        };
        let period = 5e-3;
        let mut t = bus.time();
        for _ in 0..200 {
            let mut buf = [0u8; 300];
            let n = read.encode(&mut buf).unwrap();
            bus.receive(t, &buf[..n]);
            t += period;
            while bus.pop_due(t).is_some() {}
        }
        let mut buf = [0u8; 300];
        let n = Instruction::Ping { id: 1 }.encode(&mut buf).unwrap();
        bus.receive(t, &buf[..n]);
        let due = bus.next_due().unwrap() - t;
        assert!(
            (due - (60e-6 + 500e-6 + 60e-6)).abs() < 1e-9,
            "the ping answered {:.1} ms after it was sent",
            due * 1e3
        );
        assert_eq!(
            bus.pop_due(f64::MAX).unwrap().bytes,
            [0xFF, 0xFF, 1, 2, 0, 0xFC]
        );
        assert!(bus.stats.replies_talked_over > 0);
    }

    #[test]
    fn sync_read_answers_in_request_order_and_skips_absent_ids() {
        let mut bus = left_arm();
        send(
            &mut bus,
            Instruction::Write {
                id: BROADCAST_ID,
                addr: reg::RETURN_DELAY_TIME.addr,
                data: &[0],
            },
        );
        send(
            &mut bus,
            Instruction::SyncRead {
                addr: 56,
                len: 15,
                ids: &[3, 1, 99, 2],
            },
        );
        // One burst: three 21-byte status packets back to back.
        let burst = bus.pop_due(f64::MAX).unwrap();
        assert!(bus.pop_due(f64::MAX).is_none());
        assert_eq!(burst.bytes.len(), 3 * 21);
        let ids: Vec<u8> = burst.bytes.chunks(21).map(|p| p[2]).collect();
        assert_eq!(ids, [3, 1, 2]);
        let last_due = burst.due;
        // Broadcast write (no reply) 9 bytes + request 11 + 3 replies × 21 bytes.
        assert!(
            (last_due - (9.0 + 11.0 + 63.0) * 10e-6).abs() < 1e-9,
            "{last_due}"
        );
    }

    #[test]
    fn sync_write_moves_servos_and_is_logged() {
        let mut bus = left_arm();
        send(
            &mut bus,
            Instruction::Write {
                id: BROADCAST_ID,
                addr: reg::TORQUE_ENABLE.addr,
                data: &[1],
            },
        );
        let payload = [5, 0x00, 0x09, 7, 0x00, 0x07];
        send(
            &mut bus,
            Instruction::SyncWrite {
                addr: 42,
                len: 2,
                payload: &payload,
            },
        );
        bus.advance_to(2.0, 0.001);
        let s5 = bus.servo_mut(5).unwrap();
        assert_eq!(s5.log.goal_min, Some(0x900));
        assert!(
            (s5.angle - (0x900 as f64 - 2048.0) * crate::servo::RAD_PER_STEP).abs() < 0.02,
            "{}",
            s5.angle
        );
        let s7 = bus.servo_mut(7).unwrap();
        assert_eq!(s7.log.goal_max, Some(0x700));
    }

    fn frames(bytes: &[u8]) -> Vec<Result<u8, feetech::DecodeError>> {
        let mut d = Decoder::new();
        d.push(bytes);
        std::iter::from_fn(|| d.finish())
            .map(|f| f.map(|f| f.id))
            .collect()
    }

    fn alone(bus: &mut SimBus, id: u8) {
        for s in &mut bus.servos {
            s.answering = s.id == id;
        }
    }

    #[test]
    fn a_lone_servo_answers_a_broadcast_ping_under_its_own_id() {
        let mut bus = left_arm();
        alone(&mut bus, 6);
        send(&mut bus, Instruction::Ping { id: BROADCAST_ID });
        let reply = bus.pop_due(f64::MAX).unwrap();
        // 6 bytes request + the factory 500 µs return delay + 6 bytes reply.
        assert!((reply.due - 620e-6).abs() < 1e-9, "{}", reply.due);
        assert_eq!(reply.bytes, [0xFF, 0xFF, 6, 2, 0, 0xF7]);
    }

    #[test]
    fn servos_answering_a_broadcast_ping_together_garble_the_line() {
        let mut bus = left_arm();
        send(&mut bus, Instruction::Ping { id: BROADCAST_ID });
        let reply = bus.pop_due(f64::MAX).unwrap();
        assert_eq!(bus.stats.replies, 8);
        assert!(frames(&reply.bytes).iter().all(Result::is_err));
    }

    #[test]
    fn a_duplicated_id_answers_twice_or_garbled() {
        let mut bus = left_arm();
        let write = |bus: &mut SimBus, id: u8, r: reg::Register, value: u8| {
            let data = [value];
            send(
                bus,
                Instruction::Write {
                    id,
                    addr: r.addr,
                    data: &data,
                },
            );
            bus.pop_due(f64::MAX).map(|r| frames(&r.bytes))
        };
        // The bicep's servo (an STS3250) becomes a second id 1 beside the shoulder's STS3095,
        // both at the factory's return delay.
        let ack = write(&mut bus, 3, reg::ID, 1);
        assert_eq!(ack, Some(vec![Ok(3)]), "acknowledged under the old id");
        send(&mut bus, Instruction::Ping { id: 3 });
        assert!(bus.pop_due(f64::MAX).is_none(), "id 3 is gone");
        // The same bytes at the same time: one packet to the host.
        send(&mut bus, Instruction::Ping { id: 1 });
        assert_eq!(frames(&bus.pop_due(f64::MAX).unwrap().bytes), [Ok(1)]);
        // Different data at the same time: garbled.
        let model = Instruction::Read {
            id: 1,
            addr: reg::MODEL_NUMBER.addr,
            len: 2,
        };
        send(&mut bus, model);
        let garbled = frames(&bus.pop_due(f64::MAX).unwrap().bytes);
        assert!(garbled.iter().all(Result::is_err), "{garbled:?}");
        // Different return delays: two intact packets, the quicker first.
        // (One of the two set directly: a request to id 1 reaches both.)
        assert!(bus.servos[0].write(reg::RETURN_DELAY_TIME.addr, &[0]));
        send(&mut bus, model);
        let reply = bus.pop_due(f64::MAX).unwrap();
        let models: Vec<u16> = reply
            .bytes
            .chunks(8)
            .map(|p| u16::from_le_bytes([p[5], p[6]]))
            .collect();
        assert_eq!(frames(&reply.bytes), [Ok(1), Ok(1)]);
        assert_eq!(
            models,
            [2569, 2825],
            "the shoulder's STS3095 (delay 0) first"
        );
    }

    /// The witness of a pressed stop: the elbow driven at its calibrated limit stays clear of
    /// its stop; uncalibrated (limits 0..4095), the same goal far beyond drives it into the
    /// stop, logged with the motor's push and the strike's speed; pushed past or swung into
    /// it by hand, torque off, neither is logged (a hit is counted).
    #[test]
    fn a_joint_its_motor_holds_past_a_stop_is_logged_and_one_held_inside_is_not() {
        let mut bus = left_arm();
        let elbow = bus.position(4).unwrap();
        let goal = |bus: &mut SimBus, steps: u16| {
            let data = steps.to_le_bytes();
            send(
                bus,
                Instruction::Write {
                    id: 4,
                    addr: reg::GOAL_POSITION.addr,
                    data: &data,
                },
            );
        };
        let torque = [1];
        send(
            &mut bus,
            Instruction::Write {
                id: 4,
                addr: reg::TORQUE_ENABLE.addr,
                data: &torque,
            },
        );
        goal(&mut bus, 4095);
        bus.advance_to(3.0, 0.001);
        let log = bus.servos[elbow].log;
        assert_eq!(
            (log.stop_press_s, log.stop_press_max_permille),
            (0.0, 0),
            "at its limit"
        );
        assert_eq!(log.stop_hits, 0, "at its limit, 0.15 rad inside its stop");

        bus.servos[elbow].clear_calibration();
        goal(&mut bus, 4095);
        bus.advance_to(6.0, 0.001);
        let log = bus.servos[elbow].log;
        assert!(log.stop_press_s > 1.0, "{log:?}");
        assert!(log.stop_press_max_permille > 100, "{log:?}");
        // Struck once at speed (it stays there, pressed).
        assert_eq!(log.stop_hits, 1, "{log:?}");
        assert!(log.stop_hit_max_speed_rad_s > 0.5, "{log:?}");

        let off = [0];
        send(
            &mut bus,
            Instruction::Write {
                id: 4,
                addr: reg::TORQUE_ENABLE.addr,
                data: &off,
            },
        );
        let before = bus.servos[elbow].log.stop_press_s;
        bus.servos[elbow].angle += 0.05;
        bus.advance_to(6.01, 0.001);
        assert_eq!(
            bus.servos[elbow].log.stop_press_s, before,
            "torque off: not the motor's"
        );

        // Swung limp into its stop again (an operator's hand): a hit, not a strike.
        let Role::ArmJoint(k) = bus.roles[elbow] else {
            panic!("the elbow is an arm joint")
        };
        let (lower, upper) = bus.arm.as_ref().unwrap().stops(k).unwrap();
        let e = &mut bus.servos[elbow];
        // Inside the stop it was pressed past, swinging toward it.
        let (inside, toward) = if e.angle > upper {
            (upper - 0.01, 3.0)
        } else {
            (lower + 0.01, -3.0)
        };
        let hits = e.log.stop_hits;
        e.log.stop_hit_max_speed_rad_s = 0.0;
        (e.angle, e.speed) = (inside, toward);
        bus.advance_to(6.05, 0.001);
        let log = bus.servos[elbow].log;
        assert_eq!(log.stop_hits, hits + 1, "{log:?}");
        assert_eq!(log.stop_hit_max_speed_rad_s, 0.0, "limp: not a strike");
        assert!(log.limp_hit_max_speed_rad_s > 1.0, "{log:?}");
    }

    /// Off the line: every arm servo's horn somewhere within the spread, no two joints alike,
    /// the same robot from the same seed; its encoder reads the horn, uncalibrated.
    #[test]
    fn a_robot_off_the_line_has_its_horns_where_the_seed_put_them_and_no_calibration() {
        let assembled = |seed| {
            let mut bus = left_arm();
            bus.assemble(seed);
            bus
        };
        let horns = |bus: &SimBus| -> Vec<f64> {
            bus.report().servos.iter().map(|s| s.horn_steps).collect()
        };
        let mut bus = assembled(7);
        let h = horns(&bus);
        assert!(h.iter().all(|h| h.abs() <= ASSEMBLY_SPREAD_STEPS), "{h:?}");
        assert!(
            h.iter().any(|&h| h > 100.0) && h.iter().any(|&h| h < -100.0),
            "{h:?}"
        );
        for (i, a) in h.iter().enumerate() {
            assert!(h[i + 1..].iter().all(|b| b != a), "{h:?}");
        }
        assert_eq!(horns(&assembled(7)), h);
        let other = horns(&assembled(8));
        assert!(other.iter().zip(&h).all(|(a, b)| a != b));
        let report = bus.report();
        for (s, r) in bus.servos.iter_mut().zip(&report.servos) {
            assert_eq!(s.get(reg::HOMING_OFFSET), 0);
            assert_eq!(s.get(reg::MIN_POSITION_LIMIT), 0);
            assert_eq!(s.get(reg::MAX_POSITION_LIMIT), 4095);
            let expected = 2048.0 + r.horn_steps + r.angle_rad / crate::servo::RAD_PER_STEP;
            let mut bytes = [0; 2];
            assert!(s.read(reg::PRESENT_POSITION.addr, 2, &mut bytes));
            let read = u16::from_le_bytes(bytes);
            assert!(
                (f64::from(read) - expected).abs() <= 1.0,
                "{read} vs {expected}"
            );
        }
        // Held where it is: torque on does not move it.
        send(
            &mut bus,
            Instruction::Write {
                id: BROADCAST_ID,
                addr: reg::TORQUE_ENABLE.addr,
                data: &[1],
            },
        );
        let before: Vec<f64> = bus.servos.iter().map(|s| s.angle).collect();
        bus.advance_to(1.0, 0.001);
        for (s, b) in bus.servos.iter().zip(&before) {
            assert!((s.angle - b).abs() < 0.02, "{} moved from {b}", s.angle);
        }
    }

    #[test]
    fn a_servo_at_another_rate_hears_nothing_until_the_host_talks_at_its_rate() {
        let mut bus = left_arm();
        alone(&mut bus, 4);
        send(
            &mut bus,
            Instruction::Write {
                id: 4,
                addr: reg::BAUD_RATE.addr,
                data: &[6],
            },
        );
        assert_eq!(
            frames(&bus.pop_due(f64::MAX).unwrap().bytes),
            [Ok(4)],
            "acknowledged first"
        );
        send(&mut bus, Instruction::Ping { id: 4 });
        assert!(bus.pop_due(f64::MAX).is_none());
        bus.set_host_baud(57_600);
        bus.advance_to(1.0, 0.001);
        let t0 = bus.time();
        send(&mut bus, Instruction::Ping { id: 4 });
        let reply = bus.pop_due(f64::MAX).unwrap();
        assert_eq!(frames(&reply.bytes), [Ok(4)]);
        // 12 bytes at 57 600 baud and the 500 µs delay.
        assert!((reply.due - t0 - (12.0 * 10.0 / 57_600.0 + 500e-6)).abs() < 1e-6);
    }

    #[test]
    fn garbage_is_counted_and_does_not_stop_the_device() {
        let mut bus = left_arm();
        bus.receive(0.0, &[0x00, 0x13, 0xFF, 0xFF, 0x01, 0x02, 0x01, 0x00]);
        send(&mut bus, Instruction::Ping { id: 2 });
        assert!(bus.stats.decode_errors >= 1);
        assert_eq!(bus.pop_due(f64::MAX).unwrap().bytes[2], 2);
    }
}
