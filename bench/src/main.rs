//! `nori-bench` (`nori bench`): benchmarks that print their figures next to the baseline they
//! are judged by, measured in the same run (this machine is shared and noisy: ratios, not
//! absolute times). No timing threshold lives in a test; these are run by hand and recorded in
//! BENCHMARKS.md with the command that gave each figure.

mod base;
mod blackbox;
mod cameras;
mod driver;
mod fleet;
mod fleet_store;
mod ik;
mod lab;
mod lidar;
mod model_lab;
mod plane;
mod record;
mod video;

use anyhow::Result;
use clap::Parser;

#[derive(Parser, Debug)]
#[command(
    name = "nori-bench",
    version,
    about = "Benchmarks of the Nori A3 stack, each next to its baseline"
)]
enum Bench {
    /// The driver's loop rate against the wire-timed simulator, as a ratio of the wire-limited rate.
    DriverRate(driver::DriverRateArgs),
    /// Batch-mode simulation speed as a multiple of real time.
    SimSpeed(driver::SimSpeedArgs),
    /// Driver → supervisor latency: iceoryx2 against a Unix socket + postcard baseline.
    StatePlane(plane::StatePlaneArgs),
    /// Camera frame latency (2.7 MB at 720p): iceoryx2 zero-copy against a Unix stream socket
    /// copy.
    CameraFrame(plane::CameraFrameArgs),
    /// A policy's action on zenoh to the goal on the simulated wire, through the fleet agent,
    /// against a goal published straight on the state plane.
    ActionLatency(fleet::ActionLatencyArgs),
    /// A key press in Nori Lab's page (headless Chromium) to the goal on the simulated wire,
    /// against a goal published straight on the state plane; the driver's rate with the lab.
    LabLatency(lab::LabLatencyArgs),
    /// An observation to the goal computed from it on the simulated wire, through a policy
    /// server: Python (`nori_client`) against the Rust reference in the same run.
    PolicyLatency(fleet::PolicyLatencyArgs),
    /// Robots streaming telemetry that one fleet collector ingests with no loss.
    FleetIngest(fleet::FleetIngestArgs),
    /// A fleet's backlog of events through the history store, against the same rows inserted
    /// straight into its database.
    FleetStore(fleet_store::FleetStoreArgs),
    /// Camera frames to a LeRobot video per codec (FFmpeg), against LeRobot's default encoder
    /// in the same run: CPU, size, fidelity, decoding cost.
    VideoEncode(video::VideoEncodeArgs),
    /// Recording the cameras (`nori record --camera`): the recorder's and its FFmpegs' CPU and
    /// memory, against the cameras streaming with nobody recording, in the same run.
    RecordVideo(record::RecordVideoArgs),
    /// The arm's inverse kinematics over random reachable targets, against the plain damped
    /// least squares on the same targets.
    Ik(ik::IkArgs),
    /// The model lab: accuracy per hidden effect, detection limits, analysis time (also `nori
    /// model bench`).
    ModelLab(model_lab::BenchArgs),
}

fn main() -> Result<()> {
    match &Bench::parse() {
        Bench::DriverRate(a) => driver::driver_rate(a),
        Bench::SimSpeed(a) => driver::sim_speed(a),
        Bench::StatePlane(a) => plane::run(a),
        Bench::CameraFrame(a) => plane::camera_frame(a),
        Bench::ActionLatency(a) => fleet::action_latency(a),
        Bench::LabLatency(a) => lab::run(a),
        Bench::PolicyLatency(a) => fleet::policy_latency(a),
        Bench::FleetIngest(a) => fleet::fleet_ingest(a),
        Bench::FleetStore(a) => fleet_store::run(a),
        Bench::VideoEncode(a) => video::run(a),
        Bench::RecordVideo(a) => record::run(a),
        Bench::Ik(a) => ik::run(a),
        Bench::ModelLab(a) => model_lab::run_bench(a),
    }
}
