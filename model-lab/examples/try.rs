#![allow(missing_docs, clippy::unwrap_used, clippy::expect_used)]
use model_lab::generate::{generate, Spec};
use model_lab::*;
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let effect = Effect::from_id(&args[1]).unwrap();
    let seed: u64 = args[2].parse().unwrap();
    let mut spec = Spec::new(effect);
    if let Some(s) = args.get(3) {
        spec.size = Some(s.parse().unwrap());
    }
    let g = generate(&spec, seed);
    let t = std::time::Instant::now();
    let out = analyze(g.dataset().unwrap(), &Options::default(), &mut |_| {}).unwrap();
    let a = &out.analysis;
    println!(
        "truth {:?} {:?} motors {} noise {:.2}",
        g.truth.effect,
        g.truth.parameter.as_ref().map(|p| p.value),
        g.truth.motors,
        g.truth.sensor_noise_c
    );
    println!(
        "cause {} params {:?} base {:.3} ext {:.3} gain {:.3} ({:.2}s)",
        a.cause,
        a.parameters,
        a.baseline_rmse,
        a.extended_rmse,
        a.gain,
        t.elapsed().as_secs_f64()
    );
    for c in &a.diagnostics.candidates {
        println!("  {:18} p={:10.3e} lr={:9.1} dBIC={:9.1} neff={:7.0} t={:6.2} gain={:6.3} par={:?} it={} {}", c.id.id(), c.p_value, c.lr, c.delta_bic, c.n_eff, c.heldout_t, c.gain, c.parameter.as_ref().map(|p| p.value), c.iterations, c.verdict);
    }
}
