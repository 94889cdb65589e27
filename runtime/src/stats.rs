//! What a node reports when it ends, for the supervisor's summary.

use serde::{Deserialize, Serialize};

/// The line prefix of a node's final statistics on its stdout.
pub const STATS_PREFIX: &str = "MICROSTEREO-STATS ";

/// What one node did, reported when it ends.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct NodeStats {
    /// Node id.
    pub id: String,
    /// Frames consumed (steps taken; frames produced for a source).
    pub frames_in: u64,
    /// Messages published.
    pub frames_out: u64,
    /// Mean step time, ms.
    pub mean_ms: f64,
    /// 99th-percentile step time, ms.
    pub p99_ms: f64,
    /// What each input lost, in the order of the node's inputs.
    pub inputs: Vec<InputStats>,
    /// Mean time from capture to the end of this node's step, ms.
    pub latency_ms: f64,
    /// The last frame number handled.
    pub last_frame: Option<u64>,
}

/// What one input of a node lost.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct InputStats {
    /// The input's port.
    pub port: String,
    /// Messages lost on its edge.
    pub dropped: u64,
    /// Frames of the stream it never delivered, lost anywhere.
    pub missing: u64,
}
