//! A camera's video in a recording: one JPEG per dataset frame, kept as the camera sent it, muxed
//! by FFmpeg into a fragmented MP4 (stream copy: no encoding on the robot; `nori bench
//! video-encode` has the figures behind that choice).
//!
//! * [`pick`] decides, at each frame tick, whether the camera's newest JPEG is fresh or whether
//!   the last one is held (the camera died, stalled or fell behind): one video frame per dataset
//!   frame whatever the camera does, so the video has a constant rate and frame `k` sits at
//!   `k / fps`, where LeRobot's decoders look for it. Pure.
//! * [`VideoWriter`] feeds FFmpeg from a thread of its own through a bounded queue: a slow disk
//!   or a stalled FFmpeg never delays a frame tick; a frame it could not take is counted.
//!   Fragmented MP4 (a fragment per keyframe, and every MJPEG frame is one), flushed packet by
//!   packet, keeps all but the last frame or two readable after a `kill -9` (without the flush,
//!   FFmpeg's output buffer held everything and the file read as nothing).
//! * [`jpeg_format`] reads a JPEG's size and FFmpeg's name of its pixel format from its frame
//!   header (`video.pix_fmt` in `info.json`, known before any video is written). Pure.
//! * [`count_frames`], [`concat`] and [`channel_histograms`] are what a commit does with the
//!   staged video: count it, append it to the dataset's video file (stream copy, cut at a frame
//!   count), and sample it for the statistics LeRobot normalises images with.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
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
pub enum VideoError {
    /// FFmpeg could not be started.
    #[error("cannot start ffmpeg for {path} (deploy/install-build-deps.sh installs it): {source}")]
    Start {
        /// The video being written.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
    /// FFmpeg failed.
    #[error("ffmpeg writing {path}: {reason}")]
    Ffmpeg {
        /// The video.
        path: PathBuf,
        /// Its exit status and error output.
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
    std::fs::write(&list_path, list).map_err(|source| VideoError::Start {
        path: list_path.clone(),
        source,
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

/// Per colour channel (R, G, B), how many samples of each value 0..=255 the first `frames`
/// frames of the video hold, sampled as LeRobot samples them for statistics: about
/// [`sample_count`] frames evenly spread, each shrunk by an integer factor to about 150 px
/// (`auto_downsample_height_width`). Returns the histograms and the frames sampled.
pub fn channel_histograms(
    path: &Path,
    frames: u64,
    width: u32,
    height: u32,
) -> Result<([[u64; 256]; 3], u64), VideoError> {
    let step = (frames / sample_count(frames).max(1)).max(1);
    let factor = if width.max(height) < 300 {
        1
    } else {
        (width.max(height) / 150).max(1)
    };
    let (w, h) = (width.div_ceil(factor), height.div_ceil(factor));
    let filter =
        format!("select='lt(n\\,{frames})*not(mod(n\\,{step}))',scale={w}:{h}:flags=neighbor");
    let rgb = run(
        Command::new("ffmpeg")
            .args(["-hide_banner", "-loglevel", "error", "-threads", "1", "-i"])
            .arg(path)
            .args(["-vf", &filter, "-fps_mode", "passthrough"])
            .args(["-f", "rawvideo", "-pix_fmt", "rgb24", "-"]),
        path,
    )?;
    let frame_len = (w * h * 3) as usize;
    if rgb.is_empty() || rgb.len() % frame_len != 0 {
        return Err(VideoError::Read {
            path: path.into(),
            reason: format!(
                "{} bytes of samples is not a whole number of {w}x{h} frames",
                rgb.len()
            ),
        });
    }
    let mut histograms = [[0u64; 256]; 3];
    for px in rgb.chunks_exact(3) {
        for (c, &v) in px.iter().enumerate() {
            histograms[c][usize::from(v)] += 1;
        }
    }
    Ok((histograms, (rgb.len() / frame_len) as u64))
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

/// Frames queued for FFmpeg at most (two seconds at 30 fps).
const QUEUE: usize = 60;

/// One camera's video being written.
pub struct VideoWriter {
    path: PathBuf,
    queue: Option<SyncSender<Vec<u8>>>,
    feeder: Option<JoinHandle<std::io::Result<()>>>,
    child: Option<Child>,
    frames: u64,
    /// Frames dropped because FFmpeg had not taken the ones before (the queue was full).
    pub dropped: u64,
}

impl VideoWriter {
    /// Starts FFmpeg muxing MJPEG frames at `fps` into the fragmented MP4 at `path`.
    pub fn start(path: &Path, fps: u32) -> Result<Self, VideoError> {
        let mut child = Command::new("ffmpeg")
            .args(["-hide_banner", "-loglevel", "error", "-y"])
            .args(["-f", "mjpeg", "-framerate", &fps.to_string(), "-i", "-"])
            .args(["-c:v", "copy", "-f", "mp4"])
            // A fragment per frame (each MJPEG frame is a keyframe), each written out at once:
            // a killed FFmpeg (or recorder) leaves all but the last frame or two readable.
            .args(["-movflags", "+frag_keyframe+empty_moov+default_base_moof"])
            .args(["-flush_packets", "1"])
            .arg(path)
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|source| VideoError::Start {
                path: path.into(),
                source,
            })?;
        let mut stdin = child.stdin.take().ok_or_else(|| VideoError::Ffmpeg {
            path: path.into(),
            reason: "no stdin".into(),
        })?;
        let (queue, frames) = sync_channel::<Vec<u8>>(QUEUE);
        let feeder = std::thread::Builder::new()
            .name("video-writer".into())
            .spawn(move || {
                for jpeg in frames {
                    stdin.write_all(&jpeg)?;
                }
                Ok(())
            })
            .map_err(|source| VideoError::Start {
                path: path.into(),
                source,
            })?;
        Ok(VideoWriter {
            path: path.into(),
            queue: Some(queue),
            feeder: Some(feeder),
            child: Some(child),
            frames: 0,
            dropped: 0,
        })
    }

    /// Queues one frame's JPEG; false if it was dropped (the queue full, or FFmpeg gone).
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

    /// FFmpeg's process id, while it runs.
    pub fn ffmpeg_pid(&self) -> Option<u32> {
        self.child.as_ref().map(Child::id)
    }

    /// Ends the video: everything queued is written and FFmpeg finishes the file. Returns the
    /// frames written.
    pub fn finish(mut self) -> Result<u64, VideoError> {
        let failed = |reason: String| VideoError::Ffmpeg {
            path: self.path.clone(),
            reason,
        };
        drop(self.queue.take());
        let fed = self.feeder.take().map(JoinHandle::join);
        let child = self
            .child
            .take()
            .ok_or_else(|| failed("finished twice".into()))?;
        let output = child
            .wait_with_output()
            .map_err(|e| failed(e.to_string()))?;
        if !output.status.success() {
            return Err(failed(format!(
                "{}: {}",
                output.status,
                String::from_utf8_lossy(&output.stderr).trim()
            )));
        }
        match fed {
            Some(Ok(Err(e))) => Err(failed(format!("feeding it: {e}"))),
            Some(Err(_)) => Err(failed("the feeding thread panicked".into())),
            _ => Ok(self.frames),
        }
    }
}

impl Drop for VideoWriter {
    /// An abandoned video is still closed properly: FFmpeg gets the end of its input and
    /// finishes the file.
    fn drop(&mut self) {
        drop(self.queue.take());
        if let Some(f) = self.feeder.take() {
            let _ = f.join();
        }
        if let Some(mut child) = self.child.take() {
            let _ = child.wait();
        }
    }
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
