//! Ground-truth evaluation in the Middlebury manner.

use schemas::{DisparityMap, Plane};
use serde::Serialize;

/// Error statistics over one set of pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Default)]
pub struct ErrorStats {
    /// Pixels in the set.
    pub pixels: u64,
    /// Share (percent) off by more than 0.5 px, missing values counted as bad.
    pub bad_0_5: f64,
    /// Share (percent) off by more than 1 px.
    pub bad_1: f64,
    /// Share (percent) off by more than 2 px.
    pub bad_2: f64,
    /// Share (percent) off by more than 4 px.
    pub bad_4: f64,
    /// Mean absolute error over pixels with a value.
    pub mean_abs_error: f64,
    /// Root mean square error over pixels with a value.
    pub rms: f64,
    /// Share (percent) of pixels with a value.
    pub density: f64,
}

/// Evaluation against ground truth.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Default)]
pub struct EvalFigures {
    /// Known pixels not occluded in the right view.
    pub nonocc: ErrorStats,
    /// All known pixels.
    pub all: ErrorStats,
}

/// Non-occluded mask from left and right ground truth: a left pixel `x` is visible when
/// the right GT at `round(x − gtL(x))` is known and agrees within 1 px.
pub fn occlusion_from_gt(gt_left: &DisparityMap, gt_right: &DisparityMap) -> Plane<bool> {
    let mut vis = Plane::filled(gt_left.width, gt_left.height, false);
    for y in 0..gt_left.height {
        let (l, r) = (gt_left.row(y), gt_right.row(y));
        for x in 0..gt_left.width {
            let d = l[x];
            if !d.is_finite() {
                continue;
            }
            let xr = (x as f32 - d).round();
            if xr >= 0.0 && (xr as usize) < r.len() {
                let dr = r[xr as usize];
                if dr.is_finite() && (d - dr).abs() <= 1.0 {
                    vis.row_mut(y)[x] = true;
                }
            }
        }
    }
    vis
}

fn stats<'a>(pairs: impl Iterator<Item = (f32, f32)> + 'a) -> ErrorStats {
    let (mut n, mut b05, mut b1, mut b2, mut b4, mut have) = (0u64, 0u64, 0u64, 0u64, 0u64, 0u64);
    let (mut abs, mut sq) = (0f64, 0f64);
    for (d, g) in pairs {
        n += 1;
        if !d.is_finite() {
            b05 += 1;
            b1 += 1;
            b2 += 1;
            b4 += 1;
            continue;
        }
        have += 1;
        let e = (d - g).abs() as f64;
        abs += e;
        sq += e * e;
        b05 += (e > 0.5) as u64;
        b1 += (e > 1.0) as u64;
        b2 += (e > 2.0) as u64;
        b4 += (e > 4.0) as u64;
    }
    let pct = |k: u64| {
        if n == 0 {
            0.0
        } else {
            100.0 * k as f64 / n as f64
        }
    };
    ErrorStats {
        pixels: n,
        bad_0_5: pct(b05),
        bad_1: pct(b1),
        bad_2: pct(b2),
        bad_4: pct(b4),
        mean_abs_error: if have == 0 { 0.0 } else { abs / have as f64 },
        rms: if have == 0 {
            0.0
        } else {
            (sq / have as f64).sqrt()
        },
        density: pct(have),
    }
}

/// Evaluates `disp` against `gt` (unknown GT = non-finite). `visible` restricts the
/// non-occluded figures; without it, every known pixel counts as non-occluded.
pub fn evaluate(
    disp: &DisparityMap,
    gt: &DisparityMap,
    visible: Option<&Plane<bool>>,
) -> EvalFigures {
    assert_eq!((disp.width, disp.height), (gt.width, gt.height));
    let known = || {
        disp.data
            .iter()
            .zip(&gt.data)
            .enumerate()
            .filter(|(_, (_, g))| g.is_finite())
    };
    let all = stats(known().map(|(_, (&d, &g))| (d, g)));
    let nonocc = match visible {
        Some(v) => stats(
            known()
                .filter(|(i, _)| v.data[*i])
                .map(|(_, (&d, &g))| (d, g)),
        ),
        None => all,
    };
    EvalFigures { nonocc, all }
}

#[cfg(test)]
mod tests {
    use super::*;
    use schemas::INVALID_DISPARITY as X;

    #[test]
    fn hand_computed_example() {
        // GT row: 5 5 5 X 2 ; disparity row: 5 6.5 X 1 2.25
        let gt = Plane::from_vec(5, 1, vec![5.0, 5.0, 5.0, X, 2.0]).unwrap();
        let d = Plane::from_vec(5, 1, vec![5.0, 6.5, X, 1.0, 2.25]).unwrap();
        let f = evaluate(&d, &gt, None);
        let a = f.all;
        assert_eq!(a.pixels, 4);
        // Errors: 0, 1.5, missing, 0.25 → bad-0.5: 1.5 + missing = 2/4; bad-1: 2/4; bad-2: 1/4.
        assert_eq!(a.bad_0_5, 50.0);
        assert_eq!(a.bad_1, 50.0);
        assert_eq!(a.bad_2, 25.0);
        assert_eq!(a.bad_4, 25.0);
        assert!((a.mean_abs_error - 1.75 / 3.0).abs() < 1e-12);
        assert!((a.rms - ((1.5f64 * 1.5 + 0.0625) / 3.0).sqrt()).abs() < 1e-12);
        assert_eq!(a.density, 75.0);
    }

    #[test]
    fn occlusion_mask_from_cross_check() {
        // Left x=2 (d=2) → right 0 says 2: visible. x=3 (d=1) → right 2 says 3: occluded.
        let gl = Plane::from_vec(4, 1, vec![X, X, 2.0, 1.0]).unwrap();
        let gr = Plane::from_vec(4, 1, vec![2.0, X, 3.0, X]).unwrap();
        let v = occlusion_from_gt(&gl, &gr);
        assert_eq!(v.data, vec![false, false, true, false]);
        let d = Plane::from_vec(4, 1, vec![0.0, 0.0, 2.0, 9.0]).unwrap();
        let f = evaluate(&d, &gl, Some(&v));
        assert_eq!(f.nonocc.pixels, 1);
        assert_eq!(f.nonocc.bad_1, 0.0);
        assert_eq!(f.all.bad_1, 50.0);
    }
}
