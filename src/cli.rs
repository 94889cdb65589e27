//! The `microstereo` command line: parses the flags and hands each command to its module.

use crate::error::CliError;
use clap::{Args, Parser, Subcommand};
use formats as io;
use std::path::PathBuf;

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
    Reconstruct(Box<crate::reconstruct::ReconstructArgs>),
    /// Compares a disparity map with ground truth (Middlebury figures).
    Eval(EvalArgs),
    /// Times every node of the stereo graph on cones and on a 1280×1024 pair.
    Bench(crate::bench::BenchArgs),
    /// Segments the cells of one image: labels, overlay, variance, histogram, cells.json.
    Segment(crate::segmentcmd::SegmentArgs),
    /// Renders a synthetic stereo-microscope scene (or sequence, or calibration z-stack) with ground truth.
    Synth(crate::synthcmd::SynthArgs),
    /// Fits the microscope's b·f_eff and disparity offset from pairs of a target at known stage heights.
    CalibrateDepth(crate::calibrate::CalibrateArgs),
    /// Calibrates both cameras and their relative pose from chessboard pairs: the calibration file rectify, triangulate and reconstruct read.
    CalibrateStereo(crate::calibstereo::CalibrateStereoArgs),
    /// Calibrates a stereo microscope (converging, nearly telecentric views) from a chessboard at known stage heights: the calibration file rectify, triangulate and reconstruct read.
    CalibrateMicroscope(crate::calibrate::CalibrateMicroscopeArgs),
    /// Registers the manipulator to the cameras: moves it through stops, finds the tip at each, fits device = M·scene + offset.
    CalibrateManipulator(crate::calibmanip::CalibrateManipulatorArgs),
    /// Imports a calibration file from OpenCV's stereo YAML or ROS camera_info, or exports one to them.
    Calibration(crate::calibfile::CalibrationArgs),
    /// Runs a launch file's graph, one process per node, and prints a summary at the end.
    Run(crate::run::RunArgs),
    /// Shows a running graph live: per node state, restarts, step times, CPU; per edge rate, drops, latency.
    Top(crate::top::TopArgs),
    /// Lists a running graph's edges, measures an edge's rate (hz) or prints its messages' headers (echo).
    Topic(crate::top::TopicArgs),
    /// Runs one node of a running graph as this process (started by `run`).
    #[command(hide = true)]
    Node(crate::run::NodeArgs),
    /// Times one edge: 0.3, 1.3 and 5 MP frames over iceoryx2 and over a Unix-domain socket.
    BenchTransport(crate::run::BenchTransportArgs),
    /// Lists a recording's channels, types, message counts, duration and rates.
    Inspect(crate::recording::InspectArgs),
    /// Runs the graph with recorded edges in place of the nodes that made them.
    Replay(crate::recording::ReplayArgs),
    /// Feeds one node its recorded inputs and compares its outputs with the recorded ones.
    TestNode(crate::recording::TestNodeArgs),
    /// Shows a recording in Rerun (or writes it as an .rrd file).
    View(crate::recording::ViewArgs),
}

/// Runs the CLI and returns the process exit code.
pub fn main() -> i32 {
    let cli = Cli::parse();
    // The commands that run a graph (its supervisor, each node) take the stop signals from
    // the start, before they make anything that would outlive them.
    if matches!(
        cli.command,
        Command::Run(_) | Command::Node(_) | Command::Replay(_)
    ) {
        runtime::signals::install();
    }
    if !matches!(
        cli.command,
        Command::Run(_)
            | Command::Node(_)
            | Command::Replay(_)
            | Command::TestNode(_)
            | Command::BenchTransport(_)
    ) {
        die_quietly_on_closed_stdout();
    }
    let result = match cli.command {
        Command::Reconstruct(a) => crate::reconstruct::reconstruct(*a),
        Command::Eval(a) => eval(a),
        Command::Bench(a) => crate::bench::bench(a),
        Command::BenchTransport(a) => crate::run::bench_transport(a),
        Command::Segment(a) => crate::segmentcmd::segment_cmd(a),
        Command::Synth(a) => crate::synthcmd::synth(a),
        Command::CalibrateDepth(a) => crate::calibrate::calibrate_depth(a),
        Command::CalibrateStereo(a) => crate::calibstereo::calibrate_stereo_cmd(a),
        Command::CalibrateMicroscope(a) => crate::calibrate::calibrate_microscope(a),
        Command::Calibration(a) => crate::calibfile::calibration_cmd(a),
        Command::CalibrateManipulator(a) => crate::calibmanip::calibrate_manipulator(a),
        Command::Run(a) => crate::run::run_cmd(a),
        Command::Node(a) => crate::run::node_cmd(a),
        // A watcher that outlived the run it watched takes the domain's memory with it.
        Command::Top(a) => crate::top::top(a).inspect(|_| {
            runtime::process::release_domain();
        }),
        Command::Topic(a) => crate::top::topic(a).inspect(|_| {
            runtime::process::release_domain();
        }),
        Command::Inspect(a) => crate::recording::inspect(a),
        Command::Replay(a) => crate::recording::replay(a),
        Command::TestNode(a) => crate::recording::test_node_cmd(a),
        Command::View(a) => crate::recording::view(a),
    };
    match result {
        Ok(()) => 0,
        Err(CliError::Reported(code)) => code,
        Err(CliError::Failed(e)) => {
            runtime::errln!("FAIL: {e}");
            1
        }
        Err(e) => {
            runtime::errln!("error: {e}");
            2
        }
    }
}

/// A one-shot command whose reader went away (`… | head -1`) ends as Unix tools do, by
/// SIGPIPE, instead of panicking in `println!`. Not for the commands that supervise
/// processes or serve sockets: there a closed peer must stay an error to handle.
fn die_quietly_on_closed_stdout() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: restores the default action of one signal; no handler runs Rust code, and it
    // is set before this process starts any thread of its own.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// Arguments of `microstereo eval`.
#[derive(Args, Debug)]
pub struct EvalArgs {
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

/// Runs `microstereo eval`.
pub fn eval(a: EvalArgs) -> Result<(), CliError> {
    // A NaN, infinite or zero scale turned every ground-truth pixel into NaN or infinity,
    // and the figures came out with exit 0.
    for (flag, s) in [
        ("--scale", a.scale),
        ("--gt-scale", a.gt_scale),
        ("--gt-right-scale", a.gt_right_scale),
    ] {
        if let Some(s) = s
            && !(s > 0.0 && s <= 1e6)
        {
            return Err(CliError::Other(format!(
                "{flag} {s} is not a scale: give the factor the PNG's values were multiplied by, above 0 and at most 1e6 (Middlebury: 4 for cones)"
            )));
        }
    }
    let disp = io::read_disparity(&a.disparity, a.scale, "disparity map")?;
    let gt = io::read_disparity(&a.gt, a.gt_scale, "ground truth")?;
    validate::eval::check_size(&disp, &a.disparity, &gt, &a.gt)?;
    let visible = match &a.gt_right {
        Some(p) => {
            let gr = io::read_disparity(p, a.gt_right_scale.or(a.gt_scale), "right ground truth")?;
            Some(validate::eval::visible_from_right(&gt, &gr, p)?)
        }
        None => None,
    };
    let f = validate::evaluate(&disp, &gt, visible.as_ref());
    if a.json {
        runtime::outln!("{}", serde_json::to_string_pretty(&f).expect("serialises"));
        return Ok(());
    }
    for line in validate::eval::table(&f, visible.is_some()) {
        runtime::outln!("{line}");
    }
    Ok(())
}
