//! The rectify node: a stereo frame in, the rectified frame out (the same frame when no
//! calibration is given: the input is already rectified).

use crate::{Rectification, RemapLut, StereoCalibration};
use runtime::step::{GraphNode, Msg, Outputs, params, send_planes};
use schemas::MessageKind;
use serde::Deserialize;

/// `params` of a rectify node.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RectifyParams {
    /// OpenCV YAML with K1, D1, K2, D2, R, T (none: pass frames through).
    #[serde(default)]
    pub calibration: Option<String>,
    /// Or two ROS camera_info YAML files, left and right, that hold the rectification.
    #[serde(default)]
    pub camera_info: Option<[String; 2]>,
}

/// Rectifies each frame with tables built once.
#[derive(Debug)]
pub struct RectifyNode {
    luts: Option<(RemapLut, RemapLut, (usize, usize))>,
}

impl RectifyNode {
    /// Reads the calibration (if any) and builds both tables.
    pub fn from_table(t: &toml::Table) -> Result<Self, String> {
        let luts = rectification(t)?.map(|rect| {
            let (w, h) = rect.size();
            (
                RemapLut::new(&rect, false, w, h),
                RemapLut::new(&rect, true, w, h),
                (w, h),
            )
        });
        Ok(Self { luts })
    }
}

/// The rectification a rectify node's `params` describe (`None`: pass frames through).
/// Reading and checking it is cheap; the resampling tables are built only by the node.
pub fn rectification(t: &toml::Table) -> Result<Option<Rectification>, String> {
    let p: RectifyParams = params(t)?;
    let read = |path: &str| {
        std::fs::read_to_string(path).map_err(|e| format!("cannot read calibration '{path}': {e}"))
    };
    match (&p.calibration, &p.camera_info) {
        (None, None) => Ok(None),
        (Some(path), None) => {
            let cal = StereoCalibration::from_opencv_yaml(&read(path)?)
                .map_err(|e| format!("calibration '{path}': {e}"))?;
            Ok(Some(Rectification::bouguet(&cal)))
        }
        (None, Some([l, r])) => Rectification::from_camera_info(&read(l)?, &read(r)?).map(Some),
        (Some(_), Some(_)) => Err("give calibration or camera_info, not both".into()),
    }
}

impl GraphNode for RectifyNode {
    fn step(&mut self, inputs: &[Msg<'_>], out: &mut dyn Outputs) -> Result<(), String> {
        let m = &inputs[0];
        let Some((ll, rl, size)) = &self.luts else {
            return out.send(0, m.header, m.payload.len(), &mut |b| {
                b.copy_from_slice(m.payload)
            });
        };
        let [l, r] = m.planes_n::<u8, 2>()?;
        if (l.width, l.height) != *size {
            return Err(format!(
                "frames are {}×{} but the calibration is for {}×{}",
                l.width, l.height, size.0, size.1
            ));
        }
        let (lo, ro) = (ll.apply(&l), rl.apply(&r));
        send_planes(out, 0, MessageKind::StereoFrame, m.stamp(), &[&lo, &ro])
    }
}
