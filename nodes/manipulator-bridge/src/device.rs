//! Manipulators the bridge can drive: the [`Device`] trait and the simulated 3-axis
//! manipulator [`SimDevice`].

use crate::geom::{P3, axpy, dist, sub};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Instant;

/// Why a device command failed.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DeviceError(pub String);

impl std::fmt::Display for DeviceError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for DeviceError {}

/// Where a device is and whether it is moving.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DeviceState {
    /// Tip position in the device's frame, µm (an estimate while a device that cannot be
    /// read during a move is moving).
    pub position: P3,
    /// Whether a move is in progress.
    pub moving: bool,
}

/// A 3-axis manipulator that moves the tip in straight lines.
pub trait Device: Send {
    /// What it is, for messages (`sim`, `MP-285 on /dev/ttyUSB0`).
    fn describe(&self) -> String;
    /// Starts a straight move to `to` at up to `speed` µm/s; returns at once.
    fn start_move(&mut self, to: P3, speed: f64) -> Result<(), DeviceError>;
    /// Reads where it is.
    fn state(&mut self) -> Result<DeviceState, DeviceError>;
    /// Stops any move as fast as the device can.
    fn stop(&mut self) -> Result<(), DeviceError>;
    /// A handle that stops the device from any thread, at once, even while another thread
    /// is in the middle of a command of this device: the emergency stop's own path, which
    /// must never wait for a read in progress.
    fn emergency_stop(&mut self) -> Result<Arc<dyn EmergencyStop>, DeviceError>;
}

/// Stops a device from any thread without waiting for anything else the device is doing.
pub trait EmergencyStop: Send + Sync {
    /// Tells the device to stop now; returns once the order has gone out. It reads no
    /// answer: the thread that owns the device settles its state afterwards.
    fn stop_now(&self) -> Result<(), DeviceError>;
}

/// The emergency stop of a manipulator on a serial line: its stop command written on a
/// second handle of the line. The kernel writes each `write` to a tty whole, so it never
/// splits a command of the driver's; the driver counts the stops `sent` to tell their
/// answers from its own.
pub(crate) struct SerialStop {
    pub(crate) port: Mutex<Box<dyn serialport::SerialPort>>,
    pub(crate) sent: Arc<std::sync::atomic::AtomicU64>,
    /// The device, for messages.
    pub(crate) name: String,
    pub(crate) command: &'static [u8],
}

impl SerialStop {
    /// The handle that sends `command` to the device on `port` (named `name`), counting in
    /// `sent`.
    pub(crate) fn on(
        port: &dyn serialport::SerialPort,
        sent: &Arc<std::sync::atomic::AtomicU64>,
        name: String,
        command: &'static [u8],
    ) -> Result<Arc<dyn EmergencyStop>, DeviceError> {
        let port = port.try_clone().map_err(|e| {
            DeviceError(format!(
                "{name}: cannot open a second handle on the line ({e})"
            ))
        })?;
        Ok(Arc::new(Self {
            port: Mutex::new(port),
            sent: sent.clone(),
            name,
            command,
        }))
    }
}

impl EmergencyStop for SerialStop {
    fn stop_now(&self) -> Result<(), DeviceError> {
        use std::io::Write;
        // Counted before it goes out: the driver then knows an answer it reads is ours.
        self.sent.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        let mut port = self.port.lock().unwrap_or_else(PoisonError::into_inner);
        port.write_all(self.command)
            .and_then(|_| port.flush())
            .map_err(|e| {
                DeviceError(format!(
                    "{}: cannot send the stop ({e}); is it still connected?",
                    self.name
                ))
            })
    }
}

/// Seconds on some clock: the wall clock for a live sim, a hand-set one in tests.
pub type Clock = Arc<dyn Fn() -> f64 + Send + Sync>;

/// The wall clock, from now.
pub fn wall_clock() -> Clock {
    let t0 = Instant::now();
    Arc::new(move || t0.elapsed().as_secs_f64())
}

/// A clock that moves only when told, for tests: the clock and its setter.
pub fn manual_clock() -> (Clock, Arc<Mutex<f64>>) {
    let t = Arc::new(Mutex::new(0.0));
    let r = t.clone();
    (Arc::new(move || *r.lock().expect("clock")), t)
}

/// A straight move: constant-acceleration phases `(duration, acceleration)` from speed
/// `v0` along `dir`.
#[derive(Clone, Debug)]
struct Move {
    from: P3,
    /// Where it ends (exactly, against rounding in the phases).
    to: P3,
    dir: P3,
    start: f64,
    v0: f64,
    phases: Vec<(f64, f64)>,
}

impl Move {
    /// Distance travelled and speed `t` seconds after the start.
    fn at(&self, t: f64) -> (f64, f64) {
        let (mut s, mut v, mut left) = (0.0, self.v0, t.max(0.0));
        for &(d, a) in &self.phases {
            let dt = left.min(d);
            s += v * dt + 0.5 * a * dt * dt;
            v += a * dt;
            left -= dt;
            if left <= 0.0 {
                break;
            }
        }
        (s, v.max(0.0))
    }

    fn duration(&self) -> f64 {
        self.phases.iter().map(|p| p.0).sum()
    }
}

/// The simulated manipulator: straight moves with a trapezoidal speed profile (speed and
/// acceleration limits), exact position readback. Clones drive the same manipulator.
#[derive(Clone)]
pub struct SimDevice {
    inner: Arc<Mutex<Sim>>,
}

struct Sim {
    clock: Clock,
    position: P3,
    max_speed: f64,
    max_accel: f64,
    current: Option<Move>,
}

impl Sim {
    /// Settles a finished move and gives the position and speed now.
    fn now(&mut self) -> (P3, f64) {
        let t = (self.clock)();
        if let Some(m) = &self.current {
            let el = t - m.start;
            let (s, v) = m.at(el);
            let p = axpy(m.from, s, m.dir);
            if el >= m.duration() {
                let p = m.to;
                self.position = p;
                self.current = None;
                return (p, 0.0);
            }
            return (p, v);
        }
        (self.position, 0.0)
    }

    /// Brakes at full deceleration from the speed it has.
    fn brake(&mut self) {
        let (p, v) = self.now();
        if let Some(m) = &self.current {
            let dir = m.dir;
            self.position = p;
            let brake = v * v / (2.0 * self.max_accel);
            self.current = (v > 1e-9).then(|| Move {
                from: p,
                to: axpy(p, brake, dir),
                dir,
                start: (self.clock)(),
                v0: v,
                phases: vec![(v / self.max_accel, -self.max_accel)],
            });
        }
    }
}

impl SimDevice {
    /// A sim at `home` with these limits (µm/s, µm/s²).
    pub fn new(home: P3, max_speed: f64, max_accel: f64, clock: Clock) -> Self {
        Self {
            inner: Arc::new(Mutex::new(Sim {
                clock,
                position: home,
                max_speed,
                max_accel,
                current: None,
            })),
        }
    }

    fn sim(&self) -> std::sync::MutexGuard<'_, Sim> {
        // The sim's state is whole after every statement: a panic elsewhere leaves it usable.
        self.inner.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

impl Device for SimDevice {
    fn describe(&self) -> String {
        "sim".into()
    }

    fn start_move(&mut self, to: P3, speed: f64) -> Result<(), DeviceError> {
        let mut sim = self.sim();
        let (from, v0) = sim.now();
        if v0 > 1e-9 {
            return Err(DeviceError(
                "the sim is still moving; stop it before a new move".into(),
            ));
        }
        let d = dist(from, to);
        sim.position = from;
        if d < 1e-12 {
            sim.current = None;
            return Ok(());
        }
        let (v, a) = (speed.min(sim.max_speed), sim.max_accel);
        let dir = sub(to, from).map(|c| c / d);
        let phases = if d >= v * v / a {
            let ta = v / a;
            vec![(ta, a), ((d - v * v / a) / v, 0.0), (ta, -a)]
        } else {
            let ta = (d / a).sqrt();
            vec![(ta, a), (ta, -a)]
        };
        let start = (sim.clock)();
        sim.current = Some(Move {
            from,
            to,
            dir,
            start,
            v0: 0.0,
            phases,
        });
        Ok(())
    }

    fn state(&mut self) -> Result<DeviceState, DeviceError> {
        let mut sim = self.sim();
        let (p, _) = sim.now();
        Ok(DeviceState {
            position: p,
            moving: sim.current.is_some(),
        })
    }

    fn stop(&mut self) -> Result<(), DeviceError> {
        self.sim().brake();
        Ok(())
    }

    fn emergency_stop(&mut self) -> Result<Arc<dyn EmergencyStop>, DeviceError> {
        Ok(Arc::new(self.clone()))
    }
}

impl EmergencyStop for SimDevice {
    fn stop_now(&self) -> Result<(), DeviceError> {
        // The sim's lock is held only for arithmetic, never across a wait.
        self.sim().brake();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_move_follows_the_trapezoid_and_ends_exactly() {
        let (clock, t) = manual_clock();
        let mut s = SimDevice::new([0.0, 0.0, 0.0], 100.0, 1000.0, clock);
        s.start_move([300.0, 400.0, 0.0], 500.0).unwrap();
        // 0.1 s to reach 100 µm/s (5 µm), 4.9 s of cruise, 0.1 s to stop: 5.1 s for 500 µm.
        *t.lock().unwrap() = 0.1;
        let p = s.state().unwrap();
        assert!(p.moving && (dist(p.position, [0.0; 3]) - 5.0).abs() < 1e-9);
        *t.lock().unwrap() = 2.6;
        assert!((dist(s.state().unwrap().position, [0.0; 3]) - 255.0).abs() < 1e-9);
        *t.lock().unwrap() = 5.1;
        let p = s.state().unwrap();
        assert!(!p.moving);
        assert!(dist(p.position, [300.0, 400.0, 0.0]) < 1e-9);
        // A short move never reaches full speed: 4 µm at 1000 µm/s² takes 2·√0.004 s.
        s.start_move([300.0, 404.0, 0.0], 100.0).unwrap();
        *t.lock().unwrap() = 5.1 + 2.0 * 0.004f64.sqrt() - 1e-6;
        assert!(s.state().unwrap().moving);
        *t.lock().unwrap() = 5.1 + 2.0 * 0.004f64.sqrt();
        assert_eq!(s.state().unwrap().position, [300.0, 404.0, 0.0]);
    }

    #[test]
    fn stop_brakes_at_full_deceleration() {
        let (clock, t) = manual_clock();
        let mut s = SimDevice::new([0.0, 0.0, 0.0], 100.0, 1000.0, clock);
        s.start_move([1000.0, 0.0, 0.0], 100.0).unwrap();
        *t.lock().unwrap() = 1.0;
        // At 95 µm, at 100 µm/s: brakes over 5 µm in 0.1 s.
        s.stop().unwrap();
        assert!(s.start_move([0.0; 3], 10.0).is_err());
        *t.lock().unwrap() = 1.1;
        let p = s.state().unwrap();
        assert!(!p.moving);
        assert!((p.position[0] - 100.0).abs() < 1e-9, "{:?}", p.position);
    }
}
