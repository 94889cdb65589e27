//! Cells in 3D, the method's cell-only stereo: on the cell-only maps, fit the substrate
//! and each cell's top, and measure every cell.
//!
//! The match node cuts the crops and the triangulate node composes their maps with the
//! `cells` crate; here are the substrate, the tops and the figures ([`cell_heights`],
//! [`measure`]).

use crate::refine::{
    BandPassed, DisparityPlane, Ground, Parallax, PeakFit, PlaneTrack, TopModel, refine_nucleus,
    refine_top, slide_rows, track_disparity_plane,
};
use crate::substrate::{self, Base, RimFit};
use cells::distance_to_cell;
use rayon::prelude::*;
use schemas::{
    Calibration, Cell, Cell3, CellQuality, DisparityMap, DisparityRange, Mask, Plane,
    SubstrateSource,
};

/// The substrate's disparity plane over the background clear of every cell (in both views'
/// masks) when the background has the texture to fix one, and per pair the substrate under
/// the left cell ([`substrate::bases`]: the plane or the rims, cross-checked; the ring
/// median, doubted, without either) and its refined top. `prior`: the plane tracked up to
/// the last frame, where one is ([`track_disparity_plane`]); the plane comes back as the
/// track to pass with the next frame.
/// `views`: the pair band-passed for the plane ([`BandPassed::of`]).
#[allow(clippy::too_many_arguments)]
pub fn cell_heights(
    (left, right): (&Plane<u8>, &Plane<u8>),
    (labels, left_mask, right_mask): (&Plane<u32>, &Mask, &Mask),
    cells: &[Cell],
    pairs: &[(usize, usize)],
    (disparity, disparity_raw): (&DisparityMap, &DisparityMap),
    range: DisparityRange,
    margin: u8,
    calib: &Calibration,
    prior: Option<&PlaneTrack>,
    views: &BandPassed,
) -> (Option<PlaneTrack>, Vec<Option<Base>>, Vec<Option<PeakFit>>) {
    let paired: Vec<&Cell> = pairs.iter().map(|&(i, _)| &cells[i]).collect();
    // The background plane and the cells' rims are independent: side by side (each rim
    // its own fit, to the same values in any order).
    let (track, rims): (_, Vec<Option<RimFit>>) = rayon::join(
        || {
            let usable = clear_background(left_mask, right_mask, range, margin as usize);
            track_disparity_plane(views, &usable, range, SUBSTRATE_MAX_STD, prior)
        },
        || {
            paired
                .par_iter()
                .map(|c| substrate::rim_disparity(left, right, labels, c, range))
                .collect()
        },
    );
    let plane = track.as_ref().map(|t| t.plane);
    let mut bases = substrate::bases(&paired, plane.as_ref(), &rims);
    for (base, cell) in bases.iter_mut().zip(&paired) {
        if base.is_none() {
            *base = ring_disparity(labels, cell, disparity_raw, disparity, margin).map(|d| Base {
                d,
                // Not a formal error: the ring's median carries the cell's own flanks.
                std: RING_STD,
                source: SubstrateSource::Ring,
                doubt: Some(
                    "neither the background nor the cell's rim has the texture to fix the substrate; it is the median matched disparity around the cell"
                        .into(),
                ),
            });
        }
    }
    // Each cell's top is its own fit: in parallel, to the same values.
    let tops = bases
        .par_iter()
        .zip(paired.par_iter())
        .map(|(base, cell)| {
            base.as_ref().and_then(|b| {
                let ground = Ground {
                    d: b.d,
                    parallax: Some(Parallax::of(calib)),
                };
                top_of_cell(left, right, labels, cell, disparity, ground)
            })
        })
        .collect();
    (track, bases, tops)
}

/// 255 at the left pixels whose `margin` square is clear of the left cells and whose every
/// possible match — the right pixels `x − d` for `d` in `range`, with the same margin — is
/// clear of the right cells. Only along the rows does the range widen the clearance: a
/// square as wide as the range took most of the background of a crowded frame (3,000 of
/// 300,000 pixels with 60 cells), where the plane then locked onto a wrong disparity.
fn clear_background(left: &Mask, right: &Mask, range: DisparityRange, margin: usize) -> Mask {
    /// Rows a task takes.
    const BAND_ROWS: usize = 32;
    let (w, h) = (left.width, left.height);
    let m = margin as i64;
    // The prefix sums are padded with their end values, so that every window's bounds,
    // clamped to the row or not, give the same count; `lo` cells before column 0.
    let lo = (range.max as i64 + m).max(m).max(0) as usize;
    let hi = (m + 1 - range.min as i64).max(m + 1).max(0) as usize;
    let mut data = vec![0u8; w * h];
    data.par_chunks_mut(w * BAND_ROWS)
        .enumerate()
        .for_each(|(band, chunk)| {
            // Per row: each column's mask count over the rows within the margin (kept as
            // the rows slide), then prefix sums along the row.
            let (mut cl, mut cr) = (vec![0u32; w], vec![0u32; w]);
            let (mut pl, mut pr) = (vec![0u32; lo + w + 1 + hi], vec![0u32; lo + w + 1 + hi]);
            let add = |counts: &mut [u32], mask: &Mask, y: usize, sign: bool| {
                for (c, &v) in counts.iter_mut().zip(mask.row(y)) {
                    let one = u32::from(v != 0);
                    if sign { *c += one } else { *c -= one }
                }
            };
            let mut window: Option<(usize, usize)> = None;
            for (i, out) in chunk.chunks_mut(w).enumerate() {
                let y = band * BAND_ROWS + i;
                let (y0, y1) = (y.saturating_sub(margin), (y + margin + 1).min(h));
                slide_rows(window, (y0, y1), |yy, enters| {
                    add(&mut cl, left, yy, enters);
                    add(&mut cr, right, yy, enters);
                });
                window = Some((y0, y1));
                for (p, c) in [(&mut pl, &cl), (&mut pr, &cr)] {
                    // A running sum in a register (read back from the table, each add
                    // waited on the store before it).
                    let mut acc = 0;
                    for (q, &v) in p[lo + 1..lo + w + 1].iter_mut().zip(c.iter()) {
                        acc += v;
                        *q = acc;
                    }
                    let end = p[lo + w];
                    p[lo + w + 1..].fill(end);
                }
                // Column x's own window is [x − m, x + m], its matches' window
                // [x − max − m, x − min + m]: offsets into the padded sums.
                let own_end = &pl[lo + m as usize + 1..][..w];
                let own_start = &pl[lo - m as usize..][..w];
                let other_end = &pr[(lo as i64 + m + 1 - range.min as i64) as usize..][..w];
                let other_start = &pr[(lo as i64 - range.max as i64 - m) as usize..][..w];
                for (x, d) in out.iter_mut().enumerate() {
                    let own = own_end[x] - own_start[x];
                    let other = other_end[x] - other_start[x];
                    *d = if own == 0 && other == 0 { 255 } else { 0 };
                }
            }
        });
    Plane::from_vec(w, h, data).expect("size")
}

/// Fewest pixels in a cell's upper 30 % for its top to be fitted with the quartic model.
const SMALL_TOP_PIXELS: usize = 300;

/// Fewest pixels in a cell's upper 30 % for the quartic model alone to give its top.
const STEADY_TOP_PIXELS: usize = 800;

/// Fewest pixels a cell top's fit may use for its height to be trusted: below it (cells
/// under about 25 px across) the fit's formal error understates the real one, which
/// reached 10–18 % on textureless synthetic cells.
const MIN_TOP_PIXELS: usize = 400;

/// Uncertainty (px) put on a ring-median substrate, which no fit stands behind.
const RING_STD: f64 = 1.0;

/// How much of the disagreement between two models of a cell's top counts as the error of
/// the one kept (one standard error per this share of it).
const MODEL_ERROR_SHARE: f64 = 1.0;

/// Standard error (px) credited to a cell top's dome fit.
const TOP_STD: f64 = 0.05;

/// Largest disagreement (px) between a cell top's fit and its matched map's 98th
/// percentile (windowed matching lowers a small dome's top by 0.3–0.5 px; a wrong fit
/// overshoots by a pixel).
const TOP_AGREE_PX: f64 = 0.6;

/// Least share of a cell's pixels with an LR-checked disparity for its height to count.
const MIN_VALID_SHARE: f64 = 0.2;

/// Least share of a cell's upper 70 % that a plateau must hold for its top to be taken as
/// flat ([`TopModel::Plateau`]): between the spread and the flat-topped cells. Fitted to
/// the true pixels of 60 cells of each profile (`examples/top_fit_bias`), flat-topped
/// cells' plateaus held 39–54 % of them (10th–90th percentile), a spread cell's
/// (`1 − ρ⁴`) 1–29 %, a dome's or a cap's 0–9 %.
const PLATEAU_SHARE: f64 = 0.35;

/// Reach of a cell's nucleus fit ([`TopModel::Nucleus`]) round its top, in units of its
/// footprint's radius. A fried egg's nucleus spans 0.3–0.55 of its footprint's radius and
/// the segmented outline lies outside the true one (the variance window): 0.6 takes the
/// nucleus and a ring of its cytoplasm. Over centred nuclei of 0.45 (the heights matrix's
/// fried eggs before their nuclei varied), 0.5 and 0.7 put fewer tops within 5 % (74 and
/// 70 of 88 against 75).
const NUCLEUS_REACH: f64 = 0.6;

/// Least share of the nucleus fit's pixels on its pedestal for the cell to be a fried egg.
/// Over the heights matrix (centred nuclei), fried eggs' pedestals held 0.50–0.62 of the
/// disc, the pedestals fitted to domes, caps and spread cells at most 0.31 (mostly under
/// 0.2); any share from 0.35 to 0.45 gave the same tops.
const PEDESTAL_SHARE: f64 = 0.4;

/// Highest pedestal, relative to the nucleus' top, for the cell to be a fried egg: fitted
/// fried eggs' cytoplasm lay at 0.23–0.32 of the top (0.3 at the centre in `synth`, less
/// round a nucleus off it), the pedestals fitted to domes at 0.4–0.8; nucleus fits that
/// had slid 40–50 % low, at 0.39–0.40 (0.4 → 0.35: textureless fried eggs with varied
/// nuclei 66 → 68 % within 5 %).
const PEDESTAL_MAX: f64 = 0.35;

/// Highest pedestal, relative to the matched map's top, for the cell to be a fried egg:
/// the map smooths a small nucleus but still shows it standing over its cytoplasm. Over
/// the heights matrix fried eggs' pedestals lay at 0.2–0.6 of the map's top; a nucleus
/// fit started tall on a small dome (a spike on its flanks, +160 %) at 0.87.
const PEDESTAL_UNDER_MAP: f64 = 0.7;

/// Largest standard error of a trusted height, relative to the height (2σ = 5 %).
const HEIGHT_MAX_REL_STD: f64 = 0.025;

/// The largest formal error (px) a background plane may have to stand for the substrate.
const SUBSTRATE_MAX_STD: f64 = 0.05;

/// Refines the top of cell `cell` photometrically over its upper part, the pixels whose
/// matched height above the substrate under it (`ground`) is at least half the cell's (its
/// 98th percentile), with the quartic model ([`TopModel::Quartic`]: exact for ellipsoidal
/// and paraboloid cells, close for flattened ones), each surface point seen where the left
/// view's parallax puts it. A small cell, whose upper part is too few pixels for fifteen
/// terms, gets the mean of the dome model over its upper 30 % and 60 %; a cell between, the
/// mean of that and the quartic.
fn top_of_cell(
    left: &Plane<u8>,
    right: &Plane<u8>,
    labels: &Plane<u32>,
    cell: &Cell,
    disparity: &DisparityMap,
    ground: Ground,
) -> Option<PeakFit> {
    let base = ground.d;
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
    let level = |f: f64| (base + f * (top - base)) as f32;
    let above = |f: f64| -> (Vec<[usize; 2]>, Vec<f32>) {
        inside
            .iter()
            .filter(|(_, d)| *d >= level(f))
            .copied()
            .unzip()
    };
    let fit = |(pixels, init): &(Vec<[usize; 2]>, Vec<f32>), model| {
        refine_top(left, right, pixels, init, Some(ground), model)
    };
    let dome = |f: f64| fit(&above(f), TopModel::Quadratic);
    // The upper 30 % alone is noisy (σ ≈ 4 % of a 25 px cell's height) and the upper 60 %
    // biased by the steep flanks (2 % low with exact geometry): their mean is the better
    // figure (73 % of small textureless cells within 5 %, against 65 % for the surer one).
    let domes = || match (dome(0.7), dome(0.4)) {
        (Some(a), Some(b)) => Some(mean_top(a, b)),
        (a, b) => a.or(b),
    };
    let shape = footprint(labels, cell);
    let n7 = inside.iter().filter(|(_, d)| *d >= level(0.7)).count();
    // A fried egg: a raised nucleus on a spread cytoplasm. On a small cell the matched map
    // smooths the nucleus away (tops 35–53 % low); a dome on a level pedestal, fitted on a
    // disc round the top, sees it. Where most of the disc lies on the pedestal and that is
    // low under the top, the cell is one. A larger cell's quartic follows its nucleus
    // (over the heights matrix, fitting them too gained no top within 5 %).
    if n7 < STEADY_TOP_PIXELS
        && let Some(shape) = shape
        && let Some(at) = place_of(inside.iter().filter(|(_, d)| *d >= level(0.7)))
        && let round = disc(&inside, shape, at, NUCLEUS_REACH)
        && let Some(nucleus) = refine_nucleus(left, right, &round.0, &round.1, Some(ground), shape)
        && nucleus.level_share >= PEDESTAL_SHARE
        && nucleus.level <= PEDESTAL_MAX * (nucleus.peak - base)
        && nucleus.level <= PEDESTAL_UNDER_MAP * (top - base)
    {
        let other = fit(
            &disc(&inside, shape, at, NUCLEUS_REACH - 0.1),
            TopModel::Nucleus(shape),
        );
        // Only the pixels on the nucleus say where its top is: they, not the disc, are what
        // the trust in its height counts.
        let on_nucleus = (nucleus.pixels as f64 * (1.0 - nucleus.level_share)).round() as usize;
        return Some(with_model_error(
            PeakFit {
                pixels: on_nucleus,
                ..nucleus
            },
            other.map(|o| nucleus.peak - o.peak),
        ));
    }
    if n7 < SMALL_TOP_PIXELS {
        // Few pixels: the top's curvature takes the footprint's shape and only its size,
        // the level and the place are fitted (four terms, not six), on the upper 40 %.
        // Over the matrix of tests/heights.rs this took the share within 5 % from 93.6 to
        // 94.9 %, with as many unflagged misses (2); the upper 60 % or 30 % did worse
        // (92.4, 93.9 %).
        return match shape.and_then(|shape| fit(&above(0.6), TopModel::Footprint(shape))) {
            Some(f) => Some(with_model_error(f, domes().map(|d| f.peak - d.peak))),
            None => domes(),
        };
    }
    let quartic = fit(&above(0.5), TopModel::Quartic);
    // Fifteen terms on a few hundred pixels ride the noise: the dome fits' mean halves it
    // (cells with 300–800 pixels in their upper 30 %: 88 → 93 % and 96 → 98 % within 5 %;
    // above, the quartic alone is better).
    let rounded = if n7 < STEADY_TOP_PIXELS
        && let (Some(q), Some(d)) = (quartic, domes())
    {
        Some(with_model_error(mean_top(q, d), Some(q.peak - d.peak)))
    } else {
        match quartic {
            Some(q) => Some(with_model_error(q, dome(0.7).map(|d| q.peak - d.peak))),
            None => dome(0.7),
        }
    };
    // Where the rounded models part by more than a trusted height's error, the top may be
    // flat: a plateau holding a large share of the upper 70 % is one.
    let parted = rounded.is_none_or(|r| r.std > HEIGHT_MAX_REL_STD * (r.peak - base));
    if parted
        && let Some(flat) = fit(&above(0.3), TopModel::Plateau)
        && flat.level_share >= PLATEAU_SHARE
    {
        let upper = fit(&above(0.5), TopModel::Plateau);
        return Some(with_model_error(flat, upper.map(|u| flat.peak - u.peak)));
    }
    rounded
}

/// The mean place of `pixels`; `None` for none.
fn place_of<'a>(pixels: impl Iterator<Item = &'a ([usize; 2], f32)>) -> Option<[f64; 2]> {
    let (mut n, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for ([x, y], _) in pixels {
        n += 1.0;
        sx += *x as f64;
        sy += *y as f64;
    }
    (n > 0.0).then(|| [sx / n, sy / n])
}

/// The pixels of `inside` (with their matched disparities) within `reach` footprint radii
/// of `[cx, cy]` (`shape`: the footprint's normalised quadratic form).
fn disc(
    inside: &[([usize; 2], f32)],
    [a, b, c]: [f64; 3],
    [cx, cy]: [f64; 2],
    reach: f64,
) -> (Vec<[usize; 2]>, Vec<f32>) {
    inside
        .iter()
        .filter(|([x, y], _)| {
            let (dx, dy) = (*x as f64 - cx, *y as f64 - cy);
            a * dx * dx + b * dx * dy + c * dy * dy <= reach * reach
        })
        .copied()
        .unzip()
}

/// `top` with the model's error added to its standard error: how far another model of
/// the same top (fitted on other pixels or with other terms) puts it (`apart`, px). The formal
/// error is the fit's noise within its model; a flat-topped or fried-egg cell is no dome
/// and no quartic, and there the models part (over the heights matrix, the formal error
/// alone covered the true height within 2σ for 45–76 % of spread and flat-topped cells).
fn with_model_error(top: PeakFit, apart: Option<f64>) -> PeakFit {
    let Some(apart) = apart.filter(|a| a.is_finite()) else {
        return top;
    };
    let model = MODEL_ERROR_SHARE * apart.abs();
    PeakFit {
        std: top.std.hypot(model),
        ..top
    }
}

/// The normalised quadratic form `[A, B, C]` of cell `cell`'s footprint in the labels
/// (`ρ² = A·dx² + B·dx·dy + C·dy²`, 1 on the ellipse of the same second moments).
fn footprint(labels: &Plane<u32>, cell: &Cell) -> Option<[f64; 3]> {
    let b = cell.bbox;
    footprint_form(
        labels,
        cell.id,
        (b.x0 as usize, b.y0 as usize),
        (b.x1 as usize, b.y1 as usize),
    )
}

/// The normalised quadratic form of label `id`'s pixels within `[x0, x1] × [y0, y1]`
/// ([`TopModel::Footprint`]'s shape); `None` for fewer than 10 pixels or a line.
pub fn footprint_form(
    labels: &Plane<u32>,
    id: u32,
    (x0, y0): (usize, usize),
    (x1, y1): (usize, usize),
) -> Option<[f64; 3]> {
    let (mut n, mut sx, mut sy, mut sxx, mut sxy, mut syy) = (0.0f64, 0.0, 0.0, 0.0, 0.0, 0.0);
    for y in y0..=y1 {
        for x in x0..=x1 {
            if *labels.get(x, y) == id {
                let (xf, yf) = (x as f64, y as f64);
                n += 1.0;
                sx += xf;
                sy += yf;
                sxx += xf * xf;
                sxy += xf * yf;
                syy += yf * yf;
            }
        }
    }
    if n < 10.0 {
        return None;
    }
    let (mx, my) = (sx / n, sy / n);
    let (cxx, cxy, cyy) = (sxx / n - mx * mx, sxy / n - mx * my, syy / n - my * my);
    let det = cxx * cyy - cxy * cxy;
    if det <= 1e-9 {
        return None;
    }
    // An ellipse of semi-axes a, b has variances a²/4, b²/4 along them.
    Some([cyy / det / 4.0, -2.0 * cxy / det / 4.0, cxx / det / 4.0])
}

/// The mean of two fits of one top, its error their errors' mean (they share pixels: the
/// mean is no surer than they are).
fn mean_top(a: PeakFit, b: PeakFit) -> PeakFit {
    PeakFit {
        peak: 0.5 * (a.peak + b.peak),
        std: 0.5 * (a.std + b.std),
        pixels: a.pixels.max(b.pixels),
        ..a
    }
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

/// Per-cell 3D figures from the left labels and cells, the right cells, their pairing, the
/// final and LR-checked disparity maps and [`cell_heights`]' bases and tops. On a textured
/// `background`, a cell standing on its plane is the region the views show off the plane
/// ([`raised_region`]) rather than its segmented pixels.
pub fn measure(
    (labels, left_cells, right_cells): (&Plane<u32>, &[Cell], &[Cell]),
    pairs: &[(usize, usize)],
    (disparity, disparity_raw): (&DisparityMap, &DisparityMap),
    (bases, tops): (&[Option<Base>], &[Option<PeakFit>]),
    background: Option<Background>,
    calib: &Calibration,
) -> Vec<Cell3> {
    // At or beyond infinite depth a disparity is no point: such pixels are left out, and a
    // cell whose substrate lies there is not measured (`beyond_infinity` counts them).
    let z_of = |d: f64| crate::depth_of(d, calib);
    let one = |k: usize, i: usize, j: usize| -> Option<Cell3> {
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
        let base = bases[k].as_ref()?;
        let d_sub = base.d;
        let matched = percentile(inside.iter().map(|p| p.2).collect(), 0.98);
        let d_top = tops[k].map(|t| t.peak).or(matched)?;
        let raised = background
            .filter(|_| base.source == SubstrateSource::Plane)
            .and_then(|bg| raised_region(labels, cell, (disparity, disparity_raw), bg));
        let centroid_px = match raised {
            Some(r) if !r.is_empty() => {
                let n = r.len() as f64;
                let c = r.iter().fold([0.0, 0.0], |a, p| {
                    [a[0] + p.0 as f64 / n, a[1] + p.1 as f64 / n]
                });
                inside = r.into_iter().filter(|p| p.2.is_finite()).collect();
                c
            }
            _ => cell.centroid,
        };
        let z_sub = z_of(d_sub)?;
        let pixel_area = (z_sub / calib.focal_px).powi(2);
        let xy = |x: usize, y: usize| {
            let d = *disparity.get(x, y) as f64;
            crate::triangulate_pixel(x as f64, y as f64, d, calib).map(|p| [p[0], p[1]])
        };
        let (mut vol, mut wx, mut wy, mut wz) = (0.0, 0.0, 0.0, 0.0);
        for &(x, y, d) in &inside {
            let Some(z) = z_of(d as f64) else { continue };
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
            if let Some([px, py, _]) = crate::triangulate_pixel(x as f64, y as f64, d as f64, calib)
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
            crate::triangulate_pixel(cell.centroid[0], cell.centroid[1], d_sub, calib)?
        };
        let contour = cell
            .contour
            .iter()
            .filter_map(|c| crate::triangulate_pixel(c[0] as f64, c[1] as f64, d_sub, calib))
            .collect();
        let valid_share = valid_raw as f64 / cell.area.max(1) as f64;
        let z_top = z_of(d_top).filter(|_| d_top > d_sub);
        let height = z_top.map(|z| z_sub - z);
        // dZ/dd' = −Z²/(b·f): the substrate's error, and the top's (its fit's, at least
        // 0.05 px, what the dome fit reaches on synthetic truth).
        let dz = |z: f64| z * z / (calib.baseline * calib.focal_px);
        let top_std = tops[k].map_or(TOP_STD, |t| t.std.max(TOP_STD));
        let height_std = z_top.map(|z| (dz(z_sub) * base.std).hypot(dz(z) * top_std));
        let doubt = base
            .doubt
            .clone()
            .or_else(|| height.is_none().then(|| "the top was not found above the substrate".into()))
            .or_else(|| {
                (valid_share < MIN_VALID_SHARE).then(|| {
                    format!(
                        "only {:.0} % of the cell's pixels passed the LR check",
                        100.0 * valid_share
                    )
                })
            })
            .or_else(|| {
                match tops[k] {
                    None => Some("the top could not be fitted: it is the matched map's".into()),
                    Some(t) if t.pixels < MIN_TOP_PIXELS => Some(format!(
                        "the cell is too small for a sure top ({} pixels fitted)",
                        t.pixels
                    )),
                    Some(_) => None,
                }
            })
            .or_else(|| {
                // The fit and the matcher's map disagree on the top: the fit found a wrong
                // minimum (seen on small cells with little texture) or the map is wrong.
                let matched = matched?;
                let diff = d_top - matched;
                (tops[k].is_some() && diff.abs() > TOP_AGREE_PX).then(|| {
                    format!(
                        "the top's fit ({d_top:.2} px) and the matched map ({matched:.2} px) disagree by {diff:+.2} px"
                    )
                })
            })
            .or_else(|| match (height, height_std) {
                (Some(h), Some(s)) if s.is_nan() || s > HEIGHT_MAX_REL_STD * h => Some(format!(
                    "the height is uncertain by {:.1} % (σ)",
                    100.0 * s / h
                )),
                _ => None,
            });
        finite(Cell3 {
            id: cell.id,
            right_id: right_cells[j].id,
            area_px: cell.area,
            centroid_px,
            disparity: d_top,
            centroid,
            substrate_z: z_sub,
            height,
            volume: vol,
            contour,
            valid_share,
            quality: CellQuality {
                substrate: base.source,
                substrate_std: base.std,
                height_std,
                residual: tops[k].map(|t| t.residual),
                trusted: doubt.is_none(),
                doubt,
            },
        })
    };
    // Each cell on its own: in parallel, in the pairs' order.
    pairs
        .par_iter()
        .enumerate()
        .filter_map(|(k, &(i, j))| one(k, i, j))
        .collect()
}

/// How far (px) a cell may reach past the calibrated field and stay trusted: the corners
/// sit half a square inside the board's edge.
const FIELD_SLACK: f64 = 2.0;

/// Takes the trust from the cells of `cells` (measured from `left`) that reach outside the
/// calibrated `field` (`[u0, v0, u1, v1]`, rectified px): there the distortion model is
/// extrapolated. Past a 7×5 board's edge a Greenough's heights came out 9–12σ low; with the
/// board across the field, 1–4σ.
pub fn flag_outside(cells: &mut [Cell3], left: &[Cell], field: [f64; 4]) {
    for c in cells.iter_mut().filter(|c| c.quality.trusted) {
        let Some(b) = left.iter().find(|l| l.id == c.id).map(|l| l.bbox) else {
            continue;
        };
        let s = FIELD_SLACK;
        let inside = b.x0 as f64 >= field[0] - s
            && b.y0 as f64 >= field[1] - s
            && b.x1 as f64 <= field[2] + s
            && b.y1 as f64 <= field[3] + s;
        if !inside {
            c.quality.trusted = false;
            c.quality.doubt = Some(format!(
                "the cell reaches outside the calibrated field (the board's corners covered x {:.0}–{:.0}, y {:.0}–{:.0} px): its height rests on the distortion model's extrapolation",
                field[0], field[2], field[1], field[3]
            ));
        }
    }
}

/// `c` if every number it carries is one (a NaN or an infinity would travel as JSON
/// `null`, which no reader of a number takes).
fn finite(c: Cell3) -> Option<Cell3> {
    let f = |v: f64| v.is_finite();
    let opt = |v: Option<f64>| v.is_none_or(f);
    (c.centroid_px.iter().all(|&v| f(v))
        && f(c.disparity)
        && c.centroid.iter().all(|&v| f(v))
        && f(c.substrate_z)
        && opt(c.height)
        && f(c.volume)
        && c.contour.iter().flatten().all(|&v| f(v))
        && f(c.valid_share)
        && f(c.quality.substrate_std)
        && opt(c.quality.height_std)
        && opt(c.quality.residual))
    .then_some(c)
}

/// How many of these substrate disparities lie at or beyond infinite depth with `calib`
/// (their cells cannot be measured): a calibration whose principal points' offset
/// (`cx_right − cx`) is missing or wrong for the pair.
pub fn beyond_infinity(bases: &[Option<Base>], calib: &Calibration) -> usize {
    bases
        .iter()
        .flatten()
        .filter(|b| crate::depth_of(b.d, calib).is_none())
        .count()
}

/// The textured background a cell stands on, for [`measure`].
#[derive(Clone, Copy)]
pub struct Background<'a> {
    /// The background's disparity plane.
    pub plane: &'a DisparityPlane,
    /// The margin matched around each cell, px.
    pub margin: u8,
    /// The rectified views.
    pub views: (&'a Plane<u8>, &'a Plane<u8>),
}

/// Half-width of the patch [`raised_region`] compares the views over.
const PATCH: i64 = 1;

/// How much better (grey levels, mean absolute difference over the patch) the cell's own
/// disparity must explain a pixel than the background plane for it to be the cell's.
const PATCH_MARGIN: f64 = 1.0;

/// Largest misfit (grey levels, as for [`PATCH_MARGIN`]) of a pixel the cell's disparity
/// explains: sensor noise of 1.5 grey levels in both views gives about 1.4, interpolating a
/// strongly textured cell adds to it (3 left a strongly textured cell 1.1 px off).
const PATCH_FIT: f64 = 4.0;

/// The pixels of `cell` by stereo, where a textured background's plane is known: those
/// whose small patch the matched disparity explains better than the plane does (mean
/// absolute difference between the views, each patch less its mean), grown from the
/// segmented pixels through the matched margin around them (no other cell's). On a strongly
/// textured substrate the variance threshold loses whole sides of a cell (its centroid
/// 2.7 px off) while the views plainly disagree with the plane there; and the matcher's
/// windows carry a cell's disparity a few pixels onto the substrate beside it, which the
/// plane explains better. Segmented pixels stay whatever they show, and beside them only
/// pixels that passed the LR check and that the matched disparity fits to noise can join.
/// `None` when the region grows past twice the segmented area (then the disparities are
/// not to be leaned on).
fn raised_region(
    labels: &Plane<u32>,
    cell: &Cell,
    (disparity, raw): (&DisparityMap, &DisparityMap),
    bg: Background,
) -> Option<Vec<(usize, usize, f32)>> {
    let (b, m) = (cell.bbox, bg.margin as usize);
    let (left, right) = bg.views;
    let (x0, y0) = (
        (b.x0 as usize).saturating_sub(m),
        (b.y0 as usize).saturating_sub(m),
    );
    let x1 = (b.x1 as usize + m + 1).min(labels.width);
    let y1 = (b.y1 as usize + m + 1).min(labels.height);
    let (w, h) = (labels.width as i64, labels.height as i64);
    // Mean absolute difference of the zero-mean patches around (x, y) with the right view
    // shifted by `d(q)`; `None` off the views.
    let misfit = |x: usize, y: usize, d: &dyn Fn(i64, i64) -> f64| -> Option<f64> {
        let mut pairs = [(0.0, 0.0); ((2 * PATCH + 1) * (2 * PATCH + 1)) as usize];
        let mut k = 0;
        for dy in -PATCH..=PATCH {
            for dx in -PATCH..=PATCH {
                let (qx, qy) = (x as i64 + dx, y as i64 + dy);
                if qx < 0 || qy < 0 || qx >= w || qy >= h {
                    return None;
                }
                let xr = qx as f64 - d(qx, qy);
                if !(xr >= 0.0 && xr <= (w - 1) as f64) {
                    return None;
                }
                let i = (xr.floor() as usize).min(w as usize - 2);
                let t = xr - i as f64;
                let row = right.row(qy as usize);
                let r = row[i] as f64 * (1.0 - t) + row[i + 1] as f64 * t;
                pairs[k] = (*left.get(qx as usize, qy as usize) as f64, r);
                k += 1;
            }
        }
        let n = pairs.len() as f64;
        let (ml, mr) = pairs
            .iter()
            .fold((0.0, 0.0), |a, p| (a.0 + p.0 / n, a.1 + p.1 / n));
        Some(
            pairs
                .iter()
                .map(|p| ((p.0 - ml) - (p.1 - mr)).abs())
                .sum::<f64>()
                / n,
        )
    };
    let on_plane = |qx: i64, qy: i64| bg.plane.at(qx as f64, qy as f64);
    // Beside the cell only what passed the LR check counts: the strip of substrate the
    // cell hides from the right camera fits neither the plane nor any disparity, and
    // post-processing fills it with the cell's.
    let raised = |x: usize, y: usize| -> Option<f32> {
        let l = *labels.get(x, y);
        let d = *raw.get(x, y);
        if !(l == cell.id || l == 0) || !d.is_finite() {
            return None;
        }
        // The patch at the pixel's own disparity, flat: with its neighbours' own, a pixel
        // of substrate beside the cell would borrow their fit.
        let own = |_: i64, _: i64| d as f64;
        let (p, c) = (misfit(x, y, &on_plane)?, misfit(x, y, &own)?);
        (c + PATCH_MARGIN < p && c < PATCH_FIT).then_some(d)
    };
    let cw = x1 - x0;
    let mut state = vec![0u8; cw * (y1 - y0)];
    let mut stack = Vec::new();
    for y in y0..y1 {
        for x in x0..x1 {
            if *labels.get(x, y) == cell.id {
                state[(y - y0) * cw + x - x0] = 1;
                stack.push((x, y));
            }
        }
    }
    let mut region = Vec::new();
    // Segmented pixels stay whether or not they pass: the flank a cell turns away from the
    // right camera is seen by the left one alone, which no disparity explains. The matched
    // margin only adds to them.
    while let Some((x, y)) = stack.pop() {
        let d = if *labels.get(x, y) == cell.id {
            *disparity.get(x, y)
        } else {
            let Some(d) = raised(x, y) else { continue };
            d
        };
        region.push((x, y, d));
        for (dx, dy) in segment::NEIGHBOURS {
            let (nx, ny) = (x as i64 + dx, y as i64 + dy);
            if nx < x0 as i64 || ny < y0 as i64 || nx >= x1 as i64 || ny >= y1 as i64 {
                continue;
            }
            let (nx, ny) = (nx as usize, ny as usize);
            let k = (ny - y0) * cw + nx - x0;
            if state[k] == 0 {
                state[k] = 1;
                stack.push((nx, ny));
            }
        }
    }
    (region.len() as u64 <= 2 * cell.area).then(|| {
        region.sort_unstable_by_key(|p| (p.1, p.0));
        region
    })
}

/// The left cells [`measure`] left out (`measured`: what it gave), most of them without a
/// partner in the right view (its segmentation lost or split them, or they stand at its
/// edge), as obstacles of unknown height: a cell the
/// pipette could touch is never left out of the targets. Each stands on the substrate where
/// the evidence allows — the background plane that `bases` used, its own rim, or the median
/// of the paired cells' bases — and is never trusted. A cell with none of these is left out
/// (there is no depth to put it at).
#[allow(clippy::too_many_arguments)]
pub fn lone_cells(
    (left, right): (&Plane<u8>, &Plane<u8>),
    (labels, cells): (&Plane<u32>, &[Cell]),
    measured: &[Cell3],
    plane: Option<&DisparityPlane>,
    bases: &[Option<Base>],
    range: DisparityRange,
    calib: &Calibration,
) -> Vec<Cell3> {
    let plane = plane.filter(|_| {
        bases
            .iter()
            .flatten()
            .any(|b| b.source == SubstrateSource::Plane)
    });
    let median = percentile(bases.iter().flatten().map(|b| b.d as f32).collect(), 0.5);
    cells
        .iter()
        .filter(|c| !measured.iter().any(|m| m.id == c.id))
        .filter_map(|cell| {
            let [x, y] = cell.centroid;
            let (d, std, source) = match plane {
                Some(pl) => (pl.at(x, y), pl.std.max(0.05), SubstrateSource::Plane),
                None => match substrate::rim_disparity(left, right, labels, cell, range) {
                    Some(r) => (r.d, r.std, SubstrateSource::Rim),
                    None => (median?, RING_STD, SubstrateSource::Rims),
                },
            };
            let z_sub = crate::depth_of(d, calib)?;
            finite(Cell3 {
                id: cell.id,
                right_id: 0,
                area_px: cell.area,
                centroid_px: cell.centroid,
                disparity: d,
                centroid: crate::triangulate_pixel(x, y, d, calib)?,
                substrate_z: z_sub,
                height: None,
                volume: 0.0,
                contour: cell
                    .contour
                    .iter()
                    .filter_map(|c| crate::triangulate_pixel(c[0] as f64, c[1] as f64, d, calib))
                    .collect(),
                valid_share: 0.0,
                quality: CellQuality {
                    substrate: source,
                    substrate_std: std,
                    height_std: None,
                    residual: None,
                    trusted: false,
                    doubt: Some(
                        "the cell could not be measured in both views (no partner in the right view, or no substrate or top under it): its height is unknown"
                            .into(),
                    ),
                },
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use schemas::{BoundingBox, INVALID_DISPARITY};

    /// The first [`clear_background`], from two summed-area tables.
    fn clear_background_reference(
        left: &Mask,
        right: &Mask,
        range: DisparityRange,
        margin: usize,
    ) -> Mask {
        let (w, h) = (left.width, left.height);
        let sl = segment::BoxSums::new(w, h, |x, y| u64::from(*left.get(x, y) != 0));
        let sr = segment::BoxSums::new(w, h, |x, y| u64::from(*right.get(x, y) != 0));
        let clip = |v: i64, hi: usize| v.clamp(0, hi as i64) as usize;
        let m = margin as i64;
        let data = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| {
                let (xi, yi) = (x as i64, y as i64);
                let (y0, y1) = (clip(yi - m, h), clip(yi + m + 1, h));
                let own = sl.rect(clip(xi - m, w), y0, clip(xi + m + 1, w), y1);
                let (r0, r1) = (
                    clip(xi - range.max as i64 - m, w),
                    clip(xi - range.min as i64 + m + 1, w),
                );
                let other = if r0 < r1 { sr.rect(r0, y0, r1, y1) } else { 0 };
                if own == 0 && other == 0 { 255 } else { 0 }
            })
            .collect();
        Plane::from_vec(w, h, data).expect("size")
    }

    #[test]
    fn the_sliding_clearance_matches_the_summed_area_one() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let mut random = |w: usize, h: usize, density: f64| {
            let data = (0..w * h)
                .map(|_| if rng.random_bool(density) { 255 } else { 0 })
                .collect();
            Plane::from_vec(w, h, data).unwrap()
        };
        let mut cleared = 0;
        for case in 0..200usize {
            let (w, h) = (1 + case % 37 * 2, 1 + case % 23 * 3);
            let density = [0.001, 0.01, 0.05][case % 3];
            let (l, r) = (random(w, h, density), random(w, h, density));
            let min = (case % 11) as i32 - 5;
            let range = DisparityRange::new(min, min + (case % 7) as i32 * 4);
            let margin = case % 5;
            let fast = clear_background(&l, &r, range, margin);
            assert_eq!(
                fast,
                clear_background_reference(&l, &r, range, margin),
                "case {case}: {w}×{h}, range {range:?}, margin {margin}"
            );
            cleared += fast.data.iter().filter(|&&v| v == 0).count();
        }
        assert!(cleared > 1000, "{cleared} pixels not clear");
    }

    fn cell(id: u32, x0: u32, y0: u32, x1: u32, y1: u32) -> Cell {
        let area = ((x1 - x0 + 1) * (y1 - y0 + 1)) as u64;
        Cell {
            id,
            area,
            centroid: [(x0 + x1) as f64 / 2.0, (y0 + y1) as f64 / 2.0],
            bbox: BoundingBox { x0, y0, x1, y1 },
            contour: vec![[x0, y0]],
            perimeter: 0.0,
        }
    }

    #[test]
    fn background_clearance_widens_along_rows_only() {
        let (w, h) = (40, 20);
        let mut left = Plane::from_vec(w, h, vec![0u8; w * h]).unwrap();
        let right = left.clone();
        *left.get_mut(20, 10) = 255;
        let mut r = right.clone();
        *r.get_mut(10, 10) = 255;
        // Left cell at x = 20 with margin 2: its 5×5 square is not background.
        let u = clear_background(&left, &right, DisparityRange::new(0, 8), 2);
        assert_eq!(*u.get(18, 8), 0);
        assert_eq!(*u.get(17, 10), 255);
        assert_eq!(*u.get(20, 13), 255);
        // Right cell at x = 10, range 0..8: left pixels 8..=20 may match it (±2 margin), and
        // only on rows 8..=12.
        let u = clear_background(
            &Plane::from_vec(w, h, vec![0u8; w * h]).unwrap(),
            &r,
            DisparityRange::new(0, 8),
            2,
        );
        let row: Vec<u8> = (0..w).map(|x| *u.get(x, 10)).collect();
        for (x, v) in row.iter().enumerate() {
            assert_eq!(*v == 0, (8..=20).contains(&x), "x = {x}");
        }
        assert_eq!(*u.get(14, 12), 0);
        assert_eq!(*u.get(14, 13), 255);
    }

    #[test]
    fn cells_left_out_stand_on_the_substrate_untrusted_without_a_height() {
        let calib = Calibration {
            baseline: 100.0,
            focal_px: 1000.0,
            cx: 20.0,
            cy: 10.0,
            cx_right: 20.0,
            unit: schemas::LengthUnit::Um,
        };
        let cells = [cell(1, 2, 2, 9, 9), cell(2, 20, 2, 29, 9)];
        let labels = Plane::from_vec(
            40,
            20,
            (0..20usize)
                .flat_map(|y| (0..40usize).map(move |x| (x, y)))
                .map(|(x, y)| match (x, y) {
                    (2..=9, 2..=9) => 1,
                    (20..=29, 2..=9) => 2,
                    _ => 0,
                })
                .collect(),
        )
        .unwrap();
        // A flat grey pair: no rim to match, so the substrate comes from the plane or
        // the measured cells' bases.
        let grey = Plane::filled(40, 20, 100u8);
        let measured = Cell3 {
            id: 1,
            right_id: 1,
            area_px: 64,
            centroid_px: [5.5, 5.5],
            disparity: 12.0,
            centroid: [0.0; 3],
            substrate_z: 10.0,
            height: Some(1.0),
            volume: 1.0,
            contour: Vec::new(),
            valid_share: 1.0,
            quality: CellQuality::default(),
        };
        let base = |source| Base {
            d: 10.0,
            std: 0.1,
            source,
            doubt: None,
        };
        let range = DisparityRange::new(0, 16);
        let plane = DisparityPlane {
            d0: 8.0,
            dx: 0.1,
            dy: 0.0,
            centre: [20.0, 5.5],
            std: 0.01,
            pixels: 100,
        };
        let lone = |plane: Option<&DisparityPlane>, bases: &[Option<Base>]| {
            lone_cells(
                (&grey, &grey),
                (&labels, &cells),
                std::slice::from_ref(&measured),
                plane,
                bases,
                range,
                &calib,
            )
        };
        // The plane the bases stood on: at cell 2's centroid (24.5, 5.5), 8 + 0.45 px.
        let out = lone(Some(&plane), &[Some(base(SubstrateSource::Plane))]);
        assert_eq!(out.len(), 1);
        let c = &out[0];
        assert_eq!((c.id, c.right_id, c.height), (2, 0, None));
        assert!((c.disparity - 8.45).abs() < 1e-12, "{}", c.disparity);
        assert!((c.substrate_z - 100.0 * 1000.0 / 8.45).abs() < 1e-9);
        assert!(!c.quality.trusted && c.quality.doubt.is_some());
        assert_eq!(c.quality.substrate, SubstrateSource::Plane);
        // A plane the bases did not use does not count: the bases' median does.
        let out = lone(Some(&plane), &[Some(base(SubstrateSource::Rim))]);
        assert_eq!(out[0].disparity, 10.0);
        assert_eq!(out[0].quality.substrate, SubstrateSource::Rims);
        // Nothing to stand on: left out.
        assert!(lone(None, &[None]).is_empty());
    }

    #[test]
    fn a_cell_the_segmentation_cut_short_is_whole_by_stereo() {
        // Textured substrate at disparity 2, a textured 12×12 block at 6 (columns 20..32,
        // rows 10..22); the segmentation has only its left half.
        let tex = |x: i64, y: i64, k: u64| -> f64 {
            let h = (x as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15)
                ^ (y as u64).wrapping_mul(0xc2b2_ae3d_27d4_eb4f)
                ^ k;
            let h = h.wrapping_mul(0x2545_f491_4f6c_dd1d);
            ((h >> 40) % 60) as f64
        };
        let block = |x: i64, y: i64| (20..32).contains(&x) && (10..22).contains(&y);
        let (w, h) = (60usize, 32usize);
        let left = Plane::from_vec(
            w,
            h,
            (0..h as i64)
                .flat_map(|y| (0..w as i64).map(move |x| (x, y)))
                .map(|(x, y)| {
                    if block(x, y) {
                        (100.0 + tex(x, y, 1)) as u8
                    } else {
                        (40.0 + tex(x, y, 2)) as u8
                    }
                })
                .collect(),
        )
        .unwrap();
        // The right view: each right pixel shows what the left saw 6 (block) or 2 px to
        // its right, the block in front.
        let right = Plane::from_vec(
            w,
            h,
            (0..h as i64)
                .flat_map(|y| (0..w as i64).map(move |x| (x, y)))
                .map(|(x, y)| {
                    if block(x + 6, y) {
                        (100.0 + tex(x + 6, y, 1)) as u8
                    } else {
                        (40.0 + tex(x + 2, y, 2)) as u8
                    }
                })
                .collect(),
        )
        .unwrap();
        let cut = |x: usize, y: usize| (20..26).contains(&x) && (10..22).contains(&y);
        let labels = Plane::from_vec(
            w,
            h,
            (0..h)
                .flat_map(|y| (0..w).map(move |x| u32::from(cut(x, y))))
                .collect(),
        )
        .unwrap();
        // The matcher's maps, exact: 6 on the block, 2 on the substrate it leaves visible,
        // nothing where the block hides it from the right view (columns 32..36).
        let map = |hidden: f32| {
            Plane::from_vec(
                w,
                h,
                (0..h as i64)
                    .flat_map(|y| (0..w as i64).map(move |x| (x, y)))
                    .map(|(x, y)| {
                        if block(x, y) {
                            6.0
                        } else if (10..22).contains(&y) && (32..36).contains(&x) {
                            hidden
                        } else {
                            2.0
                        }
                    })
                    .collect(),
            )
            .unwrap()
        };
        let (filled, raw) = (map(6.0), map(INVALID_DISPARITY));
        let plane = DisparityPlane {
            d0: 2.0,
            dx: 0.0,
            dy: 0.0,
            centre: [30.0, 16.0],
            std: 0.01,
            pixels: 1000,
        };
        let c = cell(1, 20, 10, 25, 21);
        let bg = Background {
            plane: &plane,
            margin: 8,
            views: (&left, &right),
        };
        let region = raised_region(&labels, &c, (&filled, &raw), bg).unwrap();
        let mut got: Vec<(usize, usize)> = region.iter().map(|p| (p.0, p.1)).collect();
        got.sort_unstable();
        // The segmented half, and the other half less its edge pixels, whose patch
        // straddles the substrate (it fits neither disparity).
        let mut want: Vec<(usize, usize)> = (20..26)
            .flat_map(|x| (10..22).map(move |y| (x, y)))
            .chain((26..31).flat_map(|x| (11..21).map(move |y| (x, y))))
            .collect();
        want.sort_unstable();
        assert_eq!(got, want);
    }
}
