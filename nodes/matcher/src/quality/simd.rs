//! The SIMD kernels of the quality matcher: the SGM sweep, 16 disparities per
//! instruction, and the row decision, 16 pixels per instruction (AVX2, every build);
//! 32 of each with AVX-512BW, chosen at run time (for the sweep only at 64 and 128
//! disparities, the counts whose whole vectors it unrolls).
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
    ///
    /// # Safety
    /// The CPU must support AVX2, `c` must hold this kernel's `nd` costs and `k` must be
    /// below `nvec`.
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
    /// minimum, P2)` into `outs`; `acc` receives their sum, plus `base` when given.
    /// The cost vector is loaded once and the sum stays in a register. Returns each
    /// path's new minimum.
    #[inline(always)]
    fn paths<const N: usize>(
        &self,
        c: &[u8],
        from: [(&[i16], i16, i16); N],
        p1: i16,
        outs: [&mut [i16]; N],
        acc: &mut [u16],
        base: Option<&[u16]>,
    ) -> [i16; N] {
        let n = self.nvec * 16;
        assert!(acc.len() >= n && c.len() >= self.nd);
        assert!(base.is_none_or(|b| b.len() >= n));
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
                let mut sum = match base {
                    Some(b) => _mm256_loadu_si256(b.as_ptr().add(k * 16) as *const __m256i),
                    None => _mm256_setzero_si256(),
                };
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
        base: Option<&[u16]>,
    ) -> [i16; N] {
        if self.nd != 64 && self.nd != 128 {
            return self.paths(c, from, p1, outs, acc, base);
        }
        let s = RawStep::new(self.nd, c, from, p1, outs, acc, base);
        // SAFETY: `RawStep::new` checked the lengths; AVX2 is enabled for this build.
        unsafe {
            if self.nd == 64 {
                step_paths::<4, N>(s)
            } else {
                step_paths::<8, N>(s)
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

/// Pixels ahead of the sweep whose costs and sums are prefetched.
const PREFETCH_AHEAD: usize = 6;

/// Asks for the `bytes` bytes at `p` in the first-level cache.
#[inline(always)]
fn prefetch<T>(p: *const T, bytes: usize) {
    let p = p as *const i8;
    for line in (0..bytes).step_by(64) {
        // SAFETY: a prefetch never faults, whatever the address.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(p.wrapping_add(line)) };
    }
}

/// P2 between two neighbouring intensities (lowered across edges).
#[inline(always)]
fn p2_between(lut: &[i16], a: u8, b: u8) -> i16 {
    lut[a.abs_diff(b) as usize]
}

/// The step of `NP` paths of one pixel, as raw pointers whose lengths [`RawStep::new`]
/// checked: costs `c`, sum `acc` and addend `base` (null: none) hold `n` values, every
/// predecessor `lp` and output `out` `n + 2` (guards included).
struct RawStep<const NP: usize> {
    c: *const u8,
    lp: [*const i16; NP],
    mins: [i16; NP],
    p2s: [i16; NP],
    p1: i16,
    out: [*mut i16; NP],
    acc: *mut u16,
    base: *const u16,
}

impl<const NP: usize> RawStep<NP> {
    /// Checks the slices of one pixel's step for `n` disparities (see
    /// [`Kernel::paths`]) and takes their pointers.
    #[inline(always)]
    fn new(
        n: usize,
        c: &[u8],
        from: [(&[i16], i16, i16); NP],
        p1: i16,
        outs: [&mut [i16]; NP],
        acc: &mut [u16],
        base: Option<&[u16]>,
    ) -> Self {
        assert!(c.len() >= n && acc.len() >= n && base.is_none_or(|b| b.len() >= n));
        assert!(from.iter().all(|f| f.0.len() >= n + 2) && outs.iter().all(|o| o.len() >= n + 2));
        Self {
            c: c.as_ptr(),
            lp: from.map(|f| f.0.as_ptr()),
            mins: from.map(|f| f.1),
            p2s: from.map(|f| f.2),
            p1,
            out: outs.map(|o| o.as_mut_ptr()),
            acc: acc.as_mut_ptr(),
            base: base.map_or(std::ptr::null(), |b| b.as_ptr()),
        }
    }
}

/// The step of `NP` paths of one pixel for exactly `16 · NV` disparities: both counts
/// are constants, so the loops unroll and the per-path constants and minima stay in
/// registers.
///
/// # Safety
/// `s` was made by [`RawStep::new`] for `16 · NV` disparities.
#[inline(always)]
unsafe fn step_paths<const NV: usize, const NP: usize>(s: RawStep<NP>) -> [i16; NP] {
    let RawStep {
        c,
        lp,
        mins,
        p2s,
        p1,
        out,
        acc,
        base,
    } = s;
    // SAFETY: the caller's promise; AVX2 is enabled for this build.
    unsafe {
        let p1v = _mm256_set1_epi16(p1);
        let jump: [__m256i; NP] = std::array::from_fn(|j| _mm256_set1_epi16(mins[j] + p2s[j]));
        let minv: [__m256i; NP] = std::array::from_fn(|j| _mm256_set1_epi16(mins[j]));
        let mut mn = [_mm256_set1_epi16(BIG); NP];
        for k in 0..NV {
            let cv = _mm256_cvtepu8_epi16(_mm_loadu_si128(c.add(k * 16) as *const __m128i));
            let mut sum = if base.is_null() {
                _mm256_setzero_si256()
            } else {
                _mm256_loadu_si256(base.add(k * 16) as *const __m256i)
            };
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

/// How [`sweep_with`] steps the paths of one pixel.
trait PathStep {
    /// The path from the left restarts (the first pixel of a row is next).
    fn row_start(&mut self) {}

    /// [`Kernel::step`]'s contract; path 0 is the path from the left.
    #[allow(clippy::too_many_arguments)]
    fn step<const N: usize>(
        &mut self,
        kern: &Kernel,
        c: &[u8],
        from: [(&[i16], i16, i16); N],
        p1: i16,
        outs: [&mut [i16]; N],
        acc: &mut [u16],
        base: Option<&[u16]>,
    ) -> [i16; N];
}

/// 16 disparities per instruction, any disparity count.
struct Avx2;

impl PathStep for Avx2 {
    #[inline(always)]
    fn step<const N: usize>(
        &mut self,
        kern: &Kernel,
        c: &[u8],
        from: [(&[i16], i16, i16); N],
        p1: i16,
        outs: [&mut [i16]; N],
        acc: &mut [u16],
        base: Option<&[u16]>,
    ) -> [i16; N] {
        kern.step(c, from, p1, outs, acc, base)
    }
}

/// 32 disparities per instruction, for 64 or 128 disparities; only reached through
/// [`sweep_avx512`], whose caller has checked the CPU.
///
/// The path from the left stays in registers from one pixel to the next, its minimum
/// as a broadcast vector: read back from memory, its `d ± 1` neighbours were unaligned
/// loads of a store still in flight, which the CPU cannot forward, and that stall sat
/// on the chain from one pixel to the next.
struct Avx512 {
    /// L of the previous pixel's path from the left, 32 disparities per register.
    left: [__m512i; 4],
    /// Its minimum in every lane.
    left_min: __m512i,
}

impl Avx512 {
    /// A path state of zeros (what a path starts from).
    fn new() -> Self {
        // SAFETY: all-zero bits are a valid __m512i.
        let zero: __m512i = unsafe { std::mem::zeroed() };
        Self {
            left: [zero; 4],
            left_min: zero,
        }
    }
}

impl PathStep for Avx512 {
    #[inline(always)]
    fn row_start(&mut self) {
        *self = Self::new();
    }

    #[inline(always)]
    fn step<const N: usize>(
        &mut self,
        kern: &Kernel,
        c: &[u8],
        from: [(&[i16], i16, i16); N],
        p1: i16,
        outs: [&mut [i16]; N],
        acc: &mut [u16],
        base: Option<&[u16]>,
    ) -> [i16; N] {
        let n = kern.nd;
        let s = RawStep::new(n, c, from, p1, outs, acc, base);
        // SAFETY: `RawStep::new` checked the lengths; the CPU has AVX-512BW (this impl
        // is only used by `sweep_avx512`).
        unsafe {
            match n {
                64 => step_paths512::<2, N>(s, self),
                128 => step_paths512::<4, N>(s, self),
                _ => panic!("the AVX-512 sweep takes 64 or 128 disparities, not {n}"),
            }
        }
    }
}

/// [`step_paths`] with 32 disparities per instruction (`32 · NV` disparities).
///
/// Path 0, the path from the left, reads its predecessor from `st` instead of `s.lp[0]`
/// (which is not read) and leaves its result there instead of in `s.out[0]` (which is
/// not written); its minimum comes from `st` too.
///
/// # Safety
/// `s` was made by [`RawStep::new`] for `32 · NV` disparities; the CPU must support
/// AVX-512F and AVX-512BW.
#[inline(always)]
unsafe fn step_paths512<const NV: usize, const NP: usize>(
    s: RawStep<NP>,
    st: &mut Avx512,
) -> [i16; NP] {
    let RawStep {
        c,
        lp,
        mins,
        p2s,
        p1,
        out,
        acc,
        base,
    } = s;
    // SAFETY: the caller's promise.
    unsafe {
        let p1v = _mm512_set1_epi16(p1);
        let big = _mm512_set1_epi16(BIG);
        let mut minv: [__m512i; NP] = std::array::from_fn(|j| _mm512_set1_epi16(mins[j]));
        minv[0] = st.left_min;
        let jump: [__m512i; NP] =
            std::array::from_fn(|j| _mm512_add_epi16(minv[j], _mm512_set1_epi16(p2s[j])));
        // Lanes of L(d − 1) and L(d + 1) from two neighbouring registers.
        let down: [i16; 32] = std::array::from_fn(|i| if i == 0 { 31 } else { 31 + i as i16 });
        let up: [i16; 32] = std::array::from_fn(|i| i as i16 + 1);
        let down = _mm512_loadu_si512(down.as_ptr() as *const _);
        let up = _mm512_loadu_si512(up.as_ptr() as *const _);
        let prev = st.left;
        let mut mn = [big; NP];
        for k in 0..NV {
            let cv = _mm512_cvtepu8_epi16(_mm256_loadu_si256(c.add(k * 32) as *const __m256i));
            let mut sum = if base.is_null() {
                _mm512_setzero_si512()
            } else {
                _mm512_loadu_si512(base.add(k * 32) as *const _)
            };
            for j in 0..NP {
                let (a, m, b) = if j == 0 {
                    let m = prev[k];
                    let below = if k > 0 { prev[k - 1] } else { big };
                    let above = if k + 1 < NV { prev[k + 1] } else { big };
                    (
                        _mm512_permutex2var_epi16(below, down, m),
                        m,
                        _mm512_permutex2var_epi16(m, up, above),
                    )
                } else {
                    let base = lp[j].add(k * 32);
                    (
                        _mm512_loadu_si512(base as *const _),
                        _mm512_loadu_si512(base.add(1) as *const _),
                        _mm512_loadu_si512(base.add(2) as *const _),
                    )
                };
                let nb = _mm512_add_epi16(_mm512_min_epi16(a, b), p1v);
                let v = _mm512_min_epi16(_mm512_min_epi16(m, nb), jump[j]);
                let v = _mm512_add_epi16(cv, _mm512_sub_epi16(v, minv[j]));
                if j == 0 {
                    st.left[k] = v;
                } else {
                    _mm512_storeu_si512(out[j].add(1 + k * 32) as *mut _, v);
                }
                mn[j] = _mm512_min_epi16(mn[j], v);
                sum = _mm512_add_epi16(sum, v);
            }
            _mm512_storeu_si512(acc.add(k * 32) as *mut _, sum);
        }
        // The left minimum stays a vector: swap halves, quarters, … and keep the min.
        let mut m = mn[0];
        m = _mm512_min_epi16(m, _mm512_shuffle_i64x2(m, m, 0b01_00_11_10));
        m = _mm512_min_epi16(m, _mm512_shuffle_i64x2(m, m, 0b10_11_00_01));
        m = _mm512_min_epi16(m, _mm512_shuffle_epi32(m, 0b01_00_11_10));
        m = _mm512_min_epi16(m, _mm512_shuffle_epi32(m, 0b10_11_00_01));
        m = _mm512_min_epi16(m, _mm512_rol_epi32(m, 16));
        st.left_min = m;
        std::array::from_fn(|j| {
            if j == 0 {
                return _mm_extract_epi16(_mm512_castsi512_si128(m), 0) as i16;
            }
            let m = _mm256_min_epi16(
                _mm512_castsi512_si256(mn[j]),
                _mm512_extracti64x4_epi64(mn[j], 1),
            );
            Kernel::hmin(m)
        })
    }
}

/// Marks a disparity that does not exist; above every summed cost the limits allow
/// (8 paths · (cost 159 + penalty 3800) < 32767).
const NONE: i16 = i16::MAX;

/// Whether a row of this size fits the i16 lane arithmetic of [`select_row`].
pub fn rows_fit(w: usize, nd: usize, dmin: i32) -> bool {
    w + nd + 2 * dmin.unsigned_abs() as usize + 64 < 30_000
}

/// Transposes the 16×16 block of `src` (rows `x`, stride `sstride`, 16 values each),
/// plus the same block of `add` when given, into `dst` (row `d` = column `d` of the
/// block, stride `dstride`).
///
/// # Safety
/// The CPU must support AVX2; `src` (and `add`) must be readable for 16 rows of 16 values
/// at stride `sstride`, `dst` writable for 16 rows of 16 at stride `dstride`.
#[inline(always)]
unsafe fn transpose16(
    src: *const u16,
    add: Option<*const u16>,
    sstride: usize,
    dst: *mut i16,
    dstride: usize,
) {
    // SAFETY: the caller guarantees 16 rows of 16 values on every side.
    unsafe {
        let a: [__m256i; 16] = std::array::from_fn(|i| {
            let v = _mm256_loadu_si256(src.add(i * sstride) as *const __m256i);
            match add {
                Some(o) => {
                    _mm256_add_epi16(v, _mm256_loadu_si256(o.add(i * sstride) as *const __m256i))
                }
                None => v,
            }
        });
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
///
/// # Safety
/// The CPU must support AVX2, and `load` must be sound for every index below `nd`.
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

/// [`super::select_row`] on `total` (plus `other` when given, the sums of the other
/// sweep) with the row transposed to disparity-major order, so that both maps are
/// decided many pixels at a time (lanes = pixels): 32 with AVX-512, else 16. Pixel
/// `x`'s sums start at `total[x · tstride]`; `mt` is scratch.
pub fn select_row(
    total: &[u16],
    other: Option<&[u16]>,
    tstride: usize,
    p: &QualityParams,
    mt: &mut Vec<u16>,
    lrow: &mut [f32],
    rrow: &mut [f32],
) {
    let wide = crate::sv::has_avx512bw();
    select_row_with(total, other, tstride, p, mt, lrow, rrow, wide)
}

/// [`select_row`] with the AVX-512 decision when `wide` (which the CPU must support).
#[allow(clippy::too_many_arguments)]
pub fn select_row_with(
    total: &[u16],
    other: Option<&[u16]>,
    tstride: usize,
    p: &QualityParams,
    mt: &mut Vec<u16>,
    lrow: &mut [f32],
    rrow: &mut [f32],
    wide: bool,
) {
    assert!(
        !wide || crate::sv::has_avx512bw(),
        "AVX-512 decision on a CPU without it"
    );
    let (w, nd) = (lrow.len(), p.range.count());
    let t = Transposed::fill(total, other, tstride, w, nd, p.range.min, mt);
    if wide {
        // SAFETY: the CPU has AVX-512BW (checked just above).
        unsafe { decide_row512(&t, p, lrow, rrow) }
    } else {
        decide_row(&t, p, lrow, rrow)
    }
}

/// A row of summed costs in disparity-major order: `mt[di · stride + pad + x]`, padded
/// with [`NONE`] on both sides so that every load of [`Transposed::load`] lies inside.
struct Transposed<'a> {
    mt: &'a [u16],
    stride: usize,
    pad: usize,
    w: usize,
    nd: usize,
    dmin: i32,
}

impl<'a> Transposed<'a> {
    /// Widest block of lanes read at once.
    const BLOCK: usize = 32;

    /// Transposes `total` (+ `other`) into `mt`.
    fn fill(
        total: &[u16],
        other: Option<&[u16]>,
        tstride: usize,
        w: usize,
        nd: usize,
        dmin: i32,
        mt: &'a mut Vec<u16>,
    ) -> Self {
        let wb = w.div_ceil(Self::BLOCK) * Self::BLOCK;
        let pad = dmin.unsigned_abs() as usize + Self::BLOCK;
        let stride = pad + wb + pad + nd + Self::BLOCK;
        if mt.len() != nd * stride {
            mt.clear();
            mt.resize(nd * stride, NONE as u16);
        }
        let base = mt.as_mut_ptr() as *mut i16;
        assert!(tstride >= nd && total.len() >= (w - 1) * tstride + nd);
        assert!(other.is_none_or(|o| o.len() >= (w - 1) * tstride + nd));
        // Transpose: mt[di][pad + x] = total[x][di]; outside 0..w stays NONE.
        let (wf, df) = (w / 16 * 16, nd / 16 * 16);
        for x0 in (0..wf).step_by(16) {
            for d0 in (0..df).step_by(16) {
                let o = x0 * tstride + d0;
                // SAFETY: rows x0..x0 + 16 < w and values d0..d0 + 16 <= nd of `total`
                // (and `other`); mt rows d0..d0 + 16 hold pad + x0 + 16 <= stride values.
                unsafe {
                    transpose16(
                        total.as_ptr().add(o),
                        other.map(|a| a.as_ptr().add(o)),
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
                let i = x * tstride + di;
                let add = other.map_or(0, |a| a[i]);
                mt[di * stride + pad + x] = total[i].wrapping_add(add);
            }
        }
        Self {
            mt,
            stride,
            pad,
            w,
            nd,
            dmin,
        }
    }

    /// Address of the value of disparity index `di` at column `col` (−pad..).
    #[inline(always)]
    fn at(&self, di: usize, col: isize) -> *const i16 {
        let o = (di * self.stride) as isize + self.pad as isize + col;
        debug_assert!(o >= 0 && o as usize + Self::BLOCK <= self.mt.len());
        // SAFETY: in bounds for every di < nd and −pad <= col <= w + |dmin| + nd, by the
        // padding (the callers' reads stay in that range).
        unsafe { self.mt.as_ptr().offset(o) as *const i16 }
    }

    /// Whether the left-based block of lanes x0..x0 + n has every disparity's right
    /// pixel inside the image (no per-lane bounds needed).
    fn interior(&self, x0: usize, n: usize) -> bool {
        x0 as i64 - self.dmin as i64 - self.nd as i64 + 1 >= 0
            && (x0 + n - 1) as i64 - (self.dmin as i64) < self.w as i64
    }
}

/// The AVX2 decision of [`select_row`], 16 pixels per instruction.
fn decide_row(t: &Transposed, p: &QualityParams, lrow: &mut [f32], rrow: &mut [f32]) {
    let (w, nd, dmin) = (t.w, t.nd, t.dmin);
    let u = p.uniqueness_ratio;
    let lanes: [i16; 16] = std::array::from_fn(|i| i as i16);
    // SAFETY: AVX2 is enabled for this build; loads go through `Transposed::at`.
    unsafe {
        let idx = _mm256_loadu_si256(lanes.as_ptr() as *const __m256i);
        let none = _mm256_set1_epi16(NONE);
        let row = |di: usize, col: isize| -> __m256i {
            _mm256_loadu_si256(t.at(di, col) as *const __m256i)
        };
        for x0 in (0..w).step_by(16) {
            // Left-based: lanes x = x0 + i; disparity index di exists when the right
            // pixel x − dmin − di lies in the image.
            let xv = _mm256_add_epi16(idx, _mm256_set1_epi16(x0 as i16));
            let hi = _mm256_sub_epi16(xv, _mm256_set1_epi16(dmin as i16));
            let lo = _mm256_sub_epi16(hi, _mm256_set1_epi16(w as i16 - 1));
            let f = if t.interior(x0, 16) {
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

/// The AVX-512 decision of [`select_row`]: 32 pixels per instruction, the sub-pixel
/// finish in vectors too.
///
/// # Safety
/// The CPU must support AVX-512F and AVX-512BW.
#[target_feature(enable = "avx512f,avx512bw")]
unsafe fn decide_row512(t: &Transposed, p: &QualityParams, lrow: &mut [f32], rrow: &mut [f32]) {
    let (w, nd, dmin) = (t.w, t.nd, t.dmin);
    let lanes: [i16; 32] = std::array::from_fn(|i| i as i16);
    // SAFETY: `lanes` holds the 64 bytes loaded; the caller guarantees AVX-512F.
    let idx = unsafe { _mm512_loadu_si512(lanes.as_ptr() as *const _) };
    let none = _mm512_set1_epi16(NONE);
    let row = |di: usize, col: isize| -> __m512i {
        // SAFETY: loads go through `Transposed::at`.
        unsafe { _mm512_loadu_si512(t.at(di, col) as *const _) }
    };
    for x0 in (0..w).step_by(32) {
        let n = 32.min(w - x0);
        let keep = if n == 32 { !0u32 } else { (1u32 << n) - 1 };
        let f = if t.interior(x0, 32) {
            decide32(nd, |di| row(di, x0 as isize))
        } else {
            // Disparity index di exists for pixel x when lo <= di <= hi.
            let hi = _mm512_sub_epi16(
                _mm512_add_epi16(idx, _mm512_set1_epi16(x0 as i16)),
                _mm512_set1_epi16(dmin as i16),
            );
            let lo = _mm512_sub_epi16(hi, _mm512_set1_epi16(w as i16 - 1));
            decide32(nd, |di| {
                let dv = _mm512_set1_epi16(di as i16);
                let ok = _mm512_mask_cmpge_epi16_mask(_mm512_cmple_epi16_mask(dv, hi), dv, lo);
                _mm512_mask_mov_epi16(none, ok, row(di, x0 as isize))
            })
        };
        // SAFETY: lrow has n values from x0 (n = its rest, at most 32).
        unsafe { finish32(f, keep, p.uniqueness_ratio, dmin, lrow.as_mut_ptr().add(x0)) };
        let f = decide32(nd, |di| row(di, x0 as isize + dmin as isize + di as isize));
        // SAFETY: as above.
        unsafe { finish32(f, keep, p.uniqueness_ratio, dmin, rrow.as_mut_ptr().add(x0)) };
    }
}

/// [`decide16`] for 32 pixels; returns best, its index, rival, a and c.
#[inline(always)]
fn decide32(nd: usize, load: impl Fn(usize) -> __m512i) -> [__m512i; 5] {
    // SAFETY: only inlined into AVX-512 functions (`decide_row512`).
    unsafe {
        let none = _mm512_set1_epi16(NONE);
        let one = _mm512_set1_epi16(1);
        let mut best = none;
        let mut bi = _mm512_setzero_si512();
        let mut dv = _mm512_setzero_si512();
        for di in 0..nd {
            let v = load(di);
            let lt = _mm512_cmplt_epi16_mask(v, best);
            best = _mm512_min_epi16(best, v);
            bi = _mm512_mask_mov_epi16(bi, lt, dv);
            dv = _mm512_add_epi16(dv, one);
        }
        let (mut rival, mut a, mut c) = (none, none, none);
        let mut diff = _mm512_sub_epi16(_mm512_setzero_si512(), bi);
        let minus1 = _mm512_set1_epi16(-1);
        for di in 0..nd {
            let v = load(di);
            // diff = di − bi: beyond ±1 it is a rival, at ∓1 the parabola's sides.
            let far = _mm512_cmpgt_epi16_mask(_mm512_abs_epi16(diff), one);
            rival = _mm512_mask_min_epi16(rival, far, rival, v);
            a = _mm512_mask_mov_epi16(a, _mm512_cmpeq_epi16_mask(diff, minus1), v);
            c = _mm512_mask_mov_epi16(c, _mm512_cmpeq_epi16_mask(diff, one), v);
            diff = _mm512_add_epi16(diff, one);
        }
        [best, bi, rival, a, c]
    }
}

/// [`finish`] for 32 lanes, in vectors: stores each decided lane of `keep` at `out`
/// (lanes without any disparity are left as they are).
///
/// # Safety
/// `out` holds the lanes of `keep`; only inlined into AVX-512 functions.
#[inline(always)]
unsafe fn finish32(f: [__m512i; 5], keep: u32, uniqueness: u16, dmin: i32, out: *mut f32) {
    // SAFETY: the caller's promise.
    unsafe {
        let none = _mm512_set1_epi16(NONE);
        let [best, bi, rival, a, c] = f;
        let has = _mm512_mask_cmpneq_epi16_mask(keep, best, none);
        let sides = _mm512_mask_cmpneq_epi16_mask(_mm512_cmpneq_epi16_mask(a, none), c, none);
        let ratio = _mm512_set1_epi32(100u32.saturating_sub(uniqueness as u32) as i32);
        let hundred = _mm512_set1_epi32(100);
        let invalid = _mm512_set1_ps(schemas::INVALID_DISPARITY);
        for half in 0..2 {
            let wide = |v: __m512i| -> __m512i {
                let h = if half == 0 {
                    _mm512_castsi512_si256(v)
                } else {
                    _mm512_extracti64x4_epi64(v, 1)
                };
                _mm512_cvtepi16_epi32(h)
            };
            let m = |k: u32| -> __mmask16 { (k >> (16 * half)) as u16 };
            let (b32, r32) = (wide(best), wide(rival));
            let rival_ok = _mm512_cmpneq_epi32_mask(r32, _mm512_set1_epi32(NONE as i32));
            let beaten = _mm512_mask_cmplt_epi32_mask(
                rival_ok,
                _mm512_mullo_epi32(r32, ratio),
                _mm512_mullo_epi32(b32, hundred),
            );
            let mut d = _mm512_add_ps(_mm512_cvtepi32_ps(wide(bi)), _mm512_set1_ps(dmin as f32));
            let (af, bf, cf) = (
                _mm512_cvtepi32_ps(wide(a)),
                _mm512_cvtepi32_ps(b32),
                _mm512_cvtepi32_ps(wide(c)),
            );
            let den = _mm512_sub_ps(
                _mm512_add_ps(af, cf),
                _mm512_mul_ps(_mm512_set1_ps(2.0), bf),
            );
            let curved = _mm512_mask_cmp_ps_mask(m(sides), den, _mm512_setzero_ps(), _CMP_GT_OQ);
            let off = _mm512_div_ps(
                _mm512_sub_ps(af, cf),
                _mm512_mul_ps(_mm512_set1_ps(2.0), den),
            );
            d = _mm512_mask_add_ps(d, curved, d, off);
            d = _mm512_mask_mov_ps(d, beaten, invalid);
            _mm512_mask_storeu_ps(out.add(16 * half), m(has), d);
        }
    }
}

/// See [`super::aggregate`]; identical output. `wide` as in [`sweep_on`].
#[cfg(test)]
pub fn aggregate(
    cost: &[u8],
    img: &Plane<u8>,
    p: &QualityParams,
    backward: bool,
    wide: bool,
) -> Vec<u16> {
    let (w, h, nd) = (img.width, img.height, p.range.count());
    let mut sum = vec![0u16; w * h * nd];
    /// Copies every row into the volume.
    struct Collect<'a> {
        sum: &'a mut [u16],
        w: usize,
        nd: usize,
    }
    impl Rows for Collect<'_> {
        fn start(&mut self, _: usize) -> Option<Vec<u16>> {
            None
        }
        fn done(&mut self, y: usize, row: Vec<u16>, _: Option<Vec<u16>>) -> Vec<u16> {
            let (w, nd) = (self.w, self.nd);
            let ndp = row.len() / w;
            for x in 0..w {
                let o = (y * w + x) * nd;
                self.sum[o..o + nd].copy_from_slice(&row[x * ndp..x * ndp + nd]);
            }
            row
        }
    }
    let rows = Collect {
        sum: &mut sum,
        w,
        nd,
    };
    sweep_on(wide, cost, img, p, backward, Vec::new(), rows);
    sum
}

/// One SGM sweep over 4 paths (see [`super::aggregate`]). The path sums of each image
/// row (in image order, `nd.div_ceil(16) · 16` per pixel) are written into a buffer of
/// that size, `row` for the first row; sums that `rows.start(y)` hands over (the other
/// sweep's) are added on the way. Returns the buffer left after the last row.
pub fn sweep(
    cost: &[u8],
    img: &Plane<u8>,
    p: &QualityParams,
    backward: bool,
    row: Vec<u16>,
    rows: impl Rows,
) -> Vec<u16> {
    let nd = p.range.count();
    let wide = (nd == 64 || nd == 128) && crate::sv::has_avx512bw();
    sweep_on(wide, cost, img, p, backward, row, rows)
}

/// [`sweep`] with the AVX-512 kernel when `wide` (for 64 or 128 disparities, on a CPU
/// that has it), else the AVX2 one.
pub fn sweep_on(
    wide: bool,
    cost: &[u8],
    img: &Plane<u8>,
    p: &QualityParams,
    backward: bool,
    row: Vec<u16>,
    rows: impl Rows,
) -> Vec<u16> {
    if wide {
        let nd = p.range.count();
        assert!(
            (nd == 64 || nd == 128) && crate::sv::has_avx512bw(),
            "no AVX-512 sweep here"
        );
        // SAFETY: the CPU has AVX-512BW (asserted just above).
        unsafe { sweep_avx512(cost, img, p, backward, row, rows) }
    } else {
        sweep_with(Avx2, cost, img, p, backward, row, rows)
    }
}

/// Where a [`sweep`]'s rows come from and go to.
pub trait Rows {
    /// Sums to add into image row `y` while it is computed, if there are any yet.
    fn start(&mut self, y: usize) -> Option<Vec<u16>>;
    /// Image row `y` is done: `row` holds its path sums plus those of `added`, the
    /// buffer [`Rows::start`] gave. Returns the buffer for the next row.
    fn done(&mut self, y: usize, row: Vec<u16>, added: Option<Vec<u16>>) -> Vec<u16>;
}

/// [`sweep_with`] compiled for AVX-512, so that [`Avx512`]'s kernel inlines into it.
///
/// # Safety
/// The CPU must support AVX-512F and AVX-512BW.
#[target_feature(enable = "avx512f,avx512bw")]
unsafe fn sweep_avx512(
    cost: &[u8],
    img: &Plane<u8>,
    p: &QualityParams,
    backward: bool,
    row: Vec<u16>,
    rows: impl Rows,
) -> Vec<u16> {
    sweep_with(Avx512::new(), cost, img, p, backward, row, rows)
}

/// The sweep of [`sweep`] with the path step `s`.
#[inline(always)]
fn sweep_with(
    mut s: impl PathStep,
    cost: &[u8],
    img: &Plane<u8>,
    p: &QualityParams,
    backward: bool,
    mut row_sum: Vec<u16>,
    mut rows: impl Rows,
) -> Vec<u16> {
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
    // Every value of the row buffers is written by the steps below.
    row_sum.resize(w * ndp, 0);
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
        let added = rows.start(oy(y));
        s.row_start();
        assert!(added.as_ref().is_none_or(|a| a.len() == w * ndp));
        for x in 0..w {
            let xi = ox(x);
            let pix = (oy(y) * w + xi) * nd;
            let c = &cost[pix..pix + nd];
            let here = irow[xi];
            let acc = &mut row_sum[xi * ndp..(xi + 1) * ndp];
            let base = added.as_ref().map(|a| &a[xi * ndp..(xi + 1) * ndp]);
            // The costs and the other sweep's sums of a pixel a few steps ahead: both
            // come from memory the hardware prefetcher does not bring in early enough.
            // Addresses past the row are harmless to prefetch (never dereferenced).
            let ahead = if backward {
                xi.wrapping_sub(PREFETCH_AHEAD)
            } else {
                xi + PREFETCH_AHEAD
            };
            prefetch(
                cost.as_ptr()
                    .wrapping_add((oy(y) * w).wrapping_add(ahead).wrapping_mul(nd)),
                nd,
            );
            if let Some(a) = &added {
                prefetch(a.as_ptr().wrapping_add(ahead.wrapping_mul(ndp)), 2 * ndp);
            }
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
                let m = s.step(
                    &kern,
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
                    base,
                );
                left_min = m[0];
                cur_min[0][x] = m[1];
                cur_min[1][x] = m[2];
                cur_min[2][x] = m[3];
            } else {
                let m = s.step(
                    &kern,
                    c,
                    [left, top],
                    p1,
                    [&mut scratch, &mut c1[o]],
                    acc,
                    base,
                );
                left_min = m[0];
                cur_min[1][x] = m[1];
            }
            std::mem::swap(&mut left_l, &mut scratch);
        }
        row_sum = rows.done(oy(y), row_sum, added);
        std::mem::swap(&mut prev, &mut cur);
        std::mem::swap(&mut prev_min, &mut cur_min);
    }
    row_sum
}
