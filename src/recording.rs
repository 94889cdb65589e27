//! Recordings from the command line: `inspect`, `replay`, `test-node` and `view`.

use crate::error::CliError;
use crate::graphopts::OutputOpts;
use clap::Args;
use pipelines::recording::usable;
use std::path::PathBuf;

/// Arguments of `microstereo view`.
#[derive(Args, Debug)]
pub struct ViewArgs {
    /// The recording.
    pub file: PathBuf,
    /// Write an .rrd file instead of showing it in a new viewer.
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// Send it to a running viewer (HOST:PORT).
    #[arg(long, conflicts_with = "output")]
    pub connect: Option<String>,
    /// Replace the --output file if it exists.
    #[arg(long, requires = "output")]
    pub overwrite: bool,
    /// Show every stage (label images, disparity maps and tiles), not only the camera
    /// frames, cells and 3D.
    #[arg(long)]
    pub all: bool,
}

/// Shows a recording in Rerun, through the viewer binary (the same code as `--viewer`).
pub fn view(a: ViewArgs) -> Result<(), CliError> {
    let (o, c) = (a.output.as_deref(), a.connect.as_deref());
    match pipelines::taps::view(&a.file, o, c, a.overwrite, a.all) {
        Err(pipelines::Error::ViewerExit(code)) => Err(CliError::Reported(code)),
        r => Ok(r?),
    }
}

/// Arguments of `microstereo inspect`.
#[derive(Args, Debug)]
pub struct InspectArgs {
    /// The recording.
    pub file: PathBuf,
}

/// Lists a recording's channels: type, messages, rate; says when the file is truncated.
pub fn inspect(a: InspectArgs) -> Result<(), CliError> {
    let o = recorder::overview(&a.file).map_err(|e| CliError::Other(e.to_string()))?;
    for line in o.table(&a.file) {
        runtime::outln!("{line}");
    }
    let problems: Vec<&String> = o.cut.iter().chain(&o.damaged).collect();
    match o.stopped(&a.file) {
        None if problems.is_empty() => Ok(()),
        None => {
            // Every damaged part but the last on its own line; the last is the error.
            let (last, rest) = problems.split_last().expect("not empty");
            for d in rest {
                runtime::errln!("{}: {d}", a.file.display());
            }
            Err(CliError::Other(format!(
                "{}: {last}; the figures above are the rest, read in full",
                a.file.display()
            )))
        }
        Some(why) => Err(CliError::Other(format!(
            "{why}; the figures above are what could be read"
        ))),
    }
}

/// Arguments of `microstereo replay`.
#[derive(Args, Debug)]
pub struct ReplayArgs {
    /// The recording.
    pub file: PathBuf,
    /// The launch file to run (default: the one stored in the recording).
    #[arg(long)]
    pub launch: Option<PathBuf>,
    /// Speed: 1.0 = as recorded, 2.0 = twice as fast, max = as fast as the graph goes.
    #[arg(long, default_value = "1.0")]
    pub rate: String,
    /// Start again at the end (frame numbers and times run on); until Ctrl-C or --frames.
    #[arg(long = "loop")]
    pub looped: bool,
    /// The nodes whose recorded outputs replace them.
    #[arg(long, num_args = 1.., default_value = "capture")]
    pub replace: Vec<String>,
    /// Stop after this many frames (default: the end of the recording).
    #[arg(long)]
    pub frames: Option<u64>,
    /// Seconds into the recording to start at (from its first frame's capture time).
    #[arg(long, default_value_t = 0.0)]
    pub start: f64,
    /// Seconds of the recording to replay (default: to its end).
    #[arg(long)]
    pub duration: Option<f64>,
    /// How the processes are run.
    #[command(flatten)]
    pub supervision: crate::run::Supervision,
    /// Recording and viewer of the replayed graph.
    #[command(flatten)]
    pub out: OutputOpts,
}

/// Runs a launch file's graph with recorded edges in place of the replaced nodes.
pub fn replay(a: ReplayArgs) -> Result<(), CliError> {
    let replay = pipelines::recording::Replay {
        replace: a.replace.clone(),
        rate: a.rate.clone(),
        looped: a.looped,
        window: (a.start, a.duration),
    };
    replay.check()?;
    let o = usable(&a.file)?;
    a.out.check()?;
    let mut graph = pipelines::recording::replay_graph(&a.file, &o, a.launch.as_deref(), &replay)?;
    a.out.apply(&mut graph)?;
    // A window of the recording ends with its last frame (the nodes take the end of the
    // stream from the source).
    let window = a.start > 0.0 || a.duration.is_some();
    let frames = match (a.frames, a.looped || window) {
        (Some(n), _) => Some(n),
        (None, true) => None,
        (None, false) => o.last_sequence.map(|s| s + 1),
    };
    crate::run::run_graph(&graph, frames, &a.supervision, &a.out).map(|_| ())
}

/// Arguments of `microstereo test-node`.
#[derive(Args, Debug)]
pub struct TestNodeArgs {
    /// The recording.
    pub file: PathBuf,
    /// The node's id.
    pub node: String,
    /// The launch file the node comes from (default: the one stored in the recording).
    #[arg(long)]
    pub launch: Option<PathBuf>,
    /// Largest difference allowed in float outputs (0: bit-exact).
    #[arg(long, default_value_t = 0.0)]
    pub tolerance: f32,
}

/// `microstereo test-node`: prints the comparison; exit 1 when an output differs.
pub fn test_node_cmd(a: TestNodeArgs) -> Result<(), CliError> {
    if !(a.tolerance >= 0.0 && a.tolerance.is_finite()) {
        return Err(CliError::Other(format!(
            "--tolerance {} must be a finite number ≥ 0",
            a.tolerance
        )));
    }
    let c = pipelines::recording::test_node(&a.file, a.launch.as_deref(), &a.node, a.tolerance)?;
    for line in c.lines(a.tolerance) {
        runtime::outln!("{line}");
    }
    if c.passed() {
        runtime::outln!("PASS");
        Ok(())
    } else if c.frames == 0 {
        Err(CliError::Other(format!(
            "{}: no frame of the recording holds all of the node's inputs and outputs",
            a.file.display()
        )))
    } else {
        Err(CliError::Failed(format!(
            "{}: outputs differ from the recording",
            c.node
        )))
    }
}
