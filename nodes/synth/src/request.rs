//! What `microstereo synth` is asked for: the numbers of its command line, checked, and the
//! scenes they make. The errors name the flags because these numbers come from them.

use crate::raw::{Layout, Microscope};
use crate::{CellSpec, Look, Optics, Pipette, Profile, Scene, Texture};

/// The appearance preset a request starts from (`--look`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum LookPreset {
    /// Textured cells with relief shading, a faintly textured substrate ([`Look::default`]).
    #[default]
    Dic,
    /// A textureless substrate under uneven light, darker cells with a membrane rim
    /// ([`Look::brightfield`]).
    Brightfield,
}

/// How strongly the substrate is textured (`--substrate-texture`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum SubstrateTexture {
    /// No texture: only noise.
    None,
    /// The default faint texture.
    Faint,
    /// A strongly textured substrate.
    Strong,
}

/// A synthetic scene, sequence or z-stack as asked for; [`Request::check`] it first. With
/// the `cli` feature it is the `synth` command's flags, with their defaults (as
/// [`Request::default`]).
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(feature = "cli", derive(clap::Args))]
pub struct Request {
    /// Image width, px.
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 640))]
    pub width: usize,
    /// Image height, px.
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 480))]
    pub height: usize,
    /// Number of cells.
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 6))]
    pub cells: usize,
    /// Footprint diameter range, µm (MIN,MAX).
    #[cfg_attr(feature = "cli", arg(long, value_delimiter = ',', default_values_t = [20.0, 100.0]))]
    pub diameter: Vec<f64>,
    /// Cell height range, µm (MIN,MAX).
    #[cfg_attr(feature = "cli", arg(long, value_delimiter = ',', default_values_t = [8.0, 25.0]))]
    pub cell_height: Vec<f64>,
    /// Random seed: same seed, same images.
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 1))]
    pub seed: u64,
    /// Sensor noise, grey levels (standard deviation).
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 1.5))]
    pub noise: f64,
    /// Defocus blur, px (Gaussian sigma).
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 0.0))]
    pub blur: f64,
    /// Pixel pitch, µm.
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 5.0))]
    pub pixel_pitch: f64,
    /// Magnification.
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 5.0))]
    pub magnification: f64,
    /// Effective focal length, µm.
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 20_000.0))]
    pub f_eff: f64,
    /// Stereo baseline, µm.
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 1_200.0))]
    pub baseline: f64,
    /// Write a sequence of this many frames (cells drift, the pipette advances).
    #[cfg_attr(feature = "cli", arg(long))]
    pub frames: Option<usize>,
    /// Largest cell drift, µm per frame.
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 1.0))]
    pub drift: f64,
    /// Add a pipette entering from the left at this height above the substrate, µm.
    #[cfg_attr(feature = "cli", arg(long))]
    pub pipette: Option<f64>,
    /// Where the pipette's tip points, degrees from +x towards +y (0: in from the left).
    #[cfg_attr(
        feature = "cli",
        arg(
            long,
            default_value_t = 0.0,
            allow_hyphen_values = true,
            requires = "pipette"
        )
    )]
    pub pipette_azimuth: f64,
    /// The tip's centre `X,Y` in µm from the image centre (default: 20 px in from the
    /// border it comes through).
    #[cfg_attr(
        feature = "cli",
        arg(
            long,
            value_delimiter = ',',
            allow_hyphen_values = true,
            requires = "pipette"
        )
    )]
    pub pipette_tip: Option<Vec<f64>>,
    /// Numerical aperture for the pipette's defocus: blurred by its height from the focal
    /// plane (blur circle radius NA·Δz; 0: always sharp).
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 0.0))]
    pub aperture: f64,
    /// Instead of cells, a textured target at these stage heights, µm (a z-stack for
    /// `calibrate-depth`).
    #[cfg_attr(
        feature = "cli",
        arg(long, value_delimiter = ',', allow_hyphen_values = true)
    )]
    pub stage_heights: Option<Vec<f64>>,
    /// Appearance preset: `dic` (textured cells with relief, a faintly textured substrate)
    /// or `brightfield` (a textureless substrate under a gradient and vignetting, darker
    /// cells with a dark membrane rim). The flags below change single properties of it.
    #[cfg_attr(feature = "cli", arg(long, value_enum, default_value_t = LookPreset::Dic))]
    pub look: LookPreset,
    /// The substrate's disparity at the image centre, px (the microscope focused above it:
    /// positive; default 0, the focal plane on the substrate).
    #[cfg_attr(feature = "cli", arg(long, allow_hyphen_values = true))]
    pub substrate_disparity: Option<f64>,
    /// Substrate texture: none, faint or strong (default: the look's).
    #[cfg_attr(feature = "cli", arg(long, value_enum))]
    pub substrate_texture: Option<SubstrateTexture>,
    /// Substrate tilt about the y and the x axis, degrees (each at most 10).
    #[cfg_attr(
        feature = "cli",
        arg(long, value_delimiter = ',', allow_hyphen_values = true)
    )]
    pub tilt: Option<Vec<f64>>,
    /// Lighting gradient across the field of view, grey levels.
    #[cfg_attr(feature = "cli", arg(long, allow_hyphen_values = true))]
    pub gradient: Option<f64>,
    /// Vignetting: the share of brightness lost at the corners (0..0.9).
    #[cfg_attr(feature = "cli", arg(long))]
    pub vignetting: Option<f64>,
    /// Darkening of the membrane rim where cells meet the substrate, grey levels (0..170).
    #[cfg_attr(feature = "cli", arg(long))]
    pub rim: Option<f64>,
    /// Cell height profile: dome (ellipsoid), cap (paraboloid), spread (flattened), flat (a plateau) or fried-egg (a raised nucleus on a thin spread cytoplasm).
    #[cfg_attr(feature = "cli", arg(long, value_enum, default_value_t = Profile::Dome))]
    pub profile: Profile,
    /// Outline irregularity: the largest amplitude of each of the radius's 2nd–4th
    /// harmonics, as a share of it (0..0.15; 0: ellipses).
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 0.0))]
    pub irregular: f64,
    /// Scatter this many debris particles on the substrate.
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 0))]
    pub debris: usize,
    /// The microscope's layout: `parallel` (rectified views from --f-eff and --baseline),
    /// or the raw views of a `cmo` (common main objective) or `greenough` microscope with
    /// --convergence, --pupil and --distortion (to calibrate with calibrate-microscope).
    #[cfg_attr(feature = "cli", arg(long, value_enum, default_value_t = Layout::Parallel))]
    pub optics: Layout,
    /// Each raw view's angle off the stage's normal, degrees (cmo, greenough).
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 5.5))]
    pub convergence: f64,
    /// Distance of the raw views' pupils above the focal plane, mm (cmo, greenough).
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 100.0))]
    pub pupil: f64,
    /// The raw views' off-axis distortion at its largest, px (cmo, greenough).
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 3.0))]
    pub distortion: f64,
    /// A z-stack of a chessboard instead of a textured target: its inner corners COLS,ROWS.
    #[cfg_attr(
        feature = "cli",
        arg(long, value_delimiter = ',', requires = "stage_heights")
    )]
    pub board: Option<Vec<usize>>,
    /// The chessboard's square side, µm.
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 100.0))]
    pub square: f64,
    /// Seed of the raw views' cameras (their small turns, scales and shifts): one
    /// microscope for a board stack and the scenes it measures, whatever their --seed.
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 1))]
    pub rig_seed: u64,
}

impl Default for Request {
    /// The command line's defaults (a test holds them to the flags').
    fn default() -> Self {
        Self {
            width: 640,
            height: 480,
            cells: 6,
            diameter: vec![20.0, 100.0],
            cell_height: vec![8.0, 25.0],
            seed: 1,
            noise: 1.5,
            blur: 0.0,
            pixel_pitch: 5.0,
            magnification: 5.0,
            f_eff: 20_000.0,
            baseline: 1_200.0,
            frames: None,
            drift: 1.0,
            pipette: None,
            pipette_azimuth: 0.0,
            pipette_tip: None,
            aperture: 0.0,
            stage_heights: None,
            look: LookPreset::Dic,
            substrate_disparity: None,
            substrate_texture: None,
            tilt: None,
            gradient: None,
            vignetting: None,
            rim: None,
            profile: Profile::Dome,
            irregular: 0.0,
            debris: 0,
            optics: Layout::Parallel,
            convergence: 5.5,
            pupil: 100.0,
            distortion: 3.0,
            board: None,
            square: 100.0,
            rig_seed: 1,
        }
    }
}

/// Why a request makes no scene.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum RequestError {
    /// An image side outside 32..8192.
    #[error("image size {width}×{height} is out of range: use 32..8192 on each side")]
    Size {
        /// Width asked for.
        width: usize,
        /// Height asked for.
        height: usize,
    },
    /// A diameter or height range without exactly two numbers.
    #[error("--diameter and --cell-height take two numbers, MIN,MAX (e.g. --diameter 20,100)")]
    NotPairs,
    /// A number outside its range (NaN and infinities included).
    #[error("{flag} {value} is out of range: use {lo}..{hi}")]
    OutOfRange {
        /// The flag that gave it.
        flag: &'static str,
        /// The number.
        value: f64,
        /// The smallest allowed.
        lo: f64,
        /// The largest allowed.
        hi: f64,
    },
    /// A diameter or height range whose MIN exceeds its MAX.
    #[error(
        "--diameter {diameter:?} and --cell-height {cell_height:?} must be positive MIN,MAX pairs with MIN ≤ MAX"
    )]
    Order {
        /// The diameter range.
        diameter: Vec<f64>,
        /// The height range.
        cell_height: Vec<f64>,
    },
    /// A tilt that is not two angles within ±10°.
    #[error(
        "--tilt {0:?} takes two angles in degrees, about y and about x, each within ±10 (e.g. --tilt 2,-1)"
    )]
    Tilt(Vec<f64>),
    /// A pipette tip that is not two finite numbers.
    #[error("--pipette-tip {0:?}: give X,Y in µm from the image centre (two finite numbers)")]
    PipetteTip(Vec<f64>),
    /// A chessboard that is not two corner counts of at least 2.
    #[error("--board {0:?}: give the inner corners COLS,ROWS, each 2..100 (e.g. --board 9,6)")]
    Board(Vec<usize>),
}

impl Request {
    /// Checks every number: the image size, that the ranges are pairs, each number's range,
    /// then that each range's MIN is positive and at most its MAX (the first failure).
    pub fn check(&self) -> Result<(), RequestError> {
        if self.width < 32 || self.height < 32 || self.width > 8192 || self.height > 8192 {
            return Err(RequestError::Size {
                width: self.width,
                height: self.height,
            });
        }
        let (d, h) = (&self.diameter, &self.cell_height);
        if d.len() != 2 || h.len() != 2 {
            return Err(RequestError::NotPairs);
        }
        // The optics span a phone camera to a long-distance microscope (µm).
        let mut checked: Vec<(&'static str, f64, f64, f64)> = vec![
            ("--pixel-pitch", self.pixel_pitch, 0.01, 1000.0),
            ("--magnification", self.magnification, 0.01, 10_000.0),
            ("--f-eff", self.f_eff, 1.0, 1e7),
            ("--baseline", self.baseline, 0.1, 1e7),
            ("--diameter", d[0], 0.5, 2000.0),
            ("--diameter", d[1], 0.5, 2000.0),
            ("--cell-height", h[0], 0.1, 1000.0),
            ("--cell-height", h[1], 0.1, 1000.0),
            ("--noise", self.noise, 0.0, 100.0),
            ("--blur", self.blur, 0.0, 50.0),
            ("--aperture", self.aperture, 0.0, 1.5),
            ("--pipette-azimuth", self.pipette_azimuth, -360.0, 360.0),
            ("--drift", self.drift, 0.0, 100.0),
            ("--cells", self.cells as f64, 0.0, 10_000.0),
            ("--debris", self.debris as f64, 0.0, 100_000.0),
            ("--irregular", self.irregular, 0.0, 0.15),
            ("--convergence", self.convergence, 0.5, 30.0),
            ("--pupil", self.pupil, 1.0, 1e7),
            ("--distortion", self.distortion, 0.0, 50.0),
            ("--square", self.square, 1.0, 1e5),
        ];
        let optional = [
            ("--pipette", self.pipette, 0.0, 10_000.0),
            ("--frames", self.frames.map(|n| n as f64), 1.0, 100_000.0),
            ("--gradient", self.gradient, -170.0, 170.0),
            ("--vignetting", self.vignetting, 0.0, 0.9),
            ("--rim", self.rim, 0.0, 170.0),
            (
                "--substrate-disparity",
                self.substrate_disparity,
                -1000.0,
                1000.0,
            ),
        ];
        for (n, v, lo, hi) in optional {
            if let Some(v) = v {
                checked.push((n, v, lo, hi));
            }
        }
        for &z in self.stage_heights.iter().flatten() {
            checked.push(("--stage-heights", z, -10_000.0, 10_000.0));
        }
        // A NaN passes no comparison, so the test is "inside", not "outside".
        if let Some(&(flag, value, lo, hi)) = checked
            .iter()
            .find(|(_, v, lo, hi)| !(lo..=hi).contains(&v))
        {
            return Err(RequestError::OutOfRange {
                flag,
                value,
                lo,
                hi,
            });
        }
        if let Some(b) = &self.board
            && (b.len() != 2 || b.iter().any(|&n| !(2..=100).contains(&n)))
        {
            return Err(RequestError::Board(b.clone()));
        }
        if d[0] <= 0.0 || d[0] > d[1] || h[0] <= 0.0 || h[0] > h[1] {
            return Err(RequestError::Order {
                diameter: d.clone(),
                cell_height: h.clone(),
            });
        }
        Ok(())
    }

    /// The optics, the look (cells textured by `texture`) and the tilt of a checked request;
    /// fails on a tilt that is not two angles within ±10°.
    pub fn setup(self, texture: Texture) -> Result<Setup, RequestError> {
        let microscope = (self.optics != Layout::Parallel).then(|| Microscope {
            layout: self.optics,
            convergence_deg: self.convergence,
            pupil: 1000.0 * self.pupil,
            um_per_px: self.pixel_pitch / self.magnification,
            width: self.width,
            height: self.height,
            distortion: self.distortion,
            aperture: if self.aperture > 0.0 {
                self.aperture
            } else {
                0.1
            },
            seed: self.rig_seed,
        });
        let optics = match &microscope {
            Some(m) => m.optics(),
            None => Optics {
                width: self.width,
                height: self.height,
                pixel_pitch: self.pixel_pitch,
                magnification: self.magnification,
                f_eff: self.f_eff,
                baseline: self.baseline,
            },
        };
        let mut look = match self.look {
            LookPreset::Dic => Look::default(),
            LookPreset::Brightfield => Look::brightfield(),
        };
        look.noise = self.noise;
        look.blur = self.blur;
        look.aperture = self.aperture;
        look.texture = texture;
        if let Some(t) = self.substrate_texture {
            look.substrate_texture = match t {
                SubstrateTexture::None => 0.0,
                SubstrateTexture::Faint => Look::default().substrate_texture,
                SubstrateTexture::Strong => 30.0,
            };
        }
        let tilt = match self.tilt.as_deref() {
            None => [0.0; 2],
            Some([x, y]) if x.abs() <= 10.0 && y.abs() <= 10.0 => {
                [x.to_radians().tan(), y.to_radians().tan()]
            }
            Some(t) => return Err(RequestError::Tilt(t.to_vec())),
        };
        if let Some(g) = self.gradient {
            look.gradient = g;
        }
        if let Some(v) = self.vignetting {
            look.vignetting = v;
        }
        if let Some(r) = self.rim {
            look.rim = r;
        }
        if microscope.is_some() {
            // The raw views blur by their own defocus.
            look.blur = 0.0;
        }
        Ok(Setup {
            request: self,
            optics,
            look,
            tilt,
            microscope,
        })
    }
}

/// A checked request with its optics, look and tilt: what its scenes are built from.
#[derive(Clone, Debug)]
pub struct Setup {
    /// The request.
    pub request: Request,
    /// The microscope.
    pub optics: Optics,
    /// The appearance.
    pub look: Look,
    /// The substrate's slope along x and along y (rise over run).
    pub tilt: [f64; 2],
    /// The raw views' microscope (`None`: the views come rectified, `optics`' own).
    pub microscope: Option<Microscope>,
}

impl Setup {
    /// How many scenes it renders: the z-stack's, the sequence's frames, or one.
    pub fn scene_count(&self) -> usize {
        match (
            &self.request.stage_heights,
            self.request.frames.unwrap_or(0),
        ) {
            (Some(zs), _) => zs.len(),
            (None, n) => n.max(1),
        }
    }

    /// The z-stack's target scenes with their stage heights (none without stage heights),
    /// each built only when reached.
    pub fn targets(&self) -> impl Iterator<Item = (f64, Scene)> + '_ {
        let r = &self.request;
        r.stage_heights
            .iter()
            .flatten()
            .enumerate()
            .map(move |(i, &z)| {
                let mut s = Scene::target(self.optics, self.look.clone(), z, r.seed + i as u64);
                s.tilt = self.tilt;
                if let Some([cols, rows]) = r.board.as_deref().map(|b| [b[0], b[1]]) {
                    s.target = false;
                    s.board = Some(crate::Chessboard {
                        cols,
                        rows,
                        square: r.square,
                    });
                }
                (z, s)
            })
    }

    /// The scene of cells (with debris and pipette as asked) and the spec it was drawn
    /// from; fails on a pipette tip that is not two finite numbers.
    pub fn cells(&self) -> Result<(Scene, CellSpec), RequestError> {
        let r = &self.request;
        let spec = CellSpec {
            count: r.cells,
            diameter: [r.diameter[0], r.diameter[1]],
            height: [r.cell_height[0], r.cell_height[1]],
            profile: r.profile,
            irregular: r.irregular,
            ..CellSpec::default()
        };
        let mut scene = Scene::random(self.optics, self.look.clone(), &spec, r.seed);
        scene.tilt = self.tilt;
        if let Some(d) = r.substrate_disparity {
            scene = scene.with_substrate_disparity(d);
        }
        if r.debris > 0 {
            scene = scene.with_debris(r.debris, [1.0, 4.0], r.seed);
        }
        if let Some(h) = r.pipette {
            let tip = match &r.pipette_tip {
                Some(t) if t.len() != 2 || t.iter().any(|v| !v.is_finite() || v.abs() > 1e6) => {
                    return Err(RequestError::PipetteTip(t.clone()));
                }
                Some(t) => Some([t[0], t[1]]),
                None => None,
            };
            scene.pipette = Some(Pipette::entering(&self.optics, h, r.pipette_azimuth, tip));
        }
        Ok((scene, spec))
    }

    /// Frame `f` of the sequence of `scene`: the cells drifted, the pipette advanced so that
    /// it crosses 60 % of the image over the sequence.
    pub fn frame(&self, scene: &Scene, f: usize) -> Scene {
        let frames = self.request.frames.unwrap_or(0);
        let step = 0.6 * self.optics.um_per_px() * self.request.width as f64 / frames.max(1) as f64;
        scene.at_frame(f, self.request.drift, step)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> Request {
        Request {
            width: 64,
            height: 48,
            cells: 3,
            diameter: vec![10.0, 20.0],
            cell_height: vec![4.0, 8.0],
            ..Request::default()
        }
    }

    fn message(r: &Request) -> String {
        r.check().unwrap_err().to_string()
    }

    #[test]
    fn out_of_range_numbers_name_their_flag_and_range() {
        let r = Request {
            noise: 200.0,
            ..small()
        };
        assert_eq!(message(&r), "--noise 200 is out of range: use 0..100");
        let r = Request {
            f_eff: f64::NAN,
            ..small()
        };
        assert_eq!(message(&r), "--f-eff NaN is out of range: use 1..10000000");
        let r = Request {
            stage_heights: Some(vec![1.0, 99_999.0]),
            ..small()
        };
        assert_eq!(
            message(&r),
            "--stage-heights 99999 is out of range: use -10000..10000"
        );
        let r = Request {
            frames: Some(0),
            ..small()
        };
        assert_eq!(message(&r), "--frames 0 is out of range: use 1..100000");
    }

    #[test]
    fn checks_run_in_the_command_lines_order() {
        // A bad size is told before bad pairs, bad pairs before a bad number, a bad number
        // before a range whose MIN exceeds its MAX.
        let r = Request {
            width: 20,
            diameter: vec![10.0],
            noise: 200.0,
            ..Request::default()
        };
        assert_eq!(
            message(&r),
            "image size 20×480 is out of range: use 32..8192 on each side"
        );
        let r = Request {
            diameter: vec![10.0],
            noise: 200.0,
            ..Request::default()
        };
        assert_eq!(
            message(&r),
            "--diameter and --cell-height take two numbers, MIN,MAX (e.g. --diameter 20,100)"
        );
        let r = Request {
            diameter: vec![50.0, 10.0],
            noise: 200.0,
            ..Request::default()
        };
        assert_eq!(message(&r), "--noise 200 is out of range: use 0..100");
        let r = Request {
            diameter: vec![50.0, 10.0],
            ..Request::default()
        };
        assert_eq!(
            message(&r),
            "--diameter [50.0, 10.0] and --cell-height [8.0, 25.0] must be positive MIN,MAX pairs with MIN ≤ MAX"
        );
        assert_eq!(Request::default().check(), Ok(()));
    }

    #[test]
    fn a_bad_tilt_or_pipette_tip_is_refused_with_its_values() {
        let r = Request {
            tilt: Some(vec![20.0, 1.0]),
            ..small()
        };
        assert_eq!(
            r.setup(Texture::Noise).unwrap_err().to_string(),
            "--tilt [20.0, 1.0] takes two angles in degrees, about y and about x, each within ±10 (e.g. --tilt 2,-1)"
        );
        let r = Request {
            pipette: Some(5.0),
            pipette_tip: Some(vec![1.0, 2.0, 3.0]),
            ..small()
        };
        let setup = r.setup(Texture::Noise).unwrap();
        assert_eq!(
            setup.cells().unwrap_err().to_string(),
            "--pipette-tip [1.0, 2.0, 3.0]: give X,Y in µm from the image centre (two finite numbers)"
        );
        // A z-stack has no pipette, so its tip is not looked at.
        let stack = Setup {
            request: Request {
                stage_heights: Some(vec![0.0, 1.0]),
                ..setup.request.clone()
            },
            ..setup
        };
        assert_eq!(stack.targets().count(), 2);
    }

    #[test]
    fn a_request_builds_the_scene_it_describes() {
        let r = Request {
            look: LookPreset::Brightfield,
            substrate_texture: Some(SubstrateTexture::Strong),
            tilt: Some(vec![2.0, -1.0]),
            rim: Some(20.0),
            noise: 0.0,
            pipette: Some(5.0),
            pipette_azimuth: 30.0,
            pipette_tip: Some(vec![3.0, -2.0]),
            debris: 4,
            substrate_disparity: Some(2.0),
            profile: Profile::Cap,
            seed: 9,
            ..small()
        };
        r.check().unwrap();
        let setup = r.setup(Texture::Noise).unwrap();
        let (scene, spec) = setup.cells().unwrap();
        // The same scene built by hand from the library's parts.
        let optics = Optics {
            width: 64,
            height: 48,
            ..Optics::default()
        };
        let look = Look {
            substrate_texture: 30.0,
            rim: 20.0,
            noise: 0.0,
            ..Look::brightfield()
        };
        let want_spec = CellSpec {
            count: 3,
            diameter: [10.0, 20.0],
            height: [4.0, 8.0],
            profile: Profile::Cap,
            ..CellSpec::default()
        };
        assert_eq!(spec, want_spec);
        let mut want = Scene::random(optics, look, &want_spec, 9);
        want.tilt = [2f64.to_radians().tan(), (-1f64).to_radians().tan()];
        let mut want = want
            .with_substrate_disparity(2.0)
            .with_debris(4, [1.0, 4.0], 9);
        want.pipette = Some(Pipette::entering(&optics, 5.0, 30.0, Some([3.0, -2.0])));
        assert_eq!(scene, want);
        // And it renders as that scene does: a tilted substrate at disparity 2 in the
        // centre, cells on it, the pipette in front.
        let (got, exp) = (scene.render(), want.render());
        assert_eq!(got.disparity.data, exp.disparity.data);
        assert_eq!(got.labels.data, exp.labels.data);
        assert!(got.labels.data.contains(&crate::PIPETTE));
        assert!(
            got.labels
                .data
                .iter()
                .any(|&l| l != 0 && l != crate::PIPETTE)
        );
        let c = got.disparity.data[24 * 64 + 32];
        assert!(c >= 1.5, "centre disparity {c}");
    }

    #[test]
    fn a_sequence_moves_and_a_stack_rises() {
        let r = Request {
            frames: Some(4),
            ..small()
        };
        let setup = r.setup(Texture::Noise).unwrap();
        assert_eq!(setup.scene_count(), 4);
        let (scene, _) = setup.cells().unwrap();
        let step = 0.6 * 1.0 * 64.0 / 4.0;
        assert_eq!(setup.frame(&scene, 2), scene.at_frame(2, 1.0, step));
        assert_ne!(setup.frame(&scene, 2), setup.frame(&scene, 0));

        let r = Request {
            stage_heights: Some(vec![-10.0, 10.0]),
            ..small()
        };
        let setup = r.setup(Texture::Noise).unwrap();
        assert_eq!(setup.scene_count(), 2);
        let t: Vec<(f64, Scene)> = setup.targets().collect();
        assert_eq!(t[0].0, -10.0);
        assert_eq!(t[1].1.stage, 10.0);
        assert_eq!(t[1].1.seed, 2);
        assert!(t.iter().all(|(_, s)| s.target));
    }

    #[cfg(feature = "cli")]
    #[test]
    fn the_flags_defaults_are_the_requests() {
        use clap::{Args, FromArgMatches};
        let cmd = Request::augment_args(clap::Command::new("synth"));
        let m = cmd.clone().try_get_matches_from(["synth"]).unwrap();
        assert_eq!(Request::from_arg_matches(&m).unwrap(), Request::default());
        let m = cmd
            .try_get_matches_from(["synth", "--profile", "fried-egg", "--tilt", "-2,1"])
            .unwrap();
        let r = Request::from_arg_matches(&m).unwrap();
        assert_eq!(
            (r.profile, r.tilt),
            (Profile::FriedEgg, Some(vec![-2.0, 1.0]))
        );
    }
}
