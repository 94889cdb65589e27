//! The flags of `run` and `replay` that add taps to a launch file's graph (a recorder,
//! `--record`; a Rerun viewer, `--viewer`), and the checks, before anything starts, that
//! they can work.

use crate::error::CliError;
use clap::Args;
use pipelines::taps;
use runtime::launch::Graph;
use std::path::{Path, PathBuf};

/// Checks, before anything starts, that `--viewer` can work: the viewer binary is built,
/// a viewer to spawn is installed, a viewer to connect to is listening, a file to save
/// does not exist yet.
pub fn check_viewer_target(opts: &OutputOpts) -> Result<(), CliError> {
    if opts.viewer.is_empty() {
        return Ok(());
    }
    taps::check_viewer_words(&opts.viewer).map_err(CliError::Other)?;
    let exe = taps::viewer_exe();
    if !exe.is_file() {
        return Err(CliError::Other(format!(
            "--viewer needs {}, which is not built; run `cargo build --release -p viewer` (it holds the rerun dependency)",
            exe.display()
        )));
    }
    match opts.viewer[0].as_str() {
        "spawn" => {
            let found = std::env::var_os("PATH")
                .is_some_and(|p| std::env::split_paths(&p).any(|d| d.join("rerun").is_file()));
            if !found {
                return Err(CliError::Other(
                    "--viewer spawn starts the `rerun` viewer, which is not on PATH; install it with `pip install rerun-sdk==0.36.*`, or use --viewer save FILE.rrd".into(),
                ));
            }
        }
        "connect" => {
            let addr = &opts.viewer[1];
            let hp = addr
                .split_once("://")
                .map_or(addr.as_str(), |(_, r)| r)
                .split('/')
                .next()
                .unwrap_or(addr);
            let reachable = std::net::ToSocketAddrs::to_socket_addrs(hp)
                .ok()
                .and_then(|mut a| a.next())
                .is_some_and(|a| {
                    std::net::TcpStream::connect_timeout(&a, std::time::Duration::from_secs(2))
                        .is_ok()
                });
            if !reachable {
                return Err(CliError::Other(format!(
                    "--viewer connect {addr}: no Rerun viewer is listening there; start one with `rerun` (it listens on 127.0.0.1:9876) or use --viewer spawn"
                )));
            }
        }
        _ => {
            let path = Path::new(&opts.viewer[1]);
            if path.exists() && !opts.overwrite {
                return Err(CliError::Other(format!(
                    "--viewer save {}: the file exists; choose another name or add --overwrite",
                    path.display()
                )));
            }
        }
    }
    Ok(())
}

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
}

impl OutputOpts {
    /// Adds the recorder and the viewer taps to `graph`.
    pub fn apply(&self, graph: &mut Graph) -> Result<(), String> {
        if let Some(path) = &self.record {
            let r = taps::Recording {
                path: path.clone(),
                edges: self.edges.clone(),
                every: self.every.clone(),
                split: self.split,
                overwrite: self.overwrite,
            };
            taps::add_recorder(graph, &r)?;
        }
        if !self.viewer.is_empty() {
            taps::add_viewer(graph, &self.viewer)?;
        }
        Ok(())
    }
}

/// Checks, before anything starts, that `--record` can create its file.
pub fn check_record_target(opts: &OutputOpts) -> Result<(), CliError> {
    let Some(path) = &opts.record else {
        return Ok(());
    };
    let first = match opts.split {
        Some(_) => recorder::file::part_path(path, 0),
        None => path.clone(),
    };
    if first.exists() && !opts.overwrite {
        return Err(CliError::Other(format!(
            "--record {}: {}the file exists; choose another name or add --overwrite",
            path.display(),
            if first == *path {
                String::new()
            } else {
                format!("its first part {} exists: ", first.display())
            }
        )));
    }
    let dir = path
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    if !dir.is_dir() {
        return Err(CliError::Other(format!(
            "--record {}: the folder {} does not exist; create it first",
            path.display(),
            dir.display()
        )));
    }
    Ok(())
}
