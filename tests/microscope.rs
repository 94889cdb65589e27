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
    let corners = inner.replace(',', "x");
    let out = run(&[
        "calibrate-microscope",
        s(&stack),
        "--inner",
        &corners,
        "--square",
        "100",
        "-o",
        s(&cal),
        "--check",
        s(&step),
    ]);
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

#[test]
fn a_cmo_microscope_calibrated_from_a_stage_stack_measures_a_held_out_step() {
    for optics in [
        [
            "--optics",
            "cmo",
            "--convergence",
            "5.5",
            "--pupil",
            "100",
            "--seed",
            "3",
        ],
        [
            "--optics",
            "cmo",
            "--convergence",
            "4",
            "--pupil",
            "400",
            "--seed",
            "5",
        ],
    ] {
        let step = held_out_step(&optics, "9,6");
        eprintln!("{optics:?}: step {step:.4} µm");
        assert!((step / 50.0 - 1.0).abs() < 0.005, "{optics:?}: {step}");
    }
}

/// A Greenough's focal plane is square to each tilted objective: at 7° the field's edges
/// are 80 µm out of focus and a 9×6 board's outer corners blur away, so its board is the
/// smaller one a user would take.
#[test]
fn a_greenough_microscope_calibrated_from_a_stage_stack_measures_a_held_out_step() {
    for optics in [
        [
            "--optics",
            "greenough",
            "--convergence",
            "7",
            "--pupil",
            "80",
            "--seed",
            "4",
        ],
        [
            "--optics",
            "greenough",
            "--convergence",
            "4.5",
            "--pupil",
            "150",
            "--seed",
            "6",
        ],
    ] {
        let step = held_out_step(&optics, "7,5");
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
        &[
            "--stage-heights=10,10,10",
            "--board",
            "9,6",
            "--square",
            "100",
        ],
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
