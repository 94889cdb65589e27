//! `microstereo synth`: writes synthetic stereo-microscope scenes, sequences and z-stacks.

use crate::error::CliError;
use clap::Args;
use std::path::PathBuf;
use synth::request::Request;

/// Arguments of `microstereo synth`.
#[derive(Args, Debug)]
pub struct SynthArgs {
    /// Output directory (created if missing).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Replace the files of an earlier scene in the output directory.
    #[arg(long)]
    pub overwrite: bool,
    /// Texture cells with this real cell image instead of procedural noise.
    #[arg(long)]
    pub texture: Option<PathBuf>,
    /// The scene, sequence or z-stack asked for.
    #[command(flatten)]
    pub request: Request,
}

/// Runs `microstereo synth`.
pub fn synth(a: SynthArgs) -> Result<(), CliError> {
    let request = a.request.clone();
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
    if setup.microscope.is_none() {
        calibration::file::write(
            &a.output.join("calibration.toml"),
            &optics.calibration(),
            optics.pixel_pitch,
        )?;
    }
    let _progress = synth::progress::RenderProgress::start(
        (optics.width, optics.height, setup.scene_count()),
        std::time::Duration::from_secs(2),
        |line| runtime::errln!("{line}"),
    );
    if let Some(zs) = &a.request.stage_heights {
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
    match a.request.frames.unwrap_or(0) {
        0 => {
            let r = synth::files::write_scene(&a.output, &scene, "", setup.microscope.as_ref())?;
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
