//! cargo-fuzz target: `bodies::telemetry_csv` (see `fuzz/bodies.rs`).
#![no_main]

#[path = "../bodies.rs"]
mod bodies;

libfuzzer_sys::fuzz_target!(|data: &[u8]| bodies::telemetry_csv(data));
