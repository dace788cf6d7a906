//! What the history store lets into its tables: each robot's message is checked before the
//! database sees it, so one robot's garbage is refused (state, layout) or quarantined with its
//! reason (a journaled event, which must not be lost once acknowledged), counted for that robot,
//! and never fails a batch that holds other robots' rows. Pure.
//!
//! The checks are PostgreSQL's own limits, nothing stricter: a NUL character, which its `text`
//! refuses, and a wall time outside what `to_timestamp` takes. A row the database still refuses
//! for its data (SQLSTATE classes 22 and 23, [`is_row_fault`]) is quarantined the same way, so
//! a limit nobody foresaw is no new single point of failure.

use fleet_agent::schema::{EventRecord, LayoutMsg, StateMsg};
use std::collections::BTreeMap;

/// The first wall time, ms since the Unix epoch, that the store refuses: a second before the
/// first that PostgreSQL's `to_timestamp` refuses ("timestamp out of range": 294277-01-01, its
/// `TIMESTAMP_END_JULIAN`), because the store sends the time as a float8, which rounds a
/// figure this large to an even number of milliseconds.
pub const WALL_MS_END: u64 = (86_400 * (109_203_528 - 2_440_588) - 1) * 1000;

/// Why a robot's message is kept out of the store's tables.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Refusal {
    /// A text field holds a NUL character (PostgreSQL's `text` cannot).
    #[error("a NUL character in its {field}")]
    Nul {
        /// Which field (`robot id`, `detail`, `joint name` ...).
        field: &'static str,
    },
    /// A wall time PostgreSQL's timestamps cannot hold.
    #[error("a wall time out of range ({wall_ms} ms after the Unix epoch)")]
    TimeOutOfRange {
        /// The time the robot sent, ms since the Unix epoch.
        wall_ms: u64,
    },
    /// The database refused the row for its data.
    #[error("the database refused it: {message} (SQLSTATE {sqlstate})")]
    Database {
        /// Its SQLSTATE (class 22 or 23).
        sqlstate: String,
        /// Its message.
        message: String,
    },
    /// A box's name is not one a shelf gives (`NNNNNN-…​.mcap`, its number first).
    #[error("box name {name:?}: not NNNNNN-….mcap with the box's number")]
    BoxName {
        /// The name sent (NULs escaped, cut at the longest name taken).
        name: String,
    },
    /// A box's size is 0 or beyond what the store takes.
    #[error(
        "a box of {size} bytes: the store takes 1 to {} bytes",
        crate::boxes::MAX_BOX_BYTES
    )]
    BoxSize {
        /// The size sent.
        size: u64,
    },
    /// A chunk's bytes are not inside its box, or more than a chunk carries.
    #[error("{len} bytes at {offset} of a box of {size} bytes")]
    ChunkOutsideBox {
        /// Where the chunk starts.
        offset: u64,
        /// Its bytes.
        len: u64,
        /// The box's size.
        size: u64,
    },
    /// A chunk names a box the store holds (by digest) with another size or name.
    #[error("the store holds this digest as {held}")]
    BoxConflict {
        /// What the store holds under it.
        held: String,
    },
    /// A box held whole does not have the digest it was sent with: its bytes are dropped and
    /// the box refused.
    #[error("its bytes do not have the digest it was sent with")]
    BoxDigest,
    /// The robot has boxes begun and not whole beyond what the store keeps open for it.
    #[error(
        "{open_bytes} bytes of this robot's boxes still to come: the store keeps {} open",
        crate::boxes::MAX_OPEN_BYTES_PER_ROBOT
    )]
    BoxQuota {
        /// The bytes still to come of its boxes begun.
        open_bytes: u64,
    },
}

impl Refusal {
    /// The refusal's kind, one word (the `refusals` table counts per kind).
    pub fn kind(&self) -> RefusalKind {
        match self {
            Refusal::Nul { .. } => RefusalKind::Nul,
            Refusal::TimeOutOfRange { .. } => RefusalKind::TimeOutOfRange,
            Refusal::Database { .. } => RefusalKind::Database,
            Refusal::BoxName { .. } => RefusalKind::BoxName,
            Refusal::BoxSize { .. } => RefusalKind::BoxSize,
            Refusal::ChunkOutsideBox { .. } => RefusalKind::ChunkOutsideBox,
            Refusal::BoxConflict { .. } => RefusalKind::BoxConflict,
            Refusal::BoxDigest => RefusalKind::BoxDigest,
            Refusal::BoxQuota { .. } => RefusalKind::BoxQuota,
        }
    }
}

/// [`Refusal`]'s variants, without their figures.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum RefusalKind {
    /// [`Refusal::Nul`].
    Nul,
    /// [`Refusal::TimeOutOfRange`].
    TimeOutOfRange,
    /// [`Refusal::Database`].
    Database,
    /// [`Refusal::BoxName`].
    BoxName,
    /// [`Refusal::BoxSize`].
    BoxSize,
    /// [`Refusal::ChunkOutsideBox`].
    ChunkOutsideBox,
    /// [`Refusal::BoxConflict`].
    BoxConflict,
    /// [`Refusal::BoxDigest`].
    BoxDigest,
    /// [`Refusal::BoxQuota`].
    BoxQuota,
}

impl RefusalKind {
    /// As the `refusals` table names it.
    pub fn as_str(self) -> &'static str {
        match self {
            RefusalKind::Nul => "nul",
            RefusalKind::TimeOutOfRange => "time_out_of_range",
            RefusalKind::Database => "database",
            RefusalKind::BoxName => "box_name",
            RefusalKind::BoxSize => "box_size",
            RefusalKind::ChunkOutsideBox => "chunk_outside_box",
            RefusalKind::BoxConflict => "box_conflict",
            RefusalKind::BoxDigest => "box_digest",
            RefusalKind::BoxQuota => "box_quota",
        }
    }
}

/// Which of a robot's messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Message {
    /// A journaled event (quarantined, not dropped).
    Event,
    /// A state sample (dropped: the next one comes in 100 ms).
    State,
    /// A joint layout (dropped: its rows are named `joint0` ... until a good one comes).
    Layout,
    /// A telemetry row the database refused.
    Telemetry,
    /// A piece of a black box (dropped and counted; the robot keeps the box).
    BoxChunk,
}

impl Message {
    /// As the `refusals` table names it.
    pub fn as_str(self) -> &'static str {
        match self {
            Message::Event => "event",
            Message::State => "state",
            Message::Layout => "layout",
            Message::Telemetry => "telemetry",
            Message::BoxChunk => "box_chunk",
        }
    }
}

pub(crate) fn text(field: &'static str, value: &str) -> Result<(), Refusal> {
    if value.contains('\0') {
        Err(Refusal::Nul { field })
    } else {
        Ok(())
    }
}

fn wall(wall_ms: u64) -> Result<(), Refusal> {
    if wall_ms < WALL_MS_END {
        Ok(())
    } else {
        Err(Refusal::TimeOutOfRange { wall_ms })
    }
}

/// Robot `robot`'s event, as the `events` table would hold it.
pub fn check_event(robot: &str, e: &EventRecord) -> Result<(), Refusal> {
    text("robot id", robot)?;
    text("kind", &e.kind)?;
    text("joint", &e.joint)?;
    text("detail", &e.detail)?;
    wall(e.wall_ms)
}

/// Robot `robot`'s state sample, as its telemetry rows would hold it.
pub fn check_state(robot: &str, m: &StateMsg) -> Result<(), Refusal> {
    text("robot id", robot)?;
    wall(m.wall_ms)
}

/// Robot `robot`'s layout, whose names its telemetry rows would hold.
pub fn check_layout(robot: &str, m: &LayoutMsg) -> Result<(), Refusal> {
    text("robot id", robot)?;
    m.joints
        .iter()
        .try_for_each(|j| text("joint name", &j.name))
}

/// The database refused a row for what it holds (data exception, class 22; integrity
/// constraint, class 23), not for the connection or the server: that row is quarantined, the
/// others are written.
pub fn is_row_fault(sqlstate: &str) -> bool {
    sqlstate.starts_with("22") || sqlstate.starts_with("23")
}

/// `text` with each NUL written `\0`, as a quarantine row can hold it.
pub fn escaped(text: &str) -> String {
    text.replace('\0', "\\0")
}

/// The refusals not yet written to the `refusals` table: per robot, message and kind, how many
/// and the last reason.
#[derive(Debug, Default)]
pub struct RefusalCounts {
    pending: BTreeMap<(String, Message, RefusalKind), (u64, String)>,
}

/// One row of [`RefusalCounts`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RefusalRow {
    /// The robot (NULs escaped).
    pub robot: String,
    /// Which of its messages.
    pub message: Message,
    /// Why they were refused (the table's `kind` column).
    pub kind: RefusalKind,
    /// How many since the last write.
    pub count: u64,
    /// The last one's reason.
    pub last_reason: String,
}

impl RefusalCounts {
    /// One more of robot `robot`'s `message`s refused.
    pub fn count(&mut self, robot: &str, message: Message, why: &Refusal) {
        let entry = self
            .pending
            .entry((escaped(robot), message, why.kind()))
            .or_insert((0, String::new()));
        entry.0 += 1;
        entry.1 = why.to_string();
    }

    /// Nothing waits to be written.
    pub fn is_empty(&self) -> bool {
        self.pending.is_empty()
    }

    /// The rows to write; [`RefusalCounts::written`] forgets them once committed.
    pub fn rows(&self) -> Vec<RefusalRow> {
        self.pending
            .iter()
            .map(
                |((robot, message, kind), (count, last_reason))| RefusalRow {
                    robot: robot.clone(),
                    message: *message,
                    kind: *kind,
                    count: *count,
                    last_reason: last_reason.clone(),
                },
            )
            .collect()
    }

    /// `rows` are in the database.
    pub fn written(&mut self, rows: &[RefusalRow]) {
        for r in rows {
            let key = (r.robot.clone(), r.message, r.kind);
            if let Some(entry) = self.pending.get_mut(&key) {
                entry.0 -= r.count.min(entry.0);
                if entry.0 == 0 {
                    self.pending.remove(&key);
                }
            }
        }
    }

    /// Every refusal counted and not yet written, for the store's log.
    pub fn total(&self) -> u64 {
        self.pending.values().map(|(n, _)| n).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fleet_agent::schema::{JointInfoMsg, SCHEMA_VERSION};

    fn event(detail: &str, wall_ms: u64) -> EventRecord {
        EventRecord {
            timestamp_ns: 1,
            wall_ms,
            origin_seq: 0,
            kind: "Stall".into(),
            joint: "left_elbow".into(),
            detail: detail.into(),
            bus: 0,
            level: 0,
            value: 0.0,
        }
    }

    #[test]
    fn a_nul_anywhere_in_an_event_s_text_or_its_robot_is_refused_by_its_field() {
        assert_eq!(check_event("r", &event("", 1)), Ok(()));
        assert_eq!(
            check_event("r", &event("a\0b", 1)),
            Err(Refusal::Nul { field: "detail" })
        );
        assert_eq!(
            check_event("r\0", &event("", 1)),
            Err(Refusal::Nul { field: "robot id" })
        );
        let mut e = event("", 1);
        e.kind = "\0".into();
        assert_eq!(check_event("r", &e), Err(Refusal::Nul { field: "kind" }));
        e.kind = "Stall".into();
        e.joint = "\0".into();
        assert_eq!(check_event("r", &e), Err(Refusal::Nul { field: "joint" }));
    }

    #[test]
    fn the_wall_time_s_bound_is_postgres_s_last_timestamp() {
        // 294276-12-31T23:59:59Z, a second before PostgreSQL's end; the store's test asks the
        // real server for both figures.
        assert_eq!(WALL_MS_END, 9_224_318_015_999_000);
        assert_eq!(check_event("r", &event("", WALL_MS_END - 1)), Ok(()));
        assert_eq!(
            check_event("r", &event("", WALL_MS_END)),
            Err(Refusal::TimeOutOfRange {
                wall_ms: WALL_MS_END
            })
        );
    }

    #[test]
    fn a_layout_with_a_nul_in_any_joint_name_is_refused() {
        let layout = |names: &[&str]| LayoutMsg {
            version: SCHEMA_VERSION,
            joints: names
                .iter()
                .map(|n| JointInfoMsg {
                    name: (*n).into(),
                    min: 0.0,
                    max: 1.0,
                })
                .collect(),
        };
        assert_eq!(check_layout("r", &layout(&["a", "b"])), Ok(()));
        assert_eq!(
            check_layout("r", &layout(&["a", "b\0"])),
            Err(Refusal::Nul {
                field: "joint name"
            })
        );
    }

    #[test]
    fn only_data_and_constraint_errors_are_the_row_s_fault() {
        assert!(is_row_fault("22021")); // a NUL in text
        assert!(is_row_fault("22008")); // timestamp out of range
        assert!(is_row_fault("23505"));
        assert!(!is_row_fault("08006")); // the connection
        assert!(!is_row_fault("57P01")); // the server shutting down
        assert!(!is_row_fault("53100")); // the disk full
    }

    #[test]
    fn refusals_are_counted_per_robot_message_and_kind_until_written() {
        let mut c = RefusalCounts::default();
        let nul = Refusal::Nul {
            field: "joint name",
        };
        c.count("a", Message::Layout, &nul);
        c.count("a", Message::Layout, &nul);
        c.count(
            "b\0",
            Message::State,
            &Refusal::TimeOutOfRange { wall_ms: u64::MAX },
        );
        let rows = c.rows();
        assert_eq!(rows.len(), 2);
        assert_eq!((rows[0].robot.as_str(), rows[0].count), ("a", 2));
        assert_eq!(rows[1].robot, "b\\0", "the robot's NUL escaped");
        assert!(rows[1].last_reason.contains("out of range"));
        // One more while the rows were being written stays pending.
        c.count("a", Message::Layout, &nul);
        c.written(&rows);
        assert_eq!(c.total(), 1);
        assert_eq!(c.rows()[0].count, 1);
    }
}
