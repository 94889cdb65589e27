//! Triangulation with the parallel-axis model, world origin midway between the cameras
//! (the paper's §2.5.2):
//!
//! ```text
//! xl = x − cx,  xr = (x − d) − cx_right,  d' = xl − xr = d + (cx_right − cx)
//! Z = b·f / d',  X = b·(xl + xr) / (2·d'),  Y = b·(y − cy) / d'
//! ```
//!
//! `f` is in pixels (for a microscope f_eff / pixel pitch, see
//! [`schemas::Calibration::from_microscope`]); coordinates come out in the calibration's
//! unit. Only pixels with a finite disparity and a positive `d'` (in front of the cameras)
//! become points; each carries the left image's colour.
//!
//! The crate also holds what the method measures per cell ([`measure`]: substrate and
//! tops by photometric fits in [`refine`], heights, volumes, 3D centroids, on the cell-only
//! maps the `cells` crate composes) and the triangulate node
//! ([`node`]).

pub mod geometry;
mod lanes;
pub mod measure;
pub mod node;
pub mod refine;
pub mod substrate;

use schemas::{Calibration, DisparityMap, Plane, Point3, PointCloud};

/// The depth `Z = b·f/d'` of disparity `d` (`d' = d + cx_right − cx`, the disparity the
/// principal points' offset makes of it); `None` at or beyond infinite depth (`d' ≤ 0`):
/// no point of the scene, and never a number that is not one.
pub fn depth_of(d: f64, c: &Calibration) -> Option<f64> {
    let dp = d + c.cx_right - c.cx;
    (dp > 0.0)
        .then(|| c.baseline * c.focal_px / dp)
        .filter(|z| z.is_finite())
}

/// One pixel's 3D position, or `None` when it has no disparity or lies at/behind infinity.
pub fn triangulate_pixel(x: f64, y: f64, d: f64, c: &Calibration) -> Option<[f64; 3]> {
    if !d.is_finite() {
        return None;
    }
    let xl = x - c.cx;
    let xr = (x - d) - c.cx_right;
    let de = xl - xr;
    if de <= 0.0 {
        return None;
    }
    let b = c.baseline;
    Some([
        b * (xl + xr) / (2.0 * de),
        b * (y - c.cy) / de,
        b * c.focal_px / de,
    ])
}

/// Triangulates every valid pixel of a left-based disparity map.
///
/// `colour` must have the map's size; pass a grey image expanded to RGB for grey input.
pub fn triangulate(
    disp: &DisparityMap,
    calib: &Calibration,
    colour: &Plane<[u8; 3]>,
) -> PointCloud {
    triangulate_every(disp, calib, &|x, y| *colour.get(x, y), 1)
}

/// Triangulates the valid pixels of every `step`-th row and column of a left-based
/// disparity map (`step` 1: every one), each coloured by `colour(x, y)`.
pub fn triangulate_every(
    disp: &DisparityMap,
    calib: &Calibration,
    colour: &dyn Fn(usize, usize) -> [u8; 3],
    step: usize,
) -> PointCloud {
    let step = step.max(1);
    let mut points = Vec::new();
    for y in (0..disp.height).step_by(step) {
        for (x, &d) in disp.row(y).iter().enumerate().step_by(step) {
            if let Some([px, py, pz]) = triangulate_pixel(x as f64, y as f64, d as f64, calib) {
                points.push(Point3 {
                    x: px,
                    y: py,
                    z: pz,
                    rgb: colour(x, y),
                    col: x as u32,
                    row: y as u32,
                });
            }
        }
    }
    PointCloud {
        unit: calib.unit,
        points,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use schemas::{INVALID_DISPARITY, LengthUnit};

    fn calib() -> Calibration {
        Calibration {
            baseline: 100.0,
            focal_px: 500.0,
            cx: 10.0,
            cy: 5.0,
            cx_right: 10.0,
            unit: LengthUnit::Mm,
        }
    }

    #[test]
    fn hand_computed_point() {
        // x=30, y=25, d=20: xl=20, xr=0, Z=100·500/20=2500, X=100·20/40=50, Y=100·20/20=100.
        let p = triangulate_pixel(30.0, 25.0, 20.0, &calib()).unwrap();
        assert_eq!(p, [50.0, 100.0, 2500.0]);
    }

    #[test]
    fn principal_point_offset_shifts_effective_disparity() {
        // cx_right − cx = −5: d = 25 behaves like 20.
        let c = Calibration {
            cx_right: 5.0,
            ..calib()
        };
        let p = triangulate_pixel(30.0, 25.0, 25.0, &c).unwrap();
        assert_eq!(p[2], 2500.0);
        // xl = 20, xr = 30 − 25 − 5 = 0.
        assert_eq!(p[0], 50.0);
        // A disparity at or beyond infinity has no point.
        assert!(triangulate_pixel(30.0, 25.0, 5.0, &c).is_none());
    }

    #[test]
    fn microscope_units() {
        // f_eff 20 mm = 20000 µm, pitch 5 µm → f = 4000 px; b = 2000 µm; d = 80 px → Z = 100000 µm.
        let c = Calibration::from_microscope(2000.0, 20000.0, 5.0, 0.0, 0.0, LengthUnit::Um);
        assert_eq!(c.focal_px, 4000.0);
        let p = triangulate_pixel(80.0, 0.0, 80.0, &c).unwrap();
        assert_eq!(p, [1000.0, 0.0, 100000.0]);
    }

    #[test]
    fn only_valid_points_with_colour() {
        let disp = Plane::from_vec(3, 1, vec![20.0, INVALID_DISPARITY, -1.0]).unwrap();
        let colour = Plane::from_vec(3, 1, vec![[1, 2, 3], [4, 5, 6], [7, 8, 9]]).unwrap();
        let cloud = triangulate(&disp, &calib(), &colour);
        assert_eq!(cloud.points.len(), 1);
        assert_eq!(cloud.points[0].rgb, [1, 2, 3]);
        assert_eq!(cloud.unit, LengthUnit::Mm);
    }

    #[test]
    fn a_stepped_cloud_is_the_whole_one_on_every_nth_row_and_column() {
        let (w, h) = (23, 17);
        let data = (0..w * h)
            .map(|i| {
                if i % 7 == 3 {
                    INVALID_DISPARITY
                } else {
                    15.0 + (i % 5) as f32
                }
            })
            .collect();
        let disp = Plane::from_vec(w, h, data).unwrap();
        let colour = |x: usize, y: usize| [x as u8, y as u8, 0];
        let whole = triangulate_every(&disp, &calib(), &colour, 1);
        for step in [1, 2, 3, 5] {
            let part = triangulate_every(&disp, &calib(), &colour, step);
            let want: Vec<&Point3> = whole
                .points
                .iter()
                .filter(|p| {
                    (p.col as usize).is_multiple_of(step) && (p.row as usize).is_multiple_of(step)
                })
                .collect();
            assert_eq!(part.points.iter().collect::<Vec<_>>(), want, "step {step}");
            assert!(!part.points.is_empty());
        }
        // Step 0 is taken as 1.
        assert_eq!(triangulate_every(&disp, &calib(), &colour, 0), whole);
    }
}
