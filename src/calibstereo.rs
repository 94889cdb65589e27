//! `microstereo calibrate-stereo`: both cameras and their relative pose from chessboard
//! pairs, written as the one calibration file that `rectify`, `triangulate`,
//! `reconstruct` and the graph read (its `[stereo]` table the raw cameras, its top level
//! the rectified geometry).

use crate::error::CliError;
use calibration::pairs::{BoardPairs, find_pairs};
use clap::Args;
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
    pub unit: schemas::LengthUnit,
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

pub(crate) fn parse_inner(s: &str) -> Result<(usize, usize), String> {
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
    let list = find_pairs(&a.dir, &a.left_prefix, &a.right_prefix)?;
    let outputs = [
        a.output.join("calibration.toml"),
        a.output.join("report.json"),
    ];
    let pngs: Vec<PathBuf> = list
        .iter()
        .map(|p| a.output.join("corners").join(format!("{}.png", p.name)))
        .collect();
    let inputs: Vec<&Path> = list
        .iter()
        .flat_map(|p| [p.left.as_path(), p.right.as_path()])
        .collect();
    let all: Vec<PathBuf> = outputs.iter().chain(&pngs).cloned().collect();
    formats::outputs::check(&all, &inputs, a.overwrite, "give -o another directory")?;

    let mut boards = BoardPairs::new(a.inner.0, a.inner.1);
    for p in &list {
        let l = capture::image::load(&p.left, "left image")?;
        let r = capture::image::load(&p.right, "right image")?;
        boards.add(&p.name, l.grey, r.grey)?;
    }
    let fit = boards.calibrate(a.square, a.max_pair_rms, |note| runtime::errln!("{note}"))?;
    let corners = a.output.join("corners");
    std::fs::create_dir_all(&corners)
        .map_err(|e| CliError::Other(format!("cannot create '{}': {e}", corners.display())))?;
    for (p, png) in fit.pairs.iter().zip(&pngs) {
        formats::write_color_png(png, &p.drawing())?;
    }
    let unit = a.unit;
    calibration::file::write_file(&outputs[0], &fit.file(unit), &fit.comment(&a.dir, unit))?;
    let report = serde_json::to_string_pretty(&fit.report(unit)).expect("json");
    formats::atomic::write_bytes(&outputs[1], report.as_bytes())?;
    for p in &fit.pairs {
        if let Some(r) = p.rms {
            runtime::outln!("pair {}: RMS {r:.3} px", p.name);
        }
    }
    runtime::outln!("{}", fit.summary(unit));
    runtime::outln!("calibration written to {}", outputs[0].display());
    Ok(())
}
