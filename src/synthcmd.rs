//! `microstereo synth`: writes synthetic stereo-microscope scenes, sequences and z-stacks.

use crate::error::CliError;
use clap::Args;
use formats as io;
use schemas::Plane;
use std::path::{Path, PathBuf};
use synth::{CellSpec, Look, Optics, Pipette, Scene, Texture};

/// Arguments of `microstereo synth`.
#[derive(Args, Debug)]
pub struct SynthArgs {
    /// Output directory (created if missing).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Replace the files of an earlier scene in the output directory.
    #[arg(long)]
    pub overwrite: bool,
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
    /// Where the pipette's tip points, degrees from +x towards +y (0: in from the left).
    #[arg(
        long,
        default_value_t = 0.0,
        allow_hyphen_values = true,
        requires = "pipette"
    )]
    pub pipette_azimuth: f64,
    /// The tip's centre `X,Y` in µm from the image centre (default: 20 px in from the
    /// border it comes through).
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        requires = "pipette"
    )]
    pub pipette_tip: Option<Vec<f64>>,
    /// Numerical aperture for the pipette's defocus: blurred by its height from the focal
    /// plane (blur circle radius NA·Δz; 0: always sharp).
    #[arg(long, default_value_t = 0.0)]
    pub aperture: f64,
    /// Instead of cells, a textured target at these stage heights, µm (a z-stack for
    /// `calibrate-depth`).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub stage_heights: Option<Vec<f64>>,
    /// Appearance preset: `dic` (textured cells with relief, a faintly textured substrate)
    /// or `brightfield` (a textureless substrate under a gradient and vignetting, darker
    /// cells with a dark membrane rim). The flags below change single properties of it.
    #[arg(long, value_enum, default_value_t = LookPreset::Dic)]
    pub look: LookPreset,
    /// The substrate's disparity at the image centre, px (the microscope focused above it:
    /// positive; default 0, the focal plane on the substrate).
    #[arg(long, allow_hyphen_values = true)]
    pub substrate_disparity: Option<f64>,
    /// Substrate texture: none, faint or strong (default: the look's).
    #[arg(long, value_enum)]
    pub substrate_texture: Option<TextureLevel>,
    /// Substrate tilt about the y and the x axis, degrees (each at most 10).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub tilt: Option<Vec<f64>>,
    /// Lighting gradient across the field of view, grey levels.
    #[arg(long, allow_hyphen_values = true)]
    pub gradient: Option<f64>,
    /// Vignetting: the share of brightness lost at the corners (0..0.9).
    #[arg(long)]
    pub vignetting: Option<f64>,
    /// Darkening of the membrane rim where cells meet the substrate, grey levels (0..170).
    #[arg(long)]
    pub rim: Option<f64>,
    /// Cell height profile: dome (ellipsoid), cap (paraboloid), spread (flattened), flat (a plateau) or fried-egg (a raised nucleus on a thin spread cytoplasm).
    #[arg(long, value_enum, default_value_t = ProfileArg::Dome)]
    pub profile: ProfileArg,
    /// Outline irregularity: the largest amplitude of each of the radius's 2nd–4th
    /// harmonics, as a share of it (0..0.15; 0: ellipses).
    #[arg(long, default_value_t = 0.0)]
    pub irregular: f64,
    /// Scatter this many debris particles on the substrate.
    #[arg(long, default_value_t = 0)]
    pub debris: usize,
}

/// `--look` values.
#[derive(clap::ValueEnum, Clone, Copy, Debug)]
pub enum LookPreset {
    /// Textured cells with relief shading, a faintly textured substrate.
    Dic,
    /// A textureless substrate under uneven light, darker cells with a membrane rim.
    Brightfield,
}

/// `--substrate-texture` values.
#[derive(clap::ValueEnum, Clone, Copy, Debug)]
pub enum TextureLevel {
    /// No texture: only noise.
    None,
    /// The default faint texture.
    Faint,
    /// A strongly textured substrate.
    Strong,
}

/// `--profile` values.
#[derive(clap::ValueEnum, Clone, Copy, Debug)]
pub enum ProfileArg {
    /// Ellipsoidal dome.
    Dome,
    /// Paraboloid cap.
    Cap,
    /// Flattened spread cell.
    Spread,
    /// Flat-topped spread cell (a plateau, steep at the margin).
    Flat,
    /// Fried egg: a thin spread cytoplasm under a raised nucleus.
    FriedEgg,
}

fn other(msg: String) -> CliError {
    CliError::Other(msg)
}

fn save_grey(path: &Path, p: &Plane<u8>) -> Result<(), CliError> {
    io::write_mask_png(path, p).map_err(CliError::from)
}

/// The files [`write_scene`] writes for `prefix`.
fn scene_files(prefix: &str) -> [String; 6] {
    [
        "left.png",
        "right.png",
        "disparity.pfm",
        "depth.pfm",
        "mask.png",
        "truth.json",
    ]
    .map(|n| format!("{prefix}{n}"))
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
    let t = synth::truth::Truth::of(scene, &r);
    let p = dir.join(format!("{prefix}truth.json"));
    io::atomic::write_bytes(
        &p,
        (serde_json::to_string_pretty(&t).expect("serialises") + "\n").as_bytes(),
    )?;
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
    if a.diameter.len() != 2 || a.cell_height.len() != 2 {
        return Err(other(
            "--diameter and --cell-height take two numbers, MIN,MAX (e.g. --diameter 20,100)"
                .into(),
        ));
    }
    // Every number in a checked range, NaN and infinities included (a NaN passes no
    // comparison, so each test is written as "inside").
    // The optics: from a phone camera to a long-distance microscope (µm).
    let mut checked: Vec<(&str, f64, f64, f64)> = vec![
        ("--pixel-pitch", a.pixel_pitch, 0.01, 1000.0),
        ("--magnification", a.magnification, 0.01, 10_000.0),
        ("--f-eff", a.f_eff, 1.0, 1e7),
        ("--baseline", a.baseline, 0.1, 1e7),
        ("--diameter", a.diameter[0], 0.5, 2000.0),
        ("--diameter", a.diameter[1], 0.5, 2000.0),
        ("--cell-height", a.cell_height[0], 0.1, 1000.0),
        ("--cell-height", a.cell_height[1], 0.1, 1000.0),
        ("--noise", a.noise, 0.0, 100.0),
        ("--blur", a.blur, 0.0, 50.0),
        ("--aperture", a.aperture, 0.0, 1.5),
        ("--pipette-azimuth", a.pipette_azimuth, -360.0, 360.0),
        ("--drift", a.drift, 0.0, 100.0),
        ("--cells", a.cells as f64, 0.0, 10_000.0),
        ("--debris", a.debris as f64, 0.0, 100_000.0),
        ("--irregular", a.irregular, 0.0, 0.15),
    ];
    let optional = [
        ("--pipette", a.pipette, 0.0, 10_000.0),
        ("--frames", a.frames.map(|n| n as f64), 1.0, 100_000.0),
        ("--gradient", a.gradient, -170.0, 170.0),
        ("--vignetting", a.vignetting, 0.0, 0.9),
        ("--rim", a.rim, 0.0, 170.0),
        (
            "--substrate-disparity",
            a.substrate_disparity,
            -1000.0,
            1000.0,
        ),
    ];
    for (n, v, lo, hi) in optional {
        if let Some(v) = v {
            checked.push((n, v, lo, hi));
        }
    }
    for &z in a.stage_heights.iter().flatten() {
        checked.push(("--stage-heights", z, -10_000.0, 10_000.0));
    }
    if let Some((n, v, lo, hi)) = checked
        .iter()
        .find(|(_, v, lo, hi)| !(lo..=hi).contains(&v))
    {
        return Err(other(format!("{n} {v} is out of range: use {lo}..{hi}")));
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
    let mut look = match a.look {
        LookPreset::Dic => Look::default(),
        LookPreset::Brightfield => Look::brightfield(),
    };
    look.noise = a.noise;
    look.blur = a.blur;
    look.aperture = a.aperture;
    look.texture = texture;
    if let Some(t) = a.substrate_texture {
        look.substrate_texture = match t {
            TextureLevel::None => 0.0,
            TextureLevel::Faint => Look::default().substrate_texture,
            TextureLevel::Strong => 30.0,
        };
    }
    let tilt = match a.tilt.as_deref() {
        None => [0.0; 2],
        Some([x, y]) if x.abs() <= 10.0 && y.abs() <= 10.0 => {
            [x.to_radians().tan(), y.to_radians().tan()]
        }
        Some(t) => {
            return Err(other(format!(
                "--tilt {t:?} takes two angles in degrees, about y and about x, each within ±10 (e.g. --tilt 2,-1)"
            )));
        }
    };
    if let Some(g) = a.gradient {
        look.gradient = g;
    }
    if let Some(v) = a.vignetting {
        look.vignetting = v;
    }
    if let Some(r) = a.rim {
        look.rim = r;
    }
    let mut names = vec!["calibration.toml".to_string()];
    match (&a.stage_heights, a.frames.unwrap_or(0)) {
        (Some(zs), _) => {
            names.push("heights.csv".into());
            names.extend((0..zs.len()).flat_map(|i| scene_files(&format!("z{i:02}_"))));
        }
        (None, 0) => names.extend(scene_files("")),
        (None, n) => names.extend((0..n).flat_map(|f| scene_files(&format!("f{f:04}_")))),
    }
    formats::outputs::check(
        &formats::outputs::in_dir(&a.output, &names),
        &[],
        a.overwrite,
        "give -o another directory",
    )?;
    std::fs::create_dir_all(&a.output).map_err(|e| {
        other(format!(
            "cannot create output directory '{}': {e}",
            a.output.display()
        ))
    })?;
    let cal = optics.calibration();
    calibration::file::write(&a.output.join("calibration.toml"), &cal, optics.pixel_pitch)?;
    let scenes = match (&a.stage_heights, a.frames.unwrap_or(0)) {
        (Some(zs), _) => zs.len(),
        (None, n) => n.max(1),
    };
    let _progress = synth::progress::RenderProgress::start(
        (optics.width, optics.height, scenes),
        std::time::Duration::from_secs(2),
        |line| runtime::errln!("{line}"),
    );
    if let Some(zs) = &a.stage_heights {
        let mut csv = String::from("left,right,z_um\n");
        for (i, &z) in zs.iter().enumerate() {
            let s = Scene::target(optics, look.clone(), z, a.seed + i as u64);
            let prefix = format!("z{i:02}_");
            write_scene(&a.output, &s, &prefix)?;
            csv += &format!("{prefix}left.png,{prefix}right.png,{z}\n");
        }
        io::atomic::write_bytes(&a.output.join("heights.csv"), csv.as_bytes())?;
        runtime::outln!(
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
        profile: match a.profile {
            ProfileArg::Dome => synth::Profile::Dome,
            ProfileArg::Cap => synth::Profile::Cap,
            ProfileArg::Spread => synth::Profile::Spread,
            ProfileArg::Flat => synth::Profile::Flat,
            ProfileArg::FriedEgg => synth::Profile::FriedEgg,
        },
        irregular: a.irregular,
        ..CellSpec::default()
    };
    let mut scene = Scene::random(optics, look, &spec, a.seed);
    scene.tilt = tilt;
    if let Some(d) = a.substrate_disparity {
        scene = scene.with_substrate_disparity(d);
    }
    if a.debris > 0 {
        scene = scene.with_debris(a.debris, [1.0, 4.0], a.seed);
    }
    if let Some(h) = a.pipette {
        let tip = match &a.pipette_tip {
            Some(t) if t.len() != 2 || t.iter().any(|v| !v.is_finite() || v.abs() > 1e6) => {
                return Err(other(format!(
                    "--pipette-tip {t:?}: give X,Y in µm from the image centre (two finite numbers)"
                )));
            }
            Some(t) => Some([t[0], t[1]]),
            None => None,
        };
        scene.pipette = Some(Pipette::entering(&optics, h, a.pipette_azimuth, tip));
    }
    if let Some(why) = synth::shortfall(&scene, &spec) {
        runtime::errln!("warning: {why}");
    }
    let frames = a.frames.unwrap_or(0);
    if frames == 0 {
        let r = write_scene(&a.output, &scene, "")?;
        let (lo, hi) = r
            .disparity
            .data
            .iter()
            .fold((f32::MAX, f32::MIN), |(x, y), &d| (x.min(d), y.max(d)));
        runtime::outln!(
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
        runtime::outln!(
            "{frames} frames of {} cells; outputs in {}",
            scene.cells.len(),
            a.output.display()
        );
    }
    Ok(())
}
