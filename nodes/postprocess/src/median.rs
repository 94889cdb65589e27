//! Median of the valid pixels of each window, eight pixels at a time.
//!
//! Every window is sorted by one data-independent sorting network (Batcher's odd–even
//! merge sort) run on eight neighbouring pixels at once in `[f32; 8]` lanes, which the
//! compiler turns into vector min/max. Invalid pixels (and the outside of the image) are
//! `+inf`, so they sort to the end and the valid values of a window are its first `n`
//! sorted entries: the median is picked per lane from there. A per-pixel selection costs
//! ~80 ns a pixel on sub-pixel maps; this costs a few. Where the CPU has AVX-512 (checked
//! at run time) the 3×3 and 5×5 windows run 16 pixels per vector with the pick in
//! vectors too: at 1280×1024 the 5×5 median drops from ~7 to ~3 ms.

use rayon::prelude::*;
use schemas::DisparityMap;

const LANES: usize = 8;
type Lane = [f32; LANES];

/// Comparators `(i, j)`, `i < j`, of Batcher's odd–even merge sort for `n` elements.
pub(crate) fn sorting_network(n: usize) -> Vec<(u16, u16)> {
    let mut net = Vec::new();
    let mut p = 1;
    while p < n {
        let mut k = p;
        while k >= 1 {
            let mut j = k % p;
            while j + k < n {
                for i in 0..k.min(n - j - k) {
                    if (i + j) / (2 * p) == (i + j + k) / (2 * p) {
                        net.push(((i + j) as u16, (i + j + k) as u16));
                    }
                }
                j += 2 * k;
            }
            k /= 2;
        }
        p *= 2;
    }
    net
}

#[inline(always)]
fn compare_exchange(v: &mut [Lane], i: usize, j: usize) {
    let (a, b) = (v[i], v[j]);
    let mut lo = [0f32; LANES];
    let mut hi = [0f32; LANES];
    for l in 0..LANES {
        // `<` rather than f32::min: no NaN handling, so it maps to one vector min/max.
        lo[l] = if a[l] < b[l] { a[l] } else { b[l] };
        hi[l] = if a[l] < b[l] { b[l] } else { a[l] };
    }
    v[i] = lo;
    v[j] = hi;
}

/// Spells a comparator list out as straight-line code on a local array, so the values
/// live in registers instead of going through memory at every comparator.
macro_rules! network {
    ($cx:ident, $v:ident; $(($i:literal, $j:literal))*) => { $( $cx(&mut $v[..], $i, $j); )* };
}

/// [`sorting_network`]`(9)` unrolled (3×3 windows), on any lane type with its
/// compare-exchange `cx`.
#[inline(always)]
fn sort9<T>(v: &mut [T; 9], cx: impl Fn(&mut [T], usize, usize)) {
    network!(cx, v; (0, 1) (2, 3) (4, 5) (6, 7) (0, 2) (1, 3) (4, 6) (5, 7) (1, 2) (5, 6) (0, 4) (1, 5) (2, 6) (3, 7) (2, 4) (3, 5) (1, 2) (3, 4) (5, 6) (0, 8) (4, 8) (2, 4) (3, 5) (6, 8) (1, 2) (3, 4) (5, 6) (7, 8));
}

/// [`sorting_network`]`(25)` unrolled (5×5 windows, the default), on any lane type
/// with its compare-exchange `cx`.
#[inline(always)]
fn sort25<T>(v: &mut [T; 25], cx: impl Fn(&mut [T], usize, usize)) {
    network!(cx, v; (0, 1) (2, 3) (4, 5) (6, 7) (8, 9) (10, 11) (12, 13) (14, 15) (16, 17) (18, 19) (20, 21) (22, 23) (0, 2) (1, 3) (4, 6) (5, 7) (8, 10) (9, 11) (12, 14) (13, 15) (16, 18) (17, 19) (20, 22) (21, 23) (1, 2) (5, 6) (9, 10) (13, 14) (17, 18) (21, 22) (0, 4) (1, 5) (2, 6) (3, 7) (8, 12) (9, 13) (10, 14) (11, 15) (16, 20) (17, 21) (18, 22) (19, 23) (2, 4) (3, 5) (10, 12) (11, 13) (18, 20) (19, 21) (1, 2) (3, 4) (5, 6) (9, 10) (11, 12) (13, 14) (17, 18) (19, 20) (21, 22) (0, 8) (1, 9) (2, 10) (3, 11) (4, 12) (5, 13) (6, 14) (7, 15) (16, 24) (4, 8) (5, 9) (6, 10) (7, 11) (20, 24) (2, 4) (3, 5) (6, 8) (7, 9) (10, 12) (11, 13) (18, 20) (19, 21) (22, 24) (1, 2) (3, 4) (5, 6) (7, 8) (9, 10) (11, 12) (13, 14) (17, 18) (19, 20) (21, 22) (23, 24) (0, 16) (1, 17) (2, 18) (3, 19) (4, 20) (5, 21) (6, 22) (7, 23) (8, 24) (8, 16) (9, 17) (10, 18) (11, 19) (12, 20) (13, 21) (14, 22) (15, 23) (4, 8) (5, 9) (6, 10) (7, 11) (12, 16) (13, 17) (14, 18) (15, 19) (20, 24) (2, 4) (3, 5) (6, 8) (7, 9) (10, 12) (11, 13) (14, 16) (15, 17) (18, 20) (19, 21) (22, 24) (1, 2) (3, 4) (5, 6) (7, 8) (9, 10) (11, 12) (13, 14) (15, 16) (17, 18) (19, 20) (21, 22) (23, 24));
}

/// Sorts the window `win` (n lanes) by the unrolled network when there is one.
#[inline(always)]
fn sort_window(win: &mut [Lane], net: &[(u16, u16)]) {
    match win.len() {
        9 => {
            let mut v: [Lane; 9] = win.try_into().expect("9");
            sort9(&mut v, compare_exchange);
            win.copy_from_slice(&v);
        }
        25 => {
            let mut v: [Lane; 25] = win.try_into().expect("25");
            sort25(&mut v, compare_exchange);
            win.copy_from_slice(&v);
        }
        _ => {
            for &(i, j) in net {
                compare_exchange(win, i as usize, j as usize);
            }
        }
    }
}

/// Median of the valid pixels of each `(2r+1)²` window, at valid pixels only.
pub fn median_valid(map: &DisparityMap, r: usize) -> DisparityMap {
    #[cfg(target_arch = "x86_64")]
    let wide = avx512::available();
    #[cfg(not(target_arch = "x86_64"))]
    let wide = false;
    median_valid_with(map, r, wide)
}

/// [`median_valid`], with the AVX-512 rows for r = 1 and 2 when `wide` (which the CPU
/// must support).
fn median_valid_with(map: &DisparityMap, r: usize, wide: bool) -> DisparityMap {
    let (w, h) = (map.width, map.height);
    let mut out = map.clone();
    if r == 0 || map.is_empty() {
        return out;
    }
    let side = 2 * r + 1;
    let n = side * side;
    let net = sorting_network(n);
    // +inf border of r pixels and a width rounded up to whole lanes.
    // Whole lanes of the widest vector (16, AVX-512).
    let pw = w.div_ceil(16) * 16 + 2 * r;
    let mut pad = vec![f32::INFINITY; pw * (h + 2 * r)];
    for y in 0..h {
        pad[(y + r) * pw + r..][..w]
            .iter_mut()
            .zip(map.row(y))
            .for_each(|(p, &v)| *p = if v.is_finite() { v } else { f32::INFINITY });
    }
    #[cfg(target_arch = "x86_64")]
    if (r == 1 || r == 2) && wide {
        assert!(avx512::available(), "AVX-512 median on a CPU without it");
        out.data.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            // SAFETY: the CPU has AVX-512F (checked just above); `pad` has rows
            // y..y + 2r + 1 of pw >= w.div_ceil(16) * 16 + 2r values.
            unsafe { avx512::median_row(&pad, pw, r, y, row) }
        });
        return out;
    }
    out.data.par_chunks_mut(w).enumerate().for_each_init(
        || vec![[0f32; LANES]; n],
        |win, (y, row)| {
            for x0 in (0..w).step_by(LANES) {
                let lanes = LANES.min(w - x0);
                if row[x0..x0 + lanes].iter().all(|v| !v.is_finite()) {
                    continue;
                }
                let mut count = [0u32; LANES];
                for dy in 0..side {
                    let src = &pad[(y + dy) * pw + x0..];
                    for dx in 0..side {
                        let lane: Lane = src[dx..dx + LANES].try_into().unwrap();
                        for l in 0..LANES {
                            count[l] += u32::from(lane[l] < f32::INFINITY);
                        }
                        win[dy * side + dx] = lane;
                    }
                }
                sort_window(win, &net);
                for l in 0..lanes {
                    if !row[x0 + l].is_finite() {
                        continue;
                    }
                    let c = count[l] as usize;
                    row[x0 + l] = if c % 2 == 1 {
                        win[c / 2][l]
                    } else {
                        0.5 * (win[c / 2 - 1][l] + win[c / 2][l])
                    };
                }
            }
        },
    );
    out
}

/// The 3×3 and 5×5 medians with AVX-512: 16 pixels per vector, a whole 5×5 window in
/// registers (32 of them), and the per-pixel pick of the middle value in vectors too.
#[cfg(target_arch = "x86_64")]
mod avx512 {
    use std::arch::x86_64::*;

    /// Whether the CPU runs AVX-512F.
    pub fn available() -> bool {
        std::arch::is_x86_feature_detected!("avx512f")
    }

    /// Medians of the valid pixels of row `y` into `row` (valid pixels only), from the
    /// `+inf`-padded map `pad` (`pw` wide, border `r` ∈ {1, 2}).
    ///
    /// # Safety
    /// The CPU must support AVX-512F; `pad` holds rows `y..=y + 2r` of `pw` values and
    /// `pw >= row.len().div_ceil(16) * 16 + 2r`.
    #[target_feature(enable = "avx512f")]
    pub unsafe fn median_row(pad: &[f32], pw: usize, r: usize, y: usize, row: &mut [f32]) {
        assert!(pad.len() >= (y + 2 * r + 1) * pw && pw >= row.len().div_ceil(16) * 16 + 2 * r);
        match r {
            1 => block_loop::<9>(pad, pw, y, row),
            _ => block_loop::<25>(pad, pw, y, row),
        }
    }

    /// The row, 16 pixels at a time, for windows of `N` = 9 or 25 pixels.
    #[inline(always)]
    fn block_loop<const N: usize>(pad: &[f32], pw: usize, y: usize, row: &mut [f32]) {
        let side = if N == 9 { 3 } else { 5 };
        let w = row.len();
        // SAFETY: AVX-512F (this is only inlined into `median_row`); every load reads
        // 16 values at pad[(y + dy) · pw + x0 + dx] with x0 + dx + 16 <= pw (asserted by
        // the caller), stores stay in `row` by the mask.
        unsafe {
            let inf = _mm512_set1_ps(f32::INFINITY);
            let one = _mm512_set1_epi32(1);
            let half = _mm512_set1_ps(0.5);
            for x0 in (0..w).step_by(16) {
                let n = 16.min(w - x0);
                let lanes: __mmask16 = if n == 16 { !0 } else { (1 << n) - 1 };
                let own = _mm512_maskz_loadu_ps(lanes, row.as_ptr().add(x0));
                let valid = _mm512_mask_cmp_ps_mask::<_CMP_LT_OQ>(lanes, own, inf);
                if valid == 0 {
                    continue;
                }
                let mut v = [inf; N];
                let mut count = _mm512_setzero_si512();
                for dy in 0..side {
                    let src = pad.as_ptr().add((y + dy) * pw + x0);
                    for dx in 0..side {
                        let l = _mm512_loadu_ps(src.add(dx));
                        let ok = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(l, inf);
                        count = _mm512_mask_add_epi32(count, ok, count, one);
                        v[dy * side + dx] = l;
                    }
                }
                // As the portable `compare_exchange`: min keeps `b` on ties, max `a`.
                let cx = |v: &mut [__m512], i: usize, j: usize| {
                    let (a, b) = (v[i], v[j]);
                    v[i] = _mm512_min_ps(a, b);
                    v[j] = _mm512_max_ps(b, a);
                };
                if N == 9 {
                    super::sort9((&mut v[..]).try_into().expect("9"), cx);
                } else {
                    super::sort25((&mut v[..]).try_into().expect("25"), cx);
                }
                // The valid values are the first `count` sorted ones: the median is the
                // mean of entries (count − 1) / 2 and count / 2 (one entry when odd).
                let lo_i = _mm512_srli_epi32(_mm512_sub_epi32(count, one), 1);
                let hi_i = _mm512_srli_epi32(count, 1);
                let (mut lo, mut hi) = (inf, inf);
                for (k, &vk) in v.iter().enumerate() {
                    let kv = _mm512_set1_epi32(k as i32);
                    lo = _mm512_mask_mov_ps(lo, _mm512_cmpeq_epi32_mask(lo_i, kv), vk);
                    hi = _mm512_mask_mov_ps(hi, _mm512_cmpeq_epi32_mask(hi_i, kv), vk);
                }
                let odd = _mm512_test_epi32_mask(count, one);
                let mid = _mm512_mask_mov_ps(_mm512_mul_ps(half, _mm512_add_ps(lo, hi)), odd, hi);
                _mm512_mask_storeu_ps(row.as_mut_ptr().add(x0), valid, mid);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use schemas::{INVALID_DISPARITY, Plane};

    /// The definition: collect the valid values of the clipped window, sort, take the middle.
    fn median_naive(map: &DisparityMap, r: usize) -> DisparityMap {
        let (w, h) = (map.width, map.height);
        let mut out = map.clone();
        for y in 0..h {
            for x in 0..w {
                if !map.get(x, y).is_finite() {
                    continue;
                }
                let mut v: Vec<f32> = (y.saturating_sub(r)..(y + r + 1).min(h))
                    .flat_map(|yy| {
                        (x.saturating_sub(r)..(x + r + 1).min(w)).map(move |xx| (xx, yy))
                    })
                    .map(|(xx, yy)| *map.get(xx, yy))
                    .filter(|v| v.is_finite())
                    .collect();
                v.sort_by(f32::total_cmp);
                let c = v.len();
                *out.get_mut(x, y) = if c % 2 == 1 {
                    v[c / 2]
                } else {
                    0.5 * (v[c / 2 - 1] + v[c / 2])
                };
            }
        }
        out
    }

    #[test]
    fn unrolled_networks_are_the_generated_ones() {
        // The literal lists in sort9/sort25 were printed from sorting_network.
        for n in [9, 25] {
            let net = sorting_network(n);
            let mut win: Vec<Lane> = (0..n)
                .map(|i| std::array::from_fn(|l| ((i * 7 + l * 13) % n) as f32))
                .collect();
            let mut by_net = win.clone();
            for &(i, j) in &net {
                compare_exchange(&mut by_net, i as usize, j as usize);
            }
            sort_window(&mut win, &net);
            assert_eq!(win, by_net, "n = {n}");
        }
    }

    #[test]
    fn network_sorts_every_binary_input() {
        // The 0-1 principle: a comparator network that sorts every 0/1 input sorts all.
        for n in 1..=13 {
            let net = sorting_network(n);
            for bits in 0u32..1 << n {
                let mut v: Vec<u32> = (0..n).map(|i| bits >> i & 1).collect();
                for &(i, j) in &net {
                    let (i, j) = (i as usize, j as usize);
                    if v[i] > v[j] {
                        v.swap(i, j);
                    }
                }
                assert!(v.windows(2).all(|p| p[0] <= p[1]), "n={n} input {bits:b}");
            }
        }
    }

    #[test]
    fn equals_the_definition_on_random_maps() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let mut next = move || rng.random::<u64>();
        for (w, h, r) in [
            (1, 1, 1),
            (7, 3, 1),
            (23, 9, 2),
            (40, 17, 2),
            (37, 11, 1),
            (50, 20, 2),
            (9, 30, 3),
            (3, 2, 4),
        ] {
            let data = (0..w * h)
                .map(|_| match next() % 4 {
                    0 => INVALID_DISPARITY,
                    // Repeated integers (paper maps) and sub-pixel values (quality maps).
                    1 => (next() % 5) as f32 - 2.0,
                    _ => (next() % 10_000) as f32 / 97.0 - 30.0,
                })
                .collect();
            let m = Plane::from_vec(w, h, data).unwrap();
            let slow = median_naive(&m, r);
            // The portable rows, and the AVX-512 ones where the CPU has them.
            #[cfg(target_arch = "x86_64")]
            let wide = [false, avx512::available()];
            #[cfg(not(target_arch = "x86_64"))]
            let wide = [false, false];
            for wide in wide {
                let fast = median_valid_with(&m, r, wide);
                for (i, (a, b)) in fast.data.iter().zip(&slow.data).enumerate() {
                    assert!(a == b, "{w}x{h} r={r} avx-512 {wide} pixel {i}: {a} vs {b}");
                }
            }
        }
    }
}
