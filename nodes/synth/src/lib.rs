//! A synthetic stereo light microscope: what its two cameras see, with exact ground truth.
//!
//! Geometry: two parallel-axis pinhole cameras at `X = ∓b/2` (the triangulation frame of
//! `triangulate`), focal length `f = f_eff / pixel_pitch` pixels, the substrate at depth
//! `Z0 = f_eff / magnification` (so one pixel spans `pixel_pitch / magnification` µm there).
//! The sensors are shifted (`cx`, `cx_right`) so both look at the same patch of substrate
//! and the substrate has disparity 0: a convergent microscope after rectification.
//!
//! Scene: cells are ellipsoidal domes standing on the substrate (footprint semi-axes `a`,
//! `b`, rotation, height `h`), textured with procedural noise (or a real cell image) fixed
//! to the cell and shaded by their slope like DIC relief; the substrate is smooth with an
//! illumination gradient and a faint texture; a pipette can enter as a tapered glass tip.
//! Every pixel is the mean of `supersample²` rays intersected exactly with the scene
//! (ray–ellipsoid and ray–sphere quadratics), so the views are sub-pixel correct; then
//! optional defocus blur and per-view sensor noise. Deterministic given the seed.
//!
//! Ground truth: the left disparity and depth at every pixel centre, the left cell labels,
//! and per cell its centroid, area, height, volume and 3D centroid.

pub mod files;
pub mod layers;
pub mod progress;
pub mod raw;
pub mod request;
pub mod tour;
pub mod truth;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use schemas::{Calibration, DisparityMap, LengthUnit, Plane};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// The optics and the sensor.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Optics {
    /// Image columns.
    pub width: usize,
    /// Image rows.
    pub height: usize,
    /// Sensor pixel pitch, µm.
    pub pixel_pitch: f64,
    /// Magnification at the substrate.
    pub magnification: f64,
    /// Effective focal length, µm.
    pub f_eff: f64,
    /// Stereo baseline, µm.
    pub baseline: f64,
}

impl Default for Optics {
    fn default() -> Self {
        // 1 µm per pixel at the substrate, 0.3 px of disparity per µm of height.
        Self {
            width: 640,
            height: 480,
            pixel_pitch: 5.0,
            magnification: 5.0,
            f_eff: 20_000.0,
            baseline: 1_200.0,
        }
    }
}

impl Optics {
    /// Focal length in pixels.
    pub fn focal_px(&self) -> f64 {
        self.f_eff / self.pixel_pitch
    }

    /// Depth of the substrate (stage height 0), µm.
    pub fn working_distance(&self) -> f64 {
        self.f_eff / self.magnification
    }

    /// Micrometres per pixel on the substrate.
    pub fn um_per_px(&self) -> f64 {
        self.pixel_pitch / self.magnification
    }

    /// The rectified calibration that triangulates these views exactly.
    pub fn calibration(&self) -> Calibration {
        let f = self.focal_px();
        let half = 0.5 * self.baseline * f / self.working_distance();
        let c = (self.width as f64 - 1.0) / 2.0;
        Calibration {
            baseline: self.baseline,
            focal_px: f,
            cx: c - half,
            cy: (self.height as f64 - 1.0) / 2.0,
            cx_right: c + half,
            unit: LengthUnit::Um,
        }
    }

    /// Disparity (as the matcher measures it) of a point at depth `z`.
    pub fn disparity_at(&self, z: f64) -> f64 {
        let c = self.calibration();
        self.baseline * c.focal_px / z - (c.cx_right - c.cx)
    }

    /// Disparity per µm of height at the substrate.
    pub fn px_per_um_height(&self) -> f64 {
        let z0 = self.working_distance();
        self.baseline * self.focal_px() / (z0 * z0)
    }
}

/// One cell: an ellipsoidal dome on the substrate.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CellShape {
    /// Footprint centre `[x, y]` on the substrate, µm (origin under the cameras' midpoint).
    pub centre: [f64; 2],
    /// Footprint semi-axes `[a, b]`, µm.
    pub semi_axes: [f64; 2],
    /// Rotation of the `a` axis from +x, radians.
    pub angle: f64,
    /// Height of the top above the substrate, µm.
    pub height: f64,
    /// Offset into the texture, so no two cells look alike.
    pub texture_offset: [f64; 2],
    /// Mean brightness relative to the substrate (grey levels).
    pub brightness: f64,
    /// The height profile across the footprint.
    #[serde(default)]
    pub profile: Profile,
    /// Outline irregularity: relative amplitudes of the footprint radius' 2nd, 3rd and 4th
    /// harmonics, then their phases (radians). All zero: an ellipse.
    #[serde(default)]
    pub outline: [f64; 6],
    /// A fried egg's nucleus: its radius over the footprint's, then its centre's offset
    /// `[u, v]` from the footprint's (in footprint semi-axes, the cell's frame).
    #[serde(default = "centred_nucleus")]
    pub nucleus: [f64; 3],
}

/// A nucleus over the inner [`NUCLEUS`] of the footprint's radius, at its centre.
pub fn centred_nucleus() -> [f64; 3] {
    [NUCLEUS, 0.0, 0.0]
}

/// How a cell's height falls from its top (`h`) to its edge, over the normalised footprint
/// radius ρ (0 at the centre, 1 on the outline).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum Profile {
    /// An ellipsoidal dome, `h·√(1 − ρ²)`: a rounded cell, its flank vertical at the edge.
    #[default]
    Dome,
    /// A paraboloid cap, `h·(1 − ρ²)`: a cell meeting the substrate at an angle.
    Cap,
    /// A flattened spread cell, `h·(1 − ρ⁴)`: a flat top over a thin margin.
    Spread,
    /// A flat-topped spread cell, `h·(1 − ρ⁸)`: a plateau over most of the footprint,
    /// falling steeply at the margin (osteoblasts spread flat on the dish).
    Flat,
    /// A fried egg: a thin spread cytoplasm, `0.3·h·(1 − ρ⁴)`, under a raised nucleus (a
    /// dome over 30–55 % of the footprint's radius, up to 0.3 of it off centre:
    /// `CellShape::nucleus`) whose top is the height.
    FriedEgg,
}

/// A fried egg's nucleus radius over its footprint's, where no other is drawn.
pub const NUCLEUS: f64 = 0.45;

impl Profile {
    /// Every profile, for test matrices.
    pub const ALL: [Profile; 5] = [
        Profile::Dome,
        Profile::Cap,
        Profile::Spread,
        Profile::Flat,
        Profile::FriedEgg,
    ];

    /// Height over the top's, at squared normalised radius `rho2` (< 1); `nucleus2`: the
    /// squared distance from a fried egg's nucleus centre over its radius'.
    fn at(self, rho2: f64, nucleus2: f64) -> f64 {
        match self {
            Profile::Dome => (1.0 - rho2).max(0.0).sqrt(),
            Profile::Cap => (1.0 - rho2).max(0.0),
            Profile::Spread => (1.0 - rho2 * rho2).max(0.0),
            Profile::Flat => (1.0 - (rho2 * rho2) * (rho2 * rho2)).max(0.0),
            Profile::FriedEgg => {
                let cytoplasm = 0.3 * (1.0 - rho2 * rho2).max(0.0);
                let nucleus = (1.0 - nucleus2).max(0.0).sqrt();
                cytoplasm.max(nucleus)
            }
        }
    }
}

impl CellShape {
    /// The outline's radius over the ellipse's in direction `phi` (cell frame).
    fn outline_at(&self, phi: f64) -> f64 {
        let o = &self.outline;
        1.0 + o[0] * (2.0 * phi + o[3]).cos()
            + o[1] * (3.0 * phi + o[4]).cos()
            + o[2] * (4.0 * phi + o[5]).cos()
    }

    /// Whether the shape is the plain ellipsoid, whose rays meet it in closed form.
    fn is_ellipsoid(&self) -> bool {
        self.profile == Profile::Dome && self.outline[..3].iter().all(|a| *a == 0.0)
    }

    /// Squared normalised radius ρ² of the point `(px, py)` in the cell's frame (µm).
    fn rho2(&self, px: f64, py: f64) -> f64 {
        let (u, v) = (px / self.semi_axes[0], py / self.semi_axes[1]);
        let r2 = u * u + v * v;
        if self.is_ellipsoid() {
            return r2;
        }
        r2 / self.outline_at(v.atan2(u)).powi(2)
    }

    /// Height of the surface above the cell's base at `(px, py)` (cell frame), `None`
    /// outside the footprint.
    fn surface(&self, px: f64, py: f64) -> Option<f64> {
        let r2 = self.rho2(px, py);
        (r2 < 1.0).then(|| {
            let (u, v) = (px / self.semi_axes[0], py / self.semi_axes[1]);
            self.height * self.profile.at(r2, self.nucleus2(u, v))
        })
    }

    /// Squared distance of `(u, v)` (in footprint semi-axes) from a fried egg's nucleus'
    /// centre, over its radius' (0 for the other profiles, which have none: the ray march
    /// asks for the surface dozens of times per pixel).
    fn nucleus2(&self, u: f64, v: f64) -> f64 {
        if self.profile != Profile::FriedEgg {
            return 0.0;
        }
        let [r, ou, ov] = self.nucleus;
        ((u - ou).powi(2) + (v - ov).powi(2)) / (r * r).max(1e-12)
    }

    /// Largest footprint radius, µm.
    pub fn reach(&self) -> f64 {
        let o = &self.outline;
        self.semi_axes[0].max(self.semi_axes[1]) * (1.0 + o[0].abs() + o[1].abs() + o[2].abs())
    }

    /// Volume and the height of its centroid above the base, integrated over the footprint.
    fn volume_and_centroid_height(&self) -> (f64, f64) {
        if self.is_ellipsoid() {
            let v = 2.0 / 3.0 * std::f64::consts::PI * self.semi_axes[0] * self.semi_axes[1];
            return (v * self.height, 3.0 / 8.0 * self.height);
        }
        // Polar grid in the ellipse's normalised frame: area element a·b·r dr dφ.
        let (nr, nphi) = (400, 720);
        let (mut v, mut m) = (0.0, 0.0);
        for j in 0..nphi {
            let phi = (j as f64 + 0.5) / nphi as f64 * std::f64::consts::TAU;
            let big = self.outline_at(phi);
            for i in 0..nr {
                let r = (i as f64 + 0.5) / nr as f64 * big;
                let n2 = self.nucleus2(r * phi.cos(), r * phi.sin());
                let z = self.height * self.profile.at((r / big).powi(2), n2);
                let da = self.semi_axes[0] * self.semi_axes[1] * r * big / nr as f64
                    * std::f64::consts::TAU
                    / nphi as f64;
                v += z * da;
                m += 0.5 * z * z * da;
            }
        }
        (v, m / v.max(1e-12))
    }
}

/// A flat particle lying on the substrate (dirt, a dead cell's fragment): a dark disc.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Debris {
    /// Centre `[x, y]` on the substrate, µm.
    pub centre: [f64; 2],
    /// Radius, µm.
    pub radius: f64,
    /// How much darker than the substrate (grey levels).
    pub darkness: f64,
}

/// A pipette: a tapered glass tip pointing along `azimuth` (0: `+x`), its body rising back
/// from it at `elevation` (0: level with the substrate). The glass is a chain of spheres
/// whose radius grows back from the tip's: `tip` is the centre of the first.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pipette {
    /// Tip position `[x, y]`, µm.
    pub tip: [f64; 2],
    /// Height of the tip's axis above the substrate, µm.
    pub height: f64,
    /// Radius at the tip, µm.
    pub tip_radius: f64,
    /// Radius growth per µm back from the tip.
    pub taper: f64,
    /// Angle of the body above the horizontal, radians.
    #[serde(default)]
    pub elevation: f64,
    /// Where the tip points in the substrate's plane, radians from `+x` towards `+y`.
    #[serde(default)]
    pub azimuth: f64,
}

impl Pipette {
    /// A level pipette `height` µm above the substrate whose body leaves the view towards
    /// `azimuth_deg`, its tip at `tip` (µm from the image centre) or, where not given, 20
    /// px in from the border the body leaves through.
    pub fn entering(optics: &Optics, height: f64, azimuth_deg: f64, tip: Option<[f64; 2]>) -> Self {
        let s = optics.um_per_px();
        let az = azimuth_deg.to_radians();
        let (w, h) = (optics.width as f64, optics.height as f64);
        let tip = match tip {
            Some(t) => t,
            None if azimuth_deg == 0.0 => [-0.5 * w * s + 20.0 * s, 0.0],
            None => {
                let (c, n) = (-az.cos(), -az.sin());
                let reach = (0.5 * w / c.abs().max(1e-9)).min(0.5 * h / n.abs().max(1e-9)) - 20.0;
                [c * reach * s, n * reach * s]
            }
        };
        Pipette {
            tip,
            height,
            tip_radius: 1.5,
            taper: 0.08,
            elevation: 0.0,
            azimuth: az,
        }
    }

    /// The pipette with its tip at camera-frame point `tip` (`[X, Y, Z]` µm), its body
    /// rising at `elevation_deg` towards `azimuth_deg` (the manipulator bridge's
    /// convention), over a substrate at depth `z0`.
    pub fn from_tip(tip: [f64; 3], elevation_deg: f64, azimuth_deg: f64, z0: f64) -> Pipette {
        Pipette {
            tip: [tip[0], tip[1]],
            height: z0 - tip[2],
            tip_radius: 1.5,
            taper: 0.08,
            elevation: elevation_deg.to_radians(),
            // The bridge names where the body goes; the renderer where the tip points.
            azimuth: (azimuth_deg + 180.0).rem_euclid(360.0).to_radians(),
        }
    }

    /// The tip's front: the glass's farthest point along the pipette's axis (which points
    /// down at `elevation` towards the tip), `[x, y, height]` µm.
    pub fn front(&self) -> [f64; 3] {
        let (ce, se) = (self.elevation.cos(), self.elevation.sin());
        [
            self.tip[0] + self.tip_radius * ce * self.azimuth.cos(),
            self.tip[1] + self.tip_radius * ce * self.azimuth.sin(),
            self.height - self.tip_radius * se,
        ]
    }
}

/// Where cell texture comes from.
#[derive(Clone, Debug, PartialEq, Default)]
pub enum Texture {
    /// Multi-octave value noise.
    #[default]
    Noise,
    /// A real cell image (grey), tiled at one image pixel per substrate pixel.
    Image(Plane<u8>),
}

/// How things look and how the sensor behaves.
#[derive(Clone, Debug, PartialEq)]
pub struct Look {
    /// Substrate brightness at the image centre.
    pub substrate: f64,
    /// Brightness change across the field of view (illumination gradient).
    pub gradient: f64,
    /// Amplitude of the substrate's faint texture.
    pub substrate_texture: f64,
    /// Amplitude of the cell texture.
    pub cell_texture: f64,
    /// Strength of the DIC-like relief shading.
    pub relief: f64,
    /// Sensor noise standard deviation, grey levels.
    pub noise: f64,
    /// Defocus blur (Gaussian sigma, px; 0 = sharp).
    pub blur: f64,
    /// Numerical aperture that defocuses the pipette by its height from the focal plane
    /// (blur circle radius `NA·Δz`; 0 = the pipette always sharp).
    pub aperture: f64,
    /// Rays per pixel along each axis.
    pub supersample: usize,
    /// Cell texture source.
    pub texture: Texture,
    /// Vignetting: the share of brightness lost at the image corners (quadratic falloff
    /// with the distance from the image centre; a property of each camera, not the scene).
    pub vignetting: f64,
    /// Darkening of the membrane rim where a cell meets the substrate (grey levels; the
    /// contact line, on the cell's edge and the substrate just outside).
    pub rim: f64,
}

/// Width of the membrane rim's dark line, µm.
const RIM_WIDTH: f64 = 1.5;

impl Look {
    /// A brightfield look: a substrate without texture under a lighting gradient and
    /// vignetting, cells darker than it with faint inner texture, little relief and a dark
    /// membrane rim.
    pub fn brightfield() -> Self {
        Self {
            substrate: 170.0,
            gradient: 40.0,
            substrate_texture: 0.0,
            cell_texture: 12.0,
            relief: 6.0,
            noise: 1.5,
            vignetting: 0.25,
            rim: 45.0,
            ..Self::default()
        }
    }
}

impl Default for Look {
    fn default() -> Self {
        Self {
            substrate: 140.0,
            gradient: 30.0,
            substrate_texture: 1.0,
            cell_texture: 30.0,
            relief: 25.0,
            noise: 1.5,
            blur: 0.0,
            aperture: 0.0,
            supersample: 2,
            texture: Texture::Noise,
            vignetting: 0.0,
            rim: 0.0,
        }
    }
}

/// A chessboard target: `cols × rows` inner corners, squares of `square` µm, with edges
/// as soft as a printed board's under the optics' resolution (about a pixel wide,
/// symmetric about each edge, so each corner is a saddle exactly at its place).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Chessboard {
    /// Inner corners along a row.
    pub cols: usize,
    /// Inner corners down a column.
    pub rows: usize,
    /// Side of a square, µm.
    pub square: f64,
}

impl Chessboard {
    /// The board's brightness offset at `(x, y)` µm (±1 on its squares, +1 on its white
    /// border beyond them).
    pub fn value(&self, x: f64, y: f64, um_per_px: f64) -> f64 {
        let half = [
            0.5 * (self.cols + 1) as f64 * self.square,
            0.5 * (self.rows + 1) as f64 * self.square,
        ];
        if x.abs() > half[0] || y.abs() > half[1] {
            return 1.0;
        }
        // Sharp to the pixel: the steepness makes each edge a pixel wide.
        let k = self.square / (std::f64::consts::PI * um_per_px);
        let wave = |t: f64, h: f64| {
            (k * (std::f64::consts::PI * (t + h) / self.square).sin()).clamp(-1.0, 1.0)
        };
        wave(x, half[0]) * wave(y, half[1])
    }
}

/// A whole scene.
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    /// Optics and sensor.
    pub optics: Optics,
    /// Appearance.
    pub look: Look,
    /// The cells.
    pub cells: Vec<CellShape>,
    /// An optional pipette.
    pub pipette: Option<Pipette>,
    /// Stage height of the substrate (µm towards the cameras; depth = Z0 − stage).
    pub stage: f64,
    /// Texture the whole substrate like a calibration target (for depth calibration).
    pub target: bool,
    /// A chessboard printed on the substrate, centred under the field (for calibrating).
    pub board: Option<Chessboard>,
    /// Substrate tilt: its height's slope along x and along y (rise over run; 2° is 0.035).
    pub tilt: [f64; 2],
    /// Particles lying on the substrate.
    pub debris: Vec<Debris>,
    /// Seed of textures and noise.
    pub seed: u64,
    /// Which frame of the scene this is ([`Scene::at_frame`]): the sensor noise is drawn
    /// anew for each, the textures stay the scene's.
    pub frame: u64,
}

/// How random scenes are drawn.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CellSpec {
    /// Number of cells.
    pub count: usize,
    /// Footprint diameter range, µm.
    pub diameter: [f64; 2],
    /// Height range, µm.
    pub height: [f64; 2],
    /// Smallest gap between footprints, µm.
    pub gap: f64,
    /// The cells' height profile.
    #[serde(default)]
    pub profile: Profile,
    /// Largest outline irregularity (amplitude of each harmonic of the radius; 0: ellipses).
    #[serde(default)]
    pub irregular: f64,
    /// Largest elongation: a cell's short axis is its long one over 1 + up to this (0: the
    /// usual 0.75–1 eccentricity only).
    #[serde(default)]
    pub elongation: f64,
}

impl CellSpec {
    /// Draws `cell`'s outline irregularity and elongation and a fried egg's nucleus
    /// (nothing for a regular spec, so that regular scenes draw no more numbers than they
    /// did).
    fn roughen(&self, cell: &mut CellShape, rng: &mut ChaCha8Rng) {
        if self.irregular > 0.0 {
            for k in 0..3 {
                cell.outline[k] = rng.random_range(0.0..=self.irregular);
                cell.outline[k + 3] = rng.random_range(0.0..std::f64::consts::TAU);
            }
        }
        if self.elongation > 0.0 {
            cell.semi_axes[1] = cell.semi_axes[0] / (1.0 + rng.random_range(0.0..=self.elongation));
            cell.height = cell.height.min(1.6 * cell.semi_axes[1]);
        }
        // Nuclei differ in size and rarely sit at the centre.
        if cell.profile == Profile::FriedEgg {
            let r = rng.random_range(0.3..=0.55);
            let off = rng.random_range(0.0..=0.3);
            let phi = rng.random_range(0.0..std::f64::consts::TAU);
            cell.nucleus = [r, off * phi.cos(), off * phi.sin()];
        }
    }
}

impl Default for CellSpec {
    fn default() -> Self {
        Self {
            count: 6,
            diameter: [20.0, 100.0],
            height: [8.0, 25.0],
            gap: 12.0,
            profile: Profile::Dome,
            irregular: 0.0,
            elongation: 0.0,
        }
    }
}

/// Rows rendered so far by this process (each view's and the ground truth's): what a long
/// render's progress is read from.
static ROWS_RENDERED: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// How many image rows this process has rendered so far: [`Scene::render`] renders three
/// per row of the image (both views and the ground truth).
pub fn rows_rendered() -> u64 {
    ROWS_RENDERED.load(std::sync::atomic::Ordering::Relaxed)
}

/// What to tell a user whose scene holds fewer cells than `spec` asked for (they did not fit
/// without overlapping), with what to change; `None` when all fit.
pub fn shortfall(scene: &Scene, spec: &CellSpec) -> Option<String> {
    let placed = scene.cells.len();
    (placed < spec.count).then(|| {
        let o = &scene.optics;
        let s = o.um_per_px();
        format!(
            "only {placed} of {} cells fit without overlapping in {}×{} px ({:.0}×{:.0} µm at {s:.2} µm/px) with footprints {}–{} µm across and {} µm apart: give a larger view (width, height), smaller cells (diameter) or fewer cells",
            spec.count,
            o.width,
            o.height,
            o.width as f64 * s,
            o.height as f64 * s,
            spec.diameter[0],
            spec.diameter[1],
            spec.gap
        )
    })
}

impl Scene {
    /// A random scene: non-overlapping cells fully inside both views. Fewer cells than asked
    /// when they do not fit ([`shortfall`] says so).
    pub fn random(optics: Optics, look: Look, spec: &CellSpec, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_ce11);
        let s = optics.um_per_px();
        let (hw, hh) = (
            0.5 * optics.width as f64 * s,
            0.5 * optics.height as f64 * s,
        );
        let margin = 6.0 * s + 0.35 * spec.height[1];
        let mut cells: Vec<CellShape> = Vec::new();
        // Cells placed so far by square of the grid: a new cell can only be too close to
        // one in its own square or the eight around it (a square is wider than any two
        // cells' reach and the gap), so thousands of cells place in a moment; the
        // decisions, and the scene, are the ones every other cell gives.
        let grown = 1.0 + 3.0 * spec.irregular;
        let square = (spec.diameter[1] * grown + spec.gap).max(1e-3) * 1.01 + 1.0;
        let key = |c: [f64; 2]| {
            (
                (c[0] / square).floor() as i64,
                (c[1] / square).floor() as i64,
            )
        };
        let mut grid: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
        for _ in 0..spec.count.saturating_mul(200) {
            if cells.len() == spec.count {
                break;
            }
            let d = rng.random_range(spec.diameter[0]..=spec.diameter[1]);
            let ecc = rng.random_range(0.75..=1.0);
            let (a, b) = (0.5 * d, 0.5 * d * ecc);
            let h = rng
                .random_range(spec.height[0]..=spec.height[1])
                .min(0.8 * d);
            let r = a * (1.0 + 3.0 * spec.irregular) + margin;
            if 2.0 * r >= 2.0 * hw.min(hh) {
                continue;
            }
            let c = [
                rng.random_range(-hw + r..hw - r),
                rng.random_range(-hh + r..hh - r),
            ];
            let (kx, ky) = key(c);
            let clear = (-1..=1).all(|dx| {
                (-1..=1).all(|dy| {
                    grid.get(&(kx + dx, ky + dy)).is_none_or(|near| {
                        near.iter().all(|&i| {
                            let o = &cells[i];
                            (o.centre[0] - c[0]).hypot(o.centre[1] - c[1])
                                > a * grown + o.reach() + spec.gap
                        })
                    })
                })
            });
            if !clear {
                continue;
            }
            let mut cell = CellShape {
                centre: c,
                semi_axes: [a, b],
                angle: rng.random_range(0.0..std::f64::consts::PI),
                height: h,
                texture_offset: [rng.random_range(0.0..1e4), rng.random_range(0.0..1e4)],
                brightness: rng.random_range(-15.0..15.0),
                profile: spec.profile,
                outline: [0.0; 6],
                nucleus: centred_nucleus(),
            };
            // Drawn after the rest, so that regular scenes stay what they were.
            spec.roughen(&mut cell, &mut rng);
            grid.entry(key(c)).or_default().push(cells.len());
            cells.push(cell);
        }
        Self::with_cells(optics, look, cells, seed)
    }

    /// A level substrate holding `cells`, nothing else, at its first frame.
    pub fn with_cells(optics: Optics, look: Look, cells: Vec<CellShape>, seed: u64) -> Self {
        Self {
            optics,
            look,
            cells,
            pipette: None,
            stage: 0.0,
            target: false,
            board: None,
            tilt: [0.0; 2],
            debris: Vec::new(),
            seed,
            frame: 0,
        }
    }

    /// A textured flat target at stage height `stage` µm, no cells.
    pub fn target(optics: Optics, look: Look, stage: f64, seed: u64) -> Self {
        Self {
            optics,
            look,
            cells: Vec::new(),
            pipette: None,
            stage,
            target: true,
            board: None,
            tilt: [0.0; 2],
            debris: Vec::new(),
            seed,
            frame: 0,
        }
    }

    /// The same scene with its substrate at disparity `d` px at the image centre (the
    /// microscope focused above or below it): the stage raised or lowered to match.
    pub fn with_substrate_disparity(mut self, d: f64) -> Self {
        let o = &self.optics;
        let c = o.calibration();
        self.stage = o.working_distance() - o.baseline * c.focal_px / (d + c.cx_right - c.cx);
        self
    }

    /// The same scene with `count` flat particles of radius `radius` µm (`[min, max]`)
    /// scattered on the substrate clear of the cells, seeded by `seed`.
    pub fn with_debris(mut self, count: usize, radius: [f64; 2], seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x00de_b715);
        let s = self.optics.um_per_px();
        let (hw, hh) = (
            0.5 * self.optics.width as f64 * s - 4.0 * s,
            0.5 * self.optics.height as f64 * s - 4.0 * s,
        );
        for _ in 0..count * 50 {
            if self.debris.len() == count {
                break;
            }
            let r = rng.random_range(radius[0]..=radius[1]);
            let c = [rng.random_range(-hw..hw), rng.random_range(-hh..hh)];
            let clear = self
                .cells
                .iter()
                .all(|o| (o.centre[0] - c[0]).hypot(o.centre[1] - c[1]) > o.reach() + r + 6.0);
            if clear {
                self.debris.push(Debris {
                    centre: c,
                    radius: r,
                    darkness: rng.random_range(40.0..90.0),
                });
            }
        }
        self
    }

    /// Height of the substrate above its level at the origin, at `(x, y)` µm.
    fn substrate_at(&self, x: f64, y: f64) -> f64 {
        self.tilt[0] * x + self.tilt[1] * y
    }

    /// The scene `frame` steps later: cells drift by their own velocity (µm per frame,
    /// up to `drift`), the pipette advances by `pipette_step` µm per frame.
    pub fn at_frame(&self, frame: usize, drift: f64, pipette_step: f64) -> Scene {
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed ^ 0xd1f7);
        let mut s = self.clone();
        for c in &mut s.cells {
            let (vx, vy) = (
                rng.random_range(-drift..=drift),
                rng.random_range(-drift..=drift),
            );
            c.centre[0] += vx * frame as f64;
            c.centre[1] += vy * frame as f64;
        }
        if let Some(p) = &mut s.pipette {
            p.tip[0] += pipette_step * frame as f64 * p.azimuth.cos();
            p.tip[1] += pipette_step * frame as f64 * p.azimuth.sin();
        }
        // Only the sensor noise is new: a substrate's and a cell's texture are theirs (until
        // December 2026 they were drawn anew for every frame, a flicker no camera shows).
        s.frame = frame as u64;
        s
    }
}

/// Gaussian sensor noise for a live source, drawn once and read from a new place for every
/// frame: a frame's noise costs an addition per pixel instead of a logarithm and a cosine
/// (30 of the 53 ms a 1280×1024 frame over a [`Backdrop`] took). Each view has its own
/// table of twice its pixels and each frame a pseudo-random start in it, so within a frame
/// every pixel's noise is its own and the views' are independent; frames share samples,
/// shifted, which nothing downstream can tell from fresh noise.
#[derive(Clone, Debug)]
pub struct NoiseTable {
    width: usize,
    height: usize,
    seed: u64,
    views: [Vec<f32>; 2],
}

impl NoiseTable {
    /// Standard normal samples for frames of `width`×`height`.
    pub fn new(width: usize, height: usize, seed: u64) -> Self {
        let n = 2 * width * height;
        let draw = |salt: u64| -> Vec<f32> {
            let mut rng = ChaCha8Rng::seed_from_u64(seed ^ salt);
            let mut v = Vec::with_capacity(n + 1);
            // Box–Muller gives two samples a draw.
            while v.len() < n {
                let u1: f64 = rng.random_range(f64::EPSILON..1.0);
                let u2: f64 = rng.random_range(0.0..1.0);
                let r = (-2.0 * u1.ln()).sqrt();
                let (s, c) = (std::f64::consts::TAU * u2).sin_cos();
                v.push((r * c) as f32);
                v.push((r * s) as f32);
            }
            v.truncate(n);
            v
        };
        let (l, r) = rayon::join(|| draw(0x6e01), || draw(0x6e02));
        Self {
            width,
            height,
            seed,
            views: [l, r],
        }
    }

    /// Whether the table is for frames of this size.
    pub fn fits(&self, width: usize, height: usize) -> bool {
        (self.width, self.height) == (width, height)
    }

    /// Both views of frame `frame`: the means plus `sigma` times the table's noise, rounded
    /// and clamped to 0–255.
    pub fn apply(
        &self,
        (left, right): (Plane<f64>, Plane<f64>),
        sigma: f64,
        frame: u64,
    ) -> (Plane<u8>, Plane<u8>) {
        let pixels = self.width * self.height;
        let one = |img: Plane<f64>, k: usize| -> Plane<u8> {
            assert_eq!(
                img.data.len(),
                pixels,
                "a noise table for another frame size"
            );
            // SplitMix64 of the seed, the frame and the view: where this frame reads.
            let mut z = self.seed ^ frame.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ (k as u64 + 1);
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^= z >> 31;
            let start = (z % (pixels as u64 + 1)) as usize;
            let noise = &self.views[k][start..start + pixels];
            let mut out = vec![0u8; pixels];
            out.par_chunks_mut(1 << 16)
                .zip(img.data.par_chunks(1 << 16))
                .zip(noise.par_chunks(1 << 16))
                .for_each(|((o, m), e)| {
                    for ((o, &m), &e) in o.iter_mut().zip(m).zip(e) {
                        *o = (m + sigma * e as f64).round().clamp(0.0, 255.0) as u8;
                    }
                });
            Plane::from_vec(img.width, img.height, out).expect("size")
        };
        (one(left, 0), one(right, 1))
    }
}

/// Both views of a scene's bare substrate (no cells, no pipette) before blur and noise:
/// what stays from frame to frame of a scene ([`Scene::at_frame`]), so that
/// [`Scene::render_views_over`] renders only what its cells and pipette touch.
#[derive(Clone, Debug)]
pub struct Backdrop {
    /// The scene it shows, less its cells and pipette.
    bare: Scene,
    /// Left and right means.
    views: [Plane<f64>; 2],
}

impl Backdrop {
    /// Renders the backdrop of `scene`.
    pub fn of(scene: &Scene) -> Self {
        let bare = scene.bare();
        let cal = bare.optics.calibration();
        let (left, right) = rayon::join(|| bare.view(false, &cal), || bare.view(true, &cal));
        Self {
            bare,
            views: [left, right],
        }
    }
}

/// Per-cell ground truth.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CellTruth {
    /// Label in the truth mask (index + 1).
    pub id: u32,
    /// The shape.
    pub shape: CellShape,
    /// Left-image pixels where the cell is the visible surface.
    pub area_px: u64,
    /// Centroid of those pixels `[x, y]`.
    pub centroid_px: [f64; 2],
    /// Projection of the footprint centre into the left image.
    pub footprint_centre_px: [f64; 2],
    /// Height above the substrate, µm.
    pub height: f64,
    /// Volume (2/3·π·a·b·h), µm³.
    pub volume: f64,
    /// Centroid of the dome's volume `[X, Y, Z]`, µm, triangulation frame.
    pub centroid: [f64; 3],
    /// Disparity of the substrate under the cell and of its top.
    pub disparity_base_top: [f64; 2],
}

/// A rendered pair and its ground truth.
#[derive(Clone, Debug)]
pub struct Rendered {
    /// Left view.
    pub left: Plane<u8>,
    /// Right view.
    pub right: Plane<u8>,
    /// Left disparity at every pixel centre.
    pub disparity: DisparityMap,
    /// Left depth at every pixel centre, µm.
    pub depth: Plane<f32>,
    /// Left labels: 0 substrate, cell `i` = `i`, `u32::MAX` pipette.
    pub labels: Plane<u32>,
    /// Per-cell truth.
    pub cells: Vec<CellTruth>,
    /// The calibration that triangulates the pair.
    pub calibration: Calibration,
}

impl Rendered {
    /// The smallest and the largest true disparity, px.
    pub fn disparity_range(&self) -> (f32, f32) {
        self.disparity
            .data
            .iter()
            .fold((f32::MAX, f32::MIN), |(a, b), &d| (a.min(d), b.max(d)))
    }
}

/// Label of pipette pixels in [`Rendered::labels`].
pub const PIPETTE: u32 = u32::MAX;

/// What a ray hits first.
#[derive(Clone, Copy, Debug)]
enum Hit {
    /// The substrate, at this height above its level at the origin.
    Substrate(f64),
    Cell(usize, [f64; 3]),
    Pipette,
}

/// Smooth value noise with a hashed lattice (no tables, any coordinates).
fn value_noise(x: f64, y: f64, seed: u64) -> f64 {
    let hash = |i: i64, j: i64| -> f64 {
        let mut h = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
            ^ seed.wrapping_mul(0x1656_67B1_9E37_79F9);
        h ^= h >> 29;
        h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h ^= h >> 32;
        (h >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    };
    let (fx, fy) = (x.floor(), y.floor());
    let (tx, ty) = (x - fx, y - fy);
    let (sx, sy) = (tx * tx * (3.0 - 2.0 * tx), ty * ty * (3.0 - 2.0 * ty));
    let (i, j) = (fx as i64, fy as i64);
    let top = hash(i, j) * (1.0 - sx) + hash(i + 1, j) * sx;
    let bot = hash(i, j + 1) * (1.0 - sx) + hash(i + 1, j + 1) * sx;
    top * (1.0 - sy) + bot * sy
}

/// Cell texture: noise at 6, 2.5 and 1 µm, or the real image.
fn cell_texture(tex: &Texture, u: f64, v: f64, seed: u64) -> f64 {
    match tex {
        Texture::Noise => {
            0.5 * value_noise(u / 6.0, v / 6.0, seed)
                + 0.35 * value_noise(u / 2.5, v / 2.5, seed + 1)
                + 0.3 * value_noise(u / 1.0, v / 1.0, seed + 2)
        }
        Texture::Image(img) => {
            let (w, h) = (img.width as f64, img.height as f64);
            let (x, y) = (u.rem_euclid(w - 1.0), v.rem_euclid(h - 1.0));
            let (x0, y0) = (x.floor() as usize, y.floor() as usize);
            let (tx, ty) = (x - x0 as f64, y - y0 as f64);
            let g =
                |a: usize, b: usize| *img.get(a.min(img.width - 1), b.min(img.height - 1)) as f64;
            let val = (g(x0, y0) * (1.0 - tx) + g(x0 + 1, y0) * tx) * (1.0 - ty)
                + (g(x0, y0 + 1) * (1.0 - tx) + g(x0 + 1, y0 + 1) * tx) * ty;
            (val - 128.0) / 64.0
        }
    }
}

impl Scene {
    fn z0(&self) -> f64 {
        self.optics.working_distance() - self.stage
    }

    /// The cells a ray through image row `v` may meet. A hit above the substrate
    /// (0 < s ≤ height) lies within the footprint's larger semi-axis of the centre, and the
    /// ray's y there is `sy·(z0 − s)` whatever the column: cells out of that reach on every
    /// height cannot be hit, so leaving them out changes no pixel.
    fn cells_on_row(&self, v: f64, cal: &Calibration) -> Vec<usize> {
        let (sy, z0) = ((v - cal.cy) / cal.focal_px, self.z0());
        (0..self.cells.len())
            .filter(|&k| {
                let c = &self.cells[k];
                // 1 µm beyond the footprint, against rounding.
                let reach = c.reach() + 1.0;
                let zk = z0 - self.substrate_at(c.centre[0], c.centre[1]);
                let (y0, y1) = (sy * zk, sy * (zk - c.height));
                y0.max(y1) >= c.centre[1] - reach && y0.min(y1) <= c.centre[1] + reach
            })
            .collect()
    }

    /// The first thing a ray through pixel `(u, v)` of a view meets, and its depth, of the
    /// cells `candidates` (those of [`Self::cells_on_row`] for `v`) and the pipette.
    fn cast(
        &self,
        right: bool,
        u: f64,
        v: f64,
        cal: &Calibration,
        candidates: &[usize],
        with_pipette: bool,
    ) -> (Hit, f64) {
        let f = cal.focal_px;
        let (ox, cx) = if right {
            (0.5 * self.optics.baseline, cal.cx_right)
        } else {
            (-0.5 * self.optics.baseline, cal.cx)
        };
        let (sx, sy) = ((u - cx) / f, (v - cal.cy) / f);
        let z0 = self.z0();
        // The ray at height s above the substrate: x = ox + sx·(z0 − s), y = sy·(z0 − s).
        // Where the ray meets the (tilted) substrate plane: s = tx·x(s) + ty·y(s).
        let [tx, ty] = self.tilt;
        let s_sub = (tx * (ox + sx * z0) + ty * sy * z0) / (1.0 + tx * sx + ty * sy);
        let mut best = (Hit::Substrate(s_sub), s_sub);
        for &k in candidates {
            let c = &self.cells[k];
            // The cell stands on the substrate's level under its centre.
            let base = self.substrate_at(c.centre[0], c.centre[1]);
            let zk = z0 - base;
            let (co, si) = (c.angle.cos(), c.angle.sin());
            let (dx, dy) = (ox + sx * zk - c.centre[0], sy * zk - c.centre[1]);
            let (px, py) = (co * dx + si * dy, -si * dx + co * dy);
            let (qx, qy) = (co * sx + si * sy, -si * sx + co * sy);
            let local = if c.is_ellipsoid() {
                let (a2, b2, h) = (c.semi_axes[0].powi(2), c.semi_axes[1].powi(2), c.height);
                // |P − Q s|² over the axes + (s/h)² = 1.
                let qa = qx * qx / a2 + qy * qy / b2 + 1.0 / (h * h);
                let qb = -2.0 * (px * qx / a2 + py * qy / b2);
                let qc = px * px / a2 + py * py / b2 - 1.0;
                let disc = qb * qb - 4.0 * qa * qc;
                if disc < 0.0 {
                    continue;
                }
                (-qb + disc.sqrt()) / (2.0 * qa)
            } else {
                match march(c, [px, py], [qx, qy]) {
                    Some(s) => s,
                    None => continue,
                }
            };
            let s = local + base;
            if s > best.1 {
                let (lx, ly) = (px - qx * local, py - qy * local);
                best = (Hit::Cell(k, [lx, ly, local]), s);
            }
        }
        if let Some(p) = self.pipette.as_ref().filter(|_| with_pipette) {
            // A chain of spheres along the axis, radius growing back from the tip. In the
            // pipette's frame (x' where the tip points, y' across) the ray at height s is
            // (pox + psx·(z0 − s), poy + psy·(z0 − s)).
            let (ca, sa) = (p.azimuth.cos(), p.azimuth.sin());
            let (pox, poy) = (ca * ox, -sa * ox);
            let (psx, psy) = (ca * sx + sa * sy, -sa * sx + ca * sy);
            let tip = [
                ca * p.tip[0] + sa * p.tip[1],
                -sa * p.tip[0] + ca * p.tip[1],
            ];
            let step = 0.5 * p.tip_radius.max(0.5);
            let len = self.pipette_length(p);
            let (ce, se) = (p.elevation.cos(), p.elevation.sin());
            let hmax = p.height + p.tip_radius + (p.taper + se) * len;
            // Only spheres the ray can reach: where it passes the heights 0..hmax its x' and
            // y' span these intervals, and a sphere at t reaches r(t) around its centre.
            let span = |a: f64, b: f64| (a.min(b), a.max(b));
            let (xlo, xhi) = span(pox + psx * z0, pox + psx * (z0 - hmax));
            let (ylo, yhi) = span(poy + psy * z0, poy + psy * (z0 - hmax));
            let dy = (ylo - tip[1]).max(tip[1] - yhi).max(0.0);
            let mut t_lo = ((tip[0] - xhi - p.tip_radius) / (ce + p.taper)).max(0.0);
            if dy > p.tip_radius {
                t_lo = t_lo.max(if p.taper > 0.0 {
                    (dy - p.tip_radius) / p.taper
                } else {
                    len
                });
            }
            let t_hi = if p.taper < ce {
                ((tip[0] - xlo + p.tip_radius) / (ce - p.taper)).min(len)
            } else {
                len
            };
            let mut k = (t_lo / step).floor().max(0.0) as u64;
            while (k as f64) * step < t_hi {
                let t = k as f64 * step;
                k += 1;
                let r = p.tip_radius + p.taper * t;
                let (ccx, ccy, ccs) = (tip[0] - t * ce, tip[1], p.height + t * se);
                let (ax, ay) = (pox + psx * z0 - ccx, poy + psy * z0 - ccy);
                let qa = psx * psx + psy * psy + 1.0;
                let qb = -2.0 * (ax * psx + ay * psy + ccs);
                let qc = ax * ax + ay * ay + ccs * ccs - r * r;
                let disc = qb * qb - 4.0 * qa * qc;
                if disc >= 0.0 {
                    let s = (-qb + disc.sqrt()) / (2.0 * qa);
                    if s > best.1 {
                        best = (Hit::Pipette, s);
                    }
                }
            }
        }
        (best.0, z0 - best.1)
    }

    /// How much of the pipette's body back from its tip can show: as far back along its
    /// axis as the farthest corner of the view's ground (with 10 % to spare for the rays'
    /// spread), at most twice the view's size. A widely tapered body rendered to twice the
    /// view's size made every pixel of a frame a candidate (210 against 26 ms at 640×480).
    fn pipette_length(&self, p: &Pipette) -> f64 {
        let um = self.optics.um_per_px();
        let (hw, hh) = (
            0.5 * self.optics.width as f64 * um,
            0.5 * self.optics.height as f64 * um,
        );
        // The body runs back from the tip, against where the tip points.
        let back = [-p.azimuth.cos(), -p.azimuth.sin()];
        let far = [[-hw, -hh], [hw, -hh], [-hw, hh], [hw, hh]]
            .iter()
            .map(|c| (c[0] - p.tip[0]) * back[0] + (c[1] - p.tip[1]) * back[1])
            .fold(0.0, f64::max);
        let ce = p.elevation.cos().max(0.05);
        (1.1 * far / ce + 10.0).min(2.0 * (2.0 * hw).max(2.0 * hh))
    }

    /// Brightness of what a ray hit (before blur and noise), dimmed by vignetting.
    fn shade(&self, hit: Hit, u: f64, v: f64, right: bool, cal: &Calibration) -> f64 {
        let lit = self.lit(hit, u, v, right, cal);
        if self.look.vignetting == 0.0 {
            return lit;
        }
        let (cu, cv) = (
            0.5 * (self.optics.width as f64 - 1.0),
            0.5 * (self.optics.height as f64 - 1.0),
        );
        let r2 = ((u - cu).powi(2) + (v - cv).powi(2)) / (cu * cu + cv * cv);
        lit * (1.0 - self.look.vignetting * r2)
    }

    /// Darkening of the membrane rim at a substrate point `(x, y)` µm just outside a cell.
    fn rim_outside(&self, x: f64, y: f64) -> f64 {
        let mut dark: f64 = 0.0;
        for c in &self.cells {
            let (dx, dy) = (x - c.centre[0], y - c.centre[1]);
            if dx.abs().max(dy.abs()) > c.reach() + 4.0 * RIM_WIDTH {
                continue;
            }
            let (co, si) = (c.angle.cos(), c.angle.sin());
            let (px, py) = (co * dx + si * dy, -si * dx + co * dy);
            let rho = c.rho2(px, py).sqrt();
            if rho >= 1.0 {
                let off = (rho - 1.0) * px.hypot(py) / rho;
                dark = dark.max((-(off / RIM_WIDTH).powi(2)).exp());
            }
        }
        self.look.rim * dark
    }

    /// Brightness of what a ray hit, before vignetting, blur and noise.
    fn lit(&self, hit: Hit, u: f64, v: f64, right: bool, cal: &Calibration) -> f64 {
        let look = &self.look;
        let f = cal.focal_px;
        let z0 = self.z0();
        let (ox, cx) = if right {
            (0.5 * self.optics.baseline, cal.cx_right)
        } else {
            (-0.5 * self.optics.baseline, cal.cx)
        };
        let x = ox + (u - cx) / f * z0;
        let y = (v - cal.cy) / f * z0;
        let half_w = 0.5 * self.optics.width as f64 * self.optics.um_per_px();
        let base = look.substrate + look.gradient * 0.5 * (x / half_w + 0.3 * y / half_w);
        match hit {
            Hit::Substrate(s) => {
                // The point hit on a tilted substrate (s = 0 when flat).
                let (x, y) = if s == 0.0 {
                    (x, y)
                } else {
                    (ox + (u - cx) / f * (z0 - s), (v - cal.cy) / f * (z0 - s))
                };
                if let Some(b) = &self.board {
                    return base + 70.0 * b.value(x, y, self.optics.um_per_px());
                }
                let amp = if self.target {
                    40.0
                } else {
                    look.substrate_texture
                };
                let t = if self.target {
                    cell_texture(&Texture::Noise, x, y, self.seed)
                } else if amp == 0.0 {
                    0.0
                } else {
                    value_noise(x / 3.0, y / 3.0, self.seed ^ 0xbac)
                };
                let mut dirt: f64 = 0.0;
                for d in &self.debris {
                    let r = (x - d.centre[0]).hypot(y - d.centre[1]);
                    dirt = dirt.max(d.darkness * (d.radius + 0.5 - r).clamp(0.0, 1.0));
                }
                let rim = if look.rim > 0.0 {
                    self.rim_outside(x, y)
                } else {
                    0.0
                };
                base + amp * t - dirt - rim
            }
            Hit::Cell(k, [lx, ly, s]) => {
                let c = &self.cells[k];
                let (a, b, h) = (c.semi_axes[0], c.semi_axes[1], c.height);
                let t = cell_texture(
                    &look.texture,
                    lx + c.texture_offset[0],
                    ly + c.texture_offset[1],
                    self.seed ^ ((k as u64 + 1) * 0x51),
                );
                // Slope of the surface along the DIC shear (45°): relief shading.
                let (gx, gy) = if c.is_ellipsoid() {
                    let zn = (s / h).max(0.05);
                    (-lx / (a * a) * h / zn, -ly / (b * b) * h / zn)
                } else {
                    let e = 0.05;
                    let z = |x: f64, y: f64| c.surface(x, y).unwrap_or(0.0);
                    (
                        ((z(lx + e, ly) - z(lx - e, ly)) / (2.0 * e)).clamp(-20.0, 20.0),
                        ((z(lx, ly + e) - z(lx, ly - e)) / (2.0 * e)).clamp(-20.0, 20.0),
                    )
                };
                let (co, si) = (c.angle.cos(), c.angle.sin());
                let (wx, wy) = (co * gx - si * gy, si * gx + co * gy);
                let slope = (wx + wy) * std::f64::consts::FRAC_1_SQRT_2;
                let rim = if look.rim > 0.0 {
                    let rho = c.rho2(lx, ly).sqrt().min(1.0);
                    let off = (1.0 - rho) * lx.hypot(ly) / rho.max(1e-6);
                    look.rim * (-(off / RIM_WIDTH).powi(2)).exp()
                } else {
                    0.0
                };
                base + c.brightness + look.cell_texture * t + look.relief * slope.tanh() - rim
            }
            Hit::Pipette => base - 70.0,
        }
    }

    fn view(&self, right: bool, cal: &Calibration) -> Plane<f64> {
        self.view_over(right, cal, None)
    }

    /// One view's means; over a `backdrop` (this scene's bare substrate in that view), only
    /// the pixels [`Scene::touched`] marks are rendered.
    fn view_over(
        &self,
        right: bool,
        cal: &Calibration,
        backdrop: Option<&Plane<f64>>,
    ) -> Plane<f64> {
        let (w, h) = (self.optics.width, self.optics.height);
        let n = self.look.supersample.max(1);
        let defocus = self.pipette_defocus_px();
        // Per row its values and, only with a defocused pipette, what the pipette darkens.
        let rows: Vec<(Vec<f64>, Vec<f64>)> = (0..h)
            .into_par_iter()
            .map(|v| {
                ROWS_RENDERED.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let sub_row = |j: usize| v as f64 + (j as f64 + 0.5) / n as f64 - 0.5;
                let touched = backdrop.map(|_| self.touched(right, v, cal));
                let mut dark_row = Vec::new();
                if touched.as_ref().is_some_and(|t| !t.contains(&true)) {
                    if defocus > 0.0 {
                        dark_row = vec![0.0; w];
                    }
                    return (backdrop.expect("with touched").row(v).to_vec(), dark_row);
                }
                let on_row: Vec<Vec<usize>> =
                    (0..n).map(|j| self.cells_on_row(sub_row(j), cal)).collect();
                let row = (0..w)
                    .map(|u| {
                        if let (Some(t), Some(b)) = (&touched, backdrop)
                            && !t[u]
                        {
                            if defocus > 0.0 {
                                dark_row.push(0.0);
                            }
                            return *b.get(u, v);
                        }
                        let (mut acc, mut dark) = (0.0, 0.0);
                        for (j, candidates) in on_row.iter().enumerate() {
                            let sv = sub_row(j);
                            for i in 0..n {
                                let su = u as f64 + (i as f64 + 0.5) / n as f64 - 0.5;
                                let (hit, _) = self.cast(right, su, sv, cal, candidates, true);
                                let lit = self.shade(hit, su, sv, right, cal);
                                acc += lit;
                                if defocus > 0.0 && matches!(hit, Hit::Pipette) {
                                    // What the pipette hides, for its darkness alone.
                                    let (behind, _) =
                                        self.cast(right, su, sv, cal, candidates, false);
                                    dark += self.shade(behind, su, sv, right, cal) - lit;
                                }
                            }
                        }
                        if defocus > 0.0 {
                            dark_row.push(dark / (n * n) as f64);
                        }
                        acc / (n * n) as f64
                    })
                    .collect();
                (row, dark_row)
            })
            .collect();
        let (values, darks): (Vec<Vec<f64>>, Vec<Vec<f64>>) = rows.into_iter().unzip();
        let view = Plane::from_vec(w, h, values.concat()).expect("size");
        if defocus == 0.0 {
            return view;
        }
        // The pipette out of focus: its darkness spread by the defocus blur over what it
        // would hide in focus.
        let dark = Plane::from_vec(w, h, darks.concat()).expect("size");
        let spread = gaussian_blur(&dark, defocus);
        let data = view
            .data
            .iter()
            .zip(&dark.data)
            .zip(&spread.data)
            .map(|((v, d), s)| v + d - s)
            .collect();
        Plane::from_vec(w, h, data).expect("size")
    }

    /// Where world point `[x, y, height]` (µm; height above the untilted substrate level)
    /// shows in the left and the right view, px.
    pub fn project(&self, p: [f64; 3]) -> [[f64; 2]; 2] {
        let cal = self.optics.calibration();
        let depth = self.z0() - p[2];
        let at = |ox: f64, cx: f64| {
            [
                cx + cal.focal_px * (p[0] - ox) / depth,
                cal.cy + cal.focal_px * p[1] / depth,
            ]
        };
        [
            at(-0.5 * self.optics.baseline, cal.cx),
            at(0.5 * self.optics.baseline, cal.cx_right),
        ]
    }

    /// The point `[X, Y, Z]` of the triangulation's camera frame (µm, origin midway between
    /// the cameras, Z the depth) that world point `[x, y, height]` is.
    pub fn camera_point(&self, p: [f64; 3]) -> [f64; 3] {
        [p[0], p[1], self.z0() - p[2]]
    }

    /// Gaussian sigma (px) of the pipette's defocus blur: half the blur circle's radius
    /// `NA·Δz` at its tip's height `Δz` from the focal plane (0 without a pipette or with
    /// `look.aperture` 0).
    pub fn pipette_defocus_px(&self) -> f64 {
        match &self.pipette {
            // The focal plane lies `stage` below the substrate (see `z0`).
            Some(p) if self.look.aperture > 0.0 => {
                0.5 * self.look.aperture * (p.height + self.stage).abs() / self.optics.um_per_px()
            }
            _ => 0.0,
        }
    }

    /// Both views before sensor noise and rounding: the means the pixel values scatter
    /// around, with noise of standard deviation `look.noise` (for bounds on what any
    /// estimator can reach from the views).
    pub fn render_means(&self) -> (Plane<f64>, Plane<f64>) {
        self.means(None)
    }

    /// Both views blurred, each rendered whole or over its view of a backdrop.
    fn means(&self, backdrop: Option<&Backdrop>) -> (Plane<f64>, Plane<f64>) {
        let cal = self.optics.calibration();
        let one = |k: usize| {
            let over = backdrop.map(|b| &b.views[k]);
            gaussian_blur(&self.view_over(k == 1, &cal, over), self.look.blur)
        };
        rayon::join(|| one(0), || one(1))
    }

    /// Renders both views, without the ground truth (what a camera would give).
    pub fn render_views(&self) -> (Plane<u8>, Plane<u8>) {
        let (left, right) = self.render_means();
        self.finish((left, right))
    }

    /// Renders both views as [`Scene::render_views`] does, to the same bytes, from a
    /// [`Backdrop`] of the scene's substrate: only the pixels its cells and pipette can
    /// touch are rendered. `backdrop` is made (or made anew) where it is not this scene's.
    pub fn render_views_over(&self, backdrop: &mut Option<Backdrop>) -> (Plane<u8>, Plane<u8>) {
        self.finish(self.render_means_over(backdrop))
    }

    /// Both views' means (before sensor noise and rounding) as [`Scene::render_means`]
    /// gives them, from a [`Backdrop`] as [`Scene::render_views_over`] renders.
    pub fn render_means_over(&self, backdrop: &mut Option<Backdrop>) -> (Plane<f64>, Plane<f64>) {
        if !backdrop.as_ref().is_some_and(|b| b.bare == self.bare()) {
            *backdrop = Some(Backdrop::of(self));
        }
        self.means(backdrop.as_ref())
    }

    /// Sensor noise and rounding on both views' means.
    fn finish(&self, (left, right): (Plane<f64>, Plane<f64>)) -> (Plane<u8>, Plane<u8>) {
        let (w, h) = (self.optics.width, self.optics.height);
        let seed = self.seed.wrapping_add(self.frame.wrapping_mul(0x9e37));
        let finish = |img: Plane<f64>, salt: u64| -> Plane<u8> {
            let mut rng = ChaCha8Rng::seed_from_u64(seed ^ salt);
            let data = img
                .data
                .iter()
                .map(|&v| {
                    (v + self.look.noise * gauss(&mut rng))
                        .round()
                        .clamp(0.0, 255.0) as u8
                })
                .collect();
            Plane::from_vec(w, h, data).expect("size")
        };
        rayon::join(|| finish(left, 0x1ef7), || finish(right, 0x7197))
    }

    /// The scene without its cells and pipette, at its first frame: what a [`Backdrop`]
    /// depends on.
    fn bare(&self) -> Scene {
        Scene {
            cells: Vec::new(),
            pipette: None,
            frame: 0,
            ..self.clone()
        }
    }

    /// Which pixels of row `v` of a view a ray may meet a cell or the pipette through, or
    /// see a cell's membrane rim darken the substrate (`true`); elsewhere the view is its
    /// bare substrate's. Each cell's reach (with its rim) and the pipette's bounds, over
    /// every height they span, are projected through the row's extent, with a pixel to
    /// spare.
    fn touched(&self, right: bool, v: usize, cal: &Calibration) -> Vec<bool> {
        let w = self.optics.width;
        let mut mask = vec![false; w];
        let f = cal.focal_px;
        let (ox, cx) = if right {
            (0.5 * self.optics.baseline, cal.cx_right)
        } else {
            (-0.5 * self.optics.baseline, cal.cx)
        };
        let z0 = self.z0();
        let sy = [(v as f64 - 0.5 - cal.cy) / f, (v as f64 + 0.5 - cal.cy) / f];
        // World boxes `[x0, x1] × [y0, y1]` over heights `[s0, s1]`, and where in the row
        // they show.
        let mut mark = |[x0, x1]: [f64; 2], [y0, y1]: [f64; 2], [s0, s1]: [f64; 2]| {
            let depths = [z0 - s0, z0 - s1];
            if depths.iter().any(|d| *d <= 0.0) {
                mask.fill(true);
                return;
            }
            let ys = sy.iter().flat_map(|a| depths.iter().map(move |d| a * d));
            let (ylo, yhi) = ys.fold((f64::MAX, f64::MIN), |(a, b), y| (a.min(y), b.max(y)));
            if yhi < y0 || ylo > y1 {
                return;
            }
            let us = [x0, x1]
                .into_iter()
                .flat_map(|x| depths.iter().map(move |d| cx + f * (x - ox) / d));
            let (ulo, uhi) = us.fold((f64::MAX, f64::MIN), |(a, b), u| (a.min(u), b.max(u)));
            let lo = (ulo - 1.0).floor().max(0.0);
            let hi = (uhi + 1.0).ceil().min(w as f64 - 1.0);
            if lo <= hi {
                mask[lo as usize..=hi as usize].fill(true);
            }
        };
        let rim = if self.look.rim > 0.0 {
            4.0 * RIM_WIDTH
        } else {
            0.0
        };
        let [tx, ty] = self.tilt;
        for c in &self.cells {
            let m = c.reach() + rim + 2.0;
            let base = self.substrate_at(c.centre[0], c.centre[1]);
            let slack = (tx.abs() + ty.abs()) * m + 1.0;
            mark(
                [c.centre[0] - m, c.centre[0] + m],
                [c.centre[1] - m, c.centre[1] + m],
                [base - slack, base + c.height + 1.0],
            );
        }
        if let Some(p) = &self.pipette {
            let len = self.pipette_length(p);
            let (ce, se) = (p.elevation.cos(), p.elevation.sin());
            let r = p.tip_radius + p.taper * len;
            let hmax = p.height + p.tip_radius + (p.taper + se.max(0.0)) * len + 1.0;
            let hmin = (p.height - r + se.min(0.0) * len - 1.0).min(0.0);
            // The box round the body's whole length (its far end is off the image).
            let (ca, sa) = (p.azimuth.cos(), p.azimuth.sin());
            let back = [p.tip[0] - ca * ce * len, p.tip[1] - sa * ce * len];
            let m = r + p.tip_radius + 2.0;
            mark(
                [p.tip[0].min(back[0]) - m, p.tip[0].max(back[0]) + m],
                [p.tip[1].min(back[1]) - m, p.tip[1].max(back[1]) + m],
                [hmin, hmax],
            );
        }
        mask
    }

    /// Renders both views and the ground truth.
    pub fn render(&self) -> Rendered {
        let cal = self.optics.calibration();
        let (w, h) = (self.optics.width, self.optics.height);
        let (left, right) = self.render_views();
        let mut disparity = Plane::filled(w, h, 0f32);
        let mut depth = Plane::filled(w, h, 0f32);
        let mut labels = Plane::filled(w, h, 0u32);
        let off = cal.cx_right - cal.cx;
        // Row by row in parallel: each pixel's ray is its own.
        depth
            .data
            .par_chunks_mut(w)
            .zip(disparity.data.par_chunks_mut(w))
            .zip(labels.data.par_chunks_mut(w))
            .enumerate()
            .for_each(|(v, ((depth, disparity), labels))| {
                ROWS_RENDERED.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let candidates = self.cells_on_row(v as f64, &cal);
                for u in 0..w {
                    let (hit, z) = self.cast(false, u as f64, v as f64, &cal, &candidates, true);
                    depth[u] = z as f32;
                    disparity[u] = (self.optics.baseline * cal.focal_px / z - off) as f32;
                    labels[u] = match hit {
                        Hit::Substrate(_) => 0,
                        Hit::Cell(k, _) => k as u32 + 1,
                        Hit::Pipette => PIPETTE,
                    };
                }
            });
        let z0 = self.z0();
        // Pixel count and coordinate sums per label, in one pass.
        let mut sums = vec![(0u64, 0f64, 0f64); self.cells.len() + 1];
        for (i, &l) in labels.data.iter().enumerate() {
            if l != 0 && l != PIPETTE {
                let s = &mut sums[l as usize];
                s.0 += 1;
                s.1 += (i % w) as f64;
                s.2 += (i / w) as f64;
            }
        }
        let cells = self
            .cells
            .iter()
            .enumerate()
            .map(|(k, c)| {
                let id = k as u32 + 1;
                let (n, sx, sy) = sums[id as usize];
                let f = cal.focal_px;
                let zb = z0 - self.substrate_at(c.centre[0], c.centre[1]);
                let (volume, zc) = c.volume_and_centroid_height();
                CellTruth {
                    id,
                    shape: *c,
                    area_px: n,
                    centroid_px: [sx / n.max(1) as f64, sy / n.max(1) as f64],
                    footprint_centre_px: [
                        cal.cx + (c.centre[0] + 0.5 * self.optics.baseline) * f / zb,
                        cal.cy + c.centre[1] * f / zb,
                    ],
                    height: c.height,
                    volume,
                    centroid: [c.centre[0], c.centre[1], zb - zc],
                    disparity_base_top: [
                        self.optics.baseline * f / zb - off,
                        self.optics.baseline * f / (zb - c.height) - off,
                    ],
                }
            })
            .collect();
        Rendered {
            left,
            right,
            disparity,
            depth,
            labels,
            cells,
            calibration: cal,
        }
    }
}

/// The local height `s` (above the cell's base) where the ray `P − Q·s` (cell frame) first
/// meets the surface of a cell of any shape, marching down from its top: `None` if it
/// misses. Steps of 1/96 of the height cannot pass through a surface whose slope the
/// ray's own (≤ 1:4) exceeds for less than a step; bisection then finds the crossing.
fn march(c: &CellShape, p: [f64; 2], q: [f64; 2]) -> Option<f64> {
    let h = c.height;
    // Closest horizontal approach over 0 ≤ s ≤ h: too far means no hit.
    let qq = q[0] * q[0] + q[1] * q[1];
    let s_near = if qq > 0.0 {
        ((p[0] * q[0] + p[1] * q[1]) / qq).clamp(0.0, h)
    } else {
        0.0
    };
    if (p[0] - q[0] * s_near).hypot(p[1] - q[1] * s_near) > c.reach() {
        return None;
    }
    let above = |s: f64| {
        c.surface(p[0] - q[0] * s, p[1] - q[1] * s)
            .is_some_and(|z| z >= s)
    };
    let n = 96;
    let step = h / n as f64;
    for i in 1..=n {
        let s = h - i as f64 * step;
        if above(s) {
            let (mut lo, mut hi) = (s, s + step);
            for _ in 0..40 {
                let mid = 0.5 * (lo + hi);
                if above(mid) {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            return Some(lo);
        }
    }
    None
}

/// A standard normal sample (Box–Muller).
fn gauss(rng: &mut ChaCha8Rng) -> f64 {
    let u1: f64 = rng.random_range(f64::EPSILON..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// Separable Gaussian blur with clamped borders (sigma 0 = unchanged).
pub fn gaussian_blur(img: &Plane<f64>, sigma: f64) -> Plane<f64> {
    if sigma <= 0.0 {
        return img.clone();
    }
    let r = (3.0 * sigma).ceil() as i64;
    let k: Vec<f64> = (-r..=r)
        .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let norm: f64 = k.iter().sum();
    let (w, h) = (img.width as i64, img.height as i64);
    let pass = |src: &Plane<f64>, horizontal: bool| -> Plane<f64> {
        let mut out = Plane::filled(src.width, src.height, 0.0);
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for (j, kv) in k.iter().enumerate() {
                    let o = j as i64 - r;
                    let (xx, yy) = if horizontal {
                        ((x + o).clamp(0, w - 1), y)
                    } else {
                        (x, (y + o).clamp(0, h - 1))
                    };
                    acc += kv * src.get(xx as usize, yy as usize);
                }
                *out.get_mut(x as usize, y as usize) = acc / norm;
            }
        }
        out
    };
    pass(&pass(img, true), false)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The placement of [`Scene::random`] checking every cell placed so far (no grid).
    fn placed_naively(optics: Optics, spec: &CellSpec, seed: u64) -> Vec<[f64; 4]> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_ce11);
        let s = optics.um_per_px();
        let (hw, hh) = (
            0.5 * optics.width as f64 * s,
            0.5 * optics.height as f64 * s,
        );
        let margin = 6.0 * s + 0.35 * spec.height[1];
        let grown = 1.0 + 3.0 * spec.irregular;
        let mut cells: Vec<CellShape> = Vec::new();
        for _ in 0..spec.count * 200 {
            if cells.len() == spec.count {
                break;
            }
            let d = rng.random_range(spec.diameter[0]..=spec.diameter[1]);
            let ecc = rng.random_range(0.75..=1.0);
            let (a, b) = (0.5 * d, 0.5 * d * ecc);
            let h = rng
                .random_range(spec.height[0]..=spec.height[1])
                .min(0.8 * d);
            let r = a * grown + margin;
            if 2.0 * r >= 2.0 * hw.min(hh) {
                continue;
            }
            let c = [
                rng.random_range(-hw + r..hw - r),
                rng.random_range(-hh + r..hh - r),
            ];
            if !cells.iter().all(|o| {
                (o.centre[0] - c[0]).hypot(o.centre[1] - c[1]) > a * grown + o.reach() + spec.gap
            }) {
                continue;
            }
            let mut cell = CellShape {
                centre: c,
                semi_axes: [a, b],
                angle: rng.random_range(0.0..std::f64::consts::PI),
                height: h,
                texture_offset: [rng.random_range(0.0..1e4), rng.random_range(0.0..1e4)],
                brightness: rng.random_range(-15.0..15.0),
                profile: spec.profile,
                outline: [0.0; 6],
                nucleus: centred_nucleus(),
            };
            spec.roughen(&mut cell, &mut rng);
            cells.push(cell);
        }
        cells
            .iter()
            .map(|c| [c.centre[0], c.centre[1], c.semi_axes[0], c.height])
            .collect()
    }

    #[test]
    fn a_fried_egg_s_nucleus_off_centre_is_its_top_and_its_volume_is_the_surface_s() {
        let cell = CellShape {
            centre: [0.0, 0.0],
            semi_axes: [30.0, 24.0],
            angle: 0.3,
            height: 12.0,
            texture_offset: [0.0; 2],
            brightness: 0.0,
            profile: Profile::FriedEgg,
            outline: [0.0; 6],
            nucleus: [0.35, 0.2, -0.15],
        };
        // The top is the nucleus' centre, at the cell's height; off the nucleus lies the
        // cytoplasm, 0.3·h·(1 − ρ⁴).
        let (nx, ny) = (0.2 * 30.0, -0.15 * 24.0);
        assert!((cell.surface(nx, ny).unwrap() - 12.0).abs() < 1e-9);
        let rho2: f64 = 0.5 * 0.5 + 0.3 * 0.3;
        let cytoplasm = 0.3 * 12.0 * (1.0 - rho2 * rho2);
        assert!((cell.surface(-0.5 * 30.0, 0.3 * 24.0).unwrap() - cytoplasm).abs() < 1e-9);
        // The volume integrated on the polar grid is the surface's, summed on a fine grid.
        let (v, _) = cell.volume_and_centroid_height();
        let step = 0.05;
        let mut sum = 0.0;
        for i in 0..(60.0 / step) as usize {
            for j in 0..(48.0 / step) as usize {
                let (x, y) = (
                    -30.0 + (i as f64 + 0.5) * step,
                    -24.0 + (j as f64 + 0.5) * step,
                );
                sum += cell.surface(x, y).unwrap_or(0.0) * step * step;
            }
        }
        assert!((v / sum - 1.0).abs() < 2e-3, "polar {v} grid {sum}");
    }

    #[test]
    fn the_grid_places_the_cells_every_cell_would_and_thousands_in_a_moment() {
        for (w, h, count, irregular, gap, dmax, seed) in [
            (640, 480, 40, 0.0, 12.0, 100.0, 1),
            (640, 480, 1000, 0.0, 12.0, 100.0, 2),
            (1280, 1024, 300, 0.3, 5.0, 60.0, 3),
            (300, 200, 50, 0.1, 0.0, 20.0, 4),
        ] {
            let optics = Optics {
                width: w,
                height: h,
                ..Optics::default()
            };
            let spec = CellSpec {
                count,
                diameter: [10.0, dmax],
                gap,
                irregular,
                ..CellSpec::default()
            };
            let scene = Scene::random(optics, Look::default(), &spec, seed);
            let got: Vec<[f64; 4]> = scene
                .cells
                .iter()
                .map(|c| [c.centre[0], c.centre[1], c.semi_axes[0], c.height])
                .collect();
            assert_eq!(got, placed_naively(optics, &spec, seed), "{w}×{h} {count}");
            assert!(!got.is_empty());
        }
        // 10 000 asked of an 8192² view (the list checked whole took tens of minutes).
        let optics = Optics {
            width: 8192,
            height: 8192,
            ..Optics::default()
        };
        let many = Scene::random(
            optics,
            Look::default(),
            &CellSpec {
                count: 10_000,
                ..CellSpec::default()
            },
            5,
        );
        assert!(many.cells.len() > 1000, "{}", many.cells.len());
    }

    #[test]
    fn substrate_has_zero_disparity_and_heights_give_the_designed_slope() {
        let o = Optics::default();
        assert!((o.disparity_at(o.working_distance())).abs() < 1e-9);
        let d10 = o.disparity_at(o.working_distance() - 10.0);
        assert!((d10 - 10.0 * o.px_per_um_height()).abs() < 0.01, "{d10}");
        assert!((o.px_per_um_height() - 0.3).abs() < 1e-9);
    }

    #[test]
    fn truth_disparity_triangulates_back_to_the_truth_depth() {
        let o = Optics {
            width: 160,
            height: 120,
            ..Optics::default()
        };
        let s = Scene::random(
            o,
            Look::default(),
            &CellSpec {
                count: 2,
                diameter: [30.0, 40.0],
                ..CellSpec::default()
            },
            4,
        );
        let r = s.render();
        let c = r.calibration;
        for i in (0..r.depth.len()).step_by(97) {
            let (x, y) = ((i % 160) as f64, (i / 160) as f64);
            let d = r.disparity.data[i] as f64;
            let z = c.baseline * c.focal_px / (d + c.cx_right - c.cx);
            assert!((z - r.depth.data[i] as f64).abs() < 1e-3 * z, "{x},{y}");
        }
    }

    #[test]
    fn each_cell_shows_its_dome_and_the_right_view_is_shifted_by_the_disparity() {
        let o = Optics {
            width: 200,
            height: 160,
            ..Optics::default()
        };
        let look = Look {
            noise: 0.0,
            ..Look::default()
        };
        let spec = CellSpec {
            count: 2,
            diameter: [40.0, 60.0],
            height: [10.0, 20.0],
            gap: 10.0,
            ..CellSpec::default()
        };
        let s = Scene::random(o, look, &spec, 9);
        assert_eq!(s.cells.len(), 2);
        let r = s.render();
        for t in &r.cells {
            // Top disparity = the largest truth disparity on the cell.
            let top = r
                .disparity
                .data
                .iter()
                .zip(&r.labels.data)
                .filter(|(_, l)| **l == t.id)
                .map(|(d, _)| *d as f64)
                .fold(0.0, f64::max);
            assert!(
                (top - t.disparity_base_top[1]).abs() < 0.05,
                "{top} vs {:?}",
                t.disparity_base_top
            );
            let (a, b) = (t.shape.semi_axes[0], t.shape.semi_axes[1]);
            let footprint = std::f64::consts::PI * a * b / o.um_per_px().powi(2);
            assert!(
                (t.area_px as f64 / footprint - 1.0).abs() < 0.08,
                "{} vs {footprint}",
                t.area_px
            );
        }
        // A left pixel on the top of a cell matches right pixel x − d (sub-pixel, bilinear).
        let t = &r.cells[0];
        let (x, y) = (
            t.centroid_px[0].round() as usize,
            t.centroid_px[1].round() as usize,
        );
        let d = *r.disparity.get(x, y) as f64;
        let xr = x as f64 - d;
        let (x0, fr) = (xr.floor() as usize, xr - xr.floor());
        let mut err = 0.0;
        for dy in 0..3 {
            for dx in 0..3 {
                let l = *r.left.get(x + dx - 1, y + dy - 1) as f64;
                let rr = (1.0 - fr) * *r.right.get(x0 + dx - 1, y + dy - 1) as f64
                    + fr * *r.right.get(x0 + dx, y + dy - 1) as f64;
                err += (l - rr).abs();
            }
        }
        assert!(err / 9.0 < 4.0, "mean photometric error {}", err / 9.0);
    }

    #[test]
    fn rays_meet_the_same_thing_among_the_cells_on_their_row_as_among_all() {
        let optics = Optics {
            width: 320,
            height: 240,
            ..Optics::default()
        };
        let spec = CellSpec {
            count: 12,
            ..CellSpec::default()
        };
        let cal = optics.calibration();
        let (mut hits, mut kept, mut rows) = (0, 0, 0);
        for seed in 1..4 {
            let scene = Scene::random(optics, Look::default(), &spec, seed).at_frame(2, 2.0, 0.0);
            let all: Vec<usize> = (0..scene.cells.len()).collect();
            for right in [false, true] {
                for v in 0..240 {
                    let sv = v as f64 + 0.25;
                    let row = scene.cells_on_row(sv, &cal);
                    (kept, rows) = (kept + row.len(), rows + all.len());
                    for u in 0..320 {
                        let (a, za) = scene.cast(right, u as f64, sv, &cal, &row, true);
                        let (b, zb) = scene.cast(right, u as f64, sv, &cal, &all, true);
                        assert_eq!(za.to_bits(), zb.to_bits(), "seed {seed} ({u}, {sv})");
                        assert_eq!(format!("{a:?}"), format!("{b:?}"));
                        hits += matches!(a, Hit::Cell(..)) as usize;
                    }
                }
            }
        }
        // The scenes have cells: the comparison covered hits, not only substrate; and most
        // cells are off most rows.
        assert!(hits > 10_000, "{hits}");
        assert!(kept * 2 < rows, "{kept} of {rows}");
    }

    #[test]
    fn same_seed_same_images() {
        let o = Optics {
            width: 64,
            height: 48,
            ..Optics::default()
        };
        let spec = CellSpec {
            count: 1,
            diameter: [20.0, 25.0],
            ..CellSpec::default()
        };
        let a = Scene::random(o, Look::default(), &spec, 3).render();
        let b = Scene::random(o, Look::default(), &spec, 3).render();
        assert_eq!(a.left, b.left);
        assert_eq!(a.right, b.right);
        let c = Scene::random(o, Look::default(), &spec, 4).render();
        assert_ne!(a.left, c.left);
    }

    /// Frames rendered over a backdrop are the full render's bytes, whatever the look, the
    /// tilt, the debris, the pipette and the frame; the textures stay, the noise changes.
    #[test]
    fn frames_over_a_backdrop_are_the_full_renders_bytes() {
        let o = Optics {
            width: 160,
            height: 120,
            ..Optics::default()
        };
        let spec = CellSpec {
            count: 3,
            diameter: [20.0, 40.0],
            irregular: 0.1,
            ..CellSpec::default()
        };
        let mut looks = vec![Look::default(), Look::brightfield()];
        looks[0].blur = 0.8;
        looks[1].supersample = 3;
        for (k, look) in looks.into_iter().enumerate() {
            for seed in 1..=3u64 {
                let mut scene = Scene::random(o, look.clone(), &spec, seed)
                    .with_substrate_disparity(4.0 * k as f64)
                    .with_debris(6, [1.0, 3.0], seed);
                scene.tilt = [0.02, -0.03];
                if seed != 2 {
                    scene.pipette = Some(Pipette {
                        tip: [-20.0, 5.0 * seed as f64],
                        height: 15.0,
                        tip_radius: 1.5,
                        taper: 0.08,
                        elevation: 0.1 * (seed as f64 - 1.0),
                        azimuth: 0.0,
                    });
                }
                if seed == 2 {
                    let cal = o.calibration();
                    let touched: usize = (0..o.height)
                        .map(|v| scene.touched(false, v, &cal).iter().filter(|t| **t).count())
                        .sum();
                    assert!(touched < o.width * o.height / 2, "{touched} pixels touched");
                }
                let mut backdrop = None;
                let mut first = None;
                for f in 0..3 {
                    let frame = scene.at_frame(f, 2.0, 15.0);
                    let fast = frame.render_views_over(&mut backdrop);
                    assert_eq!(fast, frame.render_views(), "look {k} seed {seed} frame {f}");
                    // A substrate pixel far from everything keeps its texture and changes
                    // only by the sensor noise.
                    let mean = frame.render_means().0;
                    match &first {
                        None => first = Some(mean),
                        Some(m0) => {
                            assert_eq!(m0.get(o.width - 2, 1), mean.get(o.width - 2, 1));
                        }
                    }
                }
                // Another stage makes another backdrop.
                let mut raised = scene.at_frame(1, 2.0, 15.0);
                raised.stage += 3.0;
                let fast = raised.render_views_over(&mut backdrop);
                assert_eq!(fast, raised.render_views(), "raised, look {k} seed {seed}");
            }
        }
    }

    /// The table's noise is Gaussian of the asked spread around the means, each view's its
    /// own, each frame's its own, and a frame's the same every time.
    #[test]
    fn table_noise_has_the_spread_and_no_ties_between_views_or_frames() {
        let (w, h) = (200, 150);
        let table = NoiseTable::new(w, h, 9);
        let means = Plane::filled(w, h, 100.0f64);
        let sigma = 3.0;
        let err =
            |p: &Plane<u8>| -> Vec<f64> { p.data.iter().map(|&v| v as f64 - 100.0).collect() };
        let (l0, r0) = table.apply((means.clone(), means.clone()), sigma, 0);
        let (l1, _) = table.apply((means.clone(), means.clone()), sigma, 1);
        assert_eq!(
            table.apply((means.clone(), means.clone()), sigma, 0),
            (l0.clone(), r0.clone())
        );
        let (e0, f0, e1) = (err(&l0), err(&r0), err(&l1));
        let n = e0.len() as f64;
        let mean = e0.iter().sum::<f64>() / n;
        // Rounding adds 1/12 to the variance.
        let sd = (e0.iter().map(|e| e * e).sum::<f64>() / n - 1.0 / 12.0).sqrt();
        assert!(mean.abs() < 0.05, "mean {mean}");
        assert!((sd / sigma - 1.0).abs() < 0.03, "sd {sd}");
        // Correlations: left against right at every shift a matcher might try, frame against
        // frame in place.
        let corr = |a: &[f64], b: &[f64], shift: usize| {
            let m = a.len() - shift;
            (0..m).map(|i| a[i + shift] * b[i]).sum::<f64>() / (m as f64 * sigma * sigma)
        };
        for shift in 0..40 {
            assert!(corr(&e0, &f0, shift).abs() < 0.02, "left-right at {shift}");
        }
        assert!(corr(&e0, &e1, 0).abs() < 0.02, "frame against frame");
    }
}
