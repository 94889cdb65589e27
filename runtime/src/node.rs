//! The node contract, from the `node-api` crate: the runtime drives what the algorithm
//! crates implement there.

pub use node_api::*;
