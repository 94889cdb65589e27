//! The scene the planner works in: cells as obstacles, the substrate, the workspace.
//!
//! The planner's coordinates are the triangulation's camera frame turned so that height
//! grows upward: `[X, Y, −Z]` in µm (X right and Y down in the left image, origin midway between the
//! cameras), so that a bigger third coordinate is farther from the substrate.
//!
//! A cell is the convex hull of its contour, extruded from below the substrate to the
//! cell's measured top (substrate + height): a prism that holds the whole cell, so
//! clearance from the prism is at least clearance from the cell. The convex hull keeps
//! every distance a convex function, which the planner's exact searches rely on.

use crate::geom::{P3, Prism, convex_hull};
use schemas::Cell3;
use schemas::Targets;
use serde::{Deserialize, Serialize};

/// One cell as an obstacle.
#[derive(Clone, Debug, PartialEq)]
pub struct Obstacle {
    /// The cell's id in its frame's left segmentation.
    pub id: u32,
    /// Its prism.
    pub prism: Prism,
    /// Centroid `[x, y]` of its footprint.
    pub centre: [f64; 2],
    /// Height of the substrate under it.
    pub base: f64,
    /// Height of its top.
    pub top: f64,
    /// Whether its measured height is trusted; an untrusted cell stands at the
    /// conservative height instead.
    pub trusted: bool,
    /// Why its height is not trusted.
    pub doubt: Option<String>,
}

/// Height given to a cell whose height is not trusted by default, µm: the tallest cell a
/// stereo microscope dish plausibly holds (a rounded 100 µm cell).
pub const UNTRUSTED_HEIGHT: f64 = 100.0;

/// The box the tip may move in, µm.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Workspace {
    /// Lowest corner `[x, y, up]`.
    pub min: P3,
    /// Highest corner.
    pub max: P3,
}

impl Workspace {
    /// Whether `p` is inside (edges included, with 1 nm of slack for rounding).
    pub fn contains(&self, p: P3) -> bool {
        (0..3).all(|k| p[k] >= self.min[k] - 1e-3 && p[k] <= self.max[k] + 1e-3)
    }

    /// Says what is wrong with the box, if anything.
    pub fn check(&self) -> Result<(), String> {
        // Manipulators travel centimetres; past 10 m a bound is a typing error.
        let fits = |v: f64| v.abs() <= 1e7;
        if (0..3).any(|k| !fits(self.min[k]) || !fits(self.max[k]) || self.min[k] >= self.max[k]) {
            return Err(format!(
                "workspace min {:?} must be below max {:?} on every axis, each within ±1e7 µm",
                self.min, self.max
            ));
        }
        Ok(())
    }
}

/// The cells of one frame as obstacles.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Scene {
    /// The frame they come from.
    pub frame: u64,
    /// Cells.
    pub cells: Vec<Obstacle>,
    /// The substrate as `up = a·x + b·y + c`, fitted to the cells' bases (none without
    /// cells).
    pub substrate: Option<[f64; 3]>,
}

/// Micrometres per unit of a calibration unit symbol.
pub fn um_per_unit(unit: &str) -> Result<f64, String> {
    Ok(match unit {
        "um" | "µm" => 1.0,
        "mm" => 1e3,
        "m" => 1e6,
        other => return Err(format!("unknown length unit '{other}' in the targets")),
    })
}

impl Obstacle {
    /// A cell of the triangulation, in µm (`k` µm per unit); a cell without a trusted
    /// height stands `untrusted` µm high, never at its doubtful height.
    pub fn from_cell(c: &Cell3, k: f64, untrusted: f64) -> Self {
        let base = -c.substrate_z * k;
        let pts: Vec<[f64; 2]> = c.contour.iter().map(|p| [p[0] * k, p[1] * k]).collect();
        let mut poly = convex_hull(&pts);
        if poly.is_empty() {
            poly.push([c.centroid[0] * k, c.centroid[1] * k]);
        }
        let n = poly.len() as f64;
        let centre = [
            poly.iter().map(|p| p[0]).sum::<f64>() / n,
            poly.iter().map(|p| p[1]).sum::<f64>() / n,
        ];
        // The contour lies on a possibly tilted substrate: reach below its lowest point.
        let zlo = c.contour.iter().map(|p| -p[2] * k).fold(base, f64::min) - 1.0;
        let trusted = c.quality.trusted && c.height.is_some();
        let top = base
            + match c.height {
                Some(h) if trusted => h.max(0.0) * k,
                _ => untrusted,
            };
        Self {
            id: c.id,
            prism: Prism {
                poly,
                zlo,
                zhi: top,
            },
            centre,
            base,
            top,
            trusted,
            doubt: if trusted {
                None
            } else {
                Some(
                    c.quality
                        .doubt
                        .clone()
                        .unwrap_or_else(|| "the cell has no height".into()),
                )
            },
        }
    }
}

impl Scene {
    /// The scene of one frame's targets; cells without a trusted height stand `untrusted`
    /// µm high.
    pub fn from_targets(t: &Targets, untrusted: f64) -> Result<Self, String> {
        let k = um_per_unit(&t.unit)?;
        let cells: Vec<Obstacle> = t
            .cells
            .iter()
            .filter(|c| c.substrate_z.is_finite())
            .map(|c| Obstacle::from_cell(c, k, untrusted))
            .collect();
        Ok(Self::new(t.frame, cells))
    }

    /// A scene of these cells, with the substrate fitted to the bases of the trusted ones
    /// (of all when none is). An untrusted cell's own base may be wrong too: it stands on
    /// the higher of its base and the fitted substrate.
    pub fn new(frame: u64, mut cells: Vec<Obstacle>) -> Self {
        let trusted = cells.iter().any(|c| c.trusted);
        let pts: Vec<P3> = cells
            .iter()
            .filter(|c| c.trusted || !trusted)
            .map(|c| [c.centre[0], c.centre[1], c.base])
            .collect();
        let substrate = fit_plane(&pts);
        if let (true, Some([a, b, c0])) = (trusted, substrate) {
            for c in cells.iter_mut().filter(|c| !c.trusted) {
                let lift = (a * c.centre[0] + b * c.centre[1] + c0 - c.base).max(0.0);
                c.top += lift;
                c.prism.zhi = c.top;
            }
        }
        Self {
            frame,
            substrate,
            cells,
        }
    }

    /// Height of the substrate at `(x, y)` (none without cells).
    pub fn substrate_at(&self, x: f64, y: f64) -> Option<f64> {
        self.substrate.map(|[a, b, c]| a * x + b * y + c)
    }

    /// The highest cell top (none without cells).
    pub fn max_top(&self) -> Option<f64> {
        self.cells.iter().map(|c| c.top).reduce(f64::max)
    }

    /// The cell with this id.
    pub fn cell(&self, id: u32) -> Option<&Obstacle> {
        self.cells.iter().find(|c| c.id == id)
    }

    /// The cell whose footprint centre is nearest `(x, y)`, within `radius`.
    pub fn nearest(&self, xy: [f64; 2], radius: f64) -> Option<&Obstacle> {
        self.cells
            .iter()
            .map(|c| (c, (c.centre[0] - xy[0]).hypot(c.centre[1] - xy[1])))
            .filter(|(_, d)| *d <= radius)
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(c, _)| c)
    }

    /// Cells within `margin` of the body `tip + s·u` (`s ∈ [0, len]`) at any of `tips`:
    /// where the pipette itself was segmented as an object, or a cell it touches.
    pub fn touching(&self, tips: &[P3], u: P3, len: f64, margin: f64) -> Vec<u32> {
        self.cells
            .iter()
            .filter(|c| {
                tips.iter()
                    .any(|&t| c.prism.dist_segment(t, u, len) < margin)
            })
            .map(|c| c.id)
            .collect()
    }
}

/// Least-squares plane `z = a·x + b·y + c` through `pts` (a level plane at their mean
/// height when fewer than three or when they are collinear).
pub fn fit_plane(pts: &[P3]) -> Option<[f64; 3]> {
    if pts.is_empty() {
        return None;
    }
    let n = pts.len() as f64;
    let mean = |k: usize| pts.iter().map(|p| p[k]).sum::<f64>() / n;
    let (mx, my, mz) = (mean(0), mean(1), mean(2));
    let level = Some([0.0, 0.0, mz]);
    if pts.len() < 3 {
        return level;
    }
    let (mut sxx, mut sxy, mut syy, mut sxz, mut syz) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for p in pts {
        let (x, y, z) = (p[0] - mx, p[1] - my, p[2] - mz);
        sxx += x * x;
        sxy += x * y;
        syy += y * y;
        sxz += x * z;
        syz += y * z;
    }
    let det = sxx * syy - sxy * sxy;
    if det.abs() < 1e-9 * (sxx * syy).max(1e-12) {
        return level;
    }
    let a = (sxz * syy - syz * sxy) / det;
    let b = (syz * sxx - sxz * sxy) / det;
    Some([a, b, mz - a * mx - b * my])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cell(id: u32, x: f64, y: f64, r: f64, substrate_z: f64, height: f64) -> Cell3 {
        let contour = (0..16)
            .map(|k| {
                let a = k as f64 * std::f64::consts::TAU / 16.0;
                [x + r * a.cos(), y + r * a.sin(), substrate_z]
            })
            .collect();
        Cell3 {
            id,
            right_id: id,
            area_px: 1,
            centroid_px: [0.0, 0.0],
            disparity: 0.0,
            centroid: [x, y, substrate_z - height / 2.0],
            substrate_z,
            height: Some(height),
            volume: 0.0,
            contour,
            valid_share: 1.0,
            quality: schemas::CellQuality {
                trusted: true,
                ..Default::default()
            },
        }
    }

    #[test]
    fn targets_become_prisms_in_micrometres_with_height_up() {
        let t = Targets {
            frame: 3,
            capture_ns: 0,
            unit: "mm".into(),
            cells: vec![
                cell(1, 0.0, 0.0, 0.01, 4.0, 0.012),
                cell(2, 0.1, 0.0, 0.01, 4.0, 0.02),
                cell(3, 0.0, 0.1, 0.01, 4.0, 0.02),
            ],
            substrate: None,
        };
        let s = Scene::from_targets(&t, 100.0).unwrap();
        assert_eq!(s.frame, 3);
        let c = s.cell(1).unwrap();
        assert!((c.base + 4000.0).abs() < 1e-9);
        assert!((c.top - (-4000.0 + 12.0)).abs() < 1e-9);
        assert!(c.prism.zlo < c.base);
        assert!(c.centre[0].abs() < 1e-9 && c.centre[1].abs() < 1e-9);
        assert_eq!(c.prism.poly.len(), 16);
        // On the rim of the 10 µm footprint, 5 µm above the top: 5 µm away.
        assert!((c.prism.dist_point([0.0, 0.0, -4000.0 + 17.0]) - 5.0).abs() < 1e-9);
        let [a, b, z] = s.substrate.unwrap();
        assert!(a.abs() < 1e-12 && b.abs() < 1e-12 && (z + 4000.0).abs() < 1e-9);
        assert_eq!(s.nearest([95.0, 0.0], 10.0).map(|c| c.id), Some(2));
        assert_eq!(s.nearest([50.0, 50.0], 10.0), None);
        assert!(
            Scene::from_targets(
                &Targets {
                    unit: "ft".into(),
                    ..t
                },
                100.0
            )
            .is_err()
        );
    }

    #[test]
    fn a_tilted_substrate_is_fitted() {
        let pts: Vec<P3> = [[0.0, 0.0], [100.0, 0.0], [0.0, 100.0], [100.0, 100.0]]
            .iter()
            .map(|p| [p[0], p[1], 0.01 * p[0] - 0.02 * p[1] + 5.0])
            .collect();
        let [a, b, c] = fit_plane(&pts).unwrap();
        assert!((a - 0.01).abs() < 1e-12 && (b + 0.02).abs() < 1e-12 && (c - 5.0).abs() < 1e-9);
        assert_eq!(
            fit_plane(&pts[..2]),
            Some([0.0, 0.0, (pts[0][2] + pts[1][2]) / 2.0])
        );
    }
}
