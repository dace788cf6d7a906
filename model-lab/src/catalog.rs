//! The catalog of model extensions: what the nominal model may be missing.

use serde::{Deserialize, Serialize};

/// Which measured quantity an extension predicts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Channel {
    /// The temperature register, °C.
    Thermal,
    /// The supply voltage seen by the servos, V.
    Electrical,
    /// The output shaft's position, rad.
    Motion,
}

/// One extension of the nominal model (or none).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Effect {
    /// No extension is supported by the data.
    None,
    /// The sensor reads a second, lagging thermal node, not the winding.
    SensorLag,
    /// Heat flows between adjacent motors of a chain.
    NeighborCoupling,
    /// Winding resistance rises with temperature (copper: 0.393 %/K).
    CopperTempco,
    /// The ambient temperature drifts (linearly over the record).
    AmbientDrift,
    /// The supply voltage drops with the total current of the bus.
    SupplySag,
    /// The current register reads with an offset.
    CurrentOffset,
    /// The nominal model misses more than the data's noise and no catalog entry explains it.
    Unexplained,
    /// Friction higher at rest than in motion (Stribeck): breakaway fading with speed.
    Stribeck,
    /// Friction proportional to the torque the gearbox carries.
    LoadFriction,
    /// Gearbox friction that differs between driving the load and being driven back by it.
    DirectionalFriction,
    /// The reflected (armature) inertia differs from the rating's.
    ArmatureError,
    /// The firmware's position-loop gain differs from the configured one.
    FirmwareGain,
    /// Play in the gearbox between the motor and the output.
    Backlash,
}

impl Effect {
    /// Every thermal and electrical extension, in the order they are tried (the motion
    /// channel's are [`crate::motion::MOTION_CATALOG`]).
    pub const CATALOG: [Effect; 6] = [
        Effect::SensorLag,
        Effect::NeighborCoupling,
        Effect::CopperTempco,
        Effect::AmbientDrift,
        Effect::SupplySag,
        Effect::CurrentOffset,
    ];

    /// The catalog id.
    pub fn id(self) -> &'static str {
        match self {
            Effect::None => "none",
            Effect::SensorLag => "sensor_lag",
            Effect::NeighborCoupling => "neighbor_coupling",
            Effect::CopperTempco => "copper_tempco",
            Effect::AmbientDrift => "ambient_drift",
            Effect::SupplySag => "supply_sag",
            Effect::CurrentOffset => "current_offset",
            Effect::Unexplained => "unexplained",
            Effect::Stribeck => "stribeck",
            Effect::LoadFriction => "load_friction",
            Effect::DirectionalFriction => "directional_friction",
            Effect::ArmatureError => "armature_error",
            Effect::FirmwareGain => "firmware_gain",
            Effect::Backlash => "backlash",
        }
    }

    /// The effect of an id.
    pub fn from_id(id: &str) -> Option<Effect> {
        [Effect::None, Effect::Unexplained]
            .into_iter()
            .chain(Effect::CATALOG)
            .chain(crate::motion::MOTION_CATALOG)
            .find(|e| e.id() == id)
    }

    /// The extension's parameter: name and unit (one per extension, shared by all motors).
    pub fn parameter(self) -> Option<(&'static str, &'static str)> {
        match self {
            Effect::None | Effect::Unexplained => None,
            Effect::SensorLag => Some(("sensor_time_constant", "s")),
            // Conductance to each neighbour over the motor's own conductance to ambient.
            Effect::NeighborCoupling => Some(("coupling_ratio", "1")),
            Effect::CopperTempco => Some(("resistance_tempco", "%/K")),
            Effect::AmbientDrift => Some(("ambient_drift", "K/h")),
            Effect::SupplySag => Some(("supply_resistance", "ohm")),
            Effect::CurrentOffset => Some(("current_offset", "A")),
            // The motion entries' parameters (several for some) are `motion::extension_params`;
            // the first is named here.
            e => crate::motion::extension_params(e)
                .first()
                .map(|p| (p.name, p.unit)),
        }
    }

    /// The size below which the extension's parameter (catalog unit, in magnitude) is no
    /// finding whatever it predicts, and why: within what the nominal model's own tolerances,
    /// the registers or the readings' noise already allow, for a record of `hours` whose
    /// channel has the noise floor `noise_floor`. (A fit that needs the extension's shape at a
    /// negligible size is fitting something else. The bounds of [`Effect::bounds`] already
    /// exclude negligible sizes of the others; the motion entries' are
    /// `motion::MotionParam::negligible`.)
    pub fn negligible(self, hours: f64, noise_floor: f64) -> Option<(f64, &'static str)> {
        match self {
            Effect::NeighborCoupling => Some((
                0.02,
                "a neighbour's heat conducted at under 2 % of the motor's own path to the air \
                 is within the nominal thermal resistance's own uncertainty",
            )),
            Effect::AmbientDrift if hours > 0.0 => Some((
                noise_floor / hours,
                "a drift that moves the ambient by less than the temperature's noise floor \
                 over the whole record is the readings' own noise",
            )),
            Effect::CurrentOffset => Some((
                0.01,
                "an offset under 10 mA is within about one and a half steps of the 6.5 mA \
                 current register",
            )),
            _ => None,
        }
    }

    /// The range the extension's parameter can take under its physics (catalog unit), and
    /// why. A fit outside it is evidence against the name, not a finding.
    pub fn bounds(self) -> Option<(f64, f64, &'static str)> {
        match self {
            Effect::None | Effect::Unexplained => None,
            Effect::SensorLag => Some((
                1.0,
                1800.0,
                "a sensor node lagging the winding by seconds to half an hour (slower is the \
                 case itself, the nominal time constant)",
            )),
            Effect::NeighborCoupling => Some((
                0.0,
                2.0,
                "heat flows from the hotter motor (≥ 0), through a bracket at most about twice \
                 as well as to the air",
            )),
            Effect::CopperTempco => Some((
                0.2,
                1.0,
                "copper's 0.393 %/K, up to 2.5 times that per kelvin of a sensor that sees only \
                 part of the winding's rise; below half of copper's is no copper",
            )),
            Effect::AmbientDrift => Some((
                -10.0,
                10.0,
                "a room warms or cools by at most about 10 K an hour",
            )),
            Effect::SupplySag => Some((
                0.005,
                2.0,
                "a battery's or a supply's internal resistance with its wiring: 5 mΩ to 2 Ω",
            )),
            Effect::CurrentOffset => Some((
                -0.5,
                0.5,
                "a current sensor's offset is a fraction of its 3 A range: at most 0.5 A",
            )),
            // The motion entries' ranges are their fits' bounds (`motion::extension_params`).
            e => crate::motion::extension_params(e)
                .first()
                .map(|p| (p.lo, p.hi, "the range of `motion::extension_params`")),
        }
    }

    /// One line on what the extension adds.
    pub fn describe(self) -> &'static str {
        match self {
            Effect::None => "no extension: the nominal model fits to within the data's noise",
            Effect::Unexplained => {
                "the nominal model misses more than the data's noise, and no catalog entry \
                 explains it"
            }
            Effect::SensorLag => "the sensor reads a second node lagging the winding",
            Effect::NeighborCoupling => "heat flows between adjacent motors of a chain",
            Effect::CopperTempco => "winding resistance rises with temperature",
            Effect::AmbientDrift => "the ambient temperature drifts",
            Effect::SupplySag => "the supply voltage drops with the bus current",
            Effect::CurrentOffset => "the current register reads with an offset",
            Effect::Stribeck => "friction is higher at rest than in motion (Stribeck)",
            Effect::LoadFriction => "friction grows with the torque the gearbox carries",
            Effect::DirectionalFriction => {
                "the gearbox's friction differs between driving the load and being back-driven"
            }
            Effect::ArmatureError => "the reflected inertia differs from the rating's",
            Effect::FirmwareGain => "the firmware's position gain differs from the configured",
            Effect::Backlash => "the gearbox has play between the motor and the output",
        }
    }

    /// The measured quantity the extension changes.
    pub fn channel(self) -> Channel {
        match self {
            Effect::SupplySag => Channel::Electrical,
            Effect::Stribeck
            | Effect::LoadFriction
            | Effect::DirectionalFriction
            | Effect::ArmatureError
            | Effect::FirmwareGain
            | Effect::Backlash => Channel::Motion,
            _ => Channel::Thermal,
        }
    }
}

impl std::fmt::Display for Effect {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.id())
    }
}
