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

/// `mask` at 255 wherever it is non-zero, and on every run of `parts` whose component
/// `keep` picks.
fn with_runs(mask: &Mask, parts: &Components, keep: impl Fn(u32) -> bool) -> Mask {
    let data = mask
        .data
        .iter()
        .map(|&m| if m != 0 { 255 } else { 0 })
        .collect();
    let mut out = Plane::from_vec(mask.width, mask.height, data).expect("same size");
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
pub fn fill_broken_outlines(mask: &Mask, radius: u8) -> Mask {
    if radius == 0 {
        return mask.clone();
    }
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
        return mask.clone();
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
    with_runs(mask, &parts, |l| {
        hole[l as usize] && border[l as usize].is_some_and(|b| b != u32::MAX)
    })
}

/// Closing with a square of half-width `radius`, the image padded so that nothing sticks to
/// its border. A square bridges a gap between the ends of an arc as wide as itself, where a
/// disc's rounded edge leaves the gap's outer corners open.
///
/// Separable running counts: the dilation over the image grown by `radius` on every side
/// (outside it the mask is background), then the erosion of that, back on the image; the
/// same pixels as imageproc's distance-transform closing of a padded copy (the test below),
/// in a fifth of the time on a mostly empty 1280×1024 frame.
fn close_square(mask: &Mask, radius: u8) -> Mask {
    let r = radius as usize;
    let (w, h) = (mask.width, mask.height);
    let (pw, ph) = (w + 2 * r, h + 2 * r);
    let span = 2 * r + 1;
    // Along rows: padded column i (x = i − r) is set where the mask has a pixel in x ± r,
    // that is in [i − 2r, i]: a difference of the row's prefix counts (kept in a register
    // as they are made; the differences then run as vector loops).
    let mut across = vec![0u8; h * pw];
    let mut prefix = vec![0u32; pw + 1];
    for (row, out) in mask
        .data
        .chunks_exact(w.max(1))
        .zip(across.chunks_exact_mut(pw))
    {
        running_counts(row, &mut prefix);
        let head = (span - 1).min(pw);
        for (o, &p) in out[..head].iter_mut().zip(&prefix[1..]) {
            *o = u8::from(p > 0);
        }
        for ((o, &p), &q) in out[head..]
            .iter_mut()
            .zip(&prefix[head + 1..])
            .zip(&prefix[head + 1 - span.min(head + 1)..])
        {
            *o = u8::from(p > q);
        }
    }
    // Down columns: padded row j (y = j − r) is set where a row within y ± r is.
    let mut dilated = vec![0u8; ph * pw];
    let mut counts = vec![0u32; pw];
    for j in 0..ph {
        if j < h {
            for (c, &a) in counts.iter_mut().zip(&across[j * pw..(j + 1) * pw]) {
                *c += u32::from(a);
            }
        }
        if j >= span && j - span < h {
            let k = j - span;
            for (c, &a) in counts.iter_mut().zip(&across[k * pw..(k + 1) * pw]) {
                *c -= u32::from(a);
            }
        }
        for (d, &c) in dilated[j * pw..(j + 1) * pw].iter_mut().zip(&counts) {
            *d = u8::from(c > 0);
        }
    }
    // The erosion: image pixel (x, y) stays where all of padded [x, x + 2r] × [y, y + 2r]
    // is set. Along rows first (a difference of prefix counts again), then down columns.
    let mut full = vec![0u8; ph * w];
    for (row, out) in dilated
        .chunks_exact(pw)
        .zip(full.chunks_exact_mut(w.max(1)))
    {
        running_counts(row, &mut prefix);
        for ((o, &p), &q) in out.iter_mut().zip(&prefix[span..]).zip(&prefix[..w]) {
            *o = u8::from(p - q == span as u32);
        }
    }
    let mut data = vec![0u8; w * h];
    let mut counts = vec![0usize; w];
    for j in 0..span - 1 {
        for (c, &f) in counts.iter_mut().zip(&full[j * w..(j + 1) * w]) {
            *c += f as usize;
        }
    }
    for y in 0..h {
        let add = y + span - 1;
        for (c, &f) in counts.iter_mut().zip(&full[add * w..(add + 1) * w]) {
            *c += f as usize;
        }
        for (d, &c) in data[y * w..(y + 1) * w].iter_mut().zip(&counts) {
            *d = if c == span { 255 } else { 0 };
        }
        for (c, &f) in counts.iter_mut().zip(&full[y * w..(y + 1) * w]) {
            *c -= f as usize;
        }
    }
    Plane::from_vec(w, h, data).expect("size")
}

/// `prefix[k]` = the number of non-zero values among `row[..k]`, for every `k` up to
/// `prefix.len() − 1` (past the row's end the count stays).
fn running_counts(row: &[u8], prefix: &mut [u32]) {
    let mut acc = 0u32;
    prefix[0] = 0;
    let n = row.len().min(prefix.len() - 1);
    let (inside, past) = prefix[1..].split_at_mut(n);
    for (p, &v) in inside.iter_mut().zip(row) {
        acc += u32::from(v != 0);
        *p = acc;
    }
    past.fill(acc);
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

/// Dilates with a disc of `radius`.
pub fn dilate(mask: &Mask, radius: u8) -> Mask {
    disc_op(mask, radius, imageproc::morphology::dilate)
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

    #[test]
    fn run_based_filling_and_removal_match_the_label_images() {
        let mut seed = 11u64;
        let mut rnd = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 33) as usize
        };
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
                    .for_each(|v| *v = u8::from(rnd() % 40 == 0) * 255);
                for _ in 0..2 + rnd() % 4 {
                    let (cx, cy) = ((rnd() % w) as f64, (rnd() % h) as f64);
                    let (r, gap) = (3.0 + (rnd() % 6) as f64, 0.3 + (rnd() % 5) as f64 * 0.2);
                    let turn = (rnd() % 628) as f64 / 100.0;
                    for y in 0..h {
                        for x in 0..w {
                            let (dx, dy) = (x as f64 - cx, y as f64 - cy);
                            let a = (dy.atan2(dx) - turn).rem_euclid(std::f64::consts::TAU);
                            if (dx.hypot(dy) - r).abs() < 0.8 && a > gap {
                                *mask.get_mut(x, y) = 255;
                            }
                        }
                    }
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

    #[test]
    fn the_running_count_closing_matches_imageproc() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut changed = 0;
        for case in 0..300 {
            let (w, h) = (rng.random_range(1..60), rng.random_range(1..60));
            let density = [0.02, 0.1, 0.3, 0.6, 0.95][case % 5];
            let data = (0..w * h)
                .map(|_| if rng.random_bool(density) { 255 } else { 0 })
                .collect();
            let m = Plane::from_vec(w, h, data).unwrap();
            let radius = rng.random_range(0..7u8);
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
