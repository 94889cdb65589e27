//! A second custom node, on the node API alone (no transport, no runtime): it keeps the
//! cells of both views whose area lies in `min_area..=max_area` pixels, so that debris
//! and clumps never reach the matcher. A new node kind is this one [`Task`] impl plus one
//! registry line (`pipelines::registry::builtin().task::<CellFilter>()`); `cargo tree
//! -p cell-filter-node` holds node-api, schemas and serde.
//!
//! ```toml
//! [[node]]
//! id = "filter"
//! kind = "cell-filter"
//! inputs = { cells = "segment/cells" }
//! params = { min_area = 200, max_area = 20000 }
//! ```

use node_api::{NodeError, Params, Stamp, Task};
use schemas::{Cell, CellLists};
use serde::Deserialize;

/// `params` of a cell-filter node.
#[derive(Clone, Copy, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CellFilterParams {
    /// Smallest area kept, px.
    #[serde(default)]
    pub min_area: u64,
    /// Largest area kept, px.
    #[serde(default = "any_area")]
    pub max_area: u64,
}

fn any_area() -> u64 {
    u64::MAX
}

impl Params for CellFilterParams {
    fn check(&self) -> Result<(), String> {
        if self.min_area > self.max_area {
            return Err(format!(
                "min_area {} is above max_area {}: no cell could pass; swap them",
                self.min_area, self.max_area
            ));
        }
        Ok(())
    }
}

node_api::ports! {
    /// What the cell-filter node reads and sends.
    pub struct Cells {
        /// Both views' cells.
        pub cells: CellLists,
    }
}

/// Keeps the cells whose area lies in the range, in their order.
#[derive(Debug)]
pub struct CellFilter {
    params: CellFilterParams,
}

impl CellFilter {
    fn keep(&self, cells: Vec<Cell>) -> Vec<Cell> {
        let p = self.params;
        cells
            .into_iter()
            .filter(|c| (p.min_area..=p.max_area).contains(&c.area))
            .collect()
    }
}

impl Task for CellFilter {
    const KIND: &'static str = "cell-filter";
    type Params = CellFilterParams;
    type Input = Cells;
    type Output = Cells;
    type Error = NodeError;

    fn new(params: CellFilterParams) -> Result<Self, NodeError> {
        Ok(Self { params })
    }

    fn process(&mut self, _: Stamp, i: Cells) -> Result<Cells, NodeError> {
        let CellLists { left, right } = i.cells;
        Ok(Cells {
            cells: CellLists {
                left: self.keep(left),
                right: self.keep(right),
            },
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use schemas::BoundingBox;

    fn cell(id: u32, area: u64) -> Cell {
        Cell {
            id,
            area,
            centroid: [0.0, 0.0],
            bbox: BoundingBox {
                x0: 0,
                y0: 0,
                x1: 1,
                y1: 1,
            },
            contour: Vec::new(),
            perimeter: 0.0,
        }
    }

    #[test]
    fn cells_outside_the_area_range_are_dropped_in_both_views() {
        let p = CellFilterParams {
            min_area: 10,
            max_area: 100,
        };
        let mut n = CellFilter::new(p).unwrap();
        let cells = CellLists {
            left: vec![cell(1, 9), cell(2, 10), cell(3, 100), cell(4, 101)],
            right: vec![cell(1, 50), cell(2, 5000)],
        };
        let out = n.process(Stamp::default(), Cells { cells }).unwrap().cells;
        let ids = |v: &[Cell]| v.iter().map(|c| c.id).collect::<Vec<_>>();
        assert_eq!(ids(&out.left), [2, 3]);
        assert_eq!(ids(&out.right), [1]);
        let swapped = CellFilterParams {
            min_area: 100,
            max_area: 10,
        };
        assert!(swapped.check().unwrap_err().contains("swap them"));
    }
}
