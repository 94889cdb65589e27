//! Cells end to end: segmentation outputs, and (for `reconstruct --cells`) pairing the
//! cells of both views, matching inside them only and measuring each in 3D.

use crate::io::{self, IoError};
use crate::render;
use schemas::{Cell, Mask, Plane};
use segment::{SegmentParams, Segmentation};
use serde::Serialize;
use std::path::Path;

/// How a segmentation compares with a ground-truth mask.
#[derive(Clone, Copy, Debug, Serialize, PartialEq)]
pub struct TruthScore {
    /// Foreground Dice overlap.
    pub dice: f64,
    /// 8-connected components of the truth mask.
    pub truth_cells: u32,
    /// Cells found.
    pub found_cells: usize,
    /// `found / truth − 1`.
    pub count_error: f64,
}

/// Scores a segmentation mask against a truth mask (non-zero = cell) of the same size.
pub fn score(mask: &Mask, truth: &Mask, found: usize) -> TruthScore {
    let (_, n) = segment::label(truth, segment::Connectivity::Eight);
    TruthScore {
        dice: segment::dice(mask, truth),
        truth_cells: n,
        found_cells: found,
        count_error: if n == 0 {
            if found == 0 { 0.0 } else { f64::INFINITY }
        } else {
            found as f64 / n as f64 - 1.0
        },
    }
}

/// What `segment` writes to cells.json.
#[derive(Serialize)]
struct SegmentReport<'a> {
    image: String,
    width: usize,
    height: usize,
    params: &'a SegmentParams,
    /// Largest local standard deviation (or variance), grey levels: 255 on variance.png.
    variance_max: f32,
    otsu_threshold: Option<u8>,
    threshold: u16,
    histogram: Vec<u64>,
    truth: Option<TruthScore>,
    cells: &'a [Cell],
}

/// Writes labels.png, overlay.png, variance.png, histogram.png and cells.json into `dir`.
pub fn write_segmentation(
    dir: &Path,
    image: &Path,
    rgb: &Plane<[u8; 3]>,
    seg: &Segmentation,
    params: &SegmentParams,
    truth: Option<TruthScore>,
) -> Result<(), IoError> {
    let werr = |p: &Path, e: &dyn std::fmt::Display| IoError::Write {
        path: p.into(),
        reason: e.to_string(),
    };
    std::fs::create_dir_all(dir).map_err(|e| werr(dir, &e))?;
    render::write_labels_png(&dir.join("labels.png"), &seg.labels)?;
    let ov = dir.join("overlay.png");
    render::overlay(rgb, &seg.cells)
        .save(&ov)
        .map_err(|e| werr(&ov, &e))?;
    io::write_mask_png(&dir.join("variance.png"), &seg.variance)?;
    let hp = dir.join("histogram.png");
    render::histogram_chart(&seg.histogram, Some(seg.threshold))
        .save(&hp)
        .map_err(|e| werr(&hp, &e))?;
    let report = SegmentReport {
        image: image.display().to_string(),
        width: rgb.width,
        height: rgb.height,
        params,
        variance_max: seg.variance_max,
        otsu_threshold: seg.otsu,
        threshold: seg.threshold,
        histogram: seg.histogram.to_vec(),
        truth,
        cells: &seg.cells,
    };
    let jp = dir.join("cells.json");
    let json = serde_json::to_string_pretty(&report).expect("serialises");
    std::fs::write(&jp, json + "\n").map_err(|e| werr(&jp, &e))
}

use crate::pipeline::{self, StereoConfig, Workspace};
use matcher::{DisparityPlane, InputError, PeakFit};
use runtime::StageTimes;
use schemas::{Calibration, Cell3, DisparityMap, DisparityRange, INVALID_DISPARITY};

/// Pairs each left cell with a right cell: rows overlap by half the smaller height, areas
/// within a factor of two, the centroid offset `xl − xr` inside the disparity range (±
/// `slack` px for segmentation jitter). Best pairs first (smallest size and row mismatch);
/// each cell is used once. Returns `(left index, right index)` in left order.
pub fn pair_cells(
    left: &[Cell],
    right: &[Cell],
    range: DisparityRange,
    slack: f64,
) -> Vec<(usize, usize)> {
    let mut cand = Vec::new();
    for (i, l) in left.iter().enumerate() {
        for (j, r) in right.iter().enumerate() {
            let overlap = l.bbox.y1.min(r.bbox.y1) as i64 - l.bbox.y0.max(r.bbox.y0) as i64 + 1;
            let hmin = (l.bbox.y1 - l.bbox.y0).min(r.bbox.y1 - r.bbox.y0) as i64 + 1;
            let ratio = l.area as f64 / r.area.max(1) as f64;
            let dx = l.centroid[0] - r.centroid[0];
            if 2 * overlap < hmin
                || !(0.5..=2.0).contains(&ratio)
                || dx < range.min as f64 - slack
                || dx > range.max as f64 + slack
            {
                continue;
            }
            let cost = (l.centroid[1] - r.centroid[1]).abs() + 20.0 * ratio.ln().abs();
            cand.push((cost, i, j));
        }
    }
    cand.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (mut used_l, mut used_r) = (vec![false; left.len()], vec![false; right.len()]);
    let mut pairs = Vec::new();
    for (_, i, j) in cand {
        if !used_l[i] && !used_r[j] {
            used_l[i] = true;
            used_r[j] = true;
            pairs.push((i, j));
        }
    }
    pairs.sort();
    pairs
}

/// Settings of cell-only stereo.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct CellStereoParams {
    /// Pixels around each cell mask that are matched too (the substrate ring).
    pub margin: u8,
}

impl Default for CellStereoParams {
    fn default() -> Self {
        Self { margin: 8 }
    }
}

/// Everything cell-only stereo produces.
#[derive(Clone, Debug)]
pub struct CellStereo {
    /// Left segmentation.
    pub left_seg: Segmentation,
    /// Right segmentation.
    pub right_seg: Segmentation,
    /// `(left cell index, right cell index)`.
    pub pairs: Vec<(usize, usize)>,
    /// Final left disparity: valid only inside the matched (dilated) cell masks.
    pub disparity: DisparityMap,
    /// After the LR check, before post-processing, same support.
    pub disparity_raw: DisparityMap,
    /// 255 where the LR check failed inside the matched regions.
    pub occlusion_left: Mask,
    /// Left pixels given to the matcher (the crops), summed over cells.
    pub matched_pixels: u64,
    /// The substrate's disparity plane fitted to the background around all cells (`None`
    /// when the background is too textureless to fix it; the rings then decide).
    pub substrate: Option<DisparityPlane>,
    /// Per pair: the substrate's disparity under the cell (the plane at its centroid, or
    /// the median on its ring when there is no plane).
    pub bases: Vec<Option<f64>>,
    /// Per pair: the cell's top refined by a photometric dome fit.
    pub tops: Vec<Option<PeakFit>>,
    /// Milliseconds per stage.
    pub times: StageTimes,
}

fn crop<T: Copy>(p: &Plane<T>, x0: usize, y0: usize, x1: usize, y1: usize) -> Plane<T> {
    let data = (y0..y1)
        .flat_map(|y| p.row(y)[x0..x1].iter().copied())
        .collect();
    Plane::from_vec(x1 - x0, y1 - y0, data).expect("size")
}

/// Segments both views, pairs the cells and runs the stereo pipeline on each pair's crop;
/// only pixels inside a left cell mask dilated by `margin` keep a disparity.
pub fn cell_stereo(
    left: &Plane<u8>,
    right: &Plane<u8>,
    cfg: &StereoConfig,
    seg: &SegmentParams,
    p: &CellStereoParams,
) -> Result<CellStereo, InputError> {
    matcher::check_inputs(left, right, cfg.range, cfg.window())?;
    let mut times = StageTimes::default();
    let (ls, rs) = times.time("segment", || {
        rayon::join(
            || segment::segment(left, seg),
            || segment::segment(right, seg),
        )
    });
    let pairs = pair_cells(&ls.cells, &rs.cells, cfg.range, 4.0);
    let (w, h) = (left.width, left.height);
    let mut disparity = Plane::filled(w, h, INVALID_DISPARITY);
    let mut disparity_raw = Plane::filled(w, h, INVALID_DISPARITY);
    let mut occlusion_left = Plane::filled(w, h, 0u8);
    let mut matched_pixels = 0u64;
    let m = p.margin as i64;
    let (dmin, dmax) = (cfg.range.min as i64, cfg.range.max as i64);
    let support = segment::dilate(&ls.mask, p.margin);
    let mut ws = Workspace::default();
    for &(i, j) in &pairs {
        let (lb, rb) = (ls.cells[i].bbox, rs.cells[j].bbox);
        let y0 = (lb.y0.min(rb.y0) as i64 - m).max(0) as usize;
        let y1 = ((lb.y1.max(rb.y1) as i64 + m + 1) as usize).min(h);
        let c0 = (lb.x0 as i64 - m - dmax)
            .min(rb.x0 as i64 - m + dmin)
            .max(0) as usize;
        let c1 =
            ((lb.x1 as i64 + m - dmin).max(rb.x1 as i64 + m + dmax) + 1).min(w as i64) as usize;
        let (cl, cr) = (crop(left, c0, y0, c1, y1), crop(right, c0, y0, c1, y1));
        let mut c = cfg.clone();
        // A narrow crop cannot hold the whole range: search what fits.
        let cw = (c1 - c0) as i32;
        c.range = DisparityRange::new(cfg.range.min.max(-(cw - 1)), cfg.range.max.min(cw - 1));
        if c.range.min >= c.range.max
            || matcher::check_inputs(&cl, &cr, c.range, c.window()).is_err()
        {
            continue;
        }
        matched_pixels += cl.len() as u64;
        let out = pipeline::run_stereo_in(&mut ws, &cl, &cr, &c)?;
        for (n, ms) in &out.times.stages {
            times.add(n, *ms);
        }
        let id = ls.cells[i].id;
        let dist = distance_to_cell(&ls.labels, id, (c0, y0), (c1, y1));
        for y in y0..y1 {
            for x in c0..c1 {
                // Own cell plus the ring around it (other cells get their own crop).
                let own = *ls.labels.get(x, y) == id
                    || (*ls.labels.get(x, y) == 0
                        && *support.get(x, y) != 0
                        && dist.get_pixel((x - c0) as u32, (y - y0) as u32).0[0] <= p.margin);
                if !own {
                    continue;
                }
                *disparity.get_mut(x, y) = *out.disparity.get(x - c0, y - y0);
                *disparity_raw.get_mut(x, y) = *out.checked.left.get(x - c0, y - y0);
                *occlusion_left.get_mut(x, y) = *out.checked.occlusion_left.get(x - c0, y - y0);
            }
        }
    }
    let (substrate, bases, tops) = cell_heights(
        (left, right),
        (&ls.labels, &ls.mask, &rs.mask),
        &ls.cells,
        &pairs,
        (&disparity, &disparity_raw),
        cfg.range,
        p.margin,
        &mut times,
    );
    Ok(CellStereo {
        left_seg: ls,
        right_seg: rs,
        pairs,
        disparity,
        disparity_raw,
        occlusion_left,
        matched_pixels,
        substrate,
        bases,
        tops,
        times,
    })
}

/// The substrate's disparity plane over the background clear of every cell (in both views'
/// masks), and per pair the substrate's disparity under the left cell (the plane, or the
/// ring median without one) and its refined top.
#[allow(clippy::too_many_arguments)]
pub fn cell_heights(
    (left, right): (&Plane<u8>, &Plane<u8>),
    (labels, left_mask, right_mask): (&Plane<u32>, &Mask, &Mask),
    cells: &[Cell],
    pairs: &[(usize, usize)],
    (disparity, disparity_raw): (&DisparityMap, &DisparityMap),
    range: DisparityRange,
    margin: u8,
    times: &mut StageTimes,
) -> (
    Option<DisparityPlane>,
    Vec<Option<f64>>,
    Vec<Option<PeakFit>>,
) {
    let substrate = times.time("substrate", || {
        let reach =
            margin as usize + range.min.unsigned_abs().max(range.max.unsigned_abs()) as usize;
        let mut both = left_mask.clone();
        for (c, r) in both.data.iter_mut().zip(&right_mask.data) {
            *c |= *r;
        }
        let usable = clear_of(&both, reach);
        matcher::fit_disparity_plane(left, right, &usable, range, SUBSTRATE_MAX_STD)
    });
    let (mut bases, mut tops) = (Vec::new(), Vec::new());
    for &(i, _) in pairs {
        let cell = &cells[i];
        let base = match &substrate {
            Some(s) => Some(s.at(cell.centroid[0], cell.centroid[1])),
            None => ring_disparity(labels, cell, disparity_raw, disparity, margin),
        };
        bases.push(base);
        tops.push(base.and_then(|base| {
            times.time("refine", || {
                top_of_cell(left, right, labels, cell, disparity, base)
            })
        }));
    }
    (substrate, bases, tops)
}

/// 255 where no non-zero pixel of `mask` lies within the `(2r+1)²` square around.
fn clear_of(mask: &Mask, r: usize) -> Mask {
    let (w, h) = (mask.width, mask.height);
    let sums = segment::BoxSums::new(w, h, |x, y| u64::from(*mask.get(x, y) != 0));
    let data = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| if sums.around(x, y, r).0 == 0 { 255 } else { 0 })
        .collect();
    Plane::from_vec(w, h, data).expect("size")
}

/// The largest formal error (px) a background plane may have to stand for the substrate.
const SUBSTRATE_MAX_STD: f64 = 0.05;

/// Refines the top of cell `cell` with the dome model over its upper part: the pixels whose
/// matched height above `base` (the substrate's disparity) is at least 70 % of the cell's
/// (its 98th percentile). Lower down, flanks steepen and the matcher's map is least sure.
fn top_of_cell(
    left: &Plane<u8>,
    right: &Plane<u8>,
    labels: &Plane<u32>,
    cell: &Cell,
    disparity: &DisparityMap,
    base: f64,
) -> Option<PeakFit> {
    let b = cell.bbox;
    let mut inside = Vec::new();
    for y in b.y0 as usize..=b.y1 as usize {
        for x in b.x0 as usize..=b.x1 as usize {
            let d = *disparity.get(x, y);
            if *labels.get(x, y) == cell.id && d.is_finite() {
                inside.push(([x, y], d));
            }
        }
    }
    let top = percentile(inside.iter().map(|p| p.1).collect(), 0.98)?;
    if top <= base {
        return None;
    }
    let level = (base + 0.7 * (top - base)) as f32;
    let (pixels, init): (Vec<[usize; 2]>, Vec<f32>) =
        inside.into_iter().filter(|(_, d)| *d >= level).unzip();
    matcher::refine_peak(left, right, &pixels, &init, Some(base))
}

/// Chebyshev distance (px, capped at 255) from each pixel of the window `[x0, x1) × [y0, y1)`
/// to the nearest pixel of cell `id`, which must lie wholly inside the window.
fn distance_to_cell(
    labels: &Plane<u32>,
    id: u32,
    (x0, y0): (usize, usize),
    (x1, y1): (usize, usize),
) -> image::GrayImage {
    let cell = image::GrayImage::from_fn((x1 - x0) as u32, (y1 - y0) as u32, |x, y| {
        image::Luma([u8::from(
            *labels.get(x0 + x as usize, y0 + y as usize) == id,
        )])
    });
    imageproc::distance_transform::distance_transform(
        &cell,
        imageproc::distance_transform::Norm::LInf,
    )
}

/// Median disparity on the ring of cell `cell` (2 px off its segmented edge, which the
/// variance window blurs, out to `margin`): after the LR check where that has values,
/// otherwise after post-processing.
fn ring_disparity(
    labels: &Plane<u32>,
    cell: &Cell,
    raw: &DisparityMap,
    filled: &DisparityMap,
    margin: u8,
) -> Option<f64> {
    let (b, m) = (cell.bbox, margin as usize);
    let (x0, y0) = (
        (b.x0 as usize).saturating_sub(m),
        (b.y0 as usize).saturating_sub(m),
    );
    let x1 = (b.x1 as usize + m + 1).min(labels.width);
    let y1 = (b.y1 as usize + m + 1).min(labels.height);
    let dist = distance_to_cell(labels, cell.id, (x0, y0), (x1, y1));
    let (mut ring, mut ring_filled) = (Vec::new(), Vec::new());
    for y in y0..y1 {
        for x in x0..x1 {
            let d = *filled.get(x, y);
            let off = dist.get_pixel((x - x0) as u32, (y - y0) as u32).0[0];
            if *labels.get(x, y) == 0 && d.is_finite() && off > 2 && off <= margin {
                let r = *raw.get(x, y);
                if r.is_finite() {
                    ring.push(r);
                }
                ring_filled.push(d);
            }
        }
    }
    percentile(ring, 0.5).or_else(|| percentile(ring_filled, 0.5))
}

fn percentile(mut v: Vec<f32>, q: f64) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    let k = ((v.len() - 1) as f64 * q).round() as usize;
    Some(v[k] as f64)
}

/// Per-cell 3D figures of paired cells (see [`Cell3`]).
pub fn measure_cells(cs: &CellStereo, calib: &Calibration) -> Vec<Cell3> {
    measure(
        (&cs.left_seg.labels, &cs.left_seg.cells, &cs.right_seg.cells),
        &cs.pairs,
        (&cs.disparity, &cs.disparity_raw),
        (&cs.bases, &cs.tops),
        calib,
    )
}

/// Per-cell 3D figures from the left labels and cells, the right cells, their pairing, the
/// final and LR-checked disparity maps and [`cell_heights`]' bases and tops.
pub fn measure(
    (labels, left_cells, right_cells): (&Plane<u32>, &[Cell], &[Cell]),
    pairs: &[(usize, usize)],
    (disparity, disparity_raw): (&DisparityMap, &DisparityMap),
    (bases, tops): (&[Option<f64>], &[Option<PeakFit>]),
    calib: &Calibration,
) -> Vec<Cell3> {
    let z_of = |d: f64| calib.baseline * calib.focal_px / (d + calib.cx_right - calib.cx);
    let mut out = Vec::new();
    for (k, &(i, j)) in pairs.iter().enumerate() {
        let cell = &left_cells[i];
        let b = cell.bbox;
        let mut inside = Vec::new();
        let mut valid_raw = 0u64;
        for y in b.y0 as usize..=b.y1 as usize {
            for x in b.x0 as usize..=b.x1 as usize {
                if *labels.get(x, y) == cell.id {
                    valid_raw += disparity_raw.get(x, y).is_finite() as u64;
                    let d = *disparity.get(x, y);
                    if d.is_finite() {
                        inside.push((x, y, d));
                    }
                }
            }
        }
        let Some(d_sub) = bases[k] else { continue };
        let Some(d_top) = tops[k]
            .map(|t| t.peak)
            .or_else(|| percentile(inside.iter().map(|p| p.2).collect(), 0.98))
        else {
            continue;
        };
        let z_sub = z_of(d_sub);
        let pixel_area = (z_sub / calib.focal_px).powi(2);
        let xy = |x: usize, y: usize| {
            let d = *disparity.get(x, y) as f64;
            triangulate::triangulate_pixel(x as f64, y as f64, d, calib).map(|p| [p[0], p[1]])
        };
        let (mut vol, mut wx, mut wy, mut wz) = (0.0, 0.0, 0.0, 0.0);
        for &(x, y, d) in &inside {
            let z = z_of(d as f64);
            let hgt = (z_sub - z).max(0.0);
            // The ground each pixel covers: one camera sees a slope facing it with more
            // pixels than the slope facing away, so equal weights would pull the centroid
            // towards that camera (by up to 2 µm on a 100 µm dome).
            let inner = x + 1 < disparity.width && y + 1 < disparity.height;
            let next = |dx: usize, dy: usize| if inner { xy(x + dx, y + dy) } else { None };
            let footprint = match (xy(x, y), next(1, 0), next(0, 1)) {
                (Some(p), Some(px), Some(py)) => {
                    let a =
                        ((px[0] - p[0]) * (py[1] - p[1]) - (py[0] - p[0]) * (px[1] - p[1])).abs();
                    a.clamp(0.25 * pixel_area, 4.0 * pixel_area)
                }
                _ => pixel_area,
            };
            let v = hgt * footprint;
            if let Some([px, py, _]) =
                triangulate::triangulate_pixel(x as f64, y as f64, d as f64, calib)
            {
                vol += v;
                wx += v * px;
                wy += v * py;
                wz += v * (z_sub - 0.5 * hgt);
            }
        }
        let centroid = if vol > 0.0 {
            [wx / vol, wy / vol, wz / vol]
        } else {
            triangulate::triangulate_pixel(cell.centroid[0], cell.centroid[1], d_sub, calib)
                .unwrap_or([f64::NAN; 3])
        };
        let contour = cell
            .contour
            .iter()
            .filter_map(|c| triangulate::triangulate_pixel(c[0] as f64, c[1] as f64, d_sub, calib))
            .collect();
        out.push(Cell3 {
            id: cell.id,
            right_id: right_cells[j].id,
            area_px: cell.area,
            centroid_px: cell.centroid,
            disparity: d_top,
            centroid,
            substrate_z: z_sub,
            height: z_sub - z_of(d_top),
            volume: vol,
            contour,
            valid_share: valid_raw as f64 / cell.area.max(1) as f64,
        });
    }
    out
}
