//! One node as its own process: inputs and outputs on shared memory, one step per frame.
//!
//! A source produces frames (paced by `fps`, or as fast as it can). Any other node sleeps in a
//! WaitSet until an input has data, joins its inputs by frame number (frames present on
//! every input, oldest first; a frame some input never got is dropped), steps, and
//! publishes its outputs
//! in loaned shared memory under the same frame number. Given a frame count, it ends after
//! the last frame, or once every input has sent an end marker (the last frames were lost
//! upstream, with a killed node); either way it sends an end marker on its outputs, and
//! again to each reader that connects later. A node that other nodes of the graph read then
//! stays until it is told to stop, because a publisher that leaves takes its unread frames
//! along. On exit it prints one [`NodeStats`] line for the supervisor.

pub use crate::edge::now_ns;
use crate::launch::Graph;
use crate::node::{GraphNode, Msg, Outputs};
use crate::registry::Registry;
use crate::restarts::Restarts;
pub use crate::stats::{InputStats, NodeStats, STATS_PREFIX};
pub(crate) use crate::stats::{mean, percentile};
use crate::transport::{
    EdgePublisher, EdgeSubscriber, Message, Overflow, Received, Transport, Wake, wait_loop,
};
use iceoryx2::node::NodeView;
use iceoryx2::prelude::*;
use schemas::FrameHeader;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

struct ShmOutputs<'a> {
    pubs: &'a [EdgePublisher],
    sent: u64,
}

impl Outputs for ShmOutputs<'_> {
    fn send(
        &mut self,
        port: usize,
        header: FrameHeader,
        len: usize,
        fill: &mut dyn FnMut(&mut [u8]),
    ) -> Result<(), String> {
        let p = self
            .pubs
            .get(port)
            .ok_or_else(|| format!("no output port {port}"))?;
        p.send(header, len, |b| fill(b))
            .map_err(|e| e.to_string())?;
        self.sent += 1;
        Ok(())
    }
}

/// The file through which the supervisor pauses and steps source `id` of run `instance`
/// (its terminal's `p` and `s`): `PAUSES STEPS`, two counts that only grow; an odd number
/// of pauses holds the source, each step lets one frame through.
pub fn control_path(instance: &str, id: &str) -> PathBuf {
    std::env::temp_dir().join(format!("microstereo-{instance}-{id}.control"))
}

/// Set (by the supervisor) for a source its terminal pauses and steps: only such a source
/// reads its control file between frames.
pub const CONTROL_ENV: &str = "MICROSTEREO_CONTROLLED";

/// Where a source is with its pause requests.
struct PauseState {
    /// The control file, for a source the terminal controls.
    path: Option<PathBuf>,
    steps: Option<u64>,
}

impl PauseState {
    fn new(instance: &str, id: &str) -> Self {
        Self {
            path: std::env::var_os(CONTROL_ENV).map(|_| control_path(instance, id)),
            steps: None,
        }
    }

    /// Whether to hold the next frame back now (a step lets one through).
    fn hold(&mut self) -> bool {
        let Some(path) = &self.path else {
            return false;
        };
        // No file: not paused.
        let (pauses, steps) = std::fs::read_to_string(path)
            .ok()
            .and_then(|t| {
                let mut w = t.split_whitespace().map(|x| x.parse::<u64>().ok());
                Some((w.next()??, w.next()??))
            })
            .unwrap_or((0, 0));
        let seen = *self.steps.get_or_insert(steps);
        if pauses % 2 == 0 {
            self.steps = Some(steps);
            return false;
        }
        if steps > seen {
            self.steps = Some(seen + 1);
            return false;
        }
        true
    }
}

/// The reader name of a source's in-flight count ([`crate::launch::InFlight`]).
const IN_FLIGHT_PORT: &str = "in-flight";

/// Without a frame coming out for this long, the frames a source counts as in flight are
/// taken as lost (a node restarted, say) and let go, so that the source cannot stall.
const IN_FLIGHT_PATIENCE: Duration = Duration::from_secs(2);

/// A source's count of its frames in flight: those it sent that have not come out of the
/// output its `in_flight` names.
struct InFlightGate {
    done: EdgeSubscriber,
    limit: u64,
    /// Frames sent and not seen done, oldest first.
    out: std::collections::VecDeque<u64>,
    /// When a frame last came out (or the count began).
    progress: Instant,
}

impl InFlightGate {
    fn new(
        transport: &Transport,
        graph: &Graph,
        instance: &str,
        id: &str,
        f: &crate::launch::InFlight,
    ) -> Result<Self, String> {
        let (node, output) = f
            .output()
            .ok_or_else(|| format!("in_flight.after = \"{}\" is not NODE/OUTPUT", f.after))?;
        let done = transport
            .reader(
                &Graph::edge_name(instance, node, output),
                &graph.edge_config(node, output),
                Some(&reader_name(id, IN_FLIGHT_PORT)),
            )
            .map_err(|e| e.to_string())?;
        Ok(Self {
            done,
            limit: f.frames,
            out: std::collections::VecDeque::new(),
            progress: Instant::now(),
        })
    }

    /// Whether there is room for one more frame now.
    fn open(&mut self) -> Result<bool, String> {
        while let Some(m) = self.done.receive().map_err(|e| e.to_string())? {
            // A frame done carries every older one still counted: those were lost.
            let seq = m.user_header().sequence;
            while self.out.front().is_some_and(|&s| s <= seq) {
                self.out.pop_front();
            }
            self.progress = Instant::now();
        }
        if self.progress.elapsed() > IN_FLIGHT_PATIENCE {
            self.out.clear();
            self.progress = Instant::now();
        }
        Ok((self.out.len() as u64) < self.limit)
    }

    /// Waits until there is room for one more frame; false when the node was asked to stop
    /// first.
    fn wait(&mut self, transport: &Transport) -> Result<bool, String> {
        while !self.open()? {
            if !transport.sleep(Duration::from_millis(1)) {
                return Ok(false);
            }
        }
        Ok(true)
    }

    /// Frame `seq` was sent.
    fn sent(&mut self, seq: u64) {
        if self.out.is_empty() {
            self.progress = Instant::now();
        }
        self.out.push_back(seq);
    }
}

/// The least queue depth of an edge from another host, on the reading host.
const REMOTE_DEPTH: usize = 8;

/// The reader name of a host's link on an edge (iceoryx2's link names none of its ports).
const LINK_READER: &str = "";

/// How long a writer waits for its readers on other hosts before it sends anyway.
const REMOTE_READERS_PATIENCE: Duration = Duration::from_secs(60);

/// After the other host's readers run, the time its link takes to bridge their edges
/// (a discovery round there, and Zenoh's declaration of it here).
const LINK_SETTLE: Duration = Duration::from_millis(400);

/// Waits until node `spec`'s readers on other hosts run (their parts' status says so): a
/// frame sent before the link over there bridged the edge would reach none of them.
fn wait_for_readers_elsewhere(
    graph: &Graph,
    instance: &str,
    spec: &crate::launch::NodeSpec,
    transport: &Transport,
) {
    let mut waiting: Vec<(String, String)> = Vec::new();
    for (port, _) in &spec.outputs {
        for (r, _) in graph.readers_of(&spec.id, port) {
            if graph.apart(r, &spec.id)
                && let Some(h) = graph.host_of(r)
                && !waiting.iter().any(|(n, _)| n == r)
            {
                waiting.push((r.to_string(), h.to_string()));
            }
        }
    }
    if waiting.is_empty() {
        return;
    }
    let t0 = Instant::now();
    let mut readers: std::collections::HashMap<String, crate::status::StatusReader> =
        Default::default();
    while !waiting.is_empty() {
        if t0.elapsed() > REMOTE_READERS_PATIENCE {
            crate::errln!(
                "warning: the readers on other hosts ({}) did not start within {} s; sending anyway",
                waiting
                    .iter()
                    .map(|(n, h)| format!("{n} on {h}"))
                    .collect::<Vec<_>>()
                    .join(", "),
                REMOTE_READERS_PATIENCE.as_secs()
            );
            return;
        }
        for (_, h) in &waiting {
            if !readers.contains_key(h)
                && let Ok(r) = crate::status::StatusReader::open(
                    &crate::status::run_name(instance, Some(h)),
                    Duration::ZERO,
                )
            {
                readers.insert(h.clone(), r);
            }
        }
        let mut running = Vec::new();
        for (h, r) in &readers {
            if let Ok(Some(s)) = r.next(Duration::ZERO) {
                running.extend(
                    s.nodes
                        .iter()
                        .filter(|n| n.state == crate::status::NodeState::Running)
                        .map(|n| (n.id.clone(), h.clone())),
                );
            }
        }
        waiting.retain(|w| !running.contains(w));
        if !waiting.is_empty() && !transport.sleep(Duration::from_millis(20)) {
            return;
        }
    }
    transport.sleep(LINK_SETTLE);
}

/// The name under which node `id` reads its input `port`.
fn reader_name(id: &str, port: &str) -> String {
    format!("{id}.{port}")
}

/// The reading ends of node `spec`'s inputs in run `instance`, named so its writers see them.
fn readers(
    transport: &Transport,
    graph: &Graph,
    instance: &str,
    spec: &crate::launch::NodeSpec,
) -> Result<Vec<EdgeSubscriber>, String> {
    spec.inputs
        .iter()
        .map(|i| {
            let (edge, cfg, name) = (
                Graph::edge_name(instance, &i.node, &i.output),
                graph.edge_config(&i.node, &i.output),
                reader_name(&spec.id, &i.port),
            );
            if graph.apart(&i.node, &spec.id) {
                // Frames from another host come in bursts (the network's, the link's
                // rounds): a deeper queue takes them without making the link wait.
                let cfg = crate::edge::EdgeConfig {
                    depth: cfg.depth.max(REMOTE_DEPTH),
                    ..cfg
                };
                transport.remote_reader(&edge, &cfg, &name)
            } else {
                transport.reader(&edge, &cfg, Some(&name))
            }
        })
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| e.to_string())
}

/// What each input of `spec` lost, from its reading end.
fn input_stats<'a>(
    spec: &crate::launch::NodeSpec,
    subs: impl IntoIterator<Item = &'a EdgeSubscriber>,
) -> Vec<InputStats> {
    spec.inputs
        .iter()
        .zip(subs)
        .map(|(i, s)| {
            let (first, last) = s.frames_seen();
            InputStats {
                port: i.port.clone(),
                dropped: s.dropped(),
                missing: s.missing(),
                first,
                last,
                end: s.end(),
                received: s.received(),
                age_ms_sum: s.age_ms_sum(),
            }
        })
        .collect()
}

/// Least time between two progress reports of a node.
pub const PROGRESS_PERIOD: Duration = Duration::from_millis(20);

/// What a node has done so far: its step and latency times, and when it last said so. A
/// node reports its statistics after a step (at most every [`PROGRESS_PERIOD`]) and while it
/// waits, not only when it ends: the supervisor keeps the last report of a node that dies
/// (killed, it has no last word) and adds it to its successor's.
struct Tally {
    times: Vec<f64>,
    latencies: Vec<f64>,
    last_frame: Option<u64>,
    reported: Instant,
    /// When the first and the last step ended (ns since the Unix epoch).
    ends: Option<(u64, u64)>,
}

impl Tally {
    fn new() -> Self {
        Self {
            times: Vec::new(),
            latencies: Vec::new(),
            last_frame: None,
            ends: None,
            // The first step reports at once.
            reported: Instant::now()
                .checked_sub(PROGRESS_PERIOD)
                .unwrap_or_else(Instant::now),
        }
    }

    /// A source's frame about to be made, reported before it is: a source killed after
    /// sending it but before its report would otherwise have its successor make that
    /// frame number again, and the nodes downstream take it twice. Killed before sending
    /// it, the frame is missing downstream, lost in the dead process.
    fn claim<'a>(
        &mut self,
        frame: u64,
        id: &str,
        spec: &crate::launch::NodeSpec,
        sent: u64,
        subs: impl IntoIterator<Item = &'a EdgeSubscriber>,
    ) {
        self.last_frame = Some(frame);
        print_stats(&self.stats(id, spec, sent, subs));
        self.reported = Instant::now();
    }

    fn step(&mut self, ms: f64, latency_ms: f64, frame: u64) {
        let now = crate::edge::now_ns();
        self.ends = Some((self.ends.map_or(now, |e| e.0), now));
        self.times.push(ms);
        self.latencies.push(latency_ms);
        self.last_frame = Some(frame);
    }

    fn stats<'a>(
        &self,
        id: &str,
        spec: &crate::launch::NodeSpec,
        sent: u64,
        subs: impl IntoIterator<Item = &'a EdgeSubscriber>,
    ) -> NodeStats {
        let mut times = self.times.clone();
        let mut latencies = self.latencies.clone();
        NodeStats {
            id: id.into(),
            frames_in: self.times.len() as u64,
            frames_out: sent,
            mean_ms: mean(&self.times),
            p99_ms: percentile(&mut times, 0.99),
            inputs: input_stats(spec, subs),
            latency_ms: mean(&self.latencies),
            last_frame: self.last_frame,
            runs: 1,
            cpu_ms: crate::stats::process_cpu_ms(),
            latency_p50_ms: percentile(&mut latencies, 0.5),
            latency_p99_ms: percentile(&mut latencies, 0.99),
            first_step_end_ns: self.ends.map(|e| e.0),
            last_step_end_ns: self.ends.map(|e| e.1),
            phase: None,
        }
    }

    /// Prints the statistics so far when the last report is old enough.
    fn report<'a>(
        &mut self,
        id: &str,
        spec: &crate::launch::NodeSpec,
        sent: u64,
        subs: impl IntoIterator<Item = &'a EdgeSubscriber>,
    ) {
        if self.reported.elapsed() >= PROGRESS_PERIOD {
            print_stats(&self.stats(id, spec, sent, subs));
            self.reported = Instant::now();
        }
    }
}

/// Runs node `id` of `graph` until its frames are done or it is told to stop.
pub fn run_node(
    graph: &Graph,
    instance: &str,
    id: &str,
    node: &mut dyn GraphNode,
    frames: Option<u64>,
    generation: u64,
) -> Result<NodeStats, String> {
    let fps = node.fps();
    let spec = graph
        .node(id)
        .ok_or_else(|| format!("no node '{id}' in {}", graph.file.display()))?;
    // Named after the run too, so that iceoryx2's node list tells the runs apart.
    let transport = Transport::new(&format!("{instance}/{id}")).map_err(|e| e.to_string())?;
    let pubs = spec
        .outputs
        .iter()
        .map(|(port, _)| {
            transport.publisher(
                &Graph::edge_name(instance, id, port),
                &graph.edge_config(id, port),
            )
        })
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| e.to_string())?;
    // Feedback inputs come after the joined ones: they are polled for their newest
    // message, the others are joined by frame.
    let mut subs = readers(&transport, graph, instance, spec)?;
    let joined = spec.inputs.iter().filter(|i| !i.feedback).count();
    let feedback: Vec<(usize, EdgeSubscriber)> = subs
        .split_off(joined)
        .into_iter()
        .enumerate()
        .map(|(j, s)| (joined + j, s))
        .collect();
    // A frame sent before a reader connects never reaches it (edges keep no history): wait
    // until every reader the graph names is there (readers outside the graph, such as a
    // test, do not count). Only at start, so a short sleep is fine.
    let expected: Vec<Vec<String>> = spec
        .outputs
        .iter()
        .map(|(port, _)| {
            let mut want: Vec<String> = graph
                .readers_of(id, port)
                .filter(|(r, _)| !graph.apart(r, id))
                .map(|(_, name)| name)
                .collect();
            // Readers on another host: this host's link reads the edge for them.
            if graph.readers_of(id, port).any(|(r, _)| graph.apart(r, id)) {
                want.push(LINK_READER.into());
            }
            want
        })
        .collect();
    let read_in_graph = graph.is_read(id);
    let t0 = Instant::now();
    while pubs.iter().zip(&expected).any(|(p, want)| {
        let have = p.reader_names();
        want.iter().any(|w| !have.contains(w))
    }) {
        if t0.elapsed() > Duration::from_secs(30) {
            crate::errln!("warning: not every reader connected within 30 s; sending anyway");
            break;
        }
        if !transport.sleep(Duration::from_millis(2)) {
            return Ok(stopped_early(id));
        }
    }
    wait_for_readers_elsewhere(graph, instance, spec, &transport);
    if crate::signals::stop_requested() {
        return Ok(stopped_early(id));
    }
    // A restarted node tells the nodes downstream that the frames its predecessor held are
    // gone, before any frame of its own (see [`Restarts`]).
    if generation > 0 {
        for p in &pubs {
            p.send_restart(generation, id).map_err(|e| e.to_string())?;
        }
    }
    let mut out = ShmOutputs {
        pubs: &pubs,
        sent: 0,
    };
    let mut tally = Tally::new();
    // A first report once the node's edges are up: its part's status shows it running
    // (what writers on other hosts wait for).
    tally.report(
        id,
        spec,
        0,
        subs.iter().chain(feedback.iter().map(|(_, s)| s)),
    );
    let run = NodeLoop {
        graph,
        instance,
        id,
        spec,
        transport: &transport,
        pubs: &pubs,
        feedback: &feedback,
        frames,
        read_in_graph,
    };
    if subs.is_empty() {
        run.produce(node, &mut out, &mut tally, fps)?;
    } else {
        run.join(node, &subs, &mut out, &mut tally)?;
    }
    Ok(tally.stats(
        id,
        spec,
        out.sent,
        subs.iter().chain(feedback.iter().map(|(_, s)| s)),
    ))
}

/// A node's loop once its edges are up: what a source's production and a task's joining
/// of its inputs share.
struct NodeLoop<'a> {
    graph: &'a Graph,
    instance: &'a str,
    id: &'a str,
    spec: &'a crate::launch::NodeSpec,
    transport: &'a Transport,
    pubs: &'a [EdgePublisher],
    /// The feedback inputs, with their index among the node's inputs.
    feedback: &'a [(usize, EdgeSubscriber)],
    frames: Option<u64>,
    read_in_graph: bool,
}

impl NodeLoop<'_> {
    /// Gives the node the newest message of each feedback input that brought one.
    fn feed(&self, node: &mut dyn GraphNode) -> Result<(), String> {
        for (k, s) in self.feedback {
            let mut newest = None;
            while let Some(m) = s.receive().map_err(|e| e.to_string())? {
                newest = Some(m);
            }
            if let Some(m) = newest {
                node.feedback(
                    *k,
                    Msg {
                        header: *m.user_header(),
                        payload: m.payload(),
                    },
                )?;
            }
        }
        Ok(())
    }

    /// A source: frames made at its pace (`fps`), held while paused, let in as the graph's
    /// in-flight limit allows, until it has no more, `frames` are made or it is stopped;
    /// then its end marker.
    fn produce(
        &self,
        node: &mut dyn GraphNode,
        out: &mut ShmOutputs,
        tally: &mut Tally,
        fps: Option<f64>,
    ) -> Result<(), String> {
        let (graph, instance, id, spec) = (self.graph, self.instance, self.id, self.spec);
        let (transport, pubs, feedback) = (self.transport, self.pubs, self.feedback);
        let (frames, read_in_graph) = (self.frames, self.read_in_graph);
        // A rate too small for a period (the kinds check their rates) counts as the slowest.
        let period = fps
            .filter(|f| *f > 0.0)
            .map(|f| Duration::try_from_secs_f64(1.0 / f).unwrap_or(Duration::MAX));
        let start = Instant::now();
        let first = first_frame_from_env()?;
        let mut seq = first;
        let mut stopped = false;
        let mut in_flight = match &spec.in_flight {
            Some(f) => Some(InFlightGate::new(transport, graph, instance, id, f)?),
            None => None,
        };
        let mut start = start;
        let mut pause = PauseState::new(instance, id);
        while frames.is_none_or(|n| seq < n) {
            // Paused from the terminal (`replay`): no frame until resumed or stepped; a
            // stop still ends it.
            let held = Instant::now();
            let mut was_held = false;
            while pause.hold() {
                was_held = true;
                // Reports go on while held (the watchdog, the status).
                tally.report(id, spec, out.sent, feedback.iter().map(|(_, s)| s));
                if !transport.sleep(Duration::from_millis(20)) {
                    stopped = true;
                    break;
                }
            }
            if stopped {
                break;
            }
            if was_held {
                start += held.elapsed();
                node.resumed();
            }
            // A paced source more than a frame behind its schedule (a loaded machine) starts
            // a new one from now instead of sending what it missed back to back: a camera
            // skips the frames it could not deliver. Catching up sent 29.7 frames/s for a
            // while at fps = 20 under two CPU hogs.
            if let Some(p) = period
                && let Some(t) = due(start, p, seq - first)
                && let Some(late) = Instant::now().checked_duration_since(t)
                && late > p
            {
                start += late;
            }
            // Also the place where a stop request is noticed between frames.
            let wait = period.map_or(Duration::ZERO, |p| {
                due(start, p, seq - first)
                    .map_or(p, |t| t.saturating_duration_since(Instant::now()))
            });
            if !sleep_beating(transport, wait, || {
                tally.report(id, spec, out.sent, feedback.iter().map(|(_, s)| s))
            }) {
                stopped = true;
                break;
            }
            // Too many frames in flight: a paced source lets this one go (a camera's frame
            // is dropped at the entrance), an unpaced one waits for room.
            if let Some(gate) = &mut in_flight {
                if period.is_some() {
                    if !gate.open()? {
                        seq += 1;
                        continue;
                    }
                } else if !gate.wait(transport)? {
                    stopped = true;
                    break;
                }
            }
            self.feed(node)?;
            tally.claim(seq, id, spec, out.sent, feedback.iter().map(|(_, s)| s));
            let (t, t_ns) = (Instant::now(), now_ns());
            match node.produce(seq, out) {
                Ok(true) => {}
                Ok(false) => break,
                // A stop request cuts a waiting send short with an error: the stop is what
                // happened.
                Err(_) if !transport.sleep(Duration::ZERO) => {
                    stopped = true;
                    break;
                }
                Err(e) => return Err(e),
            }
            tally.step(
                t.elapsed().as_secs_f64() * 1e3,
                now_ns().saturating_sub(t_ns) as f64 / 1e6,
                seq,
            );
            tally.report(id, spec, out.sent, feedback.iter().map(|(_, s)| s));
            if let Some(gate) = &mut in_flight {
                gate.sent(seq);
            }
            seq += 1;
        }
        if !stopped {
            let last = seq.checked_sub(1);
            let mut ends = EndMarkers::new(pubs, last);
            linger(transport, read_in_graph, || {
                ends.resend();
                tally.report(id, spec, out.sent, feedback.iter().map(|(_, s)| s))
            });
        }
        Ok(())
    }

    /// A task or a sink: its inputs' messages joined by frame number (inputs ahead hold
    /// theirs, frames passed over or lost upstream let go), one step per complete frame,
    /// until every input's stream ended, `frames` are done or it is stopped; then its end
    /// marker.
    fn join(
        &self,
        node: &mut dyn GraphNode,
        subs: &[EdgeSubscriber],
        out: &mut ShmOutputs,
        tally: &mut Tally,
    ) -> Result<(), String> {
        let (graph, id, spec) = (self.graph, self.id, self.spec);
        let (transport, pubs, feedback) = (self.transport, self.pubs, self.feedback);
        let (frames, read_in_graph) = (self.frames, self.read_in_graph);
        let refs: Vec<&EdgeSubscriber> = subs.iter().collect();
        let mut pending: Vec<Vec<Message>> = subs.iter().map(|_| Vec::new()).collect();
        let seq_of = |m: &Message| m.user_header().sequence;
        let mut done = false;
        // Per input, the stream's last frame number once its writer said it had ended.
        let mut ended: Vec<Option<u64>> = vec![None; subs.len()];
        let mut restarts = Restarts::new(graph, spec, subs.len());
        // The last frame number each input delivered.
        let mut last_seq: Vec<Option<u64>> = vec![None; subs.len()];
        let joined = wait_loop::<String>(&refs, Duration::from_millis(500), |wake, _| {
            if wake == Wake::Stop {
                return Ok(false);
            }
            tally.report(
                id,
                spec,
                out.sent,
                subs.iter().chain(feedback.iter().map(|(_, s)| s)),
            );
            for (i, s) in subs.iter().enumerate() {
                loop {
                    // An input ahead of the others holds its frames until they catch up, up
                    // to its borrow limit: then a lossy edge lets its oldest go, a lossless
                    // one leaves the rest queued (its writer waits) — unless a restart
                    // upstream lost frames that the other inputs will never be joined with.
                    if pending[i].len() >= crate::transport::max_held(&s.config()) {
                        if s.config().overflow == Overflow::DropOldest || restarts.active() {
                            pending[i].remove(0);
                            s.discard();
                        } else {
                            break;
                        }
                    }
                    match s.receive_item()? {
                        Some(Received::Frame(m)) => {
                            last_seq[i] = Some(seq_of(&m));
                            restarts.frame(i);
                            pending[i].push(m);
                        }
                        Some(Received::Restart { generation, node }) => {
                            for (g, n) in restarts.marker(i, generation, &node) {
                                for p in pubs {
                                    p.send_restart(g, &n).map_err(|e| e.to_string())?;
                                }
                            }
                        }
                        Some(Received::End { last }) => ended[i] = ended[i].max(Some(last)),
                        None => break,
                    }
                }
            }
            // A frame that an input has passed over (it delivered a later one without it)
            // can never be joined: let it go on the others too.
            for i in 0..pending.len() {
                let passed_over = |s: u64| {
                    (0..pending.len()).any(|j| {
                        j != i
                            && last_seq[j].is_some_and(|l| l > s)
                            && !pending[j].iter().any(|o| seq_of(o) == s)
                    })
                };
                let gone: Vec<u64> = pending[i]
                    .iter()
                    .map(seq_of)
                    .filter(|s| passed_over(*s))
                    .collect();
                pending[i].retain(|m| !gone.contains(&seq_of(m)));
                for _ in &gone {
                    subs[i].discard();
                }
            }
            // The oldest frame every input has; frames older than it can no longer be joined.
            while let Some(seq) = pending[0]
                .iter()
                .map(seq_of)
                .filter(|s| {
                    pending[1..]
                        .iter()
                        .all(|p| p.iter().any(|m| seq_of(m) == *s))
                })
                .min()
            {
                let msgs: Vec<Msg<'_>> = pending
                    .iter()
                    .map(|p| {
                        let m = p.iter().find(|m| seq_of(m) == seq).expect("common");
                        Msg {
                            header: *m.user_header(),
                            payload: m.payload(),
                        }
                    })
                    .collect();
                self.feed(node)?;
                let t = Instant::now();
                node.step(&msgs, out)?;
                tally.step(
                    t.elapsed().as_secs_f64() * 1e3,
                    now_ns().saturating_sub(msgs[0].header.capture_ns) as f64 / 1e6,
                    seq,
                );
                for p in &mut pending {
                    p.retain(|m| seq_of(m) > seq);
                }
                tally.report(
                    id,
                    spec,
                    out.sent,
                    subs.iter().chain(feedback.iter().map(|(_, s)| s)),
                );
                if frames.is_some_and(|n| seq + 1 >= n) {
                    done = true;
                    return Ok(false);
                }
            }
            // Every input's stream has ended: what is still held can never be joined (its
            // partners were lost upstream, near the run's end), and no frame is to come.
            if ended.iter().all(Option::is_some) {
                for (p, s) in pending.iter_mut().zip(subs) {
                    for _ in p.drain(..) {
                        s.discard();
                    }
                }
                done = true;
                return Ok(false);
            }
            Ok(true)
        });
        match joined {
            Ok(()) => {}
            Err(_) if !transport.sleep(Duration::ZERO) => {}
            Err(e) => return Err(e),
        }
        if done {
            let last = ended
                .iter()
                .flatten()
                .copied()
                .max()
                .or(frames.map(|n| n - 1));
            let mut ends = EndMarkers::new(pubs, last);
            linger(transport, read_in_graph, || {
                ends.resend();
                tally.report(
                    id,
                    spec,
                    out.sent,
                    subs.iter().chain(feedback.iter().map(|(_, s)| s)),
                )
            });
        }
        Ok(())
    }
}

/// Runs node `id` of `graph` as a tap (a recorder or a viewer): every message on each of
/// its inputs goes to `on_msg` (input index, header, payload) as it arrives, not joined by
/// frame. Ends on a stop request, or once every input's stream ended (its end marker came,
/// or, given a frame count, its last frame).
pub fn run_tap(
    graph: &Graph,
    instance: &str,
    id: &str,
    frames: Option<u64>,
    mut on_msg: impl FnMut(usize, &FrameHeader, &[u8]) -> Result<(), String>,
) -> Result<NodeStats, String> {
    let spec = graph
        .node(id)
        .ok_or_else(|| format!("no node '{id}' in {}", graph.file.display()))?;
    let transport = Transport::new(&format!("{instance}/{id}")).map_err(|e| e.to_string())?;
    let subs = readers(&transport, graph, instance, spec)?;
    let refs: Vec<&EdgeSubscriber> = subs.iter().collect();
    let mut finished = vec![false; subs.len()];
    let mut times = Vec::new();
    let mut last_frame = None;
    let mut received = 0u64;
    let mut reported = Instant::now();
    let stats = |received: u64, times: &[f64], last_frame: Option<u64>| NodeStats {
        id: id.into(),
        frames_in: received,
        frames_out: 0,
        mean_ms: mean(times),
        p99_ms: percentile(&mut times.to_vec(), 0.99),
        inputs: input_stats(spec, &subs),
        latency_ms: 0.0,
        last_frame,
        runs: 1,
        cpu_ms: crate::stats::process_cpu_ms(),
        latency_p50_ms: 0.0,
        latency_p99_ms: 0.0,
        first_step_end_ns: None,
        last_step_end_ns: None,
        phase: None,
    };
    wait_loop::<String>(&refs, Duration::from_millis(500), |wake, _| {
        if wake == Wake::Stop {
            return Ok(false);
        }
        // Reports for the watchdog (and for a restart's accounting) as a node does.
        if reported.elapsed() >= PROGRESS_PERIOD {
            print_stats(&stats(received, &times, last_frame));
            reported = Instant::now();
        }
        for (i, s) in subs.iter().enumerate() {
            while let Some(item) = s.receive_item()? {
                let m = match item {
                    Received::Frame(m) => m,
                    // The stream ended (its last frames lost upstream, say): none will come.
                    Received::End { .. } => {
                        finished[i] = true;
                        continue;
                    }
                    Received::Restart { .. } => continue,
                };
                let t = Instant::now();
                let h = *m.user_header();
                on_msg(i, &h, m.payload())?;
                times.push(t.elapsed().as_secs_f64() * 1e3);
                received += 1;
                last_frame = last_frame.max(Some(h.sequence));
                finished[i] |= frames.is_some_and(|n| h.sequence + 1 >= n);
            }
        }
        // Every stream ended (or delivered its last frame): nothing more will come.
        Ok(!finished.iter().all(|f| *f))
    })?;
    Ok(stats(received, &times, last_frame))
}

/// A node's end markers: sent on every output when its last frame is done, and again to
/// each reader that connects later (a reader restarted after the end was sent would wait
/// for ever for frames that will not come), and on a lossless edge until every reader got
/// it: a restarted writer's reader that has not yet opened its connection to it, with a
/// full queue, is skipped (what a CPU-starved reader of a fast restarted source met: it
/// waited for ever).
struct EndMarkers<'a> {
    pubs: &'a [EdgePublisher],
    last: Option<u64>,
    /// Per output, the readers (their unique ids) that have been sent the marker.
    told: Vec<Vec<String>>,
    /// Per output, whether the last marker reached fewer readers than there were.
    short: Vec<bool>,
}

impl<'a> EndMarkers<'a> {
    /// Sends the end of a stream whose last frame was `last` (none: no frame at all, nothing
    /// to end) on every output.
    fn new(pubs: &'a [EdgePublisher], last: Option<u64>) -> Self {
        let mut m = Self {
            pubs,
            last,
            told: vec![Vec::new(); pubs.len()],
            short: vec![false; pubs.len()],
        };
        m.send(true);
        m
    }

    /// Sends the marker on the outputs where a reader connected since the last time, or
    /// that a lossless edge's last marker did not reach whole.
    fn resend(&mut self) {
        self.send(false);
    }

    /// `wait`: the first marker waits for room in a reader's full queue, as a frame does;
    /// later ones skip it (a reader that has ended takes nothing more: its queue would
    /// fill, and the writer wait for ever).
    fn send(&mut self, wait: bool) {
        let Some(last) = self.last else { return };
        for ((p, told), short) in self.pubs.iter().zip(&mut self.told).zip(&mut self.short) {
            let now = p.reader_ids();
            if now.iter().any(|r| !told.contains(r)) || *short {
                // A send that fails (cut short by a stop) changes nothing: the node's work
                // is done, and it only lingers for its readers.
                // A drop-oldest edge delivers to every connected reader (at the cost of its
                // oldest message); a lossless one may skip one, and sends again.
                *short = p
                    .send_end(last, wait)
                    .is_ok_and(|n| p.lossless() && n < now.len());
            }
            *told = now;
        }
    }
}

/// How often a node that sleeps (a paced source between frames, a node lingering after its
/// last frame) wakes to report, for the supervisor's watchdog.
const BEAT: Duration = Duration::from_millis(250);

/// After its last frame, a node that other nodes read stays until it is told to stop: its
/// readers may not have taken every frame yet, and a publisher that leaves takes its unread
/// frames along (the supervisor stops such nodes once every node nobody reads has ended).
/// It reports (`beat`) while it waits.
fn linger(transport: &Transport, read_in_graph: bool, mut beat: impl FnMut()) {
    while read_in_graph && transport.sleep(BEAT) {
        beat();
    }
}

/// [`Transport::sleep`] for `wait`, reporting (`beat`) every [`BEAT`] on the way; false
/// when a stop request cut it short.
/// When frame `n` of a source paced at `period` from `start` is due (`None`: beyond any
/// clock this process will see).
fn due(start: Instant, period: Duration, n: u64) -> Option<Instant> {
    let ns = period.as_nanos().checked_mul(u128::from(n))?;
    start.checked_add(Duration::from_nanos(u64::try_from(ns).ok()?))
}

fn sleep_beating(transport: &Transport, wait: Duration, mut beat: impl FnMut()) -> bool {
    let start = Instant::now();
    loop {
        let left = wait.saturating_sub(start.elapsed());
        if !transport.sleep(left.min(BEAT)) {
            return false;
        }
        if left <= BEAT {
            return true;
        }
        beat();
    }
}

/// Nodes of run `instance` on this machine that died without removing their shared memory.
pub fn dead_nodes(instance: &str) -> usize {
    set_log_level_from_env_or(LogLevel::Error);
    let prefix = format!("{instance}/");
    let mut dead = 0;
    let _ = Node::<crate::transport::Service>::list(crate::transport::iceoryx_config(), |state| {
        if let NodeState::Dead(view) = state
            && view
                .details()
                .as_ref()
                .is_some_and(|d| d.name().as_str().starts_with(&prefix))
        {
            dead += 1;
        }
        CallbackProgression::Continue
    });
    dead
}

/// What [`remove_stale_resources`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StaleCleanup {
    /// Dead nodes whose shared memory was removed.
    pub removed: usize,
    /// Unfinished shared-memory files (left by a process killed while creating them) removed.
    pub empty_files: usize,
    /// The clean-up did not finish within its time and was left behind.
    pub gave_up: bool,
}

/// How old an empty shared-memory file must be to count as left by a dead creator (a live
/// one gives it its size within microseconds of creating it).
pub const UNSIZED_AGE: Duration = Duration::from_secs(1);

/// How long a run waits for the clean-up of dead nodes before it starts anyway.
pub const STALE_CLEANUP_LIMIT: Duration = Duration::from_secs(5);

/// Where POSIX shared memory lives on this system.
const SHM_DIR: &str = "/dev/shm";

/// Removes the shared-memory resources of nodes that died without cleaning up (on this
/// machine, any run), within a few seconds.
pub fn remove_stale_resources() -> StaleCleanup {
    set_log_level_from_env_or(LogLevel::Error);
    let config = crate::transport::iceoryx_config();
    // iceoryx2 0.10 waits forever to open shared memory that has no size yet, which is what
    // a node killed while creating an edge leaves: remove it before touching the dead node.
    let empty_files = remove_unsized_shm(
        std::path::Path::new(SHM_DIR),
        config.global.prefix.as_str(),
        UNSIZED_AGE,
    );
    let (tx, rx) = std::sync::mpsc::channel();
    // Any other hazard of that kind must not stop the graph from starting: the clean-up runs
    // aside and is left behind after a deadline.
    std::thread::spawn(move || {
        let mut removed = 0;
        let mut stuck = Vec::new();
        let mut clean = |stuck: &mut Vec<String>| {
            let _ = Node::<crate::transport::Service>::list(config, |state| {
                if let NodeState::Dead(view) = state {
                    let id = view.id().to_string();
                    match view.try_remove_stale_resources() {
                        Ok(()) => removed += 1,
                        Err(_) => stuck.push(id),
                    }
                }
                CallbackProgression::Continue
            });
        };
        clean(&mut stuck);
        // A node killed while it wrote a tag leaves the tag unfinished, which iceoryx2
        // neither reads nor removes, and its node's directory then cannot go: such tags
        // are removed (the node is dead, nobody finishes them) and the node cleaned again.
        if remove_unfinished_tags(config, &stuck) > 0 {
            clean(&mut Vec::new());
        }
        let _ = tx.send(removed);
    });
    match rx.recv_timeout(STALE_CLEANUP_LIMIT) {
        Ok(removed) => StaleCleanup {
            removed,
            empty_files,
            gave_up: false,
        },
        Err(_) => StaleCleanup {
            removed: 0,
            empty_files,
            gave_up: true,
        },
    }
}

/// Releases the domain ([`release_domain`]) when dropped: for a process that makes nodes
/// of its own outside a run (a test, a tool), declared before them so that it goes last.
pub struct ReleaseDomain;

impl Drop for ReleaseDomain {
    fn drop(&mut self) {
        release_domain();
    }
}

/// Removes the unfinished tags (empty, owner read-write: their writer died while writing
/// them) in the directories of the dead nodes `ids` (as iceoryx2 shows a node id: its value
/// in hexadecimal). Returns how many were removed.
fn remove_unfinished_tags(config: &iceoryx2::config::Config, ids: &[String]) -> usize {
    use std::os::unix::fs::PermissionsExt;
    let nodes = PathBuf::from(config.global.node_dir().to_string());
    let mut removed = 0;
    for id in ids {
        let Ok(value) = u128::from_str_radix(id, 16) else {
            continue;
        };
        let Ok(dir) = std::fs::read_dir(nodes.join(value.to_string())) else {
            continue;
        };
        for e in dir.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let tag = name.ends_with(&config.global.node.service_tag_suffix.to_string())
                || name.ends_with(&config.global.node.port_tag_suffix.to_string());
            let unfinished = e.metadata().is_ok_and(|m| {
                m.is_file() && m.len() == 0 && m.permissions().mode() & 0o777 == 0o600
            });
            if tag && unfinished && std::fs::remove_file(e.path()).is_ok() {
                removed += 1;
            }
        }
    }
    removed
}

/// Removes the domain's own shared memory (iceoryx2's node counter, which outlives every
/// node by design) when no node of the domain lives any more: the last run of a domain
/// leaves nothing behind. Returns whether it was removed.
pub fn release_domain() -> bool {
    set_log_level_from_env_or(LogLevel::Error);
    let config = crate::transport::iceoryx_config();
    let mut in_use = false;
    let listed = Node::<crate::transport::Service>::list(config, |state| {
        match state {
            NodeState::Dead(view) => {
                // A dead node's resources go first; one that cannot be removed keeps the
                // domain in use.
                in_use |= view.try_remove_stale_resources().is_err();
            }
            _ => in_use = true,
        }
        CallbackProgression::Continue
    });
    if listed.is_err() || in_use {
        return false;
    }
    // SAFETY: iceoryx2 asks that no other process use the domain. No node of it lives: a
    // process that opened the segment and has yet to make its node keeps its own mapping
    // and its id (ids are made of the process id and the time besides this counter), and
    // the next one makes the segment anew.
    unsafe {
        iceoryx2::testing::remove_global_mgmt_segment::<crate::transport::Service>(config)
            .unwrap_or(false)
    }
}

/// Removes the files in `dir` named `prefix*` older than `age` that their creator never
/// finished: empty (it died before giving them a size), or still write-only (iceoryx2
/// creates shared memory owner-write-only and opens it up once initialised; such a file
/// has no service or node that names it, so nothing else ever removes it). A live creator
/// does both within microseconds.
fn remove_unsized_shm(dir: &std::path::Path, prefix: &str, age: Duration) -> usize {
    use std::os::unix::fs::PermissionsExt;
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .filter_map(Result::ok)
        .filter(|e| e.file_name().to_string_lossy().starts_with(prefix))
        .filter(|e| {
            e.metadata().is_ok_and(|m| {
                m.is_file()
                    && (m.len() == 0 || m.permissions().mode() & 0o777 == 0o200)
                    && m.modified()
                        .ok()
                        .and_then(|t| t.elapsed().ok())
                        .is_some_and(|a| a > age)
            })
        })
        .filter(|e| std::fs::remove_file(e.path()).is_ok())
        .count()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_old_unfinished_files_of_the_prefix_are_removed() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let old = std::time::SystemTime::now() - Duration::from_secs(60);
        let make = |name: &str, bytes: &[u8], when: Option<std::time::SystemTime>| {
            let p = dir.path().join(name);
            std::fs::write(&p, bytes).unwrap();
            if let Some(t) = when {
                std::fs::File::options()
                    .write(true)
                    .open(&p)
                    .unwrap()
                    .set_modified(t)
                    .unwrap();
            }
        };
        make("iox2_a.dynamic", b"", Some(old));
        make("iox2_b.dynamic", b"", None);
        make("iox2_c.dynamic", b"x", Some(old));
        make("other.dynamic", b"", Some(old));
        // Sized but never opened up: its creator died during initialisation.
        make("iox2_d.event_mgmt", b"x", Some(old));
        make("iox2_e.event_mgmt", b"x", None);
        for f in ["iox2_d.event_mgmt", "iox2_e.event_mgmt"] {
            let p = dir.path().join(f);
            std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o200)).unwrap();
        }
        let n = remove_unsized_shm(dir.path(), "iox2_", Duration::from_secs(10));
        let mut left: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        left.sort();
        assert_eq!(n, 2);
        assert_eq!(
            left,
            [
                "iox2_b.dynamic",
                "iox2_c.dynamic",
                "iox2_e.event_mgmt",
                "other.dynamic"
            ]
        );
    }
}

/// How a node process is started: `--graph FILE --id ID --instance NAME [--frames N]`
/// (the supervisor writes the whole graph, rewrites applied, to FILE as JSON).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NodeArgs {
    /// The graph file.
    pub graph: PathBuf,
    /// The node's id in it.
    pub id: String,
    /// The running graph (names its shared memory).
    pub instance: String,
    /// Stop after this many frames.
    pub frames: Option<u64>,
    /// The run's restart count when the supervisor started this process (0: first start;
    /// given in [`GENERATION_ENV`], which programs built before it ignore).
    pub generation: u64,
}

/// The environment variable in which the supervisor gives a restarted node process the
/// run's restart count.
pub const GENERATION_ENV: &str = "MICROSTEREO_RESTART_GENERATION";

/// The environment variable in which the supervisor gives a restarted source the number
/// of its first frame: the one after the last its predecessor reported, so that a
/// restarted capture neither numbers frames anew nor makes more than the run asks for.
pub const FIRST_FRAME_ENV: &str = "MICROSTEREO_FIRST_FRAME";

/// The first frame number the supervisor gave this process (0 when none).
pub fn first_frame_from_env() -> Result<u64, String> {
    match std::env::var(FIRST_FRAME_ENV) {
        Err(_) => Ok(0),
        Ok(v) => v
            .parse()
            .map_err(|_| format!("{FIRST_FRAME_ENV}={v} is not a frame number")),
    }
}

/// The restart count the supervisor gave this process (0 when none).
pub fn generation_from_env() -> Result<u64, String> {
    match std::env::var(GENERATION_ENV) {
        Err(_) => Ok(0),
        Ok(v) => v
            .parse()
            .map_err(|_| format!("{GENERATION_ENV}={v} is not a restart count")),
    }
}

/// What a node program is asked to do.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Invocation {
    /// Run as node `id` of a running graph.
    Run(NodeArgs),
    /// Print its kind's ports as JSON after checking `params` (TOML) with the inputs
    /// `connected`; exit code 2 with the reason when they do not fit.
    Describe {
        /// The node's `params` table as TOML.
        params: String,
        /// Its connected inputs.
        connected: Vec<String>,
    },
}

impl Invocation {
    /// Reads the arguments the supervisor (or the launch validator) passes.
    pub fn parse(args: &[String]) -> Result<Self, String> {
        let mut graph = None;
        let mut id = None;
        let mut instance = None;
        let mut frames = None;
        let mut describe = false;
        let mut params = String::new();
        let mut connected = Vec::new();
        let mut it = args.iter();
        while let Some(a) = it.next() {
            let mut value = |name: &str| {
                it.next()
                    .cloned()
                    .ok_or_else(|| format!("{name} needs a value"))
            };
            match a.as_str() {
                "--graph" => graph = Some(PathBuf::from(value("--graph")?)),
                "--id" => id = Some(value("--id")?),
                "--instance" => instance = Some(value("--instance")?),
                "--frames" => {
                    let v = value("--frames")?;
                    frames = Some(
                        v.parse::<u64>()
                            .map_err(|_| format!("--frames {v} is not a frame count"))?,
                    );
                }
                "--describe" => describe = true,
                "--params" => params = value("--params")?,
                "--connected" => {
                    connected = value("--connected")?
                        .split(',')
                        .filter(|s| !s.is_empty())
                        .map(String::from)
                        .collect()
                }
                other => return Err(format!("unknown argument '{other}'")),
            }
        }
        if describe {
            return Ok(Invocation::Describe { params, connected });
        }
        let generation = generation_from_env()?;
        match (graph, id) {
            (Some(graph), Some(id)) => Ok(Invocation::Run(NodeArgs {
                graph,
                id,
                instance: instance.unwrap_or_else(|| "default".into()),
                frames,
                generation,
            })),
            _ => Err(
                "a node program runs with --graph FILE --id ID [--instance NAME] [--frames N] (as `microstereo run` starts it), or with --describe"
                    .into(),
            ),
        }
    }
}

impl NodeArgs {
    /// The arguments that start a node with these settings.
    pub fn to_args(&self) -> Vec<String> {
        let mut v = vec![
            "--graph".to_string(),
            self.graph.display().to_string(),
            "--id".into(),
            self.id.clone(),
            "--instance".into(),
            self.instance.clone(),
        ];
        if let Some(n) = self.frames {
            v.push("--frames".into());
            v.push(n.to_string());
        }
        v
    }
}

/// Reads a graph file that the supervisor wrote.
pub fn load_graph(path: &Path) -> Result<Graph, String> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("cannot read the graph file {}: {e}", path.display()))?;
    serde_json::from_str(&text).map_err(|e| format!("graph file {}: {e}", path.display()))
}

/// Writes `graph` for its node processes.
pub fn write_graph(path: &Path, graph: &Graph) -> Result<(), String> {
    let json = serde_json::to_string(graph).map_err(|e| e.to_string())?;
    std::fs::write(path, json).map_err(|e| format!("cannot write {}: {e}", path.display()))
}

/// The report of a node stopped before it handled a frame.
fn stopped_early(id: &str) -> NodeStats {
    NodeStats {
        id: id.into(),
        runs: 1,
        cpu_ms: crate::stats::process_cpu_ms(),
        ..NodeStats::default()
    }
}

/// Runs node `a.id` of the graph in `a.graph` as this process, with the node kinds of
/// `registry` (an `exec` node's program holds its one kind there). A node asked to stop
/// ends quietly with what it did, whatever its stop cut short (a wait for a writer, a
/// send): the stop is what happened, not an error.
pub fn run_graph_node(registry: &Registry, a: &NodeArgs) -> Result<NodeStats, String> {
    crate::signals::install();
    AS_PROCESS.store(true, std::sync::atomic::Ordering::Relaxed);
    match run_graph_node_inner(registry, a) {
        Err(_) if crate::signals::stop_requested() => Ok(stopped_early(&a.id)),
        r => r,
    }
}

fn run_graph_node_inner(registry: &Registry, a: &NodeArgs) -> Result<NodeStats, String> {
    let graph = load_graph(&a.graph)?;
    let spec = graph
        .node(&a.id)
        .ok_or_else(|| format!("no node '{}' in {}", a.id, a.graph.display()))?;
    if let Some(main) = spec.kind().and_then(|k| registry.tap_main(k)) {
        return main(&graph, &a.instance, &a.id, a.frames)
            .map_err(|e| format!("node '{}': {e}", a.id));
    }
    let mut node = match spec.kind() {
        Some(_) => registry.build(spec),
        None => registry.build_as_only_kind(spec),
    }
    .map_err(|e| format!("node '{}': {e}", a.id))?;
    run_node(
        &graph,
        &a.instance,
        &a.id,
        node.as_mut(),
        a.frames,
        a.generation,
    )
    .map_err(|e| format!("node '{}': {e}", a.id))
}

/// Set while this process runs a node of a graph for a supervisor (not in-process).
static AS_PROCESS: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Tells the supervisor (and `top`) what this node is doing before its first frame when
/// that takes long, e.g. `rendering the loop: 12 of 30 frames`. Nothing happens where the
/// node does not run as a process of a graph (in `reconstruct`, in tests).
pub fn report_phase(phase: &str) {
    if AS_PROCESS.load(std::sync::atomic::Ordering::Relaxed) {
        print_stats(&NodeStats {
            runs: 1,
            cpu_ms: crate::stats::process_cpu_ms(),
            phase: Some(phase.into()),
            ..NodeStats::default()
        });
    }
}

/// Prints a node's statistics the way the supervisor reads them.
pub fn print_stats(stats: &NodeStats) {
    crate::outln!(
        "{STATS_PREFIX}{}",
        serde_json::to_string(stats).expect("serialises")
    );
}

/// A child dies with its parent, even when the parent is killed with SIGKILL.
pub fn set_parent_death_signal() {
    #[cfg(target_os = "linux")]
    // SAFETY: prctl with PR_SET_PDEATHSIG only sets a flag of this process.
    unsafe {
        libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
    }
}

/// The whole `main` of a node program of its own (an `exec` node in a launch file) that
/// holds the one kind in `registry`: runs it in the graph as the supervisor asks, or
/// describes its ports to the launch validator. Returns the process exit code.
///
/// ```no_run
/// # struct Invert;
/// # impl runtime::node::Task for Invert {
/// #     const KIND: &'static str = "invert";
/// #     type Params = runtime::node::NoParams;
/// #     type Input = runtime::node::NoPorts;
/// #     type Output = runtime::node::NoPorts;
/// #     type Error = String;
/// #     fn new(_: Self::Params) -> Result<Self, String> { Ok(Invert) }
/// #     fn process(&mut self, _: runtime::node::Stamp, _: runtime::node::NoPorts) -> Result<runtime::node::NoPorts, String> { Ok(runtime::node::NoPorts) }
/// # }
/// fn main() {
///     std::process::exit(runtime::process::exec_main(runtime::registry::Registry::new().task::<Invert>()));
/// }
/// ```
pub fn exec_main(registry: Registry) -> i32 {
    crate::signals::install();
    set_parent_death_signal();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let result = Invocation::parse(&args).and_then(|inv| match inv {
        Invocation::Describe { params, connected } => {
            let params: toml::Table = toml::from_str(&params)
                .map_err(|e| format!("--params is not a TOML table: {}", e.message()))?;
            let spec = registry.describe_only_kind(&params, &connected)?;
            crate::outln!("{}", serde_json::to_string(&spec).expect("serialises"));
            Ok(())
        }
        Invocation::Run(a) => run_graph_node(&registry, &a).map(|s| print_stats(&s)),
    });
    match result {
        Ok(()) => 0,
        Err(e) => {
            crate::errln!("error: {e}");
            2
        }
    }
}
