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

/// Checks, before anything starts, that `--viewer` can work: the viewer binary is built,
/// a viewer to spawn is installed, a viewer to connect to is listening, a file to save
/// does not exist yet.
pub fn check_viewer(words: &[String], overwrite: bool) -> Result<(), String> {
    if words.is_empty() {
        return Ok(());
    }
    check_viewer_words(words)?;
    let exe = viewer_exe();
    if !exe.is_file() {
        return Err(format!(
            "--viewer needs {}, which is not built; run `cargo build --release -p viewer` (it holds the rerun dependency)",
            exe.display()
        ));
    }
    match words[0].as_str() {
        "spawn" => {
            let found = std::env::var_os("PATH")
                .is_some_and(|p| std::env::split_paths(&p).any(|d| d.join("rerun").is_file()));
            if !found {
                return Err(
                    "--viewer spawn starts the `rerun` viewer, which is not on PATH; install it with `pip install rerun-sdk==0.36.*`, or use --viewer save FILE.rrd".into(),
                );
            }
        }
        "connect" => {
            let addr = &words[1];
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
                return Err(format!(
                    "--viewer connect {addr}: no Rerun viewer is listening there; start one with `rerun` (it listens on 127.0.0.1:9876) or use --viewer spawn"
                ));
            }
        }
        _ => {
            let path = Path::new(&words[1]);
            if path.exists() && !overwrite {
                return Err(format!(
                    "--viewer save {}: the file exists; choose another name or add --overwrite",
                    path.display()
                ));
            }
        }
    }
    Ok(())
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

/// Checks, before anything starts, that `--record` can create its file.
pub fn check_recording(r: &Recording) -> Result<(), String> {
    let path = &r.path;
    let first = match r.split {
        Some(_) => recorder::file::part_path(path, 0),
        None => path.clone(),
    };
    if first.exists() && !r.overwrite {
        return Err(format!(
            "--record {}: {}the file exists; choose another name or add --overwrite",
            path.display(),
            if first == *path {
                String::new()
            } else {
                format!("its first part {} exists: ", first.display())
            }
        ));
    }
    let dir = path
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    if !dir.is_dir() {
        return Err(format!(
            "--record {}: the folder {} does not exist; create it first",
            path.display(),
            dir.display()
        ));
    }
    Ok(())
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
/// takes them; `all_stages` shows the label images and disparity maps too.
pub fn add_viewer(graph: &mut Graph, words: &[String], all_stages: bool) -> Result<(), String> {
    check_viewer_words(words)?;
    let words = words.iter().cloned().map(toml::Value::String).collect();
    let stages = if all_stages { "all" } else { "cells" };
    let mut params = toml::Table::from_iter([
        ("target".to_string(), toml::Value::Array(words)),
        ("stages".to_string(), toml::Value::String(stages.into())),
    ]);
    // The cameras place the images in the 3D view, as the recorder's CameraInfo does.
    if let Some(c) = crate::registry::cameras(graph) {
        params.insert(
            "cameras".into(),
            toml::Value::try_from(c).map_err(|e| e.to_string())?,
        );
    }
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

/// Shows a recording in Rerun through the viewer binary (the same code as `--viewer`):
/// saved to `output` (written under a temporary name, renamed when complete), sent to a
/// viewer at `connect`, or shown in a new viewer; `all_stages` shows the label images and
/// disparity maps too.
pub fn view(
    file: &Path,
    output: Option<&Path>,
    connect: Option<&str>,
    overwrite: bool,
    all_stages: bool,
) -> Result<(), crate::Error> {
    let words = match (output, connect) {
        (Some(p), _) => vec!["save".into(), p.display().to_string()],
        (None, Some(c)) => vec!["connect".into(), c.to_string()],
        (None, None) => vec!["spawn".into()],
    };
    check_viewer(&words, overwrite).map_err(crate::Error::Viewer)?;
    if let Some(o) = output {
        formats::outputs::check(
            &[o.to_path_buf()],
            &[file],
            overwrite,
            "give -o another file",
        )?;
    }
    let tmp = output.map(formats::atomic::temp_beside);
    // The viewer binary checks the recording itself before it shows anything.
    let mut cmd = std::process::Command::new(viewer_exe());
    cmd.arg("view").arg(file);
    if all_stages {
        cmd.args(["--stages", "all"]);
    }
    if let Some(t) = &tmp {
        cmd.arg("-o").arg(t);
    } else if let Some(c) = connect {
        cmd.arg("--connect").arg(c);
    }
    let status = cmd
        .status()
        .map_err(|e| crate::Error::Viewer(format!("cannot run {}: {e}", viewer_exe().display())))?;
    let done = match status.code() {
        Some(0) => Ok(()),
        Some(code) => Err(crate::Error::ViewerExit(code)),
        None => Err(crate::Error::Viewer(format!(
            "the viewer failed ({status})"
        ))),
    };
    let (Some(t), Some(o)) = (&tmp, output) else {
        return done;
    };
    let kept = done.and_then(|_| {
        formats::atomic::commit(t, o, true)
            .map_err(|e| crate::Error::Viewer(format!("cannot write '{}': {e}", o.display())))
    });
    if kept.is_err() {
        let _ = std::fs::remove_file(t);
    }
    kept
}
