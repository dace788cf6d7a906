//! `nori policy-server`: the reference off-board inference server. It serves every robot that
//! publishes observations on `nori/*/observation`, answering each with an action chunk from a
//! scripted wave or a replayed trajectory (`fleet::policy::ScriptedPolicy`), or, with
//! `--seek-camera`, from what a camera sees (`fleet::seek::ColourSeek`: turn two joints until a
//! coloured object is in the middle of the picture), at most every `--chunk-every-ms`. A Python
//! VLA/ACT server speaks the same schema (docs/fleet-schema.md).

use crate::dashboard::zenoh_error;
use anyhow::{Context, Result};
use clap::Args;
use fleet::policy::{Motion, ScriptedPolicy, Trajectory};
use fleet::seek::{ColourSeek, SeekState};
use fleet_agent::keys::{all_robots, robot_key, robot_of};
use fleet_agent::schema::{decode, encode, ActionChunk, LayoutMsg, ObservationMsg};
use fleet_agent::zenoh::handlers::FifoChannelHandler;
use fleet_agent::zenoh::pubsub::Subscriber;
use fleet_agent::zenoh::qos::{CongestionControl, Priority};
use fleet_agent::zenoh::sample::Sample;
use fleet_agent::zenoh::Session;
use fleet_agent::zenoh::Wait;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// Where `nori policy-server` listens when told nothing: the robots' agents connect here by
/// default.
pub const DEFAULT_LISTEN: &str = "tcp/127.0.0.1:7447";

/// Options of `nori policy-server` (listens on tcp/127.0.0.1:7447 by default).
#[derive(Args, Debug)]
pub struct PolicyServerArgs {
    #[command(flatten)]
    pub zenoh: crate::dashboard::FleetSideArgs,
    /// Joints the wave moves (comma-separated).
    #[arg(long, value_delimiter = ',', default_value = "left_elbow,right_elbow")]
    pub joints: Vec<String>,
    /// Centre of the wave, rad.
    #[arg(long, default_value_t = -0.8, allow_hyphen_values = true)]
    pub centre: f32,
    /// Amplitude, rad.
    #[arg(long, default_value_t = 0.4)]
    pub amplitude: f32,
    /// Period, s.
    #[arg(long, default_value_t = 4.0)]
    pub period_s: f32,
    /// Replay this trajectory instead of the wave: a CSV `t_s,<joint>,<joint>,...` (rad), looped
    /// on each robot's clock.
    #[arg(long, conflicts_with_all = ["joints", "centre", "amplitude", "period_s"])]
    pub replay: Option<PathBuf>,
    /// See instead: centre the object of `--seek-colour` in this camera's picture (the robot's
    /// agent must send it: `[observation] cameras` in fleet-agent.toml).
    #[arg(long, conflicts_with_all = ["replay", "joints", "centre", "amplitude", "period_s"])]
    pub seek_camera: Option<String>,
    /// The object's colour, R,G,B (the simulated scene's red ball by default).
    #[arg(long, value_delimiter = ',', num_args = 3, default_value = "210,30,30")]
    pub seek_colour: Vec<u8>,
    /// The two joints turned to centre it.
    #[arg(
        long,
        value_delimiter = ',',
        num_args = 2,
        default_value = "left_shoulder_roll,left_elbow"
    )]
    pub seek_joints: Vec<String>,
    /// Steps per chunk.
    #[arg(long, default_value_t = 25)]
    pub steps: usize,
    /// Time between steps, ms.
    #[arg(long, default_value_t = 20)]
    pub step_ms: u64,
    /// A robot gets a new chunk at most this often, ms.
    #[arg(long, default_value_t = 100)]
    pub chunk_every_ms: u64,
    /// Stop after this many seconds and print what was served as JSON.
    #[arg(long)]
    pub run_for: Option<f64>,
}

#[derive(Default)]
struct Robot {
    layout: Option<LayoutMsg>,
    last_chunk: Option<Instant>,
    seq: u64,
    observations: u64,
    seek: SeekState,
    /// Seeing: observations with the camera's image in which the object was not found.
    not_seen: u64,
}

/// What the server plays.
enum Serving {
    Scripted(ScriptedPolicy),
    Seeing(ColourSeek),
}

/// Serves until Ctrl-C (or `--run-for`).
pub fn run(args: &PolicyServerArgs) -> Result<()> {
    telemetry::process::init_logging();
    let stop = telemetry::process::stop_flag()?;
    let policy = Serving::from_args(args)?;
    let session = args
        .zenoh
        .open(DEFAULT_LISTEN)
        .context("opening the policy server's zenoh session")?;
    let observations = session
        .declare_subscriber(all_robots("observation"))
        .wait()
        .map_err(zenoh_error)?;
    let layouts = session
        .declare_subscriber(all_robots("layout"))
        .wait()
        .map_err(zenoh_error)?;
    tracing::info!(listen = ?args.zenoh.listen, replay = ?args.replay, joints = ?args.joints, "serving every robot on {}", all_robots("observation"));
    let mut robots: BTreeMap<String, Robot> = BTreeMap::new();
    let every = Duration::from_millis(args.chunk_every_ms);
    let started = Instant::now();
    while !stop.load(Ordering::Relaxed)
        && args
            .run_for
            .is_none_or(|s| started.elapsed().as_secs_f64() < s)
    {
        let layouts_came = take_layouts(&layouts, &mut robots);
        let observations_came =
            serve_observations(&session, &observations, &mut robots, &policy, every)?;
        if !layouts_came && !observations_came {
            std::thread::sleep(Duration::from_millis(1));
        }
    }
    println!("{}", serde_json::json!({ "robots": served(&robots) }));
    Ok(())
}

/// A subscription whose samples are taken when the loop gets to them.
type Queue = Subscriber<FifoChannelHandler<Sample>>;

impl Serving {
    /// What the options say to play: seeing with `--seek-camera`, else the replay or the wave.
    fn from_args(args: &PolicyServerArgs) -> Result<Serving> {
        let motion = match &args.replay {
            Some(path) => {
                let text = std::fs::read_to_string(path)
                    .with_context(|| format!("reading {}", path.display()))?;
                Motion::Replay(
                    Trajectory::parse(&text).with_context(|| format!("{}", path.display()))?,
                )
            }
            None => Motion::Wave {
                joints: args.joints.clone(),
                centre: args.centre,
                amplitude: args.amplitude,
                period_s: args.period_s,
            },
        };
        Ok(match &args.seek_camera {
            Some(camera) => Serving::Seeing(ColourSeek {
                camera: camera.clone(),
                colour: [
                    args.seek_colour[0],
                    args.seek_colour[1],
                    args.seek_colour[2],
                ],
                tolerance: 60,
                joints: [args.seek_joints[0].clone(), args.seek_joints[1].clone()],
                // The picture lags the joints by a capture and up to three observations: a
                // gentle gain keeps the loop from overshooting on old pictures.
                gain: 0.3,
                max_step_rad: 0.06,
                probe_rad: 0.04,
                deadband: 0.05,
                steps: args.steps,
                step_ms: args.step_ms,
            }),
            None => Serving::Scripted(ScriptedPolicy {
                motion,
                steps: args.steps,
                step_ms: args.step_ms,
            }),
        })
    }

    /// The chunk `robot` (`id`) gets for `obs`, if any: none before its layout is known; a
    /// scripted one at most every `every`; a seeing one on each picture of its camera.
    fn chunk(
        &self,
        robot: &mut Robot,
        id: &str,
        obs: &ObservationMsg,
        every: Duration,
    ) -> Option<ActionChunk> {
        let layout = robot.layout.as_ref()?;
        match self {
            Serving::Scripted(p) => {
                if robot.last_chunk.is_some_and(|t| t.elapsed() < every) {
                    return None;
                }
                p.chunk(obs, layout, robot.seq + 1)
            }
            // Every observation that carries the camera's picture: what is learnt from
            // each move needs each picture.
            Serving::Seeing(p) => {
                if !obs.images.iter().any(|i| i.camera == p.camera) {
                    return None;
                }
                let chunk = p.chunk(obs, layout, &mut robot.seek, robot.seq + 1);
                tracing::debug!(robot = id, state = ?robot.seek, "seeing");
                match chunk {
                    Ok(None) => {
                        robot.not_seen += 1;
                        None
                    }
                    Ok(c) => c,
                    Err(e) => {
                        tracing::warn!(robot = id, "{e}");
                        None
                    }
                }
            }
        }
    }
}

/// Takes the layouts that came; true if any did.
fn take_layouts(layouts: &Queue, robots: &mut BTreeMap<String, Robot>) -> bool {
    let mut came = false;
    while let Ok(Some(sample)) = layouts.try_recv() {
        came = true;
        let Some(id) = robot_of(sample.key_expr().as_str()) else {
            continue;
        };
        match decode::<LayoutMsg>(&sample.payload().to_bytes()) {
            Ok(l) => robots.entry(id.into()).or_default().layout = Some(l),
            Err(e) => tracing::warn!(robot = id, "unreadable layout: {e}"),
        }
    }
    came
}

/// Answers the observations that came with the chunks the policy gives; true if any came.
fn serve_observations(
    session: &Session,
    observations: &Queue,
    robots: &mut BTreeMap<String, Robot>,
    policy: &Serving,
    every: Duration,
) -> Result<bool> {
    let mut came = false;
    while let Ok(Some(sample)) = observations.try_recv() {
        came = true;
        let Some(id) = robot_of(sample.key_expr().as_str()) else {
            continue;
        };
        let robot = robots.entry(id.into()).or_default();
        robot.observations += 1;
        let obs = decode::<ObservationMsg>(&sample.payload().to_bytes());
        let Some(chunk) = obs
            .ok()
            .and_then(|obs| policy.chunk(robot, id, &obs, every))
        else {
            continue;
        };
        session
            .put(robot_key(id, "actions"), encode(&chunk))
            .congestion_control(CongestionControl::Drop)
            .priority(Priority::InteractiveHigh)
            .express(true)
            .wait()
            .map_err(zenoh_error)?;
        robot.seq += 1;
        robot.last_chunk = Some(Instant::now());
    }
    Ok(came)
}

/// What each robot was served, for the exit report.
fn served(robots: &BTreeMap<String, Robot>) -> serde_json::Map<String, serde_json::Value> {
    robots
        .iter()
        .map(|(id, r)| {
            (
                id.clone(),
                serde_json::json!({"observations": r.observations, "chunks": r.seq,
                    "seek_calibrated": r.seek.calibrated(), "not_seen": r.not_seen}),
            )
        })
        .collect()
}
