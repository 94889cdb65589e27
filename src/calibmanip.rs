//! `microstereo calibrate-manipulator`: the manipulator registered to the cameras. The
//! device is moved through a grid of stops around where the tip stands; at each the tip
//! is found in both views ([`camera_calibration::pipette`]) and triangulated; the map
//! `device = M·scene + offset` (rotation, each axis's scale and sign, offset) is fitted by
//! least squares, each stop's residual reported, a fit whose residuals are too large
//! refused, and the registration written where the bridge reads it (its `registration`
//! parameter). `--offset-only` re-registers after a pipette change from one stop.

use crate::error::CliError;
use camera_calibration::pipette::find_tip;
use clap::Args;
use manipulator_bridge::device::{Device, SimDevice, wall_clock};
use manipulator_bridge::geom::P3;
use manipulator_bridge::registration::Registration;
use rectify::RemapLut;
use schemas::{Calibration, StereoFrame};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// What turns a frame into a tip in the scene: the rectification (for raw cameras) and the
/// rectified geometry.
pub struct Optics {
    /// Resampling tables of a raw pair, left and right (`None`: frames come rectified).
    pub rectify: Option<(RemapLut, RemapLut)>,
    /// The rectified views' geometry.
    pub calibration: Calibration,
}

/// The tip's front in the camera frame `[X, Y, Z]` µm (the bridge's), from one frame.
pub fn tip_in_scene(frame: &StereoFrame, optics: &Optics) -> Result<P3, String> {
    let (l, r) = match &optics.rectify {
        Some((ll, rl)) => (ll.apply(&frame.left), rl.apply(&frame.right)),
        None => (frame.left.clone(), frame.right.clone()),
    };
    let tl = find_tip(&l).map_err(|e| format!("left view: {e}"))?;
    let tr = find_tip(&r).map_err(|e| format!("right view: {e}"))?;
    let rows = (tl.front[1] - tr.front[1]).abs();
    if rows > 3.0 {
        return Err(format!(
            "the tips found lie {rows:.1} px apart across the rows (left at {:.1}, {:.1}; right at {:.1}, {:.1}): not one tip, or the views are not rectified",
            tl.front[0], tl.front[1], tr.front[0], tr.front[1]
        ));
    }
    let y = 0.5 * (tl.front[1] + tr.front[1]);
    let d = tl.front[0] - tr.front[0];
    let c = &optics.calibration;
    let p = triangulate::triangulate_pixel(tl.front[0], y, d, c)
        .ok_or_else(|| format!("the tips' disparity {d:.2} px puts the tip behind the cameras"))?;
    let um = c.unit.metres() / 1e-6;
    Ok([p[0] * um, p[1] * um, p[2] * um])
}

/// One stop of a registration.
#[derive(Clone, Debug, PartialEq)]
pub struct Stop {
    /// Where the device read it was, µm.
    pub device: P3,
    /// Where the tip was found in the scene, µm (`None`: not found, see `why`).
    pub scene: Option<P3>,
    /// Why the tip was not found.
    pub why: Option<String>,
    /// Distance between the fit's device position for the tip and the device's own, µm.
    pub residual: Option<f64>,
}

/// A fitted registration and its stops.
#[derive(Clone, Debug)]
pub struct Fitted {
    /// The map.
    pub registration: Registration,
    /// Every stop, in the order visited.
    pub stops: Vec<Stop>,
    /// Root mean square residual over the stops used, µm.
    pub rms: f64,
}

/// Moves `device` to `to` and waits until it stands (30 s at most).
fn settle(device: &mut dyn Device, to: P3, speed: f64) -> Result<P3, String> {
    device.start_move(to, speed).map_err(|e| e.0)?;
    let t0 = Instant::now();
    loop {
        let s = device.state().map_err(|e| e.0)?;
        if !s.moving {
            return Ok(s.position);
        }
        if t0.elapsed() > Duration::from_secs(30) {
            let _ = device.stop();
            return Err(format!("the device did not reach {to:?} within 30 s"));
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// The device positions of a `grid` (`[nx, ny, nz]`) of stops spanning `±span` around
/// `start` on the device's own axes.
pub fn grid_stops(start: P3, grid: [usize; 3], span: P3) -> Vec<P3> {
    let at = |k: usize, n: usize, s: f64| {
        if n < 2 {
            0.0
        } else {
            -s + 2.0 * s * k as f64 / (n - 1) as f64
        }
    };
    let mut v = Vec::new();
    for k in 0..grid[2] {
        for j in 0..grid[1] {
            for i in 0..grid[0] {
                v.push([
                    start[0] + at(i, grid[0], span[0]),
                    start[1] + at(j, grid[1], span[1]),
                    start[2] + at(k, grid[2], span[2]),
                ]);
            }
        }
    }
    v
}

/// Registers `device` to the scene: visits `stops` (device positions) at `speed`, finds
/// the tip in the frame `grab` gives at each (told where the device stands) and fits the
/// map; the device goes back to where it started. [`Fitted::refuse`] says whether the fit
/// is good enough.
pub fn register(
    device: &mut dyn Device,
    grab: &mut dyn FnMut(P3) -> Result<StereoFrame, String>,
    optics: &Optics,
    stops: &[P3],
    speed: f64,
) -> Result<Fitted, String> {
    let start = device.state().map_err(|e| e.0)?.position;
    let mut visited = Vec::new();
    for &to in stops {
        let at = settle(device, to, speed)?;
        let found = grab(at).and_then(|f| tip_in_scene(&f, optics));
        visited.push(match found {
            Ok(p) => Stop {
                device: at,
                scene: Some(p),
                why: None,
                residual: None,
            },
            Err(e) => Stop {
                device: at,
                scene: None,
                why: Some(e),
                residual: None,
            },
        });
    }
    settle(device, start, speed)?;
    let pairs: Vec<(P3, P3)> = visited
        .iter()
        .filter_map(|s| s.scene.map(|p| (p, s.device)))
        .collect();
    if pairs.len() < 6 {
        let why: Vec<String> = visited
            .iter()
            .filter_map(|s| s.why.clone())
            .take(3)
            .collect();
        return Err(format!(
            "the tip was found at {} of {} stops; the fit needs 6 ({})",
            pairs.len(),
            visited.len(),
            why.join("; ")
        ));
    }
    // A stop whose tip was found off the others' fit (a cell's edge beside it in one
    // view, say) is left out, the worst first, up to a quarter of them.
    let mut used: Vec<usize> = (0..visited.len())
        .filter(|&k| visited[k].scene.is_some())
        .collect();
    let fit_of = |visited: &[Stop], used: &[usize]| {
        let pairs: Vec<(P3, P3)> = used
            .iter()
            .map(|&k| (visited[k].scene.expect("found"), visited[k].device))
            .collect();
        Registration::fit(&pairs)
    };
    let (mut registration, mut residuals) = fit_of(&visited, &used)?;
    let most = used.len() / 4;
    for _ in 0..most {
        let mut sorted = residuals.clone();
        sorted.sort_by(f64::total_cmp);
        let limit = (3.0 * sorted[sorted.len() / 2]).max(1.0);
        let (worst, r) = residuals
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .expect("stops");
        if *r <= limit {
            break;
        }
        let k = used.remove(worst);
        visited[k].why = Some(format!(
            "tip found {r:.1} µm off the other stops' fit; left out"
        ));
        (registration, residuals) = fit_of(&visited, &used)?;
    }
    for (&k, r) in used.iter().zip(&residuals) {
        visited[k].residual = Some(*r);
    }
    let rms = (residuals.iter().map(|v| v * v).sum::<f64>() / residuals.len() as f64).sqrt();
    Ok(Fitted {
        registration,
        stops: visited,
        rms,
    })
}

impl Fitted {
    /// Why the fit is not to be used: its residuals' rms over `max_rms` µm.
    pub fn refuse(&self, max_rms: f64) -> Option<String> {
        let worst = self
            .stops
            .iter()
            .filter_map(|s| s.residual)
            .fold(0.0, f64::max);
        (self.rms > max_rms).then(|| format!(
            "the fit's residuals are {:.2} µm rms (largest {worst:.2}), over --max-rms {max_rms}: the tip was found at the wrong place at some stops, or the device's axes do not move it in straight lines; nothing written",
            self.rms
        ))
    }
}

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

/// The mounting `--sim-mount` describes.
pub fn mount(v: &[f64]) -> Result<Registration, String> {
    if v.len() != 7 {
        return Err(format!(
            "--sim-mount takes 7 numbers (degrees, 3 scales, 3 offsets), not {}",
            v.len()
        ));
    }
    let (c, s) = (v[0].to_radians().cos(), v[0].to_radians().sin());
    let r = Registration {
        matrix: [
            v[1] * c,
            -v[1] * s,
            0.0,
            v[2] * s,
            v[2] * c,
            0.0,
            0.0,
            0.0,
            v[3],
        ],
        offset: [v[4], v[5], v[6]],
    };
    r.check().map_err(|e| format!("--sim-mount: {e}"))?;
    Ok(r)
}

/// The synthetic microscope a simulated manipulator is seen through: a scene of cells,
/// the pipette drawn where the device's true mounting puts it.
pub struct SimMicroscope {
    /// The scene (its pipette is set for each frame).
    pub scene: synth::Scene,
    /// The simulated manipulator's true mounting.
    pub mount: Registration,
    /// Pipette elevation and azimuth of its body (the bridge's convention), degrees.
    pub pipette_deg: (f64, f64),
}

impl SimMicroscope {
    /// A 640×480 synthetic microscope with five cells of `seed`.
    pub fn new(seed: u64, mount: Registration) -> Self {
        let optics = synth::Optics {
            width: 640,
            height: 480,
            ..synth::Optics::default()
        };
        let spec = synth::CellSpec {
            count: 5,
            ..synth::CellSpec::default()
        };
        let scene = synth::Scene::random(
            optics,
            synth::Look {
                aperture: 0.1,
                ..synth::Look::default()
            },
            &spec,
            seed,
        );
        Self {
            scene,
            mount,
            pipette_deg: (30.0, 180.0),
        }
    }

    /// The frame with the device at `device`.
    pub fn frame(&mut self, device: P3) -> StereoFrame {
        let tip = self.mount.to_scene(device);
        let z0 = self.scene.optics.working_distance();
        self.scene.pipette = Some(capture::synthetic::pipette_from(
            tip,
            self.pipette_deg.0,
            self.pipette_deg.1,
            z0,
        ));
        let (left, right) = self.scene.render_views();
        StereoFrame { left, right }
    }
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
    crate::outputs::check(
        std::slice::from_ref(&a.output),
        &inputs,
        a.overwrite,
        "give -o another file",
    )?;
    let geometry_of = |p: &Path, w: usize, h: usize| -> Result<Optics, CliError> {
        let file = triangulate::calibration::read_file(p).map_err(CliError::Other)?;
        let source = format!("'{}'", p.display());
        let calibration = file.resolve(w, h, &source).map_err(CliError::Other)?;
        let rectify = file
            .cameras(&source)
            .map_err(CliError::Other)?
            .map(|cal| rectify::Rectification::bouguet(&cal).luts());
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
