//! The Python client (`python/nori_client`) reads the fleet's messages with a codec driven by
//! `schema.json`, the formats of these Rust types as `serde-reflection` traces them, and both
//! sides check the same golden bytes (`python/nori_client/tests/golden.json`). A change to a
//! message fails here until the file is regenerated (`NORI_BLESS=1 cargo test -p fleet-agent
//! --test python_schema`), and then fails the Python tests until the client follows.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use fleet_agent::schema::{
    decode, encode, AckMsg, ActionChunk, BoxAckMsg, BoxChunkMsg, EventMsg, LayoutMsg,
    ObservationMsg, PreviewMsg, ScanMsg, StateMsg, StatusMsg, SCHEMA_VERSION,
};
use serde::{de::DeserializeOwned, Serialize};
use serde_json::{json, Value};
use serde_reflection::{Tracer, TracerConfig};
use std::path::PathBuf;

fn python_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../python/nori_client")
}

fn bless() -> bool {
    std::env::var_os("NORI_BLESS").is_some()
}

/// Every message that crosses zenoh, by its Rust name.
const MESSAGES: [&str; 11] = [
    "StateMsg",
    "LayoutMsg",
    "EventMsg",
    "ObservationMsg",
    "ActionChunk",
    "StatusMsg",
    "PreviewMsg",
    "ScanMsg",
    "AckMsg",
    "BoxChunkMsg",
    "BoxAckMsg",
];

fn traced() -> Value {
    let mut tracer = Tracer::new(TracerConfig::default());
    tracer.trace_simple_type::<StateMsg>().unwrap();
    tracer.trace_simple_type::<LayoutMsg>().unwrap();
    tracer.trace_simple_type::<EventMsg>().unwrap();
    tracer.trace_simple_type::<ObservationMsg>().unwrap();
    tracer.trace_simple_type::<ActionChunk>().unwrap();
    tracer.trace_simple_type::<StatusMsg>().unwrap();
    tracer.trace_simple_type::<PreviewMsg>().unwrap();
    tracer.trace_simple_type::<ScanMsg>().unwrap();
    tracer.trace_simple_type::<AckMsg>().unwrap();
    tracer.trace_simple_type::<BoxChunkMsg>().unwrap();
    tracer.trace_simple_type::<BoxAckMsg>().unwrap();
    let registry = tracer.registry().unwrap();
    json!({
        "about": "The fleet messages' formats traced from fleet_agent::schema by serde-reflection (fleet-agent/tests/python_schema.rs); do not edit.",
        "version": SCHEMA_VERSION,
        "messages": MESSAGES,
        "types": registry,
    })
}

/// Compares `text` with the file at `path`, or writes it there when blessing.
fn check_file(path: &PathBuf, text: &str) {
    if bless() {
        std::fs::write(path, text).unwrap();
        return;
    }
    let on_disk = std::fs::read_to_string(path).unwrap_or_default();
    assert!(
        on_disk == text,
        "{} is not what the Rust types trace: a message changed. Regenerate it with \
         NORI_BLESS=1 cargo test -p fleet-agent --test python_schema, then make the Python \
         client and its tests follow.",
        path.display()
    );
}

#[test]
fn the_python_schema_is_traced_from_the_rust_types() {
    let text = serde_json::to_string_pretty(&traced()).unwrap() + "\n";
    check_file(&python_dir().join("src/nori_client/schema.json"), &text);
}

/// `value` as message `T`: its bytes, and the value read back from them.
fn golden<T: Serialize + DeserializeOwned>(value: &Value) -> (String, Value) {
    let msg: T = serde_json::from_value(value.clone()).unwrap_or_else(|e| {
        panic!(
            "a golden value is not a {}: {e}",
            std::any::type_name::<T>()
        )
    });
    let bytes = encode(&msg);
    let back: T = decode(&bytes).unwrap();
    let hex = bytes.iter().map(|b| format!("{b:02x}")).collect();
    (hex, serde_json::to_value(back).unwrap())
}

#[test]
fn golden_bytes_are_what_the_rust_side_writes_and_reads() {
    let path = python_dir().join("tests/golden.json");
    let mut file: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let mut covered = std::collections::BTreeSet::new();
    for entry in file["messages"].as_array_mut().unwrap() {
        let kind = entry["type"].as_str().unwrap().to_string();
        let (hex, back) = match kind.as_str() {
            "StateMsg" => golden::<StateMsg>(&entry["value"]),
            "LayoutMsg" => golden::<LayoutMsg>(&entry["value"]),
            "EventMsg" => golden::<EventMsg>(&entry["value"]),
            "ObservationMsg" => golden::<ObservationMsg>(&entry["value"]),
            "ActionChunk" => golden::<ActionChunk>(&entry["value"]),
            "StatusMsg" => golden::<StatusMsg>(&entry["value"]),
            "PreviewMsg" => golden::<PreviewMsg>(&entry["value"]),
            "ScanMsg" => golden::<ScanMsg>(&entry["value"]),
            "AckMsg" => golden::<AckMsg>(&entry["value"]),
            "BoxChunkMsg" => golden::<BoxChunkMsg>(&entry["value"]),
            "BoxAckMsg" => golden::<BoxAckMsg>(&entry["value"]),
            other => panic!("golden.json names {other}, not a fleet message"),
        };
        // Values are chosen exact in f32, so reading back gives the very same JSON.
        assert_eq!(back, entry["value"], "{kind} does not read back as written");
        if !bless() {
            assert_eq!(entry["hex"], hex, "{kind}: the bytes changed");
        }
        entry["hex"] = Value::String(hex);
        covered.insert(kind);
    }
    assert_eq!(
        covered.into_iter().collect::<Vec<_>>(),
        {
            let mut all = MESSAGES.map(String::from).to_vec();
            all.sort();
            all
        },
        "every message has golden bytes"
    );
    check_file(
        &path,
        &(serde_json::to_string_pretty(&file).unwrap() + "\n"),
    );
}
