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
