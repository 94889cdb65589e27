//! A stereo microscope calibrated from a chessboard moved through known stage heights
//! (`heights.csv`, the z-stack `calibrate-depth` reads): each view's model fitted to the
//! board's corners at their heights ([`crate::microscope::fit_view`]), the pair rectified
//! onto the stage plane, and the result refused, with the reason and what to add, when it
//! does not fix what it must.

use crate::board::find_board;
use crate::file::CalibrationFile;
use crate::microscope::{Observation, Rig, Uncertainty, ViewFit, fit_view, uncertainty};
use schemas::{LengthUnit, Plane};

/// A pair of views of the board at a stage height.
#[derive(Clone, Debug)]
pub struct StagePair {
    /// The pair's name (its left image's file name).
    pub name: String,
    /// The left view.
    pub left: Plane<u8>,
    /// The right view.
    pub right: Plane<u8>,
    /// The stage height, µm.
    pub z: f64,
}

/// What became of one pair.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct PairUse {
    /// The pair's name.
    pub name: String,
    /// Its stage height, µm.
    pub z: f64,
    /// Why it was not used (its board not found).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub not_used: Option<String>,
    /// Its corners' reprojection error, left and right (RMS, px).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rms: Option<[f64; 2]>,
}

/// A pair's stage height and its board's corners, left and right.
type Seen = (f64, Vec<[f64; 2]>, Vec<[f64; 2]>);

/// A microscope calibrated from a stage stack.
#[derive(Clone, Debug)]
pub struct StageFit {
    /// The rectified pair.
    pub rig: Rig,
    /// Both views' fits.
    pub fits: [ViewFit; 2],
    /// The standard errors of what it measures.
    pub uncertainty: Uncertainty,
    /// Each pair, used or not.
    pub pairs: Vec<PairUse>,
    /// Whether `heights.csv`'s heights grow away from the cameras (then turned round: the
    /// calibration's heights grow towards them).
    pub turned: bool,
    /// The stage heights' span, µm.
    pub span: [f64; 2],
    /// How far the parallel-axis pair is from the model over the field at the span's
    /// heights: rows (px) and heights (µm).
    pub holds: (f64, f64),
}

/// The depth scale's largest relative standard error a calibration is written with.
pub const MAX_SCALE_ERROR: f64 = 0.0025;
/// The largest reprojection error (px) of a view a calibration is written with.
pub const MAX_RMS: f64 = 0.5;

/// A board's corners refined again in a window a fifth of a square wide each way: the
/// finder's window is made for boards of 25–35 px squares, and a microscope's board (a
/// hundred pixels a square, blurred by defocus across a Greenough's tilted focal plane)
/// needs its corners' whole saddle, or the blur's gradient pulls them (0.2 px RMS and a
/// depth scale 1.9 % off at 7°, measured).
fn refined(img: &Plane<u8>, b: &crate::board::Board) -> Vec<[f64; 2]> {
    let c = &b.corners;
    let mut gaps = Vec::new();
    for r in 0..b.rows {
        for k in 0..b.cols - 1 {
            let (p, q) = (c[r * b.cols + k], c[r * b.cols + k + 1]);
            gaps.push((p[0] - q[0]).hypot(p[1] - q[1]));
        }
    }
    gaps.sort_by(f64::total_cmp);
    let square = gaps.get(gaps.len() / 2).copied().unwrap_or(0.0);
    let half = (0.2 * square).round().clamp(5.0, 30.0) as usize;
    if half <= crate::board::SUBPIX_HALF_WINDOW {
        return c.clone();
    }
    c.iter()
        .map(|&p| {
            let q = crate::board::corner_subpix(img, p, half);
            if q[0].is_finite() && q[1].is_finite() {
                q
            } else {
                p
            }
        })
        .collect()
}

/// The pairs left out and why, as the end of a sentence.
fn not_used(uses: &[PairUse]) -> String {
    let out: Vec<String> = uses
        .iter()
        .filter_map(|u| {
            u.not_used
                .as_ref()
                .map(|why| format!("{} (z {} µm): {why}", u.name, u.z))
        })
        .collect();
    if out.is_empty() {
        String::new()
    } else {
        format!("; not used: {}", out.join("; "))
    }
}

/// Calibrates the microscope from `pairs`, a board of `cols × rows` inner corners with
/// squares `square` µm; fails with the reason and what to add.
pub fn calibrate_stage(
    pairs: &[StagePair],
    cols: usize,
    rows: usize,
    square: f64,
) -> Result<StageFit, String> {
    let Some(first) = pairs.first() else {
        return Err(
            "no pairs: give a folder with heights.csv (left,right,z_um) and its images".into(),
        );
    };
    let size = (first.left.width, first.left.height);
    let mut uses = Vec::new();
    let mut seen: Vec<Seen> = Vec::new();
    let mut reference: Option<crate::board::Board> = None;
    for p in pairs {
        if (p.left.width, p.left.height) != size || (p.right.width, p.right.height) != size {
            return Err(format!(
                "pair '{}' is {}×{} / {}×{}, the first {}×{}: every image must have one size",
                p.name, p.left.width, p.left.height, p.right.width, p.right.height, size.0, size.1
            ));
        }
        let found = find_board(&p.left, cols, rows)
            .map_err(|e| format!("left view: {e}"))
            .and_then(|mut lb| {
                if let Some(r) = &reference {
                    lb.align_to(r);
                }
                find_board(&p.right, cols, rows)
                    .map_err(|e| format!("right view: {e}"))
                    .map(|mut rb| {
                        rb.align_to(&lb);
                        (lb, rb)
                    })
            });
        match found {
            Ok((lb, rb)) => {
                reference.get_or_insert_with(|| lb.clone());
                seen.push((p.z, refined(&p.left, &lb), refined(&p.right, &rb)));
                uses.push(PairUse {
                    name: p.name.clone(),
                    z: p.z,
                    not_used: None,
                    rms: None,
                });
            }
            Err(e) => uses.push(PairUse {
                name: p.name.clone(),
                z: p.z,
                not_used: Some(e),
                rms: None,
            }),
        }
    }
    let mut heights: Vec<f64> = seen.iter().map(|s| s.0).collect();
    heights.sort_by(f64::total_cmp);
    heights.dedup();
    if heights.len() < 3 {
        return Err(format!(
            "the board was found at {} stage height(s) ({} of {} pairs): the depth is undetermined; add pairs at three or more heights spanning the cells' depth (e.g. −40, −20, 0, 20, 40 µm), the whole board in both views{}",
            heights.len(),
            seen.len(),
            pairs.len(),
            not_used(&uses)
        ));
    }
    let span = [heights[0], heights[heights.len() - 1]];
    let observe = |turn: f64, right: bool| -> Vec<Observation> {
        seen.iter()
            .flat_map(|(z, l, r)| {
                let c = if right { r } else { l };
                c.iter().enumerate().map(move |(k, px)| Observation {
                    world: [
                        (k % cols) as f64 * square,
                        (k / cols) as f64 * square,
                        turn * z,
                    ],
                    pixel: *px,
                })
            })
            .collect()
    };
    let fit = |turn: f64| -> Result<[ViewFit; 2], String> {
        Ok([
            fit_view(&observe(turn, false), size).map_err(|e| format!("left view: {e}"))?,
            fit_view(&observe(turn, true), size).map_err(|e| format!("right view: {e}"))?,
        ])
    };
    let mut fits = fit(1.0)?;
    // Heights must grow towards the cameras: where both centres lie below the stage, the
    // file's heights run the other way.
    let below = |f: &ViewFit| {
        let c = f.model.centre();
        c.w != 0.0 && c.z / c.w < span[0]
    };
    let turned = below(&fits[0]) && below(&fits[1]);
    if turned {
        fits = fit(-1.0)?;
    }
    let worst = fits[0].rms.max(fits[1].rms);
    if worst > MAX_RMS {
        return Err(format!(
            "the corners do not follow one microscope model (reprojection error {:.2} px left, {:.2} px right; at most {MAX_RMS} is written): check that each row of heights.csv names the right images and that the board only moved up and down between them",
            fits[0].rms, fits[1].rms
        ));
    }
    let mid = 0.5 * (span[0] + span[1]) * if turned { -1.0 } else { 1.0 };
    let mut rig = Rig::new(fits[0].model.clone(), fits[1].model.clone(), size, mid)?;
    let turn = if turned { -1.0 } else { 1.0 };
    rig.field = observe(turn, false)
        .iter()
        .filter_map(|o| rig.rectified_of(false, o.world))
        .fold(None, |b: Option<[f64; 4]>, p| {
            let b = b.unwrap_or([p[0], p[1], p[0], p[1]]);
            Some([
                b[0].min(p[0]),
                b[1].min(p[1]),
                b[2].max(p[0]),
                b[3].max(p[1]),
            ])
        });
    let u = uncertainty(&rig, [&fits[0], &fits[1]]);
    let [k, k_std] = u.px_per_um;
    if k.is_nan() || k.abs() <= 1e-3 {
        return Err(format!(
            "the views barely converge ({k:.2e} px of disparity per µm of height): a stereo microscope's views are a few degrees apart; check that left and right are two views, not one"
        ));
    }
    if k_std / k.abs() > MAX_SCALE_ERROR {
        return Err(format!(
            "the depth scale is undetermined: {k:.4} ± {k_std:.4} px per µm ({:.2} %, at most {:.2} % is written); add pairs at more stage heights, spread over a wider span (now {} to {} µm), the whole board in both views{}",
            100.0 * k_std / k.abs(),
            100.0 * MAX_SCALE_ERROR,
            span[0],
            span[1],
            not_used(&uses)
        ));
    }
    let half = 0.5 * (span[1] - span[0]);
    let holds = rig.holds(half);
    let used = uses.iter_mut().filter(|u| u.not_used.is_none());
    for (u, (z, l, r)) in used.zip(&seen) {
        let rms = |f: &ViewFit, c: &[[f64; 2]]| {
            let s: f64 = c
                .iter()
                .enumerate()
                .map(|(k, px)| {
                    let w = [
                        (k % cols) as f64 * square,
                        (k / cols) as f64 * square,
                        if turned { -z } else { *z },
                    ];
                    let p = f.model.project(w).unwrap_or([f64::NAN; 2]);
                    (p[0] - px[0]).powi(2) + (p[1] - px[1]).powi(2)
                })
                .sum();
            (s / (2 * c.len()) as f64).sqrt()
        };
        u.rms = Some([rms(&fits[0], l), rms(&fits[1], r)]);
    }
    Ok(StageFit {
        rig,
        fits,
        uncertainty: u,
        pairs: uses,
        turned,
        span,
        holds,
    })
}

impl StageFit {
    /// The calibration file: the rectified pair's parallel-axis geometry at the top, the
    /// views and their rectification in `[microscope]`.
    pub fn file(&self) -> CalibrationFile {
        let c = self.rig.calibration();
        CalibrationFile {
            baseline: c.baseline,
            focal_px: Some(c.focal_px),
            f_eff: None,
            pixel_pitch: None,
            cx: Some(c.cx),
            cy: Some(c.cy),
            cx_right: Some(c.cx_right),
            unit: Some(LengthUnit::Um),
            stereo: None,
            microscope: Some(Box::new(self.rig.clone())),
        }
    }

    /// The disparity range (px, as matched) the stack's heights span, widened by half.
    pub fn disparity_range(&self) -> [f64; 2] {
        let half = 0.75 * (self.span[1] - self.span[0]);
        let a = self.rig.disparity_at(-half);
        let b = self.rig.disparity_at(half);
        [a.min(b), a.max(b)]
    }

    /// The report as JSON.
    pub fn report(&self) -> serde_json::Value {
        let u = &self.uncertainty;
        serde_json::json!({
            "model": "projective views of the stage frame with polynomial distortion, rectified onto the stage plane",
            "rms_px": [self.fits[0].rms, self.fits[1].rms],
            "corners": [self.fits[0].corners, self.fits[1].corners],
            "um_per_px": u.scale,
            "view_angle_deg": u.angle_deg,
            "pupil_um": u.pupil.map(|[d, s]| serde_json::json!({"distance": if d.is_finite() { serde_json::json!(d) } else { serde_json::json!("telecentric") }, "inverse_std": s})),
            "px_per_um_height": u.px_per_um,
            "stage_span_um": self.span,
            "heights_turned": self.turned,
            "disparity_range_px": self.disparity_range(),
            "field_px": self.rig.field,
            "rectified_rows_within_px": self.holds.0,
            "parallel_axis_heights_within_um": self.holds.1,
            "pairs": self.pairs,
        })
    }

    /// A few lines for the terminal.
    pub fn summary(&self) -> String {
        let u = &self.uncertainty;
        let [lo, hi] = self.disparity_range();
        let pupil = |[d, s]: [f64; 2]| {
            if d.is_finite() && d < 1e8 {
                format!("{:.0} mm (1/d ± {:.1e}/µm)", d / 1000.0, s)
            } else {
                format!("telecentric (1/d ± {s:.1e}/µm)")
            }
        };
        let used = self.pairs.iter().filter(|p| p.not_used.is_none()).count();
        let field = match self.rig.field {
            Some(f) => format!(
                "\nthe board covered x {:.0}–{:.0}, y {:.0}–{:.0} px of the {}×{} rectified frame ({:.0} %): cells outside it are measured but not trusted (move the board across the field, or use a larger one, to widen it)",
                f[0],
                f[2],
                f[1],
                f[3],
                self.rig.width,
                self.rig.height,
                100.0 * (f[2] - f[0]).max(0.0) * (f[3] - f[1]).max(0.0)
                    / (self.rig.width * self.rig.height) as f64
            ),
            None => String::new(),
        };
        format!(
            "{used} of {} pairs used, stage {} to {} µm{}\nreprojection error {:.3} px left, {:.3} px right\nscale {:.4} ± {:.4} and {:.4} ± {:.4} µm/px; views {:.2} ± {:.2}° and {:.2} ± {:.2}° off the stage normal\npupils: {}, {}\ndepth: {:.5} ± {:.5} px of disparity per µm of height ({:.3} %)\nrectified rows agree within {:.3} px, heights within {:.3} µm over the field\ndisparity range for the stack's depth and half again: {:.0} to {:.0} px{field}",
            self.pairs.len(),
            self.span[0],
            self.span[1],
            if self.turned {
                " (heights.csv's heights grow away from the cameras: turned round)"
            } else {
                ""
            },
            self.fits[0].rms,
            self.fits[1].rms,
            u.scale[0][0],
            u.scale[0][1],
            u.scale[1][0],
            u.scale[1][1],
            u.angle_deg[0][0],
            u.angle_deg[0][1],
            u.angle_deg[1][0],
            u.angle_deg[1][1],
            pupil(u.pupil[0]),
            pupil(u.pupil[1]),
            u.px_per_um[0],
            u.px_per_um[1],
            100.0 * u.px_per_um[1] / u.px_per_um[0].abs(),
            self.holds.0,
            self.holds.1,
            lo.floor(),
            hi.ceil()
        )
    }
}

/// A held-out pair measured through a calibration.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Checked {
    /// The pair's name.
    pub name: String,
    /// Its stage height, µm.
    pub z: f64,
    /// The target's disparity at the view's centre, rectified (px).
    pub disparity: Option<f64>,
    /// The height measured from it, µm (in `heights.csv`'s sense).
    pub measured: Option<f64>,
}

impl StageFit {
    /// Measures the stage height of each of `pairs` (a flat textured target filling the
    /// views' middle) through the calibration: each view rectified onto the stage plane by
    /// `rectify(view, right)` (the rectifier's tables of [`StageFit::rig`]), the target's
    /// disparity fitted to the images ([`crate::target::target_disparity`]), triangulated.
    pub fn check(
        &self,
        pairs: &[StagePair],
        rectify: &dyn Fn(&Plane<u8>, bool) -> Plane<u8>,
    ) -> Vec<Checked> {
        let [lo, hi] = self.disparity_range();
        let c = self.rig.calibration();
        let sign = if self.turned { -1.0 } else { 1.0 };
        let size = (self.rig.width, self.rig.height);
        pairs
            .iter()
            .map(|p| {
                let same = (p.left.width, p.left.height) == size
                    && (p.right.width, p.right.height) == size;
                let d = same
                    .then(|| {
                        crate::target::target_disparity(
                            &rectify(&p.left, false),
                            &rectify(&p.right, true),
                            lo.floor() as i32 - 2,
                            hi.ceil() as i32 + 2,
                        )
                    })
                    .flatten();
                let measured = d.map(|d| {
                    let z = c.baseline * c.focal_px / (d + c.cx_right - c.cx);
                    sign * (self.rig.z_ref + c.focal_px * self.rig.scale - z)
                });
                Checked {
                    name: p.name.clone(),
                    z: p.z,
                    disparity: d,
                    measured,
                }
            })
            .collect()
    }
}

/// The held-out pairs as lines: each height measured against the stage's, then each step
/// between pairs in order of height.
pub fn check_lines(checked: &[Checked]) -> Vec<String> {
    let mut lines: Vec<String> = checked
        .iter()
        .map(|c| match c.measured {
            Some(m) => format!(
                "held out {} (stage {} µm): measured {m:.3} µm ({:+.3} µm)",
                c.name,
                c.z,
                m - c.z
            ),
            None => format!("held out {} (stage {} µm): no target found", c.name, c.z),
        })
        .collect();
    let mut by_z: Vec<(f64, f64)> = checked
        .iter()
        .filter_map(|c| c.measured.map(|m| (c.z, m)))
        .collect();
    by_z.sort_by(|a, b| a.0.total_cmp(&b.0));
    for w in by_z.windows(2) {
        let (stage, measured) = (w[1].0 - w[0].0, w[1].1 - w[0].1);
        if stage != 0.0 {
            lines.push(format!(
                "step {} → {} µm: measured {measured:.3} µm ({:+.2} %)",
                w[0].0,
                w[1].0,
                100.0 * (measured / stage - 1.0)
            ));
        }
    }
    lines
}
