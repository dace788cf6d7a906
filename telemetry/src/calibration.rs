//! Where a robot's calibration came from: the `[calibrated]` table `nori calibrate` stamps on
//! the file it writes. The driver reads the whole file (`bus_driver::config`); the fleet agent
//! reads only this stamp, to tell the fleet which calibration the robot runs.

use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Where a robot keeps its calibration: state written by `nori calibrate`, not a package's
/// conffile (an upgrade must not put another robot's calibration back).
pub const CALIBRATION_FILE: &str = "/var/lib/nori/calibration.toml";

/// The calibration file format this build reads.
pub const CALIBRATION_FORMAT: u32 = 1;

/// Who calibrated the robot, when and how.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct Provenance {
    /// The file's format ([`CALIBRATION_FORMAT`]).
    pub format: u32,
    /// The robot's id.
    pub robot: String,
    /// When, RFC 3339 (UTC).
    pub at: String,
    /// How the ranges were found.
    pub method: CalibrationMethod,
}

/// How a calibration found each joint's stops.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum CalibrationMethod {
    /// An operator moved each joint from stop to stop, torque off.
    ByHand,
    /// Each joint driven slowly at a low torque into its stops.
    Automatic,
}

impl CalibrationMethod {
    /// Its name in the file (`by-hand`, `automatic`).
    pub fn key(self) -> &'static str {
        match self {
            CalibrationMethod::ByHand => "by-hand",
            CalibrationMethod::Automatic => "automatic",
        }
    }
}

/// A calibration file's stamp, and how many joints it calibrates.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Stamp {
    /// Its `[calibrated]` table; `None` for a file written by hand.
    pub provenance: Option<Provenance>,
    /// Joints it holds.
    pub joints: usize,
}

/// A calibration file whose stamp cannot be read.
#[derive(Debug, Error, PartialEq)]
pub enum StampError {
    /// Not TOML, or its `[calibrated]` table is not one.
    #[error("not a calibration file: {0}")]
    Malformed(String),
    /// A format this build does not read.
    #[error("calibration format {found}, this build reads {CALIBRATION_FORMAT}")]
    Format {
        /// The file's.
        found: u32,
    },
}

/// Reads the stamp of a calibration file's `text` (its joints are the driver's to check).
pub fn stamp_of(text: &str) -> Result<Stamp, StampError> {
    #[derive(Deserialize)]
    struct File {
        calibrated: Option<Provenance>,
        #[serde(default)]
        joint: toml::Table,
    }
    let file: File = toml::from_str(text).map_err(|e| StampError::Malformed(e.to_string()))?;
    if let Some(p) = file
        .calibrated
        .as_ref()
        .filter(|p| p.format != CALIBRATION_FORMAT)
    {
        return Err(StampError::Format { found: p.format });
    }
    Ok(Stamp {
        provenance: file.calibrated,
        joints: file.joint.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const STAMPED: &str = r#"
[calibrated]
format = 1
robot = "a3-0042"
at = "2026-11-29T05:00:00Z"
method = "by-hand"

[joint.left_elbow]
homing-offset = -120
range-min = 1100
range-max = 3000

[joint.left_gripper]
homing-offset = 10
range-min = 1900
range-max = 2900
"#;

    #[test]
    fn a_stamped_file_gives_who_when_how_and_its_joints() {
        let s = stamp_of(STAMPED).unwrap();
        let p = s.provenance.unwrap();
        assert_eq!(
            (p.robot.as_str(), p.at.as_str(), p.method.key()),
            ("a3-0042", "2026-11-29T05:00:00Z", "by-hand")
        );
        assert_eq!(s.joints, 2);
    }

    #[test]
    fn a_file_written_by_hand_has_no_stamp_and_a_bad_one_is_refused_by_name() {
        let unstamped = STAMPED.split("[joint.left_elbow]").nth(1).unwrap();
        let s = stamp_of(&format!("[joint.left_elbow]{unstamped}")).unwrap();
        assert_eq!((s.provenance, s.joints), (None, 2));
        let other = STAMPED.replace("format = 1", "format = 2");
        assert_eq!(stamp_of(&other), Err(StampError::Format { found: 2 }));
        let unknown = STAMPED.replace("method = \"by-hand\"", "method = \"guessed\"");
        assert!(matches!(stamp_of(&unknown), Err(StampError::Malformed(_))));
        assert!(matches!(
            stamp_of("joint = 3"),
            Err(StampError::Malformed(_))
        ));
    }
}
