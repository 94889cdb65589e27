//! The signals that end a run (SIGINT, SIGTERM, SIGHUP, SIGQUIT), taken the same way by the
//! supervisor and by every node: a handler that only raises a flag, installed before the
//! process makes anything that must be cleaned up.
//!
//! iceoryx2 installs a handler of its own for SIGINT, SIGTERM and SIGQUIT the first time
//! anything asks for it (a node's first wait), and reads *and clears* the signal it saw at
//! several places (creating shared memory among them). A stop told only to iceoryx2 can
//! therefore be lost, and a process killed by a signal's default action while it creates
//! an edge leaves the edge half made for every later run ("hangs in creation"). So
//! [`install`] lets iceoryx2 install its handler first and then puts one in front of it
//! that keeps the stop for good and hands the signal on: iceoryx2's waits still wake up.

use std::sync::atomic::{AtomicBool, AtomicI32, AtomicUsize, Ordering};

/// The signals that ask a run or a node to stop.
pub const STOP_SIGNALS: [i32; 4] = [libc::SIGINT, libc::SIGTERM, libc::SIGHUP, libc::SIGQUIT];

static STOP: AtomicBool = AtomicBool::new(false);
/// The first stop signal that came (0: none yet).
static FIRST: AtomicI32 = AtomicI32::new(0);
/// How many stop signals came.
static COUNT: AtomicUsize = AtomicUsize::new(0);
/// The handler each signal had before ours (iceoryx2's), to hand it on; 0: none.
static PREVIOUS: [AtomicUsize; 4] = [const { AtomicUsize::new(0) }; 4];

extern "C" fn on_signal(sig: libc::c_int) {
    // Only atomics here: a signal handler may interrupt anything.
    STOP.store(true, Ordering::SeqCst);
    let _ = FIRST.compare_exchange(0, sig, Ordering::SeqCst, Ordering::SeqCst);
    COUNT.fetch_add(1, Ordering::SeqCst);
    if let Some(k) = STOP_SIGNALS.iter().position(|&s| s == sig) {
        let prev = PREVIOUS[k].load(Ordering::SeqCst);
        if prev != 0 {
            // SAFETY: `prev` is a plain one-argument handler that was installed for this
            // signal (checked in `install`: neither SIG_DFL, SIG_IGN nor an SA_SIGINFO one),
            // and handlers stay valid for the life of the process.
            let f: extern "C" fn(libc::c_int) = unsafe { std::mem::transmute(prev) };
            f(sig);
        }
    }
}

/// Takes the stop signals for this process from now on (idempotent). Call it first thing in
/// `main` of a supervisor or a node, before any shared memory, lock or file is made.
pub fn install() {
    static DONE: std::sync::Once = std::sync::Once::new();
    DONE.call_once(|| {
        // iceoryx2's handler first (it installs it once per process, on first use), so
        // that ours stays in front of it.
        let _ = iceoryx2_bb_posix::signal::SignalHandler::last_signal();
        for (k, &sig) in STOP_SIGNALS.iter().enumerate() {
            // SAFETY: sigaction with a zeroed, then filled, sigaction struct; the handler
            // is async-signal-safe (atomics only, and the previous handler, which was
            // installed to run in a handler).
            unsafe {
                let mut action: libc::sigaction = std::mem::zeroed();
                let mut old: libc::sigaction = std::mem::zeroed();
                action.sa_sigaction = on_signal as extern "C" fn(libc::c_int) as usize;
                // Interrupted system calls fail with EINTR, so that waits notice the stop.
                action.sa_flags = 0;
                libc::sigemptyset(&mut action.sa_mask);
                if libc::sigaction(sig, &action, &mut old) == 0
                    && old.sa_sigaction != libc::SIG_DFL
                    && old.sa_sigaction != libc::SIG_IGN
                    && old.sa_flags & libc::SA_SIGINFO == 0
                {
                    PREVIOUS[k].store(old.sa_sigaction, Ordering::SeqCst);
                }
            }
        }
    });
}

/// Whether this process was asked to stop (by a signal, or by [`request_stop`]).
pub fn stop_requested() -> bool {
    STOP.load(Ordering::SeqCst)
}

/// Records a stop that came another way (iceoryx2 reported a termination request).
pub fn request_stop() {
    STOP.store(true, Ordering::SeqCst);
}

/// The first stop signal that came, if any.
pub fn first_signal() -> Option<i32> {
    match FIRST.load(Ordering::SeqCst) {
        0 => None,
        s => Some(s),
    }
}

/// How many stop signals came so far (a second Ctrl-C means: stop now).
pub fn signal_count() -> usize {
    COUNT.load(Ordering::SeqCst)
}

/// Sleeps for `d`, in short slices so that a stop is noticed; false when the process was
/// asked to stop (at once, or during the sleep).
pub fn sleep(d: std::time::Duration) -> bool {
    const SLICE: std::time::Duration = std::time::Duration::from_millis(20);
    let start = std::time::Instant::now();
    loop {
        if stop_requested() {
            return false;
        }
        let left = d.saturating_sub(start.elapsed());
        if left.is_zero() {
            return true;
        }
        std::thread::sleep(left.min(SLICE));
    }
}

/// A signal's usual name (`SIGINT`), for messages.
pub fn name(sig: i32) -> &'static str {
    match sig {
        libc::SIGINT => "SIGINT",
        libc::SIGTERM => "SIGTERM",
        libc::SIGHUP => "SIGHUP",
        libc::SIGQUIT => "SIGQUIT",
        _ => "a signal",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stop_signal_is_kept_and_handed_on_to_iceoryx2() {
        // The flag is the process's: the test runs in a process of its own.
        const CHILD: &str = "MICROSTEREO_SIGNALS_TEST_CHILD";
        if std::env::var_os(CHILD).is_none() {
            let out = std::process::Command::new(std::env::current_exe().unwrap())
                .args([
                    "--exact",
                    "signals::tests::a_stop_signal_is_kept_and_handed_on_to_iceoryx2",
                    "--test-threads=1",
                ])
                .env(CHILD, "1")
                .output()
                .unwrap();
            assert!(
                out.status.success() && String::from_utf8_lossy(&out.stdout).contains("1 passed"),
                "{}{}",
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            );
            return;
        }
        install();
        install();
        assert!(!stop_requested());
        // SAFETY: raise(3) on this process, whose handler for SIGHUP is ours.
        unsafe {
            libc::raise(libc::SIGHUP);
        }
        assert!(stop_requested());
        assert_eq!(first_signal(), Some(libc::SIGHUP));
        // SIGTERM reaches iceoryx2's handler behind ours: its termination request is seen.
        // SAFETY: as above, for SIGTERM.
        unsafe {
            libc::raise(libc::SIGTERM);
        }
        assert!(iceoryx2_bb_posix::signal::SignalHandler::termination_requested());
        assert_eq!(first_signal(), Some(libc::SIGHUP));
        assert_eq!(signal_count(), 2);
    }
}
