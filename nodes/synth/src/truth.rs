//! The truth a rendered scene is written with (`truth.json`): the optics, the cells, the
//! pipette, and the disparity range the scene spans.

use crate::{CellTruth, Optics, Pipette, Rendered, Scene};
use serde::Serialize;

/// What truth.json holds.
#[derive(Serialize)]
pub struct Truth<'a> {
    /// The microscope.
    pub optics: &'a Optics,
    /// The seed it was drawn with.
    pub seed: u64,
    /// The rig's calibration.
    pub calibration: &'a schemas::Calibration,
    /// Disparity per µm of height at the substrate.
    pub px_per_um_height: f64,
    /// The smallest and largest true disparity, px.
    pub disparity_range: [f64; 2],
    /// Each cell's truth.
    pub cells: &'a [CellTruth],
    /// The pipette, where there is one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pipette: Option<PipetteTruth>,
}

/// The pipette in truth.json.
#[derive(Serialize)]
pub struct PipetteTruth {
    /// Its shape and place.
    pub spec: Pipette,
    /// The tip's front (the glass's farthest point along it), `[x, y, height]` µm.
    pub front: [f64; 3],
    /// The same in the camera frame `[X, Y, Z]` µm.
    pub front_camera: [f64; 3],
    /// The front in the left and the right view, px.
    pub front_px: [[f64; 2]; 2],
    /// Its defocus blur (Gaussian sigma, px).
    pub defocus_px: f64,
}

impl<'a> Truth<'a> {
    /// The truth of `scene` as `r` rendered it.
    pub fn of(scene: &'a Scene, r: &'a Rendered) -> Self {
        let (lo, hi) = r.disparity_range();
        Truth {
            optics: &scene.optics,
            seed: scene.seed,
            calibration: &r.calibration,
            px_per_um_height: scene.optics.px_per_um_height(),
            disparity_range: [lo as f64, hi as f64],
            cells: &r.cells,
            pipette: scene.pipette.map(|p| PipetteTruth {
                spec: p,
                front: p.front(),
                front_camera: scene.camera_point(p.front()),
                front_px: scene.project(p.front()),
                defocus_px: scene.pipette_defocus_px(),
            }),
        }
    }
}
