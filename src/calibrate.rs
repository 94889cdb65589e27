//! `microstereo calibrate-depth`: the microscope's b·f_eff and disparity offset from a
//! z-stack — each pair through the stereo graph, the target's disparity fitted against its
//! stage height (`calibration::file::fit_depth`).

use crate::error::CliError;
use clap::Args;
use schemas::{Calibration, DisparityRange, LengthUnit};
use std::path::{Path, PathBuf};

/// Arguments of `microstereo calibrate-depth`.
#[derive(Args, Debug)]
pub struct CalibrateArgs {
    /// Directory with the pairs and `heights.csv` (columns left,right,z_um), or pairs named
    /// `left_z<Z>.png` / `right_z<Z>.png` with Z in µm.
    pub dir: PathBuf,
    /// Stereo baseline, µm (splits b·f into f).
    #[arg(long)]
    pub baseline: f64,
    /// Sensor pixel pitch, µm: also reports f_eff = f · pitch.
    #[arg(long)]
    pub pixel_pitch: Option<f64>,
    /// Depth of the target at stage height 0, µm; fitted when not given.
    #[arg(long)]
    pub working_distance: Option<f64>,
    /// Smallest disparity searched.
    #[arg(long, default_value_t = -64, allow_hyphen_values = true)]
    pub min_disparity: i32,
    /// Largest disparity searched.
    #[arg(long, default_value_t = 64, allow_hyphen_values = true)]
    pub max_disparity: i32,
    /// Calibration file to write (default DIR/calibration-fitted.toml; never one of the
    /// stack's own files).
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// Write the fit into this existing calibration file instead: its geometry is replaced
    /// and its `[stereo]` cameras (from `calibrate-stereo`) kept, in µm.
    #[arg(long, conflicts_with_all = ["output", "overwrite"])]
    pub into: Option<PathBuf>,
    /// Replace the output file if it exists.
    #[arg(long)]
    pub overwrite: bool,
}

/// Refuses an output that is one of the stack's inputs (its images, its `heights.csv`, or
/// the scene's own `calibration.toml`), or that exists without `overwrite`; before any work.
fn check_output(
    out: &Path,
    dir: &Path,
    stack: &[(PathBuf, PathBuf, f64)],
    overwrite: bool,
) -> Result<(), CliError> {
    let inputs: Vec<PathBuf> = stack
        .iter()
        .flat_map(|(l, r, _)| [l.clone(), r.clone()])
        .chain([dir.join("heights.csv"), dir.join("calibration.toml")])
        .collect();
    let inputs: Vec<&Path> = inputs.iter().map(PathBuf::as_path).collect();
    formats::outputs::check(
        &[out.to_path_buf()],
        &inputs,
        overwrite,
        "give -o another file",
    )?;
    Ok(())
}

/// Runs `microstereo calibrate-depth`.
pub fn calibrate_depth(a: CalibrateArgs) -> Result<(), CliError> {
    // Every length in µm, within what optics have (a NaN is inside no range).
    let lengths = [
        ("--baseline", Some(a.baseline), 0.1, 1e7),
        ("--pixel-pitch", a.pixel_pitch, 0.01, 1000.0),
        ("--working-distance", a.working_distance, -1e7, 1e7),
    ];
    for (flag, v, lo, hi) in lengths {
        if let Some(v) = v
            && !(lo..=hi).contains(&v)
        {
            return Err(CliError::Other(format!(
                "{flag} {v} is out of range: use {lo}..{hi} (µm)"
            )));
        }
    }
    let stack = calibration::stack::read_stack(&a.dir).map_err(CliError::Other)?;
    let out = a
        .into
        .clone()
        .or_else(|| a.output.clone())
        .unwrap_or_else(|| a.dir.join("calibration-fitted.toml"));
    // `--into` replaces the file it names, by request; it is read first, and checked
    // against the stack like any output.
    let into = match &a.into {
        Some(p) => Some(calibration::file::read_file(p).map_err(CliError::Other)?),
        None => None,
    };
    check_output(&out, &a.dir, &stack, a.overwrite || into.is_some())?;
    let mut zs: Vec<f64> = stack.iter().map(|s| s.2).collect();
    zs.sort_by(|a, b| a.total_cmp(b));
    zs.dedup();
    if zs.len() < 3 {
        return Err(CliError::Other(format!(
            "the z-stack in '{}' has {} distinct heights; the fit needs at least 3 (give pairs at three or more stage heights)",
            a.dir.display(),
            zs.len()
        )));
    }
    if let Some(w) = a.working_distance
        && (w.is_nan() || w <= zs[zs.len() - 1])
    {
        return Err(CliError::Other(format!(
            "--working-distance {w} must exceed the highest stage height {}",
            zs[zs.len() - 1]
        )));
    }
    let range = DisparityRange::new(a.min_disparity, a.max_disparity);
    let mut z = Vec::new();
    let mut d = Vec::new();
    let mut size = None;
    for (l, r, zi) in &stack {
        let (di, dims) = pipelines::stereo::target_disparity(l, r, range).map_err(|e| {
            CliError::with_flags(
                e,
                &[
                    ("min_disparity", "--min-disparity"),
                    ("max_disparity", "--max-disparity"),
                ],
            )
        })?;
        size.get_or_insert(dims);
        z.push(*zi);
        d.push(di);
    }
    let fit = calibration::file::fit_depth(&z, &d, a.working_distance);
    fit.check(&z, a.working_distance.is_none())?;
    let (w, h) = size.unwrap_or((0, 0));
    let f_px = fit.b_f / a.baseline;
    let cx = (w as f64 - 1.0) / 2.0;
    let cal = Calibration {
        baseline: a.baseline,
        focal_px: f_px,
        cx,
        cy: (h as f64 - 1.0) / 2.0,
        cx_right: cx + fit.offset,
        unit: LengthUnit::Um,
    };
    match into {
        Some(old) => {
            // The cameras' translation follows the file into µm.
            let scale = old
                .unit
                .map_or(1.0, |u| u.metres() / LengthUnit::Um.metres());
            let stereo = old.stereo.map(|mut t| {
                t.t = t.t.map(|v| v * scale);
                t
            });
            let file = calibration::file::CalibrationFile {
                stereo,
                ..calibration::file::CalibrationFile::from_calibration(
                    &cal,
                    a.pixel_pitch.unwrap_or(1.0),
                )
            };
            calibration::file::write_file(
                &out,
                &file,
                &format!("Geometry fitted by microstereo calibrate-depth from the z-stack in '{}'; [stereo] kept.", a.dir.display()),
            )
            .map_err(CliError::Other)?;
        }
        None => calibration::file::write(&out, &cal, a.pixel_pitch.unwrap_or(1.0))?,
    }
    runtime::outln!("{:>10} {:>12} {:>12}", "z (µm)", "d (px)", "resid (px)");
    for ((zi, di), ri) in z.iter().zip(&d).zip(&fit.residuals) {
        runtime::outln!("{zi:>10.2} {di:>12.3} {ri:>12.4}");
    }
    let rms = (fit.residuals.iter().map(|r| r * r).sum::<f64>() / z.len() as f64).sqrt();
    runtime::outln!(
        "b·f = {:.1} µm·px, f = {:.2} px{}, disparity offset {:.3} px, working distance {:.1} µm ({}); rms residual {:.4} px",
        fit.b_f,
        f_px,
        a.pixel_pitch
            .map(|p| format!(" (f_eff = {:.1} µm)", f_px * p))
            .unwrap_or_default(),
        fit.offset,
        fit.working_distance,
        if a.working_distance.is_some() {
            "given"
        } else {
            "fitted"
        },
        rms
    );
    runtime::outln!("calibration written to {}", out.display());
    Ok(())
}

/// Arguments of `microstereo calibrate-microscope`.
#[derive(Args, Debug)]
pub struct CalibrateMicroscopeArgs {
    /// Directory with the chessboard's pairs at known stage heights and `heights.csv`
    /// (left,right,z_um; z towards the cameras).
    pub dir: PathBuf,
    /// Inner corners of the board, along a row × down a column (e.g. 9x6).
    #[arg(long, value_parser = crate::calibstereo::parse_inner)]
    pub inner: (usize, usize),
    /// Side of a square, µm.
    #[arg(long)]
    pub square: f64,
    /// Output directory: calibration.toml and report.json.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Replace earlier outputs.
    #[arg(long)]
    pub overwrite: bool,
    /// A held-out stack (heights.csv) of a flat textured target to measure through the
    /// calibration: each pair's height and each step, measured against the stage's.
    #[arg(long)]
    pub check: Option<PathBuf>,
}

/// Runs `microstereo calibrate-microscope`.
pub fn calibrate_microscope(a: CalibrateMicroscopeArgs) -> Result<(), CliError> {
    let (fit, checked) = pipelines::microscope::calibrate_microscope(
        &a.dir,
        &a.output,
        a.inner,
        a.square,
        a.overwrite,
        a.check.as_deref(),
    )?;
    for line in pipelines::microscope::lines(&fit, &checked, &a.output) {
        runtime::outln!("{line}");
    }
    Ok(())
}
