//! The node kinds this binary runs: one list built from the node types.

use runtime::Registry;
use runtime::launch::Graph;

/// Every built-in node kind, in pipeline order, and the recorder and replay kinds that
/// `--record` and `replay` put into a graph.
pub fn builtin() -> Registry {
    Registry::new()
        .source::<capture::Capture>()
        .source::<capture::ImagePair>()
        .task::<rectify::node::Rectify>()
        .task::<segment::node::Segment>()
        .task::<matcher::node::Match>()
        .task::<matcher::node::MatchLr>()
        .task::<matcher::node::MatchRl>()
        .task::<validate::node::Validate>()
        .task::<postprocess::node::Postprocess>()
        .task::<triangulate::node::Triangulate>()
        .task::<track::node::TrackNode>()
        .task::<manipulator_bridge::node::BridgeNode>()
        .tap(recorder::node::RECORDER_KIND, recorder::node::run_recorder)
        .rewritten(recorder::node::REPLAY_KIND, |spec| {
            Ok(Box::new(recorder::node::ReplayNode::from_spec(spec)?))
        })
}

/// The geometry the graph's triangulate node uses and the image size, when the launch
/// file says both (a synthetic capture, or a capture with `width` and `height`): what the
/// recorder writes as the cameras' CameraInfo.
pub fn cameras(graph: &Graph) -> Option<recorder::node::Cameras> {
    let of_kind = |kind: &str| graph.nodes.iter().find(|n| n.kind() == Some(kind));
    let (tri, cap) = (
        of_kind(<triangulate::node::Triangulate as runtime::node::Task>::KIND)?,
        of_kind(<capture::Capture as runtime::node::Source>::KIND)?,
    );
    let cap: capture::CaptureParams = runtime::registry::parse_params(&cap.params).ok()?;
    let (width, height) = cap.frame_size()?;
    let tri: triangulate::node::TriangulateParams =
        runtime::registry::parse_params(&tri.params).ok()?;
    // Where a rectify node rectifies, the capture's images are raw: no CameraInfo for them.
    let rectifies = graph.nodes.iter().any(|n| {
        n.kind() == Some(<rectify::node::Rectify as runtime::node::Task>::KIND)
            && runtime::registry::parse_params::<rectify::node::RectifyParams>(&n.params)
                .is_ok_and(|p| p.calibration.is_some() || p.camera_info.is_some())
    });
    let capture = of_kind(<capture::Capture as runtime::node::Source>::KIND)?;
    let raw = if rectifies {
        graph
            .output_edges(&capture.id)
            .into_iter()
            .map(|(e, _)| e)
            .collect()
    } else {
        Vec::new()
    };
    Some(recorder::node::Cameras {
        calibration: tri.calibration.resolve(width, height).ok()?,
        width,
        height,
        raw,
    })
}
