//! `top`: a running graph's nodes and edges, as tables printed every interval (without a
//! terminal, or once) or as a live view redrawn until a key ends it.

use crate::Error;
use crate::attach::{Attach, interval};
use runtime::status::{self, GraphStatus, StatusReader};
use std::time::{Duration, Instant};

/// What `top` shows and how often.
#[derive(Debug, Clone)]
pub struct TopOptions {
    /// The run.
    pub attach: Attach,
    /// Seconds between refreshes (0.05..3600); the figures are over the last one.
    pub interval: f64,
    /// One table measured over one interval, then return.
    pub once: bool,
}

/// Runs `top`: tables on stdout when `once` is set or stdout is no terminal, else the
/// live view.
pub fn top(o: &TopOptions) -> Result<(), Error> {
    use std::io::IsTerminal;
    let every = interval("--interval", o.interval)?;
    let (reader, first) = o.attach.open()?;
    if o.once || !std::io::stdout().is_terminal() {
        let mut prev = first;
        loop {
            let t0 = Instant::now();
            let mut now = None;
            while t0.elapsed() < every {
                if let Some(s) = reader
                    .next(every.saturating_sub(t0.elapsed()))
                    .map_err(Error::Status)?
                {
                    let ended = s.ended;
                    now = Some(s);
                    if ended {
                        break;
                    }
                }
            }
            let Some(now) = now else {
                return Err(Error::StoppedPublishing(prev.instance));
            };
            runtime::outln!("{}", text(Some(&prev), &now));
            if o.once || now.ended {
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

/// `s` cut to its last `n - 1` characters after an ellipsis when longer than `n`: a
/// kind's path ends in what tells it apart.
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
fn live(reader: &StatusReader, first: GraphStatus, every: Duration) -> Result<(), Error> {
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
                Err(e) => break Err(Error::Status(e)),
            }
            next_at = Instant::now() + every;
            if let Err(e) = terminal.draw(|f| draw(f, prev.as_ref(), &now, &note)) {
                break Err(Error::Draw(e));
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
            Err(e) => break Err(Error::ReadTerminal(e)),
        }
    };
    ratatui::restore();
    result
}

#[cfg(test)]
mod tests {
    use super::*;
    #[test]
    fn the_live_view_draws_the_nodes_and_edges_of_a_snapshot() {
        let g = pipelines::launch::load_with(None, &[]).unwrap();
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
