//! The in-process executor: a graph's nodes stepped one after another in this process.
//!
//! `reconstruct`, `bench`, the tests and `test-node` run graphs this way; `run` runs the
//! same node values as processes ([`crate::process`]). Per frame, sources produce and every
//! other node steps on the messages its producers sent for that frame, in the graph's order
//! (producers first); a feedback input gets the newest message its producer sent so far.

use crate::launch::Graph;
use crate::node::{GraphNode, Msg, Outputs};
use crate::registry::Registry;
use schemas::FrameHeader;
use std::collections::HashMap;
use std::time::Instant;

/// Output messages kept in memory: `(header, payload)` per port.
#[derive(Debug, Default)]
pub struct Collected {
    /// Per output port, the messages sent this step.
    pub ports: Vec<Vec<(FrameHeader, Vec<u8>)>>,
}

impl Outputs for Collected {
    fn send(
        &mut self,
        port: usize,
        header: FrameHeader,
        len: usize,
        fill: &mut dyn FnMut(&mut [u8]),
    ) -> Result<(), String> {
        if self.ports.len() <= port {
            self.ports.resize_with(port + 1, Vec::new);
        }
        let mut buf = vec![0u8; len];
        fill(&mut buf);
        self.ports[port].push((header, buf));
        Ok(())
    }
}

/// One message of an edge.
pub type Logged = (FrameHeader, Vec<u8>);

/// Every message of every edge, keyed by `(node id, output port)`, in frame order.
pub type EdgeLog = HashMap<(String, String), Vec<Logged>>;

/// What one frame of an in-process run produced.
#[derive(Debug, Default)]
pub struct Frame {
    /// The messages of this frame, keyed by `(node id, output port)`.
    pub edges: HashMap<(String, String), Logged>,
    /// Milliseconds each node took, in the graph's order.
    pub ms: Vec<(String, f64)>,
}

impl Frame {
    /// The message node `id` sent on `port` this frame.
    pub fn get(&self, id: &str, port: &str) -> Option<Msg<'_>> {
        self.edges
            .get(&(id.to_string(), port.to_string()))
            .map(|(h, p)| Msg {
                header: *h,
                payload: p,
            })
    }

    /// The message a built graph's output `o` sent this frame, as its own type.
    pub fn read<M: schemas::msg::Message>(&self, o: &crate::build::Out<M>) -> Result<M, String> {
        self.decode(o.node(), o.port())
    }

    /// That message decoded as `M`.
    pub fn decode<M: schemas::msg::Message>(&self, id: &str, port: &str) -> Result<M, String> {
        let m = self
            .get(id, port)
            .ok_or_else(|| format!("nothing on {id}/{port} this frame"))?;
        M::decode(&m.header, m.payload).map_err(|e| format!("{id}/{port}: {e}"))
    }
}

/// A graph and its node values, run in this process.
pub struct InProcess {
    graph: Graph,
    nodes: Vec<Box<dyn GraphNode>>,
    /// The newest message of every edge a feedback input reads, with its number.
    newest: HashMap<(String, String), (u64, Logged)>,
    /// Per `(node, input index)`, the number of the feedback message it got last.
    delivered: HashMap<(String, usize), u64>,
    /// Messages sent on fed-back edges so far (numbers them).
    sent: u64,
    /// Those edges.
    fed_back: std::collections::HashSet<(String, String)>,
    seq: u64,
}

impl InProcess {
    /// Builds every node of `graph` from `registry`.
    pub fn new(graph: &Graph, registry: &Registry) -> Result<Self, String> {
        let nodes = graph
            .nodes
            .iter()
            .map(|n| {
                registry
                    .build(n)
                    .map_err(|e| format!("node '{}': {e}", n.id))
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self::with_nodes(graph, nodes))
    }

    /// Runs `graph` with the given node values (one per node, in the graph's order).
    pub fn with_nodes(graph: &Graph, nodes: Vec<Box<dyn GraphNode>>) -> Self {
        assert_eq!(
            graph.nodes.len(),
            nodes.len(),
            "one node value per node of the graph"
        );
        let fed_back = graph
            .nodes
            .iter()
            .flat_map(|n| &n.inputs)
            .filter(|i| i.feedback)
            .map(|i| (i.node.clone(), i.output.clone()))
            .collect();
        Self {
            graph: graph.clone(),
            nodes,
            newest: HashMap::new(),
            delivered: HashMap::new(),
            sent: 0,
            fed_back,
            seq: 0,
        }
    }

    /// The pace of the slowest paced source (frames/s), if any: the most a graph fed by it
    /// can take, however fast its nodes are.
    pub fn pace(&self) -> Option<f64> {
        self.nodes
            .iter()
            .filter_map(|n| n.fps())
            .filter(|f| *f > 0.0)
            .min_by(f64::total_cmp)
    }

    /// Runs the next frame; `None` once a source has no more.
    pub fn step(&mut self) -> Result<Option<Frame>, String> {
        let seq = self.seq;
        let mut frame = Frame::default();
        for (spec, node) in self.graph.nodes.iter().zip(self.nodes.iter_mut()) {
            let mut out = Collected::default();
            // Feedback: the newest message its producer sent so far (this frame's when the
            // producer came first, else an earlier frame's), once, as a node process gets it.
            for (k, i) in spec.inputs.iter().enumerate().filter(|(_, i)| i.feedback) {
                let Some((n, (h, p))) = self.newest.get(&(i.node.clone(), i.output.clone())) else {
                    continue;
                };
                let last = self.delivered.insert((spec.id.clone(), k), *n);
                if last != Some(*n) {
                    node.feedback(
                        k,
                        Msg {
                            header: *h,
                            payload: p,
                        },
                    )
                    .map_err(|e| format!("{}: {e}", spec.id))?;
                }
            }
            let t = Instant::now();
            if spec.inputs.iter().all(|i| i.feedback) {
                if !node
                    .produce(seq, &mut out)
                    .map_err(|e| format!("{}: {e}", spec.id))?
                {
                    return Ok(None);
                }
            } else {
                let msgs: Vec<Msg<'_>> = spec
                    .inputs
                    .iter()
                    .filter(|i| !i.feedback)
                    .map(|i| {
                        frame.get(&i.node, &i.output).ok_or_else(|| {
                            format!("{}: no message on {}/{}", spec.id, i.node, i.output)
                        })
                    })
                    .collect::<Result<_, _>>()?;
                node.step(&msgs, &mut out)
                    .map_err(|e| format!("{}: {e}", spec.id))?;
            }
            frame
                .ms
                .push((spec.id.clone(), t.elapsed().as_secs_f64() * 1e3));
            for (port, msgs) in out.ports.into_iter().enumerate() {
                let name = spec.outputs[port].0.clone();
                for m in msgs {
                    let key = (spec.id.clone(), name.clone());
                    if self.fed_back.contains(&key) {
                        self.sent += 1;
                        self.newest.insert(key.clone(), (self.sent, m.clone()));
                    }
                    frame.edges.insert(key, m);
                }
            }
        }
        self.seq += 1;
        Ok(Some(frame))
    }

    /// Runs up to `frames` frames and returns everything every edge carried.
    pub fn run(&mut self, frames: u64) -> Result<EdgeLog, String> {
        let mut log: EdgeLog = HashMap::new();
        for _ in 0..frames {
            let Some(f) = self.step()? else { break };
            let mut edges: Vec<_> = f.edges.into_iter().collect();
            edges.sort_by(|a, b| a.0.cmp(&b.0));
            for (k, m) in edges {
                log.entry(k).or_default().push(m);
            }
        }
        Ok(log)
    }
}

/// Runs `graph` in this process for `frames` frames and prints per node the mean and 99th
/// percentile step time, then the frame rate and the CPU used (`run --in-process`). Returns
/// the rate and the pace of the graph's paced sources (which this run ignores).
pub fn run_timed(
    graph: &Graph,
    registry: &Registry,
    frames: u64,
) -> Result<(f64, Option<f64>), String> {
    let mut exec = InProcess::new(graph, registry)?;
    let cpu0 = crate::stats::process_cpu_ms();
    let t0 = std::time::Instant::now();
    let mut times: Vec<(String, Vec<f64>)> = Vec::new();
    let mut done = 0u64;
    for _ in 0..frames {
        let Some(f) = exec.step()? else {
            break;
        };
        for (k, (id, ms)) in f.ms.into_iter().enumerate() {
            match times.get_mut(k) {
                Some(t) => t.1.push(ms),
                None => times.push((id, vec![ms])),
            }
        }
        done += 1;
    }
    let wall = t0.elapsed().as_secs_f64();
    let cpu = crate::stats::process_cpu_ms() - cpu0;
    crate::outln!();
    crate::outln!(
        "{:<20} {:>9} {:>10} {:>10}",
        "node",
        "frames",
        "mean ms",
        "p99 ms"
    );
    for (id, mut t) in times {
        let mean = crate::stats::mean(&t);
        let p99 = crate::stats::percentile(&mut t, 0.99);
        crate::outln!("{:<20} {:>9} {:>10.2} {:>10.2}", id, t.len(), mean, p99);
    }
    let rate = done as f64 / wall.max(1e-9);
    crate::outln!(
        "{done} frame(s) in one process in {wall:.2} s: {rate:.2} frames/s; CPU {:.0} % of one core",
        100.0 * cpu / (wall * 1e3).max(1e-9)
    );
    Ok((rate, exec.pace()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::launch::LaunchFile;
    use crate::node::{NoParams, NoPorts, NodeError, Sink, Source, Stamp, Task};
    use schemas::{Disparity, Plane};
    use std::path::Path;
    use std::sync::Mutex;

    crate::ports! {
        /// One map.
        pub struct Map {
            /// The map.
            pub map: Disparity,
        }
    }

    /// Frame `n` is a 2×1 map of `n`; three frames.
    struct Count;
    impl Source for Count {
        const KIND: &'static str = "count";
        type Params = NoParams;
        type Output = Map;
        type Feedback = NoPorts;
        type Error = NodeError;
        fn new(_: NoParams) -> Result<Self, NodeError> {
            Ok(Count)
        }
        fn produce(&mut self, seq: u64) -> Result<Option<(u64, Map)>, NodeError> {
            let map = Plane::filled(2, 1, seq as f32);
            Ok((seq < 3).then_some((
                1000 + seq,
                Map {
                    map: Disparity { map },
                },
            )))
        }
    }

    struct Double;
    impl Task for Double {
        const KIND: &'static str = "double";
        type Params = NoParams;
        type Input = Map;
        type Output = Map;
        type Error = NodeError;
        fn new(_: NoParams) -> Result<Self, NodeError> {
            Ok(Double)
        }
        fn process(&mut self, _: Stamp, mut i: Map) -> Result<Map, NodeError> {
            i.map.map.data.iter_mut().for_each(|v| *v *= 2.0);
            Ok(i)
        }
    }

    static SEEN: Mutex<Vec<(Stamp, f32)>> = Mutex::new(Vec::new());

    struct Keep;
    impl Sink for Keep {
        const KIND: &'static str = "keep";
        type Params = NoParams;
        type Input = Map;
        type Error = NodeError;
        fn new(_: NoParams) -> Result<Self, NodeError> {
            Ok(Keep)
        }
        fn consume(&mut self, stamp: Stamp, i: Map) -> Result<(), NodeError> {
            SEEN.lock().unwrap().push((stamp, i.map.map.data[0]));
            Ok(())
        }
    }

    #[test]
    fn a_source_a_task_and_a_sink_run_frame_by_frame_with_their_stamps() {
        let kinds = Registry::new()
            .source::<Count>()
            .task::<Double>()
            .sink::<Keep>();
        let text = "[[node]]\nid = \"c\"\nkind = \"count\"\n\n[[node]]\nid = \"d\"\nkind = \"double\"\ninputs = { map = \"c/map\" }\n\n[[node]]\nid = \"k\"\nkind = \"keep\"\ninputs = { map = \"d/map\" }\n";
        let g = LaunchFile::parse(Path::new("t.toml"), text)
            .unwrap()
            .validate(&kinds)
            .unwrap();
        let log = InProcess::new(&g, &kinds).unwrap().run(10).unwrap();
        // Three frames, then the source has no more.
        assert_eq!(log[&("d".to_string(), "map".to_string())].len(), 3);
        let seen = SEEN.lock().unwrap().clone();
        let want: Vec<(Stamp, f32)> = (0..3)
            .map(|n| {
                (
                    Stamp {
                        sequence: n,
                        capture_ns: 1000 + n,
                    },
                    2.0 * n as f32,
                )
            })
            .collect();
        assert_eq!(seen, want);
        // Unknown params are refused by the params type.
        let bad = text.replace(
            "kind = \"double\"\n",
            "kind = \"double\"\nparams = { gain = 2 }\n",
        );
        let e = LaunchFile::parse(Path::new("t.toml"), &bad)
            .unwrap()
            .validate(&kinds)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("t.toml:8: node 'd': bad params: unknown field `gain`"),
            "{e}"
        );
    }
}
