//! microstereo: a stereo light microscope as a 3D sensor — the command line.
//!
//! The binary only wires: it turns flags into graphs of the node crates (presets for the
//! one-shot commands, launch files for `run`), runs them with the runtime's executor or
//! supervisor, and writes what they produce.
//!
//! - [`cli`]: the commands and their dispatch; [`error`]: the one error type;
//! - the built-in node kinds, the default graph and the stereo graph of `reconstruct`,
//!   `bench` and `calibrate-depth` are the `pipelines` crate's;
//! - [`reconstruct`], [`bench`], [`segmentcmd`], [`synthcmd`], [`calibrate`]: one-shot
//!   commands;
//! - [`run`], [`graphopts`], [`recording`]: the process graph, its taps and replays, and
//!   recordings (`inspect`, `replay`, `test-node`, `view`); [`top`]: a running graph seen
//!   live (`top`, `topic`).

pub mod bench;
pub mod calibfile;
pub mod calibmanip;
pub mod calibrate;
pub mod calibstereo;
pub mod cli;
pub mod error;
pub mod graphopts;
pub mod reconstruct;
pub mod recording;
pub mod run;
pub mod segmentcmd;
pub mod synthcmd;
pub mod top;
