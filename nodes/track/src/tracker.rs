//! The tracker: frame by frame, each cell of the targets is given to the track of the same
//! physical cell, or starts a new one.
//!
//! Each track predicts where its cell is now (constant velocity); a stage move, which
//! shifts every cell at once, is found first as the common shift that explains the most
//! cells; then tracks and cells are paired by least total squared distance in 3D within
//! each track's gate (an optimal assignment: two cells passing close never swap ids while
//! each stays nearer its own prediction). A new cell is tentative until it has been seen
//! in `confirm_frames` frames; a confirmed cell that is not seen (covered by the pipette,
//! out of view) is kept as lost, predicted, for `keep_lost_s` seconds and gets its id back
//! when it reappears near where it should be. Ids count up and are never reused.

use crate::fuse::{Observation, change_point, fuse_heights};
use pathfinding::prelude::{Matrix, kuhn_munkres_min};
use schemas::{Cell3, Targets, Track, TrackState, Tracks};
use serde::Deserialize;
use std::collections::VecDeque;

/// How the tracker pairs cells over time (launch-file `params` of a track node).
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TrackerParams {
    /// Frames a new cell must be seen in before its track is confirmed.
    #[serde(default = "d_confirm")]
    pub confirm_frames: u32,
    /// Seconds a confirmed track is kept while its cell is not seen.
    #[serde(default = "d_keep")]
    pub keep_lost_s: f64,
    /// Least distance, µm, a cell may lie from its track's prediction and still be its.
    #[serde(default = "d_gate")]
    pub gate_um: f64,
    /// The gate as a share of the cell's footprint radius, where that is more.
    #[serde(default = "d_gate_share")]
    pub gate_share: f64,
    /// Fastest a cell moves on its own while unseen, µm/s: a lost track's gate grows by
    /// twice its own last speed plus `drift_um_s`, at most this.
    #[serde(default = "d_speed")]
    pub max_speed_um_s: f64,
    /// How fast an unseen cell that was still may have started to move, µm/s.
    #[serde(default = "d_drift")]
    pub drift_um_s: f64,
    /// Largest common shift between two frames (a stage move), µm.
    #[serde(default = "d_shift")]
    pub max_shift_um: f64,
    /// Frames whose heights are fused.
    #[serde(default = "d_window")]
    pub window: u32,
    /// Frames that must agree on a new height before the old ones are dropped (a cell
    /// pushed, injected or dividing); 0 never drops them.
    #[serde(default = "d_change")]
    pub change_frames: u32,
    /// Frames a second, for frames without capture times.
    #[serde(default = "d_fps")]
    pub fps: f64,
}

fn d_confirm() -> u32 {
    3
}
fn d_keep() -> f64 {
    3.0
}
fn d_gate() -> f64 {
    6.0
}
fn d_gate_share() -> f64 {
    0.5
}
fn d_speed() -> f64 {
    40.0
}
fn d_drift() -> f64 {
    10.0
}
fn d_shift() -> f64 {
    300.0
}
fn d_window() -> u32 {
    30
}
fn d_change() -> u32 {
    3
}
fn d_fps() -> f64 {
    30.0
}

impl Default for TrackerParams {
    fn default() -> Self {
        Self {
            confirm_frames: d_confirm(),
            keep_lost_s: d_keep(),
            gate_um: d_gate(),
            gate_share: d_gate_share(),
            max_speed_um_s: d_speed(),
            drift_um_s: d_drift(),
            max_shift_um: d_shift(),
            window: d_window(),
            change_frames: d_change(),
            fps: d_fps(),
        }
    }
}

impl TrackerParams {
    /// Why these parameters cannot work, if they cannot.
    pub fn check(&self) -> Result<(), String> {
        let pos = |v: f64, name: &str, max: f64| {
            if v.is_finite() && v > 0.0 && v <= max {
                Ok(())
            } else {
                Err(format!("{name} = {v} must be above 0 and at most {max}"))
            }
        };
        pos(self.keep_lost_s, "keep_lost_s", 3600.0)?;
        pos(self.gate_um, "gate_um", 1e4)?;
        pos(self.gate_share, "gate_share", 10.0)?;
        pos(self.max_speed_um_s, "max_speed_um_s", 1e5)?;
        pos(self.drift_um_s, "drift_um_s", 1e5)?;
        pos(self.max_shift_um, "max_shift_um", 1e5)?;
        pos(self.fps, "fps", 10000.0)?;
        if !(1..=100).contains(&self.confirm_frames) {
            return Err(format!(
                "confirm_frames = {} must be 1 to 100",
                self.confirm_frames
            ));
        }
        if !(1..=10000).contains(&self.window) {
            return Err(format!("window = {} must be 1 to 10000", self.window));
        }
        if self.change_frames >= self.window {
            return Err(format!(
                "change_frames = {} must be less than window = {}",
                self.change_frames, self.window
            ));
        }
        Ok(())
    }
}

/// Position gain of the α-β filter: how much of a frame's surprise is believed.
const ALPHA: f64 = 0.7;
/// Velocity gain of the α-β filter.
const BETA: f64 = 0.15;
/// A lost track's velocity kept per [`LOST_DAMPING_STEP_S`]: an unseen cell is not assumed
/// to drift on.
const LOST_DAMPING: f64 = 0.9;
/// The time over which a lost track keeps [`LOST_DAMPING`] of its velocity: a frame at
/// 30 frames a second.
const LOST_DAMPING_STEP_S: f64 = 1.0 / 30.0;
/// Weight of the depth in the pairing distance: a centroid's Z is the noisiest axis.
const Z_WEIGHT: f64 = 0.25;
/// Frames a tentative track may miss before it is dropped as noise.
const TENTATIVE_MISSES: u32 = 1;
/// The change of a cell's footprint radius between frames beyond which it counts as cut.
const CUT_SHARE: f64 = 0.1;

/// Micrometres per unit of a targets' unit symbol.
pub fn um_per_unit(unit: &str) -> Result<f64, String> {
    Ok(match unit {
        "um" | "µm" => 1.0,
        "mm" => 1e3,
        "m" => 1e6,
        other => {
            return Err(format!(
                "unknown length unit '{other}' in the targets (µm, mm or m)"
            ));
        }
    })
}

/// One track as the tracker keeps it.
#[derive(Clone, Debug)]
struct Live {
    id: u32,
    state: TrackState,
    age: u32,
    hits: u32,
    missed: u32,
    /// Seconds since it was last seen.
    unseen_s: f64,
    pos: [f64; 3],
    vel: [f64; 3],
    /// Running mean of the squared XY surprise, unit².
    surprise2: f64,
    /// Footprint radius, unit.
    radius: f64,
    /// Whether its last sighting was cut (its footprint changing fast: the view's edge, the
    /// pipette): where the whole cell is, is then known only to its radius.
    cut: bool,
    cell: Option<Cell3>,
    obs: VecDeque<Observation>,
}

/// The state of the tracker between frames: every live track.
#[derive(Clone, Debug)]
pub struct Tracker {
    params: TrackerParams,
    tracks: Vec<Live>,
    next_id: u32,
    last: Option<(u64, u64)>,
}

/// The footprint radius of a cell: from its contour's area on the substrate, else its
/// pixel area is unknown in units and half the contour's extent stands in.
fn footprint_radius(c: &Cell3) -> f64 {
    let p = &c.contour;
    if p.len() >= 3 {
        let mut a = 0.0;
        for i in 0..p.len() {
            let (u, v) = (p[i], p[(i + 1) % p.len()]);
            a += u[0] * v[1] - v[0] * u[1];
        }
        let a = a.abs() * 0.5;
        if a > 0.0 {
            return (a / std::f64::consts::PI).sqrt();
        }
    }
    0.0
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

fn xy2(d: [f64; 3]) -> f64 {
    d[0] * d[0] + d[1] * d[1]
}

impl Tracker {
    /// A tracker with no track yet; ids start at 1.
    pub fn new(params: TrackerParams) -> Self {
        Self {
            params,
            tracks: Vec::new(),
            next_id: 1,
            last: None,
        }
    }

    /// The gate of a track, in the targets' unit (`k` µm per unit).
    fn gate(&self, t: &Live, k: f64) -> f64 {
        let p = &self.params;
        let base = (p.gate_um / k).max(p.gate_share * t.radius);
        // A still cell covered by the pipette stays where it was: with every lost gate
        // growing at the fastest speed a cell has, a covered cell's track took a fragment
        // of the retracting pipette 20 µm away, and the cell a new id a frame later.
        let speed = (2.0 * xy2(t.vel).sqrt() + p.drift_um_s / k).min(p.max_speed_um_s / k);
        let grown = if t.cut && t.missed > 0 {
            // Lost while cut (leaving the view): the whole cell lies within its radius of
            // the part last seen. Grown at its speed only, the leaver's track missed it
            // coming back (its cut centroid had moved with its visible part).
            f64::INFINITY
        } else {
            base + speed * t.unseen_s
        };
        // An unseen cell is never sought further than its own radius beyond the base gate:
        // farther away lies another cell's ground.
        grown.min(base + t.radius.max(p.gate_um / k))
    }

    /// The common shift of every cell since the last frame that explains more cells than
    /// no shift does (a stage move), or zero.
    fn stage_shift(
        &self,
        preds: &[[f64; 3]],
        gates: &[f64],
        dets: &[[f64; 3]],
        k: f64,
    ) -> [f64; 3] {
        let reference: Vec<usize> = (0..self.tracks.len())
            .filter(|&i| {
                self.tracks[i].state != TrackState::Tentative && self.tracks[i].missed <= 1
            })
            .collect();
        if reference.len() < 2 || dets.len() < 2 {
            return [0.0; 3];
        }
        // How many reference tracks a shift explains (a cell within the gate of the
        // shifted prediction), their squared residuals' sum, and the residuals' median:
        // what is left of the common motion after the shift.
        let explained = |shift: [f64; 3]| -> (usize, f64, [f64; 3]) {
            let mut rs: Vec<[f64; 3]> = Vec::new();
            for &i in &reference {
                let p = add(preds[i], shift);
                let best = dets
                    .iter()
                    .map(|d| sub(*d, p))
                    .filter(|r| xy2(*r) <= gates[i] * gates[i])
                    .min_by(|a, b| xy2(*a).total_cmp(&xy2(*b)));
                rs.extend(best);
            }
            let cost = rs.iter().map(|r| xy2(*r)).sum();
            (rs.len(), cost, median3(&rs))
        };
        let (still, still_cost, still_mid) = explained([0.0; 3]);
        // Explained without a jump: the stage may still move (a smooth move starts and
        // ends slowly), and what every cell shares is its motion, not theirs: left in the
        // residuals, the tracks' velocities took it up and overshot by 5 µm a frame after
        // a 100 µm move stopped.
        let common = |n: usize, mid: [f64; 3]| {
            if n >= 2 && 2 * n >= reference.len() {
                mid
            } else {
                [0.0; 3]
            }
        };
        if still == reference.len() {
            return common(still, still_mid);
        }
        let reach = self.params.max_shift_um / k;
        let mut best: Option<(usize, f64, [f64; 3])> = None;
        for &i in &reference {
            for d in dets {
                let s = sub(*d, preds[i]);
                if xy2(s) > reach * reach {
                    continue;
                }
                let (n, cost, _) = explained(s);
                if best.is_none_or(|(bn, bc, _)| n > bn || (n == bn && cost < bc)) {
                    best = Some((n, cost, s));
                }
            }
        }
        match best {
            Some((n, cost, s))
                if (n > still || (n == still && cost < still_cost))
                    && 2 * n >= reference.len()
                    && n >= 2 =>
            {
                let (n, _, mid) = explained(s);
                add(s, common(n, mid))
            }
            _ => common(still, still_mid),
        }
    }

    /// Takes one frame's cells and says every live track.
    pub fn update(&mut self, t: &Targets) -> Result<Tracks, String> {
        let k = um_per_unit(&t.unit)?;
        let p = self.params.clone();
        let dt = match self.last {
            Some((_, ns)) if t.capture_ns > ns && ns > 0 => (t.capture_ns - ns) as f64 * 1e-9,
            Some((frame, _)) if t.frame > frame => (t.frame - frame) as f64 / p.fps,
            Some(_) => 1.0 / p.fps,
            None => 0.0,
        }
        .min(60.0);
        self.last = Some((t.frame, t.capture_ns));
        for tr in &mut self.tracks {
            tr.pos = add(tr.pos, tr.vel.map(|v| v * dt));
            tr.unseen_s += dt;
            tr.age += 1;
        }
        let cells: Vec<&Cell3> = t
            .cells
            .iter()
            .filter(|c| c.centroid.iter().all(|v| v.is_finite()))
            .collect();
        let dets: Vec<[f64; 3]> = cells.iter().map(|c| c.centroid).collect();
        let gates: Vec<f64> = self.tracks.iter().map(|tr| self.gate(tr, k)).collect();
        let preds: Vec<[f64; 3]> = self.tracks.iter().map(|tr| tr.pos).collect();
        let shift = self.stage_shift(&preds, &gates, &dets, k);
        let preds: Vec<[f64; 3]> = preds.iter().map(|q| add(*q, shift)).collect();
        let pairs = assign(&self.tracks, &preds, &gates, &dets);
        let mut matched = vec![false; dets.len()];
        let mut residuals = Vec::new();
        for (i, j) in pairs.iter().enumerate() {
            let tr = &mut self.tracks[i];
            let Some(j) = *j else { continue };
            matched[j] = true;
            let c = cells[j];
            let r = sub(dets[j], preds[i]);
            if tr.state != TrackState::Tentative {
                residuals.push(r);
            }
            let seen_dt = tr.unseen_s.max(1e-3);
            // Seen again after a gap, its prediction is stale: it is where it is seen (a
            // leaver's track, re-found 6 µm from its prediction and put 4 µm short of its
            // cell, lost it the next frame).
            tr.pos = if tr.missed > 0 {
                dets[j]
            } else {
                add(preds[i], r.map(|v| v * ALPHA))
            };
            // A cell whose footprint grew or shrank by more than CUT_SHARE since the last
            // frames is being cut (by the view's edge as it comes in, by the pipette): its
            // centroid moves with its visible part, not with it, so its speed is not taken
            // from this frame. Taken, a cell coming into view during a stage move gave its
            // track a speed it did not have, and the track overshot it when the move ended.
            let rad = footprint_radius(c);
            let cut =
                tr.radius > 0.0 && rad > 0.0 && (rad - tr.radius).abs() > CUT_SHARE * tr.radius;
            if !cut {
                if tr.hits == 1 && tr.missed == 0 {
                    // Its second sighting: the first measure of its speed.
                    tr.vel = r.map(|v| v / seen_dt);
                } else if tr.missed > 0 {
                    // Seen again after a gap: the speed it had is doubtful.
                    tr.vel = tr.vel.map(|v| v * 0.5);
                } else {
                    for (v, r) in tr.vel.iter_mut().zip(r) {
                        *v += BETA * r / seen_dt;
                    }
                }
            }
            tr.surprise2 = 0.8 * tr.surprise2 + 0.2 * xy2(r);
            tr.cut = cut;
            if rad > 0.0 {
                // A cell's footprint grows as it comes into view and never shrinks fast: a
                // smaller one is a cut (leaving the view, under the pipette), so the radius
                // that sets the gate follows a shrinking footprint slowly. Followed at the
                // same pace both ways, the leaver's gate shrank with its visible part and its
                // track missed it coming back 19 µm away.
                let follow = if rad < tr.radius { 0.05 } else { 0.3 };
                tr.radius = if tr.radius > 0.0 {
                    (1.0 - follow) * tr.radius + follow * rad
                } else {
                    rad
                };
            }
            tr.hits += 1;
            tr.missed = 0;
            tr.unseen_s = 0.0;
            tr.state = if tr.hits >= p.confirm_frames || tr.state == TrackState::Lost {
                TrackState::Confirmed
            } else {
                tr.state
            };
            if let Some(o) = observation(t.frame, c) {
                tr.obs.push_back(o);
                while tr.obs.len() > p.window as usize {
                    tr.obs.pop_front();
                }
                if let Some(at) = change_point(tr.obs.make_contiguous(), p.change_frames as usize) {
                    tr.obs.drain(..at);
                }
            }
            tr.cell = Some(c.clone());
        }
        // The common motion of the cells seen this frame moves the unseen ones too.
        let common = if residuals.len() >= 3 {
            median3(&residuals)
        } else {
            [0.0; 3]
        };
        let keep_s = p.keep_lost_s;
        for (i, j) in pairs.iter().enumerate() {
            if j.is_some() {
                continue;
            }
            let tr = &mut self.tracks[i];
            tr.pos = match (&tr.cell, tr.cut && tr.missed == 0) {
                // Lost while cut, its prediction went on at the speed it had before the cut:
                // it waits where its visible part was last seen (moved with the stage and
                // the others).
                (Some(c), true) => add(add(c.centroid, shift), common),
                _ => add(preds[i], common),
            };
            tr.missed += 1;
            // Lost while cut (leaving the view, under the pipette), its speed is the one it
            // had before the cut: where the cell went is unknown, and the gate spans it. Coasting on, a
            // leaver's track drifted 25 µm beyond where its cell was last seen and missed it
            // coming back. Otherwise the speed decays with time, not with the frames let in:
            // per frame, a loaded graph's lost tracks coasted two to four times as far.
            tr.vel = if tr.cut {
                [0.0; 3]
            } else {
                tr.vel
                    .map(|v| v * LOST_DAMPING.powf(dt / LOST_DAMPING_STEP_S))
            };
            if tr.state == TrackState::Confirmed {
                tr.state = TrackState::Lost;
            }
        }
        self.tracks.retain(|tr| match tr.state {
            TrackState::Tentative => tr.missed <= TENTATIVE_MISSES,
            TrackState::Lost => tr.unseen_s <= keep_s,
            TrackState::Confirmed => true,
        });
        for (j, c) in cells.iter().enumerate() {
            if matched[j] {
                continue;
            }
            let id = self.next_id;
            self.next_id = self
                .next_id
                .checked_add(1)
                .ok_or("the run has used every track id (2^32): restart it")?;
            let mut tr = Live {
                id,
                state: if p.confirm_frames <= 1 {
                    TrackState::Confirmed
                } else {
                    TrackState::Tentative
                },
                age: 1,
                hits: 1,
                missed: 0,
                unseen_s: 0.0,
                pos: dets[j],
                vel: [0.0; 3],
                surprise2: (p.gate_um / k / 2.0).powi(2),
                radius: footprint_radius(c),
                cut: false,
                cell: Some((*c).clone()),
                obs: VecDeque::new(),
            };
            tr.obs.extend(observation(t.frame, c));
            self.tracks.push(tr);
        }
        let tracks = self
            .tracks
            .iter_mut()
            .map(|tr| {
                let f = fuse_heights(tr.obs.make_contiguous());
                let pos_std = (tr.surprise2 * ALPHA / (2.0 - ALPHA)).sqrt();
                Track {
                    id: tr.id,
                    state: tr.state,
                    age: tr.age,
                    missed: tr.missed,
                    frames_used: f.map_or(0, |f| f.used),
                    position: tr.pos,
                    position_std: pos_std,
                    velocity: tr.vel,
                    height: f.map(|f| f.height),
                    height_std: f.map(|f| f.std),
                    volume: f
                        .map_or_else(|| tr.cell.as_ref().map_or(0.0, |c| c.volume), |f| f.volume),
                    volume_std: f.map_or(0.0, |f| f.volume_std),
                    trusted: f.is_some_and(|f| {
                        f.height > 0.0
                            && 2 * f.trusted_used >= f.used
                            && f.trusted_used > 0
                            && f.std <= 0.025 * f.height
                    }),
                    cell: if tr.missed == 0 {
                        tr.cell.clone()
                    } else {
                        None
                    },
                }
            })
            .collect();
        Ok(Tracks {
            frame: t.frame,
            capture_ns: t.capture_ns,
            unit: t.unit.clone(),
            shift: add(shift, common),
            tracks,
            substrate: t.substrate,
        })
    }
}

/// The per-axis median of `rs` (zero for none).
fn median3(rs: &[[f64; 3]]) -> [f64; 3] {
    if rs.is_empty() {
        return [0.0; 3];
    }
    let mut m = [0.0; 3];
    for (a, v) in m.iter_mut().enumerate() {
        let mut x: Vec<f64> = rs.iter().map(|r| r[a]).collect();
        x.sort_by(f64::total_cmp);
        let h = x.len() / 2;
        *v = if x.len().is_multiple_of(2) {
            0.5 * (x[h - 1] + x[h])
        } else {
            x[h]
        };
    }
    m
}

/// A frame's measurement of a cell's height, where it has one with an error.
fn observation(frame: u64, c: &Cell3) -> Option<Observation> {
    Some(Observation {
        frame,
        height: c.height?,
        std: c.quality.height_std?,
        trusted: c.quality.trusted,
        volume: c.volume,
    })
}

/// Pairs tracks with cells: the least total cost of squared 3D distances (depth weighed
/// down), each over its track's gate squared, within each track's gate; a track beyond
/// every gate, or better left unpaired, gets `None`. Confirmed tracks are preferred to
/// tentative and lost ones at equal distance. In units of each track's own gate, leaving
/// any track unpaired costs the same: in µm², a lost track with a wide gate (a pipette's
/// fragment, coasting) cost so much to leave unpaired that it took a cell 12 µm away from
/// the confirmed track 0.1 µm from it.
fn assign(
    tracks: &[Live],
    preds: &[[f64; 3]],
    gates: &[f64],
    dets: &[[f64; 3]],
) -> Vec<Option<usize>> {
    let (n, m) = (tracks.len(), dets.len());
    if n == 0 || m == 0 {
        return vec![None; n];
    }
    // Costs scaled to integers: the assignment is exact on integers and the same on every
    // machine.
    let q = |c: f64| (c * 1e6).round() as i64;
    let far = i64::MAX / ((n + m) as i64 * 4);
    let mut w = Matrix::new(n, m + n, far);
    for i in 0..n {
        let g2 = (gates[i] * gates[i]).max(1e-12);
        let penalty = if tracks[i].state == TrackState::Confirmed {
            0.0
        } else {
            0.25
        };
        for j in 0..m {
            let d = sub(dets[j], preds[i]);
            let xy = xy2(d);
            if xy <= g2 {
                w[(i, j)] = q(xy / g2 + (Z_WEIGHT * d[2] * d[2] / g2).min(1.0) + penalty);
            }
        }
        // Left unpaired: worse than any pairing within the gate.
        w[(i, m + i)] = q(2.25) + 1;
    }
    let (_, cols) = kuhn_munkres_min(&w);
    cols.into_iter()
        .enumerate()
        .map(|(i, j)| (j < m && w[(i, j)] < far).then_some(j))
        .collect()
}
