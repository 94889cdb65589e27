//! `microstereo bench`: the stereo graph (match → validate → post-process) on cones and a
//! 1280×1024 pair, both matchers, each node timed by the in-process executor over a stream
//! of frames (as a live graph keeps its buffers from frame to frame).

use crate::error::CliError;
use clap::Args;
use pipelines::timing::bench_pairs;
use schemas::DisparityRange;
use std::path::PathBuf;

/// Arguments of `microstereo bench`.
#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Directory with the cones pair (im2.png, im6.png); default: the pair built into this
    /// program (tests/data/cones).
    #[arg(long)]
    cones: Option<PathBuf>,
    /// Runs per measurement (the median is reported), 1..=1000.
    #[arg(long, default_value_t = 5, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=1000))]
    repeat: usize,
    /// Write the results as JSON here too.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Also write the 1280×1024 pair as PNGs here (so other tools can time the same images).
    #[arg(long, conflicts_with = "cones_only")]
    write_pairs: Option<PathBuf>,
    /// Replace the files --json and --write-pairs name if they exist.
    #[arg(long)]
    overwrite: bool,
    /// Skip the 1280×1024 pair.
    #[arg(long)]
    cones_only: bool,
    /// SGM paths of quality mode: 4 (the default) or 8.
    #[arg(long, value_parser = clap::builder::TypedValueParser::map(clap::builder::PossibleValuesParser::new(["4", "8"]), |s: String| s.parse::<u8>().expect("4 or 8")))]
    paths: Option<u8>,
}

/// The 1280×1024 pair's files (`--write-pairs`).
const PAIR_NAMES: [&str; 2] = ["synth1280_left.png", "synth1280_right.png"];

/// The Middlebury cones pair (tests/data/cones, see its README), built in.
const CONES_LEFT: &[u8] = include_bytes!("../tests/data/cones/im2.png");
/// The right view of the built-in cones pair.
const CONES_RIGHT: &[u8] = include_bytes!("../tests/data/cones/im6.png");

/// Runs `microstereo bench`.
pub fn bench(a: BenchArgs) -> Result<(), CliError> {
    let mut outputs: Vec<PathBuf> = a.json.iter().cloned().collect();
    if let Some(d) = &a.write_pairs {
        outputs.extend(formats::outputs::in_dir(d, PAIR_NAMES));
    }
    let tmp = std::env::temp_dir().join(format!("microstereo-bench-{}", std::process::id()));
    let cones = match &a.cones {
        Some(c) => c.clone(),
        None => {
            // The pair built in, so that an installed program needs no checkout.
            let d = tmp.join("cones");
            std::fs::create_dir_all(&d)
                .map_err(|e| CliError::Other(format!("cannot create '{}': {e}", d.display())))?;
            for (name, bytes) in [("im2.png", CONES_LEFT), ("im6.png", CONES_RIGHT)] {
                std::fs::write(d.join(name), bytes).map_err(|e| {
                    CliError::Other(format!("cannot write '{}': {e}", d.join(name).display()))
                })?;
            }
            d
        }
    };
    let (l, r) = (cones.join("im2.png"), cones.join("im6.png"));
    formats::outputs::check(&outputs, &[&l, &r], a.overwrite, "choose other names")?;
    let dir = a.write_pairs.clone().unwrap_or_else(|| tmp.clone());
    let mut pairs = vec![("cones".to_string(), l, r)];
    if !a.cones_only {
        let s = synth::layers::standard_scene(1280, 1024, 4, 14, 7);
        std::fs::create_dir_all(&dir)
            .map_err(|e| CliError::Other(format!("cannot create '{}': {e}", dir.display())))?;
        let [left, right] = PAIR_NAMES.map(|n| dir.join(n));
        formats::write_mask_png(&left, &s.left)?;
        formats::write_mask_png(&right, &s.right)?;
        pairs.push(("synth1280".into(), left, right));
    }
    let result = bench_all(&a, &pairs);
    let _ = std::fs::remove_dir_all(&tmp);
    result
}

fn bench_all(a: &BenchArgs, pairs: &[(String, PathBuf, PathBuf)]) -> Result<(), CliError> {
    let range = DisparityRange::new(0, 63);
    let repeat = a.repeat.max(1);
    runtime::outln!(
        "{} threads; median of {repeat} runs; ranges 0..63 (64 disparities, as SGBM numDisparities=64)",
        rayon::current_num_threads(),
    );
    let lines = bench_pairs(pairs, range, repeat, a.paths, |l| {
        runtime::outln!("{}", l.summary());
    })
    .map_err(|e| CliError::with_flags(e, &[]))?;
    if let Some(p) = &a.json {
        formats::atomic::write_bytes(
            p,
            serde_json::to_string_pretty(&lines)
                .expect("serialises")
                .as_bytes(),
        )?;
    }
    Ok(())
}
