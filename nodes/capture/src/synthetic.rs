//! The capture node's synthetic source: one rendered stereo-microscope frame per step, the
//! cells drifting and an optional pipette advancing from frame to frame. Given the
//! manipulator's state on its `tip` feedback input, it draws the pipette where the
//! manipulator says the tip is (a closed loop with a simulated manipulator).

use schemas::{ManipulatorState, StereoFrame};
use serde::Deserialize;
use synth::{Backdrop, CellSpec, Look, NoiseTable, Optics, Pipette, Scene};

/// `params` of a `capture` node with `source = "synthetic"`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SyntheticParams {
    /// `synthetic`.
    #[serde(default = "synthetic")]
    pub source: String,
    /// Frame width, px.
    #[serde(default = "default_width")]
    pub width: usize,
    /// Frame height, px.
    #[serde(default = "default_height")]
    pub height: usize,
    /// Number of cells.
    #[serde(default = "default_cells")]
    pub cells: usize,
    /// Scene seed.
    #[serde(default = "default_seed")]
    pub seed: u64,
    /// Largest cell drift, µm per frame.
    #[serde(default = "default_drift")]
    pub drift: f64,
    /// Pipette height above the substrate, µm (none without it).
    #[serde(default)]
    pub pipette: Option<f64>,
    /// Frames per second (as fast as possible without it).
    #[serde(default)]
    pub fps: Option<f64>,
}

fn synthetic() -> String {
    "synthetic".into()
}
fn default_width() -> usize {
    1280
}
fn default_height() -> usize {
    1024
}
fn default_cells() -> usize {
    10
}
fn default_seed() -> u64 {
    1
}
fn default_drift() -> f64 {
    1.0
}

impl SyntheticParams {
    /// Reads and checks a `params` table.
    pub fn from_table(t: &toml::Table) -> Result<Self, String> {
        let p: Self = runtime::registry::from_table(t)?;
        if !(16..=8192).contains(&p.width) || !(16..=8192).contains(&p.height) {
            return Err(format!(
                "{}×{} is not a frame size (16..8192)",
                p.width, p.height
            ));
        }
        if p.fps.is_some_and(|f| f.is_nan() || f <= 0.0) {
            return Err("fps must be positive".into());
        }
        Ok(p)
    }
}

/// Renders the frames of one synthetic scene.
#[derive(Debug)]
pub struct SyntheticCapture {
    scene: Scene,
    drift: f64,
    step: f64,
    /// The pipette where the manipulator last said it was.
    manipulated: Option<Pipette>,
    /// The scene's bare substrate, rendered once: a frame renders only what its cells and
    /// pipette touch (53 against 244 ms at 1280×1024 with 10 cells), to the same bytes.
    backdrop: Option<Backdrop>,
    /// The sensor noise, drawn once (a frame's own would cost more than its rendering).
    noise: Option<NoiseTable>,
}

impl SyntheticCapture {
    /// The scene the parameters describe.
    pub fn new(p: &SyntheticParams) -> Self {
        let optics = Optics {
            width: p.width,
            height: p.height,
            ..Optics::default()
        };
        let spec = CellSpec {
            count: p.cells,
            ..CellSpec::default()
        };
        let mut scene = Scene::random(optics, Look::default(), &spec, p.seed);
        let s = optics.um_per_px();
        scene.pipette = p.pipette.map(|h| Pipette {
            tip: [-0.5 * p.width as f64 * s + 20.0 * s, 0.0],
            height: h,
            tip_radius: 1.5,
            taper: 0.08,
            elevation: 0.0,
        });
        Self {
            scene,
            drift: p.drift,
            step: 4.0 * s,
            manipulated: None,
            backdrop: None,
            noise: None,
        }
    }

    /// The calibration that triangulates the frames.
    pub fn calibration(&self) -> schemas::Calibration {
        self.scene.optics.calibration()
    }
}

/// The pipette a manipulator state describes in a scene whose substrate lies at depth `z0`
/// (the state's third coordinate is `−Z`, µm).
pub fn pipette_at(m: &ManipulatorState, z0: f64) -> Pipette {
    Pipette {
        tip: [m.tip[0], m.tip[1]],
        height: m.tip[2] + z0,
        tip_radius: 1.5,
        taper: 0.08,
        elevation: m.elevation_deg.to_radians(),
    }
}

impl SyntheticCapture {
    /// Draws the pipette where the manipulator says its tip is from now on.
    pub fn set_tip(&mut self, m: &ManipulatorState) {
        // Drawn as coming from −x, the only direction the renderer knows.
        self.manipulated = Some(pipette_at(m, self.scene.optics.working_distance()));
    }

    /// Renders frame `seq`.
    pub fn frame(&mut self, seq: u64) -> StereoFrame {
        let mut scene = self.scene.at_frame(seq as usize, self.drift, self.step);
        if self.manipulated.is_some() {
            scene.pipette = self.manipulated;
        }
        let means = scene.render_means_over(&mut self.backdrop);
        let (w, h) = (scene.optics.width, scene.optics.height);
        if !self.noise.as_ref().is_some_and(|n| n.fits(w, h)) {
            self.noise = Some(NoiseTable::new(w, h, scene.seed));
        }
        let noise = self.noise.as_ref().expect("made above");
        let (left, right) = noise.apply(means, scene.look.noise, seq);
        StereoFrame { left, right }
    }
}
