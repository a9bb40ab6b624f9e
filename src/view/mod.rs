//! The live view: what the browser page draws, and how it gets there.
//!
//! A [`LiveScene`] describes a rig's world for the page: static geometry ([`SceneView`]:
//! walls with openings, cylinders such as branches, paint already on), the rig as
//! world-space polylines at given joint values, and paint added since the last call. The arm
//! has one from its rig model ([`ArmScene`]); the painting room and the sloth bring theirs.
//! The streaming cycle feeds a [`LiveSlot`] through a [`LiveSink`] without allocating or
//! blocking; the [`LiveHub`] samples the slot at the page's frame rate and builds the
//! WebSocket messages ([`frame`]). The scene's types and their Foxglove form are the leaf
//! [`crate::scene`]'s. The page itself is in `page/`, embedded in the binary.
//!
//! This module reads the rig and the cycle's records; it must not move the arm, talk to a
//! link or touch the cycle's timing.

mod arm;
pub mod frame;
mod hub;
mod live;
pub mod page;
mod plan;
mod program;
pub mod solid;
mod trace;

pub use arm::{ArmScene, joint_origins, joint_origins_from};
pub use hub::{JobView, LiveHub, SceneChange, SceneCursor};
pub use live::{LiveSample, LiveSink, LiveSlot};
pub use plan::{MAX_PATH_POINTS, MAX_TARGETS_DRAWN, PlanView, TargetView};
pub use program::{PartsDrawing, ProgramView, program_view};
pub use solid::CellDrawing;
pub use trace::ToolTrace;

use crate::scene::{PaintQuad, Point, SceneView};
use serde::Serialize;

/// What a rig's world shows the page. Called from the view's sampling task (about 50 times
/// a second), never from the streaming cycle: implementations may allocate and lock.
pub trait LiveScene: Send + Sync {
    /// The static geometry (and all paint so far).
    fn scene(&self) -> SceneView;
    /// The rig at the joint values `actual` (rad or m, in the rig's joint order), as
    /// world-space polylines the page draws as links: for a serial rig, the origin of every
    /// joint frame and then the tool; a branching rig (the sloth) returns one per limb.
    fn chains(&self, actual: &[f64]) -> Vec<Vec<Point>>;
    /// Paint added since the previous call.
    fn drain_paint(&mut self) -> Vec<PaintQuad> {
        Vec::new()
    }
}

/// One joint as the page labels it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct JointLabel {
    pub name: String,
    /// `deg` (revolute) or `m` (prismatic): the unit of the values the page receives.
    pub unit: &'static str,
}

impl JointLabel {
    pub fn for_rig(rig: &crate::rig::Rig) -> Vec<JointLabel> {
        rig.joints
            .iter()
            .map(|joint| JointLabel {
                name: joint.name.clone(),
                unit: joint.kind.unit(),
            })
            .collect()
    }
}
