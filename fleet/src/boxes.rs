//! The black boxes robots send to the store (`nori/<robot>/blackbox/chunk`): what a chunk must
//! be to be kept, and what the store does with it given what it holds of its box. Pure: the
//! store's binary runs the plan in one transaction per chunk and acknowledges after the commit.
//!
//! A box is kept by its robot and its SHA-256. Its chunks are appended only at the offset the
//! store holds: anything else is answered with that offset (a robot resending after an outage,
//! an agent restarted with a store that kept more, or less). Once held whole, the bytes are
//! checked against the digest; only then is the box acknowledged complete.

use crate::admission::Refusal;
use fleet_agent::schema::BoxChunkMsg;

/// The largest box the store takes, bytes (a robot's shelf is 512 MB; a box of five minutes
/// of every channel is tens of MB).
pub const MAX_BOX_BYTES: u64 = 256 << 20;

/// The bytes of boxes a robot may have open at the store (not yet whole) at once: a robot's
/// certificate in the wrong hands cannot fill the store's disk with boxes begun.
pub const MAX_OPEN_BYTES_PER_ROBOT: u64 = 1 << 30;

/// A box not whole that no chunk has touched for this long is dropped from the store (its
/// robot still has it, and begins it again when it sends it): an abandoned box (trimmed off
/// the robot's shelf, refused, a robot gone) does not count against its robot's bound for
/// ever. As a PostgreSQL interval.
pub const ABANDONED_AFTER: &str = "1 hour";

/// The longest box name the store takes (`NNNNNN-YYYYMMDDTHHMMSSZ-kind.mcap`).
pub const MAX_NAME_LEN: usize = 128;

/// What the store holds of a box.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Held {
    /// Its number on the robot's shelf.
    pub number: u64,
    /// Its file name.
    pub name: String,
    /// Its size.
    pub size: u64,
    /// Bytes held from the start.
    pub received: u64,
    /// Held whole and checked.
    pub complete: bool,
}

/// What the store does with a chunk.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Plan {
    /// The box is new: keep its row (nothing held yet).
    pub open: bool,
    /// Append the chunk's bytes at `held.received` (then, if that completes the box, check
    /// it). Otherwise nothing is written, and the answer is what is held: a probe, a copy, a
    /// chunk beyond the offset held, a box already whole.
    pub append: bool,
    /// What the store holds of the box before the chunk.
    pub held: Held,
}

/// Checks robot `robot`'s chunk before the database sees it: a box name the shelf would give,
/// a size the store takes, the bytes inside the box.
pub fn check_chunk(robot: &str, c: &BoxChunkMsg) -> Result<(), Refusal> {
    let name_ok = c.name.len() <= MAX_NAME_LEN
        && c.name.ends_with(".mcap")
        && c.name.split_once('-').is_some_and(|(n, _)| {
            n.len() >= 6 && n.bytes().all(|b| b.is_ascii_digit()) && n.parse() == Ok(c.number)
        })
        && c.name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"-_.".contains(&b));
    crate::admission::text("robot id", robot)?;
    if !name_ok {
        return Err(Refusal::BoxName {
            name: crate::admission::escaped(&c.name.chars().take(MAX_NAME_LEN).collect::<String>()),
        });
    }
    if c.size == 0 || c.size > MAX_BOX_BYTES {
        return Err(Refusal::BoxSize { size: c.size });
    }
    let len = c.data.len() as u64;
    if len > fleet_agent::config::MAX_BOX_CHUNK_BYTES || c.offset.saturating_add(len) > c.size {
        return Err(Refusal::ChunkOutsideBox {
            offset: c.offset,
            len,
            size: c.size,
        });
    }
    Ok(())
}

/// Whether a robot with `open_bytes` still to come of its boxes begun may begin one of `size`.
pub fn within_quota(open_bytes: u64, size: u64) -> Result<(), Refusal> {
    if open_bytes.saturating_add(size) > MAX_OPEN_BYTES_PER_ROBOT {
        Err(Refusal::BoxQuota { open_bytes })
    } else {
        Ok(())
    }
}

/// What to do with a checked chunk, given what the store holds of its box (`None`: nothing).
/// A chunk that names the box (its digest) with another size or name is refused: the digest
/// is the box's identity, and one robot's garbage must not bend another's box.
pub fn plan(held: Option<Held>, c: &BoxChunkMsg) -> Result<Plan, Refusal> {
    let open = held.is_none();
    let held = held.unwrap_or_else(|| Held {
        number: c.number,
        name: c.name.clone(),
        size: c.size,
        received: 0,
        complete: false,
    });
    if held.size != c.size || held.name != c.name {
        return Err(Refusal::BoxConflict {
            held: format!("{} bytes, {}", held.size, held.name),
        });
    }
    Ok(Plan {
        open,
        append: !held.complete && !c.data.is_empty() && c.offset == held.received,
        held,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use fleet_agent::schema::SCHEMA_VERSION;

    fn chunk(offset: u64, len: usize) -> BoxChunkMsg {
        BoxChunkMsg {
            version: SCHEMA_VERSION,
            number: 12,
            name: "000012-20261130T020000Z-thermal_trip.mcap".into(),
            size: 1000,
            digest: [3; 32],
            offset,
            data: vec![7; len],
        }
    }

    fn held(received: u64, complete: bool) -> Held {
        Held {
            number: 12,
            name: chunk(0, 0).name,
            size: 1000,
            received,
            complete,
        }
    }

    /// (opens, appends) of `c` on `h`.
    fn does(h: Option<Held>, c: &BoxChunkMsg) -> (bool, bool) {
        let p = plan(h, c).unwrap();
        (p.open, p.append)
    }

    #[test]
    fn a_chunk_is_appended_only_at_the_offset_held() {
        assert_eq!(does(None, &chunk(0, 0)), (true, false), "a probe opens");
        assert_eq!(does(None, &chunk(0, 100)), (true, true));
        assert_eq!(does(None, &chunk(100, 100)), (true, false));
        assert_eq!(does(Some(held(0, false)), &chunk(0, 100)), (false, true));
        assert_eq!(
            does(Some(held(200, false)), &chunk(200, 100)),
            (false, true)
        );
        for (h, c) in [
            (held(200, false), chunk(100, 100)),
            (held(200, false), chunk(300, 100)),
            (held(200, false), chunk(200, 0)),
            (held(1000, true), chunk(900, 100)),
        ] {
            assert_eq!(
                does(Some(h.clone()), &c),
                (false, false),
                "{h:?} {}",
                c.offset
            );
        }
        let mut other = chunk(0, 10);
        other.size = 999;
        assert!(matches!(
            plan(Some(held(0, false)), &other),
            Err(Refusal::BoxConflict { .. })
        ));
        other = chunk(0, 10);
        other.name = "000012-20261130T020000Z-saved.mcap".into();
        assert!(matches!(
            plan(Some(held(0, false)), &other),
            Err(Refusal::BoxConflict { .. })
        ));
    }

    #[test]
    fn a_robot_s_boxes_begun_are_bounded() {
        assert_eq!(within_quota(0, MAX_OPEN_BYTES_PER_ROBOT), Ok(()));
        let most = MAX_OPEN_BYTES_PER_ROBOT - 1000;
        assert_eq!(within_quota(most, 1000), Ok(()));
        assert_eq!(
            within_quota(most, 1001),
            Err(Refusal::BoxQuota { open_bytes: most })
        );
        assert!(within_quota(u64::MAX, 1).is_err());
    }

    #[test]
    fn garbage_is_refused_by_what_is_wrong() {
        assert_eq!(check_chunk("r1", &chunk(900, 100)), Ok(()));
        let mut c = chunk(950, 100);
        assert!(matches!(
            check_chunk("r1", &c),
            Err(Refusal::ChunkOutsideBox { .. })
        ));
        c = chunk(0, 0);
        c.offset = u64::MAX;
        assert!(matches!(
            check_chunk("r1", &c),
            Err(Refusal::ChunkOutsideBox { .. })
        ));
        c = chunk(0, 0);
        c.size = 0;
        assert_eq!(check_chunk("r1", &c), Err(Refusal::BoxSize { size: 0 }));
        c = chunk(0, 0);
        c.size = MAX_BOX_BYTES;
        c.data = vec![0; fleet_agent::config::MAX_BOX_CHUNK_BYTES as usize + 1];
        assert!(matches!(
            check_chunk("r1", &c),
            Err(Refusal::ChunkOutsideBox { .. })
        ));
        c.data.pop();
        assert_eq!(check_chunk("r1", &c), Ok(()), "the largest chunk");
        c = chunk(0, 0);
        c.size = MAX_BOX_BYTES + 1;
        assert_eq!(
            check_chunk("r1", &c),
            Err(Refusal::BoxSize {
                size: MAX_BOX_BYTES + 1
            })
        );
        for name in [
            "../../etc/passwd.mcap",
            "000013-T-x.mcap",
            "000012-T-x.mcap.partial",
            "12-T-x.mcap",
            "000012-T-a b.mcap",
            "000012-T-\0.mcap",
        ] {
            c = chunk(0, 0);
            c.name = name.into();
            assert!(
                matches!(check_chunk("r1", &c), Err(Refusal::BoxName { .. })),
                "{name:?}"
            );
        }
        c = chunk(0, 0);
        c.name = format!("000012-{}.mcap", "x".repeat(200));
        assert!(matches!(
            check_chunk("r1", &c),
            Err(Refusal::BoxName { .. })
        ));
    }
}
