//! Where the graph's stereo frames come from: two source kinds.
//!
//! `capture` (the live graph's source), by its `source` parameter:
//! - `"synthetic"` ([`synthetic`]): the synthetic stereo microscope, cells drifting and an
//!   optional pipette advancing from frame to frame (the embedded default); its `tip`
//!   feedback input draws the pipette where the manipulator says;
//! - `"files"` ([`files`]): rectified image pairs on disk, named by two glob patterns (`*`
//!   and `?` in the file name), paired in sorted order, optionally looped;
//! - `"v4l"` (`camera`, cargo feature `v4l`): two V4L2 cameras, paired by driver timestamp.
//!
//! `image-pair` ([`ImagePair`]): one stereo pair from two image files, sent `frames` times,
//! with the left view in colour for the points (what `reconstruct` runs on).

#[cfg(feature = "v4l")]
pub mod camera;
pub mod files;
pub mod image;
pub mod synthetic;

use node_api::{NoPorts, NodeError, Params, Source};
use runtime::process::now_ns;
use schemas::{Image, ManipulatorState, StereoFrame};
use serde::Deserialize;
use std::path::PathBuf;

/// `params` of a capture node: those of its `source`.
#[derive(Clone, Debug)]
pub enum CaptureParams {
    /// `source = "synthetic"` (the default).
    Synthetic(synthetic::SyntheticParams),
    /// `source = "files"`.
    Files(files::FileParams),
    /// `source = "v4l"`.
    #[cfg(feature = "v4l")]
    V4l(camera::CameraParams),
}

impl<'de> Deserialize<'de> for CaptureParams {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let t = toml::Table::deserialize(d)?;
        let source = t
            .get("source")
            .map(|v| v.as_str().unwrap_or("?"))
            .unwrap_or("synthetic");
        let p = match source {
            "synthetic" => synthetic::SyntheticParams::from_table(&t).map(Self::Synthetic),
            "files" => files::FileParams::from_table(&t).map(Self::Files),
            #[cfg(feature = "v4l")]
            "v4l" => camera::CameraParams::from_table(&t).map(Self::V4l),
            #[cfg(not(feature = "v4l"))]
            "v4l" => Err("this build has no camera support; build with --features v4l".into()),
            other => Err(format!(
                "source '{other}' is not available; use \"synthetic\", \"files\" or \"v4l\""
            )),
        };
        p.map_err(serde::de::Error::custom)
    }
}

impl Params for CaptureParams {
    fn check(&self) -> Result<(), String> {
        match self {
            // Listing the files is cheap and finds a wrong pattern before the graph starts;
            // a camera is opened only by the node (every process of a graph would find it
            // busy otherwise).
            Self::Files(p) => {
                check_fps(p.fps)?;
                files::FileCapture::new(p.clone()).map(|_| ())
            }
            Self::Synthetic(p) => {
                check_fps(p.fps)?;
                if p.cells > 10_000 {
                    return Err(format!("cells {} is out of range: use 0..=10000", p.cells));
                }
                if p.motion == synthetic::Motion::Tour
                    && (!(6..=40).contains(&p.cells) || !(300..=100_000).contains(&p.tour_frames))
                {
                    return Err(format!(
                        "motion = \"tour\" takes 6..=40 cells and tour_frames 300..=100000 (got cells = {}, tour_frames = {})",
                        p.cells, p.tour_frames
                    ));
                }
                if !(0.0..=100.0).contains(&p.drift) {
                    return Err(format!(
                        "drift {} is out of range: use 0..=100 µm per frame",
                        p.drift
                    ));
                }
                if let Some(h) = p.pipette
                    && !(0.0..=10_000.0).contains(&h)
                {
                    return Err(format!("pipette {h} is out of range: use 0..=10000 µm"));
                }
                Ok(())
            }
            #[cfg(feature = "v4l")]
            Self::V4l(p) => {
                check_fps(p.fps)?;
                if !(p.max_skew_ms > 0.0 && p.max_skew_ms <= 1000.0) {
                    return Err(format!(
                        "max_skew_ms {} is out of range: use above 0, at most 1000 ms",
                        p.max_skew_ms
                    ));
                }
                Ok(())
            }
        }
    }
}

/// The slowest camera rate a capture takes: a frame every 1000 s.
pub const MIN_FPS: f64 = 1e-3;
/// The fastest camera rate a capture takes.
pub const MAX_FPS: f64 = 10_000.0;

/// Checks a frame rate: within [`MIN_FPS`]..=[`MAX_FPS`] (leave it out to run unpaced).
pub fn check_fps(fps: Option<f64>) -> Result<(), String> {
    match fps {
        Some(f) if !(MIN_FPS..=MAX_FPS).contains(&f) => Err(format!(
            "fps {f} is out of range: use {MIN_FPS} to {MAX_FPS} frames per second, or leave fps out to run as fast as the graph takes frames"
        )),
        _ => Ok(()),
    }
}

impl CaptureParams {
    /// The frame size these settings give, where they say it.
    pub fn frame_size(&self) -> Option<(usize, usize)> {
        match self {
            Self::Synthetic(p) => Some((p.width, p.height)),
            #[cfg(feature = "v4l")]
            Self::V4l(p) => Some((p.width as usize, p.height as usize)),
            Self::Files(_) => None,
        }
    }

    fn fps(&self) -> Option<f64> {
        match self {
            Self::Synthetic(p) => p.fps,
            Self::Files(p) => p.fps,
            #[cfg(feature = "v4l")]
            Self::V4l(p) => p.fps,
        }
    }
}

node_api::ports! {
    /// What a capture node sends.
    pub struct CaptureOut {
        /// The stereo pair.
        pub frame: StereoFrame,
    }
}

node_api::ports! {
    /// What a capture node takes when it comes.
    pub struct CaptureFeedback {
        /// The manipulator's state: a synthetic scene draws the pipette there.
        pub tip: Option<ManipulatorState>,
    }
}

enum Device {
    Synthetic(Box<synthetic::SyntheticCapture>),
    Files(files::FileCapture),
    #[cfg(feature = "v4l")]
    V4l(Box<camera::CameraCapture>),
}

/// The capture node.
pub struct Capture {
    device: Device,
    fps: Option<f64>,
}

impl std::fmt::Debug for Capture {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Capture").field("fps", &self.fps).finish()
    }
}

impl Source for Capture {
    const KIND: &'static str = "capture";
    type Params = CaptureParams;
    type Output = CaptureOut;
    type Feedback = CaptureFeedback;
    type Error = NodeError;

    fn new(p: CaptureParams) -> Result<Self, NodeError> {
        let fps = p.fps();
        let device = match p {
            CaptureParams::Synthetic(s) => {
                let mut c = synthetic::SyntheticCapture::new(&s);
                // Before the camera's clock starts, as a camera's start-up would.
                c.render_loop();
                Device::Synthetic(Box::new(c))
            }
            CaptureParams::Files(f) => Device::Files(files::FileCapture::new(f)?),
            #[cfg(feature = "v4l")]
            CaptureParams::V4l(c) => Device::V4l(Box::new(camera::CameraCapture::new(&c)?)),
        };
        Ok(Self { device, fps })
    }

    fn produce(&mut self, seq: u64) -> Result<Option<(u64, CaptureOut)>, NodeError> {
        let frame = match &mut self.device {
            Device::Synthetic(s) => {
                let at = s.stamp(seq, self.fps);
                return Ok(Some((
                    at,
                    CaptureOut {
                        frame: s.frame(seq),
                    },
                )));
            }
            Device::Files(f) => f.frame(seq)?,
            #[cfg(feature = "v4l")]
            Device::V4l(c) => Some(c.next_frame()?),
        };
        Ok(frame.map(|frame| (now_ns(), CaptureOut { frame })))
    }

    fn feedback(&mut self, fb: CaptureFeedback) -> Result<(), NodeError> {
        if let (Device::Synthetic(s), Some(m)) = (&mut self.device, &fb.tip) {
            s.set_tip(m);
        }
        Ok(())
    }

    fn fps(&self) -> Option<f64> {
        self.fps
    }
}

/// `params` of an image-pair node.
#[derive(Clone, Debug, serde::Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImagePairParams {
    /// The left image (PNG, JPEG or TIFF; colour is converted to grey for matching).
    pub left: PathBuf,
    /// The right image.
    pub right: PathBuf,
    /// How many frames to send the pair in (a benchmark repeats it).
    #[serde(default = "one")]
    pub frames: u64,
}

fn one() -> u64 {
    1
}

impl Params for ImagePairParams {
    fn check(&self) -> Result<(), String> {
        if self.frames == 0 {
            return Err("frames must be at least 1".into());
        }
        Ok(())
    }
}

node_api::ports! {
    /// What an image-pair node sends.
    pub struct ImagePairOut {
        /// The grey pair.
        pub frame: StereoFrame,
        /// The left view in colour.
        pub colour: Image,
    }
}

/// One stereo pair from two image files, read once.
#[derive(Debug)]
pub struct ImagePair {
    frame: StereoFrame,
    colour: Image,
    frames: u64,
}

impl Source for ImagePair {
    const KIND: &'static str = "image-pair";
    type Params = ImagePairParams;
    type Output = ImagePairOut;
    type Feedback = NoPorts;
    type Error = String;

    fn new(p: ImagePairParams) -> Result<Self, String> {
        let l = image::load(&p.left, "left image")?;
        let r = image::load(&p.right, "right image")?;
        if (l.grey.width, l.grey.height) != (r.grey.width, r.grey.height) {
            return Err(format!(
                "left image '{}' is {}×{} but right image '{}' is {}×{}; a rectified pair must have the same size",
                p.left.display(),
                l.grey.width,
                l.grey.height,
                p.right.display(),
                r.grey.width,
                r.grey.height
            ));
        }
        Ok(Self {
            frame: StereoFrame {
                left: l.grey,
                right: r.grey,
            },
            colour: Image::Rgb(l.rgb),
            frames: p.frames,
        })
    }

    fn produce(&mut self, seq: u64) -> Result<Option<(u64, ImagePairOut)>, String> {
        if seq >= self.frames {
            return Ok(None);
        }
        Ok(Some((
            now_ns(),
            ImagePairOut {
                frame: self.frame.clone(),
                colour: self.colour.clone(),
            },
        )))
    }
}
