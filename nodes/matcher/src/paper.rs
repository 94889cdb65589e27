//! The paper's matcher: support-value candidates, NCC + SV decision, row constraints.
//!
//! Per pixel and direction: the `k` disparities with the highest support value are the
//! candidates; the winner maximises `NCC + SV / SVmax` over the same window (ties: higher
//! NCC, then smaller |d|, then smaller d). Constraints are row-local (rectified images):
//! the disparity range, uniqueness (a pixel of the other image claimed by several pixels
//! keeps only the best), and the optional ordering and continuity checks.
//!
//! Everything a row needs — the SV and the NCC cross-correlation sums of every disparity —
//! is computed once into a per-thread slab and read by both directions: right pixel `xr`
//! at disparity `d` is the same pair of windows as left pixel `xr + d`.

use crate::sv::{self, Descriptors, SvKernel, Weights};
use rayon::prelude::*;
use schemas::{DisparityMap, DisparityRange, INVALID_DISPARITY, Plane};
use serde::{Deserialize, Serialize};

/// Parameters of the paper matcher.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PaperParams {
    /// Disparities searched.
    pub range: DisparityRange,
    /// Window side W (odd, 3..=31).
    pub window: usize,
    /// Weight matrix of the support value.
    pub weights: Weights,
    /// How many top-SV candidates go on to the NCC decision.
    pub candidates: usize,
    /// Keep only the best of several pixels claiming the same pixel of the other image.
    /// Off by default: on slanted surfaces integer disparities legitimately map two
    /// pixels onto one, and the LR check already rejects the real conflicts.
    pub uniqueness: bool,
    /// Invalidate matches that break the left-to-right order of their row neighbours.
    pub ordering: bool,
    /// Invalidate matches no row neighbour supports (neighbour disparity within 1 px).
    pub continuity: bool,
}

impl Default for PaperParams {
    fn default() -> Self {
        Self {
            range: DisparityRange::new(0, 64),
            window: 13,
            weights: Weights::Equal,
            candidates: 3,
            uniqueness: false,
            ordering: false,
            continuity: false,
        }
    }
}

/// Which directions to match.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Directions {
    /// Left image as reference only (the match-lr node).
    LeftToRight,
    /// Right image as reference only (the match-rl node).
    RightToLeft,
    /// Both, sharing the cost slab.
    Both,
}

/// Result of the paper matcher; maps of a direction not matched are all invalid.
#[derive(Clone, Debug)]
pub struct PaperMatch {
    /// Left-based disparity (integer values), left→right.
    pub left: DisparityMap,
    /// Right-based disparity (right pixel `xr` matches left `xr + d`), right→left.
    pub right: DisparityMap,
    /// Decision score `NCC + SV/SVmax` of each left match.
    pub left_score: Plane<f32>,
    /// Decision score of each right match.
    pub right_score: Plane<f32>,
    /// Support-value evaluations performed (pixel × disparity pairs, shared by both directions).
    pub evaluations: u64,
}

/// `true` when decision `(score, ncc, d)` beats the current best.
#[inline(always)]
fn decision_better(a: (f64, f64, i32), b: (f64, f64, i32)) -> bool {
    if a.0 != b.0 {
        return a.0 > b.0;
    }
    if a.1 != b.1 {
        return a.1 > b.1;
    }
    if a.2.unsigned_abs() != b.2.unsigned_abs() {
        return a.2.unsigned_abs() < b.2.unsigned_abs();
    }
    a.2 < b.2
}

/// Per-image data shared by all rows.
struct Side {
    padded: Plane<u8>,
    sums: Plane<u32>,
    /// 1 / sqrt(n · variance) of each window, 0 for a flat window.
    inv_dev: Vec<f64>,
    desc: Descriptors,
}

fn prepare(img: &Plane<u8>, window: usize) -> Side {
    let r = (window - 1) / 2;
    let padded = sv::pad_replicate(img, r);
    let (sums, sq) = sv::window_sums(&padded, window);
    let n = (window * window) as f64;
    let inv_dev = sums
        .data
        .iter()
        .zip(&sq.data)
        .map(|(&s, &q)| {
            let v = q as f64 - (s as f64) * (s as f64) / n;
            if v > 1e-6 { 1.0 / v.sqrt() } else { 0.0 }
        })
        .collect();
    let desc = sv::descriptors_from_padded(&padded, &sums, window);
    Side {
        padded,
        sums,
        inv_dev,
        desc,
    }
}

/// Rows per parallel band: enough to amortise the window's start-up sums.
const BAND: usize = 16;

/// Matches a rectified grey pair with the paper's method.
///
/// Both images must have the same size and the window must fit (checked by the caller, see
/// [`crate::check_inputs`]).
pub fn match_paper(
    left: &Plane<u8>,
    right: &Plane<u8>,
    params: &PaperParams,
    directions: Directions,
) -> PaperMatch {
    let (w, h) = (left.width, left.height);
    let window = params.window;
    let kernel = SvKernel::new(window, params.weights);
    let (ls, rs) = rayon::join(|| prepare(left, window), || prepare(right, window));
    let ctx = RowCtx {
        w,
        window,
        params,
        kernel: &kernel,
        l: &ls,
        r: &rs,
        directions,
    };
    let mut out_l = vec![INVALID_DISPARITY; w * h];
    let mut out_r = vec![INVALID_DISPARITY; w * h];
    let mut sc_l = vec![0f32; w * h];
    let mut sc_r = vec![0f32; w * h];
    let evaluations: u64 = out_l
        .par_chunks_mut(BAND * w)
        .zip(out_r.par_chunks_mut(BAND * w))
        .zip(sc_l.par_chunks_mut(BAND * w))
        .zip(sc_r.par_chunks_mut(BAND * w))
        .enumerate()
        .map(|(b, (((dl, dr), sl), sr))| {
            let y0 = b * BAND;
            let y1 = (y0 + BAND).min(h);
            ctx.band(y0, y1, dl, dr, sl, sr)
        })
        .sum();
    let plane = |data| Plane {
        width: w,
        height: h,
        data,
    };
    PaperMatch {
        left: plane(out_l),
        right: plane(out_r),
        left_score: plane(sc_l),
        right_score: plane(sc_r),
        evaluations,
    }
}

struct RowCtx<'a> {
    w: usize,
    window: usize,
    params: &'a PaperParams,
    kernel: &'a SvKernel,
    l: &'a Side,
    r: &'a Side,
    directions: Directions,
}

impl RowCtx<'_> {
    /// Columns `u` of the padded images where both `u` and `u − d` exist.
    fn padded_span(&self, d: i32) -> (usize, usize) {
        let pw = self.l.padded.width as i32;
        let lo = d.max(0);
        let hi = pw.min(pw + d);
        (lo as usize, hi.max(lo) as usize)
    }

    /// Left columns `x` whose match `x − d` lies inside the right image.
    fn left_span(&self, d: i32) -> (usize, usize) {
        let w = self.w as i32;
        let lo = d.max(0);
        let hi = w.min(w + d);
        (lo as usize, hi.max(lo) as usize)
    }

    fn band(
        &self,
        y0: usize,
        y1: usize,
        out_l: &mut [f32],
        out_r: &mut [f32],
        sc_l: &mut [f32],
        sc_r: &mut [f32],
    ) -> u64 {
        let w = self.w;
        let range = self.params.range;
        let nd = range.count();
        let pw = self.l.padded.width;
        let win = self.window;
        let lp = &self.l.padded.data;
        let rp = &self.r.padded.data;
        let mut colsum = vec![0u32; nd * pw];
        let mut cross = vec![0u32; nd * w];
        let mut prefix = Vec::new();
        let mut svs = vec![0u32; nd * w];
        let mut evaluations = 0u64;
        let k = self.params.candidates.max(1);
        let mut top_sv = vec![-1i32; w * k];
        let mut top_d = vec![0i32; w * k];
        let mut count = vec![0u8; w];
        let mut order: Vec<i32> = (range.min..=range.max).collect();
        order.sort_by_key(|&d| (d.unsigned_abs(), d));
        let mut row_l = vec![(INVALID_DISPARITY, 0f32, 0f64); w];
        let mut row_r = vec![(INVALID_DISPARITY, 0f32, 0f64); w];
        for y in y0..y1 {
            // NCC cross sums: column sums over the window rows, slid along the row.
            for (di, d) in (range.min..=range.max).enumerate() {
                let (ulo, uhi) = self.padded_span(d);
                let col = &mut colsum[di * pw..(di + 1) * pw];
                let du = d as isize;
                let rs = (ulo as isize - du) as usize;
                let n = uhi - ulo;
                // Row py's products l·r over the span: (left run, right run).
                let runs = |py: usize| {
                    let lrow = &lp[py * pw..(py + 1) * pw];
                    let rrow = &rp[py * pw..(py + 1) * pw];
                    (&lrow[ulo..uhi], &rrow[rs..rs + n])
                };
                let c = &mut col[ulo..uhi];
                if y == y0 {
                    c.fill(0);
                    for i in 0..win {
                        let (a, b) = runs(y + i);
                        for k in 0..n {
                            c[k] = c[k].wrapping_add(a[k] as u32 * b[k] as u32);
                        }
                    }
                } else {
                    // The row entering the window and the row leaving it, in one pass.
                    let ((a, b), (e, f)) = (runs(y + win - 1), runs(y - 1));
                    for k in 0..n {
                        let enter = a[k] as u32 * b[k] as u32;
                        let leave = e[k] as u32 * f[k] as u32;
                        c[k] = c[k].wrapping_add(enter).wrapping_sub(leave);
                    }
                }
                let (xlo, xhi) = self.left_span(d);
                let cr = &mut cross[di * w..(di + 1) * w];
                if xlo < xhi {
                    window_sums_row(
                        &col[xlo..xhi + win - 1],
                        win,
                        &mut cr[xlo..xhi],
                        &mut prefix,
                    );
                }
                self.kernel.support_row(
                    self.l.desc.row(y),
                    self.r.desc.row(y),
                    xlo,
                    xhi,
                    du,
                    &mut svs[di * w..(di + 1) * w],
                );
                evaluations += (xhi - xlo) as u64;
            }
            let n = (win * win) as f64;
            let ncc = |x: usize, xr: usize, di: usize| -> f64 {
                let sl = self.l.sums.data[y * w + x] as f64;
                let sr = self.r.sums.data[y * w + xr] as f64;
                let num = cross[di * w + x] as f64 - sl * sr / n;
                num * self.l.inv_dev[y * w + x] * self.r.inv_dev[y * w + xr]
            };
            let svmax = self.kernel.max as f64;
            let wi = w as i32;
            for rl in [false, true] {
                if (!rl && self.directions == Directions::RightToLeft)
                    || (rl && self.directions == Directions::LeftToRight)
                {
                    continue;
                }
                // Top-k by SV per reference pixel, slot j of pixel p at [j * w + p] (−1 =
                // empty). Disparities come in order of |d| then d, and a candidate must be
                // strictly better to move up: that is the tie rule. The insertion is a
                // branch-free network, so it vectorises across pixels.
                top_sv.fill(-1);
                for &d in &order {
                    let di = (d - range.min) as usize;
                    let sv = &svs[di * w..(di + 1) * w];
                    // Reference pixels p whose partner exists; the slab is indexed by left x.
                    let (plo, phi) = if rl {
                        ((-d).max(0) as usize, wi.min(wi - d).max(0) as usize)
                    } else {
                        (d.max(0) as usize, wi.min(wi + d).max(0) as usize)
                    };
                    if plo >= phi {
                        continue;
                    }
                    let off = if rl { d as isize } else { 0 };
                    let vals = &sv[(plo as isize + off) as usize..(phi as isize + off) as usize];
                    for j in (0..k).rev() {
                        let (above_t, cur_t) = top_sv.split_at_mut(j * w);
                        let (above_d, cur_d) = top_d.split_at_mut(j * w);
                        let n = phi - plo;
                        let ct = &mut cur_t[plo..phi];
                        let cd = &mut cur_d[plo..phi];
                        if j == 0 {
                            insert_top(&vals[..n], d, ct, cd, None);
                        } else {
                            let at = &above_t[(j - 1) * w + plo..(j - 1) * w + phi];
                            let ad = &above_d[(j - 1) * w + plo..(j - 1) * w + phi];
                            insert_top(&vals[..n], d, ct, cd, Some((at, ad)));
                        }
                    }
                }
                for p in 0..w {
                    count[p] = (0..k).filter(|&j| top_sv[j * w + p] >= 0).count() as u8;
                }
                let row = if rl { &mut row_r } else { &mut row_l };
                for p in 0..w {
                    let mut best: Option<(f64, f64, i32)> = None;
                    for c in 0..count[p] as usize {
                        let d = top_d[c * w + p];
                        let (x, xr) = if rl {
                            ((p as i32 + d) as usize, p)
                        } else {
                            (p, (p as i32 - d) as usize)
                        };
                        let di = (d - range.min) as usize;
                        let nc = ncc(x, xr, di);
                        let cand = (nc + top_sv[c * w + p] as f64 / svmax, nc, d);
                        if best.is_none_or(|b| decision_better(cand, b)) {
                            best = Some(cand);
                        }
                    }
                    row[p] = match best {
                        Some((s, nc, d)) => (d as f32, s as f32, nc),
                        None => (INVALID_DISPARITY, 0.0, 0.0),
                    };
                }
            }
            if self.params.uniqueness {
                enforce_uniqueness(&mut row_l, |x, d| x as i32 - d);
                enforce_uniqueness(&mut row_r, |xr, d| xr as i32 + d);
            }
            if self.params.ordering {
                enforce_ordering(&mut row_l, |x, d| x as i32 - d);
                enforce_ordering(&mut row_r, |xr, d| xr as i32 + d);
            }
            if self.params.continuity {
                enforce_continuity(&mut row_l);
                enforce_continuity(&mut row_r);
            }
            let o = (y - y0) * w;
            for x in 0..w {
                out_l[o + x] = row_l[x].0;
                sc_l[o + x] = row_l[x].1;
                out_r[o + x] = row_r[x].0;
                sc_r[o + x] = row_r[x].1;
            }
        }
        evaluations
    }
}

/// `out[x] = Σ col[x..x + win]` for every `x < out.len()` (`col` holds `out.len() + win − 1`
/// values, wrapping arithmetic), as differences of a prefix sum. A running window sum is
/// a chain of dependent adds; the prefix sum is built eight values at a time with an
/// in-register scan.
fn window_sums_row(col: &[u32], win: usize, out: &mut [u32], prefix: &mut Vec<u32>) {
    let n = col.len();
    debug_assert_eq!(n, out.len() + win - 1);
    // prefix[i] = Σ col[..i], n + 1 values.
    prefix.clear();
    prefix.resize(n + 1, 0);
    let (mut i, mut carry) = prefix_sums_simd(col, prefix);
    while i < n {
        carry = carry.wrapping_add(col[i]);
        prefix[i + 1] = carry;
        i += 1;
    }
    for (x, o) in out.iter_mut().enumerate() {
        *o = prefix[x + win].wrapping_sub(prefix[x]);
    }
}

/// The vector part of [`window_sums_row`]'s prefix sum: fills `prefix[1..=i]` for the
/// first `i` (a multiple of 8) values and returns `i` and `Σ col[..i]`.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
fn prefix_sums_simd(col: &[u32], prefix: &mut [u32]) -> (usize, u32) {
    use std::arch::x86_64::*;
    let n = col.len();
    assert!(prefix.len() > n);
    let mut i = 0;
    // SAFETY: AVX2 is enabled for this build; loads read col[i..i + 8] and stores write
    // prefix[i + 1..i + 9], both inside (i + 8 <= n < prefix.len()).
    unsafe {
        let mut carry = _mm256_setzero_si256();
        let last = _mm256_set1_epi32(7);
        let low_total = _mm256_set_epi32(3, 3, 3, 3, 0, 0, 0, 0);
        while i + 8 <= n {
            let mut v = _mm256_loadu_si256(col.as_ptr().add(i) as *const __m256i);
            // Scan inside each 128-bit half, then carry the low half's total up.
            v = _mm256_add_epi32(v, _mm256_slli_si256(v, 4));
            v = _mm256_add_epi32(v, _mm256_slli_si256(v, 8));
            let lo = _mm256_permutevar8x32_epi32(v, low_total);
            let lo = _mm256_blend_epi32(lo, _mm256_setzero_si256(), 0x0f);
            v = _mm256_add_epi32(_mm256_add_epi32(v, lo), carry);
            _mm256_storeu_si256(prefix.as_mut_ptr().add(i + 1) as *mut __m256i, v);
            carry = _mm256_permutevar8x32_epi32(v, last);
            i += 8;
        }
        (i, _mm256_extract_epi32(carry, 0) as u32)
    }
}

/// Without AVX2 the prefix sum is all scalar.
#[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
fn prefix_sums_simd(_: &[u32], _: &mut [u32]) -> (usize, u32) {
    (0, 0)
}

/// One slot of the branch-free top-k insertion, for a run of pixels: value `v[i]` at
/// disparity `d` against the slot `(t, td)` and the slot above it `(at, ad)` (none for the
/// first slot). Slots are sorted (above ≥ current), so the slot's new value is
/// `max(t, min(v, above))`, and its disparity moves down from above when `v > above`.
#[inline(always)]
fn insert_top(v: &[u32], d: i32, t: &mut [i32], td: &mut [i32], above: Option<(&[i32], &[i32])>) {
    let n = v.len();
    let mut i = 0;
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    {
        use std::arch::x86_64::*;
        // SAFETY: every access is at index i..i + 8 ≤ n of slices at least n long (checked
        // by the asserts), and AVX2 is enabled for this build.
        unsafe {
            assert!(t.len() >= n && td.len() >= n);
            let dv = _mm256_set1_epi32(d);
            while i + 8 <= n {
                let vv = _mm256_loadu_si256(v.as_ptr().add(i) as *const __m256i);
                let tv = _mm256_loadu_si256(t.as_ptr().add(i) as *const __m256i);
                let tdv = _mm256_loadu_si256(td.as_ptr().add(i) as *const __m256i);
                let gt = _mm256_cmpgt_epi32(vv, tv);
                let mut nd = _mm256_blendv_epi8(tdv, dv, gt);
                let nt = match above {
                    None => _mm256_max_epi32(tv, vv),
                    Some((at, ad)) => {
                        assert!(at.len() >= n && ad.len() >= n);
                        let av = _mm256_loadu_si256(at.as_ptr().add(i) as *const __m256i);
                        let adv = _mm256_loadu_si256(ad.as_ptr().add(i) as *const __m256i);
                        nd = _mm256_blendv_epi8(nd, adv, _mm256_cmpgt_epi32(vv, av));
                        _mm256_max_epi32(tv, _mm256_min_epi32(vv, av))
                    }
                };
                _mm256_storeu_si256(t.as_mut_ptr().add(i) as *mut __m256i, nt);
                _mm256_storeu_si256(td.as_mut_ptr().add(i) as *mut __m256i, nd);
                i += 8;
            }
        }
    }
    for i in i..n {
        let x = v[i] as i32;
        let moved = if x > t[i] { d } else { td[i] };
        match above {
            None => {
                td[i] = moved;
                t[i] = t[i].max(x);
            }
            Some((at, ad)) => {
                td[i] = if x > at[i] { ad[i] } else { moved };
                t[i] = t[i].max(x.min(at[i]));
            }
        }
    }
}

/// Row entries are `(disparity, score, ncc)`; a pixel of the other image claimed by several
/// pixels keeps the best claimant (score, then NCC, then smaller |d|).
fn enforce_uniqueness(row: &mut [(f32, f32, f64)], target: impl Fn(usize, i32) -> i32) {
    let w = row.len();
    let mut owner: Vec<Option<usize>> = vec![None; w];
    for x in 0..w {
        let (d, s, nc) = row[x];
        if !d.is_finite() {
            continue;
        }
        let t = target(x, d as i32);
        if !(0..w as i32).contains(&t) {
            continue;
        }
        let slot = &mut owner[t as usize];
        match *slot {
            None => *slot = Some(x),
            Some(o) => {
                let (od, os, onc) = row[o];
                if decision_better((s as f64, nc, d as i32), (os as f64, onc, od as i32)) {
                    row[o].0 = INVALID_DISPARITY;
                    *slot = Some(x);
                } else {
                    row[x].0 = INVALID_DISPARITY;
                }
            }
        }
    }
}

/// Invalidates both members of every pair of consecutive valid matches whose targets are
/// not in the same left-to-right order as the pixels themselves.
fn enforce_ordering(row: &mut [(f32, f32, f64)], target: impl Fn(usize, i32) -> i32) {
    let valid: Vec<usize> = (0..row.len()).filter(|&x| row[x].0.is_finite()).collect();
    let mut bad = vec![false; row.len()];
    for pair in valid.windows(2) {
        let (a, b) = (pair[0], pair[1]);
        if target(b, row[b].0 as i32) <= target(a, row[a].0 as i32) {
            bad[a] = true;
            bad[b] = true;
        }
    }
    for (x, b) in bad.into_iter().enumerate() {
        if b {
            row[x].0 = INVALID_DISPARITY;
        }
    }
}

/// Invalidates matches with no row neighbour within 1 px of disparity.
fn enforce_continuity(row: &mut [(f32, f32, f64)]) {
    let d: Vec<f32> = row.iter().map(|e| e.0).collect();
    for x in 0..row.len() {
        if !d[x].is_finite() {
            continue;
        }
        let near = |o: Option<usize>| {
            o.and_then(|o| d.get(o))
                .is_some_and(|&n| (n - d[x]).abs() <= 1.0)
        };
        if !near(x.checked_sub(1)) && !near(Some(x + 1)) {
            row[x].0 = INVALID_DISPARITY;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(ds: &[f32]) -> Vec<(f32, f32, f64)> {
        ds.iter().map(|&d| (d, 1.0, 0.5)).collect()
    }

    #[test]
    fn uniqueness_keeps_the_best_claimant() {
        // x=2 (d=1) and x=3 (d=2) both claim right pixel 1; x=3 scores higher.
        let mut r = row(&[0.0, 5.0, 1.0, 2.0]);
        r[1].0 = INVALID_DISPARITY;
        r[3].1 = 2.0;
        enforce_uniqueness(&mut r, |x, d| x as i32 - d);
        let ds: Vec<f32> = r.iter().map(|e| e.0).collect();
        assert_eq!(ds, vec![0.0, INVALID_DISPARITY, INVALID_DISPARITY, 2.0]);
    }

    #[test]
    fn ordering_flags_crossing_matches() {
        // Targets: 10-0=10, 11-5=6 (crosses), 12-0=12 after the crossing pair.
        let mut r = vec![(INVALID_DISPARITY, 0.0, 0.0); 13];
        r[10] = (0.0, 1.0, 0.0);
        r[11] = (5.0, 1.0, 0.0);
        r[12] = (0.0, 1.0, 0.0);
        enforce_ordering(&mut r, |x, d| x as i32 - d);
        assert!(!r[10].0.is_finite() && !r[11].0.is_finite());
        // 12 (target 12) is in order after 11 (target 6), so it stays.
        assert_eq!(r[12].0, 0.0);
    }

    #[test]
    fn continuity_removes_unsupported_matches() {
        let mut r = row(&[3.0, 3.0, 9.0, 4.0, INVALID_DISPARITY, 7.0]);
        enforce_continuity(&mut r);
        let ds: Vec<f32> = r.iter().map(|e| e.0).collect();
        assert_eq!(
            ds,
            vec![
                3.0,
                3.0,
                INVALID_DISPARITY,
                INVALID_DISPARITY,
                INVALID_DISPARITY,
                INVALID_DISPARITY
            ]
        );
    }

    #[test]
    fn window_sums_row_equals_direct_sums() {
        let col: Vec<u32> = (0..90u32)
            .map(|i| i.wrapping_mul(2_654_435_761) >> 7)
            .collect();
        let mut prefix = Vec::new();
        for win in [1, 2, 3, 5, 13, 31] {
            for len in [1, 3, 7, 8, 9, 16, 17, 40, 60] {
                let c = &col[..len + win - 1];
                let mut out = vec![0; len];
                window_sums_row(c, win, &mut out, &mut prefix);
                for x in 0..len {
                    let direct = c[x..x + win].iter().fold(0u32, |a, &v| a.wrapping_add(v));
                    assert_eq!(out[x], direct, "win {win} len {len} x {x}");
                }
            }
        }
    }
}
