//! The segment node: a stereo frame in; both views' label images and cell lists out.

use crate::{SegmentParams, segment};
use node_api::{NodeError, Params, Stamp, Task};
use schemas::{CellLists, Labels, StereoFrame};

impl Params for SegmentParams {
    fn check(&self) -> Result<(), String> {
        // Areas past a 10 000 × 10 000 image's are typing errors, not settings.
        const MAX_AREA: usize = 100_000_000;
        if self.variance_radius == 0 || self.variance_radius > 50 {
            return Err(format!(
                "variance_radius {} is out of range: use 1..=50",
                self.variance_radius
            ));
        }
        if !(0.0..=255.0).contains(&self.min_std) {
            return Err(format!(
                "min_std {} is out of range: use 0..=255 grey levels",
                self.min_std
            ));
        }
        if !(0.0..=20.0).contains(&self.noise_floor) {
            return Err(format!(
                "noise_floor {} is out of range: use 0..=20 times the image's noise",
                self.noise_floor
            ));
        }
        if self.min_area > MAX_AREA {
            return Err(format!(
                "min_area {} is out of range: use 0..={MAX_AREA} pixels",
                self.min_area
            ));
        }
        if self.open_radius > 50 || self.close_radius > 50 {
            return Err("open_radius and close_radius must be 0..=50".into());
        }
        Ok(())
    }
}

node_api::ports! {
    /// What the segment node reads.
    pub struct SegmentIn {
        /// The rectified pair.
        pub frame: StereoFrame,
    }
}

node_api::ports! {
    /// What the segment node sends.
    pub struct SegmentOut {
        /// Both views' label images.
        pub labels: Labels,
        /// Both views' cells.
        pub cells: CellLists,
    }
}

/// Segments both views of each frame.
#[derive(Debug)]
pub struct Segment {
    /// Settings.
    pub params: SegmentParams,
}

impl Task for Segment {
    const KIND: &'static str = "segment";
    type Params = SegmentParams;
    type Input = SegmentIn;
    type Output = SegmentOut;
    type Error = NodeError;

    fn new(params: SegmentParams) -> Result<Self, NodeError> {
        Ok(Self { params })
    }

    fn process(&mut self, _: Stamp, input: SegmentIn) -> Result<SegmentOut, NodeError> {
        let StereoFrame { left, right } = &input.frame;
        let (ls, rs) = rayon::join(
            || segment(left, &self.params),
            || segment(right, &self.params),
        );
        Ok(SegmentOut {
            labels: Labels {
                left: ls.labels,
                right: rs.labels,
            },
            cells: CellLists {
                left: ls.cells,
                right: rs.cells,
            },
        })
    }
}
