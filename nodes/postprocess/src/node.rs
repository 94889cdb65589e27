//! The postprocess node: a checked disparity map in, the post-processed map out.

use crate::{PostParams, postprocess};
use runtime::step::{GraphNode, Msg, Outputs, params_over, send_planes};
use schemas::MessageKind;

/// Reads the `params` of a postprocess node (the fields of [`PostParams`]; defaults are
/// the quality matcher's).
pub fn params_from_table(t: &toml::Table) -> Result<PostParams, String> {
    let defaults = PostParams {
        min_region: 100,
        region_max_diff: 1.0,
        median_radius: 2,
        fill: crate::Fill::Background,
    };
    params_over(&defaults, t)
}

/// Post-processes each frame's map.
#[derive(Debug)]
pub struct PostprocessNode {
    /// Settings.
    pub params: PostParams,
}

impl GraphNode for PostprocessNode {
    fn step(&mut self, inputs: &[Msg<'_>], out: &mut dyn Outputs) -> Result<(), String> {
        let [map] = inputs[0].planes_n::<f32, 1>()?;
        let post = postprocess(&map, &self.params);
        send_planes(out, 0, MessageKind::Disparity, inputs[0].stamp(), &[&post])
    }
}
