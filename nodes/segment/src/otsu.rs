//! Grey-level histogram and Otsu's threshold.

use schemas::Plane;

/// Counts of each grey level 0..=255.
pub fn histogram(img: &Plane<u8>) -> [u64; 256] {
    // Four counts side by side, added at the end: a run of one level (a variance image's
    // background) otherwise made every increment wait on the one before it.
    let mut parts = [[0u64; 256]; 4];
    let mut quads = img.data.chunks_exact(4);
    for q in &mut quads {
        for (part, &v) in parts.iter_mut().zip(q) {
            part[v as usize] += 1;
        }
    }
    for &v in quads.remainder() {
        parts[0][v as usize] += 1;
    }
    let mut h = [0u64; 256];
    for part in &parts {
        for (o, &c) in h.iter_mut().zip(part) {
            *o += c;
        }
    }
    h
}

/// Otsu's threshold: the `t` maximising the between-class variance of `[0, t)` against
/// `[t, 255]`, so foreground is `value >= t`. `None` when fewer than two levels occur (there
/// is nothing to split). Ties go to the smallest `t`.
pub fn otsu_threshold(hist: &[u64; 256]) -> Option<u8> {
    let total: u64 = hist.iter().sum();
    let sum: f64 = hist
        .iter()
        .enumerate()
        .map(|(i, &c)| i as f64 * c as f64)
        .sum();
    let (mut w0, mut sum0) = (0u64, 0f64);
    let mut best: Option<(f64, u8)> = None;
    for t in 1..256usize {
        w0 += hist[t - 1];
        sum0 += (t - 1) as f64 * hist[t - 1] as f64;
        let w1 = total - w0;
        if w0 == 0 || w1 == 0 {
            continue;
        }
        let (m0, m1) = (sum0 / w0 as f64, (sum - sum0) / w1 as f64);
        let between = w0 as f64 * w1 as f64 * (m0 - m1) * (m0 - m1);
        if best.is_none_or(|(b, _)| between > b) {
            best = Some((between, t as u8));
        }
    }
    best.map(|(_, t)| t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_spikes_split_between_them() {
        let mut h = [0u64; 256];
        h[20] = 100;
        h[200] = 50;
        // Every t in 21..=200 separates the spikes equally well; the first wins.
        assert_eq!(otsu_threshold(&h), Some(21));
    }

    #[test]
    fn bimodal_threshold_lies_between_the_modes() {
        let mut h = [0u64; 256];
        for (i, hv) in h.iter_mut().enumerate() {
            let g = |m: f64, s: f64| (-(i as f64 - m).powi(2) / (2.0 * s * s)).exp();
            *hv = (1000.0 * g(40.0, 8.0) + 400.0 * g(160.0, 15.0)).round() as u64;
        }
        let t = otsu_threshold(&h).unwrap() as usize;
        // The rounded modes leave an empty valley; every t in it splits equally well.
        assert!(h[t - 1] > 0 && h[t] == 0, "{t}");
        assert!((60..=80).contains(&t), "{t}");
    }

    #[test]
    fn a_single_level_has_no_threshold() {
        let mut h = [0u64; 256];
        h[7] = 10;
        assert_eq!(otsu_threshold(&h), None);
        assert_eq!(otsu_threshold(&[0; 256]), None);
    }

    #[test]
    fn histogram_counts_every_pixel() {
        let img = Plane::from_vec(3, 2, vec![0, 0, 5, 255, 5, 5]).unwrap();
        let h = histogram(&img);
        assert_eq!((h[0], h[5], h[255], h.iter().sum::<u64>()), (2, 3, 1, 6));
    }
}
