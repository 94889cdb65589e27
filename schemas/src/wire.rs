//! What travels on an edge of the process graph: a fixed `#[repr(C)]` [`FrameHeader`] and a
//! byte payload of any length, both in shared memory. The header says how to read the
//! payload ([`PixelFormat`], [`MessageKind`]); images travel row by row, `stride` bytes per
//! row, little-endian for multi-byte pixels.

#[cfg(feature = "iceoryx2")]
use iceoryx2::prelude::ZeroCopySend;
use serde::{Deserialize, Serialize};

/// How the pixels of an image payload are laid out.
#[repr(u32)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PixelFormat {
    /// Not an image (cell lists, point clouds, targets).
    None = 0,
    /// 8-bit grey.
    Mono8 = 1,
    /// 32-bit float, one channel (disparity; NaN = invalid).
    F32 = 2,
    /// 32-bit unsigned labels.
    U32 = 3,
    /// 8-bit RGB.
    Rgb8 = 4,
}

impl PixelFormat {
    /// Bytes per pixel (0 for non-images).
    pub fn bytes_per_pixel(self) -> usize {
        match self {
            Self::None => 0,
            Self::Mono8 => 1,
            Self::F32 | Self::U32 => 4,
            Self::Rgb8 => 3,
        }
    }

    /// The format with this wire value.
    pub fn from_u32(v: u32) -> Option<Self> {
        Some(match v {
            0 => Self::None,
            1 => Self::Mono8,
            2 => Self::F32,
            3 => Self::U32,
            4 => Self::Rgb8,
            _ => return None,
        })
    }
}

/// What a message on an edge is; an input accepts only the kind its node expects.
#[repr(u32)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MessageKind {
    /// A rectified or raw stereo pair: the left image, then the right, same format and size.
    StereoFrame = 1,
    /// One image.
    Image = 2,
    /// A disparity map (F32).
    Disparity = 3,
    /// Left and right label images (U32), left first.
    Labels = 4,
    /// Cells of both views (JSON).
    CellList = 5,
    /// Points `[x, y, z]` as F32 and colours as RGB8 (see [`crate::PointCloud`]).
    PointCloud = 6,
    /// Per-cell 3D targets for the manipulator (JSON).
    Targets = 7,
    /// Left- and right-based full-frame maps (F32), left first; recordings and custom
    /// nodes may carry it, the built-in nodes send tiles.
    DisparityPair = 8,
    /// Where the manipulator's pipette is and what it is doing (JSON).
    ManipulatorState = 9,
    /// Disparity maps of a frame in tiles: the whole frame, or one crop per cell pair.
    DisparityTiles = 10,
    /// The cells followed over time: one id per physical cell, fused measurements (JSON).
    Tracks = 11,
}

impl MessageKind {
    /// Every kind, in wire order.
    pub const ALL: [MessageKind; 11] = [
        Self::StereoFrame,
        Self::Image,
        Self::Disparity,
        Self::Labels,
        Self::CellList,
        Self::PointCloud,
        Self::Targets,
        Self::DisparityPair,
        Self::ManipulatorState,
        Self::DisparityTiles,
        Self::Tracks,
    ];

    /// Its name in launch files and recordings (`stereo-frame`, `disparity`, …).
    pub fn name(self) -> &'static str {
        match self {
            Self::StereoFrame => "stereo-frame",
            Self::Image => "image",
            Self::Disparity => "disparity",
            Self::Labels => "labels",
            Self::CellList => "cell-list",
            Self::PointCloud => "point-cloud",
            Self::Targets => "targets",
            Self::DisparityPair => "disparity-pair",
            Self::ManipulatorState => "manipulator-state",
            Self::DisparityTiles => "disparity-tiles",
            Self::Tracks => "tracks",
        }
    }

    /// The kind with this [`name`](Self::name).
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }

    /// The kind with this wire value.
    pub fn from_u32(v: u32) -> Option<Self> {
        Some(match v {
            1 => Self::StereoFrame,
            2 => Self::Image,
            3 => Self::Disparity,
            4 => Self::Labels,
            5 => Self::CellList,
            6 => Self::PointCloud,
            7 => Self::Targets,
            8 => Self::DisparityPair,
            9 => Self::ManipulatorState,
            10 => Self::DisparityTiles,
            11 => Self::Tracks,
            _ => return None,
        })
    }
}

/// The header in front of every payload on an edge.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
// The transport sends it as iceoryx2's user header; the algorithm crates need no transport.
#[cfg_attr(feature = "iceoryx2", derive(ZeroCopySend))]
pub struct FrameHeader {
    /// Frame number from the capture node; every derived message keeps its frame's number.
    pub sequence: u64,
    /// Capture time, nanoseconds since the Unix epoch.
    pub capture_ns: u64,
    /// Messages the writer sent on this edge before this one, set by the transport: a gap
    /// is a message dropped on this edge, while a gap in `sequence` may be upstream.
    pub edge_sequence: u64,
    /// Image width in pixels (0 for non-images).
    pub width: u32,
    /// Image height in pixels (0 for non-images).
    pub height: u32,
    /// Bytes per image row in the payload.
    pub stride: u32,
    /// [`PixelFormat`] as its wire value.
    pub format: u32,
    /// [`MessageKind`] as its wire value.
    pub kind: u32,
    /// Images in the payload (2 for a stereo frame or a pair of maps).
    pub images: u32,
}

impl Default for FrameHeader {
    fn default() -> Self {
        Self {
            sequence: 0,
            capture_ns: 0,
            edge_sequence: 0,
            width: 0,
            height: 0,
            stride: 0,
            format: PixelFormat::None as u32,
            kind: MessageKind::Image as u32,
            images: 0,
        }
    }
}

impl FrameHeader {
    /// A header for `images` images of `width × height` in `format`, rows packed.
    pub fn image(
        kind: MessageKind,
        format: PixelFormat,
        width: usize,
        height: usize,
        images: u32,
    ) -> Self {
        Self {
            width: width as u32,
            height: height as u32,
            stride: (width * format.bytes_per_pixel()) as u32,
            format: format as u32,
            kind: kind as u32,
            images,
            ..Self::default()
        }
    }

    /// Payload bytes the header describes for images (0 for non-images).
    pub fn image_bytes(&self) -> usize {
        self.stride as usize * self.height as usize * self.images as usize
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_is_plain_old_data_of_a_fixed_layout() {
        assert_eq!(core::mem::size_of::<FrameHeader>(), 48);
        assert_eq!(core::mem::align_of::<FrameHeader>(), 8);
        let h = FrameHeader::image(MessageKind::StereoFrame, PixelFormat::Mono8, 640, 480, 2);
        assert_eq!(h.image_bytes(), 2 * 640 * 480);
        assert_eq!(
            MessageKind::from_u32(h.kind),
            Some(MessageKind::StereoFrame)
        );
        assert_eq!(PixelFormat::from_u32(h.format), Some(PixelFormat::Mono8));
        assert_eq!(PixelFormat::from_u32(99), None);
        assert_eq!(MessageKind::from_u32(0), None);
        for k in MessageKind::ALL {
            assert_eq!(MessageKind::from_u32(k as u32), Some(k));
            assert_eq!(MessageKind::from_name(k.name()), Some(k));
            let serde_name = serde_json::to_string(&k).unwrap();
            assert_eq!(serde_name.trim_matches('"'), k.name());
        }
    }

    #[test]
    fn planes_round_trip_and_mismatches_are_refused() {
        let a =
            crate::Plane::from_vec(3, 2, vec![1.5f32, -2.0, f32::NAN, 0.0, 7.25, 1e-3]).unwrap();
        let b = crate::Plane::from_vec(3, 2, vec![9f32; 6]).unwrap();
        let (h, len) = planes_header(MessageKind::DisparityPair, &[&a, &b]);
        assert_eq!(len, 2 * 6 * 4);
        let mut buf = vec![0u8; len];
        write_planes(&[&a, &b], &mut buf);
        let back: Vec<crate::Plane<f32>> = read_planes(&h, &buf).unwrap();
        assert_eq!(back.len(), 2);
        let bits = |p: &crate::Plane<f32>| p.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!((bits(&back[0]), bits(&back[1])), (bits(&a), bits(&b)));
        assert!(read_planes::<u8>(&h, &buf).is_err());
        assert!(read_planes::<f32>(&h, &buf[..len - 1]).is_err());
    }
}

/// Why a payload cannot be read as the message its header announces.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("bad {kind:?} message: {reason}")]
pub struct WireError {
    /// The kind announced.
    pub kind: Option<MessageKind>,
    /// What does not fit.
    pub reason: String,
}

/// A pixel type that travels as little-endian bytes (plain data: on a little-endian machine
/// a plane's bytes are its wire bytes).
pub trait WirePixel: Copy + Default + bytemuck::Pod {
    /// Its format.
    const FORMAT: PixelFormat;
    /// Writes one pixel.
    fn put(self, out: &mut [u8]);
    /// Reads one pixel.
    fn get(b: &[u8]) -> Self;
}

impl WirePixel for u8 {
    const FORMAT: PixelFormat = PixelFormat::Mono8;
    fn put(self, out: &mut [u8]) {
        out[0] = self;
    }
    fn get(b: &[u8]) -> Self {
        b[0]
    }
}

impl WirePixel for f32 {
    const FORMAT: PixelFormat = PixelFormat::F32;
    fn put(self, out: &mut [u8]) {
        out[..4].copy_from_slice(&self.to_le_bytes());
    }
    fn get(b: &[u8]) -> Self {
        f32::from_le_bytes([b[0], b[1], b[2], b[3]])
    }
}

impl WirePixel for u32 {
    const FORMAT: PixelFormat = PixelFormat::U32;
    fn put(self, out: &mut [u8]) {
        out[..4].copy_from_slice(&self.to_le_bytes());
    }
    fn get(b: &[u8]) -> Self {
        u32::from_le_bytes([b[0], b[1], b[2], b[3]])
    }
}

/// The header for `planes` (all the same size) as message `kind`, and their byte length.
pub fn planes_header<T: WirePixel>(
    kind: MessageKind,
    planes: &[&crate::Plane<T>],
) -> (FrameHeader, usize) {
    let (w, h) = planes.first().map_or((0, 0), |p| (p.width, p.height));
    let hd = FrameHeader::image(kind, T::FORMAT, w, h, planes.len() as u32);
    (hd, hd.image_bytes())
}

/// Writes `planes` row by row into `out` (sized by [`planes_header`]).
pub fn write_planes<T: WirePixel>(planes: &[&crate::Plane<T>], out: &mut [u8]) {
    let bpp = T::FORMAT.bytes_per_pixel();
    let mut rest = out;
    for p in planes {
        let (this, next) = rest.split_at_mut(p.data.len() * bpp);
        if cfg!(target_endian = "little") {
            // One copy: pixel by pixel, a 1280×1024 label plane took milliseconds.
            this.copy_from_slice(bytemuck::cast_slice(&p.data));
        } else {
            for (o, &v) in this.chunks_exact_mut(bpp).zip(&p.data) {
                v.put(o);
            }
        }
        rest = next;
    }
}

/// Reads the planes of a message whose header says `T`'s format.
pub fn read_planes<T: WirePixel>(
    header: &FrameHeader,
    payload: &[u8],
) -> Result<Vec<crate::Plane<T>>, WireError> {
    let kind = MessageKind::from_u32(header.kind);
    let bad = |reason: String| WireError { kind, reason };
    if PixelFormat::from_u32(header.format) != Some(T::FORMAT) {
        return Err(bad(format!(
            "pixel format {} where {:?} was expected",
            header.format,
            T::FORMAT
        )));
    }
    let bpp = T::FORMAT.bytes_per_pixel();
    let (w, h) = (header.width as usize, header.height as usize);
    if header.stride as usize != w * bpp || payload.len() != header.image_bytes() {
        return Err(bad(format!(
            "{} payload bytes for {} image(s) of {w}×{h} (stride {})",
            payload.len(),
            header.images,
            header.stride
        )));
    }
    Ok(payload
        .chunks_exact((w * h * bpp).max(1))
        .take(header.images as usize)
        .map(|c| {
            // Converted pixel by pixel into a new plane: as fast as a zeroed plane and one
            // copy of the bytes (measured in the triangulate node).
            let data = c.chunks_exact(bpp).map(T::get).collect();
            crate::Plane::from_vec(w, h, data).expect("size")
        })
        .collect())
}

/// The header of a JSON message of `kind` (cell lists, targets).
pub fn json_header(kind: MessageKind) -> FrameHeader {
    FrameHeader {
        kind: kind as u32,
        format: PixelFormat::None as u32,
        ..FrameHeader::default()
    }
}

/// Bytes per point of a point-cloud message: `x, y, z` as little-endian f32, then `r, g, b`.
pub const CLOUD_POINT_BYTES: usize = 15;
