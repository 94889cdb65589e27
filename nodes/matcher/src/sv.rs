//! The support value (SV) of the paper, bit-packed.
//!
//! Each pixel gets a descriptor: its W×W window binarised against the window's own mean
//! (bit = 1 where pixel ≥ mean), packed row-major into `words` u64s. The support value of
//! two windows is the sum of the weights of the positions where the bits agree. With equal
//! weights that is `W² − popcount(a ^ b)`; with decreasing weights (centre `R + 1`, one less
//! per ring outwards, outermost ring 1, `R = (W − 1) / 2`) it is
//! `Σ_k (|M_k| − popcount((a ^ b) & M_k))` over the nested squares `M_k` = "weight ≥ k":
//! one masked popcount per ring. Windows are clamped at the image border (edge pixels
//! repeat), both here and in [`support_value_naive`].

use rayon::prelude::*;
use schemas::Plane;
use serde::{Deserialize, Serialize};

/// Smallest supported window side.
pub const MIN_WINDOW: usize = 3;
/// Largest supported window side.
pub const MAX_WINDOW: usize = 31;

/// Weight matrix W(i, j) of the support value.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum Weights {
    /// Every position weighs 1.
    #[default]
    Equal,
    /// Centre weighs R + 1, falling by one per ring to 1 on the outermost ring.
    Decreasing,
}

/// The weight of window position `(i, j)` (0-based, row `i`, column `j`) for window side `w`.
pub fn weight_at(weights: Weights, w: usize, i: usize, j: usize) -> u32 {
    let r = (w - 1) / 2;
    match weights {
        Weights::Equal => 1,
        Weights::Decreasing => {
            let ring = i.abs_diff(r).max(j.abs_diff(r));
            (r + 1 - ring) as u32
        }
    }
}

/// Precomputed masks that turn a descriptor XOR into a support value.
#[derive(Clone, Debug)]
pub struct SvKernel {
    /// Window side W.
    pub window: usize,
    /// u64 words per descriptor.
    pub words: usize,
    /// Weight type.
    pub weights: Weights,
    /// Nested masks M_k (k = 1..=R+1), `words` u64s each; empty for equal weights.
    masks: Vec<u64>,
    /// |M_k| for each mask.
    mask_sizes: Vec<u32>,
    /// The largest possible support value (all positions agree).
    pub max: u32,
}

impl SvKernel {
    /// Builds the kernel for an odd window side in `MIN_WINDOW..=MAX_WINDOW`.
    pub fn new(window: usize, weights: Weights) -> Self {
        assert!(window % 2 == 1 && (MIN_WINDOW..=MAX_WINDOW).contains(&window));
        let words = (window * window).div_ceil(64);
        let r = (window - 1) / 2;
        let mut masks = Vec::new();
        let mut mask_sizes = Vec::new();
        if weights == Weights::Decreasing {
            for k in 1..=r + 1 {
                let mut m = vec![0u64; words];
                let mut n = 0;
                for i in 0..window {
                    for j in 0..window {
                        if weight_at(weights, window, i, j) >= k as u32 {
                            let bit = i * window + j;
                            m[bit / 64] |= 1 << (bit % 64);
                            n += 1;
                        }
                    }
                }
                masks.extend(m);
                mask_sizes.push(n);
            }
        }
        let max = (0..window)
            .flat_map(|i| (0..window).map(move |j| (i, j)))
            .map(|(i, j)| weight_at(weights, window, i, j))
            .sum();
        Self {
            window,
            words,
            weights,
            masks,
            mask_sizes,
            max,
        }
    }

    /// Support value of two descriptors of `words` u64s each.
    #[inline(always)]
    pub fn support(&self, a: &[u64], b: &[u64]) -> u32 {
        match self.weights {
            Weights::Equal => {
                let mut diff = 0;
                for k in 0..self.words {
                    diff += (a[k] ^ b[k]).count_ones();
                }
                self.max - diff
            }
            Weights::Decreasing => {
                let mut sv = 0;
                for (m, &size) in self.masks.chunks_exact(self.words).zip(&self.mask_sizes) {
                    let mut diff = 0;
                    for k in 0..self.words {
                        diff += ((a[k] ^ b[k]) & m[k]).count_ones();
                    }
                    sv += size - diff;
                }
                sv
            }
        }
    }
}

/// Equal-weight support values of one row for one disparity, `NW` words per descriptor:
/// `out[x] = max − popcount(left[x] ^ right[x − d])` for `x` in `xlo..xhi`. Rows are
/// word-planar (word `k` of pixel `x` at `k * width + x`), so every word is a contiguous
/// run that vectorises.
#[inline(always)]
fn sv_row_equal<const NW: usize>(
    max: u32,
    left: &[u64],
    right: &[u64],
    xlo: usize,
    xhi: usize,
    d: isize,
    out: &mut [u32],
) {
    let w = left.len() / NW;
    let n = xhi - xlo;
    let rs = (xlo as isize - d) as usize;
    let l: [&[u64]; NW] = std::array::from_fn(|k| &left[k * w + xlo..k * w + xhi]);
    let r: [&[u64]; NW] = std::array::from_fn(|k| &right[k * w + rs..k * w + rs + n]);
    let out = &mut out[xlo..xhi];
    let mut i = 0;
    #[cfg(target_arch = "x86_64")]
    if has_vpopcnt() {
        // SAFETY: the CPU supports the features (checked at run time); slices are n long.
        unsafe { i = sv_row_equal_vpopcnt::<NW>(max, &l, &r, out) };
    }
    for x in i..n {
        let mut diff = 0;
        for k in 0..NW {
            diff += (l[k][x] ^ r[k][x]).count_ones();
        }
        out[x] = max - diff;
    }
}

/// Whether this CPU has AVX-512 F and BW (32 lanes of 16 bits, 64 of 8, per
/// instruction). Checked once per row or sweep, never per pixel.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(crate) fn has_avx512bw() -> bool {
    std::arch::is_x86_feature_detected!("avx512f")
        && std::arch::is_x86_feature_detected!("avx512bw")
}

/// Whether this CPU has AVX-512 F/VL/BW and VPOPCNTDQ (eight 64-bit popcounts per
/// instruction).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(crate) fn has_vpopcnt() -> bool {
    std::arch::is_x86_feature_detected!("avx512f")
        && std::arch::is_x86_feature_detected!("avx512vl")
        && std::arch::is_x86_feature_detected!("avx512bw")
        && std::arch::is_x86_feature_detected!("avx512vpopcntdq")
}

/// [`sv_row_equal`] eight pixels at a time with AVX-512 popcounts; returns how many pixels
/// it did (a multiple of 8), the caller finishes the rest.
///
/// # Safety
/// The CPU must support AVX-512F and AVX-512 VPOPCNTDQ ([`has_vpopcnt`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vpopcntdq")]
unsafe fn sv_row_equal_vpopcnt<const NW: usize>(
    max: u32,
    l: &[&[u64]; NW],
    r: &[&[u64]; NW],
    out: &mut [u32],
) -> usize {
    use std::arch::x86_64::*;
    let n = out.len();
    let maxv = _mm256_set1_epi32(max as i32);
    let mut i = 0;
    while i + 8 <= n {
        let mut acc = _mm512_setzero_si512();
        for k in 0..NW {
            // SAFETY: i + 8 <= n and every plane slice is n long.
            let (a, b) = unsafe {
                (
                    _mm512_loadu_si512(l[k].as_ptr().add(i) as *const _),
                    _mm512_loadu_si512(r[k].as_ptr().add(i) as *const _),
                )
            };
            acc = _mm512_add_epi64(acc, _mm512_popcnt_epi64(_mm512_xor_si512(a, b)));
        }
        let diff = _mm512_cvtepi64_epi32(acc);
        // SAFETY: as above.
        unsafe {
            _mm256_storeu_si256(
                out.as_mut_ptr().add(i) as *mut __m256i,
                _mm256_sub_epi32(maxv, diff),
            )
        };
        i += 8;
    }
    i
}

impl SvKernel {
    /// Support values of one image row for one disparity `d`: `out[x]` for left pixels
    /// `x` in `xlo..xhi` against right pixels `x − d` (word-planar descriptor rows of both
    /// images, see [`Descriptors::row`]).
    pub fn support_row(
        &self,
        left: &[u64],
        right: &[u64],
        xlo: usize,
        xhi: usize,
        d: isize,
        out: &mut [u32],
    ) {
        macro_rules! fixed {
            ($($n:literal)*) => {
                match self.words {
                    $($n => sv_row_equal::<$n>(self.max, left, right, xlo, xhi, d, out),)*
                    _ => unreachable!("window ≤ 31 needs at most 16 words"),
                }
            };
        }
        if self.weights == Weights::Equal {
            fixed!(1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16);
        } else {
            let nw = self.words;
            let w = left.len() / nw;
            let mut a = [0u64; 16];
            let mut b = [0u64; 16];
            for x in xlo..xhi {
                let xr = (x as isize - d) as usize;
                for k in 0..nw {
                    a[k] = left[k * w + x];
                    b[k] = right[k * w + xr];
                }
                out[x] = self.support(&a[..nw], &b[..nw]);
            }
        }
    }
}

/// Bit-packed window descriptors of every pixel of an image.
#[derive(Clone, Debug)]
pub struct Descriptors {
    /// Image columns.
    pub width: usize,
    /// Image rows.
    pub height: usize,
    /// u64 words per pixel.
    pub words: usize,
    /// `width * height * words` words: per row, `words` planes of `width` words (word `k`
    /// of pixel `x` of row `y` at `(y * words + k) * width + x`).
    pub data: Vec<u64>,
}

impl Descriptors {
    /// The descriptor of pixel `(x, y)`, gathered from the word planes.
    pub fn at(&self, x: usize, y: usize) -> Vec<u64> {
        let row = self.row(y);
        (0..self.words).map(|k| row[k * self.width + x]).collect()
    }

    /// All descriptors of row `y`, `words` planes of `width` words.
    #[inline(always)]
    pub fn row(&self, y: usize) -> &[u64] {
        let o = y * self.width * self.words;
        &self.data[o..o + self.width * self.words]
    }
}

/// The image with `r` replicated pixels on every side, so windows never need clamping.
pub fn pad_replicate(img: &Plane<u8>, r: usize) -> Plane<u8> {
    let (w, h) = (img.width, img.height);
    let pw = w + 2 * r;
    let ph = h + 2 * r;
    let mut out = vec![0u8; pw * ph];
    for py in 0..ph {
        let sy = py.saturating_sub(r).min(h - 1);
        let src = img.row(sy);
        let dst = &mut out[py * pw..(py + 1) * pw];
        dst[..r].fill(src[0]);
        dst[r..r + w].copy_from_slice(src);
        dst[r + w..].fill(src[w - 1]);
    }
    Plane {
        width: pw,
        height: ph,
        data: out,
    }
}

/// Per-pixel window sums over a padded image: `sum[x, y]` = Σ of the W×W window centred on
/// original pixel `(x, y)`, plus the sum of squares.
pub fn window_sums(padded: &Plane<u8>, window: usize) -> (Plane<u32>, Plane<u64>) {
    let r = (window - 1) / 2;
    let w = padded.width - 2 * r;
    let h = padded.height - 2 * r;
    let pw = padded.width;
    // Vertical sums over `window` rows for every padded column, then a horizontal slide.
    let mut sums = vec![0u32; w * h];
    let mut sq = vec![0u64; w * h];
    sums.par_chunks_mut(w)
        .zip(sq.par_chunks_mut(w))
        .enumerate()
        .for_each_init(
            || (vec![0u32; pw], vec![0u32; pw]),
            |(col, colq), (y, (srow, qrow))| {
                col.fill(0);
                colq.fill(0);
                for i in 0..window {
                    let row = &padded.data[(y + i) * pw..(y + i + 1) * pw];
                    for (u, &v) in row.iter().enumerate() {
                        col[u] += v as u32;
                        colq[u] += (v as u32) * (v as u32);
                    }
                }
                let mut s: u32 = col[..window].iter().sum();
                let mut q: u64 = colq[..window].iter().map(|&v| v as u64).sum();
                for x in 0..w {
                    srow[x] = s;
                    qrow[x] = q;
                    if x + window < pw {
                        s = s + col[x + window] - col[x];
                        q = q + colq[x + window] as u64 - colq[x] as u64;
                    }
                }
            },
        );
    (
        Plane {
            width: w,
            height: h,
            data: sums,
        },
        Plane {
            width: w,
            height: h,
            data: sq,
        },
    )
}

/// Bits `j < window` set where `row[j] >= t`.
#[inline(always)]
pub(crate) fn row_bits(row: &[u8], t: u8, window: usize) -> u64 {
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    if row.len() >= 32 {
        use std::arch::x86_64::*;
        // SAFETY: the slice holds at least 32 bytes and AVX2 is enabled for this build.
        let mask = unsafe {
            let v = _mm256_loadu_si256(row.as_ptr() as *const __m256i);
            let th = _mm256_set1_epi8(t as i8);
            let ge = _mm256_cmpeq_epi8(_mm256_max_epu8(v, th), v);
            _mm256_movemask_epi8(ge) as u32 as u64
        };
        return mask & ((1u64 << window) - 1);
    }
    let mut bits = 0u64;
    for (j, &v) in row[..window].iter().enumerate() {
        bits |= ((v >= t) as u64) << j;
    }
    bits
}

/// Computes the descriptor of every pixel: window binarised against its own mean.
///
/// `pixel ≥ mean` is evaluated exactly in integers as `pixel ≥ ceil(sum / W²)`.
pub fn descriptors(img: &Plane<u8>, window: usize) -> Descriptors {
    let r = (window - 1) / 2;
    let padded = pad_replicate(img, r);
    let (sums, _) = window_sums(&padded, window);
    descriptors_from_padded(&padded, &sums, window)
}

/// [`descriptors`] for an image already padded by `(window − 1) / 2` with its window sums.
pub fn descriptors_from_padded(
    padded: &Plane<u8>,
    sums: &Plane<u32>,
    window: usize,
) -> Descriptors {
    let (w, h) = (sums.width, sums.height);
    let words = (window * window).div_ceil(64);
    let n = (window * window) as u32;
    let pw = padded.width;
    let mut data = vec![0u64; w * h * words];
    data.par_chunks_mut(w * words)
        .enumerate()
        .for_each(|(y, out)| {
            #[allow(unused_mut)]
            let mut x0 = 0;
            #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
            while x0 + BLOCK <= w {
                descriptor_block(padded, sums, window, y, x0, out);
                x0 += BLOCK;
            }
            for x in x0..w {
                let t = sums.data[y * w + x].div_ceil(n);
                // A mean never exceeds 255, so the rounded-up threshold fits a byte.
                let t = t.min(255) as u8;
                let mut d = [0u64; 16];
                let mut bit = 0usize;
                for i in 0..window {
                    // One window row at a time: gather its bits, then splice them in.
                    let bits =
                        row_bits(&padded.data[(y + i) * pw + x..(y + i + 1) * pw], t, window);
                    let word = bit / 64;
                    let off = bit % 64;
                    d[word] |= bits << off;
                    if off + window > 64 {
                        d[word + 1] |= bits >> (64 - off);
                    }
                    bit += window;
                }
                for k in 0..words {
                    out[k * w + x] = d[k];
                }
            }
        });
    Descriptors {
        width: w,
        height: h,
        words,
        data,
    }
}

/// Pixels per vectorised descriptor block.
pub(crate) const BLOCK: usize = 32;

/// Window-row bit masks of 32 pixels at once: for the pixels `x0..x0 + 32` with
/// thresholds `t`, and each window row `i < rows` (padded row `top + i`), calls
/// `emit(i, bits)` where bit `j < cols` of `bits[p]` is set when
/// `padded[top + i][x0 + p + j] >= t[p]`. One byte compare per window column tests all 32
/// pixels and ORs the result into per-pixel bytes (bit `j % 8` of byte group `j / 8`).
/// Needs `x0 + 32 + cols − 1 <= padded.width`, `top + rows <= padded.height`, `cols <= 32`.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
pub(crate) fn block_row_bits(
    padded: &Plane<u8>,
    top: usize,
    (rows, cols): (usize, usize),
    x0: usize,
    t: &[u8; BLOCK],
    mut emit: impl FnMut(usize, &[u64; BLOCK]),
) {
    use std::arch::x86_64::*;
    let pw = padded.width;
    assert!(x0 + BLOCK + cols - 1 <= pw && top + rows <= padded.height && cols <= 32);
    let mut groups = [[0u8; BLOCK]; 4];
    // SAFETY: AVX2 is enabled for this build; every load reads 32 bytes at
    // (top + i) * pw + x0 + j with j < cols, inside row top + i (asserted above).
    unsafe {
        let tv = _mm256_loadu_si256(t.as_ptr() as *const __m256i);
        for i in 0..rows {
            let row = padded.data.as_ptr().add((top + i) * pw + x0);
            let mut acc = [_mm256_setzero_si256(); 4];
            for j in 0..cols {
                let v = _mm256_loadu_si256(row.add(j) as *const __m256i);
                let ge = _mm256_cmpeq_epi8(_mm256_max_epu8(v, tv), v);
                let bit = _mm256_set1_epi8((1u8 << (j % 8)) as i8);
                acc[j / 8] = _mm256_or_si256(acc[j / 8], _mm256_and_si256(ge, bit));
            }
            for g in 0..cols.div_ceil(8) {
                _mm256_storeu_si256(groups[g].as_mut_ptr() as *mut __m256i, acc[g]);
            }
            let mut bits = [0u64; BLOCK];
            for (p, b) in bits.iter_mut().enumerate() {
                *b = groups[0][p] as u64
                    | (groups[1][p] as u64) << 8
                    | (groups[2][p] as u64) << 16
                    | (groups[3][p] as u64) << 24;
            }
            emit(i, &bits);
        }
    }
}

/// Descriptors of the 32 pixels `x0..x0 + 32` of row `y`, spliced into the word planes
/// `out` of that row. Needs `x0 + 32 <= width`: the padded rows are `width + window − 1`
/// long.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
fn descriptor_block(
    padded: &Plane<u8>,
    sums: &Plane<u32>,
    window: usize,
    y: usize,
    x0: usize,
    out: &mut [u64],
) {
    let w = sums.width;
    let n = (window * window) as u32;
    let mut t = [0u8; BLOCK];
    for (p, tp) in t.iter_mut().enumerate() {
        *tp = sums.data[y * w + x0 + p].div_ceil(n).min(255) as u8;
    }
    block_row_bits(padded, y, (window, window), x0, &t, |i, bits| {
        let bit = i * window;
        let (word, off) = (bit / 64, bit % 64);
        for (o, &b) in out[word * w + x0..][..BLOCK].iter_mut().zip(bits) {
            *o |= b << off;
        }
        if off + window > 64 {
            for (o, &b) in out[(word + 1) * w + x0..][..BLOCK].iter_mut().zip(bits) {
                *o |= b >> (64 - off);
            }
        }
    });
}

/// The support value straight from the definition, for tests and documentation: binarise
/// both clamped windows against their own means and add the weights where they agree.
pub fn support_value_naive(
    left: &Plane<u8>,
    right: &Plane<u8>,
    (xl, yl): (usize, usize),
    (xr, yr): (usize, usize),
    window: usize,
    weights: Weights,
) -> u32 {
    let r = (window - 1) as isize / 2;
    let bin = |img: &Plane<u8>, cx: usize, cy: usize| -> Vec<bool> {
        let px = |i: isize, j: isize| -> f64 {
            let y = (cy as isize + i).clamp(0, img.height as isize - 1) as usize;
            let x = (cx as isize + j).clamp(0, img.width as isize - 1) as usize;
            *img.get(x, y) as f64
        };
        let mut vals = Vec::new();
        for i in -r..=r {
            for j in -r..=r {
                vals.push(px(i, j));
            }
        }
        let mean = vals.iter().sum::<f64>() / vals.len() as f64;
        vals.iter().map(|&v| v >= mean).collect()
    };
    let a = bin(left, xl, yl);
    let b = bin(right, xr, yr);
    let mut sv = 0;
    for i in 0..window {
        for j in 0..window {
            if a[i * window + j] == b[i * window + j] {
                sv += weight_at(weights, window, i, j);
            }
        }
    }
    sv
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_image(w: usize, h: usize, seed: u64, levels: u8) -> Plane<u8> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let data = (0..w * h).map(|_| rng.random_range(0..levels)).collect();
        Plane::from_vec(w, h, data).unwrap()
    }

    #[test]
    fn decreasing_weights_fall_by_one_per_ring() {
        // 5×5: centre 3, first ring 2, outer ring 1.
        assert_eq!(weight_at(Weights::Decreasing, 5, 2, 2), 3);
        assert_eq!(weight_at(Weights::Decreasing, 5, 1, 3), 2);
        assert_eq!(weight_at(Weights::Decreasing, 5, 0, 4), 1);
        assert_eq!(weight_at(Weights::Decreasing, 5, 4, 2), 1);
        assert_eq!(SvKernel::new(5, Weights::Decreasing).max, 3 + 8 * 2 + 16);
        assert_eq!(SvKernel::new(13, Weights::Equal).max, 169);
        assert_eq!(SvKernel::new(13, Weights::Equal).words, 3);
        assert_eq!(SvKernel::new(31, Weights::Equal).words, 16);
    }

    #[test]
    fn identical_windows_give_the_maximum() {
        let img = random_image(20, 20, 1, 255);
        for weights in [Weights::Equal, Weights::Decreasing] {
            let k = SvKernel::new(7, weights);
            let d = descriptors(&img, 7);
            assert_eq!(k.support(&d.at(5, 5), &d.at(5, 5)), k.max);
            assert_eq!(
                support_value_naive(&img, &img, (5, 5), (5, 5), 7, weights),
                k.max
            );
        }
    }

    #[test]
    fn flat_window_is_all_ones() {
        // Every pixel equals the mean, so every bit is set (pixel ≥ mean).
        let img = Plane::filled(9, 9, 77u8);
        let d = descriptors(&img, 5);
        assert_eq!(d.at(4, 4)[0], (1u64 << 25) - 1);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        /// The bit-packed SV equals the definition for every window size, weight type and
        /// position, borders included.
        #[test]
        fn packed_support_value_matches_definition(
            half in 1usize..=15,
            seed in 0u64..1000,
            levels in prop::sample::select(vec![2u8, 4, 255]),
            decreasing in any::<bool>(),
            xl in 0usize..40, yl in 0usize..30, xr in 0usize..40, yr in 0usize..30,
        ) {
            let window = 2 * half + 1;
            let weights = if decreasing { Weights::Decreasing } else { Weights::Equal };
            let left = random_image(40, 30, seed, levels);
            let right = random_image(40, 30, seed + 7, levels);
            let k = SvKernel::new(window, weights);
            let dl = descriptors(&left, window);
            let dr = descriptors(&right, window);
            let fast = k.support(&dl.at(xl, yl), &dr.at(xr, yr));
            let naive = support_value_naive(&left, &right, (xl, yl), (xr, yr), window, weights);
            prop_assert_eq!(fast, naive);
        }

        /// A whole row at one disparity (the matcher's path: vectorised where the CPU
        /// allows) equals the per-pixel support value.
        #[test]
        fn support_row_matches_support(
            half in 1usize..=15,
            seed in 0u64..1000,
            decreasing in any::<bool>(),
            d in -20isize..20,
            y in 0usize..30,
        ) {
            let window = 2 * half + 1;
            let weights = if decreasing { Weights::Decreasing } else { Weights::Equal };
            let left = random_image(40, 30, seed, 255);
            let right = random_image(40, 30, seed + 3, 255);
            let k = SvKernel::new(window, weights);
            let dl = descriptors(&left, window);
            let dr = descriptors(&right, window);
            let (xlo, xhi) = (d.max(0) as usize, (40 + d).min(40) as usize);
            let mut out = vec![0u32; 40];
            k.support_row(dl.row(y), dr.row(y), xlo, xhi, d, &mut out);
            for x in xlo..xhi {
                let xr = (x as isize - d) as usize;
                prop_assert_eq!(out[x], k.support(&dl.at(x, y), &dr.at(xr, y)), "x {}", x);
            }
        }
    }
}
