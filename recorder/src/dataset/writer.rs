//! Recording an episode: [`Dataset::begin_episode`] stages it (its `episode.json`, each camera's
//! staged video), and [`EpisodeWriter`] takes its frames, handing each flush interval to a
//! background thread that writes it as a part file; the episode is then committed, left staged
//! or discarded.

use super::layout::{remove_dir, staged_video};
use super::meta::{json_bytes, StagedEpisode};
use super::{Dataset, STAGING};
use crate::error::RecordError;
use crate::features::Features;
use crate::fsutil;
use crate::pq::{self, DataRow, EpisodeRow};
use crate::sampler::Frame;
use crate::video::StagedVideo;
use parquet::file::writer::SerializedFileWriter;
use std::path::PathBuf;
use std::sync::mpsc;

fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

impl Dataset {
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

impl Drop for EpisodeWriter<'_> {
    fn drop(&mut self) {
        // Every path out waits for the writer thread, so no part is written after the dataset's
        // lock is released.
        let _ = self.wait_for_writer();
    }
}
