//! How well tracks follow cells whose identities are known: id switches, ids given to two
//! cells, ids reused, and how many frames a cell waits for a confirmed track (the
//! CLEAR-MOT counts a tracker is judged by).

use schemas::{TrackState, Tracks};
use std::collections::{BTreeMap, BTreeSet};

/// One true cell in one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TruthCell {
    /// Its identity.
    pub id: usize,
    /// Footprint centre `[X, Y]` in the tracks' frame and unit.
    pub centre: [f64; 2],
    /// Footprint radius (the largest), same unit.
    pub radius: f64,
    /// Whether it can be seen whole: only then is a track owed to it.
    pub visible: bool,
}

/// What [`score`] found.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TrackScore {
    /// Frames scored.
    pub frames: usize,
    /// Visible true cells summed over the frames.
    pub visible: usize,
    /// Of those, the ones a confirmed track was on.
    pub matched: usize,
    /// A cell's confirmed track changed id: `frame: cell c: id a → b`.
    pub switches: Vec<String>,
    /// One id was given to two cells: `id: cells`.
    pub shared: Vec<String>,
    /// Ids that ended and came back.
    pub reused: Vec<u32>,
    /// Visible spells whose cell waited more than the allowed frames for a confirmed track:
    /// `frame: cell c waited n`.
    pub late: Vec<String>,
    /// The longest wait for a confirmed track over every visible spell, frames.
    pub longest_wait: usize,
    /// Confirmed tracks seen on no true cell, summed over the frames (the pipette, a cell
    /// cut by the view's edge, a split).
    pub strays: usize,
    /// Distinct track ids given to true cells.
    pub ids: usize,
}

impl TrackScore {
    /// Whether nothing went wrong: no switch, no shared or reused id, no late cell.
    pub fn clean(&self) -> bool {
        self.switches.is_empty()
            && self.shared.is_empty()
            && self.reused.is_empty()
            && self.late.is_empty()
    }
}

/// Scores `runs` (the tracks of consecutive frames, in order) against `truth` (every true
/// cell of a frame). A confirmed track seen this frame is on the nearest true cell within
/// half its radius; ids are followed over the frames where a cell is visible whole. A cell
/// that becomes visible must be on a confirmed track within `wait` frames (counted in the
/// frames given).
pub fn score(runs: &[Tracks], truth: impl Fn(u64) -> Vec<TruthCell>, wait: usize) -> TrackScore {
    let mut s = TrackScore {
        frames: runs.len(),
        ..TrackScore::default()
    };
    let mut last_id: BTreeMap<usize, u32> = BTreeMap::new();
    let mut owners: BTreeMap<u32, BTreeSet<usize>> = BTreeMap::new();
    let mut ended: BTreeSet<u32> = BTreeSet::new();
    let mut live: BTreeSet<u32> = BTreeSet::new();
    // Per cell, the frame index its current visible spell began, while it waits, and
    // whether it was already counted late.
    let mut waiting: BTreeMap<usize, (usize, bool)> = BTreeMap::new();
    let mut was_visible: BTreeSet<usize> = BTreeSet::new();
    for (k, t) in runs.iter().enumerate() {
        let now: BTreeSet<u32> = t.tracks.iter().map(|tr| tr.id).collect();
        for id in &now {
            if ended.contains(id) && !s.reused.contains(id) {
                s.reused.push(*id);
            }
        }
        ended.extend(live.difference(&now));
        live = now;
        let cells = truth(t.frame);
        let seen: Vec<(u32, [f64; 2])> = t
            .tracks
            .iter()
            .filter(|tr| tr.state == TrackState::Confirmed)
            .filter_map(|tr| {
                tr.cell
                    .as_ref()
                    .map(|c| (tr.id, [c.centroid[0], c.centroid[1]]))
            })
            .collect();
        // Nearest pairs first, each track and cell used once.
        let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
        for (a, (_, p)) in seen.iter().enumerate() {
            for (b, c) in cells.iter().enumerate() {
                let d = (p[0] - c.centre[0]).hypot(p[1] - c.centre[1]);
                if d <= 0.5 * c.radius {
                    pairs.push((d, a, b));
                }
            }
        }
        pairs.sort_by(|x, y| x.0.total_cmp(&y.0));
        let (mut used_t, mut used_c) = (vec![false; seen.len()], vec![false; cells.len()]);
        let mut on: BTreeMap<usize, u32> = BTreeMap::new();
        for (_, a, b) in pairs {
            if used_t[a] || used_c[b] {
                continue;
            }
            used_t[a] = true;
            used_c[b] = true;
            on.insert(cells[b].id, seen[a].0);
        }
        s.strays += used_t
            .iter()
            .zip(&seen)
            .filter(|(u, (_, p))| {
                !**u && !cells
                    .iter()
                    .any(|c| (p[0] - c.centre[0]).hypot(p[1] - c.centre[1]) <= c.radius)
            })
            .count();
        for c in &cells {
            let id = on.get(&c.id).copied();
            // Only where the cell is seen whole: one entering the view, cut by its edge,
            // may be taken up by a new track as it comes in (its cut centroid moves as its
            // visible part grows); a change between two whole sightings is a switch, gaps
            // between them included.
            if let Some(id) = id.filter(|_| c.visible) {
                owners.entry(id).or_default().insert(c.id);
                if let Some(old) = last_id.insert(c.id, id)
                    && old != id
                {
                    s.switches
                        .push(format!("frame {}: cell {}: id {old} → {id}", t.frame, c.id));
                }
            }
            if !c.visible {
                was_visible.remove(&c.id);
                waiting.remove(&c.id);
                continue;
            }
            s.visible += 1;
            s.matched += usize::from(id.is_some());
            if was_visible.insert(c.id) {
                waiting.insert(c.id, (k, false));
            }
            if let Some(&(since, told)) = waiting.get(&c.id) {
                let waited = k - since;
                let late = waited > wait && !told;
                if late {
                    s.late.push(format!(
                        "frame {}: cell {} has waited {waited} frames",
                        t.frame, c.id
                    ));
                }
                if id.is_some() {
                    s.longest_wait = s.longest_wait.max(waited);
                    waiting.remove(&c.id);
                } else if late {
                    waiting.insert(c.id, (since, true));
                }
            }
        }
    }
    s.ids = owners.len();
    s.shared = owners
        .iter()
        .filter(|(_, cells)| cells.len() > 1)
        .map(|(id, cells)| format!("id {id}: cells {cells:?}"))
        .collect();
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use schemas::{Cell3, Track};

    fn track(id: u32, state: TrackState, at: Option<[f64; 2]>) -> Track {
        Track {
            id,
            state,
            age: 0,
            missed: 0,
            frames_used: 0,
            position: [0.0; 3],
            position_std: 0.0,
            velocity: [0.0; 3],
            height: None,
            height_std: None,
            volume: 0.0,
            volume_std: 0.0,
            trusted: false,
            cell: at.map(|p| Cell3 {
                id: 0,
                right_id: 0,
                area_px: 1,
                centroid_px: p,
                disparity: 0.0,
                centroid: [p[0], p[1], 0.0],
                substrate_z: 0.0,
                height: None,
                volume: 0.0,
                contour: Vec::new(),
                valid_share: 1.0,
                quality: schemas::CellQuality::default(),
            }),
        }
    }

    fn frame(frame: u64, tracks: Vec<Track>) -> Tracks {
        Tracks {
            frame,
            capture_ns: 0,
            unit: "um".into(),
            shift: [0.0; 3],
            tracks,
            substrate: None,
        }
    }

    fn two_cells(_: u64) -> Vec<TruthCell> {
        vec![
            TruthCell {
                id: 0,
                centre: [0.0, 0.0],
                radius: 10.0,
                visible: true,
            },
            TruthCell {
                id: 1,
                centre: [100.0, 0.0],
                radius: 10.0,
                visible: true,
            },
        ]
    }

    #[test]
    fn swapped_ids_a_late_confirmation_and_a_reused_id_are_each_counted() {
        use TrackState::{Confirmed as C, Tentative as T};
        let runs = vec![
            frame(
                0,
                vec![
                    track(1, C, Some([1.0, 0.0])),
                    track(2, T, Some([100.0, 0.0])),
                ],
            ),
            frame(
                1,
                vec![
                    track(1, C, Some([0.0, 1.0])),
                    track(2, T, Some([100.0, 0.0])),
                ],
            ),
            frame(
                2,
                vec![
                    track(1, C, Some([0.0, 0.0])),
                    track(2, C, Some([99.0, 0.0])),
                ],
            ),
            // The ids swap, and id 1 is then missing for a frame and comes back.
            frame(
                3,
                vec![
                    track(2, C, Some([0.0, 0.0])),
                    track(1, C, Some([100.0, 0.0])),
                ],
            ),
            frame(4, vec![track(2, C, Some([0.0, 0.0]))]),
            frame(
                5,
                vec![
                    track(2, C, Some([0.0, 0.0])),
                    track(1, C, Some([100.0, 0.0])),
                ],
            ),
        ];
        let s = score(&runs, two_cells, 1);
        assert_eq!(s.frames, 6);
        assert_eq!(s.visible, 12);
        assert_eq!(s.matched, 9);
        assert_eq!(
            s.switches,
            vec!["frame 3: cell 0: id 1 → 2", "frame 3: cell 1: id 2 → 1"]
        );
        assert_eq!(s.shared.len(), 2);
        assert_eq!(s.reused, vec![1]);
        assert_eq!(s.late, vec!["frame 2: cell 1 has waited 2 frames"]);
        assert_eq!(s.longest_wait, 2);
        assert!(!s.clean());
        // Far from every cell, a confirmed track is a stray; within half a radius it is on it.
        let runs = vec![frame(
            0,
            vec![
                track(1, C, Some([50.0, 0.0])),
                track(2, C, Some([4.0, 0.0])),
            ],
        )];
        let s = score(&runs, two_cells, 5);
        assert_eq!((s.strays, s.matched, s.ids), (1, 1, 1));
        assert!(s.clean());
        // A cell cut by the view's edge taken up by a new track as it comes in whole: no
        // switch; a change between two whole sightings across a gap: one.
        let entering = |f: u64| {
            vec![TruthCell {
                id: 0,
                centre: [0.0, 0.0],
                radius: 10.0,
                visible: !(1..=2).contains(&f),
            }]
        };
        let runs = vec![
            frame(1, vec![track(3, C, Some([1.0, 0.0]))]),
            frame(2, vec![track(4, C, Some([0.5, 0.0]))]),
            frame(3, vec![track(4, C, Some([0.0, 0.0]))]),
        ];
        assert!(score(&runs, entering, 5).switches.is_empty());
        let runs = vec![
            frame(0, vec![track(3, C, Some([0.0, 0.0]))]),
            frame(1, vec![track(3, C, Some([1.0, 0.0]))]),
            frame(3, vec![track(4, C, Some([0.0, 0.0]))]),
        ];
        assert_eq!(
            score(&runs, entering, 5).switches,
            vec!["frame 3: cell 0: id 3 → 4"]
        );
    }
}
