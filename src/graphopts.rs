//! The flags of `run` and `replay` that add taps to a launch file's graph (a recorder,
//! `--record`; a Rerun viewer, `--viewer`), and the checks, before anything starts, that
//! they can work.

use crate::error::CliError;
use clap::Args;
use pipelines::taps;
use runtime::launch::Graph;
use std::path::PathBuf;

/// Where a run's edges go besides the graph: a recording, a Rerun viewer.
#[derive(Args, Debug, Clone, Default)]
pub struct OutputOpts {
    /// Record the graph's edges into this MCAP file (ros2 profile, CDR messages).
    #[arg(long)]
    pub record: Option<PathBuf>,
    /// Record only the edges that match one of these (NODE/OUTPUT, `*` for any
    /// characters, e.g. 'rectify/*' '*/disparity').
    #[arg(long, num_args = 1.., requires = "record")]
    pub edges: Vec<String>,
    /// Record the edges that match PATTERN at a reduced rate, the first frame at or after
    /// every Nth frame number, which counts the camera's frames (repeatable; e.g.
    /// 'rectify/frame=10' keeps the images of one camera frame in ten while the cells and
    /// targets keep every frame).
    #[arg(long, value_name = "PATTERN=N", value_parser = taps::parse_every, requires = "record")]
    pub every: Vec<(String, u64)>,
    /// Split the recording into files: a new one once SIZE of messages (before
    /// compression, e.g. 1GiB, 500MB) are in the current one, or every TIME (e.g. 10min,
    /// 30s): NAME-000.mcap, NAME-001.mcap, …;
    /// `replay`, `inspect`, `view` and `test-node` given NAME.mcap read the parts as one.
    #[arg(long, value_name = "SIZE|TIME", value_parser = taps::parse_split, requires = "record")]
    pub split: Option<taps::Split>,
    /// Replace the file given to --record or to --viewer save if it exists.
    #[arg(long)]
    pub overwrite: bool,
    /// Show the graph in Rerun: `spawn` a viewer, `connect HOST:PORT` to a running one, or
    /// `save FILE.rrd` (needs the viewer binary: cargo build --release -p viewer).
    #[arg(long, num_args = 1..=2, value_names = ["MODE", "WHERE"])]
    pub viewer: Vec<String>,
    /// Show every stage in the viewer (label images, disparity maps and tiles), not only
    /// the camera frames, cells and 3D (about 1 MB a 1280×1024 frame).
    #[arg(long, requires = "viewer")]
    pub viewer_all: bool,
}

impl OutputOpts {
    /// The recorder tap `--record` asks for.
    pub fn recording(&self) -> Option<taps::Recording> {
        self.record.as_ref().map(|path| taps::Recording {
            path: path.clone(),
            edges: self.edges.clone(),
            every: self.every.clone(),
            split: self.split,
            overwrite: self.overwrite,
        })
    }

    /// Checks, before anything starts, that the recording can be created and the viewer
    /// can work.
    pub fn check(&self) -> Result<(), CliError> {
        if let Some(r) = self.recording() {
            taps::check_recording(&r).map_err(CliError::Other)?;
        }
        taps::check_viewer(&self.viewer, self.overwrite).map_err(CliError::Other)?;
        Ok(())
    }

    /// Adds the recorder and the viewer taps to `graph`.
    pub fn apply(&self, graph: &mut Graph) -> Result<(), String> {
        if let Some(r) = self.recording() {
            taps::add_recorder(graph, &r)?;
        }
        if !self.viewer.is_empty() {
            taps::add_viewer(graph, &self.viewer, self.viewer_all)?;
        }
        Ok(())
    }
}
