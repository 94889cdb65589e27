//! The segment node: a stereo frame in; both views' label images and cell lists out.

use crate::{SegmentParams, segment};
use runtime::step::{GraphNode, Msg, Outputs, params};
use schemas::MessageKind;
use schemas::wire::{CellLists, json_header, planes_header, read_planes, write_planes};

/// Reads and checks the `params` of a `segment` node (the fields of [`SegmentParams`]).
pub fn params_from_table(t: &toml::Table) -> Result<SegmentParams, String> {
    let mut full = toml::Table::try_from(SegmentParams::default()).map_err(|e| e.to_string())?;
    for (k, v) in t {
        if !full.contains_key(k) {
            return Err(format!(
                "unknown parameter '{k}'; known: {}",
                full.keys().cloned().collect::<Vec<_>>().join(", ")
            ));
        }
        full.insert(k.clone(), v.clone());
    }
    let p: SegmentParams = params(&full)?;
    if p.variance_radius == 0 || p.variance_radius > 50 {
        return Err(format!(
            "variance_radius {} must be 1..=50",
            p.variance_radius
        ));
    }
    Ok(p)
}

/// Segments both views of each frame.
#[derive(Debug)]
pub struct SegmentNode {
    /// Settings.
    pub params: SegmentParams,
}

impl GraphNode for SegmentNode {
    fn step(&mut self, inputs: &[Msg<'_>], out: &mut dyn Outputs) -> Result<(), String> {
        let frame = &inputs[0];
        let views = read_planes::<u8>(&frame.header, frame.payload).map_err(|e| e.to_string())?;
        let [l, r] = views.as_slice() else {
            return Err(format!("a stereo frame has 2 images, not {}", views.len()));
        };
        let (ls, rs) = rayon::join(|| segment(l, &self.params), || segment(r, &self.params));
        let (mut h, len) = planes_header(MessageKind::Labels, &[&ls.labels, &rs.labels]);
        h.sequence = frame.header.sequence;
        h.capture_ns = frame.header.capture_ns;
        out.send(0, h, len, &mut |b| {
            write_planes(&[&ls.labels, &rs.labels], b)
        })?;
        let cells = serde_json::to_vec(&CellLists {
            left: ls.cells,
            right: rs.cells,
        })
        .map_err(|e| e.to_string())?;
        let h = schemas::FrameHeader {
            sequence: frame.header.sequence,
            capture_ns: frame.header.capture_ns,
            ..json_header(MessageKind::CellList)
        };
        out.send(1, h, cells.len(), &mut |b| b.copy_from_slice(&cells))
    }
}
