//! A stereo microscope as it is built: two converging, nearly telecentric views of the
//! stage (a common-main-objective or a Greenough microscope, or a bench rig seen close).
//!
//! Each view is a projective camera of the stage's frame — `x, y` along the board, `z` the
//! stage height (µm) — followed by a polynomial image distortion ([`ViewModel`]). A
//! projective camera holds the telecentric limit (its centre at infinity) as well as a
//! pinhole, so nothing is assumed about how far the pupils are; the stage heights fix the
//! metric depth. [`fit_view`] fits one view to a board seen at known stage heights, with
//! the parameters' covariance, and [`Rig::new`] rectifies the pair onto the stage plane:
//! a rectified pixel is a point of the plane at the reference height, seen by each view
//! through its own centre, so the focal plane lies at zero disparity and a point's
//! disparity grows with its height. With both centres at one height above the plane the
//! rectified pair is exactly a parallel-axis pair ([`Rig::calibration`]: focal length
//! `H/s`, principal points offset by `b/s`), which the triangulate node measures in; at
//! the telecentric limit the centres stand [`FAR`] above the plane.

use crate::lm::minimise;
use nalgebra::{DMatrix, DVector, Matrix3, Matrix3x4, Vector3, Vector4};
use schemas::{Calibration, LengthUnit};
use serde::{Deserialize, Serialize};

/// How far above the stage a centre at (or beyond) the telecentric limit is put, µm: a
/// 100 µm cell measured through centres this far differs from the telecentric height by
/// 1e-5 of it, and `b·f` stays far inside what the triangulation computes exactly.
pub const FAR: f64 = 1e7;

/// Distortion terms on the horizontal image coordinate (`x² xy y² x³ x²y xy² y³`), then on
/// the vertical (`x² x³ x²y xy² y³`). The vertical `xy` and `y²` terms are left to the
/// projective camera: its perspective bends lines in just these two ways, so with them both
/// the fit would have no single answer.
const TERMS: usize = 12;
/// Parameters of one view: the camera matrix in normalised coordinates (its last entry 1)
/// and the distortion.
const PARAMS: usize = 11 + TERMS;

fn monomials(x: f64, y: f64) -> [f64; 7] {
    [
        x * x,
        x * y,
        y * y,
        x * x * x,
        x * x * y,
        x * y * y,
        y * y * y,
    ]
}

/// The distortion offset (normalised units) at normalised raw point `(x, y)`.
fn offset(c: &[f64], x: f64, y: f64) -> [f64; 2] {
    let m = monomials(x, y);
    let du: f64 = (0..7).map(|i| c[i] * m[i]).sum();
    let dv = c[7] * m[0] + c[8] * m[3] + c[9] * m[4] + c[10] * m[5] + c[11] * m[6];
    [du, dv]
}

/// One view of the microscope: where a point of the stage's frame shows in the raw image.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewModel {
    /// The 3×4 camera matrix, row by row: the undistorted pixel is `P·(x, y, z, 1)`.
    pub p: [f64; 12],
    /// Centre `[cx, cy]` and scale (px) the distortion is written about.
    pub norm: [f64; 3],
    /// Distortion: undistorted = raw + scale·Σ cᵢ·mᵢ((raw − centre)/scale) (see `TERMS`).
    pub dist: [f64; TERMS],
}

impl ViewModel {
    fn matrix(&self) -> Matrix3x4<f64> {
        Matrix3x4::from_row_slice(&self.p)
    }

    /// The undistorted pixel of raw pixel `raw`.
    pub fn undistort(&self, raw: [f64; 2]) -> [f64; 2] {
        let [cx, cy, s] = self.norm;
        let o = offset(&self.dist, (raw[0] - cx) / s, (raw[1] - cy) / s);
        [raw[0] + s * o[0], raw[1] + s * o[1]]
    }

    /// The raw pixel whose undistorted pixel is `ideal` (fixed-point iteration: the
    /// distortion is a few pixels over a field of a thousand).
    pub fn distort(&self, ideal: [f64; 2]) -> [f64; 2] {
        let [cx, cy, s] = self.norm;
        let mut raw = ideal;
        for _ in 0..30 {
            let o = offset(&self.dist, (raw[0] - cx) / s, (raw[1] - cy) / s);
            let next = [ideal[0] - s * o[0], ideal[1] - s * o[1]];
            let moved = (next[0] - raw[0]).abs() + (next[1] - raw[1]).abs();
            raw = next;
            if moved < 1e-9 {
                break;
            }
        }
        raw
    }

    /// The undistorted pixel of stage point `w` (`None` at the camera's centre).
    pub fn ideal(&self, w: [f64; 3]) -> Option<[f64; 2]> {
        let q = self.matrix() * Vector4::new(w[0], w[1], w[2], 1.0);
        (q.z.abs() > 0.0).then(|| [q.x / q.z, q.y / q.z])
    }

    /// The raw pixel of stage point `w`.
    pub fn project(&self, w: [f64; 3]) -> Option<[f64; 2]> {
        self.ideal(w).map(|i| self.distort(i))
    }

    /// The homography from the plane at height `z` (its `x, y, 1`) to undistorted pixels.
    fn plane(&self, z: f64) -> Matrix3<f64> {
        let p = self.matrix();
        let mut g = Matrix3::zeros();
        for r in 0..3 {
            g[(r, 0)] = p[(r, 0)];
            g[(r, 1)] = p[(r, 1)];
            g[(r, 2)] = p[(r, 2)] * z + p[(r, 3)];
        }
        g
    }

    /// Where on the plane at height `z` the view sees stage point `w` (along its ray).
    fn on_plane(&self, z: f64, w: [f64; 3]) -> Option<[f64; 2]> {
        let q = self.matrix() * Vector4::new(w[0], w[1], w[2], 1.0);
        let x = self.plane(z).try_inverse()? * q;
        (x.z.abs() > 0.0).then(|| [x.x / x.z, x.y / x.z])
    }

    /// The camera's centre, homogeneous (its last coordinate 0 at the telecentric limit).
    pub fn centre(&self) -> Vector4<f64> {
        let p = self.matrix();
        let det = |a: usize, b: usize, c: usize| {
            Matrix3::from_columns(&[p.column(a), p.column(b), p.column(c)]).determinant()
        };
        Vector4::new(det(1, 2, 3), -det(0, 2, 3), det(0, 1, 3), -det(0, 1, 2))
    }
}

/// A board corner seen by a view: its place in the stage's frame (µm) and in the raw image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observation {
    /// `[x, y, z]`: along the board, and the stage height.
    pub world: [f64; 3],
    /// Its raw pixel.
    pub pixel: [f64; 2],
}

/// The normalisation a view is fitted in (well-conditioned normal equations).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Frame {
    wc: [f64; 3],
    ws: f64,
    ic: [f64; 2],
    is: f64,
}

impl Frame {
    fn world(&self, w: [f64; 3]) -> [f64; 3] {
        std::array::from_fn(|i| (w[i] - self.wc[i]) / self.ws)
    }

    /// The physical model of normalised parameters `q`.
    fn model(&self, q: &[f64]) -> ViewModel {
        let mut pn = [0.0; 12];
        pn[..11].copy_from_slice(&q[..11]);
        pn[11] = 1.0;
        let pn = Matrix3x4::from_row_slice(&pn);
        let s = 1.0 / self.ws;
        let aw = nalgebra::Matrix4::new(
            s,
            0.0,
            0.0,
            -self.wc[0] * s,
            0.0,
            s,
            0.0,
            -self.wc[1] * s,
            0.0,
            0.0,
            s,
            -self.wc[2] * s,
            0.0,
            0.0,
            0.0,
            1.0,
        );
        let ai = Matrix3::new(
            self.is, 0.0, self.ic[0], 0.0, self.is, self.ic[1], 0.0, 0.0, 1.0,
        );
        let p = ai * pn * aw;
        let n = p.norm();
        ViewModel {
            p: std::array::from_fn(|i| p[(i / 4, i % 4)] / n),
            norm: [self.ic[0], self.ic[1], self.is],
            dist: std::array::from_fn(|i| q[11 + i]),
        }
    }
}

/// One view fitted: the model, how well it holds, and how well its parameters are known.
#[derive(Clone, Debug)]
pub struct ViewFit {
    /// The fitted view.
    pub model: ViewModel,
    /// Reprojection error, px (RMS over both coordinates).
    pub rms: f64,
    /// How many corners it was fitted to.
    pub corners: usize,
    frame: Frame,
    params: Vec<f64>,
    cov: DMatrix<f64>,
}

impl ViewFit {
    /// The standard error of a quantity `g` of the view (delta method on the parameters'
    /// covariance, central differences).
    fn std_of(&self, g: &dyn Fn(&ViewModel) -> f64) -> f64 {
        let grad = self.gradient(g);
        (grad.transpose() * &self.cov * &grad)[(0, 0)]
            .max(0.0)
            .sqrt()
    }

    fn gradient(&self, g: &dyn Fn(&ViewModel) -> f64) -> DVector<f64> {
        DVector::from_iterator(
            PARAMS,
            (0..PARAMS).map(|j| {
                let h = 1e-6 * self.params[j].abs().max(1e-3);
                let mut q = self.params.clone();
                q[j] += h;
                let a = g(&self.frame.model(&q));
                q[j] -= 2.0 * h;
                let b = g(&self.frame.model(&q));
                (a - b) / (2.0 * h)
            }),
        )
    }
}

fn residuals(f: &Frame, obs: &[([f64; 3], [f64; 2])], q: &[f64], r: &mut Vec<f64>) {
    r.clear();
    for (w, m) in obs {
        let x = [w[0], w[1], w[2], 1.0];
        let row = |k: usize| {
            (0..4)
                .map(|i| {
                    if 4 * k + i == 11 {
                        x[i]
                    } else {
                        q[4 * k + i] * x[i]
                    }
                })
                .sum::<f64>()
        };
        let den = row(2);
        let o = offset(&q[11..], m[0], m[1]);
        r.push(f.is * (row(0) / den - m[0] - o[0]));
        r.push(f.is * (row(1) / den - m[1] - o[1]));
    }
}

/// Fits a view to corners seen at known stage heights in images of `size` (at least 12
/// corners, spread over at least two heights: a single plane leaves the depth free).
pub fn fit_view(obs: &[Observation], size: (usize, usize)) -> Result<ViewFit, String> {
    if obs.len() < 12 {
        return Err(format!("{} corners; at least 12 are needed", obs.len()));
    }
    let mut zs: Vec<f64> = obs.iter().map(|o| o.world[2]).collect();
    zs.sort_by(f64::total_cmp);
    zs.dedup();
    if zs.len() < 2 {
        return Err(format!(
            "every corner lies at one stage height ({} µm): the depth is undetermined; add pairs at three or more stage heights spanning the cells' depth",
            zs[0]
        ));
    }
    let n = obs.len() as f64;
    let wc: [f64; 3] = std::array::from_fn(|i| obs.iter().map(|o| o.world[i]).sum::<f64>() / n);
    let ws = (obs
        .iter()
        .map(|o| (0..3).map(|i| (o.world[i] - wc[i]).powi(2)).sum::<f64>())
        .sum::<f64>()
        / n)
        .sqrt()
        .max(1e-9);
    let frame = Frame {
        wc,
        ws,
        ic: [0.5 * size.0 as f64, 0.5 * size.1 as f64],
        is: 0.5 * size.0.max(size.1) as f64,
    };
    let norm: Vec<([f64; 3], [f64; 2])> = obs
        .iter()
        .map(|o| {
            (
                frame.world(o.world),
                [
                    (o.pixel[0] - frame.ic[0]) / frame.is,
                    (o.pixel[1] - frame.ic[1]) / frame.is,
                ],
            )
        })
        .collect();
    // The linear start (DLT with the last entry 1, no distortion).
    let mut a = DMatrix::<f64>::zeros(2 * norm.len(), 11);
    let mut b = DVector::<f64>::zeros(2 * norm.len());
    for (k, (w, m)) in norm.iter().enumerate() {
        for i in 0..3 {
            a[(2 * k, i)] = w[i];
            a[(2 * k + 1, 4 + i)] = w[i];
            a[(2 * k, 8 + i)] = -m[0] * w[i];
            a[(2 * k + 1, 8 + i)] = -m[1] * w[i];
        }
        a[(2 * k, 3)] = 1.0;
        a[(2 * k + 1, 7)] = 1.0;
        b[2 * k] = m[0];
        b[2 * k + 1] = m[1];
    }
    let start = a
        .clone()
        .svd(true, true)
        .solve(&b, 1e-12)
        .map_err(|e| format!("the linear start failed: {e}"))?;
    let mut q: Vec<f64> = start.iter().copied().chain([0.0; TERMS]).collect();
    let steps = vec![1e-7; PARAMS];
    let res = |q: &[f64], r: &mut Vec<f64>| residuals(&frame, &norm, q, r);
    let cost = minimise(&mut q, &steps, &res, 100);
    let m = 2 * norm.len();
    // The covariance: σ²·(JᵀJ)⁻¹ with σ² the residuals' variance.
    let mut jac = DMatrix::<f64>::zeros(m, PARAMS);
    let (mut rp, mut rm) = (Vec::new(), Vec::new());
    for j in 0..PARAMS {
        let mut t = q.clone();
        t[j] += 1e-7;
        res(&t, &mut rp);
        t[j] -= 2e-7;
        res(&t, &mut rm);
        for i in 0..m {
            jac[(i, j)] = (rp[i] - rm[i]) / 2e-7;
        }
    }
    let sigma2 = cost / (m as f64 - PARAMS as f64).max(1.0);
    let cov = (jac.transpose() * &jac)
        .try_inverse()
        .ok_or("the corners leave the view's model undetermined (its normal matrix is singular): spread the board over the field and the heights")?
        * sigma2;
    Ok(ViewFit {
        model: frame.model(&q),
        rms: (cost / m as f64).sqrt(),
        corners: obs.len(),
        frame,
        params: q,
        cov,
    })
}

/// Both views rectified onto the stage plane at `z_ref`, as a calibration file's
/// `[microscope]` table holds them. Rectified pixel `(u, v)` of either view is the plane
/// point `origin + scale·(u·e1 + v·e2)` with `e2` a quarter turn from `e1`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rig {
    /// Image width (px), raw and rectified.
    pub width: usize,
    /// Image height (px).
    pub height: usize,
    /// The left view.
    pub left: ViewModel,
    /// The right view.
    pub right: ViewModel,
    /// The stage height at zero disparity (the rectification's plane), µm.
    pub z_ref: f64,
    /// The plane point of rectified pixel (0, 0), µm.
    pub origin: [f64; 2],
    /// The rectified rows' direction on the plane (unit; disparity grows along it).
    pub e1: [f64; 2],
    /// The rectified columns' direction on the plane (unit, perpendicular to `e1`).
    pub e2: [f64; 2],
    /// µm of the plane per rectified pixel.
    pub scale: f64,
    /// The part of the rectified frame the board's corners covered, `[u0, v0, u1, v1]` px
    /// (left view, every height): the fit holds there; beyond it the distortion is
    /// extrapolated (a Greenough's heights 9–12σ low 100–160 µm past a 7×5 board's edge).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field: Option<[f64; 4]>,
}

impl Rig {
    /// The rectification of `left` and `right` (images of `size`) onto the plane at `z_ref`:
    /// its rows along the disparity of a point raised at the left view's centre, its pixel
    /// the left view's there, its centre the left view's.
    pub fn new(
        left: ViewModel,
        right: ViewModel,
        size: (usize, usize),
        z_ref: f64,
    ) -> Result<Self, String> {
        let (w, h) = (size.0 as f64, size.1 as f64);
        let gl = left
            .plane(z_ref)
            .try_inverse()
            .ok_or("the left view does not see the stage plane")?;
        let to_plane = |g: &Matrix3<f64>, p: [f64; 2]| {
            let x = g * Vector3::new(p[0], p[1], 1.0);
            [x.x / x.z, x.y / x.z]
        };
        let c = [0.5 * (w - 1.0), 0.5 * (h - 1.0)];
        let f = to_plane(&gl, left.undistort(c));
        // The plane's scale under the left view at its centre.
        let fx = to_plane(&gl, left.undistort([c[0] + 1.0, c[1]]));
        let fy = to_plane(&gl, left.undistort([c[0], c[1] + 1.0]));
        let det = ((fx[0] - f[0]) * (fy[1] - f[1]) - (fx[1] - f[1]) * (fy[0] - f[0])).abs();
        let scale = det.sqrt();
        let dz = 10.0 * scale;
        let raised = [f[0], f[1], z_ref + dz];
        let (ql, qr) = (
            left.on_plane(z_ref, raised).ok_or("no left ray")?,
            right.on_plane(z_ref, raised).ok_or("no right ray")?,
        );
        let d = [ql[0] - qr[0], ql[1] - qr[1]];
        let nd = d[0].hypot(d[1]);
        if !(nd > 1e-6 * dz && scale.is_finite() && scale > 0.0) {
            return Err(
                "the two views see a raised point in the same place: they do not converge (no depth from their disparity)".into(),
            );
        }
        let e1 = [d[0] / nd, d[1] / nd];
        // Rows down the image as in the raw view.
        let mut e2 = [-e1[1], e1[0]];
        let down = [fy[0] - f[0], fy[1] - f[1]];
        if e2[0] * down[0] + e2[1] * down[1] < 0.0 {
            e2 = [-e2[0], -e2[1]];
        }
        let origin = [
            f[0] - scale * (c[0] * e1[0] + c[1] * e2[0]),
            f[1] - scale * (c[0] * e1[1] + c[1] * e2[1]),
        ];
        Ok(Self {
            width: size.0,
            height: size.1,
            left,
            right,
            z_ref,
            origin,
            e1,
            e2,
            scale,
            field: None,
        })
    }

    /// The plane point of rectified pixel `(u, v)`.
    pub fn plane_point(&self, u: f64, v: f64) -> [f64; 2] {
        let e2 = self.e2;
        [
            self.origin[0] + self.scale * (u * self.e1[0] + v * e2[0]),
            self.origin[1] + self.scale * (u * self.e1[1] + v * e2[1]),
        ]
    }

    /// The rectified pixel of plane point `p`.
    pub fn rectified(&self, p: [f64; 2]) -> [f64; 2] {
        let e2 = self.e2;
        let d = [p[0] - self.origin[0], p[1] - self.origin[1]];
        [
            (d[0] * self.e1[0] + d[1] * self.e1[1]) / self.scale,
            (d[0] * e2[0] + d[1] * e2[1]) / self.scale,
        ]
    }

    /// The view `right` or left.
    pub fn view(&self, right: bool) -> &ViewModel {
        if right { &self.right } else { &self.left }
    }

    /// Where rectified pixel `(u, v)` of a view comes from in its raw image.
    pub fn source(&self, right: bool, u: f64, v: f64) -> (f64, f64) {
        let p = self.plane_point(u, v);
        let view = self.view(right);
        let r = view
            .project([p[0], p[1], self.z_ref])
            .unwrap_or([f64::NAN, f64::NAN]);
        (r[0], r[1])
    }

    /// Where a view shows stage point `w` in the rectified image.
    pub fn rectified_of(&self, right: bool, w: [f64; 3]) -> Option<[f64; 2]> {
        self.view(right)
            .on_plane(self.z_ref, w)
            .map(|p| self.rectified(p))
    }

    /// Both centres as points above the plane (µm): at their common height where they are
    /// near enough, each moved along its ray through the field's centre to that height;
    /// beyond [`FAR`] (or at infinity) at `FAR`.
    fn centres(&self) -> [[f64; 3]; 2] {
        let f = self.plane_point(
            0.5 * (self.width as f64 - 1.0),
            0.5 * (self.height as f64 - 1.0),
        );
        let f3 = [f[0], f[1], self.z_ref];
        let dirs = [&self.left, &self.right].map(|v| {
            let c = v.centre();
            // The direction from the field's centre towards the centre, and its distance
            // in height (infinite at the telecentric limit).
            let towards = [c.x - f3[0] * c.w, c.y - f3[1] * c.w, c.z - f3[2] * c.w];
            let sign = if towards[2] < 0.0 { -1.0 } else { 1.0 };
            let dir = towards.map(|t| t * sign);
            let height = if c.w.abs() > 0.0 {
                (c.z / c.w - self.z_ref).abs()
            } else {
                f64::INFINITY
            };
            (dir, height)
        });
        let hh = 0.5 * (dirs[0].1 + dirs[1].1);
        let hh = if hh.is_finite() { hh.min(FAR) } else { FAR };
        dirs.map(|(d, _)| {
            let t = hh / d[2];
            [f3[0] + t * d[0], f3[1] + t * d[1], f3[2] + hh]
        })
    }

    /// The rectified pair as a parallel-axis pair: what the triangulate node measures in
    /// (µm; depth from the centres' height, `x` along the rows).
    pub fn calibration(&self) -> Calibration {
        let [cl, cr] = self.centres();
        let hh = cl[2] - self.z_ref;
        let pl = self.rectified([cl[0], cl[1]]);
        let pr = self.rectified([cr[0], cr[1]]);
        Calibration {
            baseline: (pr[0] - pl[0]) * self.scale,
            focal_px: hh / self.scale,
            cx: pl[0],
            cy: 0.5 * (pl[1] + pr[1]),
            cx_right: pr[0],
            unit: LengthUnit::Um,
        }
    }

    /// How far the parallel-axis pair of [`Rig::calibration`] is from the model over the
    /// field, for points `±span` µm about the plane: the largest row difference between the
    /// views (px) and the largest height error of a point triangulated from its rectified
    /// pixels (µm).
    pub fn holds(&self, span: f64) -> (f64, f64) {
        let cal = self.calibration();
        let (mut rows, mut heights): (f64, f64) = (0.0, 0.0);
        for i in 0..=8 {
            for j in 0..=8 {
                let u = (self.width as f64 - 1.0) * i as f64 / 8.0;
                let v = (self.height as f64 - 1.0) * j as f64 / 8.0;
                let p = self.plane_point(u, v);
                for hgt in [-span, -0.5 * span, 0.5 * span, span] {
                    let w = [p[0], p[1], self.z_ref + hgt];
                    let (Some(l), Some(r)) =
                        (self.rectified_of(false, w), self.rectified_of(true, w))
                    else {
                        continue;
                    };
                    rows = rows.max((l[1] - r[1]).abs());
                    let dp = l[0] - r[0] + cal.cx_right - cal.cx;
                    let z = cal.baseline * cal.focal_px / dp;
                    heights = heights.max((cal.focal_px * self.scale - z - hgt).abs());
                }
            }
        }
        (rows, heights)
    }

    /// The disparity (px, as matched) of a point `h` µm above the plane at the field's
    /// centre.
    pub fn disparity_at(&self, h: f64) -> f64 {
        let c = self.calibration();
        c.baseline * c.focal_px / (c.focal_px * self.scale - h) - (c.cx_right - c.cx)
    }

    /// Checks a table read from a file.
    pub fn check(&self) -> Result<(), String> {
        let finite = self
            .left
            .p
            .iter()
            .chain(&self.right.p)
            .chain(&self.left.dist)
            .chain(&self.right.dist)
            .chain(&self.left.norm)
            .chain(&self.right.norm)
            .chain(&self.origin)
            .chain(&self.e1)
            .chain([&self.z_ref, &self.scale])
            .all(|v| v.is_finite());
        if !finite {
            return Err("[microscope] holds a number that is not finite".into());
        }
        if self.width < 2 || self.height < 2 {
            return Err("[microscope] width and height must be the image size".into());
        }
        let [a, b] = self.e1;
        let [c, d] = self.e2;
        let unit = |x: f64, y: f64| (x.hypot(y) - 1.0).abs() < 1e-6;
        if !(self.scale > 0.0 && unit(a, b) && unit(c, d) && (a * c + b * d).abs() < 1e-6) {
            return Err(
                "[microscope] scale must be positive and e1, e2 perpendicular unit vectors".into(),
            );
        }
        if self.left.norm[2] <= 0.0 || self.right.norm[2] <= 0.0 {
            return Err("[microscope] a view's distortion scale must be positive".into());
        }
        let c = self.calibration();
        crate::file::check(&c, "[microscope]")
    }
}

/// Standard errors of what a microscope calibration measures.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Uncertainty {
    /// µm of the stage plane per pixel, each view, and its standard error.
    pub scale: [[f64; 2]; 2],
    /// Each view's angle from the stage's normal at the field's centre (degrees) and its
    /// standard error.
    pub angle_deg: [[f64; 2]; 2],
    /// Each view's distance from its centre to the plane (µm; infinite at the telecentric
    /// limit) and the standard error of its inverse (1/µm).
    pub pupil: [[f64; 2]; 2],
    /// The disparity a micrometre of height makes at the field's centre (px/µm) and its
    /// standard error.
    pub px_per_um: [f64; 2],
}

/// What a view shows of a point raised `dz` at plane point `f`: its offset on the plane.
fn shift(v: &ViewModel, z_ref: f64, f: [f64; 2], dz: f64) -> [f64; 2] {
    let q = v
        .on_plane(z_ref, [f[0], f[1], z_ref + dz])
        .unwrap_or([f64::NAN; 2]);
    [q[0] - f[0], q[1] - f[1]]
}

/// The standard errors of `rig`'s measures from its views' fits.
pub fn uncertainty(rig: &Rig, fits: [&ViewFit; 2]) -> Uncertainty {
    let f = rig.plane_point(
        0.5 * (rig.width as f64 - 1.0),
        0.5 * (rig.height as f64 - 1.0),
    );
    let z = rig.z_ref;
    let dz = 10.0;
    let scale = |v: &ViewModel| {
        let g = v.plane(z);
        let img = |p: [f64; 2]| {
            let x = g * Vector3::new(p[0], p[1], 1.0);
            [x.x / x.z, x.y / x.z]
        };
        let (a, b, c) = (img(f), img([f[0] + 1.0, f[1]]), img([f[0], f[1] + 1.0]));
        1.0 / ((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))
            .abs()
            .sqrt()
    };
    let angle = |v: &ViewModel| {
        let s = shift(v, z, f, dz);
        (s[0].hypot(s[1]) / dz).atan().to_degrees()
    };
    let inv_pupil = |v: &ViewModel| {
        let c = v.centre();
        if c.z.abs() > 0.0 {
            (c.w / c.z).abs() / (1.0 - z * c.w / c.z).abs().max(1e-12)
        } else {
            0.0
        }
    };
    let along = |v: &ViewModel| {
        let s = shift(v, z, f, dz);
        (s[0] * rig.e1[0] + s[1] * rig.e1[1]) / (rig.scale * dz)
    };
    let each = |g: &dyn Fn(&ViewModel) -> f64| -> [[f64; 2]; 2] {
        [0, 1].map(|k| [g(&fits[k].model), fits[k].std_of(g)])
    };
    let pupil = each(&inv_pupil).map(|[v, s]| [if v > 0.0 { 1.0 / v } else { f64::INFINITY }, s]);
    let (sl, sr) = (fits[0].std_of(&along), fits[1].std_of(&along));
    Uncertainty {
        scale: each(&scale),
        angle_deg: each(&angle),
        pupil,
        px_per_um: [along(&fits[0].model) - along(&fits[1].model), sl.hypot(sr)],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A converging view: a pinhole `pupil` µm above the stage, `angle` degrees off the
    /// stage's normal along x, 1 µm per px, turned `roll` degrees in its image, with a
    /// distortion of `k` (radial, about a point off the image's centre).
    fn view(angle: f64, pupil: f64, roll: f64, k: f64, size: (usize, usize)) -> ViewModel {
        let t = angle.to_radians();
        // Centre at (pupil·tan t, 0, pupil); the image is the plane's, seen from there.
        let c = [pupil * t.tan(), 0.0, pupil];
        let (cr, sr) = (roll.to_radians().cos(), roll.to_radians().sin());
        // Plane point → image: rotate by roll, 1 px per µm, about the image's centre; a
        // point at height z is first carried along its ray to the plane.
        let (w, h) = (size.0 as f64, size.1 as f64);
        // P = A·[I | 0 on the plane] composed with the central projection onto z = 0.
        let proj = Matrix3x4::new(
            c[2], 0.0, -c[0], 0.0, 0.0, c[2], -c[1], 0.0, 0.0, 0.0, -1.0, c[2],
        );
        let a = Matrix3::new(cr, -sr, 0.5 * w, sr, cr, 0.5 * h, 0.0, 0.0, 1.0);
        let p = a * proj;
        let n = p.norm();
        let mut dist = [0.0; TERMS];
        // Radial about (±0.3 w, 0): k·(x − a)·r² expanded is cubic and quadratic terms.
        dist[3] = k;
        dist[5] = k;
        dist[9] = k;
        dist[11] = k;
        dist[0] = -0.9 * k * angle.signum();
        ViewModel {
            p: std::array::from_fn(|i| p[(i / 4, i % 4)] / n),
            norm: [0.5 * w, 0.5 * h, 0.5 * w.max(h)],
            dist,
        }
    }

    fn corners(v: &ViewModel, heights: &[f64], noise: f64, seed: u64) -> Vec<Observation> {
        let mut s = seed;
        let mut rnd = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let mut out = Vec::new();
        for &z in heights {
            for i in 0..9 {
                for j in 0..6 {
                    let w = [-400.0 + 100.0 * i as f64, -250.0 + 100.0 * j as f64, z];
                    let p = v.project(w).unwrap();
                    out.push(Observation {
                        world: w,
                        pixel: [p[0] + noise * rnd(), p[1] + noise * rnd()],
                    });
                }
            }
        }
        out
    }

    #[test]
    fn distortion_inverts() {
        let v = view(5.0, 1e5, 1.0, 0.01, (1280, 1024));
        for p in [[0.0, 0.0], [1279.0, 1023.0], [300.0, 800.0]] {
            let i = v.undistort(p);
            let r = v.distort(i);
            assert!((r[0] - p[0]).abs() < 1e-7 && (r[1] - p[1]).abs() < 1e-7);
        }
    }

    #[test]
    fn a_converging_near_telecentric_pair_fits_rectifies_and_triangulates() {
        let size = (1280, 1024);
        for (pupil, angle) in [(1e5, 5.5), (3e5, 4.0), (1e9, 7.0)] {
            let (l, r) = (
                view(-angle, pupil, 0.4, 0.004, size),
                view(angle, pupil, -0.7, 0.006, size),
            );
            let heights = [-40.0, -30.0, -20.0, -10.0, 0.0, 10.0, 20.0, 30.0, 40.0];
            let (fl, fr) = (
                fit_view(&corners(&l, &heights, 0.05, 1), size).unwrap(),
                fit_view(&corners(&r, &heights, 0.05, 2), size).unwrap(),
            );
            assert!(fl.rms < 0.03 && fr.rms < 0.03, "{} {}", fl.rms, fr.rms);
            let rig = Rig::new(fl.model.clone(), fr.model.clone(), size, 0.0).unwrap();
            rig.check().unwrap();
            let (rows, heights_err) = rig.holds(40.0);
            // Fitted centres a per cent apart in height are put at one: 0.1 % of a height.
            assert!(
                rows < 0.02 && heights_err < 0.1,
                "{pupil}: {rows} {heights_err}"
            );
            // The true pair's disparity per µm: 2·tan(angle)/µm per px.
            let u = uncertainty(&rig, [&fl, &fr]);
            let truth = 2.0 * angle.to_radians().tan();
            assert!(
                (u.px_per_um[0] / truth - 1.0).abs() < 2e-3,
                "{pupil}: {:?} against {truth}",
                u.px_per_um
            );
            assert!(u.px_per_um[1] / u.px_per_um[0] < 1e-3, "{u:?}");
            // A 50 µm step measured from the true views through the fitted rig.
            let cal = rig.calibration();
            let z_of = |h: f64| {
                let w = [123.0, -87.0, h];
                // Through the raw pixels of the true views, undistorted by the fitted ones.
                let raw_l = l.project(w).unwrap();
                let raw_r = r.project(w).unwrap();
                let to_rect = |m: &ViewModel, raw: [f64; 2]| {
                    let i = m.undistort(raw);
                    let g = m.plane(rig.z_ref).try_inverse().unwrap();
                    let x = g * Vector3::new(i[0], i[1], 1.0);
                    rig.rectified([x.x / x.z, x.y / x.z])
                };
                let (a, b) = (to_rect(&rig.left, raw_l), to_rect(&rig.right, raw_r));
                cal.baseline * cal.focal_px / (a[0] - b[0] + cal.cx_right - cal.cx)
            };
            let step = z_of(-25.0) - z_of(25.0);
            eprintln!("{pupil}: step {step} holds {heights_err}");
            assert!((step / 50.0 - 1.0).abs() < 1e-3, "{pupil}: {step}");
        }
    }

    #[test]
    fn one_height_is_refused() {
        let size = (640, 480);
        let v = view(5.0, 1e5, 0.0, 0.0, size);
        let err = fit_view(&corners(&v, &[0.0], 0.05, 3), size).unwrap_err();
        assert!(err.contains("undetermined"), "{err}");
    }
}
