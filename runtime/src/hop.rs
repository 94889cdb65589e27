//! What one edge costs: the same frames sent over iceoryx2 shared memory (loaned, written in
//! place, the reader woken by an event) and copied through a Unix-domain socket, between two
//! threads. `microstereo bench-transport` prints both side by side.
//!
//! Latency is measured one frame at a time (the writer waits for the reader's
//! acknowledgement before the next frame, so no queue forms): from just before the send,
//! after the frame is written, to the reader holding the frame, having read its first and last
//! byte. Throughput is frames sent back to back through a lossless edge of depth 4.

use crate::process::{now_ns, percentile};
use crate::transport::{EdgeConfig, Overflow, Transport, Wake, wait_loop};
use schemas::{FrameHeader, MessageKind, PixelFormat};
use std::io::{Read, Write};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// The cost of one edge for one frame size.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HopStats {
    /// Median send-to-read latency, µs.
    pub p50_us: f64,
    /// 99th-percentile send-to-read latency, µs.
    pub p99_us: f64,
    /// Frames per second, back to back.
    pub fps: f64,
}

fn fill(b: &mut [u8], k: usize) {
    // Touches every page, as a camera's driver or a node writing its result would.
    for (i, v) in b.iter_mut().enumerate().step_by(4096) {
        *v = (i / 4096 + k) as u8;
    }
    if let Some(last) = b.last_mut() {
        *last = k as u8;
    }
}

/// What the reader saw of one frame: its stamp and two of its bytes.
type Seen = (u64, u8, u8);

/// `frames` frames of `bytes` bytes over an iceoryx2 edge, latency then throughput.
pub fn iceoryx2(bytes: usize, frames: usize) -> Result<HopStats, String> {
    let edge = format!("microstereo/bench/{}/{bytes}", std::process::id());
    let cfg = EdgeConfig {
        depth: 4,
        overflow: Overflow::Block,
    };
    let run = |paced: bool| -> Result<(Vec<f64>, Duration), String> {
        let t = Transport::new("bench-writer").map_err(|e| e.to_string())?;
        let p = t.publisher(&edge, &cfg).map_err(|e| e.to_string())?;
        let (seen_tx, seen_rx) = mpsc::channel::<Seen>();
        let reader = {
            let edge = edge.clone();
            std::thread::spawn(move || -> Result<(), String> {
                let t = Transport::new("bench-reader").map_err(|e| e.to_string())?;
                let s = t
                    .reader(&edge, &cfg, Some("bench.in"))
                    .map_err(|e| e.to_string())?;
                let mut got = 0;
                wait_loop::<String>(&[&s], Duration::from_secs(5), |wake, _| {
                    let before = got;
                    while let Some(m) = s.receive()? {
                        let seen = now_ns();
                        let b = m.payload();
                        let _ =
                            seen_tx.send((seen - m.user_header().capture_ns, b[0], b[b.len() - 1]));
                        got += 1;
                    }
                    if wake == Wake::Timeout && got == before {
                        return Err("no frame within 5 s".into());
                    }
                    Ok(got < frames && wake != Wake::Stop)
                })
            })
        };
        let start = Instant::now();
        while p.reader_names().is_empty() {
            if start.elapsed() > Duration::from_secs(10) {
                return Err("the reader did not connect".into());
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        let (lat, elapsed) = drive(frames, bytes, paced, &seen_rx, |k| {
            let header = FrameHeader {
                sequence: k as u64,
                ..FrameHeader::image(MessageKind::Image, PixelFormat::Mono8, bytes, 1, 1)
            };
            p.send_stamped(header, bytes, |b| fill(b, k))
                .map_err(|e| e.to_string())
        })?;
        reader.join().map_err(|_| "the reader panicked")??;
        Ok((lat, elapsed))
    };
    measure(frames, run)
}

/// Sends `frames` frames with `send(k)`: one at a time, each latency kept, when `paced`;
/// else back to back. Returns the latencies and the time until the reader had them all.
fn drive(
    frames: usize,
    bytes: usize,
    paced: bool,
    seen: &mpsc::Receiver<Seen>,
    mut send: impl FnMut(usize) -> Result<(), String>,
) -> Result<(Vec<f64>, Duration), String> {
    let mut lat = Vec::with_capacity(frames);
    let start = Instant::now();
    for k in 0..frames {
        send(k)?;
        if paced {
            lat.push(check(seen.recv_timeout(Duration::from_secs(10)), bytes, k)?);
        }
    }
    if !paced {
        for k in 0..frames {
            check(seen.recv_timeout(Duration::from_secs(10)), bytes, k)?;
        }
    }
    Ok((lat, start.elapsed()))
}

/// A latency run then a throughput run of `run`.
fn measure(
    frames: usize,
    run: impl Fn(bool) -> Result<(Vec<f64>, Duration), String>,
) -> Result<HopStats, String> {
    let (mut lat, _) = run(true)?;
    let (_, elapsed) = run(false)?;
    Ok(HopStats {
        p50_us: percentile(&mut lat, 0.5),
        p99_us: percentile(&mut lat, 0.99),
        fps: frames as f64 / elapsed.as_secs_f64(),
    })
}

/// The latency of a frame from what the reader saw; the two bytes prove it read frame `k`.
fn check(
    seen: Result<Seen, mpsc::RecvTimeoutError>,
    bytes: usize,
    k: usize,
) -> Result<f64, String> {
    let (ns, first, last) =
        seen.map_err(|_| format!("frame {k} of {bytes} bytes never arrived"))?;
    if first != k as u8 || last != k as u8 {
        return Err(format!("frame {k}: the reader saw the wrong bytes"));
    }
    Ok(ns as f64 / 1e3)
}

/// `frames` frames of `bytes` bytes copied through a Unix-domain socket, latency then
/// throughput.
pub fn unix_socket(bytes: usize, frames: usize) -> Result<HopStats, String> {
    let run = |paced: bool| -> Result<(Vec<f64>, Duration), String> {
        let (mut w, mut r) =
            std::os::unix::net::UnixStream::pair().map_err(|e| format!("socket pair: {e}"))?;
        let (seen_tx, seen_rx) = mpsc::channel::<Seen>();
        let reader = std::thread::spawn(move || -> std::io::Result<()> {
            let mut buf = vec![0u8; bytes];
            let mut head = [0u8; 8];
            for _ in 0..frames {
                r.read_exact(&mut head)?;
                r.read_exact(&mut buf)?;
                let seen = now_ns();
                let _ = seen_tx.send((seen - u64::from_le_bytes(head), buf[0], buf[buf.len() - 1]));
            }
            Ok(())
        });
        let mut frame = vec![0u8; bytes];
        let (lat, elapsed) = drive(frames, bytes, paced, &seen_rx, |k| {
            fill(&mut frame, k);
            w.write_all(&now_ns().to_le_bytes())
                .and_then(|_| w.write_all(&frame))
                .map_err(|e| format!("socket write: {e}"))
        })?;
        reader
            .join()
            .map_err(|_| "the reader panicked")?
            .map_err(|e| format!("socket read: {e}"))?;
        Ok((lat, elapsed))
    };
    measure(frames, run)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_edges_carry_every_frame_intact() {
        // The byte checks inside fail the run on a lost or stale frame.
        for bytes in [1000, 300_000] {
            let a = iceoryx2(bytes, 20).unwrap();
            let b = unix_socket(bytes, 20).unwrap();
            assert!(
                a.p50_us > 0.0 && a.p99_us >= a.p50_us && a.fps > 0.0,
                "{a:?}"
            );
            assert!(
                b.p50_us > 0.0 && b.p99_us >= b.p50_us && b.fps > 0.0,
                "{b:?}"
            );
        }
    }
}
