//! Message types of microstereo, defined once.
//!
//! Every node, the CLI, the transport, the recorder and the viewer use these types, so a
//! disparity map or a point cloud means the same thing everywhere: a [`Plane`] is a dense
//! row-major image of any pixel type, a [`DisparityMap`] is a `Plane<f32>` where
//! [`INVALID_DISPARITY`] (+inf, as in Middlebury PFM files) marks "no value", and
//! [`Calibration`] carries what triangulation needs in explicit units.

pub mod msg;
pub mod wire;

use serde::{Deserialize, Serialize};

pub use msg::{
    CellLists, Cloud, CloudPoint, Disparity, DisparityPair, DisparityTile, DisparityTiles, Image,
    Labels, ManipulatorState, Message, PathPlan, Side, StereoFrame, Targets, Track, TrackState,
    Tracks,
};
pub use wire::{FrameHeader, MessageKind, PixelFormat};

/// Marker for "no disparity here": +inf, the Middlebury PFM convention.
pub const INVALID_DISPARITY: f32 = f32::INFINITY;

/// A dense, row-major image plane of any pixel type.
#[derive(Clone, Debug, PartialEq)]
pub struct Plane<T> {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// `width * height` pixels, row after row.
    pub data: Vec<T>,
}

impl<T: Clone> Plane<T> {
    /// A plane filled with one value.
    pub fn filled(width: usize, height: usize, value: T) -> Self {
        Self {
            width,
            height,
            data: vec![value; width * height],
        }
    }

    /// Wraps existing pixels; `None` when the length does not match the size.
    pub fn from_vec(width: usize, height: usize, data: Vec<T>) -> Option<Self> {
        (data.len() == width * height).then_some(Self {
            width,
            height,
            data,
        })
    }
}

impl<T> Plane<T> {
    /// The pixel at column `x`, row `y`.
    #[inline]
    pub fn get(&self, x: usize, y: usize) -> &T {
        &self.data[y * self.width + x]
    }

    /// Mutable access to the pixel at column `x`, row `y`.
    #[inline]
    pub fn get_mut(&mut self, x: usize, y: usize) -> &mut T {
        &mut self.data[y * self.width + x]
    }

    /// Row `y` as a slice.
    #[inline]
    pub fn row(&self, y: usize) -> &[T] {
        &self.data[y * self.width..(y + 1) * self.width]
    }

    /// Row `y` as a mutable slice.
    #[inline]
    pub fn row_mut(&mut self, y: usize) -> &mut [T] {
        &mut self.data[y * self.width..(y + 1) * self.width]
    }

    /// Total number of pixels.
    pub fn len(&self) -> usize {
        self.data.len()
    }

    /// True for a 0×N or N×0 plane.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }
}

/// Left- or right-based disparity in pixels; [`INVALID_DISPARITY`] where unknown.
///
/// Sign convention everywhere: a left pixel `x` with disparity `d` matches right pixel
/// `x - d`; a right-based map stores the same `d`, so right pixel `xr` matches `xr + d`.
pub type DisparityMap = Plane<f32>;

/// A binary mask: 0 = off, 255 = on (so it can be saved as a PNG unchanged).
pub type Mask = Plane<u8>;

/// True when a disparity value is usable.
#[inline]
pub fn is_valid_disparity(d: f32) -> bool {
    d.is_finite()
}

/// Share of valid pixels of a disparity map, 0..1.
pub fn density(map: &DisparityMap) -> f64 {
    if map.is_empty() {
        return 0.0;
    }
    map.data.iter().filter(|d| d.is_finite()).count() as f64 / map.len() as f64
}

/// Inclusive integer disparity search range; negative values are allowed (convergent optics).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct DisparityRange {
    /// Smallest disparity searched.
    pub min: i32,
    /// Largest disparity searched.
    pub max: i32,
}

impl DisparityRange {
    /// A range `min..=max`.
    pub const fn new(min: i32, max: i32) -> Self {
        Self { min, max }
    }

    /// Number of disparities searched.
    pub fn count(&self) -> usize {
        (self.max - self.min + 1).max(0) as usize
    }
}

/// Length unit of a calibration and of everything triangulated with it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum LengthUnit {
    /// Micrometres: microscope scenes.
    #[serde(alias = "µm", alias = "micrometre", alias = "micrometer")]
    Um,
    /// Millimetres: bench-top stereo rigs and Middlebury scenes.
    #[default]
    Mm,
    /// Metres.
    M,
}

impl LengthUnit {
    /// The unit in metres (to convert between units).
    pub fn metres(&self) -> f64 {
        match self {
            LengthUnit::Um => 1e-6,
            LengthUnit::Mm => 1e-3,
            LengthUnit::M => 1.0,
        }
    }

    /// Short symbol for reports and file headers.
    pub fn symbol(&self) -> &'static str {
        match self {
            LengthUnit::Um => "µm",
            LengthUnit::Mm => "mm",
            LengthUnit::M => "m",
        }
    }
}

/// Rectified parallel-axis stereo geometry, everything triangulation needs.
///
/// `focal_px` is the focal length in pixels; for a microscope it is f_eff / pixel pitch
/// (see [`Calibration::from_microscope`]). Principal points are in pixels of the rectified
/// images; `cx_right` differs from `cx` in convergent or shifted set-ups.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    /// Distance between the two optical centres, in `unit`.
    pub baseline: f64,
    /// Focal length in pixels.
    pub focal_px: f64,
    /// Principal point column of the left image.
    pub cx: f64,
    /// Principal point row (shared by both rectified images).
    pub cy: f64,
    /// Principal point column of the right image.
    pub cx_right: f64,
    /// Unit of `baseline` and of every triangulated coordinate.
    pub unit: LengthUnit,
}

impl Calibration {
    /// A microscope calibration: effective focal length and pixel pitch in the same unit.
    pub fn from_microscope(
        baseline: f64,
        f_eff: f64,
        pixel_pitch: f64,
        cx: f64,
        cy: f64,
        unit: LengthUnit,
    ) -> Self {
        Self {
            baseline,
            focal_px: f_eff / pixel_pitch,
            cx,
            cy,
            cx_right: cx,
            unit,
        }
    }
}

/// One triangulated point with the left image's colour.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Point3 {
    /// Horizontal position, origin midway between the cameras.
    pub x: f64,
    /// Vertical position (image rows grow downwards, so does Y).
    pub y: f64,
    /// Depth along the optical axis.
    pub z: f64,
    /// Colour from the left image (grey images give r = g = b).
    pub rgb: [u8; 3],
    /// Left image column the point came from.
    pub col: u32,
    /// Left image row the point came from.
    pub row: u32,
}

/// A metric point cloud: valid points only.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct PointCloud {
    /// Unit of every coordinate.
    pub unit: LengthUnit,
    /// The points, in left-image row-major order.
    pub points: Vec<Point3>,
}

/// The paper's validation figures (Fig. 13): how left→right and right→left matches agree.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct ValidationFigures {
    /// Left pixels with a left→right match (the denominator of the shares below).
    pub matched: u64,
    /// Share whose right→left match agrees exactly (tolerance 0).
    pub consistent_exact: f64,
    /// Share off by exactly one pixel.
    pub off_by_one: f64,
    /// Share off by more than one pixel, or whose partner has no match.
    pub off_by_more: f64,
    /// Share consistent within the tolerance used by the check.
    pub consistent_within_tolerance: f64,
    /// The tolerance used by the check, in pixels.
    pub tolerance: u32,
}

/// Axis-aligned pixel box `[x0, x1] × [y0, y1]`, inclusive.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct BoundingBox {
    /// First column.
    pub x0: u32,
    /// First row.
    pub y0: u32,
    /// Last column.
    pub x1: u32,
    /// Last row.
    pub y1: u32,
}

/// One segmented cell in one image: what segmentation hands to matching and the manipulator.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Cell {
    /// Label in the label image (1, 2, …, in raster order of the first pixel).
    pub id: u32,
    /// Pixels.
    pub area: u64,
    /// Mean pixel position `[x, y]`.
    pub centroid: [f64; 2],
    /// Extent.
    pub bbox: BoundingBox,
    /// Closed outer boundary `[x, y]`, counter-clockwise on screen, first pixel the
    /// cell's first in raster order (not repeated at the end).
    pub contour: Vec<[u32; 2]>,
    /// Length of the contour's chain code: 1 per axis step, √2 per diagonal.
    pub perimeter: f64,
}

/// Per-cell 3D figures from a stereo pair, in the calibration's unit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Cell3 {
    /// Id of the cell in the left image's segmentation.
    pub id: u32,
    /// Id of the paired cell in the right image's segmentation.
    pub right_id: u32,
    /// Left-image pixels of the cell.
    pub area_px: u64,
    /// Left-image centroid `[x, y]` in pixels: of the segmented cell, grown on a textured
    /// background by the pixels the views show off the substrate's plane.
    pub centroid_px: [f64; 2],
    /// Disparity of the cell's top, pixels: a photometric dome fit over the cell's upper
    /// part (the 98th percentile of the matched map where the fit fails).
    pub disparity: f64,
    /// 3D centroid `[X, Y, Z]` of the cell's surface points.
    pub centroid: [f64; 3],
    /// Depth of the substrate under the cell (where it came from: `quality.substrate`).
    pub substrate_z: f64,
    /// Height of the cell's top above the substrate; `None` when the top was not found
    /// above the substrate (never a negative height). Trust it only with `quality.trusted`.
    pub height: Option<f64>,
    /// Volume between the cell's surface and the substrate.
    pub volume: f64,
    /// The contour lifted onto the substrate plane: `[X, Y, Z]` per contour pixel.
    pub contour: Vec<[f64; 3]>,
    /// Share of the cell's pixels with a valid disparity after the LR check, 0..1.
    pub valid_share: f64,
    /// How far the height can be trusted, and why not.
    #[serde(default)]
    pub quality: CellQuality,
}

/// Where the substrate under a cell came from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SubstrateSource {
    /// The background's disparity plane, fitted over the whole textured background.
    Plane,
    /// The cell's own rim: the band just outside its outline.
    Rim,
    /// The plane through the other cells' rims.
    Rims,
    /// The median matched disparity on a ring around the cell (weakest).
    Ring,
    /// Nothing: no height.
    #[default]
    None,
}

/// Per-cell quality of a height.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CellQuality {
    /// Where the substrate under the cell came from.
    pub substrate: SubstrateSource,
    /// Standard error of the substrate's disparity under the cell, px.
    pub substrate_std: f64,
    /// Standard error of the height, in the calibration's unit (`None` without a height).
    pub height_std: Option<f64>,
    /// Robust scale of the top fit's intensity residual, grey levels (`None`: no fit).
    pub residual: Option<f64>,
    /// Whether the height can be trusted: its sources agree and it is sure to 2.5 %.
    pub trusted: bool,
    /// Why not, when it cannot.
    pub doubt: Option<String>,
}

/// A disparity plane `d(x, y) = d0 + dx·(x − centre.x) + dy·(y − centre.y)`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DisparityPlane {
    /// Disparity at `centre`, px.
    pub d0: f64,
    /// Change per pixel along x.
    pub dx: f64,
    /// Change per pixel along y.
    pub dy: f64,
    /// Where `d0` applies `[x, y]`.
    pub centre: [f64; 2],
    /// Formal standard error of `d0` (px); neighbouring residuals correlate, so the real one
    /// is larger.
    pub std: f64,
    /// Pixels used.
    pub pixels: u64,
}

impl DisparityPlane {
    /// The plane's disparity at `(x, y)`.
    pub fn at(&self, x: f64, y: f64) -> f64 {
        self.d0 + self.dx * (x - self.centre[0]) + self.dy * (y - self.centre[1])
    }
}
