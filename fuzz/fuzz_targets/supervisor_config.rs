//! cargo-fuzz target: `bodies::supervisor_config` (see `fuzz/bodies.rs`).
#![no_main]

#[path = "../bodies.rs"]
mod bodies;

libfuzzer_sys::fuzz_target!(|data: &[u8]| bodies::supervisor_config(data));
