//! A running graph's state, now: the supervisor publishes a snapshot on an iceoryx2 service
//! of its instance a few times a second; `microstereo top`, `topic` and `run`'s progress
//! line read it. Nothing here touches the graph's own edges: a reader of the status never
//! slows the graph.

use crate::launch::Graph;
use crate::stats::NodeStats;
use crate::transport::{EdgeConfig, EdgePublisher, EdgeSubscriber, Overflow, Transport};
use schemas::FrameHeader;
use serde::{Deserialize, Serialize};
use std::time::{Duration, Instant};

/// How often the supervisor publishes the status.
pub const STATUS_PERIOD: Duration = Duration::from_millis(250);

/// The header `kind` of a status message (no message kind of the schemas has it).
pub const STATUS_KIND: u32 = u32::MAX - 2;

/// The iceoryx2 service a run's status is published on (no node id has an `@`): one per
/// part of a graph split over hosts.
pub fn status_service(instance: &str, host: Option<&str>) -> String {
    match host {
        Some(h) => format!("microstereo/{instance}/@status/{h}"),
        None => format!("microstereo/{instance}/@status"),
    }
}

/// Every status service a run of `instance` may publish: the whole graph's and each host
/// part's.
pub fn status_services<'a, V>(
    instance: &'a str,
    hosts: &'a std::collections::BTreeMap<String, V>,
) -> impl Iterator<Item = String> + 'a {
    std::iter::once(status_service(instance, None))
        .chain(hosts.keys().map(move |h| status_service(instance, Some(h))))
}

/// A run as `top` and `topic` name it: `INSTANCE`, or `INSTANCE@HOST` for one part of a
/// graph split over hosts.
pub fn run_name(instance: &str, host: Option<&str>) -> String {
    match host {
        Some(h) => format!("{instance}@{h}"),
        None => instance.to_string(),
    }
}

/// What a node's processes are doing.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum NodeState {
    /// Its process runs and has not reported yet.
    Starting,
    /// Its process prepares its first frame (its report says what it does).
    Preparing,
    /// Its process runs and reports.
    Running,
    /// Its process ended and another starts after the back-off.
    Restarting,
    /// It ended cleanly.
    Exited,
    /// It failed beyond its restart policy.
    Failed,
}

impl NodeState {
    /// The word `top` shows.
    pub fn word(self) -> &'static str {
        match self {
            NodeState::Starting => "starting",
            NodeState::Preparing => "preparing",
            NodeState::Running => "running",
            NodeState::Restarting => "restarting",
            NodeState::Exited => "exited",
            NodeState::Failed => "failed",
        }
    }
}

/// One input of a node: which output it reads.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct InputInfo {
    /// The input's port.
    pub port: String,
    /// The writing node.
    pub node: String,
    /// The writer's output port.
    pub output: String,
}

/// One output of a node: its edge.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct OutputInfo {
    /// The output port.
    pub port: String,
    /// The message it carries.
    pub message: String,
    /// The edge's iceoryx2 service.
    pub service: String,
    /// Frames a reader may have queued.
    pub depth: usize,
    /// Whether the writer waits for a reader's full queue.
    pub lossless: bool,
    /// Its readers, as `NODE.PORT`.
    pub readers: Vec<String>,
}

/// One node of a running graph.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NodeStatus {
    /// Node id.
    pub id: String,
    /// Its kind (or the program of an `exec` node).
    pub kind: String,
    /// What its processes are doing.
    pub state: NodeState,
    /// Restarts so far.
    pub restarts: u32,
    /// The process running it now.
    pub pid: Option<u32>,
    /// Its figures so far over every process that ran it (`None` before its first report).
    pub stats: Option<NodeStats>,
    /// Its inputs, in the order of its statistics' inputs.
    pub inputs: Vec<InputInfo>,
    /// Its outputs.
    pub outputs: Vec<OutputInfo>,
}

/// A snapshot of a running graph.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GraphStatus {
    /// The run's instance name.
    pub instance: String,
    /// The part's host, for a graph split over hosts.
    #[serde(default)]
    pub host: Option<String>,
    /// The supervisor's process id.
    pub supervisor_pid: u32,
    /// The launch file it runs.
    pub launch: String,
    /// When the run started, ns since the Unix epoch.
    pub started_ns: u64,
    /// When this snapshot was taken, ns since the Unix epoch.
    pub now_ns: u64,
    /// The frames it was asked for (`None`: until stopped).
    pub frames: Option<u64>,
    /// The run is over: the last snapshot.
    pub ended: bool,
    /// The nodes, producers first.
    pub nodes: Vec<NodeStatus>,
    /// The graph's own ends ([`Graph::ends`]).
    pub ends: Vec<String>,
}

impl GraphStatus {
    /// A snapshot of `graph` with nothing reported yet (the supervisor fills in the rest).
    pub fn of(
        graph: &Graph,
        instance: &str,
        host: Option<&str>,
        frames: Option<u64>,
        started_ns: u64,
    ) -> Self {
        let readers = |id: &str, port: &str| -> Vec<String> {
            graph
                .nodes
                .iter()
                .flat_map(|n| n.inputs.iter().map(move |i| (n, i)))
                .filter(|(_, i)| i.node == id && i.output == port)
                .map(|(n, i)| format!("{}.{}", n.id, i.port))
                .collect()
        };
        Self {
            instance: instance.into(),
            host: host.map(String::from),
            supervisor_pid: std::process::id(),
            launch: graph.file.display().to_string(),
            started_ns,
            now_ns: started_ns,
            frames,
            ended: false,
            nodes: graph
                .nodes
                .iter()
                .filter(|n| host.is_none() || n.host.as_deref() == host)
                .map(|n| NodeStatus {
                    id: n.id.clone(),
                    kind: match &n.runner {
                        crate::launch::Runner::Builtin(k) => k.clone(),
                        crate::launch::Runner::Exec(p) => p.display().to_string(),
                    },
                    state: NodeState::Starting,
                    restarts: 0,
                    pid: None,
                    stats: None,
                    inputs: n
                        .inputs
                        .iter()
                        .map(|i| InputInfo {
                            port: i.port.clone(),
                            node: i.node.clone(),
                            output: i.output.clone(),
                        })
                        .collect(),
                    outputs: n
                        .outputs
                        .iter()
                        .map(|(port, kind)| {
                            let cfg = graph.edge_config(&n.id, port);
                            OutputInfo {
                                port: port.clone(),
                                message: kind.name().into(),
                                service: Graph::edge_name(instance, &n.id, port),
                                depth: cfg.depth,
                                lossless: cfg.overflow == Overflow::Block,
                                readers: readers(&n.id, port),
                            }
                        })
                        .collect(),
                })
                .collect(),
            ends: graph
                .ends()
                .iter()
                .filter(|n| host.is_none() || n.host.as_deref() == host)
                .map(|n| n.id.clone())
                .collect(),
        }
    }

    /// The node `id`.
    pub fn node(&self, id: &str) -> Option<&NodeStatus> {
        self.nodes.iter().find(|n| n.id == id)
    }

    /// Every edge as (writer, output): `NODE/PORT`, the name `topic` takes.
    pub fn edges(&self) -> impl Iterator<Item = (&NodeStatus, &OutputInfo)> {
        self.nodes
            .iter()
            .flat_map(|n| n.outputs.iter().map(move |o| (n, o)))
    }
}

/// A node's row of `top`: figures over the window between two snapshots.
#[derive(Clone, Debug, PartialEq)]
pub struct NodeRow {
    /// Node id.
    pub id: String,
    /// Its kind.
    pub kind: String,
    /// What its processes are doing.
    pub state: NodeState,
    /// Restarts so far.
    pub restarts: u32,
    /// Frames it handled so far.
    pub frames: u64,
    /// Frames a second over the window.
    pub rate: f64,
    /// Mean step time over the window, ms (`None`: no step in it).
    pub mean_ms: Option<f64>,
    /// 99th-percentile step time over the run so far, ms.
    pub p99_ms: f64,
    /// Its processes' CPU over the window, % of one core.
    pub cpu_percent: f64,
    /// What a preparing node does, or how long a running one has produced nothing (after
    /// [`QUIET_AFTER`]).
    pub note: Option<String>,
}

/// How long a running node may go without a step before `top` says so.
pub const QUIET_AFTER: std::time::Duration = std::time::Duration::from_secs(3);

/// An edge's row of `top` (one per reader): figures over the window between two snapshots.
#[derive(Clone, Debug, PartialEq)]
pub struct EdgeRow {
    /// `WRITER/OUTPUT → READER.PORT`.
    pub name: String,
    /// Messages a second the reader received over the window.
    pub rate: f64,
    /// Messages lost on the edge so far.
    pub dropped: u64,
    /// Frames of the stream that never reached the reader so far.
    pub missing: u64,
    /// Mean age of the frames the reader received over the window (capture to receipt), ms.
    pub latency_ms: Option<f64>,
}

/// The run as a whole: what `run`'s progress line shows.
#[derive(Clone, Debug, PartialEq)]
pub struct Progress {
    /// Frames through every end of the graph.
    pub done: u64,
    /// The frames asked for.
    pub frames: Option<u64>,
    /// Frames a second through the graph over the window.
    pub rate: f64,
    /// Messages lost on every edge so far.
    pub dropped: u64,
    /// Restarts so far.
    pub restarts: u32,
    /// Seconds since the run started.
    pub elapsed_s: f64,
}

/// Seconds between two snapshots (`None` when `prev` is not an earlier snapshot of the
/// same run).
fn window<'a>(prev: Option<&'a GraphStatus>, now: &GraphStatus) -> Option<(f64, &'a GraphStatus)> {
    let p = prev?;
    (p.now_ns < now.now_ns && p.started_ns == now.started_ns && p.instance == now.instance)
        .then(|| ((now.now_ns - p.now_ns) as f64 * 1e-9, p))
}

/// The nodes' rows over the window from `prev` to `now` (from the run's start without
/// `prev`).
pub fn node_rows(prev: Option<&GraphStatus>, now: &GraphStatus) -> Vec<NodeRow> {
    let w = window(prev, now);
    let since_start = ((now.now_ns.saturating_sub(now.started_ns)) as f64 * 1e-9).max(1e-9);
    now.nodes
        .iter()
        .map(|n| {
            let s = n.stats.clone().unwrap_or_default();
            let before = w
                .and_then(|(_, p)| p.node(&n.id))
                .and_then(|p| p.stats.clone())
                .unwrap_or_default();
            let secs = w.map_or(since_start, |(dt, _)| dt);
            let frames = s.frames_in.saturating_sub(before.frames_in);
            let busy = s.mean_ms * s.frames_in as f64 - before.mean_ms * before.frames_in as f64;
            let quiet_ns = now
                .now_ns
                .saturating_sub(s.last_step_end_ns.unwrap_or(now.started_ns));
            let note = match n.state {
                NodeState::Preparing => s.phase.clone(),
                NodeState::Running if !now.ended && quiet_ns >= QUIET_AFTER.as_nanos() as u64 => {
                    Some(format!("nothing for {:.0} s", quiet_ns as f64 * 1e-9))
                }
                _ => None,
            };
            NodeRow {
                id: n.id.clone(),
                kind: n.kind.clone(),
                state: n.state,
                restarts: n.restarts,
                frames: s.frames_in,
                rate: frames as f64 / secs,
                mean_ms: (frames > 0).then(|| (busy / frames as f64).max(0.0)),
                p99_ms: s.p99_ms,
                cpu_percent: ((s.cpu_ms - before.cpu_ms).max(0.0) / (secs * 1e3)) * 100.0,
                note,
            }
        })
        .collect()
}

/// The edges' rows (one per reader) over the window from `prev` to `now`.
pub fn edge_rows(prev: Option<&GraphStatus>, now: &GraphStatus) -> Vec<EdgeRow> {
    let w = window(prev, now);
    let since_start = ((now.now_ns.saturating_sub(now.started_ns)) as f64 * 1e-9).max(1e-9);
    let secs = w.map_or(since_start, |(dt, _)| dt);
    let mut rows = Vec::new();
    for n in &now.nodes {
        let before = w
            .and_then(|(_, p)| p.node(&n.id))
            .and_then(|p| p.stats.as_ref());
        for (k, i) in n.inputs.iter().enumerate() {
            let s = n
                .stats
                .as_ref()
                .and_then(|s| s.inputs.get(k))
                .cloned()
                .unwrap_or_default();
            let b = before
                .and_then(|b| b.inputs.get(k))
                .cloned()
                .unwrap_or_default();
            let got = s.received.saturating_sub(b.received);
            rows.push(EdgeRow {
                name: format!("{}/{} → {}.{}", i.node, i.output, n.id, i.port),
                rate: got as f64 / secs,
                dropped: s.dropped,
                missing: s.missing,
                latency_ms: (got > 0).then(|| (s.age_ms_sum - b.age_ms_sum).max(0.0) / got as f64),
            });
        }
    }
    rows
}

/// Frames through every end of the graph in `s`.
fn done(s: &GraphStatus) -> u64 {
    s.ends
        .iter()
        .map(|id| {
            s.node(id)
                .and_then(|n| n.stats.as_ref())
                .map_or(0, |st| st.frames_in)
        })
        .min()
        .unwrap_or(0)
}

/// The run's progress over the window from `prev` to `now`.
pub fn progress(prev: Option<&GraphStatus>, now: &GraphStatus) -> Progress {
    let elapsed_s = (now.now_ns.saturating_sub(now.started_ns)) as f64 * 1e-9;
    let d = done(now);
    let rate = match window(prev, now) {
        Some((dt, p)) => d.saturating_sub(done(p)) as f64 / dt,
        None => d as f64 / elapsed_s.max(1e-9),
    };
    Progress {
        done: d,
        frames: now.frames,
        rate,
        dropped: now
            .nodes
            .iter()
            .filter_map(|n| n.stats.as_ref())
            .flat_map(|s| &s.inputs)
            .map(|i| i.dropped)
            .sum(),
        restarts: now.nodes.iter().map(|n| n.restarts).sum(),
        elapsed_s,
    }
}

impl Progress {
    /// The one-line status `run` shows on a terminal.
    pub fn line(&self) -> String {
        format!(
            "{} frame(s){} · {:.1} frames/s · {} dropped · {} restart(s) · {:.0} s",
            self.done,
            self.frames.map_or(String::new(), |f| format!(" of {f}")),
            self.rate,
            self.dropped,
            self.restarts,
            self.elapsed_s
        )
    }
}

/// The supervisor's end of the status service.
pub struct StatusPublisher {
    // The publisher lives on the transport's iceoryx2 node.
    _transport: Transport,
    publisher: EdgePublisher,
    sent: u64,
}

/// The status edge: the newest snapshot only.
const STATUS_EDGE: EdgeConfig = EdgeConfig {
    depth: 1,
    overflow: Overflow::DropOldest,
};

impl StatusPublisher {
    /// Opens the status service of run `instance` (of its part on `host`).
    pub fn new(instance: &str, host: Option<&str>) -> Result<Self, String> {
        let transport =
            Transport::new(&format!("{instance}/supervisor")).map_err(|e| e.to_string())?;
        let publisher = transport
            .publisher(&status_service(instance, host), &STATUS_EDGE)
            .map_err(|e| e.to_string())?;
        Ok(Self {
            _transport: transport,
            publisher,
            sent: 0,
        })
    }

    /// Publishes `status`.
    pub fn publish(&mut self, status: &GraphStatus) -> Result<(), String> {
        let json = serde_json::to_vec(status).map_err(|e| e.to_string())?;
        let header = FrameHeader {
            sequence: self.sent,
            capture_ns: status.now_ns,
            kind: STATUS_KIND,
            ..FrameHeader::default()
        };
        self.publisher
            .send(header, json.len(), |b| b.copy_from_slice(&json))
            .map_err(|e| e.to_string())?;
        self.sent += 1;
        Ok(())
    }
}

/// A reader of a running graph's status.
pub struct StatusReader {
    transport: Transport,
    sub: EdgeSubscriber,
}

impl StatusReader {
    /// Attaches to run `name` ([`run_name`]: `INSTANCE` or `INSTANCE@HOST`), waiting up to
    /// `patience` for it to start.
    pub fn open(name: &str, patience: Duration) -> Result<Self, String> {
        let (instance, host) = match name.split_once('@') {
            Some((i, h)) => (i, Some(h)),
            None => (name, None),
        };
        let transport =
            Transport::new(&format!("watch-{}", std::process::id())).map_err(|e| e.to_string())?;
        let t0 = Instant::now();
        let sub = loop {
            match transport.watcher(&status_service(instance, host)) {
                Ok(s) => break s,
                Err(e) if t0.elapsed() >= patience => {
                    return Err(format!(
                        "no graph is running as '{name}' ({e}): start one with `microstereo run --instance {instance}`, or give --instance of a running one"
                    ));
                }
                Err(_) => {
                    if !transport.sleep(Duration::from_millis(50)) {
                        return Err("stopped".into());
                    }
                }
            }
        };
        Ok(Self { transport, sub })
    }

    /// The newest snapshot published within `timeout` (`None` when none came).
    pub fn next(&self, timeout: Duration) -> Result<Option<GraphStatus>, String> {
        let t0 = Instant::now();
        let mut newest = None;
        loop {
            while let Some(m) = self.sub.receive().map_err(|e| e.to_string())? {
                if m.user_header().kind == STATUS_KIND {
                    newest = Some(
                        serde_json::from_slice::<GraphStatus>(m.payload())
                            .map_err(|e| format!("a status message did not read: {e}"))?,
                    );
                }
            }
            if newest.is_some() || t0.elapsed() >= timeout {
                return Ok(newest);
            }
            if !self.transport.sleep(Duration::from_millis(10)) {
                return Ok(newest);
            }
        }
    }

    /// The transport this reader is on (to open watchers of the graph's edges beside it).
    pub fn transport(&self) -> &Transport {
        &self.transport
    }
}

/// The lock file of run `name` ([`run_name`]; [`crate::supervisor`] holds it while it runs).
pub(crate) fn lock_path(name: &str) -> std::path::PathBuf {
    std::env::temp_dir().join(format!("microstereo-{name}.lock"))
}

/// The runs going on on this machine now, newest first: instance names whose lock a
/// supervisor holds.
pub fn running_instances() -> Vec<String> {
    use std::os::fd::AsRawFd;
    let Ok(dir) = std::fs::read_dir(std::env::temp_dir()) else {
        return Vec::new();
    };
    let mut found: Vec<(std::time::SystemTime, String)> = dir
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let instance = name.strip_prefix("microstereo-")?.strip_suffix(".lock")?;
            let f = std::fs::File::open(e.path()).ok()?;
            // SAFETY: flock on a descriptor this function owns; no memory is involved.
            let free = unsafe { libc::flock(f.as_raw_fd(), libc::LOCK_SH | libc::LOCK_NB) } == 0;
            // A shared lock taken only to look is let go with the file.
            (!free).then(|| {
                (
                    e.metadata().and_then(|m| m.modified()).ok(),
                    instance.to_string(),
                )
            })
        })
        .filter_map(|(t, i)| Some((t?, i)))
        .collect();
    found.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
    found.into_iter().map(|(_, i)| i).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stats::InputStats;

    fn snapshot(at_s: u64, frames: u64, cpu_ms: f64, received: u64, age: f64) -> GraphStatus {
        let s = 1_000_000_000;
        let stats = |id: &str, mean: f64| NodeStats {
            id: id.into(),
            frames_in: frames,
            mean_ms: mean,
            cpu_ms,
            p99_ms: 2.0 * mean,
            inputs: vec![InputStats {
                port: "in".into(),
                received,
                age_ms_sum: age,
                dropped: 1,
                ..InputStats::default()
            }],
            ..NodeStats::default()
        };
        let node = |id: &str, mean: f64| NodeStatus {
            id: id.into(),
            kind: "k".into(),
            state: NodeState::Running,
            restarts: 0,
            pid: Some(1),
            stats: Some(stats(id, mean)),
            inputs: vec![InputInfo {
                port: "in".into(),
                node: "src".into(),
                output: "out".into(),
            }],
            outputs: Vec::new(),
        };
        GraphStatus {
            instance: "i".into(),
            host: None,
            supervisor_pid: 1,
            launch: "l".into(),
            started_ns: 10 * s,
            now_ns: (10 + at_s) * s,
            frames: Some(100),
            ended: false,
            nodes: vec![node("a", 4.0), node("b", 8.0)],
            ends: vec!["a".into(), "b".into()],
        }
    }

    #[test]
    fn rows_measure_the_window_between_two_snapshots() {
        // 2 s in: 20 frames, 30 received at 5 ms each; 4 s in: 60 frames (mean 4 ms over
        // the run), 110 received at 7 ms each.
        let a = snapshot(2, 20, 100.0, 30, 150.0);
        let b = snapshot(4, 60, 700.0, 110, 150.0 + 80.0 * 7.0);
        let n = node_rows(Some(&a), &b);
        assert_eq!(n[0].rate, 20.0);
        assert!((n[0].mean_ms.unwrap() - 4.0).abs() < 1e-9);
        assert_eq!((n[0].frames, n[0].p99_ms), (60, 8.0));
        // 600 ms of CPU in 2 s.
        assert!((n[0].cpu_percent - 30.0).abs() < 1e-9);
        let e = edge_rows(Some(&a), &b);
        assert_eq!(e.len(), 2);
        assert_eq!(e[0].name, "src/out → a.in");
        assert_eq!(e[0].rate, 40.0);
        assert!((e[0].latency_ms.unwrap() - 7.0).abs() < 1e-9);
        let p = progress(Some(&a), &b);
        assert_eq!((p.done, p.rate, p.dropped, p.elapsed_s), (60, 20.0, 2, 4.0));
        assert_eq!(
            p.line(),
            "60 frame(s) of 100 · 20.0 frames/s · 2 dropped · 0 restart(s) · 4 s"
        );
        // Without an earlier snapshot (or with one of another run): since the start.
        let first = node_rows(None, &b);
        assert_eq!(first[0].rate, 15.0);
        let mut other = a.clone();
        other.started_ns += 1;
        assert_eq!(progress(Some(&other), &b).rate, 15.0);
        // No step in the window: no mean.
        assert_eq!(
            node_rows(Some(&b), &snapshot(5, 60, 700.0, 110, 0.0))[0].mean_ms,
            None
        );
    }

    #[test]
    fn a_published_status_reaches_a_reader_of_its_instance() {
        let _domain = crate::process::ReleaseDomain;
        let instance = format!("status-test-{}", std::process::id());
        let mut p = StatusPublisher::new(&instance, None).unwrap();
        let r = StatusReader::open(&instance, Duration::from_secs(5)).unwrap();
        let mut s = snapshot(1, 5, 10.0, 5, 5.0);
        s.instance = instance.clone();
        // The service keeps no history: a reader gets what is published after it came.
        let t0 = Instant::now();
        let got = loop {
            p.publish(&s).unwrap();
            if let Some(g) = r.next(Duration::from_millis(50)).unwrap() {
                break g;
            }
            assert!(t0.elapsed() < Duration::from_secs(10), "no status arrived");
        };
        assert_eq!(got, s);
        let err = StatusReader::open("no-such-run-here", Duration::ZERO)
            .err()
            .unwrap();
        assert!(
            err.contains("no graph is running as 'no-such-run-here'"),
            "{err}"
        );
    }
}
