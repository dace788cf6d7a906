//! Data that lie: every channel is checked against the servo's physical ranges and against the
//! unit mistakes that are easy to make before anything is fitted. What is unambiguous is fixed
//! (and said); a channel that is nonsense is refused (emptied, so no model is fitted to it),
//! naming the column; a stuck temperature sensor's readings are dropped. The clock's jumps
//! are found where the row order is still known, when the data are read
//! ([`crate::data::Dataset::from_runs`]), and reported here with the rest.

use crate::data::Dataset;
use serde::Serialize;

/// The physical ranges the data are held against (the servo's rating).
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// Stall current, A: no motor current is larger.
    pub stall_current_a: f64,
    /// Highest supply voltage the servo takes, V.
    pub max_supply_v: f64,
    /// Highest temperature a Feetech register can read before the firmware cuts off, °C.
    pub max_temperature_c: f64,
    /// Fastest a joint turns, rad/s.
    pub max_speed_rad_s: f64,
}

impl Default for Limits {
    /// An STS3215 on a 12 V bus.
    fn default() -> Self {
        Limits {
            stall_current_a: 2.7,
            max_supply_v: 16.8,
            max_temperature_c: 100.0,
            max_speed_rad_s: 30.0,
        }
    }
}

/// What the audit did about a finding.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Action {
    /// Corrected (an unambiguous unit mistake).
    Fixed,
    /// The column emptied: nonsense, or a unit that cannot be told.
    Refused,
    /// Some readings dropped (a stuck sensor, a clock jump).
    Dropped,
    /// Said, and used as it is (a little beyond the rating: another motor, a harder duty).
    Flagged,
}

impl Action {
    /// Its name, as `--json` writes it.
    pub fn as_str(self) -> &'static str {
        match self {
            Action::Fixed => "fixed",
            Action::Refused => "refused",
            Action::Dropped => "dropped",
            Action::Flagged => "flagged",
        }
    }
}

impl std::fmt::Display for Action {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The columns refused, each with why, for the error that says nothing is left to analyse.
pub fn refused(findings: &[Finding]) -> String {
    findings
        .iter()
        .filter(|f| f.action == Action::Refused)
        .map(|f| format!("{}: {}", f.column, f.detail))
        .collect::<Vec<_>>()
        .join("; ")
}

/// One thing found wrong with the data.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Finding {
    /// The column.
    pub column: &'static str,
    /// What was found: `milliamps`, `register_counts`, `tenths_of_volts`, `millivolts`,
    /// `kelvin`, `degrees`, `beyond_physics`, `ambiguous_unit`, `stuck`, `clock_jump`.
    pub kind: &'static str,
    /// What was done.
    pub action: Action,
    /// The figures, for a reader.
    pub detail: String,
}

/// A column's 99th percentile of |value| and its median, over finite values.
fn spread(col: &[Vec<f64>]) -> Option<(f64, f64, usize)> {
    let mut v: Vec<f64> = col
        .iter()
        .flatten()
        .copied()
        .filter(|x| x.is_finite())
        .collect();
    if v.is_empty() {
        return None;
    }
    let n = v.len();
    let mut abs: Vec<f64> = v.iter().map(|x| x.abs()).collect();
    abs.sort_by(f64::total_cmp);
    v.sort_by(f64::total_cmp);
    Some((abs[(n - 1) * 99 / 100], v[n / 2], n))
}

/// Whether (nearly) every finite value is a whole multiple of `step`.
fn multiples_of(col: &[Vec<f64>], step: f64) -> bool {
    let (mut on, mut all) = (0usize, 0usize);
    for &x in col.iter().flatten().filter(|x| x.is_finite()) {
        all += 1;
        let r = x / step;
        if (r - r.round()).abs() < 1e-6 * r.abs().max(1.0) {
            on += 1;
        }
    }
    all > 0 && on * 1000 >= all * 999
}

fn scale(col: &mut [Vec<f64>], f: impl Fn(f64) -> f64) {
    for x in col.iter_mut().flatten() {
        *x = f(*x);
    }
}

fn refuse(col: &mut [Vec<f64>]) {
    for x in col.iter_mut().flatten() {
        *x = f64::NAN;
    }
}

/// Up to this many times a current's, a voltage's or a temperature's physical limit, data are
/// taken as real (flagged: another servo, a harder duty); beyond it, as a unit mistake or
/// nonsense. Angles and speeds have no such margin: beyond a turn is a unit mistake.
pub const BEYOND_RATING: f64 = 5.0;

/// What a column's values can be: |value| up to `limit` (`tolerance` times it flagged but
/// used), the median within `plausible`, in `unit`.
struct Physical<'a> {
    unit: &'a str,
    limit: f64,
    tolerance: f64,
    plausible: (f64, f64),
}

/// A unit a column may have been written in by mistake: its name, the factor to the right
/// unit, and whether its values would be whole numbers (a raw register).
struct Mistake {
    kind: &'static str,
    factor: f64,
    offset: f64,
    integers: bool,
    what: &'static str,
}

/// Checks one column whose |values| must stay within `limit` (99th percentile) and whose
/// median must lie in `plausible`: within, nothing; beyond, the one mistake whose fix brings
/// it within (whole-number mistakes only for whole-number data); none or several: refused.
fn check_scale(
    col: &mut [Vec<f64>],
    column: &'static str,
    range: Physical,
    mistakes: &[Mistake],
    out: &mut Vec<Finding>,
) {
    let Physical {
        unit,
        limit,
        tolerance,
        plausible,
    } = range;
    let Some((p99, median, n)) = spread(col) else {
        return;
    };
    let within =
        |p99: f64, median: f64| p99 <= limit && median >= plausible.0 && median <= plausible.1;
    if within(p99, median) {
        return;
    }
    // A little beyond the rating is another motor or a harder duty than rated, not a unit
    // mistake (those are factors of ten or more): said, and used as it is.
    if p99 <= tolerance * limit && median >= plausible.0 && median <= plausible.1 {
        out.push(Finding {
            column,
            kind: "beyond_rating",
            action: Action::Flagged,
            detail: format!(
                "{} values, 99th percentile of |value| {p99:.4} {unit}, above the servo's \
                 {limit} {unit} but within {tolerance} times it: another motor than \
                 `--servo`, or a duty beyond its rating; used as it is",
                spread(col).map_or(0, |s| s.2)
            ),
        });
        return;
    }
    let integers = multiples_of(col, 1.0);
    let fixed = |m: &Mistake| -> Vec<Vec<f64>> {
        col.iter()
            .map(|v| v.iter().map(|x| (x + m.offset) * m.factor).collect())
            .collect()
    };
    let fits: Vec<&Mistake> = mistakes
        .iter()
        .filter(|m| !m.integers || integers)
        .filter(|m| spread(&fixed(m)).is_some_and(|(p, med, _)| within(p, med)))
        .collect();
    let seen = format!(
        "{n} values, median {median:.4}, 99th percentile of |value| {p99:.4}; the servo's \
         range is |value| ≤ {limit} {unit} with a median in [{}, {}] {unit}",
        plausible.0, plausible.1
    );
    match fits.as_slice() {
        [m] => {
            let (factor, offset) = (m.factor, m.offset);
            scale(col, |x| (x + offset) * factor);
            out.push(Finding {
                column,
                kind: m.kind,
                action: Action::Fixed,
                detail: format!("{seen}: {}; converted to {unit}", m.what),
            });
        }
        [] => {
            refuse(col);
            out.push(Finding {
                column,
                kind: "beyond_physics",
                action: Action::Refused,
                detail: format!("{seen}, and no unit mistake explains it: the column is not used"),
            });
        }
        several => {
            refuse(col);
            let names: Vec<&str> = several.iter().map(|m| m.what).collect();
            out.push(Finding {
                column,
                kind: "ambiguous_unit",
                action: Action::Refused,
                detail: format!(
                    "{seen}; it could be {}: the column is not used (convert it and run again)",
                    names.join(" or ")
                ),
            });
        }
    }
}

/// A temperature register that stays on one reading at least this long while its motor's
/// heating changes is stuck, s.
pub const STUCK_MIN_S: f64 = 1200.0;
/// The window the heating (mean I²) is averaged over, s.
const STUCK_WINDOW_S: f64 = 300.0;
/// Change of the windowed mean I² within such a run that must move the register, A²: a servo
/// heats 5–15 K per A², so at least a kelvin or so.
pub const STUCK_HEATING_CHANGE_A2: f64 = 0.25;

/// Drops the readings of temperature sensors that are stuck: one reading held for at least
/// [`STUCK_MIN_S`] within a segment while the motor's mean I² over [`STUCK_WINDOW_S`]
/// windows changes by [`STUCK_HEATING_CHANGE_A2`] or more.
fn stuck_temperatures(d: &mut Dataset, out: &mut Vec<Finding>) {
    let segments = d.segments();
    for m in 0..d.motors.len() {
        for &(s, e) in &segments {
            let mut k = s;
            while k < e {
                let Some(first) = (k..e).find(|&j| d.temperature[m][j].is_finite()) else {
                    break;
                };
                let v = d.temperature[m][first];
                let mut end = first + 1;
                let mut last = first;
                while end < e && !(d.temperature[m][end].is_finite() && d.temperature[m][end] != v)
                {
                    if d.temperature[m][end].is_finite() {
                        last = end;
                    }
                    end += 1;
                }
                // The span the one reading was seen over (missing readings after it prove
                // nothing).
                let span = d.t[last] - d.t[first];
                if span >= STUCK_MIN_S {
                    let change = heating_change(d, m, first, last + 1);
                    if change >= STUCK_HEATING_CHANGE_A2 {
                        let count = (first..=last)
                            .filter(|&j| d.temperature[m][j].is_finite())
                            .count();
                        for j in first..=last {
                            d.temperature[m][j] = f64::NAN;
                        }
                        out.push(Finding {
                            column: "temperature_c",
                            kind: "stuck",
                            action: Action::Dropped,
                            detail: format!(
                                "motor {} reads {v} °C unchanged for {span:.0} s (t = {:.0}–{:.0} s) \
                                 while its mean I² over {STUCK_WINDOW_S:.0} s changed by \
                                 {change:.2} A²: a stuck sensor; its {count} readings there dropped",
                                d.motors[m],
                                d.t[first],
                                d.t[last]
                            ),
                        });
                    }
                }
                k = end;
            }
        }
    }
}

/// The range of motor `m`'s mean I² over [`STUCK_WINDOW_S`] windows in samples `a..b`.
fn heating_change(d: &Dataset, m: usize, a: usize, b: usize) -> f64 {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    let mut start = a;
    while start < b {
        let end = (start..b)
            .find(|&j| d.t[j] - d.t[start] >= STUCK_WINDOW_S)
            .unwrap_or(b);
        if d.t[end - 1] - d.t[start] >= 0.8 * STUCK_WINDOW_S {
            let i2: Vec<f64> = d.current[m][start..end]
                .iter()
                .filter(|x| x.is_finite())
                .map(|x| x * x)
                .collect();
            if !i2.is_empty() {
                let mean = i2.iter().sum::<f64>() / i2.len() as f64;
                lo = lo.min(mean);
                hi = hi.max(mean);
            }
        }
        start = end;
    }
    if hi >= lo {
        hi - lo
    } else {
        0.0
    }
}

/// Checks and repairs `d` against `limits`; returns what was found (the clock's jumps found
/// when reading first).
pub fn check(d: &mut Dataset, limits: &Limits) -> Vec<Finding> {
    let mut out = d.clock_findings.clone();
    check_current(&mut d.current, limits, &mut out);
    check_voltage(&mut d.voltage, limits, &mut out);
    check_temperature(&mut d.temperature, limits, &mut out);
    check_motion(d, limits, &mut out);
    stuck_temperatures(d, &mut out);
    out
}

impl Mistake {
    /// A raw register's whole counts, `factor` of the unit each.
    const fn counts(kind: &'static str, factor: f64, what: &'static str) -> Mistake {
        Mistake {
            kind,
            factor,
            offset: 0.0,
            integers: true,
            what,
        }
    }

    /// A unit `factor` of the right one.
    const fn plain(kind: &'static str, factor: f64, what: &'static str) -> Mistake {
        Mistake {
            kind,
            factor,
            offset: 0.0,
            integers: false,
            what,
        }
    }
}

/// The current: mA (a multiple of the register's 6.5 mA step when converted from it) or raw
/// counts of 6.5 mA; far beyond the stall current only.
fn check_current(current: &mut [Vec<f64>], limits: &Limits, out: &mut Vec<Finding>) {
    if spread(current).is_some_and(|(p99, _, _)| p99 > BEYOND_RATING * limits.stall_current_a)
        && multiples_of(current, 6.5)
    {
        scale(current, |x| x / 1000.0);
        out.push(Finding {
            column: "current_a",
            kind: "milliamps",
            action: Action::Fixed,
            detail: format!(
                "beyond the stall current ({} A) and every value a multiple of 6.5 (the current \
                 register's step in mA): milliamperes; divided by 1000",
                limits.stall_current_a
            ),
        });
    }
    check_scale(
        current,
        "current_a",
        Physical {
            unit: "A",
            limit: limits.stall_current_a,
            tolerance: BEYOND_RATING,
            plausible: (-limits.stall_current_a, limits.stall_current_a),
        },
        &[
            Mistake::counts("register_counts", 0.0065, "raw register counts of 6.5 mA"),
            Mistake::plain("milliamps", 0.001, "milliamperes"),
        ],
        out,
    );
}

/// The supply voltage: the register's raw 0.1 V counts, or millivolts.
fn check_voltage(voltage: &mut [Vec<f64>], limits: &Limits, out: &mut Vec<Finding>) {
    check_scale(
        voltage,
        "voltage_v",
        Physical {
            unit: "V",
            limit: limits.max_supply_v,
            tolerance: BEYOND_RATING,
            plausible: (3.0, limits.max_supply_v),
        },
        &[
            Mistake::counts(
                "tenths_of_volts",
                0.1,
                "the voltage register's raw 0.1 V counts",
            ),
            Mistake::plain("millivolts", 0.001, "millivolts"),
        ],
        out,
    );
}

/// The temperature: kelvin.
fn check_temperature(temperature: &mut [Vec<f64>], limits: &Limits, out: &mut Vec<Finding>) {
    let kelvin = Mistake {
        kind: "kelvin",
        factor: 1.0,
        offset: -273.15,
        integers: false,
        what: "kelvin",
    };
    check_scale(
        temperature,
        "temperature_c",
        Physical {
            unit: "°C",
            limit: limits.max_temperature_c,
            tolerance: BEYOND_RATING,
            plausible: (-20.0, limits.max_temperature_c),
        },
        &[kelvin],
        out,
    );
}

/// The positions, goals and velocities: raw encoder counts, or degrees.
fn check_motion(d: &mut Dataset, limits: &Limits, out: &mut Vec<Finding>) {
    let turn = 2.0 * std::f64::consts::PI;
    let angle_mistakes = [
        Mistake {
            kind: "register_counts",
            factor: turn / 4096.0,
            offset: -2048.0,
            integers: true,
            what: "raw position counts (4096 a turn, 2048 the middle)",
        },
        Mistake::plain("degrees", turn / 360.0, "degrees"),
    ];
    for (col, name) in [(&mut d.position, "position_rad"), (&mut d.goal, "goal_rad")] {
        check_scale(
            col,
            name,
            Physical {
                unit: "rad",
                limit: turn,
                tolerance: 1.0,
                plausible: (-turn, turn),
            },
            &angle_mistakes,
            out,
        );
    }
    check_scale(
        &mut d.velocity,
        "velocity_rad_s",
        Physical {
            unit: "rad/s",
            limit: limits.max_speed_rad_s,
            tolerance: 1.0,
            plausible: (-limits.max_speed_rad_s, limits.max_speed_rad_s),
        },
        &[
            Mistake::counts(
                "register_counts",
                turn / 4096.0,
                "raw speed counts (steps/s)",
            ),
            Mistake::plain("degrees", turn / 360.0, "degrees per second"),
        ],
        out,
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::catalog::Effect;
    use crate::data::{parse_csv, Dataset, Meta};
    use crate::generate::{generate, Spec};

    /// Generated data (one hidden effect, 2 h at 2 s, 3 motors) with each CSV line passed
    /// through `edit` (header included), read back.
    fn dirty(effect: Effect, edit: impl Fn(usize, &str) -> String) -> Dataset {
        let g = generate(
            &Spec {
                motors: Some(3),
                period_s: 2.0,
                ..Spec::new(effect)
            },
            5,
        );
        let csv: String = g
            .csv
            .lines()
            .enumerate()
            .map(|(n, l)| edit(n, l) + "\n")
            .collect();
        let rows = parse_csv(&csv, "dirty").unwrap();
        let meta: Meta = serde_json::from_str(&g.meta).unwrap();
        Dataset::from_runs(vec![("dirty".into(), rows)], meta, "dirty").unwrap()
    }

    /// Column `c` (0-based) of a data line multiplied by `f` and shifted by `o`, written
    /// with `digits`.
    fn column(line: &str, c: usize, f: f64, o: f64, digits: usize) -> String {
        let mut cells: Vec<String> = line.split(',').map(str::to_string).collect();
        if let Ok(v) = cells[c].parse::<f64>() {
            cells[c] = format!("{:.*}", digits, v * f + o);
        }
        cells.join(",")
    }

    fn kinds(f: &[Finding]) -> Vec<(&str, &str, &str)> {
        f.iter()
            .map(|f| (f.column, f.kind, f.action.as_str()))
            .collect()
    }

    // The generator's columns: t_s, motor, voltage_v, temperature_c, current_a.

    #[test]
    fn a_current_in_milliamps_is_converted_and_said() {
        let clean = dirty(Effect::None, |_, l| l.into());
        let mut d = dirty(Effect::None, |n, l| {
            if n == 0 {
                l.into()
            } else {
                column(l, 4, 1000.0, 0.0, 1)
            }
        });
        let f = check(&mut d, &Limits::default());
        assert_eq!(kinds(&f), [("current_a", "milliamps", "fixed")], "{f:#?}");
        for (a, b) in d
            .current
            .iter()
            .flatten()
            .zip(clean.current.iter().flatten())
        {
            assert!(
                a.is_nan() && b.is_nan() || (a - b).abs() < 1e-9,
                "{a} vs {b}"
            );
        }
    }

    #[test]
    fn raw_counts_are_converted_and_an_ambiguous_column_is_refused() {
        // Voltage in the register's raw 0.1 V counts: whole numbers, ×0.1 (millivolts would
        // be 0.12 V).
        let mut d = dirty(Effect::None, |n, l| {
            if n == 0 {
                l.into()
            } else {
                column(l, 2, 10.0, 0.0, 0)
            }
        });
        let f = check(&mut d, &Limits::default());
        assert_eq!(
            kinds(&f),
            [("voltage_v", "tenths_of_volts", "fixed")],
            "{f:#?}"
        );
        assert!(d
            .voltage
            .iter()
            .flatten()
            .filter(|x| x.is_finite())
            .all(|x| (11.0..13.0).contains(x)));
        // The current register's raw counts, whole numbers: as milliamperes they would fit
        // too (from another sensor than the 6.5 mA register). Neither is sure: refused.
        let mut d = dirty(Effect::None, |n, l| {
            if n == 0 {
                l.into()
            } else {
                column(l, 4, 1.0 / 0.0065, 0.0, 0)
            }
        });
        let f = check(&mut d, &Limits::default());
        assert_eq!(
            kinds(&f),
            [("current_a", "ambiguous_unit", "refused")],
            "{f:#?}"
        );
        assert!(f[0].detail.contains("milliamperes") && f[0].detail.contains("raw register"));
        assert!(
            d.current.iter().flatten().all(|x| x.is_nan()),
            "refused: not used"
        );
    }

    #[test]
    fn nonsense_is_refused_naming_the_column_and_kelvin_is_converted() {
        // Currents a hundred times too large with decimals: no known mistake makes them amperes.
        let mut d = dirty(Effect::None, |n, l| {
            if n == 0 {
                l.into()
            } else {
                column(l, 4, 40000.0, 9.0, 3)
            }
        });
        let f = check(&mut d, &Limits::default());
        assert_eq!(
            kinds(&f),
            [("current_a", "beyond_physics", "refused")],
            "{f:#?}"
        );
        let mut d = dirty(Effect::None, |n, l| {
            if n == 0 {
                l.into()
            } else {
                column(l, 3, 1.0, 273.15, 2)
            }
        });
        let f = check(&mut d, &Limits::default());
        assert_eq!(kinds(&f), [("temperature_c", "kelvin", "fixed")], "{f:#?}");
        let t = d
            .temperature
            .iter()
            .flatten()
            .copied()
            // (the generator's 0 °C and 150 °C read glitches aside: rejected later)
            .filter(|x| x.is_finite() && *x > 1.0 && *x < 100.0);
        assert!(t.clone().count() > 1000 && t.clone().all(|x| (15.0..80.0).contains(&x)));
    }

    #[test]
    fn a_stuck_temperature_sensor_is_found_and_its_readings_dropped() {
        // Motor 2's register holds its reading from t = 2000 s to 4400 s.
        let held = std::cell::Cell::new(None::<String>);
        let mut d = dirty(Effect::None, |n, l| {
            let cells: Vec<&str> = l.split(',').collect();
            if n == 0 || cells[1] != "2" {
                return l.into();
            }
            let t: f64 = cells[0].parse().unwrap();
            if !(2000.0..4400.0).contains(&t) || cells[3].is_empty() {
                return l.into();
            }
            let v = held.take().unwrap_or_else(|| cells[3].to_string());
            held.set(Some(v.clone()));
            let mut c: Vec<String> = cells.iter().map(|s| s.to_string()).collect();
            c[3] = v;
            c.join(",")
        });
        let before = d.temperature[1].iter().filter(|x| x.is_finite()).count();
        let f = check(&mut d, &Limits::default());
        let stuck: Vec<&Finding> = f.iter().filter(|f| f.kind == "stuck").collect();
        assert_eq!(stuck.len(), 1, "{f:#?}");
        assert!(stuck[0].detail.contains("motor 2"), "{}", stuck[0].detail);
        let after = d.temperature[1].iter().filter(|x| x.is_finite()).count();
        assert!(before - after > 1000, "{before} -> {after}");
        // The other motors keep every reading.
        assert!(f.iter().all(|f| f.kind == "stuck"));
    }

    #[test]
    fn a_clock_that_steps_back_is_repaired_where_the_rows_are_still_in_order() {
        // From data row 3000 on, the clock reads 500 s early.
        let d = dirty(Effect::None, |n, l| {
            if n < 3000 {
                l.into()
            } else {
                column(l, 0, 1.0, -500.0, 3)
            }
        });
        let f = &d.clock_findings;
        assert_eq!(kinds(f), [("t_s", "clock_jump", "fixed")], "{f:#?}");
        assert!(f[0].detail.contains("500.0"), "{}", f[0].detail);
        // Time runs on: no sample time twice, none backwards, one grid step of 2 s.
        assert!(d.t.windows(2).all(|w| w[1] > w[0]));
        let clean = dirty(Effect::None, |_, l| l.into());
        assert_eq!(d.t.len(), clean.t.len());
        // Two rows of a motor swapped (a logger's threads racing) are no jump either.
        let g = generate(
            &Spec {
                motors: Some(2),
                period_s: 2.0,
                ..Spec::new(Effect::None)
            },
            5,
        );
        let mut lines: Vec<&str> = g.csv.lines().collect();
        lines.swap(101, 103);
        let rows = parse_csv(&(lines.join("\n") + "\n"), "swapped").unwrap();
        let d = Dataset::from_runs(vec![("s".into(), rows)], Meta::default(), "s").unwrap();
        assert!(d.clock_findings.is_empty(), "{:?}", d.clock_findings);
        // A file sorted by motor is no jump.
        let g = generate(
            &Spec {
                motors: Some(2),
                period_s: 2.0,
                ..Spec::new(Effect::None)
            },
            5,
        );
        let mut lines: Vec<&str> = g.csv.lines().skip(1).collect();
        lines.sort_by_key(|l| l.split(',').nth(1).map(str::to_string));
        let csv = format!(
            "t_s,motor,voltage_v,temperature_c,current_a\n{}\n",
            lines.join("\n")
        );
        let rows = parse_csv(&csv, "by-motor").unwrap();
        let d = Dataset::from_runs(vec![("m".into(), rows)], Meta::default(), "m").unwrap();
        assert!(d.clock_findings.is_empty(), "{:?}", d.clock_findings);
    }

    #[test]
    fn a_current_a_little_beyond_the_rating_is_flagged_and_used() {
        // Twice as much current as the generator's: another motor than an STS3215.
        let clean = dirty(Effect::None, |_, l| l.into());
        let mut d = dirty(Effect::None, |n, l| {
            if n == 0 {
                l.into()
            } else {
                column(l, 4, 2.5, 0.0, 4)
            }
        });
        let f = check(&mut d, &Limits::default());
        assert_eq!(
            kinds(&f),
            [("current_a", "beyond_rating", "flagged")],
            "{f:#?}"
        );
        let (a, b) = (d.current[0][10], clean.current[0][10]);
        assert!((a - 2.5 * b).abs() < 1e-3, "{a} {b}: used as it is");
    }

    #[test]
    fn small_angles_in_degrees_are_converted_not_taken_for_radians() {
        // ±20° swings: a 99th percentile of 20, three times a turn in radians.
        let mut csv = String::from("t_s,motor,goal_rad,position_rad\n");
        for k in 0..500 {
            let t = f64::from(k) * 0.02;
            let deg = 20.0 * (2.0 * t).sin();
            csv.push_str(&format!("{t:.2},1,{deg:.3},{:.3}\n", 0.98 * deg));
        }
        let rows = parse_csv(&csv, "deg").unwrap();
        let mut d = Dataset::from_runs(vec![("deg".into(), rows)], Meta::default(), "d").unwrap();
        let f = check(&mut d, &Limits::default());
        assert_eq!(
            kinds(&f),
            [
                ("position_rad", "degrees", "fixed"),
                ("goal_rad", "degrees", "fixed")
            ],
            "{f:#?}"
        );
        let max = d.position[0].iter().fold(0.0_f64, |m, x| m.max(x.abs()));
        assert!((max - 0.98 * 20f64.to_radians()).abs() < 0.01, "{max}");
    }

    #[test]
    fn clean_data_pass_untouched() {
        for effect in [Effect::None, Effect::CurrentOffset, Effect::SupplySag] {
            let mut d = dirty(effect, |_, l| l.into());
            let f = check(&mut d, &Limits::default());
            assert!(f.is_empty(), "{effect}: {f:#?}");
        }
    }
}
