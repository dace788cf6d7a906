//! The servo constants the simulator runs, per model: the robot description's rating, and
//! where the model lab found a rating wrong on measured runs, its finding on top (the motion
//! extension and the friction it was calibrated with), shipped in `sim/constants/<model>.toml`
//! as `nori model analyze --model-out` wrote it, with the runs it was fitted on. The runs it
//! names are not all the data: the ones left out are where the gain is checked
//! (`docs/model-lab.md`, "The lab's findings in the simulator").

use crate::extension::{ExtensionError, ModelExtension};
use feetech::registers::ServoModel;

/// The findings shipped with the simulator, each its model's.
const SHIPPED: [(ServoModel, &str, &str); 1] = [(
    ServoModel::Sts3250,
    "sim/constants/sts3250.toml",
    include_str!("../constants/sts3250.toml"),
)];

/// Which constants a simulated servo runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ConstantsChoice {
    /// The description's ratings, with the model lab's shipped findings on top.
    Fitted,
    /// The description's ratings alone.
    Rated,
}

/// One servo model's finding, as the simulator runs it.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelConstants {
    /// The servo model.
    pub model: ServoModel,
    /// Where the finding was read from.
    pub origin: String,
    /// The model lab's file.
    pub finding: ModelExtension,
}

impl ModelConstants {
    /// A finding for `model` read from `text` (`origin` names it in errors): a model extension
    /// whose motion part was fitted on this model, with nothing that belongs to a bus rather
    /// than a servo (a neighbour's coupling, the ambient, the supply's wiring).
    pub fn parse(model: ServoModel, text: &str, origin: &str) -> Result<Self, ExtensionError> {
        let finding = ModelExtension::parse(text, origin)?;
        let invalid = |key: &str, reason: String| ExtensionError::Invalid {
            path: origin.into(),
            key: key.into(),
            reason,
        };
        if finding.servo.as_deref() != Some(model.key()) {
            return Err(invalid(
                "servo",
                format!(
                    "fitted on {}, not on {}",
                    finding.servo.as_deref().unwrap_or("no servo model"),
                    model.key()
                ),
            ));
        }
        for (key, set) in [
            (
                "neighbor-coupling-ratio",
                finding.neighbor_coupling_ratio.is_some(),
            ),
            (
                "ambient-drift-k-per-h",
                finding.ambient_drift_k_per_h.is_some(),
            ),
            (
                "supply-resistance-ohm",
                finding.supply_resistance_ohm.is_some(),
            ),
        ] {
            if set {
                return Err(invalid(
                    key,
                    "a bus's constant, not a servo model's: apply it to a bus".into(),
                ));
            }
        }
        Ok(ModelConstants {
            model,
            origin: origin.into(),
            finding,
        })
    }

    /// What it changes from the rating, and where it came from, in a line.
    pub fn describe(&self) -> String {
        let f = &self.finding;
        let mut changes = Vec::new();
        if let Some(e) = f.armature_error {
            changes.push(format!("reflected inertia {:+.0} %", 100.0 * e));
        }
        if let Some(e) = f.duty_gain_error {
            changes.push(format!("position loop's gain {:+.0} %", 100.0 * e));
        }
        if let Some(b) = f.backlash_rad {
            changes.push(format!("play {b:.4} rad"));
        }
        if let Some(s) = f.stribeck_nm {
            changes.push(format!("Stribeck {s:.3} N·m"));
        }
        if let Some(r) = f.friction_drive_ratio {
            changes.push(format!(
                "torque-proportional friction {r:.3} (back-driven {:.3})",
                f.friction_back_ratio.unwrap_or(r)
            ));
        }
        if let Some(c) = f.fitted_coulomb_nm {
            changes.push(format!("Coulomb {c:.3} N·m"));
        }
        if let Some(v) = f.fitted_viscous_nms {
            changes.push(format!("viscous {v:.3} N·m·s/rad"));
        }
        let gain = f.motion_heldout_gain.map_or(String::new(), |g| {
            format!(", held-out error {:+.1} %", -100.0 * g)
        });
        let left = if f.motion_misfit_left {
            "; a misfit beyond it is still unexplained"
        } else {
            ""
        };
        format!(
            "{}: the model lab's `{}` ({}), fitted on {} run(s){gain}{left} [{}]",
            self.model.key(),
            f.cause,
            changes.join(", "),
            f.fitted_on.len(),
            self.origin
        )
    }
}

/// The findings the simulator ships, for `choice` (none for the ratings alone).
pub fn shipped(choice: ConstantsChoice) -> Result<Vec<ModelConstants>, ExtensionError> {
    match choice {
        ConstantsChoice::Rated => Ok(Vec::new()),
        ConstantsChoice::Fitted => SHIPPED
            .iter()
            .map(|(model, origin, text)| ModelConstants::parse(*model, text, origin))
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    #[test]
    fn the_shipped_findings_parse_and_say_where_they_came_from() {
        let all = shipped(ConstantsChoice::Fitted).unwrap();
        assert_eq!(all.len(), SHIPPED.len());
        for c in &all {
            assert!(!c.finding.fitted_on.is_empty(), "{}", c.describe());
            assert!(c.describe().contains(c.model.key()));
        }
        assert!(shipped(ConstantsChoice::Rated).unwrap().is_empty());
    }

    #[test]
    fn a_finding_for_another_model_or_a_bus_is_refused() {
        let text = "format = 1\ncause = \"armature_error\"\nservo = \"sts3215\"\n\
                    armature-error = -0.5\n";
        let e = ModelConstants::parse(ServoModel::Sts3250, text, "x.toml").unwrap_err();
        assert!(e.to_string().contains("not on sts3250"), "{e}");
        let text = "format = 1\ncause = \"supply_sag\"\nservo = \"sts3250\"\n\
                    supply-resistance-ohm = 0.2\n";
        let e = ModelConstants::parse(ServoModel::Sts3250, text, "x.toml").unwrap_err();
        assert!(e.to_string().contains("a bus's constant"), "{e}");
        let text = "format = 1\ncause = \"armature_error\"\narmature-error = -0.5\n";
        let e = ModelConstants::parse(ServoModel::Sts3250, text, "x.toml").unwrap_err();
        assert!(e.to_string().contains("no servo model"), "{e}");
    }
}
