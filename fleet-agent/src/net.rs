//! Opening a zenoh session from the stack's configuration. zenoh is re-exported from this
//! crate so that the rest of the workspace uses the one version pinned here.

use crate::config::ZenohConfig;
use thiserror::Error;

/// Sessions a node of the fleet tier accepts (zenoh's `transport/unicast/max_sessions`, 1 000
/// by default, past which a robot is refused): a site router's robots, a cloud router's sites
/// and services, a fleet-side process's robots when they connect to it straight. The rule
/// and its figures (file descriptors, memory per session): `docs/fleet-sizing.md`.
pub const FLEET_NODE_MAX_SESSIONS: usize = 10_000;

/// File descriptors a fleet node needs for `max_sessions` sessions: one socket each, and what
/// the process holds besides (listeners, its own links, files, the runtime's).
pub fn descriptors_for(max_sessions: usize) -> u64 {
    max_sessions as u64 + 512
}

/// A session that could not be opened.
#[derive(Debug, Error)]
pub enum NetError {
    /// The JSON5 file or a key could not be applied.
    #[error("zenoh configuration: {0}")]
    Config(String),
    /// zenoh refused to open (endpoint in use, bad certificate ...).
    #[error("opening the zenoh session: {0}")]
    Open(String),
}

/// The zenoh configuration for `z`: its JSON5 file first, then mode and endpoints, with
/// multicast scouting off (robots find the fleet through configured endpoints, never by
/// broadcasting on a home network).
pub fn zenoh_config(z: &ZenohConfig) -> Result<zenoh::Config, NetError> {
    let mut config = match &z.config_file {
        Some(path) => zenoh::Config::from_file(path)
            .map_err(|e| NetError::Config(format!("{}: {e}", path.display())))?,
        None => zenoh::Config::default(),
    };
    let json = |v: &Vec<String>| serde_json::to_string(v).unwrap_or_else(|_| "[]".into());
    for (key, value) in [
        ("mode", format!("{:?}", z.mode)),
        ("connect/endpoints", json(&z.connect)),
        ("listen/endpoints", json(&z.listen)),
        ("scouting/multicast/enabled", "false".into()),
    ] {
        config
            .insert_json5(key, &value)
            .map_err(|e| NetError::Config(format!("{key} = {value}: {e}")))?;
    }
    Ok(config)
}

/// Opens a session configured wholly by a zenoh JSON5 file (a router, a client identity).
pub fn open_file(path: &std::path::Path) -> Result<zenoh::Session, NetError> {
    use zenoh::Wait;
    let config = zenoh::Config::from_file(path)
        .map_err(|e| NetError::Config(format!("{}: {e}", path.display())))?;
    zenoh::open(config)
        .wait()
        .map_err(|e| NetError::Open(e.to_string()))
}

/// Opens the session of a fleet-side process (`nori fleet`, `nori policy-server`): wholly from
/// its zenoh JSON5 file when given (a TLS identity, a client of the router the file names), else
/// a peer on `listen` and `connect`, listening on `default_listen` when told neither (where the
/// robots' agents connect by default).
pub fn open_fleet_side(
    zenoh_config: Option<&std::path::Path>,
    listen: &[String],
    connect: &[String],
    default_listen: &str,
) -> Result<zenoh::Session, NetError> {
    if let Some(file) = zenoh_config {
        return open_file(file);
    }
    let mut config = self::zenoh_config(&ZenohConfig {
        mode: "peer".into(),
        listen: if listen.is_empty() && connect.is_empty() {
            vec![default_listen.into()]
        } else {
            listen.to_vec()
        },
        connect: connect.to_vec(),
        config_file: None,
    })?;
    // Robots connect to it straight: every one of them a session.
    let key = "transport/unicast/max_sessions";
    config
        .insert_json5(key, &FLEET_NODE_MAX_SESSIONS.to_string())
        .map_err(|e| NetError::Config(format!("{key}: {e}")))?;
    use zenoh::Wait;
    zenoh::open(config)
        .wait()
        .map_err(|e| NetError::Open(e.to_string()))
}

/// The sessions `config` accepts (`transport/unicast/max_sessions`).
pub fn max_sessions(config: &zenoh::Config) -> Option<usize> {
    config
        .get_json("transport/unicast/max_sessions")
        .ok()?
        .parse()
        .ok()
}

/// Opens a session (blocking; zenoh runs its own runtime).
pub fn open(z: &ZenohConfig) -> Result<zenoh::Session, NetError> {
    use zenoh::Wait;
    zenoh::open(zenoh_config(z)?)
        .wait()
        .map_err(|e| NetError::Open(e.to_string()))
}
