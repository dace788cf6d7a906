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

use crate::error::RecordError;
use crate::features::{CameraMeta, FeatureSpec, Features, Ordered, SCALARS};
use crate::fsutil;
use crate::pq::{self, DataRow, EpisodeRow, VideoSpan};
use crate::sampler::Frame;
use crate::stats::FeatureStats;
use crate::video::{self, StagedVideo};
use nix::fcntl::{Flock, FlockArg};
use parquet::file::writer::SerializedFileWriter;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::mpsc;

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

/// `meta/info.json`, field for field and in the order LeRobot 0.6 writes it (its `DatasetInfo`
/// dataclass, serialised field by field).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Info {
    /// "v3.0".
    pub codebase_version: String,
    /// Frames per second.
    pub fps: u32,
    /// Features in order.
    #[serde(deserialize_with = "ordered_features")]
    pub features: Ordered<FeatureSpec>,
    /// Episodes.
    pub total_episodes: i64,
    /// Frames.
    pub total_frames: i64,
    /// Distinct tasks.
    pub total_tasks: i64,
    /// Files per chunk.
    pub chunks_size: i64,
    /// Data file size limit, MB.
    pub data_files_size_in_mb: u64,
    /// Video file size limit, MB.
    pub video_files_size_in_mb: u64,
    /// Data file template.
    pub data_path: String,
    /// Video file template; `null`: no video.
    pub video_path: Option<String>,
    /// Robot type.
    pub robot_type: Option<String>,
    /// `{"train": "0:N"}`.
    pub splits: BTreeMap<String, String>,
}

fn ordered_features<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<Ordered<FeatureSpec>, D::Error> {
    // Deserialised into a sorted map: the order matters only for writing, and a dataset is
    // compared with the recording's features key by key.
    let map = BTreeMap::<String, FeatureSpec>::deserialize(d)?;
    Ok(Ordered(map.into_iter().collect()))
}

/// `meta/nori.json`: what LeRobot's files do not say about the robot.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct NoriMeta {
    /// The recorded joints, with bus, id and servo model.
    pub features: Features,
    /// Where `action` comes from.
    pub action: String,
    /// How a missing sample is stored.
    pub missing: String,
}

/// What [`Dataset::open`] found and repaired.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Recovery {
    /// Leftover temporaries removed.
    pub temporaries_removed: usize,
    /// Data rows no episode referenced, cut off.
    pub orphan_rows_removed: i64,
    /// Staged episodes completed from their flushed parts: (episode index, frames).
    pub recovered: Vec<(i64, usize)>,
    /// Staged episodes dropped: (staged index, frames, why).
    pub dropped: Vec<(i64, usize, String)>,
    /// Staging directories of episodes that had been committed already.
    pub already_committed: usize,
    /// Video frames no episode referenced, cut off (from the end of a camera's last file, or
    /// whole files).
    pub orphan_video_frames_removed: u64,
}

impl Recovery {
    /// Whether anything had to be repaired.
    pub fn is_clean(&self) -> bool {
        *self == Recovery::default()
    }
}

/// `episode.json` of a staged episode.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct StagedEpisode {
    episode_index: i64,
    task: String,
    fps: u32,
    started_unix_ms: u64,
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

fn data_file(chunk: i64, file: i64) -> String {
    format!("data/chunk-{chunk:03}/file-{file:03}.parquet")
}

fn episodes_file(chunk: i64, file: i64) -> String {
    format!("meta/episodes/chunk-{chunk:03}/file-{file:03}.parquet")
}

fn video_file(key: &str, chunk: i64, file: i64) -> String {
    format!("videos/{key}/chunk-{chunk:03}/file-{file:03}.mp4")
}

/// Where a staged episode's video stream of `camera` is.
fn staged_video(dir: &Path, camera: &CameraMeta) -> PathBuf {
    dir.join("videos").join(format!("{}.mjpeg", camera.key()))
}

fn next_file(chunk: i64, file: i64) -> (i64, i64) {
    if file == CHUNKS_SIZE - 1 {
        (chunk + 1, 0)
    } else {
        (chunk, file + 1)
    }
}

/// `chunk-NNN/file-NNN.<ext>` files under `dir`, sorted, with their indices.
fn chunk_files(dir: &Path, ext: &str) -> Result<Vec<(i64, i64, PathBuf)>, RecordError> {
    let mut out = Vec::new();
    let Ok(chunks) = std::fs::read_dir(dir) else {
        return Ok(out);
    };
    for c in chunks.flatten() {
        let name = c.file_name().to_string_lossy().into_owned();
        let Some(chunk) = name
            .strip_prefix("chunk-")
            .and_then(|n| n.parse::<i64>().ok())
        else {
            continue;
        };
        let files = std::fs::read_dir(c.path()).map_err(RecordError::io(c.path(), "listing"))?;
        for f in files.flatten() {
            let fname = f.file_name().to_string_lossy().into_owned();
            if let Some(file) = fname
                .strip_prefix("file-")
                .and_then(|n| n.strip_suffix(ext))
                .and_then(|n| n.strip_suffix('.'))
                .and_then(|n| n.parse::<i64>().ok())
            {
                out.push((chunk, file, f.path()));
            }
        }
    }
    out.sort();
    Ok(out)
}

fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, RecordError> {
    let text = std::fs::read_to_string(path).map_err(RecordError::io(path, "reading"))?;
    serde_json::from_str(&text).map_err(|source| RecordError::Json {
        path: path.into(),
        source,
    })
}

fn json_bytes<T: Serialize>(path: &Path, value: &T) -> Result<Vec<u8>, RecordError> {
    let mut v = serde_json::to_vec_pretty(value).map_err(|source| RecordError::Json {
        path: path.into(),
        source,
    })?;
    v.push(b'\n');
    Ok(v)
}

fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

impl Dataset {
    /// Opens the dataset at `root` (creating it if there is none) for recording `features`,
    /// after repairing what a crash left (see the module documentation). With `drop_unfinished`
    /// an episode a crash interrupted is dropped instead of completed from its flushed parts.
    pub fn open(
        root: &Path,
        settings: Settings,
        features: Features,
        drop_unfinished: bool,
    ) -> Result<(Dataset, Recovery), RecordError> {
        if settings.fps == 0 || settings.fps > 1000 {
            return Err(RecordError::Request(format!(
                "fps {} is outside 1..=1000",
                settings.fps
            )));
        }
        if features.joints.is_empty() {
            return Err(RecordError::Request("no joint to record".into()));
        }
        let staging = root.join(STAGING);
        fsutil::create_dir(&staging)?;
        let lock_path = staging.join("lock");
        let lock_file = File::options()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&lock_path)
            .map_err(RecordError::io(&lock_path, "opening the lock"))?;
        let lock = Flock::lock(lock_file, FlockArg::LockExclusiveNonblock).map_err(|_| {
            RecordError::Busy {
                root: root.into(),
                lock: lock_path.clone(),
            }
        })?;
        let mut ds = Dataset {
            root: root.into(),
            settings,
            features,
            tasks: Vec::new(),
            episodes: Vec::new(),
            _lock: lock,
        };
        let mut recovery = Recovery {
            temporaries_removed: fsutil::remove_temporaries(root)?,
            ..Recovery::default()
        };
        let info_path = root.join("meta/info.json");
        if info_path.exists() {
            ds.check_compatible(&read_json::<Info>(&info_path)?)?;
            ds.load()?;
            recovery.orphan_rows_removed = ds.cut_orphan_rows()?;
            recovery.orphan_video_frames_removed = ds.cut_orphan_video()?;
        } else if root.join("data").exists() || root.join("meta/episodes").exists() {
            return Err(RecordError::invalid(
                root,
                "has data but no meta/info.json: not a dataset this recorder can extend",
            ));
        }
        ds.write_summaries()?;
        ds.recover_staged(drop_unfinished, &mut recovery)?;
        Ok((ds, recovery))
    }

    fn check_compatible(&self, info: &Info) -> Result<(), RecordError> {
        let differ = |reason: String| RecordError::Incompatible {
            root: self.root.clone(),
            reason,
        };
        if info.codebase_version != CODEBASE_VERSION {
            return Err(differ(format!(
                "codebase_version {} (this recorder writes {CODEBASE_VERSION})",
                info.codebase_version
            )));
        }
        if info.fps != self.settings.fps {
            return Err(differ(format!(
                "recorded at {} fps, asked for {}",
                info.fps, self.settings.fps
            )));
        }
        if info.robot_type.as_deref() != Some(self.settings.robot_type.as_str()) {
            return Err(differ(format!(
                "robot_type {:?}, asked for {:?}",
                info.robot_type, self.settings.robot_type
            )));
        }
        let mut theirs = info.features.0.clone();
        let mut ours = self.features.info_json(self.settings.fps).0;
        theirs.sort_by(|a, b| a.0.cmp(&b.0));
        ours.sort_by(|a, b| a.0.cmp(&b.0));
        if theirs != ours {
            let names = |f: &[(String, FeatureSpec)]| {
                f.iter()
                    .find(|(k, _)| k == "observation.state")
                    .and_then(|(_, s)| s.names.clone())
                    .unwrap_or_default()
                    .join(",")
            };
            return Err(differ(format!(
                "its features differ from this robot's (joints there: {}; here: {})",
                names(&theirs),
                names(&ours)
            )));
        }
        self.settings_size_check(info)
    }

    fn settings_size_check(&self, info: &Info) -> Result<(), RecordError> {
        if info.chunks_size != CHUNKS_SIZE {
            return Err(RecordError::Incompatible {
                root: self.root.clone(),
                reason: format!(
                    "chunks_size {} (this recorder uses {CHUNKS_SIZE})",
                    info.chunks_size
                ),
            });
        }
        Ok(())
    }

    /// Loads the task and episode tables and checks that they describe one contiguous dataset.
    fn load(&mut self) -> Result<(), RecordError> {
        let tasks_path = self.root.join("meta/tasks.parquet");
        if tasks_path.exists() {
            self.tasks = pq::read_tasks(&tasks_path)?;
        }
        for (_, _, path) in chunk_files(&self.root.join("meta/episodes"), "parquet")? {
            self.episodes
                .extend(pq::read_episodes(&path, &self.features)?);
        }
        self.episodes.sort_by_key(|e| e.episode_index);
        let mut next_index = 0;
        for (i, e) in self.episodes.iter().enumerate() {
            let problem = if e.episode_index != i as i64 {
                Some(format!(
                    "episode {} where {i} was expected",
                    e.episode_index
                ))
            } else if e.dataset_from_index != next_index
                || e.dataset_to_index - e.dataset_from_index != e.length
            {
                Some(format!(
                    "episode {} spans {}..{} with length {} (expected to start at {next_index})",
                    e.episode_index, e.dataset_from_index, e.dataset_to_index, e.length
                ))
            } else if e.tasks.iter().any(|t| !self.tasks.contains(t)) {
                Some(format!(
                    "episode {} has a task missing from tasks.parquet",
                    e.episode_index
                ))
            } else {
                None
            };
            if let Some(p) = problem {
                return Err(RecordError::invalid(self.root.join("meta/episodes"), p));
            }
            next_index = e.dataset_to_index;
        }
        Ok(())
    }

    /// Cuts off row groups of data files that no committed episode references (one per
    /// episode, in order); returns the rows removed.
    fn cut_orphan_rows(&mut self) -> Result<i64, RecordError> {
        let mut removed = 0;
        for (chunk, file, path) in chunk_files(&self.root.join("data"), "parquet")? {
            let committed: Vec<&EpisodeRow> = self
                .episodes
                .iter()
                .filter(|e| e.data_chunk_index == chunk && e.data_file_index == file)
                .collect();
            let (groups, _) = pq::row_groups(&path)?;
            if groups.len() < committed.len()
                || committed.iter().zip(&groups).any(|(e, &n)| e.length != n)
            {
                return Err(RecordError::invalid(
                    &path,
                    format!(
                        "row groups {groups:?} do not hold the {} episode(s) the episode table places here",
                        committed.len()
                    ),
                ));
            }
            if groups.len() == committed.len() {
                continue;
            }
            removed += groups[committed.len()..].iter().sum::<i64>();
            if committed.is_empty() {
                std::fs::remove_file(&path)
                    .map_err(RecordError::io(&path, "removing an unreferenced data file"))?;
                if let Some(dir) = path.parent() {
                    fsutil::sync_dir(dir)?;
                }
            } else {
                let keep = committed.len();
                self.rewrite_data_file(&path, keep, &[])?;
            }
        }
        Ok(removed)
    }

    /// Cuts off video frames that no committed episode references: a camera's files after its
    /// last referenced one are removed, and that one is cut to the frames its episodes span.
    /// Returns the frames removed.
    fn cut_orphan_video(&mut self) -> Result<u64, RecordError> {
        let mut removed = 0;
        for (c, camera) in self.features.cameras.iter().enumerate() {
            let key = camera.key();
            let spans: Vec<(i64, i64, i64)> = self
                .episodes
                .iter()
                .map(|e| {
                    e.videos
                        .get(c)
                        .map(|v| (v.chunk_index, v.file_index, e.length))
                        .ok_or_else(|| {
                            RecordError::invalid(
                                self.root.join("meta/episodes"),
                                format!("episode {} has no video of {key}", e.episode_index),
                            )
                        })
                })
                .collect::<Result<_, _>>()?;
            let last = spans.last().map(|&(chunk, file, _)| (chunk, file));
            for (chunk, file, path) in chunk_files(&self.root.join("videos").join(&key), "mp4")? {
                if last.is_some_and(|l| (chunk, file) <= l) {
                    continue;
                }
                removed += video::count_frames(&path).unwrap_or(0);
                std::fs::remove_file(&path).map_err(RecordError::io(
                    &path,
                    "removing an unreferenced video file",
                ))?;
                if let Some(dir) = path.parent() {
                    fsutil::sync_dir(dir)?;
                }
            }
            let Some((chunk, file)) = last else {
                continue;
            };
            let referenced: i64 = spans
                .iter()
                .filter(|&&(c, f, _)| (c, f) == (chunk, file))
                .map(|&(_, _, len)| len)
                .sum();
            let path = self.root.join(video_file(&key, chunk, file));
            let held = video::count_frames(&path)?;
            match held.cmp(&(referenced as u64)) {
                std::cmp::Ordering::Equal => {}
                std::cmp::Ordering::Less => {
                    return Err(RecordError::invalid(
                        &path,
                        format!("holds {held} frames; its episodes span {referenced}"),
                    ))
                }
                std::cmp::Ordering::Greater => {
                    let tmp = fsutil::temp_path(&path);
                    let piece = video::Piece {
                        path: &path,
                        frames: referenced as u64,
                    };
                    video::concat(&[piece], self.settings.fps, &tmp)?;
                    fsutil::rename_into_place(&tmp, &path)?;
                    removed += held - referenced as u64;
                }
            }
        }
        Ok(removed)
    }

    /// Replaces a data file with its first `keep` row groups plus `rows` as a new one.
    fn rewrite_data_file(
        &self,
        path: &Path,
        keep: usize,
        rows: &[DataRow],
    ) -> Result<(), RecordError> {
        let schema = pq::data_schema(&self.features).map_err(RecordError::parquet(path))?;
        let existing = if keep > 0 {
            let (_, theirs) = pq::row_groups(path)?;
            if theirs != schema {
                return Err(RecordError::invalid(
                    path,
                    "its schema differs from the dataset's features",
                ));
            }
            Some(File::open(path).map_err(RecordError::io(path, "opening"))?)
        } else {
            None
        };
        let props = pq::properties(pq::data_metadata(&self.features));
        fsutil::replace_with(path, |out| {
            let mut writer = SerializedFileWriter::new(out, schema.clone(), props)
                .map_err(RecordError::parquet(path))?;
            if let Some(src) = &existing {
                pq::copy_row_groups(&mut writer, src, keep).map_err(RecordError::parquet(path))?;
            }
            if !rows.is_empty() {
                pq::write_data_rows(&mut writer, &self.features, rows)
                    .map_err(RecordError::parquet(path))?;
            }
            writer.close().map_err(RecordError::parquet(path))?;
            Ok(())
        })
    }

    /// Rewrites `info.json`, `stats.json` and `nori.json` from the episode table.
    fn write_summaries(&self) -> Result<(), RecordError> {
        let total_frames = self.episodes.last().map_or(0, |e| e.dataset_to_index);
        let mut splits = BTreeMap::new();
        if !self.episodes.is_empty() {
            splits.insert("train".to_string(), format!("0:{}", self.episodes.len()));
        }
        let info = Info {
            codebase_version: CODEBASE_VERSION.into(),
            fps: self.settings.fps,
            features: self.features.info_json(self.settings.fps),
            total_episodes: self.episodes.len() as i64,
            total_frames,
            total_tasks: self.tasks.len() as i64,
            chunks_size: CHUNKS_SIZE,
            data_files_size_in_mb: self.settings.data_files_size_in_mb,
            video_files_size_in_mb: VIDEO_FILES_SIZE_IN_MB,
            data_path: DATA_PATH.into(),
            video_path: (!self.features.cameras.is_empty()).then(|| VIDEO_PATH.into()),
            robot_type: Some(self.settings.robot_type.clone()),
            splits,
        };
        let nori = NoriMeta {
            features: self.features.clone(),
            action: "the joint position goal the bus-driver sent in the sampled cycle, after its calibration clamp (JointState goal_rad)".into(),
            missing: "observation.joint_valid = 0: no valid read of the joint (or of a gripper's grip force) within the last frame period; its values are its last read, held. observation.camera_valid = 0: the camera's image is its last one, held (none captured within the staleness bound). Frames are recorded only once every joint was read and every camera seen".into(),
        };
        let path = self.root.join("meta/nori.json");
        fsutil::replace(&path, &json_bytes(&path, &nori)?)?;
        if !self.episodes.is_empty() {
            let stats = Ordered(
                self.features
                    .keys()
                    .into_iter()
                    .filter_map(|key| {
                        let image = self.features.is_video(&key);
                        let parts: Vec<FeatureStats> = self
                            .episodes
                            .iter()
                            .filter_map(|e| {
                                e.stats
                                    .iter()
                                    .find(|(k, _)| *k == key)
                                    .map(|(_, s)| s.clone())
                            })
                            .collect();
                        FeatureStats::aggregate(&parts).map(|s| (key, s.to_json(image)))
                    })
                    .collect(),
            );
            let path = self.root.join("meta/stats.json");
            fsutil::replace(&path, &json_bytes(&path, &stats)?)?;
        }
        // info.json last: it is what a reader opens first, and it only ever counts episodes
        // whose rows and metadata are already in place.
        let path = self.root.join("meta/info.json");
        fsutil::replace(&path, &json_bytes(&path, &info)?)
    }

    fn recover_staged(
        &mut self,
        drop_unfinished: bool,
        recovery: &mut Recovery,
    ) -> Result<(), RecordError> {
        let staging = self.root.join(STAGING);
        let mut dirs: Vec<PathBuf> = std::fs::read_dir(&staging)
            .map_err(RecordError::io(&staging, "listing"))?
            .flatten()
            .map(|e| e.path())
            .filter(|p| {
                p.is_dir()
                    && p.file_name()
                        .is_some_and(|n| n.to_string_lossy().starts_with("episode-"))
            })
            .collect();
        dirs.sort();
        for dir in dirs {
            let meta = read_json::<StagedEpisode>(&dir.join("episode.json")).ok();
            let Some(meta) = meta else {
                // Killed before its episode.json was in place: no part can exist yet.
                recovery.dropped.push((-1, 0, "no episode.json".into()));
                remove_dir(&dir)?;
                continue;
            };
            if meta.episode_index < self.episodes.len() as i64 {
                recovery.already_committed += 1;
                remove_dir(&dir)?;
                continue;
            }
            let mut frames = self.read_parts(&dir)?;
            let (in_videos, short) = self.staged_video_frames(&dir);
            let unplaceable = frames.len();
            frames.truncate(in_videos.min(unplaceable));
            if frames.is_empty() || drop_unfinished || meta.fps != self.settings.fps {
                let why = if unplaceable == 0 {
                    "no frame was flushed".to_string()
                } else if frames.is_empty() {
                    format!("no frame of its video{}", short.unwrap_or_default())
                } else if drop_unfinished {
                    "unfinished episodes are dropped (asked)".to_string()
                } else {
                    "staged at another fps".to_string()
                };
                recovery
                    .dropped
                    .push((meta.episode_index, unplaceable, why));
                remove_dir(&dir)?;
                continue;
            }
            let row = self.commit(&meta.task, &frames, &dir)?;
            recovery.recovered.push((row.episode_index, frames.len()));
            remove_dir(&dir)?;
        }
        Ok(())
    }

    /// The frames every camera's staged video of the episode staged in `dir` holds (unbounded
    /// without cameras), and which camera holds the fewest, with its reason if unreadable.
    fn staged_video_frames(&self, dir: &Path) -> (usize, Option<String>) {
        let mut fewest = (usize::MAX, None);
        for camera in &self.features.cameras {
            let (n, why) = match video::staged_frames(&staged_video(dir, camera)) {
                Ok(f) => (
                    f.len(),
                    format!(" (camera {}: {} frames)", camera.name, f.len()),
                ),
                Err(e) => (0, format!(" (camera {}: {e})", camera.name)),
            };
            if n < fewest.0 {
                fewest = (n, Some(why));
            }
        }
        fewest
    }

    /// The frames of a staged episode's parts, in order, up to the first gap.
    fn read_parts(&self, dir: &Path) -> Result<Vec<Frame>, RecordError> {
        let mut parts: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(RecordError::io(dir, "listing"))?
            .flatten()
            .map(|e| e.path())
            .filter(|p| p.extension().is_some_and(|x| x == "parquet"))
            .collect();
        parts.sort();
        let mut frames = Vec::new();
        for part in parts {
            let rows = pq::read_data(&part, &self.features)?;
            // Parts are renamed into place whole and in order, so a gap means a part is
            // missing (removed by hand): what follows it cannot be placed in time.
            if rows
                .first()
                .is_some_and(|r| r.frame_index != frames.len() as i64)
            {
                break;
            }
            frames.extend(rows.into_iter().map(|r| r.frame));
        }
        Ok(frames)
    }

    /// Starts recording an episode of `task`: its frames are staged every `flush_every` frames.
    pub fn begin_episode(
        &mut self,
        task: &str,
        flush_every: usize,
    ) -> Result<EpisodeWriter<'_>, RecordError> {
        if task.trim().is_empty() {
            return Err(RecordError::Request("the task description is empty".into()));
        }
        if flush_every == 0 || flush_every > self.settings.fps as usize {
            return Err(RecordError::Request(format!(
                "flush every {flush_every} frames: must be 1..={} (at most one second at {} fps)",
                self.settings.fps, self.settings.fps
            )));
        }
        let episode_index = self.episodes.len() as i64;
        let dir = self
            .root
            .join(STAGING)
            .join(format!("episode-{episode_index:06}"));
        if dir.exists() {
            remove_dir(&dir)?;
        }
        fsutil::create_dir(&dir)?;
        let staged = StagedEpisode {
            episode_index,
            task: task.into(),
            fps: self.settings.fps,
            started_unix_ms: unix_ms(),
        };
        let path = dir.join("episode.json");
        fsutil::replace(&path, &json_bytes(&path, &staged)?)?;
        let mut videos = Vec::new();
        if !self.features.cameras.is_empty() {
            fsutil::create_dir(&dir.join("videos"))?;
        }
        for camera in &self.features.cameras {
            videos.push(StagedVideo::start(
                &staged_video(&dir, camera),
                u64::from(self.settings.fps),
            )?);
        }
        let (jobs, queue) = mpsc::channel();
        let (done, written) = mpsc::channel();
        let features = self.features.clone();
        let writer = std::thread::Builder::new()
            .name("staged-parts".into())
            .spawn(move || part_writer(features, queue, done))
            .map_err(RecordError::io(&dir, "starting the staged-part writer"))?;
        Ok(EpisodeWriter {
            dataset: self,
            dir,
            task: task.into(),
            episode_index,
            frames: Vec::new(),
            flushed: 0,
            parts: 0,
            flush_every,
            jobs: Some(jobs),
            written,
            on_disk: 0,
            writer: Some(writer),
            videos,
        })
    }

    /// Appends an episode of `frames` of `task`, staged in `staged` (its videos), to the
    /// dataset (see the module documentation for the order of the writes).
    fn commit(
        &mut self,
        task: &str,
        frames: &[Frame],
        staged: &Path,
    ) -> Result<EpisodeRow, RecordError> {
        let task_index = match self.tasks.iter().position(|t| t == task) {
            Some(i) => i as i64,
            None => {
                self.tasks.push(task.into());
                let path = self.root.join("meta/tasks.parquet");
                let tasks = self.tasks.clone();
                fsutil::replace_with(&path, |f| {
                    pq::write_tasks(f, &tasks).map_err(RecordError::parquet(&path))
                })?;
                (self.tasks.len() - 1) as i64
            }
        };
        // LeRobot's rule: a file takes the new episode unless its size plus the episode's,
        // estimated at the file's own bytes per unit (frames, or episode rows), reaches the limit.
        let limit = (self.settings.data_files_size_in_mb * 1024 * 1024) as f64;
        let too_big = |rel: &str, units_in_file: i64, new_units: i64| {
            std::fs::metadata(self.root.join(rel)).is_ok_and(|m| {
                let size = m.len() as f64;
                let per_unit = size / units_in_file.max(1) as f64;
                size + per_unit * new_units as f64 >= limit
            })
        };
        let episode_index = self.episodes.len() as i64;
        let from = self.episodes.last().map_or(0, |e| e.dataset_to_index);
        let (mut chunk, mut file) = self
            .episodes
            .last()
            .map_or((0, 0), |e| (e.data_chunk_index, e.data_file_index));
        let frames_in_file: i64 = self
            .episodes
            .iter()
            .filter(|e| e.data_chunk_index == chunk && e.data_file_index == file)
            .map(|e| e.length)
            .sum();
        if too_big(&data_file(chunk, file), frames_in_file, frames.len() as i64) {
            (chunk, file) = next_file(chunk, file);
        }
        let fps = self.settings.fps as f64;
        let rows: Vec<DataRow> = frames
            .iter()
            .enumerate()
            .map(|(i, f)| DataRow {
                frame: f.clone(),
                timestamp: (i as f64 / fps) as f32,
                frame_index: i as i64,
                episode_index,
                index: from + i as i64,
                task_index,
            })
            .collect();
        let in_file = self
            .episodes
            .iter()
            .filter(|e| e.data_chunk_index == chunk && e.data_file_index == file)
            .count();
        self.rewrite_data_file(&self.root.join(data_file(chunk, file)), in_file, &rows)?;
        let (videos, video_stats) = self.append_videos(staged, frames.len() as u64)?;

        let (mut meta_chunk, mut meta_file) = self
            .episodes
            .last()
            .map_or((0, 0), |e| (e.meta_chunk_index, e.meta_file_index));
        let rows_in_file = self
            .episodes
            .iter()
            .filter(|e| e.meta_chunk_index == meta_chunk && e.meta_file_index == meta_file)
            .count() as i64;
        if too_big(&episodes_file(meta_chunk, meta_file), rows_in_file, 1) {
            (meta_chunk, meta_file) = next_file(meta_chunk, meta_file);
        }
        let row = EpisodeRow {
            episode_index,
            tasks: vec![task.into()],
            length: frames.len() as i64,
            data_chunk_index: chunk,
            data_file_index: file,
            dataset_from_index: from,
            dataset_to_index: from + frames.len() as i64,
            videos,
            stats: episode_stats(&self.features, &rows, video_stats),
            meta_chunk_index: meta_chunk,
            meta_file_index: meta_file,
        };
        let mut same_file: Vec<EpisodeRow> = self
            .episodes
            .iter()
            .filter(|e| e.meta_chunk_index == meta_chunk && e.meta_file_index == meta_file)
            .cloned()
            .collect();
        same_file.push(row.clone());
        let path = self.root.join(episodes_file(meta_chunk, meta_file));
        let features = self.features.clone();
        fsutil::replace_with(&path, |f| {
            pq::write_episodes(f, &features, &same_file).map_err(RecordError::parquet(&path))
        })?;
        self.episodes.push(row.clone());
        self.write_summaries()?;
        Ok(row)
    }

    /// Appends the first `frames` frames of each camera's video staged in `staged` to the
    /// camera's video file (a new file when the current one would pass the size limit), and
    /// samples them for statistics. Returns where each landed and its statistics.
    fn append_videos(
        &self,
        staged: &Path,
        frames: u64,
    ) -> Result<(Vec<VideoSpan>, KeyedStats), RecordError> {
        let fps = f64::from(self.settings.fps);
        let limit = self.settings.video_files_size_in_mb * 1024 * 1024;
        let mut spans = Vec::new();
        let mut stats = Vec::new();
        for (c, camera) in self.features.cameras.iter().enumerate() {
            let key = camera.key();
            let stream = staged_video(staged, camera);
            let jpegs = video::staged_frames(&stream)?;
            if (jpegs.len() as u64) < frames {
                return Err(RecordError::invalid(
                    &stream,
                    format!(
                        "holds {} whole JPEGs, the episode {frames} frames",
                        jpegs.len()
                    ),
                ));
            }
            let (histograms, sampled) = video::image_histograms(frames, |k| {
                video::read_staged(&stream, jpegs[k as usize])
            })?;
            stats.push((
                key.clone(),
                FeatureStats::of_histograms(&histograms, sampled),
            ));
            let episode = stream.with_extension("mp4");
            video::mux(&stream, frames, self.settings.fps, &episode)?;
            let (mut chunk, mut file) = self
                .episodes
                .last()
                .and_then(|e| e.videos.get(c))
                .map_or((0, 0), |v| (v.chunk_index, v.file_index));
            let mut in_file: i64 = self
                .episodes
                .iter()
                .filter(|e| {
                    e.videos
                        .get(c)
                        .is_some_and(|v| (v.chunk_index, v.file_index) == (chunk, file))
                })
                .map(|e| e.length)
                .sum();
            let size = |p: &Path| std::fs::metadata(p).map_or(0, |m| m.len());
            let current = self.root.join(video_file(&key, chunk, file));
            if in_file > 0 && size(&current) + size(&episode) >= limit {
                (chunk, file) = next_file(chunk, file);
                in_file = 0;
            }
            let path = self.root.join(video_file(&key, chunk, file));
            let mut pieces = Vec::new();
            if in_file > 0 {
                pieces.push(video::Piece {
                    path: &path,
                    frames: in_file as u64,
                });
            }
            pieces.push(video::Piece {
                path: &episode,
                frames,
            });
            let tmp = fsutil::temp_path(&path);
            if let Some(dir) = path.parent() {
                fsutil::create_dir(dir)?;
            }
            video::concat(&pieces, self.settings.fps, &tmp)?;
            fsutil::rename_into_place(&tmp, &path)?;
            spans.push(VideoSpan {
                chunk_index: chunk,
                file_index: file,
                from_timestamp: in_file as f64 / fps,
                to_timestamp: (in_file as u64 + frames) as f64 / fps,
            });
        }
        Ok((spans, stats))
    }

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
        read_episode_rows(&self.root, &self.features, &self.episodes, episode_index)
    }
}

/// Rows of `episode_index` among `episodes`, from its data file, checked against its length.
fn read_episode_rows(
    root: &Path,
    features: &Features,
    episodes: &[EpisodeRow],
    episode_index: i64,
) -> Result<Vec<DataRow>, RecordError> {
    let e = episodes
        .iter()
        .find(|e| e.episode_index == episode_index)
        .ok_or_else(|| {
            RecordError::Request(format!(
                "no episode {episode_index} in {} (it has {})",
                root.display(),
                episodes.len()
            ))
        })?;
    let path = root.join(data_file(e.data_chunk_index, e.data_file_index));
    let rows: Vec<DataRow> = pq::read_data(&path, features)?
        .into_iter()
        .filter(|r| r.episode_index == episode_index)
        .collect();
    if rows.len() as i64 != e.length {
        return Err(RecordError::invalid(
            &path,
            format!(
                "episode {episode_index} has {} rows, its length is {}",
                rows.len(),
                e.length
            ),
        ));
    }
    Ok(rows)
}

/// Statistics by feature key.
type KeyedStats = Vec<(String, FeatureStats)>;

/// Statistics of every feature of one episode, in feature order (`videos`: the cameras').
fn episode_stats(features: &Features, rows: &[DataRow], videos: KeyedStats) -> KeyedStats {
    let n = rows.len();
    let mut out = Vec::new();
    for v in features.vectors() {
        let columns: Vec<Vec<f64>> = (0..features.width(v))
            .map(|d| {
                rows.iter()
                    .map(|r| f64::from(r.frame.vector(v)[d]))
                    .collect()
            })
            .collect();
        out.push((v.key().to_string(), FeatureStats::of_columns(&columns, n)));
    }
    out.extend(videos);
    for (key, _) in SCALARS {
        let column: Vec<f64> = rows
            .iter()
            .map(|r| match key {
                "timestamp" => f64::from(r.timestamp),
                "frame_index" => r.frame_index as f64,
                "episode_index" => r.episode_index as f64,
                "index" => r.index as f64,
                _ => r.task_index as f64,
            })
            .collect();
        out.push((key.to_string(), FeatureStats::of_columns(&[column], n)));
    }
    out
}

fn remove_dir(dir: &Path) -> Result<(), RecordError> {
    std::fs::remove_dir_all(dir).map_err(RecordError::io(dir, "removing"))?;
    if let Some(parent) = dir.parent() {
        fsutil::sync_dir(parent)?;
    }
    Ok(())
}

/// A part handed to the background writer: its file and rows.
type PartJob = (PathBuf, Vec<DataRow>);

/// Writes staged parts in order, off the recording loop: an fsync on a busy disk takes tens to
/// hundreds of milliseconds, which would otherwise delay the frame ticks. Ends at the first
/// error (reported when the episode is flushed or finished) or when the channel closes.
fn part_writer(
    features: Features,
    jobs: mpsc::Receiver<PartJob>,
    written: mpsc::Sender<usize>,
) -> Result<(), RecordError> {
    let schema = pq::data_schema(&features).map_err(RecordError::parquet("staged part schema"))?;
    for (n, (path, rows)) in jobs.into_iter().enumerate() {
        fsutil::replace_with(&path, |out| {
            let mut w = SerializedFileWriter::new(out, schema.clone(), pq::properties(Vec::new()))
                .map_err(RecordError::parquet(&path))?;
            pq::write_data_rows(&mut w, &features, &rows).map_err(RecordError::parquet(&path))?;
            w.close().map_err(RecordError::parquet(&path))?;
            Ok(())
        })?;
        // The recorder may have stopped listening; the part is on disk either way.
        let _ = written.send(n + 1);
    }
    Ok(())
}

/// The episode being recorded: frames in memory, handed every flush interval to a background
/// writer that stages them as a part file.
///
/// What a crash loses: the frames not yet handed over (less than one flush interval) and the
/// part being written at that moment, if its rename has not happened (one more interval at
/// most, usually a few milliseconds of writing). `nori record` flushes every 500 ms by default,
/// so the loss stays within one second unless a write takes longer than half a second.
pub struct EpisodeWriter<'a> {
    dataset: &'a mut Dataset,
    dir: PathBuf,
    task: String,
    episode_index: i64,
    frames: Vec<Frame>,
    flushed: usize,
    parts: usize,
    flush_every: usize,
    jobs: Option<mpsc::Sender<PartJob>>,
    written: mpsc::Receiver<usize>,
    on_disk: usize,
    writer: Option<std::thread::JoinHandle<Result<(), RecordError>>>,
    /// Each camera's staged video, in [`Features::cameras`] order.
    videos: Vec<StagedVideo>,
}

impl EpisodeWriter<'_> {
    /// Adds the next frame of a dataset without cameras; flushes when a flush interval is full.
    /// Returns whether it flushed.
    pub fn push(&mut self, frame: Frame) -> Result<bool, RecordError> {
        self.push_with_images(frame, Vec::new())
    }

    /// Adds the next frame with each camera's JPEG (in [`Features::cameras`] order). A frame
    /// some camera's video could not take (its writer two seconds behind) is not added, so the
    /// data and the videos stay frame for frame: the episode should end there
    /// ([`RecordError::VideoBehind`]).
    pub fn push_with_images(
        &mut self,
        frame: Frame,
        images: Vec<Vec<u8>>,
    ) -> Result<bool, RecordError> {
        if images.len() != self.videos.len() {
            return Err(RecordError::Request(format!(
                "{} image(s) for {} camera(s)",
                images.len(),
                self.videos.len()
            )));
        }
        for (c, (video, jpeg)) in self.videos.iter_mut().zip(images).enumerate() {
            if !video.push(jpeg) {
                return Err(RecordError::VideoBehind {
                    camera: self.dataset.features.cameras[c].name.clone(),
                });
            }
        }
        self.frames.push(frame);
        if self.frames.len() - self.flushed >= self.flush_every {
            self.flush()?;
            return Ok(true);
        }
        Ok(false)
    }

    /// Hands the frames not yet staged to the writer, as one part file.
    pub fn flush(&mut self) -> Result<(), RecordError> {
        if self.flushed == self.frames.len() {
            return Ok(());
        }
        let fps = f64::from(self.dataset.settings.fps);
        let from = self
            .dataset
            .episodes
            .last()
            .map_or(0, |e| e.dataset_to_index);
        let rows: Vec<DataRow> = self.frames[self.flushed..]
            .iter()
            .enumerate()
            .map(|(k, f)| {
                let i = self.flushed + k;
                DataRow {
                    frame: f.clone(),
                    timestamp: (i as f64 / fps) as f32,
                    frame_index: i as i64,
                    episode_index: self.episode_index,
                    index: from + i as i64,
                    // Provisional: the task's index is settled when the episode is committed.
                    task_index: -1,
                }
            })
            .collect();
        let path = self.dir.join(format!("part-{:06}.parquet", self.parts));
        let sent = self
            .jobs
            .as_ref()
            .is_some_and(|jobs| jobs.send((path, rows)).is_ok());
        if !sent {
            // The writer stopped: its error says why.
            self.wait_for_writer()?;
            return Err(RecordError::Request(
                "the staged-part writer stopped".into(),
            ));
        }
        self.parts += 1;
        self.flushed = self.frames.len();
        Ok(())
    }

    /// Closes the queue and waits until every part handed over is on disk.
    fn wait_for_writer(&mut self) -> Result<(), RecordError> {
        self.jobs = None;
        match self.writer.take().map(std::thread::JoinHandle::join) {
            Some(Ok(result)) => result,
            Some(Err(_)) => Err(RecordError::Request(
                "the staged-part writer panicked".into(),
            )),
            None => Ok(()),
        }
    }

    /// Waits until every part handed to the writer is on disk (renamed and synced).
    pub fn sync(&mut self) -> Result<(), RecordError> {
        while self.on_disk < self.parts {
            match self.written.recv() {
                Ok(n) => self.on_disk = n,
                Err(_) => {
                    self.wait_for_writer()?;
                    return Err(RecordError::Request(
                        "the staged-part writer stopped".into(),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Frames so far.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Whether no frame was taken yet.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Frames handed to the part writer.
    pub fn flushed(&self) -> usize {
        self.flushed
    }

    /// Commits the episode to the dataset; `None` (and nothing written) if it has no frame.
    pub fn finish(mut self) -> Result<Option<EpisodeRow>, RecordError> {
        self.wait_for_writer()?;
        for video in std::mem::take(&mut self.videos) {
            video.finish()?;
        }
        // Every video holds at least the frames pushed (one may hold one more, see
        // `push_with_images`); a video FFmpeg lost frames of shortens the episode.
        let (in_videos, _) = self.dataset.staged_video_frames(&self.dir);
        let mut frames = std::mem::take(&mut self.frames);
        frames.truncate(in_videos);
        if frames.is_empty() {
            remove_dir(&self.dir)?;
            return Ok(None);
        }
        let row = self.dataset.commit(&self.task, &frames, &self.dir)?;
        remove_dir(&self.dir)?;
        Ok(Some(row))
    }

    /// Stops without committing, as a crash right after the last flush would: the staged parts
    /// stay for the next [`Dataset::open`] to complete or drop.
    pub fn abandon(mut self) -> Result<(), RecordError> {
        self.wait_for_writer()
    }

    /// Drops the episode (its staged parts too).
    pub fn discard(mut self) -> Result<(), RecordError> {
        self.wait_for_writer()?;
        remove_dir(&self.dir)
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

impl Drop for EpisodeWriter<'_> {
    fn drop(&mut self) {
        // Every path out waits for the writer thread, so no part is written after the dataset's
        // lock is released.
        let _ = self.wait_for_writer();
    }
}

/// A dataset opened for reading only (no lock, no repair): what `info.json`, `nori.json` and
/// the episode table say. Rows a crashed commit left unreferenced are not seen.
pub struct DatasetReader {
    /// The root.
    pub root: PathBuf,
    /// `meta/info.json`.
    pub info: Info,
    /// The recorded joints (`meta/nori.json`).
    pub features: Features,
    /// Committed episodes.
    pub episodes: Vec<EpisodeRow>,
}

impl DatasetReader {
    /// Reads the metadata of the dataset at `root`.
    pub fn open(root: &Path) -> Result<DatasetReader, RecordError> {
        let info: Info = read_json(&root.join("meta/info.json"))?;
        let nori: NoriMeta = read_json(&root.join("meta/nori.json"))?;
        let mut episodes = Vec::new();
        for (_, _, path) in chunk_files(&root.join("meta/episodes"), "parquet")? {
            episodes.extend(pq::read_episodes(&path, &nori.features)?);
        }
        episodes.sort_by_key(|e| e.episode_index);
        episodes.truncate(usize::try_from(info.total_episodes).unwrap_or(0));
        Ok(DatasetReader {
            root: root.into(),
            info,
            features: nori.features,
            episodes,
        })
    }

    /// Rows of one committed episode.
    pub fn read_episode(&self, episode_index: i64) -> Result<Vec<DataRow>, RecordError> {
        read_episode_rows(&self.root, &self.features, &self.episodes, episode_index)
    }
}
