//! Configuration files of the stack's processes: one error type and one way to read TOML, so
//! every process names the file and the key the same way when it refuses a configuration.

use serde::de::DeserializeOwned;
use std::path::Path;
use thiserror::Error;

/// A configuration that cannot be used.
#[derive(Debug, Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// File.
        path: String,
        /// Cause.
        source: std::io::Error,
    },
    /// Syntax, a wrong type or an unknown key; the message names the key and position. (Not a
    /// `source`: the message already carries it, and error chains would print it twice.)
    #[error("{path}: {detail}")]
    Parse {
        /// File.
        path: String,
        /// The parser's message (line, column, key, what was expected).
        detail: toml::de::Error,
    },
    /// A value that parses but cannot be right.
    #[error("{path}: {key}: {reason}")]
    Invalid {
        /// File.
        path: String,
        /// Offending key.
        key: String,
        /// Why.
        reason: String,
    },
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

/// An [`ConfigError::Invalid`] for `key` of `origin`.
pub fn invalid(origin: &str, key: impl Into<String>, reason: impl Into<String>) -> ConfigError {
    ConfigError::Invalid {
        path: origin.into(),
        key: key.into(),
        reason: reason.into(),
    }
}
