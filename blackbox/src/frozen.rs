//! A frozen box: an MCAP file written chunk by chunk while its window is open (each finished
//! chunk flushed and synced, so a `kill -9` or a power cut leaves every finished chunk
//! readable), finished with its summary when the window closes; read back linearly, which a
//! box cut short still allows, and recovered into a whole file at the next start.

use crate::channel::{Channel, EventMessage};
use crate::ring::Record;
use std::collections::BTreeMap;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// The suffix of a box still being written (or cut short).
pub const PARTIAL_SUFFIX: &str = ".mcap.partial";

/// A box that cannot be written or read.
#[derive(Debug, Error)]
pub enum BoxError {
    /// The MCAP layer refused.
    #[error("MCAP: {0}")]
    Mcap(#[from] mcap::McapError),
    /// The file could not be written or read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The system's error.
        source: std::io::Error,
    },
}

/// What froze a box, as its metadata says.
pub const METADATA_NAME: &str = "nori.blackbox";

/// A file whose `flush` also syncs its data to the device: the MCAP writer flushes after each
/// finished chunk, so a finished chunk is on the card before the next one starts.
pub struct Durable {
    file: BufWriter<std::fs::File>,
}

impl Durable {
    /// Creates `path`.
    pub fn create(path: &Path) -> Result<Durable, BoxError> {
        let file = std::fs::File::create(path).map_err(|source| BoxError::Io {
            path: path.into(),
            source,
        })?;
        Ok(Durable {
            file: BufWriter::with_capacity(64 * 1024, file),
        })
    }
}

impl Write for Durable {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.file.write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.file.flush()?;
        self.file.get_ref().sync_data()
    }
}

impl Seek for Durable {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        self.file.seek(pos)
    }
}

/// A box being written.
pub struct BoxWriter<W: Write + Seek> {
    mcap: mcap::Writer<W>,
    channels: BTreeMap<Channel, u16>,
    /// The cameras its thumbnails are of (`Channel::Thumbnail(k)` is `cameras[k]`'s).
    cameras: Vec<String>,
    /// The offset from the robot's monotonic clock to the wall clock, ns (MCAP times are wall
    /// times, so a viewer shows when it happened; the messages keep the monotonic stamps).
    wall_offset_ns: i128,
    sequence: u32,
    /// Messages written.
    pub messages: u64,
}

impl<W: Write + Seek> BoxWriter<W> {
    /// Starts a box on `w`, with the event that froze it as its metadata.
    pub fn new(
        w: W,
        trigger: &EventMessage,
        robot: &str,
        wall_offset_ns: i128,
    ) -> Result<Self, BoxError> {
        BoxWriter::with_cameras(w, trigger, robot, wall_offset_ns, &[])
    }

    /// [`BoxWriter::new`], for a recorder whose thumbnails are of `cameras` (kept in the
    /// metadata: a reader names each thumbnail topic's camera from it).
    pub fn with_cameras(
        w: W,
        trigger: &EventMessage,
        robot: &str,
        wall_offset_ns: i128,
        cameras: &[String],
    ) -> Result<Self, BoxError> {
        let options = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .chunk_size(Some(256 * 1024))
            .compression_threads(0)
            .profile("")
            .library(concat!("nori-blackbox ", env!("CARGO_PKG_VERSION")));
        let mut mcap = options.create(w)?;
        let metadata = mcap::records::Metadata {
            name: METADATA_NAME.into(),
            metadata: BTreeMap::from([
                ("robot".to_string(), robot.to_string()),
                ("trigger".to_string(), trigger.kind.clone()),
                ("event".to_string(), crate::channel::to_json_string(trigger)),
                ("wall_offset_ns".to_string(), wall_offset_ns.to_string()),
                (
                    "cameras".to_string(),
                    crate::channel::to_json_string(&cameras),
                ),
            ]),
        };
        mcap.write_metadata(&metadata)?;
        Ok(BoxWriter {
            mcap,
            channels: BTreeMap::new(),
            cameras: cameras.to_vec(),
            wall_offset_ns,
            sequence: 0,
            messages: 0,
        })
    }

    fn channel_id(&mut self, c: Channel) -> Result<u16, BoxError> {
        if let Some(&id) = self.channels.get(&c) {
            return Ok(id);
        }
        let schema = self
            .mcap
            .add_schema(c.schema_name(), "jsonschema", c.schema().as_bytes())?;
        let id =
            self.mcap
                .add_channel(schema, &c.topic_in(&self.cameras), "json", &BTreeMap::new())?;
        self.channels.insert(c, id);
        Ok(id)
    }

    /// Writes one message.
    pub fn write(&mut self, r: Record) -> Result<(), BoxError> {
        let id = self.channel_id(r.channel)?;
        let wall = (r.t_ns as i128 + self.wall_offset_ns).max(0) as u64;
        self.sequence = self.sequence.wrapping_add(1);
        self.mcap.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id: id,
                sequence: self.sequence,
                log_time: wall,
                publish_time: wall,
            },
            r.data,
        )?;
        self.messages += 1;
        Ok(())
    }

    /// Ends the chunk in progress and syncs it: everything written so far survives a crash.
    pub fn flush(&mut self) -> Result<(), BoxError> {
        self.mcap.flush()?;
        Ok(())
    }

    /// Writes the summary and the footer.
    pub fn finish(mut self) -> Result<W, BoxError> {
        self.mcap.finish()?;
        Ok(self.mcap.into_inner())
    }
}

/// One message read back from a box.
#[derive(Debug, Clone, PartialEq)]
pub struct Message {
    /// Its channel (`None`: a topic this version does not know, or a thumbnail of a camera
    /// the box's metadata does not name).
    pub channel: Option<Channel>,
    /// Its topic.
    pub topic: String,
    /// Its log time (wall clock), ns.
    pub log_time: u64,
    /// Its JSON.
    pub data: Vec<u8>,
}

/// A box read back whole into memory (a small one: tests and tools; [`visit`] streams).
#[derive(Debug, Clone, Default)]
pub struct ReadBox {
    /// Its metadata (what froze it).
    pub metadata: BTreeMap<String, String>,
    /// Its messages, in file order.
    pub messages: Vec<Message>,
    /// How far it could be read.
    pub extent: Extent,
}

/// How far a box could be read.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct Extent {
    /// It ends with its footer (a box cut short by a crash does not: its finished chunks are
    /// all read).
    pub complete: bool,
    /// Chunks that could not be read (damaged: a checksum, a decompression or a record that
    /// fails), their messages lost and counted here.
    pub bad_chunks: usize,
    /// The reading stopped at its budget of bytes decompressed (`visit_within`).
    pub cut_at_budget: bool,
}

/// The largest chunk a box is read with, uncompressed (ours are 256 kB; other tools' up to a
/// few MB).
pub const MAX_CHUNK_BYTES: u64 = 16 << 20;

/// One thing read from a box, in file order.
#[derive(Debug, Clone, Copy)]
pub enum Item<'a> {
    /// The box's metadata (what froze it).
    Metadata(&'a BTreeMap<String, String>),
    /// One message.
    Message {
        /// Its topic.
        topic: &'a str,
        /// Its log time (wall clock), ns.
        log_time: u64,
        /// Its JSON.
        data: &'a [u8],
    },
}

/// Reads a box linearly, as far as it is whole, handing each item to `f` as it is decoded
/// (one chunk in memory at a time).
pub fn visit(bytes: &[u8], f: &mut dyn FnMut(Item)) -> Extent {
    visit_within(bytes, u64::MAX, f)
}

/// [`visit`], stopping once `budget` bytes have been decompressed: a box from outside (the
/// fleet's store reads every robot's) costs bounded time, however far it decompresses.
pub fn visit_within(bytes: &[u8], budget: u64, f: &mut dyn FnMut(Item)) -> Extent {
    use mcap::records::Record as R;
    let mut extent = Extent::default();
    let mut spent = 0u64;
    let mut topics: BTreeMap<u16, String> = BTreeMap::new();
    let options = mcap::read::Options::IgnoreEndMagic.into();
    let Ok(reader) = mcap::read::LinearReader::new_with_options(bytes, options) else {
        return extent;
    };
    fn message(
        f: &mut dyn FnMut(Item),
        topics: &BTreeMap<u16, String>,
        id: u16,
        log_time: u64,
        data: &[u8],
    ) {
        let topic = topics.get(&id).map_or("", String::as_str);
        f(Item::Message {
            topic,
            log_time,
            data,
        })
    }
    for record in reader {
        let Ok(record) = record else { break };
        match record {
            R::Channel(c) => {
                topics.insert(c.id, c.topic.clone());
            }
            R::Metadata(m) if m.name == METADATA_NAME => f(Item::Metadata(&m.metadata)),
            R::Message { header, data } => {
                message(f, &topics, header.channel_id, header.log_time, &data)
            }
            R::Chunk { header, data } => {
                // A damaged chunk is skipped before it is counted (its header's size may be
                // anything); a sound one is at most MAX_CHUNK_BYTES decompressed.
                let Some(raw) = chunk_bytes(&header, &data) else {
                    extent.bad_chunks += 1;
                    continue;
                };
                spent = spent.saturating_add(raw.len() as u64);
                if spent > budget {
                    extent.cut_at_budget = true;
                    break;
                }
                for r in mcap::read::LinearReader::sans_magic(&raw) {
                    match r {
                        Ok(R::Channel(c)) => {
                            topics.insert(c.id, c.topic.clone());
                        }
                        Ok(R::Message { header, data }) => {
                            message(f, &topics, header.channel_id, header.log_time, &data)
                        }
                        Ok(_) => {}
                        Err(_) => {
                            extent.bad_chunks += 1;
                            break;
                        }
                    }
                }
            }
            R::Footer(_) => extent.complete = true,
            _ => {}
        }
    }
    extent
}

/// A chunk's records, decompressed and checked against its checksum; `None` if it is damaged.
/// Done here rather than by `mcap`'s chunk reader, which trusts the lengths inside a damaged
/// chunk (seen: an abort asking for 7·10¹⁸ bytes on one flipped byte).
fn chunk_bytes(header: &mcap::records::ChunkHeader, data: &[u8]) -> Option<Vec<u8>> {
    if header.uncompressed_size > MAX_CHUNK_BYTES || header.compressed_size != data.len() as u64 {
        return None;
    }
    let raw = match header.compression.as_str() {
        "" => data.to_vec(),
        "zstd" => zstd::bulk::decompress(data, header.uncompressed_size as usize).ok()?,
        _ => return None,
    };
    let sound = raw.len() as u64 == header.uncompressed_size
        && (header.uncompressed_crc == 0 || crc32fast::hash(&raw) == header.uncompressed_crc);
    sound.then_some(raw)
}

/// The cameras a box's metadata says its thumbnails are of (none in a box from before them,
/// or whose list does not parse: its thumbnails are then no channel of this version's). At most
/// [`MAX_CAMERAS`](crate::channel::MAX_CAMERAS) are taken.
pub fn cameras(metadata: &BTreeMap<String, String>) -> Vec<String> {
    let mut names: Vec<String> = metadata
        .get("cameras")
        .and_then(|c| serde_json::from_str(c).ok())
        .unwrap_or_default();
    names.truncate(crate::channel::MAX_CAMERAS);
    names
}

/// Reads a box whole into memory.
pub fn read(bytes: &[u8]) -> ReadBox {
    let mut out = ReadBox::default();
    let mut names = Vec::new();
    out.extent = visit(bytes, &mut |item| match item {
        Item::Metadata(m) => {
            out.metadata = m.clone();
            names = cameras(m);
        }
        Item::Message {
            topic,
            log_time,
            data,
        } => out.messages.push(Message {
            channel: Channel::from_topic_in(topic, &names),
            topic: topic.into(),
            log_time,
            data: data.to_vec(),
        }),
    });
    out
}

/// The metadata of a box (what froze it), read as far as it goes.
pub fn metadata(bytes: &[u8]) -> BTreeMap<String, String> {
    let mut out = BTreeMap::new();
    visit(bytes, &mut |item| {
        if let Item::Metadata(m) = item {
            out = m.clone();
        }
    });
    out
}

/// A box made whole by [`recover`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Recovered {
    /// The whole box.
    pub path: PathBuf,
    /// Messages it holds.
    pub messages: usize,
    /// Chunks of the cut box that could not be read.
    pub bad_chunks: usize,
}

/// Rewrites a box cut short (`NAME.mcap.partial`) into a whole `NAME.mcap` holding everything
/// a linear read gets from it (one chunk decoded at a time), and keeps the cut file beside it as
/// `NAME.mcap.cut`: a read stops at the first record it cannot parse, and what lies after a
/// damaged stretch (a power cut mid-write) may still be read by other means. The shelf's cap
/// removes it in its turn.
pub fn recover(partial: &Path) -> Result<Recovered, BoxError> {
    let io = |source| BoxError::Io {
        path: partial.into(),
        source,
    };
    let bytes = std::fs::read(partial).map_err(io)?;
    let meta = metadata(&bytes);
    let stem = partial.to_string_lossy();
    let stem = stem.trim_end_matches(PARTIAL_SUFFIX);
    let whole = PathBuf::from(format!("{stem}.mcap"));
    let trigger: EventMessage = meta
        .get("event")
        .and_then(|e| serde_json::from_str(e).ok())
        .unwrap_or(EventMessage {
            timestamp_ns: 0,
            kind: "unknown".into(),
            joint: None,
            bus: None,
            level: 0,
            value: 0.0,
        });
    let robot = meta.get("robot").cloned().unwrap_or_default();
    let offset: i128 = meta
        .get("wall_offset_ns")
        .and_then(|o| o.parse().ok())
        .unwrap_or(0);
    let tmp = PathBuf::from(format!("{stem}.mcap.recovering"));
    let names = cameras(&meta);
    let mut w = BoxWriter::with_cameras(Durable::create(&tmp)?, &trigger, &robot, offset, &names)?;
    let (mut messages, mut failed) = (0, None);
    let extent = visit(&bytes, &mut |item| {
        let Item::Message {
            topic,
            log_time,
            data,
        } = item
        else {
            return;
        };
        let Some(channel) = Channel::from_topic_in(topic, &names) else {
            return;
        };
        if failed.is_none() {
            let t_ns = (log_time as i128 - offset).max(0) as u64;
            failed = w
                .write(Record {
                    channel,
                    t_ns,
                    data,
                })
                .err();
            messages += 1;
        }
    });
    if let Some(e) = failed {
        return Err(e);
    }
    w.finish()?.flush().map_err(io)?;
    std::fs::rename(&tmp, &whole).map_err(io)?;
    std::fs::rename(partial, format!("{stem}.mcap.cut")).map_err(io)?;
    Ok(Recovered {
        path: whole,
        messages,
        bad_chunks: extent.bad_chunks,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;

    fn trigger() -> EventMessage {
        EventMessage {
            timestamp_ns: 50,
            kind: "thermal_trip".into(),
            joint: Some("left_elbow".into()),
            bus: Some("left_arm".into()),
            level: 0,
            value: 59.0,
        }
    }

    fn two_cameras() -> Vec<String> {
        vec!["head".into(), "left_wrist".into()]
    }

    /// `n` messages, one in ten a thumbnail of the left wrist's.
    fn write_box(n: u64, flush_every: u64) -> (Vec<u8>, Vec<usize>) {
        let cursor = Cursor::new(Vec::new());
        let mut w =
            BoxWriter::with_cameras(cursor, &trigger(), "r1", 1_000, &two_cameras()).unwrap();
        let mut flushed_at = Vec::new();
        for t in 0..n {
            let data = format!("{{\"timestamp_ns\": {t}}}");
            w.write(Record {
                channel: match t % 10 {
                    9 => Channel::Thumbnail(1),
                    t if t % 2 == 0 => Channel::Wire,
                    _ => Channel::JointStates,
                },
                t_ns: t,
                data: data.as_bytes(),
            })
            .unwrap();
            if (t + 1) % flush_every == 0 {
                w.flush().unwrap();
                flushed_at.push(t as usize + 1);
            }
        }
        (w.finish().unwrap().into_inner(), flushed_at)
    }

    #[test]
    fn a_box_reads_back_whole_with_its_trigger_and_wall_times() {
        let (bytes, _) = write_box(100, 30);
        let b = read(&bytes);
        assert!(b.extent.complete);
        assert_eq!(b.metadata["trigger"], "thermal_trip");
        let event: EventMessage = serde_json::from_str(&b.metadata["event"]).unwrap();
        assert_eq!(event, trigger());
        assert_eq!(b.messages.len(), 100);
        assert_eq!(b.messages[3].channel, Some(Channel::JointStates));
        assert_eq!(b.messages[3].log_time, 1_003);
        assert_eq!(b.messages[3].data, b"{\"timestamp_ns\": 3}");
        assert_eq!(cameras(&b.metadata), two_cameras());
        assert_eq!(b.messages[9].channel, Some(Channel::Thumbnail(1)));
        assert_eq!(b.messages[9].topic, "/camera/left_wrist/thumbnail");
    }

    #[test]
    fn a_box_cut_anywhere_keeps_every_finished_chunk() {
        let (bytes, flushed_at) = write_box(100, 30);
        let whole = read(&bytes);
        let mut cuts_seen = 0;
        // Cut the file at every length: what was flushed before the cut is all there, in order.
        for len in (0..bytes.len()).step_by(7) {
            let cut = read(&bytes[..len]);
            assert!(!cut.extent.complete || len + 200 > bytes.len(), "{len}");
            assert_eq!(cut.extent.bad_chunks, 0, "a cut chunk is not a damaged one");
            assert_eq!(cut.messages[..], whole.messages[..cut.messages.len()]);
            if cut.messages.len() >= 30 {
                cuts_seen += 1;
            }
        }
        assert!(cuts_seen > 0);
        // A cut just after the first flushed chunk keeps exactly its messages.
        let first_chunk_end = (0..bytes.len())
            .find(|&len| read(&bytes[..len]).messages.len() == flushed_at[0])
            .unwrap();
        assert!(first_chunk_end < bytes.len() / 2);
    }

    #[test]
    fn a_damaged_chunk_is_counted_and_the_chunks_after_it_still_read() {
        let (bytes, _) = write_box(100, 30);
        let whole = read(&bytes).messages.len();
        let mut counted = 0;
        for at in (bytes.len() / 8..bytes.len() / 2).step_by(3) {
            let mut damaged = bytes.clone();
            damaged[at] ^= 0x55;
            let b = read(&damaged);
            assert!(b.messages.len() <= whole);
            if b.extent.bad_chunks > 0 && b.messages.len() >= 30 && b.extent.complete {
                counted += 1;
            }
        }
        assert!(
            counted > 10,
            "{counted} damaged chunks counted with the rest read"
        );
    }

    #[test]
    fn a_partial_box_is_recovered_into_a_whole_one() {
        let dir = std::env::temp_dir().join(format!("nori-bb-recover-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (bytes, flushed_at) = write_box(100, 30);
        let cut_len = (0..bytes.len())
            .find(|&len| read(&bytes[..len]).messages.len() == flushed_at[1])
            .unwrap();
        let partial = dir.join(format!("box{PARTIAL_SUFFIX}"));
        std::fs::write(&partial, &bytes[..cut_len + 5]).unwrap();
        let r = recover(&partial).unwrap();
        assert_eq!((r.messages, r.bad_chunks), (60, 0));
        assert!(!partial.exists());
        let cut = dir.join("box.mcap.cut");
        assert_eq!(
            std::fs::read(&cut).unwrap(),
            bytes[..cut_len + 5],
            "the cut file kept"
        );
        let b = read(&std::fs::read(&r.path).unwrap());
        assert!(b.extent.complete);
        assert_eq!(b.messages.len(), 60);
        assert_eq!(b.metadata["trigger"], "thermal_trip");
        assert_eq!(b.messages[59].log_time, 1_059);
        // The thumbnails keep their camera's topic.
        let cut_box = read(&bytes[..cut_len + 5]);
        assert_eq!(b.messages, cut_box.messages);
        assert_eq!(
            b.messages
                .iter()
                .filter(|m| m.channel == Some(Channel::Thumbnail(1)))
                .count(),
            6
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
