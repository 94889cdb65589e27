//! Local variance over a `(2M+1)²` window in O(1) per pixel from integral images of I and I².

use crate::BoxSums;
use schemas::Plane;
use serde::{Deserialize, Serialize};

/// How the variance is mapped onto 0–255 before Otsu.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum VarianceScale {
    /// The standard deviation (√variance) scaled so the largest is 255. The variance's heavy
    /// tail (a few edge pixels hundreds of times the cell interior) otherwise crowds every
    /// cell pixel into the lowest bins, where Otsu cannot separate them.
    StdDev,
    /// The variance itself scaled so the largest is 255, as printed in the paper.
    Variance,
    /// `ln(1 + standard deviation)` scaled so the largest is 255: a pipette or a dark
    /// debris edge, several times the cells' contrast, then no longer draws Otsu's
    /// threshold up between the cells and itself (the default).
    #[default]
    LogStdDev,
}

/// Variance of the `(2·radius+1)²` window around every pixel; at the borders the window is
/// clipped to the image (the variance of the pixels that exist).
pub fn local_variance(img: &Plane<u8>, radius: usize) -> Plane<f32> {
    let (w, h) = (img.width, img.height);
    let s1 = BoxSums::new(w, h, |x, y| *img.get(x, y) as u64);
    let s2 = BoxSums::new(w, h, |x, y| (*img.get(x, y) as u64).pow(2));
    let mut out = Plane::filled(w, h, 0f32);
    for y in 0..h {
        for x in 0..w {
            let ((s, n), (s2, _)) = (s1.around(x, y, radius), s2.around(x, y, radius));
            // Exact in integers: n·ΣI² − (ΣI)² ≥ 0, so no cancellation below zero.
            let num = n * s2 - s * s;
            *out.get_mut(x, y) = (num as f64 / (n * n) as f64) as f32;
        }
    }
    out
}

/// Maps a variance image onto 0–255 (rounded); an all-flat image maps to all zeros.
pub fn normalise(var: &Plane<f32>, scale: VarianceScale) -> (Plane<u8>, f32) {
    let f = |v: f32| match scale {
        VarianceScale::StdDev => v.sqrt(),
        VarianceScale::Variance => v,
        VarianceScale::LogStdDev => v.sqrt().ln_1p(),
    };
    let f_inv = |y: f32| match scale {
        VarianceScale::StdDev => y * y,
        VarianceScale::Variance => y,
        VarianceScale::LogStdDev => y.exp_m1().powi(2),
    };
    // Every scale grows with the variance: the largest maps from the largest, and each
    // output level from a range of variances, so one search among 255 bounds replaces a
    // square root and a logarithm per pixel.
    let max = f(var.data.iter().copied().fold(0f32, f32::max));
    let k = if max > 0.0 { 255.0 / max } else { 0.0 };
    let bounds: Vec<f32> = if k > 0.0 {
        (1..=255).map(|i| f_inv((i as f32 - 0.5) / k)).collect()
    } else {
        Vec::new()
    };
    let data = var
        .data
        .iter()
        .map(|&v| {
            if k > 0.0 {
                bounds.partition_point(|&b| b <= v) as u8
            } else {
                0
            }
        })
        .collect();
    (
        Plane::from_vec(var.width, var.height, data).expect("same size"),
        max,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brute(img: &Plane<u8>, r: usize) -> Plane<f32> {
        let mut out = Plane::filled(img.width, img.height, 0f32);
        for y in 0..img.height {
            for x in 0..img.width {
                let mut v = Vec::new();
                for yy in y.saturating_sub(r)..(y + r + 1).min(img.height) {
                    for xx in x.saturating_sub(r)..(x + r + 1).min(img.width) {
                        v.push(*img.get(xx, yy) as f64);
                    }
                }
                let m = v.iter().sum::<f64>() / v.len() as f64;
                let var = v.iter().map(|a| (a - m) * (a - m)).sum::<f64>() / v.len() as f64;
                *out.get_mut(x, y) = var as f32;
            }
        }
        out
    }

    #[test]
    fn integral_variance_matches_the_direct_sum() {
        let data: Vec<u8> = (0..23 * 17)
            .map(|i| ((i * 97 + i * i) % 251) as u8)
            .collect();
        let img = Plane::from_vec(23, 17, data).unwrap();
        for r in [0, 1, 3, 9] {
            let a = local_variance(&img, r);
            let b = brute(&img, r);
            for (p, q) in a.data.iter().zip(&b.data) {
                assert!((p - q).abs() <= 1e-3 * q.max(1.0), "r={r}: {p} vs {q}");
            }
        }
    }

    #[test]
    fn flat_image_has_zero_variance_and_normalises_to_zero() {
        let img = Plane::filled(8, 6, 77u8);
        let v = local_variance(&img, 2);
        assert!(v.data.iter().all(|&x| x == 0.0));
        let (n, max) = normalise(&v, VarianceScale::StdDev);
        assert_eq!(max, 0.0);
        assert!(n.data.iter().all(|&x| x == 0));
    }

    #[test]
    fn normalisation_puts_the_largest_at_255() {
        let v = Plane::from_vec(4, 1, vec![0.0, 4.0, 16.0, 64.0]).unwrap();
        let (s, max) = normalise(&v, VarianceScale::StdDev);
        assert_eq!(max, 8.0);
        assert_eq!(s.data, vec![0, 64, 128, 255]);
        let (l, _) = normalise(&v, VarianceScale::Variance);
        assert_eq!(l.data, vec![0, 16, 64, 255]);
        // ln(1 + σ) for σ = 0, 2, 4, 8: 0, 1.0986, 1.6094, 2.1972 of 2.1972.
        let (g, max) = normalise(&v, VarianceScale::LogStdDev);
        assert!((max - 9f32.ln()).abs() < 1e-6);
        assert_eq!(g.data, vec![0, 128, 187, 255]);
    }
}
