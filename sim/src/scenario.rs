//! Physical set-ups for the protection scenarios: what is on the table, in the hand or in the
//! way. The goals that drive the robot into them belong to the scenario runner (`nori sim
//! scenario`); here is only the world.

use crate::description::{GraspObject, Obstacle, RobotDescription};

/// A named set-up of the left arm.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Scenario {
    /// A 0.3 kg payload at the tool: held horizontal (5.3 N·m with the arm's own 3.7 N·m), the
    /// shoulder draws ~6 A, below its 8 A over-current backstop, and heats toward the limit in
    /// about ten minutes.
    Overheat,
    /// A sphere in the tool's path when the shoulder pitches forward.
    Stall,
    /// A soft object between the gripper's fingers, first contact at 0.55 rad.
    Grip,
}

/// The bus all scenarios use.
pub const SCENARIO_BUS: &str = "left_arm";
/// Gripper angle at first contact with the grip scenario's object, rad.
pub const GRIP_CONTACT_RAD: f64 = 0.55;

impl Scenario {
    /// Applies the set-up to a description.
    pub fn apply(self, d: &mut RobotDescription) {
        let Some(arm) = d
            .bus
            .iter_mut()
            .find(|b| b.name == SCENARIO_BUS)
            .and_then(|b| b.arm.as_mut())
        else {
            return;
        };
        match self {
            Scenario::Overheat => arm.payload_kg = 0.3,
            Scenario::Stall => {
                // The tool swings on a 0.55 m circle about the shoulder (y axis) toward −x as the
                // shoulder pitch rises; the sphere sits on that circle at 0.6 rad.
                let reach = 0.55;
                let (s, c) = 0.6f64.sin_cos();
                arm.obstacle.push(Obstacle {
                    center: [
                        arm.base[0] - reach * s,
                        arm.base[1],
                        arm.base[2] - reach * c,
                    ],
                    radius_m: 0.05,
                    stiffness_n_per_m: 20_000.0,
                });
            }
            Scenario::Grip => {
                if let Some(g) = arm.gripper.as_mut() {
                    g.object = Some(GraspObject {
                        contact_rad: GRIP_CONTACT_RAD,
                        stiffness_nm_per_rad: 20.0,
                    });
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bus::SimBus;
    use feetech::registers as reg;

    fn bus(s: Scenario) -> SimBus {
        let mut d = RobotDescription::nori_a3();
        s.apply(&mut d);
        let mut b = SimBus::new(&d, d.bus(SCENARIO_BUS).unwrap());
        // As the driver sets them up (deploy/config/bus-driver.toml backstops).
        for servo in &mut b.servos {
            let amps = match servo.model {
                feetech::ServoModel::Sts3095 => 8.0,
                feetech::ServoModel::Sts3250 => 3.2,
                feetech::ServoModel::Sts3215 => 2.0,
            };
            let units = (amps / feetech::AMPS_PER_CURRENT_UNIT) as u16;
            servo.write(reg::LOCK.addr, &[0]);
            servo.write(reg::PROTECTION_CURRENT.addr, &units.to_le_bytes());
            servo.write(reg::OVER_CURRENT_PROTECTION_TIME.addr, &[100]);
            servo.write(reg::TORQUE_LIMIT.addr, &800u16.to_le_bytes());
            servo.write(reg::TORQUE_ENABLE.addr, &[1]);
        }
        b
    }

    fn goal(b: &mut SimBus, id: u8, rad: f64) {
        let steps = (2048.0 + rad * 4096.0 / std::f64::consts::TAU).round() as u16;
        b.servo_mut(id)
            .unwrap()
            .write(reg::GOAL_POSITION.addr, &steps.to_le_bytes());
    }

    #[test]
    fn the_stall_obstacle_stops_the_shoulder_short_of_its_goal() {
        let mut b = bus(Scenario::Stall);
        goal(&mut b, 1, 1.2);
        // Before the 1 s over-current backstop would act (the supervisor acts in ~0.15 s).
        b.advance_to(0.8, 0.001);
        let s = b.servo_mut(1).unwrap();
        assert!(s.angle > 0.3 && s.angle < 0.6, "stopped at {}", s.angle);
        assert!(s.current.abs() > 3.0, "pushing with {} A", s.current);
    }

    #[test]
    fn the_grip_object_resists_closing() {
        let mut b = bus(Scenario::Grip);
        goal(&mut b, 8, 0.05);
        b.advance_to(3.0, 0.001);
        let s = b.servo_mut(8).unwrap();
        assert!(s.angle < 0.55 && s.angle > 0.05, "squeezed to {}", s.angle);
        assert!(s.current.abs() > 0.5, "squeezing with {} A", s.current);
    }

    #[test]
    fn the_overheat_payload_loads_the_shoulder_below_its_protection() {
        let mut b = bus(Scenario::Overheat);
        goal(&mut b, 1, std::f64::consts::FRAC_PI_2);
        b.advance_to(4.0, 0.001);
        let s = b.servo_mut(1).unwrap();
        assert!(
            s.current.abs() > 4.0 && s.current.abs() < 8.0,
            "holding with {} A",
            s.current
        );
    }
}
