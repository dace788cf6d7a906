//! The fleet's statistics over a period, the figures the paper promises from shipped units:
//! protection events by kind and per robot-day, time above each warning temperature, the
//! hottest motors and how close they came to the trip, stalls per joint, and the robots whose
//! figures drift. Pure: the aggregates the database returns (`nori fleet report` runs the
//! queries) in, a [`Report`] out, rendered as text, JSON or a page of plots.

use serde::Serialize;
use std::collections::BTreeMap;
use std::fmt::Write;

/// One robot's figures for one joint over the period (one row of the telemetry aggregate).
#[derive(Debug, Clone, PartialEq)]
pub struct JointFigures {
    /// The robot.
    pub robot: String,
    /// The joint.
    pub joint: String,
    /// Hottest reading, °C (NaN: never read).
    pub temp_max_c: f32,
    /// Seconds at or above each warning level.
    pub above_warn_s: Vec<f64>,
    /// Mean temperature over the period's first half and second half, °C (NaN: no reading).
    pub mean_first_c: f64,
    /// See `mean_first_c`.
    pub mean_second_c: f64,
}

/// The aggregates a report is made of.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Aggregates {
    /// Per robot, the days its telemetry covers in the period.
    pub robot_days: BTreeMap<String, f64>,
    /// Per robot, event counts by kind.
    pub events: BTreeMap<String, BTreeMap<String, u64>>,
    /// Per robot, event counts in the period's first and second half (for the drift).
    pub events_by_half: BTreeMap<String, [u64; 2]>,
    /// Stalls per joint name, fleet-wide.
    pub stalls: BTreeMap<String, u64>,
    /// Per robot and joint.
    pub joints: Vec<JointFigures>,
    /// The black boxes the store has from the period, each under its event, oldest first.
    pub boxes: Vec<BoxLine>,
    /// The trips of the period the store has no box of (the robot keeps it, or had none).
    pub trips_without_box: Vec<TripLine>,
}

/// A black box the store has, under the event that froze it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BoxLine {
    /// The robot.
    pub robot: String,
    /// When: its event's time (UTC), else when the store first heard of it.
    pub at: String,
    /// Its event: the journal's kind (`ThermalTrip`), else the box's own trigger
    /// (`lift_obstruction`, `saved`), empty while it is not whole.
    pub event: String,
    /// The joint it is about (empty: none named).
    pub joint: String,
    /// Its file name on the robot's shelf.
    pub name: String,
    /// Its SHA-256, hex: its name at the dashboard (`/boxes/<robot>/<digest>`).
    pub digest: String,
    /// Its size and the bytes held, bytes.
    pub size: u64,
    /// See `size`.
    pub received: u64,
    /// Held whole and checked.
    pub complete: bool,
    /// What led to its event, read from it.
    pub lead_up: Option<blackbox::lead_up::LeadUp>,
}

/// A trip of the period, from the journal.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TripLine {
    /// The robot.
    pub robot: String,
    /// When (UTC).
    pub at: String,
    /// The journal's kind.
    pub kind: String,
    /// The joint (empty: none).
    pub joint: String,
}

/// What led to one robot's joint's trips, from their boxes.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TripCauses {
    /// The robot.
    pub robot: String,
    /// The joint.
    pub joint: String,
    /// Trips with a box.
    pub trips: u64,
    /// The mean rise of the joint's temperature over each box before its trip, °C.
    pub mean_rise_c: f64,
    /// The hottest reading before any of them, °C.
    pub temp_max_c: f32,
    /// The highest current before any of them, A.
    pub current_peak_a: f32,
    /// The protections that acted before them, by kind, summed.
    pub events_before: BTreeMap<String, u64>,
}

/// What the report is judged against.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Limits {
    /// The software trip, °C.
    pub trip_c: f32,
    /// The warning levels, °C.
    pub warn_c: Vec<f32>,
    /// A joint whose mean temperature rose this much from the first half to the second drifts.
    pub drift_c: f64,
    /// A robot whose events per day rose this many times from the first half to the second
    /// (with at least 5 in the second) drifts.
    pub drift_events: f64,
}

/// The event kinds that are protections acting (the rest are the stack's own life: starts,
/// restores, refused commands).
pub const PROTECTIONS: [&str; 7] = [
    "ThermalWarning",
    "ThermalTrip",
    "DriverTrip",
    "FirmwareProtection",
    "OutputLost",
    "Stall",
    "TorqueReduced",
];

/// One robot's line.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RobotLine {
    /// The robot.
    pub robot: String,
    /// Days of telemetry.
    pub robot_days: f64,
    /// Protection events by kind.
    pub protections: BTreeMap<String, u64>,
    /// Protection events per robot-day.
    pub per_day: f64,
}

/// A motor near its limit.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HotMotor {
    /// The robot.
    pub robot: String,
    /// The joint.
    pub joint: String,
    /// Its hottest reading, °C.
    pub temp_max_c: f32,
    /// The trip minus that, °C (negative: it reached the trip).
    pub margin_c: f32,
    /// Seconds at or above each warning level.
    pub above_warn_s: Vec<f64>,
}

/// A figure that moved.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Drift {
    /// The robot.
    pub robot: String,
    /// What drifted (`left_elbow mean temperature`, `events per day`).
    pub what: String,
    /// Over the first half.
    pub before: f64,
    /// Over the second half.
    pub after: f64,
}

/// The fleet's statistics over a period.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    /// Robots seen (telemetry or events).
    pub robots: usize,
    /// Robot-days of telemetry.
    pub robot_days: f64,
    /// Protection events by kind, fleet-wide, and per robot-day.
    pub by_kind: BTreeMap<String, (u64, f64)>,
    /// Per robot, the most protection events per day first.
    pub per_robot: Vec<RobotLine>,
    /// Motors by hottest reading, hottest first.
    pub hottest: Vec<HotMotor>,
    /// Seconds above each warning level, fleet-wide.
    pub above_warn_s: Vec<f64>,
    /// Stalls per joint, most first.
    pub stalls: Vec<(String, u64)>,
    /// Drifting figures.
    pub drifts: Vec<Drift>,
    /// The black boxes, each under its event.
    pub boxes: Vec<BoxLine>,
    /// The trips without a whole box in the store (none kept, or one still arriving).
    pub trips_without_box: Vec<TripLine>,
    /// What led to the trips, per robot and joint, from their boxes: the most trips first.
    pub trip_causes: Vec<TripCauses>,
    /// The limits judged against.
    pub limits: Limits,
}

fn per_day(n: u64, days: f64) -> f64 {
    if days > 0.0 {
        n as f64 / days
    } else {
        0.0
    }
}

impl Report {
    /// The report of `a` judged against `limits`; `hottest` motors listed at most.
    pub fn new(a: &Aggregates, limits: Limits, hottest: usize) -> Report {
        let total_days: f64 = a.robot_days.values().sum();
        let mut by_kind: BTreeMap<String, (u64, f64)> = BTreeMap::new();
        let mut robots: Vec<&String> = a.robot_days.keys().chain(a.events.keys()).collect();
        robots.sort();
        robots.dedup();
        let mut per_robot = Vec::new();
        for robot in &robots {
            let days = a.robot_days.get(*robot).copied().unwrap_or(0.0);
            let protections: BTreeMap<String, u64> = a
                .events
                .get(*robot)
                .map(|kinds| {
                    kinds
                        .iter()
                        .filter(|(k, _)| PROTECTIONS.contains(&k.as_str()))
                        .map(|(k, n)| (k.clone(), *n))
                        .collect()
                })
                .unwrap_or_default();
            for (k, n) in &protections {
                by_kind.entry(k.clone()).or_default().0 += n;
            }
            let n: u64 = protections.values().sum();
            per_robot.push(RobotLine {
                robot: (*robot).clone(),
                robot_days: days,
                protections,
                per_day: per_day(n, days),
            });
        }
        for v in by_kind.values_mut() {
            v.1 = per_day(v.0, total_days);
        }
        per_robot.sort_by(|x, y| y.per_day.total_cmp(&x.per_day).then(x.robot.cmp(&y.robot)));
        let levels = limits.warn_c.len();
        let mut above_warn_s = vec![0.0; levels];
        for j in &a.joints {
            for (total, s) in above_warn_s.iter_mut().zip(&j.above_warn_s) {
                *total += s;
            }
        }
        let mut hot: Vec<HotMotor> = a
            .joints
            .iter()
            .filter(|j| j.temp_max_c.is_finite())
            .map(|j| HotMotor {
                robot: j.robot.clone(),
                joint: j.joint.clone(),
                temp_max_c: j.temp_max_c,
                margin_c: limits.trip_c - j.temp_max_c,
                above_warn_s: j.above_warn_s.clone(),
            })
            .collect();
        hot.sort_by(|x, y| y.temp_max_c.total_cmp(&x.temp_max_c));
        hot.truncate(hottest);
        let mut stalls: Vec<(String, u64)> =
            a.stalls.iter().map(|(j, n)| (j.clone(), *n)).collect();
        stalls.sort_by(|x, y| y.1.cmp(&x.1).then(x.0.cmp(&y.0)));
        Report {
            robots: robots.len(),
            robot_days: total_days,
            by_kind,
            per_robot,
            hottest: hot,
            above_warn_s,
            stalls,
            drifts: drifts(a, &limits),
            boxes: a.boxes.clone(),
            trips_without_box: a.trips_without_box.clone(),
            trip_causes: trip_causes(&a.boxes),
            limits,
        }
    }

    /// The report as text tables.
    pub fn text(&self) -> String {
        let mut t = String::new();
        let _ = writeln!(
            t,
            "{} robots, {:.2} robot-days of telemetry",
            self.robots, self.robot_days
        );
        let _ = writeln!(t, "\nprotection events          count   per robot-day");
        for (kind, (n, rate)) in &self.by_kind {
            let _ = writeln!(t, "  {kind:<22} {n:>7}   {rate:>13.3}");
        }
        if self.by_kind.is_empty() {
            let _ = writeln!(t, "  none");
        }
        let _ = writeln!(t, "\nrobots, most protection events per day first");
        for r in &self.per_robot {
            let kinds: Vec<String> = r
                .protections
                .iter()
                .map(|(k, n)| format!("{k} {n}"))
                .collect();
            let _ = writeln!(
                t,
                "  {:<20} {:>7.2} days  {:>8.2}/day  {}",
                r.robot,
                r.robot_days,
                r.per_day,
                kinds.join(", ")
            );
        }
        let warn: Vec<String> = self
            .limits
            .warn_c
            .iter()
            .zip(&self.above_warn_s)
            .map(|(c, s)| format!("≥{c} °C {:.0} s", s))
            .collect();
        let _ = writeln!(
            t,
            "\ntime above the warning levels, fleet-wide: {}",
            warn.join(", ")
        );
        let _ = writeln!(
            t,
            "\nhottest motors (trip at {} °C)       max °C   margin   s above each warning",
            self.limits.trip_c
        );
        for m in &self.hottest {
            let above: Vec<String> = m.above_warn_s.iter().map(|s| format!("{s:.0}")).collect();
            let _ = writeln!(
                t,
                "  {:<16} {:<20} {:>6.1}   {:>6.1}   {}",
                m.robot,
                m.joint,
                m.temp_max_c,
                m.margin_c,
                above.join(" / ")
            );
        }
        let _ = writeln!(t, "\nstalls per joint");
        for (joint, n) in &self.stalls {
            let _ = writeln!(t, "  {joint:<24} {n:>6}");
        }
        if self.stalls.is_empty() {
            let _ = writeln!(t, "  none");
        }
        let _ = writeln!(t, "\ndrifting (first half → second half of the period)");
        for d in &self.drifts {
            let _ = writeln!(
                t,
                "  {:<20} {:<36} {:>8.2} → {:>8.2}",
                d.robot, d.what, d.before, d.after
            );
        }
        if self.drifts.is_empty() {
            let _ = writeln!(t, "  none");
        }
        self.boxes_text(&mut t);
        t
    }

    /// The black boxes under their events, the trips without one, and what led to the trips.
    fn boxes_text(&self, t: &mut String) {
        let _ = writeln!(
            t,
            "
black boxes, each under its event"
        );
        for b in &self.boxes {
            let state = if b.complete {
                format!("{} kB", b.size / 1000)
            } else {
                format!("{}% received", b.received * 100 / b.size.max(1))
            };
            let _ = writeln!(
                t,
                "  {}  {:<16} {:<20} {:<16}\n      {} ({state}, {})",
                b.at,
                b.robot,
                b.event,
                b.joint,
                b.name,
                &b.digest[..b.digest.len().min(12)]
            );
        }
        if self.boxes.is_empty() {
            let _ = writeln!(t, "  none");
        }
        for trip in &self.trips_without_box {
            let _ = writeln!(
                t,
                "  {}  {:<16} {:<20} {:<16}\n      no whole box in the store (yet)",
                trip.at, trip.robot, trip.kind, trip.joint
            );
        }
        let _ = writeln!(
            t,
            "\nwhat led to the trips, from their boxes   trips  rise °C  max °C  peak A  before"
        );
        for c in &self.trip_causes {
            let before: Vec<String> = c
                .events_before
                .iter()
                .map(|(k, n)| format!("{k} {n}"))
                .collect();
            let _ = writeln!(
                t,
                "  {:<16} {:<22} {:>6} {:>8.1} {:>7.1} {:>7.2}  {}",
                c.robot,
                c.joint,
                c.trips,
                c.mean_rise_c,
                c.temp_max_c,
                c.current_peak_a,
                before.join(", ")
            );
        }
        if self.trip_causes.is_empty() {
            let _ = writeln!(t, "  none");
        }
    }

    /// The report as a self-contained HTML page with bar charts (SVG, no script).
    pub fn html(&self, title: &str) -> String {
        let mut h = String::new();
        let _ = write!(
            h,
            "<!doctype html><meta charset=utf-8><title>{t}</title>\
             <style>body{{font:14px sans-serif;margin:2em}}svg text{{font:12px sans-serif}}</style>\
             <h1>{t}</h1><p>{} robots, {:.2} robot-days of telemetry.</p>",
            self.robots,
            self.robot_days,
            t = escape(title)
        );
        let rates: Vec<(String, f64)> = self
            .per_robot
            .iter()
            .map(|r| (r.robot.clone(), r.per_day))
            .collect();
        h += "<h2>Protection events per robot-day</h2>";
        h += &bars(&rates, None, "/day");
        let temps: Vec<(String, f64)> = self
            .hottest
            .iter()
            .map(|m| (format!("{} {}", m.robot, m.joint), f64::from(m.temp_max_c)))
            .collect();
        let _ = write!(
            h,
            "<h2>Hottest motors (the line: the trip at {} °C)</h2>",
            self.limits.trip_c
        );
        h += &bars(&temps, Some(f64::from(self.limits.trip_c)), " °C");
        let stalls: Vec<(String, f64)> = self
            .stalls
            .iter()
            .map(|(j, n)| (j.clone(), *n as f64))
            .collect();
        h += "<h2>Stalls per joint</h2>";
        h += &bars(&stalls, None, "");
        h += &self.boxes_html();
        h += "<h2>The figures</h2><pre>";
        h += &escape(&self.text());
        h += "</pre>";
        h
    }
}

impl Report {
    /// The black boxes as a table, each a link to download it from the dashboard.
    fn boxes_html(&self) -> String {
        let mut h = String::from("<h2>Black boxes</h2>");
        if self.boxes.is_empty() {
            return h + "<p>none</p>";
        }
        h += "<table><tr><th>when (UTC)<th>robot<th>event<th>joint<th>box<th>held</tr>";
        for b in &self.boxes {
            let name = escape(&b.name);
            let link = if b.complete {
                format!(
                    "<a href=\"/boxes/{}/{}.mcap\">{name}</a>",
                    escape(&b.robot),
                    b.digest
                )
            } else {
                name
            };
            let _ = write!(
                h,
                "<tr><td>{}<td>{}<td>{}<td>{}<td>{link}<td>{}/{} kB</tr>",
                escape(&b.at),
                escape(&b.robot),
                escape(&b.event),
                escape(&b.joint),
                b.received / 1000,
                b.size / 1000
            );
        }
        h + "</table>"
    }
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// A horizontal bar chart of `rows`, with a vertical line at `mark` when given.
fn bars(rows: &[(String, f64)], mark: Option<f64>, unit: &str) -> String {
    if rows.is_empty() {
        return "<p>none</p>".into();
    }
    let top = rows
        .iter()
        .map(|r| r.1)
        .chain(mark)
        .fold(0.0_f64, f64::max)
        .max(1e-9);
    let (label_w, bar_w, row_h) = (260.0, 420.0, 20.0);
    let height = row_h * rows.len() as f64 + 10.0;
    let mut s = format!(
        "<svg width=\"{}\" height=\"{height}\" role=\"img\">",
        label_w + bar_w + 90.0
    );
    // The mark first: the bars' figures are written over it.
    if let Some(m) = mark {
        let x = label_w + m / top * bar_w;
        let _ = write!(
            s,
            "<line x1=\"{x:.1}\" x2=\"{x:.1}\" y1=\"0\" y2=\"{height}\" stroke=\"#c0392b\" stroke-width=\"2\"/>"
        );
    }
    for (i, (label, v)) in rows.iter().enumerate() {
        let y = i as f64 * row_h + 5.0;
        let w = (v / top * bar_w).max(0.0);
        let _ = write!(
            s,
            "<text x=\"{x}\" y=\"{ty}\" text-anchor=\"end\">{l}</text>\
             <rect x=\"{label_w}\" y=\"{y}\" width=\"{w:.1}\" height=\"{bh}\" fill=\"#4a7fb5\"/>\
             <text x=\"{vx:.1}\" y=\"{ty}\">{v:.2}{unit}</text>",
            x = label_w - 6.0,
            ty = y + 13.0,
            l = escape(label),
            bh = row_h - 4.0,
            vx = label_w + w + 4.0,
        );
    }
    s + "</svg>"
}

/// What led to the trips, per robot and joint, from the boxes whose trigger is a trip.
fn trip_causes(boxes: &[BoxLine]) -> Vec<TripCauses> {
    // Each robot's joint: its figures, and the sum and count of its rises.
    let mut by: BTreeMap<(String, String), (TripCauses, (f64, u32))> = BTreeMap::new();
    for b in boxes {
        let Some(l) = &b.lead_up else {
            continue;
        };
        let tripped = (l.trigger.as_ref())
            .is_some_and(|t| blackbox::lead_up::TRIPS.contains(&t.kind.as_str()));
        if !tripped {
            continue;
        }
        let joint = l.joint.clone().unwrap_or_default();
        let (c, rises) = by
            .entry((b.robot.clone(), joint.clone()))
            .or_insert_with(|| {
                (
                    TripCauses {
                        robot: b.robot.clone(),
                        joint,
                        trips: 0,
                        mean_rise_c: 0.0,
                        temp_max_c: f32::NAN,
                        current_peak_a: 0.0,
                        events_before: BTreeMap::new(),
                    },
                    (0.0, 0),
                )
            });
        c.trips += 1;
        if let Some([first, max, last]) = l.temperature_c {
            rises.0 += f64::from(last - first);
            rises.1 += 1;
            // NaN until the first reading: `max` takes the other.
            c.temp_max_c = c.temp_max_c.max(max);
        }
        if let Some([_, peak]) = l.current_a {
            c.current_peak_a = c.current_peak_a.max(peak);
        }
        for (k, n) in &l.events_before {
            *c.events_before.entry(k.clone()).or_insert(0) += n;
        }
    }
    let mut out: Vec<TripCauses> = by
        .into_values()
        .map(|(mut c, (sum, n))| {
            c.mean_rise_c = if n > 0 { sum / f64::from(n) } else { f64::NAN };
            c
        })
        .collect();
    out.sort_by(|x, y| y.trips.cmp(&x.trips).then(x.robot.cmp(&y.robot)));
    out
}

/// Joints whose mean temperature rose by `drift_c` or more, and robots whose protection events
/// per half rose `drift_events` times (with at least 5 in the second half).
fn drifts(a: &Aggregates, limits: &Limits) -> Vec<Drift> {
    let mut out = Vec::new();
    for j in &a.joints {
        let rise = j.mean_second_c - j.mean_first_c;
        if rise.is_finite() && rise >= limits.drift_c {
            out.push(Drift {
                robot: j.robot.clone(),
                what: format!("{} mean temperature, °C", j.joint),
                before: j.mean_first_c,
                after: j.mean_second_c,
            });
        }
    }
    for (robot, [first, second]) in &a.events_by_half {
        let grew = *second >= 5 && (*second as f64) >= limits.drift_events * (*first).max(1) as f64;
        if grew {
            out.push(Drift {
                robot: robot.clone(),
                what: "protection events".into(),
                before: *first as f64,
                after: *second as f64,
            });
        }
    }
    out.sort_by(|x, y| x.robot.cmp(&y.robot).then(x.what.cmp(&y.what)));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits() -> Limits {
        Limits {
            trip_c: 59.0,
            warn_c: vec![50.0, 54.0, 57.0],
            drift_c: 3.0,
            drift_events: 3.0,
        }
    }

    fn joint(robot: &str, name: &str, max: f32, above: [f64; 3], means: [f64; 2]) -> JointFigures {
        JointFigures {
            robot: robot.into(),
            joint: name.into(),
            temp_max_c: max,
            above_warn_s: above.to_vec(),
            mean_first_c: means[0],
            mean_second_c: means[1],
        }
    }

    fn aggregates() -> Aggregates {
        let mut a = Aggregates::default();
        a.robot_days.insert("a".into(), 2.0);
        a.robot_days.insert("b".into(), 0.5);
        a.events.insert(
            "a".into(),
            BTreeMap::from([
                ("ThermalWarning".into(), 6),
                ("Stall".into(), 2),
                ("AgentStarted".into(), 9),
            ]),
        );
        a.events
            .insert("b".into(), BTreeMap::from([("ThermalTrip".into(), 1)]));
        a.events
            .insert("c".into(), BTreeMap::from([("Stall".into(), 1)]));
        a.events_by_half.insert("a".into(), [1, 7]);
        a.events_by_half.insert("b".into(), [0, 1]);
        a.stalls.insert("left_elbow".into(), 2);
        a.stalls.insert("right_wrist".into(), 1);
        a.joints = vec![
            joint("a", "left_elbow", 55.5, [300.0, 20.0, 0.0], [40.0, 44.5]),
            joint(
                "b",
                "left_shoulder",
                59.2,
                [100.0, 60.0, 12.0],
                [45.0, 46.0],
            ),
            joint("b", "neck", f32::NAN, [0.0; 3], [f64::NAN, f64::NAN]),
        ];
        a
    }

    #[test]
    fn rates_are_per_robot_day_and_only_protections_count() {
        let r = Report::new(&aggregates(), limits(), 10);
        assert_eq!(
            r.robots, 3,
            "a robot with events but no telemetry is still a robot"
        );
        assert_eq!(r.robot_days, 2.5);
        assert_eq!(r.by_kind["ThermalWarning"], (6, 6.0 / 2.5));
        assert_eq!(r.by_kind["Stall"].0, 3);
        assert!(!r.by_kind.contains_key("AgentStarted"));
        let order: Vec<&str> = r.per_robot.iter().map(|l| l.robot.as_str()).collect();
        assert_eq!(
            order,
            ["a", "b", "c"],
            "a: 8 in 2 days = 4/day; b: 1 in 0.5 = 2/day"
        );
        assert_eq!(r.per_robot[0].per_day, 4.0);
        assert_eq!(r.per_robot[2].per_day, 0.0, "no telemetry: no rate");
    }

    #[test]
    fn the_hottest_come_first_with_their_margin_to_the_trip_and_drift_is_flagged() {
        let r = Report::new(&aggregates(), limits(), 1);
        assert_eq!(r.hottest.len(), 1);
        let h = &r.hottest[0];
        assert_eq!((h.robot.as_str(), h.joint.as_str()), ("b", "left_shoulder"));
        assert!(
            (h.margin_c + 0.2).abs() < 1e-5,
            "it passed the trip by 0.2 °C"
        );
        assert_eq!(r.above_warn_s, [400.0, 80.0, 12.0]);
        assert_eq!(r.stalls[0], ("left_elbow".into(), 2));
        let drifts: Vec<(&str, &str)> = r
            .drifts
            .iter()
            .map(|d| (d.robot.as_str(), d.what.as_str()))
            .collect();
        assert_eq!(
            drifts,
            [
                ("a", "left_elbow mean temperature, °C"),
                ("a", "protection events")
            ],
            "b's shoulder rose 1 °C, b's events are too few"
        );
        let text = r.text();
        assert!(
            text.contains("left_shoulder") && text.contains("-0.2"),
            "{text}"
        );
        let page = r.html("fleet <test>");
        assert!(page.contains("<p>none</p>"), "no boxes");
        assert!(page.contains("<svg") && page.contains("fleet &lt;test&gt;"));
    }

    fn a_box(robot: &str, trigger: &str, joint: &str, temps: [f32; 3], peak: f32) -> BoxLine {
        let lead_up = blackbox::lead_up::LeadUp {
            trigger: Some(blackbox::channel::EventMessage {
                timestamp_ns: 1,
                kind: trigger.into(),
                joint: Some(joint.into()),
                bus: None,
                level: 0,
                value: 0.0,
            }),
            triggers: Vec::new(),
            joint: Some(joint.into()),
            seconds_before: 120.0,
            temperature_c: Some(temps),
            current_a: Some([0.8, peak]),
            events_before: BTreeMap::from([("stall_retry".into(), 2)]),
            cut_short: false,
        };
        BoxLine {
            robot: robot.into(),
            at: "2026-11-30 02:00:00".into(),
            event: "ThermalTrip".into(),
            joint: joint.into(),
            name: "000001-T-thermal_trip.mcap".into(),
            digest: "ab".repeat(32),
            size: 2_000_000,
            received: 2_000_000,
            complete: true,
            lead_up: Some(lead_up),
        }
    }

    #[test]
    fn boxes_are_listed_under_their_events_and_the_trips_told_by_what_led_to_them() {
        let mut a = aggregates();
        let mut uploading = a_box("b", "saved", "neck", [30.0; 3], 0.1);
        (uploading.received, uploading.complete, uploading.lead_up) = (500_000, false, None);
        a.boxes = vec![
            a_box("a", "thermal_trip", "left_elbow", [50.0, 59.5, 59.0], 1.5),
            a_box("a", "thermal_trip", "left_elbow", [54.0, 59.2, 59.0], 2.5),
            a_box("a", "saved", "left_elbow", [40.0, 41.0, 41.0], 9.0),
            uploading,
        ];
        a.trips_without_box = vec![TripLine {
            robot: "b".into(),
            at: "2026-11-30 03:00:00".into(),
            kind: "DriverTrip".into(),
            joint: String::new(),
        }];
        let r = Report::new(&a, limits(), 10);
        assert_eq!(r.trip_causes.len(), 1, "a saved box is no trip");
        let c = &r.trip_causes[0];
        assert_eq!(
            (c.robot.as_str(), c.joint.as_str(), c.trips),
            ("a", "left_elbow", 2)
        );
        assert_eq!(c.mean_rise_c, 7.0, "9 and 5 °C");
        assert_eq!((c.temp_max_c, c.current_peak_a), (59.5, 2.5));
        assert_eq!(c.events_before["stall_retry"], 4);
        let text = r.text();
        for line in [
            "25% received",
            "2000 kB",
            "no whole box in the store (yet)",
            "stall_retry 4",
        ] {
            assert!(text.contains(line), "{line}: {text}");
        }
        let page = r.html("fleet");
        let link = format!("<a href=\"/boxes/a/{}.mcap\">", "ab".repeat(32));
        assert_eq!(
            page.matches(&link).count(),
            3,
            "the whole boxes link to their download"
        );
    }
}
