//! Edge refinement: a variance window that touches a cell lifts the pixels around it too, so
//! the thresholded mask runs up to M px past the cell — further where the edge contrast is
//! strong (the bright side of DIC relief), so the centroid moves as well as the area.
//! [`peel_edges`] takes back that skirt: mask pixels on the outside of the mask that look
//! like the smooth background around them are removed, layer by layer.

use schemas::{Mask, Plane};

/// Box sums over `(2r+1)²` windows (clamped at the edges) of `f(x, y)`.
fn box_sums(w: usize, h: usize, r: usize, f: impl Fn(usize, usize) -> f64) -> Vec<f64> {
    let mut sat = vec![0f64; (w + 1) * (h + 1)];
    for y in 0..h {
        let mut acc = 0.0;
        for x in 0..w {
            acc += f(x, y);
            sat[(y + 1) * (w + 1) + x + 1] = sat[y * (w + 1) + x + 1] + acc;
        }
    }
    let mut out = vec![0f64; w * h];
    for y in 0..h {
        let (y0, y1) = (y.saturating_sub(r), (y + r + 1).min(h));
        for x in 0..w {
            let (x0, x1) = (x.saturating_sub(r), (x + r + 1).min(w));
            out[y * w + x] = sat[y1 * (w + 1) + x1] + sat[y0 * (w + 1) + x0]
                - sat[y0 * (w + 1) + x1]
                - sat[y1 * (w + 1) + x0];
        }
    }
    out
}

/// Removes up to `layers` outer layers of `mask` where they look like background. With `r`
/// the difference from the local background mean (the mean of the background pixels in the
/// `(2·bg_radius+1)²` window) and σ the background's robust spread: for up to `layers`
/// layers, a mask pixel 4-adjacent to the background goes when the mean of `r²` over its
/// 3×3 neighbourhood is at most `(0.75kσ)²` — a whole neighbourhood of background, so texture
/// at the true edge stops it — and then up to two more layers go where `|r| ≤ kσ` on its
/// own: the pixels right against the cell. Pixels with no background in their window are
/// kept.
pub fn peel_edges(img: &Plane<u8>, mask: &Mask, layers: usize, bg_radius: usize, k: f64) -> Mask {
    let (w, h) = (img.width, img.height);
    let mut out = mask.clone();
    if layers == 0 || w == 0 || h == 0 {
        return out;
    }
    let is_bg = |x: usize, y: usize| *mask.get(x, y) == 0;
    let n = box_sums(w, h, bg_radius, |x, y| f64::from(u8::from(is_bg(x, y))));
    let s = box_sums(w, h, bg_radius, |x, y| {
        if is_bg(x, y) {
            *img.get(x, y) as f64
        } else {
            0.0
        }
    });
    let mean = |x: usize, y: usize| {
        let i = y * w + x;
        (n[i] > 0.0).then(|| s[i] / n[i])
    };
    // Spread of the background about its local mean (median absolute deviation).
    let mut dev: Vec<f64> = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .filter(|&(x, y)| is_bg(x, y))
        .filter_map(|(x, y)| mean(x, y).map(|m| (*img.get(x, y) as f64 - m).abs()))
        .collect();
    if dev.is_empty() {
        return out;
    }
    let mid = dev.len() / 2;
    let (_, m, _) = dev.select_nth_unstable_by(mid, f64::total_cmp);
    let tol = k * 1.4826 * m.max(0.5);
    let r = |x: usize, y: usize| mean(x, y).map(|m| *img.get(x, y) as f64 - m);
    // No background around: as far from it as a grey level can be (finite, for the sums).
    let energy = box_sums(w, h, 1, |x, y| r(x, y).map_or(255.0 * 255.0, |v| v * v));
    let cells = box_sums(w, h, 1, |_, _| 1.0);
    // The neighbourhood test averages nine pixels, so it can be tighter.
    let quiet_tol = 0.75 * tol;
    let quiet = |x: usize, y: usize| energy[y * w + x] / cells[y * w + x] <= quiet_tol * quiet_tol;
    let alone = |x: usize, y: usize| r(x, y).is_some_and(|v| v.abs() <= tol);
    // The pixels next to the cell form a band one pixel wide in the chessboard sense: two
    // 4-connected layers deep where the edge runs diagonally.
    for _ in 0..2 * layers {
        if peel_round(&mut out, &quiet) == 0 {
            break;
        }
    }
    for _ in 0..2 {
        if peel_round(&mut out, &alone) == 0 {
            break;
        }
    }
    out
}

/// Hands to the background every mask pixel 4-adjacent to it that passes `test`; returns
/// how many went.
fn peel_round(out: &mut Mask, test: &dyn Fn(usize, usize) -> bool) -> usize {
    let (w, h) = (out.width, out.height);
    let peel: Vec<(usize, usize)> = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .filter(|&(x, y)| {
            *out.get(x, y) != 0
                && ((x > 0 && *out.get(x - 1, y) == 0)
                    || (x + 1 < w && *out.get(x + 1, y) == 0)
                    || (y > 0 && *out.get(x, y - 1) == 0)
                    || (y + 1 < h && *out.get(x, y + 1) == 0))
                && test(x, y)
        })
        .collect();
    for &(x, y) in &peel {
        *out.get_mut(x, y) = 0;
    }
    peel.len()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 40×30 background at 100 (± 1 by a fixed pattern) with a disc of radius 8 at
    /// (20, 15) whose pixels alternate 60 / 150.
    fn disc() -> (Plane<u8>, Vec<bool>) {
        let (w, h) = (40, 30);
        let mut img = Plane::filled(w, h, 0u8);
        let mut inside = vec![false; w * h];
        for y in 0..h {
            for x in 0..w {
                let d = (x as f64 - 20.0).hypot(y as f64 - 15.0);
                let v = if d <= 8.0 {
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

    #[test]
    fn peels_a_fat_mask_back_to_the_disc() {
        let (img, inside) = disc();
        // The mask a variance window of radius 3 would give: the disc grown by 3 px.
        let fat = Plane::from_vec(
            40,
            30,
            (0..30)
                .flat_map(|y| (0..40).map(move |x| (x, y)))
                .map(|(x, y)| {
                    if (x as f64 - 20.0).hypot(y as f64 - 15.0) <= 11.0 {
                        255
                    } else {
                        0
                    }
                })
                .collect(),
        )
        .unwrap();
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
        let fat = Plane::from_vec(
            40,
            30,
            (0..30)
                .flat_map(|y| (0..40).map(move |x| (x, y)))
                .map(|(x, y)| {
                    if (x as f64 - 20.0).hypot(y as f64 - 15.0) <= 14.0 {
                        255
                    } else {
                        0
                    }
                })
                .collect(),
        )
        .unwrap();
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
                if (x as f64 - 20.0).hypot(y as f64 - 15.0) <= 8.0 {
                    assert_ne!(*one.get(x, y), 0, "disc pixel ({x}, {y}) kept");
                }
            }
        }
        // A mask covering everything has no background to compare with: kept whole.
        let all = Plane::filled(40, 30, 255u8);
        assert_eq!(peel_edges(&img, &all, 4, 12, 2.0), all);
    }
}
