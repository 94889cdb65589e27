//! Recordings of the graph's edges as MCAP files that other tools read.
//!
//! The format: MCAP profile `ros2`, message encoding `cdr`, schema encoding `ros2msg` with
//! each type's full definition ([`ros2`]). Camera frames, label images and disparity maps
//! are `sensor_msgs/msg/Image` (a stereo message becomes a `left` and a `right` topic), the
//! cloud is `sensor_msgs/msg/PointCloud2`, cells and targets are `microstereo_msgs` types.
//! [`file`] writes and reads such files (reading gives back each message bit for bit, and
//! what a truncated file holds); [`node`] is the recorder node and the replay source.

pub mod file;
pub mod node;
pub mod ros2;
pub mod scene;

pub use file::{
    EdgeMessage, EdgeReader, FrameReader, Overview, RecordingError, RecordingWriter, overview,
};
