//! Two V4L2 cameras as a frame source (cargo feature `v4l`): each frame is the pair of
//! grey images whose driver timestamps lie closest, within `max_skew_ms`.

use schemas::{Plane, StereoFrame};
use serde::Deserialize;
use v4l::buffer::Type;
use v4l::io::traits::CaptureStream;
use v4l::prelude::*;
use v4l::video::Capture;

/// `params` of a `capture` node with `source = "v4l"`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraParams {
    /// `v4l`.
    pub source: String,
    /// Left camera device, e.g. `/dev/video0`.
    pub left: String,
    /// Right camera device.
    pub right: String,
    /// Requested width (the driver may pick another; both cameras must agree).
    #[serde(default = "default_width")]
    pub width: u32,
    /// Requested height.
    #[serde(default = "default_height")]
    pub height: u32,
    /// Largest time between the two images of a pair, ms.
    #[serde(default = "default_skew")]
    pub max_skew_ms: f64,
    /// Frames per second to pass on (all the cameras give without it).
    #[serde(default)]
    pub fps: Option<f64>,
}

fn default_width() -> u32 {
    640
}
fn default_height() -> u32 {
    480
}
fn default_skew() -> f64 {
    20.0
}

impl CameraParams {
    /// Reads a `params` table.
    pub fn from_table(t: &toml::Table) -> Result<Self, String> {
        runtime::registry::from_table(t)
    }
}

struct Camera {
    path: String,
    stream: MmapStream<'static>,
    format: v4l::Format,
    // The stream maps this device's buffers; it must outlive them.
    _device: Device,
}

impl std::fmt::Debug for Camera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Camera({})", self.path)
    }
}

impl Camera {
    fn open(path: &str, w: u32, h: u32) -> Result<Self, String> {
        let device = Device::with_path(path).map_err(|e| {
            format!("cannot open camera '{path}': {e}; check the path (ls /dev/video*) and that no other program holds it")
        })?;
        let mut fmt = device
            .format()
            .map_err(|e| format!("camera '{path}': cannot read its format: {e}"))?;
        fmt.width = w;
        fmt.height = h;
        fmt.fourcc = v4l::FourCC::new(b"YUYV");
        let format = device
            .set_format(&fmt)
            .map_err(|e| format!("camera '{path}': cannot set {w}×{h}: {e}"))?;
        let grey = [v4l::FourCC::new(b"YUYV"), v4l::FourCC::new(b"GREY")];
        if !grey.contains(&format.fourcc) {
            return Err(format!(
                "camera '{path}' gives {}, but only YUYV or GREY can be read",
                format.fourcc
            ));
        }
        let stream = MmapStream::with_buffers(&device, Type::VideoCapture, 4)
            .map_err(|e| format!("camera '{path}': cannot start streaming: {e}"))?;
        Ok(Self {
            path: path.into(),
            stream,
            format,
            _device: device,
        })
    }

    /// The next image as grey levels and its driver timestamp (µs).
    fn next(&mut self) -> Result<(Plane<u8>, i64), String> {
        let (buf, meta) = self
            .stream
            .next()
            .map_err(|e| format!("camera '{}': {e}", self.path))?;
        let (w, h) = (self.format.width as usize, self.format.height as usize);
        let stride = self.format.stride as usize;
        let yuyv = self.format.fourcc == v4l::FourCC::new(b"YUYV");
        let mut data = Vec::with_capacity(w * h);
        for y in 0..h {
            let row = buf
                .get(y * stride..)
                .ok_or_else(|| format!("camera '{}': a short frame", self.path))?;
            for x in 0..w {
                // YUYV keeps luminance in every other byte.
                data.push(if yuyv { row[2 * x] } else { row[x] });
            }
        }
        let t = meta.timestamp.sec * 1_000_000 + meta.timestamp.usec;
        Ok((Plane::from_vec(w, h, data).expect("size"), t))
    }
}

/// Pairs the frames of two cameras.
#[derive(Debug)]
pub struct CameraCapture {
    left: Camera,
    right: Camera,
    max_skew_us: i64,
}

impl CameraCapture {
    /// Opens both cameras; a missing one is an error naming it.
    pub fn new(p: &CameraParams) -> Result<Self, String> {
        let left = Camera::open(&p.left, p.width, p.height)?;
        let right = Camera::open(&p.right, p.width, p.height)?;
        if (left.format.width, left.format.height) != (right.format.width, right.format.height) {
            return Err(format!(
                "cameras '{}' and '{}' give {}×{} and {}×{}; they must agree",
                p.left,
                p.right,
                left.format.width,
                left.format.height,
                right.format.width,
                right.format.height
            ));
        }
        Ok(Self {
            left,
            right,
            max_skew_us: (p.max_skew_ms * 1000.0) as i64,
        })
    }
}

impl CameraCapture {
    /// The next pair whose images lie within `max_skew_ms` of each other.
    pub fn next_frame(&mut self) -> Result<StereoFrame, String> {
        let (mut l, mut tl) = self.left.next()?;
        let (mut r, mut tr) = self.right.next()?;
        // Drop the older image until the two are close enough (a few tries).
        for _ in 0..8 {
            if (tl - tr).abs() <= self.max_skew_us {
                break;
            }
            if tl < tr {
                (l, tl) = self.left.next()?;
            } else {
                (r, tr) = self.right.next()?;
            }
        }
        if (tl - tr).abs() > self.max_skew_us {
            return Err(format!(
                "the cameras drift apart: images {} ms apart after 8 tries; raise max_skew_ms or sync the cameras",
                (tl - tr).abs() as f64 / 1000.0
            ));
        }
        Ok(StereoFrame { left: l, right: r })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_camera_is_named_in_the_error() {
        let p = CameraParams {
            source: "v4l".into(),
            left: "/dev/video-microstereo-missing".into(),
            right: "/dev/video-microstereo-missing2".into(),
            width: 640,
            height: 480,
            max_skew_ms: 20.0,
            fps: None,
        };
        let e = CameraCapture::new(&p).unwrap_err();
        assert!(
            e.starts_with("cannot open camera '/dev/video-microstereo-missing'")
                && e.contains("ls /dev/video*"),
            "{e}"
        );
    }
}
