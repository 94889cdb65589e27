//! Thin arcs around a larger object belong to it: an embryo's zona pellucida, a ring of
//! texture around a textureless perivitelline space, breaks into arcs under the variance
//! threshold, and each arc would otherwise be a cell of its own.

use imageproc::point::Point;
use schemas::Plane;

/// Largest solidity (area over convex-hull area) of a component that counts as an arc.
const ARC_SOLIDITY: f64 = 0.35;

/// Least ratio of the enclosed object's area to the arc's.
const ARC_AREA_RATIO: u64 = 2;

struct Component {
    area: u64,
    /// Raster-first pixel: where its boundary trace starts.
    first: [u32; 2],
    hull: Vec<[f64; 2]>,
    hull_area: f64,
}

/// Relabels, in place, every thin arc of `labels` (`1..=n`) whose convex hull reaches into a
/// component at least twice its size with that component's id, closes every arc that
/// reaches into none and follows an ellipse round most of its turn (a cell's rim open on
/// one side, [`close_open_ring`]), and renumbers the labels
/// `1..=m` in their old order. Returns `m` and, per new id, where its boundary trace starts
/// (the raster-first pixel of its largest piece, so that an absorbed arc does not become
/// the contour).
pub fn absorb_rings(labels: &mut Plane<u32>, n: u32) -> (u32, Vec<[u32; 2]>) {
    let mut comps = components(labels, n);
    let into = hosts(&comps, |b, hull| reaches(labels, b as u32, hull));
    for (a, c) in comps.iter_mut().enumerate() {
        if into[a] == a as u32
            && let Some(c) = c
        {
            close_open_ring(labels, a as u32, c);
        }
    }
    renumber(labels, &comps, &into)
}

/// Largest solidity of a hostless component that may be an open ring (a cell's rim whose
/// near side fell under the variance threshold).
const OPEN_RING_SOLIDITY: f64 = 0.5;

/// Least turn (of 36 ten-degree sectors round the fitted ellipse's centre) an open ring's
/// pixels must cover: a crescent, not a hook or a bar. The crescents of flat-topped cells
/// seen at a slant (the heights matrix's strong perspective and 1280×1024 views) covered
/// 24–33; a thin 143° arc of 98 px, whose conic bends in on it, 23.
const OPEN_RING_SECTORS: usize = 24;

/// Fewest pixels of an open ring: the variance band round a cell of 20 px across (thin
/// short arcs fit conics that bend in on them).
const OPEN_RING_PIXELS: u64 = 200;

/// Largest share of an open ring's pixels off its fitted ellipse by more than a third of
/// its radius.
const OPEN_RING_OFF: f64 = 0.1;

/// Fills, with label `id`, the background inside the ellipse that the hostless arc `c`
/// follows, where it is one: a flat-topped cell seen at a slant shows its rim on the far
/// side only (the plateau hides the near flank), and the variance threshold keeps a
/// crescent whose gap is too wide to close ([`crate::fill_broken_outlines`]). The ellipse
/// is a least-squares conic through the arc's pixels; it must cover at least 240° of turn,
/// fit them within a third of its radius, stay within the arc's box grown by a quarter and
/// cover no other label's pixels (beyond 2 %). Updates `c`'s area and first pixel.
fn close_open_ring(labels: &mut Plane<u32>, id: u32, c: &mut Component) {
    let solidity = c.area as f64 / (c.hull_area + 0.5 * perimeter(&c.hull) + 1.0);
    if solidity > OPEN_RING_SOLIDITY || c.hull.len() < 3 || c.area < OPEN_RING_PIXELS {
        return;
    }
    let (lo, hi) = hull_box(&c.hull);
    let [x0, y0, x1, y1] = pixel_box(labels, lo, hi);
    let mut pts = Vec::new();
    for y in y0..=y1 {
        for (i, &l) in labels.row(y)[x0..=x1].iter().enumerate() {
            if l == id {
                pts.push([(x0 + i) as f64, y as f64]);
            }
        }
    }
    let Some(e) = Ellipse::fit(&pts) else {
        return;
    };
    // A rim encloses far more than itself; an ellipse fitted inside a short thick arc
    // does not.
    if e.area() < 2.0 * pts.len() as f64 {
        return;
    }
    // Normalised radius of each arc pixel, and the sectors of turn they cover.
    let mut sectors = [false; 36];
    let mut off = 0usize;
    let mut rho: Vec<f64> = Vec::with_capacity(pts.len());
    for &p in &pts {
        let (r, angle) = e.polar(p);
        rho.push(r);
        if (r - 1.0).abs() > 1.0 / 3.0 {
            off += 1;
        }
        let k = ((angle + std::f64::consts::PI) / std::f64::consts::TAU * 36.0) as usize;
        sectors[k.min(35)] = true;
    }
    if sectors.iter().filter(|s| **s).count() < OPEN_RING_SECTORS
        || off as f64 > OPEN_RING_OFF * pts.len() as f64
    {
        return;
    }
    // Out to the arc's own outer edge (its 95th percentile radius).
    rho.sort_by(f64::total_cmp);
    let outer = rho[(rho.len() - 1) * 95 / 100];
    let [bx0, by0, bx1, by1] = e.bounds(outer);
    let grow = [0.25 * (hi[0] - lo[0]), 0.25 * (hi[1] - lo[1])];
    if bx0 < lo[0] - grow[0]
        || bx1 > hi[0] + grow[0]
        || by0 < lo[1] - grow[1]
        || by1 > hi[1] + grow[1]
    {
        return;
    }
    let (fx0, fx1) = (
        bx0.floor().max(0.0) as usize,
        (bx1.ceil() as usize).min(labels.width - 1),
    );
    let (fy0, fy1) = (
        by0.floor().max(0.0) as usize,
        (by1.ceil() as usize).min(labels.height - 1),
    );
    let (mut fill, mut other) = (Vec::new(), 0usize);
    for y in fy0..=fy1 {
        for x in fx0..=fx1 {
            if e.polar([x as f64, y as f64]).0 <= outer {
                match *labels.get(x, y) {
                    0 => fill.push((x, y)),
                    l if l != id => other += 1,
                    _ => {}
                }
            }
        }
    }
    if other as f64 > 0.02 * (fill.len() + other + pts.len()) as f64 {
        return;
    }
    for &(x, y) in &fill {
        *labels.get_mut(x, y) = id;
        if (y as u32, x as u32) < (c.first[1], c.first[0]) {
            c.first = [x as u32, y as u32];
        }
    }
    c.area += fill.len() as u64;
}

/// An ellipse `(p − c)ᵀ·M·(p − c) = 1`.
struct Ellipse {
    centre: [f64; 2],
    /// `M` as `[m00, m01, m11]`.
    m: [f64; 3],
}

impl Ellipse {
    /// The least-squares conic `A·x² + B·x·y + C·y² + D·x + E·y + F = 0` with `A + C = 1`
    /// through `pts` (centred and scaled for its conditioning), if it is an ellipse no
    /// more than three times as long as it is wide.
    fn fit(pts: &[[f64; 2]]) -> Option<Self> {
        if pts.len() < 10 {
            return None;
        }
        let n = pts.len() as f64;
        let mean = pts
            .iter()
            .fold([0.0, 0.0], |a, p| [a[0] + p[0] / n, a[1] + p[1] / n]);
        let scale = (pts
            .iter()
            .map(|p| (p[0] - mean[0]).powi(2) + (p[1] - mean[1]).powi(2))
            .sum::<f64>()
            / n)
            .sqrt()
            .max(1e-9);
        // With C = 1 − A: A·(x² − y²) + B·x·y + D·x + E·y + F = −y².
        let mut ata = [[0.0f64; 5]; 5];
        let mut atb = [0.0f64; 5];
        for p in pts {
            let (x, y) = ((p[0] - mean[0]) / scale, (p[1] - mean[1]) / scale);
            let row = [x * x - y * y, x * y, x, y, 1.0];
            for i in 0..5 {
                for j in 0..5 {
                    ata[i][j] += row[i] * row[j];
                }
                atb[i] += row[i] * (-y * y);
            }
        }
        let [a, b, d, e, f] = solve5(ata, atb)?;
        let c = 1.0 - a;
        let det = 4.0 * a * c - b * b;
        if det <= 0.0 {
            return None;
        }
        // Centre: ∇ = 0.
        let cx = (b * e - 2.0 * c * d) / det;
        let cy = (b * d - 2.0 * a * e) / det;
        let f0 = f + 0.5 * (d * cx + e * cy);
        if f0 >= 0.0 {
            return None;
        }
        let m = [-a / f0, -0.5 * b / f0, -c / f0];
        // Eigenvalues of M: the inverse squared semi-axes.
        let (tr, dm) = (m[0] + m[2], m[0] * m[2] - m[1] * m[1]);
        let disc = (0.25 * tr * tr - dm).max(0.0).sqrt();
        let (l1, l2) = (0.5 * tr + disc, 0.5 * tr - disc);
        if l2 <= 0.0 || l1 / l2 > 9.0 {
            return None;
        }
        let s2 = scale * scale;
        Some(Self {
            centre: [mean[0] + cx * scale, mean[1] + cy * scale],
            m: [m[0] / s2, m[1] / s2, m[2] / s2],
        })
    }

    /// Normalised radius (1 on the ellipse) and angle in its normalised frame of `p`.
    fn polar(&self, p: [f64; 2]) -> (f64, f64) {
        let (dx, dy) = (p[0] - self.centre[0], p[1] - self.centre[1]);
        let q = self.m[0] * dx * dx + 2.0 * self.m[1] * dx * dy + self.m[2] * dy * dy;
        // The angle in a frame where the ellipse is a circle: M's square root applied.
        let (u, v) = (
            self.m[0].sqrt() * dx + self.m[1] / self.m[0].sqrt() * dy,
            (self.m[2] - self.m[1] * self.m[1] / self.m[0])
                .max(0.0)
                .sqrt()
                * dy,
        );
        (q.max(0.0).sqrt(), v.atan2(u))
    }

    /// Area (px²).
    fn area(&self) -> f64 {
        std::f64::consts::PI / (self.m[0] * self.m[2] - self.m[1] * self.m[1]).sqrt()
    }

    /// The box `[x0, y0, x1, y1]` of the ellipse scaled by `r`.
    fn bounds(&self, r: f64) -> [f64; 4] {
        // Half extents of {q ≤ r²}: r·√(M⁻¹ diagonal).
        let det = self.m[0] * self.m[2] - self.m[1] * self.m[1];
        let (hx, hy) = (r * (self.m[2] / det).sqrt(), r * (self.m[0] / det).sqrt());
        [
            self.centre[0] - hx,
            self.centre[1] - hy,
            self.centre[0] + hx,
            self.centre[1] + hy,
        ]
    }
}

/// `x` with `a·x = b` (Gaussian elimination with partial pivoting); `None` when singular.
fn solve5(mut a: [[f64; 5]; 5], mut b: [f64; 5]) -> Option<[f64; 5]> {
    for col in 0..5 {
        let piv = (col..5).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[piv][col].abs() < 1e-12 {
            return None;
        }
        a.swap(col, piv);
        b.swap(col, piv);
        let pivot = a[col];
        for r in col + 1..5 {
            let f = a[r][col] / pivot[col];
            for (v, p) in a[r][col..].iter_mut().zip(&pivot[col..]) {
                *v -= f * p;
            }
            b[r] -= f * b[col];
        }
    }
    let mut x = [0.0; 5];
    for r in (0..5).rev() {
        let s: f64 = (r + 1..5).map(|k| a[r][k] * x[k]).sum();
        x[r] = (b[r] - s) / a[r][r];
    }
    Some(x)
}

/// Per label `0..=n` of `labels`, in one pass: its area, its raster-first pixel and the
/// convex hull of each of its rows' first and last pixel (pixels come row by row, so the
/// ends span the hull as all would), not a list of every pixel (3 MB a 1280×1024 view).
fn components(labels: &Plane<u32>, n: u32) -> Vec<Option<Component>> {
    struct Scan {
        area: u64,
        ends: Vec<Point<i64>>,
    }
    let mut scans: Vec<Option<Scan>> = (0..=n).map(|_| None).collect();
    for y in 0..labels.height {
        crate::label::for_each_labelled(labels.row(y), |x, l| {
            let p = Point::new(x as i64, y as i64);
            let s = scans[l as usize].get_or_insert_with(|| Scan {
                area: 0,
                ends: Vec::new(),
            });
            s.area += 1;
            match s.ends.last_mut() {
                Some(last) if last.y == p.y => *last = p,
                _ => s.ends.extend([p, p]),
            }
        });
    }
    scans
        .into_iter()
        .map(|s| {
            let s = s?;
            let first = s.ends[0];
            Some(Component::new(
                s.area,
                [first.x as u32, first.y as u32],
                s.ends,
            ))
        })
        .collect()
}

impl Component {
    fn new(area: u64, first: [u32; 2], ends: Vec<Point<i64>>) -> Self {
        let hull: Vec<[f64; 2]> = imageproc::geometry::convex_hull(ends)
            .iter()
            .map(|q| [q.x as f64, q.y as f64])
            .collect();
        let hull_area = polygon_area(&hull);
        Self {
            area,
            first,
            hull,
            hull_area,
        }
    }
}

/// The corners `(lo, hi)` of `hull`'s box.
fn hull_box(hull: &[[f64; 2]]) -> ([f64; 2], [f64; 2]) {
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for q in hull {
        for k in 0..2 {
            lo[k] = lo[k].min(q[k]);
            hi[k] = hi[k].max(q[k]);
        }
    }
    (lo, hi)
}

/// The pixels `[x0, y0, x1, y1]` (inclusive) of the box `lo..hi` that lie in `labels`.
fn pixel_box(labels: &Plane<u32>, lo: [f64; 2], hi: [f64; 2]) -> [usize; 4] {
    [
        lo[0].max(0.0) as usize,
        lo[1].max(0.0) as usize,
        (hi[0] as usize).min(labels.width - 1),
        (hi[1] as usize).min(labels.height - 1),
    ]
}

/// Whether a pixel of label `b` lies strictly inside `hull`: only the hull's box can hold
/// one.
fn reaches(labels: &Plane<u32>, b: u32, hull: &[[f64; 2]]) -> bool {
    let (lo, hi) = hull_box(hull);
    let [x0, y0, x1, y1] = pixel_box(labels, lo, hi);
    (y0..=y1).any(|y| {
        labels.row(y)[x0..=x1]
            .iter()
            .enumerate()
            .any(|(i, &l)| l == b && inside(hull, [(x0 + i) as f64, y as f64]))
    })
}

/// Per label, the label it joins: each arc the largest qualifying object its hull reaches
/// into (`reaches(b, hull)`), every other label itself.
fn hosts(comps: &[Option<Component>], reaches: impl Fn(usize, &[[f64; 2]]) -> bool) -> Vec<u32> {
    let mut into: Vec<u32> = (0..comps.len() as u32).collect();
    for (a, ca) in comps.iter().enumerate() {
        let Some(ca) = ca else { continue };
        // The hull of pixel centres misses half a pixel all round.
        let solidity = ca.area as f64 / (ca.hull_area + 0.5 * perimeter(&ca.hull) + 1.0);
        if solidity > ARC_SOLIDITY || ca.hull.len() < 3 {
            continue;
        }
        let host = comps
            .iter()
            .enumerate()
            .filter(|(b, cb)| {
                *b != a
                    && cb
                        .as_ref()
                        .is_some_and(|cb| cb.area >= ARC_AREA_RATIO * ca.area)
            })
            .filter(|(b, _)| reaches(*b, &ca.hull))
            .max_by_key(|(_, cb)| cb.as_ref().map_or(0, |c| c.area))
            .map(|(b, _)| b as u32);
        if let Some(h) = host {
            into[a] = h;
        }
    }
    into
}

/// Relabels every label as the one it joins (`into`) and numbers the survivors `1..=m` in
/// their old order; returns `m` and, per new id, where its boundary trace starts.
fn renumber(
    labels: &mut Plane<u32>,
    comps: &[Option<Component>],
    into: &[u32],
) -> (u32, Vec<[u32; 2]>) {
    let n = comps.len() - 1;
    let mut new_id = vec![0u32; n + 1];
    let mut starts = vec![[0, 0]];
    for l in 1..=n {
        if into[l] == l as u32 && comps[l].is_some() {
            new_id[l] = starts.len() as u32;
            starts.push(comps[l].as_ref().map_or([0, 0], |c| c.first));
        }
    }
    for l in 1..=n {
        if into[l] != l as u32 {
            new_id[l] = new_id[into[l] as usize];
        }
    }
    // Nothing absorbed and no label missing: the labels stay as they are.
    if new_id.iter().enumerate().any(|(l, &v)| v != l as u32) {
        for v in labels.data.iter_mut() {
            *v = new_id[*v as usize];
        }
    }
    (starts.len() as u32 - 1, starts)
}

/// Area of a simple polygon (shoelace).
fn polygon_area(p: &[[f64; 2]]) -> f64 {
    let n = p.len();
    (0..n)
        .map(|i| {
            let (a, b) = (p[i], p[(i + 1) % n]);
            a[0] * b[1] - b[0] * a[1]
        })
        .sum::<f64>()
        .abs()
        / 2.0
}

fn perimeter(p: &[[f64; 2]]) -> f64 {
    let n = p.len();
    (0..n)
        .map(|i| {
            let (a, b) = (p[i], p[(i + 1) % n]);
            (a[0] - b[0]).hypot(a[1] - b[1])
        })
        .sum()
}

/// Whether `q` lies strictly inside the convex polygon `hull` (either orientation).
fn inside(hull: &[[f64; 2]], q: [f64; 2]) -> bool {
    let n = hull.len();
    let mut sign = 0.0f64;
    for i in 0..n {
        let (a, b) = (hull[i], hull[(i + 1) % n]);
        let c = (b[0] - a[0]) * (q[1] - a[1]) - (b[1] - a[1]) * (q[0] - a[0]);
        if c == 0.0 {
            return false;
        }
        if sign == 0.0 {
            sign = c.signum();
        } else if c.signum() != sign {
            return false;
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A disc of radius `r` at `c` with label `l`, and an arc of the ring `r0..r1` between
    /// angles `a0..a1` (radians) with label `m`.
    fn scene(c: [f64; 2], r: f64, ring: (f64, f64), arcs: &[(f64, f64)]) -> Plane<u32> {
        let mut p = Plane::filled(120, 120, 0u32);
        for y in 0..120 {
            for x in 0..120 {
                let (dx, dy) = (x as f64 - c[0], y as f64 - c[1]);
                let d = dx.hypot(dy);
                let a = dy.atan2(dx);
                if d <= r {
                    *p.get_mut(x, y) = 1;
                } else if d >= ring.0
                    && d <= ring.1
                    && let Some(k) = arcs.iter().position(|&(a0, a1)| a >= a0 && a <= a1)
                {
                    *p.get_mut(x, y) = 2 + k as u32;
                }
            }
        }
        p
    }

    #[test]
    fn arcs_around_a_body_join_it_and_the_trace_starts_on_the_body() {
        let mut p = scene(
            [60.0, 60.0],
            30.0,
            (38.0, 41.0),
            &[(-3.0, -1.2), (0.2, 2.0)],
        );
        let (n, starts) = absorb_rings(&mut p, 3);
        assert_eq!(n, 1);
        assert!(p.data.iter().all(|&l| l <= 1));
        // The body's first raster pixel, not the upper arc's.
        assert_eq!(starts[1], [60, 30]);
        assert_eq!(p.data.iter().filter(|&&l| l == 1).count(), {
            let q = scene(
                [60.0, 60.0],
                30.0,
                (38.0, 41.0),
                &[(-3.0, -1.2), (0.2, 2.0)],
            );
            q.data.iter().filter(|&&l| l != 0).count()
        });
    }

    /// The first [`absorb_rings`]'s scan and host search: every pixel of every label listed.
    fn absorb_rings_reference(labels: &mut Plane<u32>, n: u32) -> (u32, Vec<[u32; 2]>) {
        let mut pts: Vec<Vec<Point<i64>>> = vec![Vec::new(); n as usize + 1];
        for y in 0..labels.height {
            for (x, &l) in labels.row(y).iter().enumerate() {
                if l != 0 {
                    pts[l as usize].push(Point::new(x as i64, y as i64));
                }
            }
        }
        let comps: Vec<Option<Component>> = pts
            .iter()
            .map(|p| {
                let first = p.first()?;
                let ends: Vec<Point<i64>> = p
                    .chunk_by(|a, b| a.y == b.y)
                    .flat_map(|row| [row[0], row[row.len() - 1]])
                    .collect();
                Some(Component::new(
                    p.len() as u64,
                    [first.x as u32, first.y as u32],
                    ends,
                ))
            })
            .collect();
        let into = hosts(&comps, |b, hull| {
            pts[b]
                .iter()
                .any(|p| inside(hull, [p.x as f64, p.y as f64]))
        });
        renumber(labels, &comps, &into)
    }

    #[test]
    fn the_row_end_scan_absorbs_as_the_first_version_did() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let mut absorbed = 0;
        for _ in 0..60 {
            // Discs with arcs around some, arcs alone, and labels left unused.
            let (w, h) = (rng.random_range(40..160), rng.random_range(40..160));
            let mut p = Plane::filled(w, h, 0u32);
            let mut n = 0u32;
            for _ in 0..rng.random_range(1..6) {
                let c = [
                    rng.random_range(0.0..w as f64),
                    rng.random_range(0.0..h as f64),
                ];
                let r = rng.random_range(3.0..25.0);
                let ring = (r + rng.random_range(1.0..8.0), 0.0);
                let ring = (ring.0, ring.0 + rng.random_range(1.0..4.0));
                let a0 = rng.random_range(-3.1..2.0);
                let arc = (a0, a0 + rng.random_range(0.3..2.5));
                let body = rng.random_bool(0.8);
                n += 2;
                for y in 0..h {
                    for x in 0..w {
                        let (dx, dy) = (x as f64 - c[0], y as f64 - c[1]);
                        let (d, a) = (dx.hypot(dy), dy.atan2(dx));
                        if body && d <= r {
                            *p.get_mut(x, y) = n - 1;
                        } else if d >= ring.0 && d <= ring.1 && a >= arc.0 && a <= arc.1 {
                            *p.get_mut(x, y) = n;
                        }
                    }
                }
            }
            let mut q = p.clone();
            let fast = absorb_rings(&mut p, n);
            assert_eq!(fast, absorb_rings_reference(&mut q, n));
            assert_eq!(p, q);
            absorbed += (n - fast.0) as usize;
        }
        assert!(absorbed > 20, "{absorbed} labels absorbed or missing");
    }

    /// A band `r0..r1` round `c` between angles `a0..a1` (radians), label 1, in 160×140.
    fn band(c: [f64; 2], (r0, r1): (f64, f64), (a0, a1): (f64, f64)) -> Plane<u32> {
        let mut p = Plane::filled(160, 140, 0u32);
        for y in 0..140usize {
            for x in 0..160usize {
                let (dx, dy) = (x as f64 - c[0], (y as f64 - c[1]) * 1.25);
                let (d, a) = (dx.hypot(dy), dy.atan2(dx));
                if d >= r0 && d <= r1 && a >= a0 && a <= a1 {
                    *p.get_mut(x, y) = 1;
                }
            }
        }
        p
    }

    #[test]
    fn a_rim_open_on_one_side_is_closed_and_a_short_arc_is_not() {
        // A flat-topped cell's rim seen at a slant: 270° of a 7 px band round an ellipse of
        // semi-axes 40 and 32 px.
        let mut p = band([80.0, 70.0], (33.0, 40.0), (-2.4, 2.4));
        let arc = p.data.iter().filter(|&&l| l == 1).count();
        let (n, starts) = absorb_rings(&mut p, 1);
        assert_eq!(n, 1);
        let (mut area, mut sx, mut sy) = (0.0, 0.0, 0.0);
        for y in 0..p.height {
            for x in 0..p.width {
                if *p.get(x, y) == 1 {
                    area += 1.0;
                    sx += x as f64;
                    sy += y as f64;
                }
            }
        }
        // The ellipse to the band's outer edge: π·40·32 px.
        let disc = std::f64::consts::PI * 40.0 * 32.0;
        assert!(
            (area / disc - 1.0).abs() < 0.08,
            "{area} of {disc} ({arc} in the arc)"
        );
        assert!((sx / area - 80.0).hypot(sy / area - 70.0) < 1.0);
        // The trace starts on the filled region's first raster pixel.
        let first = (0..p.height)
            .flat_map(|y| (0..p.width).map(move |x| (x, y)))
            .find(|&(x, y)| *p.get(x, y) == 1)
            .unwrap();
        assert_eq!(starts[1], [first.0 as u32, first.1 as u32]);
        // 150° of the same band: a hook, left as it is.
        let mut q = band([80.0, 70.0], (33.0, 40.0), (-1.3, 1.3));
        let before = q.clone();
        absorb_rings(&mut q, 1);
        assert_eq!(q, before);
    }

    #[test]
    fn two_compact_cells_and_a_far_arc_stay_apart() {
        // Two discs side by side keep their ids; an arc whose hull reaches no object stays.
        let mut p = Plane::filled(120, 120, 0u32);
        for y in 0..120usize {
            for x in 0..120usize {
                let d = |cx: f64, cy: f64| (x as f64 - cx).hypot(y as f64 - cy);
                if d(30.0, 30.0) <= 15.0 {
                    *p.get_mut(x, y) = 1;
                } else if d(80.0, 30.0) <= 15.0 {
                    *p.get_mut(x, y) = 2;
                } else if (d(60.0, 200.0) - 110.0).abs() <= 1.5 && y > 95 {
                    *p.get_mut(x, y) = 3;
                }
            }
        }
        let before = p.clone();
        let (n, _) = absorb_rings(&mut p, 3);
        assert_eq!(n, 3);
        assert_eq!(p, before);
    }
}
