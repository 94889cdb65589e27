//! `calibrate-stereo` end to end on the OpenCV sample chessboard pairs
//! (tests/data/calibration/pairs), and the calibration file it writes read by the
//! rectifier (in the graph) and by `reconstruct` on a raw pair.

use camera_calibration::board::find_board;
use matcher::{Mode, node::Region};
use microstereo::presets::{Stereo, ids};
use microstereo::reconstruct::run_once;
use schemas::{DisparityRange, StereoFrame};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_microstereo"))
        .args(args)
        .output()
        .expect("binary runs")
}

fn pairs() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/calibration/pairs")
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn assert_clean_failure(out: &Output, needle: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "stderr: {err}");
    assert!(!err.contains("panicked"), "panic: {err}");
    assert!(err.contains(needle), "expected '{needle}' in: {err}");
}

/// OpenCV's figures on the same pairs (scripts/stereo_calibration_fixture.py).
const OPENCV_RMS: f64 = 0.215;
const OPENCV_BASELINE: f64 = 83.176;

#[test]
fn calibrate_stereo_matches_opencv_and_its_file_rectifies_the_pairs() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cal");
    let src = pairs();
    let args = [
        "calibrate-stereo",
        s(&src),
        "--inner",
        "9x6",
        "--square",
        "25",
        "--unit",
        "mm",
        "-o",
        s(&out),
    ];
    let o = run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("13 of 13 pairs used"), "{stdout}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let rms = report["rms_px"].as_f64().unwrap();
    let baseline = report["baseline"].as_f64().unwrap();
    assert!((rms / OPENCV_RMS - 1.0).abs() <= 0.1, "RMS {rms}");
    assert!(
        (baseline / OPENCV_BASELINE - 1.0).abs() <= 0.005,
        "baseline {baseline}"
    );
    assert!(report["rectified"]["worst_board_row_px"].as_f64().unwrap() <= 0.5);
    for p in report["pairs"].as_array().unwrap() {
        let name = p["name"].as_str().unwrap();
        assert!(
            out.join("corners").join(format!("{name}.png")).exists(),
            "{name}"
        );
    }
    // The file: the rectified geometry for triangulate, the raw cameras for rectify.
    let cal = out.join("calibration.toml");
    let file = triangulate::calibration::read_file(&cal).unwrap();
    assert!((file.baseline / OPENCV_BASELINE - 1.0).abs() <= 0.005);
    assert!(file.stereo.is_some());
    // A second run keeps the first one's outputs unless told.
    assert_clean_failure(&run(&args), "add --overwrite");

    // The graph's rectify node reads it: in every rectified pair the board's rows lie on
    // the same image rows.
    let mut worst: f64 = 0.0;
    for i in [1, 5, 9, 14] {
        let preset = Stereo {
            rectify: Some(s(&cal).to_string()),
            post: None,
            ..Stereo::whole_frame(
                pairs().join(format!("left{i:02}.jpg")),
                pairs().join(format!("right{i:02}.jpg")),
                Mode::Quality,
                DisparityRange::new(0, 16),
            )
        };
        assert_eq!(preset.matching.region, Region::Frame);
        let f = run_once(&preset).unwrap();
        let frame: StereoFrame = f.decode(ids::RECTIFY, "frame").unwrap();
        let l = find_board(&frame.left, 9, 6).unwrap();
        let mut r = find_board(&frame.right, 9, 6).unwrap();
        r.align_to(&l);
        for (p, q) in l.corners.iter().zip(&r.corners) {
            worst = worst.max((p[1] - q[1]).abs());
        }
    }
    // Every corner, not only each row's mean: within a pixel after resampling.
    assert!(worst < 1.0, "worst corner row difference {worst:.3} px");

    // reconstruct takes a raw pair with the file and rectifies it first; a pair of another
    // size is one clear error.
    let rc = dir.path().join("rc");
    let (l, r) = (pairs().join("left01.jpg"), pairs().join("right01.jpg"));
    let o = run(&[
        "reconstruct",
        s(&l),
        s(&r),
        "-o",
        s(&rc),
        "--calibration",
        s(&cal),
        "--min-disparity",
        "40",
        "--max-disparity",
        "120",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(rc.join("points.ply").exists());
    let small = dir.path().join("small.png");
    image::imageops::resize(
        &image::open(&l).unwrap().to_luma8(),
        320,
        240,
        image::imageops::FilterType::Triangle,
    )
    .save(&small)
    .unwrap();
    let o = run(&[
        "reconstruct",
        s(&small),
        s(&small),
        "-o",
        s(&dir.path().join("rc2")),
        "--calibration",
        s(&cal),
    ]);
    assert_clean_failure(&o, "frames are 320×240 but the calibration is for 640×480");
    // Already rectified: --rectified skips the cameras.
    let o = run(&[
        "reconstruct",
        s(&small),
        s(&small),
        "-o",
        s(&dir.path().join("rc3")),
        "--calibration",
        s(&cal),
        "--rectified",
        "--min-disparity",
        "0",
        "--max-disparity",
        "8",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn calibrate_stereo_reports_and_leaves_out_pairs_without_a_board() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("pairs");
    std::fs::create_dir_all(&src).unwrap();
    for i in [1, 2, 3, 4] {
        for side in ["left", "right"] {
            let name = format!("{side}{i:02}.jpg");
            std::fs::copy(pairs().join(&name), src.join(&name)).unwrap();
        }
    }
    // A pair whose right view shows no board (a blank image).
    image::GrayImage::from_pixel(640, 480, image::Luma([128]))
        .save(src.join("left99.png"))
        .unwrap();
    std::fs::copy(src.join("left99.png"), src.join("right99.png")).unwrap();
    let out = dir.path().join("cal");
    let o = run(&[
        "calibrate-stereo",
        s(&src),
        "--inner",
        "9x6",
        "--square",
        "25",
        "--unit",
        "mm",
        "-o",
        s(&out),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("pair 99: left view: board not found"), "{err}");
    assert!(String::from_utf8_lossy(&o.stdout).contains("4 of 5 pairs used"));
    assert!(out.join("corners/99.png").exists());
    // Too few usable pairs, a wrong board size, no pairs, a bad square: one clear error.
    std::fs::remove_file(src.join("left04.jpg")).unwrap();
    std::fs::remove_file(src.join("left03.jpg")).unwrap();
    let o = run(&[
        "calibrate-stereo",
        s(&src),
        "--inner",
        "9x6",
        "--square",
        "25",
        "--unit",
        "mm",
        "-o",
        s(&dir.path().join("c2")),
    ]);
    assert_clean_failure(&o, "2 usable pairs of 3");
    let o = run(&[
        "calibrate-stereo",
        s(&src),
        "--inner",
        "7x5",
        "--square",
        "25",
        "--unit",
        "mm",
        "-o",
        s(&dir.path().join("c3")),
    ]);
    assert_clean_failure(&o, "usable pairs");
    let o = run(&[
        "calibrate-stereo",
        s(dir.path()),
        "--inner",
        "9x6",
        "--square",
        "25",
        "--unit",
        "mm",
        "-o",
        s(&dir.path().join("c4")),
    ]);
    assert_clean_failure(&o, "no image pairs in");
    let o = run(&[
        "calibrate-stereo",
        s(&src),
        "--inner",
        "9",
        "--square",
        "25",
        "--unit",
        "mm",
        "-o",
        s(&dir.path().join("c5")),
    ]);
    assert_clean_failure(&o, "COLSxROWS");
    let o = run(&[
        "calibrate-stereo",
        s(&src),
        "--inner",
        "9x6",
        "--square",
        "-2",
        "--unit",
        "mm",
        "-o",
        s(&dir.path().join("c6")),
    ]);
    assert_clean_failure(&o, "--square");
}
