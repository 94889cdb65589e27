//! The graphs the one-shot commands run: their flags become node parameters of an
//! in-memory launch file, checked by the same validator as any launch file and run by the
//! in-process executor on the same node values as `microstereo run`.

use crate::error::CliError;
use matcher::Mode;
use matcher::node::{MatchParams, Region};
use postprocess::PostParams;
use runtime::exec::InProcess;
use runtime::launch::{Graph, LaunchFile};
use schemas::DisparityRange;
use segment::SegmentParams;
use std::path::{Path, PathBuf};
use triangulate::geometry::Geometry;
use validate::node::ValidateParams;

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

fn table<T: serde::Serialize>(v: &T) -> toml::Table {
    match toml::Value::try_from(v) {
        Ok(toml::Value::Table(t)) => t,
        _ => toml::Table::new(),
    }
}

fn node(id: &str, kind: &str, inputs: &[(&str, &str)], params: toml::Table) -> toml::Value {
    let mut n = toml::Table::new();
    n.insert("id".into(), id.into());
    n.insert("kind".into(), kind.into());
    if !inputs.is_empty() {
        let i: toml::Table = inputs
            .iter()
            .map(|(p, from)| (p.to_string(), toml::Value::from(*from)))
            .collect();
        n.insert("inputs".into(), toml::Value::Table(i));
    }
    if !params.is_empty() {
        n.insert("params".into(), toml::Value::Table(params));
    }
    toml::Value::Table(n)
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

    /// The graph as launch-file text.
    pub fn launch_text(&self) -> String {
        use ids::*;
        let mut nodes = vec![node(
            PAIR,
            "image-pair",
            &[],
            table(&capture::ImagePairParams {
                left: self.left.clone(),
                right: self.right.clone(),
                frames: self.frames,
            }),
        )];
        // A raw pair is rectified first; every later node reads the rectified views (and
        // the points go grey: the colour view is not rectified).
        let frame = if let Some(cal) = &self.rectify {
            nodes.push(node(
                RECTIFY,
                "rectify",
                &[("frame", "pair/frame")],
                toml::Table::from_iter([(
                    "calibration".to_string(),
                    toml::Value::from(cal.as_str()),
                )]),
            ));
            "rectify/frame"
        } else {
            "pair/frame"
        };
        let mut matching = self.matching.clone();
        matching.region = if self.segment.is_some() {
            Region::Cells
        } else {
            Region::Frame
        };
        let mut match_in = vec![("frame", frame)];
        if let Some(s) = &self.segment {
            nodes.push(node(SEGMENT, "segment", &[("frame", frame)], table(s)));
            match_in.push(("cells", "segment/cells"));
        }
        nodes.push(node(MATCH, "match", &match_in, table(&matching)));
        nodes.push(node(
            VALIDATE,
            "validate",
            &[("left", "match/left"), ("right", "match/right")],
            table(&self.validate),
        ));
        if let Some(p) = &self.post {
            nodes.push(node(
                POSTPROCESS,
                "postprocess",
                &[("disparity", "validate/left")],
                table(p),
            ));
            if let Some(g) = &self.geometry {
                let mut inputs = vec![("frame", frame), ("disparity", "postprocess/disparity")];
                if self.rectify.is_none() {
                    inputs.push(("colour", "pair/colour"));
                }
                if self.segment.is_some() {
                    inputs.extend([
                        ("checked", "validate/left"),
                        ("labels", "segment/labels"),
                        ("cells", "segment/cells"),
                    ]);
                }
                let params = toml::Table::from_iter([(
                    "calibration".to_string(),
                    toml::Value::from(g.clone()),
                )]);
                nodes.push(node(TRIANGULATE, "triangulate", &inputs, params));
            }
        }
        let doc = toml::Table::from_iter([("node".to_string(), toml::Value::Array(nodes))]);
        toml::to_string(&doc).expect("a launch table serialises")
    }

    /// The graph, validated against the built-in kinds (`flags` name the parameters in
    /// errors by the command's flags).
    pub fn graph(&self, flags: &[(&str, &str)]) -> Result<Graph, CliError> {
        LaunchFile::parse(Path::new("preset"), &self.launch_text())
            .and_then(|f| f.validate(&crate::registry::builtin()))
            .map_err(|e| {
                let lines: Vec<String> =
                    e.0.iter()
                        .map(|e| in_flag_terms(&e.message, flags))
                        .collect();
                CliError::Other(lines.join("\n"))
            })
    }

    /// The graph's nodes, built and ready to run in this process.
    pub fn start(&self, flags: &[(&str, &str)]) -> Result<(Graph, InProcess), CliError> {
        let g = self.graph(flags)?;
        let run = InProcess::new(&g, &crate::registry::builtin()).map_err(CliError::Other)?;
        Ok((g, run))
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

/// A node's message in the terms of a command line: `node 'x': bad params: ` dropped and
/// each parameter named by its flag.
pub fn in_flag_terms(message: &str, flags: &[(&str, &str)]) -> String {
    let m = message
        .split_once(": bad params: ")
        .map_or(message, |(_, m)| m);
    let mut out = String::with_capacity(m.len());
    let mut word = String::new();
    let flush = |word: &mut String, out: &mut String| {
        match flags.iter().find(|(p, _)| *p == word) {
            Some((_, f)) => out.push_str(f),
            None => out.push_str(word),
        }
        word.clear();
    };
    for c in m.chars() {
        if c.is_ascii_alphanumeric() || c == '_' {
            word.push(c);
        } else {
            flush(&mut word, &mut out);
            out.push(c);
        }
    }
    flush(&mut word, &mut out);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parameters_are_named_by_their_flags() {
        let flags = [("window", "--window"), ("min_disparity", "--min-disparity")];
        assert_eq!(
            in_flag_terms(
                "node 'match': bad params: window 12 is not allowed; min_disparity_x window",
                &flags
            ),
            "--window 12 is not allowed; min_disparity_x --window"
        );
    }
}
