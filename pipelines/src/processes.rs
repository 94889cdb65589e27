//! A graph run as processes of this program: one `node` process per node, supervised, its
//! summary printed.

use crate::Error;
use crate::taps::{RECORDER_ID, Recording};
use runtime::launch::Graph;
use runtime::supervisor::RunOptions;

/// Runs `graph` as processes of this program (each node as `THIS node …`) with `o` (its
/// `builtin` and `controls` are filled in here), in the iceoryx2 `domain`, prints the
/// summary and what `recording` holds; returns the frame rate.
pub fn run(
    graph: &Graph,
    mut o: RunOptions,
    domain: Option<&str>,
    recording: Option<&Recording>,
) -> Result<f64, Error> {
    if !(0.0..=600.0).contains(&o.grace) {
        return Err(Error::Options(format!(
            "--grace {} is out of range: use 0..600 seconds",
            o.grace
        )));
    }
    if o.frames == Some(0) {
        return Err(Error::Options(
            "--frames 0 would never end: give at least 1, or leave it out to run until Ctrl-C"
                .into(),
        ));
    }
    runtime::transport::set_domain(domain).map_err(Error::Options)?;
    let exe = std::env::current_exe()
        .map_err(|e| Error::Start(format!("cannot find this program: {e}")))?;
    o.builtin = vec![exe.into_os_string(), "node".into()];
    o.controls = graph
        .nodes
        .iter()
        .filter(|n| n.kind() == Some(recorder::node::REPLAY_KIND))
        .map(|n| n.id.clone())
        .collect();
    let report = runtime::supervisor::run(graph, &o).map_err(Error::Start)?;
    if let Some(sig) = report.signal
        && report.stats.is_empty()
    {
        runtime::errln!(
            "stopped by {} before the graph started",
            runtime::signals::name(sig)
        );
    }
    let (stats, host) = (&report.stats, report.host.as_deref());
    let rate = runtime::supervisor::print_summary(graph, stats, report.wall, o.frames, host);
    if let Some(f) = report.failure {
        let kept = recording
            .map(|r| recorder::file::unfinished_parts(&r.path))
            .unwrap_or_default();
        let kept = if kept.is_empty() {
            String::new()
        } else {
            format!(
                "; the unfinished recording is kept as {} (readable up to its last flush)",
                kept.join(", ")
            )
        };
        return Err(Error::Stopped(format!("the run stopped early: {f}{kept}")));
    }
    if let Some(r) = recording {
        let written = stats.get(RECORDER_ID).map_or(0, |s| s.frames_out);
        let line = recorder::file::written(&r.path, written, r.split.is_some());
        runtime::outln!("{line}");
    }
    Ok(rate)
}
