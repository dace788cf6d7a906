//! The fleet's history, as `nori fleet-store` keeps it in PostgreSQL: every journaled event
//! once, and the joints' telemetry rolled up per robot and period. Pure: messages in, rows out;
//! the database and zenoh are wired in the binary (`fleet/src/bin/nori-fleet/store.rs`).
//!
//! Why rolled up, not sampled: what the fleet asks of telemetry is how hot and how loaded each
//! motor ran and for how long it sat above each warning temperature, and a sample every minute
//! would miss a ten-second excursion. Every state message (10 Hz from each robot by default)
//! is folded into its robot's current period; one row per robot and period is written.

use fleet_agent::schema::{EventRecord, LayoutMsg, StateMsg};
use std::collections::HashMap;

/// The database's tables (idempotent: run at every start).
pub const SCHEMA_SQL: &str = "
CREATE TABLE IF NOT EXISTS events (
    id          bigserial PRIMARY KEY,
    robot       text        NOT NULL,
    journal     bigint      NOT NULL,
    seq         bigint      NOT NULL,
    at          timestamptz NOT NULL,
    robot_ns    bigint      NOT NULL,
    origin_seq  bigint      NOT NULL,
    kind        text        NOT NULL,
    joint       text        NOT NULL,
    detail      text        NOT NULL,
    bus         smallint    NOT NULL,
    level       smallint    NOT NULL,
    value       real        NOT NULL,
    stored_at   timestamptz NOT NULL DEFAULT now()
);
-- One row per journaled event however often it comes; unnumbered ones (seq 0: the robot's
-- journal failed) are each their own.
CREATE UNIQUE INDEX IF NOT EXISTS events_once ON events (robot, journal, seq) WHERE seq > 0;
-- And a supervisor event once, by its own number and time, even if the robot journaled it
-- twice (its record torn after it was stored, then replayed to the agent by the state plane).
CREATE UNIQUE INDEX IF NOT EXISTS events_origin_once ON events (robot, robot_ns, origin_seq)
    WHERE origin_seq > 0;
CREATE INDEX IF NOT EXISTS events_at ON events USING brin (at);
CREATE INDEX IF NOT EXISTS events_robot_at ON events (robot, at);
CREATE TABLE IF NOT EXISTS journals (
    robot          text        NOT NULL,
    journal        bigint      NOT NULL,
    stored_through bigint      NOT NULL,
    lost           bigint      NOT NULL,
    updated_at     timestamptz NOT NULL DEFAULT now(),
    PRIMARY KEY (robot, journal)
);
CREATE TABLE IF NOT EXISTS telemetry (
    robot        text        NOT NULL,
    at           timestamptz NOT NULL,
    period_s     real        NOT NULL,
    samples      integer     NOT NULL,
    joints       text[]      NOT NULL,
    temp_max_c   real[]      NOT NULL,
    temp_mean_c  real[]      NOT NULL,
    current_max_a real[]     NOT NULL,
    above_warn_s real[]      NOT NULL,
    PRIMARY KEY (robot, at)
);
CREATE INDEX IF NOT EXISTS telemetry_at ON telemetry USING brin (at);
-- A journaled event the store could not keep in `events` (`fleet::admission`): acknowledged to
-- its robot all the same, so kept here with the reason, as the robot sent it (JSON, NULs
-- escaped), once.
CREATE TABLE IF NOT EXISTS quarantine (
    robot      text        NOT NULL,
    journal    bigint      NOT NULL,
    seq        bigint      NOT NULL,
    reason     text        NOT NULL,
    event      text        NOT NULL,
    stored_at  timestamptz NOT NULL DEFAULT now()
);
CREATE UNIQUE INDEX IF NOT EXISTS quarantine_once ON quarantine (robot, journal, seq) WHERE seq > 0;
-- Each robot's messages refused, per message and reason kind: how many, and the last reason.
CREATE TABLE IF NOT EXISTS refusals (
    robot       text        NOT NULL,
    what        text        NOT NULL,
    kind        text        NOT NULL,
    count       bigint      NOT NULL,
    last_reason text        NOT NULL,
    first_at    timestamptz NOT NULL DEFAULT now(),
    last_at     timestamptz NOT NULL DEFAULT now(),
    PRIMARY KEY (robot, what, kind)
);
-- The black boxes robots send (`fleet::boxes`): one row per box, kept by its robot and SHA-256,
-- its bytes in `box_chunks` in the order they came (appended only at `received`). `complete`
-- once held whole and checked against the digest; then the event told about (its first trip,
-- else what froze it: `trigger`, `joint`, `event_ns` on the robot's clock), every event that
-- froze or kept it open (`trigger_ns`) and what led to it (`blackbox::lead_up`, JSON) are read
-- from the box. One not whole and untouched for an hour is dropped (its robot still has it).
CREATE TABLE IF NOT EXISTS boxes (
    robot        text        NOT NULL,
    digest       bytea       NOT NULL,
    number       bigint      NOT NULL,
    name         text        NOT NULL,
    size         bigint      NOT NULL,
    received     bigint      NOT NULL DEFAULT 0,
    complete     boolean     NOT NULL DEFAULT false,
    first_at     timestamptz NOT NULL DEFAULT now(),
    touched_at   timestamptz NOT NULL DEFAULT now(),
    completed_at timestamptz,
    trigger      text,
    joint        text,
    event_ns     bigint,
    trigger_ns   bigint[],
    lead_up      jsonb,
    PRIMARY KEY (robot, digest)
);
CREATE INDEX IF NOT EXISTS boxes_first_at ON boxes (first_at);
CREATE INDEX IF NOT EXISTS boxes_event ON boxes (robot, event_ns);
CREATE TABLE IF NOT EXISTS box_chunks (
    robot   text   NOT NULL,
    digest  bytea  NOT NULL,
    at_byte bigint NOT NULL,
    data    bytea  NOT NULL,
    PRIMARY KEY (robot, digest, at_byte)
);
-- What each robot runs: its agent's newest start (`AgentStarted`, whose detail is the
-- nori-robot package version, empty for a build from source); its history is those events.
-- Newest by arrival (a robot delivers its journal oldest first), not by the robot's wall clock,
-- which a Pi without a real-time clock may have set ahead before NTP corrected it.
CREATE OR REPLACE VIEW robot_versions AS
    SELECT DISTINCT ON (robot) robot, detail AS installed_version, at AS running_since
    FROM events WHERE kind = 'AgentStarted' ORDER BY robot, id DESC;
-- The calibration each robot runs: its agent's newest start's `CalibrationInForce` (detail:
-- `none`, or the method, the time and the robot the file names; value: its joints); its
-- history is those events (the same calibration again at each start).
CREATE OR REPLACE VIEW robot_calibrations AS
    SELECT DISTINCT ON (robot) robot,
        NULLIF(split_part(detail, ' ', 1), 'none') AS method,
        NULLIF(NULLIF(split_part(detail, ' ', 2), '-'), '') AS calibrated_at,
        NULLIF(NULLIF(regexp_replace(detail, '^\\S+ \\S+ ?', ''), '-'), '') AS calibrated_for,
        value::int AS joints,
        at AS reported_at
    FROM events WHERE kind = 'CalibrationInForce' ORDER BY robot, id DESC;
";

/// A batch of events into `events` in one statement (copies already there skipped; the rows
/// affected are the events new to the table): the columns of [`EventColumns`], as arrays.
pub const INSERT_EVENTS_SQL: &str = "INSERT INTO events \
     (robot, journal, seq, at, robot_ns, origin_seq, kind, joint, detail, bus, level, value) \
     SELECT r, j, s, to_timestamp(w / 1000.0), ns, o, k, jt, d, b, l, v FROM unnest(\
     $1::text[], $2::bigint[], $3::bigint[], $4::float8[], $5::bigint[], $6::bigint[], \
     $7::text[], $8::text[], $9::text[], $10::int2[], $11::int2[], $12::float4[]) \
     AS t(r, j, s, w, ns, o, k, jt, d, b, l, v) ON CONFLICT DO NOTHING";

/// One event into `quarantine`: robot, journal, seq, reason, the event (a copy already there
/// is skipped).
pub const QUARANTINE_SQL: &str = "INSERT INTO quarantine (robot, journal, seq, reason, event) \
     VALUES ($1, $2, $3, $4, $5) ON CONFLICT DO NOTHING";

/// Adds robot, message, kind, count, last reason to `refusals`.
pub const COUNT_REFUSALS_SQL: &str =
    "INSERT INTO refusals (robot, what, kind, count, last_reason) \
     VALUES ($1, $2, $3, $4, $5) ON CONFLICT (robot, what, kind) DO UPDATE SET \
     count = refusals.count + excluded.count, last_reason = excluded.last_reason, last_at = now()";

/// One event into `events` (a copy already there is skipped): robot, journal, seq, wall ms,
/// robot ns, origin seq, kind, joint, detail, bus, level, value. The store's statement, and
/// the baseline of `nori bench fleet-store`.
pub const INSERT_EVENT_SQL: &str = "INSERT INTO events \
     (robot, journal, seq, at, robot_ns, origin_seq, kind, joint, detail, bus, level, value) \
     VALUES ($1, $2, $3, to_timestamp($4::float8 / 1000.0), $5, $6, $7, $8, $9, $10, $11, $12) \
     ON CONFLICT DO NOTHING";

/// One event as [`INSERT_EVENT_SQL`] takes it: robot `robot`'s journal `journal`, number `seq`.
pub struct EventRow<'a> {
    robot: &'a str,
    numbers: [i64; 4],
    wall_ms: f64,
    bus_level: [i16; 2],
    event: &'a EventRecord,
}

impl<'a> EventRow<'a> {
    /// The row of `event`.
    pub fn new(robot: &'a str, journal: u64, seq: u64, event: &'a EventRecord) -> Self {
        EventRow {
            robot,
            numbers: [
                journal as i64,
                seq as i64,
                event.timestamp_ns as i64,
                event.origin_seq as i64,
            ],
            wall_ms: event.wall_ms as f64,
            bus_level: [i16::from(event.bus), i16::from(event.level)],
            event,
        }
    }

    /// The statement's twelve parameters, in order.
    pub fn params(&self) -> [&(dyn postgres::types::ToSql + Sync); 12] {
        let [journal, seq, robot_ns, origin_seq] = &self.numbers;
        let [bus, level] = &self.bus_level;
        let e = self.event;
        [
            &self.robot,
            journal,
            seq,
            &self.wall_ms,
            robot_ns,
            origin_seq,
            &e.kind,
            &e.joint,
            &e.detail,
            bus,
            level,
            &e.value,
        ]
    }
}

/// A batch of events as [`INSERT_EVENTS_SQL`] takes them: one array per column.
#[derive(Debug, Default)]
pub struct EventColumns {
    robot: Vec<String>,
    journal: Vec<i64>,
    seq: Vec<i64>,
    wall_ms: Vec<f64>,
    robot_ns: Vec<i64>,
    origin_seq: Vec<i64>,
    kind: Vec<String>,
    joint: Vec<String>,
    detail: Vec<String>,
    bus: Vec<i16>,
    level: Vec<i16>,
    value: Vec<f32>,
}

impl EventColumns {
    /// Adds robot `robot`'s journal `journal`, number `seq`.
    pub fn push(&mut self, robot: &str, journal: u64, seq: u64, e: &EventRecord) {
        self.robot.push(robot.to_string());
        self.journal.push(journal as i64);
        self.seq.push(seq as i64);
        self.wall_ms.push(e.wall_ms as f64);
        self.robot_ns.push(e.timestamp_ns as i64);
        self.origin_seq.push(e.origin_seq as i64);
        self.kind.push(e.kind.clone());
        self.joint.push(e.joint.clone());
        self.detail.push(e.detail.clone());
        self.bus.push(i16::from(e.bus));
        self.level.push(i16::from(e.level));
        self.value.push(e.value);
    }

    /// Events in the batch.
    pub fn len(&self) -> usize {
        self.robot.len()
    }

    /// No event in the batch.
    pub fn is_empty(&self) -> bool {
        self.robot.is_empty()
    }

    /// The statement's twelve parameters, in order.
    pub fn params(&self) -> [&(dyn postgres::types::ToSql + Sync); 12] {
        [
            &self.robot,
            &self.journal,
            &self.seq,
            &self.wall_ms,
            &self.robot_ns,
            &self.origin_seq,
            &self.kind,
            &self.joint,
            &self.detail,
            &self.bus,
            &self.level,
            &self.value,
        ]
    }
}

/// How telemetry is rolled up.
#[derive(Debug, Clone, PartialEq)]
pub struct RollupConfig {
    /// One row per robot per this many ms of its wall clock.
    pub period_ms: u64,
    /// Temperatures whose time above is kept per joint, °C (the supervisor's warning levels).
    pub warn_c: Vec<f32>,
    /// A gap between two samples longer than this counts as this long, ms (a robot offline is
    /// not hot for the whole outage).
    pub max_gap_ms: u64,
}

/// One robot's period, rolled up: per joint, in the layout's order.
#[derive(Debug, Clone, PartialEq)]
pub struct RollupRow {
    /// The robot.
    pub robot: String,
    /// The period's start, ms since the Unix epoch (robot wall clock).
    pub start_ms: u64,
    /// Its length, s.
    pub period_s: f32,
    /// State messages folded in.
    pub samples: u32,
    /// Joint names.
    pub joints: Vec<String>,
    /// Hottest reading, °C (NaN: never read).
    pub temp_max_c: Vec<f32>,
    /// Mean reading, °C.
    pub temp_mean_c: Vec<f32>,
    /// Largest current, A.
    pub current_max_a: Vec<f32>,
    /// Seconds at or above each warning level, joint-major (`joints × warn_c`).
    pub above_warn_s: Vec<f32>,
}

#[derive(Debug)]
struct Open {
    row: RollupRow,
    temp_sum: Vec<f64>,
    temp_n: Vec<u32>,
    last_ms: u64,
}

/// Every robot's open period.
#[derive(Debug)]
pub struct Rollups {
    config: RollupConfig,
    names: HashMap<String, Vec<String>>,
    open: HashMap<String, Open>,
}

impl Rollups {
    /// No robot yet.
    pub fn new(config: RollupConfig) -> Rollups {
        Rollups {
            config,
            names: HashMap::new(),
            open: HashMap::new(),
        }
    }

    /// A robot's layout: its joints' names (the open period's too: a layout comes every few
    /// seconds, after a store's start a period has begun without it).
    pub fn layout(&mut self, robot: &str, layout: &LayoutMsg) {
        let names: Vec<String> = layout.joints.iter().map(|j| j.name.clone()).collect();
        if let Some(open) = self.open.get_mut(robot) {
            if open.row.joints.len() == names.len() {
                open.row.joints.clone_from(&names);
            }
        }
        self.names.insert(robot.to_string(), names);
    }

    /// Folds one state message in; returns the robot's previous period when this one starts a
    /// new period (or a new joint count).
    pub fn state(&mut self, robot: &str, msg: &StateMsg) -> Option<RollupRow> {
        let period = self.config.period_ms.max(1);
        let start_ms = msg.wall_ms - msg.wall_ms % period;
        let n = msg.joints.len();
        let levels = self.config.warn_c.len();
        let closed = match self.open.get(robot) {
            Some(o) if o.row.start_ms == start_ms && o.row.joints.len() == n => None,
            Some(_) => self.open.remove(robot).map(finish),
            None => None,
        };
        let names = self.names.get(robot);
        let open = self.open.entry(robot.to_string()).or_insert_with(|| Open {
            row: RollupRow {
                robot: robot.to_string(),
                start_ms,
                period_s: period as f32 / 1000.0,
                samples: 0,
                joints: (0..n)
                    .map(|i| {
                        names
                            .filter(|v| v.len() == n)
                            .map_or_else(|| format!("joint{i}"), |v| v[i].clone())
                    })
                    .collect(),
                temp_max_c: vec![f32::NAN; n],
                temp_mean_c: vec![f32::NAN; n],
                current_max_a: vec![f32::NAN; n],
                above_warn_s: vec![0.0; n * levels],
            },
            temp_sum: vec![0.0; n],
            temp_n: vec![0; n],
            last_ms: msg.wall_ms,
        });
        let dt_s = msg
            .wall_ms
            .saturating_sub(open.last_ms)
            .min(self.config.max_gap_ms) as f32
            / 1000.0;
        open.last_ms = open.last_ms.max(msg.wall_ms);
        open.row.samples += 1;
        for (i, j) in msg.joints.iter().enumerate() {
            if !j.valid || !j.temperature_c.is_finite() {
                continue;
            }
            let r = &mut open.row;
            r.temp_max_c[i] = r.temp_max_c[i].max(j.temperature_c);
            r.current_max_a[i] = r.current_max_a[i].max(j.current_a.abs());
            open.temp_sum[i] += f64::from(j.temperature_c);
            open.temp_n[i] += 1;
            for (k, &warn) in self.config.warn_c.iter().enumerate() {
                if j.temperature_c >= warn {
                    r.above_warn_s[i * levels + k] += dt_s;
                }
            }
        }
        closed
    }

    /// The periods that ended before `now_ms` by more than a period (their robot fell silent):
    /// closed and returned.
    pub fn close_idle(&mut self, now_ms: u64) -> Vec<RollupRow> {
        let period = self.config.period_ms.max(1);
        let idle: Vec<String> = self
            .open
            .iter()
            .filter(|(_, o)| o.row.start_ms + 2 * period <= now_ms)
            .map(|(r, _)| r.clone())
            .collect();
        idle.iter()
            .filter_map(|r| self.open.remove(r))
            .map(finish)
            .collect()
    }

    /// Every open period, closed (at shutdown).
    pub fn close_all(&mut self) -> Vec<RollupRow> {
        self.open.drain().map(|(_, o)| finish(o)).collect()
    }
}

fn finish(mut o: Open) -> RollupRow {
    for (i, mean) in o.row.temp_mean_c.iter_mut().enumerate() {
        if o.temp_n[i] > 0 {
            *mean = (o.temp_sum[i] / f64::from(o.temp_n[i])) as f32;
        }
    }
    o.row
}

#[cfg(test)]
mod tests {
    use super::*;
    use fleet_agent::schema::{JointInfoMsg, JointMsg, SCHEMA_VERSION};

    fn msg(wall_ms: u64, temps: &[f32]) -> StateMsg {
        StateMsg {
            version: SCHEMA_VERSION,
            seq: 0,
            timestamp_ns: 0,
            wall_ms,
            safe_state: false,
            deadline_misses: 0,
            joints: temps
                .iter()
                .map(|&t| JointMsg {
                    position: 0.0,
                    velocity: 0.0,
                    temperature_c: t,
                    current_a: -t / 100.0,
                    goal: 0.0,
                    valid: t > 0.0,
                    torque: true,
                    flags: 0,
                })
                .collect(),
            lift: None,
            base: None,
        }
    }

    fn rollups() -> Rollups {
        Rollups::new(RollupConfig {
            period_ms: 60_000,
            warn_c: vec![50.0, 54.0],
            max_gap_ms: 1_000,
        })
    }

    #[test]
    fn a_period_keeps_the_hottest_the_mean_the_peak_current_and_the_time_above_each_level() {
        let mut r = rollups();
        r.layout(
            "a",
            &LayoutMsg {
                version: SCHEMA_VERSION,
                joints: ["elbow", "wrist"]
                    .iter()
                    .map(|n| JointInfoMsg {
                        name: (*n).into(),
                        min: -1.0,
                        max: 1.0,
                    })
                    .collect(),
            },
        );
        // 10 Hz for 30 s: the elbow at 52 °C for the last 20 s, the wrist never read.
        for k in 0..300u64 {
            let t = if k >= 100 { 52.0 } else { 40.0 };
            assert_eq!(r.state("a", &msg(120_000 + k * 100, &[t, 0.0])), None);
        }
        // A minute later, at 55 °C: a new period, which counts no time above for the gap.
        let row = r
            .state("a", &msg(190_000, &[55.0, 0.0]))
            .expect("a new period");
        assert_eq!((row.start_ms, row.samples), (120_000, 300));
        assert_eq!(row.joints, ["elbow", "wrist"]);
        assert_eq!(row.temp_max_c[0], 52.0);
        assert!((row.temp_mean_c[0] - (40.0 * 100.0 + 52.0 * 200.0) / 300.0).abs() < 1e-4);
        assert!((row.current_max_a[0] - 0.52).abs() < 1e-6);
        assert!(
            (row.above_warn_s[0] - 20.0).abs() < 0.05,
            "{}",
            row.above_warn_s[0]
        );
        assert_eq!(row.above_warn_s[1], 0.0, "never at 54 °C");
        assert!(
            row.temp_max_c[1].is_nan() && row.temp_mean_c[1].is_nan(),
            "never read"
        );
        let all = r.close_all();
        assert_eq!(all.len(), 1);
        assert_eq!(
            all[0].above_warn_s[..2],
            [0.0, 0.0],
            "the gap is no time above"
        );
        assert_eq!(all[0].start_ms, 180_000);
    }

    #[test]
    fn a_layout_arriving_mid_period_names_its_joints() {
        let mut r = rollups();
        r.state("a", &msg(60_000, &[30.0]));
        let layout = LayoutMsg {
            version: SCHEMA_VERSION,
            joints: vec![JointInfoMsg {
                name: "neck".into(),
                min: -1.0,
                max: 1.0,
            }],
        };
        r.layout("a", &layout);
        assert_eq!(r.close_all()[0].joints, ["neck"]);
    }

    #[test]
    fn a_silent_robot_s_period_is_closed_once_it_is_a_period_past_its_end() {
        let mut r = rollups();
        r.state("a", &msg(60_000, &[30.0]));
        r.state("b", &msg(130_000, &[30.0]));
        assert!(r.close_idle(179_999).is_empty());
        let closed = r.close_idle(180_000);
        assert_eq!(closed.len(), 1);
        assert_eq!(
            (closed[0].robot.as_str(), closed[0].joints[0].as_str()),
            ("a", "joint0")
        );
        assert_eq!(r.close_all().len(), 1);
    }
}
