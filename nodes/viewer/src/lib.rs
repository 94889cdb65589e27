//! The graph in Rerun, from live edges or from a recording: one code path ([`Sink::log`]).
//!
//! Every edge message becomes Rerun data with its meaning: camera frames as JPEG images under
//! `/world/left` and `/world/right` (each camera's Pinhole and place in the 3D view when the
//! cameras are known: a cell in an image is the cell in 3D), and with [`Stages::All`] label images as `SegmentationImage`s and cell contours as
//! `LineStrips2D` on top of them, disparity maps as colour-mapped `DepthImage`s under
//! `/disparity` (tiles pasted into their frame), other images under `/images`, the point
//! cloud and the targets as
//! `Points3D` under `/world` in metres, and one `TextLog` line per message under `/logs`.
//! Timelines: `frame` (the frame number) and `capture_time`, the recording's own clock (no
//! `log_time`); `/world` is right-down-forward (`ViewCoordinates::RDF`). The blueprint lays out
//! left | right | disparity | 3D over the log.
//!
//! This crate is the only one that depends on `rerun`; the `microstereo` CLI runs its
//! binary, `microstereo-viewer`, as a process.

use rerun::RecordingStream;
use rerun::blueprint::{
    Blueprint, Horizontal, Spatial2DView, Spatial3DView, TextLogView, Vertical,
};
use schemas::{
    CellLists, Cloud, Disparity, DisparityMap, DisparityPair, DisparityTiles, FrameHeader, Image,
    Labels, ManipulatorState, Message, MessageKind, StereoFrame, Targets, Tracks,
};
use std::collections::HashMap;
use std::path::PathBuf;

/// Where the Rerun data goes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Target {
    /// A new viewer process (the `rerun` program on PATH).
    Spawn,
    /// A running viewer at this gRPC URL (`rerun+http://HOST:PORT/proxy`).
    Connect(String),
    /// An `.rrd` file.
    Save(PathBuf),
}

impl Target {
    /// Reads the `--viewer` words: `spawn`, `connect ADDR`, `save FILE.rrd`.
    pub fn parse(words: &[String]) -> Result<Self, String> {
        match words {
            [m] if m == "spawn" => Ok(Self::Spawn),
            [m, a] if m == "connect" => Ok(Self::Connect(grpc_url(a))),
            [m, f] if m == "save" => Ok(Self::Save(f.into())),
            _ => Err(format!(
                "--viewer {}: give spawn, connect HOST:PORT or save FILE.rrd",
                words.join(" ")
            )),
        }
    }
}

/// The gRPC URL of a viewer given as `HOST:PORT` or as a full `rerun+http://…` URL.
pub fn grpc_url(addr: &str) -> String {
    if addr.contains("://") {
        addr.to_string()
    } else {
        format!("rerun+http://{addr}/proxy")
    }
}

/// The `HOST:PORT` of a viewer URL (to check that something listens there).
pub fn host_port(url: &str) -> &str {
    let rest = url.split_once("://").map_or(url, |(_, r)| r);
    rest.split('/').next().unwrap_or(rest)
}

/// The layout: left | right | disparity | 3D above the log.
pub fn blueprint() -> Blueprint {
    Blueprint::new(
        Vertical::new([
            Horizontal::new([
                Spatial2DView::new("left").with_origin("/world/left").into(),
                Spatial2DView::new("right")
                    .with_origin("/world/right")
                    .into(),
                Spatial2DView::new("disparity")
                    .with_origin("/disparity")
                    .into(),
                Spatial3DView::new("3D (m)").with_origin("/world").into(),
            ])
            .into(),
            TextLogView::new("log").with_origin("/logs").into(),
        ])
        .with_row_shares([4.0, 1.0]),
    )
}

/// Opens a Rerun stream to `target` with the blueprint.
pub fn open(target: &Target) -> Result<RecordingStream, String> {
    let b = rerun::RecordingStreamBuilder::new("microstereo").with_blueprint(blueprint());
    let rec = match target {
        Target::Spawn => b.spawn(),
        Target::Connect(url) => b.connect_grpc_opts(url.clone()),
        Target::Save(p) => b.save(p),
    }
    .map_err(|e| format!("Rerun: {e}"))?;
    Ok(rec)
}

/// What the viewer shows.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Stages {
    /// The camera frames (JPEG), cells, targets, tracks, the cloud and the pipette: a
    /// 1280×1024 frame of the default graph in about 1 MB.
    #[default]
    Cells,
    /// Those and every intermediate stage: label images, disparity maps and tiles.
    All,
}

impl Stages {
    /// Reads `cells` or `all`.
    pub fn parse(word: &str) -> Result<Self, String> {
        match word {
            "cells" => Ok(Self::Cells),
            "all" => Ok(Self::All),
            _ => Err(format!(
                "stages '{word}': give cells (frames, cells and 3D) or all (and labels, disparity maps and tiles)"
            )),
        }
    }
}

/// JPEG quality of the camera frames shown: at 1280×1024 a microscope frame takes about
/// 0.2 MB against 1.3 MB raw.
const JPEG_QUALITY: u8 = 90;

/// A recording stream that the graph's messages are logged to.
pub struct Sink {
    rec: RecordingStream,
    /// Metres per unit of the calibration, once a targets message has said which.
    metres: Option<f64>,
    /// Clouds waiting for their frame's targets (which carry the unit).
    clouds: HashMap<u64, (String, FrameHeader, Cloud)>,
    /// Each track's recent tops, for its trail.
    trails: HashMap<u32, std::collections::VecDeque<[f32; 3]>>,
    /// What is shown.
    stages: Stages,
}

impl std::fmt::Debug for Sink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Sink")
            .field("metres", &self.metres)
            .finish()
    }
}

/// Tops a track's trail keeps (a second at 30 frames/s).
const TRAIL: usize = 30;

fn metres_per(unit: &str) -> f64 {
    match unit {
        "µm" | "um" => 1e-6,
        "mm" => 1e-3,
        _ => 1.0,
    }
}

fn err(e: impl std::fmt::Display) -> String {
    format!("Rerun: {e}")
}

impl Sink {
    /// Logs into `rec`, on the recording's own clock (`capture_time`, `frame`; no
    /// `log_time`, the time this process logged), `/world` right-down-forward.
    pub fn new(rec: RecordingStream) -> Result<Self, String> {
        rec.set_log_time_enabled(false);
        // Our 3D frame is the rectified cameras': X right, Y down, Z along the view.
        rec.log_static("/world", &rerun::ViewCoordinates::RDF())
            .map_err(err)?;
        Ok(Self {
            rec,
            metres: None,
            clouds: HashMap::new(),
            trails: HashMap::new(),
            stages: Stages::Cells,
        })
    }

    /// Shows `stages`.
    pub fn with_stages(mut self, stages: Stages) -> Self {
        self.stages = stages;
        self
    }

    /// Places the rectified cameras `calib` (images `width × height`) in the 3D view: each
    /// camera's Pinhole and its place, half the baseline either side of `/world`'s origin,
    /// so that the images under `/world/left` and `/world/right` sit in the 3D scene.
    pub fn with_cameras(
        self,
        calib: &schemas::Calibration,
        (width, height): (usize, usize),
    ) -> Result<Self, String> {
        let half = (0.5 * calib.baseline * calib.unit.metres()) as f32;
        for (side, x, cx) in [("left", -half, calib.cx), ("right", half, calib.cx_right)] {
            let path = format!("/world/{side}");
            self.rec
                .log_static(
                    path.as_str(),
                    &rerun::Transform3D::from_translation([x, 0.0, 0.0]),
                )
                .map_err(err)?;
            let f = calib.focal_px as f32;
            self.rec
                .log_static(
                    path.as_str(),
                    &rerun::Pinhole::from_focal_length_and_resolution(
                        [f, f],
                        [width as f32, height as f32],
                    )
                    .with_principal_point([cx as f32, calib.cy as f32]),
                )
                .map_err(err)?;
        }
        Ok(self)
    }

    /// The stream.
    pub fn stream(&self) -> &RecordingStream {
        &self.rec
    }

    /// Logs one message of `edge` (`NODE/OUTPUT`).
    pub fn log(
        &mut self,
        edge: &str,
        kind: MessageKind,
        h: &FrameHeader,
        payload: &[u8],
    ) -> Result<(), String> {
        self.rec.set_time_sequence("frame", h.sequence as i64);
        self.rec
            .set_timestamp_nanos_since_epoch("capture_time", h.capture_ns as i64);
        let bad = |e: schemas::wire::WireError| format!("{edge}: {e}");
        let intermediate = matches!(
            kind,
            MessageKind::Labels
                | MessageKind::Disparity
                | MessageKind::DisparityPair
                | MessageKind::DisparityTiles
        );
        if intermediate && self.stages == Stages::Cells {
            return Ok(());
        }
        let summary = match kind {
            MessageKind::StereoFrame => {
                let f = StereoFrame::decode(h, payload).map_err(bad)?;
                for (side, p) in [("left", &f.left), ("right", &f.right)] {
                    self.log_image(&format!("/world/{side}/{edge}"), &Image::Grey(p.clone()))?;
                }
                format!("{}×{}, 2 image(s)", f.left.width, f.left.height)
            }
            MessageKind::Image => {
                let img = Image::decode(h, payload).map_err(bad)?;
                self.log_image(&format!("/images/{edge}"), &img)?;
                let (w, ht) = img.size();
                format!("{w}×{ht}, 1 image(s)")
            }
            MessageKind::Labels => {
                let l = Labels::decode(h, payload).map_err(bad)?;
                let mut cells = 0;
                for (side, p) in [("left", &l.left), ("right", &l.right)] {
                    let bytes: Vec<u8> = p.data.iter().flat_map(|v| v.to_le_bytes()).collect();
                    let img = rerun::SegmentationImage::new(
                        bytes,
                        rerun::datatypes::ImageFormat::segmentation(
                            [p.width as u32, p.height as u32],
                            rerun::datatypes::ChannelDatatype::U32,
                        ),
                    )
                    .with_opacity(0.4);
                    cells = cells.max(p.data.iter().copied().max().unwrap_or(0));
                    self.rec
                        .log(format!("/world/{side}/{edge}"), &img)
                        .map_err(err)?;
                }
                format!("labels up to {cells}")
            }
            MessageKind::Disparity => {
                let d = Disparity::decode(h, payload).map_err(bad)?;
                self.log_depth(&format!("/disparity/{edge}"), &d.map)?
            }
            MessageKind::DisparityPair => {
                let d = DisparityPair::decode(h, payload).map_err(bad)?;
                self.log_depth(&format!("/disparity/{edge}/left"), &d.left)?;
                self.log_depth(&format!("/disparity/{edge}/right"), &d.right)?
            }
            MessageKind::DisparityTiles => {
                let t = DisparityTiles::decode(h, payload).map_err(bad)?;
                // Tiles are shown where they lie in the frame; a right-based map under the
                // right camera's name.
                let shown = self.log_depth(&format!("/disparity/{edge}"), &t.paste())?;
                format!("{} tile(s), {shown}", t.tiles.len())
            }
            MessageKind::CellList => {
                let lists = CellLists::decode(h, payload).map_err(bad)?;
                for (side, cells) in [("left", &lists.left), ("right", &lists.right)] {
                    let strips: Vec<Vec<[f32; 2]>> = cells
                        .iter()
                        .map(|c| {
                            let mut s: Vec<[f32; 2]> = c
                                .contour
                                .iter()
                                .map(|p| [p[0] as f32, p[1] as f32])
                                .collect();
                            if let Some(&f) = s.first() {
                                s.push(f);
                            }
                            s
                        })
                        .collect();
                    let labels: Vec<String> =
                        cells.iter().map(|c| format!("cell {}", c.id)).collect();
                    self.rec
                        .log(
                            format!("/world/{side}/{edge}/contours"),
                            &rerun::LineStrips2D::new(strips)
                                .with_labels(labels)
                                .with_class_ids(cells.iter().map(|c| c.id as u16)),
                        )
                        .map_err(err)?;
                }
                format!("{} + {} cells", lists.left.len(), lists.right.len())
            }
            MessageKind::PointCloud => {
                let cloud = Cloud::decode(h, payload).map_err(bad)?;
                // A cloud waits for its frame's unit; its line goes with it, so that the
                // view is the same whichever of the two arrived first.
                match self.metres {
                    Some(m) => self.log_cloud(edge, h, &cloud, m)?,
                    None => {
                        self.clouds
                            .insert(h.sequence, (edge.to_string(), *h, cloud));
                    }
                }
                return Ok(());
            }
            MessageKind::ManipulatorState => {
                let st = ManipulatorState::decode(h, payload).map_err(bad)?;
                // The state's frame is the 3D view's, [X, Y, Z]; in µm, the view's in m.
                let w = |p: [f64; 3]| p.map(|v| (v * 1e-6) as f32);
                let (e, a) = (st.elevation_deg.to_radians(), st.azimuth_deg.to_radians());
                // 200 µm of the body, enough to see where it points.
                let back = [
                    st.tip[0] + 200.0 * e.cos() * a.cos(),
                    st.tip[1] + 200.0 * e.cos() * a.sin(),
                    // The body rises: towards the cameras, smaller Z.
                    st.tip[2] - 200.0 * e.sin(),
                ];
                self.rec
                    .log(
                        format!("/world/{edge}/pipette"),
                        &rerun::LineStrips3D::new([vec![w(st.tip), w(back)]])
                            .with_labels([format!("pipette ({}, {})", st.device, st.status)]),
                    )
                    .map_err(err)?;
                self.rec
                    .log(
                        format!("/world/{edge}/tip"),
                        &rerun::Points3D::new([w(st.tip)])
                            .with_radii([rerun::components::Radius::new_ui_points(5.0)]),
                    )
                    .map_err(err)?;
                if let Some(plan) = &st.plan {
                    self.rec
                        .log(
                            format!("/world/{edge}/plan"),
                            &rerun::LineStrips3D::new([plan
                                .waypoints
                                .iter()
                                .map(|p| w(*p))
                                .collect::<Vec<_>>()])
                            .with_labels([format!("{} ({:.0} µm)", plan.goal, plan.length)]),
                        )
                        .map_err(err)?;
                }
                if !st.trajectory.is_empty() {
                    self.rec
                        .log(
                            format!("/world/{edge}/trajectory"),
                            &rerun::Points3D::new(
                                st.trajectory.iter().map(|t| w([t[1], t[2], t[3]])),
                            )
                            .with_radii([rerun::components::Radius::new_ui_points(1.5)]),
                        )
                        .map_err(err)?;
                }
                format!(
                    "{} {}: tip ({:.1}, {:.1}, {:.1}) µm, {} sample(s)",
                    st.device,
                    st.status,
                    st.tip[0],
                    st.tip[1],
                    st.tip[2],
                    st.trajectory.len()
                )
            }
            MessageKind::Tracks => {
                let t = Tracks::decode(h, payload).map_err(bad)?;
                let m = metres_per(&t.unit);
                self.metres = Some(m);
                self.log_tracks(edge, &t, m)?
            }
            MessageKind::Targets => {
                let t = Targets::decode(h, payload).map_err(bad)?;
                let m = metres_per(&t.unit);
                self.metres = Some(m);
                if let Some((e, ch, p)) = self.clouds.remove(&h.sequence) {
                    // The cloud's frame and capture time are this message's.
                    self.log_cloud(&e, &ch, &p, m)?;
                }
                let tops: Vec<[f32; 3]> = t
                    .cells
                    .iter()
                    .map(|c| {
                        [
                            (c.centroid[0] * m) as f32,
                            (c.centroid[1] * m) as f32,
                            ((c.substrate_z - c.height.unwrap_or(0.0)) * m) as f32,
                        ]
                    })
                    .collect();
                let labels: Vec<String> = t
                    .cells
                    .iter()
                    .map(|c| match (c.height, &c.quality.doubt) {
                        (Some(h), None) => format!("cell {}: {h:.1} {} high", c.id, t.unit),
                        (Some(h), Some(_)) => {
                            format!("cell {}: {h:.1} {} high? (not trusted)", c.id, t.unit)
                        }
                        (None, _) => format!("cell {}: no height", c.id),
                    })
                    .collect();
                self.rec
                    .log(
                        format!("/world/{edge}"),
                        &rerun::Points3D::new(tops)
                            .with_labels(labels)
                            .with_radii([rerun::components::Radius::new_ui_points(6.0)])
                            .with_class_ids(t.cells.iter().map(|c| c.id as u16)),
                    )
                    .map_err(err)?;
                let rings: Vec<Vec<[f32; 3]>> = t
                    .cells
                    .iter()
                    .map(|c| {
                        c.contour
                            .iter()
                            .map(|p| [(p[0] * m) as f32, (p[1] * m) as f32, (p[2] * m) as f32])
                            .collect()
                    })
                    .collect();
                self.rec
                    .log(
                        format!("/world/{edge}/contours"),
                        &rerun::LineStrips3D::new(rings)
                            .with_class_ids(t.cells.iter().map(|c| c.id as u16)),
                    )
                    .map_err(err)?;
                format!("{} target cell(s)", t.cells.len())
            }
        };
        self.log_line(edge, h, &summary)
    }

    /// One line per message under `/logs/NODE`, at the message's frame.
    fn log_line(&self, edge: &str, h: &FrameHeader, summary: &str) -> Result<(), String> {
        self.rec
            .log(
                format!("/logs/{}", edge.split('/').next().unwrap_or(edge)),
                &rerun::TextLog::new(format!("{edge}: frame {}: {summary}", h.sequence))
                    .with_level(rerun::TextLogLevel::INFO),
            )
            .map_err(err)
    }

    /// Each track as its fused top with a stable colour (its id as the class), its
    /// label, and a trail of its last tops; tracks that ended lose their trail.
    fn log_tracks(&mut self, edge: &str, t: &Tracks, m: f64) -> Result<String, String> {
        let top = |tr: &schemas::Track| {
            let base = tr.cell.as_ref().map_or(tr.position[2], |c| c.substrate_z);
            [
                (tr.position[0] * m) as f32,
                (tr.position[1] * m) as f32,
                ((base - tr.height.unwrap_or(0.0)) * m) as f32,
            ]
        };
        let live: std::collections::HashSet<u32> = t.tracks.iter().map(|t| t.id).collect();
        self.trails.retain(|id, _| live.contains(id));
        for tr in &t.tracks {
            let trail = self.trails.entry(tr.id).or_default();
            trail.push_back(top(tr));
            while trail.len() > TRAIL {
                trail.pop_front();
            }
        }
        let labels: Vec<String> = t
            .tracks
            .iter()
            .map(|tr| {
                let state = match tr.state {
                    schemas::TrackState::Tentative => "tentative",
                    schemas::TrackState::Confirmed => "confirmed",
                    schemas::TrackState::Lost => "lost",
                };
                match (tr.height, tr.height_std) {
                    (Some(h), Some(s)) => format!(
                        "track {} ({state}): {h:.1} ± {s:.1} {}{}",
                        tr.id,
                        t.unit,
                        if tr.trusted { "" } else { "?" }
                    ),
                    _ => format!("track {} ({state}): no height", tr.id),
                }
            })
            .collect();
        let ids = || t.tracks.iter().map(|tr| (tr.id % 65536) as u16);
        self.rec
            .log(
                format!("/world/{edge}"),
                &rerun::Points3D::new(t.tracks.iter().map(top))
                    .with_labels(labels)
                    .with_radii([rerun::components::Radius::new_ui_points(6.0)])
                    .with_class_ids(ids()),
            )
            .map_err(err)?;
        let trails: Vec<Vec<[f32; 3]>> = t
            .tracks
            .iter()
            .map(|tr| self.trails[&tr.id].iter().copied().collect())
            .collect();
        self.rec
            .log(
                format!("/world/{edge}/trails"),
                &rerun::LineStrips3D::new(trails).with_class_ids(ids()),
            )
            .map_err(err)?;
        let confirmed = t
            .tracks
            .iter()
            .filter(|tr| tr.state == schemas::TrackState::Confirmed)
            .count();
        Ok(format!(
            "{} track(s), {confirmed} confirmed",
            t.tracks.len()
        ))
    }

    /// Logs a camera image as JPEG ([`JPEG_QUALITY`]).
    fn log_image(&mut self, path: &str, img: &Image) -> Result<(), String> {
        use image::ImageEncoder;
        let (w, h) = img.size();
        let (bytes, colour) = match img {
            Image::Grey(p) => (p.data.clone(), image::ExtendedColorType::L8),
            Image::Rgb(p) => (
                p.data.iter().flatten().copied().collect::<Vec<u8>>(),
                image::ExtendedColorType::Rgb8,
            ),
        };
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, JPEG_QUALITY)
            .write_image(&bytes, w as u32, h as u32, colour)
            .map_err(|e| format!("{path}: JPEG: {e}"))?;
        let r = rerun::EncodedImage::from_file_contents(jpeg)
            .with_media_type(rerun::components::MediaType::JPEG);
        self.rec.log(path, &r).map_err(err)
    }

    /// Logs a disparity map as a colour-mapped depth image; returns its summary.
    fn log_depth(&mut self, path: &str, map: &DisparityMap) -> Result<String, String> {
        // Rerun reads 0 as "no depth": invalid pixels become 0; the colour range is the
        // map's own.
        let (mut lo, mut hi) = (f32::MAX, f32::MIN);
        let mut valid = 0usize;
        let mut bytes = Vec::with_capacity(4 * map.len());
        for &v in &map.data {
            if v.is_finite() {
                (lo, hi) = (lo.min(v), hi.max(v));
                valid += 1;
                bytes.extend_from_slice(&v.to_le_bytes());
            } else {
                bytes.extend_from_slice(&[0; 4]);
            }
        }
        let (w, ht) = (map.width as u32, map.height as u32);
        let mut img = rerun::DepthImage::from_data_type_and_bytes(
            bytes,
            [w, ht],
            rerun::datatypes::ChannelDatatype::F32,
        )
        // A disparity is no depth: one "meter" per pixel of disparity, as the colour range says.
        .with_meter(1.0)
        .with_colormap(rerun::components::Colormap::Turbo);
        if lo <= hi {
            img = img.with_depth_range(rerun::components::ValueRange::new(
                f64::from(lo),
                f64::from(hi),
            ));
        }
        self.rec.log(path, &img).map_err(err)?;
        Ok(format!(
            "{w}×{ht}, {:.1} % valid",
            100.0 * valid as f64 / (map.len().max(1) as f64)
        ))
    }

    fn log_cloud(
        &mut self,
        edge: &str,
        h: &FrameHeader,
        cloud: &Cloud,
        m: f64,
    ) -> Result<(), String> {
        self.rec.set_time_sequence("frame", h.sequence as i64);
        self.rec
            .set_timestamp_nanos_since_epoch("capture_time", h.capture_ns as i64);
        let (pos, col): (Vec<[f32; 3]>, Vec<rerun::Color>) = cloud
            .points
            .iter()
            .map(|p| {
                (
                    p.xyz.map(|v| (f64::from(v) * m) as f32),
                    rerun::Color::from_rgb(p.rgb[0], p.rgb[1], p.rgb[2]),
                )
            })
            .unzip();
        let n = pos.len();
        self.rec
            .log(
                format!("/world/{edge}"),
                &rerun::Points3D::new(pos).with_colors(col),
            )
            .map_err(err)?;
        self.log_line(edge, h, &format!("{n} points"))
    }

    /// Logs clouds still waiting for a unit (in the calibration's unit), flushes and closes
    /// the sink.
    pub fn finish(mut self) -> Result<(), String> {
        let waiting: Vec<_> = self.clouds.drain().collect();
        for (_, (e, h, p)) in waiting {
            self.log_cloud(&e, &h, &p, self.metres.unwrap_or(1.0))?;
        }
        self.rec.flush_blocking().map_err(err)?;
        // Closes the file (its footer) or connection now, even while another thread still
        // holds a clone of the stream (the node-log reader does).
        self.rec.disconnect();
        Ok(())
    }
}

/// Logs one line a node wrote, as the supervisor forwards it (`NODE<TAB>LEVEL<TAB>LINE`),
/// under `/logs/nodes/NODE`.
pub fn log_node_line(rec: &RecordingStream, line: &str) {
    let mut parts = line.splitn(3, '\t');
    let (Some(node), Some(level), Some(text)) = (parts.next(), parts.next(), parts.next()) else {
        return;
    };
    let level = if level == "WARN" {
        rerun::TextLogLevel::WARN
    } else {
        rerun::TextLogLevel::INFO
    };
    let _ = rec.log(
        format!("/logs/nodes/{node}"),
        &rerun::TextLog::new(text).with_level(level),
    );
}

/// Logs every message of a recording (what `microstereo view` shows).
pub fn log_recording(sink: &mut Sink, path: &std::path::Path) -> Result<u64, String> {
    let mut n = 0;
    for m in recorder::EdgeReader::open(path, None).map_err(|e| e.to_string())? {
        let m = m.map_err(|e| e.to_string())?;
        sink.log(&m.edge, m.kind, &m.header, &m.payload)?;
        n += 1;
    }
    Ok(n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::{BTreeMap, BTreeSet};

    #[test]
    fn node_log_lines_become_text_logs_per_node() {
        let (rec, storage) = rerun::RecordingStreamBuilder::new("microstereo-test")
            .memory()
            .unwrap();
        log_node_line(&rec, "segment\tWARN\tslow frame");
        log_node_line(&rec, "not a forwarded line");
        rec.flush_blocking().unwrap();
        let paths: Vec<String> = storage
            .take()
            .into_iter()
            .filter_map(|m| match m {
                rerun::log::LogMsg::ArrowMsg(_, a) => Some(
                    rerun::log::Chunk::from_arrow_msg(&a)
                        .unwrap()
                        .entity_path()
                        .to_string(),
                ),
                _ => None,
            })
            .filter(|p| p.starts_with("/logs"))
            .collect();
        assert_eq!(paths, ["/logs/nodes/segment"]);
    }

    /// The text lines of a stream, as `(path, frame, text)`.
    fn lines(msgs: Vec<rerun::log::LogMsg>) -> BTreeSet<(String, i64, String)> {
        let mut out = BTreeSet::new();
        for m in msgs {
            let rerun::log::LogMsg::ArrowMsg(_, a) = m else {
                continue;
            };
            let chunk = rerun::log::Chunk::from_arrow_msg(&a).unwrap();
            let path = chunk.entity_path().to_string();
            if !path.starts_with("/logs") {
                continue;
            }
            let frames = chunk.timelines()[&"frame".into()].times_raw().to_vec();
            let texts = chunk
                .iter_component::<rerun::components::Text>(
                    rerun::TextLog::descriptor_text().component,
                )
                .map(|t| {
                    t.as_slice()
                        .iter()
                        .map(|t| t.to_string())
                        .collect::<Vec<_>>()
                })
                .collect::<Vec<_>>();
            for (f, t) in frames.iter().zip(texts) {
                for t in t {
                    out.insert((path.clone(), *f, t));
                }
            }
        }
        out
    }

    #[test]
    fn a_cloud_gets_its_line_whether_it_comes_before_or_after_its_targets() {
        let cloud = Cloud {
            points: vec![
                schemas::CloudPoint {
                    xyz: [1.0, 2.0, 3.0],
                    rgb: [9, 9, 9],
                },
                schemas::CloudPoint {
                    xyz: [4.0, 5.0, 6.0],
                    rgb: [1, 2, 3],
                },
            ],
        };
        let targets = Targets {
            frame: 3,
            capture_ns: 7,
            unit: "µm".into(),
            cells: vec![],
            substrate: None,
        };
        let enc = |e: schemas::msg::Encoded<'_>| {
            let mut h = e.header;
            h.sequence = 3;
            h.capture_ns = 7;
            (h, e.to_vec())
        };
        let (ch, cp) = enc(cloud.encode());
        let (th, tp) = enc(targets.encode());
        let run = |cloud_first: bool| {
            let (rec, storage) = rerun::RecordingStreamBuilder::new("microstereo-test")
                .memory()
                .unwrap();
            let mut sink = Sink::new(rec).unwrap();
            let mut send = |c: bool| {
                if c {
                    sink.log("triangulate/cloud", MessageKind::PointCloud, &ch, &cp)
                } else {
                    sink.log("triangulate/targets", MessageKind::Targets, &th, &tp)
                }
            };
            send(cloud_first).unwrap();
            send(!cloud_first).unwrap();
            sink.stream().flush_blocking().unwrap();
            let got = lines(storage.take());
            sink.finish().unwrap();
            got
        };
        let first = run(true);
        assert!(
            first.contains(&(
                "/logs/triangulate".into(),
                3,
                "triangulate/cloud: frame 3: 2 points".into()
            )),
            "{first:?}"
        );
        assert_eq!(first, run(false));
    }

    #[test]
    fn viewer_words_and_addresses() {
        let w = |s: &str| s.split(' ').map(String::from).collect::<Vec<_>>();
        assert_eq!(Target::parse(&w("spawn")), Ok(Target::Spawn));
        assert_eq!(
            Target::parse(&w("connect 127.0.0.1:9876")),
            Ok(Target::Connect("rerun+http://127.0.0.1:9876/proxy".into()))
        );
        assert_eq!(
            Target::parse(&w("save out.rrd")),
            Ok(Target::Save("out.rrd".into()))
        );
        assert!(Target::parse(&w("connect")).is_err());
        assert_eq!(
            host_port("rerun+http://10.0.0.2:9000/proxy"),
            "10.0.0.2:9000"
        );
    }

    #[test]
    fn the_bundled_recording_becomes_images_depth_segmentation_and_points() {
        let (rec, storage) = rerun::RecordingStreamBuilder::new("microstereo-test")
            .memory()
            .unwrap();
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../recordings/default.mcap");
        let (calib, size) = recorder::file::recorded_cameras(&path).unwrap();
        // The default graph's synthetic rig: 1200 µm apart, f = 4000 px.
        assert!((calib.baseline - 0.0012).abs() < 1e-12, "{calib:?}");
        assert_eq!(calib.focal_px, 4000.0);
        assert_eq!(size, (640, 512));
        let mut sink = Sink::new(rec)
            .unwrap()
            .with_stages(Stages::All)
            .with_cameras(&calib, size)
            .unwrap();
        // 61 MCAP messages: the stereo frames and label pairs are one edge message each, and
        // the frame tree, CameraInfo, markers and annotations are not edges: 14 edges, 2 frames.
        assert_eq!(log_recording(&mut sink, &path).unwrap(), 28);
        // Closing a memory stream moves what it holds to the next sink: take it first.
        sink.stream().flush_blocking().unwrap();
        let msgs = storage.take();
        sink.finish().unwrap();
        let mut seen: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
        let mut frames = BTreeSet::new();
        let mut timelines = BTreeSet::new();
        for msg in msgs {
            if let rerun::log::LogMsg::ArrowMsg(_, a) = msg {
                let chunk = rerun::log::Chunk::from_arrow_msg(&a).unwrap();
                if let Some(col) = chunk.timelines().get(&"frame".into()) {
                    frames.extend(col.times_raw().iter().copied());
                }
                timelines.extend(chunk.timelines().keys().map(|t| t.to_string()));
                let entry = seen.entry(chunk.entity_path().to_string()).or_default();
                for d in chunk.component_descriptors() {
                    if let Some(a) = d.archetype {
                        entry.insert(a.short_name().to_string());
                    }
                }
            }
        }
        let has = |path: &str, arch: &str| {
            assert!(
                seen.get(path).is_some_and(|s| s.contains(arch)),
                "{path} should hold {arch}; seen: {seen:#?}"
            )
        };
        has("/world", "ViewCoordinates");
        has("/world/left/rectify/frame", "EncodedImage");
        has("/world/right/rectify/frame", "EncodedImage");
        has("/world/left/segment/labels", "SegmentationImage");
        has("/world/left/segment/cells/contours", "LineStrips2D");
        has("/world/right/segment/cells/contours", "LineStrips2D");
        // The cameras from the recording's CameraInfo: the images are in the 3D scene.
        has("/world/left", "Pinhole");
        has("/world/right", "Transform3D");
        // Tiles pasted into their frames.
        has("/disparity/postprocess/disparity", "DepthImage");
        has("/disparity/match/left", "DepthImage");
        has("/disparity/match/right", "DepthImage");
        has("/disparity/triangulate/disparity", "DepthImage");
        has("/world/triangulate/cloud", "Points3D");
        has("/world/triangulate/targets", "Points3D");
        has("/world/triangulate/targets/contours", "LineStrips3D");
        has("/logs/segment", "TextLog");
        has("/world/manipulator-bridge/state/pipette", "LineStrips3D");
        has("/world/manipulator-bridge/state/tip", "Points3D");
        assert_eq!(frames, BTreeSet::from([0, 1]));
        // No time this process logged: the recording's own clock only.
        assert!(!timelines.contains("log_time"), "{timelines:?}");
        assert!(timelines.contains("capture_time"), "{timelines:?}");
    }

    /// By default the viewer shows the camera frames, cells and 3D, not the intermediate
    /// stages: the bundled 640×512 recording (every pixel's point in its cloud) stays
    /// within the 1.5 MB a 1280×1024 frame may take, scaled to its pixels.
    #[test]
    fn by_default_the_frames_are_jpeg_and_the_intermediate_stages_stay_out() {
        let (rec, storage) = rerun::RecordingStreamBuilder::new("microstereo-test")
            .memory()
            .unwrap();
        let mut sink = Sink::new(rec).unwrap();
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../recordings/default.mcap");
        log_recording(&mut sink, &path).unwrap();
        sink.stream().flush_blocking().unwrap();
        let msgs = storage.take();
        sink.finish().unwrap();
        let mut archetypes = BTreeSet::new();
        let mut bytes = 0;
        for msg in msgs {
            if let rerun::log::LogMsg::ArrowMsg(_, a) = msg {
                bytes += a.batch.get_array_memory_size();
                let chunk = rerun::log::Chunk::from_arrow_msg(&a).unwrap();
                for d in chunk.component_descriptors() {
                    if let Some(a) = d.archetype {
                        archetypes.insert(a.short_name().to_string());
                    }
                }
            }
        }
        assert!(archetypes.contains("EncodedImage"), "{archetypes:?}");
        for gone in ["Image", "DepthImage", "SegmentationImage"] {
            assert!(!archetypes.contains(gone), "{gone}: {archetypes:?}");
        }
        let per_frame = 1_500_000 * (640 * 512) / (1280 * 1024);
        assert!(bytes < 2 * per_frame, "{bytes} bytes for 2 frames");
    }
}
