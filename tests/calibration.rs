//! `calibrate-stereo` end to end on the OpenCV sample chessboard pairs
//! (tests/data/calibration/pairs), and the calibration file it writes read by the
//! rectifier (in the graph) and by `reconstruct` on a raw pair.

mod common;

use calibration::board::find_board;
use common::{assert_clean_failure, run, s};
use matcher::{Mode, node::Region};
use pipelines::stereo::Stereo;
use schemas::{DisparityRange, StereoFrame};
use std::path::{Path, PathBuf};
use std::process::Output;

fn pairs() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/calibration/pairs")
}

/// `calibrate-stereo SRC --inner INNER --square SQUARE --unit mm -o OUT`, then `extra`.
fn calibrate(src: &Path, inner: &str, square: &str, out: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "calibrate-stereo",
        s(src),
        "--inner",
        inner,
        "--square",
        square,
        "--unit",
        "mm",
        "-o",
        s(out),
    ];
    args.extend(extra);
    run(&args)
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
    let file = calibration::file::read_file(&cal).unwrap();
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
        let f = preset.run_once().unwrap();
        let frame: StereoFrame = f.read(&preset.outs().frame).unwrap();
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
    let o = calibrate(&src, "9x6", "25", &out, &[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("pair 99: left view: board not found"), "{err}");
    assert!(String::from_utf8_lossy(&o.stdout).contains("4 of 5 pairs used"));
    assert!(out.join("corners/99.png").exists());
    // A pair that fits worse than the limit is left out and the rest refitted.
    let o = calibrate(
        &src,
        "9x6",
        "25",
        &dir.path().join("strict"),
        &["--max-pair-rms", "0.05"],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("fits badly (RMS") && err.contains("left out, refitting"),
        "{err}"
    );
    assert!(
        String::from_utf8_lossy(&o.stdout).contains("3 of 5 pairs used"),
        "{}",
        String::from_utf8_lossy(&o.stdout)
    );
    // Too few usable pairs, a wrong board size, no pairs, a bad square: one clear error.
    std::fs::remove_file(src.join("left04.jpg")).unwrap();
    std::fs::remove_file(src.join("left03.jpg")).unwrap();
    let o = calibrate(&src, "9x6", "25", &dir.path().join("c2"), &[]);
    assert_clean_failure(&o, "2 usable pairs of 3");
    let o = calibrate(&src, "7x5", "25", &dir.path().join("c3"), &[]);
    assert_clean_failure(&o, "usable pairs");
    let o = calibrate(dir.path(), "9x6", "25", &dir.path().join("c4"), &[]);
    assert_clean_failure(&o, "no image pairs in");
    let o = calibrate(&src, "9", "25", &dir.path().join("c5"), &[]);
    assert_clean_failure(&o, "COLSxROWS");
    let o = calibrate(&src, "9x6", "-2", &dir.path().join("c6"), &[]);
    assert_clean_failure(&o, "--square");
}

/// The numbers of `key = [...]` in a calibration file's text.
fn numbers(text: &str, key: &str) -> Vec<f64> {
    let line = text
        .lines()
        .find(|l| l.starts_with(&format!("{key} = ")))
        .unwrap();
    line.split_once('=')
        .unwrap()
        .1
        .trim()
        .trim_matches(['[', ']'])
        .split(',')
        .map(|v| v.trim().parse().unwrap())
        .collect()
}

#[test]
fn calibrations_import_and_export_opencv_yaml_and_camera_info_unchanged() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    let fixture = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/calibration/opencv_chessboard_stereo.yaml");
    let ok = |o: Output| assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    ok(run(&[
        "calibration",
        "import",
        "--opencv",
        s(&fixture),
        "--unit",
        "mm",
        "-o",
        s(&p("a.toml")),
    ]));
    ok(run(&[
        "calibration",
        "export",
        s(&p("a.toml")),
        "--opencv",
        s(&p("b.yaml")),
        "--camera-info",
        s(&p("l.yaml")),
        s(&p("r.yaml")),
    ]));
    ok(run(&[
        "calibration",
        "import",
        "--opencv",
        s(&p("b.yaml")),
        "--unit",
        "mm",
        "-o",
        s(&p("b.toml")),
    ]));
    ok(run(&[
        "calibration",
        "import",
        "--camera-info",
        s(&p("l.yaml")),
        s(&p("r.yaml")),
        "--unit",
        "mm",
        "-o",
        s(&p("c.toml")),
    ]));
    let text = |n: &str| std::fs::read_to_string(p(n)).unwrap();
    for other in ["b.toml", "c.toml"] {
        for key in ["k1", "d1", "k2", "d2", "r", "t"] {
            let (x, y) = (numbers(&text("a.toml"), key), numbers(&text(other), key));
            assert_eq!(x.len(), y.len());
            for (u, v) in x.iter().zip(&y) {
                assert!(
                    (u - v).abs() < 1e-9 * u.abs().max(1.0),
                    "{other} {key}: {u} vs {v}"
                );
            }
        }
    }
    // The exported camera_info rectify exactly as the file's own cameras do.
    let a = calibration::file::read_file(&p("a.toml")).unwrap();
    let ours = calibration::stereo::Rectification::bouguet(&a.cameras("a").unwrap().unwrap());
    let theirs =
        calibration::stereo::Rectification::from_camera_info(&text("l.yaml"), &text("r.yaml"))
            .unwrap();
    for (x, y) in [(10.0, 20.0), (320.0, 240.0), (600.0, 450.0)] {
        for right in [false, true] {
            let (u, v) = (ours.point(right, x, y), theirs.point(right, x, y));
            assert!(
                (u.0 - v.0).abs() < 1e-6 && (u.1 - v.1).abs() < 1e-6,
                "{u:?} vs {v:?}"
            );
        }
    }
    // ROS's Tx = −fx·B with B in metres (the file's baseline is in mm), and OpenCV's Q
    // puts a disparity at the depth the file's geometry gives it.
    let after = |text: &str, key: &str| -> Vec<f64> {
        let from = text.find(key).unwrap();
        let data = &text[from..];
        let (open, close) = (data.find('[').unwrap(), data.find(']').unwrap());
        data[open + 1..close]
            .split(',')
            .map(|v| v.trim().parse().unwrap())
            .collect()
    };
    let p2 = after(&text("r.yaml"), "projection_matrix");
    let want = -p2[0] * ours.baseline * 1e-3;
    assert!(
        (p2[3] - want).abs() < 1e-9 * want.abs(),
        "Tx {} vs {want}",
        p2[3]
    );
    assert!(
        (-p2[3] / p2[0] - 0.08318).abs() < 5e-5,
        "B {} m",
        -p2[3] / p2[0]
    );
    let q = after(&text("b.yaml"), "Q: !!opencv-matrix");
    let (x, y, d) = (300.0, 200.0, 40.0);
    let row = |r: usize| q[4 * r] * x + q[4 * r + 1] * y + q[4 * r + 2] * d + q[4 * r + 3];
    let z = row(2) / row(3);
    let truth = ours.f * ours.baseline / (d - (ours.c[0] - ours.cx_right));
    assert!(
        (z - truth).abs() < 1e-9 * truth,
        "Q gives Z {z}, the geometry {truth}"
    );
    assert!((row(0) / row(3) - (x - ours.c[0]) * truth / ours.f).abs() < 1e-6);
    // OpenCV's own result: the same cameras (only its rectification's scale differs).
    let cv = calibration::stereo::StereoCalibration::from_opencv_yaml(
        &std::fs::read_to_string(&fixture).unwrap(),
    )
    .unwrap();
    assert!((a.baseline - cv.t.norm()).abs() < 0.05 * cv.t.norm());
    // Nothing to export, an input as the output, a file that is not a calibration.
    let synthetic = p("geometry.toml");
    std::fs::write(
        &synthetic,
        "baseline = 1200.0\nfocal_px = 4000.0\nunit = \"um\"\n",
    )
    .unwrap();
    assert_clean_failure(
        &run(&[
            "calibration",
            "export",
            s(&synthetic),
            "--opencv",
            s(&p("x.yaml")),
        ]),
        "has no [stereo] table",
    );
    assert_clean_failure(
        &run(&[
            "calibration",
            "import",
            "--opencv",
            s(&p("b.yaml")),
            "--unit",
            "mm",
            "-o",
            s(&p("b.yaml")),
            "--overwrite",
        ]),
        "would be overwritten",
    );
    assert_clean_failure(
        &run(&[
            "calibration",
            "import",
            "--opencv",
            s(&synthetic),
            "--unit",
            "mm",
            "-o",
            s(&p("y.toml")),
        ]),
        "no 'K1' matrix",
    );
}

#[test]
fn calibrate_depth_writes_into_a_calibration_file_and_keeps_its_cameras() {
    let dir = tempfile::tempdir().unwrap();
    let st = dir.path().join("stack");
    let o = run(&[
        "synth",
        "-o",
        s(&st),
        "--stage-heights=-120,0,120",
        "--f-eff",
        "18000",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let fixture = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/calibration/opencv_chessboard_stereo.yaml");
    let file = dir.path().join("rig.toml");
    assert!(
        run(&[
            "calibration",
            "import",
            "--opencv",
            s(&fixture),
            "--unit",
            "mm",
            "-o",
            s(&file)
        ])
        .status
        .success()
    );
    let before = calibration::file::read_file(&file).unwrap();
    let o = run(&[
        "calibrate-depth",
        s(&st),
        "--baseline",
        "1200",
        "--pixel-pitch",
        "5",
        "--working-distance",
        "3600",
        "--into",
        s(&file),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let after = calibration::file::read_file(&file).unwrap();
    let f_eff = after.f_eff.unwrap();
    assert!((f_eff / 18000.0 - 1.0).abs() < 0.01, "f_eff {f_eff}");
    assert_eq!(after.unit, Some(schemas::LengthUnit::Um));
    let (b, a) = (before.stereo.unwrap(), after.stereo.unwrap());
    assert_eq!((a.k1, a.d1.clone(), a.r), (b.k1, b.d1.clone(), b.r));
    for (x, y) in a.t.iter().zip(&b.t) {
        assert!((x - 1000.0 * y).abs() < 1e-9 * x.abs(), "{x} vs {y} mm");
    }
    // Never into the scene's own truth.
    let truth = st.join("calibration.toml");
    assert_clean_failure(
        &run(&[
            "calibrate-depth",
            s(&st),
            "--baseline",
            "1200",
            "--into",
            s(&truth),
        ]),
        "would be overwritten",
    );
}

#[test]
fn calibrate_manipulator_registers_a_mounted_sim_and_the_bridge_reads_it() {
    let dir = tempfile::tempdir().unwrap();
    let reg = dir.path().join("registration.toml");
    let mount = ["--sim-mount", "30,1.1,-1,0.9,1200,-300,5000"];
    let mut args = vec!["calibrate-manipulator", "-o", s(&reg)];
    args.extend(mount);
    let o = run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("one axis flipped"), "{stdout}");
    // The bridge reads the file; its matrix is the mounting's within 1.5 %.
    let params = manipulator_bridge::node::BridgeParams::from_table(
        &toml::from_str(&format!("registration = {:?}", s(&reg))).unwrap(),
    )
    .unwrap();
    let r = params.registration().unwrap();
    let truth = registration::mount(&[30.0, 1.1, -1.0, 0.9, 1200.0, -300.0, 5000.0]).unwrap();
    for (a, b) in r.matrix.iter().zip(&truth.matrix) {
        assert!(
            (a - b).abs() < 0.015,
            "{:?} vs {:?}",
            r.matrix,
            truth.matrix
        );
    }
    // A pipette change: one stop re-registers the offset on the same axes.
    let re = dir.path().join("re.toml");
    let mut args = vec![
        "calibrate-manipulator",
        "--offset-only",
        s(&reg),
        "-o",
        s(&re),
    ];
    args.extend(mount);
    let o = run(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let again = manipulator_bridge::registration::Registration::read(s(&re)).unwrap();
    assert_eq!(again.matrix, r.matrix);
    let moved: f64 = (0..3)
        .map(|k| (again.offset[k] - r.offset[k]).powi(2))
        .sum::<f64>()
        .sqrt();
    assert!(
        moved < 3.0,
        "the same pipette re-registered {moved:.2} µm away"
    );
    // Bad input: one clear error each, nothing written over.
    let text = std::fs::read_to_string(&reg).unwrap();
    assert_clean_failure(
        &run(&["calibrate-manipulator", "-o", s(&reg)]),
        "add --overwrite",
    );
    assert_clean_failure(
        &run(&[
            "calibrate-manipulator",
            "--grid",
            "1x1x1",
            "-o",
            s(&dir.path().join("x.toml")),
        ]),
        "--grid",
    );
    assert_clean_failure(
        &run(&[
            "calibrate-manipulator",
            "--sim-mount",
            "30,1",
            "-o",
            s(&dir.path().join("x.toml")),
        ]),
        "--sim-mount takes 7",
    );
    assert_clean_failure(
        &run(&[
            "calibrate-manipulator",
            "--sim-mount",
            "0,1,0,1,0,0,0",
            "-o",
            s(&dir.path().join("x.toml")),
        ]),
        "determinant",
    );
    assert_clean_failure(
        &run(&[
            "calibrate-manipulator",
            "--device",
            "mp285",
            "-o",
            s(&dir.path().join("x.toml")),
        ]),
        "--port",
    );
    assert_clean_failure(
        &run(&[
            "calibrate-manipulator",
            "--offset-only",
            s(&dir.path().join("none.toml")),
            "-o",
            s(&dir.path().join("x.toml")),
        ]),
        "cannot be read",
    );
    assert_eq!(std::fs::read_to_string(&reg).unwrap(), text);
}
