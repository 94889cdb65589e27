//! The manipulator bridge: moves a micropipette among the reconstructed cells, safely.
//!
//! - [`scene`]: each frame's cells as obstacles (convex prisms), the substrate, the
//!   workspace.
//! - [`plan`]: obstacle-avoiding approach, retract and goto paths for a pipette whose whole
//!   body keeps a clearance from every cell but its target.
//! - [`geom`]: the exact distances the planner relies on.

pub mod device;
pub mod geom;
pub mod mp285;
pub mod plan;
pub mod scene;
