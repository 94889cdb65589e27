//! Geometry of the pipette among the cells: convex prisms, the pipette body as a segment,
//! and exact distances between them.
//!
//! Every distance here is from a point moving affinely (along the body, along a path leg)
//! to a convex set, so it is a convex function of the parameters: a golden-section search
//! finds its minimum, and a nested one the minimum over the parallelogram a body sweeps.

/// A point or vector `[x, y, up]` in µm.
pub type P3 = [f64; 3];

/// Between the planner's frame (`[X, Y, up]`, the third coordinate growing upward) and the
/// camera frame every interface uses (`[X, Y, Z]` of the triangulation, Z the depth from
/// the cameras): `[x, y, −z]`, its own inverse.
pub fn flip(p: P3) -> P3 {
    [p[0], p[1], -p[2]]
}

/// `a + s·b`.
pub fn axpy(a: P3, s: f64, b: P3) -> P3 {
    [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]]
}

/// `b − a`.
pub fn sub(b: P3, a: P3) -> P3 {
    [b[0] - a[0], b[1] - a[1], b[2] - a[2]]
}

/// Euclidean length.
pub fn norm(v: P3) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

/// Distance between two points.
pub fn dist(a: P3, b: P3) -> f64 {
    norm(sub(b, a))
}

/// A convex polygon (counter-clockwise in x-y) extruded between two heights: a cell as an
/// obstacle.
#[derive(Clone, Debug, PartialEq)]
pub struct Prism {
    /// Vertices, counter-clockwise, at least one.
    pub poly: Vec<[f64; 2]>,
    /// Bottom height.
    pub zlo: f64,
    /// Top height.
    pub zhi: f64,
}

/// The convex hull of `pts`, counter-clockwise (Andrew's monotone chain); duplicates and
/// collinear points are dropped.
pub fn convex_hull(pts: &[[f64; 2]]) -> Vec<[f64; 2]> {
    let mut p: Vec<[f64; 2]> = pts.to_vec();
    p.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    p.dedup();
    if p.len() < 3 {
        return p;
    }
    let cross = |o: [f64; 2], a: [f64; 2], b: [f64; 2]| {
        (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
    };
    let mut hull: Vec<[f64; 2]> = Vec::with_capacity(2 * p.len());
    for pass in 0..2 {
        let start = hull.len();
        let iter: Box<dyn Iterator<Item = &[f64; 2]>> = if pass == 0 {
            Box::new(p.iter())
        } else {
            Box::new(p.iter().rev())
        };
        for &q in iter {
            while hull.len() >= start + 2
                && cross(hull[hull.len() - 2], hull[hull.len() - 1], q) <= 0.0
            {
                hull.pop();
            }
            hull.push(q);
        }
        hull.pop();
    }
    hull
}

impl Prism {
    /// Distance in x-y from `(x, y)` to the polygon (0 inside).
    pub fn dist_xy(&self, x: f64, y: f64) -> f64 {
        let n = self.poly.len();
        if n == 1 {
            return (x - self.poly[0][0]).hypot(y - self.poly[0][1]);
        }
        let mut inside = n >= 3;
        let mut best = f64::INFINITY;
        for i in 0..n {
            let a = self.poly[i];
            let b = self.poly[(i + 1) % n];
            let (ex, ey) = (b[0] - a[0], b[1] - a[1]);
            let (px, py) = (x - a[0], y - a[1]);
            // Left of every counter-clockwise edge is inside.
            if ex * py - ey * px < 0.0 {
                inside = false;
            }
            let len2 = ex * ex + ey * ey;
            let t = if len2 > 0.0 {
                ((px * ex + py * ey) / len2).clamp(0.0, 1.0)
            } else {
                0.0
            };
            best = best.min((px - t * ex).hypot(py - t * ey));
        }
        if inside { 0.0 } else { best }
    }

    /// Distance from point `p` to the prism (0 inside): the prism is the product of the
    /// polygon and the height interval, so the two distances add in quadrature.
    pub fn dist_point(&self, p: P3) -> f64 {
        let dz = (self.zlo - p[2]).max(p[2] - self.zhi).max(0.0);
        self.dist_xy(p[0], p[1]).hypot(dz)
    }

    /// Distance from the segment `a + s·u`, `s ∈ [0, len]`, to the prism.
    pub fn dist_segment(&self, a: P3, u: P3, len: f64) -> f64 {
        golden_min(0.0, len, |s| self.dist_point(axpy(a, s, u)))
    }

    /// Distance from the parallelogram the body `tip + s·u` (`s ∈ [0, len]`) sweeps while
    /// the tip moves from `a` to `b`, to the prism.
    pub fn dist_swept(&self, a: P3, b: P3, u: P3, len: f64) -> f64 {
        let d = sub(b, a);
        if norm(d) < 1e-12 {
            return self.dist_segment(a, u, len);
        }
        golden_min(0.0, 1.0, |t| self.dist_segment(axpy(a, t, d), u, len))
    }

    /// The axis-aligned box around the prism: `(min, max)`.
    pub fn bounds(&self) -> (P3, P3) {
        let mut lo = [f64::INFINITY, f64::INFINITY, self.zlo];
        let mut hi = [f64::NEG_INFINITY, f64::NEG_INFINITY, self.zhi];
        for p in &self.poly {
            lo[0] = lo[0].min(p[0]);
            lo[1] = lo[1].min(p[1]);
            hi[0] = hi[0].max(p[0]);
            hi[1] = hi[1].max(p[1]);
        }
        (lo, hi)
    }
}

/// Distance between two axis-aligned boxes (0 when they overlap): a lower bound of the
/// distance between anything inside them.
pub fn box_dist(a: (P3, P3), b: (P3, P3)) -> f64 {
    let mut s = 0.0;
    for k in 0..3 {
        let gap = (b.0[k] - a.1[k]).max(a.0[k] - b.1[k]).max(0.0);
        s += gap * gap;
    }
    s.sqrt()
}

/// The box around the body `tip + s·u` (`s ∈ [0, len]`) swept from tip `a` to tip `b`.
pub fn swept_bounds(a: P3, b: P3, u: P3, len: f64) -> (P3, P3) {
    let corners = [a, b, axpy(a, len, u), axpy(b, len, u)];
    let mut lo = corners[0];
    let mut hi = corners[0];
    for c in &corners[1..] {
        for k in 0..3 {
            lo[k] = lo[k].min(c[k]);
            hi[k] = hi[k].max(c[k]);
        }
    }
    (lo, hi)
}

/// The minimum of a convex function on `[lo, hi]` (golden-section search to 1e-10 of the
/// interval, ends included).
pub fn golden_min(lo: f64, hi: f64, f: impl Fn(f64) -> f64) -> f64 {
    const R: f64 = 0.618_033_988_749_894_8;
    let (mut a, mut b) = (lo, hi);
    let ends = f(lo).min(f(hi));
    if hi - lo <= 0.0 {
        return ends;
    }
    let tol = 1e-10 * (hi - lo);
    let mut c = b - R * (b - a);
    let mut d = a + R * (b - a);
    let (mut fc, mut fd) = (f(c), f(d));
    while b - a > tol {
        if fc <= fd {
            b = d;
            d = c;
            fd = fc;
            c = b - R * (b - a);
            fc = f(c);
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + R * (b - a);
            fd = f(d);
        }
        if fc.min(fd) == 0.0 {
            return 0.0;
        }
    }
    ends.min(fc).min(fd)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square() -> Prism {
        Prism {
            poly: vec![[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]],
            zlo: 0.0,
            zhi: 5.0,
        }
    }

    #[test]
    fn hull_is_counter_clockwise_and_drops_inner_points() {
        let h = convex_hull(&[
            [0.0, 0.0],
            [2.0, 0.0],
            [1.0, 1.0],
            [2.0, 2.0],
            [0.0, 2.0],
            [1.0, 0.0],
        ]);
        assert_eq!(h, vec![[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]]);
    }

    #[test]
    fn point_distances_are_exact() {
        let p = square();
        assert_eq!(p.dist_point([5.0, 5.0, 2.0]), 0.0);
        assert_eq!(p.dist_point([13.0, 5.0, 2.0]), 3.0);
        assert_eq!(p.dist_point([5.0, 5.0, 9.0]), 4.0);
        // 3 beside and 4 above the top edge: 5.
        assert!((p.dist_point([13.0, 5.0, 9.0]) - 5.0).abs() < 1e-12);
        // Corner in x-y.
        assert!((p.dist_point([13.0, 14.0, 1.0]) - 5.0).abs() < 1e-12);
    }

    #[test]
    fn segment_and_swept_distances_find_the_closest_point() {
        let p = square();
        // A horizontal body passing 2 above the top: 2.
        let d = p.dist_segment([-5.0, 5.0, 7.0], [1.0, 0.0, 0.0], 20.0);
        assert!((d - 2.0).abs() < 1e-9, "{d}");
        // A body rising at 45° from a tip 3 beside the prism: its tip is closest.
        let s = std::f64::consts::FRAC_1_SQRT_2;
        let d = p.dist_segment([13.0, 5.0, 1.0], [s, 0.0, s], 50.0);
        assert!((d - 3.0).abs() < 1e-9, "{d}");
        // A vertical body swept across above the prism at 1 above its top.
        let d = p.dist_swept([-10.0, 5.0, 6.0], [20.0, 5.0, 6.0], [0.0, 0.0, 1.0], 30.0);
        assert!((d - 1.0).abs() < 1e-9, "{d}");
        // Swept through it: 0.
        let d = p.dist_swept([-10.0, 5.0, 3.0], [20.0, 5.0, 3.0], [0.0, 0.0, 1.0], 30.0);
        assert_eq!(d, 0.0);
    }

    #[test]
    fn box_distance_is_a_lower_bound() {
        let p = square();
        let b = swept_bounds([20.0, 5.0, 1.0], [30.0, 5.0, 1.0], [1.0, 0.0, 0.0], 5.0);
        assert!((box_dist(p.bounds(), b) - 10.0).abs() < 1e-12);
        assert!(
            box_dist(p.bounds(), b)
                <= p.dist_swept([20.0, 5.0, 1.0], [30.0, 5.0, 1.0], [1.0, 0.0, 0.0], 5.0) + 1e-12
        );
    }
}
