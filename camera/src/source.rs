//! Where frames come from: a V4L2 device (the robot's UVC cameras) or a byte stream on a Unix
//! socket (the simulator's cameras). The camera process opens whichever the device path is.

use crate::stream::StreamReader;
use std::io::Read;
use std::os::unix::fs::FileTypeExt;
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::Duration;
use telemetry::sensors::PixelFormat;
use thiserror::Error;

pub use crate::mode::Mode;

/// One frame as the device delivered it.
#[derive(Debug)]
pub struct RawFrame<'a> {
    /// The format of `bytes`.
    pub format: PixelFormat,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Bytes per row (packed formats).
    pub stride: u32,
    /// The device's frame sequence (a gap is a frame it dropped).
    pub sequence: u32,
    /// Capture time, ns on the common clock.
    pub capture_ns: u64,
    /// The pixels.
    pub bytes: &'a [u8],
}

/// A source that failed.
#[derive(Debug, Error)]
#[allow(missing_docs, reason = "each field is shown in its variant's message")]
pub enum SourceError {
    /// No device at the path.
    #[error("no camera at {0}")]
    Missing(PathBuf),
    /// The device cannot deliver the configured mode.
    #[error("{path}: the camera cannot deliver {wanted}: {detail}")]
    Mode {
        /// The device's path.
        path: PathBuf,
        /// The configured mode.
        wanted: String,
        /// What it offered or said.
        detail: String,
    },
    /// The device stopped delivering (unplugged, the simulator gone).
    #[error("{path}: {source}")]
    Io {
        /// The device's path.
        path: PathBuf,
        source: std::io::Error,
    },
    /// A frame of a format or size other than the configured one.
    #[error("{path}: a frame of {got}, the camera is set to {wanted}")]
    Unexpected {
        /// The device's path.
        path: PathBuf,
        /// The configured mode.
        wanted: String,
        /// What arrived.
        got: String,
    },
    /// V4L2 support is not built into this binary.
    #[error("{0}: a V4L2 device, and this build has no V4L2 support")]
    NoV4l2(PathBuf),
}

/// A camera delivering frames.
pub trait FrameSource {
    /// The next frame, waiting at most `timeout`; `Ok(None)` when none came in time.
    fn next_frame(&mut self, timeout: Duration) -> Result<Option<RawFrame<'_>>, SourceError>;
}

/// Opens the camera at `path` in `mode`: a Unix socket is the simulator's stream, anything else
/// a V4L2 device.
pub fn open(path: &Path, mode: Mode) -> Result<Box<dyn FrameSource>, SourceError> {
    let meta = std::fs::metadata(path).map_err(|_| SourceError::Missing(path.to_path_buf()))?;
    if meta.file_type().is_socket() {
        return Ok(Box::new(SocketSource::connect(path, mode)?));
    }
    #[cfg(feature = "process")]
    {
        Ok(Box::new(crate::v4l2::V4l2Source::open(path, mode)?))
    }
    #[cfg(not(feature = "process"))]
    {
        Err(SourceError::NoV4l2(path.to_path_buf()))
    }
}

/// The simulator's camera: frames on a Unix socket ([`crate::stream`]).
pub struct SocketSource {
    path: PathBuf,
    socket: UnixStream,
    reader: StreamReader,
    mode: Mode,
    chunk: Vec<u8>,
}

impl SocketSource {
    /// Connects to the socket at `path`.
    pub fn connect(path: &Path, mode: Mode) -> Result<Self, SourceError> {
        let socket = UnixStream::connect(path).map_err(|source| SourceError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Ok(SocketSource {
            path: path.to_path_buf(),
            socket,
            reader: StreamReader::new(mode.max_frame_bytes()),
            mode,
            chunk: vec![0; 256 * 1024],
        })
    }
}

impl FrameSource for SocketSource {
    fn next_frame(&mut self, timeout: Duration) -> Result<Option<RawFrame<'_>>, SourceError> {
        let io = |source| SourceError::Io {
            path: self.path.clone(),
            source,
        };
        let deadline = std::time::Instant::now() + timeout;
        // A frame already buffered is returned first; otherwise read until one is whole.
        while !self.reader.has_frame() {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            if left.is_zero() {
                return Ok(None);
            }
            self.socket.set_read_timeout(Some(left)).map_err(io)?;
            match self.socket.read(&mut self.chunk) {
                Ok(0) => {
                    return Err(io(std::io::Error::new(
                        std::io::ErrorKind::UnexpectedEof,
                        "the camera closed its stream",
                    )))
                }
                Ok(n) => self.reader.push(&self.chunk[..n]),
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) =>
                {
                    return Ok(None)
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(io(e)),
            }
        }
        let mode = self.mode;
        let path = self.path.clone();
        let Some((h, bytes)) = self.reader.next_frame() else {
            return Ok(None);
        };
        let format = h.format();
        if format != Some(mode.format) || (h.width, h.height) != (mode.width, mode.height) {
            return Err(SourceError::Unexpected {
                path,
                wanted: describe(mode.format, mode.width, mode.height),
                got: format!(
                    "{} {}×{}",
                    String::from_utf8_lossy(&h.fourcc),
                    h.width,
                    h.height
                ),
            });
        }
        Ok(Some(RawFrame {
            format: mode.format,
            width: h.width,
            height: h.height,
            stride: mode.format.stride(h.width).unwrap_or(0),
            sequence: h.sequence,
            capture_ns: h.capture_ns,
            bytes,
        }))
    }
}

/// "MJPG 1280×720".
pub fn describe(format: PixelFormat, width: u32, height: u32) -> String {
    format!(
        "{} {width}×{height}",
        String::from_utf8_lossy(&format.fourcc())
    )
}
