//! The postprocess node: checked disparity tiles in, post-processed tiles out (each tile on
//! its own: a cell's crop is filled and smoothed within itself).

use crate::{PostParams, postprocess};
use node_api::{NodeError, Params, Stamp, Task};
use rayon::prelude::*;
use schemas::{DisparityTiles, Side};

impl Params for PostParams {
    fn check(&self) -> Result<(), String> {
        if self.median_radius > crate::MAX_MEDIAN_RADIUS {
            return Err(format!(
                "median_radius {} must be 0..={} (a {}×{} window at most)",
                self.median_radius,
                crate::MAX_MEDIAN_RADIUS,
                2 * crate::MAX_MEDIAN_RADIUS + 1,
                2 * crate::MAX_MEDIAN_RADIUS + 1
            ));
        }
        // Regions past a 10 000 × 10 000 image's are typing errors, not settings.
        if self.min_region > 100_000_000 {
            return Err(format!(
                "min_region {} is out of range: use 0..=100000000 pixels",
                self.min_region
            ));
        }
        if !(self.region_max_diff >= 0.0 && self.region_max_diff.is_finite()) {
            return Err(format!(
                "region_max_diff {} must be a number ≥ 0",
                self.region_max_diff
            ));
        }
        Ok(())
    }
}

node_api::ports! {
    /// What the postprocess node reads and sends.
    pub struct Tiles {
        /// Left-based disparity tiles.
        pub disparity: DisparityTiles,
    }
}

/// Post-processes each frame's tiles.
#[derive(Debug)]
pub struct Postprocess {
    /// Settings.
    pub params: PostParams,
}

impl Task for Postprocess {
    const KIND: &'static str = "postprocess";
    type Params = PostParams;
    type Input = Tiles;
    type Output = Tiles;
    type Error = NodeError;

    fn new(params: PostParams) -> Result<Self, NodeError> {
        Ok(Self { params })
    }

    fn process(&mut self, _: Stamp, i: Tiles) -> Result<Tiles, NodeError> {
        let d = &i.disparity;
        if d.side != Side::Left {
            return Err(NodeError::Failed(
                "post-processing takes left-based tiles (validate/left)".into(),
            ));
        }
        // The tiles side by side: one after another, each step's own parallel loops woke
        // the other thread for every tile (over half the node's CPU went to kernel context
        // switches).
        let tiles = d
            .tiles
            .par_iter()
            .map(|t| match t.map.is_empty() {
                true => t.clone(),
                false => t.with_map(postprocess(&t.map, &self.params)),
            })
            .collect();
        Ok(Tiles {
            disparity: d.with_tiles(Side::Left, tiles),
        })
    }
}
