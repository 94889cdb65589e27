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
                for x in 0..w {
                    // The figures come from the same lookups as the check.
                    let diff = lrow[x]
                        .is_finite()
                        .then(|| partner(rrow, x, lrow[x], -1.0).map(|p| (p - lrow[x]).abs()));
                    if let Some(diff) = diff {
                        c.add(diff, tol);
                    }
                    if !diff.flatten().is_some_and(|d| d <= tol) {
                        ol[x] = INVALID_DISPARITY;
                        ocl[x] = 255;
                    }
                    let ok = rrow[x].is_finite()
                        && partner(lrow, x, rrow[x], 1.0)
                            .is_some_and(|p| (p - rrow[x]).abs() <= tol);
                    if !ok {
                        or[x] = INVALID_DISPARITY;
                        ocr[x] = 255;
                    }
                }
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

#[cfg(test)]
mod tests {
    use super::*;

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
}
