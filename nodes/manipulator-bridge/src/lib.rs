//! The manipulator bridge: moves a micropipette among the reconstructed cells, safely.
//!
//! - [`scene`]: each frame's cells as obstacles (convex prisms), the substrate, the
//!   workspace.
//! - [`plan`]: obstacle-avoiding approach, retract and goto paths for a pipette whose whole
//!   body keeps a clearance from every cell but its target.
//! - [`geom`]: the exact distances the planner relies on.
//! - [`device`]: the manipulator trait and the simulated manipulator; [`mp285`]: the
//!   Sutter MP-285 serial driver and its emulator; [`scientifica`]: Scientifica's ASCII
//!   protocol and its emulator; [`registration`]: the device's frame on the scene's.
//! - [`protocol`], [`bridge`], [`node`]: the TCP commands and events, the controller that
//!   executes them safely, and the graph node.

pub mod bridge;
pub mod device;
pub mod geom;
pub mod mp285;
pub mod node;
pub mod plan;
pub mod protocol;
pub mod registration;
pub mod scene;
pub mod scientifica;
pub mod testing;
