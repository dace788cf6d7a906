//! The trip latch on disk: which joints' buses a thermal (or firmware-protection) trip has
//! latched off. It is the one record of a latch that outlives every process:
//!
//! - the supervisor is its only writer: it records a trip before the directive that announces
//!   it, and clears it only when the operator's re-enable is granted;
//! - the bus-driver reads it at start, before it turns any torque on, so a bus latched off
//!   stays off whatever the start order of the processes and whether a supervisor is up; and
//!   again before it obeys a directive that re-enables a latched bus (the record, not the
//!   directive, says the latch is released).
//!
//! One joint name per line (names survive a driver started on a subset of the buses, where bus
//! indices do not), and [`OPERATOR_STOP`] while an operator's stop is in force (the supervisor
//! restores it at start, so no restart ends a stop; the driver, which matches joint names,
//! passes over it). Written atomically ([`crate::durable`]): temporary file, fsync, rename,
//! fsync of the directory, so a crash or power loss leaves the old or the new record, never
//! half and never none.

use std::path::{Path, PathBuf};
use thiserror::Error;

/// The record could not be read or written.
#[derive(Debug, Error)]
#[error("trip latch {path}: {action}: {source}")]
pub struct LatchError {
    /// The record's path.
    pub path: PathBuf,
    /// What was being done.
    pub action: &'static str,
    /// Why it failed.
    #[source]
    pub source: std::io::Error,
}

/// Lines of the record starting with this are the record's own, never a joint (the driver's
/// configuration refuses such joint names).
pub const RESERVED_PREFIX: &str = "@";
/// The record's line for an operator's stop in force.
pub const OPERATOR_STOP: &str = "@operator-stop";

/// Where the latch is kept when no path is given: `<temp dir>/nori-<domain>-trips` (a
/// development default; the robot's units pass `/var/lib/nori/trips` to both processes).
pub fn default_path(domain: &str) -> PathBuf {
    std::env::temp_dir().join(format!("nori-{domain}-trips"))
}

/// The joint names of a record's text (blank lines and surrounding space ignored).
pub fn parse(text: &str) -> Vec<String> {
    text.lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .map(String::from)
        .collect()
}

/// Reads the latched joints; a missing record means none is latched.
pub fn load(path: &Path) -> Result<Vec<String>, LatchError> {
    match std::fs::read_to_string(path) {
        Ok(text) => Ok(parse(&text)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Vec::new()),
        Err(source) => Err(LatchError {
            path: path.into(),
            action: "reading",
            source,
        }),
    }
}

/// Records `joints` as latched, atomically and durably (see the module documentation).
pub fn save(path: &Path, joints: &[String]) -> Result<(), LatchError> {
    let text: String = joints.iter().map(|j| format!("{j}\n")).collect();
    crate::durable::replace(path, text.as_bytes()).map_err(|(action, source)| LatchError {
        path: path.into(),
        action,
        source,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn a_saved_record_loads_back_and_a_missing_one_is_empty() {
        let dir = std::env::temp_dir().join(format!("nori-latch-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("trips");
        let _ = std::fs::remove_file(&path);
        assert!(load(&path).unwrap().is_empty());
        let joints = vec!["left_elbow".to_string(), "left_gripper".to_string()];
        save(&path, &joints).unwrap();
        assert_eq!(load(&path).unwrap(), joints);
        assert!(!path.with_extension("tmp").exists());
        save(&path, &[]).unwrap();
        assert!(load(&path).unwrap().is_empty());
        assert_eq!(parse("  a \n\n b\n"), ["a", "b"]);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn an_unreadable_record_is_an_error_not_an_empty_latch() {
        // A directory where the record should be: reading fails, and must not read as "none".
        let dir = std::env::temp_dir().join(format!("nori-latch-dir-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        assert!(load(&dir).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
