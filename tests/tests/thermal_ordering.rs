//! The two thermal tiers in closed loop, on simulated time (no processes, no sleeping): the
//! simulated left arm in batch mode, the supervisor's logic fed a joint-state frame every 5 ms,
//! its bus-disable directive applied as the driver applies it (broadcast torque off). In every
//! set-up the software trip must come first: no firmware cutoff, no winding at 60 °C.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use feetech::registers as reg;
use sim::scenario::SCENARIO_BUS;
use sim::{RobotDescription, SimBus};
use supervisor::{Supervisor, SupervisorConfig};
use telemetry::config::ProcessConfig;
use telemetry::frames::{JointInfo, JointLayout, JointRole};
use telemetry::{JointSample, JointState};

const STEP: f64 = 0.001;
const FRAME_EVERY: usize = 5;

struct Setup {
    name: &'static str,
    payload_kg: f64,
    ambient_c: f64,
    goals: &'static [(u8, f64)],
    thermal_speedup: f64,
}

struct Outcome {
    tripped_at_s: Option<f64>,
    max_winding_c: f64,
    cutoffs: u64,
}

fn write_u16(bus: &mut SimBus, id: u8, r: feetech::Register, v: u16) {
    let bytes = v.to_le_bytes();
    bus.servo_mut(id)
        .unwrap()
        .write(r.addr, &bytes[..r.size as usize]);
}

fn run(setup: &Setup) -> Outcome {
    let mut d = RobotDescription::nori_a3();
    d.ambient_c = setup.ambient_c;
    let desc = d.bus.iter_mut().find(|b| b.name == SCENARIO_BUS).unwrap();
    desc.arm.as_mut().unwrap().payload_kg = setup.payload_kg;
    let mut bus = SimBus::new(&d, d.bus(SCENARIO_BUS).unwrap());
    bus.thermal_speedup = setup.thermal_speedup;
    let ids: Vec<u8> = bus.servos.iter().map(|s| s.id).collect();
    // As the driver sets the servos up (deploy/config/bus-driver.toml).
    for &id in &ids {
        let amps = match bus.servo_mut(id).unwrap().model {
            feetech::ServoModel::Sts3095 => 8.0,
            feetech::ServoModel::Sts3250 => 3.2,
            feetech::ServoModel::Sts3215 => 2.0,
        };
        write_u16(&mut bus, id, reg::LOCK, 0);
        write_u16(&mut bus, id, reg::MAX_TEMPERATURE_LIMIT, 60);
        write_u16(
            &mut bus,
            id,
            reg::PROTECTION_CURRENT,
            (amps / feetech::AMPS_PER_CURRENT_UNIT) as u16,
        );
        write_u16(&mut bus, id, reg::OVER_CURRENT_PROTECTION_TIME, 100);
        write_u16(&mut bus, id, reg::TORQUE_LIMIT, 800);
        write_u16(&mut bus, id, reg::TORQUE_ENABLE, 1);
    }
    for &(id, rad) in setup.goals {
        let steps = (2048.0 + rad * 4096.0 / std::f64::consts::TAU).round() as u16;
        write_u16(&mut bus, id, reg::GOAL_POSITION, steps);
    }
    let mut layout = JointLayout {
        joint_count: ids.len() as u32,
        bus_count: 1,
        ..JointLayout::default()
    };
    for (i, s) in bus.servos.iter().enumerate() {
        let mut info = JointInfo {
            role: if i == 7 {
                JointRole::Gripper as u8
            } else {
                JointRole::Joint as u8
            },
            model: s.model.model_number(),
            id: s.id,
            max_temperature_c: 60,
            ..JointInfo::default()
        };
        info.set_name(if i == 7 { "left_gripper" } else { "joint" });
        layout.joints[i] = info;
    }
    let mut sup = Supervisor::new(&layout, SupervisorConfig::embedded().unwrap()).unwrap();
    let mut tripped_at_s = None;
    let mut step = 0usize;
    // Long enough to reach 59 °C in every set-up, and 30 s more after the trip.
    while bus.time() < 120.0 && tripped_at_s.is_none_or(|t| bus.time() < t + 30.0) {
        bus.step(STEP);
        step += 1;
        if !step.is_multiple_of(FRAME_EVERY) {
            continue;
        }
        let mut state = JointState {
            seq: step as u64,
            timestamp_ns: (bus.time() * 1e9) as u64,
            joint_count: ids.len() as u32,
            ..JointState::default()
        };
        for (i, s) in bus.servos.iter_mut().enumerate() {
            let mut fb = [0u8; 15];
            s.read(reg::FEEDBACK_ADDR, 15, &mut fb);
            let f = feetech::FeedbackBlock::parse(&fb).unwrap();
            state.joints[i] = JointSample {
                position_rad: ((f64::from(f.position) - 2048.0) / 651.9) as f32,
                current_a: (f64::from(f.current) * feetech::AMPS_PER_CURRENT_UNIT) as f32,
                temperature_c: f32::from(f.temperature),
                goal_rad: ((f64::from(s.get(reg::GOAL_POSITION)) - 2048.0) / 651.9) as f32,
                load: f.load as f32 / 1000.0,
                valid: 1,
                torque_enabled: u8::from(s.torque_enabled()),
                ..JointSample::default()
            };
        }
        sup.on_state(&state);
        let directives = sup.directives(state.timestamp_ns);
        if directives.bus_enabled & 1 == 0 && tripped_at_s.is_none() {
            tripped_at_s = Some(bus.time());
            // The driver's reaction: broadcast torque off.
            for s in &mut bus.servos {
                s.write(reg::TORQUE_ENABLE.addr, &[0]);
            }
        }
    }
    Outcome {
        tripped_at_s,
        max_winding_c: bus
            .servos
            .iter()
            .map(|s| s.max_temperature)
            .fold(f64::MIN, f64::max),
        cutoffs: bus.servos.iter().map(|s| s.log.hardware_cutoffs).sum(),
    }
}

#[test]
fn in_every_thermal_setup_the_software_trip_comes_first_and_nothing_reaches_60_c() {
    const HALF_PI: f64 = std::f64::consts::FRAC_PI_2;
    let setups = [
        Setup {
            name: "shoulder holds 0.3 kg",
            payload_kg: 0.3,
            ambient_c: 25.0,
            goals: &[(1, HALF_PI)],
            thermal_speedup: 120.0,
        },
        Setup {
            name: "hot room, 40 °C",
            payload_kg: 0.3,
            ambient_c: 40.0,
            goals: &[(1, HALF_PI)],
            thermal_speedup: 120.0,
        },
        Setup {
            name: "lighter load, slower heating",
            payload_kg: 0.2,
            ambient_c: 35.0,
            goals: &[(1, HALF_PI)],
            thermal_speedup: 120.0,
        },
        Setup {
            name: "elbow holds the rated 1.5 kg level",
            payload_kg: 1.5,
            ambient_c: 30.0,
            goals: &[(4, -HALF_PI)],
            thermal_speedup: 120.0,
        },
        Setup {
            name: "fast heating (speed-up 600)",
            payload_kg: 0.3,
            ambient_c: 25.0,
            goals: &[(1, HALF_PI)],
            thermal_speedup: 600.0,
        },
    ];
    for setup in &setups {
        let o = run(setup);
        assert!(
            o.tripped_at_s.is_some(),
            "{}: no software trip (hottest {:.1} °C)",
            setup.name,
            o.max_winding_c
        );
        assert_eq!(o.cutoffs, 0, "{}: the firmware cutoff fired", setup.name);
        assert!(
            o.max_winding_c < 60.0,
            "{}: a winding reached {:.2} °C",
            setup.name,
            o.max_winding_c
        );
    }
}
