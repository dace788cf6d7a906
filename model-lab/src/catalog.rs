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
}

impl Effect {
    /// Every extension, in the order they are tried.
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
        }
    }

    /// The effect of an id.
    pub fn from_id(id: &str) -> Option<Effect> {
        std::iter::once(Effect::None)
            .chain(Effect::CATALOG)
            .find(|e| e.id() == id)
    }

    /// The extension's parameter: name and unit (one per extension, shared by all motors).
    pub fn parameter(self) -> Option<(&'static str, &'static str)> {
        match self {
            Effect::None => None,
            Effect::SensorLag => Some(("sensor_time_constant", "s")),
            // Conductance to each neighbour over the motor's own conductance to ambient.
            Effect::NeighborCoupling => Some(("coupling_ratio", "1")),
            Effect::CopperTempco => Some(("resistance_tempco", "%/K")),
            Effect::AmbientDrift => Some(("ambient_drift", "K/h")),
            Effect::SupplySag => Some(("supply_resistance", "ohm")),
            Effect::CurrentOffset => Some(("current_offset", "A")),
        }
    }

    /// One line on what the extension adds.
    pub fn describe(self) -> &'static str {
        match self {
            Effect::None => "no extension: the nominal model is as good as the data can tell",
            Effect::SensorLag => "the sensor reads a second node lagging the winding",
            Effect::NeighborCoupling => "heat flows between adjacent motors of a chain",
            Effect::CopperTempco => "winding resistance rises with temperature",
            Effect::AmbientDrift => "the ambient temperature drifts",
            Effect::SupplySag => "the supply voltage drops with the bus current",
            Effect::CurrentOffset => "the current register reads with an offset",
        }
    }

    /// The measured quantity the extension changes.
    pub fn channel(self) -> Channel {
        match self {
            Effect::SupplySag => Channel::Electrical,
            _ => Channel::Thermal,
        }
    }
}

impl std::fmt::Display for Effect {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.id())
    }
}
