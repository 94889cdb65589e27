//! The validate node: the left- and right-based tiles in; both checked against each other
//! tile by tile (the LR consistency check) out, the left tiles with the paper's figures.

use node_api::{NodeError, Params, Stamp, Task};
use rayon::prelude::*;
use schemas::{DisparityTile, DisparityTiles, Side};
use serde::{Deserialize, Serialize};

/// `params` of a validate node.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ValidateParams {
    /// LR tolerance, 0..=4 px.
    #[serde(default = "default_tolerance")]
    pub tolerance: u32,
}

fn default_tolerance() -> u32 {
    1
}

impl Default for ValidateParams {
    fn default() -> Self {
        Self {
            tolerance: default_tolerance(),
        }
    }
}

impl Params for ValidateParams {
    fn check(&self) -> Result<(), String> {
        if self.tolerance > crate::MAX_TOLERANCE {
            return Err(format!(
                "tolerance {} must be 0..={}",
                self.tolerance,
                crate::MAX_TOLERANCE
            ));
        }
        Ok(())
    }
}

node_api::ports! {
    /// What the validate node reads.
    pub struct ValidateIn {
        /// Left-based tiles (left → right matches).
        pub left: DisparityTiles,
        /// Right-based tiles of the same layout (right → left matches).
        pub right: DisparityTiles,
    }
}

node_api::ports! {
    /// What the validate node sends.
    pub struct ValidateOut {
        /// The left tiles, inconsistent pixels invalid, each with the paper's figures.
        pub left: DisparityTiles,
        /// The right tiles, inconsistent pixels invalid.
        pub right: DisparityTiles,
    }
}

/// Checks each frame's pair of maps.
#[derive(Debug)]
pub struct Validate {
    /// Settings.
    pub params: ValidateParams,
}

impl Task for Validate {
    const KIND: &'static str = "validate";
    type Params = ValidateParams;
    type Input = ValidateIn;
    type Output = ValidateOut;
    type Error = NodeError;

    fn new(params: ValidateParams) -> Result<Self, NodeError> {
        Ok(Self { params })
    }

    fn process(&mut self, _: Stamp, i: ValidateIn) -> Result<ValidateOut, NodeError> {
        let (l, r) = (&i.left, &i.right);
        let same = |a: &DisparityTile, b: &DisparityTile| {
            (a.x, a.y, a.map.width, a.map.height, a.cells)
                == (b.x, b.y, b.map.width, b.map.height, b.cells)
        };
        if l.side != Side::Left || r.side != Side::Right {
            return Err(NodeError::Failed(format!(
                "left takes left-based tiles and right right-based ones, not {:?} and {:?}",
                l.side, r.side
            )));
        }
        if (l.width, l.height, l.tiles.len()) != (r.width, r.height, r.tiles.len())
            || !l.tiles.iter().zip(&r.tiles).all(|(a, b)| same(a, b))
        {
            return Err(NodeError::Failed(
                "the left and right tiles differ in layout; both must come from one match".into(),
            ));
        }
        // The tiles side by side: one after another, each check's own parallel loops woke
        // the other thread for every tile (over half the node's CPU went to kernel context
        // switches).
        let (left, right): (Vec<_>, Vec<_>) = l
            .tiles
            .par_iter()
            .zip(&r.tiles)
            .map(|(a, b)| {
                if a.map.is_empty() {
                    return (a.clone(), b.clone());
                }
                let c = crate::lr_check(&a.map, &b.map, self.params.tolerance);
                (
                    DisparityTile {
                        figures: Some(c.figures),
                        ..a.with_map(c.left)
                    },
                    b.with_map(c.right),
                )
            })
            .unzip();
        Ok(ValidateOut {
            left: l.with_tiles(Side::Left, left),
            right: r.with_tiles(Side::Right, right),
        })
    }
}
