//! A rendered scene as files: both views, the true disparity and depth, the labels and
//! `truth.json`, each name with a prefix (a frame's or a stack slice's).

use crate::raw::Microscope;
use crate::request::Setup;
use crate::{PIPETTE, Rendered, Scene};
use formats::IoError;
use schemas::Plane;
use std::path::Path;

/// The files [`write_scene`] writes for `prefix`: of raw views (`raw`) only the views and
/// `truth.json` (the true maps are of rectified views).
pub fn scene_files(prefix: &str, raw: bool) -> Vec<String> {
    let all = [
        "left.png",
        "right.png",
        "disparity.pfm",
        "depth.pfm",
        "mask.png",
        "truth.json",
    ];
    all.iter()
        .filter(|n| !raw || ["left.png", "right.png", "truth.json"].contains(n))
        .map(|n| format!("{prefix}{n}"))
        .collect()
}

/// The prefix of stack slice `i`'s files.
pub fn slice_prefix(i: usize) -> String {
    format!("z{i:02}_")
}

/// The prefix of frame `f`'s files.
pub fn frame_prefix(f: usize) -> String {
    format!("f{f:04}_")
}

/// Every file `setup` writes: `calibration.toml` (of rectified views only: raw ones are
/// calibrated), then a stack's `heights.csv` and slices, a sequence's frames, or one
/// scene's files.
pub fn names(setup: &Setup) -> Vec<String> {
    let r = &setup.request;
    let raw = setup.microscope.is_some();
    let mut names = Vec::new();
    if !raw {
        names.push("calibration.toml".to_string());
    }
    match (&r.stage_heights, r.frames.unwrap_or(0)) {
        (Some(zs), _) => {
            names.push("heights.csv".into());
            names.extend((0..zs.len()).flat_map(|i| scene_files(&slice_prefix(i), raw)));
        }
        (None, 0) => names.extend(scene_files("", raw)),
        (None, n) => names.extend((0..n).flat_map(|f| scene_files(&frame_prefix(f), raw))),
    }
    names
}

/// Renders `scene` and writes its files into `dir`, each name prefixed with `prefix`: as
/// `microscope`'s raw views where it is given (then only the views and `truth.json`).
pub fn write_scene(
    dir: &Path,
    scene: &Scene,
    prefix: &str,
    microscope: Option<&Microscope>,
) -> Result<Rendered, IoError> {
    let r = scene.render();
    if let Some(m) = microscope {
        let (left, right) = m.render(scene);
        formats::write_mask_png(&dir.join(format!("{prefix}left.png")), &left)?;
        formats::write_mask_png(&dir.join(format!("{prefix}right.png")), &right)?;
        write_truth(dir, scene, &r, prefix)?;
        return Ok(r);
    }
    formats::write_mask_png(&dir.join(format!("{prefix}left.png")), &r.left)?;
    formats::write_mask_png(&dir.join(format!("{prefix}right.png")), &r.right)?;
    formats::write_pfm(&dir.join(format!("{prefix}disparity.pfm")), &r.disparity)?;
    formats::write_pfm(&dir.join(format!("{prefix}depth.pfm")), &r.depth)?;
    // A 16-bit label image cannot hold u32::MAX: the pipette gets its largest value.
    let labels = Plane::from_vec(
        r.labels.width,
        r.labels.height,
        r.labels
            .data
            .iter()
            .map(|&l| if l == PIPETTE { 65535 } else { l })
            .collect(),
    )
    .expect("size");
    formats::render::write_labels_png(&dir.join(format!("{prefix}mask.png")), &labels)?;
    write_truth(dir, scene, &r, prefix)?;
    Ok(r)
}

fn write_truth(dir: &Path, scene: &Scene, r: &Rendered, prefix: &str) -> Result<(), IoError> {
    let t = crate::truth::Truth::of(scene, r);
    formats::atomic::write_bytes(
        &dir.join(format!("{prefix}truth.json")),
        (serde_json::to_string_pretty(&t).expect("serialises") + "\n").as_bytes(),
    )
}

/// Renders the z-stack of `setup` into `dir`: each slice's files and `heights.csv`, the
/// list of its pairs with their stage heights (what `calibrate-depth` reads).
pub fn write_stack(dir: &Path, setup: &Setup) -> Result<(), IoError> {
    let mut csv = String::from("left,right,z_um\n");
    for (i, (z, s)) in setup.targets().enumerate() {
        let prefix = slice_prefix(i);
        write_scene(dir, &s, &prefix, setup.microscope.as_ref())?;
        csv += &format!("{prefix}left.png,{prefix}right.png,{z}\n");
    }
    formats::atomic::write_bytes(&dir.join("heights.csv"), csv.as_bytes())
}

/// Renders each frame of the sequence of `scene` into `dir`.
pub fn write_frames(dir: &Path, setup: &Setup, scene: &Scene) -> Result<(), IoError> {
    for f in 0..setup.request.frames.unwrap_or(0) {
        write_scene(
            dir,
            &setup.frame(scene, f),
            &frame_prefix(f),
            setup.microscope.as_ref(),
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Texture;
    use crate::request::Request;

    fn setup(r: Request) -> Setup {
        Request {
            width: 48,
            height: 40,
            cells: 2,
            diameter: vec![10.0, 16.0],
            ..r
        }
        .setup(Texture::Noise)
        .unwrap()
    }

    #[test]
    fn names_list_each_scenes_files() {
        let one = names(&setup(Request::default()));
        assert_eq!(
            one,
            [
                "calibration.toml",
                "left.png",
                "right.png",
                "disparity.pfm",
                "depth.pfm",
                "mask.png",
                "truth.json"
            ]
        );
        let seq = names(&setup(Request {
            frames: Some(2),
            ..Request::default()
        }));
        assert_eq!(seq.len(), 13);
        assert_eq!(seq[1], "f0000_left.png");
        assert_eq!(seq[12], "f0001_truth.json");
        let stack = names(&setup(Request {
            stage_heights: Some(vec![0.0, 1.0, 2.0]),
            frames: Some(5),
            ..Request::default()
        }));
        assert_eq!(stack.len(), 2 + 18);
        assert_eq!(stack[1], "heights.csv");
        assert_eq!(stack[19], "z02_truth.json");
    }

    #[test]
    fn a_stack_writes_its_slices_and_their_heights() {
        let dir = tempfile::tempdir().unwrap();
        let s = setup(Request {
            stage_heights: Some(vec![-5.0, 2.5]),
            ..Request::default()
        });
        write_stack(dir.path(), &s).unwrap();
        let csv = std::fs::read_to_string(dir.path().join("heights.csv")).unwrap();
        assert_eq!(
            csv,
            "left,right,z_um\nz00_left.png,z00_right.png,-5\nz01_left.png,z01_right.png,2.5\n"
        );
        let mut written: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        written.sort();
        let mut want: Vec<String> = names(&s).into_iter().skip(1).collect();
        want.sort();
        assert_eq!(written, want);
    }

    #[test]
    fn a_scene_is_written_as_rendered() {
        let dir = tempfile::tempdir().unwrap();
        let s = setup(Request {
            pipette: Some(3.0),
            ..Request::default()
        });
        let (scene, _) = s.cells().unwrap();
        let r = write_scene(dir.path(), &scene, "p_", None).unwrap();
        assert_eq!(r.disparity.data, scene.render().disparity.data);
        let d = formats::read_pfm(&dir.path().join("p_disparity.pfm"), "disparity").unwrap();
        assert_eq!(d.data, r.disparity.data);
        let truth: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(dir.path().join("p_truth.json")).unwrap(),
        )
        .unwrap();
        let (lo, hi) = r.disparity_range();
        assert_eq!(truth["disparity_range"][0].as_f64(), Some(lo as f64));
        assert_eq!(truth["disparity_range"][1].as_f64(), Some(hi as f64));
        assert!(truth["pipette"].is_object());
        for n in scene_files("p_", false) {
            assert!(dir.path().join(&n).is_file(), "{n}");
        }
    }

    #[test]
    fn a_raw_microscopes_stack_is_its_views_and_truth_without_a_calibration() {
        let raw = setup(Request {
            optics: crate::raw::Layout::Cmo,
            stage_heights: Some(vec![0.0, 10.0]),
            ..Request::default()
        });
        assert_eq!(
            names(&raw),
            [
                "heights.csv",
                "z00_left.png",
                "z00_right.png",
                "z00_truth.json",
                "z01_left.png",
                "z01_right.png",
                "z01_truth.json"
            ]
        );
        let m = raw.microscope.expect("a raw microscope");
        assert_eq!((m.width, m.height), (48, 40));
        assert_eq!(raw.optics.width, 48 + 2 * 48);
    }
}
