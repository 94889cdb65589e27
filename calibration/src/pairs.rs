//! A rig calibrated from a folder of chessboard pairs (`microstereo calibrate-stereo`):
//! the pairs found by name ([`find_pairs`]), the board found in both views of each
//! ([`BoardPairs::add`]), both cameras and their pose fitted with the pairs that fit
//! badly left out ([`BoardPairs::calibrate`]), and what is written of it: the calibration
//! file, the report and each pair's corners drawn ([`PairResult::drawing`]).

use crate::board::{Board, find_board};
use crate::calibrate::{Corners, PairView, Stereo, calibrate_stereo, row_gap};
use crate::file::CalibrationFile;
use crate::stereo::{Rectification, StereoCalibration};
use image::{Rgb, RgbImage};
use imageproc::drawing::{draw_hollow_circle_mut, draw_line_segment_mut};
use schemas::{LengthUnit, Plane};
use std::path::{Path, PathBuf};

/// Why a folder of pairs gave no calibration (each message as the user reads it).
#[derive(Debug, thiserror::Error)]
pub enum PairsError {
    /// The boards do not determine the cameras: the fit's standard errors say so.
    #[error(
        "the pairs do not determine the cameras: {0}. Add pairs with the board tilted 20–45° in different directions and nearer and farther; for a stereo microscope (views a few degrees apart, nearly telecentric), whose boards cannot tilt that far, use calibrate-microscope with pairs at known stage heights"
    )]
    Undetermined(String),
    /// The folder cannot be listed.
    #[error("cannot read the pairs' directory '{}': {source}", dir.display())]
    ReadDir {
        /// The folder.
        dir: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// No file has a partner under the other prefix.
    #[error(
        "no image pairs in '{}': expected {left}NAME and {right}NAME files (PNG, JPEG or TIFF) with the same NAME; set --left-prefix/--right-prefix for other names",
        dir.display()
    )]
    NoPairs {
        /// The folder.
        dir: PathBuf,
        /// Prefix of the left images.
        left: String,
        /// Prefix of the right images.
        right: String,
    },
    /// The two views of a pair differ in size.
    #[error(
        "pair {name}: the left image is {}×{} but the right {}×{}; both cameras must give one size",
        left.0, left.1, right.0, right.1
    )]
    Sides {
        /// The pair.
        name: String,
        /// The left view's width and height.
        left: (usize, usize),
        /// The right view's.
        right: (usize, usize),
    },
    /// A pair differs in size from the first.
    #[error(
        "pair {name} is {}×{} but the first pair {}×{}: calibrate one image size at a time",
        size.0, size.1, first.0, first.1
    )]
    Size {
        /// The pair.
        name: String,
        /// Its size.
        size: (usize, usize),
        /// The first pair's.
        first: (usize, usize),
    },
    /// Too few pairs show the whole board in both views.
    #[error(
        "{usable} usable pairs of {pairs}; calibration needs at least 3 with the board seen whole in both views at different angles (see the reasons above)"
    )]
    TooFew {
        /// Pairs with the board found in both views and not left out.
        usable: usize,
        /// All pairs.
        pairs: usize,
    },
    /// The fit itself failed.
    #[error("{0}")]
    Fit(String),
}

/// One pair's two image files.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct PairFiles {
    /// What the two names share, without the extension.
    pub name: String,
    /// The left image.
    pub left: PathBuf,
    /// The right image.
    pub right: PathBuf,
}

/// The pairs in `dir`, by name: `<left_prefix>NAME` and `<right_prefix>NAME` images (PNG,
/// JPEG or TIFF by extension).
pub fn find_pairs(
    dir: &Path,
    left_prefix: &str,
    right_prefix: &str,
) -> Result<Vec<PairFiles>, PairsError> {
    let entries = std::fs::read_dir(dir).map_err(|source| PairsError::ReadDir {
        dir: dir.to_path_buf(),
        source,
    })?;
    let image = |p: &Path| {
        p.extension().and_then(|e| e.to_str()).is_some_and(|e| {
            matches!(
                e.to_ascii_lowercase().as_str(),
                "png" | "jpg" | "jpeg" | "tif" | "tiff"
            )
        })
    };
    let mut out = Vec::new();
    for e in entries.flatten() {
        let p = e.path();
        let Some(name) = p.file_name().and_then(|n| n.to_str()) else {
            continue;
        };
        if let Some(rest) = name.strip_prefix(left_prefix)
            && image(&p)
        {
            let right = dir.join(format!("{right_prefix}{rest}"));
            if right.exists() {
                let stem = Path::new(rest)
                    .file_stem()
                    .and_then(|s| s.to_str())
                    .unwrap_or(rest);
                out.push(PairFiles {
                    name: stem.to_string(),
                    left: p.clone(),
                    right,
                });
            }
        }
    }
    out.sort();
    if out.is_empty() {
        return Err(PairsError::NoPairs {
            dir: dir.to_path_buf(),
            left: left_prefix.to_string(),
            right: right_prefix.to_string(),
        });
    }
    Ok(out)
}

/// One pair's outcome.
#[derive(Clone, Debug)]
pub struct PairResult {
    /// The pair's name.
    pub name: String,
    /// The board in the left and right views (in one order), or why it was not found.
    pub boards: Result<(Board, Board), String>,
    /// Its reprojection error in the final fit (px; `None`: not used).
    pub rms: Option<f64>,
    /// Why it was left out of the fit although its boards were found.
    pub left_out: Option<String>,
    /// The left view.
    pub left: Plane<u8>,
    /// The right view.
    pub right: Plane<u8>,
}

impl PairResult {
    /// Why the pair is not in the fit (`None`: it is).
    pub fn why_not_used(&self) -> Option<String> {
        self.left_out
            .clone()
            .or_else(|| self.boards.as_ref().err().cloned())
    }

    /// Both views side by side, each found corner ringed, rows joined (the first row red,
    /// the rest green; grey when the pair was left out).
    pub fn drawing(&self) -> RgbImage {
        let (l, r) = (&self.left, &self.right);
        let left_out = self.left_out.is_some() || self.boards.is_err();
        let (w, h) = (l.width as u32, l.height as u32);
        let mut img = RgbImage::from_fn(2 * w, h, |x, y| {
            let v = if x < w {
                *l.get(x as usize, y as usize)
            } else {
                *r.get((x - w) as usize, y as usize)
            };
            Rgb([v, v, v])
        });
        if let Ok((lb, rb)) = &self.boards {
            for (b, dx) in [(lb, 0.0f32), (rb, w as f32)] {
                for (k, p) in b.corners.iter().enumerate() {
                    let colour = if left_out {
                        Rgb([160, 160, 160])
                    } else if k < b.cols {
                        Rgb([230, 40, 40])
                    } else {
                        Rgb([40, 210, 60])
                    };
                    let c = (p[0] as f32 + dx, p[1] as f32);
                    draw_hollow_circle_mut(
                        &mut img,
                        (c.0.round() as i32, c.1.round() as i32),
                        4,
                        colour,
                    );
                    if k % b.cols != 0 {
                        let q = b.corners[k - 1];
                        draw_line_segment_mut(&mut img, (q[0] as f32 + dx, q[1] as f32), c, colour);
                    }
                }
            }
        }
        img
    }
}

/// Pairs of views of one `cols × rows` board (inner corners), the board found in each.
#[derive(Clone, Debug)]
pub struct BoardPairs {
    cols: usize,
    rows: usize,
    size: Option<(usize, usize)>,
    pairs: Vec<PairResult>,
}

impl BoardPairs {
    /// No pairs yet, of a board with `cols × rows` inner corners.
    pub fn new(cols: usize, rows: usize) -> Self {
        Self {
            cols,
            rows,
            size: None,
            pairs: Vec::new(),
        }
    }

    /// Adds the pair `name` and finds the board in both its views; a board not found
    /// leaves the pair out of the fit, a size unlike the rest is an error.
    pub fn add(&mut self, name: &str, left: Plane<u8>, right: Plane<u8>) -> Result<(), PairsError> {
        let s = (left.width, left.height);
        if (right.width, right.height) != s {
            return Err(PairsError::Sides {
                name: name.to_string(),
                left: s,
                right: (right.width, right.height),
            });
        }
        let first = *self.size.get_or_insert(s);
        if first != s {
            return Err(PairsError::Size {
                name: name.to_string(),
                size: s,
                first,
            });
        }
        let (cols, rows) = (self.cols, self.rows);
        let found =
            |img, side: &str| find_board(img, cols, rows).map_err(|e| format!("{side} view: {e}"));
        let boards = found(&left, "left").and_then(|lb| {
            found(&right, "right").map(|mut rb| {
                rb.align_to(&lb);
                (lb, rb)
            })
        });
        self.pairs.push(PairResult {
            name: name.to_string(),
            boards,
            rms: None,
            left_out: None,
            left,
            right,
        });
        Ok(())
    }

    /// Both cameras and their pose fitted to the pairs whose board was found, squares
    /// `square` long. While the worst pair's reprojection error exceeds `max_pair_rms`
    /// (default: 3 times the pairs' median, at least 1 px) and more than 3 pairs are used,
    /// it is left out and the rest refitted. `note` is told each pair left out, as it is.
    pub fn calibrate(
        mut self,
        square: f64,
        max_pair_rms: Option<f64>,
        mut note: impl FnMut(String),
    ) -> Result<PairsFit, PairsError> {
        let (cols, rows) = (self.cols, self.rows);
        // Unset only without pairs, which the fit refuses before it is used.
        let size = self.size.unwrap_or((0, 0));
        let object: Vec<[f64; 2]> = (0..rows)
            .flat_map(|b| (0..cols).map(move |c| [c as f64 * square, b as f64 * square]))
            .collect();
        let fit = |results: &[PairResult]| -> Result<(Vec<usize>, Stereo), PairsError> {
            let used: Vec<usize> = (0..results.len())
                .filter(|&i| results[i].boards.is_ok() && results[i].left_out.is_none())
                .collect();
            if used.len() < 3 {
                return Err(PairsError::TooFew {
                    usable: used.len(),
                    pairs: results.len(),
                });
            }
            let (l, r): (Vec<Corners>, Vec<Corners>) = used
                .iter()
                .map(|&i| {
                    let (lb, rb) = results[i].boards.as_ref().expect("usable");
                    (lb.corners.clone(), rb.corners.clone())
                })
                .unzip();
            let s = calibrate_stereo(&l, &r, &object, size).map_err(PairsError::Fit)?;
            Ok((used, s))
        };
        for p in &self.pairs {
            if let Err(e) = &p.boards {
                note(format!("pair {}: {e}; left out", p.name));
            }
        }
        let results = &mut self.pairs;
        let (used, stereo) = loop {
            let (used, s) = fit(results)?;
            let mut sorted = s.pair_rms.clone();
            sorted.sort_by(f64::total_cmp);
            let limit = max_pair_rms.unwrap_or((3.0 * sorted[sorted.len() / 2]).max(1.0));
            let (k, worst) = s
                .pair_rms
                .iter()
                .enumerate()
                .max_by(|x, y| x.1.total_cmp(y.1))
                .map(|(k, v)| (k, *v))
                .expect("pairs");
            if worst > limit && used.len() > 3 {
                let p = &mut results[used[k]];
                note(format!(
                    "pair {}: fits badly (RMS {worst:.3} px, limit {limit:.3}); left out, refitting",
                    p.name
                ));
                p.left_out = Some(format!("RMS {worst:.3} px over the limit {limit:.3} px"));
                continue;
            }
            for (k, &i) in used.iter().enumerate() {
                results[i].rms = Some(s.pair_rms[k]);
            }
            break (used, s);
        };
        let [fl, fr] = [stereo.left[0], stereo.right[0]];
        let [sl, sr, sb] = stereo.std;
        let baseline = stereo.t.norm();
        let worst = (sl / fl).max(sr / fr).max(sb / baseline);
        if worst.is_nan() || worst > MAX_RELATIVE_STD {
            let pm = |v: f64, e: f64, digits: usize| {
                if e.is_finite() {
                    format!("{v:.digits$} ± {e:.digits$}")
                } else {
                    format!("{v:.digits$} (its error unbounded)")
                }
            };
            return Err(PairsError::Undetermined(format!(
                "focal lengths {} and {} px, baseline {}{}",
                pm(fl, sl, 1),
                pm(fr, sr, 1),
                pm(baseline, sb, 4),
                if worst.is_finite() {
                    format!(
                        " ({:.1} % at worst, at most {:.1} % is written)",
                        100.0 * worst,
                        100.0 * MAX_RELATIVE_STD
                    )
                } else {
                    String::new()
                }
            )));
        }
        let calibration = stereo.calibration(size);
        let rectification = Rectification::bouguet(&calibration);
        // The rectification's own check: each board row's mean rectified row in both views.
        let boards: Vec<PairView> = used
            .iter()
            .map(|&i| {
                let (lb, rb) = self.pairs[i].boards.as_ref().expect("used");
                (&lb.corners[..], &rb.corners[..])
            })
            .collect();
        let worst_row = row_gap(&rectification, &boards, cols);
        Ok(PairsFit {
            pairs: self.pairs,
            used: used.len(),
            stereo,
            calibration,
            rectification,
            worst_row,
            inner: (cols, rows),
            square,
        })
    }
}

/// The largest relative standard error of a focal length or the baseline that
/// `calibrate-stereo` writes a calibration with.
pub const MAX_RELATIVE_STD: f64 = 0.02;

/// A rig calibrated from board pairs.
#[derive(Clone, Debug)]
pub struct PairsFit {
    /// Every pair, in name order.
    pub pairs: Vec<PairResult>,
    /// How many pairs the final fit used.
    pub used: usize,
    /// The fit.
    pub stereo: Stereo,
    /// The rig as the rectifier reads it.
    pub calibration: StereoCalibration,
    /// Its Bouguet rectification.
    pub rectification: Rectification,
    /// The largest gap between a board row's mean rectified row in the left view and in
    /// the right (px).
    pub worst_row: f64,
    /// The board's inner corners, along a row and down a column.
    pub inner: (usize, usize),
    /// The side of a square, in the unit of lengths.
    pub square: f64,
}

impl PairsFit {
    /// The calibration file, lengths in `unit` (the unit of `square`).
    pub fn file(&self, unit: LengthUnit) -> CalibrationFile {
        CalibrationFile::from_stereo(&self.calibration, unit, Some(self.stereo.rms))
    }

    /// The comment heading the calibration file, the pairs read from `dir`.
    pub fn comment(&self, dir: &Path, unit: LengthUnit) -> String {
        format!(
            "Written by microstereo calibrate-stereo from {} of {} pairs in '{}' ({}x{} inner corners, squares of {} {}): RMS {:.4} px.\n{}",
            self.used,
            self.pairs.len(),
            dir.display(),
            self.inner.0,
            self.inner.1,
            self.square,
            unit.symbol(),
            self.stereo.rms,
            crate::file::LAYOUT
        )
    }

    /// The report: each pair's outcome, both cameras, the rectification and its check.
    pub fn report(&self, unit: LengthUnit) -> serde_json::Value {
        let (stereo, rect) = (&self.stereo, &self.rectification);
        serde_json::json!({
            "pairs": self.pairs.iter().map(|p| serde_json::json!({
                "name": p.name,
                "used": p.rms.is_some(),
                "rms_px": p.rms,
                "left_out": p.why_not_used(),
            })).collect::<Vec<_>>(),
            "rms_px": stereo.rms,
            "baseline": stereo.t.norm(),
            "standard_errors": {
                "left_fx_px": stereo.std[0], "right_fx_px": stereo.std[1], "baseline": stereo.std[2],
            },
            "unit": unit.symbol(),
            "left": stereo.left,
            "right": stereo.right,
            "rectified": {
                "focal_px": rect.f, "cx": rect.c[0], "cy": rect.c[1], "cx_right": rect.cx_right,
                "baseline": rect.baseline, "worst_board_row_px": self.worst_row,
            },
        })
    }

    /// One line: pairs used, RMS, baseline, both cameras' focal lengths, the rectified
    /// focal length and how well it puts the boards' rows on one row.
    pub fn summary(&self, unit: LengthUnit) -> String {
        let s = &self.stereo;
        format!(
            "{} of {} pairs used: RMS {:.4} px; baseline {:.3} ± {:.3} {u}; left fx {:.1} fy {:.1} px, right fx {:.1} fy {:.1} px (fx ± {:.1}, ± {:.1}); rectified: focal {:.1} px, every board row within {:.3} px of one row",
            self.used,
            self.pairs.len(),
            s.rms,
            s.t.norm(),
            s.std[2],
            s.left[0],
            s.left[1],
            s.right[0],
            s.right[1],
            s.std[0],
            s.std[1],
            self.rectification.f,
            self.worst_row,
            u = unit.symbol()
        )
    }
}
