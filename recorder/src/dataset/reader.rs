//! Reading a dataset without its lock or repair ([`DatasetReader`]), and one committed episode's
//! rows back from its data file (for [`DatasetReader`] and [`Dataset::read_episode`](super::Dataset::read_episode)).

use super::layout::{chunk_files, data_file};
use super::meta::{read_json, Info, NoriMeta};
use crate::error::RecordError;
use crate::features::Features;
use crate::pq::{self, DataRow, EpisodeRow};
use std::path::{Path, PathBuf};

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

/// Rows of `episode_index` among `episodes`, from its data file, checked against its length.
pub(super) fn read_episode_rows(
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
