//! Times each step of `segment::segment` on a view of the default graph's scene (1280×1024,
//! 10 cells), for choosing what to speed up next.
//!
//! `cargo run --release --example segment_steps [RUNS]`
use segment::{
    Connectivity, SegmentParams, absorb_rings, close, describe_cells_from, fill_broken_outlines,
    fill_holes, histogram, label, open, otsu_threshold, peel_edges, remove_small, variance_levels,
};
use std::time::Instant;

fn main() {
    // As the node's binary does (src/main.rs): freed maps are kept for the next frame.
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets allocator parameters; called before any thread starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 1 << 30);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30);
    }
    let runs: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(5);
    // The default graph's capture, with its default parameters: its first frame's left view.
    let params = capture::synthetic::SyntheticParams::from_table(&toml::Table::new())
        .expect("the default parameters");
    let img = capture::synthetic::SyntheticCapture::new(&params)
        .frame(0)
        .left;
    let p = SegmentParams::default();
    let mut steps: Vec<(&str, f64)> = Vec::new();
    let mut add = |name: &'static str, t: Instant| {
        let ms = t.elapsed().as_secs_f64() * 1e3;
        match steps.iter_mut().find(|(n, _)| *n == name) {
            Some(s) => s.1 += ms,
            None => steps.push((name, ms)),
        }
    };
    for _ in 0..runs {
        let whole = Instant::now();
        let t = Instant::now();
        let (variance, _) = variance_levels(&img, p.variance_radius, p.scale);
        add("variance levels 0-255", t);
        let t = Instant::now();
        let threshold = otsu_threshold(&histogram(&variance)).unwrap_or(255);
        let data = variance
            .data
            .iter()
            .map(|&v| if v >= threshold { 255 } else { 0 })
            .collect();
        let mut mask = runtime_plane(img.width, img.height, data);
        add("otsu + threshold", t);
        let t = Instant::now();
        mask = close(&open(&mask, p.open_radius), p.close_radius);
        add("open/close", t);
        let t = Instant::now();
        mask = fill_holes(&mask);
        add("fill holes", t);
        let t = Instant::now();
        mask = fill_broken_outlines(&mask, p.variance_radius as u8 + 1);
        add("fill broken outlines", t);
        let t = Instant::now();
        let m = p.variance_radius;
        mask = peel_edges(&img, &mask, m + 1, 4 * m + 4, 2.25);
        add("peel edges", t);
        let t = Instant::now();
        mask = remove_small(&mask, p.min_area);
        add("remove small", t);
        let t = Instant::now();
        let (mut labels, n) = label(&mask, Connectivity::Eight);
        add("label", t);
        let t = Instant::now();
        let (n, starts) = absorb_rings(&mut labels, n);
        add("absorb rings", t);
        let t = Instant::now();
        let cells = describe_cells_from(&labels, n, Some(&starts));
        add("describe cells", t);
        assert!(!cells.is_empty());
        add("whole", whole);
    }
    for (name, ms) in steps {
        println!("{name:>22} {:7.2} ms", ms / runs as f64);
    }
}

fn runtime_plane(w: usize, h: usize, data: Vec<u8>) -> schemas::Mask {
    schemas::Mask::from_vec(w, h, data).expect("same size")
}
