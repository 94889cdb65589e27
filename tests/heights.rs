//! Heights you can trust: a matrix of generated stereo-microscope scenes under the
//! conditions a real rig shows (textureless or textured substrate anywhere in the search
//! range, tilted, unevenly lit; rounded, capped, spread and irregular cells; debris and a
//! pipette), every cell compared with its exact truth.
//!
//! Environment: `HEIGHTS_ONLY=text` runs the conditions whose name holds it,
//! `HEIGHTS_DETAIL` prints every cell, `HEIGHTS_BOUND` adds the Cramér–Rao column,
//! `HEIGHTS_SAVE=dir` writes each scene's views there as PNG (to segment or reconstruct
//! them by hand).

mod common;

use common::cell_targets;
use schemas::{Cell3, DisparityRange};
use synth::{CellSpec, Look, Optics, Pipette, Profile, Scene};

/// One condition of the matrix.
#[derive(Clone)]
struct Condition {
    name: String,
    look: Look,
    /// The substrate's disparity at the image centre, px.
    substrate: f64,
    range: DisparityRange,
    /// Tilt about each axis, degrees.
    tilt: [f64; 2],
    profile: Profile,
    irregular: f64,
    debris: usize,
    cells: usize,
    pipette: bool,
    size: (usize, usize),
    elongation: f64,
    /// The optics, where not the default's (a short working distance: strong perspective).
    optics: Option<Optics>,
    /// A condition the method does not meet yet (the cells-over-time issue's new shapes and
    /// geometry): in the table and the acceptance bars, not in the bars that must hold.
    open: bool,
}

impl Condition {
    fn new(name: &str) -> Self {
        Self {
            name: name.into(),
            look: Look::default(),
            substrate: 0.0,
            range: DisparityRange::new(-4, 12),
            tilt: [0.0; 2],
            profile: Profile::Dome,
            irregular: 0.0,
            debris: 0,
            cells: 5,
            pipette: false,
            size: (640, 480),
            elongation: 0.0,
            optics: None,
            open: false,
        }
    }

    fn scene(&self, seed: u64) -> Scene {
        let optics = Optics {
            width: self.size.0,
            height: self.size.1,
            ..self.optics.unwrap_or_default()
        };
        let spec = CellSpec {
            count: self.cells,
            profile: self.profile,
            irregular: self.irregular,
            elongation: self.elongation,
            ..CellSpec::default()
        };
        let mut s = Scene::random(optics, self.look.clone(), &spec, seed)
            .with_substrate_disparity(self.substrate)
            .with_debris(self.debris, [1.0, 4.0], seed);
        s.tilt = self.tilt.map(|d: f64| d.to_radians().tan());
        if self.pipette {
            let um = optics.um_per_px();
            s.pipette = Some(Pipette {
                tip: [-0.5 * optics.width as f64 * um + 20.0 * um, 0.0],
                height: 30.0,
                tip_radius: 1.5,
                taper: 0.08,
                elevation: 0.0,
                azimuth: 0.0,
            });
        }
        s
    }
}

/// One cell's height: relative error (None: no height reported), whether it was
/// flagged, its stated standard error relative to the true height.
type Height = (Option<f64>, bool, Option<f64>);

/// What one scene gave, cell by cell.
#[derive(Default)]
struct Outcome {
    cells: usize,
    found: usize,
    worst_centroid_px: f64,
    /// Per found cell: relative height error (None: no height reported), whether the
    /// cell was flagged, and its stated standard error relative to the true height.
    heights: Vec<Height>,
    negative: usize,
    /// With `HEIGHTS_BOUND` set, per found cell: the Cramér–Rao bound on its relative
    /// height error's standard deviation (see [`height_bound`]).
    best: Vec<f64>,
}

/// The Cramér–Rao bound on each cell's height in a scene: the smallest relative standard
/// deviation an unbiased estimator of it can have, per truth cell. The sensor noise is
/// Gaussian, σ per pixel; the unknowns are every cell's height and the substrate's plane
/// (its level and both slopes); everything else (each cell's outline, shape and texture,
/// the lighting) counts as known, so the bound is looser than the real problem. The Fisher
/// information is Σ ∂μ/∂θᵢ ∂μ/∂θⱼ / σ² over both views' noiseless pixel means μ, each
/// derivative a central difference of two renders (steps that move edges by about a
/// quarter pixel either way: the renderer's supersampling makes finer steps jump); the cells
/// do not overlap, so each pixel's height derivative is its nearest cell's. Rounding to grey
/// levels is left out (it only adds noise).
fn height_bound(
    c: &Condition,
    seed: u64,
    truth: &[synth::CellTruth],
    cal: &schemas::Calibration,
) -> Vec<f64> {
    let scene = c.scene(seed);
    let n = truth.len();
    // Steps: cell heights ±5 %; the substrate's level by a quarter pixel of disparity; the
    // slopes by as much at the image's edge.
    let eps = 0.05;
    let total = c.substrate + cal.cx_right - cal.cx;
    let ds = 0.25 * cal.baseline * cal.focal_px / (total * total);
    let half_w = 0.5 * scene.optics.width as f64 * scene.optics.um_per_px();
    let dt = ds / half_w;
    let vary = |k: usize, sign: f64| {
        let mut s = scene.clone();
        match k {
            0 => s
                .cells
                .iter_mut()
                .for_each(|c| c.height *= 1.0 + sign * eps),
            1 => s.stage += sign * ds,
            2 => s.tilt[0] += sign * dt,
            _ => s.tilt[1] += sign * dt,
        }
        s.render_means()
    };
    let steps = [eps, ds, dt, dt];
    let diffs: Vec<(schemas::Plane<f64>, schemas::Plane<f64>)> = (0..4)
        .map(|k| {
            let (lp, rp) = vary(k, 1.0);
            let (lm, rm) = vary(k, -1.0);
            let d = |p: &schemas::Plane<f64>, m: &schemas::Plane<f64>| {
                let data = p
                    .data
                    .iter()
                    .zip(&m.data)
                    .map(|(a, b)| (a - b) / (2.0 * steps[k]))
                    .collect();
                schemas::Plane::from_vec(p.width, p.height, data).expect("size")
            };
            (d(&lp, &lm), d(&rp, &rm))
        })
        .collect();
    // Fisher blocks: per cell the height's own information and its cross terms with the
    // plane, and the plane's 3×3 block (all over σ² at the end).
    let (mut own, mut cross, mut plane) = (vec![0.0f64; n], vec![[0.0f64; 3]; n], [[0.0f64; 3]; 3]);
    for (view, right) in [(0usize, false), (1, true)] {
        let pick = |k: usize| if view == 0 { &diffs[k].0 } else { &diffs[k].1 };
        let (w, h) = (pick(0).width, pick(0).height);
        for y in 0..h {
            for x in 0..w {
                let g = [
                    *pick(0).get(x, y),
                    *pick(1).get(x, y),
                    *pick(2).get(x, y),
                    *pick(3).get(x, y),
                ];
                for p in 0..3 {
                    for q in 0..3 {
                        plane[p][q] += g[p + 1] * g[q + 1];
                    }
                }
                if g[0] == 0.0 {
                    continue;
                }
                // The nearest cell, in radii, where it appears in this view.
                let near = truth
                    .iter()
                    .enumerate()
                    .map(|(k, t)| {
                        let shift = if right {
                            0.5 * (t.disparity_base_top[0] + t.disparity_base_top[1])
                        } else {
                            0.0
                        };
                        let r = (t.area_px as f64 / std::f64::consts::PI).sqrt().max(1.0);
                        let dist = (x as f64 - t.centroid_px[0] + shift)
                            .hypot(y as f64 - t.centroid_px[1]);
                        (k, dist / r)
                    })
                    .min_by(|p, q| p.1.total_cmp(&q.1));
                if let Some((k, _)) = near {
                    own[k] += g[0] * g[0];
                    for p in 0..3 {
                        cross[k][p] += g[0] * g[p + 1];
                    }
                }
            }
        }
    }
    // The plane's information less what the heights take (Schur complement), inverted.
    let mut sch = plane;
    for k in 0..n {
        if own[k] > 0.0 {
            for p in 0..3 {
                for q in 0..3 {
                    sch[p][q] -= cross[k][p] * cross[k][q] / own[k];
                }
            }
        }
    }
    let inv = invert3(sch);
    let var = c.look.noise * c.look.noise;
    (0..n)
        .map(|k| {
            if own[k] <= 0.0 {
                return f64::INFINITY;
            }
            let ck = cross[k];
            let mut quad = 0.0;
            for p in 0..3 {
                for q in 0..3 {
                    quad += ck[p] * inv.map_or(0.0, |m| m[p][q]) * ck[q];
                }
            }
            // Relative variance of the best unbiased height: [F⁻¹]ₖₖ, with the noise.
            (var * (1.0 / own[k] + quad / (own[k] * own[k]))).sqrt()
        })
        .collect()
}

/// The inverse of a 3×3 matrix (None: singular).
fn invert3(m: [[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let c = |i: usize, j: usize| {
        let (a, b) = ((i + 1) % 3, (i + 2) % 3);
        let (p, q) = ((j + 1) % 3, (j + 2) % 3);
        m[a][p] * m[b][q] - m[a][q] * m[b][p]
    };
    let det = m[0][0] * c(0, 0) + m[0][1] * c(0, 1) + m[0][2] * c(0, 2);
    if det.abs() < 1e-300 {
        return None;
    }
    // The adjugate is the transposed cofactor matrix.
    Some(std::array::from_fn(|j| {
        std::array::from_fn(|i| c(i, j) / det)
    }))
}

/// The share of heights within 5 % that estimators reaching the bounds `rel` (relative
/// standard deviations, Gaussian errors) would give, on average.
fn share_within_bound(rel: &[f64]) -> f64 {
    let p: f64 = rel
        .iter()
        .map(|&r| erf(0.05 / (r * std::f64::consts::SQRT_2)))
        .sum();
    p / rel.len().max(1) as f64
}

/// The error function (Abramowitz and Stegun 7.1.26, error below 1.5e-7).
fn erf(x: f64) -> f64 {
    let t = 1.0 / (1.0 + 0.327_591_1 * x.abs());
    let p = t
        * (0.254_829_592
            + t * (-0.284_496_736
                + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    (1.0 - p * (-x * x).exp()).copysign(x)
}

fn evaluate(c: &Condition, seed: u64) -> Outcome {
    let scene = c.scene(seed);
    let r = scene.render();
    if let Some(dir) = std::env::var_os("HEIGHTS_SAVE") {
        let dir = std::path::Path::new(&dir);
        std::fs::create_dir_all(dir).unwrap();
        for (view, p) in [("left", &r.left), ("right", &r.right)] {
            let name: String = c
                .name
                .chars()
                .filter(|ch| ch.is_ascii_alphanumeric())
                .collect();
            image::GrayImage::from_raw(p.width as u32, p.height as u32, p.data.clone())
                .unwrap()
                .save(dir.join(format!("{name}-{seed}-{view}.png")))
                .unwrap();
        }
    }
    let (targets, _) = cell_targets(&r.left, &r.right, &r.calibration, c.range);
    let mut o = Outcome {
        cells: r.cells.len(),
        ..Outcome::default()
    };
    let best = std::env::var_os("HEIGHTS_BOUND")
        .map(|_| height_bound(c, seed, &r.cells, &r.calibration))
        .unwrap_or_default();
    for (k, t) in r.cells.iter().enumerate() {
        let near = |m: &&Cell3| {
            (m.centroid_px[0] - t.centroid_px[0]).hypot(m.centroid_px[1] - t.centroid_px[1])
        };
        let Some(m) = targets
            .cells
            .iter()
            .min_by(|a, b| near(a).total_cmp(&near(b)))
        else {
            continue;
        };
        if near(&m) > 5.0 {
            continue;
        }
        o.found += 1;
        if let Some(&b) = best.get(k) {
            o.best.push(b);
        }
        o.worst_centroid_px = o.worst_centroid_px.max(near(&m));
        o.heights.push((
            m.height.map(|h| h / t.height - 1.0),
            !m.quality.trusted,
            m.quality.height_std.map(|s| s / t.height),
        ));
        if std::env::var_os("HEIGHTS_DETAIL").is_some() {
            let cal = &r.calibration;
            let base = cal.baseline * cal.focal_px / m.substrate_z - (cal.cx_right - cal.cx);
            let [tb, tt] = t.disparity_base_top;
            eprintln!(
                "      seed {seed} cell {} {:?} at ({:.0}, {:.0}) area {} (found {}, centroid off {:.2} px) true base {tb:.2} top {tt:.2} | base {:+.3} top {:+.3} | err {:?} % {:?} {:?}",
                t.id,
                t.shape.profile,
                t.centroid_px[0],
                t.centroid_px[1],
                t.area_px,
                m.area_px,
                near(&m),
                base - tb,
                m.disparity - tt,
                m.height
                    .map(|h| (1000.0 * (h / t.height - 1.0)).round() / 10.0),
                m.quality.substrate,
                m.quality.doubt
            );
        }
    }
    o.negative = targets
        .cells
        .iter()
        .filter(|m| m.height.is_some_and(|h| h < 0.0))
        .count();
    o
}

/// The matrix: every condition of a real rig, one at a time and together.
fn matrix() -> Vec<(Condition, std::ops::RangeInclusive<u64>)> {
    let mut m = Vec::new();
    let mut add = |c: Condition, seeds: std::ops::RangeInclusive<u64>| m.push((c, seeds));
    let bright = |name: &str, d: f64, range: (i32, i32)| {
        let mut c = Condition::new(name);
        c.look = Look::brightfield();
        c.substrate = d;
        c.range = DisparityRange::new(range.0, range.1);
        c
    };
    let textured = |name: &str, amp: f64, d: f64, range: (i32, i32)| {
        let mut c = Condition::new(name);
        c.look.substrate_texture = amp;
        c.substrate = d;
        c.range = DisparityRange::new(range.0, range.1);
        c
    };
    // The case: textureless, gradient and vignetting, focused above the substrate.
    add(
        bright("textureless, substrate at 8 of 0..24", 8.0, (0, 24)),
        1..=16,
    );
    add(
        bright("textureless, mid-range 16 of 0..32", 16.0, (0, 32)),
        1..=12,
    );
    add(
        bright("textureless, wide range 0..64, at 30", 30.0, (0, 64)),
        1..=8,
    );
    add(
        textured("faint texture, at 12 of 0..24", 1.0, 12.0, (0, 24)),
        1..=12,
    );
    add(
        textured("strong texture, at 20 of 0..48", 8.0, 20.0, (0, 48)),
        1..=10,
    );
    let mut t = bright("textureless, tilted 2° and 2°", 12.0, (0, 32));
    t.tilt = [2.0, 2.0];
    add(t, 1..=12);
    let mut t = textured("faint texture, tilted 2° and −2°", 1.0, 12.0, (0, 32));
    t.tilt = [2.0, -2.0];
    add(t, 1..=10);
    let mut t = textured(
        "faint texture, strong gradient and vignetting",
        1.0,
        4.0,
        (-4, 16),
    );
    t.look.gradient = 80.0;
    t.look.vignetting = 0.35;
    add(t, 1..=10);
    let mut t = bright("textureless, many cells (≈40 % of the image)", 8.0, (0, 24));
    t.cells = 60;
    add(t, 1..=4);
    let mut t = textured("faint texture, many cells", 1.0, 8.0, (0, 24));
    t.cells = 60;
    add(t, 1..=3);
    let mut t = bright("textureless, capped cells", 8.0, (0, 24));
    t.profile = Profile::Cap;
    add(t, 1..=12);
    let mut t = textured("faint texture, spread cells", 1.0, 8.0, (0, 24));
    t.profile = Profile::Spread;
    add(t, 1..=12);
    let mut t = bright("textureless, spread cells", 8.0, (0, 24));
    t.profile = Profile::Spread;
    add(t, 1..=10);
    let mut t = bright("textureless, irregular outlines", 8.0, (0, 24));
    t.irregular = 0.12;
    add(t, 1..=12);
    let mut t = textured("faint texture, irregular capped cells", 1.0, 8.0, (0, 24));
    t.irregular = 0.12;
    t.profile = Profile::Cap;
    add(t, 1..=8);
    let mut t = bright("textureless, debris and a pipette", 8.0, (0, 24));
    t.debris = 30;
    t.pipette = true;
    add(t, 1..=12);
    let mut t = textured("default look (faint texture), debris", 1.0, 0.0, (-4, 12));
    t.debris = 30;
    add(t, 1..=8);
    // A symmetric range with the substrate at −range/2 and +range/2.
    add(
        bright("textureless, at −6 of −12..12", -6.0, (-12, 12)),
        1..=10,
    );
    add(
        bright("textureless, at +6 of −12..12", 6.0, (-12, 12)),
        1..=10,
    );
    add(
        textured("faint texture, at −8 of −16..16", 1.0, -8.0, (-16, 16)),
        1..=6,
    );
    add(
        textured("faint texture, at +8 of −16..16", 1.0, 8.0, (-16, 16)),
        1..=6,
    );
    // Shapes the dome does not describe: flat-topped spread cells, fried eggs (a raised
    // nucleus on a thin cytoplasm), elongated and irregular cells.
    let open_shape = |mut c: Condition, profile: Profile| {
        c.profile = profile;
        c.open = true;
        c
    };
    for (name, profile) in [
        ("flat-topped cells", Profile::Flat),
        ("fried eggs", Profile::FriedEgg),
    ] {
        add(
            open_shape(
                bright(&format!("textureless, {name}"), 8.0, (0, 24)),
                profile,
            ),
            1..=10,
        );
        add(
            open_shape(
                textured(&format!("faint texture, {name}"), 1.0, 8.0, (0, 24)),
                profile,
            ),
            1..=8,
        );
    }
    let mut t = textured(
        "faint texture, elongated irregular cells",
        1.0,
        8.0,
        (0, 24),
    );
    t.elongation = 1.5;
    t.irregular = 0.1;
    t.open = true;
    add(t, 1..=8);
    // A short working distance (400 µm; the same 0.3 px of disparity per µm of height):
    // a 20 µm cell spans 5 % of the depth, so depth varies strongly across it.
    let mut t = textured("faint texture, strong perspective", 1.0, 8.0, (0, 24));
    t.optics = Some(Optics {
        f_eff: 2_000.0,
        baseline: 120.0,
        ..Optics::default()
    });
    t.open = true;
    add(t, 1..=8);
    let mut t = bright("textureless, strong perspective, flat-topped", 8.0, (0, 24));
    t.profile = Profile::Flat;
    t.optics = Some(Optics {
        f_eff: 2_000.0,
        baseline: 120.0,
        ..Optics::default()
    });
    t.open = true;
    add(t, 1..=6);
    // The open shapes on a large sensor: cells of the same size in µm, farther from the
    // principal point (stronger parallax at the edges).
    for (name, profile) in [
        ("1280×1024 textureless, fried eggs", Profile::FriedEgg),
        ("1280×1024 textureless, flat-topped", Profile::Flat),
    ] {
        let mut t = open_shape(bright(name, 8.0, (0, 24)), profile);
        t.size = (1280, 1024);
        t.cells = 10;
        add(t, 1..=4);
    }
    let mut t = bright("1280×1024 textureless", 8.0, (0, 24));
    t.size = (1280, 1024);
    t.cells = 10;
    add(t, 1..=6);
    let mut t = textured("1280×1024 faint texture, tilted", 1.0, 8.0, (0, 32));
    t.size = (1280, 1024);
    t.cells = 10;
    t.tilt = [1.5, -1.0];
    add(t, 1..=4);
    m
}

/// The matrix's figures: scenes, per found cell (relative height error, flagged), the worst
/// centroid error and the cells not found, with the per-condition table printed.
struct Figures {
    scenes: usize,
    /// The conditions that must hold.
    all: Vec<Height>,
    /// Every condition, the open ones too.
    every: Vec<Height>,
    /// The open conditions' cells not found and worst centroid error.
    open_missing: Vec<String>,
    open_worst: f64,
    cells: usize,
    worst_centroid: f64,
    negatives: usize,
    missing: Vec<String>,
}

fn run_matrix() -> Figures {
    let (mut scenes, mut all, mut every) = (0, Vec::new(), Vec::new());
    let (mut open_missing, mut open_worst, mut open_negatives) = (Vec::new(), 0.0f64, 0);
    let (mut worst_centroid, mut negatives, mut missing) = (0.0f64, 0, Vec::new());
    let mut total_cells = 0;
    let mut table = String::from(
        "| condition | scenes | cells | found | worst centroid px | median abs height err % | worst % | <= 5 % | flagged | unflagged > 5 % | within 2σ | best possible <= 5 % (median CRLB σ) |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    let only = std::env::var("HEIGHTS_ONLY").ok();
    let mut all_best: Vec<f64> = Vec::new();
    for (c, seeds) in matrix() {
        if only.as_ref().is_some_and(|o| !c.name.contains(o.as_str())) {
            continue;
        }
        let (mut n, mut cells, mut found, mut worst_c) = (0, 0, 0, 0.0f64);
        let mut hs: Vec<Height> = Vec::new();
        let mut best: Vec<f64> = Vec::new();
        for seed in seeds {
            let o = evaluate(&c, seed);
            n += 1;
            cells += o.cells;
            total_cells += o.cells;
            found += o.found;
            worst_c = worst_c.max(o.worst_centroid_px);
            negatives += o.negative;
            open_negatives += usize::from(c.open) * o.negative;
            if o.found != o.cells {
                let m = format!("{} seed {seed}: {}/{}", c.name, o.found, o.cells);
                if c.open {
                    open_missing.push(m);
                } else {
                    missing.push(m);
                }
            }
            for (k, h) in o.heights.iter().enumerate() {
                if !h.0.is_some_and(|e| e.abs() <= 0.05) {
                    eprintln!(
                        "    {} seed {seed} cell {k}: height error {:?} % (σ {:?} %), flagged {}",
                        c.name,
                        h.0.map(|e| (1000.0 * e).round() / 10.0),
                        h.2.map(|e| (1000.0 * e).round() / 10.0),
                        h.1
                    );
                }
            }
            hs.extend(o.heights);
            best.extend(o.best);
        }
        scenes += n;
        if c.open {
            open_worst = open_worst.max(worst_c);
        } else {
            worst_centroid = worst_centroid.max(worst_c);
        }
        let mut abs: Vec<f64> = hs
            .iter()
            .map(|h| h.0.map_or(f64::INFINITY, f64::abs))
            .collect();
        abs.sort_by(f64::total_cmp);
        let within = abs.iter().filter(|e| **e <= 0.05).count();
        let flagged = hs.iter().filter(|h| h.1).count();
        let bad = hs
            .iter()
            .filter(|h| !h.1 && !h.0.is_some_and(|e| e.abs() <= 0.05))
            .count();
        let row = format!(
            "| {} | {n} | {cells} | {found} | {worst_c:.2} | {:.1} | {:.1} | {:.1} % | {flagged} | {bad} | {:.1} % | {} |\n",
            c.name,
            100.0 * abs.get(abs.len() / 2).copied().unwrap_or(f64::NAN),
            100.0 * abs.last().copied().unwrap_or(f64::NAN),
            100.0 * within as f64 / abs.len().max(1) as f64,
            100.0 * covered(&hs, 2.0),
            if best.is_empty() {
                "–".to_string()
            } else {
                let mut b = best.clone();
                b.sort_by(f64::total_cmp);
                format!(
                    "{:.1} % ({:.2} %)",
                    100.0 * share_within_bound(&b),
                    100.0 * b[b.len() / 2]
                )
            },
        );
        all_best.extend(&best);
        eprint!("{row}");
        table += &row;
        every.extend(hs.iter().copied());
        if !c.open {
            all.extend(hs);
        }
    }
    eprintln!("{table}");
    if !all_best.is_empty() {
        eprintln!(
            "best possible share within 5 % over the matrix (Cramér–Rao): {:.2} %",
            100.0 * share_within_bound(&all_best)
        );
    }
    eprintln!(
        "open conditions: cells not found {open_missing:?}, worst centroid {open_worst:.2} px, {open_negatives} negative heights"
    );
    Figures {
        scenes,
        all,
        every,
        open_missing,
        open_worst,
        cells: total_cells,
        worst_centroid,
        negatives,
        missing,
    }
}

/// The share of cells whose true height lies within `k` stated standard errors.
fn covered(all: &[Height], k: f64) -> f64 {
    let n = all
        .iter()
        .filter(|h| matches!((h.0, h.2), (Some(e), Some(s)) if e.abs() <= k * s))
        .count();
    n as f64 / all.len().max(1) as f64
}

fn share_within(all: &[Height], bound: f64) -> f64 {
    let n = all
        .iter()
        .filter(|h| h.0.is_some_and(|e| e.abs() <= bound))
        .count();
    n as f64 / all.len().max(1) as f64
}

/// What holds today on every condition, and must keep holding: no negative height, every
/// large error flagged (the bound is 8 %, not yet the 5 %), every cell found with its
/// centroid within 1 px, and most heights within 5 % (94.9 % when this was written, 95.0 % since the top fits stop sooner).
#[test]
fn heights_are_never_negative_and_large_errors_are_flagged() {
    let f = run_matrix();
    let share = share_within(&f.all, 0.05);
    eprintln!(
        "{} scenes, {} cells, {} found: {:.1} % within 5 %, {:.1} % within 2σ, worst centroid {:.2} px; conditions that hold: {} cells, {:.1} % within 5 %, {:.1} % within 2σ",
        f.scenes,
        f.cells,
        f.every.len(),
        100.0 * share_within(&f.every, 0.05),
        100.0 * covered(&f.every, 2.0),
        f.worst_centroid.max(f.open_worst),
        f.all.len(),
        100.0 * share,
        100.0 * covered(&f.all, 2.0),
    );
    assert!(f.scenes >= 200, "{} scenes", f.scenes);
    assert_eq!(f.negatives, 0, "negative heights reported");
    assert!(f.missing.is_empty(), "cells not found: {:?}", f.missing);
    assert!(
        f.worst_centroid <= 1.0,
        "centroid error {:.2} px",
        f.worst_centroid
    );
    let unflagged: Vec<_> = f
        .all
        .iter()
        .filter(|h| !h.1 && !h.0.is_some_and(|e| e.abs() <= 0.08))
        .collect();
    assert!(
        unflagged.is_empty(),
        "heights off by more than 8 % (or missing) without a flag: {unflagged:?}"
    );
    assert!(
        share >= 0.94,
        "{:.1} % of heights within 5 %",
        100.0 * share
    );
}

/// The acceptance bars of the cells-over-time issue (46) for one pair, not all met yet: run
/// with `--ignored`. ≥ 95 % within 5 %, no trusted cell beyond 5 %, the true height within
/// 2 stated standard errors for ≥ 90 % of cells.
#[test]
#[ignore]
fn heights_meet_the_acceptance_bars() {
    let f = run_matrix();
    assert!(f.missing.is_empty(), "cells not found: {:?}", f.missing);
    assert!(
        f.open_missing.is_empty(),
        "cells not found: {:?}",
        f.open_missing
    );
    assert_eq!(f.negatives, 0, "negative heights reported");
    let share = share_within(&f.every, 0.05);
    assert!(
        share >= 0.95,
        "{:.1} % of heights within 5 %",
        100.0 * share
    );
    let unflagged = f
        .every
        .iter()
        .filter(|h| !h.1 && !h.0.is_some_and(|e| e.abs() <= 0.05))
        .count();
    assert_eq!(unflagged, 0, "heights off by more than 5 % without a flag");
    let cover = covered(&f.every, 2.0);
    assert!(cover >= 0.90, "{:.1} % within 2σ", 100.0 * cover);
    assert!(
        f.worst_centroid.max(f.open_worst) <= 1.0,
        "centroid error {} px",
        f.worst_centroid.max(f.open_worst)
    );
}

/// Tracked heights: each scene of the matrix's first `seeds` seeds per condition seen in 10
/// frames (the same cells, new sensor noise in each, as a still dish under the camera),
/// every frame's targets through the tracker, each cell's fused height after the tenth
/// frame against its truth. Prints a row per condition; returns every cell's figures and
/// the held conditions' ones.
fn run_tracked(seeds: u64) -> (Vec<Height>, Vec<Height>) {
    const FRAMES: u64 = 10;
    let (mut every, mut held) = (Vec::new(), Vec::new());
    let only = std::env::var("HEIGHTS_ONLY").ok();
    let mut table = String::from(
        "| condition (tracked, 10 frames) | cells | fused <= 5 % | single <= 5 % | fused within 2σ | fused trusted beyond 5 % |\n|---|---|---|---|---|---|\n",
    );
    for (c, range) in matrix() {
        if only.as_ref().is_some_and(|o| !c.name.contains(o.as_str())) {
            continue;
        }
        let mut hs: Vec<Height> = Vec::new();
        let mut single: Vec<Height> = Vec::new();
        for seed in range.take(seeds as usize) {
            let scene = c.scene(seed);
            let mut tracker = track::Tracker::new(track::TrackerParams::default());
            let mut last = None;
            let mut rendered = None;
            for k in 0..FRAMES {
                let mut s = scene.clone();
                s.frame = k;
                let r = s.render();
                let (mut targets, _) = cell_targets(&r.left, &r.right, &r.calibration, c.range);
                targets.frame = k;
                targets.capture_ns = 1_000_000_000 + k * 33_333_333;
                if k == 0 {
                    for t in &r.cells {
                        let m = targets.cells.iter().min_by(|a, b| {
                            let d = |m: &&Cell3| {
                                (m.centroid_px[0] - t.centroid_px[0])
                                    .hypot(m.centroid_px[1] - t.centroid_px[1])
                            };
                            d(a).total_cmp(&d(b))
                        });
                        if let Some(m) = m {
                            single.push((
                                m.height.map(|h| h / t.height - 1.0),
                                !m.quality.trusted,
                                m.quality.height_std.map(|s| s / t.height),
                            ));
                        }
                    }
                }
                last = Some(tracker.update(&targets).unwrap());
                rendered = Some(r);
            }
            let (tracks, r) = (last.unwrap(), rendered.unwrap());
            for t in &r.cells {
                let near = |tr: &&schemas::Track| {
                    tr.cell.as_ref().map_or(f64::INFINITY, |m| {
                        (m.centroid_px[0] - t.centroid_px[0])
                            .hypot(m.centroid_px[1] - t.centroid_px[1])
                    })
                };
                let Some(tr) = tracks
                    .tracks
                    .iter()
                    .filter(|tr| near(tr) <= 5.0)
                    .min_by(|a, b| near(a).total_cmp(&near(b)))
                else {
                    continue;
                };
                hs.push((
                    tr.height.map(|h| h / t.height - 1.0),
                    !tr.trusted,
                    tr.height_std.map(|s| s / t.height),
                ));
                if std::env::var_os("HEIGHTS_DETAIL").is_some() {
                    let pct = |v: Option<f64>| v.map(|v| (1000.0 * v / t.height).round() / 10.0);
                    eprintln!(
                        "      tracked seed {seed} cell {} {:?} area {}: fused {:?} % (σ {:?} %, trusted {}), frames used {}",
                        t.id,
                        t.shape.profile,
                        t.area_px,
                        pct(tr.height.map(|h| h - t.height)),
                        pct(tr.height_std),
                        tr.trusted,
                        tr.frames_used,
                    );
                }
            }
        }
        let bad = hs
            .iter()
            .filter(|h| !h.1 && !h.0.is_some_and(|e| e.abs() <= 0.05))
            .count();
        let row = format!(
            "| {} | {} | {:.1} % | {:.1} % | {:.1} % | {bad} |\n",
            c.name,
            hs.len(),
            100.0 * share_within(&hs, 0.05),
            100.0 * share_within(&single, 0.05),
            100.0 * covered(&hs, 2.0),
        );
        eprint!("{row}");
        table += &row;
        every.extend(hs.iter().copied());
        if !c.open {
            held.extend(hs);
        }
    }
    eprintln!("{table}");
    eprintln!(
        "tracked: {} cells, {:.1} % within 5 %, {:.1} % within 2σ, {} trusted beyond 5 %; conditions that hold: {:.1} % within 5 %, {:.1} % within 2σ",
        every.len(),
        100.0 * share_within(&every, 0.05),
        100.0 * covered(&every, 2.0),
        every
            .iter()
            .filter(|h| !h.1 && !h.0.is_some_and(|e| e.abs() <= 0.05))
            .count(),
        100.0 * share_within(&held, 0.05),
        100.0 * covered(&held, 2.0),
    );
    (every, held)
}

/// Fused over 10 frames, a cell's height is as good as one pair's and its stated error
/// still covers it: on the matrix's first seed of every condition.
#[test]
fn tracked_heights_over_ten_frames() {
    let (every, held) = run_tracked(1);
    assert!(every.len() >= 100, "{} cells", every.len());
    let within = share_within(&held, 0.05);
    assert!(within >= 0.94, "{:.1} % within 5 %", 100.0 * within);
    let cover = covered(&every, 2.0);
    assert!(cover >= 0.90, "{:.1} % within 2σ", 100.0 * cover);
}
