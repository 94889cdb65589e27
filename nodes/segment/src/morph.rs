//! Mask clean-up: hole filling, small-blob removal, opening and closing.

use crate::label::{Components, Connectivity, components_where, label};
use image::GrayImage;
use imageproc::distance_transform::Norm;
use schemas::{Mask, Plane};

/// Sets every background pixel that is not 4-connected to the image border (a hole in an
/// 8-connected foreground) to foreground.
pub fn fill_holes(mask: &Mask) -> Mask {
    let (w, h) = (mask.width, mask.height);
    let bg = components_where(mask, |&v| v == 0, Connectivity::Four);
    let mut outside = vec![false; bg.n as usize + 1];
    for &(y, x0, x1, l) in &bg.runs {
        outside[l as usize] |= y == 0 || y + 1 == h || x0 == 0 || x1 == w;
    }
    with_runs(mask, &bg, |l| !outside[l as usize])
}

/// `mask` at 255 wherever it is non-zero, 0 elsewhere.
fn binary(mask: &Mask) -> Mask {
    let data = mask
        .data
        .iter()
        .map(|&m| if m != 0 { 255 } else { 0 })
        .collect();
    Plane::from_vec(mask.width, mask.height, data).expect("same size")
}

/// `mask` at 255 wherever it is non-zero, and on every run of `parts` whose component
/// `keep` picks.
fn with_runs(mask: &Mask, parts: &Components, keep: impl Fn(u32) -> bool) -> Mask {
    let mut out = binary(mask);
    for &(y, x0, x1, l) in &parts.runs {
        if keep(l) {
            out.row_mut(y)[x0..x1].fill(255);
        }
    }
    out
}

/// Fills the inside of outlines broken by gaps narrower than about `2·radius` px, which
/// [`fill_holes`] leaves open: a tall cell's membrane rim, seen at a slant by one camera,
/// thins to nothing on one side, and under a faint inner texture the variance threshold
/// keeps only a horseshoe. What a closing with a disc of `radius` adds, with the holes it
/// then encloses, joins the mask wherever it holds such a hole and borders one component
/// only; the closing's bridges between neighbouring cells and its rounding of bays stay out.
///
/// Worked out in boxes around the cells (with what lies within reach of them) rather than
/// over the whole frame: a 1280×1024 view with ten cells 3.0–3.3 → 0.8–0.9 ms, the same
/// pixels (tested against the whole-frame version).
pub fn fill_broken_outlines(mask: &Mask, radius: u8) -> Mask {
    if radius == 0 {
        return mask.clone();
    }
    let regions =
        outline_regions(mask, radius).unwrap_or_else(|| vec![[0, 0, mask.width, mask.height]]);
    fill_broken_outlines_in(mask, radius, &regions)
}

/// Most components [`outline_regions`] groups; beyond, the whole frame is one region.
const MAX_GROUPED_COMPONENTS: usize = 400;

/// Disjoint boxes `[x0, y0, x1, y1)` that together hold every component of `mask` with the
/// background within `2·radius + 2` px of it, components nearer each other than that in one
/// box: what [`fill_broken_outlines`] adds to a component depends on the mask within
/// `2·radius` px of it only, so each box can be worked on alone. `None` where the boxes would
/// cover more than half the frame, or the components are too many to group (specks of
/// noise): the whole frame is then no slower.
fn outline_regions(mask: &Mask, radius: u8) -> Option<Vec<[usize; 4]>> {
    let (w, h) = (mask.width, mask.height);
    let reach = 2 * radius as usize + 2;
    let parts = components_where(mask, |&v| v != 0, Connectivity::Eight);
    if parts.n as usize > MAX_GROUPED_COMPONENTS {
        return None;
    }
    let mut boxes = vec![[usize::MAX, usize::MAX, 0, 0]; parts.n as usize + 1];
    for &(y, x0, x1, l) in &parts.runs {
        let b = &mut boxes[l as usize];
        *b = [b[0].min(x0), b[1].min(y), b[2].max(x1), b[3].max(y + 1)];
    }
    let mut regions: Vec<[usize; 4]> = boxes[1..]
        .iter()
        .map(|b| {
            [
                b[0].saturating_sub(reach),
                b[1].saturating_sub(reach),
                (b[2] + reach).min(w),
                (b[3] + reach).min(h),
            ]
        })
        .collect();
    // Boxes that meet are merged until none do (a few dozen cells: a quadratic sweep is
    // plenty).
    let meet =
        |a: &[usize; 4], b: &[usize; 4]| a[0] < b[2] && b[0] < a[2] && a[1] < b[3] && b[1] < a[3];
    let mut merged = true;
    while merged {
        merged = false;
        let mut i = 0;
        while i < regions.len() {
            let mut j = i + 1;
            while j < regions.len() {
                if meet(&regions[i], &regions[j]) {
                    let b = regions.swap_remove(j);
                    let a = &mut regions[i];
                    *a = [
                        a[0].min(b[0]),
                        a[1].min(b[1]),
                        a[2].max(b[2]),
                        a[3].max(b[3]),
                    ];
                    merged = true;
                } else {
                    j += 1;
                }
            }
            i += 1;
        }
    }
    let area: usize = regions.iter().map(|b| (b[2] - b[0]) * (b[3] - b[1])).sum();
    (2 * area <= w * h).then_some(regions)
}

/// [`fill_broken_outlines`] worked out in each of `regions` (disjoint boxes, see
/// [`outline_regions`]) on its own.
fn fill_broken_outlines_in(mask: &Mask, radius: u8, regions: &[[usize; 4]]) -> Mask {
    let mut any_added = false;
    let mut kept: Vec<(usize, usize, usize)> = Vec::new();
    for &[x0, y0, x1, y1] in regions {
        let crop = if [x0, y0, x1, y1] == [0, 0, mask.width, mask.height] {
            mask.clone()
        } else {
            let data = (y0..y1)
                .flat_map(|y| mask.row(y)[x0..x1].iter().copied())
                .collect();
            Plane::from_vec(x1 - x0, y1 - y0, data).expect("the region's size")
        };
        if let Some(runs) = broken_outline_runs(&crop, radius) {
            any_added = true;
            kept.extend(runs.into_iter().map(|(y, a, b)| (y + y0, a + x0, b + x0)));
        }
    }
    if !any_added {
        return mask.clone();
    }
    let mut out = binary(mask);
    for (y, x0, x1) in kept {
        out.row_mut(y)[x0..x1].fill(255);
    }
    out
}

/// The runs `(y, x0, x1)` that [`fill_broken_outlines`] adds to `mask`; `None` where the
/// closing adds nothing at all.
fn broken_outline_runs(mask: &Mask, radius: u8) -> Option<Vec<(usize, usize, usize)>> {
    let closed = close_square(mask, radius);
    let filled = fill_holes(&closed);
    let (w, h) = (mask.width, mask.height);
    let added = Plane::from_vec(
        w,
        h,
        filled
            .data
            .iter()
            .zip(&mask.data)
            .map(|(&f, &m)| f != 0 && m == 0)
            .collect::<Vec<bool>>(),
    )
    .expect("same size");
    let parts = components_where(&added, |&a| a, Connectivity::Eight);
    let n = parts.n;
    if n == 0 {
        return None;
    }
    let (cells, _) = label(mask, Connectivity::Eight);
    // Per added part: whether it holds a hole of the closed mask, and the one component it
    // borders (`None` before any, `Some(u32::MAX)` for more than one): read along each of
    // its runs and the pixels around the run.
    let mut hole = vec![false; n as usize + 1];
    let mut border: Vec<Option<u32>> = vec![None; n as usize + 1];
    for &(y, x0, x1, l) in &parts.runs {
        let p = l as usize;
        hole[p] |= closed.row(y)[x0..x1].contains(&0);
        let (lo, hi) = (x0.saturating_sub(1), (x1 + 1).min(w));
        let above_below = [y.checked_sub(1), (y + 1 < h).then_some(y + 1)];
        let ends = [x0.checked_sub(1), (x1 < w).then_some(x1)];
        let around = above_below
            .into_iter()
            .flatten()
            .flat_map(|v| cells.row(v)[lo..hi].iter())
            .chain(ends.into_iter().flatten().map(|x| cells.get(x, y)));
        for &c in around {
            if c != 0 {
                border[p] = match border[p] {
                    None => Some(c),
                    Some(b) if b == c => Some(b),
                    Some(_) => Some(u32::MAX),
                };
            }
        }
    }
    Some(
        parts
            .runs
            .iter()
            .filter(|r| hole[r.3 as usize] && border[r.3 as usize].is_some_and(|b| b != u32::MAX))
            .map(|&(y, x0, x1, _)| (y, x0, x1))
            .collect(),
    )
}

/// Closing with a square of half-width `radius`, the image padded so that nothing sticks to
/// its border. A square bridges a gap between the ends of an arc as wide as itself, where a
/// disc's rounded edge leaves the gap's outer corners open.
///
/// Separable passes over rows of bits (64 pixels a word), each window an OR or AND of
/// doubling shifts: the dilation over the image grown by `radius` on every side (outside it
/// the mask is background), then the erosion of that, back on the image; the same pixels as
/// imageproc's distance-transform closing of a padded copy (the test below). On a
/// 1280×1024 view, 1.7–1.9 ms with running counts of bytes before.
fn close_square(mask: &Mask, radius: u8) -> Mask {
    let r = radius as usize;
    let (w, h) = (mask.width, mask.height);
    let span = 2 * r + 1;
    // Rows of bits, 64 pixels a word. Bit k of a row stands for x = k − o, o a whole number
    // of words of at least 3r, so that every window read below lies inside the row and
    // the image packs word by word; rows t stand for y = t − 2r likewise.
    let o = (3 * r).next_multiple_of(64);
    let bits = o + w + 3 * r;
    let nw = bits.div_ceil(64);
    let rows = h + 4 * r;
    let mut grid = vec![0u64; rows * nw];
    for (y, row) in mask.data.chunks_exact(w.max(1)).enumerate().take(h) {
        let out = &mut grid[(y + 2 * r) * nw + o / 64..][..w.div_ceil(64)];
        for (word, chunk) in out.iter_mut().zip(row.chunks(64)) {
            *word = chunk
                .iter()
                .enumerate()
                .fold(0, |acc, (i, &v)| acc | (u64::from(v != 0) << i));
        }
    }
    let mut tmp = vec![0u64; nw];
    // Along rows: bit k becomes the OR of bits [k, k + 2r], the dilation of x = k + r − o.
    for row in grid.chunks_exact_mut(nw) {
        forward_bits(row, span, false, &mut tmp);
    }
    // Down columns: row t becomes the OR of rows [t, t + 2r]; then, for the erosion, the
    // AND of rows [t, t + 2r] of that (row y of the result is image row y).
    forward_rows(&mut grid, nw, rows, span, false);
    forward_rows(&mut grid, nw, rows, span, true);
    // Along rows again, the erosion: bit k the AND of bits [k, k + 2r]; image pixel x is
    // bit x + o − 2r (the two windows of 2r + 1 centred on x, each shifted by r), moved to
    // bit x to be unpacked a byte of bits at a time.
    let mut data = vec![0u8; w * h];
    let mut at_x = vec![0u64; nw];
    for (y, out) in data.chunks_exact_mut(w.max(1)).enumerate().take(h) {
        let row = &mut grid[y * nw..][..nw];
        forward_bits(row, span, true, &mut tmp);
        shift_down(row, o - 2 * r, &mut at_x);
        for (bytes, b) in out
            .chunks_mut(8)
            .zip(at_x.iter().flat_map(|w| w.to_le_bytes()))
        {
            bytes.copy_from_slice(&SPREAD[b as usize].to_le_bytes()[..bytes.len()]);
        }
    }
    Plane::from_vec(w, h, data).expect("size")
}

/// Each byte of bits spread to eight bytes of 0 or 255 (the lowest bit first).
const SPREAD: [u64; 256] = {
    let mut t = [0u64; 256];
    let mut b = 0;
    while b < 256 {
        let mut i = 0;
        while i < 8 {
            if b >> i & 1 == 1 {
                t[b] |= 0xFF << (8 * i);
            }
            i += 1;
        }
        b += 1;
    }
    t
};

/// `out` bit `b` = `row` bit `b + s` (bits past the row's end count as 0).
fn shift_down(row: &[u64], s: usize, out: &mut [u64]) {
    let (q, m) = (s / 64, s % 64);
    for (j, o) in out.iter_mut().enumerate() {
        let a = row.get(j + q).copied().unwrap_or(0);
        let b = row.get(j + q + 1).copied().unwrap_or(0);
        *o = if m == 0 {
            a
        } else {
            (a >> m) | (b << (64 - m))
        };
    }
}

/// Bit `b` of `row` (64 to a word, the lowest first) becomes the OR (`and`: the AND) of
/// bits `[b, b + len)`, bits past the row's end counting as 0: by doubling windows.
fn forward_bits(row: &mut [u64], len: usize, and: bool, tmp: &mut [u64]) {
    let mut step = |row: &mut [u64], s: usize| {
        shift_down(row, s, tmp);
        for (v, &t) in row.iter_mut().zip(tmp.iter()) {
            *v = if and { *v & t } else { *v | t };
        }
    };
    let mut k = 1;
    while 2 * k <= len {
        step(row, k);
        k *= 2;
    }
    if len > k {
        step(row, len - k);
    }
}

/// Row `t` of `grid` (`rows` rows of `nw` words) becomes the OR (`and`: the AND) of rows
/// `[t, t + len)`, rows past the last counting as 0: by doubling windows, in place (a row
/// reads only rows below it, not yet changed in that pass).
fn forward_rows(grid: &mut [u64], nw: usize, rows: usize, len: usize, and: bool) {
    let mut pass = |k: usize| {
        for t in 0..rows {
            let (head, tail) = grid.split_at_mut((t + 1) * nw);
            let row = &mut head[t * nw..];
            match (t + k < rows, and) {
                (true, _) => {
                    let below = &tail[(k - 1) * nw..][..nw];
                    for (v, &b) in row.iter_mut().zip(below) {
                        *v = if and { *v & b } else { *v | b };
                    }
                }
                (false, true) => row.fill(0),
                (false, false) => {}
            }
        }
    };
    let mut k = 1;
    while 2 * k <= len {
        pass(k);
        k *= 2;
    }
    if len > k {
        pass(len - k);
    }
}

/// Drops 8-connected blobs of fewer than `min_area` pixels.
pub fn remove_small(mask: &Mask, min_area: usize) -> Mask {
    let c = components_where(mask, |&v| v != 0, Connectivity::Eight);
    let mut area = vec![0usize; c.n as usize + 1];
    for &(_, x0, x1, l) in &c.runs {
        area[l as usize] += x1 - x0;
    }
    let mut out = Plane::filled(mask.width, mask.height, 0u8);
    for &(y, x0, x1, l) in &c.runs {
        if area[l as usize] >= min_area {
            out.row_mut(y)[x0..x1].fill(255);
        }
    }
    out
}

/// Applies an imageproc binary morphology operation with a disc of `radius` (0 = none).
fn disc_op(mask: &Mask, radius: u8, op: fn(&GrayImage, Norm, u8) -> GrayImage) -> Mask {
    if radius == 0 {
        return mask.clone();
    }
    let g = GrayImage::from_raw(mask.width as u32, mask.height as u32, mask.data.clone())
        .expect("size");
    Plane::from_vec(mask.width, mask.height, op(&g, Norm::L2, radius).into_raw()).expect("size")
}

/// Morphological opening with a disc of `radius` (removes specks and thin spurs).
pub fn open(mask: &Mask, radius: u8) -> Mask {
    disc_op(mask, radius, imageproc::morphology::open)
}

/// Morphological closing with a disc of `radius` (bridges small gaps in a cell's outline).
pub fn close(mask: &Mask, radius: u8) -> Mask {
    disc_op(mask, radius, imageproc::morphology::close)
}

/// Dilates with a disc of `radius`: 255 where a mask pixel lies within `radius` (Euclidean),
/// as imageproc's L2 dilation, row by row in bits: a row's bits widened by the disc's
/// half-width at each row offset (`⌊√(r² − dy²)⌋`), the offsets ORed (imageproc's distance
/// transform took over 40 % of the triangulate node's tile composition).
pub fn dilate(mask: &Mask, radius: u8) -> Mask {
    if radius == 0 {
        return mask.clone();
    }
    let (w, h) = (mask.width, mask.height);
    let r = radius as usize;
    // Rows padded by `r` bits on the left, so that widening never reaches before bit 0.
    let nw = (w + 2 * r).div_ceil(64) + 1;
    let half: Vec<usize> = (0..=r).map(|dy| (r * r - dy * dy).isqrt()).collect();
    let mut widths = half.clone();
    widths.sort_unstable();
    widths.dedup();
    // Per row, per distinct half-width `hw`: bit `x` set where a mask pixel of the row lies
    // within `hw` of `x`.
    let (mut tmp, mut padded, mut f) = (vec![0u64; nw], vec![0u64; nw], vec![0u64; nw]);
    let mut wide = vec![0u64; h * widths.len() * nw];
    for y in 0..h {
        padded.fill(0);
        for (x, _) in mask.row(y).iter().enumerate().filter(|(_, v)| **v != 0) {
            let b = x + r;
            padded[b / 64] |= 1 << (b % 64);
        }
        for (k, &hw) in widths.iter().enumerate() {
            f.copy_from_slice(&padded);
            forward_bits(&mut f, 2 * hw + 1, false, &mut tmp);
            let out = &mut wide[(y * widths.len() + k) * nw..][..nw];
            shift_down(&f, r - hw, out);
        }
    }
    let mut out = Plane::filled(w, h, 0u8);
    let mut acc = vec![0u64; nw];
    for y in 0..h {
        acc.fill(0);
        for (dy, &hw) in half.iter().enumerate() {
            let k = widths.binary_search(&hw).expect("listed");
            for v in [y.checked_sub(dy), (dy > 0).then_some(y + dy)]
                .into_iter()
                .flatten()
                .filter(|&v| v < h)
            {
                for (a, &b) in acc
                    .iter_mut()
                    .zip(&wide[(v * widths.len() + k) * nw..][..nw])
                {
                    *a |= b;
                }
            }
        }
        for (x, o) in out.row_mut(y).iter_mut().enumerate() {
            if acc[x / 64] >> (x % 64) & 1 != 0 {
                *o = 255;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::label::{NEIGHBOURS, label_where};

    /// The first hole filling: a label image of the background.
    fn fill_holes_reference(mask: &Mask) -> Mask {
        let (bg, n) = label_where(mask, |&v| v == 0, Connectivity::Four);
        let (w, h) = (mask.width, mask.height);
        let mut outside = vec![false; n as usize + 1];
        for x in 0..w {
            outside[*bg.get(x, 0) as usize] = true;
            outside[*bg.get(x, h - 1) as usize] = true;
        }
        for y in 0..h {
            outside[*bg.get(0, y) as usize] = true;
            outside[*bg.get(w - 1, y) as usize] = true;
        }
        let data = mask
            .data
            .iter()
            .zip(&bg.data)
            .map(|(&m, &l)| {
                if m != 0 || !outside[l as usize] {
                    255
                } else {
                    0
                }
            })
            .collect();
        Plane::from_vec(w, h, data).expect("same size")
    }

    /// The first small-blob removal: a label image of the mask.
    fn remove_small_reference(mask: &Mask, min_area: usize) -> Mask {
        let (labels, n) = label(mask, Connectivity::Eight);
        let mut area = vec![0usize; n as usize + 1];
        for &l in &labels.data {
            area[l as usize] += 1;
        }
        let data = labels
            .data
            .iter()
            .map(|&l| {
                if l != 0 && area[l as usize] >= min_area {
                    255
                } else {
                    0
                }
            })
            .collect();
        Plane::from_vec(mask.width, mask.height, data).expect("same size")
    }

    /// The first broken-outline filling: label images of the added parts and the mask.
    fn fill_broken_outlines_reference(mask: &Mask, radius: u8) -> Mask {
        if radius == 0 {
            return mask.clone();
        }
        let closed = close_square(mask, radius);
        let filled = fill_holes_reference(&closed);
        let (w, h) = (mask.width, mask.height);
        let added = Plane::from_vec(
            w,
            h,
            filled
                .data
                .iter()
                .zip(&mask.data)
                .map(|(&f, &m)| f != 0 && m == 0)
                .collect::<Vec<bool>>(),
        )
        .expect("same size");
        let (parts, n) = label_where(&added, |&a| a, Connectivity::Eight);
        if n == 0 {
            return mask.clone();
        }
        let (cells, _) = label(mask, Connectivity::Eight);
        // Per added part: whether it holds a hole of the closed mask, and the one component it
        // borders (`None` before any, `Some(u32::MAX)` for more than one).
        let mut hole = vec![false; n as usize + 1];
        let mut border: Vec<Option<u32>> = vec![None; n as usize + 1];
        for y in 0..h {
            for x in 0..w {
                let p = *parts.get(x, y) as usize;
                if p == 0 {
                    continue;
                }
                hole[p] |= *closed.get(x, y) == 0;
                for (dx, dy) in NEIGHBOURS {
                    let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                    if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 {
                        continue;
                    }
                    let c = *cells.get(nx as usize, ny as usize);
                    if c != 0 {
                        border[p] = match border[p] {
                            None => Some(c),
                            Some(b) if b == c => Some(b),
                            Some(_) => Some(u32::MAX),
                        };
                    }
                }
            }
        }
        let keep: Vec<bool> = (0..=n as usize)
            .map(|p| p > 0 && hole[p] && border[p].is_some_and(|b| b != u32::MAX))
            .collect();
        let data = mask
            .data
            .iter()
            .zip(&parts.data)
            .map(|(&m, &p)| if m != 0 || keep[p as usize] { 255 } else { 0 })
            .collect();
        Plane::from_vec(w, h, data).expect("same size")
    }

    /// A small deterministic generator of test cases.
    fn lcg(mut seed: u64) -> impl FnMut() -> usize {
        move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 33) as usize
        }
    }

    /// Draws a ring of radius `r` about `(cx, cy)` into `mask`, open over the `gap` radians
    /// from `turn`: an outline to mend.
    fn ring(mask: &mut Mask, (cx, cy): (f64, f64), r: f64, gap: f64, turn: f64) {
        for y in 0..mask.height {
            for x in 0..mask.width {
                let (dx, dy) = (x as f64 - cx, y as f64 - cy);
                let a = (dy.atan2(dx) - turn).rem_euclid(std::f64::consts::TAU);
                if (dx.hypot(dy) - r).abs() < 0.8 && a > gap {
                    *mask.get_mut(x, y) = 255;
                }
            }
        }
    }

    #[test]
    fn broken_outlines_region_by_region_match_the_whole_frame() {
        let mut rnd = lcg(29);
        let mut regions_seen = 0;
        for case in 0..60 {
            let (w, h) = (120 + rnd() % 120, 90 + rnd() % 90);
            let mut mask = Plane::filled(w, h, 0u8);
            // Broken rings anywhere (some on the border, some close enough to be bridged),
            // one inside a larger one every third case, and a few specks.
            for _ in 0..3 + rnd() % 8 {
                let (cx, cy) = ((rnd() % w) as f64, (rnd() % h) as f64);
                let (r, gap) = (3.0 + (rnd() % 8) as f64, 0.3 + (rnd() % 5) as f64 * 0.2);
                ring(&mut mask, (cx, cy), r, gap, (rnd() % 628) as f64 / 100.0);
                if case % 3 == 0 {
                    ring(&mut mask, (cx, cy), r + 9.0, 0.5, 1.0);
                }
            }
            for _ in 0..rnd() % 12 {
                *mask.get_mut(rnd() % w, rnd() % h) = 255;
            }
            for radius in 1..=4u8 {
                let whole = fill_broken_outlines_reference(&mask, radius);
                if let Some(regions) = outline_regions(&mask, radius) {
                    regions_seen += regions.len();
                    for (i, a) in regions.iter().enumerate() {
                        for b in &regions[i + 1..] {
                            let meet = a[0] < b[2] && b[0] < a[2] && a[1] < b[3] && b[1] < a[3];
                            assert!(!meet, "case {case}: {a:?} and {b:?} overlap");
                        }
                    }
                    assert_eq!(
                        fill_broken_outlines_in(&mask, radius, &regions),
                        whole,
                        "case {case}, radius {radius}: {regions:?}"
                    );
                }
                assert_eq!(fill_broken_outlines(&mask, radius), whole, "case {case}");
            }
        }
        assert!(
            regions_seen > 300,
            "{regions_seen} regions: the cases barely test them"
        );
    }

    #[test]
    fn run_based_filling_and_removal_match_the_label_images() {
        let mut rnd = lcg(11);
        let (mut filled, mut removed, mut outlined) = (0, 0, 0);
        for case in 0..200 {
            let (w, h) = match case % 2 {
                0 => (1 + rnd() % 40, 1 + rnd() % 30),
                _ => (20 + rnd() % 30, 20 + rnd() % 30),
            };
            let density = 20 + rnd() % 60;
            // Values other than 255 too: any non-zero pixel is foreground.
            let mut mask = Plane::from_vec(
                w,
                h,
                (0..w * h)
                    .map(|_| {
                        if rnd() % 100 < density {
                            [1, 255][rnd() % 2]
                        } else {
                            0
                        }
                    })
                    .collect(),
            )
            .expect("size");
            // Every other case: sparse specks and rings with gaps (outlines to mend).
            if case % 2 == 1 {
                mask.data
                    .iter_mut()
                    .for_each(|v| *v = u8::from(rnd().is_multiple_of(40)) * 255);
                for _ in 0..2 + rnd() % 4 {
                    let (cx, cy) = ((rnd() % w) as f64, (rnd() % h) as f64);
                    let (r, gap) = (3.0 + (rnd() % 6) as f64, 0.3 + (rnd() % 5) as f64 * 0.2);
                    let turn = (rnd() % 628) as f64 / 100.0;
                    ring(&mut mask, (cx, cy), r, gap, turn);
                }
            }
            let a = fill_holes(&mask);
            assert_eq!(a, fill_holes_reference(&mask), "holes, case {case}");
            filled += a
                .data
                .iter()
                .zip(&mask.data)
                .filter(|(a, m)| **a != 0 && **m == 0)
                .count();
            let radius = (rnd() % 4) as u8;
            let c = fill_broken_outlines(&mask, radius);
            assert_eq!(
                c,
                fill_broken_outlines_reference(&mask, radius),
                "outlines, case {case}"
            );
            outlined += c
                .data
                .iter()
                .zip(&a.data)
                .filter(|(c, a)| **c != 0 && **a == 0)
                .count();
            let min_area = rnd() % 8;
            let b = remove_small(&mask, min_area);
            assert_eq!(
                b,
                remove_small_reference(&mask, min_area),
                "small, case {case}"
            );
            removed += b
                .data
                .iter()
                .zip(&mask.data)
                .filter(|(b, m)| **b == 0 && **m != 0)
                .count();
        }
        assert!(
            filled > 100 && removed > 100 && outlined > 300,
            "{filled} filled, {removed} removed, {outlined} more inside broken outlines"
        );
    }

    /// The first [`close_square`]: imageproc's closing of a padded copy.
    fn close_square_reference(mask: &Mask, radius: u8) -> Mask {
        let pad = radius as usize + 1;
        let (w, h) = (mask.width, mask.height);
        let g = GrayImage::from_fn((w + 2 * pad) as u32, (h + 2 * pad) as u32, |x, y| {
            let (x, y) = (x as usize, y as usize);
            let inside = (pad..pad + w).contains(&x) && (pad..pad + h).contains(&y);
            image::Luma([if inside {
                *mask.get(x - pad, y - pad)
            } else {
                0
            }])
        });
        let c = imageproc::morphology::close(&g, Norm::LInf, radius);
        let data = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| c.get_pixel((x + pad) as u32, (y + pad) as u32).0[0])
            .collect();
        Plane::from_vec(w, h, data).expect("size")
    }
    use crate::testutil::mask;

    /// A `w × h` mask, each pixel on (255) with probability `density`.
    fn random_mask(rng: &mut impl rand::Rng, w: usize, h: usize, density: f64) -> Mask {
        let data = (0..w * h)
            .map(|_| if rng.random_bool(density) { 255 } else { 0 })
            .collect();
        Plane::from_vec(w, h, data).unwrap()
    }

    #[test]
    fn the_bitwise_dilation_matches_imageproc() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for case in 0..300 {
            let (w, h) = match case % 3 {
                0 => (rng.random_range(1..40), rng.random_range(1..40)),
                1 => (rng.random_range(60..200), rng.random_range(1..30)),
                _ => (rng.random_range(1..140), rng.random_range(1..20)),
            };
            let density = [0.005, 0.02, 0.1, 0.4, 0.9][case % 5];
            let m = random_mask(&mut rng, w, h, density);
            let radius = rng.random_range(0..12u8);
            let want = disc_op(&m, radius, imageproc::morphology::dilate);
            assert_eq!(
                dilate(&m, radius).data,
                want.data,
                "{w}×{h}, radius {radius}"
            );
        }
    }

    #[test]
    fn the_bitwise_closing_matches_imageproc() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut changed = 0;
        for case in 0..300 {
            // Rows of one to several words, windows shifted by whole words too.
            let (w, h) = match case % 3 {
                0 => (rng.random_range(1..60), rng.random_range(1..60)),
                1 => (rng.random_range(60..200), rng.random_range(1..40)),
                _ => (rng.random_range(1..140), rng.random_range(1..30)),
            };
            let density = [0.02, 0.1, 0.3, 0.6, 0.95][case % 5];
            let m = random_mask(&mut rng, w, h, density);
            let radius = match case % 3 {
                2 => rng.random_range(7..80u8),
                _ => rng.random_range(0..7u8),
            };
            let fast = close_square(&m, radius);
            assert_eq!(
                fast,
                close_square_reference(&m, radius),
                "{w}×{h}, density {density}, radius {radius}"
            );
            changed += fast
                .data
                .iter()
                .zip(&m.data)
                .filter(|(a, b)| a != b)
                .count();
        }
        assert!(changed > 1000, "the closings change {changed} pixels");
    }

    #[test]
    fn holes_fill_but_bays_open_to_the_border_stay() {
        let m = mask(&["#####.", "#..#..", "#####.", "#.#...", "#.#..."]);
        let f = fill_holes(&m);
        assert_eq!(f, mask(&["#####.", "####..", "#####.", "#.#...", "#.#..."]));
    }

    #[test]
    fn diagonal_gap_does_not_let_a_hole_leak() {
        // The centre touches the outside only through a corner: a hole for 8-connected cells.
        let m = mask(&["##.", "#.#", ".##"]);
        assert_eq!(fill_holes(&m), mask(&["##.", "###", ".##"]));
    }

    #[test]
    fn a_ring_broken_by_a_gap_fills_but_neighbours_and_bays_stay_apart() {
        // A thick ring open by two pixels on its left, and beside it two blocks a gap apart
        // and an open bay: only the ring's inside (with its gap) joins the mask.
        let m = mask(&[
            "....................",
            "..##########........",
            "..##########........",
            "..##......##..##.##.",
            "..##......##..##.##.",
            "..........##..##.##.",
            "..........##..##.##.",
            "..##......##..##.##.",
            "..##......##..##.##.",
            "..##########........",
            "..##########..#####.",
            "..............#...#.",
            "..............#...#.",
            "....................",
        ]);
        assert_eq!(
            fill_broken_outlines(&m, 2),
            mask(&[
                "....................",
                "..##########........",
                "..##########........",
                "..##########..##.##.",
                "..##########..##.##.",
                "..##########..##.##.",
                "..##########..##.##.",
                "..##########..##.##.",
                "..##########..##.##.",
                "..##########........",
                "..##########..#####.",
                "..............#...#.",
                "..............#...#.",
                "....................",
            ])
        );
        assert_eq!(fill_broken_outlines(&m, 0), m);
    }

    #[test]
    fn small_blobs_go_large_stay() {
        let m = mask(&["##....", "##..#.", "......", "###..."]);
        assert_eq!(
            remove_small(&m, 3),
            mask(&["##....", "##....", "......", "###..."])
        );
    }

    #[test]
    fn opening_removes_a_speck_closing_fills_a_pinhole() {
        let mut m = Plane::filled(20, 20, 0u8);
        for y in 5..15 {
            for x in 5..15 {
                *m.get_mut(x, y) = 255;
            }
        }
        *m.get_mut(1, 1) = 255;
        let o = open(&m, 1);
        assert_eq!(*o.get(1, 1), 0);
        assert_eq!(*o.get(10, 10), 255);
        *m.get_mut(10, 10) = 0;
        let c = close(&m, 1);
        assert_eq!(*c.get(10, 10), 255);
        assert_eq!(*c.get(10, 4), 0);
    }
}
