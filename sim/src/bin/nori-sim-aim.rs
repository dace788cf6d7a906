//! `nori sim aim` (`nori-sim-aim`): the simulated world's ground truth about one camera and one
//! object: where the object is in the camera's picture and how far the arm's tool point is from
//! it, with the arm at `--at`, and (with `--centre`) the angles of two joints that centre it. A
//! scripted demonstrator asks it where to go; an evaluation asks it where a policy left the arm
//! (the joint angles of the simulator's report). Prints JSON.

use anyhow::{anyhow, Context, Result};
use clap::Parser;
use sim::aim::Aim;
use sim::RobotDescription;
use std::collections::BTreeMap;
use std::path::PathBuf;

#[derive(Parser)]
#[command(
    name = "nori-sim-aim",
    version,
    about = "Where an object is in a simulated camera's picture, and how to centre it"
)]
struct Args {
    /// Robot description (TOML); the embedded Nori A3 when absent.
    #[arg(long)]
    description: Option<PathBuf>,
    /// The camera (on an arm).
    #[arg(long)]
    camera: String,
    /// The object, by its name in the description.
    #[arg(long, default_value = "red ball")]
    object: String,
    /// Joint angles of the arm, `name=rad` (repeatable or comma-separated); others at 0.
    #[arg(long, value_delimiter = ',')]
    at: Vec<String>,
    /// Two joints to turn (from `--at`) until the object is at the picture's centre.
    #[arg(long, value_delimiter = ',')]
    centre: Option<Vec<String>>,
}

fn main() -> Result<()> {
    let args = Args::parse();
    let robot = match &args.description {
        Some(p) => RobotDescription::load(p).with_context(|| format!("loading {}", p.display()))?,
        None => RobotDescription::nori_a3(),
    };
    let mut at = BTreeMap::new();
    for pair in &args.at {
        let (name, value) = pair
            .split_once('=')
            .ok_or_else(|| anyhow!("--at {pair:?}: use name=rad"))?;
        let value: f64 = value
            .parse()
            .with_context(|| format!("--at {pair:?}: {value:?} is not a number"))?;
        at.insert(name.to_string(), value);
    }
    let mut aim = Aim::new(&robot, &args.camera, &args.object)?;
    let mut out = serde_json::json!({
        "offset": aim.offset(&at),
        "tip_distance_m": aim.tip_distance(&at),
    });
    if let Some(joints) = &args.centre {
        if joints.len() != 2 {
            return Err(anyhow!("--centre {joints:?}: name two joints, a,b"));
        }
        let centred = aim.centre(&at, [&joints[0], &joints[1]])?;
        out["centre"] = serde_json::json!({
            "at": joints.iter().map(|j| (j.clone(), centred[j])).collect::<BTreeMap<_, _>>(),
            "offset": aim.offset(&centred),
            "tip_distance_m": aim.tip_distance(&centred),
        });
    }
    println!("{out}");
    Ok(())
}
