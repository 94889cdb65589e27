//! `microstereo segment`: one image's cells, with its intermediate images and, given a
//! truth mask, its Dice overlap.

use crate::error::CliError;
use clap::{Args, ValueEnum};
use formats::{self as io, IoError};
use schemas::Plane;
use segment::{SegmentParams, Segmentation, report};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The flags of the segmentation parameters, for errors.
const FLAGS: &[(&str, &str)] = &[
    ("variance_radius", "--variance-radius"),
    ("min_std", "--min-std"),
    ("noise_floor", "--noise-floor"),
    ("min_area", "--min-area"),
    ("open_radius", "--open"),
    ("close_radius", "--close"),
];

#[derive(Clone, Copy, Debug, ValueEnum)]
enum ScaleArg {
    StdDev,
    Variance,
    LogStdDev,
}

/// Segmentation settings shared by `segment` and `reconstruct --cells`.
#[derive(Args, Debug, Clone)]
pub struct SegmentOpts {
    /// M: the local variance window is (2M+1)×(2M+1).
    #[arg(long, default_value_t = SegmentParams::default().variance_radius)]
    variance_radius: usize,
    /// Blobs smaller than this many pixels are not cells.
    #[arg(long, default_value_t = SegmentParams::default().min_area)]
    min_area: usize,
    /// Smallest local standard deviation (grey levels) that can be cell.
    #[arg(long, default_value_t = SegmentParams::default().min_std)]
    min_std: f32,
    /// Cells' local std is at least this many times the image's noise (0: --min-std alone).
    #[arg(long, default_value_t = SegmentParams::default().noise_floor)]
    noise_floor: f32,
    /// How the variance maps onto 0–255 before Otsu.
    #[arg(long, value_enum, default_value = "log-std-dev")]
    variance_scale: ScaleArg,
    /// Opening radius (px) before hole filling; 0 = off.
    #[arg(long, default_value_t = SegmentParams::default().open_radius)]
    open: u8,
    /// Closing radius (px) before hole filling; 0 = off.
    #[arg(long, default_value_t = SegmentParams::default().close_radius)]
    close: u8,
    /// Keep holes inside cells.
    #[arg(long)]
    no_fill_holes: bool,
    /// Keep the skirt the variance window adds around each cell (up to M+1 px) instead of
    /// peeling it back where it looks like background (the paper's plain threshold).
    #[arg(long)]
    no_peel: bool,
    /// Keep thin arcs around a larger object (an embryo's zona pellucida) as objects of
    /// their own instead of joining them to it, and a rim open on one side open.
    #[arg(long)]
    no_absorb_rings: bool,
}

impl SegmentOpts {
    /// The segment node's parameters these flags give (checked by the node).
    pub fn params(&self) -> SegmentParams {
        SegmentParams {
            variance_radius: self.variance_radius,
            scale: match self.variance_scale {
                ScaleArg::StdDev => segment::VarianceScale::StdDev,
                ScaleArg::Variance => segment::VarianceScale::Variance,
                ScaleArg::LogStdDev => segment::VarianceScale::LogStdDev,
            },
            min_std: self.min_std,
            noise_floor: self.noise_floor,
            min_area: self.min_area,
            fill_holes: !self.no_fill_holes,
            open_radius: self.open,
            close_radius: self.close,
            peel_edges: !self.no_peel,
            absorb_rings: !self.no_absorb_rings,
        }
    }

    /// [`SegmentOpts::params`], checked: a bad value is refused in the terms of its flag.
    pub fn checked(&self) -> Result<SegmentParams, CliError> {
        let p = self.params();
        runtime::node::Params::check(&p)
            .map_err(|e| CliError::Other(crate::error::in_flag_terms(&e, FLAGS)))?;
        Ok(p)
    }
}
/// Arguments of `microstereo segment`.
#[derive(Args, Debug)]
pub struct SegmentArgs {
    /// Microscope image (PNG, JPEG or TIFF; colour is converted to grey).
    image: PathBuf,
    /// Output directory (created if missing).
    #[arg(short, long)]
    output: PathBuf,
    /// Replace the outputs of an earlier run in the output directory.
    #[arg(long)]
    overwrite: bool,
    #[command(flatten)]
    opts: SegmentOpts,
    /// Ground-truth mask (non-zero = cell): prints Dice and the cell-count error.
    #[arg(long)]
    truth: Option<PathBuf>,
    /// The truth mask marks cells with zero (BBBC003's raw TIFF convention).
    #[arg(long, requires = "truth")]
    truth_inverted: bool,
}

/// Runs `microstereo segment`.
pub fn segment_cmd(a: SegmentArgs) -> Result<(), CliError> {
    let params = a.opts.checked()?;
    let inputs: Vec<&Path> = std::iter::once(a.image.as_path())
        .chain(a.truth.as_deref())
        .collect();
    formats::outputs::check(
        &formats::outputs::in_dir(&a.output, OUTPUT_NAMES),
        &inputs,
        a.overwrite,
        "give -o another directory",
    )?;
    let img = capture::image::load(&a.image, "image").map_err(CliError::Other)?;
    let truth = match &a.truth {
        Some(p) => {
            let t = capture::image::load(p, "truth mask").map_err(CliError::Other)?;
            let size = (img.grey.width, img.grey.height);
            Some(report::truth_mask(&t.grey, p, size, a.truth_inverted)?)
        }
        None => None,
    };
    let t = Instant::now();
    let seg = segment::segment(&img.grey, &params);
    let ms = t.elapsed().as_secs_f64() * 1e3;
    let score = truth
        .as_ref()
        .map(|t| segment::score(&seg.mask, t, seg.cells.len()));
    write_segmentation(&a.output, &a.image, &img.rgb, &seg, &params, score)?;
    if seg.cells.len() > 65535 {
        let n = seg.cells.len();
        runtime::errln!("warning: {n} cells; labels.png holds ids up to 65535, cells.json has all");
    }
    for line in report::summary(&seg, ms, score.as_ref()) {
        runtime::outln!("{line}");
    }
    runtime::outln!("outputs in {}", a.output.display());
    Ok(())
}

/// What `segment` writes into its output directory.
const OUTPUT_NAMES: [&str; 5] = [
    "labels.png",
    "overlay.png",
    "variance.png",
    "histogram.png",
    "cells.json",
];

/// Writes labels.png, overlay.png, variance.png, histogram.png and cells.json into `dir`.
pub fn write_segmentation(
    dir: &Path,
    image: &Path,
    rgb: &Plane<[u8; 3]>,
    seg: &Segmentation,
    params: &SegmentParams,
    truth: Option<segment::TruthScore>,
) -> Result<(), IoError> {
    std::fs::create_dir_all(dir).map_err(|e| IoError::Write {
        path: dir.into(),
        reason: e.to_string(),
    })?;
    io::render::write_labels_png(&dir.join("labels.png"), &seg.labels)?;
    io::write_color_png(
        &dir.join("overlay.png"),
        &io::render::overlay(rgb, &seg.cells),
    )?;
    io::write_mask_png(&dir.join("variance.png"), &seg.variance)?;
    let chart = io::render::histogram_chart(&seg.histogram, Some(seg.threshold));
    io::write_color_png(&dir.join("histogram.png"), &chart)?;
    let r = report::SegmentReport::new(image, seg, params, truth);
    let json = serde_json::to_string_pretty(&r).expect("serialises");
    io::atomic::write_bytes(&dir.join("cells.json"), (json + "\n").as_bytes())
}
