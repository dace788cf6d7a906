//! `nori bench state-plane`: driver → supervisor latency of one joint-state frame, iceoryx2
//! (zero-copy shared memory) side by side with a Unix datagram socket carrying the same frame
//! encoded with postcard, in the same run. The reader is a second process
//! (`nori-bench-plane-reader`); latency is its receive time minus the frame's send time on the shared
//! CLOCK_MONOTONIC.

use anyhow::{bail, Context, Result};
use bench::Transport;
use camera::stream::StreamHeader;
use clap::Args;
use std::io::{BufRead, BufReader, Lines, Write};
use std::os::unix::net::{UnixDatagram, UnixStream};
use std::path::PathBuf;
use std::process::{Child, ChildStdout, Command, Stdio};
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::plane::{self, publish, CameraStream, Plane};
use telemetry::sensors::{CameraFrameHeader, PixelFormat};
use telemetry::JointState;

/// Options of `nori bench state-plane`.
#[derive(Args, Debug)]
pub struct StatePlaneArgs {
    /// Frames per transport.
    #[arg(long, default_value_t = 100_000)]
    frames: u64,
    /// Send rate, Hz.
    #[arg(long, default_value_t = 2000.0)]
    rate_hz: f64,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

/// The reading process, started and listening.
struct Reader {
    child: Child,
    lines: Lines<BufReader<ChildStdout>>,
    domain: String,
    socket: PathBuf,
}

impl Reader {
    /// Starts `nori-bench-plane-reader` on `transport` for `frames` frames (camera frames of
    /// `camera_bytes` when given), and waits until it listens.
    fn start(transport: Transport, frames: u64, camera_bytes: Option<usize>) -> Result<Self> {
        let pid = std::process::id();
        let domain = format!("nori_bench_{pid}");
        let socket = std::env::temp_dir().join(format!("nori-bench-{pid}.sock"));
        let mut command = Command::new(stack::sibling("nori-bench-plane-reader")?);
        command
            .arg("--transport")
            .arg(format!("{transport:?}").to_lowercase())
            .args(["--domain", &domain, "--socket"])
            .arg(&socket)
            .args(["--frames", &frames.to_string()]);
        if let Some(bytes) = camera_bytes {
            command.args(["--camera-bytes", &bytes.to_string()]);
        }
        let mut child = command
            .stdout(Stdio::piped())
            .spawn()
            .context("starting the reader")?;
        let mut lines = BufReader::new(child.stdout.take().context("reader stdout")?).lines();
        if lines.next().transpose()?.as_deref() != Some("ready") {
            bail!("the reader did not start");
        }
        Ok(Reader {
            child,
            lines,
            domain,
            socket,
        })
    }

    /// The reader's figures, with the writer's send errors.
    fn finish(mut self, send_errors: u64) -> Result<serde_json::Value> {
        let result = self
            .lines
            .next()
            .transpose()?
            .context("no result from the reader")?;
        let _ = self.child.wait();
        let mut v: serde_json::Value = serde_json::from_str(&result)?;
        v["send_errors"] = send_errors.into();
        Ok(v)
    }
}

fn run_one(transport: Transport, args: &StatePlaneArgs) -> Result<serde_json::Value> {
    let reader = Reader::start(transport, args.frames, None)?;
    let (domain, socket) = (&reader.domain, &reader.socket);
    let node = Plane::open(domain, "bench-writer")?;
    let publisher = node.publisher(&plane::JOINT_STATE)?;
    let out = UnixDatagram::unbound()?;
    let mut state = JointState {
        joint_count: 18,
        ..JointState::default()
    };
    let mut buf = [0u8; 2048];
    // Let the reader's subscriber connect before the first frame.
    std::thread::sleep(Duration::from_millis(200));
    let period = Duration::from_secs_f64(1.0 / args.rate_hz);
    let mut next_send = Instant::now();
    let mut send_errors = 0u64;
    for seq in 1..=args.frames {
        state.seq = seq;
        state.timestamp_ns = monotonic_ns();
        let sent = match transport {
            Transport::Iceoryx2 => publish(&publisher, &state).is_ok(),
            Transport::Uds => match postcard::to_slice(&state, &mut buf) {
                Ok(bytes) => out.send_to(bytes, socket).is_ok(),
                Err(_) => false,
            },
        };
        if !sent {
            send_errors += 1;
        }
        next_send += period;
        if let Some(wait) = next_send.checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
    }
    reader.finish(send_errors)
}

/// Runs `nori bench state-plane`.
pub fn run(args: &StatePlaneArgs) -> Result<()> {
    let size = std::mem::size_of::<JointState>();
    let mut buf = [0u8; 2048];
    let encoded = postcard::to_slice(&JointState::default(), &mut buf)
        .map(|b| b.len())
        .unwrap_or(0);
    let ice = run_one(Transport::Iceoryx2, args)?;
    let uds = run_one(Transport::Uds, args)?;
    let ratio = |k: &str| ice[k].as_f64().unwrap_or(f64::NAN) / uds[k].as_f64().unwrap_or(f64::NAN);
    let out = serde_json::json!({
        "frame_bytes": size,
        "postcard_bytes": encoded,
        "frames": args.frames,
        "rate_hz": args.rate_hz,
        "iceoryx2": ice,
        "uds_postcard": uds,
        "iceoryx2_p50_us": ice["p50_us"],
        "iceoryx2_p99_us": ice["p99_us"],
        "uds_p50_us": uds["p50_us"],
        "uds_p99_us": uds["p99_us"],
        "p50_ratio": ratio("p50_us"),
        "p99_ratio": ratio("p99_us"),
        "reader": "iceoryx2 reader spins on receive(); UDS reader blocks in recv",
    });
    if args.json {
        println!("{out}");
    } else {
        println!(
            "joint-state frame ({size} B; {encoded} B postcard), {} frames at {} Hz, second process:\n  iceoryx2      p50 {:>7.1} µs  p99 {:>7.1} µs  max {:>8.1} µs\n  UDS+postcard  p50 {:>7.1} µs  p99 {:>7.1} µs  max {:>8.1} µs\n  ratio iceoryx2/UDS: p50 {:.2}, p99 {:.2}",
            args.frames,
            args.rate_hz,
            ice["p50_us"].as_f64().unwrap_or(f64::NAN),
            ice["p99_us"].as_f64().unwrap_or(f64::NAN),
            ice["max_us"].as_f64().unwrap_or(f64::NAN),
            uds["p50_us"].as_f64().unwrap_or(f64::NAN),
            uds["p99_us"].as_f64().unwrap_or(f64::NAN),
            uds["max_us"].as_f64().unwrap_or(f64::NAN),
            ratio("p50_us"),
            ratio("p99_us")
        );
    }
    Ok(())
}

/// Options of `nori bench camera-frame`.
#[derive(Args, Debug)]
pub struct CameraFrameArgs {
    /// Frames per transport.
    #[arg(long, default_value_t = 300)]
    frames: u64,
    /// Frame rate, Hz.
    #[arg(long, default_value_t = 30.0)]
    rate_hz: f64,
    /// Image width, px (RGB24).
    #[arg(long, default_value_t = 1280)]
    width: u32,
    /// Image height, px.
    #[arg(long, default_value_t = 720)]
    height: u32,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

/// Sends `args.frames` camera frames of `image` over `transport`; the image is written into
/// the sample (iceoryx2: what the camera's decoder does) or into the socket (a copy through the
/// kernel), and its send time is taken once it is whole in the writer's memory.
fn camera_one(
    transport: Transport,
    args: &CameraFrameArgs,
    image: &[u8],
) -> Result<serde_json::Value> {
    let reader = Reader::start(transport, args.frames, Some(image.len()))?;
    let node = Plane::open(&reader.domain, "bench-writer")?;
    let publisher = node.camera_publisher("bench", CameraStream::Rgb, image.len())?;
    let mut socket = match transport {
        Transport::Uds => Some(UnixStream::connect(&reader.socket).context("connecting")?),
        Transport::Iceoryx2 => None,
    };
    // Let the reader's subscriber connect before the first frame.
    std::thread::sleep(Duration::from_millis(200));
    let period = Duration::from_secs_f64(1.0 / args.rate_hz);
    let mut next_send = Instant::now();
    let mut send_errors = 0u64;
    for seq in 0..args.frames {
        let sent = match socket.as_mut() {
            None => match publisher.loan_slice_uninit(image.len()) {
                Ok(sample) => {
                    let mut sample = sample.write_from_slice(image);
                    *sample.user_header_mut() = CameraFrameHeader {
                        seq,
                        publish_ns: monotonic_ns(),
                        ..CameraFrameHeader::default()
                    };
                    sample.send().is_ok()
                }
                Err(_) => false,
            },
            Some(out) => {
                let header = StreamHeader {
                    fourcc: PixelFormat::Rgb24.fourcc(),
                    width: args.width,
                    height: args.height,
                    sequence: seq as u32,
                    len: image.len() as u32,
                    capture_ns: monotonic_ns(),
                };
                out.write_all(&header.encode())
                    .and_then(|()| out.write_all(image))
                    .is_ok()
            }
        };
        if !sent {
            send_errors += 1;
        }
        next_send += period;
        if let Some(wait) = next_send.checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
    }
    drop(socket);
    reader.finish(send_errors)
}

/// Runs `nori bench camera-frame`.
pub fn camera_frame(args: &CameraFrameArgs) -> Result<()> {
    let bytes = camera::convert::rgb_len(args.width, args.height);
    // A picture, not zeros: pages of zeros could be shared or compressed away.
    let image: Vec<u8> = (0..bytes).map(|i| (i * 31 % 251) as u8).collect();
    let ice = camera_one(Transport::Iceoryx2, args, &image)?;
    let uds = camera_one(Transport::Uds, args, &image)?;
    let ratio = |k: &str| ice[k].as_f64().unwrap_or(f64::NAN) / uds[k].as_f64().unwrap_or(f64::NAN);
    let (thumb_us, copy_us, thumb_bytes) = thumbnail_cost(args, &image)?;
    let out = serde_json::json!({
        "frame_bytes": bytes,
        "frames": args.frames,
        "rate_hz": args.rate_hz,
        "iceoryx2": ice,
        "uds_stream_copy": uds,
        "p50_ratio": ratio("p50_us"),
        "p99_ratio": ratio("p99_us"),
        "reader": "second process; reads one byte of each 4 KiB page of every frame; iceoryx2 reader spins on receive(), the socket reader blocks in read",
        "fleet_thumbnail_us": thumb_us,
        "frame_copy_us": copy_us,
        "thumbnail_ratio": thumb_us / copy_us,
        "thumbnail_bytes": thumb_bytes,
    });
    if args.json {
        println!("{out}");
    } else {
        let f = |v: &serde_json::Value, k: &str| v[k].as_f64().unwrap_or(f64::NAN);
        println!(
            "camera frame {}×{} RGB ({bytes} B), {} frames at {} Hz, second process:\n  iceoryx2 (zero-copy)     p50 {:>8.1} µs  p99 {:>8.1} µs  max {:>8.1} µs  received {}\n  Unix stream socket copy  p50 {:>8.1} µs  p99 {:>8.1} µs  max {:>8.1} µs  received {}\n  ratio iceoryx2/socket: p50 {:.3}, p99 {:.3}",
            args.width, args.height, args.frames, args.rate_hz,
            f(&ice, "p50_us"), f(&ice, "p99_us"), f(&ice, "max_us"), ice["received"],
            f(&uds, "p50_us"), f(&uds, "p99_us"), f(&uds, "max_us"), uds["received"],
            ratio("p50_us"), ratio("p99_us")
        );
        println!(
            "the fleet agent's thumbnail of one frame (box average to 160 px wide, JPEG, {thumb_bytes} B): {thumb_us:.0} µs, against one copy of the frame: {copy_us:.0} µs (ratio {:.2}); four cameras every 2 s: {:.3} % of a core",
            thumb_us / copy_us,
            4.0 * thumb_us / 2e6 * 100.0
        );
    }
    Ok(())
}

/// The median time of the fleet agent's thumbnail of `image` (defaults: every 2 s per camera,
/// 160 px wide, quality 70) and, as the baseline of the same run, of one copy of the frame;
/// and the thumbnail's size.
fn thumbnail_cost(args: &CameraFrameArgs, image: &[u8]) -> Result<(f64, f64, usize)> {
    let mut header = telemetry::sensors::CameraFrameHeader {
        fourcc: telemetry::sensors::PixelFormat::Rgb24.fourcc(),
        width: args.width,
        height: args.height,
        stride: args.width * 3,
        ..Default::default()
    };
    header.set_camera("bench");
    let mut thumbnailer = camera::thumbnail::Thumbnailer::new(160, 70);
    let mut copy = vec![0u8; image.len()];
    let (mut thumb, mut copied, mut bytes) = (Vec::new(), Vec::new(), 0);
    for _ in 0..41 {
        let t = Instant::now();
        bytes = thumbnailer.make(&header, image)?.0.len();
        thumb.push(t.elapsed().as_secs_f64() * 1e6);
        let t = Instant::now();
        copy.copy_from_slice(image);
        std::hint::black_box(&copy);
        copied.push(t.elapsed().as_secs_f64() * 1e6);
    }
    Ok((
        telemetry::stats::quantile(&thumb, 0.5),
        telemetry::stats::quantile(&copied, 0.5),
        bytes,
    ))
}
