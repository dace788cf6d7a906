//! Demonstration recording in LeRobot's v3.0 dataset layout, crash-safe.
//!
//! The pure parts (sampling the state plane at a fixed rate, statistics, the LeRobot layout and
//! its metadata, the CSV export format) are separate from the one module that touches files,
//! [`dataset`], so the tests drive them directly. The `nori record` process only moves frames
//! from the state plane into a [`dataset::EpisodeWriter`].
//!
//! Layout (LeRobot v3.0, `lerobot/datasets/utils.py`):
//!
//! ```text
//! <root>/meta/info.json                                 codebase_version, fps, features, paths
//! <root>/meta/stats.json                                min/max/mean/std/count/q01..q99 per feature
//! <root>/meta/tasks.parquet                             task text (pandas index) -> task_index
//! <root>/meta/episodes/chunk-000/file-000.parquet       one row per episode, with its stats
//! <root>/data/chunk-000/file-000.parquet                frames, one row group per episode
//! <root>/meta/nori.json                                 the joint layout (bus, id, model): not LeRobot's
//! <root>/.nori-staging/                                 while open: the lock, the episode being recorded
//! ```
//!
//! Crash safety: see [`dataset`].
//!
//! * `sampler`: the state plane sampled at the recording rate (sans-IO); `features`: what a
//!   dataset holds; `stats`: LeRobot's feature statistics; `video`: a camera's frames.
//! * `dataset` (`src/dataset/`): the one module on files, a room each: `writer` (an episode's
//!   frames staged as parts), `commit` (an episode made durable: data, video, episode table,
//!   summaries), `recovery` (`Dataset::open`: lock, checks, repair after a crash), `meta`
//!   (`info.json`, `nori.json`, `episode.json`, the summaries), `reader` (a dataset read without
//!   lock) and `layout` (where each file is); its map is in `dataset/mod.rs`. With it: `pq` (its
//!   parquet tables), `arrow_schema` (the Arrow schema they carry), `fsutil` (durable
//!   replacement), `csv` (export for the model lab) and `error` (each error names its file).
//! * `nori-record` (`src/main.rs`, feature `process`) moves frames from the plane into it.

pub mod arrow_schema;
pub mod csv;
pub mod dataset;
pub mod error;
pub mod features;
pub mod fsutil;
pub mod pq;
pub mod sampler;
pub mod stats;
pub mod video;

pub use dataset::{Dataset, EpisodeWriter, Recovery};
pub use error::RecordError;
pub use features::{Features, JointMeta};
pub use sampler::{Frame, Sampler};
