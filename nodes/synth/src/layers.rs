//! Synthetic rectified pairs with exact ground truth: layered fronto-parallel planes.
//!
//! Each layer is a rectangle of its own random texture at an integer disparity; larger
//! disparity = nearer, so it hides the layers behind it. The right view shows a layer's
//! texture shifted by its disparity, which makes every non-occluded match exact and the
//! occlusions real. Deterministic given the seed.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use schemas::{DisparityMap, Plane};

/// A rectangle `[x0, x1) × [y0, y1)` (left-image coordinates) at disparity `d`.
#[derive(Clone, Copy, Debug)]
pub struct Layer {
    /// First column.
    pub x0: usize,
    /// First row.
    pub y0: usize,
    /// One past the last column.
    pub x1: usize,
    /// One past the last row.
    pub y1: usize,
    /// Integer disparity.
    pub d: i32,
}

/// A generated pair and its ground truth.
pub struct SyntheticPair {
    /// Left grey image.
    pub left: Plane<u8>,
    /// Right grey image.
    pub right: Plane<u8>,
    /// Left-based ground-truth disparity (every pixel known).
    pub gt_left: DisparityMap,
    /// Right-based ground-truth disparity.
    pub gt_right: DisparityMap,
}

/// Band-limited random texture: the sum of value noise at a few scales plus fine grain.
fn texture(w: usize, h: usize, rng: &mut ChaCha8Rng) -> Vec<f32> {
    let mut out = vec![0f32; w * h];
    for (cell, amp) in [(16usize, 50f32), (6, 40.0), (2, 30.0)] {
        let gw = w / cell + 2;
        let gh = h / cell + 2;
        let grid: Vec<f32> = (0..gw * gh).map(|_| rng.random_range(-1.0..1.0)).collect();
        for y in 0..h {
            let fy = y as f32 / cell as f32;
            let (iy, ty) = (fy as usize, fy.fract());
            for x in 0..w {
                let fx = x as f32 / cell as f32;
                let (ix, tx) = (fx as usize, fx.fract());
                let g = |a: usize, b: usize| grid[b * gw + a];
                let top = g(ix, iy) * (1.0 - tx) + g(ix + 1, iy) * tx;
                let bot = g(ix, iy + 1) * (1.0 - tx) + g(ix + 1, iy + 1) * tx;
                out[y * w + x] += amp * (top * (1.0 - ty) + bot * ty);
            }
        }
    }
    for v in out.iter_mut() {
        *v += rng.random_range(-12.0..12.0);
    }
    out
}

/// Renders a scene: `background` disparity everywhere plus `layers` drawn in order of
/// increasing disparity (nearer on top).
pub fn render(w: usize, h: usize, background: i32, layers: &[Layer], seed: u64) -> SyntheticPair {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut all = vec![Layer {
        x0: 0,
        y0: 0,
        x1: usize::MAX,
        y1: usize::MAX,
        d: background,
    }];
    let mut sorted = layers.to_vec();
    sorted.sort_by_key(|l| l.d);
    all.extend(sorted);
    // Texture coordinates are left-image columns, so a margin covers every shift.
    let margin = all
        .iter()
        .map(|l| l.d.unsigned_abs() as usize)
        .max()
        .unwrap_or(0)
        + 1;
    let tw = w + 2 * margin;
    let textures: Vec<Vec<f32>> = all.iter().map(|_| texture(tw, h, &mut rng)).collect();
    let covers = |l: &Layer, x: i64, y: usize| -> bool {
        x >= l.x0 as i64 && x < l.x1.min(i64::MAX as usize) as i64 && y >= l.y0 && y < l.y1
    };
    // For a view, the frontmost layer at a pixel; `shift` maps view column to left column.
    let view = |right: bool| -> (Plane<u8>, DisparityMap) {
        let mut img = Plane::filled(w, h, 0u8);
        let mut gt = Plane::filled(w, h, 0f32);
        for y in 0..h {
            for x in 0..w {
                let mut hit = 0;
                for (k, l) in all.iter().enumerate() {
                    let lx = if right {
                        x as i64 + l.d as i64
                    } else {
                        x as i64
                    };
                    if covers(l, lx, y) {
                        hit = k;
                    }
                }
                let l = &all[hit];
                let lx = if right {
                    x as i64 + l.d as i64
                } else {
                    x as i64
                };
                let t = textures[hit][y * tw + (lx + margin as i64) as usize];
                *img.get_mut(x, y) = (128.0 + t).clamp(0.0, 255.0) as u8;
                *gt.get_mut(x, y) = l.d as f32;
            }
        }
        (img, gt)
    };
    let (left, gt_left) = view(false);
    let (right, gt_right) = view(true);
    SyntheticPair {
        left,
        right,
        gt_left,
        gt_right,
    }
}

/// A standard test scene: background at `base`, three overlapping rectangles at
/// `base + step`, `base + 2·step` and `base + 3·step`.
pub fn standard_scene(w: usize, h: usize, base: i32, step: i32, seed: u64) -> SyntheticPair {
    let layers = [
        Layer {
            x0: w / 8,
            y0: h / 6,
            x1: w / 2,
            y1: h / 2,
            d: base + step,
        },
        Layer {
            x0: w / 3,
            y0: h / 3,
            x1: 3 * w / 4,
            y1: 5 * h / 6,
            d: base + 2 * step,
        },
        Layer {
            x0: 5 * w / 8,
            y0: h / 8,
            x1: 7 * w / 8,
            y1: h / 3,
            d: base + 3 * step,
        },
    ];
    render(w, h, base, &layers, seed)
}
