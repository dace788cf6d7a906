//! The black box's shelf as the agent sees it: the I/O beside the pure [`crate::box_upload`].
//! A thread of its own lists the finished boxes, hashes each new one (SHA-256, its identity at
//! the store) and reads the chunks the agent asks for, so the agent's loop, which forwards
//! goals, never waits on the SD card. The shelf is only read: the recorder alone removes boxes
//! (its cap).

use crate::box_upload::{ChunkToSend, ShelvedBox};
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::mpsc::{sync_channel, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::time::{Duration, Instant};
use thiserror::Error;

/// A chunk that could not be read.
#[derive(Debug, Error)]
pub enum ShelfError {
    /// The file could not be opened or read.
    #[error("box {name}: {source}")]
    Io {
        /// The box's file name.
        name: String,
        /// The system's error.
        source: std::io::Error,
    },
    /// The file is not the size it was listed with (rewritten, or being removed).
    #[error("box {name}: {now} bytes, listed with {listed}")]
    Changed {
        /// The box's file name.
        name: String,
        /// Its size when listed.
        listed: u64,
        /// Its size now.
        now: u64,
    },
}

/// A chunk read, or why it could not be.
pub type ChunkRead = (ChunkToSend, Result<Vec<u8>, ShelfError>);

/// The shelf watched by its thread.
#[derive(Debug)]
pub struct ShelfWatch {
    listings: Receiver<Vec<ShelvedBox>>,
    requests: SyncSender<ChunkToSend>,
    reads: Receiver<ChunkRead>,
}

impl ShelfWatch {
    /// Watches `dir`, listing it every `every` and reading the chunks asked for meanwhile (the
    /// thread ends with the watch).
    pub fn spawn(dir: PathBuf, every: Duration) -> std::io::Result<ShelfWatch> {
        // One listing in flight: a loop that has not taken the last gets the next one later.
        let (listing_tx, listings) = sync_channel(1);
        let (requests, asked) = sync_channel::<ChunkToSend>(1);
        let (read_tx, reads) = sync_channel(1);
        std::thread::Builder::new()
            .name("box-shelf".into())
            .spawn(move || {
                let mut digests = Digests::default();
                let mut sent: Option<Vec<ShelvedBox>> = None;
                let mut next_listing = Instant::now();
                loop {
                    let wait = next_listing.saturating_duration_since(Instant::now());
                    match asked.recv_timeout(wait) {
                        Ok(chunk) => {
                            let read = read_chunk(&dir, &chunk);
                            if read_tx.send((chunk, read)).is_err() {
                                return;
                            }
                            continue;
                        }
                        Err(RecvTimeoutError::Timeout) => {}
                        Err(RecvTimeoutError::Disconnected) => return,
                    }
                    next_listing = Instant::now() + every;
                    let listing = digests.list(&dir);
                    if sent.as_ref() != Some(&listing) {
                        match listing_tx.try_send(listing.clone()) {
                            Ok(()) => sent = Some(listing),
                            Err(TrySendError::Full(_)) => {}
                            Err(TrySendError::Disconnected(_)) => return,
                        }
                    }
                }
            })?;
        Ok(ShelfWatch {
            listings,
            requests,
            reads,
        })
    }

    /// The shelf's newest listing, if it changed since the last call.
    pub fn listing(&self) -> Option<Vec<ShelvedBox>> {
        self.listings.try_iter().last()
    }

    /// Asks for the bytes of `chunk`; whether the thread took the request (one at a time).
    pub fn ask(&self, chunk: &ChunkToSend) -> bool {
        self.requests.try_send(chunk.clone()).is_ok()
    }

    /// A chunk asked for, once read.
    pub fn read(&self) -> Option<ChunkRead> {
        self.reads.try_recv().ok()
    }
}

/// A box file as listed: its number, name, size and modification time (a file rewritten
/// under its name is hashed again).
type Listed = (u64, String, u64, Option<std::time::SystemTime>);

/// The digest of each box already hashed.
#[derive(Debug, Default)]
struct Digests {
    known: HashMap<Listed, [u8; 32]>,
}

impl Digests {
    /// The finished boxes in `dir`, each new one hashed; one that cannot be read whole is left
    /// for the next listing.
    fn list(&mut self, dir: &Path) -> Vec<ShelvedBox> {
        let mut out = Vec::new();
        let mut seen = Vec::new();
        for (number, path, size) in blackbox::shelf::whole_boxes(dir) {
            let Some(name) = path.file_name().and_then(|n| n.to_str()) else {
                continue;
            };
            let modified = std::fs::metadata(&path).and_then(|m| m.modified()).ok();
            let key = (number, name.to_string(), size, modified);
            let digest = match self.known.get(&key) {
                Some(d) => *d,
                None => match hash_file(&path, size) {
                    Ok(d) => *self.known.entry(key.clone()).or_insert(d),
                    Err(e) => {
                        tracing::debug!("box {}: not hashed yet: {e}", path.display());
                        continue;
                    }
                },
            };
            seen.push(key);
            out.push(ShelvedBox {
                number,
                name: name.to_string(),
                size,
                digest,
            });
        }
        self.known.retain(|k, _| seen.contains(k));
        out
    }
}

/// The SHA-256 of the file at `path`, which must be `size` bytes.
fn hash_file(path: &Path, size: u64) -> std::io::Result<[u8; 32]> {
    let mut file = std::fs::File::open(path)?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 64 * 1024];
    let mut total = 0u64;
    loop {
        let n = file.read(&mut buf)?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
        total += n as u64;
    }
    // Read once: its pages need not stay in the agent's share of the memory.
    let _ = nix::fcntl::posix_fadvise(
        &file,
        0,
        0,
        nix::fcntl::PosixFadviseAdvice::POSIX_FADV_DONTNEED,
    );
    if total != size {
        return Err(std::io::Error::other(format!(
            "{total} bytes, listed with {size}"
        )));
    }
    Ok(hasher.finalize().into())
}

/// The bytes of `chunk` from the box in `dir`.
fn read_chunk(dir: &Path, chunk: &ChunkToSend) -> Result<Vec<u8>, ShelfError> {
    let io = |source| ShelfError::Io {
        name: chunk.name.clone(),
        source,
    };
    let mut file = std::fs::File::open(dir.join(&chunk.name)).map_err(io)?;
    let now = file.metadata().map_err(io)?.len();
    if now != chunk.size {
        return Err(ShelfError::Changed {
            name: chunk.name.clone(),
            listed: chunk.size,
            now,
        });
    }
    file.seek(SeekFrom::Start(chunk.offset)).map_err(io)?;
    let mut data = vec![0u8; usize::try_from(chunk.len).unwrap_or(0)];
    file.read_exact(&mut data).map_err(io)?;
    Ok(data)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    fn scratch(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("nori-box-shelf-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn finished_boxes_are_listed_with_their_digest_and_read_by_chunk() {
        let dir = scratch("list");
        let bytes: Vec<u8> = (0..1000u32).map(|i| (i * 7) as u8).collect();
        std::fs::write(dir.join("000002-T-thermal_trip.mcap"), &bytes).unwrap();
        std::fs::write(dir.join("000003-T-saved.mcap.partial"), b"being written").unwrap();
        std::fs::write(dir.join("export.csv"), b"an operator's").unwrap();
        let mut digests = Digests::default();
        let listing = digests.list(&dir);
        assert_eq!(listing.len(), 1, "{listing:?}");
        let b = &listing[0];
        assert_eq!((b.number, b.size), (2, 1000));
        let expected: [u8; 32] = Sha256::digest(&bytes).into();
        assert_eq!(b.digest, expected);
        let chunk = ChunkToSend {
            number: 2,
            name: b.name.clone(),
            size: 1000,
            digest: b.digest,
            offset: 900,
            len: 100,
        };
        assert_eq!(read_chunk(&dir, &chunk).unwrap(), &bytes[900..]);
        // Rewritten at the same size: hashed again, another box.
        std::thread::sleep(Duration::from_millis(20));
        let other: Vec<u8> = bytes.iter().map(|b| b ^ 1).collect();
        std::fs::write(dir.join(&b.name), &other).unwrap();
        let again = digests.list(&dir);
        let expected: [u8; 32] = Sha256::digest(&other).into();
        assert_eq!(again[0].digest, expected);
        std::fs::write(dir.join(&b.name), &bytes).unwrap();
        // Rewritten under its name: refused, not sent as the box it was.
        std::fs::write(dir.join(&b.name), b"short").unwrap();
        assert!(matches!(
            read_chunk(&dir, &chunk),
            Err(ShelfError::Changed { now: 5, .. })
        ));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_thread_hands_over_each_new_listing_and_the_chunks_asked_for() {
        let dir = scratch("thread");
        let watch = ShelfWatch::spawn(dir.clone(), Duration::from_millis(5)).unwrap();
        std::fs::write(dir.join("000001-T-saved.mcap"), b"box").unwrap();
        let mut got = None;
        for _ in 0..2000 {
            if let Some(l) = watch.listing().filter(|l| !l.is_empty()) {
                got = Some(l);
                break;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        let b = got.unwrap().remove(0);
        assert_eq!(b.name, "000001-T-saved.mcap");
        let chunk = ChunkToSend {
            number: 1,
            name: b.name,
            size: 3,
            digest: b.digest,
            offset: 1,
            len: 2,
        };
        assert!(watch.ask(&chunk));
        let mut read = None;
        for _ in 0..2000 {
            read = watch.read();
            if read.is_some() {
                break;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        let (asked, bytes) = read.unwrap();
        assert_eq!((asked, bytes.unwrap()), (chunk, b"ox".to_vec()));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
