//! `microstereo run` (the graph as processes), `microstereo node` (one of them) and
//! `microstereo bench-transport`.

use crate::error::CliError;
use crate::graphopts::OutputOpts;
use clap::Args;
use runtime::launch::Graph;
use std::path::{Path, PathBuf};

/// Reads and validates a launch file against the built-in kinds; every problem becomes one
/// error.
pub fn load(path: &Path) -> Result<Graph, CliError> {
    Ok(pipelines::launch::load(path)?)
}

/// Reads and checks a launch file (`None`: the built-in default graph) with `overrides`
/// (`NODE.PARAM=VALUE`) applied first.
pub fn load_with(path: Option<&Path>, overrides: &[String]) -> Result<Graph, CliError> {
    Ok(pipelines::launch::load_with(path, overrides)?)
}

/// Arguments of `microstereo node` (as the supervisor starts it).
#[derive(Args, Debug)]
pub struct NodeArgs {
    /// The graph file the supervisor wrote.
    #[arg(long)]
    pub graph: PathBuf,
    /// The node's id in it.
    #[arg(long)]
    pub id: String,
    /// The running graph this node belongs to (names its shared memory).
    #[arg(long, default_value = "default")]
    pub instance: String,
    /// Stop after this many frames.
    #[arg(long)]
    pub frames: Option<u64>,
}

/// Runs one node of a running graph as this process.
pub fn node_cmd(a: NodeArgs) -> Result<(), CliError> {
    runtime::process::set_parent_death_signal();
    let args = runtime::process::NodeArgs {
        graph: a.graph,
        id: a.id,
        instance: a.instance,
        frames: a.frames,
        generation: runtime::process::generation_from_env()?,
    };
    let stats = runtime::process::run_graph_node(&pipelines::registry::builtin(), &args)?;
    runtime::process::print_stats(&stats);
    Ok(())
}

/// Arguments of `microstereo run`.
#[derive(Args, Debug)]
pub struct RunArgs {
    /// The launch file (default: the default graph, built into this program).
    pub launch: Option<PathBuf>,
    /// Overrides a node's parameter, checked as the file is: `NODE.PARAM=VALUE`
    /// (repeatable), e.g. `--set manipulator-bridge.listen=127.0.0.1:7879`.
    #[arg(long = "set", value_name = "NODE.PARAM=VALUE")]
    pub set: Vec<String>,
    /// Stop after this many frames (run until Ctrl-C without it).
    #[arg(long)]
    pub frames: Option<u64>,
    /// Run every node in this process instead, one after another for each frame (the
    /// executor `reconstruct` and the tests use), and print each node's step times and the
    /// frame rate: the yardstick for the processes' rate. Needs --frames; sources are not
    /// paced and no frame is dropped.
    #[arg(long, requires = "frames", conflicts_with_all = ["record", "viewer", "instance"])]
    pub in_process: bool,
    /// Run the nodes as processes, then the same nodes in one process (as --in-process),
    /// and print the processes' frame rate as a share of the in-process one (capped at a
    /// paced source's rate, which no graph fed by it can pass). Needs --frames.
    #[arg(long, requires = "frames", conflicts_with_all = ["in_process", "record", "viewer"])]
    pub compare: bool,
    /// How the processes are run.
    #[command(flatten)]
    pub supervision: Supervision,
    /// Recording of edges and the Rerun viewer.
    #[command(flatten)]
    pub out: OutputOpts,
}

/// How `run` and `replay` run a graph's processes.
#[derive(Args, Debug, Clone)]
pub struct Supervision {
    /// Seconds a node gets to end after SIGTERM before it is killed.
    #[arg(long, default_value_t = 3.0, allow_hyphen_values = true)]
    pub grace: f64,
    /// Names this run's shared memory (default: the supervisor's process id), so that
    /// graphs running side by side do not share edges; readers outside the graph use it.
    #[arg(long)]
    pub instance: Option<String>,
    /// No progress line while it runs (one is shown when stderr is a terminal: frames,
    /// frames/s, drops, restarts); `microstereo top` shows a running graph in full.
    #[arg(long, short)]
    pub quiet: bool,
    /// Run only this host's part of a graph split over hosts (`host = "NAME"` per node,
    /// `[hosts.NAME]` with the link's endpoints): its edges to the other hosts go over
    /// iceoryx2's Zenoh link, the rest stays shared memory.
    #[arg(long)]
    pub host: Option<String>,
    /// Zenoh endpoint this part's link listens on, e.g. `tcp/0.0.0.0:7447` (repeatable;
    /// replaces the launch file's `listen` and `connect`).
    #[arg(long, requires = "host")]
    pub listen: Vec<String>,
    /// Zenoh endpoint of another host's link to connect to, e.g. `tcp/capture-pc:7447`
    /// (repeatable; replaces the launch file's `listen` and `connect`).
    #[arg(long, requires = "host")]
    pub connect: Vec<String>,
    /// The iceoryx2 domain to run in: graphs in different domains share no memory, even on
    /// one machine (two parts of a graph on one machine, say). Default: $MICROSTEREO_DOMAIN,
    /// else the default domain.
    #[arg(long)]
    pub domain: Option<String>,
}

/// Runs `graph` as processes and prints the summary; returns the frame rate.
pub fn run_graph(
    graph: &Graph,
    frames: Option<u64>,
    s: &Supervision,
    out: &OutputOpts,
) -> Result<f64, CliError> {
    let endpoints = (!s.listen.is_empty() || !s.connect.is_empty()).then(|| hostlink::Endpoints {
        listen: s.listen.clone(),
        connect: s.connect.clone(),
    });
    let o = runtime::supervisor::RunOptions {
        builtin: vec![],
        frames,
        grace: s.grace,
        instance: s.instance.clone(),
        progress: !s.quiet,
        host: s.host.clone(),
        endpoints,
        controls: vec![],
    };
    let rec = out.recording();
    Ok(pipelines::processes::run(
        graph,
        o,
        s.domain.as_deref(),
        rec.as_ref(),
    )?)
}

/// Runs the graph: one process per node, logs prefixed, restarts, clean stop, summary.
pub fn run_cmd(a: RunArgs) -> Result<(), CliError> {
    a.out.check()?;
    let mut graph = load_with(a.launch.as_deref(), &a.set)?;
    if a.in_process {
        return run_in_process(&graph, a.frames.unwrap_or(1)).map(|_| ());
    }
    let alone_graph = a.compare.then(|| graph.clone());
    a.out.apply(&mut graph)?;
    let rate = run_graph(&graph, a.frames, &a.supervision, &a.out)?;
    if let Some(g) = alone_graph {
        let (alone, pace) = run_in_process(&g, a.frames.unwrap_or(1))?;
        // A camera of `pace` frames/s caps both runs: one process faster than the camera
        // could take no more frames from it than the processes can.
        let yardstick = pace.map_or(alone, |p| alone.min(p));
        let capped = match pace {
            Some(p) if p < alone => {
                format!(" unpaced, which the source's {p:.0} frames/s cap at {yardstick:.2}")
            }
            _ => String::new(),
        };
        runtime::outln!(
            "as processes {rate:.2} frames/s, in one process {alone:.2}{capped}: {:.2}× the in-process rate (the processes' sources keep their pace and their entrances drop what the graph cannot take; in one process every frame is taken in turn)",
            rate / yardstick.max(1e-9)
        );
    }
    Ok(())
}

/// Runs `graph` in this process for `frames` frames and prints per node the mean and 99th
/// percentile step time, then the frame rate and the CPU used. Returns the rate and the
/// pace of the graph's paced sources (which this run ignores).
fn run_in_process(graph: &Graph, frames: u64) -> Result<(f64, Option<f64>), CliError> {
    if frames == 0 {
        return Err(CliError::Other(
            "--frames 0 runs nothing: give at least 1".into(),
        ));
    }
    runtime::exec::run_timed(graph, &pipelines::registry::builtin(), frames)
        .map_err(CliError::Other)
}

/// Where `bench-transport` runs the two ends of the edge.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum BenchPlacement {
    /// Wherever the scheduler puts them.
    Free,
    /// Both pinned to one core.
    OneCore,
    /// Writer and reader pinned to two different cores.
    TwoCores,
    /// Each of the three, one table each.
    All,
}

/// Arguments of `microstereo bench-transport`.
#[derive(Args, Debug)]
pub struct BenchTransportArgs {
    /// Frames per size and transport (latency and throughput each).
    #[arg(long, default_value_t = 300)]
    pub frames: usize,
    /// Where the writer and the reader run.
    #[arg(long, value_enum, default_value_t = BenchPlacement::All)]
    pub placement: BenchPlacement,
}

/// Times one edge over iceoryx2 and over a Unix-domain socket for three frame sizes and
/// prints them side by side, with the ratios, for each placement of the two ends asked.
pub fn bench_transport(a: BenchTransportArgs) -> Result<(), CliError> {
    use runtime::hop::Placement;
    // Its edges live in this process: the domain's own memory goes with them.
    let _domain = runtime::process::ReleaseDomain;
    if a.frames < 2 {
        return Err(CliError::Other(format!(
            "--frames {} is too few to time; use at least 2",
            a.frames
        )));
    }
    let placements = match a.placement {
        BenchPlacement::Free => vec![Placement::Free],
        BenchPlacement::OneCore => vec![Placement::OneCore],
        BenchPlacement::TwoCores => vec![Placement::TwoCores],
        BenchPlacement::All => vec![Placement::OneCore, Placement::TwoCores, Placement::Free],
    };
    runtime::hop::print_tables(a.frames, &placements).map_err(CliError::Other)?;
    Ok(())
}
