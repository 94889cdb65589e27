//! The capture node's synthetic source: one rendered stereo-microscope frame per step, the
//! cells drifting and an optional pipette advancing from frame to frame. Given the
//! manipulator's state on its `tip` feedback input, it draws the pipette where the
//! manipulator says the tip is (a closed loop with a simulated manipulator).

use schemas::{ManipulatorState, StereoFrame};
use serde::Deserialize;
use synth::tour::{Tour, TourSpec};
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
    /// Render this many frames once, each when first asked for, and play them forwards
    /// and backwards in turn (0, 1, …, repeat−1, repeat−2, …, 1, 0, 1, …), so a frame costs
    /// a copy, as a camera's would, not a render (the renderer took a fifth of the default
    /// graph's CPU), and no cell ever jumps between two frames (a loop played from its
    /// start again moved every cell back by up to 29 drift steps at once, which a tracker
    /// or the bridge following its target cannot tell from another cell). Every frame is
    /// rendered without it, and while the pipette follows a manipulator.
    #[serde(default)]
    pub repeat: Option<usize>,
    /// How the cells move: `"drift"` (each its own steady drift, the pipette advancing) or
    /// `"tour"` ([`synth::tour`]: drift, crossing rows, a close pass, a cell leaving the view
    /// and coming back, one covered by the pipette for 10 frames, a 100 µm stage move;
    /// `frames` long, then played backwards), what a tracker is measured on.
    #[serde(default)]
    pub motion: Motion,
    /// The tour's length, frames (at least 300).
    #[serde(default = "default_tour_frames")]
    pub tour_frames: usize,
    /// The microscope's look: `"default"` (textured cells on a faintly textured substrate)
    /// or `"brightfield"` (textureless substrate, gradient, vignetting, dark membrane rims).
    #[serde(default)]
    pub look: LookName,
}

/// How a synthetic scene's cells move.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Motion {
    /// Each cell drifts at its own steady velocity.
    #[default]
    Drift,
    /// The choreographed tour of [`synth::tour::Tour`].
    Tour,
}

/// A synthetic microscope's look.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LookName {
    /// [`Look::default`].
    #[default]
    Default,
    /// [`Look::brightfield`].
    Brightfield,
}

fn default_tour_frames() -> usize {
    600
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
        crate::check_fps(p.fps)?;
        if let Some(n) = p.repeat {
            // Two bytes a pixel per frame are kept: at most 2 GiB in all.
            let bytes = (n as u128) * (p.width * p.height * 2) as u128;
            if n == 0 || bytes > 2 << 30 {
                return Err(format!(
                    "repeat = {n} would keep {} MiB of frames at {}×{}: give 1 or more frames, at most 2 GiB of them (omit repeat to render every frame)",
                    bytes >> 20,
                    p.width,
                    p.height
                ));
            }
        }
        Ok(p)
    }
}

/// Renders the frames of one synthetic scene.
#[derive(Debug)]
pub struct SyntheticCapture {
    scene: Scene,
    /// With `motion = "tour"`, the choreography.
    tour: Option<Tour>,
    drift: f64,
    step: f64,
    /// The pipette where the manipulator last said it was.
    manipulated: Option<Pipette>,
    /// The scene's bare substrate, rendered once: a frame renders only what its cells and
    /// pipette touch (53 against 244 ms at 1280×1024 with 10 cells), to the same bytes.
    backdrop: Option<Backdrop>,
    /// The sensor noise, drawn once (a frame's own would cost more than its rendering).
    noise: Option<NoiseTable>,
    /// With `repeat`, the loop's frames rendered so far.
    played: Vec<Option<StereoFrame>>,
    /// With `fps`, the time of frame 0, ns since the epoch: frame `k` shows the scene at
    /// `k / fps` after it.
    epoch_ns: Option<u64>,
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
        let look = match p.look {
            LookName::Default => Look::default(),
            LookName::Brightfield => Look::brightfield(),
        };
        let tour = (p.motion == Motion::Tour).then(|| {
            let spec = TourSpec {
                cells: p.cells,
                frames: p.tour_frames,
                ..TourSpec::default()
            };
            Tour::new(optics, look.clone(), &spec, p.seed)
        });
        let mut scene = match &tour {
            Some(t) => t.at(0),
            None => Scene::random(optics, look, &spec, p.seed),
        };
        if tour.is_none()
            && let Some(why) = synth::shortfall(&scene, &spec)
        {
            runtime::errln!("warning: {why}");
        }
        let s = optics.um_per_px();
        if tour.is_some() {
            scene.pipette = None;
        } else {
            scene.pipette = p.pipette.map(|h| Pipette {
                tip: [-0.5 * p.width as f64 * s + 20.0 * s, 0.0],
                height: h,
                tip_radius: 1.5,
                taper: 0.08,
                elevation: 0.0,
                azimuth: 0.0,
            });
        }
        Self {
            scene,
            tour,
            drift: p.drift,
            step: 4.0 * s,
            manipulated: None,
            backdrop: None,
            noise: None,
            played: vec![None; p.repeat.unwrap_or(0)],
            epoch_ns: None,
        }
    }

    /// The tour the cells follow, with `motion = "tour"`: each frame's truth.
    pub fn tour(&self) -> Option<&Tour> {
        self.tour.as_ref()
    }

    /// The calibration that triangulates the frames.
    pub fn calibration(&self) -> schemas::Calibration {
        self.scene.optics.calibration()
    }
}

/// Which of a loop's `n` frames plays as frame `seq`: forwards, then backwards, so that
/// consecutive frames are always neighbours in the loop.
pub fn loop_index(seq: u64, n: u64) -> u64 {
    if n <= 1 {
        return 0;
    }
    let period = 2 * (n - 1);
    let m = seq % period;
    if m < n { m } else { period - m }
}

/// The longest [`SyntheticCapture::render_loop`] renders ahead (the graph's readers wait
/// 30 s for a writer to appear: `runtime::transport::WRITER_WAIT`).
pub const LOOP_RENDER_BUDGET: std::time::Duration = std::time::Duration::from_secs(10);

/// The pipette a manipulator state describes in a scene whose substrate lies at depth `z0`
/// (the state's positions are in the camera frame, its third coordinate the depth, µm).
pub fn pipette_at(m: &ManipulatorState, z0: f64) -> Pipette {
    Pipette::from_tip(m.tip, m.elevation_deg, m.azimuth_deg, z0)
}

impl SyntheticCapture {
    /// The capture time of frame `seq`: paced at `fps`, the time its scene shows (frame 0's
    /// time, the first frame's wall-clock time less its frames, plus `seq / fps`), so that
    /// what a frame shows and when agree even where the renderer is slower than the camera
    /// (a pipette's frame takes ten times a plain one's: stamped when made, a tracker saw
    /// a cell covered for 10 frames stay covered 3 s and its track end); then the stamps
    /// fall behind the wall clock, and the graph's latencies show by how much. Unpaced,
    /// the wall clock.
    pub fn stamp(&mut self, seq: u64, fps: Option<f64>) -> u64 {
        let now = runtime::process::now_ns();
        let Some(fps) = fps else { return now };
        let after = |k: u64| (k as f64 / fps * 1e9) as u64;
        let epoch = *self
            .epoch_ns
            .get_or_insert_with(|| now.saturating_sub(after(seq)));
        epoch.saturating_add(after(seq))
    }

    /// Draws the pipette where the manipulator says its tip is from now on.
    pub fn set_tip(&mut self, m: &ManipulatorState) {
        self.manipulated = Some(pipette_at(m, self.scene.optics.working_distance()));
    }

    /// Renders the frames of the loop (with `repeat`) that are not rendered yet, so that
    /// none is rendered while the camera runs: at 30 frames/s the loop's 30 renders at
    /// 1280×1024 (about 50 ms of a core each) otherwise took the graph's CPU during its
    /// first seconds, and a short run let few frames in. For [`LOOP_RENDER_BUDGET`] at
    /// most, since the graph's readers wait only so long for the camera to appear; the
    /// rest are rendered when first asked for.
    pub fn render_loop(&mut self) {
        let start = std::time::Instant::now();
        let n = self.played.len();
        let mut told = None::<std::time::Instant>;
        for k in 0..n {
            // A stop (the graph ends while the camera starts) cuts it short too.
            if start.elapsed() > LOOP_RENDER_BUDGET || runtime::signals::stop_requested() {
                break;
            }
            // Said while it takes long, so that `top` shows what the camera does.
            if told.is_none_or(|t| t.elapsed() > std::time::Duration::from_millis(250)) {
                runtime::process::report_phase(&format!(
                    "rendering its loop ahead: {k} of {n} frames"
                ));
                told = Some(std::time::Instant::now());
            }
            if self.played[k].is_none() {
                self.played[k] = Some(self.render(k as u64));
            }
        }
    }

    /// Frame `seq`: rendered, or with `repeat` (and no manipulator) taken from the loop.
    pub fn frame(&mut self, seq: u64) -> StereoFrame {
        let n = self.played.len() as u64;
        if n == 0 || self.manipulated.is_some() {
            return self.render(seq);
        }
        let k = loop_index(seq, n) as usize;
        if self.played[k].is_none() {
            self.played[k] = Some(self.render(k as u64));
        }
        self.played[k].clone().expect("rendered above")
    }

    /// Renders frame `seq`.
    fn render(&mut self, seq: u64) -> StereoFrame {
        let mut scene = match &self.tour {
            Some(t) => t.at(seq),
            None => self.scene.at_frame(seq as usize, self.drift, self.step),
        };
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

#[cfg(test)]
mod tests {
    use super::*;

    fn params(repeat: Option<usize>) -> SyntheticParams {
        let mut t = toml::Table::new();
        t.insert("width".into(), toml::Value::Integer(64));
        t.insert("height".into(), toml::Value::Integer(48));
        t.insert("cells".into(), toml::Value::Integer(2));
        if let Some(n) = repeat {
            t.insert("repeat".into(), toml::Value::Integer(n as i64));
        }
        SyntheticParams::from_table(&t).expect("valid params")
    }

    #[test]
    fn a_repeated_sequence_is_the_rendered_one_in_a_loop() {
        let mut live = SyntheticCapture::new(&params(None));
        let mut looped = SyntheticCapture::new(&params(Some(3)));
        let first: Vec<StereoFrame> = (0..3).map(|k| live.frame(k)).collect();
        assert_ne!(first[0], first[1], "the cells drift and the noise changes");
        // Forwards and back: 0 1 2 1 0 1 2 1 …, asked out of order, as after a restart
        // that goes on from a later frame.
        let played = [0, 1, 2, 1, 0, 1, 2, 1, 0];
        for seq in [4, 0, 1, 2, 3, 5, 7, 6, 8] {
            assert_eq!(
                looped.frame(seq),
                first[played[seq as usize]],
                "frame {seq}"
            );
        }
        assert_eq!(
            (0..9).map(|s| loop_index(s, 3)).collect::<Vec<_>>(),
            played.map(|k| k as u64)
        );
        assert_eq!(loop_index(7, 1), 0);
        // Consecutive frames are neighbours in the loop, so no cell ever jumps.
        for n in 2..40 {
            for s in 0..200 {
                assert_eq!(
                    loop_index(s, n).abs_diff(loop_index(s + 1, n)),
                    1,
                    "n {n} s {s}"
                );
            }
        }
        assert_ne!(live.frame(3), first[0], "without repeat every frame is new");
        // Rendered up front, the loop holds the same frames, and none is left to render.
        let mut ahead = SyntheticCapture::new(&params(Some(3)));
        ahead.render_loop();
        assert!(ahead.played.iter().all(Option::is_some));
        for seq in [5, 0, 1] {
            assert_eq!(ahead.frame(seq), first[played[seq as usize]], "frame {seq}");
        }
        // Without repeat there is no loop to render.
        let mut plain = SyntheticCapture::new(&params(None));
        plain.render_loop();
        assert!(plain.played.is_empty());
    }

    #[test]
    fn a_manipulated_pipette_is_drawn_live_even_with_repeat() {
        let mut looped = SyntheticCapture::new(&params(Some(2)));
        let mut live = SyntheticCapture::new(&params(None));
        let plain = live.frame(2);
        looped.frame(0);
        let state = ManipulatorState {
            frame: 0,
            capture_ns: 0,
            device: "sim".into(),
            status: "idle".into(),
            // 20 µm above the substrate (at the working distance's depth), in the middle.
            tip: [0.0, 0.0, looped.scene.optics.working_distance() - 20.0],
            elevation_deg: 20.0,
            azimuth_deg: 180.0,
            clearance: 10.0,
            trajectory: Vec::new(),
            plan: None,
            ignored: Vec::new(),
        };
        looped.set_tip(&state);
        live.set_tip(&state);
        let drawn = looped.frame(2);
        assert_ne!(drawn, plain, "the pipette is in this frame");
        assert_eq!(
            drawn,
            live.frame(2),
            "rendered live, not the loop's frame 0"
        );
    }

    #[test]
    fn repeat_must_be_a_loop_that_fits_memory() {
        for (n, ok) in [(0, false), (1, true), (100_000_000, false)] {
            let mut t = toml::Table::new();
            t.insert("repeat".into(), toml::Value::Integer(n));
            let r = SyntheticParams::from_table(&t);
            assert_eq!(r.is_ok(), ok, "repeat = {n}: {r:?}");
        }
    }
}
