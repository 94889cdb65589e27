//! The calibration file that `reconstruct --calibration`, the triangulate node and
//! `calibrate-depth` share: rectified parallel-axis geometry in TOML or JSON.
//!
//! ```toml
//! baseline = 2000.0     # in `unit`
//! f_eff = 20000.0       # effective focal length ...
//! pixel_pitch = 5.0     # ... and pixel pitch, same unit (or: focal_px = 4000.0)
//! cx = 639.5            # optional, default image centre
//! cy = 511.5
//! unit = "um"
//!
//! [stereo]              # optional: the raw cameras (`calibrate-stereo`), for the rectifier
//! width = 640
//! height = 480
//! k1 = [533.4, 0.0, 342.5, 0.0, 533.4, 234.7, 0.0, 0.0, 1.0]
//! d1 = [-0.28, 0.039, 0.0012, -0.00013, 0.119]
//! # k2, d2, r (left → right rotation, row by row), t (left → right, in `unit`)
//! ```

use schemas::{Calibration, LengthUnit};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// A calibration as written in a file (or inline in a launch file).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationFile {
    /// Distance between the optical centres, in `unit`.
    pub baseline: f64,
    /// Focal length in pixels (or `f_eff` with `pixel_pitch`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub focal_px: Option<f64>,
    /// Effective focal length, in `unit`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub f_eff: Option<f64>,
    /// Pixel pitch, in `unit`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pixel_pitch: Option<f64>,
    /// Left principal point column (default: the image centre).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cx: Option<f64>,
    /// Principal point row (default: the image centre).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cy: Option<f64>,
    /// Right principal point column (default: `cx`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cx_right: Option<f64>,
    /// Unit of `baseline` and so of every length triangulated from it (required: a
    /// microscope's µm and a bench rig's mm differ a thousandfold).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unit: Option<LengthUnit>,
    /// The raw cameras, for rectifying raw pairs (`None`: the images come rectified).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stereo: Option<Box<crate::stereo::StereoTable>>,
    /// A stereo microscope's views and their rectification onto the stage plane
    /// (`calibrate-microscope`), for the rectifier; the top level is its parallel-axis
    /// geometry.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub microscope: Option<Box<crate::microscope::Rig>>,
}

impl CalibrationFile {
    /// The geometry for images of `w × h` (`source` names the file in errors).
    pub fn resolve(&self, w: usize, h: usize, source: &str) -> Result<Calibration, String> {
        let focal = match (self.focal_px, self.f_eff, self.pixel_pitch) {
            (Some(fp), None, None) => fp,
            (None, Some(fe), Some(pp)) if pp > 0.0 => fe / pp,
            _ => {
                return Err(format!(
                    "calibration {source}: give either focal_px, or f_eff with pixel_pitch (> 0)"
                ));
            }
        };
        let Some(unit) = self.unit else {
            return Err(format!(
                "calibration {source}: no unit for baseline {}: add unit = \"um\" (a microscope), \"mm\" or \"m\"",
                self.baseline
            ));
        };
        let cx = self.cx.unwrap_or((w as f64 - 1.0) / 2.0);
        let c = Calibration {
            baseline: self.baseline,
            focal_px: focal,
            cx,
            cy: self.cy.unwrap_or((h as f64 - 1.0) / 2.0),
            cx_right: self.cx_right.unwrap_or(cx),
            unit,
        };
        check(&c, source)?;
        self.cameras(source)?;
        if let Some(m) = &self.microscope {
            if self.stereo.is_some() {
                return Err(format!(
                    "calibration {source}: give [stereo] (a bench rig's cameras) or [microscope], not both"
                ));
            }
            m.check()
                .map_err(|e| format!("calibration {source}: {e}"))?;
        }
        Ok(c)
    }

    /// The file of a calibrated stereo pair: its raw cameras in `[stereo]` and the
    /// geometry of its Bouguet rectification (baseline, focal length, principal points) for
    /// triangulating the rectified views; lengths in `unit`.
    pub fn from_stereo(
        cal: &crate::stereo::StereoCalibration,
        unit: LengthUnit,
        rms: Option<f64>,
    ) -> Self {
        let rect = crate::stereo::Rectification::bouguet(cal);
        Self {
            baseline: rect.baseline,
            focal_px: Some(rect.f),
            f_eff: None,
            pixel_pitch: None,
            cx: Some(rect.c[0]),
            cy: Some(rect.c[1]),
            cx_right: Some(rect.cx_right),
            unit: Some(unit),
            stereo: Some(Box::new(crate::stereo::StereoTable {
                rms,
                ..crate::stereo::StereoTable::from(cal)
            })),
            microscope: None,
        }
    }

    /// The file of cameras calibrated elsewhere (OpenCV's stereo YAML, ROS camera_info),
    /// lengths in `unit`: their table checked as it will be when the file is read.
    pub fn imported(
        cal: &crate::stereo::StereoCalibration,
        unit: LengthUnit,
    ) -> Result<Self, String> {
        crate::stereo::StereoTable::from(cal).calibration()?;
        Ok(Self::from_stereo(cal, unit, None))
    }

    /// The raw cameras to export (`source` names the file in errors): a file without a
    /// `[stereo]` table has none.
    pub fn exported_cameras(
        &self,
        source: &str,
    ) -> Result<crate::stereo::StereoCalibration, String> {
        self.cameras(source)?.ok_or_else(|| {
            format!(
                "calibration {source} has no [stereo] table (the raw cameras) to export; make one with calibrate-stereo or calibration import"
            )
        })
    }

    /// The raw cameras, checked (`None` without a `[stereo]` table).
    pub fn cameras(
        &self,
        source: &str,
    ) -> Result<Option<crate::stereo::StereoCalibration>, String> {
        self.stereo
            .as_ref()
            .map(|t| {
                t.calibration()
                    .map_err(|e| format!("calibration {source}: {e}"))
            })
            .transpose()
    }

    /// A rectified geometry given by hand: `baseline` in `unit`, focal length `focal_px`,
    /// principal points `cx`, `cy` and `cx_right` (default: the image centre; the right
    /// one the left's).
    pub fn inline(
        (baseline, focal_px): (f64, f64),
        (cx, cy, cx_right): (Option<f64>, Option<f64>, Option<f64>),
        unit: Option<LengthUnit>,
    ) -> Self {
        Self {
            baseline,
            focal_px: Some(focal_px),
            f_eff: None,
            pixel_pitch: None,
            cx,
            cy,
            cx_right: cx_right.or(cx),
            unit,
            stereo: None,
            microscope: None,
        }
    }

    /// Metres per unit of the file (`source` names it in the error): a file without a
    /// unit cannot be put in ROS's metres.
    pub fn metres(&self, source: &str) -> Result<f64, String> {
        self.unit.map(|u| u.metres()).ok_or_else(|| {
            format!(
                "calibration {source} gives no unit, and camera_info's Tx is in metres: add unit = \"mm\" (or \"um\", \"m\") to it"
            )
        })
    }

    /// The file form of a geometry (focal length as f_eff and `pitch`).
    pub fn from_calibration(c: &Calibration, pitch: f64) -> Self {
        Self {
            baseline: c.baseline,
            focal_px: None,
            f_eff: Some(c.focal_px * pitch),
            pixel_pitch: Some(pitch),
            cx: Some(c.cx),
            cy: Some(c.cy),
            cx_right: Some(c.cx_right),
            unit: Some(c.unit),
            stereo: None,
            microscope: None,
        }
    }
}

/// The comment line that says which part of a file with raw cameras is read by what.
pub const LAYOUT: &str = "# Top level: the rectified views' geometry (triangulate); [stereo]: the raw cameras (rectify).";

/// Checks that a geometry can triangulate (`source` names where it came from).
pub fn check(c: &Calibration, source: &str) -> Result<(), String> {
    if !(c.baseline > 0.0 && c.baseline.is_finite() && c.focal_px > 0.0 && c.focal_px.is_finite()) {
        return Err(format!(
            "calibration {source}: baseline ({}) and focal length ({} px) must be positive",
            c.baseline, c.focal_px
        ));
    }
    // Past these, b·f/d and the coordinates overflow or lose every digit: no optics has them.
    if c.baseline > 1e9 || c.focal_px > 1e9 {
        return Err(format!(
            "calibration {source}: baseline ({}) and focal length ({} px) must be at most 1e9 each",
            c.baseline, c.focal_px
        ));
    }
    for (name, v) in [("cx", c.cx), ("cy", c.cy), ("cx_right", c.cx_right)] {
        if !(v.is_finite() && v.abs() <= 1e6) {
            return Err(format!(
                "calibration {source}: {name} ({v}) must be a finite pixel column or row (within ±1e6)"
            ));
        }
    }
    Ok(())
}

/// Reads a calibration file (TOML, or JSON by its `.json` extension).
pub fn read_file(path: &Path) -> Result<CalibrationFile, String> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("calibration file '{}' cannot be read: {e}", path.display()))?;
    let is_json = path.extension().is_some_and(|e| e == "json");
    if is_json {
        serde_json::from_str(&text).map_err(|e| e.to_string())
    } else {
        toml::from_str(&text).map_err(|e| e.to_string())
    }
    .map_err(|e| {
        format!(
            "calibration file '{}' is not valid: {e}; expected baseline, focal_px (or f_eff and pixel_pitch), optional cx, cy, cx_right, unit",
            path.display()
        )
    })
}

/// Writes `f` as a TOML calibration file (atomically; the caller checks overwriting).
pub fn write_file(path: &Path, f: &CalibrationFile, comment: &str) -> Result<(), String> {
    let body = toml::to_string(f).map_err(|e| e.to_string())?;
    let text = format!("# {comment}\n{body}");
    formats::atomic::write_bytes(path, text.as_bytes()).map_err(|e| e.to_string())
}

/// Reads a calibration file for images of `w × h`.
pub fn load(path: &Path, w: usize, h: usize) -> Result<Calibration, String> {
    read_file(path)?.resolve(w, h, &format!("file '{}'", path.display()))
}

/// Writes `c` as a calibration file (focal length as f_eff and `pitch`).
pub fn write(path: &Path, c: &Calibration, pitch: f64) -> Result<(), String> {
    let text = format!(
        "# Written by microstereo: rectified parallel-axis geometry.\nbaseline = {}\nf_eff = {}\npixel_pitch = {}\ncx = {}\ncy = {}\ncx_right = {}\nunit = \"{}\"\n",
        c.baseline,
        c.focal_px * pitch,
        pitch,
        c.cx,
        c.cy,
        c.cx_right,
        match c.unit {
            LengthUnit::Um => "um",
            LengthUnit::Mm => "mm",
            LengthUnit::M => "m",
        }
    );
    formats::atomic::write_bytes(path, text.as_bytes()).map_err(|e| e.to_string())
}

/// Depth calibration from a z-stack: each pair shows a flat textured target at a known
/// stage height `z` (µm, towards the cameras). Its depth is `Z = W − z` (`W`: the working
/// distance, depth at `z = 0`), and the measured disparity follows `d = B / Z − offset` with
/// `B = b·f` (baseline × focal length in pixels). With `W` known the fit is linear least
/// squares in `(B, offset)`; otherwise `W` is found too, by a golden-section search on the
/// fit's residual (the curvature of `d(z)`).
/// The fitted model and its residuals.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthFit {
    /// b·f, µm·px.
    pub b_f: f64,
    /// Disparity offset (`cx_right − cx`), px.
    pub offset: f64,
    /// Working distance used or found, µm.
    pub working_distance: f64,
    /// Measured minus modelled disparity per height, px.
    pub residuals: Vec<f64>,
}

fn linear_fit(z: &[f64], d: &[f64], w: f64) -> (f64, f64, f64) {
    // d = B·x − off with x = 1/(W − z).
    let n = z.len() as f64;
    let x: Vec<f64> = z.iter().map(|&z| 1.0 / (w - z)).collect();
    let (mx, md) = (x.iter().sum::<f64>() / n, d.iter().sum::<f64>() / n);
    let sxx: f64 = x.iter().map(|v| (v - mx) * (v - mx)).sum();
    let sxd: f64 = x.iter().zip(d).map(|(v, e)| (v - mx) * (e - md)).sum();
    let b = sxd / sxx;
    let off = b * mx - md;
    let rss = x
        .iter()
        .zip(d)
        .map(|(v, e)| (b * v - off - e).powi(2))
        .sum();
    (b, off, rss)
}

/// The largest working distance [`fit_depth`] searches, beyond the highest stage, µm.
const FARTHEST: f64 = 1e7;

impl DepthFit {
    /// Refuses a fit that cannot be written as a depth calibration (`searched`: the
    /// working distance was fitted, not given), with the reason and what to do.
    pub fn check(&self, z: &[f64], searched: bool) -> Result<(), String> {
        let rms = (self.residuals.iter().map(|r| r * r).sum::<f64>()
            / self.residuals.len().max(1) as f64)
            .sqrt();
        if rms > 0.3 {
            return Err(format!(
                "the target's disparities do not follow one depth model (residual {rms:.2} px RMS): the pairs must be rectified; for a stereo microscope's raw views (converging, nearly telecentric) use calibrate-microscope with a chessboard at known stage heights"
            ));
        }
        if self.b_f.is_nan() || self.b_f <= 0.0 {
            return Err(format!(
                "the target's disparity does not grow with the stage height (b·f = {:.3e}): are left and right swapped, or do heights.csv's heights grow away from the cameras?",
                self.b_f
            ));
        }
        let zmax = z.iter().copied().fold(f64::MIN, f64::max);
        if searched && self.working_distance - zmax > 0.99 * FARTHEST {
            return Err(
                "the z-stack shows no perspective (the views are telecentric within its noise), so the working distance and b·f are undetermined: give --working-distance, or calibrate the microscope with calibrate-microscope from a chessboard at known stage heights".into(),
            );
        }
        Ok(())
    }
}

/// Fits `d = B/(W − z) − offset` to measured `(z, d)`; `w` fixed or searched.
pub fn fit_depth(z: &[f64], d: &[f64], w: Option<f64>) -> DepthFit {
    let zmax = z.iter().copied().fold(f64::MIN, f64::max);
    let w = w.unwrap_or_else(|| {
        // Golden section on log(W − zmax) over 1 µm .. 10 m.
        let f = |t: f64| linear_fit(z, d, zmax + t.exp()).2;
        let (mut a, mut b) = (0f64, FARTHEST.ln());
        let g = 0.5 * (5f64.sqrt() - 1.0);
        let (mut c, mut e) = (b - g * (b - a), a + g * (b - a));
        for _ in 0..200 {
            if f(c) < f(e) {
                b = e;
            } else {
                a = c;
            }
            c = b - g * (b - a);
            e = a + g * (b - a);
        }
        zmax + (0.5 * (a + b)).exp()
    });
    let (b_f, offset, _) = linear_fit(z, d, w);
    let residuals = z
        .iter()
        .zip(d)
        .map(|(&z, &d)| d - (b_f / (w - z) - offset))
        .collect();
    DepthFit {
        b_f,
        offset,
        working_distance: w,
        residuals,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_resolves_with_the_image_centre_and_round_trips() {
        let dir = std::env::temp_dir().join(format!("calib-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("c.toml");
        std::fs::write(
            &p,
            "baseline = 2000.0\nf_eff = 20000.0\npixel_pitch = 5.0\nunit = \"um\"\n",
        )
        .unwrap();
        let c = load(&p, 640, 480).unwrap();
        assert_eq!(
            (c.focal_px, c.cx, c.cy, c.cx_right),
            (4000.0, 319.5, 239.5, 319.5)
        );
        assert_eq!(c.unit, LengthUnit::Um);
        write(&p, &c, 5.0).unwrap();
        assert_eq!(load(&p, 10, 10).unwrap(), c);
        std::fs::write(&p, "baseline = 2000.0\nfocal_px = 1.0\nf_eff = 3.0\n").unwrap();
        assert!(load(&p, 4, 4).unwrap_err().contains("give either focal_px"));
        std::fs::write(&p, "baseline = -1.0\nfocal_px = 1.0\nunit = \"mm\"\n").unwrap();
        assert!(load(&p, 4, 4).unwrap_err().contains("must be positive"));
        // No unit is assumed: µm and mm differ a thousandfold.
        std::fs::write(&p, "baseline = 2000.0\nfocal_px = 1.0\n").unwrap();
        assert!(load(&p, 4, 4).unwrap_err().contains("add unit = \"um\""));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn imported_cameras_export_again_and_a_plain_geometry_has_none() {
        use crate::stereo::StereoCalibration;
        use nalgebra::{Matrix3, Vector3};
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
        let f = CalibrationFile::imported(&cal, LengthUnit::Mm).unwrap();
        assert_eq!((f.baseline, f.unit), (60.0, Some(LengthUnit::Mm)));
        assert_eq!(f.exported_cameras("'a'").unwrap(), cal);
        let plain = CalibrationFile { stereo: None, ..f };
        assert_eq!(
            plain.exported_cameras("'a'").unwrap_err(),
            "calibration 'a' has no [stereo] table (the raw cameras) to export; make one with calibrate-stereo or calibration import"
        );
        let bad = StereoCalibration {
            size: (0, 0),
            ..cal
        };
        assert!(CalibrationFile::imported(&bad, LengthUnit::Mm).is_err());
    }

    #[test]
    fn fit_recovers_an_exact_model_with_and_without_the_working_distance() {
        let (bf, off, w) = (4.8e6, 1200.0, 4000.0);
        let z: Vec<f64> = (-4..=4).map(|i| 40.0 * i as f64).collect();
        let d: Vec<f64> = z.iter().map(|z| bf / (w - z) - off).collect();
        let f = fit_depth(&z, &d, Some(w));
        assert!((f.b_f / bf - 1.0).abs() < 1e-9 && (f.offset - off).abs() < 1e-6);
        let g = fit_depth(&z, &d, None);
        assert!((g.working_distance / w - 1.0).abs() < 1e-3, "{g:?}");
        assert!((g.b_f / bf - 1.0).abs() < 2e-3, "{g:?}");
        g.check(&z, true).unwrap();
        // A telecentric stack: disparity linear in height, the fit runs to its bound.
        let flat: Vec<f64> = z.iter().map(|z| 0.19 * z).collect();
        let t = fit_depth(&z, &flat, None);
        assert!(t.check(&z, true).unwrap_err().contains("no perspective"));
        assert!(fit_depth(&z, &flat, Some(1e5)).check(&z, false).is_ok());
        // Falling with height, and scattered.
        let down: Vec<f64> = flat.iter().map(|d| -d).collect();
        let e = fit_depth(&z, &down, Some(1e5))
            .check(&z, false)
            .unwrap_err();
        assert!(e.contains("does not grow"), "{e}");
        let noisy: Vec<f64> = flat
            .iter()
            .enumerate()
            .map(|(i, d)| d + if i % 2 == 0 { 1.0 } else { -1.0 })
            .collect();
        let e = fit_depth(&z, &noisy, Some(1e5))
            .check(&z, false)
            .unwrap_err();
        assert!(e.contains("calibrate-microscope"), "{e}");
    }
}
