//! zenoh key expressions: everything a robot says or hears lives under `nori/<robot-id>/`.
//!
//! | key | direction | what |
//! |---|---|---|
//! | `nori/<id>/state` | robot → fleet | [`crate::schema::StateMsg`], rate-limited |
//! | `nori/<id>/layout` | robot → fleet | [`crate::schema::LayoutMsg`], on change and every few seconds |
//! | `nori/<id>/events` | robot → fleet | [`crate::schema::EventMsg`], every journaled event, again until acknowledged |
//! | `nori/<id>/acks` | fleet store → robot | [`crate::schema::AckMsg`]: the journal is stored through an event |
//! | `nori/<id>/preview` | robot → fleet | [`crate::schema::PreviewMsg`], a camera thumbnail now and then |
//! | `nori/<id>/scan` | robot → fleet | [`crate::schema::ScanMsg`], a lidar revolution now and then |
//! | `nori/<id>/blackbox/chunk` | robot → fleet store | [`crate::schema::BoxChunkMsg`], a frozen box piece by piece, again until acknowledged |
//! | `nori/<id>/blackbox/ack` | fleet store → robot | [`crate::schema::BoxAckMsg`]: how much of a box the store holds |
//! | `nori/<id>/observation` | robot → inference | [`crate::schema::ObservationMsg`] |
//! | `nori/<id>/actions` | inference → robot | [`crate::schema::ActionChunk`] |
//! | `nori/<id>/alive` | liveliness token | present while the agent runs |
//! | `nori/<id>/status` | queryable | [`crate::schema::StatusMsg`]: versions, config, health, counters, bus and sensor counts |

use thiserror::Error;

/// The root of every key.
pub const ROOT: &str = "nori";

/// A robot id that cannot be part of a key.
#[derive(Debug, Error, PartialEq)]
#[error("robot id {0:?}: use 1-64 of a-z A-Z 0-9 - _ (it becomes a zenoh key chunk)")]
pub struct BadRobotId(pub String);

/// Checks a robot id: one key chunk, no wildcards or separators.
pub fn check_robot_id(id: &str) -> Result<(), BadRobotId> {
    let ok = !id.is_empty()
        && id.len() <= 64
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
    if ok {
        Ok(())
    } else {
        Err(BadRobotId(id.into()))
    }
}

/// `nori/<id>/<leaf>`.
pub fn robot_key(id: &str, leaf: &str) -> String {
    format!("{ROOT}/{id}/{leaf}")
}

/// `nori/*/<leaf>`: the same leaf of every robot.
pub fn all_robots(leaf: &str) -> String {
    format!("{ROOT}/*/{leaf}")
}

/// A shard pattern that is not one key-expression chunk of robot ids.
#[derive(Debug, Error, PartialEq)]
#[error(
    "robot pattern {0:?}: use `*`, or a-z A-Z 0-9 - _ with `$*` for any run of them \
     (`$*0`: ids ending in 0; `lab-$*`: ids starting with lab-)"
)]
pub struct BadRobotPattern(pub String);

/// `nori/<pattern>/<leaf>` for each of `patterns`: the robots one shard of the fleet side
/// (a collector, a store) serves. A fleet too big for one process runs several, each given
/// the patterns of its share (`$*0`..`$*4` and `$*5`..`$*9` split it in two by the last digit).
pub fn robots_matching(patterns: &[String], leaf: &str) -> Result<Vec<String>, BadRobotPattern> {
    patterns
        .iter()
        .map(|p| {
            // A robot id with `$*` standing for any run of its characters.
            let chunk = p == "*" || check_robot_id(&p.replace("$*", "x")).is_ok();
            let key = format!("{ROOT}/{p}/{leaf}");
            match zenoh::key_expr::KeyExpr::try_from(key.clone()) {
                Ok(k) if chunk && k.as_str() == key => Ok(key),
                _ => Err(BadRobotPattern(p.clone())),
            }
        })
        .collect()
}

/// The robot id in `nori/<id>/...`.
pub fn robot_of(key: &str) -> Option<&str> {
    let mut parts = key.split('/');
    (parts.next()? == ROOT).then_some(())?;
    parts.next().filter(|id| check_robot_id(id).is_ok())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_shard_is_one_chunk_of_robot_ids() {
        let keys = robots_matching(&["*".into(), "$*0".into(), "lab-$*".into()], "events");
        assert_eq!(
            keys.unwrap(),
            ["nori/*/events", "nori/$*0/events", "nori/lab-$*/events"]
        );
        for bad in ["", "**", "a/b", "a*", "$", "$*$*", "x y", "*0"] {
            assert_eq!(
                robots_matching(&[bad.into()], "state"),
                Err(BadRobotPattern(bad.into())),
                "{bad:?}"
            );
        }
    }

    #[test]
    fn robot_ids_are_single_safe_chunks() {
        assert!(check_robot_id("a3-0001").is_ok());
        for bad in ["", "a/b", "*", "a**", "r$1", "robot one", &"x".repeat(65)] {
            assert_eq!(check_robot_id(bad), Err(BadRobotId(bad.into())));
        }
        assert_eq!(robot_key("a3-0001", "state"), "nori/a3-0001/state");
        assert_eq!(robot_of("nori/a3-0001/actions"), Some("a3-0001"));
        assert_eq!(robot_of("other/a3-0001/actions"), None);
    }
}
