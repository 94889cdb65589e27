//! The AVX2 kernels of the quality matcher: the SGM sweep, 16 disparities per
//! instruction, and the row decision, 16 pixels per instruction.
//!
//! Path rows are stored per pixel as `[guard, L(0) … L(ndp − 1), guard]` with `ndp` the
//! disparity count rounded up to 16: lanes past the last disparity and the guards hold
//! [`BIG`], so the `d ± 1` neighbours are plain unaligned loads and never win a minimum.
//! All values stay non-negative, so the horizontal minimum is `phminposuw`.

use super::QualityParams;
use schemas::Plane;
use std::arch::x86_64::*;

/// Value of lanes that are not disparities; above any real path cost.
pub const BIG: i16 = 0x3fff;

/// Per-sweep constants of the kernel.
struct Kernel {
    nvec: usize,
    nd: usize,
    /// Lanes of the last vector that are past the last disparity.
    tail: __m256i,
}

impl Kernel {
    /// Loads the 16 costs of vector `k` as i16 (the last vector from a zero-padded copy).
    #[inline(always)]
    unsafe fn cost(&self, c: &[u8], pad: &[u8; 16], k: usize) -> __m256i {
        // SAFETY: full vectors lie inside `c` (nd bytes); the tail comes from `pad`.
        unsafe {
            let p = if (k + 1) * 16 <= self.nd {
                c.as_ptr().add(k * 16)
            } else {
                pad.as_ptr()
            };
            _mm256_cvtepu8_epi16(_mm_loadu_si128(p as *const __m128i))
        }
    }

    /// Horizontal minimum of non-negative i16 lanes.
    #[inline(always)]
    fn hmin(mn: __m256i) -> i16 {
        // SAFETY: AVX2 (and so SSE4.1) is enabled for this build.
        unsafe {
            let m = _mm_min_epi16(_mm256_castsi256_si128(mn), _mm256_extracti128_si256(mn, 1));
            _mm_extract_epi16(_mm_minpos_epu16(m), 0) as i16
        }
    }

    /// `N` paths stepped together from their predecessors `(values with guards,
    /// minimum, P2)` into `outs`; `acc` receives their sum. The cost vector is loaded
    /// once and the sum stays in a register. Returns each path's new minimum.
    #[inline(always)]
    fn paths<const N: usize>(
        &self,
        c: &[u8],
        from: [(&[i16], i16, i16); N],
        p1: i16,
        outs: [&mut [i16]; N],
        acc: &mut [u16],
    ) -> [i16; N] {
        let n = self.nvec * 16;
        assert!(acc.len() >= n && c.len() >= self.nd);
        for (lp, _, _) in &from {
            assert!(lp.len() >= n + 2);
        }
        for out in &outs {
            assert!(out.len() >= n + 2);
        }
        let pad = self.pad(c);
        // SAFETY: AVX2 is enabled for this build; loads and stores stay inside the
        // slices (lengths asserted above).
        unsafe {
            let p1v = _mm256_set1_epi16(p1);
            let jump: [__m256i; N] =
                std::array::from_fn(|j| _mm256_set1_epi16(from[j].1 + from[j].2));
            let minv: [__m256i; N] = std::array::from_fn(|j| _mm256_set1_epi16(from[j].1));
            let mut mn = [_mm256_set1_epi16(BIG); N];
            let big = _mm256_set1_epi16(BIG);
            for k in 0..self.nvec {
                let cv = self.cost(c, &pad, k);
                let mut sum = _mm256_setzero_si256();
                for j in 0..N {
                    let base = from[j].0.as_ptr().add(k * 16);
                    let a = _mm256_loadu_si256(base as *const __m256i);
                    let m = _mm256_loadu_si256(base.add(1) as *const __m256i);
                    let b = _mm256_loadu_si256(base.add(2) as *const __m256i);
                    let nb = _mm256_add_epi16(_mm256_min_epi16(a, b), p1v);
                    let v = _mm256_min_epi16(_mm256_min_epi16(m, nb), jump[j]);
                    let mut v = _mm256_add_epi16(cv, _mm256_sub_epi16(v, minv[j]));
                    if k + 1 == self.nvec {
                        v = _mm256_blendv_epi8(v, big, self.tail);
                    }
                    _mm256_storeu_si256(outs[j].as_mut_ptr().add(1 + k * 16) as *mut __m256i, v);
                    mn[j] = _mm256_min_epi16(mn[j], v);
                    sum = _mm256_add_epi16(sum, v);
                }
                _mm256_storeu_si256(acc.as_mut_ptr().add(k * 16) as *mut __m256i, sum);
            }
            std::array::from_fn(|j| Self::hmin(mn[j]))
        }
    }

    /// [`Kernel::paths`], through the fully unrolled [`step_paths`] for the common
    /// disparity counts 64 and 128.
    #[inline(always)]
    fn step<const N: usize>(
        &self,
        c: &[u8],
        from: [(&[i16], i16, i16); N],
        p1: i16,
        outs: [&mut [i16]; N],
        acc: &mut [u16],
    ) -> [i16; N] {
        if self.nd != 64 && self.nd != 128 {
            return self.paths(c, from, p1, outs, acc);
        }
        let n = self.nd;
        assert!(c.len() >= n && acc.len() >= n);
        assert!(from.iter().all(|f| f.0.len() >= n + 2) && outs.iter().all(|o| o.len() >= n + 2));
        let lps = from.map(|f| f.0.as_ptr());
        let mins = from.map(|f| f.1);
        let p2s = from.map(|f| f.2);
        let outs = outs.map(|o| o.as_mut_ptr());
        // SAFETY: costs and sum hold nd values, every predecessor and output nd + 2
        // (asserted above); AVX2 is enabled for this build.
        unsafe {
            if n == 64 {
                step_paths::<4, N>(c.as_ptr(), lps, mins, p2s, p1, outs, acc.as_mut_ptr())
            } else {
                step_paths::<8, N>(c.as_ptr(), lps, mins, p2s, p1, outs, acc.as_mut_ptr())
            }
        }
    }

    /// The last partial vector's costs, zero-padded (unused when nd is a multiple of 16).
    #[inline(always)]
    fn pad(&self, c: &[u8]) -> [u8; 16] {
        let mut pad = [0u8; 16];
        let full = self.nd / 16 * 16;
        pad[..self.nd - full].copy_from_slice(&c[full..self.nd]);
        pad
    }
}

/// P2 between two neighbouring intensities (lowered across edges).
#[inline(always)]
fn p2_between(lut: &[i16], a: u8, b: u8) -> i16 {
    lut[a.abs_diff(b) as usize]
}

/// The step of `NP` paths of one pixel for exactly `16 · NV` disparities: both counts
/// are constants, so the loops unroll and the per-path constants and minima stay in
/// registers.
///
/// # Safety
/// `c` and `acc` point at `16 · NV` values, every `lp` and `out` at `16 · NV + 2`.
#[inline(always)]
unsafe fn step_paths<const NV: usize, const NP: usize>(
    c: *const u8,
    lp: [*const i16; NP],
    mins: [i16; NP],
    p2s: [i16; NP],
    p1: i16,
    out: [*mut i16; NP],
    acc: *mut u16,
) -> [i16; NP] {
    // SAFETY: the caller's promise; AVX2 is enabled for this build.
    unsafe {
        let p1v = _mm256_set1_epi16(p1);
        let jump: [__m256i; NP] = std::array::from_fn(|j| _mm256_set1_epi16(mins[j] + p2s[j]));
        let minv: [__m256i; NP] = std::array::from_fn(|j| _mm256_set1_epi16(mins[j]));
        let mut mn = [_mm256_set1_epi16(BIG); NP];
        for k in 0..NV {
            let cv = _mm256_cvtepu8_epi16(_mm_loadu_si128(c.add(k * 16) as *const __m128i));
            let mut sum = _mm256_setzero_si256();
            for j in 0..NP {
                let base = lp[j].add(k * 16);
                let a = _mm256_loadu_si256(base as *const __m256i);
                let m = _mm256_loadu_si256(base.add(1) as *const __m256i);
                let b = _mm256_loadu_si256(base.add(2) as *const __m256i);
                let nb = _mm256_add_epi16(_mm256_min_epi16(a, b), p1v);
                let v = _mm256_min_epi16(_mm256_min_epi16(m, nb), jump[j]);
                let v = _mm256_add_epi16(cv, _mm256_sub_epi16(v, minv[j]));
                _mm256_storeu_si256(out[j].add(1 + k * 16) as *mut __m256i, v);
                mn[j] = _mm256_min_epi16(mn[j], v);
                sum = _mm256_add_epi16(sum, v);
            }
            _mm256_storeu_si256(acc.add(k * 16) as *mut __m256i, sum);
        }
        std::array::from_fn(|j| Kernel::hmin(mn[j]))
    }
}

/// Marks a disparity that does not exist; above every summed cost the limits allow
/// (8 paths · (cost 159 + penalty 3800) < 32767).
const NONE: i16 = i16::MAX;

/// Whether a row of this size fits the i16 lane arithmetic of [`select_row`].
pub fn rows_fit(w: usize, nd: usize, dmin: i32) -> bool {
    w + nd + 2 * dmin.unsigned_abs() as usize + 64 < 30_000
}

/// Transposes the 16×16 block of `src` (rows `x`, stride `sstride`, 16 values each)
/// into `dst` (row `d` = column `d` of the block, stride `dstride`).
#[inline(always)]
unsafe fn transpose16(src: *const u16, sstride: usize, dst: *mut i16, dstride: usize) {
    // SAFETY: the caller guarantees 16 rows of 16 values on both sides.
    unsafe {
        let a: [__m256i; 16] =
            std::array::from_fn(|i| _mm256_loadu_si256(src.add(i * sstride) as *const __m256i));
        for half in 0..2 {
            // Rows i and i + 8 of one 8-column half share a register: an in-lane
            // 8×8 transpose then yields whole 16-row columns.
            let x: [__m256i; 8] = std::array::from_fn(|i| match half {
                0 => _mm256_permute2x128_si256(a[i], a[i + 8], 0x20),
                _ => _mm256_permute2x128_si256(a[i], a[i + 8], 0x31),
            });
            let b = [
                _mm256_unpacklo_epi16(x[0], x[1]),
                _mm256_unpackhi_epi16(x[0], x[1]),
                _mm256_unpacklo_epi16(x[2], x[3]),
                _mm256_unpackhi_epi16(x[2], x[3]),
                _mm256_unpacklo_epi16(x[4], x[5]),
                _mm256_unpackhi_epi16(x[4], x[5]),
                _mm256_unpacklo_epi16(x[6], x[7]),
                _mm256_unpackhi_epi16(x[6], x[7]),
            ];
            let c = [
                _mm256_unpacklo_epi32(b[0], b[2]),
                _mm256_unpackhi_epi32(b[0], b[2]),
                _mm256_unpacklo_epi32(b[1], b[3]),
                _mm256_unpackhi_epi32(b[1], b[3]),
                _mm256_unpacklo_epi32(b[4], b[6]),
                _mm256_unpackhi_epi32(b[4], b[6]),
                _mm256_unpacklo_epi32(b[5], b[7]),
                _mm256_unpackhi_epi32(b[5], b[7]),
            ];
            let y = [
                _mm256_unpacklo_epi64(c[0], c[4]),
                _mm256_unpackhi_epi64(c[0], c[4]),
                _mm256_unpacklo_epi64(c[1], c[5]),
                _mm256_unpackhi_epi64(c[1], c[5]),
                _mm256_unpacklo_epi64(c[2], c[6]),
                _mm256_unpackhi_epi64(c[2], c[6]),
                _mm256_unpacklo_epi64(c[3], c[7]),
                _mm256_unpackhi_epi64(c[3], c[7]),
            ];
            for (j, v) in y.iter().enumerate() {
                _mm256_storeu_si256(dst.add((half * 8 + j) * dstride) as *mut __m256i, *v);
            }
        }
    }
}

/// The decision for 16 pixels at once, one lane each: `load(di)` gives the 16 summed
/// costs at disparity index `di` ([`NONE`] where it does not exist). Returns per lane
/// the best cost, its first index, the best cost more than one index away, and the
/// costs at index − 1 and + 1 ([`NONE`] where absent).
#[inline(always)]
unsafe fn decide16(nd: usize, load: impl Fn(usize) -> __m256i) -> [[i16; 16]; 5] {
    // SAFETY: AVX2 is enabled for this build; `load` is the caller's promise.
    unsafe {
        let none = _mm256_set1_epi16(NONE);
        let mut best = none;
        let mut bi = _mm256_setzero_si256();
        for di in 0..nd {
            let v = load(di);
            let lt = _mm256_cmpgt_epi16(best, v);
            best = _mm256_min_epi16(best, v);
            bi = _mm256_blendv_epi8(bi, _mm256_set1_epi16(di as i16), lt);
        }
        let (lo2, hi2) = (
            _mm256_sub_epi16(bi, _mm256_set1_epi16(2)),
            _mm256_add_epi16(bi, _mm256_set1_epi16(2)),
        );
        let (bm1, bp1) = (
            _mm256_sub_epi16(bi, _mm256_set1_epi16(1)),
            _mm256_add_epi16(bi, _mm256_set1_epi16(1)),
        );
        let (mut rival, mut a, mut c) = (none, none, none);
        for di in 0..nd {
            let v = load(di);
            let dv = _mm256_set1_epi16(di as i16);
            let near = _mm256_and_si256(_mm256_cmpgt_epi16(dv, lo2), _mm256_cmpgt_epi16(hi2, dv));
            rival = _mm256_min_epi16(rival, _mm256_blendv_epi8(v, none, near));
            a = _mm256_blendv_epi8(a, v, _mm256_cmpeq_epi16(dv, bm1));
            c = _mm256_blendv_epi8(c, v, _mm256_cmpeq_epi16(dv, bp1));
        }
        let mut out = [[0i16; 16]; 5];
        for (o, v) in out.iter_mut().zip([best, bi, rival, a, c]) {
            _mm256_storeu_si256(o.as_mut_ptr() as *mut __m256i, v);
        }
        out
    }
}

/// Turns [`decide16`]'s figures for one lane into a disparity, as [`super::decide`].
#[inline(always)]
fn finish(f: &[[i16; 16]; 5], lane: usize, uniqueness: u16, dmin: i32) -> Option<f32> {
    let (best, bi, rival, a, c) = (f[0][lane], f[1][lane], f[2][lane], f[3][lane], f[4][lane]);
    if best == NONE {
        return None;
    }
    let u = uniqueness as u32;
    if rival != NONE && (rival as u32) * 100u32.saturating_sub(u) < (best as u32) * 100 {
        return Some(schemas::INVALID_DISPARITY);
    }
    let mut d = bi as f32 + dmin as f32;
    if a != NONE && c != NONE {
        let (a, b, c) = (a as f32, best as f32, c as f32);
        let den = a + c - 2.0 * b;
        if den > 0.0 {
            d += (a - c) / (2.0 * den);
        }
    }
    Some(d)
}

/// [`super::select_row`] with the row transposed to disparity-major order, so that
/// both maps are decided 16 pixels at a time (lanes = pixels). Pixel `x`'s sums start
/// at `total[x · tstride]`; `mt` is scratch.
pub fn select_row(
    total: &[u16],
    tstride: usize,
    p: &QualityParams,
    mt: &mut Vec<u16>,
    lrow: &mut [f32],
    rrow: &mut [f32],
) {
    let (w, nd) = (lrow.len(), p.range.count());
    let dmin = p.range.min;
    let u = p.uniqueness_ratio;
    let w16 = w.div_ceil(16) * 16;
    let pad = dmin.unsigned_abs() as usize + 16;
    let stride = pad + w16 + pad + nd + 16;
    if mt.len() != nd * stride {
        mt.clear();
        mt.resize(nd * stride, NONE as u16);
    }
    let base = mt.as_mut_ptr() as *mut i16;
    assert!(tstride >= nd && total.len() >= (w - 1) * tstride + nd);
    // Transpose: mt[di][pad + x] = total[x][di]; outside 0..w stays NONE.
    let (wf, df) = (w / 16 * 16, nd / 16 * 16);
    for x0 in (0..wf).step_by(16) {
        for d0 in (0..df).step_by(16) {
            // SAFETY: rows x0..x0 + 16 < w and values d0..d0 + 16 <= nd of `total`;
            // mt rows d0..d0 + 16 hold pad + x0 + 16 <= stride values.
            unsafe {
                transpose16(
                    total.as_ptr().add(x0 * tstride + d0),
                    tstride,
                    base.add(d0 * stride + pad + x0),
                    stride,
                )
            };
        }
    }
    for x in 0..w {
        let from = if x < wf { df } else { 0 };
        for di in from..nd {
            mt[di * stride + pad + x] = total[x * tstride + di];
        }
    }
    let mt = &mt[..];
    let lanes: [i16; 16] = std::array::from_fn(|i| i as i16);
    // SAFETY: AVX2 is enabled for this build. Every load reads 16 values of row di at
    // column pad + x0 + (0 or dmin + di) with x0 < w16: inside the row by the padding
    // (dmin + di >= −pad + 16, and pad + w16 + dmin + di + 16 <= stride).
    unsafe {
        let idx = _mm256_loadu_si256(lanes.as_ptr() as *const __m256i);
        let none = _mm256_set1_epi16(NONE);
        let row = |di: usize, col: isize| -> __m256i {
            let o = (di * stride) as isize + pad as isize + col;
            _mm256_loadu_si256(mt.as_ptr().offset(o) as *const __m256i)
        };
        for x0 in (0..w16).step_by(16) {
            // Left-based: lanes x = x0 + i; disparity index di exists when the right
            // pixel x − dmin − di lies in the image.
            let interior = x0 as i64 - dmin as i64 - nd as i64 + 1 >= 0
                && (x0 + 15) as i64 - (dmin as i64) < w as i64;
            let xv = _mm256_add_epi16(idx, _mm256_set1_epi16(x0 as i16));
            let hi = _mm256_sub_epi16(xv, _mm256_set1_epi16(dmin as i16));
            let lo = _mm256_sub_epi16(hi, _mm256_set1_epi16(w as i16 - 1));
            let f = if interior {
                decide16(nd, |di| row(di, x0 as isize))
            } else {
                decide16(nd, |di| {
                    let dv = _mm256_set1_epi16(di as i16);
                    let ok = _mm256_andnot_si256(
                        _mm256_or_si256(_mm256_cmpgt_epi16(dv, hi), _mm256_cmpgt_epi16(lo, dv)),
                        _mm256_set1_epi16(-1),
                    );
                    _mm256_blendv_epi8(none, row(di, x0 as isize), ok)
                })
            };
            for lane in 0..16.min(w - x0) {
                if let Some(d) = finish(&f, lane, u, dmin) {
                    lrow[x0 + lane] = d;
                }
            }
            // Right-based: lanes xr = x0 + i read left pixel xr + dmin + di, which
            // the padding marks NONE outside the image.
            let f = decide16(nd, |di| row(di, x0 as isize + dmin as isize + di as isize));
            for lane in 0..16.min(w - x0) {
                if let Some(d) = finish(&f, lane, u, dmin) {
                    rrow[x0 + lane] = d;
                }
            }
        }
    }
}

/// See [`super::aggregate`]; identical output.
#[cfg(test)]
pub fn aggregate(cost: &[u8], img: &Plane<u8>, p: &QualityParams, backward: bool) -> Vec<u16> {
    let (w, h, nd) = (img.width, img.height, p.range.count());
    let mut sum = vec![0u16; w * h * nd];
    let ndp = nd.div_ceil(16) * 16;
    sweep(cost, img, p, backward, |y, row| {
        for x in 0..w {
            let o = (y * w + x) * nd;
            sum[o..o + nd].copy_from_slice(&row[x * ndp..x * ndp + nd]);
        }
        row
    });
    sum
}

/// One SGM sweep over 4 paths (see [`super::aggregate`]). Each finished image row
/// (path sums in image order, `nd.div_ceil(16) · 16` per pixel) goes to
/// `row_done(y, row)`, which hands back a buffer of the same size for the next row.
pub fn sweep(
    cost: &[u8],
    img: &Plane<u8>,
    p: &QualityParams,
    backward: bool,
    mut row_done: impl FnMut(usize, Vec<u16>) -> Vec<u16>,
) {
    let (w, h, nd) = (img.width, img.height, p.range.count());
    let nvec = nd.div_ceil(16);
    let ndp = nvec * 16;
    let stride = ndp + 2;
    let lanes: [i16; 16] = std::array::from_fn(|i| i as i16);
    // SAFETY: AVX2 is enabled for this build; `lanes` is 16 i16s.
    let tail = unsafe {
        let idx = _mm256_loadu_si256(lanes.as_ptr() as *const __m256i);
        let last = ((nd - (nvec - 1) * 16) as i16) - 1;
        _mm256_cmpgt_epi16(idx, _mm256_set1_epi16(last))
    };
    let kern = Kernel { nvec, nd, tail };
    let mut row_sum = vec![0u16; w * ndp];
    let diagonals = p.paths >= 8;
    let mut prev: [Vec<i16>; 3] = std::array::from_fn(|_| vec![BIG; w * stride]);
    let mut cur: [Vec<i16>; 3] = std::array::from_fn(|_| vec![BIG; w * stride]);
    let mut prev_min = [vec![0i16; w], vec![0i16; w], vec![0i16; w]];
    let mut cur_min = prev_min.clone();
    let mut left_l = vec![BIG; stride];
    let mut scratch = vec![BIG; stride];
    // A path with no predecessor starts at L = C: an all-zero predecessor with
    // minimum 0 gives exactly that (every candidate of the minimum is ≥ 0).
    let zeros = vec![0i16; stride];
    let mut left_min: i16 = 0;
    let p1 = p.p1 as i16;
    let p2_lut = super::p2_table(p);
    let oy = |y: usize| if backward { h - 1 - y } else { y };
    let ox = |x: usize| if backward { w - 1 - x } else { x };
    for y in 0..h {
        let irow = img.row(oy(y));
        let iprev = img.row(if y > 0 { oy(y - 1) } else { oy(y) });
        let [c0, c1, c2] = &mut cur;
        for x in 0..w {
            let xi = ox(x);
            let pix = (oy(y) * w + xi) * nd;
            let c = &cost[pix..pix + nd];
            let here = irow[xi];
            let acc = &mut row_sum[xi * ndp..(xi + 1) * ndp];
            // Predecessor of path k (0 = top-left, 1 = top, 2 = top-right) and of the
            // path from the left: (values, minimum, P2). Plain inline code: as closures
            // these were calls, a fifth of the sweep.
            macro_rules! from_row {
                ($k:expr, $sx:expr) => {
                    match $sx {
                        Some(sx) if y > 0 => (
                            &prev[$k][sx * stride..(sx + 1) * stride],
                            prev_min[$k][sx],
                            p2_between(&p2_lut, here, iprev[ox(sx)]),
                        ),
                        _ => (&zeros[..], 0, 0),
                    }
                };
            }
            let left = if x == 0 {
                (&zeros[..], 0, 0)
            } else {
                (
                    &left_l[..],
                    left_min,
                    p2_between(&p2_lut, here, irow[ox(x - 1)]),
                )
            };
            let top: (&[i16], i16, i16) = from_row!(1, Some(x));
            let o = x * stride..(x + 1) * stride;
            if diagonals {
                let tl = from_row!(0, x.checked_sub(1));
                let tr = from_row!(2, (x + 1 < w).then_some(x + 1));
                let m = kern.step(
                    c,
                    [left, tl, top, tr],
                    p1,
                    [
                        &mut scratch,
                        &mut c0[o.clone()],
                        &mut c1[o.clone()],
                        &mut c2[o],
                    ],
                    acc,
                );
                left_min = m[0];
                cur_min[0][x] = m[1];
                cur_min[1][x] = m[2];
                cur_min[2][x] = m[3];
            } else {
                let m = kern.step(c, [left, top], p1, [&mut scratch, &mut c1[o]], acc);
                left_min = m[0];
                cur_min[1][x] = m[1];
            }
            std::mem::swap(&mut left_l, &mut scratch);
        }
        row_sum = row_done(oy(y), row_sum);
        std::mem::swap(&mut prev, &mut cur);
        std::mem::swap(&mut prev_min, &mut cur_min);
    }
}
