//! `launch.toml`: the graph as a file, checked whole before anything starts.
//!
//! ```toml
//! [[node]]
//! id = "capture"
//! kind = "capture"                       # a built-in kind, or exec = "path/to/binary"
//! params = { source = "synthetic", width = 1280, height = 1024 }
//! restart = { policy = "on-failure", max = 3, backoff_ms = 500, heartbeat_ms = 5000 }
//! in_flight = { after = "manipulator-bridge/state", frames = 2 }  # a source's frames in flight
//!
//! [[node]]
//! id = "segment"
//! kind = "segment"
//! inputs = { frame = "capture/frame" }   # or { from = "capture/frame", depth = 4, overflow = "block" }
//! ```
//!
//! [`LaunchFile::parse`] reads it; [`LaunchFile::validate`] checks it against the kinds the
//! binary knows (a [`Catalog`], the registry of node types) and against what an `exec`
//! node's program declares (it is asked with `--describe`): unknown kinds, unknown or
//! duplicate ids, inputs from unknown nodes or outputs, unknown input ports, message-type
//! mismatches, missing inputs, cycles and bad parameters — each reported as
//! `file:line: what; how to fix`.

use crate::edge::{EdgeConfig, Overflow};
use schemas::MessageKind;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use toml::Spanned;

/// One problem in a launch file, with where it is.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{file}:{line}: {message}")]
pub struct LaunchError {
    /// The launch file.
    pub file: String,
    /// 1-based line (0 when the whole file is at fault).
    pub line: usize,
    /// What is wrong and how to fix it.
    pub message: String,
}

/// Every problem found in a launch file, in file order.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LaunchErrors(pub Vec<LaunchError>);

impl std::fmt::Display for LaunchErrors {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for (i, e) in self.0.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "{e}")?;
        }
        Ok(())
    }
}

impl std::error::Error for LaunchErrors {}

/// When a node that ended is started again.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RestartPolicy {
    /// Never (the default): the graph stops when a node fails.
    #[default]
    Never,
    /// When it exits with an error or a signal.
    OnFailure,
    /// Whenever it exits.
    Always,
}

/// A node's restart settings.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Restart {
    /// When to restart.
    #[serde(default)]
    pub policy: RestartPolicy,
    /// Most restarts before the graph gives up on the node.
    #[serde(default = "default_max_restarts")]
    pub max: u32,
    /// Wait before a restart, doubled after each one.
    #[serde(default = "default_backoff_ms")]
    pub backoff_ms: u64,
    /// The watchdog: a node that has not reported for this long (stuck in a step, stopped
    /// by SIGSTOP, deadlocked) is killed, and then restarted by `policy` like any failed
    /// node. Nodes report after every step and at least twice a second while they wait;
    /// a step or a blocked send longer than this counts as a hang. Off when absent; the
    /// watch starts with a node's first report, not while it starts up.
    // Left out of the graph file when off: exec programs built before it refuse the field.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub heartbeat_ms: Option<u64>,
}

/// The shortest watchdog time a launch file may ask for: an idle node reports every
/// 500 ms.
pub const MIN_HEARTBEAT_MS: u64 = 1000;

/// The most readers an edge of a launch file may have (of the transport's
/// [`MAX_READERS`](crate::transport::MAX_READERS), the rest are kept for the readers a run
/// adds).
pub const MAX_GRAPH_READERS: usize = crate::transport::MAX_READERS - 4;

/// The longest restart back-off a launch file may ask for, ms (ten minutes).
pub const MAX_BACKOFF_MS: u64 = 600_000;

fn default_max_restarts() -> u32 {
    3
}

fn default_backoff_ms() -> u64 {
    200
}

impl Default for Restart {
    fn default() -> Self {
        Self {
            policy: RestartPolicy::Never,
            max: default_max_restarts(),
            backoff_ms: default_backoff_ms(),
            heartbeat_ms: None,
        }
    }
}

/// An input as written: a source, or a source with queue settings.
#[derive(Clone, Debug, Deserialize)]
#[serde(untagged)]
enum InputDecl {
    Source(String),
    Full {
        from: String,
        #[serde(default)]
        depth: Option<usize>,
        #[serde(default)]
        overflow: Option<Overflow>,
    },
}

/// Ports of an `exec` node, which the binary cannot know.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct PortsDecl {
    #[serde(default)]
    inputs: BTreeMap<String, MessageKind>,
    #[serde(default)]
    outputs: BTreeMap<String, MessageKind>,
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct NodeDecl {
    id: Spanned<String>,
    #[serde(default)]
    kind: Option<Spanned<String>>,
    #[serde(default)]
    exec: Option<Spanned<String>>,
    #[serde(default)]
    inputs: BTreeMap<String, Spanned<InputDecl>>,
    #[serde(default)]
    params: Option<Spanned<toml::Table>>,
    #[serde(default)]
    restart: Option<Spanned<Restart>>,
    #[serde(default)]
    ports: Option<Spanned<PortsDecl>>,
    #[serde(default)]
    in_flight: Option<Spanned<InFlight>>,
    #[serde(default)]
    host: Option<Spanned<String>>,
}

/// A source's limit on the frames in flight: it lets a frame in only while fewer than
/// `frames` of those it sent have yet to come out of `after` (usually the graph's last
/// output). Frames then wait in no queue: a paced source drops the frames it cannot let in,
/// as a camera's frames are dropped at the entrance; an unpaced one waits.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InFlight {
    /// The output whose frames count as done, `NODE/OUTPUT`.
    pub after: String,
    /// Most frames sent and not yet done.
    pub frames: u64,
}

impl InFlight {
    /// `after` as its node and output; `None` unless it is `NODE/OUTPUT` with both named.
    pub fn output(&self) -> Option<(&str, &str)> {
        self.after
            .split_once('/')
            .filter(|(node, output)| !node.is_empty() && !output.is_empty())
    }
}

/// The most frames a source may keep in flight.
const MAX_IN_FLIGHT: u64 = 64;

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileDecl {
    #[serde(default)]
    node: Vec<Spanned<NodeDecl>>,
    #[serde(default)]
    hosts: BTreeMap<String, Spanned<Host>>,
}

/// A host of a graph split over machines (`[hosts.NAME]`): where its part's link listens
/// and whom it connects to (Zenoh endpoints such as `tcp/0.0.0.0:7447`).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Host {
    /// Endpoints its link listens on.
    #[serde(default)]
    pub listen: Vec<String>,
    /// Endpoints of other hosts its link connects to.
    #[serde(default)]
    pub connect: Vec<String>,
}

/// One port of a node kind: its name and the message it carries.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Port {
    /// Name in launch files.
    pub name: String,
    /// Message kind.
    pub kind: MessageKind,
    /// An input that may stay unconnected.
    #[serde(default)]
    pub optional: bool,
}

/// What a node kind consumes and produces.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct KindSpec {
    /// Input ports and the message each expects.
    pub inputs: Vec<Port>,
    /// Feedback ports: optional inputs that may close a loop (a sink's state back to a
    /// source). The node takes their newest message when it has one, never waits for them,
    /// and they do not count as edges for the order of the graph or for its cycles.
    pub feedback: Vec<Port>,
    /// Output ports and the message each carries.
    pub outputs: Vec<Port>,
}

/// The node kinds a launch file is checked against (the registry of node types).
pub trait Catalog {
    /// Kinds a launch file may name, in the order to list them.
    fn kinds(&self) -> Vec<String>;
    /// Ports of `kind`.
    fn spec(&self, kind: &str) -> Option<KindSpec>;
    /// Checks `params` of a node of `kind` whose inputs `connected` are connected.
    fn check(&self, kind: &str, params: &toml::Table, connected: &[&str]) -> Result<(), String>;
    /// Ports of an `exec` node's program (which checks `params` and `connected` too).
    fn exec(
        &self,
        program: &Path,
        params: &toml::Table,
        connected: &[&str],
    ) -> Result<KindSpec, String> {
        describe_exec(program, params, connected)
    }
}

/// How a node runs.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Runner {
    /// `microstereo node KIND …`.
    Builtin(String),
    /// A custom binary speaking the same protocol.
    Exec(PathBuf),
}

/// One input after validation.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Input {
    /// Input port name.
    pub port: String,
    /// Producing node id.
    pub node: String,
    /// Producing output port.
    pub output: String,
    /// Queue settings.
    pub edge: EdgeConfig,
    /// A feedback input (see [`KindSpec::feedback`]): newest message only, never joined.
    pub feedback: bool,
}

/// A `params` table as TOML text inside the graph's JSON (JSON has no TOML types).
mod toml_text {
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub fn serialize<S: Serializer>(t: &toml::Table, s: S) -> Result<S::Ok, S::Error> {
        toml::to_string(t)
            .map_err(serde::ser::Error::custom)?
            .serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<toml::Table, D::Error> {
        let text = String::deserialize(d)?;
        toml::from_str(&text).map_err(serde::de::Error::custom)
    }
}

/// One node after validation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NodeSpec {
    /// Unique id.
    pub id: String,
    /// How it runs.
    pub runner: Runner,
    /// Its inputs, in the order its kind declares its input ports, feedback inputs last.
    pub inputs: Vec<Input>,
    /// Its output ports and their messages.
    pub outputs: Vec<(String, MessageKind)>,
    /// Its parameters.
    #[serde(with = "toml_text")]
    pub params: toml::Table,
    /// Restart settings.
    pub restart: Restart,
    /// A tap added by a rewrite (recorder, viewer): it reads edges as they come and is
    /// not one of the graph's own ends.
    #[serde(default)]
    pub tap: bool,
    /// Takes every other node's log lines on its stdin (`NODE<TAB>LEVEL<TAB>LINE`).
    #[serde(default)]
    pub logs: bool,
    /// A source's limit on its frames in flight.
    #[serde(default)]
    pub in_flight: Option<InFlight>,
    /// The host whose part runs it (`None`: a graph on one machine).
    #[serde(default)]
    pub host: Option<String>,
}

impl NodeSpec {
    /// Its built-in kind (`None` for an `exec` node).
    pub fn kind(&self) -> Option<&str> {
        match &self.runner {
            Runner::Builtin(k) => Some(k),
            Runner::Exec(_) => None,
        }
    }
}

/// A launch file that passed validation: nodes in an order where every producer comes
/// before its consumers.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Graph {
    /// Where it was read from.
    pub file: PathBuf,
    /// The launch file's text (what a recording stores; empty for a graph built in code).
    #[serde(default)]
    pub text: String,
    /// Nodes, producers first.
    pub nodes: Vec<NodeSpec>,
    /// The hosts of a graph split over machines, by name.
    #[serde(default)]
    pub hosts: BTreeMap<String, Host>,
}

impl Graph {
    /// The shared-memory name of output `port` of node `id` in the running graph
    /// `instance` (two graphs on one machine do not share edges).
    pub fn edge_name(instance: &str, id: &str, port: &str) -> String {
        format!("microstereo/{instance}/{id}/{port}")
    }

    /// Queue settings of output `port` of node `id`, the same for every port of the edge:
    /// the deepest queue any reader asks for, and blocking if any reader asks for it.
    /// An edge no node reads (one only a recorder or viewer taps) follows its writer's
    /// inputs: lossless when they all are, so a lossless graph records every frame.
    pub fn edge_config(&self, id: &str, port: &str) -> EdgeConfig {
        let mut cfg: Option<EdgeConfig> = None;
        for i in self.nodes.iter().flat_map(|n| &n.inputs) {
            if i.node == id && i.output == port {
                let c = cfg.get_or_insert(i.edge);
                c.depth = c.depth.max(i.edge.depth);
                if i.edge.overflow == Overflow::Block {
                    c.overflow = Overflow::Block;
                }
            }
        }
        // A source counting this output's frames as done reads only the newest: unless
        // another reader blocks, its writer never waits for it.
        if self.in_flight_readers(id, port).next().is_some() {
            cfg.get_or_insert(EdgeConfig {
                depth: 1,
                overflow: Overflow::DropOldest,
            });
        }
        cfg.unwrap_or_else(|| self.writer_config(id))
    }

    /// The sources that count output `port` of node `id` as where their frames are done.
    pub fn in_flight_readers<'a>(
        &'a self,
        id: &'a str,
        port: &'a str,
    ) -> impl Iterator<Item = &'a NodeSpec> + 'a {
        self.nodes.iter().filter(move |n| {
            n.in_flight
                .as_ref()
                .and_then(InFlight::output)
                .is_some_and(|(a, b)| a == id && b == port)
        })
    }

    /// Queue settings for an unread output of node `id`: blocking with its inputs' deepest
    /// queue when every joined input blocks, the default otherwise (a source's included).
    fn writer_config(&self, id: &str) -> EdgeConfig {
        let joined: Vec<&Input> = self
            .node(id)
            .map(|n| n.inputs.iter().filter(|i| !i.feedback).collect())
            .unwrap_or_default();
        if !joined.is_empty() && joined.iter().all(|i| i.edge.overflow == Overflow::Block) {
            EdgeConfig {
                depth: joined.iter().map(|i| i.edge.depth).max().unwrap_or(1),
                overflow: Overflow::Block,
            }
        } else {
            EdgeConfig::default()
        }
    }

    /// The node with this id.
    pub fn node(&self, id: &str) -> Option<&NodeSpec> {
        self.nodes.iter().find(|n| n.id == id)
    }

    /// The host that runs node `id` (`None`: a graph on one machine).
    pub fn host_of(&self, id: &str) -> Option<&str> {
        self.node(id).and_then(|n| n.host.as_deref())
    }

    /// Whether nodes `a` and `b` run on different hosts.
    pub fn apart(&self, a: &str, b: &str) -> bool {
        self.host_of(a) != self.host_of(b)
    }

    /// The readers of output `port` of node `id`: (reader node id, reader name), the
    /// in-flight counts of sources included.
    pub fn readers_of<'a>(
        &'a self,
        id: &'a str,
        port: &'a str,
    ) -> impl Iterator<Item = (&'a str, String)> + 'a {
        self.nodes
            .iter()
            .flat_map(|n| n.inputs.iter().map(move |i| (n, i)))
            .filter(move |(_, i)| i.node == id && i.output == port)
            .map(|(n, i)| (n.id.as_str(), format!("{}.{}", n.id, i.port)))
            .chain(
                self.in_flight_readers(id, port)
                    .map(|n| (n.id.as_str(), format!("{}.in-flight", n.id))),
            )
    }

    /// The edges between hosts, as (writer, output): those a host's link carries.
    pub fn cross_host_edges(&self) -> Vec<(String, String)> {
        let mut out = Vec::new();
        for n in &self.nodes {
            for (port, _) in &n.outputs {
                if self
                    .readers_of(&n.id, port)
                    .any(|(r, _)| self.apart(r, &n.id))
                {
                    out.push((n.id.clone(), port.clone()));
                }
            }
        }
        out
    }

    /// The graph's own ends: nodes no other node reads, taps (recorder, viewer) and
    /// feedback inputs aside. A frame is through the graph once every end has taken it.
    pub fn ends(&self) -> Vec<&NodeSpec> {
        let own = |n: &&NodeSpec| !n.tap;
        self.nodes
            .iter()
            .filter(own)
            .filter(|n| {
                !self
                    .nodes
                    .iter()
                    .filter(own)
                    .any(|m| m.inputs.iter().any(|i| i.node == n.id && !i.feedback))
            })
            .collect()
    }

    /// Whether some node of the graph reads an output of node `id` (feedback inputs do
    /// not count: they take the newest message and lose nothing when a writer leaves).
    pub fn is_read(&self, id: &str) -> bool {
        self.nodes
            .iter()
            .any(|n| n.inputs.iter().any(|i| i.node == id && !i.feedback))
    }
}

/// Whether `text` matches `pattern`, where `*` stands for any run of characters.
pub fn glob_match(pattern: &str, text: &str) -> bool {
    let (p, t) = (pattern.as_bytes(), text.as_bytes());
    // Greedy match with backtracking to the last star: linear for one star, fine for a few.
    let (mut pi, mut ti, mut star, mut mark) = (0, 0, None, 0);
    while ti < t.len() {
        if pi < p.len() && p[pi] == b'*' {
            star = Some(pi);
            mark = ti;
            pi += 1;
        } else if pi < p.len() && p[pi] == t[ti] {
            pi += 1;
            ti += 1;
        } else if let Some(s) = star {
            pi = s + 1;
            mark += 1;
            ti = mark;
        } else {
            return false;
        }
    }
    p[pi..].iter().all(|&c| c == b'*')
}

impl Graph {
    /// Every output of the graph as `(NODE/OUTPUT, message)`, producers first.
    pub fn edges(&self) -> Vec<(String, MessageKind)> {
        self.nodes
            .iter()
            .flat_map(|n| self.output_edges(&n.id))
            .collect()
    }

    /// The outputs of node `id` as `(NODE/OUTPUT, message)`, in its port order.
    pub fn output_edges(&self, id: &str) -> Vec<(String, MessageKind)> {
        self.node(id).map_or_else(Vec::new, |n| {
            n.outputs
                .iter()
                .map(|(p, k)| (format!("{id}/{p}"), *k))
                .collect()
        })
    }

    /// The inputs of node `id` as `(NODE/OUTPUT, message)`, in its port order.
    pub fn input_edges(&self, id: &str) -> Vec<(String, MessageKind)> {
        self.node(id).map_or_else(Vec::new, |n| {
            n.inputs
                .iter()
                .filter_map(|i| {
                    let (_, kind) = self
                        .node(&i.node)?
                        .outputs
                        .iter()
                        .find(|(o, _)| *o == i.output)?;
                    Some((format!("{}/{}", i.node, i.output), *kind))
                })
                .collect()
        })
    }

    /// Adds node `id` of built-in `kind` reading every edge that matches one of `patterns`
    /// (`NODE/OUTPUT`, `*` for any characters; no pattern: every edge), each under the port
    /// `NODE.OUTPUT` and with the edge's own queue settings. A pattern that matches nothing
    /// is an error that lists the edges.
    pub fn add_tap(
        &mut self,
        id: &str,
        kind: &str,
        patterns: &[String],
        params: toml::Table,
    ) -> Result<(), String> {
        if self.node(id).is_some() {
            return Err(format!("the graph already has a node '{id}'"));
        }
        let edges = self.edges();
        for p in patterns {
            if !edges.iter().any(|(e, _)| glob_match(p, e)) {
                return Err(format!(
                    "no edge matches '{p}'; the edges: {}",
                    edges
                        .iter()
                        .map(|(e, _)| e.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ));
            }
        }
        let inputs = edges
            .iter()
            .filter(|(e, _)| patterns.is_empty() || patterns.iter().any(|p| glob_match(p, e)))
            .map(|(e, _)| {
                let (node, output) = e.split_once('/').expect("NODE/OUTPUT");
                Input {
                    port: format!("{node}.{output}"),
                    node: node.into(),
                    output: output.into(),
                    edge: self.edge_config(node, output),
                    feedback: false,
                }
            })
            .collect();
        self.nodes.push(NodeSpec {
            id: id.into(),
            runner: Runner::Builtin(kind.into()),
            inputs,
            outputs: Vec::new(),
            params,
            restart: Restart::default(),
            tap: true,
            logs: false,
            in_flight: None,
            host: None,
        });
        Ok(())
    }

    /// Turns nodes `ids` into sources of built-in `kind` (their outputs stay, their inputs
    /// go; `params` gains `node = ID`), then drops the nodes that fed only them.
    pub fn replace_with_sources(
        &mut self,
        ids: &[String],
        kind: &str,
        params: &toml::Table,
    ) -> Result<(), String> {
        let read_before: Vec<String> = self
            .nodes
            .iter()
            .filter(|n| self.is_read(&n.id))
            .map(|n| n.id.clone())
            .collect();
        for id in ids {
            let names = self
                .nodes
                .iter()
                .map(|n| n.id.as_str())
                .collect::<Vec<_>>()
                .join(", ");
            let Some(n) = self.nodes.iter_mut().find(|n| n.id == *id) else {
                return Err(format!("no node '{id}' to replace; the nodes: {names}"));
            };
            if n.outputs.is_empty() {
                return Err(format!("node '{id}' has no outputs to replay"));
            }
            n.runner = Runner::Builtin(kind.into());
            n.inputs.clear();
            n.params = params.clone();
            n.params
                .insert("node".into(), toml::Value::String(id.clone()));
            n.restart = Restart::default();
        }
        // A node that fed only replaced nodes has nobody to feed now.
        loop {
            let idle: Vec<String> = self
                .nodes
                .iter()
                .filter(|n| read_before.contains(&n.id) && !self.is_read(&n.id))
                .map(|n| n.id.clone())
                .collect();
            if idle.is_empty() {
                return Ok(());
            }
            self.nodes.retain(|n| !idle.contains(&n.id));
        }
    }
}

/// A node's inputs as `(NODE/OUTPUT, message expected, byte offset in the file)`.
type Wanted = Vec<(String, MessageKind, usize)>;

/// A parsed, not yet validated, launch file.
#[derive(Clone, Debug)]
pub struct LaunchFile {
    path: PathBuf,
    text: String,
    decl: FileDecl,
}

fn line_of(text: &str, offset: usize) -> usize {
    text[..offset.min(text.len())]
        .bytes()
        .filter(|&b| b == b'\n')
        .count()
        + 1
}

/// Launch-file text with parameters overridden, as `run --set` does: each of `overrides`
/// is `NODE.PARAM=VALUE` (`PARAM` may be a dotted path into a table, `VALUE` any TOML
/// value, or else taken as a string). The result (comments dropped, the overrides named in
/// its first lines) is parsed and checked as any launch file, and is what a recording
/// stores, so that a replay runs what ran.
pub fn with_overrides(path: &Path, text: &str, overrides: &[String]) -> Result<String, String> {
    let mut doc: toml::Table =
        toml::from_str(text).map_err(|e| format!("{}: {}", path.display(), e.message()))?;
    for spec in overrides {
        let bad = |why: &str| {
            format!(
                "--set '{spec}': {why}; give NODE.PARAM=VALUE, e.g. manipulator-bridge.listen=127.0.0.1:7879"
            )
        };
        let (lhs, value) = spec.split_once('=').ok_or_else(|| bad("no '='"))?;
        let (node, param) = lhs
            .split_once('.')
            .ok_or_else(|| bad("no '.' between the node and its parameter"))?;
        let keys: Vec<&str> = param.split('.').collect();
        if node.is_empty() || keys.iter().any(|k| k.is_empty()) {
            return Err(bad("an empty name"));
        }
        let value = toml::from_str::<toml::Table>(&format!("v = {value}"))
            .ok()
            .and_then(|mut t| t.remove("v"))
            .unwrap_or_else(|| toml::Value::String(value.to_string()));
        let nodes = doc
            .get_mut("node")
            .and_then(|n| n.as_array_mut())
            .ok_or_else(|| bad("the launch file has no [[node]]"))?;
        let ids: Vec<String> = nodes
            .iter()
            .filter_map(|n| n.get("id").and_then(|i| i.as_str()).map(String::from))
            .collect();
        let Some(decl) = nodes
            .iter_mut()
            .find(|n| n.get("id").and_then(|i| i.as_str()) == Some(node))
        else {
            return Err(format!(
                "--set '{spec}': no node '{node}' in {}; its nodes: {}",
                path.display(),
                ids.join(", ")
            ));
        };
        let decl = decl
            .as_table_mut()
            .ok_or_else(|| bad("the node is not a table"))?;
        let mut table = decl
            .entry("params")
            .or_insert_with(|| toml::Value::Table(toml::Table::new()))
            .as_table_mut()
            .ok_or_else(|| bad("the node's params are not a table"))?;
        for k in &keys[..keys.len() - 1] {
            table = table
                .entry(k.to_string())
                .or_insert_with(|| toml::Value::Table(toml::Table::new()))
                .as_table_mut()
                .ok_or_else(|| bad(&format!("'{k}' of node '{node}' is not a table")))?;
        }
        table.insert(keys[keys.len() - 1].to_string(), value);
    }
    let body = toml::to_string(&doc).map_err(|e| e.to_string())?;
    Ok(format!(
        "# {} with run --set {}\n{body}",
        path.display(),
        overrides.join(" --set ")
    ))
}

impl LaunchFile {
    /// Reads and parses `path`.
    pub fn read(path: &Path) -> Result<Self, LaunchErrors> {
        let text = std::fs::read_to_string(path).map_err(|e| {
            LaunchErrors(vec![LaunchError {
                file: path.display().to_string(),
                line: 0,
                message: format!("cannot read the launch file: {e}"),
            }])
        })?;
        Self::parse(path, &text)
    }

    /// Parses launch-file text (`path` names it in errors).
    pub fn parse(path: &Path, text: &str) -> Result<Self, LaunchErrors> {
        let decl: FileDecl = toml::from_str(text).map_err(|e| {
            LaunchErrors(vec![LaunchError {
                file: path.display().to_string(),
                line: e.span().map_or(0, |s| line_of(text, s.start)),
                message: format!(
                    "{}; see the launch.toml format in runtime/src/launch.rs",
                    e.message()
                ),
            }])
        })?;
        Ok(Self {
            path: path.into(),
            text: text.into(),
            decl,
        })
    }

    /// Checks the whole graph against the node kinds of `catalog`; every problem is
    /// reported. The checks run as passes: each node alone, then the in-flight outputs,
    /// the edges' kinds, the order (no cycle), the hosts and the edges' readers.
    pub fn validate(&self, catalog: &dyn Catalog) -> Result<Graph, LaunchErrors> {
        let mut f = Findings {
            file: self.path.display().to_string(),
            text: &self.text,
            errs: Vec::new(),
        };
        let mut seen: HashMap<String, usize> = HashMap::new();
        let nodes: Vec<(NodeSpec, Wanted)> = self
            .decl
            .node
            .iter()
            .filter_map(|n| self.node_pass(n, catalog, &mut seen, &mut f))
            .collect();
        self.in_flight_pass(&nodes, &mut f);
        edges_pass(&nodes, &mut f);
        let order = order_pass(&nodes, &seen, &mut f);
        self.hosts_pass(&mut f);
        readers_pass(&nodes, &seen, &mut f);
        if self.decl.node.is_empty() {
            f.errs.push(LaunchError {
                file: f.file.clone(),
                line: 0,
                message: "no [[node]] in the launch file".into(),
            });
        }
        let mut errs = f.errs;
        if !errs.is_empty() {
            errs.sort_by_key(|e| e.line);
            return Err(LaunchErrors(errs));
        }
        let mut slots: Vec<Option<NodeSpec>> = nodes.into_iter().map(|(n, _)| Some(n)).collect();
        Ok(Graph {
            file: self.path.clone(),
            text: self.text.clone(),
            nodes: order
                .into_iter()
                .map(|i| slots[i].take().expect("once"))
                .collect(),
            hosts: self
                .decl
                .hosts
                .iter()
                .map(|(k, v)| (k.clone(), v.get_ref().clone()))
                .collect(),
        })
    }

    /// One node on its own: its id, its kind or program and parameters, its inputs and its
    /// limits; `None` where it cannot be a node of the graph.
    fn node_pass(
        &self,
        n: &Spanned<NodeDecl>,
        catalog: &dyn Catalog,
        seen: &mut HashMap<String, usize>,
        f: &mut Findings,
    ) -> Option<(NodeSpec, Wanted)> {
        let at = n.span().start;
        let n = n.get_ref();
        let id = n.id.get_ref().clone();
        let id_at = n.id.span().start;
        if id.is_empty()
            || id.len() > 64
            || !id
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
        {
            f.err(
                id_at,
                format!(
                    "node id '{}' must be 1 to 64 letters, digits, '-' or '_'",
                    // A runaway id is shown by its start, not repeated whole.
                    match id.char_indices().nth(40) {
                        Some((i, _)) =>
                            format!("{}… ({} characters)", &id[..i], id.chars().count()),
                        None => id.clone(),
                    }
                ),
            );
        }
        if let Some(first) = seen.insert(id.clone(), id_at) {
            f.err(
                id_at,
                format!(
                    "duplicate node id '{id}' (first at line {}); give every node its own id",
                    line_of(&self.text, first)
                ),
            );
            return None;
        }
        let params = n
            .params
            .as_ref()
            .map(|p| p.get_ref().clone())
            .unwrap_or_default();
        let params_at = n.params.as_ref().map_or(at, |p| p.span().start);
        let connected: Vec<&str> = n.inputs.keys().map(String::as_str).collect();
        let (runner, spec) = runner_of(n, &id, at, (&params, params_at), &connected, catalog, f)?;
        let (mut inputs, wanted) = inputs_of(n, &id, &spec, f);
        // A node reads its inputs in the order its kind declares them: joined inputs
        // first, then feedback inputs.
        inputs.sort_by_key(|i| {
            spec.inputs
                .iter()
                .chain(&spec.feedback)
                .position(|p| p.name == i.port)
        });
        // A node whose inputs are all optional must still read one of them.
        if !spec.inputs.is_empty()
            && spec.inputs.iter().all(|p| p.optional)
            && n.inputs
                .keys()
                .all(|k| spec.feedback.iter().any(|f| f.name == *k))
        {
            f.err(
                at,
                format!(
                    "node '{id}' reads nothing; connect at least one of its inputs: {}",
                    port_names(&spec.inputs.iter().collect::<Vec<_>>())
                ),
            );
        }
        for p in spec.inputs.iter().filter(|p| !p.optional) {
            if !n.inputs.contains_key(&p.name) {
                f.err(
                    at,
                    format!(
                        "node '{id}': input '{}' is not connected; add inputs = {{ {} = \"NODE/OUTPUT\" }}",
                        p.name, p.name
                    ),
                );
            }
        }
        if let Some(r) = &n.restart
            && r.get_ref().backoff_ms > MAX_BACKOFF_MS
        {
            f.err(
                r.span().start,
                format!(
                    "node '{id}': backoff_ms = {} is out of range; give 0 to {MAX_BACKOFF_MS} (it doubles while a node keeps failing)",
                    r.get_ref().backoff_ms
                ),
            );
        }
        if let Some(r) = &n.restart
            && let Some(h) = r.get_ref().heartbeat_ms
            && !(MIN_HEARTBEAT_MS..=86_400_000).contains(&h)
        {
            f.err(
                r.span().start,
                format!(
                    "node '{id}': heartbeat_ms = {h} is out of range; give {MIN_HEARTBEAT_MS} to 86400000 (a node reports every 500 ms while it waits)"
                ),
            );
        }
        if let Some(fl) = &n.in_flight {
            let (at, fl) = (fl.span().start, fl.get_ref());
            if inputs.iter().any(|i| !i.feedback) {
                f.err(
                    at,
                    format!(
                        "node '{id}': in_flight is for sources (nodes that read no frames); give it to the node whose frames enter the graph"
                    ),
                );
            }
            if !(1..=MAX_IN_FLIGHT).contains(&fl.frames) {
                f.err(
                    at,
                    format!(
                        "node '{id}': in_flight.frames = {} is out of range; give 1 to {MAX_IN_FLIGHT}",
                        fl.frames
                    ),
                );
            }
            if fl.output().is_none() {
                f.err(
                    at,
                    format!(
                        "node '{id}': in_flight.after = \"{}\" is not NODE/OUTPUT; name the output whose frames count as done",
                        fl.after
                    ),
                );
            }
        }
        Some((
            NodeSpec {
                id,
                runner,
                inputs,
                outputs: spec
                    .outputs
                    .iter()
                    .map(|p| (p.name.clone(), p.kind))
                    .collect(),
                params,
                restart: n.restart.as_ref().map(|r| *r.get_ref()).unwrap_or_default(),
                tap: false,
                logs: false,
                in_flight: n.in_flight.as_ref().map(|f| f.get_ref().clone()),
                host: n.host.as_ref().map(|h| h.get_ref().clone()),
            },
            wanted,
        ))
    }

    /// A source's `in_flight` names an existing output.
    fn in_flight_pass(&self, nodes: &[(NodeSpec, Wanted)], f: &mut Findings) {
        for n in &self.decl.node {
            let Some(fl) = &n.get_ref().in_flight else {
                continue;
            };
            let Some((src, out)) = fl.get_ref().output() else {
                continue;
            };
            let exists = nodes
                .iter()
                .any(|(p, _)| p.id == src && p.outputs.iter().any(|(o, _)| o == out));
            if !exists {
                f.err(
                    fl.span().start,
                    format!(
                        "node '{}': in_flight.after = \"{src}/{out}\" is no node's output; name the output whose frames count as done",
                        n.get_ref().id.get_ref()
                    ),
                );
            }
        }
    }

    /// Every node on a host the file declares, where it declares any.
    fn hosts_pass(&self, f: &mut Findings) {
        for (name, h) in &self.decl.hosts {
            if name.is_empty()
                || name.len() > 64
                || !name
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
            {
                f.err(
                    h.span().start,
                    format!(
                        "[hosts.{name}]: a host name is 1 to 64 letters, digits, '-', '_' or '.'"
                    ),
                );
            }
        }
        for n in &self.decl.node {
            let d = n.get_ref();
            match (&d.host, self.decl.hosts.is_empty()) {
                (Some(h), true) => f.err(
                    h.span().start,
                    format!(
                        "node '{}': host = \"{}\" but the file declares no [hosts]; add [hosts.{}] with its link's listen/connect endpoints",
                        d.id.get_ref(),
                        h.get_ref(),
                        h.get_ref()
                    ),
                ),
                (Some(h), false) if !self.decl.hosts.contains_key(h.get_ref()) => f.err(
                    h.span().start,
                    format!(
                        "node '{}': no host '{}' in [hosts]; the hosts: {}",
                        d.id.get_ref(),
                        h.get_ref(),
                        self.decl
                            .hosts
                            .keys()
                            .cloned()
                            .collect::<Vec<_>>()
                            .join(", ")
                    ),
                ),
                (None, false) => f.err(
                    n.span().start,
                    format!(
                        "node '{}' has no host; in a launch file with [hosts] every node names the host that runs it",
                        d.id.get_ref()
                    ),
                ),
                _ => {}
            }
        }
    }
}

/// A launch file's problems as its passes find them, each with its line.
struct Findings<'a> {
    file: String,
    text: &'a str,
    errs: Vec<LaunchError>,
}

impl Findings<'_> {
    /// A problem at byte `at` of the file.
    fn err(&mut self, at: usize, message: String) {
        self.errs.push(LaunchError {
            file: self.file.clone(),
            line: line_of(self.text, at),
            message,
        });
    }
}

/// A node's runner and its kind's ports: a built-in kind (its parameters checked) or a
/// program (asked for its ports, which must agree with any the file writes).
#[allow(clippy::too_many_arguments)]
fn runner_of(
    n: &NodeDecl,
    id: &str,
    at: usize,
    (params, params_at): (&toml::Table, usize),
    connected: &[&str],
    catalog: &dyn Catalog,
    f: &mut Findings,
) -> Option<(Runner, KindSpec)> {
    Some(match (&n.kind, &n.exec) {
        (Some(k), None) => match catalog.spec(k.get_ref()) {
            Some(spec) => {
                if let Err(m) = catalog.check(k.get_ref(), params, connected) {
                    f.err(params_at, format!("node '{id}': bad params: {m}"));
                }
                (Runner::Builtin(k.get_ref().clone()), spec)
            }
            None => {
                f.err(
                    k.span().start,
                    format!(
                        "node '{id}': unknown kind '{}'; known kinds: {}, or use exec = \"path\"",
                        k.get_ref(),
                        catalog.kinds().join(", ")
                    ),
                );
                return None;
            }
        },
        (None, Some(e)) => {
            let program = PathBuf::from(e.get_ref());
            let spec = match catalog.exec(&program, params, connected) {
                Ok(spec) => spec,
                Err(m) => {
                    f.err(e.span().start, format!("node '{id}': {m}"));
                    return None;
                }
            };
            // Ports written in the launch file must be the ones the program declares.
            if let Some(p) = &n.ports {
                let said = p.get_ref();
                let of = |v: &[Port]| -> BTreeMap<String, MessageKind> {
                    v.iter().map(|p| (p.name.clone(), p.kind)).collect()
                };
                let inputs: BTreeMap<String, MessageKind> = of(&spec.inputs)
                    .into_iter()
                    .chain(of(&spec.feedback))
                    .collect();
                for (what, written, declared) in [
                    ("inputs", &said.inputs, inputs),
                    ("outputs", &said.outputs, of(&spec.outputs)),
                ] {
                    if *written != declared {
                        let show = |m: &BTreeMap<String, MessageKind>| {
                            m.iter()
                                .map(|(k, v)| format!("{k} = \"{}\"", v.name()))
                                .collect::<Vec<_>>()
                                .join(", ")
                        };
                        f.err(
                            p.span().start,
                            format!(
                                "node '{id}': ports say {what} {{ {} }} but {} declares {{ {} }}; fix or remove ports",
                                show(written),
                                program.display(),
                                show(&declared)
                            ),
                        );
                    }
                }
            }
            (Runner::Exec(program), spec)
        }
        _ => {
            f.err(
                at,
                format!("node '{id}': give exactly one of kind = \"…\" or exec = \"…\""),
            );
            return None;
        }
    })
}

/// A node's inputs as its kind declares them, and the outputs they read (checked once
/// every node is known).
fn inputs_of(n: &NodeDecl, id: &str, spec: &KindSpec, f: &mut Findings) -> (Vec<Input>, Wanted) {
    let mut inputs = Vec::new();
    let mut wanted = Vec::new();
    for (port, decl) in &n.inputs {
        let iat = decl.span().start;
        let is_feedback = spec.feedback.iter().any(|p| p.name == *port);
        let Some(declared) = spec
            .inputs
            .iter()
            .chain(&spec.feedback)
            .find(|p| p.name == *port)
        else {
            let all: Vec<&Port> = spec.inputs.iter().chain(&spec.feedback).collect();
            f.err(
                iat,
                format!(
                    "node '{id}' has no input '{port}'; its inputs: {}",
                    port_names(&all)
                ),
            );
            continue;
        };
        let kind = declared.kind;
        let (from, depth, overflow) = match decl.get_ref() {
            InputDecl::Source(s) => (s.clone(), None, None),
            InputDecl::Full {
                from,
                depth,
                overflow,
            } => (from.clone(), *depth, *overflow),
        };
        let Some((src, out)) = from.split_once('/') else {
            f.err(
                iat,
                format!("node '{id}' input '{port}': '{from}' must be NODE/OUTPUT"),
            );
            continue;
        };
        let mut edge = EdgeConfig::default();
        if let Some(d) = depth {
            if d == 0 || d > 64 {
                f.err(
                    iat,
                    format!("node '{id}' input '{port}': depth {d} must be 1..=64"),
                );
            }
            edge.depth = d;
        }
        if let Some(o) = overflow {
            edge.overflow = o;
        }
        if is_feedback {
            if depth.is_some_and(|d| d != 1) || overflow == Some(Overflow::Block) {
                f.err(
                    iat,
                    format!(
                        "node '{id}' input '{port}' is a feedback input: it always takes the newest message (depth 1, drop-oldest); remove depth and overflow"
                    ),
                );
            }
            edge = EdgeConfig {
                depth: 1,
                overflow: Overflow::DropOldest,
            };
        }
        wanted.push((format!("{src}/{out}"), kind, iat));
        inputs.push(Input {
            port: port.clone(),
            node: src.into(),
            output: out.into(),
            edge,
            feedback: is_feedback,
        });
    }
    (inputs, wanted)
}

/// Every input names an existing output of the right message type.
fn edges_pass(nodes: &[(NodeSpec, Wanted)], f: &mut Findings) {
    for (node, wanted) in nodes {
        for (from, kind, iat) in wanted {
            let (src, out) = from.split_once('/').expect("checked");
            let Some((producer, _)) = nodes.iter().find(|(n, _)| n.id == src) else {
                f.err(
                    *iat,
                    format!(
                        "node '{}' reads '{from}' but there is no node '{src}'",
                        node.id
                    ),
                );
                continue;
            };
            match producer.outputs.iter().find(|(p, _)| p == out) {
                None => f.err(
                    *iat,
                    format!(
                        "node '{}' reads '{from}' but '{src}' has no output '{out}'; its outputs: {}",
                        node.id,
                        names(&producer.outputs)
                    ),
                ),
                Some((_, m)) if m != kind => f.err(
                    *iat,
                    format!(
                        "node '{}' reads '{from}', which carries {m:?}, but expects {kind:?}",
                        node.id
                    ),
                ),
                Some(_) => {}
            }
        }
    }
}

/// The nodes' order, producers first; what remains sits on a cycle.
fn order_pass(
    nodes: &[(NodeSpec, Wanted)],
    seen: &HashMap<String, usize>,
    f: &mut Findings,
) -> Vec<usize> {
    let mut order: Vec<usize> = Vec::new();
    let mut placed = vec![false; nodes.len()];
    loop {
        let before = order.len();
        for (i, (n, _)) in nodes.iter().enumerate() {
            if !placed[i]
                && n.inputs.iter().filter(|i| !i.feedback).all(|inp| {
                    nodes
                        .iter()
                        .position(|(m, _)| m.id == inp.node)
                        .is_none_or(|j| placed[j])
                })
            {
                placed[i] = true;
                order.push(i);
            }
        }
        if order.len() == before {
            break;
        }
    }
    if order.len() < nodes.len() {
        let on_cycle: Vec<&str> = nodes
            .iter()
            .enumerate()
            .filter(|(i, _)| !placed[*i])
            .map(|(_, (n, _))| n.id.as_str())
            .collect();
        let at = seen.get(on_cycle[0]).copied().unwrap_or(0);
        f.err(
            at,
            format!(
                "the graph has a cycle through {}; an edge must not lead back to its own producer",
                on_cycle.join(", ")
            ),
        );
    }
    order
}

/// An edge holds so many readers; the graph leaves room for the ones added to it (a
/// recorder, a viewer, the link to another host, a watcher such as `topic`).
fn readers_pass(nodes: &[(NodeSpec, Wanted)], seen: &HashMap<String, usize>, f: &mut Findings) {
    let mut readers: BTreeMap<(&str, &str), usize> = BTreeMap::new();
    for (n, _) in nodes {
        for i in &n.inputs {
            *readers.entry((&i.node, &i.output)).or_default() += 1;
        }
    }
    for ((node, output), n) in readers {
        if n > MAX_GRAPH_READERS {
            f.err(
                seen.get(node).copied().unwrap_or(0),
                format!(
                    "edge '{node}/{output}' has {n} readers; an edge of a launch file takes at most {MAX_GRAPH_READERS} (iceoryx2 holds {} per edge, with room kept for a recorder, a viewer, the link between hosts and a watcher): let fewer nodes read it, or pass it on through a node",
                    crate::transport::MAX_READERS
                ),
            );
        }
    }
}

fn port_names(ports: &[&Port]) -> String {
    if ports.is_empty() {
        "none".into()
    } else {
        ports
            .iter()
            .map(|p| p.name.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    }
}

fn names(ports: &[(String, MessageKind)]) -> String {
    if ports.is_empty() {
        "none".into()
    } else {
        ports
            .iter()
            .map(|(p, _)| p.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// How long an `exec` node's program may take to describe itself.
const DESCRIBE_LIMIT: Duration = Duration::from_secs(10);

/// Asks an `exec` node's program for its ports, checking `params` with the inputs
/// `connected` (it runs `PROGRAM --describe --params TOML --connected a,b`).
pub fn describe_exec(
    program: &Path,
    params: &toml::Table,
    connected: &[&str],
) -> Result<KindSpec, String> {
    let mut child = std::process::Command::new(program)
        .arg("--describe")
        .arg("--params")
        .arg(toml::to_string(params).map_err(|e| e.to_string())?)
        .arg("--connected")
        .arg(connected.join(","))
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .map_err(|e| {
            format!(
                "cannot start '{}': {e}; build it or give the right path",
                program.display()
            )
        })?;
    let t0 = Instant::now();
    loop {
        match child.try_wait() {
            Ok(Some(_)) => break,
            Ok(None) if t0.elapsed() < DESCRIBE_LIMIT => {
                std::thread::sleep(Duration::from_millis(5))
            }
            _ => {
                let _ = child.kill();
                let _ = child.wait();
                return Err(format!(
                    "'{}' did not describe its ports within {} s (is it a microstereo node program?)",
                    program.display(),
                    DESCRIBE_LIMIT.as_secs()
                ));
            }
        }
    }
    let out = child.wait_with_output().map_err(|e| e.to_string())?;
    if !out.status.success() {
        let why = String::from_utf8_lossy(&out.stderr);
        let why = why.trim().trim_start_matches("error: ");
        return Err(if why.is_empty() {
            format!(
                "'{}' refused to describe its ports ({})",
                program.display(),
                out.status
            )
        } else {
            format!("bad params: {why}")
        });
    }
    serde_json::from_slice(&out.stdout).map_err(|e| {
        format!(
            "'{}' --describe did not print its ports ({e}); is it a microstereo node program (runtime::process::exec_main)?",
            program.display()
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn no_params(t: &toml::Table) -> Result<(), String> {
        match t.keys().next() {
            Some(k) => Err(format!("unknown parameter '{k}'")),
            None => Ok(()),
        }
    }

    fn seed_param(t: &toml::Table) -> Result<(), String> {
        for (k, v) in t {
            match (k.as_str(), v) {
                ("seed", toml::Value::Integer(_)) => {}
                ("seed", _) => return Err("'seed' must be an integer".into()),
                _ => return Err(format!("unknown parameter '{k}'")),
            }
        }
        Ok(())
    }

    fn port(name: &str, kind: MessageKind) -> Port {
        Port {
            name: name.into(),
            kind,
            optional: false,
        }
    }

    struct Kinds;

    impl Catalog for Kinds {
        fn kinds(&self) -> Vec<String> {
            vec!["source".into(), "filter".into(), "sink".into()]
        }
        fn spec(&self, k: &str) -> Option<KindSpec> {
            Some(match k {
                "source" => KindSpec {
                    inputs: vec![],
                    feedback: vec![Port {
                        optional: true,
                        ..port("state", MessageKind::Disparity)
                    }],
                    outputs: vec![port("frame", MessageKind::StereoFrame)],
                },
                "filter" => KindSpec {
                    inputs: vec![
                        port("frame", MessageKind::StereoFrame),
                        Port {
                            optional: true,
                            ..port("mask", MessageKind::Image)
                        },
                    ],
                    feedback: vec![],
                    outputs: vec![port("frame", MessageKind::StereoFrame)],
                },
                "sink" => KindSpec {
                    inputs: vec![port("disparity", MessageKind::Disparity)],
                    feedback: vec![],
                    outputs: vec![port("disparity", MessageKind::Disparity)],
                },
                "overlay" => KindSpec {
                    inputs: vec![Port {
                        optional: true,
                        ..port("mask", MessageKind::Image)
                    }],
                    feedback: vec![],
                    outputs: vec![],
                },
                _ => return None,
            })
        }
        fn check(&self, k: &str, t: &toml::Table, _: &[&str]) -> Result<(), String> {
            if k == "source" {
                seed_param(t)
            } else {
                no_params(t)
            }
        }
        fn exec(&self, p: &Path, _: &toml::Table, _: &[&str]) -> Result<KindSpec, String> {
            if p == Path::new("/opt/my-node") {
                Ok(KindSpec {
                    inputs: vec![port("frame", MessageKind::StereoFrame)],
                    feedback: vec![],
                    outputs: vec![port("cloud", MessageKind::PointCloud)],
                })
            } else {
                Err(format!("{} cannot be started", p.display()))
            }
        }
    }

    fn check(text: &str) -> Result<Graph, LaunchErrors> {
        LaunchFile::parse(Path::new("g.toml"), text)?.validate(&Kinds)
    }

    #[test]
    fn globs_match_whole_names() {
        for (p, t, want) in [
            ("a/frame", "a/frame", true),
            ("a/*", "a/frame", true),
            ("*/disparity", "match-lr/disparity", true),
            ("*/disparity", "match-lr/disparity2", false),
            ("*", "x/y", true),
            ("m*-*/d*", "match-lr/disparity", true),
            ("a/frame", "a/frames", false),
            ("b/*", "a/frame", false),
        ] {
            assert_eq!(glob_match(p, t), want, "{p} ~ {t}");
        }
    }

    fn chain() -> Graph {
        check(
            r#"
[[node]]
id = "a"
kind = "source"

[[node]]
id = "b"
kind = "filter"
inputs = { frame = { from = "a/frame", depth = 4, overflow = "block" } }

[[node]]
id = "c"
kind = "filter"
inputs = { frame = "b/frame" }
"#,
        )
        .unwrap()
    }

    #[test]
    fn a_tap_reads_the_matching_edges_with_their_settings() {
        let mut g = chain();
        g.add_tap("rec", "recorder", &["b/*".into()], toml::Table::new())
            .unwrap();
        let rec = g.node("rec").unwrap();
        assert_eq!(
            rec.inputs,
            [Input {
                port: "b.frame".into(),
                node: "b".into(),
                output: "frame".into(),
                edge: EdgeConfig::default(),
                feedback: false,
            }]
        );
        assert!(rec.tap);
        let mut g = chain();
        g.add_tap("rec", "recorder", &[], toml::Table::new())
            .unwrap();
        let ports: Vec<_> = g
            .node("rec")
            .unwrap()
            .inputs
            .iter()
            .map(|i| i.port.as_str())
            .collect();
        assert_eq!(ports, ["a.frame", "b.frame", "c.frame"]);
        assert_eq!(
            g.node("rec").unwrap().inputs[0].edge.overflow,
            Overflow::Block
        );
        let e = chain()
            .add_tap("rec", "recorder", &["x/*".into()], toml::Table::new())
            .unwrap_err();
        assert!(
            e.contains("no edge matches 'x/*'") && e.contains("a/frame, b/frame"),
            "{e}"
        );
    }

    #[test]
    fn an_unread_edge_follows_its_writers_inputs() {
        let mut lossless = chain();
        lossless.nodes.retain(|n| n.id != "c");
        // Nothing reads b/frame: a recorder on it must not lose what the graph keeps.
        assert_eq!(
            lossless.edge_config("b", "frame"),
            EdgeConfig {
                depth: 4,
                overflow: Overflow::Block
            }
        );
        // A lossy writer (c reads b/frame with the default queue) records lossy.
        assert_eq!(chain().edge_config("c", "frame"), EdgeConfig::default());
        // A source with no reader has nothing to follow.
        let lone = check("[[node]]\nid = \"a\"\nkind = \"source\"\n").unwrap();
        assert_eq!(lone.edge_config("a", "frame"), EdgeConfig::default());
    }

    #[test]
    fn replaced_nodes_become_sources_and_what_fed_only_them_goes() {
        let mut g = chain();
        let params = toml::Table::from_iter([("file".to_string(), toml::Value::from("r.mcap"))]);
        g.replace_with_sources(&["b".into()], "replay", &params)
            .unwrap();
        let ids: Vec<_> = g.nodes.iter().map(|n| n.id.as_str()).collect();
        assert_eq!(ids, ["b", "c"]);
        let b = g.node("b").unwrap();
        assert_eq!(b.runner, Runner::Builtin("replay".into()));
        assert!(b.inputs.is_empty());
        assert_eq!(b.params.get("node").and_then(|v| v.as_str()), Some("b"));
        assert_eq!(b.outputs, [("frame".to_string(), MessageKind::StereoFrame)]);
        let e = chain()
            .replace_with_sources(&["zz".into()], "replay", &params)
            .unwrap_err();
        assert!(e.contains("no node 'zz'") && e.contains("a, b, c"), "{e}");
    }

    #[test]
    fn a_sources_frames_in_flight_are_read_and_checked() {
        let text = |f: &str| {
            format!(
                "[[node]]\nid = \"a\"\nkind = \"source\"\n{f}\n\n[[node]]\nid = \"b\"\nkind = \"filter\"\ninputs = {{ frame = \"a/frame\" }}\n"
            )
        };
        let g = check(&text("in_flight = { after = \"b/frame\", frames = 2 }")).unwrap();
        let want = InFlight {
            after: "b/frame".into(),
            frames: 2,
        };
        assert_eq!(g.node("a").unwrap().in_flight, Some(want));
        // The source reads the output it waits on as newest-only: the writer never waits
        // for it.
        assert_eq!(
            g.edge_config("b", "frame"),
            EdgeConfig {
                depth: 1,
                overflow: Overflow::DropOldest
            }
        );
        assert_eq!(g.in_flight_readers("b", "frame").count(), 1);
        assert_eq!(check(&text("")).unwrap().node("a").unwrap().in_flight, None);
        for (bad, says) in [
            (
                "in_flight = { after = \"b/frame\", frames = 0 }",
                "frames = 0 is out of range",
            ),
            (
                "in_flight = { after = \"b/frame\", frames = 65 }",
                "frames = 65 is out of range",
            ),
            (
                "in_flight = { after = \"b\", frames = 1 }",
                "is not NODE/OUTPUT",
            ),
            (
                "in_flight = { after = \"c/frame\", frames = 1 }",
                "is no node's output",
            ),
            (
                "in_flight = { after = \"b/cloud\", frames = 1 }",
                "is no node's output",
            ),
            (
                "in_flight = { after = \"b/frame\", frames = 1, wait = 3 }",
                "unknown field",
            ),
        ] {
            let e = check(&text(bad)).unwrap_err().to_string();
            assert!(e.contains(says) && e.contains("g.toml:4"), "{bad}: {e}");
        }
        // Only a source lets frames in.
        let e = check(
            "[[node]]\nid = \"a\"\nkind = \"source\"\n\n[[node]]\nid = \"b\"\nkind = \"filter\"\ninputs = { frame = \"a/frame\" }\nin_flight = { after = \"b/frame\", frames = 1 }\n",
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("in_flight is for sources"), "{e}");
    }

    #[test]
    fn an_edge_read_by_more_nodes_than_it_holds_and_a_huge_back_off_are_refused() {
        let mut text = String::from("[[node]]\nid = \"a\"\nkind = \"source\"\n");
        for k in 0..MAX_GRAPH_READERS + 1 {
            text += &format!(
                "\n[[node]]\nid = \"f{k}\"\nkind = \"filter\"\ninputs = {{ frame = \"a/frame\" }}\n"
            );
        }
        let e = check(&text).unwrap_err().to_string();
        assert!(
            e.contains(&format!(
                "edge 'a/frame' has {} readers",
                MAX_GRAPH_READERS + 1
            )) && e.contains("g.toml:2:"),
            "{e}"
        );
        // As many as it holds are fine.
        let fine: String = text
            .split("\n[[node]]")
            .take(MAX_GRAPH_READERS + 1)
            .collect::<Vec<_>>()
            .join("\n[[node]]");
        assert!(check(&fine).is_ok());
        let e = check(
            "[[node]]\nid = \"a\"\nkind = \"source\"\nrestart = { policy = \"always\", backoff_ms = 600001 }\n",
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("backoff_ms = 600001 is out of range"), "{e}");
    }

    #[test]
    fn a_watchdog_time_is_read_and_checked() {
        let text = |h: &str| {
            format!(
                "[[node]]\nid = \"a\"\nkind = \"source\"\nrestart = {{ policy = \"on-failure\", heartbeat_ms = {h} }}\n"
            )
        };
        let g = check(&text("2000")).unwrap();
        assert_eq!(g.node("a").unwrap().restart.heartbeat_ms, Some(2000));
        for bad in ["0", "999", "100000000"] {
            let e = check(&text(bad)).unwrap_err().to_string();
            assert!(
                e.contains(&format!("heartbeat_ms = {bad} is out of range"))
                    && e.contains("g.toml:4:"),
                "{e}"
            );
        }
        assert_eq!(
            check("[[node]]\nid = \"a\"\nkind = \"source\"\n")
                .unwrap()
                .node("a")
                .unwrap()
                .restart
                .heartbeat_ms,
            None
        );
    }

    #[test]
    fn a_chain_validates_producers_first_with_queue_settings() {
        let g = check(
            r#"
[[node]]
id = "b"
kind = "filter"
inputs = { frame = { from = "a/frame", depth = 4, overflow = "block" } }
restart = { policy = "on-failure", max = 2 }

[[node]]
id = "a"
kind = "source"
params = { seed = 7 }

[[node]]
id = "c"
exec = "/opt/my-node"
inputs = { frame = "b/frame" }
ports = { inputs = { frame = "stereo-frame" }, outputs = { cloud = "point-cloud" } }
"#,
        )
        .unwrap();
        let ids: Vec<&str> = g.nodes.iter().map(|n| n.id.as_str()).collect();
        assert_eq!(ids, ["a", "b", "c"]);
        let b = g.node("b").unwrap();
        assert_eq!(
            b.inputs,
            vec![Input {
                port: "frame".into(),
                node: "a".into(),
                output: "frame".into(),
                edge: EdgeConfig {
                    depth: 4,
                    overflow: Overflow::Block
                },
                feedback: false,
            }]
        );
        assert_eq!(b.restart.policy, RestartPolicy::OnFailure);
        assert_eq!((b.restart.max, b.restart.backoff_ms), (2, 200));
        assert_eq!(
            g.node("c").unwrap().runner,
            Runner::Exec("/opt/my-node".into())
        );
        assert_eq!(g.node("c").unwrap().inputs[0].edge, EdgeConfig::default());
        assert_eq!(
            Graph::edge_name("run1", "a", "frame"),
            "microstereo/run1/a/frame"
        );
    }

    fn messages(text: &str) -> Vec<String> {
        check(text)
            .unwrap_err()
            .0
            .iter()
            .map(|e| e.to_string())
            .collect()
    }

    /// A runaway id (issue 19: 5,000 characters) is refused, and shown by its start only.
    #[test]
    fn a_runaway_id_is_refused_and_not_echoed_whole() {
        let id = "x".repeat(5000);
        let m = messages(&format!("[[node]]\nid = \"{id}\"\nkind = \"source\"\n"));
        assert!(
            m[0].contains("must be 1 to 64 letters") && m[0].contains("… (5000 characters)"),
            "{m:?}"
        );
        assert!(m[0].len() < 200, "{} characters", m[0].len());
    }

    #[test]
    fn every_problem_is_reported_with_its_line() {
        let m = messages(
            r#"[[node]]
id = "a"
kind = "source"
params = { seed = "x" }

[[node]]
id = "a"
kind = "source"

[[node]]
id = "f"
kind = "fliter"

[[node]]
id = "s"
kind = "sink"
inputs = { disparity = "a/frame" }

[[node]]
id = "t"
kind = "sink"
inputs = { disparity = "ghost/out", extra = "a/frame" }

[[node]]
id = "u"
kind = "sink"
"#,
        );
        assert_eq!(
            m,
            vec![
                "g.toml:4: node 'a': bad params: 'seed' must be an integer",
                "g.toml:7: duplicate node id 'a' (first at line 2); give every node its own id",
                "g.toml:12: node 'f': unknown kind 'fliter'; known kinds: source, filter, sink, or use exec = \"path\"",
                "g.toml:17: node 's' reads 'a/frame', which carries StereoFrame, but expects Disparity",
                "g.toml:22: node 't' has no input 'extra'; its inputs: disparity",
                "g.toml:22: node 't' reads 'ghost/out' but there is no node 'ghost'",
                "g.toml:24: node 'u': input 'disparity' is not connected; add inputs = { disparity = \"NODE/OUTPUT\" }",
            ]
        );
    }

    #[test]
    fn params_may_be_written_as_tables_of_their_own() {
        // `[node.params]` and `[node.params.sub]` headers, dotted keys: the same table as
        // inline `params = { … }` (toml 0.8 refused a sub-table without its parent header).
        let g = check(
            "[[node]]\nid = \"a\"\nkind = \"source\"\n\n[node.params]\nseed = 3\n\n[[node]]\nid = \"b\"\nkind = \"filter\"\ninputs = { frame = \"a/frame\" }\n",
        )
        .unwrap();
        assert_eq!(g.node("a").unwrap().params["seed"].as_integer(), Some(3));
        let f = LaunchFile::parse(
            Path::new("g.toml"),
            "[[node]]\nid = \"t\"\nkind = \"filter\"\n\n[node.params.calibration]\nbaseline = 1.5\n",
        )
        .unwrap();
        let p = f.decl.node[0].get_ref().params.as_ref().unwrap().get_ref();
        assert_eq!(p["calibration"]["baseline"].as_float(), Some(1.5));
    }

    #[test]
    fn optional_inputs_may_stay_open_but_a_task_must_read_something() {
        // The filter's optional mask is not connected: fine.
        let g = check(
            "[[node]]\nid = \"a\"\nkind = \"source\"\n\n[[node]]\nid = \"f\"\nkind = \"filter\"\ninputs = { frame = \"a/frame\" }\n",
        )
        .unwrap();
        assert_eq!(g.node("f").unwrap().inputs.len(), 1);
        // A node with only optional inputs and none connected reads nothing.
        let m = messages("[[node]]\nid = \"o\"\nkind = \"overlay\"\n");
        assert_eq!(
            m,
            vec!["g.toml:1: node 'o' reads nothing; connect at least one of its inputs: mask"]
        );
    }

    #[test]
    fn cycles_syntax_and_empty_files_are_refused() {
        let m = messages(
            r#"[[node]]
id = "x"
kind = "filter"
inputs = { frame = "y/frame" }

[[node]]
id = "y"
kind = "filter"
inputs = { frame = "x/frame" }
"#,
        );
        assert_eq!(
            m,
            vec![
                "g.toml:2: the graph has a cycle through x, y; an edge must not lead back to its own producer"
            ]
        );
        let e = check("[[node]]\nid = \"a\"\nkind = 3\n").unwrap_err();
        assert_eq!(e.0.len(), 1);
        assert_eq!(e.0[0].line, 3, "{e}");
        let e = check("[[node]]\nid = \"a\"\nkidn = \"source\"\n").unwrap_err();
        assert!(e.0[0].message.contains("kidn"), "{e}");
        assert_eq!(
            messages(""),
            vec!["g.toml:0: no [[node]] in the launch file"]
        );
        let m = messages(
            "[[node]]\nid = \"a\"\nkind = \"filter\"\ninputs = { frame = { from = \"a-frame\", depth = 0 } }\n",
        );
        assert_eq!(
            m,
            vec!["g.toml:4: node 'a' input 'frame': 'a-frame' must be NODE/OUTPUT"]
        );
    }
}
