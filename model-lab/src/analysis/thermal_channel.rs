//! The thermal channel: the nominal model on the register's likelihood, every single
//! extension, then two at once.

use super::*;

/// Prepares the thermal channel, or None when it has nothing to work with.
pub(super) fn thermal_data(d: &Dataset, split: usize) -> Option<ThermalData> {
    let motors: Vec<usize> = (0..d.motors.len())
        .filter(|&m| {
            d.current[m].iter().any(|v| v.is_finite())
                && d.temperature[m][..split]
                    .iter()
                    .filter(|v| v.is_finite())
                    .count()
                    >= 20
        })
        .collect();
    if motors.is_empty() {
        return None;
    }
    let segments = d.segments();
    let fit_segments = segments.iter().filter(|(s, _)| *s < split).count();
    let measured: Vec<Vec<f64>> = motors.iter().map(|&m| d.temperature[m].clone()).collect();
    let valid = |m: usize, r: std::ops::Range<usize>| -> Vec<usize> {
        r.filter(|&k| measured[m][k].is_finite()).collect()
    };
    let pos = |dm: usize| motors.iter().position(|&x| x == dm);
    let data_init = (0..motors.len())
        .map(|m| {
            let fallback = stats::mean(&measured[m]);
            segments
                .iter()
                .map(|&(s, e)| {
                    let mut first: Vec<f64> = measured[m][s..e]
                        .iter()
                        .copied()
                        .filter(|v| v.is_finite())
                        .take(5)
                        .collect();
                    first.sort_by(f64::total_cmp);
                    first.get(first.len() / 2).copied().unwrap_or(fallback)
                })
                .collect()
        })
        .collect();
    Some(ThermalData {
        t: d.t.clone(),
        segments,
        split,
        current: motors
            .iter()
            .map(|&m| electrical::hold(&d.current[m]))
            .collect(),
        neighbours: motors
            .iter()
            .map(|&m| d.neighbours(m).into_iter().filter_map(pos).collect())
            .collect(),
        fit_idx: (0..motors.len()).map(|m| valid(m, 0..split)).collect(),
        held_idx: (0..motors.len())
            .map(|m| valid(m, split..d.t.len()))
            .collect(),
        fit_segments,
        data_init,
        quantum: d.temperature_quantum,
        measured,
        motors,
    })
}

/// Candidate regressors of the thermal residuals, pooled like the residuals (motor-major,
/// held-out readings). Each is what one extension would add to the prediction.
pub(super) fn thermal_regressors(
    td: &ThermalData,
    nominal: &[Vec<f64>],
) -> BTreeMap<String, Vec<f64>> {
    let mut r: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    let t0 = td.t.first().copied().unwrap_or(0.0);
    for m in 0..td.n() {
        let bus_current: Vec<f64> = (0..td.t.len())
            .map(|k| (0..td.n()).map(|j| td.current[j][k].abs()).sum())
            .collect();
        for &k in &td.held_idx[m] {
            let i = td.current[m][k];
            let kp = k.saturating_sub(1);
            let dtk = (td.t[k] - td.t[kp]).max(1e-9);
            let nb = &td.neighbours[m];
            let nb_diff = if nb.is_empty() {
                0.0
            } else {
                nb.iter().map(|&j| nominal[j][k]).sum::<f64>() / nb.len() as f64 - nominal[m][k]
            };
            let push = |r: &mut BTreeMap<String, Vec<f64>>, name: &str, v: f64| {
                r.entry(name.to_string()).or_default().push(v)
            };
            push(&mut r, "current_squared", i * i);
            push(&mut r, "current", i);
            push(
                &mut r,
                "temperature_x_current_squared",
                nominal[m][k] * i * i,
            );
            push(&mut r, "time", td.t[k] - t0);
            push(&mut r, "neighbor_temperature_difference", nb_diff);
            push(
                &mut r,
                "temperature_rate",
                (nominal[m][k] - nominal[m][kp]) / dtk,
            );
            push(&mut r, "bus_current", bus_current[k]);
        }
    }
    r
}

/// The thermal channel: its outcome and the fits the figures and the model file need.
pub(super) struct ThermalOutcome {
    pub(super) channel: ChannelOutcome,
    /// The register's noise, as estimated with the nominal model, °C.
    pub(super) register_noise: f64,
    /// The nominal model's fit and its predictions.
    pub(super) nominal: (ThermalFit, Vec<Vec<f64>>),
    /// The fit the channel's verdict is judged with, when an extension is supported: the
    /// named pair's, or the best single's.
    pub(super) best: Option<(ThermalFit, Vec<Vec<f64>>)>,
    /// Two effects named together.
    pub(super) pair: Option<NamedPair>,
    /// The form of the nominal model's misfit, when searched ([`Options::search_form`]).
    pub(super) form: Option<crate::form::Form>,
}

/// Two thermal effects named together, each with the value it took beside the other.
#[derive(Debug, Clone, Copy)]
pub(super) struct NamedPair {
    pub(super) first: Effect,
    pub(super) second: Effect,
    pub(super) values: (f64, f64),
}

/// The thermal channel's nominal model on the register's likelihood, with the register
/// estimated from a least-squares fit first.
pub(super) fn thermal_nominal(
    td: &ThermalData,
    progress: &mut dyn FnMut(&str),
) -> (ThermalFit, Register) {
    progress(&format!(
        "thermal: fitting the nominal model on {} motors, {} readings",
        td.n(),
        td.fit_count()
    ));
    let ls = fit_nominal(td);
    let ls_pred = ThermalModel::new(td, Effect::None).predict(&ls.p);
    let ls_res: Vec<f64> = (0..td.n())
        .flat_map(|m| residuals_at(&ls_pred[m], &td.measured[m], &td.fit_idx[m]))
        .collect();
    let reg = Register::estimate(td.quantum, &ls_res);
    progress(&format!(
        "thermal: refitting on the register's likelihood (step {} °C, noise {:.3} °C)",
        td.quantum,
        reg.sigma()
    ));
    (refit_nominal(td, &ls, &reg), reg)
}

/// Held-out residuals per motor of the thermal predictions `pred`.
pub(super) fn thermal_held(td: &ThermalData, pred: &[Vec<f64>]) -> Vec<Vec<f64>> {
    (0..td.n())
        .map(|m| residuals_at(&pred[m], &td.measured[m], &td.held_idx[m]))
        .collect()
}

/// What the thermal channel's tries share: its data, the register, the nominal model and
/// what extensions are judged against.
pub(super) struct ThermalTries<'a> {
    pub(super) td: &'a ThermalData,
    pub(super) reg: &'a Register,
    pub(super) nominal: &'a ThermalFit,
    pub(super) nominal_pred: &'a [Vec<f64>],
    pub(super) nominal_held: &'a [Vec<f64>],
    pub(super) against_nominal: Yardstick<'a>,
    /// Motor ids, in the channel's order.
    pub(super) ids: &'a [i64],
    pub(super) floor: &'a NoiseFloor,
}

/// A single thermal extension as tried: its fit and predictions.
pub(super) type ThermalSingle = (Effect, ThermalFit, Vec<Vec<f64>>);

/// The thermal channel: the nominal model, every single extension, then pairs.
pub(super) fn thermal_channel(
    td: &ThermalData,
    d: &Dataset,
    opts: &Options,
    hours: f64,
    progress: &mut dyn FnMut(&str),
) -> ThermalOutcome {
    let (nom, reg) = thermal_nominal(td, progress);
    let nom_pred = ThermalModel::new(td, Effect::None).predict(&nom.p);
    let held = thermal_held(td, &nom_pred);
    let floor = NoiseFloor::of(&td.measured, td.quantum, &td.segments);
    let ids: Vec<i64> = td.motors.iter().map(|&dm| d.motors[dm]).collect();
    let nominal_verdict = verdict(Channel::Thermal, None, &ids, &held, "°C", &floor);
    let held_currents: Vec<Vec<f64>> = (0..td.n())
        .map(|m| td.held_idx[m].iter().map(|&k| td.current[m][k]).collect())
        .collect();
    let regimes = Regimes::of(&held_currents, &ids);
    let tries = ThermalTries {
        td,
        reg: &reg,
        nominal: &nom,
        nominal_pred: &nom_pred,
        nominal_held: &held,
        against_nominal: Yardstick {
            before: &nominal_verdict,
            floor: floor.floor,
            hours,
            regimes: Some(&regimes),
        },
        ids: &ids,
        floor: &floor,
    };
    let (mut candidates, singles) = tries.singles(&opts.candidates, progress);
    let mut best = best_supported(&candidates, Channel::Thermal);
    let mut chosen = best.and_then(|b| {
        singles
            .iter()
            .find(|(e, _, _)| *e == b)
            .map(|(_, f, p)| (f.clone(), p.clone()))
    });
    let pair = tries.pairs(best, &singles, &mut candidates, progress);
    if let Some((named, fit, pred)) = &pair {
        best = Some(named.first);
        chosen = Some((fit.clone(), pred.clone()));
    }
    let left = thermal_held(td, chosen.as_ref().map_or(&nom_pred, |(_, p)| p));
    let form = (opts.search_form && td.n() <= crate::form::MAX_MOTORS).then(|| {
        progress("thermal: searching the misfit's form");
        super::thermal_form::thermal_form(d, td, &nom, &nom_pred)
    });
    ThermalOutcome {
        channel: ChannelOutcome {
            misfit: misfit(&held, thermal_regressors(td, &nom_pred), "°C", floor),
            candidates,
            verdict: verdict(Channel::Thermal, best, &ids, &left, "°C", &floor),
            held: held_residuals(&ids, &td.held_idx, &held),
        },
        register_noise: reg.sigma(),
        nominal: (nom, nom_pred),
        best: chosen,
        pair: pair.map(|(named, _, _)| named),
        form,
    }
}

impl ThermalTries<'_> {
    /// Every thermal extension of `catalog` fitted alone and judged against the nominal
    /// model: the candidates and their fits, in catalog order.
    pub(super) fn singles(
        &self,
        catalog: &[Effect],
        progress: &mut dyn FnMut(&str),
    ) -> (Vec<Candidate>, Vec<ThermalSingle>) {
        let td = self.td;
        let mut candidates = Vec::new();
        let mut fits = Vec::new();
        for (i, &effect) in catalog
            .iter()
            .filter(|e| {
                e.channel() == Channel::Thermal && !matches!(e, Effect::None | Effect::Unexplained)
            })
            .enumerate()
        {
            if effect == Effect::NeighborCoupling && td.neighbours.iter().all(Vec::is_empty) {
                continue;
            }
            progress(&format!("thermal: fitting {effect} ({})", i + 1));
            let fit = fit_extension(td, self.nominal, effect, Some(self.reg));
            let model = ThermalModel::new(td, effect);
            let pred = model.predict(&fit.p);
            let parameter = effect.parameter().map(|(name, unit)| Parameter {
                name: name.into(),
                value: model.decode(&fit.p).extension,
                unit: unit.into(),
            });
            let test = deviance_test(
                td,
                self.reg,
                self.nominal_pred,
                &pred,
                self.nominal.sse,
                fit.sse,
            );
            candidates.push(judge(
                Evidence {
                    effect,
                    parameter,
                    base_sse: self.nominal.sse,
                    sse: fit.sse,
                    test,
                    base_res: self.nominal_held,
                    res: &thermal_held(td, &pred),
                    iterations: fit.iterations,
                },
                &self.against_nominal,
            ));
            fits.push((effect, fit, pred));
        }
        (candidates, fits)
    }

    /// Two effects at once: the best supported single (or, without one, the strongest
    /// significant one: two effects can spoil each other's held-out test alone) fitted
    /// together with each other one (an effect can hide another: a drift masks a lag until
    /// the drift is modelled). A second is named beside the first when it passes every test
    /// against the first alone; among several, the strongest ([`stronger_second`]). Each
    /// second tried is pushed to `candidates`; a first that stood only with its second is
    /// marked supported beside it. The named pair with its fit and predictions.
    pub(super) fn pairs(
        &self,
        best: Option<Effect>,
        singles: &[ThermalSingle],
        candidates: &mut Vec<Candidate>,
        progress: &mut dyn FnMut(&str),
    ) -> Option<(NamedPair, ThermalFit, Vec<Vec<f64>>)> {
        let base = best.or_else(|| strongest_significant(candidates, Channel::Thermal))?;
        let (a, fa, base_pred) = singles.iter().find(|(e, _, _)| *e == base)?;
        let base_held = thermal_held(self.td, base_pred);
        let after_first = verdict(
            Channel::Thermal,
            Some(*a),
            self.ids,
            &base_held,
            "°C",
            self.floor,
        );
        let against_first = Yardstick {
            before: &after_first,
            ..self.against_nominal
        };
        let first = (*a, fa, &base_pred[..], &base_held[..]);
        let mut best_pair: Option<PairFit> = None;
        for (b, fb, _) in singles.iter().filter(|(e, _, _)| e != a) {
            progress(&format!("thermal: fitting {a} with {b}"));
            let pair = self.second(first, (*b, fb), &against_first, best.is_none());
            let candidate = pair.candidate.clone();
            if candidate.verdict.supported()
                && best_pair
                    .as_ref()
                    .is_none_or(|p| stronger_second(&candidate, &p.candidate))
            {
                best_pair = Some(pair);
            }
            candidates.push(candidate);
        }
        let p = best_pair?;
        // A first that stood only with its second is supported now, and says so.
        if let Some(c) = candidates
            .iter_mut()
            .find(|c| c.id == *a && c.with.is_none() && !c.verdict.supported())
        {
            c.verdict = Verdict::SupportedBeside {
                second: p.candidate.id,
                alone: Box::new(c.verdict.clone()),
            };
        }
        let named = NamedPair {
            first: *a,
            second: p.candidate.id,
            values: p.values,
        };
        Some((named, p.fit, p.prediction))
    }

    /// The second `b` fitted beside the first `a` (its fit, predictions and held-out
    /// residuals) and judged against the first alone; with `alone_unsupported` (the first
    /// was no supported extension on its own), the pair must stand against the nominal
    /// model too.
    pub(super) fn second(
        &self,
        (a, fa, base_pred, base_held): (Effect, &ThermalFit, &[Vec<f64>], &[Vec<f64>]),
        (b, fb): (Effect, &ThermalFit),
        against_first: &Yardstick,
        alone_unsupported: bool,
    ) -> PairFit {
        let td = self.td;
        let pair = fit_pair(td, fa, fb, Some(self.reg));
        let model = pair.model(td);
        let pair_pred = model.predict(&pair.p);
        let decoded = model.decode(&pair.p);
        let pair_held = thermal_held(td, &pair_pred);
        let test = deviance_test(td, self.reg, base_pred, &pair_pred, fa.sse, pair.sse);
        let parameter = b.parameter().map(|(name, unit)| Parameter {
            name: name.into(),
            value: decoded.second_extension,
            unit: unit.into(),
        });
        // The second against the first alone, under the fitting part's test or another.
        let judge_second = |test: FitTest| {
            judge(
                Evidence {
                    effect: b,
                    parameter: parameter.clone(),
                    base_sse: fa.sse,
                    sse: pair.sse,
                    test,
                    base_res: base_held,
                    res: &pair_held,
                    iterations: pair.iterations,
                },
                against_first,
            )
        };
        let mut c = judge_second(test);
        // The second is often nearly collinear with the first on the fitting part (a current
        // offset and copper's coefficient both scale the heating) and shows where the winding
        // runs hottest, in the held-out part: where the fitting part alone falls short, its
        // test and the held-out slope's decide together.
        let alpha = ALPHA / Effect::CATALOG.len() as f64;
        if !c.verdict.supported() && c.plausible && (c.p_value >= alpha || c.delta_bic <= 0.0) {
            let alone = Box::new(c.verdict.clone());
            let combined = judge_second(test.with_heldout(c.heldout_slope_t));
            if combined.verdict.supported() {
                c = Candidate {
                    verdict: Verdict::SupportedWithHeldout {
                        fisher_p: combined.p_value,
                        alone,
                    },
                    ..combined
                };
            }
        }
        c.with = Some(a);
        if c.verdict.supported() && alone_unsupported {
            let pair_param = a.parameter().map(|(name, unit)| Parameter {
                name: name.into(),
                value: decoded.extension,
                unit: unit.into(),
            });
            // Two parameters against the nominal model: χ²(2), two BIC penalties.
            let test = deviance_test(
                td,
                self.reg,
                self.nominal_pred,
                &pair_pred,
                self.nominal.sse,
                pair.sse,
            )
            .with_params(2.0);
            let whole = judge(
                Evidence {
                    effect: a,
                    parameter: pair_param,
                    base_sse: self.nominal.sse,
                    sse: pair.sse,
                    test,
                    base_res: self.nominal_held,
                    res: &pair_held,
                    iterations: pair.iterations,
                },
                &self.against_nominal,
            );
            if !whole.verdict.supported() {
                c.verdict = Verdict::PairNotSupported {
                    first: a,
                    whole: Box::new(whole.verdict),
                };
            }
        }
        // The first's parameter, refitted beside the second, must still be physical.
        if c.verdict.supported()
            && !a
                .bounds()
                .is_none_or(|(lo, hi, _)| (lo..=hi).contains(&decoded.extension))
        {
            c.verdict = Verdict::FirstOutsidePhysics {
                first: a,
                value: decoded.extension,
            };
        }
        PairFit {
            candidate: c,
            fit: pair,
            prediction: pair_pred,
            values: (decoded.extension, decoded.second_extension),
        }
    }
}

/// A pair of thermal extensions fitted together, as tried.
pub(super) struct PairFit {
    /// The second's candidate (tried beside the first).
    pub(super) candidate: Candidate,
    /// The pair's fit.
    pub(super) fit: ThermalFit,
    /// Its predictions.
    pub(super) prediction: Vec<Vec<f64>>,
    /// The first's and the second's parameters, in the catalog's units.
    pub(super) values: (f64, f64),
}
