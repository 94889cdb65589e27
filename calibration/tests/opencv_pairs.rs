//! The OpenCV sample chessboard pairs (tests/data/calibration/pairs, 640×480, 9×6 inner
//! corners of 25 mm) against OpenCV's own calibration of them
//! (scripts/stereo_calibration_fixture.py: RMS 0.215 px, baseline 83.18 mm).

use calibration::board::{Board, find_board};
use calibration::calibrate::{Corners, calibrate_stereo, row_gap};
use calibration::stereo::Rectification;
use schemas::Plane;
use std::path::PathBuf;

fn data() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/data/calibration")
}

fn object() -> Vec<[f64; 2]> {
    (0..6)
        .flat_map(|b| (0..9).map(move |a| [25.0 * a as f64, 25.0 * b as f64]))
        .collect()
}

/// OpenCV's corners, per pair (left, right).
fn opencv_corners() -> Vec<(u64, Corners, Corners)> {
    let text = std::fs::read_to_string(data().join("opencv_chessboard_corners.json")).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    let pts = |x: &serde_json::Value| -> Vec<[f64; 2]> {
        x.as_array()
            .unwrap()
            .iter()
            .map(|p| [p[0].as_f64().unwrap(), p[1].as_f64().unwrap()])
            .collect()
    };
    v.as_array()
        .unwrap()
        .iter()
        .map(|p| {
            (
                p["pair"].as_u64().unwrap(),
                pts(&p["left"]),
                pts(&p["right"]),
            )
        })
        .collect()
}

const OPENCV_RMS: f64 = 0.215;
const OPENCV_BASELINE: f64 = 83.176;

/// Calibrates the pairs and checks the baseline against OpenCV's and the rectified board
/// rows (within 0.5 px); the fit.
fn calibrate_and_check(l: &[Corners], r: &[Corners], what: &str) -> calibration::calibrate::Stereo {
    let s = calibrate_stereo(l, r, &object(), (640, 480)).unwrap();
    let baseline = s.t.norm();
    eprintln!(
        "{what}: RMS {:.4} px (OpenCV {OPENCV_RMS}), baseline {baseline:.3} mm (OpenCV {OPENCV_BASELINE}), per pair {:?}",
        s.rms, s.pair_rms
    );
    assert!(
        (baseline / OPENCV_BASELINE - 1.0).abs() <= 0.005,
        "baseline {baseline}"
    );
    let rect = Rectification::bouguet(&s.calibration((640, 480)));
    let both: Vec<calibration::calibrate::PairView> =
        l.iter().zip(r).map(|(a, b)| (&a[..], &b[..])).collect();
    let worst = row_gap(&rect, &both, 9);
    eprintln!("worst board row difference after rectification {worst:.3} px");
    assert!(worst <= 0.5, "{worst}");
    s
}

#[test]
fn on_opencvs_corners_the_rig_matches_opencvs() {
    let pairs = opencv_corners();
    let (l, r): (Vec<_>, Vec<_>) = pairs.iter().map(|p| (p.1.clone(), p.2.clone())).unzip();
    let s = calibrate_and_check(&l, &r, "on OpenCV's corners");
    assert!((s.rms / OPENCV_RMS - 1.0).abs() <= 0.1, "rms {}", s.rms);
}

fn grey(path: &std::path::Path) -> Plane<u8> {
    let img = image::open(path).unwrap().to_luma8();
    let (w, h) = img.dimensions();
    Plane::from_vec(w as usize, h as usize, img.into_raw()).unwrap()
}

#[test]
fn our_corners_are_opencvs_and_calibrate_the_same_rig() {
    let pairs = opencv_corners();
    let mut ours = Vec::new();
    let mut worst_corner: f64 = 0.0;
    let mut sq = (0.0, 0usize);
    for (i, lcv, rcv) in &pairs {
        let find = |side: &str| {
            find_board(&grey(&data().join(format!("pairs/{side}{i:02}.jpg"))), 9, 6).unwrap()
        };
        let l = find("left");
        let mut r = find("right");
        r.align_to(&l);
        // OpenCV may list a board from its other end: compare in the order nearest to it.
        for (b, cv) in [(&l, lcv), (&r, rcv)] {
            let flipped: Vec<_> = b.corners.iter().rev().copied().collect();
            let d = |v: &[[f64; 2]]| -> Vec<f64> {
                v.iter()
                    .zip(cv)
                    .map(|(p, q)| (p[0] - q[0]).hypot(p[1] - q[1]))
                    .collect()
            };
            let (a, f) = (d(&b.corners), d(&flipped));
            let e = if a.iter().sum::<f64>() < f.iter().sum::<f64>() {
                a
            } else {
                f
            };
            for x in e {
                worst_corner = worst_corner.max(x);
                sq.0 += x * x;
                sq.1 += 1;
            }
        }
        ours.push((l, r));
    }
    let rms_corner = (sq.0 / sq.1 as f64).sqrt();
    eprintln!("our corners against OpenCV's: rms {rms_corner:.3} px, worst {worst_corner:.3} px");
    assert!(
        rms_corner < 0.1 && worst_corner < 0.5,
        "{rms_corner} {worst_corner}"
    );
    let (l, r): (Vec<_>, Vec<_>) = ours
        .iter()
        .map(|(l, r): &(Board, Board)| (l.corners.clone(), r.corners.clone()))
        .unzip();
    let s = calibrate_and_check(&l, &r, "on our corners");
    assert!((s.rms / OPENCV_RMS - 1.0).abs() <= 0.1, "rms {}", s.rms);
}
