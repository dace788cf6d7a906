//! A LeRobot v3.0 dataset on disk, extended one episode at a time, crash-safe.
//!
//! # Crash safety
//!
//! LeRobot keeps its parquet writers open and writes the footers when the dataset is finalised,
//! so a killed recorder leaves files without footers: unreadable, everything lost. Here no file
//! of the dataset is ever open for appending:
//!
//! * **While recording**, every flush interval (at most one second of frames) is written as a
//!   small, complete parquet file `.nori-staging/episode-NNNNNN/part-NNNNNN.parquet` (temporary,
//!   fsync, rename, fsync of the directory), by a background thread so that a slow fsync never
//!   delays a frame. A `kill -9` loses the frames since the last flush and the part being
//!   written, if any (see [`EpisodeWriter`]).
//! * **At the end of an episode** it is committed: the task table if the task is new, then the
//!   data file (the old file's row groups copied as encoded bytes plus one new row group for the
//!   episode, written to a temporary and renamed over the old file), then the episode table, then
//!   `stats.json` and `info.json`, each replaced atomically; the staged parts are removed last.
//!   Every file is at every moment either its old or its new complete version.
//! * **At the next start** ([`Dataset::open`]) the commit of an interrupted episode is rolled
//!   forward or back: temporaries are removed; row groups of a data file that no episode
//!   references (a crash between the data file's rename and the episode table's) are cut off;
//!   `info.json` and `stats.json` are rewritten from the episode table; an episode still staged is
//!   committed from its flushed parts (or dropped, if asked, or if it has no frame) and its staging
//!   directory removed.
//!
//! `info.json` is written last, so everything it counts is in place at every moment. From the
//! data file's rename to `info.json`'s, the files disagree only about the one episode in flight:
//! the data file already holds its rows (after the committed ones), then the episode table its
//! row and `stats.json` its statistics, while `info.json` does not count it yet. Every file still
//! reads, and every episode `info.json` counts is where the episode table says; the next start
//! rolls the episode forward (its row is in the episode table) or cuts its rows off and completes
//! it again from its staged parts (it is not).
//!
//! # Video
//!
//! Each camera's frames of an episode are staged as the JPEGs back to back with an index
//! (`.nori-staging/episode-NNNNNN/videos/<key>.mjpeg` and `.idx`, [`crate::video::StagedVideo`]:
//! one JPEG per dataset frame, written as it comes). The commit samples them for the image
//! statistics, muxes them into an MP4 and appends that to the camera's video file
//! (`videos/<key>/chunk-NNN/file-NNN.mp4`, a new file once 200 MB would be passed) by stream
//! copy into a temporary renamed over the file, after the data file and before the episode
//! table. Every piece is cut at a frame count, so a
//! video file is always exactly its committed episodes plus, after a crash between its rename and
//! the episode table's, the one in flight: [`Dataset::open`] cuts that off (or removes a file no
//! episode references), and recovering a staged episode takes the frames that its data parts
//! *and* every camera's staged video hold.
//!
//! A lock (`flock` on `.nori-staging/lock`) keeps a second recorder out; the kernel releases it
//! when the holder dies, however it dies. Closing the dataset removes the lock and the staging
//! directory once it is empty, so a dataset closed cleanly holds only LeRobot's files (nothing
//! of ours would be published by `push_to_hub`); after a crash they stay until the next open
//! (`nori dataset recover`) repairs and closes it.
//!
//! # Map
//!
//! * `mod.rs`: the layout's constants, [`Settings`], [`Dataset`] (its lock, what it holds, its
//!   accessors) and the removal of the lock and the empty staging directory on drop.
//! * `writer`: recording an episode: [`Dataset::begin_episode`] stages it, [`EpisodeWriter`]
//!   takes its frames and JPEGs and hands each flush interval to the background part writer;
//!   `finish` commits it, `abandon` leaves it staged, `discard` drops it.
//! * `commit`: finishing an episode durably: the task table, the data file (rewritten with the
//!   episode's row group), each camera's video file, the episode table and the summaries; the
//!   episode's statistics.
//! * `recovery`: [`Dataset::open`]: creating or opening a dataset under its lock, checking it
//!   matches the recording, and repairing what a crash left ([`Recovery`]): temporaries, orphan
//!   rows and video frames, staged episodes completed or dropped.
//! * `meta`: the JSON metadata: `info.json` ([`Info`]), `nori.json` ([`NoriMeta`]), a staged
//!   episode's `episode.json`, and rewriting `info.json`, `stats.json` and `nori.json` from the
//!   episode table.
//! * `reader`: [`DatasetReader`], a dataset read without lock or repair, and reading one
//!   episode's rows back.
//! * `layout`: where each file is (data, episode and video files by chunk and index, the next
//!   file, the chunk files under a directory, a staged episode's video stream) and removing a
//!   staged directory durably.

use crate::error::RecordError;
use crate::features::Features;
use crate::pq::{DataRow, EpisodeRow};
use nix::fcntl::Flock;
use std::fs::File;
use std::path::{Path, PathBuf};

mod commit;
mod layout;
mod meta;
mod reader;
mod recovery;
mod writer;

pub use meta::{Info, NoriMeta};
pub use reader::DatasetReader;
pub use recovery::Recovery;
pub use writer::EpisodeWriter;

/// `codebase_version` of the layout written.
pub const CODEBASE_VERSION: &str = "v3.0";
/// LeRobot's `DEFAULT_CHUNK_SIZE`: files per chunk directory.
pub const CHUNKS_SIZE: i64 = 1000;
/// LeRobot's `DEFAULT_DATA_FILE_SIZE_IN_MB`.
pub const DATA_FILES_SIZE_IN_MB: u64 = 100;
/// LeRobot's `DEFAULT_VIDEO_FILE_SIZE_IN_MB` (200 since LeRobot 0.4.1).
pub const VIDEO_FILES_SIZE_IN_MB: u64 = 200;
/// LeRobot's `DEFAULT_DATA_PATH`.
pub const DATA_PATH: &str = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet";
/// LeRobot's `DEFAULT_VIDEO_PATH`.
pub const VIDEO_PATH: &str = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4";
/// Staging directory under the root (hidden: LeRobot reads only `data/`, `meta/`, `videos/`).
pub const STAGING: &str = ".nori-staging";

/// How a dataset is recorded; fixed when it is created.
#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    /// Frames per second.
    pub fps: u32,
    /// `robot_type` of `info.json`.
    pub robot_type: String,
    /// Size at which a data (or episode) file is closed and the next one started, MB.
    pub data_files_size_in_mb: u64,
    /// Size at which a video file is closed and the next one started, MB.
    pub video_files_size_in_mb: u64,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            fps: 30,
            robot_type: "nori_a3".into(),
            data_files_size_in_mb: DATA_FILES_SIZE_IN_MB,
            video_files_size_in_mb: VIDEO_FILES_SIZE_IN_MB,
        }
    }
}

/// An open dataset (holding its lock).
pub struct Dataset {
    root: PathBuf,
    settings: Settings,
    features: Features,
    tasks: Vec<String>,
    episodes: Vec<EpisodeRow>,
    _lock: Flock<File>,
}

impl Dataset {
    /// The dataset's root.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Its settings.
    pub fn settings(&self) -> &Settings {
        &self.settings
    }

    /// Its features.
    pub fn features(&self) -> &Features {
        &self.features
    }

    /// Committed episodes.
    pub fn episodes(&self) -> &[EpisodeRow] {
        &self.episodes
    }

    /// Task texts by index.
    pub fn tasks(&self) -> &[String] {
        &self.tasks
    }

    /// Rows of one committed episode, read back from its data file.
    pub fn read_episode(&self, episode_index: i64) -> Result<Vec<DataRow>, RecordError> {
        reader::read_episode_rows(&self.root, &self.features, &self.episodes, episode_index)
    }
}

impl Drop for Dataset {
    fn drop(&mut self) {
        // Unlinked while still held (the lock itself is released after this body): a recorder
        // that opens the path now creates a new lock file and takes that one.
        let staging = self.root.join(STAGING);
        let _ = std::fs::remove_file(staging.join("lock"));
        // Fails, as it should, while an episode is still staged.
        let _ = std::fs::remove_dir(&staging);
    }
}
