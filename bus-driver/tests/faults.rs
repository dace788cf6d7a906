//! The real driver against the simulated A3 over an in-memory link, with line faults injected
//! by the simulator (seeded): corrupted, dropped and truncated replies, a servo that stops
//! answering, a bus whose device disappears and comes back. The simulator records what each
//! servo really measured, so every value the driver publishes as valid is checked against it.
//!
//! In memory (not on a pseudo-terminal) so that the comparison is exact and the run
//! deterministic: each cycle's truth is the simulator's answer to that cycle's SYNC_READ. The
//! same faults on the real pseudo-terminals, with the real binaries, are in `tests/tests/faults.rs`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use bus_driver::config::SafeState;
use bus_driver::driver::GoalRejection;
use bus_driver::transport::TransportError;
use bus_driver::{Driver, LoadedConfig, Transport};
use feetech::registers::{self as reg, FeedbackBlock};
use sim::faults::{FaultCounts, LineFaults};
use sim::{RobotDescription, SimBus};
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use telemetry::clock::monotonic_ns;
use telemetry::frames::{BusHealth, JOINT_FLAG_BUS_LOST};
use telemetry::GoalFrame;

/// One simulated bus behind an in-memory link that can be pulled out.
struct SimLink {
    bus: Arc<Mutex<SimBus>>,
    inbox: VecDeque<u8>,
    gone: Arc<AtomicBool>,
    baud: u32,
}

fn gone_error() -> TransportError {
    TransportError::Io {
        device: "sim".into(),
        source: std::io::Error::new(std::io::ErrorKind::BrokenPipe, "unplugged"),
    }
}

impl Transport for SimLink {
    fn baud(&self) -> u32 {
        self.baud
    }
    fn send(&mut self, bytes: &[u8]) -> Result<(), TransportError> {
        if self.gone.load(Ordering::SeqCst) {
            return Err(gone_error());
        }
        let mut bus = self.bus.lock().unwrap();
        let t = bus.time();
        bus.receive(t, bytes);
        Ok(())
    }
    fn receive(&mut self, buf: &mut [u8], _timeout: Duration) -> Result<usize, TransportError> {
        if self.gone.load(Ordering::SeqCst) {
            return Err(gone_error());
        }
        if self.inbox.is_empty() {
            let mut bus = self.bus.lock().unwrap();
            while let Some(r) = bus.pop_due(f64::MAX) {
                self.inbox.extend(r.bytes);
            }
        }
        let n = buf.len().min(self.inbox.len());
        for (b, v) in buf.iter_mut().zip(self.inbox.drain(..n)) {
            *b = v;
        }
        Ok(n)
    }
    fn discard_input(&mut self) -> Result<(), TransportError> {
        if self.gone.load(Ordering::SeqCst) {
            return Err(gone_error());
        }
        self.inbox.clear();
        Ok(())
    }
    fn reopen(&mut self) -> Result<(), TransportError> {
        if self.gone.load(Ordering::SeqCst) {
            return Err(TransportError::Open {
                device: "sim".into(),
                baud: self.baud,
                source: serialport::Error::new(serialport::ErrorKind::NoDevice, "unplugged"),
            });
        }
        self.inbox.clear();
        Ok(())
    }
}

struct Rig {
    buses: Vec<Arc<Mutex<SimBus>>>,
    gone: Vec<Arc<AtomicBool>>,
    config: LoadedConfig,
    driver: Driver<SimLink>,
}

fn rig(faults: Option<LineFaults>, safe_state: SafeState) -> Rig {
    let robot = RobotDescription::nori_a3();
    let mut config = LoadedConfig::embedded().unwrap();
    // No supervisor here (its part is tested with the processes); wire time only.
    config.config.supervisor_timeout_ms = 0;
    config.config.reply_timeout_margin_us = 0;
    config.config.safe_state = safe_state;
    let mut buses = Vec::new();
    let mut gone = Vec::new();
    let mut links = Vec::new();
    for (i, b) in config.config.bus.iter().enumerate() {
        let d = robot.bus(&b.name).unwrap();
        let mut bus = SimBus::new(&robot, d);
        bus.set_line_faults(faults.map(|f| LineFaults {
            seed: f.seed + i as u64,
            ..f
        }));
        let bus = Arc::new(Mutex::new(bus));
        let g = Arc::new(AtomicBool::new(false));
        links.push(SimLink {
            bus: bus.clone(),
            inbox: VecDeque::new(),
            gone: g.clone(),
            baud: b.baud,
        });
        buses.push(bus);
        gone.push(g);
    }
    let mut driver = Driver::new(&config, links);
    let failures = driver.setup();
    assert!(failures.is_empty(), "setup failed: {failures:?}");
    Rig {
        buses,
        gone,
        config,
        driver,
    }
}

impl Rig {
    /// One cycle, then the mechanics advance 5 ms.
    fn cycle(&mut self) -> telemetry::JointState {
        let s = *self.driver.cycle();
        for b in &self.buses {
            let mut b = b.lock().unwrap();
            let t = b.time() + 0.005;
            b.advance_to(t, 0.001);
        }
        s
    }

    fn faults(&self) -> FaultCounts {
        self.buses
            .iter()
            .fold(FaultCounts::default(), |mut acc, b| {
                let f = b.lock().unwrap().stats.faults;
                acc.flipped += f.flipped;
                acc.double_flipped += f.double_flipped;
                acc.dropped += f.dropped;
                acc.truncated += f.truncated;
                acc
            })
    }

    fn health(&self) -> BusHealth {
        let mut h = BusHealth::default();
        self.driver.health(&mut h);
        h
    }

    /// Every valid sample equals what the servo really measured for this cycle's read;
    /// returns how many valid samples were checked.
    fn check_against_truth(&self, s: &telemetry::JointState) -> usize {
        self.compare_with_truth(s, |joint, have, want| {
            assert_eq!(
                have, want,
                "{joint}: published value is not what it measured"
            );
        })
    }

    /// Calls `visit(joint, published, measured)` with (position rad, temperature °C, voltage V,
    /// load, current A) of every valid sample; returns how many there were.
    fn compare_with_truth(
        &self,
        s: &telemetry::JointState,
        mut visit: impl FnMut(&str, [f32; 5], [f32; 5]),
    ) -> usize {
        let mut checked = 0;
        let mut j = 0;
        for (bi, bus_cfg) in self.config.config.bus.iter().enumerate() {
            let sim = self.buses[bi].lock().unwrap();
            for servo in &bus_cfg.servo {
                let got = s.joints[j];
                j += 1;
                if !got.is_valid() {
                    assert_eq!(got.position_rad, 0.0, "a missing joint carries no value");
                    continue;
                }
                let truth = sim.feedback_truth(servo.id).unwrap_or_else(|| {
                    panic!("{} valid but its servo did not answer", servo.joint)
                });
                let f = FeedbackBlock::parse(truth).unwrap();
                let position = match self.config.calibration.joint.get(&servo.joint) {
                    Some(cal) if bus_cfg.mode == bus_driver::config::Mode::Position => {
                        cal.to_rad(f.position)
                    }
                    _ => f64::from(f.position) / bus_driver::calibration::STEPS_PER_RAD,
                };
                let want = [
                    position as f32,
                    f32::from(f.temperature),
                    f32::from(f.voltage) / 10.0,
                    f.load as f32 / 1000.0,
                    (f64::from(f.current) * feetech::AMPS_PER_CURRENT_UNIT) as f32,
                ];
                let have = [
                    got.position_rad,
                    got.temperature_c,
                    got.voltage_v,
                    got.load,
                    got.current_a,
                ];
                visit(&servo.joint, have, want);
                checked += 1;
            }
        }
        checked
    }
}

/// Soak: 1 % of replies corrupted (flipped bit, dropped or truncated; seeded) for 3000 cycles.
/// No corrupted value is ever published as valid, every fault is seen as a missing sample (never
/// a stale or wrong one), counted by kind, and no servo is taken off for it.
#[test]
fn one_percent_corrupted_replies_never_publish_a_wrong_value() {
    let faults = LineFaults {
        seed: 42,
        bit_flip_rate: 0.006,
        drop_rate: 0.002,
        truncate_rate: 0.002,
        ..LineFaults::default()
    };
    let mut rig = rig(Some(faults), SafeState::Hold);
    let n = 3000;
    let mut checked = 0;
    let mut missing = 0;
    for _ in 0..n {
        let s = rig.cycle();
        checked += rig.check_against_truth(&s);
        missing += s.joints().iter().filter(|j| !j.is_valid()).count();
    }
    let injected = rig.faults();
    let h = rig.health();
    let counted: u64 = h
        .buses()
        .iter()
        .map(|b| b.counters.missing + b.counters.implausible)
        .sum();
    let checksum: u64 = h.buses().iter().map(|b| b.counters.checksum_errors).sum();
    let framing: u64 = h
        .buses()
        .iter()
        .map(|b| b.counters.framing_errors + b.counters.unexpected_replies)
        .sum();
    eprintln!(
        "soak: {n} cycles, {checked} valid samples checked, {missing} missing; injected {injected:?}; \
         driver counted missing {counted}, checksum {checksum}, framing/unexpected {framing}"
    );
    assert!(injected.flipped > 50 && injected.dropped > 10 && injected.truncated > 10);
    // Every corrupted feedback reply costs that sample (it is never taken as valid): at least
    // as many missing samples as faults injected into feedback replies, which are nearly all
    // of them (setup's few unicast replies aside); a corrupted packet may take its successor.
    assert!(
        missing as u64 + 20 >= injected.total(),
        "{missing} < {injected:?}"
    );
    assert!((missing as u64) <= 3 * injected.total() + 5);
    assert_eq!(counted, missing as u64, "missing samples are counted");
    assert!(checksum > 0, "flipped bits show up as checksum errors");
    assert!(
        rig.driver.ready().all(|r| r),
        "no servo taken off for 1 % faults"
    );
    assert!(h
        .buses()
        .iter()
        .all(|b| b.counters.servos_lost == 0 && b.counters.disconnects == 0));
    assert!(checked as f64 >= 0.95 * (n * 18) as f64);
}

/// Soak with two flipped bits in 2 % of replies: about 7 % of those pass the 8-bit sum
/// checksum and decode as a reply. The plausibility gate holds back every one that moved a
/// temperature, supply or position further than the servo can, or reads an impossible load,
/// current or speed: what is still published wrong stays within those bounds, and no
/// temperature reading is ever further than 2 °C from the truth (no false thermal trip, no
/// hot motor hidden).
#[test]
fn two_flipped_bits_that_pass_the_checksum_never_publish_a_large_error() {
    use bus_driver::plausibility::{
        MAX_CURRENT, POSITION_STEP, TEMPERATURE_STEP_C, VOLTAGE_STEP_V,
    };
    let faults = LineFaults {
        seed: 4242,
        double_flip_rate: 0.02,
        ..LineFaults::default()
    };
    let mut rig = rig(Some(faults), SafeState::Hold);
    let n = 3000;
    let (mut checked, mut wrong) = (0, 0);
    let mut worst = [0f32; 5];
    for _ in 0..n {
        let s = rig.cycle();
        checked += rig.compare_with_truth(&s, |_, have, want| {
            if have != want {
                wrong += 1;
            }
            for (w, (h, t)) in worst.iter_mut().zip(have.iter().zip(&want)) {
                *w = w.max((h - t).abs());
            }
        });
    }
    let injected = rig.faults();
    let h = rig.health();
    let sum = |f: fn(&telemetry::frames::BusCounters) -> u64| -> u64 {
        h.buses().iter().map(|b| f(&b.counters)).sum()
    };
    let (implausible, checksum) = (sum(|c| c.implausible), sum(|c| c.checksum_errors));
    eprintln!(
        "double flips: {n} cycles, injected {} double-flipped replies; driver counted checksum \
         {checksum}, implausible {implausible}; {checked} valid samples, {wrong} published with \
         a small error; largest errors: position {:.4} rad, temperature {} °C, voltage {} V, \
         load {}, current {} A",
        injected.double_flipped, worst[0], worst[1], worst[2], worst[3], worst[4]
    );
    assert!(injected.double_flipped > 500, "{injected:?}");
    assert!(
        checksum > 0 && implausible > 0,
        "both defences were exercised"
    );
    let step_rad = (POSITION_STEP / bus_driver::calibration::STEPS_PER_RAD) as f32;
    assert!(
        worst[0] <= step_rad * 1.01,
        "position error {} rad",
        worst[0]
    );
    assert!(
        worst[1] <= TEMPERATURE_STEP_C as f32,
        "temperature error {} °C",
        worst[1]
    );
    assert!(
        worst[2] <= VOLTAGE_STEP_V as f32 + 1e-3,
        "voltage error {} V",
        worst[2]
    );
    assert!(worst[3] <= 2.0, "load error {}", worst[3]);
    let max_a = (f64::from(MAX_CURRENT) * feetech::AMPS_PER_CURRENT_UNIT) as f32;
    assert!(worst[4] <= 2.0 * max_a, "current error {} A", worst[4]);
    assert!(rig.driver.ready().all(|r| r), "no servo taken off");
    assert!(checked as f64 >= 0.95 * (n * 18) as f64);
}

/// A servo that stops answering is missing at once, taken off after 200 ms (the safe state
/// written to it), and set up again when it answers; the others never miss a cycle.
#[test]
fn a_silent_servo_is_taken_off_and_comes_back() {
    let mut rig = rig(None, SafeState::Hold);
    for _ in 0..10 {
        rig.cycle();
    }
    rig.buses[0].lock().unwrap().servo_mut(3).unwrap().answering = false;
    let joint = 2; // left arm, id 3
    for k in 0..60 {
        let s = rig.cycle();
        assert!(!s.joints[joint].is_valid());
        for (j, sample) in s.joints().iter().enumerate() {
            assert!(
                j == joint || sample.is_valid(),
                "joint {j} missed cycle {k}"
            );
        }
        rig.check_against_truth(&s);
    }
    assert!(!rig.driver.ready().nth(joint).unwrap(), "taken off");
    assert_eq!(rig.health().buses[0].counters.servos_lost, 1);
    rig.buses[0].lock().unwrap().servo_mut(3).unwrap().answering = true;
    let mut back_after = None;
    for k in 0..100 {
        let s = rig.cycle();
        rig.check_against_truth(&s);
        if rig.driver.ready().nth(joint).unwrap() {
            back_after = Some(k);
            break;
        }
    }
    assert!(back_after.is_some(), "set up again once it answers");
    assert!(rig.driver.ready().all(|r| r));
}

/// A bus whose device disappears: its joints are missing and flagged, the others keep running;
/// it is reopened when it returns, the safe state applied to the bus at once, then its servos
/// are set up again from where they are.
fn bus_unplugged_and_back(safe_state: SafeState) {
    let mut rig = rig(None, safe_state);
    for _ in 0..10 {
        rig.cycle();
    }
    rig.gone[1].store(true, Ordering::SeqCst);
    let right = 8..16;
    for k in 0..100 {
        let s = rig.cycle();
        for (j, sample) in s.joints().iter().enumerate() {
            if right.contains(&j) {
                assert!(!sample.is_valid());
                assert!(sample.flags & JOINT_FLAG_BUS_LOST != 0);
            } else {
                assert!(sample.is_valid(), "joint {j} missed cycle {k}");
            }
        }
    }
    let h = rig.health();
    assert_eq!(h.buses[1].counters.disconnects, 1);
    assert_eq!(h.buses[1].counters.reconnects, 0);
    assert!(rig.driver.ready().skip(8).take(8).all(|r| !r));
    let before: Vec<u64> = {
        let b = rig.buses[1].lock().unwrap();
        b.servos.iter().map(|s| s.log.torque_off_writes).collect()
    };
    rig.gone[1].store(false, Ordering::SeqCst);
    let mut cycles = 0;
    while !rig.driver.ready().all(|r| r) {
        let s = rig.cycle();
        rig.check_against_truth(&s);
        cycles += 1;
        assert!(cycles < 200, "bus not back after {cycles} cycles");
    }
    let h = rig.health();
    assert_eq!(h.buses[1].counters.reconnects, 1);
    let b = rig.buses[1].lock().unwrap();
    for (s, before) in b.servos.iter().zip(before) {
        // Set up again: torque off first (setup and, for torque-off, the bus-wide safe state).
        assert!(
            s.log.torque_off_writes > before,
            "servo {} not set up again",
            s.id
        );
        assert!(s.torque_enabled());
    }
    let _ = monotonic_ns();
}

#[test]
fn an_unplugged_bus_is_reopened_hold() {
    bus_unplugged_and_back(SafeState::Hold);
}

#[test]
fn an_unplugged_bus_is_reopened_torque_off() {
    bus_unplugged_and_back(SafeState::TorqueOff);
}

/// Every kind of bad goal frame is refused whole, with its own reason and counter, and nothing
/// of it reaches a servo: the goal registers on the (simulated) servos stay as they were.
/// Out-of-range goals are not refused but clamped at the bus layer, and counted.
#[test]
fn every_bad_goal_frame_is_refused_with_its_reason_and_nothing_reaches_the_wire() {
    let mut rig = rig(None, SafeState::Hold);
    for _ in 0..5 {
        rig.cycle();
    }
    let registers = |rig: &Rig| -> Vec<i32> {
        rig.buses
            .iter()
            .enumerate()
            .flat_map(|(bi, b)| {
                let b = b.lock().unwrap();
                let r = if bi == 2 {
                    reg::GOAL_VELOCITY
                } else {
                    reg::GOAL_POSITION
                };
                b.servos.iter().map(|s| s.get(r)).collect::<Vec<_>>()
            })
            .collect()
    };
    let before = registers(&rig);
    let frame = |set: &[(usize, f32)], t: u64| {
        let mut f = GoalFrame {
            joint_count: 18,
            timestamp_ns: t,
            ..GoalFrame::default()
        };
        for &(j, q) in set {
            f.mask |= 1 << j;
            f.position_rad[j] = q;
        }
        f
    };
    let now = monotonic_ns();
    let ms = 1_000_000;
    let mut wrong_count = frame(&[(0, 0.3)], now);
    wrong_count.joint_count = 17;
    let mut beyond_mask = frame(&[(0, 0.3)], now);
    beyond_mask.mask |= 1 << 20;
    let cases: Vec<(GoalFrame, GoalRejection)> = vec![
        (
            wrong_count,
            GoalRejection::WrongJointCount {
                expected: 18,
                got: 17,
            },
        ),
        (
            beyond_mask,
            GoalRejection::MaskOutOfRange {
                mask: 1 | 1 << 20,
                joint_count: 18,
            },
        ),
        (
            frame(&[(0, 0.3)], now - 500 * ms),
            GoalRejection::Stale {
                age_ms: 500,
                limit_ms: 100,
            },
        ),
        (
            frame(&[(0, 0.3)], now + 50 * ms),
            GoalRejection::FromTheFuture { ahead_ms: 50 },
        ),
        (
            frame(&[(0, 0.3), (4, f32::NAN)], now),
            GoalRejection::NotFinite(bus_driver::calibration::GoalError::NotFinite {
                joint: 4,
                value: f32::NAN,
            }),
        ),
        (
            frame(&[(0, 0.3), (9, f32::INFINITY)], now),
            GoalRejection::NotFinite(bus_driver::calibration::GoalError::NotFinite {
                joint: 9,
                value: f32::INFINITY,
            }),
        ),
        (
            frame(&[(0, 0.3), (16, f32::NEG_INFINITY)], now),
            GoalRejection::NotFinite(bus_driver::calibration::GoalError::NotFinite {
                joint: 16,
                value: f32::NEG_INFINITY,
            }),
        ),
    ];
    for (f, want) in &cases {
        let got = rig.driver.apply_goals(f, now).unwrap_err();
        match (got, want) {
            // NaN != NaN: compare the joint only.
            (
                GoalRejection::NotFinite(bus_driver::calibration::GoalError::NotFinite {
                    joint: a,
                    value: va,
                }),
                GoalRejection::NotFinite(bus_driver::calibration::GoalError::NotFinite {
                    joint: b,
                    value: vb,
                }),
            ) => assert!(a == *b && (va == *vb || va.is_nan() && vb.is_nan())),
            (got, want) => assert_eq!(got, *want),
        }
        assert!(!got.to_string().is_empty());
        for _ in 0..3 {
            rig.cycle();
        }
        assert_eq!(
            registers(&rig),
            before,
            "{want}: something reached the wire"
        );
    }
    let c = rig.driver.counters;
    assert_eq!(
        (
            c.goals_malformed,
            c.goals_stale,
            c.goals_not_finite,
            c.goals_accepted
        ),
        (2, 2, 3, 0)
    );

    // Out of range: applied, clamped into the calibrated range (the speed limit for wheels).
    let cal = rig.config.calibration.joint["left_shoulder_pitch"];
    let cal5 = rig.config.calibration.joint["right_shoulder_pitch"];
    rig.driver
        .apply_goals(&frame(&[(0, 1e30), (8, -100.0), (17, 1e9)], now), now)
        .unwrap();
    rig.cycle();
    let after = registers(&rig);
    // At an end of the range (which end depends on the joint's inversion).
    assert!(after[0] == cal.range_min || after[0] == cal.range_max);
    assert!(after[8] == cal5.range_min || after[8] == cal5.range_max);
    let max_steps = (rig.config.config.max_wheel_speed_rad_s
        * bus_driver::calibration::STEPS_PER_RAD)
        .round() as i32;
    assert_eq!(
        after[17].abs(),
        max_steps,
        "wheel speed clamped to the limit"
    );
    assert_eq!(rig.driver.counters.goals_clamped, 3);

    // In the safe state goals are refused; after it, goals made before the recovery too.
    rig.driver.enter_safe_state();
    assert_eq!(
        rig.driver.apply_goals(&frame(&[(0, 0.3)], now), now),
        Err(GoalRejection::SafeState)
    );
    let recovered = monotonic_ns();
    rig.driver.leave_safe_state(recovered);
    assert_eq!(
        rig.driver
            .apply_goals(&frame(&[(0, 0.3)], recovered - ms), recovered),
        Err(GoalRejection::BeforeRecovery)
    );
    assert!(rig
        .driver
        .apply_goals(&frame(&[(0, 0.3)], recovered), recovered)
        .is_ok());
    let c = rig.driver.counters;
    assert_eq!((c.goals_in_safe_state, c.goals_stale), (1, 3));
}

/// Directives for another joint count are refused whole; torque limits above the configured
/// maximum never raise it.
#[test]
fn directives_of_the_wrong_shape_are_refused() {
    let mut rig = rig(None, SafeState::Hold);
    let d = telemetry::frames::Directives {
        joint_count: 5,
        bus_enabled: 0,
        ..Default::default()
    };
    let e = rig.driver.apply_directives(&d).unwrap_err();
    assert_eq!((e.expected, e.got), (18, 5));
    rig.cycle();
    assert!(
        rig.driver.ready().all(|r| r),
        "a refused directive disabled nothing"
    );
    let mut d = telemetry::frames::Directives {
        joint_count: 18,
        ..Default::default()
    };
    d.torque_limit_permille = [1000; telemetry::MAX_JOINTS];
    rig.driver.apply_directives(&d).unwrap();
    rig.cycle();
    let b = rig.buses[0].lock().unwrap();
    let max = (rig.config.config.backstops["sts3095"].max_torque_limit_percent * 10.0) as i32;
    assert!(b.servos[0].get(reg::TORQUE_LIMIT) <= max);
}
