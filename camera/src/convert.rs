//! What a camera delivers, turned into the RGB24 the plane carries: packed YUYV converted,
//! MJPEG decoded. Each check that a frame is whole happens here, before a pixel is written to
//! the plane, so a corrupt frame is refused (and counted by the caller), never half-published.

use telemetry::sensors::PixelFormat;
use thiserror::Error;
use zune_core::bytestream::ZCursor;
use zune_core::colorspace::ColorSpace;
use zune_core::options::DecoderOptions;
use zune_jpeg::JpegDecoder;

/// Why a delivered frame cannot become an image.
#[derive(Debug, Error, PartialEq)]
pub enum FrameError {
    /// The buffer is shorter than the format and size need (a frame cut short).
    #[error("{format:?} {width}×{height} needs {needed} bytes, the frame has {got}")]
    Short {
        /// The format.
        format: PixelFormat,
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// Bytes needed.
        needed: usize,
        /// Bytes delivered.
        got: usize,
    },
    /// The JPEG does not decode.
    #[error("corrupt JPEG: {0}")]
    Jpeg(String),
    /// The JPEG decodes to another size than the camera was set to.
    #[error("JPEG of {got_width}×{got_height}, the camera is set to {width}×{height}")]
    JpegSize {
        /// Configured width.
        width: u32,
        /// Configured height.
        height: u32,
        /// Decoded width.
        got_width: u32,
        /// Decoded height.
        got_height: u32,
    },
    /// The output buffer does not fit width × height × 3.
    #[error("output of {got} bytes for a {width}×{height} RGB image")]
    Output {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// Bytes of the output.
        got: usize,
    },
    /// A format this stack does not convert.
    #[error("pixel format {0:?} is not converted to RGB")]
    Unsupported(PixelFormat),
}

/// Bytes of an RGB24 image.
pub fn rgb_len(width: u32, height: u32) -> usize {
    width as usize * height as usize * 3
}

/// Converts one delivered frame (`format`, `width` × `height`, rows `stride` bytes apart for the
/// packed formats) into tightly packed RGB24 in `out` (exactly [`rgb_len`] bytes).
pub fn to_rgb(
    format: PixelFormat,
    width: u32,
    height: u32,
    stride: u32,
    frame: &[u8],
    out: &mut [u8],
) -> Result<(), FrameError> {
    if out.len() != rgb_len(width, height) {
        return Err(FrameError::Output {
            width,
            height,
            got: out.len(),
        });
    }
    match format {
        PixelFormat::Rgb24 | PixelFormat::Yuyv => {
            let row = format.stride(width).unwrap_or(0) as usize;
            let stride = (stride as usize).max(row);
            let needed = stride * (height as usize).saturating_sub(1) + row;
            if frame.len() < needed {
                return Err(FrameError::Short {
                    format,
                    width,
                    height,
                    needed,
                    got: frame.len(),
                });
            }
            for (y, dst) in out.chunks_exact_mut(width as usize * 3).enumerate() {
                let src = &frame[y * stride..y * stride + row];
                if format == PixelFormat::Rgb24 {
                    dst.copy_from_slice(src);
                } else {
                    yuyv_row_to_rgb(src, dst);
                }
            }
            Ok(())
        }
        PixelFormat::Mjpeg => decode_jpeg(frame, width, height, out),
    }
}

/// One row of YUYV (Y0 U Y1 V per two pixels, BT.601 limited range as UVC cameras send it).
fn yuyv_row_to_rgb(src: &[u8], dst: &mut [u8]) {
    for (yuyv, rgb) in src.chunks_exact(4).zip(dst.chunks_exact_mut(6)) {
        let (u, v) = (i32::from(yuyv[1]) - 128, i32::from(yuyv[3]) - 128);
        // Fixed point ×256: R = 1.164(Y−16) + 1.596V, G = … − 0.392U − 0.813V, B = … + 2.017U.
        let (rv, guv, bu) = (409 * v, -100 * u - 208 * v, 516 * u);
        for (k, &y) in [yuyv[0], yuyv[2]].iter().enumerate() {
            let c = 298 * (i32::from(y) - 16) + 128;
            rgb[3 * k] = clamp_u8((c + rv) >> 8);
            rgb[3 * k + 1] = clamp_u8((c + guv) >> 8);
            rgb[3 * k + 2] = clamp_u8((c + bu) >> 8);
        }
    }
}

fn clamp_u8(v: i32) -> u8 {
    v.clamp(0, 255) as u8
}

/// Packs RGB24 into YUYV (BT.601 limited range), averaging the chroma of each pixel pair: what
/// a UVC camera's sensor pipeline does. The simulator's YUYV cameras use it.
pub fn rgb_to_yuyv(rgb: &[u8], out: &mut [u8]) {
    for (px, yuyv) in rgb.chunks_exact(6).zip(out.chunks_exact_mut(4)) {
        let luma = |p: &[u8]| {
            let (r, g, b) = (i32::from(p[0]), i32::from(p[1]), i32::from(p[2]));
            (((66 * r + 129 * g + 25 * b + 128) >> 8) + 16, r, g, b)
        };
        let (y0, r0, g0, b0) = luma(&px[0..3]);
        let (y1, r1, g1, b1) = luma(&px[3..6]);
        let (r, g, b) = ((r0 + r1) / 2, (g0 + g1) / 2, (b0 + b1) / 2);
        let u = ((-38 * r - 74 * g + 112 * b + 128) >> 8) + 128;
        let v = ((112 * r - 94 * g - 18 * b + 128) >> 8) + 128;
        yuyv.copy_from_slice(&[clamp_u8(y0), clamp_u8(u), clamp_u8(y1), clamp_u8(v)]);
    }
}

fn decode_jpeg(frame: &[u8], width: u32, height: u32, out: &mut [u8]) -> Result<(), FrameError> {
    let options = DecoderOptions::default()
        .jpeg_set_out_colorspace(ColorSpace::RGB)
        .set_max_width(width as usize)
        .set_max_height(height as usize)
        .set_strict_mode(true);
    let mut decoder = JpegDecoder::new_with_options(ZCursor::new(frame), options);
    decoder
        .decode_headers()
        .map_err(|e| FrameError::Jpeg(e.to_string()))?;
    let (got_width, got_height) = decoder
        .info()
        .map(|i| (u32::from(i.width), u32::from(i.height)))
        .unwrap_or((0, 0));
    if (got_width, got_height) != (width, height) {
        return Err(FrameError::JpegSize {
            width,
            height,
            got_width,
            got_height,
        });
    }
    decoder
        .decode_into(out)
        .map_err(|e| FrameError::Jpeg(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gradient(width: u32, height: u32) -> Vec<u8> {
        let mut rgb = vec![0u8; rgb_len(width, height)];
        for (i, px) in rgb.chunks_exact_mut(3).enumerate() {
            let (x, y) = (i as u32 % width, i as u32 / width);
            px.copy_from_slice(&[(x * 8) as u8, (y * 8) as u8, 128]);
        }
        rgb
    }

    fn jpeg(rgb: &[u8], width: u32, height: u32) -> Vec<u8> {
        let mut bytes = Vec::new();
        jpeg_encoder::Encoder::new(&mut bytes, 95)
            .encode(
                rgb,
                width as u16,
                height as u16,
                jpeg_encoder::ColorType::Rgb,
            )
            .unwrap();
        bytes
    }

    fn max_diff(a: &[u8], b: &[u8]) -> u8 {
        a.iter().zip(b).map(|(x, y)| x.abs_diff(*y)).max().unwrap()
    }

    #[test]
    fn yuyv_round_trips_within_the_chroma_subsampling() {
        // Flat colour pairs: no chroma is lost to subsampling, only rounding.
        let colours = [
            [255u8, 0, 0],
            [0, 255, 0],
            [0, 0, 255],
            [128, 128, 128],
            [20, 200, 90],
        ];
        let rgb: Vec<u8> = colours.iter().flat_map(|c| [*c, *c]).flatten().collect();
        let mut yuyv = vec![0u8; rgb.len() / 3 * 2];
        rgb_to_yuyv(&rgb, &mut yuyv);
        let mut back = vec![0u8; rgb.len()];
        to_rgb(PixelFormat::Yuyv, 10, 1, 20, &yuyv, &mut back).unwrap();
        assert!(max_diff(&rgb, &back) <= 4, "{rgb:?} -> {back:?}");
        // Known values (BT.601 limited range): black is Y 16, white Y 235, grey U = V = 128.
        let mut black_white = [0u8; 4];
        rgb_to_yuyv(&[0, 0, 0, 255, 255, 255], &mut black_white);
        assert_eq!(black_white, [16, 128, 235, 128]);
    }

    #[test]
    fn padded_rows_are_skipped_and_a_short_frame_refused() {
        let (w, h) = (2u32, 2u32);
        // Rows of 4 bytes of YUYV padded to 8.
        let mut frame = vec![0xEEu8; 8 * 2];
        frame[0..4].copy_from_slice(&[235, 128, 235, 128]);
        frame[8..12].copy_from_slice(&[16, 128, 16, 128]);
        let mut out = vec![0u8; rgb_len(w, h)];
        to_rgb(PixelFormat::Yuyv, w, h, 8, &frame, &mut out).unwrap();
        assert_eq!(out, [255, 255, 255, 255, 255, 255, 0, 0, 0, 0, 0, 0]);
        // The last row needs no padding after it; one byte less than that is short.
        let err = to_rgb(PixelFormat::Yuyv, w, h, 8, &frame[..11], &mut out).unwrap_err();
        assert!(
            matches!(
                err,
                FrameError::Short {
                    needed: 12,
                    got: 11,
                    ..
                }
            ),
            "{err}"
        );
        let err = to_rgb(PixelFormat::Rgb24, w, h, 6, &frame, &mut out[..3]).unwrap_err();
        assert!(matches!(err, FrameError::Output { got: 3, .. }), "{err}");
    }

    #[test]
    fn a_jpeg_decodes_to_its_image_and_a_corrupt_one_is_refused() {
        let (w, h) = (32u32, 24u32);
        let rgb = gradient(w, h);
        let bytes = jpeg(&rgb, w, h);
        let mut out = vec![0u8; rgb_len(w, h)];
        to_rgb(PixelFormat::Mjpeg, w, h, 0, &bytes, &mut out).unwrap();
        let mean_error = rgb
            .iter()
            .zip(&out)
            .map(|(a, b)| f64::from(a.abs_diff(*b)))
            .sum::<f64>()
            / rgb.len() as f64;
        assert!(mean_error < 3.0, "mean error {mean_error}");

        // Cut short, garbage, another size: each refused with its reason.
        let cut = to_rgb(
            PixelFormat::Mjpeg,
            w,
            h,
            0,
            &bytes[..bytes.len() / 2],
            &mut out,
        );
        assert!(matches!(cut, Err(FrameError::Jpeg(_))), "{cut:?}");
        let garbage = to_rgb(PixelFormat::Mjpeg, w, h, 0, &[0x42; 500], &mut out);
        assert!(matches!(garbage, Err(FrameError::Jpeg(_))), "{garbage:?}");
        let mut small = vec![0u8; rgb_len(16, 12)];
        let other = to_rgb(PixelFormat::Mjpeg, 16, 12, 0, &bytes, &mut small);
        assert!(
            matches!(
                other,
                Err(FrameError::Jpeg(_)) | Err(FrameError::JpegSize { .. })
            ),
            "{other:?}"
        );
    }
}
