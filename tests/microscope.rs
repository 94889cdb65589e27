//! A stereo microscope as it is built: raw views of a CMO and a Greenough microscope
//! (converging ±4–7°, nearly telecentric, off-axis distortion, defocus), rendered by
//! `synth --optics`, calibrated by `calibrate-microscope` from a chessboard at nine stage
//! heights, and a held-out 50 µm stage step measured by `reconstruct` from the raw pairs.

mod common;

use common::{assert_clean_failure, run, s};
use std::path::Path;

/// `synth` into `dir` with the microscope's flags and `extra`.
fn synth(dir: &Path, optics: &[&str], extra: &[&str]) {
    let mut args = vec!["synth", "--width", "1280", "--height", "1024", "-o", s(dir)];
    args.extend_from_slice(optics);
    args.extend_from_slice(extra);
    let out = run(&args);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// `calibrate-microscope` on `stack` (a board of `inner` corners COLS,ROWS with 100 µm
/// squares) into `cal`, with `extra` flags.
fn calibrate(stack: &Path, inner: &str, cal: &Path, extra: &[&str]) -> std::process::Output {
    let corners = inner.replace(',', "x");
    let mut args = vec![
        "calibrate-microscope",
        s(stack),
        "--inner",
        &corners,
        "--square",
        "100",
        "-o",
        s(cal),
    ];
    args.extend_from_slice(extra);
    run(&args)
}

/// `reconstruct --cells` of the raw pair `left`, `right` through calibration file `file` over
/// −12..12 px into `out`; its cells.json.
fn cells_of(left: &Path, right: &Path, file: &Path, out: &Path) -> serde_json::Value {
    let done = run(&[
        "reconstruct",
        s(left),
        s(right),
        "-o",
        s(out),
        "--cells",
        "--calibration",
        s(file),
        "--min-disparity",
        "-12",
        "--max-disparity",
        "12",
    ]);
    assert!(
        done.status.success(),
        "{}",
        String::from_utf8_lossy(&done.stderr)
    );
    serde_json::from_slice(&std::fs::read(out.join("cells.json")).unwrap()).unwrap()
}

/// Calibrates `optics` from a stack of a board of `inner` corners (COLS,ROWS; 100 µm
/// squares) and measures a held-out 50 µm step (a speckle target at stage heights −20 and
/// +30 µm) through it; returns the step measured, µm.
fn held_out_step(optics: &[&str], inner: &str) -> f64 {
    let dir = tempfile::tempdir().unwrap();
    let (stack, cal, step) = (
        dir.path().join("stack"),
        dir.path().join("cal"),
        dir.path().join("step"),
    );
    synth(
        &stack,
        optics,
        &[
            "--stage-heights=-40,-30,-20,-10,0,10,20,30,40",
            "--board",
            inner,
            "--square",
            "100",
        ],
    );
    synth(&step, optics, &["--stage-heights=-20,30"]);
    let out = calibrate(&stack, inner, &cal, &["--check", s(&step)]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("{text}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(cal.join("report.json")).unwrap()).unwrap();
    let m = |i: usize| report["check"][i]["measured"].as_f64().unwrap();
    m(1) - m(0)
}

/// Each microscope `(layout, convergence °, pupils mm, rig seed)` calibrated from a stack
/// of a board of `inner` corners measures the held-out 50 µm step within 0.5 %.
fn steps_hold(microscopes: &[(&str, &str, &str, &str)], inner: &str) {
    for &(layout, convergence, pupil, seed) in microscopes {
        let optics = [
            "--optics",
            layout,
            "--convergence",
            convergence,
            "--pupil",
            pupil,
            "--rig-seed",
            seed,
        ];
        let step = held_out_step(&optics, inner);
        eprintln!("{optics:?}: step {step:.4} µm");
        assert!((step / 50.0 - 1.0).abs() < 0.005, "{optics:?}: {step}");
    }
}

#[test]
fn a_cmo_microscope_calibrated_from_a_stage_stack_measures_a_held_out_step() {
    steps_hold(
        &[("cmo", "5.5", "100", "3"), ("cmo", "4", "400", "5")],
        "9,6",
    );
}

/// A Greenough's focal plane is square to each tilted objective: at 7° the field's edges
/// are 80 µm out of focus and a 9×6 board's outer corners blur away, so its board is the
/// smaller one a user would take.
#[test]
fn a_greenough_microscope_calibrated_from_a_stage_stack_measures_a_held_out_step() {
    steps_hold(
        &[
            ("greenough", "7", "80", "4"),
            ("greenough", "4.5", "150", "6"),
        ],
        "7,5",
    );
}

#[test]
fn a_stack_at_one_height_is_refused_and_nothing_written() {
    let dir = tempfile::tempdir().unwrap();
    let stack = dir.path().join("stack");
    synth(
        &stack,
        &["--optics", "cmo"],
        &[
            "--stage-heights=10,10,10",
            "--board",
            "9,6",
            "--square",
            "100",
        ],
    );
    let cal = dir.path().join("cal");
    let out = calibrate(&stack, "9,6", &cal, &[]);
    assert_clean_failure(&out, "the depth is undetermined");
    assert!(!cal.exists());
}

/// The default graph with its capture reading `left`/`right` (raw views) from files, the
/// rectifier and the triangulate node on the microscope's calibration `cal`, the matcher's
/// range `range`, a lossless entrance and the bridge on a free port.
fn raw_graph(left: &Path, right: &Path, cal: &Path, range: [i32; 2]) -> String {
    let text =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("launch.toml")).unwrap();
    let swaps = [
        (
            "params = { source = \"synthetic\", width = 1280, height = 1024, cells = 10, seed = 1, repeat = 30, fps = 30 }".to_string(),
            format!(
                "params = {{ source = \"files\", left = \"{}\", right = \"{}\", repeat = true }}",
                left.display(),
                right.display()
            ),
        ),
        (
            "inputs = { frame = { from = \"capture/frame\", depth = 1 } }".into(),
            format!(
                "inputs = {{ frame = {{ from = \"capture/frame\", depth = 1, overflow = \"block\" }} }}\nparams = {{ calibration = \"{}\" }}",
                cal.display()
            ),
        ),
        (
            "params = { min_disparity = -4, max_disparity = 12 }".into(),
            format!(
                "params = {{ min_disparity = {}, max_disparity = {} }}",
                range[0], range[1]
            ),
        ),
        (
            "params = { calibration = \"synthetic\", cloud_step = 4 }".into(),
            format!(
                "params = {{ calibration = \"{}\", cloud_step = 4 }}",
                cal.display()
            ),
        ),
        ("127.0.0.1:7878".into(), "127.0.0.1:0".into()),
    ];
    swaps.iter().fold(text, |t, (a, b)| {
        assert!(t.contains(a.as_str()), "the default graph changed: {a}");
        t.replace(a.as_str(), b)
    })
}

/// The live graph on a CMO microscope's raw pairs: rectified onto the stage plane by the
/// calibration `calibrate-microscope` wrote, its cells measured as `reconstruct --cells`
/// measures them from the same raw pair, to the bit.
#[test]
fn the_live_graph_runs_on_raw_pairs_with_the_microscope_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let optics = ["--optics", "cmo", "--rig-seed", "2", "--aperture", "0.3"];
    let (stack, cal, scene) = (
        dir.path().join("stack"),
        dir.path().join("cal"),
        dir.path().join("scene"),
    );
    synth(
        &stack,
        &optics,
        &["--stage-heights=-40,-20,0,20,40", "--board", "9,6"],
    );
    let out = calibrate(&stack, "9,6", &cal, &[]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    synth(
        &scene,
        &optics,
        &["--cells", "10", "--cell-height", "10,30", "--seed", "5"],
    );
    let (l, r, file) = (
        scene.join("left.png"),
        scene.join("right.png"),
        cal.join("calibration.toml"),
    );
    let launch = dir.path().join("raw.toml");
    std::fs::write(&launch, raw_graph(&l, &r, &file, [-12, 12])).unwrap();
    let rec = dir.path().join("run.mcap");
    let out = run(&[
        "run",
        s(&launch),
        "--frames",
        "1",
        "--record",
        s(&rec),
        "--edges",
        "triangulate/targets",
        "--instance",
        &format!("raw{}", std::process::id()),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report = cells_of(&l, &r, &file, &dir.path().join("reconstruct"));
    let want = report["cells"].as_array().unwrap();
    let measured = want.iter().filter(|c| c["height"].is_number()).count();
    assert!(measured >= 4, "{measured} cells measured: {report}");
    let msg = recorder::EdgeReader::open(&rec, None)
        .unwrap()
        .map(|m| m.unwrap())
        .find(|m| m.edge == "triangulate/targets")
        .expect("a targets message");
    let t: schemas::Targets = schemas::Message::decode(&msg.header, &msg.payload).unwrap();
    assert_eq!(
        serde_json::to_value(&t.cells).unwrap().as_array().unwrap(),
        want
    );
}

/// Cell heights from a CMO microscope's raw pairs, through the calibration a board across
/// half the field gives: 72 domes 10–30 µm tall in six scenes at NA 0.1 (blurred to the
/// diffraction limit), each trusted cell compared with its truth. A trusted height is
/// within 3 σ of its stated error, most within 2 %; a cell reaching outside the field the
/// board covered is not trusted, and says why.
#[test]
fn cell_heights_on_raw_cmo_pairs_are_within_their_stated_error() {
    let dir = tempfile::tempdir().unwrap();
    let optics = [
        "--optics",
        "cmo",
        "--convergence",
        "5",
        "--pupil",
        "150",
        "--rig-seed",
        "3",
    ];
    let (stack, cal) = (dir.path().join("stack"), dir.path().join("cal"));
    synth(
        &stack,
        &optics,
        &[
            "--stage-heights=-40,-30,-20,-10,0,10,20,30,40",
            "--board",
            "11,8",
        ],
    );
    let out = calibrate(&stack, "11,8", &cal, &[]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (mut trusted, mut within2, mut outside) = (0, 0, 0);
    for seed in ["11", "12", "13", "14", "15", "16"] {
        let (scene, o) = (
            dir.path().join(format!("scene{seed}")),
            dir.path().join(format!("cells{seed}")),
        );
        synth(
            &scene,
            &optics,
            &["--cells", "12", "--cell-height", "10,30", "--seed", seed],
        );
        let got = cells_of(
            &scene.join("left.png"),
            &scene.join("right.png"),
            &cal.join("calibration.toml"),
            &o,
        );
        let truth: serde_json::Value =
            serde_json::from_slice(&std::fs::read(scene.join("truth.json")).unwrap()).unwrap();
        let truth = truth["cells"].as_array().unwrap();
        for c in got["cells"].as_array().unwrap() {
            let q = &c["quality"];
            let doubt = q["doubt"].as_str().unwrap_or("");
            outside += usize::from(doubt.contains("outside the calibrated field"));
            if !q["trusted"].as_bool().unwrap() {
                continue;
            }
            let at = |v: &serde_json::Value, k: usize| v["centroid"][k].as_f64().unwrap();
            let near = truth
                .iter()
                .min_by(|a, b| {
                    let d =
                        |t: &serde_json::Value| (at(t, 0) - at(c, 0)).hypot(at(t, 1) - at(c, 1));
                    d(a).total_cmp(&d(b))
                })
                .unwrap();
            let (h, want) = (
                c["height"].as_f64().unwrap(),
                near["height"].as_f64().unwrap(),
            );
            let (err, std) = (h - want, q["height_std"].as_f64().unwrap());
            eprintln!(
                "seed {seed}: {h:.2} µm against {want:.2} ({:+.1} %, {:+.1} σ)",
                100.0 * err / want,
                err / std
            );
            assert!(
                err.abs() <= 3.0 * std,
                "seed {seed}: a trusted height {h:.2} µm against {want:.2} (σ {std:.2})"
            );
            trusted += 1;
            within2 += usize::from(err.abs() <= 0.02 * want);
        }
    }
    eprintln!("{trusted} trusted, {within2} within 2 %, {outside} outside the field");
    assert!(trusted >= 8, "{trusted} trusted heights");
    assert!(
        4 * within2 >= 3 * trusted,
        "{within2} of {trusted} within 2 %"
    );
    assert!(outside >= 1, "no cell outside the calibrated field");
}

/// What `calibrate-stereo` met on a microscope: ten board pairs tilted at most 3° (all a
/// microscope's depth of field allows) seen by a CMO's converging, nearly telecentric views
/// fit to a small reprojection error, but a pinhole's focal lengths and baseline are
/// undetermined there: refused with the reason and what to use, no file written.
#[test]
fn calibrate_stereo_refuses_a_microscopes_tilted_boards() {
    let dir = tempfile::tempdir().unwrap();
    let pairs = dir.path().join("pairs");
    std::fs::create_dir_all(&pairs).unwrap();
    let tilts = ["3,0", "-3,0", "0,3", "0,-3", "2,2", "-2,2", "2,-2", "-2,-2"];
    for (i, t) in tilts.iter().enumerate() {
        let one = dir.path().join(format!("s{i}"));
        let z = format!("--stage-heights={}", 10 * (i as i32 % 5) - 20);
        let tilt = format!("--tilt={t}");
        let seed = (i + 1).to_string();
        synth(
            &one,
            &["--optics", "cmo", "--rig-seed", "3"],
            &[&z, &tilt, "--seed", &seed, "--board", "9,6"],
        );
        for side in ["left", "right"] {
            std::fs::copy(
                one.join(format!("z00_{side}.png")),
                pairs.join(format!("{side}{i:02}.png")),
            )
            .unwrap();
        }
    }
    let cal = dir.path().join("cal");
    let out = run(&[
        "calibrate-stereo",
        s(&pairs),
        "--inner",
        "9x6",
        "--square",
        "100",
        "--unit",
        "um",
        "-o",
        s(&cal),
    ]);
    assert_clean_failure(&out, "the pairs do not determine the cameras");
    assert_clean_failure(&out, "calibrate-microscope");
    assert!(!cal.join("calibration.toml").exists());
}

/// The paper's route on a CMO microscope's raw pairs: the matched disparities of its
/// unrectified, turned views follow no depth model (0.93 px RMS, measured), and
/// `calibrate-depth` says so and writes nothing (it wrote a negative focal length).
#[test]
fn calibrate_depth_refuses_a_microscopes_raw_stack() {
    let dir = tempfile::tempdir().unwrap();
    let stack = dir.path().join("stack");
    let out = run(&[
        "synth",
        "--width",
        "640",
        "--height",
        "512",
        "--optics",
        "cmo",
        "--stage-heights=-40,-20,0,20,40",
        "-o",
        s(&stack),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let fitted = dir.path().join("fitted.toml");
    let out = run(&[
        "calibrate-depth",
        s(&stack),
        "--baseline",
        "19000",
        "--min-disparity",
        "-16",
        "--max-disparity",
        "16",
        "-o",
        s(&fitted),
    ]);
    assert_clean_failure(&out, "use calibrate-microscope");
    assert!(!fitted.exists());
}
