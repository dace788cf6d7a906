//! The truth-model generator: measured-like data carrying one hidden effect of random size.
//!
//! The truth is integrated independently of the lab's fitting code (RK4 on the full ODE, four
//! sub-steps per sample) so a test cannot pass merely because generator and fitter share a
//! discretisation. What the data get: a random number of motors on one chain, a random duty
//! profile per motor (rests, back-and-forth moves, holds), sensor noise, the integer °C register,
//! occasional 0 °C / 150 °C read glitches, empty cells and dropped rows, a 0.1 V voltage register
//! and the 6.5 mA current register.

use crate::analysis::Parameter;
use crate::catalog::Effect;
use crate::data::{parse_csv, DataError, Dataset, Meta};
use sim::rng::Rng;
use std::fmt::Write as _;

/// The range a hidden effect's size is drawn from (magnitude; some effects get a random sign),
/// in the catalog's unit.
pub fn size_range(effect: Effect) -> (f64, f64) {
    match effect {
        Effect::SensorLag => (30.0, 240.0),
        Effect::NeighborCoupling => (0.15, 1.0),
        // Copper's 0.393 %/K is inside.
        Effect::CopperTempco => (0.25, 0.8),
        Effect::AmbientDrift => (1.0, 4.0),
        Effect::SupplySag => (0.03, 0.3),
        Effect::CurrentOffset => (0.05, 0.25),
        // Nothing hidden, or the motion channel's (`motion_size_range`).
        _ => (0.0, 0.0),
    }
}

fn signed(effect: Effect) -> bool {
    matches!(effect, Effect::AmbientDrift | Effect::CurrentOffset)
}

/// Effects the catalog has no entry for: hidden in data, the lab must answer `unexplained`
/// (never a catalog name).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Foreign {
    /// The cooling changes part-way (a fan stops, the servo is re-mounted): from a random time
    /// in the record's second half every motor's copper-loss gain is 40–80 % higher.
    CoolingLoss,
    /// An unlogged heat source (a board's regulator) warms one motor by 6–12 K at equilibrium,
    /// on and off with a random period of 20–60 min.
    HiddenHeater,
}

impl Foreign {
    /// Every foreign effect.
    pub const ALL: [Foreign; 2] = [Foreign::CoolingLoss, Foreign::HiddenHeater];

    /// Its name.
    pub fn id(self) -> &'static str {
        match self {
            Foreign::CoolingLoss => "cooling_loss",
            Foreign::HiddenHeater => "hidden_heater",
        }
    }

    /// The foreign effect of a name.
    pub fn from_id(id: &str) -> Option<Foreign> {
        Foreign::ALL.into_iter().find(|f| f.id() == id)
    }
}

/// Data that lie: a channel written wrong, for the audit to find.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dirty {
    /// The current column in milliamperes (the register's 6.5 mA steps × 1000).
    Milliamps,
    /// One motor's temperature register stuck at its reading for 30–60 min, from a random
    /// time in the first two thirds of the record.
    StuckSensor,
    /// The logger's clock steps back 2–15 min at a random row in the middle of the record.
    ClockJump,
}

impl Dirty {
    /// Every kind.
    pub const ALL: [Dirty; 3] = [Dirty::Milliamps, Dirty::StuckSensor, Dirty::ClockJump];

    /// Its name, and the audit's finding for it.
    pub fn id(self) -> &'static str {
        match self {
            Dirty::Milliamps => "milliamps",
            Dirty::StuckSensor => "stuck",
            Dirty::ClockJump => "clock_jump",
        }
    }
}

/// What to generate.
#[derive(Debug, Clone)]
pub struct Spec {
    /// The hidden effect.
    pub effect: Effect,
    /// An effect outside the catalog, hidden as well.
    pub foreign: Option<Foreign>,
    /// A second catalog effect hidden beside the first (its size drawn from its range).
    pub second: Option<Effect>,
    /// A channel written wrong.
    pub dirty: Option<Dirty>,
    /// Its size (catalog unit); drawn from [`size_range`] when None.
    pub size: Option<f64>,
    /// Recording length, s.
    pub duration_s: f64,
    /// Sample period, s.
    pub period_s: f64,
    /// Motor count; drawn from 2..=8 when None.
    pub motors: Option<usize>,
}

impl Spec {
    /// Two hours at 1 Hz, random motor count and size.
    pub fn new(effect: Effect) -> Self {
        Spec {
            effect,
            foreign: None,
            second: None,
            dirty: None,
            size: None,
            duration_s: 7200.0,
            period_s: 1.0,
            motors: None,
        }
    }
}

/// The hidden truth, to score the lab against.
#[derive(Debug, Clone)]
pub struct Truth {
    /// The hidden effect.
    pub effect: Effect,
    /// The hidden effect outside the catalog, if any.
    pub foreign: Option<Foreign>,
    /// The second hidden catalog effect's parameter, if any.
    pub second: Option<(Effect, Parameter)>,
    /// Its parameter, named like the lab names it.
    pub parameter: Option<Parameter>,
    /// Motors in the generated data.
    pub motors: usize,
    /// Per motor τ, s.
    pub tau_s: Vec<f64>,
    /// Per motor k, K/A².
    pub gain_k_per_a2: Vec<f64>,
    /// Sensor noise (before rounding), °C.
    pub sensor_noise_c: f64,
}

/// Generated data.
#[derive(Debug, Clone)]
pub struct Generated {
    /// The CSV text.
    pub csv: String,
    /// The sidecar JSON text.
    pub meta: String,
    /// The truth.
    pub truth: Truth,
}

impl Generated {
    /// The data as the reader sees them.
    pub fn dataset(&self) -> Result<Dataset, DataError> {
        let rows = parse_csv(&self.csv, "generated")?;
        let meta: Meta = serde_json::from_str(&self.meta).map_err(|source| DataError::Meta {
            path: "generated.meta.json".into(),
            source,
        })?;
        Dataset::from_runs(vec![("generated".into(), rows)], meta, "generated")
    }
}

/// The current register's step, A.
const CURRENT_LSB_A: f64 = 0.0065;

/// Generates one data set.
pub fn generate(spec: &Spec, seed: u64) -> Generated {
    let mut rng = Rng::new(seed ^ 0x6D6F_6465_6C6C_6162);
    let effect = spec.effect;
    let n = spec.motors.unwrap_or_else(|| rng.int(2, 8));
    let (lo, hi) = size_range(effect);
    let mut size = spec.size.unwrap_or_else(|| rng.range(lo, hi));
    if signed(effect) && spec.size.is_none() {
        size *= rng.sign();
    }
    let tau: Vec<f64> = (0..n).map(|_| rng.range(300.0, 900.0)).collect();
    let gain: Vec<f64> = (0..n).map(|_| rng.range(6.0, 14.0)).collect();
    let ambient = rng.range(20.0, 30.0);
    let idle: Vec<f64> = (0..n).map(|_| ambient + rng.range(0.5, 2.0)).collect();
    let noise = rng.range(0.05, 0.3);
    let v0 = rng.range(11.5, 12.5);
    let v_off: Vec<f64> = (0..n).map(|_| rng.range(-0.1, 0.1)).collect();
    let steps = (spec.duration_s / spec.period_s).round() as usize;
    let current = duty_profile(&mut rng, n, steps, spec.period_s);
    let warm: Vec<f64> = (0..n).map(|_| rng.range(0.0, 3.0)).collect();
    // The foreign effect and the second one draw from a generator of their own: the same seed
    // without them gives the same data as before they existed.
    let mut frng = Rng::new(seed ^ 0x666F_7265_6967_6E00);
    let second = spec.second.filter(|e| *e != effect).map(|e| {
        let (lo, hi) = size_range(e);
        let mut v = frng.range(lo, hi);
        if signed(e) {
            v *= frng.sign();
        }
        (e, v)
    });
    let size_of = |e: Effect| match second {
        _ if effect == e => size,
        Some((s, v)) if s == e => v,
        _ => 0.0,
    };
    let duration = steps as f64 * spec.period_s;
    let plant = Plant {
        tau: &tau,
        gain: &gain,
        idle: &idle,
        current: &current,
        lag: size_of(Effect::SensorLag),
        kappa: size_of(Effect::NeighborCoupling),
        alpha: size_of(Effect::CopperTempco) / 100.0,
        drift_h: size_of(Effect::AmbientDrift),
        foreign: ForeignHeat::draw(spec.foreign, &mut frng, duration, n),
    };
    let winding: Vec<f64> = (0..n).map(|m| idle[m] + warm[m]).collect();
    let readings = plant.readings(winding, steps, spec.period_s);
    let registers = Registers {
        period_s: spec.period_s,
        steps,
        current: &current,
        readings: &readings,
        noise,
        offset: size_of(Effect::CurrentOffset),
        sag_ohm: size_of(Effect::SupplySag),
        v0,
        v_off: &v_off,
        faults: Faults::draw(spec.dirty, &mut frng, duration, n),
        milliamps: spec.dirty == Some(Dirty::Milliamps),
    };
    let csv = registers.csv(&mut rng);
    let chain: Vec<String> = (1..=n).map(|m| m.to_string()).collect();
    let meta = format!("{{\"chains\": [[{}]]}}", chain.join(","));
    Generated {
        csv,
        meta,
        truth: Truth {
            effect,
            foreign: spec.foreign,
            second: second.and_then(|(e, v)| {
                e.parameter().map(|(name, unit)| {
                    (
                        e,
                        Parameter {
                            name: name.into(),
                            value: v,
                            unit: unit.into(),
                        },
                    )
                })
            }),
            parameter: effect.parameter().map(|(name, unit)| Parameter {
                name: name.into(),
                value: size,
                unit: unit.into(),
            }),
            motors: n,
            tau_s: tau,
            gain_k_per_a2: gain,
            sensor_noise_c: noise,
        },
    }
}

/// Per motor, the current of a duty profile: phases of rest, back-and-forth moves and holds,
/// `steps` samples `period_s` apart.
fn duty_profile(rng: &mut Rng, n: usize, steps: usize, period_s: f64) -> Vec<Vec<f64>> {
    let mut current = vec![vec![0.0; steps]; n];
    for cur in current.iter_mut() {
        let mut k = 0;
        while k < steps {
            let len = (rng.range(60.0, 480.0) / period_s).max(1.0) as usize;
            let rest = rng.chance(0.3);
            let amp = rng.range(0.3, 1.5);
            let moving = rng.chance(0.6);
            let mut sign = rng.sign();
            let mut next_flip = k + (rng.range(2.0, 8.0) / period_s).max(1.0) as usize;
            for (j, c) in cur.iter_mut().enumerate().skip(k).take(len) {
                if moving && j >= next_flip {
                    sign = -sign;
                    next_flip = j + (rng.range(2.0, 8.0) / period_s).max(1.0) as usize;
                }
                *c = if rest {
                    0.0
                } else {
                    sign * amp * (1.0 + 0.1 * rng.normal())
                };
            }
            k += len;
        }
    }
    current
}

/// The heat of an effect outside the catalog: cooling lost from a time on, or a hidden heater
/// switched on and off under one motor.
struct ForeignHeat {
    /// From this time, s, the cooling is worse ...
    loss_from_s: f64,
    /// ... by this fraction (the heating through the winding's losses grows by it).
    loss: f64,
    /// The heated motor (none: `usize::MAX`) ...
    heated: usize,
    /// ... its heater's heat, K ...
    heater_k: f64,
    /// ... on for the first half of every period of this length, s.
    heater_period_s: f64,
}

impl ForeignHeat {
    /// `foreign`'s heat in a record of `duration` s of `n` motors, drawn from `frng`.
    fn draw(foreign: Option<Foreign>, frng: &mut Rng, duration: f64, n: usize) -> ForeignHeat {
        let (loss_from_s, loss) = match foreign {
            Some(Foreign::CoolingLoss) => (frng.range(0.5, 0.9) * duration, frng.range(0.4, 0.8)),
            _ => (f64::INFINITY, 0.0),
        };
        let (heated, heater_k, heater_period_s) = match foreign {
            Some(Foreign::HiddenHeater) => (
                frng.int(0, n - 1),
                frng.range(6.0, 12.0),
                frng.range(1200.0, 3600.0),
            ),
            _ => (usize::MAX, 0.0, 1.0),
        };
        ForeignHeat {
            loss_from_s,
            loss,
            heated,
            heater_k,
            heater_period_s,
        }
    }
}

/// The truth: per motor a winding and its sensor, heated by the current, with the hidden
/// effects' sizes (0: absent).
struct Plant<'a> {
    /// Time constants, s.
    tau: &'a [f64],
    /// Heating per A², K.
    gain: &'a [f64],
    /// Idle temperatures, °C.
    idle: &'a [f64],
    /// Currents per motor per sample, A.
    current: &'a [Vec<f64>],
    /// Sensor lag, s.
    lag: f64,
    /// Neighbour coupling.
    kappa: f64,
    /// Copper's temperature coefficient, 1/K.
    alpha: f64,
    /// Ambient drift, K/h.
    drift_h: f64,
    /// Heat from outside the catalog.
    foreign: ForeignHeat,
}

impl Plant<'_> {
    /// The truth ODE's derivatives of windings `w` and sensors `s` at time `t` in sample `k`.
    fn deriv(&self, t: f64, w: &[f64], s: &[f64], k: usize, dw: &mut [f64], ds: &mut [f64]) {
        let n = self.idle.len();
        let f = &self.foreign;
        for m in 0..n {
            let i = self.current[m][k];
            let cooling = if t >= f.loss_from_s {
                1.0 + f.loss
            } else {
                1.0
            };
            let mut heat = self.idle[m]
                + self.drift_h * t / 3600.0
                + cooling * self.gain[m] * (1.0 + self.alpha * (w[m] - 25.0)) * i * i
                - w[m];
            if m == f.heated && (t / f.heater_period_s).fract() < 0.5 {
                heat += f.heater_k;
            }
            if self.kappa != 0.0 {
                if m > 0 {
                    heat += self.kappa * (w[m - 1] - w[m]);
                }
                if m + 1 < n {
                    heat += self.kappa * (w[m + 1] - w[m]);
                }
            }
            dw[m] = heat / self.tau[m];
            ds[m] = if self.lag > 0.0 {
                (w[m] - s[m]) / self.lag
            } else {
                0.0
            };
        }
    }

    /// The sensors' true readings per motor at `steps` samples `period_s` apart, from windings
    /// (and sensors) at `w` (RK4, four sub-steps per sample).
    fn readings(&self, mut w: Vec<f64>, steps: usize, period_s: f64) -> Vec<Vec<f64>> {
        let n = w.len();
        let mut s = w.clone();
        let sub = 4;
        let h = period_s / sub as f64;
        let mut readings = vec![vec![0.0; steps]; n];
        let (mut k1w, mut k1s) = (vec![0.0; n], vec![0.0; n]);
        let (mut k2w, mut k2s) = (vec![0.0; n], vec![0.0; n]);
        let (mut k3w, mut k3s) = (vec![0.0; n], vec![0.0; n]);
        let (mut k4w, mut k4s) = (vec![0.0; n], vec![0.0; n]);
        let (mut tw, mut ts) = (vec![0.0; n], vec![0.0; n]);
        for k in 0..steps {
            for (m, r) in readings.iter_mut().enumerate() {
                r[k] = if self.lag > 0.0 { s[m] } else { w[m] };
            }
            for j in 0..sub {
                let t = k as f64 * period_s + j as f64 * h;
                self.deriv(t, &w, &s, k, &mut k1w, &mut k1s);
                for m in 0..n {
                    tw[m] = w[m] + 0.5 * h * k1w[m];
                    ts[m] = s[m] + 0.5 * h * k1s[m];
                }
                self.deriv(t + 0.5 * h, &tw, &ts, k, &mut k2w, &mut k2s);
                for m in 0..n {
                    tw[m] = w[m] + 0.5 * h * k2w[m];
                    ts[m] = s[m] + 0.5 * h * k2s[m];
                }
                self.deriv(t + 0.5 * h, &tw, &ts, k, &mut k3w, &mut k3s);
                for m in 0..n {
                    tw[m] = w[m] + h * k3w[m];
                    ts[m] = s[m] + h * k3s[m];
                }
                self.deriv(t + h, &tw, &ts, k, &mut k4w, &mut k4s);
                for m in 0..n {
                    w[m] += h / 6.0 * (k1w[m] + 2.0 * k2w[m] + 2.0 * k3w[m] + k4w[m]);
                    s[m] += h / 6.0 * (k1s[m] + 2.0 * k2s[m] + 2.0 * k3s[m] + k4s[m]);
                }
            }
        }
        readings
    }
}

/// What a dirty channel does to the registers: a temperature sensor stuck for a while, the
/// clock stepping back.
struct Faults {
    /// The stuck motor (none: `usize::MAX`) ...
    stuck_motor: usize,
    /// ... stuck over this span of time, s.
    stuck: std::ops::Range<f64>,
    /// From this time, s, the clock reads ...
    jump_from: f64,
    /// ... this much early, s.
    jump_s: f64,
}

impl Faults {
    /// `dirty`'s faults in a record of `duration` s of `n` motors, drawn from `frng`.
    fn draw(dirty: Option<Dirty>, frng: &mut Rng, duration: f64, n: usize) -> Faults {
        let (stuck_motor, stuck_from, stuck_until) = match dirty {
            Some(Dirty::StuckSensor) => {
                let from = frng.range(0.05, 0.6) * duration;
                (frng.int(0, n - 1), from, from + frng.range(1800.0, 3600.0))
            }
            _ => (usize::MAX, 0.0, 0.0),
        };
        let (jump_from, jump_s) = match dirty {
            Some(Dirty::ClockJump) => (frng.range(0.3, 0.7) * duration, frng.range(120.0, 900.0)),
            _ => (f64::INFINITY, 0.0),
        };
        Faults {
            stuck_motor,
            stuck: stuck_from..stuck_until,
            jump_from,
            jump_s,
        }
    }
}

/// The registers the truth is read through: the integer °C register with noise and glitches,
/// the 0.1 V supply register sagging with the bus current, the 6.5 mA current register.
struct Registers<'a> {
    /// Sample period, s.
    period_s: f64,
    /// Samples per motor, `period_s` apart.
    steps: usize,
    /// Currents per motor per sample, A.
    current: &'a [Vec<f64>],
    /// The sensors' true readings per motor per sample, °C.
    readings: &'a [Vec<f64>],
    /// The temperature sensor's noise, °C.
    noise: f64,
    /// The current register's offset, A.
    offset: f64,
    /// The supply's resistance, Ω.
    sag_ohm: f64,
    /// The supply's voltage, V ...
    v0: f64,
    /// ... and each motor's reading's offset from it.
    v_off: &'a [f64],
    /// A dirty channel's faults.
    faults: Faults,
    /// The current written in mA.
    milliamps: bool,
}

impl Registers<'_> {
    /// The CSV text, rows dropped and cells emptied at random (from `rng`).
    fn csv(&self, rng: &mut Rng) -> String {
        let n = self.readings.len();
        let f = &self.faults;
        let mut stuck_reading: Option<String> = None;
        let mut csv = String::from("t_s,motor,voltage_v,temperature_c,current_a\n");
        for k in 0..self.steps {
            let true_t = k as f64 * self.period_s;
            let t = if true_t >= f.jump_from {
                true_t - f.jump_s
            } else {
                true_t
            };
            let bus: f64 = (0..n).map(|m| self.current[m][k].abs()).sum();
            for m in 0..n {
                if rng.chance(0.003) {
                    continue; // dropped row
                }
                let mut temp = if rng.chance(0.003) {
                    String::new()
                } else if rng.chance(0.002) {
                    if rng.chance(0.5) { "0" } else { "150" }.to_string()
                } else {
                    format!(
                        "{}",
                        (self.readings[m][k] + self.noise * rng.normal()).round()
                    )
                };
                if m == f.stuck_motor && f.stuck.contains(&true_t) {
                    // Stuck on its first good reading of the interval.
                    match &stuck_reading {
                        Some(r) => temp.clone_from(r),
                        None if !temp.is_empty() && temp != "0" && temp != "150" => {
                            stuck_reading = Some(temp.clone());
                        }
                        None => {}
                    }
                }
                let i_reg = ((self.current[m][k] + self.offset + 0.01 * rng.normal())
                    / CURRENT_LSB_A)
                    .round()
                    * CURRENT_LSB_A;
                let v = ((self.v0 + self.v_off[m] - self.sag_ohm * bus + 0.03 * rng.normal())
                    * 10.0)
                    .round()
                    / 10.0;
                if self.milliamps {
                    let ma = 1000.0 * i_reg;
                    let _ = writeln!(csv, "{t:.3},{},{v:.1},{temp},{ma:.1}", m + 1);
                } else {
                    let _ = writeln!(csv, "{t:.3},{},{v:.1},{temp},{i_reg:.4}", m + 1);
                }
            }
        }
        csv
    }
}

/// The range a hidden motion effect's first parameter is drawn from (magnitude; the armature
/// and gain errors get a random sign, with a smaller range below zero).
pub fn motion_size_range(effect: Effect) -> (f64, f64) {
    match effect {
        Effect::Stribeck => (0.12, 0.25),
        Effect::LoadFriction => (0.1, 0.3),
        Effect::DirectionalFriction => (0.2, 0.4),
        Effect::ArmatureError => (0.6, 1.5),
        Effect::FirmwareGain => (0.25, 0.6),
        Effect::Backlash => (0.01, 0.04),
        _ => (0.0, 0.0),
    }
}

/// The parameter that carries a hidden motion effect: the first (a Stribeck friction's excess
/// at rest, not its width), or the directional friction's stronger side.
fn carrier(effect: Effect, parameters: &[f64]) -> usize {
    (0..parameters.len())
        .max_by(|&a, &b| parameters[a].abs().total_cmp(&parameters[b].abs()))
        .filter(|_| effect == Effect::DirectionalFriction)
        .unwrap_or(0)
}

/// A run's goal (rad) and torque enable at a time (s).
type Trajectory = fn(f64) -> (f64, bool);

/// Measured-like motion runs with one hidden mechanical effect (or none).
#[derive(Debug, Clone)]
pub struct GeneratedMotion {
    /// Per run: a name and its CSV text (telemetry format, motor 1).
    pub runs: Vec<(String, String)>,
    /// The load of every run.
    pub mechanics: crate::data::Mechanics,
    /// The hidden effect.
    pub effect: Effect,
    /// Its parameters in `motion::extension_params` order.
    pub parameters: Vec<f64>,
    /// The friction the truth had, N·m and N·m·s/rad.
    pub coulomb_viscous: (f64, f64),
}

impl GeneratedMotion {
    /// The runs as the reader sees them, each with its mechanics.
    pub fn dataset(&self) -> Result<Dataset, DataError> {
        let mut runs = Vec::new();
        for (name, csv) in &self.runs {
            runs.push((name.clone(), parse_csv(csv, name)?));
        }
        let mut d = Dataset::from_runs(runs, Meta::default(), "generated motion")?;
        for r in &mut d.runs {
            r.mechanics = Some(self.mechanics);
        }
        Ok(d)
    }

    /// The index of the parameter that carries the effect (its size).
    pub fn carrier(&self) -> usize {
        carrier(self.effect, &self.parameters)
    }
}

/// Four 6 s runs of one STS3250 swinging a mass on an arm, as on BAM's bench (a double sine,
/// lift and drop with the torque released at 2 s, a chirp, up and down steps), sampled at
/// about 50 Hz with jitter, positions in encoder steps, the supply sagging with the current in
/// 0.1 V steps; the truth is the simulator's servo at a tenth of the lab's step, carrying the
/// hidden effect and friction of its own.
pub fn generate_motion(effect: Effect, seed: u64) -> GeneratedMotion {
    generate_motion_sized(effect, seed, None)
}

/// [`generate_motion`] with the effect's size `given` (the value of the parameter that carries
/// it, signed; the rest drawn from `seed` as there), for what the size alone decides.
pub fn generate_motion_sized(effect: Effect, seed: u64, given: Option<f64>) -> GeneratedMotion {
    use crate::motion::{decode, MotionParams};
    use sim::servo::{Servo, Surroundings, RAD_PER_STEP};
    let mut rng = Rng::new(seed ^ 0x6D6F_7469_6F6E_0000);
    let robot = sim::RobotDescription::nori_a3();
    // The description always has the STS3250 (the arms' shoulders).
    let Some(rating) = robot.rating("sts3250") else {
        return GeneratedMotion {
            runs: Vec::new(),
            mechanics: crate::data::Mechanics {
                mass_kg: 0.0,
                length_m: 0.0,
                kp: 32.0,
            },
            effect,
            parameters: Vec::new(),
            coulomb_viscous: (0.0, 0.0),
        };
    };
    let mechanics = crate::data::Mechanics {
        mass_kg: rng.range(0.6, 1.4),
        length_m: rng.range(0.08, 0.14),
        kp: 32.0,
    };
    let (lo, hi) = motion_size_range(effect);
    let size = rng.range(lo, hi);
    let mut parameters = match effect {
        Effect::Stribeck => vec![size, rng.range(0.1, 0.6)],
        Effect::LoadFriction | Effect::Backlash => vec![size],
        // Back-driven much worse than driving (a worm-like gear), or the other way.
        Effect::DirectionalFriction => {
            let other = rng.range(0.0, 0.05);
            if rng.chance(0.5) {
                vec![other, size]
            } else {
                vec![size, other]
            }
        }
        Effect::ArmatureError => vec![if rng.chance(0.5) { size } else { -0.4 * size }],
        Effect::FirmwareGain => vec![if rng.chance(0.5) { size } else { -0.5 * size }],
        _ => Vec::new(),
    };
    let at = carrier(effect, &parameters);
    if let (Some(given), Some(p)) = (given, parameters.get_mut(at)) {
        *p = given;
    }
    let coulomb_viscous = (rng.range(0.03, 0.12), rng.range(0.03, 0.15));
    let mut x = vec![coulomb_viscous.0, coulomb_viscous.1];
    x.extend(&parameters);
    let truth: MotionParams = decode(effect, &x);
    let (m, l) = (mechanics.mass_kg, mechanics.length_m);
    let trajectories: [(&str, Trajectory); 4] = [
        ("sin_sin", |t| {
            (1.2 * (1.3 * t).sin() * (0.4 * t).sin().abs().max(0.3), true)
        }),
        ("lift_and_drop", |t| (-1.4 * (t / 0.6).min(1.0), t < 2.0)),
        ("chirp", |t| ((0.25 * t * t).sin(), true)),
        ("up_and_down", |t| {
            let g = if t < 1.5 {
                1.4 * t / 1.5
            } else if t < 3.5 {
                1.4
            } else {
                1.1
            };
            (g, true)
        }),
    ];
    let mut runs = Vec::new();
    for (name, goal_of) in trajectories {
        let mut s = Servo::new(1, rating.model, rating, 0.0, 25.0);
        s.plant.coulomb = truth.coulomb_nm;
        s.plant.viscous = truth.viscous_nms;
        s.extension = truth.ext;
        s.configure_for_replay(32);
        s.command_torque(true);
        let mut csv = String::from("t_s,motor,goal_rad,position_rad,voltage_v,torque_enabled\n");
        let h = 1e-4;
        let mut t = 0.0;
        let mut next_sample = 0.0;
        let mut torque = true;
        while t < 6.0 {
            if t >= next_sample {
                let (goal, on) = goal_of(t);
                let goal = (goal / RAD_PER_STEP).round() * RAD_PER_STEP;
                if on != torque {
                    s.command_torque(on);
                    torque = on;
                }
                s.command_goal(goal);
                let position = (s.angle / RAD_PER_STEP).round() * RAD_PER_STEP;
                let volts =
                    ((12.6 - 0.45 * s.current.abs() + 0.03 * rng.normal()) * 10.0).round() / 10.0;
                let _ = writeln!(
                    csv,
                    "{t:.4},1,{goal:.6},{position:.6},{volts:.1},{}",
                    u8::from(torque)
                );
                next_sample += 0.02 + 0.003 * rng.normal().clamp(-1.0, 1.0);
            }
            s.supply = 12.6 - 0.45 * s.current.abs();
            s.step(h, Surroundings::BENCH.pendulum(m, l, &s, h));
            t += h;
        }
        runs.push((format!("{name}.csv"), csv));
    }
    GeneratedMotion {
        runs,
        mechanics,
        effect,
        parameters,
        coulomb_viscous,
    }
}
