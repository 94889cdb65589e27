//! One node as its own process: inputs and outputs on shared memory, one step per frame.
//!
//! A source produces frames (paced by `fps`, or as fast as it can). Any other node sleeps in a
//! WaitSet until an input has data, joins its inputs by frame number (frames present on
//! every input, oldest first; a frame some input never got is dropped), steps, and
//! publishes its outputs
//! in loaned shared memory under the same frame number. Given a frame count, it ends after
//! the last frame; a node that other nodes of the graph read then stays until it is told to
//! stop, because a publisher that leaves takes its unread frames along. On exit it prints
//! one [`NodeStats`] line for the supervisor.

use crate::launch::Graph;
use crate::step::{GraphNode, Msg, Outputs};
use crate::transport::{EdgePublisher, EdgeSubscriber, Message, Transport, Wake, wait_loop};
use iceoryx2::node::NodeView;
use iceoryx2::prelude::*;
use schemas::FrameHeader;
use serde::{Deserialize, Serialize};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// The line prefix of a node's final statistics on its stdout.
pub const STATS_PREFIX: &str = "MICROSTEREO-STATS ";

/// What one node did, reported when it ends.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct NodeStats {
    /// Node id.
    pub id: String,
    /// Frames consumed (steps taken; frames produced for a source).
    pub frames_in: u64,
    /// Messages published.
    pub frames_out: u64,
    /// Mean step time, ms.
    pub mean_ms: f64,
    /// 99th-percentile step time, ms.
    pub p99_ms: f64,
    /// Per input `(port, frames that never arrived)`.
    pub drops: Vec<(String, u64)>,
    /// Mean time from capture to the end of this node's step, ms.
    pub latency_ms: f64,
    /// The last frame number handled.
    pub last_frame: Option<u64>,
}

/// Nanoseconds since the Unix epoch (capture timestamps).
pub fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

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

/// The name under which node `id` reads its input `port`.
fn reader_name(id: &str, port: &str) -> String {
    format!("{id}.{port}")
}

fn percentile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// Runs node `id` of `graph` until its frames are done or it is told to stop.
pub fn run_node(
    graph: &Graph,
    instance: &str,
    id: &str,
    node: &mut dyn GraphNode,
    frames: Option<u64>,
    fps: Option<f64>,
) -> Result<NodeStats, String> {
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
    let subs = spec
        .inputs
        .iter()
        .map(|i| {
            transport.reader(
                &Graph::edge_name(instance, &i.node, &i.output),
                &graph.edge_config(&i.node, &i.output),
                Some(&reader_name(id, &i.port)),
            )
        })
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| e.to_string())?;
    // A frame sent before a reader connects never reaches it (edges keep no history): wait
    // until every reader the graph names is there (readers outside the graph, such as a
    // recorder or a test, do not count). Only at start, so a short sleep is fine.
    let expected: Vec<Vec<String>> = spec
        .outputs
        .iter()
        .map(|(port, _)| {
            graph
                .nodes
                .iter()
                .flat_map(|n| n.inputs.iter().map(move |i| (n, i)))
                .filter(|(_, i)| i.node == id && i.output == *port)
                .map(|(n, i)| reader_name(&n.id, &i.port))
                .collect()
        })
        .collect();
    let read_in_graph = expected.iter().any(|w| !w.is_empty());
    let t0 = Instant::now();
    while pubs.iter().zip(&expected).any(|(p, want)| {
        let have = p.reader_names();
        want.iter().any(|w| !have.contains(w))
    }) {
        if t0.elapsed() > Duration::from_secs(30) {
            eprintln!("warning: not every reader connected within 30 s; sending anyway");
            break;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    let mut out = ShmOutputs {
        pubs: &pubs,
        sent: 0,
    };
    let mut times = Vec::new();
    let mut latencies = Vec::new();
    let mut last_frame = None;
    if subs.is_empty() {
        let period = fps
            .filter(|f| *f > 0.0)
            .map(|f| Duration::from_secs_f64(1.0 / f));
        let start = Instant::now();
        let mut seq = 0u64;
        let mut stopped = false;
        while frames.is_none_or(|n| seq < n) {
            // Also the place where a stop request is noticed between frames.
            let wait = period.map_or(Duration::ZERO, |p| {
                (start + p * seq as u32).saturating_duration_since(Instant::now())
            });
            if !transport.sleep(wait) {
                stopped = true;
                break;
            }
            let (t, t_ns) = (Instant::now(), now_ns());
            if !node.produce(seq, &mut out)? {
                break;
            }
            times.push(t.elapsed().as_secs_f64() * 1e3);
            latencies.push(now_ns().saturating_sub(t_ns) as f64 / 1e6);
            last_frame = Some(seq);
            seq += 1;
        }
        if !stopped {
            linger(&transport, read_in_graph);
        }
    } else {
        let refs: Vec<&EdgeSubscriber> = subs.iter().collect();
        let mut pending: Vec<Vec<Message>> = subs.iter().map(|_| Vec::new()).collect();
        let seq_of = |m: &Message| m.user_header().sequence;
        let mut done = false;
        wait_loop::<String>(&refs, Duration::from_secs(1), |wake, _| {
            if wake == Wake::Stop {
                return Ok(false);
            }
            for (i, s) in subs.iter().enumerate() {
                while let Some(m) = s.receive()? {
                    pending[i].push(m);
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
                let t = Instant::now();
                node.step(&msgs, &mut out)?;
                times.push(t.elapsed().as_secs_f64() * 1e3);
                latencies.push(now_ns().saturating_sub(msgs[0].header.capture_ns) as f64 / 1e6);
                last_frame = Some(seq);
                for p in &mut pending {
                    p.retain(|m| seq_of(m) > seq);
                }
                if frames.is_some_and(|n| seq + 1 >= n) {
                    done = true;
                    return Ok(false);
                }
            }
            Ok(true)
        })?;
        if done {
            linger(&transport, read_in_graph);
        }
    }
    let steps = times.len() as u64;
    let mean_ms = if times.is_empty() {
        0.0
    } else {
        times.iter().sum::<f64>() / times.len() as f64
    };
    Ok(NodeStats {
        id: id.into(),
        frames_in: steps,
        frames_out: out.sent,
        mean_ms,
        p99_ms: percentile(&mut times, 0.99),
        drops: spec
            .inputs
            .iter()
            .zip(&subs)
            .map(|(i, s)| (i.port.clone(), s.dropped()))
            .collect(),
        latency_ms: if latencies.is_empty() {
            0.0
        } else {
            latencies.iter().sum::<f64>() / latencies.len() as f64
        },
        last_frame,
    })
}

/// After its last frame, a node that other nodes read stays until it is told to stop: its
/// readers may not have taken every frame yet, and a publisher that leaves takes its unread
/// frames along (the supervisor stops such nodes once every node nobody reads has ended).
fn linger(transport: &Transport, read_in_graph: bool) {
    while read_in_graph && transport.sleep(Duration::from_secs(3600)) {}
}

/// Nodes of run `instance` on this machine that died without removing their shared memory.
pub fn dead_nodes(instance: &str) -> usize {
    set_log_level_from_env_or(LogLevel::Error);
    let prefix = format!("{instance}/");
    let mut dead = 0;
    let _ = Node::<crate::transport::Service>::list(Config::global_config(), |state| {
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

/// Removes the shared-memory resources of graph nodes that died without cleaning up.
pub fn remove_stale_resources() -> usize {
    set_log_level_from_env_or(LogLevel::Error);
    let mut removed = 0;
    let _ = Node::<crate::transport::Service>::list(Config::global_config(), |state| {
        if let NodeState::Dead(view) = state
            && view.try_remove_stale_resources().is_ok()
        {
            removed += 1;
        }
        CallbackProgression::Continue
    });
    removed
}
