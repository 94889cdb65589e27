//! `microstereo reconstruct`: one stereo pair through the method's graph (whole frame, or
//! `--cells`: only the cells), its outputs written to a folder.

use crate::error::CliError;
use crate::segmentcmd::SegmentOpts;
use calibration::file::CalibrationFile;
use clap::Args;
use formats as io;
use matcher::node::{MatchParams, Region};
use matcher::{Mode, PaperParams, QualityParams, Weights};
use pipelines::maps::{CellMaps, PairMaps, occlusion};
use pipelines::range::{RangeKind, auto_range, candidate_ranges};
use pipelines::report::{CellsReport, PairReport};
use pipelines::stereo::Stereo;
use postprocess::{Fill, PostParams};
use runtime::exec::Frame;
use schemas::{DisparityRange, LengthUnit};
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;
use triangulate::geometry::Geometry;
use validate::node::ValidateParams;

/// Arguments of `microstereo reconstruct`.
#[derive(Args, Debug)]
pub struct ReconstructArgs {
    /// Rectified left image (PNG, JPEG or TIFF).
    left: PathBuf,
    /// Rectified right image.
    right: PathBuf,
    /// Output directory (created if missing).
    #[arg(short, long)]
    output: PathBuf,
    /// Replace the outputs of an earlier run in the output directory.
    #[arg(long)]
    overwrite: bool,
    /// Matcher: `quality` (semi-global) or `paper` (support value + NCC).
    #[arg(long, value_enum, default_value = "quality")]
    mode: Mode,
    /// Smallest disparity searched (may be negative).
    #[arg(long, allow_hyphen_values = true, requires = "max_disparity")]
    min_disparity: Option<i32>,
    /// Largest disparity searched.
    #[arg(
        long,
        allow_hyphen_values = true,
        requires = "min_disparity",
        conflicts_with = "auto_range"
    )]
    max_disparity: Option<i32>,
    /// Pick the range with the highest LR consistency among `--range-radii`.
    #[arg(long)]
    auto_range: bool,
    /// Radii tried by `--auto-range`.
    #[arg(long, value_delimiter = ',', default_value = "4,8,12,16,24,32,48,64")]
    range_radii: Vec<u32>,
    /// `symmetric` tries −r..r (convergent microscope), `positive` tries 0..r.
    #[arg(long, value_enum, default_value = "symmetric")]
    range_kind: RangeKind,
    /// Support-value / NCC window side (paper mode; odd, 3..31).
    #[arg(long, default_value_t = PaperParams::default().window)]
    window: usize,
    /// Support-value weights (paper mode).
    #[arg(long, value_enum, default_value = "equal")]
    weights: Weights,
    /// Top-SV candidates passed to the NCC decision (paper mode).
    #[arg(long, default_value_t = PaperParams::default().candidates)]
    candidates: usize,
    /// Enable the uniqueness constraint (paper mode): a pixel claimed by several keeps the best.
    #[arg(long)]
    uniqueness: bool,
    /// Enable the ordering check (paper mode).
    #[arg(long)]
    ordering: bool,
    /// Enable the continuity check (paper mode).
    #[arg(long)]
    continuity: bool,
    /// SGM penalty for 1 px disparity changes (quality mode).
    #[arg(long, default_value_t = QualityParams::default().p1)]
    p1: u16,
    /// SGM penalty for larger jumps, lowered across intensity edges (quality mode).
    #[arg(long, default_value_t = QualityParams::default().p2)]
    p2: u16,
    /// Percent by which the best cost must beat other disparities (quality mode).
    #[arg(long, default_value_t = QualityParams::default().uniqueness_ratio)]
    uniqueness_ratio: u16,
    /// Weight of the gradient term in the cost (quality mode; 0 = census only).
    #[arg(long, default_value_t = QualityParams::default().gradient_weight)]
    gradient_weight: u16,
    /// SGM paths: 4 or 8 (quality mode).
    #[arg(long, default_value_t = QualityParams::default().paths,
          value_parser = clap::builder::TypedValueParser::map(clap::builder::PossibleValuesParser::new(["4", "8"]), |s: String| s.parse::<u8>().expect("4 or 8")))]
    paths: u8,
    /// LR consistency tolerance in pixels (0..4).
    #[arg(long, default_value_t = ValidateParams::default().tolerance)]
    lr_tolerance: u32,
    /// Valid regions smaller than this are removed (default: 50 paper, 100 quality).
    #[arg(long)]
    min_region: Option<usize>,
    /// Median radius over valid pixels (0 = off, 2 = 5×5).
    #[arg(long, default_value_t = PostParams::default().median_radius)]
    median: usize,
    /// How invalid pixels are filled.
    #[arg(long, value_enum, default_value = "background")]
    fill: Fill,
    /// Baseline for triangulation (in `--unit`, which it requires).
    #[arg(
        long,
        requires_all = ["focal", "unit"],
        conflicts_with = "calibration",
        allow_hyphen_values = true
    )]
    baseline: Option<f64>,
    /// Focal length in pixels.
    #[arg(long, requires = "baseline", allow_hyphen_values = true)]
    focal: Option<f64>,
    /// Principal point column (default: image centre).
    #[arg(long, allow_hyphen_values = true)]
    cx: Option<f64>,
    /// Principal point row (default: image centre).
    #[arg(long, allow_hyphen_values = true)]
    cy: Option<f64>,
    /// Right principal point column (default: `--cx`).
    #[arg(long, allow_hyphen_values = true)]
    cx_right: Option<f64>,
    /// Unit of `--baseline`, and so of every length written and printed (µm for a
    /// microscope: `um`). Required with `--baseline`: no unit is assumed.
    #[arg(long, value_enum, requires = "baseline")]
    unit: Option<LengthUnit>,
    /// Calibration file (TOML or JSON): baseline, focal_px or f_eff + pixel_pitch, cx, cy,
    /// unit; with a `[stereo]` table (`calibrate-stereo` writes one) the pair is taken as
    /// raw and rectified first.
    #[arg(long)]
    calibration: Option<PathBuf>,
    /// The pair is already rectified: do not rectify it with the calibration's `[stereo]`
    /// cameras.
    #[arg(long, requires = "calibration")]
    rectified: bool,
    /// Segment both views and match only the cells (plus `--cell-margin`); writes cells.json.
    #[arg(long)]
    cells: bool,
    /// Pixels around each cell that are matched too: the substrate ring for its height.
    #[arg(long, default_value_t = cells::DEFAULT_MARGIN)]
    cell_margin: u8,
    #[command(flatten)]
    seg: SegmentOpts,
}

/// The flags of the parameters they set, for errors.
const FLAGS: &[(&str, &str)] = &[
    ("min_disparity", "--min-disparity"),
    ("max_disparity", "--max-disparity"),
    ("window", "--window"),
    ("candidates", "--candidates"),
    ("paths", "--paths"),
    ("p1", "--p1"),
    ("p2", "--p2"),
    ("uniqueness_ratio", "--uniqueness-ratio"),
    ("gradient_weight", "--gradient-weight"),
    ("tolerance", "--lr-tolerance"),
    ("min_region", "--min-region"),
    ("median_radius", "--median"),
    ("margin", "--cell-margin"),
];

impl ReconstructArgs {
    /// The graph its flags describe over `range`.
    fn preset(&self, range: DisparityRange) -> Result<Stereo, CliError> {
        let mode = self.mode;
        let matching = MatchParams {
            window: self.window,
            weights: self.weights,
            candidates: self.candidates,
            uniqueness: self.uniqueness,
            ordering: self.ordering,
            continuity: self.continuity,
            paths: self.paths,
            p1: self.p1,
            p2: self.p2,
            uniqueness_ratio: self.uniqueness_ratio,
            gradient_weight: self.gradient_weight,
            margin: self.cell_margin,
            ..MatchParams::new(mode, range, Region::Frame)
        };
        let mut post = pipelines::stereo::post_for(mode);
        if let Some(m) = self.min_region {
            post.min_region = m;
        }
        post.median_radius = self.median;
        post.fill = self.fill;
        Ok(Stereo {
            left: self.left.clone(),
            right: self.right.clone(),
            frames: 1,
            matching,
            validate: ValidateParams {
                tolerance: self.lr_tolerance,
            },
            post: Some(post),
            segment: self.cells.then(|| self.seg.params()),
            geometry: self.geometry(),
            rectify: self.rectify_with()?,
        })
    }

    /// The calibration file to rectify the pair with: the given one when it holds the raw
    /// cameras and `--rectified` is not given.
    fn rectify_with(&self) -> Result<Option<String>, CliError> {
        let Some(p) = self.calibration.as_ref().filter(|_| !self.rectified) else {
            return Ok(None);
        };
        let file = calibration::file::read_file(p).map_err(CliError::Other)?;
        Ok((file.stereo.is_some() || file.microscope.is_some()).then(|| p.display().to_string()))
    }

    fn geometry(&self) -> Option<Geometry> {
        match (&self.calibration, self.baseline, self.focal) {
            (Some(p), _, _) => Some(Geometry::File(p.display().to_string())),
            (None, Some(b), Some(f)) => Some(Geometry::Inline(CalibrationFile::inline(
                (b, f),
                (self.cx, self.cy, self.cx_right),
                self.unit,
            ))),
            _ => None,
        }
    }
}

/// An input under one of the output names in the output directory (a scene's true
/// `disparity.pfm`, say) would be destroyed: refused before any work.
fn refuse_inputs_as_outputs(a: &ReconstructArgs) -> Result<(), CliError> {
    let inputs = [Some(&a.left), Some(&a.right), a.calibration.as_ref()];
    let inputs: Vec<&std::path::Path> = inputs.into_iter().flatten().map(|p| p.as_path()).collect();
    formats::outputs::check(
        &formats::outputs::in_dir(&a.output, pipelines::report::OUTPUT_NAMES),
        &inputs,
        a.overwrite,
        "give -o another directory",
    )?;
    Ok(())
}

/// Checks the flags that only some runs use (geometry without --cells, segmentation
/// without --cells, range radii without --auto-range) before any work: a bad value is
/// refused whether or not this run would have read it. (Flags every run uses are checked
/// with their node's parameters when the graph is built, before it runs.)
fn check_every_flag(a: &ReconstructArgs) -> Result<(), CliError> {
    for (flag, v) in [("--cx", a.cx), ("--cy", a.cy), ("--cx-right", a.cx_right)] {
        if let Some(v) = v
            && !(v.is_finite() && v.abs() <= 1e6)
        {
            return Err(CliError::Other(format!(
                "{flag} ({v}) must be a finite pixel column or row (within ±1e6)"
            )));
        }
    }
    if let Some(r) = a.range_radii.iter().find(|r| !(1..=65_536).contains(*r)) {
        return Err(CliError::Other(format!(
            "--range-radii: {r} is out of range: use radii of 1..65536 px"
        )));
    }
    a.seg.checked().map(|_| ())
}

fn mkdir(o: &std::path::Path) -> Result<(), CliError> {
    std::fs::create_dir_all(o).map_err(|e| {
        CliError::Other(format!(
            "cannot create output directory '{}': {e}",
            o.display()
        ))
    })
}

/// Runs `microstereo reconstruct`.
pub fn reconstruct(a: ReconstructArgs) -> Result<(), CliError> {
    let t0 = Instant::now();
    check_every_flag(&a)?;
    refuse_inputs_as_outputs(&a)?;
    if a.cells {
        if a.geometry().is_none() {
            return Err(CliError::Other(
                "--cells measures cells in 3D: give --calibration FILE or --baseline and --focal"
                    .into(),
            ));
        }
        if a.auto_range {
            return Err(CliError::Other(
                "--cells takes the range from --min-disparity/--max-disparity (the cells' heights), not --auto-range".into(),
            ));
        }
    }
    let size = || -> Result<(usize, usize), CliError> {
        let l = capture::image::load(&a.left, "left image").map_err(CliError::Other)?;
        Ok((l.grey.width, l.grey.height))
    };
    let (range, curve, auto_ms) = match (a.min_disparity, a.max_disparity) {
        (Some(lo), Some(hi)) => (DisparityRange::new(lo, hi), None, None),
        _ if a.auto_range => {
            let (w, _) = size()?;
            let ranges = candidate_ranges(a.range_kind, &a.range_radii, w);
            if ranges.is_empty() {
                return Err(CliError::Other(format!(
                    "--range-radii {:?} has no radius between 1 and the image width {w}",
                    a.range_radii
                )));
            }
            let t = Instant::now();
            // Check the pair and every flag before the (possibly long) range search.
            let base = a.preset(ranges[0])?;
            base.graph().map_err(|e| CliError::with_flags(e, FLAGS))?;
            let (best, c) =
                auto_range(&base, &ranges).map_err(|e| CliError::with_flags(e, FLAGS))?;
            (best, Some(c), Some(t.elapsed().as_secs_f64() * 1e3))
        }
        _ => {
            let (w, _) = size()?;
            (
                DisparityRange::new(0, 64.min(w as i32 / 2).max(1)),
                None,
                None,
            )
        }
    };
    let preset = a.preset(range)?;
    let f = preset
        .run_once()
        .map_err(|e| CliError::with_flags(e, FLAGS))?;
    let mut times = serde_json::Map::new();
    if let Some(ms) = auto_ms {
        times.insert("auto_range".into(), serde_json::json!(round3(ms)));
    }
    for (k, v) in &f.ms {
        times.insert(k.clone(), serde_json::json!(round3(*v)));
    }
    if a.cells {
        return write_cells(&a, &preset, &f, times, t0);
    }
    let PairMaps {
        checked,
        raw,
        raw_right,
        disparity,
        cloud,
    } = preset.pair_maps(&f)?;
    let unit = cloud
        .as_ref()
        .map(|(_, t)| pipelines::report::unit_of(&t.unit));
    // Everything computed: only now touch the output directory.
    let o = &a.output;
    mkdir(o)?;
    let tw = Instant::now();
    io::write_pfm(&o.join("disparity.pfm"), &disparity)?;
    io::write_pfm(&o.join("disparity_raw.pfm"), &raw)?;
    let lost = io::write_disparity_png(&o.join("disparity.png"), &disparity)?;
    if lost > 0 {
        runtime::errln!(
            "warning: {lost} pixels have disparities disparity.png cannot hold (below 1/512 px, where 0 already means unknown, or ≥ 256); disparity.pfm has them"
        );
    }
    io::write_color_png(
        &o.join("disparity_color.png"),
        &io::disparity_color(&disparity, range.min as f32, range.max as f32),
    )?;
    io::write_mask_png(&o.join("occlusion_left.png"), &occlusion(&raw))?;
    io::write_mask_png(&o.join("occlusion_right.png"), &occlusion(&raw_right))?;
    if let (Some((c, _)), Some(u)) = (&cloud, unit) {
        io::write_ply(&o.join("points.ply"), c, u)?;
    }
    times.insert(
        "write".into(),
        serde_json::json!(round3(tw.elapsed().as_secs_f64() * 1e3)),
    );
    let report = PairReport::new(
        &preset,
        (&checked, &raw, &disparity),
        cloud.as_ref().map(|(c, t)| (c, t)),
        (range, curve),
        times,
    );
    if let Some(c) = &report.auto_range_curve {
        let chart = pipelines::html::range_curve(c, range);
        io::write_color_png(&o.join("range_curve.png"), &chart)?;
    }
    let figures = report.validation;
    let total_ms = report.total_ms;
    write_json(&o.join("report.json"), &report)?;
    let page = pipelines::html::pair_page(o, &report, &figures, cloud.as_ref().map(|c| &c.0));
    io::atomic::write_bytes(&o.join("report.html"), page.as_bytes())?;
    runtime::outln!(
        "{:?} mode, range {}..{}: consistent {:.1} %, off by 1 {:.1} %, off by more {:.1} %; density after LR check {:.1} %",
        a.mode,
        range.min,
        range.max,
        100.0 * figures.consistent_exact,
        100.0 * figures.off_by_one,
        100.0 * figures.off_by_more,
        100.0 * schemas::density(&raw)
    );
    if let (Some((c, _)), Some(u)) = (&cloud, unit) {
        runtime::outln!("{} points ({})", c.points.len(), u.symbol());
    }
    runtime::outln!("total {:.1} ms; outputs in {}", total_ms, o.display());
    Ok(())
}

fn round3(v: f64) -> f64 {
    (v * 1000.0).round() / 1000.0
}

fn write_json<T: Serialize>(path: &std::path::Path, v: &T) -> Result<(), CliError> {
    let json = serde_json::to_string_pretty(v).expect("serialises");
    io::atomic::write_bytes(path, (json + "\n").as_bytes()).map_err(CliError::from)
}

fn write_cells(
    a: &ReconstructArgs,
    preset: &Stereo,
    f: &Frame,
    mut times: serde_json::Map<String, serde_json::Value>,
    t0: Instant,
) -> Result<(), CliError> {
    let CellMaps {
        labels,
        lists,
        tiles,
        targets,
        cloud,
        disparity,
        composed,
        colour,
    } = preset.cell_maps(f)?;
    let unit = pipelines::report::unit_of(&targets.unit);
    let o = &a.output;
    mkdir(o)?;
    let tw = Instant::now();
    let d = &disparity.map;
    io::write_pfm(&o.join("disparity.pfm"), d)?;
    io::write_pfm(&o.join("disparity_raw.pfm"), &composed.raw)?;
    io::write_disparity_png(&o.join("disparity.png"), d)?;
    let range = preset.matching.range();
    io::write_color_png(
        &o.join("disparity_color.png"),
        &io::disparity_color(d, range.min as f32, range.max as f32),
    )?;
    io::write_mask_png(&o.join("occlusion_left.png"), &composed.occlusion)?;
    io::render::write_labels_png(&o.join("labels_left.png"), &labels.left)?;
    io::render::write_labels_png(&o.join("labels_right.png"), &labels.right)?;
    let ov = o.join("overlay_left.png");
    io::write_color_png(&ov, &io::render::overlay(&colour.to_rgb(), &lists.left))?;
    io::write_ply(&o.join("points.ply"), &cloud, unit)?;
    times.insert(
        "write".into(),
        serde_json::json!(round3(tw.elapsed().as_secs_f64() * 1e3)),
    );
    let report = CellsReport::new(preset, (&lists, &tiles, &targets), d, times);
    write_json(&o.join("cells.json"), &report)?;
    let hist = preset.variance_histogram(f);
    let page = pipelines::html::cells_page(o, &report, (&targets, &tiles, &cloud), hist.as_ref());
    io::atomic::write_bytes(&o.join("report.html"), page.as_bytes())?;
    runtime::outln!(
        "{} cells left, {} right, {} paired; matched {:.1} % of the image",
        report.cells_left,
        report.cells_right,
        report.pairs,
        100.0 * report.matched_share
    );
    for c in &targets.cells {
        runtime::outln!("{}", pipelines::report::cell_line(c, unit.symbol()));
    }
    runtime::outln!(
        "total {:.1} ms; outputs in {}",
        t0.elapsed().as_secs_f64() * 1e3,
        o.display()
    );
    Ok(())
}
