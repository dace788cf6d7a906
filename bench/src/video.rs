//! `video-encode`: the cost of turning a camera's frames into a LeRobot video, per codec, next
//! to LeRobot's own default (SVT-AV1, preset 12, CRF 30, a keyframe every 2 frames) measured in
//! the same run. The frames are the simulated A3 seen from one of its cameras with the left arm
//! moving, rendered before anything is timed; each candidate is FFmpeg (the encoder the robot
//! would run: the Pi 5 has no hardware encoder) fed raw RGB on its stdin and writing a
//! fragmented MP4 (what a recording that may be killed writes). Its CPU comes from the kernel's
//! accounting of the finished child; the video is decoded back to count its frames and to
//! measure its fidelity (PSNR against the rendered frames) and its decoding cost, which training
//! pays on every epoch.

use anyhow::{bail, Context, Result};
use clap::Args;
use sim::camera::Scene;
use sim::{RobotDescription, SimBus};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

/// Options of `nori bench video-encode`.
#[derive(Args, Debug)]
pub struct VideoEncodeArgs {
    /// Frames to encode per candidate.
    #[arg(long, default_value_t = 300)]
    frames: usize,
    /// Distinct frames rendered (the clip is looped to `frames`).
    #[arg(long, default_value_t = 60)]
    distinct: usize,
    /// The camera whose view is encoded.
    #[arg(long, default_value = "head")]
    camera: String,
    /// Image width, px.
    #[arg(long, default_value_t = 1280)]
    width: u32,
    /// Image height, px.
    #[arg(long, default_value_t = 720)]
    height: u32,
    /// Frames per second.
    #[arg(long, default_value_t = 30)]
    fps: u32,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

/// The candidates: a name and FFmpeg's output options. The first is the baseline. `copy` keeps
/// the camera's own MJPEG (the frames JPEG-encoded first, as a UVC camera sends them: that work
/// is the camera's, not timed).
const CANDIDATES: &[(&str, &[&str])] = &[
    (
        "LeRobot's default: libsvtav1 preset 12, crf 30, g 2",
        &[
            "-c:v",
            "libsvtav1",
            "-preset",
            "12",
            "-crf",
            "30",
            "-g",
            "2",
        ],
    ),
    (
        "libsvtav1 preset 12, crf 30, g 30",
        &[
            "-c:v",
            "libsvtav1",
            "-preset",
            "12",
            "-crf",
            "30",
            "-g",
            "30",
        ],
    ),
    (
        "libx264 ultrafast, crf 23, g 30, no B-frames",
        &[
            "-c:v",
            "libx264",
            "-preset",
            "ultrafast",
            "-crf",
            "23",
            "-g",
            "30",
            "-bf",
            "0",
        ],
    ),
    (
        "libx264 veryfast, crf 23, g 30, no B-frames",
        &[
            "-c:v", "libx264", "-preset", "veryfast", "-crf", "23", "-g", "30", "-bf", "0",
        ],
    ),
    ("the camera's MJPEG, stream copy", &["-c:v", "copy"]),
];

/// JPEG quality of the simulated cameras' MJPEG (as `sim::camera` sends it).
const CAMERA_JPEG_QUALITY: u8 = 85;

fn jpeg(rgb: &[u8], width: u32, height: u32) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    jpeg_encoder::Encoder::new(&mut out, CAMERA_JPEG_QUALITY)
        .encode(
            rgb,
            width as u16,
            height as u16,
            jpeg_encoder::ColorType::Rgb,
        )
        .context("encoding a camera frame")?;
    Ok(out)
}

/// The clip: `n` views of the moving arm, RGB24.
fn render_clip(args: &VideoEncodeArgs) -> Result<Vec<Vec<u8>>> {
    let mut robot = RobotDescription::nori_a3();
    let Some(camera) = robot.camera.iter_mut().find(|c| c.name == args.camera) else {
        bail!("the A3 has no camera {:?}", args.camera);
    };
    (camera.width, camera.height, camera.fps) = (args.width, args.height, args.fps);
    let camera = camera.clone();
    let mut scene = Scene::new(&robot);
    let mut buses: Vec<SimBus> = robot.bus.iter().map(|b| SimBus::new(&robot, b)).collect();
    let mut clip = Vec::with_capacity(args.distinct);
    for k in 0..args.distinct.max(1) {
        let phase = std::f64::consts::TAU * k as f64 / args.distinct.max(1) as f64;
        if let Some(left) = buses.iter_mut().find(|b| b.name == "left_arm") {
            // Shoulder forward and back, elbow bending: the arm sweeps over the table.
            for (id, angle) in [(1, -0.6 + 0.4 * phase.sin()), (4, -0.9 + 0.5 * phase.cos())] {
                if let Some(servo) = left.servo_mut(id) {
                    servo.angle = angle;
                }
            }
        }
        scene.pose(&buses);
        let mut rgb = vec![0u8; camera::convert::rgb_len(args.width, args.height)];
        scene.render(&camera, &mut rgb);
        clip.push(rgb);
    }
    Ok(clip)
}

/// CPU time (user + system) of this process's waited-for children so far, s.
fn children_cpu_s() -> f64 {
    use nix::sys::resource::{getrusage, UsageWho};
    getrusage(UsageWho::RUSAGE_CHILDREN).map_or(0.0, |u| {
        let t = |tv: nix::sys::time::TimeVal| tv.tv_sec() as f64 + tv.tv_usec() as f64 * 1e-6;
        t(u.user_time()) + t(u.system_time())
    })
}

/// One candidate's figures.
struct Encoded {
    wall_s: f64,
    cpu_s: f64,
    bytes: u64,
    decoded_frames: usize,
    decode_cpu_s: f64,
    psnr_db: f64,
}

fn ffmpeg() -> Command {
    let mut c = Command::new("ffmpeg");
    c.args(["-hide_banner", "-loglevel", "error", "-nostdin", "-y"]);
    c
}

fn encode(
    args: &VideoEncodeArgs,
    clip: &[Vec<u8>],
    jpegs: &[Vec<u8>],
    codec: &[&str],
    out: &Path,
) -> Result<Encoded> {
    let size = format!("{}x{}", args.width, args.height);
    let copy = codec.contains(&"copy");
    let input: Vec<&str> = if copy {
        vec!["-f", "mjpeg"]
    } else {
        vec!["-f", "rawvideo", "-pix_fmt", "rgb24", "-s", &size]
    };
    let pix_fmt: &[&str] = if copy { &[] } else { &["-pix_fmt", "yuv420p"] };
    let cpu_before = children_cpu_s();
    let started = Instant::now();
    let mut child = Command::new("ffmpeg")
        .args(["-hide_banner", "-loglevel", "error", "-y"])
        .args(&input)
        .args(["-r", &args.fps.to_string(), "-i", "-"])
        .args(codec)
        .args(pix_fmt)
        .args(["-movflags", "+frag_keyframe+empty_moov+default_base_moof"])
        .arg(out)
        .stdin(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .context(
            "starting ffmpeg (apt install ffmpeg; deploy/install-build-deps.sh installs it)",
        )?;
    let mut stdin = child.stdin.take().context("ffmpeg's stdin")?;
    for i in 0..args.frames {
        let frame = if copy {
            &jpegs[i % jpegs.len()]
        } else {
            &clip[i % clip.len()]
        };
        stdin.write_all(frame).context("feeding ffmpeg")?;
    }
    drop(stdin);
    let result = child.wait_with_output().context("waiting for ffmpeg")?;
    let wall_s = started.elapsed().as_secs_f64();
    let cpu_s = children_cpu_s() - cpu_before;
    if !result.status.success() {
        bail!(
            "ffmpeg {}: {}",
            codec.join(" "),
            String::from_utf8_lossy(&result.stderr)
        );
    }
    let bytes = std::fs::metadata(out)?.len();
    // Decoded back as training would read it: every frame, RGB.
    let cpu_before = children_cpu_s();
    let mut decoder = ffmpeg()
        .arg("-i")
        .arg(out)
        .args(["-f", "rawvideo", "-pix_fmt", "rgb24", "-"])
        .stdout(Stdio::piped())
        .spawn()
        .context("starting ffmpeg to decode")?;
    let mut stdout = decoder.stdout.take().context("ffmpeg's stdout")?;
    let frame_len = clip[0].len();
    let mut frame = vec![0u8; frame_len];
    let (mut decoded_frames, mut mse_sum) = (0usize, 0.0f64);
    while stdout.read_exact(&mut frame).is_ok() {
        let original = &clip[decoded_frames % clip.len()];
        let se: u64 = frame
            .iter()
            .zip(original)
            .map(|(&a, &b)| u64::from(a.abs_diff(b)).pow(2))
            .sum();
        mse_sum += se as f64 / frame_len as f64;
        decoded_frames += 1;
    }
    decoder.wait().context("waiting for the decoder")?;
    let decode_cpu_s = children_cpu_s() - cpu_before;
    let mse = mse_sum / decoded_frames.max(1) as f64;
    let psnr_db = if mse > 0.0 {
        10.0 * (255.0f64 * 255.0 / mse).log10()
    } else {
        f64::INFINITY
    };
    Ok(Encoded {
        wall_s,
        cpu_s,
        bytes,
        decoded_frames,
        decode_cpu_s,
        psnr_db,
    })
}

pub fn run(args: &VideoEncodeArgs) -> Result<()> {
    if args.frames == 0 || args.fps == 0 {
        bail!("--frames and --fps must be positive");
    }
    let t0 = Instant::now();
    let clip = render_clip(args)?;
    let jpegs = clip
        .iter()
        .map(|rgb| jpeg(rgb, args.width, args.height))
        .collect::<Result<Vec<_>>>()?;
    let render_s = t0.elapsed().as_secs_f64();
    let dir: PathBuf =
        std::env::temp_dir().join(format!("nori-bench-video-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let mut rows = Vec::new();
    for (i, (name, codec)) in CANDIDATES.iter().enumerate() {
        let e = encode(
            args,
            &clip,
            &jpegs,
            codec,
            &dir.join(format!("candidate-{i}.mp4")),
        )?;
        rows.push((name, e));
    }
    let _ = std::fs::remove_dir_all(&dir);
    let frames = args.frames as f64;
    let seconds_of_video = frames / f64::from(args.fps);
    let baseline_cpu = rows[0].1.cpu_s;
    let figures: Vec<serde_json::Value> = rows
        .iter()
        .map(|(name, e)| {
            serde_json::json!({
                "candidate": name,
                "encode_fps": frames / e.wall_s.max(1e-9),
                "encode_cpu_ms_per_frame": 1e3 * e.cpu_s / frames,
                "cores_for_4_cameras": 4.0 * e.cpu_s / seconds_of_video,
                "cpu_ratio_to_lerobot_default": e.cpu_s / baseline_cpu.max(1e-9),
                "mb_per_camera_minute": e.bytes as f64 / 1e6 * 60.0 / seconds_of_video,
                "decoded_frames": e.decoded_frames,
                "decode_cpu_ms_per_frame": 1e3 * e.decode_cpu_s / e.decoded_frames.max(1) as f64,
                "psnr_db": e.psnr_db,
            })
        })
        .collect();
    for (f, (name, e)) in figures.iter().zip(&rows) {
        if e.decoded_frames != args.frames {
            bail!(
                "{name}: {} frames decoded of {} encoded: {f}",
                e.decoded_frames,
                args.frames
            );
        }
    }
    let out = serde_json::json!({
        "camera": args.camera, "width": args.width, "height": args.height, "fps": args.fps,
        "frames": args.frames, "distinct_frames": clip.len(), "render_s": render_s,
        "candidates": figures,
    });
    if args.json {
        println!("{out}");
        return Ok(());
    }
    println!(
        "{} frames of the {} camera ({}×{} at {} fps, {} distinct, the left arm sweeping), each candidate FFmpeg writing a fragmented MP4 from raw RGB:",
        args.frames, args.camera, args.width, args.height, args.fps, clip.len()
    );
    for f in &figures {
        println!(
            "  {}: {:.0} frames/s, {:.1} ms of CPU a frame ({:.2} cores for 4 cameras at {} fps; ×{:.2} LeRobot's default), {:.1} MB per camera-minute, PSNR {:.1} dB, decoding {:.2} ms a frame",
            f["candidate"].as_str().unwrap_or_default(),
            f["encode_fps"].as_f64().unwrap_or(f64::NAN),
            f["encode_cpu_ms_per_frame"].as_f64().unwrap_or(f64::NAN),
            f["cores_for_4_cameras"].as_f64().unwrap_or(f64::NAN),
            args.fps,
            f["cpu_ratio_to_lerobot_default"].as_f64().unwrap_or(f64::NAN),
            f["mb_per_camera_minute"].as_f64().unwrap_or(f64::NAN),
            f["psnr_db"].as_f64().unwrap_or(f64::NAN),
            f["decode_cpu_ms_per_frame"].as_f64().unwrap_or(f64::NAN),
        );
    }
    Ok(())
}
