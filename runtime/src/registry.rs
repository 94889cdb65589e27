//! The node kinds a binary knows: one list built from the node types.
//!
//! ```ignore
//! let kinds = Registry::new()
//!     .source::<capture::Capture>()
//!     .task::<segment::node::Segment>()
//!     .task::<matcher::node::Match>();
//! ```
//!
//! Each entry takes its ports, its parameter check and its constructor from the type's
//! [`Source`], [`Task`] or [`Sink`] impl, so the launch validator ([`crate::launch`])
//! checks a launch file against what the nodes themselves declare, and a new node is one
//! impl plus one line here.

use crate::launch::{Catalog, Graph, KindSpec, NodeSpec, Port};
use crate::node::{
    GraphNode, Params, PortDecl, PortSet, Sink, Source, Task, sink_node, source_node, task_node,
};
use crate::stats::NodeStats;

type Check = Box<dyn Fn(&toml::Table, &[&str]) -> Result<(), String> + Send + Sync>;
type Build = Box<dyn Fn(&NodeSpec) -> Result<Box<dyn GraphNode>, String> + Send + Sync>;
/// A tap's whole process: `(graph, instance, node id, frames)` to its statistics.
pub type TapMain =
    Box<dyn Fn(&Graph, &str, &str, Option<u64>) -> Result<NodeStats, String> + Send + Sync>;

enum How {
    Build(Build),
    Tap(TapMain),
}

struct Kind {
    name: String,
    spec: KindSpec,
    check: Check,
    how: How,
    /// Written in launch files (taps and replay sources are added by graph rewrites).
    launchable: bool,
}

/// The node kinds of a binary.
#[derive(Default)]
pub struct Registry {
    kinds: Vec<Kind>,
}

impl std::fmt::Debug for Registry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list()
            .entries(self.kinds.iter().map(|k| &k.name))
            .finish()
    }
}

/// Reads a `params` table (or part of one) into a settings type, without checks.
pub fn from_table<T: serde::de::DeserializeOwned>(t: &toml::Table) -> Result<T, String> {
    toml::Value::Table(t.clone())
        .try_into()
        .map_err(|e: toml::de::Error| e.message().to_string())
}

/// Reads a node's `params` table into its parameter type and checks it.
pub fn parse_params<P: Params>(t: &toml::Table) -> Result<P, String> {
    let p: P = from_table(t)?;
    p.check()?;
    Ok(p)
}

fn ports(decl: &[PortDecl]) -> Vec<Port> {
    decl.iter()
        .map(|p| Port {
            name: p.name.to_string(),
            kind: p.kind,
            optional: p.optional,
        })
        .collect()
}

/// The names of the node's joined (not feedback) inputs, in launch order.
fn joined(spec: &NodeSpec) -> Vec<String> {
    spec.inputs
        .iter()
        .filter(|i| !i.feedback)
        .map(|i| i.port.clone())
        .collect()
}

impl Registry {
    /// No kinds yet.
    pub fn new() -> Self {
        Self::default()
    }

    fn push(mut self, kind: Kind) -> Self {
        assert!(
            self.kinds.iter().all(|k| k.name != kind.name),
            "node kind '{}' registered twice",
            kind.name
        );
        self.kinds.push(kind);
        self
    }

    /// Adds a source kind.
    pub fn source<S: Source>(self) -> Self {
        assert!(
            S::Feedback::PORTS.iter().all(|p| p.optional),
            "{}: feedback ports are optional (Option<M>)",
            S::KIND
        );
        self.push(Kind {
            name: S::KIND.into(),
            spec: KindSpec {
                inputs: Vec::new(),
                feedback: ports(S::Feedback::PORTS),
                outputs: ports(S::Output::PORTS),
            },
            check: Box::new(|t, _| parse_params::<S::Params>(t).map(|_| ())),
            how: How::Build(Box::new(|spec: &NodeSpec| {
                let p = parse_params::<S::Params>(&spec.params)?;
                let node = S::new(p).map_err(|e| e.to_string())?;
                let all: Vec<String> = spec.inputs.iter().map(|i| i.port.clone()).collect();
                Ok(source_node(node, &all))
            })),
            launchable: true,
        })
    }

    /// Adds a task kind.
    pub fn task<T: Task>(self) -> Self {
        self.push(Kind {
            name: T::KIND.into(),
            spec: KindSpec {
                inputs: ports(T::Input::PORTS),
                feedback: Vec::new(),
                outputs: ports(T::Output::PORTS),
            },
            check: Box::new(|t, connected| {
                let p = parse_params::<T::Params>(t)?;
                T::check_inputs(&p, connected)
            }),
            how: How::Build(Box::new(|spec: &NodeSpec| {
                let p = parse_params::<T::Params>(&spec.params)?;
                let node = T::new(p).map_err(|e| e.to_string())?;
                Ok(task_node(node, &joined(spec)))
            })),
            launchable: true,
        })
    }

    /// Adds a sink kind.
    pub fn sink<K: Sink>(self) -> Self {
        self.push(Kind {
            name: K::KIND.into(),
            spec: KindSpec {
                inputs: ports(K::Input::PORTS),
                feedback: Vec::new(),
                outputs: Vec::new(),
            },
            check: Box::new(|t, _| parse_params::<K::Params>(t).map(|_| ())),
            how: How::Build(Box::new(|spec: &NodeSpec| {
                let p = parse_params::<K::Params>(&spec.params)?;
                let node = K::new(p).map_err(|e| e.to_string())?;
                Ok(sink_node(node, &joined(spec)))
            })),
            launchable: true,
        })
    }

    /// Adds a kind that graph rewrites put in (not written in launch files) and whose ports
    /// the rewrite sets: `build` makes its node from the node's whole spec.
    pub fn rewritten(
        self,
        name: &str,
        build: impl Fn(&NodeSpec) -> Result<Box<dyn GraphNode>, String> + Send + Sync + 'static,
    ) -> Self {
        self.push(Kind {
            name: name.into(),
            spec: KindSpec::default(),
            check: Box::new(|_, _| Ok(())),
            how: How::Build(Box::new(build)),
            launchable: false,
        })
    }

    /// Adds a tap kind (a recorder): a node that a graph rewrite connects to edges and that
    /// runs its own process loop `main` instead of stepping on joined frames.
    pub fn tap(
        self,
        name: &str,
        main: impl Fn(&Graph, &str, &str, Option<u64>) -> Result<NodeStats, String>
        + Send
        + Sync
        + 'static,
    ) -> Self {
        self.push(Kind {
            name: name.into(),
            spec: KindSpec::default(),
            check: Box::new(|_, _| Ok(())),
            how: How::Tap(Box::new(main)),
            launchable: false,
        })
    }

    fn kind(&self, name: &str) -> Option<&Kind> {
        self.kinds.iter().find(|k| k.name == name)
    }

    /// Builds the node value of node `spec` (of one of these kinds).
    pub fn build(&self, spec: &NodeSpec) -> Result<Box<dyn GraphNode>, String> {
        let kind = spec.kind().ok_or_else(|| {
            format!(
                "node '{}' runs a program of its own; it cannot run in this process",
                spec.id
            )
        })?;
        match self.kind(kind).map(|k| &k.how) {
            Some(How::Build(b)) => b(spec),
            Some(How::Tap(_)) => Err(format!("node '{}' is a tap: it runs as a process", spec.id)),
            None => Err(format!("unknown kind '{kind}'")),
        }
    }

    /// The one kind of a node program of its own (`exec` in a launch file).
    fn only(&self) -> Result<&Kind, String> {
        let mut it = self.kinds.iter().filter(|k| k.launchable);
        match (it.next(), it.next()) {
            (Some(k), None) => Ok(k),
            _ => Err(format!(
                "this program holds {} node kinds ({}); an exec node's program holds one",
                self.kinds.iter().filter(|k| k.launchable).count(),
                self.kinds()
                    .iter()
                    .map(String::as_str)
                    .collect::<Vec<_>>()
                    .join(", ")
            )),
        }
    }

    /// Builds node `spec` as the one kind this program holds (an `exec` node).
    pub fn build_as_only_kind(&self, spec: &NodeSpec) -> Result<Box<dyn GraphNode>, String> {
        match &self.only()?.how {
            How::Build(b) => b(spec),
            How::Tap(_) => Err(format!("node '{}' is a tap: it runs as a process", spec.id)),
        }
    }

    /// The ports of the one kind this program holds, once `params` (with the inputs
    /// `connected`) pass its check.
    pub fn describe_only_kind(
        &self,
        params: &toml::Table,
        connected: &[String],
    ) -> Result<KindSpec, String> {
        let k = self.only()?;
        let connected: Vec<&str> = connected.iter().map(String::as_str).collect();
        (k.check)(params, &connected)?;
        Ok(k.spec.clone())
    }

    /// The process loop of a tap kind.
    pub fn tap_main(&self, kind: &str) -> Option<&TapMain> {
        match self.kind(kind).map(|k| &k.how) {
            Some(How::Tap(m)) => Some(m),
            _ => None,
        }
    }
}

impl Catalog for Registry {
    fn kinds(&self) -> Vec<String> {
        self.kinds
            .iter()
            .filter(|k| k.launchable)
            .map(|k| k.name.clone())
            .collect()
    }

    fn spec(&self, kind: &str) -> Option<KindSpec> {
        self.kind(kind)
            .filter(|k| k.launchable)
            .map(|k| k.spec.clone())
    }

    fn check(&self, kind: &str, params: &toml::Table, connected: &[&str]) -> Result<(), String> {
        match self.kind(kind) {
            Some(k) => (k.check)(params, connected),
            None => Err(format!("unknown kind '{kind}'")),
        }
    }
}
