//! The process graph from the command line: the built-in node kinds, `microstereo node`
//! (one node as a process) and `microstereo run` (the supervisor).

use crate::cli::CliError;
use clap::Args;
use runtime::launch::{Graph, KindSpec, LaunchFile, Runner};
use runtime::process::{NodeStats, STATS_PREFIX};
use runtime::step::GraphNode;
use schemas::MessageKind as M;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};
use tokio::io::{AsyncBufReadExt, BufReader};

/// The built-in node kinds, in pipeline order.
pub const KINDS: &[&str] = &[
    "capture",
    "rectify",
    "segment",
    "match-lr",
    "match-rl",
    "validate",
    "postprocess",
    "triangulate",
    "manipulator-bridge",
];

fn ok_capture(t: &toml::Table) -> Result<(), String> {
    capture::check_params(t)
}
fn ok_rectify(t: &toml::Table) -> Result<(), String> {
    rectify::node::rectification(t).map(|_| ())
}
fn ok_segment(t: &toml::Table) -> Result<(), String> {
    segment::node::params_from_table(t).map(|_| ())
}
fn ok_match(t: &toml::Table) -> Result<(), String> {
    matcher::node::MatchParams::from_table(t).map(|_| ())
}
fn ok_validate(t: &toml::Table) -> Result<(), String> {
    validate::node::ValidateParams::from_table(t).map(|_| ())
}
fn ok_post(t: &toml::Table) -> Result<(), String> {
    postprocess::node::params_from_table(t).map(|_| ())
}
fn ok_triangulate(t: &toml::Table) -> Result<(), String> {
    crate::nodes::TriangulateParams::from_table(t).map(|_| ())
}
fn ok_bridge(t: &toml::Table) -> Result<(), String> {
    manipulator_bridge::node::BridgeParams::from_table(t).map(|_| ())
}

/// Ports and parameter check of a built-in kind.
pub fn kind_spec(kind: &str) -> Option<KindSpec> {
    let spec = |inputs: Vec<(&'static str, M)>,
                outputs: Vec<(&'static str, M)>,
                check_params: fn(&toml::Table) -> Result<(), String>| KindSpec {
        inputs,
        feedback: vec![],
        outputs,
        check_params,
    };
    Some(match kind {
        "capture" => KindSpec {
            // The manipulator's state, so that a synthetic scene draws the pipette.
            feedback: vec![("tip", M::ManipulatorState)],
            ..spec(vec![], vec![("frame", M::StereoFrame)], ok_capture)
        },
        "rectify" => spec(
            vec![("frame", M::StereoFrame)],
            vec![("frame", M::StereoFrame)],
            ok_rectify,
        ),
        "segment" => spec(
            vec![("frame", M::StereoFrame)],
            vec![("labels", M::Labels), ("cells", M::CellList)],
            ok_segment,
        ),
        "match-lr" | "match-rl" => spec(
            vec![("frame", M::StereoFrame)],
            vec![("disparity", M::Disparity)],
            ok_match,
        ),
        "validate" => spec(
            vec![("left", M::Disparity), ("right", M::Disparity)],
            vec![("disparity", M::Disparity), ("occlusion", M::Image)],
            ok_validate,
        ),
        "postprocess" => spec(
            vec![("disparity", M::Disparity)],
            vec![("disparity", M::Disparity)],
            ok_post,
        ),
        "triangulate" => spec(
            vec![
                ("frame", M::StereoFrame),
                ("labels", M::Labels),
                ("cells", M::CellList),
                ("disparity", M::Disparity),
                ("checked", M::Disparity),
            ],
            vec![("cloud", M::PointCloud), ("targets", M::Targets)],
            ok_triangulate,
        ),
        "manipulator-bridge" => spec(
            vec![("targets", M::Targets)],
            vec![("state", M::ManipulatorState)],
            ok_bridge,
        ),
        _ => return None,
    })
}

/// Builds the node value of a built-in kind from its (validated) parameters.
pub fn build(kind: &str, params: &toml::Table) -> Result<Box<dyn GraphNode>, String> {
    Ok(match kind {
        "capture" => capture::build(params)?,
        "rectify" => Box::new(rectify::node::RectifyNode::from_table(params)?),
        "segment" => Box::new(segment::node::SegmentNode {
            params: segment::node::params_from_table(params)?,
        }),
        "match-lr" | "match-rl" => Box::new(matcher::node::MatchNode::new(
            matcher::node::MatchParams::from_table(params)?,
            kind == "match-rl",
        )),
        "validate" => Box::new(validate::node::ValidateNode {
            params: validate::node::ValidateParams::from_table(params)?,
        }),
        "postprocess" => Box::new(postprocess::node::PostprocessNode {
            params: postprocess::node::params_from_table(params)?,
        }),
        "triangulate" => Box::new(crate::nodes::TriangulateNode::new(
            crate::nodes::TriangulateParams::from_table(params)?,
        )),
        "manipulator-bridge" => Box::new(manipulator_bridge::node::BridgeNode::new(
            &manipulator_bridge::node::BridgeParams::from_table(params)?,
        )?),
        other => return Err(format!("unknown kind '{other}'")),
    })
}

/// Reads and validates a launch file; every problem becomes one error.
pub fn load(path: &Path) -> Result<Graph, CliError> {
    LaunchFile::read(path)
        .and_then(|f| f.validate(&kind_spec, KINDS))
        .map_err(|e| {
            CliError::Other(format!(
                "{e}\n({} problem(s) in the launch file)",
                e.0.len()
            ))
        })
}

/// The node values of a graph, in its order (exec nodes cannot run in-process).
pub fn build_all(graph: &Graph) -> Result<Vec<Box<dyn GraphNode>>, CliError> {
    graph
        .nodes
        .iter()
        .map(|n| crate::recording::build_spec(n).map_err(CliError::Other))
        .collect()
}

/// Arguments of `microstereo node`.
#[derive(Args, Debug)]
pub struct NodeArgs {
    /// The launch file the node belongs to.
    #[arg(long)]
    pub launch: PathBuf,
    /// The node's id in it.
    #[arg(long)]
    pub id: String,
    /// Stop after this many frames.
    #[arg(long)]
    pub frames: Option<u64>,
    /// The running graph this node belongs to (names its shared memory).
    #[arg(long, default_value = "default")]
    pub instance: String,
    /// How the run changed the launch file's graph.
    #[command(flatten)]
    pub opts: crate::recording::GraphOpts,
}

/// Runs one node as this process.
pub fn node_cmd(a: NodeArgs) -> Result<(), CliError> {
    set_parent_death_signal();
    let graph = crate::recording::load_with(&a.launch, &a.opts)?;
    let spec = graph
        .node(&a.id)
        .ok_or_else(|| CliError::Other(format!("no node '{}' in {}", a.id, a.launch.display())))?;
    let Runner::Builtin(kind) = &spec.runner else {
        return Err(CliError::Other(format!(
            "node '{}' is not a built-in kind",
            a.id
        )));
    };
    if kind == recorder::node::RECORDER_KIND {
        let stats = recorder::node::run_recorder(
            &graph,
            &a.instance,
            &a.id,
            a.frames,
            graph_calibration(&graph),
        )
        .map_err(|e| CliError::Other(format!("node '{}': {e}", a.id)))?;
        println!(
            "{STATS_PREFIX}{}",
            serde_json::to_string(&stats).expect("serialises")
        );
        return Ok(());
    }
    let mut node = crate::recording::build_spec(spec).map_err(CliError::Other)?;
    let fps = spec
        .params
        .get("fps")
        .and_then(|v| v.as_float().or(v.as_integer().map(|i| i as f64)));
    let stats =
        runtime::process::run_node(&graph, &a.instance, &a.id, node.as_mut(), a.frames, fps)
            .map_err(|e| CliError::Other(format!("node '{}': {e}", a.id)))?;
    println!(
        "{STATS_PREFIX}{}",
        serde_json::to_string(&stats).expect("serialises")
    );
    Ok(())
}

/// The calibration the graph's triangulate node uses, with the image size, when the launch
/// file says both (a synthetic capture, or a capture with `width` and `height`).
pub fn graph_calibration(graph: &Graph) -> Option<(schemas::Calibration, (usize, usize))> {
    let of_kind = |kind: &str| {
        graph
            .nodes
            .iter()
            .find(|n| matches!(&n.runner, Runner::Builtin(k) if k == kind))
    };
    let (tri, cap) = (of_kind("triangulate")?, of_kind("capture")?);
    let size = match cap.params.get("source").and_then(|s| s.as_str()) {
        None | Some("synthetic") => {
            let p = capture::synthetic::SyntheticParams::from_table(&cap.params).ok()?;
            (p.width, p.height)
        }
        _ => {
            let dim = |k: &str| cap.params.get(k)?.as_integer().map(|v| v as usize);
            (dim("width")?, dim("height")?)
        }
    };
    let p = crate::nodes::TriangulateParams::from_table(&tri.params).ok()?;
    let calib = if p.calibration == "synthetic" {
        synth::Optics {
            width: size.0,
            height: size.1,
            ..synth::Optics::default()
        }
        .calibration()
    } else {
        crate::cli::load_calibration(Path::new(&p.calibration), size.0, size.1).ok()?
    };
    Some((calib, size))
}

/// The command line the supervisor gives an `exec` node.
#[derive(clap::Parser, Debug)]
struct ExecCli {
    #[command(flatten)]
    args: NodeArgs,
}

/// The whole `main` of a custom node binary (an `exec` node in a launch file): reads the
/// arguments the supervisor passes (`--launch`, `--id`, `--instance`, `--frames`), builds the
/// node with `make` from its launch-file entry, runs it on the graph's shared memory and
/// prints its statistics for the summary. Returns the process exit code.
pub fn exec_main(
    make: impl FnOnce(&runtime::launch::NodeSpec) -> Result<Box<dyn GraphNode>, String>,
) -> i32 {
    use clap::Parser;
    set_parent_death_signal();
    let a = ExecCli::parse().args;
    let run = || -> Result<NodeStats, CliError> {
        let graph = crate::recording::load_with(&a.launch, &a.opts)?;
        let spec = graph.node(&a.id).ok_or_else(|| {
            CliError::Other(format!("no node '{}' in {}", a.id, a.launch.display()))
        })?;
        let mut node = make(spec).map_err(CliError::Other)?;
        runtime::process::run_node(&graph, &a.instance, &a.id, node.as_mut(), a.frames, None)
            .map_err(|e| CliError::Other(format!("node '{}': {e}", a.id)))
    };
    match run() {
        Ok(stats) => {
            println!(
                "{STATS_PREFIX}{}",
                serde_json::to_string(&stats).expect("serialises")
            );
            0
        }
        Err(e) => {
            eprintln!("error: {e}");
            2
        }
    }
}

/// A child dies with its parent, even when the parent is killed with SIGKILL.
fn set_parent_death_signal() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: prctl with PR_SET_PDEATHSIG only sets a flag of this process.
    unsafe {
        libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
    }
}

/// Arguments of `microstereo run`.
#[derive(Args, Debug)]
pub struct RunArgs {
    /// The launch file.
    #[arg(default_value = concat!(env!("CARGO_MANIFEST_DIR"), "/launch.toml"))]
    pub launch: PathBuf,
    /// Stop after this many frames (run until Ctrl-C without it).
    #[arg(long)]
    pub frames: Option<u64>,
    /// Seconds a node gets to end after SIGTERM before it is killed.
    #[arg(long, default_value_t = 3.0)]
    pub grace: f64,
    /// Names this run's shared memory (default: the supervisor's process id), so that
    /// graphs running side by side do not share edges; readers outside the graph use it.
    #[arg(long)]
    pub instance: Option<String>,
    /// Recording (and, from `replay`, replay) of edges.
    #[command(flatten)]
    pub opts: crate::recording::GraphOpts,
}

/// Runs the graph: one process per node, logs prefixed, restarts, clean stop, summary.
pub fn run_cmd(a: RunArgs) -> Result<(), CliError> {
    crate::recording::check_record_target(&a.opts.out)?;
    crate::recording::check_viewer_target(&a.opts.out)?;
    let graph = crate::recording::load_with(&a.launch, &a.opts)?;
    let stale = runtime::process::remove_stale_resources();
    if stale.removed > 0 || stale.empty_files > 0 {
        eprintln!(
            "removed the shared memory of {} dead node(s) and {} unfinished edge(s)",
            stale.removed, stale.empty_files
        );
    }
    if stale.gave_up {
        eprintln!(
            "warning: the shared memory of dead nodes could not be removed within {:?}; \
             the graph starts anyway (`rm /dev/shm/iox2_*` and `rm -r /tmp/iceoryx2` with \
             no graph running clears it)",
            runtime::process::STALE_CLEANUP_LIMIT
        );
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| CliError::Other(format!("cannot start the supervisor: {e}")))?;
    let (stats, wall) = rt.block_on(supervise(&graph, &a))?;
    print_summary(&graph, &stats, wall, a.frames);
    if let Some(path) = &a.opts.out.record {
        let written = stats
            .get(crate::recording::RECORDER_ID)
            .map_or(0, |s| s.frames_out);
        let size = std::fs::metadata(path).map_or(0, |m| m.len());
        println!(
            "recorded {written} message(s) into {} ({:.1} MB); `microstereo inspect {}` lists them",
            path.display(),
            size as f64 / 1e6,
            path.display()
        );
    }
    Ok(())
}

struct Child {
    id: String,
    proc: tokio::process::Child,
    restarts: u32,
}

fn spawn(
    graph: &Graph,
    instance: &str,
    id: &str,
    frames: Option<u64>,
    opts: &crate::recording::GraphOpts,
) -> Result<tokio::process::Child, CliError> {
    let spec = graph.node(id).expect("validated");
    let mut cmd = match &spec.runner {
        Runner::Builtin(_) => {
            let exe = std::env::current_exe()
                .map_err(|e| CliError::Other(format!("cannot find this program: {e}")))?;
            let mut c = tokio::process::Command::new(exe);
            c.arg("node");
            c
        }
        Runner::Exec(p) => tokio::process::Command::new(p),
    };
    cmd.arg("--launch")
        .arg(&graph.file)
        .arg("--id")
        .arg(id)
        .arg("--instance")
        .arg(instance);
    if let Some(n) = frames {
        cmd.arg("--frames").arg(n.to_string());
    }
    cmd.args(opts.to_args());
    cmd.stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .stdin(if id == crate::recording::VIEWER_ID {
            Stdio::piped()
        } else {
            Stdio::null()
        })
        .kill_on_drop(true);
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: only async-signal-safe prctl between fork and exec.
    unsafe {
        cmd.pre_exec(|| {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
            Ok(())
        });
    }
    cmd.spawn()
        .map_err(|e| CliError::Other(format!("cannot start node '{id}': {e}")))
}

type StatsSink = std::sync::Arc<std::sync::Mutex<HashMap<String, NodeStats>>>;

/// Where node log lines go besides the terminal: the Rerun viewer node's stdin, as
/// `NODE<TAB>LEVEL<TAB>LINE`.
type LogTap = Option<tokio::sync::mpsc::UnboundedSender<String>>;

fn forward_logs(id: &str, child: &mut tokio::process::Child, stats: &StatsSink, tap: &LogTap) {
    if let Some(out) = child.stdout.take() {
        let (id, stats, tap) = (id.to_string(), stats.clone(), tap.clone());
        tokio::spawn(async move {
            let mut lines = BufReader::new(out).lines();
            while let Ok(Some(l)) = lines.next_line().await {
                match l.strip_prefix(STATS_PREFIX) {
                    Some(j) => {
                        if let Ok(s) = serde_json::from_str::<NodeStats>(j) {
                            stats.lock().expect("stats").insert(id.clone(), s);
                        }
                    }
                    None => {
                        if let Some(t) = &tap {
                            let _ = t.send(format!("{id}\tINFO\t{l}"));
                        }
                        println!("[{id}] {l}")
                    }
                }
            }
        });
    }
    if let Some(err) = child.stderr.take() {
        let (id, tap) = (id.to_string(), tap.clone());
        tokio::spawn(async move {
            let mut lines = BufReader::new(err).lines();
            while let Ok(Some(l)) = lines.next_line().await {
                if let Some(t) = &tap {
                    let _ = t.send(format!("{id}\tWARN\t{l}"));
                }
                eprintln!("[{id}] {l}");
            }
        });
    }
    // The viewer reads the other nodes' log lines on its stdin.
    if id == crate::recording::VIEWER_ID
        && let Some(mut stdin) = child.stdin.take()
        && let Some(rx) = VIEWER_LOGS.lock().expect("logs").take()
    {
        use tokio::io::AsyncWriteExt;
        let mut rx: tokio::sync::mpsc::UnboundedReceiver<String> = rx;
        tokio::spawn(async move {
            while let Some(mut line) = rx.recv().await {
                line.push('\n');
                if stdin.write_all(line.as_bytes()).await.is_err() {
                    break;
                }
            }
        });
    }
}

/// The receiving end of the log tap, taken by the first viewer process started.
static VIEWER_LOGS: std::sync::Mutex<Option<tokio::sync::mpsc::UnboundedReceiver<String>>> =
    std::sync::Mutex::new(None);

fn terminate(children: &[Child]) {
    for c in children {
        if let Some(pid) = c.proc.id() {
            // SAFETY: kill(2) on our own child's pid.
            unsafe {
                libc::kill(pid as i32, libc::SIGTERM);
            }
        }
    }
}

async fn supervise(
    graph: &Graph,
    a: &RunArgs,
) -> Result<(HashMap<String, NodeStats>, Duration), CliError> {
    use tokio::signal::unix::{SignalKind, signal};
    let stats: StatsSink = Default::default();
    let instance = a
        .instance
        .clone()
        .unwrap_or_else(|| format!("run{}", std::process::id()));
    let start = Instant::now();
    let tap: LogTap = graph.node(crate::recording::VIEWER_ID).map(|_| {
        let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
        *VIEWER_LOGS.lock().expect("logs") = Some(rx);
        tx
    });
    let mut children = Vec::new();
    for n in &graph.nodes {
        let mut proc = spawn(graph, &instance, &n.id, a.frames, &a.opts)?;
        forward_logs(&n.id, &mut proc, &stats, &tap);
        children.push(Child {
            id: n.id.clone(),
            proc,
            restarts: 0,
        });
    }
    let mut sigterm = signal(SignalKind::terminate())
        .map_err(|e| CliError::Other(format!("cannot watch SIGTERM: {e}")))?;
    // A node that others read stays after its last frame (its readers may still be taking
    // them) until it is told to stop.
    let mut failure: Option<String> = None;
    let mut stopping = false;
    loop {
        if children.is_empty() {
            break;
        }
        // Every node nobody reads is done: the ones they read may go.
        if !stopping && children.iter().all(|c| graph.is_read(&c.id)) {
            stopping = true;
            terminate(&children);
        }
        let exited = {
            let waits = children
                .iter_mut()
                .enumerate()
                .map(|(i, c)| Box::pin(async move { (i, c.proc.wait().await) }));
            tokio::select! {
                (r, _, _) = futures_select(waits) => Some(r),
                _ = tokio::signal::ctrl_c() => None,
                _ = sigterm.recv() => None,
                _ = tokio::time::sleep(Duration::from_secs_f64(a.grace)), if stopping => {
                    for c in &mut children {
                        let _ = c.proc.start_kill();
                    }
                    None
                }
            }
        };
        let Some((i, status)) = exited else {
            if !stopping {
                eprintln!("stopping the graph");
                stopping = true;
                terminate(&children);
            }
            continue;
        };
        let status = status.map_err(|e| CliError::Other(format!("waiting for a node: {e}")))?;
        let c = children.remove(i);
        let spec = graph.node(&c.id).expect("validated");
        let failed = !status.success();
        let restart = !stopping
            && match spec.restart.policy {
                runtime::launch::RestartPolicy::Never => false,
                runtime::launch::RestartPolicy::OnFailure => failed,
                runtime::launch::RestartPolicy::Always => true,
            }
            && c.restarts < spec.restart.max;
        if restart {
            let wait = Duration::from_millis(spec.restart.backoff_ms << c.restarts.min(10));
            eprintln!(
                "[{}] exited ({status}); restart {} of {} in {:?}",
                c.id,
                c.restarts + 1,
                spec.restart.max,
                wait
            );
            tokio::time::sleep(wait).await;
            if failed {
                // A node that died holds its places on its edges (a full queue of a dead
                // reader blocks a lossless writer): free them before its successor joins.
                let stale = tokio::task::spawn_blocking(runtime::process::remove_stale_resources)
                    .await
                    .unwrap_or_default();
                if stale.gave_up {
                    eprintln!("[{}] warning: its shared memory could not be removed", c.id);
                }
            }
            let mut proc = spawn(graph, &instance, &c.id, a.frames, &a.opts)?;
            forward_logs(&c.id, &mut proc, &stats, &tap);
            children.push(Child {
                id: c.id,
                proc,
                restarts: c.restarts + 1,
            });
        } else if failed && !stopping {
            failure = Some(format!("node '{}' failed ({status})", c.id));
            stopping = true;
            terminate(&children);
        }
    }
    // Give the log forwarders a moment to flush the last lines.
    tokio::time::sleep(Duration::from_millis(50)).await;
    let wall = start.elapsed();
    let stats = stats.lock().expect("stats").clone();
    match failure {
        Some(f) => Err(CliError::Other(f)),
        None => Ok((stats, wall)),
    }
}

/// The first of several futures to finish, with its index.
async fn futures_select<F, T>(futs: impl Iterator<Item = F>) -> (T, usize, ())
where
    F: std::future::Future<Output = T> + Unpin,
{
    let mut futs: Vec<F> = futs.collect();
    std::future::poll_fn(move |cx| {
        for (i, f) in futs.iter_mut().enumerate() {
            if let std::task::Poll::Ready(v) = std::pin::Pin::new(f).poll(cx) {
                return std::task::Poll::Ready((v, i, ()));
            }
        }
        std::task::Poll::Pending
    })
    .await
}

fn print_summary(
    graph: &Graph,
    stats: &HashMap<String, NodeStats>,
    wall: Duration,
    frames: Option<u64>,
) {
    println!();
    println!(
        "{:<20} {:>9} {:>9} {:>10} {:>10} {:>12}",
        "node", "frames in", "out", "mean ms", "p99 ms", "latency ms"
    );
    for n in &graph.nodes {
        match stats.get(&n.id) {
            Some(s) => println!(
                "{:<20} {:>9} {:>9} {:>10.2} {:>10.2} {:>12.1}",
                n.id, s.frames_in, s.frames_out, s.mean_ms, s.p99_ms, s.latency_ms
            ),
            None => println!("{:<20} (no report)", n.id),
        }
    }
    // Per edge: messages its own queue lost, and frames of the stream that never reached
    // the reader (lost there, upstream, or in a restarted writer).
    let mut rows = Vec::new();
    for n in &graph.nodes {
        if let Some(s) = stats.get(&n.id) {
            for (i, lost) in n.inputs.iter().zip(&s.inputs) {
                rows.push((
                    format!("{}/{} → {}.{}", i.node, i.output, n.id, i.port),
                    lost,
                ));
            }
        }
    }
    let width = rows
        .iter()
        .map(|r| r.0.chars().count())
        .max()
        .unwrap_or(4)
        .max(4);
    println!();
    println!(
        "{:<width$} {:>8} {:>14}",
        "edge", "dropped", "never arrived"
    );
    for (edge, lost) in &rows {
        println!("{:<width$} {:>8} {:>14}", edge, lost.dropped, lost.missing);
    }
    // The graph's own ends: nodes no other node reads, taps (recorder, viewer) and
    // feedback inputs aside.
    let tap = |id: &str| id == crate::recording::RECORDER_ID || id == crate::recording::VIEWER_ID;
    let sinks: Vec<&NodeStats> = graph
        .nodes
        .iter()
        .filter(|n| !tap(&n.id))
        .filter(|n| {
            !graph
                .nodes
                .iter()
                .filter(|m| !tap(&m.id))
                .any(|m| m.inputs.iter().any(|i| i.node == n.id && !i.feedback))
        })
        .filter_map(|n| stats.get(&n.id))
        .collect();
    let done = sinks.iter().map(|s| s.frames_in).min().unwrap_or(0);
    println!(
        "{done} frame(s){} in {:.2} s: {:.2} frames/s; capture → last output latency {:.1} ms",
        frames.map_or(String::new(), |n| format!(" of {n}")),
        wall.as_secs_f64(),
        done as f64 / wall.as_secs_f64().max(1e-9),
        sinks.iter().map(|s| s.latency_ms).fold(0.0, f64::max)
    );
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
    for placement in placements {
        let (wake50, wake99) =
            runtime::hop::wake_floor(a.frames, placement).map_err(CliError::Other)?;
        println!(
            "writer and reader {} (a bare thread wake-up: p50 {wake50:.1} µs, p99 {wake99:.1} µs)",
            match placement {
                Placement::OneCore => "on one core",
                Placement::TwoCores => "on two cores",
                Placement::Free => "where the scheduler puts them",
            }
        );
        println!(
            "{:<22} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9} {:>8} {:>8}",
            "frame",
            "shm p50",
            "shm p99",
            "shm fps",
            "uds p50",
            "uds p99",
            "uds fps",
            "p50 ×",
            "fps ×"
        );
        for (name, w, h) in [
            ("0.3 MP (640×480)", 640usize, 480usize),
            ("1.3 MP (1280×1024)", 1280, 1024),
            ("5 MP (2592×1944)", 2592, 1944),
        ] {
            let bytes = w * h;
            let shm =
                runtime::hop::iceoryx2(bytes, a.frames, placement).map_err(CliError::Other)?;
            let uds =
                runtime::hop::unix_socket(bytes, a.frames, placement).map_err(CliError::Other)?;
            println!(
                "{:<22} {:>9.1} {:>9.1} {:>9.0} {:>9.1} {:>9.1} {:>9.0} {:>8.1} {:>8.1}",
                name,
                shm.p50_us,
                shm.p99_us,
                shm.fps,
                uds.p50_us,
                uds.p99_us,
                uds.fps,
                uds.p50_us / shm.p50_us,
                shm.fps / uds.fps
            );
        }
    }
    println!(
        "latencies in µs, one frame at a time; fps back to back through a lossless edge of depth 4"
    );
    Ok(())
}
