//! The host's end of a simulated bus in memory, shared by the commissioning tests.

#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use bus_driver::transport::{Transport, TransportError};
use commission::calibrate::Stops;
use commission::scan::Plan;
use commission::session::JointToCalibrate;
use sim::{RobotDescription, SimBus};
use std::cell::RefCell;
use std::collections::VecDeque;
use std::time::Duration;

/// The host's end of a simulated bus, opened at a rate.
pub struct Line<'a> {
    bus: &'a RefCell<SimBus>,
    inbox: VecDeque<u8>,
    baud: u32,
}

impl Transport for Line<'_> {
    fn baud(&self) -> u32 {
        self.baud
    }
    fn send(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        let mut bus = self.bus.borrow_mut();
        let t = bus.time();
        bus.receive(t, bytes);
        Ok(())
    }
    fn receive(&mut self, buf: &mut [u8], _timeout: Duration) -> Result<usize, TransportError> {
        while let Some(r) = self.bus.borrow_mut().pop_due(f64::MAX) {
            self.inbox.extend(r.bytes);
        }
        let n = buf.len().min(self.inbox.len());
        for (b, v) in buf.iter_mut().zip(self.inbox.drain(..n)) {
            *b = v;
        }
        Ok(n)
    }
    fn set_baud(&mut self, baud: u32) -> Result<(), TransportError> {
        self.bus.borrow_mut().set_host_baud(baud);
        self.baud = baud;
        Ok(())
    }
    fn discard_input(&mut self) -> Result<(), TransportError> {
        self.inbox.clear();
        Ok(())
    }
}

pub fn left_arm() -> SimBus {
    let d = RobotDescription::nori_a3();
    SimBus::new(&d, d.bus("left_arm").unwrap())
}

/// Ids 0–12 at the bus's rate and at 57 600 baud (a whole scan is every id at eight rates;
/// the in-memory line makes these few enough for a unit test).
pub fn plan() -> Plan {
    Plan {
        ids: 0..=12,
        expected: (1..=8).collect(),
        rates: vec![1_000_000, 57_600],
        window: Duration::from_micros(600),
        attempts: 3,
    }
}

/// The host's end of `bus`, opened at its description's rate.
pub fn line(bus: &RefCell<SimBus>) -> Line<'_> {
    let baud = bus.borrow().baud;
    bus.borrow_mut().set_host_baud(baud);
    Line {
        bus,
        inbox: VecDeque::new(),
        baud,
    }
}

/// The left arm as the driver leaves it at its first start: each servo's EEPROM as the driver
/// writes it (backstops) and the calibration left it (homing offset, limits), locked.
pub fn as_set_up_by_the_driver(mut bus: SimBus) -> SimBus {
    use telemetry::config::ProcessConfig;
    let loaded = bus_driver::LoadedConfig::embedded().unwrap();
    let config = loaded.config.bus(&bus.name).unwrap();
    for s in &config.servo {
        let backstops = &loaded.config.backstops[&s.model];
        let calibration = loaded.calibration_for(config, &s.joint);
        let servo = bus.servo_mut(s.id).unwrap();
        assert!(servo.write(feetech::registers::LOCK.addr, &[0]));
        let calibrated = calibration
            .as_ref()
            .map(bus_driver::backstops::calibration_settings);
        let wanted = bus_driver::backstops::desired(backstops, config.mode);
        for want in wanted.into_iter().chain(calibrated.into_iter().flatten()) {
            let raw = bus_driver::bus::encode(want.register, want.value)
                .unwrap()
                .to_le_bytes();
            assert!(servo.write(want.register.addr, &raw[..usize::from(want.register.size)]));
        }
        assert!(servo.write(feetech::registers::LOCK.addr, &[1]));
    }
    bus
}

/// The left arm's joints and gripper, with their stops from the description.
pub fn targets(robot: &RobotDescription) -> Vec<JointToCalibrate> {
    let d = robot.bus("left_arm").unwrap();
    let arm = d.arm.as_ref().unwrap();
    let name = |id: u8| d.servo.iter().find(|s| s.id == id).unwrap().joint.clone();
    let model = |id: u8| {
        let key = &d.servo.iter().find(|s| s.id == id).unwrap().model;
        feetech::ServoModel::from_key(key).unwrap()
    };
    let mut t: Vec<JointToCalibrate> = arm
        .joint
        .iter()
        .map(|j| JointToCalibrate {
            joint: name(j.servo),
            id: j.servo,
            model: model(j.servo),
            stops: Stops {
                lower_rad: j.lower_rad,
                upper_rad: j.upper_rad,
                inverted: false,
            },
        })
        .collect();
    let g = arm.gripper.as_ref().unwrap();
    t.push(JointToCalibrate {
        joint: name(g.servo),
        id: g.servo,
        model: model(g.servo),
        stops: Stops {
            lower_rad: g.lower_rad,
            upper_rad: g.upper_rad,
            inverted: false,
        },
    });
    t
}
