//! The fleet's view of the robot's eyes: a small JPEG of a camera's picture now and then
//! (`nori/<id>/preview`) and the lidar's revolution (`nori/<id>/scan`), for the dashboard, not
//! for policies (those take the camera's own JPEG in their observations).
//!
//! The thumbnail is made on the robot (`camera::thumbnail`: about 3 KB where the camera's own
//! JPEG is 30-300 KB, so four cameras of 800 robots stay a few MB/s at the fleet). Pure: frames
//! in, messages out.

use crate::schema::{PreviewMsg, ScanMsg, SCHEMA_VERSION};
use telemetry::sensors::{CameraFrameHeader, LidarScan};

/// The preview message of a thumbnail of the frame `header` describes.
pub fn preview_msg(
    header: &CameraFrameHeader,
    jpeg: &[u8],
    width: u32,
    height: u32,
    wall_ms: u64,
) -> PreviewMsg {
    PreviewMsg {
        version: SCHEMA_VERSION,
        camera: header.camera().to_string(),
        seq: header.seq,
        capture_ns: header.capture_ns,
        wall_ms,
        width,
        height,
        source_width: header.width,
        source_height: header.height,
        encoding: "jpeg".into(),
        data: jpeg.to_vec(),
    }
}

/// The scan message of one revolution: every point measured, in order, with its range (0: no
/// return).
pub fn scan_msg(scan: &LidarScan, wall_ms: u64) -> ScanMsg {
    let points = scan.points();
    ScanMsg {
        version: SCHEMA_VERSION,
        seq: scan.seq,
        start_ns: scan.start_ns,
        end_ns: scan.end_ns,
        wall_ms,
        angle_rad: points.iter().map(|p| p.angle_rad).collect(),
        range_m: points.iter().map(|p| p.range_m).collect(),
        quality: points.iter().map(|p| p.quality).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use telemetry::sensors::ScanPoint;

    #[test]
    fn a_scan_message_keeps_every_point_in_order() {
        let mut scan = LidarScan {
            seq: 4,
            start_ns: 10,
            end_ns: 100_000_010,
            point_count: 3,
            ..Default::default()
        };
        for (i, p) in scan.points.iter_mut().take(3).enumerate() {
            *p = ScanPoint {
                angle_rad: i as f32,
                range_m: if i == 1 { 0.0 } else { 2.0 + i as f32 },
                quality: 40,
                reserved: [0; 3],
            };
        }
        let m = scan_msg(&scan, 5);
        assert_eq!(m.angle_rad, vec![0.0, 1.0, 2.0]);
        assert_eq!(m.range_m, vec![2.0, 0.0, 4.0]);
        assert_eq!(m.quality, vec![40; 3]);
        assert_eq!(
            (m.seq, m.start_ns, m.end_ns, m.wall_ms),
            (4, 10, 100_000_010, 5)
        );
    }
}
