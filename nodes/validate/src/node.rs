//! The validate node: left- and right-based maps in; the LR-checked left map and the left
//! occlusion mask out.

use runtime::step::{GraphNode, Msg, Outputs, params, send_planes};
use schemas::MessageKind;
use serde::Deserialize;

/// `params` of a validate node.
#[derive(Clone, Copy, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ValidateParams {
    /// LR tolerance, 0..=4 px.
    #[serde(default = "default_tolerance")]
    pub tolerance: u32,
}

fn default_tolerance() -> u32 {
    1
}

impl ValidateParams {
    /// Reads and checks a `params` table.
    pub fn from_table(t: &toml::Table) -> Result<Self, String> {
        let p: Self = params(t)?;
        if p.tolerance > 4 {
            return Err(format!("tolerance {} must be 0..=4", p.tolerance));
        }
        Ok(p)
    }
}

/// Checks each frame's pair of maps.
#[derive(Debug)]
pub struct ValidateNode {
    /// Settings.
    pub params: ValidateParams,
}

impl GraphNode for ValidateNode {
    fn step(&mut self, inputs: &[Msg<'_>], out: &mut dyn Outputs) -> Result<(), String> {
        let [l] = inputs[0].planes_n::<f32, 1>()?;
        let [r] = inputs[1].planes_n::<f32, 1>()?;
        if (l.width, l.height) != (r.width, r.height) {
            return Err("left and right maps differ in size".into());
        }
        let c = crate::lr_check(&l, &r, self.params.tolerance);
        let stamp = inputs[0].stamp();
        send_planes(out, 0, MessageKind::Disparity, stamp, &[&c.left])?;
        send_planes(out, 1, MessageKind::Image, stamp, &[&c.occlusion_left])
    }
}
