//! The MP-285 driver against the emulator on a pseudo-terminal: the driver opens the pty's
//! device path as it would a USB serial adapter.

use manipulator_bridge::device::Device;
use manipulator_bridge::mp285::{Mp285, emulator};
use serialport::{SerialPort, TTYPort};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// An emulator on a new pty and a driver on its other end.
fn connect() -> (Mp285, Arc<Mutex<emulator::EmulatorState>>, TTYPort) {
    let (master, slave) = TTYPort::pair().expect("a pseudo-terminal");
    let path = slave.name().expect("the pty has a path");
    let state = emulator::spawn(Box::new(master));
    let d = Mp285::open(&path, Duration::from_millis(500)).expect("driver connects");
    // The slave end stays open so that the line does not hang up between opens.
    (d, state, slave)
}

fn wait_idle(d: &mut Mp285) -> [f64; 3] {
    let t0 = Instant::now();
    loop {
        let s = d.state().expect("state");
        if !s.moving {
            return s.position;
        }
        assert!(t0.elapsed() < Duration::from_secs(10), "move did not end");
        std::thread::sleep(Duration::from_millis(5));
    }
}

#[test]
fn moves_and_position_readback_are_exact_in_microsteps() {
    let (mut d, state, _slave) = connect();
    assert_eq!(d.steps_per_um(), 25.0);
    assert_eq!(d.state().unwrap().position, [0.0; 3]);
    d.start_move([100.04, -20.0, 5.52], 800.0).unwrap();
    assert!(d.state().unwrap().moving);
    let p = wait_idle(&mut d);
    // 0.04 µm per microstep: 2501, −500 and 138 microsteps.
    assert_eq!(p, [2501.0 / 25.0, -20.0, 138.0 / 25.0]);
    {
        let s = state.lock().unwrap();
        assert_eq!(s.steps, [2501, -500, 138]);
        assert_eq!(s.velocity, 800 | 0x8000, "fine resolution, 800 µm/s");
        assert_eq!(s.moves, 1);
    }
    // Positions between microsteps round to the nearest: 1.02 µm is 25.5 → 26 steps.
    d.start_move([1.02, -0.01, 0.0], 800.0).unwrap();
    assert_eq!(wait_idle(&mut d), [26.0 / 25.0, 0.0, 0.0]);
    assert_eq!(state.lock().unwrap().steps, [26, 0, 0]);
    // The velocity is set once while it does not change.
    let vs = state
        .lock()
        .unwrap()
        .commands
        .iter()
        .filter(|&&c| c == b'V')
        .count();
    assert_eq!(vs, 1);
}

#[test]
fn an_interrupt_stops_a_move_where_it_is() {
    let (mut d, state, _slave) = connect();
    d.start_move([50.0, 0.0, 0.0], 20.0).unwrap();
    std::thread::sleep(Duration::from_millis(300));
    // Underway at 20 µm/s: the estimate moves on while the controller cannot be read.
    let est = d.state().unwrap();
    assert!(
        est.moving && est.position[0] > 2.0 && est.position[0] < 10.0,
        "{est:?}"
    );
    d.stop().unwrap();
    let p = d.state().unwrap();
    assert!(!p.moving);
    let s = state.lock().unwrap().clone();
    assert_eq!(s.interrupted, 1);
    assert_eq!(p.position[0], s.steps[0] as f64 / 25.0);
    assert!(
        p.position[0] > 4.0 && p.position[0] < 20.0,
        "{:?}",
        p.position
    );
    // It takes commands again.
    d.start_move([0.0, 0.0, 0.0], 1000.0).unwrap();
    assert_eq!(wait_idle(&mut d), [0.0; 3]);
}

/// A bridge killed mid-move leaves the controller moving, deaf to commands until the
/// move's end: the next driver to open the line stops it first, and knows where it is.
#[test]
fn opening_stops_a_move_an_earlier_driver_left_running() {
    let (master, slave) = TTYPort::pair().expect("a pseudo-terminal");
    let path = slave.name().expect("the pty has a path");
    let state = emulator::spawn(Box::new(master));
    let mut first = Mp285::open(&path, Duration::from_millis(500)).expect("driver connects");
    assert!(
        !first.interrupted_on_open(),
        "an idle controller has nothing to stop"
    );
    // 100 µm at 20 µm/s: five seconds, far longer than the test waits.
    first.start_move([100.0, 0.0, 0.0], 20.0).unwrap();
    std::thread::sleep(Duration::from_millis(300));
    drop(first);
    let t0 = Instant::now();
    let mut second = Mp285::open(&path, Duration::from_millis(500)).expect("driver connects");
    let opened_in = t0.elapsed();
    assert!(second.interrupted_on_open());
    assert!(
        opened_in < Duration::from_secs(2),
        "opening waited {opened_in:?} (for the move's end?)"
    );
    let s = state.lock().unwrap().clone();
    assert_eq!(s.interrupted, 1);
    assert_eq!(s.moves, 0, "the move never reached its end");
    let p = second.state().unwrap();
    assert!(!p.moving);
    assert_eq!(p.position[0], s.steps[0] as f64 / 25.0);
    assert!(
        p.position[0] > 3.0 && p.position[0] < 50.0,
        "stopped at {:?}",
        p.position
    );
    // Still stopped a while later: nothing carried the old move on.
    std::thread::sleep(Duration::from_millis(300));
    assert_eq!(state.lock().unwrap().steps, s.steps);
    // And it takes commands at once.
    second.start_move([0.0, 0.0, 0.0], 1000.0).unwrap();
    assert_eq!(wait_idle(&mut second), [0.0; 3]);
    drop(slave);
}

#[test]
fn a_missing_a_silent_and_a_vanished_device_are_clear_errors() {
    let e = Mp285::open("/dev/does-not-exist-mp285", Duration::from_millis(200))
        .err()
        .unwrap();
    assert!(
        e.0.contains("cannot open the MP-285 port /dev/does-not-exist-mp285"),
        "{e}"
    );

    let (mut d, state, _slave) = connect();
    state.lock().unwrap().mute = true;
    // Past the emulator's current read, so that it sees the flag first.
    std::thread::sleep(Duration::from_millis(50));
    // The first move sets the velocity, which needs an answer.
    let e = d
        .start_move([1.0, 0.0, 0.0], 100.0)
        .expect_err("no answer is an error");
    assert!(
        e.0.contains("MP-285 on /dev/pts/") && e.0.contains("no answer within 0.5 s"),
        "{e}"
    );

    let (mut d, state, slave) = connect();
    state.lock().unwrap().hang_up = true;
    std::thread::sleep(Duration::from_millis(50));
    drop(slave);
    let r = d.start_move([1.0, 0.0, 0.0], 100.0).and_then(|_| {
        std::thread::sleep(Duration::from_millis(100));
        d.state().map(|_| ())
    });
    let r = r.and_then(|_| d.stop());
    let e = r.expect_err("a vanished device is an error");
    assert!(e.0.starts_with("MP-285 on /dev/pts/"), "{e}");
}

#[test]
fn an_error_code_from_the_controller_is_reported() {
    // A controller that answers every command with error 4 (bad command).
    let (mut master, slave) = TTYPort::pair().unwrap();
    let path = slave.name().unwrap();
    master.set_timeout(Duration::from_millis(20)).unwrap();
    std::thread::spawn(move || {
        let mut b = [0u8; 64];
        loop {
            match master.read(&mut b) {
                Ok(0) => return,
                Ok(_) => {
                    if master.write_all(b"4\r").is_err() {
                        return;
                    }
                }
                Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                Err(_) => return,
            }
        }
    });
    let e = Mp285::open(&path, Duration::from_millis(300))
        .err()
        .unwrap();
    assert!(e.0.contains("error: bad command"), "{e}");
    drop(slave);
}

use std::io::{Read, Write};

/// The emergency stop's handle interrupts a move from another thread while the driver
/// keeps polling, without waiting for the driver; the driver takes the interrupted move's
/// answer as the move's end, not as a fault, and an interrupt to an idle controller
/// changes nothing.
#[test]
fn the_emergency_handle_stops_a_move_from_another_thread() {
    let (mut d, state, _slave) = connect();
    let estop = d.emergency_stop().unwrap();
    d.start_move([50.0, 0.0, 0.0], 20.0).unwrap();
    let handle = estop.clone();
    let stopper = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(300));
        handle.stop_now().unwrap();
    });
    let p = wait_idle(&mut d);
    stopper.join().unwrap();
    let s = state.lock().unwrap().clone();
    assert_eq!((s.interrupted, s.moves), (1, 0));
    assert_eq!(p[0], s.steps[0] as f64 / 25.0);
    assert!(p[0] > 3.0 && p[0] < 12.0, "{p:?}");
    // Idle: ignored; the driver goes on exactly.
    estop.stop_now().unwrap();
    d.start_move([1.0, 2.0, 3.0], 800.0).unwrap();
    assert_eq!(wait_idle(&mut d), [1.0, 2.0, 3.0]);
    assert_eq!(state.lock().unwrap().moves, 1);
}
