//! Where a triangulate node's geometry comes from (`calibration` in its params): the
//! synthetic microscope's optics, a calibration file, or the file's keys inline.

use calibration::file::{CalibrationFile, read_file};
use schemas::Calibration;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Where a triangulate node's geometry comes from (`calibration` in its params): the
/// synthetic microscope's optics, a calibration file, or the numbers themselves.
#[derive(Clone, Debug, PartialEq)]
pub enum Geometry {
    /// `"synthetic"`: the optics of `microstereo synth` and the synthetic capture.
    Synthetic,
    /// A calibration file's path.
    File(String),
    /// A table with the file's keys.
    Inline(CalibrationFile),
}

impl<'de> Deserialize<'de> for Geometry {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> serde::de::Visitor<'de> for V {
            type Value = Geometry;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("\"synthetic\", a calibration file's path or a table of its keys")
            }
            fn visit_str<E: serde::de::Error>(self, s: &str) -> Result<Geometry, E> {
                Ok(if s == "synthetic" {
                    Geometry::Synthetic
                } else {
                    Geometry::File(s.into())
                })
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(self, m: A) -> Result<Geometry, A::Error> {
                CalibrationFile::deserialize(serde::de::value::MapAccessDeserializer::new(m))
                    .map(Geometry::Inline)
            }
        }
        d.deserialize_any(V)
    }
}

impl Serialize for Geometry {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            Geometry::Synthetic => s.serialize_str("synthetic"),
            Geometry::File(p) => s.serialize_str(p),
            Geometry::Inline(f) => f.serialize(s),
        }
    }
}

impl From<Geometry> for toml::Value {
    fn from(g: Geometry) -> Self {
        toml::Value::try_from(g).expect("a calibration serialises")
    }
}

impl Geometry {
    /// Checks what can be checked without the image size: the file is readable and valid.
    pub fn check(&self) -> Result<(), String> {
        match self {
            Geometry::Synthetic => Ok(()),
            Geometry::File(p) => read_file(Path::new(p)).map(|_| ()),
            Geometry::Inline(f) => f.resolve(2, 2, "given inline").map(|_| ()),
        }
    }

    /// The geometry for images of `w × h`.
    pub fn resolve(&self, w: usize, h: usize) -> Result<Calibration, String> {
        self.resolve_with_field(w, h).map(|(c, _)| c)
    }

    /// The geometry for images of `w × h`, and the rectified field a microscope
    /// calibration's board covered (`calibration::microscope::Rig::field`) where the file
    /// names one for that size: the file read once.
    pub fn resolve_with_field(
        &self,
        w: usize,
        h: usize,
    ) -> Result<(Calibration, Option<[f64; 4]>), String> {
        let field = |f: &CalibrationFile| {
            f.microscope
                .as_ref()
                .filter(|r| (r.width, r.height) == (w, h))
                .and_then(|r| r.field)
        };
        match self {
            Geometry::Synthetic => Ok((
                synth::Optics {
                    width: w,
                    height: h,
                    ..synth::Optics::default()
                }
                .calibration(),
                None,
            )),
            Geometry::File(p) => {
                let f = read_file(Path::new(p))?;
                Ok((f.resolve(w, h, &format!("file '{p}'"))?, field(&f)))
            }
            Geometry::Inline(f) => Ok((f.resolve(w, h, "given inline")?, field(f))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use schemas::LengthUnit;

    #[test]
    fn a_geometry_is_a_name_a_path_or_a_table() {
        #[derive(Deserialize)]
        struct P {
            calibration: Geometry,
        }
        let g = |s: &str| -> Result<Geometry, String> {
            let t: toml::Table = toml::from_str(s).map_err(|e| e.to_string())?;
            toml::Value::Table(t)
                .try_into::<P>()
                .map(|p| p.calibration)
                .map_err(|e| e.to_string())
        };
        assert_eq!(
            g("calibration = \"synthetic\"").unwrap(),
            Geometry::Synthetic
        );
        assert_eq!(
            g("calibration = \"a.toml\"").unwrap(),
            Geometry::File("a.toml".into())
        );
        let inline = g("calibration = { baseline = 1.5, focal_px = 900.0, unit = \"m\" }").unwrap();
        let c = inline.resolve(11, 5).unwrap();
        assert_eq!((c.baseline, c.focal_px, c.cx, c.cy), (1.5, 900.0, 5.0, 2.0));
        assert_eq!(c.unit, LengthUnit::M);
        assert!(
            g("calibration = { baseline = 1.5, focal = 900.0 }")
                .unwrap_err()
                .contains("focal")
        );
        assert!(g("calibration = 3").unwrap_err().contains("integer"));
        let back = toml::Table::from_iter([(
            "calibration".to_string(),
            toml::Value::from(inline.clone()),
        )]);
        assert_eq!(g(&toml::to_string(&back).unwrap()).unwrap(), inline);
    }
}
