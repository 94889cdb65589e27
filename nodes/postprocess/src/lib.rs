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

pub use median::median_valid;
use schemas::{DisparityMap, INVALID_DISPARITY};
use serde::{Deserialize, Serialize};

/// How invalid pixels are filled.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Fill {
    /// The smaller disparity of the two nearest valid neighbours.
    #[default]
    Background,
    /// Linear interpolation between the two nearest valid neighbours.
    Linear,
    /// Leave invalid pixels invalid.
    None,
}

/// Post-processing settings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
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

impl Default for PostParams {
    fn default() -> Self {
        Self {
            min_region: 50,
            region_max_diff: 1.0,
            median_radius: 1,
            fill: Fill::Background,
        }
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
pub fn remove_small_regions(map: &mut DisparityMap, min_size: usize, max_diff: f32) -> usize {
    let (w, h) = (map.width, map.height);
    let mut seen = vec![false; w * h];
    let mut stack = Vec::new();
    let mut region = Vec::new();
    let mut removed = 0;
    for start in 0..w * h {
        if seen[start] || !map.data[start].is_finite() {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        region.clear();
        while let Some(i) = stack.pop() {
            region.push(i);
            let (x, y) = (i % w, i / w);
            let d = map.data[i];
            let mut visit = |j: usize| {
                if !seen[j] && map.data[j].is_finite() && (map.data[j] - d).abs() <= max_diff {
                    seen[j] = true;
                    stack.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < w {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - w);
            }
            if y + 1 < h {
                visit(i + w);
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
    let mut empty_rows = Vec::new();
    for y in 0..h {
        if !fill_line(map.row_mut(y), rule) {
            empty_rows.push(y);
        }
    }
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
