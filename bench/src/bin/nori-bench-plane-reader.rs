//! `nori-bench-plane-reader`: the reading process of `nori bench state-plane` and `nori bench
//! camera-frame` (started by them, not by hand). Records each frame's latency (receive time minus
//! the send time on the shared CLOCK_MONOTONIC), prints "ready" once listening, then one JSON
//! line of results.

use anyhow::{Context, Result};
use bench::Transport;
use camera::stream::StreamReader;
use clap::Parser;
use std::io::Read;
use std::os::unix::net::{UnixDatagram, UnixListener};
use std::path::PathBuf;
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::plane::{self, next, CameraStream, Plane};
use telemetry::stats::quantile_sorted;
use telemetry::JointState;

/// The reader of `nori bench state-plane`.
#[derive(Parser, Debug)]
#[command(name = "nori-bench-plane-reader", version)]
struct PeerArgs {
    /// Transport to read.
    #[arg(long, value_enum)]
    transport: Transport,
    /// iceoryx2 domain.
    #[arg(long)]
    domain: String,
    /// Socket path (uds).
    #[arg(long)]
    socket: PathBuf,
    /// Frames to expect (the last one, seq = frames, ends the run).
    #[arg(long)]
    frames: u64,
    /// Read camera frames of this many bytes (the plane's camera service `bench`, or the camera
    /// stream framing on a Unix stream socket) instead of joint-state frames.
    #[arg(long)]
    camera_bytes: Option<usize>,
}

fn main() -> Result<()> {
    let args = &PeerArgs::parse();
    let latencies = match args.camera_bytes {
        Some(bytes) => read_camera_frames(args, bytes)?,
        None => read_joint_states(args)?,
    };
    let mut us: Vec<f64> = latencies.iter().map(|&ns| ns as f64 / 1e3).collect();
    us.sort_by(f64::total_cmp);
    let out = serde_json::json!({
        "received": us.len(),
        "p50_us": quantile_sorted(&us, 0.5),
        "p99_us": quantile_sorted(&us, 0.99),
        "max_us": quantile_sorted(&us, 1.0),
    });
    println!("{out}");
    Ok(())
}

/// Latencies of camera frames, ns. The reader reads one byte of each 4 KiB page of the image, as
/// a consumer that uses it must at least map it (the socket's copy has touched every byte).
fn read_camera_frames(args: &PeerArgs, bytes: usize) -> Result<Vec<u64>> {
    let mut latencies = Vec::with_capacity(args.frames as usize);
    let mut checksum = 0u64;
    let mut touch = |image: &[u8]| {
        checksum = image
            .iter()
            .step_by(4096)
            .fold(checksum, |a, &b| a.wrapping_add(u64::from(b)));
    };
    let deadline = Instant::now() + Duration::from_secs(600);
    match args.transport {
        Transport::Iceoryx2 => {
            let node = Plane::open(&args.domain, "bench-reader")?;
            let sub = node.camera_subscriber("bench", CameraStream::Rgb)?;
            println!("ready");
            while Instant::now() < deadline {
                match sub.receive() {
                    Ok(Some(sample)) => {
                        touch(sample.payload());
                        let h = sample.user_header();
                        latencies.push(monotonic_ns().saturating_sub(h.publish_ns));
                        if h.seq + 1 >= args.frames {
                            break;
                        }
                    }
                    _ => std::hint::spin_loop(),
                }
            }
        }
        Transport::Uds => {
            let _ = std::fs::remove_file(&args.socket);
            let listener = UnixListener::bind(&args.socket).context("binding the socket")?;
            println!("ready");
            let (mut stream, _) = listener.accept().context("accepting the writer")?;
            let mut reader = StreamReader::new(bytes);
            let mut chunk = vec![0u8; 1 << 20];
            'frames: while Instant::now() < deadline {
                let n = stream.read(&mut chunk).context("receiving")?;
                if n == 0 {
                    break;
                }
                reader.push(&chunk[..n]);
                while let Some((h, image)) = reader.next_frame() {
                    touch(image);
                    latencies.push(monotonic_ns().saturating_sub(h.capture_ns));
                    if u64::from(h.sequence) + 1 >= args.frames {
                        break 'frames;
                    }
                }
            }
            let _ = std::fs::remove_file(&args.socket);
        }
    }
    // Keep the reads.
    std::hint::black_box(checksum);
    Ok(latencies)
}

/// Latencies of joint-state frames, ns.
fn read_joint_states(args: &PeerArgs) -> Result<Vec<u64>> {
    let mut latencies: Vec<u64> = Vec::with_capacity(args.frames as usize);
    let mut last_seq = 0;
    let record = |state: &JointState, latencies: &mut Vec<u64>, last_seq: &mut u64| {
        latencies.push(monotonic_ns().saturating_sub(state.timestamp_ns));
        *last_seq = state.seq;
    };
    match args.transport {
        Transport::Iceoryx2 => {
            let node = Plane::open(&args.domain, "bench-reader")?;
            let sub = node.subscriber(&plane::JOINT_STATE)?;
            println!("ready");
            let deadline = Instant::now() + Duration::from_secs(600);
            while last_seq < args.frames && Instant::now() < deadline {
                match next(&sub) {
                    Some(s) => record(&s, &mut latencies, &mut last_seq),
                    // Spin, as a reader on its own core does (the Pi has four); yielding
                    // instead measured a worse tail on a two-core machine.
                    None => std::hint::spin_loop(),
                }
            }
        }
        Transport::Uds => {
            let _ = std::fs::remove_file(&args.socket);
            let socket = UnixDatagram::bind(&args.socket).context("binding the socket")?;
            socket.set_read_timeout(Some(Duration::from_secs(5)))?;
            println!("ready");
            let mut buf = [0u8; 2048];
            while last_seq < args.frames {
                let n = socket.recv(&mut buf).context("receiving (timed out?)")?;
                let state: JointState = postcard::from_bytes(&buf[..n]).context("decoding")?;
                record(&state, &mut latencies, &mut last_seq);
            }
            let _ = std::fs::remove_file(&args.socket);
        }
    }
    Ok(latencies)
}
