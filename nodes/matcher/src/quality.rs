//! Quality mode: census + gradient cost, semi-global aggregation over 4 or 8 paths.
//!
//! Cost: Hamming distance of 9×7 census descriptors (robust to the gain and offset
//! differences between two microscope cameras) plus a truncated difference of horizontal
//! gradients (sharpens depth edges). Aggregation: Hirschmüller's SGM over 4 paths
//! (horizontal and vertical, the default) or 8 (with the diagonals), with the large-jump
//! penalty P2 lowered across intensity edges. On the four Middlebury sets 8 paths gain
//! 0.04 points of mean bad-1 (2.67 against 2.71 %) for 16–25 % more matching time, so 4
//! is the default. Two passes (top-down and bottom-up, half the paths each) run in parallel
//! and meet: whichever reaches an image row second adds the other's sums into its own
//! and decides the row. Decision: winner-takes-all with a uniqueness ratio and a
//! sub-pixel parabola; the right-based map is read from the same sums along their
//! diagonals, so the LR check costs no second matching.
//!
//! With AVX2 (every build of this project) the sweeps run 16 disparities per
//! instruction and the decision 16 pixels per instruction; where the CPU has AVX-512BW
//! (checked at run time) 32 of each. The plain versions remain for penalties beyond the
//! SIMD limits and as the reference the tests compare against.

use rayon::prelude::*;
use schemas::{DisparityMap, DisparityRange, INVALID_DISPARITY, Plane};
use serde::{Deserialize, Serialize};
use std::sync::{Mutex, MutexGuard};

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
    /// Percent margin by which the best cost must beat every non-neighbour disparity
    /// (100 or more rejects every pixel that has a rival and a best cost above 0).
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
            paths: 4,
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
    #[cfg(target_arch = "x86_64")]
    let wide = crate::sv::has_avx512bw();
    #[cfg(not(target_arch = "x86_64"))]
    let wide = false;
    census_with(img, wide)
}

/// [`census`], 64 pixels at a time with AVX-512 when `wide` (which the CPU must
/// support), else 32 with AVX2.
fn census_with(img: &Plane<u8>, wide: bool) -> Plane<u64> {
    let (w, h) = (img.width, img.height);
    let padded = crate::sv::pad_replicate(img, CENSUS_RX);
    let pw = padded.width;
    let cw = 2 * CENSUS_RX + 1;
    let full = (1u64 << cw) - 1;
    let mut out = vec![0u64; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        #[allow(unused_mut)]
        let mut x0 = 0;
        #[cfg(target_arch = "x86_64")]
        if wide {
            assert!(
                crate::sv::has_avx512bw(),
                "AVX-512 census on a CPU without it"
            );
            // SAFETY: the CPU has AVX-512BW (asserted just above).
            x0 = unsafe { census512::row(&padded, img.row(y), y, row) };
        }
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

/// The census with AVX-512: one byte compare tests a window position for 64 pixels.
#[cfg(target_arch = "x86_64")]
mod census512 {
    use super::{CENSUS_RX, CENSUS_RY};
    use schemas::Plane;
    use std::arch::x86_64::*;

    /// Census words of row `y` (grey values `centre`) into `out`, 64 pixels at a time
    /// from the start; returns how many pixels it did (a multiple of 64). `padded` is
    /// the image with `CENSUS_RX` replicated pixels on every side.
    ///
    /// # Safety
    /// The CPU must support AVX-512F and AVX-512BW.
    #[target_feature(enable = "avx512f,avx512bw")]
    pub unsafe fn row(padded: &Plane<u8>, centre: &[u8], y: usize, out: &mut [u64]) -> usize {
        const COLS: usize = 2 * CENSUS_RX + 1;
        const ROWS: usize = 2 * CENSUS_RY + 1;
        let (w, pw) = (out.len(), padded.width);
        assert!(centre.len() == w && pw == w + 2 * CENSUS_RX);
        assert!(padded.height > y + CENSUS_RX + CENSUS_RY);
        let full = _mm512_set1_epi64(((1u128 << (COLS * ROWS)) - 1) as i64);
        let mut x0 = 0;
        while x0 + 64 <= w {
            // SAFETY: the window rows y + RX − RY + i lie inside `padded` and the loads
            // read bytes x0 + j .. x0 + j + 64 <= w + 2·RX of them (asserted above);
            // `centre` and `out` hold x0 + 64 values.
            unsafe {
                let t = _mm512_loadu_si512(centre.as_ptr().add(x0) as *const _);
                // Per pixel, bits of the window rows so far, in 64-bit lanes of 8
                // consecutive pixels.
                let mut acc = [_mm512_setzero_si512(); 8];
                for i in 0..ROWS {
                    let src = padded
                        .data
                        .as_ptr()
                        .add((y + CENSUS_RX - CENSUS_RY + i) * pw + x0);
                    // Bit j of a pixel's byte in lo (j < 8) or hi (j = 8): not darker.
                    let (mut lo, mut hi) = (_mm512_setzero_si512(), _mm512_setzero_si512());
                    for j in 0..COLS {
                        let v = _mm512_loadu_si512(src.add(j) as *const _);
                        let ge = _mm512_cmpge_epu8_mask(v, t);
                        let bit = _mm512_set1_epi8((1u8 << (j % 8)) as i8);
                        if j < 8 {
                            lo = _mm512_mask_add_epi8(lo, ge, lo, bit);
                        } else {
                            hi = _mm512_mask_add_epi8(hi, ge, hi, bit);
                        }
                    }
                    // 9-bit words per pixel; each 128-bit lane L of the unpacked
                    // vectors holds pixels 16L..16L + 8 (low) and 16L + 8..16L + 16.
                    let words = [_mm512_unpacklo_epi8(lo, hi), _mm512_unpackhi_epi8(lo, hi)];
                    let shift = _mm_cvtsi64_si128(((ROWS - 1 - i) * COLS) as i64);
                    for (q, a) in acc.iter_mut().enumerate() {
                        let (lane, half) = (q / 2, q % 2);
                        let part = match lane {
                            0 => _mm512_extracti32x4_epi32::<0>(words[half]),
                            1 => _mm512_extracti32x4_epi32::<1>(words[half]),
                            2 => _mm512_extracti32x4_epi32::<2>(words[half]),
                            _ => _mm512_extracti32x4_epi32::<3>(words[half]),
                        };
                        let wide = _mm512_sll_epi64(_mm512_cvtepu16_epi64(part), shift);
                        *a = _mm512_or_si512(*a, wide);
                    }
                }
                for (q, a) in acc.iter().enumerate() {
                    // "darker than the centre" = not (≥ centre).
                    let v = _mm512_andnot_si512(*a, full);
                    _mm512_storeu_si512(out.as_mut_ptr().add(x0 + 8 * q) as *mut _, v);
                }
            }
            x0 += 64;
        }
        x0
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

/// Matching cost volume `[y][x][d]` (u8) into `cost`; disparities whose right pixel falls
/// outside the image get [`COST_OUTSIDE`].
fn cost_volume(left: &Plane<u8>, right: &Plane<u8>, p: &QualityParams, cost: &mut Vec<u8>) {
    let (w, h) = (left.width, left.height);
    let nd = p.range.count();
    let ((cl, cr), (gl, gr)) = rayon::join(
        || rayon::join(|| census(left), || census(right)),
        || rayon::join(|| sobel_x(left), || sobel_x(right)),
    );
    // Every entry is written below, disparities outside the image included, by the
    // threads that own the rows: a volume of the right size is reused as it is.
    if cost.len() != w * h * nd {
        *cost = vec![0u8; w * h * nd];
    }
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
    ///
    /// # Safety
    /// The CPU must support AVX-512F, VL, BW and VPOPCNTDQ.
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

/// Buffers the quality matcher keeps from one frame to the next. The cost volume is
/// `w·h·n` bytes (84 MB at 1280×1024 and 64 disparities): faulting fresh pages in for it
/// every frame took longer than computing it, so a stream of frames reuses one.
#[derive(Debug, Default)]
pub struct QualityWorkspace {
    cost: Vec<u8>,
    /// Row buffers of path sums: the sweeps leave half the image's rows behind for each
    /// other (168 MB at 1280×1024), which cost as much to fault in as the cost volume.
    rows: Vec<Vec<u16>>,
}

/// Matches a rectified grey pair (checked with [`crate::check_inputs`]), with buffers
/// allocated for this call alone; [`match_quality_in`] reuses them across frames.
pub fn match_quality(left: &Plane<u8>, right: &Plane<u8>, p: &QualityParams) -> QualityMatch {
    match_quality_in(&mut QualityWorkspace::default(), left, right, p)
}

/// Matches a rectified grey pair (checked with [`crate::check_inputs`]) in the buffers of
/// `ws`, which keep their size for the next frame.
pub fn match_quality_in(
    ws: &mut QualityWorkspace,
    left: &Plane<u8>,
    right: &Plane<u8>,
    p: &QualityParams,
) -> QualityMatch {
    let (w, h) = (left.width, left.height);
    let nd = p.range.count();
    cost_volume(left, right, p, &mut ws.cost);
    let cost = &ws.cost;
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    if simd_applies(p) && simd::rows_fit(w, nd, p.range.min) {
        let (dl, dr) = meeting_sweeps(cost, left, p, &mut ws.rows);
        return QualityMatch {
            left: dl,
            right: dr,
            evaluations: (w * h * nd) as u64,
        };
    }
    let (s1, s2) = rayon::join(
        || aggregate(cost, left, p, false),
        || aggregate(cost, left, p, true),
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
fn aggregate(cost: &[u8], img: &Plane<u8>, p: &QualityParams, backward: bool) -> Vec<u16> {
    let (w, h, nd) = (img.width, img.height, p.range.count());
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
    let p2_lut = p2_table(p);
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
/// the sweep that reaches it first leaves its path sums in the row's slot, and the
/// second adds them into its own (while it computes the row, when they are there in
/// time) and decides the row at once. The decision runs inside the sweeps, half the
/// rows on each thread. `rows` keeps the row buffers for the next frame.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
fn meeting_sweeps(
    cost: &[u8],
    img: &Plane<u8>,
    p: &QualityParams,
    rows: &mut Vec<Vec<u16>>,
) -> (DisparityMap, DisparityMap) {
    let (w, h, nd) = (img.width, img.height, p.range.count());
    let ndp = nd.div_ceil(16) * 16;
    rows.retain(|r| r.len() == w * ndp);
    let mut left = vec![INVALID_DISPARITY; w * h];
    let mut right = vec![INVALID_DISPARITY; w * h];
    let shared = Meeting {
        slots: left
            .chunks_mut(w)
            .zip(right.chunks_mut(w))
            .map(|out| {
                Mutex::new(Slot {
                    sums: None,
                    out: Some(out),
                })
            })
            .collect(),
        pool: Mutex::new(std::mem::take(rows)),
        w,
        ndp,
    };
    let run = |backward: bool| {
        let mut side = MeetingSide {
            shared: &shared,
            p,
            scratch: Vec::new(),
        };
        let last = simd::sweep(cost, img, p, backward, shared.buffer(), &mut side);
        lock(&shared.pool).push(last);
    };
    rayon::join(|| run(false), || run(true));
    *rows = shared.pool.into_inner().unwrap_or_else(|e| e.into_inner());
    let plane = |data| Plane {
        width: w,
        height: h,
        data,
    };
    (plane(left), plane(right))
}

/// Locks a mutex whether or not another thread panicked holding it (the data stay
/// consistent: every critical section below is a plain move).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// One image row of a [`Meeting`].
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
struct Slot<'a> {
    /// The sums the first sweep to finish the row left for the second.
    sums: Option<Vec<u16>>,
    /// The row of the left- and the right-based map, until the row is decided.
    out: Option<(&'a mut [f32], &'a mut [f32])>,
}

/// What the two sweeps of [`meeting_sweeps`] share.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
struct Meeting<'a> {
    /// Per image row: its slot.
    slots: Vec<Mutex<Slot<'a>>>,
    /// Free row buffers. Every value of a buffer is overwritten by the sweep, so none
    /// needs clearing.
    pool: Mutex<Vec<Vec<u16>>>,
    /// Row width.
    w: usize,
    /// Values per pixel in a row buffer.
    ndp: usize,
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
impl Meeting<'_> {
    /// A free row buffer.
    fn buffer(&self) -> Vec<u16> {
        lock(&self.pool)
            .pop()
            .unwrap_or_else(|| vec![0u16; self.w * self.ndp])
    }
}

/// One sweep's end of a [`Meeting`].
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
struct MeetingSide<'a, 'o> {
    shared: &'a Meeting<'o>,
    p: &'a QualityParams,
    scratch: Vec<u16>,
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
impl MeetingSide<'_, '_> {
    /// Decides row `y` from `total` (+ `other`) into the maps.
    fn decide(&mut self, y: usize, total: &[u16], other: Option<&[u16]>) {
        let out = lock(&self.shared.slots[y]).out.take();
        let (lrow, rrow) = out.expect("every row is decided once");
        let ndp = self.shared.ndp;
        simd::select_row(total, other, ndp, self.p, &mut self.scratch, lrow, rrow);
    }
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
impl simd::Rows for &mut MeetingSide<'_, '_> {
    fn start(&mut self, y: usize) -> Option<Vec<u16>> {
        lock(&self.shared.slots[y]).sums.take()
    }

    fn done(&mut self, y: usize, row: Vec<u16>, added: Option<Vec<u16>>) -> Vec<u16> {
        let other = match added {
            Some(other) => {
                // `row` is the total already.
                self.decide(y, &row, None);
                other
            }
            None => {
                let mut slot = lock(&self.shared.slots[y]);
                match slot.sums.take() {
                    // The other sweep finished the row while this one computed it.
                    Some(other) => {
                        drop(slot);
                        self.decide(y, &row, Some(&other));
                        other
                    }
                    None => {
                        slot.sums = Some(row);
                        drop(slot);
                        return self.shared.buffer();
                    }
                }
            }
        };
        // Both buffers are free now: one serves this sweep's next row.
        lock(&self.shared.pool).push(other);
        row
    }
}

/// The AVX2 kernels: SGM sweep and row decision.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
mod simd;

/// P2 by intensity step `|ΔI|` (index 0..=255): lowered across edges, always above P1.
fn p2_table(p: &QualityParams) -> Vec<i16> {
    let p1 = p.p1 as i16;
    (0..256u32)
        .map(|g| ((p.p2 as u32 * 16 / (16 + g)) as i16).max(p1 + 1))
        .collect()
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
                select_row(total, p, buf, lrow, rrow);
            },
        );
    let plane = |data| Plane {
        width: w,
        height: h,
        data,
    };
    (plane(left), plane(right))
}

/// Decides one row from its summed path costs `total` (`w · nd`, `w` the length of the
/// output rows): the left-based map from each pixel's disparities, the right-based one
/// along the diagonals. `buf` is scratch.
fn select_row(
    total: &[u16],
    p: &QualityParams,
    buf: &mut Vec<u16>,
    lrow: &mut [f32],
    rrow: &mut [f32],
) {
    let (w, nd) = (lrow.len(), p.range.count());
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
        lrow[x] = decide(&t[lo..hi], lo, p.uniqueness_ratio, dmin);
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
        rrow[xr] = decide(&buf[lo..hi], lo, p.uniqueness_ratio, dmin);
    }
}

/// Whether the SIMD path (sweeps and decision) applies: with the penalties it accepts, its
/// guard values stay apart from real costs and eight summed paths stay below `i16::MAX`.
fn simd_applies(p: &QualityParams) -> bool {
    cfg!(all(target_arch = "x86_64", target_feature = "avx2"))
        && p.p1 <= MAX_SIMD_PENALTY
        && p.p2 <= MAX_SIMD_PENALTY
}

/// Largest P1/P2 the SIMD path accepts (see [`simd_applies`]).
const MAX_SIMD_PENALTY: u16 = 3800;

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
        if i.abs_diff(bi) > 1 && (v as u32) * 100u32.saturating_sub(u) < (best as u32) * 100 {
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
                // The AVX-512 kernel covers 64 and 128 disparities where the CPU has it.
                let wide = (nd == 64 || nd == 128) && crate::sv::has_avx512bw();
                for (backward, wide) in [(false, false), (true, false), (false, wide), (true, wide)]
                {
                    assert_eq!(
                        simd::aggregate(&cost, &img, &p, backward, wide),
                        aggregate(&cost, &img, &p, backward),
                        "nd {nd} paths {paths} backward {backward} avx-512 {wide}"
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
            let (mut l2, mut r2) = (vec![INVALID_DISPARITY; w], vec![INVALID_DISPARITY; w]);
            let mut buf = Vec::new();
            select_row(&total, &p, &mut buf, &mut l2, &mut r2);
            assert!(l2.iter().any(|d| d.is_finite()) && r2.iter().any(|d| d.is_finite()));
            // The AVX2 decision, and the AVX-512 one where the CPU has it; the sums
            // whole, or as two parts added on the way (the meeting sweeps' case).
            let half: Vec<u16> = total.iter().map(|t| t / 2).collect();
            let rest: Vec<u16> = total.iter().zip(&half).map(|(t, h)| t - h).collect();
            for wide in [false, true] {
                if wide && !crate::sv::has_avx512bw() {
                    continue;
                }
                for (sums, other) in [(&total[..], None), (&half[..], Some(&rest[..]))] {
                    let (mut l1, mut r1) = (vec![INVALID_DISPARITY; w], vec![INVALID_DISPARITY; w]);
                    simd::select_row_with(sums, other, nd, &p, &mut buf, &mut l1, &mut r1, wide);
                    let same = |a: &[f32], b: &[f32]| {
                        a.iter()
                            .zip(b)
                            .all(|(x, y)| x == y || (x.is_infinite() && y.is_infinite()))
                    };
                    let case = format!("w {w} nd {nd} dmin {dmin} avx-512 {wide}");
                    assert!(same(&l1, &l2), "left {case}");
                    assert!(same(&r1, &r2), "right {case}");
                }
            }
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
        // The AVX2 blocks, and the AVX-512 ones where the CPU has them.
        #[cfg(target_arch = "x86_64")]
        let wide = crate::sv::has_avx512bw();
        #[cfg(not(target_arch = "x86_64"))]
        let wide = false;
        let c = census_with(&img, false);
        assert_eq!(census_with(&img, wide).data, c.data);
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
        for (dmin, nd, paths) in [
            (0, 16, 4),
            (-4, 21, 8),
            (0, 64, 4),
            (0, 64, 8),
            (-9, 128, 8),
        ] {
            let p = QualityParams {
                range: DisparityRange::new(dmin, dmin + nd as i32 - 1),
                paths,
                ..Default::default()
            };
            let fast = match_quality(&left, &right, &p);
            let mut cost = Vec::new();
            cost_volume(&left, &right, &p, &mut cost);
            let s1 = aggregate(&cost, &left, &p, false);
            let s2 = aggregate(&cost, &left, &p, true);
            let mut buf = Vec::new();
            for y in 0..h {
                let o = y * w * nd;
                let total: Vec<u16> = (0..w * nd)
                    .map(|i| s1[o + i].wrapping_add(s2[o + i]))
                    .collect();
                let (mut l, mut r) = (vec![INVALID_DISPARITY; w], vec![INVALID_DISPARITY; w]);
                select_row(&total, &p, &mut buf, &mut l, &mut r);
                let same = |a: &[f32], b: &[f32]| {
                    a.iter()
                        .zip(b)
                        .all(|(x, y)| x == y || (x.is_infinite() && y.is_infinite()))
                };
                assert!(
                    same(fast.left.row(y), &l),
                    "left row {y}, range {dmin}+{nd}, {paths} paths"
                );
                assert!(
                    same(fast.right.row(y), &r),
                    "right row {y}, range {dmin}+{nd}, {paths} paths"
                );
            }
            assert!(fast.left.data.iter().filter(|d| d.is_finite()).count() > w * h / 4);
        }
    }

    #[test]
    fn a_reused_workspace_gives_the_fresh_result() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (w, h) = (57, 33);
        let mut pair = || {
            let l: Vec<u8> = (0..w * h).map(|_| rng.random::<u8>()).collect();
            let r: Vec<u8> = (0..w * h).map(|i| l[(i + 2).min(w * h - 1)]).collect();
            (
                Plane::from_vec(w, h, l).unwrap(),
                Plane::from_vec(w, h, r).unwrap(),
            )
        };
        let (a, b) = (pair(), pair());
        let p = QualityParams {
            range: DisparityRange::new(-2, 17),
            ..Default::default()
        };
        let mut ws = QualityWorkspace::default();
        match_quality_in(&mut ws, &a.0, &a.1, &p);
        // Same size: the second frame runs in the first frame's buffers.
        let reused = match_quality_in(&mut ws, &b.0, &b.1, &p);
        let fresh = match_quality(&b.0, &b.1, &p);
        let bits = |m: &DisparityMap| m.data.iter().map(|d| d.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&reused.left), bits(&fresh.left));
        assert_eq!(bits(&reused.right), bits(&fresh.right));
        assert!(fresh.left.data.iter().filter(|d| d.is_finite()).count() > w * h / 2);
    }
}
