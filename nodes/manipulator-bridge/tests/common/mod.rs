//! What the bridge's TCP tests share: a round cell, the simulated device, a controller.

#![allow(dead_code)]

use manipulator_bridge::bridge::{Bridge, BridgeConfig};
use manipulator_bridge::device::{Device, DeviceError, SimDevice, wall_clock};
use schemas::Cell3;
use serde_json::Value;
use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

/// A round cell of radius `r` and height `h` at `(x, y)` on the substrate at depth 4000 µm.
pub fn cell(id: u32, x: f64, y: f64, r: f64, h: f64) -> Cell3 {
    Cell3 {
        id,
        right_id: id,
        area_px: 1,
        centroid_px: [0.0, 0.0],
        disparity: 0.0,
        centroid: [x, y, 4000.0 - h / 2.0],
        substrate_z: 4000.0,
        height: Some(h),
        volume: 0.0,
        contour: (0..24)
            .map(|k| {
                let a = k as f64 * std::f64::consts::TAU / 24.0;
                [x + r * a.cos(), y + r * a.sin(), 4000.0]
            })
            .collect(),
        valid_share: 1.0,
        quality: schemas::CellQuality {
            trusted: true,
            ..Default::default()
        },
    }
}

/// The simulated manipulator at the bridge's home.
pub fn sim(cfg: &BridgeConfig) -> Result<Box<dyn Device>, DeviceError> {
    Ok(Box::new(SimDevice::new(
        cfg.device_for(cfg.home),
        1000.0,
        2000.0,
        wall_clock(),
    )))
}

/// A controller on the bridge's TCP port.
pub struct Client {
    /// Its sending side.
    pub w: TcpStream,
    /// Its lines from the bridge.
    pub lines: std::io::Lines<BufReader<TcpStream>>,
}

impl Client {
    /// Connects and waits until the bridge holds it.
    pub fn connect(b: &Bridge) -> Self {
        let s = TcpStream::connect(b.addr).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
        // Each command in one write, without Nagle's wait: a command sent in two small
        // writes waited for the first one's acknowledgement (up to 40 ms) before the
        // newline went out.
        s.set_nodelay(true).unwrap();
        let t0 = Instant::now();
        while b.controllers() == 0 {
            assert!(t0.elapsed() < Duration::from_secs(5));
            std::thread::sleep(Duration::from_millis(1));
        }
        Self {
            w: s.try_clone().unwrap(),
            lines: BufReader::new(s).lines(),
        }
    }

    /// Sends one command line.
    pub fn send(&mut self, line: &str) {
        self.w.write_all(format!("{line}\n").as_bytes()).unwrap();
    }

    /// The next event of one of these kinds (scenes and progress skipped unless asked).
    pub fn next(&mut self, want: &[&str]) -> Value {
        loop {
            let l = self.lines.next().expect("open").expect("a line in time");
            let v: Value = serde_json::from_str(&l).unwrap();
            if want.contains(&v["event"].as_str().unwrap()) {
                return v;
            }
        }
    }
}
