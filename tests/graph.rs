//! The process graph: real processes on real shared memory compute exactly what the same
//! nodes compute in one process.

use microstereo::run::load;
use runtime::exec::InProcess;
use runtime::launch::Graph;
use runtime::transport::Transport;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_microstereo")
}

/// The custom node of `examples/invert-node`, built beside `microstereo` by
/// `cargo test --workspace`.
fn invert_bin() -> PathBuf {
    let p = Path::new(bin()).with_file_name("microstereo-invert");
    assert!(
        p.is_file(),
        "{} is missing: run the tests with `cargo test --workspace` (or `cargo build -p invert-node`)",
        p.display()
    );
    p
}

/// Starts `microstereo ARGS` with its output piped; it dies with this test process, so that
/// a test that fails or is killed leaves no graph running.
fn start(args: &[&str]) -> Child {
    start_with(args, Stdio::piped, Stdio::piped)
}

/// [`start`] with the given stdout and stderr.
fn start_with(args: &[&str], out: fn() -> Stdio, err: fn() -> Stdio) -> Child {
    use std::os::unix::process::CommandExt;
    let mut cmd = Command::new(bin());
    cmd.args(args).stdout(out()).stderr(err());
    // SAFETY: only async-signal-safe prctl between fork and exec.
    unsafe {
        cmd.pre_exec(|| {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
            Ok(())
        });
    }
    cmd.spawn().unwrap()
}

/// Waits for `child` to end within `limit`; past it, kills it and fails with what it said,
/// so that a hung graph is one failed test rather than a hung test run.
fn finish(mut child: Child, limit: Duration) -> Output {
    use std::io::Read;
    let pipe = |r: Option<Box<dyn Read + Send>>| {
        std::thread::spawn(move || {
            let mut v = Vec::new();
            if let Some(mut r) = r {
                let _ = r.read_to_end(&mut v);
            }
            v
        })
    };
    let out = pipe(child.stdout.take().map(|p| Box::new(p) as _));
    let err = pipe(child.stderr.take().map(|p| Box::new(p) as _));
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break Some(s);
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let (stdout, stderr) = (out.join().unwrap(), err.join().unwrap());
    match status {
        Some(status) => Output {
            status,
            stdout,
            stderr,
        },
        None => panic!(
            "still running after {limit:?}; it said:\n{}\n{}",
            String::from_utf8_lossy(&stdout),
            String::from_utf8_lossy(&stderr)
        ),
    }
}

/// Starts `microstereo run FILE --frames N --instance NAME`.
fn start_run(file: &Path, frames: u64, instance: &str) -> Child {
    let n = frames.to_string();
    start(&[
        "run",
        file.to_str().unwrap(),
        "--frames",
        &n,
        "--instance",
        instance,
    ])
}

/// From a run's summary: how many of its `frames` frames reached the end of the graph.
fn frames_done(summary: &str, frames: u64) -> u64 {
    summary
        .lines()
        .find_map(|l| l.split_once(&format!(" frame(s) of {frames}")))
        .and_then(|(n, _)| n.trim().parse().ok())
        .expect("a summary")
}

/// From a run's summary: the frames node `id` took in, over every process that ran it,
/// and how many processes did.
fn node_frames_in(summary: &str, id: &str) -> (u64, u64) {
    summary
        .lines()
        .find_map(|l| {
            let rest = l.strip_prefix(id)?.strip_prefix(' ')?;
            let n = rest.split_whitespace().next()?.parse().ok()?;
            let runs = rest
                .split_once("  (")
                .and_then(|(_, r)| r.split_whitespace().next()?.parse().ok())
                .unwrap_or(1);
            Some((n, runs))
        })
        .expect("the node's row")
}

/// From a run's summary: the frames dropped on the edge printed as `edge` (`a/b → c.d`).
fn drops_on(summary: &str, edge: &str) -> u64 {
    edge_figures(summary, edge).0
}

/// From a run's summary: the frames that never reached the input of `edge`, lost anywhere.
fn missing_at(summary: &str, edge: &str) -> u64 {
    edge_figures(summary, edge).1
}

/// The `(dropped, never arrived)` columns of `edge`'s row in the summary's edge table.
fn edge_figures(summary: &str, edge: &str) -> (u64, u64) {
    summary
        .lines()
        .find_map(|l| {
            let rest = l.strip_prefix(edge)?;
            let v: Vec<u64> = rest
                .split_whitespace()
                .map(|x| x.parse().ok())
                .collect::<Option<_>>()?;
            (v.len() == 2).then(|| (v[0], v[1]))
        })
        .unwrap_or_else(|| panic!("no row for {edge} in {summary}"))
}

/// Runs `microstereo ARGS` to its end (at most two minutes).
fn run(args: &[&str]) -> Output {
    finish(start(args), Duration::from_secs(120))
}

/// What a watched edge carried: `(frame, payload)` per message.
type Edge = Vec<(u64, Vec<u8>)>;

/// Runs `microstereo run FILE --frames N` under its own instance name while this process
/// reads the `watched` edges too (subscribed before anything runs); returns every message
/// of each as `(frame, payload)` and the run's output.
fn run_and_watch(
    file: &Path,
    graph: &Graph,
    frames: u64,
    watched: &[(&str, &str)],
) -> (Vec<Edge>, std::process::Output) {
    let instance = format!("watch{}", std::process::id());
    let instance = format!("{instance}-{}", file.file_stem().unwrap().to_string_lossy());
    let _domain = runtime::process::ReleaseDomain;
    let t = Transport::new("graph-test").unwrap();
    let subs: Vec<_> = watched
        .iter()
        .map(|(n, p)| {
            t.subscriber(&Graph::edge_name(&instance, n, p), &graph.edge_config(n, p))
                .unwrap()
        })
        .collect();
    let run = start_run(file, frames, &instance);
    let mut got: Vec<Edge> = vec![Vec::new(); watched.len()];
    let begin = Instant::now();
    let refs: Vec<_> = subs.iter().collect();
    let mut ready = Vec::new();
    while got.iter().any(|g| (g.len() as u64) < frames) {
        if begin.elapsed() > Duration::from_secs(120) {
            eprintln!(
                "{:?} frames per watched edge after 120 s",
                got.iter().map(Vec::len).collect::<Vec<_>>()
            );
            finish(run, Duration::ZERO);
            unreachable!("finish fails a run that has not ended");
        }
        runtime::transport::wait_any(&refs, Duration::from_millis(200), &mut ready).unwrap();
        for (i, s) in subs.iter().enumerate() {
            while let Some(m) = s.receive().unwrap() {
                got[i].push((m.user_header().sequence, m.payload().to_vec()));
            }
        }
    }
    (got, finish(run, Duration::from_secs(60)))
}

#[test]
fn graph_of_processes_equals_the_in_process_pipeline_bit_for_bit() {
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/graph/small.toml");
    let graph = load(&file).unwrap();
    let frames = 4u64;
    // Read the final edges from this test process too, subscribed before anything runs.
    let watched = [
        ("postprocess", "disparity"),
        ("segment", "labels"),
        ("segment", "cells"),
        ("triangulate", "cloud"),
        ("triangulate", "targets"),
    ];
    let (got, out) = run_and_watch(&file, &graph, frames, &watched);
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{summary}");
    assert!(summary.contains("4 frame(s) of 4"), "{summary}");
    // The same nodes, in this process.
    let log = InProcess::new(&graph, &pipelines::registry::builtin())
        .unwrap()
        .run(frames)
        .unwrap();
    for ((n, p), g) in watched.iter().zip(&got) {
        let want = &log[&(n.to_string(), p.to_string())];
        assert_eq!(want.len() as u64, frames);
        for (k, (seq, bytes)) in g.iter().enumerate() {
            assert_eq!(*seq, k as u64, "{n}/{p}: frames in order");
            if *p == "targets" {
                // The scene carries its capture time, which differs between the runs; every
                // other field must be equal, floats to the bit.
                let strip = |b: &[u8]| {
                    let mut v: serde_json::Value = serde_json::from_slice(b).unwrap();
                    v.as_object_mut().unwrap().remove("capture_ns");
                    v
                };
                let (a, b) = (strip(bytes), strip(&want[k].1));
                assert!(!a["cells"].as_array().unwrap().is_empty());
                assert_eq!(a, b, "{n}/{p} frame {k}");
                continue;
            }
            assert!(
                *bytes == want[k].1,
                "{n}/{p} frame {k}: {} bytes from the graph, {} in-process, equal: false",
                bytes.len(),
                want[k].1.len()
            );
        }
    }
    // Every node ran as its own process and reported.
    for id in ["capture", "segment", "match", "validate", "postprocess"] {
        assert!(
            summary
                .lines()
                .any(|l| l.starts_with(id) && !l.contains("no report")),
            "{id}: {summary}"
        );
    }
}

#[test]
fn a_source_with_frames_in_flight_lets_in_only_what_the_graph_has_finished() {
    // The small graph with its source paced far beyond what the graph takes (100 frames/s
    // for 3 s: long enough for several frames even on a loaded machine, where the first
    // takes a second) and one frame in flight at a time: the frames it cannot let in are
    // dropped at the source, and every frame it lets in is finished (none waits in a
    // queue).
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/graph/small.toml"),
    )
    .unwrap();
    let capture = "params = { width = 320, height = 240, cells = 3, seed = 5, drift = 2.0 }";
    assert!(text.contains(capture), "the small graph's capture changed");
    let text = text.replace(
        capture,
        "params = { width = 320, height = 240, cells = 3, seed = 5, drift = 2.0, fps = 100 }\nin_flight = { after = \"manipulator-bridge/state\", frames = 1 }",
    );
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("in-flight.toml");
    std::fs::write(&file, text).unwrap();
    let frames = 300;
    let out = finish(
        start_run(&file, frames, &format!("inflight{}", std::process::id())),
        Duration::from_secs(120),
    );
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{summary}");
    let (sent, _) = node_frames_in(&summary, "capture");
    let (bridged, _) = node_frames_in(&summary, "manipulator-bridge");
    assert!(
        sent >= 2 && sent < frames,
        "{sent} frames let in: {summary}"
    );
    assert_eq!(bridged, sent, "{summary}");
    assert_eq!(frames_done(&summary, frames), sent, "{summary}");
}

#[test]
fn bad_launch_files_are_refused_with_file_and_line() {
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("bad.toml");
    std::fs::write(
        &f,
        "[[node]]\nid = \"capture\"\nkind = \"capture\"\nparams = { source = \"camera\" }\n\n[[node]]\nid = \"m\"\nkind = \"match\"\ninputs = { frame = \"capture/frame\" }\nparams = { min_disparity = 5, max_disparity = 1, region = \"frame\" }\n",
    )
    .unwrap();
    let out = run(&["run", f.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    let name = f.display().to_string();
    assert!(
        err.contains(&format!(
            "{name}:4: node 'capture': bad params: source 'camera' is not available"
        )),
        "{err}"
    );
    assert!(
        err.contains(&format!(
            "{name}:10: node 'm': bad params: disparity range 5..1 is empty"
        )),
        "{err}"
    );
    let out = run(&["run", dir.path().join("missing.toml").to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("cannot read the launch file"));
    // Ports and message kinds are the nodes' own declarations: a port a node does not
    // have, an edge of the wrong kind, and an exec node's ports written unlike what its
    // program declares are each refused before anything starts, with their line.
    std::fs::write(
        &f,
        format!(
            r#"[[node]]
id = "capture"
kind = "capture"

[[node]]
id = "segment"
kind = "segment"
inputs = {{ frame = "capture/frame" }}

[[node]]
id = "match"
kind = "match"
inputs = {{ frame = "capture/frame", cels = "segment/cells" }}
params = {{ min_disparity = 0, max_disparity = 8 }}

[[node]]
id = "validate"
kind = "validate"
inputs = {{ left = "segment/cells", right = "match/right" }}

[[node]]
id = "invert"
exec = "{}"
inputs = {{ frame = "capture/frame" }}
ports = {{ inputs = {{ frame = "disparity-tiles" }}, outputs = {{ frame = "stereo-frame" }} }}
"#,
            invert_bin().display()
        ),
    )
    .unwrap();
    let out = run(&["run", f.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    for want in [
        format!("{name}:14: node 'match': bad params: region = \"cells\" (the default)"),
        format!("{name}:13: node 'match' has no input 'cels'; its inputs: frame, cells"),
        format!(
            "{name}:19: node 'validate' reads 'segment/cells', which carries CellList, but expects DisparityTiles"
        ),
        format!(
            "{name}:25: node 'invert': ports say inputs {{ frame = \"disparity-tiles\" }} but {} declares {{ frame = \"stereo-frame\" }}",
            invert_bin().display()
        ),
    ] {
        assert!(err.contains(&want), "{want}\nnot in\n{err}");
    }
    assert!(!err.contains("panicked"), "{err}");
}

/// Pids whose parent is `ppid` (from /proc).
fn children_of(ppid: u32) -> Vec<u32> {
    std::fs::read_dir("/proc")
        .unwrap()
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .filter(|pid| {
            std::fs::read_to_string(format!("/proc/{pid}/stat"))
                .ok()
                .and_then(|s| {
                    // "pid (comm) state ppid ...": the command may hold spaces.
                    let rest = &s[s.rfind(')')? + 2..];
                    rest.split(' ').nth(1)?.parse::<u32>().ok()
                })
                == Some(ppid)
        })
        .collect()
}

/// The pid of node `id` of the run `sup` supervises, once it has started (within 20 s).
fn wait_node_pid(sup: &Child, id: &str) -> u32 {
    wait_live_node_pid(sup, id, &[], Duration::from_secs(20))
}

/// The pid of a live process of node `id` of the run `sup` supervises, none of `except`
/// (already killed) and not a zombie the supervisor has yet to reap, within `limit`.
fn wait_live_node_pid(sup: &Child, id: &str, except: &[u32], limit: Duration) -> u32 {
    let begin = Instant::now();
    loop {
        let found = children_of(sup.id()).into_iter().find(|p| {
            !except.contains(p)
                && std::fs::read_to_string(format!("/proc/{p}/cmdline"))
                    .is_ok_and(|c| c.contains(&format!("--id\0{id}\0")))
                && std::fs::read_to_string(format!("/proc/{p}/stat"))
                    .ok()
                    .and_then(|s| s.get(s.rfind(')')? + 2..)?.chars().next())
                    .is_some_and(|state| state != 'Z')
        });
        if let Some(pid) = found {
            return pid;
        }
        assert!(begin.elapsed() < limit, "no live {id} process");
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Held by the two heaviest tests, so that they never load the machine at once: the chaos
/// run's thousand frames and the closed loop's paced run (73 s alone under two CPU hogs,
/// against its 90 s limit).
fn heavy() -> std::sync::MutexGuard<'static, ()> {
    static HEAVY: std::sync::Mutex<()> = std::sync::Mutex::new(());
    HEAVY
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// The text of `tests/data/graph/small.toml`.
fn small_graph() -> String {
    std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/graph/small.toml"),
    )
    .unwrap()
}

/// Launch text `text` with `restart` (a `restart = { … }` line) under every node's kind.
fn with_restart(text: &str, restart: &str) -> String {
    text.lines()
        .flat_map(|l| {
            [l, "\n"]
                .into_iter()
                .chain(l.starts_with("kind = ").then_some(restart))
        })
        .collect()
}

#[test]
fn one_process_per_node_and_none_left_when_the_supervisor_is_killed() {
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/graph/small.toml");
    let instance = format!("killed{}", std::process::id());
    let mut sup = start_with(
        &["run", file.to_str().unwrap(), "--instance", &instance],
        Stdio::null,
        Stdio::null,
    );
    let start = Instant::now();
    let nodes = load(&file).unwrap().nodes.len();
    let mut kids = Vec::new();
    while kids.len() < nodes && start.elapsed() < Duration::from_secs(20) {
        std::thread::sleep(Duration::from_millis(50));
        kids = children_of(sup.id());
    }
    assert_eq!(kids.len(), nodes, "one process per node");
    // A second run under the same instance would share its edges: refused, clearly.
    let twin = run(&[
        "run",
        file.to_str().unwrap(),
        "--frames",
        "2",
        "--instance",
        &instance,
    ]);
    let err = String::from_utf8_lossy(&twin.stderr);
    assert_eq!(twin.status.code(), Some(2), "{err}");
    assert!(err.contains("is in use by another run"), "{err}");
    sup.kill().unwrap(); // SIGKILL: no chance to clean up.
    sup.wait().unwrap();
    let gone = |pid: &u32| {
        !Path::new(&format!("/proc/{pid}")).exists()
            || std::fs::read_to_string(format!("/proc/{pid}/stat"))
                .is_ok_and(|s| s.contains(") Z "))
    };
    let start = Instant::now();
    while !kids.iter().all(gone) {
        assert!(
            start.elapsed() < Duration::from_secs(5),
            "orphans left: {kids:?}"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    // The killed nodes left their shared memory; the next run removes it and works. A node
    // killed while creating an edge leaves it unsized, which counts as dead once it is old
    // enough.
    std::thread::sleep(runtime::process::UNSIZED_AGE + Duration::from_millis(500));
    let dead_before = runtime::process::dead_nodes(&instance);
    // The killed supervisor's hold on its instance went with it: the lock is free.
    {
        use std::os::fd::AsRawFd;
        let lock =
            std::fs::File::open(std::env::temp_dir().join(format!("microstereo-{instance}.lock")))
                .unwrap();
        // SAFETY: flock on a descriptor this test owns.
        let rc = unsafe { libc::flock(lock.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
        assert_eq!(
            rc, 0,
            "the instance is still locked after its supervisor died"
        );
    }
    // The next run of the instance takes over what the killed one left: its lock, its
    // graph file, its shared memory.
    let out = run(&[
        "run",
        file.to_str().unwrap(),
        "--frames",
        "2",
        "--instance",
        &instance,
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        String::from_utf8_lossy(&out.stdout).contains("2 frame(s) of 2"),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
    let left: Vec<_> = std::fs::read_dir(std::env::temp_dir())
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(&format!("microstereo-{instance}")))
        .collect();
    assert!(left.is_empty(), "left behind: {left:?}");
    // SIGKILL left the nodes' shared memory behind (unless another test's run, which starts
    // the same way, has removed it already); after a run has started, none is left (within a
    // few seconds: a run started beside this one may be the one removing it).
    eprintln!("dead nodes of the killed run: {dead_before} before the next run");
    let start = Instant::now();
    while runtime::process::dead_nodes(&instance) > 0 && start.elapsed() < Duration::from_secs(8) {
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(runtime::process::dead_nodes(&instance), 0);
}

/// Runs the small graph paced at 8 frames/s for `frames` frames with a restart policy on
/// node `victim` (and `restart_extra` in its restart table), sends it `signal` 0.8 s in,
/// and returns the run's output and its instance.
fn signal_mid_run(
    victim: &str,
    frames: u64,
    signal: i32,
    restart_extra: &str,
) -> (std::process::Output, String) {
    let dir = tempfile::tempdir().unwrap();
    let small = small_graph()
        // Paced, so that the kill lands mid-run.
        .replace("drift = 2.0 }", "drift = 2.0, fps = 8.0 }");
    let small = small.replacen(
        &format!("id = \"{victim}\"\n"),
        &format!(
            "id = \"{victim}\"\nrestart = {{ policy = \"on-failure\", max = 2, backoff_ms = 50{restart_extra} }}\n"
        ),
        1,
    );
    assert!(small.contains("restart = {"));
    let file = dir.path().join("kill-node.toml");
    std::fs::write(&file, small).unwrap();
    let instance = format!("sig{signal}{victim}{}", std::process::id());
    let sup = start_run(&file, frames, &instance);
    let pid = wait_node_pid(&sup, victim);
    // A few frames in (8 per second), well before the last.
    std::thread::sleep(Duration::from_millis(800));
    // SAFETY: kill(2) on a process this test started (through the supervisor).
    unsafe {
        libc::kill(pid as i32, signal);
    }
    (finish(sup, Duration::from_secs(120)), instance)
}

/// No process of run `instance` is left, and no shared memory of a dead node of it.
fn assert_nothing_left(instance: &str) {
    let left: Vec<u32> = std::fs::read_dir("/proc")
        .unwrap()
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .filter(|p| {
            std::fs::read_to_string(format!("/proc/{p}/cmdline"))
                .is_ok_and(|c| c.contains(instance))
        })
        .collect();
    assert!(left.is_empty(), "processes left: {left:?}");
    assert_eq!(runtime::process::dead_nodes(instance), 0);
}

/// [`signal_mid_run`] with SIGKILL.
fn kill_mid_run(victim: &str, frames: u64) -> (std::process::Output, String) {
    signal_mid_run(victim, frames, libc::SIGKILL, "")
}

#[test]
fn a_node_killed_mid_run_is_restarted_and_the_run_completes_clean() {
    let frames = 24u64;
    let (out, instance) = kill_mid_run("match", frames);
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(
        stderr.contains("[match] exited (signal: 9 (SIGKILL)); restart 1 of 2"),
        "{stderr}"
    );
    // The run got to its end through the restarted matcher; the frames it missed while down
    // (and the one it was killed on) are the ones the summary counts as never reaching the
    // next node, though no edge dropped them (the graph is lossless).
    let done = frames_done(&stdout, frames);
    let missed = missing_at(&stdout, "match/left → validate.left");
    assert!(done >= frames / 2, "{stdout}");
    // (None at all when the kill lands between frames and the restart beats the next one.)
    assert_eq!(done + missed, frames, "{stdout}");
    assert_eq!(
        drops_on(&stdout, "match/left → validate.left"),
        0,
        "{stdout}"
    );
    assert!(
        stdout
            .lines()
            .any(|l| l.starts_with("match ") && !l.contains("no report")),
        "{stdout}"
    );
    // Its row counts both processes (the killed one if it lived to report): every frame
    // that reached the next node was one of their steps, bar one the killed one may have
    // finished after its last report.
    let (steps, runs) = node_frames_in(&stdout, "match");
    assert!((1..=2).contains(&runs), "{stdout}");
    assert!(
        (frames - missed).saturating_sub(steps) <= 1 && steps <= frames - missed,
        "match took {steps} steps for {} frames passed on\n{stdout}",
        frames - missed
    );
    assert_nothing_left(&instance);
}

#[test]
fn a_restarted_source_goes_on_from_its_last_frame() {
    // Before, a restarted capture numbered its frames from 0 again and made the run's
    // frame count anew: the run never ended at its count, and the frames of the two
    // processes collided downstream.
    let frames = 24u64;
    let (out, _) = kill_mid_run("capture", frames);
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(
        stderr.contains("[capture] exited (signal: 9 (SIGKILL)); restart 1 of 2"),
        "{stderr}"
    );
    // Both processes together made the run's frames, bar the one the killed process was
    // making (it claims a frame before making it, so no number is made twice; its count
    // is of frames it finished).
    let (made, runs) = node_frames_in(&stdout, "capture");
    assert!((1..=2).contains(&runs), "{stdout}");
    assert!((frames - 1..=frames).contains(&made), "{stdout}");
    let done = frames_done(&stdout, frames);
    // No frame is taken twice downstream.
    assert!(done <= frames && done >= frames / 2, "{stdout}");
}

#[test]
fn a_stopped_node_is_killed_by_the_watchdog_and_restarted() {
    // SIGSTOP freezes the matcher: without a watchdog the graph waits for it for ever.
    let frames = 24u64;
    let (out, _) = signal_mid_run("match", frames, libc::SIGSTOP, ", heartbeat_ms = 1000");
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(
        stderr.contains("[match] no report for") && stderr.contains("hung; killing it"),
        "{stderr}"
    );
    assert!(
        stderr.contains("[match] exited (hung: no report for") && stderr.contains("restart 1 of 2"),
        "{stderr}"
    );
    let done = frames_done(&stdout, frames);
    let missed = missing_at(&stdout, "match/left → validate.left");
    assert!(done >= frames / 3, "{stdout}");
    assert_eq!(done + missed, frames, "{stdout}");
}

#[test]
fn a_source_faster_than_the_graph_drops_frames_on_lossy_edges_and_the_run_ends() {
    // The small graph with its edges left lossy (depth 2, drop the oldest) and a source that
    // reads files as fast as it can: the joining nodes get frames on some inputs far ahead
    // of the others and must let the oldest go instead of holding every one.
    let small = small_graph()
    .replace(", depth = 8, overflow = \"block\"", "")
    .replace(
        "params = { width = 320, height = 240, cells = 3, seed = 5, drift = 2.0 }",
        &format!(
            "params = {{ source = \"files\", left = \"{c}/im2.png\", right = \"{c}/im6.png\", repeat = true }}",
            c = Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("tests/data/cones")
                .display()
        ),
    );
    assert!(!small.contains("overflow") && small.contains("files"));
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("lossy.toml");
    std::fs::write(&file, small).unwrap();
    let frames = 40u64;
    let out = run(&[
        "run",
        file.to_str().unwrap(),
        "--frames",
        &frames.to_string(),
    ]);
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(out.status.success(), "{stdout}\n{stderr}");
    // Every node read the source's last frame; the frames between went where the summary
    // says: dropped on the lossy edges, and the edges that dropped none lost none.
    let done = frames_done(&stdout, frames);
    assert!(done >= 1 && done < frames, "{stdout}");
    let figures: Vec<(u64, u64)> = stdout
        .lines()
        .filter(|l| l.contains(" → ") && !l.contains("frame(s)"))
        .map(|l| edge_figures(&stdout, l.split("  ").next().unwrap()))
        .collect();
    assert_eq!(figures.len(), 12, "{stdout}");
    assert!(figures.iter().map(|f| f.0).sum::<u64>() > 0, "{stdout}");
    let to_sink = edge_figures(&stdout, "triangulate/targets → manipulator-bridge.targets");
    assert!(to_sink.1 >= to_sink.0, "{stdout}");
}

#[test]
fn a_failing_node_is_restarted_by_its_policy() {
    let dir = tempfile::tempdir().unwrap();
    // Fails on its first start, then runs the example custom node.
    let script = dir.path().join("flaky.sh");
    std::fs::write(
        &script,
        format!(
            "#!/bin/sh\nif [ \"$1\" != --describe ] && [ ! -e '{m}' ]; then touch '{m}'; echo 'first start fails' >&2; exit 3; fi\nexec '{b}' \"$@\"\n",
            m = dir.path().join("started").display(),
            b = invert_bin().display()
        ),
    )
    .unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&script, std::fs::Permissions::from_mode(0o755)).unwrap();
    let file = dir.path().join("restart.toml");
    std::fs::write(
        &file,
        format!(
            r#"
[[node]]
id = "capture"
kind = "capture"
params = {{ width = 160, height = 120, cells = 2, seed = 3 }}

# Lossless: an unpaced source's frames on a lossy edge of depth 1 reach a node that
# starts slowly (on a loaded machine) only as the newest, and the count below is exact.
[[node]]
id = "flaky"
exec = "{}"
inputs = {{ frame = {{ from = "capture/frame", depth = 1, overflow = "block" }} }}
restart = {{ policy = "on-failure", max = 2, backoff_ms = 50 }}
"#,
            script.display()
        ),
    )
    .unwrap();
    let out = run(&["run", file.to_str().unwrap(), "--frames", "3"]);
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(stderr.contains("[flaky] first start fails"), "{stderr}");
    assert!(
        stderr.contains("[flaky] exited (exit status: 3); restart 1 of 2"),
        "{stderr}"
    );
    assert!(
        stdout
            .lines()
            .any(|l| l.starts_with("flaky") && l.contains(" 3 ")),
        "{stdout}"
    );
    // Without a restart policy the same failure stops the graph with an error.
    std::fs::remove_file(dir.path().join("started")).unwrap();
    std::fs::write(
        &file,
        std::fs::read_to_string(&file)
            .unwrap()
            .replace("restart = {", "# restart = {"),
    )
    .unwrap();
    let out = run(&["run", file.to_str().unwrap(), "--frames", "3"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("node 'flaky' failed (exit status: 3)"));
}

/// A TCP port free right now, for a bridge to listen on.
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Connects to the bridge on `port`, retrying while its graph starts.
fn connect_to_bridge(port: u16, within: Duration) -> std::net::TcpStream {
    let t0 = Instant::now();
    loop {
        match std::net::TcpStream::connect(("127.0.0.1", port)) {
            Ok(s) => return s,
            Err(_) if t0.elapsed() < within => std::thread::sleep(Duration::from_millis(20)),
            Err(e) => panic!("no bridge on port {port}: {e}"),
        }
    }
}

#[test]
fn the_bridge_serves_one_json_scene_per_frame_to_a_tcp_controller() {
    use std::io::BufRead;
    let port = free_port();
    let dir = tempfile::tempdir().unwrap();
    let small = small_graph()
        .replace("127.0.0.1:0", &format!("127.0.0.1:{port}"))
        // The capture paces itself so that the controller connects before the last frame.
        .replace("drift = 2.0 }", "drift = 2.0, fps = 10.0 }");
    let file = dir.path().join("bridge.toml");
    std::fs::write(&file, small).unwrap();
    let run = start(&["run", file.to_str().unwrap(), "--frames", "6"]);
    let stream = connect_to_bridge(port, Duration::from_secs(20));
    stream
        .set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    let mut frames = Vec::new();
    for line in std::io::BufReader::new(stream).lines() {
        let Ok(line) = line else { break };
        let scene: serde_json::Value = serde_json::from_str(&line).unwrap();
        assert_eq!(scene["unit"], "µm");
        let cells = scene["cells"].as_array().unwrap();
        assert_eq!(cells.len(), 3, "{line}");
        for c in cells {
            assert!(c["height"].as_f64().unwrap() > 5.0);
            assert_eq!(c["centroid"].as_array().unwrap().len(), 3);
            assert!(!c["contour"].as_array().unwrap().is_empty());
        }
        frames.push(scene["frame"].as_u64().unwrap());
    }
    let out = finish(run, Duration::from_secs(60));
    assert!(out.status.success());
    // Frames arrive in order, the last one included; the first may pass before we connect.
    assert!(frames.windows(2).all(|w| w[1] == w[0] + 1), "{frames:?}");
    assert_eq!(frames.last(), Some(&5), "{frames:?}");
}

#[test]
fn a_custom_exec_node_joins_the_graph() {
    let dir = tempfile::tempdir().unwrap();
    // Pairs that grow from frame to frame: each needs new shared memory on every edge.
    for (k, w) in [96u32, 192, 384, 768, 1536].into_iter().enumerate() {
        for side in ["l", "r"] {
            let img = image::GrayImage::from_fn(w, w * 2 / 3, |x, y| {
                image::Luma([((x * 7 + y * 13 + (x * y) % 31) % 256) as u8])
            });
            img.save(dir.path().join(format!("{side}{k}.png"))).unwrap();
        }
    }
    let file = dir.path().join("exec.toml");
    std::fs::write(
        &file,
        format!(
            r#"
[[node]]
id = "capture"
kind = "capture"
params = {{ source = "files", left = "{dir}/l?.png", right = "{dir}/r?.png" }}

[[node]]
id = "invert"
exec = "{invert}"
inputs = {{ frame = {{ from = "capture/frame", depth = 8, overflow = "block" }} }}
ports = {{ inputs = {{ frame = "stereo-frame" }}, outputs = {{ frame = "stereo-frame" }} }}

[[node]]
id = "segment"
kind = "segment"
inputs = {{ frame = {{ from = "invert/frame", depth = 8, overflow = "block" }} }}
"#,
            dir = dir.path().display(),
            invert = invert_bin().display()
        ),
    )
    .unwrap();
    let graph = load(&file).unwrap();
    let (got, out) = run_and_watch(
        &file,
        &graph,
        5,
        &[("capture", "frame"), ("invert", "frame")],
    );
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{summary}");
    for ((_, c), (_, i)) in got[0].iter().zip(&got[1]) {
        assert!(c.iter().zip(i).all(|(a, b)| 255 - a == *b) && c.len() == i.len());
    }
    // The custom node reported like the built-in ones, and its reader got every frame.
    assert!(
        summary
            .lines()
            .any(|l| l.starts_with("invert") && l.contains(" 5 ")),
        "{summary}"
    );
    // The invert forwards a frame in a few milliseconds, so it has the last, largest frame
    // out while the slower segmentation is still busy with the one before: it must stay
    // until that frame is read (a writer that leaves takes its unread frames along).
    assert!(
        summary
            .lines()
            .any(|l| l.starts_with("segment") && l.contains(" 5 ")),
        "{summary}"
    );
    assert!(summary.contains("5 frame(s) of 5"), "{summary}");
}

/// Every message of a recording by `(edge, frame)`.
fn recorded(
    path: &Path,
) -> std::collections::BTreeMap<(String, u64), (schemas::FrameHeader, Vec<u8>)> {
    recorder::EdgeReader::open(path, None)
        .unwrap()
        .map(|m| {
            let m = m.unwrap();
            ((m.edge, m.header.sequence), (m.header, m.payload))
        })
        .collect()
}

/// `--every`: images and labels recorded for one frame in three, the same frames on both
/// edges and the same bytes as a full recording of the same run would hold; the cells of
/// every frame.
#[test]
fn edges_recorded_every_third_frame_keep_the_same_frames_and_the_rest_keep_all() {
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/graph/small.toml");
    let dir = tempfile::tempdir().unwrap();
    let (thin, full) = (dir.path().join("thin.mcap"), dir.path().join("full.mcap"));
    let id = std::process::id();
    for (path, every) in [(&thin, true), (&full, false)] {
        let mut args = vec![
            "run".to_string(),
            file.to_str().unwrap().into(),
            "--frames".into(),
            "10".into(),
            "--record".into(),
            path.to_str().unwrap().into(),
            "--edges".into(),
            "capture/frame".into(),
            "segment/*".into(),
            "--instance".into(),
            format!("every{id}{every}"),
        ];
        if every {
            args.extend(
                ["--every", "capture/frame=3", "--every", "segment/labels=3"].map(String::from),
            );
        }
        let args: Vec<&str> = args.iter().map(|a| a.as_str()).collect();
        let out = run(&args);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let (thin, full) = (recorded(&thin), recorded(&full));
    let frames = |m: &std::collections::BTreeMap<(String, u64), _>, edge: &str| -> Vec<u64> {
        m.keys()
            .filter(|(e, _)| e == edge)
            .map(|(_, s)| *s)
            .collect()
    };
    // The small graph loses no frame: every third frame number from the first.
    assert_eq!(frames(&thin, "capture/frame"), [0, 3, 6, 9]);
    assert_eq!(frames(&thin, "segment/labels"), [0, 3, 6, 9]);
    assert_eq!(frames(&thin, "segment/cells"), (0..10).collect::<Vec<_>>());
    assert_eq!(frames(&full, "capture/frame"), (0..10).collect::<Vec<_>>());
    for (key, (h, p)) in &thin {
        let (h2, p2) = &full[key];
        assert_eq!(h.sequence, h2.sequence, "{key:?}");
        assert!(p == p2, "{key:?}: payloads differ");
    }
}

#[test]
fn a_replayed_recording_reproduces_every_downstream_edge_bit_for_bit() {
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/graph/small.toml");
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a.mcap"), dir.path().join("b.mcap"));
    let id = std::process::id();
    let out = run(&[
        "run",
        file.to_str().unwrap(),
        "--frames",
        "4",
        "--record",
        a.to_str().unwrap(),
        "--instance",
        &format!("rec{id}"),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The capture node is replaced by the recording; every other node computes again.
    let out = run(&[
        "replay",
        a.to_str().unwrap(),
        "--rate",
        "max",
        "--record",
        b.to_str().unwrap(),
        "--instance",
        &format!("replay{id}"),
    ]);
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(said.contains("4 frame(s) of 4"), "{said}");
    let (first, second) = (recorded(&a), recorded(&b));
    let edges: std::collections::BTreeSet<&str> = first.keys().map(|(e, _)| e.as_str()).collect();
    // 11 edges and the bridge's state (idle: no wall-clock samples, so replayable too).
    assert_eq!(edges.len(), 12, "{edges:?}");
    assert_eq!(first.len(), 48);
    assert_eq!(
        first.keys().collect::<Vec<_>>(),
        second.keys().collect::<Vec<_>>()
    );
    for (key, (h, p)) in &first {
        let (h2, p2) = &second[key];
        assert_eq!(h, h2, "{key:?}");
        assert!(p == p2, "{key:?}: payloads differ");
    }
    // In a loop the four recorded frames come round again with frame numbers running on.
    let out = run(&[
        "replay",
        a.to_str().unwrap(),
        "--rate",
        "max",
        "--loop",
        "--frames",
        "10",
        "--instance",
        &format!("loop{id}"),
    ]);
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(said.contains("10 frame(s) of 10"), "{said}");
}

#[test]
fn a_recorder_killed_with_sigkill_leaves_a_file_readable_to_its_last_flush() {
    let dir = tempfile::tempdir().unwrap();
    let text = small_graph().replace(
        "seed = 5, drift = 2.0 }",
        "seed = 5, drift = 2.0, fps = 5.0 }",
    );
    assert!(text.contains("fps = 5.0"));
    let file = dir.path().join("paced.toml");
    std::fs::write(&file, text).unwrap();
    let rec = dir.path().join("killed.mcap");
    let sup = start(&[
        "run",
        file.to_str().unwrap(),
        "--record",
        rec.to_str().unwrap(),
        "--instance",
        &format!("sigkill{}", std::process::id()),
    ]);
    let is_recorder = |pid: &u32| {
        std::fs::read(format!("/proc/{pid}/cmdline")).is_ok_and(|c| {
            c.split(|b| *b == 0)
                .collect::<Vec<_>>()
                .windows(2)
                .any(|w| w == [b"--id".as_slice(), b"recorder"])
        })
    };
    let start = Instant::now();
    let recorder = loop {
        if let Some(p) = children_of(sup.id()).into_iter().find(is_recorder) {
            break p;
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "no recorder process"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    // Several flushes' worth of frames (5 per second), then no chance to close the file.
    std::thread::sleep(Duration::from_millis(3500));
    // SAFETY: kill(2) on a process this test started.
    unsafe {
        libc::kill(recorder as i32, libc::SIGKILL);
    }
    let out = finish(sup, Duration::from_secs(30));
    assert_eq!(
        out.status.code(),
        Some(2),
        "the run fails: its recorder died"
    );
    // The recording never took its final name: what it holds is under the recorder's
    // `.part` name, which the run's error names.
    assert!(!rec.exists(), "a half recording under the final name");
    let part = dir.path().join(format!("killed.mcap.{recorder}.part"));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains(part.to_str().unwrap()), "{err}");
    let rec = part;
    let mut reader = recorder::EdgeReader::open(&rec, None).unwrap();
    let got: Vec<_> = reader.by_ref().collect::<Result<_, _>>().unwrap();
    // 10 edges at 5 frames/s for 3.5 s; at most the last second can be lost, and the
    // reader says where the file breaks off.
    assert!(got.len() >= 10, "{} messages readable", got.len());
    let lost = reader.lost();
    assert!(lost.len() == 1 && lost[0].contains("truncated"), "{lost:?}");
    // The commands read it as far as it goes (a replay of what was recorded).
    let replayed = run(&["replay", rec.to_str().unwrap(), "--quiet"]);
    assert!(
        replayed.status.success()
            && String::from_utf8_lossy(&replayed.stderr).contains("the file is truncated"),
        "{}",
        String::from_utf8_lossy(&replayed.stderr)
    );
    let out = run(&["inspect", rec.to_str().unwrap()]);
    let (said, err) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert_eq!(out.status.code(), Some(2));
    assert!(
        said.contains("/capture/frame/left") && said.contains("sensor_msgs/msg/Image"),
        "{said}"
    );
    assert!(
        err.contains("truncated") && !err.contains("panicked"),
        "{err}"
    );
}

/// The closed loop: the graph runs with the simulated manipulator, the capture draws the
/// pipette where the sim says it is, a controller sends `approach` over TCP, then
/// `retract`. The recorded state edge shows the tip reaching the injection point within
/// 1 µm without the body ever coming within the clearance of another cell (checked against
/// the recorded scene of each frame), and the retract bringing it out above every cell.
#[test]
fn the_sim_manipulator_approaches_a_cell_and_retracts_in_closed_loop() {
    let _heavy = heavy();
    use manipulator_bridge::geom::dist;
    use manipulator_bridge::node::BridgeParams;
    use manipulator_bridge::scene::Scene;
    use schemas::{ManipulatorState, Targets};
    use std::io::{BufRead, Write};
    let port = free_port();
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/graph/manipulator.toml"),
    )
    .unwrap()
    .replace("127.0.0.1:0", &format!("127.0.0.1:{port}"));
    let file = dir.path().join("manipulator.toml");
    std::fs::write(&file, &text).unwrap();
    let rec = dir.path().join("loop.mcap");
    let run = start(&[
        "run",
        file.to_str().unwrap(),
        "--frames",
        "120",
        "--instance",
        "manipulator-loop",
        "--record",
        rec.to_str().unwrap(),
        "--edges",
        "triangulate/targets",
        "manipulator-bridge/state",
    ]);
    let stream = connect_to_bridge(port, Duration::from_secs(30));
    stream
        .set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();
    let mut w = stream.try_clone().unwrap();
    let mut lines = std::io::BufReader::new(stream).lines();
    let mut next_event = |want: &[&str]| -> serde_json::Value {
        loop {
            let l = lines
                .next()
                .expect("the bridge closed")
                .expect("a line in time");
            let v: serde_json::Value = serde_json::from_str(&l).unwrap();
            let e = v["event"].as_str().unwrap().to_string();
            if want.contains(&e.as_str()) {
                return v;
            }
            assert!(e != "error", "{l}");
        }
    };
    let scene = next_event(&["scene"]);
    let cell = scene["cells"][0]["id"].as_u64().unwrap();
    // A malformed line gets an error on this connection, which stays usable.
    w.write_all(b"{\"cmd\": \"dance\"}\n").unwrap();
    let e = next_event(&["error"]);
    assert!(
        e["message"]
            .as_str()
            .unwrap()
            .contains("unknown command 'dance'"),
        "{e}"
    );
    writeln!(w, "{{\"cmd\": \"approach\", \"cell\": {cell}}}").unwrap();
    let plan = next_event(&["plan", "blocked"]);
    assert_eq!(plan["event"], "plan", "{plan}");
    let arrived = next_event(&["arrived", "blocked"]);
    assert_eq!(arrived["event"], "arrived", "{arrived}");
    assert_eq!(arrived["plan"]["goal"], "approach");
    assert!(arrived["error_um"].as_f64().unwrap() < 1.0, "{arrived}");
    w.write_all(b"{\"cmd\": \"retract\"}\n").unwrap();
    let back = next_event(&["arrived", "blocked"]);
    assert_eq!(back["event"], "arrived", "{back}");
    assert_eq!(back["plan"]["goal"], "retract");
    drop(w);
    let out = finish(run, Duration::from_secs(90));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    // What the recording says.
    let params = BridgeParams::from_table(
        text.parse::<toml::Table>().unwrap()["node"]
            .as_array()
            .unwrap()
            .last()
            .unwrap()["params"]
            .as_table()
            .unwrap(),
    )
    .unwrap();
    let cfg = params.config().planner;
    let u = cfg.pipette.axis();
    let mut scenes = std::collections::HashMap::new();
    let mut states = Vec::new();
    for m in recorder::file::EdgeReader::open(&rec, None).unwrap() {
        let m = m.unwrap();
        if m.edge == "triangulate/targets" {
            let t: Targets = serde_json::from_slice(&m.payload).unwrap();
            scenes.insert(
                t.frame,
                Scene::from_targets(&t, manipulator_bridge::scene::UNTRUSTED_HEIGHT).unwrap(),
            );
        } else {
            let s: ManipulatorState = serde_json::from_slice(&m.payload).unwrap();
            states.push(s);
        }
    }
    assert!(states.len() > 60, "{} states", states.len());
    // The state is in the camera frame; the planner's scenes have the third coordinate up.
    use manipulator_bridge::geom::flip;
    let mut approach = states
        .iter()
        .rev()
        .filter_map(|s| s.plan.clone())
        .find(|p| p.goal == "approach")
        .expect("an approach plan");
    let mut retract = states.iter().rev().find_map(|s| s.plan.clone()).unwrap();
    assert_eq!(retract.goal, "retract");
    approach.end = flip(approach.end);
    retract.end = flip(retract.end);
    let samples: Vec<(u64, [f64; 3])> = states
        .iter()
        .flat_map(|s| {
            s.trajectory
                .iter()
                .map(|t| (s.frame, flip([t[1], t[2], t[3]])))
        })
        .collect();
    assert!(samples.len() > 50, "{} samples", samples.len());
    // Arrival: the tip stood within 1 µm of the injection point.
    let closest = samples
        .iter()
        .map(|(_, p)| dist(*p, approach.end))
        .fold(f64::INFINITY, f64::min);
    assert!(closest < 1.0, "closest approach {closest} µm");
    let target_of = |scene: &Scene| {
        scene
            .nearest([approach.end[0], approach.end[1]], 15.0)
            .map(|c| c.id)
    };
    // Clearance: every sample, against the cells of its frame other than the target (the
    // cell nearest the injection point) and the objects taken for the pipette itself.
    let mut checked = 0;
    for (frame, tip) in &samples {
        let state = states.iter().find(|s| s.frame == *frame).unwrap();
        let scene = &scenes[frame];
        let target = target_of(scene);
        for c in &scene.cells {
            if Some(c.id) == target || state.ignored.contains(&c.id) {
                continue;
            }
            let d = c.prism.dist_segment(*tip, u, cfg.pipette.length);
            assert!(
                d >= cfg.clearance - 0.1,
                "frame {frame}: tip {tip:?} is {d} µm from cell {}",
                c.id
            );
            checked += 1;
        }
        assert!(cfg.workspace.contains(*tip));
    }
    assert!(checked > 100, "{checked} checks");
    // Out: the last sample is the retract's end, above every cell top by the clearance.
    let last = samples.last().unwrap().1;
    assert!(
        dist(last, retract.end) < 1e-6,
        "{last:?} vs {:?}",
        retract.end
    );
    // Above every other cell of every frame (objects taken for the pipette itself are not
    // cells) and above the target as measured when the approach was planned: once the
    // pipette is over it, the target's image holds the pipette's too, and its measured top
    // rises towards the tip.
    let planned = &scenes[&approach.frame];
    let target_top = planned
        .cells
        .iter()
        .find(|c| Some(c.id) == target_of(planned))
        .expect("the target in the plan's scene")
        .top;
    let tallest = states
        .iter()
        .flat_map(|st| {
            let scene = &scenes[&st.frame];
            let target = target_of(scene);
            scene
                .cells
                .iter()
                .filter(move |c| Some(c.id) != target && !st.ignored.contains(&c.id))
                .map(|c| c.top)
        })
        .fold(target_top, f64::max);
    assert!(
        last[2] > tallest + cfg.clearance,
        "{last:?} below {tallest}"
    );
}

/// The default launch file with its capture reading the pair `left`/`right` from files, a
/// lossless entrance (so that every frame is measured) and the bridge on a free port.
fn default_graph_on(left: &Path, right: &Path) -> String {
    let text =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("launch.toml")).unwrap();
    let capture = "params = { source = \"synthetic\", width = 1280, height = 1024, cells = 10, seed = 1, repeat = 30, fps = 30 }";
    assert!(text.contains(capture), "the default capture changed");
    text.replace(
        capture,
        &format!(
            "params = {{ source = \"files\", left = \"{}\", right = \"{}\", repeat = true }}",
            left.display(),
            right.display()
        ),
    )
    .replace("127.0.0.1:7878", "127.0.0.1:0")
    .replace(
        "inputs = { frame = { from = \"capture/frame\", depth = 1 } }",
        "inputs = { frame = { from = \"capture/frame\", depth = 1, overflow = \"block\" } }",
    )
}

/// Asserts two JSON values equal but for numbers, which may differ by `tol` (absolute
/// below 1, relative above).
fn assert_close(a: &serde_json::Value, b: &serde_json::Value, tol: f64, at: &str) {
    use serde_json::Value;
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            assert!(
                (x - y).abs() <= tol * x.abs().max(y.abs()).max(1.0),
                "{at}: {x} vs {y}"
            );
        }
        (Value::Array(x), Value::Array(y)) => {
            assert_eq!(x.len(), y.len(), "{at}: lengths");
            for (k, (p, q)) in x.iter().zip(y).enumerate() {
                assert_close(p, q, tol, &format!("{at}[{k}]"));
            }
        }
        (Value::Object(x), Value::Object(y)) => {
            assert_eq!(
                x.keys().collect::<Vec<_>>(),
                y.keys().collect::<Vec<_>>(),
                "{at}: keys"
            );
            for (k, p) in x {
                assert_close(p, &y[k], tol, &format!("{at}.{k}"));
            }
        }
        _ => assert_eq!(a, b, "{at}"),
    }
}

#[test]
fn the_default_graph_measures_the_cells_of_reconstruct_cells_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    let out = run(&[
        "synth",
        "-o",
        scene.to_str().unwrap(),
        "--width",
        "640",
        "--height",
        "480",
        "--cells",
        "6",
        "--seed",
        "4",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (l, r) = (scene.join("left.png"), scene.join("right.png"));
    // The graph as processes, its cells and final map recorded.
    let file = dir.path().join("default-on-files.toml");
    std::fs::write(&file, default_graph_on(&l, &r)).unwrap();
    let rec = dir.path().join("run.mcap");
    let out = run(&[
        "run",
        file.to_str().unwrap(),
        "--frames",
        "2",
        "--record",
        rec.to_str().unwrap(),
        "--edges",
        "triangulate/*",
        "segment/labels",
        "--instance",
        &format!("cells{}", std::process::id()),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The one-shot command on the same pair.
    let o = dir.path().join("reconstruct");
    let out = run(&[
        "reconstruct",
        l.to_str().unwrap(),
        r.to_str().unwrap(),
        "-o",
        o.to_str().unwrap(),
        "--cells",
        "--calibration",
        scene.join("calibration.toml").to_str().unwrap(),
        "--min-disparity",
        "-4",
        "--max-disparity",
        "12",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(o.join("cells.json")).unwrap()).unwrap();
    let want = report["cells"].as_array().unwrap();
    assert!(want.len() >= 5, "{report}");
    let msgs = recorded(&rec);
    for frame in 0..2u64 {
        let (h, p) = &msgs[&("triangulate/targets".to_string(), frame)];
        let t: schemas::Targets = schemas::Message::decode(h, p).unwrap();
        let got = serde_json::to_value(&t.cells).unwrap();
        let plane = serde_json::to_value(t.substrate).unwrap();
        if frame == 0 {
            // Every field of every cell, floats to the bit (JSON keeps f64 exactly).
            assert_eq!(got.as_array().unwrap(), want, "frame {frame}");
            assert_eq!(plane, report["substrate_plane"]);
        } else {
            // The graph tracks the substrate: the second frame's plane is fitted on every
            // second row from the first's and combined with it, so it ends within its
            // formal error of the frame's own whole fit, and the cells move by as little.
            let tracked = t.substrate.expect("a tracked plane");
            let own: schemas::DisparityPlane =
                serde_json::from_value(report["substrate_plane"].clone()).unwrap();
            for [x, y] in [[0.0, 0.0], [639.0, 0.0], [0.0, 479.0], [639.0, 479.0]] {
                let off = (tracked.at(x, y) - own.at(x, y)).abs();
                assert!(off <= 2.0 * own.std, "plane at ({x}, {y}): {off} px off");
            }
            assert_close(&got, &report["cells"], 1e-3, &format!("frame {frame}"));
        }
        // The final map is valid only on the cells and their 8 px rings: nowhere farther
        // than 8 px (and the matcher's window) from a segmented pixel.
        let (h, p) = &msgs[&("triangulate/disparity".to_string(), frame)];
        let d: schemas::Disparity = schemas::Message::decode(h, p).unwrap();
        let (h, p) = &msgs[&("segment/labels".to_string(), frame)];
        let labels: schemas::Labels = schemas::Message::decode(h, p).unwrap();
        let (w, ht) = (d.map.width, d.map.height);
        let near_cell = |x: usize, y: usize| {
            (y.saturating_sub(8)..(y + 9).min(ht))
                .any(|v| (x.saturating_sub(8)..(x + 9).min(w)).any(|u| *labels.left.get(u, v) != 0))
        };
        let mut valid = 0;
        for y in 0..ht {
            for x in 0..w {
                if d.map.get(x, y).is_finite() {
                    valid += 1;
                    assert!(
                        near_cell(x, y),
                        "frame {frame}: ({x}, {y}) is valid far from any cell"
                    );
                }
            }
        }
        let share = valid as f64 / (w * ht) as f64;
        assert!(share > 0.02 && share < 0.5, "valid share {share}");
    }
    // The one-shot command's map is the same map.
    let d = formats::read_pfm(&o.join("disparity.pfm"), "map").unwrap();
    let (h, p) = &msgs[&("triangulate/disparity".to_string(), 0)];
    let g: schemas::Disparity = schemas::Message::decode(h, p).unwrap();
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert!(bits(&d.data) == bits(&g.map.data));
}

/// `text` read as the launch file `custom.toml` and checked against `kinds`: the graph, or
/// the validator's errors as one text.
fn custom(text: &str, kinds: &runtime::Registry) -> Result<runtime::launch::Graph, String> {
    runtime::launch::LaunchFile::parse(Path::new("custom.toml"), text)
        .unwrap()
        .validate(kinds)
        .map_err(|e| e.to_string())
}

#[test]
fn a_node_kind_from_outside_the_built_in_crates_runs_in_a_graph() {
    // One registry line adds the example's kind to the built-in ones; the launch file names
    // it like any other kind, and the validator checks its ports and params.
    let kinds = pipelines::registry::builtin().task::<invert_node::Invert>();
    let text = r#"
[[node]]
id = "capture"
kind = "capture"
params = { width = 160, height = 120, cells = 2, seed = 3 }

[[node]]
id = "invert"
kind = "invert"
inputs = { frame = "capture/frame" }
params = { level = 200 }

[[node]]
id = "segment"
kind = "segment"
inputs = { frame = "invert/frame" }
"#;
    let graph = custom(text, &kinds).unwrap();
    let log = InProcess::new(&graph, &kinds).unwrap().run(2).unwrap();
    let key = |n: &str, p: &str| (n.to_string(), p.to_string());
    for (c, i) in log[&key("capture", "frame")]
        .iter()
        .zip(&log[&key("invert", "frame")])
    {
        let (c, i): (schemas::StereoFrame, schemas::StereoFrame) = (
            schemas::Message::decode(&c.0, &c.1).unwrap(),
            schemas::Message::decode(&i.0, &i.1).unwrap(),
        );
        assert!(
            c.left
                .data
                .iter()
                .zip(&i.left.data)
                .all(|(a, b)| 200u8.saturating_sub(*a) == *b)
        );
        assert!(
            c.right
                .data
                .iter()
                .zip(&i.right.data)
                .all(|(a, b)| 200u8.saturating_sub(*a) == *b)
        );
    }
    assert_eq!(log[&key("segment", "cells")].len(), 2);
    // Its params are checked like a built-in node's.
    let bad = text.replace("level = 200", "level = 0, colour = true");
    let e = custom(&bad, &kinds).unwrap_err();
    assert!(
        e.contains("custom.toml:11: node 'invert': bad params: unknown field `colour`"),
        "{e}"
    );
}

#[test]
fn a_second_node_kind_is_one_crate_and_one_registry_line() {
    // examples/cell-filter-node depends on node-api, schemas and serde only; one line adds
    // its kind, and the launch validator checks its ports' kinds with their lines.
    let kinds = pipelines::registry::builtin().task::<cell_filter_node::CellFilter>();
    let text = r#"
[[node]]
id = "capture"
kind = "capture"
params = { width = 320, height = 240, cells = 6, seed = 5 }

[[node]]
id = "segment"
kind = "segment"
inputs = { frame = "capture/frame" }

[[node]]
id = "filter"
kind = "cell-filter"
inputs = { cells = "segment/cells" }
params = { min_area = 400, max_area = 2500 }
"#;
    let graph = custom(text, &kinds).unwrap();
    let log = InProcess::new(&graph, &kinds).unwrap().run(2).unwrap();
    let key = |n: &str, p: &str| (n.to_string(), p.to_string());
    let (mut kept, mut dropped) = (0, 0);
    for (c, f) in log[&key("segment", "cells")]
        .iter()
        .zip(&log[&key("filter", "cells")])
    {
        let (c, f): (schemas::CellLists, schemas::CellLists) = (
            schemas::Message::decode(&c.0, &c.1).unwrap(),
            schemas::Message::decode(&f.0, &f.1).unwrap(),
        );
        for (all, some) in [(&c.left, &f.left), (&c.right, &f.right)] {
            let want: Vec<&schemas::Cell> = all
                .iter()
                .filter(|c| (400..=2500).contains(&c.area))
                .collect();
            assert_eq!(some.iter().collect::<Vec<_>>(), want);
            kept += some.len();
            dropped += all.len() - some.len();
        }
    }
    // The scene's cells span the range's both sides: the filter has work to do.
    assert!(kept > 0 && dropped > 0, "kept {kept}, dropped {dropped}");
    // A port fed the wrong message is refused with its line.
    let bad = text.replace("segment/cells", "segment/labels");
    let e = custom(&bad, &kinds).unwrap_err();
    assert!(
        e.contains("custom.toml:15: node 'filter' reads 'segment/labels', which carries Labels, but expects CellList"),
        "{e}"
    );
}

/// A node stopped from outside with SIGTERM (it ends cleanly, or fails on its way out) ends
/// a run without a restart policy with the summary and the reason; it used to leave the
/// graph waiting for that node's frames for ever (issue 19 #2).
#[test]
fn a_node_stopped_from_outside_ends_the_run_with_the_summary_and_the_reason() {
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/graph/small.toml");
    let instance = format!("sigterm{}", std::process::id());
    // Enough frames that the run cannot end by itself before the signal lands.
    let sup = start_run(&file, 100_000, &instance);
    let segment = wait_node_pid(&sup, "segment");
    // Let it take some frames first.
    std::thread::sleep(Duration::from_millis(1500));
    // SAFETY: kill(2) on a pid of this test's own run.
    unsafe {
        libc::kill(segment as i32, libc::SIGTERM);
    }
    let out = finish(sup, Duration::from_secs(60));
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert_eq!(out.status.code(), Some(2), "{stdout}\n{stderr}");
    assert!(
        stderr.contains("the run stopped early: node 'segment' failed"),
        "{stderr}"
    );
    assert!(
        stdout.contains(" frame(s) of 100000"),
        "no summary: {stdout}"
    );
}

/// The embedded default graph (lossless after its entry, depth 1), small, its source as fast
/// as it goes (the graph is saturated), every node restarted on failure: after kill -9 of a
/// node that others join with (match, segment, then triangulate) the controller gets scenes
/// again. After the first restart the graph used to stand still: the joining node held
/// frames whose partners had died with the killed node (issue 19 #1).
#[test]
fn the_default_graph_keeps_moving_through_restarts_of_joined_nodes() {
    use std::io::BufRead;
    let port = free_port();
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("launch.toml"))
        .unwrap()
        .replace(
            "width = 1280, height = 1024, cells = 10, seed = 1, repeat = 30, fps = 30 }",
            "width = 320, height = 256, cells = 4, seed = 1, repeat = 30 }",
        )
        .replace("127.0.0.1:7878", &format!("127.0.0.1:{port}"));
    assert!(text.contains("cells = 4") && text.contains(&format!(":{port}")));
    let restarting = with_restart(
        &text,
        "restart = { policy = \"on-failure\", max = 3, backoff_ms = 200 }\n",
    );
    assert_eq!(restarting.matches("restart = {").count(), 9);
    let file = dir.path().join("restarts.toml");
    std::fs::write(&file, &restarting).unwrap();
    let instance = format!("restarts{}", std::process::id());
    // Until told to stop.
    let sup = start_run(&file, 1_000_000, &instance);
    let stream = connect_to_bridge(port, Duration::from_secs(30));
    let (tx, scenes) = std::sync::mpsc::channel::<u64>();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(stream).lines() {
            let Ok(line) = line else { break };
            let scene: serde_json::Value = serde_json::from_str(&line).unwrap();
            if tx.send(scene["frame"].as_u64().unwrap()).is_err() {
                break;
            }
        }
    });
    // Twenty scenes within a minute each, or the graph stands still: more than the frames
    // that the queues and joins after the killed node hold, which reach the controller
    // even when nothing moves again.
    let moving = |after: &str| {
        let mut last = Instant::now();
        let mut longest = Duration::ZERO;
        for _ in 0..20 {
            if scenes.recv_timeout(Duration::from_secs(60)).is_err() {
                panic!("no scene for 60 s after {after}");
            }
            longest = longest.max(last.elapsed());
            last = Instant::now();
        }
        longest
    };
    moving("the start");
    for victim in ["match", "segment", "triangulate"] {
        let pid = wait_node_pid(&sup, victim);
        // The scenes sent before the kill.
        while scenes.try_recv().is_ok() {}
        // SAFETY: kill(2) on a pid of this test's own run.
        unsafe {
            libc::kill(pid as i32, libc::SIGKILL);
        }
        let gap = moving(&format!("the restart of {victim}"));
        eprintln!("killed {victim}: the longest wait for a scene after it was {gap:?}");
    }
    // SAFETY: kill(2) on the supervisor this test started.
    unsafe {
        libc::kill(sup.id() as i32, libc::SIGTERM);
    }
    let out = finish(sup, Duration::from_secs(60));
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(out.status.success(), "{stdout}\n{stderr}");
    for victim in ["match", "segment", "triangulate"] {
        assert!(
            stderr.contains(&format!(
                "[{victim}] exited (signal: 9 (SIGKILL)); restart 1 of 3"
            )),
            "{victim}: {stderr}"
        );
    }
    assert!(
        stdout.contains(" frame(s) of 1000000"),
        "no summary: {stdout}"
    );
}

/// One chaos run: the small lossless graph, every node under a restart policy, `frames`
/// frames, and `kills` SIGKILLs of random nodes at random frames (seeded by `seed`). The run
/// must complete, every frame accounted for at the graph's end (arrived, dropped or lost
/// upstream), no process and no shared memory of it left. Returns the longest wait between
/// two scenes at the bridge (a restart's stall; a frame takes about 25 ms here).
fn chaos_run(frames: u64, kills: usize, seed: u64) -> Duration {
    use rand::{Rng, SeedableRng};
    use std::io::BufRead;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let port = free_port();
    let dir = tempfile::tempdir().unwrap();
    let small = small_graph()
        // Small frames from a camera of 100 frames/s: a thousand of them take ten seconds
        // whatever the machine. Unpaced, the graph took 1000 frames in 3 s, faster than
        // killed nodes came back under load: the capture ran out of frames while they
        // restarted, the last few hundred were lost and no scene came for the test to see
        // (a run that had ended, read as a stall).
        .replace(
            "width = 320, height = 240, cells = 3",
            "width = 192, height = 128, cells = 2, fps = 100",
        )
        .replace("127.0.0.1:0", &format!("127.0.0.1:{port}"));
    let text = with_restart(
        &small,
        "restart = { policy = \"on-failure\", max = 30, backoff_ms = 50 }\n",
    );
    let nodes = [
        "capture",
        "segment",
        "match",
        "validate",
        "postprocess",
        "triangulate",
        "manipulator-bridge",
    ];
    assert_eq!(text.matches("restart = {").count(), nodes.len());
    assert!(text.contains("cells = 2, fps = 100") && text.contains(&format!(":{port}")));
    let file = dir.path().join("chaos.toml");
    std::fs::write(&file, &text).unwrap();
    let instance = format!("chaos{}-{seed}", std::process::id());
    let sup = start_run(&file, frames, &instance);
    // The scenes' frame numbers, read from the bridge (reconnecting when it is the one
    // killed) until the run is over.
    let (tx, scenes) = std::sync::mpsc::channel::<u64>();
    let over = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let reader = {
        let over = over.clone();
        std::thread::spawn(move || {
            while !over.load(std::sync::atomic::Ordering::Relaxed) {
                let Ok(stream) = std::net::TcpStream::connect(("127.0.0.1", port)) else {
                    std::thread::sleep(Duration::from_millis(20));
                    continue;
                };
                stream
                    .set_read_timeout(Some(Duration::from_millis(500)))
                    .unwrap();
                let mut lines = std::io::BufReader::new(stream);
                let mut line = String::new();
                loop {
                    line.clear();
                    match lines.read_line(&mut line) {
                        Ok(0) => break,
                        Ok(_) => {
                            let scene: serde_json::Value = serde_json::from_str(&line).unwrap();
                            if let Some(f) = scene["frame"].as_u64() {
                                let _ = tx.send(f);
                            }
                        }
                        Err(e)
                            if matches!(
                                e.kind(),
                                std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                            ) =>
                        {
                            if over.load(std::sync::atomic::Ordering::Relaxed) {
                                return;
                            }
                        }
                        Err(_) => break,
                    }
                }
            }
        })
    };
    let mut at: Vec<u64> = (0..kills)
        .map(|_| rng.random_range(20..frames.saturating_sub(40).max(21)))
        .collect();
    at.sort_unstable();
    // Until the first scene, the graph is starting, not stalled.
    let start_wait = Instant::now();
    while scenes.recv_timeout(Duration::from_secs(1)).is_err() {
        assert!(
            start_wait.elapsed() < Duration::from_secs(120),
            "no first scene"
        );
    }
    let mut seen = 0u64;
    let mut longest = Duration::ZERO;
    let mut last = Instant::now();
    let mut killed: Vec<&str> = Vec::new();
    let mut delivered: Vec<u64> = Vec::new();
    // False when no scene came for 60 s: the graph stands still.
    let mut next = |seen: &mut u64| match scenes.recv_timeout(Duration::from_secs(60)) {
        Ok(f) => {
            delivered.push(f);
            *seen = (*seen).max(f);
            longest = longest.max(last.elapsed());
            last = Instant::now();
            true
        }
        Err(_) => false,
    };
    let mut stalled = false;
    let mut pids: Vec<u32> = Vec::new();
    'kills: for &frame in &at {
        while seen < frame {
            if !next(&mut seen) {
                stalled = true;
                break 'kills;
            }
        }
        let victim = nodes[rng.random_range(0..nodes.len())];
        // Not a process killed before, nor one not yet reaped (a second kill of the same
        // node in quick succession found the first's zombie).
        let pid = wait_live_node_pid(&sup, victim, &pids, Duration::from_secs(30));
        // SAFETY: kill(2) on a node process of this test's own run.
        unsafe {
            libc::kill(pid as i32, libc::SIGKILL);
        }
        pids.push(pid);
        killed.push(victim);
    }
    // The stall after the last kill, too (kills land at least 40 frames before the end).
    while !stalled && seen + 30 < frames {
        stalled = !next(&mut seen);
    }
    if stalled {
        // What the supervisor and its nodes said, for the failure.
        // SAFETY: kill(2) on the supervisor this test started.
        unsafe {
            libc::kill(sup.id() as i32, libc::SIGTERM);
        }
    }
    let out = finish(sup, Duration::from_secs(300));
    over.store(true, std::sync::atomic::Ordering::Relaxed);
    reader.join().unwrap();
    delivered.extend(scenes.try_iter());
    // A restarted source goes on after its predecessor's last frame, never from an earlier
    // one: no frame number reaches the bridge twice.
    delivered.sort_unstable();
    let twice: Vec<u64> = delivered
        .windows(2)
        .filter(|w| w[0] == w[1])
        .map(|w| w[0])
        .collect();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(
        !stalled,
        "no scene for 60 s at frame {seen} after killing {killed:?} (seed {seed})\n{stdout}\n{stderr}"
    );
    assert!(
        out.status.success(),
        "seed {seed}, killed {killed:?}\n{stdout}\n{stderr}"
    );
    assert!(
        twice.is_empty(),
        "frames {twice:?} reached the bridge twice (seed {seed}, killed {killed:?})"
    );
    assert_eq!(
        stderr
            .matches("exited (signal: 9 (SIGKILL)); restart")
            .count(),
        kills,
        "seed {seed}, killed {killed:?}\n{stderr}"
    );
    // Every frame the capture offered is accounted for at the graph's end: it reached the
    // bridge, or the edge into it counts it as dropped or as lost upstream.
    let done = frames_done(&stdout, frames);
    let edge = "triangulate/targets → manipulator-bridge.targets";
    let (dropped, missing) = edge_figures(&stdout, edge);
    let (made, _) = node_frames_in(&stdout, "capture");
    let capture_kills = killed.iter().filter(|k| **k == "capture").count() as u64;
    assert!(
        made <= frames && made + capture_kills >= frames,
        "capture made {made} of {frames} with {capture_kills} kills (seed {seed})\n{stdout}"
    );
    assert_eq!(
        done + dropped + missing,
        frames,
        "seed {seed}, killed {killed:?}\n{stdout}"
    );
    assert_nothing_left(&instance);
    eprintln!(
        "chaos seed {seed}: {done} of {frames} frames through, {missing} lost, {dropped} dropped; killed {killed:?}; longest wait for a scene after a kill {longest:?}"
    );
    longest
}

/// Issue 19's chaos test: a 1000-frame run with 20 random kills across all nodes completes
/// with every frame accounted for. `CHAOS_RUNS=10` repeats it with ten seeds (the note's
/// figure); `CHAOS_SEED` picks the first seed.
#[test]
fn twenty_random_kills_across_the_graph_lose_no_frame_unaccounted() {
    let _heavy = heavy();
    let runs: u64 = std::env::var("CHAOS_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1);
    let first: u64 = std::env::var("CHAOS_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1);
    for seed in first..first + runs {
        chaos_run(1000, 20, seed);
    }
}

/// Issue 22's overrides: `run` without a launch file runs the default graph built into the
/// program, from a directory with nothing in it; `--set` changes a node's parameter (here
/// the bridge's port, so that two default graphs run side by side, each its own instance);
/// a bad override is one clear error before anything starts.
#[test]
fn the_built_in_graph_runs_anywhere_and_set_overrides_its_parameters() {
    let _heavy = heavy();
    let empty = tempfile::tempdir().unwrap();
    let (p1, p2) = (free_port(), free_port());
    let start = |instance: &str, port: u16| {
        std::process::Command::new(bin())
            .current_dir(empty.path())
            .args(["run", "--frames", "3", "--instance", instance])
            .args([
                "--set",
                &format!("manipulator-bridge.listen=127.0.0.1:{port}"),
            ])
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap()
    };
    let (a, b) = (
        start(&format!("set-a-{p1}"), p1),
        start(&format!("set-b-{p2}"), p2),
    );
    for child in [a, b] {
        let out = child.wait_with_output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{err}");
        assert!(!err.contains("already in use"), "{err}");
    }
    assert_eq!(
        std::fs::read_dir(empty.path()).unwrap().count(),
        0,
        "nothing written"
    );
    let bad = |set: &str, needle: &str| {
        let out = std::process::Command::new(bin())
            .current_dir(empty.path())
            .args(["run", "--frames", "1", "--set", set])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{set}: {err}");
        assert!(
            err.contains(needle) && !err.contains("panicked"),
            "{set}: {err}"
        );
    };
    bad("nope.listen=1", "no node 'nope'");
    bad("manipulator-bridge.max_speed=-5", "max_speed");
    bad("manipulator-bridge.no_such_param=1", "no_such_param");
    bad("manipulator-bridge", "give NODE.PARAM=VALUE");
}

/// The number after `key` in `text` (the first word after it that reads as one).
fn number_after(text: &str, key: &str) -> f64 {
    let at = text
        .find(key)
        .unwrap_or_else(|| panic!("'{key}' not in:\n{text}"));
    text[at + key.len()..]
        .split_whitespace()
        .find_map(|w| w.parse::<f64>().ok())
        .unwrap_or_else(|| panic!("no number after '{key}' in:\n{text}"))
}

#[test]
fn top_and_topic_measure_a_running_graph_at_the_rate_its_summary_reports() {
    let _heavy = heavy();
    let instance = format!("live-{}", std::process::id());
    let graph = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/graph/small.toml");
    let run = Command::new(bin())
        .args(["run", graph.to_str().unwrap(), "--frames", "260"])
        .args(["--set", "capture.fps=20", "--instance", &instance])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let tool = |args: &[&str]| {
        let out = Command::new(bin())
            .args(args)
            .args(["--instance", &instance])
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(
            out.status.success(),
            "{args:?}: {text}{}",
            String::from_utf8_lossy(&out.stderr)
        );
        text
    };
    // Past the start: the figures are over the window, not since the start.
    std::thread::sleep(Duration::from_secs(3));
    let top = tool(&["top", "--once", "--interval", "2"]);
    let list = tool(&["topic", "list"]);
    let hz = tool(&[
        "topic",
        "hz",
        "capture/frame",
        "--window",
        "2",
        "--count",
        "2",
    ]);
    let echo = tool(&["topic", "echo", "triangulate/targets", "--count", "3"]);
    let out = run.wait_with_output().unwrap();
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let sustained = number_after(&summary, "sustained");
    assert!(sustained > 10.0, "{summary}");
    let near = |what: &str, r: f64| {
        assert!(
            (r / sustained - 1.0).abs() <= 0.1,
            "{what}: {r:.2} against the summary's {sustained:.2} frames/s\n{top}\n{hz}"
        )
    };
    // top: the capture node's frames/s and an edge's messages/s.
    let capture_row = top.lines().find(|l| l.starts_with("capture ")).unwrap();
    // node, kind, state, restarts, frames, frames/s, …
    let columns: Vec<&str> = capture_row.split_whitespace().collect();
    assert_eq!(columns[2], "running", "{top}");
    near("top capture", columns[5].parse().unwrap());
    let edge_row = top
        .lines()
        .find(|l| l.starts_with("capture/frame → segment.frame"))
        .unwrap();
    near("top edge", number_after(edge_row, "segment.frame"));
    assert!(top.contains(&instance), "{top}");
    // hz: every report.
    let reports: Vec<&str> = hz.lines().collect();
    assert_eq!(reports.len(), 2, "{hz}");
    for r in reports {
        near("topic hz", number_after(r, "capture/frame:"));
    }
    // list: every edge with its message and readers.
    assert!(
        list.lines().any(|l| l.starts_with("capture/frame")
            && l.contains("stereo-frame")
            && l.contains("segment.frame, match.frame, triangulate.frame")),
        "{list}"
    );
    // echo: three headers in frame order, then the summary.
    let frames: Vec<u64> = echo
        .lines()
        .filter(|l| l.starts_with("frame "))
        .map(|l| number_after(l, "frame") as u64)
        .collect();
    assert_eq!(frames.len(), 3, "{echo}");
    assert!(frames.windows(2).all(|w| w[1] == w[0] + 1), "{echo}");
    assert!(echo.contains("targets"), "{echo}");
    assert!(echo.contains("3 message(s) in"), "{echo}");
    // A run that is not there: one clear error.
    let none = Command::new(bin())
        .args(["top", "--once", "--instance", "no-such-run"])
        .output()
        .unwrap();
    assert_eq!(none.status.code(), Some(2));
    let err = String::from_utf8_lossy(&none.stderr);
    assert!(
        err.contains("no graph is running as 'no-such-run'"),
        "{err}"
    );
}

/// A pseudo-terminal pair: (the side a terminal program reads, the side it writes to).
fn pty() -> (std::fs::File, std::fs::File) {
    use std::os::fd::FromRawFd;
    let (mut master, mut slave) = (0, 0);
    // SAFETY: openpty writes the two descriptors it opens into the integers given; the
    // name, termios and window-size arguments may be null.
    let rc = unsafe {
        libc::openpty(
            &mut master,
            &mut slave,
            std::ptr::null_mut(),
            std::ptr::null(),
            std::ptr::null(),
        )
    };
    assert_eq!(rc, 0, "openpty");
    // SAFETY: both descriptors were just opened by openpty and are owned by nobody else.
    unsafe {
        (
            std::fs::File::from_raw_fd(master),
            std::fs::File::from_raw_fd(slave),
        )
    }
}

#[test]
fn run_shows_a_progress_line_on_a_terminal_and_quiet_turns_it_off() {
    let _heavy = heavy();
    let graph = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/graph/small.toml");
    let on_terminal = |quiet: bool| {
        let (mut master, slave) = pty();
        let mut cmd = Command::new(bin());
        cmd.args(["run", graph.to_str().unwrap(), "--frames", "40"])
            .args(["--set", "capture.fps=20"])
            .stdout(Stdio::piped())
            .stderr(Stdio::from(slave));
        if quiet {
            cmd.arg("--quiet");
        }
        let child = cmd.spawn().unwrap();
        // The parent's copy of the terminal's writing side went into the command; reading
        // ends (EIO) once the child's copies close.
        let reader = std::thread::spawn(move || {
            let mut all = Vec::new();
            let _ = std::io::Read::read_to_end(&mut master, &mut all);
            String::from_utf8_lossy(&all).into_owned()
        });
        let out = child.wait_with_output().unwrap();
        drop(cmd);
        assert!(out.status.success());
        let terminal = reader.join().unwrap();
        (terminal, String::from_utf8_lossy(&out.stdout).into_owned())
    };
    let (terminal, stdout) = on_terminal(false);
    assert!(terminal.contains(" frame(s) of 40 · "), "{terminal:?}");
    assert!(
        terminal.contains(" frames/s · 0 dropped · 0 restart(s)"),
        "{terminal:?}"
    );
    // The summary goes to stdout as before, without the line.
    assert!(stdout.contains("40 frame(s) of 40 in"), "{stdout}");
    assert!(!stdout.contains(" · "), "{stdout}");
    let (terminal, _) = on_terminal(true);
    assert!(!terminal.contains("frame(s)"), "{terminal:?}");
}

/// Header and payload of every recorded message, the capture clock aside (each run has its
/// own).
type Recorded = Vec<((String, u64), (schemas::FrameHeader, Vec<u8>))>;

fn recorded_content(path: &Path) -> Recorded {
    recorded(path)
        .into_iter()
        .map(|(k, (h, p))| {
            (
                k,
                (
                    schemas::FrameHeader {
                        capture_ns: 0,
                        edge_sequence: 0,
                        ..h
                    },
                    p,
                ),
            )
        })
        .collect()
}

#[test]
fn a_graph_over_two_hosts_runs_in_two_domains_joined_by_the_link_and_delivers_every_frame_whole() {
    let _heavy = heavy();
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/graph/two_hosts.toml");
    let dir = tempfile::tempdir().unwrap();
    let (whole, split) = (dir.path().join("whole.mcap"), dir.path().join("split.mcap"));
    let pid = std::process::id();
    let edges = [
        "rectify/frame",
        "segment/labels",
        "match/left",
        "triangulate/targets",
    ];
    let run = |extra: &[String]| {
        Command::new(bin())
            .args(["run", file.to_str().unwrap(), "--frames", "12", "--quiet"])
            .args(extra)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    };
    let s = |v: &[&str]| v.iter().map(|x| x.to_string()).collect::<Vec<_>>();
    let record = |path: &Path| {
        let mut a = s(&["--record", path.to_str().unwrap(), "--edges"]);
        a.extend(s(&edges));
        a
    };
    // The whole graph on one host, one domain: the reference.
    let mut a = s(&["--instance", &format!("two-whole-{pid}")]);
    a.extend(record(&whole));
    let out = run(&a).wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The same graph as two parts in two domains: nothing of one is visible to the other
    // but through the link, over loopback.
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let instance = format!("two-{pid}");
    let mut b = s(&[
        "--host",
        "workstation",
        "--domain",
        &format!("ws{pid}"),
        "--instance",
        &instance,
        "--listen",
        &endpoint,
    ]);
    b.extend(record(&split));
    let workstation = run(&b);
    let microscope = run(&s(&[
        "--host",
        "microscope",
        "--domain",
        &format!("ms{pid}"),
        "--instance",
        &instance,
        "--connect",
        &endpoint,
    ]));
    let (ws, ms) = (
        workstation.wait_with_output().unwrap(),
        microscope.wait_with_output().unwrap(),
    );
    let text = |o: &Output| {
        format!(
            "{}{}",
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr)
        )
    };
    assert!(ws.status.success(), "workstation: {}", text(&ws));
    assert!(ms.status.success(), "microscope: {}", text(&ms));
    // Each part reports its own nodes; the workstation's end saw every frame.
    let ws_out = String::from_utf8_lossy(&ws.stdout);
    let ms_out = String::from_utf8_lossy(&ms.stdout);
    assert!(ws_out.contains("12 frame(s) of 12"), "{ws_out}");
    assert!(!ws_out.contains("(no report)") && !ms_out.contains("(no report)"));
    assert!(ms_out.lines().any(|l| l.starts_with("match ")), "{ms_out}");
    assert!(
        !ms_out.lines().any(|l| l.starts_with("triangulate ")),
        "{ms_out}"
    );
    // Every frame of every recorded edge, bit for bit as on one host: the images that
    // crossed the link, and what the workstation made of them.
    let (w, p) = (recorded_content(&whole), recorded_content(&split));
    assert_eq!(w.len(), 12 * edges.len());
    assert_eq!(
        w.iter().map(|e| &e.0).collect::<Vec<_>>(),
        p.iter().map(|e| &e.0).collect::<Vec<_>>()
    );
    for (a, b) in w.iter().zip(&p) {
        if a.0.0 == "triangulate/targets" {
            // The cells and substrate, bit for bit; the capture time is the run's own.
            let t = |(h, p): &(schemas::FrameHeader, Vec<u8>)| schemas::Targets {
                capture_ns: 0,
                ..<schemas::Targets as schemas::Message>::decode(h, p).unwrap()
            };
            assert_eq!(t(&a.1), t(&b.1), "{:?} differs across the link", a.0);
            assert!(!t(&a.1).cells.is_empty());
        } else {
            assert!(a == b, "{:?} differs across the link", a.0);
        }
    }
}

/// Sum of the recorded messages' bytes (before compression).
fn recorded_bytes(path: &Path) -> u64 {
    recorder::overview(path)
        .unwrap()
        .channels
        .iter()
        .filter(|c| c.edge.is_some())
        .map(|c| c.bytes)
        .sum()
}

#[test]
fn a_recording_split_into_three_parts_replays_bit_identical_to_an_unsplit_one() {
    let _heavy = heavy();
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/graph/small.toml");
    let dir = tempfile::tempdir().unwrap();
    let p = |name: &str| dir.path().join(name);
    let pid = std::process::id();
    let go = |args: &[&str]| {
        let out = Command::new(bin())
            .args(args)
            .arg("--quiet")
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    let s = |p: &Path| p.to_str().unwrap().to_string();
    // A recording of the graph, then two replays of it recorded: one whole, one split.
    let source = p("source.mcap");
    go(&[
        "run",
        &s(&file),
        "--frames",
        "24",
        "--instance",
        &format!("split-src-{pid}"),
        "--record",
        &s(&source),
    ]);
    let replay = |from: &Path, to: &Path, split: Option<String>, tag: &str| {
        let mut args = vec![
            "replay".to_string(),
            s(from),
            "--rate".into(),
            "max".into(),
            "--instance".into(),
            format!("split-{tag}-{pid}"),
            "--record".into(),
            s(to),
        ];
        if let Some(sz) = split {
            args.extend(["--split".to_string(), sz]);
        }
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        go(&refs)
    };
    let whole = p("whole.mcap");
    replay(&source, &whole, None, "whole");
    // A part holds at least the limit: 40 % of the whole makes two full parts and a third.
    let limit = recorded_bytes(&whole) * 2 / 5;
    let split = p("split.mcap");
    let said = replay(&source, &split, Some(format!("{limit}B")), "split");
    let parts: Vec<PathBuf> = (0..5)
        .map(|i| recorder::file::part_path(&split, i))
        .filter(|f| f.exists())
        .collect();
    assert_eq!(parts.len(), 3, "{said}");
    assert!(!split.exists());
    assert!(said.contains("as 3 part(s)"), "{said}");
    // Read through its name, the parts are one recording: the same messages as the whole.
    let (w, sp) = (recorded(&whole), recorded(&split));
    assert_eq!(w.len(), 24 * 12);
    assert!(
        w == sp,
        "the split recording holds other messages than the whole one"
    );
    // Each part alone is a recording of its own (launch file and cameras first).
    for f in &parts {
        let o = recorder::overview(f).unwrap();
        assert!(o.launch.is_some() && o.error.is_none(), "{}", f.display());
    }
    assert_eq!(
        parts.iter().map(|f| recorded(f).len()).sum::<usize>(),
        w.len()
    );
    // Replayed, both drive the graph to the same outputs, bit for bit.
    let (again_w, again_s) = (p("again-whole.mcap"), p("again-split.mcap"));
    replay(&whole, &again_w, None, "again-whole");
    replay(&split, &again_s, None, "again-split");
    let (a, b) = (recorded(&again_w), recorded(&again_s));
    assert_eq!(a.len(), w.len());
    assert!(
        a == b,
        "the replays of the split and the whole recording differ"
    );
    // A window of the split recording: --start and --duration on its own clock.
    let first = w.values().map(|(h, _)| h.capture_ns).min().unwrap();
    let last = w.values().map(|(h, _)| h.capture_ns).max().unwrap();
    let span = (last - first) as f64 * 1e-9;
    let (start, duration) = (span / 4.0, span / 2.0);
    let window = p("window.mcap");
    go(&[
        "replay",
        &s(&split),
        "--rate",
        "max",
        "--instance",
        &format!("split-window-{pid}"),
        "--start",
        &format!("{start}"),
        "--duration",
        &format!("{duration}"),
        "--record",
        &s(&window),
    ]);
    let want: std::collections::BTreeSet<u64> = w
        .values()
        .map(|(h, _)| h.capture_ns)
        .filter(|&ns| {
            let t = (ns - first) as f64 * 1e-9;
            t >= start && t < start + duration
        })
        .collect();
    let got: std::collections::BTreeSet<u64> = recorded(&window)
        .values()
        .map(|(h, _)| h.capture_ns)
        .collect();
    assert!(!want.is_empty());
    assert_eq!(got, want);
}

#[test]
fn a_replay_pauses_steps_and_resumes_from_the_terminal() {
    let _heavy = heavy();
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/graph/small.toml");
    let dir = tempfile::tempdir().unwrap();
    let source = dir.path().join("source.mcap");
    let pid = std::process::id();
    let out = Command::new(bin())
        .args(["run", file.to_str().unwrap(), "--frames", "40", "--quiet"])
        .args([
            "--set",
            "capture.fps=20",
            "--instance",
            &format!("pause-src-{pid}"),
        ])
        .args(["--record", source.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The replay at recorded speed (2 s), its stdin a terminal.
    let instance = format!("pause-{pid}");
    let (mut keys, slave) = pty();
    let replay = Command::new(bin())
        .args(["replay", source.to_str().unwrap(), "--quiet"])
        .args(["--instance", &instance])
        .stdin(Stdio::from(slave))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let status = runtime::status::StatusReader::open(&instance, Duration::from_secs(20)).unwrap();
    let sent = || loop {
        if let Some(s) = status.next(Duration::from_secs(2)).unwrap() {
            return s
                .node("capture")
                .and_then(|n| n.stats.as_ref())
                .map_or(0, |st| st.frames_out);
        }
    };
    let t0 = Instant::now();
    while sent() < 4 {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "the replay never started"
        );
    }
    let type_line = |keys: &mut std::fs::File, l: &str| {
        use std::io::Write;
        keys.write_all(format!("{l}\n").as_bytes()).unwrap();
        keys.flush().unwrap();
    };
    type_line(&mut keys, "p");
    std::thread::sleep(Duration::from_millis(600));
    let paused = sent();
    std::thread::sleep(Duration::from_millis(1200));
    assert_eq!(sent(), paused, "frames went on while paused");
    assert!(paused < 40, "the replay ended before the pause");
    for _ in 0..3 {
        type_line(&mut keys, "s");
        std::thread::sleep(Duration::from_millis(400));
    }
    assert_eq!(sent(), paused + 3, "three steps, three frames");
    type_line(&mut keys, "p");
    let out = replay.wait_with_output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(text.contains("40 frame(s) of 40"), "{text}");
}
