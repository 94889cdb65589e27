//! Image files in: grey for matching and segmenting, colour for the points.

use schemas::Plane;
use std::path::Path;

/// An input image in both forms the pipeline needs.
#[derive(Clone, Debug, PartialEq)]
pub struct LoadedImage {
    /// Luminance, for matching.
    pub grey: Plane<u8>,
    /// Colour (grey replicated for grey files), for point colours.
    pub rgb: Plane<[u8; 3]>,
}

/// Loads an image file (PNG, JPEG or TIFF) as grey and colour planes; `what` names it in
/// errors ("left image", …).
pub fn load(path: &Path, what: &str) -> Result<LoadedImage, String> {
    if !path.exists() {
        return Err(format!(
            "{what} '{}' does not exist; check the path",
            path.display()
        ));
    }
    let unreadable =
        |e: &dyn std::fmt::Display| format!("{what} '{}' cannot be read: {e}", path.display());
    let img = image::ImageReader::open(path)
        .map_err(|e| unreadable(&e))?
        .with_guessed_format()
        .map_err(|e| unreadable(&e))?
        .decode()
        .map_err(|e| unreadable(&format!("{e} (expected PNG, JPEG or TIFF)")))?;
    let g = img.to_luma8();
    let c = img.to_rgb8();
    let (w, h) = (g.width() as usize, g.height() as usize);
    Ok(LoadedImage {
        grey: Plane::from_vec(w, h, g.into_raw()).expect("size"),
        rgb: Plane::from_vec(
            w,
            h,
            c.into_raw()
                .chunks_exact(3)
                .map(|p| [p[0], p[1], p[2]])
                .collect(),
        )
        .expect("size"),
    })
}
