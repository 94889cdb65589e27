//! microstereo: a stereo light microscope as a 3D sensor.
//!
//! This crate is the command-line front end and the in-process pipeline that ties the node
//! libraries together:
//!
//! - [`pipeline`]: match → LR check → post-process, and range auto-selection, one copy
//!   used by every command and test;
//! - [`io`]: images in; PFM, 16-bit PNG, colour PNG, masks and PLY out;
//! - [`synthetic`]: textured pairs with exact ground truth for tests and benchmarks;
//! - [`cli`]: the `microstereo` commands (`reconstruct`, `eval`, `bench`, `segment`,
//!   `synth`, `calibrate-depth`);
//! - [`cells`]: segmentation outputs and cell-only stereo; [`render`]: overlays and charts;
//! - [`synthcmd`], [`calibrate`]: the `synth` and `calibrate-depth` commands.
//!
//! The algorithms live in the node crates: `matcher`, `validate`, `postprocess`,
//! `triangulate`; the message types in `schemas`.

pub mod calibrate;
pub mod cells;
pub mod cli;
pub mod graph;
pub mod io;
pub mod nodes;
pub mod pipeline;
pub mod recording;
pub mod render;
pub mod synthcmd;
pub mod synthetic;
