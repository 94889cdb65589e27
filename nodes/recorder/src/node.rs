//! The recorder node (a tap on the graph's edges that writes them to MCAP) and the replay
//! source (recorded edges sent again in place of the node that made them).

use crate::file::{EdgeMessage, FrameReader, RecordingError, RecordingWriter};
use node_api::{GraphNode, Outputs};
use runtime::launch::{Graph, NodeSpec};
use runtime::process::{NodeStats, now_ns};
use schemas::{FrameHeader, MessageKind};
use serde::Deserialize;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{RecvTimeoutError, sync_channel};
use std::time::{Duration, Instant};

/// The built-in kind name of the recorder.
pub const RECORDER_KIND: &str = "recorder";
/// The built-in kind name of the replay source.
pub const REPLAY_KIND: &str = "replay";

/// Messages the recorder may hold between taking them from shared memory and writing them;
/// beyond that it takes no more until the writer catches up, so a message that reached the
/// recorder is always written and any loss happens on the edge, where it is counted.
const QUEUE: usize = 64;

/// `params` of a recorder node.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecorderParams {
    /// The MCAP file to write.
    pub path: PathBuf,
    /// Replace an existing file.
    #[serde(default)]
    pub overwrite: bool,
    /// The rectified cameras' geometry and image size, recorded as their CameraInfo.
    #[serde(default)]
    pub cameras: Option<Cameras>,
    /// Edges recorded at a reduced rate: `NODE/OUTPUT` pattern (`*` for any characters) →
    /// N, keeping about one frame in N ([`Thinning`]); the other edges keep every frame.
    #[serde(default)]
    pub every: std::collections::BTreeMap<String, u64>,
    /// Start a new file once this many bytes of messages (before compression) are in the
    /// current one: `path`'s parts `NAME-000.mcap`, `NAME-001.mcap`, … ([`file::part_path`]).
    #[serde(default)]
    pub split_bytes: Option<u64>,
    /// Start a new file once the current one is this many seconds old.
    #[serde(default)]
    pub split_seconds: Option<f64>,
}

/// Starts part `index` of recording `path` (the file itself when not `split`) with the
/// launch file and the cameras first.
fn create_part(
    path: &Path,
    overwrite: bool,
    split: bool,
    index: usize,
    launch: &Option<(PathBuf, String)>,
    cameras: &Option<Cameras>,
) -> Result<RecordingWriter, String> {
    let path = if split {
        crate::file::part_path(path, index)
    } else {
        path.to_path_buf()
    };
    let mut w = RecordingWriter::create(&path, overwrite).map_err(|e| e.to_string())?;
    if let Some((file, text)) = launch {
        w.write_launch(file, text).map_err(|e| e.to_string())?;
    }
    if let Some(c) = cameras {
        w.write_cameras(&c.calibration, (c.width, c.height), &c.raw, now_ns())
            .map_err(|e| e.to_string())?;
    }
    Ok(w)
}

/// A recording written as one file, or split into parts by size or time, each part a
/// whole recording (the launch file and the cameras first) and all of them read as one.
struct Parts {
    path: PathBuf,
    overwrite: bool,
    split_bytes: Option<u64>,
    split_seconds: Option<f64>,
    launch: Option<(PathBuf, String)>,
    cameras: Option<Cameras>,
    index: usize,
    started: std::time::Instant,
    writer: RecordingWriter,
    /// Messages in the parts already finished.
    done: u64,
}

impl Parts {
    fn split(&self) -> bool {
        self.split_bytes.is_some() || self.split_seconds.is_some()
    }

    fn create(&self, index: usize) -> Result<RecordingWriter, String> {
        create_part(
            &self.path,
            self.overwrite,
            self.split(),
            index,
            &self.launch,
            &self.cameras,
        )
    }

    fn open(p: &RecorderParams, graph: &Graph) -> Result<Self, String> {
        let launch = (!graph.text.is_empty()).then(|| (graph.file.clone(), graph.text.clone()));
        let split = p.split_bytes.is_some() || p.split_seconds.is_some();
        let writer = create_part(&p.path, p.overwrite, split, 0, &launch, &p.cameras)?;
        Ok(Self {
            path: p.path.clone(),
            overwrite: p.overwrite,
            split_bytes: p.split_bytes,
            split_seconds: p.split_seconds,
            launch,
            cameras: p.cameras.clone(),
            index: 0,
            started: std::time::Instant::now(),
            writer,
            done: 0,
        })
    }

    /// Writes one message, into a new part first when the current one is full or old.
    fn write(
        &mut self,
        edge: &str,
        kind: MessageKind,
        header: &FrameHeader,
        payload: &[u8],
        log_time: u64,
    ) -> Result<(), RecordingError> {
        let full = self.split_bytes.is_some_and(|b| self.writer.bytes >= b)
            || self
                .split_seconds
                .is_some_and(|s| self.started.elapsed().as_secs_f64() >= s);
        if full && self.writer.messages > 0 {
            let next = self
                .create(self.index + 1)
                .map_err(|reason| RecordingError::Io {
                    path: crate::file::part_path(&self.path, self.index + 1),
                    what: "starting the next part",
                    reason,
                })?;
            let old = std::mem::replace(&mut self.writer, next);
            self.done += old.messages;
            old.finish()?;
            self.index += 1;
            self.started = std::time::Instant::now();
        }
        self.writer.write(edge, kind, header, payload, log_time)
    }

    fn finish(self) -> Result<u64, RecordingError> {
        let n = self.done + self.writer.messages;
        self.writer.finish()?;
        Ok(n)
    }
}

/// The frames kept by the edges recorded at one reduced rate: the first frame at or after
/// every Nth frame number. Every edge of the rate keeps the same frames (a frame's first
/// message to arrive decides for all), so a kept frame has its images and maps together,
/// and frames the graph never let in shift the choice instead of leaving a gap.
#[derive(Debug)]
pub struct Thinning {
    n: u64,
    due: Option<u64>,
    kept: std::collections::VecDeque<u64>,
}

/// How many recent kept frame numbers a [`Thinning`] remembers: a frame's messages reach
/// the recorder within a few frames of each other.
const THINNING_MEMORY: usize = 64;

impl Thinning {
    /// Keeps about one frame in `n` (`n` ≥ 1).
    pub fn new(n: u64) -> Self {
        Self {
            n: n.max(1),
            due: None,
            kept: Default::default(),
        }
    }

    /// Whether the message of frame `sequence` is recorded.
    pub fn keep(&mut self, sequence: u64) -> bool {
        if self.kept.contains(&sequence) {
            return true;
        }
        if self.due.is_some_and(|d| sequence < d) {
            return false;
        }
        self.due = Some(sequence.saturating_add(self.n));
        if self.kept.len() == THINNING_MEMORY {
            self.kept.pop_front();
        }
        self.kept.push_back(sequence);
        true
    }
}

/// Per recorded edge, the index of its rate in `rates` (`None`: every frame), from the
/// `every` patterns; an error names a pattern that matches no recorded edge or an edge two
/// patterns give different rates.
pub fn edge_rates(
    every: &std::collections::BTreeMap<String, u64>,
    edges: &[String],
) -> Result<(Vec<Option<usize>>, Vec<u64>), String> {
    let mut rates: Vec<u64> = Vec::new();
    let mut of_edge = vec![None; edges.len()];
    for (pattern, &n) in every {
        if n == 0 {
            return Err(format!(
                "recording '{pattern}' every 0 frames: give N of 1 or more"
            ));
        }
        let mut matched = false;
        for (k, e) in edges.iter().enumerate() {
            if !runtime::launch::glob_match(pattern, e) {
                continue;
            }
            matched = true;
            let slot = rates.iter().position(|&r| r == n).unwrap_or_else(|| {
                rates.push(n);
                rates.len() - 1
            });
            match of_edge[k] {
                Some(old) if rates[old] != n => {
                    return Err(format!(
                        "edge '{e}' is recorded every {} and every {n} frames by two patterns: give it one rate",
                        rates[old]
                    ));
                }
                _ => of_edge[k] = Some(slot),
            }
        }
        if !matched {
            return Err(format!(
                "'{pattern}' (recorded every {n} frames) matches no recorded edge; the recorded edges: {}",
                edges.join(", ")
            ));
        }
    }
    Ok((of_edge, rates))
}

/// What the recorder writes as the cameras' CameraInfo.
#[derive(Clone, Debug, serde::Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Cameras {
    /// The rectified geometry.
    pub calibration: schemas::Calibration,
    /// Image width.
    pub width: usize,
    /// Image height.
    pub height: usize,
    /// Edges whose images are not rectified (a capture's, where the graph rectifies
    /// them): no CameraInfo goes beside them.
    #[serde(default)]
    pub raw: Vec<String>,
}

/// A message taken from an edge, on its way to the writer thread.
struct Taken {
    input: usize,
    header: FrameHeader,
    payload: Vec<u8>,
    log_time: u64,
}

/// Runs node `id` of `graph` as the recorder: every message on its inputs is copied out of
/// shared memory at once and written by a second thread (CDR, zstd chunks, a flush at least
/// every second). When the writer falls behind, the recorder waits and its edges' own
/// queues take the strain: a lossy edge drops (and counts) there, a lossless one holds its
/// writer back. The graph's launch file is stored in the recording, and with `cameras` in
/// its parameters each camera's CameraInfo is recorded first.
pub fn run_recorder(
    graph: &Graph,
    instance: &str,
    id: &str,
    frames: Option<u64>,
) -> Result<NodeStats, String> {
    let spec = graph
        .node(id)
        .ok_or_else(|| format!("no node '{id}' in {}", graph.file.display()))?;
    let p: RecorderParams = runtime::registry::from_table(&spec.params)?;
    if let Some(s) = p.split_seconds
        && !(1.0..=1e7).contains(&s)
    {
        return Err(format!(
            "split_seconds {s} is out of range: use 1 to 10000000 seconds"
        ));
    }
    if p.split_bytes == Some(0) {
        return Err("split_bytes 0 would start a file per message: give at least 1".into());
    }
    let edges = graph.input_edges(id);
    let names: Vec<String> = edges.iter().map(|(e, _)| e.clone()).collect();
    let (rate_of, rates) = edge_rates(&p.every, &names)?;
    let mut thinning: Vec<Thinning> = rates.iter().map(|&n| Thinning::new(n)).collect();
    let mut writer = Parts::open(&p, graph)?;
    let (tx, rx) = sync_channel::<Taken>(QUEUE);
    let thread_edges = edges.clone();
    let writing = std::thread::spawn(move || -> Result<u64, RecordingError> {
        loop {
            match rx.recv_timeout(Duration::from_millis(200)) {
                Ok(t) => {
                    let (edge, kind) = &thread_edges[t.input];
                    writer.write(edge, *kind, &t.header, &t.payload, t.log_time)?;
                }
                Err(RecvTimeoutError::Timeout) => writer.writer.flush_if_due()?,
                Err(RecvTimeoutError::Disconnected) => break,
            }
        }
        writer.finish()
    });
    let tapped =
        runtime::process::run_tap(graph, instance, id, frames, |input, header, payload| {
            if let Some(r) = rate_of[input]
                && !thinning[r].keep(header.sequence)
            {
                return Ok(());
            }
            let t = Taken {
                input,
                header: *header,
                payload: payload.to_vec(),
                log_time: now_ns(),
            };
            tx.send(t)
                .map_err(|_| "the writer stopped (see its error below)".to_string())
        });
    drop(tx);
    let written = writing
        .join()
        .map_err(|_| "the writer thread panicked".to_string())?
        .map_err(|e| e.to_string());
    match (tapped, written) {
        (Ok(s), Ok(n)) => Ok(NodeStats { frames_out: n, ..s }),
        (Err(e), Err(w)) => Err(format!("{e}; {w}")),
        (Err(e), _) | (_, Err(e)) => Err(e),
    }
}

/// How fast a replay runs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Rate {
    /// As fast as the graph takes frames.
    Max,
    /// This many times the recorded speed.
    Times(f64),
}

impl Rate {
    /// The slowest replay: a thousandth of the recorded speed (a second of recording in
    /// about 17 minutes).
    pub const SLOWEST: f64 = 1e-3;
    /// The fastest paced replay (`max` takes frames as fast as the graph does).
    pub const FASTEST: f64 = 1e3;

    /// Reads `1.0`, `0.5`, `max`.
    pub fn parse(s: &str) -> Result<Self, String> {
        if s == "max" {
            return Ok(Self::Max);
        }
        match s.parse::<f64>() {
            Ok(r) if (Self::SLOWEST..=Self::FASTEST).contains(&r) => Ok(Self::Times(r)),
            _ => Err(format!(
                "rate '{s}' is neither 'max' nor a speed from {} to {} (1.0 = recorded speed)",
                Self::SLOWEST,
                Self::FASTEST
            )),
        }
    }
}

/// `params` of a replay node (set by `microstereo replay`).
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReplayParams {
    /// The recording.
    pub file: PathBuf,
    /// The node whose outputs it replays.
    pub node: String,
    /// `max` or a speed factor.
    #[serde(default = "recorded_speed")]
    pub rate: String,
    /// Start again at the end, with frame numbers and times running on.
    #[serde(default)]
    pub r#loop: bool,
    /// Seconds of the recording (from its first frame's capture) to skip.
    #[serde(default)]
    pub start: f64,
    /// Seconds of the recording to replay from `start` (the rest of it without).
    #[serde(default)]
    pub duration: Option<f64>,
}

fn recorded_speed() -> String {
    "1.0".into()
}

/// Sends the recorded messages of one node's outputs, frame by frame, at recorded timing or
/// as fast as possible.
#[derive(Debug)]
pub struct ReplayNode {
    params: ReplayParams,
    rate: Rate,
    /// The node's outputs, in port order, as `NODE/OUTPUT`.
    edges: Vec<String>,
    frames: FrameReader,
    /// The first frame's capture time and when it was sent.
    clock: Option<(u64, Instant)>,
    /// Added to frame numbers and capture times after each loop.
    offset: (u64, u64),
    /// The first frame of the recording: number and capture time.
    first: Option<(u64, u64)>,
    /// The last frame sent from the recording: number and capture time.
    last: Option<(u64, u64)>,
    /// Frames skipped in earlier passes (some output missing).
    skipped: u64,
    /// The recording's first capture time (`start` counts from it).
    origin: Option<u64>,
}

impl ReplayNode {
    /// The replay source that a graph rewrite put in place of a recorded node.
    pub fn from_spec(spec: &NodeSpec) -> Result<Self, String> {
        let p: ReplayParams = runtime::registry::from_table(&spec.params)?;
        let outputs: Vec<String> = spec.outputs.iter().map(|(p, _)| p.clone()).collect();
        Self::new(p, &outputs)
    }

    /// A replay of node `params.node`, whose outputs are `outputs` (port names in order).
    pub fn new(params: ReplayParams, outputs: &[String]) -> Result<Self, String> {
        let rate = Rate::parse(&params.rate)?;
        if !(params.start >= 0.0 && params.start.is_finite())
            || params.duration.is_some_and(|d| !(d > 0.0 && d.is_finite()))
        {
            return Err(format!(
                "replay window start {} s, duration {:?} s: give a start of 0 or more and a duration above 0",
                params.start, params.duration
            ));
        }
        let edges: Vec<String> = outputs
            .iter()
            .map(|o| format!("{}/{o}", params.node))
            .collect();
        let frames = FrameReader::open(&params.file, edges.clone()).map_err(|e| e.to_string())?;
        Ok(Self {
            params,
            rate,
            edges,
            frames,
            clock: None,
            offset: (0, 0),
            first: None,
            last: None,
            skipped: 0,
            origin: None,
        })
    }

    /// The next whole frame of this pass, or `None` at its end.
    fn next_frame(&mut self) -> Result<Option<Vec<EdgeMessage>>, String> {
        loop {
            let Some(msgs) = self.frames.next().transpose().map_err(|e| e.to_string())? else {
                return Ok(None);
            };
            // The window `start`..`start + duration` of the recording's own clock.
            let ns = msgs[0].header.capture_ns;
            let origin = *self.origin.get_or_insert(ns);
            let from = origin.saturating_add((self.params.start * 1e9) as u64);
            if ns < from {
                continue;
            }
            if let Some(d) = self.params.duration
                && ns >= from.saturating_add((d * 1e9) as u64)
            {
                return Ok(None);
            }
            return Ok(Some(msgs));
        }
    }
}

impl GraphNode for ReplayNode {
    fn resumed(&mut self) {
        // After a pause the recorded timing goes on from the next frame.
        self.clock = None;
    }

    fn produce(&mut self, _seq: u64, out: &mut dyn Outputs) -> Result<bool, String> {
        let mut msgs = self.next_frame()?;
        if msgs.is_none() {
            self.skipped += self.frames.incomplete;
            if let (true, Some((first_seq, first_ns)), Some((last_seq, last_ns))) =
                (self.params.r#loop, self.first, self.last)
            {
                // Frame numbers and times run on past the end of the last pass.
                let frames = last_seq - first_seq + 1;
                let period = (last_ns - first_ns) / frames.saturating_sub(1).max(1);
                self.offset.0 += frames;
                self.offset.1 += last_ns - first_ns + period;
                self.frames = FrameReader::open(&self.params.file, self.edges.clone())
                    .map_err(|e| e.to_string())?;
                msgs = self.next_frame()?;
            }
        }
        let Some(msgs) = msgs else {
            for d in self.frames.lost().iter().chain(&self.frames.damaged()) {
                runtime::errln!("{}: {d}", self.params.file.display());
            }
            if self.skipped > 0 {
                runtime::errln!(
                    "{}: {} recorded frame(s) lack some of {} and were skipped",
                    self.params.file.display(),
                    self.skipped,
                    self.edges.join(", ")
                );
            }
            return Ok(false);
        };
        let (seq, ns) = (msgs[0].header.sequence, msgs[0].header.capture_ns);
        self.first.get_or_insert((seq, ns));
        self.last = Some((seq, ns));
        let ns_out = ns + self.offset.1;
        if let Rate::Times(r) = self.rate {
            let (c0, t0) = *self.clock.get_or_insert((ns_out, Instant::now()));
            let after = Duration::try_from_secs_f64(ns_out.saturating_sub(c0) as f64 / 1e9 / r)
                .unwrap_or(Duration::MAX);
            let wait = after.saturating_sub(t0.elapsed());
            // A stop cuts the wait short (a slow replay waits long between frames).
            if !runtime::signals::sleep(wait) {
                return Ok(false);
            }
        }
        for (port, m) in msgs.iter().enumerate() {
            let h = FrameHeader {
                sequence: m.header.sequence + self.offset.0,
                capture_ns: ns_out,
                ..m.header
            };
            out.send(port, h, m.payload.len(), &mut |b| {
                b.copy_from_slice(&m.payload)
            })?;
        }
        Ok(true)
    }
}

/// Checks that `path` holds every edge in `edges` with the message kind the graph expects:
/// one error naming what is missing or different, and how to fix it.
pub fn check_channels(
    path: &Path,
    overview: &crate::file::Overview,
    edges: &[(String, MessageKind)],
) -> Result<(), String> {
    let mut problems = Vec::new();
    for (edge, kind) in edges {
        let chans = overview.edge(edge);
        if chans.is_empty() {
            problems.push(format!("no channel for edge '{edge}'"));
        } else if let Some(c) = chans.iter().find(|c| c.kind != Some(*kind)) {
            problems.push(format!(
                "edge '{edge}' carries {} in the recording ({}) but {} in the launch file",
                c.kind.map_or("an unknown kind", |k| k.name()),
                c.schema,
                kind.name()
            ));
        }
    }
    if problems.is_empty() {
        return Ok(());
    }
    let have: Vec<&str> = overview
        .channels
        .iter()
        .filter_map(|c| c.edge.as_deref())
        .fold(Vec::new(), |mut v, e| {
            if !v.contains(&e) {
                v.push(e);
            }
            v
        });
    Err(format!(
        "{}: {}; it holds: {}. Record those edges (microstereo run --record FILE --edges NODE/OUTPUT) or replace other nodes",
        path.display(),
        problems.join("; "),
        if have.is_empty() {
            "no edges".to_string()
        } else {
            have.join(", ")
        }
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thinning_keeps_the_first_frame_at_or_after_every_nth() {
        let mut t = Thinning::new(3);
        let kept: Vec<u64> = (0..10).filter(|&s| t.keep(s)).collect();
        assert_eq!(kept, [0, 3, 6, 9]);
        // Frames the graph never let in shift the choice instead of leaving a gap.
        let mut t = Thinning::new(3);
        let kept: Vec<u64> = [1, 2, 5, 7, 8, 11, 12]
            .into_iter()
            .filter(|&s| t.keep(s))
            .collect();
        assert_eq!(kept, [1, 5, 8, 11]);
        // Every edge of the rate follows the first message of a frame to arrive.
        let mut t = Thinning::new(3);
        assert!(t.keep(4));
        assert!(!t.keep(5));
        assert!(t.keep(4), "a second edge's message of a kept frame");
        assert!(t.keep(7));
        assert!(!t.keep(6), "a late message of a frame not kept");
        let mut t = Thinning::new(1);
        assert!((0..5).all(|s| t.keep(s)));
    }

    #[test]
    fn edge_rates_match_patterns_and_refuse_conflicts_and_misses() {
        let edges: Vec<String> = ["rectify/frame", "segment/labels", "segment/cells"]
            .map(String::from)
            .into();
        let every = |pairs: &[(&str, u64)]| -> std::collections::BTreeMap<String, u64> {
            pairs.iter().map(|(p, n)| (p.to_string(), *n)).collect()
        };
        let (of, rates) =
            edge_rates(&every(&[("rectify/*", 10), ("*/labels", 10)]), &edges).unwrap();
        assert_eq!(of, [Some(0), Some(0), None]);
        assert_eq!(rates, [10]);
        let (of, rates) = edge_rates(
            &every(&[("rectify/frame", 10), ("segment/labels", 5)]),
            &edges,
        )
        .unwrap();
        assert_eq!(
            of.iter().map(|o| o.map(|k| rates[k])).collect::<Vec<_>>(),
            [Some(10), Some(5), None]
        );
        let e = edge_rates(&every(&[("segment/*", 10), ("*/cells", 5)]), &edges).unwrap_err();
        assert!(e.contains("segment/cells") && e.contains("one rate"), "{e}");
        let e = edge_rates(&every(&[("match/*", 2)]), &edges).unwrap_err();
        assert!(e.contains("matches no recorded edge"), "{e}");
        let e = edge_rates(&every(&[("segment/cells", 0)]), &edges).unwrap_err();
        assert!(e.contains("every 0"), "{e}");
    }
}
