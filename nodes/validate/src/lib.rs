//! Validation of disparity maps: left/right consistency and ground-truth evaluation.
//!
//! - [`lr_check`]: a left pixel `x` with disparity `dL` is consistent when the right map
//!   at `xr = round(x − dL)` holds `dR` with `|dL − dR| ≤ tolerance`; the same test from
//!   the right side gives the right occlusion mask. Inconsistent pixels are occlusions or
//!   false matches and become invalid.
//! - [`validation_figures`]: the paper's Fig. 13 — of the left matches, the share consistent
//!   exactly, off by exactly one pixel, off by more (or without a partner).
//! - [`evaluate`]: Middlebury-style errors against ground truth (bad-0.5/1/2/4, mean abs
//!   error, RMS, density) over non-occluded and over all known pixels.

// The check reads a pixel's column both as an index and as a coordinate (x − d).
#![allow(clippy::needless_range_loop)]

pub mod eval;
pub mod node;

pub use eval::{ErrorStats, EvalFigures, evaluate, occlusion_from_gt};

use rayon::prelude::*;
use schemas::{DisparityMap, INVALID_DISPARITY, Mask, Plane, ValidationFigures};

/// Largest tolerance the paper's relaxation allows.
pub const MAX_TOLERANCE: u32 = 4;

/// Output of the consistency check.
#[derive(Clone, Debug)]
pub struct Checked {
    /// Left disparity with inconsistent pixels set invalid.
    pub left: DisparityMap,
    /// Right disparity with inconsistent pixels set invalid.
    pub right: DisparityMap,
    /// 255 where a left pixel is occluded or falsely matched (no consistent match).
    pub occlusion_left: Mask,
    /// 255 where a right pixel is occluded or falsely matched.
    pub occlusion_right: Mask,
    /// The paper's figures for this pair of maps.
    pub figures: ValidationFigures,
}

/// The partner's disparity for a pixel at `x` with disparity `d`, or `None` when the
/// partner lies outside the image or has no value. `sign` is −1 from left to right.
#[inline]
fn partner(other: &[f32], x: usize, d: f32, sign: f32) -> Option<f32> {
    // Round half away from zero, as f32::round, which is a library call on x86; below
    // −0.5 the partner is outside anyway.
    let t = x as f32 + sign * d;
    if t <= -0.5 {
        return None;
    }
    let t = (t + 0.5).floor();
    if t >= other.len() as f32 {
        return None;
    }
    let v = other[t as usize];
    v.is_finite().then_some(v)
}

/// Checks one row of `this` map against the `other` map's row (`sign` −1 from left to
/// right): inconsistent pixels become invalid in `out` and 255 in `occ`, and `counts`
/// tallies the figures. Eight pixels at a time where the build has AVX2.
fn check_row(
    this: &[f32],
    other: &[f32],
    sign: f32,
    tol: f32,
    out: &mut [f32],
    occ: &mut [u8],
    counts: &mut Counts,
) {
    let x0 = check_row_simd(this, other, sign, tol, out, occ, counts);
    for x in x0..this.len() {
        // The figures come from the same lookups as the check.
        let d = this[x];
        let diff = d
            .is_finite()
            .then(|| partner(other, x, d, sign).map(|p| (p - d).abs()));
        if let Some(diff) = diff {
            counts.add(diff, tol);
        }
        if !diff.flatten().is_some_and(|d| d <= tol) {
            out[x] = INVALID_DISPARITY;
            occ[x] = 255;
        }
    }
}

/// The vector part of [`check_row`]: the same float operations as [`partner`], with the
/// partner fetched by a masked gather. Returns how many pixels it did (a multiple of 8).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
fn check_row_simd(
    this: &[f32],
    other: &[f32],
    sign: f32,
    tol: f32,
    out: &mut [f32],
    occ: &mut [u8],
    counts: &mut Counts,
) -> usize {
    use std::arch::x86_64::*;
    let n = this.len();
    assert!(other.len() == n && out.len() == n && occ.len() == n && n < 1 << 24);
    let mut x0 = 0;
    // SAFETY: AVX2 is enabled for this build; loads and stores touch [x0, x0 + 8) < n, and
    // the gather reads other[t] only in lanes where 0 <= t < n.
    unsafe {
        let inf = _mm256_set1_ps(f32::INFINITY);
        let abs = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff));
        let half = _mm256_set1_ps(0.5);
        let len = _mm256_set1_ps(n as f32);
        let signv = _mm256_set1_ps(sign);
        let tolv = _mm256_set1_ps(tol);
        let lanes = _mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0);
        let finite = |v: __m256| _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_and_ps(v, abs), inf);
        while x0 + 8 <= n {
            let d = _mm256_loadu_ps(this.as_ptr().add(x0));
            let has_d = finite(d);
            let x = _mm256_add_ps(_mm256_set1_ps(x0 as f32), lanes);
            let raw = _mm256_add_ps(x, _mm256_mul_ps(signv, d));
            let t = _mm256_floor_ps(_mm256_add_ps(raw, half));
            let inside = _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_GT_OQ>(raw, _mm256_set1_ps(-0.5)),
                _mm256_cmp_ps::<_CMP_LT_OQ>(t, len),
            );
            let fetch = _mm256_and_ps(has_d, inside);
            let idx = _mm256_cvttps_epi32(_mm256_and_ps(t, fetch));
            let p = _mm256_mask_i32gather_ps::<4>(inf, other.as_ptr(), idx, fetch);
            let has_p = _mm256_and_ps(fetch, finite(p));
            let diff = _mm256_and_ps(_mm256_sub_ps(p, d), abs);
            let bits = |m: __m256| _mm256_movemask_ps(m) as u32;
            let lt = |a: __m256, b: f32| _mm256_cmp_ps::<_CMP_LT_OQ>(a, _mm256_set1_ps(b));
            let ok = bits(has_p) & bits(_mm256_cmp_ps::<_CMP_LE_OQ>(diff, tolv));
            counts.matched += bits(has_d).count_ones() as u64;
            let exact = bits(has_p) & bits(lt(diff, 0.5));
            counts.exact += exact.count_ones() as u64;
            counts.one += (bits(has_p) & !exact & bits(lt(diff, 1.5))).count_ones() as u64;
            counts.within += ok.count_ones() as u64;
            if ok != 0xff {
                for l in 0..8 {
                    if ok >> l & 1 == 0 {
                        out[x0 + l] = INVALID_DISPARITY;
                        occ[x0 + l] = 255;
                    }
                }
            }
            x0 += 8;
        }
    }
    x0
}

/// Without AVX2 the check is all scalar.
#[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
fn check_row_simd(
    _: &[f32],
    _: &[f32],
    _: f32,
    _: f32,
    _: &mut [f32],
    _: &mut [u8],
    _: &mut Counts,
) -> usize {
    0
}

/// Left/right consistency check with a tolerance of 0..=4 px.
///
/// Both maps must have the same size (callers get them from one matcher run).
pub fn lr_check(left: &DisparityMap, right: &DisparityMap, tolerance: u32) -> Checked {
    assert_eq!((left.width, left.height), (right.width, right.height));
    let (w, h) = (left.width, left.height);
    let tol = tolerance as f32;
    let mut out_l = left.clone();
    let mut out_r = right.clone();
    let mut occ_l = Plane::filled(w, h, 0u8);
    let mut occ_r = Plane::filled(w, h, 0u8);
    let mut counts = Counts::default();
    if w > 0 {
        counts = out_l
            .data
            .par_chunks_mut(w)
            .zip(out_r.data.par_chunks_mut(w))
            .zip(occ_l.data.par_chunks_mut(w))
            .zip(occ_r.data.par_chunks_mut(w))
            .enumerate()
            .map(|(y, (((ol, or), ocl), ocr))| {
                let (lrow, rrow) = (left.row(y), right.row(y));
                let mut c = Counts::default();
                check_row(lrow, rrow, -1.0, tol, ol, ocl, &mut c);
                check_row(rrow, lrow, 1.0, tol, or, ocr, &mut Counts::default());
                c
            })
            .reduce(Counts::default, Counts::merge);
    }
    Checked {
        left: out_l,
        right: out_r,
        occlusion_left: occ_l,
        occlusion_right: occ_r,
        figures: counts.figures(tolerance),
    }
}

/// Tallies behind [`ValidationFigures`].
#[derive(Clone, Copy, Default)]
struct Counts {
    matched: u64,
    exact: u64,
    one: u64,
    within: u64,
}

impl Counts {
    /// One left match whose partner differs by `diff` (`None`: no partner).
    #[inline(always)]
    fn add(&mut self, diff: Option<f32>, tol: f32) {
        self.matched += 1;
        if let Some(diff) = diff {
            // Sub-pixel maps: "exact" means within half a pixel, "one" within 1.5.
            if diff < 0.5 {
                self.exact += 1;
            } else if diff < 1.5 {
                self.one += 1;
            }
            if diff <= tol {
                self.within += 1;
            }
        }
    }

    fn merge(a: Self, b: Self) -> Self {
        Self {
            matched: a.matched + b.matched,
            exact: a.exact + b.exact,
            one: a.one + b.one,
            within: a.within + b.within,
        }
    }

    fn figures(&self, tolerance: u32) -> ValidationFigures {
        let share = |n: u64| {
            if self.matched == 0 {
                0.0
            } else {
                n as f64 / self.matched as f64
            }
        };
        ValidationFigures {
            matched: self.matched,
            consistent_exact: share(self.exact),
            off_by_one: share(self.one),
            off_by_more: share(self.matched - self.exact - self.one),
            consistent_within_tolerance: share(self.within),
            tolerance,
        }
    }
}

/// The paper's validation figures of raw left and right maps.
pub fn validation_figures(
    left: &DisparityMap,
    right: &DisparityMap,
    tolerance: u32,
) -> ValidationFigures {
    let tol = tolerance as f32;
    (0..left.height)
        .into_par_iter()
        .map(|y| {
            let (lrow, rrow) = (left.row(y), right.row(y));
            let mut c = Counts::default();
            for (x, &d) in lrow.iter().enumerate() {
                if d.is_finite() {
                    c.add(partner(rrow, x, d, -1.0).map(|p| (p - d).abs()), tol);
                }
            }
            c
        })
        .reduce(Counts::default, Counts::merge)
        .figures(tolerance)
}

/// The paper's score for a disparity range (its Fig. 12): the left pixels the LR check
/// kept inside the range, over the pixels that have a candidate at all in `range` (the
/// right pixel `x − d` exists for some `d`). A match within half a pixel of either end of
/// the range is not evidence: a disparity beyond the range is clamped there, and both views
/// clamp alike, so it passes the LR check; counted, the narrowest range would always win.
pub fn consistency_ratio(checked_left: &DisparityMap, range: schemas::DisparityRange) -> f64 {
    consistency_ratio_within(checked_left, range, None)
}

/// [`consistency_ratio`] over the pixels of `mask` (non-zero) alone: the textured regions
/// a matcher can decide on (the paper matches only the cells; a textureless background is
/// consistent or not by chance and would swamp them).
pub fn consistency_ratio_within(
    checked_left: &DisparityMap,
    range: schemas::DisparityRange,
    mask: Option<&schemas::Mask>,
) -> f64 {
    let w = checked_left.width;
    let has_candidate: Vec<bool> = (0..w as i64)
        .map(|x| (range.min as i64..=range.max as i64).any(|d| (0..w as i64).contains(&(x - d))))
        .collect();
    let (lo, hi) = (range.min as f32 + 0.5, range.max as f32 - 0.5);
    let (mut total, mut inside) = (0usize, 0usize);
    for (i, &d) in checked_left.data.iter().enumerate() {
        if !has_candidate[i % w] || mask.is_some_and(|m| m.data[i] == 0) {
            continue;
        }
        total += 1;
        inside += (d.is_finite() && d > lo && d < hi) as usize;
    }
    inside as f64 / total.max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn map(rows: &[&[f32]]) -> DisparityMap {
        let w = rows[0].len();
        Plane::from_vec(w, rows.len(), rows.concat()).unwrap()
    }
    const X: f32 = INVALID_DISPARITY;

    #[test]
    fn hand_made_row_is_checked_both_ways() {
        // Left x=2 (d=2) → right 0 holds 2: consistent. x=3 (d=1) → right 2 holds 3: off by 2.
        // x=4 (d=2) → right 2 holds 3: off by 1. x=5 (d=0) → right 5 is invalid.
        let left = map(&[&[X, X, 2.0, 1.0, 2.0, 0.0]]);
        let right = map(&[&[2.0, X, 3.0, X, X, X]]);
        let t0 = lr_check(&left, &right, 0);
        assert_eq!(t0.left.row(0), &[X, X, 2.0, X, X, X]);
        assert_eq!(t0.occlusion_left.row(0), &[255, 255, 0, 255, 255, 255]);
        // Right 0 (d=2) → left 2 holds 2: ok. Right 2 (d=3) → left 5 holds 0: bad.
        assert_eq!(t0.right.row(0), &[2.0, X, X, X, X, X]);
        assert_eq!(t0.occlusion_right.row(0), &[0, 255, 255, 255, 255, 255]);
        let t1 = lr_check(&left, &right, 1);
        assert_eq!(t1.left.row(0), &[X, X, 2.0, X, 2.0, X]);
        let t2 = lr_check(&left, &right, 2);
        assert_eq!(t2.left.row(0), &[X, X, 2.0, 1.0, 2.0, X]);
        let f = t1.figures;
        assert_eq!(f, validation_figures(&left, &right, 1));
        assert_eq!(f.matched, 4);
        assert_eq!(f.consistent_exact, 0.25);
        assert_eq!(f.off_by_one, 0.25);
        assert_eq!(f.off_by_more, 0.5);
        assert_eq!(f.consistent_within_tolerance, 0.5);
    }

    #[test]
    fn negative_disparities_point_right() {
        // Left x=1 with d=−2 matches right x=3, which says d=−2 back.
        let left = map(&[&[X, -2.0, X, X, X]]);
        let right = map(&[&[X, X, X, -2.0, X]]);
        let c = lr_check(&left, &right, 0);
        assert_eq!(c.left.row(0)[1], -2.0);
        assert_eq!(c.right.row(0)[3], -2.0);
        assert_eq!(c.figures.consistent_exact, 1.0);
    }

    #[test]
    fn vector_row_check_equals_the_scalar_one() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut next = move || rng.random::<u64>();
        for n in [1, 7, 8, 9, 31, 64, 100] {
            for tol in [0.0, 1.0, 4.0] {
                // Half-pixel disparities hit the rounding edges (x − d = −0.5, k + 0.5).
                let mut row = || -> Vec<f32> {
                    (0..n)
                        .map(|_| match next() % 8 {
                            0 => INVALID_DISPARITY,
                            1 => f32::NAN,
                            2 => (next() % 20) as f32 * 0.5 - 3.0,
                            _ => (next() % 400) as f32 * 0.037 - 2.0,
                        })
                        .collect()
                };
                let (this, other) = (row(), row());
                for sign in [-1.0, 1.0] {
                    let (mut o1, mut c1, mut k1) = (this.clone(), vec![0u8; n], Counts::default());
                    check_row(&this, &other, sign, tol, &mut o1, &mut c1, &mut k1);
                    // The reference: the scalar loop through `partner` alone.
                    let (mut o2, mut c2, mut k2) = (this.clone(), vec![0u8; n], Counts::default());
                    for x in 0..n {
                        let d = this[x];
                        let diff = d
                            .is_finite()
                            .then(|| partner(&other, x, d, sign).map(|p| (p - d).abs()));
                        if let Some(diff) = diff {
                            k2.add(diff, tol);
                        }
                        if !diff.flatten().is_some_and(|d| d <= tol) {
                            o2[x] = INVALID_DISPARITY;
                            c2[x] = 255;
                        }
                    }
                    let same = o1.iter().zip(&o2).all(|(a, b)| a.to_bits() == b.to_bits());
                    assert!(same && c1 == c2, "n {n} tol {tol} sign {sign}");
                    assert_eq!(
                        (k1.matched, k1.exact, k1.one, k1.within),
                        (k2.matched, k2.exact, k2.one, k2.within)
                    );
                }
            }
        }
    }

    #[test]
    fn the_consistency_ratio_counts_kept_pixels_inside_the_range_among_those_with_a_candidate() {
        // 6 columns, range 2..5: columns 0 and 1 have no partner (x − d < 0), so 4 × 2
        // pixels have a candidate. Kept: 3.0 and 4.2 inside; 2.0, 2.4 and 5.0 lie within
        // half a pixel of an end (clamped, not evidence).
        let inf = f32::INFINITY;
        let m = Plane::from_vec(
            6,
            2,
            vec![inf, inf, 2.0, 3.0, inf, 5.0, inf, inf, 2.4, 4.2, inf, inf],
        )
        .unwrap();
        let r = consistency_ratio(&m, schemas::DisparityRange::new(2, 5));
        assert_eq!(r, 2.0 / 8.0);
        // Over 0..8 every column has one (d = 0) and all five are inside.
        let r = consistency_ratio(&m, schemas::DisparityRange::new(0, 8));
        assert_eq!(r, 5.0 / 12.0);
    }
}
