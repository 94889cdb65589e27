//! The stereo graph the one-shot commands run: their flags become node parameters of an
//! in-memory launch file, checked by the same validator as any launch file and run by the
//! in-process executor on the same node values as `microstereo run`.

use crate::Error;
use capture::ImagePairOut;
use matcher::Mode;
use matcher::node::{BothOut, MatchIn};
use matcher::node::{MatchParams, Region};
use postprocess::PostParams;
use postprocess::node::Tiles;
use runtime::build::{GraphBuilder, Out, params_of};
use runtime::exec::{Frame, InProcess};
use runtime::launch::{Graph, LaunchFile};
use schemas::DisparityRange;
use schemas::{CellLists, Cloud, Disparity, DisparityTiles, Image, Labels, StereoFrame, Targets};
use segment::SegmentParams;
use segment::node::{SegmentIn, SegmentOut};
use std::path::{Path, PathBuf};
use triangulate::geometry::Geometry;
use triangulate::node::{TriangulateIn, TriangulateOut};
use validate::node::ValidateParams;
use validate::node::{ValidateIn, ValidateOut};

/// A stereo pair through the method's chain: image pair → (segment →) match → validate
/// (→ post-process → triangulate).
#[derive(Clone, Debug)]
pub struct Stereo {
    /// Left image file.
    pub left: PathBuf,
    /// Right image file.
    pub right: PathBuf,
    /// Frames to send the pair in (a benchmark repeats it).
    pub frames: u64,
    /// The match node (its region is set by `segment`).
    pub matching: MatchParams,
    /// The validate node.
    pub validate: ValidateParams,
    /// The postprocess node; `None` ends the graph after validation.
    pub post: Option<PostParams>,
    /// Segment both views and match only the cells.
    pub segment: Option<SegmentParams>,
    /// Triangulate (and measure the cells) with this geometry.
    pub geometry: Option<Geometry>,
    /// Rectify the raw pair first with this calibration file's cameras (its `[stereo]`
    /// table, or OpenCV's stereo YAML).
    pub rectify: Option<String>,
}

/// The node ids of a [`Stereo`] graph.
pub mod ids {
    /// The image pair.
    pub const PAIR: &str = "pair";
    /// Rectification of a raw pair.
    pub const RECTIFY: &str = "rectify";
    /// Segmentation.
    pub const SEGMENT: &str = "segment";
    /// Matching, both directions.
    pub const MATCH: &str = "match";
    /// The LR check.
    pub const VALIDATE: &str = "validate";
    /// Post-processing.
    pub const POSTPROCESS: &str = "postprocess";
    /// Triangulation and the cells in 3D.
    pub const TRIANGULATE: &str = "triangulate";
}

/// The outputs of a [`Stereo`] graph a command reads, typed (`None`: the node is not in
/// this graph).
#[derive(Clone, Debug)]
pub struct StereoOuts {
    /// The left view in colour, as read.
    pub colour: Out<Image>,
    /// The views every later node reads: rectified, or as read.
    pub frame: Out<StereoFrame>,
    /// The cells' label images.
    pub labels: Option<Out<Labels>>,
    /// Both views' cells.
    pub cells: Option<Out<CellLists>>,
    /// The left-based matches.
    pub matched: Out<DisparityTiles>,
    /// The right-based matches.
    pub matched_right: Out<DisparityTiles>,
    /// The left-based map after the LR check.
    pub checked: Out<DisparityTiles>,
    /// The right-based map after the LR check.
    pub checked_right: Out<DisparityTiles>,
    /// The post-processed map.
    pub post: Option<Out<DisparityTiles>>,
    /// The final map in frame coordinates.
    pub disparity: Option<Out<Disparity>>,
    /// The point cloud.
    pub cloud: Option<Out<Cloud>>,
    /// The cells in 3D.
    pub targets: Option<Out<Targets>>,
}

/// The message on `o` this frame, where this graph has that output.
pub fn got<M: schemas::msg::Message>(f: &Frame, o: &Option<Out<M>>) -> Result<M, Error> {
    f.read(o.as_ref().ok_or(Error::NoSuchOutput)?)
        .map_err(Error::Node)
}

impl Stereo {
    /// Whole-frame matching of `left` and `right` over `range` with every default of
    /// `mode` (its post-processing included), one frame, no triangulation.
    pub fn whole_frame(left: PathBuf, right: PathBuf, mode: Mode, range: DisparityRange) -> Self {
        Self {
            left,
            right,
            frames: 1,
            matching: MatchParams::new(mode, range, Region::Frame),
            validate: ValidateParams::default(),
            post: Some(post_for(mode)),
            segment: None,
            geometry: None,
            rectify: None,
        }
    }

    /// The graph built from its node types, and the outputs a command reads.
    pub fn build(&self) -> (GraphBuilder, StereoOuts) {
        use ids::*;
        let mut g = GraphBuilder::new();
        let pair = g.source::<capture::ImagePair>(
            PAIR,
            params_of(&capture::ImagePairParams {
                left: self.left.clone(),
                right: self.right.clone(),
                frames: self.frames,
            }),
        );
        let colour = pair.out(ImagePairOut::colour);
        // A raw pair is rectified first; every later node reads the rectified views (and
        // the points go grey: the colour view is not rectified).
        let frame = match &self.rectify {
            Some(cal) => {
                let r = g.task::<rectify::node::Rectify>(
                    RECTIFY,
                    toml::Table::from_iter([(
                        "calibration".to_string(),
                        toml::Value::from(cal.as_str()),
                    )]),
                );
                g.connect(
                    &r,
                    rectify::node::Frame::frame,
                    &pair.out(ImagePairOut::frame),
                );
                r.out(rectify::node::Frame::frame)
            }
            None => pair.out(ImagePairOut::frame),
        };
        let mut matching = self.matching.clone();
        matching.region = if self.segment.is_some() {
            Region::Cells
        } else {
            Region::Frame
        };
        let seg = self.segment.as_ref().map(|s| {
            let seg = g.task::<segment::node::Segment>(SEGMENT, params_of(s));
            g.connect(&seg, SegmentIn::frame, &frame);
            seg
        });
        let m = g.task::<matcher::node::Match>(MATCH, params_of(&matching));
        g.connect(&m, MatchIn::frame, &frame);
        if let Some(seg) = &seg {
            g.connect(&m, MatchIn::cells, &seg.out(SegmentOut::cells));
        }
        let v = g.task::<validate::node::Validate>(VALIDATE, params_of(&self.validate));
        g.connect(&v, ValidateIn::left, &m.out(BothOut::left));
        g.connect(&v, ValidateIn::right, &m.out(BothOut::right));
        let mut outs = StereoOuts {
            colour,
            frame: frame.clone(),
            labels: seg.as_ref().map(|s| s.out(SegmentOut::labels)),
            cells: seg.as_ref().map(|s| s.out(SegmentOut::cells)),
            matched: m.out(BothOut::left),
            matched_right: m.out(BothOut::right),
            checked: v.out(ValidateOut::left),
            checked_right: v.out(ValidateOut::right),
            post: None,
            disparity: None,
            cloud: None,
            targets: None,
        };
        if let Some(p) = &self.post {
            let post = g.task::<postprocess::node::Postprocess>(POSTPROCESS, params_of(p));
            g.connect(&post, Tiles::disparity, &outs.checked);
            outs.post = Some(post.out(Tiles::disparity));
            if let Some(geometry) = &self.geometry {
                let t = g.task::<triangulate::node::Triangulate>(
                    TRIANGULATE,
                    toml::Table::from_iter([(
                        "calibration".to_string(),
                        toml::Value::from(geometry.clone()),
                    )]),
                );
                g.connect(&t, TriangulateIn::frame, &frame);
                g.connect(&t, TriangulateIn::disparity, &post.out(Tiles::disparity));
                if self.rectify.is_none() {
                    g.connect(&t, TriangulateIn::colour, &outs.colour);
                }
                if let Some(seg) = &seg {
                    g.connect(&t, TriangulateIn::checked, &outs.checked);
                    g.connect(&t, TriangulateIn::labels, &seg.out(SegmentOut::labels));
                    g.connect(&t, TriangulateIn::cells, &seg.out(SegmentOut::cells));
                }
                outs.disparity = Some(t.out(TriangulateOut::disparity));
                outs.cloud = Some(t.out(TriangulateOut::cloud));
                outs.targets = Some(t.out(TriangulateOut::targets));
            }
        }
        (g, outs)
    }

    /// The graph as launch-file text.
    pub fn launch_text(&self) -> String {
        self.build().0.launch_text()
    }

    /// The outputs a command reads.
    pub fn outs(&self) -> StereoOuts {
        self.build().1
    }

    /// The graph, validated against the built-in kinds.
    pub fn graph(&self) -> Result<Graph, Error> {
        LaunchFile::parse(Path::new("preset"), &self.launch_text())
            .and_then(|f| f.validate(&crate::registry::builtin()))
            .map_err(Error::Invalid)
    }

    /// The graph's nodes, built and ready to run in this process.
    pub fn start(&self) -> Result<(Graph, InProcess), Error> {
        let g = self.graph()?;
        let run = InProcess::new(&g, &crate::registry::builtin()).map_err(Error::Start)?;
        Ok((g, run))
    }

    /// Runs one frame: its messages and node times.
    pub fn run_once(&self) -> Result<Frame, Error> {
        let (_, mut run) = self.start()?;
        run.step().map_err(Error::Node)?.ok_or(Error::NoFrame)
    }
}

/// The post-processing that suits a matcher's maps: whole-pixel maps (the paper's) keep
/// smaller regions than sub-pixel ones.
pub fn post_for(mode: Mode) -> PostParams {
    match mode {
        Mode::Paper => PostParams::WHOLE_PIXEL,
        Mode::Quality => PostParams::SUBPIXEL,
    }
}

/// A target's disparity: the median of the valid LR-checked disparities in the central
/// half of the image (quality matcher, no post-processing), and the image size.
pub fn target_disparity(
    l: &Path,
    r: &Path,
    range: DisparityRange,
) -> Result<(f64, (usize, usize)), Error> {
    let preset = Stereo {
        post: None,
        ..Stereo::whole_frame(l.to_path_buf(), r.to_path_buf(), Mode::Quality, range)
    };
    let (_, mut run) = preset.start()?;
    let f = run
        .step()
        .map_err(Error::Node)?
        .ok_or_else(|| Error::Node(format!("'{}' gave no frame", l.display())))?;
    let checked = f.read(&preset.outs().checked).map_err(Error::Node)?.paste();
    let (w, h) = (checked.width, checked.height);
    let mut v: Vec<f32> = (h / 4..3 * h / 4)
        .flat_map(|y| checked.row(y)[w / 4..3 * w / 4].to_vec())
        .filter(|d| d.is_finite())
        .collect();
    if v.len() < 100 {
        return Err(Error::TooFewMatches {
            file: l.display().to_string(),
            pixels: v.len(),
            min: range.min,
            max: range.max,
        });
    }
    v.sort_by(|a, b| a.total_cmp(b));
    Ok((v[v.len() / 2] as f64, (w, h)))
}
