//! The bridge between the graph, the controllers and the manipulator.
//!
//! Three kinds of threads share one [`Shared`] state:
//! - the graph node hands in each frame's targets ([`Bridge::on_targets`]): they become the
//!   scene (objects touching the pipette's recent body are taken for the pipette itself),
//!   are served to every controller, and the reply is the state message of that frame;
//! - one reader per controller parses commands; `stop` raises the emergency flag at once,
//!   so it wins over everything queued;
//! - the controller thread owns the device: it plans, moves leg by leg, polls the position,
//!   re-checks the rest of the path against every new scene (replanning or stopping when
//!   it is blocked) and stops when the scene goes stale.
//!
//! The bridge enforces the workspace and the speed limit itself; the device's own limits
//! come on top.

use crate::device::{Device, DeviceError};
use crate::geom::{P3, dist, flip};
use crate::plan::{
    Goal, NoPath, Plan, PlannerConfig, check_rest, injection_point, plan_approach, plan_goto,
    plan_retract,
};
use crate::protocol::{Command, Line, MAX_LINE, parse_command, read_line, shorten};
use crate::registration::Registration;
use crate::scene::Scene;
use schemas::{ManipulatorState, PathPlan, Targets};
use serde_json::{Value, json};
use std::collections::VecDeque;
use std::io::{BufReader, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, channel};
use std::sync::{Arc, Mutex};
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

/// The connected controllers.
#[derive(Default)]
struct Clients {
    next_id: u64,
    list: Vec<(u64, TcpStream)>,
}

impl Clients {
    fn broadcast(&mut self, line: &str) {
        // A controller that went away is dropped; the others keep their feed.
        self.list
            .retain_mut(|(_, s)| s.write_all(line.as_bytes()).is_ok());
    }

    fn send(&mut self, id: u64, line: &str) {
        self.list
            .retain_mut(|(i, s)| *i != id || s.write_all(line.as_bytes()).is_ok());
    }

    /// Ends what goes out to one controller (after what was sent) and forgets it.
    fn close(&mut self, id: u64) {
        self.list.retain(|(i, s)| {
            if *i == id {
                let _ = s.shutdown(std::net::Shutdown::Write);
            }
            *i != id
        });
    }
}

/// State shared by the node, the readers and the controller thread.
struct Shared {
    scene: Option<(Scene, Instant, u64)>,
    tip: P3,
    status: String,
    plan: Option<PathPlan>,
    trajectory: Vec<[f64; 4]>,
    /// Recent tip positions `(wall-clock ns, tip)`, for telling the pipette from cells.
    history: VecDeque<(u64, P3)>,
    device: String,
}

/// The manipulator bridge: TCP server, controller thread and shared state.
pub struct Bridge {
    cfg: BridgeConfig,
    shared: Arc<Mutex<Shared>>,
    clients: Arc<Mutex<Clients>>,
    /// Where it listens.
    pub addr: SocketAddr,
    /// Set when the bridge is dropped: the accepting thread then ends and frees the port.
    closing: Arc<AtomicBool>,
}

impl Drop for Bridge {
    fn drop(&mut self) {
        // The accepting thread waits in accept(): a connection of our own wakes it to see
        // the flag (an in-process graph's bridge kept its port until the program ended).
        self.closing.store(true, Ordering::SeqCst);
        let _ = TcpStream::connect_timeout(&self.addr, Duration::from_millis(500));
    }
}

/// What the controller thread is doing.
struct Job {
    plan: Plan,
    /// The waypoint it is moving to.
    next: usize,
    speed: f64,
    /// The target's footprint centre as last seen (approach only).
    target: Option<[f64; 2]>,
    seen_scene: u64,
    last_progress: Instant,
}

struct Controller {
    cfg: BridgeConfig,
    device: Option<Box<dyn Device>>,
    missing: String,
    shared: Arc<Mutex<Shared>>,
    clients: Arc<Mutex<Clients>>,
    estop: Arc<AtomicBool>,
    rx: Receiver<(u64, Command)>,
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
            device: device.as_ref().map_or("none".into(), |d| d.describe()),
        }));
        let clients: Arc<Mutex<Clients>> = Arc::default();
        let estop = Arc::new(AtomicBool::new(false));
        let closing = Arc::new(AtomicBool::new(false));
        let (tx, rx) = channel();
        {
            let (clients, estop, closing) = (clients.clone(), estop.clone(), closing.clone());
            std::thread::spawn(move || accept(listener, clients, tx, estop, closing));
        }
        let mut c = Controller {
            cfg: cfg.clone(),
            device,
            missing,
            shared: shared.clone(),
            clients: clients.clone(),
            estop,
            rx,
            job: None,
            inside: None,
            t0: Instant::now(),
        };
        if let Some(d) = c.device.as_mut() {
            match d.state() {
                Ok(s) => c.shared.lock().expect("shared").tip = cfg.tip_at(s.position),
                Err(e) => {
                    c.missing = e.0;
                    c.device = None;
                }
            }
        }
        std::thread::spawn(move || c.run());
        Ok(Self {
            cfg,
            shared,
            clients,
            addr,
            closing,
        })
    }

    /// Controllers connected now.
    pub fn controllers(&self) -> usize {
        self.clients.lock().expect("clients").list.len()
    }

    /// Takes one frame's targets: updates the scene, serves
    /// it to the controllers and returns the manipulator state for this frame.
    pub fn on_targets(&self, t: &Targets) -> Result<ManipulatorState, String> {
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
        // The scene line: the targets as they travel (their JSON), tagged.
        let raw = &serde_json::to_vec(t).map_err(|e| e.to_string())?[..];
        let mut line = Vec::with_capacity(raw.len() + 20);
        line.extend_from_slice(b"{\"event\":\"scene\",");
        line.extend_from_slice(raw.strip_prefix(b"{").unwrap_or(raw));
        line.push(b'\n');
        self.clients
            .lock()
            .expect("clients")
            .broadcast(&String::from_utf8_lossy(&line));
        Ok(state)
    }
}

fn accept(
    listener: TcpListener,
    clients: Arc<Mutex<Clients>>,
    tx: Sender<(u64, Command)>,
    estop: Arc<AtomicBool>,
    closing: Arc<AtomicBool>,
) {
    for s in listener.incoming().flatten() {
        if closing.load(Ordering::SeqCst) {
            return;
        }
        let _ = s.set_nodelay(true);
        // A controller that stops reading must not stall the graph: a write that cannot
        // go out within this time drops it.
        let _ = s.set_write_timeout(Some(Duration::from_millis(200)));
        let Ok(reader) = s.try_clone() else { continue };
        let id = {
            let mut c = clients.lock().expect("clients");
            c.next_id += 1;
            let id = c.next_id;
            c.list.push((id, s));
            id
        };
        let (clients, tx, estop) = (clients.clone(), tx.clone(), estop.clone());
        std::thread::spawn(move || {
            let mut reader = BufReader::new(reader);
            loop {
                let line = match read_line(&mut reader, MAX_LINE) {
                    Ok(Line::Text(l)) => l,
                    Ok(Line::NotUtf8) => {
                        clients.lock().expect("clients").send(
                            id,
                            &event(
                                "error",
                                json!({ "message": "the line is not UTF-8 text; send one JSON command per line" }),
                            ),
                        );
                        continue;
                    }
                    Ok(Line::TooLong) => {
                        let mut c = clients.lock().expect("clients");
                        c.send(
                            id,
                            &event(
                                "error",
                                json!({ "message": format!("a line longer than {MAX_LINE} bytes; closing this connection") }),
                            ),
                        );
                        c.close(id);
                        drop(c);
                        // Read what is still coming and throw it away, for a while: closing
                        // with unread input would reset the connection and could lose the
                        // error line on its way out.
                        let mut s = reader.into_inner();
                        let _ = s.set_read_timeout(Some(Duration::from_millis(200)));
                        let t0 = Instant::now();
                        let mut sink = [0u8; 8192];
                        while t0.elapsed() < Duration::from_secs(2)
                            && matches!(std::io::Read::read(&mut s, &mut sink), Ok(n) if n > 0)
                        {
                        }
                        break;
                    }
                    Ok(Line::End) | Err(_) => break,
                };
                if line.trim().is_empty() {
                    continue;
                }
                match parse_command(&line) {
                    Ok(Command::Stop) => {
                        // Seen by the controller before anything queued.
                        estop.store(true, Ordering::SeqCst);
                        let _ = tx.send((id, Command::Stop));
                    }
                    Ok(c) => {
                        if tx.send((id, c)).is_err() {
                            break;
                        }
                    }
                    Err(m) => clients.lock().expect("clients").send(
                        id,
                        &event(
                            "error",
                            json!({ "message": m, "command": shorten(&line, 200) }),
                        ),
                    ),
                }
            }
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
            if self.estop.swap(false, Ordering::SeqCst) {
                self.emergency_stop();
            }
            match self.rx.recv_timeout(self.cfg.poll) {
                Ok((_, Command::Stop)) => self.emergency_stop(),
                Ok((id, c)) => self.command(id, c),
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => return,
            }
            self.tick();
        }
    }

    fn emergency_stop(&mut self) {
        self.estop.store(false, Ordering::SeqCst);
        let mut dropped = 0;
        while let Ok((id, c)) = self.rx.try_recv() {
            if c != Command::Stop {
                dropped += 1;
                self.tell(
                    id,
                    &event(
                        "error",
                        json!({ "message": "dropped: an emergency stop came after it" }),
                    ),
                );
            }
        }
        self.job = None;
        let tip = self.shared.lock().expect("shared").tip;
        if let Some(d) = self.device.as_mut()
            && let Err(e) = d.stop()
        {
            self.fail(e);
            return;
        }
        self.set_status("stopped");
        self.broadcast(&event(
            "stopped",
            json!({ "tip": flip(tip), "dropped": dropped }),
        ));
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

    fn plan_for(&self, c: &Command, scene: &Scene, tip: P3) -> Result<Plan, NoPath> {
        let cfg = &self.cfg.planner;
        match *c {
            Command::Approach { cell, .. } => plan_approach(scene, cfg, tip, cell),
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

    fn command(&mut self, id: u64, c: Command) {
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
        let speed = match c {
            Command::Approach { speed, .. }
            | Command::Retract { speed }
            | Command::Goto { speed, .. }
            | Command::Home { speed } => speed,
            Command::Stop => None,
        }
        .map_or(self.cfg.max_speed, |s| s.min(self.cfg.max_speed));
        match self.plan_for(&c, &scene, tip) {
            Ok(plan) => {
                let target = match plan.goal {
                    Goal::Approach { cell } => scene.cell(cell).map(|c| c.centre),
                    _ => None,
                };
                self.begin(plan, speed, target, seq, None);
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
        target: Option<[f64; 2]>,
        seen: u64,
        replanned: Option<String>,
    ) {
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
        let job = self.job.as_mut().expect("job");
        if !st.moving {
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
            let to = job.plan.waypoints[job.next];
            // In device units: no scene direction moves faster than `speed`.
            let speed = job.speed * self.cfg.registration.least_stretch();
            let r = self
                .device
                .as_mut()
                .expect("device")
                .start_move(self.cfg.device_for(to), speed);
            if let Err(e) = r {
                return self.fail(e);
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

    /// Checks the rest of the path against a new scene; replans or stops when it is
    /// blocked or the target moved. `false` when the job ended.
    fn recheck(&mut self, tip: P3, seq: u64) -> bool {
        let Ok((scene, _)) = self.fresh_scene() else {
            return true;
        };
        let cfg = self.cfg.planner;
        let job = self.job.as_mut().expect("job");
        job.seen_scene = seq;
        let committed = job.next > job.plan.axial_from;
        let mut exempt = None;
        let mut moved = false;
        if let Some(centre) = job.target
            && let Some(c) = scene.nearest(centre, self.cfg.track_radius)
        {
            exempt = Some(c.id);
            job.target = Some(c.centre);
            moved = !committed
                && dist(injection_point(c, &cfg), job.plan.end) > self.cfg.replan_tolerance;
        }
        let blocked = check_rest(&scene, &cfg, &job.plan, tip, job.next.max(1), exempt);
        if blocked.is_empty() && !moved {
            return true;
        }
        let (goal, speed, end) = (job.plan.goal, job.speed, job.plan.end);
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
                Some(cell) => Command::Approach { cell, speed: None },
                None => {
                    self.set_status("blocked");
                    self.broadcast(&event(
                        "blocked",
                        json!({ "reason": format!("{reason}, and the target is lost"), "cells": blocked }),
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
        match self.plan_for(&cmd, &scene, tip) {
            Ok(plan) => {
                self.begin(
                    plan,
                    speed,
                    target,
                    seq,
                    Some(format!("{reason}; replanned")),
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
