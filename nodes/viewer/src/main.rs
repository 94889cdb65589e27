//! `microstereo-viewer`: the graph in Rerun.
//!
//! `microstereo-viewer view REC.mcap [-o OUT.rrd | --connect ADDR]` shows a recording; run
//! with a node's arguments (`--launch … --id …`, as `microstereo run --viewer …` starts it)
//! it is a tap on the running graph's edges. Errors: one line, exit code 2.

use clap::Parser;
use microstereo::graph::NodeArgs;
use runtime::process::STATS_PREFIX;
use std::path::PathBuf;
use viewer::{Sink, Target};

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
}

/// Runs as the graph's viewer tap.
#[derive(Parser, Debug)]
#[command(name = "microstereo-viewer")]
struct NodeCli {
    #[command(flatten)]
    node: NodeArgs,
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
            None => Ok(()),
        })?;
    let mut sink = Sink::new(viewer::open(&target)?);
    let n = viewer::log_recording(&mut sink, &a.file)?;
    sink.finish()?;
    eprintln!("{n} message(s) of {} shown", a.file.display());
    Ok(())
}

fn tap(a: NodeCli) -> Result<(), String> {
    let a = a.node;
    let graph = microstereo::recording::load_with(&a.launch, &a.opts).map_err(|e| e.to_string())?;
    let spec = graph
        .node(&a.id)
        .ok_or_else(|| format!("no node '{}' in {}", a.id, a.launch.display()))?;
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
    let edges = graph.input_edges(&a.id);
    let mut sink = Sink::new(viewer::open(&target)?);
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
    println!(
        "{STATS_PREFIX}{}",
        serde_json::to_string(&stats).map_err(|e| e.to_string())?
    );
    Ok(())
}

fn main() {
    let result = if std::env::args().nth(1).as_deref() == Some("view") {
        view(ViewCli::parse_from(std::env::args().skip(1)))
    } else {
        tap(NodeCli::parse())
    };
    if let Err(e) = result {
        eprintln!("error: {e}");
        std::process::exit(2);
    }
}
