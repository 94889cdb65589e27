//! End-to-end accuracy of both matchers through the graph's own nodes (the image pair →
//! match → validate → post-process preset, run in-process).

use matcher::Mode;
use pipelines::range::{RangeKind, auto_range, candidate_ranges};
use pipelines::stereo::Stereo;
use schemas::{DisparityMap, DisparityRange, Plane};
use std::path::{Path, PathBuf};
use synth::layers::standard_scene;

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

fn save(dir: &Path, name: &str, p: &Plane<u8>) -> PathBuf {
    let path = dir.join(name);
    image::GrayImage::from_raw(p.width as u32, p.height as u32, p.data.clone())
        .unwrap()
        .save(&path)
        .unwrap();
    path
}

/// The stereo graph of a mode over `range` on two image files.
fn preset(left: PathBuf, right: PathBuf, mode: Mode, range: DisparityRange) -> Stereo {
    Stereo::whole_frame(left, right, mode, range)
}

/// The final map of `p`.
fn final_map(p: &Stereo) -> DisparityMap {
    let f = p.run_once().unwrap();
    f.read(p.outs().post.as_ref().unwrap()).unwrap().paste()
}

/// Share of non-occluded pixels (per the GT cross-check) whose disparity rounds to the GT.
fn exact_share(d: &DisparityMap, gl: &DisparityMap, gr: &DisparityMap) -> f64 {
    let vis = validate::occlusion_from_gt(gl, gr);
    let (mut n, mut ok) = (0usize, 0usize);
    for i in 0..d.len() {
        if vis.data[i] {
            n += 1;
            ok += (d.data[i].is_finite() && (d.data[i] - gl.data[i]).abs() < 0.5) as usize;
        }
    }
    ok as f64 / n as f64
}

#[test]
fn synthetic_pairs_are_exact_in_both_modes_negative_disparities_included() {
    let dir = tempfile::tempdir().unwrap();
    // Layers at −7, −2, 3, 8 px, and at 2, 10, 18, 26 px.
    for (base, step, range, seed) in [
        (-7, 5, DisparityRange::new(-10, 10), 1),
        (2, 8, DisparityRange::new(0, 32), 2),
    ] {
        let s = standard_scene(640, 480, base, step, seed);
        let (l, r) = (
            save(dir.path(), "l.png", &s.left),
            save(dir.path(), "r.png", &s.right),
        );
        for mode in [Mode::Paper, Mode::Quality] {
            let d = final_map(&preset(l.clone(), r.clone(), mode, range));
            let share = exact_share(&d, &s.gt_left, &s.gt_right);
            assert!(
                share >= 0.99,
                "{mode:?} base {base}: only {:.2} % exact",
                share * 100.0
            );
        }
    }
}

fn cones_bad1(mode: Mode, paths: Option<u8>) -> f64 {
    let gl = formats::read_disparity(&data("cones/disp2.png"), Some(4.0), "gt").unwrap();
    let gr = formats::read_disparity(&data("cones/disp6.png"), Some(4.0), "gt").unwrap();
    let mut p = preset(
        data("cones/im2.png"),
        data("cones/im6.png"),
        mode,
        DisparityRange::new(0, 63),
    );
    if let Some(n) = paths {
        p.matching.paths = n;
    }
    let vis = validate::occlusion_from_gt(&gl, &gr);
    validate::evaluate(&final_map(&p), &gl, Some(&vis))
        .nonocc
        .bad_1
}

#[test]
fn cones_paper_mode_bad1_within_bar() {
    // Measured 10.09 % when this guard was written; the bar is 10.5 %.
    let b = cones_bad1(Mode::Paper, None);
    assert!(b <= 10.5, "paper bad-1 on cones {b:.2} %");
    assert!(
        b > 5.0,
        "suspiciously good paper bad-1 {b:.2} %: is the GT read right?"
    );
}

#[test]
fn cones_quality_mode_beats_sgbm() {
    // OpenCV StereoSGBM-3WAY reaches 4.26 % here; we measured 3.80 % with the default 4
    // SGM paths and 3.66 % with 8.
    let four = cones_bad1(Mode::Quality, None);
    assert!(four < 4.26, "quality bad-1 on cones {four:.2} %");
    let eight = cones_bad1(Mode::Quality, Some(8));
    assert!(eight < 4.26, "quality bad-1 on cones, 8 paths {eight:.2} %");
    assert!(four != eight, "--paths 8 should change the result");
}

/// Offered radii 1..16, auto-range picks a range that holds the scene's disparities (±R)
/// and at most ±2R, in both modes: on fronto-parallel layers and on a microscope's cells on
/// a faintly textured, tilted substrate (continuous disparities; R: the cells'). A match
/// the range only clamped at its end is not evidence, or the narrowest range would win;
/// and the score is the cells', or the substrate would swamp them (it picked ±3 here).
#[test]
fn auto_range_holds_the_scene_and_at_most_twice_it() {
    let dir = tempfile::tempdir().unwrap();
    let mut scenes = Vec::new();
    // Layers at −6, −2, 2, 6 px (R = 6) and at −3, −1, 1, 3 px (R = 3).
    for (base, step, seed) in [(-6, 4, 3), (-3, 2, 4)] {
        let s = standard_scene(320, 240, base, step, seed);
        scenes.push((s.left, s.right, (base + 3 * step).max(-base) as f32));
    }
    let cells = synth::request::Request {
        width: 320,
        height: 240,
        cells: 4,
        seed: 5,
        tilt: Some(vec![5.0, -2.0]),
        substrate_disparity: Some(-3.0),
        ..Default::default()
    };
    let (scene, _) = cells.setup(synth::Texture::Noise).unwrap().cells().unwrap();
    let r = scene.render();
    // The cells' disparities (the textured regions auto-range scores; the faint
    // substrate's far corners, tilted to −8.3 px here, are not evidence either way).
    let reach = r
        .disparity
        .data
        .iter()
        .zip(&r.labels.data)
        .filter(|p| *p.1 != 0)
        .fold(0f32, |a, p| a.max(p.0.abs()));
    scenes.push((r.left, r.right, reach));
    let radii = [1, 2, 3, 4, 5, 6, 8, 10, 12, 16];
    for (i, (l, r, reach)) in scenes.iter().enumerate() {
        let (l, r) = (
            save(dir.path(), &format!("l{i}.png"), l),
            save(dir.path(), &format!("r{i}.png"), r),
        );
        let ranges = candidate_ranges(RangeKind::Symmetric, &radii, 320);
        for mode in [Mode::Quality, Mode::Paper] {
            let base = preset(l.clone(), r.clone(), mode, ranges[0]);
            let (best, curve) = auto_range(&base, &ranges).unwrap();
            let picked = best.max as f32;
            assert!(
                picked >= *reach && picked <= 2.0 * reach.ceil(),
                "scene {i} (±{reach:.2} px), {mode:?}: picked ±{picked}; curve {curve:?}"
            );
        }
    }
}

#[test]
fn auto_range_picks_the_narrowest_range_that_covers_the_scene() {
    // True disparities −3..9: ±4 and ±8 miss the nearest layer, ±12 covers everything.
    let dir = tempfile::tempdir().unwrap();
    let s = standard_scene(240, 180, -3, 4, 5);
    let base = preset(
        save(dir.path(), "l.png", &s.left),
        save(dir.path(), "r.png", &s.right),
        Mode::Paper,
        DisparityRange::new(0, 1),
    );
    let ranges = candidate_ranges(RangeKind::Symmetric, &[4, 8, 12, 24, 48], 240);
    let (best, curve) = auto_range(&base, &ranges).unwrap();
    assert_eq!(curve.len(), 5);
    assert_eq!(best, DisparityRange::new(-12, 12), "curve: {curve:?}");
    // The curve rises to the covering range and falls after it (the paper's Fig. 12).
    let r: Vec<f64> = curve.iter().map(|s| s.consistency_ratio).collect();
    assert!(
        r[0] < r[1] && r[1] < r[2] && r[2] > r[3] && r[3] > r[4],
        "{curve:?}"
    );
}

#[test]
fn left_and_right_directions_agree_on_a_plain_shift() {
    // A whole image shifted by 5 px: every left pixel with a partner says 5, and so does
    // every right pixel, in both modes — as the match node sends them.
    let dir = tempfile::tempdir().unwrap();
    let s = standard_scene(120, 90, 5, 0, 9);
    let (l, r) = (
        save(dir.path(), "l.png", &s.left),
        save(dir.path(), "r.png", &s.right),
    );
    for mode in [Mode::Paper, Mode::Quality] {
        let p = preset(l.clone(), r.clone(), mode, DisparityRange::new(0, 12));
        let (f, outs) = (p.run_once().unwrap(), p.outs());
        let map = |port| {
            let o = if port == "left" {
                &outs.matched
            } else {
                &outs.matched_right
            };
            f.read(o).unwrap().paste()
        };
        let check = |m: &Plane<f32>, skip_left: usize, skip_right: usize| {
            for y in 8..82 {
                for x in skip_left..120 - skip_right {
                    let d = *m.get(x, y);
                    assert!((d - 5.0).abs() < 0.5, "{mode:?} ({x},{y}) = {d}");
                }
            }
        };
        check(&map("left"), 17, 8);
        check(&map("right"), 8, 17);
    }
}
