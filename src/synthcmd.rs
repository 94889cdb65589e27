//! `microstereo synth`: writes synthetic stereo-microscope scenes, sequences and z-stacks.

use crate::error::CliError;
use clap::Args;
use std::path::PathBuf;
use synth::request::{LookPreset as Preset, Request, SubstrateTexture};

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

impl SynthArgs {
    /// The numbers these flags ask for.
    fn request(&self) -> Request {
        Request {
            width: self.width,
            height: self.height,
            cells: self.cells,
            diameter: self.diameter.clone(),
            cell_height: self.cell_height.clone(),
            seed: self.seed,
            noise: self.noise,
            blur: self.blur,
            pixel_pitch: self.pixel_pitch,
            magnification: self.magnification,
            f_eff: self.f_eff,
            baseline: self.baseline,
            frames: self.frames,
            drift: self.drift,
            pipette: self.pipette,
            pipette_azimuth: self.pipette_azimuth,
            pipette_tip: self.pipette_tip.clone(),
            aperture: self.aperture,
            stage_heights: self.stage_heights.clone(),
            look: match self.look {
                LookPreset::Dic => Preset::Dic,
                LookPreset::Brightfield => Preset::Brightfield,
            },
            substrate_disparity: self.substrate_disparity,
            substrate_texture: self.substrate_texture.map(|t| match t {
                TextureLevel::None => SubstrateTexture::None,
                TextureLevel::Faint => SubstrateTexture::Faint,
                TextureLevel::Strong => SubstrateTexture::Strong,
            }),
            tilt: self.tilt.clone(),
            gradient: self.gradient,
            vignetting: self.vignetting,
            rim: self.rim,
            profile: match self.profile {
                ProfileArg::Dome => synth::Profile::Dome,
                ProfileArg::Cap => synth::Profile::Cap,
                ProfileArg::Spread => synth::Profile::Spread,
                ProfileArg::Flat => synth::Profile::Flat,
                ProfileArg::FriedEgg => synth::Profile::FriedEgg,
            },
            irregular: self.irregular,
            debris: self.debris,
        }
    }
}

/// Runs `microstereo synth`.
pub fn synth(a: SynthArgs) -> Result<(), CliError> {
    let request = a.request();
    request.check()?;
    let texture = match &a.texture {
        Some(p) => synth::Texture::Image(capture::image::load(p, "texture image")?.grey),
        None => synth::Texture::Noise,
    };
    let setup = request.setup(texture)?;
    formats::outputs::check(
        &formats::outputs::in_dir(&a.output, synth::files::names(&setup)),
        &[],
        a.overwrite,
        "give -o another directory",
    )?;
    std::fs::create_dir_all(&a.output).map_err(|e| {
        CliError::Other(format!(
            "cannot create output directory '{}': {e}",
            a.output.display()
        ))
    })?;
    let optics = setup.optics;
    calibration::file::write(
        &a.output.join("calibration.toml"),
        &optics.calibration(),
        optics.pixel_pitch,
    )?;
    let _progress = synth::progress::RenderProgress::start(
        (optics.width, optics.height, setup.scene_count()),
        std::time::Duration::from_secs(2),
        |line| runtime::errln!("{line}"),
    );
    if let Some(zs) = &a.stage_heights {
        synth::files::write_stack(&a.output, &setup)?;
        runtime::outln!(
            "{} target pairs at stage heights {:?} µm; working distance {} µm; outputs in {}",
            zs.len(),
            zs,
            optics.working_distance(),
            a.output.display()
        );
        return Ok(());
    }
    let (scene, spec) = setup.cells()?;
    if let Some(why) = synth::shortfall(&scene, &spec) {
        runtime::errln!("warning: {why}");
    }
    match a.frames.unwrap_or(0) {
        0 => {
            let r = synth::files::write_scene(&a.output, &scene, "")?;
            let (lo, hi) = r.disparity_range();
            runtime::outln!(
                "{} cells; disparity {lo:.2}..{hi:.2} px ({:.3} px per µm of height); outputs in {}",
                r.cells.len(),
                optics.px_per_um_height(),
                a.output.display()
            );
        }
        frames => {
            synth::files::write_frames(&a.output, &setup, &scene)?;
            runtime::outln!(
                "{frames} frames of {} cells; outputs in {}",
                scene.cells.len(),
                a.output.display()
            );
        }
    }
    Ok(())
}
