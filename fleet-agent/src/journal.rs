//! The robot's event journal: an append-only, bounded, crash-safe file of the events the agent
//! sends to the fleet, each under a sequence number that rises across restarts, so that what an
//! outage or a crash of the agent kept from the fleet can be sent again and de-duplicated there.
//! (This is the journal itself; its delivery with acknowledgements is the next part of the
//! fleet-at-scale work.)
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
pub enum JournalError {
    /// Reading, writing, syncing or listing the journal's files failed.
    #[error("event journal {path}: {source}")]
    Io {
        /// The file or directory.
        path: String,
        /// Cause.
        source: std::io::Error,
    },
    /// A payload over [`MAX_PAYLOAD`].
    #[error("an event of {len} bytes is over the journal's {MAX_PAYLOAD}-byte records")]
    TooLarge {
        /// Its length.
        len: usize,
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
}

/// The journal in a directory of its own.
#[derive(Debug)]
pub struct Journal {
    dir: PathBuf,
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
        let mut journal = Journal {
            dir: dir.to_path_buf(),
            segment_bound: bound_bytes / 2,
            file: None,
            segments,
            len,
            next_seq: last_seq + 1,
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
        for k in 0..5u8 {
            assert_eq!(j.append(&[k; 10]).unwrap(), u64::from(k) + 1);
        }
        drop(j);
        let segment = std::fs::read_dir(&dir)
            .unwrap()
            .next()
            .unwrap()
            .unwrap()
            .path();
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
            .map(|e| e.unwrap().metadata().unwrap().len())
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
