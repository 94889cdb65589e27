//! File formats of microstereo's results: PFM and 16-bit PNG disparity maps (in and out),
//! masks, colour-mapped maps with a legend, binary PLY point clouds ([`render`]: label images,
//! cell overlays and histograms). Every error names the file and the fix.

pub mod atomic;
pub mod outputs;
pub mod render;

use image::{ImageBuffer, Luma, Rgb, RgbImage};
use schemas::{Cloud, DisparityMap, INVALID_DISPARITY, LengthUnit, Mask, Plane};
use std::fs::File;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};

/// A failure reading or writing a file, with the path it concerns.
#[derive(Debug, thiserror::Error)]
pub enum IoError {
    /// The file does not exist.
    #[error("{what} '{path}' does not exist; check the path")]
    Missing {
        /// Role of the file ("left image", …).
        what: String,
        /// The path given.
        path: PathBuf,
    },
    /// The file exists but cannot be decoded.
    #[error("{what} '{path}' cannot be read: {reason}")]
    Unreadable {
        /// Role of the file.
        what: String,
        /// The path given.
        path: PathBuf,
        /// Decoder message.
        reason: String,
    },
    /// Writing failed.
    #[error("cannot write '{path}': {reason}")]
    Write {
        /// Output path.
        path: PathBuf,
        /// OS or encoder message.
        reason: String,
    },
}

fn unreadable(what: &str, path: &Path, reason: impl ToString) -> IoError {
    IoError::Unreadable {
        what: what.into(),
        path: path.into(),
        reason: reason.to_string(),
    }
}

fn write_err(path: &Path, reason: impl ToString) -> IoError {
    IoError::Write {
        path: path.into(),
        reason: reason.to_string(),
    }
}

/// Writes a Middlebury PFM (grey, little-endian, bottom row first; invalid = +inf).
pub fn write_pfm(path: &Path, map: &DisparityMap) -> Result<(), IoError> {
    let mut body = Vec::with_capacity(map.len() * 4 + 32);
    body.extend_from_slice(format!("Pf\n{} {}\n-1.0\n", map.width, map.height).as_bytes());
    for y in (0..map.height).rev() {
        for v in map.row(y) {
            body.extend_from_slice(&v.to_le_bytes());
        }
    }
    atomic::write_bytes(path, &body)
}

/// Largest PFM side read, px: far past any camera, and small enough that the pixel count
/// cannot overflow.
const PFM_MAX_SIDE: usize = 1 << 16;

/// Reads a grey PFM; non-finite values stay non-finite (unknown). The header is checked
/// against the file before anything is allocated: a size past [`PFM_MAX_SIDE`] or one that
/// the file's length does not hold is refused.
pub fn read_pfm(path: &Path, what: &str) -> Result<DisparityMap, IoError> {
    let f = File::open(path).map_err(|_| IoError::Missing {
        what: what.into(),
        path: path.into(),
    })?;
    let file_len = f.metadata().map_err(|e| unreadable(what, path, e))?.len();
    let mut r = BufReader::new(f);
    let mut tokens = Vec::new();
    let mut line = String::new();
    let mut header_len = 0u64;
    while tokens.len() < 4 {
        line.clear();
        // A header line is a few characters: a binary file without newlines is not read
        // whole to find one.
        let n = (&mut r)
            .take(256)
            .read_line(&mut line)
            .map_err(|e| unreadable(what, path, e))?;
        if n == 0 {
            return Err(unreadable(what, path, "truncated PFM header"));
        }
        if !line.ends_with('\n') && n == 256 {
            return Err(unreadable(
                what,
                path,
                "not a PFM (no header line within 256 bytes)",
            ));
        }
        header_len += n as u64;
        tokens.extend(line.split_whitespace().map(String::from));
    }
    if tokens[0] != "Pf" {
        return Err(unreadable(
            what,
            path,
            format!("not a grey PFM (magic '{}', expected 'Pf')", tokens[0]),
        ));
    }
    let parse = |s: &str| {
        s.parse::<usize>()
            .ok()
            .filter(|v| (1..=PFM_MAX_SIDE).contains(v))
            .ok_or_else(|| {
                unreadable(
                    what,
                    path,
                    format!("bad PFM size '{s}' (a whole number of pixels, 1 to {PFM_MAX_SIDE})"),
                )
            })
    };
    let (w, h) = (parse(&tokens[1])?, parse(&tokens[2])?);
    let scale: f32 = tokens[3]
        .parse()
        .ok()
        .filter(|s: &f32| s.is_finite() && *s != 0.0)
        .ok_or_else(|| {
            unreadable(
                what,
                path,
                format!("bad PFM scale '{}' (a non-zero number)", tokens[3]),
            )
        })?;
    // At most 2¹⁶ × 2¹⁶ × 4 bytes: no overflow.
    let need = (w * h * 4) as u64;
    if file_len.saturating_sub(header_len) < need {
        return Err(unreadable(
            what,
            path,
            format!(
                "truncated PFM data (the header says {w}×{h} floats, {need} bytes; the file holds {})",
                file_len.saturating_sub(header_len)
            ),
        ));
    }
    let mut raw = vec![0u8; w * h * 4];
    r.read_exact(&mut raw).map_err(|_| {
        unreadable(
            what,
            path,
            format!("truncated PFM data (expected {w}×{h} floats)"),
        )
    })?;
    let mut data = vec![0f32; w * h];
    for (i, c) in raw.chunks_exact(4).enumerate() {
        let b = [c[0], c[1], c[2], c[3]];
        let v = if scale < 0.0 {
            f32::from_le_bytes(b)
        } else {
            f32::from_be_bytes(b)
        };
        let (x, yb) = (i % w, i / w);
        data[(h - 1 - yb) * w + x] = v;
    }
    Ok(Plane::from_vec(w, h, data).expect("size"))
}

/// Reads a disparity map from PFM, or from a PNG holding `d · scale` (0 = unknown).
///
/// With `scale = None` a 16-bit PNG is read with scale 256 (our `disparity.png`) and an
/// 8-bit one with scale 1.
pub fn read_disparity(
    path: &Path,
    scale: Option<f32>,
    what: &str,
) -> Result<DisparityMap, IoError> {
    if !path.exists() {
        return Err(IoError::Missing {
            what: what.into(),
            path: path.into(),
        });
    }
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    if ext == "pfm" {
        let mut m = read_pfm(path, what)?;
        if let Some(s) = scale {
            m.data.iter_mut().for_each(|v| *v /= s);
        }
        return Ok(m);
    }
    let img = image::open(path).map_err(|e| unreadable(what, path, e))?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let (vals, default_scale): (Vec<u16>, f32) = match img {
        image::DynamicImage::ImageLuma16(b) => (b.into_raw(), 256.0),
        other => (
            other
                .to_luma8()
                .into_raw()
                .into_iter()
                .map(u16::from)
                .collect(),
            1.0,
        ),
    };
    let s = scale.unwrap_or(default_scale);
    let data = vals
        .into_iter()
        .map(|v| {
            if v == 0 {
                INVALID_DISPARITY
            } else {
                v as f32 / s
            }
        })
        .collect();
    Ok(Plane::from_vec(w, h, data).expect("size"))
}

/// Writes `disparity.png`: 16-bit, `d · 256`, 0 = invalid. Returns how many valid pixels
/// could not be stored (negative or ≥ 256 disparities).
pub fn write_disparity_png(path: &Path, map: &DisparityMap) -> Result<usize, IoError> {
    let mut lost = 0;
    let data: Vec<u16> = map
        .data
        .iter()
        .map(|&d| {
            if !d.is_finite() {
                return 0;
            }
            let v = (d * 256.0).round();
            if (1.0..=65535.0).contains(&v) {
                v as u16
            } else {
                lost += 1;
                0
            }
        })
        .collect();
    let img: ImageBuffer<Luma<u16>, Vec<u16>> =
        ImageBuffer::from_raw(map.width as u32, map.height as u32, data).expect("size");
    atomic::write_atomically(path, |tmp| img.save(tmp).map_err(|e| write_err(path, e)))?;
    Ok(lost)
}

/// Writes a 0/255 mask as an 8-bit PNG.
pub fn write_mask_png(path: &Path, mask: &Mask) -> Result<(), IoError> {
    let img: ImageBuffer<Luma<u8>, Vec<u8>> =
        ImageBuffer::from_raw(mask.width as u32, mask.height as u32, mask.data.clone())
            .expect("size");
    atomic::write_atomically(path, |tmp| img.save(tmp).map_err(|e| write_err(path, e)))
}

/// Turbo-like colour map (blue = far/small disparity, red = near/large), 0..1 in.
pub fn colormap(t: f32) -> [u8; 3] {
    // Piecewise-linear through the Turbo colour map's key colours.
    const KEYS: [[f32; 3]; 7] = [
        [48.0, 18.0, 59.0],
        [70.0, 131.0, 253.0],
        [27.0, 229.0, 181.0],
        [164.0, 252.0, 60.0],
        [251.0, 185.0, 56.0],
        [228.0, 70.0, 12.0],
        [122.0, 4.0, 3.0],
    ];
    let t = t.clamp(0.0, 1.0) * (KEYS.len() - 1) as f32;
    let i = (t.floor() as usize).min(KEYS.len() - 2);
    let f = t - i as f32;
    let mut out = [0u8; 3];
    for c in 0..3 {
        out[c] = (KEYS[i][c] + f * (KEYS[i + 1][c] - KEYS[i][c])).round() as u8;
    }
    out
}

/// 3×5 bitmap glyphs for the legend's numbers.
fn glyph(c: char) -> Option<[u8; 5]> {
    Some(match c {
        '0' => [0b111, 0b101, 0b101, 0b101, 0b111],
        '1' => [0b010, 0b110, 0b010, 0b010, 0b111],
        '2' => [0b111, 0b001, 0b111, 0b100, 0b111],
        '3' => [0b111, 0b001, 0b111, 0b001, 0b111],
        '4' => [0b101, 0b101, 0b111, 0b001, 0b001],
        '5' => [0b111, 0b100, 0b111, 0b001, 0b111],
        '6' => [0b111, 0b100, 0b111, 0b101, 0b111],
        '7' => [0b111, 0b001, 0b010, 0b010, 0b010],
        '8' => [0b111, 0b101, 0b111, 0b101, 0b111],
        '9' => [0b111, 0b101, 0b111, 0b001, 0b111],
        '-' => [0b000, 0b000, 0b111, 0b000, 0b000],
        '.' => [0b000, 0b000, 0b000, 0b000, 0b010],
        ' ' => [0; 5],
        _ => return None,
    })
}

fn draw_text(img: &mut RgbImage, x0: u32, y0: u32, text: &str, scale: u32, colour: [u8; 3]) {
    let mut x = x0;
    for c in text.chars() {
        if let Some(g) = glyph(c) {
            for (gy, bits) in g.iter().enumerate() {
                for gx in 0..3 {
                    if bits & (0b100 >> gx) != 0 {
                        for sy in 0..scale {
                            for sx in 0..scale {
                                let (px, py) = (x + gx * scale + sx, y0 + gy as u32 * scale + sy);
                                if px < img.width() && py < img.height() {
                                    img.put_pixel(px, py, Rgb(colour));
                                }
                            }
                        }
                    }
                }
            }
        }
        x += 4 * scale;
    }
}

/// Pseudo-colour rendering of a disparity map with a legend bar (min at the bottom, max at
/// the top, labelled); invalid pixels are black.
pub fn disparity_color(map: &DisparityMap, lo: f32, hi: f32) -> RgbImage {
    let (w, h) = (map.width as u32, map.height as u32);
    let bar = 60u32.max(w / 12);
    let mut img = RgbImage::from_pixel(w + bar, h, Rgb([255, 255, 255]));
    let span = (hi - lo).max(1e-6);
    for y in 0..h {
        for x in 0..w {
            let d = *map.get(x as usize, y as usize);
            let c = if d.is_finite() {
                colormap((d - lo) / span)
            } else {
                [0, 0, 0]
            };
            img.put_pixel(x, y, Rgb(c));
        }
    }
    let scale = if h >= 300 { 2 } else { 1 };
    let text_h = 5 * scale + 4;
    let (top, bottom) = (text_h + 2, h.saturating_sub(text_h + 2));
    for y in top..bottom.max(top) {
        let t = 1.0 - (y - top) as f32 / (bottom - top).max(1) as f32;
        for x in w + 8..w + 8 + bar / 3 {
            img.put_pixel(x, y, Rgb(colormap(t)));
        }
    }
    draw_text(&mut img, w + 4, 2, &format!("{hi:.1}"), scale, [0, 0, 0]);
    draw_text(
        &mut img,
        w + 4,
        bottom + 3,
        &format!("{lo:.1}"),
        scale,
        [0, 0, 0],
    );
    img
}

/// Writes the colour rendering to a PNG.
pub fn write_color_png(path: &Path, img: &RgbImage) -> Result<(), IoError> {
    atomic::write_atomically(path, |tmp| img.save(tmp).map_err(|e| write_err(path, e)))
}

/// Writes a binary little-endian PLY point cloud (float x y z, uchar red green blue).
pub fn write_ply(path: &Path, cloud: &Cloud, unit: LengthUnit) -> Result<(), IoError> {
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment microstereo point cloud, unit {}\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
        unit.symbol(),
        cloud.points.len()
    );
    let mut body = Vec::with_capacity(header.len() + cloud.points.len() * 15);
    body.extend_from_slice(header.as_bytes());
    for p in &cloud.points {
        for v in p.xyz {
            body.extend_from_slice(&v.to_le_bytes());
        }
        body.extend_from_slice(&p.rgb);
    }
    atomic::write_bytes(path, &body)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pfm_round_trip_keeps_inf_and_orientation() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.pfm");
        let m = Plane::from_vec(3, 2, vec![1.0, 2.5, INVALID_DISPARITY, -4.0, 5.0, 6.0]).unwrap();
        write_pfm(&p, &m).unwrap();
        let back = read_pfm(&p, "map").unwrap();
        assert_eq!(back.width, 3);
        assert_eq!(back.data[..2], m.data[..2]);
        assert!(back.data[2].is_infinite());
        assert_eq!(back.data[3..], m.data[3..]);
    }

    #[test]
    fn png_disparity_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.png");
        let m = Plane::from_vec(3, 1, vec![1.25, INVALID_DISPARITY, -2.0]).unwrap();
        let lost = write_disparity_png(&p, &m).unwrap();
        assert_eq!(lost, 1);
        let back = read_disparity(&p, None, "map").unwrap();
        assert_eq!(back.data[0], 1.25);
        assert!(!back.data[1].is_finite() && !back.data[2].is_finite());
    }

    #[test]
    fn truncated_pfm_is_a_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t.pfm");
        std::fs::write(&p, b"Pf\n4 4\n-1.0\n\0\0\0\0").unwrap();
        let e = read_pfm(&p, "disparity").unwrap_err().to_string();
        assert!(e.contains("truncated PFM data"), "{e}");
    }

    #[test]
    fn a_pfm_header_is_checked_before_anything_is_allocated() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("h.pfm");
        let cases: [(&[u8], &str); 7] = [
            (
                b"Pf\n100000 100000\n-1.0\n\0\0\0\0",
                "bad PFM size '100000'",
            ),
            (b"Pf\n4294967296 4294967296\n-1.0\n", "bad PFM size"),
            (b"Pf\n60000 60000\n-1.0\n\0\0\0\0", "truncated PFM data"),
            (b"Pf\n0 4\n-1.0\n", "bad PFM size '0'"),
            (b"Pf\n-3 4\n-1.0\n", "bad PFM size '-3'"),
            (b"Pf\n1 1\nNaN\n\0\0\0\0", "bad PFM scale 'NaN'"),
            (&[b'P'; 4096], "no header line"),
        ];
        for (bytes, want) in cases {
            std::fs::write(&p, bytes).unwrap();
            let e = read_pfm(&p, "disparity").unwrap_err().to_string();
            assert!(e.contains(want), "{e} (wanted {want})");
        }
    }
}
