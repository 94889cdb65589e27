//! The bridge on tracks, over real TCP with the simulated manipulator: commands name a
//! track, the cell approached is the track's even when per-frame ids swap every frame, a
//! drifting cell is reached where it is, and tracks that cannot be approached are refused
//! with the reason.

mod common;

use common::{Client, cell, sim};
use manipulator_bridge::bridge::{Bridge, BridgeConfig};
use manipulator_bridge::geom::flip;
use manipulator_bridge::node::BridgeParams;
use manipulator_bridge::plan::injection_point;
use manipulator_bridge::scene::Obstacle;
use schemas::{Cell3, Track, TrackState, Tracks};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

fn track(id: u32, state: TrackState, c: Option<Cell3>, v: [f64; 2]) -> Track {
    let p = c.as_ref().map_or([0.0; 3], |c| c.centroid);
    Track {
        id,
        state,
        age: 10,
        missed: if c.is_some() { 0 } else { 3 },
        frames_used: 10,
        position: p,
        position_std: 0.2,
        velocity: [v[0], v[1], 0.0],
        height: c.as_ref().and_then(|c| c.height),
        height_std: Some(0.1),
        volume: 0.0,
        volume_std: 0.0,
        trusted: true,
        cell: c,
    }
}

fn config() -> BridgeConfig {
    let mut t = toml::Table::new();
    t.insert("stale_ms".into(), toml::Value::Integer(3000));
    t.insert("max_speed".into(), toml::Value::Float(100.0));
    BridgeParams::from_table(&t).unwrap().config()
}

/// Where the drifting cell (track 7) is `t` seconds after the start: 20 µm/s along +y.
fn drifter(t: f64) -> [f64; 2] {
    [40.0, -30.0 + 20.0 * t]
}

/// The scene at `t` s, captured `latency` s before it reaches the bridge: track 7 drifts,
/// track 9 stands; their per-frame ids swap every frame.
fn scene(frame: u64, t: f64, latency: f64, now_ns: u64) -> Tracks {
    let a = drifter(t - latency);
    let (ia, ib) = if frame.is_multiple_of(2) {
        (1, 2)
    } else {
        (2, 1)
    };
    Tracks {
        frame,
        capture_ns: now_ns - (latency * 1e9) as u64,
        unit: "um".into(),
        shift: [0.0; 3],
        tracks: vec![
            track(
                7,
                TrackState::Confirmed,
                Some(cell(ia, a[0], a[1], 12.0, 10.0)),
                [0.0, 20.0],
            ),
            track(
                9,
                TrackState::Confirmed,
                Some(cell(ib, 160.0, 60.0, 12.0, 14.0)),
                [0.0; 2],
            ),
            track(
                11,
                TrackState::Tentative,
                Some(cell(3, -200.0, 200.0, 8.0, 6.0)),
                [0.0; 2],
            ),
            track(12, TrackState::Lost, None, [0.0; 2]),
        ],
        substrate: None,
    }
}

#[test]
fn an_approach_names_a_track_and_reaches_its_drifting_cell_though_frame_ids_swap() {
    let cfg = config();
    let b = Bridge::start(cfg.clone(), "127.0.0.1:0", sim(&cfg)).unwrap();
    let stop = AtomicBool::new(false);
    let t0 = Instant::now();
    // 60 ms from capture to the bridge, as the default graph's loop.
    let latency = 0.06;
    /// Stops the feeding thread however the test ends (a failed assertion included).
    struct Stop<'a>(&'a AtomicBool);
    impl Drop for Stop<'_> {
        fn drop(&mut self) {
            self.0.store(true, Ordering::SeqCst);
        }
    }
    std::thread::scope(|s| {
        let _stop = Stop(&stop);
        s.spawn(|| {
            let mut f = 0;
            while !stop.load(Ordering::SeqCst) {
                let t = t0.elapsed().as_secs_f64();
                b.on_tracks(&scene(f, t, latency, runtime::process::now_ns()))
                    .unwrap();
                f += 1;
                std::thread::sleep(Duration::from_millis(33));
            }
        });
        let mut c = Client::connect(&b);
        let sc = c.next(&["scene"]);
        assert_eq!(sc["ids"], "track", "{sc}");
        let ids: Vec<u64> = sc["cells"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c["id"].as_u64().unwrap())
            .collect();
        // The lost track has no cell yet to stand for it; the others are cells by track.
        assert_eq!(ids, vec![7, 9, 11], "{sc}");
        // A per-frame index is refused: it names another cell every frame here.
        c.send(r#"{"cmd":"approach","cell":1}"#);
        let e = c.next(&["error", "plan"]);
        assert!(
            e["message"].as_str().unwrap().contains("by its track"),
            "{e}"
        );
        c.send(r#"{"cmd":"approach","track":11}"#);
        let e = c.next(&["error", "plan"]);
        assert!(e["message"].as_str().unwrap().contains("tentative"), "{e}");
        c.send(r#"{"cmd":"approach","track":12}"#);
        let e = c.next(&["error", "plan"]);
        assert!(e["message"].as_str().unwrap().contains("is lost"), "{e}");
        c.send(r#"{"cmd":"approach","track":99}"#);
        let e = c.next(&["error", "plan"]);
        assert!(
            e["message"].as_str().unwrap().contains("no track 99"),
            "{e}"
        );
        c.send(r#"{"cmd":"approach","track":7,"speed":100}"#);
        let plan = c.next(&["plan", "error", "blocked"]);
        assert_eq!(plan["event"], "plan", "{plan}");
        assert_eq!(plan["plan"]["target"], 7, "{plan}");
        let ev = c.next(&["arrived", "blocked", "error", "stopped"]);
        let t = t0.elapsed().as_secs_f64();
        assert_eq!(ev["event"], "arrived", "{ev}");
        let tip: Vec<f64> = ev["tip"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        // Where the cell is now: its injection point, as the planner places it.
        let now = drifter(t);
        let truth = Obstacle::from_cell(&cell(7, now[0], now[1], 12.0, 10.0), 1.0, 100.0);
        let want = flip(injection_point(&truth, &cfg.planner));
        let err =
            ((tip[0] - want[0]).powi(2) + (tip[1] - want[1]).powi(2) + (tip[2] - want[2]).powi(2))
                .sqrt();
        let other = flip(injection_point(
            &Obstacle::from_cell(&cell(9, 160.0, 60.0, 12.0, 14.0), 1.0, 100.0),
            &cfg.planner,
        ));
        let to_other = ((tip[0] - other[0]).powi(2) + (tip[1] - other[1]).powi(2)).sqrt();
        eprintln!(
            "arrived {err:.2} µm from the drifting cell's injection point ({to_other:.0} µm from the other)"
        );
        assert!(to_other > 100.0);
        // The instrument's goal: within 2 µm of the drifting cell's injection point. Measured
        // 1.0–1.17 µm (two CPU hogs and a build beside it; 1.2–1.5 before the last short legs
        // led the cell by its velocity over their own time): what is left is the drift
        // between the arrival and this reading.
        assert!(
            err < 2.0,
            "{err} µm off: tip {tip:?}, injection point {want:?}"
        );
    });
}

#[test]
fn a_track_that_ended_is_refused_with_when_it_was_last_seen() {
    let cfg = config();
    let b = Bridge::start(cfg.clone(), "127.0.0.1:0", sim(&cfg)).unwrap();
    let mut c = Client::connect(&b);
    let now = runtime::process::now_ns();
    b.on_tracks(&scene(0, 0.0, 0.0, now)).unwrap();
    let mut later = scene(1, 0.03, 0.0, now);
    later.tracks.retain(|t| t.id != 9);
    b.on_tracks(&later).unwrap();
    c.send(r#"{"cmd":"approach","track":9}"#);
    let e = c.next(&["error", "plan"]);
    let m = e["message"].as_str().unwrap();
    assert!(m.contains("track 9 ended") && m.contains("frame 0"), "{e}");
}
