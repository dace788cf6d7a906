//! Where each file of the dataset is: the data, episode and video files by chunk and file index,
//! the file after a full one, the chunk files under a directory, a staged episode's video stream;
//! and removing a staged directory durably.

use super::CHUNKS_SIZE;
use crate::error::RecordError;
use crate::features::CameraMeta;
use crate::fsutil;
use std::path::{Path, PathBuf};

pub(super) fn data_file(chunk: i64, file: i64) -> String {
    format!("data/chunk-{chunk:03}/file-{file:03}.parquet")
}

pub(super) fn episodes_file(chunk: i64, file: i64) -> String {
    format!("meta/episodes/chunk-{chunk:03}/file-{file:03}.parquet")
}

pub(super) fn video_file(key: &str, chunk: i64, file: i64) -> String {
    format!("videos/{key}/chunk-{chunk:03}/file-{file:03}.mp4")
}

/// Where a staged episode's video stream of `camera` is.
pub(super) fn staged_video(dir: &Path, camera: &CameraMeta) -> PathBuf {
    dir.join("videos").join(format!("{}.mjpeg", camera.key()))
}

pub(super) fn next_file(chunk: i64, file: i64) -> (i64, i64) {
    if file == CHUNKS_SIZE - 1 {
        (chunk + 1, 0)
    } else {
        (chunk, file + 1)
    }
}

/// `chunk-NNN/file-NNN.<ext>` files under `dir`, sorted, with their indices.
pub(super) fn chunk_files(dir: &Path, ext: &str) -> Result<Vec<(i64, i64, PathBuf)>, RecordError> {
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

pub(super) fn remove_dir(dir: &Path) -> Result<(), RecordError> {
    std::fs::remove_dir_all(dir).map_err(RecordError::io(dir, "removing"))?;
    if let Some(parent) = dir.parent() {
        fsutil::sync_dir(parent)?;
    }
    Ok(())
}
