//! The black box on the simulated robot: the overheat scenario's trip freezes a box holding the
//! bus's bytes as the simulator's own record of its wire has them and the trip; a box read by
//! the official `mcap` package with every message checked against its schema; the recorder
//! killed in the middle of a box leaves it readable and made whole at its restart; and the
//! recorder stopped leaves the driver's loop as it was.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use blackbox::channel::{wire_chunks, Channel};
use blackbox::frozen::{self, ReadBox, PARTIAL_SUFFIX};
use nori_tests::{binary, scratch, wait_for, ArmStack};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};
use telemetry::wire::Direction;

fn files_ending(dir: &Path, suffix: &str) -> Vec<PathBuf> {
    let mut out: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.to_string_lossy().ends_with(suffix))
        .collect();
    out.sort();
    out
}

fn read_box(path: &Path) -> ReadBox {
    frozen::read(&std::fs::read(path).unwrap())
}

/// The box's traffic on `bus`: every chunk, in order.
fn wire_of(b: &ReadBox, bus: &str) -> Vec<(u64, Direction, Vec<u8>)> {
    b.messages
        .iter()
        .filter(|m| m.channel == Some(Channel::Wire))
        .filter_map(|m| wire_chunks(&m.data))
        .filter(|r| r.bus == bus)
        .flat_map(|r| r.chunks)
        .collect()
}

fn find(haystack: &[u8], needle: &[u8], from: usize) -> Option<usize> {
    (from..=haystack.len().checked_sub(needle.len())?)
        .find(|&i| &haystack[i..i + needle.len()] == needle)
}

/// Reads `path` with the official Python `mcap` package; `None` when it is not installed
/// outside CI (in CI a missing package fails).
fn python_read(path: &Path, partial: bool) -> Option<Value> {
    let has = Command::new("python3")
        .args(["-c", "import mcap, jsonschema"])
        .status()
        .is_ok_and(|s| s.success());
    if !has {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI needs the mcap and jsonschema Python packages (.ci/run installs them)"
        );
        eprintln!(
            "note: python3 has no mcap/jsonschema: the box is not read by the official reader"
        );
        return None;
    }
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("python/check_blackbox.py");
    let mut cmd = Command::new("python3");
    cmd.arg(script).arg(path);
    if partial {
        cmd.arg("--partial");
    }
    let out = cmd.output().unwrap();
    assert!(
        out.status.success(),
        "the official reader refused {}: {}",
        path.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    Some(serde_json::from_slice(&out.stdout).unwrap())
}

/// The official reader's messages per topic agree with ours.
fn assert_python_agrees(path: &Path, partial: bool) {
    let Some(v) = python_read(path, partial) else {
        return;
    };
    let ours = blackbox::export::summary(&std::fs::read(path).unwrap()).per_topic;
    assert!(!ours.is_empty());
    for (topic, n) in &ours {
        assert_eq!(v["messages"][topic], *n as u64, "{topic}: {v}");
    }
    assert_eq!(v["footer"], !partial);
}

#[test]
fn an_overheat_trip_freezes_a_box_with_the_bus_bytes_as_the_simulator_saw_them() {
    let _one_at_a_time = nori_tests::serial();
    let dir = scratch("blackbox-overheat");
    let out = Command::new(binary("nori"))
        .args(["sim", "scenario", "overheat", "--json", "--timeout", "120"])
        .arg("--blackbox")
        .arg(&dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(v["software_trip_s"].as_f64().is_some(), "no trip: {v}");

    let boxes = dir.join("boxes");
    assert!(
        files_ending(&boxes, PARTIAL_SUFFIX).is_empty(),
        "a box left unfinished"
    );
    let whole = files_ending(&boxes, ".mcap");
    let (trip_box, b) = whole
        .iter()
        .map(|p| (p, read_box(p)))
        .find(|(_, b)| {
            b.messages.iter().any(|m| {
                m.channel == Some(Channel::Triggers)
                    && String::from_utf8_lossy(&m.data).contains("\"thermal_trip\"")
            })
        })
        .unwrap_or_else(|| panic!("no box frozen by the trip: {whole:?}"));
    assert!(b.extent.complete);
    let events: Vec<Value> = b
        .messages
        .iter()
        .filter(|m| m.channel == Some(Channel::Events))
        .map(|m| serde_json::from_slice(&m.data).unwrap())
        .collect();
    let trip = events
        .iter()
        .find(|e| e["kind"] == "thermal_trip")
        .unwrap_or_else(|| panic!("the trip event is not in the box: {events:?}"));
    assert_eq!(trip["joint"], "left_shoulder_pitch");
    let trip_ns = trip["timestamp_ns"].as_u64().unwrap();

    // The bus's bytes, byte for byte as the simulator's own record has them: what the driver
    // sent is one unbroken stretch of what the simulator received; each piece of what the
    // driver read is, in order, in what the simulator sent (a late reply the driver discarded
    // unread is the only thing it may lack).
    let lost: u64 = b
        .messages
        .iter()
        .filter(|m| m.channel == Some(Channel::Wire))
        .map(|m| {
            let v: Value = serde_json::from_slice(&m.data).unwrap();
            v["lost_bytes"].as_u64().unwrap()
        })
        .sum();
    assert_eq!(lost, 0, "the tap lost bytes (its frames overflowed)");
    let wire = wire_of(&b, "left_arm");
    let sent: Vec<u8> = wire
        .iter()
        .filter(|c| c.1 == Direction::Sent)
        .flat_map(|c| c.2.clone())
        .collect();
    let sim_received = std::fs::read(dir.join("sim-wire/left_arm.received")).unwrap();
    let sim_sent = std::fs::read(dir.join("sim-wire/left_arm.sent")).unwrap();
    let before_trip = wire.iter().filter(|c| c.0 < trip_ns).count();
    assert!(before_trip > 1_000, "{before_trip} chunks before the trip");
    let first_ns = wire.first().unwrap().0;
    assert!(
        trip_ns - first_ns > 2_000_000_000,
        "the box holds {} s before the trip",
        (trip_ns - first_ns) as f64 * 1e-9
    );
    assert!(
        find(&sim_received, &sent, 0).is_some(),
        "the {} bytes the box says were sent are not one stretch of the {} the simulator received",
        sent.len(),
        sim_received.len()
    );
    let mut at = 0;
    let mut received = 0;
    for (t, _, bytes) in wire.iter().filter(|c| c.1 == Direction::Received) {
        at = find(&sim_sent, bytes, at).unwrap_or_else(|| {
            panic!("a read at {t} ns ({bytes:02x?}) is not in what the simulator sent after {at}")
        }) + bytes.len();
        received += bytes.len();
    }
    assert!(received > 10_000, "{received} bytes read");

    assert_python_agrees(trip_box, false);

    // The model lab reads the box as it is: one run of its joint states, the bus's motors
    // with their chain and servo model from the box's layout.
    let (_, analysis) = analyze(trip_box);
    assert_eq!(
        analysis["motors"].as_array().map(Vec::len),
        Some(8),
        "{analysis}"
    );

    // Replayed into the simulator with the scenario's payload and heating, the box agrees
    // with the simulator that recorded it (docs/blackbox.md, "Replay": bounds).
    let replay = replay(
        trip_box,
        &["--scenario", "overheat", "--thermal-speedup", "120"],
    );
    let servos = bus_servos(&replay, "left_arm");
    assert_eq!(servos.len(), 8, "{replay}");
    for s in servos {
        let compared = s["compared"].as_u64().unwrap();
        assert!(compared > 500, "{s}");
        assert_eq!(s["only_recorded"], 0, "{s}");
        // A reply the driver gave up on (the real-time simulator late on a loaded machine)
        // is one the replay still gets.
        assert!(s["only_simulated"].as_u64().unwrap() * 50 < compared, "{s}");
        assert!(error(s, "Present_Position", "rms") < 1.0, "{s}");
        assert!(error(s, "Present_Temperature", "rms") < 0.5, "{s}");
        assert!(error(s, "Present_Current", "rms") < 0.5, "{s}");
        assert!(error(s, "Present_Voltage", "max_abs") < 0.05, "{s}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// `nori sim replay BOX ARGS --json`.
fn replay(path: &Path, args: &[&str]) -> Value {
    let out = Command::new(binary("nori"))
        .args(["sim", "replay", "--json"])
        .arg(path)
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// A replay's servos on `bus`.
fn bus_servos<'a>(replay: &'a Value, bus: &str) -> &'a Vec<Value> {
    let b = replay["buses"]
        .as_array()
        .unwrap()
        .iter()
        .find(|b| b["bus"] == bus)
        .unwrap_or_else(|| panic!("no {bus} in {replay}"));
    b["servos"].as_array().unwrap()
}

/// A replayed servo's `figure` (`bias`, `rms`, `max_abs`) of `register`.
fn error(servo: &Value, register: &str, figure: &str) -> f64 {
    let r = servo["registers"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["register"] == register)
        .unwrap_or_else(|| panic!("{register} not compared: {servo}"));
    r["error"][figure].as_f64().unwrap()
}

/// The stall scenario with the black box beside it; its one box. `extension`: a model
/// extension the simulator runs on every servo.
fn stall_box(dir: &Path, extension: Option<&Path>) -> PathBuf {
    let mut cmd = Command::new(binary("nori"));
    cmd.args(["sim", "scenario", "stall", "--json", "--timeout", "120"])
        .arg("--blackbox")
        .arg(dir);
    if let Some(m) = extension {
        cmd.arg("--model-extension").arg(m);
    }
    let out = cmd.output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let boxes = files_ending(&dir.join("boxes"), ".mcap");
    assert_eq!(boxes.len(), 1, "{boxes:?}");
    boxes[0].clone()
}

/// The causes `nori model analyze` names from a box, and its JSON.
fn analyze(path: &Path) -> (Vec<String>, Value) {
    let out = Command::new(binary("nori"))
        .args(["model", "analyze", "--json"])
        .arg(path)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    let causes = v["causes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c.as_str().unwrap().to_string())
        .collect();
    (causes, v)
}

#[test]
fn a_supply_sag_hidden_in_the_simulator_shows_in_the_replay_and_the_lab_names_it() {
    let _one_at_a_time = nori_tests::serial();
    let dir = scratch("blackbox-hidden-sag");
    // The same scenario on the simulator as it is: the lab finds nothing, the replay agrees.
    let plain = stall_box(&dir.join("plain"), None);
    let (causes, v) = analyze(&plain);
    assert!(causes.is_empty(), "named on a plain box: {causes:?} {v}");
    for s in bus_servos(&replay(&plain, &["--scenario", "stall"]), "left_arm") {
        assert!(error(s, "Present_Voltage", "max_abs") < 0.05, "{s}");
    }

    // The supply sagging 0.25 Ω with the bus's current, hidden from both.
    let sag = dir.join("sag.toml");
    std::fs::write(
        &sag,
        "format = 1\ncause = \"supply_sag\"\nsupply-resistance-ohm = 0.25\n",
    )
    .unwrap();
    let sagged = stall_box(&dir.join("sagged"), Some(&sag));
    let nominal = replay(&sagged, &["--scenario", "stall"]);
    for s in bus_servos(&nominal, "left_arm") {
        // The simulator's supply stays up where the robot's sagged.
        assert!(error(s, "Present_Voltage", "bias") > 0.5, "{s}");
    }
    let sag_arg = sag.display().to_string();
    let modelled = replay(
        &sagged,
        &["--scenario", "stall", "--model-extension", &sag_arg],
    );
    for s in bus_servos(&modelled, "left_arm") {
        assert!(error(s, "Present_Voltage", "bias").abs() < 0.1, "{s}");
    }
    let (causes, v) = analyze(&sagged);
    assert_eq!(causes, ["supply_sag"], "{v}");
    let ohm = v["parameters"][0]["value"].as_f64().unwrap();
    assert!((ohm - 0.25).abs() < 0.05, "fitted {ohm} Ω for 0.25: {v}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The recorder's process on `stack`'s domain, its boxes in `boxes`.
/// The driver's cycles over `d`, read from its joint-state frames.
fn cycles_over(domain: &str, d: Duration) -> u64 {
    let node = telemetry::plane::Plane::open(domain, "bb-test-watch").unwrap();
    let states = node.subscriber(&telemetry::plane::JOINT_STATE).unwrap();
    let first = wait_for(Duration::from_secs(5), "a state frame", || {
        telemetry::plane::newest(&states)
    });
    let start = Instant::now();
    let mut last = first;
    while start.elapsed() < d {
        if let Some(s) = telemetry::plane::newest(&states) {
            assert_eq!(
                s.flags & telemetry::frames::STATE_FLAG_SAFE_STATE,
                0,
                "the driver fell into its safe state"
            );
            last = s;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    last.seq - first.seq
}

#[test]
fn a_recorder_killed_mid_box_leaves_it_readable_and_a_stopped_one_holds_nothing_up() {
    let _one_at_a_time = nori_tests::serial();
    let mut stack = ArmStack::start("blackbox-kill", &[]);
    let boxes = stack.dir.join("boxes");
    std::fs::create_dir_all(&boxes).unwrap();
    let mut rec = stack.recorder(&boxes, &[], "blackbox-1.log");
    nori_tests::wait_for(Duration::from_secs(20), "the driver to drive", || {
        (cycles_over(&stack.domain, Duration::from_millis(200)) > 0).then_some(())
    });
    std::thread::sleep(Duration::from_secs(2));
    let saved = Command::new(binary("nori-blackbox"))
        .args(["save", "--domain", &stack.domain])
        .output()
        .unwrap();
    assert!(
        saved.status.success(),
        "{}",
        String::from_utf8_lossy(&saved.stderr)
    );
    let partial = wait_for(Duration::from_secs(5), "a box being frozen", || {
        files_ending(&boxes, PARTIAL_SUFFIX).pop()
    });
    assert!(partial.to_string_lossy().contains("saved"), "{partial:?}");
    // Two of its one-second flushes, then killed mid-box.
    std::thread::sleep(Duration::from_millis(2_500));
    rec.kill();
    let cut = read_box(&partial);
    assert!(!cut.extent.complete);
    let states = cut
        .messages
        .iter()
        .filter(|m| m.channel == Some(Channel::JointStates))
        .count();
    assert!(
        states > 400,
        "{states} joint-state frames kept of the seconds before the kill"
    );
    // What came after the save reached the disk by the once-a-second flushes, not only the
    // ring's copy at the box's opening: more than a second of it.
    let saved_at = cut
        .messages
        .iter()
        .find(|m| m.channel == Some(Channel::Triggers))
        .map(|m| m.log_time)
        .expect("the trigger in the box");
    let after = cut
        .messages
        .iter()
        .filter(|m| m.channel == Some(Channel::JointStates) && m.log_time > saved_at)
        .count();
    assert!(
        after > 200,
        "{after} joint-state frames after the save were flushed before the kill"
    );
    assert!(!wire_of(&cut, "left_arm").is_empty());
    assert!(cut
        .messages
        .iter()
        .any(|m| m.channel == Some(Channel::Triggers)));
    assert_python_agrees(&partial, true);

    // Stopped (SIGSTOP: a hung recorder), it holds the driver to nothing: the driver's cycles
    // over two seconds are those of the two seconds before.
    let mut rec = stack.recorder(&boxes, &[], "blackbox-2.log");
    // Made whole beside the recording loop, the cut file kept beside it.
    let whole = wait_for(Duration::from_secs(20), "the cut box made whole", || {
        (!partial.exists()).then(|| files_ending(&boxes, ".mcap"))
    });
    assert_eq!(
        whole.len(),
        1,
        "the cut box made whole at the restart: {whole:?}"
    );
    assert_eq!(files_ending(&boxes, ".mcap.cut").len(), 1);
    let recovered = read_box(&whole[0]);
    assert!(recovered.extent.complete);
    assert_eq!(recovered.messages.len(), cut.messages.len());
    let running = cycles_over(&stack.domain, Duration::from_secs(2));
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(rec.pid() as i32),
        nix::sys::signal::Signal::SIGSTOP,
    )
    .unwrap();
    let hung = cycles_over(&stack.domain, Duration::from_secs(2));
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(rec.pid() as i32),
        nix::sys::signal::Signal::SIGCONT,
    )
    .unwrap();
    assert!(
        hung * 10 >= running * 9,
        "the driver ran {hung} cycles with the recorder stopped, {running} before"
    );
    assert!(stack.driver.running() && stack.supervisor.running());
    rec.terminate(Duration::from_secs(5));
}
