//! Recordings run against the built-in kinds: the graph a replay or a node test runs, and
//! one node checked against what it recorded (`microstereo test-node`).

use crate::Error;
use recorder::file::{FrameReader, Overview};
use recorder::node::check_channels;
use runtime::harness::{NodeCheck, Recorded};
use runtime::launch::{Graph, LaunchFile};
use schemas::MessageKind;
use std::path::Path;

/// Reads the channel overview of a recording; a corrupt file, or one with nothing
/// readable, is an error that says what was read. A file cut short (its writer died, the
/// disk filled, a copy lost its tail) is used up to its last whole record, the loss said
/// on stderr.
pub fn usable(path: &Path) -> Result<Overview, Error> {
    let o = recorder::overview(path).map_err(|e| Error::Recording(e.to_string()))?;
    if let Some(why) = o.stopped(path) {
        return Err(Error::Recording(format!(
            "{why}; `microstereo inspect {}` shows what it holds",
            path.display()
        )));
    }
    let messages: u64 = o.channels.iter().map(|c| c.messages).sum();
    if messages == 0 {
        let why: Vec<&str> = o.cut.iter().chain(&o.damaged).map(String::as_str).collect();
        return Err(Error::Recording(format!(
            "{}: no message in it can be read{}",
            path.display(),
            if why.is_empty() {
                " (it holds none)".to_string()
            } else {
                format!(": {}", why.join("; "))
            }
        )));
    }
    // Damaged chunks cost their own messages only, a cut its tail: the rest is used, the
    // loss is said.
    for d in o.cut.iter().chain(&o.damaged) {
        runtime::errln!("warning: {}: {d}", path.display());
    }
    Ok(o)
}

/// The launch file a replay or a node test runs: `launch`, or the one the recording holds.
pub fn launch_of(file: &Path, o: &Overview, launch: Option<&Path>) -> Result<Graph, Error> {
    match launch {
        Some(l) => crate::launch::load(l),
        None => {
            let (from, text) = o.launch.as_ref().ok_or_else(|| {
                Error::Recording(format!(
                    "{} holds no launch file; give one with --launch",
                    file.display()
                ))
            })?;
            LaunchFile::parse(Path::new(from), text)
                .and_then(|f| f.validate(&crate::registry::builtin()))
                .map_err(|e| {
                    Error::Recording(format!("the launch file stored in {}: {e}", file.display()))
                })
        }
    }
}

/// How a replay runs a recording.
#[derive(Clone, Debug)]
pub struct Replay {
    /// The nodes whose recorded outputs replace them.
    pub replace: Vec<String>,
    /// Speed: `1.0` as recorded, `max` as fast as the graph goes.
    pub rate: String,
    /// Start again at the end.
    pub looped: bool,
    /// Seconds into the recording to start at, and how many to replay (`None`: to its end).
    pub window: (f64, Option<f64>),
}

impl Replay {
    /// Checks the rate and the window before anything is read.
    pub fn check(&self) -> Result<(), Error> {
        recorder::node::Rate::parse(&self.rate)
            .map_err(|e| Error::Options(format!("--rate: {e}")))?;
        let (start, duration) = self.window;
        if !(0.0..=1e9).contains(&start) {
            return Err(Error::Options(format!(
                "--start {start} is out of range: give 0 to 1e9 seconds into the recording"
            )));
        }
        if let Some(d) = duration
            && !(d > 0.0 && d <= 1e9)
        {
            return Err(Error::Options(format!(
                "--duration {d} is out of range: give above 0 to 1e9 seconds"
            )));
        }
        Ok(())
    }
}

/// The graph a replay of `file` (overview `o`) runs: `launch`, or the one the recording
/// holds, with the replaced nodes turned into sources of what they recorded.
pub fn replay_graph(
    file: &Path,
    o: &Overview,
    launch: Option<&Path>,
    r: &Replay,
) -> Result<Graph, Error> {
    let mut graph = launch_of(file, o, launch)?;
    // A start past the end would send no frame, and the graph wait for one.
    let edges = o.channels.iter().filter(|c| c.edge.is_some());
    if let (Some(t0), Some(t1)) = (
        edges.clone().map(|c| c.first_ns).min(),
        edges.map(|c| c.last_ns).max(),
    ) {
        let span = (t1 - t0) as f64 * 1e-9;
        if r.window.0 > 0.0 && r.window.0 >= span {
            return Err(Error::PastTheEnd {
                start: r.window.0,
                file: file.display().to_string(),
                span,
            });
        }
    }
    let mut replaced: Vec<(String, MessageKind)> = Vec::new();
    for id in &r.replace {
        if graph.node(id).is_none() {
            return Err(Error::NoSuchNode {
                id: id.clone(),
                file: graph.file.display().to_string(),
            });
        }
        replaced.extend(graph.output_edges(id));
    }
    check_channels(file, o, &replaced).map_err(Error::Recording)?;
    crate::taps::apply_replay(&mut graph, file, &r.replace, &r.rate, r.looped, r.window)
        .map_err(Error::Recording)?;
    Ok(graph)
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
) -> Result<NodeCheck, Error> {
    let o = usable(file)?;
    let graph = launch_of(file, &o, launch)?;
    let spec = graph.node(id).ok_or_else(|| {
        Error::Recording(format!(
            "no node '{id}' in {}; its nodes: {}",
            graph.file.display(),
            graph
                .nodes
                .iter()
                .map(|n| n.id.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        ))
    })?;
    let Some(kind) = spec.kind() else {
        return Err(Error::Recording(format!(
            "node '{id}' is an exec node; test-node runs built-in kinds"
        )));
    };
    let bridge = kind == <manipulator_bridge::node::BridgeNode as runtime::node::Task>::KIND;
    // The bridge's state follows the wall clock (device polling): its check is what it
    // serves over TCP.
    let (inputs, outputs) = runtime::harness::edges_under_test(&graph, id, &|k| {
        bridge && k == MessageKind::ManipulatorState
    });
    let all: Vec<(String, MessageKind)> = inputs.iter().chain(&outputs).cloned().collect();
    check_channels(file, &o, &all).map_err(Error::Recording)?;
    let edges: Vec<String> = all.iter().map(|(e, _)| e.clone()).collect();
    let mut frames = FrameReader::open(file, edges).map_err(|e| Error::Recording(e.to_string()))?;
    let names: Vec<String> = outputs.iter().map(|(e, _)| e.clone()).collect();
    let recorded = frames.by_ref().map(|f| {
        f.map(|msgs| {
            msgs.into_iter()
                .map(|m| (m.header, m.payload))
                .collect::<Vec<Recorded>>()
        })
        .map_err(|e| e.to_string())
    });
    let connected: Vec<String> = spec.inputs.iter().map(|i| i.port.clone()).collect();
    let (mut node, extra) = if bridge {
        let (node, served) = manipulator_bridge::testing::under_test(&spec.params, &connected)
            .map_err(Error::Start)?;
        (node, Some(("TCP lines".to_string(), served)))
    } else {
        let node = crate::registry::builtin()
            .build(spec)
            .map_err(Error::Start)?;
        (node, None)
    };
    let mut check = runtime::harness::check_node(
        id,
        node.as_mut(),
        inputs.len(),
        &names,
        recorded,
        tolerance,
        extra,
    )
    .map_err(Error::Node)?;
    check.incomplete = frames.incomplete;
    Ok(check)
}
