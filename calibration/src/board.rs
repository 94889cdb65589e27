//! Finding a chessboard's inner corners in one image, in the board's own order.
//!
//! ChESS corners and their grid labels come from `calib-targets-chessboard`; this module
//! picks the board's `cols × rows` window out of the labelled grid, fills a corner the
//! grid missed from the homography of its neighbours, refines every corner to sub-pixel
//! precision (OpenCV's `cornerSubPix`: the point where the image gradients of the window
//! around it are all orthogonal to the rays from it) and orders the corners row after row.

use calib_targets_chessboard::{
    ChessboardDetector, ChessboardParams, GrayImageView, detect_corners,
};
use chess_corners::DetectorConfig;
use nalgebra::{Matrix3, Vector3};
use schemas::Plane;
use std::collections::HashMap;

/// A board's inner corners as found in one image.
#[derive(Clone, Debug, PartialEq)]
pub struct Board {
    /// Inner corners along a row of the board.
    pub cols: usize,
    /// Rows of inner corners.
    pub rows: usize,
    /// The corners, row after row (`cols` per row), in pixels.
    pub corners: Vec<[f64; 2]>,
}

/// Why a board was not found in an image.
#[derive(Clone, Debug, PartialEq)]
pub enum BoardError {
    /// Too few of its corners were seen to place the board.
    NotFound {
        /// Corners of the board's window that the grid labelled.
        seen: usize,
        /// Corners the board has.
        wanted: usize,
    },
    /// Corners were found but do not lie on a regular grid.
    Irregular(String),
}

impl std::fmt::Display for BoardError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            BoardError::NotFound { seen, wanted } => {
                write!(
                    f,
                    "board not found ({seen} of its {wanted} inner corners seen)"
                )
            }
            BoardError::Irregular(why) => write!(f, "corners off the board's grid: {why}"),
        }
    }
}

/// Half-width of the sub-pixel window (an 11×11 window): squares of 25–35 px stay clear of
/// their neighbours' corners even at a slant, where a 23×23 window moved corners by up to
/// 3.6 px (measured with OpenCV on the sample boards).
pub const SUBPIX_HALF_WINDOW: usize = 5;

/// Least share of a board's corners the grid must label for the rest to be filled in.
const MIN_SEEN: f64 = 0.75;

/// Largest distance (in squares) a refined corner may be from where its row and column
/// neighbours put it.
const MAX_OFF_GRID: f64 = 0.25;

/// Finds the `cols × rows` inner corners of a chessboard in `img`.
///
/// Orientation: rows run along the board's longer side when `cols != rows` as given;
/// the first corner is the one with row direction pointing right in the image (down when
/// the row is vertical) and the column direction clockwise from it. A second view of the
/// same board can be brought into the same order with [`Board::align_to`].
pub fn find_board(img: &Plane<u8>, cols: usize, rows: usize) -> Result<Board, BoardError> {
    let view = GrayImageView {
        width: img.width,
        height: img.height,
        data: &img.data,
    };
    let corners = detect_corners(&view, &DetectorConfig::chess());
    let wanted = cols * rows;
    let Ok(detector) = ChessboardDetector::new(ChessboardParams::default()) else {
        return Err(BoardError::NotFound { seen: 0, wanted });
    };
    let Some(det) = detector.detect(&corners) else {
        return Err(BoardError::NotFound { seen: 0, wanted });
    };
    let grid: HashMap<(i32, i32), [f64; 2]> = det
        .corners
        .iter()
        .map(|c| {
            (
                (c.grid.u, c.grid.v),
                [c.position.x as f64, c.position.y as f64],
            )
        })
        .collect();
    // The window of the board's size, in either orientation, that holds the most labels.
    let (mut best, mut seen) = (None, 0);
    let (u0, u1) = bounds(grid.keys().map(|k| k.0));
    let (v0, v1) = bounds(grid.keys().map(|k| k.1));
    for (w, h, swapped) in [(cols, rows, false), (rows, cols, true)] {
        for su in u0..=u1 - w as i32 + 1 {
            for sv in v0..=v1 - h as i32 + 1 {
                let n = (0..w as i32)
                    .flat_map(|a| (0..h as i32).map(move |b| (su + a, sv + b)))
                    .filter(|k| grid.contains_key(k))
                    .count();
                if n > seen {
                    (best, seen) = (Some((su, sv, swapped)), n);
                }
            }
        }
        if cols == rows {
            break;
        }
    }
    let Some((su, sv, swapped)) = best.filter(|_| seen as f64 >= MIN_SEEN * wanted as f64) else {
        return Err(BoardError::NotFound { seen, wanted });
    };
    // Board (a along a row, b down the columns) → grid label.
    let label = |a: usize, b: usize| {
        if swapped {
            (su + b as i32, sv + a as i32)
        } else {
            (su + a as i32, sv + b as i32)
        }
    };
    let known: Vec<([f64; 2], [f64; 2])> = (0..rows)
        .flat_map(|b| (0..cols).map(move |a| (a, b)))
        .filter_map(|(a, b)| grid.get(&label(a, b)).map(|p| ([a as f64, b as f64], *p)))
        .collect();
    let hom = homography(&known)
        .ok_or_else(|| BoardError::Irregular("no homography through the corners".into()))?;
    let mut out = Vec::with_capacity(wanted);
    for b in 0..rows {
        for a in 0..cols {
            let start = grid
                .get(&label(a, b))
                .copied()
                .unwrap_or_else(|| apply(&hom, [a as f64, b as f64]));
            out.push(corner_subpix(img, start, SUBPIX_HALF_WINDOW));
        }
    }
    let mut board = Board {
        cols,
        rows,
        corners: out,
    };
    board.check()?;
    board.canonical();
    Ok(board)
}

fn bounds(v: impl Iterator<Item = i32>) -> (i32, i32) {
    v.fold((i32::MAX, i32::MIN), |(lo, hi), x| (lo.min(x), hi.max(x)))
}

impl Board {
    fn at(&self, a: usize, b: usize) -> [f64; 2] {
        self.corners[b * self.cols + a]
    }

    /// The direction along a row (first to last corner of the middle row) and down a column.
    fn axes(&self) -> ([f64; 2], [f64; 2]) {
        let (p, q) = (
            self.at(0, self.rows / 2),
            self.at(self.cols - 1, self.rows / 2),
        );
        let (r, s) = (
            self.at(self.cols / 2, 0),
            self.at(self.cols / 2, self.rows - 1),
        );
        ([q[0] - p[0], q[1] - p[1]], [s[0] - r[0], s[1] - r[1]])
    }

    /// Reverses the rows (`flip_a`) and/or the columns (`flip_b`).
    fn flip(&mut self, flip_a: bool, flip_b: bool) {
        let (c, r) = (self.cols, self.rows);
        let old = self.corners.clone();
        for b in 0..r {
            for a in 0..c {
                let (sa, sb) = (
                    if flip_a { c - 1 - a } else { a },
                    if flip_b { r - 1 - b } else { b },
                );
                self.corners[b * c + a] = old[sb * c + sa];
            }
        }
    }

    /// Rows pointing right (down when vertical), columns clockwise from them.
    fn canonical(&mut self) {
        let (ra, _) = self.axes();
        let flip_a = if ra[0].abs() >= ra[1].abs() {
            ra[0] < 0.0
        } else {
            ra[1] < 0.0
        };
        self.flip(flip_a, false);
        let (ra, rb) = self.axes();
        self.flip(false, ra[0] * rb[1] - ra[1] * rb[0] < 0.0);
    }

    /// Puts this view's corners in the order of `other`'s (the same board seen by the
    /// other camera): of the board's symmetric orderings, the one whose row and column
    /// directions agree with `other`'s.
    pub fn align_to(&mut self, other: &Board) {
        let (oa, ob) = other.axes();
        let (sa, sb) = self.axes();
        let dot = |p: [f64; 2], q: [f64; 2]| p[0] * q[0] + p[1] * q[1];
        self.flip(dot(oa, sa) < 0.0, dot(ob, sb) < 0.0);
    }

    /// Each inner corner against the mean of its two row (or column) neighbours: a
    /// corner more than [`MAX_OFF_GRID`] of a square off both is not on the board.
    fn check(&self) -> Result<(), BoardError> {
        let (c, r) = (self.cols, self.rows);
        let d = |p: [f64; 2], q: [f64; 2]| (p[0] - q[0]).hypot(p[1] - q[1]);
        let mid = |p: [f64; 2], q: [f64; 2]| [0.5 * (p[0] + q[0]), 0.5 * (p[1] + q[1])];
        for b in 0..r {
            for a in 0..c {
                let p = self.at(a, b);
                if !(p[0].is_finite() && p[1].is_finite()) {
                    return Err(BoardError::Irregular(format!("corner ({a}, {b}) lost")));
                }
                let mut worst: Option<f64> = None;
                if a > 0 && a + 1 < c {
                    let (l, rr) = (self.at(a - 1, b), self.at(a + 1, b));
                    let off = d(p, mid(l, rr)) / (0.5 * d(l, rr)).max(1.0);
                    worst = Some(worst.map_or(off, |w: f64| w.min(off)));
                }
                if b > 0 && b + 1 < r {
                    let (u, dn) = (self.at(a, b - 1), self.at(a, b + 1));
                    let off = d(p, mid(u, dn)) / (0.5 * d(u, dn)).max(1.0);
                    worst = Some(worst.map_or(off, |w: f64| w.min(off)));
                }
                if let Some(off) = worst
                    && off > MAX_OFF_GRID
                {
                    return Err(BoardError::Irregular(format!(
                        "corner ({a}, {b}) at ({:.1}, {:.1}) is {off:.2} of a square off its neighbours' line",
                        p[0], p[1]
                    )));
                }
            }
        }
        Ok(())
    }
}

/// The homography from board coordinates to pixels through `pairs` (normalised DLT).
pub fn homography(pairs: &[([f64; 2], [f64; 2])]) -> Option<Matrix3<f64>> {
    if pairs.len() < 4 {
        return None;
    }
    let norm = |pts: &mut dyn Iterator<Item = [f64; 2]>| {
        let v: Vec<[f64; 2]> = pts.collect();
        let n = v.len() as f64;
        let (mx, my) = v
            .iter()
            .fold((0.0, 0.0), |a, p| (a.0 + p[0] / n, a.1 + p[1] / n));
        let s = v.iter().map(|p| (p[0] - mx).hypot(p[1] - my)).sum::<f64>() / n;
        let k = if s > 0.0 {
            std::f64::consts::SQRT_2 / s
        } else {
            1.0
        };
        Matrix3::new(k, 0.0, -k * mx, 0.0, k, -k * my, 0.0, 0.0, 1.0)
    };
    let ta = norm(&mut pairs.iter().map(|p| p.0));
    let tb = norm(&mut pairs.iter().map(|p| p.1));
    let mut m = nalgebra::DMatrix::<f64>::zeros(2 * pairs.len(), 9);
    for (i, (a, b)) in pairs.iter().enumerate() {
        let pa = ta * Vector3::new(a[0], a[1], 1.0);
        let pb = tb * Vector3::new(b[0], b[1], 1.0);
        let (x, y, u, v) = (pa.x, pa.y, pb.x, pb.y);
        let r0 = [-x, -y, -1.0, 0.0, 0.0, 0.0, u * x, u * y, u];
        let r1 = [0.0, 0.0, 0.0, -x, -y, -1.0, v * x, v * y, v];
        for j in 0..9 {
            m[(2 * i, j)] = r0[j];
            m[(2 * i + 1, j)] = r1[j];
        }
    }
    let ata = m.transpose() * &m;
    let eig = ata.symmetric_eigen();
    let k = eig.eigenvalues.imin();
    let h = eig.eigenvectors.column(k);
    let hn = Matrix3::from_row_slice(h.as_slice());
    let hm = tb.try_inverse()? * hn * ta;
    let s = hm[(2, 2)];
    (s.abs() > 1e-12).then(|| hm / s)
}

/// Where homography `h` takes point `p`.
pub fn apply(h: &Matrix3<f64>, p: [f64; 2]) -> [f64; 2] {
    let q = h * Vector3::new(p[0], p[1], 1.0);
    [q.x / q.z, q.y / q.z]
}

/// Bilinear sample of `img` at `(x, y)`, clamped to the image.
fn sample(img: &Plane<u8>, x: f64, y: f64) -> f64 {
    let x = x.clamp(0.0, (img.width - 1) as f64);
    let y = y.clamp(0.0, (img.height - 1) as f64);
    crate::bilinear(img, x, y).expect("clamped into the image")
}

/// OpenCV's `cornerSubPix`: moves `start` to the point `q` that minimises
/// `Σ w·(∇I(p)·(p − q))²` over the `(2·half + 1)²` window around it (a corner's gradients
/// are all orthogonal to the rays from it), with Gaussian weights, until it moves less
/// than 10⁻³ px or 30 times.
pub fn corner_subpix(img: &Plane<u8>, start: [f64; 2], half: usize) -> [f64; 2] {
    let h = half as i32;
    let mut q = start;
    for _ in 0..30 {
        let (mut a, mut b, mut c, mut bx, mut by) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for j in -h..=h {
            for i in -h..=h {
                let (x, y) = (q[0] + i as f64, q[1] + j as f64);
                let gx = 0.5 * (sample(img, x + 1.0, y) - sample(img, x - 1.0, y));
                let gy = 0.5 * (sample(img, x, y + 1.0) - sample(img, x, y - 1.0));
                let rr = ((i * i + j * j) as f64) / (half * half) as f64;
                let w = (-rr).exp();
                let (gxx, gxy, gyy) = (gx * gx * w, gx * gy * w, gy * gy * w);
                a += gxx;
                b += gxy;
                c += gyy;
                bx += gxx * x + gxy * y;
                by += gxy * x + gyy * y;
            }
        }
        let det = a * c - b * b;
        if det.abs() < 1e-9 {
            break;
        }
        let n = [(c * bx - b * by) / det, (a * by - b * bx) / det];
        let moved = (n[0] - q[0]).hypot(n[1] - q[1]);
        q = n;
        if moved < 1e-3 {
            break;
        }
        if (q[0] - start[0]).hypot(q[1] - start[1]) > half as f64 {
            return [f64::NAN, f64::NAN];
        }
    }
    q
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A rendered chessboard (8×8 samples a pixel) under a homography.
    fn render(w: usize, h: usize, hom: &Matrix3<f64>, squares: (usize, usize)) -> Plane<u8> {
        let inv = hom.try_inverse().unwrap();
        let mut data = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0f64;
                for k in 0..64 {
                    let (dx, dy) = (
                        (k % 8) as f64 / 8.0 + 1.0 / 16.0,
                        (k / 8) as f64 / 8.0 + 1.0 / 16.0,
                    );
                    let p = apply(&inv, [x as f64 + dx - 0.5, y as f64 + dy - 0.5]);
                    let inside = p[0] >= -1.0
                        && p[1] >= -1.0
                        && p[0] < squares.0 as f64 - 1.0
                        && p[1] < squares.1 as f64 - 1.0;
                    let dark = ((p[0] + 1.0).floor() as i64 + (p[1] + 1.0).floor() as i64) % 2 == 0;
                    acc += if inside && dark { 30.0 } else { 220.0 };
                }
                data[y * w + x] = (acc / 64.0).round() as u8;
            }
        }
        Plane::from_vec(w, h, data).unwrap()
    }

    #[test]
    fn a_rendered_board_is_found_to_a_tenth_of_a_pixel_in_order() {
        // 9×6 inner corners (10×7 squares) of 30 px, turned 10° and seen at a slant.
        let hom = Matrix3::new(29.0, -5.0, 150.0, 5.5, 28.0, 120.0, 0.0002, 0.0001, 1.0);
        let img = render(640, 480, &hom, (10, 7));
        let board = find_board(&img, 9, 6).unwrap();
        assert_eq!(board.corners.len(), 54);
        for b in 0..6 {
            for a in 0..9 {
                let truth = apply(&hom, [a as f64, b as f64]);
                let p = board.at(a, b);
                let e = (p[0] - truth[0]).hypot(p[1] - truth[1]);
                assert!(
                    e < 0.1,
                    "corner ({a}, {b}) at {p:?}, truth {truth:?}: {e:.3} px"
                );
            }
        }
        // The same board upside down in the image still lists its corners row after row
        // with rows pointing right.
        let flip = Matrix3::new(-1.0, 0.0, 8.0, 0.0, -1.0, 5.0, 0.0, 0.0, 1.0);
        let img = render(640, 480, &(hom * flip), (10, 7));
        let board = find_board(&img, 9, 6).unwrap();
        let (ra, rb) = board.axes();
        assert!(ra[0] > 0.0 && ra[0] * rb[1] - ra[1] * rb[0] > 0.0);
    }

    #[test]
    fn a_blank_image_has_no_board() {
        let img = Plane::from_vec(200, 100, vec![128u8; 200 * 100]).unwrap();
        assert!(matches!(
            find_board(&img, 9, 6),
            Err(BoardError::NotFound { .. })
        ));
    }

    #[test]
    fn subpix_finds_an_exact_corner_from_two_pixels_away() {
        let hom = Matrix3::new(30.0, 0.0, 100.3, 0.0, 30.0, 80.7, 0.0, 0.0, 1.0);
        let img = render(400, 300, &hom, (8, 6));
        let truth = apply(&hom, [2.0, 2.0]);
        let q = corner_subpix(&img, [truth[0] + 1.6, truth[1] - 1.2], 5);
        assert!(
            (q[0] - truth[0]).hypot(q[1] - truth[1]) < 0.05,
            "{q:?} vs {truth:?}"
        );
    }
}
