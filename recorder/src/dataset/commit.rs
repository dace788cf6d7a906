//! Finishing an episode durably: `Dataset::commit` writes the task table if the task is new,
//! the data file (its committed row groups copied plus the episode's), each camera's video file
//! (the staged stream muxed and appended), the episode table and the summaries, each replaced
//! atomically and in that order (see the module documentation); and the episode's statistics.

use super::layout::{data_file, episodes_file, next_file, staged_video, video_file};
use super::Dataset;
use crate::error::RecordError;
use crate::features::{Features, SCALARS};
use crate::fsutil;
use crate::pq::{self, DataRow, EpisodeRow, VideoSpan};
use crate::sampler::Frame;
use crate::stats::FeatureStats;
use crate::video;
use parquet::file::writer::SerializedFileWriter;
use std::fs::File;
use std::path::Path;

impl Dataset {
    /// Appends an episode of `frames` of `task`, staged in `staged` (its videos), to the
    /// dataset (see the module documentation for the order of the writes).
    pub(super) fn commit(
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
    /// Replaces a data file with its first `keep` row groups plus `rows` as a new one.
    pub(super) fn rewrite_data_file(
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
