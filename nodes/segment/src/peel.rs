//! Edge refinement: a variance window that touches a cell lifts the pixels around it too, so
//! the thresholded mask runs up to M px past the cell — further where the edge contrast is
//! strong (the bright side of DIC relief), so the centroid moves as well as the area.
//! [`peel_edges`] takes back that skirt: mask pixels on the outside of the mask that look
//! like the smooth background around them are removed, layer by layer.

use crate::BoxSums;
use schemas::{Mask, Plane};

/// Whether a boundary pixel `(x, y)` goes to the background.
type PeelTest<'a> = &'a dyn Fn(usize, usize) -> bool;

/// The 4-neighbours of `(x, y)` inside a `w × h` image.
fn neighbours4(x: usize, y: usize, w: usize, h: usize) -> impl Iterator<Item = (usize, usize)> {
    [
        (x.wrapping_sub(1), y),
        (x + 1, y),
        (x, y.wrapping_sub(1)),
        (x, y + 1),
    ]
    .into_iter()
    .filter(move |&(u, v)| u < w && v < h)
}

/// Removes up to `layers` outer layers of `mask` where they look like background. With `r`
/// the difference from the local background mean (the mean of the background pixels in the
/// `(2·bg_radius+1)²` window) and σ the background's robust spread: for up to `layers`
/// layers, a mask pixel 4-adjacent to the background goes when the mean of `r²` over its
/// 3×3 neighbourhood is at most `(0.75kσ)²` — a whole neighbourhood of background, so texture
/// at the true edge stops it — and then one more layer goes where `|r| ≤ kσ` on its own:
/// the pixels right against the cell. Last, what is left of the skirt goes where it sticks
/// out: pixels with at most one 4-neighbour or three 8-neighbours in the mask, and pixels
/// with four that lie within 1.5kσ of the background. Pixels with no background in
/// their window are kept.
pub fn peel_edges(img: &Plane<u8>, mask: &Mask, layers: usize, bg_radius: usize, k: f64) -> Mask {
    let table = match wrapped_sum_bits(img.width, img.height, bg_radius.max(layers)) {
        Some(bits) => Table::Wrapped(bits),
        None if (img.width * img.height) as u64 * 255 < 1 << 32 => Table::Packed,
        None => Table::Apart,
    };
    peel_with(img, mask, layers, bg_radius, k, table)
}

/// How the background's window sums are tabulated.
#[derive(Clone, Copy, Debug)]
enum Table {
    /// Count and grey-level sum packed in one wrapping `u32` table, the sum in the low
    /// bits given: exact while a window's two fields fit in 32 bits (4 MB for a 1280×1024
    /// view).
    Wrapped(u32),
    /// Both in one `u64` table: exact while the whole frame's sum fits 32 bits.
    Packed,
    /// Two `u64` tables.
    Apart,
}

/// The bits of the grey-level sum's field when a window of radius `r` (clipped to the frame)
/// packs its count and sum into 32 bits, `None` when they do not fit.
fn wrapped_sum_bits(w: usize, h: usize, r: usize) -> Option<u32> {
    let side = |n: usize| (2 * r + 1).min(n) as u64;
    let most = side(w) * side(h);
    let bits = |v: u64| 64 - v.leading_zeros();
    let sum_bits = bits(255 * most);
    (sum_bits + bits(most) <= 32).then_some(sum_bits)
}

/// [`peel_edges`] with the background's window sums in the given table.
fn peel_with(
    img: &Plane<u8>,
    mask: &Mask,
    layers: usize,
    bg_radius: usize,
    k: f64,
    table: Table,
) -> Mask {
    let (w, h) = (img.width, img.height);
    let mut out = mask.clone();
    if layers == 0 || w == 0 || h == 0 {
        return out;
    }
    let is_bg = |x: usize, y: usize| *mask.get(x, y) == 0;
    // The background's count and grey-level sum in every window ([`Table`]): both in one
    // table where their fields fit (count in the high bits, sum in the low; a window's sums
    // are differences of the table's, each field non-negative), two tables otherwise.
    let sums = match table {
        Table::Wrapped(bits) => Sums::Wrapped(
            BoxSums::<u32>::from_rows(w, h, |y, row| {
                for ((v, &m), &g) in row.iter_mut().zip(mask.row(y)).zip(img.row(y)) {
                    *v = if m == 0 { 1 << bits | g as u32 } else { 0 };
                }
            }),
            bits,
        ),
        Table::Packed => Sums::Packed(BoxSums::from_rows(w, h, |y, row| {
            for ((v, &m), &g) in row.iter_mut().zip(mask.row(y)).zip(img.row(y)) {
                *v = if m == 0 { 1 << 32 | g as u64 } else { 0 };
            }
        })),
        Table::Apart => Sums::Apart(
            BoxSums::new(w, h, |x, y| u64::from(is_bg(x, y))),
            BoxSums::new(w, h, |x, y| {
                if is_bg(x, y) {
                    *img.get(x, y) as u64
                } else {
                    0
                }
            }),
        ),
    };
    let background = |x: usize, y: usize, r: usize| -> (u64, u64) {
        match &sums {
            Sums::Wrapped(t, bits) => {
                let v = t.around(x, y, r).0;
                ((v >> bits) as u64, (v & ((1 << bits) - 1)) as u64)
            }
            Sums::Packed(t) => {
                let v = t.around(x, y, r).0;
                (v >> 32, v & 0xffff_ffff)
            }
            Sums::Apart(n, s) => (n.around(x, y, r).0, s.around(x, y, r).0),
        }
    };
    // The pixel's difference from the background's mean around it (None: no background).
    let r_of = |x: usize, y: usize| -> f64 {
        let (c, s) = background(x, y, bg_radius);
        if c > 0 {
            *img.get(x, y) as f64 - s as f64 / c as f64
        } else {
            f64::NAN
        }
    };
    // Worked out where read: each test keeps what it kept (below), so each pixel's r is
    // read a few times, not once a round; a table of every pixel's r, zeroed for each
    // frame, cost more than all of that (10 MB for a 1280×1024 view).
    let r = |x: usize, y: usize| {
        let v = r_of(x, y);
        (!v.is_nan()).then_some(v)
    };
    // Spread of the background about its local mean (median absolute deviation), from
    // every third pixel along both axes: plenty for one number.
    // Not kept: the sample spans the frame, the tests only its edges.
    let mut dev: Vec<f64> = Vec::with_capacity(w.div_ceil(3) * h.div_ceil(3));
    for y in (0..h).step_by(3) {
        let row = mask.row(y);
        match &sums {
            // The usual table read a row at a time: `r_of`'s values, its window bounds
            // worked out once a row (a third of the peel went on this sample).
            Sums::Wrapped(t, bits) => {
                let (y0, y1) = (y.saturating_sub(bg_radius), (y + bg_radius + 1).min(h));
                let (a, b) = t.rows(y0, y1);
                let grey = img.row(y);
                for x in (0..w).step_by(3).filter(|&x| row[x] == 0) {
                    let (x0, x1) = (x.saturating_sub(bg_radius), (x + bg_radius + 1).min(w));
                    let v = b[x1]
                        .wrapping_add(a[x0])
                        .wrapping_sub(a[x1])
                        .wrapping_sub(b[x0]);
                    let (c, s) = ((v >> bits) as u64, (v & ((1 << bits) - 1)) as u64);
                    if c > 0 {
                        dev.push((grey[x] as f64 - s as f64 / c as f64).abs());
                    }
                }
            }
            _ => {
                for x in (0..w).step_by(3) {
                    if row[x] == 0 {
                        let v = r_of(x, y);
                        if !v.is_nan() {
                            dev.push(v.abs());
                        }
                    }
                }
            }
        }
    }
    if dev.is_empty() {
        return out;
    }
    let mid = dev.len() / 2;
    let (_, m, _) = dev.select_nth_unstable_by(mid, f64::total_cmp);
    let tol = k * 1.4826 * m.max(0.5);
    // The neighbourhood test averages nine pixels, so it can be tighter.
    let quiet_tol = 0.75 * tol;
    let quiet = |x: usize, y: usize| {
        let (mut e, mut c) = (0.0, 0.0);
        for v in y.saturating_sub(1)..(y + 2).min(h) {
            for u in x.saturating_sub(1)..(x + 2).min(w) {
                // No background around: as far from it as a grey level can be.
                e += r(u, v).map_or(255.0 * 255.0, |d| d * d);
                c += 1.0;
            }
        }
        e / c <= quiet_tol * quiet_tol
    };
    let alone = |x: usize, y: usize| r(x, y).is_some_and(|v| v.abs() <= tol);
    // The variance window lifts at most `layers` px of skirt (Chebyshev distance) around a
    // cell: nothing deeper in the mask is peeled. Without the cap a strongly textured
    // background (its spread wide, so the tests loose) ate 3–5 px into the dim side of a
    // cell and moved its centroid by up to 3 px.
    // Within `layers` px of the background: some background in the window of that radius.
    // (The Chebyshev distance transform this replaces saturates at min(w + h, 255).)
    let everywhere = layers >= (w + h).min(255);
    let shallow = |x: usize, y: usize| everywhere || background(x, y, layers).0 > 0;
    let quiet = |x: usize, y: usize| shallow(x, y) && quiet(x, y);
    let alone = |x: usize, y: usize| shallow(x, y) && alone(x, y);
    // The mask's pixels with a 4-neighbour in the background, in raster order, run by run
    // ([`row_runs`](crate::label::row_runs) passes the empty stretches a chunk at a time): a
    // run's ends are open to the side unless they touch the frame's edge, any of its pixels
    // above or below background (a pixel's four neighbours looked up one by one took an
    // eighth of the peel).
    let mut boundary: Vec<(usize, usize)> = Vec::new();
    for y in 0..h {
        let (up, down) = (
            y.checked_sub(1).map(|v| mask.row(v)),
            (y + 1 < h).then(|| mask.row(y + 1)),
        );
        let open = |r: Option<&[u8]>, x: usize| r.is_some_and(|r| r[x] == 0);
        crate::label::row_runs(mask.row(y), &|&m: &u8| m != 0, |x0, x1| {
            for x in x0..x1 {
                let side = (x == x0 && x0 > 0) || (x + 1 == x1 && x1 < w);
                if side || open(up, x) || open(down, x) {
                    boundary.push((x, y));
                }
            }
        });
    }
    let mut listed = vec![false; w * h];
    let test_rounds: [(PeelTest, usize); 2] = [(&quiet, 2 * layers), (&alone, 1)];
    for (test, rounds) in test_rounds {
        // Each test reads only the first mask's background (r and the depth), not what the
        // rounds peeled: a pixel it kept, it keeps in every later round. The kept lead the
        // next round's boundary, so only the pixels behind them, newly exposed, are tested.
        let mut known = 0;
        for _ in 0..rounds {
            let (mut gone, mut kept) = (Vec::new(), Vec::new());
            for (i, &(x, y)) in boundary.iter().enumerate() {
                if i >= known && test(x, y) {
                    gone.push((x, y));
                } else {
                    kept.push((x, y));
                }
            }
            known = kept.len();
            if !peel_boundary(&mut out, &mut boundary, gone, kept, &mut listed) {
                break;
            }
        }
    }
    // What is left of the skirt can hang on by a corner: a pixel with at most one
    // 4-neighbour or three 8-neighbours in the mask ends a line or a spur, and one with four
    // sticks out (on a cell's rounded edge every pixel has five) — gone if it is within
    // 1.5 kσ of the background.
    for _ in 0..2 * layers {
        let (gone, kept): (Vec<_>, Vec<_>) = boundary.iter().partition(|&&(x, y)| {
            let n4 = neighbours4(x, y, w, h)
                .filter(|&(u, v)| *out.get(u, v) != 0)
                .count();
            let n8 = (y.saturating_sub(1)..(y + 2).min(h))
                .flat_map(|v| (x.saturating_sub(1)..(x + 2).min(w)).map(move |u| (u, v)))
                .filter(|&(u, v)| (u, v) != (x, y) && *out.get(u, v) != 0)
                .count();
            shallow(x, y)
                && (n4 <= 1
                    || n8 <= 3
                    || (n8 <= 4 && r(x, y).is_some_and(|v| v.abs() <= 1.5 * tol)))
        });
        if !peel_boundary(&mut out, &mut boundary, gone, kept, &mut listed) {
            break;
        }
    }
    out
}

/// The background's window sums: both in one table, or apart.
enum Sums {
    Wrapped(BoxSums<u32>, u32),
    Packed(BoxSums),
    Apart(BoxSums, BoxSums),
}

/// Hands `gone` to the background and makes the boundary `kept` plus the mask pixels that
/// `gone` exposes; false when nothing went. `listed` is an all-false scratch grid.
fn peel_boundary(
    out: &mut Mask,
    boundary: &mut Vec<(usize, usize)>,
    gone: Vec<(usize, usize)>,
    kept: Vec<(usize, usize)>,
    listed: &mut [bool],
) -> bool {
    let (w, h) = (out.width, out.height);
    if gone.is_empty() {
        return false;
    }
    for &(x, y) in &gone {
        *out.get_mut(x, y) = 0;
    }
    // The new boundary as a set (the tests do not depend on its order): what was kept, then
    // each newly exposed mask pixel once; `listed` marks members and is left all false.
    let mut next = kept;
    for &(x, y) in &next {
        listed[y * w + x] = true;
    }
    for &(x, y) in &gone {
        for (u, v) in neighbours4(x, y, w, h) {
            if *out.get(u, v) != 0 && !listed[v * w + u] {
                listed[v * w + u] = true;
                next.push((u, v));
            }
        }
    }
    for &(x, y) in &next {
        listed[y * w + x] = false;
    }
    *boundary = next;
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The first version of [`peel_edges`] (every r tabulated, the depth from a distance
    /// transform), which the fast one must match.
    fn peel_edges_reference(
        img: &Plane<u8>,
        mask: &Mask,
        layers: usize,
        bg_radius: usize,
        k: f64,
    ) -> Mask {
        let (w, h) = (img.width, img.height);
        let mut out = mask.clone();
        if layers == 0 || w == 0 || h == 0 {
            return out;
        }
        let is_bg = |x: usize, y: usize| *mask.get(x, y) == 0;
        let n = BoxSums::new(w, h, |x, y| u64::from(is_bg(x, y)));
        let s = BoxSums::new(w, h, |x, y| {
            if is_bg(x, y) {
                *img.get(x, y) as u64
            } else {
                0
            }
        });
        // Every test below reads r many times over, for the same pixels round after round:
        // tabulated once (NaN where the window holds no background).
        let table: Vec<f64> = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| {
                let c = n.around(x, y, bg_radius).0;
                if c > 0 {
                    *img.get(x, y) as f64 - s.around(x, y, bg_radius).0 as f64 / c as f64
                } else {
                    f64::NAN
                }
            })
            .collect();
        let r = |x: usize, y: usize| {
            let v = table[y * w + x];
            (!v.is_nan()).then_some(v)
        };
        // Spread of the background about its local mean (median absolute deviation), from
        // every third pixel along both axes: plenty for one number.
        let mut dev: Vec<f64> = (0..h)
            .step_by(3)
            .flat_map(|y| (0..w).step_by(3).map(move |x| (x, y)))
            .filter(|&(x, y)| is_bg(x, y))
            .filter_map(|(x, y)| r(x, y).map(f64::abs))
            .collect();
        if dev.is_empty() {
            return out;
        }
        let mid = dev.len() / 2;
        let (_, m, _) = dev.select_nth_unstable_by(mid, f64::total_cmp);
        let tol = k * 1.4826 * m.max(0.5);
        // The neighbourhood test averages nine pixels, so it can be tighter.
        let quiet_tol = 0.75 * tol;
        let quiet = |x: usize, y: usize| {
            let (mut e, mut c) = (0.0, 0.0);
            for v in y.saturating_sub(1)..(y + 2).min(h) {
                for u in x.saturating_sub(1)..(x + 2).min(w) {
                    // No background around: as far from it as a grey level can be.
                    e += r(u, v).map_or(255.0 * 255.0, |d| d * d);
                    c += 1.0;
                }
            }
            e / c <= quiet_tol * quiet_tol
        };
        let alone = |x: usize, y: usize| r(x, y).is_some_and(|v| v.abs() <= tol);
        // The variance window lifts at most `layers` px of skirt (Chebyshev distance) around a
        // cell: nothing deeper in the mask is peeled. Without the cap a strongly textured
        // background (its spread wide, so the tests loose) ate 3–5 px into the dim side of a
        // cell and moved its centroid by up to 3 px.
        let depth = {
            let bg = image::GrayImage::from_fn(w as u32, h as u32, |x, y| {
                image::Luma([u8::from(is_bg(x as usize, y as usize))])
            });
            imageproc::distance_transform::distance_transform(
                &bg,
                imageproc::distance_transform::Norm::LInf,
            )
        };
        let shallow =
            |x: usize, y: usize| (depth.get_pixel(x as u32, y as u32).0[0] as usize) <= layers;
        let quiet = |x: usize, y: usize| shallow(x, y) && quiet(x, y);
        let alone = |x: usize, y: usize| shallow(x, y) && alone(x, y);
        let mut boundary: Vec<(usize, usize)> = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .filter(|&(x, y)| {
                *mask.get(x, y) != 0 && neighbours4(x, y, w, h).any(|(u, v)| is_bg(u, v))
            })
            .collect();
        let mut listed = vec![false; w * h];
        let test_rounds: [(PeelTest, usize); 2] = [(&quiet, 2 * layers), (&alone, 1)];
        for (test, rounds) in test_rounds {
            for _ in 0..rounds {
                let (gone, kept): (Vec<_>, Vec<_>) =
                    boundary.iter().partition(|&&(x, y)| test(x, y));
                if !peel_boundary(&mut out, &mut boundary, gone, kept, &mut listed) {
                    break;
                }
            }
        }
        // What is left of the skirt can hang on by a corner: a pixel with at most one
        // 4-neighbour or three 8-neighbours in the mask ends a line or a spur, and one with four
        // sticks out (on a cell's rounded edge every pixel has five) — gone if it is within
        // 1.5 kσ of the background.
        for _ in 0..2 * layers {
            let (gone, kept): (Vec<_>, Vec<_>) = boundary.iter().partition(|&&(x, y)| {
                let n4 = neighbours4(x, y, w, h)
                    .filter(|&(u, v)| *out.get(u, v) != 0)
                    .count();
                let n8 = (y.saturating_sub(1)..(y + 2).min(h))
                    .flat_map(|v| (x.saturating_sub(1)..(x + 2).min(w)).map(move |u| (u, v)))
                    .filter(|&(u, v)| (u, v) != (x, y) && *out.get(u, v) != 0)
                    .count();
                shallow(x, y)
                    && (n4 <= 1
                        || n8 <= 3
                        || (n8 <= 4 && r(x, y).is_some_and(|v| v.abs() <= 1.5 * tol)))
            });
            if !peel_boundary(&mut out, &mut boundary, gone, kept, &mut listed) {
                break;
            }
        }
        out
    }

    /// A 40×30 background at 100 (± 1 by a fixed pattern) with a disc of radius 8.3 at
    /// (20, 15) whose pixels alternate 60 / 150.
    fn disc() -> (Plane<u8>, Vec<bool>) {
        let (w, h) = (40, 30);
        let mut img = Plane::filled(w, h, 0u8);
        let mut inside = vec![false; w * h];
        for y in 0..h {
            for x in 0..w {
                let d = (x as f64 - 20.0).hypot(y as f64 - 15.0);
                let v = if d <= 8.3 {
                    inside[y * w + x] = true;
                    if (x + y) % 2 == 0 { 60 } else { 150 }
                } else {
                    100 + ((x * 7 + y * 3) % 3) as u8 - 1
                };
                *img.get_mut(x, y) = v;
            }
        }
        (img, inside)
    }

    /// The disc's mask grown to `radius`, as a variance window would leave it.
    fn grown(radius: f64) -> Mask {
        let data = (0..30)
            .flat_map(|y| (0..40).map(move |x| (x, y)))
            .map(|(x, y)| {
                if (x as f64 - 20.0).hypot(y as f64 - 15.0) <= radius {
                    255
                } else {
                    0
                }
            })
            .collect();
        Plane::from_vec(40, 30, data).unwrap()
    }

    #[test]
    fn peels_a_fat_mask_back_to_the_disc() {
        let (img, inside) = disc();
        // The mask a variance window of radius 3 would give: the disc grown by 3 px.
        let fat = grown(11.0);
        let thin = peel_edges(&img, &fat, 4, 12, 2.0);
        for (i, &t) in thin.data.iter().enumerate() {
            assert_eq!(t != 0, inside[i], "pixel ({}, {})", i % 40, i / 40);
        }
        // No layers: unchanged.
        assert_eq!(peel_edges(&img, &fat, 0, 12, 2.0), fat);
    }

    #[test]
    fn fewer_layers_peel_less_and_unknown_surroundings_stay() {
        let (img, _) = disc();
        let fat = grown(14.0);
        let (one, four) = (
            peel_edges(&img, &fat, 1, 12, 2.0),
            peel_edges(&img, &fat, 4, 12, 2.0),
        );
        let removed = |m: &Mask| fat.data.iter().zip(&m.data).filter(|(a, b)| a != b).count();
        // One neighbourhood layer (two 4-connected rounds) and two single-pixel rounds
        // cannot reach the disc from 6 px out everywhere: some skirt is left.
        assert!(
            removed(&one) < removed(&four),
            "{} vs {}",
            removed(&one),
            removed(&four)
        );
        assert!(
            one.data
                .iter()
                .zip(&four.data)
                .all(|(o, f)| *o != 0 || *f == 0)
        );
        for y in 0..30 {
            for x in 0..40 {
                if (x as f64 - 20.0).hypot(y as f64 - 15.0) <= 8.3 {
                    assert_ne!(*one.get(x, y), 0, "disc pixel ({x}, {y}) kept");
                }
            }
        }
        // A mask covering everything has no background to compare with: kept whole.
        let all = Plane::filled(40, 30, 255u8);
        assert_eq!(peel_edges(&img, &all, 4, 12, 2.0), all);
    }

    /// A `w × h` scene of textured blobs on a noisy background with a lighting gradient,
    /// and a mask that overshoots them by up to 5 px, with specks and a hole or two: what
    /// the variance threshold hands on.
    pub(crate) fn blobs(w: usize, h: usize, seed: u64) -> (Plane<u8>, Mask) {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let discs: Vec<(f64, f64, f64, f64)> = (0..rng.random_range(1..8))
            .map(|_| {
                (
                    rng.random_range(0.0..w as f64),
                    rng.random_range(0.0..h as f64),
                    rng.random_range(3.0..18.0),
                    rng.random_range(0.0..5.0),
                )
            })
            .collect();
        let mut img = Plane::filled(w, h, 0u8);
        let mut mask = Plane::filled(w, h, 0u8);
        for y in 0..h {
            for x in 0..w {
                let (fx, fy) = (x as f64, y as f64);
                let mut v = 90.0 + 30.0 * fx / w as f64 + rng.random_range(-4.0..4.0);
                for &(cx, cy, r, grow) in &discs {
                    let d = (fx - cx).hypot(fy - cy);
                    if d <= r {
                        v = rng.random_range(40.0..190.0);
                    }
                    if d <= r + grow && d > 1.5 {
                        *mask.get_mut(x, y) = 255;
                    }
                }
                if rng.random_bool(0.002) {
                    *mask.get_mut(x, y) = 255;
                }
                *img.get_mut(x, y) = v as u8;
            }
        }
        (img, mask)
    }

    #[test]
    fn the_fast_peel_matches_the_first_version_exactly() {
        let mut peeled = 0;
        for seed in 0..40 {
            let (w, h) = [(96, 64), (40, 120), (17, 9), (150, 150)][seed as usize % 4];
            let (img, mask) = blobs(w, h, seed);
            for (layers, bg_radius, k) in [(4, 16, 2.25), (1, 4, 2.0), (6, 9, 3.0), (300, 5, 2.25)]
            {
                let fast = peel_edges(&img, &mask, layers, bg_radius, k);
                let first = peel_edges_reference(&img, &mask, layers, bg_radius, k);
                assert_eq!(
                    fast, first,
                    "seed {seed}, layers {layers}, radius {bg_radius}, k {k}"
                );
                // Every table gives the same mask: wrapped (where it fits), packed in u64
                // (frames whose sum fits 32 bits) and two tables (larger frames).
                for table in [Table::Packed, Table::Apart]
                    .into_iter()
                    .chain(wrapped_sum_bits(w, h, bg_radius.max(layers)).map(Table::Wrapped))
                {
                    let other = peel_with(&img, &mask, layers, bg_radius, k, table);
                    assert_eq!(other, first, "{table:?}, seed {seed}");
                }
                peeled += fast
                    .data
                    .iter()
                    .zip(&mask.data)
                    .filter(|(a, b)| a != b)
                    .count();
            }
        }
        // The scenes give the peel work to do.
        assert!(peeled > 5000, "{peeled} pixels peeled");
    }
}
