//! The supervisor as one pure state machine: joint-state frames in (with their timestamps as the
//! clock), directives, events and grip force out. The process around it only moves frames.

use crate::config::{GripCalibration, SupervisorConfig};
use crate::event::{Event, TripCause};
use crate::grip::grip_force;
use crate::stall::{StallAction, StallDetector, StallKind};
use crate::thermal::{BusThermal, ThermalEvent};
use std::time::Duration;
use telemetry::frames::{
    Directives, GripFrame, GripSample, JointLayout, JointRole, JointSample, JointState,
    SupervisorCommand, SupervisorEvent, COMMAND_REENABLE_BUS, COMMAND_REFUSED_NOT_STOPPED,
    COMMAND_REFUSED_NOT_TRIPPED, COMMAND_REFUSED_NO_SUCH_BUS, COMMAND_REFUSED_UNKNOWN_KIND,
    COMMAND_RESUME, COMMAND_STOP, DIRECTIVE_FLAG_STOP, JOINT_FLAG_DRIVER_TRIP,
    JOINT_FLAG_OUTPUT_LOST, MAX_BUSES, MAX_GRIPPERS,
};
use telemetry::watchdog::{Liveness, Watchdog};
use telemetry::MAX_JOINTS;
use thiserror::Error;

/// A layout the supervisor cannot supervise.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum LayoutError {
    /// More buses than a directives frame can address.
    #[error("{0} buses exceed the {MAX_BUSES} a directives frame addresses")]
    TooManyBuses(u32),
    /// More grippers than a grip frame carries.
    #[error("{0} grippers exceed the {MAX_GRIPPERS} a grip frame carries")]
    TooManyGrippers(usize),
    /// A gripper without grip-force calibration.
    #[error("gripper {0:?} has no [grip.{0}] calibration in the supervisor configuration")]
    NoGripCalibration(String),
    /// The software trip would not fire before a motor's firmware cutoff (the two tiers must be
    /// ordered: the recoverable, bus-wide trip first).
    #[error("thermal.trip-c {trip_c} °C is not at least 1 °C below {joint}'s firmware cutoff of {cutoff_c} °C (the driver's Max_Temperature_Limit)")]
    TripNotBelowCutoff {
        /// The joint.
        joint: String,
        /// Its firmware cutoff, as the driver publishes it.
        cutoff_c: u8,
        /// The configured software trip.
        trip_c: f32,
    },
}

/// Status bits of the firmware protections that unload a motor: overheat, over-current,
/// overload (the STS status byte; `Unloading_Condition` enables each).
pub const PROTECTION_BITS: u8 = 0x04 | 0x08 | 0x20;
/// Consecutive frames a protection bit must be seen before it counts: one corrupted reply that
/// passed the checksum must not latch a bus off.
pub const PROTECTION_CONFIRM_FRAMES: u8 = 2;

pub use crate::event::NONE;

/// The supervisor's state.
pub struct Supervisor {
    config: SupervisorConfig,
    layout: JointLayout,
    stall: Vec<StallDetector>,
    buses: Vec<BusThermal>,
    grippers: Vec<(usize, GripCalibration)>,
    directives: Directives,
    events: Vec<SupervisorEvent>,
    grip: GripFrame,
    event_seq: u64,
    output_lost: Vec<bool>,
    /// Per joint: consecutive frames with a protection bit, and whether it was reported.
    protection: Vec<(u8, bool)>,
    /// Per bus: the driver's own trip flag was seen (reported once per onset).
    driver_trip: Vec<bool>,
    /// Bus enables, torque limits and flags last handed out.
    published: (u32, [u16; MAX_JOINTS], u32),
    /// The driver's heartbeats, and what was last said of them.
    driver: DriverWatch,
}

/// The driver's liveness from its heartbeats; kept across a new layout (the same driver, or its
/// successor, is watched on).
#[derive(Debug, Clone, Copy)]
struct DriverWatch {
    watchdog: Watchdog,
    state: Liveness,
}

impl Supervisor {
    /// A supervisor for the driver's `layout`.
    pub fn new(layout: &JointLayout, config: SupervisorConfig) -> Result<Self, LayoutError> {
        if layout.bus_count as usize > MAX_BUSES {
            return Err(LayoutError::TooManyBuses(layout.bus_count));
        }
        let joints = layout.joints();
        let trip_c = config.thermal.trip_c;
        if let Some(j) = joints
            .iter()
            .find(|j| trip_c > f32::from(j.max_temperature_c) - 1.0)
        {
            return Err(LayoutError::TripNotBelowCutoff {
                joint: j.name().into(),
                cutoff_c: j.max_temperature_c,
                trip_c,
            });
        }
        let stall = joints
            .iter()
            .map(|j| {
                let kind = match j.role() {
                    JointRole::Wheel => StallKind::Wheel,
                    JointRole::Gripper => StallKind::Gripper,
                    _ => StallKind::Joint,
                };
                StallDetector::new(kind, config.stall_current(j.model), &config.stall)
            })
            .collect();
        let buses = (0..layout.bus_count as usize)
            .map(|b| {
                BusThermal::new(
                    (0..joints.len())
                        .filter(|&j| joints[j].bus as usize == b)
                        .collect(),
                )
            })
            .collect();
        let mut grippers = Vec::new();
        for (i, j) in joints
            .iter()
            .enumerate()
            .filter(|(_, j)| j.role() == JointRole::Gripper)
        {
            let cal = config
                .grip
                .get(j.name())
                .copied()
                .ok_or_else(|| LayoutError::NoGripCalibration(j.name().into()))?;
            grippers.push((i, cal));
        }
        if grippers.len() > MAX_GRIPPERS {
            return Err(LayoutError::TooManyGrippers(grippers.len()));
        }
        let directives = Directives {
            joint_count: layout.joint_count,
            ..Directives::default()
        };
        Ok(Supervisor {
            layout: *layout,
            stall,
            buses,
            grip: GripFrame {
                gripper_count: grippers.len() as u32,
                ..GripFrame::default()
            },
            grippers,
            directives,
            events: Vec::with_capacity(64),
            event_seq: 0,
            output_lost: vec![false; joints.len()],
            protection: vec![(0, false); joints.len()],
            driver_trip: vec![false; layout.bus_count as usize],
            published: (
                directives.bus_enabled,
                directives.torque_limit_permille,
                directives.flags,
            ),
            driver: DriverWatch {
                watchdog: Watchdog::new(Duration::from_millis(config.driver_timeout_ms)),
                state: Liveness::Unknown,
            },
            config,
        })
    }

    /// The layout supervised.
    pub fn layout(&self) -> &JointLayout {
        &self.layout
    }

    /// Records an event at `now_ns` (numbered in order; a frame only at the edge).
    pub fn event(&mut self, now_ns: u64, event: Event) {
        self.event_seq += 1;
        self.events.push(event.frame(self.event_seq, now_ns));
    }

    /// Takes over the driver's watch from the instance this one replaces (a new layout).
    pub fn inherit_driver_watch(&mut self, previous: &Supervisor) {
        self.driver = previous.driver;
    }

    /// A driver heartbeat from process `pid`, received at `now_ns`: a new process is reported
    /// back at once, with its pid.
    pub fn driver_beat(&mut self, now_ns: u64, pid: u32) {
        if self.driver.watchdog.beat(now_ns, pid) {
            self.event(now_ns, Event::DriverBack { pid: Some(pid) });
        }
    }

    /// Judges the driver's liveness at `now_ns`: lost after the configured silence, back when
    /// heard again (each reported once).
    pub fn watch_driver(&mut self, now_ns: u64) -> Liveness {
        let now = self.driver.watchdog.liveness(now_ns);
        match (self.driver.state, now) {
            (Liveness::Alive, Liveness::Lost) => {
                let silence = self.driver.watchdog.silence(now_ns).unwrap_or_default();
                let silence_s = silence.as_secs_f32();
                self.event(now_ns, Event::DriverLost { silence_s });
            }
            (Liveness::Lost, Liveness::Alive) => {
                self.event(now_ns, Event::DriverBack { pid: None });
            }
            _ => {}
        }
        self.driver.state = now;
        now
    }

    /// The driver's liveness as last judged by [`Supervisor::watch_driver`].
    pub fn driver_liveness(&self) -> Liveness {
        self.driver.state
    }

    /// Events since the last drain, in order.
    pub fn drain_events(&mut self) -> std::vec::Drain<'_, SupervisorEvent> {
        self.events.drain(..)
    }

    /// The directives now, stamped with `now_ns` and a fresh sequence number.
    pub fn directives(&mut self, now_ns: u64) -> Directives {
        self.directives.seq += 1;
        self.directives.timestamp_ns = now_ns;
        self.published = (
            self.directives.bus_enabled,
            self.directives.torque_limit_permille,
            self.directives.flags,
        );
        self.directives
    }

    /// Whether the directives differ from those last returned by [`Supervisor::directives`].
    pub fn directives_changed(&self) -> bool {
        (
            self.directives.bus_enabled,
            self.directives.torque_limit_permille,
            self.directives.flags,
        ) != self.published
    }

    /// The grip force of the last frame.
    pub fn grip(&self) -> &GripFrame {
        &self.grip
    }

    /// Whether an operator's stop is in force.
    pub fn stopped(&self) -> bool {
        self.directives.flags & DIRECTIVE_FLAG_STOP != 0
    }

    /// Whether bus `b` is tripped.
    pub fn bus_tripped(&self, b: usize) -> bool {
        self.buses.get(b).is_some_and(|t| t.tripped)
    }

    /// Tripped buses, one bit each.
    pub fn tripped_buses(&self) -> u32 {
        (0..self.buses.len().min(32))
            .filter(|&b| self.buses[b].tripped)
            .fold(0, |mask, b| mask | (1 << b))
    }

    /// The joints of every tripped bus, by name: what must survive a restart of this process
    /// (the latch is the operator's to release, not a crash's).
    pub fn tripped_joints(&self) -> Vec<String> {
        let joints = self.layout.joints();
        self.buses
            .iter()
            .filter(|b| b.tripped)
            .flat_map(|b| b.joints().iter().map(|&j| joints[j].name().to_string()))
            .collect()
    }

    /// Latches again the trips a previous instance recorded: every bus holding one of `names`.
    /// Returns the buses tripped; names not in the layout are ignored (a reconfigured robot).
    pub fn restore_trips(&mut self, names: &[String], now_ns: u64) -> Vec<u8> {
        if names.iter().any(|n| n == telemetry::latch::OPERATOR_STOP) {
            self.directives.flags |= DIRECTIVE_FLAG_STOP;
            self.event(now_ns, Event::OperatorStop { restored: true });
        }
        let joints = self.layout.joints();
        let mut restored = Vec::new();
        for (b, bus) in self.buses.iter_mut().enumerate() {
            let named = bus
                .joints()
                .iter()
                .any(|&j| names.iter().any(|n| n == joints[j].name()));
            if named && bus.force_trip() {
                restored.push(b as u8);
            }
        }
        for &b in &restored {
            self.directives.bus_enabled &= !(1 << b);
            self.event(
                now_ns,
                Event::ThermalTrip {
                    joint: None,
                    bus: b,
                    cause: TripCause::Restored,
                    temperature_c: f32::NAN,
                },
            );
        }
        restored
    }

    /// Feeds one joint-state frame. A frame for another layout is ignored (returns false).
    pub fn on_state(&mut self, state: &JointState) -> bool {
        if state.joint_count != self.layout.joint_count {
            return false;
        }
        let (now, joints) = (state.timestamp_ns, state.joints());
        self.stall_tier(now, joints);
        self.output_lost_tier(now, joints);
        self.firmware_tier(now, joints);
        self.driver_tier(now, joints);
        self.thermal_tier(now, joints);
        self.directives.bus_enabled = (0..32u32)
            .filter(|&b| !self.bus_tripped(b as usize))
            .fold(0, |mask, b| mask | (1 << b));
        self.grip_force(state);
        true
    }

    /// Stall detection and reaction, joint by joint.
    fn stall_tier(&mut self, now: u64, joints: &[JointSample]) {
        // Stall detection and reaction.
        for (j, sample) in joints.iter().enumerate() {
            let detector = &mut self.stall[j];
            // A wheel's is its speed (its position wraps; its goal is a speed).
            let wheel = self.layout.joints[j].role() == JointRole::Wheel;
            let motion = if wheel {
                sample.velocity_rad_s
            } else {
                sample.position_rad
            };
            let reading = sample
                .is_valid()
                .then_some((motion, sample.current_a, sample.goal_rad));
            let action = detector.update(reading, &self.config.stall);
            let limit = detector.torque_limit_permille(&self.config.stall);
            self.directives.torque_limit_permille[j] = limit;
            let (bus, current) = (self.layout.joints[j].bus, sample.current_a);
            let j8 = j as u8;
            let stall = Event::Stall {
                joint: j8,
                bus,
                current_a: current,
            };
            match action {
                StallAction::None => {}
                StallAction::Retry => {
                    self.event(now, stall);
                    self.event(
                        now,
                        Event::StallRetry {
                            joint: j8,
                            bus,
                            current_a: current,
                        },
                    );
                }
                StallAction::Reduce => {
                    if self.layout.joints[j].role() == JointRole::Gripper {
                        self.event(now, stall);
                    }
                    let limit_percent = f32::from(limit) / 10.0;
                    self.event(
                        now,
                        Event::TorqueReduced {
                            joint: j8,
                            bus,
                            limit_percent,
                        },
                    );
                }
                StallAction::Restore => self.event(
                    now,
                    Event::TorqueRestored {
                        joint: j8,
                        bus,
                        current_a: current,
                    },
                ),
            }
        }
    }

    /// A motor's output cut where the software tier did not fire.
    fn output_lost_tier(&mut self, now: u64, joints: &[JointSample]) {
        // The hardware tier fired somewhere the software tier did not: the driver saw a motor's
        // output vanish. Disable that bus too.
        for (j, sample) in joints.iter().enumerate() {
            let lost = sample.flags & JOINT_FLAG_OUTPUT_LOST != 0;
            if lost && !self.output_lost[j] {
                let (joint, bus) = (j as u8, self.layout.joints[j].bus);
                let temperature_c = sample.temperature_c;
                let event = Event::OutputLost {
                    joint,
                    bus,
                    temperature_c,
                };
                self.trip_from_outside(now, event, Some(joint), bus, temperature_c);
            }
            self.output_lost[j] = lost;
        }
    }

    /// A firmware protection's status bits, confirmed over two frames.
    fn firmware_tier(&mut self, now: u64, joints: &[JointSample]) {
        // The hardware tier announced itself: a firmware protection's status bit (seen in two
        // frames in a row) disables the bus like the software trip.
        for (j, sample) in joints.iter().enumerate() {
            let bits = if sample.is_valid() {
                sample.status & PROTECTION_BITS
            } else {
                0
            };
            let (frames, reported) = &mut self.protection[j];
            if bits == 0 {
                if sample.is_valid() {
                    (*frames, *reported) = (0, false);
                }
                continue;
            }
            *frames = frames.saturating_add(1);
            if *frames < PROTECTION_CONFIRM_FRAMES || *reported {
                continue;
            }
            *reported = true;
            let (joint, bus) = (j as u8, self.layout.joints[j].bus);
            let temperature_c = sample.temperature_c;
            let event = Event::FirmwareProtection {
                joint,
                bus,
                bits,
                temperature_c,
            };
            self.trip_from_outside(now, event, Some(joint), bus, temperature_c);
        }
    }

    /// The driver's last-resort trips, taken over as this supervisor's latches.
    fn driver_tier(&mut self, now: u64, joints: &[JointSample]) {
        // The driver's last-resort tier tripped a bus while no supervisor was heard: the trip
        // becomes this supervisor's, latched and recorded like its own.
        for b in 0..self.driver_trip.len() {
            let mut hottest = f32::NEG_INFINITY;
            let mut flagged = false;
            for (j, sample) in joints.iter().enumerate() {
                if self.layout.joints[j].bus as usize == b {
                    flagged |= sample.flags & JOINT_FLAG_DRIVER_TRIP != 0;
                    if sample.is_valid() {
                        hottest = hottest.max(sample.temperature_c);
                    }
                }
            }
            if flagged && !self.driver_trip[b] {
                let event = Event::DriverTrip {
                    bus: b as u8,
                    hottest_c: hottest,
                };
                self.trip_from_outside(now, event, None, b as u8, hottest);
            }
            self.driver_trip[b] = flagged;
        }
    }

    /// The software thermal tier, bus by bus.
    fn thermal_tier(&mut self, now: u64, joints: &[JointSample]) {
        // Thermal tier, bus by bus.
        let t = now as f64 * 1e-9;
        for b in 0..self.buses.len() {
            let event = self.buses[b].update(
                t,
                |j| {
                    joints
                        .get(j)
                        .filter(|s| s.is_valid())
                        .map(|s| s.temperature_c)
                },
                &self.config.thermal,
            );
            match event {
                Some(ThermalEvent::Trip {
                    joint,
                    temperature_c,
                }) => self.event(
                    now,
                    Event::ThermalTrip {
                        joint: Some(joint as u8),
                        bus: b as u8,
                        cause: TripCause::Software,
                        temperature_c,
                    },
                ),
                Some(ThermalEvent::Warning {
                    level,
                    joint,
                    time_to_trip_s,
                }) => self.event(
                    now,
                    Event::ThermalWarning {
                        joint: joint as u8,
                        bus: b as u8,
                        level,
                        time_to_trip_s,
                    },
                ),
                None => {}
            }
        }
    }

    /// Grip force from the frame's current read.
    fn grip_force(&mut self, state: &JointState) {
        let (now, joints) = (state.timestamp_ns, state.joints());
        // Grip force from the same current read.
        self.grip.state_seq = state.seq;
        self.grip.timestamp_ns = now;
        for (k, &(j, cal)) in self.grippers.iter().enumerate() {
            let s = &joints[j];
            self.grip.grippers[k] = GripSample {
                joint: j as u8,
                valid: s.valid,
                reserved: [0; 2],
                current_a: s.current_a,
                force: if s.is_valid() {
                    grip_force(s.current_a, &cal)
                } else {
                    0.0
                },
            };
        }
    }

    /// A tier outside this process fired on `bus` (the firmware, or the driver's own): the event
    /// that says how, then the bus latched like a software trip (with a `ThermalTrip` event
    /// when it was not tripped already).
    fn trip_from_outside(
        &mut self,
        now: u64,
        event: Event,
        joint: Option<u8>,
        bus: u8,
        temperature_c: f32,
    ) {
        self.event(now, event);
        if self
            .buses
            .get_mut(usize::from(bus))
            .is_some_and(BusThermal::force_trip)
        {
            let cause = TripCause::Outside;
            self.event(
                now,
                Event::ThermalTrip {
                    joint,
                    bus,
                    cause,
                    temperature_c,
                },
            );
        }
    }

    /// An operator's command. Re-enabling a bus is granted only after it has cooled. A command
    /// that is not carried out is answered with a reason, never silently dropped: the operator
    /// (`nori reenable`) waits for an answer.
    pub fn command(&mut self, cmd: &SupervisorCommand, now_ns: u64) {
        let refused = |s: &mut Self, why: u8| {
            let (bus, command) = (cmd.bus, cmd.kind);
            s.event(now_ns, Event::CommandRefused { bus, why, command });
        };
        match cmd.kind {
            COMMAND_REENABLE_BUS => {}
            COMMAND_STOP => {
                // A second press changes nothing and says nothing: the stop is in force.
                if !self.stopped() {
                    self.directives.flags |= DIRECTIVE_FLAG_STOP;
                    self.event(now_ns, Event::OperatorStop { restored: false });
                }
                return;
            }
            COMMAND_RESUME => {
                if !self.stopped() {
                    return refused(self, COMMAND_REFUSED_NOT_STOPPED);
                }
                self.directives.flags &= !DIRECTIVE_FLAG_STOP;
                return self.event(now_ns, Event::OperatorResume);
            }
            _ => return refused(self, COMMAND_REFUSED_UNKNOWN_KIND),
        }
        let b = cmd.bus as usize;
        let Some(bus) = self.buses.get_mut(b) else {
            return refused(self, COMMAND_REFUSED_NO_SUCH_BUS);
        };
        if !bus.tripped {
            return refused(self, COMMAND_REFUSED_NOT_TRIPPED);
        }
        match bus.reenable(&self.config.thermal, now_ns as f64 * 1e-9) {
            Ok(()) => {
                self.directives.bus_enabled |= 1 << b;
                self.event(now_ns, Event::BusReenabled { bus: cmd.bus });
            }
            Err(hottest_c) => self.event(
                now_ns,
                Event::ReenableRefused {
                    bus: cmd.bus,
                    hottest_c,
                },
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use telemetry::config::ProcessConfig;
    use telemetry::frames::{EventKind, JointInfo};

    use telemetry::clock::MS;

    /// Two buses: bus 0 an arm joint (STS3250) and a gripper, bus 1 one joint.
    fn layout() -> JointLayout {
        let mut l = JointLayout {
            joint_count: 3,
            bus_count: 2,
            ..JointLayout::default()
        };
        let mut j = |i: usize, name: &str, bus: u8, role: JointRole, model: u16| {
            let mut info = JointInfo {
                bus,
                role: role as u8,
                model,
                max_temperature_c: 60,
                ..JointInfo::default()
            };
            info.set_name(name);
            l.joints[i] = info;
        };
        j(0, "left_wrist_pitch", 0, JointRole::Joint, 2825);
        j(1, "left_gripper", 0, JointRole::Gripper, 777);
        j(2, "right_elbow", 1, JointRole::Joint, 2569);
        l
    }

    fn state(seq: u64, t_ns: u64, f: impl Fn(usize, &mut JointSample)) -> JointState {
        let mut s = JointState {
            seq,
            timestamp_ns: t_ns,
            joint_count: 3,
            ..JointState::default()
        };
        for (i, j) in s.joints[..3].iter_mut().enumerate() {
            *j = JointSample {
                valid: 1,
                torque_enabled: 1,
                temperature_c: 30.0,
                ..JointSample::default()
            };
            f(i, j);
        }
        s
    }

    fn kinds(sup: &mut Supervisor) -> Vec<EventKind> {
        sup.drain_events().filter_map(|e| e.kind()).collect()
    }

    #[test]
    fn a_trip_survives_a_restart_until_the_operator_releases_it() {
        let config = || SupervisorConfig::embedded().unwrap();
        let at = |temperature: f32, k: u64| {
            state(k, k * 5 * MS, move |i, j| {
                if i == 0 {
                    j.temperature_c = temperature
                }
            })
        };
        let mut first = Supervisor::new(&layout(), config()).unwrap();
        first.on_state(&at(59.0, 1));
        assert!(first.bus_tripped(0));
        let record = first.tripped_joints();
        assert_eq!(record, ["left_wrist_pitch", "left_gripper"]);

        // A new instance (a crash and restart): the bus comes up latched although the motor has
        // cooled below the trip, and stays so until an explicit command is granted.
        let mut second = Supervisor::new(&layout(), config()).unwrap();
        assert_eq!(second.restore_trips(&record, 0), [0]);
        for k in 0..50 {
            second.on_state(&at(55.0, k));
        }
        assert_eq!(second.directives(0).bus_enabled & 0b11, 0b10, "latched");
        assert!(second
            .restore_trips(&["no_such_joint".into()], 0)
            .is_empty());
        for k in 50..100 {
            second.on_state(&at(45.0, k));
        }
        let cmd = SupervisorCommand {
            kind: COMMAND_REENABLE_BUS,
            bus: 0,
            ..SupervisorCommand::default()
        };
        second.command(&cmd, 0);
        assert_eq!(second.directives(0).bus_enabled & 0b11, 0b11);
        assert!(second.tripped_joints().is_empty());
    }

    #[test]
    fn an_overheating_motor_disables_its_whole_bus_before_the_firmware_cutoff() {
        let mut sup = Supervisor::new(&layout(), SupervisorConfig::embedded().unwrap()).unwrap();
        let mut temperature = 40.0f32;
        let mut tripped_at = None;
        let mut first_warning_at = None;
        for k in 0..200_000u64 {
            // Joint 0 heats 1 °C per 10 s of a mock clock at 200 Hz.
            let t = k * 5 * MS;
            temperature = (40.0 + (k as f32 * 0.005) / 10.0).floor();
            let s = state(k, t, |i, j| {
                if i == 0 {
                    j.temperature_c = temperature
                }
            });
            sup.on_state(&s);
            if first_warning_at.is_none()
                && sup
                    .events
                    .iter()
                    .any(|e| e.kind() == Some(EventKind::ThermalWarning))
            {
                first_warning_at = Some(temperature);
            }
            let d = sup.directives(t);
            if d.bus_enabled & 1 == 0 {
                tripped_at = Some(temperature);
                assert_eq!(d.bus_enabled & 2, 2, "only the hot motor's bus is disabled");
                break;
            }
        }
        assert_eq!(tripped_at, Some(59.0), "software trip at 59 °C");
        // The frames' nanoseconds are read as seconds: the trajectory warns before the first
        // temperature level (50 °C) does.
        assert!(
            first_warning_at.is_some_and(|t| t < 50.0),
            "first warning at {first_warning_at:?} °C"
        );
        assert!(temperature < 60.0, "before the 60 °C firmware cutoff");
        let events = kinds(&mut sup);
        assert_eq!(events.last(), Some(&EventKind::ThermalTrip));
        assert!(events.contains(&EventKind::ThermalWarning));
        // Latched: cooling alone does not re-enable, an explicit command does (after cooling).
        let cmd = SupervisorCommand {
            kind: COMMAND_REENABLE_BUS,
            bus: 0,
            ..SupervisorCommand::default()
        };
        sup.command(&cmd, 0);
        assert_eq!(kinds(&mut sup), [EventKind::ReenableRefused]);
        // Commands that cannot be carried out are answered with their reason.
        for (bad, why) in [
            (
                SupervisorCommand { kind: 99, ..cmd },
                COMMAND_REFUSED_UNKNOWN_KIND,
            ),
            (
                SupervisorCommand { bus: 7, ..cmd },
                COMMAND_REFUSED_NO_SUCH_BUS,
            ),
            (
                SupervisorCommand { bus: 1, ..cmd },
                COMMAND_REFUSED_NOT_TRIPPED,
            ),
        ] {
            sup.command(&bad, 0);
            let e = sup.drain_events().next_back().unwrap();
            assert_eq!((e.kind(), e.level), (Some(EventKind::CommandRefused), why));
        }
        assert_eq!(sup.directives(0).bus_enabled & 1, 0, "still latched");
        for k in 0..100 {
            sup.on_state(&state(k, (1000 + k) * 5 * MS, |_, j| {
                j.temperature_c = 45.0
            }));
            assert_eq!(sup.directives(0).bus_enabled & 1, 0, "still latched");
        }
        kinds(&mut sup);
        sup.command(&cmd, 0);
        assert_eq!(kinds(&mut sup), [EventKind::BusReenabled]);
        assert_eq!(sup.directives(0).bus_enabled & 3, 3);
    }

    #[test]
    fn a_stalled_joint_is_retried_then_reduced_and_a_gripper_holds_gently() {
        let mut sup = Supervisor::new(&layout(), SupervisorConfig::embedded().unwrap()).unwrap();
        // Joint 0 pushes into an obstacle; the gripper squeezes an object.
        let pushing = |i: usize, j: &mut JointSample| {
            if i < 2 {
                j.position_rad = 0.3;
                j.goal_rad = 0.8;
                j.current_a = 2.0;
            }
        };
        for k in 0..15 {
            sup.on_state(&state(k, k * 5 * MS, pushing));
        }
        let d = sup.directives(0);
        assert_eq!(
            d.torque_limit_permille[0], 0,
            "first stall: retry at full torque"
        );
        assert_eq!(
            d.torque_limit_permille[1], 250,
            "gripper: reduced grip torque"
        );
        assert_eq!(
            kinds(&mut sup),
            [
                EventKind::Stall,
                EventKind::StallRetry,
                EventKind::Stall,
                EventKind::TorqueReduced
            ]
        );
        for k in 15..30 {
            sup.on_state(&state(k, k * 5 * MS, pushing));
        }
        assert_eq!(
            sup.directives(0).torque_limit_permille[0],
            300,
            "stalled again: reduced"
        );
        assert_eq!(kinds(&mut sup), [EventKind::TorqueReduced]);
        // A new target restores the torque.
        sup.on_state(&state(31, 31 * 5 * MS, |i, j| {
            pushing(i, j);
            j.goal_rad = -0.5;
        }));
        assert_eq!(sup.directives(0).torque_limit_permille[0], 0);
        assert!(kinds(&mut sup).contains(&EventKind::TorqueRestored));
    }

    #[test]
    fn grip_force_rises_with_current_beside_the_raw_reading() {
        let mut sup = Supervisor::new(&layout(), SupervisorConfig::embedded().unwrap()).unwrap();
        let mut last = -1.0;
        for k in 0..50 {
            let current = k as f32 * 0.02;
            sup.on_state(&state(k, k * 5 * MS, |i, j| {
                if i == 1 {
                    j.current_a = current
                }
            }));
            let g = sup.grip().grippers[0];
            assert_eq!((g.joint, g.current_a), (1, current));
            assert!(g.force >= last && (0.0..=1.0).contains(&g.force));
            last = g.force;
        }
        assert_eq!(last, 1.0);
    }

    #[test]
    fn an_inferred_firmware_cutoff_disables_the_bus() {
        let mut sup = Supervisor::new(&layout(), SupervisorConfig::embedded().unwrap()).unwrap();
        sup.on_state(&state(1, 0, |i, j| {
            if i == 2 {
                j.flags = JOINT_FLAG_OUTPUT_LOST;
                j.temperature_c = 58.0
            }
        }));
        assert_eq!(sup.directives(0).bus_enabled & 3, 1, "bus 1 disabled");
        assert_eq!(
            kinds(&mut sup)[..2],
            [EventKind::OutputLost, EventKind::ThermalTrip]
        );
    }

    #[test]
    fn a_gripper_without_calibration_is_refused() {
        let mut config = SupervisorConfig::embedded().unwrap();
        config.grip.clear();
        assert!(matches!(
            Supervisor::new(&layout(), config),
            Err(LayoutError::NoGripCalibration(_))
        ));
    }

    #[test]
    fn a_trip_not_below_a_published_firmware_cutoff_is_refused() {
        let mut l = layout();
        // The driver publishes a cutoff of 55 °C for one motor: a 59 °C trip would come after.
        l.joints[2].max_temperature_c = 55;
        match Supervisor::new(&l, SupervisorConfig::embedded().unwrap()) {
            Err(LayoutError::TripNotBelowCutoff {
                joint, cutoff_c, ..
            }) => {
                assert_eq!((joint.as_str(), cutoff_c), ("right_elbow", 55))
            }
            other => panic!("accepted: {:?}", other.map(|_| ())),
        }
        // 60 °C leaves the 1 °C the paper's ordering needs; 59.5 does not.
        l.joints[2].max_temperature_c = 60;
        assert!(Supervisor::new(&l, SupervisorConfig::embedded().unwrap()).is_ok());
        let mut config = SupervisorConfig::embedded().unwrap();
        config.thermal.trip_c = 59.5;
        assert!(Supervisor::new(&l, config).is_err());
    }

    #[test]
    fn a_firmware_protection_bit_disables_the_bus_once_confirmed() {
        for bit in [0x04u8, 0x08, 0x20] {
            let mut sup =
                Supervisor::new(&layout(), SupervisorConfig::embedded().unwrap()).unwrap();
            let with_bit = |k: u64| {
                state(k, k * 5 * MS, move |i, j| {
                    if i == 2 {
                        j.status = bit;
                        j.temperature_c = 52.0;
                    }
                })
            };
            // One frame with the bit (a corrupted reply can carry one): nothing yet.
            sup.on_state(&with_bit(1));
            assert_eq!(
                sup.directives(0).bus_enabled & 3,
                3,
                "bit {bit:#x}: one frame"
            );
            sup.on_state(&state(2, 10 * MS, |_, _| {}));
            sup.on_state(&with_bit(3));
            assert_eq!(
                sup.directives(0).bus_enabled & 3,
                3,
                "bit {bit:#x}: not in a row"
            );
            sup.on_state(&with_bit(4));
            assert_eq!(
                sup.directives(0).bus_enabled & 3,
                1,
                "bit {bit:#x}: bus 1 off"
            );
            let events: Vec<SupervisorEvent> = sup.drain_events().collect();
            let e = events
                .iter()
                .find(|e| e.kind() == Some(EventKind::FirmwareProtection))
                .expect("reported");
            assert_eq!((e.level, e.joint, e.bus, e.value), (bit, 2, 1, 52.0));
            let at = |k| events.iter().position(|e| e.kind() == Some(k));
            assert!(at(EventKind::FirmwareProtection) < at(EventKind::ThermalTrip));
            assert_eq!(
                sup.tripped_joints(),
                ["right_elbow"],
                "latched and recorded"
            );
            sup.on_state(&with_bit(5));
            assert!(kinds(&mut sup).is_empty(), "reported once");
        }
        // The voltage and angle-sensor bits are not protections that unload the motor.
        let mut sup = Supervisor::new(&layout(), SupervisorConfig::embedded().unwrap()).unwrap();
        for k in 0..10 {
            sup.on_state(&state(k, k * 5 * MS, |_, j| j.status = 0x03));
        }
        assert_eq!(sup.directives(0).bus_enabled & 3, 3);
    }

    #[test]
    fn the_drivers_own_trip_becomes_the_supervisors_latch() {
        let mut sup = Supervisor::new(&layout(), SupervisorConfig::embedded().unwrap()).unwrap();
        sup.on_state(&state(1, 0, |i, j| {
            if i == 2 {
                j.flags = JOINT_FLAG_DRIVER_TRIP | telemetry::frames::JOINT_FLAG_BUS_DISABLED;
                j.temperature_c = 59.0;
            } else if i < 2 {
                j.temperature_c = 58.0;
            }
        }));
        assert_eq!(
            sup.directives(0).bus_enabled & 3,
            1,
            "bus 1 off in the directives"
        );
        assert_eq!(
            kinds(&mut sup)[..2],
            [EventKind::DriverTrip, EventKind::ThermalTrip]
        );
        assert_eq!(sup.tripped_joints(), ["right_elbow"]);
    }

    /// What the process around the state machine relies on: the layout it was made for (a
    /// different one makes a new supervisor), the trips as a bus mask (recorded when it
    /// changes), whether the directives changed (published at once), rising sequence numbers.
    #[test]
    fn the_process_facing_accessors_say_what_happened() {
        let mut sup = Supervisor::new(&layout(), SupervisorConfig::embedded().unwrap()).unwrap();
        assert_eq!(*sup.layout(), layout());
        assert_eq!(sup.tripped_buses(), 0);
        let first = sup.directives(1);
        assert!(!sup.directives_changed());
        sup.on_state(&state(1, 5 * MS, |i, j| {
            if i == 2 {
                j.temperature_c = 59.0
            }
        }));
        assert!(sup.directives_changed(), "a trip changes the directives");
        assert_eq!(sup.tripped_buses(), 0b10);
        let second = sup.directives(2);
        assert!(second.seq > first.seq);
        assert!(!sup.directives_changed(), "handed out");
        // Both buses tripped: both bits.
        sup.on_state(&state(2, 10 * MS, |_, j| j.temperature_c = 59.0));
        assert_eq!(sup.tripped_buses(), 0b11);
        let events: Vec<SupervisorEvent> = sup.drain_events().collect();
        assert!(events.len() >= 2 && events[0].seq >= 1);
        assert!(events.windows(2).all(|w| w[1].seq > w[0].seq), "{events:?}");
    }

    /// A restored latch is in the directives at once, before any frame is judged (a
    /// supervisor that restarts with the driver down must not announce the bus as on).
    #[test]
    fn restored_trips_are_in_the_first_directives() {
        let mut sup = Supervisor::new(&layout(), SupervisorConfig::embedded().unwrap()).unwrap();
        assert_eq!(sup.restore_trips(&["right_elbow".into()], 0), [1]);
        assert_eq!(sup.directives(0).bus_enabled & 0b11, 0b01);
        let mut both = Supervisor::new(&layout(), SupervisorConfig::embedded().unwrap()).unwrap();
        both.restore_trips(&["left_gripper".into(), "right_elbow".into()], 0);
        assert_eq!(both.directives(0).bus_enabled & 0b11, 0);
        assert_eq!(both.tripped_buses(), 0b11);
    }

    /// The re-enable of bus 1, judged at the robot's own time: granted on fresh cool readings,
    /// refused when the newest reading of a motor is more than a second old.
    #[test]
    fn a_reenable_is_judged_on_fresh_readings_of_its_own_bus() {
        let mut sup = Supervisor::new(&layout(), SupervisorConfig::embedded().unwrap()).unwrap();
        let at = |k: u64, t: f32| state(k, k * 5 * MS, move |_, j| j.temperature_c = t);
        sup.on_state(&at(1, 59.0));
        for k in 2..40 {
            sup.on_state(&at(k, 45.0));
        }
        let cmd = SupervisorCommand {
            kind: COMMAND_REENABLE_BUS,
            bus: 1,
            ..SupervisorCommand::default()
        };
        // Two seconds after the last reading: stale.
        sup.command(&cmd, 39 * 5 * MS + 2_000 * MS);
        assert_eq!(kinds(&mut sup).last(), Some(&EventKind::ReenableRefused));
        assert_eq!(sup.directives(0).bus_enabled & 0b10, 0);
        sup.command(&cmd, 39 * 5 * MS + 10 * MS);
        assert_eq!(kinds(&mut sup).last(), Some(&EventKind::BusReenabled));
        assert_eq!(sup.directives(0).bus_enabled & 0b10, 0b10, "bus 1 back on");
        assert_eq!(sup.tripped_buses() & 0b10, 0);
    }

    #[test]
    fn a_torque_reduction_event_carries_the_limit_in_percent() {
        let mut sup = Supervisor::new(&layout(), SupervisorConfig::embedded().unwrap()).unwrap();
        for k in 0..15 {
            sup.on_state(&state(k, k * 5 * MS, |i, j| {
                if i == 1 {
                    j.position_rad = 0.3;
                    j.goal_rad = 0.8;
                    j.current_a = 2.0;
                }
            }));
        }
        let e = sup
            .drain_events()
            .find(|e| e.kind() == Some(EventKind::TorqueReduced))
            .unwrap();
        assert_eq!((e.joint, e.value), (1, 25.0));
    }
}
