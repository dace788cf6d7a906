//! What this robot runs, as the fleet sees it: the version of the `nori-robot` package that
//! installed it, read from the file the package ships (`/usr/lib/nori/version`), or none for a
//! build run from a source tree. Pure: the binary reads the file and passes its text here.
//!
//! The agent reads it once, at its start: an upgrade restarts the agent (the package's
//! maintainer scripts), so what it read is what runs, not what was unpacked since.
//!
//! The calibration the robot runs, likewise: the stamp `nori calibrate` writes on the file
//! the driver loads ([`CALIBRATION_FILE`]), read at the agent's start (a calibration is made
//! with the stack stopped, so every process starts again after one).

use crate::schema::CalibrationMsg;
pub use telemetry::calibration::CALIBRATION_FILE;
use telemetry::calibration::{stamp_of, StampError};
use thiserror::Error;

/// Where the `nori-robot` package writes its version.
pub const VERSION_FILE: &str = "/usr/lib/nori/version";

/// The longest version accepted (Debian sets no bound; a line of a status is not a file).
const MAX_LEN: usize = 64;

/// A version file that cannot be what the package wrote.
#[derive(Debug, Error, PartialEq, Eq)]
pub enum VersionFileError {
    /// Nothing in it.
    #[error("the version file is empty")]
    Empty,
    /// More than one line, or a character a Debian version cannot have.
    #[error("{0:?} is not a Debian version (digits first, then 0-9 A-Z a-z . + ~ - :)")]
    NotAVersion(String),
    /// Longer than [`MAX_LEN`].
    #[error("a version of {0} bytes (at most {MAX_LEN})")]
    TooLong(usize),
}

/// The installed package's version from the text of [`VERSION_FILE`]: one line, a Debian
/// version (`0.1.0+57`, `1:2.0~beta1-3`).
pub fn parse_version_file(text: &str) -> Result<String, VersionFileError> {
    let v = text.strip_suffix('\n').unwrap_or(text);
    if v.is_empty() {
        return Err(VersionFileError::Empty);
    }
    if v.len() > MAX_LEN {
        return Err(VersionFileError::TooLong(v.len()));
    }
    let allowed = |c: char| c.is_ascii_alphanumeric() || ".+~-:".contains(c);
    if !v.starts_with(|c: char| c.is_ascii_digit()) || !v.chars().all(allowed) {
        return Err(VersionFileError::NotAVersion(v.into()));
    }
    Ok(v.into())
}

/// The method of a calibration file with no `[calibrated]` stamp (written by hand).
pub const UNSTAMPED: &str = "unstamped";
/// The method reported when the driver's configuration names no calibration file: the driver
/// runs the embedded calibration, the simulated A3's (right for the simulator, wrong for any
/// robot).
pub const EMBEDDED: &str = "embedded";
/// Where the packaged driver's configuration is.
pub const DRIVER_CONFIG: &str = "/etc/nori/bus-driver.toml";

/// The calibration file the driver's configuration (its text, found in `dir`) names, relative
/// to `dir`; `None` when it names none (the driver runs the embedded calibration).
pub fn calibration_file_of(
    driver_config: &str,
    dir: &std::path::Path,
) -> Result<Option<std::path::PathBuf>, CalibrationFileError> {
    let table: toml::Table = toml::from_str(driver_config)
        .map_err(|e| CalibrationFileError::Stamp(StampError::Malformed(e.to_string())))?;
    match table.get("calibration-file") {
        None => Ok(None),
        Some(toml::Value::String(file)) => Ok(Some(dir.join(file))),
        Some(other) => Err(CalibrationFileError::Stamp(StampError::Malformed(format!(
            "calibration-file = {other}: not a path"
        )))),
    }
}

/// What the fleet is told when the driver runs the embedded calibration.
pub fn embedded_calibration() -> CalibrationMsg {
    CalibrationMsg {
        method: EMBEDDED.into(),
        at: String::new(),
        robot: String::new(),
        joints: 0,
    }
}

/// A calibration file whose stamp cannot be reported.
#[derive(Debug, Error, PartialEq)]
pub enum CalibrationFileError {
    /// Its stamp cannot be read.
    #[error(transparent)]
    Stamp(#[from] StampError),
    /// A field too long for a line of a status.
    #[error("its {field} is {len} bytes (at most {MAX_LEN})")]
    TooLong {
        /// The field: `robot` or `time`.
        field: &'static str,
        /// Its length.
        len: usize,
    },
}

/// The calibration the robot runs, from the text of its calibration file.
pub fn calibration_in_force(text: &str) -> Result<CalibrationMsg, CalibrationFileError> {
    let stamp = stamp_of(text)?;
    let joints = u16::try_from(stamp.joints).unwrap_or(u16::MAX);
    let msg = match stamp.provenance {
        Some(p) => CalibrationMsg {
            method: p.method.key().into(),
            at: p.at,
            robot: p.robot,
            joints,
        },
        None => CalibrationMsg {
            method: UNSTAMPED.into(),
            at: String::new(),
            robot: String::new(),
            joints,
        },
    };
    for (field, value) in [("robot", &msg.robot), ("time", &msg.at)] {
        if value.len() > MAX_LEN {
            return Err(CalibrationFileError::TooLong {
                field,
                len: value.len(),
            });
        }
    }
    Ok(msg)
}

/// The detail of the agent's [`crate::delivery::CALIBRATION_IN_FORCE`] event: `none` (no
/// file), or the method, the time and the robot the file names, space-separated (`-` for an
/// empty field; the robot last, as it may hold spaces).
pub fn calibration_detail(calibration: Option<&CalibrationMsg>) -> String {
    let Some(c) = calibration else {
        return "none".into();
    };
    let or_dash = |s: &str| {
        if s.is_empty() {
            "-".to_string()
        } else {
            s.replace(' ', "_")
        }
    };
    format!(
        "{} {} {}",
        c.method,
        or_dash(&c.at),
        if c.robot.is_empty() { "-" } else { &c.robot }
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    const STAMPED: &str = "[calibrated]\nformat = 1\nrobot = \"a3 0042\"\n\
        at = \"2026-11-29T05:00:00Z\"\nmethod = \"automatic\"\n\
        [joint.left_elbow]\nhoming-offset = 3\nrange-min = 1000\nrange-max = 3000\n";

    #[test]
    fn the_calibration_in_force_is_its_stamp_and_its_event_says_it_in_one_line() {
        let c = calibration_in_force(STAMPED).unwrap();
        assert_eq!(
            (c.method.as_str(), c.at.as_str(), c.robot.as_str(), c.joints),
            ("automatic", "2026-11-29T05:00:00Z", "a3 0042", 1)
        );
        assert_eq!(
            calibration_detail(Some(&c)),
            "automatic 2026-11-29T05:00:00Z a3 0042"
        );
        assert_eq!(calibration_detail(None), "none");
        let by_hand = STAMPED.split("[joint").nth(1).unwrap();
        let c = calibration_in_force(&format!("[joint{by_hand}")).unwrap();
        assert_eq!((c.method.as_str(), c.joints), (UNSTAMPED, 1));
        assert_eq!(calibration_detail(Some(&c)), "unstamped - -");
    }

    /// The calibration reported is the one the driver's configuration names: relative to it,
    /// or none (the embedded one).
    #[test]
    fn the_calibration_reported_is_the_one_the_driver_s_configuration_names() {
        let dir = std::path::Path::new("/etc/nori");
        let packaged = "rate-hz = 200\ncalibration-file = \"/var/lib/nori/calibration.toml\"\n";
        assert_eq!(
            calibration_file_of(packaged, dir).unwrap().as_deref(),
            Some(std::path::Path::new("/var/lib/nori/calibration.toml"))
        );
        let relative = "calibration-file = \"calibration.toml\"\n";
        assert_eq!(
            calibration_file_of(relative, dir).unwrap().as_deref(),
            Some(std::path::Path::new("/etc/nori/calibration.toml"))
        );
        let commented = "rate-hz = 200\n# calibration-file = \"calibration.toml\"\n";
        assert_eq!(calibration_file_of(commented, dir).unwrap(), None);
        assert!(calibration_file_of("calibration-file = 3", dir).is_err());
        assert!(calibration_file_of("rate-hz = [", dir).is_err());
    }

    #[test]
    fn a_calibration_that_cannot_be_reported_is_refused_by_name() {
        let other = STAMPED.replace("format = 1", "format = 9");
        assert_eq!(
            calibration_in_force(&other),
            Err(CalibrationFileError::Stamp(StampError::Format { found: 9 }))
        );
        let long = STAMPED.replace("a3 0042", &"r".repeat(MAX_LEN + 1));
        assert_eq!(
            calibration_in_force(&long),
            Err(CalibrationFileError::TooLong {
                field: "robot",
                len: MAX_LEN + 1
            })
        );
    }

    #[test]
    fn the_package_s_version_is_read_with_or_without_its_newline() {
        assert_eq!(parse_version_file("0.1.0+57\n").as_deref(), Ok("0.1.0+57"));
        assert_eq!(
            parse_version_file("1:2.0~beta1-3").as_deref(),
            Ok("1:2.0~beta1-3")
        );
    }

    #[test]
    fn a_file_that_is_not_one_version_is_refused_by_name() {
        assert_eq!(parse_version_file(""), Err(VersionFileError::Empty));
        assert_eq!(parse_version_file("\n"), Err(VersionFileError::Empty));
        for bad in [
            "0.1.0\n0.1.1",
            "v0.1.0",
            "0.1.0 amd64",
            "0.1\0",
            "0.1.0\n\n",
        ] {
            assert_eq!(
                parse_version_file(bad),
                Err(VersionFileError::NotAVersion(
                    bad.strip_suffix('\n').unwrap_or(bad).into()
                )),
                "{bad:?}"
            );
        }
        let long = "1".repeat(MAX_LEN + 1);
        assert_eq!(
            parse_version_file(&long),
            Err(VersionFileError::TooLong(MAX_LEN + 1))
        );
        assert!(parse_version_file(&"1".repeat(MAX_LEN)).is_ok());
    }
}
