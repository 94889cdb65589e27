//! The paper's range selection: the disparity range whose matches are most consistent.

use crate::Error;
use crate::stereo::Stereo;
use schemas::DisparityRange;
use serde::Serialize;

/// How the candidate ranges are built from radii.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum RangeKind {
    /// `−r..r`: convergent microscope optics.
    Symmetric,
    /// `0..r`: parallel rigs.
    Positive,
}

/// The candidate ranges for radii `rs` that fit an image `width` wide.
pub fn candidate_ranges(kind: RangeKind, rs: &[u32], width: usize) -> Vec<DisparityRange> {
    rs.iter()
        .filter(|&&r| r > 0 && (r as usize) < width)
        .map(|&r| match kind {
            RangeKind::Symmetric => DisparityRange::new(-(r as i32), r as i32),
            RangeKind::Positive => DisparityRange::new(0, r as i32),
        })
        .collect()
}

/// One point of the range-selection curve (the paper's Fig. 12).
#[derive(Clone, Copy, Debug, Serialize, PartialEq)]
pub struct RangeScore {
    /// The range tried.
    pub range: DisparityRange,
    /// Consistent left pixels (within the LR tolerance) inside the range, not within half a
    /// pixel of its ends (where a match beyond it is clamped), over all pixels with a
    /// candidate.
    pub consistency_ratio: f64,
}

/// `base` (matching and its LR check) over each of `ranges`; the range with the highest
/// consistency ratio (ties: the narrower, listed first), and the whole curve. The ratio is
/// taken over the textured regions of the left view (the segmentation's mask) when they
/// are at least a twentieth of it: there the matches decide; elsewhere over every pixel.
pub fn auto_range(
    base: &Stereo,
    ranges: &[DisparityRange],
) -> Result<(DisparityRange, Vec<RangeScore>), Error> {
    let mut curve = Vec::new();
    let mut mask: Option<schemas::Mask> = None;
    for &range in ranges {
        let mut preset = Stereo {
            post: None,
            geometry: None,
            segment: None,
            ..base.clone()
        };
        preset.matching.min_disparity = range.min;
        preset.matching.max_disparity = range.max;
        let f = preset.run_once()?;
        let outs = preset.outs();
        if curve.is_empty() {
            mask = textured(&f.read(&outs.frame).map_err(Error::Node)?.left);
        }
        let checked = f.read(&outs.checked).map_err(Error::Node)?.paste();
        curve.push(RangeScore {
            range,
            consistency_ratio: validate::consistency_ratio_within(&checked, range, mask.as_ref()),
        });
    }
    let best = curve
        .iter()
        .fold(None::<RangeScore>, |b, s| match b {
            Some(b) if b.consistency_ratio >= s.consistency_ratio => Some(b),
            _ => Some(*s),
        })
        .ok_or(Error::NoRange)?;
    Ok((best.range, curve))
}

/// The segmentation's mask of `left` when it covers at least a twentieth of the view (less
/// is too little to score a range on).
fn textured(left: &schemas::Plane<u8>) -> Option<schemas::Mask> {
    let m = segment::segment(left, &segment::SegmentParams::default()).mask;
    let share = m.data.iter().filter(|&&v| v != 0).count() as f64 / m.len() as f64;
    (share >= 0.05).then_some(m)
}
