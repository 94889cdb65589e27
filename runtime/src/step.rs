//! The graph's view of a node: one step from one frame's input messages to its output
//! messages, as bytes with a [`FrameHeader`]. The same [`GraphNode`] value runs in a node
//! process behind the shared-memory transport ([`crate::process`]) and in-process
//! ([`run_in_process`]), so a graph and its in-process twin compute the same bytes.

use crate::launch::Graph;
use schemas::wire::{WirePixel, json_header, planes_header, read_planes, write_planes};
use schemas::{FrameHeader, MessageKind, Plane};
use std::collections::HashMap;

/// A message as a node reads it.
#[derive(Clone, Copy, Debug)]
pub struct Msg<'a> {
    /// Its header.
    pub header: FrameHeader,
    /// Its payload.
    pub payload: &'a [u8],
}

/// Which frame a message belongs to: `(sequence, capture time)`, carried by everything
/// derived from it.
pub type Stamp = (u64, u64);

impl Msg<'_> {
    /// Its frame's stamp.
    pub fn stamp(&self) -> Stamp {
        (self.header.sequence, self.header.capture_ns)
    }

    /// Its images, which must hold pixels of type `T`.
    pub fn planes<T: WirePixel>(&self) -> Result<Vec<Plane<T>>, String> {
        read_planes(&self.header, self.payload).map_err(|e| e.to_string())
    }

    /// Its images when there must be exactly `N` (a stereo frame, a pair of label images).
    pub fn planes_n<T: WirePixel, const N: usize>(&self) -> Result<[Plane<T>; N], String> {
        let v = self.planes::<T>()?;
        let n = v.len();
        v.try_into().map_err(|_| {
            format!(
                "a {:?} message with {n} image(s), not {N}",
                MessageKind::from_u32(self.header.kind)
            )
        })
    }
}

/// Sends `planes` as one message of `kind` on output `port`, stamped with `stamp`.
pub fn send_planes<T: WirePixel>(
    out: &mut dyn Outputs,
    port: usize,
    kind: MessageKind,
    (sequence, capture_ns): Stamp,
    planes: &[&Plane<T>],
) -> Result<(), String> {
    let (h, len) = planes_header(kind, planes);
    let h = FrameHeader {
        sequence,
        capture_ns,
        ..h
    };
    out.send(port, h, len, &mut |b| write_planes(planes, b))
}

/// Sends `bytes` (JSON) as one message of `kind` on output `port`, stamped with `stamp`.
pub fn send_json(
    out: &mut dyn Outputs,
    port: usize,
    kind: MessageKind,
    (sequence, capture_ns): Stamp,
    bytes: &[u8],
) -> Result<(), String> {
    let h = FrameHeader {
        sequence,
        capture_ns,
        ..json_header(kind)
    };
    out.send(port, h, bytes.len(), &mut |b| b.copy_from_slice(bytes))
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

    /// The newest message of feedback input `port` (its index among the node's inputs),
    /// given before the next step or production whenever a new one arrived.
    fn feedback(&mut self, _port: usize, _msg: Msg<'_>) -> Result<(), String> {
        Ok(())
    }

    /// One step on one frame's inputs, in the order of the node's input ports (feedback
    /// inputs left out).
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

/// Reads a node's `params` table over the settings `defaults`: every key must be one of
/// theirs (for settings types that already serialise, so have no `deny_unknown_fields`).
pub fn params_over<T: serde::Serialize + serde::de::DeserializeOwned>(
    defaults: &T,
    t: &toml::Table,
) -> Result<T, String> {
    let mut full = toml::Table::try_from(defaults).map_err(|e| e.to_string())?;
    for (k, v) in t {
        if !full.contains_key(k) {
            return Err(format!(
                "unknown parameter '{k}'; known: {}",
                full.keys().cloned().collect::<Vec<_>>().join(", ")
            ));
        }
        full.insert(k.clone(), v.clone());
    }
    params(&full)
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
            // Feedback: the newest message its producer sent so far (this frame's when the
            // producer came first, else the last frame's).
            for (k, i) in spec.inputs.iter().enumerate().filter(|(_, i)| i.feedback) {
                if let Some((h, p)) = log
                    .get(&(i.node.clone(), i.output.clone()))
                    .and_then(|v| v.last())
                {
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
            if spec.inputs.iter().all(|i| i.feedback) {
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
                    .filter(|i| !i.feedback)
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
