//! The validate node: left- and right-based maps in; the LR-checked left map and the left
//! occlusion mask out.

use runtime::step::{GraphNode, Msg, Outputs, params};
use schemas::MessageKind;
use schemas::wire::{planes_header, read_planes, write_planes};
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
        let one = |m: &Msg<'_>| -> Result<schemas::DisparityMap, String> {
            read_planes::<f32>(&m.header, m.payload)
                .map_err(|e| e.to_string())?
                .pop()
                .ok_or_else(|| "an empty disparity message".to_string())
        };
        let (l, r) = (one(&inputs[0])?, one(&inputs[1])?);
        if (l.width, l.height) != (r.width, r.height) {
            return Err("left and right maps differ in size".into());
        }
        let c = crate::lr_check(&l, &r, self.params.tolerance);
        let (seq, t) = (inputs[0].header.sequence, inputs[0].header.capture_ns);
        let (mut h, len) = planes_header(MessageKind::Disparity, &[&c.left]);
        (h.sequence, h.capture_ns) = (seq, t);
        out.send(0, h, len, &mut |b| write_planes(&[&c.left], b))?;
        let (mut h, len) = planes_header(MessageKind::Image, &[&c.occlusion_left]);
        (h.sequence, h.capture_ns) = (seq, t);
        out.send(1, h, len, &mut |b| write_planes(&[&c.occlusion_left], b))
    }
}
