//! What every process of the stack does first: log to stderr (level from `RUST_LOG`, default
//! info), and turn SIGINT/SIGTERM into a flag its loop checks, so it can stop cleanly (torque
//! off, in the driver's case) instead of dying.

use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// Logging to stderr, level from `RUST_LOG` (default `info`).
pub fn init_logging() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
}

/// A flag set when SIGINT or SIGTERM arrives.
pub fn stop_flag() -> std::io::Result<Arc<AtomicBool>> {
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(signal, stop.clone())?;
    }
    Ok(stop)
}
