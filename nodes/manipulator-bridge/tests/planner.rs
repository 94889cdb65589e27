//! Property tests of the planner on random scenes: every returned path keeps the whole
//! pipette body clear of every cell but the target (checked by dense sampling, not by the
//! planner's own searches), and a target walled in by tall neighbours has no path.

use manipulator_bridge::geom::{P3, Prism, axpy, box_dist, dist, sub, swept_bounds};
use manipulator_bridge::plan::{
    Entry, PipetteGeometry, PlannerConfig, plan_approach, plan_goto, plan_retract,
};
use manipulator_bridge::scene::{Obstacle, Scene, Workspace};
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// An elliptic cell standing on the substrate at height 0.
fn ellipse(id: u32, c: [f64; 2], axes: [f64; 2], angle: f64, h: f64) -> Obstacle {
    let (co, si) = (angle.cos(), angle.sin());
    let poly: Vec<[f64; 2]> = (0..20)
        .map(|k| {
            let t = k as f64 * std::f64::consts::TAU / 20.0;
            let (x, y) = (axes[0] * t.cos(), axes[1] * t.sin());
            [c[0] + co * x - si * y, c[1] + si * x + co * y]
        })
        .collect();
    Obstacle {
        id,
        prism: Prism {
            poly,
            zlo: -1.0,
            zhi: h,
        },
        centre: c,
        base: 0.0,
        top: h,
        trusted: true,
        doubt: None,
    }
}

fn config(elevation: f64, azimuth: f64, entry: Entry) -> PlannerConfig {
    PlannerConfig {
        pipette: PipetteGeometry {
            elevation_deg: elevation,
            azimuth_deg: azimuth,
            length: 300.0,
        },
        entry,
        workspace: Workspace {
            min: [-600.0, -600.0, 0.0],
            max: [600.0, 600.0, 400.0],
        },
        ..PlannerConfig::default()
    }
}

/// The least distance between the body and the cells but `exempt` over one leg, by
/// sampling tip and body every `step` µm.
fn sampled_clearance(
    scene: &Scene,
    cfg: &PlannerConfig,
    a: P3,
    b: P3,
    exempt: Option<u32>,
    step: f64,
) -> f64 {
    let u = cfg.pipette.axis();
    let len = cfg.pipette.length;
    let nt = (dist(a, b) / step).ceil().max(1.0) as usize;
    let ns = (len / step).ceil() as usize;
    let mut best = f64::INFINITY;
    let sweep = swept_bounds(a, b, u, len);
    // Cells whose boxes are far from the swept body's box cannot break the clearance.
    for c in scene
        .cells
        .iter()
        .filter(|c| Some(c.id) != exempt && box_dist(c.prism.bounds(), sweep) < cfg.clearance + 5.0)
    {
        for i in 0..=nt {
            let tip = axpy(a, i as f64 / nt as f64, sub(b, a));
            for k in 0..=ns {
                let p = axpy(tip, k as f64 * len / ns as f64, u);
                let d = c.prism.dist_point(p);
                best = best.min(d);
            }
        }
    }
    best.min(cfg.clearance + 5.0)
}

/// Random non-overlapping cells around the origin.
fn random_scene(seed: u64, n: usize) -> Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut cells: Vec<Obstacle> = Vec::new();
    let mut tries = 0;
    while cells.len() < n && tries < 1000 {
        tries += 1;
        let c = [
            rng.random_range(-250.0..250.0),
            rng.random_range(-250.0..250.0),
        ];
        let axes: [f64; 2] = [rng.random_range(8.0..30.0), rng.random_range(8.0..30.0)];
        if cells
            .iter()
            .any(|o| (o.centre[0] - c[0]).hypot(o.centre[1] - c[1]) < axes[0].max(axes[1]) + 35.0)
        {
            continue;
        }
        let id = cells.len() as u32 + 1;
        cells.push(ellipse(
            id,
            c,
            axes,
            rng.random_range(0.0..3.2),
            rng.random_range(5.0..45.0),
        ));
    }
    Scene::new(1, cells)
}

/// A start where the whole body keeps the clearance from every cell.
fn random_start(scene: &Scene, cfg: &PlannerConfig, rng: &mut ChaCha8Rng) -> P3 {
    loop {
        let p = [
            rng.random_range(-400.0..400.0),
            rng.random_range(-400.0..400.0),
            rng.random_range(10.0..150.0),
        ];
        if sampled_clearance(scene, cfg, p, p, None, 0.5) > cfg.clearance + 1.0 {
            return p;
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    #[test]
    fn returned_paths_keep_the_body_clear_of_every_other_cell(
        seed in 0u64..1_000_000,
        n in 2usize..10,
        elevation in 20.0f64..45.0,
        azimuth in 0.0f64..360.0,
        side in any::<bool>(),
    ) {
        let scene = random_scene(seed, n);
        let cfg = config(elevation, azimuth, if side { Entry::Side } else { Entry::Top });
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed);
        let start = random_start(&scene, &cfg, &mut rng);
        let target = scene.cells[rng.random_range(0..scene.cells.len())].id;
        match plan_approach(&scene, &cfg, start, target) {
            Ok(plan) => {
                prop_assert_eq!(plan.waypoints[0], start);
                prop_assert!(plan.min_clearance >= cfg.clearance);
                let u = cfg.pipette.axis();
                for (k, w) in plan.waypoints.windows(2).enumerate() {
                    let d = sampled_clearance(&scene, &cfg, w[0], w[1], Some(target), 0.5);
                    prop_assert!(d >= cfg.clearance - 1e-6,
                        "leg {} {:?} → {:?} comes within {} µm of a cell", k, w[0], w[1], d);
                    prop_assert!(cfg.workspace.contains(w[1]));
                    if k >= plan.axial_from {
                        // Along the axis: the leg is parallel to the body.
                        let v = sub(w[1], w[0]);
                        let l = dist(w[0], w[1]);
                        let cos = -(v[0] * u[0] + v[1] * u[1] + v[2] * u[2]) / l;
                        prop_assert!((cos - 1.0).abs() < 1e-9, "axial leg {} is off the axis", k);
                    }
                }
                // Same scene, same path.
                prop_assert_eq!(plan_approach(&scene, &cfg, start, target).unwrap(), plan.clone());
                // And back out.
                let r = plan_retract(&scene, &cfg, plan.end, Some(target)).unwrap();
                let d = sampled_clearance(&scene, &cfg, r.waypoints[0], r.waypoints[1], Some(target), 0.5);
                prop_assert!(d >= cfg.clearance - 1e-6);
            }
            Err(e) => {
                // Only a real obstacle or the workspace may refuse it.
                prop_assert!(!e.blocking.is_empty() || e.reason.contains("out of reach"), "{}", e.reason);
            }
        }
    }

    #[test]
    fn goto_paths_keep_the_body_clear_of_every_cell(seed in 0u64..1_000_000, n in 2usize..10) {
        let scene = random_scene(seed, n);
        let cfg = config(30.0, 180.0, Entry::Top);
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x90);
        let (a, b) = (random_start(&scene, &cfg, &mut rng), random_start(&scene, &cfg, &mut rng));
        let plan = plan_goto(&scene, &cfg, a, b).unwrap();
        prop_assert_eq!(plan.end, b);
        for w in plan.waypoints.windows(2) {
            prop_assert!(sampled_clearance(&scene, &cfg, w[0], w[1], None, 0.5) >= cfg.clearance - 1e-6);
        }
    }

    #[test]
    fn a_target_walled_in_by_tall_neighbours_has_no_path(
        x in -100.0f64..100.0,
        y in -100.0f64..100.0,
        elevation in 20.0f64..45.0,
        azimuth in 0.0f64..360.0,
        side in any::<bool>(),
    ) {
        let cfg = config(elevation, azimuth, if side { Entry::Side } else { Entry::Top });
        let mut cells = vec![ellipse(1, [x, y], [10.0, 10.0], 0.0, 12.0)];
        // Twelve cells of radius 10 on a ring of radius 40: gaps of 1 µm, and every one
        // taller than the axis at its far edge (45° over 50 µm) by 10 µm.
        for k in 0..12 {
            let a = k as f64 * std::f64::consts::TAU / 12.0;
            cells.push(ellipse(k + 2, [x + 40.0 * a.cos(), y + 40.0 * a.sin()], [10.0, 10.0], 0.0, 12.0 + 50.0 + 10.0));
        }
        let walled = Scene::new(1, cells.clone());
        let e = plan_approach(&walled, &cfg, [-500.0, -500.0, 350.0], 1).unwrap_err();
        prop_assert!(e.reason.contains("walled in"), "{}", e.reason);
        prop_assert!(!e.blocking.is_empty() && !e.blocking.contains(&1));
        // Without the ring the same target is reachable.
        let open = Scene::new(1, cells[..1].to_vec());
        prop_assert!(plan_approach(&open, &cfg, [-500.0, -500.0, 350.0], 1).is_ok());
    }
}

/// A cell of a frame's targets, in µm with depth down (substrate at depth 4000), circular
/// of radius `r`; `height: None` or `trusted: false` as the triangulation reports them.
fn target_cell(id: u32, x: f64, r: f64, height: Option<f64>, trusted: bool) -> schemas::Cell3 {
    let z0 = 4000.0;
    schemas::Cell3 {
        id,
        right_id: id,
        area_px: 100,
        centroid_px: [0.0, 0.0],
        disparity: 0.0,
        centroid: [x, 0.0, z0 - height.unwrap_or(0.0) / 2.0],
        substrate_z: z0,
        height,
        volume: 0.0,
        contour: (0..24)
            .map(|k| {
                let a = k as f64 * std::f64::consts::TAU / 24.0;
                [x + r * a.cos(), r * a.sin(), z0]
            })
            .collect(),
        valid_share: 0.9,
        quality: schemas::CellQuality {
            trusted,
            doubt: (!trusted).then(|| "the background plane and the cell's rim disagree".into()),
            ..Default::default()
        },
    }
}

#[test]
fn an_untrusted_neighbour_is_cleared_at_the_conservative_height_and_an_untrusted_target_refused() {
    // The target (1) between two neighbours whose measured heights are low but not trusted:
    // 2 with a doubtful 4 µm, 3 with no height at all.
    let targets = schemas::Targets {
        frame: 7,
        capture_ns: 0,
        unit: "µm".into(),
        cells: vec![
            target_cell(1, 0.0, 20.0, Some(12.0), true),
            target_cell(2, -70.0, 25.0, Some(4.0), false),
            target_cell(3, 70.0, 25.0, None, false),
        ],
        substrate: None,
    };
    let conservative = 100.0;
    let scene = Scene::from_targets(&targets, conservative).unwrap();
    let base = scene.cell(1).unwrap().base;
    assert!((scene.cell(1).unwrap().top - base - 12.0).abs() < 1e-9);
    for id in [2, 3] {
        let c = scene.cell(id).unwrap();
        assert!(!c.trusted && c.doubt.is_some());
        assert!(
            (c.top - base - conservative).abs() < 1e-9,
            "cell {id}: top {}",
            c.top
        );
        assert!((c.prism.zhi - c.top).abs() < 1e-9);
    }
    // What the path is checked against: the neighbours as trusted cells 100 µm tall.
    let reference = Scene::from_targets(
        &schemas::Targets {
            cells: vec![
                target_cell(1, 0.0, 20.0, Some(12.0), true),
                target_cell(2, -70.0, 25.0, Some(conservative), true),
                target_cell(3, 70.0, 25.0, Some(conservative), true),
            ],
            ..targets.clone()
        },
        conservative,
    )
    .unwrap();
    let cfg_at = |azimuth: f64| {
        let mut cfg = config(30.0, azimuth, Entry::Side);
        cfg.workspace.min[2] = base;
        cfg.workspace.max[2] = base + 400.0;
        cfg
    };
    // Along x the pipette's axis passes over a neighbour 35–60 µm up: clear of a 4 µm cell,
    // not of one standing at the conservative height, so the target is walled in.
    for (azimuth, neighbour) in [(180.0, 2), (0.0, 3)] {
        let e = plan_approach(&scene, &cfg_at(azimuth), [0.0, 150.0, base + 150.0], 1).unwrap_err();
        assert!(
            e.blocking.contains(&neighbour),
            "{}: {:?}",
            e.reason,
            e.blocking
        );
    }
    // Along y the axis is free; starting beyond a neighbour below its conservative top,
    // every leg keeps the clearance from both as if they were 100 µm tall.
    let mut planned = 0;
    for (azimuth, sx) in [(90.0, -160.0), (270.0, 160.0)] {
        let cfg = cfg_at(azimuth);
        let start = [sx, 0.0, base + 30.0];
        assert!(sampled_clearance(&scene, &cfg, start, start, None, 0.5) >= cfg.clearance);
        let plan = plan_approach(&scene, &cfg, start, 1).unwrap();
        planned += 1;
        for w in plan.waypoints.windows(2) {
            let d = sampled_clearance(&reference, &cfg, w[0], w[1], Some(1), 0.5);
            assert!(
                d >= cfg.clearance - 1e-6,
                "leg {w:?} within {d} µm of a neighbour"
            );
        }
        // An untrusted cell is never a target, whatever the path.
        for id in [2, 3] {
            let e = plan_approach(&scene, &cfg, [0.0, 150.0, base + 150.0], id).unwrap_err();
            assert!(e.reason.contains("no trusted height"), "{}", e.reason);
            assert_eq!(e.blocking, vec![id]);
        }
    }
    assert_eq!(planned, 2);
}
