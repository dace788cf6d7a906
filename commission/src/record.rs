//! A calibration written down: a versioned file (the robot, when, how, each servo's model and
//! firmware) that the driver reads, written atomically (a power cut leaves the old file or the
//! new one, never half of one), the previous one kept beside it, and what changed between them
//! said joint by joint.

use bus_driver::calibration::{JointCalibration, STEPS_PER_RAD};
use bus_driver::config::CalibrationFile;
use std::fmt;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// A calibration that could not be written.
#[derive(Debug, Error)]
pub enum RecordError {
    /// The file could not be made into TOML.
    #[error("the calibration could not be written as TOML: {0}")]
    Toml(#[from] toml::ser::Error),
    /// The file system refused.
    #[error("{path}: {step}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What was being done.
        step: telemetry::durable::Step,
        /// What the file system said.
        source: std::io::Error,
    },
}

/// What a calibration changed for one joint.
#[derive(Debug, Clone, PartialEq)]
pub struct JointChange {
    /// The joint.
    pub joint: String,
    /// Its calibration before (none: new).
    pub before: Option<JointCalibration>,
    /// After (none: no longer calibrated).
    pub after: Option<JointCalibration>,
}

/// The joints whose calibration differs between `old` and `new`, in name order.
pub fn changes(old: Option<&CalibrationFile>, new: &CalibrationFile) -> Vec<JointChange> {
    let empty = std::collections::BTreeMap::new();
    let before = old.map_or(&empty, |f| &f.joint);
    let mut names: Vec<&String> = before.keys().chain(new.joint.keys()).collect();
    names.sort();
    names.dedup();
    names
        .into_iter()
        .filter_map(|j| {
            let (b, a) = (before.get(j).copied(), new.joint.get(j).copied());
            (b != a).then(|| JointChange {
                joint: j.clone(),
                before: b,
                after: a,
            })
        })
        .collect()
}

impl fmt::Display for JointChange {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let deg = |steps: i32| f64::from(steps) / STEPS_PER_RAD * 180.0 / std::f64::consts::PI;
        match (self.before, self.after) {
            (Some(b), Some(a)) => write!(
                f,
                "{}: homing offset {} → {} ({:+.1}°), range {}..{} → {}..{} ({:+.1}°, {:+.1}°)",
                self.joint,
                b.homing_offset,
                a.homing_offset,
                deg(a.homing_offset - b.homing_offset),
                b.range_min,
                b.range_max,
                a.range_min,
                a.range_max,
                deg(a.range_min - b.range_min),
                deg(a.range_max - b.range_max),
            ),
            (None, Some(a)) => write!(
                f,
                "{}: new, homing offset {}, range {}..{}",
                self.joint, a.homing_offset, a.range_min, a.range_max
            ),
            (Some(_), None) => write!(f, "{}: no longer calibrated", self.joint),
            (None, None) => write!(f, "{}: unchanged", self.joint),
        }
    }
}

/// The file's text: a header saying what wrote it, then the TOML the driver reads.
pub fn render(file: &CalibrationFile) -> Result<String, RecordError> {
    let mut text = String::from(
        "# Written by `nori calibrate`: each joint's homing offset and range (steps of \
         Present_Position),\n# also held in each servo's EEPROM, which the driver checks \
         against this file.\n\n",
    );
    text.push_str(&toml::to_string(file)?);
    Ok(text)
}

/// The previous calibration's path beside `path`.
pub fn previous_path(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".previous");
    path.with_file_name(name)
}

/// Replaces the file at `path` with `text`, the old one kept as [`previous_path`]; each
/// written atomically and durably ([`telemetry::durable`]): after a power cut either
/// calibration is there whole.
pub fn replace(path: &Path, text: &str) -> Result<(), RecordError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |(step, source)| RecordError::Io { path, step, source }
    };
    if path.exists() {
        let old = std::fs::read(path).map_err(|e| io(path)(("reading", e)))?;
        let previous = previous_path(path);
        telemetry::durable::replace(&previous, &old).map_err(io(&previous))?;
    }
    telemetry::durable::replace(path, text.as_bytes()).map_err(io(path))
}

#[cfg(test)]
mod tests {
    use super::*;
    use bus_driver::config::{
        CalibrationMethod, Provenance, ServoIdentity, CALIBRATION_FORMAT, DEFAULT_CALIBRATION_TOML,
    };

    fn embedded() -> CalibrationFile {
        toml::from_str(DEFAULT_CALIBRATION_TOML).unwrap()
    }

    fn calibrated(mut file: CalibrationFile) -> CalibrationFile {
        file.calibrated = Some(Provenance {
            format: CALIBRATION_FORMAT,
            robot: "sim-0001".into(),
            at: "2026-11-29T02:00:00Z".into(),
            method: CalibrationMethod::ByHand,
        });
        file.servo.insert(
            "left_elbow".into(),
            ServoIdentity {
                id: 4,
                model: "sts3095".into(),
                firmware: "3.10".into(),
            },
        );
        file
    }

    /// What is written is what the driver reads back, provenance and all, and the driver's
    /// own loader accepts it.
    #[test]
    fn the_written_file_reads_back_as_written_and_loads_in_the_driver() {
        let mut file = calibrated(embedded());
        file.joint.get_mut("left_elbow").unwrap().homing_offset = -37;
        let text = render(&file).unwrap();
        let back: CalibrationFile = toml::from_str(&text).unwrap();
        assert_eq!(back, file);
        let config = bus_driver::config::DEFAULT_CONFIG_TOML;
        bus_driver::LoadedConfig::parse_texts(config, "c.toml", &text, "cal.toml").unwrap();
        // A format this driver does not know is refused, naming it.
        let future = text.replace("format = 1", "format = 2");
        let e = bus_driver::LoadedConfig::parse_texts(config, "c.toml", &future, "cal.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("format 2"), "{e}");
    }

    #[test]
    fn changes_name_each_joint_that_moved_and_nothing_else() {
        let old = embedded();
        let mut new = calibrated(embedded());
        assert!(
            changes(Some(&old), &new).is_empty(),
            "provenance is no change"
        );
        let elbow = new.joint.get_mut("left_elbow").unwrap();
        elbow.homing_offset += 37;
        elbow.range_min += 37;
        elbow.range_max += 37;
        new.joint.remove("right_gripper");
        let c = changes(Some(&old), &new);
        let said: Vec<String> = c.iter().map(ToString::to_string).collect();
        assert_eq!(said.len(), 2, "{said:?}");
        assert!(
            said[0].starts_with("left_elbow: homing offset 0 → 37 (+3.3°)"),
            "{said:?}"
        );
        assert_eq!(said[1], "right_gripper: no longer calibrated");
        assert_eq!(changes(None, &new).len(), new.joint.len());
    }

    #[test]
    fn replacing_keeps_the_previous_file_and_leaves_no_temporary_behind() {
        let dir = std::env::temp_dir().join(format!("nori-record-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("calibration.toml");
        replace(&path, "first").unwrap();
        assert!(!previous_path(&path).exists());
        replace(&path, "second").unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "second");
        assert_eq!(
            std::fs::read_to_string(previous_path(&path)).unwrap(),
            "first"
        );
        let mut names: Vec<String> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert_eq!(names, ["calibration.toml", "calibration.toml.previous"]);
        // A directory that is not there: a clear error naming the file.
        let e = replace(&dir.join("no/such/calibration.toml"), "x").unwrap_err();
        assert!(e.to_string().contains("no/such"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
