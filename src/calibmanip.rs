//! `microstereo calibrate-manipulator`: the manipulator registered to the cameras. The
//! device is moved through a grid of stops around where the tip stands; at each the tip
//! is found in both views (the `registration` crate) and triangulated; the map
//! `device = M·scene + offset` (rotation, each axis's scale and sign, offset) is fitted by
//! least squares, each stop's residual reported, a fit whose residuals are too large
//! refused, and the registration written where the bridge reads it (its `registration`
//! parameter). `--offset-only` re-registers after a pipette change from one stop.

use crate::error::CliError;
use clap::Args;
use manipulator_bridge::device::{Device, SimDevice, wall_clock};
use manipulator_bridge::geom::P3;
use manipulator_bridge::registration::Registration;
use registration::{
    Fitted, Optics, SimMicroscope, Stop, grid_stops, mount, register, tip_in_scene,
};
use schemas::StereoFrame;
use std::path::{Path, PathBuf};
use std::time::Duration;

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

fn parse_grid(s: &str) -> Result<[usize; 3], String> {
    let v: Vec<usize> = s
        .split(['x', 'X'])
        .map(|p| p.trim().parse().unwrap_or(0))
        .collect();
    if v.len() != 3 || v.iter().any(|n| *n == 0 || *n > 10) || v.iter().product::<usize>() < 6 {
        return Err(format!(
            "--grid '{s}': give NXxNYxNZ stops (each 1..10, at least 6 in all, e.g. 3x3x2)"
        ));
    }
    Ok([v[0], v[1], v[2]])
}

/// Runs `calibrate-manipulator`.
pub fn calibrate_manipulator(a: CalibrateManipulatorArgs) -> Result<(), CliError> {
    let grid = parse_grid(&a.grid)?;
    if a.span.len() != 3
        || a.span
            .iter()
            .any(|v| !(v.is_finite() && *v > 0.0 && *v <= 5000.0))
    {
        return Err(CliError::Other(format!(
            "--span {:?}: give three half-travels in µm (0..5000)",
            a.span
        )));
    }
    if !(a.max_rms > 0.0 && a.max_rms <= 1000.0) {
        return Err(CliError::Other(format!(
            "--max-rms {} must be in 0..1000 µm",
            a.max_rms
        )));
    }
    // Manipulators travel at most centimetres a second.
    if !(a.speed > 0.0 && a.speed <= 1e5) {
        return Err(CliError::Other(format!(
            "--speed {} must be in 0..1e5 µm/s",
            a.speed
        )));
    }
    if a.sim_start.len() != 3 || a.sim_start.iter().any(|v| !v.is_finite() || v.abs() > 1e6) {
        return Err(CliError::Other(format!(
            "--sim-start {:?}: give X,Y,Z in µm (each within ±1e6)",
            a.sim_start
        )));
    }
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
    let geometry_of = |p: &Path, w: usize, h: usize| -> Result<Optics, CliError> {
        let file = calibration::file::read_file(p).map_err(CliError::Other)?;
        let source = format!("'{}'", p.display());
        let calibration = file.resolve(w, h, &source).map_err(CliError::Other)?;
        let rectify = file
            .cameras(&source)
            .map_err(CliError::Other)?
            .map(|cal| rectify::luts(&calibration::stereo::Rectification::bouguet(&cal)));
        Ok(Optics {
            rectify,
            calibration,
        })
    };
    let (mut device, mut grab, optics): (Box<dyn Device>, Grab, Optics) = match a.device.as_str() {
        "sim" => {
            let m = mount(&a.sim_mount)?;
            if a.sim_start.len() != 3 {
                return Err(CliError::Other("--sim-start takes X,Y,UP in µm".into()));
            }
            let start = [a.sim_start[0], a.sim_start[1], a.sim_start[2]];
            let mut micro = SimMicroscope::new(a.seed, m);
            let (w, h) = (micro.scene.optics.width, micro.scene.optics.height);
            let optics = match &a.calibration {
                Some(p) => geometry_of(p, w, h)?,
                None => Optics {
                    rectify: None,
                    calibration: micro.scene.optics.calibration(),
                },
            };
            let dev = SimDevice::new(m.to_device(start), 4.0 * a.speed, 20_000.0, wall_clock());
            (
                Box::new(dev),
                Box::new(move |at| Ok(micro.frame(at))),
                optics,
            )
        }
        d @ ("mp285" | "scientifica") => {
            let port = a
                .port
                .as_deref()
                .ok_or(format!("--device {d} needs --port (its serial port)"))?;
            let cal = a
                .calibration
                .as_ref()
                .ok_or("a real device needs the cameras' --calibration")?;
            let cams = a
                .cameras
                .clone()
                .ok_or("a real device needs --cameras LEFT RIGHT")?;
            let dev: Box<dyn Device> = if d == "mp285" {
                Box::new(
                    manipulator_bridge::mp285::Mp285::open(port, Duration::from_secs(2))
                        .map_err(|e| CliError::Other(e.0))?,
                )
            } else {
                Box::new(
                    manipulator_bridge::scientifica::Scientifica::open(
                        port,
                        Duration::from_secs(2),
                    )
                    .map_err(|e| CliError::Other(e.0))?,
                )
            };
            let (grab, (w, h)) = cameras(&cams)?;
            (dev, grab, geometry_of(cal, w, h)?)
        }
        d => {
            return Err(CliError::Other(format!(
                "unknown --device '{d}'; devices: sim, mp285, scientifica"
            )));
        }
    };
    let (registration, stops, rms) = if let Some(reg) = earlier {
        let at = device.state().map_err(|e| CliError::Other(e.0))?.position;
        let scene = grab(at)
            .and_then(|f| tip_in_scene(&f, &optics))
            .map_err(CliError::Other)?;
        let r = reg.with_offset_through(scene, at);
        runtime::outln!(
            "offset re-registered at device {at:?}: tip at scene {scene:?}; offset {:?} (was {:?})",
            r.offset,
            reg.offset
        );
        (
            r,
            vec![Stop {
                device: at,
                scene: Some(scene),
                why: None,
                residual: Some(0.0),
            }],
            0.0,
        )
    } else {
        let start = device.state().map_err(|e| CliError::Other(e.0))?.position;
        let stops = grid_stops(start, grid, [a.span[0], a.span[1], a.span[2]]);
        let f = register(device.as_mut(), &mut grab, &optics, &stops, a.speed)
            .map_err(CliError::Other)?;
        (f.registration, f.stops, f.rms)
    };
    let refusal = Fitted {
        registration,
        stops: stops.clone(),
        rms,
    }
    .refuse(a.max_rms);
    for (k, s) in stops.iter().enumerate() {
        match (&s.scene, s.residual, &s.why) {
            (Some(p), Some(r), _) => runtime::outln!(
                "stop {:>2}: device [{:.1}, {:.1}, {:.1}] -> tip [{:.2}, {:.2}, {:.2}] µm, residual {r:.3} µm",
                k + 1,
                s.device[0],
                s.device[1],
                s.device[2],
                p[0],
                p[1],
                p[2]
            ),
            (_, _, Some(why)) => runtime::outln!(
                "stop {:>2}: device [{:.1}, {:.1}, {:.1}]: {why}",
                k + 1,
                s.device[0],
                s.device[1],
                s.device[2]
            ),
            _ => {}
        }
    }
    if let Some(why) = refusal {
        return Err(CliError::Other(why));
    }
    let m = &registration.matrix;
    let det = m[0] * (m[4] * m[8] - m[5] * m[7]) - m[1] * (m[3] * m[8] - m[5] * m[6])
        + m[2] * (m[3] * m[7] - m[4] * m[6]);
    let svd = nalgebra::Matrix3::from_row_slice(m).svd(false, false);
    let scales = svd.singular_values;
    runtime::outln!(
        "registration: rms residual {rms:.3} µm over {} stops; axis scales {:.4} {:.4} {:.4}; {}; device = M·scene + offset with M rows [{:.4} {:.4} {:.4}] [{:.4} {:.4} {:.4}] [{:.4} {:.4} {:.4}]",
        stops.iter().filter(|s| s.residual.is_some()).count(),
        scales[0],
        scales[1],
        scales[2],
        if det < 0.0 {
            "one axis flipped (a left-handed device frame)"
        } else {
            "right-handed"
        },
        m[0],
        m[1],
        m[2],
        m[3],
        m[4],
        m[5],
        m[6],
        m[7],
        m[8]
    );
    let rows: Vec<String> = stops
        .iter()
        .map(|s| match (&s.scene, s.residual) {
            (Some(p), Some(r)) => format!(
                "{{ device = {:?}, scene = {:?}, residual_um = {r} }}",
                s.device, p
            ),
            _ => format!(
                "{{ device = {:?}, left_out = {:?} }}",
                s.device,
                s.why.clone().unwrap_or_default()
            ),
        })
        .collect();
    let text = format!(
        "# Written by microstereo calibrate-manipulator: device = matrix · [X, Y, Z] + offset (µm; matrix row by row;\n# [X, Y, Z]: the triangulation's camera frame, Z the depth). The bridge reads it: registration = \"{}\".\nmatrix = {:?}\noffset = {:?}\nrms_um = {rms}\nstops = [\n  {}\n]\n",
        a.output.display(),
        registration.matrix,
        registration.offset,
        rows.join(",\n  ")
    );
    formats::atomic::write_bytes(&a.output, text.as_bytes())
        .map_err(|e| CliError::Other(e.to_string()))?;
    runtime::outln!("registration written to {}", a.output.display());
    Ok(())
}

/// A source of frames, told where the device stands.
type Grab = Box<dyn FnMut(P3) -> Result<StereoFrame, String>>;

#[cfg(feature = "v4l")]
fn cameras(c: &[String]) -> Result<(Grab, (usize, usize)), CliError> {
    let p = capture::camera::CameraParams {
        source: "camera".into(),
        left: c[0].clone(),
        right: c[1].clone(),
        width: 1280,
        height: 1024,
        max_skew_ms: 20.0,
        fps: None,
    };
    let mut cam = capture::camera::CameraCapture::new(&p).map_err(CliError::Other)?;
    let first = cam.next_frame().map_err(CliError::Other)?;
    let size = (first.left.width, first.left.height);
    Ok((Box::new(move |_| cam.next_frame()), size))
}

#[cfg(not(feature = "v4l"))]
fn cameras(_: &[String]) -> Result<(Grab, (usize, usize)), CliError> {
    Err(CliError::Other(
        "cameras need a build with --features v4l".into(),
    ))
}
