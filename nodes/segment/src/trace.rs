//! Boundary following by chain code, with the paper's rule for where each search starts.
//!
//! Directions `P0..P7` run counter-clockwise on screen from east: P0 = E, P1 = NE, P2 = N,
//! P3 = NW, P4 = W, P5 = SW, P6 = S, P7 = SE (rows grow downwards). From the current pixel
//! the neighbours are searched in increasing direction order, starting at
//! [`search_start`]; the first one inside the region is the next boundary pixel. The walk
//! keeps the region on its left, so the outer boundary comes out counter-clockwise.

use schemas::Plane;

/// Pixel offsets `(dx, dy)` of directions P0..P7.
pub const DIRECTIONS: [(i32, i32); 8] = [
    (1, 0),
    (1, -1),
    (0, -1),
    (-1, -1),
    (-1, 0),
    (-1, 1),
    (0, 1),
    (1, 1),
];

/// Where the search for the next pixel starts after a move in direction `last`.
///
/// The paper writes the last direction as `i − 1` and starts at `P(i+5)` for `0 < i < 3`
/// and at `P(i−3)` for `3 < i < 8` (mod 8). Both formulas are `last + 6` (mod 8): the
/// search starts 90° clockwise of the last move, on the outside of the region. The two
/// cases it leaves open, `i = 0` (last move P7) and `i = 3` (last move P2), complete the
/// same way: `P5` and `P0`. That start is always outside the region or already known to be
/// a boundary pixel, so no boundary pixel is skipped; the tests check it on every shape
/// class named in the issue and on random shapes against an independent definition.
pub fn search_start(last: usize) -> usize {
    (last + 6) % 8
}

/// Traces the outer boundary of the region `labels == id` that contains `start`, which must
/// be the region's first pixel in raster order. Returns the boundary pixels `[x, y]` in
/// order (counter-clockwise on screen), without repeating the first at the end; a
/// one-pixel-wide part is walked out and back, so its pixels appear twice.
pub fn trace_boundary(labels: &Plane<u32>, id: u32, start: [u32; 2]) -> Vec<[u32; 2]> {
    let (w, h) = (labels.width as i64, labels.height as i64);
    let inside = |x: i64, y: i64| {
        x >= 0 && y >= 0 && x < w && y < h && *labels.get(x as usize, y as usize) == id
    };
    // Above and left of the first raster pixel is outside: pretend we arrived moving south,
    // so the first search starts at P4 (west).
    let step = |p: [u32; 2], last: usize| -> Option<(usize, [u32; 2])> {
        let s = search_start(last);
        (0..8).map(|k| (s + k) % 8).find_map(|d| {
            let (dx, dy) = DIRECTIONS[d];
            let (x, y) = (p[0] as i64 + dx as i64, p[1] as i64 + dy as i64);
            inside(x, y).then_some((d, [x as u32, y as u32]))
        })
    };
    let mut contour = vec![start];
    let Some((d0, second)) = step(start, 6) else {
        return contour;
    };
    let (mut cur, mut last) = (second, d0);
    // The walk is determined by (pixel, last move): when the first move repeats, the
    // boundary is closed.
    loop {
        let (d, next) = step(cur, last).expect("a region pixel reached from a neighbour has one");
        if cur == start && next == second {
            break;
        }
        contour.push(cur);
        cur = next;
        last = d;
    }
    contour
}

/// Length of a closed chain: 1 per axis step, √2 per diagonal step (a single pixel: 0).
pub fn chain_length(contour: &[[u32; 2]]) -> f64 {
    if contour.len() < 2 {
        return 0.0;
    }
    let n = contour.len();
    (0..n)
        .map(|i| {
            let (a, b) = (contour[i], contour[(i + 1) % n]);
            if a[0] != b[0] && a[1] != b[1] {
                std::f64::consts::SQRT_2
            } else {
                1.0
            }
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::label::{Connectivity, label};
    use crate::morph::fill_holes;
    use crate::testutil::mask;
    use proptest::prelude::*;
    use schemas::Mask;
    use std::collections::BTreeSet;

    fn first_pixel(labels: &Plane<u32>, id: u32) -> [u32; 2] {
        let i = labels.data.iter().position(|&l| l == id).unwrap();
        [(i % labels.width) as u32, (i / labels.width) as u32]
    }

    fn trace_only(m: &Mask) -> Vec<[u32; 2]> {
        let (l, n) = label(m, Connectivity::Eight);
        assert_eq!(n, 1);
        trace_boundary(&l, 1, first_pixel(&l, 1))
    }

    /// Pixels of region `id` with an edge neighbour outside it (or the image edge).
    fn boundary_set(labels: &Plane<u32>, id: u32) -> BTreeSet<[u32; 2]> {
        let (w, h) = (labels.width as i64, labels.height as i64);
        let mut s = BTreeSet::new();
        for y in 0..h {
            for x in 0..w {
                if *labels.get(x as usize, y as usize) != id {
                    continue;
                }
                let out = [(1, 0), (-1, 0), (0, 1), (0, -1)].iter().any(|(dx, dy)| {
                    let (a, b) = (x + dx, y + dy);
                    a < 0 || b < 0 || a >= w || b >= h || *labels.get(a as usize, b as usize) != id
                });
                if out {
                    s.insert([x as u32, y as u32]);
                }
            }
        }
        s
    }

    fn assert_closed_chain(c: &[[u32; 2]]) {
        for i in 0..c.len() {
            let (a, b) = (c[i], c[(i + 1) % c.len()]);
            let (dx, dy) = (a[0].abs_diff(b[0]), a[1].abs_diff(b[1]));
            assert!(
                dx <= 1 && dy <= 1 && (dx, dy) != (0, 0) || c.len() == 1,
                "{a:?} → {b:?}"
            );
        }
    }

    /// Traces a one-region mask and checks the chain is closed and visits exactly the
    /// region's boundary pixels.
    fn trace_whole_boundary(m: &Mask) -> Vec<[u32; 2]> {
        let c = trace_only(m);
        assert_closed_chain(&c);
        let (l, _) = label(m, Connectivity::Eight);
        assert_eq!(
            c.iter().copied().collect::<BTreeSet<_>>(),
            boundary_set(&l, 1)
        );
        c
    }

    #[test]
    fn single_pixel() {
        let c = trace_only(&mask(&["...", ".#.", "..."]));
        assert_eq!(c, vec![[1, 1]]);
        assert_eq!(chain_length(&c), 0.0);
    }

    #[test]
    fn one_pixel_wide_line_is_walked_out_and_back() {
        let c = trace_only(&mask(&[".....", ".###.", "....."]));
        assert_eq!(c, vec![[1, 1], [2, 1], [3, 1], [2, 1]]);
        assert_eq!(chain_length(&c), 4.0);
        let d = trace_only(&mask(&["#...", ".#..", "..#."]));
        assert_eq!(d, vec![[0, 0], [1, 1], [2, 2], [1, 1]]);
    }

    #[test]
    fn square_goes_counter_clockwise_on_screen() {
        let c = trace_only(&mask(&["....", ".##.", ".##.", "...."]));
        assert_eq!(c, vec![[1, 1], [1, 2], [2, 2], [2, 1]]);
        assert_eq!(chain_length(&c), 4.0);
    }

    #[test]
    fn ring_with_a_hole_gives_its_outer_boundary() {
        let m = mask(&[
            ".......", ".#####.", ".#...#.", ".#...#.", ".#...#.", ".#####.", ".......",
        ]);
        let c = trace_only(&m);
        assert_eq!(c.len(), 16);
        assert_closed_chain(&c);
        let (l, _) = label(&m, Connectivity::Eight);
        let outer: BTreeSet<_> = boundary_set(&l, 1)
            .into_iter()
            .filter(|p| p[0] == 1 || p[0] == 5 || p[1] == 1 || p[1] == 5)
            .collect();
        assert_eq!(c.iter().copied().collect::<BTreeSet<_>>(), outer);
    }

    #[test]
    fn concave_shape_follows_every_notch() {
        let c = trace_whole_boundary(&mask(&[
            "#.#.#..", "#.#.#..", "#####..", "..#....", "..####.", ".....#.",
        ]));
        assert_eq!(c[..4], [[0, 0], [0, 1], [0, 2], [1, 2]]);
    }

    #[test]
    fn blob_touching_the_border() {
        let c = trace_whole_boundary(&mask(&["###..", "####.", "###..", "##..."]));
        assert_eq!(c[0], [0, 0]);
    }

    #[test]
    fn paper_rule_is_last_plus_six_and_completes_the_open_cases() {
        // i = last + 1: P(i+5) for i = 1, 2; P(i−3) for i = 4..7.
        for i in [1usize, 2] {
            assert_eq!(search_start(i - 1), (i + 5) % 8);
        }
        for i in 4usize..8 {
            assert_eq!(search_start(i - 1), i - 3);
        }
        assert_eq!((search_start(7), search_start(2)), (5, 0));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]
        /// On random hole-free regions the trace visits exactly the pixels with an outside
        /// edge neighbour, each step to an 8-neighbour, and closes.
        #[test]
        fn trace_visits_exactly_the_boundary(bits in proptest::collection::vec(0u8..3, 12 * 10)) {
            let data = bits.iter().map(|&b| if b > 0 { 255 } else { 0 }).collect();
            let m = fill_holes(&Plane::from_vec(12, 10, data).unwrap());
            let (l, n) = label(&m, Connectivity::Eight);
            for id in 1..=n {
                let c = trace_boundary(&l, id, first_pixel(&l, id));
                assert_closed_chain(&c);
                prop_assert_eq!(c.iter().copied().collect::<BTreeSet<_>>(), boundary_set(&l, id));
            }
        }
    }
}
