//! Calibration in microstereo, in one place: the rig's model and its rectification
//! ([`stereo`]: [`stereo::StereoCalibration`], [`stereo::Rectification`]), the calibration
//! file the rectifier, the triangulate node, `reconstruct` and the calibrate commands share
//! ([`file`]), chessboard corners (`board::find_board`), both cameras and their relative
//! pose fitted to pairs of views (`calibrate::calibrate_stereo`; these two under the
//! default feature `boards`), a folder of board pairs calibrated as one rig
//! (`pairs::find_pairs`, `pairs::BoardPairs`, also under `boards`) and the microscope's
//! depth from a z-stack ([`file::fit_depth`]).

#[cfg(feature = "boards")]
pub mod board;
#[cfg(feature = "boards")]
pub mod calibrate;
pub mod file;
pub mod lm;
pub mod microscope;
#[cfg(feature = "boards")]
pub mod pairs;
pub mod stack;
#[cfg(feature = "boards")]
pub mod stage;
pub mod stereo;
pub mod target;

use schemas::Plane;

/// Bilinear sample of `p` at `(x, y)`; `None` outside the pixel centres' span.
pub fn bilinear<T: Copy + Into<f64>>(p: &Plane<T>, x: f64, y: f64) -> Option<f64> {
    if !(x >= 0.0 && y >= 0.0 && x <= (p.width - 1) as f64 && y <= (p.height - 1) as f64) {
        return None;
    }
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(p.width - 1), (y0 + 1).min(p.height - 1));
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    let g = |x: usize, y: usize| (*p.get(x, y)).into();
    Some(
        (g(x0, y0) * (1.0 - fx) + g(x1, y0) * fx) * (1.0 - fy)
            + (g(x0, y1) * (1.0 - fx) + g(x1, y1) * fx) * fy,
    )
}
