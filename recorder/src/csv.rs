//! Export of recorded episodes to the telemetry CSV format the model lab reads
//! (`data/README.md`: long format, one row per motor per sample, empty cells for missing
//! samples: a joint `observation.joint_valid` marks as held), one file per episode with its
//! `NAME.meta.json` sidecar.
//!
//! Episodes are separate runs (nothing is known about the robot between two), so each gets its
//! own file: the model lab reads a directory as a sequence of runs, each its own segment.
//! `motor` is the joint's index in the dataset (unique across buses, where servo ids are not);
//! the sidecar gives the daisy chains (per bus, in the driver's order) and the servo models.

use crate::dataset::DatasetReader;
use crate::error::RecordError;
use crate::features::Features;
use crate::fsutil;
use crate::pq::DataRow;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The CSV header.
pub const HEADER: &str =
    "t_s,motor,goal_rad,position_rad,velocity_rad_s,voltage_v,temperature_c,current_a";

fn cell(out: &mut String, v: f32) {
    out.push(',');
    if v.is_finite() {
        let _ = write!(out, "{v}");
    }
}

/// The CSV text of one episode's rows.
pub fn episode_csv(features: &Features, rows: &[DataRow]) -> String {
    let mut out = String::with_capacity(64 * rows.len() * features.joints.len() + HEADER.len());
    out.push_str(HEADER);
    out.push('\n');
    for r in rows {
        for j in 0..features.joints.len() {
            let _ = write!(out, "{:.6},{j}", r.timestamp);
            let f = &r.frame;
            // A held read (the joint was not read in this frame period) is a missing sample.
            let held = f.valid.get(j).is_none_or(|&v| v < 0.5);
            for v in [
                f.action[j],
                f.state[j],
                f.velocity[j],
                f.voltage[j],
                f.temperature[j],
                f.current[j],
            ] {
                cell(&mut out, if held { f32::NAN } else { v });
            }
            out.push('\n');
        }
    }
    out
}

/// The sidecar: chains per bus (motor indices in the driver's order) and servo models.
pub fn sidecar(features: &Features) -> serde_json::Value {
    let mut chains: BTreeMap<u8, Vec<usize>> = BTreeMap::new();
    let mut servo = serde_json::Map::new();
    for (i, j) in features.joints.iter().enumerate() {
        chains.entry(j.bus).or_default().push(i);
        if let Some(key) = j.servo_key() {
            servo.insert(i.to_string(), key.into());
        }
    }
    serde_json::json!({
        "chains": chains.into_values().collect::<Vec<_>>(),
        "servo": servo,
        "joints": features.joint_names(),
    })
}

/// Writes `episode-NNNNNN.csv` and its sidecar into `out_dir` for each of `episodes` (all when
/// empty); returns the CSV files written.
pub fn export(root: &Path, out_dir: &Path, episodes: &[i64]) -> Result<Vec<PathBuf>, RecordError> {
    let ds = DatasetReader::open(root)?;
    let chosen: Vec<i64> = if episodes.is_empty() {
        ds.episodes.iter().map(|e| e.episode_index).collect()
    } else {
        episodes.to_vec()
    };
    if chosen.is_empty() {
        return Err(RecordError::Request(format!(
            "{} has no episode to export",
            root.display()
        )));
    }
    fsutil::create_dir(out_dir)?;
    let side =
        serde_json::to_vec_pretty(&sidecar(&ds.features)).map_err(|source| RecordError::Json {
            path: out_dir.into(),
            source,
        })?;
    let mut written = Vec::new();
    for e in chosen {
        let rows = ds.read_episode(e)?;
        let path = out_dir.join(format!("episode-{e:06}.csv"));
        fsutil::replace(&path, episode_csv(&ds.features, &rows).as_bytes())?;
        fsutil::replace(&out_dir.join(format!("episode-{e:06}.meta.json")), &side)?;
        written.push(path);
    }
    Ok(written)
}
