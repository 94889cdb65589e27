//! `microstereo synth`: writes synthetic stereo-microscope scenes, sequences and z-stacks.

use crate::error::CliError;
use clap::Args;
use formats as io;
use schemas::Plane;
use serde::Serialize;
use std::path::{Path, PathBuf};
use synth::{CellSpec, Look, Optics, Pipette, Scene, Texture};

/// Arguments of `microstereo synth`.
#[derive(Args, Debug)]
pub struct SynthArgs {
    /// Output directory (created if missing).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Image width, px.
    #[arg(long, default_value_t = 640)]
    pub width: usize,
    /// Image height, px.
    #[arg(long, default_value_t = 480)]
    pub height: usize,
    /// Number of cells.
    #[arg(long, default_value_t = 6)]
    pub cells: usize,
    /// Footprint diameter range, µm (MIN,MAX).
    #[arg(long, value_delimiter = ',', default_values_t = [20.0, 100.0])]
    pub diameter: Vec<f64>,
    /// Cell height range, µm (MIN,MAX).
    #[arg(long, value_delimiter = ',', default_values_t = [8.0, 25.0])]
    pub cell_height: Vec<f64>,
    /// Random seed: same seed, same images.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Sensor noise, grey levels (standard deviation).
    #[arg(long, default_value_t = 1.5)]
    pub noise: f64,
    /// Defocus blur, px (Gaussian sigma).
    #[arg(long, default_value_t = 0.0)]
    pub blur: f64,
    /// Texture cells with this real cell image instead of procedural noise.
    #[arg(long)]
    pub texture: Option<PathBuf>,
    /// Pixel pitch, µm.
    #[arg(long, default_value_t = 5.0)]
    pub pixel_pitch: f64,
    /// Magnification.
    #[arg(long, default_value_t = 5.0)]
    pub magnification: f64,
    /// Effective focal length, µm.
    #[arg(long, default_value_t = 20_000.0)]
    pub f_eff: f64,
    /// Stereo baseline, µm.
    #[arg(long, default_value_t = 1_200.0)]
    pub baseline: f64,
    /// Write a sequence of this many frames (cells drift, the pipette advances).
    #[arg(long)]
    pub frames: Option<usize>,
    /// Largest cell drift, µm per frame.
    #[arg(long, default_value_t = 1.0)]
    pub drift: f64,
    /// Add a pipette entering from the left at this height above the substrate, µm.
    #[arg(long)]
    pub pipette: Option<f64>,
    /// Instead of cells, a textured target at these stage heights, µm (a z-stack for
    /// `calibrate-depth`).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub stage_heights: Option<Vec<f64>>,
}

/// What truth.json holds.
#[derive(Serialize)]
struct Truth<'a> {
    optics: &'a Optics,
    seed: u64,
    calibration: &'a schemas::Calibration,
    /// Disparity per µm of height at the substrate.
    px_per_um_height: f64,
    disparity_range: [f64; 2],
    cells: &'a [synth::CellTruth],
}

fn other(msg: String) -> CliError {
    CliError::Other(msg)
}

fn save_grey(path: &Path, p: &Plane<u8>) -> Result<(), CliError> {
    io::write_mask_png(path, p).map_err(CliError::from)
}

fn write_scene(dir: &Path, scene: &Scene, prefix: &str) -> Result<synth::Rendered, CliError> {
    let r = scene.render();
    save_grey(&dir.join(format!("{prefix}left.png")), &r.left)?;
    save_grey(&dir.join(format!("{prefix}right.png")), &r.right)?;
    io::write_pfm(&dir.join(format!("{prefix}disparity.pfm")), &r.disparity)?;
    io::write_pfm(&dir.join(format!("{prefix}depth.pfm")), &r.depth)?;
    let labels = Plane::from_vec(
        r.labels.width,
        r.labels.height,
        r.labels
            .data
            .iter()
            .map(|&l| if l == synth::PIPETTE { 65535 } else { l })
            .collect(),
    )
    .expect("size");
    io::render::write_labels_png(&dir.join(format!("{prefix}mask.png")), &labels)?;
    let (lo, hi) = r
        .disparity
        .data
        .iter()
        .fold((f32::MAX, f32::MIN), |(a, b), &d| (a.min(d), b.max(d)));
    let t = Truth {
        optics: &scene.optics,
        seed: scene.seed,
        calibration: &r.calibration,
        px_per_um_height: scene.optics.px_per_um_height(),
        disparity_range: [lo as f64, hi as f64],
        cells: &r.cells,
    };
    let p = dir.join(format!("{prefix}truth.json"));
    std::fs::write(
        &p,
        serde_json::to_string_pretty(&t).expect("serialises") + "\n",
    )
    .map_err(|e| other(format!("cannot write '{}': {e}", p.display())))?;
    Ok(r)
}

/// Runs `microstereo synth`.
pub fn synth(a: SynthArgs) -> Result<(), CliError> {
    if a.width < 32 || a.height < 32 || a.width > 8192 || a.height > 8192 {
        return Err(other(format!(
            "image size {}×{} is out of range: use 32..8192 on each side",
            a.width, a.height
        )));
    }
    let positive = [
        ("--pixel-pitch", a.pixel_pitch),
        ("--magnification", a.magnification),
        ("--f-eff", a.f_eff),
        ("--baseline", a.baseline),
    ];
    if let Some((n, v)) = positive.iter().find(|(_, v)| !(*v > 0.0 && v.is_finite())) {
        return Err(other(format!("{n} {v} must be a positive number")));
    }
    if a.diameter.len() != 2 || a.cell_height.len() != 2 {
        return Err(other(
            "--diameter and --cell-height take two numbers, MIN,MAX (e.g. --diameter 20,100)"
                .into(),
        ));
    }
    if a.diameter[0] <= 0.0
        || a.diameter[0] > a.diameter[1]
        || a.cell_height[0] <= 0.0
        || a.cell_height[0] > a.cell_height[1]
    {
        return Err(other(format!(
            "--diameter {:?} and --cell-height {:?} must be positive MIN,MAX pairs with MIN ≤ MAX",
            a.diameter, a.cell_height
        )));
    }
    let texture = match &a.texture {
        Some(p) => Texture::Image(capture::image::load(p, "texture image")?.grey),
        None => Texture::Noise,
    };
    let optics = Optics {
        width: a.width,
        height: a.height,
        pixel_pitch: a.pixel_pitch,
        magnification: a.magnification,
        f_eff: a.f_eff,
        baseline: a.baseline,
    };
    let look = Look {
        noise: a.noise.max(0.0),
        blur: a.blur.max(0.0),
        texture,
        ..Look::default()
    };
    std::fs::create_dir_all(&a.output).map_err(|e| {
        other(format!(
            "cannot create output directory '{}': {e}",
            a.output.display()
        ))
    })?;
    let cal = optics.calibration();
    triangulate::calibration::write(&a.output.join("calibration.toml"), &cal, optics.pixel_pitch)?;
    if let Some(zs) = &a.stage_heights {
        let mut csv = String::from("left,right,z_um\n");
        for (i, &z) in zs.iter().enumerate() {
            let s = Scene::target(optics, look.clone(), z, a.seed + i as u64);
            let prefix = format!("z{i:02}_");
            write_scene(&a.output, &s, &prefix)?;
            csv += &format!("{prefix}left.png,{prefix}right.png,{z}\n");
        }
        std::fs::write(a.output.join("heights.csv"), csv)
            .map_err(|e| other(format!("cannot write heights.csv: {e}")))?;
        println!(
            "{} target pairs at stage heights {:?} µm; working distance {} µm; outputs in {}",
            zs.len(),
            zs,
            optics.working_distance(),
            a.output.display()
        );
        return Ok(());
    }
    let spec = CellSpec {
        count: a.cells,
        diameter: [a.diameter[0], a.diameter[1]],
        height: [a.cell_height[0], a.cell_height[1]],
        ..CellSpec::default()
    };
    let mut scene = Scene::random(optics, look, &spec, a.seed);
    if let Some(h) = a.pipette {
        let s = optics.um_per_px();
        scene.pipette = Some(Pipette {
            tip: [-0.5 * a.width as f64 * s + 20.0 * s, 0.0],
            height: h,
            tip_radius: 1.5,
            taper: 0.08,
            elevation: 0.0,
        });
    }
    if scene.cells.len() < a.cells {
        eprintln!(
            "warning: only {} of {} cells fit without overlapping",
            scene.cells.len(),
            a.cells
        );
    }
    let frames = a.frames.unwrap_or(0);
    if frames == 0 {
        let r = write_scene(&a.output, &scene, "")?;
        let (lo, hi) = r
            .disparity
            .data
            .iter()
            .fold((f32::MAX, f32::MIN), |(x, y), &d| (x.min(d), y.max(d)));
        println!(
            "{} cells; disparity {lo:.2}..{hi:.2} px ({:.3} px per µm of height); outputs in {}",
            r.cells.len(),
            optics.px_per_um_height(),
            a.output.display()
        );
    } else {
        for f in 0..frames {
            let step = 0.6 * optics.um_per_px() * a.width as f64 / frames.max(1) as f64;
            write_scene(
                &a.output,
                &scene.at_frame(f, a.drift, step),
                &format!("f{f:04}_"),
            )?;
        }
        println!(
            "{frames} frames of {} cells; outputs in {}",
            scene.cells.len(),
            a.output.display()
        );
    }
    Ok(())
}
