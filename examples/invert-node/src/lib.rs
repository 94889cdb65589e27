//! A custom node, written against the node API alone: it inverts the grey levels of each
//! stereo frame. A new node kind is this one [`Task`] impl plus one registry line, either
//! in a program of its own (`src/main.rs`, an `exec` node in a launch file) or in a binary
//! that embeds the built-in kinds (`pipelines::registry::builtin().task::<Invert>()`).
//!
//! ```toml
//! [[node]]
//! id = "invert"
//! exec = "target/release/microstereo-invert"
//! inputs = { frame = "capture/frame" }
//! params = { level = 255 }
//! ```

use node_api::{NodeError, Params, Stamp, Task};
use schemas::StereoFrame;
use serde::Deserialize;

/// `params` of an invert node.
#[derive(Clone, Copy, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InvertParams {
    /// Grey level that black becomes (each pixel `v` becomes `level − v`, at least 0).
    #[serde(default = "white")]
    pub level: u8,
}

fn white() -> u8 {
    255
}

impl Params for InvertParams {
    fn check(&self) -> Result<(), String> {
        if self.level == 0 {
            return Err("level 0 would make every frame black; use 1..=255".into());
        }
        Ok(())
    }
}

node_api::ports! {
    /// What the invert node reads and sends.
    pub struct Frame {
        /// A stereo pair.
        pub frame: StereoFrame,
    }
}

/// Inverts both views of each frame.
#[derive(Debug)]
pub struct Invert {
    level: u8,
}

impl Task for Invert {
    const KIND: &'static str = "invert";
    type Params = InvertParams;
    type Input = Frame;
    type Output = Frame;
    type Error = NodeError;

    fn new(p: InvertParams) -> Result<Self, NodeError> {
        Ok(Self { level: p.level })
    }

    fn process(&mut self, _: Stamp, mut i: Frame) -> Result<Frame, NodeError> {
        for view in [&mut i.frame.left, &mut i.frame.right] {
            for v in &mut view.data {
                *v = self.level.saturating_sub(*v);
            }
        }
        Ok(i)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use schemas::Plane;

    #[test]
    fn both_views_are_inverted_below_the_level() {
        let mut n = Invert::new(InvertParams { level: 200 }).unwrap();
        let frame = StereoFrame {
            left: Plane::from_vec(3, 1, vec![0, 100, 250]).unwrap(),
            right: Plane::from_vec(3, 1, vec![200, 1, 199]).unwrap(),
        };
        let out = n.process(Stamp::default(), Frame { frame }).unwrap().frame;
        assert_eq!(out.left.data, [200, 100, 0]);
        assert_eq!(out.right.data, [0, 199, 1]);
        assert!(InvertParams { level: 0 }.check().is_err());
    }
}
