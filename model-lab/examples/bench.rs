#![allow(missing_docs, clippy::unwrap_used, clippy::expect_used)]
fn main() {
    let a: Vec<String> = std::env::args().collect();
    let s = model_lab::bench::Settings {
        seeds: a[1].parse().unwrap(),
        sweep_seeds: a[2].parse().unwrap(),
        jobs: 2,
        ..Default::default()
    };
    let r = model_lab::bench::run(&s, &mut |l| eprintln!("{l}"));
    for e in &r.effects {
        println!(
            "{:?} acc {:.2} conf {:?} sweep {:?}",
            e.effect, e.accuracy, e.confusions, e.sweep
        );
        for d in &e.detail {
            if d.named != e.effect {
                println!(
                    "   miss seed {} size {:.3} named {:?} motors {}",
                    d.seed, d.size, d.named, d.motors
                );
            }
        }
    }
    println!("{:.1}s", r.seconds);
}
