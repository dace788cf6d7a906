//! A camera's staged stream and the MP4 made of it, against the real FFmpeg
//! (`deploy/install-build-deps.sh` installs it), read back with ffprobe: one frame per JPEG, at
//! `k / fps`, the MJPEG untouched; a stream a crash cut short keeps its whole JPEGs; the image
//! statistics sample the frames LeRobot samples.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use recorder::video::{self, StagedVideo};
use std::path::{Path, PathBuf};
use std::process::Command;

fn dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("nori-video-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A 64×48 JPEG whose brightness says which frame it is.
fn jpeg(k: usize) -> Vec<u8> {
    let rgb = vec![(k * 5 % 256) as u8; 64 * 48 * 3];
    let mut out = Vec::new();
    jpeg_encoder::Encoder::new(&mut out, 85)
        .encode(&rgb, 64, 48, jpeg_encoder::ColorType::Rgb)
        .unwrap();
    out
}

/// ffprobe's view of the video's packets: (codec, packet times in s, packet sizes).
fn probe(path: &Path) -> (String, Vec<f64>, Vec<usize>) {
    let out = Command::new("ffprobe")
        .args(["-v", "error", "-select_streams", "v:0", "-of", "json"])
        .args(["-show_entries", "stream=codec_name:packet=pts_time,size"])
        .arg(path)
        .output()
        .expect("ffprobe (deploy/install-build-deps.sh installs ffmpeg)");
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap_or_default();
    let codec = v["streams"][0]["codec_name"]
        .as_str()
        .unwrap_or_default()
        .to_string();
    let packets = v["packets"].as_array().cloned().unwrap_or_default();
    let times = packets
        .iter()
        .map(|p| p["pts_time"].as_str().unwrap().parse::<f64>().unwrap())
        .collect();
    let sizes = packets
        .iter()
        .map(|p| p["size"].as_str().unwrap().parse::<usize>().unwrap())
        .collect();
    (codec, times, sizes)
}

#[test]
fn every_jpeg_is_one_frame_at_its_time_untouched() {
    let d = dir("frames");
    let stream = d.join("head.mjpeg");
    let mut w = StagedVideo::start(&stream, 30).unwrap();
    let frames: Vec<Vec<u8>> = (0..45).map(jpeg).collect();
    for f in &frames {
        assert!(w.push(f.clone()));
    }
    assert_eq!(w.finish().unwrap(), 45);
    let staged = video::staged_frames(&stream).unwrap();
    let sent: Vec<usize> = frames.iter().map(Vec::len).collect();
    assert_eq!(
        staged.iter().map(|&(_, n)| n as usize).collect::<Vec<_>>(),
        sent
    );
    assert_eq!(video::read_staged(&stream, staged[7]).unwrap(), frames[7]);
    // The MP4 of its first 40 frames: FFmpeg's parser splits the stream where the index does.
    let path = d.join("head.mp4");
    video::mux(&stream, 40, 30, &path).unwrap();
    let (codec, times, sizes) = probe(&path);
    assert_eq!(codec, "mjpeg");
    assert_eq!(times.len(), 40);
    for (k, t) in times.iter().enumerate() {
        assert!((t - k as f64 / 30.0).abs() < 1e-4, "frame {k} at {t} s");
    }
    assert_eq!(sizes, sent[..40], "stream copy: each packet is its JPEG");
    assert_eq!(video::count_frames(&path).unwrap(), 40);
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn a_stream_a_crash_cut_short_keeps_its_whole_jpegs_in_order() {
    let d = dir("cut");
    let stream = d.join("head.mjpeg");
    let mut w = StagedVideo::start(&stream, 30).unwrap();
    for k in 0..10 {
        w.push(jpeg(k));
    }
    w.finish().unwrap();
    let whole = video::staged_frames(&stream).unwrap();
    let index = stream.with_extension("idx");
    let f = std::fs::OpenOptions::new()
        .write(true)
        .open(&stream)
        .unwrap();
    // The tenth JPEG lost its end marker, with its index entry on disk.
    f.set_len(whole[9].0 + whole[9].1 - 1).unwrap();
    assert_eq!(video::staged_frames(&stream).unwrap(), whole[..9]);
    // An index entry torn in the middle.
    std::fs::OpenOptions::new()
        .write(true)
        .open(&index)
        .unwrap()
        .set_len(16 * 6 + 9)
        .unwrap();
    assert_eq!(video::staged_frames(&stream).unwrap(), whole[..6]);
    // An entry pointing at bytes that are no JPEG start: nothing from it on.
    let mut bytes = std::fs::read(&stream).unwrap();
    bytes[whole[3].0 as usize] = 0;
    std::fs::write(&stream, bytes).unwrap();
    assert_eq!(video::staged_frames(&stream).unwrap(), whole[..3]);
    // No index at all: an error naming the stream, not an empty success.
    std::fs::remove_file(&index).unwrap();
    let e = video::staged_frames(&stream).unwrap_err().to_string();
    assert!(e.contains("head.mjpeg"), "{e}");
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn a_stream_that_cannot_be_written_says_why() {
    let d = dir("bad");
    let e = StagedVideo::start(&d.join("missing/head.mjpeg"), 30)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("staged video") && e.contains("missing/head.mjpeg"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn image_statistics_sample_the_frames_lerobot_samples() {
    // numpy.round(numpy.linspace(0, 999, 177)) (1000 ** 0.75 = 177.8): LeRobot's
    // sample_indices for 1000 frames; the first few and the last.
    let mut asked = Vec::new();
    let (_, sampled) = video::image_histograms(1000, |k| {
        asked.push(k);
        Ok(jpeg(k as usize))
    })
    .unwrap();
    assert_eq!(sampled, 177);
    assert_eq!(asked.len(), 177);
    assert_eq!(&asked[..5], [0, 6, 11, 17, 23]);
    assert_eq!(*asked.last().unwrap(), 999);
    // Short episodes: every frame (LeRobot's floor of 100 samples, capped at the length).
    let mut asked = Vec::new();
    video::image_histograms(7, |k| {
        asked.push(k);
        Ok(jpeg(k as usize))
    })
    .unwrap();
    assert_eq!(asked, [0, 1, 2, 3, 4, 5, 6]);
    // A JPEG that does not decode names its frame.
    let e = video::image_histograms(3, |k| Ok(if k == 1 { b"junk".to_vec() } else { jpeg(0) }))
        .unwrap_err()
        .to_string();
    assert!(e.contains("frame 1"), "{e}");
}
