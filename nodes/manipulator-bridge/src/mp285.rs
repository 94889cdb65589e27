//! The Sutter MP-285 over a serial line (9600 baud, 8N1), after the public reference
//! manual, and an emulator of it for tests.
//!
//! Commands end with CR (0x0D) and are answered with CR; positions are three little-endian
//! `i32` in microsteps:
//!
//! | command | bytes | answer |
//! |---|---|---|
//! | status | `s` CR | 32 status bytes, CR (microsteps per µm at bytes 24–25) |
//! | position | `c` CR | 12 bytes x y z, CR |
//! | move | `m` x y z CR | CR when the move is done |
//! | velocity | `V` u16 CR | CR (bits 0–14: µm/s; bit 15: 50 microsteps per step) |
//! | interrupt | 0x03 | ends a move; the move's answer is then error 8 (interrupted) |
//!
//! An error is one code byte before the CR: 0 serial over-run, 1 frame error, 2 buffer
//! over-run, 4 bad command, 8 move interrupted (as an ASCII digit or as the raw value; both
//! are read). The controller cannot report its position during a move, so the driver
//! estimates it from the commanded speed until the move's CR arrives.

use crate::device::{Device, DeviceError, DeviceState, EmergencyStop, SerialStop};
use crate::geom::{P3, axpy, dist, sub};
use serialport::SerialPort;
use std::io::{Read, Write};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

const CR: u8 = 0x0d;
const INTERRUPT: u8 = 0x03;

/// How long one read waits: answers come in one burst, so a gap this long after a code
/// and a CR means the answer is complete.
const READ_SLICE: Duration = Duration::from_millis(20);

/// Highest velocity the controller takes in fine (50 microsteps per step) mode, µm/s.
pub const MAX_FINE_SPEED: f64 = 1310.0;

/// What an error code byte means.
pub fn error_text(code: u8) -> &'static str {
    match code {
        b'0' | 0 => "serial over-run",
        b'1' | 1 => "frame error",
        b'2' | 2 => "buffer over-run",
        b'4' | 4 => "bad command",
        b'8' | 8 => "move interrupted",
        _ => "unknown error code",
    }
}

/// An MP-285 on a serial port.
pub struct Mp285 {
    port: Box<dyn SerialPort>,
    name: String,
    steps_per_um: f64,
    speed: Option<u16>,
    /// The move in progress: from, to, start, speed.
    moving: Option<(P3, P3, Instant, f64)>,
    position: P3,
    timeout: Duration,
    /// Whether opening found a move under way (an earlier driver's, e.g. a bridge killed
    /// mid-move) and interrupted it.
    interrupted_on_open: bool,
    /// Interrupts sent by the emergency stop's handle, from another thread.
    estops: Arc<AtomicU64>,
    /// Of those, the ones this driver has accounted for.
    estops_seen: u64,
}

/// How long opening waits for the answer to its interrupt: the controller answers an
/// interrupted move at once and an idle one not at all.
const OPEN_INTERRUPT_WAIT: Duration = Duration::from_millis(150);

impl Mp285 {
    /// Opens the controller on serial port `path` and reads its status and position.
    pub fn open(path: &str, timeout: Duration) -> Result<Self, DeviceError> {
        let port = serialport::new(path, 9600)
            .timeout(READ_SLICE)
            .open()
            .map_err(|e| {
                DeviceError(format!(
                    "cannot open the MP-285 port {path}: {e}; check the cable and the device path"
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
            steps_per_um: 25.0,
            speed: None,
            moving: None,
            position: [0.0; 3],
            timeout,
            interrupted_on_open: false,
            estops: Arc::default(),
            estops_seen: 0,
        };
        let _ = d.port.set_timeout(READ_SLICE);
        d.interrupted_on_open = d.stop_any_move()?;
        let status = d.command(b"s", 32)?;
        let per_um = u16::from_le_bytes([status[24], status[25]]);
        if per_um == 0 {
            return Err(d.err("reports 0 microsteps per µm in its status".into()));
        }
        d.steps_per_um = per_um as f64;
        d.position = d.read_position()?;
        Ok(d)
    }

    /// Whether opening found the controller still moving and stopped it.
    pub fn interrupted_on_open(&self) -> bool {
        self.interrupted_on_open
    }

    /// Interrupts whatever move the controller may be making and waits for the line to
    /// fall quiet, returning whether a move was interrupted. A driver that opens the line
    /// cannot know whether an earlier one (a bridge killed mid-move and restarted) left a
    /// move running: the controller would go on to that move's end, deaf to every command
    /// meanwhile. An idle controller ignores the interrupt.
    fn stop_any_move(&mut self) -> Result<bool, DeviceError> {
        let _ = self.port.clear(serialport::ClearBuffer::All);
        self.write(&[INTERRUPT])?;
        let mut seen = Vec::new();
        let mut quiet_since = Instant::now();
        let deadline = Instant::now() + self.timeout.max(OPEN_INTERRUPT_WAIT);
        let mut b = [0u8; 16];
        while Instant::now() < deadline {
            match self.port.read(&mut b) {
                Ok(0) => {
                    return Err(self.err("the line closed; is it still connected?".into()));
                }
                Ok(k) => {
                    seen.extend_from_slice(&b[..k]);
                    quiet_since = Instant::now();
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::TimedOut | std::io::ErrorKind::Interrupted
                    ) => {}
                Err(e) => {
                    return Err(self.err(format!("cannot read ({e}); is it still connected?")));
                }
            }
            if quiet_since.elapsed() >= OPEN_INTERRUPT_WAIT {
                break;
            }
        }
        let _ = self.port.clear(serialport::ClearBuffer::Input);
        // The interrupted move's answer is error 8 and a CR; a move that ended just before
        // the interrupt answers with its CR alone.
        Ok(seen
            .windows(2)
            .any(|w| matches!(w[0], b'8' | 8) && w[1] == CR))
    }

    /// Microsteps per µm, from the controller's status.
    pub fn steps_per_um(&self) -> f64 {
        self.steps_per_um
    }

    fn err(&self, what: String) -> DeviceError {
        DeviceError(format!("MP-285 on {}: {what}", self.name))
    }

    fn write(&mut self, bytes: &[u8]) -> Result<(), DeviceError> {
        self.port
            .write_all(bytes)
            .and_then(|_| self.port.flush())
            .map_err(|e| self.err(format!("cannot write ({e}); is it still connected?")))
    }

    /// Reads `n` data bytes and the CR, or the error code the controller sends instead.
    fn read_answer(&mut self, n: usize) -> Result<Vec<u8>, DeviceError> {
        let mut buf = vec![0u8; n + 1];
        let mut got = 0;
        let deadline = Instant::now() + self.timeout;
        while got < buf.len() {
            match self.port.read(&mut buf[got..]) {
                Ok(0) => {
                    return Err(self.err("the line closed; is it still connected?".into()));
                }
                Ok(k) => got += k,
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::TimedOut | std::io::ErrorKind::Interrupted
                    ) =>
                {
                    // A code and a CR, then silence, where data was due: an error.
                    if got == 2 && buf[1] == CR && n > 1 {
                        return Err(self.err(format!("error: {}", error_text(buf[0]))));
                    }
                }
                Err(e) => {
                    return Err(self.err(format!("cannot read ({e}); is it still connected?")));
                }
            }
            if got < buf.len() && Instant::now() > deadline {
                return Err(self.err(format!(
                    "no answer within {:.1} s (got {got} of {} bytes); is it on and connected?",
                    self.timeout.as_secs_f64(),
                    n + 1
                )));
            }
        }
        if n == 0 && buf[0] != CR {
            let mut cr = [0u8; 1];
            let _ = self.port.read_exact(&mut cr);
            return Err(self.err(format!("error: {}", error_text(buf[0]))));
        }
        if buf[n] != CR {
            return Err(self.err(format!("answer {buf:02x?} does not end with CR")));
        }
        buf.truncate(n);
        Ok(buf)
    }

    fn command(&mut self, cmd: &[u8], answer: usize) -> Result<Vec<u8>, DeviceError> {
        let mut b = cmd.to_vec();
        b.push(CR);
        self.write(&b)?;
        self.read_answer(answer)
    }

    fn read_position(&mut self) -> Result<P3, DeviceError> {
        let b = self.command(b"c", 12)?;
        let s = |k: usize| i32::from_le_bytes(b[4 * k..4 * k + 4].try_into().expect("4")) as f64;
        Ok([0, 1, 2].map(|k| s(k) / self.steps_per_um))
    }

    /// Microsteps for a position, refusing what an `i32` cannot hold.
    fn steps(&self, p: P3) -> Result<[i32; 3], DeviceError> {
        let mut out = [0i32; 3];
        for k in 0..3 {
            let s = (p[k] * self.steps_per_um).round();
            if !s.is_finite() || s.abs() > i32::MAX as f64 {
                return Err(self.err(format!("position {p:?} µm is beyond its range")));
            }
            out[k] = s as i32;
        }
        Ok(out)
    }

    /// Checks for the answer that ends the move in progress, without waiting.
    fn poll_move(&mut self) -> Result<bool, DeviceError> {
        let waiting = self
            .port
            .bytes_to_read()
            .map_err(|e| self.err(format!("cannot read ({e}); is it still connected?")))?;
        if waiting == 0 {
            return Ok(false);
        }
        let mut b = [0u8; 1];
        self.port
            .read_exact(&mut b)
            .map_err(|e| self.err(format!("cannot read ({e})")))?;
        if b[0] != CR {
            let mut cr = [0u8; 1];
            let _ = self.port.read_exact(&mut cr);
            self.moving = None;
            let ours = self.estops.load(Ordering::SeqCst);
            if matches!(b[0], b'8' | 8) && ours != self.estops_seen {
                // Interrupted by the emergency stop: the move ended where it stood.
                self.estops_seen = ours;
                return Ok(true);
            }
            return Err(self.err(format!("move failed: error {}", error_text(b[0]))));
        }
        Ok(true)
    }
}

impl Device for Mp285 {
    fn describe(&self) -> String {
        format!("MP-285 on {}", self.name)
    }

    fn start_move(&mut self, to: P3, speed: f64) -> Result<(), DeviceError> {
        if self.moving.is_some() {
            return Err(self.err("still moving; stop it before a new move".into()));
        }
        let v = speed.clamp(1.0, MAX_FINE_SPEED).round() as u16;
        if self.speed != Some(v) {
            let [lo, hi] = (v | 0x8000).to_le_bytes();
            self.command(&[b'V', lo, hi], 0)?;
            self.speed = Some(v);
        }
        let s = self.steps(to)?;
        let mut cmd = vec![b'm'];
        for k in s {
            cmd.extend_from_slice(&k.to_le_bytes());
        }
        cmd.push(CR);
        self.write(&cmd)?;
        self.moving = Some((self.position, to, Instant::now(), v as f64));
        Ok(())
    }

    fn state(&mut self) -> Result<DeviceState, DeviceError> {
        if let Some((from, to, t0, v)) = self.moving {
            if !self.poll_move()? {
                let d = dist(from, to);
                let s = (t0.elapsed().as_secs_f64() * v).min(d);
                let est = if d > 0.0 {
                    axpy(from, s / d, sub(to, from))
                } else {
                    to
                };
                return Ok(DeviceState {
                    position: est,
                    moving: true,
                });
            }
            self.moving = None;
            self.position = self.read_position()?;
        }
        Ok(DeviceState {
            position: self.position,
            moving: false,
        })
    }

    fn stop(&mut self) -> Result<(), DeviceError> {
        if self.moving.is_none() {
            return Ok(());
        }
        self.write(&[INTERRUPT])?;
        // The move ends with its CR (it was done) or with error 8 (interrupted).
        let mut b = [0u8; 1];
        let deadline = Instant::now() + self.timeout;
        loop {
            match self.port.read(&mut b) {
                Ok(1) if b[0] == CR => break,
                Ok(1) => {}
                Ok(_) => {}
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::TimedOut | std::io::ErrorKind::Interrupted
                    ) => {}
                Err(e) => return Err(self.err(format!("cannot read ({e})"))),
            }
            if Instant::now() > deadline {
                return Err(self.err("did not confirm the interrupt; is it connected?".into()));
            }
        }
        self.moving = None;
        self.estops_seen = self.estops.load(Ordering::SeqCst);
        self.position = self.read_position()?;
        Ok(())
    }

    fn emergency_stop(&mut self) -> Result<Arc<dyn EmergencyStop>, DeviceError> {
        // The controller takes an interrupt at any moment; an idle one ignores it.
        SerialStop::on(&*self.port, &self.estops, self.describe(), &[INTERRUPT])
    }
}

/// An MP-285 emulated on the master side of a pseudo-terminal, for tests and dry runs.
pub mod emulator {
    use super::{CR, INTERRUPT};
    use std::io::{Read, Write};
    use std::sync::{Arc, Mutex};
    use std::time::{Duration, Instant};

    /// What the emulated controller holds.
    #[derive(Clone, Debug, Default)]
    pub struct EmulatorState {
        /// Position, microsteps.
        pub steps: [i32; 3],
        /// Velocity word last set (µm/s | fine bit).
        pub velocity: u16,
        /// Every command byte received, in order.
        pub commands: Vec<u8>,
        /// Moves completed.
        pub moves: u32,
        /// Moves interrupted.
        pub interrupted: u32,
        /// Set to make it stop answering (a controller switched off).
        pub mute: bool,
        /// Set to make it close its end of the line (a cable pulled).
        pub hang_up: bool,
    }

    /// Microsteps per µm the emulator reports (the MP-285's usual 25: 0.04 µm a step).
    pub const STEPS_PER_UM: u16 = 25;

    fn status() -> [u8; 32] {
        let mut s = [0u8; 32];
        s[24..26].copy_from_slice(&STEPS_PER_UM.to_le_bytes());
        s[28..30].copy_from_slice(&(200u16).to_le_bytes());
        s[30..32].copy_from_slice(&(313u16).to_le_bytes());
        s
    }

    /// Runs the emulator on `port` (the master side of a pty) in a thread until the line
    /// closes; `state` shows what it did.
    pub fn spawn(mut port: Box<dyn serialport::SerialPort>) -> Arc<Mutex<EmulatorState>> {
        let state = Arc::new(Mutex::new(EmulatorState {
            velocity: 200,
            ..Default::default()
        }));
        let st = state.clone();
        let _ = port.set_timeout(Duration::from_millis(5));
        std::thread::spawn(move || {
            let mut buf: Vec<u8> = Vec::new();
            let mut byte = [0u8; 64];
            // A move in progress: from, to (microsteps), start, duration.
            let mut moving: Option<([i32; 3], [i32; 3], Instant, f64)> = None;
            loop {
                {
                    let s = st.lock().expect("state");
                    if s.hang_up {
                        return;
                    }
                    if s.mute {
                        drop(s);
                        let _ = port.read(&mut byte);
                        continue;
                    }
                }
                match port.read(&mut byte) {
                    Ok(0) => return,
                    Ok(k) => buf.extend_from_slice(&byte[..k]),
                    Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                    Err(_) => return,
                }
                if let Some((from, to, t0, dur)) = moving {
                    let frac = (t0.elapsed().as_secs_f64() / dur).min(1.0);
                    let at = |f: f64| {
                        [0, 1, 2].map(|k| from[k] + ((to[k] - from[k]) as f64 * f).round() as i32)
                    };
                    if let Some(i) = buf.iter().position(|&b| b == INTERRUPT) {
                        buf.drain(..=i);
                        let mut s = st.lock().expect("state");
                        s.steps = at(frac);
                        s.interrupted += 1;
                        s.commands.push(INTERRUPT);
                        moving = None;
                        if port.write_all(&[b'8', CR]).is_err() {
                            return;
                        }
                        continue;
                    }
                    if frac >= 1.0 {
                        let mut s = st.lock().expect("state");
                        s.steps = to;
                        s.moves += 1;
                        moving = None;
                        if port.write_all(&[CR]).is_err() {
                            return;
                        }
                    }
                    // The controller does not read other commands during a move.
                    continue;
                }
                while let Some(&cmd) = buf.first() {
                    let need = match cmd {
                        b'm' => 14,
                        b'V' => 4,
                        INTERRUPT => 1,
                        _ => 2,
                    };
                    if buf.len() < need {
                        break;
                    }
                    let c: Vec<u8> = buf.drain(..need).collect();
                    let mut s = st.lock().expect("state");
                    s.commands.push(cmd);
                    let ok_cr = c[need - 1] == CR || cmd == INTERRUPT;
                    let reply: Vec<u8> = match (cmd, ok_cr) {
                        (_, false) => {
                            // Resynchronise at the next CR.
                            if let Some(i) = buf.iter().position(|&b| b == CR) {
                                buf.drain(..=i);
                            }
                            vec![b'4', CR]
                        }
                        (b's', _) => {
                            let mut r = status().to_vec();
                            r[28..30].copy_from_slice(&s.velocity.to_le_bytes());
                            r.push(CR);
                            r
                        }
                        (b'c', _) => {
                            let mut r: Vec<u8> =
                                s.steps.iter().flat_map(|v| v.to_le_bytes()).collect();
                            r.push(CR);
                            r
                        }
                        (b'V', _) => {
                            s.velocity = u16::from_le_bytes([c[1], c[2]]);
                            vec![CR]
                        }
                        (b'm', _) => {
                            let to = [0, 1, 2].map(|k| {
                                i32::from_le_bytes(c[1 + 4 * k..5 + 4 * k].try_into().expect("4"))
                            });
                            let d_um = (0..3)
                                .map(|k| ((to[k] - s.steps[k]) as f64).powi(2))
                                .sum::<f64>()
                                .sqrt()
                                / STEPS_PER_UM as f64;
                            let v = (s.velocity & 0x7fff).max(1) as f64;
                            moving = Some((s.steps, to, Instant::now(), (d_um / v).max(1e-3)));
                            vec![]
                        }
                        (b'o', _) => {
                            s.steps = [0; 3];
                            vec![CR]
                        }
                        (b'n', _) => vec![CR],
                        (INTERRUPT, _) => vec![],
                        _ => vec![b'4', CR],
                    };
                    drop(s);
                    if !reply.is_empty() && port.write_all(&reply).is_err() {
                        return;
                    }
                    if moving.is_some() {
                        break;
                    }
                }
            }
        });
        state
    }
}
