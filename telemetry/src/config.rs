//! Configuration files of the stack's processes: one error type and one way to read TOML, so
//! every process names the file and the key the same way when it refuses a configuration.

use serde::de::DeserializeOwned;
use std::path::Path;
use thiserror::Error;

/// A configuration that cannot be used.
#[derive(Debug, Error)]
#[allow(missing_docs, reason = "each field is shown in its variant's message")]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    /// Syntax, a wrong type or an unknown key; the message names the key and position. (Not a
    /// `source`: the message already carries it, and error chains would print it twice.)
    #[error("{path}: {detail}")]
    Parse {
        path: String,
        /// The parser's message (line, column, key, what was expected).
        detail: toml::de::Error,
    },
    /// A value that parses but cannot be right.
    #[error("{path}: {key}: {reason}")]
    Invalid {
        path: String,
        /// Offending key.
        key: String,
        reason: String,
    },
}

/// The configuration of one of the stack's processes: embedded in its binary (the commented
/// file of `deploy/config/`, which `--print-default-config` prints), or read from `--config`.
/// One way to load all three, so each names the file and the key the same way when it refuses.
pub trait ProcessConfig: Sized {
    /// The commented default, embedded.
    const DEFAULT_TOML: &'static str;
    /// Its file name, to name the embedded default in errors (`<embedded NAME>`).
    const FILE_NAME: &'static str;

    /// Parses and validates `text`; `origin` names it in errors; files it names are found
    /// relative to `dir` (`None`: the embedded default, which names none).
    fn parse_in(text: &str, origin: &str, dir: Option<&Path>) -> Result<Self, ConfigError>;

    /// The embedded default.
    fn embedded() -> Result<Self, ConfigError> {
        Self::parse_in(
            Self::DEFAULT_TOML,
            &format!("<embedded {}>", Self::FILE_NAME),
            None,
        )
    }

    /// A file (and what it names, relative to it).
    fn load(path: &Path) -> Result<Self, ConfigError> {
        Self::parse_in(&read(path)?, &path.display().to_string(), path.parent())
    }

    /// `--config PATH` when given, the embedded default otherwise.
    fn from_arg(path: Option<&Path>) -> Result<Self, ConfigError> {
        match path {
            Some(p) => Self::load(p),
            None => Self::embedded(),
        }
    }
}

/// Reads a configuration file as text.
pub fn read(path: &Path) -> Result<String, ConfigError> {
    std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
        path: path.display().to_string(),
        source,
    })
}

/// Parses TOML text; `origin` names it in errors.
pub fn parse<T: DeserializeOwned>(text: &str, origin: &str) -> Result<T, ConfigError> {
    toml::from_str(text).map_err(|detail| ConfigError::Parse {
        path: origin.into(),
        detail,
    })
}

/// `Ok` when `value` lies in `range`, else an [`ConfigError::Invalid`] for `key` of `origin`
/// that says so (`unit` follows the range: `" ms"`, `" pixels"`, or `""`).
pub fn within<T: PartialOrd + std::fmt::Display>(
    origin: &str,
    key: &str,
    value: T,
    range: std::ops::RangeInclusive<T>,
    unit: &str,
) -> Result<(), ConfigError> {
    if range.contains(&value) {
        return Ok(());
    }
    let (lo, hi) = range.into_inner();
    Err(invalid(
        origin,
        key,
        format!("{value} is outside {lo}..={hi}{unit}"),
    ))
}

/// An [`ConfigError::Invalid`] for `key` of `origin`.
pub fn invalid(origin: &str, key: impl Into<String>, reason: impl Into<String>) -> ConfigError {
    ConfigError::Invalid {
        path: origin.into(),
        key: key.into(),
        reason: reason.into(),
    }
}
