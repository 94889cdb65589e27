//! A choreographed sequence of a dish under the microscope, with each cell's identity known
//! in every frame: what a tracker is measured on.
//!
//! Over `frames` frames (30 a second): most cells drift slowly (a few µm/s, as cells in a
//! dish do), never touching; two cross each other's rows; two pass within 1.3 diameters of
//! each other; one drifts out of the view and comes back; one is covered by the pipette
//! for 10 frames (it sweeps in from the side, rests across the cell and leaves); then the
//! stage moves the whole dish by 100 µm within a second, taking some cells out of view and
//! bringing others (waiting beside the view) in. Positions are linear between key frames,
//! so the truth at any frame is exact.

use crate::{CellShape, CellSpec, Look, Optics, Pipette, Scene};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// How a tour is drawn.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TourSpec {
    /// Number of cells (at least the 6 with roles; at most 40).
    pub cells: usize,
    /// Length of the tour, frames (at least 300).
    pub frames: usize,
    /// Fastest free drift, µm per frame.
    pub drift: f64,
    /// The stage move's length, µm (along +x, within 30 frames).
    pub stage_move: f64,
}

impl Default for TourSpec {
    fn default() -> Self {
        Self {
            cells: 16,
            frames: 600,
            drift: 0.15,
            stage_move: 100.0,
        }
    }
}

/// Which cell plays which part.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Roles {
    /// Two cells whose rows cross mid-tour.
    pub crossing: [usize; 2],
    /// Two cells that pass within 1.3 diameters of each other.
    pub close: [usize; 2],
    /// The cell that leaves the view and comes back.
    pub leaver: usize,
    /// The cell the pipette covers.
    pub covered: usize,
}

/// One cell's place in one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TourCell {
    /// Its index in the tour (its true identity).
    pub cell: usize,
    /// Footprint centre `[x, y]` on the substrate, µm, in the cameras' frame.
    pub centre: [f64; 2],
    /// Its largest footprint radius, µm.
    pub reach: f64,
    /// Wholly inside the view (with a margin) and not under the pipette.
    pub visible: bool,
}

/// A cell's motion: offsets from its start at key frames, linear between them.
#[derive(Clone, Debug, PartialEq)]
struct Path(Vec<(f64, [f64; 2])>);

impl Path {
    fn linear(v: [f64; 2], frames: f64) -> Self {
        Self(vec![
            (0.0, [0.0; 2]),
            (frames, [v[0] * frames, v[1] * frames]),
        ])
    }

    fn at(&self, f: f64) -> [f64; 2] {
        let k = &self.0;
        if f <= k[0].0 {
            return k[0].1;
        }
        for w in k.windows(2) {
            let ((f0, a), (f1, b)) = (w[0], w[1]);
            if f <= f1 {
                let t = if f1 > f0 { (f - f0) / (f1 - f0) } else { 1.0 };
                return [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
            }
        }
        k[k.len() - 1].1
    }
}

/// The choreographed scene.
#[derive(Clone, Debug, PartialEq)]
pub struct Tour {
    /// The dish at frame 0.
    base: Scene,
    paths: Vec<Path>,
    /// Who plays which part.
    pub roles: Roles,
    /// Length, frames.
    pub frames: usize,
    /// First frame of the stage move and its length (µm along +x).
    stage: (f64, f64),
    /// The pipette's pass: frames it enters, rests from, leaves at, is gone by; the tip
    /// where it rests.
    pass: ([f64; 4], Pipette),
}

/// Frames the stage move takes (one second at 30 frames/s).
pub const STAGE_FRAMES: f64 = 30.0;
/// Frames the pipette rests across its cell.
pub const COVER_FRAMES: f64 = 10.0;

impl Tour {
    /// A tour of the dish `optics` sees, in `look`, drawn from `seed`.
    pub fn new(optics: Optics, look: Look, spec: &TourSpec, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x0070_7572);
        let n = spec.cells.clamp(6, 40);
        let frames = spec.frames.max(300);
        let fl = frames as f64;
        let s = optics.um_per_px();
        let (hw, hh) = (
            0.5 * optics.width as f64 * s,
            0.5 * optics.height as f64 * s,
        );
        let gap = 10.0;
        let mut cells: Vec<CellShape> = Vec::new();
        let mut paths: Vec<Path> = Vec::new();
        let shape = |rng: &mut ChaCha8Rng, c: [f64; 2], d: f64| {
            let ecc = rng.random_range(0.8..=1.0);
            CellShape {
                centre: c,
                semi_axes: [0.5 * d, 0.5 * d * ecc],
                angle: rng.random_range(0.0..std::f64::consts::PI),
                height: rng.random_range(8.0..=18.0_f64).min(0.6 * d),
                texture_offset: [rng.random_range(0.0..1e4), rng.random_range(0.0..1e4)],
                brightness: rng.random_range(-15.0..15.0),
                profile: CellSpec::default().profile,
                outline: [0.0; 6],
                nucleus: crate::centred_nucleus(),
            }
        };
        // The parts, placed in the view's inner region (left of its middle for the rows
        // that cross, below it for the close pass, at the right edge for the leaver, above
        // right for the covered one), clear of one another.
        let (ux, uy) = (hw / 320.0, hh / 240.0);
        let d = |rng: &mut ChaCha8Rng| rng.random_range(26.0..=34.0);
        // Crossing rows: 70 µm apart in x, moving in y in opposite senses.
        let travel = 200.0 * uy;
        let x0 = -170.0 * ux;
        for (k, sign) in [(0.0, 1.0), (1.0, -1.0)] {
            let c = [x0 + 70.0 * k, -sign * 0.5 * travel];
            let dd = d(&mut rng);
            cells.push(shape(&mut rng, c, dd));
            paths.push(Path::linear([0.0, sign * travel / fl], fl));
        }
        // A close pass: rows 1.3 diameters apart, moving in x in opposite senses, closest
        // at 40 % of the tour.
        let dd = d(&mut rng);
        let row = 1.3 * dd;
        let reach = 90.0 * ux;
        for (k, sign) in [(0.0, 1.0), (1.0, -1.0)] {
            let c = [60.0 * ux - sign * reach, 150.0 * uy + row * k - 0.5 * row];
            let mut cell = shape(&mut rng, c, dd);
            cell.semi_axes[1] = cell.semi_axes[0];
            cells.push(cell);
            let v = sign * reach / (0.4 * fl);
            paths.push(Path::linear([v, 0.0], fl));
        }
        // The leaver: beside the right edge; from 15 % of the tour it drifts out (1 µm a
        // frame), stays out for 10 frames and comes back.
        let dd = d(&mut rng);
        let c = [hw - 0.5 * dd - 20.0, -150.0 * uy];
        let out = 0.5 * dd + 20.0 + 0.5 * dd + 8.0;
        let t0 = 0.15 * fl;
        cells.push(shape(&mut rng, c, dd));
        paths.push(Path(vec![
            (0.0, [0.0; 2]),
            (t0, [0.0; 2]),
            (t0 + out, [out, 0.0]),
            (t0 + out + 10.0, [out, 0.0]),
            (t0 + 2.0 * out + 10.0, [0.0; 2]),
        ]));
        // The covered cell: the pipette comes in from the right along its row at 60 % of
        // the tour, rests across it and leaves.
        let dd = d(&mut rng);
        let cc = [150.0 * ux, -40.0 * uy];
        cells.push(shape(&mut rng, cc, dd));
        paths.push(Path::linear([0.0, 0.0], fl));
        let rest = 0.6 * fl;
        let pass = [
            rest - 8.0,
            rest,
            rest + COVER_FRAMES,
            rest + COVER_FRAMES + 8.0,
        ];
        let tip = Pipette {
            tip: [cc[0] - 0.5 * dd - 80.0, cc[1]],
            height: 30.0,
            tip_radius: 1.5,
            taper: 0.15,
            elevation: 0.08,
            azimuth: std::f64::consts::PI,
        };
        let roles = Roles {
            crossing: [0, 1],
            close: [2, 3],
            leaver: 4,
            covered: 5,
        };
        let stage = (0.8 * fl, spec.stage_move);
        // The rest drift freely, never within `gap` of another cell, never under the
        // pipette's pass; some wait left of the view for the stage move to bring them in.
        let step = 2.0;
        let sampled: Vec<f64> = (0..=(frames / step as usize))
            .map(|k| k as f64 * step)
            .collect();
        let reach_of = |c: &CellShape| c.semi_axes[0].max(c.semi_axes[1]);
        for _ in 0..(n * 400) {
            if cells.len() == n {
                break;
            }
            let dd = rng.random_range(24.0..=44.0);
            let beside = cells.len() % 4 == 3;
            let r = 0.5 * dd + 6.0;
            let c = if beside {
                [
                    rng.random_range(-hw - spec.stage_move + r..-hw - r),
                    rng.random_range(-hh + r..hh - r),
                ]
            } else {
                [
                    rng.random_range(-hw + r..hw - r),
                    rng.random_range(-hh + r..hh - r),
                ]
            };
            let v = [
                rng.random_range(-spec.drift..=spec.drift),
                rng.random_range(-spec.drift..=spec.drift),
            ];
            let cand = shape(&mut rng, c, dd);
            let path = Path::linear(v, fl);
            let ok = sampled.iter().all(|&f| {
                let p = add(c, path.at(f));
                // In the dish: never beyond the room the view and the stage move give.
                let inside = p[0] - r > -hw - spec.stage_move
                    && p[0] + r < hw
                    && p[1] - r > -hh
                    && p[1] + r < hh;
                let clear = cells.iter().zip(&paths).all(|(o, op)| {
                    let q = add(o.centre, op.at(f));
                    (p[0] - q[0]).hypot(p[1] - q[1]) > reach_of(&cand) + reach_of(o) + gap
                });
                // Clear of the pipette's path: its row band right of the covered cell's
                // far side, while it passes.
                let piped = f >= pass[0] - step
                    && f <= pass[3] + step
                    && (p[1] - cc[1]).abs() < r + 40.0
                    && p[0] + r > tip.tip[0] - 10.0;
                inside && clear && !piped
            });
            if ok {
                cells.push(cand);
                paths.push(path);
            }
        }
        let base = Scene::with_cells(optics, look, cells, seed);
        Self {
            base,
            paths,
            roles,
            frames,
            stage,
            pass: (pass, tip),
        }
    }

    /// The stage's offset at frame `f`, µm: a smooth move of `stage.1` µm along +x over
    /// [`STAGE_FRAMES`] frames.
    fn stage_at(&self, f: f64) -> [f64; 2] {
        let t = ((f - self.stage.0) / STAGE_FRAMES).clamp(0.0, 1.0);
        [
            self.stage.1 * 0.5 * (1.0 - (std::f64::consts::PI * t).cos()),
            0.0,
        ]
    }

    /// The pipette at frame `f`, if it is in the view then.
    fn pipette_at(&self, f: f64) -> Option<Pipette> {
        let ([enter, rest, leave, gone], tip) = self.pass;
        if f < enter || f > gone {
            return None;
        }
        let hw = 0.5 * self.base.optics.width as f64 * self.base.optics.um_per_px();
        let away = hw + 10.0;
        let t = if f < rest {
            (rest - f) / (rest - enter)
        } else if f <= leave {
            0.0
        } else {
            (f - leave) / (gone - leave)
        };
        let mut p = tip;
        p.tip[0] += t * (away - tip.tip[0]);
        Some(p)
    }

    /// The scene at frame `frame` (the tour played forwards, then backwards, and so on, so
    /// no cell ever jumps).
    pub fn at(&self, frame: u64) -> Scene {
        let f = self.tour_frame(frame);
        let mut s = self.base.clone();
        let stage = self.stage_at(f);
        for (c, p) in s.cells.iter_mut().zip(&self.paths) {
            c.centre = add(add(c.centre, p.at(f)), stage);
        }
        s.pipette = self.pipette_at(f);
        s.frame = frame;
        s
    }

    /// Where in the tour frame `frame` of an endless run falls.
    fn tour_frame(&self, frame: u64) -> f64 {
        let n = self.frames as u64 + 1;
        let period = 2 * (n - 1);
        let m = frame % period;
        (if m < n { m } else { period - m }) as f64
    }

    /// Every cell's place at frame `frame`, and whether it can be seen whole.
    pub fn truth(&self, frame: u64) -> Vec<TourCell> {
        let f = self.tour_frame(frame);
        let scene = self.at(frame);
        let o = &scene.optics;
        let s = o.um_per_px();
        let (hw, hh) = (0.5 * o.width as f64 * s, 0.5 * o.height as f64 * s);
        let margin = 4.0 * s;
        let ([enter, _, _, gone], _) = self.pass;
        scene
            .cells
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let reach = c.reach();
                let inside = c.centre[0] - reach > -hw + margin
                    && c.centre[0] + reach < hw - margin
                    && c.centre[1] - reach > -hh + margin
                    && c.centre[1] + reach < hh - margin;
                let covered = i == self.roles.covered && f >= enter && f <= gone;
                TourCell {
                    cell: i,
                    centre: c.centre,
                    reach,
                    visible: inside && !covered,
                }
            })
            .collect()
    }
}

fn add(a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    [a[0] + b[0], a[1] + b[1]]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tour_plays_every_part_and_no_two_cells_touch() {
        for seed in 0..6 {
            let t = Tour::new(
                Optics::default(),
                Look::brightfield(),
                &TourSpec::default(),
                seed,
            );
            assert_eq!(t.base.cells.len(), 16, "seed {seed}");
            let mut min_close = f64::INFINITY;
            let (mut leaver_out, mut leaver_back) = (false, false);
            let mut covered_hidden = 0;
            let mut y_order = Vec::new();
            for f in 0..=t.frames as u64 {
                let truth = t.truth(f);
                for (i, a) in truth.iter().enumerate() {
                    for b in &truth[i + 1..] {
                        let dist = (a.centre[0] - b.centre[0]).hypot(a.centre[1] - b.centre[1]);
                        assert!(
                            dist > a.reach + b.reach + 5.0,
                            "seed {seed} frame {f}: cells {} and {} touch",
                            a.cell,
                            b.cell
                        );
                    }
                }
                let [p, q] = t.roles.close.map(|i| truth[i]);
                let d = (p.centre[0] - q.centre[0]).hypot(p.centre[1] - q.centre[1]);
                min_close = min_close.min(d / (2.0 * p.reach));
                let l = truth[t.roles.leaver];
                leaver_out |= !l.visible && f > 0;
                leaver_back |= leaver_out && l.visible;
                covered_hidden += usize::from(!truth[t.roles.covered].visible);
                let [a, b] = t.roles.crossing.map(|i| truth[i].centre[1]);
                y_order.push(a < b);
            }
            assert!(min_close < 1.5, "seed {seed}: closest {min_close}");
            assert!(leaver_out && leaver_back, "seed {seed}");
            assert!((10..=40).contains(&covered_hidden), "{covered_hidden}");
            assert!(y_order.first() != y_order.last(), "rows crossed");
            // The stage moves every cell by 100 µm within 30 frames.
            let (a, b) = (t.truth(480), t.truth(510));
            for (x, y) in a.iter().zip(&b) {
                let moved = y.centre[0] - x.centre[0];
                assert!((moved - 100.0).abs() < 0.4 * 30.0, "{moved}");
            }
            // Played on, it turns back instead of jumping.
            assert_eq!(t.truth(601), t.truth(599));
        }
    }
}
