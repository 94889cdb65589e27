//! Bouguet rectification on a real calibration (OpenCV's chessboard pairs, computed once by
//! scripts/stereo_calibration_fixture.py): the rotations agree with OpenCV's, and the corners
//! of every pair land on the same rows.

use calibration::stereo::{Rectification, StereoCalibration};

fn data(name: &str) -> String {
    std::fs::read_to_string(format!(
        "{}/../../tests/data/calibration/{name}",
        env!("CARGO_MANIFEST_DIR")
    ))
    .unwrap()
}

fn matrix(text: &str, key: &str) -> Vec<f64> {
    let i = text.find(&format!("{key}:")).unwrap();
    let rest = &text[i..];
    let (a, b) = (rest.find('[').unwrap(), rest.find(']').unwrap());
    rest[a + 1..b]
        .split(',')
        .map(|v| v.trim().parse().unwrap())
        .collect()
}

#[test]
fn rotations_match_opencv_and_corners_share_rows() {
    let yaml = data("opencv_chessboard_stereo.yaml");
    let cal = StereoCalibration::from_opencv_yaml(&yaml).unwrap();
    assert_eq!(cal.size, (640, 480));
    let rect = Rectification::bouguet(&cal);
    for (ours, key) in [(&rect.r1, "R1"), (&rect.r2, "R2")] {
        let cv = matrix(&yaml, key);
        for r in 0..3 {
            for c in 0..3 {
                assert!(
                    (ours[(r, c)] - cv[r * 3 + c]).abs() < 1e-9,
                    "{key} ({r},{c})"
                );
            }
        }
    }
    assert!((rect.baseline - 83.18).abs() < 0.05, "{}", rect.baseline);
    let pairs: Vec<serde_json::Value> =
        serde_json::from_str(&data("opencv_chessboard_corners.json")).unwrap();
    assert_eq!(pairs.len(), 13);
    let mut all = Vec::new();
    let mut worst_row: f64 = 0.0;
    for p in &pairs {
        let (l, r) = (
            p["left"].as_array().unwrap(),
            p["right"].as_array().unwrap(),
        );
        assert_eq!((l.len(), r.len()), (54, 54));
        let dy: Vec<f64> = l
            .iter()
            .zip(r)
            .map(|(a, b)| {
                let (_, yl) = rect.point(false, a[0].as_f64().unwrap(), a[1].as_f64().unwrap());
                let (_, yr) = rect.point(true, b[0].as_f64().unwrap(), b[1].as_f64().unwrap());
                yl - yr
            })
            .collect();
        // Each board row (9 corners) lies on one image row in both views: averaging the
        // row takes out the corner detector's own noise (RMS 0.2 px), which no
        // rectification can remove.
        for row in dy.chunks(9) {
            worst_row = worst_row.max((row.iter().sum::<f64>() / 9.0).abs());
        }
        // Single corners: as close as OpenCV's own rectification of the same corners gets
        // (its new camera differs a little from ours, so within 10 %).
        let worst = dy.iter().fold(0.0f64, |m, d| m.max(d.abs()));
        let cv = p["opencv_dy_max"].as_f64().unwrap();
        assert!(
            worst <= 1.1 * cv + 0.02,
            "pair {}: {worst:.3} px vs OpenCV {cv:.3}",
            p["pair"]
        );
        all.extend(dy.iter().map(|d| d.abs()));
    }
    all.sort_by(f64::total_cmp);
    let median = all[all.len() / 2];
    let p95 = all[all.len() * 95 / 100];
    eprintln!(
        "board rows within {worst_row:.3} px; corners: median {median:.3} px, 95th percentile {p95:.3} px, worst {:.3}",
        all[all.len() - 1]
    );
    assert!(worst_row <= 0.5, "a board row is {worst_row:.3} px apart");
    assert!(median < 0.15 && p95 < 0.5, "median {median}, p95 {p95}");
}

#[test]
fn bad_calibration_files_say_what_is_missing() {
    let e =
        StereoCalibration::from_opencv_yaml("%YAML 1.2\nK1: !!opencv-matrix\n   data: [ 1, 2 ]\n")
            .unwrap_err();
    assert!(e.contains("'K1' has 2 numbers"), "{e}");
    let e = StereoCalibration::from_opencv_yaml("image_width: 10\n").unwrap_err();
    assert!(e.contains("no 'K1'"), "{e}");
}

#[test]
fn the_resampling_table_inverts_the_point_map() {
    let cal = StereoCalibration::from_opencv_yaml(&data("opencv_chessboard_stereo.yaml")).unwrap();
    let rect = Rectification::bouguet(&cal);
    for right in [false, true] {
        for y in (40..440).step_by(50) {
            for x in (40..600).step_by(70) {
                let (u, v) = rect.point(right, x as f64, y as f64);
                let (xs, ys) = rect.source(right, u, v);
                assert!(
                    (xs - x as f64).abs() < 1e-6 && (ys - y as f64).abs() < 1e-6,
                    "{right} ({x}, {y}) → ({u}, {v}) → ({xs}, {ys})"
                );
            }
        }
    }
    // The table samples the source where the map says: a ramp image comes back as the
    // source x coordinate of every rectified pixel.
    let ramp = schemas::Plane::from_vec(
        640,
        480,
        (0..480)
            .flat_map(|_| (0..640).map(|x| (x / 3) as u8))
            .collect(),
    )
    .unwrap();
    let lut = rectify::RemapLut::new(&rect.clone().into(), false, 640, 480);
    let out = lut.apply(&ramp);
    let (xs, _) = rect.source(false, 320.0, 240.0);
    assert!(
        (*out.get(320, 240) as f64 - xs / 3.0).abs() <= 1.0,
        "{} vs {}",
        out.get(320, 240),
        xs / 3.0
    );
}

#[test]
fn ros_camera_info_pairs_rectify_like_opencv() {
    let rect = Rectification::from_camera_info(
        &data("opencv_chessboard_left_camera_info.yaml"),
        &data("opencv_chessboard_right_camera_info.yaml"),
    )
    .unwrap();
    assert_eq!(rect.size(), (640, 480));
    // ROS gives the baseline in metres: the 83.18 mm of the OpenCV calibration.
    assert!((rect.baseline - 0.08318).abs() < 5e-5, "{}", rect.baseline);
    let pairs: Vec<serde_json::Value> =
        serde_json::from_str(&data("opencv_chessboard_corners.json")).unwrap();
    for p in &pairs {
        let (l, r) = (
            p["left"].as_array().unwrap(),
            p["right"].as_array().unwrap(),
        );
        let worst = l
            .iter()
            .zip(r)
            .map(|(a, b)| {
                let (_, yl) = rect.point(false, a[0].as_f64().unwrap(), a[1].as_f64().unwrap());
                let (_, yr) = rect.point(true, b[0].as_f64().unwrap(), b[1].as_f64().unwrap());
                (yl - yr).abs()
            })
            .fold(0.0, f64::max);
        // The same rectification as OpenCV's: the same rows to within rounding.
        let cv = p["opencv_dy_max"].as_f64().unwrap();
        assert!(
            (worst - cv).abs() < 0.01,
            "pair {}: {worst} vs {cv}",
            p["pair"]
        );
    }
    let e = Rectification::from_camera_info("image_width: 1\n", "").unwrap_err();
    assert!(e.starts_with("left camera_info:"), "{e}");
}

#[test]
fn pixels_from_outside_the_view_repeat_its_edge() {
    // A black border is an edge no scene has: segmentation took it for the most textured
    // thing in a microscope's rectified frame and its threshold then lost the cells.
    let cal = StereoCalibration::from_opencv_yaml(&data("opencv_chessboard_stereo.yaml")).unwrap();
    let rect = Rectification::bouguet(&cal);
    // OpenCV's rectification keeps the sample rig's frame inside both views: a larger
    // output reaches past them.
    let (w, h) = (800, 600);
    let outside = (0..h)
        .flat_map(|v| (0..w).map(move |u| (u, v)))
        .filter(|&(u, v)| {
            let (x, y) = rect.source(false, u as f64, v as f64);
            !(0.0..=639.0).contains(&x) || !(0.0..=479.0).contains(&y)
        })
        .count();
    assert!(
        outside > 1000,
        "{outside} rectified pixels from outside the view"
    );
    let grey = schemas::Plane::filled(640, 480, 200u8);
    let out = rectify::RemapLut::new(&rect.into(), false, w, h).apply(&grey);
    assert!(out.data.iter().all(|&v| v == 200));
}
