//! The `microstereo` binary end to end: outputs, report, eval, and bad input.

mod common;

use common::{assert_clean_failure, run, s};
use std::path::{Path, PathBuf};
use std::process::Command;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_microstereo"))
}

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

/// The figures of a report.html: each title and its picture, checked to be a whole PNG
/// with something drawn (more than one colour) and to be counted by the page's own script.
fn report_figures(page: &Path) -> Vec<(String, image::RgbImage)> {
    use base64::Engine;
    let html = std::fs::read_to_string(page).unwrap();
    let mut out = Vec::new();
    for part in html.split("<figure><h2>").skip(1) {
        let title = part[..part.find("</h2>").unwrap()].to_string();
        let start = part.find("base64,").unwrap() + 7;
        let end = start + part[start..].find('"').unwrap();
        let png = base64::engine::general_purpose::STANDARD
            .decode(&part[start..end])
            .unwrap();
        let img = image::load_from_memory(&png).unwrap().to_rgb8();
        let first = *img.get_pixel(0, 0);
        assert!(
            img.pixels().any(|p| *p != first),
            "{title}: a blank picture"
        );
        out.push((title, img));
    }
    assert!(html.contains(&format!("data-figures=\"{}\"", out.len())));
    out
}

#[test]
fn reconstruct_writes_every_output_and_eval_reads_it() {
    let dir = tempfile::tempdir().unwrap();
    let o = dir.path().join("out");
    let (l, r) = (data("cones/im2.png"), data("cones/im6.png"));
    let out = run(&[
        "reconstruct",
        s(&l),
        s(&r),
        "-o",
        s(&o),
        "--mode",
        "paper",
        "--min-disparity",
        "0",
        "--max-disparity",
        "63",
        "--baseline",
        "160",
        "--focal",
        "3740",
        "--unit",
        "mm",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for f in [
        "disparity.pfm",
        "disparity_raw.pfm",
        "disparity.png",
        "disparity_color.png",
        "occlusion_left.png",
        "occlusion_right.png",
        "points.ply",
        "report.json",
        "report.html",
    ] {
        assert!(o.join(f).is_file(), "{f} missing");
    }
    let titles: Vec<String> = report_figures(&o.join("report.html"))
        .into_iter()
        .map(|f| f.0)
        .collect();
    assert_eq!(titles, ["Validation", "Disparity", "Occlusions", "3D view"]);
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(o.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["mode"], "paper");
    assert_eq!(report["range"]["max"], 63);
    let v = &report["validation"];
    let sum = v["consistent_exact"].as_f64().unwrap()
        + v["off_by_one"].as_f64().unwrap()
        + v["off_by_more"].as_f64().unwrap();
    assert!((sum - 1.0).abs() < 1e-9);
    assert!(report["times_ms"]["match"].as_f64().unwrap() > 0.0);
    assert_eq!(
        report["density"], 1.0,
        "background fill makes the map dense"
    );
    // The PLY holds exactly the reported points, each 15 bytes.
    let ply = std::fs::read(o.join("points.ply")).unwrap();
    let n = report["points"].as_u64().unwrap() as usize;
    let header_end = ply.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let header = String::from_utf8_lossy(&ply[..header_end]);
    assert!(header.contains(&format!("element vertex {n}")));
    assert!(header.contains("unit mm"));
    assert_eq!(ply.len() - header_end, n * 15);
    // eval reads the PFM and the PNG alike and agrees with the library's figures.
    let gt = data("cones/disp2.png");
    let gtr = data("cones/disp6.png");
    let e = |map: &str| -> serde_json::Value {
        let out = run(&[
            "eval",
            s(&o.join(map)),
            "--gt",
            s(&gt),
            "--gt-scale",
            "4",
            "--gt-right",
            s(&gtr),
            "--json",
        ]);
        assert!(out.status.success());
        serde_json::from_slice(&out.stdout).unwrap()
    };
    let (pfm, png) = (e("disparity.pfm"), e("disparity.png"));
    let b = pfm["nonocc"]["bad_1"].as_f64().unwrap();
    assert!(b > 5.0 && b <= 10.5, "paper bad-1 {b}");
    assert!((png["nonocc"]["bad_1"].as_f64().unwrap() - b).abs() < 0.01);
    let table = run(&[
        "eval",
        s(&o.join("disparity.pfm")),
        "--gt",
        s(&gt),
        "--gt-scale",
        "4",
    ]);
    assert!(String::from_utf8_lossy(&table.stdout).contains("bad1%"));
}

#[test]
fn auto_range_reports_the_curve() {
    let dir = tempfile::tempdir().unwrap();
    let o = dir.path().join("auto");
    let out = run(&[
        "reconstruct",
        s(&data("cones/im2.png")),
        s(&data("cones/im6.png")),
        "-o",
        s(&o),
        "--mode",
        "paper",
        "--auto-range",
        "--range-kind",
        "positive",
        "--range-radii",
        "16,32,64",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(o.join("report.json")).unwrap()).unwrap();
    let curve = report["auto_range_curve"].as_array().unwrap();
    assert_eq!(curve.len(), 3);
    // Cones spans about 0..55 px: only 0..64 covers it.
    assert_eq!(report["range"]["max"], 64);
    // And the curve is drawn, the chosen (last) range's marker in red at the right end.
    let chart = image::open(o.join("range_curve.png")).unwrap().to_rgb8();
    assert_eq!(chart.dimensions(), (560, 260));
    let red = |x: u32| (0..260).any(|y| chart.get_pixel(x, y).0 == [220, 0, 0]);
    assert!(
        red(536) && !red(294),
        "the marker is on the last point only"
    );
}

#[test]
fn bad_input_gives_one_clear_error_and_keeps_existing_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let o = dir.path().join("out");
    std::fs::create_dir_all(&o).unwrap();
    std::fs::write(o.join("disparity.pfm"), b"earlier result").unwrap();
    let (l, r) = (data("cones/im2.png"), data("cones/im6.png"));
    let (l, r) = (s(&l), s(&r));
    let garbage = dir.path().join("garbage.png");
    std::fs::write(&garbage, b"not an image").unwrap();
    let small = dir.path().join("small.png");
    image::GrayImage::new(100, 80).save(&small).unwrap();
    let oo = s(&o);
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (
            vec!["reconstruct", "/nonexistent/left.png", r, "-o", oo],
            "does not exist",
        ),
        (
            vec!["reconstruct", l, s(&garbage), "-o", oo],
            "cannot be read",
        ),
        (vec!["reconstruct", l, s(&small), "-o", oo], "same size"),
        (
            vec![
                "reconstruct",
                l,
                r,
                "-o",
                oo,
                "--min-disparity",
                "10",
                "--max-disparity",
                "10",
            ],
            "is empty",
        ),
        (
            vec![
                "reconstruct",
                l,
                r,
                "-o",
                oo,
                "--min-disparity",
                "20",
                "--max-disparity",
                "5",
            ],
            "is empty",
        ),
        (
            vec![
                "reconstruct",
                l,
                r,
                "-o",
                oo,
                "--mode",
                "paper",
                "--window",
                "12",
            ],
            "odd size",
        ),
        (
            vec![
                "reconstruct",
                l,
                r,
                "-o",
                oo,
                "--mode",
                "paper",
                "--window",
                "35",
            ],
            "odd size",
        ),
        (
            vec![
                "reconstruct",
                l,
                r,
                "-o",
                oo,
                "--min-disparity",
                "-500",
                "--max-disparity",
                "5",
            ],
            "wider than the image",
        ),
        (
            vec!["reconstruct", l, r, "-o", oo, "--lr-tolerance", "7"],
            "--lr-tolerance",
        ),
        // No unit is assumed for a baseline: µm and mm differ a thousandfold.
        (
            vec![
                "reconstruct",
                l,
                r,
                "-o",
                oo,
                "--baseline",
                "160",
                "--focal",
                "935",
            ],
            "--unit",
        ),
        (
            vec![
                "reconstruct",
                l,
                r,
                "-o",
                oo,
                "--baseline",
                "-1",
                "--focal",
                "100",
                "--unit",
                "mm",
            ],
            "must be positive",
        ),
        (
            vec!["eval", "/nonexistent.pfm", "--gt", l],
            "does not exist",
        ),
        (vec!["eval", s(&small), "--gt", l], "same view and size"),
    ];
    // An earlier output is refused without --overwrite; with it, bad input still fails
    // before anything is written.
    assert_clean_failure(
        &run(&["reconstruct", l, r, "-o", oo]),
        "disparity.pfm' exists (from an earlier run?): add --overwrite",
    );
    for (mut args, needle) in cases {
        if args[0] == "reconstruct" {
            args.push("--overwrite");
        }
        let out = run(&args);
        assert_clean_failure(&out, needle);
        assert_eq!(
            std::fs::read(o.join("disparity.pfm")).unwrap(),
            b"earlier result",
            "{args:?}"
        );
    }
    // A window larger than the image is named as such.
    let tiny = dir.path().join("tiny.png");
    image::GrayImage::new(20, 20).save(&tiny).unwrap();
    let out = run(&[
        "reconstruct",
        s(&tiny),
        s(&tiny),
        "-o",
        oo,
        "--mode",
        "paper",
        "--window",
        "31",
        "--min-disparity",
        "0",
        "--max-disparity",
        "5",
        "--overwrite",
    ]);
    assert_clean_failure(&out, "does not fit");
}

#[test]
fn quality_mode_takes_images_smaller_than_its_census_window() {
    // The census pads its borders, so a 40×4 strip (shorter than the 9×7 census) matches.
    let dir = tempfile::tempdir().unwrap();
    let (l, r) = (dir.path().join("l.png"), dir.path().join("r.png"));
    let left =
        image::GrayImage::from_fn(40, 4, |x, y| image::Luma([((x * 37 + y * 11) % 251) as u8]));
    // The right view is the left shifted by 2 px.
    let right = image::GrayImage::from_fn(40, 4, |x, y| *left.get_pixel((x + 2).min(39), y));
    left.save(&l).unwrap();
    right.save(&r).unwrap();
    let o = dir.path().join("out");
    let out = run(&[
        "reconstruct",
        s(&l),
        s(&r),
        "-o",
        s(&o),
        "--mode",
        "quality",
        "--min-disparity",
        "0",
        "--max-disparity",
        "5",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let d = formats::read_disparity(&o.join("disparity.pfm"), None, "out").unwrap();
    // Away from the left border (x < 2 has no partner) most pixels find the 2 px shift.
    let inner: Vec<f32> = (0..4)
        .flat_map(|y| (8..32).map(move |x| (x, y)))
        .map(|(x, y)| *d.get(x, y))
        .collect();
    let right_shift = inner.iter().filter(|v| (**v - 2.0).abs() < 0.5).count();
    assert!(
        right_shift * 10 >= inner.len() * 9,
        "{right_shift} of {}",
        inner.len()
    );
}

fn json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

/// Segments a real image against its ground truth through the binary.
fn segment_real(
    image: &str,
    truth: &str,
    extra: &[&str],
) -> (serde_json::Value, PathBuf, tempfile::TempDir) {
    let dir = tempfile::tempdir().unwrap();
    let o = dir.path().join("seg");
    let (i, t) = (data(image), data(truth));
    let mut args = vec!["segment", s(&i), "-o", s(&o), "--truth", s(&t)];
    args.extend_from_slice(extra);
    let out = run(&args);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    (json(&o.join("cells.json")), o, dir)
}

#[test]
fn segment_finds_the_cho_cells_of_bbbc030() {
    let (r, o, _dir) = segment_real("cells/cho22_crop.png", "cells/cho22_crop_mask.png", &[]);
    let t = &r["truth"];
    assert!(t["dice"].as_f64().unwrap() >= 0.90, "{t}");
    assert_eq!(
        (t["found_cells"].as_u64(), t["truth_cells"].as_u64()),
        (Some(7), Some(7))
    );
    let cells = r["cells"].as_array().unwrap();
    assert_eq!(cells.len(), 7);
    for c in cells {
        // CHO cells here are ~50 px across: areas 1500–7000 px, closed contours around them.
        let area = c["area"].as_u64().unwrap();
        assert!((1500..7000).contains(&area), "{c}");
        let contour = c["contour"].as_array().unwrap();
        let per = c["perimeter"].as_f64().unwrap();
        assert!(contour.len() as f64 <= per + 1.0 && per < 2.0 * contour.len() as f64);
    }
    for f in ["labels.png", "overlay.png", "variance.png", "histogram.png"] {
        assert!(o.join(f).exists(), "{f}");
    }
    let labels = image::open(o.join("labels.png")).unwrap();
    assert!(matches!(labels, image::DynamicImage::ImageLuma16(_)));
    let l = labels.to_luma16();
    let max = l.pixels().map(|p| p.0[0]).max().unwrap();
    assert_eq!(max, 7);
    let hist: u64 = r["histogram"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap())
        .sum();
    assert_eq!(hist, 760 * 620);
}

#[test]
fn segment_finds_the_embryo_of_bbbc003() {
    let (r, _, _dir) = segment_real(
        "cells/bbbc003_7_20_M3M1.png",
        "cells/bbbc003_7_20_M3M1_truth.png",
        &["--min-area", "2000"],
    );
    let t = &r["truth"];
    assert!(t["dice"].as_f64().unwrap() >= 0.93, "{t}");
    assert_eq!(
        (t["found_cells"].as_u64(), t["truth_cells"].as_u64()),
        (Some(1), Some(1))
    );
    let c = &r["cells"][0];
    let [x, y] = [
        c["centroid"][0].as_f64().unwrap(),
        c["centroid"][1].as_f64().unwrap(),
    ];
    assert!((x - 240.0).abs() < 40.0 && (y - 300.0).abs() < 60.0, "{c}");
}

#[test]
fn an_embryo_and_the_arcs_of_its_zona_are_one_object() {
    // Debris (450–680 px) stays under --min-area 1000; the zona's arcs (400 and 1600 px)
    // pass it but join the embryo instead of being cells of their own.
    let (r, _, _dir) = segment_real(
        "cells/bbbc003_7_19_M1E18.png",
        "cells/bbbc003_7_19_M1E18_truth.png",
        &["--min-area", "400"],
    );
    let t = &r["truth"];
    assert!(t["dice"].as_f64().unwrap() >= 0.85, "{t}");
    let cells = r["cells"].as_array().unwrap();
    let big: Vec<_> = cells
        .iter()
        .filter(|c| c["area"].as_u64().unwrap() >= 1000)
        .collect();
    assert_eq!(big.len(), 1, "{cells:?}");
    let c = big[0];
    // The embryo's own boundary is the contour, the arcs widen its box.
    let (x, y) = (
        c["centroid"][0].as_f64().unwrap(),
        c["centroid"][1].as_f64().unwrap(),
    );
    assert!((x - 248.0).abs() < 15.0 && (y - 280.0).abs() < 15.0, "{c}");
    assert!(c["bbox"]["x0"].as_u64().unwrap() <= 140, "{c}");
    // Without the absorption the arcs are cells.
    let (r, _, _dir) = segment_real(
        "cells/bbbc003_7_19_M1E18.png",
        "cells/bbbc003_7_19_M1E18_truth.png",
        &["--min-area", "400", "--no-absorb-rings"],
    );
    let n = r["cells"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["area"].as_u64().unwrap() >= 1000)
        .count();
    assert_eq!(n, 2);
}

#[test]
fn segment_of_an_empty_image_is_zero_cells_not_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let img = dir.path().join("flat.png");
    image::GrayImage::from_pixel(64, 48, image::Luma([128]))
        .save(&img)
        .unwrap();
    let o = dir.path().join("seg");
    let out = run(&["segment", s(&img), "-o", s(&o)]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("0 cells"));
    let r = json(&o.join("cells.json"));
    assert_eq!(r["cells"].as_array().unwrap().len(), 0);
    assert_eq!(r["otsu_threshold"], serde_json::Value::Null);
}

#[test]
fn segment_bad_input_is_one_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let o = dir.path().join("seg");
    let missing = dir.path().join("nope.png");
    assert_clean_failure(
        &run(&["segment", s(&missing), "-o", s(&o)]),
        "does not exist",
    );
    let img = data("cells/cho22_crop.png");
    let other = data("cells/bbbc003_7_20_M3M1_truth.png");
    assert_clean_failure(
        &run(&["segment", s(&img), "-o", s(&o), "--truth", s(&other)]),
        "give the mask of this image",
    );
    assert_clean_failure(
        &run(&["segment", s(&img), "-o", s(&o), "--variance-radius", "0"]),
        "--variance-radius 0 is out of range",
    );
    assert!(!o.exists(), "nothing written on error");
}

#[test]
fn synth_then_reconstruct_cells_writes_per_cell_figures() {
    let dir = tempfile::tempdir().unwrap();
    let sc = dir.path().join("scene");
    let out = run(&["synth", "-o", s(&sc), "--seed", "3", "--cells", "4"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let truth = json(&sc.join("truth.json"));
    assert_eq!(truth["cells"].as_array().unwrap().len(), 4);
    let o = dir.path().join("rec");
    let (l, r, c) = (
        sc.join("left.png"),
        sc.join("right.png"),
        sc.join("calibration.toml"),
    );
    let out = run(&[
        "reconstruct",
        s(&l),
        s(&r),
        "-o",
        s(&o),
        "--cells",
        "--calibration",
        s(&c),
        "--min-disparity",
        "-4",
        "--max-disparity",
        "12",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let rep = json(&o.join("cells.json"));
    assert_eq!(rep["pairs"].as_u64(), Some(4));
    assert!(rep["matched_share"].as_f64().unwrap() < 0.5);
    for t in truth["cells"].as_array().unwrap() {
        let (tx, ty) = (
            t["centroid_px"][0].as_f64().unwrap(),
            t["centroid_px"][1].as_f64().unwrap(),
        );
        let m = rep["cells"].as_array().unwrap().iter().find(|c| {
            (c["centroid_px"][0].as_f64().unwrap() - tx)
                .hypot(c["centroid_px"][1].as_f64().unwrap() - ty)
                < 2.0
        });
        let m = m.unwrap_or_else(|| panic!("no cell near ({tx}, {ty})"));
        let (hm, ht) = (m["height"].as_f64().unwrap(), t["height"].as_f64().unwrap());
        assert!((hm / ht - 1.0).abs() < 0.4, "height {hm} vs {ht}");
        assert!(m["volume"].as_f64().unwrap() > 0.0);
        assert!(!m["contour"].as_array().unwrap().is_empty());
    }
    // The outputs of a cell run are all there, and no temporary file is left beside them.
    for f in [
        "disparity.pfm",
        "points.ply",
        "overlay_left.png",
        "labels_left.png",
        "report.html",
    ] {
        assert!(o.join(f).exists(), "{f}");
    }
    // The page holds the paper's figures of a cell run, and each cell's row.
    let titles: Vec<String> = report_figures(&o.join("report.html"))
        .into_iter()
        .map(|f| f.0)
        .collect();
    assert_eq!(
        titles,
        [
            "Segmentation",
            "Boundaries",
            "Validation",
            "Disparity",
            "Occlusions",
            "3D view"
        ]
    );
    let page = std::fs::read_to_string(o.join("report.html")).unwrap();
    let cells = page.split("<h2>Cells</h2>").nth(1).unwrap();
    let cells = &cells[..cells.find("</table>").unwrap()];
    assert_eq!(cells.matches("<tr><td>").count(), 4, "one row per cell");
    for d in [&o, &sc] {
        for e in std::fs::read_dir(d).unwrap() {
            let name = e.unwrap().file_name().to_string_lossy().into_owned();
            assert!(
                !name.starts_with('.') && !name.contains(".tmp"),
                "{name} left"
            );
        }
    }
    // Nothing is written over an earlier scene, segmentation or reconstruction without
    // --overwrite; with it, the same command succeeds.
    let before = std::fs::read(sc.join("left.png")).unwrap();
    let again = ["synth", "-o", s(&sc), "--seed", "4", "--cells", "4"];
    assert_clean_failure(
        &run(&again),
        "calibration.toml' exists (from an earlier run?)",
    );
    assert_eq!(std::fs::read(sc.join("left.png")).unwrap(), before);
    let mut with = again.to_vec();
    with.push("--overwrite");
    assert!(run(&with).status.success());
    assert_ne!(std::fs::read(sc.join("left.png")).unwrap(), before);
    let seg = dir.path().join("seg");
    let first = ["segment", s(&l), "-o", s(&seg)];
    assert!(run(&first).status.success());
    assert_clean_failure(&run(&first), "exists (from an earlier run?)");
    // An output directory holding the image itself: the image is never an output.
    let inside = sc.join("labels.png");
    let onto = ["segment", s(&inside), "-o", s(&sc), "--overwrite"];
    std::fs::copy(&l, sc.join("labels.png")).unwrap();
    assert_clean_failure(&run(&onto), "would be overwritten by the output");
}

#[test]
fn calibrate_depth_recovers_f_eff_from_a_synthetic_stack() {
    let dir = tempfile::tempdir().unwrap();
    let st = dir.path().join("stack");
    let out = run(&[
        "synth",
        "-o",
        s(&st),
        "--stage-heights=-120,-60,0,60,120",
        "--f-eff",
        "18000",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // Working distance = f_eff / magnification = 3600 µm.
    let out = run(&[
        "calibrate-depth",
        s(&st),
        "--baseline",
        "1200",
        "--pixel-pitch",
        "5",
        "--working-distance",
        "3600",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let truth = std::fs::read_to_string(st.join("calibration.toml")).unwrap();
    let text = std::fs::read_to_string(st.join("calibration-fitted.toml")).unwrap();
    let f_eff: f64 = text
        .lines()
        .find_map(|l| l.strip_prefix("f_eff = "))
        .unwrap()
        .parse()
        .unwrap();
    assert!((f_eff / 18000.0 - 1.0).abs() < 0.01, "f_eff {f_eff}");
    // Nothing lost: the scene's true calibration is left as it was, a second run does not
    // replace the fit without --overwrite, and the true calibration is never an output.
    assert_eq!(
        std::fs::read_to_string(st.join("calibration.toml")).unwrap(),
        truth
    );
    let again = ["calibrate-depth", s(&st), "--baseline", "1200"];
    assert_clean_failure(
        &run(&again),
        "exists (from an earlier run?): add --overwrite",
    );
    let mut with = again.to_vec();
    with.push("--overwrite");
    assert!(run(&with).status.success());
    let onto_truth = st.join("calibration.toml");
    let mut bad = again.to_vec();
    bad.extend(["-o", s(&onto_truth), "--overwrite"]);
    assert_clean_failure(&run(&bad), "would be overwritten by the output");
    assert_eq!(std::fs::read_to_string(&onto_truth).unwrap(), truth);
    // Too few heights.
    let two = dir.path().join("two");
    std::fs::create_dir_all(&two).unwrap();
    std::fs::write(
        two.join("heights.csv"),
        "left,right,z_um\nz00_left.png,z00_right.png,0\nz01_left.png,z01_right.png,5\n",
    )
    .unwrap();
    assert_clean_failure(
        &run(&["calibrate-depth", s(&two), "--baseline", "1200"]),
        "needs at least 3",
    );
}

/// Asked for more cells than fit, synth says how many it placed and what to change.
#[test]
fn synth_says_when_the_cells_asked_for_do_not_fit() {
    let dir = tempfile::tempdir().unwrap();
    let out = run(&["synth", "-o", s(&dir.path().join("s")), "--cells", "1000"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("of 1000 cells fit without overlapping in 640×480 px")
            && err.contains("give a larger view"),
        "{err}"
    );
    let placed: usize = err
        .split("only ")
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .and_then(|n| n.parse().ok())
        .expect("a count");
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(said.starts_with(&format!("{placed} cells;")), "{said}");
}

/// A calibration as a user writes it by hand (baseline, focal length, unit; no principal
/// points): `reconstruct --cells` and the graph work with it, and every number they give is
/// one (a disparity at infinite depth used to become JSON `null`, which the bridge and
/// `reconstruct` then failed to read back).
#[test]
fn a_calibration_without_its_optional_keys_works() {
    let dir = tempfile::tempdir().unwrap();
    let sc = dir.path().join("scene");
    let out = run(&["synth", "-o", s(&sc), "--seed", "3", "--cells", "4"]);
    assert!(out.status.success());
    let hand = dir.path().join("hand.toml");
    std::fs::write(&hand, "baseline = 1200\nfocal_px = 4000\nunit = \"um\"\n").unwrap();
    let o = dir.path().join("rec");
    let out = run(&[
        "reconstruct",
        s(&sc.join("left.png")),
        s(&sc.join("right.png")),
        "-o",
        s(&o),
        "--cells",
        "--calibration",
        s(&hand),
        "--min-disparity",
        "-4",
        "--max-disparity",
        "12",
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    // This pair's disparities need the principal points' offset: what cannot be placed is
    // said, the rest measured.
    assert!(err.contains("at or beyond infinite depth"), "{err}");
    let rep = json(&o.join("cells.json"));
    for c in rep["cells"].as_array().unwrap() {
        for v in c["centroid"].as_array().unwrap() {
            assert!(v.as_f64().is_some_and(f64::is_finite), "{c}");
        }
    }
    // The graph with it inline: the bridge reads every frame's targets.
    let graph = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/graph/small.toml");
    let out = run(&[
        "run",
        s(&graph),
        "--frames",
        "3",
        "--set",
        "triangulate.calibration={ baseline = 1200, focal_px = 4000, unit = \"um\" }",
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        String::from_utf8_lossy(&out.stdout).contains("3 frame(s) of 3"),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
}

#[test]
fn cells_bad_input_and_empty_scenes() {
    let dir = tempfile::tempdir().unwrap();
    let flat = dir.path().join("flat.png");
    image::GrayImage::from_pixel(96, 64, image::Luma([120]))
        .save(&flat)
        .unwrap();
    let o = dir.path().join("o");
    // All background: zero cells, not an error.
    let out = run(&[
        "reconstruct",
        s(&flat),
        s(&flat),
        "-o",
        s(&o),
        "--cells",
        "--baseline",
        "1200",
        "--focal",
        "4000",
        "--unit",
        "um",
        "--min-disparity",
        "-4",
        "--max-disparity",
        "12",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(json(&o.join("cells.json"))["pairs"].as_u64(), Some(0));
    // Different sizes.
    let small = dir.path().join("small.png");
    image::GrayImage::from_pixel(80, 64, image::Luma([120]))
        .save(&small)
        .unwrap();
    let o2 = dir.path().join("o2");
    let out = run(&[
        "reconstruct",
        s(&flat),
        s(&small),
        "-o",
        s(&o2),
        "--cells",
        "--baseline",
        "1",
        "--focal",
        "1",
        "--unit",
        "um",
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(!String::from_utf8_lossy(&out.stderr).contains("panicked"));
    assert!(!o2.exists());
    // An unreadable calibration file, and one without a unit.
    for (name, text, needle) in [
        ("bad.toml", "baseline = \"wide\"\n", "is not valid"),
        (
            "unitless.toml",
            "baseline = 1200.0\nfocal_px = 4000.0\n",
            "add unit = \"um\"",
        ),
    ] {
        let file = dir.path().join(name);
        std::fs::write(&file, text).unwrap();
        assert_clean_failure(
            &run(&[
                "reconstruct",
                s(&flat),
                s(&flat),
                "-o",
                s(&o2),
                "--cells",
                "--calibration",
                s(&file),
            ]),
            needle,
        );
    }
    assert!(!o2.exists());
    // --cells without geometry.
    assert_clean_failure(
        &run(&["reconstruct", s(&flat), s(&flat), "-o", s(&o2), "--cells"]),
        "--cells measures cells in 3D",
    );
}

#[test]
fn bench_transport_prints_both_edges_per_frame_size() {
    let out = run(&[
        "bench-transport",
        "--frames",
        "20",
        "--placement",
        "one-core",
    ]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        text.contains("on one core (a bare thread wake-up: p50"),
        "{text}"
    );
    let rows: Vec<Vec<f64>> = text
        .lines()
        .filter(|l| l.contains(" MP ("))
        .map(|l| {
            l.split_whitespace()
                .rev()
                .take(8)
                .map(|v| v.parse().unwrap())
                .collect()
        })
        .collect();
    assert_eq!(rows.len(), 3, "{text}");
    for r in rows {
        // Reversed: fps ×, p50 ×, uds fps, uds p99, uds p50, shm fps, shm p99, shm p50.
        let (shm50, shm99, uds50, uds99) = (r[7], r[6], r[4], r[3]);
        assert!(shm50 > 0.0 && shm99 >= shm50 && uds99 >= uds50, "{r:?}");
        assert!((r[1] - uds50 / shm50).abs() < 0.06 * r[1] + 0.06, "{r:?}");
    }
    assert_clean_failure(&run(&["bench-transport", "--frames", "1"]), "too few");
}

fn bundled_recording() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("recordings/default.mcap")
}

/// A copy of the bundled recording with only `edges` (and its launch file).
fn recording_of(dir: &Path, name: &str, edges: &[&str]) -> PathBuf {
    let path = dir.join(name);
    let mut w = recorder::RecordingWriter::create(&path, false).unwrap();
    let launch = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("recordings/default.toml");
    w.write_launch(&launch, &std::fs::read_to_string(&launch).unwrap())
        .unwrap();
    let want = edges.iter().map(|e| e.to_string()).collect();
    for m in recorder::EdgeReader::open(&bundled_recording(), Some(want)).unwrap() {
        let m = m.unwrap();
        w.write(&m.edge, m.kind, &m.header, &m.payload, m.log_time)
            .unwrap();
    }
    w.finish().unwrap();
    path
}

#[test]
fn inspect_lists_the_bundled_recording() {
    let out = run(&["inspect", s(&bundled_recording())]);
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(said.contains("61 messages on 31 channels"), "{said}");
    assert!(said.contains("frames 0–1"), "{said}");
    for (topic, ty, n) in [
        ("/rectify/frame/left/image", "sensor_msgs/msg/Image", "2"),
        (
            "/rectify/frame/right/camera_info",
            "sensor_msgs/msg/CameraInfo",
            "2",
        ),
        ("/triangulate/cloud", "sensor_msgs/msg/PointCloud2", "2"),
        ("/segment/cells", "microstereo_msgs/msg/CellArray", "2"),
        ("/triangulate/targets", "microstereo_msgs/msg/Targets", "2"),
        (
            "/triangulate/targets/markers",
            "visualization_msgs/msg/MarkerArray",
            "2",
        ),
        ("/match/left", "microstereo_msgs/msg/DisparityTiles", "2"),
        ("/triangulate/disparity/image", "sensor_msgs/msg/Image", "2"),
        // The frame tree, once.
        ("/tf_static", "tf2_msgs/msg/TFMessage", "1"),
    ] {
        let line = said
            .lines()
            .find(|l| l.split_whitespace().next() == Some(topic))
            .unwrap_or_else(|| panic!("{topic}: {said}"));
        assert!(line.contains(ty), "{line}");
        assert_eq!(line.split_whitespace().nth(2), Some(n), "{line}");
    }
}

/// The chunks of an MCAP file: where each record starts and how long its body is.
fn chunks(d: &[u8]) -> Vec<(usize, usize)> {
    let (mut at, mut out) = (8, Vec::new());
    while at + 9 <= d.len() {
        let len = u64::from_le_bytes(d[at + 1..at + 9].try_into().unwrap()) as usize;
        match d[at] {
            0x06 => out.push((at + 9, len)),
            0x0f => break,
            _ => {}
        }
        at += 9 + len;
    }
    out
}

/// A recording cut short (its writer died, the disk filled, a copy lost its tail) is read
/// up to its last whole chunk by replay, test-node and view, each saying what was lost.
#[test]
fn a_recording_cut_short_is_used_up_to_its_last_whole_chunk() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(bundled_recording()).unwrap();
    let found = chunks(&bytes);
    assert_eq!(found.len(), 2, "{found:?}");
    // Cut inside the second chunk: the first one's frames are whole.
    let (second, len) = found[1];
    let cut = dir.path().join("cut.mcap");
    std::fs::write(&cut, &bytes[..second + len / 3]).unwrap();
    let said = |out: &std::process::Output| {
        let err = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(
            out.status.success() && !err.contains("panicked"),
            "{}\n{err}",
            String::from_utf8_lossy(&out.stdout)
        );
        assert!(
            err.contains("the file is truncated")
                && err.contains(&format!("at byte {} of {}", second - 9, second + len / 3)),
            "{err}"
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    let out = said(&run(&["replay", s(&cut), "--quiet"]));
    assert!(out.contains("2 frame(s) of 2"), "{out}");
    let out = said(&run(&["test-node", s(&cut), "segment"]));
    assert!(out.contains("PASS"), "{out}");
    let rrd = dir.path().join("cut.rrd");
    said(&run(&["view", s(&cut), "-o", s(&rrd)]));
    assert!(rrd.metadata().unwrap().len() > 100_000);
}

#[test]
fn bad_recordings_get_one_clear_error_and_exit_2() {
    let dir = tempfile::tempdir().unwrap();
    // Not an MCAP file.
    let junk = dir.path().join("junk.mcap");
    std::fs::write(&junk, "P6 this is no recording").unwrap();
    for cmd in ["inspect", "replay"] {
        assert_clean_failure(&run(&[cmd, s(&junk)]), "not an MCAP file");
    }
    assert_clean_failure(
        &run(&["test-node", s(&junk), "segment"]),
        "not an MCAP file",
    );
    // Truncated inside its first chunk: nothing in it can be read.
    let bytes = std::fs::read(bundled_recording()).unwrap();
    let cut = dir.path().join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    for args in [
        vec!["replay", s(&cut)],
        vec!["test-node", s(&cut), "segment"],
        vec!["view", s(&cut), "-o", s(&dir.path().join("cut.rrd"))],
    ] {
        let out = run(&args);
        assert_clean_failure(&out, "truncated");
        assert_clean_failure(&out, "no message in it can be read");
    }
    let out = run(&["inspect", s(&cut)]);
    assert_clean_failure(&out, "truncated");
    assert!(String::from_utf8_lossy(&out.stdout).contains("topic"));
    // Every chunk damaged: nothing to show either.
    let mut flipped = bytes.clone();
    for (at, len) in chunks(&bytes) {
        flipped[at + len / 2] ^= 0x5a;
        flipped[at + len / 2 + 1] ^= 0x5a;
    }
    let damaged = dir.path().join("damaged.mcap");
    std::fs::write(&damaged, &flipped).unwrap();
    for args in [
        vec!["replay", s(&damaged)],
        vec![
            "view",
            s(&damaged),
            "-o",
            s(&dir.path().join("damaged.rrd")),
        ],
    ] {
        assert_clean_failure(&run(&args), "no message in it can be read");
    }
    // Missing channels: the recording has no capture frames to replay.
    let maps = recording_of(dir.path(), "maps.mcap", &["match/left"]);
    assert_clean_failure(
        &run(&["replay", s(&maps)]),
        "no channel for edge 'capture/frame'; it holds: match/left",
    );
    // A schema mismatch: replacing the matcher with a recording whose match/left and
    // match/right channels are in fact stereo frames.
    let odd = dir.path().join("odd.mcap");
    let mut w = recorder::RecordingWriter::create(&odd, false).unwrap();
    for m in recorder::EdgeReader::open(&bundled_recording(), Some(vec!["capture/frame".into()]))
        .unwrap()
    {
        let m = m.unwrap();
        for edge in ["match/left", "match/right"] {
            w.write(edge, m.kind, &m.header, &m.payload, m.log_time)
                .unwrap();
        }
    }
    w.finish().unwrap();
    let launch = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("recordings/default.toml");
    assert_clean_failure(
        &run(&[
            "replay",
            s(&odd),
            "--launch",
            s(&launch),
            "--replace",
            "match",
        ]),
        "edge 'match/left' carries stereo-frame in the recording (sensor_msgs/msg/Image) but disparity-tiles in the launch file",
    );
    // No launch file stored and none given.
    assert_clean_failure(
        &run(&["replay", s(&odd)]),
        "holds no launch file; give one with --launch",
    );
    // A bad rate and an unknown node.
    assert_clean_failure(&run(&["replay", s(&maps), "--rate", "fast"]), "--rate");
    assert_clean_failure(
        &run(&["replay", s(&maps), "--replace", "nope"]),
        "has no node 'nope'",
    );
}

#[test]
fn recording_never_overwrites_an_existing_file_by_accident() {
    let dir = tempfile::tempdir().unwrap();
    let old = dir.path().join("old.mcap");
    std::fs::write(&old, b"an earlier recording").unwrap();
    let out = run(&["run", "--frames", "1", "--record", s(&old)]);
    assert_clean_failure(
        &out,
        "the file exists; choose another name or add --overwrite",
    );
    assert_eq!(std::fs::read(&old).unwrap(), b"an earlier recording");
    let out = run(&["run", "--frames", "1", "--record", "/no/such/dir/x.mcap"]);
    assert_clean_failure(&out, "the folder /no/such/dir does not exist");
    let out = run(&[
        "run",
        "--frames",
        "1",
        "--record",
        s(&dir.path().join("n.mcap")),
        "--edges",
        "nope/*",
    ]);
    assert_clean_failure(&out, "no edge matches 'nope/*'; the edges: capture/frame");
}

#[test]
fn a_live_run_and_a_recording_turn_into_rerun_files() {
    let dir = tempfile::tempdir().unwrap();
    let small = data("graph/small.toml");
    let (rrd, rec, viewed) = (
        dir.path().join("live.rrd"),
        dir.path().join("live.mcap"),
        dir.path().join("viewed.rrd"),
    );
    let instance = format!("viewer{}", std::process::id());
    let out = run(&[
        "run",
        s(&small),
        "--frames",
        "2",
        "--instance",
        &instance,
        "--viewer",
        "save",
        s(&rrd),
        "--record",
        s(&rec),
    ]);
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The viewer took every message of every edge: 12 edges (the bridge's state too), 2
    // frames.
    let row = said.lines().find(|l| l.starts_with("viewer ")).unwrap();
    assert_eq!(row.split_whitespace().nth(1), Some("24"), "{row}");
    let out = run(&["view", s(&rec), "-o", s(&viewed)]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for f in [&rrd, &viewed] {
        let b = std::fs::read(f).unwrap();
        assert!(
            b.len() > 100_000 && b.starts_with(b"RRF2"),
            "{}: {} bytes",
            f.display(),
            b.len()
        );
    }
}

#[test]
fn a_viewer_that_cannot_work_is_refused_before_the_graph_starts() {
    let dir = tempfile::tempdir().unwrap();
    // Nothing listens on port 1.
    assert_clean_failure(
        &run(&["run", "--frames", "1", "--viewer", "connect", "127.0.0.1:1"]),
        "--viewer connect 127.0.0.1:1: no Rerun viewer is listening there",
    );
    let old = dir.path().join("old.rrd");
    std::fs::write(&old, b"kept").unwrap();
    assert_clean_failure(
        &run(&["run", "--frames", "1", "--viewer", "save", s(&old)]),
        "the file exists",
    );
    assert_eq!(std::fs::read(&old).unwrap(), b"kept");
    assert_clean_failure(
        &run(&["run", "--frames", "1", "--viewer", "show"]),
        "give spawn, connect HOST:PORT or save FILE.rrd",
    );
    let out = bin()
        .args(["run", "--frames", "1", "--viewer", "spawn"])
        .env("PATH", dir.path())
        .output()
        .unwrap();
    assert_clean_failure(
        &out,
        "which is not on PATH; install it with `pip install rerun-sdk==0.36.*`",
    );
    let junk = dir.path().join("junk.mcap");
    std::fs::write(&junk, b"no").unwrap();
    assert_clean_failure(
        &run(&["view", s(&junk), "-o", s(&dir.path().join("x.rrd"))]),
        "not an MCAP file",
    );
}

/// Numbers no command can use (NaN, infinities, huge, zero where it never ends) are one
/// clear error with exit code 2 before anything is written or started (issue 19 #10, #11,
/// #12).
#[test]
fn bad_numbers_are_one_clear_error_before_anything_starts() {
    let dir = tempfile::tempdir().unwrap();
    let o = dir.path().join("out");
    let (l, r) = (data("cones/im2.png"), data("cones/im6.png"));
    let small = data("graph/small.toml");
    let geo = |extra: &[&'static str]| {
        let mut v = vec!["reconstruct", s(&l), s(&r), "-o", s(&o), "--unit", "um"];
        if !extra.contains(&"--baseline") {
            v.extend_from_slice(&["--baseline", "1000", "--focal", "2000"]);
        }
        v.extend_from_slice(extra);
        v
    };
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (
            vec!["synth", "-o", s(&o), "--diameter", "NaN,NaN"],
            "--diameter NaN",
        ),
        (vec!["synth", "-o", s(&o), "--drift", "NaN"], "--drift NaN"),
        (
            vec!["synth", "-o", s(&o), "--blur", "1e9"],
            "--blur 1000000000",
        ),
        (
            vec!["synth", "-o", s(&o), "--cell-height", "1,inf"],
            "--cell-height inf",
        ),
        (vec!["synth", "-o", s(&o), "--frames", "0"], "--frames 0"),
        (
            vec!["run", s(&small), "--grace", "NaN", "--frames", "2"],
            "--grace NaN",
        ),
        (
            vec!["run", s(&small), "--grace", "1e9", "--frames", "2"],
            "--grace 1000000000",
        ),
        (
            vec!["run", s(&small), "--grace", "-1", "--frames", "2"],
            "--grace -1",
        ),
        (
            vec!["run", s(&small), "--frames", "0"],
            "--frames 0 would never end",
        ),
        (geo(&["--cx", "NaN"]), "cx (NaN)"),
        (geo(&["--cx", "-inf"]), "cx (-inf)"),
        (
            geo(&["--baseline", "1e300", "--focal", "1e300"]),
            "at most 1e9",
        ),
        (geo(&["--median", "1000000000"]), "--median 1000000000"),
    ];
    let (gt, disp) = (data("cones/disp2.png"), data("cones/disp6.png"));
    let eval =
        |flag: &'static str, v: &'static str| vec!["eval", s(&disp), "--gt", s(&gt), flag, v];
    // Found by a sweep of bad values over every subcommand: eval took these with exit 0.
    let cases: Vec<(Vec<&str>, &str)> = cases
        .into_iter()
        .chain([
            (eval("--gt-scale", "NaN"), "--gt-scale NaN is not a scale"),
            (eval("--gt-scale", "inf"), "--gt-scale inf is not a scale"),
            (eval("--gt-scale", "0"), "--gt-scale 0 is not a scale"),
            (
                eval("--gt-scale", "1e9"),
                "--gt-scale 1000000000 is not a scale",
            ),
            (
                eval("--scale", "1e30"),
                "--scale 1000000000000000000000000000000 is not",
            ),
            (
                eval("--gt-right-scale", "NaN"),
                "--gt-right-scale NaN is not",
            ),
        ])
        .collect();
    for (args, needle) in cases {
        let out = run(&args);
        assert_clean_failure(&out, needle);
        assert!(!o.exists(), "{args:?} wrote its output before failing");
    }
}

/// An input named like one of the outputs, in the output directory, is never overwritten
/// (issue 19 #9).
#[test]
fn reconstruct_never_writes_over_its_input() {
    let dir = tempfile::tempdir().unwrap();
    let left = dir.path().join("disparity.png");
    std::fs::copy(data("cones/im2.png"), &left).unwrap();
    let before = std::fs::read(&left).unwrap();
    let out = run(&[
        "reconstruct",
        s(&left),
        s(&data("cones/im6.png")),
        "-o",
        s(dir.path()),
        "--overwrite",
    ]);
    assert_clean_failure(&out, "would be overwritten by the output '");
    assert!(String::from_utf8_lossy(&out.stderr).contains("disparity.png': give -o another"));
    assert_eq!(std::fs::read(&left).unwrap(), before);
    assert!(!dir.path().join("disparity.pfm").exists());
}

/// A reader that goes away (`| head -1`) ends a command quietly: SIGPIPE as any Unix
/// tool, or a normal end for the graph commands, which ignore SIGPIPE to stop their
/// nodes cleanly; never a panic about printing (issue 19 #11).
#[test]
fn a_closed_stdout_ends_a_command_without_a_panic() {
    use std::os::unix::process::ExitStatusExt;
    let small = data("graph/small.toml");
    let bundled = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("recordings/default.mcap");
    let cases: Vec<Vec<&str>> = vec![
        vec!["inspect", s(&bundled)],
        vec!["run", s(&small), "--frames", "2"],
        vec!["test-node", s(&bundled), "segment"],
        vec!["--help"],
    ];
    for args in cases {
        let mut child = bin()
            .args(&args)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        // The reading end closes before the command prints anything.
        drop(child.stdout.take());
        let out = child.wait_with_output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !err.contains("panicked") && !err.contains("failed printing"),
            "{args:?}: {err}"
        );
        let quiet = out.status.signal() == Some(libc::SIGPIPE) || out.status.code() == Some(0);
        assert!(quiet, "{args:?}: {:?} {err}", out.status);
    }
}

/// `run --compare` runs the graph as processes, then in one process, and says what share
/// of the in-process rate the processes reach, from the two summaries' own rates.
#[test]
fn run_compare_gives_the_processes_rate_as_a_share_of_the_in_process_one() {
    let small = data("graph/small.toml");
    let (procs, alone, share, line) = compare_rates(&small);
    assert!(!line.contains("cap at"), "{line}");
    assert!(
        (share - procs / alone).abs() <= 0.01,
        "{line} from {procs} and {alone}"
    );
    // A camera of 4 frames/s caps what one process could take from it: the yardstick is
    // the camera's rate, not the faster unpaced run.
    let dir = tempfile::tempdir().unwrap();
    let paced = dir.path().join("paced.toml");
    let text = std::fs::read_to_string(&small).unwrap().replacen(
        "drift = 2.0 }",
        "drift = 2.0, fps = 4 }",
        1,
    );
    std::fs::write(&paced, text).unwrap();
    let (procs, alone, share, line) = compare_rates(&paced);
    assert!(alone > 4.0, "{line}");
    assert!(line.contains("cap at 4.00"), "{line}");
    assert!(
        (share - procs / 4.0).abs() <= 0.01,
        "{line} from {procs} and the camera's 4"
    );
    for bad in [
        vec!["run", s(&small), "--compare"],
        vec![
            "run",
            s(&small),
            "--compare",
            "--in-process",
            "--frames",
            "2",
        ],
    ] {
        assert_eq!(run(&bad).status.code(), Some(2), "{bad:?}");
    }
}

/// `run FILE --frames 3 --compare`: the processes' rate, the in-process one, the share
/// printed and its line.
fn compare_rates(file: &Path) -> (f64, f64, f64, String) {
    let out = run(&["run", s(file), "--frames", "3", "--compare"]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let rate = |line: &str| -> f64 {
        let before = line.split(" frames/s").next().expect("a rate");
        before
            .rsplit(' ')
            .next()
            .unwrap()
            .parse()
            .expect("a number")
    };
    let alone = text
        .lines()
        .find(|l| l.contains("frame(s) in one process"))
        .map(rate)
        .unwrap_or_else(|| panic!("no in-process summary: {text}"));
    let procs = text
        .lines()
        .find(|l| l.contains("frame(s) of 3 in"))
        .map(rate)
        .unwrap_or_else(|| panic!("no processes' summary: {text}"));
    let line = text
        .lines()
        .find(|l| l.contains("the in-process rate"))
        .unwrap_or_else(|| panic!("no comparison: {text}"));
    let share: f64 = line
        .split('×')
        .next()
        .unwrap()
        .rsplit(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!(alone > 0.0 && procs > 0.0, "{text}");
    // The rate the graph sustained from its first output to its last, past the start-up.
    let sustained: f64 = text
        .lines()
        .find(|l| l.contains("frame(s) of 3 in"))
        .and_then(|l| l.split("; sustained ").nth(1))
        .and_then(|r| r.split(' ').next())
        .and_then(|r| r.parse().ok())
        .unwrap_or_else(|| panic!("no sustained rate: {text}"));
    assert!(sustained.is_finite() && sustained > 0.0, "{text}");
    (procs, alone, share, line.to_string())
}

/// `run --in-process` steps every node of the launch file in this process: each node
/// reports every frame, and it refuses what only processes do.
#[test]
fn run_in_process_steps_every_node_on_every_frame() {
    let small = data("graph/small.toml");
    let out = run(&["run", s(&small), "--frames", "3", "--in-process"]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for node in [
        "capture",
        "segment",
        "match",
        "validate",
        "postprocess",
        "triangulate",
        "manipulator-bridge",
    ] {
        let line = text
            .lines()
            .find(|l| l.split_whitespace().next() == Some(node))
            .unwrap_or_else(|| panic!("no line for {node}: {text}"));
        assert_eq!(line.split_whitespace().nth(1), Some("3"), "{line}");
    }
    assert!(text.contains("3 frame(s) in one process"), "{text}");
    for bad in [
        vec!["run", s(&small), "--in-process"],
        vec![
            "run",
            s(&small),
            "--in-process",
            "--frames",
            "2",
            "--record",
            "x.mcap",
        ],
        vec!["run", s(&small), "--in-process", "--frames", "0"],
    ] {
        let out = run(&bad);
        assert_eq!(out.status.code(), Some(2), "{bad:?}");
    }
}
