//! Times the embedded synthetic source, the default graph's capture (1280×1024, 10 cells,
//! drifting): every frame rendered whole, against frames over the scene's backdrop, and
//! those with the noise of a table drawn once (what the capture node does), in turn.
//!
//! `cargo run --release --example capture_render [FRAMES]`
use std::time::Instant;
use synth::{CellSpec, Look, NoiseTable, Optics, Scene};

fn main() {
    let frames: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(10);
    let optics = Optics {
        width: 1280,
        height: 1024,
        ..Optics::default()
    };
    let spec = CellSpec {
        count: 10,
        ..CellSpec::default()
    };
    let scene = Scene::random(optics, Look::default(), &spec, 1);
    let mut backdrop = None;
    let t = Instant::now();
    let _ = scene.render_views_over(&mut backdrop);
    println!(
        "backdrop and frame 0: {:.1} ms",
        t.elapsed().as_secs_f64() * 1e3
    );
    let t = Instant::now();
    let table = NoiseTable::new(optics.width, optics.height, 1);
    println!("noise table: {:.1} ms", t.elapsed().as_secs_f64() * 1e3);
    let (mut whole, mut over, mut tabled) = (0.0, 0.0, 0.0);
    for f in 1..=frames {
        let s = scene.at_frame(f, 1.0, 4.0);
        let t = Instant::now();
        let a = s.render_views();
        whole += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let b = s.render_views_over(&mut backdrop);
        over += t.elapsed().as_secs_f64();
        assert!(a == b, "frame {f} differs");
        let t = Instant::now();
        let _ = table.apply(s.render_means_over(&mut backdrop), s.look.noise, f as u64);
        tabled += t.elapsed().as_secs_f64();
    }
    let n = frames as f64;
    println!(
        "{frames} frames: whole {:.1} ms, over the backdrop {:.1} ms ({:.1}× faster), with table noise {:.1} ms ({:.1}× faster) a frame",
        1e3 * whole / n,
        1e3 * over / n,
        whole / over,
        1e3 * tabled / n,
        whole / tabled
    );
}
