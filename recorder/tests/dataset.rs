//! The dataset on disk: episodes committed and read back, resuming, refusing what does not fit,
//! and every crash state the commit protocol can leave, each repaired at the next open.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use recorder::dataset::{DatasetReader, Settings, STAGING};
use recorder::{Dataset, Features, Frame, RecordError};
use std::path::{Path, PathBuf};
use telemetry::frames::{JointInfo, JointLayout, JointRole};

fn features() -> Features {
    let mut l = JointLayout {
        joint_count: 3,
        bus_count: 1,
        ..JointLayout::default()
    };
    for (i, (n, r)) in [
        ("left_shoulder", JointRole::Joint),
        ("left_elbow", JointRole::Joint),
        ("left_gripper", JointRole::Gripper),
    ]
    .iter()
    .enumerate()
    {
        let mut j = JointInfo {
            role: *r as u8,
            id: i as u8 + 1,
            model: 777,
            range_rad: [-2.0, 2.0],
            ..JointInfo::default()
        };
        j.set_name(n);
        l.joints[i] = j;
    }
    Features::from_layout(&l)
}

/// A frame whose values say which episode and frame it is.
fn frame(f: &Features, episode: usize, i: usize) -> Frame {
    let mut fr = Frame::missing(f);
    for j in 0..f.joints.len() {
        let x = episode as f32 * 100.0 + i as f32 * 0.01 + j as f32;
        fr.state[j] = x;
        fr.action[j] = x + 0.5;
        fr.velocity[j] = 0.1;
        fr.current[j] = 0.2 + j as f32;
        fr.temperature[j] = 30.0;
        fr.voltage[j] = 12.0;
        // Every fifth frame holds joint 1's last read.
        fr.valid[j] = if j == 1 && i % 5 == 4 { 0.0 } else { 1.0 };
    }
    fr.grip_force[0] = (i % 10) as f32 / 10.0;
    fr
}

fn dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("nori-recorder-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn open(root: &Path) -> (Dataset, recorder::Recovery) {
    Dataset::open(root, Settings::default(), features(), false).unwrap()
}

fn record(ds: &mut Dataset, task: &str, episode: usize, frames: usize) {
    let f = ds.features().clone();
    let mut w = ds.begin_episode(task, 30).unwrap();
    for i in 0..frames {
        w.push(frame(&f, episode, i)).unwrap();
    }
    w.finish().unwrap().unwrap();
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            copy_dir(&p, &to.join(e.file_name()));
        } else {
            std::fs::copy(&p, to.join(e.file_name())).unwrap();
        }
    }
}

#[test]
fn episodes_are_committed_read_back_and_extended_after_a_restart() {
    let root = dir("roundtrip");
    {
        let (mut ds, rec) = open(&root);
        assert!(rec.is_clean());
        record(&mut ds, "wave", 0, 45);
        record(&mut ds, "grasp", 1, 31);
    }
    let (mut ds, rec) = open(&root);
    assert!(rec.is_clean(), "{rec:?}");
    assert_eq!(ds.episodes().len(), 2);
    assert_eq!(ds.tasks(), ["wave", "grasp"]);
    record(&mut ds, "wave", 2, 10);
    let e = &ds.episodes()[2];
    assert_eq!((e.dataset_from_index, e.dataset_to_index), (76, 86));
    assert_eq!(
        (e.data_chunk_index, e.data_file_index),
        (0, 0),
        "appended to the same file"
    );

    let rows = ds.read_episode(1).unwrap();
    assert_eq!(rows.len(), 31);
    let f = features();
    for (i, r) in rows.iter().enumerate() {
        assert_eq!(r.frame, frame(&f, 1, i));
        assert_eq!(r.frame_index, i as i64);
        assert_eq!(r.index, 45 + i as i64);
        assert_eq!(r.task_index, 1);
        assert_eq!(r.timestamp, (i as f64 / 30.0) as f32);
    }
    assert_eq!(
        ds.read_episode(2).unwrap()[0].task_index,
        0,
        "a known task keeps its index"
    );
    let info: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(root.join("meta/info.json")).unwrap())
            .unwrap();
    assert_eq!(info["total_frames"], 86);
    assert_eq!(info["total_episodes"], 3);
    assert_eq!(info["splits"]["train"], "0:3");
    assert_eq!(
        info["video_files_size_in_mb"], 200,
        "LeRobot's default since 0.4.1"
    );
    // Keys in the order LeRobot 0.6 writes them (its DatasetInfo dataclass).
    let text = std::fs::read_to_string(root.join("meta/info.json")).unwrap();
    let order = [
        "codebase_version",
        "fps",
        "features",
        "total_episodes",
        "total_frames",
        "total_tasks",
        "chunks_size",
        "data_files_size_in_mb",
        "video_files_size_in_mb",
        "data_path",
        "video_path",
        "robot_type",
        "splits",
    ];
    let at: Vec<usize> = order
        .iter()
        .map(|k| {
            text.find(&format!("\n  \"{k}\""))
                .unwrap_or_else(|| panic!("{k}"))
        })
        .collect();
    assert!(at.windows(2).all(|w| w[0] < w[1]), "{text}");
    assert_eq!(
        info["features"]["observation.joint_valid"]["names"],
        serde_json::json!(["left_shoulder", "left_elbow", "left_gripper"])
    );
    let stats: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(root.join("meta/stats.json")).unwrap())
            .unwrap();
    assert_eq!(stats["observation.state"]["count"], serde_json::json!([86]));
    assert_eq!(stats["index"]["max"], serde_json::json!([85.0]));
    assert!(matches!(ds.read_episode(3), Err(RecordError::Request(_))));
    assert!(root.join(".nori-staging/lock").exists(), "held while open");
    drop(ds);
    // Closed: nothing of the recorder's is left for `push_to_hub` to publish.
    assert!(!root.join(".nori-staging").exists());
    let reader = DatasetReader::open(&root).unwrap();
    assert_eq!(reader.features, f);
    assert_eq!(reader.read_episode(0).unwrap().len(), 45);
    assert!(
        !root.join(".nori-staging").exists(),
        "a reader takes no lock"
    );
}

#[test]
fn a_second_recorder_and_other_settings_are_refused_with_the_reason() {
    let root = dir("refuse");
    let (mut ds, _) = open(&root);
    record(&mut ds, "wave", 0, 5);
    let second = Dataset::open(&root, Settings::default(), features(), false);
    assert!(matches!(second, Err(RecordError::Busy { .. })), "locked");
    drop(ds);
    let other_fps = Settings {
        fps: 50,
        ..Settings::default()
    };
    let e = Dataset::open(&root, other_fps, features(), false)
        .err()
        .unwrap();
    assert!(
        e.to_string().contains("recorded at 30 fps, asked for 50"),
        "{e}"
    );
    let mut fewer = features();
    fewer.joints.pop();
    let e = Dataset::open(&root, Settings::default(), fewer, false)
        .err()
        .unwrap();
    assert!(e.to_string().contains("features differ"), "{e}");
    let (mut ds, _) = open(&root);
    assert!(matches!(
        ds.begin_episode(" ", 30),
        Err(RecordError::Request(_))
    ));
    assert!(
        matches!(ds.begin_episode("x", 31), Err(RecordError::Request(_))),
        "more than 1 s per flush"
    );
    let bad = dir("bad-fps");
    let zero = Settings {
        fps: 0,
        ..Settings::default()
    };
    assert!(matches!(
        Dataset::open(&bad, zero, features(), false),
        Err(RecordError::Request(_))
    ));
}

#[test]
fn an_episode_killed_mid_recording_is_completed_from_its_flushed_parts() {
    let root = dir("killed");
    let f = features();
    {
        let (mut ds, _) = open(&root);
        record(&mut ds, "wave", 0, 20);
        let mut w = ds.begin_episode("grasp", 30).unwrap();
        for i in 0..75 {
            w.push(frame(&f, 1, i)).unwrap();
        }
        assert_eq!(
            w.flushed(),
            60,
            "two full seconds staged, 15 frames in memory"
        );
        // A crash after the last flush: the writer and the dataset vanish without finishing.
        w.abandon().unwrap();
    }
    let (ds, rec) = open(&root);
    assert_eq!(rec.recovered, vec![(1, 60)]);
    assert_eq!(ds.episodes().len(), 2);
    let rows = ds.read_episode(1).unwrap();
    assert_eq!(rows.len(), 60);
    assert_eq!(rows[59].frame, frame(&f, 1, 59));
    assert_eq!(rows[0].index, 20);
    assert!(!root.join(STAGING).join("episode-000001").exists());
    drop(ds);
    let (_, rec) = open(&root);
    assert!(rec.is_clean(), "repaired once: {rec:?}");
}

#[test]
fn an_unfinished_episode_can_be_dropped_and_one_without_frames_always_is() {
    let root = dir("drop");
    let f = features();
    {
        let (mut ds, _) = open(&root);
        let mut w = ds.begin_episode("wave", 10).unwrap();
        for i in 0..25 {
            w.push(frame(&f, 0, i)).unwrap();
        }
        w.abandon().unwrap();
    }
    let (ds, rec) = Dataset::open(&root, Settings::default(), features(), true).unwrap();
    assert_eq!(rec.dropped.len(), 1);
    assert_eq!(rec.dropped[0].1, 20);
    assert!(ds.episodes().is_empty());
    drop(ds);
    {
        let (mut ds, _) = open(&root);
        let w = ds.begin_episode("wave", 10).unwrap();
        w.abandon().unwrap();
    }
    let (ds, rec) = open(&root);
    assert_eq!(rec.dropped[0].2, "no frame was flushed");
    assert!(ds.episodes().is_empty());
}

#[test]
fn a_crash_between_the_data_file_and_the_episode_table_is_rolled_forward() {
    let root = dir("mid-commit");
    let f = features();
    let saved = dir("mid-commit-saved");
    {
        let (mut ds, _) = open(&root);
        record(&mut ds, "wave", 0, 40);
        let mut w = ds.begin_episode("wave", 30).unwrap();
        for i in 0..50 {
            w.push(frame(&f, 1, i)).unwrap();
        }
        w.sync().unwrap();
        // What the disk held just before the commit: meta files and the staged parts.
        copy_dir(&root.join("meta"), &saved.join("meta"));
        copy_dir(&root.join(STAGING), &saved.join(STAGING));
        w.finish().unwrap();
    }
    // The crash came after the data file's rename and before the episode table's: the new
    // data file with the old metadata, the staged parts still there, a temporary left over.
    std::fs::remove_dir_all(root.join("meta")).unwrap();
    copy_dir(&saved.join("meta"), &root.join("meta"));
    let _ = std::fs::remove_file(saved.join(STAGING).join("lock"));
    copy_dir(&saved.join(STAGING), &root.join(STAGING));
    std::fs::write(
        root.join("data/chunk-000/file-000.parquet.tmp"),
        b"half a file",
    )
    .unwrap();
    let reader = DatasetReader::open(&root).unwrap();
    assert_eq!(
        reader.episodes.len(),
        1,
        "readers see the committed episode only"
    );
    assert_eq!(reader.read_episode(0).unwrap().len(), 40);

    let (ds, rec) = open(&root);
    assert_eq!(rec.orphan_rows_removed, 50);
    assert_eq!(rec.temporaries_removed, 1);
    assert_eq!(
        rec.recovered,
        vec![(1, 30)],
        "completed from the one flushed part"
    );
    assert_eq!(ds.read_episode(1).unwrap().len(), 30);
    assert_eq!(ds.read_episode(0).unwrap()[39].frame, frame(&f, 0, 39));
}

#[test]
fn staging_left_after_a_commit_is_removed_without_a_second_copy() {
    let root = dir("after-commit");
    let f = features();
    let saved = dir("after-commit-saved");
    {
        let (mut ds, _) = open(&root);
        let mut w = ds.begin_episode("wave", 30).unwrap();
        for i in 0..30 {
            w.push(frame(&f, 0, i)).unwrap();
        }
        copy_dir(&root.join(STAGING), &saved.join(STAGING));
        w.finish().unwrap();
    }
    let _ = std::fs::remove_file(saved.join(STAGING).join("lock"));
    copy_dir(&saved.join(STAGING), &root.join(STAGING));
    let (ds, rec) = open(&root);
    assert_eq!(rec.already_committed, 1);
    assert_eq!(ds.episodes().len(), 1);
}

#[test]
fn data_files_roll_over_at_the_size_limit() {
    let root = dir("rollover");
    let settings = Settings {
        data_files_size_in_mb: 1,
        ..Settings::default()
    };
    let (mut ds, _) = Dataset::open(&root, settings, features(), false).unwrap();
    // Values that do not compress: 19 floats, about 80 bytes a frame, so 16000 frames pass 1 MB.
    let f = features();
    let mut w = ds.begin_episode("wave", 30).unwrap();
    let mut x = 0x1234_5678u32;
    for _ in 0..16000 {
        let mut fr = Frame::missing(&f);
        for v in [
            &mut fr.state,
            &mut fr.action,
            &mut fr.velocity,
            &mut fr.current,
            &mut fr.temperature,
            &mut fr.voltage,
            &mut fr.grip_force,
        ] {
            for slot in v.iter_mut() {
                x ^= x << 13;
                x ^= x >> 17;
                x ^= x << 5;
                *slot = x as f32 / u32::MAX as f32;
            }
        }
        w.push(fr).unwrap();
    }
    w.finish().unwrap();
    record(&mut ds, "wave", 1, 10);
    let e = ds.episodes();
    assert_eq!((e[0].data_chunk_index, e[0].data_file_index), (0, 0));
    assert_eq!(
        (e[1].data_chunk_index, e[1].data_file_index),
        (0, 1),
        "a new file past 1 MB"
    );
    assert!(root.join("data/chunk-000/file-001.parquet").exists());
    assert_eq!(ds.read_episode(1).unwrap().len(), 10);
    drop(ds);
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn the_csv_export_is_the_model_labs_format() {
    let root = dir("csv");
    let (mut ds, _) = open(&root);
    record(&mut ds, "wave", 0, 12);
    let f = ds.features().clone();
    let mut w = ds.begin_episode("wave", 30).unwrap();
    let mut fr = frame(&f, 1, 0);
    fr.valid[1] = 0.0;
    w.push(fr).unwrap();
    w.finish().unwrap();
    drop(ds);
    let out = dir("csv-out");
    let files = recorder::csv::export(&root, &out, &[]).unwrap();
    assert_eq!(files.len(), 2);
    let text = std::fs::read_to_string(&files[1]).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines[0], recorder::csv::HEADER);
    assert_eq!(lines.len(), 1 + 3, "one row per joint");
    assert_eq!(
        lines[2], "0.000000,1,,,,,,",
        "a joint whose last read is held is a missing sample"
    );
    assert_eq!(lines[3], "0.000000,2,102.5,102,0.1,12,30,2.2");
    let side: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(out.join("episode-000001.meta.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(side["chains"], serde_json::json!([[0, 1, 2]]));
    assert_eq!(side["servo"]["2"], "sts3215");
    let e = recorder::csv::export(&root, &out, &[7]).err().unwrap();
    assert!(e.to_string().contains("no episode 7"), "{e}");
}
