//! The graph's view of a node: one step from one frame's input messages to its output
//! messages, as bytes with a [`FrameHeader`]. The same [`GraphNode`] value runs in a node
//! process behind the shared-memory transport ([`crate::process`]) and in-process
//! ([`run_in_process`]), so a graph and its in-process twin compute the same bytes.

use crate::launch::Graph;
use schemas::FrameHeader;
use std::collections::HashMap;

/// A message as a node reads it.
#[derive(Clone, Copy, Debug)]
pub struct Msg<'a> {
    /// Its header.
    pub header: FrameHeader,
    /// Its payload.
    pub payload: &'a [u8],
}

/// Where a step writes its outputs.
pub trait Outputs {
    /// Sends `len` bytes on output `port` (index into the node's outputs), written in place
    /// by `fill`.
    fn send(
        &mut self,
        port: usize,
        header: FrameHeader,
        len: usize,
        fill: &mut dyn FnMut(&mut [u8]),
    ) -> Result<(), String>;
}

/// A node as the graph runs it.
pub trait GraphNode {
    /// A source makes frame `seq` (its only step); `Ok(false)` when it has no more.
    fn produce(&mut self, _seq: u64, _out: &mut dyn Outputs) -> Result<bool, String> {
        Err("this node has inputs: it steps, it does not produce".into())
    }

    /// One step on one frame's inputs, in the order of the node's input ports.
    fn step(&mut self, _inputs: &[Msg<'_>], _out: &mut dyn Outputs) -> Result<(), String> {
        Err("this node is a source: it produces, it does not step".into())
    }
}

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

/// Reads a node's `params` table into its settings type (unknown keys are refused when the
/// type says `deny_unknown_fields`).
pub fn params<T: serde::de::DeserializeOwned>(t: &toml::Table) -> Result<T, String> {
    toml::Value::Table(t.clone())
        .try_into()
        .map_err(|e: toml::de::Error| e.message().to_string())
}

/// Every message of every edge, keyed by `(node id, output port)`, in frame order.
pub type EdgeLog = HashMap<(String, String), Vec<(FrameHeader, Vec<u8>)>>;

/// Runs `frames` frames of `graph` in this process with the given node values (one per
/// graph node, same order): sources produce, every other node steps on the messages its
/// producers sent for that frame. Returns everything every edge carried.
pub fn run_in_process(
    graph: &Graph,
    nodes: &mut [Box<dyn GraphNode>],
    frames: u64,
) -> Result<EdgeLog, String> {
    let mut log: EdgeLog = HashMap::new();
    for seq in 0..frames {
        let mut this: HashMap<(String, String), (FrameHeader, Vec<u8>)> = HashMap::new();
        for (spec, node) in graph.nodes.iter().zip(nodes.iter_mut()) {
            let mut out = Collected::default();
            if spec.inputs.is_empty() {
                if !node
                    .produce(seq, &mut out)
                    .map_err(|e| format!("{}: {e}", spec.id))?
                {
                    return Ok(log);
                }
            } else {
                let msgs: Vec<Msg<'_>> = spec
                    .inputs
                    .iter()
                    .map(|i| {
                        this.get(&(i.node.clone(), i.output.clone()))
                            .map(|(h, p)| Msg {
                                header: *h,
                                payload: p,
                            })
                            .ok_or_else(|| {
                                format!("{}: no message on {}/{}", spec.id, i.node, i.output)
                            })
                    })
                    .collect::<Result<_, _>>()?;
                node.step(&msgs, &mut out)
                    .map_err(|e| format!("{}: {e}", spec.id))?;
            }
            for (port, msgs) in out.ports.into_iter().enumerate() {
                let name = spec.outputs[port].0.clone();
                for m in msgs {
                    log.entry((spec.id.clone(), name.clone()))
                        .or_default()
                        .push(m.clone());
                    this.insert((spec.id.clone(), name.clone()), m);
                }
            }
        }
    }
    Ok(log)
}
