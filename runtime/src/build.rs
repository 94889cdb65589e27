//! Graphs built in code from node types: each node's kind from its type's `KIND`, each
//! edge from the two ends' typed ports (a [`Port`] of one message type connects only to a
//! port of the same), the parameters from the node's own params type. The result is a
//! launch file's text, checked by the same validator as any launch file; a run's results
//! are read by the same typed handles ([`crate::exec::Frame::read`]).
//!
//! ```
//! use runtime::build::GraphBuilder;
//! # use runtime::node::{NoParams, NoPorts, NodeError, Params, Source, Stamp, Task};
//! # runtime::ports! { pub struct Out { pub frame: schemas::StereoFrame } }
//! # runtime::ports! { pub struct In { pub frame: schemas::StereoFrame } }
//! # struct Camera;
//! # impl Source for Camera {
//! #     const KIND: &'static str = "camera";
//! #     type Params = NoParams;
//! #     type Output = Out;
//! #     type Feedback = NoPorts;
//! #     type Error = NodeError;
//! #     fn new(_: NoParams) -> Result<Self, NodeError> { Ok(Camera) }
//! #     fn produce(&mut self, _: u64) -> Result<Option<(u64, Out)>, NodeError> { Ok(None) }
//! # }
//! # struct Blur;
//! # impl Task for Blur {
//! #     const KIND: &'static str = "blur";
//! #     type Params = NoParams;
//! #     type Input = In;
//! #     type Output = Out;
//! #     type Error = NodeError;
//! #     fn new(_: NoParams) -> Result<Self, NodeError> { Ok(Blur) }
//! #     fn process(&mut self, _: Stamp, i: In) -> Result<Out, NodeError> { Ok(Out { frame: i.frame }) }
//! # }
//! let mut g = GraphBuilder::new();
//! let cam = g.source::<Camera>("cam", toml::Table::new());
//! let blur = g.task::<Blur>("blur", toml::Table::new());
//! g.connect(&blur, In::frame, &cam.out(Out::frame));
//! assert!(g.launch_text().contains("kind = \"blur\""));
//! ```

use crate::node::{NoPorts, Port, Sink, Source, Task};
use std::marker::PhantomData;

/// A node added to a [`GraphBuilder`]: its id, and the port sets of its inputs `I` and
/// outputs `O` (a source's inputs are its feedback).
pub struct Handle<I, O> {
    id: String,
    index: usize,
    of: PhantomData<fn() -> (I, O)>,
}

impl<I, O> Handle<I, O> {
    /// Its output `port`, to connect or to read a run's result by.
    pub fn out<M>(&self, port: Port<O, M>) -> Out<M> {
        Out {
            node: self.id.clone(),
            port: port.name(),
            of: PhantomData,
        }
    }
}

/// One node's output port in a built graph, carrying `M`.
pub struct Out<M> {
    node: String,
    port: &'static str,
    of: PhantomData<fn() -> M>,
}

impl<M> Out<M> {
    /// The node's id.
    pub fn node(&self) -> &str {
        &self.node
    }

    /// The port's name.
    pub fn port(&self) -> &'static str {
        self.port
    }
}

impl<M> Clone for Out<M> {
    fn clone(&self) -> Self {
        Self {
            node: self.node.clone(),
            port: self.port,
            of: PhantomData,
        }
    }
}

impl<M> std::fmt::Debug for Out<M> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.node, self.port)
    }
}

/// One node as the builder keeps it until the text is written.
struct Entry {
    id: String,
    kind: &'static str,
    inputs: Vec<(&'static str, String)>,
    params: toml::Table,
}

/// A graph under construction, in the order its nodes are added.
#[derive(Default)]
pub struct GraphBuilder {
    nodes: Vec<Entry>,
}

impl GraphBuilder {
    /// No nodes yet.
    pub fn new() -> Self {
        Self::default()
    }

    fn add<I, O>(&mut self, id: &str, kind: &'static str, params: toml::Table) -> Handle<I, O> {
        self.nodes.push(Entry {
            id: id.into(),
            kind,
            inputs: Vec::new(),
            params,
        });
        Handle {
            id: id.into(),
            index: self.nodes.len() - 1,
            of: PhantomData,
        }
    }

    /// Adds a source of type `S` named `id` with the launch file's `params` keys.
    pub fn source<S: Source>(
        &mut self,
        id: &str,
        params: toml::Table,
    ) -> Handle<S::Feedback, S::Output> {
        self.add(id, S::KIND, params)
    }

    /// Adds a task of type `T` named `id` with the launch file's `params` keys.
    pub fn task<T: Task>(&mut self, id: &str, params: toml::Table) -> Handle<T::Input, T::Output> {
        self.add(id, T::KIND, params)
    }

    /// Adds a sink of type `K` named `id` with the launch file's `params` keys.
    pub fn sink<K: Sink>(&mut self, id: &str, params: toml::Table) -> Handle<K::Input, NoPorts> {
        self.add(id, K::KIND, params)
    }

    /// Feeds `to`'s input `port` from the output `from`: both carry `M`.
    pub fn connect<I, O, M>(&mut self, to: &Handle<I, O>, port: Port<I, M>, from: &Out<M>) {
        self.nodes[to.index]
            .inputs
            .push((port.name(), format!("{}/{}", from.node, from.port)));
    }

    /// The graph as launch-file text: its `[[node]]` tables in the order added.
    pub fn launch_text(&self) -> String {
        let nodes = self
            .nodes
            .iter()
            .map(|e| {
                let mut n = toml::Table::new();
                n.insert("id".into(), e.id.clone().into());
                n.insert("kind".into(), e.kind.into());
                if !e.inputs.is_empty() {
                    let i: toml::Table = e
                        .inputs
                        .iter()
                        .map(|(p, from)| (p.to_string(), toml::Value::from(from.as_str())))
                        .collect();
                    n.insert("inputs".into(), toml::Value::Table(i));
                }
                if !e.params.is_empty() {
                    n.insert("params".into(), toml::Value::Table(e.params.clone()));
                }
                toml::Value::Table(n)
            })
            .collect();
        let doc = toml::Table::from_iter([("node".to_string(), toml::Value::Array(nodes))]);
        toml::to_string(&doc).expect("a launch table serialises")
    }
}

/// `v` as a launch file's `params` table (empty where it is not a table).
pub fn params_of<T: serde::Serialize>(v: &T) -> toml::Table {
    match toml::Value::try_from(v) {
        Ok(toml::Value::Table(t)) => t,
        _ => toml::Table::new(),
    }
}
