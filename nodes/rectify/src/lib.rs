//! Stereo rectification for microstereo: [`RemapLut`] resamples whole images (bilinear)
//! from a table built once from the rig's [`Rectifier`] (the `calibration` crate's
//! Bouguet rectification, as OpenCV's `stereoRectify`, or a microscope's onto its stage
//! plane), and the rectify node applies both views' tables to every frame.

pub mod node;

use calibration::stereo::Rectifier;

/// The resampling tables of both views of `rect`, left and right, at the calibrated size.
pub fn luts(rect: &Rectifier) -> (RemapLut, RemapLut) {
    let (w, h) = rect.size();
    (
        RemapLut::new(rect, false, w, h),
        RemapLut::new(rect, true, w, h),
    )
}

/// A precomputed resampling table for one view.
#[derive(Clone, Debug)]
pub struct RemapLut {
    width: usize,
    height: usize,
    /// Per output pixel: source `(x, y)` (NaN where the rectifier has none).
    map: Vec<(f32, f32)>,
}

impl RemapLut {
    /// The table of view `right` for output images of `width × height`.
    pub fn new(rect: &Rectifier, right: bool, width: usize, height: usize) -> Self {
        let map = (0..height)
            .flat_map(|v| (0..width).map(move |u| (u, v)))
            .map(|(u, v)| {
                let (x, y) = rect.source(right, u as f64, v as f64);
                (x as f32, y as f32)
            })
            .collect();
        Self { width, height, map }
    }

    /// Resamples `img` (bilinear); a pixel whose source lies outside the view repeats the
    /// view's nearest edge, as OpenCV's `BORDER_REPLICATE`: a black border would be an
    /// edge that segmentation and matching take for texture.
    pub fn apply(&self, img: &schemas::Plane<u8>) -> schemas::Plane<u8> {
        let (w, h) = (img.width as f32, img.height as f32);
        let data = self
            .map
            .iter()
            .map(|&(x, y)| {
                if !(x.is_finite() && y.is_finite()) {
                    return 0;
                }
                let (x, y) = (x.clamp(0.0, w - 1.0), y.clamp(0.0, h - 1.0));
                let (x0, y0) = (x.floor() as usize, y.floor() as usize);
                let (x1, y1) = ((x0 + 1).min(img.width - 1), (y0 + 1).min(img.height - 1));
                let (fx, fy) = (x - x0 as f32, y - y0 as f32);
                let g = |xx, yy| *img.get(xx, yy) as f32;
                let top = g(x0, y0) * (1.0 - fx) + g(x1, y0) * fx;
                let bot = g(x0, y1) * (1.0 - fx) + g(x1, y1) * fx;
                (top * (1.0 - fy) + bot * fy).round().clamp(0.0, 255.0) as u8
            })
            .collect();
        schemas::Plane::from_vec(self.width, self.height, data).expect("size")
    }
}
