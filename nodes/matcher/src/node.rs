//! The match nodes: a stereo frame (and its cells) in; disparity tiles out.
//!
//! - `match` computes both directions in one pass (both matchers share their cost slab
//!   or volume between the directions) and sends the left-based tiles on `left` and the
//!   right-based ones on `right`;
//! - `match-lr` and `match-rl` send one direction each: the paper's shape, two processes;
//!   each computes the whole cost slab or volume, so together they cost about twice one
//!   `match` (README, "Process graph").
//!
//! `region = "cells"` (the default, the method's way) pairs the cells of both views and
//! matches each pair's crop: both boxes, `margin` pixels around them and room for the
//! range. `region = "frame"` matches the whole frame as one tile (ordinary stereo pairs).

use crate::{Directions, InputError, Mode, PaperParams, QualityParams, QualityWorkspace, Weights};
use cells::{DEFAULT_MARGIN, PAIRING_SLACK, crop, crop_of, pair_cells};
use node_api::{NodeError, Params, Stamp, Task};
use rayon::prelude::*;
use schemas::{
    CellLists, DisparityMap, DisparityRange, DisparityTile, DisparityTiles, Plane, Side,
    StereoFrame,
};
use serde::{Deserialize, Serialize};

/// What a match node matches.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Region {
    /// Each cell pair's crop (needs the `cells` input).
    #[default]
    Cells,
    /// The whole frame.
    Frame,
}

/// `params` of a match node. The matcher settings of the other mode are ignored.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MatchParams {
    /// Which matcher.
    #[serde(default)]
    pub mode: Mode,
    /// Smallest disparity searched (may be negative).
    pub min_disparity: i32,
    /// Largest disparity searched.
    pub max_disparity: i32,
    /// Cell crops or the whole frame.
    #[serde(default)]
    pub region: Region,
    /// Pixels matched around each cell (its substrate ring), cells only.
    #[serde(default = "default_margin")]
    pub margin: u8,
    /// Paper: support-value / NCC window side (odd, 3..=31).
    #[serde(default = "paper_window")]
    pub window: usize,
    /// Paper: support-value weights.
    #[serde(default = "paper_weights")]
    pub weights: Weights,
    /// Paper: top-SV candidates passed to the NCC decision (1..=16).
    #[serde(default = "paper_candidates")]
    pub candidates: usize,
    /// Paper: a pixel claimed by several keeps the best.
    #[serde(default = "paper_uniqueness")]
    pub uniqueness: bool,
    /// Paper: the ordering check.
    #[serde(default = "paper_ordering")]
    pub ordering: bool,
    /// Paper: the continuity check.
    #[serde(default = "paper_continuity")]
    pub continuity: bool,
    /// Quality: SGM paths, 4 or 8.
    #[serde(default = "quality_paths")]
    pub paths: u8,
    /// Quality: penalty for 1 px disparity changes.
    #[serde(default = "quality_p1")]
    pub p1: u16,
    /// Quality: penalty for larger jumps (lowered across intensity edges).
    #[serde(default = "quality_p2")]
    pub p2: u16,
    /// Quality: percent by which the best cost must beat other disparities (0..=99).
    #[serde(default = "quality_uniqueness_ratio")]
    pub uniqueness_ratio: u16,
    /// Quality: weight of the gradient term (0 = census only).
    #[serde(default = "quality_gradient_weight")]
    pub gradient_weight: u16,
}

fn default_margin() -> u8 {
    DEFAULT_MARGIN
}
fn paper_window() -> usize {
    PaperParams::default().window
}
fn paper_weights() -> Weights {
    PaperParams::default().weights
}
fn paper_candidates() -> usize {
    PaperParams::default().candidates
}
fn paper_uniqueness() -> bool {
    PaperParams::default().uniqueness
}
fn paper_ordering() -> bool {
    PaperParams::default().ordering
}
fn paper_continuity() -> bool {
    PaperParams::default().continuity
}
fn quality_paths() -> u8 {
    QualityParams::default().paths
}
fn quality_p1() -> u16 {
    QualityParams::default().p1
}
fn quality_p2() -> u16 {
    QualityParams::default().p2
}
fn quality_uniqueness_ratio() -> u16 {
    QualityParams::default().uniqueness_ratio
}
fn quality_gradient_weight() -> u16 {
    QualityParams::default().gradient_weight
}

impl MatchParams {
    /// The defaults of every setting over `range`.
    pub fn new(mode: Mode, range: DisparityRange, region: Region) -> Self {
        Self {
            mode,
            min_disparity: range.min,
            max_disparity: range.max,
            region,
            margin: default_margin(),
            window: paper_window(),
            weights: paper_weights(),
            candidates: paper_candidates(),
            uniqueness: paper_uniqueness(),
            ordering: paper_ordering(),
            continuity: paper_continuity(),
            paths: quality_paths(),
            p1: quality_p1(),
            p2: quality_p2(),
            uniqueness_ratio: quality_uniqueness_ratio(),
            gradient_weight: quality_gradient_weight(),
        }
    }

    /// The range searched.
    pub fn range(&self) -> DisparityRange {
        DisparityRange::new(self.min_disparity, self.max_disparity)
    }

    /// The paper matcher's settings over `range`.
    pub fn paper(&self, range: DisparityRange) -> PaperParams {
        PaperParams {
            range,
            window: self.window,
            weights: self.weights,
            candidates: self.candidates,
            uniqueness: self.uniqueness,
            ordering: self.ordering,
            continuity: self.continuity,
        }
    }

    /// The quality matcher's settings over `range`.
    pub fn quality(&self, range: DisparityRange) -> QualityParams {
        QualityParams {
            range,
            paths: self.paths,
            p1: self.p1,
            p2: self.p2,
            uniqueness_ratio: self.uniqueness_ratio,
            gradient_weight: self.gradient_weight,
            ..QualityParams::default()
        }
    }

    /// The window the input checks apply: the paper window. Quality mode has none to
    /// check: its census pads the image borders, so any image size works.
    pub fn window(&self) -> Option<usize> {
        match self.mode {
            Mode::Paper => Some(self.window),
            Mode::Quality => None,
        }
    }
}

impl Params for MatchParams {
    fn check(&self) -> Result<(), String> {
        if self.min_disparity >= self.max_disparity {
            return Err(format!(
                "disparity range {}..{} is empty: min_disparity must be below max_disparity",
                self.min_disparity, self.max_disparity
            ));
        }
        if self.window.is_multiple_of(2)
            || !(crate::sv::MIN_WINDOW..=crate::sv::MAX_WINDOW).contains(&self.window)
        {
            return Err(format!(
                "window {} is not allowed: use an odd size between {} and {}",
                self.window,
                crate::sv::MIN_WINDOW,
                crate::sv::MAX_WINDOW
            ));
        }
        if !(1..=16).contains(&self.candidates) {
            return Err(format!("candidates {} must be 1..=16", self.candidates));
        }
        if !matches!(self.paths, 4 | 8) {
            return Err(format!("paths {} must be 4 or 8", self.paths));
        }
        if self.p2 <= self.p1 {
            return Err(format!(
                "p2 ({}) must be larger than p1 ({})",
                self.p2, self.p1
            ));
        }
        if self.uniqueness_ratio > 99 {
            return Err(format!(
                "uniqueness_ratio {} must be 0..=99 (percent)",
                self.uniqueness_ratio
            ));
        }
        Ok(())
    }
}

node_api::ports! {
    /// What a match node reads.
    pub struct MatchIn {
        /// The rectified pair.
        pub frame: StereoFrame,
        /// Both views' cells (`region = "cells"`).
        pub cells: Option<CellLists>,
    }
}

node_api::ports! {
    /// What `match` sends.
    pub struct BothOut {
        /// Left-based tiles.
        pub left: DisparityTiles,
        /// Right-based tiles, same layout.
        pub right: DisparityTiles,
    }
}

node_api::ports! {
    /// What `match-lr` sends.
    pub struct LeftOut {
        /// Left-based tiles.
        pub left: DisparityTiles,
    }
}

node_api::ports! {
    /// What `match-rl` sends.
    pub struct RightOut {
        /// Right-based tiles.
        pub right: DisparityTiles,
    }
}

/// One frame's matching: the tiles of both directions (in paper mode a direction not asked
/// for is left invalid; the quality matcher always computes both).
#[derive(Debug)]
pub struct Matcher {
    /// Settings.
    pub params: MatchParams,
    /// Workspaces kept from frame to frame, one taken by each crop matched at once.
    spare: std::sync::Mutex<Vec<QualityWorkspace>>,
}

impl Matcher {
    /// A matcher with checked settings.
    pub fn new(params: MatchParams) -> Self {
        Self {
            params,
            spare: std::sync::Mutex::new(Vec::new()),
        }
    }

    /// Matches one crop pair over `range`: left- and right-based maps, evaluations.
    fn match_crop(
        &self,
        l: &Plane<u8>,
        r: &Plane<u8>,
        range: DisparityRange,
        dirs: Directions,
    ) -> (DisparityMap, DisparityMap, u64) {
        match self.params.mode {
            Mode::Paper => {
                let m = crate::match_paper(l, r, &self.params.paper(range), dirs);
                (m.left, m.right, m.evaluations)
            }
            Mode::Quality => {
                let pool = || self.spare.lock().unwrap_or_else(|e| e.into_inner());
                let mut ws = pool().pop().unwrap_or_default();
                let m = crate::match_quality_in(&mut ws, l, r, &self.params.quality(range));
                pool().push(ws);
                (m.left, m.right, m.evaluations)
            }
        }
    }

    /// Matches one frame: the left- and right-based tiles.
    pub fn run(
        &mut self,
        frame: &StereoFrame,
        cells: Option<&CellLists>,
        dirs: Directions,
    ) -> Result<(DisparityTiles, DisparityTiles), InputError> {
        let (left, right) = (&frame.left, &frame.right);
        let range = self.params.range();
        let window = self.params.window();
        crate::check_inputs(left, right, range, window)?;
        let (w, h) = (left.width, left.height);
        let Some(cells) = cells else {
            let (ml, mr, ev) = self.match_crop(left, right, range, dirs);
            return Ok((
                DisparityTiles::whole(Side::Left, range, ml, ev),
                DisparityTiles::whole(Side::Right, range, mr, ev),
            ));
        };
        let margin = self.params.margin;
        let pairs = pair_cells(&cells.left, &cells.right, range, PAIRING_SLACK);
        // The crops side by side, each matched on its own (its steps' own parallel loops
        // then run mostly on the thread that started them: one crop after another, every
        // step of every crop woke the other thread, a quarter of the node's CPU in kernel
        // context switches), collected in the pairs' order.
        let (lt, rt): (Vec<DisparityTile>, Vec<DisparityTile>) = pairs
            .par_iter()
            .map(|&(i, j)| {
                let (lc, rc) = (&cells.left[i], &cells.right[j]);
                let c = crop_of(lc, rc, range, margin, (w, h));
                let (cl, cr) = (
                    crop(left, c.x0, c.y0, c.x1, c.y1),
                    crop(right, c.x0, c.y0, c.x1, c.y1),
                );
                // A pair whose crop cannot hold a range (or the window) stays paired,
                // unmatched.
                let usable = c
                    .range
                    .filter(|r| crate::check_inputs(&cl, &cr, *r, window).is_ok());
                let (ml, mr, ev, trange) = match usable {
                    Some(r) => {
                        let (ml, mr, ev) = self.match_crop(&cl, &cr, r, dirs);
                        (ml, mr, ev, r)
                    }
                    None => (
                        Plane::filled(0, 0, 0.0),
                        Plane::filled(0, 0, 0.0),
                        0,
                        c.range.unwrap_or(range),
                    ),
                };
                let tile = |map| DisparityTile {
                    x: c.x0,
                    y: c.y0,
                    range: trange,
                    cells: Some((lc.id, rc.id)),
                    map,
                    evaluations: ev,
                    figures: None,
                };
                (tile(ml), tile(mr))
            })
            .unzip();
        let tiles = |side, tiles| DisparityTiles {
            width: w,
            height: h,
            side,
            range,
            margin,
            tiles,
        };
        Ok((tiles(Side::Left, lt), tiles(Side::Right, rt)))
    }
}

fn check_region(p: &MatchParams, connected: &[&str]) -> Result<(), String> {
    match (p.region, connected.contains(&"cells")) {
        (Region::Cells, false) => Err(
            "region = \"cells\" (the default) matches each cell pair's crop and needs the input cells = \"segment/cells\"; set region = \"frame\" to match whole frames".into(),
        ),
        (Region::Frame, true) => Err(
            "region = \"frame\" matches whole frames and reads no cells; remove the cells input or set region = \"cells\"".into(),
        ),
        _ => Ok(()),
    }
}

fn cells_of<'a>(
    p: &MatchParams,
    cells: Option<&'a CellLists>,
) -> Result<Option<&'a CellLists>, NodeError> {
    match (p.region, cells) {
        (Region::Frame, _) => Ok(None),
        (Region::Cells, Some(c)) => Ok(Some(c)),
        (Region::Cells, None) => Err(NodeError::Failed(
            "region = \"cells\" and no cells input".into(),
        )),
    }
}

/// What a match kind sends: which directions it matches and how its outputs hold them.
pub trait Directed: node_api::PortSet + 'static {
    /// The kind's name in launch files.
    const KIND: &'static str;
    /// The directions it matches.
    const DIRECTIONS: Directions;
    /// Its outputs from the left- and right-based tiles.
    fn from_tiles(left: DisparityTiles, right: DisparityTiles) -> Self;
}

impl Directed for BothOut {
    const KIND: &'static str = "match";
    const DIRECTIONS: Directions = Directions::Both;
    fn from_tiles(left: DisparityTiles, right: DisparityTiles) -> Self {
        Self { left, right }
    }
}

impl Directed for LeftOut {
    const KIND: &'static str = "match-lr";
    const DIRECTIONS: Directions = Directions::LeftToRight;
    fn from_tiles(left: DisparityTiles, _: DisparityTiles) -> Self {
        Self { left }
    }
}

impl Directed for RightOut {
    const KIND: &'static str = "match-rl";
    const DIRECTIONS: Directions = Directions::RightToLeft;
    fn from_tiles(_: DisparityTiles, right: DisparityTiles) -> Self {
        Self { right }
    }
}

/// A match node sending the directions of `O`.
#[derive(Debug)]
pub struct Matching<O> {
    /// The matcher and its settings.
    pub matcher: Matcher,
    out: std::marker::PhantomData<O>,
}

/// `match`: both directions in one pass.
pub type Match = Matching<BothOut>;
/// `match-lr`: the left-based direction only.
pub type MatchLr = Matching<LeftOut>;
/// `match-rl`: the right-based direction only.
pub type MatchRl = Matching<RightOut>;

impl<O: Directed> Task for Matching<O> {
    const KIND: &'static str = O::KIND;
    type Params = MatchParams;
    type Input = MatchIn;
    type Output = O;
    type Error = NodeError;

    fn new(params: MatchParams) -> Result<Self, NodeError> {
        Ok(Self {
            matcher: Matcher::new(params),
            out: std::marker::PhantomData,
        })
    }

    fn check_inputs(p: &MatchParams, connected: &[&str]) -> Result<(), String> {
        check_region(p, connected)
    }

    fn process(&mut self, _: Stamp, i: MatchIn) -> Result<O, NodeError> {
        let cells = cells_of(&self.matcher.params, i.cells.as_ref())?;
        let (left, right) = self
            .matcher
            .run(&i.frame, cells, O::DIRECTIONS)
            .map_err(|e| NodeError::Failed(e.to_string()))?;
        Ok(O::from_tiles(left, right))
    }
}
