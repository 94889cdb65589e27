//! The stereo rig as calibrated: both cameras' intrinsics, distortion and relative pose
//! ([`StereoCalibration`], read from OpenCV's `FileStorage` YAML or a calibration file's
//! `[stereo]` table) and Bouguet's rectification of it ([`Rectification`], as OpenCV's
//! `stereoRectify`): both cameras turned by half the relative rotation and then onto the
//! baseline, so that epipolar lines become image rows, with one new camera matrix for both
//! views.

use nalgebra::{Matrix3, Rotation3, Vector3};

/// Intrinsics, distortion and relative pose of a stereo pair.
#[derive(Clone, Debug, PartialEq)]
pub struct StereoCalibration {
    /// Left camera matrix.
    pub k1: Matrix3<f64>,
    /// Left distortion `k1 k2 p1 p2 [k3]`.
    pub d1: Vec<f64>,
    /// Right camera matrix.
    pub k2: Matrix3<f64>,
    /// Right distortion.
    pub d2: Vec<f64>,
    /// Rotation from the left camera's frame to the right's.
    pub r: Matrix3<f64>,
    /// Translation from the left camera's frame to the right's.
    pub t: Vector3<f64>,
    /// Image size `(width, height)`.
    pub size: (usize, usize),
}

/// The numbers of an `!!opencv-matrix` named `key` in OpenCV YAML text.
fn opencv_matrix(text: &str, key: &str) -> Result<Vec<f64>, String> {
    let start = text
        .find(&format!("\n{key}:"))
        .ok_or_else(|| format!("no '{key}' matrix"))?;
    let rest = &text[start..];
    let data = rest
        .find("data:")
        .ok_or_else(|| format!("'{key}' has no data"))?;
    let open = rest[data..]
        .find('[')
        .ok_or_else(|| format!("'{key}': no '['"))?
        + data;
    let close = rest[open..]
        .find(']')
        .ok_or_else(|| format!("'{key}': no ']'"))?
        + open;
    rest[open + 1..close]
        .split(',')
        .map(|v| {
            v.trim()
                .parse::<f64>()
                .map_err(|e| format!("'{key}': '{}' is not a number: {e}", v.trim()))
        })
        .collect()
}

/// The `data: [...]` list under `key` in ROS camera_info YAML.
fn yaml_data(text: &str, key: &str) -> Result<Vec<f64>, String> {
    opencv_matrix(text, key)
}

fn scalar(text: &str, key: &str) -> Result<usize, String> {
    text.lines()
        .find_map(|l| l.strip_prefix(&format!("{key}:")))
        .ok_or_else(|| format!("no '{key}'"))?
        .trim()
        .parse()
        .map_err(|e| format!("'{key}': {e}"))
}

impl StereoCalibration {
    /// Reads OpenCV `FileStorage` YAML with K1, D1, K2, D2, R, T, image_width, image_height.
    pub fn from_opencv_yaml(text: &str) -> Result<Self, String> {
        let text = format!("\n{text}");
        let m3 = |k: &str| -> Result<Matrix3<f64>, String> {
            let v = opencv_matrix(&text, k)?;
            if v.len() != 9 {
                return Err(format!("'{k}' has {} numbers, a 3×3 matrix 9", v.len()));
            }
            Ok(Matrix3::from_row_slice(&v))
        };
        let dist = |k: &str| -> Result<Vec<f64>, String> {
            let v = opencv_matrix(&text, k)?;
            if !(4..=5).contains(&v.len()) {
                return Err(format!(
                    "'{k}' has {} coefficients; 4 or 5 are read",
                    v.len()
                ));
            }
            Ok(v)
        };
        let (k1, d1, k2, d2, r) = (m3("K1")?, dist("D1")?, m3("K2")?, dist("D2")?, m3("R")?);
        let t = opencv_matrix(&text, "T")?;
        if t.len() != 3 {
            return Err(format!("'T' has {} numbers, not 3", t.len()));
        }
        Ok(Self {
            k1,
            d1,
            k2,
            d2,
            r,
            t: Vector3::new(t[0], t[1], t[2]),
            size: (
                scalar(&text, "image_width")?,
                scalar(&text, "image_height")?,
            ),
        })
    }
}

/// The raw cameras as a calibration file's `[stereo]` table holds them (matrices row by
/// row): what `calibrate-stereo` writes and the rectifier reads.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StereoTable {
    /// Image width the cameras were calibrated at (px).
    pub width: usize,
    /// Image height (px).
    pub height: usize,
    /// Left camera matrix.
    pub k1: [f64; 9],
    /// Left distortion `k1 k2 p1 p2 [k3]`.
    pub d1: Vec<f64>,
    /// Right camera matrix.
    pub k2: [f64; 9],
    /// Right distortion.
    pub d2: Vec<f64>,
    /// Rotation from the left camera's frame to the right's.
    pub r: [f64; 9],
    /// Translation from the left camera's frame to the right's, in the file's `unit`.
    pub t: [f64; 3],
    /// The calibration's reprojection error (px), for the record.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rms: Option<f64>,
}

impl From<&StereoCalibration> for StereoTable {
    fn from(c: &StereoCalibration) -> Self {
        let rows = |m: &Matrix3<f64>| -> [f64; 9] { std::array::from_fn(|i| m[(i / 3, i % 3)]) };
        Self {
            width: c.size.0,
            height: c.size.1,
            k1: rows(&c.k1),
            d1: c.d1.clone(),
            k2: rows(&c.k2),
            d2: c.d2.clone(),
            r: rows(&c.r),
            t: [c.t.x, c.t.y, c.t.z],
            rms: None,
        }
    }
}

impl StereoTable {
    /// The calibration, checked: positive focal lengths, 4 or 5 distortion terms, a
    /// rotation for `r`, a translation that is not zero.
    pub fn calibration(&self) -> Result<StereoCalibration, String> {
        let k = |m: &[f64; 9], name: &str| -> Result<Matrix3<f64>, String> {
            let k = Matrix3::from_row_slice(m);
            if !(k[(0, 0)] > 0.0 && k[(1, 1)] > 0.0 && k.iter().all(|v| v.is_finite()))
                || k[(1, 0)] != 0.0
                || k[(2, 0)] != 0.0
                || k[(2, 1)] != 0.0
                || k[(2, 2)] != 1.0
            {
                return Err(format!(
                    "[stereo] {name} is not a camera matrix [fx, s, cx, 0, fy, cy, 0, 0, 1] with fx, fy > 0"
                ));
            }
            Ok(k)
        };
        for (d, name) in [(&self.d1, "d1"), (&self.d2, "d2")] {
            if !(4..=5).contains(&d.len()) || d.iter().any(|v| !v.is_finite()) {
                return Err(format!(
                    "[stereo] {name} has {} distortion terms; give k1 k2 p1 p2 [k3]",
                    d.len()
                ));
            }
        }
        let r = Matrix3::from_row_slice(&self.r);
        if (r * r.transpose() - Matrix3::identity()).norm() > 1e-6 || r.determinant() < 0.0 {
            return Err("[stereo] r is not a rotation (r·rᵀ must be the identity)".into());
        }
        let t = Vector3::from_row_slice(&self.t);
        if !(t.norm() > 0.0 && t.norm().is_finite()) {
            return Err("[stereo] t must be the cameras' (non-zero) offset".into());
        }
        if self.width < 2 || self.height < 2 {
            return Err("[stereo] width and height must be the calibrated image size".into());
        }
        Ok(StereoCalibration {
            k1: k(&self.k1, "k1")?,
            d1: self.d1.clone(),
            k2: k(&self.k2, "k2")?,
            d2: self.d2.clone(),
            r,
            t,
            size: (self.width, self.height),
        })
    }
}

/// Reads the raw cameras from `path`: microstereo's calibration file (TOML with a
/// `[stereo]` table) or OpenCV's stereo YAML (K1, D1, K2, D2, R, T).
pub fn read_stereo(path: &str) -> Result<StereoCalibration, String> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("cannot read calibration '{path}': {e}"))?;
    if text.trim_start().starts_with("%YAML") || text.contains("!!opencv-matrix") {
        return StereoCalibration::from_opencv_yaml(&text)
            .map_err(|e| format!("calibration '{path}' (OpenCV YAML): {e}"));
    }
    #[derive(serde::Deserialize)]
    struct OnlyStereo {
        stereo: Option<StereoTable>,
    }
    let f: OnlyStereo = toml::from_str(&text).map_err(|e| {
        format!("calibration '{path}' is neither microstereo's TOML nor OpenCV's YAML: {e}")
    })?;
    f.stereo
        .ok_or_else(|| {
            format!(
                "calibration '{path}' has no [stereo] table (the raw cameras): it describes rectified images only; make one with `microstereo calibrate-stereo` or import OpenCV's with `microstereo calibration import`"
            )
        })?
        .calibration()
        .map_err(|e| format!("calibration '{path}': {e}"))
}

/// What resamples a raw pair into rectified views: a bench rig's Bouguet rectification or
/// a microscope's onto its stage plane.
#[derive(Clone, Debug, PartialEq)]
pub enum Rectifier {
    /// Pinhole cameras turned onto their baseline.
    Bouguet(Rectification),
    /// A stereo microscope's views rectified onto the stage plane.
    Microscope(crate::microscope::Rig),
}

impl From<Rectification> for Rectifier {
    fn from(r: Rectification) -> Self {
        Rectifier::Bouguet(r)
    }
}

impl Rectifier {
    /// Where rectified pixel `(u, v)` of a view comes from in its raw image.
    pub fn source(&self, right: bool, u: f64, v: f64) -> (f64, f64) {
        match self {
            Rectifier::Bouguet(r) => r.source(right, u, v),
            Rectifier::Microscope(m) => m.source(right, u, v),
        }
    }

    /// The raw (and rectified) image size.
    pub fn size(&self) -> (usize, usize) {
        match self {
            Rectifier::Bouguet(r) => r.size(),
            Rectifier::Microscope(m) => (m.width, m.height),
        }
    }
}

/// Reads what rectifies raw pairs from `path`: a calibration file's `[microscope]` table
/// (`calibrate-microscope`), else the raw cameras as [`read_stereo`] reads them.
pub fn read_rectifier(path: &str) -> Result<Rectifier, String> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("cannot read calibration '{path}': {e}"))?;
    #[derive(serde::Deserialize)]
    struct OnlyMicroscope {
        microscope: Option<crate::microscope::Rig>,
    }
    if let Ok(OnlyMicroscope {
        microscope: Some(m),
    }) = toml::from_str(&text)
    {
        m.check()
            .map_err(|e| format!("calibration '{path}': {e}"))?;
        return Ok(Rectifier::Microscope(m));
    }
    read_stereo(path).map(|c| Rectifier::Bouguet(Rectification::bouguet(&c)))
}

/// Applies radial-tangential distortion `k1 k2 p1 p2 [k3]` to normalised coordinates (OpenCV's model).
pub fn distort(d: &[f64], x: f64, y: f64) -> (f64, f64) {
    let (k1, k2, p1, p2) = (d[0], d[1], d[2], d[3]);
    let k3 = d.get(4).copied().unwrap_or(0.0);
    let r2 = x * x + y * y;
    let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    (
        x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
        y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
    )
}

/// Inverts [`distort`] by fixed-point iteration (as OpenCV's `undistortPoints`).
fn undistort(d: &[f64], xd: f64, yd: f64) -> (f64, f64) {
    let (mut x, mut y) = (xd, yd);
    for _ in 0..20 {
        let (dx, dy) = distort(d, x, y);
        x += xd - dx;
        y += yd - dy;
    }
    (x, y)
}

/// Both views' rectifying rotations and the shared new camera.
#[derive(Clone, Debug, PartialEq)]
pub struct Rectification {
    /// Rotation applied to the left camera.
    pub r1: Matrix3<f64>,
    /// Rotation applied to the right camera.
    pub r2: Matrix3<f64>,
    /// Focal length of the rectified views, px.
    pub f: f64,
    /// Principal point of the rectified views `[cx, cy]` (the left view's cx).
    pub c: [f64; 2],
    /// The right rectified view's cx (differs from the left's in shifted set-ups).
    pub cx_right: f64,
    /// Baseline along the rectified x axis (`T` turned by `r2`), calibration units.
    pub baseline: f64,
    calib: StereoCalibration,
}

impl Rectification {
    /// Bouguet's rectification of `calib`.
    pub fn bouguet(calib: &StereoCalibration) -> Self {
        // Half of the relative rotation each, in opposite senses.
        let om = Rotation3::from_matrix_unchecked(calib.r).scaled_axis();
        let r_r = Rotation3::new(-0.5 * om);
        let t = r_r * calib.t;
        // Then both onto the baseline (horizontal).
        let uu = Vector3::new(t.x.signum(), 0.0, 0.0);
        let ww = t.cross(&uu);
        let nw = ww.norm();
        let w_r = if nw > 0.0 {
            Rotation3::new(ww * ((t.x.abs() / t.norm()).acos() / nw))
        } else {
            Rotation3::identity()
        };
        let r1 = (w_r * r_r.inverse()).into_inner();
        let r2 = (w_r * r_r).into_inner();
        // One camera for both: the smaller vertical focal length (no view is enlarged), the
        // mean principal point.
        let f = calib.k1[(1, 1)].min(calib.k2[(1, 1)]);
        let c = [
            0.5 * (calib.k1[(0, 2)] + calib.k2[(0, 2)]),
            0.5 * (calib.k1[(1, 2)] + calib.k2[(1, 2)]),
        ];
        Self {
            r1,
            r2,
            f,
            c,
            cx_right: c[0],
            baseline: (r2 * calib.t).x.abs(),
            calib: calib.clone(),
        }
    }

    /// The rectification two ROS `camera_info` YAML files already hold (camera_matrix,
    /// distortion_coefficients, rectification_matrix, projection_matrix); the baseline in
    /// metres, as ROS gives the right camera's `Tx = −fx·B`.
    pub fn from_camera_info(left: &str, right: &str) -> Result<Self, String> {
        let read = |text: &str, side: &str| -> Result<_, String> {
            let text = format!("\n{text}");
            let field = |k: &str, n: usize| -> Result<Vec<f64>, String> {
                let v = yaml_data(&text, k).map_err(|e| format!("{side} camera_info: {e}"))?;
                if v.len() != n {
                    return Err(format!(
                        "{side} camera_info: '{k}' has {} numbers, not {n}",
                        v.len()
                    ));
                }
                Ok(v)
            };
            let d = yaml_data(&text, "distortion_coefficients")
                .map_err(|e| format!("{side} camera_info: {e}"))?;
            if !(4..=5).contains(&d.len()) {
                return Err(format!(
                    "{side} camera_info: {} distortion coefficients; 4 or 5 are read",
                    d.len()
                ));
            }
            let size = (
                scalar(&text, "image_width").map_err(|e| format!("{side} camera_info: {e}"))?,
                scalar(&text, "image_height").map_err(|e| format!("{side} camera_info: {e}"))?,
            );
            Ok((
                Matrix3::from_row_slice(&field("camera_matrix", 9)?),
                d,
                Matrix3::from_row_slice(&field("rectification_matrix", 9)?),
                field("projection_matrix", 12)?,
                size,
            ))
        };
        let (k1, d1, r1, p1, s1) = read(left, "left")?;
        let (k2, d2, r2, p2, s2) = read(right, "right")?;
        if s1 != s2 {
            return Err(format!("left camera_info is {s1:?} but right is {s2:?}"));
        }
        if (p1[0] - p2[0]).abs() > 1e-6 * p1[0] || (p1[6] - p2[6]).abs() > 1e-6 {
            return Err(
                "the two projection matrices differ in focal length or cy: not a rectified pair"
                    .into(),
            );
        }
        let baseline = (p2[3] / p2[0]).abs();
        Ok(Self {
            r1,
            r2,
            f: p1[0],
            c: [p1[2], p1[6]],
            cx_right: p2[2],
            baseline,
            calib: StereoCalibration {
                k1,
                d1,
                k2,
                d2,
                // Both rectified frames are parallel: R2·X_r = R1·X_l + (−b, 0, 0).
                r: r2.transpose() * r1,
                t: r2.transpose() * Vector3::new(-baseline, 0.0, 0.0),
                size: s1,
            },
        })
    }

    /// The raw cameras this rectification is of.
    pub fn calibration(&self) -> &StereoCalibration {
        &self.calib
    }

    /// The image size the calibration is for.
    pub fn size(&self) -> (usize, usize) {
        self.calib.size
    }

    /// Where pixel `(x, y)` of the original left (`right == false`) or right view lands in
    /// the rectified view.
    pub fn point(&self, right: bool, x: f64, y: f64) -> (f64, f64) {
        let (k, d, r) = if right {
            (&self.calib.k2, &self.calib.d2, &self.r2)
        } else {
            (&self.calib.k1, &self.calib.d1, &self.r1)
        };
        let xd = (x - k[(0, 2)] - k[(0, 1)] / k[(1, 1)] * (y - k[(1, 2)])) / k[(0, 0)];
        let yd = (y - k[(1, 2)]) / k[(1, 1)];
        let (xu, yu) = undistort(d, xd, yd);
        let p = r * Vector3::new(xu, yu, 1.0);
        let cx = if right { self.cx_right } else { self.c[0] };
        (cx + self.f * p.x / p.z, self.c[1] + self.f * p.y / p.z)
    }

    /// Where rectified pixel `(u, v)` comes from in the original view.
    pub fn source(&self, right: bool, u: f64, v: f64) -> (f64, f64) {
        let (k, d, r) = if right {
            (&self.calib.k2, &self.calib.d2, &self.r2)
        } else {
            (&self.calib.k1, &self.calib.d1, &self.r1)
        };
        let ray =
            r.transpose() * Vector3::new((u - self.c[0]) / self.f, (v - self.c[1]) / self.f, 1.0);
        let (x, y) = distort(d, ray.x / ray.z, ray.y / ray.z);
        (
            k[(0, 0)] * x + k[(0, 1)] * y + k[(0, 2)],
            k[(1, 1)] * y + k[(1, 2)],
        )
    }
}

/// `name` as an OpenCV `FileStorage` matrix of `rows × cols` doubles.
fn opencv_text(name: &str, rows: usize, cols: usize, v: &[f64]) -> String {
    let data: Vec<String> = v.iter().map(|x| format!("{x:?}")).collect();
    format!(
        "{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {} ]\n",
        data.join(", ")
    )
}

/// The entries of `m`, row by row.
fn row_major(m: &Matrix3<f64>) -> Vec<f64> {
    (0..9).map(|i| m[(i / 3, i % 3)]).collect()
}

impl Rectification {
    /// The projection matrices of the rectified views, the right one's fourth column
    /// `−f·b` with the baseline `b` scaled by `scale` (1 keeps the calibration's unit, as
    /// OpenCV's P2 shares T's unit; ROS wants metres).
    pub fn projections(&self, scale: f64) -> (Vec<f64>, Vec<f64>) {
        let (f, [cx, cy]) = (self.f, self.c);
        let p1 = vec![f, 0.0, cx, 0.0, 0.0, f, cy, 0.0, 0.0, 0.0, 1.0, 0.0];
        let p2 = vec![
            f,
            0.0,
            self.cx_right,
            -f * self.baseline * scale,
            0.0,
            f,
            cy,
            0.0,
            0.0,
            0.0,
            1.0,
            0.0,
        ];
        (p1, p2)
    }

    /// OpenCV's disparity-to-depth matrix `Q` of this rectification (`stereoRectify`'s, for
    /// `reprojectImageTo3D`): `[X Y Z W]ᵀ = Q·[x y d 1]ᵀ`, lengths in the calibration's
    /// unit; the principal points' offset makes `d = cx − cx'` the disparity at infinity.
    pub fn q_matrix(&self) -> [f64; 16] {
        let (f, [cx, cy], b) = (self.f, self.c, self.baseline);
        [
            1.0,
            0.0,
            0.0,
            -cx,
            0.0,
            1.0,
            0.0,
            -cy,
            0.0,
            0.0,
            0.0,
            f,
            0.0,
            0.0,
            1.0 / b,
            (self.cx_right - cx) / b,
        ]
    }

    /// The raw cameras and this rectification as OpenCV's stereo YAML (`stereoCalibrate`'s
    /// K1, D1, K2, D2, R, T and `stereoRectify`'s R1, R2, P1, P2, Q), what
    /// [`StereoCalibration::from_opencv_yaml`] reads back.
    pub fn to_opencv_yaml(&self) -> String {
        let cal = &self.calib;
        let (p1, p2) = self.projections(1.0);
        let mut text = String::from("%YAML:1.0\n---\n");
        text += &format!(
            "image_width: {}\nimage_height: {}\n",
            cal.size.0, cal.size.1
        );
        text += &opencv_text("K1", 3, 3, &row_major(&cal.k1));
        text += &opencv_text("D1", 1, cal.d1.len(), &cal.d1);
        text += &opencv_text("K2", 3, 3, &row_major(&cal.k2));
        text += &opencv_text("D2", 1, cal.d2.len(), &cal.d2);
        text += &opencv_text("R", 3, 3, &row_major(&cal.r));
        text += &opencv_text("T", 3, 1, cal.t.as_slice());
        text += &opencv_text("R1", 3, 3, &row_major(&self.r1));
        text += &opencv_text("R2", 3, 3, &row_major(&self.r2));
        text += &opencv_text("P1", 3, 4, &p1);
        text += &opencv_text("P2", 3, 4, &p2);
        text += &opencv_text("Q", 4, 4, &self.q_matrix());
        text
    }

    /// The left and right views as ROS `camera_info` YAML (plumb_bob), what
    /// [`Rectification::from_camera_info`] reads back; `metres` is the calibration's unit
    /// in metres, for ROS's `Tx = −fx·B` with `B` in metres.
    pub fn to_camera_info(&self, metres: f64) -> [String; 2] {
        let cal = &self.calib;
        let (p1, p2) = self.projections(metres);
        let data = |v: &[f64]| {
            v.iter()
                .map(|x| format!("{x:?}"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        [
            ("left", &cal.k1, &cal.d1, &self.r1, &p1),
            ("right", &cal.k2, &cal.d2, &self.r2, &p2),
        ]
        .map(|(side, k, d, r, p)| {
            format!(
                "image_width: {}\nimage_height: {}\ncamera_name: {side}\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: [{}]\ndistortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: {}\n  data: [{}]\nrectification_matrix:\n  rows: 3\n  cols: 3\n  data: [{}]\nprojection_matrix:\n  rows: 3\n  cols: 4\n  data: [{}]\n",
                cal.size.0,
                cal.size.1,
                data(&row_major(k)),
                d.len(),
                data(d),
                data(&row_major(r)),
                data(p)
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distortion_round_trips_and_an_aligned_pair_is_left_alone() {
        let d = [-0.27, 0.1, 0.001, -0.0005, -0.02];
        for (x, y) in [(0.0, 0.0), (0.3, -0.2), (-0.5, 0.4)] {
            let (xd, yd) = distort(&d, x, y);
            let (xu, yu) = undistort(&d, xd, yd);
            assert!((xu - x).abs() < 1e-9 && (yu - y).abs() < 1e-9, "{x} {y}");
        }
        let k = Matrix3::new(500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0);
        let cal = StereoCalibration {
            k1: k,
            d1: vec![0.0; 5],
            k2: k,
            d2: vec![0.0; 5],
            r: Matrix3::identity(),
            t: Vector3::new(-60.0, 0.0, 0.0),
            size: (640, 480),
        };
        let rect = Rectification::bouguet(&cal);
        assert!((rect.r1 - Matrix3::identity()).norm() < 1e-12);
        assert!((rect.r2 - Matrix3::identity()).norm() < 1e-12);
        assert_eq!(rect.point(true, 100.0, 50.0), (100.0, 50.0));
        assert!((rect.baseline - 60.0).abs() < 1e-12);
    }
}
