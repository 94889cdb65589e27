//! Recordings from the command line: `run --record`, `inspect`, `replay` and `test-node`.
//!
//! Recording and replay change the graph the same way in every process: the supervisor
//! hands its [`GraphOpts`] to each node process, which applies them to the launch file it
//! reads ([`load_with`]), so all of them see one graph with a recorder tap or with replay
//! sources in place of the replaced nodes.

use crate::cli::CliError;
use crate::graph::{KINDS, build, kind_spec};
use clap::Args;
use recorder::file::{FrameReader, Overview};
use recorder::node::{RECORDER_KIND, REPLAY_KIND, ReplayNode, ReplayParams, check_channels};
use runtime::launch::{Graph, LaunchFile, NodeSpec, Runner};
use runtime::step::{Collected, GraphNode, Msg};
use schemas::{FrameHeader, MessageKind, PixelFormat};
use std::io::BufRead;
use std::path::{Path, PathBuf};

/// The recorder's node id in a graph run with `--record`.
pub const RECORDER_ID: &str = "recorder";

/// The Rerun viewer tap's node id in a graph run with `--viewer`.
pub const VIEWER_ID: &str = "viewer";

/// The viewer binary: next to this program (`cargo build --release -p viewer` builds it;
/// it alone links rerun).
pub fn viewer_exe() -> PathBuf {
    std::env::current_exe()
        .ok()
        .and_then(|p| p.parent().map(|d| d.join("microstereo-viewer")))
        .unwrap_or_else(|| PathBuf::from("microstereo-viewer"))
}

fn check_viewer_words(w: &[String]) -> Result<(), String> {
    match w {
        [m] if m == "spawn" => Ok(()),
        [m, _] if m == "connect" || m == "save" => Ok(()),
        _ => Err(format!(
            "--viewer {}: give spawn, connect HOST:PORT or save FILE.rrd",
            w.join(" ")
        )),
    }
}

/// Checks, before anything starts, that `--viewer` can work: the viewer binary is built,
/// a viewer to spawn is installed, a viewer to connect to is listening, a file to save
/// does not exist yet.
pub fn check_viewer_target(opts: &OutputOpts) -> Result<(), CliError> {
    if opts.viewer.is_empty() {
        return Ok(());
    }
    check_viewer_words(&opts.viewer).map_err(CliError::Other)?;
    let exe = viewer_exe();
    if !exe.is_file() {
        return Err(CliError::Other(format!(
            "--viewer needs {}, which is not built; run `cargo build --release -p viewer` (it holds the rerun dependency)",
            exe.display()
        )));
    }
    match opts.viewer[0].as_str() {
        "spawn" => {
            let found = std::env::var_os("PATH")
                .is_some_and(|p| std::env::split_paths(&p).any(|d| d.join("rerun").is_file()));
            if !found {
                return Err(CliError::Other(
                    "--viewer spawn starts the `rerun` viewer, which is not on PATH; install it with `pip install rerun-sdk==0.36.*`, or use --viewer save FILE.rrd".into(),
                ));
            }
        }
        "connect" => {
            let addr = &opts.viewer[1];
            let hp = addr
                .split_once("://")
                .map_or(addr.as_str(), |(_, r)| r)
                .split('/')
                .next()
                .unwrap_or(addr);
            let reachable = std::net::ToSocketAddrs::to_socket_addrs(hp)
                .ok()
                .and_then(|mut a| a.next())
                .is_some_and(|a| {
                    std::net::TcpStream::connect_timeout(&a, std::time::Duration::from_secs(2))
                        .is_ok()
                });
            if !reachable {
                return Err(CliError::Other(format!(
                    "--viewer connect {addr}: no Rerun viewer is listening there; start one with `rerun` (it listens on 127.0.0.1:9876) or use --viewer spawn"
                )));
            }
        }
        _ => {
            let path = Path::new(&opts.viewer[1]);
            if path.exists() {
                return Err(CliError::Other(format!(
                    "--viewer save {}: the file exists; choose another name",
                    path.display()
                )));
            }
        }
    }
    Ok(())
}

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
}

/// Shows a recording in Rerun, through the viewer binary (the same code as `--viewer`).
pub fn view(a: ViewArgs) -> Result<(), CliError> {
    let viewer = match (&a.output, &a.connect) {
        (Some(p), _) => vec!["save".into(), p.display().to_string()],
        (None, Some(c)) => vec!["connect".into(), c.clone()],
        (None, None) => vec!["spawn".into()],
    };
    check_viewer_target(&OutputOpts {
        viewer,
        ..OutputOpts::default()
    })?;
    // The viewer binary checks the recording itself before it shows anything.
    let mut cmd = std::process::Command::new(viewer_exe());
    cmd.arg("view").arg(&a.file);
    if let Some(o) = &a.output {
        cmd.arg("-o").arg(o);
    } else if let Some(c) = &a.connect {
        cmd.arg("--connect").arg(c);
    }
    let status = cmd
        .status()
        .map_err(|e| CliError::Other(format!("cannot run {}: {e}", viewer_exe().display())))?;
    match status.code() {
        Some(0) => Ok(()),
        Some(code) => Err(CliError::Reported(code)),
        None => Err(CliError::Other(format!("the viewer failed ({status})"))),
    }
}

/// Where a run's edges go besides the graph: a recording, a Rerun viewer.
#[derive(Args, Debug, Clone, Default)]
pub struct OutputOpts {
    /// Record the graph's edges into this MCAP file (ros2 profile, CDR messages).
    #[arg(long)]
    pub record: Option<PathBuf>,
    /// Record only the edges that match one of these (NODE/OUTPUT, `*` for any
    /// characters, e.g. 'rectify/*' '*/disparity').
    #[arg(long, num_args = 1.., requires = "record")]
    pub edges: Vec<String>,
    /// Replace the file given to --record if it exists.
    #[arg(long, requires = "record")]
    pub overwrite: bool,
    /// Show the graph in Rerun: `spawn` a viewer, `connect HOST:PORT` to a running one, or
    /// `save FILE.rrd` (needs the viewer binary: cargo build --release -p viewer).
    #[arg(long, num_args = 1..=2, value_names = ["MODE", "WHERE"])]
    pub viewer: Vec<String>,
}

/// How a run changes its launch file's graph: a recorder tap, a viewer tap, replay sources.
#[derive(Args, Debug, Clone, Default)]
pub struct GraphOpts {
    /// Recording and viewer.
    #[command(flatten)]
    pub out: OutputOpts,
    /// Replay this recording in place of the --replace nodes (set by `replay`).
    #[arg(long, hide = true)]
    pub replay: Option<PathBuf>,
    /// The nodes whose outputs are replayed.
    #[arg(long, hide = true, num_args = 1..)]
    pub replace: Vec<String>,
    /// Replay speed.
    #[arg(long, hide = true, default_value = "1.0")]
    pub rate: String,
    /// Replay in a loop.
    #[arg(long = "loop", hide = true)]
    pub looped: bool,
}

impl GraphOpts {
    /// The same options as arguments for a node process.
    pub fn to_args(&self) -> Vec<String> {
        let mut v = Vec::new();
        let out = &self.out;
        if let Some(r) = &out.record {
            v.push("--record".into());
            v.push(r.display().to_string());
            if !out.edges.is_empty() {
                v.push("--edges".into());
                v.extend(out.edges.iter().cloned());
            }
            if out.overwrite {
                v.push("--overwrite".into());
            }
        }
        if !out.viewer.is_empty() {
            v.push("--viewer".into());
            v.extend(out.viewer.iter().cloned());
        }
        if let Some(r) = &self.replay {
            v.push("--replay".into());
            v.push(r.display().to_string());
            v.push("--replace".into());
            v.extend(self.replace.iter().cloned());
            v.push("--rate".into());
            v.push(self.rate.clone());
            if self.looped {
                v.push("--loop".into());
            }
        }
        v
    }

    /// Applies the options to `graph`: replay sources first, then the recorder, so that a
    /// replayed run can be recorded again.
    pub fn apply(&self, graph: &mut Graph) -> Result<(), String> {
        if let Some(file) = &self.replay {
            let params = toml::Table::from_iter([
                (
                    "file".to_string(),
                    toml::Value::String(file.display().to_string()),
                ),
                ("rate".to_string(), toml::Value::String(self.rate.clone())),
                ("loop".to_string(), toml::Value::Boolean(self.looped)),
            ]);
            graph.replace_with_sources(&self.replace, REPLAY_KIND, &params)?;
        }
        let out = &self.out;
        if let Some(path) = &out.record {
            let params = toml::Table::from_iter([
                (
                    "path".to_string(),
                    toml::Value::String(path.display().to_string()),
                ),
                ("overwrite".to_string(), toml::Value::Boolean(out.overwrite)),
            ]);
            graph.add_tap(RECORDER_ID, RECORDER_KIND, &out.edges, params)?;
        }
        if !out.viewer.is_empty() {
            check_viewer_words(&out.viewer)?;
            let words = out
                .viewer
                .iter()
                .cloned()
                .map(toml::Value::String)
                .collect();
            let params =
                toml::Table::from_iter([("target".to_string(), toml::Value::Array(words))]);
            graph.add_tap(VIEWER_ID, "viewer", &[], params)?;
            let n = graph.nodes.last_mut().expect("added");
            n.runner = Runner::Exec(viewer_exe());
        }
        Ok(())
    }
}

/// Reads a launch file and applies `opts` to its graph.
pub fn load_with(path: &Path, opts: &GraphOpts) -> Result<Graph, CliError> {
    let mut g = crate::graph::load(path)?;
    opts.apply(&mut g).map_err(CliError::Other)?;
    Ok(g)
}

/// Builds the node value of any node of a graph, replay sources included.
pub fn build_spec(spec: &NodeSpec) -> Result<Box<dyn GraphNode>, String> {
    match &spec.runner {
        Runner::Builtin(k) if k == REPLAY_KIND => {
            let p: ReplayParams = runtime::step::params(&spec.params)?;
            let outputs: Vec<String> = spec.outputs.iter().map(|(p, _)| p.clone()).collect();
            Ok(Box::new(ReplayNode::new(p, &outputs)?))
        }
        Runner::Builtin(k) => build(k, &spec.params),
        Runner::Exec(p) => Err(format!(
            "node '{}' runs '{}', which cannot run in-process",
            spec.id,
            p.display()
        )),
    }
}

/// Checks, before anything starts, that `--record` can create its file.
pub fn check_record_target(opts: &OutputOpts) -> Result<(), CliError> {
    let Some(path) = &opts.record else {
        return Ok(());
    };
    if path.exists() && !opts.overwrite {
        return Err(CliError::Other(format!(
            "--record {}: the file exists; choose another name or add --overwrite",
            path.display()
        )));
    }
    let dir = path
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    if !dir.is_dir() {
        return Err(CliError::Other(format!(
            "--record {}: the folder {} does not exist; create it first",
            path.display(),
            dir.display()
        )));
    }
    Ok(())
}

/// Reads the channel overview of a recording; a file that cannot be read to its end is an
/// error that says what was read.
fn readable(path: &Path) -> Result<Overview, CliError> {
    let o = recorder::overview(path).map_err(|e| CliError::Other(e.to_string()))?;
    if let Some(why) = stopped(path, &o) {
        return Err(CliError::Other(format!(
            "{why}; `microstereo inspect {}` shows what it holds",
            path.display()
        )));
    }
    Ok(o)
}

/// Why reading `path` stopped before its end, if it did.
fn stopped(path: &Path, o: &Overview) -> Option<String> {
    o.error.as_ref().map(|e| {
        format!(
            "{}: {e}{}",
            path.display(),
            if o.truncated {
                " (the file is truncated: its recorder did not close it)"
            } else {
                ""
            }
        )
    })
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
    let (first, last) = o.channels.iter().fold((u64::MAX, 0u64), |(f, l), c| {
        (f.min(c.first_ns), l.max(c.last_ns))
    });
    let span = if o.channels.is_empty() {
        0.0
    } else {
        (last - first) as f64 / 1e9
    };
    let total: u64 = o.channels.iter().map(|c| c.messages).sum();
    let bytes: u64 = o.channels.iter().map(|c| c.bytes).sum();
    println!("{}", a.file.display());
    println!(
        "  {total} messages on {} channels, {:.2} s, frames {}–{}, {:.1} MB of CDR data",
        o.channels.len(),
        span,
        o.first_sequence.map_or("-".into(), |s| s.to_string()),
        o.last_sequence.map_or("-".into(), |s| s.to_string()),
        bytes as f64 / 1e6,
    );
    if let Some((path, _)) = &o.launch {
        println!("  launch file: {path} (stored in the recording)");
    }
    let w = o
        .channels
        .iter()
        .map(|c| c.topic.chars().count())
        .max()
        .unwrap_or(5)
        .max(5);
    let tw = o
        .channels
        .iter()
        .map(|c| c.schema.chars().count())
        .max()
        .unwrap_or(4)
        .max(4);
    println!(
        "  {:<w$} {:<tw$} {:>8} {:>9} {:>10}",
        "topic", "type", "messages", "rate Hz", "MB"
    );
    for c in &o.channels {
        let dt = (c.last_ns - c.first_ns) as f64 / 1e9;
        let rate = if c.messages > 1 && dt > 0.0 {
            format!("{:.2}", (c.messages - 1) as f64 / dt)
        } else {
            "-".into()
        };
        println!(
            "  {:<w$} {:<tw$} {:>8} {:>9} {:>10.2}",
            c.topic,
            c.schema,
            c.messages,
            rate,
            c.bytes as f64 / 1e6
        );
    }
    match stopped(&a.file, &o) {
        None => Ok(()),
        Some(why) => Err(CliError::Other(format!(
            "{why}; the figures above are what could be read"
        ))),
    }
}

/// Writes the launch file stored in a recording to a temporary file (node processes read
/// their graph from a file).
fn stored_launch(path: &Path, o: &Overview) -> Result<PathBuf, CliError> {
    let Some((from, text)) = &o.launch else {
        return Err(CliError::Other(format!(
            "{} holds no launch file; give one with --launch",
            path.display()
        )));
    };
    let out = std::env::temp_dir().join(format!(
        "microstereo-launch-{}-{}.toml",
        std::process::id(),
        Path::new(from)
            .file_stem()
            .map_or("recorded".into(), |s| s.to_string_lossy())
    ));
    std::fs::write(&out, text).map_err(|e| {
        CliError::Other(format!(
            "cannot write the recording's launch file to {}: {e}",
            out.display()
        ))
    })?;
    Ok(out)
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
    /// Seconds a node gets to end after SIGTERM before it is killed.
    #[arg(long, default_value_t = 3.0)]
    pub grace: f64,
    /// Names this run's shared memory (default: the supervisor's process id).
    #[arg(long)]
    pub instance: Option<String>,
    /// Recording and viewer of the replayed graph.
    #[command(flatten)]
    pub out: OutputOpts,
}

/// Runs a launch file's graph with recorded edges in place of the replaced nodes.
pub fn replay(a: ReplayArgs) -> Result<(), CliError> {
    recorder::node::Rate::parse(&a.rate).map_err(|e| CliError::Other(format!("--rate: {e}")))?;
    let o = readable(&a.file)?;
    let (launch, temporary) = match &a.launch {
        Some(l) => (l.clone(), false),
        None => (stored_launch(&a.file, &o)?, true),
    };
    let result = replay_with(&a, &o, launch.clone());
    if temporary {
        let _ = std::fs::remove_file(&launch);
    }
    result
}

fn replay_with(a: &ReplayArgs, o: &Overview, launch: PathBuf) -> Result<(), CliError> {
    let file = std::path::absolute(&a.file).unwrap_or(a.file.clone());
    let opts = GraphOpts {
        out: a.out.clone(),
        replay: Some(file),
        replace: a.replace.clone(),
        rate: a.rate.clone(),
        looped: a.looped,
    };
    check_record_target(&opts.out)?;
    let base = crate::graph::load(&launch)?;
    let mut replaced: Vec<(String, MessageKind)> = Vec::new();
    for id in &a.replace {
        if base.node(id).is_none() {
            return Err(CliError::Other(format!(
                "--replace {id}: {} has no node '{id}'",
                launch.display()
            )));
        }
        replaced.extend(base.output_edges(id));
    }
    check_channels(&a.file, o, &replaced).map_err(CliError::Other)?;
    let frames = match (a.frames, a.looped) {
        (Some(n), _) => Some(n),
        (None, true) => None,
        (None, false) => o.last_sequence.map(|s| s + 1),
    };
    crate::graph::run_cmd(crate::graph::RunArgs {
        launch,
        frames,
        grace: a.grace,
        instance: a.instance.clone(),
        opts,
    })
}

/// What `test-node` found on one output.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct OutputCheck {
    /// `NODE/OUTPUT`.
    pub edge: String,
    /// Frames compared.
    pub compared: u64,
    /// Frames whose header and payload are bit-identical to the recording.
    pub identical: u64,
    /// Frames that differ only by float values within the tolerance.
    pub within_tolerance: u64,
    /// Largest difference of a float value, or of a byte, seen.
    pub max_diff: f64,
    /// The first difference found, described.
    pub first_difference: Option<String>,
}

/// What `test-node` found.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NodeCheck {
    /// The node.
    pub node: String,
    /// Frames the node stepped on.
    pub frames: u64,
    /// Frames the recording holds only in part (skipped).
    pub incomplete: u64,
    /// Per output.
    pub outputs: Vec<OutputCheck>,
}

impl NodeCheck {
    /// Whether every compared frame matched.
    pub fn passed(&self) -> bool {
        self.frames > 0
            && self.outputs.iter().all(|o| {
                o.compared == self.frames && o.identical + o.within_tolerance == o.compared
            })
    }
}

/// Compares one produced message with the recorded one.
fn compare(
    out: &mut OutputCheck,
    got: (&FrameHeader, &[u8]),
    want: (&FrameHeader, &[u8]),
    tolerance: f32,
    ignore_time: bool,
) {
    out.compared += 1;
    let norm = |h: &FrameHeader| FrameHeader {
        edge_sequence: 0,
        capture_ns: if ignore_time { 0 } else { h.capture_ns },
        ..*h
    };
    let (gh, wh) = (norm(got.0), norm(want.0));
    if gh != wh {
        out.first_difference.get_or_insert_with(|| {
            format!("frame {}: header {gh:?} ≠ recorded {wh:?}", wh.sequence)
        });
        return;
    }
    if got.1 == want.1 {
        out.identical += 1;
        return;
    }
    let floats = PixelFormat::from_u32(wh.format) == Some(PixelFormat::F32)
        && got.1.len() == want.1.len()
        && got.1.len().is_multiple_of(4);
    let mut worst = 0f64;
    let mut first = None;
    if floats {
        for (i, (a, b)) in got
            .1
            .chunks_exact(4)
            .zip(want.1.chunks_exact(4))
            .enumerate()
        {
            let a = f32::from_le_bytes([a[0], a[1], a[2], a[3]]);
            let b = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            let d = if a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()) {
                0.0
            } else if a.is_finite() && b.is_finite() {
                f64::from((a - b).abs())
            } else {
                f64::INFINITY
            };
            if d > worst {
                worst = d;
                first.get_or_insert(format!("value {i}: {a} ≠ recorded {b}"));
            }
        }
    } else {
        let i = got.1.iter().zip(want.1).position(|(a, b)| a != b);
        worst = f64::INFINITY;
        first = Some(match i {
            Some(i) => format!(
                "byte {i} differs ({} bytes against {})",
                got.1.len(),
                want.1.len()
            ),
            None => format!("{} bytes against {}", got.1.len(), want.1.len()),
        });
    }
    out.max_diff = out.max_diff.max(worst);
    if floats && worst <= f64::from(tolerance) {
        out.within_tolerance += 1;
    } else {
        out.first_difference
            .get_or_insert_with(|| format!("frame {}: {}", wh.sequence, first.unwrap_or_default()));
    }
}

/// Feeds node `id` of the recording's graph (or of `launch`) its recorded inputs and
/// compares what it sends with the recorded outputs. A source makes frames 0, 1, … and is
/// compared without capture times (wall clock); the manipulator bridge is checked by what
/// it serves a controller over TCP, against the targets it was given.
pub fn test_node(
    file: &Path,
    launch: Option<&Path>,
    id: &str,
    tolerance: f32,
) -> Result<NodeCheck, CliError> {
    let o = readable(file)?;
    let (lpath, text) = match launch {
        Some(l) => (
            l.to_path_buf(),
            std::fs::read_to_string(l).map_err(|e| {
                CliError::Other(format!("cannot read the launch file {}: {e}", l.display()))
            })?,
        ),
        None => o
            .launch
            .clone()
            .map(|(p, t)| (PathBuf::from(p), t))
            .ok_or_else(|| {
                CliError::Other(format!(
                    "{} holds no launch file; give one with --launch",
                    file.display()
                ))
            })?,
    };
    let graph = LaunchFile::parse(&lpath, &text)
        .and_then(|f| f.validate(&kind_spec, KINDS))
        .map_err(|e| CliError::Other(e.to_string()))?;
    let spec = graph.node(id).ok_or_else(|| {
        CliError::Other(format!(
            "no node '{id}' in {}; its nodes: {}",
            lpath.display(),
            graph
                .nodes
                .iter()
                .map(|n| n.id.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        ))
    })?;
    let Runner::Builtin(kind) = &spec.runner else {
        return Err(CliError::Other(format!(
            "node '{id}' is an exec node; test-node runs built-in kinds"
        )));
    };
    let bridge = kind == "manipulator-bridge";
    // Feedback inputs carry whatever was newest when the node ran: not replayable.
    let inputs: Vec<(String, MessageKind)> = graph
        .input_edges(id)
        .into_iter()
        .zip(&spec.inputs)
        .filter(|(_, i)| !i.feedback)
        .map(|(e, _)| e)
        .collect();
    // The bridge's state follows the wall clock (device polling): its check is what it
    // serves over TCP.
    let outputs: Vec<(String, MessageKind)> = graph
        .output_edges(id)
        .into_iter()
        .filter(|(_, k)| !(bridge && *k == MessageKind::ManipulatorState))
        .collect();
    let all: Vec<(String, MessageKind)> = inputs.iter().chain(&outputs).cloned().collect();
    check_channels(file, &o, &all).map_err(CliError::Other)?;
    let mut params = spec.params.clone();
    let mut served = None;
    if bridge {
        // Never the production port: the system picks a free one.
        params.insert("listen".into(), toml::Value::String("127.0.0.1:0".into()));
    }
    let mut node: Box<dyn GraphNode> = if bridge {
        let b = manipulator_bridge::node::BridgeNode::new(
            &manipulator_bridge::node::BridgeParams::from_table(&params)
                .map_err(CliError::Other)?,
        )
        .map_err(CliError::Other)?;
        let client = std::net::TcpStream::connect(b.addr)
            .map_err(|e| CliError::Other(format!("cannot connect to the bridge: {e}")))?;
        client
            .set_read_timeout(Some(std::time::Duration::from_secs(10)))
            .map_err(|e| CliError::Other(e.to_string()))?;
        served = Some(std::io::BufReader::new(client));
        // The bridge takes controllers on its own thread: wait until it holds this one.
        let t0 = std::time::Instant::now();
        while b.controllers() == 0 {
            if t0.elapsed() > std::time::Duration::from_secs(10) {
                return Err(CliError::Other(
                    "the bridge did not take a controller within 10 s".into(),
                ));
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        Box::new(b)
    } else {
        build(kind, &params).map_err(CliError::Other)?
    };
    let mut check = NodeCheck {
        node: id.into(),
        outputs: outputs
            .iter()
            .map(|(e, _)| OutputCheck {
                edge: e.clone(),
                ..OutputCheck::default()
            })
            .collect(),
        ..NodeCheck::default()
    };
    if bridge {
        check.outputs.push(OutputCheck {
            edge: "TCP lines".into(),
            ..OutputCheck::default()
        });
    }
    let edges: Vec<String> = all.iter().map(|(e, _)| e.clone()).collect();
    let mut frames = FrameReader::open(file, edges).map_err(|e| CliError::Other(e.to_string()))?;
    let source = inputs.is_empty();
    // Each frame holds the inputs' messages, then the outputs'.
    for f in frames.by_ref() {
        let f = f.map_err(|e| CliError::Other(e.to_string()))?;
        let seq = f[0].header.sequence;
        let mut out = Collected::default();
        if source {
            if !node.produce(seq, &mut out).map_err(CliError::Other)? {
                break;
            }
        } else {
            let msgs: Vec<Msg<'_>> = f[..inputs.len()]
                .iter()
                .map(|m| Msg {
                    header: m.header,
                    payload: &m.payload,
                })
                .collect();
            node.step(&msgs, &mut out)
                .map_err(|e| CliError::Other(format!("{id}, frame {seq}: {e}")))?;
        }
        check.frames += 1;
        for (port, want) in f[inputs.len()..].iter().enumerate() {
            let c = &mut check.outputs[port];
            match out.ports.get(port).and_then(|p| p.first()) {
                Some((h, p)) => {
                    compare(c, (h, p), (&want.header, &want.payload), tolerance, source)
                }
                None => {
                    c.compared += 1;
                    c.first_difference
                        .get_or_insert_with(|| format!("frame {seq}: nothing sent"));
                }
            }
        }
        if let Some(r) = served.as_mut() {
            let want = &f[0];
            let mut line = String::new();
            let c = check.outputs.last_mut().expect("pushed");
            c.compared += 1;
            match r.read_line(&mut line) {
                Ok(_)
                    if line
                        .trim_end_matches('\n')
                        .strip_prefix("{\"event\":\"scene\",")
                        .is_some_and(|rest| rest.as_bytes() == &want.payload[1..]) =>
                {
                    c.identical += 1
                }
                Ok(_) => {
                    c.first_difference.get_or_insert_with(|| {
                        format!("frame {seq}: served a line other than the targets given")
                    });
                }
                Err(e) => {
                    c.first_difference
                        .get_or_insert_with(|| format!("frame {seq}: nothing served ({e})"));
                }
            }
        }
    }
    check.incomplete = frames.incomplete;
    Ok(check)
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
    let c = test_node(&a.file, a.launch.as_deref(), &a.node, a.tolerance)?;
    println!(
        "{}: {} frame(s) stepped on recorded inputs{}",
        c.node,
        c.frames,
        if c.incomplete > 0 {
            format!(", {} recorded only in part (skipped)", c.incomplete)
        } else {
            String::new()
        }
    );
    for o in &c.outputs {
        println!(
            "  {:<28} {:>4} compared {:>4} identical {:>4} within ±{}  max diff {}{}",
            o.edge,
            o.compared,
            o.identical,
            o.within_tolerance,
            a.tolerance,
            o.max_diff,
            o.first_difference
                .as_ref()
                .map_or(String::new(), |d| format!("  first: {d}"))
        );
    }
    if c.passed() {
        println!("PASS");
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
