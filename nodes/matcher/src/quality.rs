//! Quality mode: census + gradient cost, semi-global aggregation over 8 paths.
//!
//! Cost: Hamming distance of 9×7 census descriptors (robust to the gain and offset
//! differences between two microscope cameras) plus a truncated difference of horizontal
//! gradients (sharpens depth edges). Aggregation: Hirschmüller's SGM over 8 paths, with the
//! large-jump penalty P2 lowered across intensity edges. Two passes (top-down and
//! bottom-up, four paths each) run in parallel. Decision: winner-takes-all with a
//! uniqueness ratio and a sub-pixel parabola; the right-based map is read from the same
//! aggregated volume along its diagonals, so the LR check costs no second matching.

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
        for (x, o) in row.iter_mut().enumerate() {
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
    let mut cost = vec![COST_OUTSIDE; w * h * nd];
    let gw = p.gradient_weight;
    let cap = p.gradient_cap;
    cost.par_chunks_mut(w * nd)
        .enumerate()
        .for_each(|(y, row)| {
            let (cl, cr) = (cl.row(y), cr.row(y));
            let (gl, gr) = (gl.row(y), gr.row(y));
            for x in 0..w {
                let out = &mut row[x * nd..(x + 1) * nd];
                for (di, o) in out.iter_mut().enumerate() {
                    let xr = x as i32 - (p.range.min + di as i32);
                    if xr < 0 || xr >= w as i32 {
                        continue;
                    }
                    let xr = xr as usize;
                    let ham = (cl[x] ^ cr[xr]).count_ones() as u16;
                    let g = (gl[x].abs_diff(gr[xr]) / 4).min(cap);
                    *o = (ham * 2 + gw * g).min(COST_OUTSIDE as u16 - 1) as u8;
                }
            }
        });
    cost
}

/// Cost given to disparities that point outside the right image.
pub const COST_OUTSIDE: u8 = 160;

/// Matches a rectified grey pair (checked with [`crate::check_inputs`]).
pub fn match_quality(left: &Plane<u8>, right: &Plane<u8>, p: &QualityParams) -> QualityMatch {
    let (w, h) = (left.width, left.height);
    let nd = p.range.count();
    let cost = cost_volume(left, right, p);
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
    let dmin = p.range.min;
    let mut left = vec![INVALID_DISPARITY; w * h];
    let mut right = vec![INVALID_DISPARITY; w * h];
    left.par_chunks_mut(w)
        .zip(right.par_chunks_mut(w))
        .enumerate()
        .for_each_init(
            || (vec![0u16; w * nd], vec![0u16; nd]),
            |(total, buf), (y, (lrow, rrow))| {
                let o = y * w * nd;
                for i in 0..w * nd {
                    total[i] = s1[o + i].wrapping_add(s2[o + i]);
                }
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
                    let mut lo = usize::MAX;
                    let mut hi = 0;
                    for (di, b) in buf.iter_mut().enumerate() {
                        let x = xr as i32 + dmin + di as i32;
                        if (0..w as i32).contains(&x) {
                            *b = total[x as usize * nd + di];
                            lo = lo.min(di);
                            hi = di + 1;
                        }
                    }
                    if lo < hi {
                        rrow[xr] = decide(&buf[lo..hi], lo, p.uniqueness_ratio, dmin);
                    }
                }
            },
        );
    let plane = |data| Plane {
        width: w,
        height: h,
        data,
    };
    (plane(left), plane(right))
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
