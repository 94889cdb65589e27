//! Camera and stereo calibration from views of a planar board: Zhang's closed-form start
//! (principal point at the image centre, as OpenCV's `initIntrinsicParams2D`), then
//! Levenberg–Marquardt on the reprojection error with OpenCV's camera model (fx, fy, cx,
//! cy, no skew; distortion k1 k2 p1 p2 k3), per camera and then both cameras jointly with
//! their relative pose (as `stereoCalibrate` with `CALIB_USE_INTRINSIC_GUESS`).

use crate::board::homography;
use crate::lm::minimise;
use crate::stereo::StereoCalibration;
use nalgebra::{Matrix3, Rotation3, Vector3};

/// One camera: `[fx, fy, cx, cy, k1, k2, p1, p2, k3]`.
pub type Intrinsics = [f64; 9];

/// One view's board corners in pixels, in the board's order.
pub type Corners = Vec<[f64; 2]>;

/// Both views' corners of one board, borrowed.
pub type PairView<'a> = (&'a [[f64; 2]], &'a [[f64; 2]]);

/// A board's pose in a camera: rotation vector, then translation.
pub type Pose = [f64; 6];

/// Where `x` (board frame) lands in the image of camera `cam` with the board at `pose`.
pub fn project(cam: &[f64], pose: &[f64], x: [f64; 3]) -> [f64; 2] {
    let r = Rotation3::new(Vector3::new(pose[0], pose[1], pose[2]));
    let p = r * Vector3::new(x[0], x[1], x[2]) + Vector3::new(pose[3], pose[4], pose[5]);
    let (xd, yd) = crate::stereo::distort(&cam[4..9], p.x / p.z, p.y / p.z);
    [cam[0] * xd + cam[2], cam[1] * yd + cam[3]]
}

/// The pose `b` composed after `a` (the board in camera 2 when `a` is it in camera 1 and
/// `b` camera 1 in camera 2).
fn compose(b: &[f64], a: &[f64]) -> Pose {
    let rb = Rotation3::new(Vector3::new(b[0], b[1], b[2]));
    let ra = Rotation3::new(Vector3::new(a[0], a[1], a[2]));
    let r = (rb * ra).scaled_axis();
    let t = rb * Vector3::new(a[3], a[4], a[5]) + Vector3::new(b[3], b[4], b[5]);
    [r.x, r.y, r.z, t.x, t.y, t.z]
}

/// A fitted camera.
#[derive(Clone, Debug, PartialEq)]
pub struct Mono {
    /// The camera.
    pub camera: Intrinsics,
    /// The board's pose in each view.
    pub poses: Vec<Pose>,
    /// Root mean square reprojection error over all corners (px).
    pub rms: f64,
}

/// A fitted stereo pair.
#[derive(Clone, Debug, PartialEq)]
pub struct Stereo {
    /// Left camera.
    pub left: Intrinsics,
    /// Right camera.
    pub right: Intrinsics,
    /// Rotation from the left camera's frame to the right's.
    pub r: Matrix3<f64>,
    /// Translation from the left camera's frame to the right's (board units).
    pub t: Vector3<f64>,
    /// The board's pose in the left camera, per pair.
    pub poses: Vec<Pose>,
    /// Root mean square reprojection error over both views' corners (px), as OpenCV's
    /// `stereoCalibrate` reports it.
    pub rms: f64,
    /// The same per pair.
    pub pair_rms: Vec<f64>,
    /// Standard errors of the left and right focal lengths `fx` (px) and of the baseline
    /// (board units), from the fit's covariance: how well the boards determine them.
    pub std: [f64; 3],
}

impl Stereo {
    /// The calibration the rectifier reads.
    pub fn calibration(&self, size: (usize, usize)) -> StereoCalibration {
        let k = |c: &Intrinsics| Matrix3::new(c[0], 0.0, c[2], 0.0, c[1], c[3], 0.0, 0.0, 1.0);
        StereoCalibration {
            k1: k(&self.left),
            d1: self.left[4..9].to_vec(),
            k2: k(&self.right),
            d2: self.right[4..9].to_vec(),
            r: self.r,
            t: self.t,
            size,
        }
    }
}

fn rms_of(sum_sq: f64, points: usize) -> f64 {
    (sum_sq / points.max(1) as f64).sqrt()
}

/// Zhang's start: focal lengths from the homographies' orthogonality with the principal
/// point at the image centre, then each view's pose from its homography.
fn initial(
    views: &[Vec<[f64; 2]>],
    object: &[[f64; 2]],
    size: (usize, usize),
) -> Result<(Intrinsics, Vec<Pose>), String> {
    let (cx, cy) = ((size.0 as f64 - 1.0) / 2.0, (size.1 as f64 - 1.0) / 2.0);
    let mut homs = Vec::new();
    for (i, v) in views.iter().enumerate() {
        let pairs: Vec<_> = object.iter().copied().zip(v.iter().copied()).collect();
        homs.push(homography(&pairs).ok_or_else(|| format!("view {}: no homography", i + 1))?);
    }
    let centre = Matrix3::new(1.0, 0.0, -cx, 0.0, 1.0, -cy, 0.0, 0.0, 1.0);
    let (mut ata, mut atb) = (
        nalgebra::Matrix2::<f64>::zeros(),
        nalgebra::Vector2::<f64>::zeros(),
    );
    for h in &homs {
        let hc = centre * h;
        let (h1, h2) = (hc.column(0), hc.column(1));
        // Each column scaled to unit norm keeps the views' equations comparable.
        let (h1, h2) = (h1 / h1.norm(), h2 / h2.norm());
        let rows = [
            ([h1.x * h2.x, h1.y * h2.y], -h1.z * h2.z),
            (
                [h1.x * h1.x - h2.x * h2.x, h1.y * h1.y - h2.y * h2.y],
                -(h1.z * h1.z - h2.z * h2.z),
            ),
        ];
        for (a, b) in rows {
            let a = nalgebra::Vector2::new(a[0], a[1]);
            ata += a * a.transpose();
            atb += a * b;
        }
    }
    let ab = ata
        .try_inverse()
        .map(|m| m * atb)
        .ok_or("the views' homographies do not fix the focal length (all boards parallel?)")?;
    let f_of = |v: f64| (v > 0.0).then(|| 1.0 / v.sqrt());
    let (fx, fy) = match (f_of(ab.x), f_of(ab.y)) {
        (Some(fx), Some(fy)) => (fx, fy),
        (Some(f), None) | (None, Some(f)) => (f, f),
        (None, None) => {
            return Err(
                "no positive focal length fits the views (boards too few or too similar)".into(),
            );
        }
    };
    let k = Matrix3::new(fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0);
    let kinv = k.try_inverse().ok_or("singular camera matrix")?;
    let poses = homs
        .iter()
        .map(|h| {
            let m = kinv * h;
            let (c0, c1, c2) = (
                m.column(0).into_owned(),
                m.column(1).into_owned(),
                m.column(2).into_owned(),
            );
            let mut l = 2.0 / (c0.norm() + c1.norm());
            if c2.z * l < 0.0 {
                l = -l;
            }
            let (r1, r2, t) = (c0 * l, c1 * l, c2 * l);
            let r = Matrix3::from_columns(&[r1, r2, r1.cross(&r2)]);
            let svd = r.svd(true, true);
            let (u, vt) = (svd.u.unwrap(), svd.v_t.unwrap());
            let mut rot = u * vt;
            if rot.determinant() < 0.0 {
                rot = -rot;
            }
            let om = Rotation3::from_matrix_unchecked(rot).scaled_axis();
            [om.x, om.y, om.z, t.x, t.y, t.z]
        })
        .collect();
    Ok(([fx, fy, cx, cy, 0.0, 0.0, 0.0, 0.0, 0.0], poses))
}

/// Difference steps for a camera's nine terms.
const CAMERA_STEPS: [f64; 9] = [1e-3, 1e-3, 1e-3, 1e-3, 1e-6, 1e-6, 1e-7, 1e-7, 1e-6];

fn pose_steps(p: &Pose) -> [f64; 6] {
    let s = 1e-6 * (p[3].abs() + p[4].abs() + p[5].abs()).max(1.0);
    [1e-7, 1e-7, 1e-7, s, s, s]
}

/// Calibrates one camera from views of a planar board: `object` holds the board's corners
/// (its plane z = 0), `views[i]` where they are in image `i` of `size`.
pub fn calibrate_camera(
    views: &[Vec<[f64; 2]>],
    object: &[[f64; 2]],
    size: (usize, usize),
) -> Result<Mono, String> {
    if views.len() < 3 {
        return Err(format!(
            "{} views; a camera needs at least 3 boards at different angles",
            views.len()
        ));
    }
    let (camera, poses) = initial(views, object, size)?;
    let n = views.len();
    let mut p: Vec<f64> = camera.to_vec();
    for pose in &poses {
        p.extend_from_slice(pose);
    }
    let mut steps = CAMERA_STEPS.to_vec();
    for pose in &poses {
        steps.extend_from_slice(&pose_steps(pose));
    }
    let res = |p: &[f64], r: &mut Vec<f64>| {
        r.clear();
        for (i, v) in views.iter().enumerate() {
            let pose = &p[9 + 6 * i..15 + 6 * i];
            for (o, m) in object.iter().zip(v) {
                let q = project(&p[..9], pose, [o[0], o[1], 0.0]);
                r.push(q[0] - m[0]);
                r.push(q[1] - m[1]);
            }
        }
    };
    let cost = minimise(&mut p, &steps, &res, 200);
    let mut camera = [0.0; 9];
    camera.copy_from_slice(&p[..9]);
    Ok(Mono {
        camera,
        poses: (0..n)
            .map(|i| p[9 + 6 * i..15 + 6 * i].try_into().expect("six"))
            .collect(),
        rms: rms_of(cost, n * object.len()),
    })
}

/// Calibrates a stereo pair from pairs of views of a planar board (`left[i]` and
/// `right[i]` the same board's corners, in `object`'s order): each camera alone, then
/// both with their relative pose, every term refined together.
pub fn calibrate_stereo(
    left: &[Vec<[f64; 2]>],
    right: &[Vec<[f64; 2]>],
    object: &[[f64; 2]],
    size: (usize, usize),
) -> Result<Stereo, String> {
    if left.len() != right.len() {
        return Err("as many left views as right views are needed".into());
    }
    let ml = calibrate_camera(left, object, size).map_err(|e| format!("left camera: {e}"))?;
    let mr = calibrate_camera(right, object, size).map_err(|e| format!("right camera: {e}"))?;
    // The relative pose: the median of the pairs' (as OpenCV starts it).
    let n = left.len();
    let rel: Vec<Pose> = (0..n)
        .map(|i| {
            let inv = invert(&ml.poses[i]);
            compose(&mr.poses[i], &inv)
        })
        .collect();
    let mut start = [0.0; 6];
    for (k, s) in start.iter_mut().enumerate() {
        let mut v: Vec<f64> = rel.iter().map(|p| p[k]).collect();
        v.sort_by(f64::total_cmp);
        *s = v[n / 2];
    }
    let mut p: Vec<f64> = ml.camera.to_vec();
    p.extend_from_slice(&mr.camera);
    p.extend_from_slice(&start);
    for pose in &ml.poses {
        p.extend_from_slice(pose);
    }
    let mut steps = CAMERA_STEPS.to_vec();
    steps.extend_from_slice(&CAMERA_STEPS);
    steps.extend_from_slice(&pose_steps(&start));
    for pose in &ml.poses {
        steps.extend_from_slice(&pose_steps(pose));
    }
    let pair_sq = |p: &[f64], i: usize, mut f: Box<dyn FnMut(f64, f64) + '_>| {
        let pl = &p[24 + 6 * i..30 + 6 * i];
        let pr = compose(&p[18..24], pl);
        for (o, (a, b)) in object.iter().zip(left[i].iter().zip(&right[i])) {
            let x = [o[0], o[1], 0.0];
            let ql = project(&p[..9], pl, x);
            let qr = project(&p[9..18], &pr, x);
            f(ql[0] - a[0], ql[1] - a[1]);
            f(qr[0] - b[0], qr[1] - b[1]);
        }
    };
    let res = |p: &[f64], r: &mut Vec<f64>| {
        r.clear();
        for i in 0..n {
            pair_sq(
                p,
                i,
                Box::new(|dx, dy| {
                    r.push(dx);
                    r.push(dy);
                }),
            );
        }
    };
    let cost = minimise(&mut p, &steps, &res, 200);
    let std = standard_errors(&p, &steps, &res, cost);
    let pair_rms = (0..n)
        .map(|i| {
            let mut s = 0.0;
            pair_sq(&p, i, Box::new(|dx, dy| s += dx * dx + dy * dy));
            rms_of(s, 2 * object.len())
        })
        .collect();
    let cam = |s: &[f64]| -> Intrinsics { s.try_into().expect("nine") };
    Ok(Stereo {
        left: cam(&p[..9]),
        right: cam(&p[9..18]),
        r: Rotation3::new(Vector3::new(p[18], p[19], p[20])).into_inner(),
        t: Vector3::new(p[21], p[22], p[23]),
        poses: (0..n)
            .map(|i| p[24 + 6 * i..30 + 6 * i].try_into().expect("six"))
            .collect(),
        rms: rms_of(cost, 2 * n * object.len()),
        pair_rms,
        std,
    })
}

/// The standard errors of the left `fx`, the right `fx` and the baseline `|t|` at the
/// stereo fit `p` (covariance `σ²·(JᵀJ)⁻¹`, σ² the residuals' variance); infinite where the
/// normal matrix is singular.
fn standard_errors(
    p: &[f64],
    steps: &[f64],
    res: &dyn Fn(&[f64], &mut Vec<f64>),
    cost: f64,
) -> [f64; 3] {
    let (mut rp, mut rm) = (Vec::new(), Vec::new());
    res(p, &mut rp);
    let m = rp.len();
    let n = p.len();
    let mut jac = nalgebra::DMatrix::<f64>::zeros(m, n);
    let mut q = p.to_vec();
    for j in 0..n {
        q[j] = p[j] + steps[j];
        res(&q, &mut rp);
        q[j] = p[j] - steps[j];
        res(&q, &mut rm);
        q[j] = p[j];
        for i in 0..m {
            jac[(i, j)] = (rp[i] - rm[i]) / (2.0 * steps[j]);
        }
    }
    let sigma2 = cost / (m as f64 - n as f64).max(1.0);
    let Some(cov) = (jac.transpose() * &jac).try_inverse() else {
        return [f64::INFINITY; 3];
    };
    let t = Vector3::new(p[21], p[22], p[23]);
    let g = t / t.norm().max(1e-300);
    let mut vb = 0.0;
    for a in 0..3 {
        for b in 0..3 {
            vb += g[a] * g[b] * cov[(21 + a, 21 + b)];
        }
    }
    [cov[(0, 0)], cov[(9, 9)], vb].map(|v| (v * sigma2).max(0.0).sqrt())
}

/// How well `rect` puts a board's rows on image rows: the largest difference, over every
/// row of `cols` corners of every pair of views, between the row's mean rectified image
/// row in the left view and in the right.
pub fn row_gap(rect: &crate::stereo::Rectification, pairs: &[PairView], cols: usize) -> f64 {
    let mut worst: f64 = 0.0;
    for (l, r) in pairs {
        for b in 0..l.len() / cols {
            let mean = |v: &[[f64; 2]], right: bool| {
                v[b * cols..(b + 1) * cols]
                    .iter()
                    .map(|p| rect.point(right, p[0], p[1]).1)
                    .sum::<f64>()
                    / cols as f64
            };
            worst = worst.max((mean(l, false) - mean(r, true)).abs());
        }
    }
    worst
}

/// The inverse of a pose.
fn invert(a: &[f64]) -> Pose {
    let r = Rotation3::new(Vector3::new(a[0], a[1], a[2])).inverse();
    let t = -(r * Vector3::new(a[3], a[4], a[5]));
    let om = r.scaled_axis();
    [om.x, om.y, om.z, t.x, t.y, t.z]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn board(cols: usize, rows: usize, square: f64) -> Vec<[f64; 2]> {
        (0..rows)
            .flat_map(|b| (0..cols).map(move |a| [a as f64 * square, b as f64 * square]))
            .collect()
    }

    /// Boards at varied tilts in front of a rig with a known calibration.
    fn views(
        cam: &[f64],
        rel: &Pose,
        object: &[[f64; 2]],
    ) -> (Vec<Corners>, Vec<Corners>, Vec<Pose>) {
        let mut l = Vec::new();
        let mut r = Vec::new();
        let mut poses = Vec::new();
        for i in 0..10 {
            let a = i as f64;
            let pose = [
                0.35 * (a * 0.9).sin(),
                0.3 * (a * 1.7).cos(),
                0.1 * (a * 0.5).sin(),
                -100.0 + 6.0 * a,
                -60.0 + 4.0 * (a * 1.3).sin(),
                480.0 + 15.0 * a,
            ];
            let pr = compose(rel, &pose);
            l.push(
                object
                    .iter()
                    .map(|o| project(&cam[..9], &pose, [o[0], o[1], 0.0]))
                    .collect(),
            );
            r.push(
                object
                    .iter()
                    .map(|o| project(&cam[9..], &pr, [o[0], o[1], 0.0]))
                    .collect(),
            );
            poses.push(pose);
        }
        (l, r, poses)
    }

    #[test]
    fn exact_corners_give_back_the_rig() {
        let cams = [
            533.0, 531.0, 342.0, 235.0, -0.28, 0.04, 0.0012, -0.0001, 0.12, //
            537.0, 536.0, 327.0, 250.0, -0.29, 0.14, -0.0005, 0.0001, -0.05,
        ];
        let rel: Pose = [0.004, 0.0071, -0.0035, -83.3, 1.1, 0.2];
        let object = board(9, 6, 25.0);
        let (l, r, _) = views(&cams, &rel, &object);
        let s = calibrate_stereo(&l, &r, &object, (640, 480)).unwrap();
        assert!(s.rms < 1e-6, "rms {}", s.rms);
        for (got, want) in s.left.iter().chain(&s.right).zip(&cams) {
            assert!(
                (got - want).abs() < 1e-4 * want.abs().max(0.01),
                "{got} vs {want}"
            );
        }
        assert!((s.t.norm() - Vector3::<f64>::new(-83.3, 1.1, 0.2).norm()).abs() < 1e-6);
    }

    #[test]
    fn noisy_corners_give_the_rig_within_their_noise() {
        let cams = [
            800.0, 800.0, 320.0, 240.0, -0.1, 0.02, 0.0, 0.0, 0.0, //
            805.0, 803.0, 318.0, 244.0, -0.12, 0.03, 0.0, 0.0, 0.0,
        ];
        let rel: Pose = [0.0, 0.02, 0.0, -60.0, 0.0, 0.0];
        let object = board(9, 6, 25.0);
        let (mut l, mut r, _) = views(&cams, &rel, &object);
        // Deterministic noise of 0.2 px rms.
        let mut k = 0u64;
        let mut noise = || {
            k = k
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((k >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 0.2 * 12f64.sqrt()
        };
        for v in l.iter_mut().chain(r.iter_mut()) {
            for p in v.iter_mut() {
                p[0] += noise();
                p[1] += noise();
            }
        }
        let s = calibrate_stereo(&l, &r, &object, (640, 480)).unwrap();
        // 0.2 px a coordinate is 0.28 px a corner, less the share the fit's 90 terms absorb.
        assert!((s.rms - 0.2 * 2f64.sqrt()).abs() < 0.02, "rms {}", s.rms);
        assert!((s.t.norm() - 60.0).abs() < 0.3, "baseline {}", s.t.norm());
        assert!((s.left[0] - 800.0).abs() < 4.0, "fx {}", s.left[0]);
    }
}
