//! Every message an edge carries, as a type with its wire codec, defined once.
//!
//! A [`Message`] knows its [`MessageKind`], how to become an edge's bytes ([`Encoded`]: the
//! header and a writer that fills the payload in place, in shared memory when the
//! transport lends it) and how to come back from them. Nodes, the recorder, the viewer and
//! the tests all read and write edges through these impls, so a cloud or a set of disparity
//! tiles is encoded in one place and decoded in one place.
//!
//! | kind | type | payload |
//! |---|---|---|
//! | `stereo-frame` | [`StereoFrame`] | left then right image, Mono8 |
//! | `image` | [`Image`] | one image, Mono8 or RGB8 |
//! | `disparity` | [`Disparity`] | one F32 map, +inf = invalid |
//! | `labels` | [`Labels`] | left then right U32 label image |
//! | `cell-list` | [`CellLists`] | JSON |
//! | `point-cloud` | [`Cloud`] | 15 bytes a point: x, y, z F32, r, g, b |
//! | `targets` | [`Targets`] | JSON |
//! | `disparity-pair` | [`DisparityPair`] | left- then right-based F32 map (no built-in node sends it) |
//! | `manipulator-state` | [`ManipulatorState`] | JSON |
//! | `disparity-tiles` | [`DisparityTiles`] | binary tile records, then every tile's F32 map |

use crate::wire::{
    CLOUD_POINT_BYTES, FrameHeader, MessageKind, PixelFormat, WireError, WirePixel, json_header,
    planes_header, read_planes, write_planes,
};
use crate::{Cell, Cell3, DisparityMap, DisparityRange, Plane, ValidationFigures};
use serde::{Deserialize, Serialize};

/// Fills a payload in place.
type Writer<'a> = Box<dyn Fn(&mut [u8]) + 'a>;

/// One message as an edge carries it: its header (the frame stamp is the sender's to set)
/// and a writer that fills exactly `len` payload bytes.
pub struct Encoded<'a> {
    /// Header: kind, pixel format, sizes.
    pub header: FrameHeader,
    /// Payload bytes.
    pub len: usize,
    write: Writer<'a>,
}

impl<'a> Encoded<'a> {
    /// A message whose payload `write` fills (`len` bytes).
    pub fn new(header: FrameHeader, len: usize, write: impl Fn(&mut [u8]) + 'a) -> Self {
        Self {
            header,
            len,
            write: Box::new(write),
        }
    }

    /// A message whose payload is already in memory.
    pub fn bytes(header: FrameHeader, bytes: Vec<u8>) -> Self {
        let len = bytes.len();
        Self::new(header, len, move |out| out.copy_from_slice(&bytes))
    }

    /// Fills `out` (`len` bytes) with the payload.
    pub fn write(&self, out: &mut [u8]) {
        (self.write)(out)
    }

    /// The payload as a vector.
    pub fn to_vec(&self) -> Vec<u8> {
        let mut v = vec![0u8; self.len];
        self.write(&mut v);
        v
    }
}

/// A message type of the graph: its kind and its wire codec.
pub trait Message: Sized {
    /// The kind its header carries and launch files name.
    const KIND: MessageKind;
    /// Its header (stamp left zero) and payload.
    fn encode(&self) -> Encoded<'_>;
    /// Reads it back; a header of another kind, or a payload that does not fit the header,
    /// is an error that says what does not fit.
    fn decode(header: &FrameHeader, payload: &[u8]) -> Result<Self, WireError>;
}

/// What a node's port holds: a message (a required port) or `Option` of one (an optional
/// port, absent when nothing is connected to it or nothing was sent on it).
pub trait Slot: Sized {
    /// The message the port carries (`M` for both `M` and `Option<M>`).
    type Msg: Message;
    /// The message kind of the port.
    const PORT_KIND: MessageKind;
    /// Whether the port may stay unconnected (inputs) or unsent (outputs).
    const OPTIONAL: bool;
    /// The port's value from its message, if one came.
    fn take(msg: Option<(&FrameHeader, &[u8])>) -> Result<Self, WireError>;
    /// The message to send, if any.
    fn encoded(&self) -> Option<Encoded<'_>>;
}

impl<T: Message> Slot for T {
    type Msg = T;
    const PORT_KIND: MessageKind = T::KIND;
    const OPTIONAL: bool = false;
    fn take(msg: Option<(&FrameHeader, &[u8])>) -> Result<Self, WireError> {
        match msg {
            Some((h, p)) => T::decode(h, p),
            None => Err(WireError {
                kind: Some(T::KIND),
                reason: "no message on a required port".into(),
            }),
        }
    }
    fn encoded(&self) -> Option<Encoded<'_>> {
        Some(self.encode())
    }
}

impl<T: Message> Slot for Option<T> {
    type Msg = T;
    const PORT_KIND: MessageKind = T::KIND;
    const OPTIONAL: bool = true;
    fn take(msg: Option<(&FrameHeader, &[u8])>) -> Result<Self, WireError> {
        msg.map(|(h, p)| T::decode(h, p)).transpose()
    }
    fn encoded(&self) -> Option<Encoded<'_>> {
        self.as_ref().map(Message::encode)
    }
}

fn wrong_kind(want: MessageKind, h: &FrameHeader) -> Result<(), WireError> {
    if h.kind == want as u32 {
        return Ok(());
    }
    Err(WireError {
        kind: Some(want),
        reason: format!(
            "the header says {}",
            MessageKind::from_u32(h.kind)
                .map_or_else(|| format!("kind {}", h.kind), |k| k.name().to_string())
        ),
    })
}

fn encode_planes<'a, T: WirePixel>(kind: MessageKind, planes: Vec<&'a Plane<T>>) -> Encoded<'a> {
    // One header describes every image: a pair of two sizes is a bug of its sender.
    assert!(
        planes
            .windows(2)
            .all(|p| (p[0].width, p[0].height) == (p[1].width, p[1].height)),
        "the images of a {} message differ in size",
        kind.name()
    );
    let (h, len) = planes_header(kind, &planes);
    Encoded::new(h, len, move |out| write_planes(&planes, out))
}

fn decode_n<T: WirePixel, const N: usize>(
    kind: MessageKind,
    h: &FrameHeader,
    payload: &[u8],
) -> Result<[Plane<T>; N], WireError> {
    wrong_kind(kind, h)?;
    let v = read_planes::<T>(h, payload)?;
    let n = v.len();
    v.try_into().map_err(|_| WireError {
        kind: Some(kind),
        reason: format!("{n} image(s), not {N}"),
    })
}

/// A message of planes: its fields in wire order, each a plane of one pixel type.
macro_rules! planes_message {
    ($(#[$m:meta])* $name:ident, $kind:expr, $px:ty, { $($(#[$fm:meta])* $field:ident),+ }) => {
        $(#[$m])*
        #[derive(Clone, Debug, PartialEq)]
        pub struct $name {
            $($(#[$fm])* pub $field: Plane<$px>,)+
        }

        impl Message for $name {
            const KIND: MessageKind = $kind;
            fn encode(&self) -> Encoded<'_> {
                encode_planes(Self::KIND, vec![$(&self.$field),+])
            }
            fn decode(h: &FrameHeader, payload: &[u8]) -> Result<Self, WireError> {
                let [$($field),+] = decode_n(Self::KIND, h, payload)?;
                Ok(Self { $($field),+ })
            }
        }
    };
}

planes_message!(
    /// A stereo pair: left and right grey images of one size (raw or rectified).
    StereoFrame, MessageKind::StereoFrame, u8, {
        /// Left view.
        left,
        /// Right view.
        right
    }
);

planes_message!(
    /// Both views' label images: 0 background, cell `i` labelled `i`.
    Labels, MessageKind::Labels, u32, {
        /// Left view.
        left,
        /// Right view.
        right
    }
);

planes_message!(
    /// One full-frame disparity map (left-based; +inf where invalid).
    Disparity, MessageKind::Disparity, f32, {
        /// The map.
        map
    }
);

planes_message!(
    /// Left- and right-based full-frame maps.
    DisparityPair, MessageKind::DisparityPair, f32, {
        /// Left-based map.
        left,
        /// Right-based map.
        right
    }
);

impl WirePixel for [u8; 3] {
    const FORMAT: PixelFormat = PixelFormat::Rgb8;
    fn put(self, out: &mut [u8]) {
        out[..3].copy_from_slice(&self);
    }
    fn get(b: &[u8]) -> Self {
        [b[0], b[1], b[2]]
    }
}

/// One image: grey (masks, single views) or colour.
#[derive(Clone, Debug, PartialEq)]
pub enum Image {
    /// 8-bit grey.
    Grey(Plane<u8>),
    /// 8-bit RGB.
    Rgb(Plane<[u8; 3]>),
}

/// A grey image in colour (grey replicated).
pub fn grey_to_rgb(p: &Plane<u8>) -> Plane<[u8; 3]> {
    Plane {
        width: p.width,
        height: p.height,
        data: p.data.iter().map(|&g| [g, g, g]).collect(),
    }
}

impl Image {
    /// The image in colour (grey replicated).
    pub fn to_rgb(&self) -> Plane<[u8; 3]> {
        match self {
            Image::Rgb(p) => p.clone(),
            Image::Grey(p) => grey_to_rgb(p),
        }
    }

    /// Its size.
    pub fn size(&self) -> (usize, usize) {
        match self {
            Image::Grey(p) => (p.width, p.height),
            Image::Rgb(p) => (p.width, p.height),
        }
    }
}

impl Message for Image {
    const KIND: MessageKind = MessageKind::Image;
    fn encode(&self) -> Encoded<'_> {
        match self {
            Image::Grey(p) => encode_planes(Self::KIND, vec![p]),
            Image::Rgb(p) => encode_planes(Self::KIND, vec![p]),
        }
    }
    fn decode(h: &FrameHeader, payload: &[u8]) -> Result<Self, WireError> {
        if PixelFormat::from_u32(h.format) == Some(PixelFormat::Rgb8) {
            let [p] = decode_n(Self::KIND, h, payload)?;
            Ok(Image::Rgb(p))
        } else {
            let [p] = decode_n(Self::KIND, h, payload)?;
            Ok(Image::Grey(p))
        }
    }
}

macro_rules! json_message {
    ($t:ty, $kind:expr, $what:literal) => {
        impl Message for $t {
            const KIND: MessageKind = $kind;
            fn encode(&self) -> Encoded<'_> {
                let bytes = serde_json::to_vec(self).expect("a message serialises");
                Encoded::bytes(json_header(Self::KIND), bytes)
            }
            fn decode(h: &FrameHeader, payload: &[u8]) -> Result<Self, WireError> {
                wrong_kind(Self::KIND, h)?;
                serde_json::from_slice(payload).map_err(|e| WireError {
                    kind: Some(Self::KIND),
                    reason: format!(concat!($what, ": {}"), e),
                })
            }
        }
    };
}

/// The cells both views hold, as the segment node sends them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CellLists {
    /// Cells of the left view.
    pub left: Vec<Cell>,
    /// Cells of the right view.
    pub right: Vec<Cell>,
}

json_message!(CellLists, MessageKind::CellList, "cell list");

/// What the triangulate node sends on `targets` and the manipulator bridge serves: the 3D
/// cells of one frame (JSON).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Targets {
    /// Frame number.
    pub frame: u64,
    /// Capture time, ns since the Unix epoch.
    pub capture_ns: u64,
    /// Unit of every coordinate.
    pub unit: String,
    /// Per-cell 3D figures.
    pub cells: Vec<Cell3>,
    /// The substrate's disparity plane fitted to the background around the cells (absent
    /// when the background is too smooth to fix one: each cell's ring stands in).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub substrate: Option<crate::DisparityPlane>,
}

json_message!(Targets, MessageKind::Targets, "targets");

/// Where a track is in its life.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TrackState {
    /// Seen in too few frames yet to be taken for a cell (it may be noise).
    Tentative,
    /// A cell seen in enough frames: its id holds for as long as it is seen.
    Confirmed,
    /// Not seen lately (covered, out of view): kept, predicted, for a while, so that the
    /// cell gets its id back when it reappears.
    Lost,
}

/// One physical cell followed over time: what the track node sends per cell.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Track {
    /// The cell's id for the whole run: never given to another cell, never reused.
    pub id: u32,
    /// Tentative, confirmed or lost.
    pub state: TrackState,
    /// Frames since the track was born (this frame included).
    pub age: u32,
    /// Frames since it was last seen (0: seen in this frame).
    pub missed: u32,
    /// Frames the fused height and volume rest on (outliers and doubtful frames left out).
    pub frames_used: u32,
    /// Fused 3D centroid `[X, Y, Z]` (in `unit`); predicted while the cell is lost.
    pub position: [f64; 3],
    /// Standard error of `position` along X and Y.
    pub position_std: f64,
    /// Velocity `[X, Y, Z]`, `unit` per second.
    pub velocity: [f64; 3],
    /// Fused height above the substrate (`None`: no frame gave one yet).
    pub height: Option<f64>,
    /// Standard error of `height`.
    pub height_std: Option<f64>,
    /// Fused volume.
    pub volume: f64,
    /// Standard error of `volume`.
    pub volume_std: f64,
    /// Whether the fused height can be trusted (sure to 2.5 %, from trusted frames).
    pub trusted: bool,
    /// This frame's measurement of the cell (absent while it is lost); its `id` is the
    /// cell's index in this frame's segmentation, which changes from frame to frame.
    pub cell: Option<Cell3>,
}

/// What the track node sends on `tracks` once per frame (JSON): every live track.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Tracks {
    /// Frame number.
    pub frame: u64,
    /// Capture time, ns since the Unix epoch.
    pub capture_ns: u64,
    /// Unit of every coordinate.
    pub unit: String,
    /// The common shift of every cell since the last frame `[X, Y, Z]` (a stage move).
    pub shift: [f64; 3],
    /// The tracks, by id.
    pub tracks: Vec<Track>,
    /// The frame's substrate plane, as the targets gave it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub substrate: Option<crate::DisparityPlane>,
}

json_message!(Tracks, MessageKind::Tracks, "tracks");

/// A planned pipette path as the bridge reports it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PathPlan {
    /// `approach`, `retract` or `goto`.
    pub goal: String,
    /// The target cell's id in the frame it was planned in (approach only).
    pub target: Option<u32>,
    /// The frame whose scene it was planned in.
    pub frame: u64,
    /// Tip waypoints `[X, Y, Z]` (camera frame), µm, the start first.
    pub waypoints: Vec<[f64; 3]>,
    /// Legs from this waypoint on run along the pipette axis (target exempt).
    pub axial_from: u32,
    /// Where it ends (the injection point of an approach).
    pub end: [f64; 3],
    /// Length, µm.
    pub length: f64,
    /// Least distance between the body and a cell other than the target, µm (none
    /// without such cells).
    pub min_clearance: Option<f64>,
}

/// What the manipulator bridge sends on `state` once per frame (JSON). Positions are in
/// the camera frame of the triangulation, `[X, Y, Z]` in µm (X right and Y down in the left
/// image, Z the depth from the cameras, origin midway between them), as every cell.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ManipulatorState {
    /// Frame number of the scene it answers.
    pub frame: u64,
    /// Capture time of that frame, ns since the Unix epoch.
    pub capture_ns: u64,
    /// The device (`sim`, `MP-285 on …`, or `none` when it is missing).
    pub device: String,
    /// `idle`, `moving`, `arrived`, `stopped`, `blocked` or `error`.
    pub status: String,
    /// Tip position `[X, Y, Z]`, µm.
    pub tip: [f64; 3],
    /// Pipette elevation above the horizontal, degrees.
    pub elevation_deg: f64,
    /// Direction the body extends to from the tip, degrees from +x.
    pub azimuth_deg: f64,
    /// Clearance the planner keeps, µm.
    pub clearance: f64,
    /// Tip samples `[t, X, Y, Z]` since the previous message (t: seconds since the bridge
    /// started), at the bridge's polling rate.
    pub trajectory: Vec<[f64; 4]>,
    /// The plan being executed or last executed.
    pub plan: Option<PathPlan>,
    /// Objects of this frame taken for the pipette itself (they touch its body).
    pub ignored: Vec<u32>,
}

json_message!(
    ManipulatorState,
    MessageKind::ManipulatorState,
    "manipulator state"
);

/// One point of a [`Cloud`]: position in the calibration's unit and colour.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CloudPoint {
    /// `[x, y, z]`.
    pub xyz: [f32; 3],
    /// `[r, g, b]`.
    pub rgb: [u8; 3],
}

/// A point cloud as it travels: valid points only, f32 coordinates.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Cloud {
    /// The points, in the left image's row-major order.
    pub points: Vec<CloudPoint>,
}

impl Cloud {
    /// The wire form of a triangulated cloud (coordinates rounded to f32).
    pub fn from_points(cloud: &crate::PointCloud) -> Self {
        Self {
            points: cloud
                .points
                .iter()
                .map(|p| CloudPoint {
                    xyz: [p.x as f32, p.y as f32, p.z as f32],
                    rgb: p.rgb,
                })
                .collect(),
        }
    }
}

impl Message for Cloud {
    const KIND: MessageKind = MessageKind::PointCloud;
    fn encode(&self) -> Encoded<'_> {
        let n = self.points.len();
        Encoded::new(cloud_header(n), n * CLOUD_POINT_BYTES, move |b| {
            for (p, o) in self
                .points
                .iter()
                .zip(b.chunks_exact_mut(CLOUD_POINT_BYTES))
            {
                for (k, v) in p.xyz.iter().enumerate() {
                    o[4 * k..4 * k + 4].copy_from_slice(&v.to_le_bytes());
                }
                o[12..15].copy_from_slice(&p.rgb);
            }
        })
    }
    fn decode(h: &FrameHeader, payload: &[u8]) -> Result<Self, WireError> {
        wrong_kind(Self::KIND, h)?;
        if payload.len() != h.width as usize * CLOUD_POINT_BYTES {
            return Err(WireError {
                kind: Some(Self::KIND),
                reason: format!("{} bytes for {} points", payload.len(), h.width),
            });
        }
        let f = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        Ok(Self {
            points: payload
                .chunks_exact(CLOUD_POINT_BYTES)
                .map(|b| CloudPoint {
                    xyz: [f(&b[0..4]), f(&b[4..8]), f(&b[8..12])],
                    rgb: [b[12], b[13], b[14]],
                })
                .collect(),
        })
    }
}

/// The header of a point-cloud message of `points` points (one row of
/// [`CLOUD_POINT_BYTES`] each).
pub fn cloud_header(points: usize) -> FrameHeader {
    FrameHeader {
        width: points as u32,
        height: 1,
        stride: CLOUD_POINT_BYTES as u32,
        format: PixelFormat::F32 as u32,
        kind: MessageKind::PointCloud as u32,
        images: 0,
        ..FrameHeader::default()
    }
}

/// Which view's pixels a disparity map indexes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Side {
    /// Left-based: left pixel `x` matches right `x − d`.
    Left,
    /// Right-based: right pixel `xr` matches left `xr + d`.
    Right,
}

/// One rectangle of a frame matched as its own stereo problem, and its map.
#[derive(Clone, Debug, PartialEq)]
pub struct DisparityTile {
    /// Left column of the rectangle in the frame (the same rectangle in both views).
    pub x: usize,
    /// Top row of the rectangle.
    pub y: usize,
    /// Disparities searched in it (the frame's range, narrowed to what the tile can hold).
    pub range: DisparityRange,
    /// The cell pair it was cut around, `(left id, right id)`; `None` for the whole frame.
    pub cells: Option<(u32, u32)>,
    /// The tile's map (`width × height` of the rectangle); 0×0 for a pair too narrow to
    /// match.
    pub map: DisparityMap,
    /// Pixel × disparity evaluations its matcher made (the left and the right tile of a
    /// pair carry the same count: add one side only).
    pub evaluations: u64,
    /// The LR check's figures, once the tile has been validated.
    pub figures: Option<ValidationFigures>,
}

impl DisparityTile {
    /// The same tile (place, range, cells, evaluations, figures) with another map of its
    /// size.
    pub fn with_map(&self, map: DisparityMap) -> Self {
        Self {
            x: self.x,
            y: self.y,
            range: self.range,
            cells: self.cells,
            map,
            evaluations: self.evaluations,
            figures: self.figures,
        }
    }
}

/// Disparity maps of a frame in tiles: one tile for the whole frame, or one per cell pair
/// (the cells' crops: the method matches only the cells).
#[derive(Clone, Debug, PartialEq)]
pub struct DisparityTiles {
    /// Frame width.
    pub width: usize,
    /// Frame height.
    pub height: usize,
    /// Which view the maps are based on.
    pub side: Side,
    /// The range the matcher was asked for.
    pub range: DisparityRange,
    /// Pixels matched around each cell (0 for a whole-frame tile).
    pub margin: u8,
    /// The tiles, in the order of the left cells they were cut around.
    pub tiles: Vec<DisparityTile>,
}

/// Bytes before the tile records: side, range and margin.
const TILES_PREAMBLE: usize = 16;
/// Bytes of one tile record.
const TILE_RECORD: usize = 88;

/// Bytes of a tiles message before its maps (the preamble and `tiles` records).
pub fn tile_records_len(tiles: usize) -> usize {
    TILES_PREAMBLE + TILE_RECORD * tiles
}

impl DisparityTiles {
    /// One tile holding the whole frame's `map`.
    pub fn whole(side: Side, range: DisparityRange, map: DisparityMap, evaluations: u64) -> Self {
        Self {
            width: map.width,
            height: map.height,
            side,
            range,
            margin: 0,
            tiles: vec![DisparityTile {
                x: 0,
                y: 0,
                range,
                cells: None,
                map,
                evaluations,
                figures: None,
            }],
        }
    }

    /// The same frame, range and margin with `tiles` based on `side` in place of these (one
    /// for each, in order): what validation and post-processing make tile by tile.
    pub fn with_tiles(&self, side: Side, tiles: Vec<DisparityTile>) -> Self {
        debug_assert_eq!(tiles.len(), self.tiles.len(), "one tile for each");
        Self {
            width: self.width,
            height: self.height,
            side,
            range: self.range,
            margin: self.margin,
            tiles,
        }
    }

    /// The tiles pasted into one frame-size map, later tiles over earlier ones; +inf
    /// outside every tile.
    pub fn paste(&self) -> DisparityMap {
        let mut out = Plane::filled(self.width, self.height, crate::INVALID_DISPARITY);
        for t in &self.tiles {
            for y in 0..t.map.height {
                out.row_mut(t.y + y)[t.x..t.x + t.map.width].copy_from_slice(t.map.row(y));
            }
        }
        out
    }

    /// Pixels handed to the matcher, summed over tiles.
    pub fn matched_pixels(&self) -> u64 {
        self.tiles.iter().map(|t| t.map.len() as u64).sum()
    }

    /// Evaluations of every tile's matcher.
    pub fn evaluations(&self) -> u64 {
        self.tiles.iter().map(|t| t.evaluations).sum()
    }
}

fn put_u32(b: &mut [u8], at: &mut usize, v: u32) {
    b[*at..*at + 4].copy_from_slice(&v.to_le_bytes());
    *at += 4;
}
fn put_u64(b: &mut [u8], at: &mut usize, v: u64) {
    b[*at..*at + 8].copy_from_slice(&v.to_le_bytes());
    *at += 8;
}
fn get_u32(b: &[u8], at: &mut usize) -> u32 {
    let v = u32::from_le_bytes(b[*at..*at + 4].try_into().expect("4 bytes"));
    *at += 4;
    v
}
fn get_u64(b: &[u8], at: &mut usize) -> u64 {
    let v = u64::from_le_bytes(b[*at..*at + 8].try_into().expect("8 bytes"));
    *at += 8;
    v
}

impl Message for DisparityTiles {
    const KIND: MessageKind = MessageKind::DisparityTiles;
    fn encode(&self) -> Encoded<'_> {
        let header = FrameHeader {
            width: self.width as u32,
            height: self.height as u32,
            stride: 0,
            format: PixelFormat::F32 as u32,
            kind: Self::KIND as u32,
            images: self.tiles.len() as u32,
            ..FrameHeader::default()
        };
        let records = tile_records_len(self.tiles.len());
        let len = records + 4 * self.matched_pixels() as usize;
        Encoded::new(header, len, move |b| {
            let mut at = 0;
            put_u32(b, &mut at, matches!(self.side, Side::Right) as u32);
            put_u32(b, &mut at, self.range.min as u32);
            put_u32(b, &mut at, self.range.max as u32);
            put_u32(b, &mut at, self.margin as u32);
            for t in &self.tiles {
                let (l, r) = t.cells.unwrap_or((0, 0));
                for v in [t.x, t.y, t.map.width, t.map.height] {
                    put_u32(b, &mut at, v as u32);
                }
                put_u32(b, &mut at, t.range.min as u32);
                put_u32(b, &mut at, t.range.max as u32);
                put_u32(b, &mut at, l);
                put_u32(b, &mut at, r);
                put_u64(b, &mut at, t.evaluations);
                let f = t.figures.unwrap_or_default();
                put_u64(b, &mut at, f.matched);
                for v in [
                    f.consistent_exact,
                    f.off_by_one,
                    f.off_by_more,
                    f.consistent_within_tolerance,
                ] {
                    put_u64(b, &mut at, v.to_bits());
                }
                put_u32(b, &mut at, f.tolerance);
                put_u32(b, &mut at, t.figures.is_some() as u32);
            }
            let mut rest = &mut b[at..];
            for t in &self.tiles {
                let (this, next) = rest.split_at_mut(4 * t.map.len());
                for (o, v) in this.chunks_exact_mut(4).zip(&t.map.data) {
                    o.copy_from_slice(&v.to_le_bytes());
                }
                rest = next;
            }
        })
    }

    fn decode(h: &FrameHeader, b: &[u8]) -> Result<Self, WireError> {
        wrong_kind(Self::KIND, h)?;
        let bad = |reason: String| WireError {
            kind: Some(Self::KIND),
            reason,
        };
        if PixelFormat::from_u32(h.format) != Some(PixelFormat::F32) {
            return Err(bad(format!(
                "pixel format {} where F32 was expected",
                h.format
            )));
        }
        let n = h.images as usize;
        let records = n
            .checked_mul(TILE_RECORD)
            .and_then(|r| r.checked_add(TILES_PREAMBLE))
            .filter(|&r| r <= b.len())
            .ok_or_else(|| bad(format!("{} bytes cannot hold {n} tile records", b.len())))?;
        let (width, height) = (h.width as usize, h.height as usize);
        let mut at = 0;
        let side = match get_u32(b, &mut at) {
            0 => Side::Left,
            1 => Side::Right,
            s => return Err(bad(format!("side {s} is neither 0 (left) nor 1 (right)"))),
        };
        let range = DisparityRange::new(get_u32(b, &mut at) as i32, get_u32(b, &mut at) as i32);
        let margin = get_u32(b, &mut at).min(255) as u8;
        let mut tiles = Vec::with_capacity(n);
        let mut data = records;
        for k in 0..n {
            let [x, y, w, th] = [0; 4].map(|_| get_u32(b, &mut at) as usize);
            let trange =
                DisparityRange::new(get_u32(b, &mut at) as i32, get_u32(b, &mut at) as i32);
            let (l, r) = (get_u32(b, &mut at), get_u32(b, &mut at));
            let evaluations = get_u64(b, &mut at);
            let matched = get_u64(b, &mut at);
            let [exact, one, more, within] = [0; 4].map(|_| f64::from_bits(get_u64(b, &mut at)));
            let tolerance = get_u32(b, &mut at);
            let has_figures = get_u32(b, &mut at) != 0;
            if x.checked_add(w).is_none_or(|e| e > width)
                || y.checked_add(th).is_none_or(|e| e > height)
            {
                return Err(bad(format!(
                    "tile {k} ({w}×{th} at {x}, {y}) reaches outside the {width}×{height} frame"
                )));
            }
            let px = w
                .checked_mul(th)
                .and_then(|n| n.checked_mul(4))
                .and_then(|n| b.get(data..data.checked_add(n)?))
                .ok_or_else(|| bad(format!("{} bytes end inside tile {k}'s map", b.len())))?;
            let bytes = px.len();
            data += bytes;
            tiles.push(DisparityTile {
                x,
                y,
                range: trange,
                cells: (l != 0 || r != 0).then_some((l, r)),
                map: Plane::from_vec(w, th, px.chunks_exact(4).map(f32::get).collect())
                    .expect("size"),
                evaluations,
                figures: has_figures.then_some(ValidationFigures {
                    matched,
                    consistent_exact: exact,
                    off_by_one: one,
                    off_by_more: more,
                    consistent_within_tolerance: within,
                    tolerance,
                }),
            });
        }
        if data != b.len() {
            return Err(bad(format!(
                "{} bytes where the tiles take {data}",
                b.len()
            )));
        }
        Ok(Self {
            width,
            height,
            side,
            range,
            margin,
            tiles,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip<M: Message + PartialEq + std::fmt::Debug>(m: &M) {
        let e = m.encode();
        assert_eq!(MessageKind::from_u32(e.header.kind), Some(M::KIND));
        let bytes = e.to_vec();
        assert_eq!(bytes.len(), e.len);
        // The transport hands the encoder a loan it has not cleared: every byte must be
        // written, whatever the loan held before.
        for old in [0x00u8, 0xA5, 0xFF] {
            let mut loan = vec![old; e.len];
            e.write(&mut loan);
            assert_eq!(loan, bytes, "bytes left unwritten over {old:#x}");
        }
        let back = M::decode(&e.header, &bytes).unwrap();
        assert_eq!(&back, m);
    }

    #[test]
    fn every_message_comes_back_as_it_went() {
        let grey = Plane::from_vec(3, 2, vec![1u8, 2, 3, 4, 5, 6]).unwrap();
        let map = Plane::from_vec(2, 2, vec![1.5f32, f32::INFINITY, -2.0, 0.25]).unwrap();
        round_trip(&StereoFrame {
            left: grey.clone(),
            right: grey.clone(),
        });
        round_trip(&Image::Grey(grey.clone()));
        round_trip(&Image::Rgb(Plane::filled(2, 1, [7u8, 8, 9])));
        round_trip(&Disparity { map: map.clone() });
        round_trip(&DisparityPair {
            left: map.clone(),
            right: map.clone(),
        });
        round_trip(&Labels {
            left: Plane::filled(2, 2, 3u32),
            right: Plane::filled(2, 2, 0u32),
        });
        round_trip(&Cloud {
            points: vec![CloudPoint {
                xyz: [1.0, -2.5, 3.25],
                rgb: [1, 2, 3],
            }],
        });
        round_trip(&CellLists {
            left: vec![],
            right: vec![],
        });
        let mut tiles = DisparityTiles::whole(Side::Left, DisparityRange::new(-4, 12), map, 16);
        tiles.width = 9;
        tiles.height = 7;
        tiles.margin = 8;
        tiles.tiles.push(DisparityTile {
            x: 5,
            y: 4,
            range: DisparityRange::new(-2, 3),
            cells: Some((3, 4)),
            map: Plane::filled(4, 3, 0.125),
            evaluations: 60,
            figures: Some(ValidationFigures {
                matched: 12,
                consistent_exact: 0.1,
                off_by_one: 1.0 / 3.0,
                off_by_more: 0.2,
                consistent_within_tolerance: 0.7,
                tolerance: 1,
            }),
        });
        tiles.tiles.push(DisparityTile {
            x: 0,
            y: 0,
            range: DisparityRange::new(0, 1),
            cells: Some((5, 1)),
            map: Plane::filled(0, 0, 0.0),
            evaluations: 0,
            figures: None,
        });
        round_trip(&tiles);
        let pasted = tiles.paste();
        assert_eq!((pasted.width, pasted.height), (9, 7));
        assert_eq!(*pasted.get(0, 1), -2.0);
        assert_eq!(*pasted.get(8, 6), 0.125);
        assert!(pasted.get(4, 6).is_infinite());
    }

    #[test]
    fn a_message_of_another_kind_or_size_is_refused() {
        let f = StereoFrame {
            left: Plane::filled(2, 2, 0u8),
            right: Plane::filled(2, 2, 0u8),
        };
        let e = f.encode();
        let bytes = e.to_vec();
        let err = Labels::decode(&e.header, &bytes).unwrap_err();
        assert!(err.reason.contains("stereo-frame"), "{err}");
        assert!(StereoFrame::decode(&e.header, &bytes[1..]).is_err());
        let t = DisparityTiles::whole(
            Side::Right,
            DisparityRange::new(0, 3),
            Plane::filled(2, 2, 1.0),
            0,
        );
        let e = t.encode();
        let mut bytes = e.to_vec();
        assert!(DisparityTiles::decode(&e.header, &bytes[..bytes.len() - 4]).is_err());
        let mut h = e.header;
        h.width = 1;
        assert!(
            DisparityTiles::decode(&h, &bytes)
                .unwrap_err()
                .reason
                .contains("outside")
        );
        bytes[0] = 7;
        assert!(DisparityTiles::decode(&e.header, &bytes).is_err());
        let none: Option<Disparity> = Slot::take(None).unwrap();
        assert!(none.is_none());
        assert!(<Disparity as Slot>::take(None).is_err());
    }
}
