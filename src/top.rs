//! `microstereo top` (a running graph, live) and `microstereo topic list | hz | echo` (its
//! edges, for scripts). Both read the status the supervisor publishes and, for `hz` and
//! `echo`, the edge itself as a watcher: a reader the graph never waits for.

use crate::error::CliError;
use clap::{Args, Subcommand};
use runtime::status::{self, GraphStatus, StatusReader};
use std::time::{Duration, Instant};

/// How long `top` and `topic` wait for a named run's status to appear.
const ATTACH_PATIENCE: Duration = Duration::from_secs(3);

/// Which running graph to look at.
#[derive(Args, Debug, Clone)]
pub struct Attach {
    /// The run: its instance (`run --instance`), `INSTANCE@HOST` for one part of a graph
    /// over hosts (default: the newest run on this machine).
    #[arg(long)]
    pub instance: Option<String>,
    /// The iceoryx2 domain it runs in (`run --domain`; default: $MICROSTEREO_DOMAIN, else
    /// the default domain).
    #[arg(long)]
    pub domain: Option<String>,
}

impl Attach {
    /// The instance to attach to: the one named, or the newest running.
    fn resolve(&self) -> Result<String, CliError> {
        match &self.instance {
            Some(i) => Ok(i.clone()),
            None => status::running_instances().into_iter().next().ok_or_else(|| {
                CliError::Other(
                    "no graph is running on this machine: start one with `microstereo run` (or name a run on another host with --instance)".into(),
                )
            }),
        }
    }

    /// Attaches to the run and takes its first snapshot.
    fn open(&self) -> Result<(StatusReader, GraphStatus), CliError> {
        runtime::transport::set_domain(self.domain.as_deref()).map_err(CliError::Other)?;
        let instance = self.resolve()?;
        let reader = StatusReader::open(&instance, ATTACH_PATIENCE).map_err(CliError::Other)?;
        let first = reader
            .next(ATTACH_PATIENCE)
            .map_err(CliError::Other)?
            .ok_or_else(|| {
                CliError::Other(format!(
                    "run '{instance}' published no status within {} s: is it still running?",
                    ATTACH_PATIENCE.as_secs()
                ))
            })?;
        Ok((reader, first))
    }
}

/// Checks a refresh interval in seconds.
fn interval(flag: &str, s: f64) -> Result<Duration, CliError> {
    if !(0.05..=3600.0).contains(&s) {
        return Err(CliError::Other(format!(
            "{flag} {s} is out of range: use 0.05..3600 seconds"
        )));
    }
    Ok(Duration::from_secs_f64(s))
}

/// Arguments of `microstereo top`.
#[derive(Args, Debug)]
pub struct TopArgs {
    #[command(flatten)]
    attach: Attach,
    /// Seconds between refreshes; the figures are over the last one.
    #[arg(long, default_value_t = 1.0)]
    interval: f64,
    /// Print one table measured over one interval and exit (for scripts); without a
    /// terminal, tables are printed every interval until the run ends.
    #[arg(long)]
    once: bool,
}

/// Runs `microstereo top`.
pub fn top(a: TopArgs) -> Result<(), CliError> {
    use std::io::IsTerminal;
    let every = interval("--interval", a.interval)?;
    let (reader, first) = a.attach.open()?;
    if a.once || !std::io::stdout().is_terminal() {
        let mut prev = first;
        loop {
            let t0 = Instant::now();
            let mut now = None;
            while t0.elapsed() < every {
                if let Some(s) = reader
                    .next(every.saturating_sub(t0.elapsed()))
                    .map_err(CliError::Other)?
                {
                    let ended = s.ended;
                    now = Some(s);
                    if ended {
                        break;
                    }
                }
            }
            let Some(now) = now else {
                return Err(CliError::Other(format!(
                    "run '{}' stopped publishing its status",
                    prev.instance
                )));
            };
            runtime::outln!("{}", text(Some(&prev), &now));
            if a.once || now.ended {
                return Ok(());
            }
            prev = now;
        }
    }
    live(&reader, first, every)
}

/// The table `top` prints without a terminal: the run, its nodes and its edges.
pub fn text(prev: Option<&GraphStatus>, now: &GraphStatus) -> String {
    use std::fmt::Write;
    let p = status::progress(prev, now);
    let mut out = String::new();
    let _ = writeln!(
        out,
        "{} ({}){}: {}",
        now.instance,
        now.launch,
        if now.ended { ", ended" } else { "" },
        p.line()
    );
    let _ = writeln!(
        out,
        "{:<20} {:<18} {:<10} {:>8} {:>9} {:>9} {:>9} {:>9} {:>7}",
        "node", "kind", "state", "restarts", "frames", "frames/s", "step ms", "p99 ms", "CPU %"
    );
    for r in status::node_rows(prev, now) {
        let _ = writeln!(
            out,
            "{:<20} {:<18} {:<10} {:>8} {:>9} {:>9.2} {:>9} {:>9.2} {:>7.1}{}",
            r.id,
            clip(&r.kind, 18),
            r.state.word(),
            r.restarts,
            r.frames,
            r.rate,
            r.mean_ms.map_or("-".into(), |m| format!("{m:.2}")),
            r.p99_ms,
            r.cpu_percent,
            r.note.as_ref().map_or(String::new(), |n| format!("  {n}"))
        );
    }
    let rows = status::edge_rows(prev, now);
    let width = rows
        .iter()
        .map(|r| r.name.chars().count())
        .max()
        .unwrap_or(4);
    let _ = writeln!(
        out,
        "{:<width$} {:>9} {:>8} {:>14} {:>11}",
        "edge", "msgs/s", "dropped", "never arrived", "latency ms"
    );
    for r in rows {
        let _ = writeln!(
            out,
            "{:<width$} {:>9.2} {:>8} {:>14} {:>11}",
            r.name,
            r.rate,
            r.dropped,
            r.missing,
            r.latency_ms.map_or("-".into(), |l| format!("{l:.1}"))
        );
    }
    out
}

fn clip(s: &str, n: usize) -> String {
    if s.chars().count() <= n {
        s.into()
    } else {
        let tail: String = s
            .chars()
            .rev()
            .take(n - 1)
            .collect::<Vec<_>>()
            .into_iter()
            .rev()
            .collect();
        format!("…{tail}")
    }
}

/// Draws one frame of the live view.
pub fn draw(f: &mut ratatui::Frame, prev: Option<&GraphStatus>, now: &GraphStatus, note: &str) {
    use ratatui::layout::{Constraint, Layout};
    use ratatui::style::{Modifier, Style};
    use ratatui::widgets::{Block, Paragraph, Row, Table};
    let nodes = status::node_rows(prev, now);
    let edges = status::edge_rows(prev, now);
    let [head, top, bottom, foot] = Layout::vertical([
        Constraint::Length(2),
        Constraint::Length(nodes.len() as u16 + 3),
        Constraint::Min(3),
        Constraint::Length(1),
    ])
    .areas(f.area());
    let p = status::progress(prev, now);
    f.render_widget(
        Paragraph::new(format!(
            "{} ({}){}\n{}",
            now.instance,
            now.launch,
            if now.ended { " — ended" } else { "" },
            p.line()
        )),
        head,
    );
    let bold = Style::default().add_modifier(Modifier::BOLD);
    let node_table = Table::new(
        nodes.iter().map(|r| {
            Row::new(vec![
                r.id.clone(),
                clip(&r.kind, 18),
                r.state.word().to_string(),
                r.restarts.to_string(),
                r.frames.to_string(),
                format!("{:.2}", r.rate),
                r.mean_ms.map_or("-".into(), |m| format!("{m:.2}")),
                format!("{:.2}", r.p99_ms),
                format!("{:.1}", r.cpu_percent),
                r.note.clone().unwrap_or_default(),
            ])
            // A node that makes nothing, or still prepares, stands out.
            .style(match (&r.note, r.state) {
                (Some(_), status::NodeState::Running) => {
                    Style::default().fg(ratatui::style::Color::Yellow)
                }
                _ => Style::default(),
            })
        }),
        [
            Constraint::Length(20),
            Constraint::Length(18),
            Constraint::Length(10),
            Constraint::Length(8),
            Constraint::Length(8),
            Constraint::Length(9),
            Constraint::Length(8),
            Constraint::Length(8),
            Constraint::Length(6),
            Constraint::Min(20),
        ],
    )
    .header(
        Row::new(vec![
            "node", "kind", "state", "restarts", "frames", "frames/s", "step ms", "p99 ms",
            "CPU %", "",
        ])
        .style(bold),
    )
    .block(Block::bordered().title("nodes"));
    f.render_widget(node_table, top);
    let width = edges
        .iter()
        .map(|r| r.name.chars().count())
        .max()
        .unwrap_or(4) as u16;
    let edge_table = Table::new(
        edges.iter().map(|r| {
            Row::new(vec![
                r.name.clone(),
                format!("{:.2}", r.rate),
                r.dropped.to_string(),
                r.missing.to_string(),
                r.latency_ms.map_or("-".into(), |l| format!("{l:.1}")),
            ])
        }),
        [
            Constraint::Length(width),
            Constraint::Length(9),
            Constraint::Length(8),
            Constraint::Length(14),
            Constraint::Length(11),
        ],
    )
    .header(
        Row::new(vec![
            "edge",
            "msgs/s",
            "dropped",
            "never arrived",
            "latency ms",
        ])
        .style(bold),
    )
    .block(Block::bordered().title("edges"));
    f.render_widget(edge_table, bottom);
    f.render_widget(Paragraph::new(note.to_string()), foot);
}

/// The live view: redrawn every `every` until `q`, Esc or Ctrl-C.
fn live(reader: &StatusReader, first: GraphStatus, every: Duration) -> Result<(), CliError> {
    use ratatui::crossterm::event::{self, Event, KeyCode, KeyModifiers};
    let mut terminal = ratatui::init();
    let mut prev: Option<GraphStatus> = None;
    let mut now = first;
    let mut next_at = Instant::now();
    let mut note = "q: quit".to_string();
    let result = loop {
        if Instant::now() >= next_at {
            match reader.next(Duration::from_millis(50)) {
                Ok(Some(s)) => {
                    prev = Some(std::mem::replace(&mut now, s));
                    note = if now.ended {
                        "the run ended · q: quit".into()
                    } else {
                        "q: quit".into()
                    };
                }
                Ok(None) if !now.ended => note = "no status from the run · q: quit".into(),
                Ok(None) => {}
                Err(e) => break Err(CliError::Other(e)),
            }
            next_at = Instant::now() + every;
            if let Err(e) = terminal.draw(|f| draw(f, prev.as_ref(), &now, &note)) {
                break Err(CliError::Other(format!("cannot draw on the terminal: {e}")));
            }
        }
        match event::poll(Duration::from_millis(50)) {
            Ok(true) => {
                if let Ok(Event::Key(k)) = event::read()
                    && (matches!(k.code, KeyCode::Char('q') | KeyCode::Esc)
                        || (k.code == KeyCode::Char('c')
                            && k.modifiers.contains(KeyModifiers::CONTROL)))
                {
                    break Ok(());
                }
            }
            Ok(false) => {}
            Err(e) => break Err(CliError::Other(format!("cannot read the terminal: {e}"))),
        }
    };
    ratatui::restore();
    result
}

/// Arguments of `microstereo topic`.
#[derive(Args, Debug)]
pub struct TopicArgs {
    #[command(subcommand)]
    command: TopicCommand,
}

#[derive(Subcommand, Debug)]
enum TopicCommand {
    /// Lists a running graph's edges: writer output, message, queue, readers.
    List(Attach),
    /// Measures an edge's message rate as it runs.
    Hz(EdgeArgs),
    /// Prints each message's header on an edge (not its pixels), then a summary.
    Echo(EdgeArgs),
}

/// Which edge of which run, and for how long.
#[derive(Args, Debug)]
struct EdgeArgs {
    /// The edge, as its writer's `NODE/OUTPUT` (`topic list` shows them).
    edge: String,
    #[command(flatten)]
    attach: Attach,
    /// Stop after this many lines (hz: reports; echo: messages); without it, until the
    /// run ends or Ctrl-C.
    #[arg(long)]
    count: Option<u64>,
    /// hz: seconds between reports (each over the messages since the last one).
    #[arg(long, default_value_t = 1.0)]
    window: f64,
}

/// Runs `microstereo topic`.
pub fn topic(a: TopicArgs) -> Result<(), CliError> {
    match a.command {
        TopicCommand::List(at) => {
            let (_, s) = at.open()?;
            list(&s);
            Ok(())
        }
        TopicCommand::Hz(e) => watch(e, false),
        TopicCommand::Echo(e) => watch(e, true),
    }
}

fn list(s: &GraphStatus) {
    runtime::outln!("{} ({})", s.instance, s.launch);
    let width = s
        .edges()
        .map(|(n, o)| n.id.len() + o.port.len() + 1)
        .max()
        .unwrap_or(4);
    for (n, o) in s.edges() {
        runtime::outln!(
            "{:<width$} {:<18} depth {:<2} {:<11} → {}",
            format!("{}/{}", n.id, o.port),
            o.message,
            o.depth,
            if o.lossless {
                "lossless"
            } else {
                "drop-oldest"
            },
            if o.readers.is_empty() {
                "(no reader)".to_string()
            } else {
                o.readers.join(", ")
            }
        );
    }
}

/// What a watcher saw over a stretch of the edge.
#[derive(Default)]
struct Tally {
    /// Frames received.
    frames: u64,
    /// Bytes received.
    bytes: u64,
    /// (receipt, edge sequence) of the first and last message.
    first: Option<(Instant, u64)>,
    last: Option<(Instant, u64)>,
    /// Ages at receipt summed, ms.
    age_ms: f64,
}

impl Tally {
    fn add(&mut self, at: Instant, edge_seq: u64, bytes: usize, age_ms: f64) {
        self.frames += 1;
        self.bytes += bytes as u64;
        self.age_ms += age_ms;
        self.first.get_or_insert((at, edge_seq));
        self.last = Some((at, edge_seq));
    }

    /// Messages a second the writer sent between the first and the last message seen
    /// (from its own count: a message this watcher lost still counts).
    fn rate(&self) -> Option<f64> {
        let ((t0, s0), (t1, s1)) = (self.first?, self.last?);
        let dt = t1.duration_since(t0).as_secs_f64();
        (s1 > s0 && dt > 0.0).then(|| (s1 - s0) as f64 / dt)
    }
}

fn watch(a: EdgeArgs, echo: bool) -> Result<(), CliError> {
    let window = interval("--window", a.window)?;
    if a.count == Some(0) {
        return Err(CliError::Other(
            "--count 0 would print nothing: give at least 1".into(),
        ));
    }
    let (reader, s) = a.attach.open()?;
    let Some((_, out)) = s
        .edges()
        .find(|(n, o)| format!("{}/{}", n.id, o.port) == a.edge)
    else {
        let known: Vec<String> = s
            .edges()
            .map(|(n, o)| format!("{}/{}", n.id, o.port))
            .collect();
        return Err(CliError::Other(format!(
            "run '{}' has no edge '{}': its edges are {}",
            s.instance,
            a.edge,
            known.join(", ")
        )));
    };
    let sub = reader
        .transport()
        .watcher(&out.service)
        .map_err(|e| CliError::Other(e.to_string()))?;
    let started = Instant::now();
    let mut all = Tally::default();
    let mut part = Tally::default();
    let mut lines = 0u64;
    let mut part_start = Instant::now();
    let mut ended = false;
    let mut last_status = Instant::now();
    'outer: loop {
        while let Some(item) = sub
            .receive_item()
            .map_err(|e| CliError::Other(e.to_string()))?
        {
            let m = match item {
                runtime::transport::Received::Frame(m) => m,
                runtime::transport::Received::End { .. } => {
                    ended = true;
                    break 'outer;
                }
                runtime::transport::Received::Restart { node, .. } => {
                    if echo {
                        runtime::outln!("(restart marker: node '{node}' started anew)");
                    }
                    continue;
                }
            };
            let h = *m.user_header();
            let at = Instant::now();
            let age = runtime::edge::now_ns().saturating_sub(h.capture_ns) as f64 * 1e-6;
            all.add(at, h.edge_sequence, m.payload().len(), age);
            part.add(at, h.edge_sequence, m.payload().len(), age);
            if echo {
                runtime::outln!("{}", header_line(&h, m.payload().len(), age));
                lines += 1;
                if a.count.is_some_and(|c| lines >= c) {
                    break 'outer;
                }
            }
        }
        if !echo && part_start.elapsed() >= window {
            runtime::outln!(
                "{}: {} msgs/s over {:.2} s ({} received, {} lost here){}",
                a.edge,
                part.rate().map_or("-".into(), |r| format!("{r:.2}")),
                part_start.elapsed().as_secs_f64(),
                part.frames,
                sub.dropped(),
                if part.frames > 0 {
                    format!("; mean age {:.1} ms", part.age_ms / part.frames as f64)
                } else {
                    String::new()
                }
            );
            // The next window starts where this one ended: its first interval is the gap
            // after this one's last message.
            part = Tally {
                first: part.last,
                ..Tally::default()
            };
            part_start = Instant::now();
            lines += 1;
            if a.count.is_some_and(|c| lines >= c) {
                break;
            }
        }
        // A run that ended without an end marker on this edge (stopped, killed).
        if last_status.elapsed() > Duration::from_millis(500) {
            last_status = Instant::now();
            if let Ok(Some(st)) = reader.next(Duration::ZERO)
                && st.ended
            {
                ended = true;
                break;
            }
        }
        if !reader.transport().sleep(Duration::from_millis(2)) {
            break;
        }
    }
    if echo {
        let secs = started.elapsed().as_secs_f64();
        runtime::outln!(
            "{} message(s) in {secs:.2} s on {}: {} msgs/s, {:.1} MB/s, {} lost here{}{}",
            all.frames,
            a.edge,
            all.rate().map_or("-".into(), |r| format!("{r:.2}")),
            all.bytes as f64 / 1e6 / secs.max(1e-9),
            sub.dropped(),
            if all.frames > 0 {
                format!(", mean age {:.1} ms", all.age_ms / all.frames as f64)
            } else {
                String::new()
            },
            if ended { "; the stream ended" } else { "" }
        );
    } else if ended {
        runtime::outln!("{}: the stream ended", a.edge);
    }
    Ok(())
}

/// One message's header as `echo` prints it.
fn header_line(h: &schemas::FrameHeader, bytes: usize, age_ms: f64) -> String {
    let kind = schemas::MessageKind::from_u32(h.kind)
        .map_or(format!("kind {}", h.kind), |k| k.name().to_string());
    let image = if h.width > 0 {
        format!(
            " {}×{} {:?} ×{}",
            h.width,
            h.height,
            schemas::PixelFormat::from_u32(h.format).unwrap_or(schemas::PixelFormat::None),
            h.images
        )
    } else {
        String::new()
    };
    format!(
        "frame {} (edge #{}) {kind}{image} {bytes} bytes, age {age_ms:.1} ms",
        h.sequence, h.edge_sequence
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_header_line_names_the_message_and_its_image() {
        let h = schemas::FrameHeader {
            sequence: 7,
            edge_sequence: 9,
            width: 640,
            height: 512,
            stride: 640,
            format: 1,
            kind: 1,
            images: 2,
            ..Default::default()
        };
        assert_eq!(
            header_line(&h, 655360, 3.25),
            "frame 7 (edge #9) stereo-frame 640×512 Mono8 ×2 655360 bytes, age 3.2 ms"
        );
        let cells = schemas::FrameHeader {
            kind: 5,
            ..Default::default()
        };
        assert_eq!(
            header_line(&cells, 12, 0.0),
            "frame 0 (edge #0) cell-list 12 bytes, age 0.0 ms"
        );
    }

    #[test]
    fn a_watchers_rate_counts_what_the_writer_sent() {
        let t0 = Instant::now();
        let mut t = Tally::default();
        t.add(t0, 10, 1, 1.0);
        assert_eq!(t.rate(), None);
        // Edge numbers 10 → 30 in 0.5 s, though only two messages came here: 40/s.
        t.add(t0 + Duration::from_millis(500), 30, 1, 3.0);
        assert!((t.rate().unwrap() - 40.0).abs() < 1e-9);
        assert_eq!((t.frames, t.age_ms), (2, 4.0));
    }

    #[test]
    fn the_live_view_draws_the_nodes_and_edges_of_a_snapshot() {
        let g = crate::run::load_with(None, &[]).unwrap();
        let mut now = GraphStatus::of(&g, "view-test", None, Some(100), 1_000_000_000);
        now.now_ns = 3_000_000_000;
        let backend = ratatui::backend::TestBackend::new(120, 40);
        let mut term = ratatui::Terminal::new(backend).unwrap();
        term.draw(|f| draw(f, None, &now, "q: quit")).unwrap();
        let screen: String = term
            .backend()
            .buffer()
            .content()
            .iter()
            .map(|c| c.symbol())
            .collect();
        assert!(screen.contains("view-test"), "{screen}");
        for n in &g.nodes {
            assert!(screen.contains(&n.id), "{} missing", n.id);
        }
        assert!(screen.contains("0 frame(s) of 100"));
        assert!(screen.contains("starting"));
        assert!(screen.contains("capture/frame → rectify.frame"), "{screen}");
    }
}
