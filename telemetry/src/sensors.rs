//! Frames of the sensor plane: camera images (a header beside a byte slice, zero-copy) and lidar
//! scans (one fixed-size frame per revolution).
//!
//! As with the joint frames, type name, size and alignment are part of a service's identity: a
//! layout change bumps the version in the type name.

use crate::frames::{name_bytes, name_text, NAME_LEN};
use iceoryx2::prelude::ZeroCopySend;

/// Whether `name` can name a camera: 1 to [`NAME_LEN`] of a-z, 0-9 and _ (it names a plane
/// service and a dataset key, and fits the frame header).
pub fn valid_camera_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= NAME_LEN
        && name
            .bytes()
            .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_')
}

/// Pixel layouts a camera frame can carry, as V4L2 four-character codes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelFormat {
    /// 8-bit R, G, B per pixel, rows top to bottom (V4L2 `RGB3`).
    Rgb24,
    /// Packed 4:2:2 Y0 U Y1 V (V4L2 `YUYV`), what UVC cameras send uncompressed.
    Yuyv,
    /// One JPEG image per frame (V4L2 `MJPG`), what UVC cameras send at 720p30.
    Mjpeg,
}

impl PixelFormat {
    /// The V4L2 four-character code.
    pub const fn fourcc(self) -> [u8; 4] {
        match self {
            PixelFormat::Rgb24 => *b"RGB3",
            PixelFormat::Yuyv => *b"YUYV",
            PixelFormat::Mjpeg => *b"MJPG",
        }
    }

    /// The format of a four-character code.
    pub fn from_fourcc(code: [u8; 4]) -> Option<Self> {
        [PixelFormat::Rgb24, PixelFormat::Yuyv, PixelFormat::Mjpeg]
            .into_iter()
            .find(|f| f.fourcc() == code)
    }

    /// Bytes of one row of `width` pixels (`None` for a compressed format).
    pub const fn stride(self, width: u32) -> Option<u32> {
        match self {
            PixelFormat::Rgb24 => Some(width * 3),
            PixelFormat::Yuyv => Some(width * 2),
            PixelFormat::Mjpeg => None,
        }
    }
}

/// The header of one camera frame; its pixels follow as the sample's byte slice.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("nori::CameraFrameHeader/2")]
pub struct CameraFrameHeader {
    /// Frames published by this camera process, from 0.
    pub seq: u64,
    /// When the image was captured (the device's timestamp), on the common clock
    /// ([`crate::clock::monotonic_ns`]): what recordings align joint frames with.
    pub capture_ns: u64,
    /// When it was published: `publish_ns − capture_ns` is the camera process's own latency.
    pub publish_ns: u64,
    /// Camera name, UTF-8, zero-padded.
    pub camera: [u8; NAME_LEN],
    /// V4L2 four-character code of the pixels ([`PixelFormat::fourcc`]).
    pub fourcc: [u8; 4],
    /// Pixels per row.
    pub width: u32,
    /// Rows (the height in pixels).
    pub height: u32,
    /// Bytes per row in the slice.
    pub stride: u32,
    /// Frames the device or this process lost so far (sequence gaps, a reader too slow).
    pub dropped: u32,
    /// Frames refused so far as corrupt (a JPEG that does not decode, a short buffer).
    pub corrupt: u32,
    /// Frames so far published more than two frame periods after their capture.
    pub late: u32,
    /// Zero: the padding to the frame's 8-byte alignment, made a field so that every byte of the
    /// shared frame is defined.
    pub reserved: u32,
}

impl CameraFrameHeader {
    /// The camera's name.
    pub fn camera(&self) -> &str {
        name_text(&self.camera)
    }

    /// Sets the camera's name, truncated to [`NAME_LEN`] bytes at a character boundary.
    pub fn set_camera(&mut self, name: &str) {
        self.camera = name_bytes(name);
    }

    /// The pixel format, if known.
    pub fn format(&self) -> Option<PixelFormat> {
        PixelFormat::from_fourcc(self.fourcc)
    }

    /// Bytes the slice must hold for this header's format and size (`None` if compressed or
    /// unknown).
    pub fn image_len(&self) -> Option<usize> {
        let stride = self.format()?.stride(self.width)?;
        (self.stride >= stride).then(|| self.stride as usize * self.height as usize)
    }
}

/// Points a scan frame can carry: an RPLIDAR C1 samples 5 kHz, so 625 points a revolution at
/// its slowest 8 Hz; the rest is margin.
pub const MAX_SCAN_POINTS: usize = 1024;

/// One measurement of a scan.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
pub struct ScanPoint {
    /// Bearing in the lidar's frame, rad, counter-clockwise from its forward axis, [0, 2π).
    pub angle_rad: f32,
    /// Range, m; 0 when the device saw no return.
    pub range_m: f32,
    /// The device's signal quality, 0..63 (0: no return).
    pub quality: u8,
    /// Zero: the padding to the point's 4-byte alignment, made a field so that every byte of the
    /// shared frame is defined.
    pub reserved: [u8; 3],
}

/// One revolution of the lidar.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("nori::LidarScan/1")]
pub struct LidarScan {
    /// Scans published by this lidar process, from 0.
    pub seq: u64,
    /// When the revolution's first point arrived, on the common clock.
    pub start_ns: u64,
    /// When its last point arrived.
    pub end_ns: u64,
    /// Points in use.
    pub point_count: u32,
    /// Measurements dropped so far as unconfirmed: next to a place where the byte stream lost
    /// its alignment (broken check bits, bytes lost or inserted), where their own bytes
    /// cannot be trusted.
    pub bad_points: u32,
    /// Times so far the reader lost the byte stream and searched for the next measurement.
    pub resyncs: u32,
    /// Revolutions dropped so far as incomplete (fewer points than a revolution holds).
    pub short_scans: u32,
    /// The points, in the order measured.
    pub points: [ScanPoint; MAX_SCAN_POINTS],
}

impl Default for LidarScan {
    fn default() -> Self {
        LidarScan {
            seq: 0,
            start_ns: 0,
            end_ns: 0,
            point_count: 0,
            bad_points: 0,
            resyncs: 0,
            short_scans: 0,
            points: [ScanPoint::default(); MAX_SCAN_POINTS],
        }
    }
}

impl LidarScan {
    /// The points in use.
    pub fn points(&self) -> &[ScanPoint] {
        &self.points[..(self.point_count as usize).min(MAX_SCAN_POINTS)]
    }

    /// Revolutions per second this scan implies (points over its duration), if it has any.
    pub fn rotation_hz(&self) -> Option<f64> {
        let span = self.end_ns.checked_sub(self.start_ns)?;
        (span > 0).then(|| 1e9 / span as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sensor_layouts_are_stable() {
        // A change here changes the service identity: bump the version in the type name.
        assert_eq!(std::mem::size_of::<CameraFrameHeader>(), 24 + NAME_LEN + 32);
        assert_eq!(std::mem::size_of::<ScanPoint>(), 12);
        assert_eq!(std::mem::size_of::<LidarScan>(), 40 + 12 * MAX_SCAN_POINTS);
    }

    #[test]
    fn formats_round_trip_their_codes_and_know_their_rows() {
        for f in [PixelFormat::Rgb24, PixelFormat::Yuyv, PixelFormat::Mjpeg] {
            assert_eq!(PixelFormat::from_fourcc(f.fourcc()), Some(f));
        }
        assert_eq!(PixelFormat::from_fourcc(*b"NV12"), None);
        assert_eq!(PixelFormat::Rgb24.stride(1280), Some(3840));
        assert_eq!(PixelFormat::Yuyv.stride(1280), Some(2560));
        assert_eq!(PixelFormat::Mjpeg.stride(1280), None);
    }

    #[test]
    fn a_header_sizes_its_image_and_refuses_a_short_stride() {
        let mut h = CameraFrameHeader {
            fourcc: PixelFormat::Rgb24.fourcc(),
            width: 1280,
            height: 720,
            stride: 3840,
            ..Default::default()
        };
        h.set_camera("head");
        assert_eq!(h.camera(), "head");
        assert_eq!(h.image_len(), Some(2_764_800));
        h.stride = 3848; // padded rows
        assert_eq!(h.image_len(), Some(3848 * 720));
        h.stride = 3000;
        assert_eq!(h.image_len(), None);
        h.fourcc = PixelFormat::Mjpeg.fourcc();
        assert_eq!(h.image_len(), None);
    }

    #[test]
    fn a_scan_knows_its_points_and_rate() {
        let mut s = LidarScan {
            point_count: 3,
            start_ns: 1_000_000_000,
            end_ns: 1_100_000_000,
            ..Default::default()
        };
        s.points[2].range_m = 4.0;
        assert_eq!(s.points().len(), 3);
        assert_eq!(s.points()[2].range_m, 4.0);
        assert!((s.rotation_hz().unwrap() - 10.0).abs() < 1e-9);
        s.point_count = u32::MAX;
        assert_eq!(s.points().len(), MAX_SCAN_POINTS);
        s.end_ns = s.start_ns;
        assert_eq!(s.rotation_hz(), None);
    }
}
