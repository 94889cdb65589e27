//! What `microstereo segment` reports: the truth mask it scores against, cells.json and
//! the summary it prints.

use crate::{SegmentParams, Segmentation, TruthScore};
use schemas::{Cell, Mask, Plane};
use serde::Serialize;
use std::path::{Path, PathBuf};

/// A truth mask that cannot score this image.
#[derive(Debug, thiserror::Error)]
pub enum TruthError {
    /// The mask is not the image's size.
    #[error(
        "truth mask '{}' is {}×{} but the image is {}×{}; give the mask of this image",
        path.display(), mask.0, mask.1, image.0, image.1
    )]
    Size {
        /// The mask's file.
        path: PathBuf,
        /// The mask's width and height.
        mask: (usize, usize),
        /// The image's width and height.
        image: (usize, usize),
    },
}

/// The cell mask (255 = cell) of a grey truth image read from `path`, of an image
/// `width`×`height`: non-zero is cell, or zero where `inverted` (BBBC003's raw TIFFs).
pub fn truth_mask(
    truth: &Plane<u8>,
    path: &Path,
    (width, height): (usize, usize),
    inverted: bool,
) -> Result<Mask, TruthError> {
    if (truth.width, truth.height) != (width, height) {
        return Err(TruthError::Size {
            path: path.into(),
            mask: (truth.width, truth.height),
            image: (width, height),
        });
    }
    let data = truth
        .data
        .iter()
        .map(|&v| if (v != 0) != inverted { 255 } else { 0 })
        .collect();
    Ok(Plane::from_vec(width, height, data).expect("same size"))
}

/// What `segment` writes to cells.json.
#[derive(Serialize)]
pub struct SegmentReport<'a> {
    image: String,
    width: usize,
    height: usize,
    params: &'a SegmentParams,
    /// Largest local standard deviation (or variance), grey levels: 255 on variance.png.
    variance_max: f32,
    /// The image's noise (local standard deviation of its quietest tenth), grey levels.
    noise_std: f32,
    otsu_threshold: Option<u8>,
    threshold: u16,
    histogram: Vec<u64>,
    truth: Option<TruthScore>,
    cells: &'a [Cell],
}

impl<'a> SegmentReport<'a> {
    /// The report of `seg`, the segmentation of `image` by `params`, scored by `truth`.
    pub fn new(
        image: &Path,
        seg: &'a Segmentation,
        params: &'a SegmentParams,
        truth: Option<TruthScore>,
    ) -> Self {
        SegmentReport {
            image: image.display().to_string(),
            width: seg.mask.width,
            height: seg.mask.height,
            params,
            variance_max: seg.variance_max,
            noise_std: seg.noise,
            otsu_threshold: seg.otsu,
            threshold: seg.threshold,
            histogram: seg.histogram.to_vec(),
            truth,
            cells: &seg.cells,
        }
    }
}

/// The lines `segment` prints about `seg` (made in `ms` milliseconds), scored by `truth`.
pub fn summary(seg: &Segmentation, ms: f64, truth: Option<&TruthScore>) -> Vec<String> {
    let mut lines = vec![match seg.otsu {
        Some(o) => format!(
            "Otsu threshold {o} of 255 (applied {}; 255 = local std {:.1} grey levels)",
            seg.threshold, seg.variance_max
        ),
        None => "flat image: no threshold, no cells".into(),
    }];
    lines.push(format!("{} cells in {ms:.1} ms", seg.cells.len()));
    if let Some(s) = truth {
        lines.push(format!(
            "truth: Dice {:.3}, {} cells found / {} in the truth ({:+.1} %)",
            s.dice,
            s.found_cells,
            s.truth_cells,
            100.0 * s.count_error
        ));
    }
    lines
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{score, segment};

    #[test]
    fn truth_mask_thresholds_either_way_round() {
        let t = Plane::from_vec(3, 1, vec![0u8, 1, 200]).unwrap();
        let p = Path::new("t.png");
        assert_eq!(
            truth_mask(&t, p, (3, 1), false).unwrap().data,
            [0, 255, 255]
        );
        assert_eq!(truth_mask(&t, p, (3, 1), true).unwrap().data, [255, 0, 0]);
    }

    #[test]
    fn truth_mask_of_another_size_is_refused() {
        let t = Plane::filled(4, 2, 0u8);
        let e = truth_mask(&t, Path::new("m.png"), (5, 3), false).unwrap_err();
        assert_eq!(
            e.to_string(),
            "truth mask 'm.png' is 4×2 but the image is 5×3; give the mask of this image"
        );
    }

    #[test]
    fn flat_image_reports_no_threshold_and_scores_zero() {
        let img = Plane::filled(20, 10, 100u8);
        let params = SegmentParams::default();
        let seg = segment(&img, &params);
        let truth = Plane::filled(20, 10, 255u8);
        let s = score(&seg.mask, &truth, seg.cells.len());
        assert_eq!(
            summary(&seg, 0.04, Some(&s)),
            [
                "flat image: no threshold, no cells",
                "0 cells in 0.0 ms",
                "truth: Dice 0.000, 0 cells found / 1 in the truth (-100.0 %)",
            ]
        );
        let json =
            serde_json::to_value(SegmentReport::new(Path::new("a.png"), &seg, &params, None))
                .unwrap();
        assert_eq!(json["image"], "a.png");
        assert_eq!(
            (json["width"].as_u64(), json["height"].as_u64()),
            (Some(20), Some(10))
        );
        assert_eq!(json["otsu_threshold"], serde_json::Value::Null);
        assert_eq!(json["threshold"], 256);
        assert_eq!(json["histogram"][0], 200);
        assert_eq!(json["cells"], serde_json::json!([]));
    }

    #[test]
    fn summary_names_the_threshold_and_count_error() {
        let mut seg = segment(&Plane::filled(4, 4, 0u8), &SegmentParams::default());
        seg.otsu = Some(115);
        seg.threshold = 120;
        seg.variance_max = 3.84;
        let s = TruthScore {
            dice: 0.8714,
            truth_cells: 1,
            found_cells: 3,
            count_error: 2.0,
        };
        assert_eq!(
            summary(&seg, 2.76, Some(&s)),
            [
                "Otsu threshold 115 of 255 (applied 120; 255 = local std 3.8 grey levels)",
                "0 cells in 2.8 ms",
                "truth: Dice 0.871, 3 cells found / 1 in the truth (+200.0 %)",
            ]
        );
        assert_eq!(summary(&seg, 1.0, None).len(), 2);
    }
}
