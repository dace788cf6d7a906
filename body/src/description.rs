//! The robot description file: servo ratings, buses, arm kinematics, grippers, obstacles.
//!
//! TOML with kebab-case keys; unknown keys are refused. The A3's description is embedded
//! ([`RobotDescription::nori_a3`]) so the simulator runs with no file at all.

use feetech::ServoModel;
use serde::Deserialize;
use std::collections::{BTreeMap, HashSet};
use std::path::Path;
use thiserror::Error;

/// The A3's description, as shipped.
pub const NORI_A3_TOML: &str = include_str!("../robots/nori-a3.toml");

/// A description that cannot be used.
#[derive(Debug, Error)]
#[allow(missing_docs, reason = "each field is shown in its variant's message")]
pub enum DescriptionError {
    /// The file could not be read.
    #[error("cannot read robot description {path}: {source}")]
    Io {
        /// File path.
        path: String,
        source: std::io::Error,
    },
    /// TOML syntax, a wrong type or an unknown key (the message names the key and line).
    #[error("robot description {path}: {source}")]
    Parse {
        /// File path.
        path: String,
        source: toml::de::Error,
    },
    /// A value that parses but is physically impossible or inconsistent.
    #[error("robot description {path}: {key}: {reason}")]
    Invalid {
        /// File path.
        path: String,
        /// The offending key.
        key: String,
        reason: String,
    },
}

/// Ratings and identified constants of one servo model.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ServoRating {
    /// The model (from the table key).
    #[serde(skip, default = "default_model")]
    pub model: ServoModel,
    /// Voltage the ratings are given at, V.
    pub rated_voltage: f64,
    /// Stall torque at rated voltage, kg·cm.
    pub stall_torque_kgcm: f64,
    /// Stall current at rated voltage, A.
    pub stall_current_a: f64,
    /// No-load output speed at rated voltage, rad/s.
    pub no_load_speed_rad_s: f64,
    /// Gearbox ratio.
    pub gear_ratio: f64,
    /// Rotor inertia reflected to the output, kg·m².
    pub armature_kgm2: f64,
    /// Coulomb friction at the output, N·m.
    pub coulomb_nm: f64,
    /// Viscous friction at the output, N·m·s/rad.
    pub viscous_nms: f64,
    /// Heat capacity of the one thermal node, J/K.
    pub heat_capacity_j_per_k: f64,
    /// Thermal resistance to ambient, K/W.
    pub thermal_resistance_k_per_w: f64,
    /// Constant electronics loss, W.
    pub idle_power_w: f64,
}

fn default_model() -> ServoModel {
    ServoModel::Sts3215
}

/// One servo on a bus.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ServoDescription {
    /// Bus id.
    pub id: u8,
    /// Joint name.
    pub joint: String,
    /// Key into `servo-models`.
    pub model: String,
    /// Starting angle, rad.
    #[serde(default)]
    pub initial_rad: f64,
}

/// One joint of an arm chain, driven by one servo.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ArmJoint {
    /// Servo id driving the joint.
    pub servo: u8,
    /// Rotation axis in the joint frame (normalised on load).
    pub axis: [f64; 3],
    /// Joint origin in the parent frame, m.
    pub origin: [f64; 3],
    /// Mass of the link the joint moves (up to the next joint), kg.
    pub mass_kg: f64,
    /// Centre of mass of that link in the joint frame, m.
    pub com: [f64; 3],
    /// Mechanical hard stop, rad.
    pub lower_rad: f64,
    /// Mechanical hard stop, rad.
    pub upper_rad: f64,
}

/// The compliant gripper.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct GripperDescription {
    /// Servo id.
    pub servo: u8,
    /// Closed stop (fingers touching), rad.
    pub lower_rad: f64,
    /// Open stop, rad.
    pub upper_rad: f64,
    /// Stiffness of the TPU fingers at the gripper joint, N·m/rad.
    pub finger_stiffness_nm_per_rad: f64,
    /// An object held between the fingers, if any.
    #[serde(default)]
    pub object: Option<GraspObject>,
}

/// An object between the fingers.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct GraspObject {
    /// Gripper angle at first contact, rad.
    pub contact_rad: f64,
    /// The object's own stiffness at the gripper joint, N·m/rad (in series with the fingers).
    pub stiffness_nm_per_rad: f64,
}

/// A sphere in the arm's workspace that links cannot pass through.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct Obstacle {
    /// Centre, m, world frame.
    pub center: [f64; 3],
    /// Radius, m.
    pub radius_m: f64,
    /// Contact stiffness, N/m.
    #[serde(default = "default_obstacle_stiffness")]
    pub stiffness_n_per_m: f64,
}

fn default_obstacle_stiffness() -> f64 {
    20_000.0
}

/// An arm: a serial chain of joints, a tip, a gripper and obstacles.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ArmDescription {
    /// Shoulder position, m, world frame.
    pub base: [f64; 3],
    /// Tool point in the last joint's frame, m.
    pub tip: [f64; 3],
    /// Mass held at the tip, kg.
    #[serde(default)]
    pub payload_kg: f64,
    /// Joints from the base outward.
    pub joint: Vec<ArmJoint>,
    /// Gripper, if fitted.
    #[serde(default)]
    pub gripper: Option<GripperDescription>,
    /// Obstacles in reach.
    #[serde(default)]
    pub obstacle: Vec<Obstacle>,
    /// How the arm calibrates itself (`nori calibrate auto`), if it can.
    #[serde(default)]
    pub calibration: Option<CalibrationPlan>,
}

/// How an arm calibrates itself: the lift's height, the speed, and the joints in the order
/// they are driven toward their stops, each at a low torque while the joints its pose names
/// hold where the pose puts them (docs/commissioning.md).
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct CalibrationPlan {
    /// The lift at least this high, m above its lowest: the straight arm clears a table.
    pub lift_m: f64,
    /// The speed each joint is driven toward its stops, rad/s.
    pub speed_rad_s: f64,
    /// Every joint and the gripper, in the order they are swept.
    pub sweep: Vec<CalibrationSweep>,
}

/// One joint's sweep in a [`CalibrationPlan`].
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct CalibrationSweep {
    /// The joint's servo.
    pub servo: u8,
    /// Its torque limit while swept and held, % of full: above what gravity asks of it in the
    /// pose, and all that presses on a stop.
    pub torque_percent: f64,
    /// Joints swept before it, held at these angles while it is swept.
    #[serde(default)]
    pub pose: Vec<PoseHold>,
}

/// A joint held at an angle.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct PoseHold {
    /// The joint's servo.
    pub servo: u8,
    /// Where it is held, rad.
    pub rad: f64,
}

/// Wheels of the differential base, in speed mode.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct WheelsDescription {
    /// Servo ids.
    pub servos: Vec<u8>,
    /// Inertia each wheel drives, kg·m².
    pub inertia_kgm2: f64,
    /// Rolling resistance, N·m·s/rad.
    pub viscous_nms: f64,
    /// Wheel radius, m (the base moves in the room when given, with `track-m`).
    #[serde(default)]
    pub wheel_radius_m: Option<f64>,
    /// Distance between the two wheels' contact points, m.
    #[serde(default)]
    pub track_m: Option<f64>,
    /// The right wheel's servo is mounted mirrored: its positive speed drives the base
    /// backwards (the left one's drives it forwards).
    #[serde(default)]
    pub right_inverted: bool,
    /// The base's footprint, a rectangle centred on it: length along its heading and width, m.
    /// What bumps into walls and objects.
    #[serde(default = "default_footprint")]
    pub footprint_m: [f64; 2],
    /// Where the base starts in the room: x, y (m), heading (rad, counter-clockwise from +x).
    #[serde(default)]
    pub start: [f64; 3],
}

fn default_footprint() -> [f64; 2] {
    [0.45, 0.45]
}

/// One serial bus.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct BusDescription {
    /// Bus name (also the device name the simulator serves).
    pub name: String,
    /// Line rate, baud.
    pub baud: u32,
    /// Supply voltage, V.
    pub supply_v: f64,
    /// Resistance of the supply and wiring, Ω: the voltage sags by R·ΣI (0 = stiff supply).
    #[serde(default)]
    pub supply_resistance_ohm: f64,
    /// Servos on the bus.
    pub servo: Vec<ServoDescription>,
    /// The arm this bus drives, if any.
    #[serde(default)]
    pub arm: Option<ArmDescription>,
    /// Wheels this bus drives, if any.
    #[serde(default)]
    pub wheels: Option<WheelsDescription>,
}

/// A whole robot.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct RobotDescription {
    /// Robot type.
    pub name: String,
    /// Ambient temperature, °C.
    pub ambient_c: f64,
    /// Gravity, m/s², world frame.
    pub gravity: [f64; 3],
    /// Ratings by model key (`sts3215`, `sts3250`, `sts3095`).
    pub servo_models: BTreeMap<String, ServoRating>,
    /// The servo buses (`[[bus]]` tables): each one's servos and the arm or wheels it drives.
    pub bus: Vec<BusDescription>,
    /// Cameras the simulator renders (served at `<device dir>/camera-<name>`).
    #[serde(default)]
    pub camera: Vec<CameraDescription>,
    /// Things in the room the cameras see (a table, something to reach for); the lidar sees
    /// those that cross its scan plane.
    #[serde(default)]
    pub object: Vec<SceneObject>,
    /// The lidar the simulator serves (at `<device dir>/lidar`).
    #[serde(default)]
    pub lidar: Option<LidarDescription>,
    /// The room's walls (what the lidar sees; the cameras do not draw them).
    #[serde(default)]
    pub room: Option<RoomDescription>,
    /// The lift column the simulator serves (its board at `<device dir>/lift`).
    #[serde(default)]
    pub lift: Option<LiftDescription>,
}

/// The lift: a telescoping column, its DC motor and the board that drives it.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct LiftDescription {
    /// Travel between the limit switches, m.
    pub travel_m: f64,
    /// Where it stands at start, m above the lower switch (the board counts from there).
    pub start_m: f64,
    /// Hall counts per metre.
    pub counts_per_m: f64,
    /// The motor's top speed under the load, m/s.
    pub max_speed_m_s: f64,
    /// What it carries (head and arms), kg.
    pub load_kg: f64,
}

/// The lidar: an RPLIDAR C1 on the base.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct LidarDescription {
    /// Optical centre on the base, m (x forward, y left, z up; the base starts at the world's
    /// origin facing +x).
    pub position: [f64; 3],
    /// Where its 0° points, degrees counter-clockwise from the base's forward axis.
    pub yaw_deg: f64,
    /// Revolutions per second (the C1: 8-12, typically 10).
    pub rotation_hz: f64,
    /// Measurements per second (the C1: 5000).
    pub sample_rate_hz: f64,
    /// Longest range, m; farther is no return.
    pub range_m: f64,
    /// Range noise, m (standard deviation).
    pub noise_m: f64,
}

/// The room: a floor plan of walls.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct RoomDescription {
    /// The walls as a closed polygon on the floor, m, world frame (the last corner joins the
    /// first).
    pub walls: Vec<[f64; 2]>,
}

/// Where a camera is fixed.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct CameraDescription {
    /// Name (the robot's `nori-camera --camera NAME`).
    pub name: String,
    /// `"body"`, or the name of the bus whose arm's tip carries it (a wrist camera).
    pub mount: String,
    /// Optical centre, m: world frame on the body, the tip's frame on a wrist.
    pub position: [f64; 3],
    /// On the body: the point it looks at, world frame. On a wrist: the direction it looks,
    /// in the tip's frame.
    pub look: [f64; 3],
    /// Horizontal field of view, degrees.
    pub fov_deg: f64,
    /// What it delivers: "yuyv" or "mjpeg".
    pub format: String,
    /// Width, px.
    pub width: u32,
    /// Height, px.
    pub height: u32,
    /// Frames per second.
    pub fps: u32,
}

/// A solid in the room.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct SceneObject {
    /// Name (for people reading the file).
    pub name: String,
    /// sRGB colour.
    pub colour: [u8; 3],
    /// A ball's centre (with `radius-m`).
    #[serde(default)]
    pub center: Option<[f64; 3]>,
    /// A ball's radius, m.
    #[serde(default)]
    pub radius_m: Option<f64>,
    /// A box's lowest corner (with `max`).
    #[serde(default)]
    pub min: Option<[f64; 3]>,
    /// A box's highest corner.
    #[serde(default)]
    pub max: Option<[f64; 3]>,
}

impl RobotDescription {
    /// The embedded Nori A3 description.
    pub fn nori_a3() -> Self {
        // The embedded file is checked by a unit test; failing here is a build defect.
        Self::parse(NORI_A3_TOML, "<embedded nori-a3.toml>")
            .unwrap_or_else(|e| panic!("embedded robot description is invalid: {e}"))
    }

    /// Reads and validates a description file.
    pub fn load(path: &Path) -> Result<Self, DescriptionError> {
        let text = std::fs::read_to_string(path).map_err(|source| DescriptionError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses and validates description text; `origin` names it in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Self, DescriptionError> {
        let mut d: RobotDescription =
            toml::from_str(text).map_err(|source| DescriptionError::Parse {
                path: origin.to_string(),
                source,
            })?;
        d.validate(origin)?;
        Ok(d)
    }

    /// The rating of a model key.
    pub fn rating(&self, key: &str) -> Option<&ServoRating> {
        self.servo_models.get(key)
    }

    /// A bus by name.
    pub fn bus(&self, name: &str) -> Option<&BusDescription> {
        self.bus.iter().find(|b| b.name == name)
    }

    /// Checks the description read from `origin` (and normalizes what it can, such as the
    /// joints' axes); the first fault found is the error.
    fn validate(&mut self, origin: &str) -> Result<(), DescriptionError> {
        validate_servo_models(&mut self.servo_models, origin)?;
        let mut names = HashSet::new();
        for (index, bus) in self.bus.iter_mut().enumerate() {
            let site = BusSite {
                origin,
                index,
                name: &bus.name,
            };
            if !names.insert(bus.name.clone()) {
                return Err(site.invalid("name", "duplicate bus name".into()));
            }
            let ids = validate_bus_servos(bus, &self.servo_models, &site)?;
            // Each servo's no-load speed on this bus's supply, rad/s.
            let free_speed: BTreeMap<u8, f64> = (bus.servo.iter())
                .filter_map(|s| {
                    let r = self.servo_models.get(&s.model)?;
                    Some((s.id, r.no_load_speed_rad_s * bus.supply_v / r.rated_voltage))
                })
                .collect();
            if let Some(arm) = &mut bus.arm {
                validate_arm(arm, &ids, &site)?;
                if let Some(plan) = &arm.calibration {
                    validate_calibration_plan(arm, plan, &free_speed, &site)?;
                }
            }
            if let Some(w) = &bus.wheels {
                validate_wheels(w, &ids, &site)?;
            }
        }
        if let Some(l) = &self.lidar {
            validate_lidar(l, origin)?;
        }
        if let Some(room) = &self.room {
            validate_room(room, origin)?;
        }
        Ok(())
    }
}

/// The error for `key` of the description read from `origin`.
fn invalid(origin: &str, key: String, reason: String) -> DescriptionError {
    DescriptionError::Invalid {
        path: origin.to_string(),
        key,
        reason,
    }
}

/// Where a bus's faults are reported: its file and its `bus[i] (name)` key.
struct BusSite<'a> {
    origin: &'a str,
    index: usize,
    name: &'a str,
}

impl BusSite<'_> {
    /// The error for `key` within this bus.
    fn invalid(&self, key: &str, reason: String) -> DescriptionError {
        invalid(
            self.origin,
            format!("bus[{}] ({}).{key}", self.index, self.name),
            reason,
        )
    }

    /// The error for a servo `id` that `key` names but the bus does not carry.
    fn not_on_bus(&self, key: &str, id: u8) -> DescriptionError {
        self.invalid(key, format!("servo {id} is not on this bus"))
    }
}

/// Each servo model is one this stack knows (its key sets the rating's model) and its
/// ratings are positive.
fn validate_servo_models(
    servo_models: &mut BTreeMap<String, ServoRating>,
    origin: &str,
) -> Result<(), DescriptionError> {
    for (key, rating) in servo_models {
        rating.model = match key.as_str() {
            "sts3215" => ServoModel::Sts3215,
            "sts3250" => ServoModel::Sts3250,
            "sts3095" => ServoModel::Sts3095,
            other => {
                return Err(invalid(
                    origin,
                    format!("servo-models.{other}"),
                    "unknown model (sts3215, sts3250, sts3095)".into(),
                ))
            }
        };
        let positive = [
            ("rated-voltage", rating.rated_voltage),
            ("stall-torque-kgcm", rating.stall_torque_kgcm),
            ("stall-current-a", rating.stall_current_a),
            ("no-load-speed-rad-s", rating.no_load_speed_rad_s),
            ("gear-ratio", rating.gear_ratio),
            ("armature-kgm2", rating.armature_kgm2),
            ("heat-capacity-j-per-k", rating.heat_capacity_j_per_k),
            (
                "thermal-resistance-k-per-w",
                rating.thermal_resistance_k_per_w,
            ),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(invalid(
                    origin,
                    format!("servo-models.{key}.{name}"),
                    format!("must be > 0, got {v}"),
                ));
            }
        }
    }
    Ok(())
}

/// A bus's line (baud, supply) and its servos: ids unique and in range, models known.
/// Gives the ids on the bus, which its arm and wheels may name.
fn validate_bus_servos(
    bus: &BusDescription,
    servo_models: &BTreeMap<String, ServoRating>,
    site: &BusSite,
) -> Result<HashSet<u8>, DescriptionError> {
    if feetech::timing::baud_code(bus.baud).is_none() {
        return Err(site.invalid(
            "baud",
            format!("{} is not a baud rate the servos support", bus.baud),
        ));
    }
    if !(bus.supply_v.is_finite() && bus.supply_v > 0.0) {
        return Err(site.invalid("supply-v", "must be > 0".into()));
    }
    let mut ids = HashSet::new();
    for s in &bus.servo {
        if s.id > feetech::MAX_ID || !ids.insert(s.id) {
            return Err(site.invalid("servo.id", format!("id {} is invalid or duplicated", s.id)));
        }
        if !servo_models.contains_key(&s.model) {
            return Err(site.invalid(
                "servo.model",
                format!("unknown model {:?} for id {}", s.model, s.id),
            ));
        }
    }
    Ok(ids)
}

/// An arm's joints (servo on the bus, a non-zero axis, made unit here, stops in order) and
/// its gripper's servo.
fn validate_arm(
    arm: &mut ArmDescription,
    ids: &HashSet<u8>,
    site: &BusSite,
) -> Result<(), DescriptionError> {
    for j in &mut arm.joint {
        if !ids.contains(&j.servo) {
            return Err(site.not_on_bus("arm.joint.servo", j.servo));
        }
        let n = (j.axis[0].powi(2) + j.axis[1].powi(2) + j.axis[2].powi(2)).sqrt();
        if !(n > 1e-9 && n.is_finite()) {
            return Err(site.invalid("arm.joint.axis", "axis must be a non-zero vector".into()));
        }
        j.axis = j.axis.map(|c| c / n);
        if j.lower_rad >= j.upper_rad {
            return Err(site.invalid(
                "arm.joint.lower-rad",
                "lower stop must be below upper stop".into(),
            ));
        }
    }
    if let Some(g) = &arm.gripper {
        if !ids.contains(&g.servo) {
            return Err(site.not_on_bus("arm.gripper.servo", g.servo));
        }
    }
    Ok(())
}

/// What a calibrated joint's stops leave of the encoder's turn at each end, rad (its zero reads
/// mid-turn): pressed past its stop or overshooting, it must not read across the wrap.
const TURN_HEADROOM_RAD: f64 = 0.1;

/// The share of full duty a servo needs over what its speed takes (back-EMF): the rest is for
/// friction, gravity and acceleration.
const SPEED_DUTY_FACTOR: f64 = 1.5;

/// A calibration plan sweeps every joint of the arm and its gripper once, at a torque that
/// presses gently yet turns the servo at the plan's speed (`free_speed`: each servo's no-load
/// speed on its bus's supply), and holds in its poses only joints already swept, inside their
/// stops.
fn validate_calibration_plan(
    arm: &ArmDescription,
    plan: &CalibrationPlan,
    free_speed: &BTreeMap<u8, f64>,
    site: &BusSite,
) -> Result<(), DescriptionError> {
    let key = "arm.calibration";
    if !(plan.lift_m.is_finite() && plan.lift_m >= 0.0) {
        return Err(site.invalid(&format!("{key}.lift-m"), "must be ≥ 0".into()));
    }
    if !(plan.speed_rad_s > 0.0 && plan.speed_rad_s <= 1.0) {
        return Err(site.invalid(
            &format!("{key}.speed-rad-s"),
            format!("{} is outside (0, 1] rad/s", plan.speed_rad_s),
        ));
    }
    let stops: BTreeMap<u8, (f64, f64)> = arm
        .joint
        .iter()
        .map(|j| (j.servo, (j.lower_rad, j.upper_rad)))
        .chain(
            arm.gripper
                .iter()
                .map(|g| (g.servo, (g.lower_rad, g.upper_rad))),
        )
        .collect();
    let mut swept = HashSet::new();
    for s in &plan.sweep {
        let at = format!("{key}.sweep (servo {})", s.servo);
        if !stops.contains_key(&s.servo) || !swept.insert(s.servo) {
            return Err(site.invalid(&at, "not a joint of the arm, or swept twice".into()));
        }
        if !(s.torque_percent > 0.0 && s.torque_percent <= 50.0) {
            return Err(site.invalid(
                &at,
                format!("torque-percent {} is outside (0, 50]", s.torque_percent),
            ));
        }
        let (lo, hi) = stops[&s.servo];
        if lo.abs().max(hi.abs()) > std::f64::consts::PI - TURN_HEADROOM_RAD {
            return Err(site.invalid(
                &at,
                format!(
                    "its stops {lo}..{hi} rad do not fit one turn of the encoder with \
                     {TURN_HEADROOM_RAD} rad to spare at each end: near a stop it would read \
                     across the wrap"
                ),
            ));
        }
        let needed = free_speed
            .get(&s.servo)
            .map_or(0.0, |v| 100.0 * SPEED_DUTY_FACTOR * plan.speed_rad_s / v);
        if s.torque_percent < needed {
            return Err(site.invalid(
                &at,
                format!(
                    "torque-percent {} cannot turn it at {} rad/s: {needed:.1} or more",
                    s.torque_percent, plan.speed_rad_s
                ),
            ));
        }
        for p in &s.pose {
            let inside = stops
                .get(&p.servo)
                .is_some_and(|&(lo, hi)| p.rad > lo && p.rad < hi);
            if p.servo == s.servo || !swept.contains(&p.servo) || !inside {
                return Err(site.invalid(
                    &at,
                    format!(
                        "its pose holds servo {} at {} rad: only a joint swept before it, \
                         inside its stops",
                        p.servo, p.rad
                    ),
                ));
            }
        }
    }
    if swept.len() != stops.len() {
        return Err(site.invalid(
            &format!("{key}.sweep"),
            "every joint of the arm and its gripper is swept".into(),
        ));
    }
    Ok(())
}

/// A base's wheels: servos on the bus, a positive geometry, two wheels and a track when it
/// moves, a footprint and a finite start pose.
fn validate_wheels(
    w: &WheelsDescription,
    ids: &HashSet<u8>,
    site: &BusSite,
) -> Result<(), DescriptionError> {
    if let Some(&id) = w.servos.iter().find(|&&id| !ids.contains(&id)) {
        return Err(site.not_on_bus("wheels.servos", id));
    }
    let geometry = [("wheel-radius-m", w.wheel_radius_m), ("track-m", w.track_m)];
    if let Some((key, value)) = geometry
        .iter()
        .find(|(_, v)| v.is_some_and(|v| !(v.is_finite() && v > 0.0)))
    {
        return Err(site.invalid(
            &format!("wheels.{key}"),
            format!("{value:?} m: a positive length"),
        ));
    }
    if w.wheel_radius_m.is_some() && (w.servos.len() != 2 || w.track_m.is_none()) {
        return Err(site.invalid(
            "wheels",
            "a moving base has two wheel servos (left, right) and a track-m".into(),
        ));
    }
    let footprint = w.footprint_m;
    if !footprint
        .iter()
        .all(|v| v.is_finite() && *v > 0.0 && *v < 5.0)
    {
        return Err(site.invalid(
            "wheels.footprint-m",
            format!("{footprint:?} m: two lengths above 0 and below 5 m"),
        ));
    }
    if !w.start.iter().all(|v| v.is_finite()) {
        return Err(site.invalid("wheels.start", "a finite pose".into()));
    }
    Ok(())
}

/// The lidar's rates, range, noise and yaw within their bounds, and a finite position.
fn validate_lidar(l: &LidarDescription, origin: &str) -> Result<(), DescriptionError> {
    let checks = [
        ("lidar.rotation-hz", l.rotation_hz, 1.0, 20.0),
        ("lidar.sample-rate-hz", l.sample_rate_hz, 100.0, 20_000.0),
        ("lidar.range-m", l.range_m, 0.1, 100.0),
        ("lidar.noise-m", l.noise_m, 0.0, 1.0),
        ("lidar.yaw-deg", l.yaw_deg, -360.0, 360.0),
    ];
    for (key, v, lo, hi) in checks {
        if !(v.is_finite() && (lo..=hi).contains(&v)) {
            return Err(invalid(origin, key.into(), format!("{v}: {lo} to {hi}")));
        }
    }
    if !l.position.iter().all(|v| v.is_finite()) {
        return Err(invalid(
            origin,
            "lidar.position".into(),
            "must be finite".into(),
        ));
    }
    Ok(())
}

/// The room's walls: a closed polygon of finite corners.
fn validate_room(room: &RoomDescription, origin: &str) -> Result<(), DescriptionError> {
    if room.walls.len() < 3 || !room.walls.iter().flatten().all(|v| v.is_finite()) {
        return Err(invalid(
            origin,
            "room.walls".into(),
            "a closed polygon needs at least three finite corners".into(),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_a3_matches_table_1() {
        let d = RobotDescription::nori_a3();
        let arm = d.bus("left_arm").unwrap();
        let models: Vec<&str> = arm.servo.iter().map(|s| s.model.as_str()).collect();
        // Paper, Table 1: shoulder ×2 and bicep STS3095, bicep rotation and wrist pitch STS3250,
        // forearm roll, wrist second axis and gripper STS3215.
        assert_eq!(
            models,
            [
                "sts3095", "sts3095", "sts3250", "sts3095", "sts3215", "sts3250", "sts3215",
                "sts3215"
            ]
        );
        assert_eq!(d.bus.iter().map(|b| b.servo.len()).sum::<usize>(), 18);
        assert_eq!(d.rating("sts3250").unwrap().model, ServoModel::Sts3250);
    }

    #[test]
    fn unknown_key_is_refused_with_its_name() {
        let text = NORI_A3_TOML.replace("ambient-c = 25.0", "ambient-c = 25.0\nambiant = 3");
        let err = RobotDescription::parse(&text, "x.toml")
            .unwrap_err()
            .to_string();
        assert!(err.contains("ambiant") && err.contains("x.toml"), "{err}");
    }

    #[test]
    fn impossible_values_are_refused() {
        let text = NORI_A3_TOML.replacen("stall-current-a = 2.7", "stall-current-a = -1", 1);
        let err = RobotDescription::parse(&text, "x.toml")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("servo-models.sts3215.stall-current-a"),
            "{err}"
        );
        let text = NORI_A3_TOML.replacen("baud = 1000000", "baud = 9600", 1);
        assert!(RobotDescription::parse(&text, "x.toml").is_err());
        for (from, to, key) in [
            (
                "wheel-radius-m = 0.075",
                "wheel-radius-m = -0.05",
                "wheels.wheel-radius-m",
            ),
            ("track-m = 0.36", "track-m = nan", "wheels.track-m"),
            ("track-m = 0.36", "", "wheels"),
            (
                "footprint-m = [0.45, 0.45]",
                "footprint-m = [0.45, 0.0]",
                "wheels.footprint",
            ),
            (
                "start = [0.0, 0.0, 0.0]",
                "start = [inf, 0.0, 0.0]",
                "wheels.start",
            ),
        ] {
            let text = NORI_A3_TOML.replacen(from, to, 1);
            let err = RobotDescription::parse(&text, "x.toml")
                .unwrap_err()
                .to_string();
            assert!(err.contains(key), "{to:?}: {err}");
        }
    }

    /// A calibration plan that would leave a joint uncalibrated, sweep one twice, hold a joint
    /// it has not calibrated yet (or outside its stops), press hard, or crawl nowhere.
    #[test]
    fn a_calibration_plan_that_is_not_safe_is_refused() {
        let gripper = "  { servo = 8, torque-percent = 10 },\n";
        for (from, to, says) in [
            (gripper, "", "every joint of the arm"),
            (
                gripper,
                "  { servo = 8, torque-percent = 10 },\n  { servo = 8, torque-percent = 10 },\n",
                "swept twice",
            ),
            (
                gripper,
                "  { servo = 9, torque-percent = 15 },\n",
                "not a joint",
            ),
            (
                "{ servo = 8, torque-percent = 10 }",
                "{ servo = 8, torque-percent = 60 }",
                "outside (0, 50]",
            ),
            (
                "{ servo = 8, torque-percent = 10 }",
                "{ servo = 8, torque-percent = 0 }",
                "outside (0, 50]",
            ),
            (
                "pose = [{ servo = 4, rad = -2.25 }]",
                "pose = [{ servo = 1, rad = 0.5 }]",
                "only a joint swept before it",
            ),
            (
                "pose = [{ servo = 4, rad = -2.25 }]",
                "pose = [{ servo = 4, rad = -2.4 }]",
                "inside its stops",
            ),
            ("speed-rad-s = 0.3", "speed-rad-s = 1.5", "speed-rad-s"),
            (
                "lower-rad = -3.0, upper-rad = 3.0",
                "lower-rad = -3.1, upper-rad = 3.0",
                "one turn",
            ),
            (
                "speed-rad-s = 0.3",
                "speed-rad-s = 0.5",
                "cannot turn it at 0.5 rad/s",
            ),
            ("lift-m = 0.6", "lift-m = -0.1", "lift-m"),
            (
                "pose = [{ servo = 4, rad = -2.25 }]",
                "pose = [{ servo = 2, rad = 0.5 }]",
                "only a joint swept before it",
            ),
            (
                "pose = [{ servo = 4, rad = -2.25 }]",
                "pose = [{ servo = 4, rad = -2.5 }]",
                "inside its stops",
            ),
            ("speed-rad-s = 0.3", "speed-rad-s = 0", "speed-rad-s"),
            ("lift-m = 0.6", "lift-m = nan", "lift-m"),
        ] {
            assert!(NORI_A3_TOML.contains(from), "{from}");
            let text = NORI_A3_TOML.replacen(from, to, 1);
            let err = RobotDescription::parse(&text, "x.toml")
                .unwrap_err()
                .to_string();
            assert!(
                err.contains(says) && err.contains("left_arm"),
                "{to:?}: {err}"
            );
        }
    }
}
