//! What ROS 2 tools and Foxglove need beside the edges to draw one scene: the frame tree
//! (`tf2_msgs/msg/TFMessage` on `/tf_static`), and the cells, tracks and pipette as
//! `visualization_msgs/msg/MarkerArray` in metres (REP 103), so that a viewer puts the
//! cells over the camera images and the substrate under the cells.
//!
//! The frames: `stage` (Z up, the root), `stereo_optical_frame` (midway between the
//! rectified cameras: X right, Y down, Z along the view; the cells' and the pipette's
//! frame, where our own messages give lengths in their `unit`) and each camera's
//! `left_camera_optical_frame` / `right_camera_optical_frame`, half the baseline either side.

use crate::ros2::{Header, MsgType, header_defs, sep, to_cdr};
use schemas::msg::Message;
use schemas::{Cell3, FrameHeader, ManipulatorState, MessageKind, Targets, Tracks};
use serde::{Deserialize, Serialize};

/// The root frame: the stage, Z up (REP 103).
pub const STAGE_FRAME: &str = "stage";
/// The frame of the cells, the cloud and the pipette: midway between the rectified
/// cameras, X right, Y down, Z along the view.
pub const STEREO_FRAME: &str = "stereo_optical_frame";

/// The optical frame of camera `side` (`left` or `right`).
pub fn camera_frame(side: &str) -> &'static str {
    if side == "right" {
        "right_camera_optical_frame"
    } else {
        "left_camera_optical_frame"
    }
}

/// rosbag2's QoS profile of a latched topic (`transient_local`, keep last 1), the channel
/// metadata `offered_qos_profiles`, so that a replay hands it to late subscribers.
pub const LATCHED_QOS: &str = "- history: 1\n  depth: 1\n  reliability: 1\n  durability: 1\n  deadline:\n    sec: 2147483647\n    nsec: 4294967295\n  lifespan:\n    sec: 2147483647\n    nsec: 4294967295\n  liveliness: 1\n  liveliness_lease_duration:\n    sec: 2147483647\n    nsec: 4294967295\n  avoid_ros_namespace_conventions: false\n";

macro_rules! geometry_defs {
    () => {
        concat!(
            header_defs!(),
            sep!(),
            "MSG: geometry_msgs/Vector3\n",
            "float64 x\n",
            "float64 y\n",
            "float64 z\n",
            sep!(),
            "MSG: geometry_msgs/Quaternion\n",
            "float64 x 0\n",
            "float64 y 0\n",
            "float64 z 0\n",
            "float64 w 1\n"
        )
    };
}

/// `tf2_msgs/msg/TFMessage`: the frame tree.
pub const TF_MESSAGE: MsgType = MsgType {
    name: "tf2_msgs/msg/TFMessage",
    definition: concat!(
        "geometry_msgs/TransformStamped[] transforms\n",
        sep!(),
        "MSG: geometry_msgs/TransformStamped\n",
        "std_msgs/Header header\n",
        "string child_frame_id\n",
        "Transform transform\n",
        sep!(),
        "MSG: geometry_msgs/Transform\n",
        "Vector3 translation\n",
        "Quaternion rotation\n",
        geometry_defs!()
    ),
};

/// `visualization_msgs/msg/MarkerArray` (ROS 2 Humble and later): the cells, tracks and
/// pipette as RViz and Foxglove draw them.
pub const MARKER_ARRAY: MsgType = MsgType {
    name: "visualization_msgs/msg/MarkerArray",
    definition: concat!(
        "Marker[] markers\n",
        sep!(),
        "MSG: visualization_msgs/Marker\n",
        "int32 ARROW=0\n",
        "int32 CUBE=1\n",
        "int32 SPHERE=2\n",
        "int32 CYLINDER=3\n",
        "int32 LINE_STRIP=4\n",
        "int32 LINE_LIST=5\n",
        "int32 CUBE_LIST=6\n",
        "int32 SPHERE_LIST=7\n",
        "int32 POINTS=8\n",
        "int32 TEXT_VIEW_FACING=9\n",
        "int32 MESH_RESOURCE=10\n",
        "int32 TRIANGLE_LIST=11\n",
        "int32 ADD=0\n",
        "int32 MODIFY=0\n",
        "int32 DELETE=2\n",
        "int32 DELETEALL=3\n",
        "std_msgs/Header header\n",
        "string ns\n",
        "int32 id\n",
        "int32 type\n",
        "int32 action\n",
        "geometry_msgs/Pose pose\n",
        "geometry_msgs/Vector3 scale\n",
        "std_msgs/ColorRGBA color\n",
        "builtin_interfaces/Duration lifetime\n",
        "bool frame_locked\n",
        "geometry_msgs/Point[] points\n",
        "std_msgs/ColorRGBA[] colors\n",
        "string texture_resource\n",
        "sensor_msgs/CompressedImage texture\n",
        "UVCoordinate[] uv_coordinates\n",
        "string text\n",
        "string mesh_resource\n",
        "MeshFile mesh_file\n",
        "bool mesh_use_embedded_materials\n",
        sep!(),
        "MSG: geometry_msgs/Pose\n",
        "Point position\n",
        "Quaternion orientation\n",
        sep!(),
        "MSG: geometry_msgs/Point\n",
        "float64 x\n",
        "float64 y\n",
        "float64 z\n",
        sep!(),
        "MSG: std_msgs/ColorRGBA\n",
        "float32 r\n",
        "float32 g\n",
        "float32 b\n",
        "float32 a\n",
        sep!(),
        "MSG: builtin_interfaces/Duration\n",
        "int32 sec\n",
        "uint32 nanosec\n",
        sep!(),
        "MSG: sensor_msgs/CompressedImage\n",
        "std_msgs/Header header\n",
        "string format\n",
        "uint8[] data\n",
        sep!(),
        "MSG: visualization_msgs/UVCoordinate\n",
        "float32 u\n",
        "float32 v\n",
        sep!(),
        "MSG: visualization_msgs/MeshFile\n",
        "string filename\n",
        "uint8[] data\n",
        geometry_defs!()
    ),
};

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
struct Vector3 {
    x: f64,
    y: f64,
    z: f64,
}

impl Vector3 {
    fn of([x, y, z]: [f64; 3]) -> Self {
        Self { x, y, z }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
struct Quaternion {
    x: f64,
    y: f64,
    z: f64,
    w: f64,
}

const IDENTITY: Quaternion = Quaternion {
    x: 0.0,
    y: 0.0,
    z: 0.0,
    w: 1.0,
};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct Transform {
    translation: Vector3,
    rotation: Quaternion,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct TransformStamped {
    header: Header,
    child_frame_id: String,
    transform: Transform,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct TfMessage {
    transforms: Vec<TransformStamped>,
}

/// The static frame tree of a rig whose rectified cameras lie `baseline_m` metres apart,
/// stamped `stamp_ns`: `stage` → `stereo_optical_frame` (turned half a turn about X, so
/// that the stage's Z points back up the view) → each camera's optical frame.
pub fn tf_static(baseline_m: f64, stamp_ns: u64) -> Result<Vec<u8>, String> {
    let link = |parent: &str, child: &str, t: [f64; 3], rotation| TransformStamped {
        header: Header::new(stamp_ns, parent),
        child_frame_id: child.into(),
        transform: Transform {
            translation: Vector3::of(t),
            rotation,
        },
    };
    let half = Quaternion {
        x: 1.0,
        y: 0.0,
        z: 0.0,
        w: 0.0,
    };
    to_cdr(&TfMessage {
        transforms: vec![
            link(STAGE_FRAME, STEREO_FRAME, [0.0; 3], half),
            link(
                STEREO_FRAME,
                camera_frame("left"),
                [-0.5 * baseline_m, 0.0, 0.0],
                IDENTITY,
            ),
            link(
                STEREO_FRAME,
                camera_frame("right"),
                [0.5 * baseline_m, 0.0, 0.0],
                IDENTITY,
            ),
        ],
    })
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
struct Color {
    r: f32,
    g: f32,
    b: f32,
    a: f32,
}

const fn rgba(r: f32, g: f32, b: f32, a: f32) -> Color {
    Color { r, g, b, a }
}

const TRUSTED: Color = rgba(0.2, 0.8, 0.3, 0.6);
const DOUBTED: Color = rgba(1.0, 0.6, 0.1, 0.5);
const NO_HEIGHT: Color = rgba(0.6, 0.6, 0.6, 0.4);
const PIPETTE: Color = rgba(0.3, 0.6, 1.0, 0.9);
const WHITE: Color = rgba(1.0, 1.0, 1.0, 1.0);
/// Behind a label: half-transparent black.
const SHADE: Color = rgba(0.0, 0.0, 0.0, 0.5);

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct Pose {
    position: Vector3,
    orientation: Quaternion,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
struct Duration {
    sec: i32,
    nanosec: u32,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct CompressedImage {
    header: Header,
    format: String,
    data: serde_bytes::ByteBuf,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct MeshFile {
    filename: String,
    data: serde_bytes::ByteBuf,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct UvCoordinate {
    u: f32,
    v: f32,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct Marker {
    header: Header,
    ns: String,
    id: i32,
    r#type: i32,
    action: i32,
    pose: Pose,
    scale: Vector3,
    color: Color,
    lifetime: Duration,
    frame_locked: bool,
    points: Vec<Vector3>,
    colors: Vec<Color>,
    texture_resource: String,
    texture: CompressedImage,
    uv_coordinates: Vec<UvCoordinate>,
    text: String,
    mesh_resource: String,
    mesh_file: MeshFile,
    mesh_use_embedded_materials: bool,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct MarkerArray {
    markers: Vec<Marker>,
}

const SPHERE: i32 = 2;
const LINE_STRIP: i32 = 4;
const TEXT: i32 = 9;
const DELETE_ALL: i32 = 3;

/// Markers of one message, in metres in [`STEREO_FRAME`], stamped with its capture time.
struct Scene {
    stamp: u64,
    markers: Vec<Marker>,
}

impl Scene {
    /// A scene whose first marker clears the previous message's: cells that left are gone.
    fn new(stamp: u64) -> Self {
        let mut s = Self {
            stamp,
            markers: Vec::new(),
        };
        s.push("", 0, 0, [0.0; 3], [0.0; 3], WHITE);
        s.markers[0].action = DELETE_ALL;
        s
    }

    fn push(&mut self, ns: &str, id: i32, r#type: i32, at: [f64; 3], scale: [f64; 3], c: Color) {
        self.markers.push(Marker {
            header: Header::new(self.stamp, STEREO_FRAME),
            ns: ns.into(),
            id,
            r#type,
            action: 0,
            pose: Pose {
                position: Vector3::of(at),
                orientation: IDENTITY,
            },
            scale: Vector3::of(scale),
            color: c,
            lifetime: Duration::default(),
            frame_locked: false,
            points: Vec::new(),
            colors: Vec::new(),
            texture_resource: String::new(),
            texture: CompressedImage {
                header: Header::new(0, ""),
                format: String::new(),
                data: Default::default(),
            },
            uv_coordinates: Vec::new(),
            text: String::new(),
            mesh_resource: String::new(),
            mesh_file: MeshFile {
                filename: String::new(),
                data: Default::default(),
            },
            mesh_use_embedded_materials: false,
        });
    }

    fn last(&mut self) -> &mut Marker {
        self.markers.last_mut().expect("pushed")
    }

    /// Cell `c` (lengths × `m` for metres) as marker `id` of `ns`: an ellipsoid over its
    /// footprint as high as the cell, its outline on the substrate and a label.
    fn cell(&mut self, ns: &str, id: i32, c: &Cell3, m: f64, label: String) {
        let colour = match (c.height, c.quality.trusted) {
            (None, _) => NO_HEIGHT,
            (Some(_), true) => TRUSTED,
            (Some(_), false) => DOUBTED,
        };
        let h = c.height.unwrap_or(0.0);
        let ([cx, cy], [a, b], angle) =
            footprint(&c.contour).unwrap_or(([c.centroid[0], c.centroid[1]], [1.0, 1.0], 0.0));
        // The cell rises from the substrate towards the cameras (smaller Z).
        let mid = [cx * m, cy * m, (c.substrate_z - 0.5 * h) * m];
        let thick = h.max(0.05 * a.min(b));
        self.push(
            ns,
            id,
            SPHERE,
            mid,
            [2.0 * a * m, 2.0 * b * m, thick * m],
            colour,
        );
        self.last().pose.orientation = Quaternion {
            x: 0.0,
            y: 0.0,
            z: (0.5 * angle).sin(),
            w: (0.5 * angle).cos(),
        };
        if c.contour.len() >= 2 {
            let width = 0.02 * a.min(b).max(1.0) * m;
            self.push(
                &format!("{ns}/outline"),
                id,
                LINE_STRIP,
                [0.0; 3],
                [width, 0.0, 0.0],
                colour,
            );
            let outline = c
                .contour
                .iter()
                .chain(c.contour.first())
                .map(|p| Vector3::of(p.map(|v| v * m)));
            self.last().points = outline.collect();
        }
        let above = [cx * m, cy * m, (c.substrate_z - h) * m - 0.3 * a * m];
        self.push(
            &format!("{ns}/label"),
            id,
            TEXT,
            above,
            [0.0, 0.0, 0.3 * a * m],
            WHITE,
        );
        self.last().text = label;
    }

    fn cdr(self) -> Result<Vec<u8>, String> {
        to_cdr(&MarkerArray {
            markers: self.markers,
        })
    }
}

/// The centre, semi-axes and angle (from +X towards +Y) of the ellipse with the second
/// moments of an outline's points (its boundary pixels, evenly spaced: an ellipse's
/// boundary has variance a²/2 along its major axis); `None` for fewer than three points.
fn footprint(contour: &[[f64; 3]]) -> Option<([f64; 2], [f64; 2], f64)> {
    if contour.len() < 3 {
        return None;
    }
    let n = contour.len() as f64;
    let (mx, my) = (
        contour.iter().map(|p| p[0]).sum::<f64>() / n,
        contour.iter().map(|p| p[1]).sum::<f64>() / n,
    );
    let (mut xx, mut xy, mut yy) = (0.0, 0.0, 0.0);
    for p in contour {
        let (dx, dy) = (p[0] - mx, p[1] - my);
        xx += dx * dx / n;
        xy += dx * dy / n;
        yy += dy * dy / n;
    }
    let mean = 0.5 * (xx + yy);
    let spread = (0.25 * (xx - yy).powi(2) + xy * xy).sqrt();
    let angle = 0.5 * (2.0 * xy).atan2(xx - yy);
    Some((
        [mx, my],
        [
            (2.0 * (mean + spread)).sqrt(),
            (2.0 * (mean - spread).max(0.0)).sqrt(),
        ],
        angle,
    ))
}

/// Metres per unit named `unit` (`µm`, `mm`, `m`); `None` for another.
fn metres_per(unit: &str) -> Option<f64> {
    match unit {
        "µm" | "um" => Some(1e-6),
        "mm" => Some(1e-3),
        "m" => Some(1.0),
        _ => None,
    }
}

/// The height of cell `c` in words, for its label.
fn height_text(c: &Cell3, unit: &str) -> String {
    match (c.height, c.quality.height_std) {
        (Some(h), Some(s)) => format!("{h:.1} ± {s:.1} {unit}"),
        (Some(h), None) => format!("{h:.1} {unit}"),
        (None, _) => "no height".into(),
    }
}

/// The markers of a message of `kind` (targets, tracks, the manipulator's state): `None`
/// for other kinds and for lengths in a unit we cannot put in metres.
pub fn markers(
    kind: MessageKind,
    h: &FrameHeader,
    payload: &[u8],
) -> Result<Option<Vec<u8>>, String> {
    let mut scene = Scene::new(h.capture_ns);
    match kind {
        MessageKind::Targets => {
            let t = Targets::decode(h, payload).map_err(|e| e.to_string())?;
            let Some(m) = metres_per(&t.unit) else {
                return Ok(None);
            };
            for c in &t.cells {
                let label = format!("cell {}: {}", c.id, height_text(c, &t.unit));
                scene.cell("cells", c.id as i32, c, m, label);
            }
        }
        MessageKind::Tracks => {
            let t = Tracks::decode(h, payload).map_err(|e| e.to_string())?;
            let Some(m) = metres_per(&t.unit) else {
                return Ok(None);
            };
            for tr in &t.tracks {
                let Some(c) = &tr.cell else { continue };
                let label = format!("track {}: {}", tr.id, height_text(c, &t.unit));
                scene.cell("tracks", tr.id as i32, c, m, label);
            }
        }
        MessageKind::ManipulatorState => {
            let st = ManipulatorState::decode(h, payload).map_err(|e| e.to_string())?;
            let m = 1e-6;
            let w = |p: [f64; 3]| Vector3::of(p.map(|v| v * m));
            let (e, a) = (st.elevation_deg.to_radians(), st.azimuth_deg.to_radians());
            // 200 µm of the body, rising towards the cameras (smaller Z).
            let back = [
                st.tip[0] + 200.0 * e.cos() * a.cos(),
                st.tip[1] + 200.0 * e.cos() * a.sin(),
                st.tip[2] - 200.0 * e.sin(),
            ];
            scene.push(
                "pipette",
                0,
                LINE_STRIP,
                [0.0; 3],
                [4.0 * m, 0.0, 0.0],
                PIPETTE,
            );
            scene.last().points = vec![w(st.tip), w(back)];
            scene.push(
                "pipette/tip",
                0,
                SPHERE,
                st.tip.map(|v| v * m),
                [6.0 * m; 3],
                PIPETTE,
            );
            if let Some(plan) = &st.plan {
                scene.push("plan", 0, LINE_STRIP, [0.0; 3], [2.0 * m, 0.0, 0.0], WHITE);
                scene.last().points = plan.waypoints.iter().map(|p| w(*p)).collect();
            }
            if !st.trajectory.is_empty() {
                scene.push(
                    "trajectory",
                    0,
                    LINE_STRIP,
                    [0.0; 3],
                    [1.0 * m, 0.0, 0.0],
                    PIPETTE,
                );
                scene.last().points = st
                    .trajectory
                    .iter()
                    .map(|t| w([t[1], t[2], t[3]]))
                    .collect();
            }
        }
        _ => return Ok(None),
    }
    scene.cdr().map(Some)
}

/// `foxglove_msgs/msg/ImageAnnotations` (foxglove_msgs 3): the cells' outlines and labels
/// drawn over the camera images by Foxglove's Image panel.
pub const IMAGE_ANNOTATIONS: MsgType = MsgType {
    name: "foxglove_msgs/msg/ImageAnnotations",
    definition: concat!(
        "foxglove_msgs/CircleAnnotation[] circles\n",
        "foxglove_msgs/PointsAnnotation[] points\n",
        "foxglove_msgs/TextAnnotation[] texts\n",
        sep!(),
        "MSG: foxglove_msgs/CircleAnnotation\n",
        "builtin_interfaces/Time timestamp\n",
        "foxglove_msgs/Point2 position\n",
        "float64 diameter\n",
        "float64 thickness\n",
        "foxglove_msgs/Color fill_color\n",
        "foxglove_msgs/Color outline_color\n",
        sep!(),
        "MSG: builtin_interfaces/Time\n",
        "int32 sec\n",
        "uint32 nanosec\n",
        sep!(),
        "MSG: foxglove_msgs/Point2\n",
        "float64 x\n",
        "float64 y\n",
        sep!(),
        "MSG: foxglove_msgs/Color\n",
        "float64 r\n",
        "float64 g\n",
        "float64 b\n",
        "float64 a\n",
        sep!(),
        "MSG: foxglove_msgs/PointsAnnotation\n",
        "builtin_interfaces/Time timestamp\n",
        "uint8 UNKNOWN=0\n",
        "uint8 POINTS=1\n",
        "uint8 LINE_LOOP=2\n",
        "uint8 LINE_STRIP=3\n",
        "uint8 LINE_LIST=4\n",
        "uint8 type\n",
        "foxglove_msgs/Point2[] points\n",
        "foxglove_msgs/Color outline_color\n",
        "foxglove_msgs/Color[] outline_colors\n",
        "foxglove_msgs/Color fill_color\n",
        "float64 thickness\n",
        sep!(),
        "MSG: foxglove_msgs/TextAnnotation\n",
        "builtin_interfaces/Time timestamp\n",
        "foxglove_msgs/Point2 position\n",
        "string text\n",
        "float64 font_size\n",
        "foxglove_msgs/Color text_color\n",
        "foxglove_msgs/Color background_color\n"
    ),
};

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
struct Rgba {
    r: f64,
    g: f64,
    b: f64,
    a: f64,
}

impl From<Color> for Rgba {
    fn from(c: Color) -> Self {
        Self {
            r: c.r.into(),
            g: c.g.into(),
            b: c.b.into(),
            a: c.a.into(),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
struct Point2 {
    x: f64,
    y: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct PointsAnnotation {
    timestamp: crate::ros2::Time,
    r#type: u8,
    points: Vec<Point2>,
    outline_color: Rgba,
    outline_colors: Vec<Rgba>,
    fill_color: Rgba,
    thickness: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct TextAnnotation {
    timestamp: crate::ros2::Time,
    position: Point2,
    text: String,
    font_size: f64,
    text_color: Rgba,
    background_color: Rgba,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct CircleAnnotation {
    timestamp: crate::ros2::Time,
    position: Point2,
    diameter: f64,
    thickness: f64,
    fill_color: Rgba,
    outline_color: Rgba,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
struct ImageAnnotations {
    circles: Vec<CircleAnnotation>,
    points: Vec<PointsAnnotation>,
    texts: Vec<TextAnnotation>,
}

impl ImageAnnotations {
    /// An outline through pixel centres `points` and a label at its first point's left.
    fn outline(&mut self, stamp: u64, points: Vec<Point2>, c: Color, label: String, at: Point2) {
        let timestamp = crate::ros2::Time::of(stamp);
        self.points.push(PointsAnnotation {
            timestamp,
            r#type: 2,
            points,
            outline_color: c.into(),
            outline_colors: Vec::new(),
            fill_color: Color { a: 0.0, ..c }.into(),
            thickness: 1.5,
        });
        self.texts.push(TextAnnotation {
            timestamp,
            position: at,
            text: label,
            font_size: 12.0,
            text_color: WHITE.into(),
            background_color: SHADE.into(),
        });
    }
}

/// The image annotations of a message of `kind`, per image side: each cell's outline and id over both views for a cell list, each cell's height
/// over the left view for targets; `[]` for other kinds.
pub fn annotations(
    kind: MessageKind,
    h: &FrameHeader,
    payload: &[u8],
) -> Result<Vec<(&'static str, Vec<u8>)>, String> {
    // Pixel centres: Foxglove's origin is the top-left pixel's corner.
    let px = |x: f64, y: f64| Point2 {
        x: x + 0.5,
        y: y + 0.5,
    };
    match kind {
        MessageKind::CellList => {
            let lists = schemas::CellLists::decode(h, payload).map_err(|e| e.to_string())?;
            [("left", &lists.left), ("right", &lists.right)]
                .into_iter()
                .map(|(side, cells)| {
                    let mut a = ImageAnnotations::default();
                    for c in cells {
                        let outline = c.contour.iter().map(|p| px(p[0] as f64, p[1] as f64));
                        let at = px(c.bbox.x0 as f64, c.bbox.y0 as f64);
                        let label = format!("cell {}", c.id);
                        a.outline(h.capture_ns, outline.collect(), TRUSTED, label, at);
                    }
                    Ok((side, to_cdr(&a)?))
                })
                .collect()
        }
        MessageKind::Targets => {
            let t = Targets::decode(h, payload).map_err(|e| e.to_string())?;
            let mut a = ImageAnnotations::default();
            for c in &t.cells {
                let colour = match (c.height, c.quality.trusted) {
                    (None, _) => NO_HEIGHT,
                    (Some(_), true) => TRUSTED,
                    (Some(_), false) => DOUBTED,
                };
                let [x, y] = c.centroid_px;
                a.texts.push(TextAnnotation {
                    timestamp: crate::ros2::Time::of(h.capture_ns),
                    position: px(x, y),
                    text: format!("cell {}: {}", c.id, height_text(c, &t.unit)),
                    font_size: 12.0,
                    text_color: colour.into(),
                    background_color: SHADE.into(),
                });
            }
            Ok(vec![("left", to_cdr(&a)?)])
        }
        _ => Ok(Vec::new()),
    }
}

/// The namespace, id and position of each marker of a `MarkerArray` (tests read them).
#[cfg(test)]
pub(crate) fn decode_markers(cdr: &[u8]) -> Result<Vec<(String, i32, [f64; 3])>, String> {
    let a: MarkerArray = crate::ros2::from_cdr(cdr, MARKER_ARRAY.name)?;
    Ok(a.markers
        .into_iter()
        .map(|m| {
            let p = m.pose.position;
            (m.ns, m.id, [p.x, p.y, p.z])
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros2::from_cdr;

    #[test]
    fn cells_are_outlined_over_both_views_at_their_pixel_centres() {
        use schemas::msg::Message;
        let cell = |id, x0| schemas::Cell {
            id,
            area: 4,
            centroid: [x0 as f64 + 0.5, 0.5],
            bbox: schemas::BoundingBox {
                x0,
                y0: 0,
                x1: x0 + 1,
                y1: 1,
            },
            contour: vec![[x0, 0], [x0 + 1, 0], [x0 + 1, 1], [x0, 1]],
            perimeter: 4.0,
        };
        let lists = schemas::CellLists {
            left: vec![cell(1, 10), cell(2, 20)],
            right: vec![cell(1, 7)],
        };
        let e = lists.encode();
        let h = FrameHeader {
            capture_ns: 2_000_000_003,
            ..e.header
        };
        let got = annotations(MessageKind::CellList, &h, &e.to_vec()).unwrap();
        let sides: Vec<_> = got.iter().map(|g| g.0).collect();
        assert_eq!(sides, ["left", "right"]);
        let left: ImageAnnotations = from_cdr(&got[0].1, IMAGE_ANNOTATIONS.name).unwrap();
        assert_eq!(left.points.len(), 2);
        assert_eq!(left.points[0].r#type, 2, "a closed outline");
        assert_eq!(left.points[0].points[0], Point2 { x: 10.5, y: 0.5 });
        assert_eq!(left.texts[1].text, "cell 2");
        assert_eq!(
            left.texts[1].timestamp,
            crate::ros2::Time::of(2_000_000_003)
        );
        let right: ImageAnnotations = from_cdr(&got[1].1, IMAGE_ANNOTATIONS.name).unwrap();
        assert_eq!(right.points.len(), 1);
    }

    #[test]
    fn an_ellipses_outline_gives_its_axes_and_angle() {
        let (a, b, t) = (30.0f64, 12.0f64, 0.5f64);
        let outline: Vec<[f64; 3]> = (0..720)
            .map(|i| {
                let s = i as f64 / 720.0 * std::f64::consts::TAU;
                let (x, y) = (a * s.cos(), b * s.sin());
                [
                    100.0 + x * t.cos() - y * t.sin(),
                    -50.0 + x * t.sin() + y * t.cos(),
                    9.0,
                ]
            })
            .collect();
        let (c, [ga, gb], gt) = footprint(&outline).unwrap();
        assert!(
            (c[0] - 100.0).abs() < 1e-9 && (c[1] + 50.0).abs() < 1e-9,
            "{c:?}"
        );
        // Evenly spaced in angle, not in length: within 2 % of the axes.
        assert!(
            (ga / a - 1.0).abs() < 0.02 && (gb / b - 1.0).abs() < 0.02,
            "{ga} {gb}"
        );
        assert!((gt - t).abs() < 1e-6, "{gt}");
    }

    #[test]
    fn the_frame_tree_puts_the_cameras_half_a_baseline_apart_under_a_z_up_stage() {
        let m: TfMessage = from_cdr(&tf_static(0.002, 5).unwrap(), TF_MESSAGE.name).unwrap();
        let names: Vec<(&str, &str)> = m
            .transforms
            .iter()
            .map(|t| (t.header.frame_id.as_str(), t.child_frame_id.as_str()))
            .collect();
        assert_eq!(
            names,
            [
                (STAGE_FRAME, STEREO_FRAME),
                (STEREO_FRAME, "left_camera_optical_frame"),
                (STEREO_FRAME, "right_camera_optical_frame")
            ]
        );
        assert_eq!(m.transforms[1].transform.translation.x, -0.001);
        assert_eq!(m.transforms[2].transform.translation.x, 0.001);
        // Half a turn about X: the view's Z (down the microscope) is the stage's −Z.
        let q = m.transforms[0].transform.rotation;
        assert_eq!((q.x, q.w), (1.0, 0.0));
    }
}
