//! The `manipulator-bridge` graph node: its launch-file parameters and its step.

use crate::bridge::{Bridge, BridgeConfig};
use crate::device::{Device, DeviceError, SimDevice, wall_clock};
use crate::geom::{P3, flip};
use crate::mp285::Mp285;
use crate::plan::{Entry, PipetteGeometry, PlannerConfig};
use crate::registration::Registration;
use crate::scene::Workspace;
use crate::scientifica::Scientifica;
use node_api::{NodeError, Params, Stamp, Task};
use schemas::{ManipulatorState, Targets, Tracks};
use serde::Deserialize;
use std::time::Duration;

/// `params` of a manipulator-bridge node (positions in the camera frame: `[X, Y, Z]` of
/// the triangulation, Z the depth from the cameras, µm).
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BridgeParams {
    /// Address to listen on for controllers.
    #[serde(default = "default_listen")]
    pub listen: String,
    /// `sim`, `mp285`, `scientifica` or `none`.
    #[serde(default = "default_device")]
    pub device: String,
    /// Serial port of an MP-285.
    #[serde(default)]
    pub port: Option<String>,
    /// Where the tip starts (sim) and where `home` goes, camera frame `[X, Y, Z]` µm.
    #[serde(default = "default_home")]
    pub home: P3,
    /// Device position = scene position + offset (the axes taken as the scene's).
    #[serde(default)]
    pub offset: P3,
    /// The whole registration instead (`device = M·scene + offset`): the file
    /// `calibrate-manipulator` writes, or a table `{ matrix = [9], offset = [3] }`.
    #[serde(default)]
    pub registration: Option<RegistrationParam>,
    /// Fastest tip speed the bridge commands, µm/s.
    #[serde(default = "default_max_speed")]
    pub max_speed: f64,
    /// The sim's acceleration limit, µm/s².
    #[serde(default = "default_max_accel")]
    pub max_accel: f64,
    /// No frame for this long stops the manipulator, ms.
    #[serde(default = "default_stale_ms")]
    pub stale_ms: u64,
    /// Device polling period, ms.
    #[serde(default = "default_poll_ms")]
    pub poll_ms: u64,
    /// Pipette elevation above the horizontal, degrees.
    #[serde(default = "default_elevation")]
    pub elevation_deg: f64,
    /// Direction the pipette body extends to, degrees from +x.
    #[serde(default = "default_azimuth")]
    pub azimuth_deg: f64,
    /// Length of the body the planner keeps clear, µm.
    #[serde(default = "default_length")]
    pub pipette_length: f64,
    /// Least distance between the body and any cell but the target, µm.
    #[serde(default = "default_clearance")]
    pub clearance: f64,
    /// Extra height of traverses above the tallest cell + clearance, µm.
    #[serde(default = "default_safe_margin")]
    pub safe_margin: f64,
    /// Pre-injection point distance back along the axis, µm.
    #[serde(default = "default_pre")]
    pub pre_distance: f64,
    /// How far past the cell's surface the tip goes, µm.
    #[serde(default)]
    pub depth: f64,
    /// Least tip height above the substrate, µm.
    #[serde(default = "default_floor")]
    pub floor_margin: f64,
    /// `top` or `side`.
    #[serde(default)]
    pub entry: Entry,
    /// The box the tip may move in, camera frame `[X, Y, Z]` µm.
    #[serde(default = "default_workspace")]
    pub workspace: Workspace,
    /// Objects this close to the pipette's recent body are the pipette itself, µm.
    #[serde(default = "default_self_margin")]
    pub self_margin: f64,
    /// How far a target may move between frames and stay the same cell, µm.
    #[serde(default = "default_track")]
    pub track_radius: f64,
    /// A target whose injection point moved farther than this is replanned, µm.
    #[serde(default = "default_replan")]
    pub replan_tolerance: f64,
    /// Height of a cell whose measured height is not trusted (an obstacle that tall,
    /// never of height zero), µm; the tallest plausible cell by default.
    #[serde(default = "default_untrusted")]
    pub untrusted_height: f64,
}

/// Where a bridge's registration comes from.
#[derive(Clone, Debug, Deserialize)]
#[serde(untagged)]
pub enum RegistrationParam {
    /// A registration file's path.
    File(String),
    /// The registration itself.
    Inline(Registration),
}

fn default_listen() -> String {
    "127.0.0.1:7878".into()
}
fn default_device() -> String {
    "sim".into()
}
fn default_home() -> P3 {
    [-300.0, 0.0, 3850.0]
}
fn default_max_speed() -> f64 {
    200.0
}
fn default_max_accel() -> f64 {
    2000.0
}
fn default_stale_ms() -> u64 {
    2000
}
fn default_poll_ms() -> u64 {
    10
}
fn default_elevation() -> f64 {
    PipetteGeometry::default().elevation_deg
}
fn default_azimuth() -> f64 {
    PipetteGeometry::default().azimuth_deg
}
fn default_length() -> f64 {
    PipetteGeometry::default().length
}
fn default_clearance() -> f64 {
    PlannerConfig::default().clearance
}
fn default_safe_margin() -> f64 {
    PlannerConfig::default().safe_margin
}
fn default_pre() -> f64 {
    PlannerConfig::default().pre_distance
}
fn default_floor() -> f64 {
    PlannerConfig::default().floor_margin
}
fn default_workspace() -> Workspace {
    flip_box(PlannerConfig::default().workspace)
}

/// A box between the planner's frame and the camera frame (its third bounds swap).
fn flip_box(w: Workspace) -> Workspace {
    Workspace {
        min: [w.min[0], w.min[1], -w.max[2]],
        max: [w.max[0], w.max[1], -w.min[2]],
    }
}
fn default_self_margin() -> f64 {
    3.0
}
fn default_track() -> f64 {
    15.0
}
fn default_untrusted() -> f64 {
    crate::scene::UNTRUSTED_HEIGHT
}
fn default_replan() -> f64 {
    // Measured injection points wander by 2–3 µm from frame to frame.
    5.0
}

impl Params for BridgeParams {
    fn check(&self) -> Result<(), String> {
        let p = self;
        p.listen
            .parse::<std::net::SocketAddr>()
            .map_err(|e| format!("listen '{}' is not an address: {e}", p.listen))?;
        match (p.device.as_str(), &p.port) {
            ("sim" | "none", _) | ("mp285" | "scientifica", Some(_)) => {}
            (d @ ("mp285" | "scientifica"), None) => {
                return Err(format!(
                    "device = \"{d}\" needs port = \"/dev/ttyUSB0\" (its serial port)"
                ));
            }
            (d, _) => {
                return Err(format!(
                    "unknown device '{d}'; devices: sim, mp285, scientifica, none"
                ));
            }
        }
        // The box as the user wrote it first: the planner's own check speaks its frame.
        p.workspace.check()?;
        let c = p.config();
        c.planner.check()?;
        p.registration()?;
        if !p.offset.iter().all(|v| (-1e7..=1e7).contains(v)) {
            return Err(format!(
                "offset {:?} must be finite, each axis within ±1e7 µm",
                p.offset
            ));
        }
        if !p.workspace.contains(p.home) {
            return Err(format!(
                "home {:?} is outside the workspace {:?} .. {:?}",
                p.home, p.workspace.min, p.workspace.max
            ));
        }
        // Each above 0 and below what any manipulator has (µm, µm/s, µm/s²).
        for (name, v, max) in [
            ("max_speed", p.max_speed, 1e5),
            ("max_accel", p.max_accel, 1e8),
            ("self_margin", p.self_margin, 1e6),
            ("track_radius", p.track_radius, 1e6),
            ("replan_tolerance", p.replan_tolerance, 1e6),
            ("untrusted_height", p.untrusted_height, 1e6),
        ] {
            if !(v > 0.0 && v <= max) {
                return Err(format!(
                    "{name} {v} is out of range: use a value above 0, at most {max}"
                ));
            }
        }
        if !(1..=60_000).contains(&p.poll_ms) || !(1..=3_600_000).contains(&p.stale_ms) {
            return Err(format!(
                "poll_ms {} and stale_ms {} are out of range: use 1..=60000 and 1..=3600000",
                p.poll_ms, p.stale_ms
            ));
        }
        Ok(())
    }
}

impl BridgeParams {
    /// Reads and checks a `params` table.
    pub fn from_table(t: &toml::Table) -> Result<Self, String> {
        runtime::registry::parse_params(t)
    }

    /// The bridge settings these parameters give.
    pub fn config(&self) -> BridgeConfig {
        BridgeConfig {
            planner: PlannerConfig {
                pipette: PipetteGeometry {
                    elevation_deg: self.elevation_deg,
                    azimuth_deg: self.azimuth_deg,
                    length: self.pipette_length,
                },
                clearance: self.clearance,
                safe_margin: self.safe_margin,
                pre_distance: self.pre_distance,
                depth: self.depth,
                floor_margin: self.floor_margin,
                entry: self.entry,
                workspace: flip_box(self.workspace),
            },
            home: flip(self.home),
            max_speed: self.max_speed,
            registration: self.registration().unwrap_or_default(),
            stale: Duration::from_millis(self.stale_ms),
            poll: Duration::from_millis(self.poll_ms),
            self_margin: self.self_margin,
            track_radius: self.track_radius,
            replan_tolerance: self.replan_tolerance,
            untrusted_height: self.untrusted_height,
            outbox_limit: crate::bridge::OUTBOX_LIMIT,
        }
    }

    /// The registration: the file or table given, or the offset alone.
    pub fn registration(&self) -> Result<Registration, String> {
        match &self.registration {
            None => Ok(Registration::offset_only(self.offset)),
            Some(_) if self.offset != [0.0; 3] => Err(
                "give offset or registration, not both (a registration holds its own offset)"
                    .into(),
            ),
            Some(RegistrationParam::File(p)) => Registration::read(p),
            Some(RegistrationParam::Inline(r)) => r.check().map(|_| *r),
        }
    }

    /// Opens the configured device.
    pub fn open_device(&self) -> Result<Box<dyn Device>, DeviceError> {
        match self.device.as_str() {
            // The sim's own limit sits above the bridge's, as a real device's would.
            "sim" => Ok(Box::new(SimDevice::new(
                self.registration().unwrap_or_default().to_device(self.home),
                self.max_speed * 2.0,
                self.max_accel,
                wall_clock(),
            ))),
            "mp285" => {
                let port = self.port.as_deref().unwrap_or_default();
                let d = Mp285::open(port, Duration::from_secs(2))?;
                if d.interrupted_on_open() {
                    runtime::errln!(
                        "manipulator-bridge: the MP-285 on {port} was still moving (an earlier \
                         bridge's move); stopped it before anything else"
                    );
                }
                Ok(Box::new(d))
            }
            "scientifica" => {
                let port = self.port.as_deref().unwrap_or_default();
                Ok(Box::new(Scientifica::open(port, Duration::from_secs(2))?))
            }
            _ => Err(DeviceError("device = \"none\" in the launch file".into())),
        }
    }
}

/// Serves each frame's scene to the controllers, moves the pipette on their commands and
/// sends the manipulator state on its one output.
pub struct BridgeNode {
    bridge: Bridge,
    /// Where it listens (the port is chosen by the system when the address says 0).
    pub addr: std::net::SocketAddr,
}

impl BridgeNode {
    /// Opens the device and starts listening; a device that cannot be opened is reported
    /// on stderr and the bridge serves the scene without it.
    pub fn new(p: &BridgeParams) -> Result<Self, String> {
        let device = p.open_device();
        if let Err(e) = &device {
            runtime::errln!("manipulator-bridge: no manipulator: {e}; serving the scene only");
        }
        let bridge = Bridge::start(p.config(), &p.listen, device)?;
        let addr = bridge.addr;
        Ok(Self { bridge, addr })
    }

    /// Controllers connected now.
    pub fn controllers(&self) -> usize {
        self.bridge.controllers()
    }
}

node_api::ports! {
    /// What the bridge reads.
    pub struct BridgeIn {
        /// The frame's cells in 3D, addressed by their per-frame ids (no track node).
        pub targets: Option<Targets>,
        /// The cells followed over time, addressed by their track ids.
        pub tracks: Option<Tracks>,
    }
}

node_api::ports! {
    /// What the bridge sends.
    pub struct BridgeOut {
        /// Where the pipette is and what it does.
        pub state: ManipulatorState,
    }
}

impl Task for BridgeNode {
    const KIND: &'static str = "manipulator-bridge";
    type Params = BridgeParams;
    type Input = BridgeIn;
    type Output = BridgeOut;
    type Error = NodeError;

    fn new(p: BridgeParams) -> Result<Self, NodeError> {
        BridgeNode::new(&p).map_err(NodeError::Failed)
    }

    fn check_inputs(_: &BridgeParams, connected: &[&str]) -> Result<(), String> {
        match (connected.contains(&"targets"), connected.contains(&"tracks")) {
            (true, false) | (false, true) => Ok(()),
            _ => Err(
                "the bridge reads one of tracks (from a track node: cells addressed by track) or targets (from triangulate: cells by their per-frame ids); connect one"
                    .into(),
            ),
        }
    }

    fn process(&mut self, _: Stamp, i: BridgeIn) -> Result<BridgeOut, NodeError> {
        let state = match (&i.tracks, &i.targets) {
            (Some(t), _) => self.bridge.on_tracks(t)?,
            (None, Some(t)) => self.bridge.on_targets(t)?,
            (None, None) => {
                return Err(NodeError::Failed(
                    "no scene came on the bridge's input this frame".into(),
                ));
            }
        };
        Ok(BridgeOut { state })
    }
}
