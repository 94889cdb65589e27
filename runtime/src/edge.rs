//! What the launch file says about an edge (queue depth, overflow) and the clock frames
//! are stamped with: the leaf every other runtime module builds on.

use serde::{Deserialize, Serialize};
use std::time::{SystemTime, UNIX_EPOCH};

/// What a full input queue does to the next frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Overflow {
    /// The oldest queued frame is dropped (live edges).
    #[default]
    DropOldest,
    /// The writer waits until the reader has taken a frame (lossless edges).
    Block,
}

/// Queue settings of one edge; every port of the edge must use the same.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct EdgeConfig {
    /// Frames a reader may have queued.
    pub depth: usize,
    /// What a full queue does.
    pub overflow: Overflow,
}

impl Default for EdgeConfig {
    fn default() -> Self {
        Self {
            depth: 2,
            overflow: Overflow::DropOldest,
        }
    }
}

/// Nanoseconds since the Unix epoch (capture timestamps).
pub fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}
