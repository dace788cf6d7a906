//! An operator's hand on a simulated arm, for calibration by hand: it takes each joint whose
//! servo has its torque off, one after another in the arm's order (the gripper last), from
//! where it rests to its lower stop, then to its upper stop, and lets it go. It moves at a
//! hand's pace and pushes with a hand's force through the arm's own mechanics: against gravity,
//! and pressed into each stop as an operator presses, so the stop's give shows in the readings
//! as it would on the robot. A joint whose torque is on is waited for, as an operator waits.

/// How fast the hand leads a joint, rad/s.
const SPEED_RAD_S: f64 = 0.8;
/// The hand's grip: torque per radian the joint lags where the hand leads it, N·m/rad ...
const STIFFNESS_NM_PER_RAD: f64 = 30.0;
/// ... its damping, N·m·s/rad ...
const DAMPING_NMS_PER_RAD: f64 = 1.0;
/// ... and the most it pushes with, N·m.
const MAX_TORQUE_NM: f64 = 4.0;
/// How far past a stop the hand leads: it presses the joint into the stop.
const PAST_STOP_RAD: f64 = 0.1;
/// How long it holds a joint against a stop before moving on, s.
const DWELL_S: f64 = 0.4;

/// One joint the hand sweeps: its servo's place on the bus and its stops, rad.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HandJoint {
    /// The servo's index on its bus.
    pub servo: usize,
    /// The lower stop, rad.
    pub lower_rad: f64,
    /// The upper stop, rad.
    pub upper_rad: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    ToLower,
    ToUpper,
}

/// What a joint's servo tells the hand.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Feel {
    /// The joint's angle, rad.
    pub angle_rad: f64,
    /// Its speed, rad/s.
    pub speed_rad_s: f64,
    /// Whether its motor holds it (the hand waits).
    pub torque_on: bool,
}

/// The hand.
#[derive(Debug, Clone, PartialEq)]
pub struct Hand {
    joints: Vec<HandJoint>,
    current: usize,
    phase: Phase,
    /// Where the hand leads the current joint, rad (taken from the joint when it starts).
    target: Option<f64>,
    held_s: f64,
}

impl Hand {
    /// A hand that will sweep `joints` in this order.
    pub fn new(joints: Vec<HandJoint>) -> Hand {
        Hand {
            joints,
            current: 0,
            phase: Phase::ToLower,
            target: None,
            held_s: 0.0,
        }
    }

    /// Whether every joint has been swept.
    pub fn done(&self) -> bool {
        self.current >= self.joints.len()
    }

    /// The joint being swept and the torque the hand puts on it this step (N·m, positive
    /// toward positive angles); `None` when done or waiting for the joint's torque to go off.
    pub fn push(&mut self, dt: f64, feel: impl Fn(usize) -> Feel) -> Option<(usize, f64)> {
        let joint = *self.joints.get(self.current)?;
        let f = feel(joint.servo);
        if f.torque_on {
            return None;
        }
        let goal = match self.phase {
            Phase::ToLower => joint.lower_rad - PAST_STOP_RAD,
            Phase::ToUpper => joint.upper_rad + PAST_STOP_RAD,
        };
        let target = self.target.get_or_insert(f.angle_rad);
        let step = SPEED_RAD_S * dt;
        *target += (goal - *target).clamp(-step, step);
        let torque = (STIFFNESS_NM_PER_RAD * (*target - f.angle_rad)
            - DAMPING_NMS_PER_RAD * f.speed_rad_s)
            .clamp(-MAX_TORQUE_NM, MAX_TORQUE_NM);
        if *target == goal {
            self.held_s += dt;
            if self.held_s >= DWELL_S {
                self.held_s = 0.0;
                match self.phase {
                    Phase::ToLower => self.phase = Phase::ToUpper,
                    Phase::ToUpper => {
                        self.phase = Phase::ToLower;
                        self.target = None;
                        self.current += 1;
                    }
                }
            }
        }
        Some((joint.servo, torque))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A joint with no load but the hand and two stiff stops, integrated here: the hand takes
    /// it to each stop in turn, presses a little into each, and then the next joint.
    #[test]
    fn the_hand_presses_each_joint_into_both_stops_in_turn() {
        let joints = vec![
            HandJoint {
                servo: 3,
                lower_rad: -1.0,
                upper_rad: 0.5,
            },
            HandJoint {
                servo: 5,
                lower_rad: 0.0,
                upper_rad: 1.2,
            },
        ];
        let mut hand = Hand::new(joints.clone());
        let mut q = [0.2f64; 8];
        let mut qd = [0.0f64; 8];
        let mut seen = [(f64::MAX, f64::MIN); 8];
        let dt = 0.001;
        let mut t = 0.0;
        while !hand.done() && t < 30.0 {
            let (i, tau) = hand
                .push(dt, |i| Feel {
                    angle_rad: q[i],
                    speed_rad_s: qd[i],
                    torque_on: false,
                })
                .unwrap();
            let j = joints.iter().find(|j| j.servo == i).unwrap();
            let stop = crate::arm::stop_torque(q[i], qd[i], j.lower_rad, j.upper_rad);
            // A light link: 0.01 kg·m², viscous 0.2 N·m·s/rad.
            qd[i] += (tau + stop - 0.2 * qd[i]) / 0.01 * dt;
            q[i] += qd[i] * dt;
            seen[i] = (seen[i].0.min(q[i]), seen[i].1.max(q[i]));
            t += dt;
        }
        assert!(hand.done(), "{t} s");
        for j in &joints {
            let (lo, hi) = seen[j.servo];
            // Into each stop, by the give of a 200 N·m/rad stop under at most 4 N·m.
            assert!(lo < j.lower_rad && lo > j.lower_rad - 0.03, "{lo}");
            assert!(hi > j.upper_rad && hi < j.upper_rad + 0.03, "{hi}");
        }
        // A joint whose torque is on is waited for.
        let mut hand = Hand::new(joints);
        let on = |_| Feel {
            angle_rad: 0.0,
            speed_rad_s: 0.0,
            torque_on: true,
        };
        assert_eq!(hand.push(dt, on), None);
        assert!(!hand.done());
    }
}
