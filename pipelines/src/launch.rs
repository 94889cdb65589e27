//! The default graph and launch files read against the built-in kinds.

use crate::Error;
use runtime::launch::{Graph, LaunchFile};
use std::path::{Path, PathBuf};

/// The default graph (`run` without a launch file): the repository's `launch.toml`.
pub const DEFAULT_LAUNCH: &str = include_str!("../../launch.toml");

/// Reads and validates a launch file against the built-in kinds; every problem becomes one
/// error.
pub fn load(path: &Path) -> Result<Graph, Error> {
    load_with(Some(path), &[])
}

/// Reads and checks a launch file (`None`: the built-in default graph) with `overrides`
/// (`NODE.PARAM=VALUE`) applied first.
pub fn load_with(path: Option<&Path>, overrides: &[String]) -> Result<Graph, Error> {
    let (name, text) = match path {
        Some(p) => (
            p.to_path_buf(),
            std::fs::read_to_string(p).map_err(|e| {
                Error::Launch(format!("{}: cannot read the launch file: {e}", p.display()))
            })?,
        ),
        None => (
            PathBuf::from("launch.toml (built in)"),
            DEFAULT_LAUNCH.to_string(),
        ),
    };
    let text = if overrides.is_empty() {
        text
    } else {
        runtime::launch::with_overrides(&name, &text, overrides).map_err(Error::Launch)?
    };
    let file = LaunchFile::parse(&name, &text).map_err(Error::LaunchFile)?;
    file.validate(&crate::registry::builtin())
        .map_err(Error::LaunchFile)
}
