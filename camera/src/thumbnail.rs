//! Thumbnails of a camera's picture: the RGB frame on the state plane averaged down by an
//! integer factor, read once with no full-size copy and no JPEG decoded, then a small JPEG (a
//! 160×90 thumbnail of a 720p frame is about 3 KB where the camera's own JPEG is 30-300 KB).
//! The fleet's dashboard previews and the black box's `/camera/<name>/thumbnail` are both made
//! here. Pure: frames in, bytes out; the buffers are reused.

use crate::mode::MAX_PIXELS;
use telemetry::sensors::{CameraFrameHeader, PixelFormat};
use thiserror::Error;

/// Why a frame gave no thumbnail.
#[derive(Debug, Error, PartialEq)]
pub enum ThumbnailError {
    /// The plane's camera frames are RGB24; anything else is a camera process of another build.
    #[error("camera {camera}: frame format {fourcc:?} is not RGB24")]
    NotRgb {
        /// The camera.
        camera: String,
        /// The header's four-character code.
        fourcc: String,
    },
    /// The header promises more pixels than the slice holds, or a size of zero.
    #[error("camera {camera}: a {width}×{height} frame (stride {stride}) needs {need} bytes, the slice has {have}")]
    Size {
        /// The camera.
        camera: String,
        /// Pixels per row.
        width: u32,
        /// Rows (the height in pixels).
        height: u32,
        /// Bytes per row.
        stride: u32,
        /// Bytes the header implies.
        need: usize,
        /// Bytes in the slice.
        have: usize,
    },
    /// A shape no camera delivers (beyond [`MAX_PIXELS`], or a side a JPEG cannot hold): a
    /// header that lies, refused before a thumbnail of it is made.
    #[error(
        "camera {camera}: a {width}×{height} frame is no camera's (at most {MAX_PIXELS} pixels)"
    )]
    Shape {
        /// The camera.
        camera: String,
        /// Pixels per row.
        width: u32,
        /// Rows of pixels.
        height: u32,
    },
    /// The JPEG encoder refused the picture.
    #[error("camera {camera}: JPEG encoding: {reason}")]
    Encode {
        /// The camera.
        camera: String,
        /// The encoder's words.
        reason: String,
    },
}

/// Makes thumbnails at most `width` pixels wide, reusing its buffers.
#[derive(Debug)]
pub struct Thumbnailer {
    width: u32,
    quality: u8,
    sums: Vec<u32>,
    small: Vec<u8>,
    jpeg: Vec<u8>,
}

impl Thumbnailer {
    /// Thumbnails at most `width` pixels wide (the frame's own width if smaller), JPEG
    /// `quality` (1-100).
    pub fn new(width: u32, quality: u8) -> Thumbnailer {
        Thumbnailer {
            width: width.max(1),
            quality: quality.clamp(1, 100),
            sums: Vec::new(),
            small: Vec::new(),
            jpeg: Vec::new(),
        }
    }

    /// Averages `pixels` (the frame `header` describes) down by the smallest integer factor
    /// that fits the width, and encodes the result; the JPEG and its size. Integer factors keep
    /// every output pixel the mean of whole source pixels, so the thumbnail is the picture,
    /// not an aliased sample of it.
    pub fn make(
        &mut self,
        header: &CameraFrameHeader,
        pixels: &[u8],
    ) -> Result<(&[u8], u32, u32), ThumbnailError> {
        let camera = header.camera().to_string();
        if header.format() != Some(PixelFormat::Rgb24) {
            return Err(ThumbnailError::NotRgb {
                camera,
                fourcc: String::from_utf8_lossy(&header.fourcc).into_owned(),
            });
        }
        let (w, h, stride) = (header.width, header.height, header.stride as usize);
        // A stride shorter than a row of pixels is as short as no bytes at all.
        let need = header
            .image_len()
            .unwrap_or(w as usize * 3 * h as usize + 1);
        if w == 0 || h == 0 || pixels.len() < need {
            return Err(ThumbnailError::Size {
                camera,
                width: w,
                height: h,
                stride: header.stride,
                need,
                have: pixels.len(),
            });
        }
        let factor = w.div_ceil(self.width).max(1);
        let (sw, sh) = ((w / factor).max(1), (h / factor).max(1));
        if w.saturating_mul(h) > MAX_PIXELS || sh > u32::from(u16::MAX) {
            return Err(ThumbnailError::Shape {
                camera,
                width: w,
                height: h,
            });
        }
        let (f, swu) = (factor as usize, sw as usize);
        self.sums.clear();
        self.sums.resize(swu * 3, 0);
        self.small.clear();
        for row in 0..sh as usize {
            self.sums.fill(0);
            for y in row * f..(row + 1) * f {
                let line = &pixels[y * stride..y * stride + swu * f * 3];
                for (x, px) in line.chunks_exact(3).enumerate() {
                    let s = &mut self.sums[(x / f) * 3..(x / f) * 3 + 3];
                    s[0] += u32::from(px[0]);
                    s[1] += u32::from(px[1]);
                    s[2] += u32::from(px[2]);
                }
            }
            let n = factor * factor;
            // Rounded to nearest: a uniform picture stays its colour exactly.
            self.small
                .extend(self.sums.iter().map(|&s| ((s + n / 2) / n) as u8));
        }
        self.jpeg.clear();
        jpeg_encoder::Encoder::new(&mut self.jpeg, self.quality)
            .encode(
                &self.small,
                sw as u16,
                sh as u16,
                jpeg_encoder::ColorType::Rgb,
            )
            .map_err(|e| ThumbnailError::Encode {
                camera,
                reason: e.to_string(),
            })?;
        Ok((&self.jpeg, sw, sh))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(w: u32, h: u32, stride: u32) -> CameraFrameHeader {
        let mut hd = CameraFrameHeader {
            seq: 7,
            capture_ns: 11,
            fourcc: PixelFormat::Rgb24.fourcc(),
            width: w,
            height: h,
            stride,
            ..Default::default()
        };
        hd.set_camera("head");
        hd
    }

    fn decode(jpeg: &[u8]) -> (Vec<u8>, usize, usize) {
        let mut d = zune_jpeg::JpegDecoder::new(zune_core::bytestream::ZCursor::new(jpeg));
        let rgb = d.decode().unwrap();
        let (w, h) = d.dimensions().unwrap();
        (rgb, w, h)
    }

    #[test]
    fn a_thumbnail_is_the_box_average_of_the_picture() {
        // 1280×720 with a padded stride: left half red, right half a blue ramp down the rows.
        let (w, h, stride) = (1280u32, 720u32, 1280 * 3 + 12);
        let mut px = vec![0u8; stride as usize * h as usize];
        for y in 0..h as usize {
            for x in 0..w as usize {
                let p = &mut px[y * stride as usize + x * 3..][..3];
                if x < 640 {
                    p.copy_from_slice(&[200, 0, 0]);
                } else {
                    p.copy_from_slice(&[0, 0, (y * 255 / 719) as u8]);
                }
            }
        }
        let mut t = Thumbnailer::new(160, 90);
        let (jpeg, tw, th) = t.make(&header(w, h, stride), &px).unwrap();
        assert_eq!((tw, th), (160, 90), "720p by 8");
        assert!(jpeg.len() < 8_000, "{} bytes", jpeg.len());
        let (rgb, dw, dh) = decode(jpeg);
        assert_eq!((dw, dh), (160, 90));
        let at = |x: usize, y: usize| &rgb[(y * 160 + x) * 3..][..3];
        // Away from the edge (JPEG blurs it): red on the left, the ramp's block mean on the right.
        for y in [5, 45, 84] {
            let red = at(40, y);
            assert!(
                red[0].abs_diff(200) <= 6 && red[1] <= 8 && red[2] <= 8,
                "{red:?}"
            );
            let blue = at(120, y);
            let expected = (y * 8..y * 8 + 8).map(|r| r * 255 / 719).sum::<usize>() / 8;
            assert!(
                usize::from(blue[2]).abs_diff(expected) <= 6,
                "row {y}: {blue:?}, expected blue {expected}"
            );
        }
    }

    #[test]
    fn a_small_frame_keeps_its_size_and_bad_frames_are_refused_by_name() {
        let mut t = Thumbnailer::new(160, 80);
        let px = vec![90u8; 64 * 48 * 3];
        let (_, tw, th) = t.make(&header(64, 48, 64 * 3), &px).unwrap();
        assert_eq!((tw, th), (64, 48));
        let err = t.make(&header(64, 48, 64 * 3), &px[..100]).unwrap_err();
        assert!(
            matches!(
                err,
                ThumbnailError::Size {
                    need: 9216,
                    have: 100,
                    ..
                }
            ),
            "{err}"
        );
        assert!(err.to_string().starts_with("camera head: a 64×48 frame"));
        let mut yuyv = header(64, 48, 128);
        yuyv.fourcc = PixelFormat::Yuyv.fourcc();
        assert_eq!(
            t.make(&yuyv, &px).unwrap_err(),
            ThumbnailError::NotRgb {
                camera: "head".into(),
                fourcc: "YUYV".into()
            }
        );
        assert!(matches!(
            t.make(&header(0, 48, 0), &px),
            Err(ThumbnailError::Size { .. })
        ));
        // A header whose shape fits the slice but no camera: refused, not a cropped JPEG.
        let tall = vec![0u8; 24 * 115_200];
        assert!(matches!(
            t.make(&header(8, 115_200, 24), &tall),
            Err(ThumbnailError::Shape {
                width: 8,
                height: 115_200,
                ..
            })
        ));
        let thin = vec![0u8; 3 * 1_000_000];
        assert!(matches!(
            t.make(&header(1, 1_000_000, 3), &thin),
            Err(ThumbnailError::Shape { .. })
        ));
    }
}
