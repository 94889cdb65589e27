//! What the synthetic-scene tests share: the method's cell graph on a rendered pair.

use calibration::file::CalibrationFile;
use matcher::Mode;
use matcher::node::{MatchParams, Region};
use pipelines::stereo::Stereo;
use postprocess::PostParams;
use schemas::{Calibration, Cell3, DisparityRange, Labels, Mask, Plane, Targets};
use segment::SegmentParams;
use std::path::Path;
use std::process::{Command, Output};
use triangulate::geometry::Geometry;

/// The `microstereo` binary run with `args`, to its end.
#[allow(dead_code)]
pub fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_microstereo"))
        .args(args)
        .output()
        .expect("binary runs")
}

/// A path as a command-line argument.
#[allow(dead_code)]
pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// One clear error line, exit code 2, no panic.
#[allow(dead_code)]
pub fn assert_clean_failure(out: &Output, needle: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "stderr: {err}");
    assert!(!err.contains("panicked"), "panic: {err}");
    assert!(err.contains(needle), "expected '{needle}' in: {err}");
}

/// The method's cell graph (image pair → segment → match the cells' crops → validate →
/// post-process → triangulate) on a rendered pair: the cells in 3D and the left mask.
// Each test file compiles this module on its own; the heights tests use only the targets.
#[allow(dead_code)]
pub fn cell_stereo(
    left: &Plane<u8>,
    right: &Plane<u8>,
    calibration: &Calibration,
    range: DisparityRange,
) -> (Vec<Cell3>, Mask) {
    let (t, m) = cell_targets(left, right, calibration, range);
    (t.cells, m)
}

/// [`cell_stereo`] with the whole targets message (the substrate plane too).
pub fn cell_targets(
    left: &Plane<u8>,
    right: &Plane<u8>,
    calibration: &Calibration,
    range: DisparityRange,
) -> (Targets, Mask) {
    let dir = tempfile::tempdir().unwrap();
    let save = |name: &str, p: &Plane<u8>| {
        let path = dir.path().join(name);
        image::GrayImage::from_raw(p.width as u32, p.height as u32, p.data.clone())
            .unwrap()
            .save(&path)
            .unwrap();
        path
    };
    let c = calibration;
    let preset = Stereo {
        left: save("left.png", left),
        right: save("right.png", right),
        frames: 1,
        matching: MatchParams::new(Mode::Quality, range, Region::Cells),
        validate: Default::default(),
        post: Some(PostParams::SUBPIXEL),
        segment: Some(SegmentParams::default()),
        geometry: Some(Geometry::Inline(CalibrationFile {
            baseline: c.baseline,
            focal_px: Some(c.focal_px),
            f_eff: None,
            pixel_pitch: None,
            cx: Some(c.cx),
            cy: Some(c.cy),
            cx_right: Some(c.cx_right),
            unit: Some(c.unit),
            stereo: None,
            microscope: None,
        })),
        rectify: None,
    };
    let f = preset.run_once().unwrap();
    let outs = preset.outs();
    let targets: Targets = f.read(outs.targets.as_ref().unwrap()).unwrap();
    let labels: Labels = f.read(outs.labels.as_ref().unwrap()).unwrap();
    (targets, cells::mask_of(&labels.left))
}
