//! The match-lr and match-rl nodes: a stereo frame in, one direction's disparity map out.
//! Both run the same matcher on the same pair; each keeps its own direction.

use crate::{Directions, Mode, PaperParams, QualityParams, QualityWorkspace};
use runtime::step::{GraphNode, Msg, Outputs, params, send_planes};
use schemas::{DisparityRange, MessageKind};
use serde::Deserialize;

/// `params` of a match node.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MatchParams {
    /// Which matcher.
    #[serde(default)]
    pub mode: Mode,
    /// Smallest disparity searched.
    pub min_disparity: i32,
    /// Largest disparity searched.
    pub max_disparity: i32,
}

impl MatchParams {
    /// Reads and checks a `params` table.
    pub fn from_table(t: &toml::Table) -> Result<Self, String> {
        let p: Self = params(t)?;
        if p.min_disparity >= p.max_disparity {
            return Err(format!(
                "min_disparity {} must be below max_disparity {}",
                p.min_disparity, p.max_disparity
            ));
        }
        Ok(p)
    }
}

/// Matches each frame and sends the left-based (`right_based == false`) or right-based map.
#[derive(Debug)]
pub struct MatchNode {
    /// Settings.
    pub params: MatchParams,
    /// Which map this node sends.
    pub right_based: bool,
    ws: QualityWorkspace,
}

impl MatchNode {
    /// A node sending the left- or right-based map.
    pub fn new(params: MatchParams, right_based: bool) -> Self {
        Self {
            params,
            right_based,
            ws: QualityWorkspace::default(),
        }
    }
}

impl GraphNode for MatchNode {
    fn step(&mut self, inputs: &[Msg<'_>], out: &mut dyn Outputs) -> Result<(), String> {
        let [l, r] = &inputs[0].planes_n::<u8, 2>()?;
        let range = DisparityRange::new(self.params.min_disparity, self.params.max_disparity);
        let map = match self.params.mode {
            Mode::Quality => {
                crate::check_inputs(l, r, range, None).map_err(|e| e.to_string())?;
                let p = QualityParams {
                    range,
                    ..QualityParams::default()
                };
                let m = crate::match_quality_in(&mut self.ws, l, r, &p);
                if self.right_based { m.right } else { m.left }
            }
            Mode::Paper => {
                let p = PaperParams {
                    range,
                    ..PaperParams::default()
                };
                crate::check_inputs(l, r, range, Some(p.window)).map_err(|e| e.to_string())?;
                let dir = if self.right_based {
                    Directions::RightToLeft
                } else {
                    Directions::LeftToRight
                };
                let m = crate::match_paper(l, r, &p, dir);
                if self.right_based { m.right } else { m.left }
            }
        };
        send_planes(out, 0, MessageKind::Disparity, inputs[0].stamp(), &[&map])
    }
}
