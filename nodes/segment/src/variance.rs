//! Local variance over a `(2M+1)²` window in O(1) per pixel from sliding sums of I and I².

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
/// clipped to the image (the variance of the pixels that exist). The window's sums of I and
/// I² slide: per column over the window's rows, then along the row, in integers, so every
/// value is exact (and the same as from integral images, the way it was computed before,
/// without their two 8-byte-per-pixel tables).
pub fn local_variance(img: &Plane<u8>, radius: usize) -> Plane<f32> {
    let (w, h) = (img.width, img.height);
    let mut out = Plane::filled(w, h, 0f32);
    if w == 0 || h == 0 {
        return out;
    }
    let (mut c1, mut c2) = (vec![0u64; w], vec![0u64; w]);
    let add_row = |c1: &mut [u64], c2: &mut [u64], y: usize, sign_add: bool| {
        for (x, &v) in img.row(y).iter().enumerate() {
            let v = v as u64;
            if sign_add {
                c1[x] += v;
                c2[x] += v * v;
            } else {
                c1[x] -= v;
                c2[x] -= v * v;
            }
        }
    };
    for y in 0..radius.min(h) {
        add_row(&mut c1, &mut c2, y, true);
    }
    // Per row, prefix sums of the column sums: every window's sums are two lookups, and the
    // columns whose window lies whole in the row share one count, so their loop vectorises.
    let (mut p1, mut p2) = (vec![0u64; w + 1], vec![0u64; w + 1]);
    for y in 0..h {
        if y + radius < h {
            add_row(&mut c1, &mut c2, y + radius, true);
        }
        if y > radius {
            add_row(&mut c1, &mut c2, y - radius - 1, false);
        }
        let rows = (y + radius + 1).min(h) - y.saturating_sub(radius);
        // Running sums in registers: read back from the table, each waited on its store.
        let (mut a1, mut a2) = (0u64, 0u64);
        for (x, (&v1, &v2)) in c1.iter().zip(&c2).enumerate() {
            a1 += v1;
            a2 += v2;
            p1[x + 1] = a1;
            p2[x + 1] = a2;
        }
        let row = out.row_mut(y);
        let at = |x0: usize, x1: usize| {
            let n = (rows * (x1 - x0)) as u64;
            let (s1, s2) = (p1[x1] - p1[x0], p2[x1] - p2[x0]);
            // Exact in integers: n·ΣI² − (ΣI)² ≥ 0, so no cancellation below zero.
            let num = n * s2 - s1 * s1;
            (num as f64 / (n * n) as f64) as f32
        };
        let (lo, hi) = (radius.min(w), w.saturating_sub(radius).max(radius.min(w)));
        for x in (0..lo).chain(hi..w) {
            row[x] = at(x.saturating_sub(radius), (x + radius + 1).min(w));
        }
        let m = hi - lo;
        if m > 0 {
            let span = 2 * radius + 1;
            let n = (rows * span) as u64;
            let nn = (n * n) as f64;
            let (t1, b1) = (&p1[span..][..m], &p1[..m]);
            let (t2, b2) = (&p2[span..][..m], &p2[..m]);
            for (j, o) in row[lo..hi].iter_mut().enumerate() {
                let (s1, s2) = (t1[j] - b1[j], t2[j] - b2[j]);
                *o = ((n * s2 - s1 * s1) as f64 / nn) as f32;
            }
        }
    }
    out
}

/// The scaled largest variance and the 255 variances at which the levels 1–255 begin
/// (none when every variance is 0), for a largest variance `largest`.
fn level_bounds(largest: f32, scale: VarianceScale) -> (f32, Vec<f32>) {
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
    let max = f(largest);
    let k = if max > 0.0 { 255.0 / max } else { 0.0 };
    let bounds: Vec<f32> = if k > 0.0 {
        (1..=255).map(|i| f_inv((i as f32 - 0.5) / k)).collect()
    } else {
        Vec::new()
    };
    (max, bounds)
}

/// Maps a variance image onto 0–255 (rounded); an all-flat image maps to all zeros.
pub fn normalise(var: &Plane<f32>, scale: VarianceScale) -> (Plane<u8>, f32) {
    let (max, bounds) = level_bounds(var.data.iter().copied().fold(0f32, f32::max), scale);
    let data = if !bounds.is_empty() {
        let level = Levels::new(&bounds);
        var.data.iter().map(|&v| level.of(v)).collect()
    } else {
        vec![0; var.data.len()]
    };
    (
        Plane::from_vec(var.width, var.height, data).expect("same size"),
        max,
    )
}

/// [`normalise`] of [`local_variance`], to the same bits, without the variance plane: the
/// windows that lie whole in the image keep only their numerators `n·ΣI² − (ΣI)²` as 32-bit
/// integers (exact, and below 2³¹ as the level table's keys need, while `n²·255² < 2³¹`:
/// windows up to 13×13; wider ones take the two steps), which map to levels through integer
/// bounds; the clipped windows of the border take the two steps on strips. The two steps
/// were over a third of a view's segmentation, in 64-bit products (not vectorised on AVX2)
/// and a division per pixel.
pub fn variance_levels(img: &Plane<u8>, radius: usize, scale: VarianceScale) -> (Plane<u8>, f32) {
    let (w, h) = (img.width, img.height);
    let span = 2 * radius + 1;
    let n = (span * span) as u64;
    if radius == 0 || w <= span || h <= span || n * n * 255 * 255 >= 1 << 31 {
        return normalise(&local_variance(img, radius), scale);
    }
    let r = radius;
    // The clipped windows: the top and bottom `r` rows, and the first and last `r` columns
    // of the rows between, each read from a strip `2r` wide, where it is clipped the same
    // way (the window of a pixel within `r` of the edge reaches at most `2r − 1` in).
    let strip = |x0: usize, y0: usize, sw: usize, sh: usize| -> Plane<f32> {
        let mut data = Vec::with_capacity(sw * sh);
        for y in y0..y0 + sh {
            data.extend_from_slice(&img.row(y)[x0..x0 + sw]);
        }
        local_variance(&Plane::from_vec(sw, sh, data).expect("strip size"), r)
    };
    let top = strip(0, 0, w, 2 * r);
    let bottom = strip(0, h - 2 * r, w, 2 * r);
    let left = strip(0, 0, 2 * r, h);
    let right = strip(w - 2 * r, 0, 2 * r, h);
    // A row's clipped windows: the whole row at the top and bottom, else its first and
    // last `r` pixels.
    let border = |y: usize| -> [&[f32]; 2] {
        if y < r {
            [top.row(y), &[]]
        } else if y >= h - r {
            [bottom.row(y - (h - 2 * r)), &[]]
        } else {
            [&left.row(y)[..r], &right.row(y)[r..]]
        }
    };
    let mut largest = 0f32;
    for y in 0..h {
        for part in border(y) {
            largest = part.iter().copied().fold(largest, f32::max);
        }
    }
    // The numerators of the whole windows, row by row from column sums that slide down.
    let (iw, ih) = (w - 2 * r, h - 2 * r);
    // Filled row by row as made (a zeroed table first cost a pass of its own).
    let mut num: Vec<u32> = Vec::with_capacity(iw * ih);
    let (mut c1, mut c2) = (vec![0u32; w], vec![0u32; w]);
    let (mut s1, mut s2) = (vec![0u32; iw], vec![0u32; iw]);
    let doublings = (usize::BITS - 1 - span.leading_zeros()) as usize;
    let (mut q1, mut q2) = (
        vec![vec![0u32; w]; doublings],
        vec![vec![0u32; w]; doublings],
    );
    let n32 = n as u32;
    let mut most = 0u32;
    for y in r..h - r {
        let mut add = |yy: usize, enters: bool| {
            for ((a, b), &v) in c1.iter_mut().zip(c2.iter_mut()).zip(img.row(yy)) {
                let v = v as u32;
                if enters {
                    *a += v;
                    *b += v * v;
                } else {
                    *a -= v;
                    *b -= v * v;
                }
            }
        };
        if y == r {
            (0..span).for_each(|yy| add(yy, true));
        } else {
            add(y + r, true);
            add(y - r - 1, false);
        }
        // Each window's sums added up from its columns: independent per pixel, so they
        // vectorise (a running prefix sum waits on itself pixel by pixel); from sums over
        // 2, 4, … columns, each into a table of its own (one pass per doubling and per set
        // bit of the window's width: 4 for 7 columns instead of 8).
        window_sums(&c1, span, &mut s1, &mut q1);
        window_sums(&c2, span, &mut s2, &mut q2);
        num.extend(s1.iter().zip(&s2).map(|(&a, &b)| n32 * b - a * a));
        most = num[(y - r) * iw..].iter().copied().fold(most, u32::max);
    }
    let nn = (n * n) as f64;
    let value = |v: u32| (v as f64 / nn) as f32;
    let (max, bounds) = level_bounds(largest.max(value(most)), scale);
    let mut data = vec![0u8; w * h];
    if bounds.is_empty() {
        return (Plane::from_vec(w, h, data).expect("size"), max);
    }
    let levels = Levels::new(&bounds);
    // The whole windows' integer bounds: the least numerator whose variance reaches each
    // bound (the variance never falls as the numerator grows), past `most` where none does.
    let limits: Vec<u32> = bounds
        .iter()
        .map(|&b| {
            let (mut lo, mut hi) = (0u64, most as u64 + 1);
            while lo < hi {
                let mid = (lo + hi) / 2;
                if value(mid as u32) >= b {
                    hi = mid
                } else {
                    lo = mid + 1
                }
            }
            lo.min(u32::MAX as u64) as u32
        })
        .collect();
    let whole = IntLevels::new(&limits, most);
    for y in 0..h {
        let row = &mut data[y * w..][..w];
        if y < r || y >= h - r {
            for (o, &v) in row.iter_mut().zip(border(y)[0]) {
                *o = levels.of(v);
            }
            continue;
        }
        let [lb, rb] = border(y);
        for (o, &v) in row[..r].iter_mut().zip(lb) {
            *o = levels.of(v);
        }
        for (o, &v) in row[w - r..].iter_mut().zip(rb) {
            *o = levels.of(v);
        }
        for (o, &v) in row[r..w - r].iter_mut().zip(&num[(y - r) * iw..][..iw]) {
            *o = whole.of(v);
        }
    }
    (Plane::from_vec(w, h, data).expect("size"), max)
}

/// `out[x] = c[x] + … + c[x + span − 1]` for every `x` of `out` (`out.len() + span − 1 ≤
/// c.len()`, the sums below 2³²): `parts[k]` gets the sums over `2^(k+1)` columns (one
/// table per doubling, so that each pass reads one table and writes another and
/// vectorises), and each set bit of `span` adds one of the tables at its offset. Integer
/// sums: the same as adding the columns one by one.
fn window_sums(c: &[u32], span: usize, out: &mut [u32], parts: &mut [Vec<u32>]) {
    let n = out.len();
    let mut width = 1;
    for k in 0..parts.len() {
        let (done, rest) = parts.split_at_mut(k);
        let prev: &[u32] = if k == 0 { c } else { &done[k - 1] };
        let next = &mut rest[0];
        let len = prev.len() - width;
        for ((o, &a), &b) in next[..len].iter_mut().zip(prev).zip(&prev[width..]) {
            *o = a + b;
        }
        width *= 2;
    }
    let mut offset = 0;
    let mut first = true;
    for bit in (0..=parts.len()).rev() {
        let width = 1 << bit;
        if span & width == 0 {
            continue;
        }
        let table: &[u32] = if bit == 0 { c } else { &parts[bit - 1] };
        let add = &table[offset..offset + n];
        if first {
            out.copy_from_slice(add);
            first = false;
        } else {
            for (o, &a) in out.iter_mut().zip(add) {
                *o += a;
            }
        }
        offset += width;
    }
}

/// [`Levels`] over integer numerators (below 2³¹): the number of `limits` at or below a
/// value, through a table over the top bits of the value as an `f32`, buckets as fine
/// relative to the value as the levels' own spacing on every scale (fixed-width buckets held
/// dozens of the levels near the background's low variance, each pixel there a search).
struct IntLevels<'a> {
    limits: &'a [u32],
    /// Per bucket: the count at its smallest value (bits 32–39), the next limit (low 32
    /// bits; at most one more lies in the bucket) or bit 40 set where more do.
    buckets: Vec<u64>,
}

impl<'a> IntLevels<'a> {
    fn key(v: u32) -> usize {
        ((v as i32 as f32).to_bits() >> BUCKET_SHIFT) as usize
    }

    /// The table for values up to `most` (below 2³¹).
    fn new(limits: &'a [u32], most: u32) -> Self {
        let n = limits.len();
        let last = Self::key(most);
        let mut buckets = Vec::with_capacity(last + 1);
        // The integers a bucket holds lie between its float ends, give or take one (the
        // conversion rounds, and never out of order): its counts at those bounds hold every
        // count within. Both bounds grow with the bucket: the counts only move forward.
        let (mut below_lo, mut below_hi) = (0, 0);
        for b in 0..=last as u32 {
            let lo = f32::from_bits(b << BUCKET_SHIFT) as f64;
            let hi = f32::from_bits((b << BUCKET_SHIFT) | ((1 << BUCKET_SHIFT) - 1)) as f64;
            let lo = (lo.floor() - 1.0).max(0.0) as u64;
            let hi = (hi.ceil() + 1.0).min(u32::MAX as f64) as u64;
            while below_lo < n && limits[below_lo] as u64 <= lo {
                below_lo += 1;
            }
            while below_hi < n && limits[below_hi] as u64 <= hi {
                below_hi += 1;
            }
            let next = limits.get(below_lo).copied().unwrap_or(u32::MAX) as u64;
            let many = u64::from(below_hi > below_lo + 1) << 40;
            buckets.push(many | (below_lo as u64) << 32 | next);
        }
        Self { limits, buckets }
    }

    fn of(&self, v: u32) -> u8 {
        let e = self.buckets[Self::key(v)];
        let lo = (e >> 32) as u8;
        if e >> 40 == 0 {
            return lo + u8::from(e as u32 <= v);
        }
        let lo = lo as usize;
        (lo + self.limits[lo..].partition_point(|&l| l <= v)) as u8
    }
}

/// Bits of an `f32`'s pattern that pick a bucket of [`Levels`].
const BUCKET_SHIFT: u32 = 16;

/// The number of `bounds` at or below a value, `bounds.partition_point(|b| b <= v)`, found
/// through a table over the top bits of the value's pattern (which orders non-negative
/// floats as their values): most buckets hold one answer, the rest a few to search. A
/// 1280×1024 view's variance took a binary search of 255 bounds per pixel before.
struct Levels<'a> {
    bounds: &'a [f32],
    /// Per bucket, the answer at its smallest and at its largest value.
    buckets: Vec<(u8, u8)>,
}

impl<'a> Levels<'a> {
    fn new(bounds: &'a [f32]) -> Self {
        // The counts of bounds at or below each bucket's ends, in one sweep: both ends grow
        // with the bucket (non-negative patterns order as their values), so the counts only
        // move forward (65,536 pairs of binary searches: the levels of a 1280×1024 view took
        // 3.5 ms with them, 3.1 ms now).
        let n = bounds.len();
        let positive = 1u32 << (31 - BUCKET_SHIFT);
        let mut buckets = Vec::with_capacity(1 << (32 - BUCKET_SHIFT));
        let (mut below_lo, mut below_hi) = (0, 0);
        for i in 0..1u32 << (32 - BUCKET_SHIFT) {
            let lo = f32::from_bits(i << BUCKET_SHIFT);
            let hi = f32::from_bits((i << BUCKET_SHIFT) | ((1 << BUCKET_SHIFT) - 1));
            // Negative and NaN patterns (top bit set) are never variances: searched.
            if i >= positive || hi.is_nan() {
                buckets.push((0, n as u8));
                continue;
            }
            while below_lo < n && bounds[below_lo] <= lo {
                below_lo += 1;
            }
            while below_hi < n && bounds[below_hi] <= hi {
                below_hi += 1;
            }
            buckets.push((below_lo as u8, below_hi as u8));
        }
        Self { bounds, buckets }
    }

    fn of(&self, v: f32) -> u8 {
        let (lo, hi) = self.buckets[(v.to_bits() >> BUCKET_SHIFT) as usize];
        // Most buckets hold one answer or straddle one bound: that comparison without a
        // branch (a quarter of a view's pixels fell in straddling buckets, half of them
        // mispredicted), a search for the rest.
        // Widened: `lo` is 255 where every bound lies below, and `lo + 1` must not wrap.
        if u16::from(hi) <= u16::from(lo) + 1 {
            let b = self
                .bounds
                .get(lo as usize)
                .copied()
                .unwrap_or(f32::INFINITY);
            return lo + u8::from((hi > lo) & (b <= v));
        }
        let (lo, hi) = (lo as usize, hi as usize);
        (lo + self.bounds[lo..hi].partition_point(|&b| b <= v)) as u8
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn window_sums_add_every_column_of_the_window() {
        let c: Vec<u32> = (0..50u32).map(|i| i * 7919 % 1013).collect();
        for span in 1..=17usize {
            let n = c.len() + 1 - span;
            let doublings = (usize::BITS - 1 - span.leading_zeros()) as usize;
            let (mut out, mut parts) = (vec![0; n], vec![vec![0; c.len()]; doublings]);
            super::window_sums(&c, span, &mut out, &mut parts);
            for (x, &o) in out.iter().enumerate() {
                assert_eq!(o, c[x..x + span].iter().sum::<u32>(), "span {span} at {x}");
            }
        }
    }

    use super::*;
    use crate::BoxSums;

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

    /// A linear congruential generator's successive states from `seed`: test values.
    fn lcg(mut x: u64) -> impl FnMut() -> u64 {
        move || {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            x
        }
    }

    /// The table's levels are the binary search's, for every scale, on values drawn across
    /// the whole range and on the bounds themselves and their neighbours.
    #[test]
    fn table_levels_match_the_search() {
        let mut bits = lcg(12345);
        let mut next = || (bits() >> 11) as f64 / (1u64 << 53) as f64;
        for scale in [
            VarianceScale::StdDev,
            VarianceScale::Variance,
            VarianceScale::LogStdDev,
        ] {
            for max in [3.0f32, 817.5, 16256.0] {
                let mut v: Vec<f32> = (0..20_000)
                    .map(|_| (max as f64 * next().powi(3)) as f32)
                    .collect();
                v.push(0.0);
                v.push(max);
                let img = Plane::from_vec(v.len(), 1, v.clone()).unwrap();
                let (levels, m) = normalise(&img, scale);
                let f = |v: f32| match scale {
                    VarianceScale::StdDev => v.sqrt(),
                    VarianceScale::Variance => v,
                    VarianceScale::LogStdDev => v.sqrt().ln_1p(),
                };
                let k = 255.0 / f(max);
                assert_eq!(m, f(max));
                let f_inv = |y: f32| match scale {
                    VarianceScale::StdDev => y * y,
                    VarianceScale::Variance => y,
                    VarianceScale::LogStdDev => y.exp_m1().powi(2),
                };
                let bounds: Vec<f32> = (1..=255).map(|i| f_inv((i as f32 - 0.5) / k)).collect();
                for (p, &val) in v.iter().enumerate() {
                    let want = bounds.partition_point(|&b| b <= val) as u8;
                    assert_eq!(*levels.get(p, 0), want, "{scale:?} max {max} value {val}");
                }
                let table = Levels::new(&bounds);
                // The swept table is the one of two binary searches per bucket.
                let count = |v: f32| bounds.partition_point(|&b| b <= v) as u8;
                for (i, &bucket) in table.buckets.iter().enumerate() {
                    let i = i as u32;
                    let lo = f32::from_bits(i << BUCKET_SHIFT);
                    let hi = f32::from_bits((i << BUCKET_SHIFT) | ((1 << BUCKET_SHIFT) - 1));
                    let want = if i >= 1 << (31 - BUCKET_SHIFT) || hi.is_nan() {
                        (0, bounds.len() as u8)
                    } else {
                        (count(lo), count(hi))
                    };
                    assert_eq!(bucket, want, "bucket {i}");
                }
                for &b in &bounds {
                    for t in [
                        b,
                        f32::from_bits(b.to_bits() - 1),
                        f32::from_bits(b.to_bits() + 1),
                    ] {
                        assert_eq!(table.of(t), bounds.partition_point(|&c| c <= t) as u8);
                    }
                }
            }
        }
    }

    /// The fused levels are the two steps' to the bit, on noise, on smooth ramps with
    /// steps, on flat images, at every scale, radius and size (thin images included).
    #[test]
    fn variance_levels_equal_normalised_variance() {
        let mut bits = lcg(99);
        let mut next = || (bits() >> 33) as u32;
        let mut images = Vec::new();
        for (w, h) in [
            (1, 1),
            (5, 9),
            (16, 16),
            (17, 18),
            (64, 40),
            (97, 61),
            (300, 7),
        ] {
            let noise: Vec<u8> = (0..w * h).map(|_| next() as u8).collect();
            let ramp: Vec<u8> = (0..w * h)
                .map(|i| {
                    let (px, py) = (i % w, i / w);
                    let step = if (px / 7 + py / 5) % 3 == 0 { 90 } else { 0 };
                    ((px + 2 * py) % 120 + step + (next() % 3) as usize) as u8
                })
                .collect();
            let spots: Vec<u8> = (0..w * h)
                .map(|i| {
                    if next() % 50 == 0 {
                        255
                    } else {
                        140 + (i % 2) as u8
                    }
                })
                .collect();
            images.push(Plane::from_vec(w, h, noise).unwrap());
            images.push(Plane::from_vec(w, h, ramp).unwrap());
            images.push(Plane::from_vec(w, h, spots).unwrap());
            images.push(Plane::filled(w, h, 200u8));
        }
        for img in &images {
            for r in [1, 2, 3, 4, 7, 8] {
                for scale in [
                    VarianceScale::StdDev,
                    VarianceScale::Variance,
                    VarianceScale::LogStdDev,
                ] {
                    let want = normalise(&local_variance(img, r), scale);
                    let got = variance_levels(img, r, scale);
                    assert_eq!(
                        got.1.to_bits(),
                        want.1.to_bits(),
                        "{}×{} r {r} {scale:?}",
                        img.width,
                        img.height
                    );
                    assert!(
                        got.0.data == want.0.data,
                        "{}×{} r {r} {scale:?}",
                        img.width,
                        img.height
                    );
                }
            }
        }
    }

    /// [`local_variance`] from integral images, the reference it is checked against.
    fn local_variance_integral(img: &Plane<u8>, radius: usize) -> Plane<f32> {
        let (w, h) = (img.width, img.height);
        let s1 = BoxSums::new(w, h, |x, y| *img.get(x, y) as u64);
        let s2 = BoxSums::new(w, h, |x, y| (*img.get(x, y) as u64).pow(2));
        let mut out = Plane::filled(w, h, 0f32);
        for y in 0..h {
            for x in 0..w {
                let ((s, n), (s2, _)) = (s1.around(x, y, radius), s2.around(x, y, radius));
                let num = n * s2 - s * s;
                *out.get_mut(x, y) = (num as f64 / (n * n) as f64) as f32;
            }
        }
        out
    }

    /// The sliding sums give the integral images' values bit for bit, at every radius
    /// (wider than the image too) and size.
    #[test]
    fn sliding_variance_equals_the_integral_one() {
        for (w, h) in [(1, 1), (1, 7), (9, 1), (23, 17), (64, 40)] {
            let data: Vec<u8> = (0..w * h)
                .map(|i| ((i * 97 + i * i * 31) % 256) as u8)
                .collect();
            let img = Plane::from_vec(w, h, data).unwrap();
            for r in [0, 1, 2, 3, 9, 70] {
                assert_eq!(
                    local_variance(&img, r).data,
                    local_variance_integral(&img, r).data,
                    "{w}×{h}, r = {r}"
                );
            }
        }
    }
}
