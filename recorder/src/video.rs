//! A camera's video in a recording: one JPEG per dataset frame, kept as the camera sent it
//! (`nori bench video-encode` has the figures behind not encoding on the robot).
//!
//! * [`pick`] decides, at each frame tick, whether the camera's newest JPEG is fresh or whether
//!   the last one is held (the camera died, stalled or fell behind): one video frame per dataset
//!   frame whatever the camera does, so the video has a constant rate and frame `k` sits at
//!   `k / fps`, where LeRobot's decoders look for it. Pure.
//! * [`StagedVideo`] appends an episode's JPEGs, as they come, to a staged stream
//!   (`<key>.mjpeg`, the JPEGs back to back) and an index of where each one is (`<key>.idx`),
//!   from a thread of its own behind a bounded queue: a slow disk never delays a frame tick, and
//!   no FFmpeg runs (nor holds its ~50 MB) while recording. A `kill -9` keeps every JPEG whose
//!   index entry was written ([`staged_frames`] checks each against the stream).
//! * At commit, [`mux`] makes an MP4 of the staged stream (FFmpeg, stream copy), [`concat`]
//!   appends it to the dataset's video file (cut at frame counts), [`image_histograms`] samples
//!   the JPEGs for the statistics LeRobot normalises images with, and [`count_frames`] counts a
//!   video file's frames (ffprobe).
//! * [`jpeg_format`] reads a JPEG's size and FFmpeg's name of its pixel format from its frame
//!   header (`video.pix_fmt` in `info.json`, known before any video is written). Pure.

use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc::{sync_channel, SyncSender, TrySendError};
use std::thread::JoinHandle;
use thiserror::Error;

/// How a tick's image was obtained.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pick {
    /// The camera's newest frame, captured within the staleness bound of the tick.
    Fresh,
    /// No frame recent enough: the previous one is held (and the frame marked).
    Held,
    /// Nothing was ever received: there is nothing to hold.
    Nothing,
}

/// The image of the tick at `tick_ns`, given the capture time of the camera's newest frame
/// received by then: fresh when it was captured no more than `stale_after_ns` before the tick.
pub fn pick(newest_capture_ns: Option<u64>, tick_ns: u64, stale_after_ns: u64) -> Pick {
    match newest_capture_ns {
        None => Pick::Nothing,
        Some(c) if tick_ns.saturating_sub(c) <= stale_after_ns => Pick::Fresh,
        Some(_) => Pick::Held,
    }
}

/// Why a video could not be written.
#[derive(Debug, Error)]
#[allow(missing_docs, reason = "each field is shown in its variant's message")]
pub enum VideoError {
    /// FFmpeg could not be started.
    #[error("cannot start ffmpeg for {path} (deploy/install-build-deps.sh installs it): {source}")]
    Start {
        /// The video being written.
        path: PathBuf,
        source: std::io::Error,
    },
    /// The staged stream of an episode could not be written.
    #[error("staged video {path}: {reason}")]
    Staged {
        /// The stream.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
    /// FFmpeg or ffprobe could not read a video.
    #[error("reading the video {path}: {reason}")]
    Read {
        /// The video.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
}

/// Runs an FFmpeg tool (`command`, about the video `path`) to its end; its standard output,
/// or why it failed.
fn run(command: &mut Command, path: &Path) -> Result<Vec<u8>, VideoError> {
    let tool = command.get_program().to_string_lossy().into_owned();
    let output = command
        .stdin(Stdio::null())
        .output()
        .map_err(|source| VideoError::Start {
            path: path.into(),
            source,
        })?;
    if !output.status.success() {
        return Err(VideoError::Read {
            path: path.into(),
            reason: format!(
                "{tool} {}: {}",
                output.status,
                String::from_utf8_lossy(&output.stderr).trim()
            ),
        });
    }
    Ok(output.stdout)
}

/// Frames of the video at `path` (its packets, counted by ffprobe: a fragmented MP4 cut off by
/// a crash counts what it holds).
pub fn count_frames(path: &Path) -> Result<u64, VideoError> {
    let out = run(
        Command::new("ffprobe")
            .args(["-v", "error", "-select_streams", "v:0", "-count_packets"])
            .args(["-show_entries", "stream=nb_read_packets", "-of", "csv=p=0"])
            .arg(path),
        path,
    )?;
    let text = String::from_utf8_lossy(&out);
    text.trim().parse().map_err(|_| VideoError::Read {
        path: path.into(),
        reason: format!("ffprobe counted {:?} packets", text.trim()),
    })
}

/// The first `frames` frames of a video, as one piece of a [`concat`].
#[derive(Debug, Clone, Copy)]
pub struct Piece<'a> {
    /// The video.
    pub path: &'a Path,
    /// Frames taken from its start.
    pub frames: u64,
}

/// Writes to `out` (an MP4, whatever its name) the pieces one after the other, by stream copy:
/// frame `k` of the result at `k / fps`. Each piece is cut at its frame count, so frames a crash
/// left after the committed ones in a video file are dropped by the next commit.
pub fn concat(pieces: &[Piece<'_>], fps: u32, out: &Path) -> Result<(), VideoError> {
    let quote = |p: &Path| format!("'{}'", p.display().to_string().replace('\'', "'\\''"));
    let mut list = String::from("ffconcat version 1.0\n");
    for p in pieces.iter().filter(|p| p.frames > 0) {
        // The concat demuxer starts the next piece at this piece's outpoint, and drops the
        // packets at or after it: the first dropped frame's time, `frames / fps`, rounded down
        // to FFmpeg's microseconds (so that frame is still dropped; the error, under a
        // microsecond, vanishes in the file's time base).
        let outpoint_us = p.frames * 1_000_000 / u64::from(fps);
        list += &format!(
            "file {}\noutpoint {}.{:06}\n",
            quote(p.path),
            outpoint_us / 1_000_000,
            outpoint_us % 1_000_000
        );
    }
    let list_path = out.with_extension("ffconcat");
    std::fs::write(&list_path, list).map_err(|e| VideoError::Staged {
        path: list_path.clone(),
        reason: e.to_string(),
    })?;
    let result = run(
        Command::new("ffmpeg")
            .args(["-hide_banner", "-loglevel", "error", "-y"])
            .args(["-f", "concat", "-safe", "0", "-i"])
            .arg(&list_path)
            .args(["-c", "copy", "-f", "mp4"])
            .arg(out),
        out,
    );
    let _ = std::fs::remove_file(&list_path);
    result.map(|_| ())
}

/// Frames LeRobot samples from an episode of `len` frames for image statistics
/// (`estimate_num_samples`: `len^0.75`, at least 100, at most 10 000, never more than `len`).
pub fn sample_count(len: u64) -> u64 {
    let floor = len.min(100);
    ((len as f64).powf(0.75) as u64).clamp(floor, 10_000)
}

/// A JPEG's size and pixel format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct JpegFormat {
    /// Width, px.
    pub width: u32,
    /// Height, px.
    pub height: u32,
    /// FFmpeg's pixel format name of its decoded samples (`yuvj420p`, ..., `gray`).
    pub pix_fmt: &'static str,
}

/// The size and pixel format of the JPEG `jpeg`, from its frame header (SOFn): the luma
/// sampling factors name the chroma subsampling, as FFmpeg's decoder names it (full-range
/// `yuvj*`: JFIF's). `None` if there is no frame header or the layout has no FFmpeg name.
pub fn jpeg_format(jpeg: &[u8]) -> Option<JpegFormat> {
    if jpeg.get(..2)? != [0xFF, 0xD8] {
        return None;
    }
    let mut at = 2;
    loop {
        // Markers may be padded with 0xFF.
        while *jpeg.get(at)? == 0xFF && *jpeg.get(at + 1)? == 0xFF {
            at += 1;
        }
        if *jpeg.get(at)? != 0xFF {
            return None;
        }
        let marker = *jpeg.get(at + 1)?;
        let len = usize::from(u16::from_be_bytes([*jpeg.get(at + 2)?, *jpeg.get(at + 3)?]));
        let body = jpeg.get(at + 4..at + 2 + len)?;
        // SOF0..SOF15, except DHT (C4), JPG (C8) and DAC (CC).
        if (0xC0..=0xCF).contains(&marker) && !matches!(marker, 0xC4 | 0xC8 | 0xCC) {
            let height = u32::from(u16::from_be_bytes([*body.get(1)?, *body.get(2)?]));
            let width = u32::from(u16::from_be_bytes([*body.get(3)?, *body.get(4)?]));
            let components = *body.get(5)?;
            let sampling = |c: usize| body.get(6 + 3 * c + 1).map(|s| (s >> 4, s & 0x0F));
            let pix_fmt = match components {
                1 => "gray",
                3 if sampling(1)? == (1, 1) && sampling(2)? == (1, 1) => match sampling(0)? {
                    (1, 1) => "yuvj444p",
                    (2, 1) => "yuvj422p",
                    (2, 2) => "yuvj420p",
                    (1, 2) => "yuvj440p",
                    (4, 1) => "yuvj411p",
                    _ => return None,
                },
                _ => return None,
            };
            return (width > 0 && height > 0).then_some(JpegFormat {
                width,
                height,
                pix_fmt,
            });
        }
        if marker == 0xDA || len < 2 {
            // Start of scan before any frame header.
            return None;
        }
        at += 2 + len;
    }
}

/// Frames queued for the staged stream's writer at most (two seconds at 30 fps).
const QUEUE: usize = 60;

/// Bytes of one index entry: the JPEG's offset and length in the stream, little-endian u64s.
const INDEX_ENTRY: usize = 16;

/// The staged stream of `video` (`<key>.mjpeg`) and its index (`<key>.idx`).
fn index_path(stream: &Path) -> PathBuf {
    stream.with_extension("idx")
}

/// One camera's JPEGs of the episode being recorded, appended to a staged stream.
pub struct StagedVideo {
    path: PathBuf,
    queue: Option<SyncSender<Vec<u8>>>,
    writer: Option<JoinHandle<std::io::Result<u64>>>,
    frames: u64,
    /// Frames dropped because the writer had not taken the ones before (the queue was full).
    pub dropped: u64,
}

impl StagedVideo {
    /// Starts the stream at `path` (and its index beside it), synced to disk every `sync_every`
    /// frames (a power loss, not a crash, is what that bounds).
    pub fn start(path: &Path, sync_every: u64) -> Result<Self, VideoError> {
        let open = |p: &Path| {
            std::fs::OpenOptions::new()
                .create(true)
                .truncate(true)
                .write(true)
                .open(p)
                .map_err(|e| VideoError::Staged {
                    path: p.into(),
                    reason: e.to_string(),
                })
        };
        let mut stream = open(path)?;
        let mut index = open(&index_path(path))?;
        let (queue, jpegs) = sync_channel::<Vec<u8>>(QUEUE);
        let writer = std::thread::Builder::new()
            .name("staged-video".into())
            .spawn(move || {
                let (mut offset, mut written) = (0u64, 0u64);
                for jpeg in jpegs {
                    stream.write_all(&jpeg)?;
                    // The entry after its JPEG: an entry on disk means its bytes are too.
                    let mut entry = [0u8; INDEX_ENTRY];
                    entry[..8].copy_from_slice(&offset.to_le_bytes());
                    entry[8..].copy_from_slice(&(jpeg.len() as u64).to_le_bytes());
                    index.write_all(&entry)?;
                    offset += jpeg.len() as u64;
                    written += 1;
                    if written.is_multiple_of(sync_every.max(1)) {
                        stream.sync_data()?;
                        index.sync_data()?;
                    }
                }
                stream.sync_all()?;
                index.sync_all()?;
                Ok(written)
            })
            .map_err(|e| VideoError::Staged {
                path: path.into(),
                reason: e.to_string(),
            })?;
        Ok(StagedVideo {
            path: path.into(),
            queue: Some(queue),
            writer: Some(writer),
            frames: 0,
            dropped: 0,
        })
    }

    /// Queues one frame's JPEG; false if it was dropped (the queue full, or the writer gone).
    pub fn push(&mut self, jpeg: Vec<u8>) -> bool {
        let Some(queue) = &self.queue else {
            return false;
        };
        match queue.try_send(jpeg) {
            Ok(()) => {
                self.frames += 1;
                true
            }
            Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) => {
                self.dropped += 1;
                false
            }
        }
    }

    /// Frames queued so far.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Ends the stream: everything queued is written and synced. Returns the frames written.
    pub fn finish(mut self) -> Result<u64, VideoError> {
        drop(self.queue.take());
        match self.writer.take().map(JoinHandle::join) {
            Some(Ok(Ok(n))) => Ok(n),
            Some(Ok(Err(e))) => Err(VideoError::Staged {
                path: self.path.clone(),
                reason: e.to_string(),
            }),
            _ => Err(VideoError::Staged {
                path: self.path.clone(),
                reason: "its writer panicked".into(),
            }),
        }
    }
}

impl Drop for StagedVideo {
    /// An abandoned stream still gets what was queued (as a crash right after would keep).
    fn drop(&mut self) {
        drop(self.queue.take());
        if let Some(w) = self.writer.take() {
            let _ = w.join();
        }
    }
}

/// Where the staged stream at `path` holds whole JPEGs, in order: the index's entries that are
/// complete, follow each other without a gap, lie within the stream and start with a JPEG's
/// start marker and end with its end marker. What a crash cut short is left out.
pub fn staged_frames(path: &Path) -> Result<Vec<(u64, u64)>, VideoError> {
    let read_err = |p: &Path, e: std::io::Error| VideoError::Read {
        path: p.into(),
        reason: e.to_string(),
    };
    let index = std::fs::read(index_path(path)).map_err(|e| read_err(path, e))?;
    let mut stream = std::fs::File::open(path).map_err(|e| read_err(path, e))?;
    let len = stream.metadata().map_err(|e| read_err(path, e))?.len();
    let mut frames = Vec::new();
    let mut expected = 0u64;
    for entry in index.chunks_exact(INDEX_ENTRY) {
        let word = |r: std::ops::Range<usize>| {
            let mut b = [0u8; 8];
            b.copy_from_slice(&entry[r]);
            u64::from_le_bytes(b)
        };
        let (offset, size) = (word(0..8), word(8..16));
        if offset != expected || size < 4 || offset.saturating_add(size) > len {
            break;
        }
        let mut ends = [0u8; 4];
        let whole = (|| -> std::io::Result<()> {
            stream.seek(SeekFrom::Start(offset))?;
            stream.read_exact(&mut ends[..2])?;
            stream.seek(SeekFrom::Start(offset + size - 2))?;
            stream.read_exact(&mut ends[2..])
        })();
        if whole.is_err() || ends != [0xFF, 0xD8, 0xFF, 0xD9] {
            break;
        }
        frames.push((offset, size));
        expected = offset + size;
    }
    Ok(frames)
}

/// Writes to `out` an MP4 of the first `frames` JPEGs of the staged stream at `stream` (FFmpeg,
/// stream copy: frame `k` at `k / fps`).
pub fn mux(stream: &Path, frames: u64, fps: u32, out: &Path) -> Result<(), VideoError> {
    run(
        Command::new("ffmpeg")
            .args(["-hide_banner", "-loglevel", "error", "-y"])
            .args(["-f", "mjpeg", "-framerate", &fps.to_string(), "-i"])
            .arg(stream)
            .args([
                "-frames:v",
                &frames.to_string(),
                "-c:v",
                "copy",
                "-f",
                "mp4",
            ])
            .arg(out),
        out,
    )
    .map(|_| ())
}

/// Per colour channel (R, G, B), how many samples of each value 0..=255 the JPEGs `jpeg(k)`,
/// `k < frames`, hold, sampled as LeRobot samples images for statistics (`compute_stats.py`):
/// [`sample_count`] frames at `round(linspace(0, frames - 1, count))`, each strided by an
/// integer factor to about 150 px (`auto_downsample_height_width`). Returns the histograms and
/// the frames sampled. A JPEG that does not decode is an error naming its frame.
pub fn image_histograms(
    frames: u64,
    mut jpeg: impl FnMut(u64) -> Result<Vec<u8>, VideoError>,
) -> Result<([[u64; 256]; 3], u64), VideoError> {
    let count = sample_count(frames);
    let mut histograms = [[0u64; 256]; 3];
    let mut rgb = Vec::new();
    for i in 0..count {
        let k = if count > 1 {
            ((i as f64) * (frames - 1) as f64 / (count - 1) as f64).round() as u64
        } else {
            0
        };
        let data = jpeg(k)?;
        let options = zune_core::options::DecoderOptions::default()
            .jpeg_set_out_colorspace(zune_core::colorspace::ColorSpace::RGB);
        let mut decoder = zune_jpeg::JpegDecoder::new_with_options(
            zune_core::bytestream::ZCursor::new(&data),
            options,
        );
        let bad = |e: String| VideoError::Read {
            path: PathBuf::from(format!("frame {k}")),
            reason: format!("its JPEG does not decode: {e}"),
        };
        decoder.decode_headers().map_err(|e| bad(e.to_string()))?;
        let (w, h) = decoder
            .info()
            .map(|i| (usize::from(i.width), usize::from(i.height)))
            .ok_or_else(|| bad("no header".into()))?;
        rgb.resize(w * h * 3, 0);
        decoder
            .decode_into(&mut rgb)
            .map_err(|e| bad(e.to_string()))?;
        let factor = if w.max(h) < 300 {
            1
        } else if w > h {
            w / 150
        } else {
            h / 150
        };
        for y in (0..h).step_by(factor) {
            for x in (0..w).step_by(factor) {
                let px = &rgb[(y * w + x) * 3..(y * w + x) * 3 + 3];
                for (c, &v) in px.iter().enumerate() {
                    histograms[c][usize::from(v)] += 1;
                }
            }
        }
    }
    Ok((histograms, count))
}

/// The JPEG at `(offset, size)` of the staged stream at `path`.
pub fn read_staged(path: &Path, (offset, size): (u64, u64)) -> Result<Vec<u8>, VideoError> {
    let mut f = std::fs::File::open(path).map_err(|e| VideoError::Read {
        path: path.into(),
        reason: e.to_string(),
    })?;
    let mut out = vec![0u8; size as usize];
    f.seek(SeekFrom::Start(offset))
        .and_then(|_| f.read_exact(&mut out))
        .map_err(|e| VideoError::Read {
            path: path.into(),
            reason: e.to_string(),
        })?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_is_fresh_within_the_bound_held_after_it_and_nothing_before_the_first() {
        let period = 33_333_333;
        let stale = period * 3 / 2;
        assert_eq!(pick(None, 1_000, stale), Pick::Nothing);
        assert_eq!(pick(Some(1_000), 1_000, stale), Pick::Fresh);
        assert_eq!(pick(Some(1_000), 1_000 + stale, stale), Pick::Fresh);
        assert_eq!(pick(Some(1_000), 1_001 + stale, stale), Pick::Held);
        // A capture stamped after the tick (clock granularity) is fresh, not a wrap-around.
        assert_eq!(pick(Some(2_000), 1_000, stale), Pick::Fresh);
    }
}
