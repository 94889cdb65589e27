//! The cell logic every stage after segmentation shares: pairing the cells of both views
//! ([`pair_cells`]), the crop each pair is matched in ([`crop_of`], [`crop`]), the cell-only
//! maps put back where each cell owns the pixels ([`compose`]), masks ([`mask_of`]) and
//! distances to a cell ([`distance_to_cell`]). The match node cuts the crops; the
//! triangulate node composes their maps and measures the cells.

use schemas::{Cell, DisparityMap, DisparityRange, DisparityTiles, INVALID_DISPARITY, Mask, Plane};

/// Pixels matched around each cell mask by default: its substrate ring.
pub const DEFAULT_MARGIN: u8 = 8;

/// Pixels by which a pair's centroid offset may leave the range (segmentation jitter).
pub const PAIRING_SLACK: f64 = 4.0;

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

/// The crop a cell pair is matched in: `[x0, x1) × [y0, y1)` of both views, and the part of
/// `range` it can hold (`None` when it is too narrow for any).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Crop {
    /// First column.
    pub x0: usize,
    /// First row.
    pub y0: usize,
    /// One past the last column.
    pub x1: usize,
    /// One past the last row.
    pub y1: usize,
    /// Disparities searched in it.
    pub range: Option<DisparityRange>,
}

/// The crop of the pair `l`–`r` in a `w × h` frame: both boxes, `margin` around them, and
/// room for every disparity of `range` on each side.
pub fn crop_of(
    l: &Cell,
    r: &Cell,
    range: DisparityRange,
    margin: u8,
    (w, h): (usize, usize),
) -> Crop {
    let (lb, rb) = (l.bbox, r.bbox);
    let m = margin as i64;
    let (dmin, dmax) = (range.min as i64, range.max as i64);
    let y0 = (lb.y0.min(rb.y0) as i64 - m).max(0) as usize;
    let y1 = ((lb.y1.max(rb.y1) as i64 + m + 1) as usize).min(h);
    let x0 = (lb.x0 as i64 - m - dmax)
        .min(rb.x0 as i64 - m + dmin)
        .max(0) as usize;
    let x1 = ((lb.x1 as i64 + m - dmin).max(rb.x1 as i64 + m + dmax) + 1).min(w as i64) as usize;
    // A narrow crop cannot hold the whole range: search what fits.
    let cw = (x1 - x0) as i32;
    let r = DisparityRange::new(range.min.max(-(cw - 1)), range.max.min(cw - 1));
    Crop {
        x0,
        y0,
        x1,
        y1,
        range: (r.min < r.max).then_some(r),
    }
}

/// The rectangle `[x0, x1) × [y0, y1)` of `p`.
pub fn crop<T: Copy>(p: &Plane<T>, x0: usize, y0: usize, x1: usize, y1: usize) -> Plane<T> {
    let data = (y0..y1)
        .flat_map(|y| p.row(y)[x0..x1].iter().copied())
        .collect();
    Plane::from_vec(x1 - x0, y1 - y0, data).expect("size")
}

/// Cell-only maps in frame coordinates: each pair's tile where its cell owns the pixel.
#[derive(Clone, Debug)]
pub struct Composed {
    /// The final (post-processed) left disparity: valid only in and around the cells.
    pub disparity: DisparityMap,
    /// After the LR check, on the same pixels.
    pub raw: DisparityMap,
    /// 255 where the LR check failed on those pixels.
    pub occlusion: Mask,
    /// `(left index, right index)` of each tile's cell pair, in tile order.
    pub pairs: Vec<(usize, usize)>,
}

/// 255 where `labels` holds a cell.
pub fn mask_of(labels: &Plane<u32>) -> Mask {
    Plane::from_vec(
        labels.width,
        labels.height,
        labels
            .data
            .iter()
            .map(|&v| if v > 0 { 255 } else { 0 })
            .collect(),
    )
    .expect("size")
}

/// Pastes each cell pair's tile of the post-processed (`post`) and LR-checked (`checked`)
/// maps where its left cell owns the pixel: the cell itself, and the background within the
/// tiles' margin of it (a later pair's ring wins where two overlap). `labels`, its
/// [`mask_of`] and `cells` are the left view's; `right` the right view's cells.
pub fn compose(
    (labels, mask): (&Plane<u32>, &Mask),
    (cells, right): (&[Cell], &[Cell]),
    post: &DisparityTiles,
    checked: &DisparityTiles,
) -> Result<Composed, String> {
    let (w, h) = (labels.width, labels.height);
    for (what, t) in [("final", post), ("checked", checked)] {
        if (t.width, t.height) != (w, h) {
            return Err(format!(
                "{what} disparity tiles of {}×{} for labels of {w}×{h}",
                t.width, t.height
            ));
        }
        if t.side != schemas::Side::Left {
            return Err(format!(
                "the {what} tiles are right-based; cells are measured on left-based ones (validate/left)"
            ));
        }
    }
    if post.tiles.len() != checked.tiles.len() || post.margin != checked.margin {
        return Err(format!(
            "{} final tiles (margin {}) but {} checked ones (margin {}); both must come from one match",
            post.tiles.len(),
            post.margin,
            checked.tiles.len(),
            checked.margin
        ));
    }
    let margin = post.margin;
    let mut disparity = Plane::filled(w, h, INVALID_DISPARITY);
    let mut raw = Plane::filled(w, h, INVALID_DISPARITY);
    let mut occlusion = Plane::filled(w, h, 0u8);
    let index = |list: &[Cell], id: u32, view: &str| {
        list.iter()
            .position(|c| c.id == id)
            .ok_or_else(|| format!("a tile names {view} cell {id}, which the cell list lacks"))
    };
    let mut pairs = Vec::new();
    for (t, c) in post.tiles.iter().zip(&checked.tiles) {
        let Some((lid, rid)) = t.cells else {
            return Err("a whole-frame tile among cell tiles".into());
        };
        if (t.x, t.y, t.map.width, t.map.height, t.cells)
            != (c.x, c.y, c.map.width, c.map.height, c.cells)
        {
            return Err(format!(
                "the final and checked tiles of cell {lid} differ in place"
            ));
        }
        pairs.push((index(cells, lid, "left")?, index(right, rid, "right")?));
        if t.map.is_empty() {
            continue;
        }
        let (x0, y0, x1, y1) = (t.x, t.y, t.x + t.map.width, t.y + t.map.height);
        let dist = distance_to_cell(labels, lid, (x0, y0), (x1, y1));
        let (support, (sx, sy)) = dilated_near(mask, margin, (x0, y0), (x1, y1));
        for y in y0..y1 {
            for x in x0..x1 {
                // Own cell plus the ring around it (other cells get their own crop).
                let own = *labels.get(x, y) == lid
                    || (*labels.get(x, y) == 0
                        && *support.get(x - sx, y - sy) != 0
                        && dist.get_pixel((x - x0) as u32, (y - y0) as u32).0[0] <= margin);
                if !own {
                    continue;
                }
                *disparity.get_mut(x, y) = *t.map.get(x - x0, y - y0);
                let r = *c.map.get(x - x0, y - y0);
                *raw.get_mut(x, y) = r;
                *occlusion.get_mut(x, y) = if r.is_finite() { 0 } else { 255 };
            }
        }
    }
    Ok(Composed {
        disparity,
        raw,
        occlusion,
        pairs,
    })
}

/// `mask` dilated by a disc of `radius` over `[x0, x1) × [y0, y1)`: the dilation of the
/// crop grown by `radius` (every pixel that can reach the window), and where that crop
/// starts. The same values as dilating the whole frame there, for a cell's tile instead of
/// 1280×1024 pixels per frame.
fn dilated_near(
    mask: &Mask,
    radius: u8,
    (x0, y0): (usize, usize),
    (x1, y1): (usize, usize),
) -> (Mask, (usize, usize)) {
    let r = radius as usize;
    let (cx0, cy0) = (x0.saturating_sub(r), y0.saturating_sub(r));
    let (cx1, cy1) = ((x1 + r).min(mask.width), (y1 + r).min(mask.height));
    (
        segment::dilate(&crop(mask, cx0, cy0, cx1, cy1), radius),
        (cx0, cy0),
    )
}

/// Chebyshev distance (px, capped at 255) from each pixel of the window `[x0, x1) × [y0, y1)`
/// to the nearest pixel of cell `id`, which must lie wholly inside the window.
pub fn distance_to_cell(
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

#[cfg(test)]
mod tests {
    use super::*;
    use schemas::BoundingBox;

    #[test]
    fn a_window_dilated_alone_is_the_frame_dilated_there() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        for case in 0..200 {
            let (w, h) = (rng.random_range(1..70), rng.random_range(1..70));
            let density = [0.002, 0.02, 0.2][case % 3];
            let data = (0..w * h)
                .map(|_| if rng.random_bool(density) { 255 } else { 0 })
                .collect();
            let mask = Plane::from_vec(w, h, data).unwrap();
            let radius = rng.random_range(0..9u8);
            let whole = segment::dilate(&mask, radius);
            let (x0, y0) = (rng.random_range(0..w), rng.random_range(0..h));
            let (x1, y1) = (rng.random_range(x0 + 1..=w), rng.random_range(y0 + 1..=h));
            let (near, (sx, sy)) = dilated_near(&mask, radius, (x0, y0), (x1, y1));
            for y in y0..y1 {
                for x in x0..x1 {
                    assert_eq!(
                        near.get(x - sx, y - sy),
                        whole.get(x, y),
                        "case {case}: ({x}, {y}) of {w}×{h}, radius {radius}"
                    );
                }
            }
        }
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
    fn cells_pair_by_rows_size_and_offset_each_once() {
        let left = [
            cell(1, 10, 10, 19, 19),
            cell(2, 50, 10, 59, 19),
            cell(3, 10, 60, 12, 62),
        ];
        // Right: cell 1 shifted by 3, cell 2 by 40 (outside −4..12), a small one.
        let right = [
            cell(1, 7, 10, 16, 19),
            cell(2, 10, 11, 19, 20),
            cell(3, 10, 60, 29, 79),
        ];
        let pairs = pair_cells(&left, &right, DisparityRange::new(-4, 12), PAIRING_SLACK);
        // Left 1 takes right 1 (offset 3, same rows) over right 2 (one row off).
        assert_eq!(pairs, [(0, 0)]);
    }

    #[test]
    fn a_crop_holds_both_boxes_the_margin_and_the_range() {
        let (l, r) = (cell(1, 40, 20, 49, 29), cell(1, 37, 20, 46, 29));
        let c = crop_of(&l, &r, DisparityRange::new(-4, 12), 8, (100, 60));
        // Left: 40 − 8 − 12 = 20; right: 37 − 8 − 4 = 25 → 20. Right end: max(49 + 8 + 4,
        // 46 + 8 + 12) + 1 = 67.
        assert_eq!((c.x0, c.y0, c.x1, c.y1), (20, 12, 67, 38));
        assert_eq!(c.range, Some(DisparityRange::new(-4, 12)));
        // At the frame's edge the crop is clipped, and a narrow one narrows the range.
        let c = crop_of(
            &cell(1, 0, 0, 1, 1),
            &cell(1, 0, 0, 1, 1),
            DisparityRange::new(0, 12),
            0,
            (4, 4),
        );
        assert_eq!((c.x0, c.x1), (0, 4));
        assert_eq!(c.range, Some(DisparityRange::new(0, 3)));
        let c = crop_of(
            &cell(1, 0, 0, 0, 0),
            &cell(1, 0, 0, 0, 0),
            DisparityRange::new(2, 12),
            0,
            (1, 1),
        );
        assert_eq!(c.range, None);
    }
}
