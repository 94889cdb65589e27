//! `microstereo calibration import|export`: the calibration file to and from OpenCV's
//! stereo YAML (`stereoCalibrate`'s K1, D1, K2, D2, R, T) and a pair of ROS
//! `camera_info` files.
//!
//! Imported cameras are rectified the way microstereo rectifies (Bouguet, one focal
//! length `min(fy1, fy2)`, the mean principal point, no scaling), so the file's top level
//! is that rectification's geometry, not the P1/P2 another tool may have chosen; exports
//! write the same rectification (R1, R2, P1, P2) for others to use.

use crate::error::CliError;
use calibration::file::{CalibrationFile, LAYOUT, read_file, write_file};
use calibration::stereo::{Rectification, StereoCalibration};
use clap::{Args, Subcommand};
use std::path::{Path, PathBuf};

/// Arguments of `microstereo calibration`.
#[derive(Args, Debug)]
pub struct CalibrationArgs {
    #[command(subcommand)]
    command: CalibrationCommand,
}

#[derive(Subcommand, Debug)]
enum CalibrationCommand {
    /// Writes a calibration file from OpenCV's stereo YAML or two ROS camera_info files.
    Import(ImportArgs),
    /// Writes a calibration file's cameras as OpenCV's stereo YAML and/or two ROS camera_info files.
    Export(ExportArgs),
}

/// Arguments of `calibration import`.
#[derive(Args, Debug)]
struct ImportArgs {
    /// OpenCV FileStorage YAML with K1, D1, K2, D2, R, T, image_width, image_height.
    #[arg(
        long,
        conflicts_with = "camera_info",
        required_unless_present = "camera_info"
    )]
    opencv: Option<PathBuf>,
    /// Left and right ROS camera_info YAML (camera_matrix, distortion_coefficients,
    /// rectification_matrix, projection_matrix).
    #[arg(long, num_args = 2, value_names = ["LEFT", "RIGHT"])]
    camera_info: Option<Vec<PathBuf>>,
    /// Unit to write the file in: OpenCV's T is in the board's square unit (give that);
    /// camera_info's Tx is in metres and is converted.
    #[arg(long, value_enum)]
    unit: schemas::LengthUnit,
    /// The calibration file to write.
    #[arg(short, long)]
    output: PathBuf,
    /// Replace the output if it exists.
    #[arg(long)]
    overwrite: bool,
}

/// Arguments of `calibration export`.
#[derive(Args, Debug)]
struct ExportArgs {
    /// A calibration file with a `[stereo]` table (from `calibrate-stereo` or `import`).
    file: PathBuf,
    /// Write OpenCV's stereo YAML here.
    #[arg(long, required_unless_present = "camera_info")]
    opencv: Option<PathBuf>,
    /// Write the left and right ROS camera_info here.
    #[arg(long, num_args = 2, value_names = ["LEFT", "RIGHT"])]
    camera_info: Option<Vec<PathBuf>>,
    /// Replace outputs that exist.
    #[arg(long)]
    overwrite: bool,
}

/// Runs `calibration import|export`.
pub fn calibration_cmd(a: CalibrationArgs) -> Result<(), CliError> {
    match a.command {
        CalibrationCommand::Import(a) => import(a),
        CalibrationCommand::Export(a) => export(a),
    }
}

fn read(p: &Path, what: &str) -> Result<String, CliError> {
    std::fs::read_to_string(p)
        .map_err(|e| CliError::Other(format!("{what} '{}' cannot be read: {e}", p.display())))
}

fn import(a: ImportArgs) -> Result<(), CliError> {
    let mut inputs: Vec<&Path> = Vec::new();
    let cal = if let Some(p) = &a.opencv {
        inputs.push(p);
        StereoCalibration::from_opencv_yaml(&read(p, "OpenCV calibration")?)
            .map_err(|e| CliError::Other(format!("OpenCV calibration '{}': {e}", p.display())))?
    } else {
        let ci = a.camera_info.as_ref().expect("clap requires one");
        inputs.extend(ci.iter().map(PathBuf::as_path));
        let mut cal = Rectification::from_camera_info(
            &read(&ci[0], "left camera_info")?,
            &read(&ci[1], "right camera_info")?,
        )?
        .calibration()
        .clone();
        // ROS gives the baseline in metres; the file holds it in --unit.
        cal.t /= a.unit.metres();
        cal
    };
    formats::outputs::check(
        std::slice::from_ref(&a.output),
        &inputs,
        a.overwrite,
        "give -o another file",
    )?;
    let file = CalibrationFile::imported(&cal, a.unit)?;
    let from: Vec<String> = inputs.iter().map(|p| p.display().to_string()).collect();
    let comment = format!(
        "Imported by microstereo calibration import from {}.\n{LAYOUT}",
        from.join(" and ")
    );
    write_file(&a.output, &file, &comment)?;
    runtime::outln!(
        "baseline {:.4} {}, rectified focal {:.2} px; written to {}",
        file.baseline,
        a.unit.symbol(),
        file.focal_px.unwrap_or(f64::NAN),
        a.output.display()
    );
    Ok(())
}

fn export(a: ExportArgs) -> Result<(), CliError> {
    let file = read_file(&a.file)?;
    let source = format!("'{}'", a.file.display());
    let cal = file.exported_cameras(&source)?;
    let mut outs: Vec<PathBuf> = a.opencv.iter().cloned().collect();
    outs.extend(a.camera_info.iter().flatten().cloned());
    formats::outputs::check(
        &outs,
        &[a.file.as_path()],
        a.overwrite,
        "give other output paths",
    )?;
    let rect = Rectification::bouguet(&cal);
    let metres = a
        .camera_info
        .as_ref()
        .map(|_| file.metres(&source))
        .transpose()?;
    let infos = metres.map(|m| rect.to_camera_info(m));
    if let Some(p) = &a.opencv {
        formats::atomic::write_bytes(p, rect.to_opencv_yaml().as_bytes())?;
        runtime::outln!("OpenCV stereo YAML written to {}", p.display());
    }
    if let (Some(ci), Some(infos)) = (&a.camera_info, infos) {
        for ((path, side), text) in ci.iter().zip(["left", "right"]).zip(infos) {
            formats::atomic::write_bytes(path, text.as_bytes())?;
            runtime::outln!("{side} camera_info written to {}", path.display());
        }
    }
    Ok(())
}
