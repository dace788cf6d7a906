//! Model extensions fitted on measured data by the model lab (`nori model analyze`), loaded
//! into a simulated bus with [`crate::SimBus::apply_extension`]: thermal and electrical
//! (sensor lag, coupling, copper, ambient, supply, current offset) and mechanical (inertia,
//! the firmware's gain, Stribeck and torque-proportional friction, directional or not, play in
//! the gearbox).
//!
//! The file is TOML with kebab-case keys; unknown keys are refused. It names the cause (a
//! catalog id of the model lab) and the extension's parameter in physical units; the fitted
//! per-motor constants travel with it for reference (in the lab's reduced form: τ, R·R_th, idle
//! equilibrium), since data motor ids need not be the robot's servo ids.
//!
//! ```toml
//! format = 1
//! cause = "sensor_lag"
//! sensor-time-constant-s = 95.0
//! ```

use serde::{Deserialize, Serialize};
use std::path::Path;
use thiserror::Error;

/// The format version this simulator reads.
pub const FORMAT: u32 = 1;

/// A model extension file that cannot be used.
#[derive(Debug, Error)]
#[allow(missing_docs, reason = "each field is shown in its variant's message")]
pub enum ExtensionError {
    /// The file could not be read.
    #[error("cannot read model extension {path}: {source}")]
    Io {
        /// File path.
        path: String,
        source: std::io::Error,
    },
    /// TOML syntax, a wrong type or an unknown key.
    #[error("model extension {path}: {source}")]
    Parse {
        /// File path.
        path: String,
        source: toml::de::Error,
    },
    /// A value that parses but cannot be simulated.
    #[error("model extension {path}: {key}: {reason}")]
    Invalid {
        /// File path.
        path: String,
        /// Offending key.
        key: String,
        reason: String,
    },
}

/// Fitted constants of one measured motor (reduced form: τ·dT/dt = idle + k·I² − T).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct FittedMotor {
    /// Motor id in the data.
    pub id: i64,
    /// Thermal time constant R_th·C, s.
    pub tau_s: f64,
    /// Copper-loss gain R·R_th, K/A².
    pub gain_k_per_a2: f64,
    /// Idle equilibrium T_amb + P0·R_th, °C.
    pub idle_c: f64,
}

/// One fitted extension of the servo model (at most one parameter is set, the cause's).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ModelExtension {
    /// Format version ([`FORMAT`]).
    pub format: u32,
    /// The cause, a model-lab catalog id (`none` when no extension is supported).
    pub cause: String,
    /// `sensor_lag`: the register reads a node lagging the winding with this time constant, s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensor_time_constant_s: Option<f64>,
    /// `neighbor_coupling`: conductance to each chain neighbour over the servo's conductance
    /// to ambient (dimensionless).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub neighbor_coupling_ratio: Option<f64>,
    /// `copper_tempco`: relative rise of winding resistance per kelvin above 25 °C, 1/K.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub resistance_tempco_per_k: Option<f64>,
    /// `ambient_drift`: ambient temperature drift, K/h.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ambient_drift_k_per_h: Option<f64>,
    /// `supply_sag`: supply and wiring resistance, Ω (the voltage sags by R·Σ|I|).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub supply_resistance_ohm: Option<f64>,
    /// `current_offset`: the current register reads the current plus this, A.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub current_offset_a: Option<f64>,
    /// `armature_error`: the reflected inertia is the rating's × (1 + this).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub armature_error: Option<f64>,
    /// `firmware_gain`: the position loop's duty per radian is the configured × (1 + this).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub duty_gain_error: Option<f64>,
    /// `stribeck`: extra friction at rest, N·m, fading as exp(−(ω/ω_s)²) ...
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stribeck_nm: Option<f64>,
    /// ... over this speed ω_s, rad/s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stribeck_speed_rad_s: Option<f64>,
    /// `load_friction` / `directional_friction`: friction proportional to the torque the
    /// gearbox carries while the motor drives the load, per N·m.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub friction_drive_ratio: Option<f64>,
    /// ... and while the load drives the motor back, per N·m.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub friction_back_ratio: Option<f64>,
    /// `backlash`: play in the gearbox between the motor and the output (the encoder's side),
    /// rad.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub backlash_rad: Option<f64>,
    /// The Coulomb friction the model lab calibrated with the extension, N·m (for reference).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fitted_coulomb_nm: Option<f64>,
    /// The viscous friction it calibrated, N·m·s/rad (for reference).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fitted_viscous_nms: Option<f64>,
    /// Relative reduction of the held-out error the extension brought, for reference.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub heldout_gain: Option<f64>,
    /// The servo model the motion channel replayed: its extension and friction are that
    /// model's constants.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub servo: Option<String>,
    /// Relative reduction of the motion channel's held-out error its extension brought.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub motion_heldout_gain: Option<f64>,
    /// A misfit that matters (beyond the positions' noise floor and an encoder step) is left
    /// with the motion extension: it is supported, not the whole story (the analysis said
    /// `unexplained` beside it).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub motion_misfit_left: bool,
    /// The runs it was fitted on, each its file: runs not named here are the ones no fit saw.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub fitted_on: Vec<String>,
    /// Fitted per-motor constants, for reference.
    #[serde(default)]
    pub motor: Vec<FittedMotor>,
}

impl ModelExtension {
    /// The nominal model: no extension.
    pub fn none() -> Self {
        ModelExtension {
            format: FORMAT,
            cause: "none".into(),
            sensor_time_constant_s: None,
            neighbor_coupling_ratio: None,
            resistance_tempco_per_k: None,
            ambient_drift_k_per_h: None,
            supply_resistance_ohm: None,
            current_offset_a: None,
            armature_error: None,
            duty_gain_error: None,
            stribeck_nm: None,
            stribeck_speed_rad_s: None,
            friction_drive_ratio: None,
            friction_back_ratio: None,
            backlash_rad: None,
            fitted_coulomb_nm: None,
            fitted_viscous_nms: None,
            heldout_gain: None,
            servo: None,
            motion_heldout_gain: None,
            motion_misfit_left: false,
            fitted_on: Vec::new(),
            motor: Vec::new(),
        }
    }

    /// Reads and validates a file.
    pub fn load(path: &Path) -> Result<Self, ExtensionError> {
        let text = std::fs::read_to_string(path).map_err(|source| ExtensionError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses and validates text; `origin` names it in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Self, ExtensionError> {
        let m: ModelExtension = toml::from_str(text).map_err(|source| ExtensionError::Parse {
            path: origin.into(),
            source,
        })?;
        let invalid = |key: &str, reason: String| ExtensionError::Invalid {
            path: origin.into(),
            key: key.into(),
            reason,
        };
        if m.format != FORMAT {
            return Err(invalid(
                "format",
                format!("version {} (this simulator reads {FORMAT})", m.format),
            ));
        }
        let checks = [
            ("sensor-time-constant-s", m.sensor_time_constant_s, 0.0),
            ("neighbor-coupling-ratio", m.neighbor_coupling_ratio, -1.0),
            ("supply-resistance-ohm", m.supply_resistance_ohm, -1.0),
            ("armature-error", m.armature_error, -1.0),
            ("duty-gain-error", m.duty_gain_error, -1.0),
            ("stribeck-speed-rad-s", m.stribeck_speed_rad_s, 0.0),
        ];
        for (key, v, above) in checks {
            if let Some(v) = v {
                if !(v.is_finite() && v > above) {
                    return Err(invalid(
                        key,
                        format!("must be finite and > {above}, got {v}"),
                    ));
                }
            }
        }
        for (key, v) in [
            ("resistance-tempco-per-k", m.resistance_tempco_per_k),
            ("ambient-drift-k-per-h", m.ambient_drift_k_per_h),
            ("current-offset-a", m.current_offset_a),
        ] {
            if v.is_some_and(|v| !v.is_finite()) {
                return Err(invalid(key, "must be finite".into()));
            }
        }
        for (key, v) in [
            ("stribeck-nm", m.stribeck_nm),
            ("friction-drive-ratio", m.friction_drive_ratio),
            ("friction-back-ratio", m.friction_back_ratio),
            ("backlash-rad", m.backlash_rad),
            ("fitted-coulomb-nm", m.fitted_coulomb_nm),
            ("fitted-viscous-nms", m.fitted_viscous_nms),
        ] {
            if v.is_some_and(|v| !(v.is_finite() && v >= 0.0)) {
                return Err(invalid(key, "must be finite and ≥ 0".into()));
            }
        }
        if m.stribeck_nm.is_some() && m.stribeck_speed_rad_s.is_none() {
            return Err(invalid(
                "stribeck-speed-rad-s",
                "needed with stribeck-nm".into(),
            ));
        }
        Ok(m)
    }

    /// The file's text.
    pub fn to_toml(&self) -> String {
        // Serialising plain numbers, strings and tables cannot fail.
        toml::to_string(self).unwrap_or_default()
    }
}

/// The per-servo part of an extension, applied by the servo's own step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ServoExtension {
    /// Time constant of the sensor node, s (0: the register reads the winding).
    pub sensor_time_constant_s: f64,
    /// Relative rise of winding resistance per kelvin above 25 °C (heating only), 1/K.
    pub resistance_tempco_per_k: f64,
    /// Offset of the current register, A.
    pub current_offset_a: f64,
    /// Relative error of the reflected inertia (0: the rating's).
    pub armature_error: f64,
    /// Relative error of the position loop's gain (0: the configured).
    pub duty_gain_error: f64,
    /// Extra friction at rest, N·m (Stribeck), ...
    pub stribeck_nm: f64,
    /// ... fading over this speed, rad/s.
    pub stribeck_speed_rad_s: f64,
    /// Friction per N·m the gearbox carries while the motor drives the load.
    pub friction_drive_ratio: f64,
    /// Friction per N·m the gearbox carries while the load drives the motor back.
    pub friction_back_ratio: f64,
    /// Play in the gearbox, rad (0: none).
    pub backlash_rad: f64,
}

impl Default for ServoExtension {
    /// The nominal servo: every extension off (Stribeck's speed 1 rad/s, so a Stribeck
    /// friction set alone never divides by zero).
    fn default() -> Self {
        ServoExtension {
            sensor_time_constant_s: 0.0,
            resistance_tempco_per_k: 0.0,
            current_offset_a: 0.0,
            armature_error: 0.0,
            duty_gain_error: 0.0,
            stribeck_nm: 0.0,
            stribeck_speed_rad_s: 1.0,
            friction_drive_ratio: 0.0,
            friction_back_ratio: 0.0,
            backlash_rad: 0.0,
        }
    }
}

impl ServoExtension {
    /// Sets the parameters `m` carries and keeps the others (an effect put on top of a
    /// model's fitted constants).
    pub fn overlay(&mut self, m: &ModelExtension) {
        for (slot, value) in [
            (&mut self.sensor_time_constant_s, m.sensor_time_constant_s),
            (&mut self.resistance_tempco_per_k, m.resistance_tempco_per_k),
            (&mut self.current_offset_a, m.current_offset_a),
            (&mut self.armature_error, m.armature_error),
            (&mut self.duty_gain_error, m.duty_gain_error),
            (&mut self.stribeck_nm, m.stribeck_nm),
            (&mut self.stribeck_speed_rad_s, m.stribeck_speed_rad_s),
            (&mut self.friction_drive_ratio, m.friction_drive_ratio),
            (&mut self.friction_back_ratio, m.friction_back_ratio),
            (&mut self.backlash_rad, m.backlash_rad),
        ] {
            if let Some(v) = value {
                *slot = v;
            }
        }
    }
}

impl From<&ModelExtension> for ServoExtension {
    fn from(m: &ModelExtension) -> Self {
        let mut ext = ServoExtension::default();
        ext.overlay(m);
        ext
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use crate::servo::{Servo, Surroundings};
    use crate::{RobotDescription, SimBus};
    use feetech::registers as reg;

    /// A servo stalled at full duty against a load it cannot move, for `seconds`.
    fn stalled(ext: &ModelExtension, seconds: f64) -> Servo {
        let d = RobotDescription::nori_a3();
        let r = d.rating("sts3215").unwrap();
        let mut s = Servo::new(1, r.model, r, 0.0, 25.0);
        s.extension = ServoExtension::from(ext);
        // No protection may cut the stall short: the test is about heat.
        s.write(reg::UNLOADING_CONDITION.addr, &[0]);
        s.write(reg::TORQUE_ENABLE.addr, &[1]);
        s.write(reg::GOAL_POSITION.addr, &(2048u16 + 400).to_le_bytes());
        let steps = (seconds / 0.01) as usize;
        for _ in 0..steps {
            s.step(0.01, Surroundings::BENCH.torque(10.0));
        }
        s
    }

    fn register_temperature(s: &mut Servo) -> i32 {
        let mut b = [0u8; 1];
        s.read(reg::PRESENT_TEMPERATURE.addr, 1, &mut b);
        i32::from(b[0])
    }

    #[test]
    fn a_loaded_extension_changes_the_thermal_behaviour() {
        let lag = ModelExtension::parse(
            "format = 1\ncause = \"sensor_lag\"\nsensor-time-constant-s = 120.0\n",
            "lag.toml",
        )
        .unwrap();
        let tempco = ModelExtension::parse(
            "format = 1\ncause = \"copper_tempco\"\nresistance-tempco-per-k = 0.00393\n",
            "tempco.toml",
        )
        .unwrap();
        let (mut nominal, mut lagged, hot) = (
            stalled(&ModelExtension::none(), 120.0),
            stalled(&lag, 120.0),
            stalled(&tempco, 120.0),
        );
        // Same winding, but the lagging sensor reads well below it while heating.
        assert!((nominal.temperature - lagged.temperature).abs() < 1e-9);
        let (rn, rl) = (
            register_temperature(&mut nominal),
            register_temperature(&mut lagged),
        );
        assert_eq!(rn, nominal.temperature.round() as i32);
        assert!(rl + 3 < rn, "lagging sensor {rl} vs winding {rn}");
        // A resistance that rises with temperature heats the winding more.
        assert!(hot.temperature > nominal.temperature + 0.5);
    }

    /// The mechanical entries: read from the file, refused when impossible, and acting in the
    /// servo's step (more inertia swings slower).
    #[test]
    fn a_loaded_mechanical_extension_changes_the_motion() {
        let m = ModelExtension::parse(
            "format = 1\ncause = \"stribeck\"\nstribeck-nm = 0.1\nstribeck-speed-rad-s = 0.3\n\
             armature-error = 0.5\nduty-gain-error = 0.2\nfriction-drive-ratio = 0.1\n\
             friction-back-ratio = 0.3\n",
            "m.toml",
        )
        .unwrap();
        let e = ServoExtension::from(&m);
        assert_eq!(
            (
                e.stribeck_nm,
                e.stribeck_speed_rad_s,
                e.armature_error,
                e.duty_gain_error
            ),
            (0.1, 0.3, 0.5, 0.2)
        );
        assert_eq!((e.friction_drive_ratio, e.friction_back_ratio), (0.1, 0.3));
        for bad in [
            "stribeck-nm = 0.1\n",
            "stribeck-nm = -0.1\nstribeck-speed-rad-s = 1.0\n",
            "armature-error = -1.0\n",
            "friction-back-ratio = -0.1\n",
        ] {
            let text = format!("format = 1\ncause = \"x\"\n{bad}");
            assert!(ModelExtension::parse(&text, "b").is_err(), "{bad}");
        }
        // A 1 kg pendulum on 0.1 m released from 0.5 rad with the torque off: the first
        // return through 0, with and without 50 % more armature inertia.
        let swing = |ext: ServoExtension| {
            let d = RobotDescription::nori_a3();
            let r = d.rating("sts3250").unwrap();
            let mut s = Servo::new(1, r.model, r, 0.5, 25.0);
            s.plant.coulomb = 0.0;
            s.extension = ext;
            let mut t = 0.0;
            while s.angle > 0.0 && t < 5.0 {
                s.step(0.0005, Surroundings::BENCH.pendulum(1.0, 0.1, &s, 0.0));
                t += 0.0005;
            }
            t
        };
        let (nominal, heavier) = (
            swing(ServoExtension::default()),
            swing(ServoExtension {
                armature_error: 0.5,
                ..ServoExtension::default()
            }),
        );
        assert!(heavier > 1.1 * nominal, "{heavier} vs {nominal}");

        // Play in the gearbox: a goal swinging ±0.3 rad through zero, a light load. The output
        // lags the motor by up to half the play each time the torque reverses, so the two runs
        // part by about that much.
        let follow = |backlash_rad: f64| {
            let d = RobotDescription::nori_a3();
            let r = d.rating("sts3250").unwrap();
            let mut s = Servo::new(1, r.model, r, 0.0, 25.0);
            s.extension = ServoExtension {
                backlash_rad,
                ..ServoExtension::default()
            };
            s.configure_for_replay(32);
            s.command_torque(true);
            let mut out = Vec::new();
            for k in 0..4000 {
                if k % 20 == 0 {
                    s.command_goal(0.3 * (k as f64 * 0.001 * 3.0).sin());
                }
                s.step(
                    0.001,
                    Surroundings::BENCH
                        .torque(0.5 * s.angle.sin())
                        .inertia(0.005),
                );
                out.push(s.angle);
            }
            out
        };
        let (rigid, loose) = (follow(0.0), follow(0.04));
        let apart = rigid
            .iter()
            .zip(&loose)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!((0.01..0.1).contains(&apart), "{apart}");
        let bad = ModelExtension::parse("format = 1\ncause = \"x\"\nbacklash-rad = -0.01\n", "b");
        assert!(bad.is_err());
    }

    #[test]
    fn bus_applies_neighbour_coupling_and_supply_sag() {
        let d = RobotDescription::nori_a3();
        let desc = d.bus("left_arm").unwrap();
        let run = |ext: &ModelExtension| {
            let mut bus = SimBus::new(&d, desc);
            bus.apply_extension(ext);
            bus.servos[0].temperature = 60.0;
            for _ in 0..30_000 {
                bus.step(0.001);
            }
            (bus.servos[1].temperature, bus.servos[3].temperature)
        };
        let coupled = ModelExtension::parse(
            "format = 1\ncause = \"neighbor_coupling\"\nneighbor-coupling-ratio = 1.0\n",
            "c.toml",
        )
        .unwrap();
        let (n1, n3) = run(&ModelExtension::none());
        let (c1, c3) = run(&coupled);
        assert!(c1 > n1 + 1.0, "neighbour {c1} vs uncoupled {n1}");
        // Heat spreads along the chain, attenuating: the third servo warms far less.
        assert!(c3 - n3 < c1 - n1);
        let bad = ModelExtension::parse(
            "format = 1\ncause = \"x\"\nsensor-time-constant-s = -1.0\n",
            "b",
        );
        assert!(bad
            .unwrap_err()
            .to_string()
            .contains("sensor-time-constant-s"));
        let unknown = ModelExtension::parse("format = 1\ncause = \"x\"\nlag = 1\n", "u");
        assert!(unknown.is_err());
        let mut sag = ModelExtension::none();
        sag.supply_resistance_ohm = Some(0.25);
        let back = ModelExtension::parse(&sag.to_toml(), "rt").unwrap();
        assert_eq!(back, sag);
    }
}
