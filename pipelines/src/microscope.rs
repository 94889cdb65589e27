//! `calibrate-microscope`: a stereo microscope calibrated from a chessboard at known stage
//! heights (a folder with `heights.csv`), written as the calibration file the rectifier,
//! the triangulate node and `reconstruct` read, with its report.

use calibration::stage::{Checked, StageFit, StagePair, calibrate_stage};
use calibration::stereo::Rectifier;
use std::path::{Path, PathBuf};

/// The files `calibrate-microscope` writes into `out`.
pub fn outputs(out: &Path) -> [PathBuf; 2] {
    [out.join("calibration.toml"), out.join("report.json")]
}

/// The stack of pairs listed in `dir`'s `heights.csv`, loaded.
fn load_stack(dir: &Path) -> Result<Vec<StagePair>, String> {
    calibration::stack::read_stack(dir)?
        .iter()
        .map(|(l, r, z)| {
            Ok(StagePair {
                name: l
                    .file_name()
                    .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
                left: capture::image::load(l, "left image")?.grey,
                right: capture::image::load(r, "right image")?.grey,
                z: *z,
            })
        })
        .collect()
}

/// Calibrates the microscope from the stack in `dir` (a board of `inner` corners, squares
/// `square` µm) and writes [`outputs`] into `out` (replacing them only with `overwrite`);
/// nothing is written when the calibration is refused. With `check`, a held-out stack of
/// a flat textured target is measured through the calibration (in the report and
/// returned).
pub fn calibrate_microscope(
    dir: &Path,
    out: &Path,
    inner: (usize, usize),
    square: f64,
    overwrite: bool,
    check: Option<&Path>,
) -> Result<(StageFit, Vec<Checked>), String> {
    if !(square > 0.0 && square <= 1e5) {
        return Err(format!(
            "--square {square} must be the board's square side in µm (0..1e5)"
        ));
    }
    let stack = calibration::stack::read_stack(dir)?;
    let files = outputs(out);
    let inputs: Vec<&Path> = stack
        .iter()
        .flat_map(|(l, r, _)| [l.as_path(), r.as_path()])
        .collect();
    formats::outputs::check(&files, &inputs, overwrite, "give -o another directory")
        .map_err(|e| e.to_string())?;
    let held_out = check.map(load_stack).transpose()?;
    let pairs = load_stack(dir)?;
    let fit = calibrate_stage(&pairs, inner.0, inner.1, square).map_err(|e| {
        format!(
            "calibration of the stack in '{}' refused: {e}",
            dir.display()
        )
    })?;
    let checked = held_out
        .map(|h| {
            let (l, r) = rectify::luts(&Rectifier::Microscope(fit.rig.clone()));
            fit.check(&h, &|img, right| {
                if right { r.apply(img) } else { l.apply(img) }
            })
        })
        .unwrap_or_default();
    std::fs::create_dir_all(out).map_err(|e| format!("cannot create '{}': {e}", out.display()))?;
    let [lo, hi] = fit.disparity_range();
    calibration::file::write_file(
        &files[0],
        &fit.file(),
        &format!(
            "Microscope calibrated by microstereo calibrate-microscope from the stage stack in '{}'.\n# Top level: the rectified views' parallel-axis geometry (triangulate); [microscope]: the views and their rectification onto the stage plane (rectify).\n# Disparity range for the stack's depth and half again: {:.0} to {:.0} px.",
            dir.display(),
            lo.floor(),
            hi.ceil()
        ),
    )?;
    let mut report = fit.report();
    if check.is_some() {
        report["check"] = serde_json::json!(checked);
    }
    let report = serde_json::to_string_pretty(&report).expect("json");
    formats::atomic::write_bytes(&files[1], report.as_bytes()).map_err(|e| e.to_string())?;
    Ok((fit, checked))
}

/// What `calibrate-microscope` tells its user: each pair's use, the summary, the held-out
/// pairs measured, and where the files are (`out`).
pub fn lines(fit: &StageFit, checked: &[Checked], out: &Path) -> Vec<String> {
    let mut lines: Vec<String> = fit
        .pairs
        .iter()
        .filter_map(|p| match (&p.not_used, p.rms) {
            (Some(why), _) => Some(format!("pair {} (z {} µm): not used: {why}", p.name, p.z)),
            (None, Some([l, r])) => Some(format!(
                "pair {} (z {} µm): RMS {l:.3} / {r:.3} px",
                p.name, p.z
            )),
            _ => None,
        })
        .collect();
    lines.push(fit.summary());
    lines.extend(calibration::stage::check_lines(checked));
    let [cal, report] = outputs(out);
    lines.push(format!(
        "calibration written to {} (report {})",
        cal.display(),
        report.display()
    ));
    lines
}
