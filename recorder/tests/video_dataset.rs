//! Video in the dataset, against the real FFmpeg: each camera's frames land in LeRobot's video
//! files frame for frame with the data (frame `k` of an episode at `from_timestamp + k / fps`),
//! files roll at their size limit, the image statistics are those of the pictures, and every
//! crash state leaves video and data agreeing after the next open.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use recorder::dataset::{Settings, STAGING};
use recorder::features::CameraMeta;
use recorder::video::{self, jpeg_format};
use recorder::{Dataset, Features, Frame};
use std::path::{Path, PathBuf};
use std::process::Command;
use telemetry::frames::{JointInfo, JointLayout, JointRole};

const W: u32 = 320;
const H: u32 = 240;

fn joints() -> Features {
    let mut l = JointLayout {
        joint_count: 1,
        bus_count: 1,
        ..JointLayout::default()
    };
    let mut j = JointInfo {
        role: JointRole::Joint as u8,
        id: 1,
        model: 777,
        range_rad: [-2.0, 2.0],
        ..JointInfo::default()
    };
    j.set_name("elbow");
    l.joints[0] = j;
    Features::from_layout(&l)
}

fn features() -> Features {
    let camera = |name: &str| CameraMeta {
        name: name.into(),
        width: W,
        height: H,
        pix_fmt: "yuvj420p".into(),
    };
    joints().with_cameras(vec![camera("head"), camera("wrist")])
}

/// A JPEG of `W`×`H`: flat grey `level` (exact statistics), or noise (large files).
fn jpeg(level: u8, noise: bool) -> Vec<u8> {
    let mut rgb = vec![level; (W * H * 3) as usize];
    if noise {
        let mut x = 0x2545_F491_u32 ^ u32::from(level);
        for p in &mut rgb {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            *p = x as u8;
        }
    }
    let mut out = Vec::new();
    jpeg_encoder::Encoder::new(&mut out, 90)
        .encode(&rgb, W as u16, H as u16, jpeg_encoder::ColorType::Rgb)
        .unwrap();
    out
}

fn frame(f: &Features, i: usize) -> Frame {
    let mut fr = Frame::missing(f);
    fr.state[0] = i as f32;
    fr.action[0] = i as f32;
    for v in [
        &mut fr.velocity,
        &mut fr.current,
        &mut fr.temperature,
        &mut fr.voltage,
        &mut fr.valid,
    ] {
        v[0] = 1.0;
    }
    fr.camera_valid = vec![1.0, if i % 4 == 3 { 0.0 } else { 1.0 }];
    fr
}

fn dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("nori-video-ds-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn settings() -> Settings {
    Settings {
        video_files_size_in_mb: 1,
        ..Settings::default()
    }
}

/// Records an episode of `frames` frames: the head camera grey at `level`, the wrist noise.
fn record(ds: &mut Dataset, frames: usize, level: u8) {
    let f = ds.features().clone();
    let mut w = ds.begin_episode("look", 15).unwrap();
    for i in 0..frames {
        w.push_with_images(frame(&f, i), vec![jpeg(level, false), jpeg(i as u8, true)])
            .unwrap();
    }
    w.finish().unwrap().unwrap();
}

/// Packet times of a video (s), by ffprobe.
fn packet_times(path: &Path) -> Vec<f64> {
    let out = Command::new("ffprobe")
        .args(["-v", "error", "-select_streams", "v:0", "-of", "csv=p=0"])
        .args(["-show_entries", "packet=pts_time"])
        .arg(path)
        .output()
        .expect("ffprobe (deploy/install-build-deps.sh installs ffmpeg)");
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| l.trim_end_matches(',').parse().unwrap())
        .collect()
}

fn probe_pix_fmt(path: &Path) -> String {
    let out = Command::new("ffprobe")
        .args(["-v", "error", "-select_streams", "v:0", "-of", "csv=p=0"])
        .args(["-show_entries", "stream=pix_fmt"])
        .arg(path)
        .output()
        .unwrap();
    String::from_utf8_lossy(&out.stdout).trim().to_string()
}

fn video(root: &Path, camera: &str, file: i64) -> PathBuf {
    root.join(format!(
        "videos/observation.images.{camera}/chunk-000/file-{file:03}.mp4"
    ))
}

#[test]
fn jpeg_headers_name_the_pixel_format_ffmpeg_decodes() {
    let d = dir("pixfmt");
    std::fs::create_dir_all(&d).unwrap();
    let j = jpeg(100, false);
    let f = jpeg_format(&j).unwrap();
    assert_eq!((f.width, f.height), (W, H));
    // Cross-checked with FFmpeg's own reading of the same JPEG, not with our parser.
    let stream = d.join("one.mjpeg");
    let mut w = video::StagedVideo::start(&stream, 30).unwrap();
    w.push(j.clone());
    w.finish().unwrap();
    let path = d.join("one.mp4");
    video::mux(&stream, 1, 30, &path).unwrap();
    assert_eq!(f.pix_fmt, probe_pix_fmt(&path));
    // Other layouts, by their frame headers.
    let with_sampling = |y: u8| {
        let mut j = j.clone();
        let sof = j.windows(2).position(|w| w == [0xFF, 0xC0]).unwrap();
        j[sof + 4 + 6 + 1] = y;
        jpeg_format(&j).map(|f| f.pix_fmt)
    };
    assert_eq!(with_sampling(0x11), Some("yuvj444p"));
    assert_eq!(with_sampling(0x21), Some("yuvj422p"));
    assert_eq!(with_sampling(0x33), None, "no FFmpeg name: refused");
    assert_eq!(jpeg_format(&j[..20]), None, "cut before its frame header");
    assert_eq!(jpeg_format(b"not a jpeg"), None);
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn each_frame_of_each_camera_lands_at_its_time_and_files_roll_at_the_limit() {
    let root = dir("commit");
    let (mut ds, _) = Dataset::open(&root, settings(), features(), false).unwrap();
    let lengths = [20usize, 25, 30];
    for (e, &n) in lengths.iter().enumerate() {
        record(&mut ds, n, 40 + 80 * e as u8);
    }
    let episodes = ds.episodes().to_vec();
    drop(ds);

    let info: serde_json::Value =
        serde_json::from_slice(&std::fs::read(root.join("meta/info.json")).unwrap()).unwrap();
    assert_eq!(
        info["video_path"],
        "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    );
    let head = &info["features"]["observation.images.head"];
    assert_eq!(head["dtype"], "video");
    assert_eq!(head["shape"], serde_json::json!([H, W, 3]));
    assert_eq!(
        head["names"],
        serde_json::json!(["height", "width", "channels"])
    );
    assert_eq!(head["info"]["video.codec"], "mjpeg");
    assert_eq!(head["info"]["video.fps"], 30);
    assert_eq!(
        info["features"]["observation.camera_valid"]["names"],
        serde_json::json!(["head", "wrist"])
    );

    // The grey head camera fits one file; the noisy wrist camera (~1 MB for two episodes)
    // rolls to a second file at the 1 MB limit.
    let wrist_files: Vec<i64> = episodes.iter().map(|e| e.videos[1].file_index).collect();
    assert_eq!(
        episodes
            .iter()
            .map(|e| e.videos[0].file_index)
            .collect::<Vec<_>>(),
        [0, 0, 0]
    );
    assert!(wrist_files.windows(2).all(|w| w[0] <= w[1]));
    assert_ne!(
        wrist_files[0], wrist_files[2],
        "the wrist video rolled over: {wrist_files:?}"
    );
    for c in 0..2 {
        let mut from_frame = 0usize;
        for (e, ep) in episodes.iter().enumerate() {
            let span = &ep.videos[c];
            if e > 0 && span.file_index != episodes[e - 1].videos[c].file_index {
                from_frame = 0;
            }
            assert!((span.from_timestamp - from_frame as f64 / 30.0).abs() < 1e-9);
            assert!(
                (span.to_timestamp - (from_frame + lengths[e]) as f64 / 30.0).abs() < 1e-9,
                "{span:?}"
            );
            from_frame += lengths[e];
        }
        // Every file holds exactly its episodes' frames, frame k at k / fps.
        for file in 0..=episodes.last().unwrap().videos[c].file_index {
            let camera = ["head", "wrist"][c];
            let times = packet_times(&video(&root, camera, file));
            let expected: usize = episodes
                .iter()
                .zip(lengths)
                .filter(|(ep, _)| ep.videos[c].file_index == file)
                .map(|(_, n)| n)
                .sum();
            assert_eq!(times.len(), expected, "{camera} file {file}");
            for (k, t) in times.iter().enumerate() {
                assert!(
                    (t - k as f64 / 30.0).abs() < 1e-4,
                    "{camera} frame {k} at {t}"
                );
            }
        }
    }

    // The head camera's statistics are those of its flat grey pictures: each episode's mean
    // is its level (JPEG keeps a flat grey within a step), and stats.json aggregates them.
    for (e, ep) in episodes.iter().enumerate() {
        let (_, s) = ep
            .stats
            .iter()
            .find(|(k, _)| k == "observation.images.head")
            .unwrap();
        let level = f64::from(40 + 80 * e as u8) / 255.0;
        for c in 0..3 {
            assert!(
                (s.mean[c] - level).abs() < 2.0 / 255.0,
                "episode {e}: {s:?}"
            );
            assert!(s.std[c] < 2.0 / 255.0);
        }
        assert_eq!(
            s.count, lengths[e] as u64,
            "short episodes: every frame sampled"
        );
    }
    let stats: serde_json::Value =
        serde_json::from_slice(&std::fs::read(root.join("meta/stats.json")).unwrap()).unwrap();
    let mean = &stats["observation.images.head"]["mean"];
    assert_eq!(mean.as_array().unwrap().len(), 3, "{mean}");
    let overall = mean[0][0][0].as_f64().unwrap();
    let expected = (20.0 * 40.0 + 25.0 * 120.0 + 30.0 * 200.0) / 75.0 / 255.0;
    assert!(
        (overall - expected).abs() < 2.0 / 255.0,
        "{overall} vs {expected}"
    );
    assert_eq!(
        stats["observation.images.head"]["count"],
        serde_json::json!([75])
    );

    // The episode table reads back (nested image statistics included) when the dataset is
    // opened again, and a fourth episode appends after the third.
    let (mut ds, recovery) = Dataset::open(&root, settings(), features(), false).unwrap();
    assert!(recovery.is_clean(), "{recovery:?}");
    assert_eq!(ds.episodes(), &episodes[..]);
    record(&mut ds, 10, 10);
    let head = packet_times(&video(&root, "head", 0));
    assert_eq!(head.len(), 85);
    drop(ds);
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn a_killed_recorder_keeps_the_frames_both_the_data_and_every_video_hold() {
    let root = dir("killed");
    let (mut ds, _) = Dataset::open(&root, settings(), features(), false).unwrap();
    record(&mut ds, 12, 100);
    let f = ds.features().clone();
    let mut w = ds.begin_episode("look", 10).unwrap();
    for i in 0..25 {
        w.push_with_images(frame(&f, i), vec![jpeg(30, false), jpeg(i as u8, true)])
            .unwrap();
    }
    // 20 frames flushed as parts; the last 5 only in the videos (the recorder died before its
    // next flush); the staged streams hold every JPEG handed over.
    w.sync().unwrap();
    w.abandon().unwrap();
    drop(ds);
    let staged = root.join(STAGING).join("episode-000001/videos");
    assert_eq!(
        video::staged_frames(&staged.join("observation.images.head.mjpeg"))
            .unwrap()
            .len(),
        25
    );
    // The wrist stream was cut short by the crash: its 18th JPEG half written, its index entry
    // there, the 19th's entry half written.
    let wrist = staged.join("observation.images.wrist.mjpeg");
    let index = staged.join("observation.images.wrist.idx");
    let entries = video::staged_frames(&wrist).unwrap();
    let (offset, size) = entries[17];
    let f_stream = std::fs::OpenOptions::new()
        .write(true)
        .open(&wrist)
        .unwrap();
    f_stream.set_len(offset + size / 2).unwrap();
    let f_index = std::fs::OpenOptions::new()
        .write(true)
        .open(&index)
        .unwrap();
    f_index.set_len(18 * 16 + 7).unwrap();

    let (ds, recovery) = Dataset::open(&root, settings(), features(), false).unwrap();
    assert_eq!(recovery.recovered, [(1, 17)], "{recovery:?}");
    let ep = &ds.episodes()[1];
    assert_eq!(ep.length, 17);
    assert_eq!(ds.read_episode(1).unwrap().len(), 17);
    assert_eq!(packet_times(&video(&root, "head", 0)).len(), 12 + 17);
    assert!((ep.videos[0].from_timestamp - 12.0 / 30.0).abs() < 1e-9);
    drop(ds);

    // A staged episode whose video is unreadable is dropped, and says why.
    let mut w_ds = Dataset::open(&root, settings(), features(), false)
        .unwrap()
        .0;
    let mut w = w_ds.begin_episode("look", 10).unwrap();
    for i in 0..10 {
        w.push_with_images(frame(&f, i), vec![jpeg(30, false), jpeg(1, true)])
            .unwrap();
    }
    w.sync().unwrap();
    w.abandon().unwrap();
    drop(w_ds);
    let staged = root.join(STAGING).join("episode-000002/videos");
    std::fs::write(staged.join("observation.images.wrist.mjpeg"), b"garbage").unwrap();
    let (ds, recovery) = Dataset::open(&root, settings(), features(), false).unwrap();
    assert_eq!(ds.episodes().len(), 2);
    let (e, n, why) = &recovery.dropped[0];
    assert_eq!((*e, *n), (2, 10));
    assert!(why.contains("wrist"), "{why}");
    drop(ds);
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn video_frames_no_episode_references_are_cut_at_the_next_open() {
    let root = dir("orphans");
    let (mut ds, _) = Dataset::open(&root, settings(), features(), false).unwrap();
    record(&mut ds, 15, 100);
    drop(ds);
    // A crash after the head video's rename and before the episode table's: 9 more frames at
    // the end of the file; and a wrist file that no episode references.
    let head = video(&root, "head", 0);
    let longer = root.join("longer.mp4");
    video::concat(
        &[
            video::Piece {
                path: &head,
                frames: 15,
            },
            video::Piece {
                path: &head,
                frames: 9,
            },
        ],
        30,
        &longer,
    )
    .unwrap();
    std::fs::rename(&longer, &head).unwrap();
    std::fs::copy(video(&root, "wrist", 0), video(&root, "wrist", 1)).unwrap();

    let (ds, recovery) = Dataset::open(&root, settings(), features(), false).unwrap();
    assert_eq!(recovery.orphan_video_frames_removed, 9 + 15, "{recovery:?}");
    assert_eq!(packet_times(&head).len(), 15);
    assert!(!video(&root, "wrist", 1).exists());
    drop(ds);

    // Fewer frames than the episodes span cannot come from a crash: refused, with the file.
    let cut = root.join("cut.mp4");
    video::concat(
        &[video::Piece {
            path: &head,
            frames: 10,
        }],
        30,
        &cut,
    )
    .unwrap();
    std::fs::rename(&cut, &head).unwrap();
    let e = Dataset::open(&root, settings(), features(), false)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("holds 10 frames") && e.contains("file-000.mp4"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn images_must_come_with_every_frame_of_a_camera_dataset() {
    let root = dir("images");
    let (mut ds, _) = Dataset::open(&root, settings(), features(), false).unwrap();
    let f = ds.features().clone();
    let mut w = ds.begin_episode("look", 10).unwrap();
    let e = w.push(frame(&f, 0)).unwrap_err().to_string();
    assert!(e.contains("0 image(s) for 2 camera(s)"), "{e}");
    assert!(w.is_empty(), "nothing recorded");
    w.discard().unwrap();
    drop(ds);
    let _ = std::fs::remove_dir_all(&root);
}
