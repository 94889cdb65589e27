//! The `microstereo` command line.

use crate::io::{self, IoError};
use crate::pipeline::{self, RangeKind, RangeScore, StereoConfig};
use clap::{Args, Parser, Subcommand, ValueEnum};
use matcher::{InputError, Mode, Weights};
use postprocess::Fill;
use schemas::{Calibration, DisparityRange, LengthUnit};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Turns a stereo light microscope into a 3D sensor.
#[derive(Parser, Debug)]
#[command(name = "microstereo", version, about)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Disparity map, occlusion masks, point cloud and report from a rectified pair.
    Reconstruct(Box<ReconstructArgs>),
    /// Compares a disparity map with ground truth (Middlebury figures).
    Eval(EvalArgs),
    /// Times every stage on cones and on a 1280×1024 pair.
    Bench(BenchArgs),
    /// Segments the cells of one image: labels, overlay, variance, histogram, cells.json.
    Segment(SegmentArgs),
    /// Renders a synthetic stereo-microscope scene (or sequence, or calibration z-stack) with ground truth.
    Synth(crate::synthcmd::SynthArgs),
    /// Fits the microscope's b·f_eff and disparity offset from pairs of a target at known stage heights.
    CalibrateDepth(crate::calibrate::CalibrateArgs),
    /// Runs a launch file's graph, one process per node, and prints a summary at the end.
    Run(crate::graph::RunArgs),
    /// Runs one node of a launch file as this process (started by `run`).
    Node(crate::graph::NodeArgs),
    /// Times one edge: 0.3, 1.3 and 5 MP frames over iceoryx2 and over a Unix-domain socket.
    BenchTransport(crate::graph::BenchTransportArgs),
    /// Lists a recording's channels, types, message counts, duration and rates.
    Inspect(crate::recording::InspectArgs),
    /// Runs the graph with recorded edges in place of the nodes that made them.
    Replay(crate::recording::ReplayArgs),
    /// Feeds one node its recorded inputs and compares its outputs with the recorded ones.
    TestNode(crate::recording::TestNodeArgs),
    /// Shows a recording in Rerun (or writes it as an .rrd file).
    View(crate::recording::ViewArgs),
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum ScaleArg {
    StdDev,
    Variance,
    LogStdDev,
}

/// Segmentation settings shared by `segment` and `reconstruct --cells`.
#[derive(Args, Debug, Clone)]
struct SegmentOpts {
    /// M: the local variance window is (2M+1)×(2M+1).
    #[arg(long, default_value_t = 3)]
    variance_radius: usize,
    /// Blobs smaller than this many pixels are not cells.
    #[arg(long, default_value_t = 200)]
    min_area: usize,
    /// Smallest local standard deviation (grey levels) that can be cell.
    #[arg(long, default_value_t = 4.0)]
    min_std: f32,
    /// How the variance maps onto 0–255 before Otsu.
    #[arg(long, value_enum, default_value = "log-std-dev")]
    variance_scale: ScaleArg,
    /// Opening radius (px) before hole filling; 0 = off.
    #[arg(long, default_value_t = 0)]
    open: u8,
    /// Closing radius (px) before hole filling; 0 = off.
    #[arg(long, default_value_t = 0)]
    close: u8,
    /// Keep holes inside cells.
    #[arg(long)]
    no_fill_holes: bool,
    /// Keep the skirt the variance window adds around each cell (up to M+1 px) instead of
    /// peeling it back where it looks like background (the paper's plain threshold).
    #[arg(long)]
    no_peel: bool,
}

impl SegmentOpts {
    fn params(&self) -> Result<segment::SegmentParams, CliError> {
        if self.variance_radius == 0 || self.variance_radius > 50 {
            return Err(CliError::Other(format!(
                "--variance-radius {} is out of range: use 1..50",
                self.variance_radius
            )));
        }
        if !(self.min_std >= 0.0 && self.min_std.is_finite()) {
            return Err(CliError::Other(format!(
                "--min-std {} must be a non-negative number",
                self.min_std
            )));
        }
        Ok(segment::SegmentParams {
            variance_radius: self.variance_radius,
            scale: match self.variance_scale {
                ScaleArg::StdDev => segment::VarianceScale::StdDev,
                ScaleArg::Variance => segment::VarianceScale::Variance,
                ScaleArg::LogStdDev => segment::VarianceScale::LogStdDev,
            },
            min_std: self.min_std,
            min_area: self.min_area,
            fill_holes: !self.no_fill_holes,
            open_radius: self.open,
            close_radius: self.close,
            peel_edges: !self.no_peel,
        })
    }
}

#[derive(Args, Debug)]
struct SegmentArgs {
    /// Microscope image (PNG, JPEG or TIFF; colour is converted to grey).
    image: PathBuf,
    /// Output directory (created if missing).
    #[arg(short, long)]
    output: PathBuf,
    #[command(flatten)]
    opts: SegmentOpts,
    /// Ground-truth mask (non-zero = cell): prints Dice and the cell-count error.
    #[arg(long)]
    truth: Option<PathBuf>,
    /// The truth mask marks cells with zero (BBBC003's raw TIFF convention).
    #[arg(long, requires = "truth")]
    truth_inverted: bool,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum ModeArg {
    Quality,
    Paper,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum WeightsArg {
    Equal,
    Decreasing,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum FillArg {
    Background,
    Linear,
    None,
}

#[derive(Clone, Copy, Debug, ValueEnum, Serialize, Deserialize, PartialEq)]
#[serde(rename_all = "lowercase")]
enum UnitArg {
    Um,
    Mm,
    M,
}

impl From<UnitArg> for LengthUnit {
    fn from(u: UnitArg) -> Self {
        match u {
            UnitArg::Um => LengthUnit::Um,
            UnitArg::Mm => LengthUnit::Mm,
            UnitArg::M => LengthUnit::M,
        }
    }
}

#[derive(Args, Debug)]
struct ReconstructArgs {
    /// Rectified left image (PNG, JPEG or TIFF).
    left: PathBuf,
    /// Rectified right image.
    right: PathBuf,
    /// Output directory (created if missing).
    #[arg(short, long)]
    output: PathBuf,
    /// Matcher: `quality` (semi-global) or `paper` (support value + NCC).
    #[arg(long, value_enum, default_value = "quality")]
    mode: ModeArg,
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
    #[arg(long, default_value_t = 13)]
    window: usize,
    /// Support-value weights (paper mode).
    #[arg(long, value_enum, default_value = "equal")]
    weights: WeightsArg,
    /// Top-SV candidates passed to the NCC decision (paper mode).
    #[arg(long, default_value_t = 3)]
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
    #[arg(long)]
    p1: Option<u16>,
    /// SGM penalty for larger jumps, lowered across intensity edges (quality mode).
    #[arg(long)]
    p2: Option<u16>,
    /// Percent by which the best cost must beat other disparities (quality mode).
    #[arg(long)]
    uniqueness_ratio: Option<u16>,
    /// Weight of the gradient term in the cost (quality mode; 0 = census only).
    #[arg(long)]
    gradient_weight: Option<u16>,
    /// SGM paths: 4 (the default) or 8 (quality mode).
    #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(["4", "8"]))]
    paths: Option<String>,
    /// LR consistency tolerance in pixels (0..4).
    #[arg(long, default_value_t = 1)]
    lr_tolerance: u32,
    /// Valid regions smaller than this are removed (default: 50 paper, 100 quality).
    #[arg(long)]
    min_region: Option<usize>,
    /// Median radius over valid pixels (0 = off, 2 = 5×5).
    #[arg(long, default_value_t = 2)]
    median: usize,
    /// How invalid pixels are filled.
    #[arg(long, value_enum, default_value = "background")]
    fill: FillArg,
    /// Baseline for triangulation (in `--unit`).
    #[arg(
        long,
        requires = "focal",
        conflicts_with = "calibration",
        allow_hyphen_values = true
    )]
    baseline: Option<f64>,
    /// Focal length in pixels.
    #[arg(long, requires = "baseline", allow_hyphen_values = true)]
    focal: Option<f64>,
    /// Principal point column (default: image centre).
    #[arg(long)]
    cx: Option<f64>,
    /// Principal point row (default: image centre).
    #[arg(long)]
    cy: Option<f64>,
    /// Right principal point column (default: `--cx`).
    #[arg(long)]
    cx_right: Option<f64>,
    /// Unit of `--baseline` and of the point cloud.
    #[arg(long, value_enum, default_value = "mm")]
    unit: UnitArg,
    /// Calibration file (TOML or JSON): baseline, focal_px or f_eff + pixel_pitch, cx, cy, unit.
    #[arg(long)]
    calibration: Option<PathBuf>,
    /// Segment both views and match only the cells (plus `--cell-margin`); writes cells.json.
    #[arg(long)]
    cells: bool,
    /// Pixels around each cell that are matched too: the substrate ring for its height.
    #[arg(long, default_value_t = 8)]
    cell_margin: u8,
    #[command(flatten)]
    seg: SegmentOpts,
}

#[derive(Args, Debug)]
struct EvalArgs {
    /// Disparity map to evaluate (PFM, or PNG holding d·scale with 0 = unknown).
    disparity: PathBuf,
    /// Scale of a PNG disparity map (default 256 for 16-bit, 1 for 8-bit).
    #[arg(long)]
    scale: Option<f32>,
    /// Left ground truth (PFM or PNG).
    #[arg(long)]
    gt: PathBuf,
    /// Scale of a PNG ground truth (Middlebury: 4 for cones, 2 for the half-size 2006 sets).
    #[arg(long)]
    gt_scale: Option<f32>,
    /// Right ground truth, for the occlusion mask.
    #[arg(long)]
    gt_right: Option<PathBuf>,
    /// Scale of the right ground truth (default: `--gt-scale`).
    #[arg(long)]
    gt_right_scale: Option<f32>,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Args, Debug)]
struct BenchArgs {
    /// Directory with the cones pair (im2.png, im6.png).
    #[arg(long, default_value = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/cones"))]
    cones: PathBuf,
    /// Runs per measurement (the median is reported).
    #[arg(long, default_value_t = 5)]
    repeat: usize,
    /// Write the results as JSON here too.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Also write the 1280×1024 pair as PNGs here (so other tools can time the same images).
    #[arg(long)]
    write_pairs: Option<PathBuf>,
    /// Skip the 1280×1024 pair.
    #[arg(long)]
    cones_only: bool,
    /// SGM paths of quality mode: 4 (the default) or 8.
    #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(["4", "8"]))]
    paths: Option<String>,
}

/// A command failure: printed once, exit code 2 (1 for [`CliError::Failed`]).
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    /// A file problem.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The pair or the parameters cannot be matched.
    #[error(transparent)]
    Input(#[from] InputError),
    /// Anything else, already phrased for the user.
    #[error("{0}")]
    Other(String),
    /// A check ran and found a difference (exit code 1, not 2).
    #[error("{0}")]
    Failed(String),
    /// A child program failed and has said why already: exit with its code, print nothing.
    #[error("exit code {0}")]
    Reported(i32),
}

/// Runs the CLI and returns the process exit code.
pub fn main() -> i32 {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Reconstruct(a) => reconstruct(*a),
        Command::Eval(a) => eval(a),
        Command::Bench(a) => bench(a),
        Command::BenchTransport(a) => crate::graph::bench_transport(a),
        Command::Segment(a) => segment_cmd(a),
        Command::Synth(a) => crate::synthcmd::synth(a),
        Command::CalibrateDepth(a) => crate::calibrate::calibrate_depth(a),
        Command::Run(a) => crate::graph::run_cmd(a),
        Command::Node(a) => crate::graph::node_cmd(a),
        Command::Inspect(a) => crate::recording::inspect(a),
        Command::Replay(a) => crate::recording::replay(a),
        Command::TestNode(a) => crate::recording::test_node_cmd(a),
        Command::View(a) => crate::recording::view(a),
    };
    match result {
        Ok(()) => 0,
        Err(CliError::Reported(code)) => code,
        Err(CliError::Failed(e)) => {
            eprintln!("FAIL: {e}");
            1
        }
        Err(e) => {
            eprintln!("error: {e}");
            2
        }
    }
}

/// Calibration file contents.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct CalibrationFile {
    baseline: f64,
    focal_px: Option<f64>,
    f_eff: Option<f64>,
    pixel_pitch: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    cx_right: Option<f64>,
    #[serde(default)]
    unit: Option<UnitArg>,
}

/// Reads a calibration file for images of `w × h`.
pub(crate) fn load_calibration(path: &Path, w: usize, h: usize) -> Result<Calibration, CliError> {
    let text = std::fs::read_to_string(path).map_err(|e| {
        CliError::Other(format!(
            "calibration file '{}' cannot be read: {e}",
            path.display()
        ))
    })?;
    let is_json = path.extension().is_some_and(|e| e == "json");
    let f: CalibrationFile = if is_json {
        serde_json::from_str(&text).map_err(|e| e.to_string())
    } else {
        toml::from_str(&text).map_err(|e| e.to_string())
    }
    .map_err(|e| {
        CliError::Other(format!(
            "calibration file '{}' is not valid: {e}; expected baseline, focal_px (or f_eff and pixel_pitch), optional cx, cy, cx_right, unit",
            path.display()
        ))
    })?;
    let focal = match (f.focal_px, f.f_eff, f.pixel_pitch) {
        (Some(fp), None, None) => fp,
        (None, Some(fe), Some(pp)) if pp > 0.0 => fe / pp,
        _ => {
            return Err(CliError::Other(format!(
                "calibration file '{}': give either focal_px, or f_eff with pixel_pitch (> 0)",
                path.display()
            )));
        }
    };
    let cx = f.cx.unwrap_or((w as f64 - 1.0) / 2.0);
    let c = Calibration {
        baseline: f.baseline,
        focal_px: focal,
        cx,
        cy: f.cy.unwrap_or((h as f64 - 1.0) / 2.0),
        cx_right: f.cx_right.unwrap_or(cx),
        unit: f.unit.unwrap_or(UnitArg::Mm).into(),
    };
    check_calibration(&c, &path.display().to_string())?;
    Ok(c)
}

/// Writes the calibration in the format `reconstruct --calibration` reads.
pub fn write_calibration(
    path: &Path,
    c: &schemas::Calibration,
    pitch: f64,
) -> Result<(), CliError> {
    let text = format!(
        "# Written by microstereo: rectified parallel-axis geometry.\nbaseline = {}\nf_eff = {}\npixel_pitch = {}\ncx = {}\ncy = {}\ncx_right = {}\nunit = \"{}\"\n",
        c.baseline,
        c.focal_px * pitch,
        pitch,
        c.cx,
        c.cy,
        c.cx_right,
        match c.unit {
            schemas::LengthUnit::Um => "um",
            schemas::LengthUnit::Mm => "mm",
            schemas::LengthUnit::M => "m",
        }
    );
    std::fs::write(path, text)
        .map_err(|e| CliError::Other(format!("cannot write '{}': {e}", path.display())))
}

fn check_calibration(c: &Calibration, source: &str) -> Result<(), CliError> {
    if !(c.baseline > 0.0 && c.baseline.is_finite() && c.focal_px > 0.0 && c.focal_px.is_finite()) {
        return Err(CliError::Other(format!(
            "calibration from {source}: baseline ({}) and focal length ({} px) must be positive",
            c.baseline, c.focal_px
        )));
    }
    Ok(())
}

/// What `report.json` holds.
#[derive(Serialize)]
struct Report<'a> {
    mode: Mode,
    left: String,
    right: String,
    width: usize,
    height: usize,
    range: DisparityRange,
    auto_range_curve: Option<Vec<RangeScore>>,
    config: &'a StereoConfig,
    validation: schemas::ValidationFigures,
    density_raw: f64,
    density: f64,
    evaluations: u64,
    points: Option<usize>,
    unit: Option<&'static str>,
    times_ms: serde_json::Map<String, serde_json::Value>,
    total_ms: f64,
}

fn reconstruct(a: ReconstructArgs) -> Result<(), CliError> {
    let left = io::load_image(&a.left, "left image")?;
    let right = io::load_image(&a.right, "right image")?;
    let (w, h) = (left.grey.width, left.grey.height);
    let mode = match a.mode {
        ModeArg::Quality => Mode::Quality,
        ModeArg::Paper => Mode::Paper,
    };
    if a.lr_tolerance > validate::MAX_TOLERANCE {
        return Err(CliError::Other(format!(
            "--lr-tolerance {} is out of range: use 0..{}",
            a.lr_tolerance,
            validate::MAX_TOLERANCE
        )));
    }
    if a.candidates == 0 || a.candidates > 16 {
        return Err(CliError::Other(format!(
            "--candidates {} is out of range: use 1..16",
            a.candidates
        )));
    }
    let default_range = DisparityRange::new(0, 64.min(w as i32 / 2).max(1));
    let range = match (a.min_disparity, a.max_disparity) {
        (Some(lo), Some(hi)) => DisparityRange::new(lo, hi),
        _ => default_range,
    };
    let mut cfg = StereoConfig::new(mode, range);
    cfg.paper.window = a.window;
    cfg.paper.weights = match a.weights {
        WeightsArg::Equal => Weights::Equal,
        WeightsArg::Decreasing => Weights::Decreasing,
    };
    cfg.paper.candidates = a.candidates;
    cfg.paper.uniqueness = a.uniqueness;
    cfg.paper.ordering = a.ordering;
    cfg.paper.continuity = a.continuity;
    cfg.lr_tolerance = a.lr_tolerance;
    let q = &mut cfg.quality;
    q.p1 = a.p1.unwrap_or(q.p1);
    q.p2 = a.p2.unwrap_or(q.p2);
    q.uniqueness_ratio = a.uniqueness_ratio.unwrap_or(q.uniqueness_ratio).min(99);
    q.gradient_weight = a.gradient_weight.unwrap_or(q.gradient_weight);
    if let Some(p) = &a.paths {
        q.paths = p.parse().expect("validated by clap");
    }
    if q.p2 <= q.p1 {
        return Err(CliError::Other(format!(
            "--p2 ({}) must be larger than --p1 ({})",
            q.p2, q.p1
        )));
    }
    if let Some(m) = a.min_region {
        cfg.post.min_region = m;
    }
    cfg.post.median_radius = a.median;
    cfg.post.fill = match a.fill {
        FillArg::Background => Fill::Background,
        FillArg::Linear => Fill::Linear,
        FillArg::None => Fill::None,
    };
    // Geometry first, so a bad calibration fails before any work.
    let calib = match (&a.calibration, a.baseline, a.focal) {
        (Some(p), _, _) => Some(load_calibration(p, w, h)?),
        (None, Some(b), Some(f)) => {
            let cx = a.cx.unwrap_or((w as f64 - 1.0) / 2.0);
            let c = Calibration {
                baseline: b,
                focal_px: f,
                cx,
                cy: a.cy.unwrap_or((h as f64 - 1.0) / 2.0),
                cx_right: a.cx_right.unwrap_or(cx),
                unit: a.unit.into(),
            };
            check_calibration(&c, "--baseline/--focal")?;
            Some(c)
        }
        _ => None,
    };
    // Check the pair before the (possibly long) range search.
    matcher::check_inputs(&left.grey, &right.grey, range, cfg.window())?;
    if a.cells {
        let Some(c) = calib else {
            return Err(CliError::Other(
                "--cells measures cells in 3D: give --calibration FILE or --baseline and --focal"
                    .into(),
            ));
        };
        if a.auto_range {
            return Err(CliError::Other(
                "--cells takes the range from --min-disparity/--max-disparity (the cells' heights), not --auto-range".into(),
            ));
        }
        return reconstruct_cells(&a, &left, &right, &cfg, &c);
    }
    let mut curve = None;
    let mut auto_ms = 0.0;
    if a.auto_range {
        let ranges = pipeline::candidate_ranges(a.range_kind, &a.range_radii, w);
        if ranges.is_empty() {
            return Err(CliError::Other(format!(
                "--range-radii {:?} has no radius between 1 and the image width {w}",
                a.range_radii
            )));
        }
        let t = Instant::now();
        let (best, c) = pipeline::auto_range(&left.grey, &right.grey, &cfg, &ranges)?;
        auto_ms = t.elapsed().as_secs_f64() * 1e3;
        cfg.range = best;
        curve = Some(c);
    }
    let mut out = pipeline::run_stereo(&left.grey, &right.grey, &cfg)?;
    if a.auto_range {
        out.times.stages.insert(0, ("auto_range".into(), auto_ms));
    }
    let cloud = calib.map(|c| {
        out.times.time("triangulate", || {
            triangulate::triangulate(&out.disparity, &c, &left.rgb)
        })
    });
    // Everything computed: only now touch the output directory.
    std::fs::create_dir_all(&a.output).map_err(|e| {
        CliError::Other(format!(
            "cannot create output directory '{}': {e}",
            a.output.display()
        ))
    })?;
    let t = Instant::now();
    let o = &a.output;
    io::write_pfm(&o.join("disparity.pfm"), &out.disparity)?;
    io::write_pfm(&o.join("disparity_raw.pfm"), &out.checked.left)?;
    let lost = io::write_disparity_png(&o.join("disparity.png"), &out.disparity)?;
    if lost > 0 {
        eprintln!(
            "warning: {lost} pixels have disparities disparity.png cannot hold (below 1/512 px, where 0 already means unknown, or ≥ 256); disparity.pfm has them"
        );
    }
    let (lo, hi) = (cfg.range.min as f32, cfg.range.max as f32);
    io::write_color_png(
        &o.join("disparity_color.png"),
        &io::disparity_color(&out.disparity, lo, hi),
    )?;
    io::write_mask_png(&o.join("occlusion_left.png"), &out.checked.occlusion_left)?;
    io::write_mask_png(&o.join("occlusion_right.png"), &out.checked.occlusion_right)?;
    if let Some(c) = &cloud {
        io::write_ply(&o.join("points.ply"), c)?;
    }
    out.times.add("write", t.elapsed().as_secs_f64() * 1e3);
    let mut times = serde_json::Map::new();
    for (k, v) in &out.times.stages {
        times.insert(k.clone(), serde_json::json!((v * 1000.0).round() / 1000.0));
    }
    let report = Report {
        mode,
        left: a.left.display().to_string(),
        right: a.right.display().to_string(),
        width: w,
        height: h,
        range: cfg.range,
        auto_range_curve: curve,
        config: &cfg,
        validation: out.figures,
        density_raw: schemas::density(&out.checked.left),
        density: schemas::density(&out.disparity),
        evaluations: out.evaluations,
        points: cloud.as_ref().map(|c| c.points.len()),
        unit: cloud.as_ref().map(|c| c.unit.symbol()),
        total_ms: out.times.total_ms(),
        times_ms: times,
    };
    let json = serde_json::to_string_pretty(&report).expect("report serialises");
    let rp = o.join("report.json");
    std::fs::write(&rp, json + "\n")
        .map_err(|e| CliError::Other(format!("cannot write '{}': {e}", rp.display())))?;
    let f = &out.figures;
    println!(
        "{mode:?} mode, range {}..{}: consistent {:.1} %, off by 1 {:.1} %, off by more {:.1} %; density after LR check {:.1} %",
        cfg.range.min,
        cfg.range.max,
        100.0 * f.consistent_exact,
        100.0 * f.off_by_one,
        100.0 * f.off_by_more,
        100.0 * schemas::density(&out.checked.left)
    );
    if let Some(c) = &cloud {
        println!("{} points ({})", c.points.len(), c.unit.symbol());
    }
    println!(
        "total {:.1} ms; outputs in {}",
        out.times.total_ms(),
        o.display()
    );
    Ok(())
}

fn eval(a: EvalArgs) -> Result<(), CliError> {
    let disp = io::read_disparity(&a.disparity, a.scale, "disparity map")?;
    let gt = io::read_disparity(&a.gt, a.gt_scale, "ground truth")?;
    if (disp.width, disp.height) != (gt.width, gt.height) {
        return Err(CliError::Other(format!(
            "disparity map '{}' is {}×{} but ground truth '{}' is {}×{}; evaluate maps of the same view and size",
            a.disparity.display(),
            disp.width,
            disp.height,
            a.gt.display(),
            gt.width,
            gt.height
        )));
    }
    let visible = match &a.gt_right {
        Some(p) => {
            let gr = io::read_disparity(p, a.gt_right_scale.or(a.gt_scale), "right ground truth")?;
            if (gr.width, gr.height) != (gt.width, gt.height) {
                return Err(CliError::Other(format!(
                    "right ground truth '{}' is {}×{} but the left one is {}×{}",
                    p.display(),
                    gr.width,
                    gr.height,
                    gt.width,
                    gt.height
                )));
            }
            Some(validate::occlusion_from_gt(&gt, &gr))
        }
        None => None,
    };
    let f = validate::evaluate(&disp, &gt, visible.as_ref());
    if a.json {
        println!("{}", serde_json::to_string_pretty(&f).expect("serialises"));
        return Ok(());
    }
    println!(
        "{:<8} {:>9} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8}",
        "pixels", "count", "bad0.5%", "bad1%", "bad2%", "bad4%", "mae", "rms", "dens%"
    );
    let label = if visible.is_some() { "nonocc" } else { "known" };
    for (name, s) in [(label, f.nonocc), ("all", f.all)] {
        println!(
            "{:<8} {:>9} {:>8.2} {:>8.2} {:>8.2} {:>8.2} {:>8.3} {:>8.3} {:>8.2}",
            name,
            s.pixels,
            s.bad_0_5,
            s.bad_1,
            s.bad_2,
            s.bad_4,
            s.mean_abs_error,
            s.rms,
            s.density
        );
        if visible.is_none() {
            break;
        }
    }
    Ok(())
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// One benchmark line.
#[derive(Serialize)]
struct BenchLine {
    pair: String,
    mode: Mode,
    width: usize,
    height: usize,
    range: DisparityRange,
    stages_ms: Vec<(String, f64)>,
    total_ms: f64,
    mevals_per_s: f64,
}

fn bench(a: BenchArgs) -> Result<(), CliError> {
    let left = io::load_image(&a.cones.join("im2.png"), "cones left image")?;
    let right = io::load_image(&a.cones.join("im6.png"), "cones right image")?;
    let mut pairs = vec![(
        "cones".to_string(),
        left.grey,
        right.grey,
        DisparityRange::new(0, 63),
    )];
    if !a.cones_only {
        let s = crate::synthetic::standard_scene(1280, 1024, 4, 14, 7);
        if let Some(dir) = &a.write_pairs {
            std::fs::create_dir_all(dir)
                .map_err(|e| CliError::Other(format!("cannot create '{}': {e}", dir.display())))?;
            for (name, p) in [
                ("synth1280_left.png", &s.left),
                ("synth1280_right.png", &s.right),
            ] {
                image::GrayImage::from_raw(p.width as u32, p.height as u32, p.data.clone())
                    .expect("size")
                    .save(dir.join(name))
                    .map_err(|e| {
                        CliError::Other(format!("cannot write '{}': {e}", dir.join(name).display()))
                    })?;
            }
        }
        pairs.push((
            "synth1280".into(),
            s.left,
            s.right,
            DisparityRange::new(0, 63),
        ));
    }
    let mut lines = Vec::new();
    println!(
        "{} threads; median of {} runs; ranges 0..63 (64 disparities, as SGBM numDisparities=64)",
        rayon::current_num_threads(),
        a.repeat
    );
    for (name, l, r, range) in &pairs {
        for mode in [Mode::Paper, Mode::Quality] {
            let mut cfg = StereoConfig::new(mode, *range);
            if let Some(p) = &a.paths {
                cfg.quality.paths = p.parse().expect("validated by clap");
            }
            let mut runs = Vec::new();
            let mut evals = 0;
            // As a live node does: one workspace for the whole stream of frames.
            let mut ws = pipeline::Workspace::default();
            for _ in 0..a.repeat.max(1) {
                let out = pipeline::run_stereo_in(&mut ws, l, r, &cfg)?;
                evals = out.evaluations;
                runs.push(out.times);
            }
            let stage_names: Vec<String> = runs[0].stages.iter().map(|(n, _)| n.clone()).collect();
            let stages: Vec<(String, f64)> = stage_names
                .iter()
                .enumerate()
                .map(|(i, n)| {
                    (
                        n.clone(),
                        median(runs.iter().map(|t| t.stages[i].1).collect()),
                    )
                })
                .collect();
            let total = median(runs.iter().map(|t| t.total_ms()).collect());
            let match_ms = stages
                .iter()
                .find(|(n, _)| n == "match")
                .map_or(total, |s| s.1);
            let line = BenchLine {
                pair: name.clone(),
                mode,
                width: l.width,
                height: l.height,
                range: *range,
                stages_ms: stages,
                total_ms: total,
                mevals_per_s: evals as f64 / (match_ms * 1e3),
            };
            let st: Vec<String> = line
                .stages_ms
                .iter()
                .map(|(n, v)| format!("{n} {v:.1}"))
                .collect();
            println!(
                "{:<10} {:<8} {:>4}×{:<4} total {:>7.1} ms  [{}]  {:.0} M disparity evaluations/s",
                name,
                format!("{mode:?}").to_lowercase(),
                l.width,
                l.height,
                total,
                st.join(", "),
                line.mevals_per_s
            );
            lines.push(line);
        }
    }
    if let Some(p) = &a.json {
        std::fs::write(p, serde_json::to_string_pretty(&lines).expect("serialises"))
            .map_err(|e| CliError::Other(format!("cannot write '{}': {e}", p.display())))?;
    }
    Ok(())
}

fn segment_cmd(a: SegmentArgs) -> Result<(), CliError> {
    let params = a.opts.params()?;
    let img = io::load_image(&a.image, "image")?;
    let truth = match &a.truth {
        Some(p) => {
            let t = io::load_image(p, "truth mask")?.grey;
            if (t.width, t.height) != (img.grey.width, img.grey.height) {
                return Err(CliError::Other(format!(
                    "truth mask '{}' is {}×{} but the image is {}×{}; give the mask of this image",
                    p.display(),
                    t.width,
                    t.height,
                    img.grey.width,
                    img.grey.height
                )));
            }
            let on = |v: u8| (v != 0) != a.truth_inverted;
            let data = t
                .data
                .iter()
                .map(|&v| if on(v) { 255 } else { 0 })
                .collect();
            Some(schemas::Plane::from_vec(t.width, t.height, data).expect("same size"))
        }
        None => None,
    };
    let t = Instant::now();
    let seg = segment::segment(&img.grey, &params);
    let ms = t.elapsed().as_secs_f64() * 1e3;
    let score = truth
        .as_ref()
        .map(|t| crate::cells::score(&seg.mask, t, seg.cells.len()));
    crate::cells::write_segmentation(&a.output, &a.image, &img.rgb, &seg, &params, score)?;
    let max_label = seg.cells.len();
    if max_label > 65535 {
        eprintln!(
            "warning: {max_label} cells; labels.png holds ids up to 65535, cells.json has all"
        );
    }
    match seg.otsu {
        Some(o) => println!(
            "Otsu threshold {o} of 255 (applied {}; 255 = local std {:.1} grey levels)",
            seg.threshold, seg.variance_max
        ),
        None => println!("flat image: no threshold, no cells"),
    }
    println!("{} cells in {ms:.1} ms", seg.cells.len());
    if let Some(s) = score {
        println!(
            "truth: Dice {:.3}, {} cells found / {} in the truth ({:+.1} %)",
            s.dice,
            s.found_cells,
            s.truth_cells,
            100.0 * s.count_error
        );
    }
    println!("outputs in {}", a.output.display());
    Ok(())
}

/// What `reconstruct --cells` writes to cells.json.
#[derive(Serialize)]
struct CellsReport<'a> {
    left: String,
    right: String,
    width: usize,
    height: usize,
    range: DisparityRange,
    unit: &'static str,
    segmentation: &'a segment::SegmentParams,
    cells_left: usize,
    cells_right: usize,
    pairs: usize,
    /// Pixels handed to the matcher over the image's pixels.
    matched_share: f64,
    /// The substrate's disparity plane over the background (absent: each cell's ring
    /// median stood in).
    substrate_plane: Option<matcher::DisparityPlane>,
    times_ms: Vec<(String, f64)>,
    cells: &'a [schemas::Cell3],
}

fn reconstruct_cells(
    a: &ReconstructArgs,
    left: &io::LoadedImage,
    right: &io::LoadedImage,
    cfg: &StereoConfig,
    calib: &Calibration,
) -> Result<(), CliError> {
    let seg = a.seg.params()?;
    let p = crate::cells::CellStereoParams {
        margin: a.cell_margin,
    };
    let mut cs = crate::cells::cell_stereo(&left.grey, &right.grey, cfg, &seg, &p)?;
    let t = Instant::now();
    let cells = crate::cells::measure_cells(&cs, calib);
    cs.times.add("measure", t.elapsed().as_secs_f64() * 1e3);
    let t = Instant::now();
    let cloud = triangulate::triangulate(&cs.disparity, calib, &left.rgb);
    cs.times.add("triangulate", t.elapsed().as_secs_f64() * 1e3);
    let o = &a.output;
    std::fs::create_dir_all(o).map_err(|e| {
        CliError::Other(format!(
            "cannot create output directory '{}': {e}",
            o.display()
        ))
    })?;
    io::write_pfm(&o.join("disparity.pfm"), &cs.disparity)?;
    io::write_pfm(&o.join("disparity_raw.pfm"), &cs.disparity_raw)?;
    io::write_disparity_png(&o.join("disparity.png"), &cs.disparity)?;
    io::write_color_png(
        &o.join("disparity_color.png"),
        &io::disparity_color(&cs.disparity, cfg.range.min as f32, cfg.range.max as f32),
    )?;
    io::write_mask_png(&o.join("occlusion_left.png"), &cs.occlusion_left)?;
    crate::render::write_labels_png(&o.join("labels_left.png"), &cs.left_seg.labels)?;
    crate::render::write_labels_png(&o.join("labels_right.png"), &cs.right_seg.labels)?;
    let ov = o.join("overlay_left.png");
    crate::render::overlay(&left.rgb, &cs.left_seg.cells)
        .save(&ov)
        .map_err(|e| CliError::Other(format!("cannot write '{}': {e}", ov.display())))?;
    io::write_ply(&o.join("points.ply"), &cloud)?;
    let (w, h) = (left.grey.width, left.grey.height);
    let report = CellsReport {
        left: a.left.display().to_string(),
        right: a.right.display().to_string(),
        width: w,
        height: h,
        range: cfg.range,
        unit: calib.unit.symbol(),
        segmentation: &seg,
        cells_left: cs.left_seg.cells.len(),
        cells_right: cs.right_seg.cells.len(),
        pairs: cs.pairs.len(),
        matched_share: cs.matched_pixels as f64 / (w * h) as f64,
        substrate_plane: cs.substrate,
        times_ms: cs.times.stages.clone(),
        cells: &cells,
    };
    let jp = o.join("cells.json");
    std::fs::write(
        &jp,
        serde_json::to_string_pretty(&report).expect("serialises") + "\n",
    )
    .map_err(|e| CliError::Other(format!("cannot write '{}': {e}", jp.display())))?;
    println!(
        "{} cells left, {} right, {} paired; matched {:.1} % of the image",
        report.cells_left,
        report.cells_right,
        report.pairs,
        100.0 * report.matched_share
    );
    for c in &cells {
        println!(
            "cell {:>3}: centroid ({:.1}, {:.1}) px, height {:.2} {u}, volume {:.0} {u}³, 3D centroid ({:.1}, {:.1}, {:.1})",
            c.id,
            c.centroid_px[0],
            c.centroid_px[1],
            c.height,
            c.volume,
            c.centroid[0],
            c.centroid[1],
            c.centroid[2],
            u = calib.unit.symbol()
        );
    }
    println!(
        "total {:.1} ms; outputs in {}",
        cs.times.total_ms(),
        o.display()
    );
    Ok(())
}
