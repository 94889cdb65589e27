//! What one edge costs: the same frames sent over iceoryx2 shared memory (loaned, written in
//! place, the reader woken by an event) and copied through a Unix-domain socket, between two
//! threads. `microstereo bench-transport` prints both side by side.
//!
//! Latency is measured one frame at a time (the writer waits for the reader's
//! acknowledgement before the next frame, so no queue forms): from just before the send,
//! after the frame is written, to the reader holding the frame, having read its first and last
//! byte. Throughput is frames sent back to back through a lossless edge of depth 4.
//!
//! Where the two ends run matters more than the transport on a virtual machine: waking a
//! thread on another core costs a hypervisor-mediated interrupt (17–24 µs at the median
//! on the 2-core development VM, for a bare futex: [`wake_floor`]), while a wake-up on the
//! same core costs 2–3 µs. [`Placement`] pins both ends to one core, to two cores, or leaves them to the
//! scheduler, and both transports are timed the same way.

use crate::process::{now_ns, percentile};
use crate::transport::{EdgeConfig, Overflow, Transport, Wake, wait_loop};
use schemas::{FrameHeader, MessageKind, PixelFormat};
use std::io::{Read, Write};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// Where the writer and the reader of the benchmark edge run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Placement {
    /// Wherever the scheduler puts them.
    Free,
    /// Both on the first CPU the process may use.
    OneCore,
    /// The writer on the first CPU the process may use, the reader on the second.
    TwoCores,
}

impl Placement {
    /// The CPUs of the writer and the reader (none: not pinned).
    fn cpus(self) -> Result<(Option<usize>, Option<usize>), String> {
        if self == Placement::Free {
            return Ok((None, None));
        }
        let allowed = allowed_cpus()?;
        match (self, allowed.as_slice()) {
            (Placement::OneCore, [a, ..]) => Ok((Some(*a), Some(*a))),
            (Placement::TwoCores, [a, b, ..]) => Ok((Some(*a), Some(*b))),
            _ => Err(format!(
                "{self:?} needs more CPUs than the {} this process may use",
                allowed.len()
            )),
        }
    }
}

#[cfg(target_os = "linux")]
fn allowed_cpus() -> Result<Vec<usize>, String> {
    // SAFETY: a zeroed cpu_set_t is a valid empty set, filled in by the kernel.
    let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
    let size = std::mem::size_of::<libc::cpu_set_t>();
    // SAFETY: `set` is a live cpu_set_t of `size` bytes.
    if unsafe { libc::sched_getaffinity(0, size, &mut set) } != 0 {
        return Err(format!(
            "reading the CPU affinity: {}",
            std::io::Error::last_os_error()
        ));
    }
    Ok((0..libc::CPU_SETSIZE as usize)
        // SAFETY: `set` is initialised and the index is below CPU_SETSIZE.
        .filter(|&c| unsafe { libc::CPU_ISSET(c, &set) })
        .collect())
}

#[cfg(target_os = "linux")]
fn pin(cpu: Option<usize>) -> Result<(), String> {
    let Some(cpu) = cpu else { return Ok(()) };
    // SAFETY: a zeroed cpu_set_t is a valid empty set.
    let mut set: libc::cpu_set_t = unsafe { std::mem::zeroed() };
    // SAFETY: CPU_SET writes bit `cpu` of the live set; a cpu past CPU_SETSIZE is ignored.
    unsafe { libc::CPU_SET(cpu, &mut set) };
    // SAFETY: `set` is a live cpu_set_t; pid 0 is the calling thread.
    if unsafe { libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set) } != 0 {
        return Err(format!(
            "pinning a benchmark thread to CPU {cpu}: {}",
            std::io::Error::last_os_error()
        ));
    }
    Ok(())
}

#[cfg(not(target_os = "linux"))]
fn allowed_cpus() -> Result<Vec<usize>, String> {
    Err("pinning benchmark threads to CPUs needs Linux; use the free placement".into())
}

#[cfg(not(target_os = "linux"))]
fn pin(cpu: Option<usize>) -> Result<(), String> {
    match cpu {
        None => Ok(()),
        Some(_) => allowed_cpus().map(|_| ()),
    }
}

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
pub fn iceoryx2(bytes: usize, frames: usize, placement: Placement) -> Result<HopStats, String> {
    let edge = format!("microstereo/bench/{}/{bytes}", std::process::id());
    let cfg = EdgeConfig {
        depth: 4,
        overflow: Overflow::Block,
    };
    let run = |paced: bool, reader_cpu: Option<usize>| -> Result<(Vec<f64>, Duration), String> {
        let t = Transport::new("bench-writer").map_err(|e| e.to_string())?;
        let p = t.publisher(&edge, &cfg).map_err(|e| e.to_string())?;
        let (seen_tx, seen_rx) = mpsc::channel::<Seen>();
        let reader = {
            let edge = edge.clone();
            std::thread::spawn(move || -> Result<(), String> {
                pin(reader_cpu)?;
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
    measure(frames, placement, run)
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

/// A latency run then a throughput run of `run(paced, reader_cpu)`, its writer on a thread
/// of its own placed as asked (the caller's CPU affinity stays as it was).
fn measure(
    frames: usize,
    placement: Placement,
    run: impl Fn(bool, Option<usize>) -> Result<(Vec<f64>, Duration), String> + Sync,
) -> Result<HopStats, String> {
    on_writer(placement, |reader_cpu| {
        let (mut lat, _) = run(true, reader_cpu)?;
        let (_, elapsed) = run(false, reader_cpu)?;
        Ok(HopStats {
            p50_us: percentile(&mut lat, 0.5),
            p99_us: percentile(&mut lat, 0.99),
            fps: frames as f64 / elapsed.as_secs_f64(),
        })
    })
}

/// Runs `writer(reader_cpu)` on a thread of its own, pinned where `placement` puts the
/// writer (the caller's CPU affinity stays as it was).
fn on_writer<T: Send>(
    placement: Placement,
    writer: impl FnOnce(Option<usize>) -> Result<T, String> + Send,
) -> Result<T, String> {
    let (writer_cpu, reader_cpu) = placement.cpus()?;
    std::thread::scope(|s| {
        s.spawn(|| {
            pin(writer_cpu)?;
            writer(reader_cpu)
        })
        .join()
        .map_err(|_| "the benchmark writer panicked".to_string())?
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
pub fn unix_socket(bytes: usize, frames: usize, placement: Placement) -> Result<HopStats, String> {
    let run = |paced: bool, reader_cpu: Option<usize>| -> Result<(Vec<f64>, Duration), String> {
        let (mut w, mut r) =
            std::os::unix::net::UnixStream::pair().map_err(|e| format!("socket pair: {e}"))?;
        let (seen_tx, seen_rx) = mpsc::channel::<Seen>();
        let reader = std::thread::spawn(move || -> Result<(), String> {
            pin(reader_cpu)?;
            let mut buf = vec![0u8; bytes];
            let mut head = [0u8; 8];
            for _ in 0..frames {
                r.read_exact(&mut head)
                    .and_then(|_| r.read_exact(&mut buf))
                    .map_err(|e| format!("socket read: {e}"))?;
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
        reader.join().map_err(|_| "the reader panicked")??;
        Ok((lat, elapsed))
    };
    measure(frames, placement, run)
}

/// The operating system's own price of a wake-up with this placement, the floor under any
/// event-driven edge: one thread parks, the other stamps the time and unparks it (a bare
/// futex), `frames` times. Returns the p50 and p99 in µs.
pub fn wake_floor(frames: usize, placement: Placement) -> Result<(f64, f64), String> {
    use std::sync::Arc;
    use std::sync::atomic::{AtomicU64, Ordering};
    on_writer(placement, |reader_cpu| {
        let stamp = Arc::new(AtomicU64::new(0));
        let (tx, rx) = mpsc::channel::<u64>();
        let reader = {
            let stamp = stamp.clone();
            std::thread::spawn(move || -> Result<(), String> {
                pin(reader_cpu)?;
                for _ in 0..frames {
                    // park() may return early; the stamp says whether this was the wake.
                    let sent = loop {
                        match stamp.swap(0, Ordering::AcqRel) {
                            0 => std::thread::park(),
                            t => break t,
                        }
                    };
                    let _ = tx.send(now_ns().saturating_sub(sent));
                }
                Ok(())
            })
        };
        let mut lat = Vec::with_capacity(frames);
        for k in 0..frames {
            stamp.store(now_ns(), Ordering::Release);
            reader.thread().unpark();
            let ns = rx
                .recv_timeout(Duration::from_secs(10))
                .map_err(|_| format!("wake-up {k} never arrived"))?;
            lat.push(ns as f64 / 1e3);
        }
        reader.join().map_err(|_| "the reader panicked")??;
        Ok((percentile(&mut lat, 0.5), percentile(&mut lat, 0.99)))
    })
}

/// Times one edge over iceoryx2 and over a Unix-domain socket for three frame sizes (0.3,
/// 1.3 and 5 MP) and prints them side by side with the ratios, one table per placement of
/// the two ends (`microstereo bench-transport`).
pub fn print_tables(frames: usize, placements: &[Placement]) -> Result<(), String> {
    for &placement in placements {
        let (wake50, wake99) = wake_floor(frames, placement)?;
        crate::outln!(
            "writer and reader {} (a bare thread wake-up: p50 {wake50:.1} µs, p99 {wake99:.1} µs)",
            match placement {
                Placement::OneCore => "on one core",
                Placement::TwoCores => "on two cores",
                Placement::Free => "where the scheduler puts them",
            }
        );
        crate::outln!(
            "{:<22} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9} {:>8} {:>8}",
            "frame",
            "shm p50",
            "shm p99",
            "shm fps",
            "uds p50",
            "uds p99",
            "uds fps",
            "p50 ×",
            "fps ×"
        );
        for (name, w, h) in [
            ("0.3 MP (640×480)", 640usize, 480usize),
            ("1.3 MP (1280×1024)", 1280, 1024),
            ("5 MP (2592×1944)", 2592, 1944),
        ] {
            let bytes = w * h;
            let shm = iceoryx2(bytes, frames, placement)?;
            let uds = unix_socket(bytes, frames, placement)?;
            crate::outln!(
                "{:<22} {:>9.1} {:>9.1} {:>9.0} {:>9.1} {:>9.1} {:>9.0} {:>8.1} {:>8.1}",
                name,
                shm.p50_us,
                shm.p99_us,
                shm.fps,
                uds.p50_us,
                uds.p99_us,
                uds.fps,
                uds.p50_us / shm.p50_us,
                shm.fps / uds.fps
            );
        }
    }
    crate::outln!(
        "latencies in µs, one frame at a time; fps back to back through a lossless edge of depth 4"
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_edges_carry_every_frame_intact() {
        // The byte checks inside fail the run on a lost or stale frame.
        for (bytes, placement) in [(1000, Placement::Free), (300_000, Placement::OneCore)] {
            let a = iceoryx2(bytes, 20, placement).unwrap();
            let b = unix_socket(bytes, 20, placement).unwrap();
            assert!(
                a.p50_us > 0.0 && a.p99_us >= a.p50_us && a.fps > 0.0,
                "{a:?}"
            );
            assert!(
                b.p50_us > 0.0 && b.p99_us >= b.p50_us && b.fps > 0.0,
                "{b:?}"
            );
        }
        let (p50, p99) = wake_floor(50, Placement::OneCore).unwrap();
        assert!(p50 > 0.0 && p99 >= p50, "{p50} {p99}");
    }

    #[test]
    #[cfg(target_os = "linux")]
    fn placements_pin_the_threads_where_they_say() {
        let cpus = allowed_cpus().unwrap();
        let (w, r) = Placement::OneCore.cpus().unwrap();
        assert_eq!((w, r), (Some(cpus[0]), Some(cpus[0])));
        assert_eq!(Placement::Free.cpus().unwrap(), (None, None));
        match Placement::TwoCores.cpus() {
            Ok((Some(w), Some(r))) => assert!(w != r && cpus.contains(&r)),
            Ok(other) => panic!("{other:?}"),
            Err(e) => assert!(cpus.len() < 2 && e.contains("needs more CPUs"), "{e}"),
        }
        for &cpu in cpus.iter().take(2) {
            let on = std::thread::spawn(move || {
                pin(Some(cpu)).unwrap();
                // SAFETY: sched_getcpu has no preconditions.
                unsafe { libc::sched_getcpu() }
            })
            .join()
            .unwrap();
            assert_eq!(on, cpu as i32);
        }
    }
}
