//! What `reconstruct` reports: `report.json` of a whole-frame run, `cells.json` of a
//! cells-only run, and one line per cell.

use crate::range::RangeScore;
use crate::stereo::Stereo;
use matcher::Mode;
use matcher::node::MatchParams;
use postprocess::PostParams;
use schemas::{
    Cell3, CellLists, Cloud, DisparityMap, DisparityRange, DisparityTiles, LengthUnit, Targets,
};
use serde::Serialize;
use validate::node::ValidateParams;

/// Every file `reconstruct` may write into its output directory.
pub const OUTPUT_NAMES: &[&str] = &[
    "disparity.pfm",
    "disparity_raw.pfm",
    "disparity.png",
    "disparity_color.png",
    "occlusion_left.png",
    "occlusion_right.png",
    "labels_left.png",
    "labels_right.png",
    "overlay_left.png",
    "points.ply",
    "report.json",
    "range_curve.png",
    "cells.json",
    "report.html",
];

/// The preset's parameters as report.json lists them.
#[derive(Serialize)]
pub struct Config<'a> {
    /// The match node's.
    #[serde(rename = "match")]
    pub matching: &'a MatchParams,
    /// The validate node's.
    pub validate: &'a ValidateParams,
    /// The postprocess node's.
    pub postprocess: &'a Option<PostParams>,
}

/// What `report.json` holds.
#[derive(Serialize)]
pub struct PairReport<'a> {
    /// The matcher.
    pub mode: Mode,
    /// The left image.
    pub left: String,
    /// The right image.
    pub right: String,
    /// Map width, px.
    pub width: usize,
    /// Map height, px.
    pub height: usize,
    /// The range matched.
    pub range: DisparityRange,
    /// The range selection's curve, where the range was selected.
    pub auto_range_curve: Option<Vec<RangeScore>>,
    /// The nodes' parameters.
    pub config: Config<'a>,
    /// The LR check's figures.
    pub validation: schemas::ValidationFigures,
    /// Pixels with a disparity after the LR check, over all.
    pub density_raw: f64,
    /// Pixels with a disparity after post-processing, over all.
    pub density: f64,
    /// Disparities the matcher evaluated.
    pub evaluations: u64,
    /// Points in the cloud, where the run triangulated.
    pub points: Option<usize>,
    /// The cloud's length unit.
    pub unit: Option<&'static str>,
    /// Each step's time, ms.
    pub times_ms: serde_json::Map<String, serde_json::Value>,
    /// Their sum, ms.
    pub total_ms: f64,
}

impl<'a> PairReport<'a> {
    /// The report of `preset`'s run: its LR-checked tiles and map, its final map, its
    /// cloud, the range (and the selection's curve) and the steps' times.
    pub fn new(
        preset: &'a Stereo,
        (checked, raw, disparity): (&DisparityTiles, &DisparityMap, &DisparityMap),
        cloud: Option<(&Cloud, &Targets)>,
        (range, curve): (DisparityRange, Option<Vec<RangeScore>>),
        times_ms: serde_json::Map<String, serde_json::Value>,
    ) -> Self {
        let total_ms: f64 = times_ms.values().filter_map(|v| v.as_f64()).sum();
        PairReport {
            mode: preset.matching.mode,
            left: preset.left.display().to_string(),
            right: preset.right.display().to_string(),
            width: disparity.width,
            height: disparity.height,
            range,
            auto_range_curve: curve,
            config: Config {
                matching: &preset.matching,
                validate: &preset.validate,
                postprocess: &preset.post,
            },
            validation: checked.tiles[0].figures.unwrap_or_default(),
            density_raw: schemas::density(raw),
            density: schemas::density(disparity),
            evaluations: checked.evaluations(),
            points: cloud.map(|(c, _)| c.points.len()),
            unit: cloud.map(|(_, t)| unit_of(&t.unit).symbol()),
            times_ms,
            total_ms,
        }
    }
}

/// The unit a message names by its symbol (millimetres for any other).
pub fn unit_of(symbol: &str) -> LengthUnit {
    match symbol {
        "µm" => LengthUnit::Um,
        "m" => LengthUnit::M,
        _ => LengthUnit::Mm,
    }
}

/// What `reconstruct --cells` writes to cells.json.
#[derive(Serialize)]
pub struct CellsReport<'a> {
    /// The left image.
    pub left: String,
    /// The right image.
    pub right: String,
    /// Map width, px.
    pub width: usize,
    /// Map height, px.
    pub height: usize,
    /// The range matched.
    pub range: DisparityRange,
    /// The length unit of the cells' figures.
    pub unit: &'a str,
    /// The segment node's parameters.
    pub segmentation: &'a Option<segment::SegmentParams>,
    /// Cells in the left view.
    pub cells_left: usize,
    /// Cells in the right view.
    pub cells_right: usize,
    /// Cell pairs matched.
    pub pairs: usize,
    /// Pixels handed to the matcher over the image's pixels.
    pub matched_share: f64,
    /// The substrate's disparity plane over the background (absent: each cell's ring
    /// median stood in).
    pub substrate_plane: Option<schemas::DisparityPlane>,
    /// Each step's time, ms.
    pub times_ms: serde_json::Map<String, serde_json::Value>,
    /// The cells in 3D.
    pub cells: &'a [Cell3],
}

impl<'a> CellsReport<'a> {
    /// The report of `preset`'s cells-only run: both views' cells, the checked tiles, the
    /// cells in 3D, the final map and the steps' times.
    pub fn new(
        preset: &'a Stereo,
        (lists, tiles, targets): (&CellLists, &DisparityTiles, &'a Targets),
        d: &DisparityMap,
        times_ms: serde_json::Map<String, serde_json::Value>,
    ) -> Self {
        let (w, h) = (d.width, d.height);
        CellsReport {
            left: preset.left.display().to_string(),
            right: preset.right.display().to_string(),
            width: w,
            height: h,
            range: preset.matching.range(),
            unit: unit_of(&targets.unit).symbol(),
            segmentation: &preset.segment,
            cells_left: lists.left.len(),
            cells_right: lists.right.len(),
            pairs: tiles.tiles.len(),
            matched_share: tiles.matched_pixels() as f64 / (w * h) as f64,
            substrate_plane: targets.substrate,
            times_ms,
            cells: &targets.cells,
        }
    }
}

/// One cell as `reconstruct --cells` prints it: centroid, height ± σ, volume, 3D centroid,
/// where its substrate came from, and why it is not trusted where it is not.
pub fn cell_line(c: &Cell3, u: &str) -> String {
    let height = match (c.height, c.quality.height_std) {
        (Some(h), Some(s)) => format!("height {h:.2} ± {s:.2} {u}"),
        (Some(h), None) => format!("height {h:.2} {u}"),
        (None, _) => "no height".into(),
    };
    let trust = match &c.quality.doubt {
        None => String::new(),
        Some(why) => format!(" — NOT TRUSTED: {why}"),
    };
    format!(
        "cell {:>3}: centroid ({:.1}, {:.1}) px, {height}, volume {:.0} {u}³, 3D centroid ({:.1}, {:.1}, {:.1}) {u}, substrate from {}{trust}",
        c.id,
        c.centroid_px[0],
        c.centroid_px[1],
        c.volume,
        c.centroid[0],
        c.centroid[1],
        c.centroid[2],
        serde_json::to_value(c.quality.substrate)
            .ok()
            .and_then(|v| v.as_str().map(String::from))
            .unwrap_or_default(),
    )
}
