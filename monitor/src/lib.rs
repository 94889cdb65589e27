//! The terminal views of a running graph: `top` (its nodes and edges, a table or live)
//! and `topic` (its edges listed, an edge's rate, its messages' headers). Both read the
//! status the supervisor publishes and, for `hz` and `echo`, the edge itself as a
//! watcher: a reader the graph never waits for. The flags that fill the options live in
//! the binary; this crate knows no command line.

mod attach;
mod error;
pub mod top;
pub mod topic;

pub use attach::Attach;
pub use error::Error;
pub use top::{TopOptions, top};
pub use topic::{EdgeOptions, echo, hz, list};
