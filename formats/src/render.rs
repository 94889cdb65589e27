//! Pictures for people: segmentation overlays, the variance histogram, label images.

use crate::IoError;
use image::{ImageBuffer, Luma, Rgb, RgbImage};
use imageproc::drawing::{draw_filled_rect_mut, draw_line_segment_mut};
use imageproc::rect::Rect;
use schemas::{Cell, Plane};
use std::path::Path;

/// 3×5 bitmap digits, one row per byte, bit 2 = left column.
const DIGITS: [[u8; 5]; 10] = [
    [7, 5, 5, 5, 7],
    [2, 6, 2, 2, 7],
    [7, 1, 7, 4, 7],
    [7, 1, 7, 1, 7],
    [5, 5, 7, 1, 1],
    [7, 4, 7, 1, 7],
    [7, 4, 7, 5, 7],
    [7, 1, 1, 1, 1],
    [7, 5, 7, 5, 7],
    [7, 5, 7, 1, 7],
];

/// Draws a decimal number with its top-left corner at `(x, y)`, each font pixel `s`×`s`,
/// on a box of colour `bg` so it reads on any picture.
pub fn draw_number(
    img: &mut RgbImage,
    (x, y): (i32, i32),
    n: u32,
    s: u32,
    [colour, bg]: [[u8; 3]; 2],
) {
    let text = n.to_string();
    let (cw, ch) = (4 * s, 6 * s);
    let bw = cw * text.len() as u32 + s;
    draw_filled_rect_mut(img, Rect::at(x, y).of_size(bw, ch + s), Rgb(bg));
    for (k, c) in text.bytes().enumerate() {
        let g = DIGITS[(c - b'0') as usize];
        for (r, bits) in g.iter().enumerate() {
            for col in 0..3 {
                if bits & (4 >> col) != 0 {
                    let px = x + (s + k as u32 * cw + col * s) as i32;
                    let py = y + (s + r as u32 * s) as i32;
                    draw_filled_rect_mut(img, Rect::at(px, py).of_size(s, s), Rgb(colour));
                }
            }
        }
    }
}

/// A distinct colour per cell id.
pub fn cell_colour(id: u32) -> [u8; 3] {
    let t = (id as f32 * 0.618_034).fract();
    crate::colormap(0.15 + 0.85 * t)
}

/// The image with every cell's contour in its colour and its id next to its centroid.
pub fn overlay(rgb: &Plane<[u8; 3]>, cells: &[Cell]) -> RgbImage {
    let mut img = RgbImage::from_fn(rgb.width as u32, rgb.height as u32, |x, y| {
        Rgb(*rgb.get(x as usize, y as usize))
    });
    let s = ((rgb.width.max(rgb.height) / 400) as u32).clamp(1, 4);
    for c in cells {
        let col = Rgb(cell_colour(c.id));
        let n = c.contour.len();
        for i in 0..n {
            let (a, b) = (c.contour[i], c.contour[(i + 1) % n]);
            draw_line_segment_mut(
                &mut img,
                (a[0] as f32, a[1] as f32),
                (b[0] as f32, b[1] as f32),
                col,
            );
        }
        draw_number(
            &mut img,
            (
                c.centroid[0] as i32 - 2 * s as i32,
                c.centroid[1] as i32 - 3 * s as i32,
            ),
            c.id,
            s,
            [[255, 255, 255], [0, 0, 0]],
        );
    }
    img
}

/// The histogram as a bar chart (counts on a log scale, so the few cell pixels show next to
/// the background's peak) with the threshold as a red line, like the paper's Fig. 17.
pub fn histogram_chart(hist: &[u64; 256], threshold: Option<u16>) -> RgbImage {
    let (w, h, pad) = (544u32, 240u32, 10u32);
    let mut img = RgbImage::from_pixel(w, h, Rgb([255, 255, 255]));
    let top = hist.iter().copied().max().unwrap_or(0).max(1) as f64;
    let plot_h = (h - 2 * pad - 20) as f64;
    for (i, &c) in hist.iter().enumerate() {
        if c == 0 {
            continue;
        }
        let bar = ((c as f64).ln_1p() / top.ln_1p() * plot_h).round().max(1.0) as u32;
        let x = (pad + 2 * i as u32) as i32;
        let y = (h - pad - 20 - bar) as i32;
        draw_filled_rect_mut(&mut img, Rect::at(x, y).of_size(2, bar), Rgb([40, 40, 40]));
    }
    let base = (h - pad - 20) as f32;
    draw_line_segment_mut(
        &mut img,
        (pad as f32, base),
        ((pad + 512) as f32, base),
        Rgb([0, 0, 0]),
    );
    for v in [0u32, 64, 128, 192, 255] {
        draw_number(
            &mut img,
            ((pad + 2 * v) as i32 - 4, base as i32 + 4),
            v,
            2,
            [[0, 0, 0], [255, 255, 255]],
        );
    }
    if let Some(t) = threshold.filter(|&t| t <= 255) {
        let x = (pad + 2 * t as u32) as f32;
        draw_line_segment_mut(&mut img, (x, pad as f32), (x, base), Rgb([220, 0, 0]));
        draw_line_segment_mut(
            &mut img,
            (x + 1.0, pad as f32),
            (x + 1.0, base),
            Rgb([220, 0, 0]),
        );
        draw_number(
            &mut img,
            (x as i32 + 4, pad as i32),
            t as u32,
            2,
            [[220, 0, 0], [255, 255, 255]],
        );
    }
    img
}

/// The range-selection curve (the paper's Fig. 12): one point per range tried, left to
/// right, labelled with its radius below, its consistency in per cent on a scale from the
/// lowest tenth below the curve to 100 %; the chosen range (`best`) in red with its
/// per cent above it.
pub fn range_curve_chart(points: &[(u32, f64)], best: usize) -> RgbImage {
    let (w, h, pad) = (560u32, 260u32, 24u32);
    let mut img = RgbImage::from_pixel(w, h, Rgb([255, 255, 255]));
    let (x0, x1) = (pad as f32 + 28.0, (w - pad) as f32);
    let (y_top, y_base) = (pad as f32 + 14.0, (h - pad - 16) as f32);
    let lo = points.iter().map(|p| p.1).fold(1.0f64, f64::min);
    let lo = ((lo * 10.0).floor() / 10.0).clamp(0.0, 0.9);
    let n = points.len().max(2) as f32 - 1.0;
    let at = |i: usize, r: f64| {
        let x = x0 + (x1 - x0) * i as f32 / n;
        let t = ((r - lo) / (1.0 - lo)).clamp(0.0, 1.0) as f32;
        (x, y_base - t * (y_base - y_top))
    };
    let black = Rgb([0, 0, 0]);
    draw_line_segment_mut(&mut img, (x0, y_base), (x1, y_base), black);
    draw_line_segment_mut(&mut img, (x0, y_top), (x0, y_base), black);
    let ink = [[0, 0, 0], [255, 255, 255]];
    for (pct, y) in [((lo * 100.0).round() as u32, y_base), (100, y_top)] {
        draw_number(&mut img, (pad as i32 - 14, y as i32 - 6), pct, 2, ink);
    }
    for (i, w) in points.windows(2).enumerate() {
        let (a, b) = (at(i, w[0].1), at(i + 1, w[1].1));
        draw_line_segment_mut(&mut img, a, b, Rgb([40, 40, 160]));
    }
    for (i, &(radius, r)) in points.iter().enumerate() {
        let (x, y) = at(i, r);
        let red = i == best;
        let colour = if red { [220, 0, 0] } else { [40, 40, 160] };
        draw_filled_rect_mut(
            &mut img,
            Rect::at(x as i32 - 3, y as i32 - 3).of_size(7, 7),
            Rgb(colour),
        );
        let digits = radius.to_string().len() as i32;
        draw_number(
            &mut img,
            (x as i32 - 4 * digits, y_base as i32 + 4),
            radius,
            2,
            ink,
        );
        if red {
            draw_line_segment_mut(&mut img, (x, y + 4.0), (x, y_base), Rgb(colour));
            let pct = (r * 100.0).round() as u32;
            draw_number(
                &mut img,
                (x as i32 - 8, y as i32 - 18),
                pct,
                2,
                [colour, [255, 255, 255]],
            );
        }
    }
    img
}

/// Writes a label image as a 16-bit PNG (labels above 65535 saturate; the caller warns).
pub fn write_labels_png(path: &Path, labels: &Plane<u32>) -> Result<(), IoError> {
    let data: Vec<u16> = labels.data.iter().map(|&l| l.min(65535) as u16).collect();
    let img =
        ImageBuffer::<Luma<u16>, _>::from_raw(labels.width as u32, labels.height as u32, data)
            .expect("size");
    crate::atomic::write_atomically(path, |tmp| {
        img.save(tmp).map_err(|e| IoError::Write {
            path: path.into(),
            reason: e.to_string(),
        })
    })
}

/// The validation split (the paper's Table 2) as one bar: the share of matched pixels
/// consistent exactly (green), off by one (amber) and off by more (red), each labelled
/// with its per cent.
pub fn validation_chart(exact: f64, off_by_one: f64, off_by_more: f64) -> RgbImage {
    let (w, h, pad) = (560u32, 80u32, 20u32);
    let mut img = RgbImage::from_pixel(w, h, Rgb([255, 255, 255]));
    let total = (exact + off_by_one + off_by_more).max(f64::MIN_POSITIVE);
    let span = (w - 2 * pad) as f64;
    let mut x = pad as f64;
    for (share, colour) in [
        (exact, [60, 170, 80]),
        (off_by_one, [240, 170, 40]),
        (off_by_more, [210, 50, 40]),
    ] {
        let bar = (share / total * span).round();
        if bar >= 1.0 {
            draw_filled_rect_mut(
                &mut img,
                Rect::at(x as i32, pad as i32).of_size(bar as u32, 28),
                Rgb(colour),
            );
        }
        let pct = (share * 100.0).round() as u32;
        draw_number(
            &mut img,
            (x as i32, pad as i32 + 34),
            pct,
            2,
            [colour, [255, 255, 255]],
        );
        x += bar;
    }
    img
}

/// Most that [`cloud_view`] stretches depth: a dome cell as high as half its width still
/// looks no taller than wide.
pub const MAX_STRETCH: f64 = 2.0;

/// The point cloud seen from above and to the side (turned 30° about the view's vertical
/// and 35° about its horizontal), fitted to 640×480, far points drawn first: a 3D view
/// that needs no viewer. Depth is shrunk so that its spread is half the wider lateral
/// one, or stretched up to [`MAX_STRETCH`] times where it is less (a street's depth would
/// otherwise fill the view, a microscope's relief vanish from it); the factor comes back
/// with the picture. The fit and the
/// stretch go by the 2nd–98th percentiles, so that a few stray points do not shrink the
/// rest. `points` are `([X, Y, Z], colour)` in any one unit.
pub fn cloud_view(points: &[([f32; 3], [u8; 3])]) -> (RgbImage, f64) {
    let (w, h, pad) = (640u32, 480u32, 16.0f64);
    let mut img = RgbImage::from_pixel(w, h, Rgb([250, 250, 250]));
    if points.is_empty() {
        return (img, 1.0);
    }
    let spread = |v: &mut Vec<f64>| -> (f64, f64) {
        v.sort_by(f64::total_cmp);
        let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
        let (lo, hi) = (at(0.02), at(0.98));
        (0.5 * (lo + hi), (hi - lo).max(f64::MIN_POSITIVE))
    };
    let axis = |k: usize| spread(&mut points.iter().map(|p| f64::from(p.0[k])).collect());
    let ((cx, sx), (cy, sy), (cz, sz)) = (axis(0), axis(1), axis(2));
    let stretch = (0.5 * sx.max(sy) / sz).min(MAX_STRETCH);
    let (a, b) = (30f64.to_radians(), 35f64.to_radians());
    let turned: Vec<([f64; 3], [u8; 3])> = points
        .iter()
        .map(|(p, col)| {
            let (x, y) = (f64::from(p[0]) - cx, f64::from(p[1]) - cy);
            let z = (f64::from(p[2]) - cz) * stretch;
            let (x1, z1) = (x * a.cos() + z * a.sin(), -x * a.sin() + z * a.cos());
            let (y2, z2) = (y * b.cos() - z1 * b.sin(), y * b.sin() + z1 * b.cos());
            ([x1, y2, z2], *col)
        })
        .collect();
    let fit = |k: usize| {
        let (c, s) = spread(&mut turned.iter().map(|p| p.0[k]).collect());
        (c - 0.5 * s, s)
    };
    let ((x0, xs), (y0, ys)) = (fit(0), fit(1));
    let scale = ((w as f64 - 2.0 * pad) / xs).min((h as f64 - 2.0 * pad) / ys);
    let mut order: Vec<usize> = (0..turned.len()).collect();
    order.sort_by(|&i, &j| turned[j].0[2].total_cmp(&turned[i].0[2]));
    for i in order {
        let ([x, y, _], col) = turned[i];
        let px = (pad + (x - x0) * scale).round() as i32;
        let py = (pad + (y - y0) * scale).round() as i32;
        if (0..w as i32 - 1).contains(&px) && (0..h as i32 - 1).contains(&py) {
            draw_filled_rect_mut(&mut img, Rect::at(px, py).of_size(2, 2), Rgb(col));
        }
    }
    (img, stretch)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn digits_draw_their_pixels() {
        let mut img = RgbImage::new(20, 10);
        draw_number(&mut img, (0, 0), 10, 1, [[255, 0, 0], [0, 0, 0]]);
        // "1" middle column top row at x = 1 + 1, y = 1; "0" left column at x = 5.
        assert_eq!(img.get_pixel(2, 1).0, [255, 0, 0]);
        assert_eq!(img.get_pixel(1, 1).0, [0, 0, 0]);
        assert_eq!(img.get_pixel(5, 3).0, [255, 0, 0]);
        assert_eq!(img.get_pixel(6, 3).0, [0, 0, 0]);
    }

    #[test]
    fn histogram_marks_the_threshold_in_red() {
        let mut h = [0u64; 256];
        h[10] = 1000;
        h[200] = 5;
        let img = histogram_chart(&h, Some(100));
        assert_eq!(img.get_pixel(210, 120).0, [220, 0, 0]);
        // Both bars are drawn, the small one shorter.
        assert_eq!(img.get_pixel(30, 205).0, [40, 40, 40]);
        assert_eq!(img.get_pixel(410, 205).0, [40, 40, 40]);
        assert_eq!(img.get_pixel(410, 40).0, [255, 255, 255]);
        assert_eq!(img.get_pixel(30, 40).0, [40, 40, 40]);
    }

    #[test]
    fn the_range_curve_marks_its_best_range_in_red_above_its_radius() {
        let pts = [
            (1, 0.04),
            (2, 0.33),
            (4, 0.94),
            (5, 0.976),
            (8, 0.96),
            (16, 0.936),
        ];
        let img = range_curve_chart(&pts, 3);
        let red = |x: u32, y: u32| *img.get_pixel(x, y) == Rgb([220, 0, 0]);
        let cols: Vec<u32> = (0..img.width())
            .filter(|&x| (0..img.height()).filter(|&y| red(x, y)).count() > 20)
            .collect();
        // The marker line stands at the fourth of six points: 3/5 of the way along the axis.
        let (x0, x1) = (24.0 + 28.0, 560.0 - 24.0);
        let want = x0 + (x1 - x0) * 3.0 / 5.0;
        assert!(
            !cols.is_empty() && cols.iter().all(|&x| (x as f32 - want).abs() <= 4.0),
            "{cols:?}"
        );
        // The lowest point (4 %) stands 4 % of the way up a scale from 0 % at the axis
        // (y 220) to 100 % (y 38): at y 212.7.
        assert_eq!(*img.get_pixel(54, 213), Rgb([40, 40, 160]));
        assert_eq!(*img.get_pixel(54, 205), Rgb([255, 255, 255]));
    }

    #[test]
    fn the_validation_bar_is_split_by_its_shares() {
        let img = validation_chart(0.5, 0.25, 0.25);
        // 520 px of bar from x = 20: green to 280, amber to 410, red to 540.
        assert_eq!(*img.get_pixel(279, 30), Rgb([60, 170, 80]));
        assert_eq!(*img.get_pixel(281, 30), Rgb([240, 170, 40]));
        assert_eq!(*img.get_pixel(409, 30), Rgb([240, 170, 40]));
        assert_eq!(*img.get_pixel(411, 30), Rgb([210, 50, 40]));
        assert_eq!(*img.get_pixel(541, 30), Rgb([255, 255, 255]));
    }

    #[test]
    fn the_cloud_view_draws_near_points_over_far_ones_and_says_its_stretch() {
        // A flat square of grey points, 100 wide, 1 deep, and one red point in its middle
        // nearer the cameras: the relief is stretched the most allowed and red is on top.
        let mut pts: Vec<([f32; 3], [u8; 3])> = (0..=100)
            .flat_map(|i| {
                (0..=100).map(move |j| ([i as f32, j as f32, 1000.0 + (i % 2) as f32], [90; 3]))
            })
            .collect();
        pts.push(([50.0, 50.0, 990.0], [255, 0, 0]));
        let (img, stretch) = cloud_view(&pts);
        assert_eq!(stretch, MAX_STRETCH);
        let red = img.pixels().filter(|p| **p == Rgb([255, 0, 0])).count();
        assert_eq!(red, 4, "one 2×2 dot, not covered");
        assert!(img.pixels().filter(|p| **p == Rgb([90; 3])).count() > 10_000);
        assert_eq!(cloud_view(&[]).0.dimensions(), (640, 480));
    }
}
