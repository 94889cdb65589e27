//! Cell segmentation for the stereo microscope, the paper's §3 steps as plain functions:
//!
//! 1. [`local_variance`] over a `(2M+1)²` window from sliding integer sums (O(1) per pixel) and
//!    [`normalise`] onto 0–255: cells are textured, the background is smooth;
//! 2. [`otsu_threshold`] on its [`histogram`] (with an absolute floor, `min_std`, so a
//!    textureless image yields no cells instead of half its noise);
//! 3. clean-up: optional [`open`]/[`close`], [`fill_holes`], [`peel_edges`] (the skirt
//!    the variance window adds around a cell goes back to the background), [`remove_small`];
//! 4. [`label`]: 8-connected components; [`absorb_rings`]: thin arcs around a larger object
//!    (an embryo's zona pellucida) join it, an arc round nothing that follows an ellipse
//!    (a flat cell's rim seen at a slant) is closed;
//! 5. [`trace_boundary`]: chain-code boundary following with the paper's search-start rule;
//! 6. per cell: id, area, centroid, bounding box, contour and perimeter ([`schemas::Cell`]).
//!
//! [`segment`] runs them all and keeps every intermediate image for the CLI to write.

mod boxsum;
mod label;
mod morph;
pub mod node;
mod otsu;
mod peel;
pub mod report;
mod rings;
mod trace;
mod variance;

pub use boxsum::{BoxSums, Summable};
pub use label::{Components, Connectivity, NEIGHBOURS, components_where, label, label_where};
pub use morph::{close, dilate, fill_broken_outlines, fill_holes, open, remove_small};
pub use otsu::{histogram, otsu_threshold};
pub use peel::peel_edges;
pub use rings::absorb_rings;
pub use trace::{DIRECTIONS, chain_length, search_start, trace_boundary};
pub use variance::{VarianceScale, local_variance, normalise, variance_levels};

use schemas::{BoundingBox, Cell, Mask, Plane};
use serde::{Deserialize, Serialize};

/// Segmentation settings (the `params` of a segment node; every key optional).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SegmentParams {
    /// M: the variance window is `(2M+1)²`.
    pub variance_radius: usize,
    /// How the variance is mapped onto 0–255.
    pub scale: VarianceScale,
    /// Smallest local standard deviation (grey levels) that can count as cell, whatever
    /// Otsu says: camera noise alone is 1–2 grey levels on the reference images.
    pub min_std: f32,
    /// The floor follows the camera too: a cell's local standard deviation is at least this
    /// many times the image's noise, read from its quietest tenth ([`noise_std`]). A fixed
    /// floor of 4 grey levels cut the interiors out of cells that a microscope's blur had
    /// left at 2.5–5 over noise of 1.5.
    pub noise_floor: f32,
    /// Blobs smaller than this many pixels are dropped.
    pub min_area: usize,
    /// Fill holes inside cells.
    pub fill_holes: bool,
    /// Opening radius before hole filling (0 = off).
    pub open_radius: u8,
    /// Closing radius before hole filling (0 = off).
    pub close_radius: u8,
    /// Peel the outer layers (up to M+1 px deep) that look like the background around them
    /// (within 2.25 robust standard deviations of it, over a `(8M+9)²` window).
    pub peel_edges: bool,
    /// Join thin arcs (solidity ≤ 0.35) to the object at least twice their size that their
    /// hull reaches into: an embryo's zona pellucida breaks into arcs around it; close an
    /// arc that reaches into none into the ellipse it follows round at least 240°.
    pub absorb_rings: bool,
}

impl Default for SegmentParams {
    fn default() -> Self {
        Self {
            variance_radius: 3,
            scale: VarianceScale::LogStdDev,
            min_std: 2.0,
            noise_floor: 2.0,
            min_area: 200,
            fill_holes: true,
            open_radius: 0,
            close_radius: 0,
            peel_edges: true,
            absorb_rings: true,
        }
    }
}

/// Everything segmentation produces, intermediate images included.
#[derive(Clone, Debug)]
pub struct Segmentation {
    /// The normalised variance image (0–255).
    pub variance: Plane<u8>,
    /// Largest value before normalisation (on the scale's own terms: ln(1 + σ), σ or σ²).
    pub variance_max: f32,
    /// The image's noise as [`noise_std`] reads it, grey levels.
    pub noise: f32,
    /// Histogram of `variance`.
    pub histogram: [u64; 256],
    /// Otsu's threshold on `variance` (`None`: the image is flat).
    pub otsu: Option<u8>,
    /// The threshold applied: Otsu's, raised to the `min_std` floor (256 = nothing passes).
    pub threshold: u16,
    /// Final foreground mask (255 = cell).
    pub mask: Mask,
    /// Label image: 0 background, cell `i` has label `i`.
    pub labels: Plane<u32>,
    /// The cells, by id.
    pub cells: Vec<Cell>,
}

/// Where on the 0–255 scale a local standard deviation of `std` grey levels falls.
fn floor_level(std: f32, max: f32, scale: VarianceScale) -> u16 {
    if max <= 0.0 {
        return 256;
    }
    let v = match scale {
        VarianceScale::StdDev => std,
        VarianceScale::Variance => std * std,
        VarianceScale::LogStdDev => std.ln_1p(),
    };
    (v / max * 255.0).ceil().clamp(0.0, 256.0) as u16
}

/// The local standard deviation (grey levels) at level `level` of a variance image whose
/// largest value is `max` on `scale`: the inverse of [`floor_level`].
fn level_std(level: usize, max: f32, scale: VarianceScale) -> f32 {
    let v = level as f32 / 255.0 * max;
    match scale {
        VarianceScale::StdDev => v,
        VarianceScale::Variance => v.max(0.0).sqrt(),
        VarianceScale::LogStdDev => v.exp_m1(),
    }
}

/// The image's noise, grey levels: the local standard deviation below which a tenth of the
/// image lies, from the variance image's `histogram`. Cells seldom cover nine tenths of a
/// frame, so the quietest tenth is background, where the window sees the camera's noise
/// (slightly under it: the tenth is the low tail of the noise's own spread).
pub fn noise_std(histogram: &[u64; 256], max: f32, scale: VarianceScale) -> f32 {
    let total: u64 = histogram.iter().sum();
    let mut seen = 0;
    for (level, &n) in histogram.iter().enumerate() {
        seen += n;
        if total > 0 && seen * 10 >= total {
            return level_std(level, max, scale);
        }
    }
    0.0
}

/// Segments the cells of a grey image.
pub fn segment(img: &Plane<u8>, p: &SegmentParams) -> Segmentation {
    let (variance, variance_max) = variance_levels(img, p.variance_radius, p.scale);
    let histogram = histogram(&variance);
    let otsu = otsu_threshold(&histogram);
    let noise = noise_std(&histogram, variance_max, p.scale);
    let floor = floor_level(p.min_std.max(p.noise_floor * noise), variance_max, p.scale);
    let threshold = otsu.map_or(256, |t| (t as u16).max(floor));
    let data = variance
        .data
        .iter()
        .map(|&v| if v as u16 >= threshold { 255 } else { 0 })
        .collect();
    let mut mask = Plane::from_vec(img.width, img.height, data).expect("same size");
    mask = close(&open(&mask, p.open_radius), p.close_radius);
    if p.fill_holes && !mask.is_empty() {
        mask = fill_holes(&mask);
        mask = fill_broken_outlines(&mask, p.variance_radius as u8 + 1);
    }
    if p.peel_edges {
        let m = p.variance_radius;
        mask = peel_edges(img, &mask, m + 1, 4 * m + 4, 2.25);
    }
    mask = remove_small(&mask, p.min_area.max(1));
    let (mut labels, n) = label(&mask, Connectivity::Eight);
    let cells = if p.absorb_rings {
        let (n, starts) = absorb_rings(&mut labels, n);
        describe_cells_from(&labels, n, Some(&starts))
    } else {
        describe_cells(&labels, n)
    };
    Segmentation {
        variance,
        variance_max,
        noise,
        histogram,
        otsu,
        threshold,
        mask,
        labels,
        cells,
    }
}

/// Per-cell figures of a label image with labels `1..=n`.
pub fn describe_cells(labels: &Plane<u32>, n: u32) -> Vec<Cell> {
    describe_cells_from(labels, n, None)
}

/// [`describe_cells`] with the boundary trace of label `i` starting at `starts[i]` (a
/// raster-first pixel of the piece whose boundary is the contour) instead of the label's
/// own raster-first pixel.
pub fn describe_cells_from(labels: &Plane<u32>, n: u32, starts: Option<&[[u32; 2]]>) -> Vec<Cell> {
    struct Acc {
        area: u64,
        sx: f64,
        sy: f64,
        bbox: BoundingBox,
        first: [u32; 2],
    }
    let mut acc: Vec<Option<Acc>> = (0..=n).map(|_| None).collect();
    for y in 0..labels.height {
        label::for_each_labelled(labels.row(y), |x, l| {
            let (x, y) = (x as u32, y as u32);
            let a = acc[l as usize].get_or_insert(Acc {
                area: 0,
                sx: 0.0,
                sy: 0.0,
                bbox: BoundingBox {
                    x0: x,
                    y0: y,
                    x1: x,
                    y1: y,
                },
                first: [x, y],
            });
            a.area += 1;
            a.sx += x as f64;
            a.sy += y as f64;
            a.bbox.x0 = a.bbox.x0.min(x);
            a.bbox.x1 = a.bbox.x1.max(x);
            a.bbox.y1 = y;
        });
    }
    acc.into_iter()
        .enumerate()
        .filter_map(|(id, a)| {
            let a = a?;
            let start = starts.and_then(|s| s.get(id).copied()).unwrap_or(a.first);
            let contour = trace_boundary(labels, id as u32, start);
            Some(Cell {
                id: id as u32,
                area: a.area,
                centroid: [a.sx / a.area as f64, a.sy / a.area as f64],
                bbox: a.bbox,
                perimeter: chain_length(&contour),
                contour,
            })
        })
        .collect()
}

/// Dice overlap `2|A∩B| / (|A|+|B|)` of two masks' non-zero pixels (1 when both are empty).
pub fn dice(a: &Mask, b: &Mask) -> f64 {
    assert_eq!((a.width, a.height), (b.width, b.height));
    let (mut both, mut na, mut nb) = (0u64, 0u64, 0u64);
    for (&x, &y) in a.data.iter().zip(&b.data) {
        na += (x != 0) as u64;
        nb += (y != 0) as u64;
        both += (x != 0 && y != 0) as u64;
    }
    if na + nb == 0 {
        1.0
    } else {
        2.0 * both as f64 / (na + nb) as f64
    }
}

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
    let (_, n) = label(truth, Connectivity::Eight);
    TruthScore {
        dice: dice(mask, truth),
        truth_cells: n,
        found_cells: found,
        count_error: if n == 0 {
            if found == 0 { 0.0 } else { f64::INFINITY }
        } else {
            found as f64 / n as f64 - 1.0
        },
    }
}

/// Test masks drawn as text: `#` on, anything else off.
#[cfg(test)]
mod testutil {
    use schemas::{Mask, Plane};

    pub fn mask(rows: &[&str]) -> Mask {
        let w = rows[0].len();
        let data = rows
            .iter()
            .flat_map(|r| r.bytes().map(|b| if b == b'#' { 255 } else { 0 }))
            .collect();
        Plane::from_vec(w, rows.len(), data).unwrap()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A smooth noisy background with textured discs; returns the image and the discs.
    fn scene(seed: u64) -> (Plane<u8>, Vec<(f64, f64, f64)>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (w, h) = (200, 150);
        let discs = vec![(50.0, 40.0, 18.0), (140.0, 60.0, 25.0), (80.0, 115.0, 14.0)];
        let mut img = Plane::filled(w, h, 0u8);
        for y in 0..h {
            for x in 0..w {
                let mut v = 120.0 + 0.1 * x as f64 + rng.random_range(-2.0..2.0);
                for &(cx, cy, r) in &discs {
                    if (x as f64 - cx).hypot(y as f64 - cy) <= r {
                        v += rng.random_range(-40.0..40.0);
                    }
                }
                *img.get_mut(x, y) = v.clamp(0.0, 255.0) as u8;
            }
        }
        (img, discs)
    }

    #[test]
    fn finds_textured_discs_on_a_smooth_background() {
        let (img, discs) = scene(3);
        let s = segment(&img, &SegmentParams::default());
        assert_eq!(s.cells.len(), 3);
        for (cell, &(cx, cy, r)) in s.cells.iter().zip(&discs) {
            assert!((cell.centroid[0] - cx).abs() < 1.0, "{:?}", cell.centroid);
            assert!((cell.centroid[1] - cy).abs() < 1.0, "{:?}", cell.centroid);
            let true_area = std::f64::consts::PI * r * r;
            // The variance window widens a cell by up to M = 3 px all round; peeling takes
            // that back to within a few per cent.
            assert!(
                (cell.area as f64 / true_area - 1.0).abs() < 0.05,
                "area {} vs {true_area}",
                cell.area
            );
            let plain = segment(
                &img,
                &SegmentParams {
                    peel_edges: false,
                    ..SegmentParams::default()
                },
            );
            let fat = plain
                .cells
                .iter()
                .find(|c| {
                    c.bbox.x0 <= cell.bbox.x0
                        && c.bbox.x1 >= cell.bbox.x1
                        && c.bbox.y0 <= cell.bbox.y0
                })
                .expect("same cell unpeeled");
            assert!(
                fat.area as f64 > true_area
                    && (fat.area as f64) < std::f64::consts::PI * (r + 3.5).powi(2),
                "unpeeled area {} vs {true_area}",
                fat.area
            );
            // The contour starts at the first raster pixel and runs all round the cell.
            assert_eq!(cell.contour[0][1], cell.bbox.y0);
            let per_circle = 2.0 * std::f64::consts::PI * r;
            assert!(
                cell.perimeter > 0.9 * per_circle && cell.perimeter < 1.3 * (per_circle + 22.0)
            );
        }
        assert!(s.otsu.is_some());
    }

    #[test]
    fn flat_and_noise_only_images_have_no_cells() {
        let flat = Plane::filled(64, 48, 90u8);
        let s = segment(&flat, &SegmentParams::default());
        assert!(s.cells.is_empty());
        assert_eq!((s.otsu, s.threshold), (None, 256));
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let data = (0..64 * 48).map(|_| rng.random_range(100..104)).collect();
        let noise = Plane::from_vec(64, 48, data).unwrap();
        let s = segment(&noise, &SegmentParams::default());
        assert!(s.cells.is_empty(), "{} cells in noise", s.cells.len());
    }

    /// Gaussian noise of `sigma` grey levels about 120 over `w × h`, discs of texture
    /// `texture` (its own standard deviation) added where `discs` lie.
    fn noisy(seed: u64, sigma: f64, texture: f64, discs: &[(f64, f64, f64)]) -> Plane<u8> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut gauss = |s: f64| {
            let (u, v): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random());
            s * (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        };
        let (w, h) = (240, 180);
        let mut img = Plane::filled(w, h, 0u8);
        for y in 0..h {
            for x in 0..w {
                let mut v = 120.0 + gauss(sigma);
                if discs
                    .iter()
                    .any(|&(cx, cy, r)| (x as f64 - cx).hypot(y as f64 - cy) <= r)
                {
                    v += gauss(texture);
                }
                *img.get_mut(x, y) = v.round().clamp(0.0, 255.0) as u8;
            }
        }
        img
    }

    #[test]
    fn the_noise_is_read_from_the_quietest_tenth() {
        for sigma in [1.0, 1.5, 3.0] {
            let img = noisy(7, sigma, 6.0, &[(80.0, 90.0, 40.0), (170.0, 70.0, 30.0)]);
            let s = segment(&img, &SegmentParams::default());
            // The tenth sits at the low tail of a 49-pixel window's spread: 0.85–1 σ.
            assert!(
                s.noise > 0.8 * sigma as f32 && s.noise < 1.02 * sigma as f32,
                "σ {sigma}: read {}",
                s.noise
            );
        }
    }

    #[test]
    fn the_floor_follows_the_noise() {
        let discs = [(70.0, 60.0, 30.0), (170.0, 110.0, 35.0)];
        // Blurred cells: texture 3.3 over noise 1.5 (3.6 in all), under the old fixed floor
        // of 4.
        let faint = noisy(3, 1.5, 3.3, &discs);
        let s = segment(&faint, &SegmentParams::default());
        assert_eq!(s.cells.len(), 2, "{:?}", s.cells.iter().map(|c| c.area));
        for (cell, &(_, _, r)) in s.cells.iter().zip(&discs) {
            let area = std::f64::consts::PI * r * r;
            // At this contrast the outermost pixels look like background: 16 % short.
            let ratio = cell.area as f64 / area;
            assert!((0.8..1.1).contains(&ratio), "{} vs {area}", cell.area);
        }
        let fixed = SegmentParams {
            min_std: 4.0,
            noise_floor: 0.0,
            ..SegmentParams::default()
        };
        let lost: u64 = segment(&faint, &fixed).cells.iter().map(|c| c.area).sum();
        assert!(lost < 1000, "{lost} px under a fixed floor of 4");
        // A noisy camera (σ 3) alone: the floor rises with it and finds nothing.
        let noise = noisy(4, 3.0, 0.0, &[]);
        assert!(segment(&noise, &SegmentParams::default()).cells.is_empty());
    }

    #[test]
    fn dice_of_known_overlaps() {
        let a = Plane::from_vec(4, 1, vec![255, 255, 0, 0]).unwrap();
        let b = Plane::from_vec(4, 1, vec![0, 255, 255, 0]).unwrap();
        assert_eq!(dice(&a, &b), 0.5);
        assert_eq!(dice(&a, &a), 1.0);
        let z = Plane::filled(4, 1, 0u8);
        assert_eq!(dice(&z, &z), 1.0);
        assert_eq!(dice(&a, &z), 0.0);
    }
}
