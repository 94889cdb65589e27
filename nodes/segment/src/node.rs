//! The segment node: a stereo frame in; both views' label images and cell lists out.

use crate::{SegmentParams, segment};
use runtime::step::{GraphNode, Msg, Outputs, params_over, send_json, send_planes};
use schemas::MessageKind;
use schemas::wire::CellLists;

/// Reads and checks the `params` of a `segment` node (the fields of [`SegmentParams`]).
pub fn params_from_table(t: &toml::Table) -> Result<SegmentParams, String> {
    let p = params_over(&SegmentParams::default(), t)?;
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
        let [l, r] = inputs[0].planes_n::<u8, 2>()?;
        let (ls, rs) = rayon::join(|| segment(&l, &self.params), || segment(&r, &self.params));
        let stamp = inputs[0].stamp();
        send_planes(
            out,
            0,
            MessageKind::Labels,
            stamp,
            &[&ls.labels, &rs.labels],
        )?;
        let cells = serde_json::to_vec(&CellLists {
            left: ls.cells,
            right: rs.cells,
        })
        .map_err(|e| e.to_string())?;
        send_json(out, 1, MessageKind::CellList, stamp, &cells)
    }
}
