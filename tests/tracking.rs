//! Tracks through the process graph: examples/tour.toml (a 600-frame choreographed tour of a
//! brightfield dish: drift, crossing rows, a close pass, a cell leaving the view and coming
//! back, one covered by the pipette for 10 frames, a 100 µm stage move within a second)
//! run as processes, its `track/tracks` edge recorded, every frame's tracks scored against
//! the tour's truth.

mod common;

use capture::synthetic::{SyntheticCapture, SyntheticParams};
use recorder::file::EdgeReader;
use schemas::{Message, Tracks};
use std::path::{Path, PathBuf};
use track::score::{TruthCell, score};

fn tour_graph() -> (String, SyntheticCapture) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/tour.toml");
    let text = std::fs::read_to_string(path).unwrap();
    let launch: toml::Table = text.parse().unwrap();
    let capture = launch["node"]
        .as_array()
        .unwrap()
        .iter()
        .find(|n| n["id"].as_str() == Some("capture"))
        .unwrap();
    let mut params = SyntheticParams::from_table(capture["params"].as_table().unwrap()).unwrap();
    // With MICROSTEREO_TOUR_MCAP, the seed and cells that recording was run with.
    let env = |name: &str| std::env::var(name).ok().and_then(|s| s.parse().ok());
    if let Some(seed) = env("MICROSTEREO_TOUR_SEED") {
        params.seed = seed as u64;
    }
    if let Some(cells) = env("MICROSTEREO_TOUR_CELLS") {
        params.cells = cells;
    }
    (text, SyntheticCapture::new(&params))
}

/// Runs the tour graph for `frames` frames, recording its tracks; `MICROSTEREO_TOUR_MCAP`
/// names a recording to score instead (to look at one run again).
fn run_tour(frames: u64, dir: &Path) -> PathBuf {
    if let Ok(p) = std::env::var("MICROSTEREO_TOUR_MCAP") {
        return p.into();
    }
    let rec = dir.join("tour.mcap");
    let instance = format!("tour{}", std::process::id());
    let launch = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/tour.toml");
    let frames = frames.to_string();
    let out = common::run(&[
        "run",
        common::s(&launch),
        "--quiet",
        "--instance",
        &instance,
        "--frames",
        &frames,
        "--record",
        common::s(&rec),
        "--edges",
        "track/tracks",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("{}", String::from_utf8_lossy(&out.stderr));
    rec
}

fn read_tracks(rec: &Path) -> Vec<Tracks> {
    // MICROSTEREO_TOUR_RETRACK: the recording's targets tracked again by this build's
    // tracker (a recording made with `--edges track/tracks triangulate/targets`).
    if std::env::var_os("MICROSTEREO_TOUR_RETRACK").is_some() {
        let mut tracker = track::Tracker::new(track::TrackerParams::default());
        return EdgeReader::open(rec, Some(vec!["triangulate/targets".into()]))
            .unwrap()
            .map(|m| {
                let m = m.unwrap();
                let t = schemas::Targets::decode(&m.header, &m.payload).unwrap();
                tracker.update(&t).unwrap()
            })
            .collect();
    }
    EdgeReader::open(rec, Some(vec!["track/tracks".into()]))
        .unwrap()
        .map(|m| {
            let m = m.unwrap();
            Tracks::decode(&m.header, &m.payload).unwrap()
        })
        .collect()
}

#[test]
fn every_cell_of_a_600_frame_tour_keeps_one_track_id_through_the_process_graph() {
    let (_, capture) = tour_graph();
    let tour = capture
        .tour()
        .expect("the tour graph's capture plays a tour");
    let dir = tempfile::tempdir().unwrap();
    let rec = run_tour(600, dir.path());
    let runs = read_tracks(&rec);
    let truth = |f: u64| -> Vec<TruthCell> {
        tour.truth(f)
            .into_iter()
            .map(|c| TruthCell {
                id: c.cell,
                centre: c.centre,
                radius: c.reach,
                visible: c.visible,
            })
            .collect()
    };
    let s = score(&runs, truth, 5);
    // MICROSTEREO_TOUR_DEBUG=CELL prints every track near that cell, frame by frame.
    if let Some(cell) = std::env::var("MICROSTEREO_TOUR_DEBUG")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
    {
        for t in &runs {
            let c = tour.truth(t.frame)[cell];
            let near: Vec<String> = t
                .tracks
                .iter()
                .filter(|tr| {
                    (tr.position[0] - c.centre[0]).hypot(tr.position[1] - c.centre[1]) < 80.0
                })
                .map(|tr| {
                    format!(
                        "{} {:?} pos {:.1},{:.1} cell {:?}",
                        tr.id,
                        tr.state,
                        tr.position[0] - c.centre[0],
                        tr.position[1] - c.centre[1],
                        tr.cell
                            .as_ref()
                            .map(|x| [x.centroid[0] - c.centre[0], x.centroid[1] - c.centre[1]])
                    )
                })
                .collect();
            let ids: Vec<u32> = t.tracks.iter().map(|tr| tr.id).collect();
            // Each confirmed track's cell against the true cell nearest it: the measurement's
            // own error, and its velocity.
            let truth_now = tour.truth(t.frame);
            let errs: Vec<String> = t
                .tracks
                .iter()
                .filter_map(|tr| {
                    let p = tr.cell.as_ref()?.centroid;
                    let c = truth_now.iter().min_by(|a, b| {
                        let d = |c: &&synth::tour::TourCell| {
                            (p[0] - c.centre[0]).hypot(p[1] - c.centre[1])
                        };
                        d(a).total_cmp(&d(b))
                    })?;
                    Some(format!(
                        "{}:{:+.1},{:+.1} v{:+.0},{:+.0}",
                        tr.id,
                        p[0] - c.centre[0],
                        p[1] - c.centre[1],
                        tr.velocity[0],
                        tr.velocity[1]
                    ))
                })
                .collect();
            eprintln!("  {errs:?}");
            let r = tour.roles.covered;
            let moved = |f: u64| tour.truth(f)[r].centre[0];
            let before = runs.iter().take_while(|x| x.frame < t.frame).last();
            let prev = before.map_or(t.frame, |x| x.frame);
            let dt_ms = before.map_or(0.0, |x| (t.capture_ns as f64 - x.capture_ns as f64) / 1e6);
            eprintln!(
                "{} dt {dt_ms:.1} ms vis {} stage moved {:.1} shift {:?}: {near:?} all {ids:?}",
                t.frame,
                c.visible,
                moved(t.frame) - moved(prev),
                t.shift
            );
        }
    }
    eprintln!(
        "tour: {} frames scored (last {}), {} of {} visible cells on a confirmed track, {} ids, longest wait {} frames, {} strays; switches {:?}; shared {:?}; reused {:?}; late {:?}",
        s.frames,
        runs.last().map_or(0, |t| t.frame),
        s.matched,
        s.visible,
        s.ids,
        s.longest_wait,
        s.strays,
        s.switches,
        s.shared,
        s.reused,
        s.late
    );
    // The frames let in span the tour; under load the entrance lets fewer in.
    assert!(s.frames >= 150, "{} frames", s.frames);
    assert!(runs.last().unwrap().frame >= 590);
    assert!(s.clean(), "{s:?}");
    // Every part was played and seen: the covered cell and the leaver were tracked again.
    let roles = tour.roles;
    for cell in [
        roles.covered,
        roles.leaver,
        roles.crossing[0],
        roles.close[0],
    ] {
        let seen_after = runs.iter().rev().take(20).any(|t| {
            t.tracks.iter().any(|tr| {
                tr.cell.is_some() && {
                    let c = tour.truth(t.frame)[cell];
                    let p = tr.cell.as_ref().unwrap().centroid;
                    (p[0] - c.centre[0]).hypot(p[1] - c.centre[1]) < 0.5 * c.reach
                }
            })
        });
        assert!(seen_after || !tour.truth(599)[cell].visible, "cell {cell}");
    }
    // Nearly every visible cell is on a confirmed track (the rest wait for confirmation or
    // are cut by the view's edge).
    assert!(s.matched as f64 >= 0.95 * s.visible as f64, "{s:?}");
}
