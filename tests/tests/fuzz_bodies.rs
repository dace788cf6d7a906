//! The cargo-fuzz bodies (`fuzz/bodies.rs`) as bounded, seeded property tests on stable Rust:
//! random bytes and mutations of valid inputs (packets, messages, configuration files, CSV)
//! through every decoder that faces outside bytes. None may panic (an invariant of the body
//! failing panics too), and none may allocate more than a bound per input: a counting allocator
//! measures each case's peak. A hang shows as the bodies' own progress bounds or a test that
//! never ends; the case counts are fixed, so the run is bounded.
//!
//! cargo-fuzz itself needs nightly, which this repository does not use; the targets in `fuzz/`
//! build with `cargo +nightly fuzz build` where nightly exists.

// The counting allocator is the one unsafe impl here (GlobalAlloc is an unsafe trait).
#![allow(unsafe_code, clippy::unwrap_used, clippy::expect_used)]

#[path = "../../fuzz/bodies.rs"]
mod bodies;

use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

struct Counting;

thread_local! {
    static LIVE: Cell<usize> = const { Cell::new(0) };
    static PEAK: Cell<usize> = const { Cell::new(0) };
}

// SAFETY: every call is forwarded to the system allocator unchanged; the bookkeeping touches
// only const-initialised thread-locals without destructors (no allocation, no re-entry).
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            grow(layout.size());
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        let _ = LIVE.try_with(|l| l.set(l.get().saturating_sub(layout.size())));
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            let _ = LIVE.try_with(|l| l.set(l.get().saturating_sub(layout.size())));
            grow(new_size);
        }
        p
    }
}

fn grow(n: usize) {
    let _ = LIVE.try_with(|l| {
        let now = l.get() + n;
        l.set(now);
        let _ = PEAK.try_with(|p| p.set(p.get().max(now)));
    });
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Runs `body` on `data` and returns the most it had allocated at once, bytes.
fn peak_of(body: fn(&[u8]), data: &[u8]) -> usize {
    let base = LIVE.with(Cell::get);
    PEAK.with(|p| p.set(base));
    body(data);
    PEAK.with(Cell::get).saturating_sub(base)
}

/// Most a body may hold at once for one input of `len` bytes: a fixed allowance (a simulated
/// bus, parser tables) plus a linear share; anything growing faster than the input fails.
fn allocation_bound(len: usize) -> usize {
    8 << 20 | (len * 2048)
}

/// A random input: raw bytes, or one of `seeds` with a few bytes replaced, inserted, deleted
/// or the tail cut.
fn input(seeds: Vec<Vec<u8>>) -> impl Strategy<Value = Vec<u8>> {
    let raw = proptest::collection::vec(any::<u8>(), 0..600);
    let n = seeds.len();
    let mutated = (
        0..n,
        proptest::collection::vec((any::<u16>(), 0u8..4, any::<u8>()), 0..8),
    )
        .prop_map(move |(s, edits)| {
            let mut v = seeds[s].clone();
            for (at, op, b) in edits {
                let at = usize::from(at) % (v.len() + 1);
                match op {
                    0 if at < v.len() => v[at] = b,
                    1 => v.insert(at, b),
                    2 if at < v.len() => {
                        v.remove(at);
                    }
                    _ => v.truncate(at),
                }
            }
            v
        });
    prop_oneof![1 => raw, 3 => mutated]
}

fn run(name: &str, body: fn(&[u8]), seeds: Vec<Vec<u8>>, cases: u32) {
    // Seeded: the same cases on every run (a failure reproduces); proptest shrinks it.
    let config = Config {
        cases,
        failure_persistence: None,
        ..Config::default()
    };
    let rng = TestRng::from_seed(RngAlgorithm::ChaCha, &[7; 32]);
    let mut runner = TestRunner::new_with_rng(config, rng);
    let worst = Cell::new(0usize);
    // The seeds themselves first: valid inputs must pass every invariant too.
    for s in &seeds {
        let peak = peak_of(body, s);
        assert!(
            peak <= allocation_bound(s.len()),
            "{name}: seed held {peak} B"
        );
    }
    runner
        .run(&input(seeds), |data| {
            let peak = peak_of(body, &data);
            worst.set(worst.get().max(peak));
            prop_assert!(
                peak <= allocation_bound(data.len()),
                "{name}: {} input bytes held {peak} B at once",
                data.len()
            );
            Ok(())
        })
        .unwrap_or_else(|e| panic!("{name}: {e}"));
    eprintln!("{name}: {cases} cases, worst allocation {} B", worst.get());
}

fn feedback_burst() -> Vec<u8> {
    use feetech::{ServoStatus, StatusPacket, MAX_PACKET};
    let mut out = Vec::new();
    for id in 1..=8u8 {
        let params: Vec<u8> = (0..15).map(|k| k * 13 + id).collect();
        let mut buf = [0u8; MAX_PACKET];
        let n = StatusPacket {
            id,
            status: ServoStatus(0),
            params: &params,
        }
        .encode(&mut buf)
        .unwrap();
        out.extend_from_slice(&buf[..n]);
    }
    out
}

fn instructions() -> Vec<Vec<u8>> {
    use feetech::Instruction;
    let mut seeds = Vec::new();
    for i in [
        Instruction::Ping { id: 1 },
        Instruction::Read {
            id: 2,
            addr: 56,
            len: 15,
        },
        Instruction::Write {
            id: 3,
            addr: 40,
            data: &[1],
        },
        Instruction::SyncRead {
            addr: 56,
            len: 15,
            ids: &[1, 2, 3, 4, 5, 6, 7, 8],
        },
        Instruction::SyncWrite {
            addr: 42,
            len: 2,
            payload: &[1, 0, 8, 2, 0, 8],
        },
    ] {
        let mut buf = [0u8; feetech::MAX_PACKET];
        let n = i.encode(&mut buf).unwrap();
        seeds.push(buf[..n].to_vec());
    }
    seeds
}

fn messages() -> Vec<Vec<u8>> {
    use fleet_agent::schema::{encode, ActionChunk, SCHEMA_VERSION};
    let good = ActionChunk {
        version: SCHEMA_VERSION,
        seq: 3,
        observation_ns: 9_900_000_000,
        step_offsets_ns: vec![20_000_000, 40_000_000],
        joint_count: 3,
        joint_mask: 0b111,
        targets: vec![0.1, -0.5, 1.0, 0.2, -1.0, 2.0],
        lift_m: Vec::new(),
        base_twist: Vec::new(),
    };
    let mut out_of_range = good.clone();
    out_of_range.targets[2] = 9.0;
    let mut nan = good.clone();
    nan.targets[0] = f32::NAN;
    let mut version = good.clone();
    version.version = SCHEMA_VERSION + 1;
    vec![
        encode(&good),
        encode(&out_of_range),
        encode(&nan),
        encode(&version),
    ]
}

const CSV: &str = "t_s,motor,temperature_c,current_a,voltage_v,position_rad,goal_rad\n\
0.0,1,30,0.1,12.0,0.0,0.0\n0.0,2,31,0.2,12.0,0.1,0.1\n0.1,1,30,0.1,12.0,0.0,0.0\n\
0.1,2,31,0.3,11.9,0.1,0.2\n0.2,1,31,0.1,12.0,0.0,0.0\n0.2,2,32,0.2,12.0,0.2,0.2\n";

#[test]
fn status_decoder_property() {
    let burst = feedback_burst();
    let mut noisy = vec![0x00, 0xFF, 0x13];
    noisy.extend_from_slice(&burst);
    run(
        "status_decoder",
        bodies::status_decoder,
        vec![burst, noisy],
        384,
    );
}

#[test]
fn device_side_property() {
    run("device_side", bodies::device_side, instructions(), 512);
}

#[test]
fn wire_messages_property() {
    run("wire_messages", bodies::wire_messages, messages(), 1024);
}

#[test]
fn driver_config_property() {
    let config = bus_driver::config::DEFAULT_CONFIG_TOML.as_bytes().to_vec();
    let mut both = config.clone();
    both.push(0);
    both.extend_from_slice(bus_driver::config::DEFAULT_CALIBRATION_TOML.as_bytes());
    run(
        "driver_config",
        bodies::driver_config,
        vec![config, both],
        256,
    );
}

#[test]
fn supervisor_config_property() {
    let seed = supervisor::config::DEFAULT_CONFIG_TOML.as_bytes().to_vec();
    run(
        "supervisor_config",
        bodies::supervisor_config,
        vec![seed],
        256,
    );
}

#[test]
fn agent_config_property() {
    let seed = fleet_agent::config::DEFAULT_CONFIG_TOML.as_bytes().to_vec();
    run("agent_config", bodies::agent_config, vec![seed], 256);
}

#[test]
fn telemetry_csv_property() {
    run(
        "telemetry_csv",
        bodies::telemetry_csv,
        vec![CSV.as_bytes().to_vec()],
        512,
    );
}

/// The one input shape random mutation rarely finds: every row a new motor id. The grid is
/// motors × samples, so without a cap this input would hold gigabytes; it is refused instead.
#[test]
fn a_csv_with_thousands_of_motors_is_refused_within_the_bound() {
    let mut csv = String::from("t_s,motor,temperature_c\n");
    for i in 0..5000 {
        csv.push_str(&format!("{}.0,{i},30\n", i));
    }
    let peak = peak_of(bodies::telemetry_csv, csv.as_bytes());
    assert!(peak <= allocation_bound(csv.len()), "held {peak} B");
    let rows = model_lab::data::parse_csv(&csv, "m.csv").unwrap();
    let e = model_lab::data::Dataset::from_runs(
        vec![("m.csv".into(), rows)],
        Default::default(),
        "m.csv",
    )
    .unwrap_err();
    assert!(e.to_string().contains("5000 distinct motor ids"), "{e}");
}

/// Two turns of an RPLIDAR C1 scan (500 nodes each, S on the first), as the device sends them.
fn lidar_turns() -> Vec<u8> {
    let mut out = vec![0x01];
    for i in 0..1000u32 {
        let index = i % 500;
        let start = u8::from(index == 0);
        let angle = ((index * 46) << 1 | 1) as u16;
        let distance = (8000 + i % 17) as u16;
        out.extend_from_slice(&[40 << 2 | (1 - start) << 1 | start]);
        out.extend_from_slice(&angle.to_le_bytes());
        out.extend_from_slice(&distance.to_le_bytes());
    }
    out
}

#[test]
fn lidar_stream_property() {
    let turns = lidar_turns();
    let mut info = vec![0x00, 0xA5, 0x5A, 0x14, 0, 0, 0, 0x04, 0x41, 2, 1, 18];
    info.extend_from_slice(&[0xAB; 16]);
    run("lidar_stream", bodies::lidar_stream, vec![turns, info], 256);
}

#[test]
fn camera_stream_property() {
    let header = camera::stream::StreamHeader {
        fourcc: *b"YUYV",
        width: 4,
        height: 2,
        sequence: 7,
        len: 16,
        capture_ns: 1_000,
    };
    let mut frames = vec![0x05];
    for _ in 0..3 {
        frames.extend_from_slice(&header.encode());
        frames.extend_from_slice(&[0x80; 16]);
    }
    run("camera_stream", bodies::camera_stream, vec![frames], 512);
}
