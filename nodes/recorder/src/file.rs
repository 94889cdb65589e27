//! Recordings on disk: an MCAP file with profile `ros2`, one channel per edge (two for a
//! message with two images), CDR messages, zstd chunks.
//!
//! Each channel's metadata names the edge (`microstereo.edge` = `NODE/OUTPUT`), its message
//! kind and the side; each MCAP message carries the frame number as its `sequence` and the
//! capture time as its `publish_time`, so that [`EdgeReader`] gives back exactly the header
//! and payload the node sent. The launch file of the run is stored as a metadata record.

use crate::ros2::{self, MsgType};
use crate::scene;
use mcap::records::MessageHeader;
use schemas::{FrameHeader, MessageKind};
use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Channel metadata key: the edge, `NODE/OUTPUT`.
pub const META_EDGE: &str = "microstereo.edge";
/// Channel metadata key: the message kind's name.
pub const META_KIND: &str = "microstereo.kind";
/// Channel metadata key: `left` or `right` for one image of a two-image message.
pub const META_SIDE: &str = "microstereo.side";
/// Name of the metadata record holding the run's launch file (`text`, `path`).
pub const META_LAUNCH: &str = "microstereo.launch";

/// How often the writer ends its chunk and flushes it to disk at the latest.
pub const FLUSH_EVERY: Duration = Duration::from_secs(1);

/// The MCAP magic that starts and ends a complete file.
const MAGIC: &[u8; 8] = b"\x89MCAP0\r\n";

/// Why a recording cannot be written or read.
#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    /// The file cannot be opened, created or written.
    #[error("{path}: {what}: {reason}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What was being done.
        what: &'static str,
        /// The system's reason.
        reason: String,
    },
    /// The file is not an MCAP file, or breaks off, or holds a record that cannot be read.
    #[error("{path}: {reason} (after {messages} message(s)){}", if *truncated { "; the file is truncated (no MCAP footer): it was not closed, e.g. its recorder was killed" } else { "" })]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
        /// Messages read before it.
        messages: u64,
        /// The file lacks the MCAP end magic.
        truncated: bool,
    },
    /// A message cannot be turned back into what its edge carried.
    #[error("{path}: channel '{topic}', frame {sequence}: {reason}")]
    Message {
        /// The file.
        path: PathBuf,
        /// Its channel's topic.
        topic: String,
        /// Its frame.
        sequence: u64,
        /// What is wrong.
        reason: String,
    },
}

/// The topic of `edge` (`NODE/OUTPUT`) for `side` and message type `msg`: an image's is
/// `/NODE/OUTPUT[/SIDE]/image`, beside its `camera_info` as ROS tools look for it.
pub fn topic(edge: &str, side: Option<&str>, msg: MsgType) -> String {
    if msg == ros2::IMAGE {
        format!("{}/image", topic_base(edge, side))
    } else {
        topic_base(edge, side)
    }
}

/// `/NODE/OUTPUT[/SIDE]`: where an edge's topics (and a side's) live.
fn topic_base(edge: &str, side: Option<&str>) -> String {
    match side {
        Some(s) => format!("/{edge}/{s}"),
        None => format!("/{edge}"),
    }
}

/// `/tf_static`: the frame tree.
pub const TF_STATIC: &str = "/tf_static";

/// rosbag2's channel metadata key for a topic's QoS.
const QOS: &str = "offered_qos_profiles";

/// Writes edge messages into an MCAP file.
pub struct RecordingWriter {
    path: PathBuf,
    /// Where it is written until [`RecordingWriter::finish`] renames it to `path`.
    part: PathBuf,
    overwrite: bool,
    mcap: mcap::Writer<BufWriter<File>>,
    schemas: HashMap<&'static str, u16>,
    channels: HashMap<(String, Option<&'static str>), u16>,
    /// Channels that are not edges' (the frame tree, CameraInfo, markers), by topic.
    side_channels: HashMap<String, u16>,
    /// The rectified cameras, their image size and the edges whose images are raw, once
    /// [`RecordingWriter::write_cameras`] has given them.
    cameras: Option<(schemas::Calibration, (usize, usize), Vec<String>)>,
    last_flush: Instant,
    /// Edge messages written.
    pub messages: u64,
    /// Bytes of messages written (before compression).
    pub bytes: u64,
}

impl std::fmt::Debug for RecordingWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RecordingWriter")
            .field("path", &self.path)
            .field("messages", &self.messages)
            .finish_non_exhaustive()
    }
}

impl RecordingWriter {
    /// Starts the recording `path`; an existing file is refused unless `overwrite`, so
    /// that no earlier recording is lost by accident. It is written as `path.PID.part`
    /// and renamed to `path` by [`RecordingWriter::finish`]: a recorder that dies leaves
    /// its partial recording (readable up to its last flushed chunk) under that name, and
    /// an earlier file at `path` intact.
    pub fn create(path: &Path, overwrite: bool) -> Result<Self, RecordingError> {
        let exists = || RecordingError::Io {
            path: path.into(),
            what: "creating the recording",
            reason: "the file exists; choose another name or allow overwriting it".into(),
        };
        if !overwrite && path.exists() {
            return Err(exists());
        }
        let mut part = path.as_os_str().to_owned();
        part.push(format!(".{}.part", std::process::id()));
        let part = PathBuf::from(part);
        let file = File::options()
            .write(true)
            .create_new(true)
            .open(&part)
            .map_err(|e| RecordingError::Io {
                path: part.clone(),
                what: "creating the recording",
                reason: io_reason(&e),
            })?;
        let mcap = mcap::WriteOptions::new()
            .profile("ros2")
            .library(concat!("microstereo ", env!("CARGO_PKG_VERSION")))
            .compression(Some(mcap::Compression::Zstd))
            .compression_level(3)
            .chunk_size(Some(8 << 20))
            .create(BufWriter::with_capacity(1 << 20, file))
            .map_err(|e| RecordingError::Io {
                path: path.into(),
                what: "starting the MCAP file",
                reason: mcap_reason(e),
            })?;
        Ok(Self {
            path: path.into(),
            part,
            overwrite,
            mcap,
            schemas: HashMap::new(),
            channels: HashMap::new(),
            side_channels: HashMap::new(),
            cameras: None,
            last_flush: Instant::now(),
            messages: 0,
            bytes: 0,
        })
    }

    fn mcap_err(
        &self,
        what: &'static str,
    ) -> impl FnOnce(mcap::McapError) -> RecordingError + use<> {
        let path = self.path.clone();
        move |e| RecordingError::Io {
            path,
            what,
            reason: mcap_reason(e),
        }
    }

    /// Stores the launch file the graph ran from.
    pub fn write_launch(&mut self, path: &Path, text: &str) -> Result<(), RecordingError> {
        let metadata = BTreeMap::from([
            ("path".to_string(), path.display().to_string()),
            ("text".to_string(), text.to_string()),
        ]);
        let err = self.mcap_err("writing the launch file");
        self.mcap
            .write_metadata(&mcap::records::Metadata {
                name: META_LAUNCH.into(),
                metadata,
            })
            .map_err(err)
    }

    /// Starts the viewers' side of the recording for rectified cameras `calib` of images
    /// `size`: the frame tree on `/tf_static` (latched) now, and from here on each image's
    /// CameraInfo beside it (but for the edges in `raw`, whose images are not rectified),
    /// the scene's markers beside the targets, tracks and the manipulator's state, and
    /// image annotations (outlines, ids, heights) beside the cell lists and targets.
    pub fn write_cameras(
        &mut self,
        calib: &schemas::Calibration,
        size: (usize, usize),
        raw: &[String],
        log_time: u64,
    ) -> Result<(), RecordingError> {
        let tf =
            scene::tf_static(calib.baseline * calib.unit.metres(), log_time).map_err(|reason| {
                RecordingError::Message {
                    path: self.path.clone(),
                    topic: TF_STATIC.into(),
                    sequence: 0,
                    reason,
                }
            })?;
        let meta = BTreeMap::from([(QOS.to_string(), scene::LATCHED_QOS.to_string())]);
        let id = self.side_channel(TF_STATIC, scene::TF_MESSAGE, &meta)?;
        self.write_side(id, 0, log_time, log_time, &tf)?;
        self.cameras = Some((*calib, size, raw.to_vec()));
        Ok(())
    }

    /// The channel of `topic` (not an edge's: readers of edges pass it by), made on first use.
    fn side_channel(
        &mut self,
        topic: &str,
        msg: MsgType,
        meta: &BTreeMap<String, String>,
    ) -> Result<u16, RecordingError> {
        if let Some(&id) = self.side_channels.get(topic) {
            return Ok(id);
        }
        let schema = self.schema(msg)?;
        let err = self.mcap_err("adding a channel");
        let id = self
            .mcap
            .add_channel(schema, topic, "cdr", meta)
            .map_err(err)?;
        self.side_channels.insert(topic.to_string(), id);
        Ok(id)
    }

    fn write_side(
        &mut self,
        channel_id: u16,
        sequence: u64,
        log_time: u64,
        publish_time: u64,
        cdr: &[u8],
    ) -> Result<(), RecordingError> {
        let err = self.mcap_err("writing a message");
        self.mcap
            .write_to_known_channel(
                &MessageHeader {
                    channel_id,
                    sequence: sequence as u32,
                    log_time,
                    publish_time,
                },
                cdr,
            )
            .map_err(err)?;
        self.bytes += cdr.len() as u64;
        Ok(())
    }

    fn schema(&mut self, msg: MsgType) -> Result<u16, RecordingError> {
        if let Some(&id) = self.schemas.get(msg.name) {
            return Ok(id);
        }
        let err = self.mcap_err("adding a schema");
        let id = self
            .mcap
            .add_schema(msg.name, "ros2msg", msg.definition.as_bytes())
            .map_err(err)?;
        self.schemas.insert(msg.name, id);
        Ok(id)
    }

    /// Writes what viewers draw beside edge message `edge` (see [`Self::write_cameras`]).
    fn write_view(
        &mut self,
        edge: &str,
        kind: MessageKind,
        header: &FrameHeader,
        payload: &[u8],
        sides: &[Option<&'static str>],
        log_time: u64,
    ) -> Result<(), RecordingError> {
        let Some((calib, size, raw)) = &self.cameras else {
            return Ok(());
        };
        let bad = |path: &Path, topic: String, reason| RecordingError::Message {
            path: path.into(),
            topic,
            sequence: header.sequence,
            reason,
        };
        if ros2::msg_type(kind) == ros2::IMAGE && !raw.iter().any(|r| r == edge) {
            let (calib, size) = (*calib, *size);
            for side in sides {
                let topic = format!("{}/camera_info", topic_base(edge, *side));
                let cdr =
                    ros2::camera_info(&calib, size, side.unwrap_or("left"), header.capture_ns)
                        .map_err(|r| bad(&self.path, topic.clone(), r))?;
                let id = self.side_channel(&topic, ros2::CAMERA_INFO, &BTreeMap::new())?;
                self.write_side(id, header.sequence, log_time, header.capture_ns, &cdr)?;
            }
        }
        let topic = format!("/{edge}/markers");
        if let Some(cdr) =
            scene::markers(kind, header, payload).map_err(|r| bad(&self.path, topic.clone(), r))?
        {
            let id = self.side_channel(&topic, scene::MARKER_ARRAY, &BTreeMap::new())?;
            self.write_side(id, header.sequence, log_time, header.capture_ns, &cdr)?;
        }
        let drawn = scene::annotations(kind, header, payload)
            .map_err(|r| bad(&self.path, topic_base(edge, None), r))?;
        for (side, cdr) in drawn {
            let topic = format!("{}/annotations", topic_base(edge, Some(side)));
            let id = self.side_channel(&topic, scene::IMAGE_ANNOTATIONS, &BTreeMap::new())?;
            self.write_side(id, header.sequence, log_time, header.capture_ns, &cdr)?;
        }
        Ok(())
    }

    fn channel(
        &mut self,
        edge: &str,
        kind: MessageKind,
        side: Option<&'static str>,
        msg: MsgType,
    ) -> Result<u16, RecordingError> {
        if let Some(&id) = self.channels.get(&(edge.to_string(), side)) {
            return Ok(id);
        }
        let schema = self.schema(msg)?;
        let mut meta = BTreeMap::from([
            (META_EDGE.to_string(), edge.to_string()),
            (META_KIND.to_string(), kind.name().to_string()),
        ]);
        if let Some(s) = side {
            meta.insert(META_SIDE.into(), s.into());
        }
        let err = self.mcap_err("adding a channel");
        let id = self
            .mcap
            .add_channel(schema, &topic(edge, side, msg), "cdr", &meta)
            .map_err(err)?;
        self.channels.insert((edge.to_string(), side), id);
        Ok(id)
    }

    /// Writes one message of `edge` (`NODE/OUTPUT`), received at `log_time` (ns since the
    /// epoch); flushes when the last flush is [`FLUSH_EVERY`] old.
    pub fn write(
        &mut self,
        edge: &str,
        kind: MessageKind,
        header: &FrameHeader,
        payload: &[u8],
        log_time: u64,
    ) -> Result<(), RecordingError> {
        let metres = self.cameras.as_ref().map(|c| c.0.unit.metres());
        let parts = ros2::encode(kind, header, payload, metres).map_err(|reason| {
            RecordingError::Message {
                path: self.path.clone(),
                topic: topic_base(edge, None),
                sequence: header.sequence,
                reason,
            }
        })?;
        let sides: Vec<_> = parts.iter().map(|p| p.side).collect();
        for p in parts {
            let channel_id = self.channel(edge, kind, p.side, p.msg)?;
            // MCAP has 32 bits for the sequence: frame numbers wrap after 2^32 frames.
            self.write_side(
                channel_id,
                header.sequence,
                log_time,
                header.capture_ns,
                &p.cdr,
            )?;
        }
        self.write_view(edge, kind, header, payload, &sides, log_time)?;
        self.messages += 1;
        self.flush_if_due()
    }

    /// Ends the chunk and flushes the file when the last flush is [`FLUSH_EVERY`] old, so
    /// that a writer killed now leaves a file readable up to here.
    pub fn flush_if_due(&mut self) -> Result<(), RecordingError> {
        if self.last_flush.elapsed() >= FLUSH_EVERY {
            let err = self.mcap_err("flushing");
            self.mcap.flush().map_err(err)?;
            self.last_flush = Instant::now();
        }
        Ok(())
    }

    /// Writes the summary and footer and closes the file.
    pub fn finish(mut self) -> Result<(), RecordingError> {
        let err = self.mcap_err("finishing the file");
        self.mcap.finish().map_err(err)?;
        let path = self.path.clone();
        self.mcap
            .into_inner()
            .into_inner()
            .map_err(|e| RecordingError::Io {
                path: path.clone(),
                what: "finishing the file",
                reason: io_reason(&e.into_error()),
            })?
            .sync_all()
            .map_err(|e| RecordingError::Io {
                path: path.clone(),
                what: "syncing the file",
                reason: io_reason(&e),
            })?;
        let part = self.part.display().to_string();
        formats::atomic::commit(&self.part, &path, self.overwrite).map_err(|e| RecordingError::Io {
            path,
            what: "renaming the finished recording into place",
            reason: if e.kind() == std::io::ErrorKind::AlreadyExists {
                format!(
                    "a file of that name appeared while recording; the recording is kept as {part}"
                )
            } else {
                format!("{e}; the recording is kept as {part}")
            },
        })
    }
}

/// One message of an edge, as its node sent it.
#[derive(Clone, Debug, PartialEq)]
pub struct EdgeMessage {
    /// `NODE/OUTPUT`.
    pub edge: String,
    /// What it is.
    pub kind: MessageKind,
    /// Its header (`edge_sequence` 0: the transport sets it when it is sent again).
    pub header: FrameHeader,
    /// Its payload.
    pub payload: Vec<u8>,
    /// When the recorder received it, ns since the epoch.
    pub log_time: u64,
}

/// One channel of a recording as [`channels`] lists it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ChannelInfo {
    /// Topic.
    pub topic: String,
    /// ROS 2 type.
    pub schema: String,
    /// The edge it belongs to, when microstereo wrote it.
    pub edge: Option<String>,
    /// The edge's message kind.
    pub kind: Option<MessageKind>,
    /// Messages on it.
    pub messages: u64,
    /// First log time, ns.
    pub first_ns: u64,
    /// Last log time, ns.
    pub last_ns: u64,
    /// Bytes of message data.
    pub bytes: u64,
}

/// What a pass over a recording found, channel by channel.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Overview {
    /// Channels in order of first appearance.
    pub channels: Vec<ChannelInfo>,
    /// The launch file stored in it, `(path, text)`.
    pub launch: Option<(String, String)>,
    /// Why reading stopped early (a corrupt file).
    pub error: Option<String>,
    /// The file ends without the MCAP footer.
    pub truncated: bool,
    /// How a truncated file (or part) broke off: read up to its last whole record, the
    /// rest lost.
    pub cut: Vec<String>,
    /// What was skipped and why (damaged chunks, found by their CRCs): the rest was read.
    pub damaged: Vec<String>,
    /// Largest frame number seen.
    pub last_sequence: Option<u64>,
    /// Smallest frame number seen.
    pub first_sequence: Option<u64>,
}

impl Overview {
    /// What `microstereo inspect` prints for the recording `file`: totals, the stored
    /// launch file, then one row per channel (type, messages, rate, size).
    pub fn table(&self, file: &Path) -> Vec<String> {
        let (first, last) = self.channels.iter().fold((u64::MAX, 0u64), |(f, l), c| {
            (f.min(c.first_ns), l.max(c.last_ns))
        });
        let span = if self.channels.is_empty() {
            0.0
        } else {
            (last - first) as f64 / 1e9
        };
        let total: u64 = self.channels.iter().map(|c| c.messages).sum();
        let bytes: u64 = self.channels.iter().map(|c| c.bytes).sum();
        let mut out = vec![
            file.display().to_string(),
            format!(
                "  {total} messages on {} channels, {:.2} s, frames {}–{}, {:.1} MB of CDR data",
                self.channels.len(),
                span,
                self.first_sequence.map_or("-".into(), |s| s.to_string()),
                self.last_sequence.map_or("-".into(), |s| s.to_string()),
                bytes as f64 / 1e6,
            ),
        ];
        if let Some((path, _)) = &self.launch {
            out.push(format!("  launch file: {path} (stored in the recording)"));
        }
        let width = |f: fn(&ChannelInfo) -> &str, least: usize| {
            self.channels
                .iter()
                .map(|c| f(c).chars().count())
                .max()
                .unwrap_or(least)
                .max(least)
        };
        let (w, tw) = (width(|c| &c.topic, 5), width(|c| &c.schema, 4));
        out.push(format!(
            "  {:<w$} {:<tw$} {:>8} {:>9} {:>10}",
            "topic", "type", "messages", "rate Hz", "MB"
        ));
        for c in &self.channels {
            let dt = (c.last_ns - c.first_ns) as f64 / 1e9;
            let rate = if c.messages > 1 && dt > 0.0 {
                format!("{:.2}", (c.messages - 1) as f64 / dt)
            } else {
                "-".into()
            };
            out.push(format!(
                "  {:<w$} {:<tw$} {:>8} {:>9} {:>10.2}",
                c.topic,
                c.schema,
                c.messages,
                rate,
                c.bytes as f64 / 1e6
            ));
        }
        out
    }

    /// Why reading the recording `file` stopped before its end, if it did.
    pub fn stopped(&self, file: &Path) -> Option<String> {
        self.error.as_ref().map(|e| {
            format!(
                "{}: {e}{}",
                file.display(),
                if self.truncated {
                    " (the file is truncated: its recorder did not close it)"
                } else {
                    ""
                }
            )
        })
    }

    /// The channels that make up `edge`.
    pub fn edge(&self, edge: &str) -> Vec<&ChannelInfo> {
        self.channels
            .iter()
            .filter(|c| c.edge.as_deref() == Some(edge))
            .collect()
    }
}

/// The name of part `i` of a recording split into files (`--split`): `run.mcap` →
/// `run-000.mcap`, `run-001.mcap`, …
pub fn part_path(path: &Path, i: usize) -> PathBuf {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let name = match path.extension() {
        Some(e) => format!("{stem}-{i:03}.{}", e.to_string_lossy()),
        None => format!("{stem}-{i:03}"),
    };
    path.with_file_name(name)
}

/// The partial files a recorder that did not finish left for `path` (`path.PID.part`).
pub fn unfinished_parts(path: &Path) -> Vec<String> {
    let (Some(dir), Some(name)) = (path.parent(), path.file_name()) else {
        return Vec::new();
    };
    let dir = if dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        dir
    };
    let prefix = format!("{}.", name.to_string_lossy());
    let mut found: Vec<String> = std::fs::read_dir(dir)
        .map(|d| {
            d.filter_map(Result::ok)
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|n| n.starts_with(&prefix) && n.ends_with(".part"))
                .map(|n| dir.join(n).display().to_string())
                .collect()
        })
        .unwrap_or_default();
    found.sort();
    found
}

/// What a run says of the recording it made at `path`: the messages `written`, its parts
/// where it was `split`, its size, and how to list it.
pub fn written(path: &Path, written: u64, split: bool) -> String {
    let files = recording_files(path);
    let size: u64 = files
        .iter()
        .map(|f| std::fs::metadata(f).map_or(0, |m| m.len()))
        .sum();
    format!(
        "recorded {written} message(s) into {}{} ({:.1} MB); `microstereo inspect {}` lists them",
        path.display(),
        if split {
            format!(" as {} part(s), {} …", files.len(), files[0].display())
        } else {
            String::new()
        },
        size as f64 / 1e6,
        path.display()
    )
}

/// The files of recording `path`: itself, or where it does not exist and it was split,
/// its parts in order ([`part_path`]), read as one recording.
pub fn recording_files(path: &Path) -> Vec<PathBuf> {
    if path.exists() || !part_path(path, 0).exists() {
        return vec![path.to_path_buf()];
    }
    (0..)
        .map(|i| part_path(path, i))
        .take_while(|p| p.exists())
        .collect()
}

/// An I/O error as a user needs it: a full disk said plainly (mcap's own words for any I/O
/// error hide which one it was).
pub fn io_reason(e: &std::io::Error) -> String {
    if e.kind() == std::io::ErrorKind::StorageFull || e.raw_os_error() == Some(28) {
        format!(
            "the disk is full (ENOSPC: {e}); free some space or record to another disk (--split keeps the parts already written whole)"
        )
    } else {
        e.to_string()
    }
}

/// An MCAP writer's error, its I/O error said as [`io_reason`] says it.
fn mcap_reason(e: mcap::McapError) -> String {
    match e {
        mcap::McapError::Io(io) => io_reason(&io),
        e => e.to_string(),
    }
}

fn open(path: &Path) -> Result<(File, bool), RecordingError> {
    let mut f = File::open(path).map_err(|e| RecordingError::Io {
        path: path.into(),
        what: "opening the recording",
        reason: e.to_string(),
    })?;
    let corrupt = |reason: String| RecordingError::Corrupt {
        path: path.into(),
        reason,
        messages: 0,
        truncated: false,
    };
    let len = f.metadata().map(|m| m.len()).unwrap_or(0);
    let mut head = [0u8; 8];
    if len < 8 || f.read_exact(&mut head).is_err() || &head != MAGIC {
        return Err(corrupt(
            "not an MCAP file (it does not start with the MCAP magic)".into(),
        ));
    }
    let mut tail = [0u8; 8];
    let complete = len >= 16
        && f.seek(SeekFrom::End(-8)).is_ok()
        && f.read_exact(&mut tail).is_ok()
        && &tail == MAGIC;
    f.seek(SeekFrom::Start(0)).map_err(|e| RecordingError::Io {
        path: path.into(),
        what: "reading the recording",
        reason: e.to_string(),
    })?;
    Ok((f, !complete))
}

/// Largest top-level record read whole (a chunk is 8 MiB as written; other writers' may be
/// larger, but a length past this is damage, not data).
const RECORD_LIMIT: u64 = 1 << 30;

/// Largest uncompressed chunk or record inside one read (microstereo writes 8 MiB chunks;
/// a larger claim is damage).
const CHUNK_LIMIT: usize = 256 << 20;

/// The raw MCAP messages of `path`, with whether the file lacks its footer.
fn raw_messages(path: &Path) -> Result<(RawMessages, bool), RecordingError> {
    let (mut f, truncated) = open(path)?;
    let len = f.metadata().map(|m| m.len()).unwrap_or(0);
    let mut raw = RawMessages {
        file: BufReader::with_capacity(
            1 << 20,
            f.try_clone().map_err(|e| RecordingError::Io {
                path: path.into(),
                what: "opening the recording",
                reason: e.to_string(),
            })?,
        ),
        offset: MAGIC.len() as u64,
        len,
        chunk: None,
        ended: false,
        channels: HashMap::new(),
        schemas: HashMap::new(),
        summary_channels: HashMap::new(),
        summary_schemas: HashMap::new(),
        launch: None,
        damaged: Vec::new(),
        undeclared: HashMap::new(),
        truncated,
        cut_at: None,
    };
    if !truncated {
        // The summary repeats every schema and channel: a message whose channel was
        // declared in a damaged chunk can still be read.
        raw.read_summary(&mut f);
    }
    raw.file
        .seek(SeekFrom::Start(raw.offset))
        .map_err(|e| RecordingError::Io {
            path: path.into(),
            what: "reading the recording",
            reason: e.to_string(),
        })?;
    Ok((raw, truncated))
}

/// Checks that the records of an uncompressed chunk (`body`: the chunk record's body) lie
/// within it, each whole: mcap 0.26 overflows a counter on one that runs past the chunk's
/// end (found by fuzzing). Compressed chunks are checked by their reader.
fn uncompressed_framing(body: &[u8]) -> Result<(), &'static str> {
    let u64_at = |i: usize| {
        body.get(i..i.checked_add(8)?)
            .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")))
    };
    let short = "its header is cut short";
    let name_len = body
        .get(28..32)
        .map(|b| u32::from_le_bytes(b.try_into().expect("4 bytes")) as usize)
        .ok_or(short)?;
    let at = 32usize.checked_add(name_len).ok_or(short)?;
    if !body.get(32..at).ok_or(short)?.is_empty() {
        return Ok(());
    }
    let n = u64_at(at).ok_or(short)?;
    let records = body.get(at + 8..).ok_or(short)?;
    if (records.len() as u64) < n {
        return Err("its records run past its end");
    }
    let mut i = 0usize;
    while (i as u64) < n {
        let len = u64_at(at + 8 + i + 1).ok_or("a record's header is cut short")?;
        i = (i as u64)
            .checked_add(9)
            .and_then(|x| x.checked_add(len))
            .filter(|&x| x <= n)
            .ok_or("a record runs past the chunk's end")? as usize;
    }
    Ok(())
}

/// An MCAP message with its channel.
struct RawMessage {
    channel: Arc<mcap::records::Channel>,
    schema: Option<String>,
    header: MessageHeader,
    data: Vec<u8>,
}

/// The records of one chunk, read by mcap's own reader (decompression, CRC) from memory.
struct ChunkRecords {
    reader: mcap::sans_io::LinearReader,
    bytes: Vec<u8>,
    fed: usize,
    /// The chunk's offset in the file.
    at: u64,
}

/// Streams the records of an MCAP file, keeping channels, schemas and the launch metadata.
/// It walks the top-level records itself and hands each chunk to a fresh reader that checks
/// the chunk's CRC before giving any of its records: a damaged chunk is skipped whole and
/// noted in `damaged`, and reading goes on with the next record.
struct RawMessages {
    file: BufReader<File>,
    /// Where the next top-level record starts.
    offset: u64,
    len: u64,
    chunk: Option<ChunkRecords>,
    ended: bool,
    channels: HashMap<u16, Arc<mcap::records::Channel>>,
    schemas: HashMap<u16, String>,
    /// Channels and schema names from the summary section.
    summary_channels: HashMap<u16, Arc<mcap::records::Channel>>,
    summary_schemas: HashMap<u16, String>,
    launch: Option<(String, String)>,
    /// What was skipped, and why: damaged chunks and records.
    damaged: Vec<String>,
    /// Messages skipped on channels that no readable record declares, per channel.
    undeclared: HashMap<u16, u64>,
    /// The file ends without its footer (its writer did not close it).
    truncated: bool,
    /// Where a truncated file breaks off: the byte its last whole record ends at.
    cut_at: Option<u64>,
}

/// A decoded record that matters here.
enum Parsed {
    Message(RawMessage),
    Other,
}

impl RawMessages {
    /// Reads the schemas and channels of the summary section (best effort: a damaged
    /// summary only loses the fallback).
    fn read_summary(&mut self, f: &mut File) {
        use mcap::records::{Record, op};
        // The footer: opcode, length, summary start, summary offset start, CRC; then the
        // magic.
        const FOOTER_LEN: u64 = 1 + 8 + 8 + 8 + 4;
        let Some(footer_at) = self.len.checked_sub(MAGIC.len() as u64 + FOOTER_LEN) else {
            return;
        };
        let mut footer = [0u8; FOOTER_LEN as usize];
        if f.seek(SeekFrom::Start(footer_at)).is_err()
            || f.read_exact(&mut footer).is_err()
            || footer[0] != op::FOOTER
        {
            return;
        }
        let start = u64::from_le_bytes(footer[9..17].try_into().expect("8 bytes"));
        if start == 0 || start >= footer_at || footer_at - start > RECORD_LIMIT {
            return;
        }
        let mut summary = vec![0u8; (footer_at - start) as usize];
        if f.seek(SeekFrom::Start(start)).is_err() || f.read_exact(&mut summary).is_err() {
            return;
        }
        let mut at = 0usize;
        while at + 9 <= summary.len() {
            let opcode = summary[at];
            let n = u64::from_le_bytes(summary[at + 1..at + 9].try_into().expect("8 bytes"));
            let Some(end) = usize::try_from(n)
                .ok()
                .and_then(|n| (at + 9).checked_add(n))
                .filter(|&e| e <= summary.len())
            else {
                return;
            };
            if !matches!(opcode, op::SCHEMA | op::CHANNEL) {
                at = end;
                continue;
            }
            match mcap::parse_record(opcode, &summary[at + 9..end]) {
                Ok(Record::Schema { header, .. }) => {
                    self.summary_schemas.insert(header.id, header.name.clone());
                }
                Ok(Record::Channel(c)) => {
                    self.summary_channels.insert(c.id, Arc::new(c));
                }
                _ => {}
            }
            at = end;
        }
    }

    /// Takes one record (top-level or from a chunk).
    fn take(&mut self, opcode: u8, data: &[u8]) -> Result<Parsed, String> {
        use mcap::records::{Record, op};
        // Only what is used is parsed: mcap 0.26 panics on some damaged records of other
        // kinds (an attachment shorter than its header, found by fuzzing).
        if !matches!(
            opcode,
            op::SCHEMA | op::CHANNEL | op::MESSAGE | op::METADATA
        ) {
            return Ok(Parsed::Other);
        }
        match mcap::parse_record(opcode, data).map_err(|e| e.to_string())? {
            Record::Schema { header, .. } => {
                self.schemas.insert(header.id, header.name.clone());
            }
            Record::Channel(c) => {
                self.channels.insert(c.id, Arc::new(c));
            }
            Record::Metadata(m) if m.name == META_LAUNCH => {
                self.launch = Some((
                    m.metadata.get("path").cloned().unwrap_or_default(),
                    m.metadata.get("text").cloned().unwrap_or_default(),
                ));
            }
            Record::Message { header, data } => {
                // A channel or schema declared only in a damaged chunk is known from the
                // summary.
                let Some(channel) = self
                    .channels
                    .get(&header.channel_id)
                    .or_else(|| self.summary_channels.get(&header.channel_id))
                    .cloned()
                else {
                    *self.undeclared.entry(header.channel_id).or_default() += 1;
                    return Ok(Parsed::Other);
                };
                let schema = self
                    .schemas
                    .get(&channel.schema_id)
                    .or_else(|| self.summary_schemas.get(&channel.schema_id))
                    .cloned();
                return Ok(Parsed::Message(RawMessage {
                    channel,
                    schema,
                    header,
                    data: data.into_owned(),
                }));
            }
            _ => {}
        }
        Ok(Parsed::Other)
    }

    /// How a truncated file broke off, once the reader got there: what was read and what
    /// was lost.
    fn cut(&self) -> Option<String> {
        let at = self.cut_at?;
        let lost = self.len - at;
        Some(if lost == 0 {
            format!(
                "the file is truncated (its writer did not close it): read to its end at byte {at}; only its index is missing"
            )
        } else {
            format!(
                "the file is truncated (its writer did not close it): read up to its last complete record, at byte {at} of {}; the {lost} byte(s) after it, an unfinished record, are lost (with whatever was never written to the file)",
                self.len
            )
        })
    }

    /// What was skipped so far, each with where and why.
    fn damage(&self) -> Vec<String> {
        let mut d = self.damaged.clone();
        let mut ids: Vec<_> = self.undeclared.iter().collect();
        ids.sort();
        for (id, n) in ids {
            d.push(format!(
                "{n} message(s) on channel {id}, which no readable record declares, skipped"
            ));
        }
        d
    }

    /// The next message; `Err` ends the reading (the file breaks off or cannot be read on).
    fn next_message(&mut self) -> Option<Result<RawMessage, String>> {
        use mcap::records::op;
        use mcap::sans_io::LinearReadEvent;
        loop {
            // The chunk is taken out while its record is read, so that the record is
            // parsed where it lies in the reader's buffer (one copy, into the message).
            if let Some(mut c) = self.chunk.take() {
                let taken = match c.reader.next_event() {
                    None => continue,
                    Some(Err(e)) => {
                        self.damaged.push(format!(
                            "the chunk at byte {} is damaged ({e}); its messages are skipped",
                            c.at
                        ));
                        continue;
                    }
                    Some(Ok(LinearReadEvent::ReadRequest(n))) => {
                        let k = n.min(c.bytes.len() - c.fed);
                        c.reader
                            .insert(k)
                            .copy_from_slice(&c.bytes[c.fed..c.fed + k]);
                        c.reader.notify_read(k);
                        c.fed += k;
                        None
                    }
                    Some(Ok(LinearReadEvent::Record { opcode, data })) => {
                        Some(self.take(opcode, data))
                    }
                };
                let at = c.at;
                self.chunk = Some(c);
                match taken {
                    Some(Ok(Parsed::Message(m))) => return Some(Ok(m)),
                    Some(Err(e)) => self.damaged.push(format!(
                        "a record in the chunk at byte {at} cannot be read ({e}); skipped"
                    )),
                    Some(Ok(Parsed::Other)) | None => {}
                }
                continue;
            }
            if self.ended {
                return None;
            }
            let at = self.offset;
            let mut head = [0u8; 9];
            let mut got = 0;
            while got < head.len() {
                match self.file.read(&mut head[got..]) {
                    Ok(0) => break,
                    Ok(k) => got += k,
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                    Err(e) => {
                        self.ended = true;
                        return Some(Err(e.to_string()));
                    }
                }
            }
            if got == 0 {
                self.ended = true;
                if self.truncated {
                    self.cut_at = Some(at);
                }
                return None;
            }
            let n = u64::from_le_bytes(head[1..].try_into().expect("8 bytes"));
            let end = at.saturating_add(9).saturating_add(n);
            if got < head.len() || end > self.len {
                self.ended = true;
                // A file cut short (its writer died, the disk filled, a copy lost its
                // tail) is read up to its last whole record; the loss is said, not fatal.
                if self.truncated {
                    self.cut_at = Some(at);
                    return None;
                }
                return Some(Err(format!(
                    "the record at byte {at} runs past the end of the file"
                )));
            }
            if n > RECORD_LIMIT {
                self.ended = true;
                return Some(Err(format!(
                    "the record at byte {at} claims {n} bytes; its length is damaged"
                )));
            }
            let opcode = head[0];
            if opcode == op::DATA_END || opcode == op::FOOTER {
                // The data section ends here; the summary repeats what it held.
                self.ended = true;
                return None;
            }
            // The record whole, its opcode and length first: a chunk is handed to its
            // reader as it lies here.
            let mut record = vec![0u8; 9 + n as usize];
            record[..9].copy_from_slice(&head);
            if let Err(e) = self.file.read_exact(&mut record[9..]) {
                self.ended = true;
                return Some(Err(e.to_string()));
            }
            self.offset = end;
            let body = &record[9..];
            if opcode == op::CHUNK {
                if let Err(e) = uncompressed_framing(body) {
                    self.damaged.push(format!(
                        "the chunk at byte {at} is damaged ({e}); its messages are skipped"
                    ));
                    continue;
                }
                // The chunk's own sizes are untrusted: a damaged one must not allocate
                // what it claims (fuzzing found terabyte claims).
                let opts = mcap::sans_io::LinearReaderOptions::default()
                    .with_skip_start_magic(true)
                    .with_skip_end_magic(true)
                    .with_prevalidate_chunk_crcs(true)
                    .with_record_length_limit(CHUNK_LIMIT);
                self.chunk = Some(ChunkRecords {
                    reader: mcap::sans_io::LinearReader::new_with_options(opts),
                    bytes: record,
                    fed: 0,
                    at,
                });
                continue;
            }
            match self.take(opcode, body) {
                Ok(Parsed::Message(m)) => return Some(Ok(m)),
                Ok(Parsed::Other) => {}
                Err(e) => self.damaged.push(format!(
                    "the record at byte {at} cannot be read ({e}); skipped"
                )),
            }
        }
    }
}

/// The rectified cameras a recording's CameraInfo gives (the first left and right ones),
/// as a geometry in metres, and their image size; `None` when it holds none. CameraInfo
/// goes beside every rectified image, so only the first two frames are read.
pub fn recorded_cameras(path: &Path) -> Option<(schemas::Calibration, (usize, usize))> {
    let (mut raw, _) = raw_messages(path).ok()?;
    let (mut left, mut right) = (None, None);
    let mut first = None;
    while let Some(Ok(m)) = raw.next_message() {
        // Frames counted on the edges' own messages (the frame tree's is numbered 0).
        let frame = m.header.sequence;
        if m.channel.metadata.contains_key(META_EDGE) && frame > *first.get_or_insert(frame) + 1 {
            return None;
        }
        if m.schema.as_deref() != Some(ros2::CAMERA_INFO.name) {
            continue;
        }
        let slot = if m.channel.topic.ends_with("/right/camera_info") {
            &mut right
        } else {
            &mut left
        };
        if slot.is_none() {
            *slot = ros2::camera_of(&m.data).ok();
        }
        if let (Some(([f, cx, cy, _], size)), Some(([_, cx_right, _, tx], _))) = (left, right) {
            let calibration = schemas::Calibration {
                baseline: -tx / f,
                focal_px: f,
                cx,
                cy,
                cx_right,
                unit: schemas::LengthUnit::M,
            };
            return (f > 0.0 && tx < 0.0).then_some((calibration, size));
        }
    }
    None
}

/// Reads a recording once and lists its channels (a truncated or corrupt file gives what
/// could be read, with the reason it stopped).
pub fn overview(path: &Path) -> Result<Overview, RecordingError> {
    let files = recording_files(path);
    let mut all = overview_of(&files[0])?;
    if files.len() > 1 {
        all.cut = all
            .cut
            .into_iter()
            .map(|c| format!("{}: {c}", files[0].display()))
            .collect();
    }
    for f in &files[1..] {
        if all.error.is_some() {
            break;
        }
        let o = overview_of(f)?;
        all.cut
            .extend(o.cut.iter().map(|c| format!("{}: {c}", f.display())));
        for c in o.channels {
            match all.channels.iter_mut().find(|a| a.topic == c.topic) {
                Some(a) => {
                    a.messages += c.messages;
                    a.bytes += c.bytes;
                    a.first_ns = a.first_ns.min(c.first_ns);
                    a.last_ns = a.last_ns.max(c.last_ns);
                }
                None => all.channels.push(c),
            }
        }
        all.launch = all.launch.or(o.launch);
        all.error = o.error.map(|e| format!("{}: {e}", f.display()));
        all.truncated |= o.truncated;
        all.damaged.extend(
            o.damaged
                .into_iter()
                .map(|d| format!("{}: {d}", f.display())),
        );
        all.last_sequence = all.last_sequence.max(o.last_sequence);
        all.first_sequence = match (all.first_sequence, o.first_sequence) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
    }
    Ok(all)
}

fn overview_of(path: &Path) -> Result<Overview, RecordingError> {
    let (mut raw, truncated) = raw_messages(path)?;
    let mut o = Overview {
        truncated,
        ..Overview::default()
    };
    let mut index: HashMap<u16, usize> = HashMap::new();
    while let Some(m) = raw.next_message() {
        let m = match m {
            Ok(m) => m,
            Err(e) => {
                o.error = Some(e);
                break;
            }
        };
        let i = *index.entry(m.channel.id).or_insert_with(|| {
            o.channels.push(ChannelInfo {
                topic: m.channel.topic.clone(),
                schema: m.schema.clone().unwrap_or_default(),
                edge: m.channel.metadata.get(META_EDGE).cloned(),
                kind: m
                    .channel
                    .metadata
                    .get(META_KIND)
                    .and_then(|k| MessageKind::from_name(k)),
                messages: 0,
                first_ns: m.header.log_time,
                last_ns: m.header.log_time,
                bytes: 0,
            });
            o.channels.len() - 1
        });
        let c = &mut o.channels[i];
        c.messages += 1;
        c.first_ns = c.first_ns.min(m.header.log_time);
        c.last_ns = c.last_ns.max(m.header.log_time);
        c.bytes += m.data.len() as u64;
        let seq = u64::from(m.header.sequence);
        o.last_sequence = Some(o.last_sequence.map_or(seq, |s| s.max(seq)));
        o.first_sequence = Some(o.first_sequence.map_or(seq, |s| s.min(seq)));
    }
    o.launch = raw.launch.take();
    o.damaged = raw.damage();
    o.cut = raw.cut().into_iter().collect();
    Ok(o)
}

/// Reads the messages of chosen edges back, in the order they were recorded, with the
/// two images of a stereo frame joined again.
pub struct EdgeReader {
    /// The file being read (a part of a split recording).
    path: PathBuf,
    /// The parts after it.
    more: std::collections::VecDeque<PathBuf>,
    raw: RawMessages,
    edges: Option<Vec<String>>,
    /// How the parts read so far broke off, where they did.
    cuts: Vec<String>,
    /// Halves of two-image messages waiting for their other side: (edge, frame) → parts.
    halves: HashMap<(String, u64), [Option<Vec<u8>>; 2]>,
    read: u64,
    done: bool,
}

impl std::fmt::Debug for EdgeReader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EdgeReader")
            .field("path", &self.path)
            .field("read", &self.read)
            .finish_non_exhaustive()
    }
}

impl EdgeReader {
    /// Opens `path`; with `edges`, only those edges' messages are decoded and given.
    pub fn open(path: &Path, edges: Option<Vec<String>>) -> Result<Self, RecordingError> {
        let mut files: std::collections::VecDeque<PathBuf> = recording_files(path).into();
        let first = files.pop_front().expect("one file at least");
        let (raw, _) = raw_messages(&first)?;
        Ok(Self {
            path: first,
            more: files,
            raw,
            edges,
            cuts: Vec::new(),
            halves: HashMap::new(),
            read: 0,
            done: false,
        })
    }

    /// The launch file stored in the recording, once the reader has passed it (it comes
    /// first in files microstereo writes).
    pub fn launch(&self) -> Option<&(String, String)> {
        self.raw.launch.as_ref()
    }

    /// What was skipped so far and why (damaged chunks): the reader goes on past them.
    pub fn damaged(&self) -> Vec<String> {
        self.raw.damage()
    }

    /// How the recording (or a part of it) broke off, once the reader got there: a file
    /// whose writer did not close it is read up to its last whole record.
    pub fn lost(&self) -> Vec<String> {
        let mut v = self.cuts.clone();
        v.extend(
            self.raw
                .cut()
                .map(|c| format!("{}: {c}", self.path.display())),
        );
        v
    }

    fn message_error(&self, topic: &str, sequence: u64, reason: String) -> RecordingError {
        RecordingError::Message {
            path: self.path.clone(),
            topic: topic.into(),
            sequence,
            reason,
        }
    }
}

impl Iterator for EdgeReader {
    type Item = Result<EdgeMessage, RecordingError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        loop {
            let m = match self.raw.next_message() {
                // A split recording goes on in its next part (after a part cut short too).
                None if !self.more.is_empty() => {
                    let next = self.more.pop_front().expect("not empty");
                    match raw_messages(&next) {
                        Ok((raw, _)) => {
                            if let Some(c) = self.raw.cut() {
                                self.cuts.push(format!("{}: {c}", self.path.display()));
                            }
                            let launch = self.raw.launch.take();
                            self.raw = raw;
                            self.raw.launch = launch;
                            self.path = next;
                            continue;
                        }
                        Err(e) => {
                            self.done = true;
                            return Some(Err(e));
                        }
                    }
                }
                None => {
                    self.done = true;
                    return None;
                }
                Some(Err(reason)) => {
                    self.done = true;
                    return Some(Err(RecordingError::Corrupt {
                        path: self.path.clone(),
                        reason,
                        messages: self.read,
                        truncated: self.raw.truncated,
                    }));
                }
                Some(Ok(m)) => m,
            };
            let meta = &m.channel.metadata;
            let (Some(edge), Some(kind)) = (meta.get(META_EDGE), meta.get(META_KIND)) else {
                continue;
            };
            if self
                .edges
                .as_ref()
                .is_some_and(|want| !want.iter().any(|e| e == edge))
            {
                continue;
            }
            let sequence = u64::from(m.header.sequence);
            let topic = m.channel.topic.clone();
            let Some(kind) = MessageKind::from_name(kind) else {
                return Some(Err(self.message_error(
                    &topic,
                    sequence,
                    format!("unknown message kind '{kind}'"),
                )));
            };
            if m.channel.message_encoding != "cdr"
                || m.schema.as_deref() != Some(ros2::msg_type(kind).name)
            {
                return Some(Err(self.message_error(
                    &topic,
                    sequence,
                    format!(
                        "a {} channel with schema {:?} in {} encoding; microstereo writes {} in cdr",
                        kind.name(),
                        m.schema,
                        m.channel.message_encoding,
                        ros2::msg_type(kind).name
                    ),
                )));
            }
            let sides = ros2::kind_sides(kind);
            let parts: Vec<Vec<u8>> = if sides.is_empty() {
                vec![m.data]
            } else {
                let side = meta.get(META_SIDE).map(String::as_str);
                let Some(i) = sides.iter().position(|s| Some(*s) == side) else {
                    return Some(Err(self.message_error(
                        &topic,
                        sequence,
                        format!("side {side:?} where left or right was expected"),
                    )));
                };
                let slot = self.halves.entry((edge.clone(), sequence)).or_default();
                slot[i] = Some(m.data);
                if slot.iter().any(Option::is_none) {
                    continue;
                }
                let [a, b] = self
                    .halves
                    .remove(&(edge.clone(), sequence))
                    .expect("present");
                vec![a.expect("both"), b.expect("both")]
            };
            let refs: Vec<&[u8]> = parts.iter().map(Vec::as_slice).collect();
            self.read += 1;
            return Some(
                ros2::decode(kind, &refs, (sequence, m.header.publish_time))
                    .map(|(header, payload)| EdgeMessage {
                        edge: edge.clone(),
                        kind,
                        header,
                        payload,
                        log_time: m.header.log_time,
                    })
                    .map_err(|reason| self.message_error(&topic, sequence, reason)),
            );
        }
    }
}

/// Whole frames of chosen edges: for each frame number, its message on every edge, in the
/// order the edges were given. Each edge's messages are recorded in frame order, so a frame
/// is complete before any later one; a frame that some edge lacks is skipped (and counted)
/// once a later frame is complete or the file ends.
#[derive(Debug)]
pub struct FrameReader {
    reader: EdgeReader,
    edges: Vec<String>,
    /// Frames read but not complete yet: frame number → message per edge.
    ahead: BTreeMap<u64, Vec<Option<EdgeMessage>>>,
    /// Frames skipped because some edge lacks them.
    pub incomplete: u64,
}

impl FrameReader {
    /// Opens `path` for the frames of `edges` (`NODE/OUTPUT`).
    pub fn open(path: &Path, edges: Vec<String>) -> Result<Self, RecordingError> {
        Ok(Self {
            reader: EdgeReader::open(path, Some(edges.clone()))?,
            edges,
            ahead: BTreeMap::new(),
            incomplete: 0,
        })
    }

    /// What was skipped so far and why (damaged chunks): the reader goes on past them.
    pub fn damaged(&self) -> Vec<String> {
        self.reader.damaged()
    }

    /// How the recording broke off, once the reader got there ([`EdgeReader::lost`]).
    pub fn lost(&self) -> Vec<String> {
        self.reader.lost()
    }
}

impl Iterator for FrameReader {
    type Item = Result<Vec<EdgeMessage>, RecordingError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some(seq) = self
                .ahead
                .iter()
                .find(|(_, m)| m.iter().all(Option::is_some))
                .map(|(s, _)| *s)
            {
                let older: Vec<u64> = self.ahead.range(..seq).map(|(s, _)| *s).collect();
                self.incomplete += older.len() as u64;
                for s in older {
                    self.ahead.remove(&s);
                }
                let msgs = self.ahead.remove(&seq).expect("present");
                return Some(Ok(msgs.into_iter().map(|m| m.expect("complete")).collect()));
            }
            match self.reader.next() {
                Some(Ok(m)) => {
                    let i = self
                        .edges
                        .iter()
                        .position(|e| *e == m.edge)
                        .expect("filtered");
                    let n = self.edges.len();
                    let seq = m.header.sequence;
                    self.ahead.entry(seq).or_insert_with(|| vec![None; n])[i] = Some(m);
                }
                Some(Err(e)) => return Some(Err(e)),
                None => {
                    self.incomplete += self.ahead.len() as u64;
                    self.ahead.clear();
                    return None;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use schemas::PixelFormat;

    fn frame(seq: u64, w: usize) -> (FrameHeader, Vec<u8>) {
        let h = FrameHeader {
            sequence: seq,
            capture_ns: 1_000 + seq,
            ..FrameHeader::image(MessageKind::StereoFrame, PixelFormat::Mono8, w, 2, 2)
        };
        let p = (0..h.image_bytes())
            .map(|i| (i as u64 * 7 + seq) as u8)
            .collect();
        (h, p)
    }

    fn write_three(path: &Path) {
        let mut w = RecordingWriter::create(path, false).unwrap();
        w.write_launch(Path::new("g.toml"), "[[node]]\n").unwrap();
        for seq in 0..3 {
            let (h, p) = frame(seq, 4);
            w.write("cam/frame", MessageKind::StereoFrame, &h, &p, 50 + seq)
                .unwrap();
        }
        w.finish().unwrap();
    }

    /// A cell of `id` at `[x, y]` µm on a substrate 150 mm down, 10 µm high, 20 µm across.
    fn cell(id: u32, [x, y]: [f64; 2]) -> schemas::Cell3 {
        let contour = (0..64)
            .map(|i| {
                let t = i as f64 / 64.0 * std::f64::consts::TAU;
                [x + 10.0 * t.cos(), y + 10.0 * t.sin(), 150_000.0]
            })
            .collect();
        schemas::Cell3 {
            id,
            right_id: id,
            area_px: 300,
            centroid_px: [0.0; 2],
            disparity: 3.0,
            centroid: [x, y, 149_995.0],
            substrate_z: 150_000.0,
            height: Some(10.0),
            volume: 2000.0,
            contour,
            valid_share: 1.0,
            quality: schemas::CellQuality {
                trusted: id == 1,
                height_std: Some(0.2),
                ..Default::default()
            },
        }
    }

    #[test]
    fn viewers_get_the_frame_tree_camera_info_beside_each_image_and_a_marker_per_cell() {
        use schemas::msg::Message;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.mcap");
        let calib = schemas::Calibration {
            baseline: 2000.0,
            focal_px: 4000.0,
            cx: 2.0,
            cy: 1.0,
            cx_right: 2.0,
            unit: schemas::LengthUnit::Um,
        };
        let mut w = RecordingWriter::create(&path, false).unwrap();
        w.write_cameras(&calib, (4, 2), &["raw/frame".into()], 10)
            .unwrap();
        let mut sent = Vec::new();
        for seq in 0..2 {
            let (h, p) = frame(seq, 4);
            for edge in ["cam/frame", "raw/frame"] {
                w.write(edge, MessageKind::StereoFrame, &h, &p, 50 + seq)
                    .unwrap();
                sent.push((edge.to_string(), h, p.clone()));
            }
        }
        let targets = schemas::Targets {
            frame: 1,
            capture_ns: 1_001,
            unit: "µm".into(),
            cells: vec![cell(1, [100.0, -40.0]), cell(4, [-250.0, 60.0])],
            substrate: None,
        };
        let e = targets.encode();
        let h = FrameHeader {
            sequence: 1,
            capture_ns: 1_001,
            ..e.header
        };
        w.write("tri/targets", MessageKind::Targets, &h, &e.to_vec(), 60)
            .unwrap();
        sent.push(("tri/targets".into(), h, e.to_vec()));
        w.finish().unwrap();
        // Our readers still get the edges, bit for bit, and nothing else.
        let back: Vec<_> = EdgeReader::open(&path, None)
            .unwrap()
            .map(|m| {
                let m = m.unwrap();
                (m.edge, m.header, m.payload)
            })
            .collect();
        assert_eq!(back, sent);
        let bytes = std::fs::read(&path).unwrap();
        let mut by_topic: BTreeMap<String, Vec<(u64, Vec<u8>)>> = BTreeMap::new();
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap();
            if m.channel.topic == TF_STATIC {
                assert!(m.channel.metadata[QOS].contains("durability: 1"));
            }
            by_topic
                .entry(m.channel.topic.clone())
                .or_default()
                .push((m.publish_time, m.data.to_vec()));
        }
        let topics: Vec<&str> = by_topic.keys().map(String::as_str).collect();
        assert_eq!(
            topics,
            [
                "/cam/frame/left/camera_info",
                "/cam/frame/left/image",
                "/cam/frame/right/camera_info",
                "/cam/frame/right/image",
                "/raw/frame/left/image",
                "/raw/frame/right/image",
                "/tf_static",
                "/tri/targets",
                "/tri/targets/left/annotations",
                "/tri/targets/markers",
            ]
        );
        for side in ["left", "right"] {
            let stamps = |kind: &str| -> Vec<u64> {
                by_topic[&format!("/cam/frame/{side}/{kind}")]
                    .iter()
                    .map(|m| m.0)
                    .collect()
            };
            assert_eq!(stamps("camera_info"), stamps("image"));
            let info = &by_topic[&format!("/cam/frame/{side}/camera_info")][1].1;
            let header: (i32, u32, String) = ros2::from_cdr(info, "CameraInfo").unwrap();
            assert_eq!(
                header,
                (0, 1_001, scene::camera_frame(side).to_string()),
                "{side}"
            );
        }
        let markers = scene::decode_markers(&by_topic["/tri/targets/markers"][0].1).unwrap();
        let cells: Vec<(i32, [f64; 3])> = markers
            .iter()
            .filter(|m| m.0 == "cells")
            .map(|m| (m.1, m.2))
            .collect();
        assert_eq!(cells.len(), 2);
        assert_eq!(cells[0].0, 1);
        assert_eq!(cells[1].0, 4);
        // In metres, the body's middle half its height over the substrate.
        let want = [100e-6, -40e-6, 149_995.0 * 1e-6];
        for (got, want) in cells[0].1.iter().zip(want) {
            assert!((got - want).abs() < 1e-9, "{:?}", cells[0].1);
        }
    }

    #[test]
    fn a_recording_reads_back_exactly_and_lists_its_channels() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.mcap");
        write_three(&path);
        let back: Vec<EdgeMessage> = EdgeReader::open(&path, None)
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(back.len(), 3);
        for (seq, m) in back.iter().enumerate() {
            let (h, p) = frame(seq as u64, 4);
            assert_eq!(
                (m.edge.as_str(), m.header, &m.payload),
                ("cam/frame", h, &p)
            );
            assert_eq!(m.log_time, 50 + seq as u64);
        }
        let o = overview(&path).unwrap();
        assert_eq!(o.error, None);
        assert!(!o.truncated);
        let topics: Vec<_> = o
            .channels
            .iter()
            .map(|c| (c.topic.as_str(), c.messages))
            .collect();
        assert_eq!(
            topics,
            [("/cam/frame/left/image", 3), ("/cam/frame/right/image", 3)]
        );
        assert_eq!(o.channels[0].schema, "sensor_msgs/msg/Image");
        assert_eq!(o.edge("cam/frame").len(), 2);
        assert_eq!((o.first_sequence, o.last_sequence), (Some(0), Some(2)));
        assert_eq!(o.launch, Some(("g.toml".into(), "[[node]]\n".into())));
        let mut frames = FrameReader::open(&path, vec!["cam/frame".into()]).unwrap();
        let seqs: Vec<u64> = frames
            .by_ref()
            .map(|f| f.unwrap()[0].header.sequence)
            .collect();
        assert_eq!((seqs, frames.incomplete), (vec![0, 1, 2], 0));
        // An existing file is not overwritten by accident.
        let e = RecordingWriter::create(&path, false).unwrap_err();
        assert!(e.to_string().contains("exists"), "{e}");
    }

    /// A recording is written under a `.part` name and renamed when it is finished: a
    /// recorder that dies leaves no half file under the final name, nor harms an earlier
    /// one (with `overwrite`) before its own is whole.
    #[test]
    fn a_recording_takes_its_name_only_when_finished() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.mcap");
        std::fs::write(&path, b"an earlier recording").unwrap();
        let mut w = RecordingWriter::create(&path, true).unwrap();
        let (h, p) = frame(0, 4);
        w.write("cam/frame", MessageKind::StereoFrame, &h, &p, 50)
            .unwrap();
        let part = w.part.clone();
        assert!(part.exists());
        assert_eq!(std::fs::read(&path).unwrap(), b"an earlier recording");
        // Dying here (dropped unfinished) keeps the partial file and the earlier one.
        drop(w);
        assert_eq!(std::fs::read(&path).unwrap(), b"an earlier recording");
        assert!(part.exists());
        std::fs::remove_file(&part).unwrap();
        let mut w = RecordingWriter::create(&path, true).unwrap();
        w.write("cam/frame", MessageKind::StereoFrame, &h, &p, 50)
            .unwrap();
        let part = w.part.clone();
        w.finish().unwrap();
        assert!(!part.exists());
        assert_eq!(EdgeReader::open(&path, None).unwrap().count(), 1);
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1, "{names:?}");
    }

    /// Offsets of the chunk records of an MCAP file and of their compressed records.
    fn chunks(d: &[u8]) -> Vec<(usize, usize, usize)> {
        let mut at = 8;
        let mut out = Vec::new();
        while at + 9 <= d.len() {
            let op = d[at];
            let len = u64::from_le_bytes(d[at + 1..at + 9].try_into().unwrap()) as usize;
            if op == 0x06 {
                let body = at + 9;
                let name = u32::from_le_bytes(d[body + 28..body + 32].try_into().unwrap()) as usize;
                let records = body + 32 + name + 8;
                let n = u64::from_le_bytes(d[records - 8..records].try_into().unwrap()) as usize;
                out.push((at, records, n));
            }
            if op == 0x0f {
                break;
            }
            at += 9 + len;
        }
        out
    }

    /// A recording of twelve frames in four chunks of three.
    fn write_four_chunks(path: &Path) {
        let mut w = RecordingWriter::create(path, false).unwrap();
        w.write_launch(Path::new("g.toml"), "[[node]]\n").unwrap();
        for seq in 0..12 {
            let (h, p) = frame(seq, 64);
            w.write("cam/frame", MessageKind::StereoFrame, &h, &p, 50 + seq)
                .unwrap();
            if seq % 3 == 2 {
                w.mcap.flush().unwrap();
            }
        }
        w.finish().unwrap();
    }

    /// A bit flipped inside one chunk costs that chunk's messages only: the chunk is
    /// reported with where it lies, every other message reads back exactly, also those on
    /// channels the damaged chunk declared (the summary repeats them).
    #[test]
    fn a_damaged_chunk_is_skipped_and_reported_and_the_rest_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.mcap");
        write_four_chunks(&path);
        let clean = std::fs::read(&path).unwrap();
        let found = chunks(&clean);
        assert_eq!(found.len(), 4, "{found:?}");
        for (k, &(at, records, n)) in found.iter().enumerate() {
            let mut d = clean.clone();
            d[records + n / 2] ^= 0x10;
            let bad = dir.path().join(format!("bad{k}.mcap"));
            std::fs::write(&bad, &d).unwrap();
            let o = overview(&bad).unwrap();
            assert_eq!(o.error, None, "chunk {k}");
            assert_eq!(o.damaged.len(), 1, "chunk {k}: {:?}", o.damaged);
            assert!(
                o.damaged[0].contains(&format!("the chunk at byte {at} is damaged")),
                "{:?}",
                o.damaged
            );
            let back: Vec<EdgeMessage> = EdgeReader::open(&bad, None)
                .unwrap()
                .collect::<Result<_, _>>()
                .unwrap();
            let seqs: Vec<u64> = back.iter().map(|m| m.header.sequence).collect();
            let want: Vec<u64> = (0..12).filter(|s| s / 3 != k as u64).collect();
            assert_eq!(seqs, want, "chunk {k}");
            for m in &back {
                let (h, p) = frame(m.header.sequence, 64);
                assert_eq!((m.header, &m.payload), (h, &p));
            }
            let mut frames = FrameReader::open(&bad, vec!["cam/frame".into()]).unwrap();
            assert_eq!(frames.by_ref().count(), 9);
            assert_eq!(frames.damaged().len(), 1);
        }
    }

    #[test]
    fn a_full_disk_is_said_plainly() {
        // /dev/full answers every write with ENOSPC, as a full disk does.
        let full = File::options().write(true).open("/dev/full").unwrap();
        let mut w = mcap::WriteOptions::new()
            .create(BufWriter::new(full))
            .unwrap();
        let e = w.flush().unwrap_err();
        let said = mcap_reason(e);
        assert!(said.starts_with("the disk is full (ENOSPC"), "{said}");
        assert_eq!(
            io_reason(&std::io::Error::from(std::io::ErrorKind::NotFound)),
            "entity not found"
        );
    }

    #[test]
    fn a_truncated_file_gives_what_it_holds_and_says_so() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.mcap");
        write_three(&path);
        let bytes = std::fs::read(&path).unwrap();
        // Cut inside the footer's summary: the data section is whole, nothing is lost.
        let cut = dir.path().join("cut.mcap");
        std::fs::write(&cut, &bytes[..bytes.len() - 30]).unwrap();
        let mut r = EdgeReader::open(&cut, None).unwrap();
        let got: Vec<_> = r.by_ref().collect::<Result<_, _>>().unwrap();
        assert_eq!(got.len(), 3);
        assert!(r.lost().is_empty(), "{:?}", r.lost());
        assert!(overview(&cut).unwrap().truncated);
        // Four chunks of three frames; cut at every byte of the third chunk: the first two
        // chunks read back exactly, the loss is said with where it begins, and nothing
        // is an error.
        let path = dir.path().join("four.mcap");
        write_four_chunks(&path);
        let clean = std::fs::read(&path).unwrap();
        let found = chunks(&clean);
        let (third, _, _) = found[2];
        let end = third
            + 9
            + u64::from_le_bytes(clean[third + 1..third + 9].try_into().unwrap()) as usize;
        let half = dir.path().join("half.mcap");
        for at in (third + 1..end).step_by(7) {
            std::fs::write(&half, &clean[..at]).unwrap();
            let o = overview(&half).unwrap();
            assert!(o.truncated && o.error.is_none(), "{o:?}");
            assert_eq!(o.channels[0].messages, 6, "cut at {at}");
            assert_eq!(o.cut.len(), 1, "{o:?}");
            assert!(
                o.cut[0].contains(&format!("at byte {third} of {at}")),
                "{:?}",
                o.cut
            );
            let mut frames = FrameReader::open(&half, vec!["cam/frame".into()]).unwrap();
            let back: Vec<_> = frames.by_ref().collect::<Result<_, _>>().unwrap();
            let seqs: Vec<u64> = back.iter().map(|f| f[0].header.sequence).collect();
            assert_eq!(seqs, (0..6).collect::<Vec<_>>());
            assert_eq!(frames.lost().len(), 1);
        }
        // Not an MCAP file at all.
        let junk = dir.path().join("junk.mcap");
        std::fs::write(&junk, b"hello, world, this is text").unwrap();
        let e = overview(&junk).unwrap_err().to_string();
        assert!(e.contains("not an MCAP file"), "{e}");
    }
}
