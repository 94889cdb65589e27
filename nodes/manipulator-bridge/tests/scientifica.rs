//! The Scientifica driver against the emulator on a pseudo-terminal, as the MP-285's.

use manipulator_bridge::device::Device;
use manipulator_bridge::scientifica::{Scientifica, emulator};
use serialport::{SerialPort, TTYPort};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

fn connect() -> (Scientifica, Arc<Mutex<emulator::EmulatorState>>, TTYPort) {
    let (master, slave) = TTYPort::pair().expect("a pseudo-terminal");
    let path = slave.name().expect("the pty has a path");
    let state = emulator::spawn(Box::new(master));
    let d = Scientifica::open(&path, Duration::from_millis(500)).expect("driver connects");
    (d, state, slave)
}

fn wait_idle(d: &mut Scientifica) -> [f64; 3] {
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
fn moves_read_back_to_the_tick_and_the_speed_is_set_once() {
    let (mut d, state, _slave) = connect();
    assert!(d.describe().contains("PatchStar"), "{}", d.describe());
    assert_eq!(d.ticks_per_um(), 100.0);
    assert_eq!(d.state().unwrap().position, [0.0; 3]);
    d.start_move([100.004, -20.0, 5.526], 800.0).unwrap();
    assert!(d.state().unwrap().moving);
    // 0.01 µm a tick: 10000, −2000 and 553 ticks.
    assert_eq!(wait_idle(&mut d), [100.0, -20.0, 5.53]);
    let s = state.lock().unwrap().clone();
    assert_eq!(s.ticks, [10000, -2000, 553]);
    assert_eq!((s.top, s.moves), (800.0, 1));
    d.start_move([0.0, 0.0, 0.0], 800.0).unwrap();
    assert_eq!(wait_idle(&mut d), [0.0; 3]);
    let tops = state
        .lock()
        .unwrap()
        .commands
        .iter()
        .filter(|c| c.starts_with("TOP"))
        .count();
    assert_eq!(tops, 1);
}

#[test]
fn a_stop_ends_a_move_where_it_is_and_the_position_is_read_during_it() {
    let (mut d, state, _slave) = connect();
    d.start_move([50.0, 0.0, 0.0], 20.0).unwrap();
    std::thread::sleep(Duration::from_millis(300));
    // The controller answers while it moves: the position is read, not estimated.
    let during = d.state().unwrap();
    assert!(
        during.moving && during.position[0] > 2.0 && during.position[0] < 20.0,
        "{during:?}"
    );
    d.stop().unwrap();
    let p = d.state().unwrap();
    assert!(
        !p.moving && p.position[0] >= during.position[0] && p.position[0] < 30.0,
        "{p:?}"
    );
    assert_eq!(state.lock().unwrap().stopped, 1);
    d.start_move([1.0, 2.0, 3.0], 1000.0).unwrap();
    assert_eq!(wait_idle(&mut d), [1.0, 2.0, 3.0]);
}

#[test]
fn a_silent_or_missing_controller_is_one_clear_error() {
    let (mut d, state, _slave) = connect();
    state.lock().unwrap().mute = true;
    let e = d.state().unwrap_err().0;
    assert!(e.contains("no answer") && e.contains("Scientifica"), "{e}");
    let e = Scientifica::open("/dev/does-not-exist", Duration::from_millis(100))
        .err()
        .unwrap()
        .0;
    assert!(
        e.contains("cannot open the Scientifica port /dev/does-not-exist"),
        "{e}"
    );
}

/// The emergency stop's handle sends `STOP` from another thread while the driver keeps
/// polling; the driver skips its answer among its own, and goes on exactly.
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
    assert_eq!((s.stopped, s.moves), (1, 0));
    assert_eq!(p[0], s.ticks[0] as f64 / 100.0);
    assert!(p[0] > 3.0 && p[0] < 12.0, "{p:?}");
    // Stopped again while still: the answers stay in step.
    estop.stop_now().unwrap();
    d.start_move([1.0, 2.0, 3.0], 800.0).unwrap();
    assert_eq!(wait_idle(&mut d), [1.0, 2.0, 3.0]);
    assert_eq!(d.state().unwrap().position, [1.0, 2.0, 3.0]);
}
