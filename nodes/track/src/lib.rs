//! Cells over time: the tracker that gives each physical cell one id for as long as it is
//! seen, fuses its measurements over the frames it was seen in, and the track node that
//! runs it between triangulate and the manipulator bridge.
//!
//! The algorithm is plain functions and one state type ([`Tracker`]) over the messages'
//! types, testable without a graph; [`node`] wraps it as a graph node.

pub mod fuse;
pub mod node;
pub mod score;
pub mod tracker;

pub use fuse::{Fused, Observation, fuse_heights};
pub use tracker::{Tracker, TrackerParams};
