//! Commit cost against the size of the data file it appends to: episodes of random
//! (incompressible) frames of a two-arm robot are committed one after the other until the file
//! reaches the size limit; each commit rewrites the file (old row groups copied as encoded bytes).
//!
//! `cargo run --release -p recorder --example commit_cost -- DIR [EPISODES] [FRAMES]`

#![allow(clippy::unwrap_used, clippy::expect_used)]

use recorder::dataset::Settings;
use recorder::{Dataset, Features, Frame};
use std::time::Instant;
use telemetry::frames::{JointInfo, JointLayout, JointRole};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let root = std::path::PathBuf::from(args.get(1).expect("DIR"));
    let episodes: usize = args.get(2).map_or(20, |a| a.parse().expect("EPISODES"));
    let frames: usize = args.get(3).map_or(18_000, |a| a.parse().expect("FRAMES"));
    let mut layout = JointLayout {
        joint_count: 16,
        bus_count: 2,
        ..JointLayout::default()
    };
    for i in 0..16 {
        let mut j = JointInfo {
            bus: (i / 8) as u8,
            id: (i % 8 + 1) as u8,
            role: if i % 8 == 7 {
                JointRole::Gripper
            } else {
                JointRole::Joint
            } as u8,
            model: 777,
            ..JointInfo::default()
        };
        j.set_name(&format!("joint_{i}"));
        layout.joints[i] = j;
    }
    let features = Features::from_layout(&layout);
    let (mut ds, _) = Dataset::open(&root, Settings::default(), features.clone(), false).unwrap();
    let mut x = 0x9E37_79B9u32;
    println!("episode,frames,data_file_mb_before,commit_ms");
    for e in 0..episodes {
        let before = ds.episodes().last().map_or(0, |l| {
            let p = root.join(format!(
                "data/chunk-{:03}/file-{:03}.parquet",
                l.data_chunk_index, l.data_file_index
            ));
            std::fs::metadata(p).map_or(0, |m| m.len())
        });
        let mut w = ds.begin_episode("bench", 30).unwrap();
        for _ in 0..frames {
            let mut f = Frame::missing(&features);
            for v in [
                &mut f.state,
                &mut f.action,
                &mut f.velocity,
                &mut f.current,
                &mut f.temperature,
                &mut f.voltage,
                &mut f.grip_force,
            ] {
                for s in v.iter_mut() {
                    x ^= x << 13;
                    x ^= x >> 17;
                    x ^= x << 5;
                    *s = x as f32 / u32::MAX as f32;
                }
            }
            w.push(f).unwrap();
        }
        w.sync().unwrap();
        let t = Instant::now();
        w.finish().unwrap();
        println!(
            "{e},{frames},{:.1},{:.1}",
            before as f64 / 1048576.0,
            t.elapsed().as_secs_f64() * 1e3
        );
    }
}
