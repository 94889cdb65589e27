//! Every way a run ends cleans up: a stop signal at any moment (start-up included), a
//! failed start, a full or broken stderr, a killed node. Each run here has an iceoryx2
//! domain of its own (named through `MICROSTEREO_DOMAIN`, as a user would), so that what it
//! left in shared memory is found by name: nothing may be.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_microstereo")
}

fn small() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/graph/small.toml")
}

/// A run's names: its instance and its iceoryx2 domain.
struct Names {
    instance: String,
    domain: String,
}

impl Names {
    fn new(what: &str) -> Self {
        let tag = format!("{what}{}", std::process::id());
        Self {
            instance: format!("life-{tag}"),
            domain: format!("life{tag}").chars().take(32).collect(),
        }
    }

    /// `microstereo ARGS --instance NAME` in the run's domain, leading a process group of
    /// its own as a shell's job does (so that a signal to the group is a terminal's).
    fn start(&self, args: &[&str], out: Stdio, err: Stdio) -> Child {
        use std::os::unix::process::CommandExt;
        let mut cmd = Command::new(bin());
        cmd.args(args)
            .args(["--instance", &self.instance])
            .env("MICROSTEREO_DOMAIN", &self.domain)
            .stdin(Stdio::null())
            .stdout(out)
            .stderr(err)
            .process_group(0);
        // SAFETY: only async-signal-safe prctl between fork and exec.
        unsafe {
            cmd.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
                Ok(())
            });
        }
        cmd.spawn().unwrap()
    }

    /// What the run left: processes, shared memory and iceoryx2 files of its domain, its
    /// lock, graph and control files.
    fn leftovers(&self) -> Vec<String> {
        let mut left = Vec::new();
        for e in std::fs::read_dir("/proc").unwrap().filter_map(Result::ok) {
            let pid = e.file_name().to_string_lossy().into_owned();
            if pid.parse::<u32>().is_err() {
                continue;
            }
            let cmd = std::fs::read(format!("/proc/{pid}/cmdline")).unwrap_or_default();
            let zombie = std::fs::read_to_string(format!("/proc/{pid}/stat"))
                .is_ok_and(|s| s.contains(") Z "));
            if !zombie && String::from_utf8_lossy(&cmd).contains(&self.instance) {
                left.push(format!("process {pid}"));
            }
        }
        let prefix = format!("ms_{}_", self.domain);
        let mut walk = vec![PathBuf::from("/dev/shm"), PathBuf::from("/tmp/iceoryx2")];
        while let Some(dir) = walk.pop() {
            for e in std::fs::read_dir(&dir).into_iter().flatten().flatten() {
                let p = e.path();
                if p.is_dir() {
                    walk.push(p.clone());
                }
                if e.file_name().to_string_lossy().starts_with(&prefix) {
                    left.push(p.display().to_string());
                }
            }
        }
        let ours = format!("microstereo-{}", self.instance);
        for e in std::fs::read_dir(std::env::temp_dir()).unwrap().flatten() {
            let n = e.file_name().to_string_lossy().into_owned();
            if n == format!("{ours}.lock") || n.starts_with(&format!("{ours}-")) {
                left.push(e.path().display().to_string());
            }
        }
        left
    }

    /// Nothing left, within a few seconds (the last node processes exit after the
    /// supervisor's summary).
    fn assert_clean(&self, what: &str) {
        let t0 = Instant::now();
        loop {
            let left = self.leftovers();
            if left.is_empty() {
                return;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(10),
                "{what}: left behind: {left:?}"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

/// Waits for `child` within `limit`, reading what it says; kills it past the limit.
fn wait(mut child: Child, limit: Duration) -> (ExitStatus, String, String) {
    use std::io::Read;
    let take = |r: Option<Box<dyn Read + Send>>| {
        std::thread::spawn(move || {
            let mut v = Vec::new();
            if let Some(mut r) = r {
                let _ = r.read_to_end(&mut v);
            }
            String::from_utf8_lossy(&v).into_owned()
        })
    };
    let out = take(child.stdout.take().map(|p| Box::new(p) as _));
    let err = take(child.stderr.take().map(|p| Box::new(p) as _));
    let t0 = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t0.elapsed() > limit {
            // SAFETY: kill(2) on the group of a process this test started.
            unsafe {
                libc::kill(-(child.id() as i32), libc::SIGKILL);
            }
            let _ = child.wait();
            panic!(
                "still running after {limit:?}:\n{}\n{}",
                out.join().unwrap(),
                err.join().unwrap()
            );
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    (status, out.join().unwrap(), err.join().unwrap())
}

/// Sends `sig` as its source would: a terminal's Ctrl-C, Ctrl-\ and hang-up reach the whole
/// foreground group, `kill` the supervisor alone.
fn send(child: &Child, sig: i32) {
    let to_group = sig != libc::SIGTERM;
    let pid = child.id() as i32;
    // SAFETY: kill(2) on a process (group) this test started.
    unsafe {
        libc::kill(if to_group { -pid } else { pid }, sig);
    }
}

/// SIGINT, SIGTERM, SIGHUP and SIGQUIT, each at start-up (at once, while the nodes start,
/// while they make their edges) and at steady state: the run ends with its summary and exit
/// code 0 (unless the signal came before the program could take it: then it made nothing),
/// no error line, and nothing of it is left.
#[test]
fn a_stop_signal_at_any_moment_ends_the_run_cleanly() {
    let file = small();
    for (sig, name) in [
        (libc::SIGINT, "int"),
        (libc::SIGTERM, "term"),
        (libc::SIGHUP, "hup"),
        (libc::SIGQUIT, "quit"),
    ] {
        for delay_ms in [0u64, 40, 250, 2500] {
            let names = Names::new(&format!("{name}{delay_ms}"));
            let child = names.start(
                &["run", file.to_str().unwrap(), "--quiet"],
                Stdio::piped(),
                Stdio::piped(),
            );
            std::thread::sleep(Duration::from_millis(delay_ms));
            send(&child, sig);
            let (status, out, err) = wait(child, Duration::from_secs(30));
            let what = format!("{name} after {delay_ms} ms");
            use std::os::unix::process::ExitStatusExt;
            match status.signal() {
                // Killed by the signal's default action: only before the program took the
                // signals, when it had made nothing yet.
                Some(s) => assert!(
                    s == sig && delay_ms == 0 && err.is_empty(),
                    "{what}: {status}\n{out}\n{err}"
                ),
                None => {
                    assert_eq!(status.code(), Some(0), "{what}:\n{out}\n{err}");
                    assert!(
                        !err.contains("error") && !err.contains("panicked"),
                        "{what}: an error line:\n{err}"
                    );
                    // Stopped before its nodes started, or with the summary of what ran.
                    assert!(
                        out.contains("frame(s)") || err.contains("before the graph started"),
                        "{what}: no summary:\n{out}\n{err}"
                    );
                }
            }
            if delay_ms == 2500 {
                // By then every node had run: none ends without its report.
                assert!(!out.contains("(no report)"), "{what}:\n{out}");
            }
            names.assert_clean(&what);
        }
    }
}

/// A graph of many nodes told to stop while its nodes still start, and told twice: it ends
/// at once, and nothing of it is left.
#[test]
fn a_large_graph_stopped_during_its_start_leaves_nothing() {
    // Thirty cameras, each with its segmentation: sixty processes.
    let mut text = String::new();
    for k in 0..30 {
        text += &format!(
            "[[node]]\nid = \"capture{k}\"\nkind = \"capture\"\nparams = {{ width = 64, height = 48, cells = 0, fps = 20.0 }}\n\n[[node]]\nid = \"seg{k}\"\nkind = \"segment\"\ninputs = {{ frame = \"capture{k}/frame\" }}\n\n"
        );
    }
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("wide.toml");
    std::fs::write(&file, text).unwrap();
    for (twice, delay_ms) in [(false, 1500u64), (true, 3000)] {
        let names = Names::new(&format!("wide{delay_ms}"));
        let child = names.start(
            &["run", file.to_str().unwrap(), "--quiet"],
            Stdio::piped(),
            Stdio::piped(),
        );
        std::thread::sleep(Duration::from_millis(delay_ms));
        send(&child, libc::SIGTERM);
        if twice {
            std::thread::sleep(Duration::from_millis(100));
            send(&child, libc::SIGTERM);
        }
        let (status, out, err) = wait(child, Duration::from_secs(60));
        assert_eq!(status.code(), Some(0), "{out}\n{err}");
        names.assert_clean(&format!("60 nodes, SIGTERM after {delay_ms} ms"));
    }
}

/// The manipulator bridge cannot listen (its port is taken): the start fails with one clear
/// error, and the same instance then runs, three times in a row.
#[test]
fn a_failed_start_leaves_its_instance_usable() {
    let busy = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = busy.local_addr().unwrap().port();
    let names = Names::new("failed");
    let small = [
        "--set",
        "capture.width=320",
        "--set",
        "capture.height=256",
        "--set",
        "capture.repeat=2",
    ];
    let listen = |p: u16| format!("manipulator-bridge.listen=\"127.0.0.1:{p}\"");
    let mut args = vec!["run", "--frames", "3", "--quiet", "--set"];
    let on_busy = listen(port);
    args.push(&on_busy);
    args.extend(small);
    let (status, out, err) = wait(
        names.start(&args, Stdio::piped(), Stdio::piped()),
        Duration::from_secs(60),
    );
    assert_eq!(status.code(), Some(2), "{out}\n{err}");
    assert!(err.contains("cannot listen on"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    names.assert_clean("the failed start");
    drop(busy);
    for k in 0..3 {
        let free = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let p = free.local_addr().unwrap().port();
        drop(free);
        let on_free = listen(p);
        let mut args = vec!["run", "--frames", "3", "--quiet", "--set"];
        args.push(&on_free);
        args.extend(small);
        let (status, out, err) = wait(
            names.start(&args, Stdio::piped(), Stdio::piped()),
            Duration::from_secs(60),
        );
        assert_eq!(status.code(), Some(0), "retry {k}:\n{out}\n{err}");
        assert!(out.contains("frame(s) of 3"), "retry {k}: {out}");
        names.assert_clean(&format!("retry {k}"));
    }
}

/// stderr and stdout on a full disk (`/dev/full`), stopped with Ctrl-C; stderr into a pipe
/// whose reader left, then a node killed: the supervisor never dies of its output, and
/// every run cleans up.
#[test]
fn a_full_or_broken_output_never_stops_the_clean_up() {
    let file = small();
    // On a full disk, then Ctrl-C.
    let names = Names::new("full");
    let full = || {
        std::fs::File::options()
            .write(true)
            .open("/dev/full")
            .unwrap()
    };
    let child = names.start(
        &["run", file.to_str().unwrap()],
        Stdio::from(full()),
        Stdio::from(full()),
    );
    std::thread::sleep(Duration::from_millis(2000));
    send(&child, libc::SIGINT);
    let (status, _, _) = wait(child, Duration::from_secs(30));
    assert_eq!(status.code(), Some(0), "{status}");
    names.assert_clean("stderr on /dev/full");
    // Into pipes nobody reads any more, then a node dies: the run fails as it should.
    let names = Names::new("broken");
    let mut child = names.start(
        &["run", file.to_str().unwrap()],
        Stdio::piped(),
        Stdio::piped(),
    );
    drop(child.stdout.take());
    drop(child.stderr.take());
    let t0 = Instant::now();
    let segment = loop {
        let found = std::fs::read_dir("/proc").unwrap().flatten().find_map(|e| {
            let pid: u32 = e.file_name().to_str()?.parse().ok()?;
            let cmd = std::fs::read(format!("/proc/{pid}/cmdline")).ok()?;
            let cmd = String::from_utf8_lossy(&cmd);
            (cmd.contains(&names.instance) && cmd.contains("--id\0segment\0")).then_some(pid)
        });
        if let Some(p) = found {
            break p;
        }
        assert!(t0.elapsed() < Duration::from_secs(20), "no segment node");
        std::thread::sleep(Duration::from_millis(20));
    };
    std::thread::sleep(Duration::from_millis(1000));
    // SAFETY: kill(2) on a node of this test's own run.
    unsafe {
        libc::kill(segment as i32, libc::SIGKILL);
    }
    let (status, _, _) = wait(child, Duration::from_secs(30));
    assert_eq!(status.code(), Some(2), "the run failed: {status}");
    names.assert_clean("stderr into a closed pipe, a node killed");
}

/// `MICROSTEREO_DOMAIN` names the domain the run's shared memory lives in; a name that
/// cannot be one is refused.
#[test]
fn the_domain_variable_is_honoured_and_checked() {
    let names = Names::new("domain");
    let child = names.start(
        &["run", small().to_str().unwrap(), "--quiet"],
        Stdio::piped(),
        Stdio::piped(),
    );
    let prefix = format!("ms_{}_", names.domain);
    let t0 = Instant::now();
    while !std::fs::read_dir("/dev/shm")
        .unwrap()
        .flatten()
        .any(|e| e.file_name().to_string_lossy().starts_with(&prefix))
    {
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "no shared memory named {prefix}*"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    send(&child, libc::SIGINT);
    let (status, out, err) = wait(child, Duration::from_secs(30));
    assert_eq!(status.code(), Some(0), "{out}\n{err}");
    names.assert_clean("a run in its own domain");
    let out = Command::new(bin())
        .args(["run", "--frames", "1"])
        .env("MICROSTEREO_DOMAIN", "no/such domain")
        .output()
        .unwrap();
    common::assert_clean_failure(&out, "MICROSTEREO_DOMAIN");
}

/// Rates and durations out of range (tiny, huge, not a number) are one clear error each,
/// before anything runs.
#[test]
fn rates_and_durations_out_of_range_are_refused() {
    for fps in ["1e-300", "0", "-3", "nan", "inf", "1e9"] {
        let out = common::run(&[
            "run",
            small().to_str().unwrap(),
            "--frames",
            "2",
            "--set",
            &format!("capture.fps={fps}"),
        ]);
        common::assert_clean_failure(&out, "fps");
    }
    let rec = Path::new(env!("CARGO_MANIFEST_DIR")).join("recordings/default.mcap");
    for rate in ["1e-300", "0", "nan", "1e9", "-1"] {
        let out = common::run(&["replay", rec.to_str().unwrap(), &format!("--rate={rate}")]);
        common::assert_clean_failure(&out, "rate");
    }
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("backoff.toml");
    std::fs::write(
        &file,
        std::fs::read_to_string(small())
            .unwrap()
            .replacen(
                "kind = \"segment\"\n",
                "kind = \"segment\"\nrestart = { policy = \"on-failure\", backoff_ms = 18446744073709551615 }\n",
                1,
            ),
    )
    .unwrap();
    let out = common::run(&["run", file.to_str().unwrap(), "--frames", "2"]);
    common::assert_clean_failure(&out, "backoff_ms");
}

/// What `top` says of a node that prepares (a camera rendering its loop ahead) and of one
/// that has produced nothing for seconds.
#[test]
fn top_shows_a_preparing_camera_and_marks_a_quiet_node() {
    let names = Names::new("top");
    // A long loop to render ahead, then one frame in five seconds.
    let child = names.start(
        &[
            "run",
            small().to_str().unwrap(),
            "--quiet",
            "--set",
            "capture.width=2048",
            "--set",
            "capture.height=2048",
            "--set",
            "capture.repeat=30",
            "--set",
            "capture.fps=0.2",
        ],
        Stdio::piped(),
        Stdio::piped(),
    );
    let top = || {
        let out = Command::new(bin())
            .args(["top", "--once", "--instance", &names.instance])
            .env("MICROSTEREO_DOMAIN", &names.domain)
            .output()
            .unwrap();
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    let row = |text: &str, id: &str| {
        text.lines()
            .find(|l| l.split_whitespace().next() == Some(id))
            .unwrap_or_default()
            .to_string()
    };
    let t0 = Instant::now();
    let mut seen = (false, false);
    while !(seen.0 && seen.1) && t0.elapsed() < Duration::from_secs(60) {
        let text = top();
        let capture = row(&text, "capture");
        seen.0 |= capture.contains("preparing") && capture.contains("rendering its loop ahead");
        // After its one frame, segment waits five seconds for the next.
        seen.1 |= row(&text, "segment").contains("nothing for");
        std::thread::sleep(Duration::from_millis(100));
    }
    send(&child, libc::SIGINT);
    let (status, out, err) = wait(child, Duration::from_secs(30));
    assert!(seen.0, "no preparing camera seen");
    assert!(seen.1, "no quiet node marked");
    assert_eq!(status.code(), Some(0), "{out}\n{err}");
    names.assert_clean("top");
}
