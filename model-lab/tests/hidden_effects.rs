//! Hidden-effect tests: the generator hides one effect of the catalog (or none) in measured-like
//! data — integer °C register, sensor noise, 0 °C / 150 °C read glitches, empty cells and dropped
//! rows, a quantised current register — and the lab must name it and recover its parameter.
//!
//! Fixed seeds, fixed sizes well inside the generator's range (the benchmark,
//! `nori model bench`, covers random sizes over ≥ 50 seeds and the detection limits). Records
//! are 2 h at 2 s per sample on 3–4 motors to keep the suite short in debug builds.

#![allow(missing_docs, clippy::unwrap_used, clippy::expect_used)]

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
        assert!(a.diagnostics.candidates.iter().all(|c| !c.supported));
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
    assert_eq!(diag["candidates"].as_array().map(Vec::len), Some(6));
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
