//! Quality mode: census + gradient cost, semi-global aggregation over 8 paths.
//!
//! Cost: Hamming distance of 9×7 census descriptors (robust to the gain and offset
//! differences between two microscope cameras) plus a truncated difference of horizontal
//! gradients (sharpens depth edges). Aggregation: Hirschmüller's SGM over 8 paths, with the
//! large-jump penalty P2 lowered across intensity edges. Two passes (top-down and
//! bottom-up, four paths each) run in parallel and meet: whichever finishes an image row
//! second adds the other's sums and decides the row. Decision: winner-takes-all with a
//! uniqueness ratio and a sub-pixel parabola; the right-based map is read from the same
//! sums along their diagonals, so the LR check costs no second matching.
//!
//! With AVX2 (every build of this project) the sweeps run 16 disparities per
//! instruction and the decision 16 pixels per instruction; the plain versions remain for
//! penalties beyond the SIMD limits and as the reference the tests compare against.

use rayon::prelude::*;
use schemas::{DisparityMap, DisparityRange, INVALID_DISPARITY, Plane};
use serde::{Deserialize, Serialize};

/// Parameters of the quality matcher.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct QualityParams {
    /// Disparities searched.
    pub range: DisparityRange,
    /// Penalty for a disparity change of 1 between neighbours.
    pub p1: u16,
    /// Penalty for larger jumps (lowered across intensity edges).
    pub p2: u16,
    /// Weight of the gradient term relative to census (0 = census only).
    pub gradient_weight: u16,
    /// Truncation of the gradient difference.
    pub gradient_cap: u16,
    /// Percent margin by which the best cost must beat every non-neighbour disparity.
    pub uniqueness_ratio: u16,
    /// Aggregation paths: 4 (horizontal + vertical) or 8 (with diagonals).
    pub paths: u8,
}

impl Default for QualityParams {
    fn default() -> Self {
        Self {
            range: DisparityRange::new(0, 64),
            p1: 14,
            p2: 140,
            gradient_weight: 1,
            gradient_cap: 30,
            uniqueness_ratio: 10,
            paths: 8,
        }
    }
}

/// Result of the quality matcher.
#[derive(Clone, Debug)]
pub struct QualityMatch {
    /// Left-based sub-pixel disparity.
    pub left: DisparityMap,
    /// Right-based sub-pixel disparity read from the same aggregated volume.
    pub right: DisparityMap,
    /// Pixel × disparity cost evaluations.
    pub evaluations: u64,
}

/// Census window half-sizes (9 wide, 7 high: 63 bits).
const CENSUS_RX: usize = 4;
const CENSUS_RY: usize = 3;

/// 9×7 census transform: bit set where the neighbour is darker than the centre (image
/// edges repeat).
pub fn census(img: &Plane<u8>) -> Plane<u64> {
    let (w, h) = (img.width, img.height);
    let padded = crate::sv::pad_replicate(img, CENSUS_RX);
    let pw = padded.width;
    let cw = 2 * CENSUS_RX + 1;
    let full = (1u64 << cw) - 1;
    let mut out = vec![0u64; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        #[allow(unused_mut)]
        let mut x0 = 0;
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        {
            use crate::sv::BLOCK;
            while x0 + BLOCK <= w {
                let t: [u8; BLOCK] = img.row(y)[x0..x0 + BLOCK].try_into().expect("block");
                let out = &mut row[x0..x0 + BLOCK];
                out.fill(0);
                let top = y + CENSUS_RX - CENSUS_RY;
                crate::sv::block_row_bits(&padded, top, (2 * CENSUS_RY + 1, cw), x0, &t, |_, b| {
                    for (o, &b) in out.iter_mut().zip(b) {
                        // "darker than the centre" = not (≥ centre).
                        *o = (*o << cw) | (!b & full);
                    }
                });
                x0 += BLOCK;
            }
        }
        for (x, o) in row.iter_mut().enumerate().skip(x0) {
            let c = *img.get(x, y);
            let mut bits = 0u64;
            for dy in 0..2 * CENSUS_RY + 1 {
                // Padded by CENSUS_RX on every side; rows beyond the census height are unused.
                let py = y + CENSUS_RX - CENSUS_RY + dy;
                let r = &padded.data[py * pw + x..(py + 1) * pw];
                // "darker than the centre" = not (≥ centre).
                bits = (bits << cw) | (!crate::sv::row_bits(r, c, cw) & full);
            }
            *o = bits;
        }
    });
    Plane {
        width: w,
        height: h,
        data: out,
    }
}

/// Horizontal Sobel response, clamped to i16.
fn sobel_x(img: &Plane<u8>) -> Plane<i16> {
    let (w, h) = (img.width, img.height);
    let mut out = vec![0i16; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let up = img.row(y.saturating_sub(1));
        let mid = img.row(y);
        let dn = img.row((y + 1).min(h - 1));
        for x in 0..w {
            let l = x.saturating_sub(1);
            let r = (x + 1).min(w - 1);
            let g = (up[r] as i16 - up[l] as i16)
                + 2 * (mid[r] as i16 - mid[l] as i16)
                + (dn[r] as i16 - dn[l] as i16);
            row[x] = g;
        }
    });
    Plane {
        width: w,
        height: h,
        data: out,
    }
}

/// Matching cost volume `[y][x][d]` (u8); disparities whose right pixel falls outside the
/// image get [`COST_OUTSIDE`].
fn cost_volume(left: &Plane<u8>, right: &Plane<u8>, p: &QualityParams) -> Vec<u8> {
    let (w, h) = (left.width, left.height);
    let nd = p.range.count();
    let ((cl, cr), (gl, gr)) = rayon::join(
        || rayon::join(|| census(left), || census(right)),
        || rayon::join(|| sobel_x(left), || sobel_x(right)),
    );
    // Zeroed (fresh pages from the kernel, no fill pass); every entry is written below,
    // disparities outside the image included, by the threads that own the rows.
    let mut cost = vec![0u8; w * h * nd];
    let gw = p.gradient_weight;
    let cap = p.gradient_cap;
    cost.par_chunks_mut(w * nd)
        .enumerate()
        .for_each(|(y, row)| {
            let r = CostRow {
                cl: cl.row(y),
                cr: cr.row(y),
                gl: gl.row(y),
                gr: gr.row(y),
                dmin: p.range.min,
                gw,
                cap,
            };
            #[cfg(target_arch = "x86_64")]
            if crate::sv::has_vpopcnt() && r.fits_i32() {
                // SAFETY: the CPU has the features (checked at run time).
                return unsafe { r.fill_avx512(row) };
            }
            for x in 0..w {
                r.cells(x, 0..nd, &mut row[x * nd..(x + 1) * nd]);
            }
        });
    cost
}

/// The inputs of one row of the cost volume.
struct CostRow<'a> {
    cl: &'a [u64],
    cr: &'a [u64],
    gl: &'a [i16],
    gr: &'a [i16],
    dmin: i32,
    gw: u16,
    cap: u16,
}

impl CostRow<'_> {
    /// Costs of left pixel `x` at disparity indices `dis` into `out[dis]`; disparities
    /// pointing outside the right image get [`COST_OUTSIDE`].
    #[inline(always)]
    fn cells(&self, x: usize, dis: std::ops::Range<usize>, out: &mut [u8]) {
        let w = self.cl.len() as i32;
        for di in dis {
            let xr = x as i32 - (self.dmin + di as i32);
            if xr < 0 || xr >= w {
                out[di] = COST_OUTSIDE;
                continue;
            }
            let xr = xr as usize;
            let ham = (self.cl[x] ^ self.cr[xr]).count_ones() as u16;
            let g = (self.gl[x].abs_diff(self.gr[xr]) / 4).min(self.cap);
            out[di] = (ham * 2 + self.gw * g).min(COST_OUTSIDE as u16 - 1) as u8;
        }
    }

    /// Whether the cost sum fits the vector path's i32 lanes exactly as it does the
    /// scalar path's u16 (Hamming ≤ 63, doubled).
    fn fits_i32(&self) -> bool {
        self.gw as u32 * self.cap as u32 + 126 <= u16::MAX as u32
    }

    /// The whole row, eight disparities at a time: the right pixels `x − d` of eight
    /// consecutive disparities are eight consecutive census words read backwards.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512vpopcntdq")]
    unsafe fn fill_avx512(&self, row: &mut [u8]) {
        use std::arch::x86_64::*;
        let w = self.cl.len();
        let nd = row.len() / w;
        let rev64 = _mm512_set_epi64(0, 1, 2, 3, 4, 5, 6, 7);
        let rev16 = _mm_set_epi8(1, 0, 3, 2, 5, 4, 7, 6, 9, 8, 11, 10, 13, 12, 15, 14);
        let capv = _mm256_set1_epi32(self.cap as i32);
        let gwv = _mm256_set1_epi32(self.gw as i32);
        let top = _mm256_set1_epi32(COST_OUTSIDE as i32 - 1);
        for x in 0..w {
            let out = &mut row[x * nd..(x + 1) * nd];
            let clx = _mm512_set1_epi64(self.cl[x] as i64);
            let glx = _mm256_set1_epi32(self.gl[x] as i32);
            let mut di = 0;
            while di + 8 <= nd {
                // Right pixels of lanes 0..8 run from `hi` down to `hi − 7`.
                let hi = x as i64 - self.dmin as i64 - di as i64;
                if hi - 7 >= 0 && hi < w as i64 {
                    let lo = (hi - 7) as usize;
                    // SAFETY: lo..lo + 8 lies inside the row (checked just above), out
                    // holds di + 8 <= nd bytes.
                    unsafe {
                        let c = _mm512_loadu_si512(self.cr.as_ptr().add(lo) as *const _);
                        let c = _mm512_permutexvar_epi64(rev64, c);
                        let ham =
                            _mm512_cvtepi64_epi32(_mm512_popcnt_epi64(_mm512_xor_si512(c, clx)));
                        let g = _mm_loadu_si128(self.gr.as_ptr().add(lo) as *const __m128i);
                        let g = _mm256_cvtepi16_epi32(_mm_shuffle_epi8(g, rev16));
                        let ad = _mm256_abs_epi32(_mm256_sub_epi32(glx, g));
                        let gq = _mm256_min_epi32(_mm256_srli_epi32(ad, 2), capv);
                        let v = _mm256_add_epi32(
                            _mm256_slli_epi32(ham, 1),
                            _mm256_mullo_epi32(gq, gwv),
                        );
                        let b = _mm256_cvtepi32_epi8(_mm256_min_epi32(v, top));
                        _mm_storel_epi64(out.as_mut_ptr().add(di) as *mut __m128i, b);
                    }
                } else {
                    self.cells(x, di..di + 8, out);
                }
                di += 8;
            }
            self.cells(x, di..nd, out);
        }
    }
}

/// Cost given to disparities that point outside the right image.
pub const COST_OUTSIDE: u8 = 160;

/// Matches a rectified grey pair (checked with [`crate::check_inputs`]).
pub fn match_quality(left: &Plane<u8>, right: &Plane<u8>, p: &QualityParams) -> QualityMatch {
    let (w, h) = (left.width, left.height);
    let nd = p.range.count();
    let cost = cost_volume(left, right, p);
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    if simd_select_applies(nd, p) && simd::rows_fit(w, nd, p.range.min) {
        let (dl, dr) = meeting_sweeps(&cost, left, w, h, nd, p);
        return QualityMatch {
            left: dl,
            right: dr,
            evaluations: (w * h * nd) as u64,
        };
    }
    let (s1, s2) = rayon::join(
        || aggregate(&cost, left, w, h, nd, p, false),
        || aggregate(&cost, left, w, h, nd, p, true),
    );
    let (dl, dr) = select(&s1, &s2, w, h, nd, p);
    QualityMatch {
        left: dl,
        right: dr,
        evaluations: (w * h * nd) as u64,
    }
}

/// One SGM sweep over 4 paths. `backward` walks bottom-up, right-to-left, which mirrors
/// the four forward paths (left, top-left, top, top-right) onto the other four.
fn aggregate(
    cost: &[u8],
    img: &Plane<u8>,
    w: usize,
    h: usize,
    nd: usize,
    p: &QualityParams,
    backward: bool,
) -> Vec<u16> {
    let mut sum = vec![0u16; w * h * nd];
    let diagonals = p.paths >= 8;
    // Lr rows for the paths from the previous row (top-left, top, top-right) and the
    // current row's path from the left; `prev`/`cur` swap each row.
    let mut prev = vec![vec![0i16; w * nd]; 3];
    let mut cur = vec![vec![0i16; w * nd]; 3];
    let mut prev_min = vec![vec![0i16; w]; 3];
    let mut cur_min = vec![vec![0i16; w]; 3];
    let mut left_l = vec![0i16; nd];
    let mut left_min: i16 = 0;
    let mut scratch = vec![0i16; nd];
    let p1 = p.p1 as i16;
    // P2 lowered across intensity edges, looked up by |ΔI|.
    let p2_lut: Vec<i16> = (0..256u32)
        .map(|g| ((p.p2 as u32 * 16 / (16 + g)) as i16).max(p1 + 1))
        .collect();
    // Walk the image in sweep order: a backward sweep reads mirrored rows and columns.
    let oy = |y: usize| if backward { h - 1 - y } else { y };
    let ox = |x: usize| if backward { w - 1 - x } else { x };
    let mut acc = vec![0u16; nd];
    for y in 0..h {
        let irow = img.row(oy(y));
        let iprev = img.row(if y > 0 { oy(y - 1) } else { oy(y) });
        for x in 0..w {
            let pix = (oy(y) * w + ox(x)) * nd;
            let c = &cost[pix..pix + nd];
            let here = irow[ox(x)] as i16;
            let p2_at = |other: u8| p2_lut[(here - other as i16).unsigned_abs() as usize];
            // Path from the left (same row).
            if x == 0 {
                for d in 0..nd {
                    left_l[d] = c[d] as i16;
                }
            } else {
                step(
                    c,
                    &left_l,
                    left_min,
                    p1,
                    p2_at(irow[ox(x - 1)]),
                    &mut scratch,
                );
                std::mem::swap(&mut left_l, &mut scratch);
            }
            left_min = min_i16(&left_l);
            for d in 0..nd {
                acc[d] = left_l[d] as u16;
            }
            // Paths from the previous row: 0 = top-left, 1 = top, 2 = top-right.
            for k in 0..3 {
                if !diagonals && k != 1 {
                    continue;
                }
                let src = match k {
                    0 => x.checked_sub(1),
                    1 => Some(x),
                    _ => (x + 1 < w).then_some(x + 1),
                };
                let out = &mut cur[k][x * nd..(x + 1) * nd];
                match (y, src) {
                    (0, _) | (_, None) => {
                        for d in 0..nd {
                            out[d] = c[d] as i16;
                        }
                    }
                    (_, Some(sx)) => {
                        let lp = &prev[k][sx * nd..(sx + 1) * nd];
                        step(c, lp, prev_min[k][sx], p1, p2_at(iprev[ox(sx)]), out);
                    }
                }
                cur_min[k][x] = min_i16(out);
                for d in 0..nd {
                    acc[d] = acc[d].wrapping_add(out[d] as u16);
                }
            }
            sum[pix..pix + nd].copy_from_slice(&acc);
        }
        std::mem::swap(&mut prev, &mut cur);
        std::mem::swap(&mut prev_min, &mut cur_min);
    }
    sum
}

/// The top-down and the bottom-up sweep run side by side and meet: for each image row,
/// the sweep that finishes it first leaves its path sums in the row's slot, and the
/// second adds its own and decides the row at once. No full volume of sums is ever
/// written, and the decision runs inside the sweeps, half the rows on each thread.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
fn meeting_sweeps(
    cost: &[u8],
    img: &Plane<u8>,
    w: usize,
    h: usize,
    nd: usize,
    p: &QualityParams,
) -> (DisparityMap, DisparityMap) {
    use std::sync::Mutex;
    type Decided = Vec<(usize, Vec<f32>, Vec<f32>)>;
    let slots: Vec<Mutex<Option<Vec<u16>>>> = (0..h).map(|_| Mutex::new(None)).collect();
    let ndp = nd.div_ceil(16) * 16;
    let run = |backward: bool| -> Decided {
        let mut decided = Vec::new();
        let mut buf = Vec::new();
        simd::sweep(cost, img, w, h, nd, p, backward, |y, mut row| {
            let other = {
                let mut slot = slots[y].lock().unwrap_or_else(|e| e.into_inner());
                match slot.take() {
                    Some(other) => other,
                    None => {
                        *slot = Some(row);
                        return vec![0u16; w * ndp];
                    }
                }
            };
            for (a, b) in row.iter_mut().zip(&other) {
                *a = a.wrapping_add(*b);
            }
            let mut lrow = vec![INVALID_DISPARITY; w];
            let mut rrow = vec![INVALID_DISPARITY; w];
            simd::select_row(&row, ndp, w, nd, p, &mut buf, &mut lrow, &mut rrow);
            decided.push((y, lrow, rrow));
            // The other sweep's buffer is free now: it serves the next row.
            other
        });
        decided
    };
    let (a, b) = rayon::join(|| run(false), || run(true));
    let mut left = vec![INVALID_DISPARITY; w * h];
    let mut right = vec![INVALID_DISPARITY; w * h];
    for (y, l, r) in a.into_iter().chain(b) {
        left[y * w..(y + 1) * w].copy_from_slice(&l);
        right[y * w..(y + 1) * w].copy_from_slice(&r);
    }
    let plane = |data| Plane {
        width: w,
        height: h,
        data,
    };
    (plane(left), plane(right))
}

/// The SGM sweep with every path step as one AVX2 pass over 16 disparities at a time.
///
/// Path rows are stored per pixel as `[guard, L(0) … L(ndp − 1), guard]` with `ndp` the
/// disparity count rounded up to 16: lanes past the last disparity and the guards hold
/// [`simd::BIG`], so the `d ± 1` neighbours are plain unaligned loads and never win a
/// minimum. All values stay non-negative, so the horizontal minimum is `phminposuw`.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
mod simd {
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
                        _mm256_storeu_si256(
                            outs[j].as_mut_ptr().add(1 + k * 16) as *mut __m256i,
                            v,
                        );
                        mn[j] = _mm256_min_epi16(mn[j], v);
                        sum = _mm256_add_epi16(sum, v);
                    }
                    _mm256_storeu_si256(acc.as_mut_ptr().add(k * 16) as *mut __m256i, sum);
                }
                std::array::from_fn(|j| Self::hmin(mn[j]))
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

    /// Horizontal minimum of unsigned u16 lanes.
    #[inline(always)]
    fn hmin_u16(v: __m256i) -> u16 {
        // SAFETY: AVX2 (and so SSE4.1) is enabled for this build.
        unsafe {
            let m = _mm_min_epu16(_mm256_castsi256_si128(v), _mm256_extracti128_si256(v, 1));
            _mm_extract_epi16(_mm_minpos_epu16(m), 0) as u16
        }
    }

    /// [`super::decide`] over `t[lo..hi]` sixteen disparities at a time; `t` holds every
    /// disparity index of the pixel (at most [`super::simd_limits::MAX_ND`]). Lanes
    /// outside `lo..hi` read as `u16::MAX`, which no real summed cost reaches.
    #[inline(always)]
    pub fn decide(t: &[u16], lo: usize, hi: usize, uniqueness: u16, dmin: i32) -> f32 {
        let nd = t.len();
        let nvec = nd.div_ceil(16);
        let mut tm = [u16::MAX; super::simd_limits::MAX_ND];
        tm[lo..hi].copy_from_slice(&t[lo..hi]);
        let lanes: [i16; 16] = std::array::from_fn(|i| i as i16);
        // SAFETY: AVX2 is enabled for this build; loads read tm[16k .. 16k + 16] with
        // 16 · nvec <= MAX_ND (nd <= MAX_ND is the caller's condition, and MAX_ND is a
        // multiple of 16).
        unsafe {
            let idx0 = _mm256_loadu_si256(lanes.as_ptr() as *const __m256i);
            let mut bestv = _mm256_set1_epi16(-1);
            for k in 0..nvec {
                let v = _mm256_loadu_si256(tm.as_ptr().add(k * 16) as *const __m256i);
                bestv = _mm256_min_epu16(bestv, v);
            }
            let best = hmin_u16(bestv);
            let bv = _mm256_set1_epi16(best as i16);
            let mut bi = 0;
            for k in 0..nvec {
                let v = _mm256_loadu_si256(tm.as_ptr().add(k * 16) as *const __m256i);
                let eq = _mm256_movemask_epi8(_mm256_cmpeq_epi16(v, bv)) as u32;
                if eq != 0 {
                    bi = k * 16 + eq.trailing_zeros() as usize / 2;
                    break;
                }
            }
            // Rival: the smallest cost more than one index away from bi.
            let lo_n = _mm256_set1_epi16(bi as i16 - 2);
            let hi_n = _mm256_set1_epi16(bi as i16 + 2);
            let mut rivalv = _mm256_set1_epi16(-1);
            for k in 0..nvec {
                let v = _mm256_loadu_si256(tm.as_ptr().add(k * 16) as *const __m256i);
                let idx = _mm256_add_epi16(idx0, _mm256_set1_epi16((k * 16) as i16));
                let near =
                    _mm256_and_si256(_mm256_cmpgt_epi16(idx, lo_n), _mm256_cmpgt_epi16(hi_n, idx));
                rivalv = _mm256_min_epu16(rivalv, _mm256_or_si256(v, near));
            }
            let rival = hmin_u16(rivalv);
            let u = uniqueness as u32;
            if rival != u16::MAX && (rival as u32) * (100 - u) < (best as u32) * 100 {
                return schemas::INVALID_DISPARITY;
            }
            let mut d = bi as f32 + dmin as f32;
            if bi > lo && bi + 1 < hi {
                let (a, b, c) = (tm[bi - 1] as f32, tm[bi] as f32, tm[bi + 1] as f32);
                let den = a + c - 2.0 * b;
                if den > 0.0 {
                    d += (a - c) / (2.0 * den);
                }
            }
            d
        }
    }

    /// P2 between two neighbouring intensities (lowered across edges).
    #[inline(always)]
    fn p2_between(lut: &[i16], a: u8, b: u8) -> i16 {
        lut[a.abs_diff(b) as usize]
    }

    /// The 8-path step of one pixel for exactly `16 · NV` disparities, written out path by
    /// path so that the per-path constants and minima stay in registers.
    ///
    /// # Safety
    /// `c` and `acc` point at `16 · NV` values, every `lp` and `out` at `16 · NV + 2`.
    #[inline(always)]
    unsafe fn step4<const NV: usize>(
        c: *const u8,
        lp: [*const i16; 4],
        mins: [i16; 4],
        p2s: [i16; 4],
        p1: i16,
        out: [*mut i16; 4],
        acc: *mut u16,
    ) -> [i16; 4] {
        // SAFETY: the caller's promise; AVX2 is enabled for this build.
        unsafe {
            let p1v = _mm256_set1_epi16(p1);
            let (j0, j1, j2, j3) = (
                _mm256_set1_epi16(mins[0] + p2s[0]),
                _mm256_set1_epi16(mins[1] + p2s[1]),
                _mm256_set1_epi16(mins[2] + p2s[2]),
                _mm256_set1_epi16(mins[3] + p2s[3]),
            );
            let (m0, m1, m2, m3) = (
                _mm256_set1_epi16(mins[0]),
                _mm256_set1_epi16(mins[1]),
                _mm256_set1_epi16(mins[2]),
                _mm256_set1_epi16(mins[3]),
            );
            let big = _mm256_set1_epi16(BIG);
            let (mut n0, mut n1, mut n2, mut n3) = (big, big, big, big);
            macro_rules! path {
                ($i:literal, $k:ident, $cv:ident, $jump:ident, $minv:ident, $mn:ident, $sum:ident) => {{
                    let base = lp[$i].add($k * 16);
                    let a = _mm256_loadu_si256(base as *const __m256i);
                    let m = _mm256_loadu_si256(base.add(1) as *const __m256i);
                    let b = _mm256_loadu_si256(base.add(2) as *const __m256i);
                    let nb = _mm256_add_epi16(_mm256_min_epi16(a, b), p1v);
                    let v = _mm256_min_epi16(_mm256_min_epi16(m, nb), $jump);
                    let v = _mm256_add_epi16($cv, _mm256_sub_epi16(v, $minv));
                    _mm256_storeu_si256(out[$i].add(1 + $k * 16) as *mut __m256i, v);
                    $mn = _mm256_min_epi16($mn, v);
                    $sum = _mm256_add_epi16($sum, v);
                }};
            }
            for k in 0..NV {
                let cv = _mm256_cvtepu8_epi16(_mm_loadu_si128(c.add(k * 16) as *const __m128i));
                let mut sum = _mm256_setzero_si256();
                path!(0, k, cv, j0, m0, n0, sum);
                path!(1, k, cv, j1, m1, n1, sum);
                path!(2, k, cv, j2, m2, n2, sum);
                path!(3, k, cv, j3, m3, n3, sum);
                _mm256_storeu_si256(acc.add(k * 16) as *mut __m256i, sum);
            }
            [
                Kernel::hmin(n0),
                Kernel::hmin(n1),
                Kernel::hmin(n2),
                Kernel::hmin(n3),
            ]
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
                let sel = if half == 0 { 0x20 } else { 0x31 };
                let x: [__m256i; 8] = std::array::from_fn(|i| match sel {
                    0x20 => _mm256_permute2x128_si256(a[i], a[i + 8], 0x20),
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
                let near =
                    _mm256_and_si256(_mm256_cmpgt_epi16(dv, lo2), _mm256_cmpgt_epi16(hi2, dv));
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
        if rival != NONE && (rival as u32) * (100 - u) < (best as u32) * 100 {
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
    #[allow(clippy::too_many_arguments)]
    pub fn select_row(
        total: &[u16],
        tstride: usize,
        w: usize,
        nd: usize,
        p: &QualityParams,
        mt: &mut Vec<u16>,
        lrow: &mut [f32],
        rrow: &mut [f32],
    ) {
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
    pub fn aggregate(
        cost: &[u8],
        img: &Plane<u8>,
        w: usize,
        h: usize,
        nd: usize,
        p: &QualityParams,
        backward: bool,
    ) -> Vec<u16> {
        let mut sum = vec![0u16; w * h * nd];
        let ndp = nd.div_ceil(16) * 16;
        sweep(cost, img, w, h, nd, p, backward, |y, row| {
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
    #[allow(clippy::too_many_arguments)]
    pub fn sweep(
        cost: &[u8],
        img: &Plane<u8>,
        w: usize,
        h: usize,
        nd: usize,
        p: &QualityParams,
        backward: bool,
        mut row_done: impl FnMut(usize, Vec<u16>) -> Vec<u16>,
    ) {
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
        let p2_lut: Vec<i16> = (0..256u32)
            .map(|g| ((p.p2 as u32 * 16 / (16 + g)) as i16).max(p1 + 1))
            .collect();
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
                if diagonals && (nd == 64 || nd == 128) {
                    let tl = from_row!(0, x.checked_sub(1));
                    let tr = from_row!(2, (x + 1 < w).then_some(x + 1));
                    let from = [left, tl, top, tr];
                    for (lp, _, _) in &from {
                        assert!(lp.len() >= stride);
                    }
                    assert!(c.len() == nd && acc.len() == nd && scratch.len() == stride);
                    let outs = [
                        scratch.as_mut_ptr(),
                        c0[o.clone()].as_mut_ptr(),
                        c1[o.clone()].as_mut_ptr(),
                        c2[o].as_mut_ptr(),
                    ];
                    let lps = from.map(|f| f.0.as_ptr());
                    let mins = from.map(|f| f.1);
                    let p2s = from.map(|f| f.2);
                    // SAFETY: every predecessor and output holds `stride` = nd + 2 values,
                    // the costs and the sum nd (asserted above); AVX2 is enabled.
                    let m = unsafe {
                        if nd == 64 {
                            step4::<4>(c.as_ptr(), lps, mins, p2s, p1, outs, acc.as_mut_ptr())
                        } else {
                            step4::<8>(c.as_ptr(), lps, mins, p2s, p1, outs, acc.as_mut_ptr())
                        }
                    };
                    left_min = m[0];
                    cur_min[0][x] = m[1];
                    cur_min[1][x] = m[2];
                    cur_min[2][x] = m[3];
                } else if diagonals {
                    let tl = from_row!(0, x.checked_sub(1));
                    let tr = from_row!(2, (x + 1 < w).then_some(x + 1));
                    let m = kern.paths(
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
                    let m = kern.paths(c, [left, top], p1, [&mut scratch, &mut c1[o]], acc);
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
}

/// Minimum of a slice; a plain fold vectorises where `Iterator::min` does not.
#[inline(always)]
fn min_i16(v: &[i16]) -> i16 {
    v.iter().fold(i16::MAX, |m, &x| m.min(x))
}

/// One SGM recurrence step:
/// `L(d) = C(d) + min(Lp(d), Lp(d±1) + P1, min Lp + P2) − min Lp`.
#[inline(always)]
fn step(c: &[u8], lp: &[i16], lp_min: i16, p1: i16, p2: i16, out: &mut [i16]) {
    let nd = c.len();
    let jump = lp_min + p2;
    if nd == 1 {
        out[0] = c[0] as i16 + lp[0].min(jump) - lp_min;
        return;
    }
    out[0] = c[0] as i16 + lp[0].min(lp[1] + p1).min(jump) - lp_min;
    out[nd - 1] = c[nd - 1] as i16 + lp[nd - 1].min(lp[nd - 2] + p1).min(jump) - lp_min;
    let (o, cc) = (&mut out[1..nd - 1], &c[1..nd - 1]);
    let (a, b, m) = (&lp[..nd - 2], &lp[2..], &lp[1..nd - 1]);
    for i in 0..nd - 2 {
        let v = m[i].min(a[i] + p1).min(b[i] + p1).min(jump);
        o[i] = cc[i] as i16 + v - lp_min;
    }
}

/// Winner-takes-all on the summed paths, with uniqueness ratio and sub-pixel parabola.
fn select(
    s1: &[u16],
    s2: &[u16],
    w: usize,
    h: usize,
    nd: usize,
    p: &QualityParams,
) -> (DisparityMap, DisparityMap) {
    let fast = simd_select_applies(nd, p);
    let mut left = vec![INVALID_DISPARITY; w * h];
    let mut right = vec![INVALID_DISPARITY; w * h];
    left.par_chunks_mut(w)
        .zip(right.par_chunks_mut(w))
        .enumerate()
        .for_each_init(
            || (vec![0u16; w * nd], Vec::new()),
            |(total, buf), (y, (lrow, rrow))| {
                let o = y * w * nd;
                for i in 0..w * nd {
                    total[i] = s1[o + i].wrapping_add(s2[o + i]);
                }
                select_row(total, w, nd, p, fast, buf, lrow, rrow);
            },
        );
    let plane = |data| Plane {
        width: w,
        height: h,
        data,
    };
    (plane(left), plane(right))
}

/// Decides one row from its summed path costs `total` (`w · nd`): the left-based map from
/// each pixel's disparities, the right-based one along the diagonals. `buf` is scratch.
#[allow(clippy::too_many_arguments)]
fn select_row(
    total: &[u16],
    w: usize,
    nd: usize,
    p: &QualityParams,
    fast: bool,
    buf: &mut Vec<u16>,
    lrow: &mut [f32],
    rrow: &mut [f32],
) {
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    if fast && simd::rows_fit(w, nd, p.range.min) {
        return simd::select_row(total, nd, w, nd, p, buf, lrow, rrow);
    }
    buf.resize(nd, 0);
    let dmin = p.range.min;
    // Left-based: every disparity whose right pixel exists.
    for x in 0..w {
        let lo = (x as i32 - w as i32 + 1 - dmin).max(0) as usize;
        let hi = ((x as i32 - dmin + 1).min(nd as i32)).max(0) as usize;
        if lo >= hi {
            continue;
        }
        let t = &total[x * nd..(x + 1) * nd];
        lrow[x] = decide_fast(t, lo, hi, p, fast);
    }
    // Right-based: right pixel xr at disparity d is left pixel xr + d.
    for xr in 0..w {
        // Disparity indices whose left pixel xr + dmin + di lies in the image.
        let base = xr as i64 + dmin as i64;
        let lo = (-base).clamp(0, nd as i64) as usize;
        let hi = (w as i64 - base).clamp(0, nd as i64) as usize;
        if lo >= hi {
            continue;
        }
        for di in lo..hi {
            buf[di] = total[(base + di as i64) as usize * nd + di];
        }
        rrow[xr] = decide_fast(buf, lo, hi, p, fast);
    }
}

/// Whether [`simd::decide`] may stand in for [`decide`]: with the penalties the SIMD sweep
/// accepts, no summed cost reaches `u16::MAX`, the value that marks unused lanes.
fn simd_select_applies(nd: usize, p: &QualityParams) -> bool {
    cfg!(all(target_arch = "x86_64", target_feature = "avx2"))
        && nd <= simd_limits::MAX_ND
        && p.p1 <= simd_limits::MAX_PENALTY
        && p.p2 <= simd_limits::MAX_PENALTY
        && p.uniqueness_ratio <= 100
}

/// Limits of the SIMD paths, also known where they are not compiled.
mod simd_limits {
    /// Largest P1/P2 for which the guard values stay apart from real costs and eight
    /// summed paths stay below `i16::MAX`.
    pub const MAX_PENALTY: u16 = 3800;
    /// Most disparities the SIMD decision holds on the stack.
    pub const MAX_ND: usize = 256;
}

/// The decision over `t[lo..hi]` (`t` holds every disparity index of the pixel).
#[inline(always)]
fn decide_fast(t: &[u16], lo: usize, hi: usize, p: &QualityParams, fast: bool) -> f32 {
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    if fast {
        return simd::decide(t, lo, hi, p.uniqueness_ratio, p.range.min);
    }
    let _ = fast;
    decide(&t[lo..hi], lo, p.uniqueness_ratio, p.range.min)
}

/// Picks the best disparity of a contiguous cost run starting at index `lo`.
#[inline]
fn decide(t: &[u16], lo: usize, uniqueness: u16, dmin: i32) -> f32 {
    let (mut best, mut bi) = (u16::MAX, 0);
    for (i, &v) in t.iter().enumerate() {
        if v < best {
            best = v;
            bi = i;
        }
    }
    let u = uniqueness as u32;
    for (i, &v) in t.iter().enumerate() {
        if i.abs_diff(bi) > 1 && (v as u32) * (100 - u) < (best as u32) * 100 {
            return INVALID_DISPARITY;
        }
    }
    let mut d = (lo + bi) as f32 + dmin as f32;
    if bi > 0 && bi + 1 < t.len() {
        let (a, b, c) = (t[bi - 1] as f32, t[bi] as f32, t[bi + 1] as f32);
        let den = a + c - 2.0 * b;
        if den > 0.0 {
            d += (a - c) / (2.0 * den);
        }
    }
    d
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[test]
    fn simd_sweep_equals_the_plain_one() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (w, h) = (37, 23);
        let img = Plane::from_vec(w, h, (0..w * h).map(|_| rng.random::<u8>()).collect()).unwrap();
        for nd in [1, 5, 16, 17, 40, 64, 128] {
            let cost: Vec<u8> = (0..w * h * nd)
                .map(|_| rng.random_range(0..COST_OUTSIDE))
                .collect();
            for paths in [4, 8] {
                let p = QualityParams {
                    range: DisparityRange::new(0, nd as i32 - 1),
                    paths,
                    ..Default::default()
                };
                for backward in [false, true] {
                    assert_eq!(
                        simd::aggregate(&cost, &img, w, h, nd, &p, backward),
                        aggregate(&cost, &img, w, h, nd, &p, backward),
                        "nd {nd} paths {paths} backward {backward}"
                    );
                }
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn vector_cost_row_equals_the_scalar_one() {
        if !crate::sv::has_vpopcnt() {
            return;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let w = 70;
        let cl: Vec<u64> = (0..w).map(|_| rng.random::<u64>() >> 1).collect();
        let cr: Vec<u64> = (0..w).map(|_| rng.random::<u64>() >> 1).collect();
        let gl: Vec<i16> = (0..w).map(|_| rng.random_range(-1020..=1020)).collect();
        let gr: Vec<i16> = (0..w).map(|_| rng.random_range(-1020..=1020)).collect();
        for (dmin, nd) in [(0, 64), (-10, 21), (5, 8), (-3, 1), (60, 16)] {
            let r = CostRow {
                cl: &cl,
                cr: &cr,
                gl: &gl,
                gr: &gr,
                dmin,
                gw: 1,
                cap: 30,
            };
            let mut fast = vec![0u8; w * nd];
            let mut slow = fast.clone();
            // SAFETY: the CPU has the features (checked above).
            unsafe { r.fill_avx512(&mut fast) };
            for x in 0..w {
                r.cells(x, 0..nd, &mut slow[x * nd..(x + 1) * nd]);
            }
            assert_eq!(fast, slow, "dmin {dmin} nd {nd}");
        }
    }

    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[test]
    fn simd_decision_equals_the_plain_one() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for _ in 0..3000 {
            let nd = rng.random_range(1..=100);
            // Few distinct values, so ties and near-ties are common.
            let t: Vec<u16> = (0..nd).map(|_| rng.random_range(200..240)).collect();
            let lo = rng.random_range(0..nd);
            let hi = rng.random_range(lo + 1..=nd);
            let u = rng.random_range(0..=30);
            let dmin = rng.random_range(-20..20);
            let a = simd::decide(&t, lo, hi, u, dmin);
            let b = decide(&t[lo..hi], lo, u, dmin);
            assert!(
                a == b || (a.is_infinite() && b.is_infinite()),
                "{t:?} {lo}..{hi} u {u}"
            );
        }
    }

    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[test]
    fn transposed_row_decision_equals_the_plain_one() {
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        for (w, nd, dmin) in [
            (40, 16, 0),
            (37, 20, -5),
            (70, 64, 3),
            (16, 1, 0),
            (50, 33, -40),
        ] {
            let p = QualityParams {
                range: DisparityRange::new(dmin, dmin + nd as i32 - 1),
                ..Default::default()
            };
            // A clear valley at a random disparity for most pixels, flat noise (ties,
            // uniqueness rejections) for the rest.
            let mut total = vec![0u16; w * nd];
            for px in total.chunks_mut(nd) {
                let valley = rng.random_range(0..nd) as i32;
                let flat = rng.random_bool(0.3);
                for (di, t) in px.iter_mut().enumerate() {
                    *t = if flat {
                        rng.random_range(900..960)
                    } else {
                        300 + (di as i32 - valley).unsigned_abs() as u16 * 40
                            + rng.random_range(0..20)
                    };
                }
            }
            let (mut l1, mut r1) = (vec![INVALID_DISPARITY; w], vec![INVALID_DISPARITY; w]);
            let (mut l2, mut r2) = (l1.clone(), r1.clone());
            let mut buf = Vec::new();
            simd::select_row(&total, nd, w, nd, &p, &mut buf, &mut l1, &mut r1);
            select_row(&total, w, nd, &p, false, &mut buf, &mut l2, &mut r2);
            let same = |a: &[f32], b: &[f32]| {
                a.iter()
                    .zip(b)
                    .all(|(x, y)| x == y || (x.is_infinite() && y.is_infinite()))
            };
            assert!(same(&l1, &l2), "left w {w} nd {nd} dmin {dmin}");
            assert!(same(&r1, &r2), "right w {w} nd {nd} dmin {dmin}");
            assert!(l1.iter().any(|d| d.is_finite()) && r1.iter().any(|d| d.is_finite()));
        }
    }

    #[test]
    fn census_follows_its_definition() {
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        let (w, h) = (75, 12);
        // Few grey levels: ties with the centre (not darker) are common.
        let img = Plane::from_vec(
            w,
            h,
            (0..w * h).map(|_| rng.random_range(0..6u8) * 40).collect(),
        )
        .unwrap();
        let c = census(&img);
        for y in 0..h {
            for x in 0..w {
                let centre = *img.get(x, y);
                let mut bits = 0u64;
                for dy in 0..7 {
                    let yy = (y as i64 + dy - 3).clamp(0, h as i64 - 1) as usize;
                    let mut row = 0u64;
                    for j in 0..9 {
                        let xx = (x as i64 + j - 4).clamp(0, w as i64 - 1) as usize;
                        row |= u64::from(*img.get(xx, yy) < centre) << j;
                    }
                    bits = (bits << 9) | row;
                }
                assert_eq!(*c.get(x, y), bits, "pixel ({x}, {y})");
            }
        }
    }

    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[test]
    fn meeting_sweeps_equal_the_plain_pipeline() {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let (w, h) = (61, 40);
        let left = Plane::from_vec(w, h, (0..w * h).map(|_| rng.random::<u8>()).collect()).unwrap();
        // The right view: the left shifted by 3 px plus noise, so matches exist.
        let right = Plane::from_vec(
            w,
            h,
            (0..w * h)
                .map(|i| {
                    let (x, y) = (i % w, i / w);
                    left.get((x + 3).min(w - 1), y)
                        .saturating_add(rng.random_range(0..8))
                })
                .collect(),
        )
        .unwrap();
        for (dmin, nd) in [(0, 16), (-4, 21), (0, 64)] {
            let p = QualityParams {
                range: DisparityRange::new(dmin, dmin + nd as i32 - 1),
                ..Default::default()
            };
            let fast = match_quality(&left, &right, &p);
            let cost = cost_volume(&left, &right, &p);
            let s1 = aggregate(&cost, &left, w, h, nd, &p, false);
            let s2 = aggregate(&cost, &left, w, h, nd, &p, true);
            let mut buf = Vec::new();
            for y in 0..h {
                let o = y * w * nd;
                let total: Vec<u16> = (0..w * nd)
                    .map(|i| s1[o + i].wrapping_add(s2[o + i]))
                    .collect();
                let (mut l, mut r) = (vec![INVALID_DISPARITY; w], vec![INVALID_DISPARITY; w]);
                select_row(&total, w, nd, &p, false, &mut buf, &mut l, &mut r);
                let same = |a: &[f32], b: &[f32]| {
                    a.iter()
                        .zip(b)
                        .all(|(x, y)| x == y || (x.is_infinite() && y.is_infinite()))
                };
                assert!(
                    same(fast.left.row(y), &l),
                    "left row {y}, range {dmin}+{nd}"
                );
                assert!(
                    same(fast.right.row(y), &r),
                    "right row {y}, range {dmin}+{nd}"
                );
            }
            assert!(fast.left.data.iter().filter(|d| d.is_finite()).count() > w * h / 4);
        }
    }
}
