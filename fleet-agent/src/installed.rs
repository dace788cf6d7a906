//! What this robot runs, as the fleet sees it: the version of the `nori-robot` package that
//! installed it, read from the file the package ships (`/usr/lib/nori/version`), or none for a
//! build run from a source tree. Pure: the binary reads the file and passes its text here.
//!
//! The agent reads it once, at its start: an upgrade restarts the agent (the package's
//! maintainer scripts), so what it read is what runs, not what was unpacked since.

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

#[cfg(test)]
mod tests {
    use super::*;

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
