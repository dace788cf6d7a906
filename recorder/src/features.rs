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

/// The joints of a recording and the features made of them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Features {
    /// Position-mode joints (arm joints and grippers), in frame order. Wheels are left out: their
    /// "position" is an angle modulo a turn and their goal a speed, not a position target.
    pub joints: Vec<JointMeta>,
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
        Features { joints }
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

    /// The vector features present (grip force only when there is a gripper).
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
        v
    }

    /// Length of a vector feature.
    pub fn width(&self, v: Vector) -> usize {
        match v {
            Vector::GripForce => self.grippers().len(),
            _ => self.joints.len(),
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
            _ => self.joint_names(),
        }
    }

    /// Every feature key, vectors then scalars: the order of `info.json` and of the data columns.
    pub fn keys(&self) -> Vec<&'static str> {
        self.vectors()
            .into_iter()
            .map(Vector::key)
            .chain(SCALARS.iter().map(|(k, _)| *k))
            .collect()
    }

    /// The `features` object of `info.json`, in order, as LeRobot writes it
    /// (`{"dtype", "shape", "names"}`, names `null` for the scalars).
    pub fn info_json(&self) -> Ordered<FeatureSpec> {
        let mut out = Vec::new();
        for v in self.vectors() {
            out.push((
                v.key().to_string(),
                FeatureSpec {
                    dtype: "float32".into(),
                    shape: vec![self.width(v)],
                    names: Some(self.names(v)),
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
        let info = serde_json::to_value(f.info_json()).unwrap();
        assert_eq!(info["observation.state"]["shape"], serde_json::json!([2]));
        assert_eq!(
            info["observation.grip_force"]["names"],
            serde_json::json!(["gripper"])
        );
        assert_eq!(info["index"]["dtype"], "int64");
        assert!(info["timestamp"]["names"].is_null());

        let no_gripper = Features::from_layout(&layout(&[("elbow", JointRole::Joint)]));
        assert!(!no_gripper.vectors().contains(&Vector::GripForce));
    }
}
