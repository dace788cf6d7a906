//! Measured data: the telemetry CSV reader (the only module of the crate that touches files),
//! the alignment of the per-motor rows on one time grid, segmentation at logging gaps and the
//! rejection of sensor glitches.
//!
//! The format is the long one of `data/README.md`: one row per motor per sample, a header
//! line naming the columns, empty cells for missing values. A directory is read as a sequence of
//! runs (its `.csv` files in name order, which is time order for time-stamped names); each run
//! starts a new segment, since nothing is known about the robot between two runs.

use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::Path;
use thiserror::Error;

/// Data that cannot be read.
#[derive(Debug, Error)]
#[allow(missing_docs, reason = "each field is shown in its variant's message")]
pub enum DataError {
    /// A file or directory could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The path.
        path: String,
        source: std::io::Error,
    },
    /// A required column is absent from the header.
    #[error("{path}: no column {column:?} in the header (found {found})")]
    MissingColumn {
        /// The file.
        path: String,
        /// The required column.
        column: &'static str,
        /// The header as read.
        found: String,
    },
    /// A cell that is neither empty nor a number.
    #[error("{path}:{line}: column {column:?}: {value:?} is not a number")]
    BadNumber {
        /// The file.
        path: String,
        /// 1-based line number.
        line: usize,
        /// Column name.
        column: String,
        /// The cell.
        value: String,
    },
    /// The sidecar `NAME.meta.json` is not valid.
    #[error("{path}: {source}")]
    Meta {
        /// The sidecar file.
        path: String,
        source: serde_json::Error,
    },
    /// Nothing usable: no rows, or no timestamps.
    #[error("{path}: no data rows")]
    Empty {
        /// The file or directory.
        path: String,
    },
    /// More distinct motor ids than any robot has: the grid (motors × samples) would grow with
    /// the square of the input.
    #[error("{path}: {count} distinct motor ids (at most {MAX_MOTORS})")]
    TooManyMotors {
        /// The file or directory.
        path: String,
        /// Distinct ids found.
        count: usize,
    },
}

/// Most distinct motor ids a data set may have (a Feetech bus addresses 253).
pub const MAX_MOTORS: usize = 256;
/// Rows whose `t_s` agree to this resolution (per second: a microsecond) are one sample.
const TIME_KEYS_PER_S: f64 = 1e6;

/// One CSV row (one motor at one time). Missing cells are NaN.
#[derive(Debug, Clone, Copy)]
pub struct Row {
    /// Time, s.
    pub t: f64,
    /// Motor id.
    pub motor: i64,
    /// Commanded position, rad.
    pub goal: f64,
    /// Measured position, rad.
    pub position: f64,
    /// Measured velocity, rad/s.
    pub velocity: f64,
    /// Supply voltage, V.
    pub voltage: f64,
    /// Temperature register, °C.
    pub temperature: f64,
    /// Motor current, A.
    pub current: f64,
    /// Ambient temperature, °C.
    pub ambient: f64,
    /// Torque enabled (1) or not (0).
    pub torque: f64,
}

/// The optional sidecar `NAME.meta.json`.
#[derive(Debug, Clone, Default, Deserialize)]
pub struct Meta {
    /// Daisy chains, as lists of motor ids in physical order.
    #[serde(default)]
    pub chains: Option<Vec<Vec<i64>>>,
    /// Servo model by motor id (as a string key).
    #[serde(default)]
    pub servo: Option<BTreeMap<String, String>>,
}

/// What a run's sidecar says about the mechanics on the servo's output: a pendulum (BAM's
/// bench: a mass on an arm, angle 0 hanging down) and the position gain the run was recorded
/// with. In `NAME.meta.json` as `"mechanics": {"mass_kg": …, "length_m": …, "kp": …}`; a
/// BAM log's own `NAME.json` (top-level `mass`, `length`, `kp`) is read too.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, serde::Serialize)]
pub struct Mechanics {
    /// Mass at the arm's end, kg.
    #[serde(alias = "mass")]
    pub mass_kg: f64,
    /// Arm length to the mass, m.
    #[serde(alias = "length")]
    pub length_m: f64,
    /// P_Coefficient the run was recorded with.
    #[serde(default = "default_kp")]
    pub kp: f64,
}

fn default_kp() -> f64 {
    32.0
}

/// One run (file) of the data: its samples `start..end` and its mechanics when known.
#[derive(Debug, Clone, PartialEq)]
pub struct RunInfo {
    /// The file.
    pub name: String,
    /// First sample.
    pub start: usize,
    /// One past the last sample.
    pub end: usize,
    /// What its sidecar says, if anything.
    pub mechanics: Option<Mechanics>,
}

#[derive(Deserialize)]
struct MechanicsSidecar {
    mechanics: Option<Mechanics>,
}

/// A run's mechanics from `NAME.meta.json` or a BAM log's `NAME.json`, if either says.
fn read_mechanics(csv: &Path) -> Result<Option<Mechanics>, DataError> {
    let read = |p: &Path| -> Result<Option<String>, DataError> {
        if !p.exists() {
            return Ok(None);
        }
        std::fs::read_to_string(p)
            .map(Some)
            .map_err(|source| DataError::Io {
                path: p.display().to_string(),
                source,
            })
    };
    let bad = |p: &Path, source| DataError::Meta {
        path: p.display().to_string(),
        source,
    };
    let meta = csv.with_extension("meta.json");
    if let Some(text) = read(&meta)? {
        let m: MechanicsSidecar = serde_json::from_str(&text).map_err(|e| bad(&meta, e))?;
        if m.mechanics.is_some() {
            return Ok(m.mechanics);
        }
    }
    let bam = csv.with_extension("json");
    match read(&bam)? {
        Some(text) => Ok(Some(serde_json::from_str(&text).map_err(|e| bad(&bam, e))?)),
        None => Ok(None),
    }
}

/// Columns a reader recognises, with the aliases it accepts for them.
const COLUMNS: &[(&str, &[&str])] = &[
    ("t_s", &["time_s", "timestamp"]),
    ("motor", &["motor_id", "id"]),
    ("goal_rad", &["goal_position"]),
    ("position_rad", &["position"]),
    ("velocity_rad_s", &["speed", "speed_rad_s"]),
    ("voltage_v", &["input_volts"]),
    ("temperature_c", &["temp", "temp_c"]),
    ("current_a", &[]),
    ("ambient_c", &[]),
    ("torque_enabled", &["torque_enable"]),
];

/// Parses one CSV text; `origin` names it in errors.
pub fn parse_csv(text: &str, origin: &str) -> Result<Vec<Row>, DataError> {
    let mut lines = text.lines().enumerate();
    let header = loop {
        match lines.next() {
            Some((_, l)) if l.trim().is_empty() || l.starts_with('#') => continue,
            Some((_, l)) => break l,
            None => {
                return Err(DataError::Empty {
                    path: origin.into(),
                })
            }
        }
    };
    let names: Vec<String> = header
        .split(',')
        .map(|s| s.trim().trim_matches('"').to_ascii_lowercase())
        .collect();
    // Column index of each recognised field, by canonical name or alias.
    let find = |canon: &str| -> Option<usize> {
        let aliases = COLUMNS
            .iter()
            .find(|(c, _)| *c == canon)
            .map(|(_, a)| *a)
            .unwrap_or(&[]);
        names
            .iter()
            .position(|n| n == canon || aliases.contains(&n.as_str()))
    };
    let required = |c: &'static str| {
        find(c).ok_or_else(|| DataError::MissingColumn {
            path: origin.into(),
            column: c,
            found: header.into(),
        })
    };
    let (it, im) = (required("t_s")?, required("motor")?);
    let idx: Vec<Option<usize>> = COLUMNS[2..].iter().map(|(c, _)| find(c)).collect();
    let mut rows = Vec::new();
    for (n, line) in lines {
        if line.trim().is_empty() {
            continue;
        }
        let cells: Vec<&str> = line.split(',').collect();
        let num = |i: usize| -> Result<f64, DataError> {
            let cell = cells.get(i).map(|c| c.trim()).unwrap_or("");
            if cell.is_empty() || cell.eq_ignore_ascii_case("nan") {
                return Ok(f64::NAN);
            }
            cell.parse::<f64>().map_err(|_| DataError::BadNumber {
                path: origin.into(),
                line: n + 1,
                column: names.get(i).cloned().unwrap_or_default(),
                value: cell.into(),
            })
        };
        let t = num(it)?;
        let motor = num(im)?;
        // A row without a time or a motor cannot be placed: it is a dropped sample.
        if !t.is_finite() || !motor.is_finite() {
            continue;
        }
        let mut v = [f64::NAN; 8];
        for (slot, i) in v.iter_mut().zip(&idx) {
            if let Some(i) = *i {
                *slot = num(i)?;
            }
        }
        rows.push(Row {
            t,
            motor: motor as i64,
            goal: v[0],
            position: v[1],
            velocity: v[2],
            voltage: v[3],
            temperature: v[4],
            current: v[5],
            ambient: v[6],
            torque: v[7],
        });
    }
    Ok(rows)
}

/// Reads a CSV file (with its sidecar, if any) or a directory of them.
pub fn load(path: &Path) -> Result<Dataset, DataError> {
    load_all(std::slice::from_ref(&path.to_path_buf()))
}

/// Reads CSV files (with their sidecars) and directories of them as one dataset, one run per
/// file: a subset of a directory's runs is named file by file (runs a fit must not see left
/// out).
pub fn load_all(paths: &[std::path::PathBuf]) -> Result<Dataset, DataError> {
    let mut files = Vec::new();
    for path in paths {
        let io = |source| DataError::Io {
            path: path.display().to_string(),
            source,
        };
        if path.is_dir() {
            for e in std::fs::read_dir(path).map_err(io)? {
                let p = e.map_err(io)?.path();
                if p.extension().is_some_and(|x| x == "csv") {
                    files.push(p);
                }
            }
        } else {
            files.push(path.clone());
        }
    }
    // A file named twice (itself and in its directory) is one run.
    files.sort();
    files.dedup();
    let origin = paths
        .iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(" ");
    let mut runs = Vec::new();
    let mut meta = Meta::default();
    for f in &files {
        let name = f.display().to_string();
        let text = std::fs::read_to_string(f).map_err(|source| DataError::Io {
            path: name.clone(),
            source,
        })?;
        runs.push((name.clone(), parse_csv(&text, &name)?));
        let side = f.with_extension("meta.json");
        if side.exists() {
            let text = std::fs::read_to_string(&side).map_err(|source| DataError::Io {
                path: side.display().to_string(),
                source,
            })?;
            meta = serde_json::from_str(&text).map_err(|source| DataError::Meta {
                path: side.display().to_string(),
                source,
            })?;
        }
    }
    let mut d = Dataset::from_runs(runs, meta, &origin)?;
    for f in &files {
        let mechanics = read_mechanics(f)?;
        let name = f.display().to_string();
        if let Some(r) = d.runs.iter_mut().find(|r| r.name == name) {
            r.mechanics = mechanics;
        }
    }
    Ok(d)
}

/// Finds where a motor's clock steps back in file order (an NTP correction, a logger restarted
/// without a new file) and shifts that motor's later rows forward so its time runs on, one
/// sample period after the last reading before the jump: sorted by time, the rows after the
/// jump would otherwise be interleaved with those before it. A file sorted by motor is no
/// jump (each motor's own rows are followed). Returns one finding per run with a jump.
fn repair_clock(name: &str, rows: &mut [Row]) -> Option<crate::audit::Finding> {
    // Per motor: the last time read (after shifts), the shift in force, its periods.
    let mut last: BTreeMap<i64, (f64, f64, Vec<f64>)> = BTreeMap::new();
    let mut jumps: Vec<(usize, f64, f64)> = Vec::new();
    for (n, r) in rows.iter_mut().enumerate() {
        let e = last
            .entry(r.motor)
            .or_insert((f64::NEG_INFINITY, 0.0, Vec::new()));
        let t = r.t + e.1;
        // A step back of a few periods is rows a little out of order (sorting fixes them); a
        // jump is longer than that and than a second.
        let period = || {
            let mut periods = e.2.clone();
            periods.sort_by(f64::total_cmp);
            periods.get(periods.len() / 2).copied().unwrap_or(0.0)
        };
        if t < e.0 - 1.0 && t < e.0 - 3.0 * period() {
            let back = e.0 - t + period();
            e.1 += back;
            jumps.push((n + 1, back, e.0));
        } else if e.0.is_finite() && t > e.0 && e.2.len() < 64 {
            e.2.push(t - e.0);
        }
        r.t += e.1;
        e.0 = e.0.max(r.t);
    }
    let (row, back, at) = *jumps.first()?;
    Some(crate::audit::Finding {
        column: "t_s",
        kind: "clock_jump",
        action: crate::audit::Action::Fixed,
        detail: format!(
            "{name}: the clock steps back {back:.3} s after t = {at:.3} s (data row {row}); \
             {} backward step(s) in all (one per motor per jump): each motor's later rows \
             shifted forward to run on from its last reading",
            jumps.len()
        ),
    })
}

/// The motor ids of `runs`, ascending; an error when there are none or more than
/// [`MAX_MOTORS`].
fn motor_ids(runs: &[(String, Vec<Row>)], origin: &str) -> Result<Vec<i64>, DataError> {
    let mut motors: Vec<i64> = runs
        .iter()
        .flat_map(|(_, r)| r.iter().map(|r| r.motor))
        .collect();
    motors.sort_unstable();
    motors.dedup();
    if motors.is_empty() {
        return Err(DataError::Empty {
            path: origin.into(),
        });
    }
    if motors.len() > MAX_MOTORS {
        return Err(DataError::TooManyMotors {
            path: origin.into(),
            count: motors.len(),
        });
    }
    Ok(motors)
}

impl Meta {
    /// The daisy chains as indices into `motors`: the sidecar's, else one chain of consecutive
    /// ids (the README's convention).
    fn chains_of(&self, motors: &[i64]) -> Vec<Vec<usize>> {
        match &self.chains {
            Some(chains) => chains
                .iter()
                .map(|c| {
                    c.iter()
                        .filter_map(|id| motors.binary_search(id).ok())
                        .collect()
                })
                .collect(),
            None => vec![(0..motors.len()).collect()],
        }
    }

    /// The servo model of each of `motors`, where the sidecar names it.
    fn servo_models_of(&self, motors: &[i64]) -> Vec<Option<String>> {
        motors
            .iter()
            .map(|id| {
                self.servo
                    .as_ref()
                    .and_then(|s| s.get(&id.to_string()).cloned())
            })
            .collect()
    }
}

/// Measured data on one time grid: `[motor][sample]`, NaN where a value is missing.
#[derive(Debug, Clone, Default)]
pub struct Dataset {
    /// Motor ids, ascending.
    pub motors: Vec<i64>,
    /// Sample times, s, increasing (runs of a directory are laid end to end).
    pub t: Vec<f64>,
    /// Sample indices where a segment starts (the first is 0). Nothing is known about the inputs
    /// between two segments, so every model restarts its state there.
    pub segment_starts: Vec<usize>,
    /// Temperature register, °C.
    pub temperature: Vec<Vec<f64>>,
    /// Motor current, A.
    pub current: Vec<Vec<f64>>,
    /// Supply voltage, V.
    pub voltage: Vec<Vec<f64>>,
    /// Commanded position, rad.
    pub goal: Vec<Vec<f64>>,
    /// Measured position, rad.
    pub position: Vec<Vec<f64>>,
    /// Measured velocity, rad/s.
    pub velocity: Vec<Vec<f64>>,
    /// Torque enabled (1) or not (0); NaN when not logged.
    pub torque_enabled: Vec<Vec<f64>>,
    /// Daisy chains as lists of motor indices (into `motors`) in physical order.
    pub chains: Vec<Vec<usize>>,
    /// Servo model keys by motor index, when a sidecar names them.
    pub servo_models: Vec<Option<String>>,
    /// Resolution of the temperature register, °C (smallest step between readings).
    pub temperature_quantum: f64,
    /// How the input was adapted (runs joined, columns absent), for the report.
    pub notes: Vec<String>,
    /// The clock's backward jumps found (and repaired) while reading, in row order.
    pub clock_findings: Vec<crate::audit::Finding>,
    /// The runs (files), in order.
    pub runs: Vec<RunInfo>,
}

/// A gap longer than this many median sample periods (and than [`MIN_SEGMENT_GAP_S`]) starts a
/// new segment: holding the last input across it would be a guess.
pub const SEGMENT_GAP_PERIODS: f64 = 20.0;
/// See [`SEGMENT_GAP_PERIODS`], s.
pub const MIN_SEGMENT_GAP_S: f64 = 60.0;

impl Dataset {
    /// Aligns the rows of one or more runs on a common grid (rows whose times agree to the
    /// millisecond are one sample).
    pub fn from_runs(
        runs: Vec<(String, Vec<Row>)>,
        meta: Meta,
        origin: &str,
    ) -> Result<Self, DataError> {
        let mut clock_findings = Vec::new();
        let runs: Vec<(String, Vec<Row>)> = runs
            .into_iter()
            .map(|(name, mut rows)| {
                clock_findings.extend(repair_clock(&name, &mut rows));
                (name, rows)
            })
            .collect();
        let motors = motor_ids(&runs, origin)?;
        let nm = motors.len();
        let mut d = Dataset {
            motors: motors.clone(),
            clock_findings,
            temperature: vec![Vec::new(); nm],
            current: vec![Vec::new(); nm],
            voltage: vec![Vec::new(); nm],
            goal: vec![Vec::new(); nm],
            position: vec![Vec::new(); nm],
            velocity: vec![Vec::new(); nm],
            torque_enabled: vec![Vec::new(); nm],
            ..Default::default()
        };
        let mut run_starts = Vec::new();
        for (name, rows) in &runs {
            if rows.is_empty() {
                continue;
            }
            run_starts.push(d.t.len());
            d.append_run(name, rows);
        }
        if d.t.len() < 2 {
            return Err(DataError::Empty {
                path: origin.into(),
            });
        }
        d.mark_segments(run_starts);
        d.chains = meta.chains_of(&motors);
        d.servo_models = meta.servo_models_of(&motors);
        d.temperature_quantum = quantum(&d.temperature);
        for (name, col) in [
            ("temperature_c", &d.temperature),
            ("current_a", &d.current),
            ("voltage_v", &d.voltage),
        ] {
            if !has_values(col) {
                d.notes.push(format!("no {name} values"));
            }
        }
        Ok(d)
    }

    /// Lays one run's rows onto the grid after the runs before it (its own clock shifted to
    /// start one second after their last sample), one sample per time.
    fn append_run(&mut self, name: &str, rows: &[Row]) {
        // Group rows by time (µs key: a millisecond would move a sample of a joint at
        // 2 rad/s by up to a step of the encoder); BTreeMap keeps them sorted.
        let mut by_t: BTreeMap<i64, Vec<&Row>> = BTreeMap::new();
        for r in rows {
            by_t.entry((r.t * TIME_KEYS_PER_S).round() as i64)
                .or_default()
                .push(r);
        }
        let first = by_t
            .keys()
            .next()
            .map_or(0.0, |&k| k as f64 / TIME_KEYS_PER_S);
        // Runs are laid end to end, one second apart; the gap starts a segment anyway.
        let shift = self.t.last().map_or(0.0, |offset| offset + 1.0 - first);
        if !self.t.is_empty() {
            self.notes.push(format!(
                "run {name} appended at t = {:.1} s (own clock shifted by {shift:.1} s)",
                first + shift
            ));
        }
        self.runs.push(RunInfo {
            name: name.to_string(),
            start: self.t.len(),
            end: self.t.len() + by_t.len(),
            mechanics: None,
        });
        for (k, group) in by_t {
            self.push_sample(k as f64 / TIME_KEYS_PER_S + shift, &group);
        }
    }

    /// Appends the sample at `t` made of `rows` (one per motor; a motor without one is
    /// missing there).
    fn push_sample(&mut self, t: f64, rows: &[&Row]) {
        self.t.push(t);
        let mut cells = vec![[f64::NAN; 7]; self.motors.len()];
        for r in rows {
            if let Ok(i) = self.motors.binary_search(&r.motor) {
                cells[i] = [
                    r.temperature,
                    r.current,
                    r.voltage,
                    r.goal,
                    r.position,
                    r.velocity,
                    r.torque,
                ];
            }
        }
        for (i, c) in cells.iter().enumerate() {
            self.temperature[i].push(c[0]);
            self.current[i].push(c[1]);
            self.voltage[i].push(c[2]);
            self.goal[i].push(c[3]);
            self.position[i].push(c[4]);
            self.velocity[i].push(c[5]);
            self.torque_enabled[i].push(c[6]);
        }
    }

    /// Starts a segment at every run start and at every long gap (said in the notes).
    fn mark_segments(&mut self, run_starts: Vec<usize>) {
        let mut dts: Vec<f64> = self.t.windows(2).map(|w| w[1] - w[0]).collect();
        dts.sort_by(f64::total_cmp);
        let median_dt = dts[dts.len() / 2];
        let gap = (SEGMENT_GAP_PERIODS * median_dt).max(MIN_SEGMENT_GAP_S);
        let mut starts = run_starts;
        for k in 1..self.t.len() {
            let dt = self.t[k] - self.t[k - 1];
            if dt > gap {
                starts.push(k);
                self.notes.push(format!(
                    "logging gap of {dt:.0} s at t = {:.0} s: new segment",
                    self.t[k - 1]
                ));
            }
        }
        starts.sort_unstable();
        starts.dedup();
        self.segment_starts = starts;
    }

    /// Number of samples on the grid.
    pub fn len(&self) -> usize {
        self.t.len()
    }

    /// True when the grid is empty.
    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }

    /// The segment sample `k` belongs to, as `(start, end)` indices.
    pub fn segments(&self) -> Vec<(usize, usize)> {
        let mut out = Vec::new();
        for (i, &s) in self.segment_starts.iter().enumerate() {
            let e = self
                .segment_starts
                .get(i + 1)
                .copied()
                .unwrap_or(self.t.len());
            if e > s {
                out.push((s, e));
            }
        }
        out
    }

    /// The neighbours of motor index `i` on its chains.
    pub fn neighbours(&self, i: usize) -> Vec<usize> {
        let mut out = Vec::new();
        for c in &self.chains {
            if let Some(p) = c.iter().position(|&m| m == i) {
                if p > 0 {
                    out.push(c[p - 1]);
                }
                if p + 1 < c.len() {
                    out.push(c[p + 1]);
                }
            }
        }
        out
    }

    /// The bus (chain) of motor index `i`: all motors sharing its supply.
    pub fn bus_of(&self, i: usize) -> Vec<usize> {
        self.chains
            .iter()
            .find(|c| c.contains(&i))
            .cloned()
            .unwrap_or_else(|| vec![i])
    }
}

/// True when any cell is a number.
pub fn has_values(col: &[Vec<f64>]) -> bool {
    col.iter().any(|m| m.iter().any(|v| v.is_finite()))
}

/// The smallest non-zero step between distinct readings (the register's resolution).
pub(crate) fn quantum(col: &[Vec<f64>]) -> f64 {
    let mut vals: Vec<f64> = col
        .iter()
        .flatten()
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    vals.sort_by(f64::total_cmp);
    vals.dedup();
    let q = vals
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|d| *d > 1e-9)
        .fold(f64::INFINITY, f64::min);
    if q.is_finite() {
        q
    } else {
        1.0
    }
}

/// What glitch rejection removed.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct Cleaning {
    /// Temperature readings dropped as glitches.
    pub temperature_glitches: usize,
    /// Temperature cells that were empty or NaN.
    pub temperature_missing: usize,
}

/// Half-width of the window a temperature reading is compared with, samples.
const GLITCH_WINDOW: usize = 4;
/// A reading further than this from its window's median is a glitch, °C. A winding that heats
/// faster than this over a few samples would already be far past any cutoff.
pub const GLITCH_JUMP_C: f64 = 5.0;

/// Rejects implausible temperature readings: those further than [`GLITCH_JUMP_C`] from the
/// median of their neighbours (the 0 °C and 150 °C read errors of the Feetech register, single
/// or a few in a row), and NaN. Rejected readings become missing.
pub fn reject_glitches(d: &mut Dataset) -> Cleaning {
    let mut c = Cleaning::default();
    for col in &mut d.temperature {
        let orig = col.clone();
        let valid: Vec<usize> = (0..orig.len()).filter(|&k| orig[k].is_finite()).collect();
        c.temperature_missing += orig.len() - valid.len();
        let mut win = Vec::with_capacity(2 * GLITCH_WINDOW + 1);
        for (j, &k) in valid.iter().enumerate() {
            win.clear();
            let lo = j.saturating_sub(GLITCH_WINDOW);
            let hi = (j + GLITCH_WINDOW + 1).min(valid.len());
            win.extend(valid[lo..hi].iter().map(|&q| orig[q]));
            win.sort_by(f64::total_cmp);
            let med = win[win.len() / 2];
            if (orig[k] - med).abs() > GLITCH_JUMP_C {
                col[k] = f64::NAN;
                c.temperature_glitches += 1;
            }
        }
    }
    c
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    #[test]
    fn rows_align_on_a_grid_and_gaps_split_segments() {
        let text = "t_s,motor,temperature_c,current_a\n\
                    0.0,2,30,0.5\n0.0,1,25,\n1.0,1,26,0.1\n1.0,2,,0.4\n2.0,1,26,0.1\n\
                    500.0,1,27,0.2\n";
        let rows = parse_csv(text, "x").unwrap();
        let d = Dataset::from_runs(vec![("x".into(), rows)], Meta::default(), "x").unwrap();
        assert_eq!(d.motors, [1, 2]);
        assert_eq!(d.t, [0.0, 1.0, 2.0, 500.0]);
        // A 498 s gap at a 1 s period starts a new segment.
        assert_eq!(d.segment_starts, [0, 3]);
        assert!(d.temperature[1][2].is_nan(), "motor 2 has no row at 2 s");
        assert!(d.current[0][0].is_nan() && d.temperature[1][1].is_nan());
        assert_eq!(d.temperature[1][0], 30.0);
        assert_eq!(d.neighbours(0), [1]);
        assert_eq!(d.temperature_quantum, 1.0);
    }

    /// BAM's logs stamp samples to 10 µs at about 50 Hz: a joint swinging at 2 rad/s moves an
    /// encoder step in under a millisecond, so the sample times are kept as logged.
    #[test]
    fn sample_times_are_kept_to_the_microsecond() {
        let text = "t_s,motor,position_rad\n0.01370,1,0.0\n0.034312,1,0.1\n0.0343,2,0.2\n";
        let rows = parse_csv(text, "x").unwrap();
        let d = Dataset::from_runs(vec![("x".into(), rows)], Meta::default(), "x").unwrap();
        assert_eq!(d.t.len(), 3, "{:?}", d.t);
        for (t, logged) in d.t.iter().zip([0.0137, 0.0343, 0.034312]) {
            assert!((t - logged).abs() < 1e-9, "{t} for {logged}");
        }
    }

    #[test]
    fn a_bad_cell_names_line_and_column() {
        let err = parse_csv("t_s,motor,current_a\n0,1,abc\n", "f.csv")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("f.csv:2") && err.contains("current_a"),
            "{err}"
        );
        let err = parse_csv("time,motor\n0,1\n", "f.csv")
            .unwrap_err()
            .to_string();
        assert!(err.contains("t_s"), "{err}");
    }

    #[test]
    fn glitches_are_dropped_and_real_steps_kept() {
        let mut temps: Vec<f64> = (0..40).map(|k| 30.0 + (k / 10) as f64).collect();
        temps[7] = 0.0;
        temps[20] = 150.0;
        temps[21] = 150.0;
        let mut d = Dataset {
            temperature: vec![temps],
            ..Default::default()
        };
        let c = reject_glitches(&mut d);
        assert_eq!(c.temperature_glitches, 3);
        let kept = d.temperature[0].iter().filter(|v| v.is_finite()).count();
        assert_eq!(kept, 37);
    }
}
