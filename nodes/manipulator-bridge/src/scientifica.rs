//! Scientifica manipulators (PatchStar, MicroStar, IVM; motion card version 3) over their
//! ASCII serial protocol, after the public command set as acq4's driver uses it, and an
//! emulator of it for tests.
//!
//! Commands and answers are ASCII lines ending in CR; positions are in ticks of 0.01 µm
//! (version 3 cards; 0.1 µm on version 2, whose position command is `POS`):
//!
//! | command | answer |
//! |---|---|
//! | `VER` | the card's version, e.g. `3.2` |
//! | `DESC` | the device's description |
//! | `P` | `x` TAB `y` TAB `z`, ticks |
//! | `ABS x y z` | `A` (the move starts) |
//! | `S` | `0` when still, another number while moving |
//! | `TOP v` | `A` (top speed, µm/s on version 3) |
//! | `STOP` | `A` (stops at once) |
//!
//! An unknown or malformed command is answered `E`. Unlike the MP-285, the controller
//! answers during a move, so the position is read, not estimated.

use crate::device::{Device, DeviceError, DeviceState, EmergencyStop, SerialStop};
use crate::geom::P3;
use serialport::SerialPort;
use std::io::{Read, Write};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

const CR: u8 = 0x0d;

/// A Scientifica manipulator on a serial line.
pub struct Scientifica {
    port: Box<dyn SerialPort>,
    name: String,
    ticks_per_um: f64,
    /// The version-2 position command (`POS`) instead of version 3's (`P`).
    old: bool,
    speed: Option<f64>,
    timeout: Duration,
    /// `STOP`s sent by the emergency stop's handle, from another thread: each is answered
    /// `A` between the driver's own answers.
    estops: Arc<AtomicU64>,
    /// Of those answers, the ones this driver has read.
    estops_read: u64,
}

impl Scientifica {
    /// Opens the controller on serial port `path` (9600 baud, 8N1) and reads its version.
    pub fn open(path: &str, timeout: Duration) -> Result<Self, DeviceError> {
        let port = serialport::new(path, 9600)
            .timeout(Duration::from_millis(20))
            .open()
            .map_err(|e| {
                DeviceError(format!(
                    "cannot open the Scientifica port {path}: {e}; check the cable and the device path"
                ))
            })?;
        Self::with_port(port, path, timeout)
    }

    /// Talks to a controller on an open port.
    pub fn with_port(
        port: Box<dyn SerialPort>,
        name: &str,
        timeout: Duration,
    ) -> Result<Self, DeviceError> {
        let mut d = Self {
            port,
            name: name.into(),
            ticks_per_um: 100.0,
            old: false,
            speed: None,
            timeout,
            estops: Arc::default(),
            estops_read: 0,
        };
        let _ = d.port.clear(serialport::ClearBuffer::All);
        let ver = d.command("VER")?;
        let v: f64 = ver
            .trim()
            .parse()
            .map_err(|_| d.err(format!("answered VER with '{ver}', not a version")))?;
        if v < 3.0 {
            d.ticks_per_um = 10.0;
            d.old = true;
        }
        let desc = d.command("DESC")?;
        d.name = format!("Scientifica {} on {name}", desc.trim());
        d.position()?;
        Ok(d)
    }

    fn err(&self, what: String) -> DeviceError {
        DeviceError(format!("{}: {what}", self.name))
    }

    /// Sends `cmd` and reads its answer line.
    fn command(&mut self, cmd: &str) -> Result<String, DeviceError> {
        self.port
            .write_all(format!("{cmd}\r").as_bytes())
            .map_err(|e| self.err(format!("cannot write ({e})")))?;
        let mut line = Vec::new();
        let mut b = [0u8; 1];
        let deadline = Instant::now() + self.timeout;
        // Commands answered with anything but `A` take an `A` for the emergency stop's.
        let acked = matches!(cmd.split(' ').next(), Some("ABS" | "TOP" | "STOP"));
        loop {
            match self.port.read(&mut b) {
                Ok(1) if b[0] == CR => {
                    if !acked
                        && line == b"A"
                        && self.estops_read < self.estops.load(Ordering::SeqCst)
                    {
                        self.estops_read += 1;
                        line.clear();
                        continue;
                    }
                    break;
                }
                Ok(1) => line.push(b[0]),
                Ok(_) => {}
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::TimedOut | std::io::ErrorKind::Interrupted
                    ) => {}
                Err(e) => return Err(self.err(format!("cannot read ({e})"))),
            }
            if Instant::now() > deadline {
                return Err(self.err(format!(
                    "no answer to '{cmd}'; is it connected and switched on?"
                )));
            }
        }
        let s = String::from_utf8_lossy(&line).into_owned();
        if s.trim() == "E" {
            return Err(self.err(format!("refused '{cmd}'")));
        }
        Ok(s)
    }

    fn position(&mut self) -> Result<P3, DeviceError> {
        let a = self.command(if self.old { "POS" } else { "P" })?;
        let v: Vec<f64> = a
            .split(['\t', ' '])
            .filter(|s| !s.is_empty())
            .filter_map(|s| s.trim().parse().ok())
            .collect();
        if v.len() != 3 {
            return Err(self.err(format!("answered its position with '{a}'")));
        }
        Ok([
            v[0] / self.ticks_per_um,
            v[1] / self.ticks_per_um,
            v[2] / self.ticks_per_um,
        ])
    }

    /// Ticks per µm the controller counts in.
    pub fn ticks_per_um(&self) -> f64 {
        self.ticks_per_um
    }
}

impl Device for Scientifica {
    fn describe(&self) -> String {
        self.name.clone()
    }

    fn start_move(&mut self, to: P3, speed: f64) -> Result<(), DeviceError> {
        if !(speed > 0.0 && speed.is_finite()) {
            return Err(self.err(format!("speed {speed} µm/s")));
        }
        let t = to.map(|v| (v * self.ticks_per_um).round());
        if t.iter().any(|v| v.abs() > i32::MAX as f64) {
            return Err(self.err(format!("{to:?} µm is beyond the controller's range")));
        }
        if self.speed != Some(speed) {
            let a = self.command(&format!("TOP {}", speed.round().max(1.0)))?;
            if a.trim() != "A" {
                return Err(self.err(format!("answered TOP with '{a}'")));
            }
            self.speed = Some(speed);
        }
        let a = self.command(&format!(
            "ABS {} {} {}",
            t[0] as i64, t[1] as i64, t[2] as i64
        ))?;
        if a.trim() != "A" {
            return Err(self.err(format!("answered ABS with '{a}'")));
        }
        Ok(())
    }

    fn state(&mut self) -> Result<DeviceState, DeviceError> {
        let s = self.command("S")?;
        let moving = s
            .trim()
            .parse::<i64>()
            .map_err(|_| self.err(format!("answered S with '{s}'")))?
            != 0;
        Ok(DeviceState {
            position: self.position()?,
            moving,
        })
    }

    fn stop(&mut self) -> Result<(), DeviceError> {
        let a = self.command("STOP")?;
        if a.trim() != "A" {
            return Err(self.err(format!("answered STOP with '{a}'")));
        }
        Ok(())
    }

    fn emergency_stop(&mut self) -> Result<Arc<dyn EmergencyStop>, DeviceError> {
        // Commands are read one by one; the driver skips the `A` this one is answered with.
        SerialStop::on(&*self.port, &self.estops, self.name.clone(), b"STOP\r")
    }
}

/// A Scientifica controller (version 3) emulated on the master side of a pseudo-terminal.
pub mod emulator {
    use super::CR;
    use std::io::{Read, Write};
    use std::sync::{Arc, Mutex};
    use std::time::{Duration, Instant};

    /// What the emulated controller holds.
    #[derive(Clone, Debug, Default)]
    pub struct EmulatorState {
        /// Position, ticks of 0.01 µm.
        pub ticks: [i64; 3],
        /// Top speed, µm/s.
        pub top: f64,
        /// Every command line received, in order.
        pub commands: Vec<String>,
        /// Moves completed.
        pub moves: u32,
        /// Moves stopped.
        pub stopped: u32,
        /// Set to make it stop answering.
        pub mute: bool,
    }

    /// Runs the emulator on `port` in a thread until the line closes.
    pub fn spawn(mut port: Box<dyn serialport::SerialPort>) -> Arc<Mutex<EmulatorState>> {
        let state = Arc::new(Mutex::new(EmulatorState {
            top: 1000.0,
            ..Default::default()
        }));
        let st = state.clone();
        let _ = port.set_timeout(Duration::from_millis(2));
        std::thread::spawn(move || {
            let mut buf: Vec<u8> = Vec::new();
            let mut byte = [0u8; 64];
            // A move: from, to (ticks), start, duration (s).
            let mut moving: Option<([i64; 3], [i64; 3], Instant, f64)> = None;
            let at = |m: &([i64; 3], [i64; 3], Instant, f64)| {
                let f = (m.2.elapsed().as_secs_f64() / m.3).min(1.0);
                [0, 1, 2].map(|k| m.0[k] + ((m.1[k] - m.0[k]) as f64 * f).round() as i64)
            };
            loop {
                match port.read(&mut byte) {
                    Ok(0) => return,
                    Ok(k) => buf.extend_from_slice(&byte[..k]),
                    Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                    Err(_) => return,
                }
                if let Some(m) = moving
                    && m.2.elapsed().as_secs_f64() >= m.3
                {
                    let mut s = st.lock().expect("state");
                    s.ticks = m.1;
                    s.moves += 1;
                    moving = None;
                }
                while let Some(i) = buf.iter().position(|&b| b == CR) {
                    let line: Vec<u8> = buf.drain(..=i).collect();
                    let cmd = String::from_utf8_lossy(&line[..line.len() - 1])
                        .trim()
                        .to_string();
                    let mut s = st.lock().expect("state");
                    if s.mute {
                        continue;
                    }
                    s.commands.push(cmd.clone());
                    if let Some(m) = moving {
                        s.ticks = at(&m);
                    }
                    let words: Vec<&str> = cmd.split_whitespace().collect();
                    let reply = match words.as_slice() {
                        [w] if w.eq_ignore_ascii_case("VER") => "3.2".to_string(),
                        [w] if w.eq_ignore_ascii_case("DESC") => "PatchStar (emulated)".to_string(),
                        [w] if w.eq_ignore_ascii_case("P") => {
                            format!("{}\t{}\t{}", s.ticks[0], s.ticks[1], s.ticks[2])
                        }
                        [w] if w.eq_ignore_ascii_case("S") => {
                            if moving.is_some() { "1" } else { "0" }.to_string()
                        }
                        [w] if w.eq_ignore_ascii_case("STOP") => {
                            if moving.take().is_some() {
                                s.stopped += 1;
                            }
                            "A".to_string()
                        }
                        [w, v] if w.eq_ignore_ascii_case("TOP") => match v.parse::<f64>() {
                            Ok(v) if v > 0.0 => {
                                s.top = v;
                                "A".to_string()
                            }
                            _ => "E".to_string(),
                        },
                        [w, x, y, z] if w.eq_ignore_ascii_case("ABS") => {
                            match (x.parse::<i64>(), y.parse::<i64>(), z.parse::<i64>()) {
                                (Ok(x), Ok(y), Ok(z)) => {
                                    let to = [x, y, z];
                                    let d_um = (0..3)
                                        .map(|k| ((to[k] - s.ticks[k]) as f64).powi(2))
                                        .sum::<f64>()
                                        .sqrt()
                                        / 100.0;
                                    moving = Some((
                                        s.ticks,
                                        to,
                                        Instant::now(),
                                        (d_um / s.top).max(1e-3),
                                    ));
                                    "A".to_string()
                                }
                                _ => "E".to_string(),
                            }
                        }
                        _ => "E".to_string(),
                    };
                    drop(s);
                    if port.write_all(format!("{reply}\r").as_bytes()).is_err() {
                        return;
                    }
                }
            }
        });
        state
    }
}
