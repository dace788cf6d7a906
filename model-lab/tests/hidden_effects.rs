//! Hidden-effect tests: the generator hides one effect of the catalog (or none) in measured-like
//! data — integer °C register, sensor noise, 0 °C / 150 °C read glitches, empty cells and dropped
//! rows, a quantised current register — and the lab must name it and recover its parameter.
//!
//! Fixed seeds, fixed sizes well inside the generator's range (the benchmark,
//! `nori model bench`, covers random sizes over ≥ 50 seeds and the detection limits). Records
//! are 2 h at 2 s per sample on 3–4 motors to keep the suite short in debug builds.

#![allow(missing_docs, clippy::unwrap_used, clippy::expect_used)]

use model_lab::audit::Action;
use model_lab::generate::{generate, Generated, Spec};
use model_lab::{analyze, Analysis, Effect, Options};

fn spec(effect: Effect, size: Option<f64>, motors: usize) -> Spec {
    Spec {
        size,
        motors: Some(motors),
        period_s: 2.0,
        ..Spec::new(effect)
    }
}

fn run(g: &Generated) -> (Analysis, sim::extension::ModelExtension) {
    let d = g.dataset().unwrap();
    let out = analyze(d, &Options::default(), &mut |_| {}).unwrap();
    (out.analysis, out.model)
}

/// Names the effect and recovers its parameter within `tol` (relative).
fn hidden(effect: Effect, size: f64, motors: usize, seed: u64, tol: f64) -> Analysis {
    let g = generate(&spec(effect, Some(size), motors), seed);
    let (a, model) = run(&g);
    assert_eq!(
        a.cause, effect,
        "seed {seed}: hid {effect} = {size}, named {} (candidates: {:#?})",
        a.cause, a.diagnostics.candidates
    );
    let (name, unit) = effect.parameter().unwrap();
    assert_eq!(a.parameters.len(), 1);
    let p = &a.parameters[0];
    assert_eq!((p.name.as_str(), p.unit.as_str()), (name, unit));
    let err = (p.value - size).abs() / size.abs();
    assert!(
        err <= tol,
        "{effect}: recovered {} {unit} for {size} {unit} ({:.1} % > {:.0} %)",
        p.value,
        100.0 * err,
        100.0 * tol
    );
    // The extension reduces the held-out error, and the model file names it.
    assert!(a.gain > 0.0 && a.extended_rmse < a.baseline_rmse, "{a:#?}");
    assert_eq!(model.cause, effect.id());
    // The data were dirty: glitches were rejected, the register is integer °C.
    assert!(a.diagnostics.cleaning.temperature_glitches > 0);
    assert!(a.diagnostics.cleaning.temperature_missing > 0);
    assert_eq!(a.diagnostics.temperature_quantum_c, 1.0);
    a
}

#[test]
fn sensor_lag_is_named_and_its_time_constant_recovered() {
    hidden(Effect::SensorLag, 120.0, 3, 11, 0.15);
}

#[test]
fn neighbor_coupling_is_named_and_its_ratio_recovered() {
    hidden(Effect::NeighborCoupling, 0.5, 4, 12, 0.15);
}

#[test]
fn copper_tempco_is_named_and_its_coefficient_recovered() {
    // The weakest effect of the catalog (a few hundredths of a kelvin under a 1 °C register);
    // these records carry half the bench's samples, so a larger coefficient, on four motors.
    hidden(Effect::CopperTempco, 0.7, 4, 17, 0.15);
}

#[test]
fn ambient_drift_is_named_and_its_rate_recovered() {
    hidden(Effect::AmbientDrift, -2.5, 3, 14, 0.15);
}

#[test]
fn supply_sag_is_named_and_its_resistance_recovered() {
    let a = hidden(Effect::SupplySag, 0.15, 3, 15, 0.15);
    // A non-thermal cause reports its own channel's figures, in volts.
    assert_eq!(a.unit, "V");
}

#[test]
fn current_offset_is_named_and_its_offset_recovered() {
    hidden(Effect::CurrentOffset, 0.12, 3, 16, 0.15);
}

#[test]
fn data_without_an_effect_give_none() {
    for seed in [21, 22] {
        let g = generate(&spec(Effect::None, None, 4), seed);
        let (a, model) = run(&g);
        assert_eq!(a.cause, Effect::None, "seed {seed}: {:#?}", a.diagnostics);
        assert!(a.parameters.is_empty());
        assert_eq!(a.gain, 0.0);
        assert_eq!(model.cause, "none");
        // Every extension was tried and refused.
        assert_eq!(a.diagnostics.candidates.len(), Effect::CATALOG.len());
        assert!(a
            .diagnostics
            .candidates
            .iter()
            .all(|c| !c.verdict.supported()));
        // The register's noise is recovered from integer readings (the nominal model is the
        // truth here, so its misfit adds nothing).
        let sigma = a.diagnostics.register_noise_c.unwrap();
        let truth = g.truth.sensor_noise_c;
        assert!(
            (sigma / truth - 1.0).abs() < 0.3,
            "seed {seed}: σ estimated {sigma:.3} °C, truth {truth:.3} °C"
        );
    }
}

#[test]
fn json_carries_the_required_fields() {
    let g = generate(&spec(Effect::AmbientDrift, Some(3.0), 2), 31);
    let (a, _) = run(&g);
    let v = serde_json::to_value(&a).unwrap();
    assert_eq!(v["cause"], "ambient_drift");
    assert_eq!(v["parameters"][0]["name"], "ambient_drift");
    assert_eq!(v["parameters"][0]["unit"], "K/h");
    assert!(v["parameters"][0]["value"].is_f64());
    for key in ["baseline_rmse_c", "extended_rmse_c", "gain"] {
        assert!(v[key].is_f64(), "{key}: {}", v[key]);
    }
    assert!(v["baseline_rmse_c"].as_f64() > v["extended_rmse_c"].as_f64());
    assert_eq!(v["motors"].as_array().map(Vec::len), Some(2));
    assert!(v["motors"][0]["baseline_rmse_c"].is_f64());
    let diag = &v["diagnostics"];
    assert!(diag["thermal"]["ljung_box_p"].is_f64());
    assert!(diag["thermal"]["correlations"]["time"].is_f64());
    // Every extension alone, then each other one beside the best (a pair fitted together).
    let candidates = diag["candidates"].as_array().unwrap();
    let alone = candidates.iter().filter(|c| c["with"].is_null()).count();
    let beside = candidates
        .iter()
        .filter(|c| c["with"] == "ambient_drift")
        .count();
    assert_eq!((alone, beside, candidates.len()), (6, 4, 10));
}

#[test]
fn the_report_has_the_plots() {
    let g = generate(&spec(Effect::SensorLag, Some(90.0), 2), 32);
    let out = analyze(g.dataset().unwrap(), &Options::default(), &mut |_| {}).unwrap();
    let files = model_lab::report::render(&out.analysis, &out.traces, "generated");
    let names: Vec<&str> = files.iter().map(|(n, _)| n.as_str()).collect();
    for want in [
        "report.md",
        "motor-1.svg",
        "motor-2.svg",
        "residual-acf.svg",
    ] {
        assert!(names.contains(&want), "{want} missing from {names:?}");
    }
    let text = |n: &str| &files.iter().find(|(f, _)| f == n).unwrap().1;
    assert!(text("report.md").contains("sensor_lag"));
    assert!(text("report.md").contains("![residual autocorrelation](residual-acf.svg)"));
    // Measured, nominal and extended series drawn over time.
    let svg = text("motor-1.svg");
    assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
    for series in ["measured", "nominal", "sensor_lag"] {
        assert!(svg.contains(series), "motor-1.svg lacks {series}");
    }
    assert!(svg.matches("<path").count() >= 2 && svg.contains("<circle"));
}

#[test]
fn the_simulator_loads_the_fitted_extension_and_behaves_differently() {
    let g = generate(&spec(Effect::NeighborCoupling, Some(0.6), 3), 41);
    let (a, model) = run(&g);
    assert_eq!(a.cause, Effect::NeighborCoupling);
    // Through the file format, as `nori model analyze --report` writes it.
    let text = model.to_toml();
    let loaded = sim::extension::ModelExtension::parse(&text, "extended-model.toml").unwrap();
    assert_eq!(loaded, model);
    assert_eq!(loaded.neighbor_coupling_ratio, Some(a.parameters[0].value));
    let robot = sim::RobotDescription::nori_a3();
    let desc = robot.bus("left_arm").unwrap();
    let neighbour_after_20_s = |ext: &sim::extension::ModelExtension| {
        let mut bus = sim::SimBus::new(&robot, desc);
        bus.apply_extension(ext);
        bus.servos[0].temperature = 60.0;
        for _ in 0..20_000 {
            bus.step(0.001);
        }
        bus.servos[1].temperature
    };
    let nominal = neighbour_after_20_s(&sim::extension::ModelExtension::none());
    let extended = neighbour_after_20_s(&loaded);
    assert!(
        extended > nominal + 0.5,
        "neighbour of a hot servo: {extended} °C extended vs {nominal} °C nominal"
    );
}

/// Effects the catalog has no entry for are `unexplained`, never a catalog name: the misfit
/// left is beyond the noise floor, and the report shows what can be seen of it.
#[test]
fn an_effect_outside_the_catalog_is_unexplained_with_its_structure() {
    use model_lab::generate::Foreign;
    for (foreign, seed) in [(Foreign::CoolingLoss, 44), (Foreign::HiddenHeater, 42)] {
        let g = generate(
            &Spec {
                foreign: Some(foreign),
                ..spec(Effect::None, None, 3)
            },
            seed,
        );
        let (a, model) = run(&g);
        assert_eq!(
            a.cause,
            Effect::Unexplained,
            "{}: {:#?}",
            foreign.id(),
            a.diagnostics.verdicts
        );
        assert!(a.parameters.is_empty());
        assert_eq!(model.cause, "unexplained");
        let thermal = &a.diagnostics.verdicts[0];
        assert!(thermal.significant && thermal.judged().contains("noise floors"));
        let u = a.unexplained.as_ref().unwrap();
        assert_eq!(u.time_course.len(), 10);
        assert_eq!(u.motors.len(), 3);
        assert_eq!(u.strongest_regressors.len(), 3);
        // The hidden heater warms one motor: it is the worst.
        if foreign == Foreign::HiddenHeater {
            assert!(u.motors[0].1 > 2.0 * u.motors[1].1, "{:?}", u.motors);
        }
        let files = model_lab::report::render(&a, &run_traces(&g), "x");
        let md = &files[0].1;
        assert!(md.contains("What is left unexplained") && md.contains("residual.svg"));
        // A worse cooling from some time on: a change of regime, stated with its form. (A
        // heater on one motor, on and off, is in no term of the library: what it gets, a
        // partial form or none, is not asserted.)
        if foreign == Foreign::CoolingLoss {
            let form = u.form.as_ref().unwrap();
            assert!(form.regime_change_s().is_some(), "{}", form.describe());
            assert!(md.contains("**Its form:** a change of regime at"), "{md}");
        }
        assert!(files.iter().any(|(n, _)| n == "residual.svg"));
    }
}

fn run_traces(g: &Generated) -> model_lab::analysis::Traces {
    let d = g.dataset().unwrap();
    analyze(d, &Options::default(), &mut |_| {}).unwrap().traces
}

/// A fit outside what the effect's physics allows is refused whatever its statistics, and
/// an extension that changes the held-out predictions by less than matters is refused too;
/// both figures are in every candidate.
#[test]
fn implausible_and_negligible_extensions_are_refused() {
    let g = generate(&spec(Effect::None, None, 4), 23);
    let (a, _) = run(&g);
    let sag = a
        .diagnostics
        .candidates
        .iter()
        .find(|c| c.id == Effect::SupplySag)
        .unwrap();
    // Null data: a supply resistance of micro-ohms, below any wiring's.
    assert!(sag.parameter.as_ref().unwrap().value.abs() < 0.005);
    assert!(
        !sag.plausible
            && sag
                .verdict
                .to_string()
                .contains("outside what its physics allows")
    );
    for c in &a.diagnostics.candidates {
        let (lo, hi) = c.bounds.unwrap();
        let v = c.parameter.as_ref().unwrap().value;
        assert_eq!(c.plausible, (lo..=hi).contains(&v), "{c:?}");
        assert!(c.required_change > 0.0 && c.heldout_change.is_finite());
    }
    assert!(a.diagnostics.verdicts.iter().all(|v| !v.significant));
    // The generator's sizes all lie where the lab's bounds allow; copper's own value too.
    for e in Effect::CATALOG {
        let (lo, hi, _) = e.bounds().unwrap();
        let (a, b) = model_lab::generate::size_range(e);
        assert!(lo <= a && b <= hi, "{e}");
    }
    let (lo, hi, _) = Effect::CopperTempco.bounds().unwrap();
    assert!(lo < 0.393 && 0.393 < hi);
}

/// A current logged in milliamperes is found, converted and said, and the hidden effect is
/// still named with its parameter.
#[test]
fn a_current_in_milliamps_is_converted_and_the_effect_still_named() {
    let g = generate(&spec(Effect::CurrentOffset, Some(0.15), 3), 43);
    let mut lines = g.csv.lines();
    let mut csv = format!("{}\n", lines.next().unwrap());
    for l in lines {
        let mut cells: Vec<String> = l.split(',').map(str::to_string).collect();
        let a: f64 = cells[4].parse().unwrap();
        cells[4] = format!("{:.1}", a * 1000.0);
        csv.push_str(&cells.join(","));
        csv.push('\n');
    }
    let dirty = Generated { csv, ..g.clone() };
    let (a, _) = run(&dirty);
    let audit = &a.diagnostics.audit;
    assert_eq!(audit.len(), 1, "{audit:#?}");
    assert_eq!(
        (audit[0].kind, audit[0].action),
        ("milliamps", Action::Fixed)
    );
    assert_eq!(
        a.cause,
        Effect::CurrentOffset,
        "{:#?}",
        a.diagnostics.candidates
    );
    let p = a.parameters[0].value;
    assert!((p - 0.15).abs() < 0.15 * 0.15, "{p}");
}

/// Two effects at once are both named, each with its parameter: two thermal ones (fitted
/// together), or a thermal and an electrical one (each channel's own). Seed 59's copper
/// coefficient beside a current offset is nearly collinear with it on the fitting part (p =
/// 0.08 there alone) and plain in the held-out part (slope t = 11.8): it is named on both
/// together.
#[test]
fn two_effects_at_once_are_both_named() {
    for (first, second, seed) in [
        (Effect::SensorLag, Effect::AmbientDrift, 51),
        (Effect::NeighborCoupling, Effect::SupplySag, 52),
        (Effect::CopperTempco, Effect::CurrentOffset, 59),
    ] {
        let g = generate(
            &Spec {
                second: Some(second),
                ..spec(first, None, 3)
            },
            seed,
        );
        let (a, model) = run(&g);
        let mut named = a.causes.clone();
        named.sort_by_key(|e| e.id());
        let mut hidden = vec![first, second];
        hidden.sort_by_key(|e| e.id());
        assert_eq!(
            named, hidden,
            "{first} + {second}: {:#?}\n{:#?}",
            a.diagnostics.candidates, a.diagnostics.verdicts
        );
        let truth = [
            g.truth.parameter.clone().unwrap(),
            g.truth.second.clone().unwrap().1,
        ];
        let found: Vec<f64> = truth
            .iter()
            .map(|t| {
                a.parameters
                    .iter()
                    .chain(
                        a.diagnostics
                            .candidates
                            .iter()
                            .filter_map(|c| c.parameter.as_ref())
                            .filter(|p| p.name == "supply_resistance"),
                    )
                    .find(|p| p.name == t.name)
                    .map_or(f64::NAN, |p| p.value)
            })
            .collect();
        for (t, f) in truth.iter().zip(&found) {
            assert!(
                (f - t.value).abs() <= 0.25 * t.value.abs(),
                "{}: {f} for {}",
                t.name,
                t.value
            );
        }
        assert!(
            model.cause.contains(first.id()) && model.cause.contains(second.id()),
            "{}",
            model.cause
        );
    }
}

/// One effect hidden is named alone, as the benchmark generates it (2 h at 1 Hz): a fit of
/// it that has not converged is not a second effect (seeds 7 and 16: the lag and the drift
/// stopped at 60 iterations, and the pair fitted from there "found" a drift of 0.08 K/h or an
/// offset of 1 mA beside them, the first merely converging), nor is a second of negligible
/// size that the held-out slope happens to follow (seed 14: a drift of −0.06 K/h).
#[test]
fn one_effect_alone_is_named_alone() {
    for (effect, seed) in [
        (Effect::SensorLag, 7),
        (Effect::AmbientDrift, 16),
        (Effect::SensorLag, 14),
    ] {
        let g = generate(&Spec::new(effect), seed);
        let (a, _) = run(&g);
        assert_eq!(
            a.causes,
            vec![effect],
            "seed {seed}: {:#?}",
            a.diagnostics.candidates
        );
        let truth = g.truth.parameter.unwrap().value;
        let found = a.parameters[0].value;
        assert!(
            (found - truth).abs() <= 0.25 * truth.abs(),
            "seed {seed}: {found} for {truth}"
        );
    }
    // The generator's sizes are findings: above what each effect counts as negligible (over
    // its 2 h, against a noise floor of half a degree).
    for e in Effect::CATALOG {
        if let Some((small, _)) = e.negligible(2.0, 0.5) {
            assert!(model_lab::generate::size_range(e).0 > small, "{e}");
        }
    }
}

/// The generator writes a channel wrong (current in mA, a stuck sensor, a clock that steps
/// back); the audit finds each, and the null data behind it still read `none`.
#[test]
fn dirty_channels_from_the_generator_are_flagged() {
    use model_lab::generate::Dirty;
    for (dirty, seed) in [
        (Dirty::Milliamps, 61),
        (Dirty::StuckSensor, 62),
        (Dirty::ClockJump, 63),
    ] {
        let g = generate(
            &Spec {
                dirty: Some(dirty),
                ..spec(Effect::None, None, 3)
            },
            seed,
        );
        let (a, _) = run(&g);
        let kinds: Vec<&str> = a.diagnostics.audit.iter().map(|f| f.kind).collect();
        assert_eq!(kinds, [dirty.id()], "{:#?}", a.diagnostics.audit);
        assert_eq!(
            a.cause,
            Effect::None,
            "{}: {:#?}",
            dirty.id(),
            a.diagnostics.verdicts
        );
    }
}
