//! The supervisor: runs a graph as one process per node, forwards their logs, restarts
//! nodes by their policy, stops the graph cleanly and prints the summary.
//!
//! The supervisor writes the graph (rewrites applied) to a file in the system's temporary
//! folder and starts every node with `--graph FILE --id ID --instance NAME`: built-in kinds
//! as `PROGRAM node …` (the program that holds the registry), `exec` nodes as their own
//! program. The file is removed when the run ends.

use crate::launch::{Graph, RestartPolicy, Runner};
use crate::process::NodeArgs;
use crate::stats::{NodeStats, STATS_PREFIX};
use crate::status::{GraphStatus, NodeState};
use std::collections::HashMap;
use std::ffi::OsString;
use std::path::PathBuf;
use std::process::Stdio;
use std::time::{Duration, Instant};
use tokio::io::{AsyncBufReadExt, BufReader};

/// How to run a graph.
#[derive(Clone, Debug)]
pub struct RunOptions {
    /// The program and leading arguments that run a built-in node (`microstereo node`).
    pub builtin: Vec<OsString>,
    /// Stop after this many frames (until Ctrl-C without it).
    pub frames: Option<u64>,
    /// Seconds a node gets to end after SIGTERM before it is killed.
    pub grace: f64,
    /// Names the run's shared memory (default: `run` and the supervisor's pid).
    pub instance: Option<String>,
    /// Show a one-line progress status on stderr while it runs (only on a terminal).
    pub progress: bool,
    /// Run only this host's part of a graph split over hosts (its edges to the other
    /// hosts carried by the link).
    pub host: Option<String>,
    /// Where this part's link listens and connects (default: the graph's `[hosts.HOST]`).
    pub endpoints: Option<hostlink::Endpoints>,
    /// Sources the terminal pauses and steps (`p`, `s` and Enter), when stdin is one.
    pub controls: Vec<String>,
}

/// What a run did: each node's statistics and how long it took.
#[derive(Clone, Debug)]
pub struct RunReport {
    /// Per node id.
    pub stats: HashMap<String, NodeStats>,
    /// Wall-clock time of the whole run.
    pub wall: Duration,
    /// The host whose part ran (`None`: the whole graph).
    pub host: Option<String>,
    /// Why the run ended early: a node failed beyond its restart policy (the stats still
    /// hold what was done until then).
    pub failure: Option<String>,
    /// The signal that stopped the run, if one did.
    pub signal: Option<i32>,
}

/// The graph file of a run, removed when the run ends.
struct GraphFile(PathBuf);

impl Drop for GraphFile {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// One run per instance name on this machine: two runs sharing one would read and write each
/// other's edges and wait on each other for ever. An exclusive `flock` on a file named after
/// the instance, held for the run; the kernel lets go of it however the supervisor ends,
/// SIGKILL included. The file is removed when the run ends (while still locked, so that a
/// run starting meanwhile never holds a lock on a file that is gone: it checks the file it
/// locked is still the one at the path).
struct InstanceLock {
    file: std::fs::File,
    path: PathBuf,
}

impl InstanceLock {
    fn take(instance: &str) -> Result<Self, String> {
        use std::io::{Read, Seek, Write};
        use std::os::fd::AsRawFd;
        use std::os::unix::fs::MetadataExt;
        let path = crate::status::lock_path(instance);
        loop {
            let mut f = std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .create(true)
                .truncate(false)
                .open(&path)
                .map_err(|e| format!("cannot open the instance lock '{}': {e}", path.display()))?;
            // SAFETY: flock on a descriptor this function owns; no memory is involved.
            let rc = unsafe { libc::flock(f.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
            if rc != 0 {
                let mut holder = String::new();
                let _ = f.read_to_string(&mut holder);
                return Err(format!(
                    "instance '{instance}' is in use by another run (supervisor process {}): give this run another --instance, or stop that one",
                    holder.trim()
                ));
            }
            // The run before may have removed the file between our open and our lock.
            let same = match (f.metadata(), std::fs::metadata(&path)) {
                (Ok(a), Ok(b)) => a.ino() == b.ino() && a.dev() == b.dev(),
                _ => false,
            };
            if !same {
                continue;
            }
            let _ = f.set_len(0);
            let _ = f.rewind();
            let _ = write!(f, "{}", std::process::id());
            return Ok(Self { file: f, path });
        }
    }
}

impl Drop for InstanceLock {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
        let _ = &self.file;
    }
}

/// Runs `graph` as processes until its frames are done, Ctrl-C or SIGTERM; a node that
/// fails beyond its restart policy stops the graph and is the report's `failure`.
pub fn run(graph: &Graph, o: &RunOptions) -> Result<RunReport, String> {
    // Before anything is made that a signal's default action would leave behind.
    crate::signals::install();
    let graph = &part_of(graph, o.host.as_deref())?;
    let stale = crate::process::remove_stale_resources();
    if stale.removed > 0 || stale.empty_files > 0 {
        crate::errln!(
            "removed the shared memory of {} dead node(s) and {} unfinished edge(s)",
            stale.removed,
            stale.empty_files
        );
    }
    if stale.gave_up {
        crate::errln!(
            "warning: the shared memory of dead nodes could not be removed within {:?}; \
             the graph starts anyway (`rm /dev/shm/iox2_*` and `rm -r /tmp/iceoryx2` with \
             no graph running clears it)",
            crate::process::STALE_CLEANUP_LIMIT
        );
    }
    let instance = o
        .instance
        .clone()
        .unwrap_or_else(|| format!("run{}", std::process::id()));
    if instance.is_empty()
        || instance.len() > 64
        || !instance
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
    {
        return Err(format!(
            "--instance '{}' is not a usable name: use 1 to 64 letters, digits, '-', '_' or '.'",
            instance.chars().take(80).collect::<String>()
        ));
    }
    let _lock = InstanceLock::take(&crate::status::run_name(&instance, o.host.as_deref()))?;
    // What a dead run of this instance may have left half made (its edges, its graph and
    // control files): nobody else makes them while the lock is held.
    let reclaimed = reclaim_instance(graph, &instance);
    if reclaimed > 0 {
        crate::errln!(
            "removed {reclaimed} file(s) an earlier run of instance '{instance}' left unfinished"
        );
    }

    // The part's link to the other hosts, up before its nodes: it carries only the edges
    // between hosts, and each only once a node here holds it (with the edge's own queue
    // settings), and the other parts' status.
    let link = match &o.host {
        Some(h) => Some(start_link(graph, o, h, &instance)?),
        None => None,
    };
    let file = GraphFile(std::env::temp_dir().join(format!(
        "microstereo-{instance}-{}.graph.json",
        std::process::id()
    )));
    crate::process::write_graph(&file.0, graph)?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| format!("cannot start the supervisor: {e}"))?;
    let (stats, wall, failure, killed) = rt.block_on(supervise(graph, o, &file.0, &instance));
    if let Some(l) = link {
        // The last status (the run ended) goes across before the link does.
        std::thread::sleep(Duration::from_millis(300));
        l.stop();
    }
    // A node killed (after its grace, or by anyone with SIGKILL) could not clean up: its
    // shared memory goes now, not at some later run's start.
    if killed {
        let _ = crate::process::remove_stale_resources();
        reclaim_instance(graph, &instance);
    }
    // The last run of a domain takes the domain's own memory with it.
    drop(rt);
    crate::process::release_domain();
    Ok(RunReport {
        stats,
        wall,
        host: o.host.clone(),
        failure,
        signal: crate::signals::first_signal(),
    })
}

/// The part of `graph` this host runs: its nodes and the taps added for it (recorder,
/// viewer), each tap reading what reaches this host; without a host, the whole graph.
fn part_of(graph: &Graph, host: Option<&str>) -> Result<Graph, String> {
    let mut graph = graph.clone();
    if host.is_none() {
        // The whole graph here: one host, whatever the file says.
        for n in &mut graph.nodes {
            n.host = None;
        }
    }
    if let Some(h) = host {
        if !graph.hosts.contains_key(h) {
            return Err(format!(
                "--host {h}: the launch file declares no such host; its hosts: {}",
                if graph.hosts.is_empty() {
                    "none (add [hosts.NAME] tables and a host per node)".to_string()
                } else {
                    graph.hosts.keys().cloned().collect::<Vec<_>>().join(", ")
                }
            ));
        }
        for n in &mut graph.nodes {
            n.host.get_or_insert_with(|| h.to_string());
        }
        // A tap here records what reaches this host: its nodes' outputs and the edges its
        // nodes read from other hosts (the others are recorded on their own host).
        let on_host = |g: &Graph, node: &str, output: &str| {
            g.host_of(node) == Some(h)
                || g.nodes.iter().any(|m| {
                    !m.tap
                        && m.host.as_deref() == Some(h)
                        && m.inputs
                            .iter()
                            .any(|i| i.node == node && i.output == output)
                })
        };
        let snapshot = graph.clone();
        for n in graph.nodes.iter_mut().filter(|n| n.tap) {
            let before = n.inputs.len();
            n.inputs.retain(|i| on_host(&snapshot, &i.node, &i.output));
            if n.inputs.len() < before {
                crate::errln!(
                    "{}: {} edge(s) written and read only on other hosts are left out here (record them on their host)",
                    n.id,
                    before - n.inputs.len()
                );
            }
        }
    }
    Ok(graph)
}

/// Removes what a dead run of `instance` left behind: edges iceoryx2 never finished making
/// (a process killed while making one leaves it "being set up" for ever, and every later
/// run of the instance then fails to open it), its graph files and its control files.
/// Only under the instance's lock, and before any node of this run starts. Returns the
/// number of files removed.
fn reclaim_instance(graph: &Graph, instance: &str) -> usize {
    let mut removed = crate::transport::remove_unfinished_services(
        graph
            .nodes
            .iter()
            .flat_map(|n| {
                n.outputs
                    .iter()
                    .map(|(port, _)| Graph::edge_name(instance, &n.id, port))
            })
            .chain(crate::status::status_services(instance, &graph.hosts)),
    );
    let tmp = std::env::temp_dir();
    if let Ok(dir) = std::fs::read_dir(&tmp) {
        let graph_file = format!("microstereo-{instance}-");
        for e in dir.filter_map(Result::ok) {
            let name = e.file_name().to_string_lossy().into_owned();
            let stale_graph = name.starts_with(&graph_file)
                && name.ends_with(".graph.json")
                && name[graph_file.len()..name.len() - ".graph.json".len()]
                    .parse::<u32>()
                    .is_ok_and(|pid| !process_alive(pid));
            if stale_graph && std::fs::remove_file(e.path()).is_ok() {
                removed += 1;
            }
        }
    }
    for n in &graph.nodes {
        let control = crate::process::control_path(instance, &n.id);
        for p in [control.with_extension("control.new"), control] {
            if std::fs::remove_file(p).is_ok() {
                removed += 1;
            }
        }
    }
    removed
}

/// Whether a process with this id exists.
fn process_alive(pid: u32) -> bool {
    // SAFETY: kill(2) with signal 0 sends nothing; it only checks that the process exists.
    let rc = unsafe { libc::kill(pid as i32, 0) };
    rc == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
}

struct Child {
    id: String,
    proc: tokio::process::Child,
    restarts: u32,
    /// The back-off's exponent should this process fail before handling a frame: one more
    /// than its predecessor's restart had (0 for the first process).
    streak: u32,
    /// Killed by the watchdog, after this long without a report.
    hung: Option<Duration>,
    /// The task reading the process's stdout (its reports): awaited when the process
    /// exits, so that its last report is in before a restart reads where it got to.
    reports: Option<tokio::task::JoinHandle<()>>,
}

fn spawn(
    graph: &Graph,
    o: &RunOptions,
    file: &std::path::Path,
    instance: &str,
    id: &str,
    generation: u64,
    first_frame: Option<u64>,
) -> Result<tokio::process::Child, String> {
    let spec = graph.node(id).expect("validated");
    let mut cmd = match &spec.runner {
        Runner::Builtin(_) => {
            let (program, args) = o
                .builtin
                .split_first()
                .ok_or("no program to run built-in nodes with")?;
            let mut c = tokio::process::Command::new(program);
            c.args(args);
            c
        }
        Runner::Exec(p) => tokio::process::Command::new(p),
    };
    cmd.args(
        NodeArgs {
            graph: file.to_path_buf(),
            id: id.into(),
            instance: instance.into(),
            frames: o.frames,
            generation,
        }
        .to_args(),
    );
    match crate::transport::domain() {
        Some(d) => cmd.env(crate::transport::DOMAIN_ENV, d),
        None => cmd.env_remove(crate::transport::DOMAIN_ENV),
    };
    // Only the sources the terminal controls look at a control file between frames.
    cmd.env_remove(crate::process::CONTROL_ENV);
    if o.controls.iter().any(|c| c == id) && std::io::IsTerminal::is_terminal(&std::io::stdin()) {
        cmd.env(crate::process::CONTROL_ENV, "1");
    }
    cmd.env_remove(crate::process::GENERATION_ENV);
    if generation > 0 {
        cmd.env(crate::process::GENERATION_ENV, generation.to_string());
    }
    cmd.env_remove(crate::process::FIRST_FRAME_ENV);
    if let Some(f) = first_frame {
        cmd.env(crate::process::FIRST_FRAME_ENV, f.to_string());
    }
    cmd.stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .stdin(if spec.logs {
            Stdio::piped()
        } else {
            Stdio::null()
        })
        .kill_on_drop(true)
        // A group of its own: the terminal's Ctrl-C, Ctrl-\ and hang-up reach the
        // supervisor only, which stops the nodes in order (a node that took the terminal's
        // SIGINT itself ended before the supervisor knew of any stop, and counted as failed).
        .process_group(0);
    #[cfg(target_os = "linux")]
    // SAFETY: only async-signal-safe prctl between fork and exec.
    unsafe {
        cmd.pre_exec(|| {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
            Ok(())
        });
    }
    cmd.spawn()
        .map_err(|e| format!("cannot start node '{id}': {e}"))
}

/// A process's last report and when it came.
#[derive(Clone)]
struct Heard {
    stats: NodeStats,
    at: Instant,
}

/// Per node id, the last report of each process that ran it, in the order they ran (`None`
/// for one that never reported).
type StatsSink = std::sync::Arc<std::sync::Mutex<HashMap<String, Vec<Option<Heard>>>>>;

/// How often the watchdog looks at the nodes' last reports.
const WATCH_TICK: Duration = Duration::from_millis(100);

/// Where node log lines go besides the terminal: the Rerun viewer node's stdin, as
/// `NODE<TAB>LEVEL<TAB>LINE`.
type LogTap = Option<tokio::sync::mpsc::UnboundedSender<String>>;

fn forward_logs(
    id: &str,
    run: usize,
    logs: bool,
    child: &mut tokio::process::Child,
    stats: &StatsSink,
    tap: &LogTap,
) -> Option<tokio::task::JoinHandle<()>> {
    let reports = child.stdout.take().map(|out| {
        let (id, stats, tap) = (id.to_string(), stats.clone(), tap.clone());
        tokio::spawn(async move {
            let mut lines = BufReader::new(out).lines();
            while let Ok(Some(l)) = lines.next_line().await {
                match l.strip_prefix(STATS_PREFIX) {
                    Some(j) => {
                        if let Ok(s) = serde_json::from_str::<NodeStats>(j) {
                            let mut all = stats.lock().expect("stats");
                            let runs = all.entry(id.clone()).or_default();
                            if runs.len() <= run {
                                runs.resize(run + 1, None);
                            }
                            runs[run] = Some(Heard {
                                stats: s,
                                at: Instant::now(),
                            });
                        }
                    }
                    None => {
                        if let Some(t) = &tap {
                            let _ = t.send(format!("{id}\tINFO\t{l}"));
                        }
                        above_progress(|| crate::outln!("[{id}] {l}"))
                    }
                }
            }
        })
    });
    if let Some(err) = child.stderr.take() {
        let (id, tap) = (id.to_string(), tap.clone());
        tokio::spawn(async move {
            let mut lines = BufReader::new(err).lines();
            while let Ok(Some(l)) = lines.next_line().await {
                if let Some(t) = &tap {
                    let _ = t.send(format!("{id}\tWARN\t{l}"));
                }
                above_progress(|| crate::errln!("[{id}] {l}"));
            }
        });
    }
    // The viewer reads the other nodes' log lines on its stdin.
    if logs
        && let Some(mut stdin) = child.stdin.take()
        && let Some(rx) = VIEWER_LOGS.lock().expect("logs").take()
    {
        use tokio::io::AsyncWriteExt;
        let mut rx: tokio::sync::mpsc::UnboundedReceiver<String> = rx;
        tokio::spawn(async move {
            while let Some(mut line) = rx.recv().await {
                line.push('\n');
                if stdin.write_all(line.as_bytes()).await.is_err() {
                    break;
                }
            }
        });
    }
    reports
}

/// The receiving end of the log tap, taken by the first viewer process started.
static VIEWER_LOGS: std::sync::Mutex<Option<tokio::sync::mpsc::UnboundedReceiver<String>>> =
    std::sync::Mutex::new(None);

/// Asks every node to stop: SIGTERM to each node's process group (the node and whatever
/// it started; each node leads a group of its own).
fn terminate(children: &[Child]) {
    for c in children {
        if let Some(pid) = c.proc.id() {
            // SAFETY: kill(2) on the process group our own child leads.
            unsafe {
                libc::kill(-(pid as i32), libc::SIGTERM);
            }
        }
    }
}

/// Kills every node that is left, with whatever it started.
fn kill_all(children: &mut [Child]) {
    for c in children {
        if let Some(pid) = c.proc.id() {
            // SAFETY: kill(2) on the process group our own child leads.
            unsafe {
                libc::kill(-(pid as i32), libc::SIGKILL);
            }
        }
        let _ = c.proc.start_kill();
    }
}

/// What a supervised run gives back: per node its reports, the wall time, why it ended
/// early (if it did) and whether a node had to be killed (its shared memory then needs
/// removing).
type Supervised = (HashMap<String, NodeStats>, Duration, Option<String>, bool);

async fn supervise(
    graph: &Graph,
    a: &RunOptions,
    file: &std::path::Path,
    instance: &str,
) -> Supervised {
    let start = Instant::now();
    let mut s = Supervisor::new(graph, a, file, instance);
    let monitor = Monitor::start(graph, instance, a, s.stats.clone(), s.states.clone());
    // A control file left by an earlier run of this instance would hold its sources.
    for n in graph.nodes.iter().filter(|n| n.inputs.is_empty()) {
        let _ = std::fs::remove_file(crate::process::control_path(instance, &n.id));
    }
    let control_files = control_from_terminal(&a.controls, instance);
    s.tap = graph.nodes.iter().find(|n| n.logs).map(|_| {
        let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
        *VIEWER_LOGS.lock().expect("logs") = Some(rx);
        tx
    });
    s.start_nodes();
    if s.failure.is_some() || crate::signals::stop_requested() {
        s.stop();
    }
    while !s.children.is_empty() {
        s.look_at_signals();
        // Every node nobody reads is done: the ones they read may go.
        if s.stopping.is_none()
            && s.children.iter().all(|c| graph.is_read(&c.id))
            && s.readers_elsewhere.all_ended()
        {
            s.stop();
        }
        s.kill_when_grace_is_over();
        match s.next_event().await {
            Event::Exit(i, status) => s.exited(i, status).await,
            Event::Tick => s.watch(),
        }
    }
    // The last reports still in their pipes (bounded, as in `exited`), and a moment for
    // the log forwarders to flush the last lines.
    let _ = tokio::time::timeout(Duration::from_secs(2), futures_all(s.unread.iter_mut())).await;
    tokio::time::sleep(Duration::from_millis(50)).await;
    let wall = start.elapsed();
    monitor.stop();
    for f in control_files {
        let _ = std::fs::remove_file(f);
    }
    let stats = s
        .stats
        .lock()
        .expect("stats")
        .iter()
        .filter_map(|(id, runs)| {
            let runs: Vec<NodeStats> = runs.iter().flatten().map(|h| h.stats.clone()).collect();
            Some((id.clone(), crate::stats::merge(&runs)?))
        })
        .collect();
    (stats, wall, s.failure, s.killed)
}

/// A run's processes while they run: started, watched, restarted by their policy, and
/// stopped (SIGTERM, then SIGKILL once the grace is over).
struct Supervisor<'a> {
    graph: &'a Graph,
    a: &'a RunOptions,
    file: &'a std::path::Path,
    instance: &'a str,
    /// Each node's reports, per run of it.
    stats: StatsSink,
    /// Each node's state for the status block.
    states: States,
    /// Where node log lines go besides the terminal.
    tap: LogTap,
    /// The processes running now.
    children: Vec<Child>,
    /// The parts on other hosts that read this one's edges: it stops once they ended.
    readers_elsewhere: RemoteParts,
    /// Why the run ends early.
    failure: Option<String>,
    /// Set once the graph is told to stop: when its grace runs out, whatever still runs is
    /// killed.
    stopping: Option<Instant>,
    grace: Duration,
    /// Whether a process of the run died by a signal (its shared memory is then removed at
    /// the end).
    killed: bool,
    /// Whether the stop's grace ran out (the rest were killed).
    grace_over: bool,
    /// Report readers of ended processes that were still reading when they were last
    /// awaited.
    unread: Vec<tokio::task::JoinHandle<()>>,
    /// Restarts so far in this run: a restarted node's markers carry the count.
    generation: u64,
    /// Signals already acted on (a second one means: now).
    signals_seen: usize,
}

impl<'a> Supervisor<'a> {
    fn new(
        graph: &'a Graph,
        a: &'a RunOptions,
        file: &'a std::path::Path,
        instance: &'a str,
    ) -> Self {
        Self {
            graph,
            a,
            file,
            instance,
            stats: Default::default(),
            states: Default::default(),
            tap: None,
            children: Vec::new(),
            readers_elsewhere: RemoteParts::of(graph, instance, a.host.as_deref()),
            failure: None,
            stopping: None,
            grace: Duration::try_from_secs_f64(a.grace).unwrap_or(Duration::ZERO),
            killed: false,
            grace_over: false,
            unread: Vec::new(),
            generation: 0,
            signals_seen: 0,
        }
    }

    /// Starts this host's nodes in the graph's order; a stop or a failure to start leaves
    /// the rest unstarted.
    fn start_nodes(&mut self) {
        let a = self.a;
        for n in self
            .graph
            .nodes
            .iter()
            .filter(|n| a.host.is_none() || n.host == a.host)
        {
            if crate::signals::stop_requested() {
                break;
            }
            if let Err(e) = self.start(&n.id, 0, 0, None) {
                self.failure = Some(e);
                break;
            }
        }
    }

    /// Starts node `id` for its run number `restarts` (a source from `first_frame`).
    fn start(
        &mut self,
        id: &str,
        restarts: u32,
        streak: u32,
        first_frame: Option<u64>,
    ) -> Result<(), String> {
        let (g, a) = (self.graph, self.a);
        let mut proc = spawn(
            g,
            a,
            self.file,
            self.instance,
            id,
            self.generation,
            first_frame,
        )?;
        set_state(&self.states, id, NodeState::Starting, restarts, proc.id());
        let logs = g.node(id).expect("validated").logs;
        let run = restarts as usize;
        let reports = forward_logs(id, run, logs, &mut proc, &self.stats, &self.tap);
        self.children.push(Child {
            id: id.to_string(),
            proc,
            restarts,
            streak,
            hung: None,
            reports,
        });
        Ok(())
    }

    /// Tells every node to stop (once): SIGTERM now, SIGKILL when the grace is over.
    fn stop(&mut self) {
        if self.stopping.is_none() {
            self.stopping = Some(Instant::now());
            terminate(&self.children);
        }
    }

    fn kill_all(&mut self) {
        kill_all(&mut self.children);
        self.killed = true;
        self.grace_over = true;
    }

    /// A signal stops the graph; a second one kills what is left.
    fn look_at_signals(&mut self) {
        let signals = crate::signals::signal_count();
        if signals > self.signals_seen
            || (self.signals_seen == 0 && crate::signals::stop_requested())
        {
            if self.stopping.is_none() {
                above_progress(|| crate::errln!("stopping the graph"));
            } else if self.signals_seen > 0 {
                above_progress(|| crate::errln!("stopping now: the nodes left are killed"));
                self.kill_all();
            }
            self.signals_seen = signals.max(1);
            self.stop();
        }
    }

    fn kill_when_grace_is_over(&mut self) {
        if let Some(t) = self.stopping
            && t.elapsed() >= self.grace
            && !self.grace_over
        {
            self.kill_all();
        }
    }

    /// Whether the nodes' reports and the other hosts are watched while the graph runs.
    fn watched(&self) -> bool {
        self.stopping.is_none()
            && (self
                .graph
                .nodes
                .iter()
                .any(|n| n.restart.heartbeat_ms.is_some())
                || !self.readers_elsewhere.is_empty())
    }

    /// The next process to exit, or a tick to look at the stop flag and the watchdog.
    async fn next_event(&mut self) -> Event {
        // The stop flag is a signal handler's: it is looked at this often.
        let tick = if self.watched() {
            WATCH_TICK
        } else {
            SIGNAL_TICK
        };
        let waits = self
            .children
            .iter_mut()
            .enumerate()
            .map(|(i, c)| Box::pin(async move { (i, c.proc.wait().await) }));
        tokio::select! {
            biased;
            (r, _, _) = futures_select(waits) => Event::Exit(r.0, r.1),
            _ = tokio::time::sleep(tick.min(SIGNAL_TICK)) => Event::Tick,
        }
    }

    /// The watchdog's look at the nodes' last reports, and at the other hosts' parts.
    fn watch(&mut self) {
        if !self.watched() {
            return;
        }
        watch(self.graph, &self.stats, &mut self.children);
        if let Some(why) = self.readers_elsewhere.look() {
            self.failure = Some(why);
            self.stop();
        }
    }

    /// Child `i` exited with `status`: restarted by its policy, or the graph stopped when
    /// it failed.
    async fn exited(&mut self, i: usize, status: std::io::Result<std::process::ExitStatus>) {
        let mut c = self.children.remove(i);
        let status = match status {
            Ok(s) => s,
            Err(e) => {
                // It cannot be waited for: killed, so that nothing outlives the run.
                let _ = c.proc.start_kill();
                self.killed = true;
                if self.stopping.is_none() {
                    self.failure = Some(format!("waiting for node '{}': {e}", c.id));
                    self.stop();
                }
                return;
            }
        };
        // Killed by a signal (SIGKILL after its grace, the watchdog, anyone): whatever it
        // had made stays until removed.
        if std::os::unix::process::ExitStatusExt::signal(&status).is_some() {
            self.killed = true;
        }
        // Its last reports may still be in the pipe (the reader task runs beside this one,
        // and lags under load): a restarted source would otherwise go on from a frame
        // before its predecessor's last and send frame numbers twice. Bounded, in case
        // something the node started keeps the pipe open; briefly once the graph stops
        // (no restart needs it, and the others' grace runs meanwhile).
        if let Some(mut r) = c.reports.take() {
            let wait = if self.stopping.is_some() {
                Duration::from_millis(300)
            } else {
                Duration::from_secs(2)
            };
            if tokio::time::timeout(wait, &mut r).await.is_err() {
                self.unread.push(r);
            }
        }
        let spec = self.graph.node(&c.id).expect("validated");
        // A node others read never ends on its own before the graph stops: one that did
        // was stopped from outside (a SIGTERM it obeyed), and its readers would wait for
        // its frames for ever. It counts as failed.
        let ended_early = self.stopping.is_none() && status.success() && self.graph.is_read(&c.id);
        let failed = !status.success() || ended_early || c.hung.is_some();
        let why = if let Some(h) = c.hung {
            format!(
                "hung: no report for {} ms, killed by the watchdog",
                h.as_millis()
            )
        } else if ended_early {
            format!("ended before the graph was done ({status}; stopped from outside?)")
        } else {
            format!("{status}")
        };
        let restart = self.stopping.is_none()
            && match spec.restart.policy {
                RestartPolicy::Never => false,
                RestartPolicy::OnFailure => failed,
                RestartPolicy::Always => true,
            }
            && c.restarts < spec.restart.max;
        if restart {
            self.restart(c, failed, &why).await;
        } else {
            let failed_now = failed && self.stopping.is_none();
            let state = if failed_now {
                NodeState::Failed
            } else {
                NodeState::Exited
            };
            set_state(&self.states, &c.id, state, c.restarts, None);
            if failed_now {
                self.failure = Some(format!("node '{}' failed ({why})", c.id));
                self.stop();
            }
        }
    }

    /// Starts the ended child `c` again after its back-off (cut short by a stop).
    async fn restart(&mut self, c: Child, failed: bool, why: &str) {
        let spec = self.graph.node(&c.id).expect("validated");
        // The back-off doubles while the node fails without handling a frame (a crash
        // loop); one that handled frames since its start comes back after the base
        // back-off, however often it was restarted before: 20 kills spread over a run
        // doubled it to 6.4 s by the eighth, and the source finished meanwhile.
        let progressed = self
            .stats
            .lock()
            .expect("stats")
            .get(&c.id)
            .and_then(|runs| runs.get(c.restarts as usize))
            .and_then(Option::as_ref)
            .is_some_and(|h| h.stats.frames_in > 0);
        let exponent = if progressed { 0 } else { c.streak };
        let wait = Duration::from_millis(
            spec.restart
                .backoff_ms
                .saturating_mul(1 << exponent.min(10)),
        );
        above_progress(|| {
            crate::errln!(
                "[{}] exited ({why}); restart {} of {} in {:?}",
                c.id,
                c.restarts + 1,
                spec.restart.max,
                wait
            )
        });
        set_state(
            &self.states,
            &c.id,
            NodeState::Restarting,
            c.restarts + 1,
            None,
        );
        if failed {
            // A node that died holds its places on its edges (a full queue of a dead
            // reader blocks a lossless writer): free them at once, so that its writers
            // go on while it is down.
            let stale = tokio::task::spawn_blocking(crate::process::remove_stale_resources)
                .await
                .unwrap_or_default();
            if stale.gave_up {
                above_progress(|| {
                    crate::errln!("[{}] warning: its shared memory could not be removed", c.id)
                });
            }
        }
        // The back-off is cut short by a stop.
        let until = Instant::now() + wait;
        while Instant::now() < until && !crate::signals::stop_requested() {
            tokio::time::sleep(SIGNAL_TICK.min(until - Instant::now())).await;
        }
        if crate::signals::stop_requested() {
            set_state(&self.states, &c.id, NodeState::Exited, c.restarts, None);
            return;
        }
        self.generation += 1;
        // A source goes on from the frame after the last its predecessors reported.
        let first_frame = spec
            .inputs
            .is_empty()
            .then(|| {
                self.stats
                    .lock()
                    .expect("stats")
                    .get(&c.id)
                    .and_then(|runs| {
                        runs.iter()
                            .flatten()
                            .filter_map(|h| h.stats.last_frame)
                            .max()
                    })
            })
            .flatten()
            .map(|l| l + 1);
        if let Err(e) = self.start(&c.id, c.restarts + 1, exponent + 1, first_frame) {
            set_state(&self.states, &c.id, NodeState::Failed, c.restarts, None);
            self.failure = Some(e);
            self.stop();
        }
    }
}

/// How often the supervisor looks at the stop flag its signal handler raises.
const SIGNAL_TICK: Duration = Duration::from_millis(20);

/// Pauses, resumes and steps the sources `ids` from the terminal, when stdin is one: a
/// line `p` pauses or resumes them, `s` lets one frame through while paused (through their
/// control files, [`crate::process::control_path`], which they read between frames).
fn control_from_terminal(ids: &[String], instance: &str) -> Vec<std::path::PathBuf> {
    use std::io::{BufRead, IsTerminal};
    if ids.is_empty() || !std::io::stdin().is_terminal() {
        return Vec::new();
    }
    above_progress(|| {
        crate::errln!(
            "{}: type p and Enter to pause or resume, s and Enter to step one frame",
            ids.join(", ")
        )
    });
    let files: Vec<std::path::PathBuf> = ids
        .iter()
        .map(|id| crate::process::control_path(instance, id))
        .collect();
    let paths = files.clone();
    // Reads until the process ends (stdin stays open while the run goes on).
    std::thread::spawn(move || {
        let (mut pauses, mut steps) = (0u64, 0u64);
        for line in std::io::stdin().lock().lines() {
            let Ok(line) = line else { break };
            let said = match line.trim() {
                "p" => {
                    pauses += 1;
                    if pauses % 2 == 1 {
                        "paused: s steps one frame, p resumes"
                    } else {
                        "resumed"
                    }
                }
                "s" if pauses % 2 == 1 => {
                    steps += 1;
                    "one frame"
                }
                "s" => "not paused: p pauses first",
                _ => continue,
            };
            for f in &paths {
                let tmp = f.with_extension("control.new");
                if std::fs::write(&tmp, format!("{pauses} {steps}")).is_ok() {
                    let _ = std::fs::rename(&tmp, f);
                }
            }
            above_progress(|| crate::errln!("{said}"));
        }
    });
    files
}

/// Per node id: what its processes are doing, its restarts and its process now.
type States = std::sync::Arc<std::sync::Mutex<HashMap<String, (NodeState, u32, Option<u32>)>>>;

fn set_state(states: &States, id: &str, state: NodeState, restarts: u32, pid: Option<u32>) {
    if let Ok(mut s) = states.lock() {
        s.insert(id.into(), (state, restarts, pid));
    }
}

/// The progress line while one is shown: log lines are printed above it.
static PROGRESS: std::sync::Mutex<Option<indicatif::ProgressBar>> = std::sync::Mutex::new(None);

/// Runs `print` with the progress line (if any) out of the way.
fn above_progress(print: impl FnOnce()) {
    let bar = PROGRESS.lock().ok().and_then(|b| b.clone());
    match bar {
        Some(b) => b.suspend(print),
        None => print(),
    }
}

/// The thread that publishes the run's status ([`crate::status`]) every
/// [`STATUS_PERIOD`](crate::status::STATUS_PERIOD) and keeps the progress line.
struct Monitor {
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Monitor {
    fn start(
        graph: &Graph,
        instance: &str,
        o: &RunOptions,
        stats: StatsSink,
        states: States,
    ) -> Self {
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let base = GraphStatus::of(
            graph,
            instance,
            o.host.as_deref(),
            o.frames,
            crate::edge::now_ns(),
        );
        let host = o.host.clone();
        let (flag, instance, progress) = (stop.clone(), instance.to_string(), o.progress);
        let thread = std::thread::spawn(move || {
            use std::io::IsTerminal;
            // The status is a view: a run whose status cannot be published still runs.
            let mut publisher =
                match crate::status::StatusPublisher::new(&instance, host.as_deref()) {
                    Ok(p) => Some(p),
                    Err(e) => {
                        above_progress(|| {
                            crate::errln!("warning: the run's status is not published: {e}")
                        });
                        None
                    }
                };
            let bar = (progress && std::io::stderr().is_terminal()).then(|| {
                let b = indicatif::ProgressBar::with_draw_target(
                    None,
                    indicatif::ProgressDrawTarget::stderr_with_hz(4),
                );
                b.set_style(
                    indicatif::ProgressStyle::with_template("{msg}")
                        .unwrap_or_else(|_| indicatif::ProgressStyle::default_spinner()),
                );
                b
            });
            if let (Some(b), Ok(mut slot)) = (&bar, PROGRESS.lock()) {
                *slot = Some(b.clone());
            }
            // The progress line's rate is over the last second or so.
            let mut history: std::collections::VecDeque<GraphStatus> = Default::default();
            loop {
                let ended = flag.load(std::sync::atomic::Ordering::Relaxed);
                let now = snapshot(&base, &stats, &states, ended);
                if let Some(p) = &mut publisher {
                    let _ = p.publish(&now);
                    // A part of a graph over hosts says it ended more than once: the link
                    // gives a sample up for a full queue, and a far part that never heard
                    // the one "ended" waited 10 s and called this part silent (1 run in 3
                    // or 4 of the two-host test under two CPU hogs).
                    if ended && host.is_some() {
                        for _ in 0..ENDED_REPEATS {
                            std::thread::sleep(Duration::from_millis(50));
                            let _ = p.publish(&now);
                        }
                    }
                }
                if let Some(b) = &bar {
                    while history
                        .front()
                        .is_some_and(|h| now.now_ns.saturating_sub(h.now_ns) > 1_000_000_000)
                    {
                        history.pop_front();
                    }
                    let p = crate::status::progress(history.front(), &now);
                    b.set_message(p.line());
                    history.push_back(now);
                }
                if ended {
                    break;
                }
                let t0 = Instant::now();
                while t0.elapsed() < crate::status::STATUS_PERIOD
                    && !flag.load(std::sync::atomic::Ordering::Relaxed)
                {
                    std::thread::sleep(Duration::from_millis(10));
                }
            }
            if let Ok(mut slot) = PROGRESS.lock() {
                *slot = None;
            }
            if let Some(b) = bar {
                b.finish_and_clear();
            }
        });
        Self {
            stop,
            thread: Some(thread),
        }
    }

    /// Publishes the last status (the run ended) and clears the progress line.
    fn stop(mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The run's status now: `base` with each node's state and figures so far.
fn snapshot(base: &GraphStatus, stats: &StatsSink, states: &States, ended: bool) -> GraphStatus {
    let mut s = base.clone();
    s.now_ns = crate::edge::now_ns();
    s.ended = ended;
    let heard = stats.lock().map(|h| h.clone()).unwrap_or_default();
    let states = states.lock().map(|s| s.clone()).unwrap_or_default();
    for n in &mut s.nodes {
        let runs = heard.get(&n.id);
        if let Some(runs) = runs {
            let all: Vec<NodeStats> = runs.iter().flatten().map(|h| h.stats.clone()).collect();
            n.stats = crate::stats::merge(&all);
        }
        if let Some(&(state, restarts, pid)) = states.get(&n.id) {
            let reported = runs
                .and_then(|r| r.get(restarts as usize))
                .is_some_and(Option::is_some);
            let preparing = n.stats.as_ref().is_some_and(|s| s.phase.is_some());
            n.state = match state {
                NodeState::Starting if reported && preparing => NodeState::Preparing,
                NodeState::Starting if reported => NodeState::Running,
                other => other,
            };
            n.restarts = restarts;
            n.pid = pid;
        }
    }
    s
}

/// Starts part `host`'s link: the graph's edges between hosts and the parts' status.
fn start_link(
    graph: &Graph,
    o: &RunOptions,
    host: &str,
    instance: &str,
) -> Result<hostlink::HostLink, String> {
    let endpoints = o.endpoints.clone().unwrap_or_else(|| {
        let h = graph.hosts.get(host).cloned().unwrap_or_default();
        hostlink::Endpoints {
            listen: h.listen,
            connect: h.connect,
        }
    });
    if endpoints.listen.is_empty() && endpoints.connect.is_empty() {
        return Err(format!(
            "host '{host}' has no link endpoints: give [hosts.{host}] listen = [\"tcp/0.0.0.0:7447\"] (or connect = [\"tcp/OTHER-HOST:7447\"]), or --listen/--connect"
        ));
    }
    let edges: std::collections::HashSet<String> = graph
        .cross_host_edges()
        .iter()
        .map(|(n, p)| Graph::edge_name(instance, n, p))
        .collect();
    let status = format!("{}/", crate::status::status_service(instance, None));
    let config = crate::transport::iceoryx_config().clone();
    let local = config.clone();
    hostlink::HostLink::start(config, &endpoints, move |name| {
        // An edge only once a node here made it with its own settings: a mirror the link
        // made first would have iceoryx2's defaults, which the node's settings then
        // contradict. A status is read only with `open`, which takes any settings.
        name.starts_with(&status)
            || (edges.contains(name)
                && iceoryx2::prelude::ServiceName::new(name).is_ok_and(|n| {
                    use iceoryx2::service::Service as _;
                    crate::transport::Service::does_exist(
                        &n,
                        &local,
                        iceoryx2::service::messaging_pattern::MessagingPattern::PublishSubscribe,
                    )
                    .unwrap_or(false)
                }))
    })
    .map_err(|e| format!("host '{host}': {e}"))
}

/// The parts on other hosts that read this part's edges, seen through their status.
struct RemoteParts {
    parts: Vec<RemotePart>,
}

struct RemotePart {
    name: String,
    reader: Option<crate::status::StatusReader>,
    ended: bool,
    last_heard: Option<Instant>,
}

/// How many more times a part of a graph over hosts publishes its last status, 50 ms apart.
const ENDED_REPEATS: usize = 5;

/// How long a part that published its status may fall silent before it counts as gone.
const PART_SILENCE: Duration = Duration::from_secs(10);

impl RemoteParts {
    fn of(graph: &Graph, instance: &str, host: Option<&str>) -> Self {
        let Some(host) = host else {
            return Self { parts: Vec::new() };
        };
        let mut hosts: Vec<String> = Vec::new();
        for n in graph
            .nodes
            .iter()
            .filter(|n| n.host.as_deref() == Some(host))
        {
            for (port, _) in &n.outputs {
                for (r, _) in graph.readers_of(&n.id, port) {
                    if let Some(h) = graph.host_of(r)
                        && h != host
                        && !hosts.iter().any(|x| x == h)
                    {
                        hosts.push(h.to_string());
                    }
                }
            }
        }
        Self {
            parts: hosts
                .into_iter()
                .map(|h| RemotePart {
                    name: crate::status::run_name(instance, Some(&h)),
                    reader: None,
                    ended: false,
                    last_heard: None,
                })
                .collect(),
        }
    }

    fn is_empty(&self) -> bool {
        self.parts.is_empty()
    }

    fn all_ended(&self) -> bool {
        self.parts.iter().all(|p| p.ended)
    }

    /// Reads their status; why the run must stop, if a part that was heard fell silent.
    fn look(&mut self) -> Option<String> {
        for p in &mut self.parts {
            if p.reader.is_none() {
                p.reader = crate::status::StatusReader::open(&p.name, Duration::ZERO).ok();
            }
            let Some(r) = &p.reader else { continue };
            if let Ok(Some(s)) = r.next(Duration::ZERO) {
                p.last_heard = Some(Instant::now());
                p.ended |= s.ended;
            }
            if !p.ended && p.last_heard.is_some_and(|t| t.elapsed() > PART_SILENCE) {
                return Some(format!(
                    "part '{}' fell silent for {} s (its host or the link between them is down)",
                    p.name,
                    PART_SILENCE.as_secs()
                ));
            }
        }
        None
    }
}

/// What woke the supervisor.
enum Event {
    /// The child at this index exited.
    Exit(usize, std::io::Result<std::process::ExitStatus>),
    /// Time to look at the stop flag and the watchdog.
    Tick,
}

/// The watchdog: kills each node whose `heartbeat_ms` has passed since its process's last
/// report (its exit then goes the way of any failure: a restart by its policy, or the end
/// of the run with the reason).
fn watch(graph: &Graph, stats: &StatsSink, children: &mut [Child]) {
    let heard = stats.lock().expect("stats");
    for c in children.iter_mut().filter(|c| c.hung.is_none()) {
        let Some(limit) = graph
            .node(&c.id)
            .and_then(|n| n.restart.heartbeat_ms)
            .map(Duration::from_millis)
        else {
            continue;
        };
        let last = heard
            .get(&c.id)
            .and_then(|runs| runs.get(c.restarts as usize))
            .and_then(|h| h.as_ref())
            .map(|h| h.at);
        // The watch starts with the process's first report.
        let Some(last) = last else { continue };
        let silent = last.elapsed();
        if silent > limit {
            crate::errln!(
                "[{}] no report for {} ms (heartbeat_ms = {}): hung; killing it",
                c.id,
                silent.as_millis(),
                limit.as_millis()
            );
            c.hung = Some(silent);
            let _ = c.proc.start_kill();
        }
    }
}

/// Waits for every one of these futures.
async fn futures_all<'a, F>(futs: impl Iterator<Item = &'a mut F>)
where
    F: std::future::Future + Unpin + 'a,
{
    for f in futs {
        let _ = f.await;
    }
}

/// The first of several futures to finish, with its index.
async fn futures_select<F, T>(futs: impl Iterator<Item = F>) -> (T, usize, ())
where
    F: std::future::Future<Output = T> + Unpin,
{
    let mut futs: Vec<F> = futs.collect();
    std::future::poll_fn(move |cx| {
        for (i, f) in futs.iter_mut().enumerate() {
            if let std::task::Poll::Ready(v) = std::pin::Pin::new(f).poll(cx) {
                return std::task::Poll::Ready((v, i, ()));
            }
        }
        std::task::Poll::Pending
    })
    .await
}

/// Prints the run's summary: per node frames and step times, per edge what was lost, the
/// frame rate and the latency of the graph's ends; returns the frame rate.
pub fn print_summary(
    graph: &Graph,
    stats: &HashMap<String, NodeStats>,
    wall: Duration,
    frames: Option<u64>,
    host: Option<&str>,
) -> f64 {
    // A part's summary: its host's nodes (and the taps it added).
    let mut graph = graph.clone();
    if host.is_some() {
        graph
            .nodes
            .retain(|n| n.host.is_none() || n.host.as_deref() == host);
    }
    let graph = &graph;
    crate::outln!();
    crate::outln!(
        "{:<20} {:>9} {:>9} {:>10} {:>10} {:>12} {:>7}",
        "node",
        "frames in",
        "out",
        "mean ms",
        "p99 ms",
        "latency ms",
        "CPU %"
    );
    // CPU: the share of one core the node's processes used over the run.
    let wall_ms = wall.as_secs_f64().max(1e-9) * 1e3;
    for n in &graph.nodes {
        match stats.get(&n.id) {
            Some(s) => crate::outln!(
                "{:<20} {:>9} {:>9} {:>10.2} {:>10.2} {:>12.1} {:>7.1}{}",
                n.id,
                s.frames_in,
                s.frames_out,
                s.mean_ms,
                s.p99_ms,
                s.latency_ms,
                100.0 * s.cpu_ms / wall_ms,
                if s.runs > 1 {
                    format!("  ({} processes: restarted)", s.runs)
                } else {
                    String::new()
                }
            ),
            None => crate::outln!("{:<20} (no report)", n.id),
        }
    }
    // Per edge: messages its own queue lost, and frames of the stream that never reached
    // the reader (lost there, upstream, or in a restarted writer).
    let mut rows = Vec::new();
    for n in &graph.nodes {
        if let Some(s) = stats.get(&n.id) {
            for (i, lost) in n.inputs.iter().zip(&s.inputs) {
                rows.push((
                    format!("{}/{} → {}.{}", i.node, i.output, n.id, i.port),
                    lost,
                ));
            }
        }
    }
    let width = rows
        .iter()
        .map(|r| r.0.chars().count())
        .max()
        .unwrap_or(4)
        .max(4);
    crate::outln!();
    crate::outln!(
        "{:<width$} {:>8} {:>14}",
        "edge",
        "dropped",
        "never arrived"
    );
    for (edge, lost) in &rows {
        crate::outln!("{:<width$} {:>8} {:>14}", edge, lost.dropped, lost.missing);
    }
    // Frames a source did not let in, its frames in flight being at their limit: they count
    // as never arrived on the edges above, but no edge lost them.
    for n in &graph.nodes {
        if let (Some(f), Some(s), Some(total)) = (&n.in_flight, stats.get(&n.id), frames) {
            crate::outln!(
                "{} let {} of {total} frames in ({} at most in flight, until out of {})",
                n.id,
                s.frames_in,
                f.frames,
                f.after
            );
        }
    }
    let sinks: Vec<&NodeStats> = graph
        .ends()
        .iter()
        .filter_map(|n| stats.get(&n.id))
        .collect();
    let done = sinks.iter().map(|s| s.frames_in).min().unwrap_or(0);
    let worst = |f: fn(&NodeStats) -> f64| sinks.iter().map(|s| f(s)).fold(0.0, f64::max);
    let rate = done as f64 / wall.as_secs_f64().max(1e-9);
    // The slowest end's rate between its first output and its last: what the graph keeps
    // up once running (the wall time above also holds the processes' start, a source's
    // renders before its clock starts, and the end).
    let sustained = sinks
        .iter()
        .map(|s| s.sustained_rate())
        .try_fold(f64::INFINITY, |a, r| r.map(|r| a.min(r)))
        .filter(|r| r.is_finite());
    crate::outln!(
        "{done} frame(s){} in {:.2} s: {rate:.2} frames/s; capture → last output latency {:.1} ms (p50 {:.1}, p99 {:.1}); CPU {:.0} % of one core{}",
        frames.map_or(String::new(), |n| format!(" of {n}")),
        wall.as_secs_f64(),
        worst(|s| s.latency_ms),
        worst(|s| s.latency_p50_ms),
        worst(|s| s.latency_p99_ms),
        100.0 * stats.values().map(|s| s.cpu_ms).sum::<f64>() / wall_ms,
        sustained.map_or(String::new(), |r| format!(
            "; sustained {r:.2} frames/s from the first output to the last"
        ))
    );
    rate
}
