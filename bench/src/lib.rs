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

/// An 18-joint state message (the A3's bus joints, the lift and the base) as a robot's agent
/// sends it.
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
        lift: Some(fleet_agent::schema::LiftMsg {
            height_m: 0.4,
            goal_m: 0.4,
            state: 2,
            held: 0,
            duty_wait_s: 0.0,
        }),
        base: Some(fleet_agent::schema::BaseMsg {
            x_m: 1.0,
            y_m: -0.5,
            heading_rad: 0.3,
            linear_m_s: 0.1,
            angular_rad_s: 0.0,
            field_distance_m: 2.0,
            flags: 0,
        }),
    }
}

/// A `/proc/<pid>/status` memory line (`VmHWM`, `RssAnon`, ...) of a process, MB; `None` once
/// it is gone.
fn status_mb(pid: &str, key: &str) -> Option<f64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status
        .lines()
        .find(|l| l.strip_prefix(key).is_some_and(|r| r.starts_with(':')))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// Peak resident set of a process, MB (VmHWM); `None` once it is gone.
pub fn peak_rss_mb(pid: u32) -> Option<f64> {
    status_mb(&pid.to_string(), "VmHWM")
}

/// Anonymous resident memory of a process now, MB (`RssAnon`); `None` once it is gone.
pub fn rss_anon_mb(pid: u32) -> Option<f64> {
    status_mb(&pid.to_string(), "RssAnon")
}

/// /proc counts CPU time in USER_HZ, which Linux fixes at 100 on every architecture.
const USER_HZ: f64 = 100.0;

/// Fields `numbers` (1-based, as `man 5 proc` numbers them) of `/proc/<pid>/stat`.
fn stat_fields<const N: usize>(pid: &str, numbers: [usize; N]) -> Option<[u64; N]> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    stat_line_fields(&stat, numbers)
}

/// Fields of a `/proc/<pid>/stat` line, counted after the command name, which is in
/// parentheses and may itself hold spaces and parentheses.
fn stat_line_fields<const N: usize>(stat: &str, numbers: [usize; N]) -> Option<[u64; N]> {
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    let mut out = [0u64; N];
    for (o, n) in out.iter_mut().zip(numbers) {
        *o = fields.get(n.checked_sub(3)?)?.parse().ok()?;
    }
    Some(out)
}

/// CPU time a process has used so far, s (utime + stime); `None` once it is gone.
pub fn cpu_seconds(pid: u32) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    Some(cpu_ticks(&stat)? as f64 / USER_HZ)
}

/// utime + stime of a `/proc/<pid>/stat` line (its 14th and 15th fields).
fn cpu_ticks(stat: &str) -> Option<u64> {
    let [user, system] = stat_line_fields(stat, [14, 15])?;
    Some(user + system)
}

/// CPU time of this process's waited-for children (and theirs), s (cutime + cstime).
pub fn children_cpu_seconds() -> Option<f64> {
    let [user, system] = stat_fields("self", [16, 17])?;
    Some((user + system) as f64 / USER_HZ)
}

/// Process ids whose parent is `parent`.
pub fn children_of(parent: u32) -> Vec<u32> {
    let Ok(dir) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    dir.flatten()
        .filter_map(|e| e.file_name().to_str()?.parse::<u32>().ok())
        .filter(|pid| stat_fields(&pid.to_string(), [4]) == Some([u64::from(parent)]))
        .collect()
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
