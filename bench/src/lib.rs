//! What the benchmarks' processes share: `nori-bench` (the benchmarks) and the helper processes
//! it starts (`nori-bench-plane-reader`, `nori-bench-fleet-publisher`).

use fleet_agent::config::ZenohConfig;
use fleet_agent::schema::{JointMsg, StateMsg, SCHEMA_VERSION};
use telemetry::clock::monotonic_ns;

/// A transport under test.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Transport {
    /// iceoryx2 publish-subscribe, the reader polling.
    Iceoryx2,
    /// A Unix datagram socket, postcard-encoded, the reader blocking in recv.
    Uds,
}

/// A zenoh session in `mode`, listening on and connecting to the given endpoints.
pub fn zenoh_session(
    listen: Vec<String>,
    connect: Vec<String>,
    mode: &str,
) -> Result<fleet_agent::zenoh::Session, fleet_agent::net::NetError> {
    fleet_agent::net::open(&ZenohConfig {
        mode: mode.into(),
        listen,
        connect,
        config_file: None,
    })
}

/// An 18-joint state message (the A3's bus joints) as a robot's agent sends it.
pub fn state_msg(seq: u64) -> StateMsg {
    StateMsg {
        version: SCHEMA_VERSION,
        seq,
        timestamp_ns: monotonic_ns(),
        wall_ms: 0,
        safe_state: false,
        deadline_misses: 0,
        joints: (0..18)
            .map(|i| JointMsg {
                position: 0.01 * i as f32,
                velocity: 0.0,
                temperature_c: 30.0,
                current_a: 0.1,
                goal: 0.0,
                valid: true,
                torque: true,
                flags: 0,
            })
            .collect(),
    }
}
