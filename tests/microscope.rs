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
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
}

/// The median disparity over the middle of a reconstruction's map.
fn median_disparity(dir: &Path) -> f64 {
    let d = formats::read_pfm(&dir.join("disparity.pfm"), "disparity").unwrap();
    let mut v: Vec<f64> = (d.height / 8..d.height * 7 / 8)
        .flat_map(|y| (d.width / 8..d.width * 7 / 8).map(move |x| (x, y)))
        .map(|(x, y)| *d.get(x, y) as f64)
        .filter(|v| v.is_finite())
        .collect();
    assert!(v.len() > d.width * d.height / 3, "{} valid", v.len());
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Calibrates `optics` from a board stack and measures a held-out 50 µm step (stage at
/// −20 and +30 µm, a speckle target); returns the step measured, µm.
fn held_out_step(optics: &[&str]) -> f64 {
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
            "9,6",
            "--square",
            "100",
        ],
    );
    let out = run(&[
        "calibrate-microscope",
        s(&stack),
        "--inner",
        "9x6",
        "--square",
        "100",
        "-o",
        s(&cal),
    ]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    eprintln!("{text}");
    synth(&step, optics, &["--stage-heights=-20,30"]);
    let file = cal.join("calibration.toml");
    let c = calibration::file::load(&file, 1280, 1024).unwrap();
    let depth = |i: usize| {
        let o = dir.path().join(format!("rec{i}"));
        let out = run(&[
            "reconstruct",
            s(&step.join(format!("z0{i}_left.png"))),
            s(&step.join(format!("z0{i}_right.png"))),
            "--calibration",
            s(&file),
            "--min-disparity",
            "-16",
            "--max-disparity",
            "16",
            "-o",
            s(&o),
        ]);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let d = median_disparity(&o);
        c.baseline * c.focal_px / (d + c.cx_right - c.cx)
    };
    depth(0) - depth(1)
}

#[test]
fn a_cmo_microscope_calibrated_from_a_stage_stack_measures_a_held_out_step() {
    for optics in [
        ["--optics", "cmo", "--convergence", "5.5", "--pupil", "100", "--seed", "3"],
        ["--optics", "cmo", "--convergence", "4", "--pupil", "400", "--seed", "5"],
    ] {
        let step = held_out_step(&optics);
        eprintln!("{optics:?}: step {step:.4} µm");
        assert!((step / 50.0 - 1.0).abs() < 0.005, "{optics:?}: {step}");
    }
}

#[test]
fn a_greenough_microscope_calibrated_from_a_stage_stack_measures_a_held_out_step() {
    for optics in [
        ["--optics", "greenough", "--convergence", "7", "--pupil", "80", "--seed", "4"],
        ["--optics", "greenough", "--convergence", "4.5", "--pupil", "150", "--seed", "6"],
    ] {
        let step = held_out_step(&optics);
        eprintln!("{optics:?}: step {step:.4} µm");
        assert!((step / 50.0 - 1.0).abs() < 0.005, "{optics:?}: {step}");
    }
}

#[test]
fn a_stack_at_one_height_is_refused_and_nothing_written() {
    let dir = tempfile::tempdir().unwrap();
    let stack = dir.path().join("stack");
    synth(
        &stack,
        &["--optics", "cmo"],
        &["--stage-heights=10,10,10", "--board", "9,6", "--square", "100"],
    );
    let cal = dir.path().join("cal");
    let out = run(&[
        "calibrate-microscope",
        s(&stack),
        "--inner",
        "9x6",
        "--square",
        "100",
        "-o",
        s(&cal),
    ]);
    assert_clean_failure(&out, "the depth is undetermined");
    assert!(!cal.exists());
}
