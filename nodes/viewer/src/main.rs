//! `microstereo-viewer`: the graph in Rerun.
//!
//! `microstereo-viewer view REC.mcap [-o OUT.rrd | --connect ADDR]` shows a recording; run
//! with a node's arguments (`--graph FILE --id ID --instance NAME`, as `microstereo run --viewer …` starts it)
//! it is a tap on the running graph's edges. Errors: one line, exit code 2.

use clap::Parser;
use runtime::process::{Invocation, NodeArgs};
use std::path::PathBuf;
use viewer::{Sink, Stages, Target};

/// Shows a recording in Rerun.
#[derive(Parser, Debug)]
#[command(name = "microstereo-viewer view")]
struct ViewCli {
    /// The recording.
    file: PathBuf,
    /// Write an .rrd file instead of showing it.
    #[arg(short, long)]
    output: Option<PathBuf>,
    /// Send it to a running viewer (HOST:PORT or rerun+http://HOST:PORT/proxy).
    #[arg(long, conflicts_with = "output")]
    connect: Option<String>,
    /// What to show: `cells` (camera frames as JPEG, cells, 3D) or `all` (and the label
    /// images, disparity maps and tiles).
    #[arg(long, default_value = "cells", value_parser = Stages::parse)]
    stages: Stages,
}

fn view(a: ViewCli) -> Result<(), String> {
    let target = match (a.output, a.connect) {
        (Some(o), _) => Target::Save(o),
        (None, Some(c)) => Target::Connect(viewer::grpc_url(&c)),
        (None, None) => Target::Spawn,
    };
    // Read the whole file first: a bad recording is reported before a viewer starts.
    recorder::overview(&a.file)
        .map_err(|e| e.to_string())
        .and_then(|o| match o.error {
            Some(e) => Err(format!("{}: {e}", a.file.display())),
            None if o.channels.iter().all(|c| c.messages == 0) => {
                let why: Vec<&str> = o.cut.iter().chain(&o.damaged).map(String::as_str).collect();
                Err(format!(
                    "{}: no message in it can be read{}",
                    a.file.display(),
                    if why.is_empty() {
                        " (it holds none)".to_string()
                    } else {
                        format!(": {}", why.join("; "))
                    }
                ))
            }
            None => {
                // Damaged chunks are skipped, a cut file read up to its last whole record;
                // the rest is shown.
                for d in o.cut.iter().chain(&o.damaged) {
                    runtime::errln!("warning: {}: {d}", a.file.display());
                }
                Ok(())
            }
        })?;
    let mut sink = Sink::new(viewer::open(&target)?)?.with_stages(a.stages);
    if let Some((calib, size)) = recorder::file::recorded_cameras(&a.file) {
        sink = sink.with_cameras(&calib, size)?;
    }
    let n = viewer::log_recording(&mut sink, &a.file)?;
    sink.finish()?;
    if n == 0 {
        return Err(format!(
            "{}: none of its messages could be shown",
            a.file.display()
        ));
    }
    runtime::errln!("{n} message(s) of {} shown", a.file.display());
    Ok(())
}

fn tap(a: NodeArgs) -> Result<(), String> {
    let graph = runtime::process::load_graph(&a.graph)?;
    let spec = graph
        .node(&a.id)
        .ok_or_else(|| format!("no node '{}' in {}", a.id, a.graph.display()))?;
    let words: Vec<String> = spec
        .params
        .get("target")
        .and_then(|v| v.as_array())
        .map(|v| {
            v.iter()
                .filter_map(|s| s.as_str().map(String::from))
                .collect()
        })
        .unwrap_or_default();
    let target = Target::parse(&words)?;
    let stages = match spec.params.get("stages").and_then(|v| v.as_str()) {
        Some(w) => Stages::parse(w)?,
        None => Stages::Cells,
    };
    let edges = graph.input_edges(&a.id);
    let mut sink = Sink::new(viewer::open(&target)?)?.with_stages(stages);
    if let Some(c) = spec.params.get("cameras") {
        let c: recorder::node::Cameras = c
            .clone()
            .try_into()
            .map_err(|e| format!("viewer: cameras: {e}"))?;
        sink = sink.with_cameras(&c.calibration, (c.width, c.height))?;
    }
    // The supervisor writes the other nodes' log lines to this process's stdin.
    let rec = sink.stream().clone();
    std::thread::spawn(move || {
        use std::io::BufRead;
        for line in std::io::stdin().lock().lines().map_while(Result::ok) {
            viewer::log_node_line(&rec, &line);
        }
    });
    let stats = runtime::process::run_tap(&graph, &a.instance, &a.id, a.frames, |i, h, p| {
        sink.log(&edges[i].0, edges[i].1, h, p)
    })?;
    sink.finish()?;
    runtime::process::print_stats(&stats);
    Ok(())
}

fn main() {
    let result = if std::env::args().nth(1).as_deref() == Some("view") {
        view(ViewCli::parse_from(std::env::args().skip(1)))
    } else {
        runtime::signals::install();
        runtime::process::set_parent_death_signal();
        let args: Vec<String> = std::env::args().skip(1).collect();
        match Invocation::parse(&args) {
            Ok(Invocation::Run(a)) => tap(a),
            Ok(Invocation::Describe { .. }) => {
                Err("the viewer is added by `run --viewer`; it is not a launch-file node".into())
            }
            Err(e) => Err(e),
        }
    };
    if let Err(e) = result {
        runtime::errln!("error: {e}");
        std::process::exit(2);
    }
}
