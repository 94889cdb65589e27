//! Two iceoryx2 domains on one machine, joined by two links over loopback: what is
//! published in one arrives in the other, bit for bit.

use hostlink::{Endpoints, HostLink};
use iceoryx2::prelude::*;
use std::time::{Duration, Instant};

#[derive(Debug, Clone, Copy, ZeroCopySend, Default, PartialEq)]
#[repr(C)]
struct Head {
    seq: u64,
    len: u64,
}

fn domain(name: &str) -> iceoryx2::config::Config {
    let mut c = iceoryx2::config::Config::global_config().clone();
    c.global.prefix = FileName::new(format!("hl{name}{}_", std::process::id()).as_bytes()).unwrap();
    c
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

#[test]
fn frames_published_in_one_domain_arrive_whole_in_the_other() {
    let (a, b) = (domain("a"), domain("b"));
    let port = free_port();
    let ep = format!("tcp/127.0.0.1:{port}");
    let service = ServiceName::new("hostlink/test/frames").unwrap();
    let open = |cfg: &iceoryx2::config::Config, node: &Node<ipc::Service>| {
        let _ = cfg;
        node.service_builder(&service)
            .publish_subscribe::<[u8]>()
            .user_header::<Head>()
            .subscriber_max_buffer_size(4)
            .max_subscribers(4)
            .history_size(0)
            .enable_safe_overflow(false)
            .open_or_create()
            .unwrap()
    };
    let node_a = NodeBuilder::new()
        .config(&a)
        .create::<ipc::Service>()
        .unwrap();
    let node_b = NodeBuilder::new()
        .config(&b)
        .create::<ipc::Service>()
        .unwrap();
    let svc_a = open(&a, &node_a);
    let svc_b = open(&b, &node_b);
    let publisher = svc_a
        .publisher_builder()
        .initial_max_slice_len(4096)
        .allocation_strategy(AllocationStrategy::PowerOfTwo)
        .create()
        .unwrap();
    let subscriber = svc_b.subscriber_builder().create().unwrap();
    let admit = |n: &str| n.starts_with("hostlink/test/");
    let link_a = HostLink::start(
        a.clone(),
        &Endpoints {
            listen: vec![ep.clone()],
            connect: vec![],
        },
        admit,
    )
    .unwrap();
    let link_b = HostLink::start(
        b.clone(),
        &Endpoints {
            listen: vec![],
            connect: vec![ep],
        },
        admit,
    )
    .unwrap();
    // Each link sees the other's offer within a few discovery rounds; until then a sample
    // reaches nobody across.
    let size = 1280 * 1024 * 2;
    let fill = |seq: u64, b: &mut [u8]| {
        for (i, v) in b.iter_mut().enumerate() {
            *v = (i as u64).wrapping_mul(31).wrapping_add(seq) as u8;
        }
    };
    let t0 = Instant::now();
    let mut got = Vec::new();
    let mut seq = 0u64;
    while got.len() < 30 {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "only {} arrived",
            got.len()
        );
        let mut s = publisher.loan_slice_uninit(size).unwrap();
        *s.user_header_mut() = Head {
            seq,
            len: size as u64,
        };
        let mut s = s.write_from_fn(|_| 0);
        fill(seq, s.payload_mut());
        s.send().unwrap();
        seq += 1;
        std::thread::sleep(Duration::from_millis(30));
        while let Some(m) = subscriber.receive().unwrap() {
            let h = *m.user_header();
            let mut want = vec![0u8; size];
            fill(h.seq, &mut want);
            assert_eq!(h.len as usize, m.payload().len());
            assert!(m.payload() == &want[..], "frame {} differs", h.seq);
            got.push(h.seq);
        }
    }
    assert!(got.windows(2).all(|w| w[1] > w[0]), "{got:?}");
    link_a.stop();
    link_b.stop();
    drop((publisher, subscriber, svc_a, svc_b, node_a, node_b));
    // The two domains were this test's alone: their own memory (iceoryx2's node counter,
    // which outlives every node) goes with them.
    for cfg in [&a, &b] {
        // SAFETY: iceoryx2 asks that no other process use the domain; these domains are
        // named after this test process, whose every node of them is gone.
        let removed = unsafe { iceoryx2::testing::remove_global_mgmt_segment::<ipc::Service>(cfg) };
        assert!(removed.is_ok_and(|r| r));
    }
}
