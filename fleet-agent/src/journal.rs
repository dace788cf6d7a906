//! The robot's event journal: an append-only, bounded, crash-safe file of the events the agent
//! sends to the fleet, each under a sequence number that rises across restarts, so that what an
//! outage or a crash of the agent kept from the fleet can be sent again and de-duplicated there.
//! Its delivery, with the fleet's acknowledgements, is [`crate::delivery`].
//!
//! Format: records back to back, each `"NJ"`, the payload's length (u16 LE), a CRC-32 (u32 LE)
//! over the sequence number and the payload, the sequence number (u64 LE), the payload. A record
//! cut short (a power cut mid-write) or damaged ends the journal there: [`Journal::open`]
//! truncates the file to its last whole record, so what is appended next follows good data and
//! nothing after a tear is ever read as a record. An appended record is on the storage
//! (`fdatasync`) before [`Journal::append`] returns.
//!
//! Bounded: records go into segment files of at most half the bound each, at most two of them;
//! when the newer one is full, the older is deleted. When full, the oldest events are dropped
//! first, and counted ([`Journal::dropped`]).
//!
//! Beside the segments, two small files: `journal-id`, the journal's identity (random, made
//! when the journal starts empty, so a wiped journal never reuses the numbers of the old one
//! under its name), and `acked`, how far the fleet has acknowledged it (written by rename;
//! lost, the agent only sends again what the fleet will de-duplicate).
//!
//! [`encode`] and [`scan`] are the format, sans-IO; [`Journal`] puts it in files.

use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// The first two bytes of every record.
pub const MAGIC: [u8; 2] = *b"NJ";
/// Bytes before a record's payload.
pub const HEADER: usize = 16;
/// The largest payload (an event message is under 100 bytes).
pub const MAX_PAYLOAD: usize = 4096;
/// The smallest bound (two segments of a few records each).
pub const MIN_BOUND: u64 = 2 * (HEADER + MAX_PAYLOAD) as u64;

/// What the journal could not do.
#[derive(Debug, Error)]
#[allow(missing_docs, reason = "each field is shown in its variant's message")]
pub enum JournalError {
    /// Reading, writing, syncing or listing the journal's files failed.
    #[error("event journal {path}: {source}")]
    Io {
        /// The file or directory.
        path: String,
        source: std::io::Error,
    },
    /// A payload over [`MAX_PAYLOAD`].
    #[error("an event of {len} bytes is over the journal's {MAX_PAYLOAD}-byte records")]
    TooLarge {
        /// Its length.
        len: usize,
    },
    /// The journal has records but its identity file is missing or unreadable: its events
    /// cannot be named to the fleet.
    #[error("event journal {path}: no readable identity beside its records (restore it, or move the journal aside to start a new one)")]
    Identity {
        /// The identity file.
        path: String,
    },
    /// A bound under [`MIN_BOUND`].
    #[error("a journal bound of {bytes} bytes is under {MIN_BOUND}")]
    Bound {
        /// The bound asked for.
        bytes: u64,
    },
}

/// One record read back.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Record {
    /// Its sequence number.
    pub seq: u64,
    /// What was appended.
    pub payload: Vec<u8>,
}

fn crc(seq: u64, payload: &[u8]) -> u32 {
    let mut h = crc32fast::Hasher::new();
    h.update(&seq.to_le_bytes());
    h.update(payload);
    h.finalize()
}

/// Appends the record of `payload` under `seq` to `out`.
pub fn encode(seq: u64, payload: &[u8], out: &mut Vec<u8>) -> Result<(), JournalError> {
    let len = u16::try_from(payload.len())
        .ok()
        .filter(|&l| usize::from(l) <= MAX_PAYLOAD)
        .ok_or(JournalError::TooLarge { len: payload.len() })?;
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&len.to_le_bytes());
    out.extend_from_slice(&crc(seq, payload).to_le_bytes());
    out.extend_from_slice(&seq.to_le_bytes());
    out.extend_from_slice(payload);
    Ok(())
}

/// The whole, undamaged records at the start of `bytes`, and how many bytes they span: the
/// first record cut short, damaged or out of sequence ends the scan.
pub fn scan(bytes: &[u8]) -> (Vec<Record>, usize) {
    let (mut records, mut at) = (Vec::new(), 0);
    while let Some(head) = bytes.get(at..at + HEADER) {
        let le = |r: std::ops::Range<usize>| {
            let mut b = [0u8; 8];
            b[..r.len()].copy_from_slice(&head[r]);
            u64::from_le_bytes(b)
        };
        let len = le(2..4) as usize;
        let (sum, seq) = (le(4..8) as u32, le(8..16));
        let Some(payload) = bytes.get(at + HEADER..at + HEADER + len) else {
            break;
        };
        let in_order = records.last().is_none_or(|r: &Record| seq > r.seq);
        if head[..2] != MAGIC || len > MAX_PAYLOAD || sum != crc(seq, payload) || !in_order {
            break;
        }
        records.push(Record {
            seq,
            payload: payload.to_vec(),
        });
        at += HEADER + len;
    }
    (records, at)
}

/// What opening the journal found.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Recovery {
    /// Whole records kept.
    pub records: usize,
    /// Bytes of a torn or damaged tail cut off.
    pub cut_bytes: u64,
    /// The fleet had acknowledged the records through this number (0: none).
    pub acked_through: u64,
}

/// The journal in a directory of its own.
#[derive(Debug)]
pub struct Journal {
    dir: PathBuf,
    id: u64,
    segment_bound: u64,
    /// Segment files, oldest first (at most two), and the newest's length.
    segments: Vec<PathBuf>,
    file: Option<File>,
    len: u64,
    next_seq: u64,
    dropped: u64,
    scratch: Vec<u8>,
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> JournalError + '_ {
    move |source| JournalError::Io {
        path: path.display().to_string(),
        source,
    }
}

const IDENTITY: &str = "journal-id";
const ACKED: &str = "acked";

/// A new identity for a journal that starts empty, on the storage before any record.
fn new_identity(dir: &Path) -> Result<u64, JournalError> {
    let mut bytes = [0u8; 8];
    let random = File::open("/dev/urandom").and_then(|mut f| {
        use std::io::Read;
        f.read_exact(&mut bytes)
    });
    let id = match random {
        Ok(()) => u64::from_le_bytes(bytes),
        // No /dev/urandom: the wall clock's nanoseconds and the process id are unique enough.
        Err(_) => {
            let t = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos() as u64);
            t ^ u64::from(std::process::id()).rotate_left(48)
        }
    }
    .max(1);
    let path = dir.join(IDENTITY);
    let mut f = File::create(&path).map_err(io(&path))?;
    f.write_all(format!("{id:016x}\n").as_bytes())
        .and_then(|()| f.sync_all())
        .map_err(io(&path))?;
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(io(dir))?;
    Ok(id)
}

fn read_identity(dir: &Path) -> Result<u64, JournalError> {
    let path = dir.join(IDENTITY);
    std::fs::read_to_string(&path)
        .ok()
        .and_then(|t| u64::from_str_radix(t.trim(), 16).ok())
        .ok_or_else(|| JournalError::Identity {
            path: path.display().to_string(),
        })
}

/// How far the fleet acknowledged journal `id` (0 when unknown, or for another journal).
fn read_acked(dir: &Path, id: u64) -> u64 {
    let text = std::fs::read_to_string(dir.join(ACKED)).unwrap_or_default();
    let mut parts = text.split_whitespace();
    match (parts.next(), parts.next().and_then(|s| s.parse().ok())) {
        (Some(of), Some(seq)) if u64::from_str_radix(of, 16).ok() == Some(id) => seq,
        _ => 0,
    }
}

/// A segment's file name: the sequence number of its first record, so names sort in order.
fn segment_name(first_seq: u64) -> String {
    format!("events-{first_seq:020}.nj")
}

impl Journal {
    /// Opens (creating) the journal in `dir`, at most `bound_bytes` on disk: keeps every whole
    /// record, cuts a torn tail off the newest segment, continues the sequence after the last.
    pub fn open(dir: &Path, bound_bytes: u64) -> Result<(Journal, Recovery), JournalError> {
        if bound_bytes < MIN_BOUND {
            return Err(JournalError::Bound { bytes: bound_bytes });
        }
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let mut segments: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(io(dir))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with("events-") && n.ends_with(".nj"))
            })
            .collect();
        segments.sort();
        // More than two (a crash between creating a segment and deleting the oldest): the
        // oldest go, as the bound says.
        while segments.len() > 2 {
            let old = segments.remove(0);
            std::fs::remove_file(&old).map_err(io(&old))?;
        }
        let mut recovery = Recovery::default();
        let mut last_seq = 0;
        let mut len = 0;
        for path in &segments {
            let bytes = std::fs::read(path).map_err(io(path))?;
            let (records, valid) = scan(&bytes);
            recovery.records += records.len();
            last_seq = records.last().map_or(last_seq, |r| r.seq);
            if valid < bytes.len() {
                recovery.cut_bytes += (bytes.len() - valid) as u64;
                let f = OpenOptions::new()
                    .write(true)
                    .open(path)
                    .map_err(io(path))?;
                f.set_len(valid as u64).map_err(io(path))?;
                f.sync_all().map_err(io(path))?;
            }
            len = valid as u64;
        }
        let id = if segments.is_empty() {
            new_identity(dir)?
        } else {
            read_identity(dir)?
        };
        // A number the fleet acknowledged is never given again, even if its record was cut
        // (it is stored; a new event under its number would be taken for a copy of it).
        recovery.acked_through = read_acked(dir, id);
        let mut journal = Journal {
            id,
            dir: dir.to_path_buf(),
            segment_bound: bound_bytes / 2,
            file: None,
            segments,
            len,
            next_seq: last_seq.max(recovery.acked_through) + 1,
            dropped: 0,
            scratch: Vec::with_capacity(HEADER + MAX_PAYLOAD),
        };
        if let Some(newest) = journal.segments.last() {
            let f = OpenOptions::new()
                .append(true)
                .open(newest)
                .map_err(io(newest))?;
            journal.file = Some(f);
        }
        Ok((journal, recovery))
    }

    /// The journal's identity.
    pub fn id(&self) -> u64 {
        self.id
    }

    /// Keeps, across restarts, that the fleet has stored every record through `seq`. Written by
    /// rename, not synced: lost in a power cut, the fleet is only sent again what it has.
    pub fn acknowledge(&self, seq: u64) -> Result<(), JournalError> {
        let (path, tmp) = (self.dir.join(ACKED), self.dir.join("acked.tmp"));
        std::fs::write(&tmp, format!("{:016x} {seq}\n", self.id)).map_err(io(&tmp))?;
        std::fs::rename(&tmp, &path).map_err(io(&path))
    }

    /// The sequence number the next record gets.
    pub fn next_seq(&self) -> u64 {
        self.next_seq
    }

    /// Records dropped (the oldest first) to keep the bound, since this journal was opened.
    pub fn dropped(&self) -> u64 {
        self.dropped
    }

    /// Appends `payload`; returns its sequence number once it is on the storage.
    pub fn append(&mut self, payload: &[u8]) -> Result<u64, JournalError> {
        let seq = self.next_seq;
        self.scratch.clear();
        encode(seq, payload, &mut self.scratch)?;
        if self.file.is_none() || self.len + self.scratch.len() as u64 > self.segment_bound {
            self.start_segment(seq)?;
        }
        let path = self.segments.last().cloned().unwrap_or_default();
        let file = self.file.as_mut().ok_or_else(|| JournalError::Io {
            path: path.display().to_string(),
            source: std::io::Error::other("no segment open"),
        })?;
        file.write_all(&self.scratch).map_err(io(&path))?;
        file.sync_data().map_err(io(&path))?;
        self.len += self.scratch.len() as u64;
        self.next_seq += 1;
        Ok(seq)
    }

    /// A new segment starting at `first_seq`; the oldest goes when there would be three.
    fn start_segment(&mut self, first_seq: u64) -> Result<(), JournalError> {
        let path = self.dir.join(segment_name(first_seq));
        let file = OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(io(&path))?;
        // The directory entry is durable before anything is written into it.
        File::open(&self.dir)
            .and_then(|d| d.sync_all())
            .map_err(io(&self.dir))?;
        self.segments.push(path);
        if self.segments.len() > 2 {
            let old = self.segments.remove(0);
            let bytes = std::fs::read(&old).map_err(io(&old))?;
            self.dropped += scan(&bytes).0.len() as u64;
            std::fs::remove_file(&old).map_err(io(&old))?;
        }
        self.file = Some(file);
        self.len = 0;
        Ok(())
    }

    /// Every record kept with a sequence number above `seq`, in order (what to send again to a
    /// fleet that has acknowledged up to `seq`).
    pub fn records_after(&self, seq: u64) -> Result<Vec<Record>, JournalError> {
        let mut out = Vec::new();
        for path in &self.segments {
            let bytes = std::fs::read(path).map_err(io(path))?;
            out.extend(scan(&bytes).0.into_iter().filter(|r| r.seq > seq));
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn three() -> Vec<u8> {
        let mut b = Vec::new();
        for (seq, p) in [(1u64, &b"trip"[..]), (2, b"stall on left_elbow"), (3, b"")] {
            encode(seq, p, &mut b).unwrap();
        }
        b
    }

    #[test]
    fn records_read_back_and_a_cut_anywhere_keeps_exactly_the_whole_ones_before_it() {
        let bytes = three();
        let (records, len) = scan(&bytes);
        assert_eq!(len, bytes.len());
        assert_eq!(records.iter().map(|r| r.seq).collect::<Vec<_>>(), [1, 2, 3]);
        assert_eq!(records[1].payload, b"stall on left_elbow");
        let ends = [HEADER + 4, 2 * HEADER + 4 + 19, bytes.len()];
        for cut in 0..bytes.len() {
            let (records, len) = scan(&bytes[..cut]);
            let whole = ends.iter().filter(|&&e| e <= cut).count();
            assert_eq!(records.len(), whole, "cut at {cut}");
            assert_eq!(len, if whole == 0 { 0 } else { ends[whole - 1] });
        }
    }

    #[test]
    fn a_damaged_record_ends_the_journal_where_it_starts() {
        let bytes = three();
        let second = HEADER + 4;
        for at in second..second + HEADER + 19 {
            let mut damaged = bytes.clone();
            damaged[at] ^= 0x40;
            let (records, len) = scan(&damaged);
            assert_eq!((records.len(), len), (1, second), "byte {at} flipped");
        }
        // A record that repeats an earlier sequence number (a copy) is no record.
        let mut copy = bytes[..second].to_vec();
        encode(1, b"again", &mut copy).unwrap();
        assert_eq!(scan(&copy).0.len(), 1);
        assert!(matches!(
            encode(1, &[0; MAX_PAYLOAD + 1], &mut Vec::new()),
            Err(JournalError::TooLarge { .. })
        ));
    }

    fn scratch(tag: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("nori-journal-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn a_power_cut_at_any_byte_keeps_every_whole_record_and_the_sequence_goes_on() {
        let dir = scratch("cut");
        let (mut j, rec) = Journal::open(&dir, 64 * 1024).unwrap();
        assert_eq!((rec, j.next_seq()), (Recovery::default(), 1));
        let id = j.id();
        for k in 0..5u8 {
            assert_eq!(j.append(&[k; 10]).unwrap(), u64::from(k) + 1);
        }
        drop(j);
        let segment = dir.join(segment_name(1));
        let full = std::fs::read(&segment).unwrap();
        let record = HEADER + 10;
        for cut in 0..full.len() {
            std::fs::write(&segment, &full[..cut]).unwrap();
            let (mut j, rec) = Journal::open(&dir, 64 * 1024).unwrap();
            let whole = cut / record;
            assert_eq!(rec.records, whole, "cut at {cut}");
            assert_eq!(rec.cut_bytes, (cut - whole * record) as u64);
            assert_eq!(
                std::fs::metadata(&segment).unwrap().len(),
                (whole * record) as u64
            );
            // What comes next follows the last whole record, and reads back.
            let seq = j.append(b"after").unwrap();
            assert_eq!(seq, whole as u64 + 1);
            assert_eq!(j.id(), id, "the same journal, under its name");
            let back = j.records_after(0).unwrap();
            assert_eq!(back.len(), whole + 1);
            assert_eq!(back.last().unwrap().payload, b"after");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn the_bound_drops_the_oldest_first_and_what_is_kept_is_contiguous() {
        let dir = scratch("bound");
        let (mut j, _) = Journal::open(&dir, MIN_BOUND).unwrap();
        let payload = [7u8; 1000];
        for _ in 0..40 {
            j.append(&payload).unwrap();
        }
        let kept = j.records_after(0).unwrap();
        let seqs: Vec<u64> = kept.iter().map(|r| r.seq).collect();
        assert_eq!(*seqs.last().unwrap(), 40, "the newest kept");
        assert!(seqs.windows(2).all(|w| w[1] == w[0] + 1), "{seqs:?}");
        assert_eq!(
            j.dropped(),
            40 - kept.len() as u64,
            "every dropped one counted"
        );
        assert!(j.dropped() > 0);
        let on_disk: u64 = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap())
            .filter(|e| e.file_name().to_string_lossy().ends_with(".nj"))
            .map(|e| e.metadata().unwrap().len())
            .sum();
        assert!(on_disk <= MIN_BOUND, "{on_disk} bytes on disk");
        assert_eq!(j.records_after(38).unwrap().len(), 2);
        // Reopened: the same records, the sequence after them.
        drop(j);
        let (j, rec) = Journal::open(&dir, MIN_BOUND).unwrap();
        assert_eq!((rec.records, j.next_seq()), (kept.len(), 41));
        assert!(matches!(
            Journal::open(&dir, 100),
            Err(JournalError::Bound { bytes: 100 })
        ));
        let _ = std::fs::remove_dir_all(&dir);
    }
}

#[cfg(test)]
mod identity {
    use super::*;

    fn scratch(tag: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("nori-journal-id-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    #[test]
    fn the_acknowledgement_survives_a_restart_for_its_own_journal_only() {
        let dir = scratch("ack");
        let (mut j, _) = Journal::open(&dir, MIN_BOUND).unwrap();
        for _ in 0..5 {
            j.append(b"e").unwrap();
        }
        j.acknowledge(3).unwrap();
        let id = j.id();
        drop(j);
        let (j, rec) = Journal::open(&dir, MIN_BOUND).unwrap();
        assert_eq!((j.id(), rec.acked_through, rec.records), (id, 3, 5));
        // Records cut after the fleet acknowledged them (a damaged disk): their numbers are
        // not given again.
        j.acknowledge(9).unwrap();
        drop(j);
        let (j, rec) = Journal::open(&dir, MIN_BOUND).unwrap();
        assert_eq!((rec.acked_through, j.next_seq()), (9, 10));
        drop(j);
        // Another journal's acknowledgement is not this one's.
        std::fs::write(dir.join(ACKED), format!("{:016x} 4\n", id ^ 1)).unwrap();
        assert_eq!(Journal::open(&dir, MIN_BOUND).unwrap().1.acked_through, 0);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_wiped_journal_starts_under_a_new_name_and_records_without_one_are_refused() {
        let dir = scratch("wipe");
        let (mut j, _) = Journal::open(&dir, MIN_BOUND).unwrap();
        j.append(b"e").unwrap();
        let id = j.id();
        drop(j);
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.extension().is_some_and(|x| x == "nj") {
                std::fs::remove_file(p).unwrap();
            }
        }
        let (j, _) = Journal::open(&dir, MIN_BOUND).unwrap();
        assert_ne!(j.id(), id, "numbers from 1 again, under a new name");
        assert_eq!(j.next_seq(), 1);
        let mut j = j;
        j.append(b"e").unwrap();
        drop(j);
        std::fs::write(dir.join(IDENTITY), "not hex").unwrap();
        assert!(matches!(
            Journal::open(&dir, MIN_BOUND),
            Err(JournalError::Identity { .. })
        ));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
