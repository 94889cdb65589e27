//! `microstereo calibrate-manipulator`: the manipulator registered to the cameras. The
//! device is moved through a grid of stops around where the tip stands; at each the tip
//! is found in both views (the `registration` crate) and triangulated; the map
//! `device = M·scene + offset` (rotation, each axis's scale and sign, offset) is fitted by
//! least squares, each stop's residual reported, a fit whose residuals are too large
//! refused, and the registration written where the bridge reads it (its `registration`
//! parameter). `--offset-only` re-registers after a pipette change from one stop.

use crate::error::CliError;
use clap::Args;
use manipulator_bridge::registration::Registration;
use registration::session::{Grab, Plan, Rig, sim_start};
use std::path::{Path, PathBuf};

/// Arguments of `microstereo calibrate-manipulator`.
#[derive(Args, Debug)]
pub struct CalibrateManipulatorArgs {
    /// `sim` (a simulated manipulator seen by the synthetic microscope), `mp285` or
    /// `scientifica`.
    #[arg(long, default_value = "sim")]
    pub device: String,
    /// Serial port of an MP-285.
    #[arg(long)]
    pub port: Option<String>,
    /// The cameras' calibration file (with `[stereo]`, frames are rectified first); the
    /// synthetic microscope's own for `sim` when not given.
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// Left and right V4L2 cameras (with a real device; build with `--features v4l`).
    #[arg(long, num_args = 2, value_names = ["LEFT", "RIGHT"])]
    pub cameras: Option<Vec<String>>,
    /// Stops along the device's x, y and z axes, e.g. 3x3x2.
    #[arg(long, default_value = "3x3x2")]
    pub grid: String,
    /// Half the travel on each device axis, µm: the tip must stand this far clear of
    /// everything below it.
    #[arg(long, value_delimiter = ',', default_value = "40,40,20")]
    pub span: Vec<f64>,
    /// Device speed between stops, µm/s.
    #[arg(long, default_value_t = 200.0)]
    pub speed: f64,
    /// Largest rms residual accepted, µm.
    #[arg(long, default_value_t = 3.0)]
    pub max_rms: f64,
    /// Re-register after a pipette change: one stop where the tip stands, the axes of
    /// this earlier registration kept, only the offset fitted.
    #[arg(long)]
    pub offset_only: Option<PathBuf>,
    /// The simulated manipulator's mounting (what the fit must find): rotation about the
    /// vertical in degrees, the scales of its x, y and z (negative: a flipped axis), and
    /// its offset x, y, z in µm.
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        default_value = "30,1.1,-1,0.9,1200,-300,5000"
    )]
    pub sim_mount: Vec<f64>,
    /// Where the simulated tip starts, camera frame `[X, Y, Z]` µm (60 µm above the synthetic
    /// substrate by default).
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        default_value = "-60,20,3940"
    )]
    pub sim_start: Vec<f64>,
    /// Seed of the synthetic scene's cells.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// The registration file to write (the bridge's `registration` parameter).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Replace the output if it exists.
    #[arg(long)]
    pub overwrite: bool,
}

/// Runs `calibrate-manipulator`.
pub fn calibrate_manipulator(a: CalibrateManipulatorArgs) -> Result<(), CliError> {
    let plan = Plan::new(&a.grid, &a.span, a.speed, a.max_rms)?;
    let start = sim_start(&a.sim_start)?;
    // The registration is written after minutes of moves: a folder that is not there is
    // said before the first.
    if let Some(parent) = a.output.parent().filter(|p| !p.as_os_str().is_empty())
        && !parent.is_dir()
    {
        return Err(CliError::Other(format!(
            "the output's folder '{}' does not exist: create it or give -o another file",
            parent.display()
        )));
    }
    let earlier = a
        .offset_only
        .as_ref()
        .map(|p| Registration::read(&p.display().to_string()))
        .transpose()?;
    let inputs: Vec<&Path> = a
        .calibration
        .iter()
        .chain(a.offset_only.iter())
        .map(PathBuf::as_path)
        .collect();
    formats::outputs::check(
        std::slice::from_ref(&a.output),
        &inputs,
        a.overwrite,
        "give -o another file",
    )?;
    let mut rig = match a.device.as_str() {
        "sim" => Rig::sim(
            a.seed,
            &a.sim_mount,
            start,
            a.speed,
            a.calibration.as_deref(),
        )?,
        d @ ("mp285" | "scientifica") => Rig::real(
            d,
            a.port.as_deref(),
            a.calibration.as_deref(),
            a.cameras.as_deref(),
            cameras,
        )?,
        d => {
            return Err(CliError::Other(format!(
                "unknown --device '{d}'; devices: sim, mp285, scientifica"
            )));
        }
    };
    let fitted = match &earlier {
        Some(reg) => {
            let f = rig.register_offset(reg)?;
            runtime::outln!(
                "offset re-registered at device {:?}: tip at scene {:?}; offset {:?} (was {:?})",
                f.stops[0].device,
                f.stops[0].scene.expect("found"),
                f.registration.offset,
                reg.offset
            );
            f
        }
        None => rig.register(&plan)?,
    };
    for line in fitted.stop_lines() {
        runtime::outln!("{line}");
    }
    if let Some(why) = fitted.refuse(plan.max_rms) {
        return Err(CliError::Other(why));
    }
    runtime::outln!("{}", fitted.summary());
    formats::atomic::write_bytes(&a.output, fitted.to_toml(&a.output).as_bytes())?;
    runtime::outln!("registration written to {}", a.output.display());
    Ok(())
}

#[cfg(feature = "v4l")]
fn cameras(c: &[String]) -> Result<(Grab, (usize, usize)), String> {
    let p = capture::camera::CameraParams {
        source: "camera".into(),
        left: c[0].clone(),
        right: c[1].clone(),
        width: 1280,
        height: 1024,
        max_skew_ms: 20.0,
        fps: None,
    };
    let mut cam = capture::camera::CameraCapture::new(&p)?;
    let first = cam.next_frame()?;
    let size = (first.left.width, first.left.height);
    Ok((Box::new(move |_| cam.next_frame()), size))
}

#[cfg(not(feature = "v4l"))]
fn cameras(_: &[String]) -> Result<(Grab, (usize, usize)), String> {
    Err("cameras need a build with --features v4l".into())
}
