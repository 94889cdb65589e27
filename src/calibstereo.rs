//! `microstereo calibrate-stereo`: both cameras and their relative pose from chessboard
//! pairs, written as the one calibration file that `rectify`, `triangulate`,
//! `reconstruct` and the graph read (its `[stereo]` table the raw cameras, its top level
//! the rectified geometry).

use crate::error::CliError;
use crate::reconstruct::UnitArg;
use calibration::board::{Board, find_board};
use calibration::calibrate::{Corners, Stereo, calibrate_stereo};
use clap::Args;
use image::{Rgb, RgbImage};
use imageproc::drawing::{draw_hollow_circle_mut, draw_line_segment_mut};
use std::path::{Path, PathBuf};

/// Arguments of `microstereo calibrate-stereo`.
#[derive(Args, Debug)]
pub struct CalibrateStereoArgs {
    /// Directory of the pairs: `left<NAME>` and `right<NAME>` images (PNG, JPEG or TIFF)
    /// with the same NAME, e.g. left01.jpg and right01.jpg.
    pub dir: PathBuf,
    /// Inner corners of the board, along a row × down a column (a board of 10×7 squares
    /// has 9x6).
    #[arg(long, value_parser = parse_inner)]
    pub inner: (usize, usize),
    /// Side of a square, in `--unit`.
    #[arg(long)]
    pub square: f64,
    /// Unit of `--square`, and so of the baseline and every length triangulated later.
    #[arg(long, value_enum)]
    pub unit: UnitArg,
    /// Output directory: calibration.toml, report.json and corners/<NAME>.png.
    #[arg(short, long)]
    pub output: PathBuf,
    /// A pair whose reprojection error (RMS, px) exceeds this is left out and the rest
    /// refitted (default: 3 times the pairs' median, at least 1 px).
    #[arg(long)]
    pub max_pair_rms: Option<f64>,
    /// Prefix of the left images.
    #[arg(long, default_value = "left")]
    pub left_prefix: String,
    /// Prefix of the right images.
    #[arg(long, default_value = "right")]
    pub right_prefix: String,
    /// Replace earlier outputs.
    #[arg(long)]
    pub overwrite: bool,
}

fn parse_inner(s: &str) -> Result<(usize, usize), String> {
    let bad = || format!("'{s}' is not COLSxROWS inner corners (e.g. 9x6, each at least 2)");
    let (c, r) = s.split_once(['x', 'X', '×']).ok_or_else(bad)?;
    let (c, r): (usize, usize) = (
        c.trim().parse().map_err(|_| bad())?,
        r.trim().parse().map_err(|_| bad())?,
    );
    if c < 2 || r < 2 || c * r > 10_000 {
        return Err(bad());
    }
    Ok((c, r))
}

/// The pairs in `dir`: (name, left path, right path), by name.
fn pairs(a: &CalibrateStereoArgs) -> Result<Vec<(String, PathBuf, PathBuf)>, CliError> {
    let entries = std::fs::read_dir(&a.dir).map_err(|e| {
        CliError::Other(format!(
            "cannot read the pairs' directory '{}': {e}",
            a.dir.display()
        ))
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
        if let Some(rest) = name.strip_prefix(&a.left_prefix)
            && image(&p)
        {
            let right = a.dir.join(format!("{}{rest}", a.right_prefix));
            if right.exists() {
                let stem = Path::new(rest)
                    .file_stem()
                    .and_then(|s| s.to_str())
                    .unwrap_or(rest);
                out.push((stem.to_string(), p.clone(), right));
            }
        }
    }
    out.sort();
    if out.is_empty() {
        return Err(CliError::Other(format!(
            "no image pairs in '{}': expected {}NAME and {}NAME files (PNG, JPEG or TIFF) with the same NAME; set --left-prefix/--right-prefix for other names",
            a.dir.display(),
            a.left_prefix,
            a.right_prefix
        )));
    }
    Ok(out)
}

/// One pair's outcome.
struct PairResult {
    name: String,
    boards: Result<(Board, Board), String>,
    rms: Option<f64>,
    left_out: Option<String>,
}

/// Runs `calibrate-stereo`.
pub fn calibrate_stereo_cmd(a: CalibrateStereoArgs) -> Result<(), CliError> {
    // Boards from a micrometre stage target to a metre poster, in any unit.
    if !(a.square > 0.0 && a.square <= 1e6) {
        return Err(CliError::Other(format!(
            "--square {} must be a positive length (at most 1e6 in its unit)",
            a.square
        )));
    }
    if let Some(m) = a.max_pair_rms
        && !(m > 0.0 && m <= 1000.0)
    {
        return Err(CliError::Other(format!(
            "--max-pair-rms {m} must be a number of pixels in 0..1000"
        )));
    }
    let list = pairs(&a)?;
    let outputs = [
        a.output.join("calibration.toml"),
        a.output.join("report.json"),
    ];
    let pngs: Vec<PathBuf> = list
        .iter()
        .map(|(n, ..)| a.output.join("corners").join(format!("{n}.png")))
        .collect();
    let inputs: Vec<&Path> = list
        .iter()
        .flat_map(|(_, l, r)| [l.as_path(), r.as_path()])
        .collect();
    let all: Vec<PathBuf> = outputs.iter().chain(&pngs).cloned().collect();
    formats::outputs::check(&all, &inputs, a.overwrite, "give -o another directory")?;

    let (cols, rows) = a.inner;
    let mut size = None;
    let mut results = Vec::new();
    let mut images = Vec::new();
    for (name, lp, rp) in &list {
        let l = capture::image::load(lp, "left image").map_err(CliError::Other)?;
        let r = capture::image::load(rp, "right image").map_err(CliError::Other)?;
        let s = (l.grey.width, l.grey.height);
        if (r.grey.width, r.grey.height) != s {
            return Err(CliError::Other(format!(
                "pair {name}: the left image is {}×{} but the right {}×{}; both cameras must give one size",
                s.0, s.1, r.grey.width, r.grey.height
            )));
        }
        if *size.get_or_insert(s) != s {
            let z = size.unwrap();
            return Err(CliError::Other(format!(
                "pair {name} is {}×{} but the first pair {}×{}: calibrate one image size at a time",
                s.0, s.1, z.0, z.1
            )));
        }
        let found =
            |img, side: &str| find_board(img, cols, rows).map_err(|e| format!("{side} view: {e}"));
        let boards = found(&l.grey, "left").and_then(|lb| {
            found(&r.grey, "right").map(|mut rb| {
                rb.align_to(&lb);
                (lb, rb)
            })
        });
        results.push(PairResult {
            name: name.clone(),
            boards,
            rms: None,
            left_out: None,
        });
        images.push((l.grey, r.grey));
    }
    let size = size.expect("at least one pair");
    let object: Vec<[f64; 2]> = (0..rows)
        .flat_map(|b| (0..cols).map(move |c| [c as f64 * a.square, b as f64 * a.square]))
        .collect();

    // Fit, leave out the worst pair while it fits badly, fit again.
    let fit = |results: &[PairResult]| -> Result<(Vec<usize>, Stereo), CliError> {
        let used: Vec<usize> = (0..results.len())
            .filter(|&i| results[i].boards.is_ok() && results[i].left_out.is_none())
            .collect();
        if used.len() < 3 {
            return Err(CliError::Other(format!(
                "{} usable pairs of {}; calibration needs at least 3 with the board seen whole in both views at different angles (see the reasons above)",
                used.len(),
                results.len()
            )));
        }
        let (l, r): (Vec<Corners>, Vec<Corners>) = used
            .iter()
            .map(|&i| {
                let (lb, rb) = results[i].boards.as_ref().expect("usable");
                (lb.corners.clone(), rb.corners.clone())
            })
            .unzip();
        let s = calibrate_stereo(&l, &r, &object, size).map_err(CliError::Other)?;
        Ok((used, s))
    };
    for p in &results {
        if let Err(e) = &p.boards {
            runtime::errln!("pair {}: {e}; left out", p.name);
        }
    }
    let (used, stereo) = loop {
        let (used, s) = fit(&results)?;
        let mut sorted = s.pair_rms.clone();
        sorted.sort_by(f64::total_cmp);
        let limit = a
            .max_pair_rms
            .unwrap_or((3.0 * sorted[sorted.len() / 2]).max(1.0));
        let (k, worst) = s
            .pair_rms
            .iter()
            .enumerate()
            .max_by(|x, y| x.1.total_cmp(y.1))
            .map(|(k, v)| (k, *v))
            .expect("pairs");
        if worst > limit && used.len() > 3 {
            let p = &mut results[used[k]];
            runtime::errln!(
                "pair {}: fits badly (RMS {worst:.3} px, limit {limit:.3}); left out, refitting",
                p.name
            );
            p.left_out = Some(format!("RMS {worst:.3} px over the limit {limit:.3} px"));
            continue;
        }
        for (k, &i) in used.iter().enumerate() {
            results[i].rms = Some(s.pair_rms[k]);
        }
        break (used, s);
    };

    let cal = stereo.calibration(size);
    let rect = calibration::stereo::Rectification::bouguet(&cal);
    // The rectification's own check: each board row's mean rectified row in both views.
    let boards: Vec<calibration::calibrate::PairView> = used
        .iter()
        .map(|&i| {
            let (lb, rb) = results[i].boards.as_ref().expect("used");
            (&lb.corners[..], &rb.corners[..])
        })
        .collect();
    let worst_row = calibration::calibrate::row_gap(&rect, &boards, cols);
    std::fs::create_dir_all(a.output.join("corners")).map_err(|e| {
        CliError::Other(format!(
            "cannot create '{}': {e}",
            a.output.join("corners").display()
        ))
    })?;
    for ((p, png), (l, r)) in results.iter().zip(&pngs).zip(&images) {
        let img = drawing(
            l,
            r,
            p.boards.as_ref().ok(),
            p.left_out.is_some() || p.boards.is_err(),
        );
        formats::write_color_png(png, &img)?;
    }
    let unit = a.unit.unit();
    let file = calibration::file::CalibrationFile::from_stereo(&cal, unit, Some(stereo.rms));
    calibration::file::write_file(
        &outputs[0],
        &file,
        &format!(
            "Written by microstereo calibrate-stereo from {} of {} pairs in '{}' ({cols}x{rows} inner corners, squares of {} {}): RMS {:.4} px.\n# Top level: the rectified views' geometry (triangulate); [stereo]: the raw cameras (rectify).",
            used.len(),
            results.len(),
            a.dir.display(),
            a.square,
            unit.symbol(),
            stereo.rms
        ),
    )
    .map_err(CliError::Other)?;
    let report = serde_json::json!({
        "pairs": results.iter().map(|p| serde_json::json!({
            "name": p.name,
            "used": p.rms.is_some(),
            "rms_px": p.rms,
            "left_out": p.left_out.clone().or_else(|| p.boards.as_ref().err().cloned()),
        })).collect::<Vec<_>>(),
        "rms_px": stereo.rms,
        "baseline": stereo.t.norm(),
        "unit": unit.symbol(),
        "left": stereo.left,
        "right": stereo.right,
        "rectified": {
            "focal_px": rect.f, "cx": rect.c[0], "cy": rect.c[1], "cx_right": rect.cx_right,
            "baseline": rect.baseline, "worst_board_row_px": worst_row,
        },
    });
    formats::atomic::write_bytes(
        &outputs[1],
        serde_json::to_string_pretty(&report)
            .expect("json")
            .as_bytes(),
    )
    .map_err(|e| CliError::Other(e.to_string()))?;
    for p in &results {
        if let Some(r) = p.rms {
            runtime::outln!("pair {}: RMS {r:.3} px", p.name);
        }
    }
    runtime::outln!(
        "{} of {} pairs used: RMS {:.4} px; baseline {:.3} {u}; left fx {:.1} fy {:.1} px, right fx {:.1} fy {:.1} px; rectified: focal {:.1} px, every board row within {worst_row:.3} px of one row",
        used.len(),
        results.len(),
        stereo.rms,
        stereo.t.norm(),
        stereo.left[0],
        stereo.left[1],
        stereo.right[0],
        stereo.right[1],
        rect.f,
        u = unit.symbol()
    );
    runtime::outln!("calibration written to {}", outputs[0].display());
    Ok(())
}

/// Both views side by side, each found corner ringed, rows joined (the first row red,
/// the rest green; grey when the pair was left out).
fn drawing(
    l: &schemas::Plane<u8>,
    r: &schemas::Plane<u8>,
    boards: Option<&(Board, Board)>,
    left_out: bool,
) -> RgbImage {
    let (w, h) = (l.width as u32, l.height as u32);
    let mut img = RgbImage::from_fn(2 * w, h, |x, y| {
        let v = if x < w {
            *l.get(x as usize, y as usize)
        } else {
            *r.get((x - w) as usize, y as usize)
        };
        Rgb([v, v, v])
    });
    if let Some((lb, rb)) = boards {
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
