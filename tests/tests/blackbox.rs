//! The black box on the simulated robot: the overheat scenario's trip freezes a box holding the
//! bus's bytes as the simulator's own record of its wire has them and the trip; a box read by
//! the official `mcap` package with every message checked against its schema; the recorder
//! killed in the middle of a box leaves it readable and made whole at its restart; the
//! recorder stopped leaves the driver's loop as it was; and a box shows a viewer the cameras'
//! thumbnails and the arm's frames, opened by Rerun's loader too.

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

/// Rerun's own MCAP loader (`rerun mcap convert`, from the `rerun-sdk` package), its messages
/// per topic as the recording it makes holds them; `None` (said) without Rerun, except in CI.
fn rerun_counts(path: &Path, dir: &Path) -> Option<std::collections::BTreeMap<String, u64>> {
    let rerun = |args: &[&str]| {
        // Rerun sends usage data unless it sees CI (its own check): never from a test.
        Command::new("python3")
            .args(["-m", "rerun"])
            .args(args)
            .env("CI", "true")
            .output()
            .unwrap()
    };
    if !rerun(&["--version"]).status.success() {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI needs Rerun (the rerun-sdk Python package: .ci/run installs it)"
        );
        eprintln!("note: python3 has no rerun-sdk: the box is not opened by Rerun's loader");
        return None;
    }
    let rrd = dir.join("box.rrd");
    let out = rerun(&[
        "mcap",
        "convert",
        &path.display().to_string(),
        "-o",
        &rrd.display().to_string(),
    ]);
    assert!(
        out.status.success(),
        "Rerun refused the box: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let printed = rerun(&["rrd", "print", &rrd.display().to_string()]);
    assert!(printed.status.success());
    // One line per chunk: `Chunk(…) with N rows (…) - /topic - data columns: [McapMessage:data]`.
    let mut counts = std::collections::BTreeMap::new();
    for line in String::from_utf8_lossy(&printed.stdout).lines() {
        let Some(rest) = line.strip_prefix("Chunk(") else {
            continue;
        };
        if !line.contains("McapMessage:data") {
            continue;
        }
        let words: Vec<&str> = rest.split_whitespace().collect();
        let rows: u64 = words[2].parse().unwrap();
        let topic = words.iter().skip_while(|w| **w != "-").nth(1).unwrap();
        *counts.entry(topic.to_string()).or_default() += rows;
    }
    Some(counts)
}

/// Composes the `/tf` tree of one message from `odom` down to `leaf`: its position in `odom`.
fn tree_position(tf: &Value, leaf: &str) -> Option<[f64; 3]> {
    use nalgebra::{Quaternion, UnitQuaternion, Vector3};
    let all = tf["transforms"].as_array().unwrap();
    let mut chain = Vec::new();
    let mut at = leaf.to_string();
    while let Some(t) = all.iter().find(|t| t["child_frame_id"] == at.as_str()) {
        chain.push(t);
        at = t["parent_frame_id"].as_str().unwrap().to_string();
    }
    if at != "odom" || chain.is_empty() {
        return None;
    }
    let (mut p, mut r) = (Vector3::zeros(), UnitQuaternion::identity());
    for t in chain.iter().rev() {
        let v = |o: &Value, k: &str| o[k].as_f64().unwrap();
        let (tr, q) = (&t["translation"], &t["rotation"]);
        p += r * Vector3::new(v(tr, "x"), v(tr, "y"), v(tr, "z"));
        r *= UnitQuaternion::from_quaternion(Quaternion::new(
            v(q, "w"),
            v(q, "x"),
            v(q, "y"),
            v(q, "z"),
        ));
    }
    Some([p.x, p.y, p.z])
}

/// Seconds between the first and the last of `msgs` by their `timestamp_ns`.
fn span_s(msgs: &[Value]) -> f64 {
    let t = |v: &Value| v["timestamp_ns"].as_u64().unwrap() as f64 * 1e-9;
    t(msgs.last().unwrap()) - t(&msgs[0])
}

/// The running camera's thumbnails (the second of the box's cameras): two a second, each a
/// 160×120 JPEG; none of the camera that is not running.
fn check_thumbnails(b: &ReadBox) {
    let thumbs: Vec<Value> = b
        .messages
        .iter()
        .filter(|m| m.channel == Some(Channel::Thumbnail(1)))
        .map(|m| serde_json::from_slice(&m.data).unwrap())
        .collect();
    assert!(
        thumbs.iter().all(|t| t["frame_id"] == "left_wrist"),
        "{:?}",
        thumbs.first()
    );
    assert!(!b.messages.iter().any(|m| m.topic.contains("/head/")));
    assert!(thumbs.len() >= 8, "{} thumbnails", thumbs.len());
    let rate = (thumbs.len() - 1) as f64 / span_s(&thumbs);
    assert!((1.5..=2.2).contains(&rate), "{rate:.2} thumbnails a second");
    for t in &thumbs {
        use base64::Engine;
        let jpeg = base64::engine::general_purpose::STANDARD
            .decode(t["data"].as_str().unwrap())
            .unwrap();
        let mut d = zune_jpeg::JpegDecoder::new(zune_core::bytestream::ZCursor::new(&jpeg));
        let pixels = d.decode().unwrap();
        assert_eq!(d.dimensions(), Some((160, 120)));
        assert_eq!(pixels.len(), 160 * 120 * 3);
        assert_eq!(t["format"], "jpeg");
    }
}

/// The arm's frames, twenty a second, each from the joint-state frame of its stamp: composed,
/// they put the tool where the description (`robot`) puts it at those joint readings, and the
/// tool moved.
fn check_frames(b: &ReadBox, robot: &Path) {
    let states: std::collections::BTreeMap<u64, Value> = b
        .messages
        .iter()
        .filter(|m| m.channel == Some(Channel::JointStates))
        .map(|m| serde_json::from_slice::<Value>(&m.data).unwrap())
        .map(|v| (v["timestamp_ns"].as_u64().unwrap(), v))
        .collect();
    let trees: Vec<Value> = b
        .messages
        .iter()
        .filter(|m| m.channel == Some(Channel::Transforms))
        .map(|m| serde_json::from_slice(&m.data).unwrap())
        .collect();
    assert!(trees.len() > 40, "{} trees", trees.len());
    let rate = (trees.len() - 1) as f64 / span_s(&trees);
    assert!((15.0..=21.0).contains(&rate), "{rate:.1} trees a second");
    let description = body::RobotDescription::load(robot).unwrap();
    let kinematics = body::kinematics::Body::from_description(&description).unwrap();
    let chain = &kinematics.arms()[0];
    let mut tools = Vec::new();
    for tree in &trees {
        assert!(
            tree_position(tree, "right_arm_tool").is_none(),
            "the right arm is not driven here: not drawn"
        );
        let state = &states[&tree["timestamp_ns"].as_u64().unwrap()];
        let q: Vec<f64> = chain
            .joint_names
            .iter()
            .map(|n| {
                let k = state["name"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .position(|x| x == n.as_str())
                    .unwrap();
                state["position"][k].as_f64().unwrap()
            })
            .collect();
        let lift = kinematics.lift_start_m();
        let want = kinematics
            .arm_pose(0, &q, lift, Default::default())
            .unwrap();
        let got = tree_position(tree, "left_arm_tool").unwrap();
        for (g, w) in got.iter().zip(want.tool) {
            assert!((g - w).abs() < 1e-4, "{got:?} against {:?}", want.tool);
        }
        tools.push(got);
    }
    let travel = tools
        .iter()
        .map(|t| {
            t.iter()
                .zip(&tools[0])
                .map(|(a, b)| (a - b).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .fold(0.0, f64::max);
    assert!(travel > 0.02, "the tool moved {travel:.3} m in the box");
}

#[test]
fn a_box_shows_a_viewer_the_cameras_and_the_arm_moving() {
    use std::sync::atomic::{AtomicBool, Ordering};
    let _one_at_a_time = nori_tests::serial();
    let files = scratch("blackbox-view-files");
    let (robot, camera_toml) = nori_tests::small_camera_files(&files);
    let stack = ArmStack::start("blackbox-view", &["--description", &robot]);
    let mut camera = stack.camera("left_wrist", &camera_toml, 1);
    // Two cameras asked for, the second running: the first gives no thumbnails and holds
    // nothing up, and the second's are its own (not numbered among the running ones).
    let config = files.join("blackbox.toml");
    std::fs::write(
        &config,
        <blackbox::config::BlackboxConfig as telemetry::config::ProcessConfig>::DEFAULT_TOML
            .replace("after-seconds = 10", "after-seconds = 2")
            .replace(
                "cameras = [\"head\", \"neck\", \"left_wrist\", \"right_wrist\"]",
                "cameras = [\"head\", \"left_wrist\"]",
            )
            .replace("every-s = 1.0", "every-s = 0.5")
            .replace("hz = 10.0", "hz = 20.0"),
    )
    .unwrap();
    let boxes = stack.dir.join("boxes");
    std::fs::create_dir_all(&boxes).unwrap();
    let config_arg = config.display().to_string();
    let mut rec = stack.recorder(
        &boxes,
        &["--config", &config_arg, "--robot", &robot],
        "blackbox.log",
    );
    // The shoulder raised while the ring records: the arm the box draws moves.
    let stop = std::sync::Arc::new(AtomicBool::new(false));
    let mover = nori_tests::hold_horizontal(&stack.domain, "left_shoulder_pitch", stop.clone());
    std::thread::sleep(Duration::from_secs(5));
    nori_tests::nori_ok(&["blackbox", "save"], &stack.domain);
    let path = wait_for(Duration::from_secs(20), "the saved box whole", || {
        files_ending(&boxes, ".mcap").pop()
    });
    stop.store(true, Ordering::Relaxed);
    mover.join().unwrap();
    let b = read_box(&path);
    assert!(b.extent.complete);
    assert_eq!(
        frozen::cameras(&b.metadata),
        ["head", "left_wrist"],
        "{:?}",
        b.metadata
    );

    check_thumbnails(&b);
    check_frames(&b, Path::new(&robot));

    // The official reader checks every message against its schema (Foxglove's among them), and
    // Rerun's loader takes every message of every topic.
    assert_python_agrees(&path, false);
    if let Some(rerun) = rerun_counts(&path, &stack.dir) {
        let ours = blackbox::export::summary(&std::fs::read(&path).unwrap()).per_topic;
        for (topic, n) in &ours {
            assert_eq!(rerun.get(topic), Some(&(*n as u64)), "{topic}: {rerun:?}");
        }
    }
    let (_, said) = rec.terminate(Duration::from_secs(5));
    let end: Value = serde_json::from_str(said.lines().last().unwrap_or("{}")).unwrap();
    assert_eq!(end["thumbnails_failed"], 0, "{said}");
    assert_eq!(
        end["joint_states_missed"], 0,
        "the recorder fell behind: {said}"
    );
    camera.terminate(Duration::from_secs(5));
    stack.stop();
}
