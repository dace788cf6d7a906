//! The readable report: Markdown with SVG plots, returned as (file name, contents) pairs for the
//! caller to write. The plots are drawn by hand (a few polylines and ticks) rather than with a
//! plotting crate: it keeps the lab free of font and image dependencies.

use crate::analysis::{
    Analysis, Candidate, Diagnostics, MotorFigures, Trace, Traces, Unexplained, LJUNG_BOX_LAGS,
};
use crate::motion::MotionAnalysis;
use crate::stats;
use std::fmt::Write as _;

/// Colours of per-motor series.
const PALETTE: [&str; 8] = [
    "#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
];

/// One line of a plot.
struct Series<'a> {
    name: &'a str,
    color: &'a str,
    points: Vec<(f64, f64)>,
    /// Draw as dots (readings) instead of a line.
    dots: bool,
}

/// Round tick positions covering [lo, hi].
fn ticks(lo: f64, hi: f64) -> Vec<f64> {
    let span = (hi - lo).max(1e-9);
    let raw = span / 6.0;
    let mag = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * mag)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * mag);
    let mut t = (lo / step).ceil() * step;
    let mut out = Vec::new();
    while t <= hi + 1e-9 * span {
        out.push(t);
        t += step;
    }
    out
}

fn fmt_tick(v: f64) -> String {
    if v.abs() >= 100.0 || v == v.round() {
        format!("{v:.0}")
    } else {
        format!("{v:.2}")
    }
}

/// Where a plot's points land: the canvas (width, height, margins left, right, top, bottom)
/// and the data's ranges on it.
struct Frame {
    w: f64,
    h: f64,
    l: f64,
    r: f64,
    t: f64,
    b: f64,
    x0: f64,
    x1: f64,
    y0: f64,
    y1: f64,
}

impl Frame {
    /// The canvas around `series`' finite points (the y range padded by 5 %; the unit square
    /// when there are none).
    fn around(series: &[Series]) -> Frame {
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for &(x, y) in series
            .iter()
            .flat_map(|s| s.points.iter())
            .filter(|p| p.1.is_finite())
        {
            x0 = x0.min(x);
            x1 = x1.max(x);
            y0 = y0.min(y);
            y1 = y1.max(y);
        }
        if x0 > x1 {
            (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
        }
        let pad = 0.05 * (y1 - y0).max(1e-6);
        Frame {
            w: 900.0,
            h: 360.0,
            l: 70.0,
            r: 20.0,
            t: 30.0,
            b: 50.0,
            x0,
            x1,
            y0: y0 - pad,
            y1: y1 + pad,
        }
    }

    /// The canvas x of data x.
    fn sx(&self, x: f64) -> f64 {
        self.l + (x - self.x0) / (self.x1 - self.x0).max(1e-12) * (self.w - self.l - self.r)
    }

    /// The canvas y of data y.
    fn sy(&self, y: f64) -> f64 {
        self.h
            - self.b
            - (y - self.y0) / (self.y1 - self.y0).max(1e-12) * (self.h - self.t - self.b)
    }

    /// The SVG's start: its size, a white background and the title.
    fn open(&self, s: &mut String, title: &str) {
        let (w, h) = (self.w, self.h);
        let _ = writeln!(
            s,
            r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-family="sans-serif" font-size="12">"#
        );
        let _ = writeln!(s, r#"<rect width="{w}" height="{h}" fill="white"/>"#);
        let _ = writeln!(
            s,
            r#"<text x="{}" y="18" text-anchor="middle" font-size="14">{}</text>"#,
            w / 2.0,
            esc(title)
        );
    }

    /// The grid lines with their tick labels, the plot's box and the axis labels.
    fn axes(&self, s: &mut String, xlabel: &str, ylabel: &str) {
        let Frame {
            w, h, l, r, t, b, ..
        } = *self;
        for tx in ticks(self.x0, self.x1) {
            let x = self.sx(tx);
            let _ = writeln!(
                s,
                r##"<line x1="{x:.1}" y1="{t}" x2="{x:.1}" y2="{}" stroke="#eee"/><text x="{x:.1}" y="{}" text-anchor="middle">{}</text>"##,
                h - b,
                h - b + 16.0,
                fmt_tick(tx)
            );
        }
        for ty in ticks(self.y0, self.y1) {
            let y = self.sy(ty);
            let _ = writeln!(
                s,
                r##"<line x1="{l}" y1="{y:.1}" x2="{}" y2="{y:.1}" stroke="#eee"/><text x="{}" y="{:.1}" text-anchor="end">{}</text>"##,
                w - r,
                l - 6.0,
                y + 4.0,
                fmt_tick(ty)
            );
        }
        let _ = writeln!(
            s,
            r#"<rect x="{l}" y="{t}" width="{}" height="{}" fill="none" stroke="black"/>"#,
            w - l - r,
            h - t - b
        );
        let _ = writeln!(
            s,
            r#"<text x="{}" y="{}" text-anchor="middle">{}</text>"#,
            (l + w - r) / 2.0,
            h - 12.0,
            esc(xlabel)
        );
        let _ = writeln!(
            s,
            r#"<text x="16" y="{}" text-anchor="middle" transform="rotate(-90 16 {})">{}</text>"#,
            h / 2.0,
            h / 2.0,
            esc(ylabel)
        );
    }

    /// A dashed line at data x `v`, where the held-out part starts.
    fn held_out_from(&self, s: &mut String, v: f64) {
        let x = self.sx(v);
        let _ = writeln!(
            s,
            r##"<line x1="{x:.1}" y1="{}" x2="{x:.1}" y2="{}" stroke="#888" stroke-dasharray="4 4"/><text x="{:.1}" y="{}" fill="#666">held out →</text>"##,
            self.t,
            self.h - self.b,
            x + 4.0,
            self.t + 14.0
        );
    }

    /// A series as dots (readings).
    fn dots(&self, s: &mut String, se: &Series) {
        for &(x, y) in se.points.iter().filter(|p| p.1.is_finite()) {
            let _ = write!(
                s,
                r#"<circle cx="{:.1}" cy="{:.1}" r="1.2" fill="{}"/>"#,
                self.sx(x),
                self.sy(y),
                se.color
            );
        }
        let _ = writeln!(s);
    }

    /// A series as a line, broken at missing values and logging gaps.
    fn line(&self, s: &mut String, se: &Series) {
        let mut dx: Vec<f64> = se.points.windows(2).map(|w| w[1].0 - w[0].0).collect();
        dx.sort_by(f64::total_cmp);
        let gap = 20.0 * dx.get(dx.len() / 2).copied().unwrap_or(f64::INFINITY);
        let mut d = String::new();
        let mut pen_up = true;
        let mut last_x = f64::NEG_INFINITY;
        for &(x, y) in &se.points {
            if !y.is_finite() || x - last_x > gap {
                pen_up = true;
            }
            last_x = x;
            if !y.is_finite() {
                continue;
            }
            let _ = write!(
                d,
                "{}{:.1},{:.1} ",
                if pen_up { "M" } else { "L" },
                self.sx(x),
                self.sy(y)
            );
            pen_up = false;
        }
        let _ = writeln!(
            s,
            r#"<path d="{d}" fill="none" stroke="{}" stroke-width="1.5"/>"#,
            se.color
        );
    }

    /// The legend's entry of the `i`-th series.
    fn legend(&self, s: &mut String, i: usize, se: &Series) {
        let ly = self.t + 14.0 + 16.0 * i as f64;
        let _ = writeln!(
            s,
            r#"<rect x="{}" y="{}" width="12" height="4" fill="{}"/><text x="{}" y="{}">{}</text>"#,
            self.l + 10.0,
            ly - 4.0,
            se.color,
            self.l + 28.0,
            ly,
            esc(se.name)
        );
    }
}

/// An SVG plot of `series` (dots or lines, with a legend), a dashed line at `vline` where the
/// held-out part starts.
fn plot(title: &str, xlabel: &str, ylabel: &str, series: &[Series], vline: Option<f64>) -> String {
    let frame = Frame::around(series);
    let mut s = String::new();
    frame.open(&mut s, title);
    frame.axes(&mut s, xlabel, ylabel);
    if let Some(v) = vline {
        frame.held_out_from(&mut s, v);
    }
    for (i, se) in series.iter().enumerate() {
        if se.dots {
            frame.dots(&mut s, se);
        } else {
            frame.line(&mut s, se);
        }
        frame.legend(&mut s, i, se);
    }
    s.push_str("</svg>\n");
    s
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// Keeps at most `max` evenly spaced points.
fn thin(points: Vec<(f64, f64)>, max: usize) -> Vec<(f64, f64)> {
    let stride = points.len().div_ceil(max.max(1)).max(1);
    points.into_iter().step_by(stride).collect()
}

fn f(v: Option<f64>, digits: usize) -> String {
    match v {
        Some(v) if v.is_finite() => format!("{v:.digits$}"),
        _ => "–".into(),
    }
}

/// The report's files: `report.md`, one SVG per motor and `residual-acf.svg`.
pub fn render(a: &Analysis, tr: &Traces, source: &str) -> Vec<(String, String)> {
    let mut r = Draft::default();
    r.summary(a, source);
    if let Some(u) = &a.unexplained {
        r.unexplained(u, a.unit, tr);
    }
    r.data(&a.diagnostics);
    r.nominal_misfits(&a.diagnostics);
    r.extensions_tried(&a.diagnostics.candidates);
    if let Some(m) = &a.motion {
        r.motion(m);
    }
    r.per_motor(&a.motors);
    r.plots(a, tr);
    let mut files = r.files;
    files.insert(0, ("report.md".into(), r.md));
    files
}

/// A report being written: its Markdown and the plots it links, in the order linked.
#[derive(Default)]
struct Draft {
    md: String,
    files: Vec<(String, String)>,
}

impl Draft {
    /// The title, the cause with its figures and parameters, and how each channel was judged.
    fn summary(&mut self, a: &Analysis, source: &str) {
        let md = &mut self.md;
        let _ = writeln!(md, "# Model lab report: {}\n", esc(source));
        if a.causes.len() > 1 {
            let all: Vec<String> = a.causes.iter().map(|c| format!("`{c}`")).collect();
            let _ = writeln!(md, "**Effects named together: {}.**\n", all.join(" + "));
        }
        let _ = writeln!(
            md,
            "**Cause: `{}`** ({}).\n\nHeld-out error on the {:?} channel: nominal {:.4} {u}, \
             extended {:.4} {u}, gain {:.1} %.\n",
            a.cause,
            a.description,
            a.channel,
            a.baseline_rmse,
            a.extended_rmse,
            100.0 * a.gain,
            u = a.unit
        );
        for p in &a.parameters {
            let _ = writeln!(md, "- `{}` = {:.4} {}", p.name, p.value, p.unit);
        }
        let _ = writeln!(
            md,
            "\nHow it was judged (the misfit left on each channel against its noise floor):\n"
        );
        for v in &a.diagnostics.verdicts {
            let _ = writeln!(
                md,
                "- {:?}, after `{}`: {} — **{}**",
                v.channel,
                v.extension.map_or("none", |e| e.id()),
                v.judged(),
                if v.significant {
                    "beyond the noise"
                } else {
                    "within the noise"
                }
            );
        }
    }

    /// What is left unexplained (in `unit`): the extensions that reduce it, what it follows,
    /// per motor and over time, and a plot of the nominal model's held-out residual.
    fn unexplained(&mut self, u: &Unexplained, unit: &str, tr: &Traces) {
        let md = &mut self.md;
        let _ = writeln!(
            md,
            "\n## What is left unexplained ({:?} channel)\n",
            u.channel
        );
        if u.partial.is_empty() {
            let _ = writeln!(md, "No catalog extension reduces it.\n");
        } else {
            for (e, gain) in &u.partial {
                let _ = writeln!(
                    md,
                    "- `{e}` reduces it ({:+.1} % held-out) but leaves it beyond the noise",
                    100.0 * gain
                );
            }
        }
        if let Some(f) = &u.form {
            let _ = writeln!(
                md,
                "\n**Its form:** {}. Terms of the missing dynamics (τ·dT/dt = nominal + …), \
                 chosen from {} by their held-out error over {} blocks of time; held-out RMSE \
                 {:.3} → {:.3} {}.\n",
                f.describe(),
                f.library,
                crate::form::FOLDS,
                f.baseline_rmse,
                f.rmse,
                f.unit
            );
        }
        let _ = writeln!(md, "\nThe nominal residual follows most:\n");
        for (k, r) in &u.strongest_regressors {
            let _ = writeln!(md, "- {k}: r = {r:+.3}");
        }
        let _ = writeln!(md, "\n| motor | held-out RMSE | bias |\n|---|---|---|");
        for (m, r, b) in &u.motors {
            let _ = writeln!(md, "| {m} | {r:.3} {unit} | {b:+.3} {unit} |");
        }
        let _ = writeln!(md, "\n| held-out span (s) | RMSE | bias |\n|---|---|---|");
        for (t0, t1, r, b) in &u.time_course {
            let _ = writeln!(md, "| {t0:.0}–{t1:.0} | {r:.3} {unit} | {b:+.3} {unit} |");
        }
        let names: Vec<String> = tr
            .series
            .iter()
            .map(|s| format!("motor {}", s.motor))
            .collect();
        let series: Vec<Series> = tr
            .series
            .iter()
            .enumerate()
            .map(|(i, s)| Series {
                name: &names[i],
                color: motor_color(i),
                points: thin(
                    (tr.split..tr.t.len())
                        .map(|k| (tr.t[k], s.nominal[k] - s.measured[k]))
                        .collect(),
                    2000,
                ),
                dots: true,
            })
            .collect();
        let svg = plot(
            "held-out residual of the nominal model (prediction − reading), per motor",
            "t (s)",
            tr.unit,
            &series,
            None,
        );
        let _ = writeln!(md, "\n![held-out residual](residual.svg)\n");
        self.files.push(("residual.svg".into(), svg));
    }

    /// The data's shape, what was cleaned, the temperature register, and the notes.
    fn data(&mut self, d: &Diagnostics) {
        let md = &mut self.md;
        let _ = writeln!(
            md,
            "\n{} samples of {} motors, {:.0} s in {} segment(s); held out from t = {:.0} s. \
             Glitches rejected: {}, missing readings: {}. Temperature register step {:.4} °C{}.\n",
            d.samples,
            d.motors,
            d.duration_s,
            d.segments,
            d.split_t_s,
            d.cleaning.temperature_glitches,
            d.cleaning.temperature_missing,
            d.temperature_quantum_c,
            d.register_noise_c.map_or(String::new(), |s| format!(
                ", noise before rounding σ = {s:.3} °C (estimated with the nominal model)"
            ))
        );
        for n in &d.notes {
            let _ = writeln!(md, "- note: {n}");
        }
    }

    /// The nominal model's held-out misfit on the thermal and electrical channels.
    fn nominal_misfits(&mut self, d: &Diagnostics) {
        let md = &mut self.md;
        for (name, m) in [("thermal", &d.thermal), ("electrical", &d.electrical)] {
            if let Some(m) = m {
                let _ = writeln!(
                    md,
                    "\n## Nominal misfit, {name} channel\n\nHeld-out RMSE {:.4} {u}, bias {:+.4} {u}, \
                     lag-1 autocorrelation {:.3}, Ljung–Box Q({LJUNG_BOX_LAGS}/motor) = {:.0} \
                     (p = {:.2e}).\n\n| regressor | correlation with residual |\n|---|---|",
                    m.rmse,
                    m.bias,
                    m.lag1_autocorrelation,
                    m.ljung_box_q,
                    m.ljung_box_p,
                    u = m.unit
                );
                for (k, v) in &m.correlations {
                    let _ = writeln!(md, "| {k} | {v:+.3} |");
                }
            }
        }
    }

    /// Every extension tried on the thermal and electrical channels, with its tests.
    fn extensions_tried(&mut self, candidates: &[Candidate]) {
        let md = &mut self.md;
        let _ = writeln!(
            md,
            "\n## Extensions tried\n\n| id | parameter | physics allows | LR | p | ΔBIC | held-out RMSE | gain | held-out slope (t) | correction (matters from) | verdict |\n|---|---|---|---|---|---|---|---|---|---|---|"
        );
        for c in candidates {
            let par = c
                .parameter
                .as_ref()
                .map_or("–".into(), |p| format!("{:.4} {}", p.value, p.unit));
            let range = c
                .bounds
                .map_or("–".into(), |(lo, hi)| format!("{lo} to {hi}"));
            let _ = writeln!(
                md,
                "| {} | {par} | {range} | {:.1} | {:.1e} | {:.1} | {:.4} | {:+.1} % | {:.2} ({:.2}) | {:.4} ({:.4}) | {} |",
                match c.with {
                    Some(w) => format!("`{}` beside `{w}`", c.id),
                    None => format!("`{}`", c.id),
                },
                c.lr,
                c.p_value,
                c.delta_bic,
                c.heldout_rmse,
                100.0 * c.gain,
                c.heldout_slope,
                c.heldout_slope_t,
                c.heldout_change,
                c.required_change,
                c.verdict
            );
        }
    }

    /// The motion channel: the servo as configured, the models held out run by run, and a
    /// plot per run.
    fn motion(&mut self, m: &MotionAnalysis) {
        let md = &mut self.md;
        let _ = writeln!(
            md,
            "\n## Motion channel ({} runs through the simulator's {})\n\n**Cause: `{}`**; {}.\n\n\
             The simulator's servo as configured (its rated friction), open loop:\n\n\
             | run | MAE (rad) | RMSE (rad) |\n|---|---|---|",
            m.as_configured.len(),
            m.servo,
            m.cause,
            m.judged()
        );
        for (run, mae, rmse) in &m.as_configured {
            let _ = writeln!(md, "| {} | {mae:.4} | {rmse:.4} |", esc(run));
        }
        if !m.always_fitted.is_empty() {
            let _ = writeln!(
                md,
                "\nNever held out: {} (the only run(s) where the load moves free of the \
                 position loop, without which no friction can be fitted).",
                m.always_fitted.join(", ")
            );
        }
        let _ = writeln!(
            md,
            "\nCalibrated and extended, each run predicted by a model fitted without it:\n\n\
             | model | held-out MAE per run (rad) | mean | gain | runs improved | parameters (fitted on all runs) | verdict |\n|---|---|---|---|---|---|---|"
        );
        for c in &m.candidates {
            let runs: Vec<String> = c.runs.iter().map(|h| format!("{:.4}", h.mae_rad)).collect();
            let pars: Vec<String> = c
                .parameters
                .iter()
                .map(|p| format!("{} = {:.4} {}", p.name, p.value, p.unit))
                .collect();
            let _ = writeln!(
                md,
                "| `{}` | {} | {:.4} | {:+.1} % | {}/{} | {} | {} |",
                c.id,
                runs.join(", "),
                c.mae_rad,
                100.0 * c.gain,
                c.improved_runs,
                c.runs.len(),
                pars.join("; "),
                c.verdict
            );
        }
        for (k, tr) in m.traces.iter().enumerate() {
            let name = format!("motion-{k}.svg");
            let svg = plot(
                &format!("{}: measured vs nominal vs {}", tr.run, m.cause),
                "t (s)",
                "rad",
                &[
                    Series {
                        name: "measured",
                        color: "#999",
                        points: thin(xy(&tr.t, &tr.measured), 3000),
                        dots: true,
                    },
                    Series {
                        name: "nominal (calibrated)",
                        color: "#1f77b4",
                        points: thin(xy(&tr.t, &tr.nominal), 3000),
                        dots: false,
                    },
                    Series {
                        name: "chosen",
                        color: "#d62728",
                        points: thin(xy(&tr.t, &tr.chosen), 3000),
                        dots: false,
                    },
                ],
                None,
            );
            let _ = writeln!(self.md, "\n![{}]({name})", esc(&tr.run));
            self.files.push((name, svg));
        }
    }

    /// Per motor: the nominal thermal model's constants and the held-out errors.
    fn per_motor(&mut self, motors: &[MotorFigures]) {
        let md = &mut self.md;
        let _ = writeln!(
            md,
            "\n## Per motor\n\n| motor | τ (s) | k (K/A²) | idle (°C) | readings fit/held | nominal RMSE (°C) | extended RMSE (°C) | bias (°C) | nominal RMSE (V) | extended RMSE (V) |\n|---|---|---|---|---|---|---|---|---|---|"
        );
        for m in motors {
            let _ = writeln!(
                md,
                "| {} | {} | {} | {} | {}/{} | {} | {} | {} | {} | {} |",
                m.motor,
                f(m.tau_s, 0),
                f(m.gain_k_per_a2, 3),
                f(m.idle_c, 2),
                m.readings.0,
                m.readings.1,
                f(m.baseline_rmse_c, 3),
                f(m.extended_rmse_c, 3),
                f(m.baseline_bias_c, 3),
                f(m.baseline_rmse_v, 4),
                f(m.extended_rmse_v, 4)
            );
        }
    }

    /// Per motor its measured and predicted series, then the held-out residual's
    /// autocorrelation (mean over motors) of the nominal and the chosen model.
    fn plots(&mut self, a: &Analysis, tr: &Traces) {
        let _ = writeln!(self.md, "\n## Plots\n");
        let split_t = tr.t.get(tr.split).copied();
        let mut acf_series = Vec::new();
        for s in &tr.series {
            let name = format!("motor-{}.svg", s.motor);
            let svg = plot(
                &format!("motor {}: measured vs nominal vs {}", s.motor, a.cause),
                "t (s)",
                tr.unit,
                &[
                    Series {
                        name: "measured",
                        color: "#999",
                        points: thin(xy(&tr.t, &s.measured), 3000),
                        dots: true,
                    },
                    Series {
                        name: "nominal",
                        color: "#1f77b4",
                        points: thin(xy(&tr.t, &s.nominal), 2000),
                        dots: false,
                    },
                    Series {
                        name: a.cause.id(),
                        color: "#d62728",
                        points: thin(xy(&tr.t, &s.extended), 2000),
                        dots: false,
                    },
                ],
                split_t,
            );
            let _ = writeln!(self.md, "![motor {}]({name})\n", s.motor);
            self.files.push((name, svg));
            acf_series.push(held_out_acf(tr, s));
        }
        if let Some(svg) = mean_acf_plot(&acf_series, a.cause.id()) {
            let _ = writeln!(self.md, "![residual autocorrelation](residual-acf.svg)\n");
            self.files.push(("residual-acf.svg".into(), svg));
        }
    }
}

/// One motor's held-out residual autocorrelation, (lag in samples, value): the nominal
/// model's and the chosen model's.
struct HeldOutAcf {
    nominal: Vec<(f64, f64)>,
    chosen: Vec<(f64, f64)>,
}

/// Motor `s`'s held-out residual autocorrelations.
fn held_out_acf(tr: &Traces, s: &Trace) -> HeldOutAcf {
    let res: Vec<f64> = (tr.split..tr.t.len())
        .map(|k| s.nominal[k] - s.measured[k])
        .collect();
    let lags = 200.min(res.len().saturating_sub(2));
    let acf = stats::autocorrelation(&res, lags);
    let ext: Vec<f64> = (tr.split..tr.t.len())
        .map(|k| s.extended[k] - s.measured[k])
        .collect();
    let acf_e = stats::autocorrelation(&ext, lags);
    HeldOutAcf {
        nominal: by_lag(acf),
        chosen: by_lag(acf_e),
    }
}

/// The plot of the motors' held-out residual autocorrelation, mean over motors, nominal vs
/// the chosen model (`chosen` its id); none without motors.
fn mean_acf_plot(acf_series: &[HeldOutAcf], chosen: &str) -> Option<String> {
    let first = acf_series.first()?;
    let len = first.nominal.len().min(first.chosen.len());
    let mean = |extended: bool| -> Vec<(f64, f64)> {
        (0..len)
            .map(|k| {
                let v: Vec<f64> = acf_series
                    .iter()
                    .filter_map(|s| {
                        if extended { &s.chosen } else { &s.nominal }
                            .get(k)
                            .map(|p| p.1)
                    })
                    .collect();
                (k as f64, stats::mean(&v))
            })
            .collect()
    };
    Some(plot(
        "held-out residual autocorrelation (mean over motors)",
        "lag (samples)",
        "autocorrelation",
        &[
            Series {
                name: "nominal",
                color: "#1f77b4",
                points: mean(false),
                dots: false,
            },
            Series {
                name: chosen,
                color: "#d62728",
                points: mean(true),
                dots: false,
            },
        ],
        None,
    ))
}

/// The colour of the `i`-th motor's series.
fn motor_color(i: usize) -> &'static str {
    PALETTE[i % PALETTE.len()]
}

/// The points (t, v) of a series `v` sampled at times `t`.
fn xy(t: &[f64], v: &[f64]) -> Vec<(f64, f64)> {
    t.iter().copied().zip(v.iter().copied()).collect()
}

/// Autocorrelations as points (lag, value).
fn by_lag(acf: Vec<f64>) -> Vec<(f64, f64)> {
    acf.into_iter()
        .enumerate()
        .map(|(k, v)| (k as f64, v))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_round_and_cover_the_range() {
        assert_eq!(ticks(0.0, 10.0), [0.0, 2.0, 4.0, 6.0, 8.0, 10.0]);
        let t = ticks(21.3, 24.9);
        assert!(t.first().is_some_and(|v| *v >= 21.3) && t.len() >= 3);
        assert!(plot("a<b", "x", "y", &[], Some(1.0)).contains("a&lt;b"));
    }
}
