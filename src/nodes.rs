//! Graph nodes whose work spans several node libraries: `triangulate` (point cloud and
//! per-cell 3D targets, with the cells code `reconstruct --cells` uses). The
//! `manipulator-bridge` node lives in its own crate.

use crate::cells::{cell_heights, measure, pair_cells};
use runtime::step::{GraphNode, Msg, Outputs, params, send_json};
use schemas::wire::{CLOUD_POINT_BYTES, CellLists, Targets, cloud_header};
use schemas::{Calibration, DisparityRange, FrameHeader, MessageKind, Plane};
use serde::Deserialize;
use std::path::PathBuf;

/// `params` of a triangulate node.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TriangulateParams {
    /// A calibration file (as `reconstruct --calibration` reads), or `synthetic` for the
    /// synthetic capture's optics.
    #[serde(default = "synthetic")]
    pub calibration: String,
    /// Disparities the match nodes search (cells are paired within it).
    pub min_disparity: i32,
    /// Largest disparity searched.
    pub max_disparity: i32,
    /// Pixels around each cell that count as its substrate ring.
    #[serde(default = "default_margin")]
    pub margin: u8,
}

fn synthetic() -> String {
    "synthetic".into()
}

fn default_margin() -> u8 {
    8
}

impl TriangulateParams {
    /// Reads and checks a `params` table.
    pub fn from_table(t: &toml::Table) -> Result<Self, String> {
        let p: Self = params(t)?;
        if p.min_disparity >= p.max_disparity {
            return Err(format!(
                "min_disparity {} must be below max_disparity {}",
                p.min_disparity, p.max_disparity
            ));
        }
        if p.calibration != "synthetic" && !PathBuf::from(&p.calibration).is_file() {
            return Err(format!(
                "calibration '{}' is not a file; give a calibration file or \"synthetic\"",
                p.calibration
            ));
        }
        Ok(p)
    }
}

/// Triangulates each frame's final map and measures its cells.
#[derive(Debug)]
pub struct TriangulateNode {
    params: TriangulateParams,
    calibration: Option<Calibration>,
}

impl TriangulateNode {
    /// A node with checked parameters.
    pub fn new(params: TriangulateParams) -> Self {
        Self {
            params,
            calibration: None,
        }
    }

    /// The calibration for frames of `w × h` (read once; a file's missing principal point
    /// defaults to the image centre).
    fn calibration(&mut self, w: usize, h: usize) -> Result<Calibration, String> {
        if let Some(c) = self.calibration {
            return Ok(c);
        }
        let c = if self.params.calibration == "synthetic" {
            synth::Optics {
                width: w,
                height: h,
                ..synth::Optics::default()
            }
            .calibration()
        } else {
            crate::cli::load_calibration(&PathBuf::from(&self.params.calibration), w, h)
                .map_err(|e| e.to_string())?
        };
        self.calibration = Some(c);
        Ok(c)
    }
}

impl GraphNode for TriangulateNode {
    fn step(&mut self, inputs: &[Msg<'_>], out: &mut dyn Outputs) -> Result<(), String> {
        let [frame, labels, cells, disparity, raw] = inputs else {
            return Err(format!("triangulate takes 5 inputs, not {}", inputs.len()));
        };
        let [left, right] = &frame.planes_n::<u8, 2>()?;
        let [ll, rl] = &labels.planes_n::<u32, 2>()?;
        let lists: CellLists =
            serde_json::from_slice(cells.payload).map_err(|e| format!("cell list: {e}"))?;
        let ([disp], [raw]) = (disparity.planes_n::<f32, 1>()?, raw.planes_n::<f32, 1>()?);
        let calib = self.calibration(left.width, left.height)?;
        let range = DisparityRange::new(self.params.min_disparity, self.params.max_disparity);
        let pairs = pair_cells(&lists.left, &lists.right, range, 4.0);
        let mask = |l: &Plane<u32>| {
            Plane::from_vec(
                l.width,
                l.height,
                l.data
                    .iter()
                    .map(|&v| if v > 0 { 255 } else { 0 })
                    .collect(),
            )
            .expect("size")
        };
        let mut times = runtime::StageTimes::default();
        let (_, bases, tops) = cell_heights(
            (left, right),
            (ll, &mask(ll), &mask(rl)),
            &lists.left,
            &pairs,
            (&disp, &raw),
            range,
            self.params.margin,
            &mut times,
        );
        let measured = measure(
            (ll, &lists.left, &lists.right),
            &pairs,
            (&disp, &raw),
            (&bases, &tops),
            &calib,
        );
        // The cloud: xyz as f32 for every valid pixel, then its grey level as RGB.
        let rgb = Plane::from_vec(
            left.width,
            left.height,
            left.data.iter().map(|&g| [g, g, g]).collect(),
        )
        .expect("size");
        let cloud = triangulate::triangulate(&disp, &calib, &rgb);
        let n = cloud.points.len();
        let h = FrameHeader {
            sequence: frame.header.sequence,
            capture_ns: frame.header.capture_ns,
            ..cloud_header(n)
        };
        out.send(0, h, n * CLOUD_POINT_BYTES, &mut |b| {
            for (k, p) in cloud.points.iter().enumerate() {
                let o = &mut b[k * CLOUD_POINT_BYTES..(k + 1) * CLOUD_POINT_BYTES];
                o[0..4].copy_from_slice(&(p.x as f32).to_le_bytes());
                o[4..8].copy_from_slice(&(p.y as f32).to_le_bytes());
                o[8..12].copy_from_slice(&(p.z as f32).to_le_bytes());
                o[12..15].copy_from_slice(&p.rgb);
            }
        })?;
        let scene = serde_json::to_vec(&Targets {
            frame: frame.header.sequence,
            capture_ns: frame.header.capture_ns,
            unit: calib.unit.symbol().into(),
            cells: measured,
        })
        .map_err(|e| e.to_string())?;
        send_json(out, 1, MessageKind::Targets, frame.stamp(), &scene)
    }
}
