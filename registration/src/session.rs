//! A registration run with a device and a source of frames (`microstereo
//! calibrate-manipulator`): its settings checked ([`Plan`]), the rig put together
//! ([`Rig::sim`], [`Rig::real`]), a grid of stops visited
//! ([`Rig::register`]) or one stop re-registering the offset after a pipette change
//! ([`Rig::register_offset`]), and what is reported and written of the fit
//! ([`Fitted::stop_lines`], [`Fitted::summary`], [`Fitted::to_toml`]).

use crate::{Fitted, Optics, SimMicroscope, Stop, grid_stops, mount, register, tip_in_scene};
use manipulator_bridge::device::{Device, SimDevice, wall_clock};
use manipulator_bridge::geom::P3;
use manipulator_bridge::registration::Registration;
use schemas::StereoFrame;
use std::path::Path;
use std::time::Duration;

/// A source of frames, told where the device stands.
pub type Grab = Box<dyn FnMut(P3) -> Result<StereoFrame, String>>;

/// What a grid registration does: its stops, how fast it moves between them, and the
/// largest rms residual it accepts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plan {
    /// Stops along the device's x, y and z axes.
    pub grid: [usize; 3],
    /// Half the travel on each device axis, µm.
    pub span: P3,
    /// Device speed between stops, µm/s.
    pub speed: f64,
    /// Largest rms residual accepted, µm.
    pub max_rms: f64,
}

impl Plan {
    /// The plan the flags `--grid NXxNYxNZ`, `--span`, `--speed` and `--max-rms` give,
    /// each checked (in that order, the errors naming the flags).
    pub fn new(grid: &str, span: &[f64], speed: f64, max_rms: f64) -> Result<Self, String> {
        let g: Vec<usize> = grid
            .split(['x', 'X'])
            .map(|p| p.trim().parse().unwrap_or(0))
            .collect();
        if g.len() != 3 || g.iter().any(|n| *n == 0 || *n > 10) || g.iter().product::<usize>() < 6 {
            return Err(format!(
                "--grid '{grid}': give NXxNYxNZ stops (each 1..10, at least 6 in all, e.g. 3x3x2)"
            ));
        }
        if span.len() != 3
            || span
                .iter()
                .any(|v| !(v.is_finite() && *v > 0.0 && *v <= 5000.0))
        {
            return Err(format!(
                "--span {span:?}: give three half-travels in µm (0..5000)"
            ));
        }
        if !(max_rms > 0.0 && max_rms <= 1000.0) {
            return Err(format!("--max-rms {max_rms} must be in 0..1000 µm"));
        }
        // Manipulators travel at most centimetres a second.
        if !(speed > 0.0 && speed <= 1e5) {
            return Err(format!("--speed {speed} must be in 0..1e5 µm/s"));
        }
        Ok(Self {
            grid: [g[0], g[1], g[2]],
            span: [span[0], span[1], span[2]],
            speed,
            max_rms,
        })
    }
}

/// Where `--sim-start` puts the simulated tip, camera frame `[X, Y, Z]` µm.
pub fn sim_start(v: &[f64]) -> Result<P3, String> {
    if v.len() != 3 || v.iter().any(|v| !v.is_finite() || v.abs() > 1e6) {
        return Err(format!(
            "--sim-start {v:?}: give X,Y,Z in µm (each within ±1e6)"
        ));
    }
    Ok([v[0], v[1], v[2]])
}

/// A real manipulator on serial port `port`: `kind` is `mp285` or `scientifica`.
fn open_device(kind: &str, port: &str) -> Result<Box<dyn Device>, String> {
    let timeout = Duration::from_secs(2);
    Ok(match kind {
        "mp285" => {
            Box::new(manipulator_bridge::mp285::Mp285::open(port, timeout).map_err(|e| e.0)?)
        }
        "scientifica" => Box::new(
            manipulator_bridge::scientifica::Scientifica::open(port, timeout).map_err(|e| e.0)?,
        ),
        d => {
            return Err(format!(
                "unknown --device '{d}'; devices: sim, mp285, scientifica"
            ));
        }
    })
}

/// A device, the frames it is seen in, and what turns them into a tip in the scene.
pub struct Rig {
    /// The manipulator.
    pub device: Box<dyn Device>,
    /// The frames, told where the device stands.
    pub grab: Grab,
    /// What turns a frame into a tip in the scene.
    pub optics: Optics,
}

impl Rig {
    /// A simulated manipulator mounted as the `--sim-mount` numbers `mount_flags` say, its
    /// tip at `start` (camera frame, µm) and moving up to 4 × `speed`, seen by the
    /// synthetic microscope of `seed`; the optics from the calibration file `calibration`
    /// when given, else the microscope's own.
    pub fn sim(
        seed: u64,
        mount_flags: &[f64],
        start: P3,
        speed: f64,
        calibration: Option<&Path>,
    ) -> Result<Self, String> {
        let m = mount(mount_flags)?;
        let mut micro = SimMicroscope::new(seed, m);
        let (w, h) = (micro.scene.optics.width, micro.scene.optics.height);
        let optics = match calibration {
            Some(p) => Optics::from_file(p, w, h)?,
            None => Optics {
                rectify: None,
                calibration: micro.scene.optics.calibration(),
            },
        };
        let device = SimDevice::new(m.to_device(start), 4.0 * speed, 20_000.0, wall_clock());
        Ok(Self {
            device: Box::new(device),
            grab: Box::new(move |at| Ok(micro.frame(at))),
            optics,
        })
    }

    /// A real manipulator of `kind` (`mp285` or `scientifica`) on serial port `port`, seen
    /// by the cameras named `cameras` (left, right), which `open_cameras` opens (their
    /// frames and size), its optics from the calibration file `calibration`. Each is
    /// needed: a missing one is named by its flag.
    pub fn real(
        kind: &str,
        port: Option<&str>,
        calibration: Option<&Path>,
        cameras: Option<&[String]>,
        open_cameras: impl FnOnce(&[String]) -> Result<(Grab, (usize, usize)), String>,
    ) -> Result<Self, String> {
        let port = port.ok_or(format!("--device {kind} needs --port (its serial port)"))?;
        let calibration = calibration.ok_or("a real device needs the cameras' --calibration")?;
        let cameras = cameras.ok_or("a real device needs --cameras LEFT RIGHT")?;
        let device = open_device(kind, port)?;
        let (grab, (w, h)) = open_cameras(cameras)?;
        Ok(Self {
            device,
            grab,
            optics: Optics::from_file(calibration, w, h)?,
        })
    }

    /// Registers the device through `plan`'s grid of stops around where it stands
    /// ([`register`]).
    pub fn register(&mut self, plan: &Plan) -> Result<Fitted, String> {
        let start = self.device.state().map_err(|e| e.0)?.position;
        let stops = grid_stops(start, plan.grid, plan.span);
        register(
            self.device.as_mut(),
            &mut self.grab,
            &self.optics,
            &stops,
            plan.speed,
        )
    }

    /// Re-registers after a pipette change: the tip found where the device stands, the
    /// axes of `earlier` kept and only the offset moved to pass through it (one stop,
    /// residual 0).
    pub fn register_offset(&mut self, earlier: &Registration) -> Result<Fitted, String> {
        let at = self.device.state().map_err(|e| e.0)?.position;
        let scene = (self.grab)(at).and_then(|f| tip_in_scene(&f, &self.optics))?;
        Ok(Fitted {
            registration: earlier.with_offset_through(scene, at),
            stops: vec![Stop {
                device: at,
                scene: Some(scene),
                why: None,
                residual: Some(0.0),
            }],
            rms: 0.0,
        })
    }
}

impl Fitted {
    /// One line per stop: where the device stood and the tip was found with its
    /// residual, or why the stop was left out.
    pub fn stop_lines(&self) -> Vec<String> {
        let mut out = Vec::new();
        for (k, s) in self.stops.iter().enumerate() {
            match (&s.scene, s.residual, &s.why) {
                (Some(p), Some(r), _) => out.push(format!(
                    "stop {:>2}: device [{:.1}, {:.1}, {:.1}] -> tip [{:.2}, {:.2}, {:.2}] µm, residual {r:.3} µm",
                    k + 1,
                    s.device[0],
                    s.device[1],
                    s.device[2],
                    p[0],
                    p[1],
                    p[2]
                )),
                (_, _, Some(why)) => out.push(format!(
                    "stop {:>2}: device [{:.1}, {:.1}, {:.1}]: {why}",
                    k + 1,
                    s.device[0],
                    s.device[1],
                    s.device[2]
                )),
                _ => {}
            }
        }
        out
    }

    /// One line: the rms residual, the stops used, each axis's scale, the handedness and
    /// the matrix.
    pub fn summary(&self) -> String {
        let m = &self.registration.matrix;
        let det = m[0] * (m[4] * m[8] - m[5] * m[7]) - m[1] * (m[3] * m[8] - m[5] * m[6])
            + m[2] * (m[3] * m[7] - m[4] * m[6]);
        let svd = nalgebra::Matrix3::from_row_slice(m).svd(false, false);
        let scales = svd.singular_values;
        format!(
            "registration: rms residual {:.3} µm over {} stops; axis scales {:.4} {:.4} {:.4}; {}; device = M·scene + offset with M rows [{:.4} {:.4} {:.4}] [{:.4} {:.4} {:.4}] [{:.4} {:.4} {:.4}]",
            self.rms,
            self.stops.iter().filter(|s| s.residual.is_some()).count(),
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
        )
    }

    /// The registration file the bridge reads (its `registration` parameter), to be
    /// written at `path` (named in its comment): the map, the rms and every stop.
    pub fn to_toml(&self, path: &Path) -> String {
        let rows: Vec<String> = self
            .stops
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
        format!(
            "# Written by microstereo calibrate-manipulator: device = matrix · [X, Y, Z] + offset (µm; matrix row by row;\n# [X, Y, Z]: the triangulation's camera frame, Z the depth). The bridge reads it: registration = \"{}\".\nmatrix = {:?}\noffset = {:?}\nrms_um = {}\nstops = [\n  {}\n]\n",
            path.display(),
            self.registration.matrix,
            self.registration.offset,
            self.rms,
            rows.join(",\n  ")
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_plan_takes_the_default_flags_and_names_the_flag_it_refuses() {
        let p = Plan::new("3x3x2", &[40.0, 40.0, 20.0], 200.0, 3.0).unwrap();
        assert_eq!(p.grid, [3, 3, 2]);
        assert_eq!(p.span, [40.0, 40.0, 20.0]);
        let refused = |g: &str, span: &[f64], speed: f64, rms: f64| {
            Plan::new(g, span, speed, rms).unwrap_err()
        };
        let span = [40.0, 40.0, 20.0];
        assert!(refused("1x1x1", &span, 200.0, 3.0).starts_with("--grid '1x1x1'"));
        assert!(refused("3x3", &span, 200.0, 3.0).starts_with("--grid"));
        assert!(refused("3x3x2", &[40.0, 40.0], 200.0, 3.0).starts_with("--span"));
        assert!(refused("3x3x2", &span, 200.0, 0.0).starts_with("--max-rms"));
        assert!(refused("3x3x2", &span, f64::NAN, 3.0).starts_with("--speed"));
        // The grid is checked first, as the flags are read.
        assert!(refused("0x0x0", &[], 0.0, 0.0).starts_with("--grid"));
        assert!(
            sim_start(&[1.0, 2.0])
                .unwrap_err()
                .starts_with("--sim-start")
        );
        assert_eq!(sim_start(&[1.0, 2.0, 3.0]).unwrap(), [1.0, 2.0, 3.0]);
    }

    #[test]
    fn a_fit_is_reported_and_written_stop_by_stop() {
        let f = Fitted {
            registration: Registration::default(),
            stops: vec![
                Stop {
                    device: [1.0, 2.0, 3.0],
                    scene: Some([4.0, 5.0, 6.0]),
                    why: None,
                    residual: Some(0.5),
                },
                Stop {
                    device: [7.0, 8.0, 9.0],
                    scene: None,
                    why: Some("no tip".into()),
                    residual: None,
                },
            ],
            rms: 0.5,
        };
        assert_eq!(
            f.stop_lines(),
            [
                "stop  1: device [1.0, 2.0, 3.0] -> tip [4.00, 5.00, 6.00] µm, residual 0.500 µm",
                "stop  2: device [7.0, 8.0, 9.0]: no tip"
            ]
        );
        assert!(f.summary().contains("over 1 stops"));
        let text = f.to_toml(Path::new("reg.toml"));
        assert!(text.contains("registration = \"reg.toml\""));
        assert!(text.contains("left_out = \"no tip\""));
    }
}
