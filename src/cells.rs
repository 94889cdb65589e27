//! Cells end to end: segmentation outputs, and (for `reconstruct --cells`) pairing the
//! cells of both views, matching inside them only and measuring each in 3D.

use crate::io::{self, IoError};
use crate::render;
use schemas::{Cell, Mask, Plane};
use segment::{SegmentParams, Segmentation};
use serde::Serialize;
use std::path::Path;

/// How a segmentation compares with a ground-truth mask.
#[derive(Clone, Copy, Debug, Serialize, PartialEq)]
pub struct TruthScore {
    /// Foreground Dice overlap.
    pub dice: f64,
    /// 8-connected components of the truth mask.
    pub truth_cells: u32,
    /// Cells found.
    pub found_cells: usize,
    /// `found / truth − 1`.
    pub count_error: f64,
}

/// Scores a segmentation mask against a truth mask (non-zero = cell) of the same size.
pub fn score(mask: &Mask, truth: &Mask, found: usize) -> TruthScore {
    let (_, n) = segment::label(truth, segment::Connectivity::Eight);
    TruthScore {
        dice: segment::dice(mask, truth),
        truth_cells: n,
        found_cells: found,
        count_error: if n == 0 {
            if found == 0 { 0.0 } else { f64::INFINITY }
        } else {
            found as f64 / n as f64 - 1.0
        },
    }
}

/// What `segment` writes to cells.json.
#[derive(Serialize)]
struct SegmentReport<'a> {
    image: String,
    width: usize,
    height: usize,
    params: &'a SegmentParams,
    /// Largest local standard deviation (or variance), grey levels: 255 on variance.png.
    variance_max: f32,
    otsu_threshold: Option<u8>,
    threshold: u16,
    histogram: Vec<u64>,
    truth: Option<TruthScore>,
    cells: &'a [Cell],
}

/// Writes labels.png, overlay.png, variance.png, histogram.png and cells.json into `dir`.
pub fn write_segmentation(
    dir: &Path,
    image: &Path,
    rgb: &Plane<[u8; 3]>,
    seg: &Segmentation,
    params: &SegmentParams,
    truth: Option<TruthScore>,
) -> Result<(), IoError> {
    let werr = |p: &Path, e: &dyn std::fmt::Display| IoError::Write {
        path: p.into(),
        reason: e.to_string(),
    };
    std::fs::create_dir_all(dir).map_err(|e| werr(dir, &e))?;
    render::write_labels_png(&dir.join("labels.png"), &seg.labels)?;
    let ov = dir.join("overlay.png");
    render::overlay(rgb, &seg.cells)
        .save(&ov)
        .map_err(|e| werr(&ov, &e))?;
    io::write_mask_png(&dir.join("variance.png"), &seg.variance)?;
    let hp = dir.join("histogram.png");
    render::histogram_chart(&seg.histogram, Some(seg.threshold))
        .save(&hp)
        .map_err(|e| werr(&hp, &e))?;
    let report = SegmentReport {
        image: image.display().to_string(),
        width: rgb.width,
        height: rgb.height,
        params,
        variance_max: seg.variance_max,
        otsu_threshold: seg.otsu,
        threshold: seg.threshold,
        histogram: seg.histogram.to_vec(),
        truth,
        cells: &seg.cells,
    };
    let jp = dir.join("cells.json");
    let json = serde_json::to_string_pretty(&report).expect("serialises");
    std::fs::write(&jp, json + "\n").map_err(|e| werr(&jp, &e))
}
