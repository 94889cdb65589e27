//! The capture node: where the graph's stereo frames come from.
//!
//! - `source = "synthetic"` ([`synthetic`]): the synthetic stereo microscope, cells drifting
//!   and an optional pipette advancing from frame to frame (the embedded default);
//! - `source = "files"` ([`files`]): rectified image pairs on disk, named by two glob
//!   patterns (`*` and `?` in the file name), paired in sorted order, optionally looped;
//! - `source = "v4l"` (`camera`, cargo feature `v4l`): two V4L2 cameras, paired by driver
//!   timestamp.

#[cfg(feature = "v4l")]
pub mod camera;
pub mod files;
pub mod synthetic;

use runtime::step::GraphNode;

fn source(t: &toml::Table) -> &str {
    t.get("source")
        .and_then(|v| v.as_str())
        .unwrap_or("synthetic")
}

/// Checks a capture node's `params` without starting anything: every process of a graph
/// validates the whole launch file, and a camera opened there would be busy for the node.
pub fn check_params(t: &toml::Table) -> Result<(), String> {
    match source(t) {
        "synthetic" => synthetic::SyntheticParams::from_table(t).map(|_| ()),
        // Listing the files is cheap and finds a wrong pattern before the graph starts.
        "files" => files::FileCapture::new(files::FileParams::from_table(t)?).map(|_| ()),
        #[cfg(feature = "v4l")]
        "v4l" => camera::CameraParams::from_table(t).map(|_| ()),
        _ => build(t).map(|_| ()),
    }
}

/// The capture node its `params` describe.
pub fn build(t: &toml::Table) -> Result<Box<dyn GraphNode>, String> {
    match source(t) {
        "synthetic" => Ok(Box::new(synthetic::SyntheticCapture::new(
            &synthetic::SyntheticParams::from_table(t)?,
        ))),
        "files" => Ok(Box::new(files::FileCapture::new(
            files::FileParams::from_table(t)?,
        )?)),
        #[cfg(feature = "v4l")]
        "v4l" => Ok(Box::new(camera::CameraCapture::new(
            &camera::CameraParams::from_table(t)?,
        )?)),
        #[cfg(not(feature = "v4l"))]
        "v4l" => Err("this build has no camera support; build with --features v4l".into()),
        other => Err(format!(
            "source '{other}' is not available; use \"synthetic\", \"files\" or \"v4l\""
        )),
    }
}

/// Frames per second a capture node's `params` ask for, if any.
pub fn fps(t: &toml::Table) -> Option<f64> {
    t.get("fps")
        .and_then(|v| v.as_float().or(v.as_integer().map(|i| i as f64)))
}
