//! What `run` and `replay` add to a launch file's graph: a recorder tap, a Rerun viewer
//! tap, and replay sources in place of recorded nodes.

use recorder::node::{RECORDER_KIND, REPLAY_KIND};
use runtime::launch::{Graph, Runner};
use std::path::{Path, PathBuf};

/// The recorder's node id in a graph run with `--record`.
pub const RECORDER_ID: &str = "recorder";

/// The Rerun viewer tap's node id in a graph run with `--viewer`.
pub const VIEWER_ID: &str = "viewer";

/// The viewer binary: next to this program (`cargo build --release -p viewer` builds it;
/// it alone links rerun).
pub fn viewer_exe() -> PathBuf {
    std::env::current_exe()
        .ok()
        .and_then(|p| p.parent().map(|d| d.join("microstereo-viewer")))
        .unwrap_or_else(|| PathBuf::from("microstereo-viewer"))
}

/// Checks the words of `--viewer`: `spawn`, `connect HOST:PORT` or `save FILE.rrd`.
pub fn check_viewer_words(w: &[String]) -> Result<(), String> {
    match w {
        [m] if m == "spawn" => Ok(()),
        [m, _] if m == "connect" || m == "save" => Ok(()),
        _ => Err(format!(
            "--viewer {}: give spawn, connect HOST:PORT or save FILE.rrd",
            w.join(" ")
        )),
    }
}

/// A recorder tap: where it writes and what.
#[derive(Clone, Debug, Default)]
pub struct Recording {
    /// The MCAP file.
    pub path: PathBuf,
    /// Edge patterns to record (none: every edge).
    pub edges: Vec<String>,
    /// Edge patterns recorded at a reduced rate: one frame in N.
    pub every: Vec<(String, u64)>,
    /// Where the recording is split into files.
    pub split: Option<Split>,
    /// Replace an existing file.
    pub overwrite: bool,
}

/// Adds a recorder tap to `graph` (with the cameras' CameraInfo where the graph says it).
pub fn add_recorder(graph: &mut Graph, r: &Recording) -> Result<(), String> {
    let path = &r.path;
    let path = std::path::absolute(path).unwrap_or(path.clone());
    let mut params = toml::Table::from_iter([
        (
            "path".to_string(),
            toml::Value::String(path.display().to_string()),
        ),
        ("overwrite".to_string(), toml::Value::Boolean(r.overwrite)),
    ]);
    if let Some(c) = crate::registry::cameras(graph) {
        params.insert(
            "cameras".into(),
            toml::Value::try_from(c).map_err(|e| e.to_string())?,
        );
    }
    let every: std::collections::BTreeMap<String, u64> = r.every.iter().cloned().collect();
    if every.len() != r.every.len() {
        return Err("--every gives one pattern twice: give each pattern once".into());
    }
    params.insert(
        "every".into(),
        toml::Value::Table(
            every
                .iter()
                .map(|(k, &n)| (k.clone(), toml::Value::Integer(n as i64)))
                .collect(),
        ),
    );
    match r.split {
        Some(Split::Bytes(b)) => {
            params.insert("split_bytes".into(), toml::Value::Integer(b as i64));
        }
        Some(Split::Seconds(t)) => {
            params.insert("split_seconds".into(), toml::Value::Float(t));
        }
        None => {}
    }
    graph.add_tap(RECORDER_ID, RECORDER_KIND, &r.edges, params)?;
    let recorded: Vec<String> = graph
        .input_edges(RECORDER_ID)
        .into_iter()
        .map(|(e, _)| e)
        .collect();
    recorder::node::edge_rates(&every, &recorded).map_err(|e| format!("--every: {e}"))?;
    Ok(())
}

/// Adds a Rerun viewer tap to `graph`, run by the viewer binary; `words` as `--viewer`
/// takes them.
pub fn add_viewer(graph: &mut Graph, words: &[String]) -> Result<(), String> {
    check_viewer_words(words)?;
    let words = words.iter().cloned().map(toml::Value::String).collect();
    let params = toml::Table::from_iter([("target".to_string(), toml::Value::Array(words))]);
    graph.add_tap(VIEWER_ID, "viewer", &[], params)?;
    let n = graph.nodes.last_mut().expect("added");
    n.runner = Runner::Exec(viewer_exe());
    n.logs = true;
    Ok(())
}

/// Most frames `--every` may skip between two recorded ones.
pub const EVERY_MAX: u64 = 1_000_000;

/// Where a recording is split (`--split`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Split {
    /// Bytes of messages (before compression) per file.
    Bytes(u64),
    /// Seconds per file.
    Seconds(f64),
}

/// Reads `--split`: a size (`1GiB`, `500MB`, `64MiB`, `100kB`) or a time (`30s`, `10min`,
/// `2h`).
pub fn parse_split(s: &str) -> Result<Split, String> {
    let t = s.trim();
    let at = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (num, unit) = t.split_at(at);
    let bad = || format!("'{s}' is neither a size (e.g. 1GiB, 500MB) nor a time (e.g. 10min, 30s)");
    let n: f64 = num.parse().map_err(|_| bad())?;
    let (bytes, secs) = match unit.trim() {
        "B" => (Some(1.0), None),
        "kB" | "KB" => (Some(1e3), None),
        "KiB" => (Some(1024.0), None),
        "MB" => (Some(1e6), None),
        "MiB" => (Some(1024.0 * 1024.0), None),
        "GB" => (Some(1e9), None),
        "GiB" => (Some(1024.0 * 1024.0 * 1024.0), None),
        "s" => (None, Some(1.0)),
        "min" => (None, Some(60.0)),
        "h" => (None, Some(3600.0)),
        _ => return Err(bad()),
    };
    match (bytes, secs) {
        (Some(u), _) => {
            let b = n * u;
            if !(1024.0..=1e15).contains(&b) {
                return Err(format!("--split {s}: give 1KiB to 1PB"));
            }
            Ok(Split::Bytes(b as u64))
        }
        (_, Some(u)) => {
            let t = n * u;
            if !(1.0..=1e7).contains(&t) {
                return Err(format!("--split {s}: give 1 s to 1e7 s"));
            }
            Ok(Split::Seconds(t))
        }
        _ => Err(bad()),
    }
}

/// Reads `--every PATTERN=N`: an edge pattern and how many frames apart it is recorded.
pub fn parse_every(s: &str) -> Result<(String, u64), String> {
    let (pattern, n) = s
        .rsplit_once('=')
        .ok_or_else(|| format!("'{s}' is not PATTERN=N (e.g. 'rectify/frame=10')"))?;
    if pattern.is_empty() || !pattern.contains('/') {
        return Err(format!(
            "'{pattern}' is not an edge pattern NODE/OUTPUT (e.g. 'rectify/frame=10')"
        ));
    }
    let n: u64 = n
        .trim()
        .parse()
        .map_err(|_| format!("'{n}' is not a whole number of frames (1 to {EVERY_MAX})"))?;
    if !(1..=EVERY_MAX).contains(&n) {
        return Err(format!("every {n} frames: give 1 to {EVERY_MAX}"));
    }
    Ok((pattern.to_string(), n))
}

/// Turns nodes `replace` of `graph` into sources that send their outputs recorded in
/// `file` (at `rate`, `looped`).
pub fn apply_replay(
    graph: &mut Graph,
    file: &Path,
    replace: &[String],
    rate: &str,
    looped: bool,
    window: (f64, Option<f64>),
) -> Result<(), String> {
    let file = std::path::absolute(file).unwrap_or(file.to_path_buf());
    let mut params = toml::Table::from_iter([
        (
            "file".to_string(),
            toml::Value::String(file.display().to_string()),
        ),
        ("rate".to_string(), toml::Value::String(rate.to_string())),
        ("loop".to_string(), toml::Value::Boolean(looped)),
        ("start".to_string(), toml::Value::Float(window.0)),
    ]);
    if let Some(d) = window.1 {
        params.insert("duration".into(), toml::Value::Float(d));
    }
    graph.replace_with_sources(replace, REPLAY_KIND, &params)
}
