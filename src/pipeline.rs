//! The stereo pipeline, in-process: match → LR check → post-process (→ triangulate).
//!
//! This is the one copy of the chain. `reconstruct`, `bench` and the tests call it; the
//! process graph will run the same node libraries one step per process.

use matcher::{Directions, InputError, Mode, PaperParams, QualityParams};
use postprocess::PostParams;
use runtime::StageTimes;
use schemas::{DisparityMap, DisparityRange, Plane, ValidationFigures};
use serde::Serialize;
use validate::Checked;

/// Everything that configures one stereo run.
#[derive(Clone, Debug, Serialize)]
pub struct StereoConfig {
    /// Which matcher.
    pub mode: Mode,
    /// Disparities searched.
    pub range: DisparityRange,
    /// Paper-mode settings (their `range` is overwritten by `range`).
    pub paper: PaperParams,
    /// Quality-mode settings (their `range` is overwritten by `range`).
    pub quality: QualityParams,
    /// LR check tolerance, 0..=4 px.
    pub lr_tolerance: u32,
    /// Post-processing.
    pub post: PostParams,
}

impl StereoConfig {
    /// Defaults of a mode over a range.
    pub fn new(mode: Mode, range: DisparityRange) -> Self {
        let post = match mode {
            Mode::Paper => PostParams {
                median_radius: 2,
                ..PostParams::default()
            },
            // Sub-pixel maps: smaller regions still count as one surface.
            Mode::Quality => PostParams {
                min_region: 100,
                region_max_diff: 1.0,
                median_radius: 2,
                fill: postprocess::Fill::Background,
            },
        };
        Self {
            mode,
            range,
            paper: PaperParams::default(),
            quality: QualityParams::default(),
            lr_tolerance: 1,
            post,
        }
    }

    /// The window the input checks apply: the paper window. Quality mode has none to
    /// check: its census pads the image borders, so any image size works.
    pub fn window(&self) -> Option<usize> {
        match self.mode {
            Mode::Paper => Some(self.paper.window),
            Mode::Quality => None,
        }
    }
}

/// Everything one stereo run produces.
#[derive(Clone, Debug)]
pub struct StereoOutput {
    /// Matcher output, left-based, before the LR check.
    pub matched_left: DisparityMap,
    /// Matcher output, right-based, before the LR check.
    pub matched_right: DisparityMap,
    /// After the LR check: `disparity_raw` and the occlusion masks.
    pub checked: Checked,
    /// The final, post-processed left disparity.
    pub disparity: DisparityMap,
    /// The paper's validation figures.
    pub figures: ValidationFigures,
    /// Milliseconds per stage.
    pub times: StageTimes,
    /// Pixel × disparity evaluations of the matcher.
    pub evaluations: u64,
}

/// Buffers a stream of stereo runs keeps from one frame to the next (a live graph node, a
/// benchmark); one-shot callers pass a fresh one.
#[derive(Debug, Default)]
pub struct Workspace {
    quality: matcher::QualityWorkspace,
}

/// Runs the matching stages (both directions) only.
pub fn match_pair(
    ws: &mut Workspace,
    left: &Plane<u8>,
    right: &Plane<u8>,
    cfg: &StereoConfig,
    times: &mut StageTimes,
) -> Result<(DisparityMap, DisparityMap, u64), InputError> {
    matcher::check_inputs(left, right, cfg.range, cfg.window())?;
    Ok(match cfg.mode {
        Mode::Paper => {
            let p = PaperParams {
                range: cfg.range,
                ..cfg.paper.clone()
            };
            let m = times.time("match", || {
                matcher::match_paper(left, right, &p, Directions::Both)
            });
            (m.left, m.right, m.evaluations)
        }
        Mode::Quality => {
            let p = QualityParams {
                range: cfg.range,
                ..cfg.quality.clone()
            };
            let m = times.time("match", || {
                matcher::match_quality_in(&mut ws.quality, left, right, &p)
            });
            (m.left, m.right, m.evaluations)
        }
    })
}

/// Runs the whole chain on a rectified grey pair.
pub fn run_stereo(
    left: &Plane<u8>,
    right: &Plane<u8>,
    cfg: &StereoConfig,
) -> Result<StereoOutput, InputError> {
    run_stereo_in(&mut Workspace::default(), left, right, cfg)
}

/// Runs the whole chain on a rectified grey pair in the buffers of `ws`.
pub fn run_stereo_in(
    ws: &mut Workspace,
    left: &Plane<u8>,
    right: &Plane<u8>,
    cfg: &StereoConfig,
) -> Result<StereoOutput, InputError> {
    let mut times = StageTimes::default();
    let (ml, mr, evaluations) = match_pair(ws, left, right, cfg, &mut times)?;
    let checked = times.time("validate", || {
        validate::lr_check(&ml, &mr, cfg.lr_tolerance)
    });
    let disparity = times.time("postprocess", || {
        postprocess::postprocess(&checked.left, &cfg.post)
    });
    Ok(StereoOutput {
        figures: checked.figures,
        matched_left: ml,
        matched_right: mr,
        checked,
        disparity,
        times,
        evaluations,
    })
}

/// One point of the range-selection curve (the paper's Fig. 12).
#[derive(Clone, Copy, Debug, Serialize, PartialEq)]
pub struct RangeScore {
    /// The range tried.
    pub range: DisparityRange,
    /// Consistent left pixels (within the LR tolerance) over all pixels with a candidate.
    pub consistency_ratio: f64,
}

/// How the candidate ranges are built from a list of radii.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, clap::ValueEnum)]
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

/// Picks the range with the highest consistency ratio; returns it and the whole curve.
/// Ties go to the narrower range (listed first).
pub fn auto_range(
    left: &Plane<u8>,
    right: &Plane<u8>,
    cfg: &StereoConfig,
    ranges: &[DisparityRange],
) -> Result<(DisparityRange, Vec<RangeScore>), InputError> {
    let mut curve = Vec::new();
    let mut ws = Workspace::default();
    for &range in ranges {
        let c = StereoConfig {
            range,
            ..cfg.clone()
        };
        let mut t = StageTimes::default();
        let (ml, mr, _) = match_pair(&mut ws, left, right, &c, &mut t)?;
        let checked = validate::lr_check(&ml, &mr, cfg.lr_tolerance);
        // Pixels that have at least one candidate: the right pixel x − d exists for some d.
        let w = left.width as i64;
        let cols = (0..w)
            .filter(|&x| (range.min as i64..=range.max as i64).any(|d| (0..w).contains(&(x - d))))
            .count();
        let total = (cols * left.height).max(1);
        let consistent = checked.left.data.iter().filter(|d| d.is_finite()).count();
        curve.push(RangeScore {
            range,
            consistency_ratio: consistent as f64 / total as f64,
        });
    }
    let best = curve
        .iter()
        .fold(None::<RangeScore>, |b, s| match b {
            Some(b) if b.consistency_ratio >= s.consistency_ratio => Some(b),
            _ => Some(*s),
        })
        .ok_or(InputError::EmptyRange { min: 0, max: 0 })?;
    Ok((best.range, curve))
}
