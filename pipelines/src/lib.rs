//! microstereo's built-in pipelines, built from the node types.
//!
//! - [`registry`]: the node kinds this project runs, one list, and the cameras a graph's
//!   recorder describes;
//! - [`launch`]: the default graph and the reading of launch files against those kinds;
//! - [`stereo`]: the stereo graph the one-shot commands run in-process (`reconstruct`,
//!   `bench`, `calibrate-depth`), its typed outputs, and what is measured on it (the
//!   paper's range selection, a target's disparity, the per-node times);
//! - [`maps`]: what one frame of it made, read back as whole maps;
//! - [`report`]: what `reconstruct` reports of a run and of each cell;
//! - [`taps`]: the recorder, viewer and replay nodes `run` and `replay` add to a graph;
//! - [`processes`]: a graph run as processes of this program, supervised;
//! - [`fuzzing`]: the fuzz targets' entry points, one per reader of untrusted bytes;
//! - [`recording`]: the graph a replay or a node test of a recording runs, and that test.

pub mod fuzzing;
pub mod html;
pub mod launch;
pub mod maps;
pub mod microscope;
pub mod processes;
pub mod range;
pub mod recording;
pub mod registry;
pub mod report;
pub mod stereo;
pub mod taps;
pub mod timing;

mod error;

pub use error::Error;
