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
/// component at least twice its size with that component's id, and renumbers the labels
/// `1..=m` in their old order. Returns `m` and, per new id, where its boundary trace starts
/// (the raster-first pixel of its largest piece, so that an absorbed arc does not become
/// the contour).
pub fn absorb_rings(labels: &mut Plane<u32>, n: u32) -> (u32, Vec<[u32; 2]>) {
    let comps = components(labels, n);
    let into = hosts(&comps, |b, hull| reaches(labels, b as u32, hull));
    renumber(labels, &comps, &into)
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

/// Whether a pixel of label `b` lies strictly inside `hull`: only the hull's box can hold
/// one.
fn reaches(labels: &Plane<u32>, b: u32, hull: &[[f64; 2]]) -> bool {
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for q in hull {
        for k in 0..2 {
            lo[k] = lo[k].min(q[k]);
            hi[k] = hi[k].max(q[k]);
        }
    }
    let (x0, x1) = (
        lo[0].max(0.0) as usize,
        (hi[0] as usize).min(labels.width - 1),
    );
    let (y0, y1) = (
        lo[1].max(0.0) as usize,
        (hi[1] as usize).min(labels.height - 1),
    );
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
