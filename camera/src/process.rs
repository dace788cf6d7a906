//! The camera process's loop: frames from the device, converted straight into the plane's shared
//! memory, each counted as published, corrupt, dropped or late. A bad frame is refused, counted
//! and logged (the first, then at each doubling of the count); it never stops the loop. A camera
//! that delivers MJPEG also has each published frame's JPEG, untouched, on its second stream
//! (what a recording stores without encoding again).

use crate::convert::{rgb_len, to_rgb};
use crate::source::{FrameSource, Mode, RawFrame, SourceError};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use telemetry::plane::{publish_frame, FramePub, PlaneError};
use telemetry::sensors::{CameraFrameHeader, PixelFormat};

/// What the process did, reported at exit.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct Counters {
    /// Frames the device delivered.
    pub captured: u64,
    /// Frames published on the plane.
    pub published: u64,
    /// Frames refused as corrupt (did not decode, cut short).
    pub corrupt: u64,
    /// Frames the device skipped (gaps in its sequence).
    pub dropped: u64,
    /// Frames published more than two frame periods after their capture.
    pub late: u64,
    /// JPEGs published on the MJPEG stream.
    pub jpegs_published: u64,
    /// JPEGs too large for the MJPEG stream's samples (their RGB frame was published).
    pub jpegs_oversized: u64,
    /// Waits of a second with no frame.
    pub silences: u64,
    /// Times the device was lost and opened again.
    pub reconnects: u64,
}

/// One camera's publishing state.
pub struct Camera {
    name: String,
    mode: Mode,
    publisher: FramePub,
    /// The MJPEG stream, for a camera that delivers MJPEG.
    jpegs: Option<FramePub>,
    last_sequence: Option<u32>,
    /// What happened so far.
    pub counters: Counters,
}

impl Camera {
    /// A camera publishing on `publisher` (made with at least [`rgb_len`] bytes per frame) and,
    /// for an MJPEG camera, its JPEGs on `jpegs` (made with [`jpeg_max_len`] bytes).
    pub fn new(name: &str, mode: Mode, publisher: FramePub, jpegs: Option<FramePub>) -> Self {
        Camera {
            name: name.into(),
            mode,
            publisher,
            jpegs,
            last_sequence: None,
            counters: Counters::default(),
        }
    }

    /// Publishes one delivered frame at `now_ns` (common clock); returns whether it was.
    pub fn handle(&mut self, frame: &RawFrame<'_>, now_ns: u64) -> Result<bool, PlaneError> {
        let c = &mut self.counters;
        c.captured += 1;
        if let Some(last) = self.last_sequence {
            // A device that restarted its count (reopened) is not a gap.
            let gap = frame.sequence.wrapping_sub(last).wrapping_sub(1);
            if gap < 1_000 {
                c.dropped += u64::from(gap);
            }
        }
        self.last_sequence = Some(frame.sequence);
        let (width, height) = (self.mode.width, self.mode.height);
        let mut header = CameraFrameHeader {
            seq: c.published,
            capture_ns: frame.capture_ns,
            publish_ns: now_ns,
            fourcc: PixelFormat::Rgb24.fourcc(),
            width,
            height,
            stride: width * 3,
            dropped: c.dropped.min(u64::from(u32::MAX)) as u32,
            corrupt: c.corrupt.min(u64::from(u32::MAX)) as u32,
            late: c.late.min(u64::from(u32::MAX)) as u32,
            ..CameraFrameHeader::default()
        };
        header.set_camera(&self.name);
        let mut refused = None;
        let sent =
            publish_frame(
                &self.publisher,
                &header,
                rgb_len(width, height),
                |out| match to_rgb(
                    frame.format,
                    frame.width,
                    frame.height,
                    frame.stride,
                    frame.bytes,
                    out,
                ) {
                    Ok(()) => true,
                    Err(e) => {
                        refused = Some(e);
                        false
                    }
                },
            )?;
        let c = &mut self.counters;
        if let Some(e) = refused {
            c.corrupt += 1;
            if c.corrupt.is_power_of_two() {
                tracing::warn!(
                    camera = %self.name,
                    corrupt = c.corrupt,
                    "frame {} refused: {e}",
                    frame.sequence
                );
            }
            return Ok(false);
        }
        c.published += 1;
        if let (Some(jpegs), PixelFormat::Mjpeg) = (&self.jpegs, frame.format) {
            if frame.bytes.len() <= jpeg_max_len(width, height) {
                let mut h = header;
                (h.fourcc, h.stride) = (PixelFormat::Mjpeg.fourcc(), 0);
                publish_frame(jpegs, &h, frame.bytes.len(), |out| {
                    out.copy_from_slice(frame.bytes);
                    true
                })?;
                c.jpegs_published += 1;
            } else {
                c.jpegs_oversized += 1;
            }
        }
        let period_ns = 1_000_000_000 / u64::from(self.mode.fps.max(1));
        if now_ns.saturating_sub(frame.capture_ns) > 2 * period_ns {
            c.late += 1;
        }
        Ok(sent)
    }
}

/// The largest JPEG the MJPEG stream carries for a `width`×`height` camera: a quarter of the
/// RGB image (UVC cameras' 720p JPEGs are 50-300 KB of its 2.7 MB).
pub fn jpeg_max_len(width: u32, height: u32) -> usize {
    rgb_len(width, height) / 4
}

/// Why the loop stopped for good.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The device is not there, or cannot deliver the configured mode: restarting will not
    /// help until someone plugs it in or fixes the configuration.
    #[error(transparent)]
    Source(#[from] SourceError),
    /// The plane refused a frame.
    #[error(transparent)]
    Plane(#[from] PlaneError),
}

/// Runs `camera` from the device at `device` until `stop` (or `run_for`): a device lost while
/// running is opened again every second, as a USB camera re-enumerates.
pub fn run(
    camera: &mut Camera,
    device: &Path,
    open: impl Fn(&Path, Mode) -> Result<Box<dyn FrameSource>, SourceError>,
    stop: &AtomicBool,
    run_for: Option<Duration>,
) -> Result<(), RunError> {
    let started = Instant::now();
    let running = || !stop.load(Ordering::Relaxed) && run_for.is_none_or(|t| started.elapsed() < t);
    let mut source = open(device, camera.mode)?;
    tracing::info!(camera = %camera.name, "streaming from {}", device.display());
    while running() {
        match source.next_frame(Duration::from_secs(1)) {
            Ok(Some(frame)) => {
                camera.handle(&frame, telemetry::clock::monotonic_ns())?;
            }
            Ok(None) => {
                camera.counters.silences += 1;
                tracing::warn!(camera = %camera.name, "no frame for a second");
            }
            Err(e @ (SourceError::Mode { .. } | SourceError::Unexpected { .. })) => {
                return Err(e.into())
            }
            Err(e) => {
                tracing::warn!(camera = %camera.name, "{e}; opening it again");
                source = loop {
                    if !running() {
                        return Ok(());
                    }
                    std::thread::sleep(Duration::from_secs(1));
                    match open(device, camera.mode) {
                        Ok(s) => break s,
                        Err(e @ SourceError::Mode { .. }) => return Err(e.into()),
                        Err(_) => {}
                    }
                };
                camera.counters.reconnects += 1;
                tracing::info!(camera = %camera.name, "streaming again");
            }
        }
    }
    Ok(())
}
