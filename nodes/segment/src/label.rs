//! Connected-component labelling of a binary mask: row runs joined by union-find.

use schemas::{Mask, Plane};

/// Pixel adjacency.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Connectivity {
    /// Edge neighbours only.
    Four,
    /// Edge and corner neighbours.
    Eight,
}

/// The offsets `(dx, dy)` of a pixel's eight neighbours.
pub const NEIGHBOURS: [(i64, i64); 8] = [
    (-1, -1),
    (0, -1),
    (1, -1),
    (-1, 0),
    (1, 0),
    (-1, 1),
    (0, 1),
    (1, 1),
];

/// A run of "on" pixels `[x0, x1)` in row `y`.
#[derive(Clone, Copy)]
struct Run {
    y: usize,
    x0: usize,
    x1: usize,
}

fn find(parent: &mut [u32], mut i: u32) -> u32 {
    while parent[i as usize] != i {
        parent[i as usize] = parent[parent[i as usize] as usize];
        i = parent[i as usize];
    }
    i
}

/// The components of the pixels where `on(value)` holds, as row runs: what a label image
/// holds, without painting one (operations that only count or keep whole components read
/// the runs).
pub struct Components {
    /// Each run `(y, x0, x1, label)`: pixels `[x0, x1)` of row `y`, in raster order, and
    /// its component 1..=n.
    pub runs: Vec<(usize, usize, usize, u32)>,
    /// Number of components, numbered in raster order of their first pixel.
    pub n: u32,
}

/// Pixels a step of [`row_runs`] tests together.
const CHUNK: usize = 32;

/// Calls `run(x0, x1)` for each run `[x0, x1)` of pixels of `row` where `on` holds, left to
/// right. A chunk of [`CHUNK`] pixels all off (or all on, inside a run) is passed at once:
/// its count of on-pixels takes no branch per pixel, where the test pixel by pixel took
/// 5 % of the live graph's CPU over mostly empty masks.
pub(crate) fn row_runs<T>(row: &[T], on: &impl Fn(&T) -> bool, mut run: impl FnMut(usize, usize)) {
    let mut open: Option<usize> = None;
    let mut pixel_by_pixel = |x0: usize, part: &[T], open: &mut Option<usize>| {
        for (x, v) in (x0..).zip(part) {
            match (on(v), *open) {
                (true, None) => *open = Some(x),
                (false, Some(s)) => {
                    run(s, x);
                    *open = None;
                }
                _ => {}
            }
        }
    };
    let mut chunks = row.chunks_exact(CHUNK);
    let mut x0 = 0;
    for part in &mut chunks {
        let count = part.iter().fold(0usize, |a, v| a + usize::from(on(v)));
        match (count, open) {
            (0, None) | (CHUNK, Some(_)) => {}
            _ => pixel_by_pixel(x0, part, &mut open),
        }
        x0 += CHUNK;
    }
    pixel_by_pixel(x0, chunks.remainder(), &mut open);
    if let Some(s) = open {
        run(s, row.len());
    }
}

/// Calls `f(x, label)` for each labelled (non-zero) pixel of a label image's row, left to
/// right, passing a chunk of [`CHUNK`] unlabelled pixels at once (a label image is mostly
/// background; the test pixel by pixel was most of a scan's time).
pub(crate) fn for_each_labelled(row: &[u32], mut f: impl FnMut(usize, u32)) {
    for (c, part) in row.chunks(CHUNK).enumerate() {
        if part.iter().fold(0, |a, &l| a | l) == 0 {
            continue;
        }
        for (x, &l) in (c * CHUNK..).zip(part) {
            if l != 0 {
                f(x, l);
            }
        }
    }
}

/// The components of the pixels where `on(value)` holds (see [`Components`]).
pub fn components_where<T>(
    img: &Plane<T>,
    on: impl Fn(&T) -> bool,
    conn: Connectivity,
) -> Components {
    let h = img.height;
    let mut runs: Vec<Run> = Vec::new();
    let mut row_start = Vec::with_capacity(h + 1);
    for y in 0..h {
        row_start.push(runs.len());
        row_runs(img.row(y), &on, |x0, x1| runs.push(Run { y, x0, x1 }));
    }
    row_start.push(runs.len());
    let mut parent: Vec<u32> = (0..runs.len() as u32).collect();
    // Corner neighbours touch when runs overlap after widening by one column.
    let reach = usize::from(conn == Connectivity::Eight);
    for y in 1..h {
        let (prev, cur) = (
            row_start[y - 1]..row_start[y],
            row_start[y]..row_start[y + 1],
        );
        let mut j = prev.start;
        for i in cur {
            let r = runs[i];
            while j < prev.end && runs[j].x1 + reach <= r.x0 {
                j += 1;
            }
            let mut k = j;
            while k < prev.end && runs[k].x0 < r.x1 + reach {
                let (a, b) = (find(&mut parent, i as u32), find(&mut parent, k as u32));
                if a != b {
                    // The older run stays the root, so roots are in raster order.
                    parent[a.max(b) as usize] = a.min(b);
                }
                k += 1;
            }
        }
    }
    let mut label_of_root = vec![0u32; runs.len()];
    let mut n = 0;
    let mut labelled = Vec::with_capacity(runs.len());
    for (i, r) in runs.iter().enumerate() {
        let root = find(&mut parent, i as u32) as usize;
        if label_of_root[root] == 0 {
            n += 1;
            label_of_root[root] = n;
        }
        labelled.push((r.y, r.x0, r.x1, label_of_root[root]));
    }
    Components { runs: labelled, n }
}

/// Labels the pixels where `on(value)` holds: 0 elsewhere, components 1..=n numbered in raster
/// order of their first pixel. Returns the label image and `n`.
pub fn label_where<T>(
    img: &Plane<T>,
    on: impl Fn(&T) -> bool,
    conn: Connectivity,
) -> (Plane<u32>, u32) {
    let c = components_where(img, on, conn);
    let mut out = Plane::filled(img.width, img.height, 0u32);
    for &(y, x0, x1, l) in &c.runs {
        out.row_mut(y)[x0..x1].fill(l);
    }
    (out, c.n)
}

/// Labels the on-pixels (non-zero) of a mask.
pub fn label(mask: &Mask, conn: Connectivity) -> (Plane<u32>, u32) {
    label_where(mask, |&v| v != 0, conn)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::mask;

    #[test]
    fn corner_contact_joins_only_with_eight_connectivity() {
        let m = mask(&["#..#", ".#..", "..#.", "...."]);
        let (l8, n8) = label(&m, Connectivity::Eight);
        assert_eq!(n8, 2);
        assert_eq!(l8.data[..4], [1, 0, 0, 2]);
        assert_eq!((*l8.get(1, 1), *l8.get(2, 2)), (1, 1));
        let (_, n4) = label(&m, Connectivity::Four);
        assert_eq!(n4, 4);
    }

    #[test]
    fn u_shape_merges_into_one_label_numbered_in_raster_order() {
        let m = mask(&["#.#.#", "#.#.#", "###.#", "....#"]);
        let (l, n) = label(&m, Connectivity::Four);
        assert_eq!(n, 2);
        assert_eq!(l.row(0), &[1, 0, 1, 0, 2]);
        assert_eq!(l.row(2), &[1, 1, 1, 0, 2]);
    }

    #[test]
    fn row_runs_are_the_pixel_by_pixel_runs() {
        // Widths around the chunk, runs of every length, mostly-off and mostly-on rows.
        let mut seed = 7u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 33) as usize
        };
        for w in [0, 1, 5, 31, 32, 33, 63, 64, 65, 100, 257, 1280] {
            for density in [0, 1, 10, 50, 90, 99, 100] {
                for _ in 0..20 {
                    let mut row = vec![0u8; w];
                    let mut x = 0;
                    while x < w {
                        let len = 1 + rnd() % 70;
                        let v = u8::from(rnd() % 100 < density);
                        for p in row.iter_mut().skip(x).take(len) {
                            *p = v;
                        }
                        x += len;
                    }
                    let mut want = Vec::new();
                    let mut x = 0;
                    while x < w {
                        if row[x] != 0 {
                            let x0 = x;
                            while x < w && row[x] != 0 {
                                x += 1;
                            }
                            want.push((x0, x));
                        } else {
                            x += 1;
                        }
                    }
                    let mut got = Vec::new();
                    row_runs(&row, &|&v: &u8| v != 0, |a, b| got.push((a, b)));
                    assert_eq!(got, want, "width {w}, density {density}: {row:?}");
                }
            }
        }
    }

    #[test]
    fn labelled_pixels_come_in_row_order() {
        for w in [0, 3, 32, 33, 70] {
            let row: Vec<u32> = (0..w as u32)
                .map(|x| [0, 0, 7, 0, 2][x as usize % 5] * u32::from(x % 37 > 30 || x < 5))
                .collect();
            let want: Vec<(usize, u32)> = row
                .iter()
                .copied()
                .enumerate()
                .filter(|&(_, l)| l != 0)
                .collect();
            let mut got = Vec::new();
            for_each_labelled(&row, |x, l| got.push((x, l)));
            assert_eq!(got, want, "width {w}");
        }
    }

    #[test]
    fn empty_and_full_masks() {
        let (_, n) = label(&Plane::filled(5, 3, 0u8), Connectivity::Eight);
        assert_eq!(n, 0);
        let (l, n) = label(&Plane::filled(5, 3, 255u8), Connectivity::Eight);
        assert_eq!(n, 1);
        assert!(l.data.iter().all(|&v| v == 1));
    }
}
