//! The manipulator registered to the cameras: the pipette's tip found in both views
//! ([`tip::find_tip`]) and triangulated at a grid of device stops ([`grid_stops`]), the map
//! `device = M·scene + offset` fitted ([`register`]), and the simulated microscope a
//! simulated manipulator is seen through ([`SimMicroscope`]). [`session`] runs it with a
//! device and a source of frames as `microstereo calibrate-manipulator` does, and says
//! what the bridge reads.

pub mod session;
pub mod tip;

use manipulator_bridge::device::Device;
use manipulator_bridge::geom::P3;
use manipulator_bridge::registration::Registration;
use rectify::RemapLut;
use schemas::{Calibration, StereoFrame};
use std::time::{Duration, Instant};
use tip::find_tip;

/// What turns a frame into a tip in the scene: the rectification (for raw cameras) and the
/// rectified geometry.
pub struct Optics {
    /// Resampling tables of a raw pair, left and right (`None`: frames come rectified).
    pub rectify: Option<(RemapLut, RemapLut)>,
    /// The rectified views' geometry.
    pub calibration: Calibration,
}

impl Optics {
    /// The optics a calibration file gives frames of `w × h`: its rectified geometry and,
    /// when it holds the raw cameras (`[stereo]`), their rectification.
    pub fn from_file(path: &std::path::Path, w: usize, h: usize) -> Result<Self, String> {
        let file = calibration::file::read_file(path)?;
        let source = format!("'{}'", path.display());
        let calibration = file.resolve(w, h, &source)?;
        let rectify = file
            .cameras(&source)?
            .map(|cal| rectify::luts(&calibration::stereo::Rectification::bouguet(&cal).into()));
        Ok(Self {
            rectify,
            calibration,
        })
    }
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
        self.scene.pipette = Some(synth::Pipette::from_tip(
            tip,
            self.pipette_deg.0,
            self.pipette_deg.1,
            z0,
        ));
        let (left, right) = self.scene.render_views();
        StereoFrame { left, right }
    }
}
