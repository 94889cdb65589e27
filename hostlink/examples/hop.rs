//! Times one edge between two iceoryx2 domains joined by two links over loopback, as the
//! graph's edges between hosts are: the latency of a frame (written in one domain, read in
//! the other; p50/p99 at a paced 10 frames/s) and the most frames a second it carries
//! (unpaced, the writer waiting for the reader), for a stereo frame at 1280×1024 and the
//! sizes of the cell-only messages.
//!
//! `cargo run --release -p hostlink --example hop [FRAMES]`

use hostlink::{Endpoints, HostLink};
use iceoryx2::prelude::*;
use std::time::{Duration, Instant};

#[derive(Debug, Clone, Copy, ZeroCopySend, Default)]
#[repr(C)]
struct Head {
    seq: u64,
    sent_ns: u64,
}

fn now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos() as u64
}

fn domain(name: &str) -> iceoryx2::config::Config {
    let mut c = iceoryx2::config::Config::global_config().clone();
    c.global.prefix =
        FileName::new(format!("hop{name}{}_", std::process::id()).as_bytes()).unwrap();
    c
}

fn main() {
    let frames: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(200);
    let (a, b) = (domain("a"), domain("b"));
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let ep = format!("tcp/127.0.0.1:{port}");
    let admit = |n: &str| n.starts_with("hop/");
    let _la = HostLink::start(
        a.clone(),
        &Endpoints {
            listen: vec![ep.clone()],
            connect: vec![],
        },
        admit,
    )
    .unwrap();
    let _lb = HostLink::start(
        b.clone(),
        &Endpoints {
            listen: vec![],
            connect: vec![ep],
        },
        admit,
    )
    .unwrap();
    let node_a = NodeBuilder::new()
        .config(&a)
        .create::<ipc::Service>()
        .unwrap();
    let node_b = NodeBuilder::new()
        .config(&b)
        .create::<ipc::Service>()
        .unwrap();
    println!(
        "{:<34} {:>10} {:>10} {:>12} {:>10} {:>8}",
        "message", "p50 ms", "p99 ms", "frames/s", "MB/s", "lost"
    );
    for (i, (name, bytes)) in [
        ("stereo frame 1280×1024 (2.6 MB)", 1280 * 1024 * 2),
        ("one image 1280×1024 (1.3 MB)", 1280 * 1024),
        ("disparity tiles of 10 cells", 160_000),
        ("labels crop / cell list", 4_000),
        ("targets (cells in 3D)", 600),
    ]
    .into_iter()
    .enumerate()
    {
        let service = ServiceName::new(&format!("hop/{i}")).unwrap();
        let open = |node: &Node<ipc::Service>| {
            node.service_builder(&service)
                .publish_subscribe::<[u8]>()
                .user_header::<Head>()
                .subscriber_max_buffer_size(8)
                .enable_safe_overflow(false)
                .open_or_create()
                .unwrap()
        };
        let (sa, sb) = (open(&node_a), open(&node_b));
        let publisher = sa
            .publisher_builder()
            .initial_max_slice_len(bytes)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .create()
            .unwrap();
        let subscriber = sb.subscriber_builder().buffer_size(8).create().unwrap();
        let send = |seq: u64| {
            let s = publisher.loan_slice_uninit(bytes).unwrap();
            let mut s = s.write_from_fn(|k| (k as u64 + seq) as u8);
            *s.user_header_mut() = Head {
                seq,
                sent_ns: now_ns(),
            };
            s.send().unwrap();
        };
        // Until the far side reads what is sent here.
        let t0 = Instant::now();
        let mut seq = 0;
        'warm: loop {
            send(seq);
            seq += 1;
            std::thread::sleep(Duration::from_millis(50));
            if subscriber.receive().unwrap().is_some() {
                break 'warm;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(30),
                "the link never carried {name}"
            );
        }
        std::thread::sleep(Duration::from_millis(200));
        while subscriber.receive().unwrap().is_some() {}
        // Latency at 10 frames/s.
        let mut lat = Vec::new();
        let paced = frames.min(100);
        for _ in 0..paced {
            send(seq);
            seq += 1;
            let t = Instant::now();
            loop {
                if let Some(m) = subscriber.receive().unwrap() {
                    lat.push((now_ns() - m.user_header().sent_ns) as f64 * 1e-6);
                    break;
                }
                assert!(t.elapsed() < Duration::from_secs(10), "a frame was lost");
                std::thread::sleep(Duration::from_micros(50));
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        lat.sort_by(f64::total_cmp);
        // Rate: as fast as the writer may with at most 8 frames on their way (the far
        // reader's queue); a frame the link lost counts once a later one arrived.
        let t = Instant::now();
        let first = seq;
        let (mut got, mut newest) = (0usize, first);
        let mut last_progress = Instant::now();
        while seq < first + frames as u64 {
            if seq - newest < 8 {
                send(seq);
                seq += 1;
            }
            while let Some(m) = subscriber.receive().unwrap() {
                got += 1;
                newest = newest.max(m.user_header().seq + 1);
                last_progress = Instant::now();
            }
            if seq - newest >= 8 {
                if last_progress.elapsed() > Duration::from_millis(500) {
                    // What is on its way is lost: go on past it.
                    newest = seq;
                }
                std::thread::sleep(Duration::from_micros(50));
            }
        }
        let end = Instant::now() + Duration::from_secs(1);
        while newest < seq && Instant::now() < end {
            while let Some(m) = subscriber.receive().unwrap() {
                got += 1;
                newest = newest.max(m.user_header().seq + 1);
            }
            std::thread::sleep(Duration::from_micros(50));
        }
        let lost = frames - got;
        let fps = got as f64 / t.elapsed().as_secs_f64();
        println!(
            "{:<34} {:>10.2} {:>10.2} {:>12.1} {:>10.1} {:>8}",
            name,
            lat[lat.len() / 2],
            lat[(lat.len() - 1) * 99 / 100],
            fps,
            fps * bytes as f64 / 1e6,
            lost
        );
    }
}
