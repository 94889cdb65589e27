//! Issue 21's closed loop: a simulated manipulator mounted turned 30° about the vertical,
//! its x stretched 1.1, its y flipped and its z shrunk 0.9, seen by the synthetic
//! microscope. `calibrate-manipulator`'s registration (tips found in the images at 18
//! stops) lets the bridge take the pipette into a cell: the true tip ends within 2 µm of
//! the planned injection point and the true body keeps its clearance from the other cells.

mod common;

use manipulator_bridge::bridge::Bridge;
use manipulator_bridge::device::{Device, SimDevice, wall_clock};
use manipulator_bridge::geom::P3;
use manipulator_bridge::node::BridgeParams;
use manipulator_bridge::scene::Scene;
use registration::{Optics, SimMicroscope, grid_stops, mount, register};
use schemas::DisparityRange;
use std::io::{BufRead, Write};
use std::time::{Duration, Instant};

#[test]
fn after_calibrate_manipulator_an_approach_reaches_the_injection_point_within_2_um() {
    let truth = mount(&[30.0, 1.1, -1.0, 0.9, 1200.0, -300.0, 5000.0]).unwrap();
    let mut micro = SimMicroscope::new(2, truth);
    let z0 = micro.scene.optics.working_distance();
    let start: P3 = [-60.0, 20.0, 3940.0];
    // Clones drive the same sim: the test reads where it truly is.
    let sim = SimDevice::new(truth.to_device(start), 2000.0, 20_000.0, wall_clock());
    let mut dev = sim.clone();
    let optics = Optics {
        rectify: None,
        calibration: micro.scene.optics.calibration(),
    };
    let at = dev.state().unwrap().position;
    let fit = register(
        &mut dev,
        &mut |p| Ok(micro.frame(p)),
        &optics,
        &grid_stops(at, [3, 3, 2], [40.0, 40.0, 20.0]),
        1000.0,
    )
    .unwrap();
    eprintln!(
        "registration rms {:.3} µm, matrix {:?}",
        fit.rms, fit.registration.matrix
    );
    assert!(fit.refuse(3.0).is_none(), "{:?}", fit.refuse(3.0));
    // Where the glass's front truly is with the device at `d`, camera frame.
    let front = |micro: &SimMicroscope, d: P3| {
        let p = synth::Pipette::from_tip(
            truth.to_scene(d),
            micro.pipette_deg.0,
            micro.pipette_deg.1,
            z0,
        )
        .front();
        [p[0], p[1], z0 - p[2]]
    };

    // The cells as the graph measures them (the bridge takes the pipette's own image for
    // the pipette; here it is out of view).
    let mut bare = micro.scene.clone();
    bare.pipette = None;
    let (left, right) = bare.render_views();
    let frame = schemas::StereoFrame { left, right };
    let (mut targets, _) = common::cell_targets(
        &frame.left,
        &frame.right,
        &optics.calibration,
        DisparityRange::new(-4, 24),
    );
    let params = BridgeParams::from_table(&toml::from_str(&format!(
        "listen = \"127.0.0.1:0\"\nregistration = {{ matrix = {:?}, offset = {:?} }}\nmax_speed = 400.0",
        fit.registration.matrix, fit.registration.offset
    )).unwrap())
    .unwrap();
    let cfg = params.config();
    let bridge = Bridge::start(cfg.clone(), "127.0.0.1:0", Ok(Box::new(sim.clone()))).unwrap();
    let client = std::net::TcpStream::connect(bridge.addr).unwrap();
    client
        .set_read_timeout(Some(Duration::from_millis(20)))
        .unwrap();
    let mut out = client.try_clone().unwrap();
    let mut lines = std::io::BufReader::new(client);
    let t0 = Instant::now();
    while bridge.controllers() == 0 {
        assert!(t0.elapsed() < Duration::from_secs(10));
        std::thread::sleep(Duration::from_millis(1));
    }
    // The target: the measured cell nearest the pipette's start, with its height trusted.
    let scene = Scene::from_targets(&targets, cfg.untrusted_height).unwrap();
    let target = scene
        .cells
        .iter()
        .filter(|c| c.trusted)
        .min_by(|a, b| {
            let d = |c: &&manipulator_bridge::scene::Obstacle| {
                (c.centre[0] - start[0]).hypot(c.centre[1] - start[1])
            };
            d(a).total_cmp(&d(b))
        })
        .expect("a trusted cell")
        .id;
    let mut sent = false;
    let mut end = None;
    let mut path: Vec<P3> = Vec::new();
    let t0 = Instant::now();
    while end.is_none() {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "no arrival within 60 s"
        );
        targets.frame += 1;
        targets.capture_ns = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_nanos() as u64;
        bridge.on_targets(&targets).unwrap();
        if !sent {
            writeln!(out, "{{\"cmd\":\"approach\",\"cell\":{target}}}").unwrap();
            sent = true;
        }
        let mut line = String::new();
        while lines.read_line(&mut line).is_ok_and(|n| n > 0) {
            let ev: serde_json::Value = serde_json::from_str(&line).unwrap();
            match ev["event"].as_str() {
                Some("arrived") => {
                    let e = &ev["end"];
                    end = Some([
                        e[0].as_f64().unwrap(),
                        e[1].as_f64().unwrap(),
                        e[2].as_f64().unwrap(),
                    ]);
                }
                Some("blocked" | "error") => panic!("{ev}"),
                _ => {}
            }
            line.clear();
        }
        path.push(front(&micro, sim.clone().state().unwrap().position));
        std::thread::sleep(Duration::from_millis(15));
    }
    let end = end.unwrap();
    let got = front(&micro, sim.clone().state().unwrap().position);
    let err =
        ((got[0] - end[0]).powi(2) + (got[1] - end[1]).powi(2) + (got[2] - end[2]).powi(2)).sqrt();
    // The true body along the whole path, against every cell but the target.
    let clearance = path
        .windows(2)
        .map(|w| {
            manipulator_bridge::plan::leg_clearance(
                &scene,
                &cfg.planner,
                // The planner's frame: the third coordinate up.
                (
                    manipulator_bridge::geom::flip(w[0]),
                    manipulator_bridge::geom::flip(w[1]),
                ),
                Some(target),
                f64::INFINITY,
            )
            .0
        })
        .fold(f64::INFINITY, f64::min);
    eprintln!(
        "true tip {err:.3} µm from the injection point {end:?}; the true body's least clearance {clearance:.2} µm (kept: {} µm)",
        cfg.planner.clearance
    );
    assert!(err <= 2.0, "{err}");
    assert!(
        clearance >= cfg.planner.clearance - err.max(1.0),
        "{clearance}"
    );
}
