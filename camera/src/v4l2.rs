//! The robot's cameras: UVC devices through V4L2 (memory-mapped buffers, the driver's own
//! capture timestamps). What can be decided without a device (whether what the device granted
//! is what was configured, its timestamps on the common clock) is pure and tested here; the
//! rest needs a camera, which this machine does not have.

use crate::source::{describe, FrameSource, Mode, RawFrame, SourceError};
use std::path::{Path, PathBuf};
use std::time::Duration;
use telemetry::sensors::PixelFormat;
use v4l::buffer::{Flags, Type};
use v4l::io::mmap::Stream;
use v4l::io::traits::CaptureStream;
use v4l::video::Capture;
use v4l::{Device, FourCC};

/// Buffers queued in the driver: enough to ride out a late reader for a frame or two, few
/// enough that a frame is never more than ~100 ms old at 30 fps.
const BUFFERS: u32 = 3;

/// What the device granted against what was asked: V4L2's `S_FMT` answers with the nearest mode
/// it has, not an error, so a camera that cannot do 720p MJPEG would otherwise silently deliver
/// something else.
pub fn check_granted(
    wanted: Mode,
    format: [u8; 4],
    width: u32,
    height: u32,
    fps: Option<(u32, u32)>,
) -> Result<(), String> {
    let got_format = PixelFormat::from_fourcc(format);
    if got_format != Some(wanted.format) || (width, height) != (wanted.width, wanted.height) {
        return Err(format!(
            "it offers {} {width}×{height} instead",
            String::from_utf8_lossy(&format)
        ));
    }
    if let Some((num, denom)) = fps {
        // The frame interval num/denom s; a camera may round 30 to 30000/1001.
        let got = f64::from(denom) / f64::from(num.max(1));
        if (got - f64::from(wanted.fps)).abs() > 0.5 {
            return Err(format!("it runs at {got:.2} fps"));
        }
    }
    Ok(())
}

/// A buffer's capture time on the common clock, if the driver stamped it with CLOCK_MONOTONIC
/// (UVC does); otherwise `None` and the reader stamps the frame when it dequeues it.
pub fn capture_ns(flags_bits: u32, sec: i64, usec: i64) -> Option<u64> {
    let clock = flags_bits & Flags::TIMESTAMP_MASK.bits();
    if clock != Flags::TIMESTAMP_MONOTONIC.bits() || sec < 0 || usec < 0 {
        return None;
    }
    Some(sec as u64 * 1_000_000_000 + usec as u64 * 1_000)
}

/// A V4L2 capture device streaming memory-mapped buffers.
pub struct V4l2Source {
    path: PathBuf,
    mode: Mode,
    stride: u32,
    // The stream holds the device's handle; the device is kept for its lifetime.
    stream: Stream<'static>,
    _device: Device,
}

impl V4l2Source {
    /// Opens `path` and sets it to `mode`, or says what it offers instead.
    pub fn open(path: &Path, mode: Mode) -> Result<Self, SourceError> {
        let io = |source| SourceError::Io {
            path: path.to_path_buf(),
            source,
        };
        let device = Device::with_path(path).map_err(io)?;
        let mut format = device.format().map_err(io)?;
        format.width = mode.width;
        format.height = mode.height;
        format.fourcc = FourCC::new(&mode.format.fourcc());
        let granted = device.set_format(&format).map_err(io)?;
        let params = device
            .set_params(&v4l::video::capture::Parameters::with_fps(mode.fps))
            .map_err(io)?;
        let interval = (params.interval.numerator, params.interval.denominator);
        check_granted(
            mode,
            granted.fourcc.repr,
            granted.width,
            granted.height,
            Some(interval),
        )
        .map_err(|detail| SourceError::Mode {
            path: path.to_path_buf(),
            wanted: format!(
                "{} at {} fps",
                describe(mode.format, mode.width, mode.height),
                mode.fps
            ),
            detail,
        })?;
        let mut stream = Stream::with_buffers(&device, Type::VideoCapture, BUFFERS).map_err(io)?;
        stream.set_timeout(Duration::from_millis(200));
        Ok(V4l2Source {
            path: path.to_path_buf(),
            mode,
            stride: granted.stride,
            stream,
            _device: device,
        })
    }
}

impl FrameSource for V4l2Source {
    fn next_frame(&mut self, timeout: Duration) -> Result<Option<RawFrame<'_>>, SourceError> {
        self.stream.set_timeout(timeout);
        let (bytes, meta) = match CaptureStream::next(&mut self.stream) {
            Ok(x) => x,
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => return Ok(None),
            Err(source) => {
                return Err(SourceError::Io {
                    path: self.path.clone(),
                    source,
                })
            }
        };
        let used = (meta.bytesused as usize).min(bytes.len());
        let capture_ns = capture_ns(meta.flags.bits(), meta.timestamp.sec, meta.timestamp.usec)
            .unwrap_or_else(telemetry::clock::monotonic_ns);
        Ok(Some(RawFrame {
            format: self.mode.format,
            width: self.mode.width,
            height: self.mode.height,
            stride: self.stride,
            sequence: meta.sequence,
            capture_ns,
            bytes: &bytes[..used],
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HD_MJPEG: Mode = Mode {
        format: PixelFormat::Mjpeg,
        width: 1280,
        height: 720,
        fps: 30,
    };

    #[test]
    fn a_granted_mode_must_be_the_configured_one() {
        assert!(check_granted(HD_MJPEG, *b"MJPG", 1280, 720, Some((1, 30))).is_ok());
        // NTSC-style rounding is the same rate.
        assert!(check_granted(HD_MJPEG, *b"MJPG", 1280, 720, Some((1001, 30000))).is_ok());
        let smaller = check_granted(HD_MJPEG, *b"MJPG", 640, 480, None).unwrap_err();
        assert_eq!(smaller, "it offers MJPG 640×480 instead");
        let yuyv = check_granted(HD_MJPEG, *b"YUYV", 1280, 720, None).unwrap_err();
        assert!(yuyv.contains("YUYV"), "{yuyv}");
        let slow = check_granted(HD_MJPEG, *b"MJPG", 1280, 720, Some((1, 10))).unwrap_err();
        assert_eq!(slow, "it runs at 10.00 fps");
    }

    #[test]
    fn only_monotonic_timestamps_are_taken_as_capture_times() {
        assert_eq!(capture_ns(0x2000, 12, 345_678), Some(12_345_678_000));
        assert_eq!(capture_ns(0x2000 | 0x1, 1, 0), Some(1_000_000_000));
        assert_eq!(capture_ns(0x0000, 12, 0), None, "unknown clock");
        assert_eq!(capture_ns(0x4000, 12, 0), None, "copied from elsewhere");
        assert_eq!(capture_ns(0x2000, -1, 0), None);
    }

    #[test]
    fn a_missing_device_is_a_clear_error() {
        let err = crate::source::open(Path::new("/dev/nori/no-such-camera"), HD_MJPEG)
            .err()
            .unwrap();
        assert_eq!(err.to_string(), "no camera at /dev/nori/no-such-camera");
    }
}
