//! The bridge between the graph, the controllers and the manipulator.
//!
//! Four kinds of threads share the bridge's state:
//! - the graph node hands in each frame's targets ([`Bridge::on_targets`]): they become the
//!   scene (objects touching the pipette's recent body are taken for the pipette itself),
//!   are served to every controller, and the reply is the state message of that frame;
//! - one reader per controller parses commands; `stop` is carried out by that reader
//!   itself: it opens a new stop epoch (every command queued before it is dropped), tells
//!   the device to stop through the device's own emergency handle and answers, sharing no
//!   lock and no queue with anything that waits on a controller or a device read;
//! - one writer per controller sends it its events from a bounded queue: a controller
//!   that stops reading is dropped once it has left [`OUTBOX_LIMIT`] bytes unread, and
//!   nobody else ever waits on its socket;
//! - the controller thread owns the device: it plans, moves leg by leg, polls the position,
//!   re-checks the rest of the path against every new scene (replanning or stopping when
//!   it is blocked) and stops when the scene goes stale.
//!
//! The bridge enforces the workspace and the speed limit itself; the device's own limits
//! come on top.

use crate::device::EmergencyStop;
use crate::device::{Device, DeviceError};
use crate::geom::{P3, dist, flip};
use crate::plan::{
    Goal, NoPath, Plan, PlannerConfig, check_rest, injection_point, plan_approach, plan_goto,
    plan_retract,
};
use crate::protocol::{Command, Line, MAX_LINE, parse_command, read_line, shorten};
use crate::registration::Registration;
use crate::scene::{Obstacle, Scene};
use schemas::{Cell3, ManipulatorState, PathPlan, Targets, TrackState, Tracks};
use serde_json::{Value, json};
use std::collections::HashMap;
use std::collections::VecDeque;
use std::io::{BufReader, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, channel};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

/// What the bridge needs besides its device.
#[derive(Clone, Debug)]
pub struct BridgeConfig {
    /// The planner's settings (pipette, clearance, workspace, …).
    pub planner: PlannerConfig,
    /// Where `home` goes, planner frame (`[X, Y, up]`), µm.
    pub home: P3,
    /// Fastest tip speed the bridge commands, µm/s.
    pub max_speed: f64,
    /// How the device's frame sits on the camera frame (`device = M·[X, Y, Z] + offset`).
    pub registration: Registration,
    /// A scene older than this stops any move and refuses new ones.
    pub stale: Duration,
    /// How often the device is polled.
    pub poll: Duration,
    /// Objects closer than this to the pipette's recent body are the pipette itself, µm.
    pub self_margin: f64,
    /// How far a target may move between frames and still be the same cell, µm.
    pub track_radius: f64,
    /// A target whose injection point moved farther than this is replanned, µm.
    pub replan_tolerance: f64,
    /// Height of a cell whose measured height is not trusted, µm.
    pub untrusted_height: f64,
    /// Bytes of events a controller may leave unread before it is dropped
    /// ([`OUTBOX_LIMIT`] by default).
    pub outbox_limit: usize,
}

impl BridgeConfig {
    /// The tip in the planner's frame when the device reads `device`.
    pub fn tip_at(&self, device: P3) -> P3 {
        flip(self.registration.to_scene(device))
    }

    /// Where the device goes to put the tip at `tip` (planner's frame).
    pub fn device_for(&self, tip: P3) -> P3 {
        self.registration.to_device(flip(tip))
    }
}

/// A line to one controller or to all.
fn event(kind: &str, mut fields: Value) -> String {
    if let Value::Object(m) = &mut fields {
        m.insert("event".into(), Value::String(kind.into()));
    }
    let mut s = fields.to_string();
    s.push('\n');
    s
}

/// Bytes of events a controller may leave unread before the bridge drops it: a feed of
/// a few seconds at camera rate. The lines are shared between controllers, so a crowd of
/// idle controllers costs this once, not once each.
pub const OUTBOX_LIMIT: usize = 16 << 20;

/// One controller's events on their way out: a bounded queue that its own writer thread
/// empties. Whoever sends only appends (or finds it full and drops the controller); no one
/// but that thread ever waits on the controller's socket.
struct Outbox {
    state: Mutex<OutState>,
    ready: Condvar,
    limit: usize,
}

#[derive(Default)]
struct OutState {
    lines: VecDeque<Arc<str>>,
    bytes: usize,
    /// No more lines: the writer sends what is queued, then ends the connection.
    closing: bool,
    /// Gone: nothing more is sent.
    dead: bool,
}

impl Outbox {
    fn lock(&self) -> MutexGuard<'_, OutState> {
        // Held only to move a line in or out; a panic cannot leave it half changed.
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Queues a line, unless the controller is gone or has left too much unread; an
    /// `urgent` one (the emergency stop's answer) goes before every line still queued.
    fn push(&self, line: &Arc<str>, urgent: bool) -> Result<(), Gone> {
        let mut st = self.lock();
        if st.dead || st.closing {
            return Err(Gone::Left);
        }
        if st.bytes + line.len() > self.limit {
            st.dead = true;
            st.lines.clear();
            drop(st);
            self.ready.notify_all();
            return Err(Gone::Overflow);
        }
        st.bytes += line.len();
        if urgent {
            st.lines.push_front(line.clone());
        } else {
            st.lines.push_back(line.clone());
        }
        drop(st);
        self.ready.notify_all();
        Ok(())
    }

    /// The next line to write; `None` when the writer should end.
    fn pop(&self) -> Option<Arc<str>> {
        let mut st = self.lock();
        loop {
            if st.dead {
                return None;
            }
            if let Some(l) = st.lines.pop_front() {
                st.bytes -= l.len();
                return Some(l);
            }
            if st.closing {
                return None;
            }
            st = self.ready.wait(st).unwrap_or_else(PoisonError::into_inner);
        }
    }

    fn set(&self, f: impl FnOnce(&mut OutState)) {
        f(&mut self.lock());
        self.ready.notify_all();
    }
}

/// Why a controller is no longer fed.
enum Gone {
    /// It hung up, or its connection was closed.
    Left,
    /// It left more than its limit of bytes unread.
    Overflow,
}

/// One connected controller.
struct Client {
    id: u64,
    out: Arc<Outbox>,
    /// For cutting the connection of a controller that is dropped.
    socket: TcpStream,
}

/// The connected controllers. Its lock is held only to queue lines, never while anything
/// is written to a socket, a connection is ended or a thread is started.
#[derive(Default)]
struct Clients {
    next_id: u64,
    list: Vec<Client>,
    /// Where the controllers cut off go to have their connections ended and be reported,
    /// off the lock: 200 idle controllers dropped at once held it 25–50 ms (under two CPU
    /// hogs), and a stop that came then waited for them.
    reaper: Option<Sender<(Client, Gone)>>,
}

impl Clients {
    fn broadcast(&mut self, line: &str) {
        self.queue(&line.into(), false, None);
    }

    /// [`Clients::broadcast`] ahead of every line still queued: what a controller waits
    /// for after a stop never waits behind scenes.
    fn broadcast_urgent(&mut self, line: &str) {
        self.queue(&line.into(), true, None);
    }

    fn send(&mut self, id: u64, line: &str) {
        self.queue(&line.into(), false, Some(id));
    }

    /// Queues `line` for controller `to` (every one: `None`); one that left too much
    /// unread, or is gone, is handed to the reaper.
    fn queue(&mut self, line: &Arc<str>, urgent: bool, to: Option<u64>) {
        let mut why = Vec::new();
        let cut: Vec<Client> = self
            .list
            .extract_if(.., |c| {
                if to.is_some_and(|id| id != c.id) {
                    return false;
                }
                match c.out.push(line, urgent) {
                    Ok(()) => false,
                    Err(g) => {
                        why.push(g);
                        true
                    }
                }
            })
            .collect();
        if cut.is_empty() {
            return;
        }
        let reaper = self.reaper.get_or_insert_with(|| {
            let (tx, rx) = channel::<(Client, Gone)>();
            std::thread::spawn(move || {
                for (k, (c, g)) in rx.into_iter().enumerate() {
                    reap(c, g);
                    // Each connection ended wakes its reader and writer: 200 at once woke
                    // 400 threads on two cores, and a stop waited behind them (64–80 ms
                    // seen, under two CPU hogs and in the full suite). A few a millisecond.
                    if k % REAP_BATCH == REAP_BATCH - 1 {
                        std::thread::sleep(std::time::Duration::from_millis(1));
                    }
                }
            });
            tx
        });
        for cut in cut.into_iter().zip(why) {
            // The reaper ends only when this sender is dropped.
            let _ = reaper.send(cut);
        }
    }

    /// Ends what goes out to one controller (after what was queued) and forgets it.
    fn close(&mut self, id: u64) {
        self.list.retain(|c| {
            if c.id == id {
                c.out.set(|st| st.closing = true);
            }
            c.id != id
        });
    }
}

/// Controllers the reaper ends before it pauses a millisecond.
const REAP_BATCH: usize = 8;

/// Ends a cut-off controller's connection (its reader and writer wake and end) and says
/// why, if it left too much unread: on the reaper's thread, where a full stderr pipe holds
/// up only the reaping, never the controllers' lock.
fn reap(c: Client, why: Gone) {
    let _ = c.socket.shutdown(std::net::Shutdown::Both);
    if let Gone::Overflow = why {
        runtime::errln!(
            "manipulator-bridge: controller {} dropped: it left more than {} kB of events unread",
            c.id,
            c.out.limit >> 10
        );
    }
}

/// Writes a controller's queued events to it until it is closed or gone.
fn write_out(out: Arc<Outbox>, mut socket: TcpStream) {
    while let Some(line) = out.pop() {
        if socket.write_all(line.as_bytes()).is_err() {
            out.set(|st| st.dead = true);
            let _ = socket.shutdown(std::net::Shutdown::Both);
            return;
        }
    }
    let _ = socket.shutdown(std::net::Shutdown::Write);
}

/// The emergency stop's state, shared by the readers and the controller thread without a
/// lock: each stop starts a new epoch; a command queued in an earlier epoch never runs.
#[derive(Default)]
struct Estop {
    epoch: AtomicU64,
    /// Commands queued for the controller thread and not yet taken.
    queued: AtomicU64,
}

/// A command on its way to the controller thread, with the stop epoch it came in.
struct Queued {
    id: u64,
    command: Command,
    epoch: u64,
}

/// State shared by the node and the controller thread (never held across a device read or
/// a socket write).
struct Shared {
    scene: Option<(Scene, Instant, u64)>,
    tip: P3,
    status: String,
    plan: Option<PathPlan>,
    trajectory: Vec<[f64; 4]>,
    /// Recent tip positions `(wall-clock ns, tip)`, for telling the pipette from cells.
    history: VecDeque<(u64, P3)>,
    /// The objects of the latest scene taken for the pipette itself (touching its recent
    /// body): no obstacles, but the cell the pipette is going into is among them.
    touching: Vec<Obstacle>,
    device: String,
    /// What the scene's ids are: per-frame cell ids, or track ids with what is known of
    /// each track.
    ids: Ids,
}

/// What a scene's cell ids name.
#[derive(Clone, Debug, Default)]
enum Ids {
    /// A cell's index in its frame (no track node feeds the bridge).
    #[default]
    Cells,
    /// Tracks: the live ones (state, frames missed, velocity `[X, Y]` µm/s) and the frame
    /// each ended one was last present in.
    Tracks {
        live: HashMap<u32, (TrackState, u32, [f64; 2])>,
        ended: HashMap<u32, u64>,
    },
}

/// The longest a scene's cells are led by their velocity, s: about the loop's latency at
/// camera rate (65–130 ms measured). A frame older than that (a loaded machine) is led no
/// further: a cell that reversed meanwhile (the synthetic scene's cells turn every second)
/// was thrown up to 24 µm off by a full second's lead, and every frame replanned the
/// approach, which never arrived.
const MAX_LEAD_S: f64 = 0.15;

/// Ended tracks remembered to say why they are refused.
const ENDED_KEPT: usize = 100_000;

/// The manipulator bridge: TCP server, controller thread and shared state.
pub struct Bridge {
    cfg: BridgeConfig,
    /// Each track's last cell and its position then: a lost track (a cell under the
    /// pipette) stays an obstacle where its track predicts it.
    last_cells: Mutex<HashMap<u32, (Cell3, [f64; 3])>>,
    shared: Arc<Mutex<Shared>>,
    clients: Arc<Mutex<Clients>>,
    /// Where it listens.
    pub addr: SocketAddr,
    /// Set when the bridge is dropped: the accepting thread then ends and frees the port.
    closing: Arc<AtomicBool>,
    estop: Arc<Estop>,
    stopper: Option<Arc<dyn EmergencyStop>>,
}

impl Drop for Bridge {
    fn drop(&mut self) {
        // A bridge that goes (its node stopped, its graph ended) leaves the device standing:
        // a serial manipulator would otherwise finish the leg it was given, into a cell
        // perhaps, with nobody watching.
        self.estop.epoch.fetch_add(1, Ordering::SeqCst);
        if let Some(s) = &self.stopper {
            let _ = s.stop_now();
        }
        // The accepting thread waits in accept(): a connection of our own wakes it to see
        // the flag (an in-process graph's bridge kept its port until the program ended).
        self.closing.store(true, Ordering::SeqCst);
        let _ = TcpStream::connect_timeout(&self.addr, Duration::from_millis(500));
        // The controllers' connections end, their readers with them, and then the
        // controller thread, which owns the device.
        for c in lock(&self.clients).list.drain(..) {
            c.out.set(|st| st.dead = true);
            let _ = c.socket.shutdown(std::net::Shutdown::Both);
        }
    }
}

/// A target cell followed from frame to frame by its footprint centre and drift.
#[derive(Clone, Copy, Debug)]
struct Follow {
    /// Its id in the scene it was last seen in (its track's, when `by_track`).
    id: u32,
    /// Whether ids are tracks: the target is then its track, wherever it is.
    by_track: bool,
    centre: [f64; 2],
    /// The frame it was last seen in.
    frame: u64,
    /// Its drift, µm per frame.
    velocity: [f64; 2],
    /// Its height above its base as last measured with trust, µm.
    height: f64,
}

impl Follow {
    fn new(c: &Obstacle, frame: u64, by_track: bool) -> Self {
        Self {
            id: c.id,
            by_track,
            centre: c.centre,
            frame,
            velocity: [0.0; 2],
            height: c.top - c.base,
        }
    }

    /// `scene` with the target standing at its last trusted height where this frame's
    /// measurement of it is doubtful: a doubtful frame of the cell the pipette goes into
    /// made it an obstacle of the tallest plausible height, in the pipette's way, and a
    /// replan refused it. Other cells keep what the frame says.
    fn trusted_in(&self, mut scene: Scene) -> Scene {
        if let Some(o) = scene
            .cells
            .iter_mut()
            .find(|o| o.id == self.id && !o.trusted)
        {
            o.top = o.base + self.height;
            o.prism.zhi = o.top;
            o.trusted = true;
            o.doubt = None;
        }
        scene
    }

    /// The cell of `scene` that is this target: the nearest to where its drift puts it
    /// now, within `radius`. Follows it there.
    fn find<'a>(&mut self, scene: &'a Scene, radius: f64) -> Option<&'a Obstacle> {
        if self.by_track {
            let c = scene.cell(self.id)?;
            self.centre = c.centre;
            self.frame = scene.frame;
            if c.trusted {
                self.height = c.top - c.base;
            }
            return Some(c);
        }
        let frames = scene.frame.saturating_sub(self.frame).max(1) as f64;
        let guess = [
            self.centre[0] + self.velocity[0] * frames,
            self.centre[1] + self.velocity[1] * frames,
        ];
        let c = scene
            .nearest(guess, radius)
            .or_else(|| scene.nearest(self.centre, radius))?;
        // Its drift from the last two sightings, no faster than the radius allows.
        let v = [0, 1].map(|k| ((c.centre[k] - self.centre[k]) / frames).clamp(-radius, radius));
        *self = Self {
            id: c.id,
            by_track: false,
            centre: c.centre,
            frame: scene.frame,
            velocity: v,
            height: if c.trusted {
                c.top - c.base
            } else {
                self.height
            },
        };
        Some(c)
    }
}

/// What the controller thread is doing.
struct Job {
    plan: Plan,
    /// The waypoint it is moving to.
    next: usize,
    speed: f64,
    /// The target as last seen (approach only).
    target: Option<Follow>,
    seen_scene: u64,
    last_progress: Instant,
    /// The stop epoch it began in: a stop since then ends it before its next move.
    epoch: u64,
    /// Short legs added after the target, which drifted while the last leg ran.
    corrections: u32,
    /// How far the leg under way's end has moved since the device was sent there, µm.
    stale: f64,
    /// Whether the device is to be sent to the leg's moved end.
    retarget: bool,
}

/// How far a tracked target may move the end of the leg under way before the device is
/// sent to the new end, µm.
const RETARGET_UM: f64 = 2.0;

/// How close to its tracked cell's injection point an approach ends, µm: farther, a short
/// leg follows the cell.
const FOLLOW_TOLERANCE_UM: f64 = 0.5;

/// Most short legs after a drifting target per approach.
const MAX_CORRECTIONS: u32 = 20;

struct Controller {
    cfg: BridgeConfig,
    device: Option<Box<dyn Device>>,
    missing: String,
    shared: Arc<Mutex<Shared>>,
    clients: Arc<Mutex<Clients>>,
    last_tip: Arc<Mutex<P3>>,
    estop: Arc<Estop>,
    /// The stop epoch whose stop it has settled.
    settled: u64,
    rx: Receiver<Queued>,
    job: Option<Job>,
    /// The cell the pipette was last sent into, by footprint centre.
    inside: Option<[f64; 2]>,
    t0: Instant,
}

fn plan_view(p: &Plan) -> PathPlan {
    PathPlan {
        goal: match p.goal {
            Goal::Approach { .. } => "approach",
            Goal::Retract => "retract",
            Goal::Goto => "goto",
        }
        .into(),
        target: match p.goal {
            Goal::Approach { cell } => Some(cell),
            _ => None,
        },
        frame: p.frame,
        waypoints: p.waypoints.iter().map(|w| flip(*w)).collect(),
        axial_from: p.axial_from as u32,
        end: flip(p.end),
        length: p.length,
        min_clearance: p.min_clearance.is_finite().then_some(p.min_clearance),
    }
}

impl Bridge {
    /// Starts listening on `listen` and the controller thread with `device` (none: the
    /// bridge serves the scene and answers motion commands with an error saying
    /// `missing`).
    pub fn start(
        cfg: BridgeConfig,
        listen: &str,
        device: Result<Box<dyn Device>, DeviceError>,
    ) -> Result<Self, String> {
        let listener =
            TcpListener::bind(listen).map_err(|e| format!("cannot listen on {listen}: {e}"))?;
        let addr = listener.local_addr().map_err(|e| e.to_string())?;
        let (device, missing) = match device {
            Ok(d) => (Some(d), String::new()),
            Err(e) => (None, e.0),
        };
        let shared = Arc::new(Mutex::new(Shared {
            scene: None,
            tip: cfg.home,
            status: if device.is_some() { "idle" } else { "error" }.into(),
            plan: None,
            trajectory: Vec::new(),
            history: VecDeque::new(),
            touching: Vec::new(),
            device: device.as_ref().map_or("none".into(), |d| d.describe()),
            ids: Ids::Cells,
        }));
        let clients: Arc<Mutex<Clients>> = Arc::default();
        let estop = Arc::new(Estop::default());
        let closing = Arc::new(AtomicBool::new(false));
        let last_tip = Arc::new(Mutex::new(flip(cfg.home)));
        let (tx, rx) = channel();
        let mut c = Controller {
            cfg: cfg.clone(),
            device,
            missing,
            shared: shared.clone(),
            clients: clients.clone(),
            last_tip: last_tip.clone(),
            estop: estop.clone(),
            settled: 0,
            rx,
            job: None,
            inside: None,
            t0: Instant::now(),
        };
        let mut stopper = None;
        if let Some(d) = c.device.as_mut() {
            match d.state().and_then(|s| Ok((s, d.emergency_stop()?))) {
                Ok((s, e)) => {
                    let tip = cfg.tip_at(s.position);
                    c.shared.lock().expect("shared").tip = tip;
                    *lock(&last_tip) = flip(tip);
                    stopper = Some(e);
                }
                Err(e) => {
                    c.missing = e.0;
                    c.device = None;
                }
            }
        }
        {
            let ctx = Readers {
                outbox_limit: cfg.outbox_limit,
                clients: clients.clone(),
                tx,
                estop: estop.clone(),
                stopper: stopper.clone(),
                last_tip,
            };
            let closing = closing.clone();
            std::thread::spawn(move || accept(listener, ctx, closing));
        }
        std::thread::spawn(move || c.run());
        Ok(Self {
            cfg,
            last_cells: Mutex::default(),
            shared,
            clients,
            addr,
            closing,
            estop,
            stopper,
        })
    }

    /// Controllers connected now.
    pub fn controllers(&self) -> usize {
        self.clients.lock().expect("clients").list.len()
    }

    /// Takes one frame's targets: updates the scene, serves
    /// it to the controllers and returns the manipulator state for this frame.
    pub fn on_targets(&self, t: &Targets) -> Result<ManipulatorState, String> {
        // The scene line: the targets as they travel (their JSON), tagged.
        let raw = &serde_json::to_vec(t).map_err(|e| e.to_string())?[..];
        let mut line = Vec::with_capacity(raw.len() + 20);
        line.extend_from_slice(b"{\"event\":\"scene\",");
        line.extend_from_slice(raw.strip_prefix(b"{").unwrap_or(raw));
        line.push(b'\n');
        self.take_scene(t, &String::from_utf8_lossy(&line))
    }

    /// Takes one frame's tracks: the scene's cells are the tracks' (ids their track ids,
    /// heights the fused ones), each led by its track's velocity over the frame's age; a
    /// lost track's cell stays where its track predicts it. Serves the scene, with the
    /// tracks, to the controllers and returns the manipulator state for this frame.
    pub fn on_tracks(&self, t: &Tracks) -> Result<ManipulatorState, String> {
        let now = runtime::process::now_ns();
        // The frame's age now: what the loop's latency has let every cell move.
        let lead_s = if t.capture_ns > 0 && now > t.capture_ns {
            ((now - t.capture_ns) as f64 * 1e-9).min(MAX_LEAD_S)
        } else {
            0.0
        };
        let mut cells = Vec::with_capacity(t.tracks.len());
        {
            let mut last = lock(&self.last_cells);
            last.retain(|id, _| t.tracks.iter().any(|tr| tr.id == *id));
            for tr in &t.tracks {
                let (mut c, moved) = match &tr.cell {
                    Some(c) => {
                        last.insert(tr.id, (c.clone(), tr.position));
                        (c.clone(), [0.0; 2])
                    }
                    None => match last.get(&tr.id) {
                        Some((c, then)) => (
                            c.clone(),
                            [tr.position[0] - then[0], tr.position[1] - then[1]],
                        ),
                        None => continue,
                    },
                };
                let d = [
                    moved[0] + tr.velocity[0] * lead_s,
                    moved[1] + tr.velocity[1] * lead_s,
                ];
                c.centroid[0] += d[0];
                c.centroid[1] += d[1];
                for p in &mut c.contour {
                    p[0] += d[0];
                    p[1] += d[1];
                }
                c.id = tr.id;
                if let (Some(h), Some(s)) = (tr.height, tr.height_std) {
                    c.height = Some(h);
                    c.quality.height_std = Some(s);
                    c.quality.trusted = tr.trusted;
                    c.quality.doubt = if tr.trusted {
                        None
                    } else {
                        Some(c.quality.doubt.take().unwrap_or_else(|| {
                            format!(
                                "its track's fused height ({h:.1} ± {s:.1}) is not yet sure to 2.5 %"
                            )
                        }))
                    };
                }
                cells.push(c);
            }
        }
        let targets = Targets {
            frame: t.frame,
            capture_ns: t.capture_ns,
            unit: t.unit.clone(),
            cells,
            substrate: t.substrate,
        };
        {
            let um = crate::scene::um_per_unit(&t.unit)?;
            let mut sh = self.shared.lock().expect("shared");
            let (old, mut ended) = match std::mem::take(&mut sh.ids) {
                Ids::Tracks { live, ended } => (live, ended),
                Ids::Cells => (HashMap::new(), HashMap::new()),
            };
            let live: HashMap<u32, (TrackState, u32, [f64; 2])> = t
                .tracks
                .iter()
                .map(|tr| {
                    let v = [tr.velocity[0] * um, tr.velocity[1] * um];
                    (tr.id, (tr.state, tr.missed, v))
                })
                .collect();
            for id in old.keys().filter(|id| !live.contains_key(id)) {
                ended.insert(*id, t.frame.saturating_sub(1));
            }
            if ended.len() > ENDED_KEPT {
                ended.clear();
            }
            sh.ids = Ids::Tracks { live, ended };
        }
        let mut v = serde_json::to_value(&targets).map_err(|e| e.to_string())?;
        let summary: Vec<Value> = t
            .tracks
            .iter()
            .map(|tr| {
                json!({
                    "id": tr.id,
                    "state": tr.state,
                    "age": tr.age,
                    "missed": tr.missed,
                    "position": tr.position,
                    "velocity": tr.velocity,
                    "height": tr.height,
                    "height_std": tr.height_std,
                    "trusted": tr.trusted,
                    "frames_used": tr.frames_used,
                })
            })
            .collect();
        if let Value::Object(m) = &mut v {
            m.insert("ids".into(), "track".into());
            m.insert("tracks".into(), summary.into());
        }
        let line = format!("{{\"event\":\"scene\",{}\n", &v.to_string()[1..]);
        self.take_scene(&targets, &line)
    }

    /// Makes `t` the scene, sends `line` to every controller and says the manipulator's
    /// state for the frame.
    fn take_scene(&self, t: &Targets, line: &str) -> Result<ManipulatorState, String> {
        let mut scene = Scene::from_targets(t, self.cfg.untrusted_height)?;
        let cfg = &self.cfg.planner;
        let u = cfg.pipette.axis();
        let mut sh = self.shared.lock().expect("shared");
        // Where the pipette may have been when this frame was captured: from a second
        // before its capture time on.
        let since = t.capture_ns.saturating_sub(1_000_000_000);
        let mut tips: Vec<P3> = sh
            .history
            .iter()
            .filter(|(ns, _)| *ns >= since)
            .map(|(_, p)| *p)
            .collect();
        tips.push(sh.tip);
        let ignored = scene.touching(&tips, u, cfg.pipette.length, self.cfg.self_margin);
        sh.touching = scene
            .cells
            .iter()
            .filter(|c| ignored.contains(&c.id))
            .cloned()
            .collect();
        scene.cells.retain(|c| !ignored.contains(&c.id));
        let seq = sh.scene.as_ref().map_or(0, |s| s.2 + 1);
        sh.scene = Some((scene, Instant::now(), seq));
        let state = ManipulatorState {
            frame: t.frame,
            capture_ns: t.capture_ns,
            device: sh.device.clone(),
            status: sh.status.clone(),
            tip: flip(sh.tip),
            elevation_deg: cfg.pipette.elevation_deg,
            azimuth_deg: cfg.pipette.azimuth_deg,
            clearance: cfg.clearance,
            trajectory: std::mem::take(&mut sh.trajectory)
                .into_iter()
                .map(|[t, x, y, up]| [t, x, y, -up])
                .collect(),
            plan: sh.plan.clone(),
            ignored,
        };
        drop(sh);
        self.clients.lock().expect("clients").broadcast(line);
        Ok(state)
    }
}

/// What every controller's reader thread holds.
#[derive(Clone)]
struct Readers {
    /// Bytes a controller may leave unread.
    outbox_limit: usize,
    clients: Arc<Mutex<Clients>>,
    tx: Sender<Queued>,
    estop: Arc<Estop>,
    /// The device's emergency stop (none without a device).
    stopper: Option<Arc<dyn EmergencyStop>>,
    last_tip: Arc<Mutex<P3>>,
}

/// A lock held only to copy or queue a few values: a panic elsewhere cannot leave what it
/// guards half changed, so a poisoned one is used as it is.
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

impl Readers {
    fn send(&self, id: u64, line: &str) {
        lock(&self.clients).send(id, line);
    }

    /// The emergency stop, on the reader that read it.
    fn emergency_stop(&self, id: u64) {
        // A new epoch first: whatever the controller thread takes from now on, or is about
        // to start, it sees the stop.
        self.estop.epoch.fetch_add(1, Ordering::SeqCst);
        let dropped = self.estop.queued.load(Ordering::SeqCst);
        let result = self.stopper.as_ref().map_or(Ok(()), |s| s.stop_now());
        let tip = *lock(&self.last_tip);
        let line = match result {
            Ok(()) => event(
                "stopped",
                json!({ "tip": tip, "dropped": dropped, "by": id }),
            ),
            Err(e) => event(
                "error",
                json!({ "message": format!("the emergency stop could not reach the device: {e}") }),
            ),
        };
        lock(&self.clients).broadcast_urgent(&line);
    }

    /// Reads one controller's commands until its connection ends.
    fn serve(&self, id: u64, reader: TcpStream) {
        let mut reader = BufReader::new(reader);
        loop {
            let line = match read_line(&mut reader, MAX_LINE) {
                Ok(Line::Text(l)) => l,
                Ok(Line::NotUtf8) => {
                    self.send(
                        id,
                        &event(
                            "error",
                            json!({ "message": "the line is not UTF-8 text; send one JSON command per line" }),
                        ),
                    );
                    continue;
                }
                Ok(Line::TooLong) => {
                    {
                        let mut c = lock(&self.clients);
                        c.send(
                            id,
                            &event(
                                "error",
                                json!({ "message": format!("a line longer than {MAX_LINE} bytes; closing this connection") }),
                            ),
                        );
                        c.close(id);
                    }
                    // Read what is still coming and throw it away, for a while: closing
                    // with unread input would reset the connection and could lose the
                    // error line on its way out. A stop among it still stops.
                    let _ = reader
                        .get_ref()
                        .set_read_timeout(Some(Duration::from_millis(200)));
                    let t0 = Instant::now();
                    while t0.elapsed() < Duration::from_secs(2) {
                        match read_line(&mut reader, MAX_LINE) {
                            Ok(Line::Text(l)) if parse_command(&l) == Ok(Command::Stop) => {
                                self.emergency_stop(id)
                            }
                            Ok(Line::Text(_) | Line::NotUtf8 | Line::TooLong) => {}
                            Ok(Line::End) | Err(_) => break,
                        }
                    }
                    break;
                }
                Ok(Line::End) | Err(_) => break,
            };
            if line.trim().is_empty() {
                continue;
            }
            match parse_command(&line) {
                Ok(Command::Stop) => self.emergency_stop(id),
                Ok(command) => {
                    self.estop.queued.fetch_add(1, Ordering::SeqCst);
                    let epoch = self.estop.epoch.load(Ordering::SeqCst);
                    if self.tx.send(Queued { id, command, epoch }).is_err() {
                        break;
                    }
                }
                Err(m) => self.send(
                    id,
                    &event(
                        "error",
                        json!({ "message": m, "command": shorten(&line, 200) }),
                    ),
                ),
            }
        }
    }
}

fn accept(listener: TcpListener, ctx: Readers, closing: Arc<AtomicBool>) {
    for s in listener.incoming() {
        if closing.load(Ordering::SeqCst) {
            return;
        }
        let Ok(s) = s else {
            // Out of file handles, say: a moment before the next try, not a busy loop.
            std::thread::sleep(Duration::from_millis(100));
            continue;
        };
        let _ = s.set_nodelay(true);
        let (Ok(reader), Ok(writer)) = (s.try_clone(), s.try_clone()) else {
            continue;
        };
        let out = Arc::new(Outbox {
            state: Mutex::default(),
            ready: Condvar::new(),
            limit: ctx.outbox_limit,
        });
        let id = {
            let mut c = lock(&ctx.clients);
            c.next_id += 1;
            let id = c.next_id;
            c.list.push(Client {
                id,
                out: out.clone(),
                socket: s,
            });
            id
        };
        std::thread::spawn(move || write_out(out, writer));
        let ctx = ctx.clone();
        std::thread::spawn(move || {
            ctx.serve(id, reader);
            // A controller that hung up (or closed its sending side) is served no longer:
            // what is queued goes out, then its connection ends and its threads with it.
            lock(&ctx.clients).close(id);
        });
    }
}

impl Controller {
    fn broadcast(&self, line: &str) {
        self.clients.lock().expect("clients").broadcast(line);
    }

    fn tell(&self, id: u64, line: &str) {
        self.clients.lock().expect("clients").send(id, line);
    }

    fn set_status(&self, s: &str) {
        self.shared.lock().expect("shared").status = s.into();
    }

    fn run(mut self) {
        loop {
            self.settle_stop();
            match self.rx.recv_timeout(self.cfg.poll) {
                Ok(q) => {
                    self.estop.queued.fetch_sub(1, Ordering::SeqCst);
                    self.settle_stop();
                    if q.epoch != self.estop.epoch.load(Ordering::SeqCst) {
                        self.tell(
                            q.id,
                            &event(
                                "error",
                                json!({ "message": "dropped: an emergency stop came after it" }),
                            ),
                        );
                    } else {
                        self.command(q.id, q.command, q.epoch);
                    }
                }
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => return,
            }
            self.tick();
        }
    }

    /// After an emergency stop (the reader already told the device): the job ends, and the
    /// device's own state is settled by its owner, this thread.
    fn settle_stop(&mut self) {
        let epoch = self.estop.epoch.load(Ordering::SeqCst);
        if epoch == self.settled {
            return;
        }
        self.settled = epoch;
        self.job = None;
        if let Some(d) = self.device.as_mut()
            && let Err(e) = d.stop()
        {
            self.fail(e);
            return;
        }
        self.set_status("stopped");
    }

    /// Whether an emergency stop came since `epoch` (and was settled).
    fn stopped_since(&mut self, epoch: u64) -> bool {
        if self.estop.epoch.load(Ordering::SeqCst) == epoch {
            return false;
        }
        self.settle_stop();
        true
    }

    fn fail(&mut self, e: DeviceError) {
        self.job = None;
        self.set_status("error");
        self.broadcast(&event("error", json!({ "message": e.0 })));
    }

    /// The scene if there is a fresh one.
    fn fresh_scene(&self) -> Result<(Scene, u64), String> {
        let sh = self.shared.lock().expect("shared");
        match &sh.scene {
            None => Err("no scene yet: no frame has reached the bridge".into()),
            Some((_, at, _)) if at.elapsed() > self.cfg.stale => Err(format!(
                "the scene is stale: no frame for {:.1} s (limit {:.1} s); not moving blind",
                at.elapsed().as_secs_f64(),
                self.cfg.stale.as_secs_f64()
            )),
            Some((s, _, seq)) => Ok((s.clone(), *seq)),
        }
    }

    /// Stops the device and waits until it stands; its position then.
    fn halt(&mut self) -> Result<P3, DeviceError> {
        let d = self.device.as_mut().expect("a device");
        d.stop()?;
        let t0 = Instant::now();
        loop {
            let s = d.state()?;
            if !s.moving {
                return Ok(self.cfg.tip_at(s.position));
            }
            if t0.elapsed() > Duration::from_secs(5) {
                return Err(DeviceError(format!(
                    "{} did not stop within 5 s",
                    d.describe()
                )));
            }
            std::thread::sleep(self.cfg.poll);
        }
    }

    /// The scene id of the cell an approach names: its track where ids are tracks (a
    /// track that is not confirmed is refused with the reason), else its frame index.
    fn target_of(&self, c: &Command) -> Result<Option<u32>, String> {
        let Command::Approach { track, cell, .. } = *c else {
            return Ok(None);
        };
        let sh = self.shared.lock().expect("shared");
        match (&sh.ids, track, cell) {
            (Ids::Cells, None, Some(c)) => Ok(Some(c)),
            (Ids::Cells, Some(t), _) => Err(format!(
                "there is no track {t}: no track node feeds this bridge; name the cell by its id in the latest frame (\"cell\"), or put a track node between triangulate and the bridge"
            )),
            (Ids::Tracks { .. }, None, Some(c)) => Err(format!(
                "\"cell\": {c} names a cell by its index in one frame, which changes from frame to frame; name it by its track (\"track\": its id in the scene lines)"
            )),
            (Ids::Tracks { live, ended }, Some(t), _) => match live.get(&t) {
                Some((TrackState::Confirmed, ..)) => Ok(Some(t)),
                Some((TrackState::Tentative, ..)) => Err(format!(
                    "track {t} is tentative: seen in too few frames yet to be taken for a cell; ask again in a few frames"
                )),
                Some((TrackState::Lost, missed, _)) => Err(format!(
                    "track {t} is lost: its cell has not been seen for {missed} frame(s) (covered or out of view); it is not approached until it is seen again"
                )),
                None => Err(match ended.get(&t) {
                    Some(f) => format!(
                        "track {t} ended: its cell was last followed in frame {f} and has been gone since; ids are never reused"
                    ),
                    None => format!("there is no track {t}"),
                }),
            },
            (_, None, None) => Err("an approach names no cell".into()),
        }
    }

    fn plan_for(
        &self,
        c: &Command,
        target: Option<u32>,
        scene: &Scene,
        tip: P3,
    ) -> Result<Plan, NoPath> {
        let cfg = &self.cfg.planner;
        match *c {
            Command::Approach { .. } => plan_approach(
                scene,
                cfg,
                tip,
                target.expect("an approach's target is resolved before it is planned"),
            ),
            Command::Retract { .. } => {
                let inside = self
                    .inside
                    .and_then(|c| scene.nearest(c, self.cfg.track_radius))
                    .map(|c| c.id);
                plan_retract(scene, cfg, tip, inside)
            }
            // Commands are in the camera frame.
            Command::Goto { x, y, z, .. } => plan_goto(scene, cfg, tip, flip([x, y, z])),
            Command::Home { .. } => plan_goto(scene, cfg, tip, self.cfg.home),
            Command::Stop => unreachable!("stop is not planned"),
        }
    }

    fn command(&mut self, id: u64, c: Command, epoch: u64) {
        if self.device.is_none() {
            let m = format!(
                "no manipulator: {}; the bridge serves the scene only",
                self.missing
            );
            self.tell(id, &event("error", json!({ "message": m })));
            return;
        }
        let (scene, seq) = match self.fresh_scene() {
            Ok(s) => s,
            Err(m) => {
                self.tell(id, &event("error", json!({ "message": m })));
                return;
            }
        };
        // A new command replaces the one under way, from where the tip stops.
        let tip = if self.job.take().is_some() {
            match self.halt() {
                Ok(p) => p,
                Err(e) => return self.fail(e),
            }
        } else {
            match self.device.as_mut().expect("device").state() {
                Ok(s) => self.cfg.tip_at(s.position),
                Err(e) => return self.fail(e),
            }
        };
        let target = match self.target_of(&c) {
            Ok(t) => t,
            Err(m) => {
                self.tell(id, &event("error", json!({ "message": m })));
                return;
            }
        };
        let by_track = matches!(self.shared.lock().expect("shared").ids, Ids::Tracks { .. });
        let speed = match c {
            Command::Approach { speed, .. }
            | Command::Retract { speed }
            | Command::Goto { speed, .. }
            | Command::Home { speed } => speed,
            Command::Stop => None,
        }
        .map_or(self.cfg.max_speed, |s| s.min(self.cfg.max_speed));
        match self.plan_for(&c, target, &scene, tip) {
            Ok(plan) => {
                let target = match plan.goal {
                    Goal::Approach { cell } => scene
                        .cell(cell)
                        .map(|c| Follow::new(c, scene.frame, by_track)),
                    _ => None,
                };
                if self.stopped_since(epoch) {
                    self.tell(
                        id,
                        &event(
                            "error",
                            json!({ "message": "dropped: an emergency stop came after it" }),
                        ),
                    );
                    return;
                }
                self.begin(plan, speed, target, seq, None, epoch);
            }
            Err(e) => {
                self.set_status("blocked");
                self.broadcast(&event(
                    "blocked",
                    json!({ "reason": e.to_string(), "cells": e.blocking, "command": c }),
                ));
            }
        }
    }

    /// Starts executing `plan`; `replanned` says why it replaces the one under way.
    fn begin(
        &mut self,
        plan: Plan,
        speed: f64,
        target: Option<Follow>,
        seen: u64,
        replanned: Option<String>,
        epoch: u64,
    ) {
        // A stop that came while it was planned: no plan is announced, none runs.
        if self.stopped_since(epoch) {
            return;
        }
        self.broadcast(&event(
            "plan",
            json!({ "plan": plan_view(&plan), "speed": speed, "replanned": replanned }),
        ));
        {
            let mut sh = self.shared.lock().expect("shared");
            sh.plan = Some(plan_view(&plan));
            sh.status = "moving".into();
        }
        // A goto leaves the cell behind; a retract still needs to know which it leaves.
        if plan.goal == Goal::Goto {
            self.inside = None;
        }
        self.job = Some(Job {
            next: 0,
            plan,
            speed,
            target,
            seen_scene: seen,
            last_progress: Instant::now(),
            epoch,
            corrections: 0,
            stale: 0.0,
            retarget: false,
        });
        // Leg 0 ends where the tip is: the first tick starts the move to waypoint 1.
    }

    fn tick(&mut self) {
        let Some(d) = self.device.as_mut() else {
            return;
        };
        let st = match d.state() {
            Ok(s) => s,
            Err(e) => return self.fail(e),
        };
        let tip = self.cfg.tip_at(st.position);
        let t = self.t0.elapsed().as_secs_f64();
        *lock(&self.last_tip) = flip(tip);
        {
            let mut sh = self.shared.lock().expect("shared");
            sh.tip = tip;
            if st.moving || self.job.is_some() {
                sh.trajectory.push([t, tip[0], tip[1], tip[2]]);
            }
            let now = runtime::process::now_ns();
            if sh.history.back().is_none_or(|(_, p)| dist(*p, tip) > 1.0) {
                sh.history.push_back((now, tip));
            }
            while sh.history.len() > 1
                && sh
                    .history
                    .front()
                    .is_some_and(|(ns, _)| now - ns > 5_000_000_000)
            {
                sh.history.pop_front();
            }
        }
        if self.job.is_none() {
            return;
        }
        // A stale scene stops the move.
        let (age, seq) = {
            let sh = self.shared.lock().expect("shared");
            sh.scene
                .as_ref()
                .map_or((Duration::MAX, 0), |s| (s.1.elapsed(), s.2))
        };
        if age > self.cfg.stale {
            self.job = None;
            if let Err(e) = self.halt() {
                return self.fail(e);
            }
            self.set_status("blocked");
            self.broadcast(&event(
                "blocked",
                json!({ "reason": format!("stale scene: no frame for {:.1} s; stopped", age.as_secs_f64()), "cells": [] }),
            ));
            return;
        }
        if self.job.as_ref().is_some_and(|j| j.seen_scene != seq) && !self.recheck(tip, seq) {
            return;
        }
        let arriving = !st.moving
            && self
                .job
                .as_ref()
                .is_some_and(|j| j.next + 1 >= j.plan.waypoints.len());
        let correction = if arriving { self.correction(tip) } else { None };
        if st.moving && self.job.as_ref().is_some_and(|j| j.retarget) {
            // The leg's end moved with the tracked cell: the device goes there instead.
            let (to, speed, epoch) = {
                let j = self.job.as_mut().expect("job");
                j.retarget = false;
                j.stale = 0.0;
                (j.plan.waypoints[j.next], j.speed, j.epoch)
            };
            if let Err(e) = self.halt() {
                return self.fail(e);
            }
            self.start_leg(to, speed, epoch);
            return;
        }
        let job = self.job.as_mut().expect("job");
        if !st.moving {
            if let Some(inj) = correction {
                // The tracked cell moved on while the last leg ran: one more short leg to
                // where its injection point is now.
                job.plan.length += dist(job.plan.end, inj);
                job.plan.waypoints.push(inj);
                job.plan.end = inj;
                job.corrections += 1;
            }
            // At the waypoint it was moving to (the tip itself for leg 0).
            job.next += 1;
            if job.next >= job.plan.waypoints.len() {
                let plan = self.job.take().expect("job").plan;
                let err = dist(tip, plan.end);
                if let Goal::Approach { .. } = plan.goal {
                    self.inside = Some([plan.end[0], plan.end[1]]);
                }
                self.set_status("arrived");
                self.broadcast(&event(
                    "arrived",
                    json!({ "tip": flip(tip), "end": flip(plan.end), "error_um": err, "plan": plan_view(&plan) }),
                ));
                return;
            }
            let (to, speed, epoch) = (job.plan.waypoints[job.next], job.speed, job.epoch);
            if !self.start_leg(to, speed, epoch) {
                return;
            }
        }
        let job = self.job.as_mut().expect("job");
        if job.last_progress.elapsed() >= Duration::from_millis(100) {
            job.last_progress = Instant::now();
            let w = &job.plan.waypoints;
            let k = job.next.min(w.len() - 1);
            let remaining =
                dist(tip, w[k]) + w[k..].windows(2).map(|p| dist(p[0], p[1])).sum::<f64>();
            let line = event(
                "progress",
                json!({ "tip": flip(tip), "leg": k, "remaining_um": remaining }),
            );
            self.broadcast(&line);
        }
    }

    /// Sends the device to `to` at `speed` µm/s unless a stop came since `epoch`; `false`
    /// when it did not move on (a stop, or a fault, said).
    fn start_leg(&mut self, to: P3, speed: f64, epoch: u64) -> bool {
        if self.stopped_since(epoch) {
            return false;
        }
        // In device units: no scene direction moves faster than `speed`.
        let speed = speed * self.cfg.registration.least_stretch();
        let r = self
            .device
            .as_mut()
            .expect("device")
            .start_move(self.cfg.device_for(to), speed);
        if let Err(e) = r {
            self.fail(e);
            return false;
        }
        // A stop that came while the move was going out: it may have reached the device
        // first, so the move is stopped again.
        !self.stopped_since(epoch)
    }

    /// Where the injection point of an approach's tracked cell is now, when it lies
    /// farther from the tip at the plan's end than [`FOLLOW_TOLERANCE_UM`] (and less than the
    /// replan tolerance: farther is a cell that moved, not one that drifts) while the last
    /// leg ran.
    fn correction(&self, tip: P3) -> Option<P3> {
        let job = self.job.as_ref()?;
        let f = job.target.as_ref()?;
        if !f.by_track || job.corrections >= MAX_CORRECTIONS {
            return None;
        }
        let Goal::Approach { .. } = job.plan.goal else {
            return None;
        };
        let (scene, _) = self.fresh_scene().ok()?;
        // The pipette at its end touches the cell: it is then among the touching ones. The
        // track's velocity leads the leg (below).
        let (touching, v) = {
            let sh = self.shared.lock().expect("shared");
            let v = match &sh.ids {
                Ids::Tracks { live, .. } => live.get(&f.id).map_or([0.0; 2], |l| l.2),
                Ids::Cells => [0.0; 2],
            };
            (sh.touching.clone(), v)
        };
        let c = scene
            .cell(f.id)
            .or_else(|| touching.iter().find(|o| o.id == f.id))?;
        if !c.trusted {
            return None;
        }
        let inj = injection_point(c, &self.cfg.planner);
        let off = dist(inj, tip);
        if !(off > FOLLOW_TOLERANCE_UM && off <= self.cfg.replan_tolerance.max(FOLLOW_TOLERANCE_UM))
        {
            return None;
        }
        // Led by the track's velocity over the leg's own time: a short leg lagged the cell
        // by what it drifted while the leg ran (arrivals 1.2–1.5 µm off a cell at 20 µm/s).
        let speed = job.speed.max(1e-6);
        let mut to = inj;
        for _ in 0..3 {
            let t = (dist(to, tip) / speed).min(MAX_LEAD_S);
            to = [inj[0] + v[0] * t, inj[1] + v[1] * t, inj[2]];
        }
        Some(to)
    }

    /// Checks the rest of the path against a new scene; replans or stops when it is
    /// blocked or the target moved. `false` when the job ended.
    fn recheck(&mut self, tip: P3, seq: u64) -> bool {
        let Ok((scene, _)) = self.fresh_scene() else {
            return true;
        };
        let cfg = self.cfg.planner;
        // The target the pipette reaches touches its body, and is then taken for the
        // pipette itself: it is followed there too.
        let touched = Scene {
            frame: scene.frame,
            cells: self.shared.lock().expect("shared").touching.clone(),
            substrate: scene.substrate,
        };
        let job = self.job.as_mut().expect("job");
        job.seen_scene = seq;
        let committed = job.next > job.plan.axial_from;
        let mut exempt = None;
        let mut moved = false;
        let mut lost = None;
        let mut scene = scene;
        if let Some(follow) = job.target.as_mut() {
            let before = *follow;
            match follow.find(&scene, self.cfg.track_radius) {
                Some(c) => {
                    exempt = Some(c.id);
                    // Where the target's measurement is doubtful, its injection point is
                    // the trusted frames' (the plan's).
                    let inj = injection_point(c, &cfg);
                    if follow.by_track && c.trusted {
                        // On its way to a tracked cell: the path moves with the cell, scene
                        // by scene (its track says it is the same cell, however far it went
                        // within `track_radius`; the path is checked again below), instead
                        // of a halt and a new plan each time it has moved more than
                        // `replan_tolerance`: on a loaded machine scenes come 5 a second and
                        // a cell at 30 µm/s moved that far in every one, so each scene
                        // replanned and the approach never arrived.
                        let d = [0, 1, 2].map(|k| inj[k] - job.plan.end[k]);
                        let off = dist(inj, job.plan.end);
                        if off > FOLLOW_TOLERANCE_UM && off <= self.cfg.track_radius {
                            // The leg under way too: its end is moved and, once it lies
                            // RETARGET_UM off where the device is going, the device is sent
                            // there instead.
                            let from = job.next.max(1);
                            for w in job.plan.waypoints.iter_mut().skip(from) {
                                *w = [w[0] + d[0], w[1] + d[1], w[2] + d[2]];
                            }
                            if job.next >= 1 {
                                job.stale += off;
                                job.retarget = job.stale > RETARGET_UM;
                            }
                            job.plan.end = inj;
                        }
                    }
                    moved = !committed
                        && c.trusted
                        && dist(inj, job.plan.end) > self.cfg.replan_tolerance;
                    scene = follow.trusted_in(scene);
                }
                None => match follow.find(&touched, self.cfg.track_radius) {
                    Some(c) => exempt = Some(c.id),
                    None => lost = Some(before),
                },
            }
        }
        if let Some(f) = lost {
            // Not found where it was or where its drift took it: the move ends here, said
            // as it is (the cell the pipette was sent into is not an obstacle to blame).
            self.job = None;
            if let Err(e) = self.halt() {
                self.fail(e);
                return false;
            }
            self.set_status("blocked");
            self.broadcast(&event(
                "blocked",
                json!({
                    "reason": format!(
                        "the target ({} {} in frame {}, at X {:.1}, Y {:.1} µm) is lost: no cell within {} µm of it in frame {}; stopped",
                        if f.by_track { "track" } else { "cell" }, f.id, f.frame, f.centre[0], f.centre[1], self.cfg.track_radius, scene.frame
                    ),
                    "cells": [],
                }),
            ));
            return false;
        }
        let blocked = check_rest(&scene, &cfg, &job.plan, tip, job.next.max(1), exempt);
        if blocked.is_empty() && !moved {
            return true;
        }
        let (goal, speed, end, epoch) = (job.plan.goal, job.speed, job.plan.end, job.epoch);
        let target = job.target;
        self.job = None;
        let tip = match self.halt() {
            Ok(p) => p,
            Err(e) => {
                self.fail(e);
                return false;
            }
        };
        let reason = if moved {
            "the target moved".to_string()
        } else {
            format!("cell(s) {blocked:?} now block the path")
        };
        let cmd = match goal {
            Goal::Approach { .. } => match exempt {
                Some(cell) => Command::Approach {
                    track: None,
                    cell: Some(cell),
                    speed: None,
                },
                None => {
                    self.set_status("blocked");
                    self.broadcast(&event(
                        "blocked",
                        json!({ "reason": format!("{reason}, and the target is unknown"), "cells": blocked }),
                    ));
                    return false;
                }
            },
            Goal::Retract => Command::Retract { speed: None },
            Goal::Goto => Command::Goto {
                x: end[0],
                y: end[1],
                z: -end[2],
                speed: None,
            },
        };
        match self.plan_for(&cmd, exempt, &scene, tip) {
            Ok(plan) => {
                self.begin(
                    plan,
                    speed,
                    target,
                    seq,
                    Some(format!("{reason}; replanned")),
                    epoch,
                );
                true
            }
            Err(e) => {
                self.set_status("blocked");
                self.broadcast(&event(
                    "blocked",
                    json!({ "reason": format!("{reason}; {e}"), "cells": e.blocking }),
                ));
                false
            }
        }
    }
}
