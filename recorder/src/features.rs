//! What a dataset holds: the joints (from the driver's layout) and the LeRobot features made of
//! them, in the order of `meta/info.json`.

use serde::{Deserialize, Serialize};
use telemetry::frames::{JointLayout, JointRole};

/// One recorded joint, as the driver's layout describes it (kept in `meta/nori.json` so a
/// dataset can be exported for the model lab without the driver configuration).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JointMeta {
    /// Joint name (the names of the vector features).
    pub name: String,
    /// Index of the joint in the driver's joint-state frame.
    pub frame_index: usize,
    /// Index of its bus in the driver configuration.
    pub bus: u8,
    /// Servo id on that bus.
    pub id: u8,
    /// `Model_Number` (777 STS3215, 2825 STS3250, 2569 STS3095).
    pub model: u16,
    /// "joint" or "gripper".
    pub role: String,
    /// Calibrated range, rad.
    pub range_rad: [f32; 2],
}

impl JointMeta {
    /// The model lab's servo key for this joint's model, if known.
    pub fn servo_key(&self) -> Option<&'static str> {
        match self.model {
            777 => Some("sts3215"),
            2825 => Some("sts3250"),
            2569 => Some("sts3095"),
            _ => None,
        }
    }
}

/// The vector features of a frame, in `info.json` order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Vector {
    /// `action`: the joint position goal the driver sent in that cycle (after its clamp), rad.
    Action,
    /// `observation.state`: joint positions, rad.
    State,
    /// `observation.velocity`: joint speeds, rad/s.
    Velocity,
    /// `observation.current`: raw motor current, A.
    Current,
    /// `observation.temperature`: the servo's temperature register, °C.
    Temperature,
    /// `observation.voltage`: supply voltage at the servo, V.
    Voltage,
    /// `observation.grip_force`: normalised grip force per gripper, 0..1.
    GripForce,
    /// `observation.joint_valid`: 1 where every value of the joint in this frame was read in
    /// this frame period, 0 where its last read is held (the servo did not answer in time).
    Valid,
    /// `observation.camera_valid`: per camera, 1 where the frame's image was captured within
    /// the staleness bound of the frame's tick, 0 where the camera's last image is held (it
    /// stalled or died). Not named `...images...`: LeRobot treats every key containing "image"
    /// as a picture.
    CameraValid,
    /// `observation.odometry`: the base's pose from its wheels, x and y (m) and heading (rad),
    /// in the frame its controller started in (recorded with the base).
    Odometry,
}

impl Vector {
    /// The LeRobot feature key.
    pub fn key(self) -> &'static str {
        match self {
            Vector::Action => "action",
            Vector::State => "observation.state",
            Vector::Velocity => "observation.velocity",
            Vector::Current => "observation.current",
            Vector::Temperature => "observation.temperature",
            Vector::Voltage => "observation.voltage",
            Vector::GripForce => "observation.grip_force",
            Vector::Valid => "observation.joint_valid",
            Vector::CameraValid => "observation.camera_valid",
            Vector::Odometry => "observation.odometry",
        }
    }
}

/// The scalar features every LeRobot frame carries (`DEFAULT_FEATURES`), in order.
pub const SCALARS: [(&str, &str); 5] = [
    ("timestamp", "float32"),
    ("frame_index", "int64"),
    ("episode_index", "int64"),
    ("index", "int64"),
    ("task_index", "int64"),
];

/// One recorded camera: its video feature `observation.images.<name>`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CameraMeta {
    /// Camera name (as on the state plane).
    pub name: String,
    /// Image width, px.
    pub width: u32,
    /// Image height, px.
    pub height: u32,
    /// FFmpeg's name of the JPEGs' pixel format (`yuvj420p`, ...): `video.pix_fmt`.
    pub pix_fmt: String,
}

impl CameraMeta {
    /// The LeRobot feature key.
    pub fn key(&self) -> String {
        format!("observation.images.{}", self.name)
    }
}

/// One axis of the body beyond the arms, appended to `action`, `observation.state` and
/// `observation.joint_valid` after the joints (the other per-servo features stay the joints').
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BodyAxis {
    /// The lift's height above its lowest, m: measured in the state, the goal in force in the
    /// action (the height held when there is none).
    LiftHeight,
    /// The base's forward speed, m/s: measured in the state; in the action what the wheels were
    /// driven with (after the acceleration limits and the protective field).
    BaseLinear,
    /// The base's turn rate, rad/s, the same way.
    BaseAngular,
}

impl BodyAxis {
    /// The dimension's name in the vector features.
    pub fn name(self) -> &'static str {
        match self {
            BodyAxis::LiftHeight => "lift.height_m",
            BodyAxis::BaseLinear => "base.linear_m_s",
            BodyAxis::BaseAngular => "base.angular_rad_s",
        }
    }
}

/// The names of `observation.odometry`.
pub const ODOMETRY_NAMES: [&str; 3] = ["base.x_m", "base.y_m", "base.heading_rad"];

/// The codec of the recorded videos: the cameras' own JPEGs, stored without encoding again
/// (`nori bench video-encode` has the figures behind that choice).
pub const VIDEO_CODEC: &str = "mjpeg";

/// The joints and cameras of a recording and the features made of them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Features {
    /// Position-mode joints (arm joints and grippers), in frame order. Wheels are left out: their
    /// "position" is an angle modulo a turn and their goal a speed, not a position target.
    pub joints: Vec<JointMeta>,
    /// Cameras recorded as videos, in feature order (none in a joints-only dataset).
    #[serde(default)]
    pub cameras: Vec<CameraMeta>,
    /// The lift and base axes recorded after the joints (none in an arms-only dataset).
    #[serde(default)]
    pub body: Vec<BodyAxis>,
}

impl Features {
    /// The position-mode joints of a layout.
    pub fn from_layout(layout: &JointLayout) -> Features {
        let joints = layout
            .joints()
            .iter()
            .enumerate()
            .filter(|(_, j)| j.role() != JointRole::Wheel)
            .map(|(i, j)| JointMeta {
                name: j.name().to_string(),
                frame_index: i,
                bus: j.bus,
                id: j.id,
                model: j.model,
                role: match j.role() {
                    JointRole::Gripper => "gripper".into(),
                    _ => "joint".into(),
                },
                range_rad: j.range_rad,
            })
            .collect();
        Features {
            joints,
            cameras: Vec::new(),
            body: Vec::new(),
        }
    }

    /// The same with the lift's height and/or the base's twist (and odometry) recorded.
    pub fn with_body(mut self, lift: bool, base: bool) -> Features {
        self.body.clear();
        if lift {
            self.body.push(BodyAxis::LiftHeight);
        }
        if base {
            self.body
                .extend([BodyAxis::BaseLinear, BodyAxis::BaseAngular]);
        }
        self
    }

    /// Whether the base is recorded (its twist and odometry).
    pub fn has_base(&self) -> bool {
        self.body.contains(&BodyAxis::BaseLinear)
    }

    /// Whether the lift is recorded.
    pub fn has_lift(&self) -> bool {
        self.body.contains(&BodyAxis::LiftHeight)
    }

    /// The same joints with `cameras` recorded as videos.
    pub fn with_cameras(mut self, cameras: Vec<CameraMeta>) -> Features {
        self.cameras = cameras;
        self
    }

    /// Joint names.
    pub fn joint_names(&self) -> Vec<String> {
        self.joints.iter().map(|j| j.name.clone()).collect()
    }

    /// The grippers among the joints (indices into [`Features::joints`]).
    pub fn grippers(&self) -> Vec<usize> {
        (0..self.joints.len())
            .filter(|&i| self.joints[i].role == "gripper")
            .collect()
    }

    /// The vector features present (grip force only when there is a gripper, camera validity
    /// only when there is a camera).
    pub fn vectors(&self) -> Vec<Vector> {
        let mut v = vec![
            Vector::Action,
            Vector::State,
            Vector::Velocity,
            Vector::Current,
            Vector::Temperature,
            Vector::Voltage,
        ];
        if !self.grippers().is_empty() {
            v.push(Vector::GripForce);
        }
        v.push(Vector::Valid);
        if !self.cameras.is_empty() {
            v.push(Vector::CameraValid);
        }
        if self.has_base() {
            v.push(Vector::Odometry);
        }
        v
    }

    /// Length of a vector feature.
    pub fn width(&self, v: Vector) -> usize {
        match v {
            Vector::GripForce => self.grippers().len(),
            Vector::CameraValid => self.cameras.len(),
            Vector::Odometry => ODOMETRY_NAMES.len(),
            Vector::Action | Vector::State | Vector::Valid => self.joints.len() + self.body.len(),
            Vector::Velocity | Vector::Current | Vector::Temperature | Vector::Voltage => {
                self.joints.len()
            }
        }
    }

    /// Names of the dimensions of a vector feature.
    pub fn names(&self, v: Vector) -> Vec<String> {
        match v {
            Vector::GripForce => self
                .grippers()
                .into_iter()
                .map(|i| self.joints[i].name.clone())
                .collect(),
            Vector::CameraValid => self.cameras.iter().map(|c| c.name.clone()).collect(),
            Vector::Odometry => ODOMETRY_NAMES.iter().map(|n| n.to_string()).collect(),
            Vector::Action | Vector::State | Vector::Valid => self
                .joint_names()
                .into_iter()
                .chain(self.body.iter().map(|a| a.name().to_string()))
                .collect(),
            Vector::Velocity | Vector::Current | Vector::Temperature | Vector::Voltage => {
                self.joint_names()
            }
        }
    }

    /// Every feature key, vectors, videos, then scalars: the order of `info.json` and of the
    /// statistics (the data columns are the vectors and the scalars: a video is in its own file).
    pub fn keys(&self) -> Vec<String> {
        self.vectors()
            .into_iter()
            .map(|v| v.key().to_string())
            .chain(self.cameras.iter().map(CameraMeta::key))
            .chain(SCALARS.iter().map(|(k, _)| k.to_string()))
            .collect()
    }

    /// Whether `key` is a video feature (its statistics are per colour channel, shaped
    /// `[3, 1, 1]` as LeRobot keeps an image's).
    pub fn is_video(&self, key: &str) -> bool {
        self.cameras.iter().any(|c| c.key() == key)
    }

    /// The `features` object of `info.json`, in order, as LeRobot writes it
    /// (`{"dtype", "shape", "names"}`, names `null` for the scalars).
    pub fn info_json(&self, fps: u32) -> Ordered<FeatureSpec> {
        let mut out = Vec::new();
        for v in self.vectors() {
            out.push((
                v.key().to_string(),
                FeatureSpec {
                    dtype: "float32".into(),
                    shape: vec![self.width(v)],
                    names: Some(self.names(v)),
                    info: None,
                },
            ));
        }
        for c in &self.cameras {
            out.push((
                c.key(),
                FeatureSpec {
                    dtype: "video".into(),
                    shape: vec![c.height as usize, c.width as usize, 3],
                    names: Some(vec!["height".into(), "width".into(), "channels".into()]),
                    info: Some(VideoInfo {
                        height: c.height,
                        width: c.width,
                        codec: VIDEO_CODEC.into(),
                        pix_fmt: c.pix_fmt.clone(),
                        is_depth_map: false,
                        fps,
                        channels: 3,
                        has_audio: false,
                    }),
                },
            ));
        }
        for (key, dtype) in SCALARS {
            out.push((
                key.to_string(),
                FeatureSpec {
                    dtype: dtype.into(),
                    shape: vec![1],
                    names: None,
                    info: None,
                },
            ));
        }
        Ordered(out)
    }
}

/// One feature of `info.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeatureSpec {
    /// numpy dtype name.
    pub dtype: String,
    /// Shape of one frame's value.
    pub shape: Vec<usize>,
    /// Names of the dimensions (`null` for scalars).
    pub names: Option<Vec<String>>,
    /// A video's stream description (video features only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub info: Option<VideoInfo>,
}

/// The `info` block of a video feature, as LeRobot writes it (`get_video_info`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VideoInfo {
    /// Frame height, px.
    #[serde(rename = "video.height")]
    pub height: u32,
    /// Frame width, px.
    #[serde(rename = "video.width")]
    pub width: u32,
    /// FFmpeg codec name.
    #[serde(rename = "video.codec")]
    pub codec: String,
    /// FFmpeg pixel format name.
    #[serde(rename = "video.pix_fmt")]
    pub pix_fmt: String,
    /// Always false here.
    #[serde(rename = "video.is_depth_map")]
    pub is_depth_map: bool,
    /// Frames per second.
    #[serde(rename = "video.fps")]
    pub fps: u32,
    /// Colour channels.
    #[serde(rename = "video.channels")]
    pub channels: u32,
    /// Always false here.
    pub has_audio: bool,
}

/// A JSON object that keeps its keys in the given order (serde_json's own map sorts them).
#[derive(Debug, Clone, PartialEq)]
pub struct Ordered<T>(pub Vec<(String, T)>);

impl<T: Serialize> Serialize for Ordered<T> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        let mut m = s.serialize_map(Some(self.0.len()))?;
        for (k, v) in &self.0 {
            m.serialize_entry(k, v)?;
        }
        m.end()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use telemetry::frames::JointInfo;

    pub(crate) fn layout(names: &[(&str, JointRole)]) -> JointLayout {
        let mut l = JointLayout {
            joint_count: names.len() as u32,
            bus_count: 1,
            ..JointLayout::default()
        };
        for (i, (n, role)) in names.iter().enumerate() {
            let mut j = JointInfo {
                role: *role as u8,
                id: i as u8 + 1,
                model: 777,
                range_rad: [-1.0, 1.0],
                ..JointInfo::default()
            };
            j.set_name(n);
            l.joints[i] = j;
        }
        l
    }

    #[test]
    fn wheels_are_left_out_and_grip_force_follows_the_grippers() {
        let f = Features::from_layout(&layout(&[
            ("elbow", JointRole::Joint),
            ("wheel", JointRole::Wheel),
            ("gripper", JointRole::Gripper),
        ]));
        assert_eq!(f.joint_names(), ["elbow", "gripper"]);
        assert_eq!(
            f.joints[1].frame_index, 2,
            "index in the driver's frame kept"
        );
        assert_eq!(f.names(Vector::GripForce), ["gripper"]);
        assert_eq!(
            f.keys(),
            [
                "action",
                "observation.state",
                "observation.velocity",
                "observation.current",
                "observation.temperature",
                "observation.voltage",
                "observation.grip_force",
                "observation.joint_valid",
                "timestamp",
                "frame_index",
                "episode_index",
                "index",
                "task_index"
            ]
        );
        let info = serde_json::to_value(f.info_json(30)).unwrap();
        assert_eq!(info["observation.state"]["shape"], serde_json::json!([2]));
        assert_eq!(
            info["observation.grip_force"]["names"],
            serde_json::json!(["gripper"])
        );
        assert_eq!(info["index"]["dtype"], "int64");
        assert!(info["timestamp"]["names"].is_null());

        let no_gripper = Features::from_layout(&layout(&[("elbow", JointRole::Joint)]));
        assert!(!no_gripper.vectors().contains(&Vector::GripForce));
        assert!(!no_gripper.vectors().contains(&Vector::Odometry));
    }

    #[test]
    fn the_lift_and_base_widen_action_state_and_validity_but_not_the_servo_features() {
        let f = Features::from_layout(&layout(&[
            ("elbow", JointRole::Joint),
            ("gripper", JointRole::Gripper),
        ]))
        .with_body(true, true);
        let body = ["lift.height_m", "base.linear_m_s", "base.angular_rad_s"];
        for v in [Vector::Action, Vector::State, Vector::Valid] {
            assert_eq!(f.width(v), 5, "{v:?}");
            assert_eq!(f.names(v)[..2], ["elbow", "gripper"]);
            assert_eq!(f.names(v)[2..], body);
        }
        for v in [Vector::Velocity, Vector::Current, Vector::Temperature] {
            assert_eq!(f.names(v), ["elbow", "gripper"], "{v:?}");
        }
        assert_eq!(f.names(Vector::Odometry), ODOMETRY_NAMES);
        assert_eq!(f.keys().last().unwrap(), "task_index");
        assert!(f.keys().contains(&"observation.odometry".to_string()));
        let lift_only = f.clone().with_body(true, false);
        assert_eq!(lift_only.width(Vector::State), 3);
        assert!(!lift_only.vectors().contains(&Vector::Odometry));
        // A dataset written before the body was recorded reads as arms only.
        let old: Features = serde_json::from_str(r#"{"joints": []}"#).unwrap();
        assert!(old.body.is_empty());
    }
}
