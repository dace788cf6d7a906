//! `nori bench state-plane`: driver → supervisor latency of one joint-state frame, iceoryx2
//! (zero-copy shared memory) side by side with a Unix datagram socket carrying the same frame
//! encoded with postcard, in the same run. The reader is a second process
//! (`nori-bench-plane-reader`); latency is its receive time minus the frame's send time on the shared
//! CLOCK_MONOTONIC.

use anyhow::{bail, Context, Result};
use bench::Transport;
use clap::Args;
use std::io::{BufRead, BufReader};
use std::os::unix::net::UnixDatagram;

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use telemetry::clock::monotonic_ns;
use telemetry::plane::{self, publish, Plane};
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

fn run_one(transport: Transport, args: &StatePlaneArgs) -> Result<serde_json::Value> {
    let pid = std::process::id();
    let domain = format!("nori_bench_{pid}");
    let socket = std::env::temp_dir().join(format!("nori-bench-{pid}.sock"));
    let mut child = Command::new(stack::sibling("nori-bench-plane-reader")?)
        .arg("--transport")
        .arg(format!("{transport:?}").to_lowercase())
        .args(["--domain", &domain, "--socket"])
        .arg(&socket)
        .args(["--frames", &args.frames.to_string()])
        .stdout(Stdio::piped())
        .spawn()
        .context("starting the reader")?;
    let mut lines = BufReader::new(child.stdout.take().context("reader stdout")?).lines();
    if lines.next().transpose()?.as_deref() != Some("ready") {
        bail!("the reader did not start");
    }
    let node = Plane::open(&domain, "bench-writer")?;
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
                Ok(bytes) => out.send_to(bytes, &socket).is_ok(),
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
    let result = lines
        .next()
        .transpose()?
        .context("no result from the reader")?;
    let _ = child.wait();
    let mut v: serde_json::Value = serde_json::from_str(&result)?;
    v["send_errors"] = send_errors.into();
    Ok(v)
}

/// Runs the benchmark.
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
