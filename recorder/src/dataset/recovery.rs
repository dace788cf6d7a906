//! Opening a dataset ([`Dataset::open`]): created if there is none, locked, checked against the
//! recording's settings and features, and repaired from what a crash left (see the module
//! documentation): temporaries removed, rows and video frames no episode references cut off, the
//! summaries rewritten, staged episodes completed from their parts or dropped ([`Recovery`]).

use super::layout::{chunk_files, remove_dir, staged_video, video_file};
use super::meta::{read_json, Info, StagedEpisode};
use super::{Dataset, Settings, CHUNKS_SIZE, CODEBASE_VERSION, STAGING};
use crate::error::RecordError;
use crate::features::{FeatureSpec, Features};
use crate::fsutil;
use crate::pq::{self, EpisodeRow};
use crate::sampler::Frame;
use crate::video;
use nix::fcntl::{Flock, FlockArg};
use std::fs::File;
use std::path::{Path, PathBuf};

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
    pub(super) fn staged_video_frames(&self, dir: &Path) -> (usize, Option<String>) {
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
}
