//! The substrate under each cell, from every source the images carry, cross-checked.
//!
//! Two kinds of evidence fix the substrate's disparity:
//! - the **background plane** ([`fit_disparity_plane`]): the whole background clear of the
//!   cells, matched photometrically. It holds on a textured substrate and is refused on a
//!   textureless one (the matching cost is flat there);
//! - each cell's **rim** ([`rim_disparity`]): the band just outside the cell's outline, where
//!   the membrane meets the substrate. The contact line and the cell's edge are the texture
//!   a brightfield image has even when the substrate has none.
//!
//! With a background plane, each cell's rim checks it; without one, the rims of all cells
//! fit a plane of their own (the substrate may be tilted) and each rim is checked against
//! the plane of the others. When most rims lie on one plane and most of them off the
//! background's, the rims outvote the background plane and it is set aside. A cell whose
//! sources disagree, or whose substrate rests on one
//! unchecked source, is flagged: its height is not to be trusted.

use crate::refine::{huber, robust_scale, sample, weighted_plane};
use schemas::{Cell, DisparityPlane, DisparityRange, Plane, SubstrateSource};

/// The substrate's disparity at a cell's rim, fitted photometrically.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RimFit {
    /// Disparity, px.
    pub d: f64,
    /// Its standard error (px), inflated for the correlation of neighbouring residuals.
    pub std: f64,
    /// Normalised cross-correlation of the band at the fitted whole disparity.
    pub ncc: f64,
    /// Band pixels used.
    pub pixels: usize,
}

/// Width (px) of the band outside a cell's outline that its rim fit uses.
pub const RIM_BAND: u8 = 4;

/// Width (px) of the band inside the outline that the rim fit uses too: the segmented edge
/// may fall a pixel outside the contact line, and further in the cell rises off the
/// substrate (a 2–3 px band biases the rim up by 0.1–0.5 px on steep cells).
const RIM_INSIDE: u8 = 1;

/// Fewest band pixels a rim is fitted on.
const RIM_MIN_PIXELS: usize = 40;

/// Least normalised cross-correlation of a rim band for its disparity to count.
const RIM_MIN_NCC: f64 = 0.6;

/// Factor from the formal to the real standard error: the band's residuals correlate over
/// about the edge's width.
const CORRELATION: f64 = 2.0;

/// The pixels of the band around cell `cell`'s outline: background at Chebyshev distance
/// 1..=[`RIM_BAND`] from it and the cell's own outermost [`RIM_INSIDE`] px.
fn rim_band(labels: &Plane<u32>, cell: &Cell) -> Vec<[usize; 2]> {
    let b = cell.bbox;
    let m = RIM_BAND as usize;
    let (x0, y0) = (
        (b.x0 as usize).saturating_sub(m),
        (b.y0 as usize).saturating_sub(m),
    );
    let x1 = (b.x1 as usize + m + 1).min(labels.width);
    let y1 = (b.y1 as usize + m + 1).min(labels.height);
    let dist = cells::distance_to_cell(labels, cell.id, (x0, y0), (x1, y1));
    let inside = {
        let outside = image::GrayImage::from_fn((x1 - x0) as u32, (y1 - y0) as u32, |x, y| {
            image::Luma([u8::from(
                *labels.get(x0 + x as usize, y0 + y as usize) != cell.id,
            )])
        });
        imageproc::distance_transform::distance_transform(
            &outside,
            imageproc::distance_transform::Norm::LInf,
        )
    };
    let mut band = Vec::new();
    for y in y0..y1 {
        for x in x0..x1 {
            let off = dist.get_pixel((x - x0) as u32, (y - y0) as u32).0[0];
            let inn = inside.get_pixel((x - x0) as u32, (y - y0) as u32).0[0];
            let l = *labels.get(x, y);
            if (l == 0 && (1..=RIM_BAND).contains(&off)) || (l == cell.id && inn <= RIM_INSIDE) {
                band.push([x, y]);
            }
        }
    }
    band
}

/// The disparity of the band just outside `cell`'s outline in the left view: the whole
/// disparity in `range` of the band's best normalised cross-correlation with the right view,
/// refined with a gain and offset by robust Gauss–Newton. `None` when the band is too small
/// or too weak to single out a disparity.
pub fn rim_disparity(
    left: &Plane<u8>,
    right: &Plane<u8>,
    labels: &Plane<u32>,
    cell: &Cell,
    range: DisparityRange,
) -> Option<RimFit> {
    let band = rim_band(labels, cell);
    if band.len() < RIM_MIN_PIXELS {
        return None;
    }
    let w = left.width as i64;
    let ncc_at = |d: i32| -> Option<f64> {
        let (mut n, mut sl, mut sr, mut sll, mut srr, mut slr) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        for &[x, y] in &band {
            let xr = x as i64 - d as i64;
            if xr < 0 || xr >= w {
                continue;
            }
            let (a, b) = (*left.get(x, y) as f64, *right.get(xr as usize, y) as f64);
            n += 1.0;
            sl += a;
            sr += b;
            sll += a * a;
            srr += b * b;
            slr += a * b;
        }
        if n < RIM_MIN_PIXELS as f64 {
            return None;
        }
        let vl = sll - sl * sl / n;
        let vr = srr - sr * sr / n;
        (vl > 1e-9 && vr > 1e-9).then(|| (slr - sl * sr / n) / (vl * vr).sqrt())
    };
    let (best, ncc) = (range.min..=range.max)
        .filter_map(|d| ncc_at(d).map(|c| (d, c)))
        .max_by(|a, b| a.1.total_cmp(&b.1))?;
    if ncc < RIM_MIN_NCC {
        return None;
    }
    // d, gain, offset.
    let mut p = [best as f64, 1.0, 0.0];
    let terms = |p: &[f64; 3]| -> Vec<(f64, [f64; 3])> {
        band.iter()
            .filter_map(|&[x, y]| {
                let (rv, rg) = sample(right.row(y), x as f64 - p[0])?;
                let e = *left.get(x, y) as f64 - (p[1] * rv + p[2]);
                Some((e, [p[1] * rg, -rv, -1.0]))
            })
            .collect()
    };
    let mut info = nalgebra::Matrix3::zeros();
    let mut scale = 1.0;
    for _ in 0..30 {
        let t = terms(&p);
        if t.len() < RIM_MIN_PIXELS {
            return None;
        }
        scale = robust_scale(t.iter().map(|t| t.0).collect()).max(0.5);
        let k = 1.5 * scale;
        let (mut a, mut g) = (nalgebra::Matrix3::zeros(), nalgebra::Vector3::zeros());
        for (e, j) in &t {
            let wt = huber(*e, k);
            let j = nalgebra::Vector3::from_column_slice(j);
            a += wt * j * j.transpose();
            g += wt * j * *e;
        }
        info = a;
        let step = a.lu().solve(&(-g))?;
        // A rim moves by a fraction of a pixel from its whole start; more is a lost fit.
        p[0] += step[0].clamp(-0.5, 0.5);
        p[1] += step[1];
        p[2] += step[2];
        if (p[0] - best as f64).abs() > 1.5 {
            return None;
        }
        if step[0].abs() < 1e-4 {
            break;
        }
    }
    let cov = info.try_inverse()?;
    let std = CORRELATION * scale * cov[(0, 0)].max(0.0).sqrt();
    std.is_finite().then_some(RimFit {
        d: p[0],
        std,
        ncc,
        pixels: band.len(),
    })
}

/// The substrate under one cell, where it came from and how sure it is.
#[derive(Clone, Debug, PartialEq)]
pub struct Base {
    /// Disparity of the substrate under the cell's centroid, px.
    pub d: f64,
    /// Its standard error, px.
    pub std: f64,
    /// Which evidence gave it.
    pub source: SubstrateSource,
    /// Why it is not to be trusted; `None` when its sources agree.
    pub doubt: Option<String>,
}

/// Least disagreement (px) between two sources that counts as a disagreement: what a
/// rim's residual bias from the cell's own edge leaves.
const AGREE_PX: f64 = 0.3;

/// How many standard errors two sources may differ by.
const AGREE_SIGMAS: f64 = 3.0;

/// Least standard error (px) a background plane is credited with at one cell: its formal
/// error covers noise, not the substrate's own unevenness.
const PLANE_FLOOR_STD: f64 = 0.05;

/// Whether two estimates (value, std) agree, and by how much they differ.
fn agree(a: (f64, f64), b: (f64, f64)) -> (bool, f64) {
    let diff = (a.0 - b.0).abs();
    (diff <= AGREE_PX.max(AGREE_SIGMAS * a.1.hypot(b.1)), diff)
}

/// A plane through `points` (`[x, y, d, std]`) by weighted least squares, then again
/// without those more than [`AGREE_PX`] (and 3σ) off: `None` with fewer than three points
/// or when they are collinear.
fn plane_through(points: &[[f64; 4]]) -> Option<([f64; 3], f64)> {
    let fit = |pts: &[[f64; 4]]| -> Option<([f64; 3], f64)> {
        if pts.len() < 3 {
            return None;
        }
        let c = weighted_plane(
            pts.iter()
                .map(|p| ([p[0], p[1], p[2]], 1.0 / p[3].max(0.02).powi(2))),
        )?;
        let res: Vec<f64> = pts
            .iter()
            .map(|p| p[2] - (c[0] + c[1] * p[0] + c[2] * p[1]))
            .collect();
        Some((c, robust_scale(res)))
    };
    let (c, _) = fit(points)?;
    let kept: Vec<[f64; 4]> = points
        .iter()
        .copied()
        .filter(|p| {
            let r = p[2] - (c[0] + c[1] * p[0] + c[2] * p[1]);
            r.abs() <= AGREE_PX.max(AGREE_SIGMAS * p[3])
        })
        .collect();
    fit(&kept).or(Some((c, f64::INFINITY)))
}

/// Formal error (px) below which a background plane stands on a richly textured
/// substrate (0.001–0.002 px there) and no vote of the rims sets it aside: on texture the
/// rims share a bias of their own (0.3–0.45 px up, the cell's edge in the band).
const SURE_PLANE_STD: f64 = 0.01;

/// Largest spread (px) of the rims about their own plane for them to outvote the background
/// plane: on a textureless substrate they agree to 0.02–0.05 px.
const RIMS_TIGHT_PX: f64 = 0.1;

/// Whether the cells' rims outvote the background `plane`: a plane on little texture, at
/// least three rims, most of them tightly on one plane of their own and most of them off
/// the background plane. A wrong background plane (seen on a textureless background crowded
/// with cells: 0.5–1.5 px off, its formal error 0.044 px) is then set aside and the
/// substrate comes from the rims, each checked against the others.
fn outvoted(cells: &[&Cell], plane: &DisparityPlane, rims: &[Option<RimFit>]) -> bool {
    if plane.std < SURE_PLANE_STD {
        return false;
    }
    let points: Vec<[f64; 4]> = cells
        .iter()
        .zip(rims)
        .filter_map(|(c, r)| r.map(|r| [c.centroid[0], c.centroid[1], r.d, r.std]))
        .collect();
    if points.len() < 3 {
        return false;
    }
    let Some((own, spread)) = plane_through(&points) else {
        return false;
    };
    // Infinite when too few rims were left after the outliers; not tight then either.
    if spread.is_nan() || spread > RIMS_TIGHT_PX {
        return false;
    }
    let p_std = plane.std.max(PLANE_FLOOR_STD);
    let (mut on_own, mut on_background) = (0, 0);
    for p in &points {
        let d_own = own[0] + own[1] * p[0] + own[2] * p[1];
        on_own += usize::from(agree((p[2], p[3]), (d_own, 0.0)).0);
        on_background += usize::from(agree((p[2], p[3]), (plane.at(p[0], p[1]), p_std)).0);
    }
    let n = points.len();
    2 * on_own > n && 2 * on_background < n && on_own >= 2 * on_background.max(1)
}

/// The substrate under each of `cells` (by their centroids) from the background `plane` (if
/// the background had the texture to fix one) and each cell's `rims`, cross-checked as the
/// module says.
pub fn bases(
    cells: &[&Cell],
    plane: Option<&DisparityPlane>,
    rims: &[Option<RimFit>],
) -> Vec<Option<Base>> {
    let at = |c: &Cell| (c.centroid[0], c.centroid[1]);
    if let Some(pl) = plane.filter(|pl| !outvoted(cells, pl, rims)) {
        let p_std = pl.std.max(PLANE_FLOOR_STD);
        return cells
            .iter()
            .zip(rims)
            .map(|(c, rim)| {
                let (x, y) = at(c);
                let d = pl.at(x, y);
                let doubt = rim.and_then(|r| {
                    let (ok, diff) = agree((d, p_std), (r.d, r.std));
                    (!ok).then(|| {
                        format!(
                            "the background plane ({d:.2} px) and the cell's rim ({:.2} px) disagree by {diff:.2} px",
                            r.d
                        )
                    })
                });
                Some(Base {
                    d,
                    std: p_std,
                    source: SubstrateSource::Plane,
                    doubt,
                })
            })
            .collect();
    }
    cells
        .iter()
        .enumerate()
        .map(|(k, c)| {
            let (x, y) = at(c);
            // The plane of the other cells' rims, to check this one's against.
            let others: Vec<[f64; 4]> = cells
                .iter()
                .zip(rims)
                .enumerate()
                .filter(|(j, _)| *j != k)
                .filter_map(|(_, (o, r))| r.map(|r| [o.centroid[0], o.centroid[1], r.d, r.std]))
                .collect();
            let from_others = plane_through(&others).and_then(|(p, spread)| {
                spread.is_finite().then(|| {
                    let std = (spread / (others.len() as f64 - 2.0).max(1.0).sqrt()).max(0.05);
                    (p[0] + p[1] * x + p[2] * y, std)
                })
            });
            match (rims[k], from_others) {
                (Some(r), Some(o)) => {
                    let (ok, diff) = agree((r.d, r.std), o);
                    Some(Base {
                        d: r.d,
                        std: r.std,
                        source: SubstrateSource::Rim,
                        doubt: (!ok).then(|| {
                            format!(
                                "the cell's rim ({:.2} px) and the plane of the other cells' rims ({:.2} px) disagree by {diff:.2} px",
                                r.d, o.0
                            )
                        }),
                    })
                }
                (Some(r), None) => {
                    // Two cells: each rim checks the other's, allowing for a tilt of 2°.
                    let doubt = match others.as_slice() {
                        [o] => {
                            let reach = 0.035 * (o[0] - x).hypot(o[1] - y);
                            let diff = (o[2] - r.d).abs();
                            (diff > AGREE_PX.max(AGREE_SIGMAS * r.std.hypot(o[3])) + reach)
                                .then(|| {
                                    format!(
                                        "the cell's rim ({:.2} px) and the other cell's ({:.2} px) disagree by {diff:.2} px",
                                        r.d, o[2]
                                    )
                                })
                        }
                        _ => Some(
                            "the substrate rests on this cell's rim alone: the background has no texture and no other cell checks it"
                                .into(),
                        ),
                    };
                    Some(Base {
                        d: r.d,
                        std: r.std,
                        source: SubstrateSource::Rim,
                        doubt,
                    })
                }
                (None, Some(o)) => Some(Base {
                    d: o.0,
                    std: o.1,
                    source: SubstrateSource::Rims,
                    doubt: None,
                }),
                (None, None) => None,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use schemas::BoundingBox;

    fn cell_at(id: u32, x: f64, y: f64) -> Cell {
        Cell {
            id,
            area: 400,
            centroid: [x, y],
            bbox: BoundingBox {
                x0: x as u32 - 10,
                y0: y as u32 - 10,
                x1: x as u32 + 10,
                y1: y as u32 + 10,
            },
            contour: Vec::new(),
            perimeter: 0.0,
        }
    }

    fn rim(d: f64) -> Option<RimFit> {
        Some(RimFit {
            d,
            std: 0.02,
            ncc: 0.9,
            pixels: 200,
        })
    }

    #[test]
    fn tight_rims_outvote_a_weak_wrong_plane_but_not_a_sure_one() {
        let cells: Vec<Cell> = [(100.0, 80.0), (400.0, 90.0), (250.0, 300.0), (520.0, 400.0)]
            .iter()
            .enumerate()
            .map(|(i, &(x, y))| cell_at(i as u32 + 1, x, y))
            .collect();
        let refs: Vec<&Cell> = cells.iter().collect();
        let rims: Vec<Option<RimFit>> = [8.01, 7.99, 8.02, 8.0].map(rim).to_vec();
        let plane = |std: f64| DisparityPlane {
            d0: 7.0,
            dx: 0.001,
            dy: -0.001,
            centre: [320.0, 240.0],
            std,
            pixels: 5000,
        };
        // Formal error 0.044 px (a crowded textureless frame): the rims win, and agree.
        let weak = bases(&refs, Some(&plane(0.044)), &rims);
        for (b, r) in weak.iter().zip(&rims) {
            let b = b.as_ref().unwrap();
            assert_eq!(b.source, SubstrateSource::Rim);
            assert_eq!(b.d, r.unwrap().d);
            assert_eq!(b.doubt, None);
        }
        // A plane on rich texture stays; every cell is flagged for the disagreement.
        let sure = bases(&refs, Some(&plane(0.002)), &rims);
        for b in &sure {
            let b = b.as_ref().unwrap();
            assert_eq!(b.source, SubstrateSource::Plane);
            assert!(b.doubt.as_ref().unwrap().contains("disagree"), "{b:?}");
        }
        // Rims that scatter do not outvote even a weak plane.
        let loose: Vec<Option<RimFit>> = [8.0, 8.6, 7.5, 8.3].map(rim).to_vec();
        let kept = bases(&refs, Some(&plane(0.044)), &loose);
        assert!(
            kept.iter()
                .all(|b| b.as_ref().unwrap().source == SubstrateSource::Plane)
        );
    }
}
