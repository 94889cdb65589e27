//! The manipulator registered to the scene: `device = M·scene + offset`, with `M` any
//! invertible 3×3 matrix (the mounting's rotation, each axis's scale and sign), fitted from
//! stops where the tip was found in the images (`microstereo calibrate-manipulator`), and
//! the quick re-registration of the offset alone after a pipette change.

use crate::geom::P3;
use serde::{Deserialize, Serialize};

/// How the device's frame sits on the scene's.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Registration {
    /// `M`, row by row: device axis `i` = `M[i]·scene`.
    pub matrix: [f64; 9],
    /// Device position of the scene's origin, µm.
    pub offset: P3,
}

impl Default for Registration {
    fn default() -> Self {
        Self::offset_only([0.0; 3])
    }
}

fn det3(m: &[f64; 9]) -> f64 {
    m[0] * (m[4] * m[8] - m[5] * m[7]) - m[1] * (m[3] * m[8] - m[5] * m[6])
        + m[2] * (m[3] * m[7] - m[4] * m[6])
}

fn inverse3(m: &[f64; 9]) -> Option<[f64; 9]> {
    let d = det3(m);
    if d.abs() < 1e-12 || !d.is_finite() {
        return None;
    }
    let c = |a: usize, b: usize, e: usize, f: usize| m[a] * m[b] - m[e] * m[f];
    Some([
        c(4, 8, 5, 7) / d,
        -c(1, 8, 2, 7) / d,
        c(1, 5, 2, 4) / d,
        -c(3, 8, 5, 6) / d,
        c(0, 8, 2, 6) / d,
        -c(0, 5, 2, 3) / d,
        c(3, 7, 4, 6) / d,
        -c(0, 7, 1, 6) / d,
        c(0, 4, 1, 3) / d,
    ])
}

fn apply(m: &[f64; 9], v: P3) -> P3 {
    [
        m[0] * v[0] + m[1] * v[1] + m[2] * v[2],
        m[3] * v[0] + m[4] * v[1] + m[5] * v[2],
        m[6] * v[0] + m[7] * v[1] + m[8] * v[2],
    ]
}

impl Registration {
    /// Axes as the scene's, the device's origin at `offset`.
    pub fn offset_only(offset: P3) -> Self {
        Self {
            matrix: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            offset,
        }
    }

    /// Says what is wrong, if anything: a matrix that cannot be inverted (an axis lost)
    /// or numbers out of any manipulator's range.
    pub fn check(&self) -> Result<(), String> {
        if !self
            .matrix
            .iter()
            .chain(&self.offset)
            .all(|v| v.is_finite())
            || self.offset.iter().any(|v| v.abs() > 1e7)
            || self.matrix.iter().any(|v| v.abs() > 1e3)
        {
            return Err("registration: matrix and offset must be finite (offset within ±1e7 µm, matrix terms within ±1000)".into());
        }
        let d = det3(&self.matrix);
        if inverse3(&self.matrix).is_none() || d.abs() < 1e-6 {
            return Err(format!(
                "registration: the matrix's determinant is {d:e}: it maps the scene onto fewer than three device axes"
            ));
        }
        Ok(())
    }

    /// Where the device goes to put the tip at scene point `p`.
    pub fn to_device(&self, p: P3) -> P3 {
        let q = apply(&self.matrix, p);
        [
            q[0] + self.offset[0],
            q[1] + self.offset[1],
            q[2] + self.offset[2],
        ]
    }

    /// Where the tip is in the scene when the device reads `d`.
    pub fn to_scene(&self, d: P3) -> P3 {
        let inv = inverse3(&self.matrix).expect("a checked registration");
        apply(
            &inv,
            [
                d[0] - self.offset[0],
                d[1] - self.offset[1],
                d[2] - self.offset[2],
            ],
        )
    }

    /// The least factor by which the device's travel exceeds the scene's (the matrix's
    /// smallest singular value): a device speed of `v` times it moves the tip at most `v`.
    pub fn least_stretch(&self) -> f64 {
        let m = &self.matrix;
        // The eigenvalues of the symmetric MᵀM, in closed form (trigonometric roots).
        let a: [f64; 9] = std::array::from_fn(|k| {
            let (i, j) = (k / 3, k % 3);
            (0..3).map(|r| m[3 * r + i] * m[3 * r + j]).sum()
        });
        let p1 = a[1] * a[1] + a[2] * a[2] + a[5] * a[5];
        let q = (a[0] + a[4] + a[8]) / 3.0;
        if p1 == 0.0 {
            return a[0].min(a[4]).min(a[8]).max(0.0).sqrt();
        }
        let p2 = (a[0] - q).powi(2) + (a[4] - q).powi(2) + (a[8] - q).powi(2) + 2.0 * p1;
        let p = (p2 / 6.0).sqrt();
        let b: [f64; 9] = std::array::from_fn(|k| (a[k] - if k % 4 == 0 { q } else { 0.0 }) / p);
        let r = (det3(&b) / 2.0).clamp(-1.0, 1.0);
        let phi = r.acos() / 3.0;
        let least = q + 2.0 * p * (phi + 2.0 * std::f64::consts::PI / 3.0).cos();
        least.max(0.0).sqrt()
    }

    /// The same matrix with the offset that puts scene point `scene` at device position
    /// `device` (one stop after a pipette change: the new tip sits elsewhere on the same
    /// axes).
    pub fn with_offset_through(&self, scene: P3, device: P3) -> Self {
        let q = apply(&self.matrix, scene);
        Self {
            matrix: self.matrix,
            offset: [device[0] - q[0], device[1] - q[1], device[2] - q[2]],
        }
    }

    /// The affine map through `pairs` of (scene, device) positions by least squares, and
    /// each pair's residual `|to_device(scene) − device|` (µm). Needs at least four stops
    /// not in one plane.
    pub fn fit(pairs: &[(P3, P3)]) -> Result<(Self, Vec<f64>), String> {
        if pairs.len() < 4 {
            return Err(format!(
                "{} stops; the fit needs at least 4 not in one plane",
                pairs.len()
            ));
        }
        let n = pairs.len() as f64;
        let mean = |f: &dyn Fn(&(P3, P3)) -> P3| {
            pairs.iter().fold([0.0; 3], |a, p| {
                let v = f(p);
                [a[0] + v[0] / n, a[1] + v[1] / n, a[2] + v[2] / n]
            })
        };
        let (ms, md) = (mean(&|p| p.0), mean(&|p| p.1));
        // Normal equations on the centred points: M = Sds · Sss⁻¹.
        let (mut sss, mut sds) = ([0.0; 9], [0.0; 9]);
        for (s, d) in pairs {
            let (s, d) = (
                [s[0] - ms[0], s[1] - ms[1], s[2] - ms[2]],
                [d[0] - md[0], d[1] - md[1], d[2] - md[2]],
            );
            for i in 0..3 {
                for j in 0..3 {
                    sss[3 * i + j] += s[i] * s[j];
                    sds[3 * i + j] += d[i] * s[j];
                }
            }
        }
        let inv = inverse3(&sss)
            .ok_or("the stops lie in one plane or on a line: spread them over all three axes")?;
        let mut m = [0.0; 9];
        for i in 0..3 {
            for j in 0..3 {
                m[3 * i + j] = (0..3).map(|k| sds[3 * i + k] * inv[3 * k + j]).sum();
            }
        }
        let q = apply(&m, ms);
        let reg = Self {
            matrix: m,
            offset: [md[0] - q[0], md[1] - q[1], md[2] - q[2]],
        };
        reg.check()?;
        let residuals = pairs
            .iter()
            .map(|(s, d)| {
                let e = reg.to_device(*s);
                ((e[0] - d[0]).powi(2) + (e[1] - d[1]).powi(2) + (e[2] - d[2]).powi(2)).sqrt()
            })
            .collect();
        Ok((reg, residuals))
    }

    /// Reads a registration file (TOML: `matrix`, `offset`, and the fit's record).
    pub fn read(path: &str) -> Result<Self, String> {
        #[derive(Deserialize)]
        struct File {
            matrix: [f64; 9],
            offset: P3,
            #[serde(flatten)]
            _record: toml::Table,
        }
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("registration '{path}' cannot be read: {e}"))?;
        let f: File = toml::from_str(&text).map_err(|e| format!("registration '{path}' is not valid: {e}; expected matrix = [9 numbers] and offset = [x, y, z]"))?;
        let r = Self {
            matrix: f.matrix,
            offset: f.offset,
        };
        r.check().map_err(|e| format!("'{path}': {e}"))?;
        Ok(r)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mount() -> Registration {
        // 30° about z, x stretched 1.1, y flipped, z 0.9, and an offset.
        let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
        Registration {
            matrix: [1.1 * c, -1.1 * s, 0.0, -s, -c, 0.0, 0.0, 0.0, 0.9],
            offset: [1200.0, -300.0, 5000.0],
        }
    }

    #[test]
    fn maps_round_trip_and_a_fit_recovers_the_mount() {
        let m = mount();
        m.check().unwrap();
        let p = [12.0, -40.0, -3900.0];
        let back = m.to_scene(m.to_device(p));
        assert!((0..3).all(|k| (back[k] - p[k]).abs() < 1e-9), "{back:?}");
        let pairs: Vec<(P3, P3)> = (0..18)
            .map(|i| {
                let s = [
                    -50.0 + 50.0 * (i % 3) as f64,
                    -50.0 + 50.0 * ((i / 3) % 3) as f64,
                    -3900.0 + 20.0 * (i / 9) as f64,
                ];
                (s, m.to_device(s))
            })
            .collect();
        let (fit, res) = Registration::fit(&pairs).unwrap();
        assert!(res.iter().all(|r| *r < 1e-6), "{res:?}");
        assert!(
            fit.matrix
                .iter()
                .zip(&m.matrix)
                .all(|(a, b)| (a - b).abs() < 1e-9)
        );
        assert!(
            (m.least_stretch() - 0.9).abs() < 1e-3,
            "{}",
            m.least_stretch()
        );
        // One stop after a pipette change: a new offset on the same axes.
        let moved = Registration {
            offset: [1210.0, -290.0, 5003.0],
            ..m
        };
        let re = m.with_offset_through(p, moved.to_device(p));
        assert!((0..3).all(|k| (re.offset[k] - moved.offset[k]).abs() < 1e-9));
    }

    #[test]
    fn degenerate_stops_and_matrices_are_refused() {
        let flat: Vec<(P3, P3)> = (0..9)
            .map(|i| ([i as f64, (i * i) as f64, 0.0], [0.0; 3]))
            .collect();
        assert!(Registration::fit(&flat).unwrap_err().contains("one plane"));
        let lost = Registration {
            matrix: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0],
            offset: [0.0; 3],
        };
        assert!(lost.check().unwrap_err().contains("determinant"));
    }
}
