//! The postprocess node: a checked disparity map in, the post-processed map out.

use crate::{PostParams, postprocess};
use runtime::step::{GraphNode, Msg, Outputs, params};
use schemas::MessageKind;
use schemas::wire::{planes_header, read_planes, write_planes};

/// Reads the `params` of a postprocess node (the fields of [`PostParams`]; defaults are
/// the quality matcher's).
pub fn params_from_table(t: &toml::Table) -> Result<PostParams, String> {
    let mut full = toml::Table::try_from(PostParams {
        min_region: 100,
        region_max_diff: 1.0,
        median_radius: 2,
        fill: crate::Fill::Background,
    })
    .map_err(|e| e.to_string())?;
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

/// Post-processes each frame's map.
#[derive(Debug)]
pub struct PostprocessNode {
    /// Settings.
    pub params: PostParams,
}

impl GraphNode for PostprocessNode {
    fn step(&mut self, inputs: &[Msg<'_>], out: &mut dyn Outputs) -> Result<(), String> {
        let m = &inputs[0];
        let map = read_planes::<f32>(&m.header, m.payload)
            .map_err(|e| e.to_string())?
            .pop()
            .ok_or_else(|| "an empty disparity message".to_string())?;
        let post = postprocess(&map, &self.params);
        let (mut h, len) = planes_header(MessageKind::Disparity, &[&post]);
        (h.sequence, h.capture_ns) = (m.header.sequence, m.header.capture_ns);
        out.send(0, h, len, &mut |b| write_planes(&[&post], b))
    }
}
