//! Times the triangulate node alone on the default graph's first two frames (1280×1024,
//! 10 cells): the first frame cold (its own substrate search), the second tracking the
//! first's plane, as in the live graph. For choosing what to speed up next.
//!
//! `cargo run --release --example triangulate_steps [RUNS]`
use runtime::exec::InProcess;
use runtime::node::{Msg, PortSet, Stamp, Task};
use std::path::Path;
use std::time::Instant;
use triangulate::node::{Triangulate, TriangulateIn, TriangulateParams};

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
        .unwrap_or(10);
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("launch.toml");
    let graph = microstereo::run::load(&file).expect("the default launch file");
    let log = InProcess::new(&graph, &pipelines::registry::builtin())
        .expect("the default graph")
        .run(2)
        .expect("two frames");
    // The node's inputs in its ports' order, as the default graph wires them.
    let edges = [
        ("rectify", "frame"),
        ("postprocess", "disparity"),
        ("validate", "left"),
        ("segment", "labels"),
        ("segment", "cells"),
    ];
    let inputs = |k: usize| -> (Stamp, TriangulateIn) {
        let msgs: Vec<Option<Msg>> = edges
            .iter()
            .map(|(n, p)| {
                let (header, payload) = &log[&(n.to_string(), p.to_string())][k];
                Some(Msg {
                    header: *header,
                    payload,
                })
            })
            .chain([None])
            .collect();
        let stamp = msgs[0].as_ref().expect("the frame").stamp();
        (stamp, TriangulateIn::decode(&msgs).expect("the inputs"))
    };
    // The default launch file's parameters: no point cloud.
    let params: TriangulateParams = toml::from_str("calibration = \"synthetic\"\ncloud_step = 0")
        .expect("the default parameters");
    let (mut cold, mut tracked) = (Vec::new(), Vec::new());
    for _ in 0..runs {
        let mut node = Triangulate::new(params.clone()).expect("the node");
        for (k, times) in [(0, &mut cold), (1, &mut tracked)] {
            let (stamp, i) = inputs(k);
            let t = Instant::now();
            node.process(stamp, i).expect("triangulated");
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    for (name, mut t) in [("first frame", cold), ("second, tracked", tracked)] {
        t.sort_by(f64::total_cmp);
        println!(
            "{name:>16}: median {:.2} ms, min {:.2} ms over {runs} runs",
            t[t.len() / 2],
            t[0]
        );
    }
}
