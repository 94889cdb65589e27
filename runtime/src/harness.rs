//! The node test harness: one node fed recorded inputs frame by frame, its outputs
//! compared with the recorded ones (bit for bit, or floats within a tolerance).
//!
//! The harness takes the recorded frames from any reader (the recorder crate reads MCAP
//! files); a frame is the node's inputs' messages, then its outputs', in port order.

use crate::exec::Collected;
use crate::launch::Graph;
use crate::node::{GraphNode, Msg};
use schemas::{FrameHeader, MessageKind, PixelFormat};

/// One recorded message.
pub type Recorded = (FrameHeader, Vec<u8>);

/// What one output compared.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct OutputCheck {
    /// `NODE/OUTPUT`, or the name of an extra check.
    pub edge: String,
    /// Frames compared.
    pub compared: u64,
    /// Frames whose header and payload are bit-identical to the recording.
    pub identical: u64,
    /// Frames that differ only by float values within the tolerance.
    pub within_tolerance: u64,
    /// Largest difference of a float value, or of a byte, seen.
    pub max_diff: f64,
    /// The first difference found, described.
    pub first_difference: Option<String>,
}

/// What a node test found.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NodeCheck {
    /// The node.
    pub node: String,
    /// Frames the node stepped on.
    pub frames: u64,
    /// Frames the recording holds only in part (skipped).
    pub incomplete: u64,
    /// Per output.
    pub outputs: Vec<OutputCheck>,
}

impl NodeCheck {
    /// Whether every compared frame matched.
    pub fn passed(&self) -> bool {
        self.frames > 0
            && self.outputs.iter().all(|o| {
                o.compared == self.frames && o.identical + o.within_tolerance == o.compared
            })
    }

    /// The report `test-node` prints: the frames, then one line per output.
    pub fn lines(&self, tolerance: f32) -> Vec<String> {
        let part = match self.incomplete {
            0 => String::new(),
            n => format!(", {n} recorded only in part (skipped)"),
        };
        let mut out = vec![format!(
            "{}: {} frame(s) stepped on recorded inputs{part}",
            self.node, self.frames
        )];
        out.extend(self.outputs.iter().map(|o| {
            format!(
                "  {:<28} {:>4} compared {:>4} identical {:>4} within ±{tolerance}  max diff {}{}",
                o.edge,
                o.compared,
                o.identical,
                o.within_tolerance,
                o.max_diff,
                o.first_difference
                    .as_ref()
                    .map_or(String::new(), |d| format!("  first: {d}"))
            )
        }));
        out
    }
}

/// Edges as `(NODE/OUTPUT, message)`.
pub type Edges = Vec<(String, MessageKind)>;

/// The edges a test of node `id` reads from a recording: its joined inputs (feedback
/// carries whatever was newest when the node ran: not replayable) and its outputs but
/// those `skip` names, each as `(NODE/OUTPUT, message)`.
pub fn edges_under_test(
    graph: &Graph,
    id: &str,
    skip: &dyn Fn(MessageKind) -> bool,
) -> (Edges, Edges) {
    let inputs = graph
        .input_edges(id)
        .into_iter()
        .zip(graph.node(id).map(|n| n.inputs.as_slice()).unwrap_or(&[]))
        .filter(|(_, i)| !i.feedback)
        .map(|(e, _)| e)
        .collect();
    let outputs = graph
        .output_edges(id)
        .into_iter()
        .filter(|(_, k)| !skip(*k))
        .collect();
    (inputs, outputs)
}

/// A check besides the outputs: gets each frame's number and recorded inputs, returns a
/// description of what differs (`Some`) or `None`.
pub type ExtraCheck<'a> = Box<dyn FnMut(u64, &[Recorded]) -> Option<String> + 'a>;

/// Steps `node` on each recorded frame (`inputs` messages, then one per name of
/// `outputs`) and compares what it sends on its first `outputs.len()` ports. A source
/// (no inputs) makes each recorded frame's number and is compared without capture times
/// (wall clock). `extra` (named) is asked about every frame too.
pub fn check_node(
    id: &str,
    node: &mut dyn GraphNode,
    inputs: usize,
    outputs: &[String],
    frames: impl Iterator<Item = Result<Vec<Recorded>, String>>,
    tolerance: f32,
    mut extra: Option<(String, ExtraCheck<'_>)>,
) -> Result<NodeCheck, String> {
    let mut check = NodeCheck {
        node: id.into(),
        outputs: outputs
            .iter()
            .map(|e| OutputCheck {
                edge: e.clone(),
                ..OutputCheck::default()
            })
            .collect(),
        ..NodeCheck::default()
    };
    if let Some((name, _)) = &extra {
        check.outputs.push(OutputCheck {
            edge: name.clone(),
            ..OutputCheck::default()
        });
    }
    let source = inputs == 0;
    for f in frames {
        let f = f?;
        let seq = f[0].0.sequence;
        let mut out = Collected::default();
        if source {
            if !node.produce(seq, &mut out)? {
                break;
            }
        } else {
            let msgs: Vec<Msg<'_>> = f[..inputs]
                .iter()
                .map(|(h, p)| Msg {
                    header: *h,
                    payload: p,
                })
                .collect();
            node.step(&msgs, &mut out)
                .map_err(|e| format!("{id}, frame {seq}: {e}"))?;
        }
        check.frames += 1;
        for (port, (wh, wp)) in f[inputs..].iter().enumerate() {
            let c = &mut check.outputs[port];
            match out.ports.get(port).and_then(|p| p.first()) {
                Some((h, p)) => compare(c, (h, p), (wh, wp), tolerance, source),
                None => {
                    c.compared += 1;
                    c.first_difference
                        .get_or_insert_with(|| format!("frame {seq}: nothing sent"));
                }
            }
        }
        if let Some((_, x)) = extra.as_mut() {
            let c = check.outputs.last_mut().expect("pushed");
            c.compared += 1;
            match x(seq, &f[..inputs]) {
                None => c.identical += 1,
                Some(d) => {
                    c.first_difference
                        .get_or_insert_with(|| format!("frame {seq}: {d}"));
                }
            }
        }
    }
    Ok(check)
}

/// Compares one produced message with the recorded one.
fn compare(
    out: &mut OutputCheck,
    got: (&FrameHeader, &[u8]),
    want: (&FrameHeader, &[u8]),
    tolerance: f32,
    ignore_time: bool,
) {
    out.compared += 1;
    let norm = |h: &FrameHeader| FrameHeader {
        edge_sequence: 0,
        capture_ns: if ignore_time { 0 } else { h.capture_ns },
        ..*h
    };
    let (gh, wh) = (norm(got.0), norm(want.0));
    if gh != wh {
        out.first_difference.get_or_insert_with(|| {
            format!("frame {}: header {gh:?} ≠ recorded {wh:?}", wh.sequence)
        });
        return;
    }
    if got.1 == want.1 {
        out.identical += 1;
        return;
    }
    // Pixel maps compare value by value; a tiles message has records before its floats,
    // which must agree exactly.
    let skip = if MessageKind::from_u32(wh.kind) == Some(MessageKind::DisparityTiles) {
        schemas::msg::tile_records_len(wh.images as usize)
    } else {
        0
    };
    let floats = PixelFormat::from_u32(wh.format) == Some(PixelFormat::F32)
        && got.1.len() == want.1.len()
        && got.1.len() >= skip
        && got.1[..skip] == want.1[..skip]
        && (got.1.len() - skip).is_multiple_of(4);
    let mut worst = 0f64;
    let mut first = None;
    if floats {
        for (i, (a, b)) in got.1[skip..]
            .chunks_exact(4)
            .zip(want.1[skip..].chunks_exact(4))
            .enumerate()
        {
            let a = f32::from_le_bytes([a[0], a[1], a[2], a[3]]);
            let b = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            let d = if a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()) {
                0.0
            } else if a.is_finite() && b.is_finite() {
                f64::from((a - b).abs())
            } else {
                f64::INFINITY
            };
            if d > worst {
                worst = d;
                first.get_or_insert(format!("value {i}: {a} ≠ recorded {b}"));
            }
        }
    } else {
        let i = got.1.iter().zip(want.1).position(|(a, b)| a != b);
        worst = f64::INFINITY;
        first = Some(match i {
            Some(i) => format!(
                "byte {i} differs ({} bytes against {})",
                got.1.len(),
                want.1.len()
            ),
            None => format!("{} bytes against {}", got.1.len(), want.1.len()),
        });
    }
    out.max_diff = out.max_diff.max(worst);
    if floats && worst <= f64::from(tolerance) {
        out.within_tolerance += 1;
    } else {
        out.first_difference
            .get_or_insert_with(|| format!("frame {}: {}", wh.sequence, first.unwrap_or_default()));
    }
}
