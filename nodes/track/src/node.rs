//! The track node: each frame's cells in, the tracks out.

use crate::tracker::{Tracker, TrackerParams};
use node_api::{NodeError, Params, Stamp, Task};
use schemas::{Targets, Tracks};

impl Params for TrackerParams {
    fn check(&self) -> Result<(), String> {
        TrackerParams::check(self)
    }
}

node_api::ports! {
    /// What the track node reads.
    pub struct TrackIn {
        /// The frame's cells in 3D.
        pub targets: Targets,
    }
}

node_api::ports! {
    /// What the track node sends.
    pub struct TrackOut {
        /// Every live track, with this frame's cell where it was seen.
        pub tracks: Tracks,
    }
}

/// Follows the cells from frame to frame.
#[derive(Debug)]
pub struct TrackNode {
    tracker: Tracker,
}

impl Task for TrackNode {
    const KIND: &'static str = "track";
    type Params = TrackerParams;
    type Input = TrackIn;
    type Output = TrackOut;
    type Error = NodeError;

    fn new(params: TrackerParams) -> Result<Self, NodeError> {
        Ok(Self {
            tracker: Tracker::new(params),
        })
    }

    fn process(&mut self, _: Stamp, i: TrackIn) -> Result<TrackOut, NodeError> {
        let tracks = self.tracker.update(&i.targets).map_err(NodeError::Failed)?;
        Ok(TrackOut { tracks })
    }
}
