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

/// Peak resident set of a process, MB (VmHWM); `None` once it is gone.
pub fn peak_rss_mb(pid: u32) -> Option<f64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// CPU time a process has used so far, s (user + system); `None` once it is gone.
pub fn cpu_seconds(pid: u32) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // /proc counts in USER_HZ, which Linux fixes at 100 on every architecture (x86-64, arm64).
    const USER_HZ: f64 = 100.0;
    Some(cpu_ticks(&stat)? as f64 / USER_HZ)
}

/// utime + stime of a `/proc/<pid>/stat` line: its 14th and 15th fields, counted after the
/// command name, which is in parentheses and may itself hold spaces and parentheses.
fn cpu_ticks(stat: &str) -> Option<u64> {
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    let field = |n: usize| fields.get(n - 3)?.parse::<u64>().ok();
    Some(field(14)? + field(15)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_time_is_read_from_utime_and_stime_after_an_awkward_name() {
        let line = "4242 (nori (cam) x) S 1 4242 4242 0 -1 4194560 900 0 7 0 \
                    1234 56 0 0 20 0 5 0 98765 123456789 3000 18446744073709551615";
        assert_eq!(cpu_ticks(line), Some(1234 + 56));
        assert_eq!(cpu_ticks("no parenthesis"), None);
        // This process: some CPU, and more after work.
        let me = std::process::id();
        let before = cpu_seconds(me).unwrap();
        let start = std::time::Instant::now();
        let mut x = 0u64;
        while start.elapsed() < std::time::Duration::from_millis(300) {
            x = std::hint::black_box(x.wrapping_mul(31).wrapping_add(7));
        }
        assert!(cpu_seconds(me).unwrap() > before);
    }
}
