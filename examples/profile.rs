//! Times the quality or paper matcher alone on cones, five runs, for profiling with perf.
//!
//! `cargo run --release --example profile [quality|quality4|paper]` (quality4: 4 SGM paths)
use capture::image as io;
use schemas::DisparityRange;
use std::time::Instant;
fn main() {
    let d = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/cones");
    let l = io::load(&d.join("im2.png"), "l").unwrap().grey;
    let r = io::load(&d.join("im6.png"), "r").unwrap().grey;
    let mode = std::env::args().nth(1).unwrap_or("quality".into());
    for _ in 0..5 {
        let t = Instant::now();
        if mode.starts_with("quality") {
            let p = matcher::QualityParams {
                range: DisparityRange::new(0, 63),
                paths: if mode == "quality4" { 4 } else { 8 },
                ..Default::default()
            };
            matcher::match_quality(&l, &r, &p);
        } else {
            let p = matcher::PaperParams {
                range: DisparityRange::new(0, 63),
                ..Default::default()
            };
            matcher::match_paper(&l, &r, &p, matcher::Directions::Both);
        }
        println!("{mode} {:.1} ms", t.elapsed().as_secs_f64() * 1e3);
    }
}
