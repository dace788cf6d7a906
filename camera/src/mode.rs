//! What a camera is set to deliver, and the limits every camera of the stack keeps: the robot's
//! configuration and the simulator's cameras are checked by the same rules.

use telemetry::sensors::PixelFormat;

/// The largest image a camera may be set to: 1920×1080 (a frame's shared memory is sized by it).
pub const MAX_PIXELS: u32 = 1920 * 1080;

/// What a camera is set to deliver.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Mode {
    /// Pixel format asked of the device.
    pub format: PixelFormat,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Frames per second.
    pub fps: u32,
}

impl Mode {
    /// The largest buffer a frame of this mode can take: the RGB image (an MJPEG frame is
    /// bounded by the uncompressed size, as a UVC camera's buffers are sized).
    pub fn max_frame_bytes(&self) -> usize {
        crate::convert::rgb_len(self.width, self.height)
    }
}

/// The format a camera's configuration names: "mjpeg" or "yuyv" (what UVC cameras send).
pub fn format_named(name: &str) -> Option<PixelFormat> {
    match name {
        "mjpeg" => Some(PixelFormat::Mjpeg),
        "yuyv" => Some(PixelFormat::Yuyv),
        _ => None,
    }
}

/// Why a size or rate cannot be a camera's: `Err((key, reason))`.
pub fn check(width: u32, height: u32, fps: u32) -> Result<(), (&'static str, String)> {
    // YUYV packs two pixels in four bytes: an odd width has no whole last pair.
    if width < 16 || height < 16 || !width.is_multiple_of(2) {
        return Err((
            "width",
            format!("{width}×{height}: at least 16×16, even width"),
        ));
    }
    if width.saturating_mul(height) > MAX_PIXELS {
        return Err((
            "width",
            format!("{width}×{height} is larger than 1920×1080"),
        ));
    }
    if !(1..=120).contains(&fps) {
        return Err(("fps", format!("{fps}: 1 to 120")));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_and_rates_outside_a_camera_are_refused_by_key() {
        assert!(check(1280, 720, 30).is_ok());
        assert!(check(1920, 1080, 120).is_ok());
        assert_eq!(check(1281, 720, 30).unwrap_err().0, "width");
        assert_eq!(check(8, 720, 30).unwrap_err().0, "width");
        assert_eq!(check(1920, 1082, 30).unwrap_err().0, "width");
        assert_eq!(check(1280, 720, 0).unwrap_err().0, "fps");
        assert_eq!(check(1280, 720, 121).unwrap_err().0, "fps");
        assert_eq!(format_named("yuyv"), Some(PixelFormat::Yuyv));
        assert_eq!(format_named("h264"), None);
    }
}
