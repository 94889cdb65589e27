//! The triangulate node: the final disparity tiles in; the point cloud, the frame's cells
//! in 3D (when given the segmentation) and the final full-frame map out.

use crate::geometry::Geometry;
use crate::measure::{Background, cell_heights, lone_cells, measure};
use crate::refine::{BandPassed, PlaneTrack};
use cells::{compose, mask_of};
use node_api::{NodeError, Params, Stamp, Task};
use schemas::{
    Calibration, CellLists, Cloud, Disparity, DisparityRange, DisparityTiles, Image, Labels,
    StereoFrame, Targets,
};
use serde::Deserialize;

/// `params` of a triangulate node.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TriangulateParams {
    /// The geometry: `"synthetic"` (the synthetic capture's optics), a calibration file, or
    /// its keys inline.
    #[serde(default = "synthetic")]
    pub calibration: Geometry,
    /// Follow the substrate plane from frame to frame: each frame where the last one's plane
    /// still holds is fitted on every second row from it and combined with it (a live
    /// substrate moves slowly; on the default graph the plane then takes 5.7 ms instead of
    /// 15.5); `false` fits every frame whole from scratch, as `reconstruct` does.
    #[serde(default = "yes")]
    pub track_substrate: bool,
    /// Pixels between the cloud's points along rows and columns: 1 (the default) sends
    /// every valid pixel of the final map, N every N-th row and column, 0 an empty cloud
    /// (the live graph's choice: its controller reads the cells, and a whole cloud is about
    /// 3 MB a 1280×1024 frame to work out and send).
    #[serde(default = "one")]
    pub cloud_step: usize,
}

fn one() -> usize {
    1
}

fn synthetic() -> Geometry {
    Geometry::Synthetic
}

fn yes() -> bool {
    true
}

impl Params for TriangulateParams {
    fn check(&self) -> Result<(), String> {
        if self.cloud_step > MAX_CLOUD_STEP {
            return Err(format!(
                "cloud_step = {} is more than {MAX_CLOUD_STEP}: give 0 (no cloud), 1 (every valid pixel) or every how many rows and columns a point is taken",
                self.cloud_step
            ));
        }
        self.calibration.check()
    }
}

/// The largest `cloud_step`: a point every 64 rows and columns is a sketch already.
const MAX_CLOUD_STEP: usize = 64;

node_api::ports! {
    /// What the triangulate node reads.
    pub struct TriangulateIn {
        /// The rectified pair (the views the cells' tops are fitted in; grey point colours).
        pub frame: StereoFrame,
        /// The final (post-processed) left disparity.
        pub disparity: DisparityTiles,
        /// After the LR check: with `labels` and `cells`, the cells are measured.
        pub checked: Option<DisparityTiles>,
        /// Both views' labels.
        pub labels: Option<Labels>,
        /// Both views' cells.
        pub cells: Option<CellLists>,
        /// The left view in colour, for the points.
        pub colour: Option<Image>,
    }
}

node_api::ports! {
    /// What the triangulate node sends.
    pub struct TriangulateOut {
        /// Every valid pixel of the final map, in the calibration's unit.
        pub cloud: Cloud,
        /// The frame's cells in 3D (none without the segmentation).
        pub targets: Targets,
        /// The final left map over the whole frame (cells only: valid in and around them).
        pub disparity: Disparity,
    }
}

/// Triangulates each frame's final map and measures its cells.
#[derive(Debug)]
pub struct Triangulate {
    params: TriangulateParams,
    /// The calibration for frames of a size, and the field its board covered.
    calibration: Option<(usize, usize, Calibration, Option<[f64; 4]>)>,
    /// The substrate plane tracked up to the last frame, its frame size and disparity range.
    plane: Option<((usize, usize), DisparityRange, PlaneTrack)>,
    /// Whether it said that cells lie beyond infinite depth (once a run).
    told_infinity: bool,
}

impl Triangulate {
    /// The calibration for frames of `w × h` (read once; a file's missing principal point
    /// defaults to the image centre).
    fn calibration(
        &mut self,
        w: usize,
        h: usize,
    ) -> Result<(Calibration, Option<[f64; 4]>), String> {
        if let Some((cw, ch, c, f)) = self.calibration
            && (cw, ch) == (w, h)
        {
            return Ok((c, f));
        }
        let (c, f) = self.params.calibration.resolve_with_field(w, h)?;
        self.calibration = Some((w, h, c, f));
        Ok((c, f))
    }
}

/// What a frame whose cells lie at or beyond infinite depth tells the user.
pub fn infinity_warning(cells: usize, calib: &Calibration) -> String {
    format!(
        "warning: {cells} cell(s) lie at or beyond infinite depth with this calibration (disparity + cx_right − cx ≤ 0, with cx_right − cx = {:.1} px) and are left out: give the calibration's cx_right (the right camera's principal point in the left's rectified frame), or check its cx",
        calib.cx_right - calib.cx
    )
}

impl Task for Triangulate {
    const KIND: &'static str = "triangulate";
    type Params = TriangulateParams;
    type Input = TriangulateIn;
    type Output = TriangulateOut;
    type Error = NodeError;

    fn new(params: TriangulateParams) -> Result<Self, NodeError> {
        Ok(Self {
            params,
            calibration: None,
            plane: None,
            told_infinity: false,
        })
    }

    fn check_inputs(_: &TriangulateParams, connected: &[&str]) -> Result<(), String> {
        let cells = ["checked", "labels", "cells"];
        let n = cells.iter().filter(|p| connected.contains(p)).count();
        if n != 0 && n != cells.len() {
            return Err(
                "measuring cells takes checked, labels and cells together; connect all three (or none for a plain point cloud)"
                    .into(),
            );
        }
        Ok(())
    }

    fn process(&mut self, stamp: Stamp, i: TriangulateIn) -> Result<TriangulateOut, NodeError> {
        let StereoFrame { left, right } = &i.frame;
        let (w, h) = (left.width, left.height);
        if i.disparity.side != schemas::Side::Left {
            return Err(NodeError::Failed(
                "triangulation takes left-based tiles (postprocess/disparity)".into(),
            ));
        }
        if (i.disparity.width, i.disparity.height) != (w, h) {
            return Err(NodeError::Failed(format!(
                "disparity tiles of {}×{} for frames of {w}×{h}",
                i.disparity.width, i.disparity.height
            )));
        }
        let (calib, field) = self.calibration(w, h)?;
        let (map, cells, substrate) = match (&i.labels, &i.cells, &i.checked) {
            (Some(labels), Some(lists), Some(checked)) => {
                // The plane's band-passed views beside the serial composition of the crops.
                let (composed, views) = rayon::join(
                    || {
                        let left_mask = mask_of(&labels.left);
                        let right_mask = mask_of(&labels.right);
                        compose(
                            (&labels.left, &left_mask),
                            (&lists.left, &lists.right),
                            &i.disparity,
                            checked,
                        )
                        .map(|c| (left_mask, right_mask, c))
                    },
                    || BandPassed::of(left, right),
                );
                let (left_mask, right_mask, c) = composed?;
                let range = i.disparity.range;
                let prior = match &self.plane {
                    Some((size, r, p)) if *size == (w, h) && *r == range => Some(p),
                    _ => None,
                };
                let (track, bases, tops) = cell_heights(
                    (left, right),
                    (&labels.left, &left_mask, &right_mask),
                    &lists.left,
                    &c.pairs,
                    (&c.disparity, &c.raw),
                    i.disparity.range,
                    i.disparity.margin,
                    &calib,
                    prior.filter(|_| self.params.track_substrate),
                    &views,
                );
                let substrate = track.as_ref().map(|t| t.plane);
                self.plane = track.map(|p| ((w, h), range, p));
                let mut cells = measure(
                    (&labels.left, &lists.left, &lists.right),
                    &c.pairs,
                    (&c.disparity, &c.raw),
                    (&bases, &tops),
                    substrate.as_ref().map(|plane| Background {
                        plane,
                        margin: i.disparity.margin,
                        views: (left, right),
                    }),
                    &calib,
                );
                let beyond = crate::measure::beyond_infinity(&bases, &calib);
                if beyond > 0 && !self.told_infinity {
                    self.told_infinity = true;
                    node_api::errln!("{}", infinity_warning(beyond, &calib));
                }
                let lone = lone_cells(
                    (left, right),
                    (&labels.left, &lists.left),
                    &cells,
                    substrate.as_ref(),
                    &bases,
                    i.disparity.range,
                    &calib,
                );
                cells.extend(lone);
                if let Some(f) = field {
                    crate::measure::flag_outside(&mut cells, &lists.left, f);
                }
                (c.disparity, cells, substrate)
            }
            _ => (i.disparity.paste(), Vec::new(), None),
        };
        if let Some(c) = &i.colour
            && c.size() != (w, h)
        {
            return Err(NodeError::Failed(format!(
                "the colour image is {}×{} but the frames are {w}×{h}",
                c.size().0,
                c.size().1
            )));
        }
        // The colour image in RGB only when a cloud is sent; without one, the left view's
        // grey.
        let cloud = match self.params.cloud_step {
            0 => Cloud::default(),
            step => {
                let rgb = i.colour.as_ref().map(Image::to_rgb);
                let colour = |x: usize, y: usize| match &rgb {
                    Some(p) => *p.get(x, y),
                    None => [*left.get(x, y); 3],
                };
                Cloud::from_points(&crate::triangulate_every(&map, &calib, &colour, step))
            }
        };
        Ok(TriangulateOut {
            cloud,
            targets: Targets {
                frame: stamp.sequence,
                capture_ns: stamp.capture_ns,
                unit: calib.unit.symbol().into(),
                cells,
                substrate,
            },
            disparity: Disparity { map },
        })
    }
}
