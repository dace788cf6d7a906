//! cargo-fuzz target: `bodies::camera_stream` (see `fuzz/bodies.rs`).
#![no_main]

#[path = "../bodies.rs"]
mod bodies;

libfuzzer_sys::fuzz_target!(|data: &[u8]| bodies::camera_stream(data));
