//! `topic`: a running graph's edges listed, and one edge watched (`hz`: its rate every
//! window; `echo`: each message's header, then a summary).

use crate::Error;
use crate::attach::{Attach, interval};
use runtime::status::GraphStatus;
use std::time::{Duration, Instant};

/// Which edge of which run, and for how long.
#[derive(Debug, Clone)]
pub struct EdgeOptions {
    /// The edge, as its writer's `NODE/OUTPUT`.
    pub edge: String,
    /// The run.
    pub attach: Attach,
    /// Stop after this many lines (hz: reports; echo: messages); `None`: until the run
    /// ends or Ctrl-C.
    pub count: Option<u64>,
    /// hz: seconds between reports (0.05..3600), each over the messages since the last.
    pub window: f64,
}

/// Prints the run's edges: writer output, message, queue, readers.
pub fn list(attach: &Attach) -> Result<(), Error> {
    let (_, s) = attach.open()?;
    print_edges(&s);
    Ok(())
}

/// Measures an edge's message rate as it runs.
pub fn hz(o: &EdgeOptions) -> Result<(), Error> {
    watch(o, false)
}

/// Prints each message's header on an edge (not its pixels), then a summary.
pub fn echo(o: &EdgeOptions) -> Result<(), Error> {
    watch(o, true)
}

fn print_edges(s: &GraphStatus) {
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

fn watch(a: &EdgeOptions, echo: bool) -> Result<(), Error> {
    let window = interval("--window", a.window)?;
    if a.count == Some(0) {
        return Err(Error::ZeroCount);
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
        return Err(Error::NoEdge {
            instance: s.instance,
            edge: a.edge.clone(),
            known: known.join(", "),
        });
    };
    let sub = reader.transport().watcher(&out.service)?;
    let started = Instant::now();
    let mut all = Tally::default();
    let mut part = Tally::default();
    let mut lines = 0u64;
    let mut part_start = Instant::now();
    let mut ended = false;
    let mut last_status = Instant::now();
    'outer: loop {
        while let Some(item) = sub.receive_item()? {
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
}
