//! The electrical channel: the constant supply against the sagging one.

use super::*;

/// The electrical channel: its outcome and the fits the figures and the model file need.
pub(super) struct ElectricalOutcome {
    pub(super) channel: ChannelOutcome,
    /// The constant supply.
    pub(super) nominal: ElectricalFit,
    /// The sagging supply, when tried.
    pub(super) sag: Option<ElectricalFit>,
}

/// The electrical channel: the constant supply, and the sagging one when the catalog has it.
pub(super) fn electrical_channel(
    ed: &ElectricalData,
    d: &Dataset,
    opts: &Options,
    hours: f64,
    progress: &mut dyn FnMut(&str),
) -> ElectricalOutcome {
    progress(&format!(
        "electrical: {} motors, {} voltage readings, current {}",
        ed.motors.len(),
        ed.fit_count(),
        ed.current_source
    ));
    let nom = electrical::fit(ed, false);
    let (fit_idx, held_idx) = (
        voltage_indices(ed, 0..ed.split),
        voltage_indices(ed, ed.split..),
    );
    let res = |f: &ElectricalFit, idx: &[Vec<usize>]| -> Vec<Vec<f64>> {
        (0..ed.motors.len())
            .map(|m| residuals_at(&f.predict(ed, m), &ed.voltage[m], &idx[m]))
            .collect()
    };
    let held = res(&nom, &held_idx);
    let regressors = BTreeMap::from([(
        "bus_current".to_string(),
        (0..ed.motors.len())
            .flat_map(|m| held_idx[m].iter().map(move |&k| ed.bus_current[m][k]))
            .collect(),
    )]);
    let floor = NoiseFloor::of(&ed.voltage, data::quantum(&ed.voltage), &d.segments());
    let ids: Vec<i64> = ed.motors.iter().map(|&dm| d.motors[dm]).collect();
    let nominal_verdict = verdict(Channel::Electrical, None, &ids, &held, "V", &floor);
    let mut candidates = Vec::new();
    let sag = opts.candidates.contains(&Effect::SupplySag).then(|| {
        progress("electrical: fitting supply_sag");
        let sag = electrical::fit(ed, true);
        let test = block_wald_test(&res(&nom, &fit_idx), &res(&sag, &fit_idx));
        candidates.push(judge(
            Evidence {
                effect: Effect::SupplySag,
                parameter: Some(Parameter {
                    name: "supply_resistance".into(),
                    value: sag.resistance_ohm,
                    unit: "ohm".into(),
                }),
                base_sse: nom.sse,
                sse: sag.sse,
                test,
                base_res: &held,
                res: &res(&sag, &held_idx),
                iterations: 1,
            },
            &Yardstick {
                before: &nominal_verdict,
                floor: floor.floor,
                hours,
                regimes: None,
            },
        ));
        sag
    });
    let best = best_supported(&candidates, Channel::Electrical);
    let left = match (&sag, best) {
        (Some(sag), Some(_)) => res(sag, &held_idx),
        _ => held.clone(),
    };
    ElectricalOutcome {
        channel: ChannelOutcome {
            misfit: misfit(&held, regressors, "V", floor),
            candidates,
            verdict: verdict(Channel::Electrical, best, &ids, &left, "V", &floor),
            held: held_residuals(&ids, &held_idx, &held),
        },
        nominal: nom,
        sag,
    }
}

/// Per motor, the indices in `range` (to the end of the record) with a voltage reading.
pub(super) fn voltage_indices(
    ed: &ElectricalData,
    range: impl std::ops::RangeBounds<usize> + Clone,
) -> Vec<Vec<usize>> {
    ed.voltage
        .iter()
        .map(|v| {
            (0..v.len())
                .filter(|k| range.contains(k) && v[*k].is_finite())
                .collect()
        })
        .collect()
}
