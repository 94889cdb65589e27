//! The runtime of microstereo: the node contract, the transport, the graph and how it runs.
//!
//! - [`node`]: one small trait per node role ([`node::Source`], [`node::Task`],
//!   [`node::Sink`]) with typed ports ([`ports!`]) and a params type;
//! - [`registry`]: the node kinds a binary knows, built from those types;
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

/// `println!` for what the graph commands print on stdout: a reader that went away (`| head
/// -1`) is not an error of the run. The graph commands keep SIGPIPE ignored (a node's pipe
/// closing must not kill the supervisor), so `println!` would panic on the closed stdout.
#[macro_export]
macro_rules! outln {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout(), $($t)*);
    }};
}

/// `eprintln!` that never panics: a full disk (`2>/dev/full`), a closed terminal or a pipe
/// whose reader left must not kill a supervisor or a node in the middle of its clean-up.
#[macro_export]
macro_rules! errln {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stderr(), $($t)*);
    }};
}

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
