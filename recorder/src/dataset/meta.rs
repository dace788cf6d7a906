//! The JSON metadata: `meta/info.json` ([`Info`]), `meta/nori.json` ([`NoriMeta`]), a staged
//! episode's `episode.json`; reading and writing them, and rewriting `info.json`, `stats.json`
//! and `nori.json` from the episode table.

use super::{
    Dataset, CHUNKS_SIZE, CODEBASE_VERSION, DATA_PATH, VIDEO_FILES_SIZE_IN_MB, VIDEO_PATH,
};
use crate::error::RecordError;
use crate::features::{FeatureSpec, Features, Ordered};
use crate::fsutil;
use crate::stats::FeatureStats;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

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
    /// Committed episodes, numbered `0..total_episodes`: the rows of the episode table a reader
    /// takes (a row written by a commit a crash cut short, beyond them, is not counted).
    pub total_episodes: i64,
    /// Frames of all committed episodes together: the data rows they span, indexed
    /// `0..total_frames` (the last episode's `dataset_to_index`).
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

/// `episode.json` of a staged episode.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) struct StagedEpisode {
    pub(super) episode_index: i64,
    pub(super) task: String,
    pub(super) fps: u32,
    pub(super) started_unix_ms: u64,
}

pub(super) fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, RecordError> {
    let text = std::fs::read_to_string(path).map_err(RecordError::io(path, "reading"))?;
    serde_json::from_str(&text).map_err(|source| RecordError::Json {
        path: path.into(),
        source,
    })
}

pub(super) fn json_bytes<T: Serialize>(path: &Path, value: &T) -> Result<Vec<u8>, RecordError> {
    let mut v = serde_json::to_vec_pretty(value).map_err(|source| RecordError::Json {
        path: path.into(),
        source,
    })?;
    v.push(b'\n');
    Ok(v)
}

impl Dataset {
    /// Rewrites `info.json`, `stats.json` and `nori.json` from the episode table.
    pub(super) fn write_summaries(&self) -> Result<(), RecordError> {
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
}
