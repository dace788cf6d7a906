//! The paper's protections on the whole multi-process stack (simulator, supervisor, driver as
//! separate processes): `nori sim scenario overheat|stall|grip --json`, checked field by field.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use nori_tests::binary;
use serde_json::Value;
use std::process::Command;

fn scenario(name: &str) -> Value {
    scenario_with(name, &[])
}

fn scenario_with(name: &str, extra: &[&str]) -> Value {
    // One scenario at a time: each runs three processes on a two-core machine.
    let _one_at_a_time = nori_tests::serial();
    let out = Command::new(binary("nori"))
        .args(["sim", "scenario", name, "--json", "--timeout", "120"])
        .args(extra)
        .output()
        .expect("running nori sim scenario");
    assert!(
        out.status.success(),
        "{name}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
    assert_eq!(v["timed_out"], false, "{name} did not reach its end: {v}");
    v
}

fn kinds(v: &Value, joint: &str) -> Vec<String> {
    v["events"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["joint"] == joint)
        .map(|e| e["kind"].as_str().unwrap().to_string())
        .collect()
}

#[test]
fn overheat_trips_the_bus_in_software_before_any_firmware_cutoff() {
    let v = scenario("overheat");
    assert!(
        v["software_trip_s"].as_f64().is_some(),
        "no software trip: {v}"
    );
    assert_eq!(v["bus_disabled"], true);
    assert_eq!(
        v["hardware_cutoff_fired"], false,
        "the firmware cutoff fired: {v}"
    );
    let max = v["max_temperature_c"].as_f64().unwrap();
    assert!(max < 60.0 && max > 55.0, "hottest winding {max} °C");
    let events = kinds(&v, "left_shoulder_pitch");
    let trip = events.iter().position(|k| k == "ThermalTrip").unwrap();
    assert!(
        events[..trip].iter().any(|k| k == "ThermalWarning"),
        "warned before the trip: {events:?}"
    );
    // The bus's torque-off reached the wire because of the trip, before the scenario stopped
    // the driver (whose own stop turns torque off too), and within a few control cycles.
    let reaction = v["trip_reaction_ms"]
        .as_f64()
        .unwrap_or_else(|| panic!("no torque-off before the stop: {v}"));
    assert!(reaction < 100.0, "trip reaction {reaction} ms");
}

#[test]
fn a_joint_driven_into_an_obstacle_is_retried_then_reduced() {
    let v = scenario("stall");
    assert!(v["stall_events"].as_u64().unwrap() >= 1);
    assert_eq!(v["torque_reduced"], true);
    let events = kinds(&v, "left_shoulder_pitch");
    let first = |k: &str| events.iter().position(|e| e == k);
    let (stall, retry, reduced) = (
        first("Stall").unwrap(),
        first("StallRetry").unwrap(),
        first("TorqueReduced").unwrap(),
    );
    assert!(
        stall <= retry && retry < reduced,
        "stall, one retry, then reduced: {events:?}"
    );
    assert_eq!(v["bus_disabled"], false);
}

#[test]
fn the_gripper_holds_gently_with_a_monotone_force_estimate() {
    let v = scenario("grip");
    assert_eq!(
        v["torque_reduced"], true,
        "the gripper drops to its grip torque: {v}"
    );
    assert!(v["stall_events"].as_u64().unwrap() >= 1);
    assert!(v["grip_force_max"].as_f64().unwrap() > 0.9);
    assert!(v["grip_squeeze_samples"].as_u64().unwrap() > 50);
    assert_eq!(
        v["grip_force_monotone_in_depth"], true,
        "{}",
        v["grip_force_by_depth"]
    );
}

/// The supervisor SIGKILLed at 55 °C in the overheat set-up and not restarted: the driver's own
/// last-resort tier turns the bus off at the trip temperature, before the firmware's 60 °C; a
/// supervisor started afterwards takes the trip over and records it.
#[test]
fn with_the_supervisor_dead_the_driver_trips_the_hot_bus_itself() {
    let v = scenario_with("overheat", &["--kill-supervisor-at", "55"]);
    let killed = v["supervisor_killed_s"]
        .as_f64()
        .expect("supervisor killed");
    let tripped = v["driver_trip_s"]
        .as_f64()
        .expect("the driver never tripped the bus");
    assert!(tripped > killed, "{v}");
    assert_eq!(
        v["hardware_cutoff_fired"], false,
        "the firmware cutoff fired: {v}"
    );
    let max = v["max_temperature_c"].as_f64().unwrap();
    assert!(max < 60.0, "hottest winding {max} °C");
    assert!(
        v["trip_reaction_ms"].as_f64().is_some(),
        "the bus's torque-off reached the wire before the stop: {v}"
    );
    let events: Vec<&str> = v["events"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|e| e["kind"].as_str())
        .collect();
    let taken = events.iter().position(|k| *k == "DriverTrip");
    let latched = events.iter().rposition(|k| *k == "ThermalTrip");
    assert!(
        taken.is_some() && latched > taken,
        "the returning supervisor took the trip over: {events:?}"
    );
    assert!(
        v["trip_record"]
            .as_array()
            .unwrap()
            .iter()
            .any(|j| j == "left_shoulder_pitch"),
        "the trip is recorded: {v}"
    );
}
