//! The disparity of a flat textured target filling a rectified pair, to a hundredth of a
//! pixel: what a stage step is measured with. A matcher's per-pixel sub-pixel estimates
//! lock towards whole pixels (0.1 px on a flat target, measured: every pixel shares one
//! fractional part, so the median inherits the bias), so the target's disparity is fitted
//! to the images themselves: the best whole shift of the middle of the views by normalised
//! cross-correlation, then a plane `d = a + b·x + c·y` with a gain and an offset between the
//! views by Gauss–Newton on the grey values, both views warped by half the disparity each
//! (the same interpolation in both, so its smoothing cancels). Both views are smoothed
//! first (Gaussian, σ 1.5 px): interpolating white sensor noise lowers its variance by up
//! to half depending on the fractional shift, which on a faint target pulled the fit 0.17 px
//! towards half pixels (measured); smoothed noise interpolates alike at every shift.

use crate::bilinear;
use nalgebra::{SMatrix, SVector};
use schemas::Plane;

/// The region the target is measured over: the middle half of the view each way.
fn region<T>(img: &Plane<T>) -> (usize, usize, usize, usize) {
    (
        img.width / 4,
        3 * img.width / 4,
        img.height / 4,
        3 * img.height / 4,
    )
}

/// The whole shift in `lo..=hi` that best correlates the middle of the views.
fn best_shift(left: &Plane<u8>, right: &Plane<u8>, lo: i32, hi: i32) -> Option<i32> {
    let (x0, x1, y0, y1) = region(left);
    let mut best: Option<(f64, i32)> = None;
    for d in lo..=hi {
        let (mut n, mut sl, mut sr, mut sll, mut srr, mut slr) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        for y in (y0..y1).step_by(2) {
            for x in (x0..x1).step_by(2) {
                let xr = x as i64 - d as i64;
                if xr < 0 || xr >= right.width as i64 {
                    continue;
                }
                let (a, b) = (*left.get(x, y) as f64, *right.get(xr as usize, y) as f64);
                n += 1.0;
                sl += a;
                sr += b;
                sll += a * a;
                srr += b * b;
                slr += a * b;
            }
        }
        if n < 100.0 {
            continue;
        }
        let cov = slr - sl * sr / n;
        let var = (sll - sl * sl / n) * (srr - sr * sr / n);
        if var <= 0.0 {
            continue;
        }
        let ncc = cov / var.sqrt();
        if best.is_none_or(|(b, _)| ncc > b) {
            best = Some((ncc, d));
        }
    }
    best.map(|b| b.1)
}

/// `img` smoothed by a Gaussian of `sigma` px (clamped borders).
fn smooth(img: &Plane<u8>, sigma: f64) -> Plane<f64> {
    let r = (3.0 * sigma).ceil() as i64;
    let k: Vec<f64> = (-r..=r)
        .map(|i| (-((i * i) as f64) / (2.0 * sigma * sigma)).exp())
        .collect();
    let sum: f64 = k.iter().sum();
    let (w, h) = (img.width as i64, img.height as i64);
    let pass = |get: &dyn Fn(i64, i64) -> f64, horizontal: bool| -> Vec<f64> {
        (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                k.iter()
                    .enumerate()
                    .map(|(j, kv)| {
                        let o = j as i64 - r;
                        let (xx, yy) = if horizontal {
                            ((x + o).clamp(0, w - 1), y)
                        } else {
                            (x, (y + o).clamp(0, h - 1))
                        };
                        kv * get(xx, yy)
                    })
                    .sum::<f64>()
                    / sum
            })
            .collect()
    };
    let first = pass(&|x, y| *img.get(x as usize, y as usize) as f64, true);
    let second = pass(&|x, y| first[(y * w + x) as usize], false);
    Plane::from_vec(img.width, img.height, second).expect("size")
}

/// The target's disparity at the view's centre (px, as matched: left x − right x), searched
/// over `lo..=hi`; `None` where the views do not hold a textured target there.
pub fn target_disparity(left: &Plane<u8>, right: &Plane<u8>, lo: i32, hi: i32) -> Option<f64> {
    let d0 = best_shift(left, right, lo, hi)? as f64;
    let (left, right) = (&smooth(left, 1.5), &smooth(right, 1.5));
    let (x0, x1, y0, y1) = region(left);
    let (cx, cy) = (0.5 * (x0 + x1) as f64, 0.5 * (y0 + y1) as f64);
    let scale = 0.5 * (x1 - x0).max(1) as f64;
    // a, b, c (the plane, b and c per half-region), gain, offset.
    let mut p = SVector::<f64, 5>::new(d0, 0.0, 0.0, 1.0, 0.0);
    for _ in 0..30 {
        let mut jtj = SMatrix::<f64, 5, 5>::zeros();
        let mut jtr = SVector::<f64, 5>::zeros();
        for y in (y0..y1).step_by(2) {
            for x in (x0..x1).step_by(2) {
                let (u, v) = ((x as f64 - cx) / scale, (y as f64 - cy) / scale);
                let d = p[0] + p[1] * u + p[2] * v;
                let (xl, xr) = (x as f64 + 0.5 * d, x as f64 - 0.5 * d);
                let yy = y as f64;
                let (Some(l), Some(l1), Some(l0), Some(r), Some(r1), Some(r0)) = (
                    bilinear(left, xl, yy),
                    bilinear(left, xl + 0.5, yy),
                    bilinear(left, xl - 0.5, yy),
                    bilinear(right, xr, yy),
                    bilinear(right, xr + 0.5, yy),
                    bilinear(right, xr - 0.5, yy),
                ) else {
                    continue;
                };
                let (gl, gr) = (l1 - l0, r1 - r0);
                // r = L(x + d/2) − (gain·R(x − d/2) + offset).
                let res = l - (p[3] * r + p[4]);
                let dd = 0.5 * gl + 0.5 * p[3] * gr;
                let j = SVector::<f64, 5>::new(dd, dd * u, dd * v, -r, -1.0);
                jtj += j * j.transpose();
                jtr += j * res;
            }
        }
        let step = jtj.cholesky()?.solve(&(-jtr));
        p += step;
        if !p.iter().all(|v| v.is_finite()) || (p[0] - d0).abs() > 2.0 {
            return None;
        }
        if step[0].abs() < 1e-5 {
            break;
        }
    }
    Some(p[0])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth random texture shifted by `d` px between the views (sampled exactly).
    fn pair(d: f64) -> (Plane<u8>, Plane<u8>) {
        let tex = |x: f64, y: f64| {
            let mut v = 128.0;
            for (k, (fx, fy, ph)) in [
                (0.31, 0.17, 0.3),
                (0.13, 0.41, 1.1),
                (0.23, -0.29, 2.0),
                (0.07, 0.11, 0.7),
                (-0.37, 0.19, 1.7),
            ]
            .iter()
            .enumerate()
            {
                v += (30.0 - 4.0 * k as f64) * (fx * x + fy * y + ph).sin();
            }
            v
        };
        let make = |shift: f64| {
            let data = (0..200 * 160)
                .map(|i| {
                    let (x, y) = ((i % 200) as f64, (i / 200) as f64);
                    tex(x + shift, y).round().clamp(0.0, 255.0) as u8
                })
                .collect();
            Plane::from_vec(200, 160, data).unwrap()
        };
        // Left at x sees what the right shows at x − d.
        (make(0.0), make(d))
    }

    #[test]
    fn a_shifted_texture_reads_its_shift_to_a_hundredth() {
        for d in [-4.82, -3.5, 0.0, 0.27, 2.5, 5.78] {
            let (l, r) = pair(d);
            let got = target_disparity(&l, &r, -8, 8).unwrap();
            assert!((got - d).abs() < 0.01, "{d}: {got}");
        }
    }
}
