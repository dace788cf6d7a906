//! `nori fleet report`: the fleet's statistics over a period, from the history `nori fleet
//! store` keeps in PostgreSQL. The database aggregates (per robot, kind, joint and half of the
//! period); `fleet::report` ranks, judges and renders.

use anyhow::{anyhow, Context, Result};
use clap::Args;
use fleet::report::{Aggregates, BoxLine, JointFigures, Limits, Report, TripLine, PROTECTIONS};
use std::path::PathBuf;

/// Options of `nori fleet report`.
#[derive(Args, Debug)]
pub struct ReportArgs {
    /// The database (as `nori fleet store --database`).
    #[arg(long)]
    pub database: String,
    /// The period: this many days up to `--to`.
    #[arg(long, default_value_t = 7.0)]
    pub days: f64,
    /// The period's start instead (a PostgreSQL timestamp: `2026-11-20`, `2026-11-20 08:00Z`).
    #[arg(long)]
    pub from: Option<String>,
    /// The period's end (default: now).
    #[arg(long)]
    pub to: Option<String>,
    /// Only this robot.
    #[arg(long)]
    pub robot: Option<String>,
    /// The software trip the margins are measured to, °C (the supervisor's `thermal.trip-c`).
    #[arg(long, default_value_t = 59.0)]
    pub trip_c: f32,
    /// The warning levels the store kept time above, °C (the store's `--warn-c`).
    #[arg(long, value_delimiter = ',', default_value = "50,54,57")]
    pub warn_c: Vec<f32>,
    /// A joint whose mean temperature rose this much from the period's first half to its second
    /// is listed as drifting, °C.
    #[arg(long, default_value_t = 3.0)]
    pub drift_c: f64,
    /// A robot whose protection events rose this many times from the first half to the second
    /// (at least 5 in the second) is listed as drifting.
    #[arg(long, default_value_t = 3.0)]
    pub drift_events: f64,
    /// Motors listed by hottest reading.
    #[arg(long, default_value_t = 10)]
    pub hottest: usize,
    /// The report as JSON on stdout instead of text.
    #[arg(long)]
    pub json: bool,
    /// Also write the report as an HTML page with its plots.
    #[arg(long)]
    pub html: Option<PathBuf>,
}

/// Runs the report.
pub fn run(args: &ReportArgs) -> Result<()> {
    let (report, title) = make(args)?;
    if let Some(path) = &args.html {
        std::fs::write(path, report.html(&title))
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{title}\n\n{}", report.text());
    }
    Ok(())
}

/// The report page of the last `days` days with the default limits (the dashboard's
/// `/report`).
pub fn html(database: &str, days: f64) -> Result<String> {
    use clap::Parser;
    #[derive(Parser)]
    struct Defaults {
        #[command(flatten)]
        report: ReportArgs,
    }
    let mut args = Defaults::try_parse_from(["report", "--database", database])?.report;
    args.days = days;
    let (report, title) = make(&args)?;
    Ok(report.html(&title))
}

/// Robot `robot`'s whole box of SHA-256 `digest_hex` from the store: its name and bytes
/// (`None`: no such box, or not whole yet).
pub fn box_bytes(
    database: &str,
    robot: &str,
    digest_hex: &str,
) -> Result<Option<(String, Vec<u8>)>> {
    let mut db = postgres::Client::connect(database, postgres::NoTls)
        .context("connecting to the fleet's database")?;
    let mut tx = db.transaction()?;
    let Some(row) = tx.query_opt(
        "SELECT name FROM boxes WHERE robot = $1 AND digest = decode($2, 'hex') AND complete",
        &[&robot, &digest_hex],
    )?
    else {
        return Ok(None);
    };
    let mut bytes = Vec::new();
    for r in tx.query(
        "SELECT data FROM box_chunks WHERE robot = $1 AND digest = decode($2, 'hex') ORDER BY at_byte",
        &[&robot, &digest_hex],
    )? {
        bytes.extend_from_slice(r.get::<_, &[u8]>(0));
    }
    Ok(Some((row.get(0), bytes)))
}

/// The report `args` ask for, and its title.
fn make(args: &ReportArgs) -> Result<(Report, String)> {
    if !(args.days > 0.0 && args.days <= 3660.0) {
        return Err(anyhow!("--days {}: use more than 0, up to 3660", args.days));
    }
    let mut db = postgres::Client::connect(&args.database, postgres::NoTls)
        .context("connecting to the fleet's database")?;
    let period = db
        .query_one(
            "SELECT extract(epoch FROM coalesce($2::text::timestamptz, now()) - make_interval(secs => $3))::float8, \
                    extract(epoch FROM coalesce($2::text::timestamptz, now()))::float8, \
                    extract(epoch FROM $1::text::timestamptz)::float8",
            &[&args.from, &args.to, &(args.days * 86_400.0)],
        )
        .context("reading the period (--from, --to: PostgreSQL timestamps)")?;
    let to: f64 = period.get(1);
    let from: f64 = period.get::<_, Option<f64>>(2).unwrap_or(period.get(0));
    if from >= to {
        return Err(anyhow!("the period is empty: --from is not before --to"));
    }
    let a = aggregates(&mut db, from, to, args.robot.as_deref())
        .context("querying the fleet's history (is this a `nori fleet store` database?)")?;
    let report = Report::new(
        &a,
        Limits {
            trip_c: args.trip_c,
            warn_c: args.warn_c.clone(),
            drift_c: args.drift_c,
            drift_events: args.drift_events,
        },
        args.hottest,
    );
    let title = format!(
        "Nori fleet, {} to {}",
        fmt_time(&mut db, from)?,
        fmt_time(&mut db, to)?
    );
    Ok((report, title))
}

fn fmt_time(db: &mut postgres::Client, t: f64) -> Result<String> {
    let row = db.query_one(
        "SELECT to_char(to_timestamp($1) AT TIME ZONE 'UTC', 'YYYY-MM-DD HH24:MI') || ' UTC'",
        &[&t],
    )?;
    Ok(row.get(0))
}

/// The period (`$1`, `$2`: Unix seconds) and the robot (`$3`, NULL for all).
const WITHIN: &str =
    "at >= to_timestamp($1) AND at < to_timestamp($2) AND ($3::text IS NULL OR robot = $3)";
/// [`WITHIN`] of the telemetry table as `t`.
const WITHIN_T: &str =
    "t.at >= to_timestamp($1) AND t.at < to_timestamp($2) AND ($3::text IS NULL OR t.robot = $3)";

/// The period's aggregates, `from` to `to` (Unix seconds), of `robot` or every robot.
fn aggregates(
    db: &mut postgres::Client,
    from: f64,
    to: f64,
    robot: Option<&str>,
) -> Result<Aggregates, postgres::Error> {
    let mid = (from + to) / 2.0;
    let within = WITHIN;
    let p: [&(dyn postgres::types::ToSql + Sync); 3] = [&from, &to, &robot];
    let mut a = Aggregates::default();
    for r in db.query(
        &format!("SELECT robot, sum(period_s)::float8 / 86400 FROM telemetry WHERE {within} GROUP BY robot"),
        &p,
    )? {
        a.robot_days.insert(r.get(0), r.get(1));
    }
    for r in db.query(
        &format!("SELECT robot, kind, count(*) FROM events WHERE {within} GROUP BY robot, kind"),
        &p,
    )? {
        let n: i64 = r.get(2);
        a.events
            .entry(r.get(0))
            .or_default()
            .insert(r.get(1), n as u64);
    }
    let kinds: Vec<String> = PROTECTIONS.iter().map(|k| k.to_string()).collect();
    for r in db.query(
        &format!(
            "SELECT robot, count(*) FILTER (WHERE at < to_timestamp($4)), count(*) FILTER (WHERE at >= to_timestamp($4)) \
             FROM events WHERE {within} AND kind = ANY($5) GROUP BY robot"
        ),
        &[&from, &to, &robot, &mid, &kinds],
    )? {
        let (first, second): (i64, i64) = (r.get(1), r.get(2));
        a.events_by_half
            .insert(r.get(0), [first as u64, second as u64]);
    }
    for r in db.query(
        &format!(
            "SELECT joint, count(*) FROM events WHERE {within} AND kind = 'Stall' GROUP BY joint"
        ),
        &p,
    )? {
        let n: i64 = r.get(1);
        a.stalls.insert(r.get(0), n as u64);
    }
    let mut above: std::collections::HashMap<(String, String), Vec<f64>> = Default::default();
    for r in db.query(
        &format!(
            "SELECT t.robot, t.joints[(a.k - 1) / l.n + 1], ((a.k - 1) % l.n)::int, sum(a.s)::float8 \
             FROM telemetry t, \
                  LATERAL (SELECT greatest(array_length(t.above_warn_s, 1) / array_length(t.joints, 1), 1) AS n) l, \
                  unnest(t.above_warn_s) WITH ORDINALITY AS a(s, k) \
             WHERE {WITHIN_T} GROUP BY 1, 2, 3"
        ),
        &p,
    )? {
        let (level, s): (i32, f64) = (r.get(2), r.get(3));
        let v = above.entry((r.get(0), r.get(1))).or_default();
        let level = level.max(0) as usize;
        if v.len() <= level {
            v.resize(level + 1, 0.0);
        }
        v[level] = s;
    }
    for r in db.query(
        &format!(
            "SELECT t.robot, j.name, max(j.tmax) FILTER (WHERE j.tmax <> 'NaN'), \
                    avg(j.tmean) FILTER (WHERE j.tmean <> 'NaN' AND t.at < to_timestamp($4)), \
                    avg(j.tmean) FILTER (WHERE j.tmean <> 'NaN' AND t.at >= to_timestamp($4)) \
             FROM telemetry t, unnest(t.joints, t.temp_max_c, t.temp_mean_c) AS j(name, tmax, tmean) \
             WHERE {WITHIN_T} GROUP BY 1, 2"
        ),
        &[&from, &to, &robot, &mid],
    )? {
        let (robot, joint): (String, String) = (r.get(0), r.get(1));
        a.joints.push(JointFigures {
            above_warn_s: above.remove(&(robot.clone(), joint.clone())).unwrap_or_default(),
            robot,
            joint,
            temp_max_c: r.get::<_, Option<f32>>(2).unwrap_or(f32::NAN),
            mean_first_c: r.get::<_, Option<f64>>(3).unwrap_or(f64::NAN),
            mean_second_c: r.get::<_, Option<f64>>(4).unwrap_or(f64::NAN),
        });
    }
    boxes(db, &p, &mut a)?;
    Ok(a)
}

/// A time as the report writes it.
const UTC: &str = "'YYYY-MM-DD HH24:MI:SS'";

/// The period's black boxes, each under its journaled event (the one the box tells about, by
/// the robot's clock), and its trips that are in no whole box in the store (a box kept open by
/// several events holds them all).
fn boxes(
    db: &mut postgres::Client,
    p: &[&(dyn postgres::types::ToSql + Sync); 3],
    a: &mut Aggregates,
) -> Result<(), postgres::Error> {
    for r in db.query(
        &format!(
            "SELECT b.robot, to_char(coalesce(e.at, b.first_at) AT TIME ZONE 'UTC', {UTC}), \
                    coalesce(e.kind, b.trigger, ''), coalesce(nullif(e.joint, ''), b.joint, ''), \
                    b.name, encode(b.digest, 'hex'), b.size, b.received, b.complete, b.lead_up::text \
             FROM boxes b LEFT JOIN LATERAL (SELECT at, kind, joint FROM events e \
                 WHERE e.robot = b.robot AND e.robot_ns = b.event_ns AND e.origin_seq > 0 \
                 ORDER BY e.id LIMIT 1) e ON true \
             WHERE coalesce(e.at, b.first_at) >= to_timestamp($1) \
               AND coalesce(e.at, b.first_at) < to_timestamp($2) \
               AND ($3::text IS NULL OR b.robot = $3) \
             ORDER BY coalesce(e.at, b.first_at), b.robot"
        ),
        p,
    )? {
        let lead_up: Option<String> = r.get(9);
        a.boxes.push(BoxLine {
            robot: r.get(0),
            at: r.get(1),
            event: r.get(2),
            joint: r.get(3),
            name: r.get(4),
            digest: r.get(5),
            size: r.get::<_, i64>(6) as u64,
            received: r.get::<_, i64>(7) as u64,
            complete: r.get(8),
            lead_up: lead_up.and_then(|j| serde_json::from_str(&j).ok()),
        });
    }
    let trips: Vec<String> = ["ThermalTrip", "FirmwareProtection", "DriverTrip"]
        .map(String::from)
        .to_vec();
    for r in db.query(
        &format!(
            "SELECT e.robot, to_char(e.at AT TIME ZONE 'UTC', {UTC}), e.kind, e.joint FROM events e \
             WHERE {WITHIN} AND e.kind = ANY($4) AND NOT EXISTS \
                 (SELECT 1 FROM boxes b WHERE b.robot = e.robot AND e.robot_ns = ANY(b.trigger_ns)) \
             ORDER BY e.at, e.robot"
        ),
        &[p[0], p[1], p[2], &trips],
    )? {
        a.trips_without_box.push(TripLine {
            robot: r.get(0),
            at: r.get(1),
            kind: r.get(2),
            joint: r.get(3),
        });
    }
    Ok(())
}
