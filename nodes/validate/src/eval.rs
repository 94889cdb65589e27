//! Ground-truth evaluation in the Middlebury manner.

use schemas::{DisparityMap, Plane};
use serde::Serialize;
use std::path::{Path, PathBuf};

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

/// A map that cannot be compared with the ground truth it was given.
#[derive(Debug, thiserror::Error)]
pub enum SizeError {
    /// The disparity map is not the size of the left ground truth.
    #[error(
        "disparity map '{}' is {}×{} but ground truth '{}' is {}×{}; evaluate maps of the same view and size",
        map.display(), map_size.0, map_size.1, gt.display(), gt_size.0, gt_size.1
    )]
    Map {
        /// The disparity map's file.
        map: PathBuf,
        /// Its width and height.
        map_size: (usize, usize),
        /// The ground truth's file.
        gt: PathBuf,
        /// Its width and height.
        gt_size: (usize, usize),
    },
    /// The right ground truth is not the size of the left one.
    #[error(
        "right ground truth '{}' is {}×{} but the left one is {}×{}",
        right.display(), right_size.0, right_size.1, left_size.0, left_size.1
    )]
    RightTruth {
        /// The right ground truth's file.
        right: PathBuf,
        /// Its width and height.
        right_size: (usize, usize),
        /// The left ground truth's width and height.
        left_size: (usize, usize),
    },
}

/// Checks that the disparity map read from `map` is the size of the ground truth read from `gt_path`.
pub fn check_size(
    disp: &DisparityMap,
    map: &Path,
    gt: &DisparityMap,
    gt_path: &Path,
) -> Result<(), SizeError> {
    if (disp.width, disp.height) == (gt.width, gt.height) {
        return Ok(());
    }
    Err(SizeError::Map {
        map: map.into(),
        map_size: (disp.width, disp.height),
        gt: gt_path.into(),
        gt_size: (gt.width, gt.height),
    })
}

/// The pixels of the left ground truth visible in the right one read from `right_path`
/// ([`occlusion_from_gt`]), once the two are known to be the same size.
pub fn visible_from_right(
    gt_left: &DisparityMap,
    gt_right: &DisparityMap,
    right_path: &Path,
) -> Result<Plane<bool>, SizeError> {
    let (left_size, right_size) = (
        (gt_left.width, gt_left.height),
        (gt_right.width, gt_right.height),
    );
    if left_size != right_size {
        return Err(SizeError::RightTruth {
            right: right_path.into(),
            right_size,
            left_size,
        });
    }
    Ok(occlusion_from_gt(gt_left, gt_right))
}

/// The figures as `microstereo eval` prints them: a header, the non-occluded row
/// (`known` when no occlusion mask was given) and, given one, the row of all known pixels.
pub fn table(f: &EvalFigures, occlusion_known: bool) -> Vec<String> {
    let mut lines = vec![format!(
        "{:<8} {:>9} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8}",
        "pixels", "count", "bad0.5%", "bad1%", "bad2%", "bad4%", "mae", "rms", "dens%"
    )];
    let rows = if occlusion_known {
        vec![("nonocc", f.nonocc), ("all", f.all)]
    } else {
        vec![("known", f.nonocc)]
    };
    for (name, s) in rows {
        lines.push(format!(
            "{:<8} {:>9} {:>8.2} {:>8.2} {:>8.2} {:>8.2} {:>8.3} {:>8.3} {:>8.2}",
            name,
            s.pixels,
            s.bad_0_5,
            s.bad_1,
            s.bad_2,
            s.bad_4,
            s.mean_abs_error,
            s.rms,
            s.density
        ));
    }
    lines
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

    #[test]
    fn table_rows_follow_the_occlusion_mask() {
        let gl = Plane::from_vec(4, 1, vec![X, X, 2.0, 1.0]).unwrap();
        let gr = Plane::from_vec(4, 1, vec![2.0, X, 3.0, X]).unwrap();
        let v = visible_from_right(&gl, &gr, Path::new("r.pfm")).unwrap();
        let d = Plane::from_vec(4, 1, vec![0.0, 0.0, 2.0, 9.0]).unwrap();
        let header =
            "pixels       count  bad0.5%    bad1%    bad2%    bad4%      mae      rms    dens%";
        assert_eq!(
            table(&evaluate(&d, &gl, Some(&v)), true),
            [
                header,
                "nonocc           1     0.00     0.00     0.00     0.00    0.000    0.000   100.00",
                "all              2    50.00    50.00    50.00    50.00    4.000    5.657   100.00",
            ]
        );
        assert_eq!(
            table(&evaluate(&d, &gl, None), false),
            [
                header,
                "known            2    50.00    50.00    50.00    50.00    4.000    5.657   100.00",
            ]
        );
    }

    #[test]
    fn maps_of_other_sizes_are_refused_by_name() {
        let a = Plane::filled(3, 2, 1.0f32);
        let b = Plane::filled(4, 2, 1.0f32);
        assert!(check_size(&a, Path::new("d.pfm"), &a, Path::new("g.png")).is_ok());
        assert_eq!(
            check_size(&a, Path::new("d.pfm"), &b, Path::new("g.png"))
                .unwrap_err()
                .to_string(),
            "disparity map 'd.pfm' is 3×2 but ground truth 'g.png' is 4×2; evaluate maps of the same view and size"
        );
        assert_eq!(
            visible_from_right(&a, &b, Path::new("r.png"))
                .unwrap_err()
                .to_string(),
            "right ground truth 'r.png' is 4×2 but the left one is 3×2"
        );
    }
}
