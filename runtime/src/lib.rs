//! The runtime of microstereo: the node contract, the transport, the graph and how it runs.
//!
//! - [`node`]: the node contract of the `node-api` crate (one small trait per node role,
//!   typed ports, a params type), re-exported;
//! - [`registry`]: the node kinds a binary knows, built from those types;
//! - [`build`]: graphs built in code from node types and their typed ports;
//! - [`edge`]: queue settings of an edge and the frame clock; [`stats`]: what a node
//!   reports when it ends;
//! - [`launch`]: `launch.toml`, checked against the registry, and the graph rewrites
//!   (recorder and viewer taps, replay sources);
//! - [`exec`]: the in-process executor (one pipeline: `reconstruct`, `bench` and the tests
//!   run the graph's own node values);
//! - [`transport`] and [`process`]: iceoryx2 edges and one node as a process;
//! - [`supervisor`]: the graph as processes, restarts, stop and summary; [`status`]: what a
//!   running graph is doing now (for `top`, `topic` and the progress line); [`restarts`]: how
//!   the nodes downstream of a restarted one get over the frames it lost;
//! - [`harness`]: a node fed recorded inputs, its outputs compared with the recording;
//! - [`hop`]: the transport benchmark.

pub use node_api::{errln, outln, ports};

pub mod build;
pub mod edge;
pub mod exec;
pub mod harness;
pub mod hop;
pub mod launch;
pub mod node;
pub mod process;
pub mod registry;
pub mod restarts;
pub mod signals;
pub mod stats;
pub mod status;
pub mod supervisor;
pub mod transport;

pub use registry::Registry;
