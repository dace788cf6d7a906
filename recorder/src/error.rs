//! The recorder's errors: each names the file and what was wrong with it.

use std::path::PathBuf;
use thiserror::Error;

/// What can go wrong while recording, recovering or exporting.
#[derive(Debug, Error)]
#[allow(missing_docs, reason = "each field is shown in its variant's message")]
pub enum RecordError {
    /// A file or directory operation failed.
    #[error("{path}: {what}: {source}")]
    Io {
        /// The path.
        path: PathBuf,
        /// What was being done.
        what: &'static str,
        source: std::io::Error,
    },
    /// A parquet file could not be written or read.
    #[error("{path}: parquet: {source}")]
    Parquet {
        /// The file.
        path: PathBuf,
        source: parquet::errors::ParquetError,
    },
    /// A JSON metadata file is not what this recorder wrote.
    #[error("{path}: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        source: serde_json::Error,
    },
    /// The file parses but its content is not a dataset this recorder can extend.
    #[error("{path}: {reason}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The existing dataset was recorded with other settings or another joint layout.
    #[error("dataset {root}: {reason}; record into a new directory")]
    Incompatible {
        /// The dataset root.
        root: PathBuf,
        /// The difference.
        reason: String,
    },
    /// Another process holds the dataset.
    #[error("dataset {root} is being recorded by another process (lock {lock})")]
    Busy {
        /// The dataset root.
        root: PathBuf,
        /// The lock file.
        lock: PathBuf,
    },
    /// A request that makes no sense (bad fps, empty task, unknown episode).
    #[error("{0}")]
    Request(String),
    /// A video could not be written or read.
    #[error(transparent)]
    Video(#[from] crate::video::VideoError),
    /// A camera's video writer fell behind (FFmpeg or the disk two seconds late): the frame was
    /// not recorded, and the episode must end before the video and the data part ways.
    #[error("the video of camera {camera} fell two seconds behind (disk or FFmpeg too slow): the episode ends here")]
    VideoBehind {
        /// The camera.
        camera: String,
    },
}

impl RecordError {
    pub(crate) fn io(
        path: impl Into<PathBuf>,
        what: &'static str,
    ) -> impl FnOnce(std::io::Error) -> Self {
        let path = path.into();
        move |source| RecordError::Io { path, what, source }
    }

    pub(crate) fn parquet(
        path: impl Into<PathBuf>,
    ) -> impl FnOnce(parquet::errors::ParquetError) -> Self {
        let path = path.into();
        move |source| RecordError::Parquet { path, source }
    }

    pub(crate) fn invalid(path: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        RecordError::Invalid {
            path: path.into(),
            reason: reason.into(),
        }
    }
}
