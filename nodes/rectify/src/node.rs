//! The rectify node: a stereo frame in, the rectified frame out (the same frame when no
//! calibration is given: the input is already rectified).

use crate::{RemapLut, luts};
use calibration::stereo::{Rectification, Rectifier, read_rectifier};
use node_api::{NodeError, Params, Stamp, Task};
use schemas::StereoFrame;
use serde::Deserialize;

/// `params` of a rectify node.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RectifyParams {
    /// The calibration file (its `[microscope]` or `[stereo]` table) or OpenCV YAML with
    /// K1, D1, K2, D2, R, T
    /// (none: pass frames through).
    #[serde(default)]
    pub calibration: Option<String>,
    /// Or two ROS camera_info YAML files, left and right, that hold the rectification.
    #[serde(default)]
    pub camera_info: Option<[String; 2]>,
}

impl RectifyParams {
    /// The rectification these parameters describe (`None`: pass frames through). Reading
    /// and checking it is cheap; the resampling tables are built only by the node.
    pub fn rectification(&self) -> Result<Option<Rectifier>, String> {
        let read = |path: &str| {
            std::fs::read_to_string(path)
                .map_err(|e| format!("cannot read calibration '{path}': {e}"))
        };
        match (&self.calibration, &self.camera_info) {
            (None, None) => Ok(None),
            (Some(path), None) => read_rectifier(path).map(Some),
            (None, Some([l, r])) => Rectification::from_camera_info(&read(l)?, &read(r)?)
                .map(|r| Some(Rectifier::Bouguet(r))),
            (Some(_), Some(_)) => Err("give calibration or camera_info, not both".into()),
        }
    }
}

impl Params for RectifyParams {
    fn check(&self) -> Result<(), String> {
        self.rectification().map(|_| ())
    }
}

node_api::ports! {
    /// What the rectify node reads and sends.
    pub struct Frame {
        /// The stereo pair.
        pub frame: StereoFrame,
    }
}

/// Rectifies each frame with tables built once.
#[derive(Debug)]
pub struct Rectify {
    luts: Option<(RemapLut, RemapLut, (usize, usize))>,
}

impl Task for Rectify {
    const KIND: &'static str = "rectify";
    type Params = RectifyParams;
    type Input = Frame;
    type Output = Frame;
    type Error = NodeError;

    fn new(p: RectifyParams) -> Result<Self, NodeError> {
        let luts = p.rectification()?.map(|rect| {
            let (l, r) = luts(&rect);
            (l, r, rect.size())
        });
        Ok(Self { luts })
    }

    fn process(&mut self, _: Stamp, i: Frame) -> Result<Frame, NodeError> {
        let Some((ll, rl, size)) = &self.luts else {
            return Ok(i);
        };
        let StereoFrame { left, right } = &i.frame;
        if (left.width, left.height) != *size {
            return Err(NodeError::Failed(format!(
                "frames are {}×{} but the calibration is for {}×{}",
                left.width, left.height, size.0, size.1
            )));
        }
        Ok(Frame {
            frame: StereoFrame {
                left: ll.apply(left),
                right: rl.apply(right),
            },
        })
    }
}
