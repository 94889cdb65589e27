//! Edge messages as ROS 2 messages in CDR: standard `sensor_msgs` types where they exist,
//! `microstereo_msgs` for cells and targets, each with its full `ros2msg` definition.
//!
//! A message with two images (a stereo frame, a pair of label images or disparity maps)
//! becomes two `sensor_msgs/msg/Image` messages, one per camera, so that every viewer shows
//! them as images. [`encode`] and [`decode`] are exact inverses: the bytes a node sent come
//! back bit for bit.

use crate::scene::{STEREO_FRAME, camera_frame};
use schemas::msg::{Message, cloud_header};
use schemas::wire::CLOUD_POINT_BYTES;
use schemas::{
    BoundingBox, Cell, Cell3, CellLists, CellQuality, DisparityPlane, DisparityRange,
    DisparityTile, DisparityTiles, FrameHeader, ManipulatorState, MessageKind, PathPlan,
    PixelFormat, Plane, Side, Targets, Track, TrackState, Tracks, ValidationFigures,
};
use serde::{Deserialize, Serialize};
use serde_bytes::ByteBuf;

/// A ROS 2 message type: its name and its full `ros2msg` definition (dependencies appended
/// after `=` separator lines, as rosbag2 writes them).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MsgType {
    /// `package/msg/Name`.
    pub name: &'static str,
    /// The definition text.
    pub definition: &'static str,
}

macro_rules! sep {
    () => {
        "================================================================================\n"
    };
}

macro_rules! header_defs {
    () => {
        concat!(
            sep!(),
            "MSG: std_msgs/Header\n",
            "builtin_interfaces/Time stamp\n",
            "string frame_id\n",
            sep!(),
            "MSG: builtin_interfaces/Time\n",
            "int32 sec\n",
            "uint32 nanosec\n"
        )
    };
}

// The definitions' separator and the header's, for the other definitions in this crate.
pub(crate) use {header_defs, sep};

/// `sensor_msgs/msg/Image`: camera frames, disparity (32FC1) and labels (32SC1).
pub const IMAGE: MsgType = MsgType {
    name: "sensor_msgs/msg/Image",
    definition: concat!(
        "std_msgs/Header header\n",
        "uint32 height\n",
        "uint32 width\n",
        "string encoding\n",
        "uint8 is_bigendian\n",
        "uint32 step\n",
        "uint8[] data\n",
        header_defs!()
    ),
};

/// `sensor_msgs/msg/PointCloud2`: the metric point cloud.
pub const POINT_CLOUD2: MsgType = MsgType {
    name: "sensor_msgs/msg/PointCloud2",
    definition: concat!(
        "std_msgs/Header header\n",
        "uint32 height\n",
        "uint32 width\n",
        "PointField[] fields\n",
        "bool is_bigendian\n",
        "uint32 point_step\n",
        "uint32 row_step\n",
        "uint8[] data\n",
        "bool is_dense\n",
        header_defs!(),
        sep!(),
        "MSG: sensor_msgs/PointField\n",
        "uint8 INT8=1\n",
        "uint8 UINT8=2\n",
        "uint8 INT16=3\n",
        "uint8 UINT16=4\n",
        "uint8 INT32=5\n",
        "uint8 UINT32=6\n",
        "uint8 FLOAT32=7\n",
        "uint8 FLOAT64=8\n",
        "string name\n",
        "uint32 offset\n",
        "uint8 datatype\n",
        "uint32 count\n"
    ),
};

/// `sensor_msgs/msg/CameraInfo`: each rectified camera's projection, from the calibration.
pub const CAMERA_INFO: MsgType = MsgType {
    name: "sensor_msgs/msg/CameraInfo",
    definition: concat!(
        "std_msgs/Header header\n",
        "uint32 height\n",
        "uint32 width\n",
        "string distortion_model\n",
        "float64[] d\n",
        "float64[9] k\n",
        "float64[9] r\n",
        "float64[12] p\n",
        "uint32 binning_x\n",
        "uint32 binning_y\n",
        "RegionOfInterest roi\n",
        header_defs!(),
        sep!(),
        "MSG: sensor_msgs/RegionOfInterest\n",
        "uint32 x_offset\n",
        "uint32 y_offset\n",
        "uint32 height\n",
        "uint32 width\n",
        "bool do_rectify\n"
    ),
};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct RegionOfInterest {
    x_offset: u32,
    y_offset: u32,
    height: u32,
    width: u32,
    do_rectify: bool,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct CameraInfo {
    header: Header,
    height: u32,
    width: u32,
    distortion_model: String,
    d: Vec<f64>,
    k: [f64; 9],
    r: [f64; 9],
    p: [f64; 12],
    binning_x: u32,
    binning_y: u32,
    roi: RegionOfInterest,
}

/// The `sensor_msgs/msg/CameraInfo` of one rectified camera (`left` or `right`) of
/// `calib` for `width × height` images, in the ROS convention: no distortion, identity
/// rectification, and the right camera's `P[3] = −f·baseline` with the baseline in metres.
pub fn camera_info(
    calib: &schemas::Calibration,
    (width, height): (usize, usize),
    side: &str,
    capture_ns: u64,
) -> Result<Vec<u8>, String> {
    let f = calib.focal_px;
    let metres = match calib.unit {
        schemas::LengthUnit::Um => 1e-6,
        schemas::LengthUnit::Mm => 1e-3,
        schemas::LengthUnit::M => 1.0,
    };
    let (cx, tx) = if side == "right" {
        (calib.cx_right, -f * calib.baseline * metres)
    } else {
        (calib.cx, 0.0)
    };
    to_cdr(&CameraInfo {
        header: Header::new(capture_ns, camera_frame(side)),
        height: height as u32,
        width: width as u32,
        distortion_model: "plumb_bob".into(),
        d: vec![0.0; 5],
        k: [f, 0.0, cx, 0.0, f, calib.cy, 0.0, 0.0, 1.0],
        r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: [f, 0.0, cx, tx, 0.0, f, calib.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
        binning_x: 0,
        binning_y: 0,
        roi: RegionOfInterest {
            x_offset: 0,
            y_offset: 0,
            height: 0,
            width: 0,
            do_rectify: false,
        },
    })
}

/// The rectified camera a `sensor_msgs/msg/CameraInfo` describes: `(f, cx, cy, Tx)` from
/// its projection (Tx = −f·B, B in metres, on the right camera) and the image size.
pub(crate) fn camera_of(cdr: &[u8]) -> Result<([f64; 4], (usize, usize)), String> {
    let c: CameraInfo = from_cdr(cdr, CAMERA_INFO.name)?;
    Ok((
        [c.p[0], c.p[2], c.p[6], c.p[3]],
        (c.width as usize, c.height as usize),
    ))
}

macro_rules! cell_def {
    () => {
        concat!(
            "uint32 id\n",
            "uint64 area\n",
            "float64[2] centroid\n",
            "uint32 x0\n",
            "uint32 y0\n",
            "uint32 x1\n",
            "uint32 y1\n",
            "uint32[] contour\n",
            "float64 perimeter\n"
        )
    };
}

/// `microstereo_msgs/msg/Cell`: one segmented cell in one image, in pixels; `contour` is
/// `x, y` interleaved.
pub const CELL: MsgType = MsgType {
    name: "microstereo_msgs/msg/Cell",
    definition: cell_def!(),
};

/// `microstereo_msgs/msg/CellArray`: the cells of both views of one frame.
pub const CELL_ARRAY: MsgType = MsgType {
    name: "microstereo_msgs/msg/CellArray",
    definition: concat!(
        "std_msgs/Header header\n",
        "Cell[] left\n",
        "Cell[] right\n",
        header_defs!(),
        sep!(),
        "MSG: microstereo_msgs/Cell\n",
        cell_def!()
    ),
};

macro_rules! cell3_def {
    () => {
        concat!(
            "uint32 id\n",
            "uint32 right_id\n",
            "uint64 area_px\n",
            "float64[2] centroid_px\n",
            "float64 disparity\n",
            "float64[3] centroid\n",
            "float64 substrate_z\n",
            "float64 height\n",
            "float64 volume\n",
            "float64[] contour\n",
            "float64 valid_share\n",
            "string substrate_source\n",
            "float64 substrate_std\n",
            "float64 height_std\n",
            "float64 residual\n",
            "bool trusted\n",
            "string doubt\n"
        )
    };
}

/// `microstereo_msgs/msg/Cell3`: one cell in 3D; `contour` is `x, y, z` interleaved;
/// `height`, `height_std` and `residual` are NaN when there is none, `doubt` empty when
/// the height is trusted; `substrate_source` is plane, rim, rims, ring or none.
pub const CELL3: MsgType = MsgType {
    name: "microstereo_msgs/msg/Cell3",
    definition: cell3_def!(),
};

macro_rules! plane_def {
    () => {
        concat!(
            "float64 d0\n",
            "float64 dx\n",
            "float64 dy\n",
            "float64[2] centre\n",
            "float64 std\n",
            "uint64 pixels\n"
        )
    };
}

/// `microstereo_msgs/msg/Targets`: the 3D cells of one frame, for the manipulator;
/// `has_substrate` false leaves `substrate` zero (no plane could be fitted).
pub const TARGETS: MsgType = MsgType {
    name: "microstereo_msgs/msg/Targets",
    definition: concat!(
        "std_msgs/Header header\n",
        "uint64 frame\n",
        "uint64 capture_ns\n",
        "string unit\n",
        "Cell3[] cells\n",
        "bool has_substrate\n",
        "DisparityPlane substrate\n",
        header_defs!(),
        sep!(),
        "MSG: microstereo_msgs/Cell3\n",
        cell3_def!(),
        sep!(),
        "MSG: microstereo_msgs/DisparityPlane\n",
        plane_def!()
    ),
};

/// `microstereo_msgs/msg/Tracks`: the cells followed over time, once per frame. A track's
/// `state` is tentative, confirmed or lost; `height` and `height_std` are NaN when no
/// frame gave a height; `cell` holds this frame's measurement (empty while lost).
pub const TRACKS: MsgType = MsgType {
    name: "microstereo_msgs/msg/Tracks",
    definition: concat!(
        "std_msgs/Header header\n",
        "uint64 frame\n",
        "uint64 capture_ns\n",
        "string unit\n",
        "float64[3] shift\n",
        "Track[] tracks\n",
        "bool has_substrate\n",
        "DisparityPlane substrate\n",
        header_defs!(),
        sep!(),
        "MSG: microstereo_msgs/Track\n",
        "uint32 id\n",
        "string state\n",
        "uint32 age\n",
        "uint32 missed\n",
        "uint32 frames_used\n",
        "float64[3] position\n",
        "float64 position_std\n",
        "float64[3] velocity\n",
        "float64 height\n",
        "float64 height_std\n",
        "float64 volume\n",
        "float64 volume_std\n",
        "bool trusted\n",
        "Cell3[] cell\n",
        sep!(),
        "MSG: microstereo_msgs/Cell3\n",
        cell3_def!(),
        sep!(),
        "MSG: microstereo_msgs/DisparityPlane\n",
        plane_def!()
    ),
};

macro_rules! figures_def {
    () => {
        concat!(
            "uint64 matched\n",
            "float64 consistent_exact\n",
            "float64 off_by_one\n",
            "float64 off_by_more\n",
            "float64 consistent_within_tolerance\n",
            "uint32 tolerance\n"
        )
    };
}

/// `microstereo_msgs/msg/DisparityTiles`: a frame's disparity maps in tiles (the whole
/// frame, or one crop per cell pair). Each tile's `data` is its map row by row (+inf
/// invalid); `left_cell` = `right_cell` = 0 marks a whole-frame tile; `has_figures` false
/// leaves `figures` zero (not validated yet).
pub const DISPARITY_TILES: MsgType = MsgType {
    name: "microstereo_msgs/msg/DisparityTiles",
    definition: concat!(
        "std_msgs/Header header\n",
        "uint32 width\n",
        "uint32 height\n",
        "string side\n",
        "int32 min_disparity\n",
        "int32 max_disparity\n",
        "uint8 margin\n",
        "DisparityTile[] tiles\n",
        header_defs!(),
        sep!(),
        "MSG: microstereo_msgs/DisparityTile\n",
        "uint32 x\n",
        "uint32 y\n",
        "uint32 width\n",
        "uint32 height\n",
        "int32 min_disparity\n",
        "int32 max_disparity\n",
        "uint32 left_cell\n",
        "uint32 right_cell\n",
        "uint64 evaluations\n",
        "bool has_figures\n",
        "ValidationFigures figures\n",
        "float32[] data\n",
        sep!(),
        "MSG: microstereo_msgs/ValidationFigures\n",
        figures_def!()
    ),
};

/// `microstereo_msgs/msg/ManipulatorState`: the pipette and its plan, once per frame.
/// Positions are the camera frame's `[X, Y, Z]` in µm; `trajectory` is `t, X, Y, Z`
/// interleaved and `plan_waypoints` `X, Y, Z`; `has_plan` false leaves the `plan_` fields empty, and a
/// negative `plan_target` or `plan_min_clearance` means none.
pub const MANIPULATOR_STATE: MsgType = MsgType {
    name: "microstereo_msgs/msg/ManipulatorState",
    definition: concat!(
        "std_msgs/Header header\n",
        "uint64 frame\n",
        "uint64 capture_ns\n",
        "string device\n",
        "string status\n",
        "float64[3] tip\n",
        "float64 elevation_deg\n",
        "float64 azimuth_deg\n",
        "float64 clearance\n",
        "float64[] trajectory\n",
        "bool has_plan\n",
        "string plan_goal\n",
        "int64 plan_target\n",
        "uint64 plan_frame\n",
        "float64[] plan_waypoints\n",
        "uint32 plan_axial_from\n",
        "float64[3] plan_end\n",
        "float64 plan_length\n",
        "float64 plan_min_clearance\n",
        "uint32[] ignored\n",
        header_defs!()
    ),
};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct RosManipulatorState {
    header: Header,
    frame: u64,
    capture_ns: u64,
    device: String,
    status: String,
    tip: [f64; 3],
    elevation_deg: f64,
    azimuth_deg: f64,
    clearance: f64,
    trajectory: Vec<f64>,
    has_plan: bool,
    plan_goal: String,
    plan_target: i64,
    plan_frame: u64,
    plan_waypoints: Vec<f64>,
    plan_axial_from: u32,
    plan_end: [f64; 3],
    plan_length: f64,
    plan_min_clearance: f64,
    ignored: Vec<u32>,
}

impl RosManipulatorState {
    fn new(m: &ManipulatorState, header: Header) -> Self {
        let p = m.plan.as_ref();
        Self {
            header,
            frame: m.frame,
            capture_ns: m.capture_ns,
            device: m.device.clone(),
            status: m.status.clone(),
            tip: m.tip,
            elevation_deg: m.elevation_deg,
            azimuth_deg: m.azimuth_deg,
            clearance: m.clearance,
            trajectory: m.trajectory.iter().flatten().copied().collect(),
            has_plan: p.is_some(),
            plan_goal: p.map(|p| p.goal.clone()).unwrap_or_default(),
            plan_target: p.and_then(|p| p.target).map_or(-1, i64::from),
            plan_frame: p.map_or(0, |p| p.frame),
            plan_waypoints: p
                .map(|p| p.waypoints.iter().flatten().copied().collect())
                .unwrap_or_default(),
            plan_axial_from: p.map_or(0, |p| p.axial_from),
            plan_end: p.map_or([0.0; 3], |p| p.end),
            plan_length: p.map_or(0.0, |p| p.length),
            plan_min_clearance: p.and_then(|p| p.min_clearance).unwrap_or(-1.0),
            ignored: m.ignored.clone(),
        }
    }

    fn into_state(self) -> Result<ManipulatorState, String> {
        if !self.trajectory.len().is_multiple_of(4) || !self.plan_waypoints.len().is_multiple_of(3)
        {
            return Err("manipulator state: trajectory or waypoints not in whole points".into());
        }
        let plan = self.has_plan.then(|| PathPlan {
            goal: self.plan_goal,
            target: u32::try_from(self.plan_target).ok(),
            frame: self.plan_frame,
            waypoints: self
                .plan_waypoints
                .chunks(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect(),
            axial_from: self.plan_axial_from,
            end: self.plan_end,
            length: self.plan_length,
            min_clearance: (self.plan_min_clearance >= 0.0).then_some(self.plan_min_clearance),
        });
        Ok(ManipulatorState {
            frame: self.frame,
            capture_ns: self.capture_ns,
            device: self.device,
            status: self.status,
            tip: self.tip,
            elevation_deg: self.elevation_deg,
            azimuth_deg: self.azimuth_deg,
            clearance: self.clearance,
            trajectory: self
                .trajectory
                .chunks(4)
                .map(|c| [c[0], c[1], c[2], c[3]])
                .collect(),
            plan,
            ignored: self.ignored,
        })
    }
}

/// `builtin_interfaces/Time`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct Time {
    sec: i32,
    nanosec: u32,
}

/// `std_msgs/Header`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct Header {
    stamp: Time,
    pub(crate) frame_id: String,
}

impl Time {
    /// The time `ns` nanoseconds after the epoch.
    pub(crate) fn of(ns: u64) -> Self {
        Self {
            sec: (ns / 1_000_000_000) as i32,
            nanosec: (ns % 1_000_000_000) as u32,
        }
    }
}

impl Header {
    /// A header stamped `capture_ns` (ns since the epoch) in frame `frame_id`.
    pub(crate) fn new(capture_ns: u64, frame_id: &str) -> Self {
        Self {
            stamp: Time {
                sec: (capture_ns / 1_000_000_000) as i32,
                nanosec: (capture_ns % 1_000_000_000) as u32,
            },
            frame_id: frame_id.into(),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct Image {
    header: Header,
    height: u32,
    width: u32,
    encoding: String,
    is_bigendian: u8,
    step: u32,
    data: ByteBuf,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct PointField {
    name: String,
    offset: u32,
    datatype: u8,
    count: u32,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct PointCloud2 {
    header: Header,
    height: u32,
    width: u32,
    fields: Vec<PointField>,
    is_bigendian: bool,
    point_step: u32,
    row_step: u32,
    data: ByteBuf,
    is_dense: bool,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct RosCell {
    id: u32,
    area: u64,
    centroid: [f64; 2],
    x0: u32,
    y0: u32,
    x1: u32,
    y1: u32,
    contour: Vec<u32>,
    perimeter: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct RosCellArray {
    header: Header,
    left: Vec<RosCell>,
    right: Vec<RosCell>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct RosCell3 {
    id: u32,
    right_id: u32,
    area_px: u64,
    centroid_px: [f64; 2],
    disparity: f64,
    centroid: [f64; 3],
    substrate_z: f64,
    height: f64,
    volume: f64,
    contour: Vec<f64>,
    valid_share: f64,
    substrate_source: String,
    substrate_std: f64,
    height_std: f64,
    residual: f64,
    trusted: bool,
    doubt: String,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct RosTargets {
    header: Header,
    frame: u64,
    capture_ns: u64,
    unit: String,
    cells: Vec<RosCell3>,
    has_substrate: bool,
    substrate: RosPlane,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct RosTrack {
    id: u32,
    state: String,
    age: u32,
    missed: u32,
    frames_used: u32,
    position: [f64; 3],
    position_std: f64,
    velocity: [f64; 3],
    height: f64,
    height_std: f64,
    volume: f64,
    volume_std: f64,
    trusted: bool,
    cell: Vec<RosCell3>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct RosTracks {
    header: Header,
    frame: u64,
    capture_ns: u64,
    unit: String,
    shift: [f64; 3],
    tracks: Vec<RosTrack>,
    has_substrate: bool,
    substrate: RosPlane,
}

impl RosPlane {
    fn of(p: Option<DisparityPlane>) -> Self {
        p.map_or_else(Self::default, |p| Self {
            d0: p.d0,
            dx: p.dx,
            dy: p.dy,
            centre: p.centre,
            std: p.std,
            pixels: p.pixels,
        })
    }

    fn plane(&self) -> DisparityPlane {
        DisparityPlane {
            d0: self.d0,
            dx: self.dx,
            dy: self.dy,
            centre: self.centre,
            std: self.std,
            pixels: self.pixels,
        }
    }
}

impl RosTrack {
    fn of(t: &Track) -> Self {
        Self {
            id: t.id,
            state: match t.state {
                TrackState::Tentative => "tentative",
                TrackState::Confirmed => "confirmed",
                TrackState::Lost => "lost",
            }
            .into(),
            age: t.age,
            missed: t.missed,
            frames_used: t.frames_used,
            position: t.position,
            position_std: t.position_std,
            velocity: t.velocity,
            height: t.height.unwrap_or(f64::NAN),
            height_std: t.height_std.unwrap_or(f64::NAN),
            volume: t.volume,
            volume_std: t.volume_std,
            trusted: t.trusted,
            cell: t.cell.iter().map(RosCell3::from).collect(),
        }
    }

    fn into_track(self) -> Result<Track, String> {
        let state = match self.state.as_str() {
            "tentative" => TrackState::Tentative,
            "confirmed" => TrackState::Confirmed,
            "lost" => TrackState::Lost,
            other => {
                return Err(format!(
                    "track {}: state '{other}' is not one of ours",
                    self.id
                ));
            }
        };
        if self.cell.len() > 1 {
            return Err(format!(
                "track {}: {} cells in one frame",
                self.id,
                self.cell.len()
            ));
        }
        Ok(Track {
            id: self.id,
            state,
            age: self.age,
            missed: self.missed,
            frames_used: self.frames_used,
            position: self.position,
            position_std: self.position_std,
            velocity: self.velocity,
            height: (!self.height.is_nan()).then_some(self.height),
            height_std: (!self.height_std.is_nan()).then_some(self.height_std),
            volume: self.volume,
            volume_std: self.volume_std,
            trusted: self.trusted,
            cell: self
                .cell
                .into_iter()
                .next()
                .map(RosCell3::into_cell3)
                .transpose()?,
        })
    }
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
struct RosPlane {
    d0: f64,
    dx: f64,
    dy: f64,
    centre: [f64; 2],
    std: f64,
    pixels: u64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct RosTiles {
    header: Header,
    width: u32,
    height: u32,
    side: String,
    min_disparity: i32,
    max_disparity: i32,
    margin: u8,
    tiles: Vec<RosTile>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct RosTile {
    x: u32,
    y: u32,
    width: u32,
    height: u32,
    min_disparity: i32,
    max_disparity: i32,
    left_cell: u32,
    right_cell: u32,
    evaluations: u64,
    has_figures: bool,
    figures: RosFigures,
    data: Vec<f32>,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
struct RosFigures {
    matched: u64,
    consistent_exact: f64,
    off_by_one: f64,
    off_by_more: f64,
    consistent_within_tolerance: f64,
    tolerance: u32,
}

impl RosTiles {
    fn new(t: &DisparityTiles, header: Header) -> Self {
        Self {
            header,
            width: t.width as u32,
            height: t.height as u32,
            side: match t.side {
                Side::Left => "left".into(),
                Side::Right => "right".into(),
            },
            min_disparity: t.range.min,
            max_disparity: t.range.max,
            margin: t.margin,
            tiles: t
                .tiles
                .iter()
                .map(|k| {
                    let (l, r) = k.cells.unwrap_or((0, 0));
                    let f = k.figures.unwrap_or_default();
                    RosTile {
                        x: k.x as u32,
                        y: k.y as u32,
                        width: k.map.width as u32,
                        height: k.map.height as u32,
                        min_disparity: k.range.min,
                        max_disparity: k.range.max,
                        left_cell: l,
                        right_cell: r,
                        evaluations: k.evaluations,
                        has_figures: k.figures.is_some(),
                        figures: RosFigures {
                            matched: f.matched,
                            consistent_exact: f.consistent_exact,
                            off_by_one: f.off_by_one,
                            off_by_more: f.off_by_more,
                            consistent_within_tolerance: f.consistent_within_tolerance,
                            tolerance: f.tolerance,
                        },
                        data: k.map.data.clone(),
                    }
                })
                .collect(),
        }
    }

    fn into_tiles(self) -> Result<DisparityTiles, String> {
        let side = match self.side.as_str() {
            "left" => Side::Left,
            "right" => Side::Right,
            s => return Err(format!("tiles based on '{s}', neither left nor right")),
        };
        let tiles = self
            .tiles
            .into_iter()
            .map(|k| {
                let f = k.figures;
                Ok(DisparityTile {
                    x: k.x as usize,
                    y: k.y as usize,
                    range: DisparityRange::new(k.min_disparity, k.max_disparity),
                    cells: (k.left_cell != 0 || k.right_cell != 0)
                        .then_some((k.left_cell, k.right_cell)),
                    map: Plane::from_vec(k.width as usize, k.height as usize, k.data)
                        .ok_or("a tile's data does not fit its size")?,
                    evaluations: k.evaluations,
                    figures: k.has_figures.then_some(ValidationFigures {
                        matched: f.matched,
                        consistent_exact: f.consistent_exact,
                        off_by_one: f.off_by_one,
                        off_by_more: f.off_by_more,
                        consistent_within_tolerance: f.consistent_within_tolerance,
                        tolerance: f.tolerance,
                    }),
                })
            })
            .collect::<Result<Vec<_>, String>>()?;
        Ok(DisparityTiles {
            width: self.width as usize,
            height: self.height as usize,
            side,
            range: DisparityRange::new(self.min_disparity, self.max_disparity),
            margin: self.margin,
            tiles,
        })
    }
}

impl From<&Cell> for RosCell {
    fn from(c: &Cell) -> Self {
        Self {
            id: c.id,
            area: c.area,
            centroid: c.centroid,
            x0: c.bbox.x0,
            y0: c.bbox.y0,
            x1: c.bbox.x1,
            y1: c.bbox.y1,
            contour: c.contour.iter().flatten().copied().collect(),
            perimeter: c.perimeter,
        }
    }
}

impl RosCell {
    fn into_cell(self) -> Result<Cell, String> {
        if !self.contour.len().is_multiple_of(2) {
            return Err(format!(
                "cell {}: contour of {} numbers is not x, y pairs",
                self.id,
                self.contour.len()
            ));
        }
        Ok(Cell {
            id: self.id,
            area: self.area,
            centroid: self.centroid,
            bbox: BoundingBox {
                x0: self.x0,
                y0: self.y0,
                x1: self.x1,
                y1: self.y1,
            },
            contour: self.contour.chunks_exact(2).map(|p| [p[0], p[1]]).collect(),
            perimeter: self.perimeter,
        })
    }
}

impl From<&Cell3> for RosCell3 {
    fn from(c: &Cell3) -> Self {
        Self {
            id: c.id,
            right_id: c.right_id,
            area_px: c.area_px,
            centroid_px: c.centroid_px,
            disparity: c.disparity,
            centroid: c.centroid,
            substrate_z: c.substrate_z,
            height: c.height.unwrap_or(f64::NAN),
            volume: c.volume,
            contour: c.contour.iter().flatten().copied().collect(),
            valid_share: c.valid_share,
            substrate_source: serde_json::to_value(c.quality.substrate)
                .ok()
                .and_then(|v| v.as_str().map(String::from))
                .unwrap_or_default(),
            substrate_std: c.quality.substrate_std,
            height_std: c.quality.height_std.unwrap_or(f64::NAN),
            residual: c.quality.residual.unwrap_or(f64::NAN),
            trusted: c.quality.trusted,
            doubt: c.quality.doubt.clone().unwrap_or_default(),
        }
    }
}

/// `None` for the NaN that stands for "none" on the wire.
fn finite(v: f64) -> Option<f64> {
    (!v.is_nan()).then_some(v)
}

impl RosCell3 {
    fn into_cell3(self) -> Result<Cell3, String> {
        if !self.contour.len().is_multiple_of(3) {
            return Err(format!(
                "cell {}: contour of {} numbers is not x, y, z triples",
                self.id,
                self.contour.len()
            ));
        }
        Ok(Cell3 {
            id: self.id,
            right_id: self.right_id,
            area_px: self.area_px,
            centroid_px: self.centroid_px,
            disparity: self.disparity,
            centroid: self.centroid,
            substrate_z: self.substrate_z,
            height: finite(self.height),
            volume: self.volume,
            contour: self
                .contour
                .chunks_exact(3)
                .map(|p| [p[0], p[1], p[2]])
                .collect(),
            valid_share: self.valid_share,
            quality: CellQuality {
                substrate: serde_json::from_value(serde_json::Value::String(
                    self.substrate_source.clone(),
                ))
                .map_err(|_| {
                    format!(
                        "cell {}: unknown substrate source '{}'",
                        self.id, self.substrate_source
                    )
                })?,
                substrate_std: self.substrate_std,
                height_std: finite(self.height_std),
                residual: finite(self.residual),
                trusted: self.trusted,
                doubt: (!self.doubt.is_empty()).then_some(self.doubt),
            },
        })
    }
}

/// One ROS 2 message of an edge message: which camera it belongs to (`None` for a message
/// of one part), its type and its CDR bytes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Part {
    /// `left` or `right` for messages with two images, `None` otherwise.
    pub side: Option<&'static str>,
    /// Its ROS 2 type.
    pub msg: MsgType,
    /// The CDR encoding (with its 4-byte encapsulation header).
    pub cdr: Vec<u8>,
}

/// The sides of a message with `images` images.
fn sides(images: u32) -> &'static [&'static str] {
    if images == 2 { &["left", "right"] } else { &[] }
}

/// The ROS 2 type of the parts of a message of `kind`.
pub fn msg_type(kind: MessageKind) -> MsgType {
    match kind {
        MessageKind::StereoFrame
        | MessageKind::Image
        | MessageKind::Disparity
        | MessageKind::Labels
        | MessageKind::DisparityPair => IMAGE,
        MessageKind::PointCloud => POINT_CLOUD2,
        MessageKind::CellList => CELL_ARRAY,
        MessageKind::Targets => TARGETS,
        MessageKind::ManipulatorState => MANIPULATOR_STATE,
        MessageKind::DisparityTiles => DISPARITY_TILES,
        MessageKind::Tracks => TRACKS,
    }
}

/// The sides a message of `kind` is split into (`[]` for one part).
pub fn kind_sides(kind: MessageKind) -> &'static [&'static str] {
    match kind {
        MessageKind::StereoFrame | MessageKind::Labels | MessageKind::DisparityPair => sides(2),
        _ => sides(1),
    }
}

/// The encoding of label images whose ids fit 16 bits (all but the rarest).
const LABELS16: &str = "16UC1";

fn image_encoding(format: PixelFormat) -> Option<&'static str> {
    Some(match format {
        PixelFormat::Mono8 => "mono8",
        PixelFormat::F32 => "32FC1",
        // Labels beyond 16 bits: ROS has no unsigned 32-bit encoding; ids stay below 2^31.
        PixelFormat::U32 => "32SC1",
        PixelFormat::Rgb8 => "rgb8",
        PixelFormat::None => return None,
    })
}

fn image_format(encoding: &str) -> Option<PixelFormat> {
    [
        PixelFormat::Mono8,
        PixelFormat::F32,
        PixelFormat::U32,
        PixelFormat::Rgb8,
    ]
    .into_iter()
    .find(|f| image_encoding(*f) == Some(encoding))
}

pub(crate) fn to_cdr<T: Serialize>(v: &T) -> Result<Vec<u8>, String> {
    cdr::serialize::<_, _, cdr::CdrLe>(v, cdr::Infinite).map_err(|e| format!("CDR: {e}"))
}

/// Decodes CDR with `cdr-encoding`, whose reader checks every length against the bytes
/// left before taking them (`cdr` allocates whatever a length field claims first: fuzzing
/// found a damaged string length that zero-filled 4 GiB).
pub(crate) fn from_cdr<'de, T: Deserialize<'de>>(b: &'de [u8], what: &str) -> Result<T, String> {
    let err = |e: String| format!("not a CDR {what}: {e}");
    // The encapsulation header: 0x00 0x01 is little-endian CDR, 0x00 0x00 big-endian.
    let body = b
        .get(4..)
        .ok_or_else(|| err("shorter than its header".into()))?;
    match (b[0], b[1]) {
        (0, 1) => cdr_encoding::from_bytes::<T, byteorder::LittleEndian>(body),
        (0, 0) => cdr_encoding::from_bytes::<T, byteorder::BigEndian>(body),
        (x, y) => {
            return Err(err(format!(
                "encapsulation {x:#04x} {y:#04x} is not plain CDR"
            )));
        }
    }
    .map(|(v, _)| v)
    .map_err(|e| err(e.to_string()))
}

/// Encodes one edge message of `kind` as its ROS 2 message(s); a cloud's lengths go into
/// metres with `metres` per unit (`None`: the unit is not known, they stay as sent).
pub fn encode(
    kind: MessageKind,
    h: &FrameHeader,
    payload: &[u8],
    metres: Option<f64>,
) -> Result<Vec<Part>, String> {
    let header = |side: &str| Header::new(h.capture_ns, side);
    let one = |msg, cdr| {
        Ok(vec![Part {
            side: None,
            msg,
            cdr,
        }])
    };
    match msg_type(kind) {
        IMAGE => {
            let format = PixelFormat::from_u32(h.format)
                .and_then(image_encoding)
                .ok_or_else(|| format!("{kind:?} message with pixel format {}", h.format))?;
            let want = kind_sides(kind);
            if h.images as usize != want.len().max(1) {
                return Err(format!("{kind:?} message with {} image(s)", h.images));
            }
            if payload.len() != h.image_bytes() {
                return Err(format!(
                    "{kind:?} message of {} bytes where its header says {}",
                    payload.len(),
                    h.image_bytes()
                ));
            }
            let size = h.stride as usize * h.height as usize;
            let names: &[&'static str] = if want.is_empty() { &[""] } else { want };
            // Labels as 16UC1, which Foxglove and RViz show, whenever they fit.
            let narrow = PixelFormat::from_u32(h.format) == Some(PixelFormat::U32)
                && payload
                    .chunks_exact(4)
                    .all(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) <= u32::from(u16::MAX));
            names
                .iter()
                .zip(payload.chunks(size.max(1)))
                .map(|(side, data)| {
                    let (encoding, step, data) = if narrow {
                        let d: Vec<u8> = data.chunks_exact(4).flat_map(|b| [b[0], b[1]]).collect();
                        (LABELS16, h.stride / 2, d)
                    } else {
                        (format, h.stride, data.to_vec())
                    };
                    let img = Image {
                        header: header(camera_frame(side)),
                        height: h.height,
                        width: h.width,
                        encoding: encoding.into(),
                        is_bigendian: 0,
                        step,
                        data: ByteBuf::from(data),
                    };
                    Ok(Part {
                        side: (!side.is_empty()).then_some(*side),
                        msg: IMAGE,
                        cdr: to_cdr(&img)?,
                    })
                })
                .collect()
        }
        POINT_CLOUD2 => {
            if payload.len() != h.width as usize * CLOUD_POINT_BYTES {
                return Err(format!(
                    "point cloud of {} bytes for {} points",
                    payload.len(),
                    h.width
                ));
            }
            one(POINT_CLOUD2, to_cdr(&ros_cloud(h, payload, metres))?)
        }
        DISPARITY_TILES => {
            let t = DisparityTiles::decode(h, payload).map_err(|e| e.to_string())?;
            let side = match t.side {
                Side::Left => "left",
                Side::Right => "right",
            };
            one(
                DISPARITY_TILES,
                to_cdr(&RosTiles::new(&t, header(camera_frame(side))))?,
            )
        }
        CELL_ARRAY => {
            let lists = CellLists::decode(h, payload).map_err(|e| e.to_string())?;
            let msg = RosCellArray {
                header: header(camera_frame("left")),
                left: lists.left.iter().map(RosCell::from).collect(),
                right: lists.right.iter().map(RosCell::from).collect(),
            };
            one(CELL_ARRAY, to_cdr(&msg)?)
        }
        TRACKS => {
            let t = Tracks::decode(h, payload).map_err(|e| e.to_string())?;
            let msg = RosTracks {
                header: header(STEREO_FRAME),
                frame: t.frame,
                capture_ns: t.capture_ns,
                unit: t.unit.clone(),
                shift: t.shift,
                tracks: t.tracks.iter().map(RosTrack::of).collect(),
                has_substrate: t.substrate.is_some(),
                substrate: RosPlane::of(t.substrate),
            };
            one(TRACKS, to_cdr(&msg)?)
        }
        MANIPULATOR_STATE => {
            let m = ManipulatorState::decode(h, payload).map_err(|e| e.to_string())?;
            one(
                MANIPULATOR_STATE,
                to_cdr(&RosManipulatorState::new(&m, header(STEREO_FRAME)))?,
            )
        }
        _ => {
            let t = Targets::decode(h, payload).map_err(|e| e.to_string())?;
            let p = t.substrate.unwrap_or(DisparityPlane {
                d0: 0.0,
                dx: 0.0,
                dy: 0.0,
                centre: [0.0; 2],
                std: 0.0,
                pixels: 0,
            });
            let msg = RosTargets {
                header: header(STEREO_FRAME),
                frame: t.frame,
                capture_ns: t.capture_ns,
                unit: t.unit,
                cells: t.cells.iter().map(RosCell3::from).collect(),
                has_substrate: t.substrate.is_some(),
                substrate: RosPlane {
                    d0: p.d0,
                    dx: p.dx,
                    dy: p.dy,
                    centre: p.centre,
                    std: p.std,
                    pixels: p.pixels,
                },
            };
            one(TARGETS, to_cdr(&msg)?)
        }
    }
}

/// Bytes of a cloud point in ROS: `x, y, z` (float32, metres), `rgb` (packed as PCL,
/// RViz and Foxglove read it) and `x_native, y_native, z_native` (float32, the values the
/// node sent, in its unit), so that a replay gives the node's bytes back.
const ROS_POINT_BYTES: usize = 28;

/// The `PointCloud2` of a cloud message (`metres` per unit of its lengths, if known).
fn ros_cloud(h: &FrameHeader, payload: &[u8], metres: Option<f64>) -> PointCloud2 {
    let field = |name: &str, offset, datatype| PointField {
        name: name.into(),
        offset,
        datatype,
        count: 1,
    };
    let m = metres.unwrap_or(1.0);
    let data = payload
        .chunks_exact(CLOUD_POINT_BYTES)
        .flat_map(|p| {
            let mut o = [0u8; ROS_POINT_BYTES];
            for k in 0..3 {
                let v = f32::from_le_bytes(p[4 * k..4 * k + 4].try_into().expect("4 bytes"));
                o[4 * k..4 * k + 4].copy_from_slice(&((v as f64 * m) as f32).to_le_bytes());
            }
            o[12..16].copy_from_slice(&[p[14], p[13], p[12], 0]);
            o[16..28].copy_from_slice(&p[..12]);
            o
        })
        .collect::<Vec<u8>>();
    PointCloud2 {
        header: Header::new(h.capture_ns, STEREO_FRAME),
        height: 1,
        width: h.width,
        fields: vec![
            field("x", 0, 7),
            field("y", 4, 7),
            field("z", 8, 7),
            field("rgb", 12, 7),
            field("x_native", 16, 7),
            field("y_native", 20, 7),
            field("z_native", 24, 7),
        ],
        is_bigendian: false,
        point_step: ROS_POINT_BYTES as u32,
        row_step: data.len() as u32,
        data: ByteBuf::from(data),
        is_dense: true,
    }
}

/// Decodes the ROS 2 message(s) of one edge message of `kind` (in [`kind_sides`] order)
/// back into the header and payload the node sent, stamped `(sequence, capture_ns)`.
pub fn decode(
    kind: MessageKind,
    parts: &[&[u8]],
    (sequence, capture_ns): (u64, u64),
) -> Result<(FrameHeader, Vec<u8>), String> {
    let stamp = |h: FrameHeader| FrameHeader {
        sequence,
        capture_ns,
        ..h
    };
    let want = kind_sides(kind).len().max(1);
    if parts.len() != want {
        return Err(format!(
            "{kind:?} message in {} part(s), not {want}",
            parts.len()
        ));
    }
    match msg_type(kind) {
        IMAGE => {
            let imgs = parts
                .iter()
                .map(|p| from_cdr::<Image>(p, IMAGE.name))
                .collect::<Result<Vec<_>, _>>()?;
            let first = &imgs[0];
            let narrow = first.encoding == LABELS16;
            let format = if narrow {
                PixelFormat::U32
            } else {
                image_format(&first.encoding).ok_or_else(|| {
                    format!("image encoding '{}' is not one of ours", first.encoding)
                })?
            };
            let h = FrameHeader::image(
                kind,
                format,
                first.width as usize,
                first.height as usize,
                imgs.len() as u32,
            );
            // Sized by the data read, not by the header's claim (checked below).
            let mut payload = Vec::with_capacity(imgs.iter().map(|i| i.data.len()).sum());
            let step = if narrow { h.stride / 2 } else { h.stride };
            for i in &imgs {
                if (i.width, i.height, i.step, &i.encoding)
                    != (first.width, first.height, step, &first.encoding)
                    || i.data.len() != step as usize * h.height as usize
                {
                    return Err(format!(
                        "image of {}×{} ({}, step {}, {} bytes) does not fit a {}×{} {} image",
                        i.width,
                        i.height,
                        i.encoding,
                        i.step,
                        i.data.len(),
                        first.width,
                        first.height,
                        first.encoding
                    ));
                }
                if narrow {
                    payload.extend(i.data.chunks_exact(2).flat_map(|b| [b[0], b[1], 0, 0]));
                } else {
                    payload.extend_from_slice(&i.data);
                }
            }
            Ok((stamp(h), payload))
        }
        POINT_CLOUD2 => {
            let c: PointCloud2 = from_cdr(parts[0], POINT_CLOUD2.name)?;
            let n = c.width as usize * c.height as usize;
            let (step, data) = (c.point_step as usize, c.data.as_slice());
            let payload = match step {
                // Ours until December 2026: the points as sent, colours as r, g, b bytes.
                CLOUD_POINT_BYTES => data.to_vec(),
                ROS_POINT_BYTES => data
                    .chunks_exact(ROS_POINT_BYTES)
                    .flat_map(|p| {
                        let mut o = [0u8; CLOUD_POINT_BYTES];
                        o[..12].copy_from_slice(&p[16..28]);
                        // Packed 0x00RRGGBB, little-endian: b, g, r.
                        o[12..].copy_from_slice(&[p[14], p[13], p[12]]);
                        o
                    })
                    .collect(),
                _ => Vec::new(),
            };
            if payload.len() != n * CLOUD_POINT_BYTES || data.len() != n * step {
                return Err(format!(
                    "point cloud with {}-byte points and {} bytes for {n} points; ours have {ROS_POINT_BYTES}-byte points",
                    c.point_step,
                    data.len(),
                ));
            }
            Ok((stamp(cloud_header(n)), payload))
        }
        CELL_ARRAY => {
            let m: RosCellArray = from_cdr(parts[0], CELL_ARRAY.name)?;
            let cells = |v: Vec<RosCell>| -> Result<Vec<Cell>, String> {
                v.into_iter().map(RosCell::into_cell).collect()
            };
            let lists = CellLists {
                left: cells(m.left)?,
                right: cells(m.right)?,
            };
            Ok(encoded(&lists, stamp))
        }
        TRACKS => {
            let m: RosTracks = from_cdr(parts[0], TRACKS.name)?;
            let t = Tracks {
                frame: m.frame,
                capture_ns: m.capture_ns,
                unit: m.unit,
                shift: m.shift,
                tracks: m
                    .tracks
                    .into_iter()
                    .map(RosTrack::into_track)
                    .collect::<Result<_, _>>()?,
                substrate: m.has_substrate.then(|| m.substrate.plane()),
            };
            Ok(encoded(&t, stamp))
        }
        MANIPULATOR_STATE => {
            let m: RosManipulatorState = from_cdr(parts[0], MANIPULATOR_STATE.name)?;
            Ok(encoded(&m.into_state()?, stamp))
        }
        DISPARITY_TILES => {
            let m: RosTiles = from_cdr(parts[0], DISPARITY_TILES.name)?;
            Ok(encoded(&m.into_tiles()?, stamp))
        }
        _ => {
            let m: RosTargets = from_cdr(parts[0], TARGETS.name)?;
            let t = Targets {
                frame: m.frame,
                capture_ns: m.capture_ns,
                unit: m.unit,
                cells: m
                    .cells
                    .into_iter()
                    .map(RosCell3::into_cell3)
                    .collect::<Result<_, _>>()?,
                substrate: m.has_substrate.then_some(DisparityPlane {
                    d0: m.substrate.d0,
                    dx: m.substrate.dx,
                    dy: m.substrate.dy,
                    centre: m.substrate.centre,
                    std: m.substrate.std,
                    pixels: m.substrate.pixels,
                }),
            };
            Ok(encoded(&t, stamp))
        }
    }
}

/// A message's header (stamped) and payload, as a node sends it.
fn encoded<M: Message>(
    m: &M,
    stamp: impl Fn(FrameHeader) -> FrameHeader,
) -> (FrameHeader, Vec<u8>) {
    let e = m.encode();
    (stamp(e.header), e.to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;
    use schemas::wire::json_header;

    fn stamped(h: FrameHeader) -> FrameHeader {
        FrameHeader {
            sequence: 7,
            capture_ns: 1_700_000_000_123_456_789,
            ..h
        }
    }

    fn round_trip(kind: MessageKind, h: FrameHeader, payload: &[u8]) -> Vec<Part> {
        let parts = encode(kind, &h, payload, Some(1e-6)).unwrap();
        let cdrs: Vec<&[u8]> = parts.iter().map(|p| p.cdr.as_slice()).collect();
        let (back, bytes) = decode(kind, &cdrs, (h.sequence, h.capture_ns)).unwrap();
        assert_eq!(back, h, "{kind:?} header");
        assert_eq!(bytes, payload, "{kind:?} payload");
        parts
    }

    #[test]
    fn every_kind_comes_back_bit_for_bit() {
        let px = |n: usize| (0..n).map(|i| (i * 37 % 251) as u8).collect::<Vec<_>>();
        for (kind, format, images) in [
            (MessageKind::StereoFrame, PixelFormat::Mono8, 2),
            (MessageKind::Image, PixelFormat::Mono8, 1),
            (MessageKind::Disparity, PixelFormat::F32, 1),
            (MessageKind::Labels, PixelFormat::U32, 2),
            (MessageKind::DisparityPair, PixelFormat::F32, 2),
        ] {
            let h = stamped(FrameHeader::image(kind, format, 5, 3, images));
            let parts = round_trip(kind, h, &px(h.image_bytes()));
            let sides: Vec<_> = parts.iter().map(|p| p.side).collect();
            let want = if images == 2 {
                vec![Some("left"), Some("right")]
            } else {
                vec![None]
            };
            assert_eq!(sides, want);
        }
        let h = stamped(cloud_header(4));
        round_trip(MessageKind::PointCloud, h, &px(4 * CLOUD_POINT_BYTES));
        let cell = Cell {
            id: 3,
            area: 120,
            centroid: [10.25, 0.1 + 0.2],
            bbox: BoundingBox {
                x0: 1,
                y0: 2,
                x1: 20,
                y1: 30,
            },
            contour: vec![[1, 2], [2, 2], [3, 4]],
            perimeter: 2.0 + std::f64::consts::SQRT_2,
        };
        let lists = CellLists {
            left: vec![cell.clone()],
            right: vec![cell.clone(), Cell { id: 4, ..cell }],
        };
        let h = stamped(json_header(MessageKind::CellList));
        round_trip(
            MessageKind::CellList,
            h,
            &serde_json::to_vec(&lists).unwrap(),
        );
        let targets = Targets {
            frame: 7,
            capture_ns: 12,
            unit: "µm".into(),
            cells: vec![
                Cell3 {
                    id: 1,
                    right_id: 2,
                    area_px: 300,
                    centroid_px: [1.0 / 3.0, 2.5],
                    disparity: 4.125,
                    centroid: [1e-7, -3.25, 1234.5678901234],
                    substrate_z: 1000.0,
                    height: Some(12.3),
                    volume: 4567.0,
                    contour: vec![[1.0, 2.0, 3.0], [0.1, 0.2, 0.3]],
                    valid_share: 0.97,
                    quality: CellQuality {
                        substrate: schemas::SubstrateSource::Rim,
                        substrate_std: 0.04,
                        height_std: Some(0.2),
                        residual: Some(1.7),
                        trusted: true,
                        doubt: None,
                    },
                },
                Cell3 {
                    id: 3,
                    right_id: 1,
                    area_px: 40,
                    centroid_px: [10.0, 20.0],
                    disparity: 1.0,
                    centroid: [0.0, 0.0, 1000.0],
                    substrate_z: 1000.0,
                    height: None,
                    volume: 0.0,
                    contour: vec![],
                    valid_share: 0.1,
                    quality: CellQuality {
                        substrate: schemas::SubstrateSource::Ring,
                        substrate_std: 1.0,
                        height_std: None,
                        residual: None,
                        trusted: false,
                        doubt: Some("the top was not found above the substrate".into()),
                    },
                },
            ],
            substrate: None,
        };
        let h = stamped(json_header(MessageKind::Targets));
        round_trip(
            MessageKind::Targets,
            h,
            &serde_json::to_vec(&targets).unwrap(),
        );
        let with_plane = Targets {
            substrate: Some(DisparityPlane {
                d0: 0.015,
                dx: -1e-5,
                dy: 2.5e-6,
                centre: [319.5, 239.5],
                std: 0.001,
                pixels: 90000,
            }),
            ..targets
        };
        round_trip(
            MessageKind::Targets,
            h,
            &serde_json::to_vec(&with_plane).unwrap(),
        );
        let tracks = Tracks {
            frame: 4,
            capture_ns: 99,
            unit: "µm".into(),
            shift: [1.5, -0.25, 0.0],
            tracks: vec![
                Track {
                    id: 17,
                    state: TrackState::Confirmed,
                    age: 40,
                    missed: 0,
                    frames_used: 30,
                    position: [10.0, -20.5, 3990.0],
                    position_std: 0.3,
                    velocity: [2.0, 0.0, -0.1],
                    height: Some(12.5),
                    height_std: Some(0.2),
                    volume: 3000.0,
                    volume_std: 50.0,
                    trusted: true,
                    cell: with_plane.cells.first().cloned(),
                },
                Track {
                    id: 18,
                    state: TrackState::Lost,
                    age: 3,
                    missed: 2,
                    frames_used: 0,
                    position: [0.0; 3],
                    position_std: 1.0,
                    velocity: [0.0; 3],
                    height: None,
                    height_std: None,
                    volume: 0.0,
                    volume_std: 0.0,
                    trusted: false,
                    cell: None,
                },
            ],
            substrate: with_plane.substrate,
        };
        let parts = round_trip(
            MessageKind::Tracks,
            stamped(json_header(MessageKind::Tracks)),
            &serde_json::to_vec(&tracks).unwrap(),
        );
        assert_eq!(parts[0].msg, TRACKS);
        let mut tiles = DisparityTiles::whole(
            Side::Left,
            DisparityRange::new(-4, 12),
            Plane::from_vec(3, 2, vec![1.5, f32::INFINITY, -0.25, f32::NAN, 3.0, 1e-7]).unwrap(),
            96,
        );
        tiles.tiles[0].figures = Some(ValidationFigures {
            matched: 5,
            consistent_exact: 0.2,
            off_by_one: 0.4,
            off_by_more: 0.4,
            consistent_within_tolerance: 0.6,
            tolerance: 1,
        });
        tiles.margin = 8;
        tiles.tiles.push(DisparityTile {
            x: 1,
            y: 0,
            range: DisparityRange::new(0, 1),
            cells: Some((2, 3)),
            map: Plane::filled(0, 0, 0.0),
            evaluations: 0,
            figures: None,
        });
        let e = tiles.encode();
        let parts = round_trip(MessageKind::DisparityTiles, stamped(e.header), &e.to_vec());
        assert_eq!(parts[0].msg, DISPARITY_TILES);
        let mut state = ManipulatorState {
            frame: 9,
            capture_ns: 77,
            device: "sim".into(),
            status: "moving".into(),
            tip: [-300.0, 0.125, -3850.5],
            elevation_deg: 30.0,
            azimuth_deg: 180.0,
            clearance: 5.0,
            trajectory: vec![[0.5, 1.0, 2.0, 3.0], [0.51, 1.5, 2.0, 3.0]],
            plan: Some(PathPlan {
                goal: "approach".into(),
                target: Some(3),
                frame: 8,
                waypoints: vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]],
                axial_from: 1,
                end: [4.0, 5.0, 6.0],
                length: 5.196,
                min_clearance: Some(12.5),
            }),
            ignored: vec![4],
        };
        let h = stamped(json_header(MessageKind::ManipulatorState));
        round_trip(
            MessageKind::ManipulatorState,
            h,
            &serde_json::to_vec(&state).unwrap(),
        );
        state.plan = None;
        round_trip(
            MessageKind::ManipulatorState,
            h,
            &serde_json::to_vec(&state).unwrap(),
        );
    }

    #[test]
    fn labels_that_fit_go_as_16uc1_and_the_cloud_in_metres_with_packed_colours() {
        let ids: Vec<u8> = [0u32, 7, 65_535, 3, 1, 2]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let h = stamped(FrameHeader::image(
            MessageKind::Labels,
            PixelFormat::U32,
            3,
            1,
            2,
        ));
        let parts = round_trip(MessageKind::Labels, h, &ids);
        let img: Image = from_cdr(&parts[1].cdr, IMAGE.name).unwrap();
        assert_eq!((img.encoding.as_str(), img.step), ("16UC1", 6));
        assert_eq!(img.data.as_slice(), &[3, 0, 1, 0, 2, 0]);
        assert_eq!(img.header.frame_id, "right_camera_optical_frame");
        // One id past 16 bits: the whole message stays 32SC1.
        let mut wide = ids.clone();
        wide[4..8].copy_from_slice(&65_536u32.to_le_bytes());
        let parts = round_trip(MessageKind::Labels, h, &wide);
        let img: Image = from_cdr(&parts[0].cdr, IMAGE.name).unwrap();
        assert_eq!(img.encoding, "32SC1");
        let mut point = Vec::new();
        for v in [250.0f32, -1500.5, 150_000.0] {
            point.extend(v.to_le_bytes());
        }
        point.extend([200, 100, 50]);
        let h = stamped(cloud_header(1));
        let parts = round_trip(MessageKind::PointCloud, h, &point);
        let c: PointCloud2 = from_cdr(&parts[0].cdr, POINT_CLOUD2.name).unwrap();
        let f = |k: usize| f32::from_le_bytes(c.data[4 * k..4 * k + 4].try_into().unwrap());
        assert_eq!([f(0), f(1), f(2)], [250e-6, -1500.5e-6, 0.15]);
        // PCL's packed 0x00RRGGBB, little-endian.
        assert_eq!(&c.data[12..16], &[50, 100, 200, 0]);
        assert_eq!(c.fields[3].name, "rgb");
        assert_eq!(c.header.frame_id, STEREO_FRAME);
    }

    #[test]
    fn an_image_is_standard_cdr() {
        // The bytes a ROS 2 reader expects: encapsulation CDR_LE, then the fields aligned
        // to their size from the start of the data.
        let h = FrameHeader {
            capture_ns: 3_000_000_005,
            ..FrameHeader::image(MessageKind::Image, PixelFormat::Mono8, 2, 1, 1)
        };
        let parts = encode(MessageKind::Image, &h, &[9, 8], None).unwrap();
        let b = &parts[0].cdr;
        let mut want = vec![0u8, 1, 0, 0];
        want.extend(3i32.to_le_bytes()); // stamp.sec
        want.extend(5u32.to_le_bytes()); // stamp.nanosec
        want.extend(26u32.to_le_bytes()); // frame_id length with its NUL
        want.extend(b"left_camera_optical_frame\0");
        want.extend([0, 0]); // align to 4
        want.extend(1u32.to_le_bytes()); // height
        want.extend(2u32.to_le_bytes()); // width
        want.extend(6u32.to_le_bytes());
        want.extend(b"mono8\0");
        want.push(0); // is_bigendian
        want.push(0); // align to 4
        want.extend(2u32.to_le_bytes()); // step
        want.extend(2u32.to_le_bytes()); // data length
        want.extend([9, 8]);
        assert_eq!(b, &want);
    }

    #[test]
    fn camera_info_holds_the_projection_with_the_baseline_in_metres() {
        let calib = schemas::Calibration {
            baseline: 2000.0,
            focal_px: 4000.0,
            cx: 320.0,
            cy: 256.0,
            cx_right: 330.0,
            unit: schemas::LengthUnit::Um,
        };
        let b = camera_info(&calib, (640, 512), "right", 5).unwrap();
        let c: CameraInfo = from_cdr(&b, CAMERA_INFO.name).unwrap();
        assert_eq!((c.width, c.height), (640, 512));
        assert_eq!(c.k, [4000.0, 0.0, 330.0, 0.0, 4000.0, 256.0, 0.0, 0.0, 1.0]);
        // −f·B with B = 2000 µm = 0.002 m.
        assert!((c.p[3] + 8.0).abs() < 1e-12, "{}", c.p[3]);
        let l: CameraInfo =
            from_cdr(&camera_info(&calib, (640, 512), "left", 5).unwrap(), "").unwrap();
        assert_eq!((l.k[2], l.p[3]), (320.0, 0.0));
    }

    #[test]
    fn malformed_messages_are_refused_with_a_reason() {
        let h = FrameHeader::image(MessageKind::Image, PixelFormat::Mono8, 4, 4, 1);
        let e = encode(MessageKind::Image, &h, &[0; 3], None).unwrap_err();
        assert!(e.contains("3 bytes"), "{e}");
        let e = decode(MessageKind::Image, &[&[0, 1, 0, 0, 9]], (0, 0)).unwrap_err();
        assert!(e.contains("not a CDR sensor_msgs/msg/Image"), "{e}");
        let e = decode(MessageKind::StereoFrame, &[&[0, 1, 0, 0]], (0, 0)).unwrap_err();
        assert!(e.contains("1 part(s), not 2"), "{e}");
        let e = encode(
            MessageKind::CellList,
            &json_header(MessageKind::CellList),
            b"{",
            None,
        )
        .unwrap_err();
        assert!(e.contains("cell list: EOF"), "{e}");
    }
}
