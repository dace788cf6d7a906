//! The video writer against the real FFmpeg (`deploy/install-build-deps.sh` installs it), read
//! back with ffprobe: one frame per pushed JPEG, at `k / fps`, the MJPEG untouched; and a video
//! whose FFmpeg is killed mid-way stays readable up to its last fragment.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use recorder::video::VideoWriter;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

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
    let path = d.join("head.mp4");
    let mut w = VideoWriter::start(&path, 30).unwrap();
    let frames: Vec<Vec<u8>> = (0..45).map(jpeg).collect();
    for f in &frames {
        assert!(w.push(f.clone()));
    }
    assert_eq!(w.finish().unwrap(), 45);
    let (codec, times, sizes) = probe(&path);
    assert_eq!(codec, "mjpeg");
    assert_eq!(times.len(), 45);
    for (k, t) in times.iter().enumerate() {
        assert!((t - k as f64 / 30.0).abs() < 1e-4, "frame {k} at {t} s");
    }
    // Stream copy: each packet is the JPEG that went in, byte for byte in size.
    let sent: Vec<usize> = frames.iter().map(Vec::len).collect();
    assert_eq!(sizes, sent);
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn a_killed_ffmpeg_leaves_a_readable_video_of_what_it_wrote() {
    let d = dir("killed");
    let path = d.join("head.mp4");
    let mut w = VideoWriter::start(&path, 30).unwrap();
    for k in 0..30 {
        w.push(jpeg(k));
    }
    // Let FFmpeg write its fragments, then kill it as a crash would.
    std::thread::sleep(Duration::from_millis(1500));
    let pid = w.ffmpeg_pid().unwrap();
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(pid as i32),
        nix::sys::signal::Signal::SIGKILL,
    )
    .unwrap();
    assert!(w.finish().is_err(), "a killed FFmpeg is an error");
    let (codec, times, _) = probe(&path);
    assert_eq!(codec, "mjpeg");
    assert!(
        times.len() >= 25,
        "{} of 30 frames readable after the kill",
        times.len()
    );
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn a_writer_that_cannot_start_says_why() {
    let d = dir("bad");
    // A directory where the file should be: FFmpeg refuses, the error carries its reason.
    let path = d.join("taken");
    std::fs::create_dir_all(&path).unwrap();
    let mut w = VideoWriter::start(&path, 30).unwrap();
    w.push(jpeg(0));
    let e = w.finish().unwrap_err().to_string();
    assert!(e.contains("ffmpeg writing") && e.contains("taken"), "{e}");
    let _ = std::fs::remove_dir_all(&d);
}
