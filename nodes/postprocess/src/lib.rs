//! Post-processing of a validated disparity map, in the paper's order:
//!
//! 1. [`remove_small_regions`]: valid regions (4-connected, neighbours within `max_diff`)
//!    smaller than `min_size` pixels are isolated false matches and become invalid.
//! 2. [`median_valid`]: median smoothing over the valid pixels of each window; invalid
//!    pixels stay invalid.
//! 3. [`fill`]: every invalid pixel takes a value from its valid neighbours along the
//!    scanline — the smaller ("background": occlusions belong to the farther surface) or a
//!    linear interpolation. Rows with no valid pixel are then filled from the rows above
//!    and below with the same rule, so the result is dense whenever anything was matched.

mod median;
pub mod node;

use rayon::prelude::*;

pub use median::median_valid;
use schemas::{DisparityMap, INVALID_DISPARITY};
use serde::{Deserialize, Serialize};

/// How invalid pixels are filled.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum Fill {
    /// The smaller disparity of the two nearest valid neighbours.
    #[default]
    Background,
    /// Linear interpolation between the two nearest valid neighbours.
    Linear,
    /// Leave invalid pixels invalid.
    None,
}

/// Post-processing settings (the `params` of a postprocess node; every key optional).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PostParams {
    /// Valid regions smaller than this many pixels are removed (0 = keep all).
    pub min_region: usize,
    /// Largest disparity step inside one region.
    pub region_max_diff: f32,
    /// Median window radius (0 = no smoothing; 1 = 3×3).
    pub median_radius: usize,
    /// Fill rule for invalid pixels.
    pub fill: Fill,
}

/// Largest median radius: an 11×11 window (a larger one blurs cells away and its cost
/// grows with the square of the radius).
pub const MAX_MEDIAN_RADIUS: usize = 5;

impl PostParams {
    /// For sub-pixel maps (the quality matcher; the node's default): smaller regions still
    /// count as one surface.
    pub const SUBPIXEL: Self = Self {
        min_region: 100,
        region_max_diff: 1.0,
        median_radius: 2,
        fill: Fill::Background,
    };
    /// For whole-pixel maps (the paper matcher).
    pub const WHOLE_PIXEL: Self = Self {
        min_region: 50,
        ..Self::SUBPIXEL
    };
}

impl Default for PostParams {
    fn default() -> Self {
        Self::SUBPIXEL
    }
}

/// Runs the three steps in order.
pub fn postprocess(map: &DisparityMap, p: &PostParams) -> DisparityMap {
    let mut out = map.clone();
    if p.min_region > 0 {
        remove_small_regions(&mut out, p.min_region, p.region_max_diff);
    }
    if p.median_radius > 0 {
        out = median_valid(&out, p.median_radius);
    }
    fill(&mut out, p.fill);
    out
}

/// Invalidates valid regions of fewer than `min_size` pixels (4-connected, neighbours
/// joined when their disparities differ by at most `max_diff`). Returns pixels removed.
///
/// Bands of rows are labelled in parallel ([`label_band`]), each with its own labels; regions
/// that touch across a band seam are then joined (union-find over the labels) and their
/// sizes added before the small ones are dropped.
pub fn remove_small_regions(map: &mut DisparityMap, min_size: usize, max_diff: f32) -> usize {
    let (w, h) = (map.width, map.height);
    if w == 0 || h == 0 {
        return 0;
    }
    let band_rows = h.div_ceil(4 * rayon::current_num_threads()).max(16);
    let joins = |a: f32, b: f32| a.is_finite() && b.is_finite() && (a - b).abs() <= max_diff;
    let data = &map.data;
    // Per band: a label per pixel (u32::MAX = invalid) and the size of each label.
    let bands: Vec<(Vec<u32>, Vec<u32>)> = data
        .par_chunks(band_rows * w)
        .map(|band| label_band(band, w, &joins))
        .collect();
    // Global label = band offset + band label; join across seams.
    let offsets: Vec<u32> = bands
        .iter()
        .scan(0u32, |acc, (_, s)| {
            let o = *acc;
            *acc += s.len() as u32;
            Some(o)
        })
        .collect();
    let total = offsets
        .last()
        .map_or(0, |&o| o as usize + bands.last().map_or(0, |b| b.1.len()));
    let mut parent: Vec<u32> = (0..total as u32).collect();
    fn find(parent: &mut [u32], mut a: u32) -> u32 {
        while parent[a as usize] != a {
            let g = parent[parent[a as usize] as usize];
            parent[a as usize] = g;
            a = g;
        }
        a
    }
    for b in 1..bands.len() {
        let (up, down) = (&bands[b - 1].0, &bands[b].0);
        let above = &up[up.len() - w..];
        let y = b * band_rows;
        for x in 0..w {
            let (la, lb) = (above[x], down[x]);
            if la != u32::MAX && lb != u32::MAX && joins(data[(y - 1) * w + x], data[y * w + x]) {
                let ra = find(&mut parent, offsets[b - 1] + la);
                let rb = find(&mut parent, offsets[b] + lb);
                parent[ra.max(rb) as usize] = ra.min(rb);
            }
        }
    }
    let mut size = vec![0u32; total];
    for (b, (_, sizes)) in bands.iter().enumerate() {
        for (l, &n) in sizes.iter().enumerate() {
            let r = find(&mut parent, offsets[b] + l as u32);
            size[r as usize] += n;
        }
    }
    // Per global label: whether it survives.
    let keep: Vec<bool> = (0..total as u32)
        .map(|l| size[find(&mut parent, l) as usize] as usize >= min_size)
        .collect();
    map.data
        .par_chunks_mut(band_rows * w)
        .zip(&bands)
        .zip(&offsets)
        .map(|((chunk, (label, _)), &o)| {
            let mut removed = 0;
            for (v, &l) in chunk.iter_mut().zip(label) {
                if l != u32::MAX && !keep[(o + l) as usize] {
                    *v = INVALID_DISPARITY;
                    removed += 1;
                }
            }
            removed
        })
        .sum()
}

/// Labels the regions of one band of rows (`w` wide): a label per pixel (`u32::MAX` =
/// invalid) and each label's size. Runs along a row are found first, then runs that
/// touch across rows are joined (union-find over runs): per pixel that is two
/// comparisons and a store, where a flood fill pushes and pops every pixel.
/// Every pixel of a region carries the region's root run; other runs get size 0.
fn label_band(band: &[f32], w: usize, joins: &impl Fn(f32, f32) -> bool) -> (Vec<u32>, Vec<u32>) {
    let mut label = vec![u32::MAX; band.len()];
    // Per run: its first pixel and its length.
    let mut runs: Vec<(usize, u32)> = Vec::new();
    let mut parent: Vec<u32> = Vec::new();
    fn find(parent: &mut [u32], mut a: u32) -> u32 {
        while parent[a as usize] != a {
            let g = parent[parent[a as usize] as usize];
            parent[a as usize] = g;
            a = g;
        }
        a
    }
    for (y, row) in band.chunks(w).enumerate() {
        let o = y * w;
        let mut x = 0;
        while x < w {
            if !row[x].is_finite() {
                x += 1;
                continue;
            }
            let start = x;
            while x + 1 < w && joins(row[x], row[x + 1]) {
                x += 1;
            }
            x += 1;
            let id = runs.len() as u32;
            runs.push((o + start, (x - start) as u32));
            parent.push(id);
            label[o + start..o + x].fill(id);
        }
        if y == 0 {
            continue;
        }
        // Join with the runs above; consecutive pixels mostly repeat the last pair.
        let mut last = (u32::MAX, u32::MAX);
        for x in 0..w {
            let (a, b) = (label[o + x], label[o - w + x]);
            if a == u32::MAX || b == u32::MAX || (a, b) == last {
                continue;
            }
            if joins(band[o + x], band[o - w + x]) {
                last = (a, b);
                let (ra, rb) = (find(&mut parent, a), find(&mut parent, b));
                parent[ra.max(rb) as usize] = ra.min(rb);
            }
        }
    }
    let mut sizes = vec![0u32; runs.len()];
    for (id, &(start, len)) in runs.iter().enumerate() {
        let root = find(&mut parent, id as u32);
        sizes[root as usize] += len;
        if root != id as u32 {
            label[start..start + len as usize].fill(root);
        }
    }
    (label, sizes)
}

/// Fills one line (a row, or a column through `stride`) in place. Returns false when the
/// line holds no valid value.
fn fill_line(line: &mut [f32], rule: Fill) -> bool {
    let n = line.len();
    let mut prev: Option<usize> = None;
    let mut any = false;
    let mut x = 0;
    while x < n {
        if line[x].is_finite() {
            prev = Some(x);
            any = true;
            x += 1;
            continue;
        }
        let start = x;
        while x < n && !line[x].is_finite() {
            x += 1;
        }
        let next = (x < n).then_some(x);
        let (va, vb) = (prev.map(|a| line[a]), next.map(|b| line[b]));
        for (i, slot) in line.iter_mut().enumerate().take(x).skip(start) {
            *slot = match (va, vb) {
                (Some(a), Some(b)) => match rule {
                    Fill::Linear => {
                        let (ia, ib) = (prev.unwrap(), next.unwrap());
                        a + (i - ia) as f32 / (ib - ia) as f32 * (b - a)
                    }
                    _ => a.min(b),
                },
                (Some(a), None) => a,
                (None, Some(b)) => b,
                (None, None) => *slot,
            };
        }
    }
    any
}

/// Fills invalid pixels along scanlines; rows without any valid pixel are filled along
/// columns afterwards.
pub fn fill(map: &mut DisparityMap, rule: Fill) {
    if rule == Fill::None || map.is_empty() {
        return;
    }
    let (w, h) = (map.width, map.height);
    let empty_rows: Vec<usize> = map
        .data
        .par_chunks_mut(w)
        .enumerate()
        .filter_map(|(y, row)| (!fill_line(row, rule)).then_some(y))
        .collect();
    if empty_rows.is_empty() || empty_rows.len() == h {
        return;
    }
    let mut col = vec![0f32; h];
    for x in 0..w {
        for (y, c) in col.iter_mut().enumerate() {
            *c = *map.get(x, y);
        }
        fill_line(&mut col, rule);
        for &y in &empty_rows {
            *map.get_mut(x, y) = col[y];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use schemas::Plane;
    const X: f32 = INVALID_DISPARITY;

    fn row(v: &[f32]) -> DisparityMap {
        Plane::from_vec(v.len(), 1, v.to_vec()).unwrap()
    }

    #[test]
    fn background_fill_takes_the_smaller_neighbour() {
        let mut m = row(&[X, 8.0, X, X, 3.0, X]);
        fill(&mut m, Fill::Background);
        assert_eq!(m.data, vec![8.0, 8.0, 3.0, 3.0, 3.0, 3.0]);
    }

    #[test]
    fn linear_fill_interpolates() {
        let mut m = row(&[X, 8.0, X, X, 2.0, X]);
        fill(&mut m, Fill::Linear);
        assert_eq!(m.data, vec![8.0, 8.0, 6.0, 4.0, 2.0, 2.0]);
    }

    #[test]
    fn empty_rows_are_filled_from_columns() {
        let mut m = Plane::from_vec(2, 3, vec![5.0, 6.0, X, X, 1.0, 9.0]).unwrap();
        fill(&mut m, Fill::Background);
        assert_eq!(m.data, vec![5.0, 6.0, 1.0, 6.0, 1.0, 9.0]);
        let mut none = Plane::from_vec(2, 1, vec![X, X]).unwrap();
        fill(&mut none, Fill::Background);
        assert!(none.data.iter().all(|v| !v.is_finite()));
    }

    /// The definition: flood-fill each region over the whole map, drop it when small.
    fn remove_small_regions_naive(map: &mut DisparityMap, min_size: usize, max_diff: f32) -> usize {
        let (w, h) = (map.width, map.height);
        let mut seen = vec![false; w * h];
        let mut removed = 0;
        for start in 0..w * h {
            if seen[start] || !map.data[start].is_finite() {
                continue;
            }
            seen[start] = true;
            let (mut stack, mut region) = (vec![start], Vec::new());
            while let Some(i) = stack.pop() {
                region.push(i);
                let (x, y) = (i % w, i / w);
                let n = [
                    (x > 0).then(|| i - 1),
                    (x + 1 < w).then(|| i + 1),
                    (y > 0).then(|| i - w),
                    (y + 1 < h).then(|| i + w),
                ];
                for j in n.into_iter().flatten() {
                    let dj = map.data[j];
                    if !seen[j] && dj.is_finite() && (dj - map.data[i]).abs() <= max_diff {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
            if region.len() < min_size {
                for &i in &region {
                    map.data[i] = INVALID_DISPARITY;
                }
                removed += region.len();
            }
        }
        removed
    }

    #[test]
    fn region_removal_equals_one_flood_fill_on_random_maps() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut next = move || rng.random::<u64>();
        // Tall maps, so several bands and seams are crossed by regions of every shape.
        for (w, h, min) in [
            (1, 1, 2),
            (30, 20, 5),
            (64, 148, 12),
            (7, 190, 3),
            (40, 300, 40),
        ] {
            let data = (0..w * h)
                .map(|i| match next() % 6 {
                    0 => INVALID_DISPARITY,
                    1 => (next() % 40) as f32 * 0.7,
                    _ => ((i % w) / 5 + (i / w) / 4) as f32 + (next() % 3) as f32 * 0.5,
                })
                .collect();
            let m = Plane::from_vec(w, h, data).unwrap();
            let (mut a, mut b) = (m.clone(), m.clone());
            let ra = remove_small_regions(&mut a, min, 1.0);
            let rb = remove_small_regions_naive(&mut b, min, 1.0);
            assert_eq!(ra, rb, "{w}x{h}");
            assert!(
                a.data
                    .iter()
                    .zip(&b.data)
                    .all(|(x, y)| x == y || (x.is_infinite() && y.is_infinite()))
            );
            assert!(ra > 0 || w * h == 1, "the map should have small regions");
        }
    }

    #[test]
    fn small_regions_are_removed() {
        // A 2-pixel island of 9s in a region of 1s (which is joined across 1 px steps).
        let mut m = Plane::from_vec(4, 2, vec![1.0, 1.0, 9.0, 9.0, 2.0, 1.0, 1.0, X]).unwrap();
        let removed = remove_small_regions(&mut m, 3, 1.0);
        assert_eq!(removed, 2);
        assert_eq!(m.data, vec![1.0, 1.0, X, X, 2.0, 1.0, 1.0, X]);
    }

    #[test]
    fn median_ignores_invalid_pixels() {
        let m = Plane::from_vec(3, 1, vec![1.0, 7.0, X]).unwrap();
        let out = median_valid(&m, 1);
        assert_eq!(out.data[0], 4.0);
        assert_eq!(out.data[1], 4.0);
        assert!(!out.data[2].is_finite());
        let m = Plane::from_vec(3, 1, vec![1.0, 7.0, 2.0]).unwrap();
        assert_eq!(median_valid(&m, 1).data[1], 2.0);
    }
}
