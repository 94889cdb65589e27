//! A stereo microscope's raw views, as its cameras give them before any rectification.
//!
//! Both layouts converge on the focal plane (the stage at height 0) from pupils `pupil` µm
//! above it, each view `convergence` degrees off the stage's normal:
//! - **CMO** (common main objective): both paths pass one objective off its axis, so each
//!   camera's image plane is conjugate to the stage plane — its view is the stage seen
//!   obliquely but without keystone — and the objective's distortion is radial about its
//!   axis, off each view's centre (mirrored between the views);
//! - **Greenough**: two objectives, each tilted to the stage: each camera looks along its
//!   own axis, so the stage shows with keystone and its focal plane is tilted — the
//!   defocus blur grows across the field.
//!
//! Each camera is also mounted a little turned, scaled and shifted (drawn from the seed).
//! Rendering is exact in the rays: a camera's raw image and the rectified view of the
//! same centre (what [`Scene`] renders, on a canvas a margin larger) differ by a
//! homography and the distortion, whatever the depth. Then the defocus blur of the
//! stage's distance from each view's focal plane, sensor noise and rounding.

use crate::{Optics, Scene, gaussian_blur};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use schemas::Plane;

/// How a stereo microscope's two paths are built.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum Layout {
    /// Two parallel-axis cameras with shifted sensors: the views come rectified.
    Parallel,
    /// A common-main-objective microscope.
    Cmo,
    /// A Greenough microscope (two tilted objectives).
    Greenough,
}

/// A stereo microscope whose raw views are rendered.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Microscope {
    /// How the paths are built.
    pub layout: Layout,
    /// Each view's angle off the stage's normal, degrees.
    pub convergence_deg: f64,
    /// Distance of the pupils above the focal plane, µm (near-telecentric: 1e5 and more).
    pub pupil: f64,
    /// µm of the stage per pixel at the image's centre.
    pub um_per_px: f64,
    /// Image columns.
    pub width: usize,
    /// Image rows.
    pub height: usize,
    /// The off-axis distortion's largest displacement in the field, px.
    pub distortion: f64,
    /// Numerical aperture of each path (defocus blur circle radius `NA·Δz`).
    pub aperture: f64,
    /// Seed of the cameras' mounting errors.
    pub seed: u64,
}

/// Pixels of canvas beyond the raw image on every side.
const MARGIN: usize = 48;

type M3 = [[f64; 3]; 3];

fn mul(a: &M3, b: &M3) -> M3 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

fn apply(m: &M3, p: [f64; 2]) -> [f64; 2] {
    let v: [f64; 3] = std::array::from_fn(|i| m[i][0] * p[0] + m[i][1] * p[1] + m[i][2]);
    [v[0] / v[2], v[1] / v[2]]
}

fn invert(m: &M3) -> M3 {
    let c = |i: usize, j: usize| {
        let (a, b) = ((i + 1) % 3, (i + 2) % 3);
        let (d, e) = ((j + 1) % 3, (j + 2) % 3);
        m[a][d] * m[b][e] - m[a][e] * m[b][d]
    };
    let det: f64 = (0..3).map(|j| m[0][j] * c(0, j)).sum();
    std::array::from_fn(|i| std::array::from_fn(|j| c(j, i) / det))
}

/// One raw view: the homography from the canvas to its undistorted image, and its
/// distortion (Brown–Conrady about `centre`, normalised by `norm` px).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RawView {
    /// Canvas pixel → undistorted raw pixel.
    pub homography: [[f64; 3]; 3],
    /// The distortion's centre, px (the objective's axis for a CMO).
    pub centre: [f64; 2],
    /// Normalising radius, px.
    pub norm: f64,
    /// Radial terms `k1 k2` and decentring terms `p1 p2`.
    pub k: [f64; 4],
    /// The stage height in focus across the view: `a + b·x` µm at raw column `x`.
    pub focus: [f64; 2],
}

impl RawView {
    /// The raw pixel of undistorted pixel `p`.
    pub fn distort(&self, p: [f64; 2]) -> [f64; 2] {
        let (x, y) = (
            (p[0] - self.centre[0]) / self.norm,
            (p[1] - self.centre[1]) / self.norm,
        );
        let r2 = x * x + y * y;
        let [k1, k2, p1, p2] = self.k;
        let radial = k1 * r2 + k2 * r2 * r2;
        let dx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let dy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        [p[0] + self.norm * dx, p[1] + self.norm * dy]
    }

    /// The undistorted pixel of raw pixel `r` (fixed-point iteration).
    pub fn undistort(&self, r: [f64; 2]) -> [f64; 2] {
        let mut p = r;
        for _ in 0..40 {
            let d = self.distort(p);
            let next = [p[0] + r[0] - d[0], p[1] + r[1] - d[1]];
            let moved = (next[0] - p[0]).abs() + (next[1] - p[1]).abs();
            p = next;
            if moved < 1e-10 {
                break;
            }
        }
        p
    }
}

impl Microscope {
    /// A CMO microscope as the published method's: ±5.5°, pupils 100 mm away, 1 µm per
    /// px, 1280×1024, 3 px of distortion, NA 0.1.
    pub fn cmo() -> Self {
        Self {
            layout: Layout::Cmo,
            convergence_deg: 5.5,
            pupil: 1e5,
            um_per_px: 1.0,
            width: 1280,
            height: 1024,
            distortion: 3.0,
            aperture: 0.1,
            seed: 1,
        }
    }

    /// The rectified canvas's optics: the parallel-axis pair of the same centres, a margin
    /// larger than the raw images (what the [`Scene`] to render must be built with).
    pub fn optics(&self) -> Optics {
        let pitch = 5.0;
        let magnification = pitch / self.um_per_px;
        Optics {
            width: self.width + 2 * MARGIN,
            height: self.height + 2 * MARGIN,
            pixel_pitch: pitch,
            magnification,
            f_eff: self.pupil * magnification,
            baseline: 2.0 * self.pupil * self.convergence_deg.to_radians().tan(),
        }
    }

    /// Both raw views.
    pub fn views(&self) -> [RawView; 2] {
        let optics = self.optics();
        let cal = optics.calibration();
        let f = optics.focal_px();
        let (w, h) = (self.width as f64, self.height as f64);
        let centre = [0.5 * (w - 1.0), 0.5 * (h - 1.0)];
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed ^ 0x0b7_1c5);
        let theta = self.convergence_deg.to_radians();
        [false, true].map(|right| {
            let sign = if right { 1.0 } else { -1.0 };
            let cx = if right { cal.cx_right } else { cal.cx };
            // Canvas pixel → ray in the canvas camera (looking straight down).
            let kc_inv: M3 = [
                [1.0 / f, 0.0, -cx / f],
                [0.0, 1.0 / f, -cal.cy / f],
                [0.0, 0.0, 1.0],
            ];
            let to_image: M3 = match self.layout {
                // The raw camera looks along the ray to the field's centre, its sensor
                // square to that axis.
                Layout::Greenough => {
                    let phi = -sign * theta;
                    let (c, s) = (phi.cos(), phi.sin());
                    // Rᵀ for R turning (0, 0, 1) to (sin φ, 0, cos φ).
                    let rt: M3 = [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]];
                    let fr = f / c;
                    let kr: M3 = [[fr, 0.0, centre[0]], [0.0, fr, centre[1]], [0.0, 0.0, 1.0]];
                    mul(&kr, &mul(&rt, &kc_inv))
                }
                // The sensor conjugate to the stage: the canvas itself, without its margin.
                Layout::Cmo | Layout::Parallel => {
                    let k: M3 = [[f, 0.0, cx], [0.0, f, cal.cy], [0.0, 0.0, 1.0]];
                    let shift: M3 = [
                        [1.0, 0.0, -(MARGIN as f64)],
                        [0.0, 1.0, -(MARGIN as f64)],
                        [0.0, 0.0, 1.0],
                    ];
                    mul(&shift, &mul(&k, &kc_inv))
                }
            };
            // The camera's mounting: turned, scaled and shifted a little about the centre.
            let (roll, scale, t) = if self.layout == Layout::Parallel {
                (0.0, 1.0, [0.0, 0.0])
            } else {
                (
                    rng.random_range(-0.8f64..0.8).to_radians(),
                    1.0 + rng.random_range(-0.005..0.005),
                    [rng.random_range(-8.0..8.0), rng.random_range(-8.0..8.0)],
                )
            };
            let (c, s) = (scale * roll.cos(), scale * roll.sin());
            let mount: M3 = [
                [c, -s, centre[0] - c * centre[0] + s * centre[1] + t[0]],
                [s, c, centre[1] - s * centre[0] - c * centre[1] + t[1]],
                [0.0, 0.0, 1.0],
            ];
            let homography = mul(&mount, &to_image);
            // The objective's axis beside the field, on the side the view comes from.
            let dc = [centre[0] - sign * 0.35 * w, centre[1] + 0.05 * h];
            let norm = 0.5 * w.hypot(h);
            let reach = [[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]]
                .iter()
                .map(|p: &[f64; 2]| (p[0] - dc[0]).hypot(p[1] - dc[1]) / norm)
                .fold(0.0, f64::max);
            let k1 = if self.layout == Layout::Parallel {
                0.0
            } else {
                self.distortion / (norm * reach.powi(3))
            };
            let k = [k1, -0.3 * k1, 0.08 * k1 * sign, -0.05 * k1];
            // The focal plane: the stage for a CMO; square to the view's axis through the
            // field's centre for a Greenough (higher on the side away from the view).
            let focus = match self.layout {
                Layout::Greenough => [0.0, -sign * theta.tan() * self.um_per_px],
                _ => [0.0, 0.0],
            };
            RawView {
                homography,
                centre: dc,
                norm,
                k,
                focus,
            }
        })
    }

    /// Where stage point `[x, y, height]` (µm, `scene`'s frame) shows in the raw views.
    pub fn project(&self, scene: &Scene, p: [f64; 3]) -> [[f64; 2]; 2] {
        let canvas = scene.project(p);
        let views = self.views();
        [0, 1].map(|k| views[k].distort(apply(&views[k].homography, canvas[k])))
    }

    /// Renders `scene` (built with [`Microscope::optics`]) as the two raw views.
    pub fn render(&self, scene: &Scene) -> (Plane<u8>, Plane<u8>) {
        let (cl, cr) = scene.render_means();
        let views = self.views();
        let (w, h) = (self.width, self.height);
        let one = |canvas: &Plane<f64>, view: &RawView, salt: u64| {
            let inv = invert(&view.homography);
            let data: Vec<f64> = (0..w * h)
                .into_par_iter()
                .map(|i| {
                    let raw = [(i % w) as f64, (i / w) as f64];
                    let c = apply(&inv, view.undistort(raw));
                    bilinear(canvas, c[0], c[1])
                })
                .collect();
            let img = Plane::from_vec(w, h, data).expect("size");
            let blurred = self.defocus(&img, view, scene.stage);
            let mut rng = ChaCha8Rng::seed_from_u64(scene.seed ^ salt ^ scene.frame);
            let data = blurred
                .data
                .iter()
                .map(|&v| {
                    (v + scene.look.noise * crate::gauss(&mut rng))
                        .round()
                        .clamp(0.0, 255.0) as u8
                })
                .collect();
            Plane::from_vec(w, h, data).expect("size")
        };
        rayon::join(
            || one(&cl, &views[0], 0x1ef7),
            || one(&cr, &views[1], 0x7197),
        )
    }

    /// The blur of a stage at height `z` across a view: the defocus blur circle's radius
    /// `NA·|z − focus(x)|` as a Gaussian sigma of half of it, over the diffraction limit
    /// (the Airy core's sigma `0.21·λ/NA`, λ 0.55 µm); across the field by blending the
    /// nearest of a few blurs.
    fn defocus(&self, img: &Plane<f64>, view: &RawView, z: f64) -> Plane<f64> {
        let w = img.width;
        let sigma = |x: f64| {
            let dz = z - (view.focus[0] + view.focus[1] * (x - 0.5 * w as f64));
            let diffraction = 0.21 * 0.55 / self.aperture.max(0.01);
            (0.5 * self.aperture * dz.abs()).hypot(diffraction) / self.um_per_px
        };
        let (lo, hi) = (0..=64)
            .map(|i| sigma(w as f64 * i as f64 / 64.0))
            .fold((f64::MAX, f64::MIN), |(a, b), s| (a.min(s), b.max(s)));
        let levels: Vec<f64> = if hi - lo < 0.05 {
            vec![0.5 * (lo + hi)]
        } else {
            (0..5).map(|i| lo + (hi - lo) * i as f64 / 4.0).collect()
        };
        let blurs: Vec<Plane<f64>> = levels.par_iter().map(|&s| gaussian_blur(img, s)).collect();
        if blurs.len() == 1 {
            return blurs.into_iter().next().expect("one");
        }
        let data = (0..img.data.len())
            .map(|i| {
                let s = sigma((i % w) as f64);
                let t = ((s - lo) / (hi - lo) * 4.0).clamp(0.0, 4.0);
                let k = (t.floor() as usize).min(3);
                let f = t - k as f64;
                blurs[k].data[i] * (1.0 - f) + blurs[k + 1].data[i] * f
            })
            .collect();
        Plane::from_vec(w, img.height, data).expect("size")
    }
}

/// Bilinear sample of `p` at `(x, y)`, clamped to its edge.
fn bilinear(p: &Plane<f64>, x: f64, y: f64) -> f64 {
    let x = x.clamp(0.0, (p.width - 1) as f64);
    let y = y.clamp(0.0, (p.height - 1) as f64);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(p.width - 1), (y0 + 1).min(p.height - 1));
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    (p.get(x0, y0) * (1.0 - fx) + p.get(x1, y0) * fx) * (1.0 - fy)
        + (p.get(x0, y1) * (1.0 - fx) + p.get(x1, y1) * fx) * fy
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distortion_inverts_and_the_views_converge_on_the_field_centre() {
        for layout in [Layout::Cmo, Layout::Greenough] {
            let m = Microscope {
                layout,
                ..Microscope::cmo()
            };
            for v in m.views() {
                for p in [[0.0, 0.0], [1279.0, 1023.0], [640.0, 100.0]] {
                    let d = v.distort(p);
                    let u = v.undistort(d);
                    assert!((u[0] - p[0]).abs() < 1e-6 && (u[1] - p[1]).abs() < 1e-6);
                }
            }
            let scene = Scene::target(m.optics(), crate::Look::default(), 0.0, 1);
            let [l, r] = m.project(&scene, [0.0, 0.0, 0.0]);
            // The mounting shifts each view by at most 8 px and the distortion by 3.
            for p in [l, r] {
                assert!(
                    (p[0] - 639.5).abs() < 14.0 && (p[1] - 511.5).abs() < 14.0,
                    "{p:?}"
                );
            }
            // A point raised 10 µm: 2·tan(5.5°)·10 ≈ 1.93 px of disparity.
            let [l2, r2] = m.project(&scene, [0.0, 0.0, 10.0]);
            let d = (l2[0] - r2[0]) - (l[0] - r[0]);
            assert!((d - 1.926).abs() < 0.05, "{layout:?}: {d}");
        }
    }
}
