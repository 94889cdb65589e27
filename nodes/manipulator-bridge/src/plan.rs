//! The approach planner: paths for the pipette tip that keep the whole body clear of
//! every cell but the target.
//!
//! A 3-axis manipulator only translates the pipette, so its body keeps one direction: the
//! unit vector `u` from the tip back along the glass, rising at the approach angle. The
//! planner builds a path that is safe by construction, then shortens it:
//!
//! 1. **Rise** straight up to the safe height `H` (the tallest top + clearance + margin).
//!    Moving up never brings the body closer to a cell standing on the substrate, so the
//!    rise is safe when the start is.
//! 2. **Traverse** at `H`: the body rises from the tip, so all of it is above every top.
//! 3. **Descend along the pipette axis** from where the axis through the injection point
//!    reaches `H`, through the pre-injection point, into the injection point. The body then
//!    stays on that one line, which is checked against every other cell: if it is blocked,
//!    the target is walled in and there is no path.
//!
//! Smoothing replaces runs of these legs by straight shortcuts (to any later waypoint or
//! to points down the axis) where the swept body keeps the clearance from every cell, the
//! target included; it is greedy and deterministic, so the same scene gives the same path.

use crate::geom::{P3, axpy, box_dist, dist, norm, sub, swept_bounds};
use crate::scene::{Obstacle, Scene, Workspace};
use serde::{Deserialize, Serialize};

/// The pipette as the planner sees it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PipetteGeometry {
    /// Angle of the body above the horizontal, degrees (micropipettes: 20–45).
    pub elevation_deg: f64,
    /// Direction the body extends to from the tip, in the x-y plane, degrees from +x (180:
    /// the pipette comes in from −x).
    pub azimuth_deg: f64,
    /// Length of the body that counts, µm (what is farther is out of reach of the cells).
    pub length: f64,
}

impl Default for PipetteGeometry {
    fn default() -> Self {
        Self {
            elevation_deg: 30.0,
            azimuth_deg: 180.0,
            length: 400.0,
        }
    }
}

impl PipetteGeometry {
    /// Unit vector from the tip back along the body.
    pub fn axis(&self) -> P3 {
        let (e, a) = (
            self.elevation_deg.to_radians(),
            self.azimuth_deg.to_radians(),
        );
        [e.cos() * a.cos(), e.cos() * a.sin(), e.sin()]
    }

    /// Says what is wrong, if anything.
    pub fn check(&self) -> Result<(), String> {
        if !(5.0..=85.0).contains(&self.elevation_deg) {
            return Err(format!(
                "pipette elevation {}° must be within 5..85 (micropipettes come in at 20–45°)",
                self.elevation_deg
            ));
        }
        let length_ok = self.length > 0.0 && self.length <= 1e6;
        if !(length_ok && (-360.0..=360.0).contains(&self.azimuth_deg)) {
            return Err(format!(
                "pipette length {} must be within 0..1e6 µm and azimuth {}° within ±360",
                self.length, self.azimuth_deg
            ));
        }
        Ok(())
    }
}

/// Where the pipette enters its target.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Entry {
    /// At the top of the cell, above its footprint centre.
    #[default]
    Top,
    /// Through the side that faces the pipette, at half the cell's height.
    Side,
}

/// What the planner needs besides the scene.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlannerConfig {
    /// The pipette.
    #[serde(default)]
    pub pipette: PipetteGeometry,
    /// Least distance between the body and any cell but the target, µm.
    pub clearance: f64,
    /// Extra height of the traverse above the tallest cell + clearance, µm.
    pub safe_margin: f64,
    /// Distance of the pre-injection point back along the axis from the injection point.
    pub pre_distance: f64,
    /// How far past the cell's surface the tip goes, along the axis, µm.
    pub depth: f64,
    /// Least height of the tip above the substrate, µm.
    pub floor_margin: f64,
    /// Where the pipette enters.
    pub entry: Entry,
    /// Where the tip may go.
    pub workspace: Workspace,
}

impl Default for PlannerConfig {
    fn default() -> Self {
        Self {
            pipette: PipetteGeometry::default(),
            clearance: 5.0,
            safe_margin: 10.0,
            pre_distance: 20.0,
            depth: 0.0,
            floor_margin: 2.0,
            entry: Entry::Top,
            workspace: Workspace {
                min: [-1000.0, -1000.0, -4100.0],
                max: [1000.0, 1000.0, -3600.0],
            },
        }
    }
}

impl PlannerConfig {
    /// Says what is wrong, if anything.
    pub fn check(&self) -> Result<(), String> {
        self.pipette.check()?;
        self.workspace.check()?;
        for (name, v) in [
            ("clearance", self.clearance),
            ("safe_margin", self.safe_margin),
            ("pre_distance", self.pre_distance),
            ("depth", self.depth),
            ("floor_margin", self.floor_margin),
        ] {
            // Past a metre, a length is a typing error.
            if !(0.0..=1e6).contains(&v) {
                return Err(format!("{name} {v} must be within 0..1e6 µm"));
            }
        }
        Ok(())
    }
}

/// What a plan is for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", tag = "kind")]
pub enum Goal {
    /// Into a cell.
    Approach {
        /// The cell's id in the plan's frame.
        cell: u32,
    },
    /// Out of a cell along the axis, up to the safe height.
    Retract,
    /// To a point.
    Goto,
}

/// A path for the tip.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    /// What it is for.
    pub goal: Goal,
    /// The frame whose scene it was planned in.
    pub frame: u64,
    /// Tip positions, the start first.
    pub waypoints: Vec<P3>,
    /// Legs from this waypoint on run along the pipette axis into (or out of) the target,
    /// which is exempt from the clearance there.
    pub axial_from: usize,
    /// Where it ends: the injection point, the retract point or the goto point.
    pub end: P3,
    /// Path length, µm.
    pub length: f64,
    /// Least distance between the body and a cell other than the target along the whole
    /// path, µm (infinite without such cells).
    pub min_clearance: f64,
}

/// Why there is no path.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NoPath {
    /// What stands in the way and what to do.
    pub reason: String,
    /// The cells that block it.
    pub blocking: Vec<u32>,
}

impl std::fmt::Display for NoPath {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "no path: {}", self.reason)
    }
}

impl std::error::Error for NoPath {}

fn no_path(reason: String, blocking: Vec<u32>) -> NoPath {
    NoPath { reason, blocking }
}

/// The least distance between the body swept from tip `a` to tip `b` and the cells other
/// than `exempt`, with the nearest cell; cells whose boxes are farther than `limit` are
/// skipped (the result is then at least `limit`).
pub fn leg_clearance(
    scene: &Scene,
    cfg: &PlannerConfig,
    (a, b): (P3, P3),
    exempt: Option<u32>,
    limit: f64,
) -> (f64, Option<u32>) {
    let u = cfg.pipette.axis();
    let len = cfg.pipette.length;
    let sweep = swept_bounds(a, b, u, len);
    let mut best = (f64::INFINITY, None);
    let mut cells: Vec<(&Obstacle, f64)> = scene
        .cells
        .iter()
        .filter(|c| Some(c.id) != exempt)
        .map(|c| (c, box_dist(c.prism.bounds(), sweep)))
        .filter(|(_, lb)| *lb < limit)
        .collect();
    // Nearest boxes first, so the others are mostly skipped by their lower bound.
    cells.sort_by(|x, y| x.1.total_cmp(&y.1));
    for (c, lb) in cells {
        if lb >= best.0 {
            continue;
        }
        let d = c.prism.dist_swept(a, b, u, len);
        if d < best.0 {
            best = (d, Some(c.id));
        }
    }
    best
}

/// Cells closer than the clearance to the body swept from `a` to `b` (all cells but
/// `exempt`).
fn blocking(scene: &Scene, cfg: &PlannerConfig, (a, b): (P3, P3), exempt: Option<u32>) -> Vec<u32> {
    let u = cfg.pipette.axis();
    scene
        .cells
        .iter()
        .filter(|c| Some(c.id) != exempt)
        .filter(|c| c.prism.dist_swept(a, b, u, cfg.pipette.length) < cfg.clearance)
        .map(|c| c.id)
        .collect()
}

/// Whether the body swept from `a` to `b` keeps the clearance from every cell but `exempt`.
pub fn leg_clear(scene: &Scene, cfg: &PlannerConfig, leg: (P3, P3), exempt: Option<u32>) -> bool {
    // A hair of margin against rounding in the searches.
    let need = cfg.clearance + 1e-6;
    leg_clearance(scene, cfg, leg, exempt, need).0 >= need
}

/// The height every traverse runs at: all of the body is then above every cell.
pub fn safe_height(scene: &Scene, cfg: &PlannerConfig) -> Option<f64> {
    scene.max_top().map(|t| t + cfg.clearance + cfg.safe_margin)
}

/// The injection point of cell `c`.
pub fn injection_point(c: &Obstacle, cfg: &PlannerConfig) -> P3 {
    let u = cfg.pipette.axis();
    let surface = match cfg.entry {
        Entry::Top => [c.centre[0], c.centre[1], c.top],
        Entry::Side => {
            let h = norm([u[0], u[1], 0.0]);
            let dir = [u[0] / h, u[1] / h];
            let r = ray_exit(&c.prism.poly, c.centre, dir);
            let z = (c.base + 0.5 * (c.top - c.base)).max(c.base + cfg.floor_margin);
            [c.centre[0] + r * dir[0], c.centre[1] + r * dir[1], z]
        }
    };
    axpy(surface, -cfg.depth, u)
}

/// How far the ray from `o` (inside the convex polygon) along `dir` runs inside it.
fn ray_exit(poly: &[[f64; 2]], o: [f64; 2], dir: [f64; 2]) -> f64 {
    let n = poly.len();
    let mut best = 0.0f64;
    for i in 0..n {
        let (a, b) = (poly[i], poly[(i + 1) % n]);
        let e = [b[0] - a[0], b[1] - a[1]];
        let den = dir[0] * e[1] - dir[1] * e[0];
        if den.abs() < 1e-12 {
            continue;
        }
        let w = [a[0] - o[0], a[1] - o[1]];
        let t = (w[0] * e[1] - w[1] * e[0]) / den;
        let s = (w[0] * dir[1] - w[1] * dir[0]) / den;
        if t >= 0.0 && (-1e-9..=1.0 + 1e-9).contains(&s) {
            best = best.max(t);
        }
    }
    best
}

/// Checks the things every plan needs of its start: inside the workspace, above the floor,
/// clear of every cell but `exempt`.
fn check_start(
    scene: &Scene,
    cfg: &PlannerConfig,
    s: P3,
    exempt: Option<u32>,
) -> Result<(), NoPath> {
    if !cfg.workspace.contains(s) {
        return Err(no_path(
            format!(
                "the tip {} is outside the workspace; move it in with goto",
                fmt_p(s)
            ),
            vec![],
        ));
    }
    let (d, near) = leg_clearance(scene, cfg, (s, s), exempt, cfg.clearance + 1e-6);
    if d < cfg.clearance {
        let id = near.expect("a cell is near");
        return Err(no_path(
            format!(
                "the pipette is {d:.1} µm from cell {id} now, within the {} µm clearance; retract first",
                cfg.clearance
            ),
            vec![id],
        ));
    }
    Ok(())
}

/// A planner point as the user gives it: the camera frame `(X, Y, Z)`, Z the depth.
fn fmt_p(p: P3) -> String {
    let [x, y, z] = crate::geom::flip(p);
    format!("(X {x:.1}, Y {y:.1}, Z {z:.1})")
}

/// The planner's workspace as the user gives it, in the camera frame.
fn fmt_box(w: &Workspace) -> String {
    let (min, max) = (crate::geom::flip(w.min), crate::geom::flip(w.max));
    format!(
        "X {:.1}..{:.1}, Y {:.1}..{:.1}, Z {:.1}..{:.1} (camera frame, µm)",
        min[0], max[0], min[1], max[1], max[2], min[2]
    )
}

/// Checks that `p` is inside the workspace and above the floor.
fn check_reach(scene: &Scene, cfg: &PlannerConfig, p: P3, what: &str) -> Result<(), NoPath> {
    if !cfg.workspace.contains(p) {
        return Err(no_path(
            format!(
                "{what} {} is out of reach: the workspace is {}",
                fmt_p(p),
                fmt_box(&cfg.workspace)
            ),
            vec![],
        ));
    }
    if let Some(floor) = scene.substrate_at(p[0], p[1])
        && p[2] < floor + cfg.floor_margin - 1e-9
    {
        return Err(no_path(
            format!(
                "{what} {} is {:.1} µm above the substrate, less than the {} µm floor margin",
                fmt_p(p),
                p[2] - floor,
                cfg.floor_margin
            ),
            vec![],
        ));
    }
    Ok(())
}

/// Plans from tip `start` into cell `cell` of `scene`.
pub fn plan_approach(
    scene: &Scene,
    cfg: &PlannerConfig,
    start: P3,
    cell: u32,
) -> Result<Plan, NoPath> {
    let Some(target) = scene.cell(cell) else {
        let ids: Vec<String> = scene.cells.iter().map(|c| c.id.to_string()).collect();
        return Err(no_path(
            format!(
                "frame {} has no cell {cell}; its cells: {}",
                scene.frame,
                if ids.is_empty() {
                    "none".into()
                } else {
                    ids.join(", ")
                }
            ),
            vec![],
        ));
    };
    if let Some(why) = &target.doubt {
        return Err(no_path(
            format!("cell {cell} has no trusted height ({why}); the pipette is not sent to it"),
            vec![cell],
        ));
    }
    let u = cfg.pipette.axis();
    let inj = injection_point(target, cfg);
    let pre = axpy(inj, cfg.pre_distance, u);
    check_reach(scene, cfg, inj, "the injection point")?;
    check_reach(scene, cfg, pre, "the pre-injection point")?;
    check_start(scene, cfg, start, Some(cell))?;
    let h = safe_height(scene, cfg)
        .expect("the scene has the target")
        .max(pre[2]);
    let entry = axpy(inj, (h - inj[2]) / u[2], u);
    check_reach(
        scene,
        cfg,
        entry,
        "the point where the axis reaches the safe height",
    )?;
    let walls = blocking(scene, cfg, (entry, inj), Some(cell));
    if !walls.is_empty() {
        let ids: Vec<String> = walls.iter().map(u32::to_string).collect();
        return Err(no_path(
            format!(
                "cell {cell} is walled in: along the pipette axis (elevation {}°, azimuth {}°) cell(s) {} come within the {} µm clearance",
                cfg.pipette.elevation_deg,
                cfg.pipette.azimuth_deg,
                ids.join(", "),
                cfg.clearance
            ),
            walls,
        ));
    }
    // Candidate stops: rise, traverse to the axis, then down the axis in eighths.
    let mut pts = vec![start];
    if start[2] < h {
        let up = [start[0], start[1], h];
        check_reach(scene, cfg, up, "the safe height above the tip")?;
        pts.push(up);
    }
    let first_axial = pts.len();
    if dist(entry, pre) > 1e-9 {
        for k in 0..8 {
            pts.push(axpy(entry, k as f64 / 8.0, sub(pre, entry)));
        }
    }
    pts.push(pre);
    let mut plan = finish(
        scene,
        cfg,
        pts,
        first_axial,
        Some(cell),
        Goal::Approach { cell },
    );
    plan.waypoints.push(inj);
    plan.end = inj;
    plan.length += dist(pre, inj);
    plan.min_clearance = plan
        .min_clearance
        .min(leg_clearance(scene, cfg, (pre, inj), Some(cell), f64::INFINITY).0);
    Ok(plan)
}

/// Plans from tip `start` back out along the axis up to the safe height (or the
/// workspace's top), leaving cell `inside` (the cell the pipette is in, if any).
pub fn plan_retract(
    scene: &Scene,
    cfg: &PlannerConfig,
    start: P3,
    inside: Option<u32>,
) -> Result<Plan, NoPath> {
    let u = cfg.pipette.axis();
    let h = safe_height(scene, cfg)
        .unwrap_or(start[2])
        .max(start[2] + cfg.pre_distance * u[2])
        .min(cfg.workspace.max[2]);
    // As far along the axis as the height asks and the workspace allows.
    let mut t = ((h - start[2]) / u[2]).max(0.0);
    for k in 0..3 {
        if u[k] > 1e-12 {
            t = t.min((cfg.workspace.max[k] - start[k]) / u[k]);
        } else if u[k] < -1e-12 {
            t = t.min((cfg.workspace.min[k] - start[k]) / u[k]);
        }
    }
    let t = t.max(0.0);
    let end = axpy(start, t, u);
    let walls = blocking(scene, cfg, (start, end), inside);
    if !walls.is_empty() {
        let ids: Vec<String> = walls.iter().map(u32::to_string).collect();
        return Err(no_path(
            format!(
                "retracting along the axis would pass within the clearance of cell(s) {}; move with goto",
                ids.join(", ")
            ),
            walls,
        ));
    }
    let min_clearance = leg_clearance(scene, cfg, (start, end), inside, f64::INFINITY).0;
    Ok(Plan {
        goal: Goal::Retract,
        frame: scene.frame,
        waypoints: vec![start, end],
        axial_from: 0,
        end,
        length: t,
        min_clearance,
    })
}

/// Plans from tip `start` to the point `goal` (the tip must be clear of every cell there).
pub fn plan_goto(scene: &Scene, cfg: &PlannerConfig, start: P3, goal: P3) -> Result<Plan, NoPath> {
    check_reach(scene, cfg, goal, "the goal")?;
    check_start(scene, cfg, start, None)?;
    let (d, near) = leg_clearance(scene, cfg, (goal, goal), None, cfg.clearance + 1e-6);
    if d < cfg.clearance {
        return Err(no_path(
            format!(
                "at the goal {} the pipette would be {d:.1} µm from cell {}, within the {} µm clearance",
                fmt_p(goal),
                near.expect("near"),
                cfg.clearance
            ),
            near.into_iter().collect(),
        ));
    }
    let mut pts = vec![start];
    if let Some(h) = safe_height(scene, cfg) {
        let (su, gu) = (
            [start[0], start[1], h.max(start[2])],
            [goal[0], goal[1], h.max(goal[2])],
        );
        for (p, what) in [
            (su, "the safe height above the tip"),
            (gu, "the safe height above the goal"),
        ] {
            if dist(p, *pts.last().expect("start")) > 1e-9 {
                check_reach(scene, cfg, p, what)?;
                pts.push(p);
            }
        }
    }
    if dist(goal, *pts.last().expect("start")) > 1e-9 {
        pts.push(goal);
    }
    let n = pts.len();
    Ok(finish(scene, cfg, pts, n, None, Goal::Goto))
}

/// Shortcuts the safe candidate path `pts` (legs from `first_axial` on run along the axis,
/// where `target` is exempt), then measures it.
fn finish(
    scene: &Scene,
    cfg: &PlannerConfig,
    pts: Vec<P3>,
    first_axial: usize,
    target: Option<u32>,
    goal: Goal,
) -> Plan {
    let mut out = vec![pts[0]];
    let mut axial_from = usize::MAX;
    let mut i = 0;
    while i + 1 < pts.len() {
        // The farthest stop reachable in a straight line: the next one always is.
        let mut j = pts.len() - 1;
        while j > i + 1 {
            let axial = i >= first_axial;
            let exempt = if axial { target } else { None };
            if leg_clear(scene, cfg, (pts[i], pts[j]), exempt) {
                break;
            }
            j -= 1;
        }
        if i >= first_axial && axial_from == usize::MAX {
            axial_from = out.len() - 1;
        }
        out.push(pts[j]);
        i = j;
    }
    if axial_from == usize::MAX {
        axial_from = out.len() - 1;
    }
    let length = out.windows(2).map(|w| dist(w[0], w[1])).sum();
    let min_clearance = out
        .windows(2)
        .map(|w| leg_clearance(scene, cfg, (w[0], w[1]), target, f64::INFINITY).0)
        .fold(f64::INFINITY, f64::min);
    Plan {
        goal,
        frame: scene.frame,
        end: *out.last().expect("start"),
        waypoints: out,
        axial_from,
        length,
        min_clearance,
    }
}

/// Checks the rest of `plan` from tip `at`, heading for waypoint `next`, against a new
/// scene (`target`: the plan's target in it): the cells that now block it, if any.
pub fn check_rest(
    scene: &Scene,
    cfg: &PlannerConfig,
    plan: &Plan,
    at: P3,
    next: usize,
    target: Option<u32>,
) -> Vec<u32> {
    let mut legs = vec![(
        next.saturating_sub(1),
        at,
        plan.waypoints.get(next).copied().unwrap_or(at),
    )];
    for k in next..plan.waypoints.len().saturating_sub(1) {
        legs.push((k, plan.waypoints[k], plan.waypoints[k + 1]));
    }
    let mut out = Vec::new();
    for (k, a, b) in legs {
        let exempt = if k >= plan.axial_from { target } else { None };
        for id in blocking(scene, cfg, (a, b), exempt) {
            if !out.contains(&id) {
                out.push(id);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::Prism;

    /// A round cell of radius `r` and height `h` on a substrate at height 0.
    pub(crate) fn round(id: u32, x: f64, y: f64, r: f64, h: f64) -> Obstacle {
        let poly = (0..24)
            .map(|k| {
                let a = k as f64 * std::f64::consts::TAU / 24.0;
                [x + r * a.cos(), y + r * a.sin()]
            })
            .collect();
        Obstacle {
            id,
            prism: Prism {
                poly,
                zlo: -1.0,
                zhi: h,
            },
            centre: [x, y],
            base: 0.0,
            top: h,
            trusted: true,
            doubt: None,
        }
    }

    fn cfg() -> PlannerConfig {
        PlannerConfig {
            workspace: Workspace {
                min: [-500.0, -500.0, 0.0],
                max: [500.0, 500.0, 300.0],
            },
            ..PlannerConfig::default()
        }
    }

    #[test]
    fn an_open_target_is_reached_from_the_axis() {
        let s = Scene::new(
            7,
            vec![
                round(1, 0.0, 0.0, 10.0, 12.0),
                round(2, 60.0, 0.0, 10.0, 15.0),
            ],
        );
        let c = cfg();
        let p = plan_approach(&s, &c, [-200.0, 50.0, 100.0], 1).unwrap();
        assert_eq!(p.frame, 7);
        assert_eq!(p.end, [0.0, 0.0, 12.0]);
        assert_eq!(p.waypoints[0], [-200.0, 50.0, 100.0]);
        // The start is above the safe height: straight to the axis, down the axis.
        let u = c.pipette.axis();
        let last = p.waypoints.len() - 1;
        let pre = p.waypoints[last - 1];
        assert!(dist(pre, axpy([0.0, 0.0, 12.0], 20.0, u)) < 1e-9);
        assert!(p.min_clearance >= c.clearance, "{}", p.min_clearance);
        let len: f64 = p.waypoints.windows(2).map(|w| dist(w[0], w[1])).sum();
        assert!((p.length - len).abs() < 1e-9);
        // Deterministic.
        assert_eq!(plan_approach(&s, &c, [-200.0, 50.0, 100.0], 1).unwrap(), p);
    }

    #[test]
    fn a_neighbour_on_the_axis_walls_the_target_in() {
        // The pipette comes from −x at 30°: a tall cell 25 µm to the −x side blocks it.
        let s = Scene::new(
            1,
            vec![
                round(1, 0.0, 0.0, 10.0, 12.0),
                round(2, -30.0, 0.0, 10.0, 40.0),
            ],
        );
        let e = plan_approach(&s, &cfg(), [-200.0, 50.0, 100.0], 1).unwrap_err();
        assert_eq!(e.blocking, vec![2]);
        assert!(e.reason.contains("walled in"), "{}", e.reason);
        // From +x the way is open.
        let mut c = cfg();
        c.pipette.azimuth_deg = 0.0;
        assert!(plan_approach(&s, &c, [200.0, 50.0, 100.0], 1).is_ok());
    }

    #[test]
    fn unknown_cells_unsafe_starts_and_out_of_reach_goals_are_refused() {
        let s = Scene::new(
            1,
            vec![
                round(1, 0.0, 0.0, 10.0, 12.0),
                round(2, 100.0, 0.0, 10.0, 12.0),
            ],
        );
        let c = cfg();
        let e = plan_approach(&s, &c, [-200.0, 0.0, 100.0], 9).unwrap_err();
        assert!(
            e.reason.contains("no cell 9") && e.reason.contains("1, 2"),
            "{}",
            e.reason
        );
        // Tip 2 µm above cell 2.
        let e = plan_approach(&s, &c, [100.0, 0.0, 14.0], 1).unwrap_err();
        assert_eq!(e.blocking, vec![2]);
        assert!(e.reason.contains("retract first"), "{}", e.reason);
        let e = plan_goto(&s, &c, [-200.0, 0.0, 100.0], [900.0, 0.0, 100.0]).unwrap_err();
        assert!(e.reason.contains("out of reach"), "{}", e.reason);
        let e = plan_goto(&s, &c, [-200.0, 0.0, 100.0], [-200.0, 0.0, 1.0]).unwrap_err();
        assert!(e.reason.contains("floor margin"), "{}", e.reason);
    }

    #[test]
    fn retract_leaves_along_the_axis_and_goto_rises_over_the_cells() {
        let s = Scene::new(
            1,
            vec![
                round(1, 0.0, 0.0, 10.0, 12.0),
                round(2, 100.0, 0.0, 10.0, 30.0),
            ],
        );
        let c = cfg();
        let inj = [0.0, 0.0, 12.0];
        let r = plan_retract(&s, &c, inj, Some(1)).unwrap();
        let h = 30.0 + c.clearance + c.safe_margin;
        assert!((r.end[2] - h).abs() < 1e-9);
        let u = c.pipette.axis();
        assert!(dist(r.end, axpy(inj, (h - 12.0) / u[2], u)) < 1e-9);
        // Without the exemption the start is inside cell 1's clearance.
        assert!(plan_retract(&s, &c, inj, None).is_err());
        // Over cell 2 from one side to the other: never below the safe height near it.
        let g = plan_goto(&s, &c, [60.0, 0.0, 20.0], [140.0, 0.0, 20.0]).unwrap();
        assert!(g.min_clearance >= c.clearance);
        assert_eq!(*g.waypoints.last().unwrap(), [140.0, 0.0, 20.0]);
        assert!(g.waypoints.iter().any(|p| p[2] > 30.0));
    }

    #[test]
    fn side_entry_hits_the_side_facing_the_pipette() {
        let s = Scene::new(1, vec![round(1, 0.0, 0.0, 10.0, 12.0)]);
        let mut c = cfg();
        c.entry = Entry::Side;
        let p = plan_approach(&s, &c, [-200.0, 0.0, 100.0], 1).unwrap();
        assert!(
            (p.end[0] + 10.0).abs() < 1e-9
                && p.end[1].abs() < 1e-9
                && (p.end[2] - 6.0).abs() < 1e-9,
            "{:?}",
            p.end
        );
    }

    #[test]
    fn a_cell_moving_into_the_path_is_found() {
        let s = Scene::new(1, vec![round(1, 0.0, 0.0, 10.0, 12.0)]);
        let c = cfg();
        let p = plan_approach(&s, &c, [-200.0, 0.0, 100.0], 1).unwrap();
        assert!(check_rest(&s, &c, &p, p.waypoints[0], 1, Some(1)).is_empty());
        // A tall cell arrives under the axis.
        let s2 = Scene::new(
            2,
            vec![
                round(1, 0.0, 0.0, 10.0, 12.0),
                round(5, -30.0, 0.0, 10.0, 60.0),
            ],
        );
        assert_eq!(check_rest(&s2, &c, &p, p.waypoints[0], 1, Some(1)), vec![5]);
    }
}
