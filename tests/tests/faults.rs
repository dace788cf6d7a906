//! Faults with the real processes on the simulator's pseudo-terminals: 1 % corrupted replies
//! (flipped bits, dropped and truncated packets, seeded) for the whole run, one servo that
//! stops answering for a while, and the right arm's bus unplugged (its pseudo-terminal closed,
//! the device link removed) and plugged back in at the same path. The driver keeps its rate
//! and the other servos running, marks what is missing, counts errors by kind on
//! `nori/bus-health`, reopens the device and sets the bus up again.
//!
//! The exact comparison of published values with what the servos measured is the in-memory
//! soak in `bus-driver/tests/faults.rs`; here, values are checked against physical bounds.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::probe::ProbeRecord;
use nori_tests::{binary, scratch, wait_for, Proc, SchedulingProbe};
use std::time::{Duration, Instant};
use telemetry::frames::{BusHealth, BUS_HEALTH_CONNECTED, JOINT_FLAG_BUS_LOST};
use telemetry::plane::{self, Plane};
use telemetry::JointState;

const UNPLUG_AT: f64 = 16.0;
const UNPLUG_FOR: f64 = 3.0;
const SILENCE_AT: f64 = 11.0;
const SILENCE_FOR: f64 = 1.5;

/// Frames of one phase of the run. Validity is counted over the cycles that kept their
/// deadline: a cycle that overran (this shared two-core machine sometimes wakes a process
/// milliseconds late) loses replies to timing, not to the line faults this test is about; those
/// cycles are counted apart (`late`), and the loop's timing is judged by the rate ratio.
#[derive(Default, Debug)]
struct Window {
    first: Option<(u64, u64, u64)>,
    last: Option<(u64, u64, u64)>,
    /// The previous frame's deadline misses and its (samples, valid), not yet counted: a frame
    /// is counted once the next one shows that neither overran.
    pending: Option<(u64, u64, u64)>,
    samples: u64,
    valid: u64,
    late: u64,
}

impl Window {
    fn add(&mut self, s: &JointState, joints: impl IntoIterator<Item = usize>) {
        let point = (s.seq, s.timestamp_ns, s.deadline_misses);
        self.first.get_or_insert(point);
        self.last = Some(point);
        let (mut samples, mut valid) = (0, 0);
        for j in joints {
            samples += 1;
            valid += u64::from(s.joints[j].is_valid());
        }
        match self.pending.replace((s.deadline_misses, samples, valid)) {
            // A deadline was missed between the two frames: both are late.
            Some((misses, _, _)) if s.deadline_misses > misses => {
                self.late += 2;
                self.pending = None;
            }
            Some((_, n, v)) => {
                self.samples += n;
                self.valid += v;
            }
            None => {}
        }
    }
    /// Cycles achieved over cycles due at the configured rate, from the driver's own frames.
    fn rate_ratio(&self, rate_hz: f64) -> f64 {
        let (Some(f), Some(l)) = (self.first, self.last) else {
            return f64::NAN;
        };
        let due = (l.1 - f.1) as f64 * 1e-9 * rate_hz;
        (l.0 - f.0) as f64 / due
    }
    /// The window's rate ratio, with the rate a probe at the same rate kept over the same span:
    /// the bound is 0.95 of what this machine let a loop keep.
    fn rate_holds(&self, rate_hz: f64, probe: &ProbeRecord) -> (f64, f64, bool) {
        let (Some(f), Some(l)) = (self.first, self.last) else {
            return (f64::NAN, f64::NAN, false);
        };
        let (ratio, kept) = (self.rate_ratio(rate_hz), probe.kept_ratio(f.1, l.1));
        (ratio, kept, ratio > 0.95 * kept)
    }
    fn miss_ratio(&self) -> f64 {
        let (Some(f), Some(l)) = (self.first, self.last) else {
            return f64::NAN;
        };
        (l.2 - f.2) as f64 / (l.0 - f.0).max(1) as f64
    }
    fn valid_ratio(&self) -> f64 {
        self.valid as f64 / self.samples.max(1) as f64
    }
    /// The valid share the 1 % line faults leave (≥ 0.97 with a 3× margin), less this window's
    /// own deadline-miss ratio: a run the machine disturbed (its driver missing deadlines) also
    /// loses replies to timing in the cycles around the misses, and is judged by that baseline
    /// from the same run, not by a fixed figure.
    fn fault_bound(&self) -> f64 {
        0.97 - self.miss_ratio()
    }
    fn holds(&self) -> bool {
        self.valid_ratio() > self.fault_bound()
    }
}

#[test]
#[allow(
    clippy::too_many_lines,
    reason = "one scenario read start to end; to be split into phases (#37)"
)]
fn corrupted_replies_a_silent_servo_and_an_unplugged_bus() {
    let dir = scratch("faults");
    let domain = format!("nori_faults_{}", std::process::id());
    let devices = dir.join("dev");
    let report = dir.join("sim-report.json");
    let unplug = format!("right_arm@{UNPLUG_AT}+{UNPLUG_FOR}");
    let silence = format!("left_arm:3@{SILENCE_AT}+{SILENCE_FOR}");
    let sim_args = [
        "sim",
        "serve",
        "--bus",
        "left_arm",
        "--bus",
        "right_arm",
        "--dir",
        devices.to_str().unwrap(),
        "--report",
        report.to_str().unwrap(),
        "--bit-flip-rate",
        "0.006",
        "--drop-rate",
        "0.002",
        "--truncate-rate",
        "0.002",
        "--fault-seed",
        "7",
        "--unplug",
        &unplug,
        "--silence",
        &silence,
    ];
    let mut sim = Proc::spawn(
        "simulator",
        &binary("nori"),
        &sim_args,
        &dir.join("sim.log"),
    );
    let started = Instant::now();
    let t = || started.elapsed().as_secs_f64();
    let mut supervisor = Proc::spawn(
        "supervisor",
        &binary("supervisor"),
        &["--domain", &domain, "--status-every", "0"],
        &dir.join("supervisor.log"),
    );
    let mut driver = Proc::spawn(
        "bus-driver",
        &binary("bus-driver"),
        &[
            "--bus",
            "left_arm",
            "--bus",
            "right_arm",
            "--device-dir",
            devices.to_str().unwrap(),
            "--domain",
            &domain,
            "--status-every",
            "0",
        ],
        &dir.join("driver.log"),
    );
    let node = Plane::open(&domain, "faults-test").unwrap();
    let state = node.subscriber(&plane::JOINT_STATE).unwrap();
    let health = node.subscriber(&plane::BUS_HEALTH).unwrap();
    let left = 0..8;
    let right = 8..16;

    // Up and driving (supervised, every servo answering with torque on).
    wait_for(Duration::from_secs(30), "16 servos driven", || {
        plane::newest(&state).filter(|s| {
            s.flags == 0 && s.joints().iter().filter(|j| j.torque_enabled == 1).count() == 16
        })
    });
    assert!(
        t() < SILENCE_AT - 3.0,
        "the stack took {:.1} s to come up: the scheduled faults would start before the soak",
        t()
    );

    let mut soak = Window::default();
    let mut silent = Window::default();
    let mut unplugged = Window::default();
    let mut unplugged_left = Window::default();
    let mut after = Window::default();
    let mut saw_lost_flag = false;
    let mut silent_servo_back = false;
    let mut implausible = Vec::new();
    let mut last_health = BusHealth::default();
    let mut all_back_at = None;
    let end = UNPLUG_AT + UNPLUG_FOR + 5.0;
    // The driver's 200 Hz against a 200 Hz loop of the test's own, over the same spans.
    let probe = SchedulingProbe::start(Duration::from_millis(5));
    while t() < end {
        let mut got = false;
        while let Some(s) = plane::next(&state) {
            got = true;
            let now = t();
            for (j, js) in s.joints().iter().enumerate() {
                let ok = !js.is_valid()
                    || ((15.0..=90.0).contains(&js.temperature_c)
                        && (9.0..=14.0).contains(&js.voltage_v)
                        && js.position_rad.abs() <= 3.3
                        && js.load.abs() <= 1.0);
                if !ok && implausible.len() < 10 {
                    implausible.push((s.seq, j, *js));
                }
            }
            if now < SILENCE_AT - 0.2 {
                soak.add(&s, 0..16);
            } else if now > SILENCE_AT + 0.5 && now < SILENCE_AT + SILENCE_FOR - 0.1 {
                // Joint 2 is servo 3 of the left arm: the others keep running.
                silent.add(&s, (0..16).filter(|&j| j != 2));
                assert!(!s.joints[2].is_valid(), "silent servo published as valid");
            } else if now > SILENCE_AT + SILENCE_FOR + 2.0 && now < UNPLUG_AT - 0.2 {
                silent_servo_back |= s.joints[2].is_valid() && s.joints[2].torque_enabled == 1;
            } else if now > UNPLUG_AT + 0.5 && now < UNPLUG_AT + UNPLUG_FOR - 0.2 {
                unplugged.add(&s, right.clone());
                unplugged_left.add(&s, left.clone());
                saw_lost_flag |= right
                    .clone()
                    .all(|j| s.joints[j].flags & JOINT_FLAG_BUS_LOST != 0);
            } else if now > UNPLUG_AT + UNPLUG_FOR + 0.3 {
                if all_back_at.is_none()
                    && s.joints()
                        .iter()
                        .all(|j| j.is_valid() && j.torque_enabled == 1)
                {
                    all_back_at = Some(now);
                }
                if all_back_at.is_some_and(|b| now > b + 0.5) {
                    after.add(&s, 0..16);
                }
            }
        }
        if let Some(h) = plane::newest(&health) {
            last_health = h;
        }
        if !got {
            std::thread::sleep(Duration::from_millis(2));
        }
        assert!(driver.running(), "the driver died");
    }
    let rate = 200.0;
    let probe = probe.finish();
    let (soak_rate, soak_kept, soak_rate_holds) = soak.rate_holds(rate, &probe);
    let (left_rate, left_kept, left_rate_holds) = unplugged_left.rate_holds(rate, &probe);
    eprintln!(
        "soak: rate ratio {soak_rate:.4} (a probe loop kept {soak_kept:.4}), deadline-miss \
         ratio {:.4}, valid {:.4} of {} samples in cycles on time ({} frames around a missed \
         deadline set apart)",
        soak.miss_ratio(),
        soak.valid_ratio(),
        soak.samples,
        soak.late
    );
    eprintln!(
        "servo silent: others valid {:.4} (deadline-miss ratio {:.4}); unplugged: right valid \
         {:.4}, left valid {:.4}, rate ratio {left_rate:.4} (probe {left_kept:.4}); back {:.2} s \
         after the replug; after: rate ratio {:.4}, valid {:.4}",
        silent.valid_ratio(),
        silent.miss_ratio(),
        unplugged.valid_ratio(),
        unplugged_left.valid_ratio(),
        all_back_at.map_or(f64::NAN, |b| b - UNPLUG_AT - UNPLUG_FOR),
        after.rate_ratio(rate),
        after.valid_ratio()
    );
    eprintln!("bus health: {:#?}", last_health.buses());

    assert!(
        implausible.is_empty(),
        "implausible valid values: {implausible:?}"
    );
    // 1 % corrupted replies: the loop keeps its rate (ratio of cycles achieved to cycles due,
    // measured from the driver's own frames, against what the machine let a probe keep) and,
    // in the cycles that kept their deadline, loses only the corrupted samples.
    assert!(
        soak_rate_holds,
        "rate ratio {soak_rate} while a probe loop kept {soak_kept}"
    );
    assert!(
        soak.holds(),
        "valid ratio {} (bound {})",
        soak.valid_ratio(),
        soak.fault_bound()
    );
    assert!(
        silent.holds(),
        "others while one servo is silent: {} (bound {})",
        silent.valid_ratio(),
        silent.fault_bound()
    );
    assert!(silent_servo_back, "the silent servo was not set up again");
    assert_eq!(unplugged.valid, 0, "an unplugged bus published values");
    assert!(saw_lost_flag, "unplugged joints not flagged");
    assert!(
        unplugged_left.holds(),
        "the left arm stalled while the right was unplugged: {} (bound {})",
        unplugged_left.valid_ratio(),
        unplugged_left.fault_bound()
    );
    assert!(
        left_rate_holds,
        "rate ratio while the right arm was unplugged: {left_rate} (a probe loop kept {left_kept})"
    );
    assert!(all_back_at.is_some(), "the right arm did not come back");
    assert!(
        after.holds(),
        "after: {} (bound {})",
        after.valid_ratio(),
        after.fault_bound()
    );
    let [l, r] = [last_health.buses[0].counters, last_health.buses[1].counters];
    let right_flags = last_health.buses[1].flags;
    assert_eq!(last_health.bus_count, 2);
    assert!(
        l.checksum_errors > 0 && r.checksum_errors > 0,
        "corruption counted by kind"
    );
    assert!(l.missing > 0 && l.disconnects == 0 && l.servos_lost == 1);
    assert!(r.disconnects >= 1 && r.reconnects >= 1 && right_flags & BUS_HEALTH_CONNECTED != 0);

    drop((state, health));
    drop(node);
    let (code, _) = driver.terminate(Duration::from_secs(5));
    assert_eq!(code, Some(0));
    supervisor.terminate(Duration::from_secs(5));
    sim.terminate(Duration::from_secs(5));
    telemetry::plane::Plane::remove_unused_domain(&domain).unwrap();
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    for bus in report["buses"].as_array().unwrap() {
        eprintln!(
            "sim {}: faults injected {}",
            bus["name"], bus["line"]["faults"]
        );
        assert!(bus["line"]["faults"]["flipped"].as_u64().unwrap() > 0);
        for servo in bus["servos"].as_array().unwrap() {
            nori_tests::assert_left_off(servo, "driver stopped");
        }
    }
}
